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
    # a limit a loaded machine's homogeneous solve meets; the hang is ended at the limit
    df = run_suite(str(tmp_path / "tiny.toml"), ["homogeneous", f"{plugin}:Slow"],
                   tmp_path / "run", progress=False, timeout=20)
    rows = df.set_index("solver")
    assert rows.loc["homogeneous", "status"] == "ok"
    slow = df[df.solver != "homogeneous"].iloc[0]
    assert slow.status == "error" and "timeout: no result after 20 s" in slow.error


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


# --------------------------------------------------------------------------- routes to truth
# Each route a hostile walk found, as a plug-in that returns the truth when it can reach it:
# sealed, it must score nothing (an error, or an estimate that is not the truth).

CHEATS = '''
import dataclasses, glob, os, tomllib
import numpy as np
from vvtbench.api import Estimate

HERE = os.path.dirname(os.path.abspath(__file__))
SCENE_TOML = {scene!r}


def answer(problem, path):
    with np.load(path) as z:
        return Estimate(w=z["w"], v=z["v"], extra={{"read": path}})


@dataclasses.dataclass
class Config:
    truth: str = {default!r}


class Neighbour:
    """Reads truth that lies beside it: a challenge's truth, a run's cache."""
    name = "neighbour"
    version = "0"
    description = "cheat"
    Config = Config

    def __init__(self, config=None):
        self.config = config or Config()

    def solve(self, problem):
        for pattern in ("work/challenge/truth/*/truth.npz", "runs/*/cache/observe/*/truth.npz",
                        "**/truth.npz"):
            for path in glob.glob(os.path.join(HERE, pattern), recursive=True):
                return answer(problem, path)
        raise RuntimeError("no truth beside it: " + repr(sorted(os.listdir(HERE))))


class Default(Neighbour):
    """Reads the file its own config default names (a run's cached truth)."""
    name = "default"

    def solve(self, problem):
        return answer(problem, self.config.truth)


class Scene(Neighbour):
    """Recomputes the truth: a shipped scene by name, else the scene's text it carries."""
    name = "scene"

    def solve(self, problem):
        from vvtbench.api import observe
        from vvtbench.scene.scene import SCENES_DIR, load_scene, parse_scene

        errors = []
        if SCENES_DIR.exists():
            errors.append("saw " + str(SCENES_DIR))
        for make in (lambda: load_scene("jello_cube_defect_top"),
                     lambda: parse_scene(tomllib.loads(SCENE_TOML))):
            try:
                _, truth = observe(make(), observation="true", n_modes=problem.n_modes,
                                   inference_shape=(3, 3, 3))
                return Estimate(w=truth.w, v=truth.v)
            except Exception as error:
                errors.append(f"{{type(error).__name__}}: {{error}}")
        raise RuntimeError(" / ".join(errors))
'''


def _cheat(folder: Path, default: str = "") -> Path:
    from vvtbench.scene.scene import SCENES_DIR

    text = (SCENES_DIR / "jello_cube_defect_top.toml").read_text()
    plugin = folder / "my_solver.py"
    plugin.write_text(CHEATS.format(scene=text, default=default))
    return plugin


def _is_truth(est, truth) -> bool:
    return est.w.shape == truth.w.shape and np.allclose(est.w, truth.w)


def test_a_plugin_is_shown_its_file_not_the_folder_beside_it(world, tmp_path):
    """The tutorial's layout: the plug-in file beside work/challenge/truth and runs/."""
    root, secret, problem, truth, _, _ = world
    for folder in ("work/challenge/truth/instance", "runs/smoke/cache/observe/0123abcd"):
        (tmp_path / folder).mkdir(parents=True)
        truth.save(tmp_path / folder)
    plugin = _cheat(tmp_path)
    with pytest.raises(SealedError, match="no truth beside") as error:
        solve_sealed(f"{plugin}:Neighbour", {}, problem)
    assert "no truth beside it: ['my_solver.py']" in str(error.value)


