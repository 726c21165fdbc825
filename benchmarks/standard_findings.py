"""What the `standard` suite shows, printed from a run's results table.

    .venv/bin/python benchmarks/standard_findings.py [runs/standard/results.parquet]

Prints, per track (instances of the families' test split):

1. NC of w and v per solver: mean [95 % bootstrap CI] over the instances, the median, and how
   many instances each is over (instances without a defect have no NC: counted apart);
2. paired comparisons on the same instances: sensitivity - vvt, learned - homogeneous, and the
   best ranked solver against the oracle (mean difference [CI], win rate);
3. the instances where the reference (oracle) is below a ranked solver in NC w, with both values;
4. extraction on the video tracks: precision, recall over the detectable modes, recall over
   all modes in band (mean [CI] over the instances); with several extractors, their ranking
   (the leaderboard's) and each solver's paired NC w between them on the same videos;
5. calibration: the 95 % interval coverage of the solvers that state standard deviations;
6. runtimes: median and maximum per solver, and the run's wall time from run.json.

Every interval is :func:`vvtbench.stats.summarize` / :func:`vvtbench.stats.paired_comparison`
(percentile bootstrap over instances, 2000 resamples, seed 0), the leaderboard's statistics.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from vvtbench.bench import read_results
from vvtbench.stats import paired_comparison, summarize


def _ci(values) -> str:
    s = summarize(values)
    if s["n"] == 0:
        return "–"
    if not np.isfinite(s["mean_ci_low"]):
        return f"{s['mean']:.3f} (n={s['n']})"
    return (f"{s['mean']:.3f} [{s['mean_ci_low']:.3f}, {s['mean_ci_high']:.3f}], median "
            f"{s['median']:.3f} (n={s['n']})")


def _pivot(d, metric: str):
    return d.pivot_table(index="scene", columns="solver", values=metric, aggfunc="first")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("results", nargs="?", default="runs/standard/results.parquet")
    args = ap.parse_args()
    df = read_results(args.results)
    run_json = Path(args.results).parent / "run.json"
    run = json.loads(run_json.read_text()) if run_json.is_file() else {}
    order = [t for t in run.get("tracks", []) if t in set(df.track)] or list(
        dict.fromkeys(df.track))
    ref = set(df[df.get("reference", False).astype(bool)].solver) if "reference" in df else set()
    print(f"{args.results}: {len(df)} rows, {df.scene.nunique()} instances, status "
          f"{df.status.value_counts().to_dict()}")
    if run:
        print(f"run: {run.get('wall_s', float('nan')) / 60:.1f} min wall, workers "
              f"{run.get('workers')}, vvtbench {run.get('vvtbench')}")
    for track in order:
        d = df[df.track == track]
        for obs in dict.fromkeys(d.observation):
            dt = d[d.observation == obs]
            ok = dt[dt.status == "ok"]
            n_inst = dt.scene.nunique()
            flat = ok.groupby("scene").nc_w.apply(lambda s: s.isna().all()).sum()
            print(f"\n== {track} ({obs} modes): {n_inst} instances, {flat} without contrast "
                  f"(no defect: NC undefined)")
            for solver in sorted(set(dt.solver)):
                s = ok[ok.solver == solver]
                bad = dt[(dt.solver == solver) & (dt.status != "ok")]
                tag = " (reference)" if solver in ref else ""
                print(f"  {solver + tag:24s} NC w {_ci(s.nc_w.astype(float))}")
                print(f"  {'':24s} NC v {_ci(s.nc_v.astype(float))}"
                      + (f"; {len(bad)} failed/invalid" if len(bad) else ""))
            w = _pivot(ok, "nc_w")
            pairs = [("sensitivity", "vvt"), ("learned", "homogeneous"), ("vvt", "homogeneous")]
            ranked = [c for c in w.columns if c not in ref]
            if ranked:
                best = max(ranked, key=lambda c: np.nanmean(w[c]) if w[c].notna().any()
                           else -np.inf)
                pairs += [(r, best) for r in ref]
            for a, b in pairs:
                if a in w and b in w:
                    p = paired_comparison(w[a], w[b])
                    ci = (f" [{p['ci_low']:+.3f}, {p['ci_high']:+.3f}]"
                          if np.isfinite(p["ci_low"]) else " (no interval)")
                    print(f"  paired NC w {a} - {b}: {p['mean_diff']:+.3f}{ci}, {a} higher on "
                          f"{p['win_rate']:.0%} of {p['n']} instances")
            for r in ref:
                if r not in w:
                    continue
                others = w[[c for c in ranked]].max(axis=1)
                who = w[[c for c in ranked]].idxmax(axis=1, skipna=True) if ranked else None
                below = w.index[(w[r] < others).fillna(False)]
                for scene in below:
                    print(f"  {r} below {who[scene]} on {scene}: NC w {w.loc[scene, r]:.3f} vs "
                          f"{others[scene]:.3f}")
            if obs.startswith("extracted") and "extraction_recall" in ok:
                cols = [c for c in ("extraction_precision", "extraction_recall",
                                    "extraction_recall_all") if c in ok]
                e = ok.groupby("scene")[cols].first()
                for c in e.columns:
                    print(f"  {c.replace('extraction_', 'extraction ')}: "
                          f"{_ci(e[c].astype(float))}")
            for c in ("interval_coverage_w", "interval_coverage_v"):
                if c in ok and ok[c].notna().any():
                    for solver, s in ok[ok[c].notna()].groupby("solver"):
                        print(f"  {solver} 95 % {c.replace('interval_coverage_', 'coverage ')}:"
                              f" {_ci(s[c].astype(float))}")
            rt = ok.groupby("solver").runtime_s.agg(["median", "max"])
            print("  runtime s (median / max): " + ", ".join(
                f"{k} {r['median']:.1f} / {r['max']:.1f}" for k, r in rt.iterrows()))
        _extractors(d)


def _extractors(d) -> None:
    """Tracks with several extracted sources: the extractor ranking (the leaderboard's) and,
    per solver, the paired NC w of each source against the default one on the same videos."""
    from vvtbench.leaderboard import extractor_ranking

    ranked = extractor_ranking(d, d.track.iloc[0])
    if ranked is None:
        return
    print(f"\n== {d.track.iloc[0]}: extractors ranked on the same videos")
    for row in ranked.to_dict("records"):
        print("  " + "; ".join(f"{k} {v}" for k, v in row.items()))
    ok = d[d.status == "ok"]
    for solver in sorted(set(ok.solver)):
        s = ok[ok.solver == solver].pivot_table(index="scene", columns="observation",
                                                 values="nc_w", aggfunc="first")
        for other in [c for c in s.columns if c != "extracted"]:
            if "extracted" in s:
                p = paired_comparison(s["extracted"], s[other])
                ci = (f" [{p['ci_low']:+.3f}, {p['ci_high']:+.3f}]"
                      if np.isfinite(p["ci_low"]) else " (no interval)")
                print(f"  {solver}: paired NC w extracted - {other}: {p['mean_diff']:+.3f}{ci}"
                      f" ({p['n']} videos)")


if __name__ == "__main__":
    main()
