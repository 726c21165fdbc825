"""The learning workflow: instances by split from generated samples, the learned baseline."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from vvtbench.datasets.instances import instances, iter_instances
from vvtbench.samples.generate import generate
from vvtbench.scene.scene import parse_scene
from vvtbench.scoring.metrics import normalized_correlation


def _scene(name: str, rng) -> dict:
    c = rng.uniform(0.012, 0.038, 3)
    return {
        "name": name, "seed": 1,
        "geometry": {"kind": "box", "cells": [5, 5, 5]},
        "material": {"E": 9000.0, "rho": 1270.0, "nu": 0.3, "defects": [
            {"shape": "box", "center": c.tolist(), "size": [0.02, 0.02, 0.02],
             "E": 90000.0, "rho": 1270.0}]},
        "simulation": {"n_modes": 10},
        "camera": {"resolution": [64, 64]},
    }


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("fam")
    rng = np.random.default_rng(4)
    for split, n in (("train", 6), ("test", 2)):
        for i in range(n):
            name = f"tinyfam-{split}-{i:05d}"
            scene = parse_scene(_scene(name, rng), name)
            path = generate(scene, root, progress=False, video=False)
            (path.parent / f"{name}.family.json").write_text(json.dumps({"split": split}))
    return root


def test_instances_by_split_and_no_simulation(data, monkeypatch):
    import vvtbench.simulation.simulate

    monkeypatch.setattr(vvtbench.simulation.simulate, "simulate", lambda *a, **k: 1 / 0)
    names = [n for n, _ in instances(data, "train")]
    assert names == [f"tinyfam-train-{i:05d}" for i in range(6)]
    assert [n for n, _ in instances(data, "test")] == [f"tinyfam-test-{i:05d}" for i in range(2)]
    assert not list(instances(data, "val"))
    pairs = list(iter_instances(data, "test", n_modes=8, inference_shape=(4, 4, 4)))
    assert len(pairs) == 2 and pairs[0][1].w.shape == (64,)
    with pytest.raises(ValueError, match="split"):
        list(instances(data, "training"))


def test_learned_trained_on_train_beats_the_floor_on_held_out_instances(data, tmp_path):
    from solvers.learned import LearnedConfig, LearnedSolver, fit, save_weights

    opts = dict(n_modes=8, inference_shape=(4, 4, 4))
    weights = fit(iter_instances(data, "train", **opts))
    assert weights["n_instances"] == weights["n_used"] == 6 and weights["members"] == 3
    path = save_weights(tmp_path / "w.npz", weights, {"family": "tinyfam", "split": "train",
                                                     "indices": [0, 5]})
    solver = LearnedSolver(LearnedConfig(weights=str(path)))
    ncs = []
    for problem, truth in iter_instances(data, "test", **opts):
        est = solver.solve(problem)
        assert est.w.mean() == pytest.approx(problem.w_mean)
        assert np.all(est.w > 0) and np.all(est.v > 0)
        ncs.append(normalized_correlation(est.w, truth.w))
    assert min(ncs) > 0.3  # a stiff block located on unseen instances; the floor scores 0
    assert est.extra["trained_on"] == "tinyfam/train"


def test_linearized_eigenvalue_shifts_match_exact_eigenvalues(data):
    """d log(mu_c) / d theta_e of the Ritz modes against a dense generalized eigensolve of
    the perturbed stiffness (scipy's LAPACK), for a small random contrast."""
    import scipy.linalg as sla

    from vvtbench.learning.modal_features import reference_basis, ritz_modes, voxel_couplings

    problem, _ = next(iter_instances(data, "test", n_modes=8, inference_shape=(4, 4, 4)))
    model = problem.model
    basis = reference_basis([problem], n_modes=12)
    mu, psi = ritz_modes(problem, basis)
    theta = 1e-5 * np.random.default_rng(0).standard_normal(problem.n_params)
    cols = np.arange(8)
    G = voxel_couplings(problem, psi, cols)
    predicted = G[cols, cols, :] @ theta                 # d mu_c, first order
    M = model.M(1.0).toarray()
    exact = sla.eigh(model.K(1.0 + theta).toarray(), M, eigvals_only=True)[:9]
    exact0 = sla.eigh(model.K(1.0).toarray(), M, eigvals_only=True)[:9]
    assert mu[:9] == pytest.approx(exact0, rel=1e-8)
    # a repeated eigenvalue splits by its cluster's own perturbation: compare cluster sums
    edges = [0, *(np.flatnonzero(np.diff(exact0) > 1e-6 * exact0[1:]) + 1)]
    clusters = [(a, b) for a, b in zip(edges, edges[1:], strict=False) if b <= 8]
    assert clusters
    for a, b in clusters:
        shift = (exact - exact0)[a:b].sum()
        assert predicted[a:b].sum() == pytest.approx(shift, rel=1e-3), (a, b)
    assert np.abs(exact - exact0)[:8].max() > 1e-7 * exact0[7]  # far above round-off


def test_pairing_drops_a_shape_it_cannot_place(data):
    """Observed modes made of the instance's own homogeneous modes, a gappy subset as an
    extraction gives, pair with them one to one; a noise shape (MAC ~ 0) is dropped by the
    MAC gate and kept (mispaired) without it."""
    import dataclasses

    from vvtbench.learning.modal_features import pair_observed, reference_basis, ritz_modes

    problem, _ = next(iter_instances(data, "test", n_modes=8, inference_shape=(4, 4, 4)))
    mu, psi = ritz_modes(problem, reference_basis([problem], n_modes=12))
    order = np.array([0, 2, 4, 6, 7, 9, 10, 11])          # gappy, as an extraction is
    gamma = np.asarray(problem.P @ psi[:, order]).T
    lam = 3.0 * mu[order]                                 # a common density scale
    gamma[3] = np.random.default_rng(1).standard_normal(gamma.shape[1])
    noisy = dataclasses.replace(problem, gamma=gamma, eigenvalues=lam)
    rows, cols, _, log_v = pair_observed(noisy, mu, psi, 12, mac_min=0.5)
    assert rows.tolist() == [0, 1, 2, 4, 5, 6, 7] and cols.tolist() == order[rows].tolist()
    assert log_v == pytest.approx(np.log(problem.w_mean / 3.0))
    rows, cols, _, _ = pair_observed(noisy, mu, psi, 12)
    assert rows.tolist() == list(range(8))


def test_weights_of_another_mesh_are_refused_in_one_error(data, tmp_path):
    from solvers.learned import LearnedConfig, LearnedSolver, fit, save_weights

    opts = dict(n_modes=8, inference_shape=(4, 4, 4))
    weights = fit(iter_instances(data, "train", **opts), members=1, epochs=1)
    weights["basis"] = weights["basis"][:-3]
    path = save_weights(tmp_path / "w.npz", weights, {"family": "tinyfam", "split": "train"})
    problem, _ = next(iter_instances(data, "test", **opts))
    with pytest.raises(ValueError, match="free DOFs"):
        LearnedSolver(LearnedConfig(weights=str(path))).solve(problem)


def test_a_family_of_two_meshes_trains_one_basis_per_mesh(data, tmp_path):
    """Square and circular drums in small: instances on two inference meshes (4 x 4 x 4 and
    3 x 4 x 4 voxels) interleaved in one train split. Each mesh's basis is the one its own
    first instances give; both meshes are solved; a mesh the train split never showed is
    refused in one error."""
    from solvers.learned import (
        LearnedConfig,
        LearnedSolver,
        fit,
        load_weights,
        mesh_key,
        reference_basis,
        save_weights,
    )

    first = list(iter_instances(data, "train", n_modes=8, inference_shape=(4, 4, 4)))
    second = list(iter_instances(data, "train", n_modes=8, inference_shape=(3, 4, 4)))[:3]
    mixed = [first[0], second[0], first[1], second[1], *first[2:], second[2]]
    weights = fit(iter(mixed), members=1, epochs=1)
    keys = weights["mesh_keys"]
    assert keys == [mesh_key(first[0][0]), mesh_key(second[0][0])] and keys[0] != keys[1]
    assert weights["n_instances"] == 9
    assert np.array_equal(weights["basis_0"], reference_basis([p for p, _ in first]))
    assert np.array_equal(weights["basis_1"], reference_basis([p for p, _ in second]))
    path = save_weights(tmp_path / "w.npz", weights, {"family": "tinyfam", "split": "train"})
    assert load_weights(path)[1]["mesh_keys"] == keys
    solver = LearnedSolver(LearnedConfig(weights=str(path)))
    for problem, _ in (first[0], second[0]):
        est = solver.solve(problem)
        assert np.all(np.isfinite(est.w)) and np.all(est.w > 0)
    third, _ = next(iter_instances(data, "test", n_modes=8, inference_shape=(4, 3, 4)))
    with pytest.raises(ValueError, match="none of the 2"):
        solver.solve(third)


def test_shipped_cube_weights_carry_a_complete_training_record():
    from solvers.learned import MODEL, load_weights, weights_path

    arrays, meta = load_weights(weights_path("cube_defects"))
    assert meta["model"] == MODEL
    assert meta["n_instances"] == len(meta["instances"]) >= 200
    if "train_store" in meta:  # trained from a feature store: the store's record of each split
        assert meta["train_store"]["instances"] == meta["n_instances"]
        assert meta["val_store"]["instances"] == len(meta["val_instances"])
        for key in ("train_store", "val_store"):
            assert len(meta[key]["sha256"]) == len(meta[key]["basis_sha256"]) == 64
    else:
        for key in ("train_sha256", "val_sha256"):
            assert len(meta[key]) == 64
    assert meta["val_instances"] and all(n.startswith("cube_defects-val-")
                                         for n in meta["val_instances"])
    # above the linear model's 0.157 on the same val instances (benchmarks/RESULTS.md)
    assert meta["val_nc_w"] > 0.18 and meta["fit_seconds"] > 0 and meta["members"] >= 1
    assert meta["observe"]["n_modes"] == 10  # the release's observation, which test scores
    assert arrays["basis"].shape[0] == 1944
    for i in range(meta["members"]):
        assert arrays[f"m{i}_W0"].shape[0] == arrays[f"m{i}_x_mean"].shape[0]
        assert all(a.dtype != object for a in arrays.values())


@pytest.mark.parametrize("family", ["cube_defects", "bunny_defects", "drum_defects"])
def test_shipped_weights_saw_only_their_familys_train_split(family):
    """The `standard` suite scores `learned` with these files: each must name its family's
    current file (sha256), the train split and train instances only."""
    import hashlib

    from solvers.learned import load_weights, weights_path
    from vvtbench.scene.families import load_family

    _, meta = load_weights(weights_path(family))
    fam = load_family(family)
    assert meta["family"] == family and meta["split"] == "train"
    assert meta["family_sha256"] == hashlib.sha256(Path(fam.source).read_bytes()).hexdigest()
    assert meta["instances"] and all(n.startswith(f"{family}-train-") for n in meta["instances"])
    lo, hi = meta["indices"]
    assert len(meta["instances"]) == hi - lo + 1
    if family != "cube_defects":  # the 3.0 model on its meshes, val scored where NC is defined
        assert meta["model"] == "modal-step-mlp" and meta["n_val_scored"] <= meta["n_val"]
        assert len(meta["mesh_keys"]) == (2 if family == "drum_defects" else 1)


@pytest.mark.parametrize("content", [b"garbage", b"PK\x03\x04truncated"])
def test_a_file_that_is_not_weights_is_named_in_one_error(tmp_path, content):
    from solvers.learned import load_weights

    bad = tmp_path / "w.npz"
    bad.write_bytes(content)
    with pytest.raises(ValueError, match="not a learned-weights file"):
        load_weights(bad)


def test_replaced_weights_are_solved_again_not_served_from_the_cache(tmp_path):
    """The solve task's key carries the weights file's sha256, not only its name."""
    import shutil

    from solvers.learned import weights_path
    from vvtbench.bench import build_graph, parse_suite

    path = tmp_path / "w.npz"
    shutil.copy(weights_path("cube_defects"), path)
    suite = parse_suite({"name": "t", "solvers": ["learned"], "seeds": [0],
                         "tracks": [{"name": "a", "scenes": ["jello_cube_homogeneous"],
                                     "solver": {"learned": {"weights": str(path)}}}]})

    def solve_keys():
        tasks, _ = build_graph(suite, suite.solvers)
        return {k for k, t in tasks.items() if t.stage == "solve"}

    first = solve_keys()
    assert len(first) == 1 and solve_keys() == first
    shutil.copy(weights_path("drum_defects"), path)  # same name, other content
    second = solve_keys()
    assert len(second) == 1 and second != first


def test_network_fits_a_nonlinear_function_a_linear_map_cannot():
    """y = |x0| + x1^2 - x0 x2 (analytic) from samples: R^2 of the network on held-out points
    against least squares on the same inputs."""
    from vvtbench.learning.mlp import fit_mlp, mlp_predict

    rng = np.random.default_rng(1)
    X = rng.uniform(-1, 1, (6000, 3))
    y = np.abs(X[:, 0]) + X[:, 1] ** 2 - X[:, 0] * X[:, 2]
    Xt = rng.uniform(-1, 1, (2000, 3))
    yt = np.abs(Xt[:, 0]) + Xt[:, 1] ** 2 - Xt[:, 0] * Xt[:, 2]
    params = fit_mlp(X, y, hidden=(32, 16), epochs=60, batch=256, lr=3e-3, seed=0)

    def r2(pred):
        return 1 - np.mean((pred - yt) ** 2) / np.var(yt)

    A = np.column_stack([X, np.ones(len(X))])
    linear = np.column_stack([Xt, np.ones(len(Xt))]) @ np.linalg.lstsq(A, y, rcond=None)[0]
    assert r2(linear) < 0.1
    assert r2(mlp_predict(params, Xt)) > 0.95
    again = fit_mlp(X, y, hidden=(32, 16), epochs=60, batch=256, lr=3e-3, seed=0)
    assert all(np.array_equal(params[k], again[k]) for k in params)  # seeded


def test_neighbourhood_means_match_scipys_nan_mean_filter():
    """Means over the active voxels of each cube, against scipy's generic_filter of nanmean
    with voids and the outside as NaN."""
    from scipy.ndimage import generic_filter

    from vvtbench.fem.voxels import VoxelGrid, VoxelMap
    from vvtbench.learning.modal_features import neighbourhood_means

    rng = np.random.default_rng(2)
    shape = (5, 4, 6)
    active = np.flatnonzero(rng.uniform(size=int(np.prod(shape))) > 0.3)
    grid = VoxelGrid(shape=shape, origin=(0.0, 0.0, 0.0), size=(1.0, 1.0, 1.0))
    vmap = VoxelMap(grid, active, active, np.arange(len(active)))
    values = rng.standard_normal((len(active), 2))
    got = neighbourhood_means(vmap, values, sizes=(3, 5))
    for j in range(2):
        full = np.full(int(np.prod(shape)), np.nan)
        full[active] = values[:, j]
        for k, size in enumerate((3, 5)):
            ref = generic_filter(full.reshape(shape), np.nanmean, size=size, mode="constant",
                                 cval=np.nan).ravel()[active]
            assert got[:, k * 2 + j] == pytest.approx(ref, rel=1e-10, abs=1e-12)


def test_the_val_score_leaves_out_a_uniform_truth_where_nc_is_undefined():
    from solvers import learned

    rng = np.random.default_rng(7)
    truth = np.exp(rng.standard_normal(64))
    weights = {"model": learned.RIDGE_MODEL, "mean": np.zeros(1), "std": np.ones(1),
               "coef_w": np.ones(1)}
    X = np.log(truth)[:, None]  # predicts the truth exactly: NC 1
    flat = {"X": X, "w": np.full(64, 3.0)}
    assert learned.mean_nc(weights, [{"X": X, "w": truth}, flat]) == pytest.approx(1.0)
    assert learned.mean_nc(weights, [flat]) is None
    record: dict = dict(weights)
    learned._record_val(record, [{"X": X, "w": truth}, flat, flat])
    assert (record["n_val"], record["n_val_scored"]) == (3, 1)
    assert record["val_nc_w"] == pytest.approx(1.0)


def test_estimate_keeps_the_predicted_fields_nc_and_is_positive():
    from solvers.learned import field_to_w

    rng = np.random.default_rng(3)
    field = rng.standard_normal(512) ** 3
    truth = np.exp(rng.standard_normal(512))
    w = field_to_w(field, 9000.0)
    assert np.all(w > 0) and w.mean() == pytest.approx(9000.0)
    assert normalized_correlation(w, truth) == pytest.approx(
        normalized_correlation(field, truth), abs=1e-12)
    assert np.all(field_to_w(np.zeros(512), 9000.0) == 9000.0)


# --------------------------------------------------------------------------- feature store
TRAIN_OPTS = ["--n", "6", "--val", "2", "--modes", "8", "--grid", "4", "4", "4",
              "--set", "members=1", "--set", "epochs=2"]


def _tiny_cube_family(folder: Path) -> Path:
    """The shipped cube family, made small: 5^3 cells, 12 modes, 96^2 px."""
    from vvtbench.scene.scene import SCENES_DIR

    text = (SCENES_DIR / "families" / "cube_defects.toml").read_text()
    text = text.replace('name = "cube_defects"', 'name = "tinycube"')
    text += ('"simulation.n_modes" = { choice = [12] }\n'
             '"geometry.cells" = { choice = [[5, 5, 5]] }\n'
             '"camera.resolution" = { choice = [[96, 96]] }\n')
    path = folder / "tinycube.toml"
    path.write_text(text)
    return path


def _tree(folder: Path) -> dict:
    return {str(p.relative_to(folder)): p.read_bytes() if p.is_file() else None
            for p in sorted(folder.rglob("*"))}


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """The same 6 train and 2 val instances trained on kept instances and through a feature
    store with --drop-instances (default store folder, in a working folder of its own)."""
    import os

    from vvtbench.cli import main

    root = tmp_path_factory.mktemp("store")
    family = _tiny_cube_family(root)
    work = root / "work"
    (work / "mine").mkdir(parents=True)
    (work / "mine" / "notes.txt").write_text("a user's file")
    before = _tree(work)
    here = os.getcwd()
    os.chdir(work)
    try:
        assert main(["train", "learned", str(family), *TRAIN_OPTS, "--drop-instances",
                     "-o", str(root / "dropped.npz")]) == 0
    finally:
        os.chdir(here)
    after = _tree(work)
    assert main(["train", "learned", str(family), *TRAIN_OPTS, "--data",
                 str(root / "kept" / "train"), "-o", str(root / "kept.npz")]) == 0
    return {"root": root, "family": family, "store": work / "data" / "tinycube" /
            "train-features", "before": before, "after": after}


def test_a_store_built_dropping_instances_gives_the_weights_of_the_kept_instances(trained):
    import hashlib

    from solvers.learned import load_weights
    from vvtbench.learning.feature_store import FeatureStore

    kept, kept_meta = load_weights(trained["root"] / "kept.npz")
    dropped, meta = load_weights(trained["root"] / "dropped.npz")
    assert meta["instances"] == kept_meta["instances"] == [
        f"tinycube-train-{i:05d}" for i in range(6)]
    assert meta["val_instances"] == kept_meta["val_instances"]
    store = FeatureStore.open(trained["store"])
    for entry in store.entries("train") + store.entries("val"):  # the same instances
        split = entry.name.split("-")[1]
        manifest = trained["root"] / "kept" / split / entry.name / "manifest.json"
        assert entry.manifest_sha256 == hashlib.sha256(manifest.read_bytes()).hexdigest()
    assert np.array_equal(dropped["basis"], kept["basis"])
    assert set(dropped) == set(kept)
    for key in kept:
        assert dropped[key] == pytest.approx(kept[key], rel=1e-9, abs=1e-12), key
    assert meta["val_nc_w"] == pytest.approx(kept_meta["val_nc_w"], abs=1e-5)
    record = meta["train_store"]
    assert record["instances"] == 6 and len(record["sha256"]) == 64
    assert record["path"] == str(trained["store"].resolve())
    assert meta["val_store"]["instances"] == 2 and meta["fit_seconds"] > 0


def test_dropped_instances_are_gone_and_nothing_else_was_touched(trained):
    from vvtbench.learning.feature_store import SCRATCH, FeatureStore

    store = trained["store"]
    assert not (store / SCRATCH).exists()
    added = set(trained["after"]) - set(trained["before"])
    assert all(name in ("data", "data/tinycube") or name.startswith(
        "data/tinycube/train-features") for name in added), sorted(added)
    assert all(trained["after"][k] == v for k, v in trained["before"].items())
    assert sorted(p.name for p in (store / "shards").iterdir()) == [
        "train-000000-000005.npz", "val-000000-000001.npz"]
    opened = FeatureStore.open(store)
    assert [e.name for e in opened.entries("train")] == [
        f"tinycube-train-{i:05d}" for i in range(6)]
    arrays = dict(opened.iter_arrays(opened.entries("val"), ("X", "w")))
    assert all(a["X"].shape == (64, 42) and a["w"].shape == (64,) for a in arrays.values())


def test_only_the_stores_own_scratch_instances_are_deleted(tmp_path):
    from vvtbench.learning.feature_store import (
        SCRATCH,
        SCRATCH_MARK,
        FeatureStoreError,
        drop_instance,
    )

    user = tmp_path / SCRATCH / "train" / "tinycube-train-00003"
    user.mkdir(parents=True)
    (user / "manifest.json").write_text("{}")
    with pytest.raises(FeatureStoreError, match="not an instance this store generated"):
        drop_instance(tmp_path, "train", "tinycube-train-00003")  # no scratch mark
    (tmp_path / SCRATCH / SCRATCH_MARK).touch()
    for name in ("../../x", "../tinycube-train-00003", "tinycube-val-00003", "notes"):
        with pytest.raises(FeatureStoreError):
            drop_instance(tmp_path, "train", name)
    assert user.is_dir()
    drop_instance(tmp_path, "train", "tinycube-train-00003")
    assert not user.exists()


@pytest.mark.parametrize("change", ["observe", "basis", "data", "not a store"])
def test_a_store_of_other_options_or_basis_is_refused_in_one_line(trained, tmp_path, change,
                                                                  capsys):
    import shutil

    from vvtbench.cli import main
    from vvtbench.io.files import write_npz

    store = tmp_path / "store"
    shutil.copytree(trained["store"], store)
    opts = list(TRAIN_OPTS)
    if change == "observe":
        opts[opts.index("--modes") + 1] = "6"
    elif change == "basis":
        with np.load(store / "basis.npz") as z:
            basis = z["basis"]
        write_npz(store / "basis.npz", {"basis": basis[:, ::-1].copy()})
    elif change == "data":
        opts += ["--data", str(tmp_path / "train")]
    else:
        shutil.rmtree(store)
        store.mkdir()
        (store / "results.csv").write_text("a user's file")
    before = _tree(store)
    capsys.readouterr()
    assert main(["train", "learned", str(trained["family"]), *opts, "--drop-instances",
                 "--features", str(store), "-o", str(tmp_path / "w.npz")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("error: ")
    assert {"observe": "key 'observe'", "basis": "basis", "data": "--data",
            "not a store": "not a feature store"}[change] in err
    assert _tree(store) == before and not (tmp_path / "w.npz").exists()
    assert not (tmp_path / "train").exists()


def test_a_killed_store_build_resumes_without_generating_finished_instances(tmp_path,
                                                                           monkeypatch):
    import solvers.learned as learned
    from vvtbench.learning import feature_store as fs

    spec = fs.StoreSpec(solver="learned", module="solvers.learned",
                        solver_version=learned.LearnedSolver.version, model=learned.MODEL,
                        family=str(_tiny_cube_family(tmp_path)), family_name="tinycube",
                        observe={"n_modes": 8, "inference_shape": (4, 4, 4),
                                 "visibility": "depth"})
    root = tmp_path / "store"
    monkeypatch.setattr(learned, "N_REFERENCE", 2)  # the basis from instances 0 and 1
    generated = []
    real_generate, real_features = fs._generate, learned.instance_features
    monkeypatch.setattr(fs, "_generate", lambda job: generated.append(
        (job["name"], (Path(job["out"]) / job["name"] / "manifest.json").is_file()))
        or real_generate(job))
    calls = []

    def killed_at_the_third(problem, truth, basis):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt  # the run is killed while featurizing instance 2
        return real_features(problem, truth, basis)

    monkeypatch.setattr(learned, "instance_features", killed_at_the_third)
    with pytest.raises(KeyboardInterrupt):
        fs.build_store(root, spec, {"train": (0, 4)}, shard_instances=2)
    store = fs.FeatureStore.open(root)
    assert [e.index for e in store.entries("train")] == [0, 1]  # complete shards only
    assert (root / fs.SCRATCH / "train" / "tinycube-train-00002" / "manifest.json").is_file()
    (root / fs.SHARDS / ".train-000002-000003.123-abcd.tmp.npz").write_bytes(b"half")
    generated.clear()
    monkeypatch.setattr(learned, "instance_features", real_features)
    store = fs.build_store(root, spec, {"train": (0, 4)}, shard_instances=2)
    # instances 0 and 1 are not generated again; 2 was complete in the scratch folder
    assert generated == [("tinycube-train-00002", True), ("tinycube-train-00003", False)]
    assert [e.index for e in store.entries("train")] == [0, 1, 2, 3]
    assert sorted(p.name for p in (root / fs.SHARDS).iterdir()) == [
        "train-000000-000001.npz", "train-000002-000003.npz"]
    assert not (root / fs.SCRATCH).exists()
    first = store.digest(store.entries("train"))
    again = fs.build_store(root, spec, {"train": (0, 4)}, shard_instances=2)
    assert again.digest(again.entries("train")) == first and len(generated) == 2


@pytest.mark.parametrize("where", ["reference", "later"])
def test_a_store_refuses_a_family_of_several_meshes_in_one_line(tmp_path, monkeypatch, where):
    """A store keeps one basis: a second mesh among the reference instances, or in a later
    instance, stops the build with an error naming the way out (mesh keys stubbed: the tiny
    family has one mesh)."""
    import solvers.learned as learned
    from vvtbench.learning import feature_store as fs

    spec = fs.StoreSpec(solver="learned", module="solvers.learned",
                        solver_version=learned.LearnedSolver.version, model=learned.MODEL,
                        family=str(_tiny_cube_family(tmp_path)), family_name="tinycube",
                        observe={"n_modes": 8, "inference_shape": (4, 4, 4),
                                 "visibility": "depth"})
    monkeypatch.setattr(learned, "N_REFERENCE", 2)
    keys = iter(["square", "circle"] if where == "reference" else ["square"] * 4 + ["circle"])
    monkeypatch.setattr(learned, "mesh_key", lambda problem: next(keys))
    root = tmp_path / "store"
    with pytest.raises(fs.FeatureStoreError, match="without --drop-instances") as error:
        fs.build_store(root, spec, {"train": (0, 3)}, shard_instances=1)
    assert "\n" not in str(error.value)
    if where == "reference":  # the refusal is final: the new store folder is gone
        assert not root.exists()
    else:  # instances 0 and 1 (the same mesh) are kept; 2 is not
        assert [e.index for e in fs.FeatureStore.open(root).entries("train")] == [0, 1]


def test_training_cost_is_bounded_by_a_number_of_steps():
    from solvers.learned import BATCH, MAX_STEPS, bounded_steps
    from vvtbench.learning.mlp import fit_mlp

    assert bounded_steps(500 * 512) == 15 * 125  # the shipped model's data: 15 full epochs
    assert bounded_steps(20000 * 381) == MAX_STEPS  # 3 721 steps an epoch: cut at 10 000
    assert bounded_steps(20000 * 512, 15, 100) == 100 and bounded_steps(10, 3, 100) == 3
    for n in (1000, 5000, 20000, 80000, 200000):
        assert bounded_steps(n * 512) == min(15 * -(-n * 512 // BATCH), MAX_STEPS)
    # `steps` counts Adam steps exactly, across passes; `epochs` alone is unchanged
    rng = np.random.default_rng(0)
    X, y = rng.standard_normal((50, 3)), rng.standard_normal(50)
    two = fit_mlp(X, y, hidden=(4,), epochs=2, batch=10, seed=1)
    same = fit_mlp(X, y, hidden=(4,), batch=10, seed=1, steps=10)
    assert all(np.array_equal(two[k], same[k]) for k in two)
    longer = fit_mlp(X, y, hidden=(4,), batch=10, seed=1, steps=11)
    assert not np.array_equal(two["W0"], longer["W0"])
    with pytest.raises(ValueError, match="steps"):
        fit_mlp(X, y, steps=0)


@pytest.mark.parametrize("key, value", [("n_slots", "40"), ("n_slots", 0), ("n_slots", 2.5),
                                        ("n_slots", True), ("mac_min", float("nan")),
                                        ("mac_min", -0.1), ("mac_min", 1.5), ("mac_min", "0.5")])
def test_a_damaged_pairing_in_the_weights_is_named_in_one_error(tmp_path, key, value):
    from solvers.learned import LearnedConfig, LearnedSolver, load_weights, weights_path

    arrays, meta = load_weights(weights_path("cube_defects"))
    bad = tmp_path / "w.npz"
    np.savez(bad, **arrays, meta_json=np.frombuffer(
        json.dumps({**meta, key: value}).encode(), dtype=np.uint8))
    with pytest.raises(ValueError, match=rf"^{re.escape(str(bad))}: meta key '{key}' is .*allowed"):
        LearnedSolver(LearnedConfig(weights=str(bad))).solve(None)


def test_weights_without_a_pairing_solve_as_before_the_gate():
    from solvers.learned import Pairing

    assert Pairing.of({}) == Pairing(20, 0.0)
    assert Pairing.of({"n_slots": 40, "mac_min": 0.5}) == Pairing(40, 0.5)
