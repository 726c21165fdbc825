"""Pack generated samples into one portable dataset: Zarr (v3) or HDF5, xarray-ready.

Layout (the same in both formats; docs/dataset.md, "Exported datasets")::

    /                          attrs: format, format_version, vvtbench, samples, README
    samples/<name>/            attrs: scene_toml, truth, camera, manifest (JSON strings), seed,
                                      sample_revision, truth_arrays, extracted
                               coords: time (s), row, col (px), mode, voxel_x/y/z (m)
    samples/<name>/video       (time, row, col) uint16 DN, chunks of 64 frames
    samples/<name>/truth/...   every array of the sample's truth.zarr, same paths, named dims
    samples/<name>/extracted/<i>/  one extracted ModeSet: shapes (extracted_mode, row, col,
                               component), per-mode scalars, power (frequency), coords
                               extracted_mode, frequency (Hz); attrs modes_json, key

Every array has named dimensions (zarr v3 ``dimension_names``; HDF5 dimension scales, the
netCDF-4 convention) and a ``units`` attribute where it has a unit, so
``xarray.open_datatree(path, engine="zarr")`` and ``engine="h5netcdf"`` open the file with
named dimensions and coordinates. The reader is :mod:`vvtbench.datasets.packed`
(``open_dataset(path)[name]`` gives a :class:`~vvtbench.datasets.packed.PackedSample` with the read
interface of :class:`vvtbench.samples.reader.Sample`); the dataset card and the Croissant file are
written by :mod:`vvtbench.datasets.card` and :mod:`vvtbench.datasets.croissant`.

Safety: :func:`pack` never writes into or through a path it did not create. The output may
not be, contain or lie inside an input; an existing output is replaced only with
``overwrite=True`` and only when it is a dataset written by this module; writing goes into a
temporary sibling ``.NAME.partial-<pid>`` renamed over the output at the end. Every sample is
checked against its manifest (sha256 of every file) before anything is written.
"""

from __future__ import annotations

import json
import os
import shutil
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from .._version import __version__
from ..io.files import NoSpaceError, check_free_space, is_disk_full, open_new, tree_bytes
from ..samples.reader import VIEW_GROUPS
from .card import dataset_card, sample_revision
from .croissant import samples_croissant
from .packed import (
    FORMAT,
    FORMAT_VERSION,
    MODESET_ARRAYS,
    VIDEO_CHUNK,
    ExportError,
    view_truth_path,
)

__all__ = ["DEFAULT_SHARD_BYTES", "ExportError", "check_output", "estimate_bytes",
           "find_extracted", "find_samples", "is_packed_dataset", "pack", "pack_stacked",
           "scene_parameters", "verify_sample"]

#: Files a Zarr dataset folder written by :func:`pack` holds at its top level.
_ZARR_TOP = {"zarr.json", "samples", "README.md", "croissant.json", "SHA256SUMS"}
SUMS = "SHA256SUMS"  # a Zarr dataset's list of every file it holds with its sha256


# --------------------------------------------------------------------------- finding inputs
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


def find_extracted(sample: str | Path) -> list[Path]:
    """Mode folders (modes.json + modes.npz) extracted from ``sample`` by a suite run.

    A run folder keeps a sample at ``cache/generate/<key>/sample`` and each extraction of it at
    ``cache/extract/<key2>/`` whose ``task.json`` names ``generate/<key>`` as its input.
    """
    sample = Path(sample)
    gen = sample.parent
    cache = gen.parent.parent
    if sample.name != "sample" or gen.parent.name != "generate":
        return []
    want = f"generate/{gen.name}"
    out = []
    for task in sorted((cache / "extract").glob("*/task.json")):
        try:
            deps = json.loads(task.read_text()).get("deps", [])
        except (OSError, ValueError):
            continue
        d = task.parent
        if deps and deps[0] == want and (d / "modes.json").is_file() \
                and (d / "modes.npz").is_file():
            out.append(d)
    return out


def verify_sample(sample: Path) -> None:
    """Raise :class:`ExportError` naming the first file of ``sample`` that is missing,
    modified or not listed in its manifest.json."""
    from ..samples.reader import DatasetError, open_sample

    try:
        s = open_sample(sample)
    except (DatasetError, OSError, ValueError) as error:
        raise ExportError(f"{sample}: cannot open sample: {error}") from None
    bad = s.verify()
    if bad:
        more = f" (and {len(bad) - 1} more)" if len(bad) > 1 else ""
        raise ExportError(f"{sample / bad[0].split(': ')[0]}: {bad[0].split(': ', 1)[1]} "
                          f"(manifest.json of sample {sample}){more}; regenerate the sample")


def _names(samples: list[Path]) -> list[str]:
    names: list[str] = []
    for s in samples:
        base = s.name if s.name != "sample" else json.loads((s / "truth.json").read_text())[
            "scene"]
        name = base
        if name in names:
            name = f"{base}-{sample_revision(s)[:8]}"
        names.append(name)
    return names


# --------------------------------------------------------------------------- size
def _raw_bytes(sample: Path, mode_dirs: list[Path]) -> int:
    """The uncompressed size of everything packed for ``sample`` (an upper bound of its packed
    size: the compressors never grow a chunk by more than a few bytes)."""
    import zarr

    from ..samples.reader import open_sample

    s = open_sample(sample, verify=False)
    total = 0
    pixel = 2 if s.info["video"]["pixel_format"] == "gray16le" else 1
    for v in (s.view(i) for i in range(s.n_views)):
        if v.has_video:
            total += v.n_frames * v.shape[0] * v.shape[1] * pixel
    total += sum(int(np.prod(a.shape)) * a.dtype.itemsize
                 for _, a in _walk_zarr(zarr.open_group(str(sample / "truth.zarr"), mode="r")))
    for d in mode_dirs:
        with np.load(d / "modes.npz", allow_pickle=False) as z:
            total += sum(z[k].nbytes for k in z.files)
        total += (d / "modes.json").stat().st_size
    return total + sum((sample / f).stat().st_size for f in
                       ("scene.toml", "truth.json", "camera.json", "manifest.json"))


def estimate_bytes(samples: list[Path], extracted: dict[Path, list[Path]], fmt: str) -> int:
    """Bytes the export of ``samples`` needs free at its output.

    HDF5: the uncompressed size of every array and attribute (an upper bound: the HDF5
    library must never meet a full disk in the middle of a file, which it does not survive).
    Zarr: the size of the input files (the lossless video and truth.zarr compress the same
    data about as well as the export does), since a full disk met while writing a Zarr
    folder is caught and the partial folder removed.
    """
    if fmt == "hdf5":
        body = sum(_raw_bytes(s, extracted.get(s, [])) for s in samples)
    else:
        body = sum(tree_bytes(s) + sum(tree_bytes(d) for d in extracted.get(s, []))
                   for s in samples)
    return int(body * 1.05) + (1 << 20) * (1 + len(samples))


# --------------------------------------------------------------------------- output safety
def _sidecars(out: Path, fmt: str) -> dict[str, Path]:
    """Where the dataset card and the Croissant file go."""
    if fmt == "zarr":
        return {"readme": out / "README.md", "croissant": out / "croissant.json"}
    return {"readme": out.with_name(out.name + ".README.md"),
            "croissant": out.with_name(out.name + ".croissant.json")}


