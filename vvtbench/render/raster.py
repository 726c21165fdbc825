"""Render-free rasterization of a triangle surface through a :class:`Camera`.

For every output pixel centre this finds the front-most surface triangle and the
perspective-correct barycentric coordinates of the surface point seen there.  Any per-vertex
quantity (e.g. an image-space mode, the Jacobian-mapped motion of each vertex) then becomes a
dense image field by barycentric interpolation, exactly and without rendering noise:
:func:`interpolate`.

Conventions are those of :mod:`vvtbench.render.camera`: pixel ``(row i, column j)`` has its
centre at ``(u, v) = (j, i)``.  A pixel is covered when its centre lies inside (or on the edge
of) a triangle; the depth test keeps the smallest camera-frame depth.

>>> import numpy as np
>>> from vvtbench.render.camera import Camera
>>> cam = Camera.look_at((0, 0, 2.0), (0, 0, 0), up=(0, 1, 0), fx=20.0, width=16, height=16)
>>> V = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0.0]])
>>> r = rasterize(cam, V, np.array([[0, 1, 2], [0, 2, 3]]))
>>> bool((r.triangle >= 0).all()), np.allclose(r.barycentric.sum(-1), 1.0)
(True, True)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .camera import Camera

__all__ = ["Raster", "interpolate", "rasterize"]


@dataclass(frozen=True)
class Raster:
    """Per-pixel surface correspondence.

    Attributes
    ----------
    triangle : (H, W) int32
        Index of the front-most triangle covering the pixel centre, -1 on background.
    barycentric : (H, W, 3) float32
        Perspective-correct barycentric weights of the triangle's three vertices
        (0 on background); they sum to 1 on covered pixels.
    depth : (H, W) float32
        Camera-frame depth of the surface point (m), ``inf`` on background.
    """

    triangle: np.ndarray
    barycentric: np.ndarray
    depth: np.ndarray

    @property
    def mask(self) -> np.ndarray:
        return self.triangle >= 0


def rasterize(camera: Camera, vertices: np.ndarray, triangles: np.ndarray) -> Raster:
    """Rasterize ``triangles`` (F, 3) over ``vertices`` (N, 3, world) at the camera's size."""
    V = np.asarray(vertices, dtype=np.float64)
    T = np.asarray(triangles, dtype=np.int64)
    H, W = camera.height, camera.width
    uv = camera.project(V)
    z = camera.depth(V)
    zbuf = np.full((H, W), np.inf)
    tri = np.full((H, W), -1, dtype=np.int32)
    bary = np.zeros((H, W, 3), dtype=np.float64)
    P = uv[T]  # (F, 3, 2)
    Z = z[T]
    lo = np.ceil(P.min(axis=1) - 1e-9).astype(np.int64)
    hi = np.floor(P.max(axis=1) + 1e-9).astype(np.int64)
    lo = np.maximum(lo, 0)
    hi = np.minimum(hi, [W - 1, H - 1])
    x0, y0 = P[:, 0, 0], P[:, 0, 1]
    e1 = P[:, 1] - P[:, 0]
    e2 = P[:, 2] - P[:, 0]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    todo = np.flatnonzero((hi[:, 0] >= lo[:, 0]) & (hi[:, 1] >= lo[:, 1]) & (np.abs(det) > 1e-12)
                          & np.all(Z > 0, axis=1))
    eps = 1e-9
    for f in todo:
        us = np.arange(lo[f, 0], hi[f, 0] + 1)
        vs = np.arange(lo[f, 1], hi[f, 1] + 1)
        du = us[None, :] - x0[f]
        dv = vs[:, None] - y0[f]
        # screen-space barycentrics of vertices 1 and 2
        b1 = (du * e2[f, 1] - dv * e2[f, 0]) / det[f]
        b2 = (dv * e1[f, 0] - du * e1[f, 1]) / det[f]
        b0 = 1.0 - b1 - b2
        inside = (b0 >= -eps) & (b1 >= -eps) & (b2 >= -eps)
        if not inside.any():
            continue
        iz = b0 / Z[f, 0] + b1 / Z[f, 1] + b2 / Z[f, 2]  # 1/z is affine in screen space
        depth = 1.0 / iz
        rows, cols = np.nonzero(inside)
        rr, cc = rows + lo[f, 1], cols + lo[f, 0]
        d = depth[rows, cols]
        closer = d < zbuf[rr, cc]
        if not closer.any():
            continue
        rr, cc, rows, cols, d = rr[closer], cc[closer], rows[closer], cols[closer], d[closer]
        zbuf[rr, cc] = d
        tri[rr, cc] = f
        w = np.stack(
            [b0[rows, cols] / Z[f, 0], b1[rows, cols] / Z[f, 1], b2[rows, cols] / Z[f, 2]], axis=1
        ) * d[:, None]
        bary[rr, cc] = w
    return Raster(tri, bary.astype(np.float32), zbuf.astype(np.float32))


def interpolate(raster: Raster, triangles: np.ndarray, values: np.ndarray,
                fill: float = np.nan) -> np.ndarray:
    """Per-vertex ``values`` (N, ...) as a dense (H, W, ...) field; ``fill`` on background."""
    vals = np.asarray(values)
    T = np.asarray(triangles, dtype=np.int64)
    m = raster.mask
    dtype = np.result_type(vals, np.float32)
    out = np.full(raster.triangle.shape + vals.shape[1:], fill, dtype=dtype)
    corners = T[raster.triangle[m]]  # (P, 3)
    b = raster.barycentric[m].astype(np.float64)
    b = b.reshape(b.shape + (1,) * (vals.ndim - 1))
    out[m] = (b[:, 0] * vals[corners[:, 0]] + b[:, 1] * vals[corners[:, 1]]
              + b[:, 2] * vals[corners[:, 2]])
    return out
