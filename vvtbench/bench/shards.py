"""A suite in shards: ``vvtbench run SUITE --shard K/N`` and ``vvtbench merge-shards``.

**The partition.** The task graph of a suite (:func:`~.graph.build_graph`) falls apart into
*units*: the connected pieces of the graph, each the samples of one instance (its scenes, one
per group member) with every extraction, observation, solve and evaluation that reads them.
A unit is never split, so no shard renders or extracts a video another shard needs. Units are
named by the sha256 of their generate keys (content hashes: the same on every machine) and
dealt to the N shards largest first, each to the shard with the least estimated cost so far
(:func:`unit_cost`: pixels rendered and extracted, observations to solve; ties go to the lower
shard). The cost does not depend on the solvers run, so shard K of N holds the same instances
whichever solvers a run names. The selection is made on the graph, before anything is
scheduled: a shard runs the same on one process, a local pool or a Dask cluster.

**The result set of a shard** (``shards/SUITE/K-of-N/``, small enough to commit): the shard's
rows (``results.csv``), the output of each of its solve tasks (``solve/KEY/``: the estimate
and its ``task.json``) and extract tasks (``extract/KEY/``: ``modes.json``, the mode shapes
cut to the pixels their readers read, :mod:`.compact`, and ``task.json``), the error record
of each failed task (``STAGE/KEY.error/``), and ``shard.json``: the suite (file and sha256),
the vvtbench version, the solvers with their versions and configs, the limits, the shard and
its units, the status of every task of the shard, the sha256 each sample's files and each
observation had, the box each extraction's shapes were cut to, and the sha256 of every file
of the folder. Never a video, a sample or an observation (they hold the truth). A result
set over :data:`SIZE_WARNING_BYTES` is reported with its largest files
(:func:`size_warning`).

**Resuming.** A run of a shard seeds its cache from the shard folder it finds (estimates and
extracted modes are not computed again; the modes written back to the full frame, NaN outside
their box) and regenerates the truth of a filmed sample without
rendering its frames when every reader of its video is seeded. A shard that ran to its end is
*complete*: running it again does nothing.

**The merge** (:func:`merge_shards`) checks that the shards are the N shards of one partition
of one suite, by one vvtbench with the same solvers, builds the suite's graph, seeds a run
folder's cache with every estimate and extraction of the shards, regenerates every sample
(without frames), observes again and scores every estimate again: the table is computed, not
copied, and equals the table of an unsharded run of the suite (its run times aside).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import uuid
from dataclasses import dataclass, field
from pathlib import Path

from .._version import __version__
from ..io.files import write_json
from ..samples.reader import sha256_file
from .compact import extraction_box, restore, write_compact
from .graph import Run, Task, content_hash
from .suite import SUITES_DIR, Suite, SuiteError, observation_kind

__all__ = ["CARRIED", "PARTITION", "SHARD_FORMAT", "SIZE_WARNING_BYTES", "Selection", "Shard",
           "ShardError", "ShardSpec", "Unit", "cache_statuses", "default_shard_dir",
           "export_shard", "file_sizes", "partition", "read_shard", "seed_cache",
           "select_shard", "shard_meta", "size_warning", "suite_ref", "suite_sha256",
           "unit_cost", "units"]

#: version of the shard folder's format (``shard.json`` ``format_version``); 2: extracted
#: modes compact (:mod:`.compact`)
SHARD_FORMAT = 2
#: the versions read (a version 1 folder carries each extraction's ``modes.npz`` as it is)
SHARD_FORMATS_READ = (1, 2)
#: a result set larger than this is reported with its largest files (:func:`size_warning`)
SIZE_WARNING_BYTES = 50_000_000
#: how the suite is cut: connected units of the graph, dealt largest first to the least
#: loaded shard by :func:`unit_cost` (a new rule gets a new name: shards cut by different
#: rules never merge)
PARTITION = "units-by-cost-1"
#: the stages whose outputs a shard carries (the rest is recomputed from the scene)
CARRIED = ("extract", "solve")

# rough seconds of one core per unit of work, from benchmarks/RESULTS.md (the standard suite's
# 6-s, 2000-FPS, 256^2 videos: a render at supersample 4 about 2-4 min, an extraction about
# 70 s; the five shipped solvers about 25 s on one 8^3 observation with 20 modes)
_RENDER_S_PER_MPX = 0.004     # per million pixels rendered (supersampling counted)
_EXTRACT_S_PER_MPX = 0.09     # per million pixels of video an extractor reads
_SAMPLE_S = 5.0               # simulate and write the truth of one sample
_OBSERVE_S = 2.0
_SOLVE_S_PER_VOXEL_MODE = 0.003  # the solves of one observation, per voxel and observed mode
_SOLVE_S = 10.0                  # ... and their sealed children's start


class ShardError(SuiteError):
    """Shards that cannot be run or merged as asked; the message names the folder and says
    what is allowed."""


@dataclass(frozen=True)
class ShardSpec:
    """Shard ``k`` of ``n`` (1 <= k <= n)."""

    k: int
    n: int

    @classmethod
    def parse(cls, text: str | ShardSpec) -> ShardSpec:
        if isinstance(text, ShardSpec):
            return text
        k, sep, n = str(text).partition("/")
        try:
            spec = cls(int(k), int(n))
        except ValueError:
            spec = None
        if not sep or spec is None or not 1 <= spec.k <= spec.n:
            raise ShardError(f"--shard {text!r}: not allowed; allowed: K/N with whole numbers "
                             "1 <= K <= N, e.g. 2/8 (the second of eight shards)")
        return spec

    @property
    def name(self) -> str:
        """The shard's folder name, ``K-of-N``."""
        return f"{self.k}-of-{self.n}"

    def __str__(self) -> str:
        return f"{self.k}/{self.n}"


