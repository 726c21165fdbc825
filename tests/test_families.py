"""Scene families (vvtbench.scene.families): format, deterministic draws, disjoint splits, and
``vvtbench generate FAMILY`` (docs/families.md)."""

from __future__ import annotations

import itertools
import json
import math
import os
import platform
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from vvtbench.bench.resolve import resolve_scenes
from vvtbench.cli import generate as cli_generate
from vvtbench.scene import families as fam
from vvtbench.scene.scene import parse_scene
from vvtbench.simulation.simulate import build_mesh, load_nodes, material_fields

SHIPPED = ("cube_defects", "bunny_defects", "drum_defects")
N = 12  # instances per split in the disjointness tests

TINY_FAMILY = """
name = "tiny_defects"
description = "a 3^3 cube with up to two defects"

[base.geometry]   # an inline base scene
kind = "box"
cells = [3, 3, 3]

[base.excitation]
kind = "pluck"
at = [0.05, 0.0, 0.05]
displacement = 0.002

[base.simulation]
n_modes = 6
duration = 0.02
fps = 1000.0

[base.camera]
resolution = [32, 32]
position = [0.16, -0.13, 0.13]
look_at = [0.025, 0.025, 0.022]
fov_y_deg = 30.0

[base.render]
supersample = 1

[defects]
count = {{ int = [0, 2] }}
size = {{ uniform = [0.2, 0.4] }}

[excitation]
at = [{{ uniform = [0.0, 1.0] }}, {{ uniform = [0.0, 1.0] }}, {{ uniform = [0.5, 1.0] }}]

[camera]
cone_deg = 10.0
"""


@pytest.fixture
def tiny(tmp_path) -> Path:
    path = tmp_path / "tiny_defects.toml"
    path.write_text(TINY_FAMILY.format(extra=""))
    return path


def _physical(scene) -> str:
    d = scene.to_toml_dict()
    return json.dumps({k: v for k, v in d.items() if k not in ("name", "description", "seed")},
                      sort_keys=True)


# --------------------------------------------------------------------------- format
@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_families_load(name):
    f = fam.load_family(name)
    assert f.name == name and f.defects is not None
    assert name in fam.list_families() and fam.is_family(name)


@pytest.mark.parametrize("text, match", [
    ('name = "x"\nbase = "jello_cube_homogeneous"\ncolour = 1\n',
     r"key 'colour': unknown key; allowed keys here: name, description, base"),
    ('name = "x"\nbase = "jello_cube_homogeneous"\n[defects]\ncount = { int = [0, 30] }\n',
     r"key 'defects.count': .*value 30 is not allowed; allowed: integers >= 0 and <= 16"),
    ('name = "x"\nbase = "jello_cube_homogeneous"\n[defects]\nsize = { normal = [0, 1] }\n',
     r"key 'defects.size': .*allowed: a value, or a table with one key of uniform"),
    ('name = "x"\nbase = "jello_cube_homogeneous"\n[defects]\nE_ratio = { loguniform = [0, 1] }\n',
     r"key 'defects.E_ratio': .*allowed: 0 < low <= high"),
    ('name = "x"\nbase = "jello_cube_homogeneous"\n[defects]\nshape = { choice = ["cone"] }\n',
     r"key 'defects.shape': .*allowed: one of 'box', 'sphere', 'ellipsoid', 'cylinder'"),
    ('name = "x"\nbase = "no_such_scene_xyz"\n', r"key 'base': .*no such scene file"),
    ('name = "x-y"\nbase = "jello_cube_homogeneous"\n', r"key 'name': .*no '-'"),
    ('name = "x"\nbase = "drum_homogeneous"\n[geometry]\naspect = [1, 1, 2]\n',
     r"key 'geometry.aspect': the base scene is not a box"),
    ('name = "x"\nbase = "jello_cube_homogeneous"\n[vary]\n"colour.x" = 1\n',
     r"not a scene key"),
])
def test_bad_family_files_give_one_line_errors(tmp_path, text, match):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(fam.FamilyError, match=match) as info:
        fam.load_family(path)
    assert "\n" not in str(info.value) and str(path) in str(info.value)


