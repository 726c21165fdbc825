"""A benchmark sample handed over as a field user would hand it over.

A rendered sample's lossless video is re-encoded as a camera writes it (:func:`encode_video`:
a 12-bit TIFF image sequence, 12-bit packed Photron ``.cih``/``.mraw`` frames, or H.264 at a
consumer quality), read back through the field readers; its camera is estimated from a few
clicked correspondences with Gaussian pixel noise (:func:`simulate_clicks`, seeded) instead of
taken from the sample; its object is a surface mesh file (:func:`write_object_surface`, an STL
in the object's frame) meshed by :func:`vvtbench.field.objects.resolve_object` instead of the
scene's geometry. :func:`field_observe` builds the inverse problem from these alone and the
truth from the sample, on the same inference mesh, so the row is scored as any other.
"""

from __future__ import annotations

import csv
import io
from collections.abc import Iterable, Mapping
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..io.files import write_text

__all__ = ["FIELD_FORMATS", "FieldSettings", "encode_video", "field_observe",
           "reprojection_error", "simulate_clicks", "write_object_surface"]

FIELD_FORMATS = ("tiff", "mraw", "h264")
OBJECT_FORMS = ("stl", "scene")


@dataclass(frozen=True)
class FieldSettings:
    """How a track's samples reach the solver (docs/suites.md, ``[tracks.field]``).

    Attributes
    ----------
    format : ``"tiff"`` (an image sequence), ``"mraw"`` (Photron ``.cih`` + packed ``.mraw``)
        or ``"h264"`` (an ``.mp4``, 8-bit).
    bit_depth : significant bits of the TIFF or MRAW samples (8, 12 or 16).
    crf : H.264 constant rate factor (0 best .. 51 worst; 23 is libx264's default).
    bitrate_mbps : H.264 average bit rate instead of ``crf``, in Mbit per second of
        recording at the capture frame rate (a consumer camera's figure: 50-100 Mbit/s).
    clicks : clicked correspondences (>= 6: the DLT estimates intrinsics and pose).
    click_noise_px : standard deviation of the Gaussian noise on each pixel coordinate.
    click_seed : seed of the click noise (None: the row's seed).
    object : ``"stl"`` (a surface mesh file of the object) or ``"scene"`` (the scene file).
    mesh : how an STL is meshed: ``"auto"`` (a block as its voxel grid, any other surface in
        tetrahedra) or ``"tet"`` (tetrahedra always); the ``--object FILE.stl:mesh=...``
        option of :func:`vvtbench.field.objects.resolve_object`.
    max_error_px : the largest reprojection error of a click accepted (px).
    """

    format: str = "tiff"
    bit_depth: int = 12
    crf: int = 23
    bitrate_mbps: float | None = None
    clicks: int = 10
    click_noise_px: float = 0.5
    click_seed: int | None = None
    object: str = "stl"
    mesh: str = "auto"
    max_error_px: float = 2.0

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any]) -> FieldSettings:
        """Settings from a validated ``[tracks.field]`` table."""
        return cls(**{k: v for k, v in dict(data).items() if k in cls.__dataclass_fields__})

    def resolved(self, seed: int) -> FieldSettings:
        """These settings with the click seed fixed (``seed``: the row's, when none is set)."""
        return self if self.click_seed is not None else replace(self, click_seed=int(seed))

    def key(self) -> dict[str, Any]:
        """What changes the encoded video (``video``) and the calibration (``clicks``)."""
        d = asdict(self)
        video = {"format": d["format"]}
        if self.format != "h264":
            video["bit_depth"] = d["bit_depth"]
        elif self.bitrate_mbps is not None:
            video["bitrate_mbps"] = d["bitrate_mbps"]
        else:
            video["crf"] = d["crf"]
        return {"video": video, "clicks": {k: d[k] for k in (
            "clicks", "click_noise_px", "click_seed", "object", "mesh", "max_error_px")}}

    def to_dict(self) -> dict[str, Any]:
        """The settings that matter, flat (for the results row)."""
        k = self.key()
        return {**k["video"], **k["clicks"]}


