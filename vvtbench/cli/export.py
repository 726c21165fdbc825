"""``vvtbench export``: pack generated samples (a folder, a run folder, or a suite, generated
first) into one Zarr or HDF5 dataset with a dataset card and a Croissant file."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from vvtbench.datasets.export import (
    DEFAULT_SHARD_BYTES,
    check_output,
    find_samples,
    pack,
    pack_stacked,
)
from vvtbench.datasets.packed import ExportError
from vvtbench.samples.reader import DatasetError


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    p = parser or argparse.ArgumentParser(prog="vvtbench export")
    p.description = (
        "pack generated samples (a sample folder, a folder of samples such as a run folder, "
        "or a suite, whose samples are generated first) into one Zarr or HDF5 dataset with a "
        "dataset card and a Croissant JSON-LD file; extracted modes found in a run folder are "
        "included")
    p.add_argument("source", help="sample folder, folder of samples / run folder, or suite")
    p.add_argument("-o", "--output", required=True, type=Path,
                   help="output .zarr folder or .h5 file (must not exist; see --overwrite)")
    p.add_argument("--format", choices=("zarr", "hdf5"), default=None,
                   help="default: hdf5 for an output ending in .h5/.hdf5/.nc, else zarr")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the output if it is a dataset written by vvtbench export "
                        "(never another file or folder)")
    p.add_argument("--layout", choices=("samples", "stacked"), default="samples",
                   help="samples: one group per sample with video and extracted modes (read by "
                        "vvtbench.datasets.packed); stacked: one Zarr store per family and "
                        "split with a "
                        "'sample' dimension (xarray.open_zarr), a Parquet index and Croissant "
                        "1.1 (truth arrays only)")
    p.add_argument("--shard-size", default=str(DEFAULT_SHARD_BYTES), metavar="BYTES",
                   help="stacked layout: largest shard file, in bytes or with a unit (500MB, "
                        "20GB; default 20GB)")
    p.add_argument("--run-dir", default=None, type=Path,
                   help="where a suite's samples are generated (default runs/SUITE)")
    return p


_UNITS = {"": 1, "B": 1, "KB": 10**3, "MB": 10**6, "GB": 10**9, "TB": 10**12,
          "KIB": 2**10, "MIB": 2**20, "GIB": 2**30, "TIB": 2**40}


def parse_size(text: str) -> int:
    """Bytes of a size such as ``20GB``, ``500MiB`` or ``4096``."""
    t = text.strip().upper().replace(" ", "")
    digits = t.rstrip("KMGTIB")
    unit = t[len(digits):]
    try:
        value = float(digits) * _UNITS[unit]
    except (ValueError, KeyError):
        raise ExportError(f"--shard-size {text!r}: allowed: a number of bytes with an optional "
                          "unit B, KB, MB, GB, TB, KiB, MiB, GiB, TiB") from None
    if not value >= 1:
        raise ExportError(f"--shard-size {text!r}: allowed: at least 1 byte")
    return int(value)


def _format(args: argparse.Namespace) -> str:
    if args.format:
        return args.format
    return "hdf5" if args.output.suffix.lower() in (".h5", ".hdf5", ".nc") else "zarr"


def _suite_samples(suite_path: Path, run_dir: Path) -> list[Path]:
    """Generate a suite's samples into ``run_dir`` (cached) and return their folders."""
    from vvtbench.bench import run_suite

    run_suite(str(suite_path), [], run_dir, until="generate", progress=sys.stderr.isatty())
    info = json.loads((run_dir / "run.json").read_text())
    return [run_dir / "cache" / k / "sample" for k in info["generated_samples"]]


def main(argv: list[str] | None = None) -> int:
    """Exit code: 0 written, 2 refused or bad input (one line on stderr)."""
    args = build_parser().parse_args(argv)
    src = Path(args.source)
    fmt = _format(args)
    try:
        if args.layout == "stacked" and fmt != "zarr":
            raise ExportError(f"{args.output}: the stacked layout is written as Zarr stores; "
                              "allowed: --format zarr (an output not ending in .h5/.hdf5/.nc)")
        shard_bytes = parse_size(args.shard_size)
        if src.is_dir():
            samples = find_samples(src)
            inputs = [src]
        else:
            from vvtbench.bench import find_suite

            suite_path = find_suite(args.source)
            run_dir = args.run_dir or Path("runs") / suite_path.stem
            inputs = [run_dir]
            # refuse an unsafe output before spending time on generating
            check_output(args.output, inputs, fmt, args.overwrite)
            samples = _suite_samples(suite_path, run_dir)
        if not samples:
            raise ExportError(f"{src}: no generated samples found")
        if args.layout == "stacked":
            out = pack_stacked(samples, args.output, str(args.source), shard_bytes=shard_bytes,
                               overwrite=args.overwrite, inputs=inputs)
        else:
            out = pack(samples, args.output, fmt, str(args.source), overwrite=args.overwrite,
                       inputs=inputs)
    except (ValueError, OSError, DatasetError) as error:  # Export/Suite/SceneError: ValueError
        from .args import explain

        print(f"error: {explain(error)}", file=sys.stderr)
        return 2
    print(f"{len(samples)} sample(s) -> {out}")
    if args.layout == "stacked" and any(
            json.loads((s / "truth.json").read_text())["video"].get("file") for s in samples):
        print("note: the stacked layout holds the truth arrays; video and extracted modes are "
              "in --layout samples only", file=sys.stderr)
    return 0

