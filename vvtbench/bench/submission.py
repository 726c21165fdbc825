"""Hidden-truth scoring: problems go out, estimates come back, truth never leaves.

A *challenge* is two folders written by :func:`write_challenge`:

* the public one, ``problems/``: ``manifest.json`` (``{"format": "vvtbench-problems", "name",
  "split_kind", "instances": {ID: {"problem_sha256": ...}}}``) and one folder per instance
  with ``problem.npz`` + ``problem.json`` (:meth:`vvtbench.solving.problem.InverseProblem.save`)
  -- what a solver author gets;
* the private one, ``truth/``: ``manifest.json`` (``"format": "vvtbench-truth"``, the same
  instances with the sha256 of their problem and truth) and per instance the problem again and
  ``truth.npz`` + ``truth.json`` -- what the scorer keeps.

Two kinds of challenge (``split_kind``, carried into every scored row):

* ``challenge`` -- a *challenge of record* (:func:`challenge_of_record`): its instances are
  drawn from a family with a secret of 32 random bytes (:func:`vvtbench.scene.families.
  draw_secret`) that is written only into the truth folder (``secret.key``). Instance ids
  are opaque (HMAC of the secret), a problem holds the observation and nothing of the draw
  (no scene, seed, family index or split), and no public split is drawn from the secret's
  streams: a participant who regenerates every public split has nothing to pair a problem
  with.
* ``public`` -- problems observed from samples anyone can regenerate (a family's public split,
  a shipped scene): for development, never a result of record.

A *submission* is a folder with ``manifest.json`` (``{"format": "vvtbench-submission",
"solver", "solver_version", "estimates": {ID: {"file": "ID/estimate.npz", "problem_sha256"}}}``)
and the estimates (``estimate.npz`` with ``w_params``, ``v_params`` per active voxel, optionally
``w_std_params``/``v_std_params``; read without pickle). :func:`write_submission` writes one;
``vvtbench solve SOLVER PROBLEMS -o SUBMISSION`` runs a plug-in over every problem.

:func:`score_submission` scores every instance of the truth's manifest from the arrays alone.
A submitted file is read only when it is a regular file reached without following a link at
any depth (no FIFO, device or link), under a size bound, and an array's header (shape and
type) is checked before any value is read; an instance the submission lacks, one answered for
another problem (its ``problem_sha256`` differs) or an unreadable estimate is an error row;
an estimate of the wrong size, with a non-finite or non-positive value, or with a negative or
non-finite standard deviation is an invalid row. Nothing the submission states is taken: not
a score, and not a runtime (the scorer measured none: ``runtime_s`` is NaN and ``sandbox`` is
``submitted``).
"""

from __future__ import annotations

import hashlib
import hmac
import json
import os
import shutil
import stat
import uuid
import zipfile
from collections.abc import Iterable, Iterator
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np

from ..io.files import write_json
from ..samples.reader import sha256_file

__all__ = ["SPLIT_KINDS", "SubmissionError", "challenge_of_record", "read_manifest",
           "score_submission", "write_challenge", "write_submission"]

PROBLEMS, TRUTH, SUBMISSION = "vvtbench-problems", "vvtbench-truth", "vvtbench-submission"
SPLIT_KINDS = ("public", "challenge")
SECRET_FILE = "secret.key"
SUBMITTED = "submitted"  # the sandbox column of a scored submission: it ran out of our sight
_MAX_ESTIMATE_BYTES = 256 << 20
_MAX_JSON_BYTES = 16 << 20
_MAX_MEMBERS = 16
_ARRAYS = ("w_params", "v_params", "w_std_params", "v_std_params")


class SubmissionError(ValueError):
    """A challenge or submission folder that cannot be read; the message names the file."""


class _Invalid(Exception):
    """A readable estimate that cannot be scored (an invalid row, with the reason and the
    sha256 of the file)."""

    sha256: str | None = None


def _problem_sha(folder: Path) -> str:
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


# --------------------------------------------------------------------------- challenges
def _new_folder(final: Path) -> Path:
    """A temporary sibling of ``final`` to write into, renamed to ``final`` when whole."""
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = final.with_name(f".{final.name}.partial-{os.getpid()}-{uuid.uuid4().hex[:8]}")
    tmp.mkdir()
    return tmp


