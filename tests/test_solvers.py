"""Inverse problem construction, the shipped solvers and the plug-in interface.

Small cubes keep the whole file fast: simulate 6^3 (or 8^3) hex8, infer on 6^3 voxels.
"""

from __future__ import annotations

import dataclasses
import textwrap

import numpy as np
import pytest

from vvtbench.cli.solve import main_solve
from vvtbench.fem.interpolate import interpolate_nodal
from vvtbench.fem.mesh import box_mesh
from vvtbench.observe import observe
from vvtbench.scene.scene import load_scene
from vvtbench.scoring.metrics import mode_match, normalized_correlation
from vvtbench.simulation.simulate import simulate
from vvtbench.solving.plugins import (
    PluginError,
    list_solvers,
    load_solver,
    parse_overrides,
)
from vvtbench.solving.problem import Estimate


def _scene(name: str, cells, n_modes: int = 30):
    s = load_scene(name)
    return s.model_copy(update={
        "geometry": s.geometry.model_copy(update={"cells": tuple(cells)}),
        "simulation": s.simulation.model_copy(update={"n_modes": n_modes}),
    })


@pytest.fixture(scope="module")
def defect6():
    return simulate(_scene("jello_cube_defect_top", (6, 6, 6)), transient=False)


@pytest.fixture(scope="module")
def defect8():
    return simulate(_scene("jello_cube_defect_top", (8, 8, 8)), transient=False)


@pytest.fixture(scope="module")
def homog8():
    return simulate(_scene("jello_cube_homogeneous", (8, 8, 8)), transient=False)


def _observe(sim, **options):
    return observe(sim, visibility="normals", **options)


@pytest.fixture(scope="module")
def observed6(defect6):
    return _observe(defect6, inference_shape=(6, 6, 6), n_modes=12)


@pytest.fixture(scope="module")
def problem6(observed6):
    return observed6[0]


@pytest.fixture(scope="module")
def truth6(observed6):
    return observed6[1]


# ----------------------------------------------------------------------------- problem


def test_interpolation_reproduces_trilinear_and_quadratic_fields():
    rng = np.random.default_rng(1)
    q = rng.uniform(0, 1, (200, 3)) * [1.0, 2.0, 3.0]

    def trilinear(p):
        return 1 + 2 * p[:, 0] - p[:, 1] + 0.5 * p[:, 2] + p[:, 0] * p[:, 1] * p[:, 2]

    m = box_mesh((3, 4, 5), (1.0, 2.0, 3.0))
    assert np.allclose(interpolate_nodal(m, trilinear(m.points), q), trilinear(q))
    m2 = box_mesh((2, 2, 2), (1.0, 2.0, 3.0), order=2)
    quad = lambda p: p[:, 0] ** 2 - p[:, 1] * p[:, 2] + p[:, 2] ** 2  # noqa: E731
    assert np.allclose(interpolate_nodal(m2, quad(m2.points), q), quad(q))


def test_interpolation_on_tets():
    from scipy.spatial import Delaunay

    from vvtbench.fem.mesh import tets_to_mesh

    rng = np.random.default_rng(3)
    corners = np.stack(np.meshgrid(*[[0.0, 1.0]] * 3, indexing="ij"), -1).reshape(-1, 3)
    g = np.vstack([corners, rng.uniform(0.05, 0.95, (60, 3))])
    tets = Delaunay(g).simplices
    lin = lambda p: 3 * p[:, 0] - p[:, 1] + 2 * p[:, 2] + 1  # noqa: E731
    q = np.random.default_rng(2).uniform(0.01, 0.99, (100, 3))
    for order in (1, 2):
        mesh = tets_to_mesh(g, tets, order=order)
        assert np.allclose(interpolate_nodal(mesh, lin(mesh.points), q), lin(q))


def test_problem_from_simulation(defect8):
    pb, truth = _observe(defect8, inference_shape=(6, 6, 6), n_modes=10)
    k, nv = pb.n_modes, len(pb.visible_nodes)
    assert pb.gamma.shape == (k, 2 * nv) and pb.P.shape == (2 * nv, pb.model.n_free)
    assert np.allclose(np.linalg.norm(pb.gamma, axis=1), 1.0)
    assert np.allclose((pb.P @ truth.modes_3d).T, pb.gamma, atol=1e-12)
    # visible: front (y=0), right (x=max) and top faces, bottom (fixed) excluded
    pts = pb.mesh.points[pb.visible_nodes]
    on = (pts[:, 1] < 1e-9) | (pts[:, 0] > 0.05 - 1e-9) | (pts[:, 2] > 0.05 - 1e-9)
    assert on.all() and (pts[:, 2] > 1e-9).all()
    # truth: volume-weighted average lies between the two materials, both present
    assert truth.w.min() == pytest.approx(9000.0) and truth.w.max() > 1e5
    assert pb.n_params == 216


