"""``vvtbench run`` (a suite through every stage, cached) and ``vvtbench check-results``."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ..bench import SuiteError, check_results, load_suite, read_results, run_suite


def main_check_results(argv: list[str] | None = None) -> int:
    """``vvtbench check-results FILE``: exit 0 when valid, 1 with the problems listed."""
    p = argparse.ArgumentParser(prog="vvtbench check-results",
                                description="validate a results table (docs/results.md)")
    p.add_argument("file", help="results .parquet or .csv (or a run folder)")
    args = p.parse_args(argv)
    problems = check_results(args.file)
    if problems:
        print(f"{args.file}: {len(problems)} problem(s)", file=sys.stderr)
        for msg in problems:
            print(f"  {msg}", file=sys.stderr)
        return 1
    df = read_results(args.file)
    print(f"{args.file}: valid ({len(df)} rows, {df['solver'].nunique()} solver(s))")
    return 0


def _parse_set(items: list[str]) -> dict[str, dict]:
    out: dict[str, dict] = {}
    for item in items:
        key, sep, value = item.partition("=")
        solver, dot, opt = key.partition(".")
        if not sep or not dot:
            raise SuiteError(f"--set {item!r}: expected SOLVER.KEY=VALUE (e.g. vvt.max_iter=5)")
        try:
            val = json.loads(value)
        except ValueError:
            val = value
        out.setdefault(solver, {})[opt] = val
    return out


def format_table(df) -> str:
    cols = ["track", "scene", "variation", "seed", "observation", "solver", "n_modes_observed",
            "nc_w", "nc_v", "sigma_star_w", "mode_mac", "runtime_s", "status"]
    view = df[[c for c in cols if c in df.columns]].copy()
    with_err = df["status"] != "ok"
    text = view.to_string(index=False, float_format=lambda x: f"{x:.3f}")
    if with_err.any():
        text += "\n\nerrors:\n" + "\n".join(
            f"  {r.solver} on {r.scene} [{r.variation}, {r.observation}]: {r.error}"
            for r in df[with_err].itertuples())
    return text


def main_run(argv: list[str] | None = None) -> int:
    """``vvtbench run SUITE [--solvers a,b] [--workers N] [--scheduler ADDR] -o DIR``."""
    p = argparse.ArgumentParser(prog="vvtbench run", description=(
        "run a benchmark suite: generate -> extract -> solve -> evaluate, cached"))
    p.add_argument("suite", help="suite name (scenes/suites/NAME.toml) or file")
    p.add_argument("--solvers", default=None,
                   help="comma-separated solver names or path/file.py:Class "
                        "(default: the suite's list)")
    p.add_argument("--set", dest="overrides", action="append", default=[],
                   metavar="SOLVER.KEY=VALUE", help="solver config override (repeatable)")
    p.add_argument("--workers", type=int, default=1, help="local worker processes (1)")
    p.add_argument("--scheduler", default=None,
                   help="address of a Dask distributed scheduler, e.g. tcp://host:8786")
    p.add_argument("-o", "--output", default=None, help="run folder (default runs/SUITE)")
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    try:
        suite = load_suite(args.suite)
        solvers = None if args.solvers is None else [s for s in args.solvers.split(",") if s]
        overrides = _parse_set(args.overrides)
    except SuiteError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    out = Path(args.output or f"runs/{suite.name}")
    df = run_suite(suite, solvers, out, workers=args.workers, scheduler=args.scheduler,
                   solver_config=overrides, progress=not args.no_progress)
    print(format_table(df))
    st = df.attrs.get("stats", {})
    summary = ", ".join(f"{s} {v['computed']} new/{v['cached']} cached"
                        + (f"/{v['failed']} failed" if v["failed"] else "")
                        for s, v in st.items() if v["tasks"])
    print(f"\n{len(df)} rows in {df.attrs.get('wall_s', 0):.1f} s ({summary}) -> "
          f"{out / 'results.parquet'}, {out / 'results.csv'}")
    return 0
