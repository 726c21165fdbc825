"""Readers of the files high-speed cameras write, behind :func:`vvtbench.video.files.open_video`.

* **Image sequences**: a folder of images, a glob (``frames/*.tif``) or a printf pattern
  (``img_%05d.png``); TIFF (8, 12 or 16 bits, read with tifffile) and PNG (8 or 16 bits).
  Frames are ordered by the number in their names (``img_2`` before ``img_10``). An image
  sequence has no frame rate.
* **Photron** ``.cih``/``.cihx`` + ``.mraw``: the header is parsed by pyMRAW
  (frame rate, size, frame count, colour bits 8/12/16, effective bit depth and side) and the
  save step read beside it (the rate of the stored frames is the record rate over the step);
  frames are read from the ``.mraw`` by offset (12-bit data is packed, two pixels in three
  bytes).
* **Phantom** ``.cine``: CINEFILEHEADER, BITMAPINFOHEADER, SETUP (``FrameRate``,
  ``RealBPP``) and the table of image offsets; gray images uncompressed at 8 or 16 bits, or
  packed: P10 (10-bit log-encoded samples, linearised to 12 bits through Phantom's table)
  and P12L (12-bit linear), both most significant bit first (see :func:`open_phantom`).
* **NumPy** ``.npy`` ``(T, H, W)`` or ``(T, H, W, C)``: real numbers only; NaN or infinite
  values are refused at the frame that holds them.

Every reader reads frame by frame, only the rows of the region of interest where the layout
allows it, so memory stays bounded whatever the file's size. A file shorter than its header
says is refused (frames expected vs found), never read as a shorter video.

Bit depth: integer samples are scaled to ``[0, 1]`` by ``2**bits - 1`` where ``bits`` is the
depth the file states (TIFF ``BitsPerSample`` or ``MaxSampleValue``/``SMaxSampleValue``,
Photron ``EffectiveBit Depth``, Phantom ``RealBPP``) or the caller's ``bit_depth``; a sample
above that range is an error (the stated depth is wrong).
"""

from __future__ import annotations

import glob
import math
import os
import re
import struct
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .frames import VideoError, to_gray

__all__ = [
    "CAMERA_SUFFIXES",
    "CINE_PACKINGS",
    "IMAGE_SUFFIXES",
    "P10_TO_LINEAR",
    "CameraFile",
    "is_camera_source",
    "open_camera_file",
    "open_image_sequence",
    "open_npy",
    "open_phantom",
    "open_photron",
    "unpack_msb_first",
    "write_cine",
]

IMAGE_SUFFIXES = (".tif", ".tiff", ".png")
CAMERA_SUFFIXES = (".cih", ".cihx", ".mraw", ".cine", ".npy", *IMAGE_SUFFIXES)
_PRINTF = re.compile(r"%(0?)(\d*)d")


Roi = tuple[int, int, int, int]


@dataclass
class CameraFile:
    """A camera file (or image sequence) opened for reading.

    Attributes
    ----------
    kind : ``"image sequence"``, ``"photron"``, ``"phantom"`` or ``"npy"``.
    path : the file, folder or pattern.
    height, width : frame size (px).
    n_frames : frames in the file.
    bits : significant bits per sample (None for floating-point data).
    fps : exact frame rate from the file's metadata, or None (image sequences, ``.npy``).
    meta : what was read from the header (JSON-serialisable).
    """

    kind: str
    path: Path
    height: int
    width: int
    n_frames: int
    bits: int | None
    fps: Fraction | None
    meta: dict[str, Any] = field(default_factory=dict)
    read_rows: Callable[[int, int, int], NDArray] | None = None
    """``read_rows(index, y0, y1)``: rows ``y0:y1`` of frame ``index`` as an integer (or
    float) array ``(y1 - y0, W[, C])``."""

    def frames(self, start: int = 0, stop: int | None = None,
               roi: Roi | None = None) -> Iterator[NDArray[np.float32]]:
        """Frames ``start:stop`` cropped to ``roi = (y0, y1, x0, x1)``, as float32 in ``[0, 1]``
        for integer samples (scaled by ``2**bits - 1``)."""
        stop = self.n_frames if stop is None else min(int(stop), self.n_frames)
        y0, y1, x0, x1 = roi if roi is not None else (0, self.height, 0, self.width)
        top = None if self.bits is None else (1 << self.bits) - 1
        assert self.read_rows is not None
        for k in range(int(start), stop):
            rows = self.read_rows(k, y0, y1)[:, x0:x1]
            if top is None:
                if not np.all(np.isfinite(rows)):
                    raise VideoError(f"{self.path}: frame {k} holds NaN or infinite values")
                out = rows.astype(np.float32)
            else:
                peak = int(rows.max()) if rows.size else 0
                if peak > top:
                    raise VideoError(
                        f"{self.path}: frame {k} holds the value {peak}, above the "
                        f"{self.bits}-bit range (0..{top}): the bit depth is wrong "
                        "(--bit-depth sets it)")
                out = rows.astype(np.float32) * np.float32(1.0 / top)
            if out.ndim == 3:
                out = to_gray(out)
            yield out


def _check_bit_depth(bit_depth: int | None, container: int, where: str) -> None:
    if bit_depth is not None and not 1 <= int(bit_depth) <= container:
        raise VideoError(f"{where}: --bit-depth {bit_depth} must be between 1 and {container} "
                         f"(the samples are stored in {container} bits)")


# --------------------------------------------------------------------------- detection
def _has_pattern(text: str) -> bool:
    return any(c in text for c in "*?[") or bool(_PRINTF.search(text))


def is_camera_source(source: str | Path) -> bool:
    """Whether ``source`` is read by this module: a folder, a glob or printf pattern, or a
    file with one of :data:`CAMERA_SUFFIXES`."""
    text = str(source)
    p = Path(text)
    if p.is_dir() or (not p.exists() and _has_pattern(p.name)):
        return True
    return p.suffix.lower() in CAMERA_SUFFIXES


