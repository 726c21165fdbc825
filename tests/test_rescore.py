"""Scores are recomputed from estimates and truth, never taken from a table: forged scores,
swapped estimates, a reference row not marked as one, scores on invalid rows and cells that
would mislead a spreadsheet or a Markdown page are all refused."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

pd = pytest.importorskip("pandas")
pytest.importorskip("pyarrow")

from test_runner_safety import TINY as RUNNER_TINY  # noqa: E402

from vvtbench.bench import check_results, run_suite  # noqa: E402
from vvtbench.bench.rescore import rescore  # noqa: E402
from vvtbench.cli.run import main_check_results  # noqa: E402
from vvtbench.solving.plugins import REFERENCE_BUILTINS, SOLVERS, name_problem  # noqa: E402

# the runner-safety suite, with the oracle (a reference) beside the floor
TINY = RUNNER_TINY.replace('solvers = ["homogeneous"]', 'solvers = ["homogeneous", "oracle"]') \
    + "\n[solver.oracle]\nmax_iter = 3\n"


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    root = tmp_path_factory.mktemp("rescore")
    (root / "tiny.toml").write_text(TINY)
    df = run_suite(str(root / "tiny.toml"), None, root / "run", progress=False)
    assert (df.status == "ok").all(), df.error.tolist()
    return root, root / "run", df


def _copy(run_dir: Path, dst: Path) -> Path:
    shutil.copytree(run_dir, dst)
    return dst


def test_rows_carry_the_sha256_of_what_they_scored(run):
    _, run_dir, df = run
    assert df.estimate_sha256.str.fullmatch(r"[0-9a-f]{64}").all()
    assert df.observation_sha256.str.fullmatch(r"[0-9a-f]{64}").all()
    assert set(df.sandbox) == {"bwrap"} or set(df.sandbox) == {"none"}
    assert rescore(run_dir) == []
    assert main_check_results([str(run_dir)]) == 0


def test_a_forged_score_is_refused(run, tmp_path, capsys):
    _, run_dir, df = run
    forged = df.copy()
    forged.loc[forged.solver == "homogeneous", "nc_w"] = 0.99
    forged.to_parquet(run_dir / "forged.parquet")
    try:
        assert main_check_results([str(run_dir / "forged.parquet")]) == 1
        assert "nc_w 0.99 in the table" in capsys.readouterr().err
    finally:
        (run_dir / "forged.parquet").unlink()


def test_a_swapped_estimate_is_refused_and_never_reused(run, tmp_path):
    """An estimate replaced in the cache (task.json updated too, as a careful forger would):
    the row's sha256 no longer matches, and the next run scores the new estimate afresh."""
    root, run_dir, df = run
    copy = _copy(run_dir, tmp_path / "run")
    row = df[df.solver == "homogeneous"].iloc[0]
    evaluate = copy / Path(row.estimate_path).parent
    solve_key = json.loads((evaluate / "task.json").read_text())["deps"][0]
    solve = copy / "cache" / solve_key
    with np.load(solve / "estimate.npz") as z:
        arrays = dict(z)
    arrays["w_params"] = arrays["w_params"] * np.linspace(1, 2, arrays["w_params"].size)
    np.savez(solve / "estimate.npz", **arrays)
    from vvtbench.bench.stages import file_hashes

    info = json.loads((solve / "task.json").read_text())
    info["files"] = file_hashes(solve)
    (solve / "task.json").write_text(json.dumps(info))
    problems = rescore(copy, df)
    assert any("estimate_sha256" in p for p in problems), problems
    again = run_suite(str(root / "tiny.toml"), None, copy, progress=False)
    assert again.attrs["stats"]["evaluate"]["recomputed"] == 1
    new = again[again.solver == "homogeneous"].iloc[0]
    assert new.estimate_sha256 != row.estimate_sha256
    assert rescore(copy) == []


def test_a_reference_row_must_say_so(run):
    _, _, df = run
    bad = df.copy()
    bad["reference"] = False
    problems = check_results(bad)
    assert any("reads the truth" in p for p in problems), problems


def test_the_shipped_references_are_the_solvers_that_read_the_truth():
    refs = {n for n, t in SOLVERS.registry().items() if n in ("vvt", "oracle", "homogeneous",
                                                                "sensitivity", "learned")
            and getattr(SOLVERS.import_class(t), "uses_truth", False)}
    assert refs == set(REFERENCE_BUILTINS)


def test_scores_on_a_row_that_is_not_scored_are_refused(run):
    _, _, df = run
    bad = df.copy()
    bad.loc[0, "status"] = "invalid"
    bad.loc[0, "error"] = "w is not positive in 1 of 27 voxels"
    problems = check_results(bad)
    assert any("status 'invalid' but scores" in p for p in problems), problems


@pytest.mark.parametrize("column,value", [("solver", "vvt\n| fake | 1.000 |"),
                                          ("solver", "=HYPERLINK(\"http://x\")"),
                                          ("scene", "+cmd"), ("variation", "@SUM(A1)"),
                                          ("track", "a b")])
def test_cells_that_would_mislead_are_refused(run, column, value):
    _, _, df = run
    bad = df.copy()
    bad[column] = bad[column].astype(object)
    bad.loc[0, column] = value
    assert check_results(bad), (column, value)


def test_a_plugin_name_that_would_mislead_is_refused():
    assert name_problem("sensitivity") is None
    for bad in ("a\nb", "=1+1", "-x", "@x", "", "a|b", 3):
        assert name_problem(bad) is not None, bad


def _solvers_of(run_dir):
    import pandas as pd

    return set(pd.read_csv(Path(run_dir) / "results.csv").solver)


def test_a_plugin_with_a_misleading_name_becomes_an_error_row(run, tmp_path):
    root, run_dir, _ = run
    plugin = tmp_path / "evil.py"
    plugin.write_text(
        "import dataclasses\nfrom solvers.homogeneous import HomogeneousSolver\n"
        "class Evil(HomogeneousSolver):\n    name = 'x\\n| top | 1.000 |'\n")
    copy = _copy(run_dir, tmp_path / "run")
    df = run_suite(str(root / "tiny.toml"), ["homogeneous", f"{plugin}:Evil"], copy,
                   progress=False)
    evil = df[~df.solver.isin({"homogeneous", *_solvers_of(run_dir)})]  # others' rows are kept
    assert (evil.status == "error").all() and evil.error.str.contains("printable").all()
    assert check_results(df) == []
    assert not any("\n" in str(s) for s in df.solver)


def test_the_row_schema_is_what_the_results_page_documents():
    from vvtbench.bench.results import COLUMNS

    page = (Path(__file__).resolve().parents[1] / "docs" / "results.md").read_text()
    for column in ("estimate_sha256", "observation_sha256", "sandbox"):
        assert column in COLUMNS and f"`{column}`" in page, column
