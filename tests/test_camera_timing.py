"""Camera timing from the file: Photron's save step, Phantom's rate, decimation and time
stamps, headers that cannot be true, and what extraction says about the record's timing.

The real files in tests/data/pyidi come from pyidi's repository (MIT; see the README there):
a FASTCAM SA-Z recording at 15 000 fps saved every 100th frame, and a packed-P10 Phantom file.
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import pytest

from vvtbench.modes.record import FREQUENCY_FLOOR_BINS, no_modes_reason, record_notes
from vvtbench.video.cameras import open_camera_file, write_cine
from vvtbench.video.files import VideoError, open_video, probe_video

DATA = Path(__file__).parent / "data" / "pyidi"
CIH = DATA / "data_showcase.cih"
CINE = DATA / "data_small_cine.cine"


# --------------------------------------------------------------------------- Photron
def test_photron_save_step_sets_the_rate_of_the_stored_frames() -> None:
    import pyMRAW

    info = probe_video(CIH)
    assert (info.width, info.height, info.n_frames) == (640, 40, 75)
    assert info.frame_rate == 150 and info.record_rate == 15000 and info.decimation == 100
    assert info.duration == pytest.approx(0.5)
    # pyMRAW, an independent reader, states the same fields (it does not divide by the step)
    reference, cih = pyMRAW.load_video(str(CIH))
    assert cih["Record Rate(fps)"] == 15000 and cih["Save Step"] == 100
    assert cih["Total Frame"] == 75 and cih["Original Total Frame"] == 15000
    vs = open_video(CIH)
    assert vs.fps == 150 and vs.meta["record_fps"] == "15000"
    assert vs.meta["decimation"] == 100 and vs.meta["decimation_key"] == "Save Step"
    np.testing.assert_allclose(np.stack(list(vs.frames)), np.asarray(reference) / 255,
                               atol=1e-6)


def test_extract_reads_the_line_at_18_hz_not_1804(tmp_path: Path,
                                                  capsys: pytest.CaptureFixture) -> None:
    from vvtbench.cli import main
    from vvtbench.modes import ModeSet

    out = tmp_path / "out"
    assert main(["extract", str(CIH), "-o", str(out), "--no-plots", "--quiet"]) == 0
    captured = capsys.readouterr()
    ms = ModeSet.load(out)
    assert ms.fps == 150 and ms.n_frames == 75
    bin_hz = 150 / 75
    assert np.min(np.abs(ms.frequencies_hz - 18.04)) < bin_hz
    assert not np.any(ms.frequencies_hz > 75)
    # the +- is never finer than the record supports (a tenth of its 2 Hz bins)
    assert np.all(ms.frequency_std_hz() >= FREQUENCY_FLOOR_BINS * bin_hz - 1e-12)
    assert "using 150 fps from the header" in captured.err
    assert "recorded at 15000 fps, every 100th frame stored: Save Step 100" in captured.err
    assert "warning: decimated record" in captured.err and "above 75 Hz" in captured.err
    assert "warning: short record: 75 frames" in captured.err
    doc = json.loads((out / "modes.json").read_text())
    kinds = [n["kind"] for n in doc["metadata"]["record_notes"]]
    assert kinds == ["aliasing", "short_record"]
    aliasing = doc["metadata"]["record_notes"][0]
    assert aliasing["record_fps"] == 15000 and aliasing["stored_fps"] == 150
    assert aliasing["nyquist_hz"] == 75 and doc["metadata"]["decimation"] == 100
    assert doc["metadata"]["frequency_floor_hz"] == pytest.approx(0.2)
    # a rate given against the file's is used, and said
    assert main(["extract", str(CIH), "--fps", "15000", "-o", str(tmp_path / "o2"),
                 "--no-plots", "--quiet"]) == 0
    assert "--fps 15000 is not the 150 fps the file states" in capsys.readouterr().err
    # nothing found: the reason is on screen
    assert main(["extract", str(CIH), "--fmin", "30", "-o", str(tmp_path / "o3"),
                 "--no-plots", "--quiet"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("0 modes") and "no peak in 30-75 Hz rose above the noise" \
        in lines[1] and "a short record (75 frames, 0.5 s)" in lines[1]


def _cihx(step: str) -> str:
    return ("<cih><fileInfo><date>2026/01/01</date></fileInfo>"
            "<deviceInfo><deviceName>FASTCAM</deviceName></deviceInfo>"
            "<recordInfo><recordRate>50000</recordRate><shutterSpeed>0.00001</shutterSpeed>"
            "</recordInfo><frameInfo><totalFrame>4</totalFrame><recordedFrame>400"
            f"</recordedFrame>{step}</frameInfo><imageDataInfo><resolution><width>8</width>"
            "<height>6</height></resolution><effectiveBit><depth>12</depth><side>Lower</side>"
            "</effectiveBit><colorInfo><bit>16</bit></colorInfo></imageDataInfo>"
            "<imageFileInfo><fileFormat>MRaw</fileFormat></imageFileInfo>"
            "<basicInfo><comment></comment></basicInfo>"
            "<playbackInfo><skip>0</skip><skipFrame>1</skipFrame></playbackInfo></cih>\n")


def test_cihx_skip_frame_is_the_save_step(tmp_path: Path) -> None:
    import pyMRAW

    data = np.arange(4 * 6 * 8, dtype=np.uint16).reshape(4, 6, 8)
    mraw, cih = pyMRAW.save_mraw(data, str(tmp_path / "rec.cih"), bit_depth=16)
    Path(cih).unlink()
    header = tmp_path / "rec.cihx"
    # frameInfo/skipFrame is the save step; playbackInfo/skipFrame only the viewer's
    header.write_bytes(b"\x00\x01binary prefix\n" + _cihx("<skipFrame>2500</skipFrame>")
                       .encode())
    vs = open_video(mraw)
    assert vs.fps == 20 and vs.meta["decimation"] == 2500
    assert vs.meta["decimation_key"] == "frameInfo/skipFrame"
    assert probe_video(header).duration == pytest.approx(0.2)
    header.write_bytes(_cihx("").encode())  # no step: every frame stored
    assert open_video(header).fps == 50000 and open_video(header).meta["decimation"] == 1
    header.write_bytes(_cihx("<skipFrame>0</skipFrame>").encode())
    with pytest.raises(VideoError, match=r"key 'frameInfo/skipFrame' is '0'; allowed: a "
                                         "whole number from 1"):
        open_video(header)


@pytest.mark.parametrize("line,bad,why", [
    ("Record Rate(fps) : 20000", "Record Rate(fps) : 1e300",
     "key 'Record Rate(fps)' is '1e300'; allowed: a frame rate above 0 and at most 1e+08"),
    ("Record Rate(fps) : 20000", "Record Rate(fps) : 0", "key 'Record Rate(fps)' is 0"),
    ("Record Rate(fps) : 20000", "Record Rate(fps) : -20000",
     "key 'Record Rate(fps)' is -20000"),
    ("Record Rate(fps) : 20000", "Record Rate(fps) : nan", "key 'Record Rate(fps)' is 'nan'"),
    ("Record Rate(fps) : 20000", "Record Rate(fps) : 20000\nSave Step : 0",
     "key 'Save Step' is 0; allowed: a whole number from 1"),
    ("Record Rate(fps) : 20000", "Record Rate(fps) : 20000\nSave Step : 2.5",
     "key 'Save Step' is 2.5"),
    ("Total Frame : 5", "Total Frame : 0", "key 'Total Frame' is 0; allowed: a whole number"),
    ("Total Frame : 5", "Total Frame : 4",
     "more than the 4 frames of 8x6 at 16 bits .* the file holds 5 such frames"),
    ("Image Width : 8", "Image Width : 4",
     "more than the 5 frames of 4x6 at 16 bits .* the file holds 10 such frames"),
])
def test_a_photron_header_that_cannot_be_true_is_one_line(tmp_path: Path, line: str,
                                                           bad: str, why: str) -> None:
    import pyMRAW

    _, cih = pyMRAW.save_mraw(np.zeros((5, 6, 8), np.uint16), str(tmp_path / "rec.cih"),
                              bit_depth=16, info_dict={"Record Rate(fps)": 20000})
    text = Path(cih).read_text()
    assert line in text
    Path(cih).write_text(text.replace(line, bad))
    with pytest.raises(VideoError) as err:
        open_video(cih)
    msg = str(err.value)
    assert msg.startswith(str(tmp_path)) and "\n" not in msg
    assert all(part in msg for part in why.split(" .* ")), msg


def test_a_header_that_cannot_be_true_is_exit_status_2(tmp_path: Path,
                                                       capsys: pytest.CaptureFixture) -> None:
    from vvtbench.cli import main

    (tmp_path / "rec.mraw").write_bytes(CIH.with_suffix(".mraw").read_bytes())
    text = CIH.read_bytes().replace(b"Record Rate(fps) : 15000", b"Record Rate(fps) : 1e300")
    (tmp_path / "rec.cih").write_bytes(text)
    assert main(["extract", str(tmp_path / "rec.cih"), "-o", str(tmp_path / "o"),
                 "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "rec.cih: key 'Record Rate(fps)' is '1e300'; allowed" in err[0]
    assert not (tmp_path / "o").exists()


# --------------------------------------------------------------------------- Phantom
def test_phantom_file_rate_duration_and_time_stamps() -> None:
    raw = CINE.read_bytes()
    off_setup = struct.unpack_from("<I", raw, 28)[0]
    # read by hand: SETUP FrameRate16 (byte 0), FrameRate (768), Length (142), FRPSteps
    # (1048), Decimation (1556); CINEFILEHEADER ImageCount (20)
    assert struct.unpack_from("<H", raw, off_setup)[0] == 100
    assert struct.unpack_from("<I", raw, off_setup + 768)[0] == 100
    assert struct.unpack_from("<H", raw, off_setup + 142)[0] == 9344
    assert struct.unpack_from("<I", raw, off_setup + 1048)[0] == 0
    assert struct.unpack_from("<I", raw, off_setup + 1556)[0] == 0
    assert struct.unpack_from("<I", raw, 20)[0] == 235
    info = probe_video(CINE)
    assert info.frame_rate == 100 and info.n_frames == 235 and info.decimation == 1
    assert info.record_rate is None and info.duration == pytest.approx(2.35)
    cam = open_camera_file(CINE)
    assert cam.meta["frame_rate_key"] == "SETUP FrameRate" and cam.meta["decimation"] == 1
    assert cam.meta["packing"] == "P10" and (cam.height, cam.width) == (32, 256)
    stamps = cam.meta["time_stamps"]  # TimeOnlyBlock: 10 ms between images
    assert stamps["n"] == 235 and stamps["fps"] == pytest.approx(100, rel=1e-4)


def _setup_offset(path: Path) -> int:
    return struct.unpack_from("<I", path.read_bytes(), 28)[0]


def _patch(path: Path, offset: int, fmt: str, *values: int) -> Path:
    raw = bytearray(path.read_bytes())
    struct.pack_into(fmt, raw, offset, *values)
    out = path.with_name(f"p{offset}_{'_'.join(map(str, values))}.cine")
    out.write_bytes(bytes(raw))
    return out


def test_phantom_decimation_time_stamps_and_profile(tmp_path: Path) -> None:
    data = np.zeros((6, 4, 8), np.uint16)
    t0 = 1000.0  # s after 1970 (small: float64 keeps the microseconds)
    good = write_cine(tmp_path / "g.cine", data, 1000, time_stamps=t0 + np.arange(6) / 1000)
    cam = open_camera_file(good)
    assert cam.fps == 1000 and cam.meta["time_stamps"]["fps"] == pytest.approx(1000, rel=1e-6)
    # images 2 ms apart do not make a 1000 fps record
    slow = write_cine(tmp_path / "s.cine", data, 1000, time_stamps=t0 + np.arange(6) / 500)
    with pytest.raises(VideoError, match=r"SETUP FrameRate 1000 \(1000 fps\) disagrees with "
                                         r"the images' time stamps .* 500 fps"):
        open_camera_file(slow)
    # SETUP Decimation divides the rate; the time stamps then agree with the quotient
    s = _setup_offset(slow)
    cam = open_camera_file(_patch(slow, s + 1556, "<I", 2))
    assert cam.fps == 500 and cam.meta["decimation"] == 2 and cam.meta["record_fps"] == "1000"
    info = probe_video(_patch(slow, s + 1556, "<I", 2))
    assert info.record_rate == 1000 and info.duration == pytest.approx(6 / 500)
    plain = write_cine(tmp_path / "p.cine", data, 1000)
    assert open_camera_file(plain).meta["time_stamps"] is None
    s = _setup_offset(plain)
    with pytest.raises(VideoError, match="frame rate profile .* FRPRate 4000 besides "
                                         "FrameRate 1000"):
        open_camera_file(_patch(_patch(plain, s + 1048, "<I", 1), s + 1116, "<II", 1000, 4000))
    with pytest.raises(VideoError, match="SETUP FrameRate16 is 0; allowed: a frame rate"):
        open_camera_file(_patch(_patch(plain, s + 768, "<I", 0), s, "<H", 0))
    with pytest.raises(VideoError, match="key 'SETUP FrameRate' is 4000000000; allowed"):
        open_camera_file(_patch(plain, s + 768, "<I", 4_000_000_000))


# --------------------------------------------------------------------------- notes
def test_record_notes_and_no_modes_reasons() -> None:
    cam = {"frame_rate": "150", "frame_rate_source": "file header", "record_fps": "15000",
           "decimation": 100, "decimation_key": "Save Step"}
    notes = record_notes(cam, 150.0, 1000, fps_source="container")
    assert [n["kind"] for n in notes] == ["aliasing"]
    assert "every 100th frame stored (Save Step 100): 150 fps" in notes[0]["message"]
    notes = record_notes(cam, 15000.0, 1000)
    assert [n["kind"] for n in notes] == ["aliasing", "fps_mismatch"]
    assert record_notes({}, 100.0, 1000) == []
    short = record_notes({}, 100.0, 500, fmin=0.25)
    assert [n["kind"] for n in short] == ["short_record"]
    assert "nothing from --fmin 0.25 Hz to 0.6 Hz was searched; 12 s" in short[0]["message"]
    assert record_notes({}, 100.0, 100)[0]["n_frames"] == 100
    meta = {"band_hz": [0.0, 50.0], "min_bin": 3, "roughness": [],
            "noise_floor": {"false_alarm": 0.01}, "rejected": []}
    assert no_modes_reason(meta, 100.0, 1000).startswith(
        "no peak in 0.3-50 Hz rose above the noise floor (false alarm 0.01)")
    meta.update(roughness=[0.5, 0.2, 0.4], rejected=[
        {"reason": "incoherent"}, {"reason": "distortion"}, {"reason": "incoherent"}])
    assert no_modes_reason(meta, 100.0, 1000).startswith(
        "all 3 candidate peaks were rejected (2 incoherent, 1 distortion")
    meta.update(band_hz=[0.0, 2.0], rejected=[])
    assert no_modes_reason(meta, 100.0, 100).startswith("nothing could be searched")


def test_noise_alone_says_why_no_mode() -> None:
    from vvtbench.modes import extract_modes

    rng = np.random.default_rng(0)
    frames = (0.5 + 0.01 * rng.standard_normal((96, 32, 32))).astype(np.float32)
    ms = extract_modes(frames, 100.0, min_bin=3)
    assert len(ms) == 0
    assert "rose above the noise floor" in ms.metadata["no_modes"]
    assert [n["kind"] for n in ms.metadata["record_notes"]] == ["short_record"]


def test_peak_picker_frequency_error_has_a_floor() -> None:
    from vvtbench.modes import modes_from_displacements

    rng = np.random.default_rng(5)
    T, fps, f0 = 512, 100.0, 23.4
    t = np.arange(T) / fps
    yy, xx = np.mgrid[0:16, 0:16]
    shape = np.stack([np.sin(np.pi * (xx + 0.5) / 16), np.cos(np.pi * (yy + 0.5) / 16)], -1)
    sig = np.exp(-2 * np.pi * f0 * 0.01 * t) * np.cos(2 * np.pi * f0 * t)
    disp = (0.05 * sig[:, None, None, None] * shape[None]
            + 1e-4 * rng.normal(size=(T, 16, 16, 2))).astype(np.float32)
    ms = modes_from_displacements(disp, fps, fmax=45)
    i = int(np.argmin(np.abs(ms.frequencies_hz - f0)))
    floor = FREQUENCY_FLOOR_BINS * fps / T
    assert ms.metadata["frequency_floor_hz"] == pytest.approx(floor)
    noise = ms.mode_list("frequency_std_noise_hz")[i]
    assert 0 < noise < floor and ms.frequency_std_hz()[i] == pytest.approx(floor)
    # a fitted line states its own (model) error, not floored
    fitted = modes_from_displacements(disp, fps, fmax=45, line_fit=True)
    j = int(np.argmin(np.abs(fitted.frequencies_hz - f0)))
    assert fitted.frequency_std_hz()[j] < floor