# --------------------------------------------------------------------------- video


def _quantize(frame: NDArray, bits: int) -> NDArray:
    top = (1 << bits) - 1
    q = np.rint(np.clip(np.asarray(frame, dtype=np.float64), 0.0, 1.0) * top)
    return q.astype(np.uint8 if bits <= 8 else np.uint16)


def _pack12(frame: NDArray[np.uint16]) -> bytes:
    """Photron 12-bit packing: two pixels in three bytes, big-endian bit order."""
    flat = frame.reshape(-1).astype(np.uint16)
    a, b = flat[0::2], flat[1::2]
    out = np.empty((a.size, 3), np.uint8)
    out[:, 0] = a >> 4
    out[:, 1] = ((a & 0xF) << 4) | (b >> 8)
    out[:, 2] = b & 0xFF
    return out.tobytes()


def _cih(n: int, height: int, width: int, fps: float, bits: int) -> str:
    return "\n".join([
        "#Camera Information Header", "Date : 2026/01/01", "Camera Type : vvtbench",
        f"Record Rate(fps) : {fps:g}", f"Shutter Speed(s) : 1/{fps:g}",
        f"Total Frame : {n}", "Original Total Frame : " + str(n),
        "Start Frame : 0", "Correct Trigger Frame : 0",
        f"Image Width : {width}", f"Image Height : {height}",
        "Color Type : Mono", f"Color Bit : {bits}", "File Format : MRaw",
        f"EffectiveBit Depth : {bits}", "EffectiveBit Side : Lower", "Comment Text : ", ""])


def encode_video(frames: Iterable[ArrayLike], fps: float, dest: str | Path,
                 settings: FieldSettings) -> Path:
    """Write ``frames`` (``(H, W)`` floats in ``[0, 1]``, streamed) into the folder ``dest``
    as a camera writes them; returns the path to open (the folder of a TIFF sequence, the
    ``.cih`` of an MRAW recording, the ``.mp4``). Frames are quantized to the format's bit
    depth (round to nearest); one frame is held at a time.

    Raises
    ------
    ValueError
        An unknown format or bit depth, or no frame.
    """
    dest = Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    fmt, bits = settings.format, int(settings.bit_depth)
    if fmt not in FIELD_FORMATS:
        raise ValueError(f"field format {fmt!r}: allowed {', '.join(FIELD_FORMATS)}")
    if fmt != "h264" and bits not in (8, 12, 16):
        raise ValueError(f"field bit_depth {bits}: allowed 8, 12, 16")
    n = 0
    if fmt == "tiff":
        import tifffile

        folder = dest / "frames"
        folder.mkdir(exist_ok=True)
        for frame in frames:
            n += 1
            q = _quantize(frame, bits)
            extra = [] if bits in (8, 16) else [(280, "H", 1, 0, True),
                                                (281, "H", 1, (1 << bits) - 1, True)]
            tifffile.imwrite(folder / f"frame_{n - 1:06d}.tif", q, photometric="minisblack",
                             extratags=extra)
        out = folder
    elif fmt == "mraw":
        shape = None
        with open(dest / "recording.mraw", "wb") as f:
            for frame in frames:
                n += 1
                q = _quantize(frame, bits)
                shape = q.shape
                if bits == 12:
                    if q.size % 2:
                        raise ValueError("12-bit MRAW frames need an even number of pixels")
                    f.write(_pack12(q))
                else:
                    f.write(q.astype(q.dtype.newbyteorder("<")).tobytes())
        if shape is None:
            raise ValueError("no frame to encode")
        write_text(dest / "recording.cih", _cih(n, shape[0], shape[1], fps, bits))
        out = dest / "recording.cih"
    else:
        writer = None
        out = dest / "video.mp4"
        try:
            for frame in frames:
                n += 1
                q = _quantize(frame, 8)
                if writer is None:
                    writer = _h264_writer(out, q.shape, fps, settings)
                writer.write(q)
        except BaseException:
            if writer is not None:
                writer.abort()
            raise
        if writer is not None:
            writer.close()
    if n == 0:
        raise ValueError("no frame to encode")
    return out


