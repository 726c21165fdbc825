"""The windowed DFT of a (damped) complex exponential: the kernel every line fit uses.

>>> import numpy as np
>>> T = 256
>>> t = np.arange(T)
>>> x = np.exp(2j * np.pi * 20.3 * t / T)              # a line at bin 20.3
>>> w = 0.5 - 0.5 * np.cos(2 * np.pi * t / T)
>>> X = np.fft.fft(w * x)[18:23]
>>> K = line_kernel(np.array([20.3]), np.array([0.0]), np.arange(18, 23), T, "hann")
>>> bool(np.allclose(K[:, 0], X))
True
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["line_kernel"]


def _geometric(d: NDArray, s: NDArray, n_frames: int) -> NDArray[np.complex128]:
    """``sum_{n<T} exp((2 pi i d / T - s) n)`` elementwise (``d`` bins, ``s`` per frame)."""
    L = 2j * np.pi * d / n_frames - s
    small = np.abs(L) < 1e-9
    Ls = np.where(small, 1e-3j, L)
    out = np.expm1(n_frames * Ls) / np.expm1(Ls)
    return np.where(small, n_frames * (1.0 + 0.5 * (n_frames - 1) * L), out)


def line_kernel(kappa: ArrayLike, half_width: ArrayLike, bins: ArrayLike, n_frames: int,
                window: str = "hann") -> NDArray[np.complex128]:
    """DFT at integer ``bins`` of windowed unit lines ``exp((2 pi i kappa / T - s) t)``.

    Parameters
    ----------
    kappa : array_like
        ``(M,)`` line frequencies in (fractional) bins.
    half_width : array_like
        ``(M,)`` half widths at half power in bins, ``h = s T / (2 pi)`` for a decay ``s``
        per frame (``zeta = h / kappa`` for a mode); 0 for an undamped line.
    bins : array_like
        ``(B,)`` DFT bins.
    n_frames : int
        Record length ``T``.
    window : {"hann", "none"}
        The periodic Hann taper of :func:`.spectrum.window_weights` or none.

    Returns
    -------
    ndarray
        ``(B, M)`` complex, unnormalised like :func:`.spectrum.bin_fields`.
    """
    k = np.atleast_1d(np.asarray(kappa, np.float64))
    s = 2.0 * np.pi * np.atleast_1d(np.asarray(half_width, np.float64)) / n_frames
    d = k[None, :] - np.asarray(bins, np.float64)[:, None]
    s = np.broadcast_to(s[None, :], d.shape)
    if window == "none":
        return _geometric(d, s, n_frames)
    if window != "hann":
        raise ValueError(f"window must be 'hann' or 'none', got {window!r}")
    return (0.5 * _geometric(d, s, n_frames) - 0.25 * _geometric(d + 1, s, n_frames)
            - 0.25 * _geometric(d - 1, s, n_frames))
