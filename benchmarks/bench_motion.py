"""Motion extraction and mode identification benchmark (issue 4).

Prints, in one run:

1. our displacement throughput (3 scales x 4 orientations, local frequency, 1 % outliers,
   sigma 2) in frames/s and Mpx*frames/s at 256^2 and 512^2;
2. the authors' baseline at 512^2: ``pyrtools.pyramids.SteerablePyramidFreq(frame, height=1,
   order=1, is_complex=True)`` rebuilt for every frame plus the level-0 phase differences to
   the reference, and the speed ratio;
3. the smallest sinusoid amplitude recovered within 20 % (automatic peak within one bin and
   amplitude of the identified mode, projected on the true pattern, within 20 %), without
   and with camera noise (additive Gaussian, 1 % of the intensity range);
4. the peak RSS of ``extract_modes`` on long synthetic videos streamed from a generator
   (displacements spilled to disk), for several lengths to show how it scales.

Run ``python benchmarks/bench_motion.py`` (about 3-4 min on 2 cores); ``--quick`` for a
smoke run, ``--rss-frames`` / ``--rss-size`` to change the long-video test (e.g.
``--rss-frames 6000 --rss-size 512`` for the issue's 6000 x 512^2 target, ~10+ min).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

import numpy as np

from vvtbench.modes import extract_modes
from vvtbench.motion import PhaseMotion


def speckle(n: int, seed: int = 0) -> tuple[np.ndarray, dict]:
    """Band-limited periodic speckle in ~[0, 1] and its spectral derivatives (for warps)."""
    rng = np.random.default_rng(seed)
    wy = 2 * np.pi * np.fft.fftfreq(n)[:, None]
    wx = 2 * np.pi * np.fft.fftfreq(n)[None, :]
    F = np.fft.fft2(rng.standard_normal((n, n))) * np.exp(-0.5 * np.hypot(wx, wy) ** 2)
    F[n // 2, :] = 0
    F[:, n // 2] = 0
    der = {
        (i, j): np.fft.ifft2(F * (1j * wx) ** i * (1j * wy) ** j).real
        for i, j in ((0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2))
    }
    s = 0.15 / der[(0, 0)].std()
    return 0.5 + s * der[(0, 0)], {k: s * v for k, v in der.items()}


def warp(ref: np.ndarray, der: dict, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Second-order Taylor warp ``I(x - u, y - v)`` (error ~|u|^3, fine for |u| <= 0.05)."""
    return (
        ref
        - u * der[(1, 0)]
        - v * der[(0, 1)]
        + 0.5 * u * u * der[(2, 0)]
        + u * v * der[(1, 1)]
        + 0.5 * v * v * der[(0, 2)]
    )


def pattern(n: int) -> np.ndarray:
    x = np.arange(n)[None, :] * np.ones((n, 1))
    y = np.arange(n)[:, None] * np.ones((1, n))
    return np.stack([np.cos(2 * np.pi * x / n), 0.5 * np.sin(2 * np.pi * y / n)], -1)


def rate(fn, n_frames: int, min_time: float) -> float:
    fn()
    best, total, reps = np.inf, 0.0, 0
    while total < min_time or reps < 2:
        t0 = time.perf_counter()
        fn()
        dt = time.perf_counter() - t0
        best, total, reps = min(best, dt), total + dt, reps + 1
    return n_frames / best


# --------------------------------------------------------------------------- 1 + 2: speed
def bench_speed(sizes: list[int], batch: int, min_time: float) -> dict[int, float]:
    out = {}
    workers = os.cpu_count() or 1
    for n in sizes:
        x = np.random.default_rng(0).random((batch, n, n), dtype=np.float32)
        for w in sorted({1, workers}):
            pm = PhaseMotion(x[0], 3, 4, workers=w)
            fps = rate(lambda pm=pm, x=x: pm.displacement(x), batch, min_time)
            print(
                f"ours {n}x{n} 3 scales x 4 orient., workers={w}: {fps:8.1f} frames/s "
                f"= {fps * n * n / 1e6:7.1f} Mpx*frames/s"
            )
            out[n] = max(out.get(n, 0.0), fps)
    return out


def bench_pyrtools(n: int, n_frames: int, min_time: float) -> float | None:
    try:
        from pyrtools.pyramids import SteerablePyramidFreq
    except ImportError:
        print("pyrtools not installed: baseline skipped")
        return None
    x = np.random.default_rng(0).random((n_frames + 1, n, n))
    ref = SteerablePyramidFreq(x[0], height=1, order=1, is_complex=True)
    ref_bands = [ref.pyr_coeffs[(0, b)] for b in range(2)]

    def run() -> None:
        for f in x[1:]:
            p = SteerablePyramidFreq(f, height=1, order=1, is_complex=True)
            for b in range(2):  # the authors' per-band phase difference and amplitude
                c = p.pyr_coeffs[(0, b)]
                np.angle(c * np.conj(ref_bands[b]))
                np.abs(c)

    fps = rate(run, n_frames, min_time)
    print(
        f"pyrtools baseline {n}x{n} (height=1, order=1 -> 2 orient., rebuilt per frame, "
        f"+ phase differences): {fps:8.2f} frames/s = {fps * n * n / 1e6:7.2f} Mpx*frames/s"
    )
    return fps


