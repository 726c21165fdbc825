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
from vvtbench.samples.generate import generate
from vvtbench.scene.scene import parse_scene

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
    from vvtbench.datasets.export import estimate_bytes

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
    from vvtbench.datasets.export import estimate_bytes, pack

    pack([tiny], tmp_path / name, fmt)
    written = sum(p.stat().st_size for p in tmp_path.rglob("*") if p.is_file())
    assert 0 < written <= estimate_bytes([tiny], {}, fmt)


@pytest.mark.parametrize("fmt,name", [("zarr", "ds.zarr"), ("hdf5", "ds.h5")])
def test_a_disk_full_mid_export_is_one_line_and_leaves_nothing(tiny, tmp_path, monkeypatch,
                                                               capsys, fmt, name):
    import vvtbench.datasets.export as ex

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
    from vvtbench.scene.scene import load_scene

    scene = _scene_file(tmp_path)
    need = disk_bytes(load_scene(scene), True, None)
    _disk_with(monkeypatch, need - 1)
    out = tmp_path / "out"
    assert main(["generate", str(scene), "-o", str(out), "--no-progress"]) == 2
    line = _one_line(capsys)
    assert str(out) in line and f"{need:,} bytes" in line, line
    assert not out.exists()


@pytest.mark.parametrize("workers", [1, 2])
def test_generate_asks_room_for_finished_samples_and_the_segments_in_flight(
        tmp_path, monkeypatch, capsys, workers):
    from vvtbench.cli.generate import disk_bytes, raw_video_bytes
    from vvtbench.scene.families import draw

    scene = draw("cube_defects", "val", 0)
    peak, raw = disk_bytes(scene, True, None), raw_video_bytes(scene, True, None)
    need = 3 * (peak - raw) + workers * raw  # not 3 peaks: segments go once joined
    assert raw > 0 and need < 3 * peak
    _disk_with(monkeypatch, need - 1)
    out = tmp_path / "out"
    assert main(["generate", "cube_defects", "--split", "val", "--n", "3", "--workers",
                 str(workers), "-o", str(out), "--no-progress"]) == 2
    line = _one_line(capsys)
    assert f"needs about {need:,} bytes" in line and "3 sample(s)" in line, line
    assert not out.exists()


def test_generate_sizes_the_rest_by_the_samples_it_has_finished(tmp_path, monkeypatch,
                                                                 capsys):
    """The bound counts the image modes dense; once modes-only samples of the run are
    finished, the rest are sized by the largest of them (a video run is not)."""
    from vvtbench.cli.generate import disk_bytes
    from vvtbench.scene.families import draw

    out = tmp_path / "out"
    assert main(["generate", "cube_defects", "--split", "val", "--n", "1", "--no-video",
                 "-o", str(out), "--no-progress"]) == 0
    sample = out / "cube_defects-val-00000"
    measured = sum(p.stat().st_size for p in sample.rglob("*") if p.is_file())
    bound = disk_bytes(draw("cube_defects", "val", 0), False, None)
    assert measured < bound
    before = sorted(p.name for p in out.iterdir())
    _disk_with(monkeypatch, 2 * measured - 1)
    args = ["generate", "cube_defects", "--split", "val", "--n", "3", "-o", str(out),
            "--no-progress"]
    assert main([*args, "--no-video"]) == 2
    line = _one_line(capsys)
    assert f"needs about {2 * measured:,} bytes" in line and "2 sample(s)" in line, line
    assert main(args) == 2  # with video: the finished modes-only sample says nothing
    assert f"needs about {2 * measured:,} bytes" not in _one_line(capsys)
    assert sorted(p.name for p in out.iterdir()) == before


def test_the_generate_estimate_bounds_what_is_written(tiny):
    from vvtbench.cli.generate import disk_bytes
    from vvtbench.scene.scene import parse_scene

    scene = parse_scene(json.loads(json.dumps(TINY)), "tiny")
    written = sum(p.stat().st_size for p in tiny.rglob("*") if p.is_file())
    video = (tiny / "video.mkv").stat().st_size
    assert written <= disk_bytes(scene, True, None)
    assert 2 * video <= disk_bytes(scene, True, None) - 4 * 2**20  # segments + joined video


