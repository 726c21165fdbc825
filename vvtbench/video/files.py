"""Video I/O for the whole package: one ffmpeg probe, one reader, one writer.

* :func:`probe_video` reads a file's size, pixel format, codec and its **exact** frame rate
  (a :class:`fractions.Fraction`, e.g. ``30000/1001`` or ``2000``).
* :func:`read_frames` decodes frames ``start:stop`` as integer ``(H, W)`` arrays (uint16 or
  uint8), frame-exactly (``-fps_mode passthrough``: no frame is dropped or duplicated because
  of time stamps).
* :class:`VideoWriter` encodes integer gray frames: lossless FFVHUFF (the default: FFmpeg's
  Huffman-coded HuffYUV, 15x faster to encode and 6x faster to decode than FFV1 at 16 bits,
  files about 25 % larger) or FFV1 (``gray16le`` or ``gray``) in Matroska, or H.264 (the
  consumer track and previews); :func:`concat_videos` joins segments. Both write a temporary
  file unique to the process next to the output and rename it into place when done (atomic;
  a symbolic link at the output is replaced, never written through).
* :func:`count_frames` counts a file's frames packet by packet (no decoding).
* :func:`open_video` opens any frame source for motion extraction as float32 gray frames.

Frame sources of :func:`open_video`: any container/codec that the ``imageio-ffmpeg`` binary
decodes (avi, mp4, mkv, ...) is read through ffmpeg's own grayscale conversion (luma): sources
with more than 8 bits per channel (e.g. ``gray16le``, ``yuv420p10le``, ``rgb48le``) are
decoded as 16-bit ``gray16le`` and scaled by ``1 / 65535``, the others as 8-bit ``gray``
scaled by ``1 / 255``.  Image sequences (a folder, a glob, a printf pattern), Photron
``.cih``/``.cihx`` + ``.mraw``, Phantom ``.cine`` and ``.npy`` files ``(T, H, W[, C])`` are
read by :mod:`vvtbench.video.cameras` (rate and bit depth from their headers, the ROI and
frame range read in place, a file cut short refused); arrays and iterables of frames are
accepted as they are.  Colour frames given as arrays use Rec. 601 luma weights.  A lossy
compressed video is described in ``meta["lossy"]`` (codec, bit depth, keyframe interval:
:func:`lossy_description`).

Frame rates.  ffmpeg prints rates of 1000 FPS and more as ``"2k fps"``, so parsing its
banner (as ``imageio_ffmpeg`` does) reads them as 0.  :func:`probe_video` instead takes the
exact rational rate that ffmpeg's filter graph receives (``showinfo``'s ``frame_rate: N/D``)
when it agrees with the stream's printed average rate, and the printed average rate
(``2k`` = 2000) otherwise (Matroska's 1 ms time base caps the former at 1000 FPS).  Videos
written by :class:`VideoWriter` carry the capture rate as the stream tag ``CAPTURE_FPS``
(an exact ``N`` or ``N/D``), which takes precedence over the container's nominal rate.
A bare stream (``.h264``, ...) or an image sequence has no time stamps: the 25 fps ffmpeg
reports for it is its demuxer's default, so its rate is unknown (None).
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import tempfile
import uuid
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .frames import VideoError, to_gray

__all__ = [
    "LOSSLESS_CODEC",
    "PLAYBACK_FPS",
    "VIDEO_SUFFIXES",
    "VideoError",
    "VideoInfo",
    "VideoStream",
    "VideoWriter",
    "FrameSpool",
    "average_frames",
    "concat_videos",
    "count_frames",
    "describe_lossy",
    "keyframe_positions",
    "lossy_description",
    "mean_frame",
    "open_video",
    "probe_video",
    "read_frames",
    "to_gray",
]

VIDEO_SUFFIXES = (".mkv", ".mp4", ".avi", ".mov", ".webm", ".m4v", ".mpg", ".mpeg", ".npy")
#: Nominal playback rate of the videos :class:`VideoWriter` writes. Matroska time stamps have
#: 1 ms resolution, so capture rates above 1000 FPS cannot be stored as time stamps; the
#: capture rate is the stream tag ``CAPTURE_FPS``.
PLAYBACK_FPS = 30
_HIGH_DEPTH = re.compile(r"(p9|p10|p12|p14|p16|9le|9be|1[0246]le|1[0246]be|48|64|f16|f32)")
BITEXACT = ["-fflags", "+bitexact", "-flags:v", "+bitexact", "-map_metadata", "-1"]
_FFV1 = ["-level", "3", "-g", "1", "-slices", "4", "-slicecrc", "1", "-threads", "2"]
_FFVHUFF = ["-pred", "median", "-threads", "1"]
#: the codec of the lossless videos vvtbench writes (``video.mkv`` of a sample)
LOSSLESS_CODEC = "ffvhuff"


def ffmpeg_exe() -> str:
    """Path of the ffmpeg binary bundled with ``imageio-ffmpeg``."""
    import imageio_ffmpeg

    return imageio_ffmpeg.get_ffmpeg_exe()


# --------------------------------------------------------------------------- frame rates
def rate_fraction(fps: float | Fraction | str) -> Fraction:
    """A frame rate as an exact fraction: ``"30000/1001"``, ``2000``, ``29.97002997...``.

    Floats are rounded to the nearest fraction with denominator at most 1001 * 1000 (so
    ``30000 / 1001`` comes back as ``Fraction(30000, 1001)``).
    """
    if isinstance(fps, Fraction):
        return fps
    if isinstance(fps, str):
        return Fraction(fps.strip())
    return Fraction(float(fps)).limit_denominator(1_001_000)


#: ffmpeg demuxers of bare streams and image sequences: no time stamps, so the rate they
#: report is their ``-framerate`` default (25), not the video's
_NO_TIMING_DEMUXERS = frozenset({
    "h264", "hevc", "vvc", "mjpeg", "m4v", "h261", "h263", "cavsvideo", "avs2", "avs3",
    "dirac", "vc1", "mpegvideo", "obu", "rawvideo", "image2", "image2pipe",
})


def _printed_rate(text: str) -> float | None:
    """ffmpeg's ``print_fps`` text (``"29.97"``, ``"1200"``, ``"2k"``) as a number."""
    m = re.fullmatch(r"([0-9]+(?:\.[0-9]+)?)(k?)", text.strip())
    if not m:
        return None
    return float(m.group(1)) * (1000.0 if m.group(2) else 1.0)


