"""End-to-end image-space mode extraction: video -> displacements -> spectrum -> modes.

Pipeline (paper Sec. 4.1, automated): frames are streamed through :class:`PhaseMotion`
(reference = the temporal mean of the record after averaging, a first pass over it),
displacement batches go to a
:class:`DisplacementStore` (RAM up to ``memory_budget``, then a temporary file), the motion
power spectrum and the complex fields at the picked peaks are computed by pixel blocks, and
each peak becomes a real, phase-aligned, unit-norm mode with a damping ratio.  Peaks whose
mode is a near-uniform translation are flagged as camera shake and dropped unless asked.
"""

from __future__ import annotations

import logging
import math
import sys
import time
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..motion.phase import upsample_periodic
from ..video.files import FrameSpool, average_frames, mean_frame, open_video
from .damping import damping_half_power, damping_lorentzian
from .jackknife import peak_uncertainty
from .lines import Lines, clean_lines, peak_gain
from .modeset import ModeSet
from .peaks import (
    Peaks,
    align_phase,
    check_band,
    distortion_products,
    keyframe_comb,
    pick_peaks,
    product_phase_residual,
    refine_frequency,
    reliable_fraction,
    roughness,
    translation_mac,
    weighted_smooth,
)
from .significance import noise_floor
from .spectrum import (
    DEFAULT_BUDGET,
    DisplacementStore,
    Window,
    bin_fields,
    motion_power_spectrum,
    pixel_noise_power,
    window_gain,
)
from .uncertainty import LINE_FIT_METHOD, block_clusters, mode_uncertainty

__all__ = ["confidence_weights", "noise_weights", "noisy_pixel_attenuation",
           "fill_unreliable_pixels", "extract_modes",
           "modes_from_displacements"]

_log = logging.getLogger(__name__)


def confidence_weights(confidence: ArrayLike, quantile: float = 0.9) -> NDArray[np.float64]:
    """Pixel weights ``min(confidence / q, 1)`` with ``q`` the ``quantile`` of the confidence.

    Saturating keeps a few very high-contrast pixels from dominating the statistics.
    """
    c = np.asarray(confidence, dtype=np.float64)
    q = float(np.quantile(c, quantile))
    if not q > 0:
        return np.ones_like(c)
    return np.minimum(c / q, 1.0)


def noise_weights(
    weights: ArrayLike, noise: ArrayLike, floor_quantile: float = 0.05
) -> NDArray[np.float64]:
    """``weights / noise``, scaled to a maximum of 1: inverse-variance pixel weights.

    ``noise`` is each pixel's motion noise power (:func:`spectrum.pixel_noise_power`),
    floored at its ``floor_quantile`` over the pixels of positive weight so that motionless,
    noise-free pixels do not take all the weight. Summing per-pixel power with inverse noise
    weights is the detection statistic for a line seen in every pixel (a whitened sum).

    >>> noise_weights(np.ones((1, 3)), np.array([[1.0, 4.0, 0.0]]), 0.5).round(3).tolist()
    [[1.0, 0.25, 1.0]]
    """
    w = np.asarray(weights, dtype=np.float64)
    n = np.asarray(noise, dtype=np.float64)
    if w.shape != n.shape:
        raise ValueError(f"weights {w.shape} and noise {n.shape} differ in shape")
    positive = (w > 0) & np.isfinite(n)
    if not positive.any():
        return w.copy()
    floor = float(np.quantile(n[positive], floor_quantile))
    if not floor > 0:
        floor = float(n[positive][n[positive] > 0].min()) if (n[positive] > 0).any() else 1.0
    out = np.where(positive, w / np.maximum(n, floor), 0.0)
    return out / out.max() if out.max() > 0 else out


def noisy_pixel_attenuation(
    noise: ArrayLike, weights: ArrayLike | None = None, quantile: float = 0.9,
    factor: float = 10.0,
) -> NDArray[np.float64]:
    """Per-pixel factors ``sqrt(min(1, factor q / N_p))`` for mode shapes, ``q`` the
    ``quantile`` of the motion noise power ``N_p`` over the pixels of positive weight.

    Pixels at occlusion edges and texture seams measure motion far less reliably than the
    rest (their noise power is decades above the median on a rendered cube) and their error
    is largely coherent with the motion, so it sits at the mode's own frequency: left as they
    are, a weak mode's unit-norm shape can hold most of its energy in 1 % of the pixels.  The
    pixels more than ``factor`` times noisier than the ``quantile`` are attenuated by the
    square root of their excess; an evenly textured image keeps every pixel.

    >>> noisy_pixel_attenuation(np.array([1.0, 1.0, 1.0, 5.0, 1000.0]), quantile=0.5).tolist()
    [1.0, 1.0, 1.0, 1.0, 0.1]
    """
    n = np.asarray(noise, dtype=np.float64)
    if not 0 < quantile <= 1:
        raise ValueError(f"quantile must be in (0, 1], got {quantile}")
    if not 0 < factor < np.inf:
        raise ValueError(f"factor must be a finite number > 0, got {factor}")
    sel = n if weights is None else n[np.asarray(weights) > 0]
    sel = sel[np.isfinite(sel)]
    q = float(np.quantile(sel, quantile)) if sel.size else 0.0
    if not q > 0:
        return np.ones_like(n)
    n = np.where(np.isnan(n), np.inf, n)  # an unmeasurable pixel is the least reliable
    return np.sqrt(np.minimum(1.0, factor * q / np.maximum(n, 1e-300)))


def fill_unreliable_pixels(
    field: ArrayLike, reliability: ArrayLike, weights: ArrayLike | None = None,
    sigma: float = 2.0,
) -> NDArray[np.float64]:
    """Unreliable pixels of a ``(H, W, C)`` field filled in from their reliable neighbours.

    ``r a + (1 - r) G(w r a) / G(w r)``: each pixel keeps the fraction ``r`` (``reliability``,
    in ``[0, 1]``, e.g. the square of :func:`noisy_pixel_attenuation`) of its own value and
    takes the rest from the Gaussian (``sigma`` pixels) average of its neighbours weighted by
    ``w r``.  Unlike an attenuation it does not pull a seam or edge pixel towards zero, which
    would bias what is read there (an object's vertices sit on its edges); a pixel with no
    reliable neighbour keeps ``r a``.

    >>> a = np.ones((5, 5, 1)); a[2, 2] = 50.0            # one unreliable pixel, read 50x
    >>> r = np.ones((5, 5)); r[2, 2] = 0.0
    >>> float(fill_unreliable_pixels(a, r, sigma=1.0)[2, 2, 0])
    1.0
    """
    a = np.asarray(field, dtype=np.float64)
    r = np.clip(np.asarray(reliability, dtype=np.float64), 0.0, 1.0)
    w = (np.ones(r.shape) if weights is None else np.asarray(weights, dtype=np.float64)) * r
    return r[..., None] * a + (1.0 - r[..., None]) * weighted_smooth(a, w, sigma)