def default_shard_dir(suite: Suite, spec: ShardSpec) -> Path:
    """``shards/SUITE/K-of-N`` (outside ``runs/``, which git ignores)."""
    return Path("shards") / suite.name / spec.name


# --------------------------------------------------------------------------- the partition

@dataclass
class Unit:
    """A connected piece of a suite's task graph: the tasks (graph order) and the rows (indices
    into the runs) that share its samples."""

    id: str
    tasks: list[str]
    runs: list[int]
    cost: float = 0.0
    label: str = ""


def units(tasks: dict[str, Task], runs: list[Run]) -> list[Unit]:
    """The units of a graph, in the order of their first task."""
    parent = {k: k for k in tasks}

    def find(k: str) -> str:
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    for k, t in tasks.items():
        for d in t.deps:
            if d in parent:
                a, b = find(k), find(d)
                if a != b:
                    parent[max(a, b)] = min(a, b)
    members: dict[str, list[str]] = {}
    for k in tasks:
        members.setdefault(find(k), []).append(k)
    rows: dict[str, list[int]] = {}
    for i, run in enumerate(runs):
        anchor = run.observe_key or run.evaluate_key
        if anchor in parent:
            rows.setdefault(find(anchor), []).append(i)
    out = []
    for root, keys in members.items():
        gens = sorted(k for k in keys if tasks[k].stage == "generate")
        label = "+".join(dict.fromkeys(tasks[k].label for k in gens))
        out.append(Unit(content_hash(gens or keys), keys, rows.get(root, []),
                        unit_cost(tasks, keys), label))
    return out


def _scene_numbers(scene: dict) -> tuple[float, float, int]:
    """(video frames, pixels rendered per frame over all views, pixels per frame) of a resolved
    scene dict."""
    try:
        sim, cam, ren = scene.get("simulation", {}), scene.get("camera", {}), scene.get("render",
                                                                                       {})
        frames = float(sim.get("fps", 0)) * float(sim.get("duration", 0)) * float(
            ren.get("frame_average", 1))
        h, w = (cam.get("resolution") or [256, 256])[:2]
        rig = cam.get("rig") if isinstance(cam.get("rig"), dict) else None
        views = int(rig.get("views", 1)) if rig else 1 + len(cam.get("views") or [])
        ss = float(ren.get("supersample", 1))
        return frames, float(h) * float(w) * ss * ss * views, int(h) * int(w)
    except (TypeError, ValueError, AttributeError):
        return 0.0, 0.0, 0


