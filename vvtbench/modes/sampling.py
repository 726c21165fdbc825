"""Image-space modes at mesh vertices: sampling, observation operator, camera from clicks.

Ordering convention (paper Eq. 4, visible vertices only)
--------------------------------------------------------
For ``n`` visible vertices with indices ``visible = [v_0, ..., v_{n-1}]`` (in that order):

* ``gamma`` rows are ``[dx_0, dy_0, dx_1, dy_1, ..., dx_{n-1}, dy_{n-1}]`` in pixels
  (``dx`` right / columns, ``dy`` down / rows).
* the observation operator ``P`` has shape ``(2 n, 3 q)`` for ``q`` mesh vertices, with 3-D
  DOFs interleaved ``[X_0, Y_0, Z_0, X_1, ...]`` (the FEM ordering, ``node * 3 + axis``); rows
  ``2 i, 2 i + 1`` hold the ``2 x 3`` Jacobian of the projection at vertex ``v_i`` in columns
  ``3 v_i .. 3 v_i + 2``.  Hidden vertices simply have no rows, which is equivalent to the
  paper's zero entries placed at the end of ``gamma``.

Clicks file format
------------------
Reference vertex <-> pixel correspondences, pixel coordinates in the :class:`Camera`
convention (``u`` column, ``v`` row, ``(0, 0)`` = centre of the top-left pixel), either

* JSON: ``{"points": [{"vertex": 12, "u": 101.5, "v": 40.25}, ...]}`` (optional extra keys,
  e.g. ``"image_size": [W, H]``, are ignored), or
* CSV with a header line containing the columns ``vertex,u,v`` (any order, extra columns
  ignored; lines starting with ``#`` are comments).
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike, NDArray
from scipy.linalg import rq
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from ..render.camera import Camera

__all__ = [
    "camera_from_clicks",
    "estimate_camera",
    "load_clicks",
    "observation_operator",
    "reprojection_rms",
    "sample_field",
    "sample_modes",
    "vertex_normals",
    "visible_vertices",
]


# --------------------------------------------------------------------------- sampling
def sample_field(field: ArrayLike, uv: ArrayLike) -> NDArray[np.float64]:
    """Bilinear interpolation of ``field`` ``(H, W, ...)`` at pixel positions ``uv``.

    Parameters
    ----------
    field : array_like
        ``(H, W)`` or ``(H, W, C)``; sample ``field[i, j]`` sits at ``(u, v) = (j, i)``.
    uv : array_like
        ``(n, 2)`` positions ``(u, v)``; must lie inside the frame,
        ``-0.5 <= u <= W - 0.5`` and ``-0.5 <= v <= H - 0.5`` (the outer half pixels are
        clamped to the edge samples).

    Returns
    -------
    ndarray
        ``(n,)`` or ``(n, C)`` float64.

    Raises
    ------
    ValueError
        If a position is outside the frame or not finite.
    """
    f = np.asarray(field)
    p = np.asarray(uv, dtype=np.float64)
    if f.ndim < 2:
        raise ValueError(f"field must be at least 2-D (H, W, ...), got {f.shape}")
    if p.ndim != 2 or p.shape[1] != 2:
        raise ValueError(f"uv must be (n, 2), got {p.shape}")
    H, W = f.shape[:2]
    u, v = p[:, 0], p[:, 1]
    bad = ~(np.isfinite(u) & np.isfinite(v))
    bad |= (u < -0.5) | (u > W - 0.5) | (v < -0.5) | (v > H - 0.5)
    if bad.any():
        i = np.flatnonzero(bad)
        raise ValueError(
            f"{i.size} position(s) outside the {W}x{H} frame, "
            f"e.g. index {i[0]} at {p[i[0]].tolist()}"
        )
    u = np.clip(u, 0.0, W - 1.0)
    v = np.clip(v, 0.0, H - 1.0)
    j0 = np.minimum(np.floor(u).astype(np.intp), max(W - 2, 0))
    i0 = np.minimum(np.floor(v).astype(np.intp), max(H - 2, 0))
    j1 = np.minimum(j0 + 1, W - 1)
    i1 = np.minimum(i0 + 1, H - 1)
    tu = (u - j0).reshape(-1, *([1] * (f.ndim - 2)))
    tv = (v - i0).reshape(-1, *([1] * (f.ndim - 2)))
    f = f.astype(np.float64, copy=False)
    top = f[i0, j0] * (1 - tu) + f[i0, j1] * tu
    bot = f[i1, j0] * (1 - tu) + f[i1, j1] * tu
    return top * (1 - tv) + bot * tv


def sample_modes(shapes: ArrayLike, uv: ArrayLike) -> NDArray[np.float64]:
    """Sample image-space modes at vertex pixel positions: ``gamma`` ``(k, 2 n)``.

    Parameters
    ----------
    shapes : array_like
        ``(k, H, W, 2)`` (or one ``(H, W, 2)``) mode fields in px.
    uv : array_like
        ``(n, 2)`` pixel positions of the visible vertices (e.g. ``camera.project(X[vis])``).

    Returns
    -------
    ndarray
        ``(k, 2 n)`` float64, rows ``[dx_0, dy_0, dx_1, dy_1, ...]`` (module notes).
    """
    s = np.asarray(shapes)
    if s.ndim == 3:
        s = s[None]
    if s.ndim != 4 or s.shape[-1] != 2:
        raise ValueError(f"shapes must be (k, H, W, 2), got {s.shape}")
    field = np.moveaxis(s, 0, 2).reshape(*s.shape[1:3], -1)  # (H, W, k*2)
    vals = sample_field(field, uv).reshape(-1, s.shape[0], 2)  # (n, k, 2)
    return np.ascontiguousarray(np.moveaxis(vals, 1, 0).reshape(s.shape[0], -1))


def observation_operator(
    camera: Camera,
    vertices: ArrayLike,
    visible: ArrayLike | None = None,
    *,
    dofs_per_node: int = 3,
    dof_index: ArrayLike | None = None,
    n_columns: int | None = None,
    scale: ArrayLike | float = 1.0,
) -> sp.csr_matrix:
    """Linear map from vertex displacements to image displacements of visible vertices.

    Parameters
    ----------
    camera : Camera
    vertices : array_like
        ``(q, 3)`` rest positions (world units) where the camera sees the vertices.
    visible : array_like, optional
        Indices (or a ``(q,)`` boolean mask) of the visible vertices, in the order of the
        ``gamma`` rows; default all vertices.
    dofs_per_node : int
        3 (solids: x, y, z) or 1 (membranes: the out-of-plane z DOF, the Jacobian's z column).
    dof_index : array_like, optional
        ``(q * dofs_per_node,)`` column of each DOF ``node * dofs_per_node + axis``, negative
        for DOFs that drop out (fixed); default the identity (column = DOF).
    n_columns : int, optional
        Number of columns; default ``q * dofs_per_node`` (or ``max(dof_index) + 1``).
    scale : float or (3,) array_like
        The DOFs live on a geometry scaled by ``scale`` (an inference mesh stretched against
        the true object): the Jacobian is divided by it, ``J diag(1/scale)``.

    Returns
    -------
    scipy.sparse.csr_matrix
        ``(2 n, n_columns)``: rows ``2 i, 2 i + 1`` hold the ``2 x d`` Jacobian of the
        projection at vertex ``visible[i]`` (px per world unit), see the module notes.

    Examples
    --------
    >>> from vvtbench.render.camera import Camera
    >>> cam = Camera.look_at((0, 0, 5), (0, 0, 0), up=(0, 1, 0), fov_y_deg=30, width=64, height=64)
    >>> observation_operator(cam, np.zeros((4, 3)), [1, 3]).shape
    (4, 12)
    """
    X = np.asarray(vertices, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3:
        raise ValueError(f"vertices must be (q, 3), got {X.shape}")
    if dofs_per_node not in (1, 3):
        raise ValueError(f"dofs_per_node must be 1 or 3, got {dofs_per_node}")
    q, d = X.shape[0], dofs_per_node
    idx = _visible_indices(visible, q)
    J = camera.jacobian(X[idx]).reshape(idx.size, 2, 3)
    J = J / np.broadcast_to(np.asarray(scale, dtype=np.float64), (3,))
    if d == 1:
        J = J[:, :, 2:3]
    index = np.arange(q * d) if dof_index is None else np.asarray(dof_index, dtype=np.int64)
    if n_columns is None:
        n_columns = q * d if dof_index is None else int(index.max(initial=-1)) + 1
    n = idx.size
    rows = np.broadcast_to(np.arange(2 * n).reshape(n, 2, 1), (n, 2, d))
    cols = np.broadcast_to(index[idx[:, None] * d + np.arange(d)][:, None, :], (n, 2, d))
    keep = cols >= 0
    return sp.csr_matrix((J[keep], (rows[keep], cols[keep])), shape=(2 * n, n_columns))


def vertex_normals(points: ArrayLike, surface: ArrayLike) -> NDArray[np.float64]:
    """Area-weighted outward normals of the surface vertices (zero for the others).

    ``points`` (q, 3); ``surface`` (F, 3) outward triangles indexing ``points``.
    """
    pts = np.asarray(points, dtype=np.float64)
    tri = np.asarray(surface, dtype=np.int64)
    p = pts[tri]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    out = np.zeros_like(pts)
    for c in range(3):
        np.add.at(out, tri[:, c], n)
    norm = np.linalg.norm(out, axis=1, keepdims=True)
    return np.divide(out, norm, out=np.zeros_like(out), where=norm > 0)


def visible_vertices(
    points: ArrayLike,
    surface: ArrayLike,
    camera: Camera,
    exclude: ArrayLike | None = None,
    depth_buffer: ArrayLike | None = None,
    depth_tol: float = 0.01,
) -> NDArray[np.int64]:
    """Surface vertices seen by ``camera``: on a surface triangle that faces the camera
    (outward normal towards the camera centre), in front of the camera and inside the frame.

    Without ``depth_buffer`` this is exact for convex objects only. ``depth_buffer`` (H, W),
    the rendered rest depth at the pixel centres (a sample's ``image/depth``, ``inf`` on the
    background), also removes self-occluded vertices as the dataset's visibility ground truth
    does: a vertex is kept when its depth is at most ``depth_tol`` times the bounding-box
    diagonal behind the buffer at its (nearest) pixel. ``points`` are where the vertices
    really are (the true object, also under a geometry mismatch).
    """
    pts = np.asarray(points, dtype=np.float64)
    tri = np.asarray(surface, dtype=np.int64)
    p = pts[tri]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    to_cam = camera.center - p.mean(axis=1)
    facing = np.einsum("ij,ij->i", n, to_cam) > 0
    nodes = np.unique(tri[facing])
    uv = camera.project(pts[nodes])
    depth = camera.depth(pts[nodes])
    inside = (
        (depth > 0) & (uv[:, 0] >= -0.5) & (uv[:, 0] <= camera.width - 0.5)
        & (uv[:, 1] >= -0.5) & (uv[:, 1] <= camera.height - 0.5)
    )
    nodes = nodes[inside]
    if depth_buffer is not None and nodes.size:
        buf = np.asarray(depth_buffer, dtype=float)
        px = np.clip(np.rint(uv[inside]).astype(int), 0, [buf.shape[1] - 1, buf.shape[0] - 1])
        diag = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))
        nodes = nodes[depth[inside] <= buf[px[:, 1], px[:, 0]] + depth_tol * diag]
    if exclude is not None and len(exclude):
        nodes = np.setdiff1d(nodes, exclude)
    return nodes


def _visible_indices(visible: ArrayLike | None, q: int) -> NDArray[np.intp]:
    if visible is None:
        return np.arange(q)
    v = np.asarray(visible)
    if v.dtype == bool:
        if v.shape != (q,):
            raise ValueError(f"visible mask must have shape ({q},), got {v.shape}")
        return np.flatnonzero(v)
    v = v.astype(np.intp).ravel()
    if v.size and (v.min() < 0 or v.max() >= q):
        raise ValueError(f"visible indices must be in [0, {q}), got range [{v.min()}, {v.max()}]")
    return v


# --------------------------------------------------------------------------- camera estimation
def _normalizer(x: NDArray[np.float64]) -> NDArray[np.float64]:
    """Hartley similarity: centroid to 0, mean distance sqrt(dim)."""
    d = x.shape[1]
    c = x.mean(axis=0)
    s = np.mean(np.linalg.norm(x - c, axis=1))
    if s <= 0:
        raise ValueError("points are all identical")
    s = math.sqrt(d) / s
    T = np.eye(d + 1)
    T[:d, :d] *= s
    T[:d, d] = -s * c
    return T


def _dlt(X: NDArray[np.float64], uv: NDArray[np.float64]) -> NDArray[np.float64]:
    """Normalised DLT estimate of the 3x4 projection matrix."""
    n = X.shape[0]
    T3, T2 = _normalizer(X), _normalizer(uv)
    Xh = np.c_[X, np.ones(n)] @ T3.T
    xh = np.c_[uv, np.ones(n)] @ T2.T
    A = np.zeros((2 * n, 12))
    A[0::2, 0:4] = Xh
    A[0::2, 8:12] = -xh[:, 0:1] * Xh
    A[1::2, 4:8] = Xh
    A[1::2, 8:12] = -xh[:, 1:2] * Xh
    _, s, vt = np.linalg.svd(A)
    if s[-2] <= 1e-9 * s[0]:
        raise ValueError("degenerate correspondences (coplanar or collinear 3-D points?)")
    Pn = vt[-1].reshape(3, 4)
    return np.linalg.solve(T2, Pn @ T3)


def _decompose(P: NDArray[np.float64]) -> tuple[NDArray, NDArray, NDArray]:
    """``P ~ K [R | t]`` with positive focal lengths and ``det(R) = +1``."""
    M = P[:, :3]
    if np.linalg.det(M) < 0:
        P = -P
        M = -M
    K, R = rq(M)
    sgn = np.sign(np.diag(K))
    sgn[sgn == 0] = 1.0
    D = np.diag(sgn)
    K, R = K @ D, D @ R
    t = np.linalg.solve(K, P[:, 3])
    scale = K[2, 2]
    return K / scale, R, t / scale


def _params_to_camera(x: NDArray[np.float64], width: int, height: int) -> Camera:
    fx, fy, cx, cy = x[:4]
    R = Rotation.from_rotvec(x[4:7]).as_matrix()
    K = [[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]
    return Camera(K=K, R=R, t=x[7:10], width=width, height=height)


def _project(x: NDArray[np.float64], X: NDArray[np.float64]) -> NDArray[np.float64]:
    fx, fy, cx, cy = x[:4]
    Xc = Rotation.from_rotvec(x[4:7]).apply(X) + x[7:10]
    return np.c_[fx * Xc[:, 0] / Xc[:, 2] + cx, fy * Xc[:, 1] / Xc[:, 2] + cy]


def reprojection_rms(camera: Camera, X: ArrayLike, uv: ArrayLike) -> float:
    """Root-mean-square reprojection error (px) over points, ``sqrt(mean |pi(X) - uv|**2)``."""
    r = camera.project(np.asarray(X, dtype=np.float64)) - np.asarray(uv, dtype=np.float64)
    return float(np.sqrt(np.mean(np.sum(r**2, axis=1))))


def estimate_camera(
    X: ArrayLike, uv: ArrayLike, width: int, height: int, *, refine: bool = True
) -> tuple[Camera, float]:
    """Camera from >= 6 vertex <-> pixel correspondences.

    Normalised DLT (Hartley & Zisserman, Alg. 7.1), RQ decomposition into ``K [R | t]``, then
    Levenberg--Marquardt refinement of the reprojection error over ``fx, fy, cx, cy`` (skew
    fixed to 0), the rotation (Rodrigues vector) and ``t``.

    Parameters
    ----------
    X : array_like
        ``(n, 3)`` world points (not all coplanar), ``n >= 6``.
    uv : array_like
        ``(n, 2)`` pixel positions (Camera convention).
    width, height : int
        Image size of the returned camera.
    refine : bool, default True
        Run the nonlinear refinement (otherwise the DLT camera with its skew set to 0).

    Returns
    -------
    camera : Camera
    rms : float
        RMS reprojection error (px), see :func:`reprojection_rms`.

    Raises
    ------
    ValueError
        Too few or degenerate points, or points behind the estimated camera.
    """
    Xa = np.asarray(X, dtype=np.float64)
    ua = np.asarray(uv, dtype=np.float64)
    if Xa.ndim != 2 or Xa.shape[1] != 3 or ua.shape != (Xa.shape[0], 2):
        raise ValueError(f"need X (n, 3) and uv (n, 2), got {Xa.shape} and {ua.shape}")
    if Xa.shape[0] < 6:
        raise ValueError(f"camera estimation needs >= 6 correspondences, got {Xa.shape[0]}")
    if not (np.all(np.isfinite(Xa)) and np.all(np.isfinite(ua))):
        raise ValueError("correspondences must be finite")
    K, R, t = _decompose(_dlt(Xa, ua))
    depth = Xa @ R[2] + t[2]
    if np.any(depth <= 0):
        raise ValueError(
            f"{int(np.sum(depth <= 0))} point(s) lie behind the DLT camera: inconsistent clicks?"
        )
    x0 = np.r_[K[0, 0], K[1, 1], K[0, 2], K[1, 2], Rotation.from_matrix(R).as_rotvec(), t]
    if refine:
        res = least_squares(
            lambda x: (_project(x, Xa) - ua).ravel(), x0, method="lm", x_scale="jac"
        )
        x0 = res.x
    cam = _params_to_camera(x0, width, height)
    return cam, reprojection_rms(cam, Xa, ua)


# --------------------------------------------------------------------------- clicks files
def load_clicks(path: str | Path) -> tuple[NDArray[np.intp], NDArray[np.float64]]:
    """Read a clicks file (JSON or CSV, see the module notes).

    Returns
    -------
    vertices : ndarray
        ``(n,)`` vertex indices.
    uv : ndarray
        ``(n, 2)`` pixel positions.

    Raises
    ------
    ValueError
        Naming the file and the offending entry / key.
    """
    path = Path(path)
    text = path.read_text()
    rows: list[tuple[object, object, object, str]] = []
    if path.suffix.lower() == ".json" or text.lstrip().startswith("{"):
        try:
            doc = json.loads(text)
        except json.JSONDecodeError as e:
            raise ValueError(f"{path}: invalid JSON: {e}") from None
        if not isinstance(doc, dict) or "points" not in doc:
            raise ValueError(f"{path}: missing key 'points' (a list of {{vertex, u, v}})")
        pts = doc["points"]
        if not isinstance(pts, list):
            raise ValueError(
                f"{path}: 'points' must be a list of {{vertex, u, v}} objects, "
                f"got {type(pts).__name__}"
            )
        for i, p in enumerate(pts):
            where = f"points[{i}]"
            if not isinstance(p, dict):
                raise ValueError(f"{path}: {where} must be an object with keys vertex, u, v")
            for key in ("vertex", "u", "v"):
                if key not in p:
                    raise ValueError(f"{path}: {where} is missing key '{key}'")
            rows.append((p["vertex"], p["u"], p["v"], where))
    else:
        lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
        reader = csv.DictReader(lines)
        fields = [f.strip() for f in (reader.fieldnames or [])]
        reader.fieldnames = fields
        for key in ("vertex", "u", "v"):
            if key not in fields:
                raise ValueError(f"{path}: CSV header lacks column '{key}' (need vertex,u,v)")
        for i, r in enumerate(reader):
            rows.append((r["vertex"], r["u"], r["v"], f"data line {i + 1}"))
    verts, uv = [], []
    for vert, u, v, where in rows:
        try:
            fv = float(vert)
            if fv != int(fv) or fv < 0:
                raise ValueError
            verts.append(int(fv))
        except (TypeError, ValueError):
            raise ValueError(
                f"{path}: {where}: 'vertex' must be a non-negative integer, got {vert!r}"
            ) from None
        pair = []
        for key, val in (("u", u), ("v", v)):
            try:
                x = float(val)
            except (TypeError, ValueError):
                raise ValueError(
                    f"{path}: {where}: '{key}' must be a number, got {val!r}"
                ) from None
            if not math.isfinite(x):
                raise ValueError(f"{path}: {where}: '{key}' must be finite, got {val!r}")
            pair.append(x)
        uv.append(pair)
    if len(set(verts)) != len(verts):
        dup = sorted({v for v in verts if verts.count(v) > 1})
        raise ValueError(f"{path}: duplicate vertex indices {dup} (one click per vertex)")
    return np.array(verts, dtype=np.intp), np.array(uv, dtype=np.float64).reshape(-1, 2)


def camera_from_clicks(
    path: str | Path, vertices: ArrayLike, width: int, height: int
) -> tuple[Camera, float]:
    """Estimate the camera from a clicks file and the mesh vertices ``(q, 3)``.

    Parameters
    ----------
    path : str or Path
        Clicks file (module notes); ``vertex`` indexes the rows of ``vertices``.
    vertices : array_like
        ``(q, 3)`` vertex positions (world units).
    width, height : int
        Image size (px) of the video the clicks were made on.

    Returns
    -------
    camera : Camera
    rms : float
        RMS reprojection error (px) over the clicked points.

    Raises
    ------
    ValueError
        Malformed file (see :func:`load_clicks`), fewer than 6 pairs, a vertex index out of
        range, or degenerate / inconsistent clicks; the message names the file.
    """
    idx, uv = load_clicks(path)
    V = np.asarray(vertices, dtype=np.float64)
    if idx.size < 6:
        raise ValueError(
            f"{path}: camera estimation needs >= 6 vertex <-> pixel pairs (non-coplanar "
            f"vertices), got {idx.size}"
        )
    if idx.max() >= V.shape[0]:
        raise ValueError(
            f"{path}: 'vertex' {int(idx.max())} out of range: the mesh has {V.shape[0]} "
            f"vertices (allowed 0 .. {V.shape[0] - 1})"
        )
    try:
        return estimate_camera(V[idx], uv, width, height)
    except ValueError as error:
        raise ValueError(f"{path}: {error}") from None
