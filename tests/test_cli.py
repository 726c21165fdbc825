"""The command line's safety: one-line errors and exit statuses, ``--debug``, did-you-mean,
samples verified on use, ``vvtbench verify``, and the video writers' data safety."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from vvtbench import cli
from vvtbench.samples import reader as ds
from vvtbench.samples.generate import generate
from vvtbench.scene.scene import parse_scene
from vvtbench.video.files import (
    VideoWriter,
    concat_videos,
    count_frames,
    ffmpeg_exe,
    probe_video,
    read_frames,
)

TINY = {
    "name": "tiny_cli",
    "seed": 7,
    "geometry": {"kind": "box", "cells": [3, 3, 3]},
    "excitation": {"kind": "pluck", "at": [0.05, 0.0, 0.05], "displacement": 0.002},
    "simulation": {"n_modes": 6, "duration": 0.05, "fps": 400.0},
    "camera": {"resolution": [48, 48], "position": [0.16, -0.13, 0.13],
               "look_at": [0.025, 0.025, 0.022], "fov_y_deg": 30.0},
    "render": {"supersample": 1},
}


@pytest.fixture(scope="module")
def sample(tmp_path_factory) -> Path:
    return generate(parse_scene(json.loads(json.dumps(TINY)), "tiny_cli"),
                    tmp_path_factory.mktemp("cli"), progress=False)


def _copy(sample: Path, tmp_path: Path, name: str = "s") -> Path:
    dst = tmp_path / name
    shutil.copytree(sample, dst)
    return dst


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


# --------------------------------------------------------------------------- errors
def test_internal_error_is_one_line_and_debug_shows_the_traceback(monkeypatch, capsys):
    def boom(args):
        raise KeyError("a bug")

    monkeypatch.setattr(cli, "run_scenes", boom)
    assert cli.main(["scenes"]) == 1
    line = _one_error_line(capsys)
    assert line.startswith("internal error: KeyError") and "--debug" in line
    with pytest.raises(KeyError):
        cli.main(["--debug", "scenes"])
    monkeypatch.setenv("VVTBENCH_DEBUG", "1")
    with pytest.raises(KeyError):
        cli.main(["scenes"])


def test_bad_input_is_one_line_exit_2(capsys, tmp_path):
    assert cli.main(["simulate", "--modes", "0"]) == 2
    assert "--modes" in _one_error_line(capsys)
    assert cli.main(["simulate", "--modes", "5000"]) == 2
    assert "simulation.n_modes" in _one_error_line(capsys)
    bad = tmp_path / "bad.toml"
    bad.write_text("[not toml")
    assert cli.main(["simulate", str(bad)]) == 2
    assert str(bad) in _one_error_line(capsys)
    with pytest.raises(Exception, match="not valid TOML"):
        cli.main(["--debug", "simulate", str(bad)])


@pytest.mark.parametrize("argv,word", [
    (["simulat"], "'simulate'"),
    (["simulate", "jello_cube_defekt_top"], "'jello_cube_defect_top'"),
    (["solve", "vt", "jello_cube_defect_top", "-o", "{tmp}/o"], "'vvt'"),
    (["export", "smok", "-o", "{tmp}/x.zarr"], "'smoke'"),
])
def test_did_you_mean(argv, word, capsys, tmp_path):
    assert cli.main([a.format(tmp=tmp_path) for a in argv]) == 2
    line = _one_error_line(capsys)
    assert f"did you mean {word}" in line


@pytest.mark.parametrize("option", [["--modes", "0"], ["--grid", "0", "4", "4"],
                                    ["--grid", "4", "4", "4", "4"],
                                    ["--geometry-scale", "-1"], ["--geometry-scale", "nan"],
                                    ["--set", "max_iter=0"], ["--set", "tol=inf"]])
def test_solve_options_are_checked_before_work(option, capsys, tmp_path, monkeypatch):
    import vvtbench.observe

    monkeypatch.setattr(vvtbench.observe, "observe", lambda *a, **k: pytest.fail("observed"))
    assert cli.main(["solve", "vvt", "jello_cube_defect_top", "-o", str(tmp_path / "o"),
                     *option]) == 2
    line = _one_error_line(capsys)
    assert option[0] in line or option[-1].split("=")[0] in line
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("option", [["--fps", "0"], ["--fmin", "50", "--fmax", "10"],
                                    ["--max-modes", "0"], ["--workers", "0"],
                                    ["--average", "0"], ["--sigma", "nan"],
                                    ["--product-roughness", "2"],
                                    ["--faint-product-ratio", "-0.1"],
                                    ["--product-scaling", "cubic"],
                                    ["--roughness-weighting", "noise"],
                                    ["--min-reliable-fraction", "-0.1"],
                                    ["--identifier", "ssi"]])
def test_extract_options(option, sample, capsys, tmp_path):
    assert cli.main(["extract", str(sample), "-o", str(tmp_path / "o"), *option]) == 2
    _one_error_line(capsys)
    assert not (tmp_path / "o").exists()


def test_extract_says_which_identifier_ran_and_why(sample, capsys, tmp_path):
    """The default ``--identifier auto`` reads the sample's pluck; a 20-frame record goes to
    the peak picker (under 128 frames an order scan does not settle), and modes.json and the
    output say so; ERA asked for on a record that short is one error line."""
    from vvtbench.modes import ModeSet

    assert cli.main(["extract", str(sample), "-o", str(tmp_path / "o"), "--no-plots"]) == 0
    out = capsys.readouterr().out
    ident = ModeSet.load(tmp_path / "o").identifier
    assert ident["requested"] == "auto" and ident["used"] == "peaks"
    assert ident["excitation"] == "pluck" and "short record (20 frames" in ident["reason"]
    assert f"identifier: peaks (auto: {ident['reason']})" in out
    assert cli.main(["extract", str(sample), "-o", str(tmp_path / "e"), "--identifier",
                     "era", "--fps", "400"]) == 2
    assert "too short for ERA" in _one_error_line(capsys)


def test_outputs_inside_a_sample_are_refused(sample, capsys):
    for argv in (["solve", "vvt", str(sample), "-o", str(sample / "out")],
                 ["extract", str(sample), "-o", str(sample / "modes")]):
        assert cli.main(argv) == 2
        assert "inside the sample" in _one_error_line(capsys)
    assert ds.open_sample(sample).verify() == []


# --------------------------------------------------------------------------- samples
def test_sample_repr_is_one_short_line(sample):
    s = ds.open_sample(sample)
    text = repr(s)
    assert "\n" not in text and len(text) < 300, text
    assert "tiny_cli" in text and "20 frames" in text and "48x48" in text and "400 fps" in text


def _cut_video(src: Path, dst: Path, frames: int) -> None:
    subprocess.run([ffmpeg_exe(), "-v", "error", "-y", "-i", str(src), "-map", "0", "-c", "copy",
                    "-frames:v", str(frames), str(dst)], check=True)


def test_truncated_video_is_an_error_on_open(sample, tmp_path):
    s = _copy(sample, tmp_path)
    _cut_video(sample / "video.mkv", tmp_path / "cut.mkv", 8)
    os.replace(tmp_path / "cut.mkv", s / "video.mkv")
    with pytest.raises(ds.DatasetError, match=r"video\.mkv: 8 frames, truth\.json "
                                              r"\(video\.frames\) says 20"):
        ds.open_sample(s)
    # even with a manifest rewritten to match the short file
    manifest = json.loads((s / "manifest.json").read_text())
    entry = manifest["files"]["video.mkv"]
    entry["bytes"] = (s / "video.mkv").stat().st_size
    entry["sha256"] = ds.sha256_file(s / "video.mkv")
    (s / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ds.DatasetError, match="8 frames"):
        ds.open_sample(s)
    # cut in the middle of a byte stream (header intact): the size, and counting, tell
    t = _copy(sample, tmp_path, "t")
    data = (t / "video.mkv").read_bytes()
    (t / "video.mkv").write_bytes(data[: len(data) // 2])
    with pytest.raises(ds.DatasetError, match=r"video\.mkv: \d+ bytes, the manifest says"):
        ds.open_sample(t)
    assert any("frames, truth.json" in p for p in ds.open_sample(t, verify=False).verify())
    assert count_frames(t / "video.mkv") < 20


def test_resized_video_is_an_error_on_open(sample, tmp_path):
    s = _copy(sample, tmp_path)
    with VideoWriter(s / "video.mkv", 24, 48, capture_fps=400) as w:
        for _ in range(20):
            w.write(np.zeros((24, 48), np.uint16))
    with pytest.raises(ds.DatasetError, match=r"frames are 48x24 px, truth\.json"):
        ds.open_sample(s)


def test_edited_scene_and_deleted_or_truncated_chunks_are_errors(sample, tmp_path):
    s = _copy(sample, tmp_path)
    toml = s / "scene.toml"
    toml.write_text(toml.read_text().replace("E = 9000.0", "E = 9100.0"))
    with pytest.raises(ds.DatasetError, match=r"scene\.toml: sha256 mismatch"):
        ds.open_sample(s)
    chunks = sorted(p for p in (sample / "truth.zarr").rglob("*")
                    if p.is_file() and "/c/" in p.as_posix())
    rel = chunks[0].relative_to(sample)
    d = _copy(sample, tmp_path, "d")
    (d / rel).unlink()
    with pytest.raises(ds.DatasetError, match=f"{rel.as_posix()}: missing"):
        ds.open_sample(d)
    t = _copy(sample, tmp_path, "t")
    (t / rel).write_bytes((t / rel).read_bytes()[:-3])
    with pytest.raises(ds.DatasetError, match=f"{rel.as_posix()}: .*truncated"):
        ds.open_sample(t)
    (t / "truth.zarr" / "extra").write_bytes(b"x")
    assert any("extra: not in the manifest" in p
               for p in ds.open_sample(t, verify=False).verify())


def test_consumers_refuse_damaged_samples(sample, tmp_path, capsys):
    s = _copy(sample, tmp_path)
    toml = s / "scene.toml"
    toml.write_text(toml.read_text().replace("E = 9000.0", "E = 9100.0"))
    for argv in (["extract", str(s), "-o", str(tmp_path / "m")],
                 ["solve", "vvt", str(s), "-o", str(tmp_path / "o"), "--observation", "true"],
                 ["export", str(s), "-o", str(tmp_path / "x.zarr")]):
        assert cli.main(argv) == 2, argv
        assert "scene.toml" in _one_error_line(capsys)
    from vvtbench.observe import observe

    with pytest.raises(ds.DatasetError, match="scene.toml"):
        observe(s, n_modes=3, inference_shape=(2, 2, 2))


# --------------------------------------------------------------------------- verify
def test_verify_sample(sample, tmp_path, capsys):
    assert cli.main(["verify", str(sample)]) == 0
    s = _copy(sample, tmp_path)
    (s / "rest.png").write_bytes(b"not a png")
    (s / "scene.toml").write_text((s / "scene.toml").read_text() + "\n")
    assert cli.main(["verify", str(s)]) == 1
    out = capsys.readouterr().out.splitlines()
    assert any(line.startswith(str(s / "rest.png")) for line in out)
    assert any(line.startswith(str(s / "scene.toml")) for line in out)


def test_verify_run_folder(sample, tmp_path, capsys):
    run = tmp_path / "run"
    gen = run / "cache" / "generate" / "abc"
    shutil.copytree(sample, gen / "sample")
    (gen / "task.json").write_text(json.dumps({"stage": "generate"}))
    task = run / "cache" / "solve" / "def"
    task.mkdir(parents=True)
    (task / "estimate.npz").write_bytes(b"12345")
    (task / "task.json").write_text(json.dumps({"stage": "solve", "files": {
        "estimate.npz": {"sha256": ds.sha256_file(task / "estimate.npz")}}}))
    assert cli.main(["verify", str(run)]) == 0
    (task / "estimate.npz").write_bytes(b"12346")
    (gen / "sample" / "truth.json").write_text("{}")
    assert cli.main(["verify", str(run)]) == 1
    out = capsys.readouterr().out
    assert f"{task / 'estimate.npz'}: sha256 mismatch" in out
    assert str(gen / "sample" / "truth.json") in out


def test_verify_exported_dataset(sample, tmp_path, capsys):
    out = tmp_path / "d.zarr"
    assert cli.main(["export", str(sample), "-o", str(out)]) == 0
    assert cli.main(["verify", str(out)]) == 0
    chunk = next(p for p in sorted((out / "samples").rglob("*"))
                 if p.is_file() and "/truth/" in p.as_posix() and "/c/" in p.as_posix())
    chunk.write_bytes(b"garbage")
    capsys.readouterr()
    assert cli.main(["verify", str(out)]) == 1
    assert f"{chunk}: sha256 differs" in capsys.readouterr().out
    (out / "SHA256SUMS").unlink()  # without its list an export is refused, in one line
    assert cli.main(["verify", str(out)]) in (1, 2)
    said = capsys.readouterr()
    assert "SHA256SUMS" in said.out + said.err or "unreadable" in said.out


# --------------------------------------------------------------------------- video writes
def test_concat_is_quoting_safe_and_atomic(tmp_path):
    d = tmp_path / "it's a \"folder\" with\nnew line"
    d.mkdir()
    segments = []
    for k in range(2):
        p = d / f"seg'{k}.mkv"
        with VideoWriter(p, 8, 8, capture_fps=400) as w:
            for j in range(3):
                w.write(np.full((8, 8), 10 * k + j, np.uint16))
        segments.append(p)
    target = tmp_path / "kept.mkv"
    target.write_bytes(b"not to be overwritten")
    out = d / "o'ut.mkv"
    out.symlink_to(target)  # a link at the output is replaced, never written through
    concat_videos(segments, out, capture_fps=400)
    assert not out.is_symlink() and target.read_bytes() == b"not to be overwritten"
    frames = np.stack(list(read_frames(out)))
    assert frames[:, 0, 0].tolist() == [0, 1, 2, 10, 11, 12]
    assert probe_video(out).capture_rate == 400
    assert sorted(p.name for p in d.iterdir()) == ["o'ut.mkv", "seg'0.mkv", "seg'1.mkv"]


def test_video_writer_is_atomic(tmp_path):
    out = tmp_path / "v.mkv"
    with pytest.raises(RuntimeError):
        with VideoWriter(out, 8, 8) as w:
            w.write(np.zeros((8, 8), np.uint16))
            raise RuntimeError("interrupted")
    assert list(tmp_path.iterdir()) == []  # no partial file, no temporary left
    w1, w2 = VideoWriter(out, 8, 8), VideoWriter(out, 8, 8)
    assert w1._tmp != w2._tmp  # unique per writer (process id + random)
    for w in (w1, w2):
        w.write(np.zeros((8, 8), np.uint16))
        w.close()
    assert [p.name for p in tmp_path.iterdir()] == ["v.mkv"]


def test_solvers_and_extractors_are_listed(capsys):
    assert cli.main(["extractors", "-v"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("farneback") and "\nphase " in out and "frequency" in out
    assert cli.main(["solvers"]) == 0
    names = [line.split()[0] for line in capsys.readouterr().out.splitlines()]
    assert {"vvt", "homogeneous", "oracle"} <= set(names)


def test_extract_names_a_missing_extractor_or_option_in_one_line(sample, capsys, tmp_path):
    for option, word in ((["--extractor", "nope"], "farneback"),
                         (["--extractor", "farneback", "--set", "winsz=3"], "winsize"),
                         (["--set", "frequency=fast"], "midpoint"),
                         (["--extractor", "farneback", "--set", "poly_n=-3"], "poly_n"),
                         (["--extractor", "farneback", "--set", "winsize=99999999999999"],
                          "winsize")):
        assert cli.main(["extract", str(sample), "-o", str(tmp_path / "o"), *option]) == 2
        assert word in _one_error_line(capsys)
        assert not (tmp_path / "o").exists()
