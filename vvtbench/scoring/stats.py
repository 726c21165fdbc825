"""Statistics of results over instances: bootstrap intervals and paired comparisons.

An *instance* is one scene and seed (:func:`instance_ids`); a statistic of a solver is taken
over the instances of one track, observation source and variation (a sweep value is never
averaged with another). Every resampling draws from a ``numpy.random.default_rng(seed)`` with
the seed given (default :data:`SEED`), so a table is reproduced exactly. Intervals are
percentile bootstrap intervals (:data:`N_BOOT` resamples, level :data:`LEVEL`); with fewer than
two values there is no interval (NaN), never a zero-width one that looks certain. Values that
are not finite (a metric undefined on an instance, e.g. NC on a constant truth) are left out
and every statistic carries the number ``n`` of values it is over.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

__all__ = ["GROUP", "LEVEL", "MIN_RANK_N", "N_BOOT", "SEED", "bootstrap_ci", "instance_ids",
           "paired_comparison", "paired_table", "summarize", "TIE_RULE", "tie_groups",
           "track_statistics", "win_rate_text"]

#: the cell of a statistic: one track, observation source, variation (sweep value) and solver
GROUP = ["track", "observation", "variation", "solver"]
#: bootstrap resamples, interval level and seed used unless told otherwise
N_BOOT, LEVEL, SEED = 2000, 0.95, 0
#: below this many instances a solver is neither ranked nor given an interval (the percentile
#: bootstrap under-covers badly on a handful of values): its mean and n only
MIN_RANK_N = 5
#: the columns naming an instance (those present in a table are used)
INSTANCE = ("scene", "seed", "instance")


def _finite(values: Sequence[float]) -> np.ndarray:
    x = np.asarray(values, dtype=float)
    return x[np.isfinite(x)]


def bootstrap_ci(values: Sequence[float], stat: Callable = np.mean, n_boot: int = N_BOOT,
                 level: float = LEVEL, seed: int = SEED) -> tuple[float, float]:
    """Percentile bootstrap interval of ``stat`` over the finite ``values``.

    Parameters
    ----------
    values : sequence of float
        The values, one per instance; non-finite ones are left out.
    stat : callable
        The statistic (``np.mean``, ``np.median`` or any function of a 1-D array).
    n_boot, level, seed : int, float, int
        Resamples, interval level and the seed of ``numpy.random.default_rng``.

    Returns
    -------
    (low, high) : tuple of float
        NaN, NaN with fewer than two finite values.

    >>> lo, hi = bootstrap_ci([0.1, 0.2, 0.3, 0.4, 0.5])
    >>> bool(0.1 < lo < 0.3 < hi < 0.5)
    True
    """
    x = _finite(values)
    if x.size < 2:
        return float("nan"), float("nan")
    rng = np.random.default_rng(seed)
    resampled = x[rng.integers(0, x.size, size=(n_boot, x.size))]
    if stat is np.mean:
        boot = resampled.mean(axis=1)
    elif stat is np.median:
        boot = np.median(resampled, axis=1)
    else:
        boot = np.apply_along_axis(stat, 1, resampled)
    a = (1.0 - level) / 2.0
    return float(np.quantile(boot, a)), float(np.quantile(boot, 1.0 - a))


def summarize(values: Sequence[float], seed: int = SEED, n_boot: int = N_BOOT,
              level: float = LEVEL) -> dict[str, float]:
    """The finite values' count, mean and median, each with its bootstrap interval.

    Returns
    -------
    dict
        ``n``, ``mean``, ``mean_ci_low``, ``mean_ci_high``, ``median``, ``median_ci_low``,
        ``median_ci_high`` (NaN where undefined: no value, or no interval from one value).
    """
    x = _finite(values)
    out: dict[str, float] = {"n": int(x.size)}
    for name, stat in (("mean", np.mean), ("median", np.median)):
        lo, hi = bootstrap_ci(x, stat, n_boot=n_boot, level=level, seed=seed)
        out |= {name: float(stat(x)) if x.size else float("nan"),
                f"{name}_ci_low": lo, f"{name}_ci_high": hi}
    return out


def paired_comparison(a: Sequence[float], b: Sequence[float], seed: int = SEED,
                      n_boot: int = N_BOOT, level: float = LEVEL) -> dict:
    """``a - b`` on the same instances (the pairs where both are finite).

    Returns
    -------
    dict
        ``n`` (pairs), ``mean_diff`` with its bootstrap interval ``ci_low``, ``ci_high``,
        ``win_rate``: the share of pairs where ``a`` is higher (ties count half), ``wins``: the
        pairs where ``a`` is higher, and ``ties``: the pairs where ``a`` equals ``b`` (shown
        with the rate: :func:`win_rate_text`).
    """
    x, y = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    ok = np.isfinite(x) & np.isfinite(y)
    d = x[ok] - y[ok]
    lo, hi = bootstrap_ci(d, n_boot=n_boot, level=level, seed=seed)
    rate = float(np.mean((d > 0) + 0.5 * (d == 0))) if d.size else float("nan")
    return {"n": int(d.size), "mean_diff": float(d.mean()) if d.size else float("nan"),
            "ci_low": lo, "ci_high": hi, "win_rate": rate, "wins": int(np.sum(d > 0)),
            "ties": int(np.sum(d == 0))}


def win_rate_text(win_rate: float, ties: int, n: int) -> str:
    """A win rate as shown beside its ties: a rate of ties alone would read as a result.

    >>> win_rate_text(0.5, 4, 4), win_rate_text(0.75, 1, 4), win_rate_text(1.0, 0, 3)
    ('all tied', '0.75 (1 tied)', '1.00')
    """
    if not n or not np.isfinite(win_rate):
        return "–"
    if ties == n:
        return "all tied"
    return f"{win_rate:.2f}" + (f" ({ties} tied)" if ties else "")


def instance_ids(df):
    """The instance of every row: its scene and seed (and ``instance`` where a table has one),
    joined with ``/`` (a pandas Series of str)."""
    cols = [c for c in INSTANCE if c in df.columns]
    ids = df[cols[0]].astype(str)
    for c in cols[1:]:
        ids = ids + "/" + df[c].astype(str)
    return ids


def _reference(df):
    import pandas as pd

    if "reference" not in df.columns:
        return pd.Series(False, index=df.index)
    return df["reference"].fillna(False).astype(bool)


def track_statistics(df, metrics: Sequence[str] = ("nc_w", "nc_v"),
                     means: Sequence[str] = (), seed: int = SEED, n_boot: int = N_BOOT):
    """One row per track, observation source, variation and solver (:data:`GROUP`, in the
    order of first appearance): statistics over its valid (``status == "ok"``) rows.

    Parameters
    ----------
    df : pandas.DataFrame
        A results table (docs/results.md).
    metrics : sequence of str
        Columns summarised with :func:`summarize`: ``{m}_n``, ``{m}_mean``, ``{m}_mean_ci_low``,
        ... (the finite values only; ``{m}_n`` counts them).
    means : sequence of str
        Columns given as the mean of their finite values only: ``{m}_mean`` and ``{m}_n``.
    seed, n_boot : int
        The bootstrap's seed and resamples.

    Returns
    -------
    pandas.DataFrame
        The :data:`GROUP` columns, ``reference``, ``runs`` (rows), ``n`` (valid rows),
        ``failed`` (``status == "error"``), ``invalid``, the metric columns, and the runtime of
        the valid rows: ``runtime_median_s``, ``runtime_q25_s``, ``runtime_q75_s``,
        ``runtime_min_s``, ``runtime_max_s``.
    """
    import pandas as pd

    d = df.assign(reference=_reference(df))
    keys = d.groupby(GROUP, sort=False)
    out = pd.DataFrame({
        "reference": keys["reference"].any(), "runs": keys.size(),
        "n": keys["status"].agg(lambda s: int((s == "ok").sum())),
        "failed": keys["status"].agg(lambda s: int((s == "error").sum())),
        "invalid": keys["status"].agg(lambda s: int((s == "invalid").sum()))})
    ok = d[d.status == "ok"]
    if len(ok):
        g = ok.groupby(GROUP, sort=False)
        parts = [g[m].apply(lambda s: pd.Series(summarize(s, seed=seed, n_boot=n_boot)))
                 .unstack().add_prefix(f"{m}_") for m in metrics]
        finite = ok[list(means)].where(np.isfinite(ok[list(means)].astype(float)))
        fg = finite.groupby([ok[c] for c in GROUP], sort=False)
        parts += [fg.mean().add_suffix("_mean"), fg.count().add_suffix("_n")]
        rt = ok["runtime_s"].where(np.isfinite(ok["runtime_s"].astype(float)))
        rg = rt.groupby([ok[c] for c in GROUP], sort=False)
        parts.append(pd.DataFrame({
            "runtime_median_s": rg.median(), "runtime_q25_s": rg.quantile(0.25),
            "runtime_q75_s": rg.quantile(0.75), "runtime_min_s": rg.min(),
            "runtime_max_s": rg.max()}))
        out = out.join(pd.concat(parts, axis=1))
    for m in metrics:  # cells without a valid row: n = 0 and NaN statistics
        for k in ("n", "mean", "mean_ci_low", "mean_ci_high", "median", "median_ci_low",
                  "median_ci_high"):
            if f"{m}_{k}" not in out:
                out[f"{m}_{k}"] = np.nan
    for m in means:
        for k in ("mean", "n"):
            if f"{m}_{k}" not in out:
                out[f"{m}_{k}"] = np.nan
    for c in ("runtime_median_s", "runtime_q25_s", "runtime_q75_s", "runtime_min_s",
              "runtime_max_s"):
        if c not in out:
            out[c] = np.nan
    counts = [f"{m}_n" for m in (*metrics, *means)]
    out[counts] = out[counts].fillna(0).astype(int)
    return out.reset_index()


def paired_table(df, metric: str = "nc_w", seed: int = SEED, n_boot: int = N_BOOT):
    """Paired comparisons between the non-reference solvers of each track, observation source
    and variation, on the instances both solved validly (``status == "ok"`` and a finite
    ``metric``; :func:`paired_comparison`).

    Within a group the solvers are ordered by their mean ``metric`` over those valid rows
    (highest first, ties by name), and each pair is given once as ``a`` (the higher) minus
    ``b``, so a positive ``mean_diff`` reads "a is better by".

    Returns
    -------
    pandas.DataFrame
        The group columns, ``a``, ``b``, ``metric`` and the :func:`paired_comparison` fields.
    """
    import pandas as pd

    cols = [*GROUP[:-1], "a", "b", "metric", "n", "mean_diff", "ci_low", "ci_high",
            "win_rate", "ties"]
    d = df.assign(_inst=instance_ids(df))[(df.status == "ok") & ~_reference(df)]
    groups = dict(iter(d.groupby(GROUP[:-1], sort=False)))
    rows = []
    for key in dict.fromkeys(zip(*(df[c] for c in GROUP[:-1]), strict=True)):  # table order
        if key not in groups:
            continue
        g = groups[key]
        wide = g.pivot_table(index="_inst", columns="solver", values=metric, aggfunc="first",
                             dropna=False)
        mean = wide.mean()
        names = sorted(wide.columns, key=lambda s: (-mean[s] if np.isfinite(mean[s])
                                                    else np.inf, str(s)))
        for i, a in enumerate(names):
            for b in names[i + 1:]:
                c = paired_comparison(wide[a], wide[b], seed=seed, n_boot=n_boot)
                rows.append({**dict(zip(GROUP[:-1], key, strict=True)), "a": a, "b": b,
                             "metric": metric, **c})
    return pd.DataFrame(rows, columns=cols)


TIE_RULE = (
    "Solvers are sorted by mean; going down that order, a solver joins the tie group of the "
    "one just above it when the paired bootstrap interval of their difference (on the "
    "instances both scored validly) includes 0 or is over fewer than {min_n} pairs; otherwise "
    "it opens a new group. Every member of a group has the rank of the group's first solver "
    "(so a chain of ties A = B, B = C is one group even when A and C differ).")


def tie_groups(wide, seed: int = SEED, n_boot: int = N_BOOT, level: float = LEVEL,
               min_n: int = MIN_RANK_N) -> list[tuple[str, int, dict | None]]:
    """Ranks with ties of the solvers (columns) of ``wide`` (rows: instances), by :data:`TIE_RULE`.

    Parameters
    ----------
    wide : pandas.DataFrame
        One column per solver, one row per instance, NaN where a solver has no valid score.
    seed, n_boot, level : int, int, float
        The paired bootstrap's seed, resamples and level.
    min_n : int
        Fewer pairs than this never separate two solvers.

    Returns
    -------
    list of (solver, rank, comparison)
        Sorted by mean (highest first, ties by name); ``rank`` is the 1-based position of
        the first solver of its tie group; ``comparison`` is the :func:`paired_comparison` of
        the solver above minus this one (None for the first).

    >>> import pandas as pd
    >>> wide = pd.DataFrame({"a": [0.9, 0.8, 0.9, 0.85, 0.95], "b": [0.1, 0.2, 0.15, 0.1, 0.2]})
    >>> [(s, r) for s, r, _ in tie_groups(wide)]
    [('a', 1), ('b', 2)]
    """
    mean = wide.mean()
    names = sorted(wide.columns, key=lambda s: (-mean[s] if np.isfinite(mean[s]) else np.inf,
                                                str(s)))
    out: list[tuple[str, int, dict | None]] = []
    for i, name in enumerate(names):
        if i == 0:
            out.append((name, 1, None))
            continue
        c = paired_comparison(wide[names[i - 1]], wide[name], seed=seed, n_boot=n_boot,
                              level=level)
        tied = (c["n"] < min_n or not np.isfinite(c["ci_low"])
                or c["ci_low"] <= 0.0 <= c["ci_high"])
        out.append((name, out[-1][1] if tied else i + 1, c))
    return out