def _exact_rate(printed: float | None, graph: Fraction | None) -> Fraction | None:
    """The exact rate: the filter graph's rational if it matches the printed average rate
    (printed to 0.01), else the printed rate (integers exact, x.xx as N*1000/1001 if so)."""
    if graph is not None and graph > 0:
        if printed is None or printed <= 0 or abs(float(graph) - printed) <= 0.0051:
            return graph
    if printed is None or printed <= 0:
        return None
    if abs(printed - round(printed)) < 0.0051:
        return Fraction(round(printed))
    ntsc = round(printed * 1.001)
    if abs(ntsc * 1000 / 1001 - printed) < 0.0051:
        return Fraction(ntsc * 1000, 1001)
    return Fraction(str(printed))


# --------------------------------------------------------------------------- probe
@dataclass(frozen=True)
class VideoInfo:
    """What :func:`probe_video` found out about the first video stream of a file.

    Attributes
    ----------
    path : the file.
    width, height : frame size (px).
    pix_fmt : the stream's pixel format (e.g. ``"gray16le"``, ``"yuv420p"``).
    codec : codec name (e.g. ``"ffv1"``, ``"h264"``).
    container_rate : exact frame rate of the container's time stamps, or None (also for a
        bare stream or an image sequence, whose rate ffmpeg only assumes).
    capture_rate : the ``CAPTURE_FPS`` stream tag (videos written by vvtbench), or None.
    duration : container duration (s), or None.
    frame_count : exact frame count stated by a camera file's header, or None.
    bits : significant bits per sample of a camera file, or None.
    n_streams : streams in the file (video, audio, data).
    record_rate : the rate a camera file says the camera recorded at, when it stored every
        ``decimation``-th frame only (Photron ``Save Step``); else None.
    decimation : recorded frames per stored frame (1: every frame stored).
    """

    path: Path
    width: int
    height: int
    pix_fmt: str
    codec: str
    container_rate: Fraction | None
    capture_rate: Fraction | None
    duration: float | None
    frame_count: int | None = None
    bits: int | None = None
    n_streams: int = 1
    record_rate: Fraction | None = None
    decimation: int = 1

    @property
    def frame_rate(self) -> Fraction | None:
        """The capture rate if tagged, else the container rate."""
        return self.capture_rate if self.capture_rate is not None else self.container_rate

    @property
    def high_depth(self) -> bool:
        """More than 8 bits per sample (decode as ``gray16le``)."""
        return bool(_HIGH_DEPTH.search(self.pix_fmt))

    @property
    def n_frames(self) -> int | None:
        """Frame count estimated from duration x container rate: ffmpeg prints the duration
        to 10 ms, so at high frame rates this may be off by a few frames (count_frames is
        exact). A camera file's header states it exactly."""
        if self.frame_count is not None:
            return self.frame_count
        if self.duration and self.container_rate:
            return int(round(self.duration * float(self.container_rate)))
        return None


def _split_top(text: str) -> list[str]:
    """Split at commas outside parentheses."""
    parts, depth, cur = [], 0, ""
    for ch in text:
        depth += ch == "("
        depth -= ch == ")"
        if ch == "," and depth == 0:
            parts.append(cur.strip())
            cur = ""
        else:
            cur += ch
    parts.append(cur.strip())
    return parts