def modes_from_displacements(
    disp: DisplacementStore | ArrayLike,
    fps: float,
    *,
    weights: ArrayLike | None = None,
    fmin: float | None = None,
    fmax: float | None = None,
    prominence: float = 0.5,
    min_separation_hz: float | None = None,
    max_modes: int | None = None,
    min_power_ratio: float = 1e-6,
    detrend: str = "mean",
    window: Window = "hann",
    shake_threshold: float = 0.9,
    keep_camera_shake: bool = False,
    reject_distortion: bool = True,
    max_roughness: float = 0.3,
    product_roughness: float = 0.15,
    faint_product_ratio: float | None = 0.01,
    product_scaling: str = "product",
    rough_sigma_px: float = 2.0,
    block_bytes: int = 64 << 20,
    confidence: ArrayLike | None = None,
    metadata: dict[str, Any] | None = None,
    output_shape: tuple[int, int] | None = None,
    false_alarm: float | None = 0.01,
    floor_half_width_bins: int = 32,
    min_bin: int = 3,
    shoulder_prominence: float | None = 0.05,
    shoulder_mac: float = 0.5,
    shoulder_bins: int = 6,
    line_fit: bool = False,
    line_radius: int = 4,
    added_roughness: float | None = 0.06,
    spectrum_weights: ArrayLike | None = None,
    shape_noise: ArrayLike | None = None,
    shape_noise_quantile: float = 0.9,
    shape_noise_factor: float = 10.0,
    shape_fill: bool = False,
    roughness_weighting: str = "shape",
    min_reliable_fraction: float | None = None,
    unreliable_roughness: float = 0.06,
    identifier: str = "peaks",
    excitation: str | None = None,
    pole_options: Mapping[str, Any] | None = None,
    pole_products: bool = True,
) -> ModeSet:
    """Identify image-space modes from displacement fields.

    Parameters
    ----------
    disp : DisplacementStore or array_like
        ``(T, H, W, 2)`` displacements (px).
    fps : float
        Frame rate (Hz) of ``disp``.
    weights : array_like, optional
        ``(H, W)`` pixel weights for the power spectrum, the phase alignment and the camera
        shake test (e.g. :func:`confidence_weights`); default uniform.
    spectrum_weights : array_like, optional
        Other ``(H, W)`` weights for the power spectrum the peaks are picked from (e.g.
        :func:`noise_weights`); ``weights`` still serve the shapes and the shake, coherence
        and distortion tests. Default: ``weights``.
    fmin, fmax, prominence, min_separation_hz, min_power_ratio : optional
        Peak picking, see :func:`peaks.pick_peaks` (``fmax > fps / 2`` raises ValueError).
    max_modes : int, optional
        Most prominent peaks analysed (before camera-shake rejection); default: every
        significant peak (the noise-floor test bounds the false ones, a cap only loses modes:
        rendered cubes have 38-42 detectable modes below 200 Hz).
    detrend : {"mean", "linear", "none"}
        Per-pixel temporal detrending.
    window : {"hann", "none"}, default "hann"
        Temporal taper before the FFT (:mod:`.spectrum`): Hann keeps the leakage of strong
        undamped modes (sidelobes ~ 1/k with "none") from masking weak modes and from
        contaminating their shapes; peaks are about 2 bins wide instead of 1.  Damping is
        fitted with the exact response of the window used (:func:`damping.damping_lorentzian`,
        :func:`damping.damping_half_power`).
    shake_threshold : float, default 0.9
        A peak with translation MAC above it is flagged ``camera_shake``.
    keep_camera_shake : bool, default False
        Keep flagged peaks in the result (otherwise listed in ``metadata["rejected"]``).
    reject_distortion : bool, default True
        Drop peaks whose shape is spatially incoherent (:func:`peaks.roughness` at
        ``rough_sigma_px`` full-resolution pixels above ``max_roughness``: no mode of an
        object varies that fast; reason ``"incoherent"``), and peaks that are harmonics /
        intermodulation products of stronger peaks (:func:`peaks.distortion_products`, at
        most half the weaker parent's power) with a roughness above ``product_roughness``
        (reason ``"distortion"``).  Second-order products of phase-based motion change sign
        with the texture (roughness ~0.3-0.5 at 256^2) while true modes are smooth (< 0.1);
        a true mode that happens to sit at a product frequency is kept.  Listed in
        ``metadata["rejected"]``.
    max_roughness, product_roughness, rough_sigma_px : float
        See ``reject_distortion``.
    faint_product_ratio : float or None, default 0.01
        With ``reject_distortion``: a product of two stronger peaks with less than this
        fraction of the weaker parent's power is rejected as ``"distortion"`` whatever its
        roughness (products of a small object or a noisy video are smooth; a true mode at a
        product frequency is rarely that faint: 0.012-0.95 on validation cubes, products
        0.0004-0.005).  ``None`` or 0 turns it off.
    shape_noise : array_like, optional
        ``(h, w)`` motion noise power of each grid pixel (:func:`spectrum.pixel_noise_power`):
        the mode shapes are multiplied by :func:`noisy_pixel_attenuation` (after the
        roughness tests), so that the least reliable pixels do not dominate a weak mode's
        shape.  Default: no attenuation.
    shape_noise_quantile, shape_noise_factor : float, default 0.9 and 10
        Pixels more than ``shape_noise_factor`` times noisier than this quantile are
        attenuated.
    shape_fill : bool, default False
        With ``shape_noise``: instead of attenuating the noisy pixels, fill them in from their
        reliable neighbours (:func:`fill_unreliable_pixels` with the attenuation's square as
        reliability, ``rough_sigma_px`` full-resolution pixels): the shape is cleaned without
        pulling the edge pixels towards zero (docs/modes.md, "Reliable pixels").
    product_scaling : {"product", "weaker"}, default "product"
        The power a faint product is compared with (:func:`peaks.distortion_products`'
        ``scaling``): ``P_i P_j / P_max``, since a product grows with both parents'
        amplitudes (a mode at the sum of two peaks well below the strongest is not taken
        for their product), or the weaker parent's power.
    block_bytes : int
        Working memory per pixel block of the FFT.
    confidence : array_like, optional
        Stored in the result.
    metadata : dict, optional
        Extra provenance stored in the result.
    output_shape : tuple of int, optional
        ``(H, W)`` of the frames when ``disp`` lives on a coarser working grid (e.g.
        :attr:`PhaseMotion.grid_shape`, sample ``(i, j)`` at pixel ``(i H / h, j W / w)``):
        each real mode is upsampled bilinearly (periodic) to it before normalisation, so
        shapes and amplitudes refer to full-resolution pixels.  ``weights`` stay on the grid.
    false_alarm : float or None, default 0.01
        Peak significance: a peak must stand above the spectrum's noise floor
        (:func:`significance.noise_floor`, a running median and a fitted chi-square law) by the
        factor for which pure noise yields a false peak anywhere in the band with at most
        this probability; ``None`` turns the test off.  See docs/modes.md.
    floor_half_width_bins : int, default 32
        Half width of the noise floor's running-median window (bins).
    min_bin : int, default 3
        Lowest peak bin: frequencies below ``min_bin / duration`` (drift, the mean removal
        and the Hann main lobe around DC) are not modes.
    shoulder_prominence, shoulder_mac, shoulder_bins :
        Resolved shoulders (docs/modes.md): a significant local maximum whose prominence is
        below ``prominence`` but at least ``shoulder_prominence`` (decades), and which has a
        stronger peak within ``shoulder_bins`` bins, is a mode of its own when its complex
        field differs from those of all such stronger peaks (complex MAC below
        ``shoulder_mac``): a mode standing on the flank of a stronger neighbour has its own
        shape, while the flank, the window's sidelobes and noise wiggles on them have the
        neighbour's.  Kept ones count against ``max_modes`` after the prominent peaks.
        ``None`` turns this off.
    line_fit : bool, default False
        Multi-channel line fit (:mod:`.lines`, docs/modes.md "Line fit"): the picked peaks
        become lines fitted with the window's exact kernel to the complex fields of every
        pixel at the ``line_radius`` bins around them (close modes under one peak separate,
        frequency, damping and amplitude come from the fit), and significant lines of the
        residual spectrum with a shape of their own are added (up to ``max_modes`` in all).
    line_radius : int, default 4
        Bins on either side of each line in its fit.
    added_roughness : float or None, default 0.06
        With ``line_fit``: a line the residual search added (weak by construction) is
        dropped when its shape's roughness is above this (reason ``"weak_incoherent"``);
        ``None`` keeps the ``max_roughness`` test alone.  0.06 was chosen on validation
        videos in no suite (docs/modes.md, "Line fit").
    roughness_weighting : {"shape", "spectrum"}, default "shape"
        Pixel weights of the roughness tests (``max_roughness``, ``product_roughness``,
        ``added_roughness``): ``weights`` (the shapes'), or ``spectrum_weights`` (e.g.
        :func:`noise_weights`, which leave out the pixels at occlusion edges and texture
        seams whose motion carries the video's distortion products, so a weak mode is judged
        on the faces it moves; docs/modes.md, "Reliable pixels").  Same without
        ``spectrum_weights``.
    min_reliable_fraction : float or None, default None
        Drop a peak (reason ``"unreliable"``) whose shape's mean energy per unit
        ``spectrum_weights`` is below this fraction of its mean energy per unit ``weights``
        (:func:`reliable_fraction`, stored for every analysed peak in
        ``metadata["reliable_fraction"]``): a line that lives on the unreliable pixels
        (occlusion edges, seams) is not the motion of the object, provided it is also rough
        under ``weights`` (:func:`peaks.roughness` above ``unreliable_roughness``, stored in
        ``metadata["roughness_shape"]``): a smooth line is coherent wherever it lives (e.g. a
        mode of a face seen at a grazing angle, whose pixels are all noisier).  ``None`` turns
        it off.
    unreliable_roughness : float, default 0.06
        See ``min_reliable_fraction``.
    identifier : {"peaks", "auto", "era", "plscf"}, default "peaks"
        How modes are identified: the peak picker (everything above), ERA on the free decay
        or pLSCF on positive power spectra over reduced channels with a stabilisation diagram
        (:mod:`.poles`), or ``"auto"``: ERA for a free decay, the peak picker for a driven
        record, decided by ``excitation`` when given, else by the envelope of the motion
        (:func:`.poles.decide_identifier`); the peak picker for a record of fewer than
        :data:`.record.MIN_FRAMES` frames or when the scan finds no stable pole.
        ``metadata["identifier"]`` records the request,
        the identifier used and why.
    excitation : str, optional
        How the object was set moving (a scene's ``excitation.kind``: ``"pluck"``,
        ``"velocity"``, ``"force"``, ...), for ``identifier="auto"``.
    pole_options : mapping, optional
        Options of :func:`.poles.scan_poles` (``block``, ``n_components``, ``max_order``,
        ``f_tol``, ...) and ``"products"``: options of
        :func:`.products.find_pole_products`.
    pole_products : bool, default True
        With a pole-based identifier: reject the modes that are products of stronger ones by
        frequency, decay, phase and shape together (:mod:`.products`).

    Returns
    -------
    ModeSet
    """
    band = check_band(fps, fmin, fmax)
    if identifier not in ("peaks", "auto", "era", "plscf"):
        raise ValueError(f"identifier must be 'peaks', 'auto', 'era' or 'plscf', got "
                         f"{identifier!r}")
    if identifier != "peaks":
        from .poles import FORCED_EXCITATIONS, decide_identifier, pole_modes, scan_poles
        from .reduce import block_channels

        popts = dict(pole_options or {})
        product_options = popts.pop("products", None)
        sw_ = weights if spectrum_weights is None else spectrum_weights
        lo_band = (max(band[0], min_bin * float(fps) / _n_frames(disp)), band[1])
        channels = None
        if identifier == "auto":
            from .record import MIN_FRAMES

            if excitation is not None and str(excitation).lower() in FORCED_EXCITATIONS:
                used, reason = decide_identifier(excitation=excitation)
            elif _n_frames(disp) < MIN_FRAMES:
                used, reason = "peaks", (f"a short record ({_n_frames(disp)} frames, under "
                                         f"{MIN_FRAMES}): too few for a model-order scan to "
                                         "settle")
            else:
                channels = block_channels(disp, weights=sw_, block=int(popts.get("block", 8)),
                                          block_bytes=block_bytes)
                used, reason = decide_identifier(channels.data, excitation=excitation)
        else:
            used, reason = identifier, "asked for"
        record = {"requested": identifier, "used": used, "reason": reason,
                  "excitation": excitation}
        scan = None
        if used != "peaks":
            try:
                scan = scan_poles(disp, fps, method=used, weights=sw_, band=lo_band,
                                  channels=channels, **popts)
            except ValueError as error:
                if identifier != "auto" or "too short" not in str(error):
                    raise
                used, reason = "peaks", f"{reason}; but {error}"
                record.update(used=used, reason=reason)
        if scan is not None and identifier == "auto" and not scan.clusters:
            used, reason = "peaks", (f"{reason}; but {scan.method.upper()} found no pole "
                                     "stable over model orders: the peak picker ran")
            record.update(used=used, reason=reason)
            scan = None
        if scan is not None:
            meta = {**dict(metadata or {}), "identifier": record, "min_bin": int(min_bin),
                    "weighted": weights is not None}
            return pole_modes(disp, fps, scan, band=lo_band, weights=weights,
                              spectrum_weights=spectrum_weights, output_shape=output_shape,
                              confidence=confidence, metadata=meta,
                              shake_threshold=shake_threshold,
                              keep_camera_shake=keep_camera_shake,
                              reject_products=pole_products and reject_distortion,
                              product_options=product_options, max_roughness=max_roughness,
                              rough_sigma_px=rough_sigma_px, min_power_ratio=min_power_ratio,
                              block_bytes=block_bytes)
        metadata = {**dict(metadata or {}), "identifier": record}
    else:
        metadata = {**dict(metadata or {}),
                    "identifier": {"requested": "peaks", "used": "peaks", "reason": "asked for",
                                   "excitation": excitation}}
    if roughness_weighting not in ("shape", "spectrum"):
        raise ValueError(f"roughness_weighting must be 'shape' or 'spectrum', got "
                         f"{roughness_weighting!r}")
    if min_reliable_fraction is not None and not min_reliable_fraction >= 0:
        raise ValueError(f"min_reliable_fraction must be >= 0 or None, got "
                         f"{min_reliable_fraction!r}")
    if not unreliable_roughness >= 0:
        raise ValueError(f"unreliable_roughness must be >= 0, got {unreliable_roughness!r}")
    if isinstance(line_radius, bool) or not isinstance(line_radius, int | np.integer) \
            or line_radius < 1:
        raise ValueError(f"line_radius must be an integer >= 1, got {line_radius!r}")
    if added_roughness is not None and not added_roughness >= 0:  # NaN fails too
        raise ValueError(f"added_roughness must be >= 0 or None, got {added_roughness!r}")
    if product_scaling not in ("product", "weaker"):
        raise ValueError(f"product_scaling must be 'product' or 'weaker', got "
                         f"{product_scaling!r}")
    if faint_product_ratio is not None and not 0 <= faint_product_ratio <= 1:
        raise ValueError(f"faint_product_ratio must be in [0, 1] or None, "
                         f"got {faint_product_ratio!r}")
    freqs, power = motion_power_spectrum(
        disp, fps, weights=weights if spectrum_weights is None else spectrum_weights,
        detrend=detrend, window=window, block_bytes=block_bytes
    )
    pk = pick_peaks(
        freqs,
        power,
        fps,
        fmin=band[0],
        fmax=band[1],
        prominence=prominence,
        min_separation_hz=min_separation_hz,
        max_peaks=max_modes,
        min_power_ratio=min_power_ratio,
        false_alarm=false_alarm,
        floor_half_width_bins=floor_half_width_bins,
        min_bin=min_bin,
    )
    w = None if weights is None else np.asarray(weights, dtype=np.float64)
    cand, cand_prom = np.zeros(0, np.int64), np.zeros(0)
    if shoulder_prominence is not None and shoulder_prominence < prominence and (
            max_modes is None or len(pk) < max_modes):
        low = pick_peaks(
            freqs, power, fps, fmin=band[0], fmax=band[1], prominence=shoulder_prominence,
            min_separation_hz=min_separation_hz, max_peaks=None,
            min_power_ratio=min_power_ratio, false_alarm=false_alarm,
            floor_half_width_bins=floor_half_width_bins, min_bin=min_bin,
        )
        pw = np.asarray(power, np.float64)
        # only candidates with a stronger peak near them need (and get) their field
        near = np.array([np.any((np.abs(low.bins - k) <= shoulder_bins) & (pw[low.bins] > pw[k]))
                         for k in low.bins], bool).reshape(-1)
        new_ = ~np.isin(low.bins, pk.bins) & near
        cand, cand_prom = low.bins[new_], low.prominences[new_]
    Z_all = bin_fields(disp, np.concatenate([pk.bins, cand]), detrend=detrend, window=window,
                       block_bytes=block_bytes)
    Z, shoulders = Z_all[: len(pk)], []
    if cand.size:
        pk, Z, shoulders = _resolved_shoulders(
            pk, Z, cand, cand_prom, Z_all[len(pk):], np.asarray(freqs, np.float64),
            np.asarray(power, np.float64), w, shoulder_bins, shoulder_mac,
            None if max_modes is None else max_modes - len(pk),
        )
    T = _n_frames(disp)
    gain = window_gain(T, window)
    lines = None
    if line_fit and len(pk):
        lines, pk, Z = _fit_lines(disp, pk, Z, np.asarray(freqs, np.float64),
                                  np.asarray(power, np.float64), float(fps), T, band, w,
                                  window, detrend, block_bytes, false_alarm, min_bin,
                                  floor_half_width_bins, shoulder_mac, max_modes,
                                  radius=line_radius)
    rows: dict[str, list] = {k: [] for k in _ROWS}
    shapes = []
    rough = []
    stride = 1.0 if output_shape is None else output_shape[0] / Z.shape[1]
    attenuation = None
    if shape_noise is not None:
        if np.shape(shape_noise) != tuple(Z.shape[1:3]):
            raise ValueError(f"shape_noise {np.shape(shape_noise)} must be the displacement "
                             f"grid {tuple(Z.shape[1:3])}")
        attenuation = noisy_pixel_attenuation(shape_noise, w, shape_noise_quantile,
                                              shape_noise_factor)
    phase = []
    reliable = []
    rough_shape = []
    sw = w if spectrum_weights is None else np.asarray(spectrum_weights, dtype=np.float64)
    rw = sw if roughness_weighting == "spectrum" else w
    for i, k in enumerate(pk.bins):
        real, theta, coll = align_phase(Z[i], w)
        rough.append(roughness(real, rw, rough_sigma_px / stride))
        rough_shape.append(rough[-1] if rw is w else roughness(real, w, rough_sigma_px / stride))
        reliable.append(1.0 if sw is w else reliable_fraction(real, w, sw))
        if attenuation is not None and shape_fill:
            real = fill_unreliable_pixels(real, attenuation**2, w, rough_sigma_px / stride)
        elif attenuation is not None:
            real = real * attenuation[..., None]
        if output_shape is not None and tuple(real.shape[:2]) != tuple(output_shape):
            real = np.moveaxis(upsample_periodic(np.moveaxis(real, -1, 0), output_shape), 0, -1)
        norm = float(np.linalg.norm(real))
        if lines is not None:
            # the fitted line: exact frequency and damping; the amplitude of the undamped
            # sinusoid with the same spectral line (|A| = a / 2 at the record's start)
            f_ref = float(lines.kappa[i]) * float(fps) / T
            zeta = float(lines.half_width[i] / lines.kappa[i])
            amp = 2.0 * norm * float(peak_gain(lines.half_width[i], T, window)[0]) / gain
        else:
            zeta, _, _ = damping_lorentzian(freqs, power, int(k), window=window, n_frames=T)
            f_ref = refine_frequency(freqs, power, int(k))
            delta = (f_ref - freqs[int(k)]) / (float(fps) / T) if T > 1 else 0.0
            amp = 2.0 * norm / gain / scalloping(delta, window)
            # the symmetric window puts a line delta bins off the bin at phase + pi delta
            theta -= math.pi * delta
        phase.append(theta % math.pi)
        rows["frequencies_hz"].append(f_ref)
        rows["damping"].append(zeta)
        rows["damping_half_power"].append(
            damping_half_power(freqs, power, int(k), window=window, n_frames=T)
        )
        rows["amplitudes_px"].append(amp)
        rows["peak_bins"].append(int(k))
        rows["prominences"].append(float(pk.prominences[i]))
        rows["collinearity"].append(coll)
        smac = translation_mac(Z[i], w)
        rows["shake_mac"].append(smac)
        rows["camera_shake"].append(smac > shake_threshold)
        shapes.append((real / norm if norm > 0 else real).astype(np.float32))
    H, W = shapes[0].shape[:2] if shapes else (0, 0)
    if not shapes:
        H, W = output_shape if output_shape is not None else _frame_shape(disp)
    arr = {
        k: np.array(v, dtype={"peak_bins": np.int64, "camera_shake": bool}.get(k, np.float64))
        for k, v in rows.items()
    }
    meta = dict(metadata or {})
    meta.update(
        band_hz=list(band),
        prominence_decades=prominence,
        min_separation_hz=min_separation_hz,
        max_modes=max_modes,
        min_power_ratio=min_power_ratio,
        detrend=detrend,
        window=window,
        shake_threshold=shake_threshold,
        reject_distortion=reject_distortion,
        max_roughness=max_roughness,
        product_roughness=product_roughness,
        faint_product_ratio=faint_product_ratio,
        product_scaling=product_scaling,
        shape_attenuation=None if attenuation is None else {
            "mode": "fill" if shape_fill else "attenuate",
            "quantile": float(shape_noise_quantile),
            "factor": float(shape_noise_factor),
            "attenuated_fraction": float(np.mean(attenuation < 1.0)),
        },
        roughness=[float(r) for r in rough],
        roughness_weighting=roughness_weighting,
        min_reliable_fraction=min_reliable_fraction,
        reliable_fraction=[float(q) for q in reliable],
        roughness_shape=[float(r) for r in rough_shape],
        unreliable_roughness=unreliable_roughness,
        phase_rad=[float(p) for p in phase],
        weighted=weights is not None,
        min_bin=int(min_bin),
        shoulder_prominence=shoulder_prominence,
        shoulder_mac=shoulder_mac,
        shoulder_bins=int(shoulder_bins),
        shoulders=shoulders,
        noise_floor=None if pk.noise is None else pk.noise.summary(),
        floor_ratio=None if pk.floor_ratio is None else [float(r) for r in pk.floor_ratio],
        analysed_index=list(range(len(pk.bins))),
        line_fit=None if lines is None else {
            "added_hz": [float(k) * float(fps) / T for k in lines.kappa[lines.added]],
            "candidates": lines.log,
        },
    )
    if lines is not None:
        meta.update(mode_uncertainty(lines, float(fps), T), uncertainty_method=LINE_FIT_METHOD)
    elif len(pk):
        meta.update(peak_uncertainty(
            disp, freqs, pk.bins, float(fps), frequency_hz=rows["frequencies_hz"],
            damping=rows["damping"], spectrum_weights=sw, shape_weights=w, detrend=detrend,
            window=window, band=band, floor_half_width_bins=floor_half_width_bins,
            block_bytes=block_bytes))
    ms = ModeSet(
        shapes=np.array(shapes, dtype=np.float32).reshape(len(shapes), H, W, 2),
        freqs_hz=freqs,
        power=power,
        fps=float(fps),
        n_frames=int(T),
        confidence=None if confidence is None else np.asarray(confidence, np.float32),
        metadata=meta,
        **arr,
    )
    shake = ms.camera_shake
    rejected = [
        {
            "bin": int(ms.peak_bins[i]),
            "frequency_hz": float(ms.frequencies_hz[i]),
            "shake_mac": float(ms.shake_mac[i]),
            "reason": "camera_shake",
        }
        for i in np.flatnonzero(shake)
        if not keep_camera_shake
    ]
    drop = shake.copy() if not keep_camera_shake else np.zeros(len(ms), bool)
    if reject_distortion and len(ms):
        f = ms.frequencies_hz
        # camera-shake peaks are parents too: the extractor's error of a translation depends
        # on the texture, so its harmonics are not translations and pass the shake test
        pw = np.asarray(power, np.float64)[ms.peak_bins]
        flagged = {
            d["index"]: d
            for d in distortion_products(f, pw, float(fps) / T, power_ratio=0.5, fps=float(fps))
        }
        faint_flagged = {} if not faint_product_ratio else {
            d["index"]: d
            for d in distortion_products(f, pw, float(fps) / T, power_ratio=faint_product_ratio,
                                         inherit=True, fps=float(fps), scaling=product_scaling)
        }
        for k in range(len(ms)):
            if drop[k]:
                continue
            entry = {
                "bin": int(ms.peak_bins[k]),
                "frequency_hz": float(f[k]),
                "roughness": float(rough[k]),
            }
            d = flagged.get(k)
            faint = faint_flagged.get(k)
            if faint is not None:
                i, j = faint["parents"]
                entry.update(
                    reason="distortion",
                    kind=faint["kind"],
                    parents_hz=[float(f[i]), float(f[j])],
                    power_ratio=faint["power_ratio"],
                    phase_residual_rad=product_phase_residual(phase, f, k, i, j, faint["kind"],
                                                              fps=fps),
                )
            elif d is not None and rough[k] > product_roughness:
                i, j = d["parents"]
                entry.update(
                    reason="distortion",
                    kind=d["kind"],
                    parents_hz=[float(f[i]), float(f[j])],
                    phase_residual_rad=product_phase_residual(phase, f, k, i, j, d["kind"],
                                                              fps=fps),
                )
            elif (min_reliable_fraction is not None and reliable[k] < min_reliable_fraction
                  and rough_shape[k] > unreliable_roughness):
                entry.update(reason="unreliable", reliable_fraction=float(reliable[k]),
                             roughness_shape=float(rough_shape[k]))
            elif rough[k] > max_roughness:
                entry.update(reason="incoherent")
            elif (added_roughness is not None and lines is not None and lines.added[k]
                  and rough[k] > added_roughness):
                entry.update(reason="weak_incoherent")
            else:
                continue
            drop[k] = True
            rejected.append(entry)
    meta["rejected"] = rejected
    return ms.select(~drop)


