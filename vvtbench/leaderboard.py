"""The leaderboard: Markdown + static HTML (no server, no external URL) from a results table.

Writes into the output folder (default ``leaderboard/``): ``README.md`` and ``index.html`` (a
summary, then per track in the order of the suite (first appearance in the table) one ranking
table per observation source and the track's figures), ``results.csv`` (a copy of the table),
``figures/`` and ``leaderboard.json``, which marks the folder as written by vvtbench and lists
its files. Figures (:mod:`vvtbench.plots`): NC against each swept value (number of modes, α_v,
geometry scale, ...), intrinsic-resolution curves, and per scene the voxel fields of the truth
and of every solver and observation source (values and contrast views), read from each run's
``fields.npz`` (the ``estimate_path`` column, relative to the results file's folder).

Data safety: the output folder may hold only files listed in its ``leaderboard.json``; a folder
holding other files is refused unless ``overwrite=True``, and even then only the leaderboard's
own files are written or removed. Every file is written atomically (temp file + rename), and
nothing is written through a symbolic link.
"""

from __future__ import annotations

import html
import json
import os
import sys
from pathlib import Path

import numpy as np

from ._version import __version__

RANK_COLUMNS = [("nc_w", "NC w"), ("nc_v", "NC v"), ("nc_at_sigma_star_w", "NC w @ σ*"),
                ("sigma_star_w", "σ* w (vox)"), ("mode_mac", "mode MAC"),
                ("freq_err_scaled", "freq err (scaled)"), ("runtime_s", "runtime (s)")]


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def ranking(df):
    """Per track and observation: solvers ranked by mean NC of w (ties: NC of v) over their
    valid rows. Reference solvers (``reference``: they saw the truth) are not ranked: they are
    listed after the ranked ones, with a note when a ranked solver is above them."""
    import pandas as pd

    if "reference" not in df.columns:
        df = df.assign(reference=False)
    ok = df[df.status == "ok"]
    groups = []
    keys = list(dict.fromkeys(zip(df.track, df.observation, strict=True)))
    order = {t: i for i, t in enumerate(dict.fromkeys(df.track))}
    keys.sort(key=lambda k: (order[k[0]], {"true": 0, "extracted": 1}.get(k[1], 2), k[1]))
    for track, obs in keys:
        g = df[(df.track == track) & (df.observation == obs)]
        gok = ok[(ok.track == track) & (ok.observation == obs)]
        agg = gok.groupby("solver")[[c for c, _ in RANK_COLUMNS]].mean(numeric_only=True)
        counts = g.groupby("solver").size().rename("runs")
        errs = g[g.status == "error"].groupby("solver").size().rename("errors")
        bad = g[g.status == "invalid"].groupby("solver").size().rename("invalid")
        ref = g.groupby("solver")["reference"].any().rename("reference")
        t = pd.concat([agg, counts, errs, bad, ref], axis=1).fillna(
            {"errors": 0, "invalid": 0})
        t[["errors", "invalid"]] = t[["errors", "invalid"]].astype(int)
        t = t.sort_values(["reference", "nc_w", "nc_v"], ascending=[True, False, False],
                          na_position="last")
        best = t[~t.reference.astype(bool)]["nc_w"].max()
        t["note"] = [f"below a ranked solver (NC w {best:.3f})"
                     if r.reference and np.isfinite(best) and r.nc_w < best else ""
                     for r in t.itertuples()]
        groups.append((track, obs, t))
    return groups


def _cells(t):
    """(rank, solver label, formatted values, runs, errors, invalid) of each table row."""
    rank = 0
    for solver, r in t.iterrows():
        if r["reference"]:
            label, shown = f"{solver} (reference)", "ref"
        else:
            rank += 1
            label, shown = solver, str(rank)
        if r["note"]:
            label += f" -- {r['note']}"
        vals = [f"{r[c]:.3f}" if np.isfinite(r[c]) else "–" for c, _ in RANK_COLUMNS]
        yield shown, label, vals, int(r["runs"]), int(r["errors"]), int(r["invalid"])


_HEAD = ["rank", "solver", *[label for _, label in RANK_COLUMNS], "runs", "errors", "invalid"]


def _md_table(t) -> str:
    lines = ["| " + " | ".join(_HEAD) + " |", "|" + "---|" * len(_HEAD)]
    for rank, label, vals, runs, errs, bad in _cells(t):
        lines.append(f"| {rank} | {label} | " + " | ".join(vals) + f" | {runs} | {errs} | {bad} |")
    return "\n".join(lines)


