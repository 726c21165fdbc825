"""Meshes: structured hex boxes, tetrahedralized surfaces, and membranes.

A :class:`Mesh` holds node coordinates, element connectivity in the node order of
:mod:`vvtbench.fem.elements`, named node sets and an outward-facing triangulated surface (for
rendering and for picking surface vertices). Meshes are plain data; functions build them.

>>> m = box_mesh((2, 1, 1), (0.02, 0.01, 0.01))
>>> m.points.shape, m.cells.shape, m.element, len(m.node_sets["bottom"])
((12, 3), (2, 8), 'hex8', 6)
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib.resources
import json
import os
import tempfile
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .elements import TET10_EDGES, Element, get_element

BOX_FACE_SETS = ("bottom", "top", "left", "right", "front", "back")


@dataclass(frozen=True)
class Mesh:
    """Nodes, elements, named node sets and an outward surface triangulation.

    Attributes
    ----------
    points : (N, 3) float64, metres.
    cells : (n_elements, nodes_per_element) int64, node order of ``element``.
    element : element name, one of ``vvtbench.fem.elements.ELEMENTS``.
    node_sets : name -> sorted int64 node indices.
    surface : (F, 3) int64 triangles with outward normals (membranes: normal +z).
    """

    points: np.ndarray
    cells: np.ndarray
    element: str
    node_sets: dict[str, np.ndarray] = field(default_factory=dict)
    surface: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), dtype=np.int64))

    @property
    def element_type(self) -> Element:
        return get_element(self.element)

    @property
    def n_nodes(self) -> int:
        return len(self.points)

    @property
    def n_elements(self) -> int:
        return len(self.cells)

    @property
    def dofs_per_node(self) -> int:
        return self.element_type.dofs_per_node

    @property
    def n_dofs(self) -> int:
        return self.n_nodes * self.dofs_per_node

    @property
    def cell_coords(self) -> np.ndarray:
        """(n_elements, nodes_per_element, 3) node coordinates per element."""
        return self.points[self.cells]

    @property
    def centroids(self) -> np.ndarray:
        """(n_elements, 3) mean of each element's corner nodes."""
        corners = self.cells[:, self.element_type.vertex_index]
        return self.points[corners].mean(axis=1)

    @property
    def surface_nodes(self) -> np.ndarray:
        """Sorted indices of the nodes on the rendered surface."""
        return np.unique(self.surface)

    @property
    def bounds(self) -> np.ndarray:
        return np.array([self.points.min(axis=0), self.points.max(axis=0)])

    def node_set(self, name: str) -> np.ndarray:
        if name not in self.node_sets:
            raise KeyError(
                f"no node set '{name}' on this {self.element} mesh; "
                f"available: {', '.join(sorted(self.node_sets))}"
            )
        return self.node_sets[name]

    def dofs_of(self, nodes: np.ndarray) -> np.ndarray:
        """Global DOF indices (node-major: node * dofs_per_node + component) of ``nodes``."""
        d = self.dofs_per_node
        return (np.asarray(nodes)[:, None] * d + np.arange(d)).ravel()

    def with_node_sets(self, extra: dict[str, np.ndarray]) -> Mesh:
        sets = dict(self.node_sets)
        sets.update({k: np.unique(np.asarray(v, dtype=np.int64)) for k, v in extra.items()})
        return Mesh(self.points, self.cells, self.element, sets, self.surface)