def test_bad_split_and_index():
    with pytest.raises(fam.FamilyError, match="allowed: train, val, test"):
        fam.draw("cube_defects", "dev", 0)
    with pytest.raises(fam.FamilyError, match="allowed: an integer"):
        fam.draw("cube_defects", "test", -1)


# --------------------------------------------------------------------------- draws
@pytest.mark.parametrize("name", SHIPPED)
def test_draw_is_deterministic_named_seeded_and_round_trips(name):
    a = fam.draw(name, "test", 3)
    b = fam.draw(name, "test", 3)
    assert a == b
    assert a.name == f"{name}-test-00003"
    assert a.seed == fam.instance_seed(name, "test", 3) == fam.family_info(name, "test", 3)["seed"]
    again = parse_scene(a.to_toml_dict(), "again")
    assert again.to_toml_dict() == a.to_toml_dict()


@pytest.mark.parametrize("name", ("cube_defects", "drum_defects"))
def test_drawn_scenes_pass_the_mesh_checks(name):
    """Every defect catches an element centroid, the pluck is on the body: what simulate
    checks before solving."""
    for i in range(8):
        scene = fam.draw(name, "train", i)
        mesh = build_mesh(scene)
        for d in scene.material.defects:
            assert d.contains(mesh.centroids).any()
        material_fields(scene, mesh)
        if scene.excitation.kind != "none":
            assert len(load_nodes(scene, mesh))


def test_cube_family_covers_what_varies():
    scenes = [fam.draw("cube_defects", "train", i) for i in range(40)]
    counts = {len(s.material.defects) for s in scenes}
    assert counts == {0, 1, 2, 3}
    defects = [d for s in scenes for d in s.material.defects]
    assert {d.shape for d in defects} == {"box", "sphere", "ellipsoid", "cylinder"}
    ratios = np.array([d.E / 9000.0 for d in defects])
    assert ratios.min() < 0.1 and ratios.max() > 10  # softer and stiffer than the matrix
    z = np.array([d.center[2] / s.geometry.size[2] for s in scenes for d in s.material.defects])
    assert z.min() < 0.2 and z.max() > 0.8  # near the fixed base, and near the top
    sizes = {tuple(s.geometry.size) for s in scenes}
    assert len(sizes) == len(scenes)  # box aspect varies
    positions = np.array([s.camera.position for s in scenes])
    base = np.array(fam.load_family("cube_defects").base and (0.16, -0.13, 0.13))
    assert np.ptp(positions, axis=0).min() > 0.01 and not np.allclose(positions, base)
    assert len({s.render.read_noise_dn for s in scenes}) > 1
    assert len({tuple(s.excitation.at) for s in scenes}) == len(scenes)


def test_drum_family_has_square_and_circular_heads():
    shapes = {fam.draw("drum_defects", "val", i).geometry.shape for i in range(12)}
    assert shapes == {"square", "circle"}


def test_camera_stays_within_its_cone():
    f = fam.load_family("cube_defects")
    base = fam._base_scene(f, f.base)
    look0, pos0 = np.array(base.camera.look_at), np.array(base.camera.position)
    for i in range(20):
        s = fam.draw("cube_defects", "test", i)
        stretch = np.array(s.geometry.size) / np.array(base.geometry.size)
        look = np.array(s.camera.look_at)
        assert np.allclose(look, look0 * stretch)
        v0, v = pos0 - look0, np.array(s.camera.position) - look
        angle = np.degrees(np.arccos(v0 @ v / np.linalg.norm(v0) / np.linalg.norm(v)))
        assert angle <= 15.0 + 1e-9


# --------------------------------------------------------------------------- disjoint splits
@pytest.mark.parametrize("name", ("cube_defects", "drum_defects"))
def test_splits_never_share_an_instance(name):
    drawn = {split: [fam.draw(name, split, i) for i in range(N)] for split in fam.SPLITS}
    for split, scenes in drawn.items():
        for s in scenes:  # the construction: a content can only ever belong to one split
            assert fam.split_of_content(s.to_toml_dict()) == split
    for a, b in itertools.combinations(fam.SPLITS, 2):
        assert not {_physical(s) for s in drawn[a]} & {_physical(s) for s in drawn[b]}
        assert not {s.seed for s in drawn[a]} & {s.seed for s in drawn[b]}
    everything = [_physical(s) for scenes in drawn.values() for s in scenes]
    assert len(set(everything)) == len(everything)


