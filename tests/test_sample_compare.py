"""Samples compared value by value (vvtbench.samples.compare): rounding, a mode's sign and the
basis of a repeated eigenvalue pass; a changed value, a sign that only some arrays share, a
changed text and a changed image fail with the file named."""

from __future__ import annotations

import json
import shutil

import imageio.v3 as iio
import numpy as np
import pytest
import zarr

from vvtbench.samples import reader as ds
from vvtbench.samples import generate as gen
from vvtbench.io.files import write_json
from vvtbench.samples.compare import (
    LINEAR_IN_MODES,
    TOLERANCES,
    SampleComparison,
    _compare_counts,
    compare_samples,
)
from vvtbench.scene.scene import parse_scene

BOX = {"name": "box", "seed": 5,
       "geometry": {"kind": "box", "size": [0.05, 0.04, 0.06], "cells": [3, 3, 3]},
       "simulation": {"n_modes": 6},
       "camera": {"resolution": [48, 48], "position": [0.16, -0.13, 0.13],
                  "look_at": [0.025, 0.02, 0.03], "fov_y_deg": 30.0}}
DRUM = {"name": "drum", "seed": 5,  # a square membrane: pairs of equal frequencies
        "geometry": {"kind": "drum", "shape": "square", "size": 0.1, "cells": 8},
        "simulation": {"n_modes": 8},
        "camera": {"resolution": [48, 48], "position": [0.05, -0.15, 0.2],
                   "look_at": [0.05, 0.05, 0.0], "fov_y_deg": 40.0}}


@pytest.fixture(scope="module")
def samples(tmp_path_factory):
    root = tmp_path_factory.mktemp("compare")
    return {name: gen.generate(parse_scene(spec, name), root, video=False, progress=False)
            for name, spec in (("box", BOX), ("drum", DRUM))}


def _copy(src, tmp_path):
    dst = tmp_path / src.name
    shutil.copytree(src, dst)
    return dst


def _edit(sample, name, fn):
    arr = zarr.open_array(str(sample / "truth.zarr" / name), mode="r+")
    arr[...] = fn(np.asarray(arr[...]))


def _remanifest(sample):
    """The manifest rewritten for the edited files (as a rebuild would have written it)."""
    doc = json.loads((sample / "manifest.json").read_text())
    for rel, entry in doc["files"].items():
        entry["sha256"] = ds.sha256_file(sample / rel)
        entry["bytes"] = (sample / rel).stat().st_size
    write_json(sample / "manifest.json", doc, indent=2, sort_keys=True)


def _turn_modes(sample, W, only=None):
    """Every array linear in the mode shapes (or those in ``only``) with its modes mixed by
    ``W`` (modes x modes)."""
    for name in only or LINEAR_IN_MODES:
        if (sample / "truth.zarr" / name).exists():
            axis = 1 if name == "modes/vectors" else 0
            _edit(sample, name, lambda x, a=axis: np.moveaxis(
                np.tensordot(np.moveaxis(x, a, -1), W, axes=1), -1, a))
    _remanifest(sample)


def test_a_sample_matches_itself_byte_for_byte(samples):
    c = compare_samples(samples["box"], samples["box"])
    assert c.ok and c.compared == 0 and c.identical > 10 and c.flipped == []


def test_rounding_and_a_sign_flipped_in_every_array_pass(samples, tmp_path):
    copy = _copy(samples["box"], tmp_path)
    W = np.diag([1.0, -1.0, 1.0, 1.0, -1.0, 1.0]) * (1 + 1e-12)  # two signs, rounding
    _turn_modes(copy, W)
    _edit(copy, "modes/eigenvalues", lambda x: x * (1 + 3e-15))
    _remanifest(copy)
    c = compare_samples(samples["box"], copy)
    assert c.ok, c.problems
    assert c.flipped == [1, 4] and 0 < c.worst["modes/vectors"] < 1e-11
    assert "2 mode(s) of opposite sign" in c.summary()


def test_a_sign_that_only_some_arrays_share_fails(samples, tmp_path):
    copy = _copy(samples["box"], tmp_path)
    _turn_modes(copy, np.diag([1.0, 1.0, -1.0, 1.0, 1.0, 1.0]), only=["modes/vectors"])
    c = compare_samples(samples["box"], copy)
    assert any(p.startswith("truth.zarr/modes/surface: values differ by 2.0e+00") and
               "in mode 2" in p for p in c.problems), c.problems


