"""Rendering speed benchmark (not part of the public API).

Run ``python -m vvtbench.render._bench`` and it prints frames per second for a
~12k-triangle speckle-textured cube, supersample=4, at 256^2 and 512^2 output,
flat, lambert and lit, with a new random displacement every frame, plus a breakdown of
where the time goes.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from .camera import Camera
from .pyrender_backend import Renderer, gl_info


def subdivided_cube(levels: int = 5, size: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """Cube surface with ``12 * 4**levels`` triangles (levels=5: 12288)."""
    import trimesh

    m = trimesh.creation.box(extents=(size, size, size))
    for _ in range(levels):
        m = m.subdivide()
    return np.asarray(m.vertices), np.asarray(m.faces)


def bench(size: int, lighting: str, supersample: int, frames: int) -> dict[str, float]:
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
        total = float(np.mean(per_frame))
        best = float(np.min(per_frame))

        # breakdown: vertex upload / draw+readback / downsample
        t0 = time.perf_counter()
        for d in disps:
            r._upload(r._rest + d)
        t_up = (time.perf_counter() - t0) / frames
        t0 = time.perf_counter()
        for _ in disps:
            r._draw()
        t_draw = (time.perf_counter() - t0) / frames
    return {
        "fps": 1.0 / total,
        "ms_frame": 1e3 * total,
        "ms_best": 1e3 * best,
        "ms_upload": 1e3 * t_up,
        "ms_draw_read": 1e3 * t_draw,
        "triangles": float(len(F)),
    }


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--supersample", type=int, default=4)
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 512])
    ap.add_argument("--lighting", nargs="+", default=["flat", "lambert", "lit"])
    args = ap.parse_args(argv)
    info = gl_info()
    print(f"GL: {info['renderer']} / {info['version']}")
    for size in args.sizes:
        for lighting in args.lighting:
            r = bench(size, lighting, args.supersample, args.frames)
            print(
                f"{size}x{size} ss={args.supersample} {lighting:7s} "
                f"{int(r['triangles'])} tris: {r['fps']:6.1f} fps "
                f"({r['ms_frame']:6.1f} ms/frame, best {r['ms_best']:.1f};"
                f" vertex upload {r['ms_upload']:.1f} ms,"
                f" draw+downsample+read {r['ms_draw_read']:.1f} ms)"
            )


if __name__ == "__main__":
    main()