def probe_video(path: str | Path) -> VideoInfo:
    """Size, pixel format, codec and exact frame rate of the first video stream of ``path``.

    Runs ffmpeg once, decoding one frame (``-vf showinfo``). Raises :class:`VideoError`
    when the file has no decodable video stream.  Image sequences (a folder, a glob, a printf
    pattern), Photron, Phantom and ``.npy`` files are described from their headers
    (:mod:`vvtbench.video.cameras`): ``codec`` is the reader's kind, ``frame_count`` and
    ``bits`` are set, the rate is that of the stored frames (a record saved every n-th frame:
    ``record_rate`` and ``decimation``) and ``duration`` the time they span.
    """
    from .cameras import is_camera_source, open_camera_file

    if is_camera_source(path):
        cam = open_camera_file(path)
        pix = "gray" if cam.bits is not None and cam.bits <= 8 else "gray16le"
        step = int(cam.meta.get("decimation") or 1)
        record = cam.meta.get("record_fps")
        return VideoInfo(Path(str(path)), cam.width, cam.height, pix, cam.kind, cam.fps, None,
                         cam.n_frames / float(cam.fps) if cam.fps else None, cam.n_frames,
                         cam.bits, record_rate=Fraction(record) if record and step > 1
                         else None, decimation=step)
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"video file not found: {path}")
    cmd = [ffmpeg_exe(), "-hide_banner", "-nostdin", "-nostats", "-v", "verbose", "-i",
           f"file:{path}",
           "-map", "0:v:0", "-frames:v", "1", "-vf", "showinfo", "-f", "null", "-"]
    proc = subprocess.run(cmd, capture_output=True, text=True, errors="replace")
    err = proc.stderr
    lines = err.splitlines()
    idx = next((i for i, ln in enumerate(lines) if re.search(r"Stream #\d+:\d+.*: Video: ", ln)),
               None)
    if proc.returncode != 0 or idx is None:
        tail = "; ".join(lines[-3:]) if lines else "no output"
        raise VideoError(f"{path}: cannot be decoded by ffmpeg: {tail}")
    parts = _split_top(lines[idx].split(": Video: ", 1)[1])
    codec = parts[0].split()[0]
    pix_fmt = next((q.split("(")[0] for q in parts[1:]
                    if re.fullmatch(r"[a-z][a-z0-9_]*(\(.*\))?", q)), "")
    width = height = 0
    printed = None
    for part in parts[1:]:
        m = re.match(r"(\d+)x(\d+)", part)
        if m and not width:
            width, height = int(m.group(1)), int(m.group(2))
        m = re.fullmatch(r"(\S+) fps", part)
        if m:
            printed = _printed_rate(m.group(1))
    graph = None
    m = re.search(r"config in time_base: \d+/\d+, frame_rate: (\d+)/(\d+)", err)
    if m and int(m.group(2)) > 0 and int(m.group(1)) > 0:
        graph = Fraction(int(m.group(1)), int(m.group(2)))
    capture = None
    for ln in lines[idx + 1:]:
        if re.match(r"\s*(Stream|Output|Input) ", ln):
            break
        m = re.match(r"\s*CAPTURE_FPS\s*:\s*(\S+)", ln, re.IGNORECASE)
        if m:
            try:
                capture = rate_fraction(m.group(1))
            except (ValueError, ZeroDivisionError):
                capture = None
            break
    duration = None
    m = re.search(r"Duration: (\d+):(\d+):(\d+(?:\.\d+)?)", err)
    if m:
        duration = int(m.group(1)) * 3600 + int(m.group(2)) * 60 + float(m.group(3))
    if not width:
        raise VideoError(f"{path}: ffmpeg reports no frame size for the video stream")
    m = re.search(r"Input #\d+, ([\w,]+), from ", err)
    guessed = m is not None and bool(set(m.group(1).split(",")) & _NO_TIMING_DEMUXERS)
    head = err.split("Stream mapping:", 1)[0].split("\nOutput #", 1)[0]
    n_streams = max(1, len(re.findall(r"^\s*Stream #\d+:\d+", head, re.MULTILINE)))
    return VideoInfo(path, width, height, pix_fmt, codec,
                     None if guessed else _exact_rate(printed, graph), capture, duration,
                     n_streams=n_streams)


