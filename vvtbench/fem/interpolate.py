"""Interpolation of nodal fields at arbitrary points with a mesh's shape functions."""

from __future__ import annotations

import numpy as np

from .mesh import Mesh

__all__ = ["interpolate_nodal"]


def interpolate_nodal(mesh: Mesh, values: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Interpolate nodal ``values`` (n_nodes, ...) with the mesh's shape functions at
    ``points`` (N, 3) -> (N, ...).

    hex8/hex27: structured axis-aligned grids (box meshes): the containing cell is found by
    bisection on the grid lines, local coordinates are affine. tet4/tet10/tri3: barycentric
    coordinates in candidate cells (nearest centroids by cKDTree); points outside the mesh use
    the best candidate with clipped barycentrics (nearest-cell extrapolation).
    """
    values = np.asarray(values)
    pts = np.atleast_2d(np.asarray(points, dtype=float))
    el = mesh.element_type
    if mesh.element.startswith("hex"):
        cell, xi = _locate_hex(mesh, pts)
    else:
        cell, xi = _locate_simplex(mesh, pts)
    N = el.shape(xi)  # (N, nn)
    vals = values[mesh.cells[cell]]  # (N, nn, ...)
    return np.einsum("pn,pn...->p...", N, vals)


def _locate_hex(mesh: Mesh, pts: np.ndarray):
    el = mesh.element_type
    corners = mesh.points[mesh.cells[:, el.vertex_index]]  # (ne, 8, 3)
    lo, hi = corners.min(axis=1), corners.max(axis=1)
    scale = max(float(np.ptp(mesh.points, axis=0).max()), 1e-300)
    idx = []
    lines = []
    for a in range(3):
        g = np.unique(np.round(lo[:, a] / scale, 9))
        lines.append(g)
        idx.append(np.searchsorted(g, np.round(lo[:, a] / scale, 9)))
    shape = tuple(len(g) for g in lines)
    table = np.full(shape, -1, dtype=np.int64)
    table[idx[0], idx[1], idx[2]] = np.arange(mesh.n_elements)
    ijk = [np.clip(np.searchsorted(lines[a], pts[:, a] / scale + 1e-12, side="right") - 1,
                   0, shape[a] - 1) for a in range(3)]
    cell = table[ijk[0], ijk[1], ijk[2]]
    if np.any(cell < 0):
        raise ValueError("interpolate_nodal: hex meshes must be structured box grids "
                         "(a point falls in a grid cell without an element)")
    xi = 2.0 * (pts - lo[cell]) / (hi[cell] - lo[cell]) - 1.0
    return cell, np.clip(xi, -1.0, 1.0)


def _locate_simplex(mesh: Mesh, pts: np.ndarray, n_candidates: int = 24):
    from scipy.spatial import cKDTree

    el = mesh.element_type
    verts = mesh.points[mesh.cells[:, el.vertex_index]]  # (ne, nv, 3)
    dim = el.rdim
    if dim == 2:
        verts = verts[:, :, :2]
        pts_d = pts[:, :2]
    else:
        pts_d = pts
    tree = cKDTree(verts.mean(axis=1))
    cell = np.zeros(len(pts), dtype=np.int64)
    xi = np.zeros((len(pts), dim))
    todo = np.arange(len(pts))
    kc = min(n_candidates, mesh.n_elements)
    while todo.size:
        _, cand = tree.query(pts_d[todo], k=kc)
        cand = cand.reshape(len(todo), kc)
        V = verts[cand]  # (N, kc, dim+1, dim)
        T = np.swapaxes(V[:, :, 1:] - V[:, :, :1], -1, -2)  # (N, kc, dim, dim)
        rhs = (pts_d[todo][:, None, :] - V[:, :, 0])[..., None]
        lam_rest = np.linalg.solve(T, rhs)[..., 0]  # (N, kc, dim)
        bary = np.concatenate([1 - lam_rest.sum(-1, keepdims=True), lam_rest], axis=-1)
        worst = bary.min(axis=-1)
        best = np.argmax(worst, axis=1)
        rows = np.arange(len(todo))
        inside = worst[rows, best] >= -1e-9
        done = inside | (kc >= mesh.n_elements)  # outside the mesh: nearest cell, clipped
        b = np.clip(bary[rows, best], 0.0, None)
        b /= b.sum(axis=1, keepdims=True)
        cell[todo[done]] = cand[rows, best][done]
        xi[todo[done]] = b[done, 1:]
        todo = todo[~done]
        kc = min(4 * kc, mesh.n_elements)
    return cell, xi
