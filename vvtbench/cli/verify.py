"""``vvtbench verify PATH``: check a sample folder, a run folder or an exported dataset.

* a sample folder (``manifest.json``): every file against the manifest's sha256 and size,
  files not listed, the video's frames counted and its frame size and pixel format against
  ``truth.json`` (:meth:`vvtbench.samples.reader.Sample.verify`), the scene and camera readable;
* a run folder (``cache/``): every generated sample (``cache/generate/*/sample``) as above,
  and every cached task whose ``task.json`` records the sha256 of its outputs (a ``files``,
  ``outputs`` or ``sha256`` table of relative path -> sha256 or ``{"sha256": ...}``);
* an exported dataset (``vvtbench export``: a Zarr folder or an HDF5 file): every file
  against the sha256 recorded at export (a Zarr folder's ``SHA256SUMS``: every chunk and
  attribute file, none missing or extra; an HDF5 file's sha256 in its Croissant file), its
  format and version, every sample's attributes, truth arrays and video readable, shapes as
  recorded;
* a run folder's results table is also re-scored: every score recomputed from the cached
  estimate and truth (:func:`vvtbench.bench.rescore.rescore`).

One line per problem on stdout, ``PATH: problem``; exit 0 when clean, 1 when problems were
found, 2 when PATH is not one of the above.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np

__all__ = ["build_parser", "main_verify", "verify_path"]


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="vvtbench verify",
        description="check a sample folder, a run folder or an exported dataset against its "
        "recorded sha256, sizes and shapes; one line per problem; exit 0 clean, 1 problems "
        "found, 2 bad input")
    p.add_argument("path", type=Path, help="sample folder, run folder, or exported dataset "
                   "(.zarr folder or .h5 file)")
    p.add_argument("--quick", action="store_true",
                   help="samples: the checks done on every open only (truth files and arrays "
                   "hashed; the video's size and probed frame count, not its hash)")
    return p


def _kind(path: Path) -> str:
    if path.is_dir():
        if (path / "manifest.json").is_file():
            return "sample"
        if (path / "cache").is_dir():
            return "run"
        if (path / "zarr.json").is_file() or (path / ".zgroup").is_file():
            return "dataset"
        if (path / "dataset.json").is_file():
            return "stacked"
        raise ValueError(f"{path}: not a sample folder (no manifest.json), a run folder (no "
                         "cache/) or an exported dataset (no zarr.json, no dataset.json)")
    if path.is_file():
        with open(path, "rb") as f:
            if f.read(8) == b"\x89HDF\r\n\x1a\n":
                return "dataset"
        raise ValueError(f"{path}: a file, but not an exported HDF5 dataset; give a sample "
                         "folder, a run folder or an exported dataset")
    raise FileNotFoundError(2, "no such file or folder", str(path))


def verify_sample(path: Path, *, full: bool = True) -> list[str]:
    """Problems of a sample folder, each ``FILE: problem`` with FILE under ``path``."""
    from ..samples.reader import DatasetError, check_sample, read_json
    from ..scene.scene import SceneError, load_scene

    try:
        manifest = read_json(path / "manifest.json")
        info = read_json(path / "truth.json") if (path / "truth.json").is_file() else {}
    except DatasetError as error:
        return [str(error)]
    problems = [f"{path / line}" for line in check_sample(path, manifest, info, full=full)]
    if not info:
        problems.append(f"{path / 'truth.json'}: missing")
    if (path / "scene.toml").is_file():
        try:
            load_scene(path / "scene.toml")
        except SceneError as error:
            problems.append(str(error))
    return problems


def _task_hashes(doc: dict) -> dict[str, str] | None:
    for key in ("files", "outputs", "sha256"):
        table = doc.get(key)
        if isinstance(table, dict) and table:
            out = {}
            for rel, entry in table.items():
                digest = entry.get("sha256") if isinstance(entry, dict) else entry
                if isinstance(digest, str):
                    out[str(rel)] = digest
            if out:
                return out
    return None


def verify_run(path: Path, *, full: bool = True) -> Iterator[str]:
    """Problems of a run folder: its generated samples and its cached tasks' outputs."""
    from ..bench.prune import pruned_absent
    from ..samples.reader import sha256_file

    cache = path / "cache"
    samples = sorted(p for p in cache.glob("generate/*/sample") if p.is_dir())
    for sample in samples:  # a video pruned by `run --prune-videos` is absent on purpose
        gone = tuple(f"{sample.parent / n}: " for n in pruned_absent(sample.parent))
        yield from (p for p in verify_sample(sample, full=full) if not p.startswith(gone))
    for task_json in sorted(cache.glob("*/*/task.json")):
        task = task_json.parent
        try:
            doc = json.loads(task_json.read_text())
            if not isinstance(doc, dict):
                raise ValueError("not a JSON object")
        except (OSError, UnicodeDecodeError, ValueError) as error:
            yield f"{task_json}: unreadable ({error})"
            continue
        hashes = _task_hashes(doc)
        if not hashes:
            continue
        pruned = pruned_absent(task)
        for rel, digest in sorted(hashes.items()):
            p = task / rel
            if ".." in Path(rel).parts or Path(rel).is_absolute():
                yield f"{task_json}: output {rel!r} is not a path inside the task folder"
            elif rel in pruned:
                continue
            elif not p.is_file():
                yield f"{p}: missing (recorded in {task_json.name})"
            elif sha256_file(p) != digest:
                yield f"{p}: sha256 mismatch (recorded in {task_json.name})"
    if not samples and not any(cache.glob("*/*/task.json")):
        yield f"{path}: a run folder with no cached tasks"
    if (path / "results.parquet").is_file():
        from ..bench.rescore import rescore

        yield from (f"{path / 'results.parquet'}: {p}" for p in rescore(path))


