"""Streaming temporal spectrum of displacement fields.

Displacement batches ``(B, H, W, 2)`` (e.g. from :meth:`PhaseMotion.iter_displacements`) are
appended to a :class:`DisplacementStore`, which keeps them in RAM while they fit in a memory
budget and otherwise spills them to a raw float32 file in a temporary directory (batch by
batch, each batch cut into column tiles so that pixel blocks read back cheaply).  Spectra
are then computed by *pixel blocks*: for a block of ``P`` columns of the ``(T, H*W*2)``
matrix an ``rfft`` over time of the ``(T, P)`` slice, so peak RAM is ``O(T * P)`` whatever
the video length.

Conventions
-----------
* Frequency axis: ``numpy.fft.rfftfreq(T, 1 / fps)`` in Hz, ``F = T // 2 + 1`` bins,
  bin spacing ``fps / T``.
* DFT without normalisation, ``X_l = sum_t d_t exp(-2 pi i l t / T)``: a sinusoid of amplitude
  ``A`` px on bin ``l`` gives ``|X_l| = A T / 2``.
* Optional taper ``window="hann"``: ``d_t`` is multiplied by the periodic Hann window
  ``w_t = (1 - cos(2 pi t / T)) / 2`` (after detrending), so ``|X_l| = A sum(w) / 2 = A T / 4``
  for a sinusoid on bin ``l``.  Its sidelobes fall as ``1 / k**3`` (rectangular: ``1 / k``),
  which keeps the leakage of strong, undamped modes from burying weaker ones.
* Motion power spectrum (paper Sec. 4.1): ``S_l = sum_p w_p (|DX_l(p)|**2 + |DY_l(p)|**2)``
  over pixels ``p`` with optional weights ``w_p`` (default 1), in px**2 (unnormalised DFT).
"""

from __future__ import annotations

import math
import os
import shutil
import tempfile
from collections.abc import Iterable, Iterator, Sequence
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "DisplacementStore",
    "Detrend",
    "Window",
    "block_columns",
    "bin_fields",
    "frequency_axis",
    "hann_from_unwindowed",
    "motion_power_spectrum",
    "pixel_noise_power",
    "window_gain",
    "window_weights",
]

Detrend = Literal["mean", "linear", "none"]
Window = Literal["hann", "none"]


def window_weights(n_frames: int, window: Window) -> NDArray[np.float64] | None:
    """The temporal taper ``(T,)`` (periodic Hann) or ``None`` for ``"none"``."""
    if window == "none":
        return None
    if window != "hann":
        raise ValueError(f"window must be 'hann' or 'none', got {window!r}")
    t = np.arange(int(n_frames), dtype=np.float64)
    return 0.5 - 0.5 * np.cos(2.0 * np.pi * t / max(int(n_frames), 1))


def window_gain(n_frames: int, window: Window) -> float:
    """``sum(w_t)``: a sinusoid of amplitude ``A`` on a bin gives ``|X_l| = A * gain / 2``."""
    w = window_weights(n_frames, window)
    return float(n_frames) if w is None else float(w.sum())


def hann_from_unwindowed(X: NDArray[np.complex128], n_frames: int) -> NDArray[np.complex128]:
    """The ``rfft`` (axis 0) of a record times the periodic Hann window, from the ``rfft`` ``X``
    of the record itself: ``0.5 X_l - 0.25 (X_{l-1} + X_{l+1})``, the bins beyond either end
    taken from the conjugate-symmetric full DFT.  Exact, so one transform gives both spectra.

    >>> x = np.random.default_rng(0).standard_normal((10, 3))
    >>> w = window_weights(10, "hann")[:, None]
    >>> bool(np.allclose(hann_from_unwindowed(np.fft.rfft(x, axis=0), 10),
    ...                  np.fft.rfft(x * w, axis=0)))
    True
    """
    T = int(n_frames)
    F = X.shape[0]
    if F != T // 2 + 1:
        raise ValueError(f"{F} rfft bins do not belong to {T} frames")
    below = np.empty_like(X)
    above = np.empty_like(X)
    below[1:] = X[:-1]
    below[0] = X[1].conj() if F > 1 else X[0].conj()
    above[:-1] = X[1:]
    above[-1] = X[-2].conj() if T % 2 == 0 and F > 1 else X[-1].conj()
    below += above
    below *= -0.25
    below += 0.5 * X
    return below