def is_packed_dataset(path: str | Path) -> bool:
    """True when ``path`` is a dataset written by :func:`pack` and holds nothing else."""
    path = Path(path)
    if path.is_symlink():
        return False
    if path.is_dir() and (path / STACKED_MARKER).is_file():
        try:
            marker = json.loads((path / STACKED_MARKER).read_text())
        except (OSError, ValueError):
            return False
        return isinstance(marker, dict) and marker.get("format") == STACKED_FORMAT
    if path.is_dir():
        meta = path / "zarr.json"
        if meta.is_symlink() or not meta.is_file():
            return False
        try:
            attrs = json.loads(meta.read_text()).get("attributes", {})
        except (OSError, ValueError):
            return False
        return attrs.get("format") == FORMAT and all(
            p.name in _ZARR_TOP for p in path.iterdir())
    if path.is_file():
        try:
            import h5py

            with h5py.File(path, "r") as f:
                fmt = f.attrs.get("format")
        except (OSError, ValueError):
            return False
        return (fmt.decode() if isinstance(fmt, bytes) else fmt) == FORMAT
    return False


def _ours_sidecar(path: Path) -> bool:
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError):
        return False
    if path.suffix == ".md":
        return text.startswith("# vvtbench dataset")
    try:
        return json.loads(text).get("vvtbench:format") == FORMAT
    except ValueError:
        return False


def _inside(a: Path, b: Path) -> bool:
    """``a`` is ``b`` or lies inside it (both resolved)."""
    return a == b or b in a.parents


def check_output(out: str | Path, inputs: list[Path], fmt: str, overwrite: bool) -> Path:
    """Refuse an output path that is, contains or lies in an input, that is (or has) a symbolic
    link, or that exists (unless ``overwrite`` and it is a dataset written by :func:`pack`).
    Returns the output path."""
    out = Path(out)
    if out.name in ("", ".", ".."):
        raise ExportError(f"{out}: the output must name a new file or folder (not '.' or '..')")
    target = out.resolve()
    for p in inputs:
        src = Path(p).resolve()
        if _inside(target, src) or _inside(src, target):
            raise ExportError(f"{out}: the output may not be, contain or lie inside the input "
                              f"{p}")
    paths = [out, *(_sidecars(out, fmt).values() if fmt == "hdf5" else [])]
    for p in paths:
        if p.is_symlink():
            raise ExportError(f"{p}: is a symbolic link; export does not write through links")
    if out.parent.exists() and not out.parent.is_dir():
        raise ExportError(f"{out.parent}: is not a folder")
    existing = [p for p in paths if p.exists()]
    if existing and not overwrite:
        raise ExportError(f"{existing[0]}: already exists; pass --overwrite (overwrite=True) "
                          "to replace a dataset written by vvtbench export")
    if out.exists():
        kind_ok = out.is_dir() if fmt == "zarr" else out.is_file()
        if not kind_ok or not is_packed_dataset(out):
            raise ExportError(f"{out}: exists and is not a {fmt} dataset written by vvtbench "
                              "export; not replacing it (choose another output path)")
    for p in paths[1:]:
        if p.exists() and not (p.is_file() and _ours_sidecar(p)):
            raise ExportError(f"{p}: exists and was not written by vvtbench export; not "
                              "replacing it")
    return out


# --------------------------------------------------------------------------- dims and units
def _truth_dims(name: str, kind: str) -> dict[str, tuple[str, ...]]:
    """Dimension names of the known truth.zarr arrays (others get ``<array>_dim_<i>``)."""
    del kind
    vox = ("voxel_x", "voxel_y", "voxel_z")
    return {
        "mesh/points": ("node", "xyz"),
        "mesh/cells": ("element", "element_node"),
        "mesh/surface": ("surface_triangle", "triangle_vertex"),
        "mesh/surface_nodes": ("surface_node",),
        "mesh/element_volumes": ("element",),
        "mesh/fixed_nodes": ("fixed_node",),
        "material/stiffness": ("element",),
        "material/density": ("element",),
        "material/nu": ("element",),
        "voxels/stiffness": vox,
        "voxels/density": vox,
        "voxels/nu": vox,
        "voxels/element_voxel": ("element",),
        "modes/eigenvalues": ("mode",),
        "modes/frequencies_hz": ("mode",),
        "modes/damping_ratios": ("mode",),
        "modes/vectors": ("free_dof", "mode"),
        "modes/free_dofs": ("free_dof",),
        "modes/surface": ("mode", "surface_node", "xyz"),
        "observation/rest_uv": ("surface_node", "uv"),
        "observation/rest_depth": ("surface_node",),
        "observation/visible": ("surface_node",),
        "observation/visible_index": ("visible_node",),
        "observation/visible_nodes": ("visible_node",),
        "observation/jacobian": ("visible_node", "uv", "xyz"),
        "observation/image_modes": ("mode", "visible_node", "uv"),
        "observation/image_modes_surface": ("mode", "surface_node", "uv"),
        "image/rest": ("row", "col"),
        "image/depth": ("row", "col"),
        "image/triangle": ("row", "col"),
        "image/barycentric": ("row", "col", "triangle_vertex"),
        "image/modes": ("mode", "row", "col", "uv"),
        "transient/displacements": ("time", "surface_node", "xyz"),
        "transient/times": ("time",),
    }.get(name, ())


def _truth_units(name: str, drum: bool) -> str | None:
    mode = "px m-1 kg-1/2"
    return {
        "mesh/points": "m",
        "mesh/element_volumes": "m2" if drum else "m3",
        "material/stiffness": "N/m" if drum else "Pa",
        "material/density": "kg/m2" if drum else "kg/m3",
        "material/nu": "1",
        "voxels/stiffness": "N/m" if drum else "Pa",
        "voxels/density": "kg/m2" if drum else "kg/m3",
        "voxels/nu": "1",
        "modes/eigenvalues": "rad2 s-2",
        "modes/frequencies_hz": "Hz",
        "modes/damping_ratios": "1",
        "modes/vectors": "kg-1/2",
        "modes/surface": "kg-1/2",
        "observation/rest_uv": "px",
        "observation/rest_depth": "m",
        "observation/jacobian": "px/m",
        "observation/image_modes": mode,
        "observation/image_modes_surface": mode,
        "image/rest": "1",
        "image/depth": "m",
        "image/barycentric": "1",
        "image/modes": mode,
        "transient/displacements": "m",
        "transient/times": "s",
    }.get(name)


# --------------------------------------------------------------------------- writers
class _Scopes:
    """Dimension sizes per group; a dimension is visible in its group and every subgroup."""

    def __init__(self) -> None:
        self.sizes: dict[str, dict[str, int]] = {}

    def lookup(self, group: str, dim: str) -> tuple[str, int] | None:
        parts = group.split("/") if group else []
        for i in range(len(parts), -1, -1):
            g = "/".join(parts[:i])
            if dim in self.sizes.get(g, {}):
                return g, self.sizes[g][dim]
        return None

    def resolve(self, group: str, name: str, shape: tuple[int, ...],
                proposal: tuple[str, ...]) -> tuple[str, ...]:
        """``proposal`` when it fits ``shape`` and every dimension's size in scope, else
        dimensions named after the array."""
        dims = proposal
        if len(dims) != len(shape) or any(
                (f := self.lookup(group, d)) is not None and f[1] != n
                for d, n in zip(dims, shape, strict=True)) or len(set(dims)) != len(dims):
            dims = tuple(f"{name}_dim_{i}" for i in range(len(shape)))
        for d, n in zip(dims, shape, strict=True):
            if self.lookup(group, d) is None:
                self.sizes.setdefault(group, {})[d] = int(n)
        return dims