def box_mesh(
    cells: tuple[int, int, int],
    size: tuple[float, float, float] = (0.05, 0.05, 0.05),
    order: int = 1,
) -> Mesh:
    """Structured hex mesh of ``[0, size]``: ``order`` 1 gives hex8, 2 gives hex27.

    Node sets: bottom (z = 0), top, left (x = 0), right, front (y = 0), back, all.
    """
    if order not in (1, 2):
        raise ValueError(f"box order must be 1 (hex8) or 2 (hex27), got {order}")
    nx, ny, nz = (int(c) for c in cells)
    if min(nx, ny, nz) < 1:
        raise ValueError(f"box cells must be >= 1 in every direction, got {cells}")
    p = order
    shape = (p * nx + 1, p * ny + 1, p * nz + 1)
    axes = [np.linspace(0.0, s, n) for s, n in zip(size, shape, strict=True)]
    gx, gy, gz = np.meshgrid(*axes, indexing="ij")
    points = np.column_stack([a.ravel(order="F") for a in (gx, gy, gz)])

    def node_id(i, j, k):
        return i + shape[0] * (j + shape[1] * k)

    a, b, c = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")
    a, b, c = (v.ravel(order="F") for v in (a, b, c))
    li, lj, lk = np.meshgrid(*(np.arange(p + 1),) * 3, indexing="ij")
    li, lj, lk = (v.ravel(order="F") for v in (li, lj, lk))
    conn = node_id(p * a[:, None] + li, p * b[:, None] + lj, p * c[:, None] + lk)
    element = "hex8" if order == 1 else "hex27"
    tol = 1e-9 * max(size)
    sets = {
        "bottom": np.flatnonzero(points[:, 2] < tol),
        "top": np.flatnonzero(points[:, 2] > size[2] - tol),
        "left": np.flatnonzero(points[:, 0] < tol),
        "right": np.flatnonzero(points[:, 0] > size[0] - tol),
        "front": np.flatnonzero(points[:, 1] < tol),
        "back": np.flatnonzero(points[:, 1] > size[1] - tol),
        "all": np.arange(len(points)),
    }
    surface = boundary_surface(points, conn, element)
    return Mesh(points, conn.astype(np.int64), element, sets, surface)


def _hex_local_faces(order: int) -> list[np.ndarray]:
    """Each hex face as a (p+1, p+1) grid of local node indices (lexicographic elements)."""
    n = order + 1
    idx = np.arange(n**3).reshape(n, n, n, order="F")
    return [idx[0], idx[-1], idx[:, 0], idx[:, -1], idx[:, :, 0], idx[:, :, -1]]


def _grid_triangles(grid: np.ndarray) -> np.ndarray:
    """Triangles (T, 3) covering a (q, q) grid of node ids, two per sub-quad."""
    a, b = grid[:-1, :-1].ravel(), grid[1:, :-1].ravel()
    c, d = grid[1:, 1:].ravel(), grid[:-1, 1:].ravel()
    return np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])


def _tet_local_faces(order: int) -> list[np.ndarray]:
    """Each tet face as local triangles (order 2: four sub-triangles over midside nodes)."""
    faces = [(1, 2, 3), (0, 3, 2), (0, 1, 3), (0, 2, 1)]
    if order == 1:
        return [np.array([f]) for f in faces]
    mid = {frozenset(e): 4 + i for i, e in enumerate(TET10_EDGES.tolist())}
    out = []
    for a, b, c in faces:
        ab, bc, ca = mid[frozenset((a, b))], mid[frozenset((b, c))], mid[frozenset((c, a))]
        out.append(np.array([[a, ab, ca], [ab, b, bc], [ca, bc, c], [ab, bc, ca]]))
    return out


def boundary_surface(points: np.ndarray, cells: np.ndarray, element: str) -> np.ndarray:
    """Outward triangles of the faces that belong to exactly one element."""
    el = get_element(element)
    if el.rdim == 2:
        tri = cells[:, el.vertex_index]
        normal_z = _triangle_normals(points, tri)[:, 2]
        return np.where(normal_z[:, None] < 0, tri[:, [0, 2, 1]], tri)
    if element.startswith("hex"):
        order = 1 if element == "hex8" else 2
        local = _hex_local_faces(order)
        patches = [_grid_triangles(g) for g in local]
        corner_sets = [np.array([g[0, 0], g[-1, 0], g[-1, -1], g[0, -1]]) for g in local]
    else:
        order = 1 if element == "tet4" else 2
        patches = _tet_local_faces(order)
        corner_sets = [np.array(f) for f in [(1, 2, 3), (0, 3, 2), (0, 1, 3), (0, 2, 1)]]
    keys = np.concatenate([np.sort(cells[:, cs], axis=1) for cs in corner_sets])
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    on_boundary = (counts[inverse.ravel()] == 1).reshape(len(corner_sets), len(cells))
    centre = points[cells[:, el.vertex_index]].mean(axis=1)
    tris = []
    for f, patch in enumerate(patches):
        owners = np.flatnonzero(on_boundary[f])
        if owners.size == 0:
            continue
        t = cells[owners][:, patch]
        normals = _triangle_normals(points, t.reshape(-1, 3)).reshape(t.shape)
        outward = points[cells[owners][:, corner_sets[f]]].mean(axis=1) - centre[owners]
        flip = np.einsum("fk,fk->f", normals.sum(axis=1), outward) < 0
        t[flip] = t[flip][..., [0, 2, 1]]
        tris.append(t.reshape(-1, 3))
    return np.concatenate(tris).astype(np.int64) if tris else np.zeros((0, 3), np.int64)


