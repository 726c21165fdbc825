"""The eigensystem realisation algorithm (ERA) on a free decay of reduced channels.

A free decay of a linear system, sampled every ``dt``, is ``y(t) = C A^t x0``: a sum of damped
exponentials ``sum_k phi_k z_k^t`` with the discrete poles ``z_k = exp(lambda_k dt)``, whatever
plucked it.  The block Hankel matrix of the record

    H0 = [[y(0),     y(1),     ..., y(q-1)],
          [y(d),     y(d+1),   ..., y(d+q-1)],
          ...
          [y((p-1)d), ...,          y((p-1)d+q-1)]]

has rank ``n`` (the state dimension) and factors as ``O X`` (observability times states).  Its
SVD gives ``O`` up to a change of basis; the one-sample shift ``H1`` (every column moved on by
one frame) gives ``A = O^+ H1 X^+`` and the first block row ``C``.  Truncating the SVD at order
``n`` gives the poles of the ``n``-state model: :func:`era_orders` returns them for every
order of a list, the input of a stabilisation diagram (:mod:`.stabilization`).

Rows may be spaced ``d`` frames apart (``row_step``) so that a few block rows span the slow
modes' periods; columns use every frame, and the one-frame shift ``H1`` gives ``z`` itself,
not ``z^d``, so nothing aliases.  The SVD is taken of the ``(p m, p m)`` Gram matrix
``H0 H0^T``, accumulated over column chunks, so the record length costs time, not memory.

Unlike covariance-driven SSI, nothing here assumes a stationary output: the record is the
decay itself (a stationary SSI halves the damping of a free decay's light modes).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["PoleSet", "era_orders", "poles_to_modal"]


@dataclass
class PoleSet:
    """Poles of one model order.

    Attributes
    ----------
    order : int
        Model order (states).
    lam : ndarray
        ``(k,)`` complex continuous-time poles ``lambda = sigma + i omega`` (rad/s), one per
        conjugate pair (``omega > 0``).
    shapes : ndarray
        ``(k, m)`` complex shapes in the reduced channels (unit norm).
    amplitude : ndarray
        ``(k,)`` size of each pole's contribution to the record (channel units; for a free
        decay the norm of its initial amplitude vector).
    """

    order: int
    lam: NDArray[np.complex128]
    shapes: NDArray[np.complex128]
    amplitude: NDArray[np.float64]

    @property
    def frequency_hz(self) -> NDArray[np.float64]:
        """Undamped natural frequencies ``|lambda| / 2 pi`` (Hz)."""
        return np.abs(self.lam) / (2 * np.pi)

    @property
    def damping(self) -> NDArray[np.float64]:
        """Damping ratios ``-Re(lambda) / |lambda|``."""
        a = np.abs(self.lam)
        return np.divide(-self.lam.real, a, out=np.zeros(a.shape), where=a > 0)


def poles_to_modal(lam: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(frequency_hz, damping)`` of continuous-time poles.

    >>> f, z = poles_to_modal([-0.1 * 2 * np.pi * 10 + 1j * 2 * np.pi * 10 * np.sqrt(0.99)])
    >>> round(float(f[0]), 6), round(float(z[0]), 6)
    (10.0, 0.1)
    """
    lam = np.asarray(lam, dtype=np.complex128)
    a = np.abs(lam)
    return a / (2 * np.pi), np.divide(-lam.real, a, out=np.zeros(a.shape), where=a > 0)


