"""The dataset cards (README.md) of :func:`vvtbench.export.pack` and
:func:`vvtbench.export.pack_stacked`, and the Croissant 1.0 JSON-LD description of the former
(the stacked layout's Croissant 1.1 file: :mod:`vvtbench.croissant`)."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from ._version import __version__
from .dataset import sha256_file
from .packed import FORMAT, FORMAT_VERSION

__all__ = ["LICENCE", "LICENSE_URL", "croissant", "dataset_card", "sample_revision",
           "stacked_card"]

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


def _human_bytes(n: float) -> str:
    for unit in ("B", "kB", "MB", "GB", "TB"):
        if n < 1000 or unit == "TB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n:.1f} TB"


def stacked_card(index, stores: dict[str, dict], source: str, shard_bytes: int) -> str:
    """The README.md of a stacked export: stores, their variables, the index, loading."""
    store_rows = "\n".join(
        f"| `{rel}` | {info['family']} | {info['split']} | {info['samples']} | "
        f"{info['samples_per_shard']} | {info['shards']} | "
        f"{', '.join(info['varying']) or '-'} |" for rel, info in stores.items())
    var_rows = []
    for rel, info in stores.items():
        for name, v in info["variables"].items():
            var_rows.append(f"| `{rel}` | `{name}` | ({', '.join(v['dims'])}) | "
                            f"{'x'.join(map(str, v['shape']))} | {v['dtype']} | "
                            f"{v['units'] or '-'} |")
    params = [c for c in index.columns if c.startswith("scene.")]
    first = next(iter(stores))
    return f"""# vvtbench dataset (stacked)

Packed by vvtbench {__version__} from `{source}`: {len(index)} instances in {len(stores)}
store(s), one Zarr v3 store per family and split with a `sample` dimension. A Croissant 1.1
description (`croissant.json`), an instance index (`index.parquet`) and the sha256 of every
file (`SHA256SUMS`) are beside this card.

## Stores

| store | family | split | samples | samples per shard | shards | padded dimensions |
|---|---|---|---|---|---|---|
{store_rows}

Shards: every array is chunked one sample per chunk and grouped by the Zarr v3 sharding codec
into shard files of at most {_human_bytes(min(shard_bytes, 2**30))} (uncompressed) each,
so an array folder holds `c/<shard>/...` and no folder more than {10_000 - 1} files.

Sizes that vary between instances of a split (mesh vertices of drums, visible vertices, ...)
are padded to the largest: floats with NaN, integers with -1, booleans with False;
`<dim>_mask` (sample, dim) is True where data is and `n_<dim>` (sample) is the true size.

## Variables

| store | variable | dimensions | shape | dtype | units |
|---|---|---|---|---|---|
{chr(10).join(var_rows)}

Every variable's `truth_path` attribute names the array of the sample's `truth.zarr` it holds;
conventions and units: vvtbench docs/dataset.md. Coordinates on `sample`: the instance id,
`family`, `split`, `index`, `seed` and `sample_revision` (first 16 hex digits of the sha256 of
the sample's manifest.json, checked against every file when packing).

Video and extracted modes are not in this layout (`vvtbench export --layout samples` keeps them).

## Index

`index.parquet`: one row per instance with `sample`, `family`, `split`, `index`, `seed`,
`sample_revision`, `store`, `row` (position on `sample`), `shard` (the shard file holding
it) and the drawn scene parameters ({len(params)} columns `scene.*`, e.g.
{", ".join(f"`{c}`" for c in params[:6])}).

## Loading

```python
import pandas as pd, xarray as xr
index = pd.read_parquet("index.parquet")
ds = xr.open_zarr("{first}")            # one Dataset, dims (sample, ...)
ds.sel(sample=index.sample[0])
```

## Generator

vvtbench {__version__}; each instance is regenerated from its family, split and index (or its
resolved scene, in the index's `scene.*` columns, with its seed).

## Licence

{LICENCE.format(version=__version__)}"""
