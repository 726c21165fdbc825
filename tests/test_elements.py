"""Tests for vvtbench.fem.elements: quadrature, shape functions, unit element matrices."""

from __future__ import annotations

import doctest
import itertools
import math

import numpy as np
import pytest

from vvtbench.fem import elements as fe
from vvtbench.fem.elements import (
    ELEMENTS,
    HEX8,
    HEX27,
    TET4,
    TET10,
    TET10_EDGES,
    TRI3,
    centroids,
    elasticity_matrix,
    element_volumes,
    get_element,
    unit_mass,
    unit_stiffness,
)

SOLIDS = [HEX8, HEX27, TET4, TET10]
ALL = [*SOLIDS, TRI3]
ids = [e.name for e in ALL]
solid_ids = [e.name for e in SOLIDS]


def _distorted(el: fe.Element, seed: int = 0, amp: float = 0.06) -> np.ndarray:
    """One randomly distorted but valid element, coords (1, nnodes, 3)."""
    rng = np.random.default_rng(seed)
    ref = el.ref_nodes / 2 if el.refdom == "hex" else el.ref_nodes
    A = np.eye(el.rdim) + 0.25 * rng.uniform(-1, 1, (el.rdim, el.rdim))
    X = ref @ A.T + 0.3 + amp * rng.uniform(-1, 1, ref.shape)
    if el.rdim == 2:
        X = np.column_stack([X, rng.uniform(-1, 1, len(X))])  # z must be ignored
    return X[None]


def _voigt(B: np.ndarray) -> np.ndarray:
    return np.array([B[0, 0], B[1, 1], B[2, 2], B[1, 2] + B[2, 1],
                     B[0, 2] + B[2, 0], B[0, 1] + B[1, 0]])


# --------------------------------------------------------------------------- quadrature


def _monomials(refdom: str, degree: int):
    dim = 2 if refdom == "tri" else 3
    for exps in itertools.product(range(degree + 1), repeat=dim):
        if refdom == "hex" or sum(exps) <= degree:
            yield exps


def _exact_monomial(refdom: str, exps: tuple[int, ...]) -> float:
    if refdom == "hex":
        return math.prod(0.0 if a % 2 else 2.0 / (a + 1) for a in exps)
    return math.prod(math.factorial(a) for a in exps) / math.factorial(sum(exps) + len(exps))


@pytest.mark.parametrize("el", [HEX8, TET4, TRI3], ids=["hex", "tet", "tri"])
@pytest.mark.parametrize("degree", range(8))
def test_quadrature_exact(el, degree):
    x, w = el.quadrature(degree)
    assert x.shape == (len(w), el.rdim)
    assert np.all(w > 0)
    for exps in _monomials(el.refdom, degree):
        got = w @ np.prod(x ** np.array(exps), axis=1)
        assert got == pytest.approx(_exact_monomial(el.refdom, exps), rel=1e-13, abs=1e-14)


def test_quadrature_not_overexact():
    # sanity check that the monomial test can fail: 2-point Gauss misses x^4
    x, w = HEX8.quadrature(2)
    assert len(w) == 8
    assert w @ x[:, 0] ** 4 != pytest.approx(_exact_monomial("hex", (4, 0, 0)))
    assert len(HEX27.quadrature(HEX27.stiffness_degree)[1]) == 27


def test_simplex_points_inside():
    x, _ = TET10.quadrature(TET10.mass_degree)
    assert np.all(x > 0) and np.all(x.sum(axis=1) < 1)
    x, _ = TRI3.quadrature(TRI3.mass_degree)
    assert np.all(x > 0) and np.all(x.sum(axis=1) < 1)


# --------------------------------------------------------------------------- shapes


@pytest.mark.parametrize("el", ALL, ids=ids)
def test_shape_functions(el):
    assert el.ref_nodes.shape == (el.nnodes, el.rdim)
    assert len(el.vertex_index) == el.corner_nodes
    np.testing.assert_allclose(el.shape(el.ref_nodes), np.eye(el.nnodes), atol=1e-14)

    rng = np.random.default_rng(1)
    xi = rng.uniform(0, 0.3, (7, el.rdim)) if el.refdom != "hex" else rng.uniform(-1, 1, (7, 3))
    N, dN = el.shape(xi), el.dshape(xi)
    assert N.shape == (7, el.nnodes) and dN.shape == (7, el.nnodes, el.rdim)
    np.testing.assert_allclose(N.sum(axis=1), 1.0, atol=1e-14)
    np.testing.assert_allclose(dN.sum(axis=1), 0.0, atol=1e-13)

    h = 1e-6
    for d in range(el.rdim):
        e = np.zeros(el.rdim)
        e[d] = h
        fd = (el.shape(xi + e) - el.shape(xi - e)) / (2 * h)
        np.testing.assert_allclose(dN[:, :, d], fd, atol=1e-8)


