"""Pack generated samples into one portable dataset file: Zarr (v3) or HDF5.

Layout (the same in both formats; docs/results.md, "Exported datasets")::

    /                      attrs: format, vvtbench, created_from, samples, licence, README
    samples/<name>/        attrs: scene_toml, truth (truth.json), camera (camera.json),
                                  manifest (manifest.json), seed, sample_revision
    samples/<name>/video   (T, H, W) uint16 (or uint8) DN, chunks of 64 frames
    samples/<name>/truth/  every array of the sample's truth.zarr, same paths

JSON documents are stored as JSON strings in attributes, so plain ``zarr``/``h5py`` read them
with ``json.loads``. ``open_dataset(path)`` wraps either file.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import tomllib
from pathlib import Path

import numpy as np

from . import __version__

FORMAT = "vvtbench.dataset-pack"
FORMAT_VERSION = 1
LICENCE = """\
* Generated data (videos, ground truth): CC BY 4.0, produced by vvtbench {version} (MIT).
* Stanford bunny (scene `bunny_defect`): from the Stanford 3D Scanning Repository
  (Stanford University Computer Graphics Laboratory, http://graphics.stanford.edu/data/3Dscanrep/),
  as shipped in pymeshlab's test data (`pymeshlab/tests/sample_meshes/bunny.obj`). The
  repository allows use for research with acknowledgement; please credit it, and do not use
  the bunny commercially without permission.
* All other geometry is procedural (boxes, drum heads).
"""


def find_samples(src: str | Path) -> list[Path]:
    """Sample folders (with truth.json and manifest.json) under ``src``."""
    src = Path(src)
    if (src / "truth.json").is_file() and (src / "manifest.json").is_file():
        return [src]
    out = []
    for p in sorted(src.rglob("truth.json")):
        d = p.parent
        if (d / "manifest.json").is_file() and not any(
                part.startswith(".") or ".tmp-" in part or part == "_work"
                for part in d.relative_to(src).parts):
            out.append(d)
    return out


def _samples_from_suite(spec: str, run_dir: Path) -> list[Path]:
    from .bench import load_suite, run_suite

    suite = load_suite(spec)
    run_suite(suite, [], run_dir, until="generate", progress=True)
    info = json.loads((run_dir / "run.json").read_text())
    return [run_dir / "cache" / k / "sample" for k in info["generated_samples"]]


def _revision(sample: Path) -> str:
    return hashlib.sha256((sample / "manifest.json").read_bytes()).hexdigest()[:16]


def _names(samples: list[Path]) -> list[str]:
    names = []
    for s in samples:
        base = s.name if s.name != "sample" else json.loads((s / "truth.json").read_text())[
            "scene"]
        name = base
        if name in names:
            name = f"{base}-{_revision(s)[:8]}"
        names.append(name)
    return names


def dataset_card(samples: list[Path], names: list[str], fmt: str, source: str) -> str:
    rows = []
    for s, n in zip(samples, names, strict=True):
        t = json.loads((s / "truth.json").read_text())
        v = t["video"]
        rows.append(f"| {n} | {t['scene']} | {t['seed']} | {v['frames']} | {v['fps']:g} | "
                    f"{v['height']}x{v['width']} | {v['bit_depth']} | {_revision(s)} |")
    table = "\n".join(rows)
    return f"""# vvtbench dataset

Packed by vvtbench {__version__} from `{source}` ({len(samples)} samples, format `{fmt}`,
layout version {FORMAT_VERSION}).

## Samples

| name | scene | seed | frames | FPS | H x W | bits | revision |
|---|---|---|---|---|---|---|---|
{table}

`revision` = first 16 hex digits of the sha256 of the sample's manifest.json (which holds the
sha256 of every file of the sample folder).

## Schema

```
/                      attrs: format, format_version, vvtbench, samples (JSON list), README
samples/<name>/        attrs (JSON strings): scene_toml (text), truth, camera, manifest;
                       seed (int), sample_revision
samples/<name>/video   (T, H, W) uint16 DN (8-bit consumer videos: uint8), 64 frames/chunk
samples/<name>/truth/  the sample's truth.zarr arrays under the same paths: mesh/, material/,
                       voxels/, modes/, observation/, image/, transient/
```