def _h264_writer(path: Path, shape: tuple[int, int], fps: float, settings: FieldSettings):
    """An 8-bit H.264 writer at ``settings.crf``, or at ``settings.bitrate_mbps`` of
    recording: the container plays at :data:`vvtbench.video.files.PLAYBACK_FPS`, so the encoder's
    rate is scaled to give each frame the bits it has at the capture rate ``fps``."""
    from ..video.files import PLAYBACK_FPS, VideoWriter

    if settings.bitrate_mbps is None:
        return VideoWriter(path, shape[0], shape[1], capture_fps=fps, pix_fmt="gray",
                           codec="h264", crf=int(settings.crf))
    return _RateWriter(path, shape, fps, settings.bitrate_mbps * 1e6 * PLAYBACK_FPS / fps)


class _RateWriter:
    """libx264 at an average bit rate (one pass, ``-b:v``), gray frames, atomic on close."""

    def __init__(self, path: Path, shape: tuple[int, int], fps: float, bits_per_s: float):
        import imageio_ffmpeg

        from ..video.files import BITEXACT, PLAYBACK_FPS, rate_fraction

        self.path, self.shape = Path(path), shape
        self._pad = (shape[0] % 2, shape[1] % 2)
        self._tmp = self.path.with_name(f".{self.path.name}.partial.mp4")
        rate = f"{max(1, round(bits_per_s / 1000))}k"
        params = ["-b:v", rate, "-maxrate", rate, "-bufsize", rate, "-preset", "medium",
                  "-threads", "1", *BITEXACT,
                  "-metadata:s:v:0", f"CAPTURE_FPS={rate_fraction(fps)}"]
        self._gen = imageio_ffmpeg.write_frames(
            f"file:{self._tmp}", (shape[1] + self._pad[1], shape[0] + self._pad[0]),
            pix_fmt_in="gray", pix_fmt_out="yuv420p", codec="libx264", quality=None,
            fps=PLAYBACK_FPS, macro_block_size=1, output_params=params,
            ffmpeg_log_level="error")
        self._gen.send(None)

    def write(self, frame: NDArray) -> None:
        a = np.asarray(frame, dtype=np.uint8)
        if any(self._pad):
            a = np.pad(a, ((0, self._pad[0]), (0, self._pad[1])))
        self._gen.send(np.ascontiguousarray(a))

    def close(self) -> None:
        self._gen.close()
        self._tmp.replace(self.path)

    def abort(self) -> None:
        try:
            self._gen.close()
        except Exception:  # noqa: BLE001 -- the partial file is removed either way
            pass
        self._tmp.unlink(missing_ok=True)


# --------------------------------------------------------------------------- object, clicks


def write_object_surface(scene: Any, path: str | Path, mesh: Any = None) -> Path:
    """An STL of the object of ``scene`` in its own frame (metres, lowest corner at the
    origin): the block of a box scene, the boundary surface of the simulation ``mesh`` of a
    mesh scene. Drums have no closed surface: give them as ``object = "scene"``.

    Raises
    ------
    ValueError
        A drum, or a mesh scene without its simulation mesh.
    """
    import trimesh

    geom = scene.geometry
    if geom.kind == "box":
        size = np.asarray(geom.size, dtype=float)
        surface = trimesh.creation.box(extents=size)
        surface.apply_translation(size / 2)
    elif mesh is not None and mesh.dofs_per_node == 3:
        surface = trimesh.Trimesh(np.asarray(mesh.points), np.asarray(mesh.surface),
                                  process=True)
        surface.apply_translation(-surface.bounds[0])
    else:
        raise ValueError(f"scene {scene.name!r} ({geom.kind}): no closed surface to write as "
                         "an STL; allowed: object = 'scene' for membranes")
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    surface.export(tmp, file_type="stl")
    tmp.replace(path)
    return path