class _ZarrWriter:
    def __init__(self, path: Path):
        import zarr

        self.root = zarr.open_group(str(path), mode="w-", zarr_format=3)

    def attrs(self, path: str, values: dict) -> None:
        g = self.root.require_group(path) if path else self.root
        g.attrs.update(values)

    def create(self, path: str, shape, dtype, dims, chunks=None, attrs=None):
        from zarr.codecs import BloscCodec

        kw = {"chunks": chunks} if chunks and all(shape) else {}
        # byte shuffle + zstd: the video is ~20 % smaller than with zarr's default (zstd)
        kw["compressors"] = BloscCodec(cname="zstd", clevel=5, shuffle="shuffle")
        a = self.root.create_array(path, shape=tuple(shape), dtype=dtype,
                                   dimension_names=list(dims), **kw)
        if attrs:
            a.attrs.update(attrs)
        return a

    def array(self, path: str, data, dims, chunks=None, attrs=None):
        data = np.asarray(data)
        a = self.create(path, data.shape, data.dtype, dims, chunks, attrs)
        if data.size:
            a[...] = data
        return a

    def coord(self, group: str, name: str, values, attrs=None) -> None:
        self.array(f"{group}/{name}", values, (name,), attrs=attrs)

    def close(self) -> None:
        import zarr

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # "consolidated metadata is not in the v3 spec"
            zarr.consolidate_metadata(self.root.store)


class _H5Writer:
    """h5py with netCDF-4 style dimension scales, so h5netcdf/xarray see named dimensions."""

    NOT_A_VARIABLE = "This is a netCDF dimension but not a netCDF variable."

    def __init__(self, path: Path, scopes: _Scopes):
        import h5py

        self.root = h5py.File(path, "w-")
        self.scopes = scopes

    def attrs(self, path: str, values: dict) -> None:
        g = self.root.require_group(path) if path else self.root
        for k, v in values.items():
            g.attrs[k] = v

    @staticmethod
    def _filters(shape, chunks) -> dict:
        if not all(shape) or not shape:
            return {}
        return {"chunks": tuple(chunks) if chunks else True, "compression": "gzip",
                "compression_opts": 4, "shuffle": True}

    def _scale(self, group: str, dim: str):
        found = self.scopes.lookup(group, dim)
        g_path, n = found if found else (group, None)
        key = f"{g_path}/{dim}" if g_path else dim
        if key not in self.root:
            ds = self.root.create_dataset(key, shape=(n,), dtype="f4")
            ds.make_scale(f"{self.NOT_A_VARIABLE}{n:10d}")
        return self.root[key]

    def create(self, path: str, shape, dtype, dims, chunks=None, attrs=None):
        a = self.root.create_dataset(path, shape=tuple(shape), dtype=dtype,
                                     **self._filters(shape, chunks))
        group = path.rsplit("/", 1)[0] if "/" in path else ""
        for i, d in enumerate(dims):
            a.dims[i].attach_scale(self._scale(group, d))
        for k, v in (attrs or {}).items():
            a.attrs[k] = v
        return a

    def array(self, path: str, data, dims, chunks=None, attrs=None):
        data = np.asarray(data)
        if data.dtype.kind == "U":
            data = data.astype("S")
        a = self.create(path, data.shape, data.dtype, dims, chunks, attrs)
        if data.size:
            a[...] = data
        return a

    def coord(self, group: str, name: str, values, attrs=None) -> None:
        values = np.asarray(values)
        a = self.root.create_dataset(f"{group}/{name}", data=values)
        a.make_scale(name)
        for k, v in (attrs or {}).items():
            a.attrs[k] = v

    def close(self) -> None:
        self.root.close()


# --------------------------------------------------------------------------- pack
def _walk_zarr(group, prefix=""):
    import zarr

    for name, obj in sorted(group.members(), key=lambda m: m[0]):
        path = f"{prefix}{name}"
        if isinstance(obj, zarr.Array):
            yield path, obj
        else:
            yield from _walk_zarr(obj, path + "/")


def _json_attr(doc: Any) -> str:
    return json.dumps(doc, sort_keys=True)


def _write_video(w, path: str, s, dims: tuple[str, str, str]) -> Any:
    """Stream the video of ``s`` (a sample or one of its views) into ``path``; returns the
    array (HDF5 flushes its chunk cache when it is released: the caller holding it to the
    end of the sample keeps the file's layout the same from one export to the next)."""
    T, (H, W) = s.n_frames, s.shape
    dtype = np.uint16 if s.info["video"]["pixel_format"] == "gray16le" else np.uint8
    ch = (min(VIDEO_CHUNK, max(T, 1)), H, W)
    video = w.create(path, (T, H, W), dtype, dims, ch,
                     {"units": "DN", "long_name": "video frames (digital numbers)",
                      "bit_depth": int(s.bit_depth)})
    buf: list[np.ndarray] = []
    start = 0
    for f in s.frames():
        buf.append(f.astype(dtype))
        if len(buf) == ch[0]:
            video[start:start + len(buf)] = np.stack(buf)
            start += len(buf)
            buf = []
    if buf:
        video[start:start + len(buf)] = np.stack(buf)
        start += len(buf)
    if start != T:
        raise ExportError(f"{s.video_path}: holds {start} frames, truth.json says {T}; "
                          "regenerate the sample")
    return video


def _view_pixel_dims(s, shape: tuple[int, int]) -> dict[int, dict[str, str]]:
    """Views 1.. of ``s``, each with the renaming of its pixel dimensions: ``row``/``col``
    when its frames are the size of view 0's (the sample's coordinates serve), else
    ``view_row``/``view_col`` (xarray aligns a group with its parents by name)."""
    out = {}
    for i in range(1, s.n_views):
        same = s.view(i).shape == tuple(shape)
        out[i] = {} if same else {"row": "view_row", "col": "view_col"}
    return out


def _write_view(w, scopes: _Scopes, sample: Path, s, group: str, index: int,
                rename: dict[str, str]) -> Any:
    """View ``index`` of ``s`` at ``group``: its camera and truth.json entry as attributes,
    its own pixel coordinates when its frame size differs from view 0's, its video (returned;
    None for a modes-only sample)."""
    v = s.view(index)
    entry = s.info["views"][index]
    H, W = v.shape
    for c, n, desc in (("row", H, "pixel row (0 = centre of the top row)"),
                       ("col", W, "pixel column")):
        if c in rename:
            scopes.sizes.setdefault(group, {})[rename[c]] = n
            w.coord(group, rename[c], np.arange(n, dtype=np.int64),
                    {"units": "px", "long_name": f"{desc} of view {index}"})
    w.attrs(group, {"camera": (sample / entry["camera"]).read_text(),
                    "view": _json_attr(entry), "index": int(index),
                    "time_offset_s": float(entry.get("time_offset_s", 0.0))})
    if not v.has_video:
        return None
    return _write_video(w, f"{group}/video", v,
                        ("time", rename.get("row", "row"), rename.get("col", "col")))