def test_a_disk_full_mid_generate_is_one_line_and_leaves_nothing(tmp_path, monkeypatch,
                                                                 capsys):
    import vvtbench.samples.generate as gen

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
    # the server never answers: returning at all shows the limit cut the wait; the bound only
    # catches a limit far beyond 1 s, generous so that a loaded machine cannot break it
    assert time.perf_counter() - t0 < 120


def test_generate_on_a_silent_scheduler_is_one_line(tmp_path, monkeypatch, capsys,
                                                    silent_server):
    import vvtbench.bench.executors as ex

    monkeypatch.setattr(ex, "SCHEDULER_TIMEOUT", 1.0)
    out = tmp_path / "out"
    code = main(["generate", str(_scene_file(tmp_path)), "-o", str(out), "--no-progress",
                 "--scheduler", silent_server])
    line = _one_line(capsys)
    assert code == 2 and silent_server in line and "no answer" in line, line


# --------------------------------------------------------------------------- run killed
SUITE = """
name = "tiny"
scenes = ["jello_cube_defect_top"]
solvers = ["homogeneous"]
seeds = [0]
observations = ["true"]

[defaults]
"geometry.cells" = [5, 5, 5]
"simulation.n_modes" = 8
"simulation.fps" = 400.0
"simulation.duration" = 0.5
"camera.resolution" = [64, 64]
n_modes = 4
inference_shape = [3, 3, 3]
"""
SLEEPER = '''
import time
from dataclasses import dataclass


@dataclass
class Config:
    pass


class Sleep:
    name = "sleep"
    version = "0.0.1"
    description = "sleeps"
    Config = Config

    def __init__(self, config=None):
        pass

    def solve(self, problem):
        while True:
            time.sleep(1)
'''


def _sealed_sleeper(run_pid: int, timeout: float = 120.0) -> int:
    """The pid of the sealed child solving with the ``Sleep`` plug-in for the run
    ``run_pid``."""
    import os
    import time

    t0 = time.time()
    while time.time() - t0 < timeout:
        for entry in os.listdir("/proc"):
            try:
                argv = Path(f"/proc/{entry}/cmdline").read_bytes().split(b"\0")
                if argv[1:3] != [b"-m", b"vvtbench.solving.sealed"]:
                    continue
                spec = json.loads(Path(argv[3].decode()).read_text())
                if spec.get("job") == "solve" and spec.get("target", "").endswith(":Sleep") \
                        and run_pid in _ancestors(int(entry)):
                    return int(entry)
            except (OSError, ValueError, IndexError):
                continue
        time.sleep(0.1)
    raise AssertionError("no sealed child solving with Sleep")


def _parent(pid: int) -> int:
    return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])


def _ancestors(pid: int) -> list[int]:
    out = []
    while pid > 1:
        pid = _parent(pid)
        out.append(pid)
    return out


def _pool_worker(pid: int) -> int:
    """The pool worker (a forkserver child) above ``pid`` (the sandbox sits in between)."""
    while pid > 1:
        pid = _parent(pid)
        if b"multiprocessing.forkserver" in Path(f"/proc/{pid}/cmdline").read_bytes():
            return pid
    raise AssertionError("the solve does not run in a pool worker")


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state not in ("Z", "X")


def _tree_state(folder: Path) -> dict[str, tuple[int, int]]:
    return {str(p.relative_to(folder)): (p.stat().st_size, p.stat().st_mtime_ns)
            for p in folder.rglob("*") if not p.is_symlink()}


def test_pool_workers_end_when_the_run_is_killed(tmp_path):
    """SIGKILL of ``vvtbench run --workers 2`` while a solve sleeps: the pool worker and its
    sealed child end within seconds and nothing more is written into the run folder."""
    import os
    import signal
    import subprocess
    import sys
    import time

    suite = tmp_path / "tiny.toml"
    suite.write_text(SUITE)
    plugin = tmp_path / "sleeper.py"
    plugin.write_text(SLEEPER)
    out = tmp_path / "run"
    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(root), *sys.path])}
    proc = subprocess.Popen([sys.executable, "-m", "vvtbench.cli", "run", str(suite), "-o",
                             str(out), "--solvers", f"{plugin}:Sleep", "--workers", "2",
                             "--timeout", "8", "--no-progress"], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    try:
        child = _sealed_sleeper(proc.pid)
        worker = _pool_worker(child)
        assert worker != proc.pid
        proc.kill()
        proc.wait(timeout=30)
        t0 = time.time()
        while (_alive(worker) or _alive(child)) and time.time() - t0 < 120:  # load: slow reaping
            time.sleep(0.2)
        assert not _alive(worker) and not _alive(child)
        before = _tree_state(out)
        time.sleep(4)  # a live worker would write its timeout row 8 s after the solve began
        assert _tree_state(out) == before
        assert not list((out / "cache").rglob("*.tmp-*"))
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)