def simulate_clicks(points: ArrayLike, surface: ArrayLike, corners: ArrayLike, camera: Any,
                    n: int, noise_px: float, seed: int
                    ) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
    """``n`` clicked correspondences a person would make: the object's visible corners first,
    then visible vertices spread over the surface
    (:func:`vvtbench.field.calibrate.candidate_vertices`), their pixels under the true
    ``camera`` plus Gaussian noise of ``noise_px`` per coordinate drawn from
    ``numpy.random.default_rng(seed)``. Returns ``(vertices, X, uv)``.

    Raises
    ------
    ValueError
        Fewer than ``n`` distinct visible vertices to click.
    """
    from .calibrate import candidate_vertices

    pts = np.asarray(points, dtype=np.float64)
    chosen = candidate_vertices(pts, surface, camera, corners, n_extra=4 * n)
    if chosen.size < n:
        raise ValueError(f"only {chosen.size} vertices of the object are visible and apart "
                         f"enough to click; {n} clicks asked")
    chosen = chosen[:n]
    rng = np.random.default_rng(int(seed))
    uv = camera.project(pts[chosen]) + rng.normal(0.0, float(noise_px), (n, 2))
    return chosen.astype(np.int64), pts[chosen], uv


def clicks_csv(X: NDArray, uv: NDArray) -> str:
    """The ``x,y,z,u,v`` clicks CSV of :mod:`vvtbench.field.calibrate`."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["x", "y", "z", "u", "v"])
    for p, q in zip(X, uv, strict=True):
        w.writerow([repr(float(v)) for v in (*p, *q)])
    return buf.getvalue()


def reprojection_error(estimated: Any, true: Any, points: ArrayLike) -> dict[str, float]:
    """Pixel distance between the projections of ``points`` by two cameras: RMS and max."""
    pts = np.asarray(points, dtype=np.float64)
    d = np.linalg.norm(estimated.project(pts) - true.project(pts), axis=1)
    return {"rms_px": float(np.sqrt(np.mean(d ** 2))), "max_px": float(np.max(d))}


# --------------------------------------------------------------------------- observe


def field_observe(sample: Any, obj: Any, camera: Any, modesets: list, inference: Mapping,
                  width: int, height: int):
    """``(problem, truth)`` of a sample seen as a field user sees it.

    The problem is that of :class:`vvtbench.observe.RealVideo` (the object ``obj`` a
    :class:`~vvtbench.field.objects.FieldObject`, the estimated ``camera``, the extracted
    ``modesets``, the priors the benchmark gives every solver: the scene's material unless
    ``inference`` sets ``nu``, ``w0``, ``v0``); the truth is the sample's, on that problem's
    inference mesh: the material averaged over each voxel, the true modes at its nodes seen
    through its observation operator, each extracted mode paired with a true one by MAC.
    """
    from .. import observe as obs
    from ..fem.elements import get_element

    membrane = get_element(sample.info["mesh"]["element"]).dofs_per_node == 1
    m = sample.scene.material
    base_w = m.tension if membrane else m.E
    base_v = m.areal_density if membrane else m.rho
    nu = inference.get("nu")
    real = obs.RealVideo(modes=list(modesets), mesh=obj.mesh, camera=camera,
                         fixed_nodes=obj.fixed_nodes, width=width, height=height,
                         nu=float(m.nu if nu is None else nu),
                         w0=float(inference.get("w0") or base_w),
                         v0=float(inference.get("v0") or base_v))
    options = obs.ObserveOptions(observation="extracted",
                                 n_modes=int(inference.get("n_modes", 10)),
                                 inference_shape=tuple(obj.inference_shape))
    problem, _ = obs.observe(real, options)
    if inference.get("w_mean") is not None:
        problem = replace(problem, w_mean=float(inference["w_mean"]))
    return obs.sample_truth(sample, problem)
