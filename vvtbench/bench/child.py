"""Solver isolation: a solve task runs in a child process with a time and a memory limit.

The parent (:func:`run_isolated`, called by :func:`vvtbench.bench.stages.execute_task`) writes a
request (the cache folder, the task as JSON, the output folder, the limits) into
``OUT/.child/request.json`` and starts ``python -m vvtbench.bench.child REQUEST`` in a new
session. The child sets ``RLIMIT_AS``, runs the stage body, writes its outputs into the output
folder itself and ``response.json`` last (atomically). The parent waits at most ``timeout``
seconds, then kills the child's whole process group; it classifies what happened from the
exit status and the response, and never trusts a response that is missing:

* no response after ``timeout`` s: ``timeout``;
* exit without a response (``os._exit``, a signal such as SIGSEGV): ``crashed``;
* ``MemoryError`` in the child (the address-space limit), or SIGKILL not sent by the parent
  (the kernel's OOM killer): ``out of memory``.

Nothing crosses the process boundary but paths and JSON (no pickle).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import traceback
from pathlib import Path

from ..io import write_json

__all__ = ["DEFAULT_TIMEOUT", "default_memory_bytes", "run_isolated"]

DEFAULT_TIMEOUT = 3600.0   # seconds per solve (``--timeout``, a suite's ``timeout``)
DEFAULT_MEMORY_FRACTION = 0.75  # of the machine's memory, divided among the workers
_LOG_TAIL = 4000


def machine_memory_bytes() -> int | None:
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return None


def default_memory_bytes(workers: int = 1) -> int | None:
    """The default memory limit of one solve: 75 % of the machine's memory / workers."""
    total = machine_memory_bytes()
    return None if total is None else int(total * DEFAULT_MEMORY_FRACTION / max(1, workers))


def _signal_name(num: int) -> str:
    try:
        return signal.Signals(num).name
    except ValueError:
        return f"signal {num}"


def _kill_group(proc: subprocess.Popen) -> None:
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass
    try:
        proc.kill()
    except ProcessLookupError:
        pass


def _child_env(threads: int | None) -> dict:
    env = dict(os.environ)
    paths = [p for p in sys.path if p and os.path.isdir(p)]
    old = env.get("PYTHONPATH")
    env["PYTHONPATH"] = os.pathsep.join(paths + ([old] if old else []))
    if threads:
        for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
            env[var] = str(threads)
    env["PYTHONFAULTHANDLER"] = "1"   # a segfault leaves its Python stack in the log
    return env


# Children of this process, so that a signal handler can end them (see executors).
RUNNING: dict[int, subprocess.Popen] = {}


def kill_running() -> None:
    """End every solve child this process started (Ctrl-C, SIGTERM)."""
    for proc in list(RUNNING.values()):
        _kill_group(proc)


