"""Option types and messages shared by every command: bounded numbers, one-line errors, and
"did you mean" for a misspelt scene, suite or solver name."""

from __future__ import annotations

import argparse
import difflib
import math
import re
from collections.abc import Callable, Iterable


def _number(kind: type, text: str) -> float:
    try:
        value = kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{text!r} is not {'an integer' if kind is int else 'a number'}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
    return value


def bounded(kind: type = float, *, gt: float | None = None, ge: float | None = None,
            le: float | None = None, also: tuple = ()) -> Callable[[str], float]:
    """An argparse ``type`` reading an int or a finite float within bounds, saying what is
    allowed when not (``also``: extra allowed values, e.g. ``-1`` for "all CPUs")."""
    parts = [f"> {gt:g}" if gt is not None else "", f">= {ge:g}" if ge is not None else "",
             f"<= {le:g}" if le is not None else ""]
    allowed = " and ".join(p for p in parts if p) or "finite"
    allowed = ("an integer " if kind is int else "a number ") + allowed + "".join(
        f" (or {a})" for a in also)

    def parse(text: str) -> float:
        value = _number(kind, text)
        if value in also:
            return value
        if (gt is not None and not value > gt) or (ge is not None and not value >= ge) \
                or (le is not None and not value <= le):
            raise argparse.ArgumentTypeError(f"{text!r}: must be {allowed}")
        return value

    parse.__name__ = kind.__name__  # argparse names the type in its messages
    return parse


positive_int = bounded(int, ge=1)
#: family instances one command may ask for
MAX_INSTANCES = 1_000_000
instance_count = bounded(int, ge=1, le=MAX_INSTANCES)
nonnegative_int = bounded(int, ge=0)
positive_float = bounded(float, gt=0)
nonnegative_float = bounded(float, ge=0)
finite_float = bounded(float)


def suggest(word: str, known: Iterable[str]) -> str:
    """``"; did you mean 'x'?"`` for the close matches of ``word`` among ``known``, else
    ``""``."""
    matches = difflib.get_close_matches(str(word), sorted(set(known)), n=3, cutoff=0.6)
    if not matches:
        return ""
    return "; did you mean " + " or ".join(repr(m) for m in matches) + "?"


def _scene_names() -> list[str]:
    from ..scene.scene import SCENES_DIR

    return sorted(p.stem for p in SCENES_DIR.glob("*.toml")) if SCENES_DIR.is_dir() else []


def _suite_names() -> list[str]:
    from ..bench import SUITES_DIR

    return sorted(p.stem for p in SUITES_DIR.glob("*.toml")) if SUITES_DIR.is_dir() else []


def _solver_names() -> list[str]:
    from ..solving.plugins import SOLVERS

    return sorted(SOLVERS.registry())  # names only: plug-ins are imported in sealed children


_UNKNOWN = (  # message pattern -> the names the unknown one is compared with
    (re.compile(r"^(?P<name>[^:\n]+): no such scene file"), _scene_names),
    (re.compile(r"^(?P<name>[^:\n]+): no such suite file"), _suite_names),
    (re.compile(r"unknown solver '(?P<name>[^']+)'"), _solver_names),
)


def one_line(message: str) -> str:
    """A message on one line (line breaks become ``"; "``)."""
    return "; ".join(part.strip() for part in str(message).splitlines() if part.strip())


def explain(error: BaseException | str) -> str:
    """The one-line message of ``error``, with a "did you mean" for a misspelt scene, suite
    or solver name, and the path for an OS error that has one."""
    if isinstance(error, OSError) and error.filename is not None and error.strerror:
        text = f"{error.filename}: {error.strerror}"
    else:
        text = str(error) or type(error).__name__
    text = one_line(text)
    for pattern, names in _UNKNOWN:
        m = pattern.search(text)
        if m and "did you mean" not in text:
            try:
                hint = suggest(m.group("name").strip(), names())
            except Exception:  # noqa: BLE001 -- a hint must never hide the error
                hint = ""
            text += hint
            break
    return text