def _write_sample(w, scopes: _Scopes, sample: Path, name: str,
                  extracted: list[Path]) -> None:
    import zarr

    from ..modes import ModeSet
    from ..samples.reader import open_sample

    s = open_sample(sample)
    drum = s.scene.geometry.kind == "drum"
    base = f"samples/{name}"
    T, (H, W) = s.n_frames, s.shape
    truth = zarr.open_group(str(sample / "truth.zarr"), mode="r")
    arrays = list(_walk_zarr(truth))
    names = [p for p, _ in arrays]
    # ---- coordinates of the sample group (inherited by every subgroup)
    times = np.arange(T) / s.fps if T else np.zeros(0)
    if "transient/times" in names and truth["transient/times"].shape == (T,):
        times = np.asarray(truth["transient/times"][...], dtype=np.float64)
    coords: dict[str, tuple[np.ndarray, dict]] = {
        "time": (times, {"units": "s", "long_name": "frame time (exposure centre)"}),
        "row": (np.arange(H, dtype=np.int64), {"units": "px", "long_name": "pixel row "
                                                "(0 = centre of the top row)"}),
        "col": (np.arange(W, dtype=np.int64), {"units": "px", "long_name": "pixel column"}),
    }
    if "modes/frequencies_hz" in names:
        m = int(truth["modes/frequencies_hz"].shape[0])
        coords["mode"] = (np.arange(m, dtype=np.int64), {"long_name": "mode index"})
    vox = s.info.get("voxels")
    if vox and len(vox.get("shape", [])) == len(vox.get("origin", [])):
        for ax, o, size, n in zip("xyz", vox["origin"], vox["size"], vox["shape"],
                                  strict=False):
            centres = o + (np.arange(n) + 0.5) * (size / n)
            coords[f"voxel_{ax}"] = (centres, {"units": "m",
                                               "long_name": f"voxel centre {ax}"})
    for c, (values, attrs) in coords.items():
        scopes.sizes.setdefault(base, {})[c] = len(values)
        w.coord(base, c, values, attrs)
    # ---- video (modes-only samples have none)
    videos = [_write_video(w, f"{base}/video", s, ("time", "row", "col"))] if s.has_video \
        else []
    # ---- truth arrays (all of them, whatever their name); view i's under views/<i>/truth/
    pixel_dims = _view_pixel_dims(s, (H, W))
    for path, arr in arrays:
        data = arr[...]
        found = view_truth_path(path)
        if found is not None and found[0] in pixel_dims:
            where, rename = f"{base}/views/{found[0]}/truth/{found[1]}", pixel_dims[found[0]]
            proposal = tuple(rename.get(d, d) for d in _truth_dims(found[1], ""))
            unit = _truth_units(found[1], drum)
        else:
            where, proposal, unit = f"{base}/truth/{path}", _truth_dims(path, ""), \
                _truth_units(path, drum)
        group, _, leaf = where.rpartition("/")
        dims = scopes.resolve(group, leaf, data.shape, proposal)
        chunks = tuple(int(c) for c in arr.chunks) if data.ndim else None
        w.array(f"{group}/{leaf}", data, dims, chunks, {"units": unit} if unit else {})
    # ---- the other views: camera, view entry, video
    for i, rename in pixel_dims.items():
        videos.append(_write_view(w, scopes, sample, s, f"{base}/views/{i}", i, rename))
    # ---- extracted modes
    keys = []
    for i, d in enumerate(extracted):
        ms = ModeSet.load(d)
        g = f"{base}/extracted/{i}"
        k, F = len(ms), len(ms.freqs_hz)
        for c, values, attrs in (
                ("extracted_mode", np.arange(k, dtype=np.int64), {"long_name": "mode index"}),
                ("frequency", ms.freqs_hz, {"units": "Hz", "long_name": "spectrum frequency"})):
            scopes.sizes.setdefault(g, {})[c] = len(values)
            w.coord(g, c, values, attrs)
        del F
        for a, (dims, unit) in MODESET_ARRAYS.items():
            data = getattr(ms, a)
            if data is None:
                continue
            data = np.asarray(data)
            dims = scopes.resolve(g, a, data.shape, dims)
            w.array(f"{g}/{a}", data, dims, None, {"units": unit} if unit else None)
        key = f"{d.parent.name}/{d.name}"
        w.attrs(g, {"modes_json": (d / "modes.json").read_text(), "key": key,
                    "fps": float(ms.fps), "n_frames": int(ms.n_frames)})
        keys.append(key)
    w.attrs(base, {
        "scene_toml": (sample / "scene.toml").read_text(),
        "truth": (sample / "truth.json").read_text(),
        "camera": (sample / "camera.json").read_text(),
        "manifest": (sample / "manifest.json").read_text(),
        "seed": int(s.info["seed"]),
        "sample_revision": sample_revision(sample),
        "truth_arrays": _json_attr(names),
        "extracted": _json_attr(keys),
    })


def pack(samples: list[Path], out: str | Path, fmt: str = "zarr", source: str = "", *,
         overwrite: bool = False, extracted: dict[Path, list[Path]] | None = None,
         inputs: list[Path] | tuple = ()) -> Path:
    """Write ``samples`` into one Zarr or HDF5 dataset at ``out``, plus a README dataset card
    and a Croissant JSON-LD file (inside a Zarr folder; beside an HDF5 file as
    ``OUT.README.md`` and ``OUT.croissant.json``).

    ``extracted`` maps a sample folder to its mode folders (default: :func:`find_extracted`).
    ``inputs`` are further paths the output must stay clear of (e.g. the folder the samples
    were found in). Raises :class:`ExportError` (nothing written) for an unsafe output path or
    a sample that does not match its manifest.
    """
    if fmt not in ("zarr", "hdf5"):
        raise ExportError(f"format must be 'zarr' or 'hdf5', got {fmt!r}")
    samples = [Path(s) for s in samples]
    if not samples:
        raise ExportError("no samples to export")
    if extracted is None:
        extracted = {s: find_extracted(s) for s in samples}
    mode_dirs = [d for s in samples for d in extracted.get(s, [])]
    out = check_output(out, [*samples, *mode_dirs, *map(Path, inputs)], fmt, overwrite)
    for s in samples:
        verify_sample(s)
    names = _names(samples)
    card = dataset_card(samples, names, fmt, source or "samples")
    tag = f"partial-{os.getpid()}"
    partial = out.with_name(f".{out.name}.{tag}")
    side = _sidecars(out, fmt)
    side_tmp = {k: p.with_name(f".{p.name}.{tag}") for k, p in side.items()} \
        if fmt == "hdf5" else {k: partial / p.name for k, p in side.items()}
    for p in [partial, *side_tmp.values()]:
        if p.exists() or p.is_symlink():
            raise ExportError(f"{p}: a temporary path of this export already exists; remove "
                              "it (left by an interrupted export)")
    out.parent.mkdir(parents=True, exist_ok=True)
    try:
        check_free_space(out.parent, estimate_bytes(samples, extracted, fmt),
                         f"the {fmt} export of {len(samples)} sample(s)")
    except NoSpaceError as error:
        raise ExportError(str(error)) from None
    from ..io.lock import RunLock, RunLocked

    try:  # one writer per output: a second export to the same path is refused
        lock = RunLock(out.parent, name=f".{out.name}.lock", remove=True).acquire()
    except RunLocked as error:
        raise ExportError(f"{out}: another export is writing it ({error})") from None
    try:
        _check_replaceable(out, fmt, overwrite)
        return _pack_locked(samples, out, fmt, source, names, card, partial, side, side_tmp,
                            extracted)
    except OSError as error:
        if not is_disk_full(error):
            raise
        raise _disk_full(out, error) from None
    finally:
        lock.release()


def _disk_full(out: Path, error: OSError) -> ExportError:
    """The one-line error of an export whose disk filled up (its partial output removed)."""
    return ExportError(f"{out}: the disk holding {out.parent} became full while writing "
                       f"({error.strerror or error}); nothing was written (the partial "
                       "output is removed); free some space and export again")


