"""Finite elements, quadrature and unit element matrices (vectorized over elements).

Every routine here works on a whole batch of elements at once: element node coordinates
are passed as an array ``coords`` of shape ``(ne, nnodes, 3)`` and element matrices are
returned as ``(ne, ndof, ndof)`` stacks.  Matrices are *unit* matrices: the stiffness is
computed with Young's modulus ``E = 1`` (membrane tension ``T = 1``) and the mass with
density ``1``, so that a heterogeneous material is assembled by scaling each element
matrix with its own ``E`` and ``rho``.

Solid element dofs are ordered node by node, ``[n0x, n0y, n0z, n1x, n1y, n1z, ...]``.
Stress and strain use Voigt order ``xx, yy, zz, yz, xz, xy`` with engineering shear strains.

Examples
--------
>>> import numpy as np
>>> from vvtbench.fem.elements import HEX8, element_volumes, unit_mass
>>> cube = (HEX8.ref_nodes[None] + 1.0) / 2.0          # one unit cube
>>> element_volumes(HEX8, cube)
array([1.])
>>> M = unit_mass(HEX8, cube)
>>> M.shape, round(float(M[0, 0::3, 0::3].sum()), 12)
((1, 24, 24), 1.0)
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike
from scipy.special import roots_jacobi

__all__ = [
    "Element",
    "Hex8",
    "Hex27",
    "Tet4",
    "Tet10",
    "Tri3",
    "HEX8",
    "HEX27",
    "TET4",
    "TET10",
    "TRI3",
    "ELEMENTS",
    "TET10_EDGES",
    "get_element",
    "gauss_hex",
    "collapsed_tet",
    "collapsed_tri",
    "elasticity_matrix",
    "unit_stiffness",
    "unit_mass",
    "element_volumes",
    "centroids",
]

TET10_EDGES = np.array([[0, 1], [1, 2], [0, 2], [0, 3], [1, 3], [2, 3]])
"""Vertex pairs of the tet10 midside nodes 4..9 (VTK quadratic-tetra order)."""

_CHUNK = 1024


# --------------------------------------------------------------------------- quadrature


def _gauss_jacobi_01(n: int, alpha: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss rule on [0, 1] for the weight ``(1 - u)**alpha``."""
    t, w = roots_jacobi(n, alpha, 0)
    return (1.0 + t) / 2.0, w / 2.0 ** (alpha + 1)


def _npoints(degree: int) -> int:
    return max(1, math.ceil((degree + 1) / 2))


def gauss_hex(degree: int) -> tuple[np.ndarray, np.ndarray]:
    """Tensor Gauss–Legendre rule on ``[-1, 1]^3``.

    Exact for every monomial ``x^a y^b z^c`` with ``max(a, b, c) <= degree`` (``n^3``
    points with ``n = ceil((degree + 1) / 2)``).  Points are in lexicographic order
    (``x`` fastest).

    >>> x, w = gauss_hex(3)
    >>> x.shape, float(w.sum())
    ((8, 3), 8.0)
    """
    g, w = np.polynomial.legendre.leggauss(_npoints(degree))
    z, y, x = np.meshgrid(g, g, g, indexing="ij")
    wz, wy, wx = np.meshgrid(w, w, w, indexing="ij")
    return np.column_stack([x.ravel(), y.ravel(), z.ravel()]), (wx * wy * wz).ravel()


def collapsed_tri(degree: int) -> tuple[np.ndarray, np.ndarray]:
    """Collapsed (Duffy) Gauss–Jacobi rule on the triangle (0,0), (1,0), (0,1).

    Exact for polynomials of total degree ``<= degree`` (in fact ``<= 2n - 1``);
    ``n^2`` points with ``n = ceil((degree + 1) / 2)``, all interior, positive weights.
    """
    n = _npoints(degree)
    u, wu = _gauss_jacobi_01(n, 1)
    v, wv = _gauss_jacobi_01(n, 0)
    U, V = np.meshgrid(u, v, indexing="ij")
    W = np.outer(wu, wv)
    x, y = U, V * (1.0 - U)
    return np.column_stack([x.ravel(), y.ravel()]), W.ravel()


