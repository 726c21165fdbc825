"""Generalized eigenmodes K phi = lambda M phi by shift-invert Lanczos.

Modes are mass-normalized (Phi^T M Phi = I), sorted by frequency and canonical, so that two
machines whose floating-point results differ in the last bits give the same modes to rounding
(not modes that differ by a sign or a rotation):

* **sign:** the entry of largest magnitude is positive; entries within ``SIGN_RTOL`` of the
  largest count as tied (mirror-symmetric modes have several), and the first of them in DOF
  order decides;
* **repeated eigenvalues:** a cluster (eigenvalues equal to ``cluster_rtol``, which symmetric
  objects such as square cubes and drums have) gets the M-orthonormal basis of its subspace
  nearest to the M-projections of fixed probe vectors (:func:`probe_vectors`, a hash of the DOF
  index: no random generator), in probe order; any basis the eigen-solver returns for the same
  subspace gives the same one.

:func:`single_threaded` runs code with one BLAS and OpenMP thread, so that results do not
depend on the number of cores (the data generator runs inside it).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

SIGN_RTOL = 1e-6
"""Entries within this relative distance of a mode's largest magnitude tie for its sign: far
above the 1e-12 by which the same mode differs between machines, far below the spread of
distinct entries of a mode."""


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
                self._solve = cholesky(A, ordering_method="metis")
            except Exception:  # indefinite (shifted) matrices: fall back to LU
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
    method: str = "auto",
) -> Modes:
    """The ``k`` lowest eigenpairs of K phi = lambda M phi.

    Parameters
    ----------
    K, M : symmetric sparse stiffness (positive semi-definite) and mass (positive definite).
    k : number of modes; must be below the matrix size.
    sigma : shift (rad/s)^2; default a tiny negative shift, so rigid-body modes are found too.
    seed : seeds the Lanczos start vector (results are deterministic).
    tol : normwise backward error (see :func:`backward_errors`) every mode must reach
        ("block"); ARPACK's relative tolerance ("arpack").
    cluster_rtol : eigenvalues closer than this (relative) are treated as one repeated value.
    method : "auto" (ARPACK below 5000 DOFs, where it is faster, else block); "block"
        (shift-invert block Krylov with Rayleigh-Ritz restarts: one sparse factorization,
        block solves; handles repeated eigenvalues naturally); "arpack" (scipy's eigsh in
        shift-invert mode); "dense" (LAPACK, small systems only).
        Systems of at most 600 DOFs always use "dense".
    """
    n = K.shape[0]
    dense = n <= 600 or method == "dense"
    if not 1 <= k <= n or (k == n and not dense):
        limit = n if dense else n - 1
        raise ValueError(f"asked for {k} modes of a system with {n} free DOFs; need 1..{limit}")
    K = sp.csc_matrix(K)
    M = sp.csc_matrix(M)
    if sigma is None:
        scale = float(np.mean(K.diagonal()) / np.mean(M.diagonal()))
        sigma = -1e-6 * scale
    if method not in ("auto", "block", "arpack", "dense"):
        raise ValueError(f"method must be 'auto', 'block', 'arpack' or 'dense', got {method!r}")
    if method == "auto":
        method = "arpack" if n < 5_000 else "block"
    if dense:
        lam, phi = _dense(K, M)
        lam, phi = lam[:k], phi[:, :k]
    elif method == "block":
        lam, phi = _block_krylov(K, M, k, sigma, seed, tol)
    else:
        op = Factorization(K - sigma * M).as_operator()
        v0 = np.random.default_rng(seed).standard_normal(n)
        ncv = min(n - 1, max(2 * k + 1, k + 32))
        lam, phi = spla.eigsh(K, k=k, M=M, sigma=sigma, OPinv=op, v0=v0, ncv=ncv, tol=tol)
    order = np.argsort(lam, kind="stable")
    lam, phi = lam[order], phi[:, order]
    phi = _orthonormalize_clusters(lam, phi, M, cluster_rtol)
    return Modes(lam, canonical_signs(phi))


def _m_orthonormalize(block, basis, M, drop=1e-10):
    """Columns of ``block`` made M-orthonormal to ``basis`` and to each other (CGS2)."""
    for _ in range(2):
        if basis is not None:
            block = block - basis @ (basis.T @ (M @ block))
        gram = block.T @ (M @ block)
        w, v = np.linalg.eigh((gram + gram.T) / 2)
        keep = w > drop * max(w.max(), 1e-300)
        block = block @ (v[:, keep] / np.sqrt(w[keep]))
    return block


def _block_krylov(K, M, k, sigma, seed, tol, max_restarts=40):
    """Lowest k eigenpairs by restarted block Krylov on (K - sigma M)^-1 M with Rayleigh-Ritz.

    Each restart builds the basis [S x, S^2 x, ..., S^depth x] (S = (K - sigma M)^-1 M) from
    the unconverged Ritz vectors x, keeps the converged ones (soft locking), and takes the
    Ritz pairs of K, M on it. One factorization serves every block solve.
    """
    from threadpoolctl import threadpool_limits

    n = K.shape[0]
    solve = Factorization(K - sigma * M)
    p = min(n // 4, k + max(10, k // 5))
    depth = 4
    x = np.random.default_rng(seed).standard_normal((n, p))
    active = np.ones(p, dtype=bool)
    norms = (abs(K).sum(axis=1).max(), abs(M).sum(axis=1).max())
    with threadpool_limits(limits=1, user_api="blas"):
        for _ in range(max_restarts):
            blocks = [x[:, ~active]] if not active.all() else []
            basis = np.hstack(blocks) if blocks else None
            block = solve(M @ x[:, active])
            for d in range(depth):
                block = _m_orthonormalize(block, basis, M)
                if block.shape[1] == 0:
                    break
                blocks.append(block)
                basis = np.hstack(blocks)
                if d < depth - 1:
                    block = solve(M @ block)
            kr = basis.T @ (K @ basis)
            theta, y = np.linalg.eigh((kr + kr.T) / 2)
            x = basis @ y[:, :p]
            res = backward_errors(K, M, theta[:p], x, norms)
            if res[:k].max() < tol:
                return theta[:k], x[:, :k]
            active = res >= tol
            active[k:] = True
    raise RuntimeError(
        f"block eigensolver did not converge after {max_restarts} restarts "
        f"(worst backward error {res[:k].max():.2e} > {tol:.0e})"
    )


def backward_errors(K, M, lam, x, norms=None) -> np.ndarray:
    """Normwise backward error of each eigenpair: ||K x - lam M x|| / ((|K| + |lam| |M|) ||x||).

    Near machine precision for an exact eigenpair, whatever the spread of the spectrum.
    """
    if norms is None:
        norms = (abs(K).sum(axis=1).max(), abs(M).sum(axis=1).max())
    r = np.linalg.norm(K @ x - (M @ x) * lam, ord=np.inf, axis=0)
    scale = (norms[0] + np.abs(lam) * norms[1]) * np.linalg.norm(x, ord=np.inf, axis=0)
    return r / scale


def _dense(K: sp.spmatrix, M: sp.spmatrix) -> tuple[np.ndarray, np.ndarray]:
    from scipy.linalg import eigh

    return eigh(K.toarray(), M.toarray())


def _orthonormalize_clusters(lam, phi, M, rtol):
    """Each cluster of eigenvalues equal to ``rtol`` made M-orthonormal (Loewdin) and, when it
    has several modes, turned to its canonical basis (the module's docstring)."""
    scale = max(np.abs(lam).max(), 1e-300)
    edges = np.flatnonzero(np.diff(lam) > rtol * np.maximum(np.abs(lam[1:]), 1e-3 * scale)) + 1
    out = phi.copy()
    for group in np.split(np.arange(len(lam)), edges):
        block = phi[:, group]
        gram = block.T @ (M @ block)
        w, v = np.linalg.eigh((gram + gram.T) / 2)
        block = block @ (v / np.sqrt(w)) @ v.T
        if len(group) > 1:
            c = block.T @ (M @ probe_vectors(block.shape[0], len(group)))
            u, _, vt = np.linalg.svd(c)
            block = block @ (u @ vt)  # the basis nearest to the probes' projections
        out[:, group] = block
    return out


def probe_vectors(n: int, m: int) -> np.ndarray:
    """``(n, m)`` fixed vectors with entries in [-1, 1), from the SplitMix64 hash of (row,
    column): the same on every machine and with every NumPy version."""
    i = np.arange(n, dtype=np.uint64)[:, None]
    j = np.arange(1, m + 1, dtype=np.uint64)[None, :]
    x = i * np.uint64(0x9E3779B97F4A7C15) + j * np.uint64(0xD1B54A32D192ED03)  # wraps mod 2^64
    x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    x = x ^ (x >> np.uint64(31))
    return (x >> np.uint64(11)).astype(np.float64) * 2.0**-52 - 1.0


def canonical_signs(phi: np.ndarray, rtol: float = SIGN_RTOL) -> np.ndarray:
    """``phi`` with each column's sign fixed: its entry of largest magnitude positive, the
    first one (lowest row) among entries within ``rtol`` of the largest."""
    mag = np.abs(phi)
    if mag.size == 0:
        return phi.copy()
    first = np.argmax(mag >= (1.0 - rtol) * mag.max(axis=0), axis=0)
    signs = np.sign(phi[first, np.arange(phi.shape[1])])
    signs[signs == 0] = 1
    return phi * signs


@contextlib.contextmanager
def single_threaded() -> Iterator[None]:
    """Run the block with one BLAS and one OpenMP thread in every library that uses them
    (NumPy's, SciPy's and CHOLMOD's OpenBLAS), so that sums are taken in one order whatever the
    number of cores. The libraries are loaded first: a limit reaches only those loaded."""
    import scipy.linalg  # noqa: F401 - loads SciPy's BLAS
    from threadpoolctl import threadpool_limits

    with contextlib.suppress(ImportError):
        import sksparse.cholmod  # type: ignore[import-not-found]  # noqa: F401
    with threadpool_limits(limits=1):
        yield


def cluster_frequencies(frequencies: np.ndarray, rtol: float = 1e-6) -> list[np.ndarray]:
    """Group indices of (sorted) frequencies that are equal to ``rtol``: repeated modes."""
    f = np.asarray(frequencies)
    edges = np.flatnonzero(np.diff(f) > rtol * np.maximum(np.abs(f[1:]), 1e-300)) + 1
    return np.split(np.arange(len(f)), edges)
