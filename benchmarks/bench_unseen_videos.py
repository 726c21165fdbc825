"""Extraction on seeded synthetic videos unlike the shipped tests.

Each seed draws one video: a crop (96-200 px a side, not always square, not a power of two)
of a band-limited random speckle (Gaussian spectrum, sigma 0.8-2.5 px), warped by 2-6 smooth
random displacement fields (sums of plane waves, max component 1) times a modal coordinate
``a_m exp(-2 pi f_m zeta_m t) cos(2 pi f_m t + phi_m)`` (amplitude 0.001-0.3 px log-uniform,
the weakest mode set to 0.001 px; frequencies anywhere from 6 bins to 0.45 fps at least 4 bins
apart; 40 % of the modes damped with zeta up to 0.01), exactly (third-order Taylor expansion
with the image's exact Fourier derivatives), at 100-2000 fps for 300-1500 frames, with white
sensor noise of 0, 0.03 or 0.1 % of the intensity range.  Half the videos are written as 16-bit
FFV1 ``.mkv`` at their frame rate and read back with no ``fps`` (the container's rate), the
others passed as arrays.

Scored with :func:`vvtbench.scoring.extraction.score_extraction` against the true fields and
frequencies (a detection matches when its frequency is within the resolution and its MAC with
the true field >= 0.5), the detectable modes being those whose spectral line over the record
(``line_px``: the amplitude of the undamped sinusoid with the same Fourier coefficient, as
:func:`~vvtbench.scoring.extraction.true_mode_amplitudes`) reaches 0.001 px.

Usage: ``python benchmarks/bench_unseen_videos.py [--n 40] [--start 0] [--set KEY=JSON ...]``
(``--set`` passes ``extract_modes`` options, e.g. ``--set 'weighting="confidence"' --set
faint_product_ratio=0 --set max_modes=20`` for the defaults before 2026-11-25).  Prints one line
per video and the totals; the seed of every draw is the video's number.
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
import time
from pathlib import Path

import numpy as np
from bench_extractors import speckle

from vvtbench.modes import extract_modes
from vvtbench.scoring.extraction import DEFAULT_FLOOR_PX, score_extraction

SPECKLE_SIZE = 256


def smooth_field(h: int, w: int, rng: np.random.Generator) -> np.ndarray:
    """A smooth ``(h, w, 2)`` displacement pattern: three random plane waves per component."""
    y, x = np.mgrid[0:h, 0:w] / max(h, w)
    out = np.zeros((h, w, 2))
    for c in range(2):
        for _ in range(3):
            kx, ky = rng.uniform(-2, 2, 2)
            out[..., c] += rng.standard_normal() * np.cos(
                2 * np.pi * (kx * x + ky * y) + rng.uniform(0, 2 * np.pi))
    return out / np.abs(out).max()


def draw(seed: int) -> dict:
    """The video of ``seed`` and its truth."""
    rng = np.random.default_rng(seed)
    h, w = (int(v) for v in rng.choice([96, 120, 128, 150, 160, 200], 2))
    sigma = float(rng.choice([0.8, 1.0, 1.5, 2.5]))
    fps = float(rng.choice([100.0, 240.0, 500.0, 1000.0, 2000.0]))
    n_frames = int(rng.choice([300, 512, 1000, 1500]))
    F, wx, wy = speckle(SPECKLE_SIZE, seed, sigma)
    y0, x0 = rng.integers(0, SPECKLE_SIZE - h), rng.integers(0, SPECKLE_SIZE - w)
    ders = {(i, j): np.fft.ifft2(F * (1j * wx) ** i * (1j * wy) ** j).real[y0:y0 + h, x0:x0 + w]
            for i in range(4) for j in range(4 - i)}
    n_modes = int(rng.integers(2, 7))
    df = fps / n_frames
    freqs: list[float] = []
    while len(freqs) < n_modes:
        f = float(rng.uniform(6 * df, 0.45 * fps))
        if all(abs(f - g) > 4 * df for g in freqs):
            freqs.append(f)
    amps = np.exp(rng.uniform(np.log(0.001), np.log(0.3), n_modes))
    amps[np.argmin(amps)] = 0.001
    zetas = np.where(rng.random(n_modes) < 0.4, rng.uniform(0.0, 0.01, n_modes), 0.0)
    fields = np.stack([smooth_field(h, w, rng) for _ in range(n_modes)])
    phases = rng.uniform(0, 2 * np.pi, n_modes)
    noise = float(rng.choice([0.0, 3e-4, 1e-3]))
    t = np.arange(n_frames) / fps
    q = amps[:, None] * np.exp(-2 * np.pi * np.outer(freqs * zetas, t)) * np.cos(
        2 * np.pi * np.outer(freqs, t) + phases[:, None])
    frames = np.empty((n_frames, h, w), np.float32)
    for k in range(n_frames):
        d = np.tensordot(q[:, k], fields, axes=1)
        img = ders[(0, 0)].copy()
        for (i, j), der in ders.items():
            if i + j:
                img += ((-1) ** (i + j) / (math.factorial(i) * math.factorial(j))
                        * d[..., 0] ** i * d[..., 1] ** j * der)
        frames[k] = img
    frames += (noise * np.ptp(ders[(0, 0)])
               * np.random.default_rng(seed + 10_000).standard_normal(frames.shape))
    fd = np.asarray(freqs) * np.sqrt(1 - zetas**2)
    line = np.abs(2 / n_frames * np.sum(q * np.exp(-2j * np.pi * np.outer(fd, t)), axis=1))
    return {"frames": frames, "fps": fps, "freqs": np.asarray(freqs), "zetas": zetas,
            "fields": fields, "amps": amps, "line_px": line, "noise": noise, "sigma": sigma,
            "to_file": bool(rng.random() < 0.5)}


def write_mkv(path: Path, frames: np.ndarray, fps: float) -> None:
    """16-bit lossless FFV1 at the true frame rate (what a high-speed camera export holds)."""
    import imageio_ffmpeg

    lo, hi = float(frames.min()), float(frames.max())
    dn = np.round((frames - lo) / (hi - lo) * 60000 + 2000).astype("<u2")
    gen = imageio_ffmpeg.write_frames(str(path), dn.shape[2:0:-1], pix_fmt_in="gray16le",
                                      pix_fmt_out="gray16le", codec="ffv1", quality=None,
                                      fps=fps, macro_block_size=1, ffmpeg_log_level="error")
    gen.send(None)
    for frame in dn:
        gen.send(np.ascontiguousarray(frame))
    gen.close()


def run(seed: int, options: dict, tmp: Path) -> dict:
    v = draw(seed)
    n_frames = len(v["frames"])
    t0 = time.perf_counter()
    if v["to_file"]:
        path = tmp / f"video_{seed}.mkv"
        write_mkv(path, v["frames"], v["fps"])
        ms = extract_modes(path, **options)
        path.unlink()
    else:
        ms = extract_modes(v["frames"], v["fps"], **options)
    elapsed = time.perf_counter() - t0
    s = score_extraction(ms, v["freqs"], v["zetas"], v["fields"] * v["amps"][:, None, None, None],
                         n_frames / v["fps"], v["fps"] / 2, amplitudes_px=v["line_px"])
    df = v["fps"] / n_frames
    false = [float(f) for f in ms.frequencies_hz
             if np.min(np.abs(f - v["freqs"])) > df or not np.isfinite(f)]
    missed = [(float(f), float(a), float(z)) for f, a, z in
              zip(v["freqs"], v["line_px"], v["zetas"], strict=True)
              if a >= DEFAULT_FLOOR_PX and not np.any(np.abs(ms.frequencies_hz - f) <= df)]
    return {"seed": seed, "fps": v["fps"], "fps_read": ms.fps, "to_file": v["to_file"],
            "shape": ms.image_shape, "n_frames": n_frames, "noise": v["noise"],
            "n_true": len(v["freqs"]), "n_detectable": s["n_detectable"],
            "n_matched_detectable": s["n_matched_detectable"], "n_detected": s["n_detected"],
            "n_matched": s["n_matched"], "false_hz": false, "missed": missed,
            "mean_mac": s["mean_mac"], "seconds": elapsed}


def _at_least(low: int):
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = low - 1
        if value < low:
            raise argparse.ArgumentTypeError(f"{text!r}: an integer >= {low}")
        return value
    return parse


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=_at_least(1), default=40)
    ap.add_argument("--start", type=_at_least(0), default=0)
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=JSON")
    args = ap.parse_args()
    options = {}
    for item in args.sets:
        key, eq, value = item.partition("=")
        try:
            options[key.strip()] = json.loads(value)
        except json.JSONDecodeError:
            eq = ""
        if not eq or not key.strip():
            ap.error(f"--set {item!r}: expected KEY=JSON, e.g. max_modes=20 or "
                     "'weighting=\"confidence\"'")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(args.start, args.start + args.n):
            r = run(seed, options, Path(tmp))
            rows.append(r)
            src = "mkv" if r["to_file"] else "array"
            print(f"{seed:3d} {r['shape'][0]}x{r['shape'][1]} {r['n_frames']} fr "
                  f"{r['fps']:g} fps ({src}, read {r['fps_read']:g}) noise {r['noise']:g}: "
                  f"{r['n_matched_detectable']}/{r['n_detectable']} detectable matched, "
                  f"{r['n_matched']}/{r['n_detected']} detections true; "
                  f"false {[round(f, 2) for f in r['false_hz']]} missed "
                  f"{[(round(f, 2), round(a, 4), round(z, 4)) for f, a, z in r['missed']]} "
                  f"({r['seconds']:.1f} s)", flush=True)
    det = sum(r["n_detectable"] for r in rows)
    hit = sum(r["n_matched_detectable"] for r in rows)
    n_det = sum(r["n_detected"] for r in rows)
    n_true = sum(r["n_matched"] for r in rows)
    n_false = sum(len(r["false_hz"]) for r in rows)
    worst = max(len(r["false_hz"]) for r in rows)
    fps_ok = all(r["fps_read"] == r["fps"] for r in rows)
    print(f"\noptions {json.dumps(options)}; seeds {args.start}..{args.start + args.n - 1}")
    print("| videos | detectable modes matched (recall) | detections matched (precision) "
          "| false peaks (off every true frequency) | videos with > 1 false | fps read right |")
    print("|---|---|---|---|---|---|")
    print(f"| {len(rows)} | {hit}/{det} = {hit / det:.2f} | {n_true}/{n_det} = "
          f"{n_true / max(n_det, 1):.2f} | {n_false} (at most {worst} in one video) | "
          f"{sum(len(r['false_hz']) > 1 for r in rows)} | {fps_ok} |")


if __name__ == "__main__":
    main()