def collapsed_tet(degree: int) -> tuple[np.ndarray, np.ndarray]:
    """Collapsed (Duffy) Gauss–Jacobi rule on the unit tetrahedron.

    Exact for polynomials of total degree ``<= degree`` (in fact ``<= 2n - 1``);
    ``n^3`` points with ``n = ceil((degree + 1) / 2)``, all interior, positive weights.

    >>> x, w = collapsed_tet(1)                   # one point: the centroid
    >>> x.round(12).tolist(), round(float(w[0]), 12)
    ([[0.25, 0.25, 0.25]], 0.166666666667)
    """
    n = _npoints(degree)
    u, wu = _gauss_jacobi_01(n, 2)
    v, wv = _gauss_jacobi_01(n, 1)
    s, ws = _gauss_jacobi_01(n, 0)
    U, V, S = np.meshgrid(u, v, s, indexing="ij")
    W = wu[:, None, None] * wv[None, :, None] * ws[None, None, :]
    x, y, z = U, V * (1.0 - U), S * (1.0 - U) * (1.0 - V)
    return np.column_stack([x.ravel(), y.ravel(), z.ravel()]), W.ravel()


_QUADRATURE = {"hex": gauss_hex, "tet": collapsed_tet, "tri": collapsed_tri}


# --------------------------------------------------------------------------- elements


class Element:
    """Base class of a Lagrange element on a reference domain.

    Attributes
    ----------
    name : str
        Short name, e.g. ``"hex8"``.
    refdom : str
        Reference domain: ``"hex"`` (``[-1, 1]^3``), ``"tet"`` or ``"tri"`` (unit simplex).
    nnodes : int
        Nodes per element.
    rdim : int
        Reference dimension.
    dofs_per_node : int
        3 for solids, 1 for the scalar membrane.
    corner_nodes : int
        Number of vertex nodes.
    vertex_index : numpy.ndarray
        Positions of the vertex nodes in element node order.
    ref_nodes : numpy.ndarray
        Reference coordinates of the nodes, ``(nnodes, rdim)``.
    stiffness_degree, mass_degree : int
        Quadrature degree used by :func:`unit_stiffness` / :func:`unit_mass`
        (exact for straight-sided elements).
    """

    name: str
    refdom: str
    nnodes: int
    rdim: int
    dofs_per_node: int
    corner_nodes: int
    vertex_index: np.ndarray
    ref_nodes: np.ndarray
    stiffness_degree: int
    mass_degree: int

    def shape(self, xi: ArrayLike) -> np.ndarray:
        """Shape functions at reference points ``xi (nq, rdim)`` -> ``(nq, nnodes)``."""
        raise NotImplementedError

    def dshape(self, xi: ArrayLike) -> np.ndarray:
        """Reference gradients ``dN/dxi`` at ``xi (nq, rdim)`` -> ``(nq, nnodes, rdim)``."""
        raise NotImplementedError

    def quadrature(self, degree: int) -> tuple[np.ndarray, np.ndarray]:
        """Quadrature points ``(nq, rdim)`` and weights ``(nq,)`` on the reference domain.

        Hexes: exact for ``max(a, b, c) <= degree``; simplices: total degree ``<= degree``.
        """
        return _QUADRATURE[self.refdom](degree)

    def _points(self, xi: ArrayLike) -> np.ndarray:
        xi = np.atleast_2d(np.asarray(xi, dtype=float))
        if xi.ndim != 2 or xi.shape[1] != self.rdim:
            raise ValueError(f"{self.name}: xi must have shape (nq, {self.rdim}), got {xi.shape}")
        return xi

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.name!r}: {self.nnodes} nodes>"


