"""Bootstrap intervals and paired comparisons (vvtbench.scoring.stats)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from vvtbench.scoring.stats import (
    bootstrap_ci,
    paired_comparison,
    paired_table,
    summarize,
    tie_groups,
    track_statistics,
)


def test_bootstrap_interval_covers_the_mean_about_95_percent_of_the_time():
    rng = np.random.default_rng(5)
    hits = 0
    for _ in range(200):
        x = rng.normal(0.3, 0.1, 30)
        lo, hi = bootstrap_ci(x, n_boot=400, seed=int(rng.integers(1 << 30)))
        hits += lo <= 0.3 <= hi
    assert 0.88 <= hits / 200 <= 0.99  # percentile bootstrap is slightly narrow at n = 30


def test_no_interval_from_fewer_than_two_values_and_reproducible():
    assert np.isnan(bootstrap_ci([0.5])).all() and np.isnan(bootstrap_ci([])).all()
    assert bootstrap_ci([1.0, 2, 3, 4], seed=3) == bootstrap_ci([1.0, 2, 3, 4], seed=3)
    s = summarize([1.0, np.nan, 3.0])
    assert s["n"] == 2 and s["mean"] == 2.0 and s["median"] == 2.0


def test_paired_comparison_uses_only_shared_instances():
    a = np.array([0.5, 0.6, 0.7, np.nan, 0.9])
    b = np.array([0.4, 0.6, 0.5, 0.1, np.nan])
    c = paired_comparison(a, b)
    assert c["n"] == 3 and np.isclose(c["mean_diff"], (0.1 + 0 + 0.2) / 3)
    assert np.isclose(c["win_rate"], (1 + 0.5 + 1) / 3) and c["ties"] == 1
    assert c["ci_low"] <= c["mean_diff"] <= c["ci_high"]


def test_a_win_rate_of_ties_alone_is_shown_as_ties_not_as_a_rate():
    from vvtbench.scoring.stats import win_rate_text

    same = paired_comparison([0.0] * 4, [0.0] * 4)
    assert same["win_rate"] == 0.5 and same["ties"] == 4
    assert win_rate_text(same["win_rate"], same["ties"], same["n"]) == "all tied"
    c = paired_comparison([0.5, 0.6, 0.7], [0.4, 0.6, 0.5])
    assert win_rate_text(c["win_rate"], c["ties"], c["n"]) == "0.83 (1 tied)"


def _table():
    rows = []
    for inst in range(6):
        for solver, base in (("a", 0.5), ("b", 0.3), ("oracle", 0.9)):
            for nm in (8, 20):
                rows.append({"track": "t", "observation": "true", "variation": f"n_modes={nm}",
                             "solver": solver, "scene": f"s{inst}", "seed": 0,
                             "reference": solver == "oracle", "status": "ok",
                             "nc_w": base + 0.01 * inst + (0.1 if nm == 20 else 0),
                             "runtime_s": 1.0 + inst})
    rows[0]["status"], rows[0]["nc_w"] = "invalid", np.nan
    return pd.DataFrame(rows)


def test_track_statistics_one_row_per_sweep_value_and_counts():
    st = track_statistics(_table(), metrics=["nc_w"])
    assert len(st) == 3 * 2  # solvers x n_modes values: never averaged over n_modes
    a8 = st[(st.solver == "a") & (st.variation == "n_modes=8")].iloc[0]
    assert a8.n == 5 and a8.nc_w_n == 5 and a8.invalid == 1 and a8.failed == 0
    assert a8.runs == 6
    assert a8.nc_w_mean_ci_low <= a8.nc_w_mean <= a8.nc_w_mean_ci_high
    assert a8.nc_w_median_ci_low <= a8.nc_w_median <= a8.nc_w_median_ci_high
    assert (a8.runtime_q25_s, a8.runtime_median_s, a8.runtime_q75_s) == (3.0, 4.0, 5.0)
    assert (a8.runtime_min_s, a8.runtime_max_s) == (2.0, 6.0)
    assert bool(st[st.solver == "oracle"].reference.all())


def test_paired_table_excludes_references():
    pt = paired_table(_table())
    assert set(zip(pt.a, pt.b, strict=True)) == {("a", "b")}
    assert (pt.mean_diff > 0.15).all() and (pt.win_rate == 1.0).all()


def test_summarize_gives_the_median_its_interval_and_counts_finite_values():
    s = summarize([0.1, 0.2, np.nan, 0.3, 0.4, 0.5])
    assert s["n"] == 5 and np.isclose(s["mean"], 0.3) and s["median"] == 0.3
    assert s["median_ci_low"] <= s["median"] <= s["median_ci_high"]
    assert (s["mean_ci_low"], s["mean_ci_high"]) == bootstrap_ci([0.1, 0.2, 0.3, 0.4, 0.5])
    empty = summarize([np.nan])
    assert empty["n"] == 0 and np.isnan([v for k, v in empty.items() if k != "n"]).all()


def test_paired_table_pairs_shared_instances_higher_mean_first_and_failed_cells():
    t = _table()
    t.loc[(t.solver == "b") & (t.scene == "s3"), ["status", "nc_w"]] = ["error", np.nan]
    t.loc[(t.solver == "a") & (t.scene == "s4") & (t.variation == "n_modes=20"), "nc_w"] = \
        np.nan  # undefined on that instance
    pt = paired_table(t)
    assert list(pt.variation) == ["n_modes=8", "n_modes=20"]  # the table's order
    assert list(pt.n) == [4, 4]  # s0 invalid for a at 8 (and s3 failed for b); s3, s4 at 20
    assert (pt.a == "a").all()  # the higher mean first: a - b > 0
    st = track_statistics(t, metrics=["nc_w"])
    b = st[st.solver == "b"].iloc[0]
    assert (b.n, b.failed, b.nc_w_n) == (5, 1, 5)
    none = track_statistics(t.assign(status="error", nc_w=np.nan), metrics=["nc_w"])
    assert (none.n == 0).all() and none.nc_w_mean.isna().all() and (none.nc_w_n == 0).all()


def _wide(**columns):
    return pd.DataFrame({k: np.asarray(v, dtype=float) for k, v in columns.items()})


def test_tie_groups_clear_winner_tie_and_chain():
    """Constructed per-instance scores: the paired differences are known exactly."""
    swing = np.tile([0.2, -0.2], 10)  # 20 instances, mean 0, sd 0.2: CI of a mean ~ +-0.09
    base = np.linspace(0.3, 0.5, 20)
    clear = tie_groups(_wide(a=base + 0.3 + swing, b=base))
    assert [(s, r) for s, r, _ in clear] == [("a", 1), ("b", 2)]
    assert clear[1][2]["ci_low"] > 0  # the difference a - b excludes 0
    tie = tie_groups(_wide(a=base + 0.05 + swing, b=base))
    assert [(s, r) for s, r, _ in tie] == [("a", 1), ("b", 1)]
    assert tie[1][2]["ci_low"] < 0 < tie[1][2]["ci_high"]
    # a = b and b = c, yet a - c = 0.10 on every instance: one group by the chain rule
    chain = tie_groups(_wide(c=base, b=base + 0.05 - swing, a=base + 0.10, d=base - 0.5))
    assert [(s, r) for s, r, _ in chain] == [("a", 1), ("b", 1), ("c", 1), ("d", 4)]
    direct = paired_comparison(base + 0.10, base)
    assert direct["ci_low"] > 0  # a and c differ, but not adjacently
    # fewer than MIN_RANK_N pairs never separate (no ranking from 3 instances)
    few = tie_groups(_wide(a=[0.9, 0.9, 0.9], b=[0.1, 0.1, 0.1]))
    assert [r for _, r, _ in few] == [1, 1]
    # only shared instances are paired: b's missing instances are left out
    holes = _wide(a=base + 0.3 + swing, b=np.where(np.arange(20) < 17, np.nan, base))
    assert [r for _, r, _ in tie_groups(holes)] == [1, 1] and tie_groups(holes)[1][2]["n"] == 3