def open_camera_file(source: str | Path, *, bit_depth: int | None = None) -> CameraFile:
    """Open an image sequence, a Photron, Phantom or ``.npy`` file (see the module notes).

    Raises :class:`VideoError` (one line naming the file) when it cannot be read and
    :class:`FileNotFoundError` when it does not exist.
    """
    text = str(source)
    p = Path(text)
    if p.is_dir() or (not p.exists() and _has_pattern(p.name)):
        return open_image_sequence(text, bit_depth=bit_depth)
    if not p.is_file():
        raise FileNotFoundError(2, "no such file", text)
    suffix = p.suffix.lower()
    if suffix in (".cih", ".cihx", ".mraw"):
        return open_photron(p, bit_depth=bit_depth)
    if suffix == ".cine":
        return open_phantom(p, bit_depth=bit_depth)
    if suffix == ".npy":
        return open_npy(p, bit_depth=bit_depth)
    if suffix in IMAGE_SUFFIXES:
        return open_image_sequence(text, bit_depth=bit_depth)
    raise VideoError(f"{p}: not a camera file (allowed: {', '.join(CAMERA_SUFFIXES)}, a "
                     "folder of images, a glob or a printf pattern)")


# --------------------------------------------------------------------------- sequences
def _natural_key(path: Path) -> tuple:
    return tuple(int(t) if t.isdigit() else t for t in re.split(r"(\d+)", path.name))


def _sequence_files(spec: str) -> list[Path]:
    p = Path(spec)
    if p.is_dir():
        files = [q for q in p.iterdir() if q.suffix.lower() in IMAGE_SUFFIXES and q.is_file()]
        suffixes = sorted({q.suffix.lower().replace(".tiff", ".tif") for q in files})
        if len(suffixes) > 1:
            raise VideoError(f"{p}: a folder of images of more than one kind "
                             f"({', '.join(suffixes)}); give a glob such as {p}/*.tif")
        return sorted(files, key=_natural_key)
    if _PRINTF.search(p.name):
        m = _PRINTF.search(p.name)
        width = int(m.group(2)) if m.group(2) else 0
        digits = rf"\d{{{width}}}" if m.group(1) and width else r"\d+"
        rx = re.compile(re.escape(p.name[:m.start()]) + f"({digits})"
                        + re.escape(p.name[m.end():]) + r"\Z")
        folder = p.parent
        if not folder.is_dir():
            return []
        found = [(int(mm.group(1)), q) for q in folder.iterdir()
                 if (mm := rx.match(q.name)) and q.is_file()]
        return [q for _, q in sorted(found)]
    return sorted((Path(q) for q in glob.glob(spec) if Path(q).is_file()), key=_natural_key)


def _number_gaps(files: list[Path]) -> str | None:
    """The first gap in the frame numbers of ``files`` (names ending in a number), or None."""
    nums = []
    for q in files:
        m = re.search(r"(\d+)\D*\Z", q.stem)
        if m is None:
            return None
        nums.append(int(m.group(1)))
    for a, b, qa, qb in zip(nums, nums[1:], files, files[1:], strict=False):
        if b != a + 1:
            return f"{qa.name} is followed by {qb.name}"
    return None


def _tiff_bits(path: Path) -> tuple[int, int, dict[str, Any]]:
    """(significant bits, container bits, tags read) of a TIFF's first page."""
    import tifffile

    with tifffile.TiffFile(path) as tif:
        page = tif.pages.first
        bps = page.bitspersample
        container = int(np.dtype(page.dtype).itemsize * 8) if page.dtype is not None else bps
        tags = {}
        for name in ("MaxSampleValue", "SMaxSampleValue"):
            tag = page.tags.get(name)
            if tag is not None:
                value = tag.value
                tags[name] = int(np.max(value)) if not isinstance(value, int) else value
    bits = int(bps)
    if bits == container:
        for value in tags.values():
            if 0 < value < (1 << container) - 1 and ((value + 1) & value) == 0:
                bits = int(value).bit_length()
                break
    return bits, container, {"BitsPerSample": int(bps), **tags}


def _read_image(path: Path) -> NDArray:
    if path.suffix.lower() in (".tif", ".tiff"):
        import tifffile

        return tifffile.imread(path, key=0)
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise VideoError(f"{path}: cannot be read as a PNG image")
    if img.ndim == 3:  # OpenCV gives BGR(A)
        img = img[..., [2, 1, 0, *([3] if img.shape[2] == 4 else [])]]
    return img


def open_image_sequence(spec: str | Path, *, bit_depth: int | None = None) -> CameraFile:
    """An image sequence: a folder, a glob, a printf pattern or a single image."""
    spec = str(spec)
    files = _sequence_files(spec)
    if not files:
        raise VideoError(f"{spec}: no image files (allowed: {', '.join(IMAGE_SUFFIXES)})")
    gap = _number_gaps(files)
    if gap is not None:
        raise VideoError(f"{spec}: frames are missing from the numbered sequence ({gap})")
    first = _read_image(files[0])
    if first.dtype.kind not in "ui" or first.dtype.itemsize > 2:
        raise VideoError(f"{files[0]}: {first.dtype} samples; image sequences must hold 8- or "
                         "16-bit integers")
    container = first.dtype.itemsize * 8
    meta: dict[str, Any] = {"files": len(files), "first_file": files[0].name,
                            "last_file": files[-1].name}
    if files[0].suffix.lower() in (".tif", ".tiff"):
        bits, container, tags = _tiff_bits(files[0])
        meta["tiff_tags"] = tags
        meta["bit_depth_source"] = "file"
    else:
        bits = container
        meta["bit_depth_source"] = "container"
    _check_bit_depth(bit_depth, container, spec)
    if bit_depth is not None:
        bits = int(bit_depth)
        meta["bit_depth_source"] = "--bit-depth"
    shape, dtype = first.shape, first.dtype

    def read_rows(k: int, y0: int, y1: int) -> NDArray:
        img = first if k == 0 else _read_image(files[k])
        if img.shape != shape or img.dtype != dtype:
            raise VideoError(f"{files[k]}: {img.shape} {img.dtype}, unlike the first image's "
                             f"{shape} {dtype}")
        return img[y0:y1]

    return CameraFile("image sequence", Path(spec), int(shape[0]), int(shape[1]), len(files),
                      bits, None, meta, read_rows)