def _gram(y: NDArray[np.float64], p: int, d: int, q: int, chunk: int
          ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``H0 H0^T`` and ``H1 H0^T`` of the block Hankel matrices (``p`` block rows ``d`` frames
    apart, ``q`` columns), accumulated over column chunks."""
    m = y.shape[1]
    G0 = np.zeros((p * m, p * m))
    G1 = np.zeros((p * m, p * m))
    for j0 in range(0, q, chunk):
        j1 = min(q, j0 + chunk)
        H0 = np.concatenate([y[i * d + j0:i * d + j1].T for i in range(p)], axis=0)
        H1 = np.concatenate([y[i * d + j0 + 1:i * d + j1 + 1].T for i in range(p)], axis=0)
        G0 += H0 @ H0.T
        G1 += H1 @ H0.T
    return G0, G1


def _matrix_root(M: NDArray[np.float64], d: int) -> NDArray[np.complex128]:
    """A ``d``-th root of ``M`` with the principal root of each eigenvalue."""
    w, V = np.linalg.eig(M)
    return (V * (w.astype(complex) ** (1.0 / d))[None, :]) @ np.linalg.inv(V)


def era_orders(y: ArrayLike, dt: float, orders: ArrayLike, *, block_rows: int | None = None,
               row_step: int = 1, start: int = 0, max_columns: int | None = None,
               chunk: int = 4096, shift: str = "rows") -> list[PoleSet]:
    """Poles of a free decay at every model order of ``orders`` (ERA, module docstring).

    Parameters
    ----------
    y : array_like
        ``(T, m)`` record, real, sample 0 the start of the decay (``start`` skips frames).
    dt : float
        Sampling interval (s).
    orders : array_like of int
        Model orders (states), each at most ``block_rows * m``.
    block_rows : int, optional
        ``p``; default ``max(4, 1 + ceil(2 n / m))`` for the largest order ``n``: a real mode
        shape fills one row of a block row for its two conjugate states, so the shift needs
        ``(p - 1) m`` well above ``n``.
    row_step : int, default 1
        ``d``: frames between block rows.
    start : int, default 0
        First frame used.
    max_columns : int, optional
        ``q``; default every column the record allows.
    chunk : int, default 4096
        Columns per accumulation step.

    Returns
    -------
    list of PoleSet
        One per order (poles with ``omega > 0``; a real pole has no frequency and is left out).

    Examples
    --------
    >>> t = np.arange(400) / 200.0
    >>> lam = 2 * np.pi * 12 * (-0.02 + 1j * np.sqrt(1 - 0.02**2))
    >>> y = np.stack([np.exp(lam * t).real, 0.5 * np.exp(lam * t).real], -1)
    >>> (ps,) = era_orders(y, 1 / 200.0, [2])
    >>> f, z = poles_to_modal(ps.lam)
    >>> round(float(f[0]), 4), round(float(z[0]), 4)
    (12.0, 0.02)
    """
    Y = np.asarray(y, dtype=np.float64)
    if Y.ndim == 1:
        Y = Y[:, None]
    if Y.ndim != 2:
        raise ValueError(f"y must be (T, m), got {Y.shape}")
    if not dt > 0:
        raise ValueError(f"dt must be > 0, got {dt!r}")
    Y = Y[int(start):]
    T, m = Y.shape
    orders = [int(n) for n in np.atleast_1d(orders)]
    if not orders or min(orders) < 1:
        raise ValueError(f"orders must be integers >= 1, got {orders}")
    d = max(1, int(row_step))
    n_max = max(orders)
    p = int(block_rows) if block_rows is not None else max(4, 1 + int(np.ceil(2 * n_max / m)))
    if p < 2:
        raise ValueError(f"block_rows must be >= 2, got {p}")
    if p * m < n_max:
        raise ValueError(f"order {n_max} exceeds the Hankel rows {p} x {m} channels")
    q = T - (p - 1) * d - 1
    if max_columns is not None:
        q = min(q, int(max_columns))
    if q < n_max:
        raise ValueError(f"the record ({T} frames) is too short for order {n_max} with "
                         f"{p} block rows {d} frames apart")
    G0, G1 = _gram(Y, p, d, q, max(1, int(chunk)))
    s2, U = np.linalg.eigh(G0)
    idx = np.argsort(s2)[::-1]
    s2, U = np.maximum(s2[idx], 0.0), U[:, idx]
    s = np.sqrt(s2)
    out: list[PoleSet] = []
    for n in orders:
        Un, sn = U[:, :n], s[:n]
        if not sn[-1] > 0:
            out.append(PoleSet(n, np.zeros(0, complex), np.zeros((0, m), complex), np.zeros(0)))
            continue
        # H0 = U S V^T, so V^T = S^-1 U^T H0 and X = S^1/2 V^T; A = O^+ H1 X^+ with
        # O = U S^1/2: A = S^-1/2 U^T H1 V S^-1/2 = S^-1/2 U^T (H1 H0^T) U S^-3/2
        isq = 1.0 / np.sqrt(sn)
        if shift == "rows":
            # shift invariance of the observability matrix O = U S^1/2 (rows d apart: A^d)
            O = Un * np.sqrt(sn)[None, :]
            Ad = np.linalg.lstsq(O[:-m], O[m:], rcond=None)[0]
            A = Ad if d == 1 else _matrix_root(Ad, d)
        else:
            A = (isq[:, None] * (Un.T @ G1 @ Un)) * (isq**3)[None, :]
        C = Un[:m] * np.sqrt(sn)[None, :]
        z, psi = np.linalg.eig(A)
        # initial state x0 = X[:, 0] = S^1/2 V^T e_0 = S^-1/2 U^T H0 e_0
        h0 = np.concatenate([Y[i * d] for i in range(p)])
        x0 = isq * (Un.T @ h0)
        w = np.linalg.solve(psi, x0)  # modal initial amplitudes
        keep = z.imag > 1e-12
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = np.log(z[keep]) / dt
        phi = C @ psi[:, keep]
        amp_vec = phi * w[keep][None, :]
        amp = 2.0 * np.linalg.norm(amp_vec, axis=0)
        norms = np.linalg.norm(phi, axis=0)
        shapes = (phi / np.where(norms > 0, norms, 1.0)[None, :]).T
        ok = np.isfinite(lam)
        order = np.argsort(lam[ok].imag)
        out.append(PoleSet(n, lam[ok][order], shapes[ok][order], amp[ok][order]))
    return out
