"""Coverage of the reported 95 % damping intervals against the true damping ratios.

For each pair of a generated sample folder (its ``truth.json``) and the mode set extracted
from its video with ``--line-fit`` (``vvtbench extract VIDEO --line-fit -o MODES``), every
identified mode is matched to the nearest true mode in frequency (within ``--tol`` relative;
unmatched modes are counted apart) and its interval ``[damping_lo, damping_hi]`` tested
for containing the true ``zeta``.  Coverage is reported over the modes whose damping is
resolved (:meth:`vvtbench.modes.ModeSet.damping_resolved`, the target: >= 90 %) and over every
matched mode with an interval, with the counts, plus the modes flagged ``close_mode_bias``.
Use val instances only, e.g.::

    vvtbench generate jello_cube_damped_center_top_front -o /tmp/cov
    vvtbench extract /tmp/cov/jello_cube_damped_center_top_front/video.mkv --line-fit \
        --weighting noise --faint-product-ratio 0.01 --max-modes 2000 --fmax 200 -o /tmp/m0
    python benchmarks/bench_damping_coverage.py /tmp/cov/jello_cube_damped_center_top_front \
        /tmp/m0
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from vvtbench.modes import ModeSet


def sample_coverage(sample: Path, modes: Path, tol: float) -> list[dict]:
    """One row per identified mode: matched truth, interval, resolved, covered."""
    truth = json.loads((sample / "truth.json").read_text())["modes"]
    f_true = np.asarray(truth["frequencies_hz"], np.float64)
    z_true = np.asarray(truth["damping_ratios"], np.float64)
    ms = ModeSet.load(modes)
    lo, hi = ms.damping_interval()
    resolved, biased = ms.damping_resolved(), ms.close_mode_bias()
    rows = []
    for i, f in enumerate(ms.frequencies_hz):
        j = int(np.argmin(np.abs(f_true - f)))
        matched = abs(f_true[j] - f) <= tol * f_true[j]
        near = np.abs(f_true - f) <= tol * f_true[j]
        covered = bool(np.any((lo[i] <= z_true[near]) & (z_true[near] <= hi[i])))
        rows.append({"sample": sample.name, "index": i, "f_hz": float(f),
                     "f_true_hz": float(f_true[j]), "matched": bool(matched),
                     "zeta": float(ms.damping[i]), "zeta_true": float(z_true[j]),
                     "lo": float(lo[i]), "hi": float(hi[i]), "resolved": bool(resolved[i]),
                     "close_mode_bias": bool(biased[i]), "covered": covered})
    return rows


def _share(rows: list[dict]) -> str:
    n = len(rows)
    k = sum(r["covered"] for r in rows)
    return f"{k}/{n} = {100.0 * k / n:.1f} %" if n else "0/0"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("pairs", nargs="+", help="SAMPLE_DIR MODES_DIR [SAMPLE_DIR MODES_DIR ...]")
    ap.add_argument("--tol", type=float, default=0.01,
                    help="relative frequency tolerance of a match (default 0.01)")
    ap.add_argument("--rows", action="store_true", help="print every mode")
    args = ap.parse_args(argv)
    if len(args.pairs) % 2:
        ap.error("give SAMPLE_DIR MODES_DIR pairs")
    rows: list[dict] = []
    for s, m in zip(args.pairs[::2], args.pairs[1::2], strict=True):
        rows += sample_coverage(Path(s), Path(m), args.tol)
    with_interval = [r for r in rows if r["matched"] and np.isfinite(r["lo"])]
    resolved = [r for r in with_interval if r["resolved"]]
    if args.rows:
        print("| sample | # | f (Hz) | f true | zeta | [lo, hi] | zeta true | resolved | "
              "close bias | covered |")
        print("|---|---|---|---|---|---|---|---|---|---|")
        for r in rows:
            print(f"| {r['sample']} | {r['index']} | {r['f_hz']:.3f} | {r['f_true_hz']:.3f} | "
                  f"{r['zeta']:.4f} | [{r['lo']:.4f}, {r['hi']:.4f}] | {r['zeta_true']:.4f} | "
                  f"{r['resolved']} | {r['close_mode_bias']} | {r['covered']} |")
    print(f"modes: {len(rows)}, matched within {args.tol:g}: "
          f"{sum(r['matched'] for r in rows)}, with an interval: {len(with_interval)}")
    print(f"coverage, resolved dampings: {_share(resolved)}")
    print(f"coverage, every matched interval: {_share(with_interval)}")
    print(f"flagged close_mode_bias: {sum(r['close_mode_bias'] for r in rows)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
