"""Generation jobs: one sample per worker process (a local pool or Dask worker).

:func:`generate_instance` generates one sample from a job dict and never raises. Progress
bars: :mod:`vvtbench.samples.progress`.
"""

from __future__ import annotations

from pathlib import Path

from ..scene.scene import SceneError, parse_scene, with_overrides
from .reader import DatasetError

__all__ = ["generate_instance"]


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

    from .generate import generate

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
                from ..scene.families import draw, family_info

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
