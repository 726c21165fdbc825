"""A resumable store of a trainable solver's per-instance training features.

Training on tens of thousands of generated instances cannot keep them: a modes-only
``cube_defects`` instance takes 2.5-3.5 MB on disk, its training features (for ``learned``
3.0: 42 numbers per voxel and the truth's w) about 0.18 MB. :func:`build_store` generates each
train and val instance into the store's own scratch folder, turns it into the solver's
training features against a basis fixed first (``reference_basis`` of the first
``N_REFERENCE`` train instances, kept in ``basis.npz``), appends the features to a shard and
deletes the instance's folder. Layout of a store folder::

    store.json          what the features are of: solver and its revision, family (and the
                        sha256 of its file), observe options, the basis' reference instances
                        and sha256
    basis.npz           the basis every shard was featurized against
    shards/SPLIT-FIRST-LAST.npz
                        complete shards only (written atomically): the instances' names,
                        indices, row counts, manifest and feature sha256, and their feature
                        arrays stacked along the first axis
    .scratch/SPLIT/     instances being featurized (marked as the store's own; removed)

A store answers for one solver revision, family file and observation: :func:`build_store`
and :meth:`FeatureStore.open` refuse, in one line, a store made for another or a shard made
against another basis. A rerun resumes: an instance already in a shard is not generated
again, and a complete instance left in the scratch folder by a killed run is featurized
without generating it again.

The solver module provides the hooks (``solvers/learned.py``): ``N_REFERENCE``,
``reference_basis(problems)``, ``instance_features(problem, truth, basis)`` and
``STORED_FEATURES`` (the keys of an item kept in the store, each an array with one row per
voxel).
"""

from __future__ import annotations

import hashlib
import importlib
import json
import re
import shutil
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

FORMAT = "vvtbench.feature-store"
STORE_FILE = "store.json"
BASIS_FILE = "basis.npz"
SHARDS = "shards"
SCRATCH = ".scratch"
SCRATCH_MARK = ".vvtbench-scratch"
SHARD_INSTANCES = 100
#: Keys of store.json a rerun must match: a store holds features of one of each.
IDENTITY = ("solver", "solver_version", "model", "family", "family_sha256", "observe",
            "n_reference")
#: Disk one modes-only instance may take in the scratch folder at its peak (measured 2.5-3.5
#: MB for cube_defects).
INSTANCE_BYTES = 4 * 2**20
_NAME = re.compile(r"^(?P<family>[A-Za-z0-9][A-Za-z0-9_.-]*)-(?P<split>train|val|test)-"
                   r"(?P<index>\d{5,})$")


class FeatureStoreError(ValueError):
    """A feature store that cannot be used as asked (one line naming the file and key)."""


@dataclass
class StoreSpec:
    """What a store's features are of.

    Attributes
    ----------
    solver : the solver's name (``learned``).
    module : the solver's module (its hooks: ``instance_features``, ``reference_basis``,
        ``N_REFERENCE``, ``STORED_FEATURES``).
    solver_version : the solver's revision (features change with it).
    model : the model name the features are for.
    family : the family file (path).
    family_name : the family's name.
    observe : observe options (:func:`vvtbench.observe.observe`) the instances are seen with.
    reference_start : index of the first train instance of the basis.
    """

    solver: str
    module: str
    solver_version: str
    model: str
    family: str
    family_name: str
    observe: dict = field(default_factory=dict)
    reference_start: int = 0

    def identity(self) -> dict:
        hooks = importlib.import_module(self.module)
        return {"solver": self.solver, "solver_version": self.solver_version,
                "model": self.model, "family": self.family_name,
                "family_sha256": hashlib.sha256(Path(self.family).read_bytes()).hexdigest(),
                "observe": json.loads(json.dumps(self.observe)),
                "n_reference": int(hooks.N_REFERENCE)}