def run_isolated(cache: Path, task, out: Path, *, timeout: float | None,
                 memory_bytes: int | None, threads: int | None = None) -> dict:
    """Run ``task`` (a solve) in a child process writing into ``out``; return the stage's
    result dict, or raise :class:`IsolationError` (timeout, crash, out of memory) or
    :class:`ChildError` (the stage raised; its message and traceback)."""
    work = out / ".child"
    work.mkdir(parents=True, exist_ok=True)
    request = work / "request.json"
    response = work / "response.json"
    write_json(request, {"cache": str(cache), "out": str(out),
                         "task": {"stage": task.stage, "key": task.key, "deps": task.deps,
                                  "payload": task.payload, "label": task.label},
                         "threads": threads, "memory_bytes": memory_bytes})
    log_path = work / "log.txt"
    t0 = time.perf_counter()
    with open(log_path, "wb") as log:
        proc = subprocess.Popen([sys.executable, "-m", "vvtbench.bench.child", str(request)],
                                stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT,
                                env=_child_env(threads), start_new_session=True)
        RUNNING[proc.pid] = proc
        timed_out = False
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            timed_out = True
        finally:
            _kill_group(proc)   # also whatever the plug-in started
            proc.wait()
            RUNNING.pop(proc.pid, None)
    seconds = time.perf_counter() - t0
    log_tail = _tail(log_path)
    limit = (f"{memory_bytes / 2**30:.3g} GB" if memory_bytes else "none")
    if timed_out:
        raise IsolationError("timeout", f"no result after {timeout:g} s (the time limit: "
                                        "--timeout or the suite's `timeout`)", log_tail)
    doc = None
    if response.is_file():
        try:
            doc = json.loads(response.read_text())
        except ValueError:
            doc = None
    code = proc.returncode
    if doc is None:
        if code is not None and code < 0:
            name = _signal_name(-code)
            if -code == signal.SIGKILL:
                raise IsolationError("out of memory", f"killed by {name} after {seconds:.1f} s "
                                     f"(probably the kernel's OOM killer; limit {limit}, "
                                     "--memory-gb)", log_tail)
            raise IsolationError("crashed", f"killed by signal {-code} ({name}) after "
                                            f"{seconds:.1f} s", log_tail)
        raise IsolationError("crashed", f"the solver process exited with code {code} without "
                                        "a result", log_tail)
    if doc.get("status") == "ok":
        return doc["result"]
    if doc.get("kind") == "MemoryError":
        raise IsolationError("out of memory", f"MemoryError: {doc.get('message', '')} "
                                              f"(limit {limit}, --memory-gb)",
                             doc.get("traceback", "") + log_tail)
    raise ChildError(doc.get("error", "unknown error"), doc.get("traceback", "") + log_tail)


def _tail(path: Path) -> str:
    try:
        data = path.read_bytes()[-_LOG_TAIL:].decode(errors="replace")
    except OSError:
        return ""
    return f"\n--- solver process output (last {_LOG_TAIL} bytes) ---\n{data}" if data else ""


class IsolationError(RuntimeError):
    """The child process timed out, crashed or ran out of memory (``kind``)."""

    def __init__(self, kind: str, message: str, log: str = ""):
        super().__init__(f"{kind}: {message}")
        self.kind, self.log = kind, log


class ChildError(RuntimeError):
    """The stage raised in the child: ``message`` is ``stage: Type: text``."""

    def __init__(self, message: str, log: str = ""):
        super().__init__(message)
        self.log = log


# --------------------------------------------------------------------------- the child side

def _die_with_parent() -> None:
    """Linux: SIGKILL this process when its parent dies (a killed worker leaves no orphan)."""
    try:
        import ctypes

        libc = ctypes.CDLL(None)
        libc.prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except Exception:  # noqa: BLE001 -- best effort, not on macOS
        pass


def child_main(request_path: str) -> int:
    ppid = os.getppid()
    _die_with_parent()
    if os.getppid() != ppid:  # the parent died before prctl
        return 1
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent decides when we stop
    req = json.loads(Path(request_path).read_text())
    response = Path(request_path).with_name("response.json")
    mem = req.get("memory_bytes")
    if mem:
        import resource

        resource.setrlimit(resource.RLIMIT_AS, (int(mem), int(mem)))
    try:
        from .graph import Task
        from .stages import STAGE_FUNCS

        t = req["task"]
        task = Task(t["stage"], t["key"], list(t["deps"]), t["payload"], t.get("label", ""))
        result = STAGE_FUNCS[task.stage](Path(req["cache"]), task, Path(req["out"]), {})
        write_json(response, {"status": "ok", "result": result})
        return 0
    except BaseException as error:  # noqa: BLE001 -- reported to the parent
        kind = type(error).__name__
        try:
            write_json(response, {"status": "error", "kind": kind, "message": str(error),
                                  "error": f"{req['task']['stage']}: {kind}: {error}",
                                  "traceback": traceback.format_exc()})
        except MemoryError:
            return 3
        return 1


if __name__ == "__main__":
    sys.exit(child_main(sys.argv[1]))
