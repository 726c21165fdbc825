"""The ceiling search: the mode misfit and its adjoint gradient, the constrained search, the
homogenised truth's voxel means, and the committed ceilings (no solver row above them)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp

from vvtbench.fem.assembly import ParametricModel
from vvtbench.fem.mesh import box_mesh, drum_mesh
from vvtbench.fem.modal import eigenmodes
from vvtbench.scoring.ceiling import (
    Misfit,
    ModeData,
    Record,
    ceiling_at,
    constrained_minimum,
    front,
    nc_and_gradient,
    nc_objective,
    rows_above_ceiling,
)

COMMITTED = Path(__file__).resolve().parent.parent / "benchmarks" / "ceiling"


@pytest.fixture(autouse=True)
def _one_blas_thread():
    """Small dense eigenproblems: one BLAS thread is faster and independent of the machine."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        yield


def _hex8():
    mesh = box_mesh((3, 3, 3), (1.0, 1.2, 0.9))
    return ParametricModel(mesh, fixed_nodes=mesh.node_sets["bottom"])


def _tri3():
    mesh = drum_mesh("square", 1.0, 5)
    return ParametricModel(mesh, fixed_nodes=mesh.node_sets["rim"])


def _fields(model, seed=0, spread=0.4):
    rng = np.random.default_rng(seed)
    m = model.n_params
    return (9000 * np.exp(spread * rng.standard_normal(m)),
            1270 * np.exp(spread * rng.standard_normal(m)))


def _data(model, w, v, k, P=None):
    md = eigenmodes(model.K(w), model.M(v), k, method="dense")
    shapes = md.vectors if P is None else np.asarray(P @ md.vectors)
    return ModeData(shapes.T, md.eigenvalues, P)


@pytest.mark.parametrize("make", [_hex8, _tri3], ids=["hex8", "tri3"])
@pytest.mark.parametrize("observed", ["every DOF", "projected"])
def test_misfit_gradient_against_finite_differences(make, observed):
    model = make()
    w, v = _fields(model)
    P = None if observed == "every DOF" else sp.random(
        30, model.n_free, density=0.3, random_state=1, format="csr")
    data = _data(model, w, v, 5, P)
    mf = Misfit(model, data, n_extra=60, series_terms=6)
    w1, v1 = _fields(model, seed=1, spread=0.2)  # a field that does not fit
    theta = np.concatenate([np.log(w * w1 / 9000), np.log(v * v1 / 1270)])
    D, g, _ = mf(theta)
    assert D > 1e-4
    rng = np.random.default_rng(2)
    for _ in range(3):
        d = rng.standard_normal(len(theta))
        h = 1e-5
        fd = (mf.value(theta + h * d) - mf.value(theta - h * d)) / (2 * h)
        assert abs(fd - g @ d) <= 1e-4 * abs(fd) + 1e-9


def test_misfit_is_zero_on_the_exact_field_and_blind_to_a_common_scale():
    model = _hex8()
    w, v = _fields(model)
    mf = Misfit(model, _data(model, w, v, 6))
    theta = np.concatenate([np.log(w), np.log(v)])
    assert mf.value(theta) < 1e-12
    assert mf.value(theta + np.log(3.0)) < 1e-12  # (3w, 3v): the same modes
    w2, _ = _fields(model, seed=5)
    assert mf.value(np.concatenate([np.log(w2), np.log(v)])) > 1e-3


def test_nc_gradient():
    rng = np.random.default_rng(0)
    x, ref = rng.random(20) + 1, rng.random(20)
    nc, g = nc_and_gradient(x, ref)
    assert nc == pytest.approx(np.corrcoef(x, ref)[0, 1])
    d = rng.standard_normal(20)
    fd = (nc_and_gradient(x + 1e-6 * d, ref)[0] - nc_and_gradient(x - 1e-6 * d, ref)[0]) / 2e-6
    assert fd == pytest.approx(g @ d, rel=1e-5)


