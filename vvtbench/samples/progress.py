"""Per-stage progress of a generation: rich progress bars plus an optional callback."""

from __future__ import annotations

from collections.abc import Callable

__all__ = ["ProgressCallback", "StageProgress"]


ProgressCallback = Callable[[str, int, int], None]


class StageProgress:
    """Per-stage progress bars (rich) plus an optional callback(stage, done, total)."""

    def __init__(self, enabled: bool, callback: ProgressCallback | None, label: str) -> None:
        self.callback = callback
        self.bar = None
        self.label = label
        if enabled:
            from rich.progress import (
                BarColumn,
                MofNCompleteColumn,
                Progress,
                TextColumn,
                TimeElapsedColumn,
                TimeRemainingColumn,
            )

            self.bar = Progress(
                TextColumn("{task.description:<28}"), BarColumn(), MofNCompleteColumn(),
                TimeElapsedColumn(), TimeRemainingColumn(), transient=False,
            )
            self.bar.start()
        self._task = None
        self._stage = ""
        self._total = 0
        self._done = 0

    def stage(self, name: str, total: int, done: int = 0) -> None:
        self._stage, self._total, self._done = name, max(int(total), 1), int(done)
        if self.bar is not None:
            self._task = self.bar.add_task(f"{self.label} {name}", total=self._total,
                                           completed=self._done)
        self._report()

    def advance(self, n: int = 1) -> None:
        self._done += n
        if self.bar is not None and self._task is not None:
            self.bar.update(self._task, completed=self._done)
        self._report()

    def _report(self) -> None:
        if self.callback is not None:
            self.callback(self._stage, self._done, self._total)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.stop()
            self.bar = None
