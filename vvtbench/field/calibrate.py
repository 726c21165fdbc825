"""The camera of a real video from clicked points on the object.

Clicks CSV (a header line, ``#`` comments allowed; pixel ``(0, 0)`` is the centre of the
top-left pixel, ``u`` to the right, ``v`` down):

* ``vertex,u,v`` -- a vertex id of the object's mesh (``vvtbench calibrate`` prints and
  draws candidates), or
* ``x,y,z,u,v`` -- a 3-D point in the object's frame (metres, lowest corner at the origin).

Three models, chosen from the points (:func:`calibrate_camera`):

* **coplanar points** (plates, drums, one face of a block), at least 4: a homography, the
  focal length from it when no intrinsics are given (square pixels, principal point at the
  image centre; needs a view that is not face-on), then the pose by PnP
  (``cv2.solvePnP``, IPPE) refined by least squares;
* **non-coplanar points with intrinsics** (fx, fy, cx, cy), at least 4: PnP;
* **non-coplanar points**, at least 6: the DLT of :func:`vvtbench.modes.sampling.estimate_camera`
  (intrinsics and pose).

The reprojection error in pixels (RMS and max) is reported; a largest error above the bound
(default :data:`DEFAULT_MAX_ERROR` px) is an error naming the worst click.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from ..render.camera import Camera

__all__ = ["DEFAULT_MAX_ERROR", "Calibration", "CalibrationError", "Clicks", "calibrate_camera",
           "calibrate_from_file", "is_coplanar", "load_clicks_csv", "parse_intrinsics"]

DEFAULT_MAX_ERROR = 2.0
COPLANAR_RTOL = 1e-3


class CalibrationError(ValueError):
    """Clicks that cannot give a camera (one line naming the file and what is missing)."""


@dataclass
class Clicks:
    """Clicked correspondences: 3-D points in the object's frame and their pixels."""

    X: NDArray[np.float64]
    uv: NDArray[np.float64]
    vertices: NDArray[np.int64] | None = None
    source: str = "<clicks>"


