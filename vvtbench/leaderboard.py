"""The leaderboard: Markdown + static HTML (no server) from a results table.

Writes into the output folder (default ``leaderboard/``): ``README.md`` (one ranking table per
track), ``index.html`` (the same tables and the figures, images referenced relatively),
``results.csv`` (a copy of the table), and ``figures/``: NC vs number of modes per solver
(per track and observation), intrinsic-resolution curves (NC against the blur sigma of the
truth), and slices of estimated vs true fields (the paper's Fig. 5 style) read from each run's
``fields.npz`` (the ``estimate_path`` column, relative to the results file's folder).
"""

from __future__ import annotations

import html
import json
import shutil
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
    for (track, obs), g in df.groupby(["track", "observation"], sort=True):
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
        rows.append("<tr>" + "".join(f"<td>{html.escape(str(x))}</td>" for x in
                                     [rank, label, *vals, runs, errs, bad]) + "</tr>")
    return "<table>" + "".join(rows) + "</table>"


def plot_nc_vs_modes(df, track: str, path: Path) -> bool:
    d = df[(df.track == track) & (df.status == "ok")]
    if d["n_modes"].nunique() < 2:
        return False
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.4), sharey=True)
    for ax, field in zip(axes, ("w", "v"), strict=True):
        for (solver, obs, scene), g in d.groupby(["solver", "observation", "scene"]):
            m = g.groupby("n_modes")[f"nc_{field}"].mean()
            ax.plot(m.index, m.values, "o-" if obs == "true" else "s--", ms=3,
                    label=f"{solver} ({obs}) {scene}")
        ax.set_xlabel("number of modes")
        ax.set_ylabel(f"NC of {field}")
        ax.grid(alpha=0.3)
    axes[1].legend(fontsize=6, loc="best")
    fig.suptitle(f"{track}: NC vs number of modes", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return True


def plot_intrinsic_resolution(df, track: str, base: Path, path: Path) -> bool:
    from .metrics import intrinsic_resolution

    d = df[(df.track == track) & (df.status == "ok") & df.estimate_path.notna()]
    if d.empty:
        return False
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.4), sharey=True)
    drawn = False
    for ax, field in zip(axes, ("w", "v"), strict=True):
        for (solver, obs), g in d.groupby(["solver", "observation"]):
            curves = []
            for p in g.estimate_path:
                f = base / p
                if not f.is_file():
                    continue
                z = np.load(f)
                ir = intrinsic_resolution(z[field], z[f"{field}_true"])
                curves.append(ir["nc"])
                sig = ir["sigmas"]
            if curves:
                drawn = True
                ax.plot(sig, np.mean(curves, axis=0), "-" if obs == "true" else "--",
                        label=f"{solver} ({obs})")
        ax.set_xlabel("σ of the Gaussian blur of the truth (voxels)")
        ax.set_ylabel(f"NC of {field} with blurred truth")
        ax.grid(alpha=0.3)
    axes[1].legend(fontsize=7)
    fig.suptitle(f"{track}: intrinsic resolution (mean over runs)", fontsize=9)
    fig.tight_layout()
    if drawn:
        fig.savefig(path, dpi=90)
    plt.close(fig)
    return drawn