def test_identical_content_cannot_land_in_two_splits(tmp_path):
    """A family with a single possible scene: only the split its content hashes to can be
    drawn; the other two fail instead of repeating it."""
    path = tmp_path / "fixed.toml"
    path.write_text('name = "fixed"\nbase = "jello_cube_homogeneous"\nattempts = 20\n')
    own = fam.split_of_content(fam._base_scene(fam.load_family(path), "jello_cube_homogeneous")
                               .model_copy(update={"name": "x"}).to_toml_dict())
    for split in fam.SPLITS:
        if split == own:
            assert fam.draw(path, split, 0).name == f"fixed-{split}-00000"
        else:
            with pytest.raises(fam.FamilyError, match="no valid draw in 20 attempts"):
                fam.draw(path, split, 0)


def test_streams_depend_on_family_split_and_index():
    seeds = {fam.instance_seed(f, s, i) for f in ("a", "b") for s in fam.SPLITS
             for i in range(50)}
    assert len(seeds) == 2 * 3 * 50


# --------------------------------------------------------------------------- generate
# instances a BLAS kernel other than this machine's drew differently while the draw normed its
# vectors with BLAS: the content hash that picks the split saw the last bit
_KERNEL_SENSITIVE = {"Haswell": [("cube_defects", "train", 9), ("cube_defects", "train", 11)],
                     "Prescott": [("cube_defects", "train", 3), ("bunny_defects", "val", 2)]}


@pytest.mark.skipif(platform.machine() not in ("x86_64", "AMD64"),
                    reason="OpenBLAS kernel names are x86-64 ones")
@pytest.mark.parametrize("kernel", sorted(_KERNEL_SENSITIVE))
def test_draws_do_not_depend_on_the_blas_kernel(kernel):
    """Another CPU is emulated by OpenBLAS's kernel choice (OPENBLAS_CORETYPE): the drawn
    scenes must be the same bits, or an instance changes."""
    cases = _KERNEL_SENSITIVE[kernel]
    code = ("import json, sys; from vvtbench.scene.families import draw; "
            "print(json.dumps([draw(f, s, i).to_toml_dict() for f, s, i in "
            f"{cases!r}]))")
    env = {**os.environ, "OPENBLAS_CORETYPE": kernel}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         check=True).stdout
    assert json.loads(out) == [json.loads(json.dumps(fam.draw(f, s, i).to_toml_dict()))
                               for f, s, i in cases]


def test_length3_rounds_like_a_fused_sum():
    v = np.array([0.1, -0.7, 0.3])
    assert fam.length3(v) == math.sqrt(fam._fma(0.3, 0.3, fam._fma(-0.7, -0.7, 0.1 * 0.1)))
    assert fam.length3([3.0, 4.0, 12.0]) == 13.0


def test_generate_family_modes_only_resumes_and_is_byte_identical(tiny, tmp_path, capsys):
    out = tmp_path / "out"
    argv = [str(tiny), "--split", "train", "--n", "2", "--start", "5", "--no-video",
            "-o", str(out), "--no-progress"]
    assert cli_generate.main(argv) == 0
    names = sorted(p.name for p in out.iterdir())
    assert names == ["tiny_defects-train-00005", "tiny_defects-train-00006"]
    sample = out / names[0]
    info = json.loads((sample / "family.json").read_text())
    assert info["family"] == "tiny_defects" and info["split"] == "train"
    assert info["index"] == 5 and info["seed"] == fam.instance_seed("tiny_defects", "train", 5)
    manifest = json.loads((sample / "manifest.json").read_text())
    assert "family.json" in manifest["files"]
    scene = fam.draw(tiny, "train", 5)
    import tomllib

    saved = parse_scene(tomllib.loads((sample / "scene.toml").read_text()), "saved")
    assert saved.to_toml_dict() == scene.to_toml_dict()
    before = {p.relative_to(sample): p.read_bytes() for p in sample.rglob("*") if p.is_file()}
    capsys.readouterr()
    assert cli_generate.main(argv) == 0  # resumable: complete samples are skipped
    assert capsys.readouterr().out.count("skipped") == 2
    assert cli_generate.main(argv + ["--overwrite"]) == 0
    after = {p.relative_to(sample): p.read_bytes() for p in sample.rglob("*") if p.is_file()}
    assert after == before


