"""Field tracks (``[tracks.field]``): the suite keys, the re-encoded video read back by the
field readers (and by the formats' own libraries), the camera from noisy clicks against the
least-squares theory, and a tiny rendered track end to end."""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import numpy as np
import pytest

from vvtbench.bench.suite import SuiteError, parse_suite
from vvtbench.field.track import (
    FieldSettings,
    encode_video,
    reprojection_error,
    simulate_clicks,
)

BASE = """
name = "f"
solvers = ["homogeneous"]
[[tracks]]
name = "cube"
scenes = ["jello_cube_defect_top"]
observations = ["extracted"]
"""


def parse(extra: str, base: str = BASE):
    return parse_suite(tomllib.loads(base + extra), "f.toml")


def error_of(extra: str, base: str = BASE) -> str:
    with pytest.raises(SuiteError) as info:
        parse(extra, base)
    msg = str(info.value)
    assert msg.startswith("f.toml: ") and "\n" not in msg
    return msg


def test_field_keys_parse_with_their_defaults():
    assert parse("").tracks[0].field is None
    t = parse("[tracks.field]\nformat = 'h264'\ncrf = 28\nclick_noise_px = 1\n").tracks[0]
    assert t.field == {"format": "h264", "crf": 28, "click_noise_px": 1}
    s = FieldSettings.from_mapping(t.field)
    assert (s.clicks, s.object, s.click_seed, s.max_error_px) == (10, "stl", None, 2.0)
    assert s.resolved(7).click_seed == 7 and s.resolved(7).resolved(9).click_seed == 7
    assert "bit_depth" not in s.to_dict() and s.to_dict()["crf"] == 28


@pytest.mark.parametrize("table, key, allowed", [
    ("format = 'avi'", "tracks[0].field.format", "'tiff'"),
    ("clicks = 5", "tracks[0].field.clicks", "6..1000"),
    ("clicks = 10.0", "tracks[0].field.clicks", "6..1000"),
    ("bit_depth = 10", "tracks[0].field.bit_depth", "8, 12 or 16"),
    ("click_noise_px = -0.1", "tracks[0].field.click_noise_px", "[0, 100]"),
    ("click_seed = -1", "tracks[0].field.click_seed", "an integer >= 0"),
    ("object = 'obj'", "tracks[0].field.object", "'stl'"),
    ("mesh = 'hex'", "tracks[0].field.mesh", "'auto'"),
    ("max_error_px = 0", "tracks[0].field.max_error_px", "(0, 1000]"),
    ("crf = 20", "tracks[0].field", "'crf' applies to 'h264' only"),
    ("format = 'h264'\nbit_depth = 12", "tracks[0].field", "allowed with 'h264': crf"),
    ("bitrate_mbps = 50", "tracks[0].field", "'bitrate_mbps' applies to 'h264' only"),
    ("format = 'h264'\ncrf = 20\nbitrate_mbps = 50", "tracks[0].field", "not both"),
    ("format = 'h264'\nbitrate_mbps = 0", "tracks[0].field.bitrate_mbps", "(0, 10000]"),
    ("clickz = 10", "tracks[0].field.clickz", "click_noise_px"),
])
def test_bad_field_values_are_one_line_errors(table, key, allowed):
    msg = error_of(f"[tracks.field]\n{table}\n")
    assert f"key '{key}'" in msg and allowed in msg, msg


def test_a_field_track_observes_extracted_modes_only():
    base = BASE.replace('observations = ["extracted"]', 'observations = ["true", "extracted"]')
    msg = error_of("[tracks.field]\n", base)
    assert "key 'tracks[0].observations'" in msg and "'true'" in msg and "allowed" in msg


def _graph(extra: str, base: str = BASE, seeds: str = ""):
    from vvtbench.bench.graph import build_graph

    return build_graph(parse(extra, base.replace('name = "f"', f'name = "f"\n{seeds}')),
                       ["homogeneous"])