def count_frames(path: str | Path) -> int:
    """The number of video frames in ``path``, counted packet by packet (stream copy, no
    decoding: the whole file is read once). A file cut short with its header intact (whose
    container duration still claims every frame) gives the frames actually there."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"video file not found: {path}")
    cmd = [ffmpeg_exe(), "-hide_banner", "-nostdin", "-v", "error", "-stats", "-i",
           f"file:{path}", "-map", "0:v:0", "-c", "copy", "-f", "null", "-"]
    proc = subprocess.run(cmd, capture_output=True, text=True, errors="replace")
    found = re.findall(r"frame=\s*(\d+)", proc.stderr)
    if not found:
        tail = "; ".join(proc.stderr.strip().splitlines()[-2:]) or "no output"
        raise VideoError(f"{path}: cannot count the frames: {tail}")
    return int(found[-1])


def _temporary_name(out: Path) -> Path:
    """A temporary file name next to ``out``, unique to this process and call, with the same
    suffix (ffmpeg picks the container by it)."""
    return out.with_name(f".{out.stem}.{os.getpid()}-{uuid.uuid4().hex[:8]}.tmp{out.suffix}")


# --------------------------------------------------------------------------- reader
def read_frames(
    path: str | Path,
    *,
    bpp: int = 2,
    start: int = 0,
    stop: int | None = None,
    info: VideoInfo | None = None,
) -> Iterator[np.ndarray]:
    """Decode frames ``start:stop`` of ``path`` as ``(H, W)`` gray integer arrays.

    Parameters
    ----------
    path : video file.
    bpp : 2 decodes to ``gray16le`` (uint16), 1 to ``gray`` (uint8), through ffmpeg's luma.
    start, stop : frame range (``stop`` None: to the end). Frames before ``start`` are
        skipped by a time seek to half a frame before it when the container's time stamps
        resolve frames, otherwise by decoding and dropping them (frame-exact either way).
    info : the file's :func:`probe_video` result (probed if not given).
    """
    if bpp not in (1, 2):
        raise ValueError(f"bpp must be 1 or 2, got {bpp}")
    info = info or probe_video(path)
    pix, dtype = ("gray16le", np.dtype("<u2")) if bpp == 2 else ("gray", np.dtype(np.uint8))
    h, w = info.height, info.width
    pre: list[str] = []
    filters: list[str] = []
    if start > 0:
        rate = info.container_rate
        if rate is not None and rate <= 250:  # time stamps (>= 1 ms) separate the frames
            pre = ["-ss", f"{(start - 0.5) / float(rate):.6f}"]
        else:
            filters = ["-vf", f"select=gte(n\\,{int(start)})"]
    limit = ["-frames:v", str(int(stop) - int(start))] if stop is not None else []
    if stop is not None and stop <= start:
        return
    cmd = [ffmpeg_exe(), "-v", "error", "-nostdin", *pre, "-i", f"file:{path}", "-map", "0:v:0",
           *filters, "-fps_mode", "passthrough", *limit, "-f", "rawvideo", "-pix_fmt", pix, "-"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    size = h * w * dtype.itemsize
    try:
        while True:
            buf = proc.stdout.read(size)
            if not buf:
                break
            if len(buf) < size:
                raise VideoError(f"{path}: truncated frame from ffmpeg ({len(buf)} of {size} B)")
            yield np.frombuffer(buf, dtype=dtype).reshape(h, w)
    finally:
        proc.stdout.close()
        if proc.poll() is None:
            proc.kill()
        proc.wait()
        msg = proc.stderr.read().decode(errors="replace").strip()
        proc.stderr.close()
    if proc.returncode not in (0, None) and msg:
        raise VideoError(f"{path}: ffmpeg failed decoding: {msg}")


# --------------------------------------------------------------------------- writer
class VideoWriter:
    """Encoder of integer gray frames (context manager).

    Parameters
    ----------
    path : output file (``.mkv`` for FFVHUFF and FFV1, ``.mp4`` for H.264).
    height, width : frame size (px).
    capture_fps : stored exactly in the stream tag ``CAPTURE_FPS`` (None: no tag).
    pix_fmt : frames given as ``"gray16le"`` (uint16) or ``"gray"`` (uint8).
    codec : ``"ffvhuff"`` or ``"ffv1"`` (lossless; stored in ``pix_fmt``; FFVHUFF is much
        cheaper to encode and decode, FFV1 smaller and slice-checksummed) or ``"h264"``
        (libx264, 8-bit; ``yuv420p`` output, odd sizes padded with zeros to even at the
        bottom/right).
    crf : H.264 constant rate factor (``codec="h264"``).
    playback_fps : the container's nominal rate (see :data:`PLAYBACK_FPS`).

    Output is bit-exact (``+bitexact`` flags, fixed threads, no time stamps in metadata).
    """

    def __init__(self, path: str | Path, height: int, width: int, *,
                 capture_fps: float | Fraction | str | None = None, pix_fmt: str = "gray16le",
                 codec: str = LOSSLESS_CODEC, crf: int = 23,
                 playback_fps: float = PLAYBACK_FPS) -> None:
        import imageio_ffmpeg

        if pix_fmt not in ("gray16le", "gray"):
            raise ValueError(f"pix_fmt must be 'gray16le' or 'gray', got {pix_fmt!r}")
        if codec not in ("ffvhuff", "ffv1", "h264"):
            raise ValueError(f"codec must be 'ffvhuff', 'ffv1' or 'h264', got {codec!r}")
        tag = [] if capture_fps is None else [
            "-metadata:s:v:0", f"CAPTURE_FPS={rate_fraction(capture_fps)}"]
        self._dtype = np.dtype("<u2") if pix_fmt == "gray16le" else np.dtype(np.uint8)
        self.shape = (int(height), int(width))
        self._pad = (0, 0)
        if codec in ("ffv1", "ffvhuff"):
            params = _FFV1 if codec == "ffv1" else _FFVHUFF
            out_fmt, vcodec, params = pix_fmt, codec, params + BITEXACT + tag
        else:
            if pix_fmt != "gray":
                raise ValueError("codec 'h264' takes 8-bit frames (pix_fmt='gray')")
            self._pad = (height % 2, width % 2)
            out_fmt, vcodec = "yuv420p", "libx264"
            params = ["-crf", str(int(crf)), "-preset", "medium", "-threads", "1",
                      *BITEXACT, *tag]
        size = (width + self._pad[1], height + self._pad[0])
        self.path = Path(path)
        self._tmp = _temporary_name(self.path)
        self._closed = False
        self._gen = imageio_ffmpeg.write_frames(
            f"file:{self._tmp}", size, pix_fmt_in=pix_fmt, pix_fmt_out=out_fmt, codec=vcodec,
            quality=None, fps=playback_fps, macro_block_size=1, output_params=params,
            ffmpeg_log_level="error",
        )
        self._gen.send(None)

    def write(self, frame: np.ndarray) -> None:
        """Append one ``(H, W)`` frame of DN."""
        a = np.asarray(frame, dtype=self._dtype)
        if a.shape != self.shape:
            raise ValueError(f"frame shape {a.shape} != writer shape {self.shape}")
        if any(self._pad):
            a = np.pad(a, ((0, self._pad[0]), (0, self._pad[1])))
        self._gen.send(np.ascontiguousarray(a))

    def close(self) -> None:
        """Finish the file and rename it to ``path`` (atomic)."""
        if self._closed:
            return
        self._closed = True
        try:
            self._gen.close()
        except BaseException:
            self._tmp.unlink(missing_ok=True)
            raise
        os.replace(self._tmp, self.path)

    def abort(self) -> None:
        """Stop encoding and remove the partial file; ``path`` is left as it was."""
        if self._closed:
            return
        self._closed = True
        try:
            self._gen.close()
        except Exception:  # noqa: BLE001 -- the partial file is removed either way
            pass
        self._tmp.unlink(missing_ok=True)

    def __enter__(self) -> VideoWriter:
        return self

    def __exit__(self, exc_type, *exc) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def _concat_line(p: Path) -> str:
    """One ``file`` line of ffmpeg's concat list: the path in single quotes, each ``'``
    written as ``'\\''`` (close the quote, an escaped quote, reopen)."""
    return "file '" + str(p).replace("'", "'\\''") + "'\n"


