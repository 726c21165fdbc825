"""Scores of the first stage: extracted image-space modes against the true ones.

:func:`score_extraction` matches detected modes (a :class:`~vvtbench.modes.ModeSet`, or
several of the same view) with a sample's true modes and returns precision, recall,
frequency, damping and shape (MAC) errors.  The formulas are in docs/modes.md, "Scoring
extraction".  Only NumPy/SciPy and the true arrays are needed: a sample holds them as
``s.frequencies_hz``, ``s.damping_ratios`` and ``s["image/modes"]``.

:func:`true_mode_amplitudes` measures, from a sample's truth alone, how large each true mode
actually is in its video (px), and :func:`score_sample_extraction` scores detections against
a sample with the headline recall over the modes that are detectable in that video: those
whose Cramér-Rao-limited SNR (``modes/crb_snr``, :mod:`vvtbench.render.crb`) reaches the
detection SNR of the extractor's false-alarm probability, or, for a sample written before
that ruler, those whose line amplitude reaches :data:`DEFAULT_FLOOR_PX`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import linear_sum_assignment

from ..modes.mac import subspace_mac

__all__ = [
    "DEFAULT_FLOOR_PX",
    "clusters_by_resolution",
    "f1_score",
    "parameter_efficiency",
    "score_extraction",
    "score_sample_extraction",
    "subspace_mac",
    "true_mode_amplitudes",
]

#: Smallest true image-space amplitude (px) a mode must have in the video to be expected in a
#: sample without the Cramér-Rao ruler (the smallest amplitude of the extraction targets).
DEFAULT_FLOOR_PX = 1e-3


def clusters_by_resolution(frequencies: ArrayLike, resolution_hz: float) -> list[list[int]]:
    """Group sorted-by-frequency indices whose consecutive gaps are below ``resolution_hz``.

    Modes closer than the frequency resolution ``1 / duration`` cannot be told apart by a
    spectrum of that record: a detection near them is matched to their span.
    """
    f = np.asarray(frequencies, dtype=np.float64)
    order = np.argsort(f, kind="stable")
    out: list[list[int]] = []
    for i in order:
        if out and f[i] - f[out[-1][-1]] < resolution_hz:
            out[-1].append(int(i))
        else:
            out.append([int(i)])
    return out


def _true_vectors(
    true_modes: NDArray[np.float64],
    shapes: NDArray[np.float64],
    uv: ArrayLike | None,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
    """Flattened true and detected vectors on common support, and that support.

    Dense truth ``(n, H, W, 2)`` (NaN off the object): pixels where every true mode is
    finite.  Truth at vertices ``(n, 2 m)`` or ``(n, m, 2)``: the detections are sampled
    bilinearly at ``uv`` ``(m, 2)``.
    """
    t = np.asarray(true_modes, dtype=np.float64)
    k = shapes.shape[0]
    if t.ndim == 4:
        if t.shape[1:] != shapes.shape[1:]:
            raise ValueError(
                f"true image modes are {t.shape[1:3]} px, detected modes {shapes.shape[1:3]}"
            )
        m = np.all(np.isfinite(t), axis=(0, 3))
        return t[:, m, :].reshape(t.shape[0], -1), shapes[:, m, :].reshape(k, -1), m
    if uv is None:
        raise ValueError("true modes given at vertices need uv (m, 2), the vertices' pixels")
    from ..modes.sampling import sample_modes

    t = t.reshape(t.shape[0], -1)
    d = sample_modes(shapes, uv) if k else np.zeros((0, t.shape[1]))
    ok = np.all(np.isfinite(t), axis=0) & np.all(np.isfinite(d), axis=0)
    return t[:, ok], d[:, ok], ok


def _nanmean(values: list[float]) -> float:
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    return float(v.mean()) if v.size else float("nan")


def score_extraction(
    modesets_or_modeset: Any,
    true_frequencies_hz: ArrayLike,
    true_damping: ArrayLike | None,
    true_image_modes: ArrayLike | Sequence[ArrayLike],
    duration_s: float,
    fmax: float,
    *,
    fmin: float = 0.0,
    min_mac: float = 0.5,
    uv: ArrayLike | Sequence[ArrayLike] | None = None,
    amplitudes_px: ArrayLike | None = None,
    floor_px: float = DEFAULT_FLOOR_PX,
    crb_snr: ArrayLike | None = None,
    crb_threshold: float | None = None,
) -> dict[str, Any]:
    """Detected modes against the true ones: precision, recall, frequency/damping/MAC errors.

    Parameters
    ----------
    modesets_or_modeset : ModeSet or sequence of ModeSet
        Detections (``frequencies_hz``, ``damping``, ``shapes``).  Several sets (videos) are
        pooled: each is matched on its own, counts are summed, and a true mode counts as
        recalled if any set matched it.
    true_frequencies_hz : array_like
        ``(n,)`` eigenfrequencies (Hz).
    true_damping : array_like or None
        ``(n,)`` damping ratios (``None``, or 0 for an undamped scene: no damping error).
    true_image_modes : array_like or sequence
        ``(n, H, W, 2)`` dense true image-space modes (NaN off the object), or at vertices
        ``(n, 2 m)`` / ``(n, m, 2)`` with ``uv``; one per set when several sets are given
        (one array is shared).
    duration_s : float
        Record length; the frequency resolution is ``df = 1 / duration_s``.
    fmax : float
        Upper end of the analysed band (Hz): true modes above it are not expected, detections
        above it are not counted.
    fmin : float, default 0
        Lower end of the band.
    min_mac : float, default 0.5
        Minimal (subspace) MAC of a match.
    uv : array_like, optional
        ``(m, 2)`` pixel positions of the vertices (per set, or shared) for vertex truth.
    amplitudes_px : array_like, optional
        ``(n,)`` amplitude of each true mode in the video (px), e.g. ``line_px`` of
        :func:`true_mode_amplitudes`.  A cluster is *detectable* when one of its modes reaches
        ``floor_px``; ``recall`` is then over the detectable clusters.  Default: every
        cluster in the band is detectable (``recall == recall_all``).
    floor_px : float, default :data:`DEFAULT_FLOOR_PX` (0.001 px)
        Detectability floor for ``amplitudes_px``.
    crb_snr : array_like, optional
        ``(n,)`` CRB-limited SNR of each true mode (``modes/crb_snr`` of a sample,
        :mod:`vvtbench.render.crb`).  Given, it defines detectability instead of
        ``amplitudes_px``: a cluster is detectable when one of its modes reaches
        ``crb_threshold``.
    crb_threshold : float, optional
        The SNR of detection (:func:`vvtbench.render.crb.detection_snr_threshold`); needed
        with ``crb_snr``.

    Returns
    -------
    dict
        ``precision`` (matched / detected in band; NaN if nothing detected), ``recall``
        (matched detectable clusters / detectable clusters in band; NaN if none),
        ``recall_all`` (matched clusters / clusters in band; NaN if none in band),
        ``recall_modes`` (true modes in matched clusters / true modes in band), ``f1`` (of
        ``precision`` and ``recall``), ``n_detectable`` (detectable clusters),
        ``n_detectable_modes``, ``n_matched_detectable``, ``detectability`` (``"crb"``,
        ``"amplitude_floor"`` or ``"all"``: the definition used), ``n_below_limit`` (true
        modes in band below the CRB detection SNR; 0 without ``crb_snr``),
        ``crb_threshold`` (NaN without ``crb_snr``), ``amplitude_floor_px`` (NaN
        unless the amplitude floor defined detectability), ``mean_abs_freq_error_hz``,
        ``mean_rel_freq_error``, ``mean_abs_damping_error``, ``mean_rel_damping_error``,
        ``mean_mac``, ``n_detected``, ``n_matched``, ``n_true_in_band``,
        ``n_clusters_in_band``, ``frequency_resolution_hz``, ``band_hz``, ``min_mac``,
        ``missed``: one dict per unmatched cluster (``true`` indices, ``frequencies_hz``,
        ``detectable``, ``amplitude_px``: the largest member amplitude or NaN, ``crb_snr``:
        the largest member SNR or NaN), and
        ``matching``: one dict per match (``set``, ``detected``, ``kind``: ``"mode"`` for a
        detection matched to one true mode, ``"cluster"`` for one matched to an unresolved
        cluster (docs/modes.md, "Matching"), ``true`` (indices of the cluster),
        ``nearest_true``, ``frequency_hz``, ``true_frequency_hz``,
        ``abs_freq_error_hz``, ``damping``, ``true_damping``, ``mac``) and ``unmatched``:
        ``(set, detected index, frequency)`` of the false detections.
    """
    from ..modes.modeset import ModeSet

    sets = [modesets_or_modeset] if isinstance(modesets_or_modeset, ModeSet) else list(
        modesets_or_modeset)
    if not sets:
        raise ValueError("no mode set given")
    if not duration_s > 0 or not fmax > fmin:
        raise ValueError(f"need duration_s > 0 and fmax > fmin, got {duration_s}, {fmin}, {fmax}")
    ft = np.atleast_1d(np.asarray(true_frequencies_hz, dtype=np.float64))
    zt = (np.zeros_like(ft) if true_damping is None
          else np.atleast_1d(np.asarray(true_damping, dtype=np.float64)))
    if zt.shape != ft.shape:
        raise ValueError(f"true_damping {zt.shape} and true_frequencies_hz {ft.shape} differ")
    shared = not (isinstance(true_image_modes, (list, tuple)) and len(true_image_modes) == len(
        sets) and np.ndim(true_image_modes[0]) >= 2)
    tms = [true_image_modes] * len(sets) if shared else list(true_image_modes)
    shared_uv = uv is None or not (isinstance(uv, (list, tuple)) and len(uv) == len(sets)
                                   and np.ndim(uv[0]) == 2)
    uvs = [uv] * len(sets) if shared_uv else list(uv)
    df = 1.0 / float(duration_s)
    band = np.flatnonzero((ft > fmin) & (ft <= fmax))
    clusters = [[int(band[i]) for i in c] for c in clusters_by_resolution(ft[band], df)]
    amp = None if amplitudes_px is None else np.atleast_1d(
        np.asarray(amplitudes_px, dtype=np.float64))
    if amp is not None and amp.shape != ft.shape:
        raise ValueError(f"amplitudes_px {amp.shape} and true_frequencies_hz {ft.shape} differ")
    snr = None if crb_snr is None else np.atleast_1d(np.asarray(crb_snr, dtype=np.float64))
    if snr is not None:
        if snr.shape != ft.shape:
            raise ValueError(f"crb_snr {snr.shape} and true_frequencies_hz {ft.shape} differ")
        if crb_threshold is None or not crb_threshold >= 0:
            raise ValueError(f"crb_snr needs crb_threshold >= 0, got {crb_threshold}")
        definition = "crb"
        above = snr >= float(crb_threshold)
    elif amp is not None:
        if not floor_px >= 0:
            raise ValueError(f"floor_px must be >= 0, got {floor_px}")
        definition = "amplitude_floor"
        above = amp >= floor_px
    else:
        definition = "all"
        above = np.ones(ft.shape, dtype=bool)
    detectable = [bool(np.any(above[c])) for c in clusters]
    modes = [int(x) for x in band]
    cluster_of = {t: j for j, c in enumerate(clusters) for t in c}
    matched_clusters: set[int] = set()
    matching: list[dict[str, Any]] = []
    unmatched: list[tuple[int, int, float]] = []
    n_detected = 0
    for s_i, (ms, tm, uv_s) in enumerate(zip(sets, tms, uvs, strict=True)):
        fd = np.asarray(ms.frequencies_hz, dtype=np.float64)
        det = np.flatnonzero((fd >= fmin) & (fd <= fmax))
        n_detected += det.size
        if det.size == 0:
            continue
        tm = np.asarray(tm, dtype=np.float64)
        if tm.shape[0] != ft.size:
            raise ValueError(f"{tm.shape[0]} true image modes for {ft.size} frequencies")
        tv, dv, _ = _true_vectors(tm, np.asarray(ms.shapes, np.float64)[det], uv_s)
        # 1. resolved: one detection per true mode, by its own frequency and shape
        mac1 = np.zeros((det.size, len(modes)))
        ok1 = np.zeros_like(mac1, dtype=bool)
        for k, t in enumerate(modes):
            for i in np.flatnonzero(np.abs(fd[det] - ft[t]) <= df):
                mac1[i, k] = subspace_mac(dv[i], tv[[t]])
                ok1[i, k] = mac1[i, k] >= min_mac
        rows, cols = _assign(ok1, mac1)
        resolved = {modes[k] for k in cols}
        pairs = []
        for i, k in zip(rows, cols, strict=True):
            # its shape may mix in the unmatched modes it cannot be told from
            t = modes[k]
            near = [x for x in clusters[cluster_of[t]]
                    if x == t or (x not in resolved and abs(ft[x] - ft[t]) < df)]
            pairs.append((int(i), cluster_of[t], t, subspace_mac(dv[i], tv[near]), "mode"))
        # 2. unresolved: a detection left over and a cluster none of whose modes it matched
        taken = {p[1] for p in pairs}
        free = [j for j in range(len(clusters)) if j not in taken]
        rest = np.setdiff1d(np.arange(det.size), rows).tolist()
        mac2 = np.zeros((len(rest), len(free)))
        ok2 = np.zeros_like(mac2, dtype=bool)
        for b, j in enumerate(free):
            c = clusters[j]
            lo, hi = ft[c].min() - df, ft[c].max() + df
            for a, i in enumerate(rest):
                if lo <= fd[det[i]] <= hi:
                    mac2[a, b] = subspace_mac(dv[i], tv[c])
                    ok2[a, b] = mac2[a, b] >= min_mac
        for a, b in zip(*_assign(ok2, mac2), strict=True):
            c = clusters[free[b]]
            near = int(c[int(np.argmin(np.abs(ft[c] - fd[det[rest[a]]])))])
            pairs.append((rest[a], free[b], near, float(mac2[a, b]), "cluster"))
        zd_all = np.asarray(ms.damping, dtype=np.float64)
        for i, j, near, mac, kind in pairs:
            d_i = int(det[i])
            matched_clusters.add(j)
            matching.append({
                "set": s_i,
                "detected": d_i,
                "true": [int(x) for x in clusters[j]],
                "nearest_true": near,
                "kind": kind,
                "frequency_hz": float(fd[d_i]),
                "true_frequency_hz": float(ft[near]),
                "abs_freq_error_hz": float(abs(fd[d_i] - ft[near])),
                "rel_freq_error": float(abs(fd[d_i] - ft[near]) / ft[near]),
                "damping": float(zd_all[d_i]),
                "true_damping": float(zt[near]),
                "mac": mac,
            })
        hit = {p[0] for p in pairs}
        unmatched += [(s_i, int(det[i]), float(fd[det[i]])) for i in range(det.size)
                      if i not in hit]
    n_matched = len(matching)
    n_cl = len(clusters)
    n_det_cl = int(sum(detectable))
    n_hit_det = sum(1 for j in matched_clusters if detectable[j])
    precision = n_matched / n_detected if n_detected else float("nan")
    recall_all = len(matched_clusters) / n_cl if n_cl else float("nan")
    recall = n_hit_det / n_det_cl if n_det_cl else float("nan")
    missed = [{
        "true": [int(x) for x in c],
        "frequencies_hz": [float(ft[x]) for x in c],
        "detectable": detectable[j],
        "amplitude_px": float("nan") if amp is None else float(amp[c].max()),
        "crb_snr": float("nan") if snr is None else float(snr[c].max()),
    } for j, c in enumerate(clusters) if j not in matched_clusters]
    recall_modes = (sum(len(clusters[j]) for j in matched_clusters) / band.size
                    if band.size else float("nan"))
    f1 = float(f1_score(precision, recall))
    damp_abs, damp_rel = [], []
    for m in matching:
        if m["true_damping"] > 0 and math.isfinite(m["damping"]):
            damp_abs.append(abs(m["damping"] - m["true_damping"]))
            damp_rel.append(abs(m["damping"] - m["true_damping"]) / m["true_damping"])
    return {
        "precision": precision,
        "recall": recall,
        "recall_all": recall_all,
        "recall_modes": recall_modes,
        "f1": f1,
        "mean_abs_freq_error_hz": _nanmean([m["abs_freq_error_hz"] for m in matching]),
        "mean_rel_freq_error": _nanmean([m["rel_freq_error"] for m in matching]),
        "mean_abs_damping_error": _nanmean(damp_abs),
        "mean_rel_damping_error": _nanmean(damp_rel),
        "median_rel_damping_error": median_relative_damping_error(matching),
        "mean_mac": _nanmean([m["mac"] for m in matching]),
        "n_detected": int(n_detected),
        "n_matched": int(n_matched),
        "n_true_in_band": int(band.size),
        "n_clusters_in_band": int(n_cl),
        "n_detectable": n_det_cl,
        "n_detectable_modes": int(np.count_nonzero(above[band])),
        "n_matched_detectable": int(n_hit_det),
        "detectability": definition,
        "n_below_limit": 0 if snr is None else int(np.count_nonzero(~above[band])),
        "crb_threshold": float("nan") if snr is None else float(crb_threshold),
        "amplitude_floor_px": float(floor_px) if definition == "amplitude_floor" else float("nan"),
        "frequency_resolution_hz": df,
        "band_hz": [float(fmin), float(fmax)],
        "min_mac": float(min_mac),
        "matching": matching,
        "unmatched": unmatched,
        "missed": missed,
    }


def median_relative_damping_error(matching: list[dict]) -> float:
    """The median of ``|zeta - zeta_true| / zeta_true`` over the matched pairs whose true
    damping is > 0 and whose detection has a finite damping; NaN when there is none (an
    undamped scene, or no matched pair with a damping).

    Parameters
    ----------
    matching : list of dict
        The ``matching`` list of :func:`score_extraction` (``damping``, ``true_damping``).

    Returns
    -------
    float

    Examples
    --------
    >>> round(median_relative_damping_error([{"damping": 0.011, "true_damping": 0.01},
    ...                                      {"damping": 0.03, "true_damping": 0.02},
    ...                                      {"damping": 0.5, "true_damping": 0.0}]), 6)
    0.3
    >>> median_relative_damping_error([])
    nan
    """
    rel = [abs(m["damping"] - m["true_damping"]) / m["true_damping"] for m in matching
           if m["true_damping"] > 0 and math.isfinite(m["damping"])]
    return float(np.median(rel)) if rel else float("nan")


def _assign(feasible: NDArray[np.bool_], macs: NDArray[np.float64]
            ) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Feasible pairs of the assignment with the most pairs, then the largest total MAC."""
    if not feasible.any():
        return np.zeros(0, np.intp), np.zeros(0, np.intp)
    rows, cols = linear_sum_assignment(np.where(feasible, 2.0 - macs, 1e6))
    keep = feasible[rows, cols]
    return rows[keep], cols[keep]


