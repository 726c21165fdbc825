"""The tutorials run as written: every ```bash block of the 'benchmark a solver' and 'train on
the data' pages is executed in order, in an empty folder, with the virtual environment's
`vvtbench` and `python` first on PATH; the scores they write are then checked."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

ROOT = Path(__file__).resolve().parents[1]
TUTORIALS = ROOT / "docs" / "tutorials"
BLOCK = re.compile(r"^```bash\n(.*?)^```", re.MULTILINE | re.DOTALL)


def bash_blocks(page: Path) -> list[str]:
    """The ```bash blocks of a Markdown page, in order."""
    return BLOCK.findall(page.read_text())


def _run_page(page: Path, folder: Path) -> None:
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}",
           "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    blocks = bash_blocks(page)
    assert blocks, f"{page.name} has no bash block"
    for block in blocks:
        proc = subprocess.run(["bash", "-euo", "pipefail", "-c", block], cwd=folder, env=env,
                              capture_output=True, text=True, timeout=240)
        assert proc.returncode == 0, (f"{page.name}:\n{block}\n{proc.stdout[-2000:]}"
                                      f"{proc.stderr[-2000:]}")


def test_blocks_are_found_and_other_fences_are_not():
    text = "a\n```bash\necho 1\n```\n```sh\nslow\n```\n```bash\necho 2\n```\n"
    assert BLOCK.findall(text) == ["echo 1\n", "echo 2\n"]


def _scores(folder: Path) -> pd.DataFrame:
    table = pd.read_parquet(folder / "results.parquet")
    assert len(table) == 2 and (table["status"] == "ok").all(), table
    return table


def test_benchmark_a_solver_runs_as_written(tmp_path):
    _run_page(TUTORIALS / "benchmark-a-solver.md", tmp_path)
    mine, floor = _scores(tmp_path / "host" / "scores"), _scores(tmp_path / "host" / "floor-scores")
    assert set(mine["solver"]) == {"onestep"} and set(floor["solver"]) == {"homogeneous"}
    assert (mine["split_kind"] == "challenge").all()
    # the host's truth and secret are never inside the participant's (the plug-in's) folder
    assert (tmp_path / "host" / "challenge" / "truth" / "secret.key").is_file()
    assert not any("truth" in p.name or p.name == "secret.key"
                   for p in (tmp_path / "participant").rglob("*"))
    # a uniform estimate scores 0, or no NC where the drawn truth has no defect (constant)
    assert ((floor["nc_w"].abs() < 1e-9) | floor["nc_w"].isna()).all()
    assert mine["estimate_sha256"].str.fullmatch("[0-9a-f]{64}").all()


@pytest.mark.skipif(not (TUTORIALS / "train-on-the-data.md").is_file(), reason="no page")
def test_train_on_the_data_runs_as_written(tmp_path):
    _run_page(TUTORIALS / "train-on-the-data.md", tmp_path)
    assert (tmp_path / "weights" / "learned.npz").is_file()
    assert set(_scores(tmp_path / "work" / "scores")["solver"]) == {"learned"}