def _fit_lines(disp: DisplacementStore | ArrayLike, pk: Peaks, Z: NDArray,
               freqs: NDArray[np.float64], power: NDArray[np.float64], fps: float, T: int,
               band: tuple[float, float], w: NDArray[np.float64] | None, window: Window,
               detrend: str, block_bytes: int, false_alarm: float | None, min_bin: int,
               floor_half_width_bins: int, max_mac: float, max_modes: int | None,
               radius: int = 4) -> tuple[Lines, Peaks, NDArray]:
    """Picked peaks -> fitted lines plus the residual's lines; the peaks and fields to analyse
    (fields are the lines' complex amplitudes ``A``, not windowed DFTs)."""
    n_top = T // 2
    lo = max(int(min_bin), int(math.ceil(band[0] * T / fps - 1e-9)), 1)
    hi = min(int(math.floor(band[1] * T / fps + 1e-9)), n_top - 1)
    first, last = max(1, lo - radius), min(n_top, hi + radius)
    fshape = Z.shape[1:]
    fields = bin_fields(disp, np.arange(first, last + 1), detrend=detrend, window=window,
                        block_bytes=block_bytes).reshape(last - first + 1, -1)
    wc = None if w is None else np.repeat(w.reshape(-1), fshape[-1])
    kappa0 = np.array([refine_frequency(freqs, power, int(k)) for k in pk.bins]) * T / fps
    lines = clean_lines(fields, first, power, kappa0, T, band=(lo, hi), weights=wc,
                        window=window, radius=radius,
                        false_alarm=0.01 if false_alarm is None else false_alarm,
                        floor_half_width_bins=floor_half_width_bins, max_mac=max_mac,
                        max_lines=max_modes, clusters=block_clusters(fshape))
    bins = np.clip(np.rint(lines.kappa).astype(np.int64), 1, n_top)
    nf = noise_floor(lines.residual, slice(lo, hi + 1), false_alarm=0.01 if false_alarm is None
                     else false_alarm, half_width_bins=floor_half_width_bins)
    prom = np.log10(np.maximum(lines.power, 1e-300) / nf.floor[bins])
    orig = np.flatnonzero(~lines.added)
    if orig.size == len(pk):
        prom[orig] = pk.prominences
    new = Peaks(bins=bins, frequencies_hz=lines.kappa * fps / T, prominences=prom,
                floor_ratio=lines.power / nf.floor[bins], noise=nf)
    return lines, new, lines.shapes.reshape(len(bins), *fshape)


