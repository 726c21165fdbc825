"""Sealed plug-ins: a hostile solver or extractor finds no truth by any route, writes nowhere
but its own output, reaches no network, and leaves no process behind."""

from __future__ import annotations

import json
import os
import shutil
import socket
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from vvtbench.observe import observe
from vvtbench.scene.scene import load_scene
from vvtbench.solving.sealed import SealedError, extract_sealed, sandbox_kind, solve_sealed

pytestmark = pytest.mark.skipif(sys.platform != "linux" or sandbox_kind() != "bwrap",
                                reason="bubblewrap cannot create a sandbox here (.ci/setup "
                                       "installs it; it needs user or root namespaces)")

HOSTILE = '''
import dataclasses, gc, inspect, os, socket, subprocess, sys, time
import numpy as np
from vvtbench.solving.problem import Estimate

SECRET = {secret!r}
TRUTH_FILE = {truth!r}
PORT = {port}
MARKER = {marker!r}


@dataclasses.dataclass
class Config:
    pass


def peek():
    seen = []
    if any(type(o).__name__ == "Truth" for o in gc.get_objects()):
        seen.append("a Truth object in memory")
    frame = inspect.currentframe()
    while frame is not None:
        if any(type(v).__name__ == "Truth" for v in frame.f_locals.values()):
            seen.append("a Truth in a caller's frame")
        frame = frame.f_back
    for path in (TRUTH_FILE, SECRET):
        if os.path.exists(path) and (os.path.isfile(path) or os.listdir(path)):
            seen.append("saw " + path)
    for root, _, files in os.walk(os.path.dirname(SECRET)):
        if any(f.startswith("truth") for f in files):
            seen.append("found truth under " + root)
    if SECRET in " ".join(sys.argv) + os.getcwd() + repr(dict(os.environ)):
        seen.append("the secret path in argv, cwd or environment")
    try:
        with open(os.path.join(SECRET, "victim.txt"), "w") as f:
            f.write("owned")
        seen.append("wrote into the secret folder")
    except OSError:
        pass
    try:
        socket.create_connection(("127.0.0.1", PORT), timeout=2).close()
        seen.append("reached the network")
    except OSError:
        pass
    return seen


class Peek:
    name = "peek"
    version = "0"
    description = "hostile"
    Config = Config

    def __init__(self, config=None):
        pass

    def solve(self, problem):
        seen = peek()
        m = problem.n_params
        return Estimate(w=np.full(m, 9000.0), v=np.full(m, 1000.0),
                        extra={{"seen": "; ".join(seen)}})


class Escape(Peek):
    name = "escape"

    def solve(self, problem):
        subprocess.Popen([sys.executable, "-c",
                          "import os, time; os.setsid(); time.sleep(300)  # " + MARKER])
        time.sleep(300)


class Linger(Peek):
    name = "linger"

    def solve(self, problem):
        subprocess.Popen([sys.executable, "-c",
                          "import os, time; os.setsid(); time.sleep(300)  # " + MARKER])
        time.sleep(0.5)
        return super().solve(problem)


class Link(Peek):
    name = "link"

    def solve(self, problem):
        import atexit

        def swap():  # after the child saved the estimate
            for name in ("estimate.npz", "estimate.json"):
                os.remove("out/" + name)
                os.symlink("/etc/hostname", "out/" + name)

        atexit.register(swap)
        return super().solve(problem)


class Liar(Peek):
    name = "liar"
    uses_truth = False
    calls = [0]

    def __init__(self, config=None):
        type(self).uses_truth = True  # claims to be a reference once running


class ExtractPeek:
    name = "extractpeek"
    version = "0"
    description = "hostile extractor"
    Config = Config

    def __init__(self, config=None):
        seen = peek()
        if seen:
            raise RuntimeError("SAW: " + "; ".join(seen))
        from vvtbench.motion.extractors import PhaseExtractor
        self.inner = PhaseExtractor()

    def prepare(self, reference):
        return self.inner.prepare(reference)
'''


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """A problem with its truth saved in a 'run folder', and a hostile plug-in file beside it
    that knows exactly where that truth is."""
    root = tmp_path_factory.mktemp("sealed")
    secret = root / "run"
    (secret / "obs").mkdir(parents=True)
    problem, truth = observe(load_scene("jello_cube_defect_top"), observation="true",
                             n_modes=6, inference_shape=(3, 3, 3))
    truth.save(secret / "obs")
    problem.save(secret / "obs")
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen()
    marker = f"vvtbench-escape-{os.getpid()}-{time.time_ns()}"
    plugin = root / "hostile.py"
    plugin.write_text(HOSTILE.format(secret=str(secret), truth=str(secret / "obs" / "truth.npz"),
                                     port=listener.getsockname()[1], marker=marker))
    yield root, secret, problem, truth, plugin, marker
    listener.close()


