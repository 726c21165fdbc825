"""Does the `quick` suite give the `standard` suite's rows and rank the solvers the same way?

    .venv/bin/python benchmarks/compare_quick.py QUICK_RESULTS STANDARD_RESULTS

Every task of `quick` is a task of `standard` with the same cache key
(``tests/test_suite.py``), so two things can be checked from the two results tables:

1. **The same rows.** Each `quick` row is matched to the `standard` row of the same track,
   solver, instance, variation, observation, number of modes and configuration hash; every
   score column must agree (exactly, NaN with NaN). Prints how many agree, differ or have no
   partner (a partial `standard` table, such as a few shards, leaves some without one).
2. **The same ranking.** Per track, observation source and variation that `quick` keeps, the
   leaderboard's ranking (:func:`vvtbench.reporting.leaderboard.ranking`: mean NC w, ties by
   the paired interval) of each table. ``same`` when the ranks are equal; ``consistent`` when
   no pair of solvers ranked apart by `standard` is ranked the other way round by `quick` (a
   tie in `quick`, over fewer instances, is consistent with an order in `standard`); otherwise
   ``reversed`` with the pairs. Reference solvers are never ranked and are left out.

Exit status 1 when a row differs or a ranking is reversed.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from vvtbench.bench import read_results
from vvtbench.reporting.leaderboard import ranking

KEY = ["track", "solver", "scene", "variation", "observation", "n_modes", "config_hash"]
SCORES = ["nc_w", "nc_v", "nc_w_uncentered", "nc_v_uncentered", "sigma_star_w",
          "sigma_star_v", "mode_mac", "freq_err_raw", "freq_err_scaled", "extraction_precision",
          "extraction_recall", "extraction_recall_all", "extraction_mean_rel_freq_error",
          "extraction_mean_mac", "extraction_median_rel_damping_error", "status"]


def same_rows(quick, standard) -> tuple[int, list[str], int]:
    """(rows agreeing, one line per differing row, rows without a partner)."""
    cols = [c for c in SCORES if c in quick.columns and c in standard.columns]
    m = quick[KEY + cols].merge(standard[KEY + cols], on=KEY, how="left",
                                suffixes=("", "_std"), indicator=True)
    alone = int((m._merge == "left_only").sum())
    m = m[m._merge == "both"]
    diffs, agree = [], 0
    for _, r in m.iterrows():
        bad = []
        for c in cols:
            a, b = r[c], r[f"{c}_std"]
            if isinstance(a, float) and isinstance(b, float):
                if not (a == b or (np.isnan(a) and np.isnan(b))):
                    bad.append(f"{c} {a!r} != {b!r}")
            elif a != b:
                bad.append(f"{c} {a!r} != {b!r}")
        if bad:
            diffs.append(f"{r.track} {r.solver} {r.scene} {r.observation}: {'; '.join(bad)}")
        else:
            agree += 1
    return agree, diffs, alone


def _ranks(df) -> dict[tuple, dict[str, int]]:
    out: dict[tuple, dict[str, int]] = {}
    for track, obs, t in ranking(df):
        for _, r in t[t["rank"].notna()].iterrows():
            out.setdefault((track, obs, r.variation), {})[r.solver] = int(r["rank"])
    return out


def _order(ranks: dict[str, int]) -> str:
    groups: dict[int, list[str]] = {}
    for s, k in ranks.items():
        groups.setdefault(k, []).append(s)
    return " > ".join(" = ".join(sorted(groups[k])) for k in sorted(groups))


def compare_rankings(quick, standard) -> list[tuple[tuple, str, str, str]]:
    """Per (track, observation, variation) ranked in `quick`: (cell, quick order, standard
    order, verdict)."""
    rq, rs = _ranks(quick), _ranks(standard)
    out = []
    for cell, q in rq.items():
        s = rs.get(cell)
        if s is None:
            out.append((cell, _order(q), "not ranked", "no standard ranking"))
            continue
        common = sorted(set(q) & set(s))
        flips = [f"{a}/{b}" for i, a in enumerate(common) for b in common[i + 1:]
                 if (s[a] - s[b]) * (q[a] - q[b]) < 0]
        same = all(q[a] < q[b] if s[a] < s[b] else q[a] > q[b] if s[a] > s[b] else q[a] == q[b]
                   for i, a in enumerate(common) for b in common[i + 1:])
        verdict = ("same" if same and set(q) == set(s) else
                   "consistent" if not flips else f"reversed: {', '.join(flips)}")
        out.append((cell, _order(q), _order(s), verdict))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("quick")
    ap.add_argument("standard")
    args = ap.parse_args()
    try:
        quick, standard = read_results(args.quick), read_results(args.standard)
    except (OSError, ValueError, KeyError) as error:
        print(f"compare_quick: cannot read a results table ({args.quick}, {args.standard}): "
              f"{error}", file=sys.stderr)
        return 2
    for name, df in (("quick", quick), ("standard", standard)):
        missing = [c for c in KEY if c not in df.columns]
        if missing:
            print(f"compare_quick: the {name} table lacks the columns {', '.join(missing)} "
                  f"(a results table of `vvtbench run` has them)", file=sys.stderr)
            return 2
    agree, diffs, alone = same_rows(quick, standard)
    print(f"rows: {len(quick)} of quick; {agree} agree with standard's in every score, "
          f"{len(diffs)} differ, {alone} without a standard row")
    for d in diffs:
        print("  differs:", d)
    print("\n| track | observation | variation | quick | standard | verdict |")
    print("|---|---|---|---|---|---|")
    bad = bool(diffs)
    for (track, obs, var), q, s, verdict in compare_rankings(quick, standard):
        print(f"| {track} | {obs} | {var} | {q} | {s} | {verdict} |")
        bad |= verdict.startswith("reversed")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
