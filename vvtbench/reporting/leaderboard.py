"""The leaderboard: Markdown + static HTML (no server, no external URL) from a results table.

Writes into the output folder (default ``leaderboard/``): ``README.md`` and ``index.html`` (a
summary, then per track in the order of the suite (first appearance in the table) one ranking
table per observation source with a row per variation and solver, the paired comparisons and
the track's figures), ``results.csv`` (a copy of the table), ``figures/`` and
``leaderboard.json``, which marks the folder as written by vvtbench, lists its files and holds
the statistics as numbers. Statistics (:mod:`vvtbench.scoring.stats`, docs/results.md "Statistics"):
mean and median of NC w and v with their percentile bootstrap intervals over instances, the
number of instances each is over, runtime median and IQR, failed and invalid counts, and paired
comparisons between ranked solvers on shared instances. Figures (:mod:`vvtbench.reporting.plots`):
NC
against each swept value (number of modes, α_v, geometry scale, ...), intrinsic-resolution
curves, and per scene the voxel fields of the truth and of every solver and observation source
(values and contrast views), read from each run's ``fields.npz`` (the ``estimate_path``
column, relative to the results file's folder). When a ceilings table (``ceilings.csv``,
:mod:`vvtbench.reporting.headroom`) is beside the results table, each track with ceilings also
gets a headroom section: per solver, the mean of its instances' ceiling minus its NC, paired
over the instances that have both.

Data safety: the output folder may hold only files listed in its ``leaderboard.json``; a folder
holding other files is refused unless ``overwrite=True``, and even then only the leaderboard's
own files are written or removed. Every file is written atomically (temp file + rename), and
nothing is written through a symbolic link.
"""

from __future__ import annotations

import html
import json
import os
import re
import sys
from pathlib import Path

import numpy as np

from .._version import __version__
from ..scoring.stats import (
    LEVEL,
    MIN_RANK_N,
    N_BOOT,
    SEED,
    TIE_RULE,
    instance_ids,
    paired_table,
    tie_groups,
    track_statistics,
    win_rate_text,
)

#: ranked metrics, each as mean and median with their bootstrap intervals over instances
RANK_METRICS = [("nc_w", "NC w"), ("nc_v", "NC v")]
#: metrics given as the mean of their finite values
MEAN_COLUMNS = [("nc_at_sigma_star_w", "NC w @ σ*"), ("sigma_star_w", "σ* w (vox)"),
                ("mode_mac", "mode MAC"), ("freq_err_scaled", "freq err (scaled)")]
#: shown only where a table has a value: the false contrast of instances whose truth is
#: constant (there NC is undefined, docs/metrics.md) and the coverage of stated intervals
UNDEFINED_NC_COLUMNS = [("false_contrast_w", "false contrast w (constant truth)"),
                        ("false_contrast_v", "false contrast v (constant truth)"),
                        ("interval_coverage_w", "95 % interval coverage w"),
                        ("interval_coverage_v", "95 % interval coverage v")]
#: a solver is ranked in a cell only when at least this fraction of its runs there gave a
#: valid estimate: a mean over the instances it chose to answer cannot outrank one over all
MIN_VALID_FRACTION = 0.9
_OBS_ORDER = {"true": 0, "extracted": 1}
_PCT = f"{LEVEL * 100:g}\u00a0%"  # "95 %" (no line break inside)

LEGEND = (
    "Every statistic is over the instances (scene × seed) of one track, observation source "
    "and variation: a sweep value (n_modes, alpha_v, ...) is never pooled with another. "
    f"`mean [low, high]`: the mean and its {_PCT} percentile bootstrap interval over "
    f"instances ({N_BOOT} resamples, numpy default_rng seed {SEED}); the median likewise. "
    f"Below {MIN_RANK_N} instances there is no interval and no rank, only the mean and n "
    "(too few instances to rank: the percentile bootstrap under-covers badly on a handful of "
    "values); between 5 and about 10 the interval is still somewhat too narrow. "
    "n: instances with a valid run; a metric undefined on an instance (NC where the truth is "
    "constant: the false contrast is given instead) is left out, and its cell then says over "
    "how many instances it is (n=k). –: no value; a mean without an interval is over fewer "
    f"than {MIN_RANK_N} instances. Runtime: median (interquartile range) of the valid runs, "
    "in seconds. "
    "failed / invalid: runs that raised / estimates that were not scored; a solver valid on "
    f"fewer than {MIN_VALID_FRACTION:.0%} of its runs in a cell is not ranked there (–). "
    "Interval coverage "
    "(solvers that state per-voxel standard deviations only): the fraction of voxels whose "
    "truth lies within estimate ± 1.96 std, nominal 0.95, not ranked. Paired comparisons, "
    "per track, source and variation, between ranked solvers on the instances both solved "
    "validly: A − B, the mean of the per-instance differences with its bootstrap interval, "
    "the win rate of A (ties count half) and the number of pairs; A is the one with the higher "
    "mean. Tie groups: " + TIE_RULE.format(min_n=MIN_RANK_N) + " A shared rank is written "
    "1=.")

SCORE_SENTENCE = (
    "Score: NC w, the centered normalized correlation between the estimated and the true "
    "stiffness field (Young's modulus) over the voxels: 1 is the true spatial pattern, 0 no "
    "relation to it, higher is better; NC v is the same for density.")

NOT_RECOMPUTED = (
    "Scores not recomputed: this table was given without its run's cache, so its scores are "
    "shown as written, not recomputed from the estimates and the truth.")
UNSANDBOXED = ("UNSANDBOXED: {n} of the runs ({solvers}) ran without a sandbox: the plug-in "
               "could read every file its user could, truth included. Their rows are marked "
               "'(unsandboxed)'; trust those scores only as far as the plug-in's code.")
RECOMPUTED = ("Scores recomputed: every scored row was recomputed from the estimate and the "
              "truth in the run's cache and agreed with the table.")


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _metric_columns(df) -> tuple[list[str], list[str]]:
    means = [c for c, _ in MEAN_COLUMNS + UNDEFINED_NC_COLUMNS if c in df.columns]
    return [c for c, _ in RANK_METRICS], means


def _page_order(t, df):
    """``t`` (rows with track, observation and variation columns) sorted stably as the pages
    show them: tracks in the table's order, true then extracted modes, variations in the
    table's (the suite's) order."""
    tracks = {x: i for i, x in enumerate(dict.fromkeys(df.track))}
    variations = {x: i for i, x in enumerate(dict.fromkeys(zip(df.track, df.variation,
                                                                 strict=True)))}
    key = t.assign(_t=t.track.map(tracks),
                   _v=[variations[k] for k in zip(t.track, t.variation, strict=True)],
                   _o=t.observation.map(lambda o: _OBS_ORDER.get(o, 2)))
    order = key.sort_values(["_t", "_o", "observation", "_v"], kind="stable").index
    return t.loc[order]