def _check_replaceable(out: Path, fmt: str, overwrite: bool) -> None:
    """An existing Zarr dataset is replaced only when it holds exactly the files its
    ``SHA256SUMS`` lists (nothing of the user's would be deleted with it)."""
    if not (overwrite and fmt == "zarr" and out.is_dir()):
        return
    from .release import ReleaseError, file_sums, read_sums

    if not (out / SUMS).is_file():
        raise ExportError(f"{out}: has no {SUMS} (written by an older vvtbench): not replacing "
                          "it, since its files cannot be told from yours; remove it yourself")
    try:
        listed = set(read_sums(out / SUMS))
        held = set(file_sums(out, exclude=(SUMS,)))
    except ReleaseError as error:
        raise ExportError(f"{out}: {error}") from None
    extra = sorted(held - listed)
    if extra:
        raise ExportError(f"{out / extra[0]}: not written by vvtbench export (not in "
                          f"{SUMS}); not replacing the dataset that holds it")


def _pack_locked(samples, out, fmt, source, names, card, partial, side, side_tmp,
                 extracted) -> Path:
    scopes = _Scopes()
    created = []
    try:
        w = _ZarrWriter(partial) if fmt == "zarr" else _H5Writer(partial, scopes)
        created.append(partial)
        try:
            w.attrs("", {"format": FORMAT, "format_version": FORMAT_VERSION,
                         "vvtbench": __version__, "samples": json.dumps(names),
                         "README": card})
            for sample, name in zip(samples, names, strict=True):
                _write_sample(w, scopes, sample, name, extracted.get(sample, []))
        finally:
            w.close()
        meta = samples_croissant(out.stem, out, fmt, partial, samples, names,
                                 source or "samples")
        for key, text in (("readme", card), ("croissant", json.dumps(meta, indent=2) + "\n")):
            p = side_tmp[key]
            with open_new(p) as f:  # exclusive: never through a link
                f.write(text.encode())
            created.append(p)
        if fmt == "zarr":  # every chunk's sha256: verify checks them, --overwrite trusts them
            from .release import file_sums, write_sums

            write_sums(file_sums(partial, exclude=(SUMS,)), partial / SUMS)
        _replace(partial, out)
        created.remove(partial)
        if fmt == "hdf5":
            for key in side:
                os.replace(side_tmp[key], side[key])
                created.remove(side_tmp[key])
    except BaseException:
        for p in created:
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p, ignore_errors=True)
            else:
                p.unlink(missing_ok=True)
        raise
    return out


def _replace(partial: Path, out: Path) -> None:
    """Rename ``partial`` to ``out``, atomically replacing an existing dataset of ours."""
    if partial.is_dir() and out.exists():
        old = out.with_name(f".{out.name}.old-{os.getpid()}")
        os.rename(out, old)
        try:
            os.rename(partial, out)
        except OSError:
            os.rename(old, out)
            raise
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(partial, out)


# --------------------------------------------------------------------------- stacked layout
STACKED_FORMAT = "vvtbench-stacked"
STACKED_VERSION = 1
STACKED_MARKER = "dataset.json"  # the marker a stacked export holds at its top level
INDEX = "index.parquet"
DEFAULT_SHARD_BYTES = 20 * 10**9  # hubs accept files up to 50 GB; 20 GB leaves room
MAX_FILES_PER_FOLDER = 10_000
WRITE_BUFFER_BYTES = 256 * 2**20  # samples are gathered into blocks of at most this size
#: A shard of one array holds at most this many uncompressed bytes: writing a block into a
#: shard reads and rewrites the shard, so this bounds the memory of an export.
SHARD_MEMORY_BYTES = 2**30

#: Dimension names of the stacked layout, renamed from the per-sample layout's.
_STACKED_RENAME = {"node": "vertex", "surface_node": "surface_vertex",
                   "visible_node": "visible_vertex", "fixed_node": "fixed_vertex",
                   "element_node": "element_vertex", "xyz": "component",
                   "voxel_x": "x", "voxel_y": "y", "voxel_z": "z"}
_COORDS = ("family", "split", "index", "seed", "sample_revision")


def _stacked_dims(path: str, ndim: int) -> tuple[str, ...]:
    """Named dimensions of a truth array in the stacked layout (without ``sample``)."""
    proposal = _truth_dims(path, "")
    if path == "voxels/volume":
        proposal = ("voxel_x", "voxel_y", "voxel_z")
    if path.startswith("mesh/node_sets/"):
        proposal = (f"{path.rsplit('/', 1)[1]}_vertex",)
    if path.startswith("voxels/") and len(proposal) == 3 and ndim < 3:
        proposal = proposal[:ndim]  # drums: a 2-D voxel grid
    if len(proposal) != ndim:
        flat = path.replace("/", "_")
        proposal = (flat,) if ndim == 1 else tuple(f"{flat}_axis{i}" for i in range(ndim))
    return tuple(_STACKED_RENAME.get(d, d) for d in proposal)


def _variable(path: str) -> str:
    return path.replace("/", "_")


def _instance(sample: Path, position: int) -> dict[str, Any]:
    """Family, split, index and seed of a sample (from its family.json when it has one)."""
    truth = json.loads((sample / "truth.json").read_text())
    fam = {}
    if (sample / "family.json").is_file():
        fam = json.loads((sample / "family.json").read_text())
    return {"sample": str(truth.get("scene", sample.name)),
            "family": str(fam.get("family") or "samples"),
            "split": str(fam.get("split") or "all"),
            "index": int(fam.get("index", position)),
            "seed": int(fam.get("seed", truth.get("seed", 0))),
            "sample_revision": sample_revision(sample)}


def scene_parameters(sample: Path) -> dict[str, Any]:
    """The drawn parameters of a sample: every scalar of its resolved scene.toml under a dotted
    key (``scene.material.E``, ``scene.geometry.size.0``, ...); lists of tables such as
    ``material.defects`` become a count and a JSON column."""
    import tomllib

    doc = tomllib.loads((sample / "scene.toml").read_text())
    out: dict[str, Any] = {}

    def walk(prefix: str, value: Any) -> None:
        if isinstance(value, dict):
            for k, v in value.items():
                walk(f"{prefix}.{k}", v)
        elif isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
            out[f"{prefix}.count"] = len(value)
            out[f"{prefix}.json"] = json.dumps(value, sort_keys=True)
        elif isinstance(value, list):
            if all(isinstance(v, (int, float, str, bool)) for v in value):
                for i, v in enumerate(value):
                    out[f"{prefix}.{i}"] = v
            else:
                out[prefix] = json.dumps(value, sort_keys=True)
        else:
            out[prefix] = value

    for key, value in doc.items():
        if key not in ("name", "description"):
            walk(f"scene.{key}", value)
    return out


