"""Uncertainty of fitted spectral lines: frequency, half width (damping) and shape.

The line fit (:mod:`.lines`) minimises ``sum_p w_p |Z_p - K(theta) A_p|^2`` over the line
parameters ``theta = (kappa, h)`` and the shapes ``A``.  Its covariance is the sandwich
``H^-1 V H^-1`` of the Gauss-Newton Hessian ``H = 2 Re J^H W J`` (``J`` the Jacobian of the
variable-projection residual at the fit) and the covariance ``V`` of the gradient, estimated
from the residual itself: the per-channel scores ``2 Re w_p J_p^H r_p`` summed within clusters
of channels (pixel blocks, whose motion noise is correlated) and their outer products summed
over clusters.  No noise level, window correlation or channel weighting has to be assumed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .kernel import line_kernel

__all__ = ["LINE_FIT_METHOD", "LineUncertainty", "Z95", "block_clusters", "damping_interval",
           "line_uncertainty", "mode_uncertainty"]

#: two-sided 95 % normal quantile used for the damping interval
Z95 = 1.959963984540054
#: the value of a mode set's ``metadata["uncertainty_method"]`` when its lines were fitted
#: (peak-picked modes: :data:`.jackknife.METHOD`)
LINE_FIT_METHOD = "line_fit_sandwich"


@dataclass(frozen=True)
class LineUncertainty:
    """Standard errors of the lines of one group (:func:`line_uncertainty`).

    Attributes
    ----------
    kappa_std, half_width_std : ndarray
        ``(M,)`` standard errors (bins).
    cov_kappa_half_width : ndarray
        ``(M,)`` covariance of each line's ``kappa`` and ``h`` (bins squared).
    max_correlation : ndarray
        ``(M,)`` largest absolute correlation of a line's parameters with another line's.
    shape_mac : ndarray
        ``(M,)`` expected weighted MAC of the fitted shape with the noiseless one,
        ``signal / (signal + noise)`` energy.
    """

    kappa_std: NDArray[np.float64]
    half_width_std: NDArray[np.float64]
    cov_kappa_half_width: NDArray[np.float64]
    max_correlation: NDArray[np.float64]
    shape_mac: NDArray[np.float64]


def block_clusters(shape: tuple[int, ...], block: int = 8) -> NDArray[np.int64]:
    """Cluster label of every channel of a ``(H, W, C)`` field: its ``block`` x ``block``
    pixel tile (flattened like ``reshape(-1)``)."""
    H, W = int(shape[0]), int(shape[1])
    C = int(np.prod(shape[2:])) if len(shape) > 2 else 1
    r = np.arange(H)[:, None] // block
    c = np.arange(W)[None, :] // block
    lab = r * ((W + block - 1) // block) + c
    return np.repeat(lab.reshape(-1), C).astype(np.int64)


#: blocks of channels are a multiple of this: of every BLAS kernel's column unroll (2, 4, 6,
#: 8, 16, ...), so a block's product is the whole array's, bit for bit
_BLOCK_QUANTUM = 960


def _channel_block(n_lines: int, n_bins: int, budget_bytes: int = 64 * 2**20) -> int:
    """Channels per block of :func:`line_uncertainty`: its complex temporaries of
    ``(2 n_lines + n_bins)`` rows stay near ``budget_bytes``.

    >>> _channel_block(241, 300), _channel_block(3, 40)
    (4800, 90240)
    """
    per = budget_bytes // (16 * (2 * int(n_lines) + int(n_bins)))
    return max(1, per // _BLOCK_QUANTUM) * _BLOCK_QUANTUM


def _window_noise_cov(n_bins: int, window: str) -> NDArray[np.float64]:
    """Correlation of the windowed DFT of white noise between consecutive bins."""
    if window == "none":
        return np.eye(n_bins)
    H = 0.5 * np.eye(n_bins) - 0.25 * np.eye(n_bins, k=1) - 0.25 * np.eye(n_bins, k=-1)
    return H @ H.T


def line_uncertainty(Z: ArrayLike, bins: ArrayLike, kappa: ArrayLike, half_width: ArrayLike,
                     n_frames: int, *, weights: ArrayLike | None = None,
                     clusters: ArrayLike | None = None, window: str = "hann",
                     eps: float = 1e-6) -> LineUncertainty:
    """Sandwich covariance of lines fitted to complex fields.

    Parameters
    ----------
    Z : array_like
        ``(B, P)`` complex fields at ``bins`` (other lines already removed).
    bins : array_like
        ``(B,)`` DFT bins of the group.
    kappa, half_width : array_like
        ``(M,)`` the fitted lines (bins).
    n_frames : int
        Record length.
    weights : array_like, optional
        ``(P,)`` channel weights of the fit.
    clusters : array_like, optional
        ``(P,)`` integer cluster of each channel (:func:`block_clusters`); channels of one
        cluster may have correlated noise.  Default: each channel alone.
    window : {"hann", "none"}
        Taper of ``Z``.

    Returns
    -------
    LineUncertainty
    """
    Zc = np.asarray(Z, np.complex128)
    b = np.asarray(bins, np.float64)
    k = np.atleast_1d(np.asarray(kappa, np.float64))
    h = np.atleast_1d(np.asarray(half_width, np.float64))
    M, P = k.size, Zc.shape[1]
    w = np.ones(P) if weights is None else np.asarray(weights, np.float64)
    K = line_kernel(k, h, b, n_frames, window)
    Kp = np.linalg.pinv(K)
    A = Kp @ Zc
    Pperp = np.eye(b.size) - K @ Kp
    dk = (line_kernel(k + eps, h, b, n_frames, window) - K) / eps
    dh = (line_kernel(k, h + eps, b, n_frames, window) - K) / eps
    D = np.concatenate([dk, dh], axis=1)
    Dh = D.conj().T
    m_of = np.concatenate([np.arange(M), np.arange(M)])
    Aw = A * w[None, :]
    Cm = (A.conj() @ Aw.T)[np.ix_(m_of, m_of)]
    Hs = 2.0 * np.real((Dh @ Pperp @ D) * Cm)
    lab = (None if clusters is None
           else np.unique(np.asarray(clusters), return_inverse=True)[1])
    scores = np.zeros((2 * M, P if lab is None else int(lab.max()) + 1 if lab.size else 0))
    sigma2 = np.empty(P)
    # channel by channel in blocks: every column below depends on its own channel only, so
    # the values are those of the whole-array expressions, with (2M + B) x block temporaries
    step = _channel_block(M, b.size)
    for c0 in range(0, P, step):
        c = slice(c0, min(P, c0 + step))
        R = Zc[:, c] - K @ A[:, c]
        s = 2.0 * np.real(Aw[m_of, c].conj() * (Dh @ R))
        if lab is None:
            scores[:, c] = s
        else:
            np.add.at(scores.T, lab[c], s.T)
        sigma2[c] = np.sum(np.abs(R) ** 2, axis=0)
    G = scores.shape[1]
    V = scores @ scores.T * (G / (G - 1.0) if G > 1 else 1.0)
    Hi = np.linalg.pinv(Hs)
    cov = Hi @ V @ Hi
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = np.abs(cov / np.outer(sd, sd))
    same = m_of[:, None] == m_of[None, :]
    corr = np.where(same | ~np.isfinite(corr), 0.0, corr)
    max_corr = np.maximum(corr[:M].max(axis=1), corr[M:].max(axis=1)) if M > 1 else np.zeros(M)
    Sb = _window_noise_cov(b.size, window)
    dof = max(float(np.real(np.trace(Pperp @ Sb))), 1e-12)
    sigma2 = sigma2 / dof
    varA = np.real(np.einsum("mb,bc,mc->m", Kp, Sb, Kp.conj()))
    noise = varA * float(np.sum(w * sigma2))
    signal = np.sum(w[None, :] * np.abs(A) ** 2, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        mac = np.where(signal > 0, signal / (signal + noise), 0.0)
    return LineUncertainty(kappa_std=sd[:M], half_width_std=sd[M:],
                           cov_kappa_half_width=cov[np.arange(M), M + np.arange(M)],
                           max_correlation=max_corr, shape_mac=mac)


def damping_interval(kappa: ArrayLike, half_width: ArrayLike, half_width_std: ArrayLike,
                     z: float = Z95) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Interval ``[lo, hi]`` of the damping ratio ``zeta = h / kappa`` (``z`` standard errors
    of the half width on each side; the frequency's share is negligible)."""
    k = np.asarray(kappa, np.float64)
    h = np.asarray(half_width, np.float64)
    s = np.asarray(half_width_std, np.float64)
    return (h - z * s) / k, (h + z * s) / k


