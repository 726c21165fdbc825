"""Damping ratio of a spectral peak.

* :func:`damping_lorentzian` and :func:`damping_half_power`: damping ratio of a peak
  (Davis et al. 2015) from a fit of, or the half-power bandwidth mapped through, the exact
  windowed finite-record spectrum of a decaying sinusoid (:func:`decay_spectrum`).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import brentq, least_squares

from .spectrum import Window

__all__ = [
    "VALLEY_RISE",
    "damping_half_power",
    "damping_lorentzian",
    "decay_spectrum",
    "lorentzian_fit",
]

# a neighbouring peak rises above the valley by more than this factor (~0.5 decade, the
# default prominence); smaller ripples of a noisy periodogram are no valley
VALLEY_RISE = 3.0
#: evaluations of the log-power polish at most: an undamped line's half width sits in a flat
#: valley the noise cannot resolve, where more steps move nothing the interval reports
POLISH_EVALUATIONS = 100


def _valley(p: NDArray[np.float64], k: int, step: int, rise: float = VALLEY_RISE) -> int:
    """Index of the valley next to peak ``k`` in direction ``step``.

    The running minimum from ``k`` on, until the power climbs above ``rise`` times it (a
    neighbouring peak) or the spectrum ends: ripples of a noisy periodogram smaller than
    ``rise`` do not stop the search.
    """
    best = i = k
    while 0 <= i + step < p.size:
        i += step
        if p[i] <= p[best]:
            best = i
        elif p[i] > rise * p[best]:
            break
    return best


def _half_power_edges(
    f: NDArray[np.float64], p: NDArray[np.float64], k: int
) -> tuple[float | None, float | None]:
    """Frequencies below and above ``f[k]`` where the power falls to ``p[k] / 2`` (linear
    interpolation between bins), each ``None`` if not reached before a valley or the edge."""
    half = 0.5 * p[k]
    edges: list[float | None] = []
    for step in (-1, 1):
        stop = _valley(p, k, step)
        i = k
        while i != stop and p[i + step] > half:
            i += step
        if i == stop or p[i + step] > half:
            edges.append(None)
            continue
        j = i + step
        t = (p[i] - half) / (p[i] - p[j])
        edges.append(float(f[i] + t * (f[j] - f[i])))
    return edges[0], edges[1]


def decay_spectrum(
    nu: float, gamma: float, bins: ArrayLike, n_frames: int, window: Window = "none"
) -> tuple[NDArray[np.complex128], NDArray[np.complex128]]:
    """DFT at integer ``bins`` of a sampled decaying complex exponential and its conjugate.

    For ``z = exp(2 pi (-gamma + i nu) / T)`` (frequency ``nu`` and decay rate ``gamma`` in
    bins, ``T = n_frames``) the DFT of ``z**t``, ``t = 0 .. T-1``, at an integer bin ``l`` is
    ``D(l) = (1 - z**T) / (1 - z exp(-2 pi i l / T))`` exactly (finite record included); a
    real mode ``Re(a z**t)`` has ``X_l = (a D+(l) + conj(a) D-(l)) / 2`` with ``D-`` the DFT of
    ``conj(z)**t``.  The periodic Hann window makes ``X_l`` the second difference
    ``D(l) / 2 - (D(l - 1) + D(l + 1)) / 4``.  Mean removal only changes bin 0 (and bin 1
    with Hann).

    Parameters
    ----------
    nu : float
        Damped frequency ``f_d / df`` (bins, ``df = fps / T``).
    gamma : float
        Decay rate ``sigma / (2 pi df)`` (bins), the half width at half maximum of the
        unwindowed peak; ``zeta = gamma / hypot(nu, gamma)``.
    bins : array_like of int
        DFT bins.
    n_frames : int
        ``T``.
    window : {"none", "hann"}
        Taper of the spectrum (see :mod:`.spectrum`).

    Returns
    -------
    d_pos, d_neg : ndarray
        ``D+`` and ``D-`` at ``bins``.
    """
    if window not in ("none", "hann"):
        raise ValueError(f"window must be 'hann' or 'none', got {window!r}")
    (d_pos,), (d_neg,) = _decay_terms(nu, gamma, bins, n_frames, window)
    return d_pos, d_neg


def _decay_terms(
    nu: float, gamma: float, bins: ArrayLike, n_frames: int, window: Window,
    derivatives: bool = False,
) -> list[tuple[NDArray[np.complex128], ...]]:
    """``(D,)``, or ``(D, dD/dnu, dD/dgamma)`` with ``derivatives``, for ``D+`` and ``D-`` of
    :func:`decay_spectrum` (``D = (1 - exp(u)) / (1 - exp(v))``, ``u = 2 pi (-gamma + i s nu)``,
    ``v = (u - 2 pi i m) / T``)."""
    ll = np.asarray(bins, dtype=np.float64)
    T = float(n_frames)
    two_pi = 2.0 * np.pi
    out = []
    for s in (1.0, -1.0):
        u = two_pi * complex(-gamma, s * nu)
        num = -np.expm1(u)

        def parts(m: NDArray[np.float64], s: float = s, u: complex = u,
                  num: complex = num) -> tuple[NDArray, ...]:
            em1 = np.expm1(two_pi * (-gamma + 1j * (s * nu - m)) / T)
            d = num / -em1
            if not derivatives:
                return (d,)
            e_num = np.exp(u)
            ratio = two_pi * (em1 + 1.0) / (T * -em1)
            d_gamma = two_pi * e_num / -em1 - d * ratio
            d_nu = 1j * s * (d * ratio - two_pi * e_num / -em1)
            return d, d_nu, d_gamma

        if window == "none":
            out.append(parts(ll))
        else:
            mid, lo, hi = parts(ll), parts(ll - 1), parts(ll + 1)
            out.append(tuple(0.5 * a - 0.25 * (b + c) for a, b, c in zip(mid, lo, hi,
                                                                         strict=True)))
    return out


def _power(d_pos: NDArray[np.complex128], d_neg: NDArray[np.complex128],
           image: complex) -> NDArray[np.float64]:
    pw = d_pos.real**2 + d_pos.imag**2 + d_neg.real**2 + d_neg.imag**2
    if image:
        pw = pw + 2.0 * np.real(image * d_pos * np.conj(d_neg))
    return pw


def _decay_power_grad(
    nu: float, gamma: float, bins: NDArray, n_frames: int, window: Window, image: complex = 0j
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """:func:`_decay_power` and its derivatives ``(F, 4)`` in ``nu``, ``gamma`` and the real
    and imaginary parts of ``image``."""
    (dp, dp_nu, dp_g), (dn, dn_nu, dn_g) = _decay_terms(nu, gamma, bins, n_frames, window,
                                                        derivatives=True)
    cross = dp * np.conj(dn)
    grads = []
    for a, b in ((dp_nu, dn_nu), (dp_g, dn_g)):
        g = 2.0 * np.real(np.conj(dp) * a + np.conj(dn) * b)
        if image:
            g = g + 2.0 * np.real(image * (a * np.conj(dn) + dp * np.conj(b)))
        grads.append(g)
    grads += [2.0 * cross.real, -2.0 * cross.imag]
    return _power(dp, dn, image), np.stack(grads, axis=1)


def _decay_power(
    nu: float, gamma: float, bins: NDArray, n_frames: int, window: Window, image: complex = 0j
) -> NDArray[np.float64]:
    """``|D+|**2 + |D-|**2 + 2 Re(image D+ conj(D-))``: the power of a real decaying mode up
    to a factor; ``image = a**2 / |a|**2`` (summed over pixels) couples the negative-frequency
    response near DC and Nyquist."""
    return _power(*decay_spectrum(nu, gamma, bins, n_frames, window), image)


def _n_frames_of(f: NDArray[np.float64], n_frames: int | None) -> int:
    T = 2 * (f.size - 1) if n_frames is None else int(n_frames)
    if T // 2 + 1 != f.size:
        raise ValueError(f"n_frames = {T} does not give {f.size} rfft bins")
    return T


def damping_half_power(
    freqs: ArrayLike,
    power: ArrayLike,
    k: int,
    *,
    window: Window = "none",
    n_frames: int | None = None,
) -> float:
    """Damping ratio from the half-power bandwidth of peak ``k``.

    ``f1 < f_k < f2`` are where the power, linearly interpolated between bins, falls to half
    of ``power[k]``, searched up to the neighbouring valleys.  For a peak many bins wide,
    ``zeta = (f2 - f1) / (2 f0)``.  The bandwidth is converted to ``zeta`` through the exact
    spectrum of a decaying sinusoid (:func:`decay_spectrum`) at the same bins, processed the
    same way: this removes the broadening by the window (a Hann peak is >= 1.5 bins wide
    even undamped) and the bias of interpolating between bins.

    Parameters
    ----------
    freqs, power : array_like
        ``(F,)`` spectrum.
    k : int
        Peak bin.
    window : {"none", "hann"}, default "none"
        Window of the spectrum (:func:`.spectrum.motion_power_spectrum`).
    n_frames : int, optional
        Record length ``T``; default ``2 (F - 1)``.

    Returns
    -------
    float
        ``nan`` when a half-power point is not reached before a valley or the spectrum edge,
        or when the bandwidth is narrower than that of an undamped sinusoid (noise).
    """
    if window not in ("none", "hann"):
        raise ValueError(f"window must be 'hann' or 'none', got {window!r}")
    f = np.asarray(freqs, dtype=np.float64)
    p = np.asarray(power, dtype=np.float64)
    lo, hi = _half_power_edges(f, p, k)
    if lo is None or hi is None:
        return float("nan")
    T = _n_frames_of(f, n_frames)
    df = f[1] - f[0]
    width = (hi - lo) / df
    nu = 0.5 * (hi + lo) / df
    reach = int(max(64, 4 * width))
    bins = np.arange(max(k - reach, 0), min(k + reach + 1, f.size), dtype=np.int64)
    fb = bins.astype(np.float64)
    kk = k - int(bins[0])

    def excess(log_gamma: float) -> float:
        m = _decay_power(nu, math.exp(log_gamma), fb, T, window)
        a, b = _half_power_edges(fb, m, kk)
        return float(reach) if a is None or b is None else (b - a) - width

    lg_lo, lg_hi = math.log(1e-4), math.log(max(nu, 2.0))
    try:
        if excess(lg_lo) >= 0:
            return float("nan")
        if excess(lg_hi) <= 0:
            gamma = math.exp(lg_hi)
        else:
            gamma = math.exp(brentq(excess, lg_lo, lg_hi, xtol=1e-6))
    except (ValueError, FloatingPointError, OverflowError):  # pragma: no cover - defensive
        return float("nan")
    return gamma / math.hypot(nu, gamma)


def damping_lorentzian(
    freqs: ArrayLike,
    power: ArrayLike,
    k: int,
    half_width_bins: int | None = None,
    *,
    window: Window = "none",
    n_frames: int | None = None,
) -> tuple[float, float, float]:
    """Damping ratio from a fit of the exact spectrum of a decaying sinusoid around peak ``k``.

    The power of a free decay ``exp(-zeta w0 t) cos(w_d t)`` near ``f_d`` is a Lorentzian of
    half width ``g = zeta f0`` (``f0 = sqrt(f_d**2 + g**2)``).  The model fitted is its exact
    finite-record DFT, :func:`decay_spectrum` (the periodic Lorentzian without window; with
    the Hann window the combination of three shifted ones, whose peak is >= 1.5 bins wide even
    undamped), ``alpha (|D+|**2 + |D-|**2 + 2 Re(b D+ conj(D-))) + c`` with the
    negative-frequency coupling ``|b| <= 1`` (matters near DC and Nyquist) and a noise floor
    ``c``.  ``f_d``, ``g`` and ``b`` are fitted by least squares of the relative residual,
    ``alpha`` and ``c`` solved linearly, over the bins between the neighbouring valleys, at
    most ``half_width_bins`` on each side (bins 0 and, with Hann, 1 excluded: mean removal
    changes them).  Exact for one decaying mode with any decay time and record length.

    Parameters
    ----------
    freqs, power : array_like
        ``(F,)`` spectrum.
    k : int
        Peak bin.
    half_width_bins : int, optional
        Maximal fit half window; default ``max(4, 6 * half-power half width)`` bins
        (at least 6 with Hann).
    window : {"none", "hann"}, default "none"
        Window of the spectrum (:func:`.spectrum.motion_power_spectrum`).
    n_frames : int, optional
        Record length ``T``; default ``2 (F - 1)``.

    Returns
    -------
    zeta : float
        ``g / f0``; ``nan`` if the fit failed or fewer than 5 bins are usable.
    f_d : float
        Fitted peak frequency (Hz).
    g : float
        Fitted half width at half maximum of the unwindowed peak (Hz).  Noise limits how
        small a ``g`` can be told from 0: about ``0.05 fps / T`` for a clean peak.
    """
    return lorentzian_fit(freqs, power, k, half_width_bins, window=window,
                          n_frames=n_frames)[:3]


def lorentzian_fit(freqs: ArrayLike, power: ArrayLike, k: int, half_width_bins: int | None = None,
                   *, window: Window = "none", n_frames: int | None = None,
                   start: NDArray[np.float64] | None = None
                   ) -> tuple[float, float, float, NDArray[np.float64] | None]:
    """:func:`damping_lorentzian` and the fitted parameters (``None`` where it failed), from
    which a fit to a similar spectrum (a jackknife's leave-one-out) can ``start``: it is then
    polished from there in log power, without the first, linear-amplitude stage."""
    f = np.asarray(freqs, dtype=np.float64)
    p = np.asarray(power, dtype=np.float64)
    T = _n_frames_of(f, n_frames)
    if window not in ("none", "hann"):
        raise ValueError(f"window must be 'hann' or 'none', got {window!r}")
    df = f[1] - f[0]
    if half_width_bins is None:
        lo_e, hi_e = _half_power_edges(f, p, k)
        sides = [abs(e - f[k]) / df for e in (lo_e, hi_e) if e is not None and math.isfinite(e)]
        hw = max(sides) if sides else 1.0
        half_width_bins = int(max(6 if window == "hann" else 4, math.ceil(6 * hw)))
    first = 2 if window == "hann" else 1
    lo = max(_valley(p, k, -1), k - half_width_bins, first)
    hi = min(_valley(p, k, 1), k + half_width_bins, f.size - 1)
    bins = np.arange(lo, hi + 1)
    ps = p[lo : hi + 1]
    ok = ps > 0
    failed = float("nan"), float(f[k]), float("nan"), None
    if ok.sum() < 5:
        return failed
    lb_, ps = bins[ok].astype(np.float64), ps[ok]
    wt = 1.0 / ps
    image = ok.sum() >= 8

    def design(y: NDArray[np.float64]) -> NDArray[np.float64]:
        b = complex(y[2], y[3]) if image else 0j
        main = _decay_power(y[0], math.exp(y[1]), lb_, T, window, b)
        return np.stack([main * wt, wt], axis=1)

    def resid(y: NDArray[np.float64]) -> NDArray[np.float64]:
        A = design(y)
        coef, *_ = np.linalg.lstsq(A, np.ones_like(ps), rcond=None)
        return A @ coef - 1.0

    lb = [k - 2.0, math.log(1e-3)] + ([-1.0, -1.0] if image else [])
    ub = [k + 2.0, math.log(max(k + 2.0, 2.0))] + ([1.0, 1.0] if image else [])
    y0 = np.clip([float(k), math.log(0.5)] + [0.0] * (len(lb) - 2), lb, ub)
    lp = np.log(ps)
    n = len(lb)
    c_lo, c_hi = math.log(ps.max() * 1e-20), math.log(ps.max())

    def log_resid(z: NDArray[np.float64]) -> NDArray[np.float64]:
        b = complex(z[2], z[3]) if image else 0j
        m = math.exp(z[n]) * _decay_power(z[0], math.exp(z[1]), lb_, T, window, b)
        return np.log(np.maximum(m + math.exp(z[n + 1]), 1e-300)) - lp

    def log_jac(z: NDArray[np.float64]) -> NDArray[np.float64]:
        b = complex(z[2], z[3]) if image else 0j
        gamma, scale, floor = math.exp(z[1]), math.exp(z[n]), math.exp(z[n + 1])
        pw, grad = _decay_power_grad(z[0], gamma, lb_, T, window, b)
        total = np.maximum(scale * pw + floor, 1e-300)
        grad[:, 1] *= gamma
        cols = [grad[:, :n] * (scale / total)[:, None], (scale * pw / total)[:, None],
                (floor / total)[:, None]]
        return np.hstack(cols)

    try:
        if start is not None and len(start) == n + 2 and np.all(np.isfinite(start)):
            z0 = np.asarray(start, np.float64).copy()
            z0[n + 1] = np.clip(z0[n + 1], c_lo, c_hi)
            a0 = float(z0[n])
        else:
            res = least_squares(resid, y0, bounds=(lb, ub), max_nfev=400)
            coef, *_ = np.linalg.lstsq(design(res.x), np.ones_like(ps), rcond=None)
            if not (np.all(np.isfinite(res.x)) and coef[0] > 0):
                return failed
            a0 = math.log(coef[0])
            z0 = np.r_[res.x, a0, np.clip(math.log(max(coef[1], 1e-30)), c_lo, c_hi)]
        # polish in log power: unbiased under the multiplicative noise of a periodogram
        bounds = (lb + [a0 - 30.0, c_lo], ub + [a0 + 30.0, c_hi])
        res = least_squares(log_resid, np.clip(z0, *bounds), jac=log_jac, bounds=bounds,
                            max_nfev=POLISH_EVALUATIONS, xtol=1e-6, ftol=1e-6)
    except (ValueError, FloatingPointError, OverflowError, np.linalg.LinAlgError):
        return failed
    if not np.all(np.isfinite(res.x)):
        return failed
    fd, g = float(res.x[0] * df), float(math.exp(res.x[1]) * df)
    f0 = math.hypot(fd, g)
    return (g / f0 if f0 > 0 else float("nan")), fd, g, res.x