def test_node_conventions():
    np.testing.assert_array_equal(HEX8.ref_nodes[[0, 1, 2, 4, 7]],
                                  [[-1, -1, -1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1], [1, 1, 1]])
    np.testing.assert_array_equal(HEX27.ref_nodes[[1, 3, 9, 13]],
                                  [[0, -1, -1], [-1, 0, -1], [-1, -1, 0], [0, 0, 0]])
    np.testing.assert_array_equal(HEX27.vertex_index, [0, 2, 6, 8, 18, 20, 24, 26])
    np.testing.assert_array_equal(HEX27.ref_nodes[HEX27.vertex_index], HEX8.ref_nodes)
    np.testing.assert_array_equal(TET10.ref_nodes[:4], TET4.ref_nodes)
    np.testing.assert_array_equal(TET10_EDGES, [[0, 1], [1, 2], [0, 2], [0, 3], [1, 3], [2, 3]])
    np.testing.assert_allclose(TET10.ref_nodes[4:], TET4.ref_nodes[TET10_EDGES].mean(axis=1))
    assert set(ELEMENTS) == {"hex8", "hex27", "tet4", "tet10", "tri3"}
    assert [get_element(n).dofs_per_node for n in ELEMENTS] == [3, 3, 3, 3, 1]


# --------------------------------------------------------------------------- stiffness


def test_elasticity_matrix():
    nu = 0.27
    S = np.linalg.inv(elasticity_matrix(nu))  # compliance, E = 1
    np.testing.assert_allclose(np.diag(S)[:3], 1.0)
    np.testing.assert_allclose(S[0, 1:3], -nu)
    np.testing.assert_allclose(np.diag(S)[3:], 2 * (1 + nu))  # 1/G with engineering shear
    assert np.count_nonzero(np.abs(S) > 1e-12) == 12
    Ds = elasticity_matrix(np.array([0.1, 0.27]))
    assert Ds.shape == (2, 6, 6)
    np.testing.assert_allclose(Ds[1], elasticity_matrix(nu))
    with pytest.raises(ValueError, match="Poisson"):
        elasticity_matrix(0.5)


def _rigid_modes(X: np.ndarray) -> np.ndarray:
    modes = []
    for a in range(3):
        u = np.zeros_like(X)
        u[:, a] = 1.0
        modes.append(u.ravel())
    for a, b in [(0, 1), (1, 2), (0, 2)]:
        u = np.zeros_like(X)
        u[:, a], u[:, b] = -X[:, b], X[:, a]
        modes.append(u.ravel())
    return np.array(modes).T


@pytest.mark.parametrize("el", ALL, ids=ids)
def test_stiffness_null_space(el):
    X = _distorted(el, seed=2)
    K = unit_stiffness(el, X, nu=0.3)
    n = el.nnodes * el.dofs_per_node
    assert K.shape == (1, n, n)
    K = K[0]
    np.testing.assert_allclose(K, K.T, rtol=0, atol=1e-13 * np.abs(K).max())
    lam = np.linalg.eigvalsh(K)
    nzero = 6 if el.dofs_per_node == 3 else 1
    scale = lam[-1]
    assert np.sum(np.abs(lam) < 1e-10 * scale) == nzero
    assert lam[nzero] > 1e-6 * scale
    R = _rigid_modes(X[0]) if el.dofs_per_node == 3 else np.ones((el.nnodes, 1))
    assert np.abs(K @ R).max() < 1e-12 * scale


@pytest.mark.parametrize("el", SOLIDS, ids=solid_ids)
def test_stiffness_matches_btdb(el):
    """Independent B^T D B assembly with the same quadrature rule."""
    X = _distorted(el, seed=3)[0]
    nu = 0.21
    xi, w = el.quadrature(el.stiffness_degree)
    dN = el.dshape(xi)
    D = elasticity_matrix(nu)
    K = np.zeros((3 * el.nnodes,) * 2)
    for q in range(len(w)):
        J = X.T @ dN[q]
        G = dN[q] @ np.linalg.inv(J)
        B = np.zeros((6, 3 * el.nnodes))
        for i, g in enumerate(G):
            B[:, 3 * i: 3 * i + 3] = [[g[0], 0, 0], [0, g[1], 0], [0, 0, g[2]],
                                      [0, g[2], g[1]], [g[2], 0, g[0]], [g[1], g[0], 0]]
        K += w[q] * np.linalg.det(J) * B.T @ D @ B
    np.testing.assert_allclose(unit_stiffness(el, X[None], nu)[0], K, rtol=0,
                               atol=1e-12 * np.abs(K).max())


