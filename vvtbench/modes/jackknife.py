"""Uncertainty of peak-picked modes: a delete-one-group jackknife over pixel blocks.

A mode found by the peak picker (no line fit) has its frequency refined on the motion power
spectrum (:func:`.peaks.refine_frequency`) and its damping fitted to it
(:func:`.damping.damping_lorentzian`).  That spectrum is a sum over pixels, ``S = sum_g S_g``,
of the spectra of ``G`` groups of pixels.  Each group is a set of 8 x 8 pixel tiles
(:func:`.uncertainty.block_clusters`) taken every ``G``-th tile, so the motion noise of
neighbouring pixels, which is correlated, stays inside one group and every group spans the
whole image.  The estimates are recomputed on every leave-one-group-out spectrum
``S - S_g`` and the jackknife variance ::

    var = (G - 1) / G * sum_g (theta_(-g) - mean_g theta_(-g))**2

is the variance of the estimate from the whole record and all pixels: every re-estimate uses
the full record, so no scaling with record length is needed.  Assumptions: the noise of
different groups is independent, and every group sees the same line shape at the peak (one
mode under it, so a group's share of the mode's energy moves no estimate: frequency and
damping do not depend on the line's height).  Two modes under one peak break the second one:
each group sees another mix, which widens the interval somewhat, but the blend's bias (a
broader, shifted line) is not a spread and is not covered; :func:`blend_misfit` detects it.

Why pixel groups and not segments of the record: a damped mode decays within the first
segment of a record several decay times long, so later segments hold noise only, segments
are not exchangeable, and a segment's line is ``K`` times narrower in bins than the full
record's, which moves the damping below what a segment resolves; the spread of segment
estimates then says little about the full-record estimate.  Pixel groups share the record.

The damping interval is ``zeta +- t_(G-1) sd`` (Student's ``t`` with ``G - 1`` degrees of
freedom, the jackknife variance's).  ``frequency_std_hz`` adds in quadrature the bias of the
parabola of :func:`.peaks.refine_frequency` on the model line with the spectrum's noise floor
(:func:`refine_bias_bins`, up to a few hundredths of a bin), a root-mean-square error.  A mode
with another analysed peak within twice the bins its damping fit reaches
(:func:`damping_fit_reach`, at least :data:`.uncertainty.CLOSE_BINS`), or whose fields at its
three bins are not one line (:func:`blend_misfit` above :data:`.uncertainty.MAX_MISFIT`,
stored as ``line_misfit``), is flagged ``close_mode_bias``; its damping is then not resolved.
With the Hann window the damping is also fitted to the spectrum without window, from the same
transforms, with its own jackknife interval, and the reported interval is the hull of the two.
Both fits are exact for a free decay from the record's first frame and then agree within their
noise; a mode that starts later (a sweep passes through it mid-record) is read as decaying
faster by the Hann fit, and the interval then spans both readings: a damping whose interval spans
more than a factor 2 is not resolved (:meth:`.ModeSet.damping_resolved`); on a linear sweep
the fit without window stays within about 15 % of the truth where the Hann fit reads up to three
times it.
No random draw is made: groups are assigned deterministically.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .damping import lorentzian_fit
from .peaks import refine_frequency
from .record import FREQUENCY_FLOOR_BINS
from .significance import noise_floor
from .spectrum import DisplacementStore, Window, _as_store, _iter_blocks, hann_from_unwindowed
from .uncertainty import CLOSE_BINS, MAX_MISFIT, block_clusters

__all__ = ["DEFAULT_GROUPS", "METHOD", "blend_misfit", "damping_fit_reach", "group_labels",
           "group_spectra", "jackknife_uncertainty", "peak_uncertainty"]

#: groups of pixel tiles left out one at a time
DEFAULT_GROUPS = 16
#: the value of ``metadata["uncertainty_method"]`` for these modes
METHOD = "pixel_block_jackknife"
#: fewest groups a jackknife is computed with
MIN_GROUPS = 5


def group_labels(frame_shape: tuple[int, ...], n_groups: int = DEFAULT_GROUPS,
                 block: int = 8) -> tuple[NDArray[np.int64], int, int]:
    """Jackknife group of every column of a ``(H, W, 2)`` displacement field.

    Tiles of ``block`` x ``block`` pixels (halved until there are at least ``n_groups``
    tiles, down to single pixels) are dealt out in raster order: tile ``b`` goes to group
    ``b mod n_groups``.

    Returns
    -------
    labels : ndarray
        ``(H * W * 2,)`` group of each column (flattened like ``reshape(-1)``).
    n_groups : int
        Groups used (fewer than asked when the field has fewer pixels).
    block : int
        Tile size used.
    """
    if n_groups < 2:
        raise ValueError(f"n_groups must be >= 2, got {n_groups}")
    H, W = int(frame_shape[0]), int(frame_shape[1])
    b = max(1, int(block))
    while b > 1 and math.ceil(H / b) * math.ceil(W / b) < n_groups:
        b //= 2
    tiles = block_clusters((H, W, *frame_shape[2:]), b)
    g = int(min(n_groups, math.ceil(H / b) * math.ceil(W / b)))
    return tiles % g, g, b


def group_spectra(disp: DisplacementStore | ArrayLike, labels: ArrayLike, n_groups: int, *,
                  weights: ArrayLike | None = None, shape_weights: ArrayLike | None = None,
                  detrend: str = "mean", window: Window = "hann",
                  block_bytes: int = 64 << 20, cross_bins: ArrayLike | None = None,
                  unwindowed: bool = False) -> tuple[NDArray[np.float64], ...]:
    """Weighted motion power spectra of pixel groups, in one pass over the displacements.

    Parameters
    ----------
    disp : DisplacementStore or array_like
        ``(T, H, W, 2)`` displacements (px), read by pixel blocks.
    labels : array_like
        ``(H * W * 2,)`` group of each column (:func:`group_labels`).
    n_groups : int
        Number of groups.
    weights, shape_weights : array_like, optional
        ``(H, W)`` pixel weights of the group spectra and of the second, total spectrum
        (default 1).
    detrend, window, block_bytes :
        As :func:`.spectrum.motion_power_spectrum`.
    cross_bins : array_like of int, optional
        ``(M,)`` peak bins: also return, for each, the ``(3, 3)`` cross-spectral matrix
        ``C_ab = sum_p w_p X_p(k + a) conj(X_p(k + b))``, ``a, b`` in ``-1, 0, 1``, with
        ``weights`` (:func:`blend_misfit`).
    unwindowed : bool, default False
        Also return the group spectra without the window, from the same transforms
        (:func:`.spectrum.hann_from_unwindowed`).

    Returns
    -------
    group_power : ndarray
        ``(G, T // 2 + 1)``; their sum is :func:`.spectrum.motion_power_spectrum` with
        ``weights``.
    shape_power : ndarray
        ``(T // 2 + 1,)`` the spectrum with ``shape_weights``.
    cross : ndarray
        ``(M, 3, 3)`` complex, with ``cross_bins`` only.
    group_power_unwindowed : ndarray
        ``(G, T // 2 + 1)``, last, with ``unwindowed`` only.
    """
    store = _as_store(disp)
    H, W = store.frame_shape[:2]
    lab = np.asarray(labels, np.int64).reshape(-1)
    if lab.size != store.n_columns:
        raise ValueError(f"labels must have {store.n_columns} entries, got {lab.size}")

    def columns(w: ArrayLike | None) -> NDArray[np.float64]:
        if w is None:
            return np.ones(store.n_columns)
        w = np.asarray(w, np.float64)
        if w.shape != (H, W):
            raise ValueError(f"weights must have shape {(H, W)}, got {w.shape}")
        return np.repeat(w.reshape(-1), store.n_columns // (H * W))

    wg, ws = columns(weights), columns(shape_weights)
    F = store.n_frames // 2 + 1
    out = np.zeros((F, n_groups + 1))
    kb = None if cross_bins is None else np.atleast_1d(np.asarray(cross_bins, np.int64))
    if kb is not None and kb.size and (kb.min() < 1 or kb.max() > F - 2):
        raise ValueError(f"cross_bins must lie in [1, {F - 2}]")
    cross = None if kb is None else np.zeros((kb.size, 3, 3), np.complex128)
    rows = None if kb is None else (kb[:, None] + np.arange(-1, 2)[None, :]).reshape(-1)
    plain = np.zeros((F, n_groups)) if unwindowed else None
    # deriving the windowed transform keeps a second one per block: smaller blocks
    budget = block_bytes * 5 // 8 if unwindowed and window != "none" else block_bytes
    for sl, x in _iter_blocks(store, budget, detrend, "none" if unwindowed else window):
        X = np.fft.rfft(x, axis=0)
        M = np.zeros((x.shape[1], n_groups + 1))
        M[np.arange(x.shape[1]), lab[sl]] = wg[sl]
        M[:, n_groups] = ws[sl]
        if plain is not None:
            plain += (X.real**2 + X.imag**2) @ M[:, :n_groups]
            if window != "none":
                X = hann_from_unwindowed(X, store.n_frames)
        p = X.real**2 + X.imag**2
        out += p @ M
        if cross is not None:
            Xs = X[rows].reshape(kb.size, 3, -1)
            cross += np.einsum("map,mbp->mab", Xs * wg[sl], Xs.conj())
    spectra = (np.ascontiguousarray(out[:, :n_groups].T), out[:, n_groups])
    spectra = spectra if cross is None else (*spectra, cross)
    return spectra if plain is None else (*spectra, np.ascontiguousarray(plain.T))


def _t95(dof: int) -> float:
    from scipy.stats import t

    return float(t.ppf(0.975, dof))


def jackknife_uncertainty(freqs: ArrayLike, group_power: ArrayLike, bins: ArrayLike, *,
                          window: Window = "hann", n_frames: int | None = None,
                          damping: ArrayLike | None = None, band: slice | None = None,
                          floor_half_width_bins: int = 32) -> dict[str, NDArray[np.float64]]:
    """Jackknife standard errors and 95 % intervals of peak frequencies and damping ratios.

    Parameters
    ----------
    freqs : array_like
        ``(F,)`` frequency axis (Hz).
    group_power : array_like
        ``(G, F)`` spectra of the groups (:func:`group_spectra`).
    bins : array_like of int
        ``(M,)`` peak bins.
    window, n_frames :
        As :func:`.damping.damping_lorentzian`.
    damping : array_like, optional
        ``(M,)`` damping ratios the intervals are centred on (default: those of the summed
        spectrum, :func:`.damping.damping_lorentzian`).
    band, floor_half_width_bins :
        Bins and half width of the summed spectrum's noise floor
        (:func:`.significance.noise_floor`), for the frequency's bias.

    Returns
    -------
    dict of ndarray
        ``noise`` (``(F,)`` mean noise power of the summed spectrum: its floor times the
        mean over the median of its chi-square law), ``frequency_std_hz`` (root-mean-square
        error: the jackknife variance plus the square of :func:`refine_bias_bins`),
        ``frequency_jackknife_std_hz``, ``frequency_bias_hz``, ``damping`` (the estimates
        the intervals are centred on), ``line_scale`` (the full fit's factor on the power of a
        unit decay from the first frame, :func:`.damping.decay_spectrum`: the squared
        amplitude at that frame, summed as the spectrum is; ``nan`` where the fit failed),
        ``damping_std``, ``damping_lo``, ``damping_hi``
        (``(M,)``; an interval of ``[0, 0.3]``, which says nothing, where fewer than half the
        leave-one-out damping fits succeed; ``nan`` where the estimate itself is not finite)
        and ``t95`` (the quantile used).
    """
    f = np.asarray(freqs, np.float64)
    Pg = np.asarray(group_power, np.float64)
    G = Pg.shape[0]
    if G < MIN_GROUPS:
        raise ValueError(f"a jackknife needs at least {MIN_GROUPS} groups, got {G}")
    k = np.atleast_1d(np.asarray(bins, np.int64))
    total = Pg.sum(axis=0)
    T = n_frames
    full = [lorentzian_fit(f, total, int(b), window=window, n_frames=T) for b in k]
    z0 = (np.array([fit[0] for fit in full]) if damping is None
          else np.asarray(damping, np.float64))
    scale = np.array([math.exp(fit[3][-2]) if fit[3] is not None else np.nan for fit in full])
    fj = np.empty((G, k.size))
    zj = np.empty((G, k.size))
    for g in range(G):
        loo = total - Pg[g]
        for i, b in enumerate(k):
            fj[g, i] = refine_frequency(f, loo, int(b))
            zj[g, i] = lorentzian_fit(f, loo, int(b), window=window, n_frames=T,
                                      start=full[i][3])[0]
    t95 = _t95(G - 1)
    sf = np.sqrt((G - 1) / G * np.sum((fj - fj.mean(axis=0)) ** 2, axis=0))
    from scipy.stats import chi2

    nf = noise_floor(total, band, half_width_bins=floor_half_width_bins)
    noise = nf.floor * nf.nu / float(chi2.median(nf.nu))
    df = float(f[1] - f[0])
    T_ = int(n_frames) if n_frames is not None else 2 * (f.size - 1)
    bias = np.zeros(k.size)
    for i, b in enumerate(k):
        nu = refine_frequency(f, total, int(b)) / df
        gamma = z0[i] * nu if np.isfinite(z0[i]) and z0[i] > 0 else 0.0
        bias[i] = refine_bias_bins(total, int(b), nu, gamma, float(noise[b]), T_, window) * df
    sz = np.full(k.size, np.nan)
    lo = np.full(k.size, np.nan)
    hi = np.full(k.size, np.nan)
    for i in range(k.size):
        z = zj[:, i][np.isfinite(zj[:, i])]
        if not np.isfinite(z0[i]):
            continue
        if z.size < max(MIN_GROUPS, (G + 1) // 2):
            lo[i], hi[i] = 0.0, 0.3
            continue
        n = z.size
        sz[i] = math.sqrt((n - 1) / n * float(np.sum((z - z.mean()) ** 2)))
        q = _t95(n - 1)
        lo[i], hi[i] = z0[i] - q * sz[i], z0[i] + q * sz[i]
    return {"noise": noise, "frequency_std_hz": np.hypot(sf, bias),
            "frequency_jackknife_std_hz": sf,
            "frequency_bias_hz": bias, "damping": z0, "line_scale": scale, "damping_std": sz,
            "damping_lo": lo, "damping_hi": hi,
            "t95": np.full(k.size, t95)}


def refine_bias_bins(power: ArrayLike, bin_: int, nu: float, gamma: float, noise: float,
                     n_frames: int, window: Window = "hann") -> float:
    """Bias (bins) of :func:`.peaks.refine_frequency` on a decaying line with a noise floor.

    The parabola through the log power at three bins is exact for no line shape: on the
    exact windowed line (:func:`.damping.decay_spectrum`, frequency ``nu`` and decay rate
    ``gamma`` in bins) scaled to ``power[bin_]`` above the expected noise power ``noise``
    (which flattens the log parabola and pulls the estimate towards the bin), it is off by
    the returned amount.  ``nu`` is the estimate; the line is placed where that estimate
    would come from (one fixed-point step).
    """
    from .damping import _decay_power

    p = np.asarray(power, np.float64)
    k = int(bin_)
    if k < 1 or k >= p.size - 1:
        return 0.0
    b3 = np.arange(k - 1, k + 2, dtype=np.float64)
    axis = np.arange(p.size, dtype=np.float64)

    def bias(centre: float) -> float:
        m = _decay_power(centre, max(gamma, 1e-4), b3, n_frames, window)
        height = max(p[k] - noise, 0.0)
        if not m[1] > 0 or not height > 0:
            return 0.0
        model = np.zeros(p.size)
        model[k - 1:k + 2] = height * m / m[1] + noise
        return refine_frequency(axis, model, k) - centre

    return float(bias(nu - bias(nu)))


def damping_fit_reach(half_width_bins: ArrayLike, window: Window = "hann") -> NDArray:
    """Bins on each side of a peak that :func:`.damping.damping_lorentzian` fits (before the
    neighbouring valleys cut them): ``max(6, ceil(6 h))`` with Hann, ``max(4, ceil(6 h))``
    without, ``h`` the half width in bins (6 where it is not finite).

    A neighbouring mode closer than twice this has its own line inside the fit's bins; the
    fit, with one line and a constant floor, then takes the neighbour's flank for its own
    width.  On noiseless damped lines (zeta 0.02) at the paper cube's frequencies, 3 s at
    2000 FPS, every mode with a neighbour that close is off by 4-70 % (26 % at 7.8 Hz, whose
    neighbour is 6.5 bins away), and each alone is within 2 %.
    """
    h = np.asarray(half_width_bins, np.float64)
    base = 6.0 if window == "hann" else 4.0
    return np.maximum(base, np.ceil(6.0 * np.where(np.isfinite(h), h, 1.0)))


def _window_bin_cov(window: Window) -> NDArray[np.float64]:
    """Covariance of white noise's windowed DFT at three consecutive bins (unwindowed
    variance 1)."""
    if window == "none":
        return np.eye(3)
    return np.array([[0.375, -0.25, 0.0625], [-0.25, 0.375, -0.25], [0.0625, -0.25, 0.375]])


def blend_misfit(cross: ArrayLike, noise: ArrayLike, window: Window = "hann") -> NDArray:
    """How far the fields at a peak's three bins are from one line: the second generalized
    eigenvalue of the cross-spectral matrix (:func:`group_spectra`) against the window's
    noise covariance, over the noise.

    One line (a mode, of any shape, phase or damping) puts the same field, scaled, in the
    three bins: rank one.  Two modes under one peak that differ in shape and frequency add a
    second direction.  Noise alone gives eigenvalues near ``noise / 0.375`` (Hann); the
    misfit is about 1 for a single line and grows with a blended one.

    Parameters
    ----------
    cross : array_like
        ``(M, 3, 3)`` cross-spectral matrices.
    noise : array_like
        ``(M,)`` mean noise power at each peak bin in the windowed spectrum (same weights).
    window : {"hann", "none"}

    Returns
    -------
    ndarray
        ``(M,)``.
    """
    from scipy.linalg import eigh

    C = np.asarray(cross, np.complex128)
    n = np.asarray(noise, np.float64)
    Sb = _window_bin_cov(window)
    out = np.full(C.shape[0], np.nan)
    for m in range(C.shape[0]):
        if not n[m] > 0:
            continue
        lam = eigh(0.5 * (C[m] + C[m].conj().T), Sb.astype(np.complex128), eigvals_only=True)
        out[m] = float(lam[-2]) * Sb[1, 1] / n[m]
    return out


def _expected_shape_mac(shape_power: NDArray[np.float64], bins: NDArray[np.int64],
                        band: slice, half_width_bins: int) -> NDArray[np.float64]:
    """``1 - noise / power`` at each peak bin of the spectrum the shapes are weighted with:
    the expected MAC of a shape with the noiseless one (signal / (signal + noise) energy),
    the noise being the mean of the floor's chi-square law (:func:`.significance.noise_floor`)."""
    from scipy.stats import chi2

    nf = noise_floor(shape_power, band, half_width_bins=half_width_bins)
    mean_over_median = nf.nu / float(chi2.median(nf.nu))
    noise = nf.floor[bins] * mean_over_median
    p = shape_power[bins]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(p > 0, np.clip(1.0 - noise / p, 0.0, 1.0), 0.0)


def peak_uncertainty(disp: DisplacementStore | ArrayLike, freqs: ArrayLike, bins: ArrayLike,
                     fps: float, *, frequency_hz: ArrayLike, damping: ArrayLike,
                     spectrum_weights: ArrayLike | None = None,
                     shape_weights: ArrayLike | None = None, detrend: str = "mean",
                     window: Window = "hann", band: tuple[float, float] | None = None,
                     floor_half_width_bins: int = 32, n_groups: int = DEFAULT_GROUPS,
                     block_bytes: int = 64 << 20) -> dict[str, list]:
    """Per-peak uncertainty lists of peak-picked modes for a mode set's metadata.

    One more pass over the displacements (:func:`group_spectra`), then
    :func:`jackknife_uncertainty` around the given estimates.

    Parameters
    ----------
    disp : DisplacementStore or array_like
        ``(T, H, W, 2)`` displacements the modes were identified from.
    freqs : array_like
        ``(F,)`` frequency axis (Hz).
    bins : array_like of int
        ``(M,)`` analysed peak bins.
    fps : float
        Frame rate (Hz).
    frequency_hz, damping : array_like
        ``(M,)`` the modes' reported frequencies and damping ratios.
    spectrum_weights : array_like, optional
        ``(H, W)`` weights of the spectrum the frequency and damping were estimated on.
    shape_weights : array_like, optional
        ``(H, W)`` weights of the shapes (for ``shape_mac_expected``).
    detrend, window : str
        As the spectrum's.
    band : tuple of float, optional
        Extraction band (Hz) of the noise floor.
    floor_half_width_bins : int
        Half width of the noise floor's running median.
    n_groups : int
        Jackknife groups (:func:`group_labels`).

    Returns
    -------
    dict
        ``frequency_std_hz`` (never below :data:`.record.FREQUENCY_FLOOR_BINS` of a bin,
        ``fps / n_frames``; ``frequency_std_noise_hz`` is the jackknife's own, with the
        parabola's bias, and ``frequency_floor_hz`` the floor), ``damping_lo``,
        ``damping_hi``, ``shape_mac_expected``,
        ``close_mode_bias``, ``line_misfit`` (``None``: no line is fitted) and, with the
        Hann window, ``damping_unwindowed`` (the damping fitted to the spectrum without
        window; ``damping_lo`` and ``damping_hi`` are then the hull of both fits' intervals)
        and ``onset_amplitude_ratio`` (the amplitude of the decay the fit without window finds
        over the Hann fit's amplitude at the first frame; see
        :attr:`.ModeSet.initial_displacement_px`), one entry per peak, JSON-ready, plus
        ``uncertainty_method`` and ``uncertainty_groups``.
    """
    store = _as_store(disp)
    k = np.atleast_1d(np.asarray(bins, np.int64))
    f = np.asarray(freqs, np.float64)
    M = k.size
    floor = FREQUENCY_FLOOR_BINS * float(fps) / store.n_frames
    empty = {"frequency_std_hz": [], "frequency_std_noise_hz": [], "damping_lo": [],
             "damping_hi": [], "shape_mac_expected": [], "close_mode_bias": [],
             "line_misfit": [], "damping_unwindowed": [], "onset_amplitude_ratio": [],
             "uncertainty_method": METHOD, "frequency_floor_hz": floor,
             "frequency_floor_bins": FREQUENCY_FLOOR_BINS}
    if M == 0:
        return {**empty, "uncertainty_groups": None}
    labels, G, block = group_labels(store.frame_shape, n_groups)
    none = [None] * M
    if G < MIN_GROUPS:
        return {**empty, "frequency_std_hz": none, "frequency_std_noise_hz": none,
                "damping_lo": none, "damping_hi": none,
                "shape_mac_expected": none, "close_mode_bias": [False] * M,
                "line_misfit": none, "damping_unwindowed": none,
                "onset_amplitude_ratio": none, "uncertainty_groups": None}
    F = f.size
    inner = (k >= 1) & (k <= F - 2)
    hann = window == "hann"
    Pg, Ps, cross, *plain = group_spectra(
        store, labels, G, weights=spectrum_weights, shape_weights=shape_weights,
        detrend=detrend, window=window, block_bytes=block_bytes,
        cross_bins=np.clip(k, 1, F - 2), unwindowed=hann)
    df = f[1] - f[0]
    lo_bin = 1 if band is None else max(1, int(math.ceil(band[0] / df - 1e-9)))
    hi_bin = f.size - 1 if band is None else min(f.size - 1, int(math.floor(band[1] / df + 1e-9)))
    in_band = slice(lo_bin, hi_bin + 1)
    ju = jackknife_uncertainty(f, Pg, k, window=window, n_frames=store.n_frames,
                               damping=damping, band=in_band,
                               floor_half_width_bins=floor_half_width_bins)
    z_plain = np.full(M, np.nan)
    onset = np.full(M, np.nan)
    if hann:
        jp = jackknife_uncertainty(f, plain[0], k, window="none", n_frames=store.n_frames,
                                   band=in_band, floor_half_width_bins=floor_half_width_bins)
        z_plain = jp["damping"]
        with np.errstate(invalid="ignore", divide="ignore"):
            onset = np.sqrt(jp["line_scale"] / ju["line_scale"])
        both = (np.isfinite(ju["damping_lo"]) & np.isfinite(ju["damping_hi"])
                & np.isfinite(jp["damping_lo"]) & np.isfinite(jp["damping_hi"]))
        ju["damping_lo"] = np.where(both, np.fmin(ju["damping_lo"], jp["damping_lo"]),
                                    ju["damping_lo"])
        ju["damping_hi"] = np.where(both, np.fmax(ju["damping_hi"], jp["damping_hi"]),
                                    ju["damping_hi"])
    mac = _expected_shape_mac(Ps, k, in_band, floor_half_width_bins)
    misfit = np.where(inner, blend_misfit(cross, ju["noise"][np.clip(k, 0, F - 1)], window),
                      np.nan)
    fr = np.asarray(frequency_hz, np.float64) / df
    gap = np.array([np.min(np.abs(np.delete(fr, i) - fr[i])) if M > 1 else np.inf
                    for i in range(M)])
    reach = 2.0 * damping_fit_reach(np.asarray(damping, np.float64) * fr, window)

    def clean(a: NDArray) -> list:
        return [float(x) if np.isfinite(x) else None for x in a]

    sf = np.asarray(ju["frequency_std_hz"], np.float64)
    return {
        **empty,
        "frequency_std_hz": clean(np.where(np.isfinite(sf), np.maximum(sf, floor), np.nan)),
        "frequency_std_noise_hz": clean(sf),
        "damping_lo": clean(ju["damping_lo"]),
        "damping_hi": clean(ju["damping_hi"]),
        "shape_mac_expected": clean(mac),
        "close_mode_bias": [bool(g < max(CLOSE_BINS, r) or m > MAX_MISFIT)
                            for g, r, m in zip(gap, reach, misfit, strict=True)],
        "line_misfit": clean(misfit),
        "damping_unwindowed": clean(z_plain),
        "onset_amplitude_ratio": clean(onset),
        "uncertainty_method": METHOD,
        "uncertainty_groups": {"groups": int(G), "block_px": int(block),
                               "t95": float(ju["t95"][0])},
    }
