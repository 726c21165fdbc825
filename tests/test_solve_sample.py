"""``vvtbench solve SOLVER SAMPLE_DIR`` and ``InverseProblem.from_sample`` on a tiny sample.

Rendering needs headless EGL (Mesa llvmpipe is fine); see tests/test_render.py.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from vvtbench.cli.solve import main_solve
from vvtbench.samples import generate as gen
from vvtbench.samples import reader as ds
from vvtbench.scene.scene import parse_scene

SAMPLE = {
    "name": "tiny_solve",
    "seed": 3,
    "geometry": {"kind": "box", "cells": [4, 4, 4]},
    "excitation": {"kind": "pluck", "at": [0.05, 0.0, 0.05], "displacement": 0.0006},
    "simulation": {"n_modes": 8, "duration": 0.5, "fps": 400.0},
    "camera": {"resolution": [80, 80], "position": [0.16, -0.13, 0.13],
               "look_at": [0.025, 0.025, 0.022], "fov_y_deg": 30.0},
    "render": {"supersample": 2},
}


@pytest.fixture(scope="module")
def sample(tmp_path_factory) -> Path:
    scene = parse_scene(json.loads(json.dumps(SAMPLE)), "tiny_solve")
    return gen.generate(scene, tmp_path_factory.mktemp("s"), progress=False)


def test_depth_buffer_drops_occluded_vertices():
    from vvtbench.fem.mesh import box_mesh
    from vvtbench.modes.sampling import visible_vertices as visible
    from vvtbench.render.camera import Camera

    def visible_vertices(mesh, cam, depth_buffer=None):
        return visible(mesh.points, mesh.surface, cam, depth_buffer=depth_buffer)

    mesh = box_mesh((2, 2, 2), (1.0, 1.0, 1.0))
    cam = Camera.look_at(position=[0.5, 0.5, 4.0], target=[0.5, 0.5, 0.5], up=(0.0, 1.0, 0.0),
                         fov_y_deg=40.0, width=32, height=32)
    seen = visible_vertices(mesh, cam)
    assert len(seen) == 9  # the top face
    buf = np.full((32, 32), np.inf)
    assert np.array_equal(visible_vertices(mesh, cam, depth_buffer=buf), seen)
    buf[:] = 1.0  # an occluder 1 m in front of the camera hides everything
    assert len(visible_vertices(mesh, cam, depth_buffer=buf)) == 0


def test_solve_sample_extracted_writes_estimate_and_reuses_modes(sample, tmp_path, capsys):
    out = tmp_path / "est"
    argv = ["vvt", str(sample), "--grid", "3", "3", "3", "--modes", "4", "--set", "max_iter=2",
            "--no-mode-match", "-o", str(out)]
    assert main_solve(argv) == 0
    for name in ("estimate.npz", "estimate.json", "solve.json", "metrics.json", "fields.npz",
                 "slices.png", "modes/modes.json"):
        assert (out / name).is_file(), name
    doc = json.loads((out / "solve.json").read_text())
    assert doc["observation"] == "extracted" and doc["problem"]["observation"] == "extracted"
    assert 1 <= doc["n_modes"] <= 4
    assert json.loads((out / "estimate.json").read_text())["iterations"] == 2
    est = np.load(out / "estimate.npz")
    assert est["w"].shape == (3, 3, 3) and np.all(np.isfinite(est["w_params"]))
    mtime = (out / "modes" / "modes.npz").stat().st_mtime_ns
    # a second run reuses the extracted modes; --modes-file gives the same problem
    assert main_solve(argv) == 0
    assert (out / "modes" / "modes.npz").stat().st_mtime_ns == mtime
    out2 = tmp_path / "est2"
    assert main_solve(["homogeneous", str(sample), "--grid", "3", "3", "3", "--modes", "4",
                       "--modes-file", str(out / "modes"), "--no-mode-match",
                       "-o", str(out2)]) == 0
    doc2 = json.loads((out2 / "solve.json").read_text())
    assert doc2["problem"]["extracted_frequencies_hz"] == doc["problem"][
        "extracted_frequencies_hz"]
    assert not (out2 / "modes").exists()


def test_solve_sample_true_observation_and_errors(sample, tmp_path, capsys):
    out = tmp_path / "true"
    assert main_solve(["homogeneous", str(sample), "--observation", "true", "--grid", "3", "3",
                       "3", "--modes", "4", "--no-mode-match", "-o", str(out)]) == 0
    assert json.loads((out / "solve.json").read_text())["problem"]["observation"] == "true"
    assert not (out / "modes").exists()
    assert main_solve(["homogeneous", str(sample), "--observation", "true", "--modes-file",
                       str(tmp_path), "-o", str(out)]) == 2
    assert main_solve(["homogeneous", str(tmp_path), "-o", str(out)]) == 2
    assert "not a vvtbench sample" in capsys.readouterr().err


def _inference_points(sample: Path) -> np.ndarray:
    """Vertices of the 3x3x3 inference mesh (``box_mesh`` of the scene's box)."""
    from vvtbench.fem.mesh import box_mesh

    size = tuple(float(v) for v in ds.open_sample(sample).scene.geometry.size)
    return box_mesh((3, 3, 3), size, 1).points


def test_solve_sample_camera_from_clicks(sample, tmp_path, capsys):
    """Clicks on 12 inference-mesh vertices, projected by the sample's camera + 0.2 px noise:
    the estimated camera images the mesh like the sample's and the extracted modes are
    sampled with it."""
    from vvtbench.modes import extract_modes
    from vvtbench.render.camera import Camera

    s = ds.open_sample(sample)
    modes = tmp_path / "modes"
    extract_modes(s.video_path, s.fps).save(modes)
    pts = _inference_points(sample)
    rng = np.random.default_rng(0)
    idx = rng.choice(len(pts), 12, replace=False)
    uv = s.camera.project(pts[idx]) + rng.normal(0.0, 0.2, (12, 2))
    clicks = tmp_path / "clicks.json"
    clicks.write_text(json.dumps({"points": [
        {"vertex": int(i), "u": float(u), "v": float(v)}
        for i, (u, v) in zip(idx, uv, strict=True)]}))
    out = tmp_path / "est"
    assert main_solve(["homogeneous", str(sample), "--grid", "3", "3", "3", "--modes", "4",
                       "--no-mode-match", "--modes-file", str(modes), "--clicks", str(clicks),
                       "-o", str(out)]) == 0
    assert "camera from 12 clicks" in capsys.readouterr().out
    doc = json.loads((out / "solve.json").read_text())
    meta = doc["problem"]
    assert meta["camera_source"] == "clicks" and meta["clicks_file"] == str(clicks)
    assert meta["clicks_rms_px"] < 0.4 and meta["observation"] == "extracted"
    # a narrow field of view leaves focal length and distance ill-determined, not the image:
    # all 64 vertices (clicked or not) are imaged as by the sample's camera, to ~noise
    est = Camera.from_dict(meta["camera"])
    err = np.linalg.norm(est.project(pts) - s.camera.project(pts), axis=1)
    assert np.sqrt(np.mean(err**2)) < 0.5
    assert meta["n_visible"] >= 10 and 1 <= len(meta["extracted_frequencies_hz"]) <= 4
    assert min(doc["extraction"]["extraction_mac"]) > 0.5


def test_solve_sample_clicks_errors(sample, tmp_path, capsys):
    out = str(tmp_path / "x")
    clicks = tmp_path / "clicks.json"
    base = ["homogeneous", str(sample), "--observation", "true", "--modes", "4", "-o", out,
            "--clicks"]
    clicks.write_text(json.dumps({"points": [{"vertex": 0, "u": 1.0}]}))
    assert main_solve([*base, str(clicks)]) == 2
    assert "clicks.json: points[0] is missing key 'v'" in capsys.readouterr().err
    clicks.write_text(json.dumps({"points": [{"vertex": i, "u": 1.0, "v": 2.0 * i}
                                             for i in range(5)]}))
    assert main_solve([*base, str(clicks)]) == 2
    assert ">= 6 vertex <-> pixel pairs" in capsys.readouterr().err
    assert main_solve([*base, str(tmp_path / "missing.json")]) == 2
    assert "--clicks" in capsys.readouterr().err
    clicks.write_text(json.dumps({"points": [{"vertex": 10 ** 6 + i, "u": 1.0, "v": 2.0 * i}
                                             for i in range(6)]}))
    assert main_solve([*base, str(clicks), "--grid", "3", "3", "3"]) == 2
    assert "out of range" in capsys.readouterr().err
    assert main_solve(["homogeneous", "jello_cube", "-o", out, "--clicks", str(clicks)]) == 2
    assert "needs a sample folder" in capsys.readouterr().err