def test_a_solver_finds_no_truth_by_any_route(world):
    root, secret, problem, truth, plugin, _ = world
    assert (secret / "obs" / "truth.npz").is_file()
    est, _, info = solve_sealed(f"{plugin}:Peek", {}, problem, truth=truth, secrets=[secret])
    assert info["sandbox"] == "bwrap" and info["reference"] is False
    assert est.extra["seen"] == ""
    assert not (secret / "victim.txt").exists()


def test_unsandboxed_the_child_still_gets_no_truth_object_nor_path(world, monkeypatch):
    """Without bubblewrap the files are readable (documented); but nothing hands the truth
    or its path to the plug-in."""
    root, secret, problem, truth, plugin, _ = world
    monkeypatch.setenv("VVTBENCH_SANDBOX", "none")
    sandbox_kind.cache_clear()
    try:
        est, _, info = solve_sealed(f"{plugin}:Peek", {}, problem, truth=truth,
                                    secrets=[secret])
    finally:
        monkeypatch.delenv("VVTBENCH_SANDBOX")
        sandbox_kind.cache_clear()
    assert info["sandbox"] == "none"
    seen = est.extra["seen"]
    assert "Truth" not in seen and "argv" not in seen


def _alive(marker: str) -> list[int]:
    out = []
    for entry in os.listdir("/proc"):
        try:
            if marker.encode() in Path(f"/proc/{entry}/cmdline").read_bytes():
                out.append(int(entry))
        except OSError:
            pass
    return out


@pytest.mark.parametrize("sandbox", ["bwrap", "none"])
def test_a_grandchild_that_left_the_group_ends_with_the_plugin(world, monkeypatch, sandbox):
    root, secret, problem, truth, plugin, marker = world
    if sandbox == "none":
        monkeypatch.setenv("VVTBENCH_SANDBOX", "none")
    sandbox_kind.cache_clear()
    try:
        with pytest.raises(SealedError, match="timeout"):
            solve_sealed(f"{plugin}:Escape", {}, problem, secrets=[secret], timeout=4)
    finally:
        monkeypatch.delenv("VVTBENCH_SANDBOX", raising=False)
        sandbox_kind.cache_clear()
    time.sleep(0.5)
    assert _alive(marker) == []


@pytest.mark.parametrize("sandbox", ["bwrap", "none"])
def test_a_grandchild_left_behind_by_a_finished_solve_ends_too(world, monkeypatch, sandbox):
    root, secret, problem, truth, plugin, marker = world
    if sandbox == "none":
        monkeypatch.setenv("VVTBENCH_SANDBOX", "none")
    sandbox_kind.cache_clear()
    try:
        est, _, _ = solve_sealed(f"{plugin}:Linger", {}, problem, secrets=[secret])
    finally:
        monkeypatch.delenv("VVTBENCH_SANDBOX", raising=False)
        sandbox_kind.cache_clear()
    time.sleep(0.5)
    assert est.w.size == problem.n_params and _alive(marker) == []


def test_links_in_the_output_are_refused(world):
    root, secret, problem, truth, plugin, _ = world
    with pytest.raises(SealedError, match="link"):
        solve_sealed(f"{plugin}:Link", {}, problem, secrets=[secret])


