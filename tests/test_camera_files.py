"""Camera files behind open_video: image sequences, Photron, Phantom, .npy, lossy videos.

Every file read here is written by the format's own library (tifffile, OpenCV, pyMRAW,
ffmpeg) or, for .cine, by a writer of the documented layout checked field by field.
"""

from __future__ import annotations

import struct
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest

from vvtbench.video.cameras import open_camera_file, write_cine
from vvtbench.video.files import VideoError, VideoWriter, open_video, probe_video


def _frames(t: int, h: int, w: int, top: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    dtype = np.uint8 if top < 256 else np.uint16
    return rng.integers(0, top + 1, size=(t, h, w)).astype(dtype)


def _stack(stream) -> np.ndarray:
    return np.stack(list(stream.frames))


# --------------------------------------------------------------------------- sequences
def _tiff_sequence(folder: Path, data: np.ndarray, max_value: int | None = None) -> None:
    import tifffile

    folder.mkdir(parents=True, exist_ok=True)
    extratags = [] if max_value is None else [(281, "H", 1, max_value, False)]
    for k, f in enumerate(data):
        tifffile.imwrite(folder / f"img_{k + 1:05d}.tif", f, extratags=extratags)


def test_tiff_12bit_in_16bit_scaled_by_its_depth(tmp_path: Path) -> None:
    data = _frames(6, 12, 10, 4095)
    _tiff_sequence(tmp_path / "seq", data, max_value=4095)
    want = data.astype(np.float64) / 4095
    for spec in (tmp_path / "seq", f"{tmp_path}/seq/*.tif", f"{tmp_path}/seq/img_%05d.tif"):
        vs = open_video(spec)
        assert vs.fps is None and vs.n_frames == 6 and vs.meta["bits"] == 12
        np.testing.assert_allclose(_stack(vs), want, atol=1e-6)
    vs = open_video(tmp_path / "seq", start=2, stop=5, roi=(3, 9, 1, 7))
    np.testing.assert_allclose(_stack(vs), want[2:5, 3:9, 1:7], atol=1e-6)
    # the header's depth can be overridden; values above the stated depth are refused
    np.testing.assert_allclose(_stack(open_video(tmp_path / "seq", bit_depth=16)),
                               data / 65535, atol=1e-6)
    with pytest.raises(VideoError, match="above the 10-bit range"):
        _stack(open_video(tmp_path / "seq", bit_depth=10))
    info = probe_video(tmp_path / "seq")
    assert (info.width, info.height, info.n_frames, info.bits) == (10, 12, 6, 12)


def test_tiff_without_depth_tag_uses_its_container(tmp_path: Path) -> None:
    data = _frames(3, 8, 8, 4095)
    _tiff_sequence(tmp_path / "seq", data)
    vs = open_video(tmp_path / "seq")
    assert vs.meta["bits"] == 16
    np.testing.assert_allclose(_stack(vs), data / 65535, atol=1e-6)


def test_png_sequences_8_and_16_bit_in_natural_order(tmp_path: Path) -> None:
    import cv2

    for top in (255, 65535):
        folder = tmp_path / f"png{top}"
        folder.mkdir()
        data = _frames(12, 9, 11, top, seed=top)
        for k, f in enumerate(data):  # unpadded numbers: frame_10 comes after frame_9
            assert cv2.imwrite(str(folder / f"frame_{k}.png"), f)
        vs = open_video(folder)
        np.testing.assert_allclose(_stack(vs), data / top, atol=1e-6)


def test_sequence_errors(tmp_path: Path) -> None:
    data = _frames(4, 6, 6, 255)
    _tiff_sequence(tmp_path / "seq", data)
    (tmp_path / "seq" / "img_00003.tif").unlink()
    with pytest.raises(VideoError, match="missing.*img_00002.tif is followed by img_00004"):
        open_video(tmp_path / "seq")
    with pytest.raises(VideoError, match="no image files"):
        open_video(f"{tmp_path}/nothing_%04d.png")
    with pytest.raises(ValueError, match="outside the 6x6 frame"):
        open_video(f"{tmp_path}/seq/img_0000[12].tif", roi=(0, 7, 0, 3))


# --------------------------------------------------------------------------- Photron
def _pack12(a: np.ndarray) -> bytes:
    v = a.reshape(-1, 2).astype(np.uint16)
    b = np.empty((v.shape[0], 3), np.uint8)
    b[:, 0] = v[:, 0] >> 4
    b[:, 1] = ((v[:, 0] & 0xF) << 4) | (v[:, 1] >> 8)
    b[:, 2] = v[:, 1] & 0xFF
    return b.tobytes()


@pytest.mark.parametrize("bits", [8, 12, 16])
def test_photron_mraw_read_like_pymraw(tmp_path: Path, bits: int) -> None:
    import pyMRAW

    data = _frames(7, 10, 12, 255 if bits == 8 else 4095, seed=bits)
    mraw, cih = pyMRAW.save_mraw(data, str(tmp_path / "rec.cih"), bit_depth=8 if bits == 8
                                 else 16, info_dict={"Record Rate(fps)": 20000})
    if bits == 12:  # pyMRAW writes 8 and 16 bits; a 12-bit recording is packed
        Path(mraw).write_bytes(_pack12(data))
        text = Path(cih).read_text().replace("Color Bit : 16", "Color Bit : 12")
        Path(cih).write_text(text)
    reference, _ = pyMRAW.load_video(cih)
    np.testing.assert_array_equal(np.asarray(reference), data)
    for given in (cih, mraw):
        vs = open_video(given, start=1, stop=6, roi=(2, 9, 3, 11))
        top = 255 if bits == 8 else 4095
        assert vs.fps == 20000 and vs.n_frames == 5 and vs.meta["bits"] == (bits if bits == 8
                                                                             else 12)
        np.testing.assert_allclose(_stack(vs), np.asarray(reference)[1:6, 2:9, 3:11] / top,
                                   atol=1e-6)
    assert probe_video(cih).frame_rate == 20000


def test_photron_truncated_and_bad_header(tmp_path: Path) -> None:
    import pyMRAW

    mraw, cih = pyMRAW.save_mraw(_frames(5, 8, 8, 4095), str(tmp_path / "rec.cih"),
                                 bit_depth=16)
    with open(mraw, "r+b") as fh:
        fh.truncate(8 * 8 * 2 * 3 + 10)
    with pytest.raises(VideoError, match="truncated: rec.cih says 5 frames .* holds 3"):
        open_video(cih)
    Path(cih).write_text(Path(cih).read_text().replace("Color Bit : 16", "Color Bit : 10"))
    with pytest.raises(VideoError, match="'Color Bit' is 10; allowed: 8, 12, 16"):
        open_video(cih)


# --------------------------------------------------------------------------- Phantom
@pytest.mark.parametrize("dtype,real_bpp", [(np.uint8, 8), (np.uint16, 12), (np.uint16, 16)])
def test_phantom_cine_round_trip(tmp_path: Path, dtype: type, real_bpp: int) -> None:
    top = (1 << real_bpp) - 1
    data = _frames(6, 9, 7, top, seed=real_bpp).astype(dtype)  # odd width: padded rows
    path = write_cine(tmp_path / "rec.cine", data, 7500, real_bpp=real_bpp,
                      annotation=b"note")
    raw = path.read_bytes()
    assert raw[:2] == b"CI"
    off_setup, off_offsets = struct.unpack_from("<II", raw, 28)
    assert struct.unpack_from("<I", raw, off_setup + 768)[0] == 7500
    assert struct.unpack_from("<I", raw, off_setup + 896)[0] == real_bpp
    first = struct.unpack_from("<q", raw, off_offsets)[0]
    ann = struct.unpack_from("<I", raw, first)[0]
    row = ((7 * data.itemsize + 3) // 4) * 4
    bottom = np.frombuffer(raw, np.uint8, row, first + ann)[:7 * data.itemsize]
    np.testing.assert_array_equal(bottom.view(dtype), data[0, -1])  # rows stored bottom-up
    vs = open_video(path, start=2, stop=5, roi=(1, 8, 2, 6))
    assert vs.fps == 7500 and vs.rate == Fraction(7500) and vs.meta["bits"] == real_bpp
    np.testing.assert_allclose(_stack(vs), data[2:5, 1:8, 2:6] / top, atol=1e-6)
    with open(path, "r+b") as fh:
        fh.truncate(len(raw) - 3)
    with pytest.raises(VideoError, match="truncated: the header says 6 images, the file holds 5"):
        open_video(path)


# --------------------------------------------------------------------------- .npy
def test_npy_checks(tmp_path: Path) -> None:
    np.save(tmp_path / "flat.npy", np.zeros((4, 5)))
    np.save(tmp_path / "complex.npy", np.zeros((2, 4, 5), complex))
    bad = np.zeros((3, 4, 5), np.float32)
    bad[2, 1, 1] = np.nan
    np.save(tmp_path / "nan.npy", bad)
    with pytest.raises(VideoError, match=r"shape \(4, 5\); a video is \(T, H, W\)"):
        open_video(tmp_path / "flat.npy")
    with pytest.raises(VideoError, match="complex128 samples"):
        open_video(tmp_path / "complex.npy")
    with pytest.raises(VideoError, match="frame 2 holds NaN"):
        _stack(open_video(tmp_path / "nan.npy"))
    good = _frames(5, 4, 6, 65535)
    np.save(tmp_path / "v.npy", good)
    np.testing.assert_allclose(_stack(open_video(tmp_path / "v.npy", start=1, stop=3)),
                               good[1:3] / 65535, atol=1e-6)
    raw = (tmp_path / "v.npy").read_bytes()
    (tmp_path / "cut.npy").write_bytes(raw[:-40])
    with pytest.raises(VideoError, match="truncated: the header says 5 frames, the file holds 4"):
        open_video(tmp_path / "cut.npy")


def test_container_frame_range_and_roi(tmp_path: Path) -> None:
    data = _frames(10, 8, 10, 65535)
    with VideoWriter(tmp_path / "v.mkv", 8, 10, capture_fps=500) as w:
        for f in data:
            w.write(f)
    vs = open_video(tmp_path / "v.mkv", start=3, stop=7, roi=(1, 6, 2, 9))
    assert vs.fps == 500 and "lossy" not in vs.meta
    np.testing.assert_allclose(_stack(vs), data[3:7, 1:6, 2:9] / 65535, atol=1e-6)
    with pytest.raises(ValueError, match="--bit-depth applies to image sequences"):
        open_video(tmp_path / "v.mkv", bit_depth=12)


def test_truncated_raw_container_is_not_a_shorter_video(tmp_path: Path) -> None:
    data = _frames(50, 16, 16, 255)
    with VideoWriter(tmp_path / "v.mkv", 16, 16, pix_fmt="gray", capture_fps=2000) as w:
        for f in data:
            w.write(f)
    assert probe_video(tmp_path / "v.mkv").n_streams == 1
    np.testing.assert_allclose(_stack(open_video(tmp_path / "v.mkv")), data / 255, atol=1e-6)
    raw = (tmp_path / "v.mkv").read_bytes()
    (tmp_path / "cut.mkv").write_bytes(raw[: int(len(raw) * 0.6)])
    with pytest.raises(VideoError, match="truncated: the container says 50 frames .* holds 3"):
        _stack(open_video(tmp_path / "cut.mkv"))
    np.save(tmp_path / "v.npy", _frames(8, 4, 4, 255))
    raw = (tmp_path / "v.npy").read_bytes()
    (tmp_path / "v.npy").write_bytes(raw[:-1])
    with pytest.raises(VideoError, match="says 8 frames, the file holds 7"):
        open_camera_file(tmp_path / "v.npy")


# --------------------------------------------------------------------------- lossy sources
def _two_mode_clip(n: int = 64, fps: int = 100, t_frames: int = 200) -> np.ndarray:
    """8-bit frames of a smooth random texture moved by two smooth modes (14 and 36.5 Hz)."""
    from scipy.ndimage import gaussian_filter, map_coordinates

    rng = np.random.default_rng(1)
    tex = gaussian_filter(rng.standard_normal((3 * n, 3 * n)), 1.5)
    tex = (tex - tex.min()) / (tex.max() - tex.min())
    y, x = np.mgrid[0:n, 0:n].astype(float)
    pa = np.stack([np.cos(2 * np.pi * x / n), 0.5 * np.sin(2 * np.pi * y / n)])
    pb = np.stack([np.sin(2 * np.pi * y / n), np.cos(2 * np.pi * x / n)])
    out = np.empty((t_frames, n, n), np.uint8)
    for k in range(t_frames):
        t = k / fps
        d = 0.3 * pa * np.cos(2 * np.pi * 14 * t) + 0.2 * pb * np.cos(2 * np.pi * 36.5 * t)
        img = map_coordinates(tex, [y + n - d[1], x + n - d[0]], order=3, mode="wrap")
        out[k] = np.clip(np.round(img * 220 + 18), 0, 255)
    return out


def _h264(path: Path, frames: np.ndarray, fps: int, gop: int) -> None:
    """H.264 with a keyframe every ``gop`` frames, the keyframes coded coarser than the
    frames between them (``ipratio`` < 1): the keyframe pumping of consumer cameras."""
    import imageio_ffmpeg

    n = frames.shape[1]
    w = imageio_ffmpeg.write_frames(
        str(path), (n, n), pix_fmt_in="gray", pix_fmt_out="yuv420p", codec="libx264", fps=fps,
        quality=None, macro_block_size=1, ffmpeg_log_level="error",
        output_params=["-qp", "18", "-x264-params", "ipratio=0.2", "-g", str(gop),
                       "-keyint_min", str(gop), "-sc_threshold", "0", "-bf", "0",
                       "-threads", "1"])
    w.send(None)
    for f in frames:
        w.send(np.ascontiguousarray(f))
    w.close()


def test_h264_keyframe_comb_rejected(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    from vvtbench.cli.extract import main_extract
    from vvtbench.modes import ModeSet
    from vvtbench.modes.extract import extract_modes

    fps, gop = 100, 10
    frames = _two_mode_clip(fps=fps)
    with VideoWriter(tmp_path / "lossless.mkv", 64, 64, pix_fmt="gray",
                     playback_fps=fps) as w:
        for f in frames:
            w.write(f)
    _h264(tmp_path / "clip.mp4", frames, fps, gop)
    clean = extract_modes(tmp_path / "lossless.mkv", fps)
    assert clean.lossy is None and "lossy" not in clean.metadata
    assert main_extract([str(tmp_path / "clip.mp4"), "--fps", str(fps), "-o",
                         str(tmp_path / "out"), "--no-plots", "--quiet"]) == 0
    out = capsys.readouterr()
    lines = [ln for ln in out.err.splitlines() if "lossy source" in ln]
    assert lines == ["warning: lossy source: h264 8-bit, a keyframe every 10 frames: peaks on "
                     "the keyframe comb (multiples of 10 Hz) are rejected; compression "
                     "artefacts move like texture (prefer the camera's raw files)"]
    lossy = ModeSet.load(tmp_path / "out")
    assert lossy.lossy["codec"] == "h264" and lossy.lossy["gop"] == gop
    assert lossy.lossy["keyframes"][:3] == [0, 10, 20]
    extra = [f for f in lossy.frequencies_hz
             if np.min(np.abs(clean.frequencies_hz - f)) > 2 * fps / 200]
    assert len(extra) <= 1
    comb = [r for r in lossy.metadata["rejected"] if r["reason"] == "keyframe"]
    assert sorted(r["harmonic"] for r in comb) == [1, 2, 3, 4]
    assert all(abs(r["frequency_hz"] - 10 * r["harmonic"]) <= 2 * fps / 200 for r in comb)
    assert "harmonic 1 of the keyframe rate 10.000 Hz, a keyframe every 10 frames" in out.out
    # without the rejection the comb would be reported as modes
    kept = extract_modes(tmp_path / "clip.mp4", fps, reject_keyframe_comb=False)
    assert len(kept) >= len(lossy) + 3


def test_old_modes_json_without_lossy_key_loads(tmp_path: Path) -> None:
    import json

    from vvtbench.modes.extract import extract_modes

    frames = _two_mode_clip(n=32, t_frames=64)
    ms = extract_modes(frames, 100.0)
    ms.metadata["lossy"] = {"codec": "h264", "gop": 5}
    ms.save(tmp_path / "m")
    doc = json.loads((tmp_path / "m" / "modes.json").read_text())
    del doc["metadata"]["lossy"]
    (tmp_path / "m" / "modes.json").write_text(json.dumps(doc))
    from vvtbench.modes import ModeSet

    assert ModeSet.load(tmp_path / "m").lossy is None


# --------------------------------------------------------------------------- command line
def test_extract_command_on_camera_files(tmp_path: Path,
                                         capsys: pytest.CaptureFixture) -> None:
    from vvtbench.cli import main
    from vvtbench.modes import ModeSet

    frames = _two_mode_clip(n=48, t_frames=120).astype(np.uint16) * 16  # 12 bits in 16
    _tiff_sequence(tmp_path / "seq", frames)  # no depth tag: --bit-depth says it
    out = tmp_path / "out"
    assert main(["extract", str(tmp_path / "seq"), "--fps", "100", "-o", str(out),
                 "--roi", "4,44,2,46", "--frames", "10:110", "--bit-depth", "12",
                 "--no-plots", "--quiet"]) == 0
    ms = ModeSet.load(out)
    assert ms.n_frames == 100 and ms.image_shape == (40, 44)
    assert ms.metadata["frame_range"] == [10, 110] and ms.metadata["roi"] == [4, 44, 2, 46]
    assert ms.metadata["bits"] == 12 and ms.metadata["bit_depth_source"] == "--bit-depth"
    assert np.min(np.abs(ms.frequencies_hz - 14.0)) < 1.0
    capsys.readouterr()
    # an image sequence has no rate; bad options are one line and status 2
    assert main(["extract", str(tmp_path / "seq"), "-o", str(tmp_path / "o2"), "--quiet"]) == 2
    assert "has no frame rate: pass --fps" in capsys.readouterr().err
    assert main(["extract", str(tmp_path / "seq"), "--fps", "100", "-o", str(tmp_path / "o3"),
                 "--frames", "100:500", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "ends after the video's 120 frames" in err[0]
    assert main(["extract", str(tmp_path / "seq"), "--fps", "100", "-o", str(tmp_path / "o4"),
                 "--frames", "9:3"]) == 2
    assert "argument --frames: frames must be START:STOP" in capsys.readouterr().err
    assert not (tmp_path / "o2").exists() and not (tmp_path / "o3").exists()


def test_photron_cihx_header(tmp_path: Path) -> None:
    import pyMRAW

    data = _frames(4, 6, 8, 4095, seed=7)
    mraw, cih = pyMRAW.save_mraw(data, str(tmp_path / "rec.cih"), bit_depth=16)
    Path(cih).unlink()
    xml = ("<cih><fileInfo><date>2026/01/01</date></fileInfo>"
           "<deviceInfo><deviceName>FASTCAM</deviceName></deviceInfo>"
           "<recordInfo><recordRate>12500</recordRate><shutterSpeed>0.00001</shutterSpeed>"
           "</recordInfo><frameInfo><totalFrame>4</totalFrame><recordedFrame>4</recordedFrame>"
           "</frameInfo><imageDataInfo><resolution><width>8</width><height>6</height>"
           "</resolution><effectiveBit><depth>12</depth><side>Lower</side></effectiveBit>"
           "<colorInfo><bit>16</bit></colorInfo></imageDataInfo>"
           "<imageFileInfo><fileFormat>MRaw</fileFormat></imageFileInfo>"
           "<basicInfo><comment>bench</comment></basicInfo></cih>\n")
    (tmp_path / "rec.cihx").write_bytes(b"\x00\x01binary prefix\n" + xml.encode())
    vs = open_video(mraw)  # the header is found next to the .mraw
    assert vs.fps == 12500 and vs.meta["bits"] == 12 and vs.meta["camera"] == "FASTCAM"
    np.testing.assert_allclose(_stack(vs), data / 4095, atol=1e-6)


def test_lossy_description_of_intra_and_lossless_codecs(tmp_path: Path) -> None:
    import imageio_ffmpeg

    from vvtbench.video.files import lossy_description

    frames = _frames(12, 16, 16, 255)
    for name, codec, fmt in (("m.avi", "mjpeg", "yuvj420p"), ("l.avi", "ffv1", "gray")):
        w = imageio_ffmpeg.write_frames(str(tmp_path / name), (16, 16), pix_fmt_in="gray",
                                        pix_fmt_out=fmt, codec=codec, fps=25, quality=None,
                                        macro_block_size=1, ffmpeg_log_level="error")
        w.send(None)
        for f in frames:
            w.send(np.ascontiguousarray(f))
        w.close()
    mjpeg = lossy_description(tmp_path / "m.avi", probe_video(tmp_path / "m.avi"))
    assert mjpeg is not None and mjpeg["codec"] == "mjpeg" and mjpeg["gop"] == 1
    assert mjpeg["frames_probed"] == 12 and mjpeg["keyframes"] == list(range(12))
    assert lossy_description(tmp_path / "l.avi", probe_video(tmp_path / "l.avi")) is None