def array_sha256(arrays: dict[str, np.ndarray]) -> str:
    """sha256 of arrays (names, dtypes, shapes and bytes, in key order)."""
    digest = hashlib.sha256()
    for key in sorted(arrays):
        a = np.ascontiguousarray(arrays[key])
        digest.update(f"{key}:{a.dtype.str}:{a.shape};".encode())
        digest.update(a.tobytes())
    return digest.hexdigest()


def _meta(arrays) -> dict:
    return json.loads(np.asarray(arrays["meta_json"]).tobytes().decode())


def _meta_array(doc: dict) -> np.ndarray:
    return np.frombuffer(json.dumps(doc).encode(), dtype=np.uint8)


@dataclass(frozen=True)
class Entry:
    """One stored instance: its shard and its rows there."""

    index: int
    name: str
    shard: Path
    row0: int
    row1: int
    manifest_sha256: str
    features_sha256: str


class FeatureStore:
    """A feature store folder (:func:`build_store` writes it)."""

    def __init__(self, root: Path, meta: dict, basis: np.ndarray) -> None:
        self.root = Path(root)
        self.meta = meta
        self.basis = basis
        self._entries: dict[str, list[Entry]] = {}

    @classmethod
    def open(cls, root: str | Path) -> FeatureStore:
        """Open a store; refuses a folder that is not one, or a basis that does not match."""
        root = Path(root)
        path = root / STORE_FILE
        if not path.is_file():
            raise FeatureStoreError(f"{root}: not a feature store (no {STORE_FILE}; build one "
                                    "with `vvtbench train SOLVER FAMILY --drop-instances`)")
        try:
            meta = json.loads(path.read_text())
        except (OSError, ValueError) as error:
            raise FeatureStoreError(f"{path}: unreadable ({error})") from None
        if not isinstance(meta, dict) or meta.get("format") != FORMAT:
            raise FeatureStoreError(f"{path}: key 'format' must be {FORMAT!r}")
        try:
            with np.load(root / BASIS_FILE, allow_pickle=False) as z:
                basis = z["basis"]
        except (OSError, ValueError, KeyError) as error:
            raise FeatureStoreError(f"{root / BASIS_FILE}: unreadable ({error})") from None
        if array_sha256({"basis": basis}) != meta.get("basis_sha256"):
            raise FeatureStoreError(f"{root / BASIS_FILE}: not the basis the store was built "
                                    f"against (key 'basis_sha256' of {path}); use another "
                                    "--features folder")
        return cls(root, meta, basis)

    def check(self, identity: dict) -> None:
        """Refuse (one line) a store made for another solver revision, family file or
        observation than ``identity``."""
        for key in IDENTITY:
            if self.meta.get(key) != identity.get(key):
                raise FeatureStoreError(
                    f"{self.root / STORE_FILE}: key {key!r} is {self.meta.get(key)!r}, this "
                    f"run's is {identity.get(key)!r}; a store holds the features of one solver "
                    "revision, family file and observation: use another --features folder")

    def shards(self, split: str) -> list[Path]:
        return sorted((self.root / SHARDS).glob(f"{split}-*.npz"))

    def entries(self, split: str) -> list[Entry]:
        """The stored instances of ``split`` in index order (each shard checked against the
        store's basis and identity)."""
        if split in self._entries:
            return self._entries[split]
        found: dict[int, Entry] = {}
        for shard in self.shards(split):
            try:
                with np.load(shard, allow_pickle=False) as z:
                    meta = _meta(z)
                    names, indices, rows = z["names"], z["indices"], z["rows"]
                    manifests, feats = z["manifest_sha256"], z["features_sha256"]
            except (OSError, ValueError, KeyError) as error:
                raise FeatureStoreError(f"{shard}: unreadable shard ({error}); remove it and "
                                        "run again to rebuild its instances") from None
            if meta.get("basis_sha256") != self.meta["basis_sha256"]:
                raise FeatureStoreError(f"{shard}: key 'basis_sha256' is not the store's "
                                        f"({self.root / BASIS_FILE}): built against another "
                                        "basis; a store never mixes them")
            if meta.get("identity_sha256") != self.identity_sha256():
                raise FeatureStoreError(f"{shard}: key 'identity_sha256' is not the store's "
                                        f"({self.root / STORE_FILE}): built for another solver "
                                        "revision, family file or observation")
            ends = np.concatenate([[0], np.cumsum(rows)])
            for j, (name, index) in enumerate(zip(names, indices, strict=True)):
                if int(index) in found:
                    raise FeatureStoreError(f"{shard}: instance {name} is also in "
                                            f"{found[int(index)].shard}")
                found[int(index)] = Entry(int(index), str(name), shard, int(ends[j]),
                                          int(ends[j + 1]), str(manifests[j]), str(feats[j]))
        self._entries[split] = [found[i] for i in sorted(found)]
        return self._entries[split]

    def identity_sha256(self) -> str:
        doc = {k: self.meta.get(k) for k in IDENTITY}
        return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()

    def select(self, split: str, start: int = 0, n: int | None = None) -> list[Entry]:
        """The stored instances of ``split`` with index in [start, start + n)."""
        stop = None if n is None else start + n
        return [e for e in self.entries(split)
                if e.index >= start and (stop is None or e.index < stop)]

    def iter_arrays(self, entries: list[Entry], keys: tuple[str, ...]
                    ) -> Iterator[tuple[Entry, dict[str, np.ndarray]]]:
        """Each entry's stored arrays ``keys`` (one shard in memory at a time)."""
        current, arrays = None, {}
        for entry in entries:
            if entry.shard != current:
                with np.load(entry.shard, allow_pickle=False) as z:
                    arrays = {k: z[k] for k in keys}
                current = entry.shard
            yield entry, {k: arrays[k][entry.row0:entry.row1] for k in keys}

    def digest(self, entries: list[Entry]) -> str:
        """sha256 over the entries' names, manifest sha256 and feature sha256 (index order):
        the same instances and features give the same digest however they were sharded."""
        h = hashlib.sha256()
        for e in entries:
            h.update(f"{e.name}:{e.manifest_sha256}:{e.features_sha256};".encode())
        return h.hexdigest()

    def record(self, entries: list[Entry]) -> dict:
        """What a weights file records of the store's instances it was trained on."""
        return {"path": str(self.root.resolve()), "instances": len(entries),
                "sha256": self.digest(entries), "basis_sha256": self.meta["basis_sha256"],
                "basis_from": self.meta.get("reference", [])}


