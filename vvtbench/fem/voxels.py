"""Element -> voxel maps: the grid on which material unknowns live.

>>> from vvtbench.fem.mesh import box_mesh
>>> m = box_mesh((4, 4, 4), (1.0, 1.0, 1.0))
>>> vm = VoxelMap.from_mesh(m, (2, 2, 2))
>>> vm.n_params, np.bincount(vm.element_param).tolist()
(8, [8, 8, 8, 8, 8, 8, 8, 8])
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .mesh import Mesh


@dataclass(frozen=True)
class VoxelGrid:
    """Axis-aligned grid: ``shape`` voxels spanning ``origin`` to ``origin + size``."""

    origin: tuple[float, float, float]
    size: tuple[float, float, float]
    shape: tuple[int, int, int]

    @property
    def spacing(self) -> np.ndarray:
        return np.asarray(self.size) / np.asarray(self.shape)

    @property
    def n_voxels(self) -> int:
        return int(np.prod(self.shape))

    def voxel_of(self, points: np.ndarray) -> np.ndarray:
        """Flat (C-order, index = (i * ny + j) * nz + k) voxel index of each point."""
        ijk = np.floor((np.asarray(points) - self.origin) / self.spacing).astype(np.int64)
        ijk = np.clip(ijk, 0, np.asarray(self.shape) - 1)
        return np.ravel_multi_index(ijk.T, self.shape)

    def centers(self) -> np.ndarray:
        """(n_voxels, 3) voxel centres in flat order."""
        axes = [o + (np.arange(n) + 0.5) * h for o, n, h in zip(self.origin, self.shape,
                                                               self.spacing, strict=True)]
        g = np.meshgrid(*axes, indexing="ij")
        return np.column_stack([a.ravel() for a in g])

    def to_dict(self) -> dict:
        return {"origin": list(self.origin), "size": list(self.size), "shape": list(self.shape)}


@dataclass(frozen=True)
class VoxelMap:
    """Which voxel each element belongs to (by centroid), and which voxels hold elements.

    Attributes
    ----------
    grid : the voxel grid.
    element_voxel : (n_elements,) flat voxel index of each element.
    active : (n_params,) sorted flat indices of voxels that contain at least one element.
    element_param : (n_elements,) index into ``active`` (the unknown each element uses).
    """

    grid: VoxelGrid
    element_voxel: np.ndarray
    active: np.ndarray
    element_param: np.ndarray

    @property
    def n_params(self) -> int:
        return len(self.active)

    @classmethod
    def from_mesh(cls, mesh: Mesh, shape: tuple[int, ...], padding: float = 0.0) -> VoxelMap:
        """Voxelize the mesh's bounding box into ``shape`` (2-D shapes for membranes)."""
        lo, hi = mesh.bounds
        shape3 = tuple(int(s) for s in shape) + (1,) * (3 - len(shape))
        extent = hi - lo
        flat = extent <= 1e-12 * max(extent.max(), 1e-300)
        extent = np.where(flat, 1.0, extent) * (1 + 2 * padding)
        origin = np.where(flat, lo - 0.5, lo - padding * (hi - lo))
        grid = VoxelGrid(tuple(origin.tolist()), tuple(extent.tolist()), shape3)
        return cls.from_grid(mesh, grid)

    @classmethod
    def from_grid(cls, mesh: Mesh, grid: VoxelGrid) -> VoxelMap:
        voxel = grid.voxel_of(mesh.centroids)
        active, param = np.unique(voxel, return_inverse=True)
        return cls(grid, voxel, active, param.ravel())

    @classmethod
    def per_element(cls, mesh: Mesh) -> VoxelMap:
        """Every element its own unknown (the simulation's map)."""
        n = mesh.n_elements
        lo, hi = mesh.bounds
        grid = VoxelGrid(tuple(lo.tolist()), tuple((hi - lo).tolist()), (n, 1, 1))
        idx = np.arange(n)
        return cls(grid, idx, idx, idx)

    def to_grid(self, values: np.ndarray, fill: float = np.nan) -> np.ndarray:
        """Per-parameter ``values`` (n_params,) as a ``grid.shape`` array; empty voxels ``fill``."""
        out = np.full(self.grid.n_voxels, fill, dtype=float)
        out[self.active] = values
        return out.reshape(self.grid.shape)

    def average(self, element_values: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
        """Volume-weighted mean of per-element values in each active voxel: (n_params,)."""
        w = np.ones(len(self.element_param)) if weights is None else np.asarray(weights)
        num = np.bincount(self.element_param, w * element_values, minlength=self.n_params)
        den = np.bincount(self.element_param, w, minlength=self.n_params)
        return num / den


# --------------------------------------------------------------------------- overlap volumes
#: The 6 tets of the Kuhn split of a hex along its 0-7 diagonal (hex8 corner order:
#: index = i + 2 j + 4 k).
_HEX_TETS = np.array([[0, a, a + b, 7] for a in (1, 2, 4) for b in (1, 2, 4) if a != b])
_EPS = 1e-12


def _axis_aligned(coords: np.ndarray, volumes: np.ndarray) -> bool:
    lo, hi = coords.min(axis=1), coords.max(axis=1)
    box = np.prod(hi - lo, axis=1)
    return bool(np.allclose(box, volumes, rtol=1e-9, atol=0.0))


def _hex_box_overlap(lo: np.ndarray, hi: np.ndarray, grid: VoxelGrid):
    """Exact overlap volumes of axis-aligned boxes ``[lo, hi]`` (n_e, 3) with the voxels."""
    origin = np.asarray(grid.origin, dtype=float)
    h = grid.spacing
    shape = np.asarray(grid.shape)
    i0 = np.clip(np.floor((lo - origin) / h).astype(np.int64), 0, shape - 1)
    i1 = np.clip(np.ceil((hi - origin) / h).astype(np.int64) - 1, 0, shape - 1)
    span = (i1 - i0).max(axis=0) + 1
    rows, cols, vals = [], [], []
    e = np.arange(len(lo))
    for off in np.ndindex(*span):
        idx = i0 + np.asarray(off)
        ok = np.all(idx <= i1, axis=1)
        a = origin + idx * h
        b = a + h
        ov = np.clip(np.minimum(hi, b) - np.maximum(lo, a), 0.0, None).prod(axis=1)
        ok &= ov > 0
        rows.append(np.ravel_multi_index(idx[ok].T, grid.shape))
        cols.append(e[ok])
        vals.append(ov[ok])
    return np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)