def unit_cost(tasks: dict[str, Task], keys: list[str]) -> float:
    """A rough estimate of a unit's seconds on one core: its renders, its extractions and one
    solve per observation (solvers not counted, so the partition is the same whichever
    solvers run)."""
    cost = 0.0
    for k in keys:
        t = tasks[k]
        if t.stage == "generate":
            cost += _SAMPLE_S
            if t.payload.get("video", True):
                frames, rendered, _ = _scene_numbers(t.payload.get("scene") or {})
                cost += _RENDER_S_PER_MPX * frames * rendered / 1e6
        elif t.stage == "extract":
            gen = tasks.get(t.deps[0]) if t.deps else None
            frames, _, pixels = _scene_numbers((gen.payload.get("scene") or {}) if gen else {})
            cost += _EXTRACT_S_PER_MPX * frames * pixels / 1e6
        elif t.stage == "observe":
            inf = t.payload.get("inference") or {}
            shape = inf.get("inference_shape") or [8, 8, 8]
            voxels = 1
            for s in shape:
                voxels *= int(s)
            cost += _OBSERVE_S + _SOLVE_S + _SOLVE_S_PER_VOXEL_MODE * voxels * int(
                inf.get("n_modes", 10))
    return round(cost, 6)


def partition(tasks: dict[str, Task], runs: list[Run], n: int) -> list[list[Unit]]:
    """The units of each of ``n`` shards: largest estimated cost first, each to the shard with
    the least cost so far (ties: the lower shard); within a shard, in graph order."""
    all_units = units(tasks, runs)
    order = {u.id: i for i, u in enumerate(all_units)}
    loads = [0.0] * n
    shards: list[list[Unit]] = [[] for _ in range(n)]
    for u in sorted(all_units, key=lambda u: (-u.cost, u.id)):
        i = min(range(n), key=lambda j: (loads[j], j))
        shards[i].append(u)
        loads[i] += u.cost
    return [sorted(s, key=lambda u: order[u.id]) for s in shards]


@dataclass
class Selection:
    """What shard ``spec`` of a graph holds."""

    spec: ShardSpec
    tasks: dict[str, Task]
    runs: list[Run]
    units: list[Unit]
    cost: float
    total_cost: float


def select_shard(tasks: dict[str, Task], runs: list[Run], spec: ShardSpec) -> Selection:
    """The tasks and rows of shard ``spec`` (graph order kept); more shards than the suite
    has units is a :class:`ShardError` (a shard would be empty)."""
    parts = partition(tasks, runs, spec.n)
    count = sum(len(p) for p in parts)
    if spec.n > count:
        raise ShardError(f"--shard {spec}: the suite has {count} instance(s) to deal out "
                         f"(samples with what reads them); allowed: N <= {count}")
    mine = parts[spec.k - 1]
    keys = {k for u in mine for k in u.tasks}
    rows = sorted(i for u in mine for i in u.runs)
    return Selection(spec, {k: t for k, t in tasks.items() if k in keys},
                     [runs[i] for i in rows], mine, sum(u.cost for u in mine),
                     sum(u.cost for p in parts for u in p))


# --------------------------------------------------------------------------- task statuses