# --------------------------------------------------------------------------- building
_BASIS_CACHE: dict[str, np.ndarray] = {}


def _basis(path: str, sha256: str) -> np.ndarray:
    if sha256 not in _BASIS_CACHE:
        with np.load(path, allow_pickle=False) as z:
            _BASIS_CACHE.clear()
            _BASIS_CACHE[sha256] = z["basis"]
    return _BASIS_CACHE[sha256]


def _generate(job: dict) -> dict:
    from ..samples.jobs import generate_instance

    return generate_instance(job)


def featurize_instance(task: dict) -> dict:
    """Generate one instance into the scratch folder (or take the complete one there) and
    compute its stored features; a worker's job, never raises.

    ``task``: ``job`` (a :func:`vvtbench.samples.jobs.generate_instance` job), ``module``,
    ``basis`` (path) and ``basis_sha256``, ``mesh_key`` (the basis' mesh, or None),
    ``observe`` (options), ``index``.
    """
    from ..observe import ObserveOptions, observe

    t0, c0 = time.perf_counter(), time.process_time()
    res = _generate(task["job"])
    out = {"name": res["name"], "index": task["index"], "path": res["path"],
           "status": res["status"], "error": res.get("error"),
           "input_error": bool(res.get("input_error")), "generated": res["status"] == "done"}
    if res["status"] == "error":
        return out
    try:
        hooks = importlib.import_module(task["module"])
        basis = _basis(task["basis"], task["basis_sha256"])
        problem, truth = observe(Path(res["path"]), ObserveOptions.resolve(None, **task["observe"]))
        if task.get("mesh_key") and hooks.mesh_key(problem) != task["mesh_key"]:
            out.update(status="error", input_error=True,
                       error="another mesh than the store's basis; a family of several "
                             "meshes trains without --drop-instances")
            return out
        item = hooks.instance_features(problem, truth, basis)
        arrays = {k: np.ascontiguousarray(item[k]) for k in hooks.STORED_FEATURES}
        manifest = Path(res["path"]) / "manifest.json"
        out.update(arrays=arrays, features_sha256=array_sha256(arrays),
                   manifest_sha256=hashlib.sha256(manifest.read_bytes()).hexdigest())
    except Exception as error:  # noqa: BLE001 -- reported by the caller, the run stops there
        out.update(status="error", error=f"{type(error).__name__}: {error}")
    out["seconds"] = time.perf_counter() - t0
    out["cpu_seconds"] = time.process_time() - c0
    return out


