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

``--ratios`` runs the texture-to-noise sweep instead: at texture-to-noise ratios (the rest
image's standard deviation over the read noise's) of 20, 5, 2 and 1, a low-contrast speckle
(contrast 0.2: no clipping even at ratio 1) of ``--size`` (default 128) moved by 0.1 px in 4
directions, ``--clips`` records of 4 x ``--repeats`` frames each, every extractor with the
reference it had before (``first``: one noisy frame at rest; ``phase`` without refinement)
and the one it has now (``mean``: the temporal mean of the record; ``phase`` refined), on the
test texture seeds ``--seeds`` (1 2 3; the choices were made on seed 0).  Per setting: the
gain (slope of measured on true motion) and ``eta`` with each record's mean error removed
(an offset the spectrum removes).  Then the same per 8 px block at ratio 5 against the
block's own bound and against the bound of the area the extractor pools
(:func:`vvtbench.scoring.crb.footprint_crb` of its measured motion transfer function).
Usage: ``python benchmarks/bench_efficiency.py --ratios [--seeds 1 2 3] [--clips 3]
[--repeats 32] [--size 128]``.
"""

from __future__ import annotations

import argparse
import io
import os
import platform
import time
from dataclasses import replace
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


RATIOS = (20.0, 5.0, 2.0, 1.0)
#: (label, extractor, config, reference): each shipped extractor as it was and as it is
VARIANTS = (
    ("phase, before (first frame, no refinement)", "phase", {"refine": 0}, "first"),
    ("phase, mean reference, no refinement", "phase", {"refine": 0}, "mean"),
    ("phase, now (mean reference, refined)", "phase", None, "mean"),
    ("farneback, before (first frame)", "farneback", None, "first"),
    ("farneback, now (mean reference)", "farneback", None, "mean"),
    ("known texture (ideal; noise-free reference)", IDEAL, None, "clean"),
)


def run_variant(name: str, config, st: EfficiencySetting) -> dict:
    if name == IDEAL:
        return extractor_efficiency(KnownTextureShift, st, config={"block": st.block_px})
    return extractor_efficiency(name, st, config=config)


def pooled(rows: list[dict]) -> dict:
    """Seeds pooled: gain their mean, eta the mean bound over the mean squared error."""
    n = len(rows)
    gains = np.array([r["gain"] for r in rows])
    etas = np.array([r["eta"] for r in rows])
    return {
        "gain": float(gains.mean()),
        "gain_se": float(gains.std(ddof=1) / np.sqrt(n)) if n > 1 else rows[0]["gain_se"],
        "eta": float(np.mean([r["crb_px"] ** 2 for r in rows])
                     / np.mean([r["rmse_px"] ** 2 for r in rows])),
        "eta_se": float(etas.std(ddof=1) / np.sqrt(n)) if n > 1 else rows[0]["eta_se"],
        "ms_frame": float(np.mean([r["ms_frame"] for r in rows])),
    }


def ratio_sweep(args: argparse.Namespace) -> None:
    """The texture-to-noise sweep (module docstring, ``--ratios``)."""
    print(f"# {datetime.now(UTC):%Y-%m-%d %H:%M} UTC, {platform.node()}, "
          f"{os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f}; speckle {args.size}^2 grain "
          f"{args.grain} px contrast 0.2, 0.1 px in 4 directions, {args.clips} records x "
          f"{4 * args.repeats} frames per seed, seeds {args.seeds}, whole-frame estimate, "
          "each record's mean error removed")
    t0 = time.time()
    table: dict[tuple[str, float], dict] = {}
    for label, name, config, ref in VARIANTS:
        for ratio in RATIOS:
            rows = []
            for seed in args.seeds:
                st = EfficiencySetting(amplitude_px=0.1, size=args.size, grain=args.grain,
                                       contrast=0.2, repeats=args.repeats, clips=args.clips,
                                       seed=seed, reference=ref, remove_offset=True)
                rows.append(run_variant(name, config, st.at_ratio(ratio)))
            table[label, ratio] = p = pooled(rows)
            print(f"{label}, ratio {ratio:g}: gain {p['gain']:.4f} +- {p['gain_se']:.4f}, eta "
                  f"{p['eta']:.3f} +- {p['eta_se']:.3f}, {p['ms_frame']:.1f} ms/frame",
                  flush=True)
    print(f"# {time.time() - t0:.0f} s")
    print("\n| extractor | " + " | ".join(f"gain @{r:g}" for r in RATIOS) + " | "
          + " | ".join(f"eta @{r:g}" for r in RATIOS) + " |")
    print("|---|" + "---|" * (2 * len(RATIOS)))
    for label, *_ in VARIANTS:
        print(f"| {label} | "
              + " | ".join(f"{table[label, r]['gain']:.3f}" for r in RATIOS) + " | "
              + " | ".join(f"{table[label, r]['eta']:.2f}" for r in RATIOS) + " |")
    print("\nPer 8 px block at ratio 5 (seed " f"{args.seeds[0]}): eta against the block's own "
          "bound and against the bound of the area the extractor pools\n")
    print("| extractor | eta, block bound | eta, footprint bound | pooled side (px) |")
    print("|---|---|---|---|")
    for label, name, config, ref in VARIANTS:
        if "before" in label or "no refinement" in label or name == IDEAL:
            continue  # the ideal per block: tests/test_efficiency.py (slow at 128^2)
        st = EfficiencySetting(amplitude_px=0.1, size=args.size, grain=args.grain,
                               contrast=0.2, repeats=args.repeats, clips=1, block=8,
                               seed=args.seeds[0], reference=ref,
                               remove_offset=True).at_ratio(5.0)
        box = run_variant(name, config, st)
        fp = run_variant(name, config, replace(st, bound="footprint"))
        print(f"| {label} | {box['eta']:.2f} | {fp['eta']:.2f} | {fp['pooled_px']:.1f} |",
              flush=True)
    print(f"# {time.time() - t0:.0f} s in all")


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
    ap.add_argument("--size", type=int, default=None, help="frame side (64; --ratios 128)")
    ap.add_argument("--repeats", type=int, default=None,
                    help="noise draws per direction (48; --ratios 32)")
    ap.add_argument("--grain", type=float, default=2.0, help="speckle grain (px)")
    ap.add_argument("--quick", action="store_true", help="3 amplitudes, 12-bit 1 %% only")
    ap.add_argument("--out", default="benchmarks/efficiency.png")
    ap.add_argument("--ratios", action="store_true",
                    help="the texture-to-noise sweep, old and new references")
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3],
                    help="texture and noise seeds of --ratios (test; 0 is for tuning)")
    ap.add_argument("--clips", type=int, default=3, help="records per seed in --ratios")
    args = ap.parse_args()
    if args.ratios:
        args.size = args.size or 128
        args.repeats = args.repeats or 32
        ratio_sweep(args)
        return
    args.size = args.size or 64
    args.repeats = args.repeats or 48
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
