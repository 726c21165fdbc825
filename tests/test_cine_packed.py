"""Packed Phantom .cine (P10, P12L): the bit order checked against a bit-stream packing written
here with numpy's packbits, the P10 linearisation table against pycine's copy of Phantom's
table, and the reader's frame range, ROI, truncation and refusals."""

from __future__ import annotations

import hashlib
import struct
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest

from vvtbench.video.cameras import (
    P10_TO_LINEAR,
    open_camera_file,
    unpack_msb_first,
    write_cine,
)
from vvtbench.video.files import VideoError, open_video


def _bit_stream(values: np.ndarray, bits: int) -> bytes:
    """``values`` as one big-endian bit stream, each sample ``bits`` bits, MSB first."""
    v = np.asarray(values, dtype=">u2").reshape(-1, 1).view(np.uint8)  # (n, 2) big-endian
    stream = np.unpackbits(v, axis=1)[:, 16 - bits:]  # the low ``bits`` bits, MSB first
    return np.packbits(stream.reshape(-1)).tobytes()


def _image_bytes(path: Path, k: int) -> bytes:
    raw = path.read_bytes()
    off_offsets = struct.unpack_from("<I", raw, 32)[0]
    start = struct.unpack_from("<q", raw, off_offsets + 8 * k)[0]
    ann = struct.unpack_from("<I", raw, start)[0]
    size = struct.unpack_from("<I", raw, start + ann - 4)[0]
    return raw[start + ann:start + ann + size]


def test_bit_order_by_hand_and_by_bit_stream() -> None:
    # P12L: 0xABC, 0x123 -> AB C1 23; P10: 0x3FF, 0, 0x155, 0x2AA -> FF C0 05 56 AA
    assert _bit_stream(np.array([0xABC, 0x123]), 12) == bytes.fromhex("abc123")
    assert _bit_stream(np.array([0x3FF, 0, 0x155, 0x2AA]), 10) == bytes.fromhex("ffc00556aa")
    np.testing.assert_array_equal(unpack_msb_first(bytes.fromhex("abc123"), 12, 2),
                                  [0xABC, 0x123])
    np.testing.assert_array_equal(unpack_msb_first(bytes.fromhex("ffc00556aa"), 10, 4),
                                  [0x3FF, 0, 0x155, 0x2AA])
    rng = np.random.default_rng(5)
    for bits, n in ((10, 4 * 301), (12, 2 * 517), (10, 4 * 7 + 3), (12, 9)):
        values = rng.integers(0, 1 << bits, n)
        np.testing.assert_array_equal(unpack_msb_first(_bit_stream(values, bits), bits, n),
                                      values)


def test_p10_table_is_phantoms() -> None:
    """Digest and points of pycine's ``linLUT`` (Phantom's P10 -> 12-bit table)."""
    table = np.asarray(P10_TO_LINEAR)
    assert table.shape == (1024,) and np.all(np.diff(table.astype(int)) >= 0)
    assert table[::64].tolist() == [2, 64, 125, 193, 290, 418, 578, 771, 998, 1260, 1559,
                                    1894, 2267, 2679, 3130, 3620]
    assert table[[1, 100, 500, 900, 1013, 1014, 1015, 1023]].tolist() == \
        [5, 98, 952, 3159, 4056, 4064, 4095, 4095]
    assert int(table.astype(int).sum()) == 1398175
    assert hashlib.sha256(table.astype("<u2").tobytes()).hexdigest() == \
        "0bbeacd109d805facf267ddbb943f1f6bf96520ee8069085301fc83436b52993"


@pytest.mark.parametrize("packing,width", [("P12L", 8), ("P12L", 7), ("P10", 12),
                                           ("P10", 9)])
def test_packed_cine_round_trip(tmp_path: Path, packing: str, width: int) -> None:
    bits = 12 if packing == "P12L" else 10
    rng = np.random.default_rng(width)
    data = rng.integers(0, 1 << bits, size=(6, 5, width)).astype(np.uint16)
    path = write_cine(tmp_path / "rec.cine", data, 12500, packing=packing, annotation=b"x")
    raw = path.read_bytes()
    assert struct.unpack_from("<I", raw, 44 + 16)[0] == {"P12L": 1024, "P10": 256}[packing]
    for k in (0, 5):  # stored top row first, rows unpadded, as one bit stream
        assert _image_bytes(path, k) == _bit_stream(data[k], bits)
    want = data.astype(np.float64) if packing == "P12L" else \
        P10_TO_LINEAR[data].astype(np.float64)
    vs = open_video(path, start=1, stop=5, roi=(1, 4, 2, width - 1))
    assert vs.fps == 12500 and vs.rate == Fraction(12500) and vs.meta["bits"] == 12
    assert vs.meta["packing"] == packing and vs.meta["stored_bits"] == bits
    assert not vs.meta["bottom_up"]
    frames = np.stack(list(vs.frames))
    np.testing.assert_allclose(frames, want[1:5, 1:4, 2:width - 1] / 4095, atol=1e-7)
    np.testing.assert_array_equal(np.rint(frames * 4095), want[1:5, 1:4, 2:width - 1])
    full = np.stack(list(open_video(path).frames))
    np.testing.assert_array_equal(np.rint(full * 4095), want)


