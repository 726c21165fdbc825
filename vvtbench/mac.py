"""The modal assurance criterion (MAC), the one definition every stage uses."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["mac", "mac_matrix"]


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