def write_challenge(instances: Iterable[tuple], public: Path, private: Path, name: str, *,
                    split_kind: str = "public", secret: bytes | None = None,
                    record: dict | None = None) -> int:
    """Write ``(id, problem, truth)`` instances (optionally ``(id, problem, truth, scene)``, the
    scene then kept in the truth folder as ``scene.toml``) as a public problems folder and a
    private truth folder. Neither may exist; both appear whole or not at all (written beside,
    then renamed). ``secret`` (a challenge of record) is written only into the truth folder;
    ``record`` adds keys to the truth manifest. Returns the number of instances."""
    public, private = Path(public), Path(private)
    if split_kind not in SPLIT_KINDS:
        raise SubmissionError(f"split_kind {split_kind!r}: allowed: {', '.join(SPLIT_KINDS)}")
    for folder in (public, private):
        if folder.exists() or folder.is_symlink():
            raise SubmissionError(f"{folder}: exists; give a new folder")
    if public.resolve() == private.resolve() or public.resolve() in private.resolve().parents \
            or private.resolve() in public.resolve().parents:
        raise SubmissionError(f"{private}: the truth folder and the public one must be apart")
    pub_tmp = _new_folder(public)
    try:
        priv_tmp = _new_folder(private)
    except BaseException:
        shutil.rmtree(pub_tmp, ignore_errors=True)
        raise
    try:
        os.chmod(priv_tmp, 0o700)
        pub, priv = {}, {}
        for item in instances:
            instance, problem, truth = item[:3]
            instance = _safe_id(instance)
            if instance in pub:
                raise SubmissionError(f"instance id {instance!r}: given twice")
            for folder in (pub_tmp / instance, priv_tmp / instance):
                folder.mkdir()
                problem.save(folder)
            truth.save(priv_tmp / instance)
            if len(item) > 3 and item[3] is not None:
                import tomli_w

                from ..io.files import write_text

                write_text(priv_tmp / instance / "scene.toml",
                           tomli_w.dumps(item[3].to_toml_dict()))
            sha = _problem_sha(pub_tmp / instance)
            pub[instance] = {"problem_sha256": sha}
            priv[instance] = {"problem_sha256": sha,
                              "truth_sha256": sha256_file(priv_tmp / instance / "truth.npz")}
        head = {"name": name, "split_kind": split_kind}
        if secret is not None:
            fd = os.open(priv_tmp / SECRET_FILE, os.O_WRONLY | os.O_CREAT | os.O_EXCL
                         | os.O_NOFOLLOW, 0o600)
            with os.fdopen(fd, "w") as f:
                f.write(bytes(secret).hex() + "\n")
            head["secret_commitment"] = secret_commitment(secret)
        write_json(pub_tmp / "manifest.json", {"format": PROBLEMS, **head, "instances": pub})
        write_json(priv_tmp / "manifest.json",
                   {"format": TRUTH, **head, **(record or {}),
                    **({"secret_file": SECRET_FILE} if secret is not None else {}),
                    "instances": priv})
        os.rename(priv_tmp, private)
        os.rename(pub_tmp, public)
    except BaseException:
        shutil.rmtree(pub_tmp, ignore_errors=True)
        shutil.rmtree(priv_tmp, ignore_errors=True)
        if private.is_dir() and not public.exists():
            shutil.rmtree(private, ignore_errors=True)
        raise
    return len(pub)


def secret_commitment(secret: bytes) -> str:
    """What a problems folder may say of its secret: a sha256 of it (256 random bits cannot
    be found from it), so that a host who later reveals the secret shows that the instances
    were drawn from it and not picked after the submissions."""
    return hashlib.sha256(b"vvtbench-challenge-commitment\0" + bytes(secret)).hexdigest()


def instance_id(secret: bytes, index: int) -> str:
    """The opaque id of instance ``index`` of a challenge of record: 16 hex digits of an
    HMAC of the secret (it names no family, split or index)."""
    return hmac.new(bytes(secret), f"vvtbench-challenge-id:{int(index)}".encode(),
                    hashlib.sha256).hexdigest()[:16]


