"""Pinhole camera model in the OpenCV convention.

Conventions
-----------
* Camera frame: ``x`` right, ``y`` down, the camera looks along ``+z``.
* World to camera: ``X_cam = R @ X_world + t``.
* Pixel coordinates ``(u, v)``: ``u`` grows to the right (column), ``v`` grows
  downwards (row) and ``(0, 0)`` is the **centre** of the top-left pixel, so
  pixel ``(i, j)`` (row ``i``, column ``j``) covers ``u in [j - 0.5, j + 0.5)``
  and ``v in [i - 0.5, i + 0.5)``.  The image centre is therefore at
  ``((width - 1) / 2, (height - 1) / 2)``.
* ``K = [[fx, skew, cx], [0, fy, cy], [0, 0, 1]]`` in pixels.

Example
-------
>>> cam = Camera.look_at((0.0, -2.0, 0.0), (0.0, 0.0, 0.0), fov_y_deg=40.0,
...                      width=64, height=48)
>>> cam.project([0.0, 0.0, 0.0]).round(6).tolist()
[31.5, 23.5]
>>> float(cam.depth([0.0, 0.0, 0.0]))
2.0
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["Camera"]


def _frozen(a: Any, shape: tuple[int, ...], name: str) -> np.ndarray:
    arr = np.array(a, dtype=np.float64)
    if arr.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite")
    arr.setflags(write=False)
    return arr


def _points(X: Any) -> tuple[np.ndarray, bool]:
    """Return ``X`` as an ``(N, 3)`` float array and whether it was a single point."""
    arr = np.asarray(X, dtype=np.float64)
    single = arr.ndim == 1
    arr = np.atleast_2d(arr)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3) or (3,), got {np.shape(X)}")
    return arr, single


@dataclass(frozen=True, eq=False)
class Camera:
    """Ideal pinhole camera (no distortion), OpenCV convention.

    Parameters
    ----------
    K : array_like, shape (3, 3)
        Intrinsic matrix in pixels; ``K[2] == [0, 0, 1]`` and ``K[1, 0] == 0``.
    R : array_like, shape (3, 3)
        World-to-camera rotation (orthonormal, ``det(R) = +1``).
    t : array_like, shape (3,)
        World-to-camera translation: ``X_cam = R @ X + t``.
    width, height : int
        Image size in pixels.

    Notes
    -----
    Instances are immutable; the stored arrays are read-only ``float64`` copies.
    Use :meth:`look_at` or :meth:`from_intrinsics` to build one conveniently.
    """

    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    width: int
    height: int

    def __post_init__(self) -> None:
        K = _frozen(self.K, (3, 3), "K")
        R = _frozen(self.R, (3, 3), "R")
        t = _frozen(self.t, (3,), "t")
        if not np.allclose(K[2], [0.0, 0.0, 1.0]) or K[1, 0] != 0.0:
            raise ValueError("K must be upper triangular with K[2] == [0, 0, 1]")
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError("focal lengths K[0,0], K[1,1] must be positive")
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) <= 0:
            raise ValueError("R must be a proper rotation matrix")
        width, height = int(self.width), int(self.height)
        if width != self.width or height != self.height or width <= 0 or height <= 0:
            raise ValueError("width and height must be positive integers")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "width", width)
        object.__setattr__(self, "height", height)

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_intrinsics(
        cls,
        fx: float,
        fy: float | None = None,
        cx: float | None = None,
        cy: float | None = None,
        *,
        width: int,
        height: int,
        R: Any = None,
        t: Any = None,
        skew: float = 0.0,
    ) -> Camera:
        """Build a camera from focal lengths and principal point (pixels).

        Parameters
        ----------
        fx, fy : float
            Focal lengths in pixels; ``fy`` defaults to ``fx`` (square pixels).
        cx, cy : float, optional
            Principal point in pixel-centre coordinates; defaults to the image
            centre ``((width - 1) / 2, (height - 1) / 2)``.
        width, height : int
            Image size in pixels.
        R, t : array_like, optional
            Extrinsics (world to camera); default identity / zero, i.e. the
            camera sits at the world origin looking along ``+z``.
        skew : float
            ``K[0, 1]``; zero for real sensors.

        Examples
        --------
        >>> cam = Camera.from_intrinsics(100.0, width=32, height=32)
        >>> cam.project([[0.0, 0.0, 1.0], [0.1, 0.0, 1.0]]).tolist()
        [[15.5, 15.5], [25.5, 15.5]]
        """
        fy = fx if fy is None else fy
        cx = (width - 1) / 2.0 if cx is None else cx
        cy = (height - 1) / 2.0 if cy is None else cy
        K = [[fx, skew, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]
        R = np.eye(3) if R is None else R
        t = np.zeros(3) if t is None else t
        return cls(K=K, R=R, t=t, width=width, height=height)

    @classmethod
    def look_at(
        cls,
        position: Sequence[float],
        target: Sequence[float],
        up: Sequence[float] = (0.0, 0.0, 1.0),
        fov_y_deg: float | None = None,
        fx: float | None = None,
        *,
        width: int,
        height: int,
        fy: float | None = None,
        cx: float | None = None,
        cy: float | None = None,
    ) -> Camera:
        """Camera at ``position`` whose optical axis passes through ``target``.

        ``target`` projects to the principal point ``(cx, cy)``, by default the
        image centre ``((width - 1) / 2, (height - 1) / 2)``.  ``up`` (world)
        appears as image up (``-v``).  Give exactly one of ``fov_y_deg`` (full
        vertical field of view, edge to edge; square pixels) or ``fx`` (focal
        length in pixels, with ``fy`` defaulting to ``fx``).

        Examples
        --------
        >>> cam = Camera.look_at((3, 0, 0), (0, 0, 0), fx=50.0, width=20, height=10)
        >>> cam.project([0.0, 0.0, 0.3]).round(9).tolist()  # world up -> image up
        [9.5, -0.5]
        """
        if (fov_y_deg is None) == (fx is None):
            raise ValueError("give exactly one of fov_y_deg or fx")
        if fy is not None and fx is None:
            raise ValueError("fy needs fx (fov_y_deg gives square pixels)")
        if fx is None:
            if not 0.0 < fov_y_deg < 180.0:
                raise ValueError("fov_y_deg must be in (0, 180)")
            fx = (height / 2.0) / math.tan(math.radians(fov_y_deg) / 2.0)
        pos = np.asarray(position, dtype=np.float64)
        z = np.asarray(target, dtype=np.float64) - pos
        nz = np.linalg.norm(z)
        if nz == 0.0:
            raise ValueError("position and target coincide")
        z /= nz
        x = np.cross(z, np.asarray(up, dtype=np.float64))
        nx = np.linalg.norm(x)
        if nx < 1e-12:
            raise ValueError("up is parallel to the viewing direction")
        x /= nx
        y = np.cross(z, x)
        R = np.stack([x, y, z])
        return cls.from_intrinsics(fx, fy, cx, cy, width=width, height=height, R=R, t=-R @ pos)

    @classmethod
    def from_spec(cls, spec: Any) -> Camera:
        """Camera of a scene's ``[camera]`` table (a :class:`vvtbench.scene.scene.CameraSpec`).

        ``resolution`` is ``[height, width]``; the focal lengths are ``fx`` and ``fy``
        (pixels, ``fy`` defaults to ``fx``) when ``fx`` is given, else they follow from
        ``fov_y_deg``; the principal point is ``(cx, cy)`` (pixels), by default the image
        centre, and ``look_at`` projects onto it.
        """
        height, width = (int(n) for n in spec.resolution)
        fx = getattr(spec, "fx", None)
        fov = None if fx is not None else spec.fov_y_deg
        fy, cx, cy = (getattr(spec, k, None) for k in ("fy", "cx", "cy"))
        return cls.look_at(
            spec.position, spec.look_at, spec.up, fov_y_deg=fov, fx=fx, width=width, height=height,
            fy=fy, cx=cx, cy=cy,
        )

    # ------------------------------------------------------------------ properties
    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def skew(self) -> float:
        return float(self.K[0, 1])

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates, ``-R.T @ t``."""
        return -self.R.T @ self.t

    @property
    def P(self) -> np.ndarray:
        """Projection matrix ``K @ [R | t]``, shape (3, 4)."""
        return self.K @ np.hstack([self.R, self.t[:, None]])

    # ------------------------------------------------------------------ geometry
    def to_camera(self, X: Any) -> np.ndarray:
        """World points (N, 3) to camera-frame points (N, 3)."""
        pts, single = _points(X)
        out = pts @ self.R.T + self.t
        return out[0] if single else out

    def project(self, X: Any) -> np.ndarray:
        """Pixel coordinates ``(u, v)`` of world points.

        Parameters
        ----------
        X : array_like, shape (N, 3) or (3,)

        Returns
        -------
        ndarray, shape (N, 2) or (2,)
            Points behind the camera still get a (meaningless) finite value
            unless their depth is exactly zero; check :meth:`depth`.
        """
        pts, single = _points(X)
        p = (pts @ self.R.T + self.t) @ self.K.T
        uv = p[:, :2] / p[:, 2:3]
        return uv[0] if single else uv

    def depth(self, X: Any) -> np.ndarray:
        """Depth along the optical axis (camera-frame ``z``) of world points."""
        pts, single = _points(X)
        z = pts @ self.R[2] + self.t[2]
        return z[0] if single else z

    def jacobian(self, X: Any) -> np.ndarray:
        """Analytic derivative of pixel position w.r.t. world displacement.

        Returns ``J`` with ``J[n] = d(u, v) / d(X[n])``, so a small world
        displacement ``dX`` of point ``n`` moves its image by ``J[n] @ dX``.

        Returns
        -------
        ndarray, shape (N, 2, 3) or (2, 3)
        """
        pts, single = _points(X)
        M = self.K @ self.R
        p = pts @ M.T + self.K @ self.t
        w = p[:, 2:3]
        uv = p[:, :2] / w
        # d(p_i / p_2) = (M_i - (p_i/p_2) M_2) / p_2
        J = (M[None, :2, :] - uv[:, :, None] * M[None, 2:3, :]) / w[:, :, None]
        return J[0] if single else J

    def scaled(self, factor: float) -> Camera:
        """Same camera with the image resampled by ``factor`` (e.g. supersampling).

        Pixel *edges* scale by ``factor``, so with the pixel-centre convention
        ``c' = factor * (c + 0.5) - 0.5``.  ``factor`` times the image size must
        be an integer.
        """
        w, h = self.width * factor, self.height * factor
        if abs(w - round(w)) > 1e-9 or abs(h - round(h)) > 1e-9:
            raise ValueError("factor * image size must be integral")
        K = self.K.copy()
        K[:2, :2] *= factor
        K[:2, 2] = factor * (K[:2, 2] + 0.5) - 0.5
        return Camera(K=K, R=self.R, t=self.t, width=round(w), height=round(h))

    def turned(self, angle: float, axis: Any, centre: Any) -> Camera:
        """The camera carried rigidly around ``centre``: turned by ``angle`` (radians, right
        hand) about ``axis`` through ``centre``; same intrinsics, so a point turned with it
        keeps its pixel.

        >>> cam = Camera.look_at((1.0, 0, 0), (0, 0, 0), fx=100.0, width=64, height=64)
        >>> back = cam.turned(np.pi, (0, 0, 1.0), (0, 0, 0))
        >>> back.project([0.0, 0.0, 0.0]).round(6).tolist(), back.center.round(6).tolist()
        ([31.5, 31.5], [-1.0, 0.0, 0.0])
        """
        a = np.asarray(axis, dtype=np.float64)
        a = a / np.linalg.norm(a)
        cross = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
        Q = np.eye(3) + math.sin(angle) * cross + (1.0 - math.cos(angle)) * (cross @ cross)
        c = np.asarray(centre, dtype=np.float64)
        R = self.R @ Q.T
        return Camera(self.K, R, self.t + self.R @ c - R @ c, self.width, self.height)

    @classmethod
    def views_from_spec(cls, spec: Any) -> list[Camera]:
        """Every camera of a scene's ``[camera]`` table: view 0 (:meth:`from_spec`), then the
        ``[[camera.views]]`` in order, or the ``[camera.rig]`` views (docs/dataset.md,
        "Several views")."""
        first = cls.from_spec(spec)
        views = getattr(spec, "views", None)
        rig = getattr(spec, "rig", None)
        if views:
            return [first, *(cls.from_spec(v) for v in views)]
        if rig is None:
            return [first]
        n, spread = int(rig.views), math.radians(float(rig.spread_deg))
        target = np.asarray(spec.look_at, dtype=np.float64)
        if rig.kind == "ring":
            return [first, *(first.turned(spread * i / n, spec.up, target) for i in range(1, n))]
        line = first.center - target
        line = line / np.linalg.norm(line)
        side = np.cross(line, np.asarray(spec.up, dtype=np.float64))
        if not np.linalg.norm(side) > 1e-9:
            side = np.cross(line, [1.0, 0.0, 0.0] if abs(line[0]) < 0.9 else [0.0, 1.0, 0.0])
        tilted = first.turned(spread / 2, side, target)
        return [first, *(tilted.turned(2 * math.pi * i / (n - 1), line, target)
                         for i in range(n - 1))]

    # ------------------------------------------------------------------ serialisation
    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-serialisable representation (lists of floats and ints)."""
        return {
            "model": "pinhole",
            "convention": "opencv, pixel (0,0) = centre of top-left pixel",
            "K": self.K.tolist(),
            "R": self.R.tolist(),
            "t": self.t.tolist(),
            "width": self.width,
            "height": self.height,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Camera:
        """Inverse of :meth:`to_dict`."""
        return cls(K=d["K"], R=d["R"], t=d["t"], width=d["width"], height=d["height"])

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Camera):
            return NotImplemented
        return (
            self.width == other.width
            and self.height == other.height
            and np.array_equal(self.K, other.K)
            and np.array_equal(self.R, other.R)
            and np.array_equal(self.t, other.t)
        )

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        c = self.center
        return (
            f"Camera({self.width}x{self.height}, fx={self.fx:.6g}, fy={self.fy:.6g}, "
            f"cx={self.cx:.6g}, cy={self.cy:.6g}, center=({c[0]:.4g}, {c[1]:.4g}, {c[2]:.4g}))"
        )
