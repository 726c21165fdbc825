"""Benchmark suites and the runner: generate -> extract -> observe -> solve -> evaluate.

A *suite* (``scenes/suites/*.toml``, format in docs/suites.md) expands into *runs*: one per
track x scene x variation x seed x observation source x solver. Each run is a chain of stage
tasks; tasks shared between runs (the same video, the same extracted modes, the same inverse
problem) are computed once:

    generate(scene)            -> sample folder (video.mkv + truth),
    vvtbench.samples.reader.generate
    extract(generate)          -> modes.npz/json, vvtbench.modes.extract_modes
    observe(scene, options, [extract...]) -> problem.npz/json + truth.npz/json (no pickle)
    solve(observe, solver, config)         -> estimate.npz/json
    evaluate(solve, observe)               -> metrics.json + fields.npz (estimate and truth grids)

Every task's output lives in ``OUT/cache/<stage>/<key>/`` where ``key`` is a content hash of
the task's inputs (resolved scene dict, stage options, vvtbench version, upstream keys): a
rerun finds the folder and recomputes nothing; a changed parameter changes the keys of the
tasks that depend on it only. A task writes into ``<key>.tmp-<pid>-<random>/`` and renames it
to ``<key>/`` at the end, so a crash leaves no half result; its ``task.json`` records the sha256
of every file, checked when the output is reused (a damaged output is recomputed and
reported). One run at a time writes a run folder (a lock on ``OUT/.lock``, :mod:`.lock`).
Every solve runs in a child process with a time and a memory limit (:mod:`.child`).
A failing task writes
``OUT/cache/<stage>/<key>.error/`` (error.json, traceback.txt) and its dependants are skipped;
the failure becomes a row with ``status = "error"`` and is retried on the next run.

Execution: in process (``workers=1``), on a local process pool (``workers=N``), or on an
existing Dask distributed cluster (``scheduler="tcp://host:port"``; the cache folder must be
on a file system the workers share).

Modules: :mod:`.suite` (the suite file and its model), :mod:`.graph` (tasks, runs, keys),
:mod:`.stages` (the stage bodies, :func:`execute_task`), :mod:`.executors` (in process, pool,
Dask), :mod:`.prune` (videos deleted once read, ``run --prune-videos``), :mod:`.results` (the
results table and its check), :mod:`.runner` (:func:`run_suite`), :mod:`.shards` (a suite in
N shards of whole instances, ``run --shard K/N``, and their result sets) and :mod:`.merge`
(:func:`merge_shards`: the shards into one table, every score recomputed).
"""

from ..io.files import jsonable, write_json
from ..solving.plugins import solver_setup
from .executors import execute_graph, make_executor
from .graph import CACHE_FORMAT, STAGES, Run, Task, build_graph, content_hash
from .merge import merge_shards
from .results import (
    COLUMNS,
    METRIC_COLUMNS,
    REQUIRED,
    check_results,
    read_results,
    results_table,
    write_results,
)
from .runner import run_suite
from .shards import ShardError, ShardSpec
from .stages import (
    STAGE_FUNCS,
    execute_task,
    load_observation,
    observe_options,
    sample_path,
)
from .suite import (
    EXTRACT_KEYS,
    INFERENCE_KEYS,
    OBSERVATIONS,
    SCENE_SECTIONS,
    SUITES_DIR,
    ExtractOptions,
    InferenceOptions,
    Suite,
    SuiteError,
    SuiteFile,
    Track,
    TrackFile,
    Variation,
    apply_overrides,
    find_suite,
    load_suite,
    parse_suite,
)

__all__ = [
    "CACHE_FORMAT", "COLUMNS", "EXTRACT_KEYS", "INFERENCE_KEYS", "METRIC_COLUMNS", "OBSERVATIONS",
    "REQUIRED", "SCENE_SECTIONS", "STAGES", "STAGE_FUNCS", "SUITES_DIR", "load_observation",
    "observe_options", "sample_path",
    "ExtractOptions", "InferenceOptions", "Run", "ShardError", "ShardSpec", "Suite",
    "SuiteError", "SuiteFile", "Task",
    "Track", "TrackFile", "Variation", "apply_overrides", "build_graph",
    "check_results", "content_hash", "execute_graph", "execute_task",
    "find_suite", "jsonable", "load_suite", "make_executor", "merge_shards", "parse_suite",
    "read_results", "results_table", "run_suite", "solver_setup", "write_json", "write_results",
]
