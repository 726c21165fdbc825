"""``vvtbench merge-shards``: the N shards of a suite (:mod:`.shards`) into one run folder,
every score recomputed.

The shards must be the N complete shards of one partition of one suite file (same sha256), by
this vvtbench, with the same solvers, versions and configs; each must hold exactly the tasks the
suite's partition gives it. The merge builds the suite's graph, seeds the run folder's cache
with every estimate and extraction the shards carry (checked against their sha256), takes the
failures of the shards as they were (a solve is never run at a merge), regenerates every
sample (a filmed one without its frames when no task left needs its video), observes again
and scores every estimate again. The table is computed, not copied; where it differs from
what a shard stated, the merge says so.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from .._version import __version__
from ..io.files import write_json
from .graph import Run, Task
from .shards import (
    CARRIED,
    PARTITION,
    Shard,
    ShardError,
    partition,
    read_shard,
    seed_cache,
    suite_sha256,
    truth_digest,
)
from .suite import SuiteError

__all__ = ["check_assignment", "check_together", "compare_rows", "expand_dirs",
           "merge_shards"]


def expand_dirs(dirs: list[str | Path]) -> list[Path]:
    """Shard folders: each folder given, or the ``K-of-N`` folders inside one that is not a
    shard itself (``shards/SUITE``)."""
    out: list[Path] = []
    for d in map(Path, dirs):
        if (d / "shard.json").is_file():
            out.append(d)
        elif d.is_dir() and any((c / "shard.json").is_file() for c in d.iterdir()):
            out.extend(sorted((c for c in d.iterdir() if (c / "shard.json").is_file()),
                              key=lambda c: c.name))
        elif not d.exists():
            raise ShardError(f"{d}: no such shard folder")
        else:
            raise ShardError(f"{d}: not a shard folder (no shard.json) and holds none; shard "
                             "folders are written by `vvtbench run SUITE --shard K/N`")
    return out


def check_together(shards: list[Shard]) -> None:
    """Refuse shards that are not the N complete shards of one partition of one suite by this
    vvtbench with the same solvers; the message says which shard differs and in what."""
    if not shards:
        raise ShardError("no shard folders given")
    first = shards[0]

    def differ(what: str, get) -> None:
        for s in shards[1:]:
            if get(s) != get(first):
                raise ShardError(f"{s.path}: {what} {get(s)!r}, but {first.path} has "
                                 f"{get(first)!r}; shards merge only when they are cut from one "
                                 "run of one suite")

    differ("suite", lambda s: s.meta["suite"]["name"])
    differ("suite file sha256", lambda s: s.meta["suite"]["sha256"])
    differ("vvtbench version", lambda s: s.meta.get("vvtbench"))
    differ("partition rule", lambda s: s.meta["shard"].get("partition"))
    differ("number of shards N", lambda s: s.spec.n)
    differ("solvers", lambda s: sorted(s.solvers()))
    differ("solver versions and configs", lambda s: sorted(
        (x["name"], x["version"], x["config_hash"]) for x in s.meta.get("solvers") or []))
    differ("solver overrides (--set)", lambda s: s.meta.get("solver_config") or {})
    if first.meta.get("vvtbench") != __version__:
        raise ShardError(f"{first.path}: written by vvtbench {first.meta.get('vvtbench')}, this "
                         f"is {__version__}; merge with the version the shards were run with, "
                         "or run the shards again with this one")
    if first.meta["shard"].get("partition") != PARTITION:
        raise ShardError(f"{first.path}: partition rule {first.meta['shard'].get('partition')!r}"
                         f" is not this vvtbench's ({PARTITION!r})")
    n = first.spec.n
    by_k: dict[int, list[Shard]] = {}
    for s in shards:
        by_k.setdefault(s.spec.k, []).append(s)
    twice = {k: v for k, v in by_k.items() if len(v) > 1}
    if twice:
        k, v = sorted(twice.items())[0]
        folders = ", ".join(str(s.path) for s in v)
        raise ShardError(f"shard {k}/{n} given {len(v)} times ({folders}); give each shard "
                         "once")
    missing = [k for k in range(1, n + 1) if k not in by_k]
    if missing:
        raise ShardError(f"shard(s) {', '.join(f'{k}/{n}' for k in missing)} missing (have "
                         f"{', '.join(f'{k}/{n}' for k in sorted(by_k))}); a merge needs all "
                         f"{n} shards")
    for s in shards:
        if not s.complete:
            c = s.meta.get("counts") or {}
            raise ShardError(f"{s.path}: shard {s.spec} is not complete ({c.get('tasks_pending')} "
                             f"of {c.get('tasks')} tasks not finished); finish it with "
                             f"`vvtbench run {s.meta['suite']['ref']} --shard {s.spec}`")


def check_assignment(shards: list[Shard], tasks: dict[str, Task], runs: list[Run]) -> None:
    """No task is held by two shards, and each shard holds exactly the tasks this suite's
    partition gives it."""
    holder: dict[str, Shard] = {}
    for s in shards:
        for k in s.tasks:
            if k in holder:
                raise ShardError(f"shards {holder[k].spec} ({holder[k].path}) and {s.spec} "
                                 f"({s.path}) both hold task {k}: they overlap")
            holder[k] = s
    n = shards[0].spec.n
    parts = partition(tasks, runs, n)
    for s in shards:
        want = {k for u in parts[s.spec.k - 1] for k in u.tasks}
        have = set(s.tasks)
        if want != have:
            extra, lack = sorted(have - want), sorted(want - have)
            example = (extra or lack)[0]
            raise ShardError(
                f"{s.path}: shard {s.spec} holds {len(have)} tasks, this suite gives it "
                f"{len(want)} ({len(extra)} not its own, {len(lack)} lacking, e.g. {example}): "
                "the suite, a scene, a solver, its version or its config is not what the shard "
                "was run with")


def _injected(tasks: dict[str, Task], statuses: dict[str, dict]) -> dict[str, dict]:
    """The results the merge takes from the shards instead of computing: every generate,
    extract or solve task that failed or was skipped there, and every task downstream of
    one."""
    out: dict[str, dict] = {}
    for k, t in tasks.items():
        st = statuses.get(k) or {}
        if t.stage in ("generate", *CARRIED) and st.get("status") in ("error", "skipped"):
            rec = {"key": k, "status": st["status"], "computed": False, "seconds": 0.0,
                   "error": st.get("error", f"{t.stage}: failed")}
            if st.get("traceback"):
                rec["traceback"] = st["traceback"]
            if st.get("upstream"):
                rec["upstream"] = st["upstream"]
            out[k] = rec
            continue
        up = next((d for d in t.deps if d in out), None)
        if up is not None:
            src = out[up]
            out[k] = {"key": k, "status": "skipped", "computed": False, "seconds": 0.0,
                      "error": src.get("error", "upstream task failed"),
                      "upstream": src.get("upstream", up) if src["status"] == "skipped"
                      else up}
    return out


_ROW_KEY = ("track", "solver", "config_hash", "scene", "variation", "seed", "observation")


def compare_rows(merged, shards: list[Shard]) -> list[str]:
    """Where the recomputed table differs from what the shards stated: a row's status, the
    estimate it scored, or a score beyond the tolerance of ``check-results`` (the
    observation's bytes may differ: eigen-solves differ in their last bits between machines
    and thread counts; :func:`merge_shards` counts those apart)."""
    from .rescore import _same
    from .results import METRIC_COLUMNS

    index = {}  # each stated row, with the scores its shard states (an older one: fewer)
    for s in shards:
        cols = [c for c in METRIC_COLUMNS if c in s.rows.columns]
        index.update({tuple(r[c] for c in _ROW_KEY): (r, cols) for _, r in s.rows.iterrows()})
    out = []
    for i, row in merged.iterrows():
        key = tuple(row[c] for c in _ROW_KEY)
        old, cols = index.get(key, (None, ()))
        where = (f"row {i} ({row['solver']}, {row['scene']}, {row['variation']}, "
                 f"{row['observation']})")
        if old is None:
            out.append(f"{where}: no shard states it")
            continue
        if row["status"] != old["status"]:
            out.append(f"{where}: status {row['status']!r} recomputed, {old['status']!r} in the "
                       "shard")
            continue
        a, b = row.get("estimate_sha256"), old.get("estimate_sha256")
        if isinstance(a, str) and isinstance(b, str) and a != b:
            out.append(f"{where}: estimate_sha256 {a[:12]}... scored, {b[:12]}... in the shard")
        wrong = [c for c in cols if not _same(row[c], old.get(c))]
        if wrong:
            c = wrong[0]
            out.append(f"{where}: {len(wrong)} score(s) differ from the shard's, e.g. {c} "
                       f"{row[c]!r} recomputed, {old.get(c)!r} in the shard")
    return out


def merge_shards(dirs: list[str | Path], out_dir: str | Path, *, workers: int = 1,
                 scheduler=None, progress: bool = True, wait: bool = False,
                 suite: str | Path | None = None, threads: int | None = None):
    """Merge the shards in ``dirs`` into the run folder ``out_dir``: one results table,
    every score recomputed (module notes). Returns the table (a DataFrame); ``df.attrs``:
    ``"differences"`` (rows whose recomputed scores differ from the shards'), ``"truth"``
    (samples regenerated to the sha256 the shard recorded, and those that differ),
    ``"stats"``, ``"shards"``."""
    from ..io.lock import RunLock
    from .executors import execute_graph, make_executor
    from .graph import STAGES, build_graph
    from .prune import VideoPlan
    from .results import results_table
    from .runner import _remove_stale_temporaries, add_previous_rows, write_table
    from .stages import cached_state, observation_sha256
    from .suite import load_suite

    shards = [read_shard(d) for d in expand_dirs(list(dirs))]
    check_together(shards)
    first = shards[0].meta
    ref = suite if suite is not None else first["suite"]["ref"]
    try:
        the_suite = load_suite(ref)
    except SuiteError as error:
        raise ShardError(f"{error} (the shards were run on suite {first['suite']['name']!r}, "
                         f"file {first['suite']['file']}; give it with --suite FILE)") from None
    if suite_sha256(the_suite) != first["suite"]["sha256"]:
        raise ShardError(f"{the_suite.source}: sha256 {suite_sha256(the_suite)[:12]}... is not "
                         f"the one the shards were run on ({first['suite']['sha256'][:12]}...); "
                         "merge with the suite file they were run with (--suite FILE)")
    limits = {"timeout": float(first["limits"]["timeout_s"]),
              "memory_bytes": first["limits"]["memory_bytes"]}
    solvers = shards[0].solvers()
    tasks, runs = build_graph(the_suite, solvers, first.get("solver_config") or {},
                              timeout=limits["timeout"])
    check_assignment(shards, tasks, runs)
    statuses: dict[str, dict] = {}
    for s in shards:
        for k, rec in s.tasks.items():
            statuses[k] = {"key": k, **rec}
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    with RunLock(out_dir, wait=wait, on_wait=lambda m: print(m, file=sys.stderr, flush=True)):
        cache = out_dir / "cache"
        cache.mkdir(parents=True, exist_ok=True)
        _remove_stale_temporaries(cache)
        seeded = seed_cache(cache, tasks, shards, errors=True)
        injected = _injected(tasks, statuses)
        to_run = {k: t for k, t in tasks.items() if k not in injected}
        for k, t in to_run.items():  # never solve or extract at a merge
            if t.stage in CARRIED:
                info, why = cached_state(cache, t)
                if info is None or why is not None:
                    raise ShardError(f"{k} ({t.label}): the shard holding it carries no intact "
                                     f"output ({why or 'none'})")
        videos = VideoPlan.build(to_run, cache)
        executor = make_executor(workers, scheduler)
        t0 = time.perf_counter()
        try:
            results = execute_graph(to_run, cache, executor, progress, threads, limits,
                                    videos=videos)
        finally:
            executor.close()
        wall = time.perf_counter() - t0
        results.update(injected)
        df = results_table(runs, results)
        differences = compare_rows(df, shards)
        truth = {"samples": 0, "samples_same": 0, "samples_changed": [],
                 "observations": 0, "observations_same": 0, "observations_changed": []}
        for k, t in tasks.items():
            rec = statuses.get(k) or {}
            if results.get(k, {}).get("status") != "ok":
                continue
            if t.stage == "generate" and rec.get("truth_sha256"):
                info = json.loads((cache / k / "task.json").read_text())
                withheld = set(rec.get("videos") or {})
                same = truth_digest(info.get("files") or {}, withheld) == rec["truth_sha256"]
                truth["samples"] += 1
                truth["samples_same"] += same
                if not same:
                    truth["samples_changed"].append(f"{k} ({t.label})")
            elif t.stage == "observe" and rec.get("observation_sha256"):
                same = observation_sha256(cache / k) == rec["observation_sha256"]
                truth["observations"] += 1
                truth["observations_same"] += same
                if not same:
                    truth["observations_changed"].append(f"{k} ({t.label})")
        stats = {s: {"tasks": 0, "computed": 0, "cached": 0, "failed": 0, "from_shards": 0}
                 for s in STAGES}
        for k, r in results.items():
            st = stats[tasks[k].stage]
            st["tasks"] += 1
            if k in injected:
                st["from_shards"] += 1
            elif r["status"] == "error":
                st["failed"] += 1
            elif r.get("computed"):
                st["computed"] += 1
            else:
                st["cached"] += 1
        df, kept = add_previous_rows(out_dir, df, runs, the_suite)
        write_table(df, out_dir)
        write_json(out_dir / "run.json", {
            "suite": the_suite.name, "suite_source": the_suite.source, "solvers": solvers,
            "tracks": [t.name for t in the_suite.tracks], "vvtbench": __version__,
            "merged_from": [{"shard": str(s.spec), "folder": str(s.path),
                             "rows": len(s.rows)} for s in shards],
            "workers": workers, "scheduler": scheduler if isinstance(scheduler, str) else (
                None if scheduler is None else "client"),
            "wall_s": wall, "stats": stats, "n_runs": len(runs), "seeded": seeded,
            "differences": differences, "regenerated": truth})
    df.attrs.update(differences=differences, stats=stats, wall_s=wall, seeded=seeded,
                    truth=truth, kept=kept,
                    shards=[str(s.spec) for s in shards])
    return df