def test_a_declared_package_is_shown_without_its_data_folders(world, tmp_path):
    """A plug-in in a folder with __init__.py is shown its package: its code and the data it
    ships, never a run, a challenge's truth or a scene inside it."""
    root, secret, problem, truth, _, _ = world
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("")
    np.savez(pkg / "sub" / "weights.npz", a=np.ones(3))
    for folder in ("challenge/truth/instance", "runs/smoke/cache/observe/0123abcd",
                   "sub/data/cache/observe/0123abcd"):
        (pkg / folder).mkdir(parents=True)
        truth.save(pkg / folder)
    (pkg / "scene.toml").write_text('name = "x"\n[geometry]\nkind = "box"\n')
    plugin = _cheat(pkg / "sub")
    with pytest.raises(SealedError, match="no truth beside") as error:
        solve_sealed(f"{plugin}:Neighbour", {}, problem)
    assert "'weights.npz'" in str(error.value)
    from vvtbench.solving.sealed import _hidden_in, plugin_code

    assert plugin_code("solver", f"{plugin}:Neighbour") == [pkg.resolve()]
    hidden = {p.relative_to(pkg.resolve()).as_posix() for p in _hidden_in(pkg.resolve())}
    assert hidden == {"challenge", "runs", "sub/data/cache", "scene.toml"}


def test_a_plugin_that_recomputes_the_truth_from_a_scene_scores_nothing(world, tmp_path):
    """No shipped scene is readable inside, and observe() refuses there (a scene carried in
    the plug-in's own code)."""
    root, secret, problem, truth, _, _ = world
    plugin = _cheat(tmp_path)
    with pytest.raises(SealedError) as error:
        solve_sealed(f"{plugin}:Scene", {}, problem)
    message = str(error.value)
    assert "saw" not in message and "no such scene file" in message
    assert "observe() is not available to a sealed plug-in" in message


def test_a_plugin_default_that_names_a_cached_truth_is_not_shown(tmp_path, monkeypatch):
    """Through the runner: the resolved config holds the plug-in's defaults; a default that
    names a run's cached truth is not bound into the sandbox, and the user naming it is
    refused."""
    from test_runner_safety import TINY

    from vvtbench.bench import run_suite
    from vvtbench.solving.plugins import PluginError
    from vvtbench.solving.sealed import describe_sealed

    (tmp_path / "tiny.toml").write_text(TINY)
    run = tmp_path / "run"
    run_suite(str(tmp_path / "tiny.toml"), ["homogeneous"], run, progress=False)
    (cached,) = sorted(run.glob("cache/observe/*/truth.npz"))
    (tmp_path / "plugin").mkdir()
    plugin = _cheat(tmp_path / "plugin", default=str(cached))
    df = run_suite(str(tmp_path / "tiny.toml"), ["homogeneous", f"{plugin}:Default"], run,
                   progress=False)
    row = df[df.solver == "default"].iloc[0]
    assert row.status == "error" and "No such file" in row.error, row.error
    with pytest.raises(PluginError, match="never shown a sample, run, cache, challenge"):
        describe_sealed("solver", f"{plugin}:Default", {"truth": str(cached)})


def test_a_named_file_is_refused_in_vvtbench_data_only(tmp_path):
    from vvtbench.solving.plugins import PluginError
    from vvtbench.solving.sealed import config_files

    (tmp_path / "project" / "weights").mkdir(parents=True)
    (tmp_path / "project" / "results.csv").write_text("a\n")  # a user's own table
    mine = tmp_path / "project" / "weights" / "w.npz"
    mine.write_bytes(b"x")
    assert config_files({"weights": str(mine)}) == {str(mine): mine}
    assert config_files({"weights": str(mine)}, named=[]) == {}  # a default: never shown
    (tmp_path / "run" / "x").mkdir(parents=True)
    (tmp_path / "run" / "run.json").write_text("{}")
    theirs = tmp_path / "run" / "x" / "w.npz"
    theirs.write_bytes(b"x")
    with pytest.raises(PluginError, match=r"config weights=.*lies in .*run, a vvtbench data "
                                          r"folder \(it holds run.json\)"):
        config_files({"weights": str(theirs)})
    with pytest.raises(PluginError, match="lies in .*, which the plug-in must not see"):
        config_files({"weights": str(mine)}, secrets=[tmp_path / "project"])


# --------------------------------------------------------------------------- limits