def concat_videos(segments: list[Path], out: Path, *, capture_fps: float | Fraction | None = None,
                  crf: int | None = None) -> None:
    """Join video segments into ``out``: stream copy, or (``crf``) re-encode as 8-bit gray
    H.264 at that CRF.

    Works for any path: the segments are linked under plain names into a private temporary
    folder, and the listing names those (a path with a quote or a newline cannot break it).
    The output is written to a temporary name unique to the process and renamed to ``out``.
    """
    out = Path(out)
    if not segments:
        raise VideoError(f"{out}: no video segments to join")
    work = Path(tempfile.mkdtemp(prefix="vvtbench-concat-"))
    tmp = _temporary_name(out)
    try:
        lines = []
        for i, seg in enumerate(segments):
            seg = Path(seg).resolve()
            if not seg.is_file():
                raise VideoError(f"{seg}: video segment not found")
            link = work / f"seg_{i:06d}{seg.suffix}"
            try:
                link.symlink_to(seg)
                lines.append(_concat_line(link))
            except OSError:  # no symbolic links here: quote the path itself
                if "\n" in str(seg) or "\r" in str(seg):
                    raise VideoError(f"{seg!r}: a segment path with a line break cannot be "
                                     "joined on this file system") from None
                lines.append(_concat_line(seg))
        listing = work / "segments.txt"
        listing.write_text("".join(lines))
        codec = ["-c", "copy"] if crf is None else [
            "-c:v", "libx264", "-preset", "medium", "-crf", str(int(crf)), "-pix_fmt", "gray",
            "-threads", "2", "-r", str(PLAYBACK_FPS)]
        tag = [] if capture_fps is None else [
            "-metadata:s:v:0", f"CAPTURE_FPS={rate_fraction(capture_fps)}"]
        cmd = [ffmpeg_exe(), "-nostdin", "-y", "-loglevel", "error", "-f", "concat", "-safe",
               "0", "-i", f"file:{listing}", *codec, *BITEXACT, *tag, f"file:{tmp.resolve()}"]
        proc = subprocess.run(cmd, capture_output=True, text=True, errors="replace")
        if proc.returncode != 0:
            raise VideoError(f"{out}: ffmpeg failed joining the video segments: "
                             + "; ".join(proc.stderr.strip().splitlines()[-3:]))
        os.replace(tmp, out)
    finally:
        tmp.unlink(missing_ok=True)
        shutil.rmtree(work, ignore_errors=True)


# --------------------------------------------------------------------------- float frames


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


