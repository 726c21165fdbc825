"""Extracted modes in a shard's result set, compact and lossless for every score.

An extraction writes each mode's dense image-space shape (``modes.npz``: ``shapes`` ``(k, H,
W, 2)`` float32, ``confidence`` ``(H, W)``): noise that does not compress, about 0.5 MB a
mode at 256². What reads it after the extraction, in a run of a suite:

* the observation of one extraction (one view, one video): the shapes bilinearly sampled at
  the pixels of the inference mesh's visible vertices, through the observation's camera
  (:func:`vvtbench.observe._sample_extracted`, :func:`vvtbench.modes.sampling.sample_field`:
  the four pixels around each position), and the extraction's scores, over the pixels where
  the sample's true image modes are finite (the object's footprint,
  :func:`vvtbench.scoring.extraction.score_sample_extraction`);
* the observation of several extractions (a group of videos merged, or views joined): every
  pixel (the shapes' MAC when merging; each view's phasors project the whole frame's
  brightness change on the shapes, :func:`vvtbench.modes.joint.modal_phasors`).

So an extraction whose every reader is of the first kind (and has run) keeps its shapes
only inside the *box*: the rows and columns that hold the footprint and the four pixels
around every vertex of each reader's inference mesh projected through that reader's camera
(read from the observation's ``problem.npz`` and ``problem.json``), widened by
:data:`MARGIN_PX` and clipped to the frame. Any other extraction (a reader of the second
kind, a reader that failed or has not run) keeps the whole frame, unless asked to cut joined
views too (``kept="footprint"``, lossy: their phasors then miss the frame outside the box).
Either way the arrays are written compressed into :data:`COMPACT_NAME` with the box, and
:func:`restore` writes a ``modes.npz`` of the full frame back, NaN outside the box, which
every reader of the first kind reads exactly as the original: the observation's bytes and
every score are the same (``tests/test_shards.py``).
"""

from __future__ import annotations

import json
import os
import shutil
import uuid
from pathlib import Path

import numpy as np

from ..io.files import write_json, write_npz
from ..samples.reader import sha256_file

__all__ = ["COMPACT_NAME", "MARGIN_PX", "MODES_KEPT", "bilinear_box", "compact_arrays",
           "expand_arrays", "extraction_box", "mask_box", "observation_box", "restore",
           "truth_box", "union_box", "write_compact"]

#: the compact arrays of an extraction in a shard folder (in place of ``modes.npz``)
COMPACT_NAME = "modes.box.npz"
#: pixels added on each side of the box (a margin for a projection's last bits)
MARGIN_PX = 2
Box = tuple[int, int, int, int]  # rows [r0, r1), columns [c0, c1)


# --------------------------------------------------------------------------- boxes

def bilinear_box(uv: np.ndarray, height: int, width: int) -> Box | None:
    """The rows and columns :func:`vvtbench.modes.sampling.sample_field` reads to sample a
    ``(height, width)`` field at the positions ``uv`` ``(n, 2)`` (``(u, v)`` = (column, row),
    clamped to the frame as it clamps them); None when a position is not finite."""
    p = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    if p.size == 0:
        return None
    if not np.isfinite(p).all():
        return None
    u = np.clip(p[:, 0], 0.0, width - 1.0)
    v = np.clip(p[:, 1], 0.0, height - 1.0)
    j0 = np.minimum(np.floor(u).astype(np.intp), max(width - 2, 0))
    i0 = np.minimum(np.floor(v).astype(np.intp), max(height - 2, 0))
    j1 = np.minimum(j0 + 1, width - 1)
    i1 = np.minimum(i0 + 1, height - 1)
    return int(i0.min()), int(i1.max()) + 1, int(j0.min()), int(j1.max()) + 1


