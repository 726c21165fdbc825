"""Frozen releases: a build is resumable, a frozen copy verifies byte for byte, and a flipped
byte, a missing, an extra or a linked file, or an edited list, fails with the file named."""

from __future__ import annotations

import os
import platform
import shutil
import subprocess
import sys

import pytest

from vvtbench.cli import main
from vvtbench.datasets.release import ReleaseError, check_environment_file, load_release, read_sums
from vvtbench.samples.compare import TOLERANCES

TINY = """
name = "tiny-release"
vvtbench = "0.1.0"
description = "two parts, a few modes-only instances"
license = "CC-BY-4.0"

[[parts]]
name = "cubes"
family = "cube_defects"
video = false
splits = { train = 2, test = 1 }

[[parts]]
name = "later"
family = "drum_defects"
video = true
splits = { test = 1 }
"""


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    root = tmp_path_factory.mktemp("release")
    definition = root / "tiny-release.toml"
    definition.write_text(TINY)
    out = root / "build"
    assert main(["release", "build", str(definition), "-o", str(out), "--part", "cubes"]) == 0
    assert main(["release", "freeze", str(out), "--release", str(definition)]) == 0
    return root, definition, out


def test_the_shipped_release_is_well_formed():
    rel = load_release("vvtbench-v1")
    assert rel.n_instances() > 0 and {p.family for p in rel.parts} == {
        "cube_defects", "drum_defects", "bunny_defects"}
    assert any(not p.video for p in rel.parts) and any(p.video for p in rel.parts)
    check_environment_file(rel)  # its lock file, as recorded
    lock = rel.environment_path.read_text()
    assert "numpy==" in lock and "scipy==" in lock and "scikit-sparse==" in lock
    assert rel.tolerances() == TOLERANCES  # the documented ones (docs/dataset.md)


@pytest.mark.parametrize("text, match", [
    ("[tolerances]\nrtol = 1e-3\n", "tolerances.rtol"),
    ("[tolerances]\ndn = 0.5\n", "tolerances.dn"),
    ('environment = "../x.lock"\n', "key 'environment'"),
])
def test_bad_tolerances_and_environments_are_refused(tmp_path, text, match):
    head, parts = TINY.split("[[parts]]", 1)
    definition = tmp_path / "bad.toml"
    definition.write_text(head + text + "[[parts]]" + parts)
    with pytest.raises(ReleaseError, match=match):
        load_release(definition)


@pytest.mark.skipif(platform.machine() not in ("x86_64", "AMD64"),
                    reason="OpenBLAS kernel names are x86-64 ones")
def test_a_rebuild_on_another_cpu_verifies_value_by_value(built, tmp_path, capsys):
    """A rebuild with another BLAS kernel (OPENBLAS_CORETYPE emulates another CPU) matches the
    frozen files value by value against a copy of them; a value beyond the tolerances, or a
    reference that is not the frozen files, fails with the file named."""
    from test_sample_compare import _edit, _remanifest

    root, definition, out = built
    rebuild = tmp_path / "rebuild"
    env = {**os.environ, "OPENBLAS_CORETYPE": "Prescott"}
    subprocess.run([sys.executable, "-m", "vvtbench.cli", "release", "build", str(definition),
                    "-o", str(rebuild), "--part", "cubes"], env=env, check=True,
                   capture_output=True)
    capsys.readouterr()
    assert main(["release", "verify", str(rebuild), "--release", str(definition), "--against",
                 str(out)]) == 0
    said = capsys.readouterr().out
    assert "match tiny-release value by value (3 samples:" in said and "rtol_f64 1e-08" in said
    sample = next((rebuild / "cubes" / "train").iterdir())
    _edit(sample, "modes/eigenvalues", lambda x: x * (1 + 1e-6))
    _remanifest(sample)
    assert main(["release", "verify", str(rebuild), "--release", str(definition), "--against",
                 str(out)]) == 1
    err = capsys.readouterr().err
    assert f"cubes/train/{sample.name}/truth.zarr/modes/eigenvalues: values differ by" in err
    assert main(["release", "verify", str(out), "--release", str(definition), "--against",
                 str(rebuild)]) == 1  # the reference must be the frozen files
    assert "the copy to compare with must be the frozen files" in capsys.readouterr().err


