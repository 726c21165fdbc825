"""Headroom: how far each solver's NC is below its instance's ceiling.

The ceilings come as a table, ``ceilings.csv``, beside a results table (``benchmarks/ceiling.py
report`` writes the standard board's). One row per instance and ceiling kind:

``instance``       the scene (``cube_defects-test-00012``), as in the results' ``scene``;
``track``          the track whose rows were given these data (``cube_true``);
``observation``    the rows' observation source (``true``) and ``n_modes`` their number of
                   modes: a ceiling applies to the rows of that track, source and modes only;
``kind``           ``w_view``, ``w_full``, ``v_view`` or ``v_full``: the field (stiffness w,
                   density v) and the data (``view``: what the rows were given; ``full``: the
                   same modes at every free DOF);
``ceiling``        the highest NC found of a field that explains the data at least as well
                   as the homogenised truth (docs/metrics.md, "Ceiling");
``eps``            that misfit (the homogenised truth's), ``homog_nc`` the homogenised truth's
                   own NC, ``method`` the search's version, ``inputs_sha256`` the inputs'.

The headroom of a solver on an instance is ``ceiling - NC`` (kind ``w_view`` for NC w,
``v_view`` for NC v); it is averaged over the instances that have both a ceiling and a valid
row of the solver (paired), with a percentile bootstrap interval
(:func:`vvtbench.scoring.stats.paired_comparison`). An instance without a ceiling is left out,
never given one.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..scoring.stats import MIN_RANK_N, SEED, paired_comparison

#: the file name looked for beside a results table
CEILINGS_FILE = "ceilings.csv"
#: the columns of a ceilings table, in order
COLUMNS = ("instance", "track", "observation", "n_modes", "kind", "ceiling", "eps",
           "homog_nc", "method", "inputs_sha256")
#: the ceiling kinds: field (w, v) and data (view, full)
KINDS = ("w_view", "w_full", "v_view", "v_full")
#: the kind a results column is compared with: the field it scores, on the data the row had
BOARD_KIND = {"nc_w": "w_view", "nc_v": "v_view"}

HEADROOM_NOTE = (
    "Headroom: per instance, the instance's ceiling minus the solver's NC (same field), then "
    "the mean over the instances that have both a ceiling and a valid row of the solver "
    f"(paired), with its bootstrap interval (none under {MIN_RANK_N} pairs); pairs: their "
    "number. The ceiling is the highest "
    "NC with the true field found by a search over fields on the inference grid whose modes "
    "explain the data the rows were given (the true modes through the track's camera) at "
    "least as well as the homogenised truth does (docs/metrics.md, \"Ceiling\"). It is one "
    "search's best: a lower bound on the supremum over such fields, not a proof that no "
    "method can do better. Instances without a committed ceiling are left out. A negative "
    "headroom is a row above its ceiling: its field explains the data worse than the "
    "homogenised truth does (a row above a ceiling that explains the data as well would "
    "contradict the ceiling; tests/test_ceiling.py checks that there is none).")


class CeilingsError(ValueError):
    """A ceilings table that cannot be used (the message names the file and the column)."""


def ceilings_beside(results: str | Path) -> Path | None:
    """The ceilings table beside ``results`` (a table, or a run folder holding one); None when
    there is none."""
    results = Path(results)
    folder = results if results.is_dir() else results.parent
    path = folder / CEILINGS_FILE
    return path if path.is_file() else None


def check_ceilings(df, source: str = CEILINGS_FILE) -> str | None:
    """The first problem of a ceilings table (one line naming ``source`` and the column), or
    None.

    >>> import pandas as pd
    >>> row = dict(instance="a", track="t", observation="true", n_modes=20, kind="w_view",
    ...            ceiling=0.9, eps=1e-3, homog_nc=0.8, method="2", inputs_sha256="x")
    >>> check_ceilings(pd.DataFrame([row])) is None
    True
    >>> check_ceilings(pd.DataFrame([row | {"ceiling": 1.5}]))
    'ceilings.csv: column ceiling, row 1: 1.5 is not an NC in [-1, 1]'
    """
    missing = [c for c in COLUMNS if c not in df.columns]
    if missing:
        return f"{source}: missing column {missing[0]} (columns: {', '.join(COLUMNS)})"
    for i, r in enumerate(df.itertuples(index=False), start=1):
        if r.kind not in KINDS:
            return f"{source}: column kind, row {i}: {r.kind!r} is not one of {', '.join(KINDS)}"
        for col, lo, hi in (("ceiling", -1.0, 1.0), ("homog_nc", -1.0, 1.0),
                            ("eps", 0.0, np.inf), ("n_modes", 1.0, np.inf)):
            x = _float(getattr(r, col))
            if not (np.isfinite(x) and lo - 1e-9 <= x <= hi + 1e-9):
                what = "an NC in [-1, 1]" if hi == 1.0 else f"a finite number >= {lo:g}"
                return f"{source}: column {col}, row {i}: {getattr(r, col)} is not {what}"
        for col in ("instance", "track", "observation"):
            if not isinstance(getattr(r, col), str) or not getattr(r, col):
                return f"{source}: column {col}, row {i}: empty"
    keys = df[["instance", "track", "observation", "n_modes", "kind"]].astype(str)
    dup = keys.duplicated()
    if dup.any():
        i = int(np.flatnonzero(dup.to_numpy())[0]) + 1
        return f"{source}: row {i}: a second ceiling of the same instance, track and kind"
    return None


def _float(x) -> float:
    try:
        return float(x)
    except (TypeError, ValueError):
        return float("nan")


def read_ceilings(path: str | Path):
    """The ceilings table at ``path`` (pandas DataFrame), checked (:func:`check_ceilings`).

    Raises
    ------
    CeilingsError
        The file cannot be read or fails the check; the message is one line naming it.
    """
    import pandas as pd

    path = Path(path)
    try:
        df = pd.read_csv(path, dtype={"instance": str, "track": str, "observation": str,
                                      "kind": str, "method": str, "inputs_sha256": str})
    except (OSError, ValueError) as error:
        raise CeilingsError(f"{path}: cannot read the ceilings table: "
                            f"{str(error).splitlines()[0] if str(error) else error}") from None
    problem = check_ceilings(df, str(path))
    if problem:
        raise CeilingsError(problem)
    return df


def paired_headroom(rows, ceilings, metric: str = "nc_w"):
    """The valid rows of ``rows`` (one cell: one track, source, variation and solver) that have
    a ceiling, each with it.

    Parameters
    ----------
    rows : pandas.DataFrame
        Results rows (``scene``, ``track``, ``observation``, ``status``, ``metric``, and
        ``n_modes`` where the table has it).
    ceilings : pandas.DataFrame
        A ceilings table (:func:`read_ceilings`).
    metric : str
        ``nc_w`` or ``nc_v``: compared with the ceiling of kind :data:`BOARD_KIND`.

    Returns
    -------
    (ceiling, nc) : tuple of numpy.ndarray
        Aligned, one entry per valid row (``status`` ok, finite ``metric``) whose instance,
        track, source and number of modes have a ceiling of that kind.
    """
    c = ceilings[ceilings.kind == BOARD_KIND[metric]]
    ok = rows[(rows.status == "ok") & np.isfinite(rows[metric].astype(float))]
    if ok.empty or c.empty:
        return np.zeros(0), np.zeros(0)
    keys = ["instance", "track", "observation"]
    left = ok.assign(instance=ok.scene.astype(str))
    if "n_modes" in ok.columns:
        keys.append("n_modes")
        left = left.assign(n_modes=left.n_modes.astype(float))
        c = c.assign(n_modes=c.n_modes.astype(float))
    m = left.merge(c[[*keys, "ceiling"]], on=keys, how="inner")
    return m.ceiling.to_numpy(float), m[metric].to_numpy(float)


def track_coverage(df, ceilings, track: str, kind: str = "w_view") -> tuple[int, int]:
    """(instances of ``track`` in ``df`` with a ceiling of ``kind``, instances of ``track`` in
    ``df``); an instance is a scene."""
    scenes = set(df.loc[df.track == track, "scene"].astype(str))
    have = set(ceilings.loc[(ceilings.track == track) & (ceilings.kind == kind), "instance"])
    return len(scenes & have), len(scenes)


def headroom_table(df, ceilings, seed: int = SEED):
    """One row per track, observation source, variation and solver that has a ceiling on at
    least one of its instances.

    Columns: ``track``, ``observation``, ``variation``, ``solver``, ``reference``; per metric
    ``m`` of :data:`BOARD_KIND` (``nc_w``, ``nc_v``): ``m_n`` (pairs), ``m_mean`` (mean of
    ceiling - NC), ``m_ci_low``, ``m_ci_high`` (its bootstrap interval, NaN under two pairs)
    and ``m_above`` (pairs where the row is above its ceiling); ``with_ceiling`` and
    ``instances``: the track's instances with a w ceiling, and all of them. Within a cell,
    solvers are ordered as given, references last.
    """
    import pandas as pd

    out = []
    tracks = set(ceilings.track)
    reference = (df["reference"].fillna(False).astype(bool) if "reference" in df.columns
                 else pd.Series(False, index=df.index))
    d = df[df.track.isin(tracks)].assign(_ref=reference)
    cover = {t: track_coverage(df, ceilings, t) for t in tracks}
    for (track, obs, var, solver), rows in d.groupby(
            ["track", "observation", "variation", "solver"], sort=False):
        rec = {"track": track, "observation": obs, "variation": var, "solver": solver,
               "reference": bool(rows._ref.any())}
        for metric in BOARD_KIND:
            top, nc = paired_headroom(rows, ceilings, metric)
            s = paired_comparison(top, nc, seed=seed)
            rec |= {f"{metric}_n": s["n"], f"{metric}_mean": s["mean_diff"],
                    f"{metric}_ci_low": s["ci_low"], f"{metric}_ci_high": s["ci_high"],
                    f"{metric}_above": int(np.sum(nc > top))}
        if rec["nc_w_n"] or rec["nc_v_n"]:
            rec["with_ceiling"], rec["instances"] = cover[track]
            out.append(rec)
    t = pd.DataFrame(out)
    if t.empty:
        return t
    return t.sort_values("reference", kind="stable").reset_index(drop=True)


__all__ = ["BOARD_KIND", "CEILINGS_FILE", "COLUMNS", "CeilingsError", "HEADROOM_NOTE", "KINDS",
           "ceilings_beside", "check_ceilings", "headroom_table", "paired_headroom",
           "read_ceilings", "track_coverage"]
