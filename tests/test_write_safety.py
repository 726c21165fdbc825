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
