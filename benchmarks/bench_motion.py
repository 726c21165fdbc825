"""Motion extraction and mode identification benchmark.

Prints, in one run:

1. our displacement throughput (3 scales x 4 orientations, local frequency, 1 % outliers,
   sigma 2, on the half-resolution working grid as ``extract_modes`` uses it, and with the
   full-resolution output) in frames/s and Mpx*frames/s at 256^2 and 512^2, with 1 thread
   and all CPUs;
2. in the same run, alternated with 1. on the same frames (a speckle image vibrating by
   0.05 px), two baselines and the speed ratios to each: the official code's per-frame
   pipeline (``official_baseline``: the frame's and the reference's
   ``pyrtools.pyramids.SteerablePyramidFreq(., order=1, is_complex=True)`` with the default
   height, 7 levels at 512^2, rebuilt for every frame; level-0 phase differences, local
   frequency, 99th-percentile outlier mask, amplitude-weighted smoothing), and its pyramid
   part alone (one pyramid per frame and the phase differences: a lower bound);
3. the smallest sinusoid amplitude recovered within 20 % (automatic peak within one bin and
   amplitude of the identified mode, projected on the true pattern, within 20 %), without
   and with camera noise (additive Gaussian, 1 % of the intensity range);
4. the peak RSS of ``extract_modes`` on long synthetic videos streamed from a generator
   (displacements spilled to disk), for several lengths to show how it scales.

Run ``python benchmarks/bench_motion.py`` (about 3-4 min on 2 cores); ``--quick`` for a
smoke run, ``--speed-only`` for 1-2 only, ``--rss-only`` for 4 only, ``--rss-frames`` /
``--rss-size`` / ``--budget-mb`` / ``--rss-video-dir`` to change the long-video test (e.g.
``--rss-only --rss-frames 6000 --rss-size 512 --budget-mb 1024 --rss-video-dir /tmp`` for
the issue's 6000 x 512^2 target from a lossless video file, ~15 min).
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
def vibration_frames(n: int, count: int, amp: float = 0.05) -> np.ndarray:
    """``count`` frames of a speckle image vibrating sub-pixel (a realistic input: phase
    differences are small, as in the videos the method is for)."""
    ref, der = speckle(n)
    pat = pattern(n)
    out = np.empty((count, n, n), np.float32)
    for t in range(count):
        d = amp * np.cos(0.7 * t) * pat
        out[t] = warp(ref, der, d[..., 0], d[..., 1])
    return out


OFFICIAL = "baseline: official per-frame pipeline (2 pyrtools pyramids, phase, 99 % mask, smooth)"
PYRAMID_ONLY = "baseline: pyrtools pyramid + level-0 phase only (lower bound)"


def pyramid_only_baseline(xs: np.ndarray) -> None:
    """The pyramid part of the official code alone: ``SteerablePyramidFreq(frame, order=1,
    is_complex=True)`` with the default height, rebuilt per frame, and the level-0 phase
    differences to the reference (built once here, which the official code does not do)."""
    from pyrtools.pyramids import SteerablePyramidFreq

    ref = SteerablePyramidFreq(xs[0], order=1, is_complex=True)
    ref_bands = [np.conj(ref.pyr_coeffs[(0, b)]) for b in range(2)]
    for f in xs[1:]:
        p = SteerablePyramidFreq(f, order=1, is_complex=True)
        for b in range(2):
            c = p.pyr_coeffs[(0, b)]
            np.angle(c * ref_bands[b])
            np.abs(c)


def official_baseline(xs: np.ndarray, filter_pct: float = 99.0, sigma: float = 3.0) -> None:
    """Every per-frame step of the official code (berthyf96/visvib-tomography, vvt/motion.py),
    re-implemented here: the frame's AND the reference's pyramids rebuilt for each frame
    (default height, order=1, complex), level-0 phase differences wrapped to (-pi, pi], the
    local frequency as the 3-tap finite difference of the phase (scipy fftconvolve), the
    Fleet-Jepson displacement, the displacements above the 99th percentile of |u| zeroed,
    then the amplitude-weighted Gaussian smoothing (sigma 3; the reference amplitude masks
    built once per video, as there)."""
    from pyrtools.pyramids import SteerablePyramidFreq
    from scipy.ndimage import gaussian_filter
    from scipy.signal import fftconvolve

    kx = np.array([[0.0, -1.0, 1.0]])
    ref = SteerablePyramidFreq(xs[0], order=1, is_complex=True)
    masks = [np.abs(ref.pyr_coeffs[(0, b)]) ** 2 for b in range(2)]
    dens = [gaussian_filter(m, sigma) for m in masks]
    for f in xs[1:]:
        p_ref = SteerablePyramidFreq(xs[0], order=1, is_complex=True)
        p = SteerablePyramidFreq(f, order=1, is_complex=True)
        for b, kern in ((0, kx), (1, kx.T)):
            phase = np.angle(p.pyr_coeffs[(0, b)])
            dphase = np.mod(np.pi + phase - np.angle(p_ref.pyr_coeffs[(0, b)]), 2 * np.pi) - np.pi
            u = dphase / -fftconvolve(phase, kern, mode="same")
            u = u * (np.abs(u) <= np.percentile(np.abs(u), filter_pct))
            gaussian_filter(u * masks[b], sigma) / dens[b]


def bench_speed(
    sizes: list[int], batch: int, min_time: float, baseline_frames: int
) -> dict[str, dict[int, float]]:
    """Ours and the authors' baseline on the same frames, alternated (best of each)."""
    try:
        from pyrtools.pyramids import SteerablePyramidFreq
    except ImportError:
        SteerablePyramidFreq = None
        print("pyrtools not installed: baseline skipped")
    workers = os.cpu_count() or 1
    res: dict[str, dict[int, float]] = {}

    def record(key: str, n: int, fps: float) -> None:
        res.setdefault(key, {})
        res[key][n] = max(res[key].get(n, 0.0), fps)

    for n in sizes:
        x = vibration_frames(n, batch)
        runs = {}
        for w in sorted({1, workers}):
            pm = PhaseMotion(x[0], 3, 4, workers=w)
            runs[f"ours, workers={w}, pipeline grid output"] = (
                lambda pm=pm, x=x: pm.displacement(x, full_resolution=False),
                batch,
            )
            runs[f"ours, workers={w}, full-resolution output"] = (
                lambda pm=pm, x=x: pm.displacement(x),
                batch,
            )
        if SteerablePyramidFreq is not None:
            xs = x[: baseline_frames + 1].astype(np.float64)
            runs[PYRAMID_ONLY] = (lambda xs=xs: pyramid_only_baseline(xs), baseline_frames)
            runs[OFFICIAL] = (lambda xs=xs: official_baseline(xs), baseline_frames)
        for _ in range(2):  # alternate, keep the best of each: both see the same load
            for key, (fn, count) in runs.items():
                record(key, n, rate(fn, count, min_time / 2))
        for key in runs:
            fps = res[key][n]
            print(f"{n}x{n} {key}: {fps:8.1f} frames/s = {fps * n * n / 1e6:7.2f} Mpx*frames/s")
        for b in (OFFICIAL, PYRAMID_ONLY):
            if b in res:
                for key in runs:
                    if not key.startswith("baseline"):
                        print(f"  ratio {n}x{n} [{key}] / [{b}]: "
                              f"{res[key][n] / res[b][n]:6.1f}x")
    return res


