"""Exported datasets (vvtbench.datasets.export, vvtbench.datasets.packed, `vvtbench export`): round
trip, xarray,
Croissant, safety.

Rendering needs headless EGL (Mesa llvmpipe is fine); see tests/test_render.py.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from vvtbench.cli import main as cli_main
from vvtbench.cli.export import main as export_main
from vvtbench.datasets.croissant import CONTEXT
from vvtbench.datasets.export import pack
from vvtbench.datasets.packed import ExportError, open_dataset
from vvtbench.modes import ModeSet
from vvtbench.render.camera import Camera
from vvtbench.samples import reader as ds
from vvtbench.samples.generate import generate
from vvtbench.scene.scene import Scene, parse_scene

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
T, H, W = 20, 32, 24
ENGINES = {"zarr": ("ds.zarr", "zarr"), "hdf5": ("ds.h5", "h5netcdf")}


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _tree(path: Path) -> dict[str, bytes]:
    return {p.relative_to(path).as_posix(): p.read_bytes()
            for p in sorted(path.rglob("*")) if p.is_file()}


def _rewrite_manifest(sample: Path) -> None:
    """Record the sample's current files in its manifest (as generate does)."""
    m = json.loads((sample / "manifest.json").read_text())
    m["files"] = {p.relative_to(sample).as_posix(): {"sha256": _sha256(p),
                                                      "bytes": p.stat().st_size,
                                                      "description": ""}
                  for p in sorted(sample.rglob("*"))
                  if p.is_file() and p.name != "manifest.json"}
    (sample / "manifest.json").write_text(json.dumps(m))


def _modeset(k: int = 2, F: int = 11) -> ModeSet:
    rng = np.random.default_rng(1)
    return ModeSet(
        frequencies_hz=np.array([120.0, 340.0])[:k], damping=np.array([0.01, np.nan])[:k],
        damping_half_power=np.full(k, 0.02), shapes=rng.normal(size=(k, H, W, 2)),
        amplitudes_px=np.full(k, 0.3), peak_bins=np.arange(k), prominences=np.ones(k),
        collinearity=np.ones(k), shake_mac=np.zeros(k), camera_shake=np.zeros(k, bool),
        freqs_hz=np.linspace(0, 1000, F), power=rng.random(F), fps=2000.0, n_frames=T,
        confidence=rng.random((H, W)).astype(np.float32), metadata={"source": "test"})


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    scene = parse_scene(json.loads(json.dumps(TINY)), "tiny")
    return generate(scene, tmp_path_factory.mktemp("samples"), progress=False,
                    preview_frames=2)


@pytest.fixture(scope="module")
def run_dir(tiny, tmp_path_factory) -> Path:
    """A run folder's layout: the sample in cache/generate/KEY/sample, one extraction of it in
    cache/extract/KEY2/, and an extra truth array family (extra/*) that the exporter does not
    know by name."""
    run = tmp_path_factory.mktemp("run")
    sample = run / "cache" / "generate" / "abc123" / "sample"
    shutil.copytree(tiny, sample)
    import zarr

    root = zarr.open_group(str(sample / "truth.zarr"), mode="r+")
    for name, data in (("extra/fixed", np.array([0, 1, 2, 5])),
                       ("extra/sets/top", np.array([3, 4])),
                       ("extra/sets/weird", np.arange(6.0).reshape(2, 3))):
        a = root.create_array(name, shape=data.shape, dtype=data.dtype)
        a[...] = data
    _rewrite_manifest(sample)
    ext = run / "cache" / "extract" / "def456"
    _modeset().save(ext)
    (ext / "task.json").write_text(json.dumps({"stage": "extract",
                                               "deps": ["generate/abc123"]}))
    other = run / "cache" / "extract" / "zzz999"  # another sample's extraction: not packed
    _modeset(1).save(other)
    (other / "task.json").write_text(json.dumps({"deps": ["generate/other"]}))
    return run


@pytest.fixture(scope="module", params=["zarr", "hdf5"])
def packed(request, run_dir, tmp_path_factory) -> tuple[str, Path, Path]:
    fmt = request.param
    out = tmp_path_factory.mktemp("out") / ENGINES[fmt][0]
    assert export_main([str(run_dir), "--format", fmt, "-o", str(out)]) == 0
    return fmt, out, run_dir / "cache" / "generate" / "abc123" / "sample"


