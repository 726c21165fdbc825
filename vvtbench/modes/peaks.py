"""Peak picking on the motion power spectrum and per-peak mode analysis.

* :func:`pick_peaks`: automatic peaks of ``log10(power)`` with :func:`scipy.signal.find_peaks`
  (prominence in decades, minimal separation in Hz, band limits, Nyquist check), optionally
  tested against the noise floor (:func:`.significance.noise_floor`).
* :func:`align_phase`: real image-space mode from a complex FFT field, after rotating by the
  phase that maximises the energy of the real part (closed form).
* :func:`translation_mac`: similarity of a mode with the best rigid image translation
  (global camera shake detection).
* :func:`distortion_products`: peaks that are harmonics or intermodulation products
  (``2 f_i``, ``f_i + f_j``, ``|f_i - f_j|``) of stronger peaks, by frequency and power
  (:mod:`.combinations` tells products from true modes at the same frequencies by phase and
  shape, up to third order).

Damping estimation lives in :mod:`.damping`, the noise floor in :mod:`.significance`, mode
merging in :mod:`.merging`.

Image-space modes are arrays ``(H, W, 2)`` (``[..., 0] = dx`` right, ``[..., 1] = dy`` down).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.signal import find_peaks

from .significance import NoiseFloor, noise_floor

__all__ = [
    "Peaks",
    "align_phase",
    "check_band",
    "distortion_products",
    "keyframe_comb",
    "pick_peaks",
    "product_phase_residual",
    "refine_frequency",
    "reliable_fraction",
    "roughness",
    "translation_mac",
    "weighted_smooth",
]


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


# --------------------------------------------------------------------------- peak analysis
def distortion_products(
    frequencies: ArrayLike,
    powers: ArrayLike,
    bin_hz: float,
    *,
    tolerance_bins: float = 0.5,
    power_ratio: float = 0.1,
    parents: ArrayLike | None = None,
    inherit: bool = False,
    fps: float | None = None,
    scaling: str = "weaker",
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
    inherit : bool, default False
        A flagged peak, as a parent, is compared through the weaker of its own parents'
        reference powers instead of its power: a product of a product (``2 f_a - f_b``,
        third order) is then measured against the peaks it comes from, of which it is a far
        smaller fraction than of the faint product it passes through.
    scaling : {"weaker", "product"}, default "weaker"
        The reference power a product is compared with: the weaker parent's, or
        ``P_i P_j / P_max`` (``P_max`` the strongest parent-eligible peak): a product's
        amplitude grows with the product of its parents' amplitudes, so two parents well
        below the strongest peak make a far fainter product than either.  Both agree for the
        products of the strongest peak.
    fps : float, optional
        Sampling rate (Hz).  When given, a product above the Nyquist frequency ``fps / 2``
        is looked for where the sampling folds it: ``c mod fps`` mirrored into
        ``[0, fps / 2]`` (e.g. ``2 x 772 Hz`` at 2000 fps appears at 456 Hz).

    Returns
    -------
    list of dict
        One per flagged peak: ``index``, ``parents`` ``(i, j)``, ``kind`` (``"harmonic"``,
        ``"sum"`` or ``"difference"``), ``expected_hz``, ``power_ratio`` (its power over
        the parents' weaker reference power).

    Examples
    --------
    >>> f, p = [5.0, 7.0, 10.0, 3.0], [100.0, 50.0, 0.05, 0.01]  # 10 = 2 x 5, 3 = 10 - 7
    >>> [d["index"] for d in distortion_products(f, p, 0.1, power_ratio=0.01)]
    [2]
    >>> [d["index"] for d in distortion_products(f, p, 0.1, power_ratio=0.01, inherit=True)]
    [2, 3]
    >>> [d["expected_hz"] for d in distortion_products([40.0, 20.0], [1.0, 1e-3], 0.1, fps=100.0)]
    [20.0]
    """
    f = np.asarray(frequencies, dtype=np.float64)
    p = np.asarray(powers, dtype=np.float64)
    if f.shape != p.shape or f.ndim != 1:
        raise ValueError("frequencies and powers must be 1-D arrays of the same length")
    tol = tolerance_bins * bin_hz
    ok = np.ones(f.size, bool) if parents is None else np.asarray(parents, bool)
    if scaling not in ("weaker", "product"):
        raise ValueError(f"scaling must be 'weaker' or 'product', got {scaling!r}")
    p_max = float(np.max(p[ok])) if np.any(ok) else 1.0
    order = np.argsort(-p, kind="stable")
    ref = p.copy()
    out = []
    for r, k in enumerate(order):
        best = None
        stronger = [i for i in order[:r] if ok[i]]
        for a, i in enumerate(stronger):
            for j in stronger[a:]:
                if p[k] >= power_ratio * _reference(ref[i], ref[j], p_max, scaling):
                    continue
                cands = [("harmonic" if i == j else "sum", f[i] + f[j])]
                if i != j:
                    cands.append(("difference", abs(f[i] - f[j])))
                if fps:
                    cands = [(kind, _folded(c, fps)) for kind, c in cands]
                for kind, c in cands:
                    err = abs(f[k] - c)
                    if err <= tol and (best is None or err < best[0]):
                        best = (err, int(i), int(j), kind, float(c))
        if best is not None:
            base = _reference(ref[best[1]], ref[best[2]], p_max, scaling)
            if inherit:
                ref[k] = base
            out.append(
                {
                    "index": int(k),
                    "parents": (best[1], best[2]),
                    "kind": best[3],
                    "expected_hz": best[4],
                    "power_ratio": float(p[k] / base) if base > 0 else float("inf"),
                }
            )
    return out