def mean_frame(frames: Iterable[ArrayLike]) -> tuple[NDArray[np.float32], int]:
    """Temporal mean of a stream of ``(H, W)`` frames (float64 sums, one frame in memory)
    and the number of frames; ``ValueError`` for an empty stream."""
    acc: NDArray[np.float64] | None = None
    n = 0
    for f in frames:
        a = np.asarray(f)
        if acc is None:
            acc = np.zeros(a.shape, np.float64)
        elif a.shape != acc.shape:
            raise ValueError(f"frame {n} is {a.shape}, the first was {acc.shape}")
        acc += a
        n += 1
    if acc is None:
        raise ValueError("the video has no frames")
    return (acc / n).astype(np.float32), n


class FrameSpool:
    """Frames kept for a second pass over a one-shot stream (context manager).

    ``append`` keeps float32 frames in RAM up to ``memory_budget`` bytes, then moves them to a
    raw file in a temporary directory under ``tmpdir`` (deleted by :meth:`close`); iterating
    gives them back in order, reading the file a chunk of frames at a time.
    """

    def __init__(self, memory_budget: int = 1 << 30, tmpdir: str | None = None,
                 chunk_bytes: int = 64 << 20) -> None:
        if memory_budget < 0:
            raise ValueError(f"memory_budget must be >= 0, got {memory_budget}")
        self.memory_budget = int(memory_budget)
        self.tmpdir = tmpdir
        self.chunk_bytes = int(chunk_bytes)
        self.shape: tuple[int, ...] | None = None
        self.n_frames = 0
        self._ram: list[NDArray[np.float32]] = []
        self._dir: str | None = None
        self._file = None

    def __enter__(self) -> FrameSpool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:  # pragma: no cover - best effort
        try:
            self.close()
        except Exception:
            pass

    @property
    def on_disk(self) -> bool:
        """Whether the frames live in the temporary file."""
        return self._file is not None

    def append(self, frame: ArrayLike) -> None:
        a = np.ascontiguousarray(frame, dtype=np.float32)
        if self.shape is None:
            self.shape = a.shape
        elif a.shape != self.shape:
            raise ValueError(f"frame {self.n_frames} is {a.shape}, the first was {self.shape}")
        self.n_frames += 1
        if self._file is None and (self.n_frames * a.nbytes <= self.memory_budget):
            self._ram.append(a)
            return
        if self._file is None:
            self._dir = tempfile.mkdtemp(prefix="vvtbench-frames-", dir=self.tmpdir)
            self._file = open(os.path.join(self._dir, "frames.f32"), "w+b")  # noqa: SIM115
            for r in self._ram:
                self._file.write(r.data)
            self._ram = []
        self._file.write(a.data)

    def __iter__(self) -> Iterator[NDArray[np.float32]]:
        if self._file is None:
            yield from self._ram
            return
        self._file.flush()
        size = int(np.prod(self.shape)) * 4
        step = max(1, self.chunk_bytes // size)
        for k0 in range(0, self.n_frames, step):
            n = min(step, self.n_frames - k0)
            self._file.seek(k0 * size)
            buf = np.frombuffer(self._file.read(n * size), np.float32)
            if buf.size != n * int(np.prod(self.shape)):
                raise OSError("short read from the frame spool")
            yield from buf.reshape(n, *self.shape)

    def close(self) -> None:
        """Release the frames and delete the temporary directory (idempotent)."""
        self._ram = []
        if self._file is not None:
            self._file.close()
            self._file = None
        if self._dir is not None:
            shutil.rmtree(self._dir, ignore_errors=True)
            self._dir = None


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
        Frame rate of a file: its ``CAPTURE_FPS`` tag, else the container's exact rate
        (:func:`probe_video`); None for arrays and iterables.
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
    rate: Fraction | None = None
    """The exact frame rate behind ``fps`` (None when unknown)."""


def _crop(frames: Iterable[NDArray], roi: tuple[int, int, int, int] | None) -> Iterator[NDArray]:
    for f in frames:
        yield f if roi is None else f[roi[0] : roi[1], roi[2] : roi[3]]


def _limit(frames: Iterable[NDArray], n: int | None) -> Iterator[NDArray]:
    for i, f in enumerate(frames):
        if n is not None and i >= n:
            return
        yield f


#: codecs that keep every sample: no compression artefacts, no keyframe comb
LOSSLESS_CODECS = frozenset({
    "ffv1", "ffvhuff", "huffyuv", "rawvideo", "png", "apng", "utvideo", "magicyuv", "tiff",
    "qtrle", "v210", "v410", "r210", "zlib", "zmbv", "flashsv", "lagarith", "fits", "bmp",
    "pgm", "pam", "qoi", "sgi", "targa", "dpx", "exr", "jpegls", "jpeg2000-lossless",
})
#: frames decoded to find the keyframes of a lossy video
KEYFRAME_PROBE_FRAMES = 600


def keyframe_positions(path: str | Path, *, max_frames: int = KEYFRAME_PROBE_FRAMES) -> tuple[
        list[int], int]:
    """Indices of the keyframes among the first ``max_frames`` frames of ``path`` and the
    number of frames looked at (decoded once through ffmpeg's ``showinfo``: ``iskey``)."""
    cmd = [ffmpeg_exe(), "-hide_banner", "-nostdin", "-nostats", "-v", "info", "-i",
           f"file:{path}", "-map", "0:v:0", "-frames:v", str(int(max_frames)),
           "-fps_mode", "passthrough", "-vf", "showinfo", "-f", "null", "-"]
    proc = subprocess.run(cmd, capture_output=True, text=True, errors="replace")
    keys, seen = [], 0
    for line in proc.stderr.splitlines():
        m = re.search(r"\bn:\s*(\d+).*\biskey:\s*([01])", line)
        if m:
            seen = max(seen, int(m.group(1)) + 1)
            if m.group(2) == "1":
                keys.append(int(m.group(1)))
    if proc.returncode != 0 and not seen:
        tail = "; ".join(proc.stderr.strip().splitlines()[-2:]) or "no output"
        raise VideoError(f"{path}: cannot read the keyframes: {tail}")
    return keys, seen


def lossy_description(path: str | Path, info: VideoInfo) -> dict[str, Any] | None:
    """What makes a compressed video lossy, or None for a lossless codec.

    Returns ``{"codec", "bits", "gop", "keyframes", "frames_probed"}``: ``gop`` is the
    keyframe interval (frames; the median spacing of the keyframes among the first
    :data:`KEYFRAME_PROBE_FRAMES` frames), 1 for intra-only codecs (MJPEG, every frame a
    keyframe), None when at most one keyframe was seen.
    """
    if info.codec in LOSSLESS_CODECS:
        return None
    keys, seen = keyframe_positions(path)
    gop: int | None = None
    if len(keys) >= 2:
        gop = int(np.median(np.diff(keys)))
    elif seen and len(keys) == seen:
        gop = 1
    return {"codec": info.codec, "bits": 16 if info.high_depth else 8,
            "pix_fmt": info.pix_fmt, "gop": gop, "keyframes": keys[:32],
            "frames_probed": int(seen)}


def describe_lossy(lossy: dict[str, Any], fps: float | None) -> str:
    """One line naming a lossy source (see :func:`lossy_description`)."""
    text = f"lossy source: {lossy['codec']} {lossy['bits']}-bit"
    gop = lossy.get("gop")
    if gop == 1:
        text += ", every frame a keyframe (intra-only)"
    elif gop:
        text += f", a keyframe every {gop} frames"
        if fps:
            text += (f": peaks on the keyframe comb (multiples of {fps / gop:g} Hz) are "
                     "rejected")
    else:
        text += f", no keyframe interval seen in {lossy.get('frames_probed', 0)} frames"
    return text + "; compression artefacts move like texture (prefer the camera's raw files)"


def _file_frames(path: Path, start: int, stop: int | None) -> tuple[
        Iterator[NDArray[np.float32]], VideoInfo, dict[str, Any]]:
    info = probe_video(path)
    bpp = 2 if info.high_depth else 1

    def gen() -> Iterator[NDArray[np.float32]]:
        count = start
        for frame in read_frames(path, bpp=bpp, info=info, start=start, stop=stop):
            count += 1
            yield to_gray(frame)
        expected = info.n_frames
        # a single-stream file whose container claims 10 % (and 3 frames) more than it holds
        # was cut short; rounding of the duration explains a frame or two, never that
        if stop is None and expected and info.n_streams == 1 \
                and count < 0.9 * expected and expected - count > 2:
            raise VideoError(f"{path}: truncated: the container says {expected} frames "
                             f"({info.duration:g} s), the file holds {count}")

    meta = {
        "source_pix_fmt": info.pix_fmt,
        "decoded_pix_fmt": "gray16le" if bpp == 2 else "gray",
        "bits": 16 if bpp == 2 else 8,
        "codec": info.codec,
        "container_fps": float(info.container_rate) if info.container_rate else None,
        "frame_rate": str(info.frame_rate) if info.frame_rate else None,
        "frame_rate_source": "CAPTURE_FPS tag" if info.capture_rate is not None
        else ("container" if info.container_rate is not None else None),
    }
    lossy = lossy_description(path, info)
    if lossy is not None:
        meta["lossy"] = lossy
    return gen(), info, meta


def _frame_range(start: int, stop: int | None, n: int | None) -> tuple[int, int | None]:
    start = int(start)
    if start < 0 or (stop is not None and int(stop) <= start):
        raise ValueError(f"frame range {start}:{'' if stop is None else stop} is empty or "
                         "negative; need 0 <= start < stop")
    if n is not None and start >= n:
        raise ValueError(f"frame range starts at {start}, and the video has {n} frames")
    stop = None if stop is None else int(stop)
    if n is not None and stop is not None and stop > n:
        raise ValueError(f"frame range {start}:{stop} ends after the video's {n} frames")
    return start, stop


def open_video(
    source: str | Path | ArrayLike | Iterable[ArrayLike],
    *,
    roi: tuple[int, int, int, int] | None = None,
    max_frames: int | None = None,
    start: int = 0,
    stop: int | None = None,
    bit_depth: int | None = None,
) -> VideoStream:
    """Open a video file, a camera file, an array ``(T, H, W[, C])`` or an iterable of frames.

    Parameters
    ----------
    source : path, array or iterable
        See the module notes; image sequences (a folder, a glob, a printf pattern), Photron
        ``.cih``/``.cihx``/``.mraw``, Phantom ``.cine`` and ``.npy`` files are read by
        :mod:`vvtbench.video.cameras` (frame rate and bit depth from their headers).
    roi : tuple of int, optional
        Crop ``(y0, y1, x0, x1)`` (rows ``y0:y1``, columns ``x0:x1``); camera files read only
        those rows.
    max_frames : int, optional
        Read at most this many frames (counted from ``start``).
    start, stop : int
        Frame range ``start:stop`` of the source (``stop`` None: to the end), applied while
        reading.
    bit_depth : int, optional
        Significant bits per sample of an image sequence, camera or ``.npy`` file (overrides
        its header): samples are scaled by ``2**bit_depth - 1``.

    Returns
    -------
    VideoStream
        For a lossy compressed video ``meta["lossy"]`` describes the codec, its bit depth and
        keyframe interval (:func:`lossy_description`).
    """
    meta: dict[str, Any] = {}
    rate: Fraction | None = None
    from .cameras import is_camera_source, open_camera_file

    if isinstance(source, (str, Path)) and is_camera_source(source):
        cam = open_camera_file(source, bit_depth=bit_depth)
        start, stop = _frame_range(start, stop, cam.n_frames)
        shape, rate = (cam.height, cam.width), cam.fps
        roi = _check_roi(roi, shape)
        last = cam.n_frames if stop is None else stop
        if max_frames is not None:
            last = min(last, start + int(max_frames))
        meta.update(source=str(source), reader=cam.kind, bits=cam.bits,
                    frame_rate=str(rate) if rate is not None else None,
                    frame_rate_source="file header" if rate is not None else None,
                    frame_range=[start, last], **cam.meta)
        if roi is not None:
            meta["roi"] = list(roi)
            shape = (roi[1] - roi[0], roi[3] - roi[2])
        return VideoStream(
            frames=cam.frames(start, last, roi), shape=(int(shape[0]), int(shape[1])),
            fps=float(rate) if rate is not None else None, n_frames=last - start, meta=meta,
            rate=rate)
    if bit_depth is not None:
        raise ValueError("--bit-depth applies to image sequences, .npy, Photron and Phantom "
                         "files; a compressed video's decoder sets its own depth")
    if isinstance(source, (str, Path)):
        path = Path(source)
        if not path.is_file():
            raise FileNotFoundError(f"video file not found: {path}")
        meta["source"] = str(path)
        start, stop = _frame_range(start, stop, None)
        frames, info, more = _file_frames(path, start, stop)
        shape, rate, n = (info.height, info.width), info.frame_rate, info.n_frames
        if n is not None:
            n = max(0, (n if stop is None else min(n, stop)) - start)
        if start or stop is not None:
            meta["frame_range"] = [start, stop]
        meta.update(more)
    elif isinstance(source, np.ndarray):
        start, stop = _frame_range(start, stop, source.shape[0])
        source = source[start:stop]
        frames, shape, n = source, tuple(source.shape[1:3]), source.shape[0]
        meta["source"] = f"array {source.shape} {source.dtype}"
    else:
        if start or stop is not None:
            source = _islice(source, start, stop)
        it = iter(source)
        try:
            first = np.asarray(next(it))
        except StopIteration:
            raise ValueError("the frame iterable is empty") from None
        frames = _chain(first, it)
        shape, n = tuple(first.shape[:2]), None
        meta["source"] = "iterable"
    roi = _check_roi(roi, shape)
    if roi is not None:
        shape = (roi[1] - roi[0], roi[3] - roi[2])
        meta["roi"] = list(roi)
    if max_frames is not None and n is not None:
        n = min(n, max_frames)
    gray = (to_gray(f) for f in _crop(_limit(frames, max_frames), roi))
    return VideoStream(
        frames=gray, shape=(int(shape[0]), int(shape[1])),
        fps=float(rate) if rate is not None else None, n_frames=n, meta=meta, rate=rate,
    )


def _check_roi(roi: tuple[int, int, int, int] | None,
               shape: tuple[int, ...]) -> tuple[int, int, int, int] | None:
    if roi is None:
        return None
    y0, y1, x0, x1 = (int(r) for r in roi)
    if not (0 <= y0 < y1 <= shape[0] and 0 <= x0 < x1 <= shape[1]):
        raise ValueError(f"roi {tuple(roi)} is outside the {shape[1]}x{shape[0]} frame "
                         "(y0,y1,x0,x1 with 0 <= y0 < y1 <= height, 0 <= x0 < x1 <= width)")
    return (y0, y1, x0, x1)


def _islice(frames: Iterable, start: int, stop: int | None) -> Iterator:
    import itertools

    start, stop = _frame_range(start, stop, None)
    return itertools.islice(frames, start, stop)


def _chain(first: NDArray, rest: Iterator) -> Iterator:
    yield first
    yield from rest