# --------------------------------------------------------------------------- 3: sensitivity
def recovered(
    amp: float, noise: float, n: int, T: int, fps: float, prominence: float = 0.5, seed: int = 0
) -> float:
    """Ratio estimated / true amplitude of the mode found within one bin (nan if none)."""
    ref, der = speckle(n, seed)
    pat = pattern(n)
    k0 = T // 6
    f0 = k0 * fps / T
    rng = np.random.default_rng(seed + 1)
    frames = np.empty((T, n, n), np.float32)
    for t in range(T):
        d = amp * np.cos(2 * np.pi * f0 * t / fps) * pat
        frames[t] = warp(ref, der, d[..., 0], d[..., 1])
    if noise:
        frames += rng.normal(0.0, noise, frames.shape).astype(np.float32)
    ms = extract_modes(frames, fps, max_modes=10, workers=-1, prominence=prominence)
    if not len(ms):
        return float("nan")
    i = int(np.argmin(np.abs(ms.frequencies_hz - f0)))
    if abs(int(ms.peak_bins[i]) - k0) > 1:
        return float("nan")
    m = np.zeros((n, n), bool)
    b = 10
    m[b:-b, b:-b] = True
    rec = ms.amplitudes_px[i] * ms.shapes[i]
    return abs(float(np.sum(rec[m] * pat[m]) / np.sum(pat[m] ** 2))) / amp


def bench_sensitivity(n: int, T: int, amps: list[float]) -> None:
    for noise, prom in ((0.0, 0.5), (0.01, 0.5), (0.01, 0.1)):
        label = "no noise" if not noise else f"camera noise sigma={noise:g} (1% of range)"
        label += f", prominence {prom:g} decades"
        smallest = None
        row = []
        for a in amps:
            r = recovered(a, noise, n, T, 100.0, prom)
            ok = np.isfinite(r) and abs(r - 1) <= 0.2
            row.append(f"{a:.0e}:{r:.3f}" + ("" if ok else "x"))
            if ok and (smallest is None or a < smallest):
                smallest = a
        print(f"sensitivity {n}x{n}, T={T}, {label}: " + "  ".join(row))
        print(
            f"  -> smallest amplitude recovered within 20%: "
            f"{smallest if smallest is not None else 'none'} px"
        )


# --------------------------------------------------------------------------- 4: RSS
_CHILD = r"""
import json, resource, sys, time
import numpy as np
sys.path.insert(0, {here!r})
from bench_motion import speckle, warp, pattern
from vvtbench.modes import extract_modes
n, T, fps = {n}, {T}, 100.0
ref, der = speckle(n)
pat = pattern(n)
def frames():
    for t in range(T):
        d = 0.02 * np.cos(2 * np.pi * 12.5 * t / fps) * pat
        yield warp(ref, der, d[..., 0], d[..., 1]).astype(np.float32)
t0 = time.perf_counter()
ms = extract_modes(frames(), fps, workers=-1, memory_budget={budget})
dt = time.perf_counter() - t0
print(json.dumps({{"rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    "seconds": dt, "f": ms.frequencies_hz.tolist(), "spilled": ms.metadata["spilled_to_disk"],
    "timing": ms.metadata["timing_s"]}}))
"""


def bench_rss(n: int, lengths: list[int], budget: int) -> None:
    here = os.path.dirname(os.path.abspath(__file__))
    for T in lengths:
        code = _CHILD.format(here=here, n=n, T=T, budget=budget)
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
        if out.returncode:
            print(out.stderr)
            continue
        r = json.loads(out.stdout.strip().splitlines()[-1])
        disp_gb = T * n * n * 2 * 4 / 1e9
        print(
            f"long video {T} x {n}^2: peak RSS {r['rss_mb']:7.0f} MB, {r['seconds']:6.1f} s "
            f"({T / r['seconds']:.1f} fr/s end to end; motion {r['timing']['motion']:.1f} s, "
            f"spectrum+modes {r['timing']['spectrum_and_modes']:.1f} s), displacements "
            f"{disp_gb:.2f} GB on disk={r['spilled']}, modes at {np.round(r['f'], 2).tolist()} Hz"
        )


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--rss-frames", type=int, nargs="+", default=[500, 1000, 2000])
    ap.add_argument("--rss-size", type=int, default=256)
    ap.add_argument("--budget-mb", type=float, default=64.0)
    args = ap.parse_args(argv)
    min_time = 0.3 if args.quick else 2.0
    print(f"CPUs: {os.cpu_count()}, numpy {np.__version__}")
    ours = bench_speed([256, 512], 16, min_time)
    base = bench_pyrtools(512, 2 if args.quick else 4, min_time)
    if base:
        print(
            f"speed ratio at 512^2 (ours, 12 bands, full displacement / pyrtools 2 bands): "
            f"{ours[512] / base:.1f}x"
        )
    amps = [1e-2, 3e-3, 1e-3, 3e-4, 1e-4, 3e-5, 1e-5]
    bench_sensitivity(64 if args.quick else 128, 128 if args.quick else 256, amps)
    lengths = [200] if args.quick else args.rss_frames
    bench_rss(args.rss_size if not args.quick else 128, lengths, int(args.budget_mb * 2**20))


if __name__ == "__main__":
    main()