def _triangle_normals(points: np.ndarray, tri: np.ndarray) -> np.ndarray:
    p = points[tri]
    return np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])


def drum_mesh(shape: str = "square", size: float = 0.1016, cells: int = 40) -> Mesh:
    """Triangulated membrane in the plane z = 0, lowest bounding-box corner at the origin.

    ``square``: side ``size``, ``cells`` divisions per side, each square cut into two
    triangles with alternating diagonals. ``circle``: diameter ``size``, ``cells`` rings of
    6k nodes each, Delaunay-triangulated. Node sets: rim (the fixed frame), all.
    """
    if cells < 2:
        raise ValueError(f"drum cells must be >= 2, got {cells}")
    if shape == "square":
        n = cells
        xs = np.linspace(0.0, size, n + 1)
        gx, gy = np.meshgrid(xs, xs, indexing="ij")
        points = np.column_stack([gx.ravel(order="F"), gy.ravel(order="F"), np.zeros(gx.size)])
        i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
        i, j = i.ravel(order="F"), j.ravel(order="F")
        v00, v10 = i + (n + 1) * j, i + 1 + (n + 1) * j
        v01, v11 = v00 + n + 1, v10 + n + 1
        even = (i + j) % 2 == 0
        tri = np.concatenate([
            np.where(even[:, None], np.column_stack([v00, v10, v11]),
                     np.column_stack([v00, v10, v01])),
            np.where(even[:, None], np.column_stack([v00, v11, v01]),
                     np.column_stack([v10, v11, v01])),
        ])
        tol = 1e-9 * size
        rim = np.flatnonzero(
            (points[:, 0] < tol) | (points[:, 1] < tol)
            | (points[:, 0] > size - tol) | (points[:, 1] > size - tol)
        )
    elif shape == "circle":
        from scipy.spatial import Delaunay

        r = size / 2
        rings = [np.zeros((1, 2))]
        for k in range(1, cells + 1):
            t = 2 * np.pi * (np.arange(6 * k) + 0.5 * (k % 2)) / (6 * k)
            rings.append(k * r / cells * np.column_stack([np.cos(t), np.sin(t)]))
        xy = np.concatenate(rings)
        tri = Delaunay(xy).simplices
        points = np.column_stack([xy + r, np.zeros(len(xy))])
        rim = np.arange(len(xy) - 6 * cells, len(xy))
    else:
        raise ValueError(f"drum shape must be 'square' or 'circle', got {shape!r}")
    tri = tri.astype(np.int64)
    surface = boundary_surface(points, tri, "tri3")
    sets = {"rim": np.sort(rim), "all": np.arange(len(points))}
    return Mesh(points, surface.copy(), "tri3", sets, surface)


def builtin_surface_path(name: str) -> Path:
    """Path of a surface mesh that ships with an installed package (``bunny``)."""
    if name == "bunny":
        p = importlib.resources.files("pymeshlab") / "tests" / "sample_meshes" / "bunny.obj"
        if not p.is_file():
            raise FileNotFoundError(
                "the Stanford bunny is read from the pymeshlab wheel, but "
                f"{p} is missing; reinstall pymeshlab (pip install pymeshlab)"
            )
        return Path(str(p))
    raise ValueError(f"unknown built-in mesh {name!r}; built-in meshes: bunny")