def cache_statuses(cache: Path, tasks: dict[str, Task]) -> dict[str, dict]:
    """What the cache holds for each task, read without hashing (the run folder's lock is
    held): ``{"status": ok|error|skipped|pending, ...}`` in the form the results table reads
    (``result`` of an ok task, ``error`` and ``traceback`` of a failed one, ``upstream`` of a
    skipped one)."""
    out: dict[str, dict] = {}
    for k, t in tasks.items():
        done = cache / k / "task.json"
        err = cache / f"{k}.error" / "error.json"
        if done.is_file():
            try:
                info = json.loads(done.read_text())
            except (OSError, ValueError):
                info = None
            if isinstance(info, dict):
                out[k] = {"key": k, "status": "ok", "computed": False, "seconds": 0.0,
                          "result": info.get("result") or {}}
                continue
        if err.is_file():
            try:
                msg = json.loads(err.read_text()).get("error") or f"{t.stage}: failed"
            except (OSError, ValueError, AttributeError):
                msg = f"{t.stage}: failed"
            out[k] = {"key": k, "status": "error", "computed": True, "seconds": 0.0,
                      "error": msg, "traceback": f"{k}.error/traceback.txt"}
            continue
        up = next((d for d in t.deps if out.get(d, {}).get("status") in ("error", "skipped")),
                  None)
        if up is not None:
            src = out[up]
            out[k] = {"key": k, "status": "skipped", "computed": False, "seconds": 0.0,
                      "error": src.get("error", "upstream task failed"),
                      "upstream": src.get("upstream", up) if src["status"] == "skipped"
                      else up}
            continue
        out[k] = {"key": k, "status": "pending"}
    return out


def _video_entries(sample_task_dir: Path) -> dict[str, dict]:
    """``{name: {"sha256", "bytes"}}`` of the files a filmed sample holds and a sample
    regenerated without frames withholds (its videos and ``preview.mp4``), names relative to
    the generate task's folder, from the sample's manifest."""
    from .prune import sample_videos

    try:
        manifest = json.loads((sample_task_dir / "sample" / "manifest.json").read_text())
    except (OSError, ValueError):
        return {}
    listed = manifest.get("files") if isinstance(manifest.get("files"), dict) else {}
    names = [*sample_videos(sample_task_dir), "sample/preview.mp4"]
    out = {}
    for name in names:
        entry = listed.get(name.removeprefix("sample/"))
        if isinstance(entry, dict) and isinstance(entry.get("sha256"), str):
            out[name] = {"sha256": entry["sha256"], "bytes": entry.get("bytes")}
    return out


def truth_digest(files: dict[str, str], withheld) -> str:
    """One sha256 over a generate task's sample files but its manifest and withheld videos:
    equal when a sample is regenerated to the same truth."""
    h = hashlib.sha256()
    for name, digest in sorted(files.items()):
        if name in withheld or name == "sample/manifest.json":
            continue
        h.update(f"{name}\0{digest}\n".encode())
    return h.hexdigest()


# --------------------------------------------------------------------------- export

def _copy_verified(src: Path, dest: Path, names: list[str], hashes: dict[str, str]) -> dict:
    """Copy ``names`` from ``src`` to ``dest`` checking each against ``hashes``; returns
    ``{name: sha256}``."""
    out = {}
    dest.mkdir(parents=True, exist_ok=True)
    for name in names:
        f = src / name
        digest = sha256_file(f)
        if name in hashes and hashes[name] != digest:
            raise OSError(f"{f}: sha256 mismatch with its task.json (edited or truncated)")
        shutil.copyfile(f, dest / name)
        out[name] = digest
    return out