class _TensorHex(Element):
    """Tensor-product Lagrange hexahedron on ``[-1, 1]^3`` with lexicographic node order."""

    refdom = "hex"
    rdim = 3
    dofs_per_node = 3
    corner_nodes = 8
    order: int

    def __init__(self) -> None:
        p = self.order + 1
        self.nnodes = p**3
        r = np.linspace(-1.0, 1.0, p)
        k, j, i = np.meshgrid(range(p), range(p), range(p), indexing="ij")
        self._ijk = np.column_stack([i.ravel(), j.ravel(), k.ravel()])
        self.ref_nodes = r[self._ijk]
        ends = np.all((self._ijk == 0) | (self._ijk == self.order), axis=1)
        self.vertex_index = np.flatnonzero(ends)

    def _line(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self.order == 1:
            one = np.ones_like(x)
            return np.stack([(1 - x) / 2, (1 + x) / 2], -1), np.stack([-one / 2, one / 2], -1)
        val = np.stack([x * (x - 1) / 2, 1 - x * x, x * (x + 1) / 2], -1)
        return val, np.stack([x - 0.5, -2 * x, x + 0.5], -1)

    def _factors(self, xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        lv, ld = self._line(self._points(xi))  # (nq, 3, p)
        a = np.arange(3)
        return lv[:, a, self._ijk], ld[:, a, self._ijk]  # (nq, nnodes, 3)

    def shape(self, xi: ArrayLike) -> np.ndarray:
        return self._factors(xi)[0].prod(axis=-1)

    def dshape(self, xi: ArrayLike) -> np.ndarray:
        v, d = self._factors(xi)
        return np.stack(
            [d[..., 0] * v[..., 1] * v[..., 2],
             v[..., 0] * d[..., 1] * v[..., 2],
             v[..., 0] * v[..., 1] * d[..., 2]],
            axis=-1,
        )


class Hex8(_TensorHex):
    """Trilinear 8-node hexahedron on ``[-1, 1]^3``.

    Nodes are in *lexicographic* tensor order (not VTK order): node ``i + 2*j + 4*k`` sits
    at ``(-1 + 2i, -1 + 2j, -1 + 2k)``, ``i, j, k in {0, 1}``.  Default quadrature 2x2x2.
    """

    name = "hex8"
    order = 1
    stiffness_degree = 2
    mass_degree = 2


class Hex27(_TensorHex):
    """Triquadratic 27-node Lagrange hexahedron on ``[-1, 1]^3``.

    Nodes are in lexicographic tensor order: node ``i + 3*j + 9*k`` sits at
    ``(-1 + i, -1 + j, -1 + k)``, ``i, j, k in {0, 1, 2}``.  The 8 vertices (``i, j, k in
    {0, 2}``) are ``vertex_index = [0, 2, 6, 8, 18, 20, 24, 26]``, in hex8 order.
    Default quadrature 3x3x3.
    """

    name = "hex27"
    order = 2
    stiffness_degree = 4
    mass_degree = 4


class Tet4(Element):
    """Linear tetrahedron with nodes (0,0,0), (1,0,0), (0,1,0), (0,0,1)."""

    name = "tet4"
    refdom = "tet"
    nnodes = 4
    rdim = 3
    dofs_per_node = 3
    corner_nodes = 4
    vertex_index = np.arange(4)
    ref_nodes = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    stiffness_degree = 0
    mass_degree = 2

    def shape(self, xi: ArrayLike) -> np.ndarray:
        xi = self._points(xi)
        return np.column_stack([1.0 - xi.sum(axis=1), xi])

    def dshape(self, xi: ArrayLike) -> np.ndarray:
        xi = self._points(xi)
        d = np.vstack([-np.ones(3), np.eye(3)])
        return np.broadcast_to(d, (len(xi), 4, 3)).copy()


class Tet10(Tet4):
    """Quadratic 10-node tetrahedron.

    Nodes 0-3 are the tet4 vertices, nodes 4-9 the midpoints of the edges
    ``TET10_EDGES = (0,1), (1,2), (0,2), (0,3), (1,3), (2,3)`` (VTK quadratic-tetra order).
    Stiffness uses an 8-point rule (exact to degree 3, so curved elements pass the patch
    test), mass a 27-point rule (degree 5).
    """

    name = "tet10"
    nnodes = 10
    ref_nodes = np.vstack([Tet4.ref_nodes, Tet4.ref_nodes[TET10_EDGES].mean(axis=1)])
    stiffness_degree = 3
    mass_degree = 4

    def shape(self, xi: ArrayLike) -> np.ndarray:
        L = super().shape(xi)
        a, b = TET10_EDGES.T
        return np.column_stack([L * (2 * L - 1), 4 * L[:, a] * L[:, b]])

    def dshape(self, xi: ArrayLike) -> np.ndarray:
        L = super().shape(xi)[:, :, None]
        dL = super().dshape(xi)
        a, b = TET10_EDGES.T
        corner = (4 * L - 1) * dL
        edge = 4 * (L[:, a] * dL[:, b] + L[:, b] * dL[:, a])
        return np.concatenate([corner, edge], axis=1)


class Tri3(Element):
    """Linear triangle (0,0), (1,0), (0,1) for the scalar membrane (1 dof per node)."""

    name = "tri3"
    refdom = "tri"
    nnodes = 3
    rdim = 2
    dofs_per_node = 1
    corner_nodes = 3
    vertex_index = np.arange(3)
    ref_nodes = np.array([[0.0, 0], [1, 0], [0, 1]])
    stiffness_degree = 0
    mass_degree = 2

    def shape(self, xi: ArrayLike) -> np.ndarray:
        xi = self._points(xi)
        return np.column_stack([1.0 - xi.sum(axis=1), xi])

    def dshape(self, xi: ArrayLike) -> np.ndarray:
        xi = self._points(xi)
        d = np.array([[-1.0, -1.0], [1, 0], [0, 1]])
        return np.broadcast_to(d, (len(xi), 3, 2)).copy()


HEX8 = Hex8()
HEX27 = Hex27()
TET4 = Tet4()
TET10 = Tet10()
TRI3 = Tri3()
ELEMENTS: dict[str, Element] = {e.name: e for e in (HEX8, HEX27, TET4, TET10, TRI3)}


def get_element(name: str) -> Element:
    """Look up an element by name.

    >>> get_element("tet10").nnodes
    10
    """
    try:
        return ELEMENTS[name]
    except KeyError:
        raise ValueError(
            f"unknown element {name!r}; allowed: {', '.join(ELEMENTS)}"
        ) from None


# --------------------------------------------------------------------------- geometry


def _coords(element: Element, coords: ArrayLike) -> np.ndarray:
    X = np.asarray(coords, dtype=float)
    sdim = (2, 3) if element.rdim == 2 else (3,)
    if X.ndim != 3 or X.shape[1] != element.nnodes or X.shape[2] not in sdim:
        want = " or ".join(f"(ne, {element.nnodes}, {d})" for d in sdim)
        raise ValueError(f"{element.name}: coords must have shape {want}, got {X.shape}")
    return X[..., : element.rdim]


def _det(J: np.ndarray) -> np.ndarray:
    """Determinants of component-first Jacobians ``J[a, b] = dx_a/dxi_b``."""
    if len(J) == 2:
        return J[0, 0] * J[1, 1] - J[0, 1] * J[1, 0]
    return J[0, 0] * _cof(J, 0, 0) + J[0, 1] * _cof(J, 0, 1) + J[0, 2] * _cof(J, 0, 2)


def _cof(J: np.ndarray, a: int, b: int) -> np.ndarray:
    a1, a2, b1, b2 = (a + 1) % 3, (a + 2) % 3, (b + 1) % 3, (b + 2) % 3
    return J[a1, b1] * J[a2, b2] - J[a1, b2] * J[a2, b1]


def _inv(J: np.ndarray, det: np.ndarray) -> np.ndarray:
    """Inverse Jacobians ``dxi_b/dx_a`` as ``(..., b, a)`` from component-first ``J``."""
    if len(J) == 2:
        inv = np.stack([J[1, 1], -J[0, 1], -J[1, 0], J[0, 0]], axis=-1)
        return inv.reshape(det.shape + (2, 2)) / det[..., None, None]
    inv = np.stack([_cof(J, a, b) for b in range(3) for a in range(3)], axis=-1)
    return inv.reshape(det.shape + (3, 3)) / det[..., None, None]


def _jacobians(
    element: Element, X: np.ndarray, degree: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Quadrature points, weights, Jacobians ``(d, d, ne, nq)`` and determinants ``(ne, nq)``.

    Raises ValueError if ``det J <= 1e-12 * prod_b |dx/dxi_b|`` at any point.
    """
    xi, w = element.quadrature(degree)
    dN = element.dshape(xi)
    J = np.tensordot(X, dN, axes=([1], [1])).transpose(1, 3, 0, 2)
    det = _det(J)
    hadamard = np.sqrt(np.einsum("abeq,abeq->beq", J, J)).prod(axis=0)  # >= |det J|
    bad = np.any(det <= 1e-12 * hadamard, axis=1)
    if bad.any():
        idx = np.flatnonzero(bad)
        raise ValueError(
            f"{idx.size} of {len(X)} {element.name} element(s) are inverted or degenerate "
            f"(non-positive Jacobian determinant at a quadrature point); first bad element "
            f"index {idx[0]} (min det J = {det[idx[0]].min():.3g})"
        )
    return xi, w, J, det


def _chunks(n: int):
    for s in range(0, n, _CHUNK):
        yield slice(s, min(s + _CHUNK, n))


# --------------------------------------------------------------------------- physics


def _lame(nu: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    nu = np.asarray(nu, dtype=float)
    if np.any(~np.isfinite(nu)) or np.any(nu <= -1.0) or np.any(nu >= 0.5):
        raise ValueError("Poisson's ratio must satisfy -1 < nu < 0.5")
    return nu / ((1 + nu) * (1 - 2 * nu)), 1.0 / (2 * (1 + nu))


def elasticity_matrix(nu: ArrayLike) -> np.ndarray:
    """Isotropic elasticity matrix for ``E = 1`` in Voigt notation.

    Order ``xx, yy, zz, yz, xz, xy`` with engineering shear strains, so that the strain
    energy density is ``0.5 * eps @ D @ eps``.

    Parameters
    ----------
    nu : float or array_like, shape (ne,)
        Poisson's ratio, ``-1 < nu < 0.5``.

    Returns
    -------
    numpy.ndarray
        ``(6, 6)`` or ``(ne, 6, 6)``; multiply by ``E`` for other moduli.

    Examples
    --------
    >>> D = elasticity_matrix(0.25)
    >>> D[0, :3].round(6).tolist(), round(float(D[3, 3]), 6)
    ([1.2, 0.4, 0.4], 0.4)
    """
    lam, mu = _lame(nu)
    D = np.zeros(lam.shape + (6, 6))
    D[..., :3, :3] = lam[..., None, None]
    i = np.arange(3)
    D[..., i, i] += 2 * mu[..., None]
    D[..., i + 3, i + 3] = mu[..., None]
    return D


def unit_stiffness(element: Element, coords: ArrayLike, nu: ArrayLike = 0.3) -> np.ndarray:
    """Element stiffness matrices for unit Young's modulus (or unit membrane tension).

    Parameters
    ----------
    element : Element
    coords : array_like
        Node coordinates ``(ne, nnodes, 3)`` in element node order; ``tri3`` also accepts
        ``(ne, 3, 2)`` and uses only ``x, y``.
    nu : float or array_like, shape (ne,)
        Poisson's ratio (ignored for ``tri3``).

    Returns
    -------
    numpy.ndarray
        Solids: ``int B^T D(E=1, nu) B dV`` of shape ``(ne, 3*nnodes, 3*nnodes)`` with dofs
        ``[n0x, n0y, n0z, n1x, ...]``.  ``tri3``: ``int grad N . grad N dA``, ``(ne, 3, 3)``.

    Raises
    ------
    ValueError
        For malformed ``coords`` or inverted/degenerate elements.
    """
    X = _coords(element, coords)
    xi, w, J, det = _jacobians(element, X, element.stiffness_degree)
    dN = element.dshape(xi)
    ne, nn, d = len(X), element.nnodes, element.rdim
    nq = len(w)
    scalar = element.dofs_per_node == 1
    if not scalar:
        lam, mu = _lame(nu)
        if lam.ndim and lam.shape != (ne,):
            raise ValueError(f"nu must be a scalar or have shape ({ne},), got {lam.shape}")
        lam, mu = np.broadcast_to(lam, (ne,)), np.broadcast_to(mu, (ne,))
    n = nn * element.dofs_per_node
    K = np.empty((ne, n, n))
    for s in _chunks(ne):
        m = s.stop - s.start
        G = np.matmul(dN, _inv(J[:, :, s], det[s]))  # (m, nq, nn, d) = dN/dx
        G *= np.sqrt(w * det[s])[:, :, None, None]
        if scalar:
            Gs = G.transpose(0, 2, 1, 3).reshape(m, nn, nq * d)
            K[s] = Gs @ Gs.transpose(0, 2, 1)
            continue
        Gv = G.reshape(m, nq, nn * d)
        A = Gv.transpose(0, 2, 1) @ Gv  # A[(i,a),(j,b)] = int G_ia G_jb
        Gs = G.transpose(0, 2, 1, 3).reshape(m, nn, nq * d)
        S = Gs @ Gs.transpose(0, 2, 1)  # int grad N_i . grad N_j
        S *= mu[s, None, None]
        A5 = A.reshape(m, nn, d, nn, d)
        Ks = K[s].reshape(m, nn, d, nn, d)
        np.multiply(A5.transpose(0, 1, 4, 3, 2), mu[s, None, None, None, None], out=Ks)
        A5 *= lam[s, None, None, None, None]
        Ks += A5
        for a in range(d):
            Ks[:, :, a, :, a] += S
    return K


def unit_mass(element: Element, coords: ArrayLike) -> np.ndarray:
    """Consistent element mass matrices for unit density.

    Solids return ``(ne, 3*nnodes, 3*nnodes)`` (block-diagonal per displacement
    component, dof order as in :func:`unit_stiffness`); ``tri3`` returns the
    unit-areal-density scalar mass ``(ne, 3, 3)``.
    """
    X = _coords(element, coords)
    xi, w, _, det = _jacobians(element, X, element.mass_degree)
    N = element.shape(xi)
    nn = element.nnodes
    NN = (N[:, :, None] * N[:, None, :]).reshape(len(w), nn * nn)
    Ms = ((w * det) @ NN).reshape(len(X), nn, nn)
    if element.dofs_per_node == 1:
        return Ms
    M = np.zeros((len(X), nn, 3, nn, 3))
    for a in range(3):
        M[:, :, a, :, a] = Ms
    return M.reshape(len(X), 3 * nn, 3 * nn)


def element_volumes(element: Element, coords: ArrayLike) -> np.ndarray:
    """Element volumes ``(ne,)`` (areas for ``tri3``); exact also for curved elements.

    >>> 6 * element_volumes(TET4, TET4.ref_nodes[None])
    array([1.])
    """
    X = _coords(element, coords)
    _, w, _, det = _jacobians(element, X, element.stiffness_degree)
    return det @ w


def centroids(coords: ArrayLike, element: Element | None = None) -> np.ndarray:
    """Element centroids ``(ne, 3)``.

    The mean of all nodes, or of the vertex nodes if ``element`` is given (equal for
    straight-sided elements).  2-D coordinates are padded with ``z = 0``.
    """
    X = np.asarray(coords, dtype=float)
    if element is not None:
        X = X[:, element.vertex_index]
    c = X.mean(axis=1)
    if c.shape[1] < 3:
        c = np.pad(c, ((0, 0), (0, 3 - c.shape[1])))
    return c