def _html_table(t) -> str:
    rows = ["<tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in _HEAD) + "</tr>"]
    for rank, label, vals, runs, errs, bad in _cells(t):
        cls = ' class="ref"' if rank == "ref" else ""
        rows.append(f"<tr{cls}>" + "".join(f"<td>{html.escape(str(x))}</td>" for x in
                                           [rank, label, *vals, runs, errs, bad]) + "</tr>")
    return "<table>" + "".join(rows) + "</table>"


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


def field_figures(df, track: str, base: Path, folder: Path, rel_dir: str, styles) -> list:
    """Per scene of ``track``: the truth and every solver × observation source of the shown
    variation and first seed, values and contrast views. Returns [(caption, rel path)]."""
    from .plots import plot_field_grids

    d = df[(df.track == track) & (df.status == "ok")]
    if d.empty or "estimate_path" not in d:
        return []
    variation = shown_variation(d)
    out = []
    for n, scene in enumerate(dict.fromkeys(d.scene)):
        ds = d[(d.scene == scene) & (d.variation == variation)]
        if ds.empty:
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
                notes[label] = f"NC w {r.nc_w:.2f}, v {r.nc_v:.2f}"
        if not estimates or truth is None:
            continue
        stem = f"{_slug(track)}_slices" + ("" if n == 0 else f"_{_slug(scene)}")
        seed = ds.seed.iloc[0]
        for normalized, suffix, what in ((False, "", "values"),
                                         (True, "_normalized", "contrast to the matrix")):
            rel = f"{rel_dir}/{stem}{suffix}.png"
            plot_field_grids(folder / Path(rel).name, truth[0], truth[1], estimates,
                             normalized=normalized, notes=notes,
                             title=f"{track}: {scene} [{variation}, seed {seed}]")
            out.append((f"{scene} [{variation}]: fields, {what}", rel))
    return out


def curve_figures(df, track: str, base: Path, folder: Path, rel_dir: str, styles) -> list:
    """NC against every swept value of the track and the intrinsic-resolution curves."""
    from .metrics import intrinsic_resolution
    from .plots import plot_intrinsic_resolution, plot_sweep, sweep_keys

    d = df[df.track == track]
    out = []
    for key in sweep_keys(d):
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
            ir = intrinsic_resolution(z[field], z[f"{field}_true"])
            c[field].append(ir["nc"])
            c["sigmas"] = ir["sigmas"]
    rel = f"{rel_dir}/{_slug(track)}_intrinsic_resolution.png"
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
def summary(df) -> list[dict]:
    """Per track (first-appearance order): the best ranked (non-reference) solver and
    observation by mean NC of w, the best reference, and the counts of runs, failed and
    invalid rows."""
    out = []
    groups = ranking(df)
    for track in dict.fromkeys(df.track):
        g = df[df.track == track]
        best = ref = None
        for tr, obs, t in groups:
            if tr != track:
                continue
            ranked = t[~t.reference.astype(bool) & np.isfinite(t.nc_w)]
            if len(ranked) and (best is None or ranked.nc_w.iloc[0] > best[2]):
                best = (ranked.index[0], obs, float(ranked.nc_w.iloc[0]))
            refs = t[t.reference.astype(bool) & np.isfinite(t.nc_w)]
            if len(refs) and (ref is None or refs.nc_w.max() > ref[2]):
                ref = (refs.nc_w.idxmax(), obs, float(refs.nc_w.max()))
        out.append({"track": track, "best": best, "reference": ref, "runs": len(g),
                    "failed": int((g.status == "error").sum()),
                    "invalid": int((g.status == "invalid").sum())})
    return out


def _fmt_best(b) -> str:
    return "–" if b is None else f"{b[0]} ({b[1]} modes): {b[2]:.3f}"


_CSS = """body{font-family:system-ui,sans-serif;max-width:1250px;margin:auto;padding:1em;
color:#222}table{border-collapse:collapse;margin:.4em 0 1.2em;font-size:.9em}
td,th{border:1px solid #ccc;padding:3px 8px;text-align:right}th{background:#eee}
td:nth-child(2){text-align:left}tr.ref td{color:#666;font-style:italic;background:#f7f7f7}
img{max-width:100%;display:block;margin:.3em 0 1em;border:1px solid #eee}
nav a{margin-right:.8em}.note{color:#555;font-size:.9em}
figure{margin:0}figcaption{font-size:.85em;color:#444}"""


def build(results: str | Path, out: str | Path = "leaderboard", overwrite: bool = False) -> Path:
    """Write the leaderboard of ``results`` (a table or a run folder) into ``out``.

    Refuses an ``out`` holding files it did not write (see :func:`prepare_output`) unless
    ``overwrite``; then writes and removes only its own files."""
    import tempfile

    from .bench import check_results, read_results
    from .io import write_json, write_text
    from .plots import Styles

    results = Path(results)
    source = results / "results.parquet" if results.is_dir() else results
    out = Path(out)
    owned = prepare_output(out, source, overwrite)
    df = read_results(results)
    if "reference" not in df.columns:
        df = df.assign(reference=False)
    base = results if results.is_dir() else results.parent
    problems = check_results(df)
    styles = Styles(df.solver.unique(), df.observation.unique())
    tracks = list(dict.fromkeys(df.track))

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

    rows = summary(df)
    n_failed = int((df.status == "error").sum())
    n_invalid = int((df.status == "invalid").sum())
    intro = (f"Generated by vvtbench {__version__} from `{results}`: {len(df)} runs "
             f"({n_failed} failed, {n_invalid} invalid), {df.solver.nunique()} solvers, "
             f"{len(tracks)} tracks. Solvers are ranked per track and observation source by "
             "mean NC of the stiffness field w over the track's valid runs (centered "
             "normalized correlation, docs/metrics.md). Reference solvers (they saw the "
             "truth: an upper bound) are marked `ref` and not ranked; failed and invalid "
             "runs are counted and never ranked.")
    md = ["# vvtbench leaderboard\n", intro + "\n"]
    if problems:
        md.append("**Schema problems:** " + "; ".join(problems[:5]) + "\n")
    md.append("## Summary\n")
    md.append("| track | best ranked solver: NC w | reference: NC w | runs | failed | invalid |")
    md.append("|---|---|---|---|---|---|")
    for r in rows:
        md.append(f"| [{r['track']}](#{_slug(r['track'])}) | {_fmt_best(r['best'])} | "
                  f"{_fmt_best(r['reference'])} | {r['runs']} | {r['failed']} | "
                  f"{r['invalid']} |")
    md.append("")
    body = []
    groups = ranking(df)
    for track in tracks:
        md.append(f'<a id="{_slug(track)}"></a>\n\n## {track}\n')
        body.append(f'<section id="{_slug(track)}"><h2>{html.escape(track)}</h2>')
        for tr, obs, t in groups:
            if tr != track:
                continue
            md.append(f"### {track} — {obs} modes\n\n" + _md_table(t) + "\n")
            body.append(f"<h3>{html.escape(track)} — {html.escape(obs)} modes</h3>"
                        + _html_table(t))
        ext = extraction_table(df, track)
        if ext is not None:
            md.append(f"### {track} — extraction (detected modes against the true ones)\n\n"
                      + _md_frame(ext) + "\n")
            body.append(f"<h3>{html.escape(track)} — extraction</h3>"
                        + ext.to_html(index=False, float_format=lambda x: f"{x:.3f}",
                                      na_rep="–", border=0))
        for caption, rel in figs[track]:
            md.append(f"**{track}: {caption}**\n\n![{track}: {caption}]({rel})\n")
            body.append(f"<figure><figcaption>{html.escape(track)}: {html.escape(caption)}"
                        f"</figcaption><img src=\"{html.escape(rel)}\" alt=\""
                        f"{html.escape(track)}: {html.escape(caption)}\">"
                        "</figure>")
        body.append("</section>")
    summary_html = ("<table><tr><th>track</th><th>best ranked solver: NC w</th>"
                    "<th>reference: NC w</th><th>runs</th><th>failed</th><th>invalid</th></tr>"
                    + "".join(f"<tr><td><a href=\"#{_slug(r['track'])}\">"
                              f"{html.escape(r['track'])}</a></td>"
                              f"<td>{html.escape(_fmt_best(r['best']))}</td>"
                              f"<td>{html.escape(_fmt_best(r['reference']))}</td>"
                              f"<td>{r['runs']}</td><td>{r['failed']}</td>"
                              f"<td>{r['invalid']}</td></tr>" for r in rows) + "</table>")
    schema = ("<p class=\"note\"><b>Schema problems:</b> "
              + html.escape("; ".join(problems[:5])) + "</p>") if problems else ""
    nav = "".join(f"<a href=\"#{_slug(t)}\">{html.escape(t)}</a>" for t in tracks)
    page = f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>vvtbench leaderboard</title><link rel="icon" href="data:,">
<style>{_CSS}</style></head><body>
<h1>vvtbench leaderboard</h1>
<p>{html.escape(intro).replace("`", "")} Data: <a href="results.csv">results.csv</a>.</p>
{schema}<nav>{nav}</nav><h2>Summary</h2>{summary_html}
{''.join(body)}
</body></html>
"""
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
        "figures": [[t, c, r] for t in tracks for c, r in figs[t]]})
    return out


def _md_frame(t) -> str:
    def cell(x):
        return f"{x:.3f}" if isinstance(x, float) and np.isfinite(x) else (
            "–" if isinstance(x, float) else str(x))

    lines = ["| " + " | ".join(map(str, t.columns)) + " |", "|" + "---|" * len(t.columns)]
    lines += ["| " + " | ".join(cell(x) for x in row) + " |" for row in t.itertuples(index=False)]
    return "\n".join(lines)


def extraction_table(df, track: str):
    """Per scene of ``track``: the extraction's precision, recall, relative frequency error
    and mean MAC of matched modes (one extraction per scene and variation; None when the
    track has no extracted modes)."""
    cols = ["extraction_precision", "extraction_recall", "extraction_mean_rel_freq_error",
            "extraction_mean_mac"]
    if not set(cols) <= set(df.columns):
        return None
    d = df[(df.track == track) & (df.observation == "extracted")]
    d = d.dropna(subset=["extraction_recall"])
    if d.empty:
        return None
    t = d.groupby(["scene", "variation"], sort=False)[cols].first().reset_index()
    return t.rename(columns={c: c.replace("extraction_", "").replace("mean_rel_freq_error",
                                                                     "freq error (rel.)")
                             for c in cols} | {"extraction_mean_mac": "mean MAC"})


__all__ = ["LeaderboardError", "build", "extraction_table", "prepare_output", "ranking",
           "summary"]