def test_constrained_search_raises_nc_and_keeps_the_constraint():
    """From a feasible field of low NC the search finds fields that still explain the data
    (D <= eps) and correlate better with the reference; every evaluated field is recorded."""
    model = _hex8()
    m = model.n_params
    w, v = _fields(model, seed=3)
    data = _data(model, w, v, 4)  # few modes: many fields explain them
    mf = Misfit(model, data, n_extra=6)
    rng = np.random.default_rng(4)
    ref = w * np.exp(0.5 * rng.standard_normal(m))  # what NC is scored against
    theta0 = np.concatenate([np.log(w), np.log(v)])
    eps = 2e-3
    rec = Record()
    constrained_minimum(mf, nc_objective(ref, "w", m), theta0, eps, start="truth", record=rec,
                        outer=3, inner=10)
    nc0 = nc_and_gradient(w, ref)[0]
    f, th = rec.best["eps"]
    assert mf.value(th) <= eps
    assert -f > nc0 + 0.02
    assert len(rec.misfit) == len(rec.value) > 10
    assert ceiling_at(rec.misfit, -np.asarray(rec.value), eps) == pytest.approx(-f)


def test_front_and_ceiling_at():
    d, nc = front(np.array([3.0, 1.0, 2.0, 4.0]), np.array([0.5, 0.2, 0.6, 0.55]))
    assert d.tolist() == [1.0, 2.0] and nc.tolist() == [0.2, 0.6]
    assert ceiling_at([3.0, 1.0], [0.5, 0.2], 2.0) == 0.2
    assert np.isnan(ceiling_at([3.0], [0.5], 2.0))


def test_rows_above_ceiling_flags_a_feasible_row_above():
    ceil = {"eps": 0.01, "ceiling": 0.8}
    rows = {"a": {"nc": 0.7, "D": 0.001}, "b": {"nc": 0.9, "D": 0.5},
            "c": {"nc": 0.85, "D": 0.005}}
    out = rows_above_ceiling(ceil, rows)
    assert out["feasible_above"] == ["c"]  # a field that explains the data scored higher
    assert out["infeasible_above"] == ["b"]  # above, but it does not explain the data


BOARD = COMMITTED.parent.parent / "leaderboard" / "standard" / "results.csv"
FAMILIES = ("cube_defects", "drum_defects")


def _committed(family=None):
    """The committed results (of ``family``, or every one), checked as the report checks
    them."""
    from benchmarks.ceiling import check_result

    if not COMMITTED.exists():
        return []
    files = sorted(COMMITTED.glob(f"{family or '*'}/*.json"))
    out = []
    for path in files:
        r = json.loads(path.read_text())
        check_result(r, str(path))
        out.append((path, r))
    return out


@pytest.mark.parametrize("family", FAMILIES)
def test_committed_ceilings_hold_every_feasible_row(family):
    """Over the family's committed results: no recomputed estimate that explains the data
    (D <= eps) scores above its instance's ceiling, every ceiling is at least the homogenised
    truth's NC, and each search's best field was feasible when it was found. Skipped only
    when the family has no committed result."""
    from benchmarks.ceiling import CEILINGS, has_ceiling

    results = _committed(family)
    if not results:
        pytest.skip(f"no committed {family} result")
    for path, r in results:
        assert r["family"] == family, path.name
        for stage in CEILINGS:
            if not has_ceiling(r, stage):
                continue
            c = r[stage]
            which, data = c["which"], c["data"]
            rows = {n: {"nc": s[f"nc_{which}"], "D": s[f"D_{data}"]}
                    for n, s in r["estimates"]["solvers"].items() if s.get("status") == "ok"}
            out = rows_above_ceiling(c, rows)
            assert out["feasible_above"] == [], (path.name, stage, out)
            assert out["unknown_above"] == [], (path.name, stage, out)
            assert c["ceiling"] >= r["homog"][f"nc_{which}"] - 1e-12
            if "check_D" in c:
                assert c["check_D"] <= c["eps"] * (1 + 1e-9), (path.name, stage)