def ranking(df, seed: int = SEED) -> list[tuple[str, str, object]]:
    """Per track (first-appearance order: the suite's) and observation source, one table
    with a row per variation and solver (:func:`vvtbench.scoring.stats.track_statistics`).

    Within a variation the solvers are ranked by mean NC of w over their valid instances,
    with ties (:func:`vvtbench.scoring.stats.tie_groups`: a solver whose paired interval against the
    one above it includes 0 shares its rank). Not ranked, and listed after the ranked ones: a
    solver without a valid NC w; one valid on fewer than :data:`MIN_VALID_FRACTION` of its
    runs in the cell (its mean would be over the instances it chose to answer); one over
    fewer than :data:`vvtbench.scoring.stats.MIN_RANK_N` instances (too few to rank). Reference
    solvers (``reference``: they saw the truth) are never ranked: they come last, with a note
    when a ranked solver of the same variation is above them. Invalid rows are never scored.

    Returns
    -------
    list of (track, observation, pandas.DataFrame)
        The table has the track_statistics columns, ``rank`` (int, or None when not ranked),
        ``tied`` (the number of solvers sharing the rank, 0 when not ranked) and ``note``.
    """
    import pandas as pd

    metrics, means = _metric_columns(df)
    st = track_statistics(df, metrics=metrics, means=means, seed=seed)
    if st.empty:
        return []
    loose = set(map(tuple, df.loc[_unsandboxed(df), ["track", "observation", "variation",
                                                     "solver"]].to_numpy().tolist()))
    st["unsandboxed"] = [tuple(k) in loose for k in
                         st[["track", "observation", "variation", "solver"]].to_numpy().tolist()]
    few = st.n < MIN_VALID_FRACTION * st.runs
    too_few = st.nc_w_n < MIN_RANK_N
    st = st.assign(_unranked=st.reference | ~np.isfinite(st.nc_w_mean.astype(float)) | few
                   | too_few)
    cell = ["track", "observation", "variation"]
    ok = df[(df.status == "ok") & ~df["reference"].fillna(False).astype(bool)]
    ok = ok.assign(_inst=instance_ids(ok))
    ranks: dict[tuple, int] = {}
    for key, t in st[~st._unranked].groupby(cell, sort=False):
        rows = ok[(ok.track == key[0]) & (ok.observation == key[1]) & (ok.variation == key[2])
                  & ok.solver.isin(t.solver)]
        wide = rows.pivot_table(index="_inst", columns="solver", values="nc_w",
                                aggfunc="first", dropna=False)
        for solver, rank, _ in tie_groups(wide, seed=seed):
            ranks[(*key, solver)] = rank
    st["rank"] = pd.Series([ranks.get(k) for k in zip(*(st[c] for c in [*cell, "solver"]),
                                                      strict=True)],
                           index=st.index, dtype=object)
    st["_sort"] = [r if r is not None else np.inf for r in st["rank"]]
    st = st.sort_values(["reference", "_unranked", "_sort", "nc_w_mean", "nc_v_mean"],
                        ascending=[True, True, True, False, False], na_position="last",
                        kind="stable")
    st = _page_order(st, df)
    shared = st.groupby([*cell, "_sort"], sort=False).solver.transform("size")
    st["tied"] = [int(k) if r is not None else 0 for k, r in zip(shared, st["rank"],
                                                                 strict=True)]
    best = st.nc_w_mean.where(~st._unranked).groupby([st[c] for c in cell]).transform("max")
    notes = []
    for ref, m, b, n, runs, nw in zip(st.reference, st.nc_w_mean, best, st.n, st.runs,
                                      st.nc_w_n, strict=True):
        if ref:
            notes.append(f"below a ranked solver (NC w {b:.2f})" if np.isfinite(b)
                         and np.isfinite(m) and m < b else "")
        elif n < runs * MIN_VALID_FRACTION:
            notes.append(f"not ranked: valid on {n} of {runs} runs")
        elif 0 < nw < MIN_RANK_N:
            notes.append(f"too few instances to rank (n={nw}, fewer than {MIN_RANK_N})")
        else:
            notes.append("")
    st["note"] = notes
    st = st.drop(columns=["_unranked", "_sort"]).reset_index(drop=True)
    return [(track, obs, t.reset_index(drop=True))
            for (track, obs), t in st.groupby(["track", "observation"], sort=False)]


# --------------------------------------------------------------------------- cells
def _num(x, digits: int = 2, sign: bool = False) -> str:
    """``x`` with ``digits`` decimals, "–" when it is not a finite number."""
    try:
        ok = np.isfinite(float(x))
    except (TypeError, ValueError):
        return "–"
    return f"{float(x):{'+' if sign else ''}.{digits}f}" if ok else "–"


def number_text(x, digits: int = 3, sign: bool = False) -> str:
    """``x`` with ``digits`` decimals or, when it is non-zero and below 0.01 in magnitude,
    with ``digits`` significant figures in scientific notation (an efficiency of 2e-4 is
    never printed as 0.000); "–" when ``x`` is not a finite number.

    >>> number_text(0.81234), number_text(2.163e-4), number_text(0.0), number_text(float("nan"))
    ('0.812', '2.16e-04', '0.000', '–')
    >>> number_text(-0.0421, 2, sign=True), number_text(3.5e-5, 2, sign=True)
    ('-0.04', '+3.5e-05')
    """
    try:
        x = float(x)
    except (TypeError, ValueError):
        return "–"
    if not np.isfinite(x):
        return "–"
    plus = "+" if sign else ""
    if x != 0 and abs(x) < 0.01:
        return f"{x:{plus}.{digits - 1}e}"
    return f"{x:{plus}.{digits}f}"


def ci_cell(value, low, high, n: int | None = None, of: int | None = None,
            sign: bool = False, digits: int = 2) -> str:
    """``0.41 [0.33, 0.49]``: a value with its interval (the interval left out when there is
    none or when ``n`` is below :data:`vvtbench.scoring.stats.MIN_RANK_N`), ``(n=k)`` appended when
    the value is over fewer instances ``n`` than the row's
    ``of``; "–" when there is no value."""
    if n == 0 or not np.isfinite(float(value)):
        return "–"
    text = _num(value, digits, sign)
    if (np.isfinite(float(low)) and np.isfinite(float(high))
            and (n is None or n >= MIN_RANK_N)):
        text += f" [{_num(low, digits, sign)}, {_num(high, digits, sign)}]"
    if n is not None and of is not None and n < of:
        text += f" (n={n})"
    return text


def _seconds(x: float) -> str:
    return f"{x:.0f}" if x >= 100 else f"{x:#.3g}"


def _runtime_cell(r) -> str:
    if not np.isfinite(r["runtime_median_s"]):
        return "–"
    return (f"{_seconds(r['runtime_median_s'])} ({_seconds(r['runtime_q25_s'])}–"
            f"{_seconds(r['runtime_q75_s'])})")


def _unsandboxed(df):
    """The rows a plug-in produced without a sandbox (column ``sandbox`` = ``none``)."""
    if "sandbox" not in df.columns:
        return np.zeros(len(df), dtype=bool)
    return (df["sandbox"].astype(str) == "none").to_numpy()


def _solver_label(r) -> str:
    """A table's solver cell: its name, marked as a reference and when it ran unsandboxed."""
    label = f"{r['solver']} (reference)" if r["reference"] else str(r["solver"])
    return label + (" (unsandboxed)" if r.get("unsandboxed", False) else "")


def _rank_label(r) -> str:
    if r["reference"]:
        return "ref"
    if r["rank"] is None:
        return "–"
    return f"{r['rank']}=" if r["tied"] > 1 else str(r["rank"])


def _ranking_rows(t) -> tuple[list[str], list[tuple[list[str], str]]]:
    """The header and the rows (cells, HTML class) of a ranking table: rank, mean NC of w
    and v with their intervals, n, failed and invalid."""
    head = ["variation", "rank", "solver"]
    head += [f"{label} mean [{_PCT} CI]" for _, label in RANK_METRICS]
    head += ["n", "failed", "invalid"]
    rows, last = [], None
    for _, r in t.iterrows():
        label = _solver_label(r)
        if r["note"]:
            label += f" -- {r['note']}"
        cells = [str(r["variation"]), _rank_label(r), label]
        cells += [ci_cell(r[f"{m}_mean"], r[f"{m}_mean_ci_low"], r[f"{m}_mean_ci_high"],
                          r[f"{m}_n"], r["n"]) for m, _ in RANK_METRICS]
        cells += [str(int(r["n"])), str(int(r["failed"])), str(int(r["invalid"]))]
        cls = " ".join(filter(None, ["ref" if r["reference"] else "",
                                     "loose" if r.get("unsandboxed", False) else "",
                                     "group" if r["variation"] != last else ""]))
        last = r["variation"]
        rows.append((cells, cls))
    return head, rows


def _detail_rows(t) -> tuple[list[str], list[tuple[list[str], str]]]:
    """The header and rows of a ranking table's details: medians, the mean-only columns and
    the runtime."""
    optional = [(c, label) for c, label in UNDEFINED_NC_COLUMNS
                if f"{c}_n" in t and (t[f"{c}_n"] > 0).any()]
    head = ["variation", "solver"]
    head += [f"{label} median [{_PCT} CI]" for _, label in RANK_METRICS]
    head += [*[label for _, label in MEAN_COLUMNS + optional], "runtime s: median (IQR)"]
    rows, last = [], None
    for _, r in t.iterrows():
        label = _solver_label(r)
        cells = [str(r["variation"]), label]
        cells += [ci_cell(r[f"{m}_median"], r[f"{m}_median_ci_low"], r[f"{m}_median_ci_high"],
                          r[f"{m}_n"], r["n"]) for m, _ in RANK_METRICS]
        for c, _ in MEAN_COLUMNS + optional:
            cells.append(ci_cell(r[f"{c}_mean"], np.nan, np.nan, r[f"{c}_n"], r["n"], digits=3)
                         if f"{c}_mean" in r else "–")
        cells.append(_runtime_cell(r))
        cls = " ".join(filter(None, ["ref" if r["reference"] else "",
                                     "loose" if r.get("unsandboxed", False) else "",
                                     "group" if r["variation"] != last else ""]))
        last = r["variation"]
        rows.append((cells, cls))
    return head, rows


