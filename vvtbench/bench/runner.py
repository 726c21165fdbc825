"""``run_suite``: the composition of the stages over a suite."""

from __future__ import annotations

import os
import time
from pathlib import Path

from .._version import __version__
from ..io import write_json
from .executors import execute_graph, make_executor
from .graph import STAGES, build_graph
from .results import results_table, write_results
from .suite import Suite, load_suite


def run_suite(suite: Suite | str | Path, solvers: list[str] | None = None,
              out_dir: str | Path = "runs", workers: int = 1, scheduler=None, *,
              solver_config: dict | None = None, progress: bool = True,
              until: str = "evaluate", threads: int | None = None):
    """Run a suite; return the results table (a pandas DataFrame).

    ``solvers``: names or ``path/file.py:Class`` (default: the suite's ``solvers``);
    ``solver_config``: ``{solver: {key: value}}`` overrides on top of the suite's
    ``[solver.NAME]`` tables; ``workers`` local processes; ``scheduler``: a Dask scheduler
    address (or a ``distributed.Client``) to run on instead; ``until``: last stage to run.
    ``df.attrs["stats"]`` holds, per stage, the number of tasks computed, found in the cache,
    failed and skipped. Writes ``OUT/results.parquet``, ``OUT/results.csv`` and ``OUT/run.json``.
    """
    if not isinstance(suite, Suite):
        suite = load_suite(suite)
    solvers = list(suite.solvers if solvers is None else solvers)
    out_dir = Path(out_dir)
    cache = out_dir / "cache"
    cache.mkdir(parents=True, exist_ok=True)
    tasks, runs = build_graph(suite, solvers, solver_config, until)
    if threads is None and workers > 1 and scheduler is None:
        threads = max(1, (os.cpu_count() or 1) // workers)
    executor = make_executor(workers, scheduler)
    t0 = time.perf_counter()
    try:
        results = execute_graph(tasks, cache, executor, progress, threads)
    finally:
        executor.close()
    wall = time.perf_counter() - t0
    stats = {s: {"tasks": 0, "computed": 0, "cached": 0, "failed": 0, "skipped": 0}
             for s in STAGES}
    for k, r in results.items():
        st = stats[tasks[k].stage]
        st["tasks"] += 1
        if r["status"] == "error":
            st["failed"] += 1
        elif r["status"] == "skipped":
            st["skipped"] += 1
        elif r["computed"]:
            st["computed"] += 1
        else:
            st["cached"] += 1
    df = results_table(runs, results) if until == "evaluate" else None
    if df is not None:
        write_results(df, out_dir)
        df.attrs["stats"] = stats
        df.attrs["wall_s"] = wall
    write_json(out_dir / "run.json", {
        "suite": suite.name, "suite_source": suite.source, "solvers": solvers,
        "vvtbench": __version__, "workers": workers,
        "scheduler": scheduler if isinstance(scheduler, str) else (None if scheduler is None
                                                                    else "client"),
        "wall_s": wall, "stats": stats, "n_runs": len(runs),
        "generated_samples": sorted(k for k in tasks if k.startswith("generate/")
                                    and results.get(k, {}).get("status") == "ok"),
    })
    if df is None:
        return {"stats": stats, "wall_s": wall, "results": results, "tasks": tasks}
    return df