def mask_box(mask: np.ndarray) -> Box | None:
    """The rows and columns holding the True pixels of a 2-D ``mask`` (None: none)."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if rows.size == 0:
        return None
    return int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1


def union_box(boxes: list[Box], height: int, width: int, margin: int = MARGIN_PX) -> Box:
    """The smallest box holding ``boxes``, widened by ``margin`` and clipped to the frame."""
    r0 = min(b[0] for b in boxes) - margin
    r1 = max(b[1] for b in boxes) + margin
    c0 = min(b[2] for b in boxes) - margin
    c1 = max(b[3] for b in boxes) + margin
    return max(r0, 0), min(r1, height), max(c0, 0), min(c1, width)


def observation_box(folder: Path, height: int, width: int,
                    view: int | None = None) -> Box | None:
    """The pixels an observation sampled an extraction's shapes at: every vertex of its
    inference mesh (``problem.npz`` ``points``, over ``meta.geometry_scale``) through its
    camera (``problem.json`` ``meta.camera``; ``meta.cameras[view]`` for a view of joined
    views), a superset of the visible ones; None when the folder does not say (then the
    whole frame is kept)."""
    from ..render.camera import Camera

    try:
        meta = json.loads((folder / "problem.json").read_text())["meta"]
        camera = Camera.from_dict(meta["camera"] if view is None else meta["cameras"][view])
        scale = np.asarray(meta.get("geometry_scale", [1.0, 1.0, 1.0]), dtype=np.float64)
        with np.load(folder / "problem.npz", allow_pickle=False) as z:
            points = np.asarray(z["points"], dtype=np.float64)
    except (OSError, ValueError, KeyError, TypeError, IndexError):
        return None
    if points.ndim != 2 or points.shape[1] != 3 or (int(camera.height), int(camera.width)) != (
            height, width):
        return None
    return bilinear_box(camera.project(points / scale), height, width)


def truth_box(sample: Path, view: int = 0) -> Box | None:
    """The footprint the extraction scores read: the pixels where every true image mode of the
    sample's view (``image/modes``) is finite; None for a sample without dense image modes."""
    from ..samples.reader import open_sample

    try:
        s = open_sample(sample, verify=False)
        s = s.view(view) if view else s
        if "image/modes" not in s:
            return None
        modes = np.asarray(s["image/modes"])
    except (OSError, ValueError, KeyError, IndexError):
        return None
    if modes.ndim != 4:
        return None
    return mask_box(np.all(np.isfinite(modes), axis=(0, 3)))


#: how a shard keeps extracted mode shapes: ``exact`` (the default) cuts them to the box only
#: where no score changes; ``footprint`` cuts those of joined views too (lossy: docs/suites.md)
MODES_KEPT = ("exact", "footprint")


def extraction_box(cache: Path, tasks: dict, key: str, statuses: dict,
                   image_shape: tuple[int, int], kept: str = "exact") -> tuple[Box | None, str]:
    """(the box an extraction's shapes are kept in, why): None (the whole frame) unless every
    task reading the extraction is an observation that ran (its problem folder in
    ``cache``, its camera and mesh stated) and reads the extraction alone -- or, with
    ``kept="footprint"``, joins it with the other views of its sample."""
    if kept not in MODES_KEPT:
        raise ValueError(f"kept={kept!r}; allowed: {', '.join(MODES_KEPT)}")
    height, width = image_shape
    view = int(tasks[key].payload.get("view", 0) or 0) if key in tasks else 0
    readers = [t for t in tasks.values() if key in t.deps]
    if not readers:
        return None, "no task reads it"
    boxes: list[Box] = []
    joined = False
    for t in readers:
        extracted = [d for d in t.deps if d in tasks and tasks[d].stage == "extract"]
        views = int((t.payload.get("inference") or {}).get("views", 1) or 1)
        if t.stage != "observe":
            return None, f"{t.key} is not an observation"
        if views > 1 and kept != "footprint":
            return None, f"{t.key} joins views: it reads every pixel"
        if views == 1 and extracted != [key]:
            return None, f"{t.key} merges videos: it reads every pixel"
        if statuses.get(t.key, {}).get("status") != "ok":
            return None, f"{t.key} has not run"
        seen = observation_box(cache / t.key, height, width, view if views > 1 else None)
        if seen is None:
            return None, f"{t.key} does not state its camera and mesh"
        boxes.append(seen)
        joined |= views > 1
        footprint = truth_box(cache / t.deps[0] / "sample", view)
        if footprint is not None:
            boxes.append(footprint)
    if joined:
        return union_box(boxes, height, width), "joined views cut to the footprint (lossy)"
    return union_box(boxes, height, width), "read only there"


# --------------------------------------------------------------------------- arrays

