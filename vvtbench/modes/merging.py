"""Merging of modes identified in several videos of the same view.

* :func:`merge_modes` (result :class:`MergedModes`): group duplicates by frequency and MAC,
  then average their sign-aligned shapes.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .mac import mac

__all__ = ["MergedModes", "merge_modes"]


@dataclass(frozen=True)
class MergedModes:
    """Result of :func:`merge_modes`, sorted by frequency.

    Attributes
    ----------
    frequencies_hz, damping : ndarray
        ``(k,)`` means over the merged duplicates (``nanmean`` for damping).
    shapes : ndarray
        ``(k, H, W, 2)`` sign-aligned, weight-averaged, unit-norm shapes.
    n_sources : ndarray
        ``(k,)`` number of input sets in which the mode was found.
    members : list of list of tuple
        ``(set index, mode index)`` of the merged inputs.
    """

    frequencies_hz: NDArray[np.float64]
    damping: NDArray[np.float64]
    shapes: NDArray[np.float32]
    n_sources: NDArray[np.int64]
    members: list[list[tuple[int, int]]]


def merge_modes(
    frequencies: Sequence[ArrayLike],
    shapes: Sequence[ArrayLike],
    damping: Sequence[ArrayLike] | None = None,
    weights: Sequence[ArrayLike] | None = None,
    *,
    freq_tol: float = 0.02,
    min_mac: float = 0.8,
) -> MergedModes:
    """Merge modes identified in several videos of the same view.

    Modes are visited by decreasing weight (e.g. amplitude); each joins the existing group
    with the highest MAC among those within ``freq_tol`` (relative) in frequency, reaching
    ``min_mac`` and holding no mode of the same set yet; otherwise it starts a new group.
    Duplicates are averaged after aligning their sign with the group's first (strongest)
    member.

    Parameters
    ----------
    frequencies : sequence of array_like
        Per set ``(k_s,)`` frequencies (Hz).
    shapes : sequence of array_like
        Per set ``(k_s, H, W, 2)`` real shapes; all sets must share ``(H, W)``.
    damping : sequence of array_like, optional
        Per set ``(k_s,)`` damping ratios.
    weights : sequence of array_like, optional
        Per set ``(k_s,)`` positive weights for ordering and averaging (default 1).
    freq_tol : float, default 0.02
        Relative frequency tolerance ``|f - f_group| <= freq_tol * f_group``.
    min_mac : float, default 0.8
        Minimal MAC for a match.

    Returns
    -------
    MergedModes
    """
    n_sets = len(frequencies)
    if n_sets == 0 or len(shapes) != n_sets:
        raise ValueError("need the same, non-zero number of frequency and shape sets")
    fs = [np.atleast_1d(np.asarray(f, dtype=np.float64)) for f in frequencies]
    ss = [np.asarray(s, dtype=np.float64) for s in shapes]
    ds = (
        [np.full(f.shape, np.nan) for f in fs]
        if damping is None
        else [np.atleast_1d(np.asarray(d, dtype=np.float64)) for d in damping]
    )
    ws = (
        [np.ones(f.shape) for f in fs]
        if weights is None
        else [np.atleast_1d(np.asarray(w, dtype=np.float64)) for w in weights]
    )
    hw = None
    for i, (f, s, d, w) in enumerate(zip(fs, ss, ds, ws, strict=True)):
        if s.ndim != 4 or s.shape[0] != f.size or s.shape[-1] != 2:
            raise ValueError(
                f"set {i}: shapes must be (k, H, W, 2) with k = {f.size}, got {s.shape}"
            )
        if d.shape != f.shape or w.shape != f.shape:
            raise ValueError(f"set {i}: damping/weights must have shape {f.shape}")
        if hw is None:
            hw = s.shape[1:3]
        elif s.shape[1:3] != hw:
            raise ValueError(f"set {i}: image size {s.shape[1:3]} differs from set 0's {hw}")
    items = [(i, j) for i in range(n_sets) for j in range(fs[i].size)]
    items.sort(key=lambda ij: (-ws[ij[0]][ij[1]], ij))
    groups: list[dict] = []
    for i, j in items:
        f, s = fs[i][j], ss[i][j]
        best, best_mac = None, min_mac
        for g in groups:
            if abs(f - g["f0"]) > freq_tol * g["f0"] or i in g["sets"]:
                continue
            m = mac(g["ref"], s)
            if m >= best_mac:
                best, best_mac = g, m
        if best is None:
            best = {"f0": f, "ref": s, "sets": set(), "members": [], "acc": np.zeros_like(s)}
            groups.append(best)
        sign = 1.0 if float(np.vdot(best["ref"], s)) >= 0 else -1.0
        n = np.linalg.norm(s)
        best["acc"] += ws[i][j] * sign * (s / n if n > 0 else s)
        best["sets"].add(i)
        best["members"].append((i, j))
    groups.sort(key=lambda g: float(np.mean([fs[i][j] for i, j in g["members"]])))
    freq = np.array([np.average([fs[i][j] for i, j in g["members"]]) for g in groups])
    damp = []
    for g in groups:
        v = np.array([ds[i][j] for i, j in g["members"]])
        damp.append(float(np.mean(v[np.isfinite(v)])) if np.isfinite(v).any() else np.nan)
    shp = np.empty((len(groups), *ss[0].shape[1:]), np.float32)
    for k, g in enumerate(groups):
        n = np.linalg.norm(g["acc"])
        shp[k] = g["acc"] / n if n > 0 else g["acc"]
    return MergedModes(
        frequencies_hz=freq,
        damping=np.array(damp, dtype=np.float64),
        shapes=shp,
        n_sources=np.array([len(g["sets"]) for g in groups], dtype=np.int64),
        members=[sorted(g["members"]) for g in groups],
    )