def test_geometry_scale_keeps_pixels(defect8):
    pb1, _ = _observe(defect8, inference_shape=(6, 6, 6), n_modes=5)
    pb2, _ = _observe(defect8, inference_shape=(6, 6, 6), n_modes=5, geometry_scale=1.3)
    assert pb2.mesh.points[:, 0].max() == pytest.approx(0.065)
    np.testing.assert_allclose(pb2.gamma, pb1.gamma, atol=1e-10)  # same observation


# ----------------------------------------------------------------------------- solvers


def test_oracle_recovers_defect_from_full_field_modes(problem6, truth6):
    est = load_solver("oracle")().solve(problem6, truth6)
    assert normalized_correlation(est.w, truth6.w) >= 0.99
    assert normalized_correlation(est.v, truth6.v) >= 0.99


def test_homogeneous_exact_on_homogeneous(homog8):
    pb, _ = _observe(homog8, inference_shape=(8, 8, 8), n_modes=8)
    est = load_solver("homogeneous")().solve(pb)
    assert est.v == pytest.approx(1270.0, rel=1e-6)


def test_vvt_keeps_homogeneous_cube_homogeneous():
    # the paper's setting: simulated on 10^3 hex8, inferred on 8^3 voxels (mesh mismatch)
    sim = simulate(_scene("jello_cube_homogeneous", (10, 10, 10), 12), transient=False)
    pb, _ = _observe(sim, inference_shape=(8, 8, 8), n_modes=10)
    cls = load_solver("vvt")
    est = cls(cls.Config(max_iter=10)).solve(pb)
    assert est.w.std() / est.w.mean() < 0.01
    assert est.v.std() / est.v.mean() < 0.01
    assert est.v.mean() == pytest.approx(1270.0, rel=0.03)


def test_vvt_homogeneous_from_a_scaled_start(homog8):
    pb, _ = _observe(homog8, inference_shape=(8, 8, 8), n_modes=10)
    cls = load_solver("vvt")
    est = cls(cls.Config(max_iter=10, w0=1.3 * 9000, v0=1.3 * 1270)).solve(pb)
    assert est.w.std() / est.w.mean() < 0.01 and est.v.std() / est.v.mean() < 0.01
    assert est.w.mean() == pytest.approx(9000.0, rel=1e-6)  # the mean anchor
    assert est.v.mean() == pytest.approx(1270.0, rel=1e-3)


def test_vvt_improves_with_more_modes(defect8):
    cls = load_solver("vvt")
    ncs = {}
    for k in (8, 20):
        pb, truth = _observe(defect8, inference_shape=(6, 6, 6), n_modes=k)
        est = cls(cls.Config(max_iter=12)).solve(pb)
        ncs[k] = normalized_correlation(est.w, truth.w)
    assert ncs[20] > ncs[8] + 0.05
    assert ncs[20] > 0.3


def test_vvt_u_update_is_exact_after_the_homogeneous_start(problem6):
    # the N_i pattern must cover heterogeneous K, M (exact cancellations at a uniform start)
    import scipy.sparse as sp
    from sksparse.cholmod import cholesky

    from solvers.vvt import USolver

    model, k = problem6.model, 4
    P = problem6.P / abs(problem6.P).max()
    PtP = (P.T @ P).tocsc()
    rhs = np.asarray(P.T @ problem6.gamma[:k].T)
    lam, y = problem6.eigenvalues[:k], np.linspace(1.0, 2.0, k)
    rng = np.random.default_rng(0)
    for method in ("direct", "auto"):
        us = USolver(model, PtP, 10.0, method=method, rtol=1e-12)
        U = np.zeros((model.n_free, k))
        for w, v in ((9000.0, 1270.0), (9000 * rng.uniform(0.5, 2, problem6.n_params),
                                        1270 * rng.uniform(0.5, 2, problem6.n_params))):
            K, M = model.K(w), model.M(v)
            U = us.solve(K, M, lam, y, rhs, U)
            for i in range(k):
                A = K - lam[i] * M
                ref = cholesky(sp.csc_matrix(y[i] * (A @ A) + 10.0 * PtP))(10.0 * rhs[:, i])
                assert np.linalg.norm(U[:, i] - ref) < 1e-8 * np.linalg.norm(ref)


