"""docs/tutorials/your-own-video.md runs as written: every ```bash block in order, in an empty
folder, with the virtual environment's ``vvtbench`` first on PATH. One substitution keeps it
fast: the invert command's ``--solver vvt`` (minutes on 2 cores) becomes ``--solver
homogeneous`` (seconds); the solve itself is exercised by the solver's own tests."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np

from vvtbench.render.camera import Camera

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "tutorials" / "your-own-video.md"
BLOCK = re.compile(r"^```bash\n(.*?)^```", re.MULTILINE | re.DOTALL)
SLOW, FAST = "--solver vvt ", "--solver homogeneous "


def test_your_own_video_runs_as_written(tmp_path):
    blocks = BLOCK.findall(PAGE.read_text())
    assert len(blocks) >= 4, "the page lost its bash blocks"
    assert sum(SLOW in b for b in blocks) == 1, "the invert command changed: update the test"
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}",
           "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    for block in blocks:
        proc = subprocess.run(["bash", "-euo", "pipefail", "-c", block.replace(SLOW, FAST)],
                              cwd=tmp_path, env=env, capture_output=True, text=True,
                              timeout=300)
        assert proc.returncode == 0, f"{block}\n{proc.stdout[-2000:]}{proc.stderr[-2000:]}"
    # the clicks are the visible corners of the cube, at their pixels in the clip's camera
    camera = Camera.from_dict(json.loads(
        (tmp_path / "clip" / "jello_cube_defect_top" / "camera.json").read_text()))
    rows = (tmp_path / "clicks.csv").read_text().split()[1:]
    assert len(rows) == 7
    xyz = np.array([[float(x) for x in r.split(",")[1:4]] for r in rows])
    uv = np.array([[float(x) for x in r.split(",")[4:6]] for r in rows])
    assert set(np.unique(xyz)) == {0.0, 0.05}
    assert np.abs(camera.project(xyz) - uv).max() < 0.01
    cal = json.loads((tmp_path / "calib" / "calibration.json").read_text())
    assert cal["max_px"] < 0.1
    report = (tmp_path / "result" / "report.md").read_text()
    assert report.startswith("# Material map")
    with np.load(tmp_path / "result" / "fields.npz") as fields:
        assert fields["w"].shape == (512,)
    modes = json.loads((tmp_path / "result" / "modes.json").read_text())
    assert modes["n_modes_used"] == 10
    assert abs(modes["frequencies_hz"][0] - 5.21) < 0.1  # the cube's first simulated mode