@pytest.mark.parametrize("family", FAMILIES)
def test_no_board_row_above_a_committed_ceiling_explains_the_data(family):
    """Every valid row of the standard board (leaderboard/standard/results.csv) of an instance
    with a committed ceiling: a row above the ceiling must be shown not to explain the data
    (its recomputed estimate, same solver version and NC, has D > eps). A row above it that
    explains the data, or whose misfit is not known, fails. Skipped only when the family has
    no committed result."""
    from benchmarks.ceiling import CEILINGS, board_rows_above, has_ceiling, read_board

    results = _committed(family)
    if not results:
        pytest.skip(f"no committed {family} result")
    board = read_board(BOARD)
    assert board is not None, f"{BOARD} is missing"
    checked, bad = 0, []
    for path, r in results:
        res = board_rows_above(r, board)
        checked += res["checked"]
        bad += [(path.name, *x) for x in res["feasible_above"] + res["unknown_above"]]
    assert bad == [], bad
    with_ceiling = sum(has_ceiling(r, s) for _, r in results for s in CEILINGS)
    assert checked > 0 or not with_ceiling  # a committed ceiling is compared with its rows


def test_board_rows_above_a_ceiling_are_sorted_by_what_is_known():
    """A board row above a ceiling: contradicts it when its recomputed estimate (same version,
    same NC) explains the data; does not when that estimate misfits; unknown otherwise."""
    import pandas as pd

    from benchmarks.ceiling import board_rows_above

    def row(solver, nc, version="1"):
        return dict(track="t", scene="s", observation="true", n_modes=20, status="ok",
                    solver=solver, solver_version=version, nc_w=nc, nc_v=0.1)

    board = pd.DataFrame([row("fits", 0.95), row("misfits", 0.95), row("other", 0.95, "2"),
                          row("below", 0.5), row("fits", 0.99) | {"scene": "x"}])
    est = {"fits": {"status": "ok", "version": "1", "nc_w": 0.95, "D_view": 1e-4},
           "misfits": {"status": "ok", "version": "1", "nc_w": 0.951, "D_view": 1.0},
           "other": {"status": "ok", "version": "1", "nc_w": 0.95, "D_view": 1e-4},
           "below": {"status": "ok", "version": "1", "nc_w": 0.5, "D_view": 1e-4}}
    r = {"track": "t", "instance": "s", "n_modes": 20, "estimates": {"solvers": est},
         "ceil_w_view": {"which": "w", "data": "view", "eps": 1e-3, "ceiling": 0.9}}
    out = board_rows_above(r, board)
    assert out["checked"] == 4
    assert out["feasible_above"] == [("fits", "ceil_w_view")]
    assert [x[:2] for x in out["unknown_above"]] == [("other", "ceil_w_view")]
    assert [x[:2] for x in out["infeasible_above"]] == [("misfits", "ceil_w_view")]


def test_the_report_prints_no_undefined_number_and_writes_the_ceilings_table(tmp_path):
    """One committed instance: no interval (n = 1) is said, never printed as nan; the ceilings
    table has a row per ceiling kind and passes the leaderboard's check."""
    import shutil

    from benchmarks.ceiling import report
    from vvtbench.reporting.headroom import read_ceilings

    results = _committed("cube_defects")
    if not results:
        pytest.skip("no committed cube_defects result")
    path, r = results[0]
    (tmp_path / "cube_defects").mkdir()
    for f in (path, path.with_suffix(".npz")):
        shutil.copy(f, tmp_path / "cube_defects" / f.name)
    text = report(tmp_path, None, BOARD, tmp_path / "ceilings.csv")
    assert "nan" not in text.lower()
    assert "(n = 1, no interval)" in text
    assert "committed: 1 of the 50 instances of the test split (cube_true)" in text
    c = read_ceilings(tmp_path / "ceilings.csv")
    kinds = [s[5:] for s in ("ceil_w_view", "ceil_w_full", "ceil_v_view", "ceil_v_full")
             if "ceiling" in r.get(s, {})]
    assert sorted(c.kind) == sorted(kinds) and set(c.instance) == {r["instance"]}
    assert (c.inputs_sha256 == r["inputs_sha256"]).all()