def _truth_names(sample: Path) -> list[str]:
    import zarr

    out = []

    def walk(g, prefix=""):
        for name, obj in g.members():
            if isinstance(obj, zarr.Array):
                out.append(prefix + name)
            else:
                walk(obj, prefix + name + "/")

    walk(zarr.open_group(str(sample / "truth.zarr"), mode="r"))
    return sorted(out)


# --------------------------------------------------------------------------- round trip
def test_packed_sample_reads_like_the_sample(packed):
    fmt, out, folder = packed
    s = ds.open_sample(folder)
    with open_dataset(out) as d:
        assert d.names == ["tiny"] and len(d) == 1
        p = d["tiny"]
        assert isinstance(p.scene, Scene) and p.scene.to_toml_dict() == s.scene.to_toml_dict()
        assert isinstance(p.camera, Camera) and p.camera == s.camera
        assert p.info == s.info and p.manifest == s.manifest and p.seed == 7
        assert (p.n_frames, p.fps, p.shape, p.bit_depth) == (T, 2000.0, (H, W), 16)
        assert p.has_video
        names = _truth_names(folder)
        assert "extra/sets/top" in names and "mesh/fixed_nodes" in names
        assert sorted(p.truth_arrays) == names
        for name in names:  # every array, same dtype and values (NaN and inf included)
            a, b = p[name], s[name]
            assert a.dtype == b.dtype and a.shape == b.shape, name
            np.testing.assert_array_equal(a, b, err_msg=name)
        np.testing.assert_array_equal(p.read_frames(), s.read_frames())
        np.testing.assert_array_equal(p.read_frames(3, 7), s.read_frames(3, 7))
        np.testing.assert_allclose(next(p.frames(5, 6, normalize=True)),
                                   next(s.frames(5, 6, normalize=True)))
        np.testing.assert_array_equal(p.frequencies_hz, s.frequencies_hz)
        np.testing.assert_array_equal(p.times, s.times)
        # the extracted modes of this sample, not the other one
        (ms,) = p.extracted_modes()
        ref = _modeset()
        for f in ("frequencies_hz", "damping", "shapes", "freqs_hz", "power", "confidence",
                  "camera_shake", "peak_bins"):
            np.testing.assert_array_equal(getattr(ms, f), getattr(ref, f), err_msg=f)
        assert (ms.fps, ms.n_frames, ms.metadata) == (ref.fps, ref.n_frames, ref.metadata)
        assert len(repr(p)) < 200 and "tiny" in repr(p) and f"{H}x{W}" in repr(p)
        assert len(repr(d)) < 200 and "1 samples" in repr(d)
        assert "Stanford 3D Scanning Repository" in d.readme
        with pytest.raises(KeyError, match="no truth array"):
            p.array("nope")


def test_sample_without_extracted_modes(tiny, tmp_path):
    out = pack([tiny], tmp_path / "x.zarr")
    with open_dataset(out) as d:
        assert d["tiny"].extracted_modes() == []