def test_rows_record_the_field_settings_and_the_click_seed():
    plain_tasks, plain = _graph("")
    assert "field" not in plain_tasks[plain[0].observe_key].payload
    assert not any(k.startswith("field.") for k in plain[0].variation_options)
    tasks, runs = _graph("[tracks.field]\nclick_noise_px = 0.25\n", seeds="seeds = [3, 4]")
    assert [r.seed for r in runs] == [3, 4]
    for r in runs:
        opts = r.variation_options
        assert opts["field.click_seed"] == r.seed and opts["field.click_noise_px"] == 0.25
        assert opts["field.format"] == "tiff" and opts["field.bit_depth"] == 12
        assert tasks[r.observe_key].payload["field"]["click_seed"] == r.seed
    # tracks that differ in their clicks only share the encoded video's extraction
    two = BASE + "[tracks.field]\n" + BASE.split("name = \"f\"")[1].split(
        "solvers = [\"homogeneous\"]")[1].replace('"cube"', '"cube2"')
    tasks, runs = _graph("[tracks.field]\nclick_noise_px = 1.0\n", two)
    assert len({k for k in tasks if k.startswith("extract/")}) == 1
    assert len({r.observe_key for r in runs}) == 2
    _, fixed = _graph("[tracks.field]\nclick_seed = 11\n", seeds="seeds = [3]")
    assert fixed[0].variation_options["field.click_seed"] == 11


def test_the_field_path_refuses_what_it_cannot_honour():
    with pytest.raises(SuiteError, match="key 'views' = 2 is not allowed"):
        _graph("[tracks.field]\n[tracks.defaults]\nviews = 2\n")
    drum = BASE.replace("jello_cube_defect_top", "drum_homogeneous")
    with pytest.raises(SuiteError, match="'field.object' = 'stl' is not allowed for the memb"):
        _graph("[tracks.field]\n", drum)


def _frames(n: int, shape=(6, 8), seed: int = 0):
    rng = np.random.default_rng(seed)
    return [rng.random(shape).astype(np.float32) for _ in range(n)]


def test_tiff_sequence_is_read_back_at_12_bits(tmp_path):
    import tifffile

    from vvtbench.video.files import open_video

    frames = _frames(5)
    path = encode_video(iter(frames), 500.0, tmp_path, FieldSettings(format="tiff"))
    files = sorted(path.iterdir())
    assert len(files) == 5
    raw = tifffile.imread(files[2])  # the format's own library
    assert raw.dtype == np.uint16 and raw.max() <= 4095
    np.testing.assert_array_equal(raw, np.rint(frames[2].astype(np.float64) * 4095))
    stream = open_video(path)
    back = list(stream.frames)
    assert len(back) == 5 and stream.fps is None  # an image sequence states no rate
    np.testing.assert_allclose(back[2], raw / 4095.0, atol=1e-7)
    assert np.max(np.abs(back[2] - frames[2])) <= 0.5 / 4095 + 1e-7


def test_mraw_is_read_back_like_pymraw(tmp_path):
    import pyMRAW

    from vvtbench.video.files import open_video

    frames = _frames(4, (6, 8), seed=1)
    cih = encode_video(iter(frames), 20000.0, tmp_path, FieldSettings(format="mraw"))
    reference, info = pyMRAW.load_video(str(cih))  # the format's own library
    want = np.rint(np.stack(frames).astype(np.float64) * 4095)
    np.testing.assert_array_equal(np.asarray(reference, dtype=np.float64), want)
    stream = open_video(cih)
    assert float(stream.fps) == 20000.0 and int(info["Color Bit"]) == 12
    np.testing.assert_allclose(np.stack(list(stream.frames)), want / 4095, atol=1e-7)


def test_h264_is_lossy_but_close(tmp_path):
    from vvtbench.video.files import open_video

    yy, xx = np.mgrid[0:32, 0:32]
    frames = [(0.5 + 0.3 * np.sin(xx / 4 + k / 3) * np.cos(yy / 5)).astype(np.float32)
              for k in range(8)]
    path = encode_video(iter(frames), 1000.0, tmp_path, FieldSettings(format="h264", crf=18))
    back = np.stack(list(open_video(path).frames))
    assert back.shape == (8, 32, 32)
    err = np.abs(back - np.stack(frames))
    assert 0 < err.mean() < 0.02


def test_h264_at_a_bit_rate_holds_that_many_bits_per_second_of_recording(tmp_path):
    """Noise frames (incompressible): the file holds about bitrate x recorded seconds."""
    from vvtbench.video.files import open_video

    frames = _frames(120, (64, 64), seed=3)  # 0.5 s at 240 fps
    sizes = {}
    for mbps in (0.5, 2.0):
        path = encode_video(iter(frames), 240.0, tmp_path / str(mbps),
                            FieldSettings(format="h264", bitrate_mbps=mbps))
        sizes[mbps] = path.stat().st_size
        assert sizes[mbps] == pytest.approx(mbps * 1e6 * 0.5 / 8, rel=0.35)
        assert len(list(open_video(path).frames)) == 120
    assert FieldSettings(format="h264", bitrate_mbps=2.0).key()["video"] == {
        "format": "h264", "bitrate_mbps": 2.0}


