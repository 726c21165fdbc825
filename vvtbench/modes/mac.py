"""The modal assurance criterion (MAC), the one definition every stage uses."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["mac", "mac_matrix", "subspace_mac"]


def mac_matrix(a: ArrayLike, b: ArrayLike) -> np.ndarray:
    """MAC between the rows of ``a`` (p, d) and of ``b`` (q, d), complex-safe:
    ``|a_i^H b_j|^2 / ((a_i^H a_i)(b_j^H b_j))``, 0 where either row is zero.

    >>> mac_matrix([[1.0, 0.0], [1.0, 1.0]], [[2.0, 0.0]]).round(3).tolist()
    [[1.0], [0.5]]
    """
    a = np.atleast_2d(np.asarray(a))
    b = np.atleast_2d(np.asarray(b))
    num = np.abs(np.conj(a) @ b.T) ** 2
    den = np.outer(np.einsum("ij,ij->i", np.conj(a), a).real,
                   np.einsum("ij,ij->i", np.conj(b), b).real)
    return np.divide(num, den, out=np.zeros(num.shape), where=den > 0)


def mac(a: ArrayLike, b: ArrayLike, weights: ArrayLike | None = None) -> float:
    """MAC of two fields of the same shape (flattened); ``weights`` (``(H, W)``) apply to
    ``(H, W, 2)`` fields."""
    x, y = np.asarray(a), np.asarray(b)
    if x.shape != y.shape:
        raise ValueError(f"shapes differ: {x.shape} vs {y.shape}")
    if weights is not None:
        s = np.sqrt(np.asarray(weights, dtype=np.float64))[..., None]
        x, y = x * s, y * s
    return float(mac_matrix(x.ravel(), y.ravel())[0, 0])


def subspace_mac(a: ArrayLike, basis: ArrayLike) -> np.ndarray | float:
    """MAC of ``a`` with the span of the rows of ``basis`` (m, d): the fraction of
    ``|a|^2`` in that span, which no change of basis inside it alters. ``a`` is one vector
    (d,), giving a float, or rows (p, d), giving one value per row. With one basis row it is
    :func:`mac_matrix`; 0 for a zero vector or an empty span.

    >>> subspace_mac([[1.0, 1.0, 0.0], [0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    array([1., 0.])
    >>> round(subspace_mac([1.0, 1.0], [[1.0, 0.0]]), 3)
    0.5
    """
    x = np.asarray(a, dtype=np.float64)
    rows = np.atleast_2d(x)
    b = np.atleast_2d(np.asarray(basis, dtype=np.float64)).reshape(-1, rows.shape[1])
    q, r = np.linalg.qr(b.T)
    keep = np.abs(np.diag(r)) > 1e-12 * max(float(np.abs(r).max(initial=0.0)), 1e-300)
    num = np.sum((q[:, keep].T @ rows.T) ** 2, axis=0)
    den = np.einsum("ij,ij->i", rows, rows)
    out = np.minimum(np.divide(num, den, out=np.zeros(num.shape), where=den > 0), 1.0)
    return float(out[0]) if x.ndim == 1 else out
