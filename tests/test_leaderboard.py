"""Leaderboard and figures on a synthetic results table (no simulator): field figures with
shared scales and every solver x observation source, curves with fixed colours, the summary,
reference and invalid rows, suite order, and the data safety of ``leaderboard -o``."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from vvtbench.bench.results import METRIC_COLUMNS
from vvtbench.cli.leaderboard import main_leaderboard
from vvtbench.io.files import write_npz
from vvtbench.reporting.leaderboard import KEPT, LeaderboardError, build, ranking, summary
from vvtbench.reporting.plots import (  # noqa: I001  (scale rules)
    Styles,
    _ratio_limit,
    _value_norm,
    bootstrap_band,
    plot_field_grids,
    plot_fields,
)

SOLVERS = ["vvt", "sensitivity", "homogeneous", "oracle"]


def _truth(shape=(4, 4, 4)):
    w, v = np.full(shape, 9000.0), np.full(shape, 1270.0)
    w[2:, 1:3, -1] = 5e6
    v[2:, 1:3, -1] = 7620.0
    return w, v


def _row(track, scene, variation, options, solver, obs, nc, *, seed=0, status="ok",
         est=None, reference=False):
    """A results row that passes check_results: every metric NaN unless the row is scored."""
    scored = status == "ok"
    metrics = {c: np.nan for c in METRIC_COLUMNS}
    if scored:
        metrics |= dict(nc_w=nc, nc_v=nc / 2, nc_w_uncentered=0.5, nc_v_uncentered=0.5,
                        sigma_star_w=1.0, sigma_star_v=1.0, nc_at_sigma_star_w=0.5,
                        nc_at_sigma_star_v=0.5, mode_mac=0.9, freq_err_raw=0.01,
                        freq_err_scaled=0.01)
    return dict(track=track, solver=solver, solver_version="1.0.0", config_hash="0" * 16,
                config="{}", scene=scene, variation=variation,
                variation_options=json.dumps(options), seed=seed, observation=obs,
                n_modes=options.get("n_modes", 10), n_modes_observed=10, **metrics,
                runtime_s=1.0, status=status, error="" if scored else "non-finite w",
                vvtbench_version="0.1.0", dataset_revision="0" * 16, estimate_path=est,
                traceback_path=None, reference=reference)


@pytest.fixture(scope="module")
def table(tmp_path_factory):
    return make_run(tmp_path_factory.mktemp("run"))


@pytest.fixture(scope="module")
def board(table, tmp_path_factory):
    """The leaderboard of ``table``, built once; a test that changes it works on a copy."""
    return build(table / "results.csv", tmp_path_factory.mktemp("board") / "lb")


def make_run(root):
    """A run folder: tracks `zeta_first` (2 scenes, an n_modes sweep, 2 seeds, both sources),
    `drums` (membranes) and `alpha` (a vvt.alpha_v sweep) in that order; one invalid row."""
    rng = np.random.default_rng(0)
    rows, k = [], 0

    def fields(w_true, v_true, scale):
        nonlocal k
        k += 1
        rel = f"evaluations/{k:04d}/fields.npz"  # no cache/: scores not recomputed
        (root / rel).parent.mkdir(parents=True)
        w = w_true ** scale * 9000 ** (1 - scale) * (1 + 0.02 * rng.standard_normal(w_true.shape))
        v = v_true ** scale * 1270 ** (1 - scale)
        write_npz(root / rel, {"w": w, "v": v, "w_true": w_true, "v_true": v_true})
        return rel

    wt, vt = _truth()
    for scene in ("cube_top", "cube_bottom"):
        for n in (8, 12, 16):
            for seed in (0, 1, 2):
                for solver in SOLVERS:
                    for obs in ("true", "extracted"):
                        nc = {"oracle": 0.9, "vvt": 0.5, "sensitivity": 0.2,
                              "homogeneous": 0.0}[solver] + 0.01 * n + 0.02 * seed
                        status = "invalid" if (solver == "sensitivity" and n == 16
                                               and scene == "cube_top" and seed == 1
                                               and obs == "true") else "ok"
                        est = fields(wt, vt, 0.3 if solver != "homogeneous" else 0.0) \
                            if status == "ok" else None
                        rows.append(_row("zeta_first", scene, f"n_modes={n}",
                                         {"n_modes": n}, solver, obs, min(nc, 1.0),
                                         seed=seed, status=status, est=est,
                                         reference=solver == "oracle"))
    dw, dv = np.full((6, 6, 1), 100.0), np.full((6, 6, 1), 0.2)
    dw[0, 0, 0] = np.nan
    dv[0, 0, 0] = np.nan
    dw[3:5, 2:4, 0] = 300.0
    for solver in SOLVERS:
        for obs in ("true", "extracted"):
            rows.append(_row("drums", "drum_a", "base", {"n_modes": 20}, solver, obs, 0.4,
                             est=fields(dw, dv, 0.5), reference=solver == "oracle"))
    for a in (1e-9, 1e-8, 1e-7):
        rows.append(_row("alpha", "cube_top", f"vvt.alpha_v={a:g}",
                         {"n_modes": 10, "vvt.alpha_v": a}, "vvt", "true", 0.3,
                         est=fields(wt, vt, 0.2)))
    df = pd.DataFrame(rows)
    df.to_csv(root / "results.csv", index=False)
    return root


def test_styles_fixed_colour_per_solver_and_line_per_source():
    many = [f"solver{i:02d}" for i in range(16)] + SOLVERS
    s = Styles(many, ["true", "extracted"])
    assert len(set(s.colours.values())) == len(many)  # never one colour for two solvers
    assert Styles(["vvt"]).colour("vvt") == s.colour("vvt")  # fixed, not position-dependent
    assert s.line("true")[0] != s.line("extracted")[0]


def test_bootstrap_band_contains_mean_and_one_value_has_none():
    x = np.array([0.1, 0.2, 0.3, 0.4, 0.5])
    lo, hi = bootstrap_band(x)
    assert lo < x.mean() < hi
    assert np.isnan(bootstrap_band([0.3])).all()


def test_colour_scales_do_not_invent_structure():
    const = np.full((4, 4, 4), 9000.0) + 5e-12 * np.arange(64).reshape(4, 4, 4)
    norm, how = _value_norm([const], "auto")
    assert how == "linear" and norm.vmax - norm.vmin >= 0.1 * 9000 * 0.99
    w, _ = _truth()
    assert _value_norm([w, const], "auto")[1] == "log"  # clay in Jello: 555x
    assert _ratio_limit([const / 9000]) >= 1.1


def test_plot_fields_keeps_the_solve_signature(tmp_path):
    wt, vt = _truth((3, 3, 2))

    class Problem:  # the part of InverseProblem plot_fields uses
        n_params, kind = 18, "solid"

        def to_grid(self, x):
            return np.asarray(x, float).reshape(3, 3, 2)

    class Truth:
        w, v = wt.ravel(), vt.ravel()

    out = plot_fields(tmp_path / "slices.png", Problem(), {"vvt": (wt.ravel() * 1.1,
                                                                   vt.ravel())}, Truth())
    assert out.is_file() and out.stat().st_size > 5000
    normalized = plot_field_grids(tmp_path / "n.png", wt[:, :, 0], vt[:, :, 0],
                                  {"a": (wt[:, :, 0], vt[:, :, 0])}, normalized=True)
    assert normalized.is_file()


def test_ranking_keeps_suite_order_and_never_ranks_references_or_invalid(table):
    df = pd.read_csv(table / "results.csv")
    groups = ranking(df)
    assert [g[0] for g in groups][::2][:2] == ["zeta_first", "drums"]  # not alphabetical
    t = dict(((tr, obs), t) for tr, obs, t in groups)[("zeta_first", "true")]
    for variation, cell in t.groupby("variation", sort=False):
        assert cell.solver.iloc[-1] == "oracle" and cell.reference.iloc[-1]
        # sensitivity answered 5 of 6 runs at n_modes=16 (< MIN_VALID_FRACTION): not ranked
        ranks = [1, 2, None] if variation == "n_modes=16" else [1, 2, 3]
        assert cell["rank"].iloc[-1] is None and list(cell["rank"].iloc[:-1]) == ranks
    sens = t[t.solver == "sensitivity"].set_index("variation")
    assert sens.loc["n_modes=16", "invalid"] == 1 and sens.loc["n_modes=8", "invalid"] == 0
    assert sens.loc["n_modes=16", "n"] == 5 and sens.loc["n_modes=16", "runs"] == 6
    assert sens.loc["n_modes=16", "note"] == "not ranked: valid on 5 of 6 runs"
    drums = dict(((tr, obs), t) for tr, obs, t in groups)[("drums", "true")]
    assert drums["rank"].isna().all()  # one instance: too few to rank
    assert set(drums.note[~drums.reference]) == {"too few instances to rank (n=1, fewer than 5)"}
    s = {r["track"]: r for r in summary(df)}
    assert s["zeta_first"]["best"]["solver"] == "vvt"
    assert s["zeta_first"]["best"]["variation"] == "n_modes=16"  # a cell, not a pooled mean
    assert s["zeta_first"]["reference"]["solver"] == "oracle"
    assert s["zeta_first"]["invalid"] == 1 and s["alpha"]["runs"] == 3


def test_sweep_values_are_never_averaged(table):
    df = pd.read_csv(table / "results.csv")
    t = dict(((tr, obs), t) for tr, obs, t in ranking(df))[("zeta_first", "extracted")]
    vvt = t[t.solver == "vvt"]
    assert list(vvt.variation) == ["n_modes=8", "n_modes=12", "n_modes=16"]  # run order
    for _, r in vvt.iterrows():
        d = df[(df.track == "zeta_first") & (df.observation == "extracted")
               & (df.solver == "vvt") & (df.variation == r.variation)]
        assert r.n == 6 and np.isclose(r.nc_w_mean, d.nc_w.mean())
    a = dict(((tr, obs), t) for tr, obs, t in ranking(df))[("alpha", "true")]
    assert len(a) == 3 and a.variation.nunique() == 3


# ------------------------------------------------------------------ statistics on the pages
def _instances_table(tmp_path, edit=None):
    """Track `t`, one variation: solvers `a` and `b` on 10 instances (5 scenes x 2 seeds),
    and the reference `oracle`; ``edit(rows)`` changes the rows first."""
    rng = np.random.default_rng(3)
    rows = []
    for i in range(5):
        for seed in (0, 1):
            for solver, base in (("a", 0.6), ("b", 0.4), ("oracle", 0.9)):
                nc = float(np.clip(base + 0.1 * rng.standard_normal(), -1, 1))
                r = _row("t", f"fam-test-{i:05d}", "base", {"n_modes": 10}, solver, "true",
                         nc, seed=seed, reference=solver == "oracle")
                r.update(false_contrast_w=np.nan, false_contrast_v=np.nan,
                         runtime_s=1.0 + i + seed)
                rows.append(r)
    if edit is not None:
        edit(rows)
    path = tmp_path / "results.csv"
    pd.DataFrame(rows).to_csv(path, index=False)
    return path


def _board(path, out):
    build(path, out)
    return ((out / "README.md").read_text(), (out / "index.html").read_text(),
            json.loads((out / "leaderboard.json").read_text()))


def test_ci_cell_is_the_bootstrap_interval_over_instances(tmp_path):
    from vvtbench.scoring.stats import N_BOOT, SEED, bootstrap_ci

    src = _instances_table(tmp_path)
    md, page, manifest = _board(src, tmp_path / "lb")
    df = pd.read_csv(src)
    assert manifest["statistics"]["seed"] == SEED and manifest["statistics"]["n_boot"] == N_BOOT
    assert "2000 resamples" in md and "seed 0" in md and "percentile bootstrap" in md
    rec = {r["solver"]: r for r in manifest["tracks"][0]["ranking"]}
    for solver in ("a", "b"):
        x = df[df.solver == solver].nc_w.to_numpy()
        lo, hi = bootstrap_ci(x, seed=SEED)
        mlo, mhi = bootstrap_ci(x, np.median, seed=SEED)
        cell = f"{x.mean():.2f} [{lo:.2f}, {hi:.2f}]"
        line, detail = [ln for ln in md.splitlines() if ln.startswith("| base |")
                        and f"| {solver} |" in ln]
        assert cell in line and f"{np.median(x):.2f} [{mlo:.2f}, {mhi:.2f}]" in detail
        assert cell in page
        r = rec[solver]  # machine-readable: numbers
        assert r["nc_w_n"] == 10 and r["n"] == 10
        assert (r["nc_w_mean_ci_low"], r["nc_w_mean_ci_high"]) == (lo, hi)
        assert np.isclose(r["nc_w_mean"], x.mean())
        assert r["runtime_median_s"] == 3.5 and r["runtime_q25_s"] == 2.25
    assert rec["a"]["rank"] == 1 and rec["b"]["rank"] == 2 and rec["oracle"]["rank"] is None
    line = [ln for ln in md.splitlines() if ln.startswith("| base |") and "| a |" in ln][1]
    assert "3.50 (2.25–4.75)" in line  # runtime: median (IQR)
    # paired: a vs b only (the reference is no competitor), on the 10 shared instances
    (p,) = manifest["tracks"][0]["paired"]["nc_w"]
    assert (p["a"], p["b"], p["n"]) == ("a", "b", 10)
    d = df[df.solver == "a"].nc_w.to_numpy() - df[df.solver == "b"].nc_w.to_numpy()
    lo, hi = bootstrap_ci(d, seed=SEED)
    assert np.isclose(p["mean_diff"], d.mean()) and (p["ci_low"], p["ci_high"]) == (lo, hi)
    assert np.isclose(p["win_rate"], np.mean(d > 0))
    assert f"| a | b | {d.mean():+.2f} [{lo:+.2f}, {hi:+.2f}] | {np.mean(d > 0):.2f} | 10 |" in md


def test_undefined_metrics_are_counted_never_shown_as_numbers(tmp_path):
    def constant_truth(rows):  # instances of scene 0: NC undefined, false contrast instead
        for r in rows:
            if r["scene"] == "fam-test-00000":
                r.update(nc_w=np.nan, nc_v=np.nan, false_contrast_w=0.2,
                         false_contrast_v=0.1)

    md, page, manifest = _board(_instances_table(tmp_path, constant_truth), tmp_path / "lb")
    rec = {r["solver"]: r for r in manifest["tracks"][0]["ranking"]}
    assert rec["a"]["n"] == 10 and rec["a"]["nc_w_n"] == 8 and rec["a"]["nc_v_n"] == 8
    assert rec["a"]["false_contrast_w_n"] == 2 and rec["a"]["false_contrast_w_mean"] == 0.2
    line, detail = [ln for ln in md.splitlines() if ln.startswith("| base |") and "| a |" in ln]
    assert line.count("(n=8)") == 2 and detail.count("(n=8)") == 2  # over 8 of 10 instances
    assert "false contrast w (constant truth)" in md and "0.200 (n=2)" in detail
    assert "nan" not in md.lower() and "nan" not in page.lower()
    assert manifest["tracks"][0]["paired"]["nc_w"][0]["n"] == 8


def test_paired_comparison_only_on_shared_instances_and_failures_counted(tmp_path):
    def holes(rows):
        for r in rows:
            if r["solver"] == "b" and r["scene"] in ("fam-test-00001", "fam-test-00002") \
                    and r["seed"] == 0:
                r.update({c: np.nan for c in METRIC_COLUMNS}, status="error",
                         error="solve: RuntimeError: boom")
            if r["solver"] == "a" and r["scene"] == "fam-test-00004" and r["seed"] == 1:
                r.update({c: np.nan for c in METRIC_COLUMNS}, status="invalid",
                         error="non-finite w")

    src = _instances_table(tmp_path, holes)
    md, page, manifest = _board(src, tmp_path / "lb")
    df = pd.read_csv(src)
    rec = {r["solver"]: r for r in manifest["tracks"][0]["ranking"]}
    assert (rec["b"]["failed"], rec["b"]["invalid"], rec["b"]["n"]) == (2, 0, 8)
    assert (rec["a"]["failed"], rec["a"]["invalid"], rec["a"]["n"]) == (0, 1, 9)
    assert next(r for r in summary(df) if r["track"] == "t")["failed"] == 2
    (p,) = manifest["tracks"][0]["paired"]["nc_w"]
    ok = df[df.status == "ok"].pivot_table(index=["scene", "seed"], columns="solver",
                                           values="nc_w").dropna()
    assert p["n"] == 7 == len(ok)
    assert np.isclose(p["mean_diff"], (ok["a"] - ok["b"]).mean())
    # b answered 8 of 10 (< MIN_VALID_FRACTION): not ranked, below a; a, 9 of 10, is ranked
    line = next(ln for ln in md.splitlines() if "| b -- not ranked: valid on 8 of 10" in ln)
    assert line.endswith("| 2 | 0 |") and "| – | b" in line  # failed, invalid; no rank
    assert rec["a"]["rank"] == 1 and rec["b"]["rank"] is None
    assert next(r for r in summary(df) if r["track"] == "t")["best"]["solver"] == "a"


def test_build_writes_every_figure_kind_and_a_summary(board):
    out = board
    manifest = json.loads((out / "leaderboard.json").read_text())
    assert manifest["generator"] == "vvtbench"
    files = set(manifest["files"])
    assert {"README.md", "index.html", "results.csv", "leaderboard.json"} <= files
    for f in files:
        assert (out / f).is_file()
    figs = [f for f in files if f.startswith("figures/")]
    assert "figures/zeta_first_nc_vs_modes.png" in figs
    assert "figures/alpha_nc_vs_vvt_alpha_v.png" in figs
    assert "figures/zeta_first_intrinsic_resolution.png" in figs
    # one field figure per scene (values and normalized), every solver x source in it
    assert "figures/zeta_first_slices.png" in figs
    assert "figures/zeta_first_slices_cube_bottom_normalized.png" in figs
    assert "figures/drums_slices.png" in figs
    page = (out / "index.html").read_text()
    assert page.index("zeta_first") < page.index("drums") < page.index("id=\"alpha\"")
    assert "Summary" in page and 'class="ref"' in page and "http" not in page
    assert "<img" in page and all(f in page for f in figs)
    md = (out / "README.md").read_text()
    assert "| ref | oracle (reference)" in md and "## Summary" in md


def test_field_figure_has_a_row_per_solver_and_source(table, tmp_path):
    from vvtbench.reporting.leaderboard import field_figures

    df = pd.read_csv(table / "results.csv")
    seen = {}

    import vvtbench.reporting.plots as plots

    real = plots.plot_field_grids

    def spy(path, tw, tv, estimates, *a, **k):
        seen[path.name] = list(estimates)
        return real(path, tw, tv, estimates, *a, **k)

    plots.plot_field_grids = spy
    try:
        field_figures(df, "drums", table, tmp_path, "figures", Styles(SOLVERS))
    finally:
        plots.plot_field_grids = real
    labels = seen["drums_slices.png"]
    assert len(labels) == 8 and labels[0].startswith("oracle (ref.)")
    assert {lab.split(", ")[1] for lab in labels} == {"true modes", "extracted modes"}


def test_output_refuses_foreign_files_and_keeps_them_with_overwrite(table, tmp_path):
    out = tmp_path / "lb"
    out.mkdir()
    (out / "README.md").write_text("my own notes")
    assert main_leaderboard([str(table / "results.csv"), "-o", str(out)]) == 2
    assert (out / "README.md").read_text() == "my own notes"
    (out / "keep.txt").write_text("keep")
    assert main_leaderboard([str(table / "results.csv"), "-o", str(out), "--overwrite"]) == 0
    assert (out / "keep.txt").read_text() == "keep"
    assert (out / "README.md").read_text().startswith("# vvtbench leaderboard")


def test_rebuild_replaces_only_own_files(table, board, tmp_path):
    import shutil

    out = tmp_path / "lb"
    shutil.copytree(board, out, symlinks=True)  # as an earlier build left it
    (out / "figures" / "old_only_mine.png").write_bytes(b"x")
    m = json.loads((out / "leaderboard.json").read_text())
    m["files"] += ["figures/old_only_mine.png", "../outside.txt"]
    (out / "leaderboard.json").write_text(json.dumps(m))
    (tmp_path / "outside.txt").write_text("not yours")
    build(table / "results.csv", out)  # own folder: no --overwrite needed
    assert not (out / "figures" / "old_only_mine.png").exists()  # stale own file removed
    assert (tmp_path / "outside.txt").read_text() == "not yours"
    assert not list(out.rglob("*.tmp*"))


def test_output_never_writes_through_symlinks_or_over_its_input(table, tmp_path):
    real = tmp_path / "real"
    real.mkdir()
    link = tmp_path / "link"
    link.symlink_to(real)
    with pytest.raises(LeaderboardError, match="symbolic link"):
        build(table / "results.csv", link)
    out = tmp_path / "lb"
    out.mkdir()
    (out / "figures").symlink_to(real)
    with pytest.raises(LeaderboardError, match="symbolic link"):
        build(table / "results.csv", out, overwrite=True)
    assert not os.listdir(real)
    src = tmp_path / "in"
    src.mkdir()
    (src / "results.csv").write_text((table / "results.csv").read_text())
    with pytest.raises(LeaderboardError, match="overwritten"):
        build(src / "results.csv", src, overwrite=True)


def test_track_order_comes_from_the_run_not_the_table(tmp_path):
    from vvtbench.reporting.leaderboard import suite_track_order

    (tmp_path / "run.json").write_text('{"tracks": ["b", "a", "gone"]}')
    assert suite_track_order(tmp_path / "results.parquet", ["a", "c", "b"]) == ["b", "a", "c"]
    assert suite_track_order(tmp_path, ["a", "b"]) == ["b", "a"]
    (tmp_path / "run.json").write_text("[1, 2]")
    assert suite_track_order(tmp_path, ["a", "b"]) == ["a", "b"]
    assert suite_track_order(tmp_path / "x" / "r.csv", ["z", "y"]) == ["z", "y"]


def test_sweep_curve_has_a_gap_where_a_run_is_not_valid(tmp_path, monkeypatch):
    """A swept value whose run was invalid is a gap in the curve, not a line drawn across it."""
    import matplotlib.axes

    from vvtbench.reporting.plots import plot_sweep

    rows = [{"scene": "s", "solver": "vvt", "observation": "true", "status": st,
             "variation_options": json.dumps({"n_modes": n}), "nc_w": w, "nc_v": w}
            for n, st, w in [(8, "ok", 0.2), (10, "invalid", np.nan), (12, "ok", 0.4)]]
    drawn = []
    plot = matplotlib.axes.Axes.plot

    def spy(self, *args, **kwargs):
        drawn.append((np.asarray(args[0], float), np.asarray(args[1], float)))
        return plot(self, *args, **kwargs)

    monkeypatch.setattr(matplotlib.axes.Axes, "plot", spy)
    assert plot_sweep(tmp_path / "f.png", pd.DataFrame(rows), "n_modes",
                      Styles(["vvt"], ["true"]))
    x, y = drawn[0]
    assert x.tolist() == [8, 10, 12] and y[0] == 0.2 and np.isnan(y[1]) and y[2] == 0.4


# ------------------------------------------------------------------ ranks that cannot mislead
def test_tied_solvers_share_a_rank_and_the_page_says_so(tmp_path):
    """b is a's score minus 0.02, plus or minus 0.1 per instance: their paired interval
    includes 0, so they share rank 1; the reference stays apart and unranked."""
    def close(rows):
        a = {(r["scene"], r["seed"]): r["nc_w"] for r in rows if r["solver"] == "a"}
        for i, r in enumerate(x for x in rows if x["solver"] == "b"):
            r.update(nc_w=min(1.0, a[(r["scene"], r["seed"])] - 0.02 + (0.1 if i % 2 else -0.1)))

    md, page, manifest = _board(_instances_table(tmp_path, close), tmp_path / "lb")
    rec = {r["solver"]: r for r in manifest["tracks"][0]["ranking"]}
    p = manifest["tracks"][0]["paired"]["nc_w"][0]
    assert p["ci_low"] < 0 < p["ci_high"]
    assert rec["a"]["rank"] == rec["b"]["rank"] == 1 and rec["oracle"]["rank"] is None
    assert "| base | 1= | a |" in md and "| base | 1= | b |" in md
    assert "tie group" in md.lower() and "includes 0" in page
    summary_line = next(ln for ln in md.splitlines() if ln.startswith("| [t](#t)"))
    assert "| b |" in summary_line  # the summary names who shares first place
    assert md.index("## Summary") < md.index("## Method") and "Tie groups" in md


def test_fewer_than_five_instances_no_rank_and_no_interval(tmp_path):
    def four_instances(rows):
        rows[:] = [r for r in rows if r["scene"] in ("fam-test-00000", "fam-test-00001")
                   and not (r["scene"] == "fam-test-00001" and r["seed"] == 1)]

    md, page, manifest = _board(_instances_table(tmp_path, four_instances), tmp_path / "lb")
    rec = {r["solver"]: r for r in manifest["tracks"][0]["ranking"]}
    assert rec["a"]["nc_w_n"] == 3 and rec["a"]["rank"] is None and rec["b"]["rank"] is None
    line = next(ln for ln in md.splitlines() if ln.startswith("| base | – | a"))
    assert "too few instances to rank (n=3, fewer than 5)" in line and "[" not in line.split("|")[4]
    assert "too few instances to rank" in page and "Below 5 instances there is no interval" in md
    assert manifest["statistics"]["min_rank_n"] == 5


@pytest.mark.parametrize("edit", ["no rows", "all failed"])
def test_an_empty_table_is_one_line_exit_2_nothing_written(tmp_path, capsys, edit):
    def empty(rows):
        if edit == "no rows":
            rows[:] = rows[:0]
        for r in rows:
            r.update({c: np.nan for c in METRIC_COLUMNS}, status="error", error="boom")

    src = _instances_table(tmp_path, empty)
    if edit == "no rows":  # a header without rows
        src.write_text(",".join(_row("t", "s", "v", {}, "a", "true", 0.1)) + "\n")
    out = tmp_path / "lb"
    assert main_leaderboard([str(src), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(src) in err
    assert ("no rows" in err) if edit == "no rows" else ("no valid scored row" in err)
    assert not out.exists()


def test_a_table_failing_its_check_or_its_rescore_is_refused(tmp_path, capsys):
    def out_of_range(rows):
        rows[3]["nc_w"] = 1.7

    src = _instances_table(tmp_path, out_of_range)
    assert main_leaderboard([str(src), "-o", str(tmp_path / "lb")]) == 2
    err = capsys.readouterr().err
    assert "row 3" in err and "nc_w" in err and not (tmp_path / "lb").exists()
    run = tmp_path / "run"
    run.mkdir()
    src = _instances_table(run)
    (run / "cache").mkdir()  # a run's cache beside the table: its scores are recomputed
    assert main_leaderboard([str(src), "-o", str(tmp_path / "lb2")]) == 2
    err = capsys.readouterr().err
    assert "does not stand when recomputed" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "lb2").exists()


def test_a_table_without_cache_says_first_that_scores_were_not_recomputed(tmp_path):
    md, page, manifest = _board(_instances_table(tmp_path), tmp_path / "lb")
    assert md.splitlines()[2].startswith("**Scores not recomputed")
    body = page[page.index("<body>"):]
    assert body.index("Scores not recomputed") < body.index("<h2>")
    assert manifest["recomputed"] is False


def test_cells_are_escaped_in_markdown_and_html(tmp_path):
    from vvtbench.reporting.leaderboard import md_cell

    evil = "base | <b>bold</b> | fake"

    def rename(rows):
        for r in rows:
            r["variation"] = evil

    md, page, _ = _board(_instances_table(tmp_path, rename), tmp_path / "lb")
    assert "<b>bold" not in md and "<b>bold" not in page and "&lt;b&gt;bold" in page
    header = next(ln for ln in md.splitlines() if ln.startswith("| variation | rank |"))
    rows = [ln for ln in md.splitlines() if ln.startswith("| base \\| &lt;b&gt;")]
    assert len(rows) == 6  # ranking and details of a, b, oracle; no row made by the name
    ranking_row = next(ln for ln in rows if "| a |" in ln and "| 1 |" in ln)
    assert ranking_row.replace("\\|", "").count("|") == header.count("|")
    assert md_cell("a\n| fake | row |\r\nb") == "a \\| fake \\| row \\| b"
    assert md_cell("x\\|y") == "x\\\\\\|y"  # a backslash cannot unescape the pipe


# ------------------------------------------------------------------ figures a person reads
def _saved_figures(monkeypatch):
    """Figures handed to save_figure, inspected before they are written and closed."""
    import vvtbench.reporting.plots as plots

    seen = []
    save = plots.save_figure

    def spy(fig, path, dpi=100):
        fig.canvas.draw()
        seen.append({"title": fig._suptitle.get_text() if fig._suptitle else "",
                     "xticks": [t.get_text() for ax in fig.axes
                                for t in ax.get_xticklabels() if t.get_text()],
                     })
        return save(fig, path, dpi=dpi)

    monkeypatch.setattr(plots, "save_figure", spy)
    return seen


def test_solve_figure_is_titled_with_scene_observation_solver_and_score(tmp_path, monkeypatch):
    seen = _saved_figures(monkeypatch)
    wt, vt = _truth((3, 3, 2))

    class Problem:
        n_params, kind = 18, "solid"

        def to_grid(self, x):
            return np.asarray(x, float).reshape(3, 3, 2)

    class Truth:
        w, v = wt.ravel(), vt.ravel()

    plot_fields(tmp_path / "slices.png", Problem(), {"vvt": (wt.ravel(), vt.ravel())}, Truth(),
                scene="cube_top", observation="extracted", solver="vvt",
                score={"NC w": 0.412, "NC v": float("nan")})
    assert seen[0]["title"].startswith("vvt on cube_top (extracted modes): NC w 0.41, "
                                       "NC v undefined")


def test_count_axes_have_integer_ticks(tmp_path, monkeypatch):
    from vvtbench.reporting.plots import plot_sweep

    seen = _saved_figures(monkeypatch)
    rows = [{"scene": "s", "solver": "vvt", "observation": "true", "status": "ok",
             "variation_options": json.dumps({"n_modes": n}), "nc_w": 0.1 * i, "nc_v": 0.1}
            for i, n in enumerate((6, 7, 8))]
    assert plot_sweep(tmp_path / "f.png", pd.DataFrame(rows), "n_modes",
                      Styles(["vvt"], ["true"]))
    ticks = seen[0]["xticks"]
    assert ticks and all(t.lstrip("−-").isdigit() for t in ticks), ticks


def test_contrast_view_first_when_the_truth_dwarfs_the_estimates():
    from vvtbench.reporting.plots import contrast_first

    wt, _ = _truth()  # 9000 to 5e6: a x556 contrast
    flat = 9000.0 * (1 + 0.1 * np.random.default_rng(1).random(wt.shape))
    assert contrast_first(wt, [flat, flat * 1.01])
    assert not contrast_first(wt, [wt * 0.9, flat])  # one estimate shows the structure
    assert not contrast_first(None, [flat])


def test_keep_figures_keeps_what_a_table_without_its_cache_cannot_redraw(tmp_path):
    wt, vt = _truth()

    def with_fields(rows):
        for k, r in enumerate(rows):
            rel = f"evaluations/{k:04d}/fields.npz"
            (tmp_path / rel).parent.mkdir(parents=True)
            write_npz(tmp_path / rel, {"w": wt * (1 + 0.01 * k), "v": vt, "w_true": wt,
                                       "v_true": vt})
            r["estimate_path"] = rel

    out = tmp_path / "lb"
    build(_instances_table(tmp_path, with_fields), out)
    drawn = json.loads((out / "leaderboard.json").read_text())["figures"]
    slices = [rel for _, _, rel in drawn if "slices" in rel]
    assert slices
    bare = tmp_path / "elsewhere"
    bare.mkdir()
    (bare / "results.csv").write_bytes((tmp_path / "results.csv").read_bytes())
    build(bare / "results.csv", out, keep_figures=True)  # its fields are not beside it
    kept = json.loads((out / "leaderboard.json").read_text())["figures"]
    assert [rel for _, _, rel in kept if "slices" in rel] == slices
    assert all(c.endswith(KEPT) for _, c, rel in kept if rel in slices)
    assert all((out / rel).is_file() for rel in slices) and KEPT in (out / "README.md").read_text()
    build(bare / "results.csv", out)  # not kept: an earlier build's own files are removed
    assert not any((out / rel).exists() for rel in slices)


def test_a_views_sweep_is_drawn_pooled_over_instances_and_against_dofs(tmp_path, monkeypatch):
    rng = np.random.default_rng(5)

    def edit(rows):
        rows.clear()
        for i in range(6):
            for n in (1, 2, 3):
                for solver, gain in (("a", 0.1), ("b", 0.0)):
                    nc = 0.3 + gain * n + 0.05 * rng.standard_normal()
                    r = _row("views_track", f"fam-test-{i:05d}", f"views={n}", {"views": n},
                             solver, "extracted", nc)
                    r.update(observed_dof_fraction=0.2 * n, false_contrast_w=np.nan,
                             false_contrast_v=np.nan)
                    if (i, n, solver) == (0, 3, "a"):  # not valid: left out of a's paired mean
                        r.update({c: np.nan for c in METRIC_COLUMNS}, status="invalid",
                                 error="non-finite w")
                    rows.append(r)

    path = _instances_table(tmp_path, edit)
    seen = []
    import vvtbench.reporting.plots as plots

    save = plots.save_figure

    def spy(fig, p, dpi=100):
        if Path(p).name.endswith("nc_vs_views.png"):
            seen.append([(line.get_label(), line.get_xydata().copy())
                         for ax in fig.axes for line in ax.get_lines()])
        return save(fig, p, dpi=dpi)

    monkeypatch.setattr(plots, "save_figure", spy)
    from vvtbench.bench.results import read_results
    from vvtbench.reporting.leaderboard import curve_figures

    table = read_results(path)
    figs = curve_figures(table, "views_track", tmp_path, tmp_path, "figures",
                         Styles(["a", "b"], ["extracted"]))
    assert figs == [("NC against the number of views and the DOFs observed",
                     "figures/views_track_nc_vs_views.png")]
    assert (tmp_path / "views_track_nc_vs_views.png").is_file()
    curves = {label: xy for label, xy in seen[0] if label.startswith(("a,", "b,"))}
    ok = table[table.status == "ok"]
    for solver, n in (("a", 5), ("b", 6)):
        xy = curves[f"{solver}, extracted modes (n={n})"]
        paired = ok[ok.solver == solver].pivot_table(index="scene", columns="variation",
                                                     values="nc_w").dropna()
        assert len(paired) == n
        np.testing.assert_allclose(xy[:, 1], paired.mean().to_numpy())
    dof_lines = [xy for label, xy in seen[0] if label.startswith("_") and len(xy) > 1]
    assert sum(len(xy) == 3 and np.allclose(xy[:, 0], [0.2, 0.4, 0.6]) for xy in dof_lines) == 11
    assert sum(len(xy) == 2 and np.allclose(xy[:, 0], [0.2, 0.4])  # the invalid row's instance
               for xy in dof_lines) == 1


def test_the_resolution_figure_draws_exactly_the_rows_its_table_averages(tmp_path, monkeypatch):
    """A defect-free instance has no NC in the table (constant truth): its curve is not drawn
    either, so the figure's n is the table's n."""
    import numpy as np
    import pandas as pd

    from vvtbench.reporting import leaderboard as lb
    from vvtbench.reporting import plots

    rng = np.random.default_rng(0)
    rows = []
    for i, defect in enumerate([True, True, False]):
        w_true = np.ones(27) + (rng.random(27) if defect else 0.0)
        np.savez(tmp_path / f"f{i}.npz", w=w_true + 0.1 * rng.random(27),
                 v=np.ones(27) + rng.random(27),
                 w_true=w_true, v_true=np.ones(27) + rng.random(27))
        rows.append({"track": "t", "solver": "s", "observation": "true", "variation": "base",
                     "status": "ok", "estimate_path": f"f{i}.npz", "scene": f"c{i}", "seed": 0,
                     "nc_w": 0.9 if defect else np.nan, "nc_v": 0.5})
    seen = {}

    def capture(path, curves, styles, title=""):
        seen.update({k: {f: len(c.get(f, [])) for f in ("w", "v")} for k, c in curves.items()})
        return False

    monkeypatch.setattr(plots, "plot_intrinsic_resolution", capture)
    lb.curve_figures(pd.DataFrame(rows), "t", tmp_path, tmp_path, "figures", styles=None)
    assert seen == {("s", "true"): {"w": 2, "v": 3}}
def test_unsandboxed_rows_are_marked_on_the_board(tmp_path):
    """A row a plug-in produced without a sandbox (sandbox = none) could have read the truth:
    the page says so first and marks its solver wherever it is shown."""
    def loose(rows):
        for r in rows:
            r["sandbox"] = "none" if r["solver"] == "b" else "bwrap"

    md, page, manifest = _board(_instances_table(tmp_path, loose), tmp_path / "lb")
    assert "UNSANDBOXED: 10 of the runs (b) ran without a sandbox" in md.split("## Summary")[0]
    assert "UNSANDBOXED" in page.split("<h2>Summary")[0]
    assert any(ln.startswith("| base |") and "| b (unsandboxed) |" in ln
               for ln in md.splitlines())
    assert not any("a (unsandboxed)" in ln for ln in md.splitlines())
    rec = {r["solver"]: r for r in manifest["tracks"][0]["ranking"]}
    assert rec["b"]["unsandboxed"] is True and rec["a"]["unsandboxed"] is False
    assert 'class="loose' in page
    (tmp_path / "sealed").mkdir()
    md, _, _ = _board(_instances_table(tmp_path / "sealed"), tmp_path / "lb2")
    assert "UNSANDBOXED" not in md and "(unsandboxed)" not in md


def test_a_table_that_ranks_nothing_is_titled_a_reproduction(table, tmp_path):
    from vvtbench.reporting.leaderboard import MIN_RANK_N, board_title

    assert board_title([{"best": None}, {"best": {"solver": "vvt"}}])[0] == "vvtbench leaderboard"
    title, sentence = board_title([{"best": None}, {"best": None}])
    assert "not a ranking" in title and f"{MIN_RANK_N} valid instances" in sentence
    df = pd.read_csv(table / "results.csv")
    few = df[df.seed == df.seed.min()].groupby(["track", "solver"]).head(1)
    few.to_csv(tmp_path / "few.csv", index=False)
    out = build(tmp_path / "few.csv", tmp_path / "lb")
    page = (out / "README.md").read_text()
    assert page.startswith("# vvtbench results: a reproduction, not a ranking")
    assert "ranks nothing" in page and "<h1>vvtbench results: a reproduction" in (
        out / "index.html").read_text()


def test_an_extraction_per_seed_is_its_own_video():
    """Two seeds of one scene are two videos: the extraction table and the extractor
    ranking keep both (not the first seed's alone); one seed shows no seed column."""
    from vvtbench.reporting.leaderboard import extraction_table, extractor_ranking

    rows = []
    for obs, shift in (("extracted", 0.0), ("extracted:farneback", -0.1)):
        for seed, recall in ((0, 0.4), (1, 0.8)):
            rows.append({"track": "v", "solver": "vvt", "observation": obs, "scene": "a",
                         "variation": "base", "seed": seed, "extraction_precision": 1.0,
                         "extraction_recall": recall + shift})
    df = pd.DataFrame(rows)
    table = extraction_table(df, "v")
    videos = table[~table.scene.astype(str).str.startswith("mean")]
    assert len(videos) == 4 and sorted(set(videos.seed)) == [0, 1]
    ranked = extractor_ranking(df, "v").set_index("observation")
    assert ranked.videos.tolist() == [2, 2]
    assert "seed" not in extraction_table(df[df.seed == 0], "v").columns


def test_a_small_efficiency_is_never_printed_as_zero(tmp_path):
    """An extraction's frequency efficiency of a few 1e-4 (errors far above the bound) and a
    relative frequency error of 1e-5 keep their significant figures on the board's page and
    in its extraction tables, where three decimals would show 0.000; an undefined one is a
    dash."""
    from vvtbench.reporting.leaderboard import extraction_sources, extraction_table

    rows = []
    for scene, eff, err in (("a", 2.5e-4, 1.2e-5), ("b", 4.5e-4, 3.4e-5)):
        rows.append({"track": "v", "solver": "vvt", "observation": "extracted",
                     "scene": scene, "variation": "base", "seed": 0, "nc_w": 0.5, "status": "ok",
                     "extraction_precision": 1.0, "extraction_recall": 0.5,
                     "extraction_mean_rel_freq_error": err,
                     "extraction_frequency_efficiency": eff,
                     "extraction_damping_efficiency": float("nan")})
    df = pd.DataFrame(rows)
    table = extraction_table(df, "v")
    mean = table[table.scene.str.startswith("mean of 2")].iloc[0]
    assert mean["frequency efficiency"] == "3.50e-04"  # two videos: no interval
    assert mean["damping efficiency"] == "–"
    from vvtbench.reporting.leaderboard import _md_frame

    page = _md_frame(extraction_table(df, "v"))
    assert "| 2.50e-04 |" in page and "| 1.20e-05 |" in page and "0.000" not in page
    sources = extraction_sources(df, "v").iloc[0]
    assert sources["frequency efficiency"].startswith("3.50e-04")


def test_extraction_sources_keep_the_suites_order_of_variations():
    """A sweep over n_modes = 8, 10, 20 is shown in that order, not as text sorts it."""
    from vvtbench.reporting.leaderboard import extraction_sources

    rows = [{"track": "v", "solver": "vvt", "observation": "extracted", "scene": "a",
             "variation": f"n_modes={n}", "seed": 0, "nc_w": 0.5, "status": "ok",
             "extraction_precision": 1.0, "extraction_recall": 0.5} for n in (8, 10, 20)]
    table = extraction_sources(pd.DataFrame(rows), "v")
    assert table.variation.tolist() == ["n_modes=8", "n_modes=10", "n_modes=20"]


def test_one_extraction_shared_by_a_sweep_is_one_video():
    """A sweep over views (or the number of modes) re-uses one extraction of the video: its
    rows count it once in the mean and in the extractor ranking, under every variation it
    stands for; a variation whose extraction differs stays its own row."""
    from vvtbench.reporting.leaderboard import extraction_table, extractor_ranking

    rows = []
    for obs, recall in (("extracted", 0.4), ("extracted@picker", 0.2)):
        for scene, shift in (("a", 0.0), ("b", 0.1)):
            for views in (1, 2, 3):
                rows.append({"track": "v", "solver": "vvt", "observation": obs,
                             "scene": scene, "variation": f"views={views}", "seed": 0,
                             "extraction_precision": 1.0,
                             "extraction_recall": recall + shift})
    rows.append(rows[0] | {"variation": "fmax=50", "extraction_recall": 0.9})
    table = extraction_table(pd.DataFrame(rows), "v")
    mine = table[table.observation == "extracted"]
    assert sorted(mine.variation.tolist()[:3]) == ["fmax=50", "views=1, views=2, views=3",
                                                   "views=1, views=2, views=3"]
    assert mine.scene.iloc[-1] == "mean of 3"  # three videos: no interval
    ranked = extractor_ranking(pd.DataFrame(rows), "v").set_index("observation")
    assert ranked.videos.tolist() == [3, 2]
