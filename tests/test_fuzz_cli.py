"""Table-driven fuzz of the command line: every command with bad numbers, missing files,
folders where files are expected, damaged samples and misspelt names.

Each case runs ``vvtbench.cli.main(argv)`` in-process and must end with the documented exit
status (2 bad input, 1 problems found / internal error), exactly one line on stderr, and no
traceback. Run as a script (``python tests/test_fuzz_cli.py``) it prints how every case
ended instead: clear, unclear, silently wrong (exit 0), crashed (traceback or an exception out
of ``main``), hung (> 120 s) -- the table in the lead's notes was made that way, before and
after.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

TINY = {
    "name": "tiny_fuzz",
    "seed": 3,
    "geometry": {"kind": "box", "cells": [4, 4, 4]},
    "material": {"E": 9000.0, "rho": 1270.0, "nu": 0.3, "defects": [
        {"shape": "box", "center": [0.03, 0.02, 0.035], "size": [0.02, 0.02, 0.02],
         "E": 9.0e4, "rho": 2000.0}]},
    "excitation": {"kind": "pluck", "at": [0.05, 0.0, 0.05], "displacement": 0.0006},
    "simulation": {"n_modes": 8, "duration": 0.5, "fps": 400.0},
    "camera": {"resolution": [80, 80], "position": [0.16, -0.13, 0.13],
               "look_at": [0.025, 0.025, 0.022], "fov_y_deg": 30.0},
    "render": {"supersample": 2},
}

S = ["solve", "vvt", "{ok}", "-o", "{out}"]
E = ["extract", "{ok}", "-o", "{out}"]
# (id, argv with {placeholders}, expected exit status)
CASES: list[tuple[str, list[str], int]] = [
    # --- commands and names
    ("command misspelt", ["simulat"], 2),
    ("command unknown", ["frobnicate", "x"], 2),
    ("no command", [], 2),
    # --- simulate
    ("simulate --modes 0", ["simulate", "--modes", "0"], 2),
    ("simulate --modes -3", ["simulate", "--modes", "-3"], 2),
    ("simulate --modes x", ["simulate", "--modes", "x"], 2),
    ("simulate --modes 99999", ["simulate", "--modes", "99999"], 2),
    ("simulate scene misspelt", ["simulate", "jelo_cube_defect_top"], 2),
    ("simulate scene is a folder", ["simulate", "{dir}"], 2),
    ("simulate scene not TOML", ["simulate", "{badtoml}"], 2),
    ("simulate scene binary", ["simulate", "{binary}"], 2),
    ("simulate scene missing", ["simulate", "{tmp}/nope.toml"], 2),
    # --- solve: numbers
    ("solve --modes 0", [*S, "--modes", "0"], 2),
    ("solve --modes -1", [*S, "--modes", "-1"], 2),
    ("solve --modes 2.5", [*S, "--modes", "2.5"], 2),
    ("solve --grid 0 4 4", [*S, "--grid", "0", "4", "4"], 2),
    ("solve --grid 4 4 4 4", [*S, "--grid", "4", "4", "4", "4"], 2),
    ("solve --grid 4 4 (box)", [*S, "--grid", "4", "4"], 2),
    ("solve --grid 1000 4 4", [*S, "--grid", "1000", "4", "4"], 2),
    ("solve --grid x", [*S, "--grid", "x"], 2),
    ("solve --geometry-scale -1", [*S, "--geometry-scale", "-1"], 2),
    ("solve --geometry-scale 0", [*S, "--geometry-scale", "0"], 2),
    ("solve --geometry-scale nan", [*S, "--geometry-scale", "nan"], 2),
    ("solve --geometry-scale inf", [*S, "--geometry-scale", "inf"], 2),
    ("solve --set max_iter=0", [*S, "--set", "max_iter=0"], 2),
    ("solve --set max_iter=-1", [*S, "--set", "max_iter=-1"], 2),
    ("solve --set max_iter=abc", [*S, "--set", "max_iter=abc"], 2),
    ("solve --set tol=nan", [*S, "--set", "tol=nan"], 2),
    ("solve --set tol=inf", [*S, "--set", "tol=inf"], 2),
    ("solve --set nosuch=1", [*S, "--set", "nosuch=1"], 2),
    ("solve --set noequals", [*S, "--set", "noequals"], 2),
    ("solve --visibility bad", [*S, "--visibility", "bad"], 2),
    # --- solve: names and files
    ("solve solver misspelt", ["solve", "vt", "{ok}", "-o", "{out}"], 2),
    ("solve solver file missing", ["solve", "{tmp}/none.py:X", "{ok}", "-o", "{out}"], 2),
    ("solve solver class missing", ["solve", "{plugin}:Nope", "{ok}", "-o", "{out}"], 2),
    ("solve solver not a solver", ["solve", "{plugin}:NotASolver", "{ok}", "-o", "{out}"], 2),
    ("solve target missing", ["solve", "vvt", "{tmp}/nope", "-o", "{out}"], 2),
    ("solve target misspelt scene", ["solve", "vvt", "jello_cube_defekt_top", "-o", "{out}"],
     2),
    ("solve target empty folder", ["solve", "vvt", "{dir}", "-o", "{out}"], 2),
    ("solve target not TOML", ["solve", "vvt", "{badtoml}", "-o", "{out}"], 2),
    ("solve target binary file", ["solve", "vvt", "{binary}", "-o", "{out}"], 2),
    ("solve truncated video (byte cut)",
     ["solve", "vvt", "{trunc}", "-o", "{out}", "--modes", "4"], 2),
    ("solve video of 86 frames", ["solve", "vvt", "{cut}", "-o", "{out}", "--modes", "4"], 2),
    ("solve video resized", ["solve", "vvt", "{resized}", "-o", "{out}", "--modes", "4",
                             "--observation", "true"], 2),
    ("solve edited scene.toml", ["solve", "vvt", "{scene}", "-o", "{out}", "--modes", "4",
                                 "--observation", "true"], 2),
    ("solve deleted zarr chunk", ["solve", "vvt", "{chunk}", "-o", "{out}", "--modes", "4",
                                  "--observation", "true"], 2),
    ("solve truncated zarr chunk", ["solve", "vvt", "{chunkcut}", "-o", "{out}", "--modes", "4",
                                    "--observation", "true"], 2),
    ("solve truth.json not JSON", ["solve", "vvt", "{badjson}", "-o", "{out}", "--modes", "4"], 2),
    ("solve -o inside the sample", ["solve", "vvt", "{ok}", "-o", "{ok}/x"], 2),
    ("solve -o is the sample", ["solve", "vvt", "{ok}", "-o", "{ok}"], 2),
    ("solve -o is a file", ["solve", "vvt", "{ok}", "-o", "{binary}"], 2),
    ("solve --clicks missing", [*S, "--clicks", "{tmp}/none.json"], 2),
    ("solve --clicks is a folder", [*S, "--clicks", "{dir}"], 2),
    ("solve --modes-file missing", [*S, "--modes-file", "{tmp}/none"], 2),
    ("solve --modes-file is a file", [*S, "--modes-file", "{binary}"], 2),
    # --- extract: numbers
    ("extract --fps 0", [*E, "--fps", "0"], 2),
    ("extract --fps -1", [*E, "--fps", "-1"], 2),
    ("extract --fps nan", [*E, "--fps", "nan"], 2),
    ("extract --fmin 50 --fmax 10", [*E, "--fmin", "50", "--fmax", "10"], 2),
    ("extract --fmax 0", [*E, "--fmax", "0"], 2),
    ("extract --fmax 1e6", [*E, "--fmax", "1e6"], 2),
    ("extract --max-modes 0", [*E, "--max-modes", "0"], 2),
    ("extract --scales 0", [*E, "--scales", "0"], 2),
    ("extract --orientations 0", [*E, "--orientations", "0"], 2),
    ("extract --batch 0", [*E, "--batch", "0"], 2),
    ("extract --average 0", [*E, "--average", "0"], 2),
    ("extract --workers 0", [*E, "--workers", "0"], 2),
    ("extract --memory-budget-mb 0", [*E, "--memory-budget-mb", "0"], 2),
    ("extract --sigma -1", [*E, "--sigma", "-1"], 2),
    ("extract --prominence nan", [*E, "--prominence", "nan"], 2),
    ("extract --min-power-ratio 2", [*E, "--min-power-ratio", "2"], 2),
    ("extract --roi 5,1,0,3", [*E, "--roi", "5,1,0,3"], 2),
    ("extract --roi 0,500,0,500", [*E, "--roi", "0,500,0,500"], 2),
    ("extract --max-frames 0", [*E, "--max-frames", "0"], 2),
    # --- extract: files
    ("extract video missing", ["extract", "{tmp}/none.mkv", "-o", "{out}"], 2),
    ("extract folder without video", ["extract", "{dir}", "-o", "{out}"], 2),
    ("extract text file as video", ["extract", "{badtoml}", "-o", "{out}", "--fps", "100"], 2),
    ("extract truncated sample video", ["extract", "{trunc}", "-o", "{out}"], 2),
    ("extract 86-frame sample video", ["extract", "{cut}", "-o", "{out}"], 2),
    ("extract sample's video file, cut", ["extract", "{cut}/video.mkv", "-o", "{out}"], 2),
    ("extract edited scene.toml", ["extract", "{scene}", "-o", "{out}"], 2),
    ("extract -o is a file", ["extract", "{ok}", "-o", "{binary}"], 2),
    ("extract -o inside the sample", ["extract", "{ok}", "-o", "{ok}/modes"], 2),
    # --- export
    ("export source missing", ["export", "{tmp}/nope", "-o", "{tmp}/x.zarr"], 2),
    ("export suite misspelt", ["export", "smok", "-o", "{tmp}/x.zarr"], 2),
    ("export -o is the source", ["export", "{ok}", "-o", "{ok}"], 2),
    ("export -o inside the source", ["export", "{ok}", "-o", "{ok}/x.zarr"], 2),
    ("export deleted zarr chunk", ["export", "{chunk}", "-o", "{tmp}/c.zarr"], 2),
    ("export 86-frame video", ["export", "{cut}", "-o", "{tmp}/c2.zarr"], 2),
    ("export empty folder", ["export", "{dir}", "-o", "{tmp}/e.zarr"], 2),
    ("export --format bad", ["export", "{ok}", "-o", "{tmp}/f.zarr", "--format", "bad"], 2),
    # --- verify
    ("verify missing", ["verify", "{tmp}/nope"], 2),
    ("verify a text file", ["verify", "{badtoml}"], 2),
    ("verify an empty folder", ["verify", "{dir}"], 2),
    ("verify truncated video", ["verify", "{trunc}"], 1),
    ("verify 86-frame video", ["verify", "{cut}"], 1),
    ("verify edited scene.toml", ["verify", "{scene}"], 1),
    ("verify deleted chunk", ["verify", "{chunk}"], 1),
    ("verify truth.json not JSON", ["verify", "{badjson}"], 1),
    # --- the other commands
    ("generate --frames 0", ["generate", "{ok}/scene.toml", "-o", "{out}", "--frames", "0"],
     2),
    ("generate --resolution 0x0", ["generate", "{ok}/scene.toml", "-o", "{out}",
                                   "--resolution", "0x0"], 2),
    ("generate --consumer-crf -5", ["generate", "{ok}/scene.toml", "-o", "{out}",
                                    "--consumer-crf", "-5", "--frames", "2"], 2),
    ("generate scene misspelt", ["generate", "jello_cube_defekt_top", "-o", "{out}"], 2),
    ("run suite misspelt", ["run", "smok", "-o", "{out}"], 2),
    ("run suite not TOML", ["run", "{badtoml}", "-o", "{out}"], 2),
    ("run --set bad choice", ["run", "smoke", "--set", "oracle.method=bogus", "-o", "{out}"], 2),
    ("run --set nan", ["run", "smoke", "--set", "sensitivity.repeat_rtol=nan", "-o", "{out}"],
     2),
    ("run --set unknown key", ["run", "smoke", "--set", "vvt.nosuch=1", "-o", "{out}"], 2),
    ("run --set unknown solver", ["run", "smoke", "--set", "nosuch.x=1", "-o", "{out}"], 2),
    ("check-results missing", ["check-results", "{tmp}/none.parquet"], 2),
    ("leaderboard missing", ["leaderboard", "{tmp}/none.parquet", "-o", "{out}"], 2),
]
# Cases whose command is outside the CLI-safety helper's files; each is a note to its owner.


def _build(root: Path) -> dict[str, str]:
    """The fixture tree: a sample, its damaged copies, odd files; placeholders -> paths."""
    import numpy as np

    from vvtbench.samples.generate import generate
    from vvtbench.scene.scene import parse_scene
    from vvtbench.video.files import ffmpeg_exe

    ok = generate(parse_scene(json.loads(json.dumps(TINY)), "tiny_fuzz"), root / "samples",
                  progress=False)
    paths = {"ok": ok, "tmp": root, "out": root / "out", "dir": root / "empty"}
    (root / "empty").mkdir()

    def copy(name: str) -> Path:
        dst = root / name
        shutil.copytree(ok, dst)
        paths[name] = dst
        return dst

    video = copy("trunc") / "video.mkv"
    video.write_bytes(video.read_bytes()[: video.stat().st_size * 43 // 100])
    cut = copy("cut") / "video.mkv"
    subprocess.run([ffmpeg_exe(), "-v", "error", "-y", "-i", str(ok / "video.mkv"), "-map", "0",
                    "-c", "copy", "-frames:v", "86", str(root / "cut86.mkv")], check=True)
    shutil.move(root / "cut86.mkv", cut)
    resized = copy("resized") / "video.mkv"
    from vvtbench.video.files import VideoWriter

    with VideoWriter(resized, 40, 40, capture_fps=400) as w:
        for _ in range(200):
            w.write(np.zeros((40, 40), np.uint16))
    toml = copy("scene") / "scene.toml"
    toml.write_text(toml.read_text().replace("E = 90000.0", "E = 900000.0"))
    chunks = sorted(p for p in (ok / "truth.zarr").rglob("*")
                    if p.is_file() and "/c/" in p.as_posix() and "stiffness" in p.as_posix())
    rel = chunks[0].relative_to(ok)
    (copy("chunk") / rel).unlink()
    cc = copy("chunkcut") / rel
    cc.write_bytes(cc.read_bytes()[: max(1, cc.stat().st_size // 2)])
    (copy("badjson") / "truth.json").write_text("{not json")
    (root / "bad.toml").write_text("this is [not toml\n")
    (root / "binary.bin").write_bytes(bytes(range(256)) * 4)
    (root / "plugin.py").write_text("class NotASolver:\n    pass\n")
    paths.update(badtoml=root / "bad.toml", binary=root / "binary.bin",
                 plugin=root / "plugin.py")
    return {k: str(v) for k, v in paths.items()}


class _Hung(Exception):
    pass


def _error_lines(stderr: str) -> list[str]:
    """The lines of stderr that are not notes (``note: ...`` tells which frame rate is used)."""
    return [ln for ln in stderr.splitlines() if ln.strip() and not ln.startswith("note:")]


def run_case(argv: list[str], env: dict[str, str],
             timeout: int = int(os.environ.get("FUZZ_TIMEOUT", "120"))):
    """(exit status or None, stdout, stderr, outcome) of one case, run in-process."""
    from vvtbench.cli import main

    args = [a.format(**env) for a in argv]
    out, err = io.StringIO(), io.StringIO()

    def alarm(*_):
        raise _Hung

    old = signal.signal(signal.SIGALRM, alarm)
    signal.alarm(timeout)
    code, escaped = None, None
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                code = main(args)
            except SystemExit as e:
                code = e.code if isinstance(e.code, int) else (1 if e.code else 0)
                if isinstance(e.code, str):
                    err.write(e.code + "\n")
    except _Hung:
        escaped = "hung"
    except BaseException as e:  # noqa: BLE001 -- an exception out of main is a crash
        escaped = f"crashed: {type(e).__name__}: {e}"
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
    return code, out.getvalue(), err.getvalue(), escaped


def classify(code, stdout: str, stderr: str, escaped, expected: int) -> str:
    if escaped:
        return escaped.split(":")[0]
    if "Traceback" in stderr:
        return "crashed"
    if code == 0:
        return "silently wrong"
    lines = _error_lines(stderr)
    if code == expected and len(lines) == 1:
        return "clear"
    return "unclear"


@pytest.fixture(scope="module")
def env(tmp_path_factory) -> dict[str, str]:
    return _build(tmp_path_factory.mktemp("fuzz"))


@pytest.mark.parametrize("name,argv,expected", CASES, ids=[c[0] for c in CASES])
def test_cli_fuzz(name, argv, expected, env, request):
    shutil.rmtree(env["out"], ignore_errors=True)
    code, stdout, stderr, escaped = run_case(argv, env)
    assert escaped is None, escaped
    assert "Traceback" not in stderr and "Traceback" not in stdout
    lines = _error_lines(stderr)
    assert code == expected, (code, stderr)
    assert len(lines) == 1, stderr
    # nothing was written into the damaged or good samples
    assert not Path(env["ok"], "x").exists() and not Path(env["ok"], "modes").exists()


def main() -> int:  # pragma: no cover -- the before/after table
    import tempfile
    from collections import Counter

    root = Path(tempfile.mkdtemp(prefix="vvtbench-fuzz-"))
    env_ = _build(root)
    tally: Counter = Counter()
    for name, argv, expected in CASES:
        shutil.rmtree(env_["out"], ignore_errors=True)
        code, stdout, stderr, escaped = run_case(argv, env_)
        outcome = classify(code, stdout, stderr, escaped, expected)
        tally[outcome] += 1
        last = (stderr.strip().splitlines() or [""])[-1][:150]
        print(f"{outcome:15s} exit {code!s:4s} {name:36s} {last}", flush=True)
    print(f"\n{len(CASES)} cases: " + ", ".join(f"{k} {v}" for k, v in tally.most_common()))
    shutil.rmtree(root, ignore_errors=True)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.path.insert(0, os.getcwd())
    raise SystemExit(main())