def test_a_solver_that_changes_its_mind_about_truth_gets_none(world):
    root, secret, problem, truth, plugin, _ = world
    with pytest.raises(SealedError, match="uses_truth"):
        solve_sealed(f"{plugin}:Liar", {}, problem, truth=truth, secrets=[secret])


def test_an_extractor_finds_no_truth_beside_the_video(world, tmp_path):
    root, secret, problem, truth, plugin, _ = world
    sample = secret / "sample"
    sample.mkdir(exist_ok=True)
    (sample / "truth.zarr").mkdir(exist_ok=True)
    (sample / "truth.zarr" / "truth.npz").write_bytes(b"x")
    rng = np.random.default_rng(0)
    base = rng.random((40, 40)).astype(np.float32)
    t = np.arange(64) / 200.0
    frames = np.stack([np.roll(base, 0, 0) + 0.01 * np.sin(2 * np.pi * 30 * ti) * base
                       for ti in t])
    np.save(sample / "video.npy", frames)
    out = tmp_path / "modes"
    result = extract_sealed(sample / "video.npy", 200.0,
                            {"extractor": f"{plugin}:ExtractPeek"}, out, secrets=[secret])
    assert result["sandbox"] == "bwrap"
    assert (out / "modes.json").is_file()
    assert json.loads((out / "modes.json").read_text())


def test_a_reference_solver_is_handed_the_truth(world):
    root, secret, problem, truth, plugin, _ = world
    est, _, info = solve_sealed("oracle", {"max_iter": 2}, problem, truth=truth,
                                secrets=[secret])
    assert info["reference"] is True and est.w.shape == truth.w.shape


def test_a_plugin_that_hangs_at_import_is_an_error_row_within_the_limit(tmp_path, monkeypatch):
    from test_runner_safety import TINY

    from vvtbench.bench import graph, run_suite

    monkeypatch.setattr(graph, "DESCRIBE_FLOOR", 3.0)  # the import's floor, not its mechanism

    (tmp_path / "tiny.toml").write_text(TINY)
    plugin = tmp_path / "slow.py"
    plugin.write_text("import time\ntime.sleep(1000)\n")
    t0 = time.perf_counter()
    df = run_suite(str(tmp_path / "tiny.toml"), ["homogeneous", f"{plugin}:Slow"],
                   tmp_path / "run", progress=False, timeout=3)
    assert time.perf_counter() - t0 < 30
    rows = df.set_index("solver")
    assert rows.loc["homogeneous", "status"] == "ok"
    slow = df[df.solver != "homogeneous"].iloc[0]
    assert slow.status == "error" and "timeout" in slow.error


NEGATIVE = '''
import dataclasses
import numpy as np
from vvtbench.solving.problem import Estimate


@dataclasses.dataclass
class Config:
    pass


class Negative:
    name = "negative"
    version = "0"
    description = "a field that is not positive"
    Config = Config

    def __init__(self, config=None):
        pass

    def solve(self, problem):
        w = np.full(problem.n_params, problem.w_mean)
        w[0] = -1.0
        return Estimate(w=w, v=np.full(problem.n_params, problem.v0))
'''


def test_solve_states_an_invalid_estimate_first_and_draws_nothing(tmp_path, capsys):
    from vvtbench.cli import main

    plugin = tmp_path / "neg.py"
    plugin.write_text(NEGATIVE)
    out = tmp_path / "out"
    args = ["solve", "homogeneous", "jello_cube_defect_top", "--grid", "3", "3", "3",
            "--modes", "4", "-o", str(out)]
    assert main(args) == 0 and (out / "slices.png").is_file()
    capsys.readouterr()
    assert main(["solve", f"{plugin}:Negative", *args[2:]]) == 1
    err = capsys.readouterr().err
    assert err.startswith("INVALID ESTIMATE, not a result: negative") and "not positive" in err
    assert not (out / "slices.png").exists()  # the earlier figure would read as this result
    assert json.loads((out / "solve.json").read_text())["status"] == "invalid"