@pytest.mark.parametrize("edit, key", [
    (lambda r: r.pop("track"), "missing key 'track'"),
    (lambda r: r["ceil_w_view"].pop("eps"), "ceil_w_view: missing key 'eps'"),
])
def test_a_bad_committed_result_is_one_line_exit_2(tmp_path, capsys, edit, key):
    from benchmarks.ceiling import main

    results = _committed("cube_defects")
    if not results:
        pytest.skip("no committed cube_defects result")
    path, r = results[0]
    edit(r)
    (tmp_path / "cube_defects").mkdir()
    bad = tmp_path / "cube_defects" / path.name
    bad.write_text(json.dumps(r))
    with pytest.raises(SystemExit) as exit_:
        main(["report", "-o", str(tmp_path), "--ceilings", str(tmp_path / "c.csv"),
              "--figures", str(tmp_path / "figures")])
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(bad) in err and key in err
    assert not (tmp_path / "c.csv").exists()


def test_the_committed_ceilings_table_matches_the_committed_results():
    """Every row of leaderboard/standard/ceilings.csv (the board's headroom reads it) is a
    committed ceiling, with the committed value and inputs; instances committed since the
    table was written are missing from it until the report runs again, never contradicted."""
    from benchmarks.ceiling import ceiling_rows
    from vvtbench.reporting.headroom import read_ceilings

    path = BOARD.parent / "ceilings.csv"
    if not path.exists():
        pytest.skip("no committed ceilings table")
    table = read_ceilings(path)
    committed = {(r["instance"], r["kind"]): r for r in ceiling_rows(_committed())}
    for row in table.to_dict("records"):
        key = (row["instance"], row["kind"])
        assert key in committed, f"{path.name}: {key} has no committed result"
        want = committed[key]
        assert row["ceiling"] == pytest.approx(want["ceiling"], abs=1e-12), key
        assert row["eps"] == pytest.approx(want["eps"], rel=1e-12), key
        assert row["inputs_sha256"] == want["inputs_sha256"], key
        assert (row["track"], row["method"]) == (want["track"], want["method"]), key


def test_report_doctests():
    import doctest

    import benchmarks.ceiling as module

    result = doctest.testmod(module)
    assert result.attempted > 0 and result.failed == 0


def test_a_committed_drum_ceiling_reproduces(tmp_path):
    """Regenerate one committed drum instance (modes only, ~1 s), rebuild its problem, and
    recompute the misfit and NC of the committed best field: it explains the data within the
    committed eps and scores the committed search value."""
    from benchmarks.ceiling import data_of, load, theta
    from vvtbench.samples.generate import generate
    from vvtbench.scene.families import draw

    files = [f for f in sorted(COMMITTED.glob("drum_defects/*.json"))
             if "ceiling" in json.loads(f.read_text()).get("ceil_w_view", {})]
    if not files:
        pytest.skip("no committed drum ceiling")
    r = json.loads(files[0].read_text())
    c = r["ceil_w_view"]
    index = int(r["instance"].rsplit("-", 1)[1])
    sample = generate(draw("drum_defects", "test", index), tmp_path, video=False,
                      progress=False)
    (sample / "family.json").write_text(json.dumps({"family": "drum_defects"}))
    _, _, p, t = load(sample)
    z = np.load(files[0].with_suffix(".npz"))
    w, v = z["ceil_w_view_w"].astype(float), z["ceil_w_view_v"].astype(float)
    D = Misfit(p.model, data_of(p, t)["view"]).value(theta(w, v))
    assert D <= c["eps"] * (1 + 1e-4)
    assert nc_and_gradient(w, t.w)[0] == pytest.approx(c["search"], abs=1e-5)
