"""The shipped scenes' camera noise (docs/scenes.md, "Camera noise") and its noise-free twins."""

from __future__ import annotations

import numpy as np
import pytest

from vvtbench.render.crb import noise_variance_dn2
from vvtbench.render.sensor import (
    FULL_WELL_ELECTRONS,
    HIGH_SPEED_READ_NOISE_DN,
    HIGH_SPEED_READ_NOISE_ELECTRONS,
    describe_sensor,
    electrons_to_dn,
    is_noise_free,
)
from vvtbench.samples import generate as gen
from vvtbench.samples import reader as ds
from vvtbench.scene.scene import SCENES_DIR, load_scene, parse_scene

SHIPPED = sorted(SCENES_DIR.glob("*.toml"))
NOISE_FREE = [p for p in SHIPPED if p.stem.endswith("_noisefree")]


def test_the_stated_camera_in_dn():
    """15 e- rms at 10 000 e- to 65 535 DN is the 98.3 DN of the scene files (to 0.1 DN)."""
    dn = electrons_to_dn(HIGH_SPEED_READ_NOISE_ELECTRONS, FULL_WELL_ELECTRONS, 16)
    assert abs(dn - HIGH_SPEED_READ_NOISE_DN) < 0.01
    assert electrons_to_dn(FULL_WELL_ELECTRONS, FULL_WELL_ELECTRONS, 12) == 4095.0
    assert describe_sensor(0.0, False).startswith("noise-free sensor")
    label = describe_sensor(HIGH_SPEED_READ_NOISE_DN, True)
    assert "shot noise" in label and "98.3 DN (15 e-)" in label
    assert describe_sensor(8.0, False) == "read noise 8 DN (1.22 e-), no shot noise"
    assert not is_noise_free(2.0, False) and not is_noise_free(0.0, True)


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.stem)
def test_shipped_scenes_film_with_the_stated_camera_or_say_noise_free(path):
    r = load_scene(path).render
    if path in NOISE_FREE:
        assert is_noise_free(r.read_noise_dn, r.shot_noise)
        twin = load_scene(path.stem.removesuffix("_noisefree"))
        a, b = load_scene(path).to_toml_dict(), twin.to_toml_dict()
        for d in (a, b):  # the twins differ in name, description and noise alone
            for key in ("name", "description"):
                d.pop(key)
            d["render"].pop("read_noise_dn")
            d["render"].pop("shot_noise")
        assert a == b
        assert "noise-free sensor" in load_scene(path).description
    else:
        assert (r.read_noise_dn, r.shot_noise, r.full_well_electrons) == (
            HIGH_SPEED_READ_NOISE_DN, True, FULL_WELL_ELECTRONS)


def _still(name: str):
    """The shipped scene, small and short, its motion scaled to nothing: every frame films
    the rest render, so a pixel's spread over time is the sensor's noise alone. The camera
    (noise, full well, bit depth) is the scene's."""
    data = load_scene(name).to_toml_dict()
    data["geometry"]["cells"] = [4, 4, 4]
    data["simulation"].update(n_modes=4, duration=24 / data["simulation"]["fps"])
    data["camera"]["resolution"] = [48, 48]
    data["render"].update(supersample=1, motion_scale=1e-6)
    return parse_scene(data, name)


@pytest.fixture(scope="module")
def stills(tmp_path_factory):
    out = tmp_path_factory.mktemp("stills")
    return {name: ds.open_sample(gen.generate(_still(name), out, progress=False))
            for name in ("jello_cube_damped_top_front", "jello_cube_damped_top_front_noisefree")}


def test_the_paper_scene_renders_with_noise_at_the_stated_level(stills):
    """On the object (intensity 0.05-0.95, clear of clipping) the frame-to-frame variance
    pooled over pixels is the model's ``I D^2 / F + r^2 + 1/12`` (DN^2) within 5 %: about
    600 pixels x 23 degrees of freedom estimate it to ~1.2 % (1 sigma)."""
    s = stills["jello_cube_damped_top_front"]
    assert s.sensor["label"] == describe_sensor(HIGH_SPEED_READ_NOISE_DN, True)
    assert not s.sensor["noise_free"]
    frames = s.read_frames().astype(np.float64)
    rest = np.asarray(s["image/rest"], dtype=np.float64)
    on = (rest > 0.05) & (rest < 0.95)
    assert on.sum() > 500
    measured = frames.var(axis=0, ddof=1)[on].mean()
    model = noise_variance_dn2(rest, 16, HIGH_SPEED_READ_NOISE_DN, True, FULL_WELL_ELECTRONS)
    assert abs(measured / model[on].mean() - 1.0) < 0.05
    # the background (intensity 0): read noise alone, clipped at 0 DN -> E[max(0, x)^2] = r^2/2
    bg = s["image/triangle"] == -1
    assert bg.sum() > 100
    rms = np.sqrt(2.0 * np.mean(frames[:, bg] ** 2))
    assert abs(rms / HIGH_SPEED_READ_NOISE_DN - 1.0) < 0.05
    # the ruler of the sample's own camera is the stored one
    np.testing.assert_allclose(s.ruler()["snr"], s.crb_snr, rtol=1e-9)


def test_the_noise_free_twin_has_no_noise(stills):
    """Every frame is the rest render rounded to whole DN; its ruler sees rounding only and
    is the noisy sample's ruler with the noise taken away."""
    s = stills["jello_cube_damped_top_front_noisefree"]
    assert s.sensor["noise_free"] and s.sensor["label"].startswith("noise-free sensor")
    frames = s.read_frames().astype(np.int64)
    clean = np.rint(np.asarray(s["image/rest"], dtype=np.float64) * 65535.0)
    diff = np.abs(frames - clean[None])
    assert diff.max() <= 1 and np.mean(diff > 0) < 1e-3  # a render's last-bit rounding at most
    assert np.all(frames.std(axis=0) < 0.5)
    noisy = stills["jello_cube_damped_top_front"].ruler(read_noise_dn=0.0, shot_noise=False)
    assert noisy["noise_free"] and noisy["sensor"] == s.sensor["label"]
    np.testing.assert_allclose(noisy["snr"], s.crb_snr, rtol=1e-6)
    assert np.all(s.crb_snr > 100 * stills["jello_cube_damped_top_front"].crb_snr)