def test_packed_depth_and_p12l_real_bpp(tmp_path: Path) -> None:
    data = np.full((2, 4, 4), 1000, np.uint16)
    p10 = write_cine(tmp_path / "p10.cine", data, 1000, packing="P10")
    cam = open_camera_file(p10)
    assert cam.bits == 12 and cam.meta["bit_depth_source"] == "P10 linearisation (12-bit)"
    assert open_camera_file(p10, bit_depth=12).meta["bit_depth_source"] == "--bit-depth"
    with pytest.raises(VideoError, match="--bit-depth 14 must be between 1 and 12"):
        open_camera_file(p10, bit_depth=14)
    small = write_cine(tmp_path / "p12.cine", data, 1000, packing="P12L", real_bpp=10)
    cam = open_camera_file(small)
    assert cam.bits == 10 and cam.meta["bit_depth_source"] == "RealBPP"
    np.testing.assert_allclose(next(cam.frames()), 1000 / 1023, atol=1e-6)


def test_truncated_packed_cine_is_refused_at_the_missing_frame(tmp_path: Path) -> None:
    data = np.arange(6 * 4 * 8, dtype=np.uint16).reshape(6, 4, 8) % 4096
    path = write_cine(tmp_path / "rec.cine", data, 500, packing="P12L")
    raw = path.read_bytes()
    image = len(_image_bytes(path, 0)) + 8
    (tmp_path / "cut.cine").write_bytes(raw[:len(raw) - 2 * image - 1])
    with pytest.raises(VideoError, match=r"cut\.cine: truncated: the header says 6 images, "
                                         r"the file holds 4"):
        open_video(tmp_path / "cut.cine")


def _patched(path: Path, offset: int, fmt: str, value: int) -> Path:
    raw = bytearray(path.read_bytes())
    struct.pack_into(fmt, raw, offset, value)
    out = path.with_name(f"patched_{offset}_{value}.cine")
    out.write_bytes(bytes(raw))
    return out


def test_what_is_not_read_is_one_line_naming_the_file(tmp_path: Path) -> None:
    path = write_cine(tmp_path / "rec.cine", np.zeros((2, 4, 8), np.uint16), 500,
                      packing="P12L")
    for offset, fmt, value, why in ((4, "<H", 2, "Compression is 2"),  # raw Bayer
                                    (44 + 16, "<I", 512, "biCompression 512"),
                                    (44 + 16, "<I", 1, "biCompression 1")):
        bad = _patched(path, offset, fmt, value)
        with pytest.raises(VideoError) as err:
            open_video(bad)
        msg = str(err.value)
        assert msg.startswith(str(bad)) and why in msg and "\n" not in msg
        assert "P10" in msg and "P12L" in msg and "8 or 16 bits" in msg
    colour = write_cine(tmp_path / "c.cine", np.zeros((2, 4, 4), np.uint8), 500)
    with pytest.raises(VideoError, match="images of 24 bits, biCompression 0; read are gray"):
        open_video(_patched(colour, 44 + 14, "<H", 24))
    first = struct.unpack_from("<q", path.read_bytes(), struct.unpack_from(
        "<I", path.read_bytes(), 32)[0])[0]
    with pytest.raises(VideoError, match="ImageSize of image 0 is 99 bytes; P12L images of "
                                         "8x4 take 48"):
        open_video(_patched(path, first + 4, "<I", 99))
    with pytest.raises(VideoError, match="AnnotationSize of image 0 is 4; the block holds"):
        open_video(_patched(path, first, "<I", 4))
    with pytest.raises(ValueError, match="up to 1023 for P10"):
        write_cine(tmp_path / "x.cine", np.full((1, 2, 4), 1024, np.uint16), 500,
                   packing="P10")
    with pytest.raises(ValueError, match="packing 'P14'; allowed"):
        write_cine(tmp_path / "x.cine", np.zeros((1, 2, 4), np.uint16), 500, packing="P14")
    assert not (tmp_path / "x.cine").exists()


def _moving_texture(n: int, fps: int, t_frames: int, hz: float) -> np.ndarray:
    """12-bit frames of a smooth random texture shifted sideways at ``hz``."""
    from scipy.ndimage import gaussian_filter, map_coordinates

    rng = np.random.default_rng(3)
    tex = gaussian_filter(rng.standard_normal((3 * n, 3 * n)), 1.5)
    tex = (tex - tex.min()) / (tex.max() - tex.min())
    y, x = np.mgrid[0:n, 0:n].astype(float)
    shape = np.cos(2 * np.pi * x / n)
    out = np.empty((t_frames, n, n), np.uint16)
    for k in range(t_frames):
        d = 0.3 * shape * np.cos(2 * np.pi * hz * k / fps)
        img = map_coordinates(tex, [y + n, x + n - d], order=3, mode="wrap")
        out[k] = np.clip(np.round(img * 3500 + 300), 0, 4095)
    return out


def test_extract_command_on_a_packed_cine(tmp_path: Path,
                                          capsys: pytest.CaptureFixture) -> None:
    from vvtbench.cli import main
    from vvtbench.modes import ModeSet

    frames = _moving_texture(36, 100, 64, 14.0)
    path = write_cine(tmp_path / "rec.cine", frames, 100, packing="P12L")
    out = tmp_path / "out"
    assert main(["extract", str(path), "-o", str(out), "--roi", "2,34,0,36",
                 "--no-plots", "--quiet"]) == 0
    ms = ModeSet.load(out)
    assert ms.n_frames == 64 and ms.image_shape == (32, 36)
    assert ms.metadata["bits"] == 12 and ms.metadata["packing"] == "P12L"
    assert np.min(np.abs(ms.frequencies_hz - 14.0)) < 1.0
    capsys.readouterr()
    cut = tmp_path / "cut.cine"
    cut.write_bytes(path.read_bytes()[:-5])
    assert main(["extract", str(cut), "-o", str(tmp_path / "o2"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "the header says 64 images, the file holds 63" in err[0]
    assert not (tmp_path / "o2").exists()