# --------------------------------------------------------------------------- 3: sensitivity
def recovered(
    amp: float,
    noise: float,
    n: int,
    T: int,
    fps: float,
    prominence: float = 0.5,
    seed: int = 0,
    window: str = "hann",
    offset: float = 0.0,
) -> float:
    """Ratio estimated / true amplitude of the mode found within one bin (nan if none).

    The sinusoid sits ``offset`` bins above bin ``T // 6`` (0 = on a bin, 0.5 = halfway).
    """
    ref, der = speckle(n, seed)
    pat = pattern(n)
    k0 = T // 6
    f0 = (k0 + offset) * fps / T
    rng = np.random.default_rng(seed + 1)
    frames = np.empty((T, n, n), np.float32)
    for t in range(T):
        d = amp * np.cos(2 * np.pi * f0 * t / fps) * pat
        frames[t] = warp(ref, der, d[..., 0], d[..., 1])
    if noise:
        frames += rng.normal(0.0, noise, frames.shape).astype(np.float32)
    ms = extract_modes(frames, fps, max_modes=10, workers=-1, prominence=prominence, window=window)
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
    """Smallest amplitude recovered; Hann (default) and no window, on a bin and halfway.

    On a bin the rectangular window is at its best (no scalloping, no leakage) and Hann
    pays its 1.5-bin noise bandwidth; halfway between bins the rectangular window loses
    36 % of the amplitude (scalloping), Hann 15 %.
    """
    cases = [
        (0.0, 0.5, "hann", 0.0),
        (0.01, 0.5, "hann", 0.0),
        (0.01, 0.1, "hann", 0.0),
        (0.01, 0.1, "none", 0.0),
        (0.01, 0.1, "hann", 0.5),
        (0.01, 0.1, "none", 0.5),
    ]
    for noise, prom, window, offset in cases:
        label = "no noise" if not noise else f"camera noise sigma={noise:g} (1% of range)"
        label += f", prominence {prom:g} decades, window {window}, "
        label += "on a bin" if offset == 0 else f"{offset:g} bin off"
        smallest = None
        row = []
        for a in amps:
            r = recovered(a, noise, n, T, 100.0, prom, window=window, offset=offset)
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
import json, os, resource, sys, tempfile, time
import numpy as np
sys.path.insert(0, {here!r})
from bench_motion import speckle, warp, pattern
from vvtbench.modes import extract_modes
n, T, fps, video = {n}, {T}, 100.0, {video!r}
ref, der = speckle(n)
pat = pattern(n)
period = 8  # 12.5 Hz at 100 fps: one period, synthesised once, then repeated
cycle = []
for t in range(period):
    d = 0.02 * np.cos(2 * np.pi * 12.5 * t / fps) * pat
    cycle.append(warp(ref, der, d[..., 0], d[..., 1]).astype(np.float32))