@pytest.fixture(scope="module")
def box_view():
    from vvtbench.field.calibrate import default_camera
    from vvtbench.field.objects import resolve_object

    obj = resolve_object("box:0.05x0.05x0.05", inference_shape=(4, 4, 4))
    return obj, default_camera(obj.mesh.points, 256, 256)


def test_noisy_click_camera_matches_least_squares_theory(box_view):
    """Monte-Carlo over click-noise seeds against the linearised least-squares results for
    p = 10 camera parameters (fx, fy, cx, cy, rotation, translation) fitted to n clicks:
    E[sum of squared residuals] = sigma^2 (2n - p), and at the clicked points the fitted
    projection moves from the true one by E[sum of squares] = sigma^2 p."""
    from vvtbench.field.calibrate import calibrate_camera

    obj, camera = box_view
    n, sigma, p = 10, 0.5, 10
    residual, at_clicks, elsewhere = [], [], []
    for seed in range(60):
        vert, X, uv = simulate_clicks(obj.mesh.points, obj.mesh.surface, obj.corner_nodes(),
                                      camera, n, sigma, seed)
        assert len(set(vert.tolist())) == n
        cal = calibrate_camera(X, uv, 256, 256, max_error=None)
        residual.append(cal.rms_px ** 2 * n)
        at_clicks.append(reprojection_error(cal.camera, camera, X)["rms_px"] ** 2 * n)
        elsewhere.append(reprojection_error(cal.camera, camera, obj.mesh.points)["rms_px"])
    assert np.mean(residual) == pytest.approx(sigma ** 2 * (2 * n - p), rel=0.2)
    assert np.mean(at_clicks) == pytest.approx(sigma ** 2 * p, rel=0.25)
    assert np.median(elsewhere) < 2 * sigma
    # without noise the clicks give the true camera
    _, X, uv = simulate_clicks(obj.mesh.points, obj.mesh.surface, obj.corner_nodes(), camera,
                               n, 0.0, 0)
    exact = calibrate_camera(X, uv, 256, 256)
    assert reprojection_error(exact.camera, camera, obj.mesh.points)["max_px"] < 1e-6
    # the same seed draws the same clicks
    a = simulate_clicks(obj.mesh.points, obj.mesh.surface, obj.corner_nodes(), camera, n,
                        sigma, 5)[2]
    b = simulate_clicks(obj.mesh.points, obj.mesh.surface, obj.corner_nodes(), camera, n,
                        sigma, 5)[2]
    np.testing.assert_array_equal(a, b)


def test_an_stl_block_is_meshed_as_the_box(tmp_path):
    import trimesh

    from vvtbench.field.objects import resolve_object
    from vvtbench.field.track import write_object_surface
    from vvtbench.observe import ObserveError
    from vvtbench.scene.scene import load_scene

    stl = write_object_surface(load_scene("jello_cube_defect_top"), tmp_path / "cube.stl")
    box = resolve_object("box:0.05x0.05x0.05", inference_shape=(4, 4, 4))
    for how in ("auto", "block"):
        obj = resolve_object(f"{stl}:mesh={how}", inference_shape=(4, 4, 4))
        assert obj.info["meshed_as"] == "block" and obj.mesh.element == "hex8"
        np.testing.assert_allclose(obj.mesh.points, box.mesh.points, atol=1e-12)
        np.testing.assert_array_equal(obj.fixed_nodes, box.fixed_nodes)
    assert resolve_object(str(stl)).mesh.element == "hex8"  # the default: auto
    assert resolve_object(f"{stl}:mesh=tet").mesh.element == "tet4"
    ball = tmp_path / "ball.stl"
    trimesh.creation.icosphere(subdivisions=1, radius=0.02).export(ball)
    assert resolve_object(f"{ball}:mesh=auto").mesh.element == "tet4"
    with pytest.raises(ObserveError, match="mesh=block, but the surface is not"):
        resolve_object(f"{ball}:mesh=block")


