"""Several cameras in one sample: scenes with views, generation of every view from one
simulation, reading a view back, joint extraction across views and the stacked problem."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from vvtbench.modes import modes_from_displacements
from vvtbench.modes.joint import joint_modes, modal_phasors
from vvtbench.observe import observe
from vvtbench.render import Camera
from vvtbench.samples import generate as gen
from vvtbench.samples import reader as ds
from vvtbench.scene.scene import SceneError, parse_scene, with_overrides

SMALL = {  # a box without symmetry (no repeated frequencies), 300 frames of 64x64 px
    "name": "small",
    "seed": 3,
    "geometry": {"kind": "box", "size": [0.05, 0.04, 0.06], "cells": [3, 3, 3]},
    "excitation": {"kind": "pluck", "at": [0.05, 0.0, 0.06], "displacement": 0.003},
    "simulation": {"n_modes": 6, "duration": 3.0, "fps": 100.0},
    "camera": {"resolution": [64, 64], "position": [0.16, -0.13, 0.13],
               "look_at": [0.025, 0.02, 0.03], "fov_y_deg": 30.0},
    "render": {"supersample": 2},
}
RIG = {"views": 2, "spread_deg": 90.0}
OBSERVE = dict(n_modes=6, inference_shape=(3, 3, 3))


def scene(camera: dict | None = None, name: str = "small", **simulation):
    data = json.loads(json.dumps(SMALL))
    data["name"] = name
    data["camera"].update(camera or {})
    data["simulation"].update(simulation)
    return parse_scene(data, f"{name}.toml")


def _tree(path: Path) -> dict[str, bytes]:
    return {p.relative_to(path).as_posix(): p.read_bytes()
            for p in sorted(path.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def samples(tmp_path_factory, monkeypatch_module):
    import vvtbench.simulation.simulate as simulate_module

    calls = []
    real = simulate_module.simulate
    monkeypatch_module.setattr(simulate_module, "simulate",
                               lambda *a, **k: calls.append(1) or real(*a, **k))
    out = tmp_path_factory.mktemp("mv")
    two = gen.generate(scene({"rig": RIG}), out / "two", progress=False)
    assert len(calls) == 1  # one simulation, rendered twice
    one = gen.generate(scene(), out / "one", progress=False)
    return one, two


@pytest.fixture(scope="module")
def monkeypatch_module():
    mp = pytest.MonkeyPatch()
    yield mp
    mp.undo()


# --------------------------------------------------------------------------- scenes


@pytest.mark.parametrize(("camera", "message"), [
    ({"rig": {"views": 1}}, "key 'camera.rig.views': got 1; allowed: an integer >= 2"),
    ({"rig": {"views": 2, "kind": "fan"}}, "key 'camera.rig.kind'"),
    ({"rig": {"views": 3, "kind": "cone", "spread_deg": 200}}, "allowed: a finite number > 0 "
     "and < 180"),
    ({"rig": {"views": 2}, "views": [{}]}, "either [[camera.views]] or [camera.rig]"),
    ({"views": [{"zoom": 2}]}, "key 'camera.views[0].zoom': unknown key; allowed keys here: "
     "position"),
    ({"rig": {"views": 2, "time_offset_s": -1}}, "key 'camera.rig.time_offset_s'"),
])
def test_bad_views_are_one_line_naming_file_key_and_allowed(camera, message):
    with pytest.raises(SceneError) as info:
        scene(camera)
    text = str(info.value)
    assert text.startswith("small.toml: ") and message in text and "\n" not in text


def test_listed_views_inherit_the_camera_and_resolve_stably():
    s = scene({"views": [{"position": [-0.1, 0.2, 0.1]}, {"fx": 90.0}]})
    first, second = s.camera.views
    assert s.camera.n_views == 3 and first.resolution == (64, 64)
    assert first.look_at == s.camera.look_at and first.fov_y_deg == 30.0
    assert Camera.from_spec(second).fx == 90.0 and second.position == (0.16, -0.13, 0.13)
    assert parse_scene(s.to_toml_dict()).to_toml_dict() == s.to_toml_dict()
    resized = with_overrides(s, resolution=(32, 48))
    assert {v.resolution for v in resized.camera.views} == {(32, 48)}
    assert "views" not in scene().to_toml_dict()["camera"]  # single view: as before


def test_ring_and_cone_views_look_at_the_same_point():
    target = np.array(SMALL["camera"]["look_at"])
    ring = Camera.views_from_spec(scene({"rig": {"views": 4, "spread_deg": 360}}).camera)
    cone = Camera.views_from_spec(scene({"rig": {"views": 4, "kind": "cone",
                                                 "spread_deg": 60}}).camera)
    c0 = ring[0].center - target
    assert ring[0] == Camera.from_spec(scene().camera) and cone[0] == ring[0]
    for i, cam in enumerate(ring):
        assert np.allclose(cam.project(target), [31.5, 31.5])
        c = cam.center - target
        assert np.linalg.norm(c) == pytest.approx(np.linalg.norm(c0))
        assert c[2] == pytest.approx(c0[2])  # turned about the vertical
        angle = np.degrees(np.arctan2(c[1], c[0]) - np.arctan2(c0[1], c0[0])) % 360
        assert angle == pytest.approx(90.0 * i)
    for cam in cone[1:]:
        c = cam.center - target
        assert np.allclose(cam.project(target), [31.5, 31.5])
        assert np.degrees(np.arccos(c @ c0 / (c0 @ c0))) == pytest.approx(30.0)


# --------------------------------------------------------------------------- generation


def test_two_views_render_two_videos_of_one_simulation(samples):
    _, two = samples
    s = ds.open_sample(two)
    assert s.verify() == [] and s.n_views == 2
    files = _tree(two)
    for rel in ("video.mkv", "camera.json", "rest.png", "views/1/video.mkv",
                "views/1/camera.json", "views/1/rest.png", "views/1/depth.png"):
        assert rel in files
    v = s.view(1)
    assert v.camera != s.camera and v.n_frames == s.n_frames == 300
    assert v.read_frames(0, 2).shape == (2, 64, 64)
    # the view's own truth, the shared truth from the root
    assert not np.array_equal(v["observation/rest_uv"], s["observation/rest_uv"])
    assert np.array_equal(v["modes/surface"], s["modes/surface"])
    assert np.allclose(v["observation/rest_uv"], v.camera.project(s["mesh/points"][
        s["mesh/surface_nodes"]]))
    assert v.require("image/modes").shape == (6, 64, 64, 2) and v.crb_snr.shape == (6,)
    with pytest.raises(ds.DatasetError, match="no view 2; the sample holds views 0..1"):
        s.view(2)


def test_view_zero_is_the_single_view_sample(samples):
    one, two = samples
    a, b = _tree(one), _tree(two)
    shared = [rel for rel in a if rel not in ("truth.json", "manifest.json", "scene.toml")]
    assert shared and all(rel in b and a[rel] == b[rel] for rel in shared)
    extra = sorted(set(b) - set(a))
    assert extra and all(rel.startswith(("views/1/", "truth.zarr/views/")) for rel in extra)
    info_a, info_b = (json.loads(x["truth.json"]) for x in (a, b))
    assert info_a == {k: v for k, v in info_b.items() if k != "views"}


def test_a_modes_only_sample_holds_every_view_without_video(tmp_path):
    cameras = {"views": [{"position": [-0.1, 0.2, 0.12]}]}
    s = ds.open_sample(gen.generate(scene(cameras), tmp_path, video=False, progress=False))
    v = s.view(1)
    assert s.n_views == 2 and not v.has_video and v.info["video"]["file"] is None
    assert v.camera == Camera.from_spec(s.scene.camera.views[0])
    assert "views/1/image/modes" not in s.truth and "views/1/image/depth" in s.truth
    problem, _ = observe(s, views=2, **OBSERVE)
    assert problem.meta["view_source"] == "sample"
    assert problem.meta["cameras"][1] == v.camera.to_dict()
    with pytest.raises(ds.DatasetError, match="modes-only"):
        next(v.frames())


FROZEN = Path(__file__).resolve().parent / "data" / "vvtbench-v1"
"""A copy of frozen files of the release vvtbench-v1 (what its list fixes, checked below)."""


def test_a_single_view_sample_of_the_frozen_release_regenerates_value_by_value(tmp_path):
    """Instance 0 of cube_defects val, generated afresh, is the frozen one: its scene and family
    record byte for byte, every value within the release's tolerances. Its other bytes are the
    frozen ones only where the floating-point arithmetic is (docs/dataset.md, "Same answer on
    every machine"): the frozen modes' signs predate the canonical ones and another CPU's BLAS
    rounds otherwise, so bytes are not compared."""
    from vvtbench.datasets.release import load_release, read_sums
    from vvtbench.samples.compare import compare_samples
    from vvtbench.samples.jobs import generate_instance

    release = load_release("vvtbench-v1")
    rel = "cube_defects-modes/val/cube_defects-val-00000"
    frozen = FROZEN / rel
    assert ds.sha256_file(frozen / "manifest.json") == read_sums(release.sums_path)[
        f"{rel}/manifest.json"]  # the kept copy is the frozen sample...
    assert ds.open_sample(frozen).verify() == []  # ...file by file
    job = generate_instance({"out": str(tmp_path), "family": "cube_defects", "split": "val",
                             "index": 0, "options": {"video": False, "progress": False}})
    path = Path(job["path"])
    assert ds.open_sample(path).verify() == []
    for name in ("scene.toml", "family.json"):  # the same bits on every machine
        assert (path / name).read_bytes() == (frozen / name).read_bytes(), name
    result = compare_samples(frozen, path, release.tolerances())
    assert result.problems == [], result.summary()
    assert result.compared > 0 and result.worst["modes/vectors"] <= 1e-10


def test_a_damaged_view_is_named_on_open(samples, tmp_path):
    _, two = samples
    copy = tmp_path / "small"
    shutil.copytree(two, copy)
    video = copy / "views" / "1" / "video.mkv"
    video.write_bytes(video.read_bytes()[: video.stat().st_size // 2])
    with pytest.raises(ds.DatasetError, match=r"views/1/video.mkv"):
        ds.open_sample(copy)
    (copy / "views" / "1" / "video.mkv").unlink()
    info = json.loads((copy / "truth.json").read_text())
    info["views"][1]["camera"] = "../camera.json"
    (copy / "truth.json").write_text(json.dumps(info))
    problems = ds.open_sample(copy, verify=False).verify()
    assert any("views[1] does not name views/1/camera.json" in p for p in problems)


def test_a_time_offset_films_the_later_view_later(tmp_path):
    step = 1.0 / SMALL["simulation"]["fps"]
    nearly_same = {"rig": {"views": 2, "spread_deg": 1e-7, "time_offset_s": 2 * step}}
    path = gen.generate(scene(nearly_same, name="late", duration=0.3), tmp_path,
                        progress=False)
    s = ds.open_sample(path)
    a = s.read_frames().astype(np.int64)
    b = s.view(1).read_frames().astype(np.int64)
    assert s.view(1).info["view"]["time_offset_s"] == pytest.approx(2 * step)
    assert np.abs(b[:-2] - a[2:]).max() <= 1  # the same camera, two frames later
    assert np.abs(b - a).max() > 20
    with pytest.raises(ds.DatasetError, match=r"camera.rig.time_offset_s.*multiples of"):
        gen.generate(scene({"rig": {"views": 2, "time_offset_s": 0.3 * step}},
                           name="odd", duration=0.1), tmp_path, progress=False)


# --------------------------------------------------------------------------- joint modes

H = W = 24
FPS, T = 200.0, 400
FREQS, AMPS, PHASES = (11.0, 23.5, 37.0), (0.05, 0.03, 0.02), (0.3, 2.0, -1.0)


def _field(a: float, b: float, c: float) -> np.ndarray:
    y, x = np.mgrid[0:H, 0:W] / H
    f = np.zeros((H, W, 2))
    f[..., 0] = np.sin(np.pi * (a * x + 0.3)) * np.cos(np.pi * b * y)
    f[..., 1] = c * np.cos(np.pi * a * x) * np.sin(np.pi * (b * y + 0.2))
    return f


# view 1 sees mode 0 with the opposite sign convention, mode 1 three times larger, not mode 2
PSI = ([_field(1, 1, 0.5), _field(2, 1, -0.7), _field(1, 3, 0.3)],
       [-0.8 * _field(1, 2, 0.4), 3.0 * _field(3, 1, 0.6), np.zeros((H, W, 2))])


def _displacements(psi: list, delay: float, rng) -> np.ndarray:
    t = np.arange(T) / FPS + delay
    d = sum(a * np.cos(2 * np.pi * f * t + p)[:, None, None, None] * s
            for a, f, p, s in zip(AMPS, FREQS, PHASES, psi, strict=True))
    return d + 1e-4 * rng.standard_normal(d.shape)


def _true_stacked(i: int) -> np.ndarray:
    v = np.concatenate([PSI[0][i].ravel(), PSI[1][i].ravel()])
    return v / np.linalg.norm(v)


@pytest.mark.parametrize("delay", [0.0, 0.013])
def test_joint_modes_recover_one_mode_set_with_aligned_phases(delay):
    rng = np.random.default_rng(1)
    disp = [_displacements(PSI[0], 0.0, rng), _displacements(PSI[1], delay, rng)]
    sets = [modes_from_displacements(d, FPS) for d in disp]
    z = [modal_phasors(d, FPS, m, kind="displacements") for d, m in zip(disp, sets,
                                                                         strict=True)]
    joint = joint_modes(sets, z, time_offsets_s=[0.0, delay])
    assert np.allclose(joint.frequencies_hz, FREQS, rtol=1e-4)
    assert (joint.members >= 0).tolist() == [[True, True], [True, True], [True, False]]
    assert abs(joint.metadata["phase_deg"][1]) < 1.0  # genlocked once the delay is removed
    norm = [[np.linalg.norm(PSI[v][i]) for v in (0, 1)] for i in (0, 1)]
    assert np.allclose(np.abs(joint.scales[:2, 1] / joint.scales[:2, 0]),
                       [n1 / n0 for n0, n1 in norm], rtol=1e-3)
    stacked = joint.stack([m.shapes.reshape(len(m), -1) for m in sets])
    for i in range(3):
        assert abs(stacked[i] @ _true_stacked(i)) > 0.9999
    # stacking the unit shapes as they are (no phases, no scales) is wrong
    naive = np.hstack([np.eye(3)[:, :len(m)] @ m.shapes.reshape(len(m), -1) for m in sets])
    naive /= np.linalg.norm(naive, axis=1, keepdims=True)
    assert abs(naive[0] @ _true_stacked(0)) < 0.5 and abs(naive[1] @ _true_stacked(1)) < 0.9
    if delay:  # a delay left unknown is absorbed by no common phase: a mode comes out wrong
        blind = joint_modes(sets, z).stack([m.shapes.reshape(len(m), -1) for m in sets])
        assert min(abs(blind[i] @ _true_stacked(i)) for i in range(2)) < 0.9


def test_phasors_from_frames_agree_with_phasors_from_motion():
    from scipy.ndimage import gaussian_filter, map_coordinates

    rng = np.random.default_rng(4)
    texture = gaussian_filter(rng.random((H, W)), 1.5)
    texture = (texture - texture.min()) / np.ptp(texture)
    disp = _displacements(PSI[0], 0.0, rng)[:200] * 4.0
    yy, xx = np.mgrid[0:H, 0:W].astype(float)
    frames = np.stack([map_coordinates(texture, (yy - d[..., 1], xx - d[..., 0]), order=3,
                                       mode="reflect") for d in disp])
    ms = modes_from_displacements(disp, FPS)
    from_motion = modal_phasors(disp, FPS, ms, kind="displacements")
    from_frames = modal_phasors(frames, FPS, ms)
    assert from_frames.shape == (3,)
    ratio = from_frames / from_motion
    assert np.all(np.abs(np.angle(ratio)) < np.radians(10))  # same phase, same sign
    assert np.all((np.abs(ratio) > 0.5) & (np.abs(ratio) < 1.5))


# --------------------------------------------------------------------------- observe + solve


def test_extracted_modes_of_two_views_make_one_stacked_problem(samples):
    _, two = samples
    one_view, _ = observe(two, observation="extracted", **OBSERVE)
    problem, truth = observe(two, observation="extracted", views=2, **OBSERVE)
    true2, _ = observe(two, views=2, **OBSERVE)
    assert problem.meta["view_source"] == "sample"
    assert problem.P.shape == true2.P.shape and problem.P.shape[0] > one_view.P.shape[0]
    assert np.allclose(problem.P.toarray(), true2.P.toarray())
    assert problem.gamma.shape == (problem.n_modes, problem.P.shape[0]) and problem.n_modes >= 3
    assert np.allclose(np.linalg.norm(problem.gamma, axis=1), 1.0)
    assert abs(problem.meta["view_phase_deg"][1]) < 5.0  # genlocked views: no phase
    assert np.median(truth.extraction_mac) > 0.8
    assert problem.meta["observed_dof_fraction"] > one_view.meta["observed_dof_fraction"]


def test_mode_sets_extracted_per_view_elsewhere_give_the_same_problem(samples):
    from vvtbench.modes import extract_modes
    from vvtbench.observe import ObserveError

    _, two = samples
    s = ds.open_sample(two)
    sets = [extract_modes(s.view(v).video_path, s.fps) for v in (0, 1)]
    given, _ = observe(two, observation="extracted", views=2, modes=sets, **OBSERVE)
    auto, _ = observe(two, observation="extracted", views=2, **OBSERVE)
    assert np.allclose(given.gamma, auto.gamma) and np.allclose(given.eigenvalues,
                                                                auto.eigenvalues)
    with pytest.raises(ObserveError, match="one mode set per view"):
        observe(two, observation="extracted", views=2, modes=sets[:1], **OBSERVE)


def test_joined_views_without_modes_are_said_in_words(samples):
    """As one view without modes is: never a bare error from deep inside the join."""
    from vvtbench.modes import extract_modes
    from vvtbench.observe import ObserveError

    _, two = samples
    s = ds.open_sample(two)
    sets = [extract_modes(s.view(v).video_path, s.fps) for v in (0, 1)]
    none = [m.select(np.zeros(len(m), dtype=bool)) for m in sets]
    with pytest.raises(ObserveError, match=r"^no modes were extracted from the views' videos"):
        observe(two, observation="extracted", views=2, modes=none, **OBSERVE)
    with pytest.raises(ObserveError, match=r"^no modes were extracted from the video of view 1 "):
        observe(two, observation="extracted", views=2, modes=[sets[0], none[1]], **OBSERVE)


@pytest.mark.parametrize("solver", ["sensitivity", "vvt"])
def test_solvers_take_the_two_view_extracted_problem_unchanged(samples, solver):
    from vvtbench.scoring.metrics import invalid_reason
    from vvtbench.solving.sealed import solve_sealed

    _, two = samples
    problem, _ = observe(two, observation="extracted", views=2, **OBSERVE)
    config = {"max_iter": 3} if solver == "vvt" else {}
    est, _, info = solve_sealed(solver, config, problem, timeout=300)
    assert est.w.shape == (problem.n_params,) and info["sandbox"] in ("bwrap", "none")
    assert invalid_reason(est.w, est.v, problem.n_params) is None or solver == "vvt"


VIEWS_SUITE = """
name = "views_micro"
scenes = ["jello_cube_defect_top"]
solvers = ["homogeneous", "sensitivity"]
seeds = [0]
observations = ["extracted"]

[defaults]
"geometry.cells" = [5, 5, 5]
"simulation.n_modes" = 12
"simulation.fps" = 400.0
"simulation.duration" = 1.0
"camera.resolution" = [96, 96]
"camera.rig.views" = 2
"render.supersample" = 2
"excitation.displacement" = 0.0006
n_modes = 5
inference_shape = [3, 3, 3]

[extract]
max_modes = 8
fmax = 150.0

[solver.sensitivity]
max_iter = 2

[[tracks]]
name = "views"
scenes = ["jello_cube_defect_top"]
[tracks.sweep]
views = [1, 2]
"""


def test_a_suite_track_extracts_every_view_and_observes_them_joined(tmp_path, capsys):
    """`views` on an extracted track of a rig sample: one extraction per view (view 0's shared
    with the one-view variation), one problem stacking both views; the findings script reads
    each row's DOFs observed and cost back from the run's cache."""
    import json

    from vvtbench.bench import run_suite

    suite_file = tmp_path / "views.toml"
    suite_file.write_text(VIEWS_SUITE)
    df = run_suite(str(suite_file), None, tmp_path / "run", progress=False)
    assert (df["status"] == "ok").all(), df[["variation", "solver", "error"]]
    stats = {s: v["computed"] for s, v in df.attrs["stats"].items()}
    assert stats["generate"] == 1 and stats["extract"] == 2 and stats["observe"] == 2
    metas = {}
    for f in (tmp_path / "run" / "cache" / "observe").rglob("problem.json"):
        meta = json.loads(f.read_text())["meta"]
        metas[meta.get("views", 1)] = meta
    assert set(metas) == {1, 2}
    assert len(metas[2]["n_visible_per_view"]) == 2
    assert metas[2]["observed_dof_fraction"] > metas[1]["observed_dof_fraction"]
    _findings_read_the_views_back(df, tmp_path / "run", metas, capsys)


def _findings_read_the_views_back(df, run_dir: Path, metas: dict, capsys) -> None:
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from standard_findings import _observed, _views, _views_of

    assert _views_of(df).tolist() == [json.loads(o)["views"] for o in df.variation_options]
    capsys.readouterr()
    _views(df, run_dir)
    out = capsys.readouterr().out
    table = [line.split(" | ") for line in out.splitlines() if line.startswith("  sensitivity |")]
    assert [(int(r[1]), float(r[2])) for r in table] == [
        (n, round(metas[n]["observed_dof_fraction"], 3)) for n in (1, 2)]
    assert table[1][4] != "--" and float(table[1][-1]) > float(table[0][-1]) > 0
    assert "NC w against DOFs observed" in out
    one, two = (df[(_views_of(df) == n) & (df.solver == "sensitivity")].iloc[0] for n in (1, 2))
    (dof1, prep1, gen1), (dof2, prep2, gen2) = (_observed(run_dir, r.estimate_path)
                                                for r in (one, two))
    assert prep2 > prep1 > 0 and gen1 == gen2 > 0  # two extractions against one; one render


VIEWS_TRACKS = ("cube_views_video", "bunny_views_video", "damped_views_video")


@pytest.mark.parametrize("name", ["standard", "standard_val"])
def test_the_standard_views_tracks_film_each_instance_with_a_ring_of_four(name):
    from vvtbench.bench.suite import load_suite

    tracks = {t.name: t for t in load_suite(name).tracks}
    for track in (tracks[n] for n in VIEWS_TRACKS):
        # the damped track also extracts its videos with the old peak picker (paired on the board)
        assert track.observations == (["extracted", "extracted@picker"]
                                      if track.name == "damped_views_video" else ["extracted"])
        assert "learned" not in track.solvers
        assert [v.inference["views"] for v in track.variations] == [1, 2, 3, 4]
        assert {v.scene_overrides["camera.rig.views"] for v in track.variations} == {4}
        split = "val" if name == "standard_val" else "test"
        assert all(f":{split}:" in g[0] for g in track.scenes if g[0].startswith("family:"))
    damped = tracks["damped_views_video"]
    if name == "standard":
        assert all(g[0].startswith("jello_cube_damped_") and len(g) == 1 for g in damped.scenes)
    else:
        pairs = {tuple(map(tuple, v.scene_overrides["damping.pairs"]))
                 for v in damped.variations}
        assert pairs == {((12.5, 0.01749), (15.5, 0.01999))}


@pytest.mark.parametrize("name", ["standard", "standard_val"])
def test_a_views_track_renders_once_extracts_each_view_once_and_nests_the_views(name):
    """One generate task (4 views) per instance, one extract task per view, and the N-view
    observation joins the first N of those extractions: the cost is linear in the views."""
    import dataclasses

    from vvtbench.bench import build_graph
    from vvtbench.bench.suite import load_suite

    suite = load_suite(name)
    track = next(t for t in suite.tracks if t.name == "damped_views_video")
    one = dataclasses.replace(suite, tracks=[dataclasses.replace(
        track, scenes=track.scenes[:1], observations=["extracted"])])
    tasks, _ = build_graph(one, ["homogeneous"], until="observe")
    by_stage = {s: [t for t in tasks.values() if t.stage == s]
                for s in ("generate", "extract", "observe")}
    (gen,), extracts, observes = by_stage["generate"], by_stage["extract"], by_stage["observe"]
    scene = gen.payload["scene"]
    assert gen.payload["video"] and scene["camera"]["rig"]["views"] == 4
    assert scene["damping"]["pairs"] == [[12.5, 0.01749], [15.5, 0.01999]]
    view_of = {t.key: t.payload.get("view", 0) for t in extracts}  # view 0: the one-view key
    assert sorted(view_of.values()) == [0, 1, 2, 3]
    assert all(t.deps == [gen.key] for t in extracts)
    assert len(observes) == 4
    for t in observes:
        n = t.payload["inference"]["views"]
        assert t.deps[0] == gen.key and [view_of[k] for k in t.deps[1:]] == list(range(n))
    # the peak-picker variant: the same render, its own extraction of each view
    both = dataclasses.replace(one, tracks=[dataclasses.replace(
        one.tracks[0], observations=["extracted", "extracted@picker"])])
    tasks2, _ = build_graph(both, ["homogeneous"], until="observe")
    assert {k for k, t in tasks2.items() if t.stage != "extract" and
            t.payload.get("observation") != "extracted@picker"} == {
        k for k, t in tasks.items() if t.stage != "extract"}
    picker = [t for t in tasks2.values() if t.stage == "extract" and t.key not in tasks]
    assert len(picker) == 4 and all(t.deps == [gen.key] for t in picker)
    assert {t.payload["options"]["identifier"] for t in picker} == {"peaks"}
    assert {t.payload["options"]["identifier"] for t in extracts} == {"auto"}
