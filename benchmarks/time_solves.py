"""Wall and CPU time of ``sensitivity`` against ``vvt`` on a run's own problems.

    .venv/bin/python benchmarks/time_solves.py runs/paper/results.parquet            # 20 modes
    .venv/bin/python benchmarks/time_solves.py runs/paper/results.parquet --modes 14

Re-solves, one at a time in this process with the machine's BLAS threads, the problems that the
run's ``modes`` track solved with ``--modes`` modes (true modes and video: the observe folders
in the run's cache), each with both solvers at their default configs, and prints wall and
process CPU seconds and NC w of each solve, with the machine's load average. Issue 16's budget
is 30 s wall per solve for an 8^3 grid with 20 modes on 2 cores; run it on an otherwise idle
machine. Writes nothing.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

from oracle_gaps import solve_and_observe_keys

from solvers.sensitivity import SensitivityConfig, SensitivitySolver
from solvers.vvt import VVTConfig, VVTSolver
from vvtbench.bench import read_results
from vvtbench.bench.stages import load_observation
from vvtbench.scoring.metrics import normalized_correlation


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("results")
    ap.add_argument("--modes", type=int, default=20)
    ap.add_argument("--track", default="modes")
    ap.add_argument("--scene", help="only this scene")
    ap.add_argument("--observation", choices=("true", "extracted"), help="only this source")
    args = ap.parse_args()
    df = read_results(args.results)
    cache = Path(args.results).parent / "cache"
    rows = df[(df.track == args.track) & (df.n_modes == args.modes) & df.estimate_path.notna()]
    rows = rows.drop_duplicates(["scene", "observation"])
    for key in ("scene", "observation"):
        if getattr(args, key):
            rows = rows[rows[key] == getattr(args, key)]
    from threadpoolctl import threadpool_info

    blas = sorted({p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"})
    print(f"{len(rows)} problems; {os.cpu_count()} cores; the process's BLAS threads: {blas} "
          "(sensitivity pins one during its solve)")
    print("| scene | observation | solver | wall s | CPU s | NC w | load (1 min) |")
    print("|---|---|---|---|---|---|---|")
    for _, row in rows.sort_values(["scene", "observation"]).iterrows():
        problem, truth = load_observation(
            cache, solve_and_observe_keys(cache, row.estimate_path)[1], truth=True)
        for name, solver in (("sensitivity", SensitivitySolver(SensitivityConfig())),
                             ("vvt", VVTSolver(VVTConfig()))):
            w0, c0 = time.perf_counter(), time.process_time()
            est = solver.solve(problem)
            wall, cpu = time.perf_counter() - w0, time.process_time() - c0
            nc = normalized_correlation(est.w, truth.w)
            print(f"| {row.scene} | {row.observation} | {name} | {wall:.1f} | {cpu:.1f} | "
                  f"{nc:.3f} | {os.getloadavg()[0]:.2f} |", flush=True)


if __name__ == "__main__":
    main()
