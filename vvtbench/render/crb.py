r"""The Cramér-Rao ruler: how well the sample's video can show motion, and which modes it can.

Model
-----
A frame of the video is ``y_t(p) = I(p - s_t(p)) + n_t(p)``: the noise-free rest render
``I`` (digital numbers, DN) displaced by the image motion ``s_t(p)`` (px), plus zero-mean
Gaussian noise, independent between pixels and frames, of variance (DN^2)

.. math::  \sigma^2(p) = \frac{v_\mathrm{shot}(p) + r^2}{A} + \frac{\Delta^2}{12},
           \qquad v_\mathrm{shot} = I_0(p)\, D^2 / F,\; \Delta = 1\ \mathrm{DN},

with ``I_0`` the intensity in [0, 1], ``D = 2^bits - 1``, ``F`` the full-well capacity
(electrons), ``r`` the read noise (DN), ``A`` sub-frames averaged into a frame (each with its
own shot and read noise, :func:`vvtbench.render.sensor.sensor_dn`) and ``Delta^2 / 12`` the rounding
to whole DN (accurate once the noise before rounding is ~0.5 DN or more).

Shift of a block
----------------
For a known texture and a shift ``s`` common to the pixels of a block ``B``, the Fisher
information of ``s`` is ``J_B = sum_{p in B} g_p g_p^T / sigma^2(p)`` with ``g_p = grad I(p)``
(DN/px), and any unbiased estimate *from the block's pixels* has ``Cov(s_hat) >= J_B^{-1}``
(px^2).  The map reports per block ``J_B`` and ``sqrt(diag(J_B^{-1}))``, the per-axis standard
deviation bound (px).  It is no bound for an extractor that pools the pixels around the block
(a smoothing window, its filters' support): that extractor holds more information than the
block's and can "beat" the map (the phase extractor by 6x per 8 px block on a 2 px speckle,
pooling about a 20 px square); :func:`footprint_crb` gives the bound of the area it pools.  The
gradient is the fourth-order central difference ``(f[x-2] - 8 f[x-1] + 8 f[x+1] - f[x+2]) / 12``
along each axis, no smoothing across (a smoothing prefilter would lower the gradient energy and
so the information), taken on the noise-free rest render, edges reflected.  Its response to a
wave of ``k`` rad/px is ``(8 sin k - sin 2k) / (6 k)``: within 0.4 % of the true derivative
up to ``k = 0.6`` (a period of 10 px), 3 % at ``k = 1``.

A mode's SNR
------------
Mode ``i`` moves pixel ``p`` by ``s_t(p) = Psi_i(p) c_i(t)``: ``Psi_i(p)`` its image-space
shape (px per unit modal coordinate, ``image/modes`` times the motion scale) and ``c_i(t)``
its modal coordinate.  Write ``a`` for the mode's amplitude at its largest visible pixel,
``c_i(t) = a w(t) / max_p |Psi_i(p)|`` with ``w(t)`` the waveform of unit peak (for a
sinusoid, ``cos(2 pi f t + phi)``; damped, ``exp(-zeta 2 pi f t) cos(2 pi f_d t + phi)``).
For small motion ``y_t(p) ~ I(p) - g_p . Psi_i(p) c_i(t) + n_t(p)``, linear in ``a``, so the
Fisher information of ``a`` is

.. math::  \mathcal{I}_a = \Big(\sum_t w(t)^2\Big)\; K_i,\qquad
           K_i = \sum_p \frac{(g_p^T \hat\psi_p)^2}{\sigma^2(p)}
               = \sum_p \hat\psi_p^T J_p \hat\psi_p,\quad
           \hat\psi_p = \Psi_i(p) / \max_q |\Psi_i(q)|,

``J_p`` the one-pixel Fisher matrix.  The amplitude's bound is ``sigma_a = 1 / sqrt(I_a)`` and
the mode's CRB-limited SNR is ``a / sigma_a = sqrt(K_i E_i)``, with ``E_i = a^2 sum_t w(t)^2``
the energy (px^2) of its motion at the largest pixel over the record: ``a^2 T / 2`` for a
sinusoid over ``T`` frames, ``a^2 sum_t exp(-2 zeta omega t) / 2`` for a damped one
(``omega T >> 1``, ``zeta << 1``; unknown phase: both quadratures have this bound).  In a
generated sample ``E_i`` is measured from the filmed motion itself, ``E_i = sum_t c_i(t)^2
max_p |Psi_i(p)|^2`` with ``c_i`` the least-squares modal coordinates of the stored surface
displacements, so any excitation (impulse, sweep, several modes) is covered.

Assumptions: an unbiased estimator; white Gaussian noise of the variance above, independent
between pixels and frames; small motion (the first-order expansion); the texture known (an
extractor that must learn it from the noisy frames does worse); for the block map, a shift
constant over a block, blocks independent and an estimate from the block's own pixels.
Lossy compression (consumer H.264) is not in the noise model: the bound is then optimistic.

Detectability
-------------
The extractors test each of ``N`` frequency bins of a spectrum against a threshold set for a
probability ``P_fa`` that noise alone puts any bin over it (:func:`vvtbench.modes.significance.
noise_floor`, ``false_alarm = 0.01``).  For the ideal detector of a line at a known frequency
(the least-squares quadratures ``(x, y)`` of the mode's known image-space pattern, each of
standard deviation ``sigma_a``), ``(x^2 + y^2) / sigma_a^2`` is ``chi2_2`` under noise alone
and non-central ``chi2_2(lambda = SNR^2)`` with the mode.  The per-bin false-alarm
probability is ``p = 1 - (1 - P_fa)^(1/N)``, the threshold ``c = chi2_2.isf(p)
= 2 ln(1/p)``, and a mode is *CRB-detectable* when ``SNR >= sqrt(lambda_50)`` with
``ncx2(2, lambda_50).median() = c``: the SNR at which the ideal detector finds it with
probability 0.5.  ``N`` is the number of bins of the record's one-sided spectrum,
``floor(T / 2)`` (every bin up to Nyquist is searched).  For ``T = 500`` frames the threshold
is 4.39 (4.00 at 100, 4.69 at 2000); it grows slowly with ``T`` (``~ sqrt(2 ln N)``).  It
follows from the extractor's false-alarm probability alone: nothing in it is fitted to
instances.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "BLOCK_PX",
    "DERIVATIVE_TAPS",
    "EXTRACTOR_FALSE_ALARM",
    "block_crb",
    "decaying_sinusoid_energy",
    "detection_snr_threshold",
    "footprint_crb",
    "image_gradient",
    "mode_information",
    "mode_snr",
    "modal_energy",
    "noise_variance_dn2",
    "pixel_fisher",
]

#: Side (px) of the square blocks of the CRB map.
BLOCK_PX = 8
#: False-alarm probability per spectrum of the extractors' peak test (noise_floor's default).
EXTRACTOR_FALSE_ALARM = 0.01
#: Fourth-order central difference, as correlation taps at offsets -2..2.
DERIVATIVE_TAPS = np.array([1.0, -8.0, 0.0, 8.0, -1.0]) / 12.0


def noise_variance_dn2(
    intensity: ArrayLike, bit_depth: int, read_noise_dn: float, shot_noise: bool,
    full_well: float, frame_average: int = 1,
) -> NDArray[np.float64]:
    """Per-pixel noise variance (DN^2) of a frame of :func:`vvtbench.render.sensor.sensor_dn`.

    ``(I D^2 / F [shot] + r^2) / A + 1/12`` for intensity ``I`` in [0, 1], ``D = 2^bits - 1``,
    full well ``F`` (electrons), read noise ``r`` (DN) and ``A`` averaged sub-frames.
    """
    if int(bit_depth) < 1 or int(frame_average) < 1:
        raise ValueError(f"bit_depth and frame_average must be >= 1, got {bit_depth}, "
                         f"{frame_average}")
    i0 = np.clip(np.asarray(intensity, dtype=np.float64), 0.0, None)
    dn_max = float(2 ** int(bit_depth) - 1)
    var = np.full(i0.shape, float(read_noise_dn) ** 2)
    if shot_noise:
        if not full_well > 0:
            raise ValueError(f"full_well must be > 0, got {full_well}")
        var = var + i0 * dn_max**2 / float(full_well)
    return var / int(frame_average) + 1.0 / 12.0


def image_gradient(frame: ArrayLike) -> NDArray[np.float64]:
    """``(H, W, 2)`` gradient ``(d/dx, d/dy)`` (x along columns) by :data:`DERIVATIVE_TAPS`
    along each axis; edges reflected."""
    from scipy.ndimage import correlate1d

    f = np.asarray(frame, dtype=np.float64)
    if f.ndim != 2:
        raise ValueError(f"frame must be 2-D, got shape {f.shape}")
    gx = correlate1d(f, DERIVATIVE_TAPS, axis=1, mode="reflect")
    gy = correlate1d(f, DERIVATIVE_TAPS, axis=0, mode="reflect")
    return np.stack([gx, gy], axis=-1)


def pixel_fisher(frame_dn: ArrayLike, variance_dn2: ArrayLike) -> NDArray[np.float64]:
    """``(H, W, 3)`` one-pixel Fisher matrices ``g g^T / sigma^2`` as ``(Jxx, Jxy, Jyy)``
    (1/px^2) of the noise-free frame ``frame_dn`` (DN) with noise variance ``variance_dn2``."""
    g = image_gradient(frame_dn)
    var = np.broadcast_to(np.asarray(variance_dn2, dtype=np.float64), g.shape[:2])
    if not np.all(var > 0):
        raise ValueError("noise variance must be > 0 at every pixel")
    gx, gy = g[..., 0], g[..., 1]
    return np.stack([gx * gx / var, gx * gy / var, gy * gy / var], axis=-1)


def block_crb(fisher_px: ArrayLike, block: int = BLOCK_PX) -> dict[str, NDArray[np.float64]]:
    """Per-block Fisher matrices and Cramér-Rao bounds of a 2-D shift.

    Parameters
    ----------
    fisher_px : array_like
        ``(H, W, 3)`` :func:`pixel_fisher`.
    block : int, default :data:`BLOCK_PX`
        Block side (px); the last row/column of blocks may be smaller.

    Returns
    -------
    dict
        ``fisher`` ``(Hb, Wb, 3)`` (``Jxx, Jxy, Jyy``, 1/px^2), ``std_px`` ``(Hb, Wb, 2)`` the
        per-axis bound ``sqrt(diag(J^{-1}))`` (px; inf where ``J`` is singular) and
        ``std_min_px`` ``(Hb, Wb)`` the bound along the best-measured direction
        ``1 / sqrt(largest eigenvalue of J)`` (inf for a textureless block).
    """
    jp = np.asarray(fisher_px, dtype=np.float64)
    b = int(block)
    if b < 1 or jp.ndim != 3 or jp.shape[2] != 3:
        raise ValueError(f"need (H, W, 3) Fisher and block >= 1, got {jp.shape}, {block}")
    H, W = jp.shape[:2]
    hb, wb = -(-H // b), -(-W // b)
    pad = np.zeros((hb * b, wb * b, 3))
    pad[:H, :W] = jp
    jb = pad.reshape(hb, b, wb, b, 3).sum(axis=(1, 3))
    jxx, jxy, jyy = jb[..., 0], jb[..., 1], jb[..., 2]
    det = jxx * jyy - jxy * jxy
    scale = np.maximum(jxx + jyy, 1e-300)
    ok = det > 1e-12 * scale**2
    with np.errstate(divide="ignore", invalid="ignore"):
        std = np.stack([np.where(ok, np.sqrt(jyy / det), np.inf),
                        np.where(ok, np.sqrt(jxx / det), np.inf)], axis=-1)
        lam = 0.5 * (jxx + jyy) + np.sqrt(0.25 * (jxx - jyy) ** 2 + jxy**2)
        std_min = np.where(lam > 0, 1.0 / np.sqrt(lam), np.inf)
    return {"fisher": jb, "std_px": std, "std_min_px": std_min}


def footprint_crb(fisher_px: ArrayLike, block: int = BLOCK_PX, sigma_px: float = 0.0, *,
                  transfer: ArrayLike | None = None, periodic: bool = False) -> dict[str, Any]:
    """Per-block bound of a shift measured over the block as an extractor pools it.

    An extractor that pools pixels with a window ``G`` (a Gaussian smoothing of its
    per-pixel estimates or normal equations, its filters' support) and is then averaged over
    block ``B`` weights pixel ``p`` by ``k_B(p) = (1_B * G)(p)``: it uses pixels outside the
    block, and :func:`block_crb`, the bound of the block's own pixels, is then no bound for
    it (an extractor can "beat" it by the ratio of the areas).  Here
    the weighted least-squares shift with these weights, from pixels of Fisher matrices
    ``J_p``, has covariance ``A^{-1} S A^{-1}`` with ``A = sum_p k_B(p) J_p`` and ``S = sum_p
    k_B(p)^2 J_p`` (a shift common to the window): for ``sigma_px = 0`` it is
    :func:`block_crb`'s ``J_B^{-1}``; for a uniform texture it is the bound of a block of
    the *pooled area* ``N = (sum k)^2 / sum k^2`` pixels (11.2^2 px for an 8 px block and
    ``sigma_px = 2``).  The yardstick of an extractor with that footprint.

    Parameters
    ----------
    fisher_px : array_like
        ``(H, W, 3)`` :func:`pixel_fisher`; ``H`` and ``W`` multiples of ``block``.
    block : int
        Block side (px).
    sigma_px : float
        Standard deviation (px) of a Gaussian pooling window; 0 = the block alone.
    transfer : array_like, optional
        Instead of ``sigma_px``: the window's response to a motion ``cos(2 pi m x / H)``,
        ``m = 0 .. H // 2`` (e.g. an extractor's measured motion transfer function,
        :func:`vvtbench.scoring.efficiency.motion_transfer`), applied along both axes
        (separable window); needs ``periodic`` and a square image.
    periodic : bool, default False
        The image wraps around (a periodic test image); otherwise edges are reflected.

    Returns
    -------
    dict
        ``std_px`` ``(Hb, Wb, 2)`` per-axis bound (px; inf where ``A`` is singular) and
        ``pooled_px`` ``sqrt(N)``, the side of the pooled area.
    """
    jp = np.asarray(fisher_px, dtype=np.float64)
    b = int(block)
    if b < 1 or jp.ndim != 3 or jp.shape[2] != 3:
        raise ValueError(f"need (H, W, 3) Fisher and block >= 1, got {jp.shape}, {block}")
    H, W = jp.shape[:2]
    if H % b or W % b:
        raise ValueError(f"block {b} must divide the image size {H}x{W}")
    sigma = float(sigma_px)
    if not sigma >= 0:
        raise ValueError(f"sigma_px must be >= 0, got {sigma_px}")
    if transfer is not None and not (periodic and H == W):
        raise ValueError("a transfer function needs a periodic, square image")
    r = 0 if periodic else int(math.ceil(4.0 * sigma))
    if r:
        jp = np.pad(jp, ((r, r), (r, r), (0, 0)), mode="reflect")
    h, w = jp.shape[:2]
    box = np.zeros((h, w))
    box[:b, :b] = 1.0
    kspec = np.fft.fft2(box)
    if transfer is not None:
        t = np.asarray(transfer, dtype=np.float64)
        if t.shape != (h // 2 + 1,):
            raise ValueError(f"transfer must have {h // 2 + 1} values, got {t.shape}")
        m = np.abs(np.rint(np.fft.fftfreq(h) * h).astype(int))
        kspec = kspec * np.outer(t[m], t[m])
    elif sigma > 0:
        # a sampled Gaussian of unit sum (periodic), not the continuous transfer function
        gy = np.exp(-0.5 * (np.minimum(np.arange(h), h - np.arange(h)) / sigma) ** 2)
        gx = np.exp(-0.5 * (np.minimum(np.arange(w), w - np.arange(w)) / sigma) ** 2)
        kspec = kspec * np.fft.fft2(np.outer(gy / gy.sum(), gx / gx.sum()))
    k = np.fft.ifft2(kspec).real  # the window of the block at the origin, wrapped
    fj = np.fft.fft2(jp, axes=(0, 1))

    def pooled(kern):  # sum_p kern(p - o) J(p) at every offset o
        return np.fft.ifft2(np.conj(np.fft.fft2(kern))[..., None] * fj, axes=(0, 1)).real

    rows = r + np.arange(H // b) * b
    cols = r + np.arange(W // b) * b
    a = pooled(k)[np.ix_(rows, cols)]
    sq = pooled(k * k)[np.ix_(rows, cols)]
    det = a[..., 0] * a[..., 2] - a[..., 1] ** 2
    scale = np.maximum(a[..., 0] + a[..., 2], 1e-300)
    ok = det > 1e-12 * scale**2
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.stack([a[..., 2], -a[..., 1], a[..., 0]], axis=-1) / det[..., None]
        # diag(A^-1 S A^-1) of symmetric 2x2 matrices (xx, xy, yy)
        vxx = (inv[..., 0] ** 2 * sq[..., 0] + 2 * inv[..., 0] * inv[..., 1] * sq[..., 1]
               + inv[..., 1] ** 2 * sq[..., 2])
        vyy = (inv[..., 1] ** 2 * sq[..., 0] + 2 * inv[..., 1] * inv[..., 2] * sq[..., 1]
               + inv[..., 2] ** 2 * sq[..., 2])
        std = np.stack([np.where(ok, np.sqrt(np.maximum(vxx, 0.0)), np.inf),
                        np.where(ok, np.sqrt(np.maximum(vyy, 0.0)), np.inf)], axis=-1)
    return {"std_px": std, "pooled_px": float(k.sum() / math.sqrt(float(np.sum(k * k))))}


def mode_information(fisher_px: ArrayLike, image_modes: Iterable[ArrayLike],
                     motion_scale: float = 1.0) -> tuple[NDArray[np.float64],
                                                         NDArray[np.float64]]:
    """``K_i`` (1/px^2) and ``max_p |Psi_i(p)|`` of each mode (module docstring).

    Parameters
    ----------
    fisher_px : array_like
        ``(H, W, 3)`` :func:`pixel_fisher`.
    image_modes : iterable of array_like
        One ``(H, W, 2)`` image-space mode shape per mode (NaN off the object), e.g. the
        rows of a sample's ``image/modes`` read one at a time.
    motion_scale : float, default 1
        Factor from the shapes to the video's motion.

    Returns
    -------
    information, gain : ndarray
        ``(n,)`` ``K_i = sum_p psi_p^T J_p psi_p`` for the shape normalised to unit peak
        (0 for a mode with no visible pixel) and ``(n,)`` its peak ``motion_scale max_p
        |Psi_i(p)|`` (px per unit modal coordinate).
    """
    jp = np.asarray(fisher_px, dtype=np.float64)
    info, gain = [], []
    for m in image_modes:
        psi = np.asarray(m, dtype=np.float64)
        if psi.shape != jp.shape[:2] + (2,):
            raise ValueError(f"mode shape {psi.shape} does not match the frame {jp.shape[:2]}")
        ok = np.all(np.isfinite(psi), axis=-1)
        px, py = np.where(ok, psi[..., 0], 0.0), np.where(ok, psi[..., 1], 0.0)
        peak = float(np.sqrt(np.max(px * px + py * py, initial=0.0)))
        if peak == 0.0:
            info.append(0.0)
            gain.append(0.0)
            continue
        q = (jp[..., 0] * px * px + 2.0 * jp[..., 1] * px * py + jp[..., 2] * py * py)
        info.append(float(q.sum()) / peak**2)
        gain.append(abs(float(motion_scale)) * peak)
    return np.asarray(info), np.asarray(gain)


def modal_energy(displacements, surface_modes: ArrayLike, *,
                 chunk_frames: int = 2048) -> NDArray[np.float64]:
    """``sum_t q_i(t)^2`` of the least-squares modal coordinates of a surface motion.

    ``displacements`` ``(T, S, 3)`` (read ``chunk_frames`` at a time, e.g. a Zarr array) are
    fit by ``surface_modes`` ``(n, S, 3)``.
    """
    surf = np.asarray(surface_modes, dtype=np.float64)
    pinv = np.linalg.pinv(surf.reshape(surf.shape[0], -1).T)
    n_t, step = int(displacements.shape[0]), max(1, int(chunk_frames))
    energy = np.zeros(surf.shape[0])
    for k0 in range(0, n_t, step):
        u = np.asarray(displacements[k0:min(n_t, k0 + step)], dtype=np.float64)
        q = u.reshape(u.shape[0], -1) @ pinv.T
        energy += np.einsum("tn,tn->n", q, q)
    return energy


def decaying_sinusoid_energy(amplitude_px: float, frequency_hz: float, damping_ratio: float,
                             n_frames: int, fps: float) -> float:
    """``a^2 sum_t exp(-2 zeta omega t) / 2`` over ``t = k / fps``, ``k < n_frames`` (px^2):
    the record's energy of a (damped) sinusoid, ``a^2 T / 2`` undamped."""
    t = np.arange(int(n_frames)) / float(fps)
    s = 2.0 * math.pi * float(frequency_hz) * float(damping_ratio)
    return float(amplitude_px) ** 2 * float(np.sum(np.exp(-2.0 * s * t))) / 2.0


