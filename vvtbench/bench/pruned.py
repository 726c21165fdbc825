"""What a cached task's record says was pruned: the files a check of its folder excuses.

Written by :mod:`vvtbench.bench.prune`, read by the checks of :mod:`vvtbench.bench.stages`.
"""

from __future__ import annotations

__all__ = ["PRUNED", "excused", "pruned_files"]

#: the ``task.json`` key of a generate task whose videos were pruned
PRUNED = "pruned"


def pruned_files(info: dict) -> dict[str, dict]:
    """``{name: {"bytes", "sha256"}}`` of the files a task's ``task.json`` records as pruned
    (names relative to the task folder, as in its ``files``)."""
    record = info.get(PRUNED) if isinstance(info, dict) else None
    entries = record.get("files") if isinstance(record, dict) else None
    out = {}
    for e in entries if isinstance(entries, list) else []:
        if isinstance(e, dict) and isinstance(e.get("name"), str) and isinstance(
                e.get("sha256"), str):
            out[e["name"]] = {"bytes": e.get("bytes"), "sha256": e["sha256"]}
    return out


def excused(info: dict) -> set[str]:
    """Names of the files a task's ``task.json`` records as pruned with the very sha256 its
    ``files`` table lists: the files a check of its folder may find absent."""
    files = info.get("files") if isinstance(info, dict) else None
    files = files if isinstance(files, dict) else {}
    return {n for n, e in pruned_files(info).items() if files.get(n) == e["sha256"]}
