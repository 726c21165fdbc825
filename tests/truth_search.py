"""A search of everything a solver can reach in its problem, for the truth (test helper).

:func:`leaves` walks attributes, ``__dict__``, dicts, lists, dataclasses, arrays and sparse
matrices; :func:`truth_in` reports the paths that hold the true material, a true 3-D mode or a
secret string (the scene's name, the sample's path).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import scipy.sparse as sp


def leaves(obj, seen=None, path="problem"):
    """(path, leaf) of every string, number and array reachable from ``obj``."""
    seen = set() if seen is None else seen
    if id(obj) in seen:
        return
    seen.add(id(obj))
    if isinstance(obj, (str, bytes, Path)):
        yield path, str(obj)
    elif isinstance(obj, (int, float, np.number)):
        yield path, np.asarray(obj, dtype=float)
    elif isinstance(obj, np.ndarray):
        yield path, obj
    elif sp.issparse(obj):
        yield path, obj.toarray()
    elif isinstance(obj, dict):
        for k, v in obj.items():
            yield from leaves(v, seen, f"{path}[{k!r}]")
    elif isinstance(obj, (list, tuple, set)):
        for i, v in enumerate(obj):
            yield from leaves(v, seen, f"{path}[{i}]")
    elif hasattr(obj, "__dict__") or dataclasses.is_dataclass(obj):
        for k, v in vars(obj).items():
            yield from leaves(v, seen, f"{path}.{k}")


def dump(problem, folder: Path) -> None:
    """Everything reachable from ``problem``: arrays to ``leaves.npz``, strings to JSON."""
    arrays, strings = {}, {}
    for i, (path, leaf) in enumerate(leaves(problem)):
        if isinstance(leaf, str):
            strings[path] = leaf
        elif np.asarray(leaf).dtype.kind in "fiub":
            arrays[f"a{i}"] = np.asarray(leaf)
            strings[f"a{i}"] = path
    folder.mkdir(parents=True, exist_ok=True)
    np.savez(folder / "leaves.npz", **arrays)
    (folder / "leaves.json").write_text(json.dumps(strings))


def truth_in(found: list[tuple[str, object]], truth, secrets: list[str]) -> list[str]:
    """Paths among ``found`` (path, leaf) pairs that hold the truth."""
    targets = [truth.w, truth.v] + [truth.modes_3d[:, i] for i in range(truth.modes_3d.shape[1])]
    hits = []
    for path, leaf in found:
        if isinstance(leaf, str):
            if any(s and s in leaf for s in secrets):
                hits.append(path)
            continue
        flat = np.asarray(leaf, dtype=float).ravel()
        if flat.size < 8:
            continue
        for t in targets:
            if flat.size == t.size and any(np.allclose(c, t, rtol=1e-6, atol=0)
                                           for c in (flat, -flat)):
                hits.append(path)
    return hits


def load_dump(folder: Path) -> list[tuple[str, object]]:
    strings = json.loads((folder / "leaves.json").read_text())
    out = [(p, s) for p, s in strings.items() if not p.startswith("a")
           or not p[1:].isdigit()]
    with np.load(folder / "leaves.npz") as z:
        out += [(strings[k], z[k]) for k in z.files]
    return out