def _scratch(root: Path, split: str) -> Path:
    scratch = root / SCRATCH
    scratch.mkdir(parents=True, exist_ok=True)
    (scratch / SCRATCH_MARK).touch()
    folder = scratch / split
    folder.mkdir(exist_ok=True)
    return folder


def drop_instance(root: Path, split: str, name: str) -> None:
    """Delete an instance folder this store generated: only ``ROOT/.scratch/SPLIT/NAME`` of a
    marked scratch folder, for a name ``FAMILY-SPLIT-INDEX`` of that split."""
    scratch = Path(root) / SCRATCH
    match = _NAME.match(name)
    if (not (scratch / SCRATCH_MARK).is_file() or match is None
            or match.group("split") != split):
        raise FeatureStoreError(f"{scratch / split / name}: not an instance this store "
                                "generated; left in place")
    folder = scratch / split / name
    if folder.is_symlink():
        raise FeatureStoreError(f"{folder}: a link, not an instance this store generated")
    if folder.is_dir():
        shutil.rmtree(folder)
    partial = scratch / split / f".{name}.partial"
    if partial.is_dir() and not partial.is_symlink():
        shutil.rmtree(partial)


def _remove_scratch(root: Path) -> None:
    scratch = Path(root) / SCRATCH
    if not (scratch / SCRATCH_MARK).is_file():
        return
    for sub in scratch.iterdir():
        if sub.is_dir() and not sub.is_symlink():
            try:
                sub.rmdir()  # empty only: a folder with anything left stays
            except OSError:
                return
    if [p.name for p in scratch.iterdir()] == [SCRATCH_MARK]:
        (scratch / SCRATCH_MARK).unlink()
        scratch.rmdir()


def _job(spec: StoreSpec, root: Path, split: str, index: int, workers: int) -> dict:
    """The generation job of one instance, as ``vvtbench generate --no-video`` makes it (one
    BLAS thread per worker process when there are several)."""
    return {"out": str(_scratch(root, split)), "family": str(spec.family), "split": split,
            "index": int(index), "name": f"{spec.family_name}-{split}-{index:05d}",
            "options": {"video": False, "progress": False}, "overwrite": False,
            **({"threads": 1} if workers > 1 else {})}


