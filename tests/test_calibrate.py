"""Calibration from clicks against the project's camera model with known poses."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from vvtbench.field.calibrate import (
    CalibrationError,
    calibrate_camera,
    calibrate_from_file,
    is_coplanar,
    load_clicks_csv,
)
from vvtbench.field.objects import resolve_object
from vvtbench.observe import ObserveError
from vvtbench.render.camera import Camera

W, H = 640, 480
ROOT = Path(__file__).resolve().parents[1]


def _plate_points(rng, n):
    return np.c_[rng.uniform(0, 0.1, (n, 2)), np.zeros(n)]


def _rms(a, b):
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1))))


@pytest.mark.parametrize("seed,n", [(0, 4), (1, 5), (2, 6), (3, 8)])
def test_plate_from_coplanar_clicks_reprojects_within_one_pixel(seed, n):
    rng = np.random.default_rng(seed)
    true = Camera.look_at((0.22, -0.28, 0.30), (0.05, 0.05, 0.0), fx=900, width=W, height=H)
    X = _plate_points(rng, n)
    uv = true.project(X) + rng.normal(0, 0.5, (n, 2))
    cal = calibrate_camera(X, uv, W, H)
    assert cal.method.startswith("homography")
    assert cal.rms_px < 1.0
    held_out = _plate_points(rng, 200)
    assert _rms(cal.camera.project(held_out), true.project(held_out)) < 1.0


def test_plate_with_given_intrinsics_recovers_the_pose():
    rng = np.random.default_rng(7)
    true = Camera.look_at((0.05, -0.25, 0.25), (0.05, 0.05, 0.0), fx=1000, width=W, height=H)
    X = _plate_points(rng, 6)
    uv = true.project(X) + rng.normal(0, 0.5, (6, 2))
    K = true.K
    cal = calibrate_camera(X, uv, W, H, intrinsics=(K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    assert np.linalg.norm(cal.camera.center - true.center) < 0.01  # metres, camera ~0.35 m off
    assert cal.intrinsics == "given"


def test_cube_from_ten_clicks_recovers_the_camera():
    rng = np.random.default_rng(3)
    true = Camera.look_at((0.30, -0.25, 0.28), (0.05, 0.05, 0.05), fx=850, width=W, height=H)
    cube = resolve_object("box:0.1x0.1x0.1")
    pts = cube.mesh.points
    ids = rng.choice(np.flatnonzero(true.depth(pts) > 0), 10, replace=False)
    X = pts[ids]
    uv = true.project(X) + rng.normal(0, 0.5, (10, 2))
    cal = calibrate_camera(X, uv, W, H)
    assert cal.method == "DLT" and not is_coplanar(X)
    assert _rms(cal.camera.project(pts), true.project(pts)) < 2.0
    assert cal.rms_px < 1.0


def test_noisy_click_above_the_bound_names_it(tmp_path):
    rng = np.random.default_rng(4)
    true = Camera.look_at((0.30, -0.25, 0.28), (0.05, 0.05, 0.05), fx=850, width=W, height=H)
    cube = resolve_object("box:0.1x0.1x0.1")
    ids = cube.corner_nodes()
    uv = true.project(cube.mesh.points[ids]) + rng.normal(0, 0.3, (len(ids), 2))
    uv[3] += (15.0, -12.0)
    path = tmp_path / "clicks.csv"
    rows = "".join(f"{i},{u},{v}\n" for i, (u, v) in zip(ids, uv, strict=True))
    path.write_text("vertex,u,v\n" + rows)
    with pytest.raises(CalibrationError, match="above the bound 2 px"):
        calibrate_from_file(path, cube.mesh.points, W, H)
    cal = calibrate_from_file(path, cube.mesh.points, W, H, max_error=None)
    assert cal.max_px > 2.0


def test_too_few_clicks(tmp_path):
    cube = resolve_object("box:0.1x0.1x0.1")
    X = cube.mesh.points[cube.corner_nodes()[:5]]
    with pytest.raises(CalibrationError, match="at least 6"):
        calibrate_camera(X, np.zeros((5, 2)) + np.arange(5)[:, None], W, H)
    with pytest.raises(CalibrationError, match="at least 4"):
        calibrate_camera(X[:3], np.zeros((3, 2)), W, H)


def test_clicks_csv_forms(tmp_path):
    pts = resolve_object("plate:0.1x0.1").mesh.points
    a = tmp_path / "a.csv"
    a.write_text("# corners\nvertex,u,v\n0,10,20\n20, 30.5,40\n")
    c = load_clicks_csv(a, pts)
    assert c.vertices.tolist() == [0, 20] and np.allclose(c.X[1], pts[20])
    b = tmp_path / "b.csv"
    b.write_text("x,y,z,u,v\n0.1,0,0,1,2\n")
    assert np.allclose(load_clicks_csv(b, pts).X, [[0.1, 0, 0]])
    bad = tmp_path / "bad.csv"
    bad.write_text("id,u,v\n0,1,2\n")
    with pytest.raises(CalibrationError, match="vertex,u,v or x,y,z,u,v"):
        load_clicks_csv(bad, pts)
    bad.write_text("vertex,u,v\n9999,1,2\n")
    with pytest.raises(CalibrationError, match="allowed 0 .. 440"):
        load_clicks_csv(bad, pts)


def test_object_forms_and_bad_input(tmp_path):
    box = resolve_object("box:0.1x0.08x0.05")
    assert np.allclose(box.mesh.points.max(0), [0.1, 0.08, 0.05])
    assert len(box.fixed_nodes) == 81 and len(box.corner_nodes()) == 8
    assert resolve_object("plate:0.1:circle").is_membrane
    for spec in ("box:0.1x0.1", "box:axbxc", "sphere:1", "nothing.stl", "box:1x1x1:fixed=top"):
        with pytest.raises(ObserveError, match="--object"):
            resolve_object(spec)


def test_surface_and_scene_objects(tmp_path):
    import trimesh

    stl = tmp_path / "block.stl"
    trimesh.creation.box(extents=(0.04, 0.03, 0.02)).export(stl)
    block = resolve_object(str(stl))  # a block is meshed as its voxel grid by default
    assert block.mesh.element == "hex8"
    obj = resolve_object(f"{stl}:mesh=tet")
    assert obj.kind == "mesh" and obj.mesh.element == "tet4"
    assert np.allclose(obj.mesh.points.min(0), 0) and np.allclose(
        obj.mesh.points.max(0), (0.04, 0.03, 0.02), atol=1e-3)
    assert len(obj.fixed_nodes) > 0 and len(obj.source_sha256) == 64
    scene = resolve_object(str(ROOT / "scenes" / "jello_cube_defect_top.toml"))
    assert scene.mesh.element == "hex8" and scene.inference_shape == (8, 8, 8)
    assert np.allclose(scene.mesh.points[scene.fixed_nodes, 2], 0)


def test_calibrate_command(tmp_path, capsys):
    from vvtbench.cli import main

    true = Camera.look_at((0.30, -0.25, 0.28), (0.05, 0.05, 0.05), fx=300, width=160,
                          height=120)
    rng = np.random.default_rng(5)
    video = tmp_path / "clip.npy"
    np.save(video, rng.random((3, 120, 160)).astype(np.float32))
    args = ["calibrate", str(video), "--object", "box:0.1x0.1x0.1", "-o", str(tmp_path / "c")]
    assert main(args) == 0
    assert (tmp_path / "c" / "calibration.png").stat().st_size > 1000
    assert "candidate vertices" in capsys.readouterr().out
    cube = resolve_object("box:0.1x0.1x0.1")
    ids = cube.corner_nodes()
    uv = true.project(cube.mesh.points[ids]) + rng.normal(0, 0.5, (len(ids), 2))
    clicks = tmp_path / "clicks.csv"
    clicks.write_text("vertex,u,v\n" + "".join(
        f"{i},{u},{v}\n" for i, (u, v) in zip(ids, uv, strict=True)))
    assert main([*args, "--clicks", str(clicks)]) == 0
    cal = json.loads((tmp_path / "c" / "calibration.json").read_text())
    assert cal["method"] == "DLT" and cal["rms_px"] < 1.0
    uv[2] += 9.0
    clicks.write_text("vertex,u,v\n" + "".join(
        f"{i},{u},{v}\n" for i, (u, v) in zip(ids, uv, strict=True)))
    assert main([*args, "--clicks", str(clicks)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--max-error" in err
    assert not (tmp_path / "c" / "calibration.json").exists()


def test_an_object_in_millimetres_is_warned_about_naming_the_unit(tmp_path, capsys):
    import warnings

    import trimesh

    from vvtbench.cli import main
    from vvtbench.field.calibrate import load_clicks_csv
    from vvtbench.field.objects import UnitWarning

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # metres: no warning at all
        assert resolve_object("box:0.05x0.05x0.05").warnings == []
        stl = tmp_path / "m.stl"
        trimesh.creation.box(extents=(0.04, 0.03, 0.02)).export(stl)
        assert resolve_object(str(stl)).warnings == []
    with pytest.warns(UnitWarning, match=r"millimetres \(it would be 0\.05 m\)"):
        box = resolve_object("box:50x50x50")
    assert len(box.warnings) == 1 and "50 m across" in box.warnings[0]
    mm = tmp_path / "mm.stl"
    trimesh.creation.box(extents=(40.0, 30.0, 20.0)).export(mm)
    with pytest.warns(UnitWarning, match="millimetres.*scale_to"):
        resolve_object(f"{mm}:mesh=tet")
    clicks = tmp_path / "mm.csv"
    clicks.write_text("x,y,z,u,v\n" + "".join(f"{x},{y},{z},{10 * i},{5 * i}\n" for i, (x, y, z)
                                              in enumerate([(0, 0, 0), (50, 0, 0), (0, 50, 0),
                                                            (50, 50, 0), (0, 0, 50),
                                                            (50, 0, 50)])))
    with pytest.warns(UnitWarning, match="clicked x,y,z.*millimetres"):
        load_clicks_csv(clicks, resolve_object("box:0.05x0.05x0.05").mesh.points)
    video = tmp_path / "clip.npy"
    np.save(video, np.random.default_rng(0).random((2, 60, 80)).astype(np.float32))
    capsys.readouterr()
    assert main(["calibrate", str(video), "--object", "box:100x100x100", "-o",
                 str(tmp_path / "c")]) == 0
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and err[0].startswith("warning: --object 'box:100x100x100'")
    assert "millimetres" in err[0]
