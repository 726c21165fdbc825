"""Sealed plug-in execution: solvers and extractors run where the truth is not.

Every plug-in call of vvtbench -- a solve, a motion extraction, and even the import that reads
a plug-in's name, version and configuration -- runs in a child process started by
:func:`run_sealed`, never in the process that holds a run's cache:

* The child gets a private working folder (``in/`` read-only: the problem or the video, and
  the truth only for a reference solver that declares ``uses_truth``; ``out/``: the one folder
  it may write) and a scrubbed environment: no cache path on its argv, in its environment or in
  its working folder.
* Where bubblewrap (``bwrap``) works, the child runs in a filesystem sandbox that shows,
  read-only, the system, the Python installation (never a project folder on ``sys.path``),
  vvtbench's own package folders (never the checkout around them: no ``scenes/``, ``runs/``),
  the plug-in's own code (its file, or the package it declares, without the data folders in
  it: :func:`plugin_code`), its inputs and the files the user named in its config
  (:func:`config_files`); its own ``/tmp`` (a scratch folder on disk, so that what a
  bounded-memory extraction spills stays on disk), no network, its own PID namespace (every
  process it starts ends with it); every path the caller names as secret (the run folder,
  the sample folder, the output folder) is hidden even where it lies inside a visible tree.
  Where bubblewrap is missing or cannot create namespaces (macOS, containers without user
  namespaces) the child runs unsandboxed, which :func:`sandbox_kind` reports, every result
  records as ``sandbox = "none"`` and :func:`warn_unsandboxed` says on the terminal: the
  plug-in then runs with the user's rights and could read any file the user can, so a score
  is only as trustworthy as the code that produced it; ``vvtbench score`` against truth the
  submitter does not hold is the trust boundary in that case. ``VVTBENCH_SANDBOX=none``
  chooses the unsandboxed child explicitly.
* Limits (:func:`run_sealed`): the child sets its own address-space limit before importing
  the plug-in; the parent measures the memory of all its processes and the disk it fills, and
  kills it, with its whole process group (and, unsandboxed, any process that left the group
  and was re-parented to the caller, which is made a child subreaper), when it goes over
  either or after ``timeout`` seconds. Its printed output is kept (the last
  :data:`LOG_TAIL` bytes).
* The parent accepts only regular files from ``out/`` (no links, no hard links), reads the
  response only after the child ended, and never trusts a missing one.

Nothing but paths and JSON crosses the boundary (no pickle).

Each working folder records the process that made it (``owner.json``: host, pid and the
process's start time). A process killed outright cannot remove its folders; the first sealed
call of a later process removes those whose owner no longer runs (:func:`remove_stale_scratch`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import shutil
import signal
import socket
import stat
import subprocess
import sys
import tempfile
import time
import traceback
from collections.abc import Iterable, Mapping, Sequence
from functools import cache
from pathlib import Path
from typing import Any

from .plugins import SEALED_MARK as MARK  # the environment mark of one sealed child

__all__ = ["SealedError", "describe_sealed", "extract_sealed", "list_sealed",
           "remove_stale_scratch", "run_sealed", "sandbox_kind", "solve_sealed"]

DEFAULT_TIMEOUT = 3600.0
LOG_TAIL = 64 * 1024  # bytes of a plug-in's output kept (its last ones)
SHM_MAX = 256 * 2**20  # the sandbox's /dev/shm (memory): at most this, and 1/8 of the limit
DISK_FRACTION = 0.5  # default disk limit: this fraction of the free space where it works
POLL_S = 0.5  # how often the memory and disk a plug-in holds are measured
MAX_ENTRIES = 100_000  # files and folders a plug-in may create in its scratch and output
_SYSTEM = ("/usr", "/etc", "/bin", "/sbin", "/lib", "/lib32", "/lib64", "/libx32")


class SealedError(RuntimeError):
    """A sealed child failed: ``kind`` is ``timeout``, ``crashed``, ``out of memory``, ``out of
    disk`` or ``error`` (the plug-in raised: the message is ``Type: text``); ``log`` its
    traceback and output tail, ``output`` the last :data:`LOG_TAIL` bytes it printed."""

    def __init__(self, kind: str, message: str, log: str = "", output: str = ""):
        super().__init__(message if kind == "error" else f"{kind}: {message}")
        self.kind, self.log, self.output = kind, log, output


# --------------------------------------------------------------------------- the sandbox


@cache
def sandbox_kind() -> str:
    """``"bwrap"`` when bubblewrap can create a sandbox here, else ``"none"`` (also when
    ``VVTBENCH_SANDBOX=none``)."""
    if os.environ.get("VVTBENCH_SANDBOX", "").lower() in ("none", "off", "0"):
        return "none"
    exe = shutil.which("bwrap")
    if exe is None:
        return "none"
    try:
        probe = subprocess.run([exe, "--ro-bind", "/", "/", "--unshare-all", "--die-with-parent",
                                "--new-session", "true"], capture_output=True, timeout=20)
    except (OSError, subprocess.TimeoutExpired):
        return "none"
    return "bwrap" if probe.returncode == 0 else "none"


_WARNED: list[bool] = []


def unsandboxed_reason() -> str:
    """Why plug-ins run without a sandbox here (when :func:`sandbox_kind` is ``"none"``)."""
    if os.environ.get("VVTBENCH_SANDBOX", "").lower() in ("none", "off", "0"):
        return "VVTBENCH_SANDBOX=none"
    if shutil.which("bwrap") is None:
        return "bubblewrap (bwrap) is not installed"
    return "bubblewrap cannot create a sandbox here (no user namespaces)"


def warn_unsandboxed() -> None:
    """Say once per process, on stderr, that plug-ins run unsandboxed and what that means."""
    if not _WARNED:
        _WARNED.append(True)
        print(f"warning: plug-ins run WITHOUT A SANDBOX here ({unsandboxed_reason()}): a "
              "plug-in can read every file you can, truth included; its rows are marked "
              "sandbox = none and 'unsandboxed' on the leaderboard "
              "(docs/explanation/sealed-evaluation.md)", file=sys.stderr)


@cache
def _bwrap_sizes() -> bool:
    """Whether this bubblewrap bounds the size of a tmpfs (``--size``, bubblewrap 0.7)."""
    try:
        out = subprocess.run([shutil.which("bwrap") or "bwrap", "--help"], capture_output=True,
                             text=True, timeout=20)
    except (OSError, subprocess.TimeoutExpired):
        return False
    return "--size" in out.stdout + out.stderr


def _package_roots() -> list[Path]:
    """The folders of vvtbench's own packages (``vvtbench/``, the shipped ``solvers/``), never
    the folder that holds them (a source checkout's root holds ``scenes/``, ``runs/``...)."""
    import importlib.util

    roots = []
    for name in ("vvtbench", "solvers"):
        spec = importlib.util.find_spec(name)
        if spec is not None and spec.submodule_search_locations:
            roots += [Path(p) for p in spec.submodule_search_locations]
    return roots


def _python_roots() -> list[Path]:
    """The Python installation: the interpreter's prefixes (its ``bin``, ``lib``, ...) and the
    site-packages folders on ``sys.path``; never another folder on ``sys.path`` (the current
    folder, a project on ``PYTHONPATH``): a plug-in's own code is shown by
    :func:`plugin_code`, vvtbench's by :func:`_package_roots`."""
    prefixes = {Path(sys.prefix), Path(sys.base_prefix), Path(sys.exec_prefix),
                Path(os.path.realpath(sys.executable)).parent.parent}
    paths = {pre / sub for pre in prefixes
             for sub in ("bin", "lib", "lib32", "lib64", "include", "pyvenv.cfg")}
    for p in sys.path:
        if p and os.path.isdir(p) and Path(p).name in ("site-packages", "dist-packages"):
            paths.add(Path(p))
    return sorted(p for p in paths if p.exists())


def _inside(path: Path, root: Path) -> bool:
    return path == root or root in path.parents


# What vvtbench writes that a plug-in must never read: a folder holding one of these files is
# a sample, a challenge's truth, a run or a cache entry ...
_DATA_MARKERS = ("truth.npz", "truth.json", "truth.zarr", "truth", "run.json", "task.json")
# ... and, inside a plug-in's package, also one holding results, a partial sample or a Zarr
# store (names too common to refuse a user's file for an ancestor holding them)
_PACKAGE_MARKERS = ("results.parquet", "results.csv", "checkpoint.json", ".zattrs", ".zgroup",
                    "zarr.json")
_DATA_NAMES = ("truth", "truth.zarr", "cache", "runs")
_SCENE_KEYS = {"geometry", "material", "defects", "excitation", "camera", "boundary", "vary",
               "tracks", "base", "simulation"}
_CODE_SUFFIXES = (".py", ".pyi", ".pyc", ".pyd", ".so")  # truth.py is code, not truth
_MAX_SHOWN = 20000  # entries of a plug-in's package walked for data


def data_folder(path: Path, package: bool = False) -> str | None:
    """What the folder ``path`` is when it holds vvtbench data a plug-in must not read -- a
    sample, dataset, challenge or submission (a ``manifest.json`` of a vvtbench format), a run
    or its cache, a cache entry, truth; with ``package`` (a folder inside a plug-in's package)
    also results, a partial sample or a Zarr store -- or None."""
    if path.name in _DATA_NAMES:
        return f"a {path.name!r} folder"
    for marker in _DATA_MARKERS + (_PACKAGE_MARKERS if package else ()):
        if os.path.lexists(path / marker):
            return f"a vvtbench data folder (it holds {marker})"
    manifest = path / "manifest.json"
    if manifest.is_file():
        try:
            with open(manifest, "rb") as f:
                doc = json.loads(f.read(1 << 20))
        except (OSError, ValueError):
            return "a folder with an unreadable manifest.json"
        if isinstance(doc, dict) and "vvtbench" in str(doc.get("format", "")):
            return f"a vvtbench data folder ({doc['format']})"
    return None


def _data_file(path: Path) -> bool:
    """Whether the file ``path`` is truth or a scene, suite or family (a TOML file that can
    regenerate a problem's truth)."""
    if path.name.startswith("truth") and path.suffix not in _CODE_SUFFIXES:
        return True
    if path.suffix.lower() != ".toml":
        return False
    import tomllib

    try:
        with open(path, "rb") as f:
            doc = tomllib.loads(f.read(1 << 20).decode("utf-8", "replace"))
    except (OSError, ValueError):
        return True
    return bool(_SCENE_KEYS & set(doc))


def forbidden_place(path: Path) -> str | None:
    """Why the file ``path`` may not be shown to a plug-in (it is truth, a scene, or lies in a
    sample, run, cache, challenge or truth folder), or None."""
    path = Path(os.path.realpath(path))
    if _data_file(path):
        return f"{path} is truth or a scene, suite or family file"
    for folder in path.parents:
        what = data_folder(folder)
        if what is not None:
            return f"{path} lies in {folder}, {what}"
    return None


def package_root(path: Path) -> Path | None:
    """The package a plug-in file declares: the outermost folder of the chain of folders with
    an ``__init__.py`` that holds ``path``, or None for a file outside any package."""
    root = None
    folder = Path(os.path.realpath(path)).parent
    while (folder / "__init__.py").is_file() and folder != folder.parent:
        root, folder = folder, folder.parent
    return root


def plugin_code(kind: str, target: str | None) -> list[Path]:
    """The code the sandbox shows of the ``kind`` plug-in ``target``: a plug-in file alone
    (``path/file.py:Class``), or the package it declares (the file lies in a folder with an
    ``__init__.py``: the outermost such folder); for ``module:Class`` or a registered name the
    folder of the module's top-level package (found, never imported). The data inside a shown
    package is hidden by :func:`_hidden_in`."""
    import importlib.util

    if not target:
        return []
    module, sep, _ = target.partition(":")
    if not sep:  # a registered name: its entry point (read from metadata, never imported)
        if kind == "solver":
            from .plugins import SOLVERS as registry
        else:
            from .extractors import EXTRACTORS as registry
        module = registry.registry().get(target, "").partition(":")[0]
        if not module:
            return []
    if module.endswith(".py") or "/" in module or "\\" in module:
        path = Path(module)
        if not path.is_file():
            return []
        return [package_root(path) or Path(os.path.realpath(path))]
    try:
        spec = importlib.util.find_spec(module.split(".")[0])
    except (ImportError, ValueError):
        return []
    if spec is None:
        return []
    if spec.submodule_search_locations:
        return [Path(p) for p in spec.submodule_search_locations]
    return [Path(spec.origin)] if spec.origin and os.path.isfile(spec.origin) else []


def _hidden_in(root: Path) -> list[Path]:
    """What the sandbox hides inside the shown package folder ``root``: every data folder
    (:func:`data_folder`) and every truth, scene, suite or family file."""
    from .plugins import PluginError

    hidden, seen = [], 0
    for folder, dirs, files in os.walk(root):
        seen += len(dirs) + len(files)
        if seen > _MAX_SHOWN:
            raise PluginError(f"{root}: more than {_MAX_SHOWN} files in the plug-in's package; "
                              "a sandbox shows a plug-in its package, which must be code (and "
                              "the data it ships), not a project folder")
        for name in list(dirs):
            sub = Path(folder) / name
            if not sub.is_symlink() and data_folder(sub, package=True) is not None:
                hidden.append(sub)
                dirs.remove(name)
        hidden += [Path(folder) / f for f in files
                   if not (Path(folder) / f).is_symlink() and _data_file(Path(folder) / f)]
    return hidden


def _bwrap_argv(work: Path, inputs: Mapping[str, Path], code: Sequence[Path],
                secrets: Sequence[Path], files: Mapping[str, Path] = {},
                shm_bytes: int = SHM_MAX) -> list[str]:
    argv = [shutil.which("bwrap") or "bwrap", "--unshare-all", "--die-with-parent",
            "--new-session", "--dev", "/dev", "--proc", "/proc",
            "--bind", str(work / "scratch"), "/tmp"]  # on disk, measured: _disk_used
    # memory the plug-in could fill without holding it: / and /dev (tmpfs in a bwrap sandbox)
    # are made read-only below; /dev/shm is a bounded tmpfs, or read-only too where bwrap
    # cannot bound one (before 0.7)
    if _bwrap_sizes():
        argv += ["--size", str(int(shm_bytes)), "--tmpfs", "/dev/shm"]
    for p in _SYSTEM:
        if os.path.islink(p):
            argv += ["--symlink", os.readlink(p), p]
        elif os.path.isdir(p):
            argv += ["--ro-bind", p, p]
    python = [Path(os.path.realpath(p)) for p in _python_roots()]
    packages = list(dict.fromkeys(Path(os.path.realpath(p))
                                  for p in [*_package_roots(), *code]))
    visible: list[Path] = []
    for root in [*python, *packages]:
        if root.exists() and not any(_inside(root, v) for v in visible):
            visible = [v for v in visible if not _inside(v, root)] + [root]
    for root in sorted(visible):
        argv += ["--ro-bind", str(root), str(root)]
    from ..scene.scene import SCENES_DIR

    hidden = [Path(os.path.realpath(s)) for s in [*secrets, SCENES_DIR]]
    for root in packages:  # the data a shown package holds
        if root.is_dir() and not any(_inside(root, p) for p in python):
            hidden += _hidden_in(root)
    hidden = sorted(set(hidden))
    hidden = [s for s in hidden if not any(_inside(s, o) and s != o for o in hidden)]
    for secret in hidden:
        if not any(_inside(secret, v) for v in visible):
            continue
        if secret.is_dir():
            argv += ["--tmpfs", str(secret), "--remount-ro", str(secret)]
        elif secret.exists():
            argv += ["--ro-bind", "/dev/null", str(secret)]
    argv += ["--dir", str(work), "--bind", str(work / "out"),
             str(work / "out"), "--ro-bind", str(work / "spec.json"), str(work / "spec.json")]
    for name, src in inputs.items():
        argv += ["--ro-bind", str(Path(src).resolve()), str(work / "in" / name)]
    for name, src in files.items():  # files the user named in the plug-in's config
        argv += ["--ro-bind", str(Path(src).resolve()), str(work / name)]
    return argv + ["--remount-ro", "/dev", "--remount-ro", "/", "--chdir", str(work), "--"]


def config_files(config: Mapping[str, Any] | None, named: Iterable[str] | None = None,
                 secrets: Sequence[Path] = ()) -> dict[str, Path]:
    """The files the user named in a plug-in's config (a string value that is an existing
    file, e.g. learned weights), to show the sealed child read-only where the config names
    them: an absolute path at itself, a relative one under the child's working folder.

    ``named``: the keys the user gave (on the command line or in a suite's solver table);
    None means every key of ``config``. A plug-in's own defaults are never shown this way
    (its declared package is shown whole, :func:`plugin_code`). A named file that is truth or
    a scene, or lies in a sample, run, cache, challenge or truth folder or in one of
    ``secrets``, is refused (:class:`vvtbench.solving.plugins.PluginError`)."""
    from .plugins import PluginError

    keys = None if named is None else set(named)
    out = {}
    for key, value in (config or {}).items():
        if keys is not None and key not in keys:
            continue
        if not isinstance(value, str) or not value or "\0" in value:
            continue
        path = Path(value)
        if not path.is_file():
            continue
        real = Path(os.path.realpath(path))
        why = forbidden_place(real) or next(
            (f"{real} lies in {s}, which the plug-in must not see" for s in secrets
             if _inside(real, Path(os.path.realpath(s)))), None)
        if why is not None:
            raise PluginError(f"config {key}={value}: {why}; a plug-in is never shown a "
                              "sample, run, cache, challenge or truth folder (copy the file "
                              "elsewhere)")
        if path.is_absolute():
            out[str(path)] = path
        elif ".." not in path.parts:
            out[path.as_posix()] = path.resolve()
    return out


def _link_inputs(work: Path, inputs: Mapping[str, Path], files: Mapping[str, Path] = {}
                 ) -> None:
    """Unsandboxed: the inputs appear under ``in/`` as hard links or copies (never as links
    that name the cache), and the relative files a config names under the working folder."""
    named = {f"../{k}": v for k, v in files.items() if not Path(k).is_absolute()}
    for name, src in {**inputs, **named}.items():
        dst = work / "in" / name
        dst.parent.mkdir(parents=True, exist_ok=True)
        src = Path(src)
        if src.is_dir():
            shutil.copytree(src, dst)
            continue
        try:
            os.link(src, dst)
        except OSError:
            shutil.copyfile(src, dst)


def _child_env(threads: int | None, marker: str = "", tmp: str = "/tmp") -> dict[str, str]:
    """The child's environment; ``tmp``: its temporary folder (``/tmp`` in the sandbox, the
    working folder's ``scratch/`` without one: where what it stores is measured)."""
    env = {MARK: marker, "PATH": "/usr/local/bin:/usr/bin:/bin", "HOME": tmp,
           "LANG": "C.UTF-8",
           "TMPDIR": tmp, "MPLCONFIGDIR": f"{tmp}/matplotlib", "PYTHONFAULTHANDLER": "1",
           "PYTHONDONTWRITEBYTECODE": "1", "PYTHONNOUSERSITE": "1",
           "PYTHONUNBUFFERED": "1"}  # its output in order, and kept up to a crash
    paths = [p for p in sys.path if p and os.path.isdir(p)]
    env["PYTHONPATH"] = os.pathsep.join(paths)
    for var in ("PYOPENGL_PLATFORM", "OPENBLAS_CORETYPE"):
        if var in os.environ:
            env[var] = os.environ[var]
    if threads:
        for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                    "NUMBA_NUM_THREADS"):
            env[var] = str(threads)
    return env