def mode_snr(information: ArrayLike, energy_px2: ArrayLike) -> NDArray[np.float64]:
    """CRB-limited SNR ``a / sigma_a = sqrt(K_i E_i)`` of each mode's amplitude."""
    k = np.asarray(information, dtype=np.float64)
    e = np.asarray(energy_px2, dtype=np.float64)
    if np.any(k < 0) or np.any(e < 0):
        raise ValueError("information and energy must be >= 0")
    return np.sqrt(k * e)


def detection_snr_threshold(n_frames: int, false_alarm: float = EXTRACTOR_FALSE_ALARM) -> float:
    """SNR at which the ideal detector of a line at a known frequency finds it with
    probability 0.5, at ``false_alarm`` over the ``floor(n_frames / 2)`` bins of the record's
    spectrum (module docstring, "Detectability")."""
    from scipy.optimize import brentq
    from scipy.stats import ncx2

    if not 0 < false_alarm < 1:
        raise ValueError(f"false_alarm must be in (0, 1), got {false_alarm}")
    n_bins = max(1, int(n_frames) // 2)
    per_bin = -math.expm1(math.log1p(-float(false_alarm)) / n_bins)
    c = 2.0 * math.log(1.0 / per_bin)
    lam = brentq(lambda x: float(ncx2.median(2, x)) - c, 1e-9, 10.0 * c + 50.0, xtol=1e-10)
    return math.sqrt(lam)