def verify_dataset_files(path: Path) -> Iterator[str]:
    """Every file of an exported dataset against the sha256 recorded at export: a Zarr
    folder's ``SHA256SUMS`` (each chunk and attribute file; none missing, none extra), an HDF5
    file's sha256 in its Croissant file."""
    from ..datasets.export import SUMS
    from ..datasets.release import ReleaseError, read_sums, verify_copy
    from ..samples.reader import sha256_file

    if path.is_dir():
        if not (path / SUMS).is_file():
            yield f"{path / SUMS}: missing (written by an older vvtbench, or deleted): the " \
                  "dataset's files cannot be checked"
            return
        try:
            expected = read_sums(path / SUMS)
        except ReleaseError as error:
            yield str(error)
            return
        yield from (f"{path / line}" for line in verify_copy(path, expected, exclude=(SUMS,)))
        return
    side = path.with_name(path.name + ".croissant.json")
    try:
        doc = json.loads(side.read_text())
        recorded = next(d.get("sha256") for d in doc.get("distribution", [])
                        if d.get("contentUrl") == path.name)
    except (OSError, ValueError, StopIteration, AttributeError):
        yield f"{side}: missing or unreadable: the file's sha256 cannot be checked"
        return
    if sha256_file(path) != recorded:
        yield f"{path}: sha256 differs from the one recorded in {side.name} (changed or damaged)"


def verify_dataset(path: Path) -> Iterator[str]:
    """Problems of an exported dataset: every file's sha256, format, version, every sample
    readable."""
    from ..datasets.packed import FORMAT_VERSION, ExportError, open_dataset

    yield from verify_dataset_files(path)

    try:
        ds = open_dataset(path)
    except (ExportError, OSError, ValueError, KeyError) as error:
        yield f"{path}: cannot be opened as a vvtbench dataset ({error})"
        return
    with ds:
        version = ds.attrs.get("format_version")
        if version != FORMAT_VERSION:
            yield (f"{path}: format_version {version!r}, this vvtbench reads "
                   f"{FORMAT_VERSION}")
        names = ds.names
        group = ds.root["samples"] if "samples" in ds.root else None
        if group is None:
            yield f"{path}: no samples group"
            return
        for name in names:
            where = f"{path}:samples/{name}"
            if name not in group:
                yield f"{where}: listed in the dataset's samples attribute but missing"
                continue
            try:
                s = ds[name]
            except Exception as error:  # noqa: BLE001 -- any failure is the dataset's
                yield f"{where}: attributes unreadable ({type(error).__name__}: {error})"
                continue
            for array in s.truth_arrays:
                try:
                    s.array(array)[...]
                except Exception as error:  # noqa: BLE001
                    yield f"{where}/truth/{array}: unreadable ({type(error).__name__}: {error})"
            yield from _video_problems(s, where)
            for i in range(1, int(getattr(s, "n_views", 1))):
                try:
                    view = s.view(i)
                except Exception as error:  # noqa: BLE001
                    yield f"{where}/views/{i}: unreadable ({type(error).__name__}: {error})"
                    continue
                yield from _video_problems(view, f"{where}/views/{i}")


