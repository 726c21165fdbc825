"""Rendering and dataset-generation benchmark.

Prints:
1. frames per second of the renderer at 256^2 and 512^2 output with the default supersampling
   (4), on the surface of the paper's 10^3 cube (jello_cube_homogeneous) and on a 12k-triangle
   cube, a new displacement every frame (goal: >= 40 fps at 256^2 on 2 cores);
2. peak RSS of whole-sample generation for 1 s and for 6 s of video (must be about equal:
   frames stream to the encoder);
3. (--full) whole-sample generation time of jello_cube_homogeneous, 6 s at 2000 FPS
   (goal: <= 10 min);
4. (--breakdown) the renderer alone on a ~12k-triangle cube at 256^2 and 512^2, flat,
   lambert and lit, with where the time goes (vertex upload, draw + read-back).

Usage: python benchmarks/bench_render.py [--full] [--frames N] [--skip-rss] [--breakdown]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time

import numpy as np

SCENE = "jello_cube_homogeneous"

_CHILD = r"""
import json, resource, sys, time
from vvtbench.samples.generate import generate
from vvtbench.scene.scene import with_overrides
from vvtbench.scene.scene import load_scene
scene = with_overrides(load_scene(sys.argv[1]), duration=float(sys.argv[2]))
t0 = time.perf_counter()
generate(scene, sys.argv[3], progress=False)
dt = time.perf_counter() - t0
print(json.dumps({
    "seconds": dt,
    "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    "peak_rss_children_mib": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024,
}))
"""


def subdivided_cube(levels: int = 5, size: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """Cube surface with ``12 * 4**levels`` triangles (levels=5: 12288)."""
    import trimesh

    m = trimesh.creation.box(extents=(size, size, size))
    for _ in range(levels):
        m = m.subdivide()
    return np.asarray(m.vertices), np.asarray(m.faces)


def breakdown(size: int, lighting: str, supersample: int, frames: int) -> dict[str, float]:
    """Renderer speed on the 12k-triangle cube, and its parts (upload; draw + read-back).

    The parts call the renderer's internal ``_upload`` / ``_draw`` steps (benchmark only)."""
    from vvtbench.render.camera import Camera
    from vvtbench.render.pyrender_backend import Renderer

    V, F = subdivided_cube()
    cam = Camera.look_at((0.22, -0.26, 0.19), (0, 0, 0), fov_y_deg=35.0, width=size, height=size)
    rng = np.random.default_rng(0)
    disps = [rng.normal(scale=1e-6, size=V.shape) for _ in range(frames)]
    with Renderer(V, F, cam, supersample=supersample, lighting=lighting) as r:
        for d in disps[:3]:  # warm-up: shader compile, framebuffer creation
            r.render(d)
        per_frame = []
        for d in disps:
            t0 = time.perf_counter()
            r.render(d)
            per_frame.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        for d in disps:
            r._upload(r._rest + d)
        t_up = (time.perf_counter() - t0) / frames
        t0 = time.perf_counter()
        for _ in disps:
            r._draw()
        t_draw = (time.perf_counter() - t0) / frames
    total = float(np.mean(per_frame))
    return {"fps": 1.0 / total, "ms_frame": 1e3 * total, "ms_best": 1e3 * float(np.min(per_frame)),
            "ms_upload": 1e3 * t_up, "ms_draw_read": 1e3 * t_draw, "triangles": float(len(F))}


def render_fps(size: int, frames: int, mesh: str) -> float:
    from vvtbench.samples.generate import scene_renderer, surface_geometry
    from vvtbench.scene.scene import load_scene, with_overrides
    from vvtbench.simulation.simulate import build_mesh

    scene = with_overrides(load_scene(SCENE), resolution=(size, size))
    if mesh == "scene":
        _, V, F = surface_geometry(build_mesh(scene))
    else:
        V, F = subdivided_cube(5, 0.05)
        V = V + 0.025
    rng = np.random.default_rng(0)
    disps = [rng.normal(scale=1e-6, size=V.shape) for _ in range(frames)]
    with scene_renderer(scene, V, F) as r:
        for d in disps[:3]:
            r.render(d)
        t0 = time.perf_counter()
        for d in disps:
            r.render(d)
        return frames / (time.perf_counter() - t0), len(F)


def generate_child(duration: float) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        out = subprocess.run([sys.executable, "-c", _CHILD, SCENE, str(duration), tmp],
                             capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=200, help="frames per fps measurement")
    ap.add_argument("--full", action="store_true", help="also time the full 6 s sample")
    ap.add_argument("--skip-rss", action="store_true")
    ap.add_argument("--breakdown", action="store_true",
                    help="only the renderer breakdown on the 12k cube (flat, lambert, lit)")
    ap.add_argument("--supersample", type=int, default=4, help="for --breakdown")
    args = ap.parse_args(argv)
    from vvtbench.render.pyrender_backend import gl_info

    info = gl_info()
    print(f"GL: {info['renderer']} / {info['version']}")
    if args.breakdown:
        for size in (256, 512):
            for lighting in ("flat", "lambert", "lit"):
                r = breakdown(size, lighting, args.supersample, min(args.frames, 30))
                print(f"{size}x{size} ss={args.supersample} {lighting:7s} "
                      f"{int(r['triangles'])} tris: {r['fps']:6.1f} fps "
                      f"({r['ms_frame']:6.1f} ms/frame, best {r['ms_best']:.1f}; vertex upload "
                      f"{r['ms_upload']:.1f} ms, draw+downsample+read {r['ms_draw_read']:.1f} ms)")
        return
    for mesh in ("scene", "12k"):
        for size in (256, 512):
            fps, ntri = render_fps(size, args.frames, mesh)
            print(f"render {size}x{size} supersample 4, {ntri:5d} triangles ({mesh}): "
                  f"{fps:6.1f} fps ({1e3 / fps:.1f} ms/frame)")
    if not args.skip_rss:
        for duration in (1.0, 6.0) if args.full else (0.5, 1.0):
            r = generate_child(duration)
            print(f"generate {SCENE}, {duration:g} s at 2000 FPS ({int(duration * 2000)} frames, "
                  f"256x256): {r['seconds']:.1f} s, peak RSS {r['peak_rss_mib']:.0f} MiB "
                  f"(ffmpeg children {r['peak_rss_children_mib']:.0f} MiB)")


if __name__ == "__main__":
    main()
