"""The observe stage: a sample (or scene, dataset entry, real video) -> (problem, truth).

A sample is self-sufficient (observing it never runs the simulator), the problem holds no
truth, and every source gives the same problem for the same data.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from truth_search import leaves, truth_in  # noqa: E402  (tests/truth_search.py)

from vvtbench.observe import ObserveError, ObserveOptions, RealVideo, Truth, observe
from vvtbench.samples import reader as ds
from vvtbench.samples.generate import generate
from vvtbench.scene.scene import parse_scene
from vvtbench.solving.problem import InverseProblem

SCENE = {
    "name": "tiny_observe",
    "seed": 3,
    "geometry": {"kind": "box", "cells": [4, 4, 4]},
    "material": {"E": 9000.0, "rho": 1270.0, "nu": 0.3, "defects": [
        {"shape": "box", "center": [0.03, 0.02, 0.035], "size": [0.02, 0.02, 0.02],
         "E": 9.0e4, "rho": 2000.0}]},
    "excitation": {"kind": "pluck", "at": [0.05, 0.0, 0.05], "displacement": 0.0006},
    "simulation": {"n_modes": 8, "duration": 0.5, "fps": 400.0},
    "camera": {"resolution": [80, 80], "position": [0.16, -0.13, 0.13],
               "look_at": [0.025, 0.025, 0.022], "fov_y_deg": 30.0},
    "render": {"supersample": 2},
}
OPTS = dict(inference_shape=(3, 3, 3), n_modes=5)


@pytest.fixture(scope="module")
def scene():
    return parse_scene(json.loads(json.dumps(SCENE)), "tiny_observe")


@pytest.fixture(scope="module")
def sample(scene, tmp_path_factory) -> Path:
    return generate(scene, tmp_path_factory.mktemp("s"), progress=False)


@pytest.fixture
def no_simulator(monkeypatch):
    import vvtbench.simulation.simulate

    def refuse(*args, **kwargs):
        raise AssertionError("the simulator ran")

    monkeypatch.setattr(vvtbench.simulation.simulate, "simulate", refuse)


def _same_problem(a: InverseProblem, b: InverseProblem) -> None:
    np.testing.assert_allclose(a.gamma, b.gamma, atol=1e-12)
    np.testing.assert_array_equal(a.eigenvalues, b.eigenvalues)
    np.testing.assert_array_equal(a.visible_nodes, b.visible_nodes)
    assert abs(a.P - b.P).max() < 1e-9 * abs(a.P).max()
    assert a.n_params == b.n_params and a.w0 == b.w0 and a.v0 == b.v0
    assert (a.mode_snr is None) == (b.mode_snr is None)
    if a.mode_snr is not None:
        np.testing.assert_array_equal(a.mode_snr, b.mode_snr)


def test_sample_is_observed_without_the_simulator(sample, scene, no_simulator):
    for obs in ("true", "extracted"):
        problem, truth = observe(sample, observation=obs, **OPTS)
        assert problem.n_modes >= 1 and truth.w.shape == (problem.n_params,)
        assert np.all(np.isfinite(truth.w)) and np.all(np.isfinite(truth.v))


def test_sample_and_scene_give_the_same_problem(sample, scene):
    a, ta = observe(sample, visibility="normals", **OPTS)
    b, tb = observe(scene, visibility="normals", **OPTS)
    _same_problem(a, b)
    np.testing.assert_array_equal(ta.w, tb.w)
    np.testing.assert_allclose(ta.modes_3d, tb.modes_3d, atol=1e-12)
    # the true observation: P applied to the truth's 3-D modes gives the observed modes
    np.testing.assert_allclose((a.P @ ta.modes_3d).T, a.gamma, atol=1e-12)


def test_truth_is_volume_weighted_and_has_both_materials(sample):
    _, truth = observe(sample, **OPTS)
    assert truth.w.min() == pytest.approx(9000.0) and truth.w.max() > 9000.0 * 1.5
    assert truth.v.min() == pytest.approx(1270.0) and truth.v.max() > 1270.0


def test_the_problem_holds_no_truth(sample):
    for obs in ("true", "extracted"):
        problem, truth = observe(sample, observation=obs, **OPTS)
        assert not hasattr(problem, "w_true") and not hasattr(problem, "modes_3d")
        assert truth_in(list(leaves(problem)), truth, ["tiny_observe", str(sample)]) == []
        # the search finds the truth when it is there (it can fail)
        leaky = dataclasses.replace(problem, meta={**problem.meta, "x": truth.w * 1.0,
                                                   "scene": "tiny_observe"})
        assert len(truth_in(list(leaves(leaky)), truth, ["tiny_observe"])) == 2


def test_problem_and_truth_round_trip_without_pickle(sample, tmp_path):
    problem, truth = observe(sample, observation="extracted", **OPTS)
    problem.save(tmp_path)
    truth.save(tmp_path)
    assert not list(tmp_path.glob("*.pkl"))
    p2, t2 = InverseProblem.load(tmp_path), Truth.load(tmp_path)
    _same_problem(problem, p2)
    assert p2.meta == json.loads(json.dumps(problem.meta))
    np.testing.assert_array_equal(p2.model.fixed_nodes, problem.model.fixed_nodes)
    for f in ("w", "v", "modes_3d", "eigenvalues", "matched", "extraction_mac"):
        np.testing.assert_array_equal(getattr(t2, f), getattr(truth, f))


def test_extracted_modes_are_paired_with_true_ones(sample):
    problem, truth = observe(sample, observation="extracted", **OPTS)
    assert problem.meta["observation"] == "extracted"
    assert 1 <= problem.n_modes <= 5
    assert truth.modes_3d.shape == (problem.model.n_free, problem.n_modes)
    assert len(set(truth.matched.tolist())) == problem.n_modes
    # modes closer than the resolution (1 / 0.5 s) cannot be told apart: a detection is any
    # combination of its cluster, scored against the cluster's span (as the extraction score)
    from vvtbench.scoring.extraction import clusters_by_resolution, subspace_mac

    f_all = np.sqrt(truth.true_eigenvalues) / (2 * np.pi)
    cluster_of = {j: c for c in clusters_by_resolution(f_all, 1 / 0.5) for j in c}
    for i, j in enumerate(truth.matched):
        assert subspace_mac(problem.gamma[i], truth.image_modes[cluster_of[j]]) > 0.5
    assert np.median(truth.extraction_mac) > 0.5
    f_obs, f_true = problem.frequencies_hz, truth.frequencies_hz
    assert np.all(np.abs(f_obs - f_true) < 1 / 0.5)  # within the resolution of a 0.5 s video


def test_extracted_modes_carry_the_snr_their_peaks_were_tested_with(sample):
    """Each extracted mode's ``mode_snr`` is its peak's power over the noise floor, the
    number the extraction's significance test compared with its threshold; true modes carry
    none (noise-free); selecting modes keeps them paired."""
    from vvtbench.modes import extract_modes
    from vvtbench.samples.reader import open_sample

    s = open_sample(sample)
    ms = extract_modes(s.read_frames(), s.fps)
    problem, _ = observe(sample, observation="extracted", modes=[ms], **OPTS)
    snr = problem.mode_snr
    assert snr is not None and snr.shape == (problem.n_modes,)
    tested = np.asarray(ms.metadata["floor_ratio"])  # of every significant peak
    assert np.all(snr > ms.metadata["noise_floor"]["factor"])
    for x in snr:
        assert np.min(np.abs(tested / x - 1)) < 1e-9
    assert observe(sample, **OPTS)[0].mode_snr is None
    np.testing.assert_array_equal(problem.select_modes([0]).mode_snr, snr[:1])
    with pytest.raises(ValueError, match="mode_snr"):
        InverseProblem(model=problem.model, gamma=problem.gamma,
                       eigenvalues=problem.eigenvalues, P=problem.P,
                       visible_nodes=problem.visible_nodes, mode_snr=snr[:-1] if
                       len(snr) > 1 else np.ones(2))


def test_selecting_modes_keeps_problem_and_truth_paired(sample):
    problem, truth = observe(sample, **OPTS)
    p3, t3 = problem.select_modes(3), truth.select_modes(3)
    np.testing.assert_allclose((p3.P @ t3.modes_3d).T, p3.gamma, atol=1e-12)


def test_geometry_scale_and_visibility(sample):
    a, _ = observe(sample, visibility="normals", **OPTS)
    b, _ = observe(sample, visibility="normals", geometry_scale=1.3, **OPTS)
    assert b.mesh.points[:, 0].max() == pytest.approx(1.3 * a.mesh.points[:, 0].max())
    np.testing.assert_allclose(b.gamma, a.gamma, atol=1e-10)  # the same pixels
    d, _ = observe(sample, visibility="depth", **OPTS)
    assert set(d.visible_nodes) <= set(a.visible_nodes)
    assert len(d.visible_nodes) >= 0.9 * len(a.visible_nodes)  # a convex cube


@pytest.mark.parametrize("bad, key", [
    ({"observation": "video"}, "observation"), ({"n_modes": 0}, "n_modes"),
    ({"inference_shape": (8, 0, 8)}, "inference_shape"), ({"geometry_scale": -1}, "geometry"),
    ({"geometry_scale": float("nan")}, "geometry"), ({"nu": 0.5}, "nu"),
    ({"visibility": "xray"}, "visibility"), ({"inference_order": 3}, "inference_order"),
    ({"bogus": 1}, "bogus"),
])
def test_bad_options_are_one_line_errors(bad, key):
    with pytest.raises(ObserveError, match=key) as info:
        ObserveOptions.from_mapping(bad)
    assert "\n" not in str(info.value)


def test_too_many_modes_is_an_error(sample):
    with pytest.raises(ObserveError, match="n_modes"):
        observe(sample, inference_shape=(3, 3, 3), n_modes=50)


def test_real_video_has_no_truth(sample):
    from vvtbench.fem.mesh import box_mesh
    from vvtbench.modes import extract_modes

    s = ds.open_sample(sample)
    size = tuple(float(v) for v in s.scene.geometry.size)
    mesh = box_mesh((3, 3, 3), size, 1)
    modes = extract_modes(s.video_path, s.fps)
    real = RealVideo(modes=[modes], mesh=mesh, camera=s.camera,
                     fixed_nodes=mesh.node_sets["bottom"], nu=0.3, w0=9000.0, v0=1270.0)
    problem, truth = observe(real, observation="extracted", n_modes=4)
    assert truth is None and problem.n_modes >= 1
    ref, _ = observe(sample, observation="extracted", modes=[modes], visibility="normals",
                     inference_shape=(3, 3, 3), n_modes=4)
    np.testing.assert_array_equal(np.sort(problem.frequencies_hz),
                                  np.sort(ref.frequencies_hz))


def test_voxel_truth_on_a_grid_finer_than_the_mesh(sample):
    # 8^3 voxels over a 4^3 mesh: no voxel inside the body is empty, means stay in range
    problem, truth = observe(sample, inference_shape=(8, 8, 8), n_modes=3)
    assert problem.n_params == 512
    for f, lo, hi in ((truth.w, 9000.0, 9.0e4), (truth.v, 1270.0, 2000.0)):
        assert np.all(np.isfinite(f)) and f.min() >= lo * (1 - 1e-12) and f.max() <= hi * 1.000001


@pytest.mark.parametrize("fmt", ["zarr", "hdf5"])
def test_exported_dataset_entry_is_observed_like_its_sample(sample, tmp_path, fmt, monkeypatch):
    from vvtbench.datasets.export import pack
    from vvtbench.datasets.packed import open_dataset

    out = pack([sample], tmp_path / ("d.zarr" if fmt == "zarr" else "d.h5"), fmt)
    ref, tref = observe(sample, **OPTS)
    import vvtbench.simulation.simulate

    monkeypatch.setattr(vvtbench.simulation.simulate, "simulate", lambda *a, **k: 1 / 0)
    with open_dataset(out) as ds_:
        entry = ds_[ds_.names[0]]
        problem, truth = observe(entry, **OPTS)
        _same_problem(problem, ref)
        np.testing.assert_array_equal(truth.w, tref.w)
        ext, _ = observe(entry, observation="extracted", **OPTS)  # from the packed video
        assert ext.n_modes >= 1


@pytest.fixture(scope="module")
def modes_only(scene, tmp_path_factory) -> Path:
    return generate(scene, tmp_path_factory.mktemp("m"), progress=False, video=False)


def test_modes_only_sample(modes_only, sample, no_simulator):
    s = ds.open_sample(modes_only)
    assert not s.has_video
    problem, truth = observe(modes_only, **OPTS)
    ref, tref = observe(sample, **OPTS)
    _same_problem(problem, ref)
    np.testing.assert_array_equal(truth.w, tref.w)
    with pytest.raises(ObserveError, match="video"):
        observe(modes_only, observation="extracted", **OPTS)


def test_a_free_bodys_rigid_body_modes_are_left_out_and_said_so():
    from vvtbench.scene.scene import load_scene, parse_scene

    data = load_scene("jello_cube_homogeneous").to_toml_dict()
    data.setdefault("boundary", {})["fixed"] = ["none"]
    data["simulation"]["n_modes"] = 12
    problem, truth = observe(parse_scene(data, "free"), n_modes=4, inference_shape=(3, 3, 3))
    assert problem.meta["rigid_body_modes_left_out"] == 6
    assert problem.frequencies_hz.min() > 1.0 and truth.eigenvalues.min() > 0
    clamped, _ = observe("jello_cube_homogeneous", n_modes=4, inference_shape=(3, 3, 3))
    assert clamped.meta["rigid_body_modes_left_out"] == 0