class _Plan:
    """Padded shapes, dtypes and dimension names of one family/split store.

    When a sample of the split holds several views, the arrays every view has of its own
    (``observation/*``, ``image/*``, ``crb/*``, ``modes/crb_*``) get a ``view`` dimension after
    ``sample`` (view 0 the sample's, view i its ``views/<i>/`` arrays); a dimension only such
    arrays have (``visible_vertex``, ``row``, ...) is padded per view.
    """

    def __init__(self, samples: list[Path]):
        import zarr

        self.shapes: dict[str, list[tuple[int, ...]]] = {}
        self.dtypes: dict[str, np.dtype] = {}
        self.dims: dict[str, tuple[str, ...]] = {}
        self.voxels: list[dict | None] = []
        self.n_views: list[int] = []
        self.cameras: list[list[tuple[dict, float]]] = []
        view_shapes: dict[str, dict[tuple[int, int], tuple[int, ...]]] = {}
        view_dtypes: dict[str, np.dtype] = {}
        for k, s in enumerate(samples):
            truth = zarr.open_group(str(s / "truth.zarr"), mode="r")
            doc = json.loads((s / "truth.json").read_text())
            entries = doc.get("views") if isinstance(doc.get("views"), list) else None
            self.n_views.append(len(entries) if entries else 1)
            self.cameras.append([(json.loads((s / e["camera"]).read_text()),
                                  float(e.get("time_offset_s", 0.0))) for e in entries]
                                if entries else
                                [(json.loads((s / "camera.json").read_text()), 0.0)])
            sizes: dict[str, int] = {}
            for path, arr in _walk_zarr(truth):
                found = view_truth_path(path)
                if found is not None:
                    if found[0] < self.n_views[-1]:
                        view_shapes.setdefault(found[1], {})[(k, found[0])] = tuple(
                            int(n) for n in arr.shape)
                        prev = view_dtypes.get(found[1])
                        view_dtypes[found[1]] = arr.dtype if prev is None else \
                            np.result_type(prev, arr.dtype)
                    continue
                dims = self.dims.get(path) or _stacked_dims(path, arr.ndim)
                if len(dims) != arr.ndim:
                    raise ExportError(f"{s / 'truth.zarr' / path}: has {arr.ndim} dimensions, "
                                      f"other samples of the split have {len(dims)}")
                clash = any(sizes.get(d, n) != n for d, n in zip(dims, arr.shape, strict=True))
                if clash:
                    dims = tuple(f"{_variable(path)}_{d}" for d in dims)
                self.dims[path] = dims
                sizes.update(zip(dims, arr.shape, strict=True))
                self.shapes.setdefault(path, []).append(tuple(int(n) for n in arr.shape))
                prev = self.dtypes.get(path)
                self.dtypes[path] = arr.dtype if prev is None else np.result_type(prev, arr.dtype)
            info = doc.get("voxels")
            self.voxels.append(info if info and len(info.get("shape", [])) ==
                               len(info.get("origin", [])) else None)
        n = len(samples)
        for path, shapes in list(self.shapes.items()):
            if len(shapes) != n:
                del self.shapes[path], self.dims[path], self.dtypes[path]
        self.views = max(self.n_views, default=1)
        self.view_paths: list[str] = []
        self.view_dims: set[str] = set()
        self.view_sizes: dict[str, list[list[int]]] = {}
        if self.views > 1:
            self._stack_views(samples, view_shapes, view_dtypes)
        self.dim_sizes: dict[str, list[int]] = {}
        for path, shapes in self.shapes.items():
            for i, d in enumerate(self.dims[path]):
                sizes_d = [sh[i] for sh in shapes]
                self.dim_sizes[d] = [max(a, b) for a, b in
                                     zip(self.dim_sizes.get(d, sizes_d), sizes_d, strict=True)]
        self.padded = {d: max(v) for d, v in self.dim_sizes.items()}
        self.varying = sorted(d for d, v in self.dim_sizes.items() if len(set(v)) > 1 or (
            d in self.view_dims and len({n for row in self.view_sizes[d] for n in row}) > 1))

    def _stack_views(self, samples: list[Path], view_shapes: dict, view_dtypes: dict) -> None:
        """Give the per-view arrays their ``view`` dimension (sizes: the largest view)."""
        self.view_paths = [p for p in self.shapes if p.startswith(VIEW_GROUPS)]
        shared = {d for p, dims in self.dims.items() if p not in self.view_paths for d in dims}
        for p in self.view_paths:
            stacked = []
            for k, n_views in enumerate(self.n_views):
                shapes = [self.shapes[p][k]]
                for v in range(1, n_views):
                    shape = view_shapes.get(p, {}).get((k, v))
                    if shape is None or len(shape) != len(shapes[0]):
                        where = samples[k] / "truth.zarr" / "views" / str(v) / p
                        raise ExportError(f"{where}: " + ("missing" if shape is None else
                                          f"has {len(shape)} dimensions") + f", view 0 of the "
                                          f"sample has {p} with {len(shapes[0])}; regenerate "
                                          "the sample")
                    shapes.append(shape)
                for i, d in enumerate(self.dims[p]):
                    if d in shared:
                        continue
                    per_view = [sh[i] for sh in shapes] + [0] * (self.views - n_views)
                    rows = self.view_sizes.setdefault(d, [[0] * self.views for _ in self.n_views])
                    rows[k] = [max(a, b) for a, b in zip(rows[k], per_view, strict=True)]
                stacked.append((n_views, *np.max(np.array(shapes), axis=0).tolist()))
            self.view_dims.update(d for d in self.dims[p] if d not in shared)
            self.shapes[p] = stacked
            self.dims[p] = ("view", *self.dims[p])
            if p in view_dtypes:
                self.dtypes[p] = np.result_type(self.dtypes[p], view_dtypes[p])

    def shape(self, path: str) -> tuple[int, ...]:
        return tuple(self.padded[d] for d in self.dims[path])

    def sample_bytes(self) -> dict[str, int]:
        """Uncompressed bytes one sample adds to each array."""
        return {p: int(np.prod(self.shape(p))) * self.dtypes[p].itemsize for p in self.shapes}


def _pad_value(dtype: np.dtype) -> Any:
    if dtype.kind == "f" or dtype.kind == "c":
        return np.nan
    if dtype.kind == "b":
        return False
    return -1 if dtype.kind == "i" else 0


def _create_stacked(group, name: str, shape: tuple[int, ...], dtype, dims: tuple[str, ...],
                    per_shard: int, attrs: dict) -> Any:
    from zarr.codecs import BloscCodec

    inner = (1, *(max(1, n) for n in shape[1:]))
    a = group.create_array(name, shape=shape, dtype=dtype, chunks=inner,
                           shards=(per_shard, *inner[1:]), dimension_names=list(dims),
                           fill_value=_pad_value(np.dtype(dtype)) if np.dtype(dtype).kind
                           != "U" else "",
                           compressors=BloscCodec(cname="zstd", clevel=5, shuffle="shuffle"))
    a.attrs.update(attrs)
    return a


