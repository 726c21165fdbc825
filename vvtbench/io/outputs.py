"""Output folders a command owns: one it created, or one it marked as its own before.

A command that writes several files into an ``-o`` folder (``score``, ``invert``, ``release
build``) first claims it with :func:`claim_output`:

* a missing folder is created and marked (a hidden ``.vvtbench-output.json`` naming the
  command);
* an empty folder is marked;
* a folder marked by the same command is the command's own: it is updated (each file through
  an atomic rename; files the command does not write are left alone);
* anything else -- a folder holding files vvtbench did not write, one marked by another
  command, a symbolic link, a file -- is refused with one line naming the folder and some of
  what it holds, before anything is written.

So a command never replaces or lists a file the user put there (a ``results.csv``, a
``report.md``, a ``SHA256SUMS``, notes).
"""

from __future__ import annotations

import json
import os
import stat
from collections.abc import Callable
from pathlib import Path

__all__ = ["MARK", "OutputError", "claim_output"]

MARK = ".vvtbench-output.json"
_MAX_MARK_BYTES = 1 << 16


class OutputError(ValueError):
    """An output folder a command may not write into; the message names it."""


def _mark_of(out: Path) -> dict | None:
    """The mark of ``out`` (a regular file, not a link, of bounded size), or None."""
    try:
        fd = os.open(out / MARK, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    except OSError:
        return None
    with os.fdopen(fd, "rb") as f:
        st = os.fstat(f.fileno())
        if not stat.S_ISREG(st.st_mode) or st.st_size > _MAX_MARK_BYTES:
            return None
        try:
            doc = json.loads(f.read())
        except ValueError:
            return None
    return doc if isinstance(doc, dict) and doc.get("generator") == "vvtbench" else None


def _shown(names: list[str]) -> str:
    return ", ".join(names[:3]) + (f" and {len(names) - 3} more" if len(names) > 3 else "")


def claim_output(out: str | Path, command: str, *, create: bool = True,
                 adopt: Callable[[Path], bool] | None = None) -> Path:
    """Check that ``vvtbench COMMAND`` may write into the folder ``out`` (module notes) and,
    with ``create``, create and mark it. ``adopt(out)`` may accept a folder the command wrote
    before folders were marked. Returns ``out``.

    Raises
    ------
    OutputError
        One line naming ``out`` and why it is not the command's.
    """
    from .files import write_json

    out = Path(out)
    label = f"-o {out}"
    if out.is_symlink():
        raise OutputError(f"{label}: a symbolic link; give a new folder (never written "
                          "through a link)")
    if out.exists() and not out.is_dir():
        raise OutputError(f"{label}: exists and is not a folder; give a new folder")
    if out.is_dir():
        mark = _mark_of(out)
        if mark is not None and mark.get("command") != command:
            raise OutputError(f"{label}: written by `vvtbench {mark.get('command')}`, not by "
                              f"`vvtbench {command}`; give a new folder")
        if mark is None:
            held = sorted(p.name for p in out.iterdir())
            if held and not (adopt is not None and adopt(out)):
                raise OutputError(f"{label}: holds files vvtbench {command} did not write "
                                  f"({_shown(held)}); give a new or empty folder (nothing in "
                                  "it is replaced)")
    if create:
        out.mkdir(parents=True, exist_ok=True)
        if _mark_of(out) is None:
            write_json(out / MARK, {"generator": "vvtbench", "command": command})
    return out