def check_secret_family(family) -> None:
    """Refuse a family whose material is not drawn at random: the truth of every instance
    would then be public (the base scene's), whatever the secret."""
    from ..scene.families import load_family

    fam = load_family(family)
    spec = fam.defects
    keys = ("position", "size", "aspect", "E_ratio", "rho_ratio", "tension_ratio",
            "areal_density_ratio")
    dists = [] if spec is None else [d for k in keys for d in
                                     (getattr(spec, k) if isinstance(getattr(spec, k), tuple)
                                      else (getattr(spec, k),))]
    random = any(d.kind in ("uniform", "loguniform") for d in dists)
    if spec is None or max(spec.count.values()) < 1 or not random:
        raise SubmissionError(f"{fam.source}: key 'defects': a challenge of record needs "
                              "defects drawn at random (a count that can be >= 1 and a "
                              "uniform or loguniform position, size or contrast); otherwise "
                              "its truth is the base scene's, which is public")


def draw_challenge(family, n: int, secret: bytes) -> list[tuple[str, Any]]:
    """``[(id, scene)]``: ``n`` instances of ``family`` drawn from ``secret``, opaque ids."""
    from ..scene.families import draw_secret

    check_secret_family(family)
    out, seen = [], set()
    for i in range(int(n)):
        instance = instance_id(secret, i)
        if instance in seen:  # 64 bits: never in practice, but ids must be unique
            raise SubmissionError(f"instance id {instance}: drawn twice; draw a new secret")
        seen.add(instance)
        out.append((instance, draw_secret(family, secret, i, instance)))
    return out


def challenge_of_record(family, n: int, out: Path, *, name: str | None = None,
                        secret: bytes | None = None, observe_options: dict | None = None,
                        progress=None) -> int:
    """Draw ``n`` instances of ``family`` from a new secret (or ``secret``), observe them
    (true modes unless ``observe_options`` says otherwise) and write ``out/problems`` (to
    hand out) and ``out/truth`` (to keep, with ``secret.key``). ``out`` must be new or
    empty. Returns the number of instances."""
    import secrets as _secrets

    from .._version import __version__
    from ..observe import observe
    from ..scene.families import SECRET_BYTES, load_family

    out = Path(out)
    if out.is_symlink() or (out.exists() and (not out.is_dir() or any(out.iterdir()))):
        raise SubmissionError(f"-o {out}: exists and is not an empty folder; give a new folder")
    fam = load_family(family)
    check_secret_family(fam)
    secret = _secrets.token_bytes(SECRET_BYTES) if secret is None else bytes(secret)
    drawn = draw_challenge(fam, n, secret)
    opts = {"observation": "true", **(observe_options or {})}
    src = Path(fam.source) if fam.source else None

    def instances() -> Iterator[tuple]:
        for k, (instance, scene) in enumerate(drawn):
            problem, truth = observe(scene, **opts)
            if progress is not None:
                progress(k + 1, len(drawn))
            yield instance, problem, truth, scene

    record = {"family": fam.name,
              "family_sha256": (hashlib.sha256(src.read_bytes()).hexdigest()
                                if src is not None and src.is_file() else None),
              "observe": opts, "vvtbench": __version__,
              "draw": {instance: k for k, (instance, _) in enumerate(drawn)}}
    created = not out.exists()
    try:
        return write_challenge(instances(), out / "problems", out / "truth",
                               name or fam.name, split_kind="challenge", secret=secret,
                               record=record)
    except BaseException:
        if created and out.is_dir() and not any(out.iterdir()):
            out.rmdir()
        raise


