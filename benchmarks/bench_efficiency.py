"""Extractor efficiency against the Cramér-Rao bound, ``eta = sigma_CRB^2 / MSE``.

For every registered extractor (``vvtbench.extractors`` entry points) and the ideal known-texture
Gauss-Newton estimator (:class:`vvtbench.scoring.efficiency.KnownTextureShift`, eta ~ 1 by
construction: the check of the machinery), at every amplitude (0.0005 - 1 px, log-spaced),
noise (0.5, 1, 2 % of full scale) and bit depth (8, 12, 16): speckle frames translated by a
known sub-pixel shift through the sensor model, the extractor's whole-frame mean estimate
against the truth (:func:`vvtbench.scoring.efficiency.extractor_efficiency`).  Prints a CSV
and Markdown tables (eta, bias and std), the share of the Fisher information in the phase
pyramid's band (:func:`~vvtbench.scoring.efficiency.band_information`), and writes the figure
(eta against amplitude, one line per extractor, a panel per noise level and bit depth).

Usage: ``python benchmarks/bench_efficiency.py [--size 64] [--repeats 48] [--quick]
[--out benchmarks/efficiency.png]``.
"""

from __future__ import annotations

import argparse
import io
import os
import platform
import time
from datetime import UTC, datetime

import numpy as np

from vvtbench.io.files import write_bytes
from vvtbench.scoring.efficiency import (
    EfficiencySetting,
    KnownTextureShift,
    band_information,
    extractor_efficiency,
    rest_image,
)
from vvtbench.solving.extractors import list_extractors

AMPLITUDES = tuple(float(a) for a in np.geomspace(0.0005, 1.0, 8))
NOISES = (0.005, 0.01, 0.02)
BITS = (8, 12, 16)
IDEAL = "known-texture"
COLUMNS = ("extractor", "noise", "bit_depth", "amplitude_px", "crb_px", "rmse_px", "bias_px",
           "std_px", "eta", "eta_se", "eta_variance", "ms_frame")


def run(name: str, st: EfficiencySetting) -> dict:
    if name == IDEAL:
        return extractor_efficiency(KnownTextureShift, st, config={"block": st.size})
    return extractor_efficiency(name, st)


def plot(rows: list[dict], names: list[str], out: str, title: str) -> None:
    """eta against amplitude, a panel per (noise, bit depth) present in ``rows``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    noises = sorted({r["noise"] for r in rows})
    bits_list = sorted({r["bit_depth"] for r in rows})
    fig, axes = plt.subplots(len(noises), len(bits_list), dpi=100, sharex=True, sharey=True,
                             figsize=(4 * len(bits_list), 0.5 + 3 * len(noises)), squeeze=False)
    colors = dict(zip(names, plt.rcParams["axes.prop_cycle"].by_key()["color"], strict=False))
    for i, z in enumerate(noises):
        for j, bits in enumerate(bits_list):
            ax = axes[i, j]
            for nm in names:
                rr = [r for r in rows if r["extractor"] == nm and r["noise"] == z
                      and r["bit_depth"] == bits]
                a = np.array([r["amplitude_px"] for r in rr])
                e = np.array([r["eta"] for r in rr])
                se = np.array([r["eta_se"] for r in rr])
                ax.errorbar(a, e, yerr=se, marker="o", ms=3, lw=1.2, capsize=2,
                            color=colors[nm], ls="--" if nm == IDEAL else "-", label=nm)
            ax.axhline(1.0, color="k", lw=0.8)
            ax.axhline(0.5, color="0.6", lw=0.6, ls=":")
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_ylim(0.02, 2.0)
            ax.grid(True, which="both", alpha=0.25)
            ax.set_title(f"noise {100 * z:g} % FS, {bits} bit", fontsize=10)
            if i == len(noises) - 1:
                ax.set_xlabel("shift amplitude (px)")
            if j == 0:
                ax.set_ylabel(r"$\eta = \sigma^2_{CRB}$ / MSE")
    axes[0, 0].legend(fontsize=8, loc="lower left")
    fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    write_bytes(out, buf.getvalue())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--repeats", type=int, default=48, help="noise draws per direction")
    ap.add_argument("--grain", type=float, default=2.0, help="speckle grain (px)")
    ap.add_argument("--quick", action="store_true", help="3 amplitudes, 12-bit 1 %% only")
    ap.add_argument("--out", default="benchmarks/efficiency.png")
    args = ap.parse_args()
    names = sorted(list_extractors()) + [IDEAL]
    amps, noises, bits_list = AMPLITUDES, NOISES, BITS
    if args.quick:
        amps, noises, bits_list = (0.001, 0.01, 0.1), (0.01,), (12,)
    print(f"# {datetime.now(UTC):%Y-%m-%d %H:%M} UTC, {platform.node()}, "
          f"{os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f}; speckle {args.size}^2 grain "
          f"{args.grain} px, 4 directions x {args.repeats} draws, whole-frame estimate")
    rows = []
    t0 = time.time()
    print(",".join(COLUMNS))
    for z in noises:
        for bits in bits_list:
            for a in amps:
                st = EfficiencySetting(amplitude_px=a, noise=z, bit_depth=bits, size=args.size,
                                       grain=args.grain, repeats=args.repeats)
                for nm in names:
                    r = run(nm, st)
                    r["extractor"] = nm
                    rows.append(r)
                    print(",".join(f"{r[c]:.4g}" if isinstance(r[c], float) else str(r[c])
                                   for c in COLUMNS), flush=True)
    print(f"# {time.time() - t0:.0f} s")
    for key, label in (("eta", "eta = CRB^2 / MSE"), ("bias_px", "bias (px)"),
                       ("std_px", "std (px)")):
        print(f"\n{label}\n\n| extractor | noise | bits | "
              + " | ".join(f"{a:.2g}" for a in amps) + " |")
        print("|---|---|---|" + "---|" * len(amps))
        for nm in names:
            for z in noises:
                for bits in bits_list:
                    rr = [r for r in rows if r["extractor"] == nm and r["noise"] == z
                          and r["bit_depth"] == bits]
                    print(f"| {nm} | {100 * z:g} % | {bits} | "
                          + " | ".join(f"{r[key]:.3g}" for r in rr) + " |")
    info = band_information(rest_image(EfficiencySetting(0.01, size=args.size,
                                                         grain=args.grain)))
    print("\nFisher information of the texture in the phase pyramid's band (3 scales): "
          + ", ".join(f"{k} {v:.3f}" for k, v in info.items()))
    plot(rows, names, args.out, f"Extractor efficiency against the Cramér-Rao bound "
         f"(speckle {args.size}$^2$, grain {args.grain:g} px, whole-frame shift)")
    print(f"\nplot: {args.out}")


if __name__ == "__main__":
    main()