HOGS = '''
import dataclasses, os, sys, time
import numpy as np
from vvtbench.api import Estimate


@dataclasses.dataclass
class Config:
    pass


class Base:
    name = "hog"
    version = "0"
    description = "fills what it can"
    Config = Config

    def __init__(self, config=None):
        pass

    def answer(self, problem, **extra):
        m = problem.n_params
        return Estimate(w=np.full(m, 9000.0), v=np.full(m, 1000.0), extra=extra)


class Tmpfs(Base):
    """Writes 256 MB into each tmpfs it can find: memory that no address space counts."""
    def solve(self, problem):
        out = {}
        for where in ("/dev/shm/x", "/x", "/dev/x"):
            n = 0
            try:
                with open(where, "wb") as f:
                    for _ in range(64):
                        f.write(bytes(4 << 20))
                        f.flush()
                        n += 4 << 20
            except OSError:
                pass
            out[where] = n
        return self.answer(problem, **out)


class Forks(Base):
    """Three processes of 350 MB each: every one under the address-space limit."""
    def solve(self, problem):
        for _ in range(3):
            if os.fork() == 0:
                a = np.ones((350 << 20) // 8)
                time.sleep(60)
                os._exit(0)
        time.sleep(60)
        return self.answer(problem)


class Disk(Base):
    """Fills its scratch folder (/tmp) with files each smaller than the limit."""
    def solve(self, problem):
        for i in range(10000):
            with open(f"/tmp/part{i}", "wb") as f:
                f.write(bytes(8 << 20))


class Chatty(Base):
    """Prints a lot, then says how it ended."""
    def solve(self, problem):
        for i in range(20000):
            print(f"line {i} " + "x" * 20)
        print("the end", file=sys.stderr)
        return self.answer(problem)


class ChattyFails(Chatty):
    def solve(self, problem):
        print("about to fail")
        raise RuntimeError("it failed")
'''


@pytest.fixture(scope="module")
def hogs(tmp_path_factory):
    path = tmp_path_factory.mktemp("hogs") / "hogs.py"
    path.write_text(HOGS)
    return path


def test_tmpfs_memory_is_bounded_and_counted(world, hogs):
    """The sandbox's / and /dev are read-only; /dev/shm holds at most 1/8 of the limit, which
    the processes' own limit leaves room for."""
    from vvtbench.solving.sealed import _bwrap_sizes

    root, secret, problem, truth, _, _ = world
    limit = 1 << 30
    est, _, _ = solve_sealed(f"{hogs}:Tmpfs", {}, problem, memory_bytes=limit)
    assert est.extra["/x"] == 0 and est.extra["/dev/x"] == 0
    assert est.extra["/dev/shm/x"] <= limit // 8
    assert est.extra["/dev/shm/x"] > 0 or not _bwrap_sizes()  # read-only where unbounded


def test_processes_are_counted_together_against_the_memory_limit(world, hogs):
    root, secret, problem, truth, _, _ = world
    with pytest.raises(SealedError, match="out of memory: its processes held"):
        solve_sealed(f"{hogs}:Forks", {}, problem, memory_bytes=1 << 30, timeout=120)


def test_scratch_disk_is_counted_against_the_disk_limit(world, hogs):
    root, secret, problem, truth, _, _ = world
    with pytest.raises(SealedError, match="out of disk") as error:
        solve_sealed(f"{hogs}:Disk", {}, problem, disk_bytes=64 << 20, timeout=120)
    assert error.value.kind == "out of disk"


def test_a_plugins_output_is_kept_capped_and_shown_on_failure(world, hogs, tmp_path):
    from vvtbench.solving.sealed import LOG_TAIL

    root, secret, problem, truth, _, _ = world
    est, _, info = solve_sealed(f"{hogs}:Chatty", {}, problem, dest=tmp_path)
    assert info["log"].endswith("the end\n") and len(info["log"].encode()) <= LOG_TAIL
    assert "line 19999" in info["log"] and "line 0 " not in info["log"]
    assert (tmp_path / "solver.log").read_text() == info["log"]
    with pytest.raises(SealedError, match="it failed") as error:
        solve_sealed(f"{hogs}:ChattyFails", {}, problem)
    assert "about to fail" in error.value.log


# --------------------------------------------------------------------------- plug-in authors