def test_a_basis_of_a_repeated_frequency_may_turn_in_every_array(samples, tmp_path):
    lam = np.asarray(ds.open_sample(samples["drum"])["modes/eigenvalues"])
    pair = next(i for i in range(len(lam) - 1) if lam[i + 1] - lam[i] < 1e-9 * lam[i])
    W = np.eye(len(lam))
    c, s = np.cos(0.5), np.sin(0.5)
    W[pair:pair + 2, pair:pair + 2] = [[c, -s], [s, c]]
    turned = _copy(samples["drum"], tmp_path / "all")
    _turn_modes(turned, W)
    assert compare_samples(samples["drum"], turned).ok
    half = _copy(samples["drum"], tmp_path / "half")
    _turn_modes(half, W, only=["modes/vectors", "modes/surface"])
    c = compare_samples(samples["drum"], half)
    assert any(p.startswith("truth.zarr/observation/image_modes") for p in c.problems), \
        c.problems


@pytest.mark.parametrize("name, factor, ok", [("modes/eigenvalues", 1 + 1e-10, True),
                                              ("modes/eigenvalues", 1 + 1e-6, False),
                                              ("mesh/points", 1 + 1e-7, False),
                                              ("image/rest", 1 + 1e-7, True),
                                              ("image/rest", 1 + 1e-3, False)])
def test_float_arrays_agree_to_their_tolerance(samples, tmp_path, name, factor, ok):
    copy = _copy(samples["box"], tmp_path)
    _edit(copy, name, lambda x: x * factor)
    _remanifest(copy)
    c = compare_samples(samples["box"], copy)
    assert c.ok == ok, c.problems
    if not ok:
        assert c.problems[0].startswith(f"truth.zarr/{name}: values differ by")


def test_integers_texts_and_json_are_exact(samples, tmp_path):
    copy = _copy(samples["box"], tmp_path)
    _edit(copy, "mesh/cells", lambda x: x[::-1])
    info = json.loads((copy / "truth.json").read_text())
    info["modes"]["frequencies_hz"][0] *= 1 + 1e-12  # rounding: passes
    info["modes"]["n"] += 1
    info["video"]["lighting"] = "other"
    (copy / "truth.json").write_text(json.dumps(info, indent=2, sort_keys=True))
    (copy / "scene.toml").write_text((copy / "scene.toml").read_text() + "\n")
    _remanifest(copy)
    problems = compare_samples(samples["box"], copy).problems
    assert "truth.zarr/mesh/cells: values differ (integers and booleans are compared " \
           "exactly)" in problems
    assert "truth.json: modes.n: 6 frozen, 7 rebuilt" in problems
    assert any(p.startswith("truth.json: video.lighting:") for p in problems)
    assert "scene.toml: differs (compared byte for byte)" in problems
    assert not any("frequencies_hz" in p for p in problems)


def test_images_may_differ_by_one_count_on_few_pixels(samples, tmp_path):
    rest = iio.imread(samples["box"] / "rest.png").astype(np.int64)
    for bump, n, ok in ((1, 1, True), (2, 1, False), (1, rest.size // 100, False)):
        copy = _copy(samples["box"], tmp_path / f"{bump}-{n}")
        img = rest.copy().ravel()
        img[:n] = np.where(img[:n] < 128, img[:n] + bump, img[:n] - bump)
        iio.imwrite(copy / "rest.png", img.reshape(rest.shape).astype(np.uint8))
        _remanifest(copy)
        c = compare_samples(samples["box"], copy)
        assert c.ok == ok, c.problems
        assert c.worst["rest.png (DN)"] == bump


def test_a_damaged_sample_is_named_before_any_comparison(samples, tmp_path):
    copy = _copy(samples["box"], tmp_path)
    (copy / "truth.json").write_text("{}")  # not what its manifest lists
    c = compare_samples(samples["box"], copy)
    assert c.problems and all(p.startswith("rebuilt sample: ") for p in c.problems)


def test_video_frames_compare_by_counts():
    frames = [np.full((4, 5), 1000, np.uint16) for _ in range(10)]
    out = SampleComparison(None, None)
    _compare_counts("video.mkv", frames, [f.copy() for f in frames], TOLERANCES, out)
    assert out.ok
    shorter = SampleComparison(None, None)
    _compare_counts("video.mkv", frames, frames[:-1], TOLERANCES, shorter)
    assert shorter.problems == ["video.mkv: the rebuilt one has 9 frame(s), the frozen one more"]
    off = [f.copy() for f in frames]
    off[3][0, 0] += 3
    far = SampleComparison(None, None)
    _compare_counts("video.mkv", frames, off, TOLERANCES, far)
    assert far.problems == ["video.mkv: 1 value(s) differ by more than 1 DN (up to 3)"]
