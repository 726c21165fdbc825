"""Multi-channel spectral line fit: close modes resolved, weak modes found under strong ones.

A mode of a video record is a (damped) complex exponential in every pixel's motion.  Its
windowed DFT is a known kernel of its fractional bin frequency ``kappa`` and decay; the complex
fields of all pixels at the bins around a group of close modes are therefore a sum of a few
kernels times unknown complex shapes:

    Z[l, p] = sum_m K(l - kappa_m, h_m) A[m, p] + noise,

linear in the shapes ``A`` and non-linear in the ``(kappa_m, h_m)`` only.  :func:`fit_group`
fits it by variable projection on the group's bin Gram matrix ``G = Z W Z^H`` (a few bins
square, whatever the pixel count), so that two modes a bin apart, one peak in the power
spectrum, come out as two lines with their own shapes, and the exact kernel gives each line's
frequency and damping without scalloping or leakage bias.  :func:`clean_lines` deflates the
fitted lines from the spectrum and looks for significant lines in the residual, whose noise
floor is no longer raised by the strong modes (CLEAN, as in radio astronomy and harmonic
retrieval); see docs/modes.md, "Line fit".

>>> import numpy as np
>>> T = 256
>>> t = np.arange(T)
>>> x = np.exp(2j * np.pi * 20.3 * t / T)              # a line at bin 20.3
>>> w = 0.5 - 0.5 * np.cos(2 * np.pi * t / T)
>>> X = np.fft.fft(w * x)[18:23]
>>> K = line_kernel(np.array([20.3]), np.array([0.0]), np.arange(18, 23), T, "hann")
>>> bool(np.allclose(K[:, 0], X))
True
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import minimize

from .kernel import line_kernel

__all__ = ["LineFit", "Lines", "bin_gram", "clean_lines", "fit_group", "group_lines",
           "line_kernel", "line_shapes", "peak_gain"]


@dataclass(frozen=True)
class LineFit:
    """Lines fitted to one group of bins (:func:`fit_group`).

    Attributes
    ----------
    kappa, half_width : ndarray
        ``(M,)`` frequency and half width (bins).
    bins : ndarray
        ``(B,)`` the group's bins.
    residual_power : ndarray
        ``(B,)`` weighted power of the residual ``Z - K A`` per bin.
    rss : float
        Sum of ``residual_power``.
    power : ndarray
        ``(M,)`` weighted power each line puts in the bin at its own frequency
        (``|K(0)|^2 sum_p w_p |A_mp|^2``, comparable with the power spectrum).
    amplitude_gram : ndarray
        ``(M, M)`` ``A W A^H``: weighted inner products of the lines' shapes.
    """

    kappa: NDArray[np.float64]
    half_width: NDArray[np.float64]
    bins: NDArray[np.int64]
    residual_power: NDArray[np.float64]
    rss: float
    power: NDArray[np.float64]
    amplitude_gram: NDArray[np.complex128]

    def mac(self, i: int, j: int) -> float:
        """Weighted complex MAC of the shapes of lines ``i`` and ``j``."""
        C = self.amplitude_gram
        den = float(np.real(C[i, i] * C[j, j]))
        return float(abs(C[i, j]) ** 2 / den) if den > 0 else 1.0


def peak_gain(half_width: ArrayLike, n_frames: int, window: str = "hann") -> NDArray[np.float64]:
    """``|K(0)|``: the kernel's modulus at each line's own frequency."""
    hw = np.atleast_1d(np.asarray(half_width, np.float64))
    return np.abs(line_kernel(np.zeros(hw.size), hw, [0.0], n_frames, window)[0])


def fit_group(G: ArrayLike, bins: ArrayLike, kappa0: ArrayLike, n_frames: int, *,
              half_width0: ArrayLike | None = None, window: str = "hann",
              max_shift: float = 1.0, max_half_width: float = 8.0) -> LineFit:
    """Fit ``M`` lines to a group of bins by variable projection on their Gram matrix.

    Parameters
    ----------
    G : array_like
        ``(B, B)`` weighted Gram matrix ``Z W Z^H`` of the complex fields ``Z`` ``(B, P)`` of
        all channels at ``bins`` (:func:`bin_gram`); the fit needs nothing else.
    bins : array_like
        ``(B,)`` consecutive DFT bins.
    kappa0 : array_like
        ``(M,)`` starting frequencies (bins); each stays within ``max_shift`` bins of it.
    n_frames : int
        Record length.
    half_width0 : array_like, optional
        ``(M,)`` starting half widths (bins), default 0.05; bounded by ``[0, max_half_width]``.
    max_half_width : float, default 8
        Widest line (bins).  The kernel is exact at any width, so a line wider than the group
        is fitted too: a mode of half width 8 bins within 0.2 % in 9 bins (``clean_lines``
        passes ``2 radius``).  A bound at the fit's edge would return it, not the damping.
    window : {"hann", "none"}
        Taper used for ``Z``.

    Returns
    -------
    LineFit
        The shapes themselves are :func:`line_shapes`.
    """
    b = np.asarray(bins, np.int64)
    Gc = np.asarray(G, np.complex128)
    k0 = np.atleast_1d(np.asarray(kappa0, np.float64))
    M = k0.size
    h0 = (np.full(M, 0.05) if half_width0 is None
          else np.clip(np.atleast_1d(np.asarray(half_width0, np.float64)), 0.0, max_half_width))
    scale = float(np.real(np.trace(Gc))) or 1.0
    Gn = Gc / scale
    eps = 1e-6

    def objective(theta: NDArray) -> tuple[float, NDArray[np.float64]]:
        # f = 1 - tr(P G) with P the projector on the kernels' span; Golub-Pereyra gradient:
        # df/dtheta_j = -2 Re (K^+ G (I - P))[j] . dK_j (each column has its own parameters)
        kap, hw = theta[:M], theta[M:]
        K = line_kernel(kap, hw, b, n_frames, window)
        Q, R = np.linalg.qr(K)
        QG = Q.conj().T @ Gn
        f = 1.0 - float(np.real(np.trace(QG @ Q)))
        try:
            X = np.linalg.solve(R, QG - (QG @ Q) @ Q.conj().T)
        except np.linalg.LinAlgError:
            return f, np.zeros_like(theta)
        dk = (line_kernel(kap + eps, hw, b, n_frames, window) - K) / eps
        dh = (line_kernel(kap, hw + eps, b, n_frames, window) - K) / eps
        g = np.concatenate([-2.0 * np.real(np.einsum("mb,bm->m", X, dk)),
                            -2.0 * np.real(np.einsum("mb,bm->m", X, dh))])
        return f, g

    bounds = ([(k - max_shift, k + max_shift) for k in k0]
              + [(0.0, max_half_width)] * M)
    x0 = np.concatenate([k0, h0])
    res = minimize(objective, x0, jac=True, method="L-BFGS-B", bounds=bounds,
                   options={"maxiter": 300, "ftol": 1e-13, "gtol": 1e-11})
    theta = res.x if res.fun <= objective(x0)[0] else x0
    K = line_kernel(theta[:M], theta[M:], b, n_frames, window)
    Kp = np.linalg.pinv(K)
    C = Kp @ Gc @ Kp.conj().T
    I_P = np.eye(b.size) - K @ Kp
    rp = np.maximum(np.real(np.einsum("bc,cd,bd->b", I_P, Gc, I_P.conj())), 0.0)
    power = peak_gain(theta[M:], n_frames, window) ** 2 * np.maximum(np.real(np.diag(C)), 0.0)
    return LineFit(kappa=theta[:M].copy(), half_width=theta[M:].copy(), bins=b,
                   residual_power=rp, rss=float(rp.sum()), power=power, amplitude_gram=C)


def line_shapes(Z: ArrayLike, bins: ArrayLike, kappa: ArrayLike, half_width: ArrayLike,
                n_frames: int, window: str = "hann") -> NDArray[np.complex128]:
    """``(M, P)`` complex shapes ``A`` of given lines: least squares ``Z = K A`` on ``bins``
    (a real sinusoid of amplitude ``a`` px has ``|A| = a / 2``)."""
    K = line_kernel(kappa, half_width, bins, n_frames, window)
    return np.linalg.lstsq(K, np.asarray(Z, np.complex128), rcond=None)[0]


def bin_gram(fields: NDArray, weights: ArrayLike | None = None,
             block: int = 1 << 14) -> NDArray[np.complex128]:
    """Weighted Gram matrix ``Z W Z^H`` ``(B, B)`` of fields ``(B, P)``, by channel blocks."""
    B, P = fields.shape
    w = None if weights is None else np.asarray(weights, np.float64)
    G = np.zeros((B, B), np.complex128)
    for a in range(0, P, block):
        Zb = np.asarray(fields[:, a:a + block], np.complex128)
        Zw = Zb if w is None else Zb * w[None, a:a + block]
        G += Zw @ Zb.conj().T
    return G


def group_lines(kappa: ArrayLike, radius: int, lo: int, hi: int) -> list[tuple[NDArray, NDArray]]:
    """Group sorted line frequencies whose bin windows ``[kappa - radius, kappa + radius]``
    overlap; returns ``(line indices, bins)`` per group, bins clipped to ``[lo, hi]``."""
    k = np.asarray(kappa, np.float64)
    order = np.argsort(k, kind="stable")
    groups: list[list[int]] = []
    for i in order:
        if groups and k[i] - k[groups[-1][-1]] <= 2 * radius:
            groups[-1].append(int(i))
        else:
            groups.append([int(i)])
    out = []
    for g in groups:
        a = max(lo, int(math.floor(k[g].min())) - radius)
        z = min(hi, int(math.ceil(k[g].max())) + radius)
        out.append((np.asarray(g, np.int64), np.arange(a, z + 1, dtype=np.int64)))
    return out


@dataclass(frozen=True)
class Lines:
    """Result of :func:`clean_lines`: every line of the band, sorted by frequency.

    Attributes
    ----------
    kappa, half_width, power : ndarray
        ``(M,)`` as in :class:`LineFit`.
    shapes : ndarray
        ``(M, P)`` complex channel amplitudes (:func:`line_shapes`).
    added : ndarray
        ``(M,)`` bool, found in the residual (not among the starting peaks).
    residual : ndarray
        ``(F,)`` the power spectrum with every fitted line removed from the bins of
        ``fields`` (other bins are the spectrum's own).
    log : list of dict
        Every residual candidate tried (``bin``, ``kept``, ``reason``).
    uncertainty : LineUncertainty, optional
        ``(M,)`` standard errors of every line (:func:`.uncertainty.line_uncertainty`).
    misfit : ndarray, optional
        ``(M,)`` residual power in the five bins around each line over the residual's noise
        floor there (about 1 when the fitted lines explain those bins).
    """

    kappa: NDArray[np.float64]
    half_width: NDArray[np.float64]
    power: NDArray[np.float64]
    shapes: NDArray[np.complex128]
    added: NDArray[np.bool_]
    residual: NDArray[np.float64]
    log: list
    uncertainty: object | None = None
    misfit: NDArray[np.float64] | None = None


def clean_lines(fields: NDArray, first_bin: int, power: ArrayLike, kappa0: ArrayLike,
                n_frames: int, *, band: tuple[int, int], weights: ArrayLike | None = None,
                window: str = "hann", radius: int = 4, false_alarm: float = 0.01,
                floor_half_width_bins: int = 32, max_mac: float = 0.5,
                min_separation: float = 0.5, max_lines: int | None = None,
                max_rounds: int = 4, clusters: ArrayLike | None = None) -> Lines:
    """Fit the starting lines, then add the significant lines of the residual (CLEAN).

    Parameters
    ----------
    fields : ndarray
        ``(F', P)`` complex fields at bins ``first_bin .. first_bin + F' - 1`` (every bin of
        the band plus ``radius`` on each side).
    first_bin : int
        Bin of ``fields[0]``.
    power : array_like
        ``(F,)`` the weighted power spectrum (all bins from 0).
    kappa0 : array_like
        Starting line frequencies (bins), e.g. the picked peaks.
    n_frames : int
        Record length.
    band : tuple of int
        ``(lo, hi)`` bins in which lines are searched.
    weights : array_like, optional
        ``(P,)`` channel weights of ``power``.
    radius : int, default 4
        Bins on each side of a line in its group's window.
    false_alarm, floor_half_width_bins :
        Significance of residual lines over the residual's noise floor
        (:func:`.significance.noise_floor`).
    max_mac : float, default 0.5
        A residual line is kept only when its shape differs from every line of its group
        (weighted complex MAC below this): leakage and fit errors of a line have its shape.
    min_separation : float, default 0.5
        Least distance (bins) of a kept residual line from the other lines.
    max_lines : int, optional
        Most lines in all.
    max_rounds : int, default 4
        Residual searches.
    clusters : array_like, optional
        ``(P,)`` cluster of each channel for the lines' covariance
        (:func:`.uncertainty.block_clusters`); default each channel alone.

    Returns
    -------
    Lines
    """
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):  # many small dense problems
        return _clean_lines(fields, first_bin, power, kappa0, n_frames, band, weights,
                            window, radius, false_alarm, floor_half_width_bins, max_mac,
                            min_separation, max_lines, max_rounds, clusters)


def _clean_lines(fields: NDArray, first_bin: int, power: ArrayLike, kappa0: ArrayLike,
                 n_frames: int, band: tuple[int, int], weights: ArrayLike | None,
                 window: str, radius: int, false_alarm: float, floor_half_width_bins: int,
                 max_mac: float, min_separation: float, max_lines: int | None,
                 max_rounds: int, clusters: ArrayLike | None = None) -> Lines:
    from scipy.signal import find_peaks

    from .significance import noise_floor
    from .uncertainty import LineUncertainty, line_uncertainty

    S = np.asarray(power, np.float64)
    P = fields.shape[1]
    lo_b, hi_b = int(band[0]), int(band[1])
    N = fields.shape[0]
    last = first_bin + N - 1
    Gall = bin_gram(fields, weights)
    all_bins = np.arange(first_bin, last + 1)
    # the fitted model at every bin is U Z with U = sum_m outer(KF_m, KP_m): line m's kernel
    # (KF, cut at `reach` bins) times its row of the window pseudo-inverse (KP)
    reach = 24
    KF = np.zeros((0, N), np.complex128)
    KP = np.zeros((0, N), np.complex128)

    def deflated(rows: NDArray, keep: NDArray) -> NDArray:
        """``(E - U + U_keep)[rows]``: the data at ``rows`` without the other lines."""
        X = -(KF[:, rows].T @ KP) if KF.shape[0] else np.zeros((rows.size, N), np.complex128)
        if keep.size:
            X += KF[keep][:, rows].T @ KP[keep]
        X[np.arange(rows.size), rows] += 1.0
        return X

    def gram(bins: NDArray, keep: NDArray) -> NDArray:
        X = deflated(bins - first_bin, keep)
        return X @ Gall @ X.conj().T

    def model(kappa: NDArray, hw: NDArray, groups: list) -> tuple[NDArray, NDArray]:
        kf = np.zeros((kappa.size, N), np.complex128)
        kp = np.zeros((kappa.size, N), np.complex128)
        for idx, bins in groups:
            K = line_kernel(kappa[idx], hw[idx], all_bins, n_frames, window)
            K[np.abs(all_bins[:, None] - kappa[idx][None, :]) > reach] = 0.0
            kf[idx] = K.T
            kp[np.ix_(idx, bins - first_bin)] = np.linalg.pinv(K[bins - first_bin])
        return kf, kp

    widest = 2.0 * radius
    kappa = np.sort(np.asarray(kappa0, np.float64))
    hw = np.full(kappa.size, 0.05)
    added = np.zeros(kappa.size, bool)
    log: list[dict] = []
    fits: list[tuple[NDArray, LineFit]] = []
    for round_ in range(max_rounds + 1):
        groups = group_lines(kappa, radius, first_bin, last)
        if KF.shape[0] != kappa.size:  # lines were added: the model of the previous fits
            KF, KP = model(kappa, hw, groups)
        fits = [(idx, fit_group(gram(bins, idx), bins, kappa[idx], n_frames,
                                half_width0=hw[idx], window=window, max_half_width=widest))
                for idx, bins in groups]
        for idx, f in fits:
            kappa[idx], hw[idx] = f.kappa, f.half_width
        KF, KP = model(kappa, hw, groups)
        X = deflated(np.arange(N), np.zeros(0, np.int64))
        resid = S.copy()
        resid[first_bin:last + 1] = np.maximum(np.real(np.sum((X @ Gall) * X.conj(), axis=1)),
                                               0.0)
        if round_ == max_rounds or (max_lines is not None and kappa.size >= max_lines):
            break
        inband = slice(lo_b, hi_b + 1)
        nf = noise_floor(resid, inband, false_alarm=false_alarm,
                         half_width_bins=floor_half_width_bins)
        thr = nf.threshold()
        logr = np.log10(np.maximum(resid, np.max(resid) * 1e-15 + 1e-300))
        pk, _ = find_peaks(logr)
        pk = pk[(pk >= lo_b) & (pk <= hi_b) & (resid[pk] > thr[pk])]
        pk = pk[np.argsort(-(resid[pk] / thr[pk]), kind="stable")]
        touched: set[int] = set()
        n_new = 0
        for c in pk:
            c = int(c)
            if kappa.size and np.min(np.abs(kappa - c)) < min_separation:
                continue
            n_model = KF.shape[0]  # lines added in this round are not in the model yet
            if np.any(np.abs(kappa[n_model:] - c) <= 2 * radius):
                continue
            near = np.flatnonzero(np.abs(kappa[:n_model] - c) <= 2 * radius)
            key = int(near[0]) if near.size else -1 - c
            if key in touched:
                continue
            k_try = np.concatenate([kappa[near], [float(c)]])
            h_try = np.concatenate([hw[near], [0.05]])
            lo_w = max(first_bin, int(math.floor(k_try.min())) - radius)
            hi_w = min(last, int(math.ceil(k_try.max())) + radius)
            bins = np.arange(lo_w, hi_w + 1)
            Gw = gram(bins, near)
            with_ = fit_group(Gw, bins, k_try, n_frames, half_width0=h_try, window=window,
                              max_half_width=widest)
            rss0 = (fit_group(Gw, bins, kappa[near], n_frames, half_width0=hw[near],
                              window=window, max_half_width=widest).rss
                    if near.size else float(np.real(np.trace(Gw))))
            j = k_try.size - 1
            kn = with_.kappa[j]
            ki = int(round(kn))
            t_new = float(thr[min(max(ki, 0), thr.size - 1)])
            sep = (float(np.min(np.abs(with_.kappa[:j] - kn))) if j else np.inf)
            mac = max((with_.mac(i, j) for i in range(j)), default=0.0)
            reason = None
            if not lo_b <= kn <= hi_b:
                reason = "band"
            elif with_.power[j] <= t_new:
                reason = "not significant"
            elif rss0 - with_.rss <= t_new:
                reason = "no fit gain"
            elif sep < min_separation:
                reason = "separation"
            elif mac >= max_mac:
                reason = "shape of a neighbour"
            log.append({"bin": c, "kappa": float(kn), "round": round_, "mac": float(mac),
                        "power_over_threshold": float(with_.power[j] / t_new),
                        "kept": reason is None, "reason": reason})
            touched.add(key)
            if reason is not None:
                continue
            kappa = np.concatenate([kappa, [kn]])
            hw = np.concatenate([hw, [with_.half_width[j]]])
            added = np.concatenate([added, [True]])
            n_new += 1
            if max_lines is not None and kappa.size >= max_lines:
                break
        if not n_new:
            break
        order = np.argsort(kappa, kind="stable")
        kappa, hw, added = kappa[order], hw[order], added[order]
    M = kappa.size
    shapes = np.zeros((M, P), np.complex128)
    pw = np.zeros(M)
    unc = {name: np.full(M, np.nan) for name in
           ("kappa_std", "half_width_std", "cov_kappa_half_width", "max_correlation",
            "shape_mac")}
    misfit = np.full(M, np.nan)
    lo_f, hi_f = max(lo_b, first_bin), min(hi_b, last)
    floor = noise_floor(resid, slice(lo_f, hi_f + 1), false_alarm=false_alarm,
                        half_width_bins=floor_half_width_bins).floor
    w_all = None if weights is None else np.asarray(weights, np.float64)
    cl = None if clusters is None else np.asarray(clusters)
    for idx, f in fits:
        X = deflated(f.bins - first_bin, idx)
        cols = np.flatnonzero(np.any(X != 0, axis=0))
        Zg = X[:, cols] @ fields[cols]
        shapes[idx] = line_shapes(Zg, f.bins, f.kappa, f.half_width, n_frames, window)
        pw[idx] = f.power
        u = line_uncertainty(Zg, f.bins, f.kappa, f.half_width, n_frames, weights=w_all,
                             clusters=cl, window=window)
        for name in unc:
            unc[name][idx] = getattr(u, name)
        for m, k in zip(idx, f.kappa, strict=True):
            near = np.arange(max(int(round(k)) - 2, first_bin), min(int(round(k)) + 3, last + 1))
            expected = float(np.sum(floor[near]))
            misfit[m] = float(np.sum(resid[near])) / expected if expected > 0 else np.inf
    return Lines(kappa=kappa, half_width=hw, power=pw, shapes=shapes, added=added,
                 residual=resid, log=log, uncertainty=LineUncertainty(**unc), misfit=misfit)