SHAPES = '''
import dataclasses
import numpy as np
from vvtbench.api import Estimate


@dataclasses.dataclass
class Config:
    pass


class Long:
    name = "long"
    version = "0"
    description = "one voxel too many"
    Config = Config

    def __init__(self, config=None):
        pass

    def solve(self, problem):
        print("solving", problem.n_params, "voxels")
        m = problem.n_params + 1
        return Estimate(w=np.full(m, 9000.0), v=np.full(m, 1000.0))


class Talks(Long):
    name = "talks"

    def solve(self, problem):
        print("solving", problem.n_params, "voxels")
        m = problem.n_params
        return Estimate(w=np.full(m, 9000.0), v=np.full(m, 1000.0))


class Fails(Long):
    name = "fails"

    def solve(self, problem):
        print("about to fail")
        raise RuntimeError("it failed")
'''


@pytest.fixture(scope="module")
def challenge(world, tmp_path_factory):
    from vvtbench.bench.submission import write_challenge

    root, secret, problem, truth, _, _ = world
    folder = tmp_path_factory.mktemp("challenge")
    write_challenge([("one", problem, truth)], folder / "problems", folder / "truth", "c")
    (folder / "shapes.py").write_text(SHAPES)
    return folder


def test_solve_refuses_a_wrong_shaped_estimate_as_score_would(world, challenge, tmp_path,
                                                               capsys):
    from vvtbench.cli import main
    from vvtbench.scoring.metrics import invalid_reason

    root, secret, problem, truth, _, _ = world
    out = tmp_path / "sub"
    assert main(["solve", f"{challenge / 'shapes.py'}:Long", str(challenge / "problems"),
                 "-o", str(out)]) == 1
    err = capsys.readouterr().err
    m = problem.n_params + 1
    reason = invalid_reason(np.ones(m), np.ones(m), problem.n_params)
    assert f"one: INVALID ESTIMATE, not submitted: {reason}" in err
    assert "solving" in err and (out / "one" / "solver.log").is_file()
    assert not (out / "manifest.json").exists()


def test_every_problem_failing_is_one_clear_line_and_the_output_is_shown(challenge, tmp_path,
                                                                        capsys):
    from vvtbench.cli import main

    out = tmp_path / "sub"
    assert main(["solve", f"{challenge / 'shapes.py'}:Fails", str(challenge / "problems"),
                 "-o", str(out)]) == 1
    err = capsys.readouterr().err
    last = err.strip().splitlines()[-1]
    assert last.startswith("error: fails solved none of the 1 problems of ") and ".tmp" not in err
    assert "RuntimeError: it failed" in err and "| about to fail" in err
    assert "about to fail" in (out / "one" / "solver.log").read_text()


def test_solve_verbose_shows_what_the_plugin_printed(world, challenge, tmp_path, capsys):
    from vvtbench.cli import main

    root, secret, problem, truth, _, _ = world
    plugin = f"{challenge / 'shapes.py'}:Talks"
    assert main(["solve", plugin, str(challenge / "problems"), "-o", str(tmp_path / "a")]) == 0
    assert "| solving" not in capsys.readouterr().out
    assert "solving" in (tmp_path / "a" / "one" / "solver.log").read_text()
    assert main(["solve", plugin, str(challenge / "problems"), "-o", str(tmp_path / "b"),
                 "--verbose"]) == 0
    assert f"| solving {problem.n_params} voxels" in capsys.readouterr().out


def test_an_unsandboxed_solve_is_said_on_the_terminal(challenge, tmp_path, capsys,
                                                      monkeypatch):
    from vvtbench.cli import main
    from vvtbench.solving import sealed

    monkeypatch.setenv("VVTBENCH_SANDBOX", "none")
    monkeypatch.setattr(sealed, "_WARNED", [])
    sandbox_kind.cache_clear()
    try:
        assert main(["solve", f"{challenge / 'shapes.py'}:Talks", str(challenge / "problems"),
                     "-o", str(tmp_path / "sub")]) == 0
    finally:
        monkeypatch.delenv("VVTBENCH_SANDBOX")
        sandbox_kind.cache_clear()
    out, err = capsys.readouterr()
    assert err.count("warning: plug-ins run WITHOUT A SANDBOX here (VVTBENCH_SANDBOX=none)") == 1
    assert "[UNSANDBOXED" in out.strip().splitlines()[-1]
