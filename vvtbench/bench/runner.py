"""``run_suite``: the composition of the stages over a suite."""

from __future__ import annotations

import json
import os
import shutil
import sys
import time
from pathlib import Path

from .._version import __version__
from ..io.files import write_json
from ..io.lock import RunLock
from .child import DEFAULT_TIMEOUT, default_memory_bytes
from .compact import MODES_KEPT
from .executors import Interrupted, execute_graph, make_executor
from .graph import STAGES, Run, build_graph
from .prune import VideoPlan
from .results import read_results, results_table, write_results
from .shards import (
    Shard,
    ShardError,
    ShardSpec,
    default_shard_dir,
    export_shard,
    read_shard,
    seed_cache,
    select_shard,
    shard_meta,
)
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
              wait: bool = False, prune_videos: bool = False,
              shard: str | ShardSpec | None = None, shard_dir: str | Path | None = None,
              retry_errors: bool = False, shard_modes: str = "exact"):
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

    The table replaces the one in ``OUT`` but keeps that table's rows of solvers this run
    does not name when they are current (:func:`add_previous_rows`): a run of one new solver
    adds its rows to the table of a run of the others (``df.attrs["kept"]``).

    ``shard="K/N"``: run only shard K of the N shards of the suite (:mod:`.shards`: whole
    instances, the same on every machine) and write its result set to ``shard_dir`` (default
    ``shards/SUITE/K-of-N``) instead of ``OUT/results.*``; the cache of ``OUT`` is seeded
    from a result set found there. A shard that is complete is not run again (unless
    ``retry_errors`` and it has failed tasks): ``df.attrs["shard"]["nothing_to_do"]``.
    ``shard_modes``: how the result set keeps the extracted mode shapes
    (:func:`.compact.extraction_box`): ``"exact"`` (every score as from the whole frame) or
    ``"footprint"`` (smaller; lossy for joined views, docs/suites.md).
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
    selection = found = None
    if shard is not None:
        if until != "evaluate":
            raise SuiteError(f"shard with until={until!r} is not allowed (allowed: until "
                             "'evaluate': a shard's result set is its rows)")
        if shard_modes not in MODES_KEPT:
            raise ShardError(f"shard_modes={shard_modes!r} is not allowed (allowed: "
                             f"{', '.join(MODES_KEPT)})")
        spec = ShardSpec.parse(shard)
        selection = select_shard(tasks, runs, spec)
        tasks, runs = selection.tasks, selection.runs
        shard_dir = Path(shard_dir) if shard_dir is not None else default_shard_dir(suite, spec)
        found = _found_shard(shard_dir, suite, spec)
        if found is not None and found.complete and set(found.tasks) == set(tasks) and not (
                retry_errors and found.meta["counts"].get("tasks_failed")):
            df = found.rows
            df.attrs["shard"] = {"spec": str(spec), "dir": str(shard_dir),
                                 "nothing_to_do": True, "meta": found.meta}
            df.attrs["stats"] = {}
            return df
    out_dir.mkdir(parents=True, exist_ok=True)
    lock = RunLock(out_dir, wait=wait,
                   on_wait=lambda msg: print(msg, file=sys.stderr, flush=True))
    with lock:
        cache = out_dir / "cache"
        cache.mkdir(parents=True, exist_ok=True)
        _remove_stale_temporaries(cache)
        if threads is None and workers > 1 and scheduler is None:
            threads = max(1, (os.cpu_count() or 1) // workers)
        seeded = None
        if found is not None and set(found.tasks) & set(tasks):
            seeded = seed_cache(cache, tasks, [found])
        videos = VideoPlan.build(tasks, cache, prune=prune_videos)
        executor = make_executor(workers, scheduler)
        t0 = time.perf_counter()
        try:
            results = execute_graph(tasks, cache, executor, progress, threads, limits,
                                    videos=videos)
        except Interrupted:
            if selection is not None:  # what is finished is kept in the shard's folder
                _write_shard(shard_dir, cache, selection, suite, solvers, solver_config,
                             limits, modes=shard_modes)
            raise
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
        shard_doc = None
        if selection is not None:
            shard_doc = _write_shard(shard_dir, cache, selection, suite, solvers,
                                     solver_config, limits, results, modes=shard_modes)
        elif df is not None:
            df, kept = add_previous_rows(out_dir, df, runs, suite)
            df.attrs["kept"] = kept
            write_table(df, out_dir)
        if df is not None:
            df.attrs["stats"] = stats
            df.attrs["wall_s"] = wall
            df.attrs["recomputed"] = recomputed
            df.attrs["pruned"] = dict(videos.freed) if prune_videos else None
            df.attrs["rerendered"] = list(videos.rerendered)
            df.attrs["prune_errors"] = list(videos.errors)
            if len(df) == 0:
                df.attrs["no_rows"] = no_rows_reason(suite, solvers)
            if shard_doc is not None:
                df.attrs["shard"] = {"spec": str(selection.spec), "dir": str(shard_dir),
                                     "nothing_to_do": False, "meta": shard_doc,
                                     "seeded": seeded}
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
            **({"shard": {"spec": str(selection.spec), "dir": str(shard_dir),
                          "rows": len(runs), "seeded": seeded}} if selection else {}),
        })
    if df is None:
        return {"stats": stats, "wall_s": wall, "results": results, "tasks": tasks,
                "recomputed": recomputed, "rerendered": videos.rerendered}
    return df


