"""The dataset card (README.md) and the Croissant 1.0 JSON-LD description written beside a
dataset packed by :func:`vvtbench.export.pack`."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from ._version import __version__
from .dataset import sha256_file
from .packed import FORMAT, FORMAT_VERSION

__all__ = ["LICENCE", "LICENSE_URL", "croissant", "dataset_card", "sample_revision"]

LICENSE_URL = "https://creativecommons.org/licenses/by/4.0/"
LICENCE = """\
* Generated data (videos, ground truth): CC BY 4.0, produced by vvtbench {version} (MIT).
* Stanford bunny (scene `bunny_defect`): from the Stanford 3D Scanning Repository
  (Stanford University Computer Graphics Laboratory, http://graphics.stanford.edu/data/3Dscanrep/),
  as shipped in pymeshlab's test data (`pymeshlab/tests/sample_meshes/bunny.obj`). The
  repository allows use for research with acknowledgement; please credit it, and do not use
  the bunny commercially without permission.
* All other geometry is procedural (boxes, drum heads).
"""


def sample_revision(sample: Path) -> str:
    """First 16 hex digits of the sha256 of the sample's manifest.json."""
    return hashlib.sha256((sample / "manifest.json").read_bytes()).hexdigest()[:16]


def dataset_card(samples: list[Path], names: list[str], fmt: str, source: str) -> str:
    rows = []
    for s, n in zip(samples, names, strict=True):
        t = json.loads((s / "truth.json").read_text())
        v = t["video"]
        rows.append(f"| {n} | {t['scene']} | {t['seed']} | {v['frames']} | {v['fps']:g} | "
                    f"{v['height']}x{v['width']} | {v['bit_depth']} | {sample_revision(s)} |")
    table = "\n".join(rows)
    return f"""# vvtbench dataset

Packed by vvtbench {__version__} from `{source}` ({len(samples)} samples, format `{fmt}`,
layout version {FORMAT_VERSION}). A Croissant (JSON-LD) description is beside this card.

## Samples

| name | scene | seed | frames | FPS | H x W | bits | revision |
|---|---|---|---|---|---|---|---|
{table}

`revision` = first 16 hex digits of the sha256 of the sample's manifest.json (which holds the
sha256 of every file of the sample folder; every file was checked against it when packing).

## Schema

```
/                            attrs: format, format_version, vvtbench, samples (JSON), README
samples/<name>/              attrs (JSON strings): scene_toml (text), truth, camera, manifest,
                             truth_arrays, extracted; seed (int), sample_revision
                             coords: time (s), row, col (px), mode, voxel_x/y/z (m, centres)
samples/<name>/video         (time, row, col) uint16 DN (8-bit consumer videos: uint8)
samples/<name>/truth/        the sample's truth.zarr arrays under the same paths: mesh/,
                             material/, voxels/, modes/, observation/, image/, transient/
samples/<name>/extracted/<i> extracted modes (if any): shapes (extracted_mode, row, col,
                             component), frequencies_hz, damping, ...; power (frequency, Hz)
```

Every array has named dimensions and a `units` attribute where it has a unit. Units and
conventions of every truth array: vvtbench docs/dataset.md (SI units, pixels with (0, 0) at
the centre of the top-left pixel, P = K[R|t]).

## Loading

```python
from vvtbench.packed import open_dataset
ds = open_dataset(PATH)
s = ds[ds.names[0]]                  # the interface of vvtbench.dataset.Sample
s.scene, s.camera, s.info, s.read_frames(0, 10), s["modes/frequencies_hz"]
s.extracted_modes()                  # list of vvtbench.modes.ModeSet
import xarray as xr                  # zarr: engine="zarr"; HDF5: engine="h5netcdf"
tree = xr.open_datatree(PATH, engine="zarr")
tree["samples/<name>"].ds.video      # dims (time, row, col), coords in s and px
```

## Generator

vvtbench {__version__}; each sample's resolved scene (with its seed) is in `scene_toml`;
regenerate with `vvtbench generate scene.toml`. Rendering is deterministic per seed on one
machine (see docs/dataset.md, "Reproducible").

## Licence

{LICENCE.format(version=__version__)}"""


def croissant(name: str, out: Path, fmt: str, partial: Path, names: list[str],
              source: str) -> dict:
    """A Croissant 1.0 JSON-LD description of the dataset written at ``partial`` (to be
    renamed ``out``)."""
    ctx = {
        "@language": "en", "@vocab": "https://schema.org/", "sc": "https://schema.org/",
        "cr": "http://mlcommons.org/croissant/", "rai": "http://mlcommons.org/croissant/RAI/",
        "dct": "http://purl.org/dc/terms/", "citeAs": "cr:citeAs", "column": "cr:column",
        "conformsTo": "dct:conformsTo", "data": {"@id": "cr:data", "@type": "@json"},
        "dataType": {"@id": "cr:dataType", "@type": "@vocab"}, "examples":
        {"@id": "cr:examples", "@type": "@json"}, "extract": "cr:extract", "field": "cr:field",
        "fileProperty": "cr:fileProperty", "fileObject": "cr:fileObject",
        "fileSet": "cr:fileSet", "format": "cr:format", "includes": "cr:includes",
        "isLiveDataset": "cr:isLiveDataset", "jsonPath": "cr:jsonPath", "key": "cr:key",
        "md5": "cr:md5", "parentField": "cr:parentField", "path": "cr:path",
        "recordSet": "cr:recordSet", "references": "cr:references", "regex": "cr:regex",
        "repeated": "cr:repeated", "replace": "cr:replace", "samplingRate": "cr:samplingRate",
        "separator": "cr:separator", "source": "cr:source", "subField": "cr:subField",
        "transform": "cr:transform",
    }
    if fmt == "zarr":
        meta = partial / "zarr.json"
        dist: list[dict] = [
            {"@type": "cr:FileObject", "@id": "zarr-metadata", "name": "zarr-metadata",
             "description": "root metadata of the Zarr v3 store (consolidated: it lists every "
                            "array, its dimension names and attributes)",
             "contentUrl": "zarr.json", "encodingFormat": "application/json",
             "sha256": sha256_file(meta)},
            {"@type": "cr:FileSet", "@id": "zarr-store", "name": "zarr-store",
             "description": "every group, array and chunk of the Zarr v3 store",
             "encodingFormat": "application/x-zarr", "includes": "samples/**"},
        ]
        src = {"fileSet": {"@id": "zarr-store"}}
    else:
        dist = [{"@type": "cr:FileObject", "@id": out.name, "name": out.name,
                 "description": "HDF5 file (netCDF-4 style dimension scales)",
                 "contentUrl": out.name, "encodingFormat": "application/x-hdf5",
                 "sha256": sha256_file(partial)}]
        src = {"fileObject": {"@id": out.name}}

    def field(fid: str, path: str, dtype: str, desc: str) -> dict:
        return {"@type": "cr:Field", "@id": f"samples/{fid}", "name": fid,
                "description": desc, "dataType": dtype,
                "source": {**src, "extract": {"column": path}}}

    fields = [
        field("name", "samples/<name>", "sc:Text", "sample name (group under samples/)"),
        field("video", "samples/<name>/video", "sc:Integer",
              "(time, row, col) uint16 video frames in DN"),
        field("scene_toml", "samples/<name>@scene_toml", "sc:Text",
              "the resolved scene (TOML) the sample was generated from"),
        field("frequencies_hz", "samples/<name>/truth/modes/frequencies_hz", "sc:Float",
              "natural frequencies (Hz) of the simulated modes"),
        field("image_modes", "samples/<name>/truth/image/modes", "sc:Float",
              "(mode, row, col, uv) true image-space modes"),
        field("stiffness", "samples/<name>/truth/material/stiffness", "sc:Float",
              "Young's modulus per element (Pa; drums: tension N/m)"),
        field("density", "samples/<name>/truth/material/density", "sc:Float",
              "density per element (kg/m3; drums kg/m2)"),
        field("points", "samples/<name>/truth/mesh/points", "sc:Float",
              "mesh node coordinates (m)"),
    ]
    return {
        "@context": ctx,
        "@type": "sc:Dataset",
        "name": name,
        "description": (f"vvtbench visual vibration tomography dataset: {len(names)} "
                        "simulated videos of vibrating objects with their ground truth "
                        f"(mesh, material, modes, camera), packed from {source}."),
        "conformsTo": "http://mlcommons.org/croissant/1.0",
        "license": LICENSE_URL,
        "url": "https://github.com/vvtbench/vvtbench",
        "version": f"{FORMAT_VERSION}.0.0",
        "creator": {"@type": "sc:Organization", "name": "vvtbench"},
        "keywords": ["visual vibration tomography", "modal analysis", "video"],
        "vvtbench:format": FORMAT,
        "vvtbench:samples": names,
        "distribution": dist,
        "recordSet": [{"@type": "cr:RecordSet", "@id": "samples", "name": "samples",
                       "description": "one record per sample (group samples/<name>)",
                       "field": fields}],
    }