DEFAULT_BUDGET = 1 << 30  # 1 GiB


def frequency_axis(n_frames: int, fps: float) -> NDArray[np.float64]:
    """Frequencies (Hz) of the ``rfft`` bins of ``n_frames`` samples at ``fps``."""
    if fps <= 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    return np.fft.rfftfreq(int(n_frames), 1.0 / float(fps))


class DisplacementStore:
    """Append-only store of displacement fields ``(T, H, W, 2)``, RAM or disk backed.

    Parameters
    ----------
    memory_budget : int, default 1 GiB
        Bytes of displacement data kept in RAM; once exceeded all data move to a raw float32
        file (``displacements.f32``) in a temporary directory and later batches are written
        there directly.  ``0`` always uses the disk.
    tmpdir : str, optional
        Parent directory of the temporary directory (default: the system's).
    tile_columns : int, default 2048
        Disk layout: every appended batch ``(B, C)`` (``C = H*W*2`` columns) is written as
        consecutive contiguous tiles ``(B, tile_columns)``, so that a pixel block over all
        frames is read with one large ``pread`` per batch (no memory map: the page cache is
        not charged to the process' RSS).

    Notes
    -----
    Use as a context manager (or call :meth:`close`) to delete the temporary file.
    """

    def __init__(
        self,
        memory_budget: int = DEFAULT_BUDGET,
        tmpdir: str | None = None,
        tile_columns: int = 2048,
    ) -> None:
        if memory_budget < 0:
            raise ValueError(f"memory_budget must be >= 0, got {memory_budget}")
        if tile_columns < 1:
            raise ValueError(f"tile_columns must be >= 1, got {tile_columns}")
        self.memory_budget = int(memory_budget)
        self.tmpdir = tmpdir
        self.tile_columns = int(tile_columns)
        self.frame_shape: tuple[int, int, int] | None = None
        self.n_frames = 0
        self._ram: list[NDArray[np.float32]] = []
        self._ram_bytes = 0
        self._dir: str | None = None
        self._path: str | None = None
        self._fd: int | None = None
        self._chunks: list[tuple[int, int]] = []  # (n_frames, byte offset) per written batch
        self._offset = 0

    # -------------------------------------------------------------- context management
    def __enter__(self) -> DisplacementStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Release the data and delete the temporary directory (idempotent)."""
        self._ram = []
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
        if self._dir is not None:
            shutil.rmtree(self._dir, ignore_errors=True)
            self._dir = None

    def __del__(self) -> None:  # pragma: no cover - best effort
        try:
            self.close()
        except Exception:
            pass

    @property
    def on_disk(self) -> bool:
        """Whether the data live in the temporary file."""
        return self._path is not None

    @property
    def path(self) -> str | None:
        """Path of the raw float32 file, if spilled."""
        return self._path

    @property
    def n_columns(self) -> int:
        """``H * W * 2``."""
        if self.frame_shape is None:
            return 0
        return int(np.prod(self.frame_shape))

    # -------------------------------------------------------------- writing
    def append(self, batch: ArrayLike) -> None:
        """Append a ``(B, H, W, 2)`` (or ``(H, W, 2)``) batch of displacements."""
        a = np.asarray(batch, dtype=np.float32)
        if a.ndim == 3:
            a = a[None]
        if a.ndim != 4 or a.shape[-1] != 2:
            raise ValueError(f"displacement batches must be (B, H, W, 2), got {a.shape}")
        if self.frame_shape is None:
            self.frame_shape = a.shape[1:]
        elif a.shape[1:] != self.frame_shape:
            raise ValueError(f"batch frame shape {a.shape[1:]} != first batch's {self.frame_shape}")
        if a.shape[0] == 0:
            return
        self.n_frames += a.shape[0]
        if self._fd is None and self._ram_bytes + a.nbytes <= self.memory_budget:
            self._ram.append(np.ascontiguousarray(a))
            self._ram_bytes += a.nbytes
            return
        if self._fd is None:
            self._spill()
        self._write(a)

    def extend(self, batches: Iterable[ArrayLike]) -> None:
        """Append every batch of an iterable."""
        for b in batches:
            self.append(b)

    def _spill(self) -> None:
        self._dir = tempfile.mkdtemp(prefix="vvtbench-disp-", dir=self.tmpdir)
        self._path = os.path.join(self._dir, "displacements.f32")
        self._fd = os.open(self._path, os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o600)
        ram, self._ram, self._ram_bytes = self._ram, [], 0
        for a in ram:
            self._write(a)

    def _write(self, a: NDArray[np.float32]) -> None:
        m = a.reshape(a.shape[0], -1)
        B, C = m.shape
        self._chunks.append((B, self._offset))
        for c0 in range(0, C, self.tile_columns):
            tile = np.ascontiguousarray(m[:, c0 : c0 + self.tile_columns])
            os.pwrite(self._fd, tile.data, self._offset)
            self._offset += tile.nbytes

    # -------------------------------------------------------------- reading
    def column_block(self, start: int, stop: int) -> NDArray[np.float32]:
        """Columns ``start:stop`` of the ``(T, H*W*2)`` matrix over all frames, float32.

        On disk, ``start`` must be a multiple of ``tile_columns``.
        """
        if self.frame_shape is None:
            raise ValueError("the store is empty")
        C = self.n_columns
        stop = min(stop, C)
        if self._fd is None:
            return np.concatenate([a.reshape(a.shape[0], -1)[:, start:stop] for a in self._ram])
        tc = self.tile_columns
        if start % tc:
            raise ValueError(f"start={start} is not a multiple of tile_columns={tc}")
        out = np.empty((self.n_frames, stop - start), np.float32)
        t0 = 0
        for B, off in self._chunks:
            for c0 in range(start, stop, tc):
                w = min(tc, C - c0)
                buf = out[t0 : t0 + B, c0 - start : c0 - start + w]
                nbytes = B * w * 4
                raw = os.pread(self._fd, nbytes, off + B * c0 * 4)
                if len(raw) != nbytes:
                    raise OSError(f"short read from {self._path}")
                buf[...] = np.frombuffer(raw, np.float32).reshape(B, w)
            t0 += B
        return out

    def block_size(self, block_bytes: int) -> int:
        """Columns per pixel block for :func:`block_columns`, rounded to whole tiles."""
        P = block_columns(self.n_frames, block_bytes, self.n_columns)
        if self.on_disk:
            P = max(self.tile_columns, P // self.tile_columns * self.tile_columns)
        return P

    def array(self) -> NDArray[np.float32]:
        """All displacements as one ``(T, H, W, 2)`` float32 array (loads it into RAM)."""
        if self.frame_shape is None:
            raise ValueError("the store is empty")
        if self._fd is None:
            if len(self._ram) > 1:
                self._ram = [np.concatenate(self._ram, axis=0)]
            return self._ram[0]
        return self.column_block(0, self.n_columns).reshape(self.n_frames, *self.frame_shape)


def block_columns(n_frames: int, block_bytes: int, n_columns: int) -> int:
    """Columns per pixel block so that a ``(T, P)`` block and its spectrum fit ``block_bytes``.

    Counts the float64 copy (8 B), its complex128 ``rfft`` (``~8 B``) and the power (``~4 B``)
    per sample.
    """
    per_col = max(1, int(n_frames)) * 20
    return int(min(max(1, n_columns), max(64, block_bytes // per_col)))


def _detrend(x: NDArray[np.float64], detrend: Detrend) -> NDArray[np.float64]:
    """Remove the temporal mean (or best line) of every column of ``x`` ``(T, P)`` in place."""
    if detrend == "none":
        return x
    x -= x.mean(axis=0, keepdims=True)
    if detrend == "linear":
        T = x.shape[0]
        t = np.arange(T, dtype=np.float64) - (T - 1) / 2.0
        denom = float(t @ t)
        if denom > 0:
            slope = (t @ x) / denom
            x -= t[:, None] * slope[None, :]
    return x


def _check_detrend(detrend: str) -> Detrend:
    if detrend not in ("mean", "linear", "none"):
        raise ValueError(f"detrend must be 'mean', 'linear' or 'none', got {detrend!r}")
    return detrend  # type: ignore[return-value]


def _column_weights(
    weights: ArrayLike | None, frame_shape: tuple[int, ...]
) -> NDArray[np.float64] | None:
    """Per-pixel weights ``(H, W)`` expanded to the ``H*W*2`` columns."""
    if weights is None:
        return None
    w = np.asarray(weights, dtype=np.float64)
    if w.shape != tuple(frame_shape[:2]):
        raise ValueError(f"weights must have shape {tuple(frame_shape[:2])}, got {w.shape}")
    if np.any(~np.isfinite(w)) or np.any(w < 0):
        raise ValueError("weights must be finite and >= 0")
    return np.repeat(w.ravel(), 2)


def _as_store(disp: DisplacementStore | ArrayLike) -> DisplacementStore:
    if isinstance(disp, DisplacementStore):
        if disp.frame_shape is None:
            raise ValueError("the displacement store is empty")
        return disp
    a = np.asarray(disp)
    if a.ndim != 4 or a.shape[-1] != 2:
        raise ValueError(f"displacements must be (T, H, W, 2), got {a.shape}")
    store = DisplacementStore(memory_budget=max(a.nbytes, 1))
    store.frame_shape = a.shape[1:]
    store.n_frames = a.shape[0]
    store._ram = [a]
    return store


def _iter_blocks(
    store: DisplacementStore, block_bytes: int, detrend: Detrend, window: Window = "none"
) -> Iterator[tuple[slice, NDArray[np.float64]]]:
    P = store.block_size(block_bytes)
    C = store.n_columns
    taper = window_weights(store.n_frames, window)
    for c0 in range(0, C, P):
        sl = slice(c0, min(c0 + P, C))
        x = np.asarray(store.column_block(sl.start, sl.stop), dtype=np.float64)
        x = _detrend(x, detrend)
        if taper is not None:
            x *= taper[:, None]
        yield sl, x


def motion_power_spectrum(
    disp: DisplacementStore | ArrayLike,
    fps: float,
    *,
    weights: ArrayLike | None = None,
    detrend: Detrend = "mean",
    window: Window = "none",
    block_bytes: int = 64 << 20,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Motion power spectrum ``S_l = sum_p w_p (|DX_l|**2 + |DY_l|**2)``, by pixel blocks.

    Parameters
    ----------
    disp : DisplacementStore or array_like
        ``(T, H, W, 2)`` displacements in px (``[..., 0] = dx``, ``[..., 1] = dy``).
    fps : float
        Frame rate (Hz).
    weights : array_like, optional
        ``(H, W)`` non-negative pixel weights (e.g. ``PhaseMotion.confidence``); default 1.
    detrend : {"mean", "linear", "none"}, default "mean"
        Per-pixel removal of the temporal mean (or least-squares line) before the FFT.
    window : {"none", "hann"}, default "none"
        Temporal taper applied after detrending (see module notes).
    block_bytes : int, default 64 MiB
        Working memory per pixel block.

    Returns
    -------
    freqs : ndarray
        ``(T//2 + 1,)`` Hz.
    power : ndarray
        ``(T//2 + 1,)`` float64, px**2 (unnormalised DFT, see module notes).
    """
    detrend = _check_detrend(detrend)
    store = _as_store(disp)
    fshape, T = store.frame_shape, store.n_frames
    if T < 2:
        raise ValueError(f"need at least 2 frames for a spectrum, got {T}")
    freqs = frequency_axis(T, fps)
    wcol = _column_weights(weights, fshape)
    power = np.zeros(freqs.size, np.float64)
    for sl, x in _iter_blocks(store, block_bytes, detrend, window):
        X = np.fft.rfft(x, axis=0)
        p = X.real**2 + X.imag**2
        power += p.sum(axis=1) if wcol is None else p @ wcol[sl]
    return freqs, power