def product_phase_residual(phases: ArrayLike, frequencies: ArrayLike, k: int, i: int, j: int,
                           kind: str, *, fps: float | None = None) -> float:
    """Phase of peak ``k`` less that of the ``kind`` product of peaks ``i, j`` (as
    :func:`distortion_products` names it), wrapped to ``[-pi/2, pi/2)``.

    A memoryless non-linearity of the measured motion turns ``cos(w_i t + p_i)`` and
    ``cos(w_j t + p_j)`` into terms at ``w_i + w_j`` with phase ``p_i + p_j`` and at
    ``|w_i - w_j|`` with ``+-(p_i - p_j)``, in every pixel, with the sign of the local
    non-linearity: a product's phase is fixed modulo ``pi`` by its parents', while a mode at
    the product frequency has the phase its excitation gave it (the same as the product's
    after a pluck, which starts every mode at 0: docs/modes.md).  ``phases`` are the phases at the
    record's start (``metadata.phase_rad`` of :func:`.extract.modes_from_displacements`).
    A product folded at the Nyquist frequency (``fps``) has its phase negated.

    >>> f = [5.0, 7.0, 12.0]                     # 12 = 5 + 7
    >>> round(product_phase_residual([0.4, 1.1, 1.5 + np.pi], f, 2, 0, 1, "sum"), 3)
    0.0
    >>> round(product_phase_residual([0.4, 1.1, 0.2], f, 2, 0, 1, "sum"), 3)
    -1.3
    """
    ph = np.asarray(phases, dtype=np.float64)
    f = np.asarray(frequencies, dtype=np.float64)
    if kind == "difference":
        hi, lo = (i, j) if f[i] >= f[j] else (j, i)
        c, expected = f[hi] - f[lo], ph[hi] - ph[lo]
    else:
        c, expected = f[i] + f[j], ph[i] + ph[j]
    if fps and c % fps > fps / 2:
        expected = -expected
    return float((ph[k] - expected + math.pi / 2) % math.pi - math.pi / 2)


def _reference(p_i: float, p_j: float, p_max: float, scaling: str) -> float:
    if scaling == "product" and p_max > 0:
        return p_i * p_j / p_max
    return min(p_i, p_j)