@dataclass
class Calibration:
    """A camera and how well it explains the clicks."""

    camera: Camera
    method: str
    rms_px: float
    max_px: float
    residuals_px: NDArray[np.float64]
    n_points: int
    intrinsics: str
    info: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable summary (camera, method, errors)."""
        return {"camera": self.camera.to_dict(), "method": self.method,
                "intrinsics": self.intrinsics, "n_points": self.n_points,
                "rms_px": self.rms_px, "max_px": self.max_px,
                "residuals_px": self.residuals_px.tolist(), **self.info}


def _float(path: str, where: str, key: str, text: Any) -> float:
    try:
        x = float(text)
    except (TypeError, ValueError):
        raise CalibrationError(f"{path}: {where}: {key!r} must be a number, got {text!r}"
                               ) from None
    if not math.isfinite(x):
        raise CalibrationError(f"{path}: {where}: {key!r} must be finite, got {text!r}")
    return x


def load_clicks_csv(path: str | Path, points: ArrayLike) -> Clicks:
    """Read a clicks CSV (module notes) against the object's mesh ``points`` ``(q, 3)``.

    Raises
    ------
    CalibrationError
        A missing file or column, a bad number, a vertex id out of range, a repeated vertex.
    """
    path = str(path)
    try:
        text = Path(path).read_text()
    except FileNotFoundError:
        raise CalibrationError(f"{path}: clicks file not found") from None
    except UnicodeDecodeError:
        raise CalibrationError(f"{path}: not a text (CSV) file") from None
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    reader = csv.DictReader(lines)
    names = [f.strip().lower() for f in (reader.fieldnames or [])]
    reader.fieldnames = names
    by_vertex = {"vertex", "u", "v"} <= set(names)
    by_point = {"x", "y", "z", "u", "v"} <= set(names)
    if not (by_vertex or by_point):
        raise CalibrationError(f"{path}: the header must name the columns vertex,u,v or "
                               f"x,y,z,u,v; found {','.join(names) or 'nothing'}")
    P = np.asarray(points, dtype=np.float64)
    X, uv, verts = [], [], []
    for i, row in enumerate(reader):
        where = f"data line {i + 1}"
        if any(row.get(k) in (None, "") for k in ("u", "v")):
            raise CalibrationError(f"{path}: {where}: missing 'u' or 'v'")
        uv.append([_float(path, where, k, row[k]) for k in ("u", "v")])
        if by_vertex and row.get("vertex") not in (None, ""):
            x = _float(path, where, "vertex", row["vertex"])
            if x != int(x) or not 0 <= x < len(P):
                raise CalibrationError(f"{path}: {where}: 'vertex' {row['vertex']!r} is not a "
                                       f"vertex id; allowed 0 .. {len(P) - 1}")
            verts.append(int(x))
            X.append(P[int(x)])
        else:
            X.append([_float(path, where, k, row.get(k)) for k in ("x", "y", "z")])
            verts.append(-1)
    used = [v for v in verts if v >= 0]
    if len(set(used)) != len(used):
        dup = sorted({v for v in used if used.count(v) > 1})
        raise CalibrationError(f"{path}: vertex {dup} clicked more than once (one click each)")
    _check_click_units(path, [x for x, v in zip(X, verts, strict=True) if v < 0], P)
    return Clicks(np.array(X, dtype=np.float64).reshape(-1, 3),
                  np.array(uv, dtype=np.float64).reshape(-1, 2),
                  np.array(verts, dtype=np.int64) if by_vertex else None, path)


def _check_click_units(path: str, points: list, mesh_points: NDArray) -> None:
    """Warn (:class:`vvtbench.field.objects.UnitWarning`) when clicked 3-D points lie far
    outside the object as if they were in millimetres."""
    if not points or not len(mesh_points):
        return
    import warnings

    from .objects import UnitWarning

    X = np.asarray(points, dtype=np.float64)
    lo, hi = mesh_points.min(0), mesh_points.max(0)
    size = float(np.max(hi - lo))
    reach = float(np.max(np.abs(np.concatenate([X - lo, X - hi])).max(1)))
    if size > 0 and reach > 100 * size:
        warnings.warn(f"{path}: clicked x,y,z reach {reach:g} m from an object {size:g} m "
                      "across: points are read in metres, in the object's frame, and these "
                      f"look like millimetres (they would reach {reach / 1000:g} m)",
                      UnitWarning, stacklevel=3)


def parse_intrinsics(text: str | Sequence[float] | None
                     ) -> tuple[float, float, float, float] | None:
    """``"fx,fy,cx,cy"`` (pixels) to a tuple, or None."""
    if text is None:
        return None
    parts = text.split(",") if isinstance(text, str) else list(text)
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) != 4 or not all(math.isfinite(v) for v in values) or min(values[:2]) <= 0:
        raise CalibrationError(f"--intrinsics {text!r}: must be fx,fy,cx,cy in pixels "
                               "(four numbers, focal lengths positive)")
    return values  # type: ignore[return-value]


def is_coplanar(X: ArrayLike, rtol: float = COPLANAR_RTOL) -> bool:
    """True when the points lie on a plane (their thinnest extent below ``rtol`` of the
    widest)."""
    Xa = np.asarray(X, dtype=np.float64)
    s = np.linalg.svd(Xa - Xa.mean(0), compute_uv=False)
    return bool(s[-1] <= rtol * s[0])


def _K(fx: float, fy: float, cx: float, cy: float) -> NDArray[np.float64]:
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _homography(p2: NDArray, uv: NDArray) -> NDArray:
    import cv2

    H, _ = cv2.findHomography(p2.astype(np.float64), uv.astype(np.float64), 0)
    if H is None or not np.all(np.isfinite(H)):
        raise CalibrationError("the clicks give no homography (collinear points?)")
    return H


def focal_from_homography(H: NDArray, cx: float, cy: float) -> float | None:
    """The focal length (px, square pixels) that makes the homography's first two columns
    orthogonal and of equal length after removing the principal point (Zhang 2000), or None
    when the view is face-on (the focal length is then not observable)."""
    T = np.array([[1.0, 0.0, -cx], [0.0, 1.0, -cy], [0.0, 0.0, 1.0]])
    h = T @ H
    h1, h2 = h[:, 0], h[:, 1]
    a = np.array([h1[0] * h2[0] + h1[1] * h2[1], h1[0] ** 2 + h1[1] ** 2 - h2[0] ** 2 - h2[1] ** 2])
    b = np.array([h1[2] * h2[2], h1[2] ** 2 - h2[2] ** 2])
    # a w + b = 0 for w = 1 / f**2, in the least-squares sense
    if not np.sum(a * a) > 0:
        return None
    w = float(-np.sum(a * b) / np.sum(a * a))
    if not w > 0 or 1.0 / math.sqrt(w) > 1e3 * max(cx, cy, 1.0):
        return None
    return 1.0 / math.sqrt(w)


def _refine(X: NDArray, uv: NDArray, K: NDArray, R: NDArray, t: NDArray, free_focal: bool
            ) -> tuple[NDArray, NDArray, NDArray]:
    cx, cy = K[0, 2], K[1, 2]

    def unpack(x):
        f = x[0] if free_focal else None
        r, tt = x[-6:-3], x[-3:]
        return f, r, tt

    def residual(x):
        f, r, tt = unpack(x)
        Kx = _K(f, f * K[1, 1] / K[0, 0], cx, cy) if free_focal else K
        Xc = Rotation.from_rotvec(r).apply(X) + tt
        p = Xc @ Kx.T
        return (p[:, :2] / p[:, 2:3] - uv).ravel()

    x0 = np.r_[[K[0, 0]] if free_focal else [], Rotation.from_matrix(R).as_rotvec(), t]
    res = least_squares(residual, x0, method="lm", x_scale="jac")
    f, r, tt = unpack(res.x)
    if free_focal:
        K = _K(abs(f), abs(f) * K[1, 1] / K[0, 0], cx, cy)
    return K, Rotation.from_rotvec(r).as_matrix(), tt


def _reprojection(X: NDArray, uv: NDArray, K: NDArray, R: NDArray, t: NDArray) -> float:
    p = (X @ R.T + t) @ K.T
    if np.any(p[:, 2] <= 0):
        return math.inf
    return float(np.sqrt(np.mean(np.sum((p[:, :2] / p[:, 2:3] - uv) ** 2, axis=1))))


def _pnp(X: NDArray, uv: NDArray, K: NDArray, planar: bool) -> tuple[NDArray, NDArray]:
    import cv2

    flags = cv2.SOLVEPNP_IPPE if planar else cv2.SOLVEPNP_EPNP
    ok, rvec, tvec = cv2.solvePnP(X.astype(np.float64), uv.astype(np.float64), K, None,
                                  flags=flags)
    if not ok:
        raise CalibrationError("PnP found no pose for the clicks")
    R, _ = cv2.Rodrigues(rvec)
    return R, tvec.ravel()


def calibrate_camera(X: ArrayLike, uv: ArrayLike, width: int, height: int, *,
                     intrinsics: Sequence[float] | None = None,
                     max_error: float | None = DEFAULT_MAX_ERROR,
                     source: str = "clicks") -> Calibration:
    """The camera that maps the object points ``X`` ``(n, 3)`` to the pixels ``uv`` ``(n, 2)``.

    Parameters
    ----------
    X, uv : correspondences (object frame, metres; pixels).
    width, height : the video's size in pixels.
    intrinsics : ``(fx, fy, cx, cy)`` in pixels, or None to estimate them.
    max_error : the largest reprojection error (px) accepted, or None for no bound.
    source : what the points came from, for messages (the clicks file).

    Raises
    ------
    CalibrationError
        Fewer points than the model needs, degenerate points, points behind the camera, or a
        reprojection error above ``max_error``; one line naming ``source``.
    """
    Xa = np.asarray(X, dtype=np.float64).reshape(-1, 3)
    ua = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    n = len(Xa)
    if n < 4:
        raise CalibrationError(f"{source}: {n} click(s); a camera needs at least 4 coplanar "
                               "(plate, drum, one face) or 6 non-coplanar points")
    planar = is_coplanar(Xa)
    cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
    info: dict[str, Any] = {"coplanar": planar}
    try:
        if planar:
            c = Xa.mean(0)
            _, _, vt = np.linalg.svd(Xa - c)
            p2 = (Xa - c) @ vt[:2].T
            if intrinsics is not None:
                K = _K(*intrinsics)
                how = "given"
            else:
                f = focal_from_homography(_homography(p2, ua), cx, cy)
                how = "focal from the homography, principal point at the image centre"
                if f is None:  # noisy or nearly face-on: start from common fields of view
                    how = "focal fitted from fields of view 15-90 deg, principal point at " \
                          "the image centre (the homography alone did not fix it)"
                best = None
                for f0 in ([f] if f is not None else
                           [height / 2 / math.tan(math.radians(a) / 2)
                            for a in (15, 25, 40, 60, 90)]):
                    K0 = _K(f0, f0, cx, cy)
                    R0, t0 = _pnp(Xa, ua, K0, planar=True)
                    K1, R1, t1 = _refine(Xa, ua, K0, R0, t0, free_focal=True)
                    err = _reprojection(Xa, ua, K1, R1, t1)
                    if best is None or err < best[0]:
                        best = (err, K1, R1, t1)
                _, K, R, t = best
            if intrinsics is not None:
                R, t = _pnp(Xa, ua, K, planar=True)
                K, R, t = _refine(Xa, ua, K, R, t, free_focal=False)
            method = "homography + PnP (coplanar)"
        elif intrinsics is not None:
            K = _K(*intrinsics)
            R, t = _pnp(Xa, ua, K, planar=False)
            K, R, t = _refine(Xa, ua, K, R, t, free_focal=False)
            how, method = "given", "PnP"
        else:
            if n < 6:
                raise CalibrationError(
                    f"{source}: {n} non-coplanar clicks; without --intrinsics the DLT needs at "
                    "least 6 (or click 4+ points on one plane)")
            from ..modes.sampling import estimate_camera

            cam, _ = estimate_camera(Xa, ua, width, height)
            K, R, t = cam.K, cam.R, cam.t
            how, method = "estimated (DLT)", "DLT"
        if np.linalg.det(R) < 0:
            raise CalibrationError(f"{source}: the clicks give a mirrored camera")
        camera = Camera(K=K, R=R, t=t, width=width, height=height)
    except CalibrationError as error:
        msg = str(error)
        raise CalibrationError(msg if msg.startswith(source) else f"{source}: {msg}") from None
    except ValueError as error:  # degenerate DLT, a camera that is not one
        raise CalibrationError(f"{source}: {error}") from None
    if np.any(camera.depth(Xa) <= 0):
        raise CalibrationError(f"{source}: {int(np.sum(camera.depth(Xa) <= 0))} clicked "
                               "point(s) fall behind the estimated camera: inconsistent clicks?")
    res = np.linalg.norm(camera.project(Xa) - ua, axis=1)
    cal = Calibration(camera, method, float(np.sqrt(np.mean(res ** 2))), float(res.max()),
                      res, n, how, info)
    if max_error is not None and cal.max_px > max_error:
        worst = int(np.argmax(res))
        raise CalibrationError(
            f"{source}: reprojection error {cal.max_px:.2f} px (RMS {cal.rms_px:.2f}) is above "
            f"the bound {max_error:g} px (--max-error); worst: data line {worst + 1}; recheck "
            "that click or add more")
    return cal


def calibrate_from_file(path: str | Path, points: ArrayLike, width: int, height: int, *,
                        intrinsics: Sequence[float] | None = None,
                        max_error: float | None = DEFAULT_MAX_ERROR) -> Calibration:
    """:func:`calibrate_camera` on a clicks CSV (:func:`load_clicks_csv`)."""
    clicks = load_clicks_csv(path, points)
    return calibrate_camera(clicks.X, clicks.uv, width, height, intrinsics=intrinsics,
                            max_error=max_error, source=str(path))


# --------------------------------------------------------------------------- pictures


def default_camera(points: ArrayLike, width: int, height: int) -> Camera:
    """A view of the object from the front right, above (azimuth -50 deg, elevation 35 deg),
    framing its bounding sphere in the image: the picture shown before any click."""
    pts = np.asarray(points, dtype=np.float64)
    centre = (pts.min(0) + pts.max(0)) / 2
    radius = max(float(np.linalg.norm(pts.max(0) - pts.min(0))) / 2, 1e-6)
    fov = 30.0
    f = (min(width, height) / 2) / math.tan(math.radians(fov) / 2)
    distance = 1.3 * radius / math.sin(math.radians(fov) / 2)
    az, el = math.radians(-50.0), math.radians(35.0)
    direction = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    return Camera.look_at(centre + distance * direction, centre, fx=f, width=width,
                          height=height)


def candidate_vertices(points: ArrayLike, surface: ArrayLike, camera: Camera,
                       corners: ArrayLike, n_extra: int = 12) -> NDArray[np.int64]:
    """Vertices worth clicking, as seen by ``camera``: the visible ``corners`` first, then up
    to ``n_extra`` visible vertices spread over the surface (farthest-point order)."""
    from ..modes.sampling import visible_vertices

    pts = np.asarray(points, dtype=np.float64)
    visible = visible_vertices(pts, surface, camera)
    if visible.size == 0:  # a membrane seen from its back: every node in the frame
        uv, z = camera.project(pts), camera.depth(pts)
        visible = np.flatnonzero((z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= camera.width - 1)
                                 & (uv[:, 1] >= 0) & (uv[:, 1] <= camera.height - 1))
    chosen = [int(c) for c in np.asarray(corners, dtype=np.int64) if c in set(visible.tolist())]
    pool = visible[~np.isin(visible, chosen)]
    if pool.size == 0:
        return np.array(chosen, dtype=np.int64)
    span = float(np.linalg.norm(pts.max(0) - pts.min(0)))
    seeds = pts[chosen] if chosen else pts[pool[:1]]
    dist = np.min(np.linalg.norm(pts[pool][:, None] - seeds[None], axis=2), axis=1)
    for _ in range(min(n_extra, pool.size)):
        i = int(np.argmax(dist))
        if dist[i] < 0.08 * span:
            break
        chosen.append(int(pool[i]))
        dist = np.minimum(dist, np.linalg.norm(pts[pool] - pts[pool[i]], axis=1))
    return np.array(chosen, dtype=np.int64)


def _to_bgr(frame: NDArray, scale: int) -> NDArray[np.uint8]:
    import cv2

    img = np.asarray(frame, dtype=np.float64)
    if img.ndim == 3:
        img = img.mean(axis=2)
    lo, hi = np.percentile(img, [0.5, 99.5])
    img = np.clip((img - lo) / max(hi - lo, 1e-12), 0, 1)
    img = (img * 255).astype(np.uint8)
    img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)


def _draw_view(img: NDArray[np.uint8], camera: Camera, points: NDArray, surface: NDArray,
               candidates: NDArray, scale: int, clicks: Clicks | None,
               title: str) -> NDArray[np.uint8]:
    import cv2

    def px(uv):
        return np.rint((np.asarray(uv) + 0.5) * scale - 0.5).astype(np.int64)

    p = points[surface]
    normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    facing = np.einsum("ij,ij->i", normal, camera.center - p.mean(1)) > 0
    if not facing.any():
        facing[:] = True
    edges = np.unique(np.sort(np.concatenate(
        [surface[facing][:, [a, b]] for a, b in ((0, 1), (1, 2), (2, 0))]), axis=1), axis=0)
    front = camera.depth(points) > 0
    uv = px(camera.project(np.where(front[:, None], points, points.mean(0))))
    for a, b in edges:
        if front[a] and front[b]:
            cv2.line(img, tuple(int(x) for x in uv[a]), tuple(int(x) for x in uv[b]),
                     (200, 140, 0), 1, cv2.LINE_AA)
    font, size = cv2.FONT_HERSHEY_SIMPLEX, 0.45
    for v in candidates:
        x, y = (int(c) for c in uv[v])
        cv2.circle(img, (x, y), 4, (0, 220, 255), -1, cv2.LINE_AA)
        label = str(int(v))
        for colour, width in (((0, 0, 0), 3), ((0, 220, 255), 1)):
            cv2.putText(img, label, (x + 6, y - 6), font, size, colour, width, cv2.LINE_AA)
    if clicks is not None:
        for X, click in zip(clicks.X, clicks.uv, strict=True):
            c = px(click)
            r = px(camera.project(X))
            cv2.drawMarker(img, (int(c[0]), int(c[1])), (0, 200, 0), cv2.MARKER_CROSS, 14, 2)
            cv2.circle(img, (int(r[0]), int(r[1])), 6, (0, 0, 255), 1, cv2.LINE_AA)
    for colour, width in (((0, 0, 0), 3), ((255, 255, 255), 1)):
        cv2.putText(img, title, (8, 20), font, 0.5, colour, width, cv2.LINE_AA)
    return img


def draw_calibration(path: str | Path, frame: NDArray, camera: Camera, points: ArrayLike,
                     surface: ArrayLike, candidates: ArrayLike, *, calibrated: bool,
                     clicks: Clicks | None = None, caption: str = "") -> Path:
    """A PNG: the video's first frame (left) and the mesh drawn by ``camera`` with the
    numbered ``candidates`` (right; on the frame too when ``calibrated``), clicked pixels as
    green crosses and their reprojections as red circles."""
    import cv2

    from ..io.files import write_bytes

    pts = np.asarray(points, dtype=np.float64)
    tri = np.asarray(surface, dtype=np.int64)
    cand = np.asarray(candidates, dtype=np.int64)
    h, w = camera.height, camera.width
    scale = max(1, int(math.ceil(480 / max(h, w))))
    left = _to_bgr(frame, scale)
    if calibrated:
        left = _draw_view(left, camera, pts, tri, cand, scale, clicks,
                          "first frame + mesh from the clicks")
    else:
        left = _draw_view(left, camera, pts, tri[:0], cand[:0], scale, clicks,
                          "first frame (no clicks yet)")
    right = np.full_like(left, 40)
    right = _draw_view(right, camera, pts, tri, cand, scale, clicks,
                       "mesh, estimated camera" if calibrated else "mesh, default view")
    gap = np.full((left.shape[0], 8, 3), 255, np.uint8)
    img = np.hstack([left, gap, right])
    if caption:
        bar = np.full((28, img.shape[1], 3), 255, np.uint8)
        cv2.putText(bar, caption, (8, 19), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1,
                    cv2.LINE_AA)
        img = np.vstack([img, bar])
    ok, data = cv2.imencode(".png", img)
    if not ok:
        raise OSError(f"{path}: cannot encode the PNG")
    write_bytes(path, data.tobytes())
    return Path(path)
