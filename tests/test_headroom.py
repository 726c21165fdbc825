"""Headroom on the board: the ceilings table beside a results table, paired means over the
instances that have a ceiling, and the section the leaderboard adds for them."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from vvtbench.bench import read_results
from vvtbench.bench.results import METRIC_COLUMNS
from vvtbench.cli.leaderboard import main_leaderboard
from vvtbench.reporting.headroom import (
    COLUMNS,
    CeilingsError,
    headroom_table,
    read_ceilings,
    track_coverage,
)
from vvtbench.reporting.leaderboard import build
from vvtbench.scoring.stats import paired_comparison

SCENES = [f"fam-test-{i:05d}" for i in range(8)]


def _row(track, scene, solver, nc, status="ok", reference=False):
    """A results row that passes check_results (true modes, 10 of them)."""
    metrics = {c: np.nan for c in METRIC_COLUMNS}
    if status == "ok":
        metrics |= dict(nc_w=nc, nc_v=nc / 2, nc_w_uncentered=0.5, nc_v_uncentered=0.5,
                        sigma_star_w=1.0, sigma_star_v=1.0, nc_at_sigma_star_w=0.5,
                        nc_at_sigma_star_v=0.5, mode_mac=0.9, freq_err_raw=0.01,
                        freq_err_scaled=0.01)
    return dict(track=track, solver=solver, solver_version="1.0.0", config_hash="0" * 16,
                config="{}", scene=scene, variation="base",
                variation_options=json.dumps({"n_modes": 10}), seed=0, observation="true",
                n_modes=10, n_modes_observed=10, **metrics, runtime_s=1.0, status=status,
                error="" if status == "ok" else "non-finite w", vvtbench_version="0.1.0",
                dataset_revision="0" * 16, estimate_path=None, traceback_path=None,
                reference=reference)


def _results(folder):
    """Tracks `t` (8 scenes) and `u` (2 scenes): solvers `a`, `b` and the reference `oracle`;
    `a` is invalid on scene 1."""
    rng = np.random.default_rng(0)
    rows = []
    for track, scenes in (("t", SCENES), ("u", SCENES[:2])):
        for i, scene in enumerate(scenes):
            for solver, base in (("a", 0.6), ("b", 0.4), ("oracle", 0.8)):
                bad = solver == "a" and i == 1
                rows.append(_row(track, scene, solver, base + 0.05 * rng.standard_normal(),
                                 status="invalid" if bad else "ok",
                                 reference=solver == "oracle"))
    path = folder / "results.csv"
    pd.DataFrame(rows).to_csv(path, index=False)
    return path


def _ceilings(folder, scenes=SCENES[:6], track="t"):
    """Ceilings of ``track`` on ``scenes`` (w and v, view data), beside the results."""
    rows = []
    for i, scene in enumerate(scenes):
        for kind, top in (("w_view", 0.9 + 0.01 * i), ("v_view", 0.95)):
            rows.append(dict(instance=scene, track=track, observation="true", n_modes=10,
                             kind=kind, ceiling=top, eps=1e-3, homog_nc=0.85, method="2",
                             inputs_sha256="0" * 64))
    path = folder / "ceilings.csv"
    pd.DataFrame(rows, columns=list(COLUMNS)).to_csv(path, index=False)
    return path


def test_headroom_is_paired_over_the_instances_with_a_ceiling_and_a_valid_row(tmp_path):
    res = read_results(_results(tmp_path))
    ceil = read_ceilings(_ceilings(tmp_path))
    t = headroom_table(res, ceil)
    assert set(t.track) == {"t"}  # no ceiling on track u: no headroom there
    rec = {r["solver"]: r for r in t.to_dict("records")}
    assert track_coverage(res, ceil, "t") == (6, 8)
    assert rec["a"]["with_ceiling"] == 6 and rec["a"]["instances"] == 8
    # a: scene 1 invalid, scenes 6 and 7 without a ceiling: 5 pairs
    assert rec["a"]["nc_w_n"] == 5 and rec["b"]["nc_w_n"] == 6
    a = res[(res.track == "t") & (res.solver == "a")].set_index("scene")
    top = ceil[ceil.kind == "w_view"].set_index("instance").ceiling
    keep = [s for s in SCENES[:6] if s != SCENES[1]]
    want = paired_comparison(top[keep].to_numpy(), a.nc_w[keep].to_numpy())
    assert rec["a"]["nc_w_mean"] == pytest.approx(want["mean_diff"])
    assert rec["a"]["nc_w_ci_low"] == pytest.approx(want["ci_low"])
    assert rec["a"]["nc_v_mean"] == pytest.approx(
        np.mean(0.95 - a.nc_v[keep].to_numpy()))
    assert rec["oracle"]["reference"] and t.solver.iloc[-1] == "oracle"


def test_a_ceiling_applies_only_to_its_source_and_number_of_modes(tmp_path):
    res = read_results(_results(tmp_path))
    ceil = read_ceilings(_ceilings(tmp_path)).assign(n_modes=20)
    assert headroom_table(res, ceil).empty


def test_the_board_shows_headroom_only_where_ceilings_are(tmp_path):
    src = _results(tmp_path)
    build(src, tmp_path / "plain")
    assert "headroom to the ceiling" not in (tmp_path / "plain" / "README.md").read_text()
    _ceilings(tmp_path)
    out = build(src, tmp_path / "lb")
    md = (out / "README.md").read_text()
    assert "### t — headroom to the ceiling (6 of 8 instances have a ceiling of NC w)" in md
    assert "### u — headroom" not in md
    assert "not a proof that no method can do better" in md
    assert "Over 6 of the track's 8 instances" in md
    assert "headroom to the ceiling" in (out / "index.html").read_text()
    manifest = json.loads((out / "leaderboard.json").read_text())
    tracks = {t["track"]: t for t in manifest["tracks"]}
    assert len(tracks["t"]["headroom"]) == 3 and "headroom" not in tracks["u"]
    assert manifest["ceilings"].endswith("ceilings.csv")
    section = md.split("### t — headroom to the ceiling")[1].split("###")[0]
    line = next(ln for ln in section.splitlines() if ln.startswith("| true modes | base | a |"))
    cells = [c.strip() for c in line.split("|")[1:-1]]
    assert cells[4] == "5" and cells[3].startswith("+0.")  # pairs; headroom with interval
    assert "[" in cells[3]


@pytest.mark.parametrize("edit, key", [
    (lambda d: d.drop(columns="eps"), "missing column eps"),
    (lambda d: d.assign(kind="w_side"), "column kind, row 1"),
    (lambda d: d.assign(ceiling=np.nan), "column ceiling, row 1"),
    (lambda d: pd.concat([d, d.iloc[:1]]), "a second ceiling"),
])
def test_a_bad_ceilings_table_is_one_line_exit_2_nothing_written(tmp_path, capsys, edit, key):
    src = _results(tmp_path)
    path = _ceilings(tmp_path)
    edit(pd.read_csv(path)).to_csv(path, index=False)
    with pytest.raises(CeilingsError, match=key):
        read_ceilings(path)
    out = tmp_path / "lb"
    assert main_leaderboard([str(src), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(path) in err and key in err
    assert not out.exists()


def test_doctests():
    import doctest

    from vvtbench.reporting import headroom

    result = doctest.testmod(headroom)
    assert result.attempted > 0 and result.failed == 0