# --------------------------------------------------------------------------- Photron
def _photron_pair(path: Path) -> tuple[Path, Path]:
    if path.suffix.lower() == ".mraw":
        for ext in (".cihx", ".cih"):
            header = path.with_suffix(ext)
            if header.is_file():
                return header, path
        raise VideoError(f"{path}: no .cih or .cihx header next to it ({path.stem}.cihx or "
                         f"{path.stem}.cih); the frame size and rate are in it")
    mraw = path.with_suffix(".mraw")
    if not mraw.is_file():
        raise VideoError(f"{path}: its image file {mraw.name} is missing")
    return path, mraw


#: the highest frame rate a camera file may state (fps): no camera records near it
MAX_FPS = Fraction(10**8)
#: the largest save step (every n-th recorded frame stored) a header may state
MAX_STEP = 10**9


def _check_rate(value: Any, where: Path, key: str) -> Fraction:
    """``value`` as an exact frame rate, or one line naming the file, the key and the range."""
    try:
        rate = Fraction(str(value).strip())
    except (ValueError, ZeroDivisionError):
        rate = None
    if rate is None or not 0 < rate <= MAX_FPS:
        raise VideoError(f"{where}: key {key!r} is {value!r}; allowed: a frame rate above 0 "
                         f"and at most {float(MAX_FPS):.0e} fps")
    return rate


def _check_step(value: Any, where: Path, key: str) -> int:
    """A save step (every ``step``-th recorded frame stored), or one line naming the key."""
    try:
        step = Fraction(str(value).strip())
    except (ValueError, ZeroDivisionError):
        step = None
    if step is None or step.denominator != 1 or not 1 <= step <= MAX_STEP:
        raise VideoError(f"{where}: key {key!r} is {value!r}; allowed: a whole number from 1 "
                         f"to {MAX_STEP:.0e} (every n-th recorded frame stored; 1: all)")
    return int(step)


def _cihx_value(header: Path, element: str) -> str | None:
    """The text of ``element`` (a path below ``<cih>``) of a ``.cihx`` header's XML, or None
    (the XML follows a binary preamble)."""
    import xml.etree.ElementTree as ET

    raw = header.read_bytes()
    a, b = raw.find(b"<cih>"), raw.rfind(b"</cih>")
    if a < 0 or b < a:
        return None
    try:
        found = ET.fromstring(raw[a:b + len(b"</cih>")]).find(element)
    except ET.ParseError as e:
        raise VideoError(f"{header}: the XML of the header is not readable ({e})") from None
    return None if found is None else (found.text or "").strip()


def _pread(fd: int, n: int, offset: int, path: Path) -> bytes:
    buf = os.pread(fd, n, offset)
    if len(buf) != n:
        raise VideoError(f"{path}: truncated: {len(buf)} of {n} bytes at offset {offset}")
    return buf


def _unpack12(buf: bytes) -> NDArray[np.uint16]:
    """Big-endian packed 12-bit samples (two in three bytes) as uint16."""
    b = np.frombuffer(buf, np.uint8).reshape(-1, 3).astype(np.uint16)
    out = np.empty((b.shape[0], 2), np.uint16)
    out[:, 0] = (b[:, 0] << 4) | (b[:, 1] >> 4)
    out[:, 1] = ((b[:, 1] & 0x0F) << 8) | b[:, 2]
    return out.reshape(-1)


