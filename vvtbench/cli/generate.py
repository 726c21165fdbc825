"""``vvtbench generate``: render scenes, suites or scene-family instances into sample folders
(argparse front end of :func:`vvtbench.generate.generate`)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

__all__ = ["build_parser", "main", "run"]


def _resolution(text: str) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"resolution must be HxW, e.g. 256x256; got {text!r}"
                                         ) from None
    return h, w


def _positive(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text!r}")
    return n


def _non_negative(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        n = -1
    if n < 0:
        raise argparse.ArgumentTypeError(f"must be an integer >= 0, got {text!r}")
    return n


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    """The ``generate`` parser (fills ``parser`` if given, e.g. a sub-command's)."""
    p = parser or argparse.ArgumentParser(
        prog="vvtbench generate", description="Render scenes into sample folders "
        "(video + ground truth); see docs/dataset.md and docs/families.md.")
    p.add_argument("scene", metavar="SCENE_SUITE_OR_FAMILY",
                   help="scene file or shipped scene name, a folder of scene TOMLs, a suite "
                        "(its [defaults] applied), or a scene family (with --split and --n)")
    p.add_argument("-o", "--out", required=True, type=Path, help="output folder")
    fam = p.add_argument_group("scene families (docs/families.md)")
    fam.add_argument("--split", choices=("train", "val", "test"),
                     help="family split to draw instances from")
    fam.add_argument("--n", type=_positive, help="number of family instances")
    fam.add_argument("--start", type=_non_negative, default=0,
                     help="first instance index (default 0): instances START..START+N-1")
    length = p.add_mutually_exclusive_group()
    length.add_argument("--frames", type=int, help="number of video frames (overrides duration)")
    length.add_argument("--duration", type=float, help="video length in seconds")
    p.add_argument("--resolution", type=_resolution, help="HxW output size, e.g. 256x256")
    p.add_argument("--overwrite", action="store_true", help="replace existing sample folders")
    p.add_argument("--consumer-crf", type=int, default=None,
                   help="write an 8-bit H.264 video at this CRF instead of lossless 16-bit")
    p.add_argument("--no-video", action="store_true",
                   help="modes-only sample: the ground truth without video or transient")
    p.add_argument("--workers", type=_positive, default=1,
                   help="local worker processes (default 1: in this process); each uses one "
                        "BLAS thread")
    p.add_argument("--scheduler", default=None,
                   help="Dask scheduler address (tcp://host:8786): generate on that cluster; "
                        "OUT must be a folder every worker can write")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    return p


def _jobs(args: argparse.Namespace) -> list[dict]:
    from ..families import is_family, load_family
    from ..scene import SceneError
    from ..scenes_resolve import resolve_scenes, with_overrides

    overrides = {"frames": args.frames, "duration": args.duration,
                 "resolution": args.resolution}
    options = {"video": not args.no_video, "consumer_crf": args.consumer_crf,
               "progress": not args.no_progress and args.workers == 1
               and args.scheduler is None}
    common = {"out": str(args.out), "options": options, "overwrite": args.overwrite}
    if is_family(args.scene):
        if args.split is None or args.n is None:
            raise SceneError(f"{args.scene}: a scene family needs --split (train, val or test) "
                             "and --n (number of instances)")
        fam = load_family(args.scene)
        return [{**common, "family": fam.source, "split": args.split, "index": i,
                 "name": f"{fam.name}-{args.split}-{i:05d}", "overrides": overrides}
                for i in range(args.start, args.start + args.n)]
    if args.split is not None or args.n is not None or args.start:
        raise SceneError(f"{args.scene}: --split, --n and --start are for scene families "
                         "(docs/families.md); this is a scene or suite")
    jobs = []
    for scene in resolve_scenes(args.scene):
        scene = with_overrides(scene, **overrides)
        if (args.out / scene.name).exists() and not args.overwrite:
            from ..dataset import DatasetError

            raise DatasetError(f"{args.out / scene.name} already exists; pass --overwrite to "
                               "replace it")
        jobs.append({**common, "scene": scene.to_toml_dict(),
                     "source": scene.source or scene.name})
    return jobs


def run(args: argparse.Namespace) -> int:
    """Run parsed arguments; returns the exit code (0 ok, 1 a sample failed, 2 bad input)."""
    from ..dataset import DatasetError
    from ..scene import SceneError

    try:
        jobs = _jobs(args)
    except (SceneError, DatasetError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    parallel = args.workers > 1 or args.scheduler is not None
    if parallel:
        for job in jobs:
            job["threads"] = 1
    failed = bad_input = 0
    for res in execute_jobs(jobs, args.workers, args.scheduler):
        if res["status"] == "error":
            failed += 1
            bad_input += bool(res.get("input_error"))
            print(f"error: {res['name']}: {res['error']}", file=sys.stderr)
        elif res["status"] == "skipped":
            print(f"{res['name']}: {res['path']} (exists, skipped)")
        else:
            print(f"{res['name']}: {res['path']}" + (f" ({res['seconds']:.1f} s)"
                                                     if parallel else ""))
    if failed:
        return 2 if bad_input == failed else 1
    return 0


def execute_jobs(jobs: list[dict], workers: int, scheduler: str | None):
    """Yield each job's result as it finishes (in process, a local pool, or Dask)."""
    from ..generate_jobs import generate_instance

    if scheduler is None and workers == 1:
        for job in jobs:
            yield generate_instance(job)
        return
    from ..bench.executors import make_executor

    executor = make_executor(workers, scheduler)
    try:
        pending = {}
        queue = list(jobs)
        limit = max(2 * workers, 4) if scheduler is None else len(jobs)
        while queue or pending:
            while queue and len(pending) < limit:
                job = queue.pop(0)
                pending[executor.submit(generate_instance, job)] = job
            for fut in executor.wait_any(list(pending)):
                job = pending.pop(fut)
                try:
                    yield fut.result()
                except Exception as error:  # a worker died
                    yield {"name": job.get("name") or job.get("scene", {}).get("name"),
                           "path": None, "status": "error", "seconds": 0.0,
                           "error": f"worker failure: {type(error).__name__}: {error}"}
    finally:
        executor.close()


def main(argv: list[str] | None = None) -> int:
    """``vvtbench generate``: returns the exit code (0 ok, 2 bad input, 1 failure)."""
    return run(build_parser().parse_args(argv))