def test_vvt_u_step_solves_a_system_cholesky_refuses_by_lu(problem6):
    """A u-step system that is not numerically positive definite (met on a bunny: a
    near-singular K - lam M beside a thin P^T P) is solved by LU, as the z-step's are, rather
    than failing the solve."""
    import scipy.sparse as sp
    from sksparse.cholmod import CholmodNotPositiveDefiniteError, cholesky

    from solvers.vvt import USolver

    model = problem6.model
    PtP = (problem6.P.T @ problem6.P).tocsc()
    K, M = model.K(9000.0), model.M(1270.0)
    us = USolver(model, PtP, 10.0, method="direct")
    us._build_pattern(K, M)
    S = sp.csc_matrix(K - 1.01 * problem6.eigenvalues[5] * M)   # indefinite
    with pytest.raises(CholmodNotPositiveDefiniteError):
        cholesky(S)
    b = np.random.default_rng(0).standard_normal(S.shape[0])
    for keep in (True, False):
        x = us._factor(S, keep=keep)(b)
        assert np.linalg.norm(S @ x - b) < 1e-8 * np.linalg.norm(b)


def test_vvt_u_solvers_give_the_same_iterates(problem6):
    cls = load_solver("vvt")
    runs = {m: cls(cls.Config(max_iter=8, tol=0.0, u_solver=m, u_rtol=1e-8)).solve(problem6)
            for m in ("direct", "pcg", "auto")}
    runs["default"] = cls(cls.Config(max_iter=8, tol=0.0)).solve(problem6)
    for m, tol in (("pcg", 1e-6), ("auto", 1e-6), ("default", 1e-4)):
        for a, b in zip(runs[m].history, runs["direct"].history, strict=True):
            assert a["rel_change_w"] == pytest.approx(b["rel_change_w"], abs=tol)
            assert a["rel_change_v"] == pytest.approx(b["rel_change_v"], abs=tol)
    exact = runs["direct"].w
    assert np.linalg.norm(runs["pcg"].w - exact) < 1e-7 * np.linalg.norm(exact)
    assert np.linalg.norm(runs["default"].w - exact) < 1e-4 * np.linalg.norm(exact)


def test_vvt_reruns_repeat_bit_for_bit(problem6):
    # the factor-refresh rule counts PCG steps, not seconds: no dependence on machine load
    cls = load_solver("vvt")
    a, b = (cls(cls.Config(max_iter=10, tol=0.0, group_rtol=0.4)).solve(problem6)
            for _ in range(2))
    assert np.array_equal(a.w, b.w) and np.array_equal(a.v, b.v)
    assert [h["factorizations"] for h in a.history] == [h["factorizations"] for h in b.history]


def test_z_gram_matches_its_definition(problem6):
    # (1/k) sum_i y_i B_i^T B_i, B_i = [G_i, -lam_i H_i], from the model's column matrices
    import scipy.sparse as sp

    from solvers.vvt import ZSystem

    model, k = problem6.model, 5
    rng = np.random.default_rng(1)
    U = rng.standard_normal((model.n_free, k))
    lam, y = problem6.eigenvalues[:k], rng.uniform(0.5, 2.0, k)
    zs = ZSystem(problem6, 1e-10, 1e-7, 1.0, problem6.w_mean)
    ref = sp.csr_matrix((2 * problem6.n_params,) * 2)
    for i in range(k):
        B = sp.hstack([model.stiffness_columns(U[:, i]), -lam[i] * model.mass_columns(U[:, i])])
        ref = ref + y[i] / k * (B.T @ B)
    G = zs.gram(U, lam, y)
    assert abs(G - ref).max() < 1e-12 * abs(ref).max()
    assert abs(zs.gram(U, lam, y, with_reg=True) - ref - zs.reg).max() < 1e-12 * abs(ref).max()


