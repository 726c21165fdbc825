"""Coverage of the reported frequency and damping intervals against the true modes.

For each pair of a generated sample folder (its ``truth.json``) and a mode set extracted from
its video (``vvtbench extract VIDEO -o MODES``, with or without ``--line-fit``), every identified
mode is matched to the nearest true mode in frequency (within ``--tol`` relative; unmatched
modes are counted apart) and tested:

* frequency: ``|f - f_d| <= q sf`` with ``f_d = f0 sqrt(1 - zeta**2)`` the true damped
  frequency (the one a spectral line sits at), ``sf`` the reported ``frequency_std_hz`` and
  ``q`` the set's 95 % quantile (1.96 for the line fit; Student's ``t`` of the jackknife's
  groups, ``metadata.uncertainty_groups.t95``, for peak-picked modes);
* damping: ``[damping_lo, damping_hi]`` contains the true ``zeta`` of a true mode within
  ``--tol`` (degenerate pairs share a frequency).

Coverage is reported per uncertainty method (``metadata.uncertainty_method``) over the modes
whose damping is resolved (:meth:`vvtbench.modes.ModeSet.damping_resolved`; the target: >= 90 %
of their intervals cover the truth) and over every matched mode with an interval, each with its
exact (Clopper-Pearson) 95 % binomial interval; modes flagged ``close_mode_bias`` are counted.
On an undamped video (every true ``zeta`` 0) a resolved damping is a false one: they are
counted apart.  Example (a val instance)::

    vvtbench generate jello_cube_damped_center_top_front -o /tmp/cov
    vvtbench extract /tmp/cov/jello_cube_damped_center_top_front/video.mkv \
        --weighting noise --faint-product-ratio 0.01 --max-modes 2000 --fmax 200 -o /tmp/m0
    python benchmarks/bench_damping_coverage.py /tmp/cov/jello_cube_damped_center_top_front \
        /tmp/m0
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from scipy.stats import beta

from vvtbench.modes import ModeSet
from vvtbench.modes.uncertainty import LINE_FIT_METHOD, Z95


def _quantile(ms: ModeSet) -> tuple[str, float]:
    method = ms.metadata.get("uncertainty_method")
    if method is None and ms.metadata.get("line_fit"):
        method = LINE_FIT_METHOD  # sets written before the method was recorded
    groups = ms.metadata.get("uncertainty_groups") or {}
    return str(method), float(groups.get("t95", Z95))


def sample_coverage(sample: Path, modes: Path, tol: float) -> list[dict]:
    """One row per identified mode: matched truth, intervals, resolved, covered."""
    doc = json.loads((sample / "truth.json").read_text())
    truth = doc["modes"]
    scene = doc.get("scene")
    name = scene.get("name", sample.name) if isinstance(scene, dict) else sample.name
    f0 = np.asarray(truth["frequencies_hz"], np.float64)
    z_true = np.asarray(truth["damping_ratios"], np.float64)
    f_true = f0 * np.sqrt(np.clip(1.0 - z_true**2, 0.0, 1.0))
    ms = ModeSet.load(modes)
    method, q = _quantile(ms)
    lo, hi = ms.damping_interval()
    sf = ms.frequency_std_hz()
    resolved, biased = ms.damping_resolved(), ms.close_mode_bias()
    rows = []
    for i, f in enumerate(ms.frequencies_hz):
        j = int(np.argmin(np.abs(f_true - f)))
        near = np.abs(f_true - f) <= tol * f_true[j]
        rows.append({
            "sample": name, "modes": str(modes), "method": method, "index": i,
            "f_hz": float(f), "f_true_hz": float(f_true[j]), "sf_hz": float(sf[i]),
            "q": q, "matched": bool(near[j]),
            "f_covered": bool(abs(f - f_true[j]) <= q * sf[i]),
            "zeta": float(ms.damping[i]), "zeta_true": float(z_true[j]),
            "lo": float(lo[i]), "hi": float(hi[i]), "resolved": bool(resolved[i]),
            "close_mode_bias": bool(biased[i]), "undamped": bool(np.all(z_true == 0)),
            "covered": bool(np.any((lo[i] <= z_true[near]) & (z_true[near] <= hi[i]))),
        })
    return rows


def clopper_pearson(k: int, n: int, level: float = 0.95) -> tuple[float, float]:
    """Exact binomial interval of a proportion ``k / n``."""
    a = 1.0 - level
    low = float(beta.ppf(a / 2, k, n - k + 1)) if k > 0 else 0.0
    high = float(beta.ppf(1 - a / 2, k + 1, n - k)) if k < n else 1.0
    return low, high


def _share(rows: list[dict], key: str) -> str:
    n = len(rows)
    if not n:
        return "0/0"
    k = sum(r[key] for r in rows)
    lo, hi = clopper_pearson(k, n)
    return f"{k}/{n} = {100.0 * k / n:.1f} % [{100 * lo:.0f}, {100 * hi:.0f}]"


def summarize(rows: list[dict]) -> list[str]:
    """Coverage lines per uncertainty method."""
    out = []
    for method in sorted({r["method"] for r in rows}):
        mine = [r for r in rows if r["method"] == method]
        matched = [r for r in mine if r["matched"]]
        with_f = [r for r in matched if np.isfinite(r["sf_hz"]) and r["sf_hz"] > 0]
        damped = [r for r in matched if not r["undamped"] and np.isfinite(r["lo"])]
        resolved = [r for r in damped if r["resolved"]]
        flat = [r for r in matched if r["undamped"]]
        f_resolved = [r for r in with_f if r["resolved"]]
        out += [
            f"{method}: {len(mine)} modes in {len({r['modes'] for r in mine})} sets, "
            f"matched within the tolerance {len(matched)}",
            f"  frequency, every matched mode: {_share(with_f, 'f_covered')}",
            f"  frequency, resolved dampings: {_share(f_resolved, 'f_covered')}",
            f"  damping, resolved (damped videos): {_share(resolved, 'covered')}",
            f"  damping, every interval (damped videos): {_share(damped, 'covered')}",
            f"  flagged close_mode_bias: {sum(r['close_mode_bias'] for r in mine)}",
        ]
        if flat:
            out.append(f"  undamped videos: {len(flat)} matched modes, "
                       f"{sum(r['resolved'] for r in flat)} resolved (a false damping), "
                       f"interval contains 0: {_share(flat, 'covered')}")
    return out


def time_jackknife(T: int = 6000, side: int = 128, fps: float = 2000.0) -> str:
    """CPU time of the peak-picked modes' uncertainty (one pass plus 16 leave-one-out fits
    per peak) beside one spectrum pass, on ``T`` frames of a ``side``-square displacement
    grid with 8 damped modes in noise (the paper cube's frequencies, seed 0)."""
    import time

    from vvtbench.modes.damping import damping_lorentzian
    from vvtbench.modes.jackknife import peak_uncertainty
    from vvtbench.modes.spectrum import motion_power_spectrum

    rng = np.random.default_rng(0)
    t = np.arange(T) / fps
    yy, xx = np.mgrid[0:side, 0:side]
    disp = np.empty((T, side, side, 2), np.float32)
    for c in range(0, T, 500):
        disp[c:c + 500] = 1e-3 * rng.standard_normal(disp[c:c + 500].shape, dtype=np.float32)
    fs = [5.65, 7.8, 12.2, 14.7, 20.1, 23.3, 25.2, 27.2]
    for i, f in enumerate(fs):
        sig = (0.02 * np.exp(-2 * np.pi * f * 0.02 * t) * np.cos(2 * np.pi * f * t))
        shape = np.stack([np.sin((i + 1) * np.pi * xx / side),
                          np.cos((i + 1) * np.pi * yy / side)], -1)
        for c in range(0, T, 500):
            disp[c:c + 500] += (sig[c:c + 500, None, None, None] * shape[None]).astype(np.float32)
    c0 = time.process_time()
    freqs, p = motion_power_spectrum(disp, fps, window="hann")
    c1 = time.process_time()
    bins = [int(round(f * T / fps)) for f in fs]
    z = [damping_lorentzian(freqs, p, k, window="hann", n_frames=T)[0] for k in bins]
    c2 = time.process_time()
    peak_uncertainty(disp, freqs, bins, fps, frequency_hz=np.array(bins) * fps / T, damping=z,
                     band=(0.0, 200.0))
    c3 = time.process_time()
    return (f"{T} frames of {side}x{side}x2, 8 peaks: spectrum pass {c1 - c0:.1f} s CPU, "
            f"peak_uncertainty {c3 - c2:.1f} s CPU")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("pairs", nargs="*", help="SAMPLE_DIR MODES_DIR [SAMPLE_DIR MODES_DIR ...]")
    ap.add_argument("--time", action="store_true",
                    help="time the peak-picked modes' uncertainty on a synthetic record")
    ap.add_argument("--tol", type=float, default=0.01,
                    help="relative frequency tolerance of a match (default 0.01)")
    ap.add_argument("--rows", action="store_true", help="print every mode")
    args = ap.parse_args(argv)
    if args.time:
        print(time_jackknife())
        if not args.pairs:
            return 0
    if not args.pairs or len(args.pairs) % 2:
        ap.error("give SAMPLE_DIR MODES_DIR pairs")
    rows: list[dict] = []
    for s, m in zip(args.pairs[::2], args.pairs[1::2], strict=True):
        rows += sample_coverage(Path(s), Path(m), args.tol)
    if args.rows:
        print("| sample | method | # | f (Hz) | sf | f_d true | f ok | zeta | [lo, hi] | "
              "zeta true | resolved | close | covered |")
        print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
        for r in rows:
            print(f"| {r['sample']} | {r['method']} | {r['index']} | {r['f_hz']:.4f} | "
                  f"{r['sf_hz']:.2g} | {r['f_true_hz']:.4f} | {r['f_covered']} | "
                  f"{r['zeta']:.4f} | [{r['lo']:.4f}, {r['hi']:.4f}] | {r['zeta_true']:.4f} | "
                  f"{r['resolved']} | {r['close_mode_bias']} | {r['covered']} |")
    print(f"modes: {len(rows)}, tolerance {args.tol:g} relative; coverage k/n = % "
          "[exact 95 % binomial interval]")
    for line in summarize(rows):
        print(line)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