TINY_FIELD = """
name = "tiny_field"
scenes = ["jello_cube_defect_top"]
solvers = ["homogeneous"]
seeds = [2]
observations = ["extracted"]

[defaults]
"geometry.cells" = [4, 4, 4]
"simulation.n_modes" = 6
"simulation.fps" = 200.0
"simulation.duration" = 0.8
"camera.resolution" = [64, 64]
"excitation.displacement" = 0.002
"render.supersample" = 1
n_modes = 3
inference_shape = [2, 2, 2]
visibility = "normals"

[extract]
max_modes = 6
fmax = 95.0

[[tracks]]
name = "field"
scenes = ["jello_cube_defect_top"]
[tracks.field]
format = "tiff"
clicks = 8
click_noise_px = 0.3

[[tracks]]
name = "field_scene"
scenes = ["jello_cube_defect_top"]
[tracks.field]
format = "tiff"
clicks = 8
click_noise_px = 0.3
object = "scene"
"""


def test_a_tiny_field_track_end_to_end(tmp_path):
    """Render, re-encode as a 12-bit TIFF sequence, extract from it, calibrate from 8 noisy
    clicks on an STL of the cube, solve and score: the row is ok and records its settings."""
    from vvtbench.bench import run_suite

    suite = tmp_path / "tiny_field.toml"
    suite.write_text(TINY_FIELD)
    df = run_suite(str(suite), None, tmp_path / "run", progress=False)
    assert len(df) == 2 and (df.status == "ok").all(), df.error.tolist()
    assert df.attrs["stats"]["extract"]["tasks"] == 1  # the two tracks share the video
    row = df[df.track == "field"].iloc[0]
    opts = json.loads(row.variation_options)
    assert opts["field.click_seed"] == 2 and opts["field.clicks"] == 8
    assert opts["field.format"] == "tiff" and opts["field.click_noise_px"] == 0.3
    cache = Path(tmp_path / "run" / "cache")
    records = {r["object"]["kind"]: r for r in (
        json.loads(f.read_text()) for f in cache.glob("observe/*/calibration.json"))}
    assert set(records) == {"mesh", "scene"}
    record = records["mesh"]
    assert record["object"]["meshed_as"] == "block" and len(record["clicked_vertices"]) == 8
    assert record["camera_error_px"]["rms_px"] < 3 * 0.3
    # the STL block and the scene give the same mesh, hence the same clicks and camera
    assert records["scene"]["clicked_vertices"] == record["clicked_vertices"]
    assert records["scene"]["camera_error_px"] == pytest.approx(record["camera_error_px"])
    (video,) = cache.glob("extract/*/field_video.json")
    assert json.loads(video.read_text())["files"] == 160  # 0.8 s at 200 fps
    assert not [p for p in (cache / "extract").iterdir() if ".tmp-" in p.name]


def test_sample_truth_is_the_truth_observe_gives(tmp_path):
    """On the problem ``observe`` builds from a sample, the truth ``sample_truth`` computes
    without the scene's inference settings is observe's own: same voxel material, each mode
    paired with itself (MAC 1, same sign and eigenvalue)."""
    from vvtbench.observe import ObserveError, observe, sample_truth
    from vvtbench.samples.generate import generate
    from vvtbench.scene.scene import parse_scene

    scene = parse_scene({
        "name": "tiny_truth", "seed": 5, "geometry": {"kind": "box", "cells": [3, 3, 3]},
        "material": {"E": 9000.0, "rho": 1270.0, "nu": 0.3, "defects": [
            {"shape": "box", "center": [0.04, 0.04, 0.04], "size": [0.03, 0.03, 0.03],
             "E": 3.0e4, "rho": 1800.0}]},
        "simulation": {"n_modes": 6}, "camera": {"resolution": [48, 48]}}, "tiny_truth")
    sample = generate(scene, tmp_path, progress=False, video=False)
    problem, truth = observe(sample, observation="true", n_modes=4, inference_shape=(2, 2, 2),
                             visibility="normals")
    paired, got = sample_truth(sample, problem)
    np.testing.assert_array_equal(got.w, truth.w)
    np.testing.assert_array_equal(got.v, truth.v)
    np.testing.assert_array_equal(got.matched, np.arange(4))
    np.testing.assert_allclose(got.extraction_mac, 1.0, atol=1e-12)
    np.testing.assert_allclose(got.modes_3d, truth.modes_3d, atol=1e-12)
    np.testing.assert_allclose(got.eigenvalues, truth.eigenvalues, rtol=1e-12)
    np.testing.assert_array_equal(paired.gamma, problem.gamma)
    assert np.isnan(paired.mode_snr).all() and got.meta["scene"] == "tiny_truth"
    with pytest.raises(ObserveError, match="cannot take the truth of a str"):
        sample_truth(str(tmp_path / "nowhere"), problem)