def export_shard(dest: Path, cache: Path, selection: Selection, meta: dict,
                 statuses: dict[str, dict] | None = None, modes: str = "exact") -> dict:
    """Write the result set of a shard into ``dest`` (replacing what is there: built beside it
    and renamed into place) from the run's ``cache``; returns its ``shard.json``.

    ``modes``: how the extracted mode shapes are kept (:func:`.compact.extraction_box`):
    ``"exact"`` (every score as the whole frame gives it) or ``"footprint"`` (lossy for
    joined views)."""
    from .results import results_table

    dest = Path(dest)
    statuses = statuses if statuses is not None else cache_statuses(cache, selection.tasks)
    tmp = dest.parent / f".{dest.name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    tmp.mkdir(parents=True)
    try:
        files: dict[str, str] = {}
        records: dict[str, dict] = {}
        for k, t in selection.tasks.items():
            st = statuses.get(k, {"status": "pending"})
            rec: dict = {"stage": t.stage, "label": t.label, "status": st["status"]}
            for f in ("error", "upstream", "traceback"):
                if st.get(f):
                    rec[f] = st[f]
            folder = cache / k
            if st["status"] == "ok" and t.stage == "extract":
                info = json.loads((folder / "task.json").read_text())
                shape = _image_shape(folder)
                box, why = extraction_box(cache, selection.tasks, k, statuses, shape, modes)
                written = write_compact(folder, tmp / k, info, box)
                files.update({f"{k}/{n}": d for n, d in written.items()})
                kept = (info.get("compact") or {}).get("box") or box
                kept = [int(x) for x in kept] if kept else None
                rec["modes"] = {"image_shape": list(shape),
                                "box": None if kept == [0, shape[0], 0, shape[1]] else kept,
                                "why": "as the shard folder it came from" if info.get("compact")
                                else why}
            elif st["status"] == "ok" and t.stage in CARRIED:
                info = json.loads((folder / "task.json").read_text())
                names = sorted(info.get("files") or {})
                copied = _copy_verified(folder, tmp / k, [*names, "task.json"],
                                        info.get("files") or {})
                files.update({f"{k}/{n}": d for n, d in copied.items()})
            elif st["status"] == "ok" and t.stage == "generate":
                info = json.loads((folder / "task.json").read_text())
                videos = _video_entries(folder) if t.payload.get("video", True) else {}
                if videos:
                    rec["videos"] = videos
                rec["truth_sha256"] = truth_digest(info.get("files") or {}, videos)
            elif st["status"] == "ok" and t.stage == "observe":
                from .stages import observation_sha256

                rec["observation_sha256"] = observation_sha256(folder)
            elif st["status"] == "error" and (cache / f"{k}.error").is_dir():
                err = cache / f"{k}.error"
                names = sorted(p.name for p in err.iterdir() if p.is_file())
                copied = _copy_verified(err, tmp / f"{k}.error", names, {})
                files.update({f"{k}.error/{n}": d for n, d in copied.items()})
            records[k] = rec
        df = results_table(selection.runs, statuses)
        with open(tmp / "results.csv", "w", newline="") as fh:
            df.to_csv(fh, index=False)
        files["results.csv"] = sha256_file(tmp / "results.csv")
        pending = sum(r["status"] == "pending" for r in records.values())
        counts = {"rows": len(df), **{s: int((df["status"] == s).sum())
                                      for s in ("ok", "invalid", "error")},
                  "tasks": len(records), "tasks_pending": pending,
                  "tasks_failed": sum(r["status"] == "error" for r in records.values())}
        doc = {"format": "vvtbench-shard", "format_version": SHARD_FORMAT,
               "vvtbench": __version__, **meta, "extracted_modes": modes,
               "shard": {"k": selection.spec.k, "n": selection.spec.n, "partition": PARTITION,
                         "units": [u.id for u in selection.units],
                         "estimated_cost_s": round(selection.cost, 1),
                         "suite_estimated_cost_s": round(selection.total_cost, 1)},
               "complete": pending == 0, "counts": counts, "tasks": records,
               "bytes": sum((tmp / n).stat().st_size for n in files), "files": files}
        write_json(tmp / "shard.json", doc)
        _swap_into_place(tmp, dest)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return doc


def _image_shape(folder: Path) -> tuple[int, int]:
    """``(H, W)`` of an extraction's mode shapes (its ``modes.json``)."""
    doc = json.loads((folder / "modes.json").read_text())
    height, width = doc["image_shape"]
    return int(height), int(width)


def file_sizes(folder: Path, names) -> list[tuple[str, int]]:
    """``[(name, bytes)]`` of the files ``names`` of ``folder``, largest first (ties by
    name)."""
    sizes = [(n, (Path(folder) / n).stat().st_size) for n in names]
    return sorted(sizes, key=lambda x: (-x[1], x[0]))