def keyframe_comb(frequencies: ArrayLike, fps: float, gop: int, tolerance_hz: float, *,
                  sampled_fps: float | None = None) -> list[dict[str, Any]]:
    """Peaks on a lossy codec's keyframe comb: within ``tolerance_hz`` of a multiple of
    ``fps / gop``.

    A keyframe every ``gop`` frames changes the compression error of every pixel with that
    period, so the motion of a texture picks up lines at ``m fps / gop`` (``m = 1 ..
    gop - 1``, and their images at ``sampled_fps`` when frames are averaged before the
    spectrum).

    Returns
    -------
    list of dict
        ``{"index", "harmonic", "comb_hz", "line_hz"}`` per peak on the comb.
    """
    f = np.asarray(frequencies, dtype=np.float64)
    if gop is None or int(gop) < 2 or f.size == 0:
        return []
    comb = float(fps) / int(gop)
    seen_at = float(sampled_fps) if sampled_fps else float(fps)
    lines = [(m, _folded(m * comb, seen_at)) for m in range(1, int(gop))]
    out = []
    for i, fi in enumerate(f):
        best = min(lines, key=lambda ml: abs(ml[1] - fi))
        if abs(best[1] - fi) <= tolerance_hz:
            out.append({"index": i, "harmonic": int(best[0]), "comb_hz": comb,
                        "line_hz": float(best[1])})
    return out


def _folded(frequency: float, fps: float) -> float:
    """Where sampling at ``fps`` shows a sinusoid of ``frequency`` Hz: in ``[0, fps / 2]``."""
    r = frequency % fps
    return min(r, fps - r)


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
    a = np.asarray(field, dtype=np.float64)
    w = np.ones(a.shape[:2]) if weights is None else np.asarray(weights, dtype=np.float64)
    num = float(np.sum(w[..., None] * (a - weighted_smooth(a, w, sigma)) ** 2))
    den = float(np.sum(w[..., None] * a**2))
    return num / den if den > 0 else 0.0


def weighted_smooth(field: ArrayLike, weights: ArrayLike, sigma: float) -> NDArray[np.float64]:
    """``G(w a) / G(w)`` per channel of a ``(H, W, C)`` field: the Gaussian (``sigma`` pixels,
    reflecting borders) average of each pixel's neighbourhood weighted by ``w``; 0 where the
    neighbourhood has no weight.

    >>> a = np.zeros((3, 3, 1)); a[1, 1] = 9.0
    >>> w = np.ones((3, 3)); w[1, 1] = 0.0            # the centre does not count
    >>> float(weighted_smooth(a, w, 1.0)[1, 1, 0])
    0.0
    """
    from scipy.ndimage import gaussian_filter

    a = np.asarray(field, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    den = gaussian_filter(w, sigma, mode="reflect")
    ok = den > 1e-12 * max(float(den.max()), 1e-300)
    out = np.empty_like(a)
    for c in range(a.shape[-1]):
        num = gaussian_filter(a[..., c] * w, sigma, mode="reflect")
        out[..., c] = np.divide(num, den, out=np.zeros_like(num), where=ok)
    return out


def reliable_fraction(field: ArrayLike, weights: ArrayLike | None,
                      reliable_weights: ArrayLike | None) -> float:
    """How much of a mode's energy sits on the reliable pixels, relative to all weighted ones.

    ``(sum r e / sum r) / (sum w e / sum w)`` with ``e = |a|**2`` per pixel, ``w`` the shape
    weights and ``r`` the reliability weights (e.g. :func:`.extract.noise_weights`, which are
    ~0 at occlusion edges and texture seams).  About 1 for a field spread like the weights
    (0.15-0.8 for the modes of a rendered cube), near 0 for one that lives on the unreliable
    pixels (the distortion products of a moving silhouette or edge).  1 when ``r`` is ``None``.

    >>> a = np.zeros((4, 4, 2)); a[0, 0] = 1.0        # all energy on pixel (0, 0)
    >>> r = np.ones((4, 4)); r[0, 0] = 0.0            # which is unreliable
    >>> reliable_fraction(a, None, r), reliable_fraction(a, None, None)
    (0.0, 1.0)
    >>> reliable_fraction(np.ones((4, 4, 2)), None, r)  # a uniform field: 1
    1.0
    """
    if reliable_weights is None:
        return 1.0
    e = np.sum(np.abs(np.asarray(field)) ** 2, axis=-1)
    w = np.ones(e.shape) if weights is None else np.asarray(weights, dtype=np.float64)
    r = np.asarray(reliable_weights, dtype=np.float64)
    if r.shape != e.shape or w.shape != e.shape:
        raise ValueError(f"weights {w.shape}, reliable weights {r.shape} and field "
                         f"{e.shape} differ in shape")
    den = float(np.sum(w * e)) * float(r.sum())
    return float(np.sum(r * e)) * float(w.sum()) / den if den > 0 else 1.0


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
