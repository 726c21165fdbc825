"""Benchmark-runner figures: a suite's wall time with 1 and 2 local workers, the
speed-up, and the cache-hit rerun time as a fraction of the first run.

    .venv/bin/python benchmarks/bench_runner.py [--suite smoke] [--keep DIR]

Each configuration runs into a fresh folder (nothing cached), then reruns into the same folder
(everything cached). Prints one line per run and the ratios; ``--json`` writes them too.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import tempfile
import time
from pathlib import Path

from vvtbench.bench import run_suite


def _timed(suite: str, out: Path, workers: int) -> tuple[float, dict]:
    t0 = time.perf_counter()
    df = run_suite(suite, out_dir=out, workers=workers, progress=False)
    elapsed = time.perf_counter() - t0
    errors = int((df["status"] != "ok").sum())
    return elapsed, {"rows": len(df), "errors": errors, "stats": df.attrs.get("stats", {})}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--suite", default="smoke")
    p.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    p.add_argument("--keep", default=None, help="keep the run folders under this directory")
    p.add_argument("--json", default=None, help="also write the figures to this file")
    a = p.parse_args()
    root = Path(a.keep) if a.keep else Path(tempfile.mkdtemp(prefix="vvt_bench_runner_"))
    print(f"suite {a.suite}; {os.cpu_count()} cores; load average "
          f"{os.getloadavg()[0]:.1f}; {platform.processor() or platform.machine()}", flush=True)
    res: dict = {"suite": a.suite, "cores": os.cpu_count()}
    try:
        for workers in a.workers:
            out = root / f"w{workers}"
            shutil.rmtree(out, ignore_errors=True)
            first, info = _timed(a.suite, out, workers)
            rerun, info2 = _timed(a.suite, out, workers)
            res[f"workers_{workers}"] = {"first_s": first, "rerun_s": rerun, **info}
            print(f"workers {workers}: first run {first:.1f} s ({info['rows']} rows, "
                  f"{info['errors']} errors); cached rerun {rerun:.2f} s = "
                  f"{100 * rerun / first:.1f} % of the first (goal < 5 %)", flush=True)
        if 1 in a.workers and 2 in a.workers:
            s = res["workers_1"]["first_s"] / res["workers_2"]["first_s"]
            res["speedup_1_to_2"] = s
            print(f"speed-up 1 -> 2 workers: {s:.2f}x", flush=True)
    finally:
        if not a.keep:
            shutil.rmtree(root, ignore_errors=True)
    if a.json:
        Path(a.json).write_text(json.dumps(res, indent=2, default=str))


if __name__ == "__main__":
    main()