def _complex_mac(a: NDArray, b: NDArray, w: NDArray[np.float64] | None) -> float:
    """``|<a, b>_w|**2 / (<a, a>_w <b, b>_w)`` of two complex ``(H, W, 2)`` fields."""
    ww = np.ones(a.shape[:2]) if w is None else w
    ab = complex(np.einsum("hwc,hwc,hw->", np.conj(a), b, ww))
    aa = float(np.einsum("hwc,hw->", np.abs(a) ** 2, ww))
    bb = float(np.einsum("hwc,hw->", np.abs(b) ** 2, ww))
    return abs(ab) ** 2 / (aa * bb) if aa > 0 and bb > 0 else 1.0


def _resolved_shoulders(pk: Peaks, Z: NDArray, cand: NDArray[np.int64],
                        cand_prom: NDArray[np.float64], Zc: NDArray,
                        freqs: NDArray[np.float64], power: NDArray[np.float64],
                        w: NDArray[np.float64] | None, max_bins: int, max_mac: float,
                        room: int | None) -> tuple[Peaks, NDArray, list]:
    """Add the low-prominence candidates ``cand`` (fields ``Zc``) whose field differs from
    that of every stronger peak within ``max_bins`` bins (complex MAC below ``max_mac``),
    strongest first, at most ``room`` of them; returns the peaks, their fields and a log
    (``bin``, ``frequency_hz``, ``mac``, ``kept`` per candidate with a stronger neighbour)."""
    bins, fields, prom = list(pk.bins), list(Z), list(pk.prominences)
    log: list[dict] = []
    n_new = 0
    for i in np.argsort(-power[cand], kind="stable"):
        k = int(cand[i])
        if room is not None and n_new >= room:
            break
        near = [j for j, b in enumerate(bins) if abs(b - k) <= max_bins and power[b] > power[k]]
        if not near:
            continue
        mac = max(_complex_mac(Zc[i], fields[j], w) for j in near)
        keep = mac < max_mac
        log.append({"bin": k, "frequency_hz": float(freqs[k]), "mac": float(mac),
                    "kept": bool(keep)})
        if keep:
            bins.append(k)
            fields.append(Zc[i])
            prom.append(float(cand_prom[i]))
            n_new += 1
    if not n_new:
        return pk, Z, log
    order = np.argsort(bins, kind="stable")
    b = np.asarray(bins, np.int64)[order]
    floor = None if pk.noise is None else pk.noise.floor
    new = Peaks(bins=b, frequencies_hz=freqs[b], prominences=np.asarray(prom)[order],
                floor_ratio=None if floor is None else power[b] / floor[b], noise=pk.noise)
    return new, np.stack([fields[j] for j in order]), log