def test_solve_leaves_nothing_half_written_on_a_full_disk(tmp_path, monkeypatch, capsys):
    import errno

    import vvtbench.reporting.plots
    from vvtbench.cli import main

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(vvtbench.reporting.plots, "plot_fields", full)
    out = tmp_path / "out"
    assert main(["solve", "homogeneous", "jello_cube_defect_top", "--grid", "3", "3", "3",
                 "--modes", "4", "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "No space left on device" in err[0] and str(out) in err[0]
    assert list(out.iterdir()) == []


def test_a_file_the_config_names_is_shown_to_the_child_where_it_names_it(tmp_path,
                                                                        monkeypatch):
    from solvers.learned import weights_path
    from vvtbench.samples.reader import sha256_file
    from vvtbench.solving.sealed import describe_sealed

    shutil.copy(weights_path("cube_defects"), tmp_path / "w.npz")
    monkeypatch.chdir(tmp_path)
    for given in ("w.npz", str(tmp_path / "w.npz")):
        d = describe_sealed("solver", "learned", {"weights": given})
        assert sha256_file(tmp_path / "w.npz") in json.dumps(d["inputs"]), d["inputs"]
        assert d["config"]["weights"] == given


def test_working_folders_of_a_killed_process_are_removed_and_no_other(tmp_path):
    """A process killed outright leaves its sealed working folders; the next sweep removes
    those whose owner is gone and leaves live owners', foreign hosts', unmarked folders and
    links alone."""
    import subprocess

    from vvtbench.solving.sealed import OWNER, PREFIX, _owner, remove_stale_scratch

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    me = _owner()

    def folder(name: str, owner: dict | None) -> Path:
        path = tmp_path / (PREFIX + name)
        (path / "scratch").mkdir(parents=True)
        (path / "scratch" / "big.bin").write_bytes(b"x" * 1000)
        if owner is not None:
            (path / OWNER).write_text(json.dumps(owner))
        return path

    stale = folder("dead", {**me, "pid": dead.pid})
    reused = folder("reused", {**me, "start": "1"})  # this pid, another start: a reused pid
    live = folder("live", me)
    foreign = folder("foreign", {**me, "host": me["host"] + "-other", "pid": dead.pid})
    unmarked = folder("unmarked", None)
    odd = [folder(f"odd{i}", {**me, "pid": pid}) for i, pid in
           enumerate([2**70, 2**40, -1, 0, "12", 1.5, True, None])]
    (folder("garbled", None) / OWNER).write_bytes(b"\xff{not json")
    (tmp_path / (PREFIX + "link")).symlink_to(stale)
    other = tmp_path / "not-ours"
    other.mkdir()
    (other / OWNER).write_text(json.dumps({**me, "pid": dead.pid}))
    removed = remove_stale_scratch(tmp_path)
    assert sorted(removed) == sorted([stale, reused])
    assert not stale.exists() and not reused.exists()
    assert live.is_dir() and foreign.is_dir() and unmarked.is_dir() and other.is_dir()
    assert all(path.is_dir() for path in odd)
    assert (tmp_path / (PREFIX + "garbled")).is_dir()
    assert (tmp_path / (PREFIX + "link")).is_symlink()


def test_the_first_sealed_call_sweeps_stale_folders_and_leaves_none_of_its_own(tmp_path,
                                                                             monkeypatch):
    import subprocess
    import tempfile

    from vvtbench.solving import sealed

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    monkeypatch.setattr(sealed, "_SWEPT", set())
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    stale = tmp_path / (sealed.PREFIX + "dead")
    stale.mkdir()
    (stale / sealed.OWNER).write_text(json.dumps({**sealed._owner(), "pid": dead.pid}))
    sealed.forget_descriptions()
    assert sealed.describe_sealed("solver", "homogeneous", timeout=120)["name"] == "homogeneous"
    assert not list(tmp_path.glob(sealed.PREFIX + "*"))