def read_manifest(folder: Path, kind: str) -> dict:
    """The manifest of a problems, truth or submission folder, checked for its format (read
    as a regular file of bounded size, never through a link)."""
    path = Path(folder) / "manifest.json"
    try:
        with _open_inside(Path(folder), "manifest.json", _MAX_JSON_BYTES) as f:
            doc = json.loads(f.read())
    except (OSError, ValueError) as error:
        raise SubmissionError(f"{path}: cannot read: {error}") from None
    if not isinstance(doc, dict) or doc.get("format") != kind:
        raise SubmissionError(f"{path}: key 'format' must be {kind!r}")
    key = "estimates" if kind == SUBMISSION else "instances"
    if not isinstance(doc.get(key), dict):
        raise SubmissionError(f"{path}: key {key!r} must be an object of instance ids")
    if kind != SUBMISSION and doc.get("split_kind", "public") not in SPLIT_KINDS:
        raise SubmissionError(f"{path}: key 'split_kind': allowed: {', '.join(SPLIT_KINDS)}")
    return doc


def write_submission(estimates: dict[str, Any], problems: Path, out: Path, solver: str,
                     version: str) -> None:
    """Write ``{id: Estimate}`` answering the problems folder ``problems`` into ``out``."""
    from ..io.files import write_npz
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
        (Path(out) / instance).mkdir(parents=True, exist_ok=True)
        write_npz(Path(out) / instance / "estimate.npz", arrays)
        entries[instance] = {"file": f"{instance}/estimate.npz",
                             "problem_sha256": man["instances"][instance]["problem_sha256"],
                             "runtime_s": float(est.runtime_s or 0.0)}
    write_json(Path(out) / "manifest.json", {"format": SUBMISSION, "solver": solver,
                                             "solver_version": version, "estimates": entries})


# --------------------------------------------------------------------------- reading
def _open_inside(root: Path, rel: str, limit: int):
    """The regular file ``root/rel`` opened for reading without following a link at any
    depth below ``root`` and without blocking (a FIFO is refused, not waited on), at most
    ``limit`` bytes; OSError or SubmissionError otherwise."""
    parts = PurePosixPath(rel).parts
    if not parts or PurePosixPath(rel).is_absolute() or any(
            p in ("", ".", "..") or "\\" in p for p in parts):
        raise SubmissionError(f"file {rel!r} must be a path inside the submission")
    dfd = os.open(root, os.O_RDONLY | os.O_DIRECTORY)
    try:
        for part in parts[:-1]:
            try:
                nfd = os.open(part, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW, dir_fd=dfd)
            except OSError as error:
                raise SubmissionError(f"{root / rel}: cannot open folder {part!r} "
                                      f"({error.strerror}; links are refused)") from None
            os.close(dfd)
            dfd = nfd
        try:
            fd = os.open(parts[-1], os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK, dir_fd=dfd)
        except OSError as error:
            raise SubmissionError(f"{root / rel}: cannot open ({error.strerror}; links are "
                                  "refused)") from None
    finally:
        os.close(dfd)
    st = os.fstat(fd)
    if not stat.S_ISREG(st.st_mode) or st.st_size > limit:
        os.close(fd)
        raise SubmissionError(f"{root / rel}: not a regular file of at most {limit >> 20} MiB "
                              "(links, FIFOs and devices are refused)")
    return os.fdopen(fd, "rb")


def _header(zf: zipfile.ZipFile, member: str) -> tuple[tuple, np.dtype]:
    with zf.open(member) as m:
        version = np.lib.format.read_magic(m)
        if version == (1, 0):
            shape, _, dtype = np.lib.format.read_array_header_1_0(m)
        elif version == (2, 0):
            shape, _, dtype = np.lib.format.read_array_header_2_0(m)
        else:
            raise ValueError(f".npy format version {version} (allowed: 1.0, 2.0)")
    return shape, dtype


