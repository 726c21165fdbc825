"""Resource faults are one line and leave nothing half-written: a full disk (found up front
from the size an export or a generation needs, or met mid-write), too many workers, a
resolution no encoder or memory can take, a scheduler that never answers."""

from __future__ import annotations

import errno
import json
import shutil
from collections import namedtuple
from pathlib import Path

import pytest

from vvtbench.cli import main
from vvtbench.generate import generate
from vvtbench.scene import parse_scene

TINY = {
    "name": "tiny",
    "seed": 7,
    "geometry": {"kind": "box", "cells": [2, 2, 2]},
    "excitation": {"kind": "pluck", "at": [0.05, 0.0, 0.05], "displacement": 0.002},
    "simulation": {"n_modes": 4, "duration": 0.01, "fps": 2000.0},
    "camera": {"resolution": [32, 24], "position": [0.16, -0.13, 0.13],
               "look_at": [0.025, 0.025, 0.022], "fov_y_deg": 30.0},
    "render": {"supersample": 1},
}
Usage = namedtuple("Usage", "total used free")


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    scene = parse_scene(json.loads(json.dumps(TINY)), "tiny")
    return generate(scene, tmp_path_factory.mktemp("samples"), progress=False,
                    preview_frames=2)


def _one_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


def _disk_with(monkeypatch, free: int) -> None:
    monkeypatch.setattr(shutil, "disk_usage", lambda path: Usage(10 * free + 1, 0, free))


@pytest.mark.parametrize("fmt,name", [("zarr", "ds.zarr"), ("hdf5", "ds.h5")])
def test_export_refuses_up_front_a_disk_without_room(tiny, tmp_path, monkeypatch, capsys,
                                                     fmt, name):
    from vvtbench.export import estimate_bytes

    need = estimate_bytes([tiny], {}, fmt)
    _disk_with(monkeypatch, need - 1)
    out = tmp_path / "out" / name
    assert main(["export", str(tiny), "--format", fmt, "-o", str(out)]) == 2
    line = _one_line(capsys)
    assert str(out.parent) in line and f"{need:,} bytes" in line, line
    assert not any(out.parent.iterdir())
    _disk_with(monkeypatch, need)
    assert main(["export", str(tiny), "--format", fmt, "-o", str(out)]) == 0


@pytest.mark.parametrize("fmt,name", [("zarr", "ds.zarr"), ("hdf5", "ds.h5")])
def test_the_export_estimate_bounds_what_is_written(tiny, tmp_path, fmt, name):
    from vvtbench.export import estimate_bytes, pack

    pack([tiny], tmp_path / name, fmt)
    written = sum(p.stat().st_size for p in tmp_path.rglob("*") if p.is_file())
    assert 0 < written <= estimate_bytes([tiny], {}, fmt)


@pytest.mark.parametrize("fmt,name", [("zarr", "ds.zarr"), ("hdf5", "ds.h5")])
def test_a_disk_full_mid_export_is_one_line_and_leaves_nothing(tiny, tmp_path, monkeypatch,
                                                               capsys, fmt, name):
    import vvtbench.export as ex

    writer = ex._ZarrWriter if fmt == "zarr" else ex._H5Writer
    real = writer.array
    calls = []

    def fills_up(self, *args, **kwargs):
        calls.append(1)
        if len(calls) == 5:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(self, *args, **kwargs)

    monkeypatch.setattr(writer, "array", fills_up)
    keep = tmp_path / "mine.txt"
    keep.write_text("mine")
    out = tmp_path / name
    assert main(["export", str(tiny), "--format", fmt, "-o", str(out)]) == 2
    line = _one_line(capsys)
    assert str(out) in line and "full" in line, line
    assert len(calls) == 5
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine.txt"]


# --------------------------------------------------------------------------- generate
def _scene_file(tmp_path: Path) -> Path:
    import tomli_w

    path = tmp_path / "tiny.toml"
    path.write_text(tomli_w.dumps(TINY))
    return path


def test_generate_refuses_up_front_a_disk_without_room(tmp_path, monkeypatch, capsys):
    from vvtbench.cli.generate import disk_bytes
    from vvtbench.scene import load_scene

    scene = _scene_file(tmp_path)
    need = disk_bytes(load_scene(scene), True, None)
    _disk_with(monkeypatch, need - 1)
    out = tmp_path / "out"
    assert main(["generate", str(scene), "-o", str(out), "--no-progress"]) == 2
    line = _one_line(capsys)
    assert str(out) in line and f"{need:,} bytes" in line, line
    assert not out.exists()


