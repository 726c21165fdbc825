"""``vvtbench leaderboard``: Markdown + static HTML leaderboard of a results table."""

from __future__ import annotations

import argparse
import sys

from ..leaderboard import build


def main_leaderboard(argv: list[str] | None = None) -> int:
    """``vvtbench leaderboard RESULTS [-o leaderboard]``."""
    p = argparse.ArgumentParser(prog="vvtbench leaderboard",
                                description="Markdown + static HTML leaderboard of a results "
                                            "table")
    p.add_argument("results", help="results.parquet/.csv, or a run folder")
    p.add_argument("-o", "--output", default="leaderboard", help="output folder")
    args = p.parse_args(argv)
    try:
        out = build(args.results, args.output)
    except (OSError, ValueError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    print(f"leaderboard -> {out / 'README.md'}, {out / 'index.html'}")
    return 0