def _create(root: Path, spec: StoreSpec, identity: dict, n_train: int, executor, log
            ) -> FeatureStore:
    """Generate the reference instances (the first ``N_REFERENCE`` train instances, or the
    ``n_train`` asked for if fewer, as ``fit`` takes them), fix the basis and write basis.npz
    and store.json."""
    from ..io.files import write_json, write_npz
    from ..observe import ObserveOptions, observe

    hooks = importlib.import_module(spec.module)
    count = max(1, min(int(hooks.N_REFERENCE), int(n_train)))
    indices = range(spec.reference_start, spec.reference_start + count)
    jobs = [_job(spec, root, "train", i, executor.slots) for i in indices]
    results = _run(executor, _generate, jobs)
    _raise_failed(results)
    results = sorted(results, key=lambda r: r["name"])
    options = ObserveOptions.resolve(None, **spec.observe)
    problems = [observe(Path(r["path"]), options)[0] for r in results]
    meshes = sorted({hooks.mesh_key(p) for p in problems}) if hasattr(hooks, "mesh_key") else []
    if len(meshes) > 1:
        for r in results:  # the refusal is final: nothing of it stays
            drop_instance(root, "train", r["name"])
        _remove_scratch(root)
        raise FeatureStoreError(f"{root}: the first {len(problems)} train instances have "
                                f"{len(meshes)} meshes; a feature store keeps one basis, so "
                                "a family of several meshes trains without --drop-instances")
    basis = hooks.reference_basis(problems)
    write_npz(root / BASIS_FILE, {"basis": basis})
    from .._version import __version__

    meta = {"format": FORMAT, **identity, "basis_sha256": array_sha256({"basis": basis}),
            **({"mesh_key": meshes[0]} if meshes else {}),
            "reference": [r["name"] for r in results],
            "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "vvtbench": __version__}
    write_json(root / STORE_FILE, meta)
    log(f"basis: {basis.shape[1]} vectors from {len(results)} train instances -> "
        f"{root / BASIS_FILE}")
    return FeatureStore(root, meta, basis)


def _run(executor, fn, items: list) -> list:
    """``fn`` of every item on ``executor``, in the items' order."""
    futures = [executor.submit(fn, item) for item in items]
    return [f.result() for f in futures]


def _raise_failed(results: list[dict]) -> None:
    failed = [r for r in results if r["status"] == "error"]
    if not failed:
        return
    first = failed[0]
    message = f"{first['name']}: {first['error']}" + (f" (and {len(failed) - 1} more)"
                                                     if len(failed) > 1 else "")
    if all(r.get("input_error") for r in failed):
        raise FeatureStoreError(message)
    raise RuntimeError(message)


def _write_shard(store: FeatureStore, split: str, results: list[dict], keys: tuple[str, ...]
                 ) -> Path:
    from ..io.files import write_npz

    results = sorted(results, key=lambda r: r["index"])
    arrays = {k: np.concatenate([r["arrays"][k] for r in results]) for k in keys}
    arrays.update(
        names=np.array([r["name"] for r in results]),
        indices=np.array([r["index"] for r in results], dtype=np.int64),
        rows=np.array([len(r["arrays"][keys[0]]) for r in results], dtype=np.int64),
        manifest_sha256=np.array([r["manifest_sha256"] for r in results]),
        features_sha256=np.array([r["features_sha256"] for r in results]),
        meta_json=_meta_array({"format": FORMAT, "split": split,
                               "basis_sha256": store.meta["basis_sha256"],
                               "identity_sha256": store.identity_sha256(),
                               "keys": list(keys)}))
    (store.root / SHARDS).mkdir(exist_ok=True)
    path = store.root / SHARDS / f"{split}-{results[0]['index']:06d}-{results[-1]['index']:06d}.npz"
    write_npz(path, arrays, compressed=False)
    store._entries.pop(split, None)
    return path


def open_for(root: str | Path, spec: StoreSpec) -> FeatureStore:
    """Open the store at ``root`` and refuse it unless it was made for ``spec``."""
    store = FeatureStore.open(root)
    store.check(spec.identity())
    return store


def build_store(root: str | Path, spec: StoreSpec, plan: dict[str, tuple[int, int]],
                workers: int = 1, shard_instances: int = SHARD_INSTANCES,
                log: Callable[[str], None] | None = None) -> FeatureStore:
    """Generate, featurize and drop the instances of ``plan`` into the store at ``root``.

    Parameters
    ----------
    root : the store folder (created; an existing folder must be a store made for ``spec``,
        or empty).
    spec : what the features are of.
    plan : split -> (first index, count), e.g. ``{"train": (0, 20000), "val": (0, 50)}``.
    workers : processes generating and featurizing instances.
    shard_instances : instances per shard (a killed run loses at most the shard in progress,
        and its instances complete in the scratch folder are featurized on the rerun).
    log : called with one line per shard written.

    Returns
    -------
    FeatureStore
        The store, holding every instance of ``plan``.
    """
    from ..bench.executors import make_executor
    from ..io.files import check_free_space
    from ..io.lock import RunLock, RunLocked

    log = log or (lambda line: None)
    root = Path(root)
    identity = spec.identity()
    if root.exists() and not root.is_dir():
        raise FeatureStoreError(f"{root}: not a folder (give a feature store folder)")
    if root.is_dir() and not (root / STORE_FILE).is_file():
        extra = sorted(p.name for p in root.iterdir() if p.name not in (
            ".lock", SCRATCH, BASIS_FILE) and not p.name.startswith(".basis."))
        if extra:
            raise FeatureStoreError(f"{root}: exists and is not a feature store (no "
                                    f"{STORE_FILE}; holds {extra[0]}); give a new or empty "
                                    "folder")
    created = not root.exists()
    root.mkdir(parents=True, exist_ok=True)
    try:
        lock = RunLock(root, remove=True).acquire()
    except RunLocked as error:
        raise FeatureStoreError(str(error)) from None
    hooks = importlib.import_module(spec.module)
    keys = tuple(hooks.STORED_FEATURES)
    executor = make_executor(workers)
    try:
        for stale in (root / SHARDS).glob(".*.tmp.npz"):  # a killed run's unfinished shard
            stale.unlink()
        if (root / STORE_FILE).is_file():
            store = open_for(root, spec)
        else:
            check_free_space(root, int(hooks.N_REFERENCE) * INSTANCE_BYTES, "the basis")
            store = _create(root, spec, identity, plan.get("train", (0, 0))[1], executor, log)
        for split, (start, n) in plan.items():
            have = {e.index for e in store.entries(split)}
            todo = [i for i in range(start, start + n) if i not in have]
            total, t0, cpu, generated = n, time.perf_counter(), 0.0, 0
            for k in range(0, len(todo), shard_instances):
                chunk = todo[k:k + shard_instances]
                check_free_space(root, len(chunk) * INSTANCE_BYTES, f"{len(chunk)} instances")
                tasks = [{"job": _job(spec, root, split, i, workers), "index": i,
                          "module": spec.module, "basis": str(root / BASIS_FILE),
                          "basis_sha256": store.meta["basis_sha256"],
                          "mesh_key": store.meta.get("mesh_key"),
                          "observe": spec.observe} for i in chunk]
                results = _run(executor, featurize_instance, tasks)
                done = [r for r in results if r["status"] != "error"]
                if done:
                    shard = _write_shard(store, split, done, keys)
                    for r in done:
                        drop_instance(root, split, r["name"])
                    cpu += sum(r["cpu_seconds"] for r in done)
                    generated += sum(r["generated"] for r in done)
                    stored = len(store.select(split, start, n))
                    rate = len(done) * 3600 / max(time.perf_counter() - t0, 1e-9)
                    log(f"{split}: {stored}/{total} instances stored ({shard.name}; "
                        f"{generated} generated this run, {rate:.0f} per hour, "
                        f"{cpu / max(len(done), 1):.2f} CPU s each in the featurizing "
                        "process)")
                    t0 = time.perf_counter()
                    cpu, generated = 0.0, 0
                _raise_failed(results)
        _remove_scratch(root)
    finally:
        executor.close()
        lock.release()
        if created and root.is_dir() and not any(root.iterdir()):
            root.rmdir()  # a refused new store leaves no folder
    return store