def open_photron(path: str | Path, *, bit_depth: int | None = None) -> CameraFile:
    """A Photron recording: its ``.cih``/``.cihx`` header (or the ``.mraw`` next to one).

    The frames' rate is the camera's ``Record Rate(fps)`` over the save step, ``Save Step``
    (``.cih``) or ``frameInfo/skipFrame`` (``.cihx``): a recording at 15000 fps saved every
    100th frame holds 150 frames per second of the record (``meta["record_fps"]``,
    ``meta["decimation"]``).  A header whose rate, step, size or frame count is impossible, or
    that describes another ``.mraw`` size, is refused in one line naming the key.
    """
    import pyMRAW

    header, mraw = _photron_pair(Path(path))
    try:
        cih = pyMRAW.get_cih(str(header))
    except Exception as e:  # noqa: BLE001 -- pyMRAW raises bare exceptions on bad headers
        raise VideoError(f"{header}: not a readable Photron header ({type(e).__name__}: "
                         f"{e})") from None
    try:
        n = int(cih["Total Frame"])
        h, w = int(cih["Image Height"]), int(cih["Image Width"])
        color_bits = int(cih["Color Bit"])
        rate = cih.get("Record Rate(fps)")
    except (KeyError, TypeError, ValueError) as e:
        raise VideoError(f"{header}: missing or invalid key {e} (needs 'Total Frame', "
                         "'Image Height', 'Image Width', 'Color Bit')") from None
    for key, value in (("Total Frame", n), ("Image Height", h), ("Image Width", w)):
        if value < 1:
            raise VideoError(f"{header}: key {key!r} is {value}; allowed: a whole number >= 1")
    if header.suffix.lower() == ".cihx":
        step_key, step = "frameInfo/skipFrame", _cihx_value(header, "frameInfo/skipFrame")
    else:
        step_key, step = "Save Step", cih.get("Save Step")
    step = 1 if step in (None, "") else _check_step(step, header, step_key)
    fmt = str(cih.get("File Format", "MRaw")).lower()
    if fmt != "mraw":
        raise VideoError(f"{header}: key 'File Format' is {cih.get('File Format')!r}; only "
                         "'MRaw' recordings are read")
    if color_bits not in (8, 12, 16):
        raise VideoError(f"{header}: key 'Color Bit' is {color_bits}; allowed: 8, 12, 16 "
                         "(monochrome)")
    effective = int(cih.get("EffectiveBit Depth", color_bits) or color_bits)
    side = str(cih.get("EffectiveBit Side", "Lower")).lower()
    _check_bit_depth(bit_depth, color_bits, str(header))
    bits = int(bit_depth) if bit_depth is not None else min(effective, color_bits)
    shift = color_bits - bits if side == "higher" and bit_depth is None else 0
    frame_bytes = h * w * color_bits // 8
    if (h * w * color_bits) % 8:
        raise VideoError(f"{header}: {w}x{h} frames of {color_bits} bits are not a whole "
                         "number of bytes")
    size = mraw.stat().st_size
    if size < n * frame_bytes:
        raise VideoError(f"{mraw}: truncated: {header.name} says {n} frames of {frame_bytes} "
                         f"bytes, the file holds {size // frame_bytes} ({size} bytes)")
    if size > n * frame_bytes:
        raise VideoError(
            f"{mraw}: {size} bytes, more than the {n} frames of {w}x{h} at {color_bits} bits "
            f"({n * frame_bytes} bytes) that {header.name} describes ('Total Frame', "
            "'Image Width', 'Image Height', 'Color Bit'): the header is not this file's (the "
            f"file holds {size / frame_bytes:g} such frames)")
    record = None if rate in (None, "") else _check_rate(rate, header, "Record Rate(fps)")
    fps = None if record is None else record / step
    meta = {"header": str(header), "mraw": str(mraw), "color_bits": color_bits,
            "effective_bits": effective, "effective_side": side,
            "bit_depth_source": "--bit-depth" if bit_depth is not None else "EffectiveBit Depth",
            "camera": cih.get("Camera Type"),
            "record_fps": None if record is None else str(record), "decimation": step,
            "decimation_key": step_key,
            "original_total_frame": cih.get("Original Total Frame")}
    row_bytes = w * color_bits // 8 if (w * color_bits) % 8 == 0 else None
    dtype = np.uint8 if color_bits == 8 else np.dtype("<u2")

    def read_rows(k: int, y0: int, y1: int) -> NDArray:
        fd = os.open(mraw, os.O_RDONLY)
        try:
            if row_bytes is not None:
                buf = _pread(fd, (y1 - y0) * row_bytes, k * frame_bytes + y0 * row_bytes, mraw)
                r0, r1 = 0, y1 - y0
            else:
                buf = _pread(fd, frame_bytes, k * frame_bytes, mraw)
                r0, r1 = y0, y1
        finally:
            os.close(fd)
        a = _unpack12(buf) if color_bits == 12 else np.frombuffer(buf, dtype)
        a = a.reshape(-1, w)[r0:r1]
        return a >> shift if shift else a

    return CameraFile("photron", header, h, w, n, bits, fps, meta, read_rows)


# --------------------------------------------------------------------------- Phantom
_CINE_HEADER = struct.Struct("<2sHHHiIiIIIIQ")  # CINEFILEHEADER, 44 bytes
_BITMAP_HEADER = struct.Struct("<IiiHHIIiiII")  # BITMAPINFOHEADER, 40 bytes
#: byte offsets inside SETUP (packed structure) of the fields read
_SETUP_FRAMERATE16 = 0
_SETUP_FRAMERATE = 768
_SETUP_REALBPP = 896
_SETUP_MIN_SIZE = _SETUP_REALBPP + 4
_SETUP_MARK = 140  # "ST", then Length (uint16): the bytes of SETUP this file holds
_SETUP_FRP_STEPS = 1048  # frame rate profile: FRPSteps, FRPImgNr[16], FRPRate[16]
_SETUP_FRP_RATE = 1116
_SETUP_DECIMATION = 1556
_SETUP_READ = _SETUP_DECIMATION + 4
#: tagged information block of the images' time stamps (a TIME64 per image)
_TIME_ONLY_BLOCK = 1002
#: time stamps and the stated rate must agree within this fraction
RATE_TOLERANCE = 0.01
#: biCompression of the packed gray images: (name, bits per stored sample)
CINE_PACKINGS = {256: ("P10", 10), 1024: ("P12L", 12)}
_PACKING_CODES = {name: (code, bits) for code, (name, bits) in CINE_PACKINGS.items()}
_CINE_SUPPORTED = ("gray images, uncompressed at 8 or 16 bits (biCompression 0) or packed at "
                   "10 bits (256, P10) or 12 bits (1024, P12L)")

#: Steps of Phantom's linearisation of P10 samples, from 2 at code 0 to 4064 at code 1014;
#: codes 1015..1023 read 4095 (the table of the Phantom SDK, used likewise by pycine).
_P10_STEPS = (
    "3111111111111011111111111111110111111111111111011111111111111101111111111111111011111111"
    "1111111011111111111111110111111111111111011111111111101111111111111111121111111112111111"
    "2111121112111211121121121121121211212121121212121212122121221212212212212212221222122212"
    "2222122222221222222222222222222222223222222232222232223222322232232232232232323223232323"
    "2323232332323233233233233233323332333233333233333333233333333333333333334333333334333343"
    "3334333433433343343433434334343434343434343443434434434434434443444344443444444344444444"
    "4444444444444444445444445444454445444544544544544545454454545454545545454554554554554555"
    "4555455554555555455555555555555555555555556555555655556555655565565565565655656565656565"
    "6565656656656566566656665666566665666666665666666666666667666666667666676666766676676676"
    "6767667676767676767676767767677677677767776777677777677777777777677777877777777777877777"
    "8777787778778778778778787877878787878878787887887887887888788887888887888888888888888888"
    "8888888988888988889888988988988988989898898988"
)


