"""Generalized eigenmodes K phi = lambda M phi by shift-invert Lanczos.

Modes are mass-normalized (Phi^T M Phi = I), sorted by frequency, deterministic (seeded start
vector, sign fixed so the largest entry is positive), and M-orthonormal inside clusters of
repeated eigenvalues, which symmetric objects such as cubes have.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla


@dataclass(frozen=True)
class Modes:
    """Eigenpairs over the free DOFs.

    Attributes
    ----------
    eigenvalues : (k,) lambda = omega^2 in (rad/s)^2.
    vectors : (n_free, k) mass-normalized mode shapes.
    """

    eigenvalues: np.ndarray
    vectors: np.ndarray

    @property
    def omega(self) -> np.ndarray:
        """Angular frequencies (rad/s); zero for rigid-body modes."""
        return np.sqrt(np.clip(self.eigenvalues, 0.0, None))

    @property
    def frequencies_hz(self) -> np.ndarray:
        return self.omega / (2 * np.pi)

    def __len__(self) -> int:
        return len(self.eigenvalues)


class Factorization:
    """A sparse LU of a symmetric matrix, reusable for many right-hand sides.

    Uses CHOLMOD (scikit-sparse) when installed, else SuperLU with the MMD_AT_PLUS_A ordering,
    which is several times faster than SuperLU's default on FEM matrices.
    """

    def __init__(self, A: sp.spmatrix) -> None:
        A = sp.csc_matrix(A)
        self.shape = A.shape
        try:
            from sksparse.cholmod import cholesky  # type: ignore[import-not-found]
        except ImportError:
            cholesky = None
        self._solve = None
        if cholesky is not None:
            try:
                self._solve = cholesky(A)
            except Exception:  # indefinite shifted matrices: fall back to LU
                self._solve = None
        if self._solve is None:
            self._solve = spla.splu(A, permc_spec="MMD_AT_PLUS_A").solve

    def __call__(self, b: np.ndarray) -> np.ndarray:
        return self._solve(b)

    def as_operator(self) -> spla.LinearOperator:
        return spla.LinearOperator(self.shape, matvec=self._solve, dtype=float)


def eigenmodes(
    K: sp.spmatrix,
    M: sp.spmatrix,
    k: int = 50,
    sigma: float | None = None,
    seed: int = 0,
    tol: float = 1e-10,
    cluster_rtol: float = 1e-7,
) -> Modes:
    """The ``k`` lowest eigenpairs of K phi = lambda M phi.

    Parameters
    ----------
    K, M : symmetric sparse stiffness (positive semi-definite) and mass (positive definite).
    k : number of modes; must be below the matrix size.
    sigma : shift (rad/s)^2; default a tiny negative shift, so rigid-body modes are found too.
    seed : seeds the Lanczos start vector (results are deterministic).
    tol : ARPACK relative tolerance.
    cluster_rtol : eigenvalues closer than this (relative) are treated as one repeated value.
    """
    n = K.shape[0]
    if not 1 <= k < n:
        raise ValueError(f"asked for {k} modes of a system with {n} free DOFs; need 1 <= k < {n}")
    K = sp.csc_matrix(K)
    M = sp.csc_matrix(M)
    if sigma is None:
        scale = float(np.mean(K.diagonal()) / np.mean(M.diagonal()))
        sigma = -1e-6 * scale
    if n <= 600:
        lam, phi = _dense(K, M)
        lam, phi = lam[:k], phi[:, :k]
    else:
        op = Factorization(K - sigma * M).as_operator()
        v0 = np.random.default_rng(seed).standard_normal(n)
        ncv = min(n - 1, max(2 * k + 1, k + 32))
        lam, phi = spla.eigsh(K, k=k, M=M, sigma=sigma, OPinv=op, v0=v0, ncv=ncv, tol=tol)
    order = np.argsort(lam)
    lam, phi = lam[order], phi[:, order]
    phi = _orthonormalize_clusters(lam, phi, M, cluster_rtol)
    return Modes(lam, _fix_signs(phi))


def _dense(K: sp.spmatrix, M: sp.spmatrix) -> tuple[np.ndarray, np.ndarray]:
    from scipy.linalg import eigh

    return eigh(K.toarray(), M.toarray())


def _orthonormalize_clusters(lam, phi, M, rtol):
    scale = max(np.abs(lam).max(), 1e-300)
    edges = np.flatnonzero(np.diff(lam) > rtol * np.maximum(np.abs(lam[1:]), 1e-3 * scale)) + 1
    out = phi.copy()
    for group in np.split(np.arange(len(lam)), edges):
        block = phi[:, group]
        gram = block.T @ (M @ block)
        w, v = np.linalg.eigh((gram + gram.T) / 2)
        out[:, group] = block @ (v / np.sqrt(w)) @ v.T
    return out


def _fix_signs(phi: np.ndarray) -> np.ndarray:
    idx = np.argmax(np.abs(phi), axis=0)
    signs = np.sign(phi[idx, np.arange(phi.shape[1])])
    signs[signs == 0] = 1
    return phi * signs


def cluster_frequencies(frequencies: np.ndarray, rtol: float = 1e-6) -> list[np.ndarray]:
    """Group indices of (sorted) frequencies that are equal to ``rtol``: repeated modes."""
    f = np.asarray(frequencies)
    edges = np.flatnonzero(np.diff(f) > rtol * np.maximum(np.abs(f[1:]), 1e-300)) + 1
    return np.split(np.arange(len(f)), edges)
