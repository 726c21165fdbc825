"""Where tasks run: in process, on a local process pool, or on a Dask cluster; the progress
display; Ctrl-C.

Solve tasks run in a child process of whichever process executes them (:mod:`.child`), so a
plug-in that hangs, exits or crashes never takes a worker (or the run) with it. A pool worker
that dies anyway (a crash in another stage) breaks the pool: the pool is restarted and the
tasks that were running are retried once; a task that breaks it twice is an error.
"""

from __future__ import annotations

import os
import signal
import sys
import time
from pathlib import Path
from typing import Any

from .graph import STAGES, Task
from .prune import VideoPlan
from .stages import execute_task

#: Seconds a Dask scheduler has to answer a connection (an address that accepts and never
#: answers would otherwise hang the command: distributed's Client waits for ever).
SCHEDULER_TIMEOUT = 10.0


class SchedulerError(ValueError):
    """A Dask scheduler address that cannot be reached or does not answer."""


def max_workers() -> int:
    """The most local worker processes a command starts: 4 per CPU of this machine."""
    return 4 * (os.cpu_count() or 1)


def check_workers(workers: int) -> int:
    """``workers`` when it is 1 to :func:`max_workers`, else ValueError saying what is
    allowed."""
    if not 1 <= int(workers) <= max_workers():
        raise ValueError(f"workers: {workers} is not allowed; allowed: 1 to {max_workers()} "
                         f"(4 per CPU; this machine has {os.cpu_count() or 1})")
    return int(workers)


def probe_scheduler(address: str, timeout: float | None = None) -> None:
    """Raise :class:`SchedulerError` unless a Dask scheduler at ``address`` answers an
    identity request within ``timeout`` seconds (default :data:`SCHEDULER_TIMEOUT`)."""
    import asyncio

    timeout = SCHEDULER_TIMEOUT if timeout is None else float(timeout)

    from distributed.comm import connect

    async def identity():
        comm = await connect(address, timeout=timeout)
        try:
            await comm.write({"op": "identity", "reply": True})
            return await comm.read()
        finally:
            comm.abort()

    try:
        reply = asyncio.run(asyncio.wait_for(identity(), timeout))
    except (TimeoutError, OSError, ValueError, TypeError) as error:
        why = str(error) or "no answer"
        if isinstance(error, TimeoutError) or "Timed out" in why:
            why = f"no answer within {timeout:g} s"
        raise SchedulerError(f"--scheduler {address}: no Dask scheduler answers there ({why}); "
                             "is the scheduler running at that address?") from None
    if not isinstance(reply, dict) or reply.get("type") != "Scheduler":
        raise SchedulerError(f"--scheduler {address}: answered, but not as a Dask scheduler "
                             f"(identity {str(reply)[:80]!r})")


class Interrupted(KeyboardInterrupt):
    """Ctrl-C during a run: ``finished`` of ``total`` tasks have a result in the cache."""

    def __init__(self, finished: int, total: int):
        super().__init__(f"interrupted: {finished} of {total} tasks finished")
        self.finished, self.total = finished, total


class _Inline:
    slots = 1

    class _Done:
        def __init__(self, value):
            self._v = value

        def result(self):
            return self._v

    def submit(self, fn, *args):
        return self._Done(fn(*args))

    def wait_any(self, futures):
        return set(futures)

    def restart(self):
        pass

    def terminate(self):
        pass

    def close(self):
        pass


def _end_with_run(run_pid: int) -> None:
    """SIGTERM this process when the run's process ``run_pid`` ends, even by SIGKILL: a pool
    worker's parent is the forkserver, which outlives a killed run, so the worker watches the
    run itself (a pidfd where Linux has one, else its pid twice a second)."""
    import threading

    main_thread = threading.main_thread().ident

    def watch() -> None:
        try:
            fd = os.pidfd_open(run_pid)
        except (AttributeError, OSError):
            fd = None
        if fd is not None:
            import select

            select.select([fd], [], [])
        else:
            while True:
                try:
                    os.kill(run_pid, 0)
                except ProcessLookupError:
                    break
                except PermissionError:
                    pass
                time.sleep(0.5)
        signal.pthread_kill(main_thread, signal.SIGTERM)  # interrupts a blocking wait

    threading.Thread(target=watch, name="vvtbench-run-watch", daemon=True).start()


