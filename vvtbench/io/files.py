"""File writing shared by every stage: atomic (temp file + rename), JSON-safe, no pickle."""

from __future__ import annotations

import contextlib
import errno
import json
import os
import shutil
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

import numpy as np

__all__ = ["NoSpaceError", "atomic_file", "check_free_space", "is_disk_full", "jsonable",
           "open_new", "write_bytes", "write_json", "write_npz", "write_text"]


class NoSpaceError(OSError):
    """A folder's file system lacks the free space a write needs (``errno`` is ENOSPC)."""

    def __str__(self) -> str:
        return str(self.strerror)


def is_disk_full(error: BaseException) -> bool:
    """True for an ``OSError`` of a full disk or an exhausted quota (ENOSPC, EDQUOT)."""
    return isinstance(error, OSError) and error.errno in (errno.ENOSPC, errno.EDQUOT)


def check_free_space(folder: str | Path, needed: int, what: str = "the output") -> None:
    """Raise :class:`NoSpaceError` (one line naming ``folder`` and the bytes) when the file
    system holding ``folder`` (or its nearest existing parent) has less than ``needed``
    bytes free."""
    folder = Path(folder)
    probe = folder
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    free = shutil.disk_usage(probe).free
    if free < needed:
        raise NoSpaceError(errno.ENOSPC,
                           f"{folder}: not enough free space for {what}: needs about "
                           f"{needed:,} bytes ({_human(needed)}), {free:,} bytes "
                           f"({_human(free)}) free; free some space or choose another folder")


def tree_bytes(folder: str | Path) -> int:
    """Bytes of the regular files under ``folder`` (links not followed)."""
    return sum(p.stat().st_size for p in Path(folder).rglob("*") if p.is_file()
               and not p.is_symlink())


def _human(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if n < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} TiB"


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


@contextlib.contextmanager
def atomic_file(path: str | Path, mode: str = "wb") -> Iterator[IO]:
    """A file object to write ``path`` through, for writers that take one (``savefig``,
    ``to_parquet``, ``to_csv``, ``np.save``): a new temporary file beside ``path`` (``O_EXCL |
    O_NOFOLLOW``), renamed over ``path`` when the block ends without an error and removed when
    it raises (a full disk leaves nothing half-written; a link at ``path`` is replaced, never
    written through).

    >>> import tempfile
    >>> p = Path(tempfile.mkdtemp()) / "a.csv"
    >>> with atomic_file(p, "w") as f:
    ...     _ = f.write("x,y\\n")
    >>> p.read_text()
    'x,y\\n'
    """
    path = Path(path)
    tmp = _temp(path)
    try:
        with open_new(tmp, mode) as f:
            yield f
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


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


#: the time stamp of every member of an .npz written here (the zip format's earliest), so that
#: the same arrays give the same bytes whenever they are written
NPZ_DATE_TIME = (1980, 1, 1, 0, 0, 0)


def write_npz(path: str | Path, arrays: dict[str, np.ndarray], compressed: bool = True) -> None:
    """``arrays`` as an .npz file, atomically (object arrays refused: no pickle).

    The file is what :func:`numpy.savez` (``compressed``: :func:`numpy.savez_compressed`)
    writes, except that every member carries the fixed time stamp :data:`NPZ_DATE_TIME`
    instead of the clock's: equal arrays give equal bytes.

    >>> import tempfile
    >>> d = Path(tempfile.mkdtemp())
    >>> write_npz(d / "a.npz", {"x": np.arange(3)})
    >>> np.load(d / "a.npz")["x"].tolist()
    [0, 1, 2]
    """
    import zipfile

    path = Path(path)
    for k, a in arrays.items():
        if np.asarray(a).dtype == object:
            raise TypeError(f"write_npz: array {k!r} has dtype object (would need pickle)")
    tmp = path.with_name(f".{path.stem}.{os.getpid()}-{uuid.uuid4().hex[:8]}.tmp.npz")
    method = zipfile.ZIP_DEFLATED if compressed else zipfile.ZIP_STORED
    try:
        with open_new(tmp) as f, zipfile.ZipFile(f, mode="w", compression=method,
                                                 allowZip64=True) as zf:
            for key, value in arrays.items():
                info = zipfile.ZipInfo(f"{key}.npy", date_time=NPZ_DATE_TIME)
                info.compress_type = method
                with zf.open(info, "w", force_zip64=True) as member:
                    np.lib.format.write_array(member, np.asanyarray(value),
                                              allow_pickle=False)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
