"""Where tasks run: in process, on a local process pool, or on a Dask cluster."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

from .graph import STAGES, Task
from .stages import execute_task


class _Inline:
    class _Done:
        def __init__(self, value):
            self._v = value

        def result(self):
            return self._v

    def submit(self, fn, *args):
        return self._Done(fn(*args))

    def wait_any(self, futures):
        return set(futures)

    def close(self):
        pass


class _Pool:
    def __init__(self, workers: int):
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        ctx = mp.get_context("spawn" if sys.platform == "darwin" else "forkserver")
        self.ex = ProcessPoolExecutor(max_workers=workers, mp_context=ctx)

    def submit(self, fn, *args):
        return self.ex.submit(fn, *args)

    def wait_any(self, futures):
        from concurrent.futures import FIRST_COMPLETED, wait

        done, _ = wait(futures, return_when=FIRST_COMPLETED)
        return done

    def close(self):
        self.ex.shutdown(wait=True, cancel_futures=True)


class _Dask:
    def __init__(self, scheduler):
        from distributed import Client

        if isinstance(scheduler, str):
            self.client, self.own = Client(scheduler), True
        else:  # a Client or a cluster object
            self.client = scheduler if hasattr(scheduler, "submit") else Client(scheduler)
            self.own = not hasattr(scheduler, "submit")

    def submit(self, fn, *args):
        return self.client.submit(fn, *args, pure=False)

    def wait_any(self, futures):
        from distributed import wait

        done, _ = wait(list(futures), return_when="FIRST_COMPLETED")
        return set(done)

    def close(self):
        if self.own:
            self.client.close()


def make_executor(workers: int = 1, scheduler=None):
    """A Dask executor for ``scheduler`` (an address, Client or cluster), else a local process
    pool of ``workers`` processes, else (``workers=1``) in process."""
    if scheduler is not None:
        return _Dask(scheduler)
    if workers > 1:
        return _Pool(workers)
    return _Inline()


def execute_graph(tasks: dict[str, Task], cache: Path, executor, progress: bool,
             threads: int | None) -> dict[str, dict]:
    from tqdm import tqdm

    remaining = dict(tasks)
    done: dict[str, dict] = {}
    bars = {}
    for stage in STAGES:
        n = sum(t.stage == stage for t in tasks.values())
        if n:
            bars[stage] = tqdm(total=n, desc=f"{stage:9s}", position=len(bars), leave=True,
                               disable=not progress, file=sys.stderr, unit="task")
    running: dict[Any, str] = {}
    try:
        while remaining or running:
            ready = [k for k, t in remaining.items() if all(d in done for d in t.deps)]
            for k in ready:
                task = remaining.pop(k)
                try:
                    running[executor.submit(execute_task, str(cache), task, threads)] = k
                except Exception as error:  # e.g. a broken process pool
                    done[k] = {"key": k, "status": "error", "computed": True, "seconds": 0.0,
                               "error": f"{task.stage}: cannot submit: "
                                        f"{type(error).__name__}: {error}"}
            if not running:
                break
            for fut in executor.wait_any(list(running)):
                k = running.pop(fut)
                try:
                    res = fut.result()
                except Exception as error:  # worker died etc.
                    res = {"key": k, "status": "error", "computed": True, "seconds": 0.0,
                           "error": f"{tasks[k].stage}: worker failure: "
                                    f"{type(error).__name__}: {error}"}
                done[k] = res
                bar = bars.get(tasks[k].stage)
                if bar is not None:
                    bar.update(1)
                    bar.set_postfix_str(tasks[k].label[:30])
    finally:
        for b in bars.values():
            b.close()
    return done
