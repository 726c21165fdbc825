"""``vvtbench run`` (a suite through every stage, cached, whole or in shards),
``vvtbench merge-shards`` and ``vvtbench check-results``."""

from __future__ import annotations

import argparse
import json
import math
import shlex
import sys
import textwrap
from pathlib import Path

from ..bench import SuiteError, check_results, load_suite, read_results, run_suite
from ..bench.rescore import has_cache, rescore
from ..bench.shards import ShardSpec
from ..solving.sealed import describe_sealed


def main_check_results(argv: list[str] | None = None) -> int:
    """``vvtbench check-results FILE``: exit 0 when valid, 1 with the problems listed."""
    p = argparse.ArgumentParser(prog="vvtbench check-results",
                                description="validate a results table (docs/results.md)")
    p.add_argument("file", help="results .parquet or .csv (or a run folder); with the run's "
                   "cache beside it every score is recomputed from the estimates and the truth")
    args = p.parse_args(argv)
    path = Path(args.file)
    if not path.exists():
        print(f"error: {path}: no such results file or run folder", file=sys.stderr)
        return 2
    problems = check_results(args.file)
    run_dir = has_cache(path)
    if not problems and run_dir is not None:
        df = read_results(args.file)
        problems = rescore(run_dir, df)
    if problems:
        print(f"{args.file}: {len(problems)} problem(s)", file=sys.stderr)
        for msg in problems:
            print(f"  {msg}", file=sys.stderr)
        return 1
    df = read_results(args.file)
    if run_dir is None:
        print(f"{args.file}: valid form ({len(df)} rows, {df['solver'].nunique()} solver(s)); "
              "scores NOT recomputed: no run cache beside the table (give the run folder, or "
              "score estimates with `vvtbench score`)")
    else:
        print(f"{args.file}: valid ({len(df)} rows, {df['solver'].nunique()} solver(s)); every "
              f"score recomputed from the estimates and the truth in {run_dir / 'cache'}")
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
    text = view.to_string(index=False, float_format=lambda x: f"{x:.3f}", na_rep="-")
    if with_err.any():
        text += "\n\nerrors:\n" + "\n".join(
            f"  {r.solver} on {r.scene} [{r.variation}, {r.observation}]: {r.error}"
            for r in df[with_err].itertuples())
    return text


LEGEND = (
    "columns: nc_w, nc_v = normalized correlation of the estimated and true stiffness and "
    "density per voxel (1 = the true pattern, 0 = none; '-' where the truth is constant: the "
    "false contrast is scored instead); sigma_star_w = the blur of the true stiffness, in "
    "voxels, at which the estimate matches it best (its resolution; '-' for a constant "
    "estimate); mode_mac = how well the estimate's own vibration modes match the observed ones "
    "(1 = exactly); runtime_s = solver seconds. Every formula: docs/metrics.md.")


def next_steps(out: Path, suite: str) -> str:
    """What to run after a suite: the board, the check, the docs."""
    q = shlex.quote(str(out))
    return (f"next: `vvtbench leaderboard {q} -o {q}/board` (ranked tables and figures), "
            f"`vvtbench check-results {q}` (every score recomputed), or run another suite "
            f"(`vvtbench run {suite} --solvers NAME,...`)")


def rerendered_lines(entries: list[dict]) -> list[str]:
    """One line per sample rendered again over its pruned videos: needed by what, and
    whether the new videos are the recorded ones."""
    out = []
    for e in entries:
        head = f"re-rendered {e['task']} ({e['label']}): {e['why']}"
        if e["same"]:
            out.append(f"{head}; the new video's sha256 is the recorded one")
        else:
            out.append(f"{head}; {e['file']} differs from the pruned one (sha256 "
                       f"{str(e['sha256_now'])[:12]}... against {e['sha256_recorded'][:12]}...): "
                       f"its {e['recomputed']} dependent cached task(s) are recomputed")
    return out


