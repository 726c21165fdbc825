"""Croissant 1.1 JSON-LD descriptions of exported datasets, one context for both layouts.

:func:`samples_croissant` describes the per-sample layout (:func:`vvtbench.datasets.export.pack`):
the
store's files with their sha256, two record sets mlcroissant reads without the store (one
record per sample, one per view of a sample, with its camera) and two that name the arrays in
the store (the sample's, and view ``i``'s when a sample has several views).

:func:`stacked_croissant` describes a stacked export
(:func:`vvtbench.datasets.export.pack_stacked`). Its file lists every file of the dataset
(``FileObject`` with sha256 for the index, the card and each store's consolidated metadata;
``FileSet`` for each store's chunks), the instance index as a record set (one field per
column, with its data type) and the responsible-AI properties (``rai:``): synthetic data
from a physics simulation, no people or personal data, the licence, provenance (vvtbench
version, the source suite or folder, the family files), intended uses and limitations.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from .._version import __version__
from ..samples.reader import sha256_file
from .card import LICENSE_URL, sample_revision
from .packed import FORMAT, FORMAT_VERSION

__all__ = ["CONFORMS_TO", "CONTEXT", "samples_croissant", "stacked_croissant"]

CONFORMS_TO = "http://mlcommons.org/croissant/1.1"

#: The JSON-LD context of Croissant 1.1 (the specification's example context).
CONTEXT: dict[str, Any] = {
    "@language": "en", "@vocab": "https://schema.org/", "sc": "https://schema.org/",
    "cr": "http://mlcommons.org/croissant/", "rai": "http://mlcommons.org/croissant/RAI/",
    "dct": "http://purl.org/dc/terms/", "prov": "http://www.w3.org/ns/prov#",
    "arrayShape": "cr:arrayShape", "citeAs": "cr:citeAs", "column": "cr:column",
    "conformsTo": "dct:conformsTo", "containedIn": "cr:containedIn",
    "equivalentProperty": "cr:equivalentProperty", "isArray": "cr:isArray",
    "data": {"@id": "cr:data", "@type": "@json"},
    "dataType": {"@id": "cr:dataType", "@type": "@vocab"},
    "examples": {"@id": "cr:examples", "@type": "@json"}, "extract": "cr:extract",
    "field": "cr:field", "fileProperty": "cr:fileProperty", "fileObject": "cr:fileObject",
    "fileSet": "cr:fileSet", "format": "cr:format", "includes": "cr:includes",
    "isLiveDataset": "cr:isLiveDataset", "jsonPath": "cr:jsonPath", "key": "cr:key",
    "md5": "cr:md5", "parentField": "cr:parentField", "path": "cr:path",
    "recordSet": "cr:recordSet", "references": "cr:references", "regex": "cr:regex",
    "repeated": "cr:repeated", "replace": "cr:replace", "samplingRate": "cr:samplingRate",
    "separator": "cr:separator", "source": "cr:source", "subField": "cr:subField",
    "transform": "cr:transform",
}

CITE_AS = ("Feng, Ogren, Daraio, Bouman. Visual Vibration Tomography: Estimating Interior "
           "Material Properties from Monocular Video. CVPR 2022.")

_DATA_TYPES = {"b": "sc:Boolean", "i": "sc:Integer", "u": "sc:Integer", "f": "sc:Float"}


def _data_type(dtype) -> str:
    return _DATA_TYPES.get(getattr(dtype, "kind", "O"), "sc:Text")


def _field_id(column: str) -> str:
    return "instances/" + "".join(c if c.isalnum() or c in "._-" else "_" for c in column)


def stacked_croissant(name: str, root: Path, index, stores: dict[str, dict],
                      source: str) -> dict[str, Any]:
    """The Croissant 1.1 JSON-LD of the stacked export written at ``root``.

    Parameters
    ----------
    name : the dataset's name (the output folder's name).
    root : the folder holding ``index.parquet``, ``README.md`` and the stores.
    index : the instance index (pandas DataFrame) as written to ``index.parquet``.
    stores : ``{relative store path: {family, split, samples, variables, ...}}``.
    source : the folder or suite the samples came from (provenance).
    """
    dist: list[dict[str, Any]] = [
        {"@type": "cr:FileObject", "@id": "index.parquet", "name": "index.parquet",
         "description": "one row per instance: ids, seed, store, row, shard, drawn scene "
                        "parameters", "contentUrl": "index.parquet",
         "encodingFormat": "application/x-parquet", "sha256": sha256_file(root / "index.parquet")},
        {"@type": "cr:FileObject", "@id": "README.md", "name": "README.md",
         "description": "dataset card", "contentUrl": "README.md",
         "encodingFormat": "text/markdown", "sha256": sha256_file(root / "README.md")},
    ]
    for rel, info in stores.items():
        variables = ", ".join(f"{v} ({', '.join(d['dims'])})"
                              for v, d in info["variables"].items())
        dist.append({"@type": "cr:FileObject", "@id": f"{rel}/zarr.json",
                     "name": f"{rel}/zarr.json",
                     "description": f"consolidated metadata of the Zarr v3 store of "
                                    f"{info['family']}/{info['split']}",
                     "contentUrl": f"{rel}/zarr.json", "encodingFormat": "application/json",
                     "sha256": sha256_file(root / rel / "zarr.json")})
        dist.append({"@type": "cr:FileSet", "@id": rel, "name": rel,
                     "description": f"Zarr v3 store, {info['samples']} instances of "
                                    f"{info['family']}/{info['split']} stacked on 'sample', "
                                    f"{info['shards']} shard(s) per array; variables: "
                                    f"{variables}; sha256 of every file: SHA256SUMS",
                     "containedIn": {"@id": f"{rel}/zarr.json"},
                     "encodingFormat": "application/x-zarr", "includes": f"{rel}/**"})
    fields = [{"@type": "cr:Field", "@id": _field_id(c), "name": c,
               "description": _describe(c), "dataType": _data_type(index[c].dtype),
               "source": {"fileObject": {"@id": "index.parquet"}, "extract": {"column": c}}}
              for c in index.columns]
    families = sorted({info["family"] for info in stores.values()})
    return {
        "@context": CONTEXT,
        "@type": "sc:Dataset",
        "name": name,
        "description": (f"vvtbench visual vibration tomography dataset: {len(index)} simulated "
                        "vibrating objects (families: " + ", ".join(families) + ") with their "
                        "ground truth (mesh, Young's modulus and density per element and voxel, "
                        "modes, their image-space projection), stacked per family and split."),
        "conformsTo": CONFORMS_TO,
        "license": LICENSE_URL,
        "url": "https://github.com/vvtbench/vvtbench",
        "version": "1.0.0",
        "creator": {"@type": "sc:Organization", "name": "vvtbench"},
        "keywords": ["visual vibration tomography", "modal analysis", "inverse problems",
                     "synthetic data"],
        "citeAs": CITE_AS,
        "distribution": dist,
        "recordSet": [{"@type": "cr:RecordSet", "@id": "instances", "name": "instances",
                       "description": "one record per instance (index.parquet); the arrays of "
                                      "an instance are at row 'row' of the store 'store'",
                       "field": fields}],
        "rai:dataCollection": (
            "Synthetic: every instance is drawn by seed from a scene family (random geometry, "
            "defects, material ratios, excitation, viewpoint, sensor noise) and simulated with "
            "the finite element method; no measurement, no scraping."),
        "rai:dataCollectionType": ["Simulation"],
        "rai:personalSensitiveInformation": "None: no people and no personal data.",
        "rai:dataUseCases": (
            "Benchmarking and training methods that recover Young's modulus and density inside "
            "an object from its surface vibration modes (visual vibration tomography), modal "
            "extraction and inverse finite-element problems."),
        "rai:dataLimitations": (
            "Linear elasticity, small displacements, isotropic materials, idealised boundary "
            "conditions and rendered (not filmed) observations: results do not transfer to "
            "real objects without validation on real video. Parameter ranges are those of the "
            "family files."),
        "rai:dataBiases": ("Shapes and materials cover only the scene families listed; "
                           "distributions are chosen by hand, not measured."),
        "rai:hasSyntheticData": True,
        "prov:wasGeneratedBy": {
            "@type": "prov:Activity",
            "name": f"vvtbench {__version__} export of {source}",
            "description": (f"generated and packed by vvtbench {__version__} from {source}; "
                            "each instance's family, split, index, seed and resolved scene "
                            "are in index.parquet"),
        },
        "vvtbench:layout": "stacked",
        "vvtbench:version": __version__,
        "vvtbench:source": source,
    }


def _describe(column: str) -> str:
    fixed = {
        "sample": "instance id (scene name), the 'sample' coordinate of its store",
        "family": "scene family", "split": "split (train, val, test)",
        "index": "instance index within its split", "seed": "the instance's recorded seed",
        "sample_revision": "first 16 hex digits of the sha256 of the instance's manifest.json",
        "store": "Zarr store (relative path) holding the instance",
        "row": "position of the instance on the store's 'sample' dimension",
        "shard": "shard file (along 'sample') of every array of the store holding the instance",
    }
    if column in fixed:
        return fixed[column]
    return f"drawn scene parameter {column[len('scene.'):]} (resolved scene.toml)"


def _record(set_id: str, fields: list[tuple[str, str, str]], rows: list[dict],
            description: str) -> dict[str, Any]:
    """A record set whose records are inline (``data``): mlcroissant reads them as they are."""
    return {"@type": "cr:RecordSet", "@id": set_id, "name": set_id, "description": description,
            "field": [{"@type": "cr:Field", "@id": f"{set_id}/{n}", "name": n,
                       "description": d, "dataType": t} for n, t, d in fields],
            "data": [{f"{set_id}/{k}": v for k, v in row.items()} for row in rows]}


#: Arrays of a packed sample named in the Croissant file: (field, path below the sample group,
#: data type, number of dimensions, description).
SAMPLE_FIELDS = (
    ("video", "video", "sc:Integer", 3, "(time, row, col) video frames in DN (uint16; uint8 "
                                        "for 8-bit consumer video)"),
    ("frequencies_hz", "truth/modes/frequencies_hz", "sc:Float", 1,
     "natural frequencies (Hz) of the simulated modes"),
    ("image_modes", "truth/image/modes", "sc:Float", 4, "(mode, row, col, uv) true image-space "
                                                        "modes of view 0"),
    ("stiffness", "truth/material/stiffness", "sc:Float", 1,
     "Young's modulus per element (Pa; drums: tension N/m)"),
    ("density", "truth/material/density", "sc:Float", 1,
     "density per element (kg/m3; drums kg/m2)"),
    ("points", "truth/mesh/points", "sc:Float", 2, "mesh node coordinates (m)"),
)
#: Arrays of view i >= 1 of a multi-view sample (below ``samples/<name>/views/<i>/``).
VIEW_FIELDS = (
    ("video", "video", "sc:Integer", 3, "(time, row, col) video frames of the view in DN; "
                                        "frame k filmed at time[k] + time_offset_s"),
    ("image_modes", "truth/image/modes", "sc:Float", 4,
     "(mode, row, col, uv) true image-space modes seen by the view"),
    ("rest_uv", "truth/observation/rest_uv", "sc:Float", 2,
     "(surface_node, uv) pixel position of every surface node at rest in the view"),
    ("visible", "truth/observation/visible", "sc:Boolean", 1,
     "(surface_node) whether the view sees the node"),
    ("jacobian", "truth/observation/jacobian", "sc:Float", 3,
     "(visible_node, uv, xyz) d(pixel)/d(position) of the nodes the view sees (px/m)"),
)


def samples_croissant(name: str, out: Path, fmt: str, partial: Path, samples: list[Path],
                      names: list[str], source: str) -> dict[str, Any]:
    """The Croissant 1.1 JSON-LD of the per-sample export written at ``partial`` (to be renamed
    ``out``) from the sample folders ``samples`` packed as ``names``."""
    if fmt == "zarr":
        dist: list[dict[str, Any]] = [
            {"@type": "cr:FileObject", "@id": "zarr-metadata", "name": "zarr-metadata",
             "description": "root metadata of the Zarr v3 store (consolidated: it lists every "
                            "array, its dimension names and attributes)",
             "contentUrl": "zarr.json", "encodingFormat": "application/json",
             "sha256": sha256_file(partial / "zarr.json")},
            {"@type": "cr:FileSet", "@id": "zarr-store", "name": "zarr-store",
             "description": "every group, array and chunk of the Zarr v3 store; sha256 of "
                            "every file: SHA256SUMS", "containedIn": {"@id": "zarr-metadata"},
             "encodingFormat": "application/x-zarr", "includes": "samples/**"},
        ]
        src: dict[str, Any] = {"fileSet": {"@id": "zarr-store"}}
    else:
        dist = [{"@type": "cr:FileObject", "@id": out.name, "name": out.name,
                 "description": "HDF5 file (netCDF-4 style dimension scales)",
                 "contentUrl": out.name, "encodingFormat": "application/x-hdf5",
                 "sha256": sha256_file(partial)}]
        src = {"fileObject": {"@id": out.name}}
    sample_rows, view_rows = [], []
    for folder, packed_name in zip(samples, names, strict=True):
        info = json.loads((folder / "truth.json").read_text())
        video = info["video"]
        views = info.get("views") if isinstance(info.get("views"), list) else None
        entries = views or [{"camera": "camera.json", "height": video["height"],
                             "width": video["width"], "time_offset_s": 0.0}]
        sample_rows.append({"name": packed_name, "scene": str(info["scene"]),
                            "seed": int(info["seed"]), "frames": int(video["frames"]),
                            "fps": float(video["fps"]), "bit_depth": int(video["bit_depth"]),
                            "views": len(entries),
                            "sample_revision": sample_revision(folder)})
        for i, entry in enumerate(entries):
            view_rows.append({"sample": packed_name, "view": i,
                              "height": int(entry["height"]), "width": int(entry["width"]),
                              "time_offset_s": float(entry.get("time_offset_s", 0.0)),
                              "camera": (folder / entry["camera"]).read_text()})
    record_sets = [
        _record("sample_index", [
            ("name", "sc:Text", "sample name (group samples/<name>)"),
            ("scene", "sc:Text", "scene name"),
            ("seed", "sc:Integer", "the sample's recorded seed"),
            ("frames", "sc:Integer", "video frames of every view"),
            ("fps", "sc:Float", "frame rate (Hz)"),
            ("bit_depth", "sc:Integer", "bits per pixel of the sensor"),
            ("views", "sc:Integer", "synchronised views (cameras) of the simulation"),
            ("sample_revision", "sc:Text", "first 16 hex digits of the sha256 of the "
                                           "sample's manifest.json")],
            sample_rows, "one record per sample (inline: read without the store)"),
        _record("view_index", [
            ("sample", "sc:Text", "sample name"),
            ("view", "sc:Integer", "view index (0: the sample's own video and camera)"),
            ("height", "sc:Integer", "frame height (px)"),
            ("width", "sc:Integer", "frame width (px)"),
            ("time_offset_s", "sc:Float", "time (s) by which the view films later than view 0"),
            ("camera", "sc:Text", "the view's camera.json (pinhole K, R, t; OpenCV "
                                  "convention)")],
            view_rows, "one record per view of every sample (inline)"),
    ]

    def array_field(set_id: str, fid: str, path: str, dtype: str, ndim: int,
                    desc: str) -> dict[str, Any]:
        return {"@type": "cr:Field", "@id": f"{set_id}/{fid}", "name": fid,
                "description": desc, "dataType": dtype, "isArray": True,
                "arrayShape": ",".join(["-1"] * ndim),
                "source": {**src, "extract": {"column": path}}}

    record_sets.append({
        "@type": "cr:RecordSet", "@id": "samples", "name": "samples",
        "description": "the arrays of one sample (group samples/<name>; view 0)",
        "field": [{"@type": "cr:Field", "@id": "samples/name", "name": "name",
                   "description": "sample name (group under samples/)", "dataType": "sc:Text",
                   "source": {**src, "extract": {"column": "samples/<name>"}}},
                  {"@type": "cr:Field", "@id": "samples/scene_toml", "name": "scene_toml",
                   "description": "the resolved scene (TOML) the sample was generated from",
                   "dataType": "sc:Text",
                   "source": {**src, "extract": {"column": "samples/<name>@scene_toml"}}},
                  *(array_field("samples", f, f"samples/<name>/{p}", t, n, d)
                    for f, p, t, n, d in SAMPLE_FIELDS)]})
    if any(row["views"] > 1 for row in sample_rows):
        record_sets.append({
            "@type": "cr:RecordSet", "@id": "views", "name": "views",
            "description": "the arrays of view i >= 1 of a multi-view sample (group "
                           "samples/<name>/views/<i>; its camera: attribute camera)",
            "field": [{"@type": "cr:Field", "@id": "views/camera", "name": "camera",
                       "description": "the view's camera.json", "dataType": "sc:Text",
                       "source": {**src, "extract": {
                           "column": "samples/<name>/views/<i>@camera"}}},
                      *(array_field("views", f, f"samples/<name>/views/<i>/{p}", t, n, d)
                        for f, p, t, n, d in VIEW_FIELDS)]})
    n_views = sum(row["views"] for row in sample_rows)
    return {
        "@context": CONTEXT,
        "@type": "sc:Dataset",
        "name": name,
        "description": (f"vvtbench visual vibration tomography dataset: {len(names)} "
                        f"simulated samples ({n_views} videos of vibrating objects) with their "
                        f"ground truth (mesh, material, modes, cameras), packed from {source}."),
        "conformsTo": CONFORMS_TO,
        "license": LICENSE_URL,
        "url": "https://github.com/vvtbench/vvtbench",
        "version": f"{FORMAT_VERSION}.0.0",
        "creator": {"@type": "sc:Organization", "name": "vvtbench"},
        "keywords": ["visual vibration tomography", "modal analysis", "video"],
        "citeAs": CITE_AS,
        "vvtbench:format": FORMAT,
        "vvtbench:samples": names,
        "vvtbench:version": __version__,
        "distribution": dist,
        "recordSet": record_sets,
    }
