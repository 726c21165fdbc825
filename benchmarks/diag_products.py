"""Which false detections are distortion products, how rough they are, and whether their
phase is a product's.

    .venv/bin/python benchmarks/diag_products.py [--line-fit] SAMPLE [SAMPLE ...]

For each generated sample (a folder with video and truth, e.g. a `standard_val` run's
``cache/generate/<key>/sample``): ``extract_modes(max_modes=30, fmax=200,
reject_distortion=False)``, detections scored against the true modes
(:func:`vvtbench.scoring.extraction.score_sample_extraction`), and every detection tested as a
second-order product of stronger ones (:func:`vvtbench.modes.peaks.distortion_products`, power
ratio 0.5, half a bin). Prints one JSON line per detection in the scored band (frequency,
false or true, product kind and parents, power ratio, roughness, phase residual), then how
many false and true detections each product-roughness threshold would reject, and how many
have a phase within 0.1, 0.2 and 0.4 rad of their product's
(:func:`vvtbench.modes.peaks.product_phase_residual`; a phase unrelated to the product's is
that close with probability 0.06, 0.13 and 0.25).
``--line-fit``: the paper suite's extraction (line fit, up to 2000 modes) instead.
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from vvtbench.modes import extract_modes
from vvtbench.modes.peaks import distortion_products, product_phase_residual
from vvtbench.samples.reader import open_sample
from vvtbench.scoring.extraction import score_sample_extraction

THRESHOLDS = (0.15, 0.12, 0.10, 0.08, 0.05)
PHASE_TOLERANCES = (0.1, 0.2, 0.4)


def detections(sample_dir: str, line_fit: bool = False) -> list[dict]:
    s = open_sample(sample_dir)
    ms = extract_modes(s.video_path, s.fps, max_modes=2000 if line_fit else 30, fmax=200.0,
                       reject_distortion=False, line_fit=line_fit)
    sc = score_sample_extraction(s, ms, 200.0)
    false = {i for _, i, _ in sc["unmatched"]}
    lo, hi = sc["band_hz"]
    f = ms.frequencies_hz
    p = np.asarray(ms.power)[ms.peak_bins]
    rough = ms.metadata["roughness"]
    phase = ms.metadata["phase_rad"] if len(ms.metadata["phase_rad"]) == len(ms) else None
    flagged = {d["index"]: d for d in distortion_products(f, p, ms.fps / ms.n_frames,
                                                          power_ratio=0.5)}
    out = []
    for k in range(len(ms)):
        d = flagged.get(k)
        if not lo <= f[k] <= hi:  # above the highest true mode nothing is scored
            continue
        out.append({"sample": sample_dir, "frequency_hz": float(f[k]), "false": k in false,
                    "product": None if d is None else d["kind"],
                    "parents_hz": None if d is None else [float(f[i]) for i in d["parents"]],
                    "power_ratio": None if d is None else float(
                        p[k] / min(p[i] for i in d["parents"])),
                    "roughness": float(rough[k]) if len(rough) == len(ms) else None,
                    "phase_residual_rad": None if d is None or phase is None else
                    product_phase_residual(phase, f, k, *d["parents"], d["kind"],
                                           fps=ms.fps)})
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("samples", nargs="+")
    ap.add_argument("--line-fit", action="store_true")
    args = ap.parse_args()
    rows = [r for s in args.samples for r in detections(s, args.line_fit)]
    for r in rows:
        print(json.dumps(r))
    products = [r for r in rows if r["product"] and r["roughness"] is not None]
    print(f"{len(rows)} detections, {sum(r['false'] for r in rows)} false, "
          f"{sum(r['false'] for r in products)} of them products")
    print("| product roughness threshold | false products rejected | true modes rejected |")
    print("|---|---|---|")
    for t in THRESHOLDS:
        print(f"| {t:.2f} | {sum(r['false'] and r['roughness'] > t for r in products)} | "
              f"{sum(not r['false'] and r['roughness'] > t for r in products)} |")

    phased = [r for r in products if r["phase_residual_rad"] is not None]
    print("| phase residual within | false products | true modes at a product frequency |")
    print("|---|---|---|")
    n_false = sum(r["false"] for r in phased)
    for tol in PHASE_TOLERANCES:
        close = [r for r in phased if abs(r["phase_residual_rad"]) <= tol]
        c_false = sum(r["false"] for r in close)
        print(f"| {tol} rad | {c_false} of {n_false} | {len(close) - c_false} of "
              f"{len(phased) - n_false} |")


if __name__ == "__main__":
    main()