def _video_problems(s, where: str) -> Iterator[str]:
    """Problems of one packed view's video: its shape against its truth, every frame read."""
    if s.has_video:
        want = (s.n_frames, *s.shape)
        if tuple(s.video.shape) != want:
            yield (f"{where}/video: shape {tuple(s.video.shape)}, truth says "
                   f"{want} (frames, height, width)")
        try:
            for _ in s.frames():
                pass
        except Exception as error:  # noqa: BLE001
            yield f"{where}/video: unreadable ({type(error).__name__}: {error})"
    elif s.info.get("video", {}).get("file"):
        yield f"{where}: the sample was filmed but the dataset holds no video"


def verify_stacked(path: Path) -> Iterator[str]:
    """Problems of a stacked export (``--layout stacked``): every file's sha256, its marker's
    format and version, and every store it lists opened by xarray with every variable read
    (one shard at a time)."""
    from ..datasets.export import STACKED_FORMAT, STACKED_MARKER, STACKED_VERSION

    yield from verify_dataset_files(path)
    try:
        marker = json.loads((path / STACKED_MARKER).read_text())
        stores = dict(marker["stores"])
    except (OSError, ValueError, KeyError, TypeError) as error:
        yield f"{path / STACKED_MARKER}: unreadable ({type(error).__name__}: {error})"
        return
    if marker.get("format") != STACKED_FORMAT:
        yield f"{path / STACKED_MARKER}: format {marker.get('format')!r}, not {STACKED_FORMAT!r}"
        return
    if marker.get("format_version") != STACKED_VERSION:
        yield (f"{path / STACKED_MARKER}: format_version {marker.get('format_version')!r}, "
               f"this vvtbench reads {STACKED_VERSION}")
    import xarray as xr

    for rel, info in stores.items():
        where = path / rel
        try:
            ds = xr.open_zarr(where)
        except Exception as error:  # noqa: BLE001 -- any failure is the export's
            yield f"{where}: cannot be opened by xarray ({type(error).__name__}: {error})"
            continue
        with ds:
            n = ds.sizes.get("sample")
            if n != info.get("samples"):
                yield f"{where}: {n} samples, {STACKED_MARKER} lists {info.get('samples')}"
            for name, var in ds.variables.items():
                try:
                    if "sample" in var.dims:  # a few samples at a time: memory stays bounded
                        for i in range(0, var.sizes["sample"], 8):
                            np.asarray(var.isel(sample=slice(i, i + 8)))
                    else:
                        np.asarray(var)
                except Exception as error:  # noqa: BLE001
                    yield f"{where}/{name}: unreadable ({type(error).__name__}: {error})"


def verify_path(path: str | Path, *, full: bool = True) -> list[str]:
    """Every problem found under ``path`` (a sample, a run folder or an exported dataset),
    one line each; raises ``FileNotFoundError``/``ValueError`` when ``path`` is none of
    them."""
    path = Path(path)
    kind = _kind(path)
    if kind == "sample":
        return verify_sample(path, full=full)
    if kind == "run":
        return list(verify_run(path, full=full))
    if kind == "stacked":
        return list(verify_stacked(path))
    return list(verify_dataset(path))


def main_verify(argv: list[str] | None = None) -> int:
    """``vvtbench verify PATH``: exit 0 clean, 1 problems found, 2 bad input."""
    args = build_parser().parse_args(argv)
    kind = _kind(args.path)
    problems = verify_path(args.path, full=not args.quick)
    for line in problems:
        print(line.replace("\n", " "))
    if problems:
        print(f"{args.path}: {len(problems)} problem(s) in this {kind}", file=sys.stderr)
        return 1
    print(f"{args.path}: {kind} ok", file=sys.stderr)
    return 0