def compact_arrays(arrays: dict[str, np.ndarray], box: Box | None) -> dict[str, np.ndarray]:
    """The arrays of a ``modes.npz`` with ``shapes`` and ``confidence`` cut to ``box`` (None:
    the whole frame), plus ``box`` (int64 ``[r0, r1, c0, c1]``) and ``image_shape`` (int64
    ``[H, W]``)."""
    shapes = np.asarray(arrays["shapes"])
    height, width = shapes.shape[1:3]
    r0, r1, c0, c1 = box if box is not None else (0, height, 0, width)
    out = dict(arrays)
    out["shapes"] = np.ascontiguousarray(shapes[:, r0:r1, c0:c1])
    if "confidence" in arrays:
        out["confidence"] = np.ascontiguousarray(np.asarray(arrays["confidence"])[r0:r1,
                                                                                 c0:c1])
    out["box"] = np.array([r0, r1, c0, c1], dtype=np.int64)
    out["image_shape"] = np.array([height, width], dtype=np.int64)
    return out


def expand_arrays(arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The inverse of :func:`compact_arrays`: ``shapes`` and ``confidence`` of the full frame,
    NaN outside the box (``box`` and ``image_shape`` dropped, the order kept)."""
    r0, r1, c0, c1 = (int(x) for x in arrays["box"])
    height, width = (int(x) for x in arrays["image_shape"])
    out = {}
    for name, a in arrays.items():
        if name in ("box", "image_shape"):
            continue
        if name == "shapes":
            full = np.full((a.shape[0], height, width, *a.shape[3:]), np.nan, dtype=a.dtype)
            full[:, r0:r1, c0:c1] = a
            a = full
        elif name == "confidence":
            full = np.full((height, width), np.nan, dtype=a.dtype)
            full[r0:r1, c0:c1] = a
            a = full
        out[name] = a
    return out


def _read_npz(path: Path) -> dict[str, np.ndarray]:
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


# --------------------------------------------------------------------------- folders

def write_compact(src: Path, dest: Path, info: dict, box: Box | None) -> dict[str, str]:
    """Write an extraction's folder ``src`` (its ``task.json`` read as ``info``) into
    ``dest``: every file as it is but ``modes.npz``, written as :data:`COMPACT_NAME` cut to
    ``box`` (a box recorded by an earlier :func:`restore` wins: outside it the shapes are
    NaN). Each file is checked against the sha256 ``info`` records first. Returns
    ``{name: sha256}`` of what was written."""
    files = info.get("files") or {}
    dest.mkdir(parents=True, exist_ok=True)
    out = {}
    for name in [*sorted(files), "task.json"]:
        f = src / name
        digest = sha256_file(f)
        if name in files and files[name] != digest:
            raise OSError(f"{f}: sha256 mismatch with its task.json (edited or truncated)")
        if name == "modes.npz":
            recorded = (info.get("compact") or {}).get("box")
            use = tuple(int(x) for x in recorded) if recorded else box
            write_npz(dest / COMPACT_NAME, compact_arrays(_read_npz(f), use))
            out[COMPACT_NAME] = sha256_file(dest / COMPACT_NAME)
            continue
        (dest / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(f, dest / name)
        out[name] = digest
    return out


def restore(src: Path, dest: Path) -> None:
    """Put a shard's extraction folder ``src`` into the cache at ``dest`` (built beside it and
    renamed into place): :data:`COMPACT_NAME` written back as ``modes.npz`` of the full frame
    (:func:`expand_arrays`), its sha256 recorded in the ``task.json`` with the box and the
    sha256 the extraction's own ``modes.npz`` had (``compact``). A folder without
    :data:`COMPACT_NAME` is copied as it is."""
    tmp = dest.parent / f"{dest.name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    try:
        shutil.copytree(src, tmp, ignore=shutil.ignore_patterns(COMPACT_NAME))
        if (src / COMPACT_NAME).is_file():
            arrays = _read_npz(src / COMPACT_NAME)
            write_npz(tmp / "modes.npz", expand_arrays(arrays), compressed=False)
            info = json.loads((src / "task.json").read_text())
            files = dict(info.get("files") or {})
            before = info.get("compact") or {"box": [int(x) for x in arrays["box"]],
                                             "modes_npz_sha256": files.get("modes.npz")}
            files["modes.npz"] = sha256_file(tmp / "modes.npz")
            write_json(tmp / "task.json", {**info, "files": files, "compact": before})
        if dest.exists():
            trash = dest.parent / f"{dest.name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}.stale"
            os.replace(dest, trash)
            shutil.rmtree(trash, ignore_errors=True)
        os.replace(tmp, dest)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
