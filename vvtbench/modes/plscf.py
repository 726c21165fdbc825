"""Least-squares complex-frequency identification (LSCF, and its poly-reference form).

The frequency-domain counterpart of :mod:`.era`.  Every channel's spectrum over a band is
modelled as a right matrix fraction with one denominator common to all channels,

    Y_c(omega) ~ B_c(Omega) A(Omega)^-1,     Omega = exp(-i omega dt),

with ``A`` and ``B_c`` polynomials of degree ``n`` in ``Omega`` and real coefficients.  The
linearised least squares ``sum_c sum_l |B_c(Omega_l) - Y_c(omega_l) A(Omega_l)|^2`` eliminates
the numerators (the reduced normal equations ``M = sum_c T_c - S_c^T R^-1 S_c``), so the
denominator of every order costs a small ``n x n`` solve whatever the number of channels; its
roots are the poles.

Two kinds of spectra are modelled, the records of two kinds of experiment:

* ``kind="decay"``: the DFT (no window) of a free decay.  At the DFT's bins the spectrum of
  ``r z^t`` over ``T`` frames is exactly ``r (1 - z^T) / (1 - z Omega)``, a rational function of
  ``Omega`` with the pole's root at ``Omega = 1 / z``; one "reference" (the initial state),
  ``A`` scalar.
* ``kind="half"``: positive power spectra (``Y_{c,r}`` between every channel and a few
  reference channels, from the correlation functions at positive lags), the input of output-only
  poly-reference LSCF (PolyMAX) for forced, swept or ambient responses.  ``A`` is an ``R x R``
  matrix polynomial for ``R`` references and the poles are the eigenvalues of its companion
  matrix.

A band of a spectrum can be fitted alone: the modes outside it are taken up by extra poles that
the stabilisation diagram (:mod:`.stabilization`) does not keep, so a band with weak modes is
not dominated by strong ones elsewhere (``band`` of :func:`lscf_orders`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .era import PoleSet

__all__ = ["half_spectra", "lscf_orders"]


def half_spectra(y: ArrayLike, references: ArrayLike, n_lags: int,
                 decay: float = 0.01) -> NDArray[np.complex128]:
    """Positive power spectra of ``y`` against its ``references`` channels: the DFT of the
    correlation functions at lags ``0 .. n_lags - 1`` under an exponential window that falls
    to ``decay`` at the last lag (its damping is added to every pole: undone by
    :func:`lscf_orders` with ``exp_window``).

    Returns ``(n_lags + 1, m, R)`` spectra at the ``rfft`` bins of ``2 n_lags`` samples.
    """
    Y = np.asarray(y, dtype=np.float64)
    Y = Y - Y.mean(axis=0)
    ref = np.asarray(references, dtype=np.int64).reshape(-1)
    T = Y.shape[0]
    L = int(n_lags)
    if not 1 < L < T:
        raise ValueError(f"n_lags must be in (1, {T}), got {n_lags}")
    nfft = 1 << int(np.ceil(np.log2(2 * T)))
    Fy = np.fft.rfft(Y, n=nfft, axis=0)
    R = np.fft.irfft(Fy[:, :, None] * np.conj(Fy[:, None, ref]), n=nfft, axis=0)[:L] / T
    win = np.exp(np.log(decay) * np.arange(L) / (L - 1))
    R = R * win[:, None, None]
    R[0] *= 0.5  # the positive half: the lag-0 term counted once of the two halves
    return np.fft.rfft(R, n=2 * L, axis=0)


def lscf_orders(spectra: ArrayLike, freqs_hz: ArrayLike, dt: float, orders: ArrayLike, *,
                band: tuple[float, float] | None = None,
                weights: ArrayLike | None = None,
                exp_window: float | None = None) -> list[PoleSet]:
    """Poles of a common-denominator rational fit of ``spectra`` at every order of ``orders``.

    Parameters
    ----------
    spectra : array_like
        ``(F, m)`` complex spectra (``kind="decay"``: the DFT of each channel of a free decay)
        or ``(F, m, R)`` positive power spectra against ``R`` references (:func:`half_spectra`).
    freqs_hz : array_like
        ``(F,)`` frequencies (Hz) of the rows.
    dt : float
        Sampling interval (s) of the record the spectra come from.
    orders : array_like of int
        Polynomial degrees ``n`` (``n R`` poles each).
    band : tuple of float, optional
        Fit only the rows in ``[band[0], band[1]]`` Hz.
    weights : array_like, optional
        ``(F,)`` weights of the rows (e.g. inverse noise power).
    exp_window : float, optional
        The damping rate (1/s) an exponential window added (:func:`half_spectra`): removed
        from every pole.

    Returns
    -------
    list of PoleSet
        One per order: poles with ``omega > 0`` and, per pole, the channels' shape (the
        numerators' residue direction) and its size.

    Examples
    --------
    >>> dt, T = 1 / 500.0, 1500
    >>> t = np.arange(T) * dt
    >>> lam = 2 * np.pi * 20 * (-0.03 + 1j * np.sqrt(1 - 0.03**2))
    >>> y = np.stack([np.exp(lam * t).real, -2 * np.exp(lam * t).real], -1)
    >>> f = np.fft.rfftfreq(T, dt)
    >>> (ps,) = lscf_orders(np.fft.rfft(y, axis=0), f, dt, [2], band=(3, 60))
    >>> round(float(ps.frequency_hz[0]), 4), round(float(ps.damping[0]), 4)
    (20.0, 0.03)
    """
    S = np.asarray(spectra, dtype=np.complex128)
    f = np.asarray(freqs_hz, dtype=np.float64).reshape(-1)
    if S.ndim == 2:
        S = S[:, :, None]
    if S.ndim != 3 or S.shape[0] != f.size:
        raise ValueError(f"spectra must be (F, m) or (F, m, R) with F = {f.size}, got {S.shape}")
    if not dt > 0:
        raise ValueError(f"dt must be > 0, got {dt!r}")
    sel = np.ones(f.size, bool) if band is None else (f >= band[0]) & (f <= band[1])
    S, f = S[sel], f[sel]
    w = np.ones(f.size) if weights is None else np.asarray(weights, np.float64).reshape(-1)[sel]
    F, m, R = S.shape
    Om = np.exp(-2j * np.pi * f * dt)
    sw = np.sqrt(w)
    out: list[PoleSet] = []
    for n in [int(k) for k in np.atleast_1d(orders)]:
        if n < 1 or F < n + 2:
            raise ValueError(f"order {n}: need at least {n + 2} frequency lines, have {F}")
        X = sw[:, None] * Om[:, None] ** np.arange(n + 1)[None, :]     # (F, n+1)
        Rm = np.real(X.conj().T @ X)
        Rinv = np.linalg.inv(Rm)
        M = np.zeros(((n + 1) * R, (n + 1) * R))
        Ss = []
        for c in range(m):
            # Y_c X_kron: rows of -kron(X_l, S_c(l))  (F, (n+1) R)
            Yc = -(X[:, :, None] * S[:, c, None, :]).reshape(F, (n + 1) * R)
            Sc = np.real(X.conj().T @ Yc)
            M += np.real(Yc.conj().T @ Yc) - Sc.T @ Rinv @ Sc
            Ss.append(Sc)
        # the constant coefficient (an R x R block) set to the identity: A(Omega) = I + A_1
        # Omega + ... + A_n Omega^n, so mu^n A(1 / mu) is monic in mu = 1 / Omega = z and the
        # eigenvalues of its companion matrix are the discrete poles themselves
        top = np.linalg.solve(M[R:, R:], -M[R:, :R])
        alpha = np.vstack([np.eye(R), top])                              # ((n+1) R, R)
        Ablk = alpha.reshape(n + 1, R, R)
        Cm = np.zeros((n * R, n * R))
        if n > 1:
            Cm[R:, :-R] = np.eye((n - 1) * R)
        for j in range(n):
            Cm[:R, j * R:(j + 1) * R] = -Ablk[j + 1]
        z, vecs = np.linalg.eig(Cm)
        roots = 1.0 / z
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = np.log(z) / dt
        if exp_window:
            lam = lam + float(exp_window)
        keep = np.isfinite(lam) & (lam.imag > 0)
        # shapes: numerators at the root, applied to the denominator's null vector there
        B = np.stack([-(Rinv @ Sc @ alpha) for Sc in Ss], 0)             # (m, n+1, R)
        ok = np.flatnonzero(keep)
        shapes = np.zeros((ok.size, m), complex)
        amp = np.zeros(ok.size)
        for i, j in enumerate(ok):
            v = vecs[:R, j] if R > 1 else np.ones(1)
            pw = roots[j] ** np.arange(n + 1)
            num = np.einsum("j,mjr,r->m", pw, B, v)
            dA = np.einsum("j,jrs,s->r", np.arange(n + 1) * roots[j] ** np.maximum(
                np.arange(n + 1) - 1, 0), Ablk, v)
            nv = np.linalg.norm(num)
            shapes[i] = num / nv if nv > 0 else num
            amp[i] = nv / max(float(np.linalg.norm(dA)), 1e-300)
        lam_k = lam[ok]
        order = np.argsort(lam_k.imag)
        out.append(PoleSet(n * R, lam_k[order], shapes[order], amp[order]))
    return out