def plot_slices(df, track: str, base: Path, path: Path, max_rows: int = 6) -> bool:
    """Rows: truth, then each solver's estimate of the track's first scene/variation; columns:
    slices of w (and v), like the paper's figures."""
    d = df[(df.track == track) & (df.status == "ok") & df.estimate_path.notna()]
    if d.empty:
        return False
    first = d.iloc[0]
    sel = d[(d.scene == first.scene) & (d.variation == first.variation)
            & (d.seed == first.seed)]
    rows = []
    for r in sel.itertuples():
        f = base / r.estimate_path
        if f.is_file():
            rows.append((f"{r.solver} ({r.observation})", np.load(f)))
    if not rows:
        return False
    rows = rows[:max_rows]
    truth = rows[0][1]
    grids = [("truth", truth["w_true"], truth["v_true"])] + [
        (label, z["w"], z["v"]) for label, z in rows]
    plt = _plt()
    w_true = truth["w_true"]
    membrane = w_true.ndim == 2
    cols = [None] if membrane else sorted({w_true.shape[1] // 4, w_true.shape[1] // 2,
                                           (3 * w_true.shape[1]) // 4})
    fig, axes = plt.subplots(len(grids), 2 * len(cols),
                             figsize=(1.7 * 2 * len(cols) + 1, 1.6 * len(grids)),
                             squeeze=False)
    for i, (label, w, v) in enumerate(grids):
        for f_i, (name, g) in enumerate((("w", w), ("v", v))):
            vmin, vmax = _colour_range(g)
            for c_i, j in enumerate(cols):
                ax = axes[i, f_i * len(cols) + c_i]
                img = g if membrane else g[:, j, :]
                ax.imshow(np.asarray(img).T, origin="lower", cmap="viridis", vmin=vmin, vmax=vmax)
                ax.set_xticks([])
                ax.set_yticks([])
                if i == 0:
                    ax.set_title(name if membrane else f"{name}, y={j}", fontsize=7)
                if f_i == 0 and c_i == 0:
                    ax.set_ylabel(label, fontsize=6)
    fig.suptitle(f"{track}: {first.scene} [{first.variation}] (colour scale per row and field)",
                 fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return True


def _colour_range(field: np.ndarray) -> tuple[float, float]:
    """Min and max of a field over all its slices; a (nearly) uniform field gets +-5 % around
    its value so that round-off is not shown as structure."""
    lo, hi = float(np.nanmin(field)), float(np.nanmax(field))
    mid = 0.5 * (lo + hi)
    if hi - lo <= 1e-6 * max(abs(mid), 1e-30):
        return mid - 0.05 * abs(mid), mid + 0.05 * abs(mid)
    return lo, hi


def _slug(s: str) -> str:
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in s)


def build(results: str | Path, out: str | Path = "leaderboard") -> Path:
    from .bench import check_results, read_results

    results = Path(results)
    df = read_results(results)
    base = results if results.is_dir() else results.parent
    problems = check_results(df)
    out = Path(out)
    (out / "figures").mkdir(parents=True, exist_ok=True)
    df.to_csv(out / "results.csv", index=False)
    md = ["# vvtbench leaderboard\n",
          f"Generated by vvtbench {__version__} from `{results}` ({len(df)} runs, "
          f"{df.solver.nunique()} solvers, {df.track.nunique()} tracks). Ranked by mean NC of "
          "the stiffness field w over the track's runs (centered normalized correlation, "
          "docs/metrics.md); errors count failed runs.\n"]
    if problems:
        md.append("**Schema problems:** " + "; ".join(problems[:5]) + "\n")
    body = []
    for track, obs, t in ranking(df):
        md.append(f"## {track} — {obs} modes\n")
        md.append(_md_table(t) + "\n")
        body.append(f"<h2>{html.escape(track)} — {html.escape(obs)} modes</h2>{_html_table(t)}")
    figs = []
    for track in sorted(df.track.unique()):
        for kind, fn in (("nc_vs_modes", lambda p, tr=track: plot_nc_vs_modes(df, tr, p)),
                         ("intrinsic_resolution",
                          lambda p, tr=track: plot_intrinsic_resolution(df, tr, base, p)),
                         ("slices", lambda p, tr=track: plot_slices(df, tr, base, p))):
            rel = f"figures/{_slug(track)}_{kind}.png"
            try:
                if fn(out / rel):
                    figs.append((track, kind, rel))
            except Exception as error:  # a figure must not stop the leaderboard
                print(f"warning: {track} {kind}: {error}", file=sys.stderr)
    if figs:
        md.append("## Figures\n")
        for track, kind, rel in figs:
            md.append(f"### {track}: {kind.replace('_', ' ')}\n\n![{track} {kind}]({rel})\n")
    (out / "README.md").write_text("\n".join(md))
    fig_html = "".join(f"<h3>{html.escape(t)}: {html.escape(k.replace('_', ' '))}</h3>"
                       f"<img src='{html.escape(r)}' alt='{html.escape(t)} {k}'>"
                       for t, k, r in figs)
    page = f"""<!doctype html><html><head><meta charset="utf-8"><title>vvtbench leaderboard</title>
<style>body{{font-family:sans-serif;max-width:1100px;margin:auto;padding:1em}}
table{{border-collapse:collapse;margin:.5em 0 1.5em}}td,th{{border:1px solid #ccc;padding:3px 8px;
text-align:right}}th{{background:#eee}}img{{max-width:100%}}</style></head><body>
<h1>vvtbench leaderboard</h1><p>vvtbench {__version__}; {len(df)} runs from
<code>{html.escape(str(results))}</code>. Ranked by mean NC of w. Data:
<a href="results.csv">results.csv</a>.</p>{''.join(body)}<h2>Figures</h2>{fig_html}
</body></html>"""
    (out / "index.html").write_text(page)
    (out / "leaderboard.json").write_text(json.dumps(
        {"vvtbench": __version__, "source": str(results), "figures": figs}, indent=1))
    return out


__all__ = ["build", "ranking", "shutil"]
