"""``run_suite``: the composition of the stages over a suite."""

from __future__ import annotations

import os
import shutil
import sys
import time
from pathlib import Path

from .._version import __version__
from ..io.files import write_json
from ..io.lock import RunLock
from .child import DEFAULT_TIMEOUT, default_memory_bytes
from .executors import execute_graph, make_executor
from .graph import STAGES, build_graph
from .prune import VideoPlan
from .results import results_table, write_results
from .suite import Suite, SuiteError, load_suite


def _remove_stale_temporaries(cache: Path) -> int:
    """Half-written task folders of an earlier, killed run (we hold the lock: nobody else
    writes here)."""
    n = 0
    for stage in STAGES:
        d = cache / stage
        if not d.is_dir():
            continue
        for p in d.iterdir():
            if ".tmp-" in p.name and p.is_dir():
                shutil.rmtree(p, ignore_errors=True)
                n += 1
    return n


def no_rows_reason(suite: Suite, solvers: list[str]) -> str:
    """Why a suite and solver list give no row."""
    if not solvers:
        return "no solvers: the suite lists none and none were given (--solvers)"
    picky = [t for t in suite.tracks if t.solvers is not None]
    if picky and len(picky) == len(suite.tracks):
        allowed = sorted({s for t in picky for s in t.solvers})
        return (f"no track runs any of the solvers {', '.join(solvers)}; the tracks allow "
                f"only {', '.join(allowed)}")
    return "the suite expands to no run"


def run_suite(suite: Suite | str | Path, solvers: list[str] | None = None,
              out_dir: str | Path = "runs", workers: int = 1, scheduler=None, *,
              solver_config: dict | None = None, progress: bool = True,
              until: str = "evaluate", threads: int | None = None,
              timeout: float | None = None, memory_gb: float | None = None,
              wait: bool = False, prune_videos: bool = False):
    """Run a suite; return the results table (a pandas DataFrame).

    ``solvers``: names or ``path/file.py:Class`` (default: the suite's ``solvers``);
    ``solver_config``: ``{solver: {key: value}}`` overrides on top of the suite's
    ``[solver.NAME]`` tables; ``workers`` local processes; ``scheduler``: a Dask scheduler
    address (or a ``distributed.Client``) to run on instead; ``until``: last stage to run.

    Every solve runs in a sealed child process (:mod:`vvtbench.solving.sealed`) limited to
    ``timeout`` seconds (default: the suite's ``timeout``, else 3600) and ``memory_gb`` of
    address space (default: the suite's ``memory_gb``, else 75 % of the machine's memory /
    workers). The run folder is
    locked for the run: a second run on it raises :class:`~vvtbench.io.lock.RunLocked`
    (or waits, ``wait=True``). Ctrl-C raises :class:`~vvtbench.bench.executors.Interrupted`.

    ``df.attrs["stats"]`` holds, per stage, the number of tasks computed, found in the cache,
    failed and skipped; ``df.attrs["recomputed"]`` the cached outputs found damaged and
    recomputed (``[(task key, label, reason)]``). Writes ``OUT/results.parquet``,
    ``OUT/results.csv`` and ``OUT/run.json``.

    ``prune_videos``: delete each sample's video files from the cache as soon as every task
    reading them is done (:mod:`.prune`); ``df.attrs["pruned"]`` says how many samples,
    files and bytes. With or without it, a sample whose pruned video a task needs again is
    rendered again and its videos checked against the recorded sha256
    (``df.attrs["rerendered"]``).
    """
    if prune_videos and until not in ("observe", "evaluate"):
        raise SuiteError(f"prune_videos with until={until!r} is not allowed (allowed: until "
                         "'observe' or 'evaluate'): the observe tasks read the videos too, so "
                         "pruning before them renders every sample again later")
    if not isinstance(suite, Suite):
        suite = load_suite(suite)
    solvers = list(suite.solvers if solvers is None else solvers)
    out_dir = Path(out_dir)
    if timeout is None:
        timeout = suite.timeout if suite.timeout is not None else DEFAULT_TIMEOUT
    if memory_gb is None:
        memory_gb = suite.memory_gb
    memory_bytes = (int(memory_gb * 2**30) if memory_gb is not None
                    else default_memory_bytes(workers if scheduler is None else 1))
    limits = {"timeout": float(timeout), "memory_bytes": memory_bytes}
    tasks, runs = build_graph(suite, solvers, solver_config, until, timeout=float(timeout))
    out_dir.mkdir(parents=True, exist_ok=True)
    lock = RunLock(out_dir, wait=wait,
                   on_wait=lambda msg: print(msg, file=sys.stderr, flush=True))
    with lock:
        cache = out_dir / "cache"
        cache.mkdir(parents=True, exist_ok=True)
        _remove_stale_temporaries(cache)
        if threads is None and workers > 1 and scheduler is None:
            threads = max(1, (os.cpu_count() or 1) // workers)
        videos = VideoPlan.build(tasks, cache, prune=prune_videos)
        executor = make_executor(workers, scheduler)
        t0 = time.perf_counter()
        try:
            results = execute_graph(tasks, cache, executor, progress, threads, limits,
                                    videos=videos)
        finally:
            executor.close()
        wall = time.perf_counter() - t0
        stats = {s: {"tasks": 0, "computed": 0, "cached": 0, "failed": 0, "skipped": 0,
                     "recomputed": 0} for s in STAGES}
        recomputed = []
        for k, r in results.items():
            st = stats[tasks[k].stage]
            st["tasks"] += 1
            if r.get("recomputed"):
                st["recomputed"] += 1
                recomputed.append((k, tasks[k].label, r["recomputed"]))
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
            df.attrs["recomputed"] = recomputed
            df.attrs["pruned"] = dict(videos.freed) if prune_videos else None
            df.attrs["rerendered"] = list(videos.rerendered)
            df.attrs["prune_errors"] = list(videos.errors)
            if len(df) == 0:
                df.attrs["no_rows"] = no_rows_reason(suite, solvers)
        write_json(out_dir / "run.json", {
            "suite": suite.name, "suite_source": suite.source, "solvers": solvers,
            "tracks": [t.name for t in suite.tracks],
            "vvtbench": __version__, "workers": workers, "threads_per_task": threads,
            "scheduler": scheduler if isinstance(scheduler, str) else (
                None if scheduler is None else "client"),
            "timeout_s": limits["timeout"], "memory_limit_bytes": memory_bytes,
            "wall_s": wall, "stats": stats, "n_runs": len(runs),
            "recomputed": [{"task": k, "label": lab, "reason": why}
                           for k, lab, why in recomputed],
            "generated_samples": sorted(k for k in tasks if k.startswith("generate/")
                                        and results.get(k, {}).get("status") == "ok"),
            "prune_videos": prune_videos,
            "pruned": dict(videos.freed) if prune_videos else None,
            "rerendered": videos.rerendered, "prune_errors": videos.errors,
        })
    if df is None:
        return {"stats": stats, "wall_s": wall, "results": results, "tasks": tasks,
                "recomputed": recomputed, "rerendered": videos.rerendered}
    return df
