"""Generation jobs: one sample per worker process, and per-stage progress reporting.

* :func:`generate_instance`: generate one sample from a job dict (a local pool or Dask
  worker); never raises.
* :class:`StageProgress`: per-stage progress bars plus an optional callback, used by
  :func:`vvtbench.generate.generate`.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from .dataset import DatasetError
from .scene import SceneError, parse_scene
from .scenes_resolve import with_overrides

__all__ = ["ProgressCallback", "StageProgress", "generate_instance"]

ProgressCallback = Callable[[str, int, int], None]


class StageProgress:
    """Per-stage progress bars (rich) plus an optional callback(stage, done, total)."""

    def __init__(self, enabled: bool, callback: ProgressCallback | None, label: str) -> None:
        self.callback = callback
        self.bar = None
        self.label = label
        if enabled:
            from rich.progress import (
                BarColumn,
                MofNCompleteColumn,
                Progress,
                TextColumn,
                TimeElapsedColumn,
                TimeRemainingColumn,
            )

            self.bar = Progress(
                TextColumn("{task.description:<28}"), BarColumn(), MofNCompleteColumn(),
                TimeElapsedColumn(), TimeRemainingColumn(), transient=False,
            )
            self.bar.start()
        self._task = None
        self._stage = ""
        self._total = 0
        self._done = 0

    def stage(self, name: str, total: int, done: int = 0) -> None:
        self._stage, self._total, self._done = name, max(int(total), 1), int(done)
        if self.bar is not None:
            self._task = self.bar.add_task(f"{self.label} {name}", total=self._total,
                                           completed=self._done)
        self._report()

    def advance(self, n: int = 1) -> None:
        self._done += n
        if self.bar is not None and self._task is not None:
            self.bar.update(self._task, completed=self._done)
        self._report()

    def _report(self) -> None:
        if self.callback is not None:
            self.callback(self._stage, self._done, self._total)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.stop()
            self.bar = None


def generate_instance(job: dict) -> dict:
    """Generate one sample for a worker process (a local pool or Dask); never raises.

    ``job``: ``out`` (folder), ``options`` (keyword arguments of :func:`generate`), and
    either ``scene`` (a resolved scene dict) or ``family`` (a family file path or name),
    ``split`` and ``index``; optional ``overrides`` (``frames``, ``duration``,
    ``resolution`` of :func:`with_overrides`), ``threads`` (BLAS threads, e.g. 1 per worker)
    and ``overwrite``. A complete sample already in ``out`` (its ``manifest.json`` exists) is
    skipped. Returns ``{"name", "path", "status": "done" | "skipped" | "error", "seconds",
    "cpu_seconds", "error"}``; ``cpu_seconds`` counts this process (every thread, e.g. the
    software rasterizer's) and the child processes it waited for (ffmpeg).
    """
    import resource
    import time

    from .generate import generate  # generate.py imports StageProgress from here

    def cpu() -> float:
        c = resource.getrusage(resource.RUSAGE_CHILDREN)
        return time.process_time() + c.ru_utime + c.ru_stime

    t0, c0 = time.perf_counter(), cpu()
    out = Path(job["out"])
    name = job.get("name") or (job["scene"]["name"] if "scene" in job else None)
    try:
        limiter = None
        if job.get("threads"):
            from threadpoolctl import threadpool_limits

            limiter = threadpool_limits(int(job["threads"]))
        try:
            if name is not None and (out / name / "manifest.json").is_file() and not job.get(
                    "overwrite"):
                return {"name": name, "path": str(out / name), "status": "skipped",
                        "seconds": time.perf_counter() - t0, "error": None}
            extra = None
            if "scene" in job:
                scene = parse_scene(job["scene"], job.get("source", job["scene"]["name"]))
            else:
                from .families import draw, family_info

                scene = draw(job["family"], job["split"], int(job["index"]))
                extra = {"family.json": family_info(job["family"], job["split"],
                                                    int(job["index"]))}
            scene = with_overrides(scene, **(job.get("overrides") or {}))
            name = scene.name
            path = generate(scene, out, overwrite=bool(job.get("overwrite")), extra_json=extra,
                            **(job.get("options") or {}))
        finally:
            if limiter is not None:
                limiter.restore_original_limits()
    except (SceneError, DatasetError) as error:
        return {"name": name, "path": None, "status": "error", "input_error": True,
                "seconds": time.perf_counter() - t0, "error": str(error)}
    except Exception as error:  # a worker reports, the run goes on
        return {"name": name, "path": None, "status": "error",
                "seconds": time.perf_counter() - t0,
                "error": f"{type(error).__name__}: {error}"}
    return {"name": name, "path": str(path), "status": "done",
            "seconds": time.perf_counter() - t0, "cpu_seconds": cpu() - c0, "error": None}
