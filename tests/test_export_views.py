"""Exporting samples filmed by several cameras: every view packed in both layouts, read back by
the formats' own libraries (xarray, h5py, zarr) and by PackedSample, equal to the sample
folder's arrays; the per-sample Croissant 1.1 file validated and read by mlcroissant.

Rendering needs headless EGL (Mesa llvmpipe is fine); see tests/test_render.py.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from vvtbench.cli import main as cli_main
from vvtbench.cli.export import main as export_main
from vvtbench.datasets.croissant import CONFORMS_TO, CONTEXT
from vvtbench.datasets.packed import ExportError, open_dataset
from vvtbench.render.camera import Camera
from vvtbench.samples import reader as ds
from vvtbench.samples.generate import generate
from vvtbench.scene.scene import parse_scene

SCENE = {
    "seed": 7,
    "geometry": {"kind": "box", "cells": [2, 2, 2]},
    "excitation": {"kind": "pluck", "at": [0.05, 0.0, 0.05], "displacement": 0.002},
    "simulation": {"n_modes": 4, "duration": 0.006, "fps": 2000.0},
    "camera": {"resolution": [32, 24], "position": [0.16, -0.13, 0.13],
               "look_at": [0.025, 0.025, 0.022], "fov_y_deg": 30.0},
    "render": {"supersample": 1},
}
RIG = {"rig": {"views": 2, "spread_deg": 60.0, "time_offset_s": 0.0005}}
# a second camera of another frame size: its pixel dimensions cannot be the sample's
LISTED = {"views": [{"position": [-0.1, 0.2, 0.12], "resolution": [20, 28]}]}
ENGINES = {"zarr": ("ds.zarr", "zarr"), "hdf5": ("ds.h5", "h5netcdf")}


def _scene(name: str, camera: dict):
    data = json.loads(json.dumps(SCENE))
    data["name"] = name
    data["camera"].update(camera)
    return parse_scene(data, f"{name}.toml")


@pytest.fixture(scope="module")
def samples(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("views")
    generate(_scene("rig", RIG), root, progress=False, preview_frames=0)
    generate(_scene("listed", LISTED), root, progress=False, preview_frames=0)
    return root


@pytest.fixture(scope="module", params=["zarr", "hdf5"])
def packed(request, samples, tmp_path_factory) -> tuple[str, Path]:
    fmt = request.param
    out = tmp_path_factory.mktemp("out") / ENGINES[fmt][0]
    assert export_main([str(samples), "--format", fmt, "-o", str(out)]) == 0
    return fmt, out


def _views(samples: Path, name: str) -> list:
    s = ds.open_sample(samples / name)
    assert s.n_views == 2
    return [s.view(i) for i in range(s.n_views)]


def test_packed_views_read_like_the_folder_views(packed, samples):
    fmt, out = packed
    with open_dataset(out) as d:
        for name in ("rig", "listed"):
            p = d[name]
            assert p.n_views == 2 and p.view(0) is p
            for i, v in enumerate(_views(samples, name)):
                pv = p.view(i)
                assert pv.camera == v.camera and pv.info == v.info
                assert (pv.n_frames, pv.shape) == (v.n_frames, v.shape)
                np.testing.assert_array_equal(pv.read_frames(), v.read_frames())
                for array in pv.truth_arrays:
                    a, b = pv[array], v[array]
                    assert a.dtype == b.dtype, array
                    np.testing.assert_array_equal(a, b, err_msg=f"{name} view {i}: {array}")
                assert "observation/jacobian" in pv.truth_arrays
            assert not np.array_equal(p.view(1)["observation/rest_uv"], p["observation/rest_uv"])
            assert f"{name!r} view 1:" in repr(p.view(1)) and "view" not in repr(p)
            with pytest.raises(ExportError, match="no view 2; the sample holds views 0..1"):
                p.view(2)
        # every truth.zarr array of the folder under its own name, views/<i>/... included
        folder = ds.open_sample(samples / "listed")
        names = [n for n in d["listed"].truth_arrays if n.startswith("views/1/")]
        assert "views/1/image/modes" in names
        for n in names:
            np.testing.assert_array_equal(d["listed"][n], folder[n])


def test_xarray_reads_every_view_with_named_dimensions(packed, samples):
    fmt, out = packed
    tree = xr.open_datatree(out, engine=ENGINES[fmt][1])
    rig = _views(samples, "rig")
    node = tree["samples/rig/views/1"].ds
    assert node.video.dims == ("time", "row", "col") and node.video.attrs["units"] == "DN"
    np.testing.assert_array_equal(node.video.values, rig[1].read_frames())
    assert node.attrs["time_offset_s"] == pytest.approx(0.0005)
    assert Camera.from_dict(json.loads(node.attrs["camera"])) == rig[1].camera
    obs = tree["samples/rig/views/1/truth/observation"].ds
    assert obs.jacobian.dims == ("visible_node", "uv", "xyz")
    assert obs.jacobian.attrs["units"] == "px/m"
    np.testing.assert_array_equal(obs.jacobian.values, rig[1]["observation/jacobian"])
    assert obs.sizes["visible_node"] == len(rig[1]["observation/visible_nodes"])
    # a view of another frame size has its own pixel coordinates
    listed = _views(samples, "listed")
    H, W = listed[1].shape
    assert (H, W) != listed[0].shape
    other = tree["samples/listed/views/1"].ds
    assert other.video.dims == ("time", "view_row", "view_col")
    np.testing.assert_array_equal(other["view_row"].values, np.arange(H))
    np.testing.assert_array_equal(other.video.values, listed[1].read_frames())
    image = tree["samples/listed/views/1/truth/image"].ds
    assert image["modes"].dims == ("mode", "view_row", "view_col", "uv")
    np.testing.assert_array_equal(image["modes"].values, listed[1]["image/modes"])
    np.testing.assert_array_equal(tree["samples/listed"].ds.video.values,
                                  listed[0].read_frames())


def test_h5py_and_zarr_read_the_views_as_written(packed, samples):
    fmt, out = packed
    v = _views(samples, "listed")[1]
    if fmt == "hdf5":
        import h5py

        with h5py.File(out, "r") as f:
            g = f["samples/listed/views/1"]
            np.testing.assert_array_equal(g["video"][...], v.read_frames())
            np.testing.assert_array_equal(g["truth/image/depth"][...], v["image/depth"])
            camera = samples / "listed" / "views" / "1" / "camera.json"
            assert json.loads(g.attrs["camera"]) == json.loads(camera.read_text())
            assert g["video"].dims[1][0].name.endswith("/view_row")
    else:
        import zarr

        g = zarr.open_group(str(out), mode="r")["samples/listed/views/1"]
        np.testing.assert_array_equal(g["video"][...], v.read_frames())
        np.testing.assert_array_equal(g["truth/crb/std_px"][...], v["crb/std_px"])
        assert g["video"].metadata.dimension_names == ("time", "view_row", "view_col")
        assert json.loads(g.attrs["view"])["folder"] == "views/1"


def test_verify_checks_the_views(packed, capsys):
    fmt, out = packed
    assert cli_main(["verify", str(out)]) == 0
    capsys.readouterr()


# --------------------------------------------------------------------------- Croissant
def _croissant_path(fmt: str, out: Path) -> Path:
    return out / "croissant.json" if fmt == "zarr" else Path(f"{out}.croissant.json")


def test_mlcroissant_validates_and_reads_samples_and_views(packed, samples, caplog):
    mlc = pytest.importorskip("mlcroissant")
    fmt, out = packed
    path = _croissant_path(fmt, out)
    meta = json.loads(path.read_text())
    assert meta["@context"] == CONTEXT and meta["conformsTo"] == CONFORMS_TO
    with caplog.at_level(logging.WARNING):
        dataset = mlc.Dataset(jsonld=str(path))
    assert not [r for r in caplog.records if "@context" in r.getMessage()]

    def text(value):
        return value.decode() if isinstance(value, bytes) else value

    records = {text(r["sample_index/name"]): r for r in dataset.records("sample_index")}
    assert sorted(records) == ["listed", "rig"]
    for name, rec in records.items():
        info = json.loads((samples / name / "truth.json").read_text())
        assert int(rec["sample_index/seed"]) == info["seed"] == 7
        assert int(rec["sample_index/frames"]) == info["video"]["frames"]
        assert int(rec["sample_index/views"]) == 2
    views = list(dataset.records("view_index"))
    assert sorted((text(r["view_index/sample"]), int(r["view_index/view"])) for r in views) == [
        ("listed", 0), ("listed", 1), ("rig", 0), ("rig", 1)]
    for r in views:
        v = _views(samples, text(r["view_index/sample"]))[int(r["view_index/view"])]
        assert Camera.from_dict(json.loads(text(r["view_index/camera"]))) == v.camera
        assert (int(r["view_index/height"]), int(r["view_index/width"])) == v.shape
    sets = {rs["name"]: rs for rs in meta["recordSet"]}
    fields = {f["name"]: f for f in sets["views"]["field"]}
    assert {"video", "camera", "image_modes", "jacobian", "rest_uv", "visible"} <= set(fields)
    assert fields["video"]["source"]["extract"]["column"] == "samples/<name>/views/<i>/video"
    assert fields["jacobian"]["isArray"] and fields["jacobian"]["arrayShape"] == "-1,-1,-1"
    assert {"video", "frequencies_hz", "stiffness", "density"} <= {
        f["name"] for f in sets["samples"]["field"]}


# --------------------------------------------------------------------------- stacked layout
@pytest.fixture(scope="module")
def stacked(samples, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("stacked") / "views"
    assert export_main([str(samples), "-o", str(out), "--layout", "stacked"]) == 0
    return out


def test_stacked_views_share_a_view_dimension_with_masks(stacked, samples):
    store = xr.open_zarr(stacked / "samples" / "all.zarr")
    assert list(store["sample"].values) == ["listed", "rig"]
    jac = store["observation_jacobian"]
    assert jac.dims == ("sample", "view", "visible_vertex", "uv", "component")
    assert store["image_modes"].dims == ("sample", "view", "mode", "row", "col", "uv")
    assert store["modes_frequencies_hz"].dims == ("sample", "mode")  # shared by the views
    assert store["visible_vertex_mask"].dims == ("sample", "view", "visible_vertex")
    for k, name in enumerate(["listed", "rig"]):
        for v, view in enumerate(_views(samples, name)):
            n = len(view["observation/visible_nodes"])
            assert int(store["n_visible_vertex"][k, v]) == n
            mask = store["visible_vertex_mask"][k, v].values
            assert mask[:n].all() and not mask[n:].any()
            np.testing.assert_array_equal(jac[k, v].values[:n], view["observation/jacobian"])
            assert np.isnan(jac[k, v].values[n:]).all()
            H, W = view.shape
            np.testing.assert_array_equal(store["image_modes"][k, v].values[:, :H, :W],
                                          view["image/modes"])
            np.testing.assert_array_equal(store["crb_std_px"][k, v].values[
                tuple(slice(0, m) for m in view["crb/std_px"].shape)], view["crb/std_px"])
            assert int(store["n_row"][k, v]) == H and int(store["n_col"][k, v]) == W
            camera = view.camera
            np.testing.assert_array_equal(store["camera_K"][k, v].values, camera.K)
            np.testing.assert_array_equal(store["camera_R"][k, v].values, camera.R)
            np.testing.assert_array_equal(store["camera_t"][k, v].values, np.ravel(camera.t))
            assert (int(store["camera_height"][k, v]), int(store["camera_width"][k, v])) == (
                H, W)
        np.testing.assert_array_equal(store["modes_frequencies_hz"][k].values,
                                      _views(samples, name)[0]["modes/frequencies_hz"])
    assert store["view_time_offset"].values.tolist() == [[0.0, 0.0], [0.0, 0.0005]]
    assert cli_main(["verify", str(stacked)]) == 0


def test_stacked_croissant_names_the_view_dimension(stacked, caplog):
    mlc = pytest.importorskip("mlcroissant")
    meta = json.loads((stacked / "croissant.json").read_text())
    (fileset,) = [d for d in meta["distribution"] if d["@type"] == "cr:FileSet"]
    assert "observation_jacobian (sample, view, visible_vertex, uv, component)" in \
        fileset["description"]
    assert "camera_K (sample, view, K_row, K_col)" in fileset["description"]
    with caplog.at_level(logging.WARNING):
        dataset = mlc.Dataset(jsonld=str(stacked / "croissant.json"))
    assert not [r for r in caplog.records if "@context" in r.getMessage()]
    assert len(list(dataset.records(record_set="instances"))) == 2


def test_verify_reads_the_video_of_every_view(packed, monkeypatch):
    from vvtbench.cli import verify

    seen = []
    real = verify._video_problems

    def spy(s, where):
        seen.append(where.rsplit("samples/", 1)[-1])
        yield from real(s, where)

    monkeypatch.setattr(verify, "_video_problems", spy)
    assert cli_main(["verify", str(packed[1])]) == 0
    assert {"rig", "rig/views/1", "listed", "listed/views/1"} <= set(seen)


def test_observe_a_packed_sample_with_its_views_as_the_folder(packed, samples):
    from vvtbench.observe import observe

    fmt, out = packed
    folder, _ = observe(samples / "rig", n_modes=3, views=2, inference_shape=[2, 2, 2])
    entry = open_dataset(out)["rig"]
    got, _ = observe(entry, n_modes=3, views=2, inference_shape=[2, 2, 2])
    assert got.P.shape == folder.P.shape and got.P.shape[0] > 0
    np.testing.assert_allclose(got.P.toarray(), folder.P.toarray())
    np.testing.assert_allclose(got.gamma, folder.gamma)
