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
   (the leaderboard's) and each solver's paired NC w between them on the same videos; and
   what the video costs each solver: its NC w from video minus from the same instances' true
   modes (paired over the instances the suite solves both ways);
5. calibration: the 95 % interval coverage of the solvers that state standard deviations;
6. runtimes: median and maximum per solver, and the run's wall time from run.json;
7. tracks that sweep ``views`` (several cameras): per solver and number of views, the fraction
   of DOFs observed, NC w, the paired difference against one view on the same instances, and the
   cost per instance (the views' extractions, the observation and the solve, from the run's
   cache); then NC w against the fraction of DOFs observed (the pooled within-instance slope of
   the gain in NC w over the gain in DOFs observed, bootstrap over instances);
8. the modes' damping intervals on the video tracks: per track, the share of resolved damping
   ratios whose 95 % interval covers the true one, and of every interval, against the true
   modes within 1 % in frequency (``benchmarks/bench_damping_coverage.py``, from the run's
   cached samples and mode sets; the target is >= 90 % of the resolved ones).

Every interval is :func:`vvtbench.scoring.stats.summarize` /
:func:`vvtbench.scoring.stats.paired_comparison`
(percentile bootstrap over instances, 2000 resamples, seed 0), the leaderboard's statistics.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from vvtbench.bench import read_results
from vvtbench.reporting.leaderboard import number_text
from vvtbench.scoring.stats import MIN_RANK_N, paired_comparison, summarize, win_rate_text


def _ci(values) -> str:
    s = summarize(values)
    if s["n"] == 0:
        return "–"
    if not np.isfinite(s["mean_ci_low"]):
        return f"{number_text(s['mean'])} (n={s['n']})"
    return (f"{number_text(s['mean'])} [{number_text(s['mean_ci_low'])}, "
            f"{number_text(s['mean_ci_high'])}], median {number_text(s['median'])} "
            f"(n={s['n']})")


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
        if _views_of(d).nunique() > 1:
            _views(d, Path(args.results).parent)
            continue
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
                    tied = f", {p['ties']} tied" if p["ties"] else ""
                    print(f"  paired NC w {a} - {b}: {p['mean_diff']:+.3f}{ci}, {a} higher on "
                          f"{p['wins']} of {p['n']} instances{tied}")
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
    _video_against_true(df, order)
    _damping_intervals(df, Path(args.results).parent, order)


def _video_against_true(df, order: list[str]) -> None:
    """What the video costs each solver: per track of extracted modes (one view), its NC w
    paired with the same solver's on the same instances from their true modes (any track of
    true modes holding the scene, the same number of modes, the base variation), video - true:
    mean [CI], the instances each way and the worst instance."""
    ok = df[(df.status == "ok") & (df.variation.astype(str) == "base")]
    true = ok[ok.observation == "true"]
    if true.empty:
        return
    key = ["scene", "solver", "n_modes"]
    true_nc = true.groupby(key).nc_w.first()
    for track in order:
        d = ok[(ok.track == track) & ok.observation.astype(str).str.startswith("extracted")]
        if d.empty:
            continue
        for obs in dict.fromkeys(d.observation):
            v = d[d.observation == obs].groupby(key).nc_w.first()
            both = v.to_frame("video").join(true_nc.rename("true"), how="inner").dropna()
            if both.empty:
                continue
            print(f"\n== {track} ({obs} modes) against the same instances' true modes")
            for solver, b in both.groupby(level="solver"):
                p = paired_comparison(b.video.to_numpy(), b.true.to_numpy())
                ci = (f" [{p['ci_low']:+.3f}, {p['ci_high']:+.3f}]"
                      if np.isfinite(p["ci_low"]) and p["n"] >= MIN_RANK_N else "")
                diff = (b.video - b.true).droplevel(["solver", "n_modes"])
                print(f"  {solver}: NC w video - true {p['mean_diff']:+.3f}{ci} (n={p['n']}; "
                      f"video higher on {p['wins']}, median {np.median(diff):+.3f}, worst "
                      f"{diff.min():+.3f} on {diff.idxmin()})")


def _extractors(d) -> None:
    """Tracks with several extracted sources: the extractor ranking (the leaderboard's) and,
    per solver, the paired NC w of each source against the default one on the same videos."""
    from vvtbench.reporting.leaderboard import extractor_ranking

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


def _observe_of(run_dir: Path, estimate_path) -> tuple[Path, str] | None:
    """(the run's cache, the key of the observe task) a row's estimate was scored against;
    None when the row has no cached evaluation."""
    if not isinstance(estimate_path, str) or not estimate_path:
        return None
    fields = Path(estimate_path)  # cache/evaluate/KEY/fields.npz
    cache = run_dir / fields.parents[2]
    deps = _task(cache, f"{fields.parts[-3]}/{fields.parts[-2]}").get("deps", [])
    return (cache, deps[1]) if len(deps) >= 2 else None


def _mode_sets(run_dir: Path, estimate_path) -> list[tuple[Path, Path]]:
    """(sample folder, mode set folder) of every view's extraction a row was observed from."""
    found = _observe_of(run_dir, estimate_path)
    if found is None:
        return []
    cache, observe_key = found
    pairs = []
    for key in _task(cache, observe_key).get("deps", [])[1:]:
        extract = _task(cache, key)
        if extract.get("stage") == "extract" and extract.get("deps"):
            pairs.append((cache / extract["deps"][0] / "sample", cache / key))
    return pairs


def _damping_intervals(df, run_dir: Path, order: list[str]) -> None:
    """Coverage of the damping intervals of every mode set the video tracks observed."""
    import sys

    sys.path.insert(0, str(Path(__file__).parent))
    from bench_damping_coverage import sample_coverage
    from bench_damping_coverage import summarize as coverage

    for track in order:
        d = df[(df.track == track) & df.observation.str.startswith("extracted")]
        sets = dict.fromkeys(pair for path in d.estimate_path
                             for pair in _mode_sets(run_dir, path))
        rows = [r for sample, modes in sets
                if (sample / "truth.json").is_file() and (modes / "modes.json").is_file()
                for r in sample_coverage(sample, modes, 0.01)]
        if rows:
            print(f"\n== {track}: damping intervals of {len(sets)} mode sets "
                  "(coverage k/n = % [exact 95 % binomial interval])")
            for line in coverage(rows):
                print("  " + line)


def _views_of(d):
    """The number of cameras of each row (1 when its variation does not say)."""
    return d.variation_options.map(lambda o: int(json.loads(o or "{}").get("views", 1)))


def _task(cache: Path, key: str) -> dict:
    path = cache / key / "task.json"
    return json.loads(path.read_text()) if path.is_file() else {}


def _observed(run_dir: Path, estimate_path) -> tuple[float, float, float]:
    """(fraction of DOFs observed, seconds of the views' extractions and the observation,
    seconds of the shared generation) of a row, from its cached tasks; NaN when not cached."""
    nan = (float("nan"),) * 3
    found = _observe_of(run_dir, estimate_path)
    if found is None:
        return nan
    cache, observe_key = found
    observe = _task(cache, observe_key)
    problem = cache / observe_key / "problem.json"
    if not observe or not problem.is_file():
        return nan
    dof = json.loads(problem.read_text())["meta"].get("observed_dof_fraction", float("nan"))
    gen, *extracts = observe["deps"]
    seconds = observe.get("seconds", float("nan")) + sum(
        _task(cache, k).get("seconds", float("nan")) for k in extracts)
    return float(dof), float(seconds), float(_task(cache, gen).get("seconds", float("nan")))


def _views(d, run_dir: Path) -> None:
    """NC w against the number of views and the fraction of DOFs observed, paired against one
    view on the same instances, with the cost per instance."""
    d = d.assign(views=_views_of(d))
    cached = [_observed(run_dir, p) for p in d.estimate_path]
    dof = [c[0] for c in cached]
    if "observed_dof_fraction" in d:  # the results column, where the table has it
        stated = d.observed_dof_fraction.to_numpy(float)
        dof = np.where(np.isfinite(stated), stated, dof)
    d = d.assign(dof=dof, prep_s=[c[1] for c in cached], generate_s=[c[2] for c in cached])
    track = d.track.iloc[0]
    for obs in dict.fromkeys(d.observation):
        dt = d[d.observation == obs]
        ok = dt[dt.status == "ok"]
        gen = dt.groupby("scene").generate_s.first()
        print(f"\n== {track} ({obs} modes): {dt.scene.nunique()} instances, views "
              f"{sorted(set(dt.views))}; generating an instance (every view): median "
              f"{gen.median():.0f} s")
        print("  solver | views | DOFs observed | NC w mean [95 % CI] | paired vs 1 view "
              "[95 % CI] | win rate | valid | s per instance (extract + observe + solve)")
        for solver in sorted(set(dt.solver)):
            w = ok[ok.solver == solver].pivot_table(index="scene", columns="views",
                                                    values="nc_w", aggfunc="first")
            for n in sorted(set(dt.views)):
                rows = dt[(dt.solver == solver) & (dt.views == n)]
                good = rows[rows.status == "ok"]
                s = summarize(good.nc_w.astype(float))
                paired = "--"
                if n != 1 and 1 in w and n in w:
                    p = paired_comparison(w[n], w[1])
                    win = win_rate_text(p["win_rate"], p["ties"], p["n"])
                    paired = (f"{p['mean_diff']:+.3f} [{p['ci_low']:+.3f}, {p['ci_high']:+.3f}] "
                              f"| {win}") if np.isfinite(p["ci_low"]) else (
                        f"{p['mean_diff']:+.3f} (n={p['n']}) | {win}")
                cost = (good.prep_s + good.runtime_s).median()
                print(f"  {solver} | {n} | {rows.dof.mean():.3f} | {s['mean']:.3f} "
                      f"[{s['mean_ci_low']:.3f}, {s['mean_ci_high']:.3f}] | {paired}"
                      f"{' | --' if paired == '--' else ''} | {len(good)}/{len(rows)} | "
                      f"{cost:.0f}")
        for solver in sorted(set(ok.solver)):
            _dof_slope(ok[ok.solver == solver], solver)


def _dof_slope(ok, solver: str) -> None:
    """The within-instance slope of NC w on the fraction of DOFs observed (gain over one view
    against the gain in DOFs observed, pooled), with a bootstrap interval over instances."""
    from vvtbench.scoring.stats import bootstrap_ci

    one = ok[ok.views == 1].set_index("scene")
    more = ok[(ok.views > 1) & ok.scene.isin(one.index)]
    gain = more.nc_w.to_numpy(float) - one.nc_w.reindex(more.scene).to_numpy(float)
    reach = more.dof.to_numpy(float) - one.dof.reindex(more.scene).to_numpy(float)
    keep = np.isfinite(gain) & np.isfinite(reach)
    scenes = more.scene.to_numpy()[keep]
    gain, reach = gain[keep], reach[keep]
    names = sorted(set(scenes))
    if not names or not np.any(reach):
        return
    index = np.searchsorted(names, scenes)

    def slope(picked) -> float:
        rows = np.concatenate([np.flatnonzero(index == int(i)) for i in picked])
        den = float(reach[rows] @ reach[rows])
        return float(gain[rows] @ reach[rows]) / den if den > 0 else float("nan")

    lo, hi = bootstrap_ci(np.arange(len(names), dtype=float), stat=slope)
    print(f"  {solver}: NC w against DOFs observed: {0.1 * slope(range(len(names))):+.3f} NC w "
          f"per +0.1 of the DOFs observed [{0.1 * lo:+.3f}, {0.1 * hi:+.3f}] "
          f"({len(names)} instances, {len(gain)} pairs with 2+ views)")


if __name__ == "__main__":
    main()