def _read_estimate(submission: Path, entry: Any, n_params: int
                   ) -> tuple[np.ndarray, np.ndarray, dict, str]:
    """``(w, v, {"w_std": ..., "v_std": ...}, sha256)`` of an entry's estimate. Every array's
    header is read first: its type must be real numbers and its size that of the problem, or
    the estimate is invalid without a value being read."""
    if not isinstance(entry, dict) or not isinstance(entry.get("file"), str):
        raise SubmissionError("its entry needs a 'file'")
    path = submission / entry["file"]
    try:
        f = _open_inside(submission, entry["file"], _MAX_ESTIMATE_BYTES)
    except OSError as error:
        raise SubmissionError(f"{path}: cannot open: {error.strerror}") from None
    with f:
        h = hashlib.sha256()
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
        f.seek(0)
        arrays: dict[str, np.ndarray] = {}
        try:
            with zipfile.ZipFile(f) as zf:
                names = zf.namelist()
                if len(names) > _MAX_MEMBERS:
                    raise ValueError(f"{len(names)} members (allowed: at most {_MAX_MEMBERS})")
                for key in _ARRAYS:
                    member = f"{key}.npy"
                    if member not in names:
                        if key in ("w_params", "v_params"):
                            raise KeyError(key)
                        continue
                    shape, dtype = _header(zf, member)
                    if dtype.hasobject or dtype.kind not in "fiu" or dtype.itemsize > 16:
                        raise ValueError(f"{key} has type {dtype} (allowed: real numbers)")
                    size = int(np.prod(shape, dtype=object))
                    if size != n_params:
                        raise _Invalid(f"{key.removesuffix('_params')} has {size} values, the "
                                       f"problem has {n_params} parameters")
                    with zf.open(member) as m:
                        arrays[key] = np.lib.format.read_array(m, allow_pickle=False)
        except _Invalid as why:
            why.sha256 = h.hexdigest()
            raise
        except (KeyError, ValueError, OSError, EOFError, zipfile.BadZipFile) as error:
            raise SubmissionError(f"{path}: not an estimate (.npz with w_params and v_params "
                                  f"of real numbers): {error}") from None
    w = arrays["w_params"].astype(float).ravel()
    v = arrays["v_params"].astype(float).ravel()
    std = {}
    for n in ("w", "v"):
        if f"{n}_std_params" in arrays:
            s = arrays[f"{n}_std_params"].astype(float).ravel()
            bad = ~np.isfinite(s) | (s < 0)
            if bad.any():
                why = _Invalid(f"{n}_std is negative or not finite in {int(bad.sum())} of "
                               f"{n_params} voxels (a standard deviation is a finite number "
                               ">= 0)")
                why.sha256 = h.hexdigest()
                raise why
            std[f"{n}_std"] = s
    return w, v, std, h.hexdigest()


# --------------------------------------------------------------------------- scoring
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
    split_kind = truth_man.get("split_kind", "public")
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
                   runtime_s=float("nan"), sandbox=SUBMITTED, split_kind=split_kind)
        for m in METRIC_COLUMNS:
            row[m] = float("nan")
        try:
            if _problem_sha(folder) != info.get("problem_sha256") or sha256_file(
                    folder / "truth.npz") != info.get("truth_sha256"):
                raise SubmissionError(f"{folder}: the truth folder does not match its manifest")
            entry = sub["estimates"].get(instance)
            if entry is None:
                raise SubmissionError("no estimate submitted")
            if not isinstance(entry, dict) or entry.get("problem_sha256") != \
                    info["problem_sha256"]:
                raise SubmissionError("the estimate answers another problem (problem_sha256 "
                                      "differs)")
            problem = InverseProblem.load(folder)
            row.update(n_modes=max(1, problem.n_modes), n_modes_observed=problem.n_modes,
                       observation_sha256=info["problem_sha256"])
            try:
                w, v, std, sha = _read_estimate(submission, entry, problem.n_params)
                reason = invalid_reason(w, v, problem.n_params)
            except _Invalid as why:
                sha, reason = why.sha256, str(why)
            row["estimate_sha256"] = sha
            if reason is not None:
                row.update(status="invalid", error=reason)
            else:
                truth = Truth.load(folder)
                ev = evaluate(problem, truth, w, v, **std)["metrics"]
                for m in METRIC_COLUMNS:
                    val = ev.get(m)
                    row[m] = float("nan") if val is None else float(val)
        except SubmissionError as error:
            row.update(status="error", error=str(error))
        rows.append(row)
    df = _coerce(pd.DataFrame(rows, columns=list(COLUMNS)))
    df.attrs["extra_estimates"] = extra
    return df


def _version() -> str:
    from .._version import __version__

    return __version__
