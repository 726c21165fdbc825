"""Dataset-generation throughput of scene families.

Prints:
1. modes-only instances of ``cube_defects`` per hour with ``--workers`` local processes
   (goal: >= 3000 per hour on 2 cores), through the same path as
   ``vvtbench generate cube_defects --split val --n N --no-video --workers W``;
2. where the time of one modes-only instance goes (cProfile, one process, one BLAS thread):
   eigen-solve, assembly, renderer set-up, GL draws, rasterizer, zarr writes, the rest;
3. (--video N) video instances at the paper's settings (6 s at 2000 FPS, 256^2) per hour with
   the same workers (goal: >= 40 per hour), or with --video-seconds S a shorter video
   extrapolated to 6 s; and where one video instance's time goes (simulate, render, sensor
   model, encode).

The machine's load average is printed before and after: other jobs distort every number.

Usage: python benchmarks/bench_generate.py [--modes 40] [--workers 2] [--video 0]
       [--video-seconds 6]
"""

from __future__ import annotations

import argparse
import cProfile
import os
import platform
import pstats
import tempfile
import time
from pathlib import Path


def _load() -> str:
    return " ".join(f"{x:.1f}" for x in os.getloadavg())


def _throughput(n: int, workers: int, video: bool, out: Path, seconds: float | None) -> float:
    from vvtbench.cli.generate import execute_jobs
    from vvtbench.scene.families import load_family

    fam = load_family("cube_defects")
    overrides = {"frames": None, "duration": seconds, "resolution": None}
    jobs = [{"out": str(out), "family": fam.source, "split": "val", "index": i,
             "name": f"cube_defects-val-{i:05d}", "overrides": overrides,
             "options": {"video": video, "progress": False},
             "threads": 1 if workers > 1 else None} for i in range(n)]
    t0 = time.perf_counter()
    results = list(execute_jobs(jobs, workers, None))
    wall = time.perf_counter() - t0
    bad = [r for r in results if r["status"] != "done"]
    if bad:
        raise SystemExit(f"failed: {bad[0]}")
    per = sorted(r["seconds"] for r in results)
    cpu = sorted(r["cpu_seconds"] for r in results)
    med = cpu[len(cpu) // 2]
    print(f"  {n} instances, {workers} worker(s): {wall:.1f} s wall, per instance median "
          f"{per[len(per) // 2]:.2f} s (min {per[0]:.2f}, max {per[-1]:.2f}) -> "
          f"{3600 * n / wall:.0f} per hour")
    print(f"  CPU time per instance (process + threads + ffmpeg): median {med:.2f} s (min "
          f"{cpu[0]:.2f}, max {cpu[-1]:.2f}) -> {workers} busy cores would make "
          f"{workers * 3600 / (sum(cpu) / len(cpu)):.0f} per hour")
    return 3600 * n / wall


GROUPS = {  # cProfile cumulative time of these functions (substring of file:function)
    "eigen-solve (fem/modal.py eigenmodes)": "modal.py:eigenmodes",
    "assembly (K, M)": "simulate.py:build_model",
    "mesh": "simulate.py:build_mesh",
    "renderer set-up (EGL context, scene, texture)": "generate.py:scene_renderer",
    "GL rest render + depth + visibility": "generate.py:_rest_views",
    "truth.zarr (all)": "generate.py:_write_truth",
    "  of which numpy rasterizer": "raster.py:rasterize",
    "  of which voxel overlap": "voxels.py:overlap_matrix",
    "render frames (GL)": "pyrender_backend.py:render",
    "sensor model (noise, quantize)": "sensor.py:sensor_dn",
    "encode (ffmpeg pipe writes)": "video.py:write",
    "join segments (ffmpeg)": "video.py:concat_videos",
    "transient (modal superposition)": "simulate.py:_transient",
    "displacement frames": "simulate.py:displacement_frames",
    "preview": "generate.py:_preview",
    "manifest (sha256)": "generate.py:_write_manifest",
    "draw (families)": "families.py:draw",
}


def _profile(video: bool, out: Path, seconds: float | None, index: int) -> None:
    from threadpoolctl import threadpool_limits

    from vvtbench.samples.generate import generate
    from vvtbench.scene.families import draw
    from vvtbench.scene.scene import with_overrides

    threadpool_limits(1)
    scene = with_overrides(draw("cube_defects", "val", index), duration=seconds)
    generate(draw("cube_defects", "val", index + 1), out / "warm", video=False,
             progress=False)  # imports, EGL and texture warm
    prof = cProfile.Profile()
    t0 = time.perf_counter()
    prof.enable()
    generate(with_overrides(draw("cube_defects", "val", index), duration=seconds), out,
             video=video, progress=False)
    prof.disable()
    total = time.perf_counter() - t0
    stats = pstats.Stats(prof).stats
    cum: dict[str, float] = {}
    for (file, _line, func), (_cc, _nc, _tt, ct, _callers) in stats.items():
        key = f"{Path(file).name}:{func}"
        cum[key] = max(cum.get(key, 0.0), ct)
    print(f"  one {'video' if video else 'modes-only'} instance ({scene.name}"
          f"{f', {seconds:g} s of video' if video else ''}): {total:.2f} s (profiled)")
    for label, key in GROUPS.items():
        t = cum.get(key, 0.0)
        if t > 0.005 * total:
            print(f"    {label:48s} {t:7.2f} s  {100 * t / total:5.1f} %")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--modes", type=int, default=40, help="modes-only instances (0: skip)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--video", type=int, default=0, help="video instances (0: skip)")
    ap.add_argument("--video-seconds", type=float, default=None,
                    help="video length (s) instead of the paper's 6 s; per hour is scaled to 6 s")
    ap.add_argument("--no-profile", action="store_true")
    args = ap.parse_args()
    print(f"machine: {platform.node()}, {os.cpu_count()} cores, load average {_load()}")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        if args.modes:
            print("modes-only cube_defects:")
            _throughput(args.modes, args.workers, False, tmp / "modes", None)
            if not args.no_profile:
                _profile(False, tmp / "prof_modes", None, 1000)
        if args.video:
            s = args.video_seconds
            print(f"video cube_defects ({s or 6:g} s at 2000 FPS, 256^2):")
            rate = _throughput(args.video, args.workers, True, tmp / "video", s)
            if s:
                print(f"  scaled to 6 s videos (render/encode dominate, linear in frames): "
                      f"~{rate * s / 6.0:.0f} per hour")
            if not args.no_profile:
                _profile(True, tmp / "prof_video", s or 6.0, 2000)
    print(f"load average after: {_load()}")


if __name__ == "__main__":
    main()