# children this process started (a signal handler ends them: see bench.executors)
RUNNING: dict[int, subprocess.Popen] = {}


def kill_running() -> None:
    """End every sealed child this process started (Ctrl-C, SIGTERM)."""
    for proc in list(RUNNING.values()):
        _kill_group(proc)


def _kill_group(proc: subprocess.Popen) -> None:
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(proc.pid, signal.SIGKILL)
    with contextlib.suppress(ProcessLookupError):
        proc.kill()


def _become_subreaper() -> bool:
    try:
        import ctypes

        return ctypes.CDLL(None).prctl(36, 1, 0, 0, 0) == 0  # PR_SET_CHILD_SUBREAPER
    except Exception:  # noqa: BLE001 -- Linux only
        return False


def _children_of(pid: int) -> list[int]:
    out = []
    for entry in os.listdir("/proc") if os.path.isdir("/proc") else []:
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat", "rb") as f:
                fields = f.read().rsplit(b")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            out.append(int(entry))
    return out


def _marked(pid: int, marker: str) -> bool:
    """Whether process ``pid`` inherited the environment mark of one sealed child."""
    try:
        with open(f"/proc/{pid}/environ", "rb") as f:
            return f"{MARK}={marker}".encode() in f.read().split(b"\0")
    except OSError:
        return False


def _reap_escaped(before: set[int], marker: str) -> None:
    """Kill processes re-parented to this (subreaper) process since ``before`` was taken that
    carry the child's mark: a plug-in's grandchildren that left its process group (never
    another task's processes, which carry no mark or another one)."""
    for _ in range(3):
        stray = [p for p in _children_of(os.getpid()) if p not in before and _marked(p, marker)]
        if not stray:
            return
        for pid in stray:
            for child in _children_of(pid):
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.kill(child, signal.SIGKILL)
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.kill(pid, signal.SIGKILL)
        for pid in stray:
            with contextlib.suppress(ChildProcessError, OSError):
                os.waitpid(pid, 0)


# --------------------------------------------------------------------------- the parent side


PREFIX = "vvtbench-sealed-"
OWNER = "owner.json"
_SWEPT: set[str] = set()


def _process_start(pid: int) -> str | None:
    """The start time of process ``pid`` (``/proc/PID/stat`` field 22, clock ticks since
    boot), or None where there is no such file."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return text[text.rfind(")") + 2:].split()[19]


def _owner() -> dict:
    return {"host": socket.gethostname(), "pid": os.getpid(),
            "start": _process_start(os.getpid())}


def _owner_gone(doc: dict) -> bool:
    """Whether the process ``owner.json`` names has ended; False for anything that is not a
    pid this system could hold."""
    pid = doc.get("pid")
    if not isinstance(pid, int) or isinstance(pid, bool) or not 0 < pid < 1 << 31:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except OSError:
        return False
    start = _process_start(pid)
    return doc.get("start") is not None and start is not None and start != doc["start"]


def remove_stale_scratch(folder: str | Path | None = None) -> list[Path]:
    """Remove the sealed working folders in ``folder`` (default: the system's temporary
    folder) whose owner process, on this host, no longer runs; return them.

    Only real folders named ``vvtbench-sealed-*``, owned by this user and holding an
    ``owner.json`` are considered; anything else is left alone.
    """
    root = Path(folder) if folder is not None else Path(tempfile.gettempdir())
    host = socket.gethostname()
    removed = []
    for path in sorted(root.glob(PREFIX + "*")):
        try:
            info = path.lstat()
            if not stat.S_ISDIR(info.st_mode) or info.st_uid != os.getuid():
                continue
            doc = json.loads((path / OWNER).read_text())
        except (OSError, ValueError):
            continue
        if isinstance(doc, dict) and doc.get("host") == host and _owner_gone(doc):
            shutil.rmtree(path, ignore_errors=True)
            removed.append(path)
    return removed


# --------------------------------------------------------------------------- the limits


def _shm_bytes(memory_bytes: int | None) -> int:
    """The size of the sandbox's ``/dev/shm``: :data:`SHM_MAX`, and at most 1/8 of the
    memory limit (it is taken off what the plug-in's processes may hold)."""
    return SHM_MAX if not memory_bytes else max(1 << 20, min(SHM_MAX, memory_bytes // 8))


def _default_disk(work: Path) -> int:
    """The default disk limit: :data:`DISK_FRACTION` of the space free where ``work`` is."""
    st = os.statvfs(work)
    return max(1 << 20, int(st.f_bavail * st.f_frsize * DISK_FRACTION))


def _gb(n: float) -> str:
    return f"{n / 2**30:.3g} GB"


def _tree(pid: int) -> list[int]:
    """``pid`` and every process below it (from ``/proc``; a process in a sandbox's PID
    namespace is listed there under its host pid)."""
    children: dict[int, list[int]] = {}
    for entry in os.listdir("/proc") if os.path.isdir("/proc") else []:
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat", "rb") as f:
                ppid = int(f.read().rsplit(b")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            continue
        children.setdefault(ppid, []).append(int(entry))
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        todo += children.get(p, [])
    return out


def _memory_held(pid: int) -> int:
    """Bytes the process tree of ``pid`` holds in memory: the sum of its processes'
    proportional set sizes (a page shared by k of them counts 1/k in each), or of their
    resident sizes where the kernel has no ``smaps_rollup``."""
    total = 0
    for p in _tree(pid):
        try:
            with open(f"/proc/{p}/smaps_rollup", "rb") as f:
                for line in f:
                    if line.startswith(b"Pss:"):
                        total += int(line.split()[1]) * 1024
                        break
            continue
        except (OSError, ValueError):
            pass
        try:
            with open(f"/proc/{p}/statm", "rb") as f:
                total += int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
        except (OSError, ValueError, IndexError):
            pass
    return total


def _disk_used(work: Path) -> tuple[int, int]:
    """(bytes, entries) the child stored in its working folder: its ``/tmp`` (``scratch/``),
    its output (``out/``) and its printed output (``log.txt``); blocks really used, so a
    sparse file counts what it holds. The count stops past :data:`MAX_ENTRIES`."""
    used, entries = 0, 0
    todo = [work / "scratch", work / "out"]
    with contextlib.suppress(OSError):
        used += os.lstat(work / "log.txt").st_blocks * 512
    while todo and entries <= MAX_ENTRIES:
        try:
            it = os.scandir(todo.pop())
        except OSError:
            continue
        with it:
            for entry in it:
                entries += 1
                try:
                    st = entry.stat(follow_symlinks=False)
                except OSError:
                    continue
                used += st.st_blocks * 512
                if entry.is_dir(follow_symlinks=False):
                    todo.append(Path(entry.path))
    return used, entries


def _watch(proc: subprocess.Popen, work: Path, timeout: float | None, memory: int | None,
           disk: int) -> tuple[bool, tuple[str, str] | None]:
    """Wait for ``proc``; every :data:`POLL_S` s measure what it holds. Returns
    ``(timed out, None)`` or ``(False, (kind, message))`` when it went over a limit (the
    caller then ends it)."""
    deadline = None if timeout is None else time.monotonic() + timeout
    while True:
        wait = POLL_S if deadline is None else min(POLL_S, deadline - time.monotonic())
        try:
            proc.wait(timeout=max(wait, 0.0))
            return False, None
        except subprocess.TimeoutExpired:
            pass
        if deadline is not None and time.monotonic() >= deadline:
            return True, None
        if memory:
            held = _memory_held(proc.pid)
            if held > memory:
                return False, ("out of memory", f"its processes held {_gb(held)} together "
                               f"(limit {_gb(memory)} besides its /dev/shm, from --memory-gb)")
        used, entries = _disk_used(work)
        if used > disk or entries > MAX_ENTRIES:
            what = (f"more than {MAX_ENTRIES} files" if entries > MAX_ENTRIES
                    else _gb(used))
            return False, ("out of disk", f"it stored {what} in its /tmp, its output and "
                           f"its printed output (limit {_gb(disk)})")


def run_sealed(spec: dict, inputs: Mapping[str, Path], dest: Path | None, *,
               secrets: Sequence[Path] = (), code: Sequence[Path] = (),
               timeout: float | None = DEFAULT_TIMEOUT, memory_bytes: int | None = None,
               threads: int | None = None, accept: Sequence[str] | None = None,
               files: Mapping[str, Path] = {}, scratch: str | Path | None = None,
               disk_bytes: int | None = None) -> dict:
    """Run the child job ``spec`` (``{"job": "solve"|"extract"|"describe", ...}``) sealed.

    ``inputs``: name -> file or folder shown read-only as ``in/<name>``; ``dest``: the folder
    the files the child wrote into ``out/`` are copied to (regular files only; ``accept``
    limits their names); ``secrets``: paths hidden from the child; ``code``: the plug-in's
    code (:func:`plugin_code`); ``files``: the files the user named in its config
    (:func:`config_files`); ``scratch``: the folder its working folder (and its ``/tmp``) is
    made in (default: the system's temporary folder).

    Limits: ``memory_bytes`` holds for everything the plug-in keeps in memory -- each process's
    address space, the proportional resident memory of all its processes together (measured
    every :data:`POLL_S` s) and the sandbox's ``/dev/shm`` (a tmpfs of at most
    :data:`SHM_MAX`, 1/8 of the limit, taken off the other two); ``disk_bytes`` (default: half
    the free space where it works) for what it stores in its ``/tmp``, its output and its
    printed output (measured every :data:`POLL_S` s; no single file larger). Returns the
    child's result dict with ``"sandbox"``, ``"seconds"`` and ``"log"`` (the last
    :data:`LOG_TAIL` bytes of its output), or raises :class:`SealedError`.
    """
    kind = sandbox_kind()
    if kind == "none":
        warn_unsandboxed()
    root = str(scratch if scratch is not None else tempfile.gettempdir())
    if root not in _SWEPT:
        _SWEPT.add(root)
        remove_stale_scratch(root)
    work = Path(tempfile.mkdtemp(prefix=PREFIX, dir=scratch))
    try:
        (work / OWNER).write_text(json.dumps(_owner()))
        (work / "out").mkdir()
        (work / "in").mkdir()
        (work / "scratch").mkdir()
        shm = _shm_bytes(memory_bytes)
        held = memory_bytes - shm if memory_bytes else None  # what its processes may hold
        disk = int(disk_bytes) if disk_bytes else _default_disk(work)
        doc = {**spec, "memory_bytes": held, "file_bytes": disk}
        (work / "spec.json").write_text(json.dumps(doc))
        cmd = [sys.executable, "-m", "vvtbench.solving.sealed", str(work / "spec.json")]
        if kind == "bwrap":  # bwrap makes the mount points inside the sandbox
            cmd = _bwrap_argv(work, inputs, code, secrets, files, shm) + cmd
        else:
            _link_inputs(work, inputs, files)
        reaper = kind == "none" and _become_subreaper()
        before = set(_children_of(os.getpid())) if reaper else set()
        log_path = work / "log.txt"
        t0 = time.perf_counter()
        timed_out, over = False, None
        env = _child_env(threads, work.name,
                         "/tmp" if kind == "bwrap" else str(work / "scratch"))
        with open(log_path, "wb") as log:
            proc = subprocess.Popen(cmd, cwd=work, stdin=subprocess.DEVNULL, stdout=log,
                                    stderr=subprocess.STDOUT, env=env, start_new_session=True)
            RUNNING[proc.pid] = proc
            try:
                timed_out, over = _watch(proc, work, timeout, held, disk)
            finally:
                _kill_group(proc)
                proc.wait()
                RUNNING.pop(proc.pid, None)
                if reaper:
                    _reap_escaped(before | {proc.pid}, work.name)
        seconds = time.perf_counter() - t0
        output = _output(log_path)
        tail = _tail(output)
        if over is not None:
            raise SealedError(*over, tail, output)
        if timed_out:
            raise SealedError("timeout", f"no result after {timeout:g} s (the time limit: "
                                         "--timeout or the suite's `timeout`)", tail, output)
        response = _read_regular(work / "out" / ".response.json")
        code = proc.returncode
        if kind == "bwrap" and code is not None and 128 < code < 128 + 65:
            code = 128 - code  # bwrap exits with 128 + the signal that ended the plug-in
        try:
            result = _classify(code, response, seconds, memory_bytes, tail)
        except SealedError as error:  # name the caller's files, not the child's view of them
            text = str(error.args[0])
            for name, src in inputs.items():
                text = text.replace(str(work / "in" / name), str(src))
            raise SealedError(error.kind, text if error.kind == "error" else
                              text.removeprefix(f"{error.kind}: "), error.log,
                              output) from None
        if dest is not None:
            _collect(work / "out", Path(dest), accept)
        return {**result, "sandbox": kind, "seconds": seconds, "log": output}
    finally:
        shutil.rmtree(work, ignore_errors=True)


@contextlib.contextmanager
def _open_regular(path: Path):
    """``path`` opened for reading if it is a regular file with one link (no link followed),
    else None."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW)
    except OSError:
        yield None
        return
    with os.fdopen(fd, "rb") as f:
        st = os.fstat(f.fileno())
        yield f if stat.S_ISREG(st.st_mode) and st.st_nlink == 1 else None


def _read_regular(path: Path, limit: int = 1 << 20) -> bytes | None:
    """The bytes (at most ``limit``) of ``path`` if it is a regular file with one link."""
    with _open_regular(path) as f:
        return None if f is None else f.read(limit)


def _classify(code: int | None, response: bytes | None, seconds: float,
              memory_bytes: int | None, tail: str) -> dict:
    limit = f"{memory_bytes / 2**30:.3g} GB" if memory_bytes else "none"
    doc = None
    if response is not None:
        try:
            doc = json.loads(response)
        except ValueError:
            doc = None
    if not isinstance(doc, dict):
        if code is not None and code < 0:
            name = _signal_name(-code)
            if -code == signal.SIGKILL:
                raise SealedError("out of memory", f"killed by {name} after {seconds:.1f} s "
                                  f"(probably the kernel's OOM killer; limit {limit}, "
                                  "--memory-gb)", tail)
            raise SealedError("crashed", f"killed by signal {-code} ({name}) after "
                                         f"{seconds:.1f} s", tail)
        raise SealedError("crashed", f"the plug-in process exited with code {code} without "
                                     "a result", tail)
    if code != 0 and doc.get("status") == "ok":
        raise SealedError("crashed", f"the plug-in process exited with code {code}", tail)
    if doc.get("status") == "ok" and isinstance(doc.get("result"), dict):
        return doc["result"]
    if doc.get("kind") == "MemoryError":
        raise SealedError("out of memory", f"MemoryError: {doc.get('message', '')} "
                                           f"(limit {limit}, --memory-gb)",
                          str(doc.get("traceback", "")) + tail)
    raise SealedError("error", str(doc.get("error", "unknown error")),
                      str(doc.get("traceback", "")) + tail)


def _collect(src: Path, dest: Path, accept: Sequence[str] | None) -> None:
    """Copy the regular files the child wrote (top level only) into ``dest``."""
    dest.mkdir(parents=True, exist_ok=True)
    for entry in sorted(os.listdir(src)):
        if entry.startswith(".") or (accept is not None and entry not in accept):
            continue
        with _open_regular(src / entry) as f:
            if f is None:
                raise SealedError("error", f"{entry}: the plug-in wrote a link or a special "
                                           "file where a result file belongs")
            _write_new(dest / entry, f)


def _write_new(path: Path, source) -> None:
    """Copy the open file ``source`` to ``path`` atomically through a fresh temporary file
    (streamed; never through a link planted at either name)."""
    from ..io.files import open_new

    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}-{time.monotonic_ns()}")
    try:
        with open_new(tmp) as f:
            shutil.copyfileobj(source, f, 1 << 20)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def _signal_name(num: int) -> str:
    try:
        return signal.Signals(num).name
    except ValueError:
        return f"signal {num}"


def _output(path: Path) -> str:
    """The last :data:`LOG_TAIL` bytes of the plug-in's output (stdout and stderr)."""
    try:
        with open(path, "rb") as f:
            f.seek(max(0, os.fstat(f.fileno()).st_size - LOG_TAIL))
            return f.read(LOG_TAIL).decode(errors="replace")
    except OSError:
        return ""


def _tail(data: str) -> str:
    return (f"\n--- plug-in process output (last {len(data.encode())} bytes) ---\n{data}"
            if data else "")


# --------------------------------------------------------------------------- the three jobs


def solve_sealed(target: str, config: Mapping[str, Any] | None, problem, *, truth=None,
                 timeout: float | None = DEFAULT_TIMEOUT, memory_bytes: int | None = None,
                 threads: int | None = None, secrets: Sequence[Path] = (),
                 dest: Path | None = None, named: Iterable[str] | None = None,
                 disk_bytes: int | None = None):
    """Solve ``problem`` with the solver ``target`` (a name or ``path/file.py:Class``) and the
    config overrides ``config`` in a sealed child; ``truth`` is handed over only when the
    solver declares ``uses_truth`` (a reference). Returns ``(estimate, wall seconds, info)``;
    ``info`` holds ``name``, ``version``, ``reference``, ``sandbox``, ``config`` and ``log``
    (the last :data:`LOG_TAIL` bytes the plug-in printed). With ``dest`` the child's
    ``estimate.npz``/``estimate.json`` are also kept there, with its printed output in
    ``solver.log``. ``named``: the keys of ``config`` the user gave (default: all), whose files
    are shown (:func:`config_files`). Limits: see :func:`run_sealed`."""
    from .problem import Estimate

    desc = describe_sealed("solver", target, config, timeout=min(timeout or 600.0, 600.0),
                           secrets=secrets, named=named)
    reference = bool(desc["uses_truth"])
    if reference and truth is None:
        from .plugins import PluginError

        raise PluginError(f"{desc['name']} is a reference solver (uses_truth): it needs the "
                          "truth, which this source does not have")
    with tempfile.TemporaryDirectory(prefix="vvtbench-problem-") as tmp:
        tmp = Path(tmp)
        (tmp / "problem").mkdir()
        problem.save(tmp / "problem")
        inputs = {"problem": tmp / "problem"}
        if reference:
            (tmp / "truth").mkdir()
            truth.save(tmp / "truth")
            inputs["truth"] = tmp / "truth"
        keep = Path(dest) if dest is not None else tmp / "estimate"
        result = run_sealed({"job": "solve", "target": _target(target),
                             "config": dict(config or {}), "reference": reference},
                            inputs, keep, secrets=[*secrets, tmp],
                            code=plugin_code("solver", target),
                            files=config_files(config, named, secrets),
                            timeout=timeout, memory_bytes=memory_bytes, threads=threads,
                            accept=("estimate.npz", "estimate.json"), disk_bytes=disk_bytes)
        estimate = Estimate.load(keep, problem)
        if dest is not None and result["log"]:
            from ..io.files import write_text

            write_text(keep / "solver.log", result["log"])
    info = {"name": desc["name"], "version": desc["version"], "reference": reference,
            "sandbox": result["sandbox"], "config": desc["config"], "log": result["log"]}
    return estimate, float(result.get("wall_s", result["seconds"])), info


def extract_sealed(video: Path | str, fps: float | None, options: Mapping[str, Any],
                   dest: Path, *, timeout: float | None = DEFAULT_TIMEOUT,
                   memory_bytes: int | None = None, threads: int | None = None,
                   secrets: Sequence[Path] = (), folder: bool = False,
                   scratch: str | Path | None = None, disk_bytes: int | None = None) -> dict:
    """Extract modes from ``video`` with :func:`vvtbench.modes.extract_modes` (``options``:
    its keyword arguments, the extractor plug-in among them) in a sealed child; the modes are
    saved into ``dest``. Returns the child's summary (``n_modes``, ``frequencies_hz``,
    ``sandbox``).

    The child sees the video file alone (a sample's video: its truth beside it stays hidden),
    or with ``folder=True`` the folder that holds it (a camera's files: a Photron ``.cih``
    beside its ``.mraw``, an image sequence given by a glob or printf pattern); a folder of
    images is shown whole."""
    video = Path(video)
    if video.is_dir():
        name, shown, source = video.name or "frames", video, video.name or "frames"
    elif folder:
        name = video.parent.resolve().name or "files"
        shown, source = video.parent, f"{name}/{video.name}"
    else:
        name = "video" + "".join(video.suffixes[-1:])
        shown, source = video, name
    extractor = options.get("extractor")
    code = plugin_code("extractor", extractor) if isinstance(extractor, str) else []
    hidden = [*secrets] if folder or video.is_dir() else [*secrets, video.parent]
    return run_sealed({"job": "extract", "video": source, "fps": fps,
                       "options": _jsonable_options(options)},
                      {name: shown}, Path(dest), secrets=hidden, code=code,
                      timeout=timeout, memory_bytes=memory_bytes, threads=threads,
                      scratch=scratch, disk_bytes=disk_bytes)


def _jsonable_options(options: Mapping[str, Any]) -> dict:
    out = {}
    for k, v in options.items():
        if isinstance(v, tuple):
            v = list(v)
        if k == "extractor" and isinstance(v, str):
            v = _target(v)
        out[k] = v
    return out


_DESCRIBED: dict[str, dict] = {}


def forget_descriptions() -> None:
    """Describe every plug-in afresh from now on (a run does this first: a file its config
    names, such as learned weights, may have been replaced since)."""
    _DESCRIBED.clear()


def describe_sealed(kind: str, target: str, config: Mapping[str, Any] | None = None, *,
                    timeout: float | None = 600.0, secrets: Sequence[Path] = (),
                    named: Iterable[str] | None = None) -> dict:
    """Import the ``kind`` (``solver`` or ``extractor``) plug-in ``target`` in a sealed child
    and return its ``name``, ``version``, ``description``, ``uses_truth``, the resolved
    ``config`` (the overrides ``config`` validated against its Config) and ``inputs`` (content
    hashes of the files its config names). ``named``: the keys of ``config`` the user gave
    (default: all), whose files are shown (:func:`config_files`). A plug-in that cannot be
    imported or configured raises :class:`vvtbench.solving.plugins.PluginError` with the
    child's one-line message."""
    from .plugins import PluginError

    files = config_files(config, named, secrets)
    stamps = {k: os.stat(v).st_mtime_ns for k, v in files.items()}
    key = json.dumps([kind, _target(target), _mtime(target), dict(config or {}), stamps],
                     sort_keys=True, default=str)
    if key not in _DESCRIBED:
        try:
            _DESCRIBED[key] = run_sealed(
                {"job": "describe", "kind": kind, "target": _target(target),
                 "config": dict(config or {})}, {}, None, secrets=secrets,
                code=plugin_code(kind, target), timeout=timeout, memory_bytes=None,
                files=files)
        except SealedError as error:
            if error.kind == "error" and error.args[0].startswith("PluginError: "):
                raise PluginError(error.args[0].removeprefix("PluginError: ")) from None
            raise PluginError(f"{target}: {error}") from None
    return _DESCRIBED[key]


def list_sealed(kind: str, timeout: float | None = 600.0) -> dict[str, dict]:
    """name -> ``{"version", "description", "fields"}`` (or ``{"error"}``) of every registered
    plug-in of ``kind`` (``solver`` or ``extractor``), imported in one sealed child."""
    if kind == "solver":
        from .plugins import SOLVERS as registry
    else:
        from .extractors import EXTRACTORS as registry
    code = [p for target in registry.registry().values() for p in plugin_code(kind, target)]
    return {k: v for k, v in run_sealed({"job": "list", "kind": kind}, {}, None,
                                        timeout=timeout, code=code).items()
            if k not in ("sandbox", "seconds", "log")}


def _target(target: str) -> str:
    """A file plug-in's path made absolute (the child runs elsewhere)."""
    module, sep, attr = target.partition(":")
    if sep and (module.endswith(".py") or "/" in module or "\\" in module):
        return f"{Path(module).resolve()}:{attr}"
    return target


def _mtime(target: str) -> float | None:
    module, sep, _ = target.partition(":")
    try:
        return os.stat(module).st_mtime_ns if sep and module.endswith(".py") else None
    except OSError:
        return None


# --------------------------------------------------------------------------- the child side


def _die_with_parent() -> None:
    try:
        import ctypes

        ctypes.CDLL(None).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except Exception:  # noqa: BLE001 -- Linux only
        pass


def _job_solve(spec: dict, work: Path) -> dict:
    from .plugins import PluginError, load_solver, run_solver
    from .problem import InverseProblem

    problem = InverseProblem.load(work / "in" / "problem")
    cls = load_solver(spec["target"])
    reference = bool(getattr(cls, "uses_truth", False))
    if reference != bool(spec["reference"]):
        raise PluginError(f"{cls.name}: declared uses_truth = {not reference} when it was "
                          f"described and {reference} when it ran")
    truth = None
    if reference:
        from .truth import Truth

        truth = Truth.load(work / "in" / "truth")
    est, wall = run_solver(cls, spec["config"], problem, truth)
    est.save(work / "out", problem, wall_s=wall)
    return {"wall_s": wall}


def _job_extract(spec: dict, work: Path) -> dict:
    from ..modes import extract_modes

    options = dict(spec["options"])
    if isinstance(options.get("roi"), list):
        options["roi"] = tuple(options["roi"])
    ms = extract_modes(str(work / "in" / spec["video"]), spec["fps"], **options)
    ms.save(work / "out")
    return {"n_modes": len(ms), "frequencies_hz": [float(f) for f in ms.frequencies_hz]}


def _job_describe(spec: dict, work: Path) -> dict:
    from .plugins import config_from_mapping

    if spec["kind"] == "solver":
        from .plugins import solver_inputs, solver_setup

        cls, config = solver_setup(spec["target"], spec["config"])
        inputs = solver_inputs(cls, config)
    else:
        from .extractors import load_extractor

        cls = load_extractor(spec["target"])
        config = dataclasses.asdict(config_from_mapping(cls.Config, spec["config"]))
        inputs = {}
    return {"name": str(cls.name), "version": str(cls.version),
            "description": str(getattr(cls, "description", "")),
            "uses_truth": bool(getattr(cls, "uses_truth", False)),
            "config": json.loads(json.dumps(config, default=str)), "inputs": dict(inputs)}


def _job_list(spec: dict, work: Path) -> dict:
    from .extractors import EXTRACTORS
    from .plugins import SOLVERS, PluginError, describe_config

    kind = SOLVERS if spec["kind"] == "solver" else EXTRACTORS
    out = {}
    for name, target in sorted(kind.registry().items()):
        try:
            cls = kind.import_class(target)
            out[name] = {"version": str(cls.version), "description": str(cls.description),
                         "fields": [list(f) for f in describe_config(cls.Config)]}
        except (PluginError, Exception) as error:  # noqa: BLE001 -- listed with its error
            out[name] = {"error": f"{type(error).__name__}: {error}"}
    return out


JOBS = {"solve": _job_solve, "extract": _job_extract, "describe": _job_describe,
        "list": _job_list}


def child_main(spec_path: str) -> int:
    ppid = os.getppid()
    _die_with_parent()
    if os.getppid() != ppid:
        return 1
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    spec_file = Path(spec_path)
    work = spec_file.parent
    response = work / "out" / ".response.json"
    spec = json.loads(spec_file.read_text())
    import resource

    mem = spec.get("memory_bytes")
    if mem:
        resource.setrlimit(resource.RLIMIT_AS, (int(mem), int(mem)))
    if spec.get("file_bytes"):  # no file larger than the disk limit (Python ignores SIGXFSZ)
        hard = resource.getrlimit(resource.RLIMIT_FSIZE)[1]
        size = int(spec["file_bytes"])
        size = size if hard == resource.RLIM_INFINITY else min(size, hard)
        resource.setrlimit(resource.RLIMIT_FSIZE, (size, size))
    try:
        result = JOBS[spec["job"]](spec, work)
        doc = {"status": "ok", "result": result}
        code = 0
    except BaseException as error:  # noqa: BLE001 -- reported to the parent
        kind = type(error).__name__
        doc = {"status": "error", "kind": kind, "message": str(error),
               "error": f"{kind}: {error}", "traceback": traceback.format_exc()}
        code = 1
    try:
        tmp = response.with_name(".response.tmp")
        tmp.write_text(json.dumps(doc, default=str))
        os.replace(tmp, response)
    except MemoryError:
        return 3
    return code


if __name__ == "__main__":
    sys.exit(child_main(sys.argv[1]))