_ROWS = (
    "frequencies_hz",
    "damping",
    "damping_half_power",
    "amplitudes_px",
    "peak_bins",
    "prominences",
    "collinearity",
    "shake_mac",
    "camera_shake",
)


def scalloping(delta: float, window: Window) -> float:
    """Relative DFT response to a sinusoid ``delta`` bins off the bin centre (<= 1).

    ``sinc(delta)`` without window, ``sinc(delta) / (1 - delta**2)`` for the periodic Hann
    window (large ``T``); ``delta`` is clipped to ``[-0.5, 0.5]``.  Dividing the peak-bin
    amplitude by it corrects the scalloping loss (up to 36 % / 15 % halfway between bins).
    """
    d = min(abs(float(delta)), 0.5)
    s = float(np.sinc(d))
    return s / (1.0 - d * d) if window == "hann" else s


def _frame_shape(disp: DisplacementStore | ArrayLike) -> tuple[int, int]:
    if isinstance(disp, DisplacementStore):
        return disp.frame_shape[:2]
    return tuple(np.shape(disp)[1:3])


def _n_frames(disp: DisplacementStore | ArrayLike) -> int:
    return int(disp.n_frames if isinstance(disp, DisplacementStore) else np.shape(disp)[0])


def extract_modes(
    source: str | Path | ArrayLike | Iterable[ArrayLike],
    fps: float | None = None,
    *,
    fmin: float | None = None,
    fmax: float | None = None,
    prominence: float = 0.5,
    min_separation_hz: float | None = None,
    max_modes: int | None = None,
    min_power_ratio: float = 1e-6,
    n_scales: int = 3,
    n_orientations: int = 4,
    sigma: float = 2.0,
    outlier_fraction: float = 0.01,
    batch: int = 32,
    workers: int | None = None,
    average: int = 1,
    roi: tuple[int, int, int, int] | None = None,
    max_frames: int | None = None,
    weighting: str = "noise",
    detrend: str = "mean",
    window: Window = "hann",
    shake_threshold: float = 0.9,
    keep_camera_shake: bool = False,
    reject_distortion: bool = True,
    product_roughness: float = 0.15,
    faint_product_ratio: float | None = 0.01,
    product_scaling: str = "product",
    shape_attenuation: bool = False,
    shape_fill: bool = False,
    memory_budget: int = DEFAULT_BUDGET,
    tmpdir: str | None = None,
    progress: bool = False,
    false_alarm: float | None = 0.01,
    min_bin: int = 3,
    shoulder_prominence: float | None = 0.05,
    extractor: Any = "phase",
    extractor_config: Any = None,
    line_fit: bool = False,
    stability: bool = False,
    roughness_weighting: str = "shape",
    min_reliable_fraction: float | None = None,
    start: int = 0,
    stop: int | None = None,
    bit_depth: int | None = None,
    reject_keyframe_comb: bool = True,
    reject_products: bool = False,
    reference: str = "mean",
    identifier: str = "peaks",
    excitation: str | None = None,
    pole_options: Mapping[str, Any] | None = None,
) -> ModeSet:
    """Extract image-space modes from a video end to end.

    Parameters
    ----------
    source : path, array or iterable
        Video file (avi/mp4/mkv/..., 8- or 16-bit, gray or colour), ``.npy`` ``(T, H, W[, C])``,
        an array, or an iterable of frames; see :func:`video.open_video`.
    fps : float, optional
        Frame rate of the recording (Hz).  Default: the container's (often wrong for
        high-speed footage); required for arrays and iterables.
    fmin, fmax, prominence, min_separation_hz, max_modes, min_power_ratio :
        Peak picking, see :func:`modes_from_displacements`.
    n_scales, n_orientations, sigma, outlier_fraction, workers :
        Motion extraction, see :class:`PhaseMotion`.
    batch : int, default 32
        Frames per motion batch.
    average : int, default 1
        Average groups of ``average`` consecutive frames first (effective fps ``fps / average``).
    roi : tuple of int, optional
        Crop ``(y0, y1, x0, x1)``.
    max_frames : int, optional
        Read at most this many frames (before averaging).
    weighting : {"confidence", "none", "noise"}, default "noise"
        Pixel weights for the spectrum, phase alignment and shake test:
        :func:`confidence_weights` of the motion confidence, uniform (paper), or (default)
        the confidence weights divided by each pixel's motion noise power
        (:func:`noise_weights` of :func:`spectrum.pixel_noise_power`: one more pass over the
        displacements) for the spectrum the peaks are picked from, the confidence weights for
        the shapes and the tests.
    detrend, window, shake_threshold, keep_camera_shake, reject_distortion, product_roughness,
    faint_product_ratio, product_scaling :
        See :func:`modes_from_displacements`.
    shape_attenuation : bool, default False
        Attenuate the pixels whose motion noise power is more than 10 times its 90 % quantile
        in the mode shapes (:func:`noisy_pixel_attenuation`; the noise pass of
        ``weighting="noise"``, made for this if needed; docs/modes.md).  Opt-in: it helps
        rendered objects with seams and distorts the shapes of evenly textured videos, whose
        noise tail is numerical.
    shape_fill : bool, default False
        Fill those pixels in from their reliable neighbours instead of attenuating them
        (:func:`fill_unreliable_pixels`; whatever ``shape_attenuation``): the weak modes'
        shapes are cleaned as much, and the pixels on an object's edges, where its vertices
        are observed, are not pulled towards zero.
    memory_budget : int, default 1 GiB
        Displacement bytes kept in RAM before spilling to a temporary file in ``tmpdir``.
    progress : bool
        Show a tqdm progress bar on stderr.
    false_alarm, min_bin, shoulder_prominence :
        Peak significance, the lowest peak bin and resolved shoulders, see
        :func:`modes_from_displacements`.
    extractor : str, class or instance, default "phase"
        Motion extractor plug-in (:mod:`vvtbench.solving.extractors`): a registered name
        (``"phase"``, ``"farneback"``, ...), ``module:Class`` / ``path.py:Class``, a class or an
        instance.  ``n_scales``, ``n_orientations``, ``sigma``, ``outlier_fraction`` and
        ``workers`` configure the phase-based extractor unless ``extractor_config`` (a
        dataclass, or a mapping whose keys win) sets them.
    extractor_config : dataclass instance or mapping, optional
        The extractor's ``Config`` (or overrides of its defaults).
    line_fit : bool, default False
        Multi-channel line fit and residual search, see :func:`modes_from_displacements`.
    stability : bool, default False
        Also search the first quarter, half and three quarters of the record for peaks
        (:func:`.stability.record_stability`) into ``metadata["stability"]``, for the
        stability figure.
    roughness_weighting, min_reliable_fraction :
        Shape tests on the reliable pixels, see :func:`modes_from_displacements` (they use the
        noise weights of ``weighting="noise"``; with other weightings they change nothing).
    start, stop, bit_depth :
        Frame range read and the bit depth of an image sequence or camera file, see
        :func:`video.open_video`.
    reject_keyframe_comb : bool, default True
        For a lossy video with a keyframe interval (``metadata["lossy"]["gop"]``), reject the
        peaks within two bins (the Hann window's main lobe) of a multiple of ``fps / gop``
        (reason ``"keyframe"``, :func:`peaks.keyframe_comb`).
    reject_products : bool, default False
        With ``reject_distortion``, also apply
        :func:`vvtbench.modes.combinations.reject_combinations`: a mode at a harmonic or
        intermodulation of up to three stronger ones whose phase and shape say it is their
        product is rejected (reason ``"product"``; docs/modes.md, "False modes of the
        extractor's own making").
    reference : {"mean", "first"}, default "mean"
        The frame the motion is measured against: the temporal mean of the (averaged) frames
        of the record, read in a first pass (a file or an array is read twice; a one-shot
        iterable is kept for the second pass, in RAM up to ``memory_budget`` and then in a
        temporary file in ``tmpdir``), or the first frame.  A noisy reference biases the
        phase extractor's amplitudes low (its noise enters every frame's frequencies and
        weights: -13 % at a texture-to-noise ratio of 5); the mean holds ``1 / T`` of one
        frame's noise variance.  Displacements are then relative to the mean position, which
        differs from the first frame's by a constant the spectrum removes.
    identifier, excitation, pole_options :
        Peak picker or pole-based identification (ERA, pLSCF) and how ``"auto"`` chooses,
        see :func:`modes_from_displacements`.  A pole-based identifier rejects products
        itself (by frequency, decay, phase and shape); ``reject_products`` applies to the
        peak picker's modes.

    Returns
    -------
    ModeSet
        ``metadata`` records the source, parameters and timings; ``fps_source`` is
        ``"argument"`` or ``"container"`` (then also logged at INFO level);
        ``record_notes`` what the record's timing and length allow
        (:func:`.record.record_notes`: a decimated record that may alias, a rate given
        against the file's, a short record) and, when no mode is kept, ``no_modes`` why
        (:func:`.record.no_modes_reason`).
    """
    if weighting not in ("confidence", "none", "noise"):
        raise ValueError(
            f"weighting must be 'confidence', 'none' or 'noise', got {weighting!r}"
        )
    video = open_video(source, roi=roi, max_frames=max_frames, start=start, stop=stop,
                       bit_depth=bit_depth)
    fps_source = "argument"
    if fps is None:
        fps = video.fps
        if fps is None:
            raise ValueError("fps is required: the source has no frame rate: pass --fps "
                             "(image sequences and arrays carry none)")
        fps_source = "container"
        _log.info("fps not given: using the container's %g fps (%s)", fps, video.meta["source"])
    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    if average < 1:
        raise ValueError(f"average must be >= 1, got {average}")
    eff_fps = float(fps) / average
    check_band(eff_fps, fmin, fmax)  # fail before the expensive part
    if reference not in ("mean", "first"):
        raise ValueError(f"reference must be 'mean' or 'first', got {reference!r}")
    frames: Iterable = average_frames(video.frames, average)
    bar = None
    if progress:
        from tqdm import tqdm

        total = None if video.n_frames is None else video.n_frames // average
        bar = tqdm(total=total, unit="fr", desc="motion", file=sys.stderr)
    t0 = time.perf_counter()
    spool = None
    if reference == "mean":
        if isinstance(source, (str, Path, np.ndarray)):  # read again for the motion
            ref, n_ref = mean_frame(frames)
            again = open_video(source, roi=roi, max_frames=max_frames, start=start, stop=stop,
                               bit_depth=bit_depth)
            frames = average_frames(again.frames, average)
        else:  # a one-shot stream: kept for the second pass
            spool = FrameSpool(memory_budget, tmpdir)
            ref, n_ref = mean_frame(_spooled(frames, spool))
            frames = iter(spool)
        reference_meta = {"kind": "mean", "frames": n_ref}
    it = iter(frames)
    try:
        first = next(it)
    except StopIteration:
        raise ValueError("the video has no frames") from None
    if reference == "first":
        ref = first
        reference_meta = {"kind": "first", "frames": 1}
    from ..solving.extractors import make_extractor

    if extractor == "phase" and (extractor_config is None or isinstance(extractor_config,
                                                                       Mapping)):
        extractor_config = {
            "n_scales": n_scales,
            "n_orientations": n_orientations,
            "sigma": sigma,
            "outlier_fraction": outlier_fraction,
            "workers": workers,
            **(extractor_config or {}),
        }
    ext = make_extractor(extractor, extractor_config)
    pm = ext.prepare(ref)
    with DisplacementStore(memory_budget, tmpdir) as store:
        # the extractor's working grid (half resolution for the decimated phase pyramid: 4x
        # less to store and transform); mode shapes are upsampled at the end
        try:
            for d in pm.iter_displacements(_chain(first, it), batch=batch):
                store.append(d)
                if bar is not None:
                    bar.update(d.shape[0])
        finally:
            if spool is not None:
                spool.close()
        if bar is not None:
            bar.close()
        t1 = time.perf_counter()
        conf = pm.grid_confidence
        weights = (
            confidence_weights(conf) if weighting != "none" and conf is not None else None
        )
        spectrum_weights = noise = None
        if weighting == "noise" or shape_attenuation or shape_fill:
            noise = pixel_noise_power(store, detrend=detrend, window=window, min_bin=min_bin)
        if weighting == "noise":
            spectrum_weights = noise_weights(
                np.ones(noise.shape) if weights is None else weights, noise)
        meta = {
            **video.meta,
            "fps_input": float(fps),
            "fps_source": fps_source,
            "average": average,
            "extractor": {"name": ext.name, "version": str(ext.version)},
            "motion": {**pm.describe(), "reference": reference_meta},
            "weighting": weighting,
            "spilled_to_disk": store.on_disk,
        }
        ms = modes_from_displacements(
            store,
            eff_fps,
            weights=weights,
            fmin=fmin,
            fmax=fmax,
            prominence=prominence,
            min_separation_hz=min_separation_hz,
            max_modes=max_modes,
            min_power_ratio=min_power_ratio,
            detrend=detrend,
            window=window,
            shake_threshold=shake_threshold,
            keep_camera_shake=keep_camera_shake,
            reject_distortion=reject_distortion,
            product_roughness=product_roughness,
            faint_product_ratio=faint_product_ratio,
            product_scaling=product_scaling,
            shape_noise=noise if shape_attenuation or shape_fill else None,
            shape_fill=bool(shape_fill),
            confidence=pm.confidence,
            metadata=meta,
            output_shape=tuple(pm.shape),
            false_alarm=false_alarm,
            min_bin=min_bin,
            shoulder_prominence=shoulder_prominence,
            line_fit=line_fit,
            spectrum_weights=spectrum_weights,
            roughness_weighting=roughness_weighting,
            min_reliable_fraction=min_reliable_fraction,
            identifier=identifier,
            excitation=excitation,
            pole_options=pole_options,
        )
        if stability:
            from .stability import record_stability

            ms.metadata["stability"] = record_stability(
                store, eff_fps, weights=weights, fmin=fmin, fmax=fmax,
                false_alarm=false_alarm, min_bin=min_bin)
    gop = (video.meta.get("lossy") or {}).get("gop")
    if reject_keyframe_comb and gop and len(ms):
        ms = _reject_keyframe_comb(ms, float(fps), int(gop))
    if reject_products and reject_distortion and len(ms) > 1 and (
            ms.metadata.get("identifier") or {}).get("used", "peaks") == "peaks":
        from .combinations import reject_combinations

        ms = reject_combinations(ms)
    from .record import no_modes_reason, record_notes

    ms.metadata["record_notes"] = record_notes(
        video.meta, float(fps), ms.n_frames, average=average, fmin=fmin, min_bin=min_bin,
        fps_source=fps_source)
    if not len(ms):
        ms.metadata["no_modes"] = no_modes_reason(ms.metadata, ms.fps, ms.n_frames)
    t2 = time.perf_counter()
    ms.metadata["timing_s"] = {"motion": t1 - t0, "spectrum_and_modes": t2 - t1}
    return ms


def _reject_keyframe_comb(ms: ModeSet, fps: float, gop: int) -> ModeSet:
    """``ms`` without its peaks on the keyframe comb of a lossy source, each listed in
    ``metadata["rejected"]`` with reason ``"keyframe"``."""
    tolerance = 2.0 * ms.fps / ms.n_frames
    on_comb = keyframe_comb(ms.frequencies_hz, fps, gop, tolerance, sampled_fps=ms.fps)
    if not on_comb:
        return ms
    drop = np.zeros(len(ms), bool)
    rejected = list(ms.metadata.get("rejected", []))
    for c in on_comb:
        k = c["index"]
        drop[k] = True
        rejected.append({"bin": int(ms.peak_bins[k]), "frequency_hz": float(ms.frequencies_hz[k]),
                         "reason": "keyframe", "gop": int(gop), "comb_hz": c["comb_hz"],
                         "harmonic": c["harmonic"], "line_hz": c["line_hz"]})
    ms.metadata["rejected"] = rejected
    return ms.select(~drop)


def _chain(first: np.ndarray, rest: Iterable) -> Iterable:
    yield first
    yield from rest


def _spooled(frames: Iterable, spool: FrameSpool) -> Iterable:
    for f in frames:
        spool.append(f)
        yield f