# --------------------------------------------------------------------------- xarray
def test_xarray_opens_with_dims_coords_and_units(packed):
    fmt, out, folder = packed
    s = ds.open_sample(folder)
    tree = xr.open_datatree(out, engine=ENGINES[fmt][1])
    node = tree["samples/tiny"].ds
    video = node["video"]
    assert video.dims == ("time", "row", "col") and video.dtype == np.uint16
    np.testing.assert_array_equal(video.values, s.read_frames())
    assert video.attrs["units"] == "DN"
    np.testing.assert_allclose(node["time"].values, s.times)
    assert node["time"].attrs["units"] == "s"
    np.testing.assert_array_equal(node["row"].values, np.arange(H))
    np.testing.assert_array_equal(node["col"].values, np.arange(W))
    assert node["row"].attrs["units"] == "px" and node["col"].attrs["units"] == "px"
    np.testing.assert_array_equal(node["mode"].values, np.arange(4))
    # voxel centres: an 8^3 grid over the 0.05 m cube
    np.testing.assert_allclose(node["voxel_x"].values, (np.arange(8) + 0.5) * 0.05 / 8)
    assert node["voxel_z"].attrs["units"] == "m"
    vox = tree["samples/tiny/truth/voxels"].ds
    assert vox["stiffness"].dims == ("voxel_x", "voxel_y", "voxel_z")
    assert vox["stiffness"].attrs["units"] == "Pa"
    np.testing.assert_array_equal(vox["stiffness"].values, s["voxels/stiffness"])
    assert "voxel_x" in vox.coords  # inherited from the sample group
    mesh = tree["samples/tiny/truth/mesh"].ds
    assert mesh["points"].dims == ("node", "xyz") and mesh["points"].attrs["units"] == "m"
    assert mesh["fixed_nodes"].dims == ("fixed_node",)
    np.testing.assert_array_equal(mesh["cells"].values, s["mesh/cells"])
    sets = tree["samples/tiny/truth/extra/sets"].ds
    np.testing.assert_array_equal(sets["top"].values, [3, 4])
    assert sets["weird"].shape == (2, 3)
    image = tree["samples/tiny/truth/image"].ds
    assert image["modes"].dims == ("mode", "row", "col", "uv")
    np.testing.assert_array_equal(image["triangle"].values, s["image/triangle"])  # -1 kept
    tr = tree["samples/tiny/truth/transient"].ds
    assert tr["displacements"].dims == ("time", "surface_node", "xyz")
    assert tr["displacements"].attrs["units"] == "m"
    modes = tree["samples/tiny/truth/modes"].ds
    assert modes["frequencies_hz"].dims == ("mode",)
    assert modes["frequencies_hz"].attrs["units"] == "Hz"
    ext = tree["samples/tiny/extracted/0"].ds
    assert ext["shapes"].dims == ("extracted_mode", "row", "col", "component")
    assert ext["power"].dims == ("frequency",)
    assert ext["frequency"].attrs["units"] == "Hz"
    np.testing.assert_allclose(ext["frequency"].values, np.linspace(0, 1000, 11))
    assert ext["frequencies_hz"].attrs["units"] == "Hz"
    # and a single group with plain open_dataset
    one = xr.open_dataset(out, group="samples/tiny/truth/material", engine=ENGINES[fmt][1])
    assert one["density"].dims == ("element",) and one["density"].attrs["units"] == "kg/m3"


def test_hdf5_has_dimension_scales_and_compression(packed):
    fmt, out, _ = packed
    if fmt != "hdf5":
        return
    import h5py

    with h5py.File(out, "r") as f:
        v = f["samples/tiny/video"]
        assert v.compression == "gzip" and v.shuffle and v.chunks[0] <= 64
        assert [d.label or v.dims[i][0].name.split("/")[-1] for i, d in enumerate(v.dims)] \
            == ["time", "row", "col"]
        assert f["samples/tiny/time"].is_scale
        pts = f["samples/tiny/truth/mesh/points"]
        assert pts.compression == "gzip" and pts.dims[0][0].name.endswith("/node")


def test_croissant_file(packed):
    fmt, out, _ = packed
    path = out / "croissant.json" if fmt == "zarr" else Path(f"{out}.croissant.json")
    meta = json.loads(path.read_text())
    assert meta["@type"] == "sc:Dataset" and meta["conformsTo"].endswith("croissant/1.1")
    assert meta["@context"] == CONTEXT  # one context for both layouts
    assert meta["license"].startswith("https://creativecommons.org/licenses/by/4.0")
    assert meta["name"] and meta["description"]
    files = [d for d in meta["distribution"] if d["@type"] == "cr:FileObject"]
    target = out / "zarr.json" if fmt == "zarr" else out
    assert files[0]["sha256"] == _sha256(target)
    sets = {rs["name"]: rs for rs in meta["recordSet"]}
    assert set(sets) == {"sample_index", "view_index", "samples"}  # no views: no "views" set
    names = {f["name"] for f in sets["samples"]["field"]}
    assert {"video", "frequencies_hz", "stiffness", "density"} <= names
    card = out / "README.md" if fmt == "zarr" else Path(f"{out}.README.md")
    assert card.read_text().startswith("# vvtbench dataset")


