"""False modes of the extractor's own making on clean synthetic videos, with and without the
rejection of harmonics and intermodulation products (:mod:`vvtbench.modes.combinations`).

Each seed draws one clean video (no sensor noise, 16-bit lossless FFV1 ``.mkv``, read back at
the container's rate): a crop (96-160 px a side) of a band-limited random speckle warped
exactly (third-order Taylor expansion with the image's exact Fourier derivatives, as
``bench_unseen_videos.py``) by 2-5 smooth random displacement fields times modal coordinates
``a_m exp(-2 pi f_m zeta_m t) cos(2 pi f_m t + phi_m)``: amplitudes log-uniform in 0.001-0.3 px
(``--max-amplitude``: 0.001-A) with the weakest at 0.001 px, 30 % of the modes damped (``zeta``
up to 0.005), frequencies from 6 bins to 0.45 fps at least 4 bins apart, 500-2000 fps, 500 or
1000 frames. Half the videos are plucked (every ``phi_m = 0``, so a product's phase is a
mode's), the others have random phases; in half of them the weakest mode sits exactly on a
combination of two stronger ones (``f_1 + f_2``, ``|f_1 - f_2|``, ``2 f_1`` or ``2 f_1 -
f_2``): a true mode that the frequency alone would take for a product. The seeds start at
70000, away from every other script's draws.

Four results per video (two extractions):

* ``default``: :func:`vvtbench.modes.extract_modes` as shipped (faint products rejected by
  power, rough ones by roughness);
* ``+ combinations``: the same followed by :func:`vvtbench.modes.combinations.reject_combinations`;
* ``shape/phase only``: ``faint_product_ratio=None`` (no rejection by power) followed by
  ``reject_combinations``;
* ``in place of the faint rule``: the same with ``reject_combinations(faint_ratio=0.01)``:
  faint candidates at a combination are products unless their phase or their sibling's shape
  says otherwise.

A detection is false when no true frequency is within one bin; a true mode (spectral line of
at least 0.001 px, ``bench_unseen_videos.py``'s ``line_px``) is lost when no detection is
within one bin.

Usage: ``python benchmarks/bench_false_modes.py [--n 16] [--start 0] [--max-amplitude 0.3]
[--diag]``; prints one
line per video and a table of the totals.  ``--diag`` prints, for every candidate of an
extraction that keeps every peak, whether it is true and its best combination's phase residual
and envelope correlation.
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from pathlib import Path

import numpy as np
from bench_extractors import speckle
from bench_unseen_videos import SPECKLE_SIZE, smooth_field, write_mkv

from vvtbench.modes import extract_modes
from vvtbench.modes.combinations import (
    Combination,
    combination_phase_residual,
    envelope_correlation,
    find_combinations,
    reject_combinations,
)

SEED_OFFSET = 70_000
FAINT_RATIO = 0.01
FLOOR_PX = 0.001


def _coincidence(freqs: list[float], order: np.ndarray, rng: np.random.Generator, lo: float,
                 hi: float, min_gap: float) -> float | None:
    """A frequency on a combination of the two strongest modes, in the band and clear of the
    other modes, or None."""
    f1 = freqs[order[0]]
    options = [2 * f1]
    if len(order) > 1:
        f2 = freqs[order[1]]
        options += [f1 + f2, abs(f1 - f2), abs(2 * f1 - f2)]
    rng.shuffle(options)
    for c in options:
        if lo <= c <= hi and all(abs(c - g) > min_gap for g in freqs):
            return float(c)
    return None


def draw(seed: int, max_amplitude: float = 0.3) -> dict:
    """The clean video of ``seed`` and its truth (amplitudes up to ``max_amplitude`` px)."""
    rng = np.random.default_rng(SEED_OFFSET + seed)
    h, w = (int(v) for v in rng.choice([96, 128, 160], 2))
    sigma = float(rng.choice([1.0, 1.5, 2.5]))
    fps = float(rng.choice([500.0, 1000.0, 2000.0]))
    n_frames = int(rng.choice([500, 1000]))
    n_modes = int(rng.integers(2, 6))
    df = fps / n_frames
    lo, hi = 6 * df, 0.45 * fps
    freqs: list[float] = []
    while len(freqs) < n_modes:
        f = float(rng.uniform(lo, hi))
        if all(abs(f - g) > 4 * df for g in freqs):
            freqs.append(f)
    amps = np.exp(rng.uniform(np.log(FLOOR_PX), np.log(max_amplitude), n_modes))
    amps[np.argmin(amps)] = FLOOR_PX
    coincident = None
    if rng.random() < 0.5:
        order = np.argsort(-amps)
        c = _coincidence([freqs[i] for i in range(n_modes) if i != order[-1]],
                         np.argsort(-np.delete(amps, order[-1])), rng, lo, hi, 4 * df)
        if c is not None:
            freqs[int(order[-1])] = c
            coincident = c
    freqs_a = np.asarray(freqs)
    zetas = np.where(rng.random(n_modes) < 0.3, rng.uniform(0.0, 0.005, n_modes), 0.0)
    plucked = bool(rng.random() < 0.5)
    phases = np.zeros(n_modes) if plucked else rng.uniform(0, 2 * np.pi, n_modes)
    fields = np.stack([smooth_field(h, w, rng) for _ in range(n_modes)])
    F, wx, wy = speckle(SPECKLE_SIZE, SEED_OFFSET + seed, sigma)
    y0, x0 = rng.integers(0, SPECKLE_SIZE - h), rng.integers(0, SPECKLE_SIZE - w)
    ders = {(i, j): np.fft.ifft2(F * (1j * wx) ** i * (1j * wy) ** j).real[y0:y0 + h, x0:x0 + w]
            for i in range(4) for j in range(4 - i)}
    t = np.arange(n_frames) / fps
    q = amps[:, None] * np.exp(-2 * np.pi * np.outer(freqs_a * zetas, t)) * np.cos(
        2 * np.pi * np.outer(freqs_a, t) + phases[:, None])
    frames = np.empty((n_frames, h, w), np.float32)
    for k in range(n_frames):
        d = np.tensordot(q[:, k], fields, axes=1)
        img = ders[(0, 0)].copy()
        for (i, j), der in ders.items():
            if i + j:
                img += ((-1) ** (i + j) / (math.factorial(i) * math.factorial(j))
                        * d[..., 0] ** i * d[..., 1] ** j * der)
        frames[k] = img
    fd = freqs_a * np.sqrt(1 - zetas**2)
    line = np.abs(2 / n_frames * np.sum(q * np.exp(-2j * np.pi * np.outer(fd, t)), axis=1))
    return {"frames": frames, "fps": fps, "freqs": freqs_a, "amps": amps, "line_px": line,
            "plucked": plucked, "coincident_hz": coincident}


def tally(freqs_found: np.ndarray, v: dict) -> tuple[list[float], list[float]]:
    """False detections and lost detectable true modes (Hz)."""
    df = v["fps"] / len(v["frames"])
    found = np.asarray(freqs_found, dtype=np.float64)
    false = [float(f) for f in found if np.min(np.abs(f - v["freqs"])) > df]
    lost = [float(f) for f, a in zip(v["freqs"], v["line_px"], strict=True)
            if a >= FLOOR_PX and not np.any(np.abs(found - f) <= df)]
    return false, lost


def diagnose(seed: int, v: dict, path: Path) -> None:
    """Every candidate of an extraction that rejects nothing, with its best combination's
    phase residual and envelope correlation."""
    ms = extract_modes(path, reject_distortion=False, faint_product_ratio=None)
    kept, _ = find_combinations(ms.frequencies_hz, ms.amplitudes_px, ms.shapes,
                                ms.fps / ms.n_frames, fps=ms.fps, max_phase_residual=np.inf,
                                min_envelope_correlation=2.0)
    del kept
    df = ms.fps / ms.n_frames
    f, a = ms.frequencies_hz, ms.amplitudes_px
    phases = np.array([ms.metadata["phase_rad"][i] for i in ms.analysed_index()])
    order = np.argsort(-a, kind="stable")
    for r, k in enumerate(order):
        true = bool(np.min(np.abs(f[k] - v["freqs"])) <= df)
        rows = []
        for c in _combinations_near(f, order[:r], f[k], df, ms.fps):
            res = combination_phase_residual(phases, f, int(k), c, fps=ms.fps)
            env = envelope_correlation(ms.shapes[k], ms.shapes[list(c.parents)],
                                       [abs(n) for n in c.coefficients])
            rows.append(f"{c.label(f)}: phase {res:+.2f} env {env:+.2f}")
        print(f"  diag {seed} {f[k]:8.2f} Hz {a[k]:.2e} {'TRUE ' if true else 'false'} "
              + ("; ".join(rows) if rows else "-"))


def _combinations_near(f: np.ndarray, parents: np.ndarray, target: float, df: float,
                       fps: float) -> list[Combination]:
    out = []
    p = [int(i) for i in parents]
    cands = [Combination((i,), (n,)) for i in p for n in (2, 3)]
    cands += [Combination((i, j), c) for a, i in enumerate(p) for j in p[a + 1:]
              for c in ((1, 1), (1, -1), (-1, 1))]
    cands += [Combination((i, j), c) for i in p for j in p if i != j for c in ((2, 1), (2, -1),
                                                                              (-2, 1))]
    for c in cands:
        fc = c.frequency(f)
        r = abs(fc) % fps
        seen = min(r, fps - r)
        if fc > 0 and abs(seen - target) <= 0.5 * df:
            out.append(c)
    return out


def run(seed: int, tmp: Path, diag: bool = False, max_amplitude: float = 0.3) -> dict:
    v = draw(seed, max_amplitude)
    path = tmp / f"clean_{seed}.mkv"
    write_mkv(path, v["frames"], v["fps"])
    t0 = time.perf_counter()
    default = extract_modes(path)
    combined = reject_combinations(default)
    every_peak = extract_modes(path, faint_product_ratio=None)
    no_power = reject_combinations(every_peak)
    in_place = reject_combinations(every_peak, faint_ratio=FAINT_RATIO)
    elapsed = time.perf_counter() - t0
    if diag:
        diagnose(seed, v, path)
    path.unlink()
    out = {"seed": seed, "fps": v["fps"], "n_frames": len(v["frames"]),
           "shape": default.image_shape, "n_true": len(v["freqs"]), "plucked": v["plucked"],
           "coincident_hz": v["coincident_hz"], "seconds": elapsed,
           "products": [f"{r['product']} ({r['test']})" for r in in_place.metadata["rejected"]
                        if r.get("reason") == "product"]}
    for name, ms in (("default", default), ("combined", combined), ("shape_phase", no_power),
                     ("in_place", in_place)):
        out[name] = tally(ms.frequencies_hz, v)
    return out


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


def _amplitude(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not value >= FLOOR_PX:
        raise argparse.ArgumentTypeError(f"{text!r}: a number of px >= {FLOOR_PX}")
    return value


COLUMNS = (("default", "default"), ("combined", "+ combinations"),
           ("shape_phase", "shape/phase only"), ("in_place", "in place of the faint rule"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=_at_least(1), default=16)
    ap.add_argument("--start", type=_at_least(0), default=0)
    ap.add_argument("--diag", action="store_true")
    ap.add_argument("--max-amplitude", type=_amplitude, default=0.3,
                    help="largest modal amplitude drawn (px, >= 0.001; default 0.3)")
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(args.start, args.start + args.n):
            r = run(seed, Path(tmp), args.diag, args.max_amplitude)
            rows.append(r)
            parts = [f"{label}: false {[round(f, 2) for f in r[key][0]]} lost "
                     f"{[round(f, 2) for f in r[key][1]]}" for key, label in COLUMNS]
            print(f"{seed:3d} {r['shape'][0]}x{r['shape'][1]} {r['n_frames']} fr {r['fps']:g} fps "
                  f"{r['n_true']} modes {'pluck' if r['plucked'] else 'random phase'}"
                  + (f", one at a combination ({r['coincident_hz']:.2f} Hz)"
                     if r["coincident_hz"] else "")
                  + f" | {' | '.join(parts)} | rejected {r['products']} ({r['seconds']:.1f} s)",
                  flush=True)
    print(f"\nseeds {args.start}..{args.start + args.n - 1}, amplitudes {FLOOR_PX}-"
          f"{args.max_amplitude} px ({len(rows)} clean videos, "
          f"{sum(r['n_true'] for r in rows)} true modes, "
          f"{sum(r['coincident_hz'] is not None for r in rows)} on a combination frequency)")
    print("| extraction | false modes | most in one video | videos with > 1 false "
          "| true modes lost |")
    print("|---|---|---|---|---|")
    for key, label in COLUMNS:
        print(f"| {label} | {sum(len(r[key][0]) for r in rows)} | "
              f"{max(len(r[key][0]) for r in rows)} | "
              f"{sum(len(r[key][0]) > 1 for r in rows)} | {sum(len(r[key][1]) for r in rows)} |")


if __name__ == "__main__":
    main()