def test_sensitivity_improves_on_the_homogeneous_start(defect6):
    # full-field observation: every non-fixed node of the inference mesh is seen
    from vvtbench.modes.sampling import observation_operator
    from vvtbench.render import Camera

    pb, truth = _observe(defect6, inference_shape=(6, 6, 6), n_modes=12)
    model = pb.model
    visible = np.setdiff1d(np.arange(pb.mesh.n_nodes), model.fixed_nodes)
    P = observation_operator(Camera.from_dict(pb.meta["camera"]), pb.mesh.points, visible,
                             dof_index=model.free_index, n_columns=model.n_free)
    gamma = (P @ truth.modes_3d).T
    pb = dataclasses.replace(pb, P=P, visible_nodes=visible,
                             gamma=gamma / np.linalg.norm(gamma, axis=1, keepdims=True))
    start = load_solver("homogeneous")().solve(pb)
    cls = load_solver("sensitivity")
    est = cls(cls.Config(max_iter=15)).solve(pb)
    nc0 = normalized_correlation(start.w, truth.w)
    assert normalized_correlation(est.w, truth.w) > nc0 + 0.3
    assert normalized_correlation(est.v, truth.v) > 0.3
    assert est.w.mean() == pytest.approx(pb.w_mean, rel=1e-9)  # the mean anchor
    assert est.history[-1]["cost"] < est.history[0]["cost"]


@pytest.mark.parametrize("name", sorted(list_solvers()))
def test_solver_contract(name, problem6, truth6, tmp_path):
    cls = load_solver(name)
    assert isinstance(cls.name, str) and cls.name == name
    assert cls.version and cls.description
    assert dataclasses.is_dataclass(cls.Config)
    for f in dataclasses.fields(cls.Config):
        assert f.metadata.get("help"), f"{name}.Config.{f.name} has no help"
    cfg = cls.Config(max_iter=3) if "max_iter" in {f.name for f in
                                                   dataclasses.fields(cls.Config)} else None
    if getattr(cls, "trainable", False):  # fit on the fixture itself: the contract, not skill
        import importlib

        module = importlib.import_module(cls.__module__)
        path = module.save_weights(tmp_path / "w.npz", module.fit([(problem6, truth6)]),
                                   {"family": "test", "split": "train"})
        cfg = cls.Config(weights=str(path))
    est = (cls(cfg).solve(problem6, truth6) if getattr(cls, "uses_truth", False)
           else cls(cfg).solve(problem6))
    assert isinstance(est, Estimate)
    assert (cls.solve.__doc__ or "").strip(), f"{name}.solve has no docstring"
    assert est.w.shape == est.v.shape == (problem6.n_params,)
    assert np.all(np.isfinite(est.w)) and np.all(np.isfinite(est.v))
    assert np.all(est.w > 0) and np.all(est.v > 0)
    assert est.runtime_s > 0 and est.solver == name and isinstance(est.config, dict)


def test_mode_match_of_the_truth(problem6, truth6):
    mm = mode_match(problem6, truth6.w, truth6.v)
    assert mm["mean_mac"] > 0.999
    assert mm["freq_rel_error"] < 1e-6
    mm2 = mode_match(problem6, 4 * truth6.w, truth6.v)  # w/v scale: f x 2
    assert mm2["freq_rel_error"] == pytest.approx(1.0, rel=1e-5)
    assert mm2["freq_rel_error_scaled"] < 1e-6 and mm2["material_scale"] == pytest.approx(0.25)


def test_mode_match_does_not_depend_on_the_basis_of_a_repeated_mode(problem6):
    from dataclasses import replace

    from vvtbench.fem.modal import Modes, cluster_frequencies, eigenmodes
    from vvtbench.scoring.metrics import REPEATED_RTOL

    w, v = np.ones(problem6.n_params), np.ones(problem6.n_params)  # a cube: repeated pairs
    model = problem6.model
    modes = eigenmodes(model.K(w), model.M(v), problem6.n_modes + 10)
    clusters = [c for c in cluster_frequencies(modes.frequencies_hz, REPEATED_RTOL) if c.size > 1]
    assert clusters, "a homogeneous cube has repeated eigenvalues"
    rng = np.random.default_rng(3)
    rotated = modes.vectors.copy()
    for c in clusters:  # any orthogonal change of basis inside each repeated mode
        q, _ = np.linalg.qr(rng.normal(size=(c.size, c.size)))
        rotated[:, c] = modes.vectors[:, c] @ q
    a = mode_match(problem6, w, v, modes=modes)
    b = mode_match(problem6, w, v, modes=replace(modes, vectors=rotated))
    assert a["mean_mac"] == pytest.approx(b["mean_mac"], abs=1e-9)
    assert a["freq_rel_error"] == pytest.approx(b["freq_rel_error"], abs=1e-9)
    inside = (problem6.P @ rotated[:, clusters[0]]).T  # observations inside one span
    one_vector = mode_match(replace(problem6, gamma=inside,
                                    eigenvalues=modes.eigenvalues[clusters[0]], mode_snr=None),
                            w, v, modes=modes)
    assert one_vector["mean_mac"] == pytest.approx(1.0, abs=1e-9)
    assert isinstance(modes, Modes)