def test_generate_family_with_workers(tiny, tmp_path):
    out = tmp_path / "out"
    assert cli_generate.main([str(tiny), "--split", "test", "--n", "3", "--no-video",
                              "--workers", "2", "-o", str(out)]) == 0
    assert len([p for p in out.iterdir() if (p / "manifest.json").is_file()]) == 3


def test_generate_family_needs_split_and_n(tiny, tmp_path, capsys):
    assert cli_generate.main([str(tiny), "-o", str(tmp_path), "--no-progress"]) == 2
    assert "needs --split" in capsys.readouterr().err
    assert cli_generate.main(["jello_cube_homogeneous", "--n", "2", "-o", str(tmp_path)]) == 2
    assert "for scene families" in capsys.readouterr().err


def test_generate_suite_applies_its_defaults():
    scenes = resolve_scenes("smoke")
    assert [s.name for s in scenes] == ["jello_cube_defect_top", "jello_cube_defect_bottom"]
    for s in scenes:
        assert s.geometry.cells == (6, 6, 6)
        assert s.camera.resolution == (128, 128)
        assert s.simulation.n_modes == 16 and s.simulation.fps == 500.0
        assert s.render.supersample == 2 and s.excitation.displacement == 0.0005


def test_generate_family_on_a_dask_cluster(tiny, tmp_path):
    """``--scheduler``: the same jobs on Dask (an in-process cluster here)."""
    distributed = pytest.importorskip("distributed")
    from vvtbench.scene.families import load_family

    f = load_family(tiny)
    jobs = [{"out": str(tmp_path), "family": f.source, "split": "val", "index": i,
             "name": f"tiny_defects-val-{i:05d}", "options": {"video": False,
                                                              "progress": False},
             "threads": 1} for i in range(2)]
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster:
        results = list(cli_generate.execute_jobs(jobs, 1, cluster))
    assert sorted(r["status"] for r in results) == ["done", "done"]
    assert all((tmp_path / j["name"] / "family.json").is_file() for j in jobs)


def test_files_of_the_base_scene_stay_found(tmp_path):
    """A base scene's relative file paths become absolute in the drawn scene."""
    (tmp_path / "base").mkdir()
    (tmp_path / "base" / "force.csv").write_text("0.0,0.0\n0.01,0.001\n")
    (tmp_path / "base" / "tapped.toml").write_text(
        'name = "tapped"\n[geometry]\nkind = "box"\ncells = [3, 3, 3]\n'
        '[excitation]\nkind = "force"\nat = [0.05, 0.0, 0.05]\n'
        '[excitation.signal]\nkind = "file"\npath = "force.csv"\n')
    (tmp_path / "fam").mkdir()
    (tmp_path / "fam" / "tapped.toml").write_text(
        'name = "tapped"\nbase = "../base/tapped.toml"\n[camera]\ncone_deg = 5.0\n')
    scene = fam.draw(tmp_path / "fam" / "tapped.toml", "val", 0)
    path = Path(scene.excitation.signal.path)
    assert path.is_absolute() and path.is_file()


@pytest.mark.parametrize("argv", [
    ["generate", "cube_defects", "--split", "val", "--n", "99999999999999999999"],
    ["generate", "cube_defects", "--split", "val", "--start", "4294967290", "--n", "10"],
    ["train", "learned", "cube_defects", "--n", "99999999999999999999", "--drop-instances"],
    ["train", "learned", "cube_defects", "--start", "4294967295", "--n", "2"],
])
def test_a_huge_or_out_of_range_instance_count_is_one_line_before_any_work(argv, tmp_path,
                                                                           capsys):
    """Not a list of 10^20 jobs: refused up front, nothing written."""
    from vvtbench.cli import main

    out = tmp_path / "out"
    with pytest.raises(SystemExit) as stop:
        code = main([*argv, "-o", str(out if argv[0] == "generate" else out / "w.npz")])
        raise SystemExit(code)
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and ("--n" in err[0] or "--start" in err[0]), err
    assert not out.exists()
