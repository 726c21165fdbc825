"""Extraction recall over the true modes detectable in the video.

For every generated sample with video in a run's cache whose scene name matches
``--scenes`` (default: the paper suite's undamped defect cubes and damped cubes), the
detected modes are scored against the truth by
:func:`vvtbench.scoring.extraction.score_sample_extraction`: precision, the headline
``recall`` over the true-mode clusters whose spectral-line amplitude in the video
(:func:`vvtbench.scoring.extraction.true_mode_amplitudes`, ``line_px``) reaches the floor,
at each ``--floors`` value, and ``recall_all`` over every cluster in the band.

The detections are those of the run's cached extract tasks, or, with ``--reextract``, a
fresh extraction with the current code and the same task options (written to ``--out``), or,
with ``--modes DIR``, the mode sets saved in ``DIR/<generate task hash>`` (e.g. extracted
with other options). ``--samples DIR ...`` scores sample folders of any origin (e.g. a
family's val split from ``vvtbench generate FAMILY --split val``) instead, extracted with a
suite track's options (``--suite``, ``--track``) and the ``--set`` overrides.

Usage::

    python benchmarks/bench_extraction_recall.py runs/paper/cache [--reextract] \
        [--set line_fit=true --set max_modes=null] \
        [--out /tmp/extract] [--modes DIR] [--floors 0.001 0.003 0.01] \
        [--scenes jello_cube_defect ...]
    python benchmarks/bench_extraction_recall.py --samples DIR [DIR ...] \
        --suite paper --track drums [--set line_fit=true]

Prints a Markdown table per sample and the pooled (micro-averaged) scores per group.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from vvtbench.bench.graph import extract_options
from vvtbench.bench.suite import SuiteError, load_suite
from vvtbench.modes import ModeSet, extract_modes
from vvtbench.samples.reader import open_sample
from vvtbench.scoring.extraction import score_sample_extraction, true_mode_amplitudes

DEFAULT_SCENES = ("jello_cube_defect_top", "jello_cube_defect_bottom", "jello_cube_damped")


def _extract_tasks(cache: Path) -> dict[str, list[tuple[Path, dict]]]:
    """generate key -> [(extract task folder, options)] of the cached extract tasks."""
    out: dict[str, list[tuple[Path, dict]]] = {}
    for t in sorted((cache / "extract").glob("*/task.json")):
        task = json.loads(t.read_text())
        out.setdefault(task["deps"][0], []).append((t.parent, task["payload"]["options"]))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("cache", type=Path, nargs="?",
                    help="a run's cache folder (runs/<suite>/cache)")
    ap.add_argument("--samples", type=Path, nargs="+", default=None,
                    help="sample folders to extract and score instead of a run's cache")
    ap.add_argument("--suite", default="paper", help="with --samples: the suite ...")
    ap.add_argument("--track", default=None, help="... and track whose options to use")
    ap.add_argument("--scenes", nargs="+", default=list(DEFAULT_SCENES),
                    help="scene name prefixes to include")
    ap.add_argument("--floors", nargs="+", type=float, default=[0.001, 0.003, 0.01])
    ap.add_argument("--reextract", action="store_true",
                    help="extract again with the current code (the tasks' options)")
    ap.add_argument("--out", type=Path, default=Path("/tmp/bench_extraction_recall"))
    ap.add_argument("--modes", type=Path, default=None,
                    help="score the mode sets saved in MODES/<generate task hash> instead")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=JSON",
                    help="with --reextract: override an extract option, e.g. line_fit=true, "
                    "max_modes=null (repeatable)")
    args = ap.parse_args()
    overrides = {}
    for kv in args.set:
        key, _, val = kv.partition("=")
        try:
            overrides[key] = json.loads(val)
        except json.JSONDecodeError:
            ap.error(f"--set {kv}: the value must be JSON (e.g. true, 0.01, null, \"noise\")")

    if (args.cache is None) == (args.samples is None):
        ap.error("give either a run's cache folder or --samples")
    if args.samples is not None:
        try:
            suite = load_suite(args.suite)
        except SuiteError as e:
            ap.error(f"--suite: {e}")
        track = next((t for t in suite.tracks if t.name == args.track), None)
        if args.track is not None and track is None:
            ap.error(f"--track: no track {args.track!r} in suite {args.suite!r}")
        missing = [str(d) for d in args.samples if not (d / "truth.json").is_file()]
        if missing:
            ap.error(f"--samples: no sample (truth.json) in {', '.join(missing)}")
        options = extract_options(suite, "extracted", track.extract if track else None)[0]
        samples = [(d / "truth.json", [(d, options)]) for d in args.samples]
    else:
        tasks = _extract_tasks(args.cache)
        samples = [(gen, tasks.get(f"generate/{gen.parent.parent.name}", [])) for gen in
                   sorted((args.cache / "generate").glob("*/sample/truth.json"))]
    rows = []
    for gen, extracts in samples:
        s = open_sample(gen.parent)
        name = s.info["scene"]
        if not s.has_video or (args.samples is None
                               and not any(name.startswith(p) for p in args.scenes)):
            continue
        for folder, options in extracts:
            t0 = time.perf_counter()
            if args.modes is not None:
                if not (args.modes / gen.parent.parent.name).exists():
                    continue
                ms = ModeSet.load(args.modes / gen.parent.parent.name)
            elif args.reextract or args.samples is not None:
                options = {**options, **overrides}
                ms = extract_modes(s.video_path, s.fps, workers=args.workers, **options)
                ms.save(args.out / folder.name)
            else:
                ms = ModeSet.load(folder)
            t_ex = time.perf_counter() - t0
            amps = true_mode_amplitudes(s, keep_coordinates=True)
            res = {fl: score_sample_extraction(s, ms, options.get("fmax"), floor_px=fl,
                                               amplitudes=amps) for fl in args.floors}
            r0 = res[args.floors[0]]
            damped = bool(np.any(np.asarray(s.damping_ratios) > 0))
            rows.append({"scene": name, "damped": damped, "res": res, "t": t_ex,
                         "n_cl": r0["n_clusters_in_band"], "n_det": r0["n_detected"],
                         "n_match": r0["n_matched"], "band": r0["band_hz"][1]})
            print(f"# {name} ({folder.name}): {len(ms)} modes, {t_ex:.0f} s", flush=True)

    fl_cols = " | ".join(f"recall ≥{fl:g} px (n)" for fl in args.floors)
    print(f"\n| scene | damped | band Hz | clusters | detected | precision | {fl_cols} "
          "| recall_all |")
    print("|---|---|---|---|---|---|" + "---|" * len(args.floors) + "---|")
    for r in rows:
        rec = " | ".join(f"{r['res'][fl]['recall']:.2f} ({r['res'][fl]['n_detectable']})"
                         for fl in args.floors)
        r0 = r["res"][args.floors[0]]
        print(f"| {r['scene']} | {'yes' if r['damped'] else 'no'} | {r['band']:.1f} | "
              f"{r['n_cl']} | {r['n_det']} | {r0['precision']:.2f} | {rec} | "
              f"{r0['recall_all']:.2f} |")
    print("\npooled (micro): matched / detected, matched detectable / detectable clusters")
    for damped in (False, True):
        grp = [r for r in rows if r["damped"] == damped]
        if not grp:
            continue
        n_det = sum(r["n_det"] for r in grp)
        p = sum(r["n_match"] for r in grp) / n_det if n_det else float("nan")
        parts = []
        for fl in args.floors:
            hit = sum(r["res"][fl]["n_matched_detectable"] for r in grp)
            den = sum(r["res"][fl]["n_detectable"] for r in grp)
            parts.append(f"recall≥{fl:g}px {hit}/{den} = {hit / den if den else float('nan'):.2f}")
        n_all = sum(r["n_cl"] for r in grp)
        hit_all = sum(round(r["res"][args.floors[0]]["recall_all"] * r["n_cl"]) for r in grp)
        print(f"{'damped' if damped else 'undamped'} ({len(grp)} videos): precision "
              f"{p:.2f}; " + "; ".join(parts) + f"; recall_all {hit_all}/{n_all} = "
              f"{hit_all / n_all if n_all else float('nan'):.2f}")


if __name__ == "__main__":
    main()