def test_every_scored_row_states_the_dofs_its_observation_sees(problem6, truth6):
    from vvtbench.observe import observed_dof_fraction
    from vvtbench.scoring.metrics import evaluate

    dof = evaluate(problem6, truth6, truth6.w, truth6.v, modes=False)["metrics"][
        "observed_dof_fraction"]
    assert dof == pytest.approx(observed_dof_fraction(problem6.P, problem6.model))
    assert 0.05 < dof < 2 / 3  # one camera sees some surface vertices, two directions each


# ----------------------------------------------------------------------------- plug-ins

PLUGIN = textwrap.dedent('''
    from dataclasses import dataclass, field
    import numpy as np
    from vvtbench.solving.problem import Estimate

    @dataclass
    class Config:
        value: float = field(default=2.0, metadata={"help": "the constant"})
        scale_v: bool = field(default=False, metadata={"help": "also scale v"})

    class ConstantSolver:
        name = "constant"
        version = "0.1"
        description = "a constant field"
        Config = Config

        def __init__(self, config=None):
            self.config = config or Config()

        def solve(self, problem):
            m = problem.n_params
            return Estimate(w=np.full(m, self.config.value), v=np.ones(m), runtime_s=1e-6,
                            solver=self.name, version=self.version)
''')


def test_plugin_from_file_and_overrides(tmp_path, problem6):
    path = tmp_path / "my_solver.py"
    path.write_text(PLUGIN)
    cls = load_solver(f"{path}:ConstantSolver")
    cfg = parse_overrides(["value=3.5", "scale_v=true"], cls.Config)
    assert cfg.value == 3.5 and cfg.scale_v is True
    assert cls(cfg).solve(problem6).w[0] == 3.5
    with pytest.raises(PluginError, match=r"unknown key.*allowed keys: value, scale_v"):
        parse_overrides(["vaule=1"], cls.Config)
    with pytest.raises(PluginError, match="cannot read 'abc' as float"):
        parse_overrides(["value=abc"], cls.Config)
    with pytest.raises(PluginError, match="expected key=value"):
        parse_overrides(["value"], cls.Config)
    with pytest.raises(PluginError, match="no attribute 'Nope'.*ConstantSolver"):
        load_solver(f"{path}:Nope")
    with pytest.raises(PluginError, match="unknown solver 'nope'; registered: .*vvt"):
        load_solver("nope")


def test_the_documented_third_party_solver_runs(tmp_path, problem6, truth6):
    from pathlib import Path

    doc = (Path(__file__).resolve().parent.parent / "docs" / "solvers.md").read_text()
    block = doc.split("A complete third-party solver")[1].split("```python\n")[1].split("```")[0]
    assert len(block.splitlines()) < 40
    (tmp_path / "my_solver.py").write_text(block)
    cls = load_solver(f"{tmp_path / 'my_solver.py'}:OneStepSolver")
    est = cls(parse_overrides(["ridge=1e-4"], cls.Config)).solve(problem6)
    assert est.w.shape == est.v.shape == (problem6.n_params,) and np.all(est.v > 0)
    assert est.w.mean() == pytest.approx(problem6.w_mean)
    # eigenvalues alone already point at the defect's density
    assert normalized_correlation(est.v, truth6.v) > 0.4


def test_vvt_overrides_parse():
    cls = load_solver("vvt")
    cfg = parse_overrides(["alpha_u=none", "max_iter=7", "preset=real"], cls.Config)
    assert cfg.alpha_u is None and cfg.max_iter == 7
    assert cfg.resolved(20).alpha_u == 0.1 and cfg.resolved(20).tol == 5e-3


def test_cli_solve_writes_outputs(tmp_path, capsys):
    rc = main_solve(["homogeneous", "jello_cube_defect_top", "--modes", "6", "--grid", "4", "4",
                     "4", "-o", str(tmp_path), "--no-mode-match"])
    assert rc == 0
    for f in ("estimate.npz", "estimate.json", "slices.png"):
        assert (tmp_path / f).is_file()
    rc = main_solve(["vvt", "jello_cube_defect_top", "--set", "bogus=1", "-o", str(tmp_path)])
    assert rc == 2 and "allowed keys" in capsys.readouterr().err


