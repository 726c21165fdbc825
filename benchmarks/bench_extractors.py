"""Motion sub-benchmark: displacement error of every registered extractor.

Synthetic video: a seeded band-limited periodic speckle image (Gaussian spectrum, sigma =
1 px), translated by exact Fourier phase ramps along a diagonal direction by a sinusoid of
amplitude A (0.001 to 1 px, 16 frames over one period), with white sensor noise of standard
deviation ``noise`` times the image's intensity range added to every frame.  Each extractor
(``vvtbench.extractors`` entry points) is prepared on the temporal mean of the frames (what
:func:`vvtbench.modes.extract_modes` gives it; the motion averages to zero over the period)
and its displacement fields are compared with the true ones over the interior (a 16 px border
left out):

* ``rmse/A``: RMS over frames, interior pixels and both components of (measured - true),
  each pixel's temporal mean error removed (a constant the spectrum removes: the reference's
  own noise or blur), relative to the RMS motion;
* ``gain``: least-squares slope of measured against true displacement (1 = unbiased);
* ``ms/frame``: wall time per frame (reference preparation excluded).

Usage: ``python benchmarks/bench_extractors.py [--size 128] [--reference mean]
[--out benchmarks/extractors.png]`` (prints a Markdown table and writes the plot;
``--reference first`` prepares the extractors on the first frame, as before the mean).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from vvtbench.solving.extractors import list_extractors, make_extractor

AMPLITUDES = (0.001, 0.003, 0.01, 0.03, 0.1, 0.3, 1.0)
NOISES = (0.0, 0.001, 0.01)
T = 16
BORDER = 16


def speckle(n: int, seed: int = 0, sigma: float = 1.0):
    rng = np.random.default_rng(seed)
    wy = 2 * np.pi * np.fft.fftfreq(n)[:, None]
    wx = 2 * np.pi * np.fft.fftfreq(n)[None, :]
    F = np.fft.fft2(rng.standard_normal((n, n))) * np.exp(-0.5 * (np.hypot(wx, wy) * sigma) ** 2)
    F[n // 2, :] = 0.0
    F[:, n // 2] = 0.0
    return F, wx, wy


def make_video(n: int, amp: float, noise: float, seed: int = 0):
    F, wx, wy = speckle(n, seed)
    t = np.arange(T)
    s = amp * np.sin(2 * np.pi * t / T)
    dx, dy = s * 0.8, s * 0.6  # diagonal motion, |d| = amp
    frames = np.stack(
        [np.fft.ifft2(F * np.exp(-1j * (wx * a + wy * b))).real
         for a, b in zip(dx, dy, strict=True)]
    )
    rng = np.random.default_rng(seed + 1)
    frames += noise * np.ptp(frames[0]) * rng.standard_normal(frames.shape)
    return frames.astype(np.float32), np.stack([dx, dy], axis=-1)


def upsample(d: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    from vvtbench.motion.phase import upsample_periodic

    if d.shape[1:3] == tuple(shape):
        return d
    return np.moveaxis(upsample_periodic(np.moveaxis(d, -1, 1), shape), 1, -1)


def measure(name: str, n: int, amp: float, noise: float, reference: str = "mean") -> dict:
    frames, true = make_video(n, amp, noise)
    motion = make_extractor(name).prepare(frames.mean(axis=0) if reference == "mean"
                                          else frames[0])
    t0 = time.perf_counter()
    d = np.concatenate(list(motion.iter_displacements(iter(frames), batch=T)))
    dt = (time.perf_counter() - t0) / T
    d = upsample(d, motion.shape)[:, BORDER:-BORDER, BORDER:-BORDER].astype(np.float64)
    tr = np.broadcast_to(true[:, None, None, :], d.shape)
    err = d - tr
    err -= err.mean(axis=0)  # an offset constant in time: the spectrum never sees it
    rmse = float(np.sqrt(np.mean(err**2)) / (amp / np.sqrt(2)))  # relative to the RMS motion
    gain = float(np.sum(d * tr) / np.sum(tr * tr))
    return {"extractor": name, "amp": amp, "noise": noise, "rmse_rel": rmse, "gain": gain,
            "ms_frame": dt * 1e3}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--out", default="benchmarks/extractors.png")
    ap.add_argument("--reference", choices=("mean", "first"), default="mean")
    args = ap.parse_args()
    names = sorted(list_extractors())
    rows = [measure(nm, args.size, a, z, args.reference)
            for nm in names for z in NOISES for a in AMPLITUDES]
    print(f"speckle {args.size}^2, {T} frames, diagonal sinusoidal translation, reference: "
          f"{args.reference}; rmse relative to the RMS true displacement per component\n")
    print("| extractor | noise | " + " | ".join(f"{a:g} px" for a in AMPLITUDES)
          + " | gain @0.01 px | ms/frame |")
    print("|---|---|" + "---|" * len(AMPLITUDES) + "---|---|")
    for nm in names:
        for z in NOISES:
            rr = [r for r in rows if r["extractor"] == nm and r["noise"] == z]
            g = next(r["gain"] for r in rr if r["amp"] == 0.01)
            ms = np.median([r["ms_frame"] for r in rr])
            print(f"| {nm} | {z:g} | " + " | ".join(f"{r['rmse_rel']:.3g}" for r in rr)
                  + f" | {g:.3f} | {ms:.1f} |")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 4.5), dpi=110)
    colors = dict(zip(names, plt.rcParams["axes.prop_cycle"].by_key()["color"], strict=False))
    styles = dict(zip(NOISES, ["-", "--", ":"], strict=True))
    for nm in names:
        for z in NOISES:
            rr = [r for r in rows if r["extractor"] == nm and r["noise"] == z]
            ax.loglog([r["amp"] for r in rr], [r["rmse_rel"] for r in rr], styles[z],
                      marker="o", ms=3, color=colors[nm], label=f"{nm}, noise {z:g}")
    ax.axhline(1.0, color="0.6", lw=0.8)
    ax.set_xlabel("translation amplitude (px)")
    ax.set_ylabel("RMS displacement error / RMS motion")
    ax.set_title(f"Motion extractors on a translated speckle ({args.size}$^2$, {T} frames)")
    ax.grid(True, which="both", alpha=0.25)
    ax.legend(fontsize=8, loc="center left", bbox_to_anchor=(1.01, 0.5))
    fig.tight_layout()
    fig.savefig(args.out)
    print(f"\nplot: {args.out}")


if __name__ == "__main__":
    main()