def _p10_table() -> NDArray[np.uint16]:
    """The 1024-entry table mapping a P10 code to a 12-bit linear value."""
    steps = np.frombuffer(_P10_STEPS.encode(), np.uint8) - ord("0")
    head = 2 + np.concatenate([[0], np.cumsum(steps)])
    return np.concatenate([head, np.full(1024 - head.size, 4095)]).astype(np.uint16)


P10_TO_LINEAR = _p10_table()


def unpack_msb_first(buf: bytes, bits: int, n: int) -> NDArray[np.uint16]:
    """The first ``n`` samples of ``bits`` bits each packed most significant bit first.

    The bytes are one big-endian bit stream: the first sample takes the high bits of the
    first byte, and a sample that crosses a byte boundary continues in the next byte's high
    bits. For 10 bits, five bytes ``b0..b4`` hold four samples ``b0<<2 | b1>>6``,
    ``(b1&0x3F)<<4 | b2>>4``, ``(b2&0x0F)<<6 | b3>>2``, ``(b3&0x03)<<8 | b4``; for 12 bits,
    three bytes hold two samples ``b0<<4 | b1>>4`` and ``(b1&0x0F)<<8 | b2``.

    Parameters
    ----------
    buf : the packed bytes (at least ``ceil(n * bits / 8)``).
    bits : 10 or 12.
    n : number of samples to return.

    Returns
    -------
    numpy.ndarray
        ``(n,)`` uint16.
    """
    per = {10: 4, 12: 2}[bits]
    group = per * bits // 8
    raw = np.frombuffer(buf, np.uint8)
    n_groups = -(-n // per)
    if raw.size < n_groups * group:
        raw = np.concatenate([raw, np.zeros(n_groups * group - raw.size, np.uint8)])
    grouped = raw[: n_groups * group].reshape(n_groups, group)
    byte = [grouped[:, j].astype(np.uint16) for j in range(group)]
    out = np.empty((n_groups, per), np.uint16)
    for i in range(per):  # sample i: bits i*bits .. of the group, within two bytes
        first, offset = divmod(i * bits, 8)
        pair = byte[first] << np.uint16(8)
        if first + 1 < group:
            pair |= byte[first + 1]
        pair >>= np.uint16(16 - offset - bits)
        pair &= np.uint16((1 << bits) - 1)
        out[:, i] = pair
    return out.reshape(-1)[:n]


def _pack_msb_first(values: NDArray, bits: int) -> bytes:
    """Inverse of :func:`unpack_msb_first`: ``values`` packed into ``ceil(n * bits / 8)``
    bytes (the last group padded with zero samples)."""
    per = {10: 4, 12: 2}[bits]
    group = per * bits // 8
    flat = np.asarray(values, np.uint64).reshape(-1)
    n = flat.size
    flat = np.concatenate([flat, np.zeros(-n % per, np.uint64)]).reshape(-1, per)
    words = np.zeros(flat.shape[0], np.uint64)
    for column in flat.T:
        words = (words << np.uint64(bits)) | column
    shifts = np.arange(group - 1, -1, -1, dtype=np.uint64) * np.uint64(8)
    out = ((words[:, None] >> shifts[None, :]) & np.uint64(0xFF)).astype(np.uint8)
    return out.reshape(-1)[: -(-n * bits // 8)].tobytes()


def open_phantom(path: str | Path, *, bit_depth: int | None = None) -> CameraFile:
    """A Phantom ``.cine`` file of gray images: uncompressed 8 or 16 bits, or packed.

    Packed images (``biCompression`` 256 "P10" and 1024 "P12L") are stored top row first,
    rows back to back with no padding, the samples packed most significant bit first
    (:func:`unpack_msb_first`: P10 four samples in five bytes, P12L two in three). P10
    samples are log-encoded: they are mapped through Phantom's linearisation table
    (:data:`P10_TO_LINEAR`) to 12-bit linear values, so a P10 file reads as 12 bits; P12L
    samples are 12-bit linear ("L"), read as ``RealBPP`` bits (12 when it is not set).
    Uncompressed images are stored bottom row first unless ``biHeight`` is negative, rows
    padded to 4 bytes. Colour, raw Bayer and other compressions are refused.
    """
    path = Path(path)
    size = path.stat().st_size
    with open(path, "rb") as fh:
        head = fh.read(_CINE_HEADER.size)
        if len(head) < _CINE_HEADER.size or head[:2] != b"CI":
            raise VideoError(f"{path}: not a .cine file (no 'CI' header)")
        (_, header_size, compression, version, first_movie, total, first_no, count,
         off_bitmap, off_setup, off_offsets, trigger) = _CINE_HEADER.unpack(head)
        fh.seek(off_bitmap)
        bm = fh.read(_BITMAP_HEADER.size)
        if len(bm) < _BITMAP_HEADER.size:
            raise VideoError(f"{path}: truncated: the image header is cut short")
        (_, width, height, _, bit_count, bi_compression, size_image, *_rest) = \
            _BITMAP_HEADER.unpack(bm)
        fh.seek(off_setup)
        setup = fh.read(_SETUP_READ)
        fh.seek(off_offsets)
        table = fh.read(8 * count)
    if compression != 0:
        raise VideoError(f"{path}: CINEFILEHEADER Compression is {compression} (1: JPEG, 2: "
                         f"raw Bayer), not 0 (gray); read are {_CINE_SUPPORTED}")
    packing = CINE_PACKINGS.get(bi_compression)
    if packing is None and (bi_compression != 0 or bit_count not in (8, 16)):
        raise VideoError(f"{path}: images of {bit_count} bits, biCompression {bi_compression}; "
                         f"read are {_CINE_SUPPORTED} (colour, raw Bayer and other "
                         "compressions are not)")
    if len(table) < 8 * count:
        found = len(table) // 8
        raise VideoError(f"{path}: truncated: the header says {count} images, the offsets "
                         f"table holds {found}")
    offsets = np.frombuffer(table, "<i8")
    h, w = abs(int(height)), int(width)
    rate = realbpp = 0
    if len(setup) >= _SETUP_MIN_SIZE:
        rate = struct.unpack_from("<I", setup, _SETUP_FRAMERATE)[0]
        realbpp = struct.unpack_from("<I", setup, _SETUP_REALBPP)[0]
    if not rate and len(setup) >= 2:
        rate = struct.unpack_from("<H", setup, _SETUP_FRAMERATE16)[0]
    if packing is None:
        stored_bits = container = int(bit_count)
        row_bytes: int | None = ((w * bit_count // 8 + 3) // 4) * 4
        frame_bytes = row_bytes * h
    else:
        stored_bits, container = packing[1], 12
        aligned = w % (8 // math.gcd(8, stored_bits)) == 0  # rows start on a byte
        row_bytes = w * stored_bits // 8 if aligned else None
        frame_bytes = -(-w * h * stored_bits // 8)
    annotation = np.empty(0)
    if count:
        with open(path, "rb") as fh:
            fh.seek(int(offsets[-1]))
            ann = fh.read(4)
        annotation = np.frombuffer(ann, "<u4") if len(ann) == 4 else annotation
    last_end = int(offsets[-1]) + (int(annotation[0]) if annotation.size else 0) + frame_bytes \
        if count else 0
    if count and (annotation.size == 0 or last_end > size):
        ends = offsets + frame_bytes
        found = int(np.count_nonzero(ends <= size)) if annotation.size == 0 else \
            int(np.count_nonzero(ends + int(annotation[0]) <= size))
        raise VideoError(f"{path}: truncated: the header says {count} images, the file holds "
                         f"{found}")
    if packing is not None and count:
        with open(path, "rb") as fh:
            fh.seek(int(offsets[0]))
            ann_size = struct.unpack("<I", fh.read(4))[0]
            fh.seek(int(offsets[0]) + ann_size - 4)
            image_size = struct.unpack("<I", fh.read(4))[0] if ann_size >= 8 else -1
        if ann_size < 8:
            raise VideoError(f"{path}: AnnotationSize of image 0 is {ann_size}; the block holds "
                             "at least its own size and ImageSize (8 bytes)")
        if image_size != frame_bytes:
            raise VideoError(f"{path}: ImageSize of image 0 is {image_size} bytes; {packing[0]} "
                             f"images of {w}x{h} take {frame_bytes} (rows unpadded)")
    _check_bit_depth(bit_depth, container, str(path))
    if packing is not None and packing[0] == "P10":
        file_bits, source = 12, "P10 linearisation (12-bit)"
    elif 0 < realbpp <= container:
        file_bits, source = int(realbpp), "RealBPP"
    else:
        file_bits, source = container, ("biBitCount" if packing is None else packing[0])
    bits = int(bit_depth) if bit_depth is not None else file_bits
    bottom_up = packing is None and height > 0
    meta = {"cine_version": int(version), "first_image_no": int(first_no),
            "first_movie_image": int(first_movie), "total_image_count": int(total),
            "bit_count": int(bit_count), "real_bpp": int(realbpp),
            "bi_compression": int(bi_compression),
            "packing": packing[0] if packing is not None else None,
            "stored_bits": stored_bits,
            "bit_depth_source": "--bit-depth" if bit_depth is not None else source,
            "bottom_up": bool(bottom_up), "header_size": int(header_size),
            "trigger_time": int(trigger)}
    dtype = np.uint8 if bit_count == 8 else np.dtype("<u2")
    bytes_pp = bit_count // 8

    def read_rows(k: int, y0: int, y1: int) -> NDArray:
        fd = os.open(path, os.O_RDONLY)
        try:
            off = int(offsets[k])
            ann_size = struct.unpack("<I", _pread(fd, 4, off, path))[0]
            data = off + ann_size
            # stored rows: bottom-up images keep the top row last
            s0, s1 = (h - y1, h - y0) if bottom_up else (y0, y1)
            if row_bytes is not None:
                buf = _pread(fd, (s1 - s0) * row_bytes, data + s0 * row_bytes, path)
            else:
                buf = _pread(fd, frame_bytes, data, path)
        finally:
            os.close(fd)
        if packing is None:
            a = np.frombuffer(buf, np.uint8).reshape(s1 - s0, row_bytes)[:, :w * bytes_pp]
            a = a.copy().view(dtype).reshape(s1 - s0, w)
            return a[::-1] if bottom_up else a
        if row_bytes is not None:
            a = unpack_msb_first(buf, stored_bits, (y1 - y0) * w).reshape(y1 - y0, w)
        else:
            a = unpack_msb_first(buf, stored_bits, h * w).reshape(h, w)[y0:y1]
        return P10_TO_LINEAR[a] if packing[0] == "P10" else a

    fps, timing = _cine_timing(path, setup, rate, int(off_setup), int(off_offsets), int(count))
    meta.update(timing)
    return CameraFile("phantom", path, h, w, int(count), bits, fps, meta, read_rows)


def _cine_time_stamps(path: Path, start: int, end: int, count: int) -> NDArray | None:
    """The images' time stamps (s after the first image's) from the tagged block
    ``TimeOnlyBlock`` (1002) between ``start`` and ``end`` (after SETUP, before the offsets
    table), or None."""
    with open(path, "rb") as fh:
        pos = start
        while pos + 8 <= end:
            fh.seek(pos)
            size, kind, _ = struct.unpack("<IHH", fh.read(8))
            if size < 8 or pos + size > end:
                return None
            if kind == _TIME_ONLY_BLOCK and size - 8 >= 8 * count:
                raw = np.frombuffer(fh.read(8 * count), "<u4").reshape(-1, 2).astype(np.int64)
                # TIME64: seconds, and fractions of a second in units of 2**-32 whose two
                # lowest bits are flags (IRIG synchronisation, event input)
                ticks = (raw[:, 1] - raw[0, 1]) * (1 << 32) + (raw[:, 0] & 0xFFFFFFFC)
                return (ticks - ticks[0]) / 2.0**32
            pos += size
    return None


def _cine_timing(path: Path, setup: bytes, rate: int, off_setup: int, off_offsets: int,
                 count: int) -> tuple[Fraction, dict[str, Any]]:
    """The frame rate of a ``.cine``'s images, checked against what else the file says.

    ``FrameRate`` (``FrameRate16`` in old files) over SETUP ``Decimation`` (the factor the
    SDK describes as reducing the rate of the images sent to external memory; 0 or 1: none);
    a frame rate profile (``FRPSteps`` > 0 with another rate in ``FRPRate``) means the images
    are not evenly spaced and is refused; the median interval of the images' time stamps
    (``TimeOnlyBlock``), when the file has them, must agree within :data:`RATE_TOLERANCE`.
    """
    length = struct.unpack_from("<H", setup, _SETUP_MARK + 2)[0] \
        if len(setup) >= _SETUP_MARK + 4 and setup[_SETUP_MARK:_SETUP_MARK + 2] == b"ST" else 0
    key = "SETUP FrameRate" if len(setup) >= _SETUP_MIN_SIZE and \
        struct.unpack_from("<I", setup, _SETUP_FRAMERATE)[0] else "SETUP FrameRate16"
    if not rate:
        raise VideoError(f"{path}: {key} is 0; allowed: a frame rate above 0 and at most "
                         f"{float(MAX_FPS):.0e} fps")
    record = _check_rate(rate, path, key)
    out: dict[str, Any] = {"frame_rate_key": key, "setup_length": int(length),
                           "decimation": 1, "record_fps": None, "time_stamps": None}
    if length >= _SETUP_FRP_RATE + 64:
        steps = struct.unpack_from("<I", setup, _SETUP_FRP_STEPS)[0]
        rates = struct.unpack_from("<16I", setup, _SETUP_FRP_RATE)[:min(16, steps + 1)]
        other = sorted({int(r) for r in rates if r and r != rate})
        if steps and other:
            raise VideoError(f"{path}: a frame rate profile (SETUP FRPSteps {steps}, FRPRate "
                             f"{', '.join(map(str, other))} besides FrameRate {rate}): the "
                             "images are not evenly spaced in time; allowed: FRPSteps 0 (save "
                             "the part recorded at one rate as its own cine)")
    fps = record
    if length >= _SETUP_DECIMATION + 4:
        step = struct.unpack_from("<I", setup, _SETUP_DECIMATION)[0]
        if step > 1:
            fps = record / _check_step(step, path, "SETUP Decimation")
            out.update(decimation=int(step), record_fps=str(record))
    tagged = off_setup + length
    stamps = _cine_time_stamps(path, tagged, off_offsets, count) \
        if length and count >= 3 and tagged < off_offsets else None
    if stamps is not None:
        interval = float(np.median(np.diff(stamps)))
        if interval > 0:
            out["time_stamps"] = {"median_interval_s": interval, "fps": 1.0 / interval,
                                  "n": int(count)}
            if abs(interval * float(fps) - 1.0) > RATE_TOLERANCE:
                said = f"{key} {rate}" + (f" / Decimation {out['decimation']}"
                                          if out["decimation"] > 1 else "")
                raise VideoError(
                    f"{path}: {said} ({float(fps):g} fps) disagrees with the images' time "
                    f"stamps (TimeOnlyBlock: a median interval of {interval * 1e3:.6g} ms, "
                    f"{1.0 / interval:.6g} fps); allowed: a rate within "
                    f"{RATE_TOLERANCE:.0%} of the time stamps'")
    return fps, out


def write_cine(path: str | Path, frames: NDArray, fps: int, *, real_bpp: int | None = None,
               annotation: bytes = b"", packing: str | None = None,
               time_stamps: NDArray | None = None) -> Path:
    """Write gray frames ``(T, H, W)`` as a ``.cine`` file, uncompressed or packed.

    The layout is the documented one: CINEFILEHEADER, BITMAPINFOHEADER, a SETUP block
    holding ``FrameRate``, ``RealBPP`` and its own length, optionally a tagged block of the
    images' time stamps (``TimeOnlyBlock``), the table of 64-bit image offsets, then each
    image after its annotation block (``AnnotationSize``, the annotation, ``ImageSize``).
    Uncompressed images (uint8 or uint16 frames) are stored bottom row first, rows padded
    to 4 bytes. With ``packing="P12L"`` (12-bit values) or ``"P10"`` (10-bit codes, which a
    reader maps through :data:`P10_TO_LINEAR`) the samples are packed most significant bit
    first, top row first, rows unpadded (:func:`unpack_msb_first`). Written to a temporary
    name and renamed into place.

    Parameters
    ----------
    path : the ``.cine`` file to write.
    frames : ``(T, H, W)`` unsigned integers.
    fps : frame rate stored in SETUP.
    real_bpp : ``RealBPP`` (default: the stored bits per sample).
    annotation : bytes stored in each image's annotation block.
    packing : None (uncompressed), ``"P10"`` or ``"P12L"``.
    time_stamps : ``(T,)`` time of each image (s, from 1970), stored as TIME64; None: none.

    Returns
    -------
    pathlib.Path
        ``path``.
    """
    frames = np.asarray(frames)
    if packing is not None:
        if packing not in _PACKING_CODES:
            raise ValueError(f"packing {packing!r}; allowed: None, "
                             f"{', '.join(map(repr, _PACKING_CODES))}")
        bi_compression, stored = _PACKING_CODES[packing]
        top = (1 << stored) - 1
        if frames.ndim != 3 or frames.dtype.kind != "u" or (frames.size and frames.max() > top):
            raise ValueError(f"frames must be (T, H, W) unsigned integers up to {top} for "
                             f"{packing}, got {frames.shape} {frames.dtype}")
        bit_count = stored
    else:
        if frames.ndim != 3 or frames.dtype not in (np.uint8, np.uint16):
            raise ValueError(f"frames must be (T, H, W) uint8 or uint16, got {frames.shape} "
                             f"{frames.dtype}")
        bi_compression, bit_count = 0, frames.dtype.itemsize * 8
    t, h, w = frames.shape
    if packing is not None:
        frame_bytes = -(-w * h * bit_count // 8)
        row_bytes = 0
    else:
        row_bytes = ((w * frames.dtype.itemsize + 3) // 4) * 4
        frame_bytes = row_bytes * h
    setup_size = 5816  # SETUP size of current cine files
    off_bitmap = _CINE_HEADER.size
    off_setup = off_bitmap + _BITMAP_HEADER.size
    tagged = b""
    if time_stamps is not None:
        stamps = np.asarray(time_stamps, np.float64).reshape(-1)
        if stamps.size != t or not np.all(np.isfinite(stamps)) or np.any(stamps < 0):
            raise ValueError(f"time_stamps must be {t} finite times >= 0 (s), got "
                             f"{stamps.size}")
        seconds = np.floor(stamps)
        fractions = np.minimum(np.round((stamps - seconds) * 2.0**32), 2.0**32 - 4)
        words = np.stack([fractions.astype(np.uint64) & 0xFFFFFFFC,
                          seconds.astype(np.uint64)], axis=1).astype("<u4")
        tagged = struct.pack("<IHH", 8 + 8 * t, _TIME_ONLY_BLOCK, 0) + words.tobytes()
    off_offsets = off_setup + setup_size + len(tagged)
    first_image = off_offsets + 8 * t
    ann_size = 8 + len(annotation)
    offsets = first_image + np.arange(t, dtype=np.int64) * (ann_size + frame_bytes)
    setup = bytearray(setup_size)
    struct.pack_into("<H", setup, _SETUP_FRAMERATE16, min(int(fps), 0xFFFF))
    struct.pack_into("<I", setup, _SETUP_FRAMERATE, int(fps))
    struct.pack_into("<I", setup, _SETUP_REALBPP, int(real_bpp or bit_count))
    struct.pack_into("<2sH", setup, _SETUP_MARK, b"ST", setup_size)
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as fh:
            fh.write(_CINE_HEADER.pack(b"CI", _CINE_HEADER.size, 0, 1, 0, t, 0, t, off_bitmap,
                                       off_setup, off_offsets, 0))
            fh.write(_BITMAP_HEADER.pack(_BITMAP_HEADER.size, w, h, 1, bit_count,
                                         bi_compression, frame_bytes, 0, 0, 0, 0))
            fh.write(bytes(setup))
            fh.write(tagged)
            fh.write(offsets.astype("<i8").tobytes())
            for f in frames:
                fh.write(struct.pack("<I", ann_size) + annotation
                         + struct.pack("<I", frame_bytes))
                if packing is not None:
                    fh.write(_pack_msb_first(f, bit_count))
                    continue
                rows = np.zeros((h, row_bytes), np.uint8)
                rows[:, :w * frames.dtype.itemsize] = \
                    np.ascontiguousarray(f[::-1]).astype(f.dtype.newbyteorder("<")) \
                    .view(np.uint8).reshape(h, -1)
                fh.write(rows.tobytes())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


# --------------------------------------------------------------------------- .npy
def open_npy(path: str | Path, *, bit_depth: int | None = None) -> CameraFile:
    """A ``.npy`` array ``(T, H, W)`` or ``(T, H, W, C)`` of real numbers, memory-mapped."""
    path = Path(path)
    with open(path, "rb") as fh:
        try:
            version = np.lib.format.read_magic(fh)
            read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                           else np.lib.format.read_array_header_2_0)
            shape, fortran, dtype = read_header(fh)
        except ValueError as e:
            raise VideoError(f"{path}: not a .npy file ({e})") from None
        data_offset = fh.tell()
    if dtype.kind not in "uifb" or dtype.hasobject:
        raise VideoError(f"{path}: {dtype} samples; a video array must hold real numbers "
                         "(integers or floats, not complex or objects)")
    if len(shape) not in (3, 4) or (len(shape) == 4 and shape[3] not in (1, 3, 4)):
        raise VideoError(f"{path}: an array of shape {shape}; a video is (T, H, W) or "
                         "(T, H, W, C) with C = 1, 3 or 4")
    if fortran:
        raise VideoError(f"{path}: a Fortran-ordered array; save it C-ordered "
                         "(np.ascontiguousarray)")
    frame_bytes = int(np.prod(shape[1:])) * dtype.itemsize
    size = path.stat().st_size - data_offset
    if size < shape[0] * frame_bytes:
        raise VideoError(f"{path}: truncated: the header says {shape[0]} frames, the file "
                         f"holds {max(size, 0) // max(frame_bytes, 1)}")
    arr = np.load(path, mmap_mode="r")
    if dtype.kind in "ui":
        container = dtype.itemsize * 8
        _check_bit_depth(bit_depth, container, str(path))
        signed = int(dtype.kind == "i")
        bits: int | None = int(bit_depth) if bit_depth is not None else container - signed
    else:
        if bit_depth is not None:
            raise VideoError(f"{path}: --bit-depth applies to integer samples, not {dtype}")
        bits = None

    def read_rows(k: int, y0: int, y1: int) -> NDArray:
        a = np.array(arr[k, y0:y1])
        return a.astype(np.uint8) if a.dtype == np.bool_ else a

    if dtype == np.bool_:
        bits = 1
    meta = {"dtype": str(dtype), "array_shape": list(shape)}
    return CameraFile("npy", path, int(shape[1]), int(shape[2]), int(shape[0]), bits, None,
                      meta, read_rows)
