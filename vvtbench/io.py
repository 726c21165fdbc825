"""File writing shared by every stage: atomic (temp file + rename), JSON-safe, no pickle."""

from __future__ import annotations

import json
import os
import uuid
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["jsonable", "open_new", "write_bytes", "write_json", "write_npz", "write_text"]


def jsonable(x: Any) -> Any:
    """Plain JSON data: numpy scalars and arrays to Python, tuples to lists, paths to str,
    non-finite floats to None."""
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return jsonable(x.tolist())
    if isinstance(x, np.generic):
        return jsonable(x.item())
    if isinstance(x, float) and not np.isfinite(x):
        return None
    if isinstance(x, Path):
        return str(x)
    return x


def _temp(path: Path) -> Path:
    return path.with_name(f".{path.name}.{os.getpid()}-{uuid.uuid4().hex[:8]}.tmp")


def open_new(path: str | Path, mode: str = "wb"):
    """A file object for a file created now at ``path``: ``O_EXCL`` (never an existing file)
    and ``O_NOFOLLOW`` (never through a link planted at that name)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o644)
    return os.fdopen(fd, mode)


def write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically: a new temporary file beside it, renamed over it
    (a link at ``path`` is replaced, never written through)."""
    path = Path(path)
    tmp = _temp(path)
    try:
        with open_new(tmp) as f:
            f.write(data)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_text(path: str | Path, text: str) -> None:
    """Write ``text`` to ``path`` atomically (a reader sees the old or the new file; a link at
    ``path`` is replaced, never written through)."""
    write_bytes(path, text.encode())


def write_json(path: str | Path, data: Any, *, indent: int = 1, sort_keys: bool = False) -> None:
    """``data`` as indented JSON (see :func:`jsonable`), atomically.

    >>> import tempfile
    >>> p = Path(tempfile.mkdtemp()) / "a.json"
    >>> write_json(p, {"x": np.float64(1.5), "y": (1, 2), "z": float("nan")})
    >>> json.loads(p.read_text())
    {'x': 1.5, 'y': [1, 2], 'z': None}
    """
    write_text(path, json.dumps(jsonable(data), indent=indent, sort_keys=sort_keys, default=str)
               + "\n")


def write_npz(path: str | Path, arrays: dict[str, np.ndarray], compressed: bool = True) -> None:
    """``arrays`` as an .npz file, atomically (object arrays refused: no pickle)."""
    path = Path(path)
    for k, a in arrays.items():
        if np.asarray(a).dtype == object:
            raise TypeError(f"write_npz: array {k!r} has dtype object (would need pickle)")
    tmp = path.with_name(f".{path.stem}.{os.getpid()}-{uuid.uuid4().hex[:8]}.tmp.npz")
    try:
        with open_new(tmp) as f:
            (np.savez_compressed if compressed else np.savez)(f, **arrays)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