# --------------------------------------------------------------------------- mesh cache
def _star_tetrahedralize(vertices, faces, **settings):
    """A valid tetrahedralization of a convex closed surface: its centroid joined to every
    face (stands in for fTetWild, which takes seconds)."""
    import numpy as np

    pts = np.vstack([vertices, np.mean(vertices, axis=0)])
    return pts, np.column_stack([faces, np.full(len(faces), len(vertices))])


@pytest.mark.parametrize("damage", ["truncate", "garbage", "wrong_indices", "link"])
def test_a_damaged_mesh_cache_is_rebuilt(tmp_path, monkeypatch, damage):
    import numpy as np
    import pytetwild
    import trimesh

    from vvtbench.fem.mesh import mesh_cache_dir, tet_mesh

    monkeypatch.setenv("VVTBENCH_CACHE", str(tmp_path / "cache"))
    box = trimesh.creation.box(extents=(0.05, 0.04, 0.03))
    calls = []

    def counted(*args, **kwargs):
        calls.append(1)
        return _star_tetrahedralize(*args)

    monkeypatch.setattr(pytetwild, "tetrahedralize", counted)
    tet_mesh(box.vertices, box.faces)
    (cache,) = mesh_cache_dir().glob("tetwild-*.npz")
    tet_mesh(box.vertices, box.faces)
    assert len(calls) == 1  # a sound cache is used
    data = cache.read_bytes()
    victim = tmp_path / "victim.npz"
    if damage == "truncate":
        cache.write_bytes(data[: len(data) // 2])
    elif damage == "garbage":
        cache.write_bytes(b"\0" * len(data))
    elif damage == "wrong_indices":
        with np.load(cache) as z:
            pts, tets = z["points"], z["tets"]
        np.savez(cache, points=pts, tets=tets + len(pts))
    else:
        victim.write_bytes(data)
        cache.unlink()
        cache.symlink_to(victim)
    mesh = tet_mesh(box.vertices, box.faces)
    assert len(calls) == 2  # rebuilt, not used and not fatal
    assert len(mesh.cells) == 12 and mesh.cells.max() < len(mesh.points)
    assert not cache.is_symlink()
    with np.load(cache) as z:  # the healed cache is sound again
        assert z["tets"].max() < len(z["points"])
    assert [p.name for p in mesh_cache_dir().iterdir()] == [cache.name]
    assert not victim.exists() or victim.read_bytes() == data


# --------------------------------------------------------------------------- atomic_file
def test_a_figure_saved_through_atomic_file_replaces_a_planted_link(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from vvtbench.io.files import atomic_file

    victim = tmp_path / "victim.png"
    victim.write_bytes(b"mine")
    out = tmp_path / "plot.png"
    out.symlink_to(victim)
    fig, ax = plt.subplots()
    ax.plot([0, 1], [1, 0])
    with atomic_file(out) as f:
        fig.savefig(f, format="png")
    plt.close(fig)
    assert victim.read_bytes() == b"mine" and not out.is_symlink()
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["plot.png", "victim.png"]


def test_a_full_disk_inside_atomic_file_leaves_the_old_file(tmp_path):
    import pandas as pd

    from vvtbench.io.files import atomic_file

    out = tmp_path / "results.parquet"
    with atomic_file(out) as f:
        pd.DataFrame({"a": [1, 2]}).to_parquet(f)
    before = out.read_bytes()
    with pytest.raises(OSError) as error, atomic_file(out) as f:
        f.write(b"PAR1 half")
        raise OSError(errno.ENOSPC, "No space left on device")
    assert error.value.errno == errno.ENOSPC
    assert out.read_bytes() == before and [p.name for p in tmp_path.iterdir()] == [out.name]
    assert pd.read_parquet(out)["a"].tolist() == [1, 2]
