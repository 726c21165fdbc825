"""One writer per run folder: an exclusive ``fcntl.flock`` on ``OUT/.lock`` held for the whole
run, with the holder's pid, host and start time written in it for the message a second run
gets. The kernel drops the lock when the holder exits, however it exits."""

from __future__ import annotations

import json
import os
import socket
import time
from pathlib import Path

__all__ = ["RunLocked", "RunLock"]


class RunLocked(RuntimeError):
    """Another process holds the run folder's lock (the message names it)."""


class RunLock:
    def __init__(self, folder: str | Path, wait: bool = False, on_wait=None,
                 name: str = ".lock", remove: bool = False):
        self.path = Path(folder) / name
        self.remove = remove  # delete the lock file on release (a lock beside a user's file)
        self.wait = wait
        self.on_wait = on_wait
        self.fd: int | None = None

    def _holder(self) -> str:
        try:
            info = json.loads(self.path.read_text() or "{}")
        except (OSError, ValueError):
            info = {}
        if not info:
            return "another process"
        started = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(info.get("start", 0)))
        return f"pid {info.get('pid')} on {info.get('host')}, started {started}"

    def acquire(self) -> RunLock:
        import fcntl

        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:  # never through a link planted at .lock
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o644)
        except OSError as error:
            raise RunLocked(f"{self.path}: cannot open the folder's lock ({error.strerror}; "
                            "a symbolic link there is refused)") from None
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = self._holder()
                if not self.wait:
                    raise RunLocked(f"{self.path.parent}: in use by another vvtbench run "
                                    f"({holder}); wait for it to finish, or use --wait"
                                    ) from None
                if self.on_wait is not None:
                    self.on_wait(f"{self.path.parent}: waiting for the run holding it "
                                 f"({holder})")
                fcntl.flock(fd, fcntl.LOCK_EX)
        except BaseException:
            os.close(fd)
            raise
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps({"pid": os.getpid(), "host": socket.gethostname(),
                                  "start": time.time()}).encode(), 0)
        self.fd = fd
        return self

    def release(self) -> None:
        if self.fd is None:
            return
        import fcntl

        try:
            os.ftruncate(self.fd, 0)
            if self.remove:
                self.path.unlink(missing_ok=True)
            fcntl.flock(self.fd, fcntl.LOCK_UN)
        finally:
            os.close(self.fd)
            self.fd = None

    def __enter__(self):
        return self.acquire()

    def __exit__(self, *exc):
        self.release()
