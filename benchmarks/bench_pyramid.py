"""Speed of the pyramid and phase motion (frames/s): ``python benchmarks/bench_pyramid.py``.

Compares, in the same run, our batched pyramid / full displacement pipeline with building a
``pyrtools.pyramids.SteerablePyramidFreq`` per frame (if pyrtools is installed).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import numpy as np

from vvtbench.motion.phase import PhaseMotion
from vvtbench.motion.pyramid import get_pyramid


def _rate(fn: Callable[[], object], n_frames: int, min_time: float = 1.0) -> float:
    """Frames per second of ``fn`` (which processes ``n_frames``), best of repeated runs."""
    fn()  # warm-up (plans, caches)
    best = np.inf
    total, reps = 0.0, 0
    while total < min_time or reps < 2:
        t0 = time.perf_counter()
        fn()
        dt = time.perf_counter() - t0
        best = min(best, dt)
        total += dt
        reps += 1
    return n_frames / best


def _frames(n: int, size: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.standard_normal((n, size, size)).astype(np.float32)


def main(argv: list[str] | None = None) -> None:
    """Print frames/s for 3 scales x 4 orientations at the requested sizes."""
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 512])
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--min-time", type=float, default=1.0)
    args = ap.parse_args(argv)
    try:
        from pyrtools.pyramids import SteerablePyramidFreq
    except ImportError:  # pragma: no cover - optional
        SteerablePyramidFreq = None
        print("pyrtools not installed: skipping the comparison")

    for size in args.sizes:
        x = _frames(args.batch, size)
        print(f"--- {size}x{size}, 3 scales x 4 orientations, batch {args.batch} ---")
        for workers in args.workers:
            for down in (True, False):
                pyr = get_pyramid((size, size), 3, 4, down)
                fps = _rate(
                    lambda p=pyr, w=workers, x=x: p.decompose(x, workers=w),
                    args.batch,
                    args.min_time,
                )
                print(f"ours pyramid  downsample={down!s:5} workers={workers}: {fps:8.1f} fr/s")
            pm = PhaseMotion(x[0], 3, 4, workers=workers)
            fps = _rate(lambda p=pm, x=x: p.displacement(x), args.batch, args.min_time)
            print(
                f"ours displacement (local freq, 1% outliers, sigma 2) workers={workers}: "
                f"{fps:8.1f} fr/s"
            )
            pm = PhaseMotion(x[0], 3, 4, workers=workers, outlier_fraction=0.0)
            fps = _rate(lambda p=pm, x=x: p.displacement(x), args.batch, args.min_time)
            print(
                f"ours displacement (no outlier removal)          workers={workers}: "
                f"{fps:8.1f} fr/s"
            )
        if SteerablePyramidFreq is not None:
            n = min(args.batch, 4)
            xs = x[:n].astype(np.float64)
            for height, order in ((3, 3), (1, 1), (3, 1)):

                def run(h: int = height, o: int = order, xs: np.ndarray = xs) -> None:
                    for f in xs:
                        SteerablePyramidFreq(f, height=h, order=o, is_complex=True)

                fps = _rate(run, n, args.min_time)
                print(
                    f"pyrtools SteerablePyramidFreq height={height} order={order} "
                    f"({order + 1} orient.) per frame: {fps:8.1f} fr/s"
                )


if __name__ == "__main__":
    main()