def _paired_rows(p) -> tuple[list[str], list[tuple[list[str], str]]]:
    """The header and rows of a paired-comparison table (:func:`stats.paired_table`)."""
    head = ["source", "variation", "A", "B", f"A − B: mean [{_PCT} CI]", "A wins",
            "pairs"]
    rows, last = [], None
    for _, r in p.iterrows():
        key = (r["observation"], r["variation"])
        rows.append(([f"{r['observation']} modes", str(r["variation"]), str(r["a"]),
                      str(r["b"]), ci_cell(r["mean_diff"], r["ci_low"], r["ci_high"],
                                           r["n"], sign=True),
                      win_rate_text(r["win_rate"], int(r.get("ties", 0)), int(r["n"])),
                      str(int(r["n"]))],
                     "group" if key != last else ""))
        last = key
    return head, rows


def md_cell(x) -> str:
    """``x`` as one Markdown table cell: ``|`` escaped, ``<``, ``>`` and ``&`` as entities,
    line breaks as spaces, so no text can end the cell, open a tag or start a row."""
    text = re.sub(r"\s*[\r\n\v\f\x1c-\x1e\x85\u2028\u2029]\s*", " ", str(x))
    return (text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")
            .replace("\\", "\\\\").replace("|", "\\|"))


def _md(head: list[str], rows) -> str:
    lines = ["| " + " | ".join(md_cell(h) for h in head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(md_cell(c) for c in cells) + " |" for cells, _ in rows]
    return "\n".join(lines)


def _html(head: list[str], rows, left: int = 1, wide: bool = False) -> str:
    """A table; the first ``left`` columns are text (left-aligned); ``wide``: its headers may
    break inside a word so that many columns fit a narrow window."""
    def td(i, x, tag="td"):
        cls = ' class="l"' if i < left else ""
        return f"<{tag}{cls}>{html.escape(str(x))}</{tag}>"

    out = ["<tr>" + "".join(td(i, h, "th") for i, h in enumerate(head)) + "</tr>"]
    for cells, cls in rows:
        out.append((f'<tr class="{cls}">' if cls else "<tr>")
                   + "".join(td(i, x) for i, x in enumerate(cells)) + "</tr>")
    table = '<table class="wide">' if wide else "<table>"
    return '<div class="scroll">' + table + "".join(out) + "</table></div>"


# --------------------------------------------------------------------------- headroom
def read_headroom(df, results):
    """(the ceilings table's path, the table, :func:`vvtbench.reporting.headroom.headroom_table`)
    when a ceilings table (``ceilings.csv``) is beside ``results``; None otherwise.

    Raises
    ------
    vvtbench.reporting.headroom.CeilingsError
        The ceilings table is there but cannot be used (one line naming the file and column).
    """
    from .headroom import ceilings_beside, headroom_table, read_ceilings

    path = ceilings_beside(results)
    if path is None:
        return None
    ceilings = read_ceilings(path)
    return path, ceilings, headroom_table(df, ceilings, seed=SEED)


def _headroom_rows(t) -> tuple[list[str], list[tuple[list[str], str]]]:
    """The header and rows of a track's headroom table (:func:`read_headroom`)."""
    head = ["source", "variation", "solver"]
    for _, label in RANK_METRICS:
        head += [f"headroom {label}: ceiling − {label}, mean [{_PCT} CI]", f"pairs ({label})"]
    head.append("rows above the ceiling (w, v)")
    rows, last = [], None
    for _, r in t.iterrows():
        key = (r["observation"], r["variation"])
        cells = [f"{r['observation']} modes", str(r["variation"]),
                 f"{r['solver']} (reference)" if r["reference"] else str(r["solver"])]
        for m, _ in RANK_METRICS:
            cells += [ci_cell(r[f"{m}_mean"], r[f"{m}_ci_low"], r[f"{m}_ci_high"],
                              int(r[f"{m}_n"]), sign=True, digits=3), str(int(r[f"{m}_n"]))]
        cells.append(f"{int(r['nc_w_above'])}, {int(r['nc_v_above'])}")
        cls = " ".join(filter(None, ["ref" if r["reference"] else "",
                                     "group" if key != last else ""]))
        last = key
        rows.append((cells, cls))
    return head, rows


def _without_ceiling(df, ceilings, track: str) -> str:
    """Why the track's other instances have no ceiling of NC w: a constant true w (every
    valid row's NC w undefined, its false contrast defined) has none; the rest none yet."""
    d = df[df.track == track]
    have = set(ceilings.loc[(ceilings.track == track) & (ceilings.kind == "w_view"), "instance"])
    rest = d[~d.scene.astype(str).isin(have)]
    if rest.empty:
        return ""
    fc = rest["false_contrast_w"] if "false_contrast_w" in rest.columns else rest.nc_w * np.nan
    constant = {str(sc) for sc, g in rest.assign(_fc=fc).groupby("scene")
                if g.nc_w.isna().all() and g._fc.notna().any()}
    pending = rest.scene.astype(str).nunique() - len(constant)
    parts = []
    if constant:
        parts.append(f"{len(constant)} have no defect in w (a constant true w: NC w undefined, "
                     "so no ceiling)")
    if pending:
        parts.append(f"{pending} have no ceiling yet")
    return "; ".join(parts) + "."


def headroom_section(headroom, df, track: str):
    """(Markdown, HTML, records for leaderboard.json) of ``track``'s headroom section, or None
    when ``headroom`` (:func:`read_headroom`) has no row of the track: a track none of whose
    instances has a ceiling shows none."""
    from .headroom import HEADROOM_NOTE, track_coverage

    if headroom is None:
        return None
    _, ceilings, table = headroom
    if table.empty:
        return None
    t = table[table.track == track]
    if t.empty:
        return None
    have, total = track_coverage(df, ceilings, track)
    title = (f"{track} — headroom to the ceiling ({have} of {total} instances have a ceiling "
             "of NC w)")
    note = HEADROOM_NOTE + (f" Over {have} of the track's {total} instances; "
                            + _without_ceiling(df, ceilings, track) if have < total else "")
    head, rows = _headroom_rows(t)
    md = f"### {md_cell(title)}\n\n" + _md(head, rows) + "\n\n" + note + "\n"
    page = (f"<h3>{html.escape(title)}</h3>" + _html(head, rows, left=3)
            + f'<p class="note">{html.escape(note)}</p>')
    return md, page, t.to_dict("records")


# --------------------------------------------------------------------------- figures
def _slug(s: str) -> str:
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in str(s))


def _load_fields(base: Path, rel) -> dict | None:
    """The ``fields.npz`` of a row (None when missing or unreadable); no pickle."""
    if not isinstance(rel, str) or not rel:
        return None
    f = base / rel
    if not f.is_file():
        return None
    try:
        with np.load(f, allow_pickle=False) as z:
            return {k: np.asarray(z[k]) for k in ("w", "v", "w_true", "v_true") if k in z}
    except (OSError, ValueError):
        return None


def _solver_order(d) -> list[str]:
    """Reference solvers first, then the others by name."""
    ref = set(d.loc[d["reference"].astype(bool), "solver"]) if "reference" in d else set()
    return sorted(d.solver.unique(), key=lambda s: (s not in ref, s))


