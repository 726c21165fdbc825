"""Statistics of results over instances: bootstrap intervals and paired comparisons.

Every resampling draws from a ``numpy.random.default_rng(seed)`` with the seed given (default
0), so a table is reproduced exactly. Intervals are percentile bootstrap intervals; with fewer
than two values there is no interval (NaN), never a zero-width one that looks certain.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

__all__ = ["bootstrap_ci", "paired_comparison", "summarize", "track_statistics",
           "paired_table"]

GROUP = ["track", "observation", "variation", "solver"]


def bootstrap_ci(values: Sequence[float], stat: Callable = np.mean, n_boot: int = 2000,
                 level: float = 0.95, seed: int = 0) -> tuple[float, float]:
    """Percentile bootstrap interval of ``stat`` over ``values`` (NaN, NaN with < 2 values).

    >>> lo, hi = bootstrap_ci([0.1, 0.2, 0.3, 0.4, 0.5])
    >>> bool(0.1 < lo < 0.3 < hi < 0.5)
    True
    """
    x = np.asarray(values, dtype=float)
    x = x[np.isfinite(x)]
    if x.size < 2:
        return float("nan"), float("nan")
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, x.size, size=(n_boot, x.size))
    boot = np.apply_along_axis(stat, 1, x[idx]) if stat not in (np.mean, np.median) else (
        x[idx].mean(axis=1) if stat is np.mean else np.median(x[idx], axis=1))
    a = (1.0 - level) / 2.0
    return float(np.quantile(boot, a)), float(np.quantile(boot, 1.0 - a))


def summarize(values: Sequence[float], seed: int = 0) -> dict[str, float]:
    """n, mean, median and the 95 % bootstrap interval of the mean of the finite values."""
    x = np.asarray(values, dtype=float)
    x = x[np.isfinite(x)]
    lo, hi = bootstrap_ci(x, seed=seed)
    return {"n": int(x.size), "mean": float(x.mean()) if x.size else float("nan"),
            "median": float(np.median(x)) if x.size else float("nan"),
            "ci_low": lo, "ci_high": hi}


def paired_comparison(a: Sequence[float], b: Sequence[float], seed: int = 0) -> dict:
    """``a - b`` on the same instances (pairs where both are finite): mean difference with
    its 95 % bootstrap interval, and the win rate of ``a`` (ties count half)."""
    x, y = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    ok = np.isfinite(x) & np.isfinite(y)
    d = x[ok] - y[ok]
    lo, hi = bootstrap_ci(d, seed=seed)
    wins = float(np.mean((d > 0) + 0.5 * (d == 0))) if d.size else float("nan")
    return {"n": int(d.size), "mean_diff": float(d.mean()) if d.size else float("nan"),
            "ci_low": lo, "ci_high": hi, "win_rate": wins}


def _instance(df):
    cols = [c for c in ("scene", "seed", "instance") if c in df.columns]
    return df[cols].astype(str).agg("/".join, axis=1)


def track_statistics(df, metric: str = "nc_w", seed: int = 0):
    """One row per track, observation source, variation (sweep value: never averaged over
    n_modes or alpha_v) and solver: mean, median and 95 % interval of ``metric`` over the
    valid (``status == "ok"``) instances, the counts of failed and invalid rows, and the
    runtime as a median with its interquartile range."""
    import pandas as pd

    rows = []
    for key, g in df.groupby(GROUP, sort=False):
        ok = g[g.status == "ok"]
        s = summarize(ok[metric], seed=seed)
        rt = ok["runtime_s"].to_numpy(dtype=float)
        rt = rt[np.isfinite(rt)]
        rows.append({**dict(zip(GROUP, key, strict=True)),
                     "reference": bool(g.get("reference", pd.Series([False])).any()),
                     **{f"{metric}_{k}": v for k, v in s.items() if k != "n"},
                     "n": s["n"], "failed": int((g.status == "error").sum()),
                     "invalid": int((g.status == "invalid").sum()),
                     "runtime_median_s": float(np.median(rt)) if rt.size else float("nan"),
                     "runtime_iqr_s": (float(np.subtract(*np.percentile(rt, [75, 25])))
                                       if rt.size else float("nan"))})
    return pd.DataFrame(rows)


def paired_table(df, metric: str = "nc_w", seed: int = 0):
    """Paired comparisons between the non-reference solvers of each track, observation and
    variation, on the instances both solved validly."""
    import pandas as pd

    rows = []
    d = df[(df.status == "ok") & ~df.get("reference", pd.Series(False, index=df.index))
           .astype(bool)].assign(_inst=lambda t: _instance(t))
    for key, g in d.groupby(GROUP[:-1], sort=False):
        wide = g.pivot_table(index="_inst", columns="solver", values=metric, aggfunc="first")
        names = list(wide.columns)
        for i, a in enumerate(names):
            for b in names[i + 1:]:
                c = paired_comparison(wide[a], wide[b], seed=seed)
                rows.append({**dict(zip(GROUP[:-1], key, strict=True)), "a": a, "b": b, **c})
    return pd.DataFrame(rows)