def _write_store(store: Path, samples: list[Path], rows: list[dict], shard_bytes: int,
                 drum: bool) -> dict[str, Any]:
    """Stream ``samples`` into one Zarr v3 store with a ``sample`` dimension; returns what the
    index and the card need (samples per shard, shard count, variables)."""
    import zarr

    plan = _Plan(samples)
    n = len(samples)
    per_sample = plan.sample_bytes()
    biggest = max(per_sample.items(), key=lambda kv: kv[1], default=("", 0))
    if biggest[1] > shard_bytes:
        raise ExportError(f"--shard-size {shard_bytes}: smaller than one sample of "
                          f"{biggest[0]} ({biggest[1]} bytes); allowed: a shard size of at "
                          f"least {biggest[1]} bytes")
    per_shard = max(1, min(n, min(shard_bytes, SHARD_MEMORY_BYTES) // max(biggest[1], 1)))
    n_shards = -(-n // per_shard)
    if n_shards >= MAX_FILES_PER_FOLDER:
        raise ExportError(f"--shard-size {shard_bytes}: {n_shards} shards per array, more "
                          f"than {MAX_FILES_PER_FOLDER - 1} files in one folder; allowed: a "
                          "larger shard size")
    root = zarr.open_group(str(store), mode="w-", zarr_format=3)
    rows_dims = ("sample",)
    arrays: dict[str, Any] = {}
    for path in plan.shapes:
        unit = _truth_units(path, drum)
        attrs = {"truth_path": path,
                 "long_name": f"{path} of the sample's truth.zarr (docs/dataset.md)",
                 "padding": "NaN (floats), -1 (integers), False (booleans) beyond a "
                            "sample's size; see <dim>_mask"}
        if unit:
            attrs["units"] = unit
        if path in plan.view_paths:
            attrs["truth_path"] = f"{path} (view 0), views/<i>/{path} (view i)"
        arrays[path] = _create_stacked(root, _variable(path), (n, *plan.shape(path)),
                                       plan.dtypes[path], ("sample", *plan.dims[path]),
                                       per_shard, attrs)
    masks = {}
    for d in plan.varying:
        if d in plan.view_dims:  # sizes that differ from one view to the next
            masks[d] = _create_stacked(root, f"{d}_mask", (n, plan.views, plan.padded[d]), bool,
                                       ("sample", "view", d), per_shard,
                                       {"long_name": f"True where {d} holds data in the view "
                                                     "(False: padding)"})
            masks[f"n_{d}"] = _create_stacked(root, f"n_{d}", (n, plan.views), np.int64,
                                              ("sample", "view"), per_shard,
                                              {"long_name": f"number of {d} of the view"})
            continue
        masks[d] = _create_stacked(root, f"{d}_mask", (n, plan.padded[d]), bool, ("sample", d),
                                   per_shard, {"long_name": f"True where {d} holds data "
                                               "(False: padding)"})
        masks[f"n_{d}"] = _create_stacked(root, f"n_{d}", (n,), np.int64, rows_dims, per_shard,
                                          {"long_name": f"number of {d} of the sample"})
    n_vox = max((len(v["shape"]) for v in plan.voxels if v), default=0)
    centres = {}
    for ax in "xyz"[:n_vox]:
        if ax in plan.padded:
            centres[ax] = _create_stacked(root, f"voxel_centre_{ax}", (n, plan.padded[ax]),
                                          np.float64, ("sample", ax), per_shard,
                                          {"units": "m", "long_name": f"voxel centre {ax}"})
    cameras = _create_cameras(root, plan, per_shard) if plan.views > 1 else {}
    coords = {"sample": (str, "instance id (scene name)"), "family": (str, "scene family"),
              "split": (str, "split (train, val, test; 'all' outside a family)"),
              "index": (np.int64, "instance index within its split"),
              "seed": (np.uint64, "the instance's recorded seed"),
              "sample_revision": (str, "first 16 hex digits of the sha256 of the sample's "
                                       "manifest.json")}
    for c, (dtype, desc) in coords.items():
        a = root.create_array(c, shape=(n,), dtype=dtype, chunks=(n,),
                              dimension_names=["sample"])
        a.attrs["long_name"] = desc
        a[:] = np.array([r[c] for r in rows], dtype=dtype if dtype is not str else object)
    root.attrs.update({"format": STACKED_FORMAT, "format_version": STACKED_VERSION,
                       "vvtbench": __version__, "samples_per_shard": per_shard,
                       "coordinates": " ".join(c for c in coords if c != "sample")})
    total_sample = sum(per_sample.values()) or 1
    block = max(1, min(per_shard, WRITE_BUFFER_BYTES // total_sample))
    # a block never straddles two shards: each shard is written whole, or in aligned blocks
    block = per_shard // -(-per_shard // block)
    for start in range(0, n, block):
        stop = min(n, start + block)
        bufs = {p: np.full((stop - start, *plan.shape(p)), _pad_value(plan.dtypes[p]),
                           dtype=plan.dtypes[p]) for p in plan.shapes}
        for i in range(start, stop):
            truth = zarr.open_group(str(samples[i] / "truth.zarr"), mode="r")
            for p in plan.shapes:
                if p in plan.view_paths:
                    for v in range(plan.n_views[i]):
                        data = truth[p if v == 0 else f"views/{v}/{p}"][...]
                        bufs[p][(i - start, v, *(slice(0, k) for k in data.shape))] = data
                    continue
                data = truth[p][...]
                bufs[p][(i - start, *(slice(0, k) for k in data.shape))] = data
        for p, a in arrays.items():
            a[start:stop] = bufs[p]
        del bufs
        for d in plan.varying:
            if d in plan.view_dims:
                counts = np.array(plan.view_sizes[d][start:stop], dtype=np.int64)
                masks[f"n_{d}"][start:stop] = counts
                masks[d][start:stop] = np.arange(plan.padded[d]) < counts[..., None]
                continue
            counts = np.array(plan.dim_sizes[d][start:stop], dtype=np.int64)
            masks[f"n_{d}"][start:stop] = counts
            masks[d][start:stop] = np.arange(plan.padded[d])[None, :] < counts[:, None]
        _write_cameras(cameras, plan, start, stop)
        for ax, a in centres.items():
            k = "xyz".index(ax)
            vals = np.full((stop - start, plan.padded[ax]), np.nan)
            for i in range(start, stop):
                v = plan.voxels[i]
                if v and k < len(v["shape"]):
                    m = int(v["shape"][k])
                    vals[i - start, :m] = v["origin"][k] + (np.arange(m) + 0.5) * (
                        v["size"][k] / m)
            a[start:stop] = vals
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "consolidated metadata is not in the v3 spec"
        zarr.consolidate_metadata(str(store))
    return {"samples_per_shard": per_shard, "shards": n_shards,
            "variables": {_variable(p): {"dims": ["sample", *plan.dims[p]],
                                         "shape": [n, *plan.shape(p)],
                                         "dtype": str(plan.dtypes[p]),
                                         "units": _truth_units(p, drum)}
                          for p in plan.shapes} | {
                              name: {"dims": ["sample", *dims], "shape": [n, *shape],
                                     "dtype": str(np.dtype(dtype)), "units": unit}
                              for name, (shape, dtype, dims, unit, _) in
                              _camera_variables(plan).items()},
            "varying": plan.varying, **({"views": plan.views} if plan.views > 1 else {})}


def _camera_variables(plan: _Plan) -> dict[str, tuple]:
    """The cameras of a store with views: name -> (shape without sample, dtype, dims, units,
    description)."""
    if plan.views <= 1:
        return {}
    v = plan.views
    return {
        "camera_K": ((v, 3, 3), np.float64, ("view", "K_row", "K_col"), "px",
                     "intrinsic matrix K of the view's camera (P = K[R|t])"),
        "camera_R": ((v, 3, 3), np.float64, ("view", "R_row", "R_col"), "1",
                     "rotation R, world to camera"),
        "camera_t": ((v, 3), np.float64, ("view", "t_component"), "m",
                     "translation t, world to camera"),
        "camera_width": ((v,), np.int64, ("view",), "px", "frame width of the view"),
        "camera_height": ((v,), np.int64, ("view",), "px", "frame height of the view"),
        "view_time_offset": ((v,), np.float64, ("view",), "s",
                             "time by which the view films later than view 0"),
    }


def _create_cameras(root, plan: _Plan, per_shard: int) -> dict[str, Any]:
    n = len(plan.n_views)
    return {name: _create_stacked(root, name, (n, *shape), dtype, ("sample", *dims), per_shard,
                                  {"units": unit, "long_name": desc, "padding": "NaN (floats), "
                                   "-1 (integers) for a view the sample does not have"})
            for name, (shape, dtype, dims, unit, desc) in _camera_variables(plan).items()}


def _write_cameras(arrays: dict[str, Any], plan: _Plan, start: int, stop: int) -> None:
    if not arrays:
        return
    specs = _camera_variables(plan)
    bufs = {name: np.full((stop - start, *shape), _pad_value(np.dtype(dtype)), dtype=dtype)
            for name, (shape, dtype, *_) in specs.items()}
    for i in range(start, stop):
        for v, (camera, offset) in enumerate(plan.cameras[i]):
            bufs["camera_K"][i - start, v] = camera["K"]
            bufs["camera_R"][i - start, v] = camera["R"]
            bufs["camera_t"][i - start, v] = np.ravel(camera["t"])
            bufs["camera_width"][i - start, v] = camera["width"]
            bufs["camera_height"][i - start, v] = camera["height"]
            bufs["view_time_offset"][i - start, v] = offset
    for name, a in arrays.items():
        a[start:stop] = bufs[name]


def _index_frame(rows: list[dict]):
    """The instance index as a pandas DataFrame; a column mixing numbers and text is text."""
    import pandas as pd

    frame = pd.DataFrame(rows)
    for col in frame.columns:
        if frame[col].dtype != object:
            continue
        values = [v for v in frame[col] if v is not None and v == v]
        if values and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                          for v in values):
            frame[col] = frame[col].astype(float)
        elif not all(isinstance(v, str) for v in values):
            frame[col] = [None if v is None or v != v else str(v) for v in frame[col]]
    if "seed" in frame:
        frame["seed"] = frame["seed"].astype(np.uint64)
    return frame


def pack_stacked(samples: list[Path], out: str | Path, source: str = "", *,
                 shard_bytes: int = DEFAULT_SHARD_BYTES, overwrite: bool = False,
                 inputs: list[Path] | tuple = ()) -> Path:
    """Write ``samples`` as one Zarr v3 store per family and split with a ``sample`` dimension.

    Layout of the output folder::

        <family>/<split>.zarr   truth arrays stacked on ``sample`` and padded to the split's
                                largest instance (``<dim>_mask``, ``n_<dim>`` where sizes vary);
                                coordinates sample (instance id), family, split, index, seed,
                                sample_revision; sharded along ``sample`` (Zarr v3 sharding
                                codec), every shard file at most ``shard_bytes``
        index.parquet           one row per instance: ids, seed, store, row, shard and every
                                drawn scene parameter
        README.md, croissant.json (Croissant 1.1), dataset.json, SHA256SUMS

    Video and extracted modes are not part of this layout (:func:`pack` keeps them). Writing
    follows :func:`pack`: checked output path, the folder lock, a temporary sibling renamed at
    the end, ``overwrite`` only of a dataset written by this module. Raises
    :class:`ExportError` with nothing written on bad input.
    """
    from .card import stacked_card
    from .croissant import stacked_croissant

    samples = [Path(s) for s in samples]
    if not samples:
        raise ExportError("no samples to export")
    if int(shard_bytes) < 1:
        raise ExportError(f"--shard-size {shard_bytes}: allowed: a positive number of bytes")
    out = check_output(out, [*samples, *map(Path, inputs)], "zarr", overwrite)
    for s in samples:
        verify_sample(s)
    rows = [_instance(s, i) for i, s in enumerate(samples)]
    seen: dict[tuple, Path] = {}
    for s, r in zip(samples, rows, strict=True):
        key = (r["family"], r["split"], r["sample"])
        if key in seen:
            raise ExportError(f"{s}: instance {r['sample']} of {r['family']}/{r['split']} is "
                              f"also {seen[key]}; export each instance once")
        seen[key] = s
    tag = f"partial-{os.getpid()}"
    partial = out.with_name(f".{out.name}.{tag}")
    if partial.exists() or partial.is_symlink():
        raise ExportError(f"{partial}: a temporary path of this export already exists; remove "
                          "it (left by an interrupted export)")
    out.parent.mkdir(parents=True, exist_ok=True)
    try:
        check_free_space(out.parent, estimate_bytes(samples, {}, "zarr"),
                         f"the stacked export of {len(samples)} sample(s)")
    except NoSpaceError as error:
        raise ExportError(str(error)) from None
    from ..io.lock import RunLock, RunLocked

    try:
        lock = RunLock(out.parent, name=f".{out.name}.lock", remove=True).acquire()
    except RunLocked as error:
        raise ExportError(f"{out}: another export is writing it ({error})") from None
    try:
        _check_replaceable(out, "zarr", overwrite)
        partial.mkdir()
        try:
            _stacked_locked(samples, rows, partial, out, source or "samples", int(shard_bytes),
                            stacked_card, stacked_croissant)
            _replace(partial, out)
        except BaseException:
            shutil.rmtree(partial, ignore_errors=True)
            raise
        return out
    except OSError as error:
        if not is_disk_full(error):
            raise
        raise _disk_full(out, error) from None
    finally:
        lock.release()


def _safe_name(text: str, what: str, sample: Path) -> str:
    if not text or text in (".", "..") or "/" in text or "\\" in text or text.startswith("."):
        raise ExportError(f"{sample / 'family.json'}: {what} {text!r} cannot name a folder; "
                          "allowed: a name without '/' that does not start with '.'")
    return text


def _stacked_locked(samples, rows, partial: Path, out: Path, source: str, shard_bytes: int,
                    card_fn, croissant_fn) -> None:
    from ..io.files import write_json, write_text
    from .release import file_sums, write_sums

    groups: dict[tuple[str, str], list[int]] = {}
    for i, r in enumerate(rows):
        key = (_safe_name(r["family"], "family", samples[i]),
               _safe_name(r["split"], "split", samples[i]))
        groups.setdefault(key, []).append(i)
    stores = {}
    for (family, split), members in sorted(groups.items()):
        rel = f"{family}/{split}.zarr"
        (partial / family).mkdir(exist_ok=True)
        drum = scene_parameters(samples[members[0]]).get("scene.geometry.kind") == "drum"
        info = _write_store(partial / rel, [samples[i] for i in members],
                            [rows[i] for i in members], shard_bytes, drum)
        stores[rel] = {"family": family, "split": split, "samples": len(members), **info}
        for row, i in enumerate(members):
            rows[i].update({"store": rel, "row": row, "shard": row // info["samples_per_shard"]})
    table = [{**r, **scene_parameters(s)} for s, r in zip(samples, rows, strict=True)]
    frame = _index_frame(table)
    tmp = partial / f".{INDEX}.tmp"
    frame.to_parquet(tmp, index=False)
    os.replace(tmp, partial / INDEX)
    write_json(partial / STACKED_MARKER, {"format": STACKED_FORMAT,
                                          "format_version": STACKED_VERSION,
                                          "vvtbench": __version__, "source": source,
                                          "shard_bytes": shard_bytes, "stores": stores},
               indent=1, sort_keys=True)
    card = card_fn(frame, stores, source, shard_bytes)
    write_text(partial / "README.md", card)
    meta = croissant_fn(out.name, partial, frame, stores, source)
    write_text(partial / "croissant.json", json.dumps(meta, indent=2) + "\n")
    write_sums(file_sums(partial, exclude=(SUMS,)), partial / SUMS)
