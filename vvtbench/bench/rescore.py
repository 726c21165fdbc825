"""Scores are recomputed, never trusted: every row of a run's results table against the
estimate and the truth in its cache.

A results row names its evaluation (``estimate_path``), and carries the sha256 of the estimate
it scored and of the observation (problem and truth) it was scored against. :func:`rescore`
checks, row by row, that the cached estimate and observation are intact and still the ones the
row names, that the row is a reference exactly when its solver was one, that validity agrees
(an invalid estimate is never scored), and that every metric recomputed from the arrays equals
the table's. ``vvtbench check-results RUN`` and ``vvtbench verify RUN`` call it.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path

from .results import METRIC_COLUMNS

__all__ = ["TOLERANCE", "has_cache", "rescore"]

TOLERANCE = 1e-6  # absolute, on metrics in [-1, 1] or relative errors (eigen-solves differ)


def _same(a, b) -> bool:
    a_nan = a is None or (isinstance(a, float) and math.isnan(a))
    b_nan = b is None or (isinstance(b, float) and math.isnan(b))
    if a_nan or b_nan:
        return a_nan and b_nan
    return abs(float(a) - float(b)) <= TOLERANCE * max(1.0, abs(float(b)))


def rescore(run_dir: str | Path, df=None,
            progress: Callable[[int, int], None] | None = None) -> list[str]:
    """Problems found recomputing every scored row (status ok or invalid) of ``df`` (default:
    the run folder's ``results.parquet``) from the run's cache; empty when every score stands.
    """
    from ..scoring.metrics import evaluate, invalid_reason
    from .results import read_results
    from .stages import load_estimate_arrays, load_observation, scored_inputs, verify_cached

    run_dir = Path(run_dir)
    cache = run_dir / "cache"
    if df is None:
        df = read_results(run_dir / "results.parquet")
    problems: list[str] = []
    rows = [(i, r) for i, r in df.iterrows() if r.get("status") in ("ok", "invalid")]
    for n, (i, row) in enumerate(rows):
        if progress:
            progress(n, len(rows))
        where = f"row {i} ({row.get('solver')}, {row.get('scene')}, {row.get('variation')})"
        path = row.get("estimate_path")
        if not isinstance(path, str) or not path.startswith("cache/evaluate/"):
            problems.append(f"{where}: no evaluation named (estimate_path {path!r})")
            continue
        folder = run_dir / Path(path).parent
        try:
            info = json.loads((folder / "task.json").read_text())
            solve_key, observe_key = info["deps"]
        except (OSError, ValueError, KeyError, TypeError):
            problems.append(f"{where}: {folder}: no readable task.json")
            continue
        damaged = None
        for key in (solve_key, observe_key):
            try:
                dep = json.loads((cache / key / "task.json").read_text())
                damaged = verify_cached(cache / key, dep)
            except (OSError, ValueError):
                damaged = "task.json unreadable"
            if damaged:
                problems.append(f"{where}: {key}: {damaged}")
                break
        if damaged:
            continue
        now = scored_inputs(cache, solve_key, observe_key)
        for key, digest in now.items():
            stated = row.get(key)
            if isinstance(stated, str) and stated != digest:
                problems.append(f"{where}: {key} {stated[:12]}... is not the sha256 of the "
                                f"cached file ({digest[:12]}...)")
        solved = json.loads((cache / solve_key / "task.json").read_text()).get("result") or {}
        if "reference" in row and bool(row["reference"]) != bool(solved.get("reference")):
            problems.append(f"{where}: 'reference' is {bool(row['reference'])} but the solver "
                            f"{'read' if solved.get('reference') else 'did not read'} the truth")
        problem, truth = load_observation(cache, observe_key, truth=True)
        w, v, std = load_estimate_arrays(cache / solve_key / "estimate.npz")
        reason = invalid_reason(w, v, problem.n_params, std.get("w_std"), std.get("v_std"))
        if (reason is None) != (row["status"] == "ok"):
            problems.append(f"{where}: status {row['status']!r} but the estimate is "
                            f"{'valid' if reason is None else 'invalid: ' + reason}")
            continue
        if reason is not None:
            continue
        ev = evaluate(problem, truth, w, v, **std)["metrics"]
        wrong = [c for c in METRIC_COLUMNS if c in row and not _same(row[c], ev.get(c))]
        if wrong:
            c = wrong[0]
            problems.append(f"{where}: {len(wrong)} score(s) differ from the recomputed ones, "
                            f"e.g. {c} {row[c]!r} in the table, {ev.get(c)!r} recomputed")
    if progress:
        progress(len(rows), len(rows))
    return problems


def has_cache(path: str | Path) -> Path | None:
    """The run folder of a results file or run folder that has its cache beside it, else
    None."""
    path = Path(path)
    run_dir = path if path.is_dir() else path.parent
    return run_dir if (run_dir / "cache").is_dir() else None

