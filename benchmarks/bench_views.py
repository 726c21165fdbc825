"""What a second camera buys, from true modes: NC w against the number of views on family
instances, with the fraction of DOFs observed and paired differences against one view.

Every instance is observed with 1..N cameras on a ring (``observe(views=N)``), every solver
runs sealed on each problem, and the table gives the mean NC w with its 95 % bootstrap
interval per solver and view count, and the paired difference against one view.

    python benchmarks/bench_views.py --family cube_defects --split test --n 12 \\
        --views 1 2 3 4 --solvers sensitivity vvt --modes 20

or, from the cache of a `vvtbench run` of a views track (finished or not: every cached solve
is scored against its observation's truth; from video, the last column is the median cost per
instance: the views' extractions, the observation and the solve, in seconds):

    python benchmarks/bench_views.py --cache runs/views/cache --solvers sensitivity vvt oracle
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def main(argv: list[str] | None = None) -> int:
    from vvtbench.cli import main as cli
    from vvtbench.datasets.export import find_samples
    from vvtbench.observe import observe
    from vvtbench.samples.reader import open_sample
    from vvtbench.scoring.metrics import evaluate, invalid_reason
    from vvtbench.solving.sealed import solve_sealed

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--family", default="cube_defects")
    p.add_argument("--split", default="test")
    p.add_argument("--n", type=int, default=12)
    p.add_argument("--views", type=int, nargs="+", default=[1, 2, 3, 4])
    p.add_argument("--solvers", nargs="+", default=["sensitivity"])
    p.add_argument("--set", action="append", default=[], metavar="SOLVER.KEY=VALUE")
    p.add_argument("--modes", type=int, default=20)
    p.add_argument("--samples", type=Path, default=None,
                   help="a folder of generated samples of the split (default: generated now)")
    p.add_argument("--json", type=Path, default=None, help="write the rows here")
    p.add_argument("--cache", type=Path, default=None,
                   help="score the cached solves of a `vvtbench run views` instead")
    args = p.parse_args(argv)
    if args.cache is not None:
        rows = rows_from_cache(args.cache)
        args.views = sorted({r["views"] for r in rows})
        table(rows, args, f"{len({r['instance'] for r in rows})} instances from {args.cache}")
        return 0
    config: dict[str, dict] = {}
    for item in args.set:
        key, _, value = item.partition("=")
        solver, _, opt = key.partition(".")
        config.setdefault(solver, {})[opt] = json.loads(value)
    folder = args.samples
    if folder is None:
        folder = Path(tempfile.mkdtemp(prefix="views-")) / args.split
        if cli(["generate", args.family, "--split", args.split, "--n", str(args.n),
                "--no-video", "-o", str(folder), "--no-progress"]) != 0:
            return 1
    samples = find_samples(folder)[: args.n]
    rows = []
    t0 = time.perf_counter()
    for path in samples:
        sample = open_sample(path)
        for views in args.views:
            problem, truth = observe(sample, n_modes=args.modes, views=views)
            for solver in args.solvers:
                est, wall, _ = solve_sealed(solver, config.get(solver, {}), problem,
                                            truth=truth, timeout=1800)
                reason = invalid_reason(est.w, est.v, problem.n_params)
                nc = float("nan") if reason else float(
                    evaluate(problem, truth, est.w, est.v, modes=False)["metrics"]["nc_w"]
                    or float("nan"))
                rows.append({"instance": path.name, "views": views, "solver": solver,
                             "nc_w": nc, "invalid": reason, "wall_s": wall,
                             "dof_fraction": problem.meta["observed_dof_fraction"]})
                print(f"{path.name} views={views} {solver}: NC w {nc:.3f} "
                      f"({problem.meta['observed_dof_fraction']:.3f} of DOFs, {wall:.1f} s)"
                      + (f" invalid: {reason}" if reason else ""), flush=True)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    table(rows, args, f"{len(samples)} instances of {args.family} {args.split}, {args.modes} "
          f"true modes, {time.perf_counter() - t0:.0f} s")
    return 0


def rows_from_cache(cache: Path) -> list[dict]:
    """One row per cached solve of a views run: its NC w against its observation's truth."""
    from vvtbench.bench.stages import load_estimate_arrays, load_observation
    from vvtbench.scoring.metrics import invalid_reason, is_constant, normalized_correlation

    rows = []
    for task in sorted((cache / "solve").glob("*/task.json")):
        info = json.loads(task.read_text())
        observe_key = info["deps"][0]
        observe = json.loads((cache / observe_key / "task.json").read_text())
        inference = observe["payload"]["inference"]
        extracts = [json.loads((cache / k / "task.json").read_text()).get("seconds", np.nan)
                    for k in observe["deps"][1:]]
        problem, truth = load_observation(cache, observe_key, truth=True)
        w, v, _ = load_estimate_arrays(task.parent / "estimate.npz")
        reason = invalid_reason(w, v, problem.n_params)
        rows.append({"instance": truth.meta["scene"], "views": inference.get("views", 1),
                     "solver": info["payload"]["solver"], "invalid": reason,
                     "nc_w": float("nan") if reason or is_constant(truth.w)
                     else normalized_correlation(w, truth.w),  # no defect: NC undefined
                     "dof_fraction": problem.meta["observed_dof_fraction"],
                     "cost_s": float(sum(extracts) + observe.get("seconds", np.nan)
                                     + info.get("seconds", np.nan))})
    return rows


def table(rows: list[dict], args, title: str) -> None:
    from vvtbench.scoring.stats import paired_comparison, summarize, win_rate_text

    print(f"\n{title}\n")
    cost = all("cost_s" in r for r in rows)
    print("| family | solver | views | DOFs observed | mean NC w [95 % CI] | scored | paired vs "
          "1 view [95 % CI] | win rate |" + (" s per instance |" if cost else ""))
    print("|---|---|---|---|---|---|---|---|" + ("---|" if cost else ""))
    families = sorted({r["instance"].rsplit("-", 2)[0] for r in rows})
    for family, solver in ((f, s) for f in families for s in args.solvers):
        mine = [r for r in rows if r["instance"].startswith(family) and r["solver"] == solver]
        base = {r["instance"]: r["nc_w"] for r in mine if r["views"] == args.views[0]}
        for views in args.views:
            sel = [r for r in mine if r["views"] == views and r["instance"] in base]
            if not sel:
                continue
            nc = [r["nc_w"] for r in sel]
            s = summarize(nc)
            frac = np.mean([r["dof_fraction"] for r in sel])
            valid = sum(np.isfinite(nc))
            paired = "--"
            win = "--"
            if views != args.views[0]:
                a = [r["nc_w"] for r in sel]
                b = [base[r["instance"]] for r in sel]
                c = paired_comparison(a, b)
                paired = (f"{c['mean_diff']:+.3f} [{c['ci_low']:+.3f}, {c['ci_high']:+.3f}] "
                          f"(n {c['n']})")
                win = win_rate_text(c["win_rate"], c["ties"], c["n"])
            print(f"| {family} | {solver} | {views} | {frac:.3f} | {s['mean']:.3f} "
                  f"[{s['mean_ci_low']:.3f}, {s['mean_ci_high']:.3f}] | {valid}/{len(sel)} | "
                  f"{paired} | {win} |"
                  + (f" {np.median([r['cost_s'] for r in sel]):.0f} |" if cost else ""))


if __name__ == "__main__":
    sys.exit(main())
