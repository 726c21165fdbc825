"""``sensitivity`` 2.x: FE model updating on eigenvalues and full projected mode shapes.

Parameters are theta = [log w; log v] (positivity for free, relative steps). For a trial
theta the model's lowest ``N = k + n_extra`` eigenpairs (lam_j, phi_j), mass-normalized, are
computed; observed mode i is paired with model mode p(i) (below) and the residuals are

    r_eig_i   = sqrt(weight_eig c_i) log(lam_p(i) / lam_obs_i)
    r_shape_i = sqrt(weight_shape c_i) (s_i q_i - gamma_i),  q_i = P phi_p(i),
                s_i = gamma_i . q_i / |q_i|^2              (the least-squares scale)

with gamma_i of unit length and c_i the confidence of observed mode i (2.3: from the
problem's ``mode_snr``, the spectral SNR of an extracted mode, c_i = 1 / (model_noise + 1 / (1
+ snr_i)) scaled to mean 1, since about 1 / (1 + snr) of a shape's energy is noise and
``model_noise`` is what the model cannot fit at any SNR; equal for true modes;
``mode_weights`` overrides). The cost is

    C = sum |r_eig|^2 + sum |r_shape|^2 + alpha_lap (|L log w|^2 + |L log v|^2)
        + 2 alpha_tv sum_edges (sqrt((D log w)_e^2 + eps^2) + sqrt((D log v)_e^2 + eps^2))

L the grid graph Laplacian (``solvers.vvt.grid_laplacian``), D the grid's first differences
(anisotropic total variation, smoothed by ``tv_eps``). Levenberg-Marquardt minimizes C; the TV
term enters the Gauss-Newton system by its IRLS majorizer alpha_tv D^T diag(1/psi) D; a step is
accepted only when the true cost decreases.

Derivatives (exact up to a controlled series truncation; no finite differences, no solve per
parameter):

* eigenvalues: dlam_i/dlog w_e = w_e phi_i^T K_e phi_i, dlam_i/dlog v_e = -lam_i v_e
  phi_i^T M_e phi_i (``stiffness_columns`` / ``mass_columns`` of phi_i, since dK/dw_e = K_e).
* mode shapes, Nelson's form (per mode j the per-parameter part is G_j V_j with the projected
  response operator V_j = Phi diag(coef_j) Q^T + sum_p mu_j^p Z_p and the element columns G_j
  of phi_j, computed as (G_j Phi) diag(coef_j) Q^T + sum_p mu_j^p G_j Z_p without forming V_j):
  dphi_i = A_i^+ g + c phi_i, g = -(dK - lam_i dM)
  phi_i, c = -1/2 phi_i^T dM phi_i, A_i^+ the inverse of K - lam_i M on the M-orthogonal
  complement of phi_i, A_i^+ = sum_{j != i} phi_j phi_j^T / (lam_j - lam_i). Over the N
  computed modes this sum is exact; the rest (j > N) is the expansion 1/(mu_j - mu_i) = sum_p
  mu_i^p / mu_j^(p+1) (mu = lam - sigma), i.e. sum_p mu_i^p [K_s^-1 (M K_s^-1)^p - sum_{j<=N}
  phi_j phi_j^T / mu_j^(p+1)] with K_s = K - sigma M, truncated after ``series_terms`` terms
  (error ~ (lam_i / lam_(N+1))^series_terms). Only the projections are needed, so one sparse
  Cholesky of K_s per iteration and ``series_terms`` multi-right-hand-side solves with P^T, Z_p
  = K_s^-1 (M K_s^-1)^p P^T, serve every mode and every parameter: P A_i^+ g = Q diag(coef_i)
  Phi^T g + sum_p mu_i^p Z_p^T g. Pairs of (near-)repeated eigenvalues (relative gap <
  ``gap_rtol``) are left out (no derivative exists there).
  d r_shape_i = (s_i I + q_i b_i^T) P dphi_i, b_i = (gamma_i - 2 s_i q_i) / |q_i|^2.

Mode tracking: at the start observed modes are paired with model modes by projected-mode MAC
(optimal assignment); afterwards each paired model mode is followed by the 3-D MAC
(phi_old^T M phi_new)^2 with the previous iteration's modes (``pairing="track"``), or
re-paired with the observations every iteration (``pairing="observed"``). Repeated
eigenvalues (2.7: equal within ``repeat_rtol``, e.g. the square cube's pairs at the homogeneous
start) have no defined eigenvectors, and the eigensolver returns a rotation that follows its
rounding (the BLAS thread count changed 5 of 20 pairs and NC w 0.90 -> 0.76 on the paper's top
cube); before pairing, each such basis phi_C is turned to the principal axes of the observed
shapes in its projected span, phi_C R with R the eigenvectors of Q_C^T G^T G Q_C (descending),
which is the same for every rotation phi_C U.

Clusters (2.1): model eigenvalues closer than ``cluster_rtol`` (relative, chained) form a
cluster C. Inside a near-degenerate cluster the individual modes are not smooth functions of
theta (they rotate by O(1) under tiny perturbations, their Nelson derivatives grow like
1/gap), which is what made 2.0's LM reject step after step from the symmetric cube start. So
the shape residual of an observation paired into C is rotation-invariant, the projection onto
the cluster's projected modes,

    r_shape_i = Pi_C gamma_i - gamma_i,   Pi_C = Q_C (Q_C^T Q_C)^-1 Q_C^T

(for a single-mode cluster this is s_i q_i - gamma_i above), whose derivative needs only the
couplings to modes outside C: d(Pi_C gamma) = (I - Pi_C) sum_j a_j dQ_j + Q_C A^-1
[e^T dQ_j]_j (a = A^-1 Q_C^T gamma, e = gamma - Pi_C gamma), with dQ_j the Nelson derivative
with the in-cluster couplings left out (``ShapeDerivatives(clusters=...)``). Observations in a
cluster are re-paired inside it by projected MAC (their eigenvalue residuals). LM trial steps
are judged with the current state's clusters (the cost is then continuous along the step); an
accepted point re-clusters.

MAC gate (2.2): an observation whose MAC with its paired model mode (or cluster) is below
``min_mac`` carries no information about the material, only a wrong pull (a false peak of the
video, a mode the model has not yet reached, a mispairing); model-updating practice pairs only
correlated modes. Such an observation gets weight 0 in both its eigenvalue and shape residuals
for that iteration (the best-correlated min(3, k) always stay in); the gate is re-evaluated at
every accepted point and held fixed along an LM step (like the clusters), and gated
observations are re-paired by projected MAC among the model modes the others leave free, so
they come back once the model reaches them. ``extra["active"]`` is the final gate.

Robust point weights (2.4): a measured mode shape can be wrong at some points in every mode
at once (on a rendered cube, the face edges: their shading changes as the faces tilt, which a
phase-based extractor reads as motion), and a least-squares fit then stiffens the field there
to keep those points still. For measured modes (the problem carries ``mode_snr``) each observed
point j gets a Cauchy weight u_j = 1 / (1 + E_j / (``robust_scale``^2 median E)) on its two
rows, E_j = sum_i c_i |e_ij|^2 its share of the shape residual at the current fit (iteratively
reweighted least squares: at the start of each finer level and after every accepted step of
the full grid); the weighted rows of each mode are rescaled to unit length.

Continuation: coarse-to-fine voxels. Level l uses blocks of 2^l x 2^l x 2^l voxels (theta =
T theta_coarse, piecewise constant prolongation), at most ``level_iters`` LM iterations per
coarse level, then the full grid for the rest of ``max_iter``. 2.5: for true modes, a fit
that ends with the eigenvalues unmatched (relative rms above ``restart_eig_rms``) is restarted
by a continuation in the mode count (the lowest ``mode_stages`` modes first, their fit the
start of the fit of all modes); 2.6: the result whose modes match the observed shapes
better (higher mean MAC, ``restart_keep``) is kept.

Mean anchor on w: the modes are invariant under (w, v) -> c (w, v) (and so are the priors on
log-parameters), so mean(w) = w_mean is imposed exactly by rescaling both fields at every
evaluation; an anchor row removes that null direction from the LM system.

Uncertainty (Laplace approximation at the optimum): Cov(theta) = s^2 H^-1, H = J^T J +
alpha_lap L^T L (+ TV majorizer) + anchor, s^2 = (data cost) / (number of data residuals of
the gated-in observations);
w_std = w sqrt(diag Cov_w) (delta method), likewise v_std, times ``std_scale``. Returned in
``Estimate.extra`` as ``w_std``, ``v_std``. The raw intervals ignore the model mismatch (voxels
coarser than the simulation mesh) and are overconfident; ``std_scale`` = 20 was calibrated on
validation cubes (pooled 95 % coverage 0.84 for w, 0.94 for v; benchmarks/RESULTS.md).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field

import numpy as np
import scipy.sparse as sp

from vvtbench.api import Estimate, InverseProblem

from .vvt import grid_laplacian

__all__ = ["SensitivityConfig", "SensitivitySolver", "grid_differences",
           "coarsening", "ShapeDerivatives", "compress_observation", "noise_weights"]


@dataclass
class SensitivityConfig:
    """Options of the FE model-updating solver."""

    max_iter: int = field(default=24, metadata={
        "help": "maximum number of LM iterations over all levels"})
    level_iters: int = field(default=4, metadata={
        "help": "maximum LM iterations on each coarse level of the continuation"})
    levels: int = field(default=2, metadata={
        "help": "coarse levels before the full grid (blocks of 2^l voxels per axis); 0: none"})
    tol: float = field(default=5e-3, metadata={
        "help": "stop a level when an accepted step lowers the cost by less than this fraction"})
    weight_eig: float = field(default=1.0, metadata={
        "help": "weight of the log-eigenvalue residuals"})
    weight_shape: float = field(default=1.0, metadata={
        "help": "weight of the projected mode-shape residuals (unit-length gamma)"})
    mode_weights: tuple[float, ...] = field(default=(), metadata={
        "help": "confidence of each observed mode (multiplies both its residuals); "
                "empty: from the problem's mode_snr (see model_noise), 1 for every mode "
                "where it has none"})
    model_noise: float = field(default=0.1, metadata={
        "help": "noise-weighted modes: c_i = 1 / (model_noise + 1 / (1 + snr_i)), scaled to "
                "mean 1, where the problem carries each mode's spectral SNR (extracted "
                "modes); model_noise is the share of a shape the model cannot fit whatever "
                "the SNR (chosen on val videos, docs/solvers.md)"})
    alpha_lap: float = field(default=3e-5, metadata={
        "help": "Laplacian prior weight on log w and log v"})
    alpha_tv: float = field(default=3e-5, metadata={
        "help": "total-variation prior weight on log w and log v"})
    tv_eps: float = field(default=0.05, metadata={
        "help": "smoothing of the TV prior (in log units)"})
    v_prior_scale: float = field(default=3.0, metadata={
        "help": "the priors on log v are this many times stronger than on log w"})
    n_extra: int = field(default=10, metadata={
        "help": "model modes beyond the observed count (tracking, exact part of dphi)"})
    series_terms: int = field(default=3, metadata={
        "help": "terms of the static-correction series for the modes above the computed ones"})
    gap_rtol: float = field(default=1e-5, metadata={
        "help": "leave out mode pairs with |lam_i - lam_j| < gap_rtol lam_i in dphi"})
    cluster_rtol: float = field(default=1e-2, metadata={
        "help": "model eigenvalues closer than this (relative, chained) form a cluster: an "
                "observation paired into it is fitted by the span of the cluster's projected "
                "modes, and its inner couplings are left out of dphi"})
    robust_scale: float = field(default=0.5, metadata={
        "help": "robust (Cauchy) weights of the observed points, for measured modes (the "
                "problem carries mode_snr): point j's two rows get u_j = 1 / (1 + E_j / "
                "(robust_scale^2 median E)), E_j its share of the confidence-weighted shape "
                "residual over the modes, re-evaluated at each finer level and after every "
                "accepted step of the full grid (IRLS). A point the video gets wrong in "
                "every mode (a cube's face edges, whose shading changes as they move) then "
                "stops pulling the field. 0.5 chosen on val videos (docs/solvers.md); 0: "
                "equal weights"})
    robust_points: str = field(default="measured", metadata={
        "help": "'measured' (robust point weights when the problem's modes were measured, "
                "i.e. carry mode_snr; true modes have no outliers, only model error), "
                "'always' or 'never'"})
    min_mac: float = field(default=0.5, metadata={
        "help": "an observed mode whose MAC with its paired model mode (or cluster) is below "
                "this is left out of the data residuals at that iteration: an uncorrelated "
                "pair carries no information, only a wrong pull (FE model-updating practice; "
                "the best-correlated min(3, k) always stay in; 0 keeps every pair; 0.5 "
                "chosen on extraction-like val observations, docs/solvers.md)"})
    repeat_rtol: float = field(default=1e-6, metadata={
        "help": "model eigenvalues equal to this (relative, chained) are repeated: their "
                "eigenvectors are an arbitrary rotation (the eigensolver's rounding, e.g. the "
                "BLAS thread count, picks it), so before pairing the basis is turned to the "
                "principal axes of the observed shapes in its projected span (a choice that "
                "does not depend on the rotation the eigensolver returned)"})
    pairing: str = field(default="track", metadata={
        "help": "'track' (3-D MAC with the previous iteration's modes) or 'observed' "
                "(re-pair by projected MAC every iteration)"})
    mu0: float = field(default=1e-2, metadata={"help": "initial Marquardt damping"})
    max_step: float = field(default=1.0, metadata={
        "help": "largest change of a log-parameter per step (trust region)"})
    uncertainty: bool = field(default=True, metadata={
        "help": "Laplace approximation at the optimum: extra['w_std'], extra['v_std']"})
    std_scale: float = field(default=20.0, metadata={
        "help": "multiplies the Laplace standard deviations (calibration: chosen on the "
                "validation cubes for 95 % coverage of the z = 1.96 intervals)"})
    mode_stages: tuple[int, ...] = field(default=(4,), metadata={
        "help": "restart by continuation in the mode count when the fit of all modes leaves "
                "the eigenvalues unmatched (relative rms above restart_eig_rms): fit the "
                "lowest k observed modes first (coarse to fine from the homogeneous start), "
                "for each k here in increasing order, then all modes from the last fit (fine "
                "level only); kept if it fits better (restart_keep). Only for true "
                "modes (no mode_snr): measured modes carry false and missed modes whose "
                "eigenvalue misfit says little about the fit. () never restarts. "
                "(4,) chosen on the drum_defects val split (docs/solvers.md)"})
    restart_eig_rms: float = field(default=0.1, metadata={
        "help": "relative rms eigenvalue misfit above which the continuation restart runs"})
    restart_keep: str = field(default="mac", metadata={
        "help": "which of the two fits is kept: 'mac' (the higher mean MAC of all observed "
                "modes with their paired model modes; chosen on the cube_defects and "
                "drum_defects val splits) or 'eigenvalues' (the lower eigenvalue misfit)"})
    w_mean: float | None = field(default=None, metadata={
        "help": "anchor for mean(w) (default: the problem's prior)"})

    def __post_init__(self) -> None:
        if self.pairing not in ("track", "observed"):
            raise ValueError(f"pairing must be 'track' or 'observed', got {self.pairing!r}")
        if np.isscalar(self.mode_weights):
            self.mode_weights = (float(self.mode_weights),)
        self.mode_weights = tuple(float(x) for x in self.mode_weights)
        if np.isscalar(self.mode_stages):
            self.mode_stages = (self.mode_stages,)
        if not all((isinstance(k, (int, np.integer)) and not isinstance(k, bool)
                    or isinstance(k, float) and k.is_integer()) and k >= 1
                   for k in self.mode_stages):
            raise ValueError(f"mode_stages must be integers >= 1, got {self.mode_stages!r}")
        self.mode_stages = tuple(int(k) for k in self.mode_stages)
        if not self.restart_eig_rms >= 0:  # NaN fails too
            raise ValueError(f"restart_eig_rms must be >= 0, got {self.restart_eig_rms!r}")
        if self.restart_keep not in ("mac", "eigenvalues"):
            raise ValueError(f"restart_keep must be 'mac' or 'eigenvalues', got "
                             f"{self.restart_keep!r}")
        if not self.model_noise > 0:  # NaN fails too
            raise ValueError(f"model_noise must be > 0, got {self.model_noise!r}")
        if self.robust_points not in ("measured", "always", "never"):
            raise ValueError(f"robust_points must be 'measured', 'always' or 'never', got "
                             f"{self.robust_points!r}")
        if not self.robust_scale >= 0:  # NaN fails too
            raise ValueError(f"robust_scale must be >= 0, got {self.robust_scale!r}")
        if not self.repeat_rtol >= 0:  # NaN fails too
            raise ValueError(f"repeat_rtol must be >= 0, got {self.repeat_rtol!r}")
        if not 0.0 <= self.min_mac <= 1.0:  # NaN fails too
            raise ValueError(f"min_mac must be in [0, 1], got {self.min_mac!r}")
        if self.series_terms < 0 or self.levels < 0:
            raise ValueError("series_terms and levels must be >= 0")


# --------------------------------------------------------------------------- grid helpers


def grid_differences(voxel_map) -> sp.csr_matrix:
    """(n_edges, n_params) first differences over the 6-neighbour edges of the active voxels
    (D^T D = ``grid_laplacian``)."""
    L = sp.triu(grid_laplacian(voxel_map), k=1).tocoo()
    n_e = L.nnz
    rows = np.repeat(np.arange(n_e), 2)
    cols = np.stack([L.row, L.col], axis=1).ravel()
    vals = np.tile([1.0, -1.0], n_e)
    return sp.csr_matrix((vals, (rows, cols)), shape=(n_e, voxel_map.n_params))


def coarsening(voxel_map, level: int) -> sp.csr_matrix:
    """(n_params, n_coarse) piecewise-constant prolongation from blocks of 2^level voxels per
    axis (identity for level 0)."""
    active = voxel_map.active
    shape = voxel_map.grid.shape
    n = len(active)
    if level == 0:
        return sp.identity(n, format="csr")
    ijk = np.array(np.unravel_index(active, shape)).T // (2 ** level)
    _, block = np.unique(ijk, axis=0, return_inverse=True)
    block = np.asarray(block).ravel()
    return sp.csr_matrix((np.ones(n), (np.arange(n), block)), shape=(n, block.max() + 1))


#: largest P (entries) compressed by a dense QR (160 MB); larger ones are used as they are
_COMPRESS_MAX_ENTRIES = 20_000_000


def compress_observation(P, gamma: np.ndarray):
    """An observation operator with fewer rows and the same shape residuals.

    Every projected mode P phi lies in range(P), so with an orthonormal basis U of it the
    shape residual of a unit gamma against any combination of projected modes splits into
    |U^T gamma - (U^T P) phi a|^2 + |gamma - U U^T gamma|^2, the second term constant. When
    P has more rows than columns (a membrane seen in two image directions per node), the
    solver works with P_c = U^T P and gamma_c = U^T gamma: identical costs, MACs and
    Jacobian normal equations, fewer rows.

    Parameters
    ----------
    P : (r, n) observation operator.
    gamma : (k, r) observed image-space modes.

    Returns
    -------
    P_c : (n, n), dense, when r > n (and P has at most 2e7 entries); ``P`` itself otherwise.
    gamma_c : (k, n) when compressed, else ``gamma``.
    rest : (k,) the constant |gamma - U U^T gamma|^2 of each observation.

    Examples
    --------
    >>> P = np.kron(np.eye(3), [[1.0], [2.0]])          # 3 DOFs, each seen in 2 rows
    >>> g = np.array([[1.0, 0.0, 0.0, 0.0, 0.0, 0.0]])
    >>> Pc, gc, rest = compress_observation(P, g)
    >>> Pc.shape, round(float(gc[0] @ gc[0] + rest[0]), 12)
    ((3, 3), 1.0)
    """
    r, n = P.shape
    gamma = np.asarray(gamma, dtype=float)
    if r <= n or r * n > _COMPRESS_MAX_ENTRIES:  # nothing to gain / a dense QR too large
        return P, gamma, np.zeros(len(gamma))
    dense = P.toarray() if sp.issparse(P) else np.asarray(P, dtype=float)
    U, R = np.linalg.qr(dense)
    gamma_c = gamma @ U
    rest = np.maximum(np.sum(gamma * gamma, axis=1) - np.sum(gamma_c * gamma_c, axis=1), 0.0)
    return R, gamma_c, rest


# --------------------------------------------------------------------------- eigenpairs


def noise_weights(snr: np.ndarray | None, model_noise: float, k: int) -> np.ndarray:
    """Per-mode confidence from the spectral SNR: ``1 / (model_noise + 1 / (1 + snr))``,
    scaled to mean 1 (the priors keep their balance with the data); a mode of unknown SNR
    (``nan``) gets the mean weight of the others, and equal weights without any SNR.

    >>> noise_weights(np.array([1.0, 1e4, np.nan]), 0.1, 3).round(3)
    array([0.286, 1.714, 1.   ])
    >>> noise_weights(None, 0.1, 2)
    array([1., 1.])
    """
    if snr is None or not np.isfinite(snr).any():
        return np.ones(k)
    snr = np.asarray(snr, dtype=float)
    c = 1.0 / (model_noise + 1.0 / (1.0 + snr))
    c[~np.isfinite(c)] = np.mean(c[np.isfinite(c)])
    return c / np.mean(c)


def _shift(lam: np.ndarray) -> float:
    """A shift below the spectrum: K - sigma M is definite (also without fixed DOFs)."""
    top = float(np.abs(lam).max())
    return -1e-3 * max(float(lam[0]), 1e-3 * top) if lam[0] > 0 else -1e-3 * top - 1.0


# --------------------------------------------------------------------------- derivatives


class ShapeDerivatives:
    """Eigenvalue and projected mode-shape derivatives at one (w, v) with respect to
    theta = [log w; log v].

    Parameters
    ----------
    model : the ParametricModel.
    P : (r, n_free) observation operator (sparse or dense).
    w, v : material.
    lam, phi : the N lowest eigenpairs of the model at (w, v), mass-normalized.
    series_terms, gap_rtol : see :class:`SensitivityConfig`.
    factor, sigma : a factorization of K - sigma M and its shift (default: made here).
    clusters : (N,) cluster label of each mode; couplings inside a cluster are left out, so
        dphi_j is the derivative of the cluster's invariant subspace (up to a rotation inside
        it), which is what a rotation-invariant residual needs.
    """

    def __init__(self, model, P, w, v, lam, phi, series_terms=3, gap_rtol=1e-5,
                 factor=None, sigma=None, clusters=None) -> None:
        from vvtbench.api import Factorization

        self.model, self.w, self.v = model, w, v
        self.lam, self.phi = lam, np.ascontiguousarray(phi)
        self.P = sp.csr_matrix(P)
        self.Q = np.asarray(self.P @ phi)
        self.gap_rtol = gap_rtol
        self.clusters = None if clusters is None else np.asarray(clusters)
        K, M = model.K(w), model.M(v)
        self.M = M
        # a small negative shift keeps K_s definite even without fixed DOFs
        self.sigma = _shift(lam) if sigma is None else sigma
        self.mu = lam - self.sigma
        self.Z = []
        if series_terms > 0:
            fac = factor if factor is not None else Factorization((K - self.sigma * M).tocsc())
            z = fac(np.asarray(self.P.T.toarray()))
            self.Z.append(np.ascontiguousarray(z))  # row-major: sparse @ dense without copies
            for _ in range(series_terms - 1):
                z = fac(np.asarray(M @ z))
                self.Z.append(np.ascontiguousarray(z))

    def mode(self, j: int):
        """(dlam_j / dtheta (2m,), P dphi_j / dtheta (r, 2m)) of model mode j.

        With the projected response operator of mode j, V_j = Phi diag(coef) Q^T + sum_p
        mu_j^p Z_p (n, r), the per-parameter part is G V_j, H V_j with the element-column
        matrices G, H of phi_j; V_j is never formed: (G Phi) diag(coef) Q^T is a small dense
        product and G Z_p a sparse one.
        """
        model, w, v = self.model, self.w, self.v
        m = len(w)
        phi = self.phi[:, j]
        lam = self.lam[j]
        G = model.stiffness_columns(phi).T.tocsr()  # (m, n): row e = (K_e phi)^T
        H = model.mass_columns(phi).T.tocsr()
        gK = G @ phi
        gM = H @ phi
        dlam = np.concatenate([w * gK, -lam * v * gM])
        mu_i = self.mu[j]
        T = len(self.Z)
        series = sum(mu_i ** p / self.mu ** (p + 1) for p in range(T)) if T else 0.0
        gap = self.lam - lam
        far = np.abs(gap) > self.gap_rtol * abs(lam)
        if self.clusters is not None:
            far &= self.clusters != self.clusters[j]
        far[j] = False
        coef = np.where(far, 1.0 / np.where(far, gap, 1.0), 0.0) - series
        # G V and H V without forming the dense (n, r) V: the modal part through the (m, N)
        # products G Phi, the static part as sparse products with each Z_p
        CQ = coef[:, None] * self.Q.T  # (N, r)
        GV = (G @ self.phi) @ CQ
        HV = (H @ self.phi) @ CQ
        for p in range(T):
            GV += mu_i ** p * (G @ self.Z[p])
            HV += mu_i ** p * (H @ self.Z[p])
        # g = -(dK - lam dM) phi: columns -w_e K_e phi (log w), lam v_e M_e phi (log v)
        dQ = np.empty((self.Q.shape[0], 2 * m))
        dQ[:, :m] = GV.T * -w
        dQ[:, m:] = HV.T * (lam * v)
        # mass normalization: c = -1/2 phi^T dM phi (v columns only)
        dQ[:, m:] += np.outer(self.Q[:, j], -0.5 * v * gM)
        return dlam, dQ


# --------------------------------------------------------------------------- the solver


class _State:
    """Model quantities at one parameter vector."""

    __slots__ = ("theta", "w", "v", "lam", "phi", "pair", "mac", "r_data", "cost",
                 "data_cost", "K", "M", "Q", "label", "groups", "obs_group", "a", "e",
                 "active")


class SensitivitySolver:
    """FE model updating: LM on eigenvalue and full projected mode-shape residuals, Nelson
    shape derivatives, Laplacian + TV priors, coarse-to-fine continuation, Laplace
    uncertainty."""

    name = "sensitivity"
    version = "2.7.0"
    description = ("FE model updating: Levenberg-Marquardt on eigenvalues and full projected "
                   "mode shapes (Nelson derivatives), Laplacian/TV priors, coarse-to-fine, "
                   "per-voxel standard deviations")
    Config = SensitivityConfig

    def __init__(self, config: SensitivityConfig | None = None) -> None:
        self.config = config if config is not None else SensitivityConfig()

    # ------------------------------------------------------------------ setup
    def _setup(self, problem: InverseProblem) -> None:
        cfg = self.config
        self.problem = problem
        self.model = problem.model
        m = problem.n_params
        self.m = m
        self.k = problem.n_modes
        self.n_model = min(self.k + max(cfg.n_extra, 0), self.model.n_free - 1)
        self.w_mean = problem.w_mean if cfg.w_mean is None else cfg.w_mean
        gamma = problem.gamma / np.linalg.norm(problem.gamma, axis=1, keepdims=True)
        self.r_obs = gamma.shape[1]
        self.P0, self.gamma0 = sp.csr_matrix(problem.P), gamma
        self.rows_per_point = 2 if self.r_obs % 2 == 0 else 1  # image (dx, dy) per point
        self._observe(np.ones(self.r_obs // self.rows_per_point))
        cw = noise_weights(problem.mode_snr, cfg.model_noise, self.k)
        if cfg.mode_weights:
            if len(cfg.mode_weights) != self.k:
                raise ValueError(f"mode_weights has {len(cfg.mode_weights)} entries, the "
                                 f"problem has {self.k} modes")
            cw = np.asarray(cfg.mode_weights, dtype=float)
        self.mode_weights = cw
        self.robust = cfg.robust_scale > 0 and (
            cfg.robust_points == "always"
            or (cfg.robust_points == "measured" and problem.mode_snr is not None))
        self.sq_eig = np.sqrt(cfg.weight_eig * cw)
        self.sq_shape = np.sqrt(cfg.weight_shape * cw)
        L = grid_laplacian(problem.voxel_map)
        D = grid_differences(problem.voxel_map)
        sv = cfg.v_prior_scale
        self.LtL = sp.block_diag([L.T @ L, sv * (L.T @ L)]).tocsr() * cfg.alpha_lap
        self.D2 = sp.block_diag([D, D]).tocsr()
        self.tv_w = np.concatenate([np.ones(D.shape[0]), sv * np.ones(D.shape[0])]) \
            * cfg.alpha_tv

    def _observe(self, point_weights: np.ndarray) -> None:
        """Observation rows weighted by ``point_weights`` (one per observed point: two
        image coordinates each), each observed mode rescaled to unit length, compressed."""
        self.point_weights = np.asarray(point_weights, dtype=float)
        d = np.sqrt(np.repeat(self.point_weights, self.rows_per_point))
        gamma = self.gamma0 * d
        self.gamma_scale = np.linalg.norm(gamma, axis=1)
        gamma /= self.gamma_scale[:, None]
        self.P, self.gamma, self.gamma_rest = compress_observation(
            sp.diags(d) @ self.P0, gamma)

    def _point_residuals(self, s: _State) -> np.ndarray:
        """Each observed point's share of the weighted shape residual at ``s``, in the
        unweighted observation (the fit's coefficients, the equal-weight residual rows)."""
        Q0 = np.asarray(self.P0 @ s.phi)
        energy = np.zeros(len(self.point_weights))
        for i in range(self.k):
            if not s.active[i]:
                continue
            members = s.groups[s.obs_group[i]][0]
            e = self.gamma0[i] - self.gamma_scale[i] * (Q0[:, members] @ s.a[i])
            energy += self.mode_weights[i] * np.sum(
                (e * e).reshape(-1, self.rows_per_point), axis=1)
        return energy

    def _reweight(self, s: _State) -> _State:
        """IRLS step of the robust point weights (Cauchy), then ``s`` re-evaluated."""
        if not self.robust:
            return s
        energy = self._point_residuals(s)
        scale = np.median(energy)
        if not scale > 0:
            return s
        self._observe(1.0 / (1.0 + energy / (self.config.robust_scale ** 2 * scale)))
        s.Q = np.asarray(self.P @ s.phi)
        return self._residuals(s)

    def _normalize(self, theta: np.ndarray) -> np.ndarray:
        """The anchor: shift log w and log v together so that mean(w) = w_mean."""
        return theta + np.log(self.w_mean / np.mean(np.exp(theta[:self.m])))

    def _prior(self, theta: np.ndarray) -> float:
        cfg = self.config
        cost = float(theta @ (self.LtL @ theta))
        if cfg.alpha_tv > 0:
            psi = np.sqrt((self.D2 @ theta) ** 2 + cfg.tv_eps ** 2)
            cost += 2.0 * float(self.tv_w @ psi)
        return cost

    def _prior_system(self, theta: np.ndarray):
        """(Hessian surrogate, gradient / 2) of the prior at theta (IRLS for TV)."""
        cfg = self.config
        Hp = self.LtL.copy()
        gp = self.LtL @ theta
        if cfg.alpha_tv > 0:
            d = self.D2 @ theta
            psi = np.sqrt(d ** 2 + cfg.tv_eps ** 2)
            Hp = Hp + self.D2.T @ sp.diags(self.tv_w / psi) @ self.D2
            gp = gp + self.D2.T @ (self.tv_w * d / psi)
        return Hp, gp

    def _evaluate(self, theta: np.ndarray, prev: _State | None,
                  label: np.ndarray | None = None,
                  active: np.ndarray | None = None) -> _State:
        from scipy.optimize import linear_sum_assignment

        from vvtbench.api import eigenmodes

        cfg = self.config
        theta = self._normalize(theta)
        m = self.m
        s = _State()
        s.theta = theta
        s.w, s.v = np.exp(theta[:m]), np.exp(theta[m:])
        s.K, s.M = self.model.K(s.w), self.model.M(s.v)
        modes = eigenmodes(s.K, s.M, self.n_model)
        lam_all, vec_all = modes.eigenvalues, modes.vectors
        s.lam, phi = lam_all[:self.n_model], vec_all[:, :self.n_model]
        Q = np.asarray(self.P @ phi)
        phi, Q = self._align_repeated(s.lam, phi, Q)
        qn = np.maximum(np.sum(Q * Q, axis=0), 1e-300)
        mac_obs = (self.gamma @ Q) ** 2 / qn[None, :]
        if prev is None or cfg.pairing == "observed":
            _, cols = linear_sum_assignment(-mac_obs)
        else:
            old = prev.phi[:, prev.pair]
            mac3 = (old.T @ (s.M @ phi)) ** 2
            _, cols = linear_sum_assignment(-mac3)
        s.pair = np.asarray(cols)
        if prev is not None and prev.active is not None and not prev.active.all():
            # observations left out by the MAC gate are not tracked: re-paired by projected
            # MAC among the model modes the correlated ones leave free, so they may come back
            idle = np.flatnonzero(prev.active == 0)
            free = np.setdiff1d(np.arange(self.n_model), s.pair[prev.active > 0])
            _, c = linear_sum_assignment(-mac_obs[np.ix_(idle, free)])
            s.pair[idle] = free[c]
        s.phi, s.Q = phi, Q
        return self._residuals(s, label, active)

    def _align_repeated(self, lam: np.ndarray, phi: np.ndarray, Q: np.ndarray):
        """Turn the basis of each repeated eigenvalue (``repeat_rtol``) to the principal axes
        of the observed shapes in its projected span: the eigenvectors R of Q_C^T G^T G Q_C
        (G the observed shapes), phi_C <- phi_C R. For any orthogonal U, phi_C U gives the
        same phi_C R (up to signs), so the pairing no longer follows the eigensolver's
        rounding inside the repeated eigenvalue."""
        from vvtbench.api import cluster_frequencies

        groups = [g for g in cluster_frequencies(lam, rtol=self.config.repeat_rtol)
                  if len(g) > 1]
        if not groups:
            return phi, Q
        phi, Q = phi.copy(), Q.copy()
        for members in groups:
            B = self.gamma @ Q[:, members]
            _, R = np.linalg.eigh(B.T @ B)
            R = R[:, ::-1]
            R *= np.where(R[np.argmax(np.abs(R), axis=0), np.arange(R.shape[1])] < 0, -1, 1)
            phi[:, members] = phi[:, members] @ R
            Q[:, members] = Q[:, members] @ R
        return phi, Q

    def _residuals(self, s: _State, label: np.ndarray | None = None,
                   active: np.ndarray | None = None) -> _State:
        """Data residuals and cost of ``s`` with the clusters ``label`` (default: from its
        eigenvalues) and the correlated pairs ``active`` (default: MAC >= ``min_mac``). Trial
        steps keep the current state's clusters and active pairs, so that the cost an LM step
        is judged by does not jump where clusters merge or split or a pair crosses the gate."""
        self._fit_clusters(s, s.Q, label)
        if active is None:
            active = (s.mac >= self.config.min_mac if self.config.min_mac > 0
                      else np.ones(self.k, dtype=bool))
            keep = min(3, self.k)
            if active.sum() < keep:
                active[np.argsort(-s.mac)[:keep]] = True
        s.active = np.asarray(active, dtype=float)
        lam_obs = self.problem.eigenvalues
        r_eig = s.active * self.sq_eig * np.log(np.maximum(s.lam[s.pair], 1e-300) / lam_obs)
        r_shape = ((s.active * self.sq_shape)[:, None] * (-s.e)).ravel()
        s.r_data = np.concatenate([r_eig, r_shape])
        s.data_cost = float(s.r_data @ s.r_data
                            + np.sum((s.active * self.sq_shape) ** 2 * self.gamma_rest))
        s.cost = s.data_cost + self._prior(s.theta)
        return s

    def _fit_clusters(self, s: _State, Q: np.ndarray, label: np.ndarray | None = None) -> None:
        """Cluster the model's eigenvalues (``cluster_rtol``), re-pair the observations
        inside each cluster by eigenvalue order, and fit each observed mode by the projection
        onto its cluster's projected modes: gamma_i ~ Q_C a_i, e_i = gamma_i - Q_C a_i.

        Sets ``label``, ``groups`` ((members, Q_C, (Q_C^T Q_C)^-1) per cluster holding an
        observation), ``obs_group``, ``a``, ``e`` (k, r) and ``mac`` = 1 - |e_i|^2.
        """
        from scipy.optimize import linear_sum_assignment

        from vvtbench.api import cluster_frequencies

        if label is None:
            label = np.empty(len(s.lam), dtype=int)
            for g, members in enumerate(cluster_frequencies(s.lam,
                                                            rtol=self.config.cluster_rtol)):
                label[members] = g
        s.label = label
        s.groups, s.obs_group, s.a = [], np.empty(self.k, dtype=int), [None] * self.k
        s.e = np.empty_like(self.gamma)
        for g in np.unique(label[s.pair]):
            obs = np.flatnonzero(label[s.pair] == g)
            members = np.flatnonzero(label == g)
            Qc = Q[:, members]
            if len(obs) > 1:  # inside a cluster: pair by projected MAC
                qn = np.maximum(np.sum(Qc * Qc, axis=0), 1e-300)
                _, cols = linear_sum_assignment(-(self.gamma[obs] @ Qc) ** 2 / qn[None, :])
                s.pair[obs] = members[cols]
            Ainv = np.linalg.pinv(Qc.T @ Qc)
            coef = Ainv @ (Qc.T @ self.gamma[obs].T)  # (c, n_obs)
            s.e[obs] = self.gamma[obs] - (Qc @ coef).T
            for n, i in enumerate(obs):
                s.obs_group[i] = len(s.groups)
                s.a[i] = coef[:, n]
            s.groups.append((members, Qc, Ainv))
        s.mac = 1.0 - np.sum(s.e * s.e, axis=1) - self.gamma_rest

    def _jacobian(self, s: _State) -> np.ndarray:
        """Dense (k + k r, 2m) Jacobian of the data residuals with respect to theta.

        Shape residual of observation i in cluster C: r_i = Pi_C gamma_i - gamma_i with
        Pi_C = Q_C A^-1 Q_C^T, A = Q_C^T Q_C; d(Pi_C gamma) = (I - Pi_C) sum_j a_j dQ_j +
        Q_C A^-1 [e^T dQ_j]_j (a = A^-1 Q_C^T gamma, e = gamma - Pi_C gamma).
        """
        cfg = self.config
        der = ShapeDerivatives(self.model, self.P, s.w, s.v, s.lam, s.phi,
                               cfg.series_terms, cfg.gap_rtol, clusters=s.label)
        k = self.k
        r = self.gamma.shape[1]
        J = np.empty((k + k * r, 2 * self.m))
        cache: dict[int, tuple[np.ndarray, np.ndarray]] = {}

        def mode(j):
            if j not in cache:
                cache[j] = der.mode(j)
            return cache[j]

        for i in range(k):
            if not s.active[i]:  # an uncorrelated pair: its residual rows are zero
                J[i] = 0.0
                J[k + i * r:k + (i + 1) * r] = 0.0
                continue
            j = s.pair[i]
            J[i] = self.sq_eig[i] * mode(j)[0] / s.lam[j]
            members, Qc, Ainv = s.groups[s.obs_group[i]]
            a, e = s.a[i], s.e[i]
            X = sum(a[c] * mode(jj)[1] for c, jj in enumerate(members))
            X -= Qc @ (Ainv @ (Qc.T @ X))
            X += Qc @ (Ainv @ np.array([e @ mode(jj)[1] for jj in members]))
            J[k + i * r:k + (i + 1) * r] = self.sq_shape[i] * X
        return J

    def _anchor(self, s: _State) -> np.ndarray:
        a = np.zeros(2 * self.m)
        a[:self.m] = s.w / (self.m * np.mean(s.w))
        return a

    # ------------------------------------------------------------------ the solver
    def solve(self, problem: InverseProblem, callback=None) -> Estimate:
        """Levenberg-Marquardt on log-parameters from the homogeneous start, fitting the
        eigenvalues and the full projected mode shapes of the paired modes, coarse to fine.

        BLAS runs single-threaded during the solve (the runner's setting): at these sizes a
        second thread costs more than it gives (20 modes on 8^3 voxels: 19.9 s with one,
        31.3 s with two on the 2-core VM), and the estimate does not depend on the machine's
        thread count.

        Parameters
        ----------
        problem : the inverse problem (no truth).
        callback : called with each iteration's history record.

        Returns
        -------
        Estimate
            ``extra``: ``w_std``, ``v_std`` (per-voxel standard deviations, Laplace
            approximation; when ``uncertainty``), ``eigenvalues``, ``mac``, ``pairing``,
            ``active``, ``point_weights`` (the robust weight of each observed point).
        """
        from threadpoolctl import threadpool_limits

        with threadpool_limits(limits=1, user_api="blas"):
            return self._solve(problem, callback)

    def _solve(self, problem: InverseProblem, callback=None) -> Estimate:
        from .homogeneous import HomogeneousSolver

        t_start = time.perf_counter()
        cfg = self.config
        self._setup(problem)
        all_levels = list(range(cfg.levels, -1, -1))
        state, history, converged = self._fit(
            problem, self._homogeneous_start(problem, HomogeneousSolver), all_levels, callback,
            stage=problem.n_modes)
        stages = sorted({k for k in cfg.mode_stages if k < problem.n_modes})
        if (stages and problem.mode_snr is None
                and self._eig_rms(state) > cfg.restart_eig_rms):
            # restart with a continuation by mode count: the lowest modes first (their
            # pairing with the model's is unambiguous even far from the truth), each fit
            # the start of the next; kept if it fits better (restart_keep)
            kept = (state, history, converged, self.point_weights)
            theta = None
            restart: list[dict] = []
            for k in stages:
                sub = problem.select_modes(np.arange(k))
                self._setup(sub)
                if theta is None:
                    theta, levels = self._homogeneous_start(sub, HomogeneousSolver), all_levels
                else:
                    levels = [0]
                st, hist, _ = self._fit(sub, theta, levels, callback, stage=k)
                restart += hist
                theta = st.theta
            self._setup(problem)
            st, hist, conv = self._fit(problem, theta, [0], callback, stage=problem.n_modes)
            restart += hist
            if self._restart_is_better(st, state):
                state, converged = st, conv
                history = history + [dict(r, restart=True) for r in restart]
            else:
                state, history, converged, pw = kept
                self._observe(pw)
                history = history + [dict(r, restart=True, kept=False) for r in restart]
        extra = {"eigenvalues": state.lam[state.pair], "mac": state.mac,
                 "pairing": state.pair, "active": state.active.astype(bool),
                 "point_weights": self.point_weights}
        if cfg.uncertainty:
            extra.update(self._uncertainty(state))
        return Estimate(
            w=state.w, v=state.v, history=history, runtime_s=time.perf_counter() - t_start,
            config=asdict(cfg), solver=self.name, version=self.version, converged=converged,
            extra=extra,
        )

    def _restart_is_better(self, restarted: _State, first: _State) -> bool:
        """Whether the restart's fit beats the first one by ``restart_keep``."""
        if self.config.restart_keep == "eigenvalues":
            return self._eig_rms(restarted) < self._eig_rms(first)
        return float(np.mean(restarted.mac)) > float(np.mean(first.mac))

    def _eig_rms(self, state: _State) -> float:
        """Relative rms misfit of the paired eigenvalues."""
        return float(np.sqrt(np.mean((state.lam[state.pair] / self.problem.eigenvalues - 1)
                                     ** 2)))

    def _homogeneous_start(self, problem: InverseProblem, homogeneous) -> np.ndarray:
        """Log-parameters of the best homogeneous fit, scaled to mean(w) = w_mean."""
        start = homogeneous().solve(problem)
        return np.concatenate([np.log(start.w * self.w_mean / np.mean(start.w)),
                               np.log(start.v * self.w_mean / np.mean(start.w))])

    def _fit(self, problem: InverseProblem, theta: np.ndarray, levels: list[int], callback,
             stage: int) -> tuple[_State, list[dict], bool]:
        """Levenberg-Marquardt from ``theta`` over the given coarsening levels (coarse first);
        returns the final state, the history and whether the fine level converged."""
        cfg = self.config
        m = self.m
        state = self._evaluate(theta, None)
        mu = cfg.mu0
        history: list[dict] = []
        converged = False
        n_eval = 1
        it = 0
        J = None
        for level in levels:
            Tm = coarsening(problem.voxel_map, level)
            if level > 0 and Tm.shape[1] >= m:
                continue
            T2 = sp.block_diag([Tm, Tm]).tocsr()
            cap = cfg.level_iters if level > 0 else cfg.max_iter
            level_it = 0
            mu = max(mu, cfg.mu0)  # a new level: new parameters, start damped again
            if history:
                state = self._reweight(state)
            while it < cfg.max_iter and level_it < cap:
                t0 = time.perf_counter()
                J = self._jacobian(state)
                Hp, gp = self._prior_system(state.theta)
                a = self._anchor(state)
                Jc = J if level == 0 else J @ T2.toarray()  # J T (dense BLAS: J is row-major)
                ac = T2.T @ a
                Hc = Jc.T @ Jc + (T2.T @ Hp @ T2).toarray() + np.outer(ac, ac)
                gc = Jc.T @ state.r_data + T2.T @ gp
                dA = np.maximum(np.diag(Hc), 1e-12 * max(np.diag(Hc).max(), 1e-300))
                accepted = False
                for _ in range(10):
                    try:
                        dc = -np.linalg.solve(Hc + mu * np.diag(dA), gc)
                    except np.linalg.LinAlgError:
                        mu *= 4.0
                        continue
                    delta = T2 @ dc
                    big = np.abs(delta).max()
                    if big > cfg.max_step:
                        delta *= cfg.max_step / big
                    trial = self._evaluate(state.theta + delta, state, state.label,
                                           state.active)
                    n_eval += 1
                    if trial.cost < state.cost:
                        accepted = True
                        break
                    mu *= 4.0
                it += 1
                level_it += 1
                if not accepted:
                    break
                decrease = (state.cost - trial.cost) / max(state.cost, 1e-300)
                state = self._residuals(trial)  # the clusters at the new point
                if level == 0:  # IRLS: the point weights follow the fine level's fit
                    state = self._reweight(state)
                mu = max(mu / 3.0, 1e-9)
                rec = {
                    "iteration": it,
                    "level": level,
                    "time_s": time.perf_counter() - t0,
                    "cost": state.cost,
                    "data_cost": state.data_cost,
                    "eig_rel_rms": float(np.sqrt(np.mean(
                        (state.lam[state.pair] / problem.eigenvalues - 1) ** 2))),
                    "mean_mac": float(np.mean(state.mac)),
                    "active": int(state.active.sum()),
                    "mu": mu,
                    "evaluations": n_eval,
                    "modes": stage,
                }
                history.append(rec)
                if callback is not None:
                    callback(rec)
                if decrease < cfg.tol:
                    break
            if level == 0:
                converged = it < cfg.max_iter
        return state, history, converged

    def _uncertainty(self, state: _State) -> dict:
        """Laplace approximation: per-voxel standard deviations of w and v."""
        m = self.m
        J = self._jacobian(state)
        Hp, _ = self._prior_system(state.theta)
        a = self._anchor(state)
        H = J.T @ J + Hp.toarray() + np.outer(a, a)
        n_rows = state.active.sum() * (1 + self.r_obs)  # rows of the active pairs
        s2 = state.data_cost / max(n_rows, 1)
        try:
            cov_diag = np.diag(np.linalg.inv(H)) * s2
        except np.linalg.LinAlgError:
            cov_diag = np.diag(np.linalg.pinv(H)) * s2
        sd = np.sqrt(np.clip(cov_diag, 0, None)) * self.config.std_scale
        return {"w_std": state.w * sd[:m], "v_std": state.v * sd[m:]}