def test_per_element_nu():
    X = np.concatenate([_distorted(TET10, s) for s in range(3)])
    nu = np.array([0.0, 0.3, 0.45])
    K = unit_stiffness(TET10, X, nu)
    for e in range(3):
        Ke = unit_stiffness(TET10, X[e:e + 1], nu[e])[0]
        np.testing.assert_allclose(K[e], Ke, rtol=0, atol=1e-13 * np.abs(Ke).max())
    assert not np.allclose(K[0], K[2])
    with pytest.raises(ValueError, match="shape"):
        unit_stiffness(TET10, X, nu[:2])


# --------------------------------------------------------------------------- mass


def _reference_volume(el: fe.Element, X: np.ndarray) -> float:
    xi, w = el.quadrature(12)
    J = np.einsum("na,qnb->qab", X[:, : el.rdim], el.dshape(xi))
    return float(w @ np.linalg.det(J))


@pytest.mark.parametrize("el", ALL, ids=ids)
def test_mass(el):
    X = _distorted(el, seed=4)
    M = unit_mass(el, X)[0]
    vol = element_volumes(el, X)
    assert vol.shape == (1,)
    assert vol[0] == pytest.approx(_reference_volume(el, X[0]), rel=1e-12)
    dpn = el.dofs_per_node
    assert M[0::dpn, 0::dpn].sum() == pytest.approx(vol[0], rel=1e-12)
    np.testing.assert_array_equal(M, M.T)
    assert np.linalg.eigvalsh(M)[0] > 0
    if dpn == 3:
        Mxx = M[0::3, 0::3]
        np.testing.assert_array_equal(M[1::3, 1::3], Mxx)
        np.testing.assert_array_equal(M[2::3, 2::3], Mxx)
        assert not M[0::3, 1::3].any() and not M[0::3, 2::3].any() and not M[1::3, 2::3].any()


@pytest.mark.parametrize("el, factor", [(TET4, 20), (TRI3, 12)], ids=["tet4", "tri3"])
def test_linear_simplex_mass_formula(el, factor):
    X = _distorted(el, seed=5, amp=0.0)
    M = unit_mass(el, X)[0][:: el.dofs_per_node, :: el.dofs_per_node]
    V = element_volumes(el, X)[0]
    np.testing.assert_allclose(M, V / factor * (1 + np.eye(el.nnodes)), rtol=1e-13)


def test_volumes_and_centroids_affine():
    rng = np.random.default_rng(6)
    A = np.eye(3) + 0.3 * rng.uniform(-1, 1, (3, 3))
    b = rng.uniform(-1, 1, 3)
    detA = np.linalg.det(A)
    assert detA > 0
    for el, refvol, refc in [(HEX8, 8, 0.0), (HEX27, 8, 0.0), (TET4, 1 / 6, 0.25),
                             (TET10, 1 / 6, 0.25)]:
        X = (el.ref_nodes @ A.T + b)[None]
        assert element_volumes(el, X)[0] == pytest.approx(refvol * detA, rel=1e-13)
        np.testing.assert_allclose(centroids(X)[0], A @ np.full(3, refc) + b, atol=1e-14)
        np.testing.assert_allclose(centroids(X, el)[0], A @ np.full(3, refc) + b, atol=1e-14)
    tri = np.array([[[0.0, 0], [2, 0], [0, 1]]])
    assert element_volumes(TRI3, tri)[0] == pytest.approx(1.0)
    tri_z = np.concatenate([tri, [[[5.0], [-1.0], [2.0]]]], axis=2)  # z is ignored
    np.testing.assert_array_equal(unit_stiffness(TRI3, tri_z), unit_stiffness(TRI3, tri))
    np.testing.assert_allclose(centroids(tri), [[2 / 3, 1 / 3, 0]])


# --------------------------------------------------------------------------- patch tests


def _hex_mesh(n: int, p: int) -> tuple[np.ndarray, np.ndarray]:
    m = p * n + 1
    g = np.linspace(0.0, 1.0, m)
    z, y, x = np.meshgrid(g, g, g, indexing="ij")
    pts = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    e = np.arange(n)
    ez, ey, ex = np.meshgrid(e, e, e, indexing="ij")
    base = (p * ex + m * p * ey + m * m * p * ez).ravel()
    loc = np.arange(p + 1)
    lk, lj, li = np.meshgrid(loc, loc, loc, indexing="ij")
    return pts, base[:, None] + (li + m * lj + m * m * lk).ravel()


