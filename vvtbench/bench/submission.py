"""Hidden-truth scoring: problems go out, estimates come back, truth never leaves.

A *challenge* is two folders written by :func:`write_challenge`:

* the public one, ``problems/``: ``manifest.json`` (``{"format": "vvtbench-problems", "name",
  "instances": {ID: {"problem_sha256": ...}}}``) and one folder per instance with
  ``problem.npz`` + ``problem.json`` (:meth:`vvtbench.solving.problem.InverseProblem.save`) -- what
  a
  solver author gets;
* the private one, ``truth/``: ``manifest.json`` (``"format": "vvtbench-truth"``, the same
  instances with the sha256 of their problem and truth) and per instance the problem again and
  ``truth.npz`` + ``truth.json`` -- what the scorer keeps.

A *submission* is a folder with ``manifest.json`` (``{"format": "vvtbench-submission",
"solver", "solver_version", "estimates": {ID: {"file": "ID/estimate.npz", "problem_sha256"}}}``)
and the estimates (``estimate.npz`` with ``w_params``, ``v_params`` per active voxel, optionally
``w_std_params``/``v_std_params``; read without pickle). :func:`write_submission` writes one;
``vvtbench solve SOLVER PROBLEMS -o SUBMISSION`` runs a plug-in over every problem.

:func:`score_submission` scores every instance of the truth's manifest: an instance the
submission lacks, one answered for another problem (its ``problem_sha256`` differs) or an
unreadable estimate is an error row, an invalid estimate an invalid row; the scores come only
from :func:`vvtbench.scoring.metrics.evaluate` on the arrays, never from the submission.
"""

from __future__ import annotations

import json
import os
import stat
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from ..io.files import write_json
from ..samples.reader import sha256_file

__all__ = ["SubmissionError", "read_manifest", "score_submission", "write_challenge",
           "write_submission"]

PROBLEMS, TRUTH, SUBMISSION = "vvtbench-problems", "vvtbench-truth", "vvtbench-submission"
_MAX_ESTIMATE_BYTES = 1 << 30


class SubmissionError(ValueError):
    """A challenge or submission folder that cannot be read; the message names the file."""


def _problem_sha(folder: Path) -> str:
    import hashlib

    h = hashlib.sha256()
    for name in ("problem.json", "problem.npz"):
        h.update(f"{name}\0{sha256_file(folder / name)}\n".encode())
    return h.hexdigest()


def _safe_id(instance: str) -> str:
    from ..solving.plugins import name_problem

    problem = name_problem(instance, max_len=120)
    if problem or instance in (".", "..") or "/" in instance or "\\" in instance:
        raise SubmissionError(f"instance id {instance!r}: {problem or 'not a folder name'}")
    return instance


def write_challenge(instances: Iterable[tuple[str, Any, Any]], public: Path, private: Path,
                    name: str) -> int:
    """Write ``(id, problem, truth)`` instances as a public problems folder and a private truth
    folder (both created here; neither may exist). Returns the number of instances."""
    public, private = Path(public), Path(private)
    for folder in (public, private):
        if folder.exists():
            raise SubmissionError(f"{folder}: exists; give a new folder")
    if public.resolve() == private.resolve() or private.resolve() in public.resolve().parents:
        raise SubmissionError(f"{private}: the truth folder must not be inside the public one")
    pub, priv = {}, {}
    for instance, problem, truth in instances:
        instance = _safe_id(instance)
        for folder in (public / instance, private / instance):
            folder.mkdir(parents=True)
            problem.save(folder)
        truth.save(private / instance)
        sha = _problem_sha(public / instance)
        pub[instance] = {"problem_sha256": sha}
        priv[instance] = {"problem_sha256": sha,
                          "truth_sha256": sha256_file(private / instance / "truth.npz")}
    write_json(public / "manifest.json", {"format": PROBLEMS, "name": name, "instances": pub})
    write_json(private / "manifest.json", {"format": TRUTH, "name": name, "instances": priv})
    return len(pub)


def read_manifest(folder: Path, kind: str) -> dict:
    """The manifest of a problems, truth or submission folder, checked for its format."""
    path = Path(folder) / "manifest.json"
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError) as error:
        raise SubmissionError(f"{path}: cannot read: {error}") from None
    if not isinstance(doc, dict) or doc.get("format") != kind:
        raise SubmissionError(f"{path}: key 'format' must be {kind!r}")
    key = "estimates" if kind == SUBMISSION else "instances"
    if not isinstance(doc.get(key), dict):
        raise SubmissionError(f"{path}: key {key!r} must be an object of instance ids")
    return doc


def write_submission(estimates: dict[str, Any], problems: Path, out: Path, solver: str,
                     version: str) -> None:
    """Write ``{id: Estimate}`` answering the problems folder ``problems`` into ``out``."""
    from ..solving.plugins import name_problem

    for label, value in (("solver", solver), ("solver_version", version)):
        if name_problem(value):
            raise SubmissionError(f"{label} {value!r}: {name_problem(value)}")
    man = read_manifest(problems, PROBLEMS)
    entries = {}
    for instance, est in estimates.items():
        instance = _safe_id(instance)
        if instance not in man["instances"]:
            raise SubmissionError(f"{instance}: not an instance of {problems}")
        arrays = {"w_params": np.asarray(est.w, float), "v_params": np.asarray(est.v, float)}
        for n in ("w_std", "v_std"):
            std = est.std(n)
            if std is not None:
                arrays[f"{n}_params"] = std
        from ..io.files import write_npz

        (Path(out) / instance).mkdir(parents=True, exist_ok=True)
        write_npz(Path(out) / instance / "estimate.npz", arrays)
        entries[instance] = {"file": f"{instance}/estimate.npz",
                             "problem_sha256": man["instances"][instance]["problem_sha256"],
                             "runtime_s": float(est.runtime_s or 0.0)}
    write_json(Path(out) / "manifest.json", {"format": SUBMISSION, "solver": solver,
                                             "solver_version": version, "estimates": entries})