def _cut(X: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Split simplices ``X`` (n, k, 3) (k = 3 triangles, 4 tets) that the plane ``d = 0``
    crosses (``d`` (n, k): signed distances of the vertices) into simplices on either side."""
    k = X.shape[1]
    pos = d > 0
    count = pos.sum(axis=1)
    out = []

    def point(a, b, da, db):  # where the edge a-b meets the plane
        t = (da / (da - db))[:, None]
        return a + t * (b - a)

    lone = (count == 1) | (count == k - 1)
    if lone.any():  # one vertex alone on its side
        Xl, dl, pl = X[lone], d[lone], pos[lone]
        alone = np.where((count[lone] == 1)[:, None], pl, ~pl)
        order = np.argsort(~alone, axis=1, kind="stable")
        Xl = np.take_along_axis(Xl, order[:, :, None], axis=1)
        dl = np.take_along_axis(dl, order, axis=1)
        a = Xl[:, 0]
        q = [point(a, Xl[:, j], dl[:, 0], dl[:, j]) for j in range(1, k)]
        if k == 4:
            b, c, e = Xl[:, 1], Xl[:, 2], Xl[:, 3]
            out += [np.stack(t, 1) for t in ((a, *q), (b, c, e, q[0]), (c, e, q[0], q[1]),
                                             (e, q[0], q[1], q[2]))]
        else:
            b, c = Xl[:, 1], Xl[:, 2]
            out += [np.stack(t, 1) for t in ((a, *q), (b, c, q[1]), (b, q[1], q[0]))]
    two = (count == 2) & (k == 4)
    if two.any():  # tets with two vertices on each side: two prisms
        Xt, dt = X[two], d[two]
        order = np.argsort(~pos[two], axis=1, kind="stable")
        Xt = np.take_along_axis(Xt, order[:, :, None], axis=1)
        dt = np.take_along_axis(dt, order, axis=1)
        a, b, c, e = (Xt[:, i] for i in range(4))
        pac, pae = point(a, c, dt[:, 0], dt[:, 2]), point(a, e, dt[:, 0], dt[:, 3])
        pbc, pbe = point(b, c, dt[:, 1], dt[:, 2]), point(b, e, dt[:, 1], dt[:, 3])
        for top, bot in (((a, pac, pae), (b, pbc, pbe)), ((c, pac, pbc), (e, pae, pbe))):
            t0, t1, t2 = top
            b0, b1, b2 = bot
            out += [np.stack(t, 1) for t in ((t0, t1, t2, b0), (t1, t2, b0, b1),
                                             (t2, b0, b1, b2))]
    return np.concatenate(out) if out else X[:0]


def _simplex_measure(X: np.ndarray) -> np.ndarray:
    """Volumes of tets (n, 4, 3) or areas of triangles (n, 3, 3)."""
    if X.shape[1] == 4:
        return np.abs(np.linalg.det(X[:, 1:] - X[:, :1])) / 6.0
    return 0.5 * np.linalg.norm(np.cross(X[:, 1] - X[:, 0], X[:, 2] - X[:, 0]), axis=1)


def _clip_to_grid(X: np.ndarray, parent: np.ndarray, grid: VoxelGrid, axes: tuple[int, ...]):
    """Cut simplices along every interior grid plane of ``axes``: each piece then lies in one
    voxel. Returns (pieces, their parent element)."""
    origin = np.asarray(grid.origin, dtype=float)
    h = grid.spacing
    for axis in axes:
        for i in range(1, grid.shape[axis]):
            c = origin[axis] + i * h[axis]
            d = X[:, :, axis] - c
            tol = _EPS * max(h[axis], 1.0)
            cross = (d.max(axis=1) > tol) & (d.min(axis=1) < -tol)
            if not cross.any():
                continue
            pieces = _cut(X[cross], d[cross])
            reps = _piece_parents(X[cross], d[cross], parent[cross])
            X = np.concatenate([X[~cross], pieces])
            parent = np.concatenate([parent[~cross], reps])
    return X, parent


def _piece_parents(X: np.ndarray, d: np.ndarray, parent: np.ndarray) -> np.ndarray:
    """Parents of :func:`_cut`'s pieces, in its output order."""
    k = X.shape[1]
    count = (d > 0).sum(axis=1)
    lone = (count == 1) | (count == k - 1)
    out = [np.tile(parent[lone], 4 if k == 4 else 3)]
    if k == 4:
        out.append(np.tile(parent[count == 2], 6))
    return np.concatenate(out)


def overlap_matrix(source, grid: VoxelGrid, *, element=None, scale=1.0):
    """Volumes of overlap between every voxel of ``grid`` and every element.

    Parameters
    ----------
    source : Mesh or ndarray
        A :class:`~vvtbench.fem.mesh.Mesh`, or element node coordinates ``(n_e, n_nodes,
        dim)`` (``dim`` 2 or 3; 2-D coordinates get ``z = 0``) together with ``element``.
    grid : VoxelGrid
        The voxel grid (membranes: a 2-D grid as :meth:`VoxelMap.from_mesh` makes it, shape
        ``(nx, ny, 1)`` with a slab around the membrane plane).
    element : str or Element, optional
        Element type name (``hex8``, ``hex27``, ``tet4``, ``tet10``, ``tri3``); required when
        ``source`` is an array, ignored for a Mesh.
    scale : float or (3,) array_like
        Multiply the coordinates by this first, per axis (a geometry scale; volumes are then
        those of the scaled body).

    Returns
    -------
    scipy.sparse.csr_matrix
        ``(n_voxels, n_elements)``: entry ``(v, e)`` is the volume (m³; m² for ``tri3``
        membranes) of element ``e`` inside voxel ``v`` (flat C-order index, as
        :meth:`VoxelGrid.voxel_of`). Column ``e`` sums to the element's volume
        (:func:`~vvtbench.fem.elements.element_volumes`), row ``v`` to the volume of the
        body inside voxel ``v`` (0 only for voxels outside the body).

    Notes
    -----
    Exact (to rounding) for straight-sided elements:

    * hexahedra spanning axis-aligned boxes (every ``box_mesh``, ``hex8`` and ``hex27``): the
      product of the three interval overlaps;
    * simplices (``tet4``, ``tet10``, ``tri3``, from their vertex nodes), and other hexahedra
      (split into 6 tets through their corner nodes): cut by every grid plane they cross
      into sub-simplices (a plane cuts a tet into a tet and a prism, or two prisms; a
      triangle into a triangle and a quadrilateral; each split into simplices), so that
      every piece lies in one voxel, which receives its volume.

    Curved elements (quadratic elements with displaced mid-side nodes, warped hexahedra) are
    intersected as their straight-sided counterparts, and each column is then rescaled to the
    element's exact volume, so the error is that of the straight-sided approximation of the
    element's shape.
    """
    import scipy.sparse as sp

    from .elements import element_volumes, get_element
    from .mesh import Mesh

    if isinstance(source, Mesh):
        el = source.element_type
        coords = source.cell_coords
    else:
        if element is None:
            raise ValueError("overlap_matrix: give element= with a coordinate array")
        el = get_element(element) if isinstance(element, str) else element
        coords = np.asarray(source, dtype=float)
    if coords.ndim != 3 or coords.shape[1] != el.nnodes:
        raise ValueError(f"coordinates must be (n_e, {el.nnodes}, dim), got {coords.shape}")
    if coords.shape[2] == 2:
        coords = np.concatenate([coords, np.zeros(coords.shape[:2] + (1,))], axis=2)
    coords = coords * np.broadcast_to(np.asarray(scale, dtype=float), (3,))
    n_e = len(coords)
    vols = element_volumes(el, coords)
    shape = (grid.n_voxels, n_e)
    corners = coords[:, el.vertex_index]
    if el.refdom == "hex":
        if _axis_aligned(corners, vols):
            r, c, v = _hex_box_overlap(coords.min(axis=1), coords.max(axis=1), grid)
            return sp.csr_matrix((v, (r, c)), shape=shape)
        X = corners[:, _HEX_TETS].reshape(-1, 4, 3)
        parent = np.repeat(np.arange(n_e), len(_HEX_TETS))
    else:
        X, parent = corners, np.arange(n_e)
    axes = (0, 1, 2) if X.shape[1] == 4 else tuple(a for a in range(3) if grid.shape[a] > 1)
    X, parent = _clip_to_grid(X, parent, grid, axes)
    w = _simplex_measure(X)
    voxel = grid.voxel_of(X.mean(axis=1))
    straight = np.bincount(parent, w, minlength=n_e)
    w = w * (vols / np.where(straight > 0, straight, 1.0))[parent]
    m = sp.csr_matrix((w, (voxel, parent)), shape=shape)
    m.sum_duplicates()
    return m


def voxel_average(overlap, values: np.ndarray) -> np.ndarray:
    """Volume-weighted mean of per-element ``values`` in every voxel: ``(n_voxels, ...)``.

    ``overlap`` is :func:`overlap_matrix`'s result; voxels that hold no part of the body are
    NaN (every voxel that does, however little, gets a value).
    """
    vals = np.asarray(values, dtype=float)
    vol = np.asarray(overlap.sum(axis=1)).ravel()
    num = overlap @ vals.reshape(len(vals), -1)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = num / vol[:, None]
    out[vol <= 0] = np.nan
    return out.reshape((overlap.shape[0],) + vals.shape[1:])


def default_voxel_shape(scene_or_kind: Any) -> tuple[int, ...]:
    """The paper's inference grids: 8x8x8 for solids, 20x20 for drums (a Scene or its
    geometry kind)."""
    kind = getattr(getattr(scene_or_kind, "geometry", None), "kind", scene_or_kind)
    return (20, 20) if kind == "drum" else (8, 8, 8)
