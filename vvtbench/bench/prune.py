"""Videos that do not fill the disk: ``vvtbench run --prune-videos``.

A generate task's sample holds one lossless video per view (``truth.json``: ``video.file``
and each ``views`` entry's ``video_file``); a 6-s, 2000-FPS, 256x256 view is about 1 GB. The
tasks that read them are the generate task's direct dependants in the graph: each extract
task (its view's video, or the video a field track re-encodes into a temporary folder the
task removes itself) and each observe task (it opens the sample verified against its manifest,
videos included; a multi-view observation reads every view's video again for its phasors).

With pruning on, once every one of those tasks is done the sample's video files are deleted
and the generate task's ``task.json`` records them under ``"pruned"`` (name, bytes, sha256,
when); the cached output stays valid (:func:`~vvtbench.bench.stages.verify_cached` accepts a
recorded pruned file as absent). A later run that needs a pruned video again (a reader whose
output is not cached or is damaged, or a run whose product is the samples themselves) renders
the sample again; renders are seeded, so the new videos' sha256 are checked against the
recorded ones, and when one differs every cached task downstream of the sample is computed
again rather than mixed with the new video. All of it happens in the process that schedules
the graph (:func:`~vvtbench.bench.executors.execute_graph`), whichever executor runs the
tasks, and only between tasks: never while a reader runs.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

from ..io.files import write_json
from .graph import Task
from .pruned import PRUNED, excused, pruned_files

__all__ = ["PRUNED", "VideoPlan", "dependants", "excused", "prune_sample", "pruned_absent",
           "pruned_files", "sample_videos", "video_readers"]


def pruned_absent(task_dir: Path) -> set[str]:
    """The :func:`excused` files of a cached task folder that are absent: what a check of the
    folder does not count as missing."""
    try:
        info = json.loads((Path(task_dir) / "task.json").read_text())
    except (OSError, ValueError):
        return set()
    return {n for n in excused(info) if not (Path(task_dir) / n).is_file()}


def sample_videos(task_dir: Path) -> list[str]:
    """The video files of the sample a generate task wrote, relative to the task folder (its
    own video and every view's); empty for a modes-only sample."""
    try:
        info = json.loads((Path(task_dir) / "sample" / "truth.json").read_text())
    except (OSError, ValueError):
        return []
    video = info.get("video") if isinstance(info.get("video"), dict) else {}
    names = [video.get("file")]
    views = info.get("views")
    names += [v.get("video_file") for v in (views if isinstance(views, list) else [])
              if isinstance(v, dict)]
    out = []
    for name in names:  # a rig's views list may name view 0's video again
        if isinstance(name, str) and name and ".." not in Path(name).parts \
                and not Path(name).is_absolute() and f"sample/{name}" not in out:
            out.append(f"sample/{name}")
    return out


def video_readers(tasks: dict[str, Task]) -> dict[str, list[str]]:
    """For every generate task that renders video, the keys of the tasks that read its
    sample: its direct dependants (extract and observe tasks)."""
    readers: dict[str, list[str]] = {k: [] for k, t in tasks.items()
                                     if t.stage == "generate" and t.payload.get("video", True)}
    for k, t in tasks.items():
        for d in t.deps:
            if d in readers:
                readers[d].append(k)
    return readers


def dependants(tasks: dict[str, Task], key: str) -> list[str]:
    """Every task downstream of ``key``, directly or not, in the order of ``tasks``."""
    children: dict[str, list[str]] = {}
    for k, t in tasks.items():
        for d in t.deps:
            children.setdefault(d, []).append(k)
    below: set[str] = set()
    todo = [key]
    while todo:
        for k in children.get(todo.pop(), []):
            if k not in below:
                below.add(k)
                todo.append(k)
    return [k for k in tasks if k in below]


def _intact(cache: Path, task: Task) -> bool:
    from .stages import cached_state

    info, why = cached_state(cache, task)
    return info is not None and why is None


def prune_sample(cache: Path, gen_key: str) -> dict:
    """Delete the video files of a generate task's sample and record them in its
    ``task.json`` (written atomically before any file goes): ``{"files": n, "bytes": n}``
    deleted now (zero when there were none left)."""
    from ..samples.reader import sha256_file

    folder = Path(cache) / gen_key
    info = json.loads((folder / "task.json").read_text())
    hashes = info.get("files") if isinstance(info.get("files"), dict) else {}
    present = [rel for rel in sample_videos(folder) if (folder / rel).is_file()]
    if not present:
        return {"files": 0, "bytes": 0}
    entries = {name: {"name": name, **e} for name, e in pruned_files(info).items()}
    for rel in present:
        digest = hashes.get(rel) or sha256_file(folder / rel)
        entries[rel] = {"name": rel, "bytes": (folder / rel).stat().st_size, "sha256": digest}
    record = {"at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
              "files": list(entries.values())}
    write_json(folder / "task.json", {**info, PRUNED: record})
    freed = 0
    for rel in present:
        freed += entries[rel]["bytes"]
        (folder / rel).unlink(missing_ok=True)
    return {"files": len(present), "bytes": freed}


@dataclass
class VideoPlan:
    """What the scheduler does about pruned and prunable videos in one run of a graph.

    Built before the run from the cache (:meth:`build`); :meth:`force_of` says which tasks
    are computed again although cached, :meth:`blocked` which cannot run, and
    :meth:`finished`, called for every finished task, prunes (``prune=True``) and checks
    re-rendered videos against the recorded sha256."""

    tasks: dict[str, Task]
    cache: Path
    prune: bool = False
    readers: dict[str, list[str]] = field(default_factory=dict)
    #: generate key -> ``{name: {"bytes", "sha256"}}`` of its videos pruned before the run
    records: dict[str, dict] = field(default_factory=dict)
    #: generate key -> the readers that need its pruned video again
    needed: dict[str, list[str]] = field(default_factory=dict)
    #: task key -> why it is computed again although its cached output is intact
    forced: dict[str, str] = field(default_factory=dict)
    #: what was pruned in this run: samples, files, bytes
    freed: dict[str, int] = field(default_factory=lambda: {"samples": 0, "files": 0,
                                                           "bytes": 0})
    #: one dict per sample rendered again over recorded pruned videos
    rerendered: list[dict] = field(default_factory=list)
    #: samples whose videos could not be pruned, one line each
    errors: list[str] = field(default_factory=list)
    _pruned: set[str] = field(default_factory=set)

    @classmethod
    def build(cls, tasks: dict[str, Task], cache: Path, prune: bool = False) -> VideoPlan:
        """The plan of a run of ``tasks`` on the cache ``cache``."""
        from .stages import cached_state

        plan = cls(tasks, Path(cache), prune, video_readers(tasks))
        for g in plan.readers:
            try:  # cheap first: only a sample with pruned videos is looked at closer
                record = pruned_files(json.loads((plan.cache / g / "task.json").read_text()))
            except (OSError, ValueError):
                continue
            gone = {n: e for n, e in record.items() if not (plan.cache / g / n).is_file()}
            if not gone:
                continue
            plan.records[g] = gone
            _, why = cached_state(plan.cache, tasks[g])
            if why is not None:
                continue  # damaged: rendered again anyway, and checked against the record
            need = [r for r in plan.readers[g] if not _intact(plan.cache, tasks[r])]
            if need or not plan.readers[g]:  # no reader here: the run's product is the sample
                plan.needed[g] = need
                plan.forced[g] = (f"its pruned video is needed again by {len(need)} task(s)"
                                  if need else "its pruned video is needed again (the "
                                  "samples are this run's output)")
        return plan

    def force_of(self, key: str) -> str | None:
        """Why the task ``key`` is computed again although cached, or None."""
        return self.forced.get(key)

    def blocked(self, key: str, done: dict[str, dict]) -> tuple[str, str] | None:
        """``(generate key, why)`` when the task ``key`` cannot run: it needs a pruned video
        whose sample failed to render again (None otherwise)."""
        for g in self.tasks[key].deps:
            if key in self.needed.get(g, ()) and done.get(g, {}).get("status") != "ok":
                return g, (f"{self.tasks[g].label}: its pruned video could not be rendered "
                           f"again ({done.get(g, {}).get('error', 'generate failed')})")
        return None

    def finished(self, key: str, done: dict[str, dict]) -> None:
        """Task ``key`` has its result in ``done``: check a re-rendered sample's videos, and
        prune every sample whose readers are now all done."""
        task = self.tasks[key]
        if task.stage == "generate":
            self._check_render(key, done[key])
        for g in [key] if task.stage == "generate" else task.deps:
            if self.prune and g in self.readers:
                self._maybe_prune(g, done)

    def _check_render(self, g: str, result: dict) -> None:
        record = self.records.get(g)
        if record is None or result.get("status") != "ok" or not result.get("computed"):
            return
        try:
            now = json.loads((self.cache / g / "task.json").read_text()).get("files") or {}
        except (OSError, ValueError):
            now = {}
        differ = [(n, e["sha256"], now.get(n)) for n, e in record.items()
                  if now.get(n) != e["sha256"]]
        entry = {"task": g, "label": self.tasks[g].label,
                 "why": self.forced.get(g, "its cached output was damaged"),
                 "needed_by": len(self.needed.get(g, [])), "same": not differ,
                 "recomputed": 0}
        if differ:
            name, old, new = differ[0]
            why = (f"the video {name} rendered again differs from the pruned one (sha256 "
                   f"{(new or 'none')[:12]}... against {old[:12]}...)")
            below = dependants(self.tasks, g)
            for k in below:
                self.forced.setdefault(k, why)
            entry.update(recomputed=len(below), file=name, sha256_recorded=old,
                         sha256_now=new)
        self.rerendered.append(entry)

    def _maybe_prune(self, g: str, done: dict[str, dict]) -> None:
        readers = self.readers[g]
        if (g in self._pruned or not readers or done.get(g, {}).get("status") != "ok"
                or not all(r in done for r in readers)):
            return
        self._pruned.add(g)
        try:
            gone = prune_sample(self.cache, g)
        except (OSError, ValueError) as error:  # the videos stay; the run goes on
            self.errors.append(f"{g} ({self.tasks[g].label}): videos not pruned: {error}")
            return
        if gone["files"]:
            self.freed["samples"] += 1
            self.freed["files"] += gone["files"]
            self.freed["bytes"] += gone["bytes"]
