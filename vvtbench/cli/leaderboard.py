"""``vvtbench leaderboard``: Markdown + static HTML leaderboard of a results table."""

from __future__ import annotations

import argparse
import sys

from ..reporting.leaderboard import build


def main_leaderboard(argv: list[str] | None = None) -> int:
    """``vvtbench leaderboard RESULTS [-o leaderboard] [--overwrite] [--keep-figures]``."""
    p = argparse.ArgumentParser(prog="vvtbench leaderboard",
                                description="Markdown + static HTML leaderboard of a results "
                                            "table")
    p.add_argument("results", help="results.parquet/.csv, or a run folder")
    p.add_argument("-o", "--output", default="leaderboard",
                   help="output folder: new, empty, or one an earlier `vvtbench leaderboard` "
                        "wrote (its leaderboard.json lists its files)")
    p.add_argument("--overwrite", action="store_true",
                   help="write into a folder that also holds other files: replace only the "
                        "leaderboard's own files (README.md, index.html, results.csv, "
                        "leaderboard.json, figures/*.png) and keep the others")
    p.add_argument("--keep-figures", action="store_true",
                   help="keep (and show, marked as kept) the figures an earlier build of the "
                        "output folder drew from run caches that are not beside this table")
    args = p.parse_args(argv)
    try:
        out = build(args.results, args.output, overwrite=args.overwrite,
                    keep_figures=args.keep_figures)
    except (OSError, ValueError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    print(f"leaderboard -> {out / 'README.md'}, {out / 'index.html'}")
    return 0