def size_warning(folder: Path, doc: dict, limit: int | None = None,
                 show: int = 5) -> str | None:
    """One line when the result set in ``folder`` (its ``shard.json`` ``doc``) is larger than
    ``limit`` bytes (default :data:`SIZE_WARNING_BYTES`), naming its ``show`` largest files;
    None when it is not."""
    limit = SIZE_WARNING_BYTES if limit is None else limit
    sizes = file_sizes(folder, [*doc.get("files", {}), "shard.json"])
    total = sum(b for _, b in sizes)
    if total <= limit:
        return None
    largest = ", ".join(f"{n} ({b / 1e6:.1f} MB)" for n, b in sizes[:show])
    return (f"warning: shard folder {folder} holds {total / 1e6:.1f} MB, more than "
            f"{limit / 1e6:.0f} MB; largest files: {largest}")


def _swap_into_place(tmp: Path, dest: Path) -> None:
    if dest.exists() or dest.is_symlink():
        trash = dest.parent / f".{dest.name}.old-{os.getpid()}-{uuid.uuid4().hex[:8]}"
        os.replace(dest, trash)
        os.replace(tmp, dest)
        shutil.rmtree(trash, ignore_errors=True)
    else:
        os.replace(tmp, dest)


# --------------------------------------------------------------------------- read

@dataclass
class Shard:
    """A shard folder read back and checked against its ``shard.json``."""

    path: Path
    meta: dict
    rows: object = field(repr=False)  # the rows (a DataFrame)

    @property
    def spec(self) -> ShardSpec:
        return ShardSpec(int(self.meta["shard"]["k"]), int(self.meta["shard"]["n"]))

    @property
    def complete(self) -> bool:
        return bool(self.meta.get("complete"))

    @property
    def tasks(self) -> dict[str, dict]:
        return self.meta.get("tasks") or {}

    def solvers(self) -> list[str]:
        return list(self.meta.get("solver_specs") or [])


def read_shard(path: str | Path) -> Shard:
    """Read a shard folder; every file ``shard.json`` lists is checked against its sha256
    (:class:`ShardError` naming the first that differs)."""
    from .results import read_results

    path = Path(path)
    doc_path = path / "shard.json"
    if not doc_path.is_file():
        raise ShardError(f"{path}: not a shard folder (no shard.json); shard folders are "
                         "written by `vvtbench run SUITE --shard K/N`")
    try:
        doc = json.loads(doc_path.read_text())
    except (OSError, ValueError) as error:
        raise ShardError(f"{doc_path}: unreadable ({error})") from None
    if not isinstance(doc, dict) or doc.get("format") != "vvtbench-shard":
        raise ShardError(f"{doc_path}: not a shard record (key 'format' must be "
                         "'vvtbench-shard')")
    if doc.get("format_version") not in SHARD_FORMATS_READ:
        raise ShardError(f"{doc_path}: key 'format_version' = {doc.get('format_version')!r} "
                         f"is not allowed (allowed: {', '.join(map(str, SHARD_FORMATS_READ))}; "
                         f"this vvtbench writes {SHARD_FORMAT})")
    for key in ("shard", "tasks", "files", "suite", "solver_specs"):
        if key not in doc:
            raise ShardError(f"{doc_path}: key {key!r} missing")
    files = doc["files"]
    for name, digest in files.items():
        f = path / name
        if ".." in Path(name).parts or Path(name).is_absolute():
            raise ShardError(f"{doc_path}: file {name!r} is not inside the folder")
        if not f.is_file():
            raise ShardError(f"{f}: missing (listed in {doc_path})")
        if sha256_file(f) != digest:
            raise ShardError(f"{f}: sha256 mismatch with {doc_path} (edited or truncated)")
    rows = read_results(path / "results.csv")
    return Shard(path, doc, rows)


# --------------------------------------------------------------------------- seeding

def _place(src: Path, dest: Path) -> None:
    """Copy the folder ``src`` to ``dest`` atomically (beside it, then renamed)."""
    tmp = dest.parent / f"{dest.name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    shutil.copytree(src, tmp)
    if dest.exists():
        trash = dest.parent / f"{dest.name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}.stale"
        os.replace(dest, trash)
        shutil.rmtree(trash, ignore_errors=True)
    os.replace(tmp, dest)


