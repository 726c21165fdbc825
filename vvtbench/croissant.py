"""Croissant 1.1 JSON-LD description of a stacked export (:func:`vvtbench.export.pack_stacked`).

The file lists every file of the dataset (``FileObject`` with sha256 for the index, the card
and each store's consolidated metadata; ``FileSet`` for each store's chunks), the instance
index as a record set (one field per column, with its data type) and the responsible-AI
properties (``rai:``): synthetic data from a physics simulation, no people or personal data,
the licence, provenance (vvtbench version, the source suite or folder, the family files),
intended uses and limitations.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from ._version import __version__
from .dataset import sha256_file
from .export_card import LICENSE_URL

__all__ = ["CONFORMS_TO", "CONTEXT", "stacked_croissant"]

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
        "citeAs": ("Feng, Ogren, Daraio, Bouman. Visual Vibration Tomography: Estimating "
                   "Interior Material Properties from Monocular Video. CVPR 2022."),
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