def _tet_mesh(n: int, quadratic: bool) -> tuple[np.ndarray, np.ndarray]:
    pts, hexes = _hex_mesh(n, 1)
    local = [[0, 1 << a, (1 << a) + (1 << b), 7] for a, b, _ in itertools.permutations(range(3))]
    tets = hexes[:, local].reshape(-1, 4)
    P = pts[tets]
    vol = np.einsum("ei,ei->e", P[:, 1] - P[:, 0], np.cross(P[:, 2] - P[:, 0], P[:, 3] - P[:, 0]))
    tets[vol < 0] = tets[vol < 0][:, [0, 2, 1, 3]]
    if not quadratic:
        return pts, tets
    edges = np.sort(tets[:, TET10_EDGES], axis=2).reshape(-1, 2)
    uniq, inv = np.unique(edges, axis=0, return_inverse=True)
    mids = pts[uniq].mean(axis=1)
    conn = np.hstack([tets, len(pts) + inv.reshape(-1, 6)])
    return np.vstack([pts, mids]), conn


def _tri_mesh(n: int) -> tuple[np.ndarray, np.ndarray]:
    g = np.linspace(0.0, 1.0, n + 1)
    y, x = np.meshgrid(g, g, indexing="ij")
    pts = np.column_stack([x.ravel(), y.ravel()])
    e = np.arange(n)
    ey, ex = np.meshgrid(e, e, indexing="ij")
    v0 = (ex + (n + 1) * ey).ravel()
    v1, v2, v3 = v0 + 1, v0 + n + 2, v0 + n + 1
    return pts, np.concatenate([np.column_stack([v0, v1, v2]), np.column_stack([v0, v2, v3])])


def _patch(el: fe.Element) -> tuple[np.ndarray, np.ndarray, float]:
    if el is HEX8:
        (pts, conn), h = _hex_mesh(3, 1), 1 / 3
    elif el is HEX27:
        (pts, conn), h = _hex_mesh(2, 2), 1 / 4
    elif el is TET4:
        (pts, conn), h = _tet_mesh(3, False), 1 / 3
    elif el is TET10:
        (pts, conn), h = _tet_mesh(2, True), 1 / 4
    else:
        (pts, conn), h = _tri_mesh(4), 1 / 4
    return pts, conn, h


def _assemble(Ke: np.ndarray, conn: np.ndarray, dpn: int, npts: int) -> np.ndarray:
    dofs = (conn[:, :, None] * dpn + np.arange(dpn)).reshape(len(conn), -1)
    K = np.zeros((npts * dpn,) * 2)
    np.add.at(K, (dofs[:, :, None], dofs[:, None, :]), Ke)
    return K


@pytest.mark.parametrize("el", ALL, ids=ids)
def test_patch(el):
    rng = np.random.default_rng(7)
    pts, conn, h = _patch(el)
    boundary = np.any((pts < 1e-12) | (pts > 1 - 1e-12), axis=1)
    assert 0 < np.count_nonzero(~boundary) < len(pts)
    pts = pts.copy()
    pts[~boundary] += 0.12 * h * rng.uniform(-1, 1, (np.count_nonzero(~boundary), pts.shape[1]))
    X = pts[conn]
    nu = 0.3
    Ke = unit_stiffness(el, X, nu)
    vol = element_volumes(el, X)
    assert vol.sum() == pytest.approx(1.0, rel=1e-12)

    dim, dpn = pts.shape[1], el.dofs_per_node
    a = rng.uniform(-1, 1, dpn)
    B = rng.uniform(-1, 1, (dpn, dim))
    u_exact = (a + pts @ B.T).ravel()
    K = _assemble(Ke, conn, dpn, len(pts))
    free = np.repeat(~boundary, dpn)
    u = u_exact.copy()
    u[free] = np.linalg.solve(K[np.ix_(free, free)], -K[np.ix_(free, ~free)] @ u_exact[~free])
    assert np.abs(u[free] - u_exact[free]).max() < 1e-10

    ue = u_exact.reshape(len(pts), dpn)[conn].reshape(len(conn), -1)
    energy = 0.5 * np.einsum("ei,eij,ej->e", ue, Ke, ue)
    if dpn == 3:
        eps = _voigt(B)
        density = 0.5 * eps @ elasticity_matrix(nu) @ eps
    else:
        density = 0.5 * B[0] @ B[0]
    np.testing.assert_allclose(energy, density * vol, rtol=1e-10)


# --------------------------------------------------------------------------- scikit-fem


def _spectrum_close(A: np.ndarray, B: np.ndarray) -> None:
    a, b = np.linalg.eigvalsh(A), np.linalg.eigvalsh(B)
    assert a.shape == b.shape
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-10 * np.abs(b).max())