def pixel_noise_power(
    disp: DisplacementStore | ArrayLike,
    *,
    detrend: Detrend = "mean",
    window: Window = "hann",
    min_bin: int = 3,
    block_bytes: int = 64 << 20,
) -> NDArray[np.float64]:
    """Each pixel's motion noise power: the median over frequency of its periodogram.

    ``N_p = median_l |DX_pl|**2 + median_l |DY_pl|**2`` over the bins ``min_bin`` .. Nyquist
    (same detrending, window and units as :func:`motion_power_spectrum`). Spectral lines
    cover few bins, so the median is the pixel's background; pixels at occlusion edges and
    texture seams measure motion far less reliably than the rest (four decades apart on a
    rendered cube) and show it here.

    Returns
    -------
    ndarray
        ``(H, W)`` float64, px**2 per bin.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> d = rng.standard_normal((256, 2, 3, 2))
    >>> d[:, 0] *= 10.0                       # the first row is 10x noisier
    >>> n = pixel_noise_power(d)
    >>> bool(np.all(n[0] / n[1] > 30))
    True
    """
    detrend = _check_detrend(detrend)
    store = _as_store(disp)
    fshape, T = store.frame_shape, store.n_frames
    if T < 2 * (min_bin + 1):
        raise ValueError(f"need at least {2 * (min_bin + 1)} frames, got {T}")
    out = np.empty(store.n_columns, np.float64)
    for sl, x in _iter_blocks(store, block_bytes, detrend, window):
        X = np.fft.rfft(x, axis=0)[min_bin:]
        out[sl] = np.median(X.real**2 + X.imag**2, axis=0)
    return out.reshape(*fshape[:2], 2).sum(axis=-1)


