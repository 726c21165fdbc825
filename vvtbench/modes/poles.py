"""Pole-based identification of image-space modes: reduced channels, a model-order scan, a
stabilisation diagram, clustering, and full-resolution shapes by projection.

:func:`identify_poles` turns a displacement record into a :class:`.ModeSet`:

1. **Reduce.** Weighted ``block x block`` tile averages of both components
   (:func:`.reduce.block_channels`, streamed), frames averaged in groups down to about
   ``oversampling`` times the band's top (exact for a free decay, :func:`.reduce.decimate_frames`),
   each channel scaled by its noise level, and the principal components of the result kept
   (``n_components``): tens of channels carrying the record's coherent motion.
2. **Scan.** ERA on the free decay (:mod:`.era`) at every order of ``orders``, or pLSCF on the
   reduced channels' positive power spectra (:mod:`.plscf`) for forced records.
3. **Stabilise and cluster** (:mod:`.stabilization`): a mode is a cluster of stable poles of
   many orders; its frequency, damping and their spread over the orders (the uncertainty) are
   the cluster's.
4. **Shapes.** Every cluster's pole ``lambda_k`` gives a modal response ``exp(lambda_k t)``
   (with its conjugate); each pixel's motion over the whole record (full frame rate) is
   regressed on all of them at once, with a constant and a drift, by least squares
   (:func:`project_poles`).  The complex coefficient field of a pole is its full-field shape
   (aligned to a real shape as the peak picker's are, :func:`.peaks.align_phase`); the regression's
   residual gives the shape's expected MAC with the noiseless one.

The record stays in its :class:`.spectrum.DisplacementStore`: every pass reads it by column
blocks, so memory is bounded whatever its length.

For forced (driven, swept) records the projection on free-decay responses does not hold;
pLSCF modes take the windowed DFT fields at their frequency instead, like the peak picker.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .era import PoleSet, era_orders
from .reduce import block_channels, channel_noise, decimate_frames
from .spectrum import DisplacementStore, _as_store
from .stabilization import PoleCluster, cluster_poles, diagram, stable_poles

__all__ = ["PoleScan", "content_top", "decide_identifier", "identify_poles", "project_poles",
           "scan_poles"]

#: excitation kinds (scene files, ``excitation=``) whose records are free decays
DECAY_EXCITATIONS = ("pluck", "velocity", "impulse", "decay", "free")
#: ... and those whose records are driven
FORCED_EXCITATIONS = ("force", "sweep", "chirp", "ambient", "forced", "shaker")


@dataclass
class PoleScan:
    """What a model-order scan found.

    Attributes
    ----------
    method : str
        ``"era"`` or ``"plscf"``.
    poles : list of PoleSet
        Poles at every order of the scan.
    stable : list of ndarray
        Which poles are stable (:func:`.stabilization.stable_poles`).
    clusters : list of PoleCluster
        The modes (:func:`.stabilization.cluster_poles`).
    settings : dict
        The reduction and scan settings (JSON-ready).
    """

    method: str
    poles: list[PoleSet]
    stable: list[NDArray[np.bool_]]
    clusters: list[PoleCluster]
    settings: dict[str, Any] = field(default_factory=dict)


def decide_identifier(channels: ArrayLike | None = None, *, excitation: str | None = None,
                      n_segments: int = 8, decay_ratio: float = 4.0) -> tuple[str, str]:
    """Which identifier a record needs, and why: ``("era", reason)`` for a free decay,
    ``("peaks", reason)`` for a driven record or one that does not decay.

    A driven ``excitation`` (:data:`FORCED_EXCITATIONS`) decides alone.  Otherwise the
    envelope of the motion does: the record (``(T, m)`` reduced channels) is cut into
    ``n_segments``; a free decay has its largest energy in the first segment and at least
    ``decay_ratio`` times more there than in the last.  A pluck (:data:`DECAY_EXCITATIONS`)
    whose motion barely decays within the record (an undamped object) goes to the peak
    picker: its lines are narrower than a bin, where the picker is at its best (on an
    undamped ``cube_defects`` val video ERA finds half the modes the picker does).  Without
    a record a decay-type excitation gives ERA.

    >>> t = np.arange(4000) / 1000.0
    >>> decay = (np.exp(-3 * t) * np.cos(60 * t))[:, None]
    >>> decide_identifier(decay)[0], decide_identifier(np.cos(60 * t)[:, None])[0]
    ('era', 'peaks')
    >>> decide_identifier(excitation="force")
    ('peaks', "excitation 'force': a driven record")
    """
    kind = None if excitation is None else str(excitation).lower()
    if kind in FORCED_EXCITATIONS:
        return "peaks", f"excitation {kind!r}: a driven record"
    if channels is None:
        if kind in DECAY_EXCITATIONS:
            return "era", f"excitation {kind!r}: a free decay"
        return "peaks", "no excitation given and no record to read it from"
    y = np.asarray(channels, dtype=np.float64)
    y = y.reshape(y.shape[0], -1)
    y = y - y.mean(axis=0)
    n = max(2, int(n_segments))
    seg = y.shape[0] // n
    if seg < 2:
        return "peaks", "record too short to read its envelope"
    e = np.array([float(np.sum(y[i * seg:(i + 1) * seg] ** 2)) for i in range(n)])
    ratio = e[0] / max(e[-1], 1e-300)
    said = f"excitation {kind!r}, " if kind is not None else ""
    if int(np.argmax(e)) == 0 and ratio >= decay_ratio:
        return "era", (f"{said}envelope: energy falls {ratio:.3g}x from the first to the last "
                       f"eighth of the record (a free decay)")
    if kind in DECAY_EXCITATIONS:
        return "peaks", (f"{said}but the envelope falls only {ratio:.3g}x over the record: "
                         "lines narrower than a bin, the peak picker's")
    return "peaks", (f"envelope: energy peaks in segment {int(np.argmax(e)) + 1} of {n} and "
                     f"falls {ratio:.3g}x (a driven record)")


def content_top(channels: ArrayLike, fps: float, band: tuple[float, float],
                margin: float = 1.25) -> float:
    """The highest frequency (Hz) the record's motion reaches: ``margin`` times the highest
    bin of the channels' summed, noise-scaled periodogram above its noise floor's
    significance threshold (:func:`.significance.noise_floor`), within ``band``; the band's
    top when nothing stands out.  Frames are averaged down to a few times it when no band
    top was given, so that ERA does not read 5 Hz poles 2000 times a second."""
    from .significance import noise_floor

    Y = np.asarray(channels, dtype=np.float64)
    Y = Y - Y.mean(axis=0)
    sd = channel_noise(Y)
    ok = sd > 0
    if not ok.any():
        return float(band[1])
    P = np.sum(np.abs(np.fft.rfft(Y[:, ok] / sd[ok], axis=0)) ** 2, axis=1)
    f = np.fft.rfftfreq(Y.shape[0], 1.0 / fps)
    inb = np.flatnonzero((f >= band[0]) & (f <= band[1]) & (np.arange(f.size) >= 3))
    if inb.size < 16:
        return float(band[1])
    nf = noise_floor(P, slice(int(inb[0]), int(inb[-1]) + 1))
    above = inb[P[inb] > nf.threshold()[inb]]
    if not above.size:
        return float(band[1])
    return float(min(band[1], max(margin * f[above[-1]], 4.0 * fps / Y.shape[0])))


def _reduce(store: DisplacementStore, fps: float, weights: NDArray | None, block: int,
            band: tuple[float, float], oversampling: float, n_components: int,
            decimation: int | None, ch: Any = None, from_content: bool = True
            ) -> tuple[NDArray, NDArray, int, dict]:
    """Reduced, decimated, noise-scaled principal components ``(T', r)``, the component
    basis ``(m, r)`` and the decimation factor."""
    if ch is None or ch.block != block:
        ch = block_channels(store, weights=weights, block=block)
    Y = ch.data
    top, over = band[1], oversampling
    if not decimation and from_content and top >= 0.99 * fps / 2:
        # no band top given: the motion's own, with more room above it (an estimate)
        top, over = content_top(Y, fps, band), max(oversampling, 8.0)
    q = int(decimation) if decimation else max(1, int(fps / (over * top)))
    Yd = decimate_frames(Y - Y.mean(axis=0), q)
    sd = channel_noise(Yd)
    ok = sd > 0
    Yn = np.zeros_like(Yd)
    Yn[:, ok] = Yd[:, ok] / sd[ok]
    U, S, Vt = np.linalg.svd(Yn, full_matrices=False)
    r = int(min(n_components, int(np.sum(S > 0)), Yn.shape[1]))
    V = Vt[:r].T
    return Yn @ V, V, q, {"block": int(block), "channels": int(Y.shape[1]), "decimation": q,
                          "components": r, "singular_values": [float(s) for s in S[:r]]}


def scan_poles(store: DisplacementStore | ArrayLike, fps: float, *, method: str = "era",
               weights: ArrayLike | None = None, band: tuple[float, float],
               block: int = 8, n_components: int = 40, oversampling: float = 2.5,
               decimation: int | None = None, max_order: int = 120, order_step: int = 4,
               block_rows: int | None = 20, f_tol: float = 0.01, z_tol: float = 0.1,
               mac_tol: float = 0.9, cluster_threshold: float = 0.05,
               min_fraction: float = 0.3, channels: Any = None) -> PoleScan:
    """Reduce the record and scan model orders (steps 1-3 of the module docstring).

    Parameters
    ----------
    store : DisplacementStore or array_like
        ``(T, H, W, 2)`` displacements (px).
    fps : float
        Frame rate (Hz).
    method : {"era", "plscf"}
        ERA on the free decay, or pLSCF on positive power spectra.
    weights : array_like, optional
        ``(H, W)`` pixel weights of the tile averages (e.g. inverse noise power).
    band : tuple of float
        Frequencies (Hz) modes are looked for in.
    block, n_components, oversampling, decimation :
        Tile size, principal components kept, frames averaged down to ``oversampling`` times
        the band's top (``decimation`` frames per group when given).
    max_order, order_step, block_rows :
        Orders ``order_step, 2 order_step, ..., max_order``; ERA's block rows.
    f_tol, z_tol, mac_tol :
        Stability of a pole against the previous order (:func:`.stabilization.stable_poles`).
    cluster_threshold, min_fraction :
        Clustering (:func:`.stabilization.cluster_poles`).
    channels : Channels, optional
        The record's tile averages with these ``weights`` and ``block``, if already made
        (:func:`.reduce.block_channels`).
    """
    if method not in ("era", "plscf"):
        raise ValueError(f"method must be 'era' or 'plscf', got {method!r}")
    st = _as_store(store)
    w = None if weights is None else np.asarray(weights, dtype=np.float64)
    Yr, V, q, info = _reduce(st, float(fps), w, int(block), band, float(oversampling),
                             int(n_components), decimation, channels,
                             from_content=method == "era")
    dt = q / float(fps)
    Tq, r = Yr.shape
    if method == "era":
        p = int(block_rows) if block_rows is not None else 20
        # the largest order the record carries: the Hankel matrix needs (p - 1) r rows and
        # q = T' - p columns above it
        top = min(int(max_order), (p - 1) * r, (Tq - p - 1) // 2)
        top -= top % int(order_step)
        if top < 2 * int(order_step):
            raise ValueError(f"the record is too short for ERA: {Tq} frames after averaging "
                             f"{q} at a time, {r} channels (need orders up to at least "
                             f"{2 * int(order_step)})")
        orders = list(range(int(order_step), top + 1, int(order_step)))
        poles = era_orders(Yr, dt, orders, block_rows=p)
    else:
        from .plscf import half_spectra, lscf_orders

        orders = list(range(int(order_step), int(max_order) + 1, int(order_step)))
        refs = np.arange(min(4, Yr.shape[1]))
        n_lags = int(min(Yr.shape[0] // 2, max(256, 8 * max(orders))))
        Sh = half_spectra(Yr, refs, n_lags)
        fr = np.fft.rfftfreq(2 * n_lags, dt)
        tau = -(n_lags - 1) * dt / math.log(0.01)
        deg = [max(1, n // len(refs)) for n in orders]
        poles = lscf_orders(Sh, fr, dt, deg, band=band, exp_window=1.0 / tau)
        info["references"] = int(len(refs))
        info["lags"] = n_lags
    for ps in poles:
        ps.shapes = ps.shapes @ V.T if ps.shapes.size else np.zeros((0, V.shape[0]), complex)
    stable = stable_poles(poles, band_hz=band, f_tol=f_tol, z_tol=z_tol, mac_tol=mac_tol)
    clusters = cluster_poles(poles, stable, threshold=cluster_threshold,
                             min_fraction=min_fraction)
    info.update(method=method, orders=orders, block_rows=block_rows, f_tol=f_tol, z_tol=z_tol,
                mac_tol=mac_tol, cluster_threshold=cluster_threshold,
                min_fraction=min_fraction, oversampling=oversampling)
    return PoleScan(method, poles, stable, clusters, info)


def project_poles(store: DisplacementStore | ArrayLike, fps: float, lam: ArrayLike, *,
                  block_bytes: int = 64 << 20) -> tuple[NDArray[np.complex128],
                                                        NDArray[np.float64]]:
    """Full-field shapes of poles by least squares on their free responses.

    Every column (pixel and component) ``x(t)`` of the record is fitted by ``c0 + c1 t +
    sum_k 2 Re(Z_k exp(lambda_k t))`` over all frames (``t`` in seconds from the first).

    Returns
    -------
    Z : ndarray
        ``(K, H, W, 2)`` complex coefficient fields (px): the pole's motion at ``t = 0`` is
        ``2 Re(Z_k)``, its amplitude ``2 |Z_k|``.
    noise : ndarray
        ``(K,)`` expected squared norm of the noise in each ``Z_k`` (px²), from the fit's
        residual and the regressors' covariance.
    """
    st = _as_store(store)
    lam = np.asarray(lam, dtype=np.complex128).reshape(-1)
    T = int(st.n_frames)
    K = lam.size
    t = np.arange(T) / float(fps)
    E = np.exp(np.outer(t, lam))
    tc = (t - t.mean()) / max(float(np.ptp(t)), 1e-300)
    X = np.column_stack([np.ones(T), tc, E.real, E.imag])
    G = X.T @ X
    Gi = np.linalg.pinv(G)
    H, W = st.frame_shape[:2]
    C = st.n_columns
    beta = np.zeros((X.shape[1], C))
    res = np.zeros(C)
    P = st.block_size(block_bytes)
    for c0 in range(0, C, P):
        c1 = min(c0 + P, C)
        x = np.asarray(st.column_block(c0, c1), dtype=np.float64)
        xb = X.T @ x
        b = Gi @ xb
        beta[:, c0:c1] = b
        res[c0:c1] = np.maximum(np.sum(x * x, axis=0) - np.sum(b * xb, axis=0), 0.0)
    dof = max(T - X.shape[1], 1)
    s2 = res / dof
    re, im = beta[2:2 + K], beta[2 + K:]
    Z = (0.5 * (re - 1j * im)).reshape(K, H, W, 2)
    d = np.diag(Gi)
    noise = 0.25 * (d[2:2 + K] + d[2 + K:]) * float(np.sum(s2))
    return Z, noise


def identify_poles(store: DisplacementStore | ArrayLike, fps: float, **kwargs: Any) -> PoleScan:
    """:func:`scan_poles` (the steps up to the clusters); :func:`.extract.modes_from_displacements`
    with ``identifier`` turns the clusters into a :class:`.ModeSet`."""
    return scan_poles(store, fps, **kwargs)


def scan_metadata(scan: PoleScan, band: tuple[float, float]) -> dict[str, Any]:
    """JSON-ready record of a scan: settings, the stabilisation diagram and the clusters."""
    return {"settings": scan.settings,
            "diagram": diagram(scan.poles, scan.stable, scan.clusters, band_hz=band),
            "clusters": [c.summary() for c in scan.clusters]}


def pole_modes(store: DisplacementStore | ArrayLike, fps: float, scan: PoleScan, *,
               band: tuple[float, float], weights: ArrayLike | None = None,
               spectrum_weights: ArrayLike | None = None,
               output_shape: tuple[int, int] | None = None,
               confidence: ArrayLike | None = None, metadata: dict[str, Any] | None = None,
               shake_threshold: float = 0.9, keep_camera_shake: bool = False,
               reject_products: bool = True, product_options: dict[str, Any] | None = None,
               max_roughness: float = 0.3, rough_sigma_px: float = 2.0,
               min_power_ratio: float = 1e-6, max_frequency_spread_bins: float = 0.3,
               block_bytes: int = 64 << 20) -> Any:
    """A :class:`.ModeSet` from the clusters of a scan (step 4 of the module docstring).

    The spectrum (Hann, ``spectrum_weights``) is kept for the plots and the line SNR; each
    mode's ``peak_bins`` is its frequency's nearest bin.  ``damping_lo`` / ``damping_hi`` are
    the cluster's median damping +- twice its spread over the orders (at least 2 % of it),
    ``frequency_std_hz`` the spread of its frequency.  Products of stronger modes are
    recognised by :func:`.products.find_pole_products` and rejected (reason ``"product"``).
    A mode is also rejected when its power (amplitude squared) is below ``min_power_ratio``
    of the strongest (reason ``"faint"``, the peak picker's ``min_power_ratio``), when its
    frequency varies over the orders by more than ``max_frequency_spread_bins`` DFT bins
    (of the record for ERA, of the correlation functions for pLSCF)
    (reason ``"unstable"``: a pole the data do not pin down, such as a noise-level product
    whose decay and frequency the scan cannot settle), as camera shake and when incoherent
    (rougher than ``max_roughness``).
    """
    from ..motion.phase import upsample_periodic
    from .lines import peak_gain
    from .modeset import ModeSet
    from .peaks import align_phase, roughness, translation_mac
    from .spectrum import motion_power_spectrum

    st = _as_store(store)
    T = int(st.n_frames)
    freqs, power = motion_power_spectrum(
        st, fps, weights=weights if spectrum_weights is None else spectrum_weights,
        window="hann", block_bytes=block_bytes)
    clusters = scan.clusters
    w = None if weights is None else np.asarray(weights, dtype=np.float64)
    lam = np.array([c.lam for c in clusters], dtype=np.complex128)
    K = lam.size
    h, wd = st.frame_shape[:2]
    H, W = (h, wd) if output_shape is None else tuple(output_shape)
    stride = H / h
    if K:
        if scan.method == "era":
            Z, noise = project_poles(st, fps, lam, block_bytes=block_bytes)
        else:
            Z = _zoom_fields(st, fps, np.abs(lam.imag) / (2 * np.pi), block_bytes)
            noise = np.zeros(K)
    else:
        Z, noise = np.zeros((0, h, wd, 2), complex), np.zeros(0)
    rows: dict[str, list] = {k: [] for k in (
        "frequencies_hz", "damping", "damping_half_power", "amplitudes_px", "peak_bins",
        "prominences", "collinearity", "shake_mac", "camera_shake")}
    shapes, phase, rough, mac_exp, fstd, zlo, zhi = [], [], [], [], [], [], []
    df = fps / T
    for k, c in enumerate(clusters):
        real, theta, coll = align_phase(Z[k], w)
        rough.append(roughness(real, w, rough_sigma_px / stride))
        if (H, W) != (h, wd):
            real = np.moveaxis(upsample_periodic(np.moveaxis(real, -1, 0), (H, W)), 0, -1)
        norm = float(np.linalg.norm(real))
        energy = float(np.sum(np.abs(Z[k]) ** 2))
        mac_exp.append(float(max(energy - noise[k], 0.0) / energy) if energy > 0 else 0.0)
        a0 = 2.0 * norm  # the real part of the field at t = 0, full-resolution pixels
        hw = max(c.damping, 0.0) * c.frequency_hz / df
        line = float(peak_gain(np.array([hw]), T, "hann")[0] / peak_gain(np.zeros(1), T,
                                                                         "hann")[0])
        b = int(min(max(round(c.frequency_hz / df), 0), freqs.size - 1))
        rows["frequencies_hz"].append(c.frequency_hz)
        rows["damping"].append(c.damping)
        rows["damping_half_power"].append(np.nan)
        rows["amplitudes_px"].append(a0 * line)
        rows["peak_bins"].append(b)
        rows["prominences"].append(np.nan)
        rows["collinearity"].append(coll)
        smac = translation_mac(Z[k], w)
        rows["shake_mac"].append(smac)
        rows["camera_shake"].append(smac > shake_threshold)
        shapes.append((real / norm if norm > 0 else real).astype(np.float32))
        phase.append(theta % math.pi)
        fstd.append(c.frequency_std_hz)
        sz = max(c.damping_std, 0.02 * abs(c.damping))
        zlo.append(c.damping - 2.0 * sz)
        zhi.append(c.damping + 2.0 * sz)
    arr = {k: np.array(v, dtype={"peak_bins": np.int64, "camera_shake": bool}.get(k, np.float64))
           for k, v in rows.items()}
    meta = dict(metadata or {})
    meta.update(
        band_hz=list(band), window="hann", min_bin=int(meta.get("min_bin", 3)),
        roughness=[float(r) for r in rough], roughness_shape=[float(r) for r in rough],
        phase_rad=[float(p) for p in phase], frequency_std_hz=[float(s) for s in fstd],
        damping_lo=[float(v) for v in zlo], damping_hi=[float(v) for v in zhi],
        shape_mac_expected=mac_exp, close_mode_bias=[False] * K,
        analysed_index=list(range(K)), uncertainty_method=f"{scan.method}_order_spread",
        poles=scan_metadata(scan, band))
    ms = ModeSet(shapes=np.array(shapes, np.float32).reshape(K, H, W, 2), freqs_hz=freqs,
                 power=power, fps=float(fps), n_frames=T,
                 confidence=None if confidence is None else np.asarray(confidence, np.float32),
                 metadata=meta, **arr)
    if K:
        # prominence: the line's power over the spectrum's noise floor (decades)
        with np.errstate(divide="ignore", invalid="ignore"):
            ms.prominences = np.log10(ms.line_snr())
    drop = np.zeros(K, bool)
    rejected = []
    if reject_products and K > 1:
        # first: a product is named as one whatever else it fails (camera-shake modes are
        # parents too: the extractor's error on a translation makes harmonics of it)
        from .products import find_pole_products

        popts = {"bin_hz": df, **(product_options or {})}
        kept, products = find_pole_products(
            ms.frequencies_hz, ms.damping, ms.amplitudes_px, Z, fps=float(fps),
            frequency_std_hz=np.asarray(fstd), damping_std=np.array(
                [c.damping_std for c in clusters]), weights=w, decay=scan.method == "era",
            roughness=np.asarray(rough), **popts)
        for d in products:
            k = d.pop("index")
            drop[k] = True
            rejected.append({"bin": int(ms.peak_bins[k]),
                             "frequency_hz": float(ms.frequencies_hz[k]),
                             "amplitude_px": float(ms.amplitudes_px[k]),
                             "roughness": float(rough[k]), **d})
        ms.metadata["products"] = {"options": popts, "tested": int(K)}
    amp2 = np.asarray(ms.amplitudes_px, np.float64) ** 2
    top = float(amp2.max()) if K else 0.0
    # the resolution the poles were read at: the record's bin for a decay, the correlation
    # functions' for power spectra
    spread_bin = df if scan.method == "era" else float(fps) / (
        scan.settings.get("decimation", 1) * 2 * scan.settings.get("lags", T))
    for k in range(K):
        if drop[k]:
            continue
        if amp2[k] < min_power_ratio * top:
            drop[k] = True
            rejected.append({"bin": int(ms.peak_bins[k]), "frequency_hz": float(
                ms.frequencies_hz[k]), "power_ratio": float(amp2[k] / top), "reason": "faint"})
        elif fstd[k] > max_frequency_spread_bins * spread_bin:
            drop[k] = True
            rejected.append({"bin": int(ms.peak_bins[k]), "frequency_hz": float(
                ms.frequencies_hz[k]), "frequency_std_hz": float(fstd[k]),
                "reason": "unstable"})
        elif ms.camera_shake[k] and not keep_camera_shake:
            drop[k] = True
            rejected.append({"bin": int(ms.peak_bins[k]), "frequency_hz": float(
                ms.frequencies_hz[k]), "shake_mac": float(ms.shake_mac[k]),
                "reason": "camera_shake"})
        elif rough[k] > max_roughness:
            drop[k] = True
            rejected.append({"bin": int(ms.peak_bins[k]), "frequency_hz": float(
                ms.frequencies_hz[k]), "roughness": float(rough[k]), "reason": "incoherent"})
    ms.metadata["rejected"] = rejected
    return ms.select(~drop)


def _zoom_fields(store: DisplacementStore, fps: float, freqs_hz: NDArray[np.float64],
                 block_bytes: int) -> NDArray[np.complex128]:
    """``(K, H, W, 2)`` Hann-windowed DFT of every column at each (non-integer) frequency."""
    from .spectrum import window_weights

    T = int(store.n_frames)
    taper = window_weights(T, "hann")
    t = np.arange(T) / float(fps)
    E = np.exp(-2j * np.pi * np.outer(freqs_hz, t)) * taper[None, :] * (2.0 / taper.sum())
    H, W = store.frame_shape[:2]
    out = np.zeros((freqs_hz.size, store.n_columns), complex)
    P = store.block_size(block_bytes)
    for c0 in range(0, store.n_columns, P):
        c1 = min(c0 + P, store.n_columns)
        x = np.asarray(store.column_block(c0, c1), dtype=np.float64)
        out[:, c0:c1] = E @ (x - x.mean(axis=0))
    return 0.5 * out.reshape(freqs_hz.size, H, W, 2)