def _worker_init(run_pid: int | None = None):
    """Pool workers: Ctrl-C is the parent's business; SIGTERM (the parent stopping the run, or
    the run's process ending, even killed) ends the solve child and removes the half-written
    task folder before exiting, so nothing is written into the run folder after the run."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)

    def on_term(signum, frame):
        import shutil

        from .child import kill_running
        from .stages import CURRENT

        kill_running()
        if CURRENT.get("tmp") is not None:
            shutil.rmtree(CURRENT["tmp"], ignore_errors=True)
        os._exit(128 + signum)

    signal.signal(signal.SIGTERM, on_term)
    if run_pid is not None:
        _end_with_run(run_pid)


class _Pool:
    def __init__(self, workers: int):
        self.workers = workers
        self._start()

    @property
    def slots(self) -> int:
        return self.workers

    def _start(self):
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        ctx = mp.get_context("spawn" if sys.platform == "darwin" else "forkserver")
        self.ex = ProcessPoolExecutor(max_workers=self.workers, mp_context=ctx,
                                      initializer=_worker_init, initargs=(os.getpid(),))

    def submit(self, fn, *args):
        return self.ex.submit(fn, *args)

    def wait_any(self, futures):
        from concurrent.futures import FIRST_COMPLETED, wait

        done, _ = wait(futures, return_when=FIRST_COMPLETED)
        return done

    def restart(self):
        self.ex.shutdown(wait=False, cancel_futures=True)
        self._start()

    def terminate(self):
        procs = list((getattr(self.ex, "_processes", None) or {}).values())
        for p in procs:
            try:
                p.terminate()
            except (OSError, AttributeError):
                pass
        self.ex.shutdown(wait=False, cancel_futures=True)
        for p in procs:
            try:
                p.join(timeout=5)
            except (OSError, AttributeError, AssertionError):
                pass

    def close(self):
        self.ex.shutdown(wait=True, cancel_futures=True)


class _Dask:
    def __init__(self, scheduler):
        from distributed import Client

        if isinstance(scheduler, str):
            probe_scheduler(scheduler)
            self.client = Client(scheduler, timeout=SCHEDULER_TIMEOUT)
            self.own = True
        else:  # a Client or a cluster object
            self.client = scheduler if hasattr(scheduler, "submit") else Client(scheduler)
            self.own = not hasattr(scheduler, "submit")
        self.futures: list = []

    @property
    def slots(self) -> int | None:
        try:
            workers = self.client.scheduler_info()["workers"].values()
            return max(1, sum(int(w.get("nthreads", 1)) for w in workers))
        except Exception:  # noqa: BLE001 -- unknown: no window
            return None

    def submit(self, fn, *args):
        fut = self.client.submit(fn, *args, pure=False)
        self.futures.append(fut)
        return fut

    def wait_any(self, futures):
        from distributed import wait

        done, _ = wait(list(futures), return_when="FIRST_COMPLETED")
        return set(done)

    def restart(self):
        pass

    def terminate(self):
        try:
            self.client.cancel(self.futures)
        except Exception:  # noqa: BLE001 -- best effort while stopping
            pass

    def close(self):
        if self.own:
            self.client.close()


def make_executor(workers: int = 1, scheduler=None):
    """A Dask executor for ``scheduler`` (an address, Client or cluster), else a local process
    pool of ``workers`` processes, else (``workers=1``) in process."""
    if scheduler is not None:
        return _Dask(scheduler)
    check_workers(workers)
    if workers > 1:
        return _Pool(workers)
    return _Inline()


# --------------------------------------------------------------------------- progress

class Progress:
    """Per-stage progress on stderr: one live ``rich`` display in a terminal; otherwise plain
    log lines (no carriage returns, no cursor codes), at most one every ``every`` seconds
    plus one when a stage completes. A stage's clock starts when its first task is submitted,
    so its rate and remaining time are its own."""

    def __init__(self, counts: dict[str, int], enabled: bool = True, stream=None,
                 every: float = 15.0):
        self.counts = {s: n for s, n in counts.items() if n}
        self.done = dict.fromkeys(self.counts, 0)
        self.failed = dict.fromkeys(self.counts, 0)
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = enabled and bool(self.counts)
        self.every = every
        self.t0 = time.monotonic()
        self.last = self.t0
        self.started: set[str] = set()
        self.live = None
        if not self.enabled:
            return
        isatty = getattr(self.stream, "isatty", lambda: False)
        if isatty() and os.environ.get("TERM") != "dumb":
            from rich.console import Console
            from rich.progress import (
                BarColumn,
                MofNCompleteColumn,
                TextColumn,
                TimeElapsedColumn,
                TimeRemainingColumn,
            )
            from rich.progress import (
                Progress as RichProgress,
            )

            self.live = RichProgress(
                TextColumn("{task.description:9s}"), BarColumn(), MofNCompleteColumn(),
                TextColumn("{task.fields[failed]}", style="red"), TimeElapsedColumn(),
                TextColumn("eta"), TimeRemainingColumn(),
                TextColumn("{task.fields[last]}", style="dim"),
                console=Console(file=self.stream), refresh_per_second=4)
            self.ids = {s: self.live.add_task(s, total=n, start=False, failed="", last="")
                        for s, n in self.counts.items()}
            self.live.start()
        else:
            total = sum(self.counts.values())
            self._line(f"{total} tasks: " + ", ".join(f"{s} {n}" for s, n in self.counts.items()))

    def _line(self, text: str) -> None:
        el = time.monotonic() - self.t0
        print(f"[{int(el // 60):02d}:{el % 60:04.1f}] {text}", file=self.stream, flush=True)

    def start(self, stage: str) -> None:
        if not self.enabled or stage in self.started:
            return
        self.started.add(stage)
        if self.live is not None:
            self.live.start_task(self.ids[stage])

    def advance(self, stage: str, label: str, ok: bool) -> None:
        if not self.enabled or stage not in self.counts:
            return
        self.start(stage)
        self.done[stage] += 1
        self.failed[stage] += 0 if ok else 1
        if self.live is not None:
            f = self.failed[stage]
            self.live.update(self.ids[stage], advance=1, failed=f"{f} failed" if f else "",
                             last=label[:30])
            return
        now = time.monotonic()
        complete = self.done[stage] == self.counts[stage]
        if complete or now - self.last >= self.every:
            self.last = now
            parts = [f"{s} {self.done[s]}/{n}" + (f" ({self.failed[s]} failed)"
                                                   if self.failed[s] else "")
                     for s, n in self.counts.items()]
            self._line(("done " + stage + "; " if complete else "") + ", ".join(parts))

    def close(self) -> None:
        if self.live is not None:
            self.live.stop()
            self.live = None


# --------------------------------------------------------------------------- the graph

def execute_graph(tasks: dict[str, Task], cache: Path, executor, progress: bool | Progress,
                  threads: int | None, limits: dict | None = None,
                  videos: VideoPlan | None = None) -> dict[str, dict]:
    """Run every task as soon as its dependencies are done; a status dict per task key.
    Ctrl-C terminates what runs (no half-written output stays) and raises
    :class:`Interrupted`.

    ``videos`` (default: built from the cache, pruning off): what to do about pruned videos
    (:class:`~vvtbench.bench.prune.VideoPlan`): samples whose pruned video a task needs are
    rendered again and checked, and with pruning on a sample's videos are deleted here, in
    the scheduling process, once every task reading them is done. While pruning, no more
    tasks are handed out than the executor has slots, the furthest stage first, so a sample's
    videos are read and deleted before the next samples are rendered: the disk holds the
    videos of about as many samples as there are workers, not of the whole suite."""
    from concurrent.futures.process import BrokenProcessPool

    videos = videos if videos is not None else VideoPlan.build(tasks, Path(cache))
    remaining = dict(tasks)
    done: dict[str, dict] = {}
    counts = {s: sum(t.stage == s for t in tasks.values()) for s in STAGES}
    bar = progress if isinstance(progress, Progress) else Progress(counts, bool(progress))
    running: dict[Any, str] = {}
    retried: set[str] = set()
    window = getattr(executor, "slots", None) if videos.prune else None
    depth = {s: i for i, s in enumerate(STAGES)}
    try:
        while remaining or running:
            ready = [k for k, t in remaining.items() if all(d in done for d in t.deps)]
            if window is not None:
                ready.sort(key=lambda k: -depth[tasks[k].stage])  # stable: suite order
                ready = ready[:max(0, window - len(running))]
            for k in ready:
                task = remaining.pop(k)
                bar.start(task.stage)
                blocked = videos.blocked(k, done)
                if blocked is not None:
                    done[k] = {"key": k, "status": "skipped", "computed": False,
                               "seconds": 0.0, "error": blocked[1], "upstream": blocked[0]}
                    bar.advance(task.stage, task.label, False)
                    videos.finished(k, done)
                    continue
                try:
                    running[executor.submit(execute_task, str(cache), task, threads,
                                            limits, videos.force_of(k))] = k
                except KeyboardInterrupt:
                    raise
                except Exception as error:  # e.g. a broken process pool
                    done[k] = {"key": k, "status": "error", "computed": True, "seconds": 0.0,
                               "error": f"{task.stage}: cannot submit: "
                                        f"{type(error).__name__}: {error}"}
                    bar.advance(task.stage, task.label, False)
                    videos.finished(k, done)
            if not running:
                if ready:  # all of them settled without running: look again
                    continue
                break
            broken = False
            for fut in executor.wait_any(list(running)):
                k = running.pop(fut)
                try:
                    res = fut.result()
                except BrokenProcessPool:
                    broken = True
                    if k not in retried:  # maybe an innocent bystander: once more
                        retried.add(k)
                        remaining[k] = tasks[k]
                        continue
                    res = {"key": k, "status": "error", "computed": True, "seconds": 0.0,
                           "error": f"{tasks[k].stage}: crashed: the worker process died "
                                    "(twice) while running this task"}
                except Exception as error:  # noqa: BLE001 -- worker died etc.
                    res = {"key": k, "status": "error", "computed": True, "seconds": 0.0,
                           "error": f"{tasks[k].stage}: worker failure: "
                                    f"{type(error).__name__}: {error}"}
                done[k] = res
                bar.advance(tasks[k].stage, tasks[k].label, res.get("status") != "error")
                videos.finished(k, done)
            if broken:
                for fut, k in list(running.items()):  # every one of them failed with the pool
                    running.pop(fut)
                    remaining[k] = tasks[k]
                    retried.add(k)
                executor.restart()
    except KeyboardInterrupt:
        bar.close()
        executor.terminate()
        from .child import kill_running

        kill_running()
        raise Interrupted(sum(r.get("status") == "ok" for r in done.values()),
                          len(tasks)) from None
    finally:
        bar.close()
    return done