Units, conventions and every truth array: vvtbench docs/dataset.md (SI units, pixels with
(0, 0) at the centre of the top-left pixel, P = K[R|t]).

## Loading

```python
import vvtbench.export as ex
ds = ex.open_dataset("{'FILE'}")
s = ds[ds.names[0]]; s.video[:10]; s["modes/frequencies_hz"]; s.truth_json; s.scene
# plain zarr:  g = zarr.open_group(FILE, mode="r"); g["samples/<name>/video"][:10]
# plain h5py:  f = h5py.File(FILE); f["samples/<name>/video"][:10];
#              json.loads(f["samples/<name>"].attrs["truth"])
```

## Generator

vvtbench {__version__}; each sample's resolved scene (with its seed) is in `scene_toml`;
regenerate with `vvtbench generate scene.toml`. Rendering is deterministic per seed on one
machine (see docs/dataset.md, "Reproducible").

## Licence

{LICENCE.format(version=__version__)}"""


def _walk_zarr(group, prefix=""):
    import zarr

    for name, obj in group.members():
        path = f"{prefix}{name}"
        if isinstance(obj, zarr.Array):
            yield path, obj
        else:
            yield from _walk_zarr(obj, path + "/")


def _frames(sample: Path):
    from .dataset import open_sample

    s = open_sample(sample)
    return s, s.frames()


class _ZarrWriter:
    def __init__(self, path: Path):
        import zarr

        self.root = zarr.open_group(str(path), mode="w")

    def group(self, path: str):
        return self.root.require_group(path)

    def array(self, path: str, data=None, shape=None, dtype=None, chunks=None):
        kw = {"chunks": chunks} if chunks else {}
        if data is not None:
            data = np.asarray(data)
            a = self.root.create_array(path, shape=data.shape, dtype=data.dtype,
                                       **({"chunks": chunks} if chunks else {}))
            if data.size:
                a[...] = data
            return a
        return self.root.create_array(path, shape=shape, dtype=dtype, **kw)

    def attrs(self, obj, values: dict):
        obj.attrs.update(values)

    def close(self):
        pass


class _H5Writer:
    def __init__(self, path: Path):
        import h5py

        self.root = h5py.File(path, "w")

    def group(self, path: str):
        return self.root.require_group(path)

    def array(self, path: str, data=None, shape=None, dtype=None, chunks=None):
        if data is not None:
            data = np.asarray(data)
            if data.dtype.kind == "U":
                data = data.astype("S")
            return self.root.create_dataset(path, data=data,
                                            chunks=chunks if data.ndim and data.size else None)
        return self.root.create_dataset(path, shape=shape, dtype=dtype, chunks=chunks)

    def attrs(self, obj, values: dict):
        for k, v in values.items():
            obj.attrs[k] = v

    def close(self):
        self.root.close()


def pack(samples: list[Path], out: str | Path, fmt: str = "zarr", source: str = "") -> Path:
    """Write ``samples`` into one Zarr or HDF5 dataset at ``out`` (+ a README dataset card)."""
    if fmt not in ("zarr", "hdf5"):
        raise ValueError(f"format must be 'zarr' or 'hdf5', got {fmt!r}")
    if not samples:
        raise ValueError("no samples to export")
    out = Path(out)
    names = _names(samples)
    card = dataset_card(samples, names, fmt, source or "samples")
    w = _ZarrWriter(out) if fmt == "zarr" else _H5Writer(out)
    try:
        w.attrs(w.root, {"format": FORMAT, "format_version": FORMAT_VERSION,
                         "vvtbench": __version__, "samples": json.dumps(names),
                         "README": card})
        for sample, name in zip(samples, names, strict=True):
            import zarr

            base = f"samples/{name}"
            g = w.group(base)
            truth_json = (sample / "truth.json").read_text()
            w.attrs(g, {
                "scene_toml": (sample / "scene.toml").read_text(),
                "truth": truth_json, "camera": (sample / "camera.json").read_text(),
                "manifest": (sample / "manifest.json").read_text(),
                "seed": int(json.loads(truth_json)["seed"]),
                "sample_revision": _revision(sample),
            })
            s, frames = _frames(sample)
            T, (H, W) = s.n_frames, s.shape
            dtype = np.uint16 if s.info["video"]["pixel_format"] == "gray16le" else np.uint8
            ch = (min(64, max(T, 1)), H, W)
            video = w.array(f"{base}/video", shape=(T, H, W), dtype=dtype, chunks=ch)
            buf, start = [], 0
            for f in frames:
                buf.append(f.astype(dtype))
                if len(buf) == ch[0]:
                    video[start:start + len(buf)] = np.stack(buf)
                    start += len(buf)
                    buf = []
            if buf:
                video[start:start + len(buf)] = np.stack(buf)
            truth = zarr.open_group(str(sample / "truth.zarr"), mode="r")
            for path, arr in _walk_zarr(truth):
                data = arr[...]
                chunks = tuple(int(c) for c in arr.chunks) if data.ndim else None
                w.array(f"{base}/truth/{path}", data=data, chunks=chunks)
    finally:
        w.close()
    readme = out / "README.md" if fmt == "zarr" else out.with_name(out.name + ".README.md")
    readme.write_text(card)
    return out


class PackedSample:
    """One sample of a packed dataset: ``video`` (lazy array), ``truth_json``, ``camera``,
    ``manifest``, ``scene`` (dict), ``s["modes/frequencies_hz"]`` reads a truth array."""

    def __init__(self, group, name: str):
        self.group, self.name = group, name
        a = group.attrs
        self.truth_json = json.loads(a["truth"])
        self.camera = json.loads(a["camera"])
        self.manifest = json.loads(a["manifest"])
        self.scene_toml = str(a["scene_toml"])
        self.scene = tomllib.loads(self.scene_toml)
        self.seed = int(a["seed"])
        self.revision = str(a["sample_revision"])

    @property
    def video(self):
        return self.group["video"]

    def __getitem__(self, path: str) -> np.ndarray:
        return np.asarray(self.group["truth"][path][...])

    def __repr__(self) -> str:
        return f"PackedSample({self.name!r}, video {tuple(self.video.shape)})"


class PackedDataset:
    def __init__(self, root, path: Path, closer=None):
        self.root, self.path, self._closer = root, path, closer
        self.attrs = dict(root.attrs)
        self.names = json.loads(self.attrs["samples"])

    def __getitem__(self, name: str) -> PackedSample:
        return PackedSample(self.root["samples"][name], name)

    def __iter__(self):
        return (self[n] for n in self.names)

    def __len__(self):
        return len(self.names)

    @property
    def readme(self) -> str:
        return str(self.attrs.get("README", ""))

    def close(self):
        if self._closer:
            self._closer()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def open_dataset(path: str | Path) -> PackedDataset:
    """Open a dataset written by ``vvtbench export`` (Zarr folder or HDF5 file)."""
    path = Path(path)
    if path.is_dir():
        import zarr

        root = zarr.open_group(str(path), mode="r")
        return PackedDataset(root, path)
    import h5py

    f = h5py.File(path, "r")
    if f.attrs.get("format") != FORMAT:
        f.close()
        raise ValueError(f"{path}: not a vvtbench dataset (no format={FORMAT!r} attribute)")
    return PackedDataset(f, path, f.close)


def main_export(argv: list[str] | None = None) -> int:
    """``vvtbench export SUITE_OR_DIR --format zarr|hdf5 -o FILE``."""
    p = argparse.ArgumentParser(prog="vvtbench export", description=(
        "pack generated samples (a folder of samples, a run folder, or a suite, which is "
        "generated first) into one Zarr or HDF5 dataset with a dataset card"))
    p.add_argument("source", help="sample folder, folder of samples / run folder, or suite")
    p.add_argument("--format", choices=("zarr", "hdf5"), default="zarr")
    p.add_argument("-o", "--output", required=True, help="output .zarr folder or .h5 file")
    p.add_argument("--run-dir", default=None,
                   help="where a suite's samples are generated (default runs/SUITE)")
    args = p.parse_args(argv)
    src = Path(args.source)
    try:
        if src.is_dir():
            samples = find_samples(src)
        else:
            from .bench import find_suite

            suite_path = find_suite(args.source)
            samples = _samples_from_suite(str(suite_path),
                                          Path(args.run_dir or f"runs/{suite_path.stem}"))
        if not samples:
            raise ValueError(f"{src}: no generated samples found")
        out = pack(samples, args.output, args.format, str(args.source))
    except (ValueError, OSError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    print(f"{len(samples)} sample(s) -> {out}")
    return 0