def bin_fields(
    disp: DisplacementStore | ArrayLike,
    bins: Sequence[int] | ArrayLike,
    *,
    detrend: Detrend = "mean",
    window: Window = "none",
    block_bytes: int = 64 << 20,
) -> NDArray[np.complex128]:
    """Complex image-space fields ``(DX_l, DY_l)`` at selected DFT bins, by pixel blocks.

    Parameters
    ----------
    disp : DisplacementStore or array_like
        ``(T, H, W, 2)`` displacements.
    bins : sequence of int
        DFT bin indices ``l`` (``0 <= l <= T // 2``).
    detrend : {"mean", "linear", "none"}
        As in :func:`motion_power_spectrum`.
    window : {"none", "hann"}
        As in :func:`motion_power_spectrum`.
    block_bytes : int
        Working memory per pixel block.

    Returns
    -------
    ndarray
        ``(k, H, W, 2)`` complex128, ``X_l = sum_t w_t d_t exp(-2 pi i l t / T)``
        (``w_t = 1`` without window).
    """
    detrend = _check_detrend(detrend)
    store = _as_store(disp)
    fshape, T = store.frame_shape, store.n_frames
    b = np.atleast_1d(np.asarray(bins, dtype=np.int64))
    if b.ndim != 1 or np.any(b < 0) or np.any(b > T // 2):
        raise ValueError(f"bins must be integers in [0, {T // 2}], got {b.tolist()}")
    out = np.empty((b.size, store.n_columns), np.complex128)
    if b.size == 0:
        return out.reshape(0, *fshape)
    if b.size > 4 * math.log2(max(T, 2)):
        # many bins: an FFT per pixel is cheaper than the (k, T) DFT rows
        for sl, x in _iter_blocks(store, block_bytes, detrend, window):
            out[:, sl] = np.fft.rfft(x, axis=0)[b]
        return out.reshape(b.size, *fshape)
    t = np.arange(T)
    # (k, T) DFT rows; exact integer phase reduction keeps it accurate for long videos
    E = np.exp(-2j * np.pi * ((b[:, None] * t[None, :]) % T) / T)
    for sl, x in _iter_blocks(store, block_bytes, detrend, window):
        out[:, sl] = E @ x
    return out.reshape(b.size, *fshape)