def _positive(what: str):
    def parse(text: str) -> float:
        try:
            x = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number ({what})") from None
        if not math.isfinite(x) or x <= 0:
            raise argparse.ArgumentTypeError(f"{text!r}: allowed: {what}")
        return x
    return parse


def _workers(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer >= 1") from None
    from vvtbench.bench.executors import max_workers

    if not 1 <= n <= max_workers():
        raise argparse.ArgumentTypeError(
            f"{text!r}: allowed: an integer from 1 to {max_workers()} (4 per CPU)")
    return n


def main_run(argv: list[str] | None = None) -> int:
    """``vvtbench run SUITE [--solvers a,b] [--workers N] [--scheduler ADDR] -o DIR``.

    Exit 0 when every row is ok; 1 when a row failed or is invalid, when there are no rows, or
    when the run folder is in use; 2 for bad input; 130 on Ctrl-C."""
    from ..bench.executors import Interrupted
    from ..io.lock import RunLocked
    from ..solving.plugins import PluginError

    p = argparse.ArgumentParser(prog="vvtbench run", description=(
        "run a benchmark suite: generate -> extract -> solve -> evaluate, cached; every solve "
        "in a child process with a time and a memory limit"))
    p.add_argument("suite", help="suite name (scenes/suites/NAME.toml) or file")
    p.add_argument("--solvers", default=None,
                   help="comma-separated solver names or path/file.py:Class "
                        "(default: the suite's list); the rows of other solvers already in "
                        "the run folder's table stay in it when they are current (same suite "
                        "file, vvtbench and instances), so a run of one more solver adds its "
                        "rows to the others'")
    p.add_argument("--set", dest="overrides", action="append", default=[],
                   metavar="SOLVER.KEY=VALUE", help="solver config override (repeatable)")
    p.add_argument("--workers", type=_workers, default=1, help="local worker processes (1)")
    p.add_argument("--scheduler", default=None,
                   help="address of a Dask distributed scheduler, e.g. tcp://host:8786")
    p.add_argument("-o", "--output", default=None, help="run folder (default runs/SUITE)")
    p.add_argument("--timeout", type=_positive("seconds > 0"), default=None,
                   help="time limit of one solve in seconds (default: the suite's `timeout`, "
                        "else 3600); a solve over it is an error row 'timeout'")
    p.add_argument("--memory-gb", type=_positive("GB > 0"), default=None,
                   help="memory limit of one solve (default: the suite's `memory_gb`, else "
                        "75%% of the machine's memory / workers)")
    p.add_argument("--wait", action="store_true",
                   help="if another run uses the folder, wait for it (default: refuse)")
    p.add_argument("--prune-videos", action="store_true",
                   help="delete each sample's video files from the run's cache as soon as every "
                        "task reading them is done (truth, previews and results are kept; a "
                        "rerun that needs a video again renders it again)")
    p.add_argument("--shard", default=None, metavar="K/N",
                   help="run only shard K of N (1 <= K <= N) of the suite: whole instances "
                        "(a video, its extractions and every solve of them in one shard), the "
                        "same on every machine and with any --workers or --scheduler; the "
                        "shard's rows, estimates and extracted modes go to --shard-dir, a "
                        "folder to commit; the run folder (-o) holds the cache. A complete "
                        "shard is not run again; an interrupted one resumes, from the cache "
                        "or from what its shard folder holds. Merge with `vvtbench "
                        "merge-shards`")
    p.add_argument("--shard-modes", default="exact", choices=["exact", "footprint"],
                   help="with --shard: how the result set keeps each extracted mode shape: "
                        "'exact' (default) only the pixels its readers read where that "
                        "changes no score, the whole frame for joined views; 'footprint' the "
                        "object's box for joined views too (smaller, lossy: scores of joined "
                        "views may change, docs/suites.md)")
    p.add_argument("--shard-dir", default=None, metavar="DIR",
                   help="where --shard writes its result set (default shards/SUITE/K-of-N); "
                        "videos and truth never go there")
    p.add_argument("--retry-errors", action="store_true",
                   help="with --shard: run the failed tasks of a complete shard again "
                        "(default: a complete shard is left as it is)")
    p.add_argument("--no-progress", action="store_true", help="no progress display")
    args = p.parse_args(argv)
    if args.shard is None and (args.shard_dir is not None or args.retry_errors
                               or args.shard_modes != "exact"):
        flag = ("--shard-dir" if args.shard_dir is not None else "--retry-errors"
                if args.retry_errors else "--shard-modes")
        print(f"error: {flag} needs --shard K/N", file=sys.stderr)
        return 2
    try:
        if args.shard is not None:
            ShardSpec.parse(args.shard)
        suite = load_suite(args.suite)
        solvers = None if args.solvers is None else [s for s in args.solvers.split(",") if s]
        overrides = _parse_set(args.overrides)
        for name, values in overrides.items():  # a bad --set is the user's, not error rows
            describe_sealed("solver", name, {**suite.solver_config.get(name, {}), **values})
    except (SuiteError, PluginError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    out = Path(args.output or f"runs/{suite.name}")
    try:
        df = run_suite(suite, solvers, out, workers=args.workers, scheduler=args.scheduler,
                       solver_config=overrides, progress=not args.no_progress,
                       timeout=args.timeout, memory_gb=args.memory_gb, wait=args.wait,
                       prune_videos=args.prune_videos, shard=args.shard,
                       shard_dir=args.shard_dir, retry_errors=args.retry_errors,
                       shard_modes=args.shard_modes)
    except Interrupted as stop:
        resume = f"vvtbench run {args.suite} -o {shlex.quote(str(out))}"
        if args.shard is not None:
            resume += f" --shard {args.shard}" + (
                f" --shard-dir {shlex.quote(args.shard_dir)}" if args.shard_dir else "")
        kept = (" and its finished work in the shard folder" if args.shard is not None
                else "")
        print(f"\ninterrupted: {stop.finished} of {stop.total} tasks finished (kept in "
              f"{out / 'cache'}{kept}); resume with `{resume}`: finished tasks are reused",
              file=sys.stderr)
        return 130
    except RunLocked as error:
        print(f"error: {error}", file=sys.stderr)
        return 1
    except (SuiteError, PluginError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    for key, label, why in df.attrs.get("recomputed", []):
        print(f"recomputed {key} ({label}): the cached output was damaged: {why}",
              file=sys.stderr)
    for line in rerendered_lines(df.attrs.get("rerendered", [])):
        print(line, file=sys.stderr)
    for line in df.attrs.get("prune_errors", []):
        print(f"warning: {line}", file=sys.stderr)
    if len(df) == 0:
        print(f"error: no rows: {df.attrs.get('no_rows', 'the suite expands to no run')}",
              file=sys.stderr)
        return 1
    if df.attrs.get("shard"):
        return _report_shard(df, args)
    kept = df.attrs.get("kept") or {}
    print(format_table(df))
    st = df.attrs.get("stats", {})
    summary = ", ".join(f"{s} {v['computed']} new/{v['cached']} cached"
                        + (f"/{v['failed']} failed" if v["failed"] else "")
                        + (f"/{v['recomputed']} recomputed" if v.get("recomputed") else "")
                        for s, v in st.items() if v["tasks"])
    pruned = df.attrs.get("pruned")
    freed = "" if pruned is None else (
        f"; videos of {pruned['samples']} sample(s) pruned, {pruned['bytes'] / 1e9:.3g} GB freed")
    print(f"\n{len(df)} rows in {df.attrs.get('wall_s', 0):.1f} s ({summary}) -> "
          f"{out / 'results.parquet'}, {out / 'results.csv'}{freed}")
    if kept.get("kept"):
        print(f"kept {sum(kept['kept'].values())} row(s) of {', '.join(sorted(kept['kept']))} "
              f"from the table already in {out} (current: same instances, evaluations in the "
              "cache); the table holds every solver's rows")
    if kept.get("dropped"):
        print(f"warning: dropped {sum(kept['dropped'].values())} row(s) of "
              f"{', '.join(sorted(kept['dropped']))} from the table already in {out}: not "
              "current (another vvtbench, an instance this suite no longer has, or an "
              f"evaluation not in the cache); run them again with `vvtbench run {args.suite} "
              f"--solvers {','.join(sorted(kept['dropped']))} -o {shlex.quote(str(out))}`",
              file=sys.stderr)
    print(textwrap.fill(LEGEND, 100))
    print(next_steps(out, args.suite))
    bad = df[df["status"] != "ok"]
    if len(bad):
        kinds = ", ".join(f"{n} {s}" for s, n in bad["status"].value_counts().items())
        print(f"error: {len(bad)} of {len(df)} rows not ok ({kinds}); see the errors above",
              file=sys.stderr)
        return 1
    return 0


def _human_bytes(n: float) -> str:
    for unit in ("B", "kB", "MB", "GB"):
        if n < 1000 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n} B"


def _report_shard(df, args) -> int:
    """What a shard run says: its rows, its folder and what to do next; exit 1 when a row
    failed."""
    from ..bench.shards import size_warning
    from ..io.files import tree_bytes

    info = df.attrs["shard"]
    meta, folder = info["meta"], info["dir"]
    c = meta.get("counts") or {}
    q = shlex.quote(folder)
    if info.get("nothing_to_do"):
        print(f"shard {info['spec']} of {meta['suite']['name']} is complete in {folder} "
              f"({c.get('rows')} rows, {c.get('tasks_failed', 0)} failed task(s)); nothing to "
              "do" + (" (--retry-errors runs its failed tasks again)"
                      if c.get("tasks_failed") else ""))
    else:
        print(format_table(df))
        st = df.attrs.get("stats", {})
        summary = ", ".join(f"{s} {v['computed']} new/{v['cached']} cached"
                            + (f"/{v['failed']} failed" if v["failed"] else "")
                            for s, v in st.items() if v["tasks"])
        seeded = info.get("seeded") or {}
        if any(seeded.values()):
            summary += (f"; from the shard folder: {seeded.get('solve', 0)} estimate(s), "
                        f"{seeded.get('extract', 0)} extraction(s), "
                        f"{seeded.get('without_frames', 0)} sample(s) without frames")
        print(f"\nshard {info['spec']}: {len(df)} rows in {df.attrs.get('wall_s', 0):.1f} s "
              f"({summary}) -> {folder} ({_human_bytes(tree_bytes(folder))}: rows, "
              "estimates, extracted modes, sha256; no video, no truth)")
        warning = size_warning(Path(folder), meta)
        if warning:
            print(f"{warning}; see docs/suites.md \"Running a suite in shards\" before "
                  "committing it", file=sys.stderr)
        print(f"next: `git add {q} && git commit -m 'shard {info['spec']} of "
              f"{meta['suite']['name']}'`; when all {meta['shard']['n']} shards are in, "
              f"`vvtbench merge-shards {shlex.quote(str(Path(folder).parent))} -o RUN_DIR` "
              "(every score recomputed)")
    bad = df[df["status"] != "ok"]
    if len(bad):
        kinds = ", ".join(f"{n} {s}" for s, n in bad["status"].value_counts().items())
        print(f"error: {len(bad)} of {len(df)} rows not ok ({kinds})", file=sys.stderr)
        return 1
    return 0


def main_merge_shards(argv: list[str] | None = None) -> int:
    """``vvtbench merge-shards DIR... -o RUN_DIR``: exit 0 when every row is ok and every
    recomputed score is the one the shards stated; 1 when a row failed or a score differs; 2
    for shards that do not make one run (which, and why, on one line)."""
    from ..bench.executors import Interrupted
    from ..bench.merge import merge_shards
    from ..io.lock import RunLocked
    from ..solving.plugins import PluginError

    p = argparse.ArgumentParser(prog="vvtbench merge-shards", description=(
        "merge the shards of a suite (written by `vvtbench run SUITE --shard K/N`) into one "
        "run folder: the shards must be all N shards of one suite file, vvtbench version and "
        "solver set; every sample is regenerated from its scene (a filmed one without its "
        "frames), every observation made again and every estimate scored again, so the table "
        "equals an unsharded run's (run times aside) and `vvtbench check-results RUN_DIR` "
        "recomputes it once more"))
    p.add_argument("shards", nargs="+", metavar="DIR",
                   help="shard folders (K-of-N), or a folder holding them (e.g. "
                        "shards/standard)")
    p.add_argument("-o", "--output", required=True, metavar="RUN_DIR",
                   help="run folder for the merged results.parquet, results.csv, run.json and "
                        "the cache the scores are recomputed in (one writer at a time; rows of "
                        "other solvers already in its table are kept when current)")
    p.add_argument("--suite", default=None, metavar="FILE",
                   help="the suite file, when it is not where the shards say (its sha256 must "
                        "be the one they were run on)")
    p.add_argument("--workers", type=_workers, default=1, help="local worker processes (1)")
    p.add_argument("--scheduler", default=None,
                   help="address of a Dask distributed scheduler, e.g. tcp://host:8786")
    p.add_argument("--wait", action="store_true",
                   help="if another run uses RUN_DIR, wait for it (default: refuse)")
    p.add_argument("--no-progress", action="store_true", help="no progress display")
    args = p.parse_args(argv)
    out = Path(args.output)
    try:
        df = merge_shards(args.shards, out, workers=args.workers, scheduler=args.scheduler,
                          progress=not args.no_progress, wait=args.wait, suite=args.suite)
    except Interrupted as stop:
        print(f"\ninterrupted: {stop.finished} of {stop.total} tasks finished; run the same "
              "command again to go on", file=sys.stderr)
        return 130
    except RunLocked as error:
        print(f"error: {error}", file=sys.stderr)
        return 1
    except (SuiteError, PluginError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    print(format_table(df))
    truth = df.attrs.get("truth") or {}
    st = df.attrs.get("stats", {})
    summary = ", ".join(f"{s} {v['computed']} new/{v['cached']} cached/{v['from_shards']} "
                        "failed in the shards" if v["from_shards"] else
                        f"{s} {v['computed']} new/{v['cached']} cached"
                        for s, v in st.items() if v["tasks"])
    print(f"\n{len(df)} rows from {len(df.attrs.get('shards', []))} shards in "
          f"{df.attrs.get('wall_s', 0):.1f} s ({summary}) -> {out / 'results.parquet'}, "
          f"{out / 'results.csv'}")
    print(f"every score recomputed from the shards' estimates and the regenerated truth: "
          f"{truth.get('samples_same', 0)} of {truth.get('samples', 0)} sample(s) and "
          f"{truth.get('observations_same', 0)} of {truth.get('observations', 0)} "
          "observation(s) regenerated to the very bytes the shards recorded"
          + ("; the others differ in their last bits (eigen-solves differ between machines "
             "and thread counts; the scores are compared within the check-results tolerance)"
             if truth.get("samples_changed") or truth.get("observations_changed") else ""))
    kept = df.attrs.get("kept") or {}
    if kept.get("kept"):
        print(f"kept {sum(kept['kept'].values())} row(s) of {', '.join(sorted(kept['kept']))} "
              f"from the table already in {out}")
    print(f"next: `vvtbench check-results {shlex.quote(str(out))}`, `vvtbench leaderboard "
          f"{shlex.quote(str(out))} -o {shlex.quote(str(out))}/board`")
    code = 0
    differences = df.attrs.get("differences") or []
    if differences:
        print(f"error: {len(differences)} row(s) recomputed differently from what their shard "
              "states (the table holds the recomputed values):", file=sys.stderr)
        for line in differences[:20]:
            print(f"  {line}", file=sys.stderr)
        code = 1
    bad = df[df["status"] != "ok"]
    if len(bad):
        kinds = ", ".join(f"{n} {s}" for s, n in bad["status"].value_counts().items())
        print(f"error: {len(bad)} of {len(df)} rows not ok ({kinds})", file=sys.stderr)
        code = 1
    return code
