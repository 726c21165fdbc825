"""Physics verification of vvtbench.fem: analytic membranes, convergence, rigid-body modes,
a scikit-fem cross-check, repeated eigenvalues, ParametricModel algebra and element order.

Every tolerance is a physical or numerical claim; none is loosened to make a test pass.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import scipy.linalg as sla
from scipy.special import jn_zeros

from vvtbench.fem import modal
from vvtbench.fem.assembly import ParametricModel
from vvtbench.fem.mesh import box_mesh, drum_mesh, tets_to_mesh
from vvtbench.fem.modal import eigenmodes
from vvtbench.fem.voxels import VoxelMap

# Membrane: tension T (N/m), areal density S (kg/m^2), size (m).
T, S, SIZE = 40.0, 0.5, 0.1016
C = np.sqrt(T / S)
# Jello block.
E_JELLO, NU, RHO = 9000.0, 0.3, 1270.0


def _drum_frequencies(shape: str, cells: int, k: int) -> np.ndarray:
    mesh = drum_mesh(shape, SIZE, cells)
    model = ParametricModel(mesh, fixed_nodes=mesh.node_sets["rim"])
    return eigenmodes(model.K(T), model.M(S), k).frequencies_hz


def _square_analytic(k: int) -> np.ndarray:
    f = [0.5 * C * np.hypot(m / SIZE, n / SIZE) for m in range(1, 10) for n in range(1, 10)]
    return np.sort(f)[:k]


def _circle_analytic(k: int) -> np.ndarray:
    a = SIZE / 2
    f = []
    for m in range(10):
        for j in jn_zeros(m, 6):
            f += [j * C / (2 * np.pi * a)] * (1 if m == 0 else 2)  # cos/sin pair for m > 0
    return np.sort(f)[:k]


def _n_leading_within(rel_err: np.ndarray, tol: float) -> int:
    bad = np.flatnonzero(np.abs(rel_err) > tol)
    return int(bad[0]) if bad.size else len(rel_err)


# --------------------------------------------------------------------------- 1, 2: membranes


@pytest.mark.parametrize(
    ("shape", "cells", "analytic"),
    [("square", 40, _square_analytic), ("circle", 24, _circle_analytic)],
)
def test_membrane_lowest_six_match_analytic(shape, cells, analytic):
    k = 6
    f = _drum_frequencies(shape, cells, k)
    ref = analytic(k)
    # the analytic list already contains both members of every (m,n)/(n,m) or cos/sin pair
    assert np.allclose(ref[1], ref[2]) and not np.isclose(ref[0], ref[1])
    err = (f - ref) / ref
    n_ok = _n_leading_within(err, 5e-3)
    assert n_ok == k, (
        f"{shape} drum ({cells} cells): only the lowest {n_ok} modes are within 0.5%; "
        f"relative errors {np.round(err * 100, 3).tolist()} %"
    )
    # linear triangles with a consistent mass are stiff: every frequency is approached from above
    assert np.all(err > 0), err


# --------------------------------------------------------------------------- 3: convergence


@pytest.mark.parametrize(
    ("shape", "cells", "analytic"),
    [("square", (10, 20, 40), _square_analytic), ("circle", (6, 12, 24), _circle_analytic)],
)
def test_membrane_fundamental_converges_at_second_order(shape, cells, analytic):
    f0 = analytic(1)[0]
    errs = np.array([abs(_drum_frequencies(shape, n, 1)[0] - f0) / f0 for n in cells])
    rates = np.log2(errs[:-1] / errs[1:])
    assert np.all((rates >= 1.7) & (rates <= 2.3)), (errs.tolist(), rates.tolist())


# --------------------------------------------------------------------------- 4: rigid body


def test_free_box_has_six_rigid_body_modes_and_exact_mass():
    size = (0.03, 0.02, 0.01)
    mesh = box_mesh((2, 2, 2), size)
    model = ParametricModel(mesh, nu=NU)
    K, M = model.K(E_JELLO), model.M(RHO)
    modes = eigenmodes(K, M, 12, method="dense")
    lam = modes.eigenvalues
    assert np.all(np.abs(lam[:6]) < 1e-8 * lam[6]), lam[:8]
    assert lam[6] > 1e-2 * lam[11] and lam[6] > 0, lam[:8]

    # rigid translations and rotations lie in the null space of K
    x = mesh.points
    rigid = []
    for a in range(3):
        t = np.zeros((mesh.n_nodes, 3))
        t[:, a] = 1
        rigid.append(t.ravel())
    for axis in np.eye(3):
        rigid.append(np.cross(axis, x - x.mean(axis=0)).ravel())
    R = model.restrict(np.array(rigid).T)
    assert np.abs(K @ R).max() < 1e-10 * abs(K).max() * np.abs(R).max()

    volume = np.prod(size)
    for a in range(3):
        ind = np.zeros((mesh.n_nodes, 3))
        ind[:, a] = 1.0
        u = model.restrict(ind.ravel())
        assert u @ (M @ u) == pytest.approx(RHO * volume, rel=1e-12)
    # the three components do not couple in the mass matrix
    ex, ey = np.zeros((mesh.n_nodes, 3)), np.zeros((mesh.n_nodes, 3))
    ex[:, 0], ey[:, 1] = 1.0, 1.0
    assert abs(model.restrict(ex.ravel()) @ (M @ model.restrict(ey.ravel()))) < 1e-15


# --------------------------------------------------------------------------- 5: scikit-fem


def test_hex8_box_matches_scikit_fem():
    skfem = pytest.importorskip("skfem")
    from skfem.helpers import dot
    from skfem.models.elasticity import lame_parameters, linear_elasticity

    cells, size = (3, 3, 3), (0.05, 0.04, 0.03)
    mesh = box_mesh(cells, size)
    model = ParametricModel(mesh, nu=NU, fixed_nodes=mesh.node_sets["bottom"])
    lam_ours = sla.eigh(model.K(E_JELLO).toarray(), model.M(RHO).toarray(), eigvals_only=True)

    axes = [np.linspace(0, s, n + 1) for s, n in zip(size, cells, strict=True)]
    m = skfem.MeshHex.init_tensor(*axes)
    basis = skfem.Basis(m, skfem.ElementVector(skfem.ElementHex1()), intorder=6)

    @skfem.BilinearForm
    def mass(u, v, w):
        return RHO * dot(u, v)

    K = linear_elasticity(*lame_parameters(E_JELLO, NU)).assemble(basis)
    M = mass.assemble(basis)
    bottom = np.flatnonzero(m.p[2] < 1e-12)
    D = basis.nodal_dofs[:, bottom].ravel()
    assert len(D) == 3 * len(mesh.node_sets["bottom"])
    Kc = skfem.condense(K, D=D, expand=False)
    Mc = skfem.condense(M, D=D, expand=False)
    assert Kc.shape == (model.n_free, model.n_free)
    lam_sk = sla.eigh(Kc.toarray(), Mc.toarray(), eigvals_only=True)
    np.testing.assert_allclose(lam_ours[:12], lam_sk[:12], rtol=1e-6)


# --------------------------------------------------------------------------- 6: repeated modes


@pytest.fixture(scope="module")
def cube_system():
    mesh = box_mesh((6, 6, 6), (0.05, 0.05, 0.05))
    model = ParametricModel(mesh, nu=NU, fixed_nodes=mesh.node_sets["bottom"])
    assert model.n_free > 600  # otherwise every method silently falls back to "dense"
    return model.K(E_JELLO), model.M(RHO)


@pytest.fixture(scope="module")
def cube_dense(cube_system):
    K, M = cube_system
    return eigenmodes(K, M, 24, method="dense")


@pytest.mark.parametrize("method", ["block", "arpack"])
def test_repeated_eigenvalues_agree_across_solvers(cube_system, cube_dense, method):
    K, M = cube_system
    k = 20
    ref = cube_dense
    modes = eigenmodes(K, M, k, method=method)
    f_ref = ref.frequencies_hz[:k]
    np.testing.assert_allclose(modes.frequencies_hz, f_ref, rtol=1e-8)

    # the cube's x/y symmetry makes pairs of equal frequencies; make sure the test sees some
    lam_all = ref.eigenvalues
    edges = np.flatnonzero(np.diff(lam_all) > 1e-6 * lam_all[1:]) + 1
    clusters = [g for g in np.split(np.arange(len(lam_all)), edges) if g[-1] < k]
    pairs = [g for g in clusters if len(g) >= 2]
    assert len(pairs) >= 4, [len(g) for g in clusters]

    for modes_ in (modes, ref):
        phi = modes_.vectors[:, :k]
        G = phi.T @ (M @ phi)
        assert np.abs(G - np.eye(k)).max() < 1e-8

    for g in pairs:
        overlap = ref.vectors[:, g].T @ (M @ modes.vectors[:, g])
        sv = np.linalg.svd(overlap, compute_uv=False)
        np.testing.assert_allclose(sv, 1.0, atol=1e-6, err_msg=f"cluster {g.tolist()}")


@pytest.mark.parametrize("method", ["block", "arpack"])
def test_canonical_modes_are_the_same_vectors_whatever_the_solver(cube_system, cube_dense,
                                                                   method):
    """Each solver returns its own basis of a repeated eigenvalue and its own signs; the
    canonical ones (sign by the largest entry, a cluster's basis by the probe vectors) agree
    vector by vector, as they must between machines."""
    K, M = cube_system
    lam = cube_dense.eigenvalues
    edges = np.flatnonzero(np.diff(lam) > 1e-6 * lam[1:]) + 1
    k = int(edges[edges <= 20].max())  # no cluster cut in two
    modes = eigenmodes(K, M, k, method=method)
    ref = cube_dense.vectors[:, :k]
    err = np.abs(modes.vectors - ref).max(axis=0) / np.abs(ref).max(axis=0)
    assert err.max() < 1e-6, err


def test_a_mode_sign_is_canonical_with_mirror_ties():
    rng = np.random.default_rng(1)
    half = rng.standard_normal((40, 6))
    half[0] = 10.0  # the largest magnitude, reached twice with opposite signs (a mirror pair)
    phi = np.vstack([half, -half[::-1]])
    canon = modal.canonical_signs(phi)
    assert np.all(canon[0] > 0)  # the first of the tied entries decides
    for flipped in (-phi, phi * np.where(np.arange(6) % 2, -1.0, 1.0)):
        noisy = flipped * (1 + 1e-13 * rng.standard_normal(flipped.shape))  # rounding
        np.testing.assert_allclose(modal.canonical_signs(noisy), canon, rtol=1e-12)


def test_probe_vectors_are_fixed_numbers():
    p = modal.probe_vectors(5, 2)
    assert p.shape == (5, 2) and np.all((p >= -1) & (p < 1))
    np.testing.assert_array_equal(p, modal.probe_vectors(9, 3)[:5, :2])
    assert p[0, 0] == modal.probe_vectors(1, 1)[0, 0]


# --------------------------------------------------------------------------- 7: ParametricModel


@pytest.fixture(scope="module")
def voxel_model():
    mesh = box_mesh((4, 4, 4), (0.04, 0.04, 0.04))
    vm = VoxelMap.from_mesh(mesh, (2, 2, 2))
    return ParametricModel(mesh, voxel_map=vm, nu=NU, fixed_nodes=mesh.node_sets["bottom"])


def test_parametric_matrices_are_voxel_sums(voxel_model):
    model = voxel_model
    assert model.n_params == 8
    rng = np.random.default_rng(1)
    w = rng.uniform(0.5, 2.0, model.n_params) * E_JELLO
    v = rng.uniform(0.5, 2.0, model.n_params) * RHO
    eye = np.eye(model.n_params)
    K_ref = sum(w[e] * model.K(eye[e]).toarray() for e in range(model.n_params))
    M_ref = sum(v[e] * model.M(eye[e]).toarray() for e in range(model.n_params))
    np.testing.assert_allclose(model.K(w).toarray(), K_ref, rtol=1e-12, atol=1e-12 * E_JELLO)
    np.testing.assert_allclose(model.M(v).toarray(), M_ref, rtol=1e-12, atol=1e-12 * RHO)

    # one-hot matrices differ: each voxel owns its own 8 elements (bottom ones lose fixed DOFs)
    K_each = [model.K(eye[e]) for e in range(model.n_params)]
    assert all(abs(Ke).sum() > 0 for Ke in K_each)
    assert abs(K_each[0] - K_each[7]).max() > 1e-3 * abs(K_each[0]).max()

    # against an independent per-element assembly
    K_elem = np.zeros((model.mesh.n_dofs,) * 2)
    for el, dofs in enumerate(model.element_dofs):
        K_elem[np.ix_(dofs, dofs)] += w[model.voxel_map.element_param[el]] * model.Ke[el]
    fd = model.free_dofs
    np.testing.assert_allclose(
        model.K(w).toarray(), K_elem[np.ix_(fd, fd)], rtol=1e-12, atol=1e-12 * E_JELLO
    )

    u = rng.standard_normal(model.n_free)
    np.testing.assert_allclose(
        model.stiffness_columns(u) @ w,
        model.K(w) @ u,
        rtol=1e-10,
        atol=1e-12 * np.abs(model.K(w) @ u).max(),
    )
    np.testing.assert_allclose(
        model.mass_columns(u) @ v,
        model.M(v) @ u,
        rtol=1e-10,
        atol=1e-12 * np.abs(model.M(v) @ u).max(),
    )


def test_parametric_scaling_laws(voxel_model):
    model = voxel_model
    rng = np.random.default_rng(2)
    w = rng.uniform(0.5, 2.0, model.n_params) * E_JELLO
    v = rng.uniform(0.5, 2.0, model.n_params) * RHO
    k = 10
    base = eigenmodes(model.K(w), model.M(v), k).eigenvalues
    same = eigenmodes(model.K(3.7 * w), model.M(3.7 * v), k).eigenvalues
    np.testing.assert_allclose(same, base, rtol=1e-10)
    f = eigenmodes(model.K(w), model.M(v), k).frequencies_hz
    f4 = eigenmodes(model.K(4 * w), model.M(v), k).frequencies_hz
    np.testing.assert_allclose(f4, 2 * f, rtol=1e-10)
    # heterogeneity matters: uniform mean values give a different spectrum
    flat = eigenmodes(model.K(w.mean()), model.M(v.mean()), k).eigenvalues
    assert np.abs(flat / base - 1).max() > 1e-3


# --------------------------------------------------------------------------- 8: element order


def _fundamental(mesh) -> float:
    model = ParametricModel(mesh, nu=NU, fixed_nodes=mesh.node_sets["bottom"])
    return float(eigenmodes(model.K(E_JELLO), model.M(RHO), 1).frequencies_hz[0])


def _kuhn_cube_tets(n: int, size: float) -> tuple[np.ndarray, np.ndarray]:
    """n^3 cubes, each split into 6 tetrahedra along its main diagonal (conforming)."""
    xs = np.linspace(0, size, n + 1)
    gx, gy, gz = np.meshgrid(xs, xs, xs, indexing="ij")
    points = np.column_stack([gx.ravel(), gy.ravel(), gz.ravel()])

    def nid(i, j, k):
        return (i * (n + 1) + j) * (n + 1) + k

    tets = []
    for i, j, k in itertools.product(range(n), repeat=3):
        for perm in itertools.permutations(range(3)):
            corner = np.array([i, j, k])
            path = [nid(*corner)]
            for axis in perm:
                corner = corner.copy()
                corner[axis] += 1
                path.append(nid(*corner))
            tets.append(path)
    return points, np.array(tets, dtype=np.int64)


def test_quadratic_elements_beat_hex8_at_equal_node_count():
    L = 0.05
    f8 = _fundamental(box_mesh((8, 8, 8), (L,) * 3))
    f16 = _fundamental(box_mesh((16, 16, 16), (L,) * 3))
    f_ref = f16 + (f16 - f8) / 3  # Richardson, O(h^2)
    f27 = _fundamental(box_mesh((4, 4, 4), (L,) * 3, order=2))
    tet10 = tets_to_mesh(*_kuhn_cube_tets(4, L), order=2)
    assert tet10.n_nodes == 9**3 and len(tet10.node_sets["bottom"]) == 81
    f_tet10 = _fundamental(tet10)

    err8 = abs(f8 - f_ref) / f_ref
    err16 = abs(f16 - f_ref) / f_ref
    err27 = abs(f27 - f_ref) / f_ref
    err_t10 = abs(f_tet10 - f_ref) / f_ref
    # all discretizations are stiff (upper bounds) and the hex8 sequence really converges
    assert min(f8, f16, f27, f_tet10) > f_ref
    assert f8 > f16 and err16 < 0.5 * err8
    # same 9^3 nodes as hex8 on 8^3, but markedly more accurate
    assert err27 < 0.5 * err8, (err27, err8)
    assert err_t10 < err8, (err_t10, err8)
