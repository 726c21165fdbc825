"""How close each extraction of a run comes to the Cramér-Rao bound of frequency and damping.

    python benchmarks/bench_parameter_efficiency.py RUN_DIR [--json OUT]

Reads every extraction in ``RUN_DIR/cache/extract`` (a ``vvtbench run`` folder: its cached
samples and extracted modes), scores it against its sample's (or view's) true modes with
:func:`vvtbench.scoring.extraction.score_sample_extraction` and prints, per video and
identifier, precision, recall over detectable modes, and the frequency and damping
efficiency (docs/metrics.md, "Efficiency of an extraction") with the number of modes each
averages, plus the median normalised error ``|x_hat - x| / CRB_x`` (a figure less driven by
the worst mode than the efficiency, which is 1 / mean of its square).
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np


def _median_z(matching: list[dict], key: str, crb: str, truth: str) -> float:
    """Median of ``|x_hat - x| / CRB_x`` over the matches the efficiency used."""
    z = [abs(m[key] - m[truth]) / m[crb] for m in matching
         if crb in m and math.isfinite(m.get(key, math.nan))
         and (key == "frequency_hz" or m[truth] > 0)]
    return float(np.median(z)) if z else math.nan


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    from vvtbench.modes import ModeSet
    from vvtbench.samples.reader import open_sample
    from vvtbench.scoring.extraction import score_sample_extraction

    cache = args.run / "cache"
    rows = []
    for task in sorted(cache.glob("extract/*/task.json")):
        t = json.loads(task.read_text())
        gen = cache / t["deps"][0]
        scene = json.loads((gen / "task.json").read_text())["payload"]["scene"]["name"]
        opts = t["payload"].get("options", {})
        view = int(t["payload"].get("view") or 0)
        sample = open_sample(gen / "sample", verify=False)
        r = score_sample_extraction(sample.view(view), ModeSet.load(task.parent),
                                    opts.get("fmax"))
        rows.append({
            "scene": scene, "view": view, "identifier": opts.get("identifier", "peaks"),
            "extractor": opts.get("extractor", "phase"),
            "precision": r["precision"], "recall": r["recall"],
            "frequency_efficiency": r["frequency_efficiency"],
            "n_frequency": r["n_frequency_efficiency"],
            "frequency_median_z": _median_z(r["matching"], "frequency_hz", "frequency_crb_hz",
                                            "true_frequency_hz"),
            "damping_efficiency": r["damping_efficiency"],
            "n_damping": r["n_damping_efficiency"],
            "damping_median_z": _median_z(r["matching"], "damping", "damping_crb",
                                          "true_damping"),
            "note": r["efficiency_note"]})
    rows.sort(key=lambda r: (r["scene"], r["view"], r["extractor"], r["identifier"]))
    print("| video | view | extractor | identifier | precision | recall | frequency efficiency "
          "(n) | median abs(f err)/CRB | damping efficiency (n) | median abs(zeta err)/CRB |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        def g(x):
            return "–" if not math.isfinite(x) else f"{x:.3g}"
        print(f"| {r['scene']} | {r['view']} | {r['extractor']} | {r['identifier']} | "
              f"{g(r['precision'])} | {g(r['recall'])} | {g(r['frequency_efficiency'])} "
              f"({r['n_frequency']}) | {g(r['frequency_median_z'])} | "
              f"{g(r['damping_efficiency'])} ({r['n_damping']}) | {g(r['damping_median_z'])} |"
              + (f" {r['note']}" if r["note"] else ""))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1, allow_nan=True))


if __name__ == "__main__":
    main()