# --------------------------------------------------------------------------- data safety
def _err(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    return err


def test_output_dot_never_deletes_the_current_folder(tiny, tmp_path, monkeypatch, capsys):
    here = tmp_path / "work"
    here.mkdir()
    (here / "keep.txt").write_text("mine")
    monkeypatch.chdir(here)
    for fmt in ("zarr", "hdf5"):
        assert export_main([str(tiny), "--format", fmt, "-o", "."]) == 2
        _err(capsys)
        assert export_main([str(tiny), "--format", fmt, "-o", ".", "--overwrite"]) == 2
        _err(capsys)
    assert sorted(p.name for p in here.iterdir()) == ["keep.txt"]
    # the folder holding the sample: contains the input
    monkeypatch.chdir(tiny.parent)
    assert export_main([str(tiny), "-o", ".", "--overwrite"]) == 2
    assert ds.open_sample(tiny).verify() == []


@pytest.mark.parametrize("where", ["itself", "inside", "parent"])
def test_output_may_not_be_contain_or_lie_in_the_input(tiny, where, capsys):
    before = _tree(tiny)
    out = {"itself": tiny, "inside": tiny / "ds.zarr", "parent": tiny.parent}[where]
    assert export_main([str(tiny), "-o", str(out), "--overwrite"]) == 2
    assert "input" in _err(capsys)
    assert _tree(tiny) == before


def test_existing_output_is_refused_unless_ours_and_overwrite(tiny, tmp_path, capsys):
    # a folder with someone else's files: refused, even with --overwrite
    other = tmp_path / "other.zarr"
    other.mkdir()
    (other / "notes.txt").write_text("x")
    assert export_main([str(tiny), "-o", str(other)]) == 2
    assert str(other) in _err(capsys)
    assert export_main([str(tiny), "-o", str(other), "--overwrite"]) == 2
    _err(capsys)
    assert (other / "notes.txt").read_text() == "x"
    # an empty folder is not ours either
    empty = tmp_path / "empty.zarr"
    empty.mkdir()
    assert export_main([str(tiny), "-o", str(empty)]) == 2
    _err(capsys)
    assert not any(empty.iterdir())
    # a file that is not our HDF5
    f = tmp_path / "data.h5"
    f.write_bytes(b"precious")
    assert export_main([str(tiny), "-o", str(f), "--overwrite"]) == 2
    assert "not a hdf5 dataset written by vvtbench" in _err(capsys)
    assert f.read_bytes() == b"precious"
    # our own dataset: refused without --overwrite, replaced with it
    for name in ("ours.zarr", "ours.h5"):
        out = tmp_path / name
        assert export_main([str(tiny), "-o", str(out)]) == 0
        capsys.readouterr()
        assert export_main([str(tiny), "-o", str(out)]) == 2
        assert "--overwrite" in _err(capsys)
        assert export_main([str(tiny), "-o", str(out), "--overwrite"]) == 0
        with open_dataset(out) as d:
            assert d.names == ["tiny"]
    # our dataset with a stranger's file inside: not replaced
    (tmp_path / "ours.zarr" / "notes.txt").write_text("x")
    assert export_main([str(tiny), "-o", str(tmp_path / "ours.zarr"), "--overwrite"]) == 2
    assert (tmp_path / "ours.zarr" / "notes.txt").is_file()
    assert not [p for p in tmp_path.iterdir() if ".partial-" in p.name or ".old-" in p.name]


def test_no_writing_through_symbolic_links(tiny, tmp_path, capsys):
    real = tmp_path / "real.zarr"
    assert export_main([str(tiny), "-o", str(real)]) == 0
    before = _tree(real)
    link = tmp_path / "link.zarr"
    link.symlink_to(real)
    assert export_main([str(tiny), "-o", str(link), "--overwrite"]) == 2
    assert "symbolic link" in _err(capsys)
    assert _tree(real) == before and link.is_symlink()
    dangling = tmp_path / "dangling.h5"
    dangling.symlink_to(tmp_path / "nowhere.h5")
    assert export_main([str(tiny), "-o", str(dangling)]) == 2
    assert not (tmp_path / "nowhere.h5").exists()
    card = tmp_path / "x.h5.README.md"  # the HDF5 sidecar is checked too
    card.symlink_to(tmp_path / "elsewhere.md")
    assert export_main([str(tiny), "-o", str(tmp_path / "x.h5")]) == 2
    assert not (tmp_path / "elsewhere.md").exists() and not (tmp_path / "x.h5").exists()


def test_writing_is_atomic(tiny, tmp_path, monkeypatch):
    import vvtbench.datasets.export as ex

    out = tmp_path / "ds.zarr"
    pack([tiny], out)
    before = _tree(out)

    def boom(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(ex, "_write_sample", boom)
    for fmt, target in (("zarr", out), ("hdf5", tmp_path / "new.h5")):
        with pytest.raises(OSError, match="disk full"):
            pack([tiny], target, fmt, overwrite=True)
    assert _tree(out) == before  # the old dataset is untouched
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds.zarr"]  # no partial left


def test_paths_with_quotes_and_spaces(tiny, tmp_path):
    src = tmp_path / "it's a \"dir\""
    shutil.copytree(tiny, src / "tiny")
    for name in ("my out's.h5", "o'k dir.zarr"):
        out = tmp_path / name
        assert cli_main(["export", str(src), "-o", str(out)]) == 0
        with open_dataset(out) as d:
            np.testing.assert_array_equal(d["tiny"].read_frames(0, 2),
                                          ds.open_sample(tiny).read_frames(0, 2))


@pytest.mark.parametrize("damage", ["delete_chunk", "edit_scene", "extra_file"])
def test_samples_are_verified_before_export(tiny, tmp_path, damage, capsys):
    s = tmp_path / "s" / "tiny"
    shutil.copytree(tiny, s)
    if damage == "delete_chunk":
        chunk = next(p for p in sorted((s / "truth.zarr" / "material").rglob("*"))
                     if p.is_file() and p.name != "zarr.json")
        chunk.unlink()
    elif damage == "edit_scene":
        chunk = s / "scene.toml"
        chunk.write_text(chunk.read_text().replace("seed = 7", "seed = 8"))
    else:
        chunk = s / "truth.zarr" / "planted.bin"
        chunk.write_bytes(b"x")
    out = tmp_path / "ds.zarr"
    assert export_main([str(s.parent), "-o", str(out)]) == 2
    err = _err(capsys)
    assert chunk.relative_to(s).as_posix() in err
    assert not out.exists()
    with pytest.raises(ExportError, match="manifest"):
        pack([s], tmp_path / "lib.h5", "hdf5")


def test_export_of_a_suite_generates_then_packs(tmp_path, capsys):
    suite = tmp_path / "mini.toml"
    suite.write_text("""
name = "mini"
scenes = ["jello_cube_defect_top"]
solvers = ["homogeneous"]
seeds = [0]
observations = ["extracted"]   # a video sample (true-modes-only suites generate modes-only samples)

[defaults]
"geometry.cells" = [2, 2, 2]
"simulation.n_modes" = 4
"simulation.fps" = 400.0
"simulation.duration" = 0.02
"camera.resolution" = [24, 24]
"render.supersample" = 1
n_modes = 2
inference_shape = [2, 2, 2]
""")
    run = tmp_path / "run"
    # refused before anything is generated
    assert export_main([str(suite), "--run-dir", str(run), "-o", str(run / "x.zarr")]) == 2
    _err(capsys)
    assert not (run / "cache").exists()
    out = tmp_path / "mini.h5"
    assert export_main([str(suite), "--run-dir", str(run), "-o", str(out)]) == 0
    sample = next((run / "cache" / "generate").glob("*/sample"))
    with open_dataset(out) as d:
        assert d.names == ["jello_cube_defect_top"]
        p = d[d.names[0]]
        np.testing.assert_array_equal(p.read_frames(), ds.open_sample(sample).read_frames())
    assert export_main(["no_such_suite", "-o", str(tmp_path / "y.zarr")]) == 2
    assert "no_such_suite" in _err(capsys)


# --------------------------------------------------------------------------- stacked layout
TINY_FAMILY = """
name = "tiny_defects"
description = "a 3^3 cube with up to two defects"

[base.geometry]
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
count = { int = [0, 2] }
size = { uniform = [0.2, 0.4] }

[excitation]
at = [{ uniform = [0.0, 1.0] }, { uniform = [0.0, 1.0] }, { uniform = [0.5, 1.0] }]

[camera]
cone_deg = 25.0
"""


def make_family_samples(root: Path, counts: dict[str, int]) -> Path:
    """Modes-only samples of a tiny family drawn by ``vvtbench generate``: root/<split>/..."""
    family = root / "tiny_defects.toml"
    family.write_text(TINY_FAMILY)
    for split, n in counts.items():
        argv = ["generate", str(family), "--split", split, "--n", str(n), "--no-video", "-o",
                str(root / "samples" / split), "--no-progress"]
        assert cli_main(argv) == 0
    return root / "samples"


@pytest.fixture(scope="module")
def family_samples(tmp_path_factory) -> Path:
    return make_family_samples(tmp_path_factory.mktemp("family"), {"train": 4, "val": 2})


@pytest.fixture(scope="module")
def stacked(family_samples, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("stacked") / "tiny"
    assert export_main([str(family_samples), "-o", str(out), "--layout", "stacked"]) == 0
    return out


def test_stacked_split_opens_as_one_dataset(stacked, family_samples):
    import zarr

    ds = xr.open_zarr(stacked / "tiny_defects" / "train.zarr")
    folders = sorted((family_samples / "train").iterdir())
    assert list(ds["sample"].values) == [p.name for p in folders]
    assert not [d for d in ds.dims if "_dim_" in d]
    assert {"sample", "vertex", "component", "mode", "x", "y", "z"} <= set(ds.dims)
    assert ds.mesh_points.dims == ("sample", "vertex", "component")
    assert ds.mesh_points.attrs["units"] == "m" and ds.material_stiffness.attrs["units"] == "Pa"
    assert list(ds.split.values) == ["train"] * 4
    assert "visible_vertex_mask" in ds and "n_visible_vertex" in ds
    for i, folder in enumerate(folders):
        fam = json.loads((folder / "family.json").read_text())
        assert int(ds.seed[i]) == fam["seed"] and int(ds["index"][i]) == fam["index"]
        truth = zarr.open_group(str(folder / "truth.zarr"), mode="r")
        n_vis = truth["observation/visible_nodes"].shape[0]
        assert int(ds.n_visible_vertex[i]) == n_vis
        assert int(ds.visible_vertex_mask[i].sum()) == n_vis
        for name in ("mesh_points", "modes_frequencies_hz", "voxels_stiffness",
                     "observation_image_modes", "observation_visible_nodes"):
            want = truth[ds[name].attrs["truth_path"]][...]
            got = ds[name][i].values
            np.testing.assert_array_equal(got[tuple(slice(0, k) for k in want.shape)], want)
        pad = ds.observation_visible_nodes[i].values[n_vis:]
        assert (pad == -1).all()
        assert np.isnan(ds.observation_image_modes[i].values[:, n_vis:]).all()
    # sizes really vary, so the masks are exercised
    assert len(set(ds.n_visible_vertex.values.tolist())) > 1


def test_stacked_index_round_trips(stacked, family_samples):
    import tomllib

    import pandas as pd

    index = pd.read_parquet(stacked / "index.parquet")
    assert len(index) == 6 and set(index.split) == {"train", "val"}
    for _, r in index.iterrows():
        folder = family_samples / r["split"] / r["sample"]
        fam = json.loads((folder / "family.json").read_text())
        assert (int(r["seed"]), int(r["index"])) == (fam["seed"], fam["index"])
        scene = tomllib.loads((folder / "scene.toml").read_text())
        assert r["scene.material.E"] == scene["material"]["E"]
        assert r["scene.excitation.at.2"] == scene["excitation"]["at"][2]
        assert r["scene.material.defects.count"] == len(scene["material"].get("defects", [])) \
            or (pd.isna(r["scene.material.defects.count"]) and not scene["material"].get(
                "defects"))
        ds = xr.open_zarr(stacked / r["store"])
        assert str(ds["sample"].values[r["row"]]) == r["sample"]
        assert r["shard"] == r["row"] // ds.attrs["samples_per_shard"]


def _shard_files(store: Path) -> list[Path]:
    return [p for p in store.rglob("*") if p.is_file() and "c" in p.relative_to(store).parts]


def test_stacked_shards_stay_within_size_and_file_count(stacked, family_samples, tmp_path,
                                                        capsys):
    import zarr

    variables = json.loads((stacked / "dataset.json").read_text())["stores"][
        "tiny_defects/train.zarr"]["variables"]
    biggest = max(int(np.prod(v["shape"][1:])) * np.dtype(v["dtype"]).itemsize
                  for v in variables.values())
    limit = 2 * biggest + 100  # two samples of the largest array per shard
    out = tmp_path / "sharded"
    assert export_main([str(family_samples / "train"), "-o", str(out), "--layout", "stacked",
                        "--shard-size", str(limit)]) == 0
    store = out / "tiny_defects" / "train.zarr"
    meta = json.loads((out / "dataset.json").read_text())["stores"]["tiny_defects/train.zarr"]
    assert meta["samples_per_shard"] == 2 and meta["shards"] == 2
    for name in meta["variables"]:
        shards = list((store / name / "c").iterdir())
        a = zarr.open_array(str(store / name), mode="r")
        assert len(shards) == -(-4 // meta["samples_per_shard"])
        assert all(p.stat().st_size <= limit for p in _shard_files(store / name))
        assert a.shards[0] == meta["samples_per_shard"]
    assert max(len(list(d.iterdir())) for d in out.rglob("*") if d.is_dir()) < 10_000
    ds = xr.open_zarr(store)
    assert ds.sizes["sample"] == 4
    assert (out / "SHA256SUMS").read_text().count("\n") == \
        sum(1 for p in out.rglob("*") if p.is_file()) - 1
    capsys.readouterr()
    assert export_main([str(family_samples / "train"), "-o", str(tmp_path / "tiny-shards"),
                        "--layout", "stacked", "--shard-size", "1kB"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--shard-size" in err and "allowed" in err
    assert not (tmp_path / "tiny-shards").exists()
    assert not [p for p in tmp_path.iterdir() if ".partial-" in p.name]


def test_stacked_refuses_bad_input_and_overwrites_only_its_own(stacked, family_samples,
                                                               tmp_path, capsys):
    src = str(family_samples / "val")
    out = tmp_path / "o"
    for argv in (["-o", str(tmp_path / "x.h5")], ["-o", str(out), "--shard-size", "lots"],
                 ["-o", str(family_samples / "val" / "inside")]):
        capsys.readouterr()
        assert export_main([src, "--layout", "stacked", *argv]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("error:") and "\n" not in err
    assert export_main([src, "-o", str(out), "--layout", "stacked"]) == 0
    assert export_main([src, "-o", str(out), "--layout", "stacked"]) == 2  # exists
    assert export_main([src, "-o", str(out), "--layout", "stacked", "--overwrite"]) == 0
    (out / "notes.txt").write_text("mine")
    assert export_main([src, "-o", str(out), "--layout", "stacked", "--overwrite"]) == 2
    assert (out / "notes.txt").read_text() == "mine"
    user = tmp_path / "user"
    user.mkdir()
    (user / "a.txt").write_text("keep")
    assert export_main([src, "-o", str(user), "--layout", "stacked", "--overwrite"]) == 2
    assert (user / "a.txt").read_text() == "keep"


def test_stacked_streams_one_sample_at_a_time_with_the_same_result(stacked, family_samples,
                                                                     tmp_path, monkeypatch):
    import vvtbench.datasets.export as export

    monkeypatch.setattr(export, "WRITE_BUFFER_BYTES", 1)  # blocks of one sample in one shard
    out = export.pack_stacked(sorted((family_samples / "train").iterdir()), tmp_path / "one")
    a = xr.open_zarr(out / "tiny_defects" / "train.zarr").load()
    b = xr.open_zarr(stacked / "tiny_defects" / "train.zarr").load()
    xr.testing.assert_identical(a, b)


def test_shard_size_units():
    from vvtbench.cli.export import parse_size

    assert parse_size("20GB") == 20 * 10**9 and parse_size("500MiB") == 500 * 2**20
    assert parse_size("4096") == 4096 and parse_size("1.5kB") == 1500
    for bad in ("", "lots", "0", "-5MB", "3XB"):
        with pytest.raises(ExportError, match="--shard-size"):
            parse_size(bad)


def test_verify_checks_a_stacked_export(stacked, tmp_path):
    import shutil

    from vvtbench.cli.verify import verify_path

    assert verify_path(stacked) == []
    copy = tmp_path / "copy"
    shutil.copytree(stacked, copy)
    shard = max((f for f in copy.rglob("*") if f.is_file() and "/c/" in f.as_posix()),
                key=lambda f: f.stat().st_size)
    data = bytearray(shard.read_bytes())
    data[len(data) // 2] ^= 0xFF
    shard.write_bytes(bytes(data))
    problems = verify_path(copy)
    assert problems and any(shard.name in p for p in problems)
