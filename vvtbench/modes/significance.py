"""Significance of spectral peaks: the noise floor of the motion spectrum.

* :class:`NoiseFloor` and :func:`noise_floor`: running-median floor of a motion power
  spectrum, the fitted chi-square law of the power around it and the detection threshold
  for a false-alarm rate (see docs/modes.md, "Peak significance").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import brentq

__all__ = ["NoiseFloor", "noise_floor"]


@dataclass(frozen=True)
class NoiseFloor:
    """Model of the motion spectrum's noise floor (:func:`noise_floor`).

    Attributes
    ----------
    floor : ndarray
        ``(F,)`` running median of the power, ``m_l`` (same unit as the power).
    nu : float
        Effective degrees of freedom of the power's scaled chi-square distribution,
        ``S_l ~ m_l chi2_nu / med(chi2_nu)`` (2 = one periodogram, ``2B`` = ``B`` averages).
    factor : float
        Detection threshold over the floor: a bin is significant when ``S_l > factor m_l``.
    false_alarm : float
        Probability that noise alone puts at least one of ``n_bins`` bins above threshold.
    n_bins : int
        Bins tested (the band).
    half_width_bins : int
        Half width of the running-median window.
    """

    floor: NDArray[np.float64]
    nu: float
    factor: float
    false_alarm: float
    n_bins: int
    half_width_bins: int

    def threshold(self) -> NDArray[np.float64]:
        """``factor * floor``, the power a peak must exceed."""
        return self.factor * self.floor

    def summary(self) -> dict:
        """JSON-ready scalars."""
        return {
            "nu": float(self.nu),
            "factor": float(self.factor),
            "false_alarm": float(self.false_alarm),
            "n_bins": int(self.n_bins),
            "half_width_bins": int(self.half_width_bins),
        }


def _log_chi2_iqr(nu: float) -> tuple[float, float]:
    """Interquartile range of ``log chi2_nu`` and its sampling s.d. per ``sqrt(n)`` bins."""
    from scipy.stats import chi2

    q = chi2.ppf([0.25, 0.75], nu)
    g = chi2.pdf(q, nu) * q  # density of log chi2 at its quartiles
    # asymptotic variances of sample quantiles and their covariance (p1 < p2)
    v1, v2, c12 = 0.1875 / g[0] ** 2, 0.1875 / g[1] ** 2, 0.0625 / (g[0] * g[1])
    return float(np.log(q[1] / q[0])), float(math.sqrt(max(v1 + v2 - 2 * c12, 0.0)))


def _fit_nu(iqr_log: float) -> float:
    """Degrees of freedom ``nu`` whose ``log chi2_nu`` has interquartile range ``iqr_log``."""
    lo, hi = 2.0, 1e7
    if not iqr_log < _log_chi2_iqr(lo)[0]:
        return lo
    if iqr_log <= _log_chi2_iqr(hi)[0]:
        return hi
    return float(math.exp(brentq(lambda x: _log_chi2_iqr(math.exp(x))[0] - iqr_log,
                                 math.log(lo), math.log(hi), xtol=1e-4)))


def _median_log_sd(nu: float, n: int) -> float:
    """S.d. of the log of the sample median of ``n`` draws of ``chi2_nu`` (asymptotic)."""
    from scipy.stats import chi2

    m = chi2.median(nu)
    return float(1.0 / (2.0 * math.sqrt(max(n, 1)) * chi2.pdf(m, nu) * m))


def _threshold_factor(nu: float, per_bin: float, sd_log_floor: float) -> float:
    """``c`` with ``E[P(chi2_nu > c med(chi2_nu) exp(e))] = per_bin``, ``e ~ N(0, sd**2)``:
    the tail probability over a floor that is itself estimated (Gauss-Hermite average)."""
    from scipy.stats import chi2

    m = chi2.median(nu)
    x, w = np.polynomial.hermite_e.hermegauss(24)
    w = w / w.sum()
    e = np.exp(sd_log_floor * x)

    def tail(log_c: float) -> float:
        return float(np.log(np.sum(w * chi2.sf(math.exp(log_c) * m * e, nu)) + 1e-300)
                     - math.log(per_bin))

    c0 = chi2.isf(per_bin, nu) / m
    hi = math.log(c0) + 8.0 * sd_log_floor + 1.0
    if tail(math.log(c0)) <= 0:
        return float(c0)
    return float(math.exp(brentq(tail, math.log(c0), hi, xtol=1e-6)))


def noise_floor(
    power: ArrayLike,
    band: slice | None = None,
    *,
    false_alarm: float = 0.01,
    half_width_bins: int = 32,
    min_nu: float = 2.0,
) -> NoiseFloor:
    """Noise floor of a motion power spectrum and the threshold for a false-alarm rate.

    Model (see docs/modes.md, "Peak significance"): away from spectral lines the power at
    bin ``l`` is ``S_l = m_l X_l / med(chi2_nu)``, ``X_l ~ chi2_nu`` (a weighted sum of
    per-pixel periodograms of correlated noise: 2 d.o.f. per independent pixel group, so
    ``nu >= 2``), with a slowly varying level ``m_l``, its median.

    * ``m_l``: median of ``S`` over ``l - K .. l + K`` (``K = half_width_bins``, clipped at the
      ends): robust to lines as long as they cover less than half of the window.
    * ``nu``: from the interquartile range of ``log(S_l / m_l)`` over all bins from the
      band's first one to Nyquist (a narrow band full of modes says little about the noise),
      matched to
      that of ``log chi2_nu`` (robust to a quarter of the bins being lines), at least
      ``min_nu``.  Lines and a non-stationary floor widen it: ``nu`` is then underestimated
      and the threshold errs on the safe side.
    * threshold: ``P(S_l > c m_l) = p`` per bin with ``p = 1 - (1 - false_alarm)**(1/N)``
      over the ``N`` bins of the band, so that noise puts no bin above it with probability
      ``1 - false_alarm``: ``c = chi2.isf(p, nu) / chi2.median(nu)``.  For ``nu = 2``
      (exponential power) ``c = log2(1/p)``: ``N = 1000``, ``false_alarm = 0.01`` gives
      ``c = 16.6`` (1.22 decades).  Neighbouring bins of a windowed spectrum are correlated,
      which only lowers the true false-alarm rate.

    Parameters
    ----------
    power : array_like
        ``(F,)`` motion power spectrum.
    band : slice, optional
        Bins tested (default all but bin 0).
    false_alarm : float, default 0.01
        Probability, per spectrum, that pure noise yields one or more significant bins.
    half_width_bins : int, default 32
        ``K``.
    min_nu : float, default 2
        Lower bound of ``nu``.

    Returns
    -------
    NoiseFloor
    """
    from scipy.ndimage import median_filter

    p = np.asarray(power, dtype=np.float64)
    if p.ndim != 1 or p.size < 3:
        raise ValueError(f"power must be 1-D with >= 3 bins, got shape {p.shape}")
    if not 0 < false_alarm < 1:
        raise ValueError(f"false_alarm must be in (0, 1), got {false_alarm}")
    K = max(1, int(half_width_bins))
    tiny = max(float(np.max(p)), 1e-300) * 1e-15
    pp = np.maximum(p, tiny)
    band = slice(1, p.size) if band is None else band
    # the bins below the band (DC, drift, the mean removal) are left out of the median, and
    # the ends are mirrored: a replicated end value would dominate the window there
    first = min(max(1, int(band.start or 0)), p.size - 2)
    seg = pp[first:]
    floor = np.empty_like(pp)
    floor[first:] = median_filter(seg, size=min(2 * K + 1, 2 * ((seg.size - 1) // 2) + 1),
                                  mode="mirror")
    floor[:first] = floor[first]
    n = int(pp[band].size)
    # the noise law is estimated over the whole spectrum above the lowest band bin (more
    # bins, mostly noise, than a narrow band full of modes), the test made in the band
    r = np.log(pp[first:] / floor[first:])
    # neighbouring bins of a tapered spectrum are correlated (Hann: ~2 per independent one)
    n_ind = max(1, r.size // 2)
    if r.size >= 8:
        q25, q75 = np.percentile(r, [25, 75])
        iqr = float(q75 - q25)
        # one-sided 95 % upper bound of the IQR (lower bound of nu): an overestimated nu
        # would lower the threshold
        _, sd = _log_chi2_iqr(_fit_nu(iqr))
        nu = max(float(min_nu), _fit_nu(iqr + 1.645 * sd / math.sqrt(n_ind)))
    else:
        nu = float(min_nu)
    per_bin = -math.expm1(math.log1p(-false_alarm) / max(n, 1))
    win = min(2 * K + 1, p.size)
    factor = _threshold_factor(nu, per_bin, _median_log_sd(nu, max(1, win // 2)))
    return NoiseFloor(floor=floor, nu=nu, factor=factor, false_alarm=float(false_alarm),
                      n_bins=n, half_width_bins=K)