def test_the_generate_estimate_bounds_what_is_written(tiny):
    from vvtbench.cli.generate import disk_bytes
    from vvtbench.scene import parse_scene

    scene = parse_scene(json.loads(json.dumps(TINY)), "tiny")
    written = sum(p.stat().st_size for p in tiny.rglob("*") if p.is_file())
    video = (tiny / "video.mkv").stat().st_size
    assert written <= disk_bytes(scene, True, None)
    assert 2 * video <= disk_bytes(scene, True, None) - 4 * 2**20  # segments + joined video


def test_a_disk_full_mid_generate_is_one_line_and_leaves_nothing(tmp_path, monkeypatch,
                                                                 capsys):
    import vvtbench.generate as gen

    real = gen._write_json_sorted

    def fills_up(path, data):
        if Path(path).name == "checkpoint.json" and "segments_done" in data:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(path, data)

    monkeypatch.setattr(gen, "_write_json_sorted", fills_up)
    out = tmp_path / "out"
    assert main(["generate", str(_scene_file(tmp_path)), "-o", str(out), "--no-progress"]) == 2
    line = _one_line(capsys)
    assert "tiny" in line and str(out) in line and "full" in line, line
    assert list(out.iterdir()) == []


@pytest.mark.parametrize("resolution,says", [("16000x16000", "bytes of memory"),
                                             ("16384x16384", "larger than ffmpeg")])
def test_a_resolution_no_memory_or_encoder_takes_is_refused_up_front(tmp_path, capsys,
                                                                      resolution, says):
    out = tmp_path / "out"
    assert main(["generate", "jello_cube_defect_top", "--resolution", resolution,
                 "-o", str(out), "--no-progress"]) == 2
    line = _one_line(capsys)
    assert says in line and "camera.resolution" in line, line
    assert not out.exists()


def test_the_render_memory_estimate_is_refused_at_16000_squared():
    from vvtbench.cli.generate import render_memory_bytes

    need = render_memory_bytes(16000, 16000, 4)
    assert need > 190e9  # 48 B per supersampled pixel: 4.1e9 of them
    assert render_memory_bytes(256, 256, 4) < 0.5e9


@pytest.mark.parametrize("command", [["generate", "jello_cube_defect_top", "-o", "x"],
                                     ["run", "smoke"]])
def test_workers_are_bounded(tmp_path, capsys, monkeypatch, command):
    import os

    monkeypatch.chdir(tmp_path)
    too_many = str(4 * (os.cpu_count() or 1) + 1)
    assert main([*command, "--workers", too_many]) == 2
    line = _one_line(capsys)
    assert "--workers" in line and f"1 to {int(too_many) - 1}" in line, line
    assert list(tmp_path.iterdir()) == []


@pytest.fixture
def silent_server():
    """A TCP address that accepts connections and never answers."""
    import socket
    import threading

    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(8)
    held = []

    def accept():
        while True:
            try:
                held.append(server.accept()[0])
            except OSError:
                return

    threading.Thread(target=accept, daemon=True).start()
    yield f"tcp://127.0.0.1:{server.getsockname()[1]}"
    server.close()
    for c in held:
        c.close()


def test_a_scheduler_that_never_answers_times_out(silent_server):
    import time

    from vvtbench.bench.executors import SchedulerError, probe_scheduler

    t0 = time.perf_counter()
    with pytest.raises(SchedulerError, match="no answer within 1 s"):
        probe_scheduler(silent_server, timeout=1)
    assert time.perf_counter() - t0 < 5


def test_generate_on_a_silent_scheduler_is_one_line(tmp_path, monkeypatch, capsys,
                                                    silent_server):
    import vvtbench.bench.executors as ex

    monkeypatch.setattr(ex, "SCHEDULER_TIMEOUT", 1.0)
    out = tmp_path / "out"
    code = main(["generate", str(_scene_file(tmp_path)), "-o", str(out), "--no-progress",
                 "--scheduler", silent_server])
    line = _one_line(capsys)
    assert code == 2 and silent_server in line and "no answer" in line, line
