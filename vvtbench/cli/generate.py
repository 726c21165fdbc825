"""``vvtbench generate``: render scenes, suites or scene-family instances into sample folders
(argparse front end of :func:`vvtbench.samples.generate.generate`)."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

__all__ = ["build_parser", "disk_bytes", "main", "render_memory_bytes", "run"]

#: Peak memory of one generating process besides its frame buffers (measured: 350 MB at 256^2).
BASE_MEMORY = 360 * 2**20
#: Bytes per rendered (supersampled) pixel at the peak of rendering (measured: 46 between
#: 512^2 and 1024^2 at supersample 4).
BYTES_PER_SUBPIXEL = 48
#: libavutil refuses a frame when (width + 128) * (height + 128) * 8 reaches 2^31
#: (``av_image_check_size``): the largest frame ffmpeg encodes or decodes.
FFMPEG_FRAME_LIMIT = 2**31


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


def _workers(text: str) -> int:
    from ..bench.executors import max_workers

    n = _positive(text)
    if n > max_workers():
        raise argparse.ArgumentTypeError(
            f"{text!r}: allowed: 1 to {max_workers()} (4 per CPU of this machine)")
    return n


def render_memory_bytes(height: int, width: int, supersample: int) -> int:
    """Peak memory of rendering one sample at ``height`` x ``width`` px and ``supersample``."""
    return BASE_MEMORY + BYTES_PER_SUBPIXEL * height * width * supersample**2


def raw_video_bytes(scene, video: bool, consumer_crf: int | None) -> int:
    """The raw frames' size of ``scene``'s video (0 without video): a bound on the encoded
    video, which the lossless codec stores at about 0.6 of it for rendered speckle and at up
    to 1 for noise."""
    if not video:
        return 0
    H, W = scene.camera.resolution
    frames = round(scene.simulation.duration * scene.simulation.fps)
    crf = consumer_crf if consumer_crf is not None else scene.render.consumer_crf
    return frames * H * W * (1 if crf is not None else 2)


def disk_bytes(scene, video: bool, consumer_crf: int | None) -> int:
    """Free space the generation of ``scene`` needs at its peak: the video segments and the
    joined video (each at most :func:`raw_video_bytes`), the dense image modes and 4 MiB. The
    segments go once the video is joined: a finished sample keeps one raw size less."""
    H, W = scene.camera.resolution
    modes = scene.simulation.n_modes * H * W * 2 * 4
    return 2 * raw_video_bytes(scene, video, consumer_crf) + modes + 4 * 2**20


def finished_bytes(out: Path, finished: list[str], video: bool, limit: int = 20) -> int | None:
    """The largest of the first ``limit`` of the ``finished`` samples in ``out`` made the same
    way (with video, or modes only), in bytes; None when there is none. A measured size of
    this run's samples: :func:`disk_bytes` bounds the dense image modes, which the store
    compresses (a modes-only drum takes 12-13 MB of its 137 MB bound)."""
    import json

    from ..io.files import tree_bytes

    sizes = []
    for name in finished[:limit]:
        try:
            info = json.loads((out / name / "truth.json").read_text())
            if (info["video"].get("file") is not None) == video:
                sizes.append(tree_bytes(out / name))
        except (OSError, ValueError, KeyError, TypeError, AttributeError):
            continue
    return max(sizes) if sizes else None


def total_disk_bytes(peaks: list[int], raws: list[int], workers: int) -> int:
    """Free space ``len(peaks)`` samples need when ``workers`` are generated at a time: each
    finished sample's size, and the segments of the ``workers`` largest in flight.

    >>> total_disk_bytes([30, 30, 30], [10, 10, 10], workers=1)
    70
    """
    kept = sum(p - r for p, r in zip(peaks, raws, strict=True))
    return kept + sum(sorted(raws, reverse=True)[:max(1, workers)])


def _physical_memory() -> int:
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def _job_scene(job: dict):
    from ..scene.scene import parse_scene, with_overrides

    if "scene" in job:
        return parse_scene(job["scene"], job.get("source", job["scene"]["name"]))
    from ..scene.families import draw

    scene = draw(job["family"], job["split"], int(job["index"]))
    return with_overrides(scene, **(job.get("overrides") or {}))


def _check_resources(jobs: list[dict], args: argparse.Namespace) -> None:
    """Refuse, before anything is rendered, a frame ffmpeg cannot take, a render larger than
    the memory each worker may use, and a total size larger than the output's free space.
    A family's instances are sized by the first one drawn; where samples of this run are
    already finished in the output, by the largest of them (:func:`finished_bytes`)."""
    from ..io.files import check_free_space
    from ..scene.scene import SceneError

    if not jobs:
        return
    scenes = [_job_scene(job) for job in (jobs if "scene" in jobs[0] else jobs[:1])]
    workers = min(args.workers, len(jobs))
    budget = int(0.75 * _physical_memory() / workers)
    for scene in scenes:
        H, W = scene.camera.resolution
        if not args.no_video and (W + 128) * (H + 128) * 8 >= FFMPEG_FRAME_LIMIT:
            raise SceneError(f"scene {scene.name}: key 'camera.resolution' {H}x{W} is larger "
                             "than ffmpeg can encode; allowed: (height + 128) * (width + 128) "
                             f"< {FFMPEG_FRAME_LIMIT // 8:,}")
        s = scene.render.supersample
        need = render_memory_bytes(H, W, s)
        if args.scheduler is None and need > budget:
            raise SceneError(
                f"scene {scene.name}: rendering {H}x{W} px at render.supersample {s} needs "
                f"about {need:,} bytes of memory; each of {workers} worker(s) may use "
                f"{budget:,} (75 % of this machine's memory); lower key 'camera.resolution' "
                "or 'render.supersample', or use fewer --workers")
    names = [str(job.get("name") or job["scene"]["name"]) for job in jobs]
    todo = [args.overwrite or not (args.out / name / "manifest.json").is_file()
            for name in names]
    sizes = [(disk_bytes(sc, not args.no_video, args.consumer_crf),
              raw_video_bytes(sc, not args.no_video, args.consumer_crf)) for sc in scenes]
    finished = [name for name, t in zip(names, todo, strict=True) if not t]
    measured = finished_bytes(args.out, finished, not args.no_video)
    if measured is not None:  # a finished sample's size, plus the segments while in flight
        sizes = [(min(peak, measured + raw), raw) for peak, raw in sizes]
    sizes = ([b for b, t in zip(sizes, todo, strict=False) if t] if len(scenes) == len(jobs)
             else sizes[:1] * sum(todo))
    in_flight = len(sizes) if args.scheduler is not None else workers  # a cluster: all
    total = total_disk_bytes([p for p, _ in sizes], [r for _, r in sizes], in_flight) \
        if sizes else 0
    if total:
        check_free_space(args.out, total, f"{sum(todo)} sample(s)")


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    """The ``generate`` parser (fills ``parser`` if given, e.g. a sub-command's)."""
    from ..scene.families import MAX_INDEX
    from .args import bounded, instance_count

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
    fam.add_argument("--n", type=instance_count, help="number of family instances")
    fam.add_argument("--start", type=bounded(int, ge=0, le=MAX_INDEX), default=0,
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
    p.add_argument("--workers", type=_workers, default=1,
                   help="local worker processes (default 1: in this process); each uses one "
                        "BLAS thread")
    p.add_argument("--scheduler", default=None,
                   help="Dask scheduler address (tcp://host:8786): generate on that cluster; "
                        "OUT must be a folder every worker can write")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    return p


def _jobs(args: argparse.Namespace) -> list[dict]:
    from ..bench.resolve import resolve_scenes
    from ..scene.families import check_index_range, is_family, load_family
    from ..scene.scene import SceneError, with_overrides

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
        check_index_range(args.start, args.n)
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
            from ..samples.reader import DatasetError

            raise DatasetError(f"{args.out / scene.name} already exists; pass --overwrite to "
                               "replace it")
        jobs.append({**common, "scene": scene.to_toml_dict(),
                     "source": scene.source or scene.name})
    return jobs


def run(args: argparse.Namespace) -> int:
    """Run parsed arguments; returns the exit code (0 ok, 1 a sample failed, 2 bad input)."""
    from ..io.files import NoSpaceError
    from ..samples.reader import DatasetError
    from ..scene.scene import SceneError

    try:
        jobs = _jobs(args)
        _check_resources(jobs, args)
    except (SceneError, DatasetError, NoSpaceError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    from ..io.lock import RunLock, RunLocked

    try:  # one writer per output folder, the lock `run` takes
        Path(args.out).mkdir(parents=True, exist_ok=True)
        lock = RunLock(args.out, remove=True).acquire()
    except (RunLocked, OSError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    try:
        return _generate_jobs(jobs, args)
    finally:
        lock.release()


def _generate_jobs(jobs: list[dict], args: argparse.Namespace) -> int:
    parallel = args.workers > 1 or args.scheduler is not None
    if parallel:
        for job in jobs:
            job["threads"] = 1
    failed = bad_input = 0
    for res in execute_jobs(jobs, args.workers, args.scheduler):
        if res["status"] == "error" and _disk_full(res["error"]):
            failed += 1
            bad_input += 1
            print(f"error: {res['name']}: the disk holding {args.out} became full "
                  f"({_removed_partial(args.out, res['name'])}); free some space and run "
                  "again", file=sys.stderr)
        elif res["status"] == "error":
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


def _disk_full(message: str | None) -> bool:
    import errno

    return any(f"[Errno {n}]" in (message or "") for n in (errno.ENOSPC, errno.EDQUOT))


def _removed_partial(out: Path, name: str | None) -> str:
    """Remove the half-written sample of ``name`` (``out/.NAME.partial``); says what it did."""
    import shutil

    if not name or "/" in name or name.startswith("."):
        return "nothing removed"
    partial = out / f".{name}.partial"
    if partial.is_dir() and not partial.is_symlink():
        shutil.rmtree(partial, ignore_errors=True)
        return f"its partial folder {partial} was removed"
    return "nothing half-written left"


def execute_jobs(jobs: list[dict], workers: int, scheduler: str | None):
    """Yield each job's result as it finishes (in process, a local pool, or Dask)."""
    from ..samples.jobs import generate_instance

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