def _unit_cube_warp(p: np.ndarray) -> np.ndarray:
    """Deterministic vertex perturbation of unit-cube points p (..., 3)."""
    s = np.sin(12.9898 * p[..., :1] + 78.233 * p[..., 1:2] + 37.719 * p[..., 2:3]
               + np.array([0.0, 1.0, 2.0]))
    return p + 0.15 * s


@pytest.mark.parametrize("el", [HEX8, HEX27, TET4, TET10, TRI3], ids=ids)
def test_against_skfem(el):
    skfem = pytest.importorskip("skfem")
    from skfem.models import lame_parameters, laplace, linear_elasticity, mass

    nu = 0.3
    if el.refdom == "hex":
        m0 = skfem.MeshHex()
        mesh = skfem.MeshHex(_unit_cube_warp(m0.p.T).T, m0.t)
        x8 = _unit_cube_warp((HEX8.ref_nodes + 1) / 2)
        X = HEX8.shape(el.ref_nodes) @ x8  # same trilinear geometry for hex27
        sk = skfem.ElementHex1() if el is HEX8 else skfem.ElementHex2()
        intorder = 3 if el is HEX8 else 5  # 2 resp. 3 Gauss points per direction
    elif el.refdom == "tet":
        V = np.array([[0.1, 0.0, 0.05], [1.2, 0.1, 0.0], [0.2, 0.9, 0.1], [0.3, 0.2, 1.1]])
        mesh = skfem.MeshTet(V.T, np.arange(4)[:, None])
        X = np.vstack([V, V[TET10_EDGES].mean(axis=1)])[: el.nnodes]
        sk = skfem.ElementTetP1() if el is TET4 else skfem.ElementTetP2()
        intorder = 4
    else:
        V = np.array([[0.1, 0.0], [1.2, 0.3], [0.2, 0.9]])
        mesh = skfem.MeshTri(V.T, np.arange(3)[:, None])
        X, sk, intorder = V, skfem.ElementTriP1(), 2

    scalar = skfem.Basis(mesh, sk, intorder=intorder)
    M_sk = mass.assemble(scalar).toarray()
    if el.dofs_per_node == 1:
        K_sk = laplace.assemble(scalar).toarray()
    else:
        vector = skfem.Basis(mesh, skfem.ElementVector(sk), intorder=intorder)
        K_sk = linear_elasticity(*lame_parameters(1.0, nu)).assemble(vector).toarray()

    K = unit_stiffness(el, X[None], nu)[0]
    M = unit_mass(el, X[None])[0][:: el.dofs_per_node, :: el.dofs_per_node]
    _spectrum_close(K, K_sk)
    _spectrum_close(M, M_sk)


# --------------------------------------------------------------------------- bad input


def test_inverted_and_degenerate_elements():
    good = _distorted(HEX8, seed=8)[0]
    mirrored = good[[1, 0, 3, 2, 5, 4, 7, 6]]  # swap i=0 <-> i=1: a reflection
    X = np.stack([good, good, mirrored, good, mirrored])
    with pytest.raises(ValueError, match=r"2 of 5 hex8 .*inverted or degenerate.*index 2"):
        unit_stiffness(HEX8, X)
    with pytest.raises(ValueError, match="index 2"):
        unit_mass(HEX8, X)
    flat = TET4.ref_nodes.copy()
    flat[3] = [0.3, 0.3, 0.0]  # four coplanar vertices
    with pytest.raises(ValueError, match=r"1 of 1 tet4 .*index 0"):
        element_volumes(TET4, flat[None])
    collapsed = np.zeros((1, 10, 3))
    with pytest.raises(ValueError, match="tet10"):
        unit_stiffness(TET10, collapsed)
    clockwise = np.array([[[0.0, 0.0], [0.0, 1.0], [1.0, 0.0]]])
    with pytest.raises(ValueError, match="tri3"):
        unit_mass(TRI3, clockwise)


def test_bad_arguments():
    with pytest.raises(ValueError, match=r"hex8, hex27, tet4, tet10, tri3") as info:
        get_element("hex20")
    assert "hex20" in str(info.value)
    with pytest.raises(ValueError, match=r"\(ne, 4, 3\)"):
        unit_stiffness(TET4, TET4.ref_nodes)  # missing element axis
    with pytest.raises(ValueError, match="Poisson"):
        unit_stiffness(TET4, TET4.ref_nodes[None], nu=-1.0)


def test_doctests():
    result = doctest.testmod(fe)
    assert result.attempted > 0 and result.failed == 0
