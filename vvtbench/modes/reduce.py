"""Reduced channels of a displacement record: block averages, streamed.

A record is ``T`` frames of ``H x W`` pixels with two components: far too many channels for a
pole-based identifier, and each pixel's motion is noisy.  A mode shape is smooth, so the
weighted average of each ``block x block`` tile and component keeps it while the noise of the
tile's pixels averages down.  :func:`block_channels` reads the record by column blocks (as the
spectrum does, :class:`.spectrum.DisplacementStore`), so a record longer than memory is reduced
in bounded memory: the result is ``(T, m)`` with ``m = 2 ceil(H / block) ceil(W / block)`` at
most (tiles without weight are left out), a few hundred channels for a 128² working grid.

:func:`decimate_frames` averages groups of frames.  For a free decay ``sum_k r_k z_k^t`` the
average of non-overlapping groups of ``q`` frames is exactly ``sum_k r_k (1 + z_k + ... +
z_k^(q-1)) / q (z_k^q)^j``: a free decay again, with the poles ``z_k^q``, from the first group on,
so no filter transient is cut off.  Each channel is finally scaled by its noise level
(:func:`channel_noise`, the median of its periodogram), so that the identifier's SVD ranks
directions by signal-to-noise rather than by raw motion.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import sparse

from .spectrum import DisplacementStore, _as_store

__all__ = ["Channels", "block_channels", "channel_noise", "decimate_frames"]


@dataclass
class Channels:
    """Reduced channels of a record.

    Attributes
    ----------
    data : ndarray
        ``(T, m)`` float64 channel time series (px, weighted tile averages).
    tiles : ndarray
        ``(m, 3)`` int: tile row, tile column and component of each channel.
    block : int
        Tile size (working-grid pixels).
    weight : ndarray
        ``(m,)`` total pixel weight of each channel's tile.
    """

    data: NDArray[np.float64]
    tiles: NDArray[np.int64]
    block: int
    weight: NDArray[np.float64]

    @property
    def n_channels(self) -> int:
        """``m``."""
        return int(self.data.shape[1])


def _tile_map(shape: tuple[int, int], block: int, w: NDArray[np.float64]
              ) -> tuple[sparse.csr_matrix, NDArray[np.int64], NDArray[np.float64]]:
    """``(H W 2, m)`` weighted averaging matrix of the tiles, their ``(row, col, comp)`` and
    weights."""
    H, W = shape
    ty, tx = -(-H // block), -(-W // block)
    iy, ix = np.divmod(np.arange(H * W), W)
    tile = (iy // block) * tx + (ix // block)
    tw = np.bincount(tile, weights=w.reshape(-1), minlength=ty * tx)
    keep = np.flatnonzero(tw > 0)
    index = np.full(ty * tx, -1)
    index[keep] = np.arange(keep.size)
    rows, cols, vals = [], [], []
    for c in range(2):
        pix = np.flatnonzero(index[tile] >= 0)
        rows.append(pix * 2 + c)
        cols.append(index[tile[pix]] * 2 + c)
        vals.append(w.reshape(-1)[pix] / tw[tile[pix]])
    M = sparse.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                          shape=(H * W * 2, keep.size * 2))
    ky, kx = np.divmod(keep, tx)
    tiles = np.stack([np.repeat(ky, 2), np.repeat(kx, 2), np.tile([0, 1], keep.size)], -1)
    return M, tiles.astype(np.int64), np.repeat(tw[keep], 2)


def block_channels(disp: DisplacementStore | ArrayLike, *, weights: ArrayLike | None = None,
                   block: int = 8, block_bytes: int = 64 << 20) -> Channels:
    """Weighted ``block x block`` tile averages of each displacement component.

    Parameters
    ----------
    disp : DisplacementStore or array_like
        ``(T, H, W, 2)`` displacements (px).
    weights : array_like, optional
        ``(H, W)`` non-negative pixel weights (e.g. inverse noise power); default uniform.
    block : int, default 8
        Tile size in pixels.
    block_bytes : int
        Working memory per column block read from the store.

    Returns
    -------
    Channels

    Examples
    --------
    >>> d = np.zeros((3, 4, 4, 2)); d[:, :2, :2, 0] = 1.0
    >>> ch = block_channels(d, block=2)
    >>> ch.data.shape, ch.data[0].tolist()[:4]
    ((3, 8), [1.0, 0.0, 0.0, 0.0])
    """
    if isinstance(block, bool) or int(block) != block or block < 1:
        raise ValueError(f"block must be an integer >= 1, got {block!r}")
    store = _as_store(disp)
    H, W = store.frame_shape[:2]
    w = np.ones((H, W)) if weights is None else np.asarray(weights, dtype=np.float64)
    if w.shape != (H, W):
        raise ValueError(f"weights must have shape {(H, W)}, got {w.shape}")
    if not np.all(np.isfinite(w)) or np.any(w < 0):
        raise ValueError("weights must be finite and >= 0")
    M, tiles, tw = _tile_map((H, W), int(block), w)
    out = np.zeros((store.n_frames, M.shape[1]))
    P = store.block_size(block_bytes)
    C = store.n_columns
    for c0 in range(0, C, P):
        c1 = min(c0 + P, C)
        x = np.asarray(store.column_block(c0, c1), dtype=np.float64)
        out += (M[c0:c1].T @ x.T).T
    return Channels(data=out, tiles=tiles, block=int(block), weight=tw)


def decimate_frames(y: ArrayLike, factor: int) -> NDArray[np.float64]:
    """Means of consecutive groups of ``factor`` frames (a trailing partial group dropped).

    >>> decimate_frames(np.arange(7.0)[:, None], 3).ravel().tolist()
    [1.0, 4.0]
    """
    a = np.asarray(y, dtype=np.float64)
    q = int(factor)
    if q < 1:
        raise ValueError(f"factor must be >= 1, got {factor!r}")
    n = a.shape[0] // q
    return a[: n * q].reshape(n, q, *a.shape[1:]).mean(axis=1)


def channel_noise(y: ArrayLike, *, min_bin: int = 3) -> NDArray[np.float64]:
    """Noise standard deviation of each channel: the median of its periodogram above
    ``min_bin`` (lines cover few bins, so the median is the broadband level), as the standard
    deviation of white noise with that periodogram (``median / ln 2`` is the mean of an
    exponential law).

    >>> rng = np.random.default_rng(0)
    >>> y = rng.standard_normal((4096, 2)) * [1.0, 0.1]
    >>> np.round(channel_noise(y), 1).tolist()
    [1.0, 0.1]
    """
    a = np.asarray(y, dtype=np.float64)
    a = a - a.mean(axis=0)
    T = a.shape[0]
    P = np.abs(np.fft.rfft(a, axis=0)) ** 2 / T
    P = P[min(max(1, int(min_bin)), max(P.shape[0] - 2, 1)):-1]
    return np.sqrt(np.median(P, axis=0) / np.log(2.0))