def _found_shard(shard_dir: Path, suite: Suite, spec: ShardSpec) -> Shard | None:
    """The result set already in ``shard_dir`` (None when there is none); one of another
    suite or shard is refused rather than replaced."""
    if not (shard_dir / "shard.json").is_file():
        if shard_dir.exists() and (not shard_dir.is_dir() or any(shard_dir.iterdir())):
            raise ShardError(f"{shard_dir}: exists and is not a shard folder (no shard.json); "
                             "give an empty or new folder (--shard-dir)")
        return None
    found = read_shard(shard_dir)
    if found.meta["suite"]["name"] != suite.name or found.spec != spec:
        raise ShardError(f"{shard_dir}: holds shard {found.spec} of suite "
                         f"{found.meta['suite']['name']!r}, not shard {spec} of {suite.name!r}; "
                         "give another folder (--shard-dir)")
    return found


def _write_shard(shard_dir: Path, cache: Path, selection, suite: Suite, solvers: list[str],
                 solver_config: dict | None, limits: dict, results: dict | None = None,
                 modes: str = "exact") -> dict:
    """The shard's result set, written under a lock of its own (one writer per folder)."""
    from .shards import cache_statuses

    statuses = cache_statuses(cache, selection.tasks)
    for k, r in (results or {}).items():  # this run's word on what failed or was skipped
        if r.get("status") in ("error", "skipped") and statuses.get(k, {}).get(
                "status") != "ok":
            statuses[k] = r
    meta = shard_meta(suite, solvers, selection.runs, solver_config or {}, limits)
    shard_dir.parent.mkdir(parents=True, exist_ok=True)
    with RunLock(shard_dir.parent, name=f".{shard_dir.name}.lock", remove=True):
        return export_shard(shard_dir, cache, selection, meta, statuses, modes)


def _instance(row) -> tuple:
    return (row["track"], row["scene"], int(row["seed"]), row["observation"],
            row["dataset_revision"])


def add_previous_rows(out_dir: Path, df, runs: list[Run], suite: Suite):
    """``df`` with the rows of the table already in ``out_dir`` (written by a run of the same
    suite file, ``run.json``) whose solvers ``df`` does not hold, when they are current: by
    this vvtbench, on an instance this suite still has (same samples), and (scored rows)
    whose evaluation is in the cache and scores an observation this run made. Returns
    ``(table, {"kept": {solver: n}, "dropped": {solver: n}})``; rows of one instance stay
    together, the solvers already there first. The table of another suite is replaced."""
    import pandas as pd

    kept: dict[str, int] = {}
    dropped: dict[str, int] = {}
    path = Path(out_dir) / "results.parquet"
    if not path.is_file() or len(df) == 0 or not _same_suite(Path(out_dir), suite):
        return df, {"kept": kept, "dropped": dropped}
    try:
        old = read_results(path)
    except Exception:  # noqa: BLE001 -- an unreadable table is replaced, as before
        return df, {"kept": kept, "dropped": dropped}
    if "solver" not in old.columns or len(old) == 0:
        return df, {"kept": kept, "dropped": dropped}
    now = set(df["solver"])
    others = old[~old["solver"].isin(now)]
    if others.empty:
        return df, {"kept": kept, "dropped": dropped}
    position: dict[tuple, int] = {}
    for i, r in enumerate(runs):
        position.setdefault((r.track, r.scene, int(r.seed), r.observation,
                             r.dataset_revision), i)
    observed = {r.observe_key for r in runs}
    keep = []
    for i, row in others.iterrows():
        ok = row.get("vvtbench_version") == __version__ and _instance(row) in position
        if ok and row["status"] in ("ok", "invalid"):
            ok = _evaluation_current(Path(out_dir), row.get("estimate_path"), observed)
        (kept if ok else dropped)[row["solver"]] = (kept if ok else dropped).get(
            row["solver"], 0) + 1
        if ok:
            keep.append(i)
    if not keep:
        return df, {"kept": kept, "dropped": dropped}
    both = pd.concat([others.loc[keep], df], ignore_index=True)
    order = sorted(range(len(both)), key=lambda j: (position.get(_instance(both.iloc[j]),
                                                                 len(runs)), j))
    both = both.iloc[order].reset_index(drop=True)
    for c in df.columns:  # the dtypes of a fresh table
        if str(both[c].dtype) != str(df[c].dtype):
            try:
                both[c] = both[c].astype(df[c].dtype)
            except (TypeError, ValueError):
                pass
    both = both[list(df.columns)]
    return both, {"kept": kept, "dropped": dropped}


def _same_suite(out_dir: Path, suite: Suite) -> bool:
    """The run folder's last run (``run.json``) ran the suite file ``suite`` came from."""
    try:
        last = json.loads((out_dir / "run.json").read_text())
        return (last.get("suite") == suite.name and Path(str(last.get("suite_source"))).resolve()
                == Path(suite.source).resolve())
    except (OSError, ValueError, AttributeError, TypeError):
        return False


def _evaluation_current(run_dir: Path, path, observed: set) -> bool:
    """A scored row's evaluation is in the cache, intact, and scores one of ``observed``."""
    from .stages import verify_cached

    if not isinstance(path, str) or not path.startswith("cache/evaluate/"):
        return False
    folder = run_dir / Path(path).parent
    try:
        info = json.loads((folder / "task.json").read_text())
        deps = info["deps"]
    except (OSError, ValueError, KeyError, TypeError):
        return False
    return len(deps) == 2 and deps[1] in observed and verify_cached(folder, info) is None


def write_table(df, out_dir: Path) -> None:
    """``OUT/results.parquet`` and ``OUT/results.csv``."""
    write_results(df, out_dir)
