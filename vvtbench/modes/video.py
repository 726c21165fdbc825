"""Reading videos as streams of float grayscale frames.

Any container/codec that the ``imageio-ffmpeg`` binary decodes (avi, mp4, mkv, ...) is read
through ffmpeg's own grayscale conversion (luma): sources with more than 8 bits per channel
(e.g. ``gray16le``, ``yuv420p10le``, ``rgb48le``) are decoded as 16-bit ``gray16le`` and
scaled by ``1 / 65535``, the others as 8-bit ``gray`` scaled by ``1 / 255``.  ``.npy`` files
``(T, H, W)`` or ``(T, H, W, C)`` are memory-mapped; arrays and iterables of frames are
accepted as they are.  Colour frames given as arrays use Rec. 601 luma weights.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["VIDEO_SUFFIXES", "VideoStream", "average_frames", "open_video", "to_gray"]

VIDEO_SUFFIXES = (".mkv", ".mp4", ".avi", ".mov", ".webm", ".m4v", ".mpg", ".mpeg", ".npy")
_LUMA = np.array([0.299, 0.587, 0.114])
_HIGH_DEPTH = re.compile(r"(p9|p10|p12|p14|p16|9le|9be|1[0246]le|1[0246]be|48|64|f16|f32)")


def to_gray(frame: ArrayLike) -> NDArray[np.float32]:
    """``(H, W)`` or ``(H, W, C)`` frame to float32 gray.

    Integer frames are scaled to ``[0, 1]`` by their dtype's maximum; ``C = 3`` or ``4``
    (alpha ignored) uses Rec. 601 luma weights, ``C = 1`` is squeezed.
    """
    a = np.asarray(frame)
    scale = 1.0
    if np.issubdtype(a.dtype, np.integer):
        scale = 1.0 / float(np.iinfo(a.dtype).max)
    elif a.dtype == np.bool_:
        a = a.astype(np.float32)
    if a.ndim == 3:
        if a.shape[-1] == 1:
            a = a[..., 0]
        elif a.shape[-1] in (3, 4):
            a = a[..., :3].astype(np.float32) @ _LUMA.astype(np.float32)
        else:
            raise ValueError(f"colour frames must have 1, 3 or 4 channels, got {a.shape}")
    if a.ndim != 2:
        raise ValueError(f"frames must be (H, W) or (H, W, C), got {a.shape}")
    out = a.astype(np.float32)
    if scale != 1.0:
        out *= np.float32(scale)
    return out


def average_frames(frames: Iterable[NDArray], n: int) -> Iterator[NDArray[np.float32]]:
    """Mean of consecutive groups of ``n`` frames (an incomplete last group is dropped)."""
    if n < 1:
        raise ValueError(f"average must be >= 1, got {n}")
    if n == 1:
        yield from (np.asarray(f, dtype=np.float32) for f in frames)
        return
    acc: NDArray[np.float64] | None = None
    k = 0
    for f in frames:
        acc = np.array(f, dtype=np.float64) if acc is None else acc + f
        k += 1
        if k == n:
            yield (acc / n).astype(np.float32)
            acc, k = None, 0


@dataclass
class VideoStream:
    """An opened video: metadata and a one-shot iterator of float32 gray frames.

    Attributes
    ----------
    frames : iterator of ndarray
        ``(H, W)`` float32 frames in ``[0, 1]`` for integer sources.
    shape : tuple of int
        ``(H, W)`` after cropping.
    fps : float or None
        Container frame rate (may be wrong for high-speed footage: pass ``fps``).
    n_frames : int or None
        Expected number of frames (estimate for compressed containers).
    meta : dict
        Source description (path, pixel format, bit depth, ...).
    """

    frames: Iterator[NDArray[np.float32]]
    shape: tuple[int, int]
    fps: float | None
    n_frames: int | None
    meta: dict[str, Any] = field(default_factory=dict)


def _crop(frames: Iterable[NDArray], roi: tuple[int, int, int, int] | None) -> Iterator[NDArray]:
    for f in frames:
        yield f if roi is None else f[roi[0] : roi[1], roi[2] : roi[3]]


def _limit(frames: Iterable[NDArray], n: int | None) -> Iterator[NDArray]:
    for i, f in enumerate(frames):
        if n is not None and i >= n:
            return
        yield f


def _ffmpeg_frames(path: Path) -> tuple[Iterator[NDArray[np.float32]], dict[str, Any]]:
    import imageio_ffmpeg

    probe = imageio_ffmpeg.read_frames(str(path), pix_fmt="gray")
    try:
        meta = next(probe)
    except (OSError, RuntimeError, StopIteration) as e:
        raise ValueError(f"{path}: cannot be decoded by ffmpeg: {e}") from None
    finally:
        probe.close()
    src_fmt = str(meta.get("pix_fmt", ""))
    high = bool(_HIGH_DEPTH.search(src_fmt.split("(")[0]))
    pix_fmt, bpp, dtype = ("gray16le", 2, "<u2") if high else ("gray", 1, np.uint8)
    w, h = meta["size"]

    def gen() -> Iterator[NDArray[np.float32]]:
        reader = imageio_ffmpeg.read_frames(str(path), pix_fmt=pix_fmt, bpp=bpp)
        try:
            next(reader)
            for buf in reader:
                yield to_gray(np.frombuffer(buf, dtype=dtype).reshape(h, w))
        finally:
            reader.close()

    fps = float(meta["fps"]) if meta.get("fps") else None
    dur = meta.get("duration")
    n = int(round(dur * fps)) if (dur and fps) else None
    info = {
        "source_pix_fmt": src_fmt,
        "decoded_pix_fmt": pix_fmt,
        "bits": 16 if high else 8,
        "codec": meta.get("codec"),
        "container_fps": fps,
    }
    return gen(), {"shape": (h, w), "fps": fps, "n_frames": n, **info}


def open_video(
    source: str | Path | ArrayLike | Iterable[ArrayLike],
    *,
    roi: tuple[int, int, int, int] | None = None,
    max_frames: int | None = None,
) -> VideoStream:
    """Open a video file, a ``.npy`` file, an array ``(T, H, W[, C])`` or an iterable of frames.

    Parameters
    ----------
    source : path, array or iterable
        See the module notes.
    roi : tuple of int, optional
        Crop ``(y0, y1, x0, x1)`` (rows ``y0:y1``, columns ``x0:x1``).
    max_frames : int, optional
        Read at most this many frames.

    Returns
    -------
    VideoStream
    """
    meta: dict[str, Any] = {}
    fps = None
    if isinstance(source, (str, Path)):
        path = Path(source)
        if not path.is_file():
            raise FileNotFoundError(f"video file not found: {path}")
        meta["source"] = str(path)
        if path.suffix.lower() == ".npy":
            arr = np.load(path, mmap_mode="r")
            frames: Iterable = arr
            shape = tuple(arr.shape[1:3])
            n = arr.shape[0]
        else:
            frames, info = _ffmpeg_frames(path)
            shape, fps, n = info.pop("shape"), info.pop("fps"), info.pop("n_frames")
            meta.update(info)
    elif isinstance(source, np.ndarray):
        frames, shape, n = source, tuple(source.shape[1:3]), source.shape[0]
        meta["source"] = f"array {source.shape} {source.dtype}"
    else:
        it = iter(source)
        try:
            first = np.asarray(next(it))
        except StopIteration:
            raise ValueError("the frame iterable is empty") from None
        frames = _chain(first, it)
        shape, n = tuple(first.shape[:2]), None
        meta["source"] = "iterable"
    if roi is not None:
        y0, y1, x0, x1 = (int(r) for r in roi)
        if not (0 <= y0 < y1 <= shape[0] and 0 <= x0 < x1 <= shape[1]):
            raise ValueError(f"roi {roi} is outside the {shape[1]}x{shape[0]} frame")
        roi = (y0, y1, x0, x1)
        shape = (y1 - y0, x1 - x0)
        meta["roi"] = list(roi)
    if max_frames is not None and n is not None:
        n = min(n, max_frames)
    gray = (to_gray(f) for f in _crop(_limit(frames, max_frames), roi))
    return VideoStream(
        frames=gray, shape=(int(shape[0]), int(shape[1])), fps=fps, n_frames=n, meta=meta
    )


def _chain(first: NDArray, rest: Iterator) -> Iterator:
    yield first
    yield from rest