def f1_score(precision: ArrayLike, recall: ArrayLike) -> NDArray[np.float64]:
    """Harmonic mean ``2PR / (P + R)`` of detection precision and recall, per video: 0 when
    nothing true was found (recall 0, with or without detections), NaN where recall is
    undefined (no detectable mode) or precision is undefined and recall is not 0.

    >>> f1_score([1.0, 0.5, np.nan, 1.0], [0.5, 0.0, 0.0, np.nan])
    array([0.66666667, 0.        , 0.        ,        nan])
    """
    p, r = np.asarray(precision, dtype=float), np.asarray(recall, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        f = 2 * p * r / (p + r)
    return np.where(r == 0, 0.0, f)


def _modal_coordinates_fit(surface_modes: NDArray[np.float64]) -> NDArray[np.float64]:
    """``(n, 3 S)`` least-squares map from stacked surface displacements to modal
    coordinates (pseudo-inverse of the ``(3 S, n)`` surface mode matrix)."""
    return np.linalg.pinv(surface_modes.reshape(surface_modes.shape[0], -1).T)


def true_mode_amplitudes(sample: Any, *, chunk_frames: int = 2048,
                         keep_coordinates: bool = False) -> dict[str, Any]:
    """How large each true mode actually is in the sample's video, from the truth alone.

    The modal coordinates ``q_i(t)`` (m kg^1/2) of the filmed motion are the least-squares
    fit of the stored surface displacements ``transient/displacements`` ``(T, S, 3)`` by the
    true surface mode shapes ``modes/surface`` (exact for the modal simulation, whose motion
    is a sum of these modes; the projection for a direct one).  With ``g_i = motion_scale *
    max_p |Psi_i(p)|`` the largest image motion per unit modal coordinate of mode ``i`` over
    the visible pixels ``p`` (``image/modes``, NaN off the object; px per m kg^1/2):

    * ``peak_px[i] = g_i max_t |q_i(t)|``: the largest image motion the mode makes at any
      visible pixel in any frame;
    * ``line_px[i] = g_i (2 / T) |sum_k q_i(t_k) exp(-2 pi i f_d,i t_k)|`` with ``f_d,i =
      f_i sqrt(1 - zeta_i**2)``: the amplitude of the undamped sinusoid that has the same
      Fourier coefficient at the mode's frequency over the record, i.e. the strength of its
      spectral line.  It equals ``peak_px`` for an undamped free vibration and is about
      ``peak_px (1 - exp(-s T_r)) / (s T_r)`` (``s = 2 pi f zeta``, ``T_r`` the record
      length) for a free decay: a mode that dies out early leaves a weak line.

    Parameters
    ----------
    sample : Sample
        An opened sample with video (:func:`vvtbench.samples.reader.open_sample`): needs
        ``transient/displacements``, ``transient/times``, ``modes/surface`` and
        ``image/modes``.
    chunk_frames : int, default 2048
        Frames read at a time.
    keep_coordinates : bool, default False
        Also return the coordinates ``q_i(t)`` themselves.

    Returns
    -------
    dict
        ``peak_px``, ``line_px``, ``modal_peak`` (``max_t |q_i|``), ``gain_px`` (``g_i``),
        each ``(n,)`` float64; ``fit_residual`` (relative RMS of the displacements the modes
        do not explain), ``motion_scale``; with ``keep_coordinates``, ``coordinates``
        ``(T, n)`` and ``times`` ``(T,)`` (s).

    Raises
    ------
    ValueError
        If the sample lacks the transient (a modes-only sample) or the arrays disagree.
    """
    for name in ("transient/displacements", "transient/times", "modes/surface", "image/modes"):
        if name not in sample:
            raise ValueError(f"the sample lacks {name!r} (a modes-only sample, or an older "
                             "format): the modes' amplitudes in the video are unknown")
    f = np.asarray(sample.frequencies_hz, dtype=np.float64)
    zeta = np.asarray(sample.damping_ratios, dtype=np.float64)
    surf = np.asarray(sample["modes/surface"], dtype=np.float64)
    if surf.shape[0] != f.size:
        raise ValueError(f"{surf.shape[0]} surface modes for {f.size} frequencies")
    pinv = _modal_coordinates_fit(surf)
    times = np.asarray(sample["transient/times"], dtype=np.float64)
    disp = sample.array("transient/displacements") if hasattr(sample, "array") else \
        sample["transient/displacements"]
    n_t = int(disp.shape[0])
    fd = f * np.sqrt(np.clip(1.0 - zeta**2, 0.0, None))
    peak_q = np.zeros(f.size)
    line = np.zeros(f.size, dtype=np.complex128)
    coordinates = np.zeros((n_t, f.size)) if keep_coordinates else None
    res2 = tot2 = 0.0
    for k0 in range(0, n_t, max(1, int(chunk_frames))):
        k1 = min(n_t, k0 + max(1, int(chunk_frames)))
        u = np.asarray(disp[k0:k1], dtype=np.float64).reshape(k1 - k0, -1)  # (t, 3 S)
        q = u @ pinv.T  # (t, n)
        if coordinates is not None:
            coordinates[k0:k1] = q
        peak_q = np.maximum(peak_q, np.abs(q).max(axis=0))
        line += np.einsum("tn,tn->n", q, np.exp(-2j * np.pi * np.outer(times[k0:k1], fd)))
        r = u - q @ surf.reshape(f.size, -1)
        res2 += float(np.sum(r * r))
        tot2 += float(np.sum(u * u))
    im = np.asarray(sample["image/modes"], dtype=np.float64)
    if im.shape[0] != f.size:
        raise ValueError(f"{im.shape[0]} image modes for {f.size} frequencies")
    norm2 = np.sum(im * im, axis=-1).reshape(f.size, -1)
    finite = np.isfinite(norm2)
    gmax = np.sqrt(np.where(finite, norm2, 0.0).max(axis=1, initial=0.0))
    video = sample.info.get("video", {})
    scale = float(video.get("motion_scale", 1.0))
    g = scale * gmax
    return {
        "peak_px": g * peak_q,
        "line_px": g * 2.0 * np.abs(line) / max(n_t, 1),
        "modal_peak": peak_q,
        "gain_px": g,
        "fit_residual": float(np.sqrt(res2 / tot2)) if tot2 > 0 else 0.0,
        "motion_scale": scale,
        **({"coordinates": coordinates, "times": times} if keep_coordinates else {}),
    }


def score_sample_extraction(
    sample: Any,
    modesets_or_modeset: Any,
    fmax: float | None = None,
    *,
    fmin: float = 0.0,
    min_mac: float = 0.5,
    floor_px: float = DEFAULT_FLOOR_PX,
    amplitudes: dict[str, Any] | None = None,
    use_crb: bool = True,
) -> dict[str, Any]:
    """Score detections against an opened sample, recall over the modes detectable in it.

    A sample written with the Cramér-Rao ruler (``modes/crb_snr``, docs/dataset.md "The
    Cramér-Rao ruler") defines detectability by it: a true mode is expected when its
    CRB-limited SNR reaches the detection SNR of the video's length
    (:func:`vvtbench.render.crb.detection_snr_threshold`), and the score's
    ``detectability`` is ``"crb"``.  An older sample falls back to the amplitude floor
    below (``"amplitude_floor"``).

    :func:`score_extraction` of the sample's true modes (``frequencies_hz``,
    ``damping_ratios``, ``image/modes``) with ``amplitudes_px`` the true modes' spectral-line
    amplitudes in the video (``line_px`` of :func:`true_mode_amplitudes`) and the
    detectability floor ``floor_px``: ``recall`` is over the true-mode clusters in the band
    with a member of at least ``floor_px``, ``recall_all`` over every cluster in the band.
    See docs/modes.md, "Scoring extraction".

    Parameters
    ----------
    sample : Sample
        Opened sample with video (:func:`vvtbench.samples.reader.open_sample`).
    modesets_or_modeset : ModeSet or sequence of ModeSet
        Detections from the sample's video (several: pooled, see :func:`score_extraction`).
    fmax : float, optional
        Upper end of the band (Hz), capped at the highest true mode (true modes above it are
        not computed, so not missing); default that mode.
    fmin, min_mac : float
        See :func:`score_extraction`.
    floor_px : float, default 0.001
        Detectability floor (px) of a sample without the ruler (or with ``use_crb=False``).
    amplitudes : dict, optional
        A precomputed :func:`true_mode_amplitudes` of the sample (it reads the whole
        transient).
    use_crb : bool, default True
        False: the amplitude floor even when the sample holds the ruler.

    Returns
    -------
    dict
        The keys of :func:`score_extraction` (``precision``, ``recall``, ``recall_all``,
        ``n_detectable``, ``mean_rel_freq_error``, ``mean_mac``, ...), plus
        ``amplitudes_px`` (the per-mode ``line_px`` list) and ``amplitude_fit_residual``.
    """
    from ..modes.modeset import ModeSet

    sets = [modesets_or_modeset] if isinstance(modesets_or_modeset, ModeSet) else list(
        modesets_or_modeset)
    if not sets:
        raise ValueError("no mode set given")
    freqs = np.asarray(sample.frequencies_hz, dtype=np.float64)
    top = float(freqs.max())
    band = top if not fmax else min(float(fmax), top)
    if amplitudes is None or "coordinates" not in amplitudes:
        amplitudes = true_mode_amplitudes(sample, keep_coordinates=True)
    amps = amplitudes
    snr = threshold = None
    if use_crb and "modes/crb_snr" in sample:
        from ..render.crb import detection_snr_threshold

        snr = np.asarray(sample["modes/crb_snr"], dtype=np.float64)
        threshold = detection_snr_threshold(int(sample.info["video"]["frames"]))
    sc = score_extraction(sets, freqs, sample.damping_ratios, sample["image/modes"],
                          sets[0].n_frames / sets[0].fps, band, fmin=fmin, min_mac=min_mac,
                          amplitudes_px=amps["line_px"], floor_px=floor_px, crb_snr=snr,
                          crb_threshold=threshold)
    sc["amplitudes_px"] = [float(a) for a in amps["line_px"]]
    sc["amplitude_fit_residual"] = float(amps["fit_residual"])
    if len(sets) > 1:
        why = "several views pooled: the ruler's SNR is one view's"
    elif snr is None:
        why = "a sample without the Cramér-Rao ruler"
    else:
        why = None
    sc.update(parameter_efficiency(
        sc["matching"], freqs, sample.damping_ratios, amps["times"], amps["coordinates"],
        snr, threshold, unavailable=why))
    return sc


def parameter_efficiency(matching: list[dict], frequencies_hz: ArrayLike,
                         damping_ratios: ArrayLike | None, times: ArrayLike,
                         coordinates: ArrayLike, crb_snr: ArrayLike | None,
                         crb_threshold: float | None, *,
                         unavailable: str | None = None) -> dict[str, Any]:
    """How close the matched modes' frequencies and damping ratios come to their Cramér-Rao
    bound (:func:`vvtbench.render.pole_crb.free_decay_bound`).

    Over the detections matched one to one (``kind == "mode"``) to a detectable true mode
    whose coordinate is a free vibration (fit residual at most
    :data:`~vvtbench.render.pole_crb.FREE_DECAY_RESIDUAL`), each error is normalised by its
    bound, ``NSE = (x_hat - x)^2 / CRB_x``, and the efficiency is ``1 / mean(NSE)``: 1 for an
    unbiased estimator at the bound, below 1 by the factor its mean squared error exceeds the
    bound (bias included).  Damping: only where the true damping is > 0 and the detection
    has a finite one.  Each used entry of ``matching`` gains ``frequency_crb_hz`` and
    ``damping_crb`` (standard deviations).

    Parameters
    ----------
    matching : list of dict
        :func:`score_extraction`'s ``matching`` (updated in place).
    frequencies_hz, damping_ratios : array_like
        The true modes' ``(n,)`` frequencies and damping ratios (``None``: undamped).
    times, coordinates : array_like
        ``(T,)`` frame times and ``(T, n)`` modal coordinates (:func:`true_mode_amplitudes`
        with ``keep_coordinates``).
    crb_snr, crb_threshold
        The true modes' CRB-limited SNR and the detection SNR (None: no ruler).
    unavailable : str, optional
        Why no efficiency is defined (given: NaN with that reason).

    Returns
    -------
    dict
        ``frequency_efficiency``, ``damping_efficiency`` (NaN where no mode qualifies),
        ``n_frequency_efficiency``, ``n_damping_efficiency`` (modes averaged) and
        ``efficiency_note`` (why a NaN, or "").

    Examples
    --------
    >>> t = np.arange(2000) / 1000.0
    >>> q = np.cos(2 * np.pi * 10.0 * t)[:, None]
    >>> m = [{"kind": "mode", "nearest_true": 0, "frequency_hz": 10.001, "damping": 0.0}]
    >>> out = parameter_efficiency(m, [10.0], [0.0], t, q, [50.0], 10.0)
    >>> round(out["frequency_efficiency"] * (0.001 / m[0]["frequency_crb_hz"]) ** 2, 6)
    1.0
    >>> out["damping_efficiency"], out["efficiency_note"]
    (nan, 'no matched mode with a true damping above 0')
    """
    from ..render.pole_crb import FREE_DECAY_RESIDUAL, free_decay_bound

    out = {"frequency_efficiency": float("nan"), "damping_efficiency": float("nan"),
           "n_frequency_efficiency": 0, "n_damping_efficiency": 0, "efficiency_note": ""}
    if unavailable:
        out["efficiency_note"] = unavailable
        return out
    ft = np.asarray(frequencies_hz, dtype=np.float64)
    zt = np.zeros_like(ft) if damping_ratios is None else np.asarray(damping_ratios, np.float64)
    snr = np.asarray(crb_snr, dtype=np.float64)
    q = np.asarray(coordinates, dtype=np.float64)
    bounds: dict[int, dict[str, float]] = {}
    nse_f, nse_z, forced = [], [], 0
    for m in matching:
        k = int(m["nearest_true"])
        if m.get("kind") != "mode" or not snr[k] >= float(crb_threshold):
            continue
        if k not in bounds:
            bounds[k] = free_decay_bound(times, q[:, k], float(snr[k]), float(ft[k]),
                                         float(zt[k]))
        b = bounds[k]
        if not b["fit_residual"] <= FREE_DECAY_RESIDUAL:
            forced += 1
            continue
        m["frequency_crb_hz"], m["damping_crb"] = b["frequency_std_hz"], b["damping_std"]
        nse_f.append((m["frequency_hz"] - ft[k]) ** 2 / b["frequency_std_hz"] ** 2)
        if zt[k] > 0 and math.isfinite(m.get("damping", math.nan)):
            nse_z.append((m["damping"] - zt[k]) ** 2 / b["damping_std"] ** 2)
    for key, nse in (("frequency", nse_f), ("damping", nse_z)):
        out[f"n_{key}_efficiency"] = len(nse)
        if nse:
            out[f"{key}_efficiency"] = 1.0 / max(float(np.mean(nse)), 1e-300)
    if not nse_f:
        out["efficiency_note"] = (
            f"{forced} matched mode(s) not in free vibration (a forced response)" if forced
            else "no detection matched one to one to a detectable true mode")
    elif not nse_z:
        out["efficiency_note"] = "no matched mode with a true damping above 0"
    return out