#: a close pair whose group misfit exceeds this (residual over noise floor) biases itself
MAX_MISFIT = 3.0
#: ... or whose parameters correlate more than this
MAX_CORRELATION = 0.8
#: lines nearer than this (bins) are a close pair
CLOSE_BINS = 4.0


def mode_uncertainty(lines: object, fps: float, n_frames: int) -> dict[str, list]:
    """Per-line uncertainty lists of a :class:`.lines.Lines` for a mode set's metadata.

    Returns ``frequency_std_hz``, ``damping_lo``, ``damping_hi`` (95 % interval of the damping
    ratio), ``shape_mac_expected`` and ``close_mode_bias`` (a line within
    :data:`CLOSE_BINS` bins of another whose group residual exceeds :data:`MAX_MISFIT` times
    the noise floor, or whose parameters correlate above :data:`MAX_CORRELATION` with the
    other's), one entry per line in the order of ``lines.kappa``.
    """
    u = lines.uncertainty
    k = np.asarray(lines.kappa, np.float64)
    lo, hi = damping_interval(k, lines.half_width, u.half_width_std)
    gap = np.array([np.min(np.abs(np.delete(k, i) - k[i])) if k.size > 1 else np.inf
                    for i in range(k.size)])
    misfit = np.asarray(lines.misfit, np.float64)
    close = (gap < CLOSE_BINS) & ((misfit > MAX_MISFIT) | (u.max_correlation > MAX_CORRELATION))

    def clean(a: NDArray) -> list:
        return [float(x) if np.isfinite(x) else None for x in a]

    return {
        "frequency_std_hz": clean(u.kappa_std * fps / n_frames),
        "damping_lo": clean(lo),
        "damping_hi": clean(hi),
        "shape_mac_expected": clean(u.shape_mac),
        "close_mode_bias": [bool(c) for c in close],
        "line_misfit": clean(misfit),
    }
