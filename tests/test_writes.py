"""Writes only where a command created: no write through a planted link, no folder outside the
run folder from a suite's name, no hidden or parent folder from a scene's name."""

from __future__ import annotations

import os

import numpy as np
import pytest

from vvtbench.bench.lock import RunLock, RunLocked
from vvtbench.cli import main
from vvtbench.io import write_json, write_npz, write_text


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
    from vvtbench.scene import SceneError, load_scene, parse_scene

    data = load_scene("jello_cube_defect_top").to_toml_dict()
    data["name"] = name
    with pytest.raises(SceneError, match="must not start with '.'"):
        parse_scene(data, "x.toml")
