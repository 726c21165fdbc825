"""Peak picking on the motion power spectrum and per-peak mode analysis.

* :func:`pick_peaks`: automatic peaks of ``log10(power)`` with :func:`scipy.signal.find_peaks`
  (prominence in decades, minimal separation in Hz, band limits, Nyquist check).
* :func:`align_phase`: real image-space mode from a complex FFT field, after rotating by the
  phase that maximises the energy of the real part (closed form).
* :func:`damping_lorentzian` and :func:`damping_half_power`: damping ratio of a peak
  (Davis et al. 2015) from a fit of, or the half-power bandwidth mapped through, the exact
  windowed finite-record spectrum of a decaying sinusoid (:func:`decay_spectrum`).
* :func:`translation_mac`: similarity of a mode with the best rigid image translation
  (global camera shake detection).
* :func:`merge_modes`: merge modes identified in several videos of the same view.
* :func:`distortion_products`: peaks that are harmonics or intermodulation products
  (``2 f_i``, ``f_i + f_j``, ``|f_i - f_j|``) of stronger peaks.

Image-space modes are arrays ``(H, W, 2)`` (``[..., 0] = dx`` right, ``[..., 1] = dy`` down).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import brentq, least_squares
from scipy.signal import find_peaks

from ..mac import mac
from .spectrum import Window

__all__ = [
    "MergedModes",
    "Peaks",
    "align_phase",
    "check_band",
    "damping_half_power",
    "damping_lorentzian",
    "decay_spectrum",
    "distortion_products",
    "mac",
    "roughness",
    "merge_modes",
    "NoiseFloor",
    "noise_floor",
    "pick_peaks",
    "refine_frequency",
    "translation_mac",
]

# a neighbouring peak rises above the valley by more than this factor (~0.5 decade, the
# default prominence); smaller ripples of a noisy periodogram are no valley
VALLEY_RISE = 3.0


# --------------------------------------------------------------------------- peak picking
def check_band(fps: float, fmin: float | None, fmax: float | None) -> tuple[float, float]:
    """Validate a frequency band against the Nyquist frequency ``fps / 2``.

    Parameters
    ----------
    fps : float
        Frame rate (Hz).
    fmin, fmax : float, optional
        Band limits (Hz); defaults ``0`` and ``fps / 2``.

    Returns
    -------
    tuple of float
        ``(fmin, fmax)``.

    Raises
    ------
    ValueError
        If ``fmax`` exceeds, or ``fmin`` reaches, the Nyquist frequency, or the band is empty
        or negative.
    """
    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    nyq = fps / 2.0
    lo = 0.0 if fmin is None else float(fmin)
    hi = nyq if fmax is None else float(fmax)
    if hi > nyq * (1 + 1e-12):
        raise ValueError(
            f"fmax = {hi:g} Hz exceeds the Nyquist frequency fps/2 = {nyq:g} Hz "
            f"(fps = {fps:g}): motion above {nyq:g} Hz is aliased; lower fmax or film faster"
        )
    if lo >= nyq:
        raise ValueError(
            f"fmin = {lo:g} Hz is not below the Nyquist frequency fps/2 = {nyq:g} Hz "
            f"(fps = {fps:g}): no frequency above {nyq:g} Hz can be measured; allowed "
            f"0 <= fmin < {nyq:g} Hz (lower fmin or film faster)"
        )
    if lo < 0 or lo >= hi:
        raise ValueError(
            f"need 0 <= fmin < fmax <= fps/2 = {nyq:g} Hz (Nyquist), got fmin = {lo:g} Hz, "
            f"fmax = {hi:g} Hz"
        )
    return lo, hi


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


@dataclass(frozen=True)
class Peaks:
    """Picked spectral peaks, sorted by frequency.

    Attributes
    ----------
    bins : ndarray
        ``(k,)`` int, DFT bin of each peak.
    frequencies_hz : ndarray
        ``(k,)`` bin frequencies (Hz).
    prominences : ndarray
        ``(k,)`` prominence in decades of power (``log10`` units).
    floor_ratio : ndarray or None
        ``(k,)`` power over the noise floor ``S_l / m_l`` (when significance was tested).
    noise : NoiseFloor or None
        The floor model used (``false_alarm`` given).
    """

    bins: NDArray[np.int64]
    frequencies_hz: NDArray[np.float64]
    prominences: NDArray[np.float64]
    floor_ratio: NDArray[np.float64] | None = None
    noise: NoiseFloor | None = None

    def __len__(self) -> int:
        return int(self.bins.size)


def pick_peaks(
    freqs: ArrayLike,
    power: ArrayLike,
    fps: float,
    *,
    fmin: float | None = None,
    fmax: float | None = None,
    prominence: float = 0.5,
    min_separation_hz: float | None = None,
    max_peaks: int | None = None,
    min_power_ratio: float = 1e-6,
    false_alarm: float | None = None,
    floor_half_width_bins: int = 32,
    min_bin: int = 1,
) -> Peaks:
    """Automatic peaks of the log power spectrum.

    Parameters
    ----------
    freqs, power : array_like
        ``(F,)`` frequency axis (Hz, uniform, starting at 0) and power spectrum.
    fps : float
        Frame rate (Hz), for the Nyquist check.
    fmin, fmax : float, optional
        Band (Hz) in which peaks are searched; default ``(0, fps / 2]``.  The DC bin is never
        a peak.
    prominence : float, default 0.5
        Minimal prominence of a peak of ``log10(power)`` (decades; 0.5 = a factor 3.2 above
        the higher of its two surrounding valleys).
    min_separation_hz : float, optional
        Minimal distance between peaks (Hz); default one bin.  The more prominent peak wins.
    max_peaks : int, optional
        Keep at most this many, the most prominent.
    min_power_ratio : float, default 1e-6
        Ignore peaks whose power is below this fraction of the strongest peak in the band
        (60 dB; guards against round-off "peaks" in a noise-free spectrum).  The log spectrum
        is also floored at ``1e-12`` times its maximum.
    false_alarm : float, optional
        Test every peak against the noise floor (:func:`noise_floor` over the band's bins):
        peaks whose power is not above ``factor`` times the running median are no modes, so
        that noise alone yields a false peak with at most this probability per spectrum.
        ``None`` (default here; :func:`.extract.extract_modes` uses 0.01) skips the test.
    floor_half_width_bins : int, default 32
        Half width of the running-median window of the floor.
    min_bin : int, default 1
        Lowest bin that may be a peak: the lowest resolvable frequency is about a bin
        (``1 / duration``); slow drift and the mean removal (and the Hann window's main lobe,
        +-2 bins) leave their power in the first bins.  ``extract_modes`` uses 3.

    Returns
    -------
    Peaks

    Raises
    ------
    ValueError
        If the band exceeds the Nyquist frequency (see :func:`check_band`) or the inputs are
        inconsistent.
    """
    f = np.asarray(freqs, dtype=np.float64)
    p = np.asarray(power, dtype=np.float64)
    if f.ndim != 1 or f.shape != p.shape or f.size < 3:
        raise ValueError(
            f"freqs and power must be 1-D of equal length >= 3, got {f.shape}, {p.shape}"
        )
    lo, hi = check_band(fps, fmin, fmax)
    if prominence < 0:
        raise ValueError(f"prominence must be >= 0, got {prominence}")
    if max_peaks is not None and max_peaks < 1:
        raise ValueError(f"max_peaks must be >= 1, got {max_peaks}")
    df = f[1] - f[0]
    floor = np.max(p) * 1e-12 + np.finfo(float).tiny
    logp = np.log10(np.maximum(p, floor))
    distance = 1 if not min_separation_hz else max(1, int(math.ceil(min_separation_hz / df - 1e-9)))
    idx, props = find_peaks(logp, prominence=prominence, distance=distance)
    prom = props["prominences"]
    keep = (idx >= max(1, int(min_bin))) & (f[idx] >= lo) & (f[idx] <= hi)
    idx, prom = idx[keep], prom[keep]
    if idx.size:
        keep = p[idx] >= min_power_ratio * np.max(p[idx])
        idx, prom = idx[keep], prom[keep]
    noise = None
    ratio = None
    if false_alarm is not None:
        inband = np.flatnonzero((f >= lo) & (f <= hi) & (np.arange(f.size) >= max(1, min_bin)))
        sl = slice(int(inband[0]), int(inband[-1]) + 1) if inband.size else slice(1, f.size)
        noise = noise_floor(p, sl, false_alarm=false_alarm,
                            half_width_bins=floor_half_width_bins)
        ratio = p[idx] / noise.floor[idx]
        keep = ratio > noise.factor
        idx, prom, ratio = idx[keep], prom[keep], ratio[keep]
    if max_peaks is not None and idx.size > max_peaks:
        top = np.argsort(-prom, kind="stable")[:max_peaks]
        idx, prom = idx[top], prom[top]
        ratio = None if ratio is None else ratio[top]
    order = np.argsort(idx)
    idx, prom = idx[order].astype(np.int64), prom[order]
    ratio = None if ratio is None else ratio[order]
    return Peaks(bins=idx, frequencies_hz=f[idx], prominences=prom, floor_ratio=ratio,
                 noise=noise)


def refine_frequency(freqs: ArrayLike, power: ArrayLike, k: int) -> float:
    """Sub-bin peak frequency by a parabola through ``log(power)`` at bins ``k-1, k, k+1``."""
    f = np.asarray(freqs, dtype=np.float64)
    p = np.asarray(power, dtype=np.float64)
    if k <= 0 or k >= f.size - 1 or np.any(p[k - 1 : k + 2] <= 0):
        return float(f[k])
    a, b, c = np.log(p[k - 1 : k + 2])
    den = a - 2 * b + c
    if den >= 0:
        return float(f[k])
    delta = float(np.clip(0.5 * (a - c) / den, -0.5, 0.5))
    return float(f[k] + delta * (f[1] - f[0]))


# --------------------------------------------------------------------------- damping
def distortion_products(
    frequencies: ArrayLike,
    powers: ArrayLike,
    bin_hz: float,
    *,
    tolerance_bins: float = 0.5,
    power_ratio: float = 0.1,
    parents: ArrayLike | None = None,
) -> list[dict]:
    """Peaks explained as second-order distortion products of stronger peaks.

    Phase-based motion (and the image formation) is slightly non-linear for motions of the
    order of a pixel: the measured motion of a vibrating object then holds, at about 1 % of
    the modal amplitudes, harmonics ``2 f_i`` and intermodulation products ``f_i + f_j``,
    ``|f_i - f_j|``.  Without spectral leakage to hide them they are clean, narrow peaks.
    A peak ``k`` is flagged when, for two peaks ``i, j`` stronger than it (flagged ones
    included, so products of products are found), ``|f_k - c| <= tolerance_bins * bin_hz``
    for ``c`` in ``{f_i + f_j, |f_i - f_j|}`` (``i = j`` gives ``2 f_i``) and ``P_k <
    power_ratio * min(P_i, P_j)``.  The sub-bin refined frequencies of products match to a
    few hundredths of a bin, but with ~20 peaks a true mode also falls near some product
    now and then (e.g. a cube's mode at 14.9 Hz next to twice 7.5 Hz), so the frequency
    test alone is not enough: :func:`modes_from_displacements` rejects a flagged peak only
    if its shape is also spatially incoherent (:func:`roughness`).

    Parameters
    ----------
    frequencies : array_like
        Refined peak frequencies (Hz).
    powers : array_like
        Peak powers (any consistent unit).
    bin_hz : float
        Frequency resolution ``fps / T`` (Hz).
    tolerance_bins : float, default 0.5
        Frequency tolerance in bins.
    power_ratio : float, default 0.1
        A product is at most this fraction of the weaker parent's power.
    parents : array_like of bool, optional
        Which peaks may be parents (default all).

    Returns
    -------
    list of dict
        One per flagged peak: ``index``, ``parents`` ``(i, j)``, ``kind`` (``"harmonic"``,
        ``"sum"`` or ``"difference"``), ``expected_hz``.
    """
    f = np.asarray(frequencies, dtype=np.float64)
    p = np.asarray(powers, dtype=np.float64)
    if f.shape != p.shape or f.ndim != 1:
        raise ValueError("frequencies and powers must be 1-D arrays of the same length")
    tol = tolerance_bins * bin_hz
    ok = np.ones(f.size, bool) if parents is None else np.asarray(parents, bool)
    order = np.argsort(-p, kind="stable")
    out = []
    for r, k in enumerate(order):
        best = None
        stronger = [i for i in order[:r] if ok[i]]
        for a, i in enumerate(stronger):
            for j in stronger[a:]:
                if p[k] >= power_ratio * min(p[i], p[j]):
                    continue
                cands = [("harmonic" if i == j else "sum", f[i] + f[j])]
                if i != j:
                    cands.append(("difference", abs(f[i] - f[j])))
                for kind, c in cands:
                    err = abs(f[k] - c)
                    if err <= tol and (best is None or err < best[0]):
                        best = (err, int(i), int(j), kind, float(c))
        if best is not None:
            out.append(
                {
                    "index": int(k),
                    "parents": (best[1], best[2]),
                    "kind": best[3],
                    "expected_hz": best[4],
                }
            )
    return out


def roughness(field: ArrayLike, weights: ArrayLike | None = None, sigma: float = 2.0) -> float:
    """Fraction of a mode's energy at fine spatial scales (spatial incoherence), in [0, 1].

    ``sum w |a - G(a)|**2 / sum w |a|**2`` with ``G`` a weight-normalised Gaussian smoothing
    of standard deviation ``sigma`` pixels.  Modes of a physical object vary smoothly over
    the image (a sinusoidal pattern of wavelength 12 px gives ~0.2 at ``sigma = 2``), while
    distortion products of phase-based motion change sign with the texture from pixel to
    pixel (~0.4 and more), as does noise.

    Parameters
    ----------
    field : array_like
        ``(H, W, 2)`` real mode.
    weights : array_like, optional
        ``(H, W)`` pixel weights (e.g. motion confidence), default uniform.
    sigma : float, default 2
        Smoothing scale (pixels of ``field``).

    Returns
    -------
    float
    """
    from scipy.ndimage import gaussian_filter

    a = np.asarray(field, dtype=np.float64)
    w = np.ones(a.shape[:2]) if weights is None else np.asarray(weights, dtype=np.float64)
    ws = gaussian_filter(w, sigma, mode="reflect")
    num = 0.0
    for c in range(a.shape[-1]):
        sm = gaussian_filter(a[..., c] * w, sigma, mode="reflect")
        sm = np.divide(sm, ws, out=np.zeros_like(sm), where=ws > 1e-12 * ws.max())
        num += float(np.sum(w * (a[..., c] - sm) ** 2))
    den = float(np.sum(w[..., None] * a**2))
    return num / den if den > 0 else 0.0


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
    ll = np.asarray(bins, dtype=np.float64)
    T = float(n_frames)
    out = []
    for s in (1.0, -1.0):
        num = -np.expm1(2.0 * np.pi * complex(-gamma, s * nu))

        def D(m: NDArray[np.float64], num: complex = num, s: float = s) -> NDArray:
            return num / -np.expm1(2.0 * np.pi * (-gamma + 1j * (s * nu - m)) / T)

        out.append(D(ll) if window == "none" else 0.5 * D(ll) - 0.25 * (D(ll - 1) + D(ll + 1)))
    return out[0], out[1]


def _decay_power(
    nu: float, gamma: float, bins: NDArray, n_frames: int, window: Window, image: complex = 0j
) -> NDArray[np.float64]:
    """``|D+|**2 + |D-|**2 + 2 Re(image D+ conj(D-))``: the power of a real decaying mode up
    to a factor; ``image = a**2 / |a|**2`` (summed over pixels) couples the negative-frequency
    response near DC and Nyquist."""
    dp, dn = decay_spectrum(nu, gamma, bins, n_frames, window)
    pw = dp.real**2 + dp.imag**2 + dn.real**2 + dn.imag**2
    if image:
        pw = pw + 2.0 * np.real(image * dp * np.conj(dn))
    return pw


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
    f = np.asarray(freqs, dtype=np.float64)
    p = np.asarray(power, dtype=np.float64)
    T = _n_frames_of(f, n_frames)
    if window not in ("none", "hann"):
        raise ValueError(f"window must be 'hann' or 'none', got {window!r}")
    df = f[1] - f[0]
    if half_width_bins is None:
        lo_e, hi_e = _half_power_edges(f, p, k)
        sides = [abs(e - f[k]) / df for e in (lo_e, hi_e) if e is not None]
        hw = max(sides) if sides else 1.0
        half_width_bins = int(max(6 if window == "hann" else 4, math.ceil(6 * hw)))
    first = 2 if window == "hann" else 1
    lo = max(_valley(p, k, -1), k - half_width_bins, first)
    hi = min(_valley(p, k, 1), k + half_width_bins, f.size - 1)
    bins = np.arange(lo, hi + 1)
    ps = p[lo : hi + 1]
    ok = ps > 0
    nan3 = float("nan"), float(f[k]), float("nan")
    if ok.sum() < 5:
        return nan3
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

    try:
        res = least_squares(resid, y0, bounds=(lb, ub), max_nfev=400)
        coef, *_ = np.linalg.lstsq(design(res.x), np.ones_like(ps), rcond=None)
        if not (np.all(np.isfinite(res.x)) and coef[0] > 0):
            return nan3
        # polish in log power: unbiased under the multiplicative noise of a periodogram
        a0 = math.log(coef[0])
        z0 = np.r_[res.x, a0, np.clip(math.log(max(coef[1], 1e-30)), c_lo, c_hi)]
        bounds = (lb + [a0 - 30.0, c_lo], ub + [a0 + 30.0, c_hi])
        res = least_squares(log_resid, np.clip(z0, *bounds), bounds=bounds, max_nfev=400)
    except (ValueError, FloatingPointError, OverflowError, np.linalg.LinAlgError):
        return nan3
    if not np.all(np.isfinite(res.x)):
        return nan3
    fd, g = float(res.x[0] * df), float(math.exp(res.x[1]) * df)
    f0 = math.hypot(fd, g)
    return (g / f0 if f0 > 0 else float("nan")), fd, g


# --------------------------------------------------------------------------- mode shapes
def _wsum(a: NDArray, w: NDArray[np.float64] | None) -> NDArray:
    """Sum over pixels ``(H, W)`` of ``(..., H, W, 2)`` with optional ``(H, W)`` weights."""
    if w is None:
        return a.sum(axis=(-3, -2, -1))
    return np.einsum("...hwc,hw->...", a, w)


def align_phase(
    z: ArrayLike, weights: ArrayLike | None = None
) -> tuple[NDArray[np.float64], float, float]:
    """Real mode from a complex field by the energy-maximising phase rotation.

    ``||Re(exp(-i theta) z)||**2 = (||z||**2 + Re(exp(-2 i theta) sum z**2)) / 2`` is maximal
    for ``theta = angle(sum z**2) / 2`` (weighted sums if ``weights``).  The sign is then
    fixed so that the largest-magnitude entry is positive.

    Parameters
    ----------
    z : array_like
        ``(H, W, 2)`` complex field (e.g. the FFT of the displacements at a peak bin).
    weights : array_like, optional
        ``(H, W)`` non-negative pixel weights.

    Returns
    -------
    real : ndarray
        ``(H, W, 2)`` float64 ``Re(exp(-i theta) z)`` (not normalised).
    theta : float
        Rotation (rad).
    collinearity : float
        ``|sum w z**2| / sum w |z|**2`` in ``[0, 1]``: 1 for a standing (real, synchronous)
        mode, 0 for a travelling / circular one whose real part is ill defined.
    """
    zz = np.asarray(z, dtype=np.complex128)
    w = None if weights is None else np.asarray(weights, dtype=np.float64)
    s2 = complex(_wsum(zz * zz, w))
    e = float(_wsum(np.abs(zz) ** 2, w))
    theta = 0.5 * math.atan2(s2.imag, s2.real)
    real = (zz * np.exp(-1j * theta)).real
    i = int(np.argmax(np.abs(real)))
    if real.flat[i] < 0:
        real = -real
        theta += math.pi
    return real, theta, (abs(s2) / e if e > 0 else 0.0)


def translation_mac(z: ArrayLike, weights: ArrayLike | None = None) -> float:
    """MAC between a field ``(H, W, 2)`` and its best rigid translation.

    The best (least-squares) translation is the weighted mean vector ``t``; the MAC reduces
    to the fraction of the field's energy explained by it,
    ``|sum w z|**2 / (sum w * sum w |z|**2)``.  Close to 1 for global camera shake.
    """
    zz = np.asarray(z)
    if zz.ndim != 3 or zz.shape[-1] != 2:
        raise ValueError(f"field must be (H, W, 2), got {zz.shape}")
    w = np.ones(zz.shape[:2]) if weights is None else np.asarray(weights, dtype=np.float64)
    sw = float(w.sum())
    mean = np.einsum("hwc,hw->c", zz, w)
    e = float(np.einsum("hwc,hw->", np.abs(zz) ** 2, w))
    if sw <= 0 or e <= 0:
        return 0.0
    return float(np.sum(np.abs(mean) ** 2) / (sw * e))


# --------------------------------------------------------------------------- merging
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
