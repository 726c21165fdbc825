"""The results table (one row per run): its columns, writing, reading and checking."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from .._version import __version__
from ..io.files import jsonable
from .graph import Run
from .suite import OBSERVATION_PATTERN, OBSERVATIONS

METRIC_COLUMNS = ("nc_w", "nc_v", "nc_w_uncentered", "nc_v_uncentered", "sigma_star_w",
                  "sigma_star_v", "nc_at_sigma_star_w", "nc_at_sigma_star_v", "mode_mac",
                  "freq_err_raw", "freq_err_scaled", "mode_mac_true", "freq_err_true_scaled",
                  "extraction_precision", "extraction_recall", "extraction_recall_all",
                  "extraction_mean_rel_freq_error", "extraction_mean_mac",
                  "extraction_median_rel_damping_error", "extraction_frequency_efficiency",
                  "extraction_damping_efficiency",
                  "false_contrast_w", "false_contrast_v",
                  "interval_coverage_w", "interval_coverage_v", "observed_dof_fraction")

COLUMNS = ("track", "solver", "solver_version", "reference", "config_hash", "config", "scene",
           "variation",
           "variation_options", "seed", "observation", "n_modes", "n_modes_observed",
           *METRIC_COLUMNS, "runtime_s", "status", "error", "vvtbench_version",
           "dataset_revision", "estimate_path", "traceback_path", "estimate_sha256",
           "observation_sha256", "sandbox", "split_kind")


def _row(run: Run, results: dict[str, dict], cache_rel: str) -> dict:
    row = {c: None for c in COLUMNS}
    row.update(track=run.track, solver=run.solver_name or run.solver,
               solver_version=run.solver_version, config_hash=run.config_hash,
               config=json.dumps(jsonable(run.config or {}), sort_keys=True),
               scene=run.scene, variation=run.variation,
               variation_options=json.dumps(jsonable(run.variation_options), sort_keys=True),
               seed=int(run.seed), observation=run.observation, n_modes=int(run.n_modes),
               reference=bool(run.reference),
               vvtbench_version=__version__, dataset_revision=run.dataset_revision,
               status="ok", error="", split_kind="public")
    for m in METRIC_COLUMNS:
        row[m] = float("nan")
    row["runtime_s"] = float("nan")
    row["n_modes_observed"] = -1
    if run.setup_error:
        row.update(status="error", error=run.setup_error)
        return row
    ev = results.get(run.evaluate_key, {})
    if ev.get("status") != "ok":
        # find the first failing task on the chain
        for k in (run.observe_key, run.solve_key, run.evaluate_key):
            r = results.get(k, {})
            if r.get("status") == "error":
                row.update(status="error", error=r.get("error", ""),
                           traceback_path=f"{cache_rel}/{r['traceback']}"
                           if r.get("traceback") else None)
                break
            if r.get("status") == "skipped" and r.get("upstream"):
                up = results.get(r["upstream"], {})
                if up.get("status") == "error":
                    row.update(status="error", error=up.get("error", r.get("error", "")),
                               traceback_path=f"{cache_rel}/{up['traceback']}"
                               if up.get("traceback") else None)
                    break
        else:
            row.update(status="error", error=ev.get("error") or "not run")
        if row["status"] != "error":
            row.update(status="error", error=ev.get("error") or "not run")
        return row
    res = ev["result"]
    sres = results.get(run.solve_key, {}).get("result", {})
    row["runtime_s"] = float(sres.get("runtime_s", float("nan")))
    row["n_modes_observed"] = int(res.get("n_modes_observed", -1))
    row.update(estimate_sha256=res.get("estimate_sha256"),
               observation_sha256=res.get("observation_sha256"),
               sandbox=sres.get("sandbox"),
               estimate_path=f"{cache_rel}/{run.evaluate_key}/fields.npz")
    if res.get("invalid"):  # never scored, never ranked
        row.update(status="invalid", error=res["invalid"])
        return row
    for m in METRIC_COLUMNS:
        val = res["metrics"].get(m)
        row[m] = float("nan") if val is None else float(val)
    return row


def results_table(runs: list[Run], results: dict[str, dict], cache_rel: str = "cache"):
    import pandas as pd

    df = pd.DataFrame([_row(r, results, cache_rel) for r in runs], columns=list(COLUMNS))
    return _coerce(df)


def _coerce(df):
    for c in METRIC_COLUMNS + ("runtime_s",):
        df[c] = df[c].astype("float64")
    for c in ("seed", "n_modes", "n_modes_observed"):
        df[c] = df[c].astype("int64")
    df["reference"] = df["reference"].astype(bool)
    for c in COLUMNS:
        if c not in METRIC_COLUMNS and c not in ("seed", "n_modes", "n_modes_observed",
                                                 "runtime_s", "reference"):
            df[c] = df[c].astype(object).where(df[c].notna(), None)
    return df


def write_results(df, out_dir: Path) -> tuple[Path, Path]:
    """results.parquet and results.csv in ``out_dir`` (atomic writes)."""
    from ..io.files import atomic_file

    out_dir = Path(out_dir)
    pq = out_dir / "results.parquet"
    csv = out_dir / "results.csv"
    with atomic_file(pq) as f:  # never through a link planted at either name
        df.to_parquet(f, index=False)
    with atomic_file(csv, "w") as f:
        df.to_csv(f, index=False)
    return pq, csv


# The type of every column (docs/results.md): how a CSV cell is read, what a Parquet column
# may hold.
_INT = ("seed", "n_modes", "n_modes_observed")
_FLOAT = (*METRIC_COLUMNS, "runtime_s")
_BOOL = ("reference",)
_OPTIONAL_STR = ("estimate_path", "traceback_path", "estimate_sha256", "observation_sha256",
                 "sandbox")
# Columns a table may lack (tables written before they existed); every other column is
# required.
OPTIONAL = ("reference", "estimate_sha256", "observation_sha256", "sandbox",
            "observed_dof_fraction", "split_kind", "extraction_median_rel_damping_error",
            "extraction_frequency_efficiency", "extraction_damping_efficiency")


def _parse_csv(raw) -> tuple[object, list[str]]:
    """Typed columns from a CSV read as strings; the cells that are not of their column's type
    (a problem each)."""
    import pandas as pd

    df = raw.copy()
    problems = []
    for c in raw.columns:
        if c in _FLOAT or c in _INT:
            vals = []
            for i, text in raw[c].items():
                t = text.strip()
                if t == "" and c in _FLOAT:
                    vals.append(float("nan"))
                    continue
                try:
                    x = float(t) if c in _FLOAT else int(t)
                except ValueError:
                    try:  # an integer written as 3.0
                        f = float(t)
                        if c in _INT and f.is_integer():
                            vals.append(int(f))
                            continue
                    except ValueError:
                        pass
                    problems.append(f"column {c!r}, row {i}: {text!r} is not "
                                    f"{'a number' if c in _FLOAT else 'an integer'}")
                    x = float("nan") if c in _FLOAT else None
                vals.append(x)
            df[c] = pd.Series(vals, index=raw.index, dtype="float64" if c in _FLOAT
                              else ("int64" if all(v is not None for v in vals) else object))
        elif c in _BOOL:
            table = {"true": True, "false": False}
            vals = []
            for i, text in raw[c].items():
                v = table.get(text.strip().lower())
                if v is None:
                    problems.append(f"column {c!r}, row {i}: {text!r} is not True or False")
                vals.append(bool(v))
            df[c] = pd.Series(vals, index=raw.index, dtype=bool)
        elif c in _OPTIONAL_STR:
            df[c] = raw[c].astype(object).where(raw[c] != "", None)
    return df, problems


def _read(path: str | Path):
    """(typed table, problems found while typing it)."""
    import pandas as pd

    path = Path(path)
    if path.is_dir():
        path = path / "results.parquet"
    if path.suffix == ".parquet":
        return pd.read_parquet(path), []
    if path.suffix == ".csv":
        # every cell as written: pandas would read the observation "true" as a boolean and a
        # version "1.0" as a float
        raw = pd.read_csv(path, dtype=str, keep_default_na=False, na_filter=False)
        return _parse_csv(raw)
    raise ValueError(f"{path}: results must be .parquet or .csv")


def read_results(path: str | Path):
    """A results table (``.parquet``, ``.csv`` or a run folder) with its columns typed as
    written by :func:`write_results` (strings stay strings in CSV too)."""
    return _read(path)[0]


_ALLOWED = {"status": ("ok", "error", "invalid"), "split_kind": ("public", "challenge")}
_RANGES = {**{c: (-1.0, 1.0) for c in ("nc_w", "nc_v", "nc_w_uncentered", "nc_v_uncentered",
                                       "nc_at_sigma_star_w", "nc_at_sigma_star_v")},
           "sigma_star_w": (0.0, None), "sigma_star_v": (0.0, None), "mode_mac": (0.0, 1.0),
           "freq_err_raw": (0.0, None), "freq_err_scaled": (0.0, None),
           "mode_mac_true": (0.0, 1.0), "freq_err_true_scaled": (0.0, None),
           "extraction_precision": (0.0, 1.0), "extraction_recall": (0.0, 1.0),
           "extraction_recall_all": (0.0, 1.0),
           "extraction_mean_rel_freq_error": (0.0, None), "extraction_mean_mac": (0.0, 1.0),
           "extraction_median_rel_damping_error": (0.0, None),
           "extraction_frequency_efficiency": (0.0, None),
           "extraction_damping_efficiency": (0.0, None),
           "false_contrast_w": (0.0, None), "false_contrast_v": (0.0, None),
           "interval_coverage_w": (0.0, 1.0), "interval_coverage_v": (0.0, 1.0),
           "observed_dof_fraction": (0.0, 1.0),
           "runtime_s": (0.0, None)}
REQUIRED = tuple(c for c in COLUMNS if c not in OPTIONAL)
# finite on every row with status ok
SCORED = ("nc_w_uncentered", "nc_v_uncentered", "runtime_s")
# and for each field NC or, where the truth is constant (NC undefined), the false contrast
SCORED_EITHER = (("nc_w", "false_contrast_w"), ("nc_v", "false_contrast_v"))
_STRINGS = ("track", "solver", "solver_version", "config_hash", "scene", "variation",
            "vvtbench_version", "dataset_revision")


# names: strict (a plug-in's name and version, a track); text: printable, no formula
_NAMES = ("track", "solver", "solver_version", "config_hash", "vvtbench_version",
          "dataset_revision", "sandbox")
_TEXT = ("scene", "variation", "observation", "error", "estimate_path", "traceback_path")
_SHA = ("estimate_sha256", "observation_sha256")
_FORMULA = "=+-@"


def _check_cells(df, err) -> None:
    """Cells that would mislead a reader: a newline (a fake Markdown row), a control character,
    a leading formula character (a spreadsheet runs it), a malformed sha256; scores on rows
    that are not scored (error, invalid); a shipped reference solver not marked as one."""
    import pandas as pd

    from ..solving.plugins import REFERENCE_BUILTINS, name_problem

    for c in _NAMES:
        if c not in df.columns:
            continue
        for i, val in df[c].items():
            if isinstance(val, str) and val and name_problem(val, max_len=200):
                err(f"column {c!r}, row {i}: {val!r} {name_problem(val, max_len=200)}")
    for c in _TEXT:
        if c not in df.columns:
            continue
        for i, val in df[c].items():
            if isinstance(val, str) and val and (not val.isprintable() or val[0] in _FORMULA):
                err(f"column {c!r}, row {i}: {val[:40]!r} must be printable text (no newline "
                    "or control character) and must not start with '=', '+', '-' or '@'")
    for c in _SHA:
        if c not in df.columns:
            continue
        for i, val in df[c].items():
            if isinstance(val, str) and not re.fullmatch(r"[0-9a-f]{64}", val):
                err(f"column {c!r}, row {i}: {val[:20]!r} must be a sha256 (64 hex digits)")
    if "status" in df.columns:
        for i, st in df["status"].items():
            if st in ("error", "invalid"):
                scored = [c for c in METRIC_COLUMNS if c in df.columns
                          and np.isfinite(pd.to_numeric(pd.Series([df.at[i, c]]),
                                                        errors="coerce").iloc[0])]
                if scored:
                    err(f"row {i}: status {st!r} but scores in {', '.join(scored[:4])} "
                        "(a row that is not scored has no scores)")
    if "reference" in df.columns and "solver" in df.columns:
        for i, (name, ref) in enumerate(zip(df["solver"], df["reference"], strict=True)):
            if name in REFERENCE_BUILTINS and not bool(ref):
                err(f"row {df.index[i]}: solver {name!r} reads the truth (a reference) but "
                    "'reference' is False")


def check_results(path_or_df, max_errors: int = 50) -> list[str]:
    """Validate a results table (file or DataFrame) against docs/results.md.

    Returns a list of problems, each naming the column, the row (0-based, as in the file's data
    rows) and what is allowed; empty when the table is valid.
    """
    import pandas as pd

    errors: list[str] = []
    if isinstance(path_or_df, pd.DataFrame):
        df = path_or_df
    else:
        try:
            df, errors = _read(path_or_df)
        except Exception as error:
            return [f"{path_or_df}: cannot read: {type(error).__name__}: {error}"]

    def err(msg):
        errors.append(msg)

    missing = [c for c in COLUMNS if c not in df.columns and c not in OPTIONAL]
    if missing:
        err(f"missing column(s): {', '.join(missing)} (required: "
            f"{', '.join(c for c in COLUMNS if c not in OPTIONAL)})")
    extra = [str(c) for c in df.columns if c not in COLUMNS]
    if extra:
        err(f"unknown column(s): {', '.join(extra)} (allowed: {', '.join(COLUMNS)})")
    if len(df) == 0:
        err("the table has no rows")
    status = df["status"] if "status" in df.columns else pd.Series([None] * len(df),
                                                                   index=df.index)
    for c in _STRINGS:
        if c not in df.columns:
            continue
        for i, val in df[c].items():
            if c == "solver_version" and status[i] == "error" and val == "":
                continue  # a solver that failed to load has no version
            if not isinstance(val, str) or not val.strip():
                err(f"column {c!r}, row {i}: {val!r} must be a non-empty string")
    for c in ("config", "variation_options", "error", "observation", "status"):
        if c not in df.columns:
            continue
        for i, val in df[c].items():
            if not isinstance(val, str):
                err(f"column {c!r}, row {i}: {val!r} must be a string")
    for c in _OPTIONAL_STR:
        if c not in df.columns:
            continue
        for i, val in df[c].items():
            if val is not None and not (isinstance(val, float) and np.isnan(val)) \
                    and not (isinstance(val, str) and val.strip()):
                err(f"column {c!r}, row {i}: {val!r} must be a path or empty")
    for c in _FLOAT:
        if c in df.columns and not pd.api.types.is_numeric_dtype(df[c]):
            err(f"column {c!r}: type {df[c].dtype} (allowed: float numbers, NaN when missing)")
    if "reference" in df.columns and not pd.api.types.is_bool_dtype(df["reference"]):
        err(f"column 'reference': type {df['reference'].dtype} (allowed: True or False)")
    if "n_modes_observed" in df.columns:
        for i, val in df["n_modes_observed"].items():
            if not isinstance(val, (int, np.integer)) or isinstance(val, bool) or val < -1:
                err(f"column 'n_modes_observed', row {i}: {val!r} must be an integer >= -1")
    for c, allowed in _ALLOWED.items():
        if c not in df.columns:
            continue
        for i, val in df[c].items():
            if val not in allowed:
                err(f"column {c!r}, row {i}: {val!r} not allowed; allowed values: "
                    f"{', '.join(allowed)}")
    if "observation" in df.columns:
        for i, val in df["observation"].items():
            if not (isinstance(val, str) and re.match(OBSERVATION_PATTERN, val)):
                err(f"column 'observation', row {i}: {val!r} not allowed; allowed values: "
                    f"{', '.join(OBSERVATIONS)}, or 'extracted:EXTRACTOR'")
    for c in ("seed", "n_modes"):
        if c not in df.columns:
            continue
        for i, val in df[c].items():
            ok = isinstance(val, (int, np.integer)) and not isinstance(val, (bool, np.bool_))
            if not ok or (c == "n_modes" and val < 1) or val < 0:
                err(f"column {c!r}, row {i}: {val!r} must be an integer"
                    + (" >= 1" if c == "n_modes" else ""))
    if "config" in df.columns:
        for i, val in df["config"].items():
            try:
                if not isinstance(json.loads(val), dict):
                    raise ValueError
            except (TypeError, ValueError):
                err(f"column 'config', row {i}: must be a JSON object (the solver config), "
                    f"got {str(val)[:40]!r}")
    if "config_hash" in df.columns:
        for i, val in df["config_hash"].items():
            if isinstance(val, str) and not all(ch in "0123456789abcdef" for ch in val):
                err(f"column 'config_hash', row {i}: {val!r} must be lower-case hex")
    for c, (lo, hi) in _RANGES.items():
        if c not in df.columns:
            continue
        col = pd.to_numeric(df[c], errors="coerce")
        for i, (raw, val) in enumerate(zip(df[c], col, strict=True)):
            if pd.isna(val):
                if raw is not None and not pd.isna(raw):
                    err(f"column {c!r}, row {df.index[i]}: {raw!r} is not a number")
                continue
            if (lo is not None and val < lo - 1e-9) or (hi is not None and val > hi + 1e-9):
                rng = f"[{lo}, {hi if hi is not None else 'inf'}]"
                err(f"column {c!r}, row {df.index[i]}: {val!r} outside the allowed range {rng}")
    if "status" in df.columns:
        for i, row in df.iterrows():
            if row["status"] == "ok":
                for c in SCORED:
                    if c == "runtime_s" and row.get("sandbox") == "submitted":
                        continue  # a scored submission: its runtime was not measured (NaN)
                    if c in df.columns and not np.isfinite(
                            pd.to_numeric(pd.Series([row[c]]), errors="coerce").iloc[0]):
                        err(f"column {c!r}, row {i}: rows with status 'ok' need a finite "
                            f"number, got {row[c]!r}")
                for a, b in SCORED_EITHER:
                    vals = [pd.to_numeric(pd.Series([row.get(c)]), errors="coerce").iloc[0]
                            for c in (a, b)]
                    if sum(bool(np.isfinite(x)) for x in vals) != 1:
                        err(f"columns {a!r}/{b!r}, row {i}: rows with status 'ok' need exactly "
                            f"one of them (NC, or the false contrast where the truth is "
                            f"constant), got {row.get(a)!r}/{row.get(b)!r}")
            elif row["status"] in ("error", "invalid") and "error" in df.columns:
                if not isinstance(row["error"], str) or not row["error"].strip():
                    err(f"column 'error', row {i}: rows with status {row['status']!r} need "
                        "the reason")
    _check_cells(df, err)
    key = [c for c in ("track", "solver", "config_hash", "scene", "variation", "seed",
                       "observation") if c in df.columns]
    if len(key) >= 6 and len(df):
        dup = df.duplicated(subset=key, keep="first")
        for i in df.index[dup]:
            err(f"row {i}: duplicate of an earlier row in columns {', '.join(key)}")
    if len(errors) > max_errors:
        errors = errors[:max_errors] + [f"... and {len(errors) - max_errors} more problem(s)"]
    return errors