def test_a_copy_verifies_byte_for_byte(built, tmp_path, capsys):
    root, definition, out = built
    sums = read_sums(definition.with_suffix(".sha256"))
    assert sums and all(k.startswith("cubes/") or "/" not in k for k in sums)
    assert "files_sha256" in definition.read_text()
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    assert main(["release", "verify", str(copy), "--release", str(definition)]) == 0
    assert "match tiny-release byte for byte" in capsys.readouterr().out


@pytest.mark.parametrize("damage", ["flip", "delete", "extra", "link"])
def test_a_damaged_copy_fails_naming_the_file(built, tmp_path, capsys, damage):
    root, definition, out = built
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    victim = next(p for p in sorted(copy.rglob("*.json")) if "cube_defects-train" in str(p))
    rel = victim.relative_to(copy).as_posix()
    if damage == "flip":
        data = bytearray(victim.read_bytes())
        data[len(data) // 2] ^= 1
        victim.write_bytes(bytes(data))
    elif damage == "delete":
        victim.unlink()
    elif damage == "extra":
        rel = "cubes/train/notes.txt"
        (copy / rel).write_text("mine")
    else:
        victim.unlink()
        os.symlink(out / rel, victim)
    capsys.readouterr()
    assert main(["release", "verify", str(copy), "--release", str(definition)]) == 1
    assert rel in capsys.readouterr().err


def test_an_edited_list_and_an_unfrozen_part_are_refused(built, tmp_path, capsys):
    root, definition, out = built
    assert main(["release", "verify", str(out), "--release", str(definition), "--part",
                 "later"]) == 2
    assert "no frozen files yet" in capsys.readouterr().err
    fake = tmp_path / "tiny-release.toml"
    shutil.copy(definition, fake)
    sums = definition.with_suffix(".sha256").read_text().splitlines()
    fake.with_suffix(".sha256").write_text("\n".join(sums[1:]) + "\n")
    assert main(["release", "verify", str(out), "--release", str(fake)]) == 2
    assert "the list was edited" in capsys.readouterr().err


def test_a_rebuild_resumes(built, capsys):
    root, definition, out = built
    before = {p: p.stat().st_mtime_ns for p in out.rglob("truth.json")}
    assert main(["release", "build", str(definition), "-o", str(out), "--part", "cubes"]) == 0
    assert {p: p.stat().st_mtime_ns for p in out.rglob("truth.json")} == before
    assert main(["release", "verify", str(out), "--release", str(definition)]) == 0


def test_a_build_lists_only_its_files_and_never_writes_over_the_users(built, tmp_path,
                                                                      capsys):
    root, definition, out = built
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)  # a build: its own folder, resumed
    (copy / "notes.txt").write_text("mine")
    (copy / "cubes" / "train" / "notes.txt").write_text("mine")
    assert main(["release", "build", str(definition), "-o", str(copy), "--part", "cubes"]) == 0
    listed = read_sums(copy / "SHA256SUMS")
    assert listed and not any("notes.txt" in k for k in listed)
    assert all(k.startswith("cubes/") and "/cube_defects-" in k for k in listed)
    assert (copy / "notes.txt").read_text() == "mine"
    (copy / ".vvtbench-output.json").unlink()  # a build made before folders were marked
    (copy / "notes.txt").unlink()
    assert main(["release", "build", str(definition), "-o", str(copy), "--part", "cubes"]) == 0
    theirs = tmp_path / "theirs"
    theirs.mkdir()
    (theirs / "SHA256SUMS").write_text("their own list\n")
    (theirs / "notes.txt").write_text("mine")
    capsys.readouterr()
    assert main(["release", "build", str(definition), "-o", str(theirs), "--part", "cubes"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(theirs) in err[0] and "SHA256SUMS" in err[0]
    assert sorted(os.listdir(theirs)) == ["SHA256SUMS", "notes.txt"]
    assert (theirs / "SHA256SUMS").read_text() == "their own list\n"
