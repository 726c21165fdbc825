"""Writes only where a command created: no write through a planted link, no folder outside the
run folder from a suite's name, no hidden or parent folder from a scene's name."""

from __future__ import annotations

import os

import numpy as np
import pytest

from vvtbench.cli import main
from vvtbench.io.files import write_json, write_npz, write_text
from vvtbench.io.lock import RunLock, RunLocked


@pytest.mark.parametrize("writer", ["text", "json", "npz"])
def test_a_link_at_the_output_is_replaced_not_written_through(tmp_path, writer):
    victim = tmp_path / "victim.txt"
    victim.write_text("mine")
    out = tmp_path / "out"
    out.symlink_to(victim)
    {"text": lambda: write_text(out, "x"), "json": lambda: write_json(out, {"a": 1}),
     "npz": lambda: write_npz(out, {"a": np.zeros(2)})}[writer]()
    assert victim.read_text() == "mine" and not out.is_symlink() and out.is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "victim.txt"]


def test_a_link_at_the_lock_is_refused(tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("mine")
    run = tmp_path / "run"
    run.mkdir()
    (run / ".lock").symlink_to(victim)
    with pytest.raises(RunLocked, match="symbolic link"):
        RunLock(run).acquire()
    assert victim.read_text() == "mine"


@pytest.mark.parametrize("name", ["../../victim", "..", ".", ".hidden", "a/b", "a b", "ü"])
def test_a_suite_name_that_is_no_folder_name_is_refused(tmp_path, capsys, name):
    suite = tmp_path / "s.toml"
    suite.write_text(f'name = "{name}"\nscenes = ["jello_cube_defect_top"]\n'
                     'solvers = ["homogeneous"]\n')
    cwd = os.getcwd()
    os.chdir(tmp_path)
    try:
        assert main(["run", str(suite)]) == 2
    finally:
        os.chdir(cwd)
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "key 'name'" in err[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.toml"]


@pytest.mark.parametrize("name", [".", "..", ".hidden"])
def test_a_scene_name_that_would_hide_or_climb_is_refused(tmp_path, capsys, name):
    from vvtbench.scene.scene import SceneError, load_scene, parse_scene

    data = load_scene("jello_cube_defect_top").to_toml_dict()
    data["name"] = name
    with pytest.raises(SceneError, match="must not start with '.'"):
        parse_scene(data, "x.toml")


@pytest.fixture(scope="module")
def sample(tmp_path_factory):
    from vvtbench.samples.generate import generate
    from vvtbench.scene.scene import load_scene

    scene = load_scene("jello_cube_defect_top")
    data = scene.to_toml_dict()
    data["geometry"]["cells"] = [5, 5, 5]
    data["simulation"]["n_modes"] = 4
    from vvtbench.scene.scene import parse_scene

    return generate(parse_scene(data, "tiny"), tmp_path_factory.mktemp("s"), progress=False,
                    video=False)


def _problems(path):
    from vvtbench.cli.verify import verify_path

    return verify_path(path)


@pytest.mark.parametrize("damage", ["flip", "delete", "attribute", "extra"])
def test_verify_checks_every_file_of_a_zarr_dataset(sample, tmp_path, damage):
    from vvtbench.datasets.export import pack

    out = pack([sample], tmp_path / "ds.zarr")
    assert _problems(out) == []
    chunk = next(p for p in sorted(out.rglob("c/*")) if p.is_file())
    if damage == "flip":
        data = bytearray(chunk.read_bytes())
        data[-1] ^= 1
        chunk.write_bytes(bytes(data))
    elif damage == "delete":
        chunk.unlink()
    elif damage == "attribute":
        meta = next(p for p in sorted(out.rglob("zarr.json")) if p.parent != out)
        meta.write_text(meta.read_text().replace('"', '"', 1) + " ")
        chunk = meta
    else:
        chunk = out / "samples" / "notes.txt"
        chunk.write_text("mine")
    problems = _problems(out)
    assert problems and str(chunk) in problems[0], problems


def test_verify_checks_an_hdf5_dataset_against_its_croissant_sha256(sample, tmp_path):
    from vvtbench.datasets.export import pack

    out = pack([sample], tmp_path / "ds.h5", "hdf5")
    assert _problems(out) == []
    data = bytearray(out.read_bytes())
    data[len(data) // 2] ^= 1
    out.write_bytes(bytes(data))
    assert any("sha256 differs" in p for p in _problems(out))


def test_overwrite_never_deletes_a_file_it_did_not_write(sample, tmp_path, capsys):
    from vvtbench.datasets.export import pack

    out = pack([sample], tmp_path / "ds.zarr")
    mine = out / "samples" / "my-notes.txt"
    mine.write_text("mine")
    assert main(["export", str(sample), "-o", str(out), "--overwrite"]) == 2
    assert "my-notes.txt" in capsys.readouterr().err and mine.read_text() == "mine"
    mine.unlink()
    assert main(["export", str(sample), "-o", str(out), "--overwrite"]) == 0


def test_two_exports_to_one_target_one_is_refused(sample, tmp_path, capsys):
    from vvtbench.io.lock import RunLock

    out = tmp_path / "ds.zarr"
    held = RunLock(tmp_path, name=".ds.zarr.lock", remove=True).acquire()  # a first export
    try:
        assert main(["export", str(sample), "-o", str(out)]) == 2
        assert "another export is writing it" in capsys.readouterr().err
        assert not out.exists()
    finally:
        held.release()
    assert main(["export", str(sample), "-o", str(out)]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds.zarr"]


def test_generate_refuses_a_link_where_it_keeps_its_unfinished_sample(tmp_path):
    from vvtbench.samples.generate import generate
    from vvtbench.samples.reader import DatasetError

    victim = tmp_path / "victim"
    victim.mkdir()
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / ".jello_cube_defect_top.partial").symlink_to(victim)
    with pytest.raises(DatasetError, match="a link or a file"):
        generate("jello_cube_defect_top", tmp_path / "out", video=False, progress=False)
    assert list(victim.iterdir()) == []


def test_generate_takes_the_folder_lock_run_takes(tmp_path, capsys):
    from vvtbench.io.lock import RunLock

    held = RunLock(tmp_path).acquire()  # a run (or another generate) writing the folder
    try:
        assert main(["generate", "jello_cube_defect_top", "--no-video", "-o",
                     str(tmp_path)]) == 2
        assert "in use by another vvtbench run" in capsys.readouterr().err
        assert not (tmp_path / "jello_cube_defect_top").exists()
    finally:
        held.release()


def test_an_npz_has_the_same_bytes_whenever_it_is_written(tmp_path, monkeypatch):
    """Equal arrays give equal bytes: no member carries the clock's time (a zip member's
    stamp has a 2-s resolution, so the clock is moved by a day between the writes)."""
    import time

    import numpy as np

    from vvtbench.io.files import write_npz

    arrays = {"w": np.linspace(0, 1, 7), "shape": np.arange(6, dtype=np.int32).reshape(2, 3)}
    for compressed in (True, False):
        write_npz(tmp_path / "a.npz", arrays, compressed=compressed)
        real = time.time
        monkeypatch.setattr(time, "time", lambda: real() + 86400.0)
        write_npz(tmp_path / "b.npz", arrays, compressed=compressed)
        monkeypatch.undo()
        assert (tmp_path / "a.npz").read_bytes() == (tmp_path / "b.npz").read_bytes()
        with np.load(tmp_path / "b.npz") as z:
            assert sorted(z.files) == ["shape", "w"]
            assert np.array_equal(z["w"], arrays["w"]) and z["shape"].dtype == np.int32