def frames():
    for t in range(T):
        yield cycle[t % period]
t_write = 0.0
if video:
    import imageio_ffmpeg
    t0 = time.perf_counter()
    w = imageio_ffmpeg.write_frames(video, (n, n), pix_fmt_in="gray16le", pix_fmt_out="gray16le",
        codec="ffv1", quality=None, fps=30, macro_block_size=1, ffmpeg_log_level="error")
    w.send(None)
    for f in frames():
        w.send(np.ascontiguousarray(np.clip(f * 65535, 0, 65535).astype(np.uint16)))
    w.close()
    t_write = time.perf_counter() - t0
    rss_write = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    src = video
else:
    src = frames()
t0 = time.perf_counter()
ms = extract_modes(src, fps, workers=-1, memory_budget={budget})
dt = time.perf_counter() - t0
print(json.dumps({{"rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    "child_rss_mb": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024,
    "seconds": dt, "write_s": t_write, "f": ms.frequencies_hz.tolist(),
    "spilled": ms.metadata["spilled_to_disk"], "timing": ms.metadata["timing_s"],
    "grid": ms.metadata["motion"]["grid_shape"], "rejected": ms.metadata["rejected"],
    "n_frames": ms.n_frames}}))
"""


def bench_rss(n: int, lengths: list[int], budget: int, video_dir: str | None = None) -> None:
    """Peak RSS and wall time of ``extract_modes`` on long synthetic videos, in a child.

    The frames (a speckle image vibrating at 12.5 Hz, 100 fps: one 8-frame period
    synthesised once and repeated) are either written first as a lossless FFV1 16-bit video
    in ``video_dir`` (not timed; the child's RSS high-water mark is then the max of writing
    and extraction, writing is streamed too) and extracted from the file (ffmpeg decoding
    included, ~50 fr/s for 512^2 16-bit FFV1 of speckle on 2 cores: it dominates), or
    streamed from a generator (no decoding: the extraction alone).
    """
    here = os.path.dirname(os.path.abspath(__file__))
    for T in lengths:
        video = "" if video_dir is None else os.path.join(video_dir, f"rss_{T}x{n}.mkv")
        code = _CHILD.format(here=here, n=n, T=T, budget=budget, video=video)
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
        if video and os.path.exists(video):
            os.remove(video)
        if out.returncode:
            print(out.stderr)
            continue
        r = json.loads(out.stdout.strip().splitlines()[-1])
        gh, gw = r["grid"]
        disp_gb = T * gh * gw * 2 * 4 / 1e9
        src = "FFV1 video file" if video else "generator"
        print(
            f"long video {T} x {n}^2 from {src}: peak RSS {r['rss_mb']:7.0f} MB (largest "
            f"ffmpeg child {r['child_rss_mb']:.0f} MB), extraction "
            f"{r['seconds']:6.1f} s ({T / r['seconds']:.1f} fr/s end to end; motion "
            f"{r['timing']['motion']:.1f} s, spectrum+peaks+modes "
            f"{r['timing']['spectrum_and_modes']:.1f} s)"
            + (f", video written in {r['write_s']:.0f} s (not counted)" if video else "")
            + f"; displacements on the {gh}x{gw} grid {disp_gb:.2f} GB, spilled to disk="
            f"{r['spilled']}; modes at {np.round(r['f'], 2).tolist()} Hz, rejected "
            f"{[(round(x['frequency_hz'], 2), x['reason']) for x in r['rejected']]}"
        )


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--rss-frames", type=int, nargs="+", default=[500, 1000, 2000])
    ap.add_argument("--rss-size", type=int, default=256)
    ap.add_argument("--budget-mb", type=float, default=64.0)
    ap.add_argument("--speed-only", action="store_true", help="only the speed comparison")
    ap.add_argument("--rss-only", action="store_true", help="only the long-video RSS test")
    ap.add_argument("--sensitivity-only", action="store_true", help="only the sensitivity")
    ap.add_argument(
        "--rss-video-dir",
        default=None,
        help="write the long synthetic videos as lossless FFV1 files here and extract from "
        "the files (default: stream frames from a generator)",
    )
    args = ap.parse_args(argv)
    min_time = 0.3 if args.quick else 2.0
    print(f"CPUs: {os.cpu_count()}, numpy {np.__version__}")
    load = os.getloadavg()
    print(f"load average before: {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    amps = [1e-2, 3e-3, 1e-3, 3e-4, 1e-4, 3e-5, 1e-5]
    if args.sensitivity_only:
        bench_sensitivity(128, 256, amps)
        return
    if args.rss_only:
        bench_rss(args.rss_size, args.rss_frames, int(args.budget_mb * 2**20), args.rss_video_dir)
        return
    bench_speed([256, 512], 32, min_time, 2 if args.quick else 6)
    if args.speed_only:
        return
    bench_sensitivity(64 if args.quick else 128, 128 if args.quick else 256, amps)
    lengths = [200] if args.quick else args.rss_frames
    bench_rss(
        args.rss_size if not args.quick else 128,
        lengths,
        int(args.budget_mb * 2**20),
        args.rss_video_dir,
    )


if __name__ == "__main__":
    main()
