"""Identifiers compared on the same displacements: the peak picker (with a suite track's
options) against pole-based identification (ERA; ``identifier="auto"``).

For every sample folder the phase extractor's displacements are computed once (kept in a
:class:`vvtbench.modes.DisplacementStore`, spilled to a temporary file past 1 GiB) and every
identifier runs on them with the weights ``extract_modes`` uses (confidence weights for the
shapes, noise weights for the spectrum and the channels); each result is scored with
:func:`vvtbench.scoring.extraction.score_sample_extraction` (``fmax`` 200 Hz; recall over the
clusters the Cramér-Rao ruler calls detectable) and the modes whose damping is within 10 % of
the truth are counted.

Usage::

    python benchmarks/bench_identifiers.py SAMPLE [SAMPLE ...] \
        [--baseline paper:damping] [--identifiers era auto] [--json OUT.json]

An identifier may carry options of the pole scan (``vvtbench.modes.poles.scan_poles``) as
JSON after a colon, e.g. ``'plscf:{"oversampling": 4}'``; each spelling is one row per sample.

``--baseline SUITE:TRACK`` picks the peak picker's options (the ``paper`` suite's damping
track: the line fit and the reliable-pixel tests; ``standard:cube_video``: the standard
suite's pinned options). Prints one row per sample and identifier and the pooled scores.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from vvtbench.bench.graph import extract_options
from vvtbench.bench.suite import load_suite
from vvtbench.modes import DisplacementStore, modes_from_displacements
from vvtbench.modes.extract import confidence_weights, noise_weights
from vvtbench.modes.spectrum import pixel_noise_power
from vvtbench.samples.reader import open_sample
from vvtbench.scoring.extraction import score_sample_extraction, true_mode_amplitudes
from vvtbench.solving.extractors import make_extractor
from vvtbench.video.files import open_video

FMAX = 200.0
PICKER_KEYS = ("weighting", "faint_product_ratio", "product_scaling", "line_fit",
               "roughness_weighting", "min_reliable_fraction", "max_modes", "fmax",
               "product_roughness")


def displacements(sample, store: DisplacementStore, reference: str = "mean"):
    """The phase extractor's displacements of the sample's video into ``store``, against the
    temporal mean frame (``extract_modes``' default) or the first frame; returns the motion
    object (grid confidence, output shape)."""
    from vvtbench.video.files import mean_frame

    if reference == "mean":
        ref, _ = mean_frame(open_video(sample.video_path).frames)
    else:
        ref = next(iter(open_video(sample.video_path).frames))
    motion = make_extractor("phase", {"workers": 1}).prepare(ref)
    for d in motion.iter_displacements(iter(open_video(sample.video_path).frames), batch=32):
        store.append(d)
    return motion


def damping_within(score: dict, tolerance: float = 0.1) -> int:
    """Matched modes whose damping is within ``tolerance`` (relative) of the nearest true
    mode's."""
    n = 0
    for m in score.get("matching", []):
        z, zt = m.get("damping"), m.get("true_damping")
        if zt and zt > 0 and z is not None and np.isfinite(z) and abs(z / zt - 1) <= tolerance:
            n += 1
    return n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("samples", type=Path, nargs="+")
    ap.add_argument("--baseline", nargs="+", default=["paper:damping"],
                    help="SUITE:TRACK whose [extract] options the peak picker uses (several: "
                    "one peak-picker run each; a suite without tracks: SUITE:)")
    ap.add_argument("--identifiers", nargs="+", default=["era", "auto"])
    ap.add_argument("--json", type=Path, default=None, help="write the rows here")
    ap.add_argument("--reference", choices=("mean", "first"), default="mean",
                    help="the motion's reference frame (extract_modes' default: mean)")
    args = ap.parse_args()
    runs = []
    for spec in args.baseline:
        suite_name, _, track_name = spec.partition(":")
        suite = load_suite(suite_name)
        track = next((t for t in suite.tracks if t.name == track_name), None)
        picker = extract_options(suite, "extracted", track.extract if track else None)[0]
        picker = {k: v for k, v in picker.items() if k in PICKER_KEYS}
        runs.append((f"peaks[{spec}]" if len(args.baseline) > 1 else "peaks", picker))
    for spec in args.identifiers:
        name, _, opts = spec.partition(":")
        runs.append((spec, {"pole_options": json.loads(opts)} if opts else {}))
    rows = []
    for path in args.samples:
        sample = open_sample(path)
        amps = true_mode_amplitudes(sample, keep_coordinates=True)
        excitation = getattr(sample.scene.excitation, "kind", None)
        with DisplacementStore() as store:
            t0 = time.perf_counter()
            motion = displacements(sample, store, args.reference)
            t_motion = time.perf_counter() - t0
            conf = motion.grid_confidence
            cw = confidence_weights(conf)
            nw = noise_weights(cw, pixel_noise_power(store))
            for name, opts in runs:
                o = dict(opts)
                sw = None if o.pop("weighting", "noise") == "confidence" else nw
                fmax = o.pop("fmax", FMAX)
                t0 = time.perf_counter()
                ident = "peaks" if name.startswith("peaks") else name.partition(":")[0]
                ms = modes_from_displacements(
                    store, sample.fps, weights=cw, spectrum_weights=sw, fmax=fmax,
                    output_shape=tuple(motion.shape), confidence=motion.confidence,
                    identifier=ident, excitation=excitation if ident == "auto" else None, **o)
                t = time.perf_counter() - t0
                sc = score_sample_extraction(sample, ms, fmax, amplitudes=amps)
                row = {"sample": sample.scene.name, "identifier": name,
                       "used": ms.identifier["used"], "modes": len(ms),
                       "precision": sc["precision"], "recall": sc["recall"],
                       "matched": sc["n_matched"], "detectable": sc["n_detectable"],
                       "damping_within_10pc": damping_within(sc),
                       "mean_rel_damping_error": sc.get("mean_rel_damping_error"),
                       "mean_mac": sc.get("mean_mac"), "seconds": round(t, 1),
                       "motion_seconds": round(t_motion, 1),
                       "frequencies_hz": [round(float(f), 3) for f in ms.frequencies_hz],
                       "rejected": [{"hz": round(r["frequency_hz"], 3), "reason": r["reason"],
                                     **({"product": r["product"]} if "product" in r else {})}
                                    for r in ms.metadata.get("rejected", [])
                                    if r["reason"] == "product"]}
                rows.append(row)
                print(f"{row['sample']:40s} {name:6s} ({row['used']:5s}) modes {len(ms):3d}  "
                      f"P {row['precision']:.3f}  R {row['recall']:.3f} "
                      f"({row['matched']}/{row['detectable']})  zeta within 10 %: "
                      f"{row['damping_within_10pc']}  {t:.0f} s", flush=True)
    print("\npooled (micro): matched / detectable, damping within 10 % / detectable")
    for name, _ in runs:
        grp = [r for r in rows if r["identifier"] == name]
        det = sum(r["detectable"] for r in grp)
        mat = sum(r["matched"] for r in grp)
        found = sum(r["modes"] for r in grp)
        good = sum(r["damping_within_10pc"] for r in grp)
        prec = sum(r["precision"] * r["modes"] for r in grp) / max(found, 1)
        print(f"  {name:6s} precision {prec:.3f}  recall {mat}/{det} = {mat / max(det, 1):.3f}"
              f"  damping within 10 %: {good}/{det} = {good / max(det, 1):.3f}")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