def load_surface(
    path: str | Path,
    up_axis: str = "z",
    scale_to: float | None = None,
    target_faces: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Load a closed surface, turn ``up_axis`` to +z, scale, simplify; lowest corner at 0."""
    import trimesh

    path = builtin_surface_path(str(path)) if str(path) == "bunny" else Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: surface mesh file not found")
    try:
        surf = trimesh.load(str(path), force="mesh", process=True)
    except Exception as error:
        raise ValueError(f"{path}: cannot read a surface mesh: {error}") from None
    if len(surf.faces) == 0:
        raise ValueError(f"{path}: the file holds no triangles")
    if not surf.is_watertight:
        raise ValueError(f"{path}: the surface is not closed (watertight); cannot fill it")
    v = np.asarray(surf.vertices, dtype=float)
    f = np.asarray(surf.faces, dtype=np.int64)
    if up_axis == "y":
        v = v[:, [0, 2, 1]] * np.array([1.0, -1.0, 1.0])
    elif up_axis == "x":
        v = v[:, [1, 2, 0]]
    elif up_axis != "z":
        raise ValueError(f"up_axis must be x, y or z, got {up_axis!r}")
    if target_faces is not None and len(f) > target_faces:
        import fast_simplification

        v, f = fast_simplification.simplify(
            v.astype(np.float32), f.astype(np.int32), target_reduction=1 - target_faces / len(f)
        )[:2]
        v = np.asarray(v, dtype=float)
        f = np.asarray(f, dtype=np.int64)
    v = v - v.min(axis=0)
    if scale_to is not None:
        v *= scale_to / v.max()
    return v, f


def tet_mesh(
    vertices: np.ndarray,
    faces: np.ndarray,
    edge_length_fac: float = 0.1,
    epsilon: float = 5e-3,
    stop_energy: float = 10.0,
    coarsen: bool = False,
    order: int = 1,
    bottom_tol: float = 0.02,
) -> Mesh:
    """Tetrahedralize a closed surface with pytetwild; tet4, or tet10 with ``order`` 2.

    pytetwild's output differs from run to run (even single-threaded), so a surface and
    settings that vvtbench ships a tetrahedralization for (``scenes/meshes/``: the built-in
    bunny at the settings of the shipped scenes and family) always get that mesh, on every
    machine and whatever the pytetwild version; any other is cached on disk, keyed by the
    surface, the settings and the pytetwild version (see :func:`mesh_cache_dir`), so the
    same scene gets the same mesh on a machine. A sample stores the mesh it used.

    Node sets: bottom (nodes within ``bottom_tol`` of the height above the lowest point), all.
    """
    import pytetwild

    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    faces = np.ascontiguousarray(faces, dtype=np.int32)
    settings = dict(edge_length_fac=edge_length_fac, epsilon=epsilon, stop_energy=stop_energy,
                    coarsen=coarsen)
    digest = hashlib.sha256(vertices.tobytes() + faces.tobytes())
    digest.update(json.dumps(settings, sort_keys=True).encode())
    shipped = shipped_mesh_dir() / f"tetwild-{digest.hexdigest()[:24]}.npz"
    digest.update(getattr(pytetwild, "__version__", "").encode())
    cache = mesh_cache_dir() / f"tetwild-{digest.hexdigest()[:24]}.npz"
    loaded = None
    if shipped.is_file():
        loaded = _load_tets(shipped)
        if isinstance(loaded, str):
            raise ValueError(f"{shipped}: the shipped tetrahedralization is damaged ({loaded}); "
                             "reinstall vvtbench")
    elif cache.is_file() or cache.is_symlink():
        loaded = _load_tets(cache)
        if isinstance(loaded, str):  # truncated or damaged: rebuilt below
            cache.unlink(missing_ok=True)
            loaded = None
    if loaded is not None:
        pts, tets = loaded
    else:
        with _scratch_cwd():  # fTetWild writes __tracked_surface.stl into the working directory
            pts, tets = pytetwild.tetrahedralize(vertices, faces, quiet=True, **settings)
        tets = np.asarray(tets, dtype=np.int64)
        used, tets = np.unique(tets, return_inverse=True)
        tets = tets.reshape(-1, 4)
        pts = np.asarray(pts, dtype=float)[used]
        from ..io.files import write_npz

        cache.parent.mkdir(parents=True, exist_ok=True)
        write_npz(cache, {"points": pts, "tets": tets}, compressed=False)
    return tets_to_mesh(pts, tets, order=order, bottom_tol=bottom_tol)


def _load_tets(path: Path) -> tuple[np.ndarray, np.ndarray] | str:
    """The points and tets of a cached tetrahedralization, or what is wrong with the file
    (unreadable, truncated, a link, arrays of the wrong shape or indices out of range)."""
    if path.is_symlink():
        return "a symbolic link"
    try:
        with np.load(path, allow_pickle=False) as z:
            pts, tets = np.asarray(z["points"]), np.asarray(z["tets"])
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as error:
        return f"unreadable: {type(error).__name__}: {error}"
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 4 or not np.isfinite(pts).all():
        return f"points of shape {pts.shape} (allowed: (n >= 4, 3), finite)"
    if tets.ndim != 2 or tets.shape[1] != 4 or not len(tets) or tets.dtype.kind not in "iu":
        return f"tets of shape {tets.shape} and dtype {tets.dtype} (allowed: (m >= 1, 4) ints)"
    if tets.min() < 0 or tets.max() >= len(pts):
        return f"tets index nodes outside 0..{len(pts) - 1}"
    return pts, tets


@contextlib.contextmanager
def _scratch_cwd():
    old = os.getcwd()
    with tempfile.TemporaryDirectory(prefix="vvtbench-tetwild-") as tmp:
        os.chdir(tmp)
        try:
            yield
        finally:
            os.chdir(old)


def shipped_mesh_dir() -> Path:
    """The tetrahedralizations vvtbench ships (``scenes/meshes``), keyed by surface and
    settings only; see :func:`tet_mesh`."""
    from ..scene.scene import SCENES_DIR

    return SCENES_DIR / "meshes"


def mesh_cache_dir() -> Path:
    """Where tetrahedralizations are cached: $VVTBENCH_CACHE/meshes, else
    ~/.cache/vvtbench/meshes."""
    root = os.environ.get("VVTBENCH_CACHE") or os.path.join(
        os.path.expanduser("~"), ".cache", "vvtbench"
    )
    return Path(root) / "meshes"


def tets_to_mesh(
    points: np.ndarray, tets: np.ndarray, order: int = 1, bottom_tol: float = 0.02
) -> Mesh:
    """A tet4/tet10 Mesh from tetrahedra, with positive orientation and midside nodes."""
    p = points[tets]
    vol = np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0])
    tets = tets.copy()
    tets[vol < 0] = tets[vol < 0][:, [0, 2, 1, 3]]
    if np.any(np.abs(vol) < 1e-18):
        raise ValueError(f"{np.sum(np.abs(vol) < 1e-18)} degenerate tetrahedra (zero volume)")
    if order == 2:
        edges = np.sort(tets[:, TET10_EDGES].reshape(-1, 2), axis=1)
        uniq, inverse = np.unique(edges, axis=0, return_inverse=True)
        mids = points[uniq].mean(axis=1)
        tets = np.hstack([tets, len(points) + inverse.reshape(-1, 6)])
        points = np.vstack([points, mids])
    elif order != 1:
        raise ValueError(f"tet order must be 1 (tet4) or 2 (tet10), got {order}")
    element = "tet4" if order == 1 else "tet10"
    z = points[:, 2]
    height = z.max() - z.min()
    sets = {
        "bottom": np.flatnonzero(z <= z.min() + bottom_tol * height),
        "all": np.arange(len(points)),
    }
    return Mesh(points, tets, element, sets, boundary_surface(points, tets, element))