def _reads_video(task: Task) -> bool:
    """A task that opens a sample's video: an extraction, or an observation that extracts
    from several views itself."""
    if task.stage == "extract":
        return True
    if task.stage == "observe":
        views = int((task.payload.get("inference") or {}).get("views", 1) or 1)
        return observation_kind(task.payload.get("observation", "true")) == "extracted" and \
            views > 1
    return False


def seed_cache(cache: Path, tasks: dict[str, Task], shards: list[Shard],
               errors: bool = False) -> dict[str, int]:
    """Put the estimates and extractions the shards carry into the run's ``cache`` where it
    has no intact output of that task, and mark each filmed sample whose video no unseeded
    task reads to be regenerated without frames (its generate task's payload gets
    ``frames = False`` and the sha256 of the videos it withholds). ``errors``: copy the error
    records of failed tasks too (what a merge shows). Returns counts."""
    from .stages import cached_state

    cache = Path(cache)
    seeded = {"extract": 0, "solve": 0, "errors": 0, "without_frames": 0}
    carried: set[str] = set()
    videos: dict[str, dict] = {}
    for shard in shards:
        for k, rec in shard.tasks.items():
            if k not in tasks:
                continue
            t = tasks[k]
            src = shard.path / k
            if rec.get("status") == "ok" and t.stage in CARRIED and src.is_dir():
                carried.add(k)
                info, why = cached_state(cache, t)
                if info is None or why is not None:
                    (cache / t.stage).mkdir(parents=True, exist_ok=True)
                    if t.stage == "extract":
                        restore(src, cache / k)
                    else:
                        _place(src, cache / k)
                    seeded[t.stage] += 1
            elif rec.get("status") == "error" and errors and (shard.path / f"{k}.error").is_dir():
                (cache / t.stage).mkdir(parents=True, exist_ok=True)
                _place(shard.path / f"{k}.error", cache / f"{k}.error")
                seeded["errors"] += 1
            if t.stage == "generate" and rec.get("status") == "ok" and rec.get("videos"):
                videos[k] = rec["videos"]
    readers: dict[str, list[str]] = {}
    for k, t in tasks.items():
        for d in t.deps:
            if d in tasks and tasks[d].stage == "generate":
                readers.setdefault(d, []).append(k)
    for g, withheld in videos.items():
        t = tasks[g]
        if not t.payload.get("video", True) or (cache / g / "task.json").is_file():
            continue
        if all(r in carried or not _reads_video(tasks[r]) for r in readers.get(g, [])):
            t.payload = {**t.payload, "frames": False, "withheld": withheld}
            seeded["without_frames"] += 1
    return seeded


# --------------------------------------------------------------------------- merge

def suite_sha256(suite: Suite) -> str:
    return sha256_file(Path(suite.source))


def suite_ref(suite: Suite) -> str:
    """How to name the suite on another machine: its name when it is a shipped suite, else
    its file as given."""
    try:
        if Path(suite.source).resolve().parent == SUITES_DIR.resolve():
            return suite.name
    except OSError:
        pass
    return str(suite.source)


def shard_meta(suite: Suite, solvers: list[str], runs: list[Run], solver_config: dict,
               limits: dict) -> dict:
    """What identifies the run a shard belongs to (``shard.json``)."""
    seen: dict[str, dict] = {}
    for r in runs:
        seen.setdefault(f"{r.solver}\0{r.config_hash}", {
            "spec": r.solver, "name": r.solver_name or r.solver, "version": r.solver_version,
            "config": r.config or {}, "config_hash": r.config_hash,
            "reference": bool(r.reference), **({"setup_error": r.setup_error}
                                               if r.setup_error else {})})
    return {"suite": {"name": suite.name, "ref": suite_ref(suite), "file": str(suite.source),
                      "sha256": suite_sha256(suite)},
            "solver_specs": list(solvers), "solver_config": solver_config or {},
            "solvers": list(seen.values()),
            "limits": {"timeout_s": limits.get("timeout"),
                       "memory_bytes": limits.get("memory_bytes")}}