def shown_variation(d) -> str:
    """The variation drawn in a track's field figures: the middle of its variations in run
    order (the paper's default of a sweep, e.g. n_modes=14 of 8...20, α_v=1e-7 of 1e-9...1e-5)."""
    variations = list(dict.fromkeys(d.variation))
    return variations[len(variations) // 2]


#: field figures drawn per track: its first scenes (instances) whose truth has contrast
MAX_FIELD_SCENES = 3


def _nc_note(r) -> str:
    cells = []
    for f in "wv":
        nc = r.get(f"nc_{f}")
        cells.append(f"{f} {nc:.2f}" if isinstance(nc, float) and np.isfinite(nc)
                     else f"{f} undefined")
    return "NC " + ", ".join(cells)


def field_figures(df, track: str, base: Path, folder: Path, rel_dir: str, styles) -> list:
    """For the first :data:`MAX_FIELD_SCENES` scenes of ``track`` whose true w is not
    constant (so NC is defined): the truth and every solver × observation source of the
    shown variation and first seed, values and contrast views; the contrast view first
    when the truth's span dwarfs the estimates'
    (:func:`vvtbench.reporting.plots.contrast_first`). Returns [(caption, rel path)]."""
    from .plots import CONTRAST_FIRST_RATIO, contrast_first, plot_field_grids

    d = df[(df.track == track) & (df.status == "ok")]
    if d.empty or "estimate_path" not in d:
        return []
    variation = shown_variation(d)
    out = []
    drawn = 0
    for scene in dict.fromkeys(d.scene):
        ds = d[(d.scene == scene) & (d.variation == variation)]
        if ds.empty or drawn >= MAX_FIELD_SCENES or not np.isfinite(
                ds.nc_w.astype(float)).any():
            continue
        ds = ds[ds.seed == ds.seed.iloc[0]]
        truth, estimates, notes = None, {}, {}
        for solver in _solver_order(ds):
            for obs in ("true", "extracted", *sorted(set(ds.observation) - {"true", "extracted"})):
                r = ds[(ds.solver == solver) & (ds.observation == obs)]
                if r.empty:
                    continue
                r = r.iloc[0]
                z = _load_fields(base, r.get("estimate_path"))
                if z is None or "w" not in z:
                    continue
                if truth is None and "w_true" in z:
                    truth = (z["w_true"], z["v_true"])
                ref = " (ref.)" if bool(r.get("reference", False)) else ""
                label = f"{solver}{ref}, {obs} modes"
                estimates[label] = (z["w"], z["v"])
                notes[label] = _nc_note(r)
        if not estimates or truth is None:
            continue
        stem = f"{_slug(track)}_slices" + ("" if drawn == 0 else f"_{_slug(scene)}")
        drawn += 1
        seed = ds.seed.iloc[0]
        views = [(False, "", "values, one colour scale shared with the truth"),
                 (True, "_normalized", "contrast to each field's matrix value")]
        first = contrast_first(truth[0], [w for w, _ in estimates.values()])
        if first:  # a shared scale would flatten every estimate
            views.reverse()
        for normalized, suffix, what in views:
            rel = f"{rel_dir}/{stem}{suffix}.png"
            plot_field_grids(folder / Path(rel).name, truth[0], truth[1], estimates,
                             normalized=normalized, notes=notes,
                             title=f"{track}: {scene} [{variation}, seed {seed}]; rows: "
                                   "solver, observation source, NC")
            why = (f" (shown first: the truth's span of w is over {CONTRAST_FIRST_RATIO:g}x "
                   "every estimate's)" if first and normalized else "")
            out.append((f"{scene} [{variation}]: fields, {what}{why}", rel))
    return out


def curve_figures(df, track: str, base: Path, folder: Path, rel_dir: str, styles) -> list:
    """NC against every swept value of the track and the intrinsic-resolution curves."""
    from ..scoring.metrics import intrinsic_resolution
    from .plots import plot_intrinsic_resolution, plot_sweep, plot_views, sweep_keys

    d = df[df.track == track]
    out = []
    for key in sweep_keys(d):
        if key == "views":  # cameras: pooled over the instances, and against DOFs observed
            rel = f"{rel_dir}/{_slug(track)}_nc_vs_views.png"
            if plot_views(folder / Path(rel).name, d, styles,
                          title=f"{track}: NC of w against the number of camera views and "
                                "the DOFs they observe"):
                out.append(("NC against the number of views and the DOFs observed", rel))
            continue
        name = "nc_vs_modes" if key == "n_modes" else f"nc_vs_{_slug(key)}"
        rel = f"{rel_dir}/{_slug(track)}_{name}.png"
        if plot_sweep(folder / Path(rel).name, d, key, styles,
                      title=f"{track}: NC against {key}"):
            out.append((f"NC against {key}", rel))
    ok = d[d.status == "ok"]
    if ok.empty or "estimate_path" not in ok:
        return out
    variation = shown_variation(ok)
    curves: dict = {}
    for r in ok[ok.variation == variation].itertuples():
        z = _load_fields(base, getattr(r, "estimate_path", None))
        if z is None or "w" not in z:
            continue
        c = curves.setdefault((r.solver, r.observation), {"w": [], "v": []})
        for field in ("w", "v"):
            # exactly the rows the table averages: an instance whose NC is undefined there (a
            # constant truth, no defect) is not drawn as a curve of zeros
            if not np.isfinite(float(getattr(r, f"nc_{field}", np.nan))):
                continue
            ir = intrinsic_resolution(z[field], z[f"{field}_true"])
            c[field].append(ir["nc"])
            c["sigmas"] = ir["sigmas"]
    rel = f"{rel_dir}/{_slug(track)}_intrinsic_resolution.png"
    curves = {k: c for k, c in curves.items() if "sigmas" in c}
    if curves and plot_intrinsic_resolution(folder / Path(rel).name, curves, styles,
                                            title=f"{track} [{variation}]: intrinsic "
                                                  "resolution (mean over instances)"):
        out.append((f"intrinsic resolution [{variation}]", rel))
    return out


# --------------------------------------------------------------------------- output safety
class LeaderboardError(ValueError):
    """The leaderboard cannot be written (unsafe output folder, unreadable table)."""


MANIFEST = "leaderboard.json"


def _owned(out: Path) -> set[str]:
    """Files (relative, POSIX) a previous ``build`` wrote into ``out``, from its manifest."""
    f = out / MANIFEST
    if not f.is_file() or f.is_symlink():
        return set()
    try:
        m = json.loads(f.read_text())
    except (OSError, ValueError):
        return set()
    if not isinstance(m, dict):
        return set()
    if m.get("generator") == "vvtbench" and isinstance(m.get("files"), list):
        names = {str(x) for x in m["files"]} | {MANIFEST}
    elif "vvtbench" in m and isinstance(m.get("figures"), list):  # before it listed files
        names = {str(x[2]) for x in m["figures"] if isinstance(x, list) and len(x) == 3}
        names |= {"README.md", "index.html", "results.csv", MANIFEST}
    else:
        return set()
    # only plain relative names inside the folder (a planted manifest must not name others)
    return {n for n in names if n and not Path(n).is_absolute() and ".." not in Path(n).parts
            and "\\" not in n}


def _existing(out: Path) -> set[str]:
    found = set()
    for root, dirs, files in os.walk(out):
        dirs[:] = [d for d in dirs if not d.startswith(".vvtbench-figures-")]
        for name in files + [d for d in dirs if (Path(root) / d).is_symlink()]:
            found.add((Path(root) / name).relative_to(out).as_posix())
    return found


def prepare_output(out: Path, source: Path, overwrite: bool = False) -> set[str]:
    """Check that ``build`` may write into ``out``; returns the files it wrote there before."""
    if out.is_symlink():
        raise LeaderboardError(f"{out} is a symbolic link; refusing to write through it")
    if out.exists() and not out.is_dir():
        raise LeaderboardError(f"{out} exists and is not a folder")
    owned = _owned(out) if out.is_dir() else set()
    if out.is_dir():
        foreign = sorted(_existing(out) - owned)
        if foreign and not overwrite:
            shown = ", ".join(foreign[:4]) + (f" and {len(foreign) - 4} more"
                                              if len(foreign) > 4 else "")
            raise LeaderboardError(
                f"{out} holds files the leaderboard did not write ({shown}); choose an empty "
                "or new folder, or pass --overwrite to replace only the leaderboard's own "
                "files (README.md, index.html, results.csv, leaderboard.json, figures/) and "
                "keep the others")
        for name in ("figures", *sorted(owned)):
            p = out / name
            if p.is_symlink():
                raise LeaderboardError(f"{p} is a symbolic link; refusing to write through it")
    src = source.resolve()
    copy = (out / "results.csv").resolve()
    if src == copy and "results.csv" not in owned:
        raise LeaderboardError(f"the input {source} would be overwritten by the leaderboard's "
                               "copy of the table; choose another output folder")
    return owned


# --------------------------------------------------------------------------- pages
def summary(df, groups: list | None = None) -> list[dict]:
    """Per track (first-appearance order): the best ranked cell (solver, observation source and
    variation with the highest mean NC of w), the best reference cell, and the counts of
    runs, failed and invalid rows.

    Parameters
    ----------
    df : pandas.DataFrame
        The results table.
    groups : list, optional
        Its :func:`ranking` (computed when not given).

    Returns
    -------
    list of dict
        ``track``, ``best`` and ``reference`` (None, or a dict: ``solver``, ``observation``,
        ``variation``, ``nc_w_mean``, ``nc_w_mean_ci_low``, ``nc_w_mean_ci_high``,
        ``nc_w_n``), ``runs``, ``failed``, ``invalid``.
    """
    import pandas as pd

    groups = ranking(df) if groups is None else groups
    cells = (pd.concat([t for _, _, t in groups], ignore_index=True) if groups else None)
    keys = ["solver", "observation", "variation", "nc_w_mean", "nc_w_mean_ci_low",
            "nc_w_mean_ci_high", "nc_w_n", "unsandboxed"]
    counts = df.groupby("track", sort=False).status.agg(
        runs="size", failed=lambda s: int((s == "error").sum()),
        invalid=lambda s: int((s == "invalid").sum()))
    out = []
    for track, c in counts.iterrows():
        best = {}
        for name, ref in (("best", False), ("reference", True)):
            t = (cells[(cells.track == track) & (cells.reference == ref)
                       & np.isfinite(cells.nc_w_mean.astype(float))
                       & (ref | cells["rank"].notna())]
                 if cells is not None else [])
            best[name] = (None if len(t) == 0 else
                          t.loc[t.nc_w_mean.astype(float).idxmax(), keys].to_dict())
        out.append({"track": track, **best, "runs": int(c.runs), "failed": int(c.failed),
                    "invalid": int(c.invalid)})
    return out


def _fmt_best(b) -> str:
    if b is None:
        return "–"
    loose = " (unsandboxed)" if b.get("unsandboxed", False) else ""
    return (f"{b['solver']}{loose} ({b['observation']} modes, {b['variation']}): "
            + ci_cell(b["nc_w_mean"], b["nc_w_mean_ci_low"], b["nc_w_mean_ci_high"],
                      int(b["nc_w_n"]))
            + f", n={int(b['nc_w_n'])}")


_CSS = """body{font-family:system-ui,sans-serif;max-width:1400px;margin:auto;padding:1em;
color:#222}table{border-collapse:collapse;margin:.4em 0 1.2em;font-size:.85em;max-width:100%}
td,th{border:1px solid #ccc;padding:3px 6px;text-align:right;overflow-wrap:break-word}
th{background:#eee}table.wide th,table.dataframe th,table.dataframe td{overflow-wrap:anywhere}
td.l,th.l{text-align:left}p.trust{background:#fff6d8;padding:.4em}
tr.group td{border-top:2px solid #888}
tr.ref td{color:#666;font-style:italic;background:#f7f7f7}
tr.loose td{background:#fde8e8}.scroll{overflow-x:auto}
img{max-width:100%;display:block;margin:.3em 0 1em;border:1px solid #eee}
nav a{margin-right:.8em}.note{color:#555;font-size:.9em;max-width:75em}
figure{margin:0}figcaption{font-size:.85em;color:#444}"""


KEPT = " (kept from the earlier build: the run's cache it was drawn from is not here)"


def _earlier_figures(out: Path, owned: set[str]) -> list[tuple[str, str, str]]:
    """(track, caption, rel path) of the figures an earlier build listed in ``out``'s manifest
    that are still there as plain files it wrote."""
    try:
        listed = json.loads((out / MANIFEST).read_text()).get("figures", [])
    except (OSError, ValueError, AttributeError):
        return []
    return [(str(t), str(c), str(r)) for t, c, r in
            (x for x in listed if isinstance(x, list) and len(x) == 3)
            if str(r) in owned and (out / str(r)).is_file() and not (out / str(r)).is_symlink()]


def build(results: str | Path, out: str | Path = "leaderboard", overwrite: bool = False,
          keep_figures: bool = False) -> Path:
    """Write the leaderboard of ``results`` (a table or a run folder) into ``out``.

    Refuses an ``out`` holding files it did not write (see :func:`prepare_output`) unless
    ``overwrite``; then writes and removes only its own files. ``keep_figures``: figures an
    earlier build of ``out`` drew that this one cannot (their run's cache is not beside the
    table) are kept and shown, their caption saying so; otherwise they are removed."""
    import tempfile

    from ..io.files import write_json, write_text
    from .plots import Styles

    results = Path(results)
    source = results / "results.parquet" if results.is_dir() else results
    out = Path(out)
    owned = prepare_output(out, source, overwrite)
    df, run_dir = checked_table(results)
    headroom = read_headroom(df, results)
    base = results if results.is_dir() else results.parent
    styles = Styles(df.solver.unique(), df.observation.unique())
    tracks = suite_track_order(results, list(dict.fromkeys(df.track)))

    groups = ranking(df)
    rows = summary(df, groups)
    paired = {m: _page_order(paired_table(df, m, seed=SEED), df) for m, _ in RANK_METRICS}
    out.mkdir(parents=True, exist_ok=True)
    (out / "figures").mkdir(exist_ok=True)
    figs: dict[str, list] = {}
    with tempfile.TemporaryDirectory(prefix=".vvtbench-figures-", dir=out) as tmp:
        tmp = Path(tmp)
        for track in tracks:
            figs[track] = []
            for fn in (curve_figures, field_figures):
                try:
                    figs[track] += fn(df, track, base, tmp, "figures", styles)
                except Exception as error:  # a figure must not stop the leaderboard
                    print(f"warning: {track} {fn.__name__}: {type(error).__name__}: {error}",
                          file=sys.stderr)
        written = {"README.md", "index.html", "results.csv", MANIFEST}
        for track in tracks:
            for _, rel in figs[track]:
                os.replace(tmp / Path(rel).name, out / rel)  # atomic, replaces a link itself
                written.add(rel)
    if keep_figures:
        for track, caption, rel in _earlier_figures(out, owned):
            if track in figs and rel not in written:
                figs[track].append((caption if caption.endswith(KEPT) else caption + KEPT,
                                    rel))
                written.add(rel)

    md, page, tracks_json = _pages(df, results, run_dir, tracks, groups, rows, paired, figs,
                                   headroom)
    write_text(out / "README.md", "\n".join(md))
    write_text(out / "index.html", page)
    write_text(out / "results.csv", df.to_csv(index=False))
    for stale in sorted(owned - written):  # own files of an earlier build, no longer made
        p = out / stale
        if p.is_file() or p.is_symlink():
            p.unlink()
    write_json(out / MANIFEST, {
        "generator": "vvtbench", "vvtbench": __version__, "source": str(results),
        "files": sorted(written),
        "figures": [[t, c, r] for t in tracks for c, r in figs[t]],
        "statistics": {"interval": "percentile bootstrap over instances", "level": LEVEL,
                       "n_boot": N_BOOT, "seed": SEED, "instance": ["scene", "seed"],
                       "cell": ["track", "observation", "variation", "solver"],
                       "track_order": "the suite file's (run.json beside the table), else "
                                      "first appearance in the results table",
                       "legend": LEGEND, "min_rank_n": MIN_RANK_N,
                       "ties": TIE_RULE.format(min_n=MIN_RANK_N)},
        "recomputed": run_dir is not None,
        "ceilings": None if headroom is None else str(headroom[0]),
        "tracks": tracks_json})
    return out


def checked_table(results: str | Path):
    """The results table of ``results`` (a table or a run folder) and its run folder when
    its scores were recomputed from the run's cache (None when there is no cache beside it).

    Raises
    ------
    LeaderboardError
        The table fails :func:`vvtbench.bench.check_results` (the first problem is named), has
        no valid scored row (``status`` ok with a finite ``nc_w``), or a score recomputed
        from the cache (:func:`vvtbench.bench.rescore.rescore`) differs from the table's.
    """
    from ..bench import check_results, read_results
    from ..bench.rescore import has_cache, rescore

    results = Path(results)
    source = results / "results.parquet" if results.is_dir() else results
    try:
        df = read_results(results)
    except (OSError, ValueError) as error:
        raise LeaderboardError(f"{source}: cannot read the results table: {error}") from None
    problems = check_results(df)
    if problems:
        more = (f" (and {len(problems) - 1} more: `vvtbench check-results {source}` lists "
                "them)") if len(problems) > 1 else ""
        raise LeaderboardError(f"{source}: {problems[0]}{more}")
    if "reference" not in df.columns:
        df = df.assign(reference=False)
    scored = (df.status == "ok") & np.isfinite(df.nc_w.astype(float))
    if not scored.any():
        raise LeaderboardError(f"{source}: no valid scored row (status ok with a finite "
                               f"nc_w) among its {len(df)} rows: nothing to rank")
    run_dir = has_cache(results)
    if run_dir is not None:
        problems = rescore(run_dir, df)
        if problems:
            more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
            raise LeaderboardError(f"{source}: a score does not stand when recomputed from "
                                   f"{run_dir / 'cache'}: {problems[0]}{more}")
    return df, run_dir


def _tied_with(groups, b) -> list[str]:
    """The other solvers sharing the rank of the summary cell ``b``."""
    for track, obs, t in groups:
        if obs != b["observation"]:
            continue
        row = t[(t.variation == b["variation"]) & (t.solver == b["solver"])]
        if len(row) and row["rank"].iloc[0] is not None:
            same = t[(t.variation == b["variation"]) & (t["rank"] == row["rank"].iloc[0])
                     & (t.solver != b["solver"])]
            if len(same) and track == row.track.iloc[0]:
                return [str(x) for x in same.solver]
    return []


def solver_versions(df) -> str:
    """One sentence naming the version of every solver in the table; a solver whose rows come
    from several versions says so, with the number of rows of each.

    >>> import pandas as pd
    >>> solver_versions(pd.DataFrame({"solver": ["a", "b", "b"],
    ...                               "solver_version": ["1.0", "1.0", "2.0"]}))
    'Solver versions: a 1.0; b 1.0 (1 row) and 2.0 (1 row): rows of several versions.'
    """
    if "solver_version" not in df:
        return "Solver versions: not recorded in this table."
    parts = []
    for solver in sorted(df.solver.unique()):
        counts = df.loc[df.solver == solver, "solver_version"].fillna("?").astype(str)
        counts = counts.value_counts().sort_index()
        if len(counts) == 1:
            parts.append(f"{solver} {counts.index[0]}")
        else:
            listed = " and ".join(f"{v} ({n} row{'s' if n != 1 else ''})"
                                  for v, n in counts.items())
            parts.append(f"{solver} {listed}: rows of several versions")
    return "Solver versions: " + "; ".join(parts) + "."


def board_title(rows: list[dict]) -> tuple[str, str]:
    """The page's title, and a sentence saying so when the table ranks nothing.

    A table in which no track has a ranked solver (fewer than ``MIN_RANK_N`` valid instances
    everywhere) reproduces experiments; it is not a ranking, and its title says so.

    >>> board_title([{"best": None}])[0]
    'vvtbench results: a reproduction, not a ranking'
    >>> board_title([{"best": {"solver": "vvt"}}])
    ('vvtbench leaderboard', '')
    """
    if any(r.get("best") for r in rows):
        return "vvtbench leaderboard", ""
    return ("vvtbench results: a reproduction, not a ranking",
            f"No track of this table has {MIN_RANK_N} valid instances of a solver, so it "
            "ranks nothing: it reproduces experiments (means per setting, with n), and a "
            "difference between two solvers here is not a result. Rankings are on boards "
            "whose tracks draw enough instances (leaderboard/standard).")


def _pages(df, results, run_dir, tracks, groups, rows, paired, figs, headroom=None):
    """(README.md lines, index.html text, the tracks' statistics for leaderboard.json);
    ``headroom``: :func:`read_headroom`'s, a section per track that has ceilings."""
    n_failed = int((df.status == "error").sum())
    n_invalid = int((df.status == "invalid").sum())
    trust = RECOMPUTED if run_dir is not None else NOT_RECOMPUTED
    loose = _unsandboxed(df)
    if loose.any():
        names = ", ".join(dict.fromkeys(df.loc[loose, "solver"].astype(str)))
        trust += " " + UNSANDBOXED.format(n=int(loose.sum()), solvers=names)
    intro = (f"{len(df)} runs ({n_failed} failed, {n_invalid} invalid: counted, never "
             f"ranked or scored) of {df.solver.nunique()} solvers on {len(tracks)} tracks, "
             f"from {results}, by vvtbench {__version__}. {SCORE_SENTENCE} Solvers are "
             "ranked per track, observation source and variation by mean NC w over the "
             "valid instances; a solver whose paired interval against the one above it "
             "includes 0 shares its rank (1=); with fewer than "
             f"{MIN_RANK_N} instances a solver shows its mean and n only: too few instances "
             "to rank. Reference solvers (they saw the truth; a reference, not a bound: "
             "a ranked solver may score above one) are shown apart, last, and never "
             "ranked. The method is at the end of the page. " + solver_versions(df))
    board_name, reproduction = board_title(rows)
    if reproduction:
        intro = reproduction + " " + intro
    md = [f"# {board_name}\n", f"**{trust}**\n", intro + "\n", "## Summary\n",
          f"| track | ranked first: NC w mean [{_PCT} CI] | tied with | reference: NC w mean "
          f"[{_PCT} CI] | runs | failed | invalid |", "|---|---|---|---|---|---|---|"]
    summary_rows = []
    for r in rows:
        tied = ", ".join(_tied_with(groups, r["best"])) if r["best"] else ""
        first = (_fmt_best(r["best"]) if r["best"] else
                 f"none ranked (fewer than {MIN_RANK_N} instances or valid runs)")
        cells = [first, tied or "–", _fmt_best(r["reference"]),
                 str(r["runs"]), str(r["failed"]), str(r["invalid"])]
        md.append(f"| [{md_cell(r['track'])}](#{_slug(r['track'])}) | "
                  + " | ".join(md_cell(c) for c in cells) + " |")
        summary_rows.append((r["track"], cells))
    md.append("")
    body, tracks_json = [], []
    for track in tracks:
        md.append(f'<a id="{_slug(track)}"></a>\n\n## {md_cell(track)}\n')
        body.append(f'<section id="{_slug(track)}"><h2>{html.escape(track)}</h2>')
        ranked = []
        for tr, obs, t in groups:
            if tr != track:
                continue
            title = f"{track} — {obs} modes: ranking by mean NC w"
            head, trows = _ranking_rows(t)
            md.append(f"### {md_cell(title)}\n\n" + _md(head, trows) + "\n")
            body.append(f"<h3>{html.escape(title)}</h3>" + _html(head, trows, left=3))
            ranked.append((obs, t))
        p = paired["nc_w"][paired["nc_w"].track == track]
        if len(p):
            head, prows = _paired_rows(p)
            title = f"{track} — paired comparisons, NC w (same instances)"
            md.append(f"### {md_cell(title)}\n\n" + _md(head, prows) + "\n")
            body.append(f"<h3>{html.escape(title)}</h3>" + _html(head, prows, left=4))
        room = headroom_section(headroom, df, track)
        if room is not None:
            md.append(room[0])
            body.append(room[1])
        for obs, t in ranked:
            head, drows = _detail_rows(t)
            title = f"{track} — {obs} modes: medians, other metrics, runtime"
            md.append(f"### {md_cell(title)}\n\n" + _md(head, drows) + "\n")
            body.append(f"<h3>{html.escape(title)}</h3>" + _html(head, drows, left=2, wide=True))
        tracks_json.append({
            "track": track,
            "ranking": [rec for _, t in ranked for rec in t.to_dict("records")],
            "paired": {m: paired[m][paired[m].track == track].to_dict("records")
                       for m in paired},
            **({} if room is None else {"headroom": room[2]})})
        for title, frame in (
                ("extractors ranked on the same videos", extractor_ranking(df, track)),
                ("extraction and NC w from each source", extraction_sources(df, track)),
                ("extraction variants against their base (paired, same videos)",
                 extraction_variants(df, track)),
                ("extraction (detected modes against the true ones)",
                 extraction_table(df, track))):
            if frame is not None:
                md.append(f"### {md_cell(track)} — {title}\n\n" + _md_frame(frame) + "\n\n"
                          + RULER_NOTE + "\n")
                body.append(f"<h3>{html.escape(track)} — {html.escape(title)}</h3>"
                            + '<div class="scroll">'
                            + frame.to_html(index=False, float_format=number_text,
                                            na_rep="–", border=0) + "</div>"
                            + f"<p>{html.escape(RULER_NOTE)}</p>")
        for caption, rel in figs[track]:
            md.append(f"**{md_cell(track)}: {md_cell(caption)}**\n\n"
                      f"![{md_cell(track)}: {md_cell(caption)}]({rel})\n")
            body.append(f"<figure><figcaption>{html.escape(track)}: {html.escape(caption)}"
                        f"</figcaption><img src=\"{html.escape(rel)}\" alt=\""
                        f"{html.escape(track)}: {html.escape(caption)}\">"
                        "</figure>")
        body.append("</section>")
    method = (f"{LEGEND} Solvers are ranked by mean NC of w; a solver valid on fewer than "
              f"{MIN_VALID_FRACTION:.0%} of its runs in a cell, or without a valid NC w, is "
              "not ranked (–).")
    md += ["## Method\n", method.replace("|", "\\|") + "\n"]
    summary_html = _html(["track", f"ranked first: NC w mean [{_PCT} CI]", "tied with",
                          f"reference: NC w mean [{_PCT} CI]", "runs", "failed", "invalid"],
                         [([track, *cells], "") for track, cells in summary_rows], left=4)
    for track, _ in summary_rows:  # link each track's name to its section
        cell = f'<td class="l">{html.escape(track)}</td>'
        summary_html = summary_html.replace(
            cell, f'<td class="l"><a href="#{_slug(track)}">{html.escape(track)}</a></td>', 1)
    nav = "".join(f"<a href=\"#{_slug(t)}\">{html.escape(t)}</a>" for t in tracks)
    page = f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>{html.escape(board_name)}</title><link rel="icon" href="data:,">
<style>{_CSS}</style></head><body>
<h1>{html.escape(board_name)}</h1>
<p class="trust"><b>{html.escape(trust)}</b></p>
<p>{html.escape(intro)} Data: <a href="results.csv">results.csv</a>.</p>
<nav>{nav} <a href="#method">method</a></nav><h2>Summary</h2>{summary_html}
{''.join(body)}
<section id="method"><h2>Method</h2><p class="note">{html.escape(method).replace("`", "")}
</p></section>
</body></html>
"""
    return md, page, tracks_json


def suite_track_order(results: str | Path, tracks: list[str]) -> list[str]:
    """``tracks`` in the suite file's order, read from the run's ``run.json`` (beside the
    results table, or in the run folder given); tracks it does not list keep their order of
    first appearance, after the listed ones."""
    p = Path(results)
    run_json = p / "run.json" if p.is_dir() else p.parent / "run.json"
    try:
        listed = json.loads(run_json.read_text()).get("tracks", [])
    except (OSError, ValueError, AttributeError):
        listed = []  # no run.json (a table from elsewhere): first appearance
    order = [t for t in listed if isinstance(t, str) and t in tracks] if isinstance(
        listed, list) else []
    return order + [t for t in tracks if t not in order]


def _md_frame(t) -> str:
    def cell(x):
        return number_text(x) if isinstance(x, float) else str(x)

    lines = ["| " + " | ".join(map(md_cell, t.columns)) + " |", "|" + "---|" * len(t.columns)]
    lines += ["| " + " | ".join(md_cell(cell(x)) for x in row) + " |"
              for row in t.itertuples(index=False)]
    return "\n".join(lines)


#: What the extraction columns measure against the physical limit.
RULER_NOTE = ("A true mode is detectable when its Cramér-Rao-limited SNR over the visible "
              "pixels in the recorded length exceeds the sample's threshold (docs/dataset.md, "
              "'The Cramér–Rao ruler'): recall (detectable) below 1 is how far an extractor "
              "is from what the video physically allows; recall (all in band) also counts the "
              "modes below that limit, which no extractor is expected to find. Frequency and "
              "damping efficiency: the Cramér-Rao bound of each one-to-one matched, detectable "
              "mode's frequency (damping ratio) over its squared error, 1 / mean(error^2 / "
              "CRB) over those modes (docs/metrics.md, 'Efficiency of an extraction'): 1 at "
              "the bound, 0.01 a mean squared error 100 times it; blank where no mode of the "
              "video qualifies (a forced response, several views pooled, an undamped scene's "
              "damping).")

_EXTRACTION_NAMES = {"extraction_precision": "precision",
                     "extraction_recall": "recall (detectable)",
                     "extraction_recall_all": "recall (all in band)",
                     "extraction_mean_rel_freq_error": "freq error (rel.)",
                     "extraction_median_rel_damping_error": "damping error (median rel.)",
                     "extraction_frequency_efficiency": "frequency efficiency",
                     "extraction_damping_efficiency": "damping efficiency",
                     "extraction_mean_mac": "mean MAC"}
#: the extraction scores of the per-source and paired variant tables
_SOURCE_METRICS = {"extraction_precision": "precision",
                   "extraction_recall": "recall (detectable)",
                   "extraction_median_rel_damping_error": "damping error",
                   "extraction_frequency_efficiency": "frequency efficiency",
                   "extraction_damping_efficiency": "damping efficiency"}
#: a video of a track: one extraction per scene, variation and seed
_VIDEO = ["scene", "variation", "seed"]


def _extractions(df, track: str):
    """(one row per extraction of ``track`` with the extraction columns, the columns), or
    None when the track has no extraction scores.

    An extraction is a source, scene, variation and seed; variations of one video whose
    scores are all equal are one extraction scored once (a sweep over the number of modes
    or of views re-uses the extraction of the sample's video), kept under its first
    variation, with every variation it stands for in ``variations``: counting it once per
    variation would make one video look like several."""
    from ..bench.suite import observation_kind

    cols = [c for c in _EXTRACTION_NAMES if c in df.columns]
    if "extraction_recall" not in cols:
        return None
    d = df[(df.track == track)
           & df.observation.map(lambda o: observation_kind(str(o)) == "extracted")]
    d = d.dropna(subset=["extraction_recall"])
    if d.empty:
        return None
    keys = ["observation"] + [k for k in _VIDEO if k in d.columns]
    t = d.groupby(keys, sort=False)[cols].first().reset_index()
    same = [k for k in keys if k != "variation"] + cols
    if "variation" in t.columns:
        filled = t[same].astype(object).where(t[same].notna(), "nan").astype(str)
        group = filled.apply(tuple, axis=1)
        names = t.groupby(group, sort=False).variation.agg(lambda v: ", ".join(map(str, v)))
        t = t[~group.duplicated()].assign(variations=group[~group.duplicated()].map(names))
    return t.reset_index(drop=True), cols


def extraction_table(df, track: str):
    """Per scene of ``track`` and extracted source: the extraction's precision, recall over
    the true modes detectable in the video, recall over every true mode in band, relative
    frequency error and mean MAC of matched modes (one extraction per scene and variation),
    then per source their mean over the scenes with its bootstrap interval; an
    ``observation`` column only when the track extracts with several extractors. None when
    the track has no extracted modes."""
    got = _extractions(df, track)
    if got is None:
        return None
    t, cols = got
    if "variations" in t.columns:
        t = t.assign(variation=t.pop("variations"))
    if "seed" in t.columns and t.seed.nunique() <= 1:  # one video per scene and variation
        t = t.drop(columns="seed")
    blank = {k: "" for k in ("variation", "seed") if k in t.columns}
    sources = list(dict.fromkeys(t.observation))
    parts = []
    for src in sources:
        ts = t[t.observation == src]
        if len(ts) > 1:
            label = f"mean of {len(ts)}" + (f" [{_PCT} CI]" if len(ts) >= MIN_RANK_N else "")
            ts = _with_row(ts, {"observation": src, "scene": label,
                                **blank, **{c: _stat_cell(ts[c]) for c in cols}})
        parts.append(ts)
    import pandas as pd

    t = pd.concat([p.astype(object) for p in parts], ignore_index=True)
    if len(sources) == 1:
        t = t.drop(columns="observation")
    return t.rename(columns=_EXTRACTION_NAMES)


def extractor_ranking(df, track: str):
    """Extractors of ``track`` ranked on the same videos (None with fewer than two extracted
    sources): per source its extractor, the number of videos, the mean F1 of detection
    (harmonic mean of precision and recall over the detectable modes) and its difference from
    the best source on the videos both scored (paired, bootstrap interval), then the mean of
    each extraction metric; sorted by mean F1."""
    got = _extractions(df, track)
    if got is None:
        return None
    t, cols = got
    t = t.drop(columns="variations", errors="ignore")
    sources = list(dict.fromkeys(t.observation))
    if len(sources) < 2:
        return None
    from ..scoring.extraction import f1_score
    from ..scoring.stats import paired_comparison

    t = t.assign(f1=f1_score(t.extraction_precision, t.extraction_recall))
    video = [k for k in _VIDEO if k in t.columns]
    per = {s: t[t.observation == s].set_index(video).f1 for s in sources}
    order = sorted(sources, key=lambda s: -np.nan_to_num(np.nanmean(per[s]), nan=-1))
    best = order[0]
    rows = []
    for src in order:
        ts = t[t.observation == src]
        row = {"observation": src,
               "extractor": _extractor_label(src),
               "videos": len(ts), "F1": _stat_cell(ts.f1)}
        if src == best:
            row[f"ΔF1 vs {best}"] = "–"
        else:
            a, b = per[src].align(per[best], join="inner")
            pc = paired_comparison(a.to_numpy(), b.to_numpy())
            row[f"ΔF1 vs {best}"] = (
                f"{number_text(pc['mean_diff'], sign=True)} [{number_text(pc['ci_low'], 2, True)}, "
                f"{number_text(pc['ci_high'], 2, True)}] ({pc['n']})"
                if np.isfinite(pc["ci_low"]) and pc["n"] >= MIN_RANK_N
                else f"{number_text(pc['mean_diff'], sign=True)} ({pc['n']})")
        rows.append(row | {_EXTRACTION_NAMES[c]: _stat_cell(ts[c]) for c in cols})
    import pandas as pd

    return pd.DataFrame(rows).astype(object)


def _extractor_label(source: str) -> str:
    """The extractor of an extracted source, with its extraction variant.

    >>> _extractor_label("extracted"), _extractor_label("extracted:farneback@picker")
    ('phase (default)', 'farneback, variant picker')
    """
    from ..bench.suite import observation_extractor, observation_variant

    variant = observation_variant(source)
    return ((observation_extractor(source) or "phase (default)")
            + (f", variant {variant}" if variant else ""))


def _stat_cell(values) -> str:
    """The mean of the finite ``values`` with its bootstrap interval (from
    :data:`~vvtbench.scoring.stats.MIN_RANK_N` values on, as on the ranking tables) and, when
    some are undefined, over how many: ``0.812 [0.74, 0.88]``, ``0.10 (n=3 of 4)``; ``–``
    when none is finite (an undefined metric is never a number)."""
    from ..scoring.stats import summarize

    x = np.asarray(values, dtype=float)
    st = summarize(x)
    if st["n"] == 0:
        return "–"
    cell = number_text(st["mean"])
    if np.isfinite(st["mean_ci_low"]) and st["n"] >= MIN_RANK_N:
        cell += f" [{number_text(st['mean_ci_low'], 2)}, {number_text(st['mean_ci_high'], 2)}]"
    return cell + (f" (n={st['n']} of {x.size})" if st["n"] < x.size else "")


def _diff_cell(a, b) -> str:
    """``a - b`` paired over the items where both are finite: the mean difference, its
    bootstrap interval (from :data:`~vvtbench.scoring.stats.MIN_RANK_N` pairs on) and the
    number of pairs (``+0.120 [+0.05, +0.19] (n=8)``); ``–`` when no pair is finite."""
    from ..scoring.stats import paired_comparison

    pc = paired_comparison(np.asarray(a, dtype=float), np.asarray(b, dtype=float))
    if pc["n"] == 0:
        return "–"
    ci = (f" [{number_text(pc['ci_low'], 2, True)}, {number_text(pc['ci_high'], 2, True)}]"
          if np.isfinite(pc["ci_low"]) and pc["n"] >= MIN_RANK_N else "")
    return f"{number_text(pc['mean_diff'], sign=True)}{ci} (n={pc['n']})"


def _source_frames(df, track: str):
    """(per extracted source of ``track``: its videos with the extraction scores, indexed by
    scene, variation and seed; per source and solver: its valid NC w over the same index; the
    solvers) or None when the track has no extraction scores."""
    from ..bench.suite import observation_kind

    if "extraction_recall" not in df.columns:
        return None
    d = df[(df.track == track)
           & df.observation.map(lambda o: observation_kind(str(o)) == "extracted")]
    if d.empty or d.extraction_recall.isna().all():
        return None
    cols = [c for c in _SOURCE_METRICS if c in d.columns]
    ok = d[d.status == "ok"]
    scores, nc = {}, {}
    for src, ds in d.groupby("observation", sort=False):
        scores[src] = ds.dropna(subset=["extraction_recall"]).groupby(_VIDEO)[cols].first()
        for solver, dv in ok[ok.observation == src].groupby("solver", sort=False):
            nc[(src, solver)] = dv.groupby(_VIDEO).nc_w.first()
    solvers = _solver_order(d)[::-1]  # competitors by name, then the references
    return scores, nc, solvers


def _variation_groups(index, order: list) -> list[str]:
    """The variations of ``index`` in ``order`` (the table's, i.e. the suite's: n_modes=8
    before n_modes=10), any not in it after them."""
    present = set(index.get_level_values("variation"))
    return ([v for v in order if v in present]
            + sorted(present.difference(order), key=str))


def extraction_sources(df, track: str):
    """Per extracted source of ``track`` (and variation, when it has several): the videos,
    the means over them of precision, recall over the detectable modes and the median relative
    damping error of the matched modes (undamped truth: ``–``), then each solver's mean NC w
    from that source over its valid instances; every mean with its bootstrap interval. None
    when the track has no extraction scores."""
    got = _source_frames(df, track)
    if got is None:
        return None
    scores, nc, solvers = got
    variations = list(dict.fromkeys(df[df.track == track].variation))
    rows = []
    for src, t in scores.items():
        for var in _variation_groups(t.index, variations):
            tv = t.xs(var, level="variation", drop_level=False)
            row = {"observation": src, "variation": var, "videos": len(tv)}
            row |= {name: _stat_cell(tv[c]) if c in tv else "–"
                    for c, name in _SOURCE_METRICS.items()}
            for solver in solvers:
                s = nc.get((src, solver))
                vals = [] if s is None else s[s.index.get_level_values("variation") == var]
                row[f"NC w {solver}"] = _stat_cell(vals) if len(vals) else "–"
            rows.append(row)
    import pandas as pd

    t = pd.DataFrame(rows).astype(object)
    return t.drop(columns="variation") if len(variations) < 2 else t


def extraction_variants(df, track: str):
    """Each extraction variant of ``track`` (``extracted@NAME``) against its base (the same
    source without ``@NAME``), paired over the same videos (scene, variation, seed): per
    variation, the mean difference variant - base of precision, recall over the detectable
    modes, the median relative damping error and each solver's NC w, with its bootstrap
    interval and the number of pairs. None when no variant has its base in the track."""
    from ..bench.suite import observation_base, observation_variant

    got = _source_frames(df, track)
    if got is None:
        return None
    scores, nc, solvers = got
    variations = list(dict.fromkeys(df[df.track == track].variation))
    rows = []
    for src, t in scores.items():
        base = observation_base(src)
        if observation_variant(src) is None or base not in scores:
            continue
        a, b = t.align(scores[base], join="inner")
        for var in _variation_groups(a.index, variations) if len(a) else []:
            at = a.index.get_level_values("variation") == var
            row = {"observation": src, "against": base, "variation": var,
                   "videos": int(at.sum())}
            row |= {f"Δ {name}": _diff_cell(a.loc[at, c], b.loc[at, c]) if c in a else "–"
                    for c, name in _SOURCE_METRICS.items()}
            for solver in solvers:
                x, y = nc.get((src, solver)), nc.get((base, solver))
                if x is None or y is None:
                    row[f"Δ NC w {solver}"] = "–"
                    continue
                x, y = x.align(y, join="inner")
                on = x.index.get_level_values("variation") == var
                row[f"Δ NC w {solver}"] = _diff_cell(x[on], y[on])
            rows.append(row)
    if not rows:
        return None
    import pandas as pd

    t = pd.DataFrame(rows).astype(object)
    return t.drop(columns="variation") if len(variations) < 2 else t


def _with_row(t, row: dict):
    """``t`` with one more row (object columns where the new row holds text)."""
    import pandas as pd

    return pd.concat([t.astype(object), pd.DataFrame([row])], ignore_index=True)


__all__ = ["LeaderboardError", "build", "extraction_sources", "extraction_table",
           "extraction_variants", "extractor_ranking",
           "prepare_output", "ranking",
           "summary"]