@pytest.mark.parametrize("mesh_kind", ["drum", "hex27"])
def test_z_gram_on_meshes_with_many_elements_per_voxel(mesh_kind):
    # circular drum (tri3, 1 DOF per node, several triangles per voxel, some voxels empty of
    # nodes) and a hex27 box on a coarser voxel grid: the per-node blocks must still sum right
    from types import SimpleNamespace

    import scipy.sparse as sp

    from solvers.vvt import ZSystem
    from vvtbench.fem.assembly import ParametricModel
    from vvtbench.fem.mesh import box_mesh, drum_mesh
    from vvtbench.fem.voxels import VoxelMap

    if mesh_kind == "drum":
        mesh = drum_mesh("circle", cells=12)
        vmap = VoxelMap.from_mesh(mesh, (5, 5))
        fixed = mesh.node_sets["rim"]
    else:
        mesh = box_mesh((4, 4, 4), (1.0, 1.0, 1.0), 2)
        vmap = VoxelMap.from_mesh(mesh, (2, 2, 2))
        fixed = mesh.node_sets["bottom"]
    model = ParametricModel(mesh, vmap, fixed_nodes=fixed)
    pb = SimpleNamespace(model=model, n_params=model.n_params, voxel_map=vmap)
    k = 3
    rng = np.random.default_rng(2)
    U = rng.standard_normal((model.n_free, k))
    lam, y = rng.uniform(1.0, 5.0, k), rng.uniform(0.5, 2.0, k)
    ref = sp.csr_matrix((2 * model.n_params,) * 2)
    for i in range(k):
        B = sp.hstack([model.stiffness_columns(U[:, i]), -lam[i] * model.mass_columns(U[:, i])])
        ref = ref + y[i] / k * (B.T @ B)
    G = ZSystem(pb, 1e-10, 1e-7, 1.0, 1.0).gram(U, lam, y)
    assert abs(G - ref).max() < 1e-12 * abs(ref).max()


def test_oracle_bounds_vvt_on_a_drum_with_sharp_defect_edges():
    # the gel bar's edges cut through the 20 x 20 voxels: the true modes are eigenvectors of
    # no voxel model, the strong-form least squares is biased (NC w < 0), the errors-in-
    # variables fit on the full field is not, and `select` picks it from the 3-D mode match
    # alone
    from solvers.oracle import OracleConfig, OracleSolver

    sim = simulate(load_scene("drum_gel_bar"), transient=False)
    pb, truth = _observe(sim, inference_shape=(20, 20), n_modes=20)
    strong = OracleSolver(OracleConfig(method="strong")).solve(pb, truth)
    best = OracleSolver().solve(pb, truth)
    vvt = load_solver("vvt")().solve(pb)
    assert best.extra["chosen"].startswith("fitted")
    assert normalized_correlation(strong.w, truth.w) < 0.0
    for f in ("w", "v"):
        nc_best = normalized_correlation(getattr(best, f), getattr(truth, f))
        assert nc_best >= normalized_correlation(getattr(vvt, f), getattr(truth, f))
        assert nc_best > 0.85


def test_oracle_keeps_the_exact_eigenvalues_of_the_paired_true_modes(problem6, truth6):
    # modes from video: a spurious peak's frequency must not reach the oracle's eigenvalues
    import dataclasses as dc

    from solvers.oracle import OracleConfig, OracleSolver

    pb, truth = problem6.select_modes(6), truth6.select_modes(6)
    lam = pb.eigenvalues.copy()
    lam[0] = lam[0] / 50.0
    fake = dc.replace(pb, eigenvalues=lam)
    cfg = OracleConfig(method="strong")
    a, b = OracleSolver(cfg).solve(pb, truth), OracleSolver(cfg).solve(fake, truth)
    np.testing.assert_array_equal(b.w, a.w)  # the observed eigenvalues never reach it
    np.testing.assert_array_equal(b.v, a.v)
    wrong = OracleSolver(cfg).solve(pb, dc.replace(truth, eigenvalues=lam))
    assert np.abs(wrong.v / a.v - 1).max() > 0.01
    upd = OracleConfig(method="updating")  # the diagnostic candidate, outside `select`
    c, d = OracleSolver(upd).solve(pb, truth), OracleSolver(upd).solve(fake, truth)
    assert c.extra["chosen"] == "updating"
    np.testing.assert_array_equal(d.w, c.w)