def _read_estimate(submission: Path, entry: Any) -> tuple[np.ndarray, np.ndarray, dict]:
    if not isinstance(entry, dict) or not isinstance(entry.get("file"), str):
        raise SubmissionError("its entry needs a 'file'")
    rel = Path(entry["file"])
    if rel.is_absolute() or ".." in rel.parts:
        raise SubmissionError(f"file {entry['file']!r} must be a path inside the submission")
    path = submission / rel
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW)
    except OSError as error:
        raise SubmissionError(f"{path}: cannot open ({error.strerror}; links are refused)"
                              ) from None
    with os.fdopen(fd, "rb") as f:
        st = os.fstat(f.fileno())
        if not stat.S_ISREG(st.st_mode) or st.st_size > _MAX_ESTIMATE_BYTES:
            raise SubmissionError(f"{path}: not a regular file under 1 GB")
        try:
            with np.load(f, allow_pickle=False) as z:
                w, v = np.asarray(z["w_params"]), np.asarray(z["v_params"])
                std = {f"{n}_std": np.asarray(z[f"{n}_std_params"]) for n in ("w", "v")
                       if f"{n}_std_params" in z.files}
        except (KeyError, ValueError, OSError) as error:
            raise SubmissionError(f"{path}: not an estimate (.npz with w_params and "
                                  f"v_params): {error}") from None
    if w.dtype.kind not in "fiu" or v.dtype.kind not in "fiu":
        raise SubmissionError(f"{path}: w_params and v_params must be real numbers")
    return w.astype(float).ravel(), v.astype(float).ravel(), std


def score_submission(submission: Path, truth_dir: Path):
    """The results table (one row per instance of the truth's manifest; the columns of
    :data:`vvtbench.bench.results.COLUMNS`) of ``submission`` scored against ``truth_dir``."""
    import pandas as pd

    from ..scoring.metrics import evaluate, invalid_reason
    from ..solving.plugins import name_problem
    from ..solving.problem import InverseProblem
    from ..solving.truth import Truth
    from .results import COLUMNS, METRIC_COLUMNS, _coerce

    submission, truth_dir = Path(submission), Path(truth_dir)
    sub = read_manifest(submission, SUBMISSION)
    truth_man = read_manifest(truth_dir, TRUTH)
    solver = sub.get("solver")
    version = sub.get("solver_version")
    for label, value in (("solver", solver), ("solver_version", version)):
        if name_problem(value):
            raise SubmissionError(f"{submission / 'manifest.json'}: key {label!r}: "
                                  f"{name_problem(value)}")
    extra = sorted(set(sub["estimates"]) - set(truth_man["instances"]))
    rows = []
    for instance, info in sorted(truth_man["instances"].items()):
        folder = truth_dir / _safe_id(instance)
        row = {c: None for c in COLUMNS}
        row.update(track=str(truth_man.get("name") or "challenge"), solver=solver,
                   solver_version=version, reference=False, config_hash="0" * 16,
                   config="{}", scene=instance, variation="base", variation_options="{}",
                   seed=0, observation="true", n_modes=1, n_modes_observed=-1,
                   status="ok", error="", vvtbench_version=_version(),
                   dataset_revision=str(info.get("problem_sha256", ""))[:16] or "unknown",
                   runtime_s=float("nan"), sandbox=None)
        for m in METRIC_COLUMNS:
            row[m] = float("nan")
        try:
            if _problem_sha(folder) != info.get("problem_sha256") or sha256_file(
                    folder / "truth.npz") != info.get("truth_sha256"):
                raise SubmissionError(f"{folder}: the truth folder does not match its manifest")
            entry = sub["estimates"].get(instance)
            if entry is None:
                raise SubmissionError("no estimate submitted")
            if entry.get("problem_sha256") != info["problem_sha256"]:
                raise SubmissionError("the estimate answers another problem (problem_sha256 "
                                      "differs)")
            w, v, std = _read_estimate(submission, entry)
            problem = InverseProblem.load(folder)
            truth = Truth.load(folder)
            row.update(n_modes=max(1, problem.n_modes), n_modes_observed=problem.n_modes,
                       estimate_sha256=sha256_file(submission / entry["file"]),
                       observation_sha256=info["problem_sha256"])
            reason = invalid_reason(w, v, problem.n_params)
            if reason is not None:
                row.update(status="invalid", error=reason)
            else:
                stds = {k: s for k, s in std.items() if s.shape == w.shape}
                ev = evaluate(problem, truth, w, v, **stds)["metrics"]
                for m in METRIC_COLUMNS:
                    val = ev.get(m)
                    row[m] = float("nan") if val is None else float(val)
                row["runtime_s"] = _stated_runtime(entry)
        except SubmissionError as error:
            row.update(status="error", error=str(error))
        rows.append(row)
    df = _coerce(pd.DataFrame(rows, columns=list(COLUMNS)))
    df.attrs["extra_estimates"] = extra
    return df


def _stated_runtime(entry: dict) -> float:
    """The runtime the submitter states (not measured by the scorer), 0 when not stated."""
    value = entry.get("runtime_s")
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) \
        and np.isfinite(value) and value >= 0
    return float(value) if ok else 0.0


def _version() -> str:
    from .._version import __version__

    return __version__
