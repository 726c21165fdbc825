"""The dataset cards (README.md) of :func:`vvtbench.datasets.export.pack` and
:func:`vvtbench.datasets.export.pack_stacked` (their Croissant 1.1 files:
:mod:`vvtbench.datasets.croissant`)."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from .._version import __version__
from .packed import FORMAT_VERSION

__all__ = ["LICENCE", "LICENSE_URL", "dataset_card", "sample_revision", "stacked_card"]

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
    """The README.md of a per-sample export (:func:`vvtbench.datasets.export.pack`)."""
    rows, several = [], []
    for s, n in zip(samples, names, strict=True):
        t = json.loads((s / "truth.json").read_text())
        v = t["video"]
        if isinstance(t.get("views"), list) and len(t["views"]) > 1:
            several.append(f"{n} ({len(t['views'])})")
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
{_views_section(several)}
## Loading

```python
from vvtbench.datasets.packed import open_dataset
ds = open_dataset(PATH)
s = ds[ds.names[0]]                  # the interface of vvtbench.samples.reader.Sample
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


def _views_section(several: list[str]) -> str:
    """The card's paragraph on samples filmed by several cameras ("" when none is)."""
    if not several:
        return ""
    return f"""
## Views

Samples filmed by several cameras (views): {", ".join(several)}. View 0 is the sample group
itself; view i >= 1 is `samples/<name>/views/<i>/`: `video` (time, row, col), attributes
`camera` (its camera.json) and `view` (its truth.json views entry, with `time_offset_s`), and
`truth/` with its own observation/, image/, crb/ and modes/crb_* arrays. In Python:
`s.n_views`, `s.view(i)` (the interface of vvtbench.samples.reader.Sample.view).
"""


def _stacked_views(stores: dict[str, dict]) -> str:
    """The stacked card's paragraph on stores with several views ("" when none has)."""
    with_views = [f"`{rel}` ({info['views']})" for rel, info in stores.items()
                  if info.get("views", 1) > 1]
    if not with_views:
        return ""
    return f"""
Views: in {", ".join(with_views)} (the split's largest number of views), the arrays each
camera has of its own (observation_*, image_*, crb_*, modes_crb_*) have a `view` dimension
after `sample` (view 0: the sample's; padded for a sample with fewer views), and
`camera_K`, `camera_R`, `camera_t`, `camera_width`, `camera_height`, `view_time_offset`
(sample, view, ...) hold every view's camera (P = K[R|t]).
"""


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
{_stacked_views(stores)}
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
