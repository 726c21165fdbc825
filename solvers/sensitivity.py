"""``sensitivity``: classical FE model updating -- Levenberg-Marquardt on modal residuals.

The structural-dynamics peer of ``vvt``. Parameters are theta = [log w; log v] (positivity
for free, relative steps). For a trial theta the model's lowest ``k + n_extra`` eigenpairs
(lam_j, phi_j), mass-normalized, are computed; observed mode i is paired with model mode
p(i) and the residuals are

    r_lam_i = (lam_p(i) - lam_obs_i) / lam_obs_i
    r_mac_i = sqrt(weight_mac) (1 - MAC(P phi_p(i), gamma_i)),  MAC(a, b) = (a.b)^2/(|a|^2 |b|^2)
    r_reg   = sqrt(alpha_reg) [L log w; L log v]       (regularization="laplacian", L the grid
              graph Laplacian of vvt) or sqrt(alpha_reg) (theta - theta_start) ("tikhonov")

and LM minimizes |r|^2 with Marquardt damping mu diag(J^T J).

Derivatives (analytic, no finite differences):

* eigenvalues: dlam_i/dw_e = phi_i^T K_e phi_i, dlam_i/dv_e = -lam_i phi_i^T M_e phi_i
  (K_e, M_e the unit matrices of voxel e; computed element-wise, = G_i^T phi_i with
  G_i = model.stiffness_columns(phi_i));
* mode shapes: modal truncation (Fox & Kapoor) over the computed model modes,
  dphi_i = sum_{j != i} phi_j phi_j^T (dK - lam_i dM) phi_i / (lam_i - lam_j)
           - 1/2 (phi_i^T dM phi_i) phi_i,
  an approximation of Nelson's exact derivative that drops the modes above the computed
  ones (their share ~ lam_i / lam_j is small for the low modes). Pairs closer than
  ``gap_rtol`` (repeated eigenvalues: symmetric cubes have them) are skipped; the phi_i term
  is irrelevant to the scale-free MAC. The MAC derivative is then
  dMAC_i = g_i^T P dphi_i, g_i = 2c/(|gamma|^2 |q|^2) (gamma - c q/|q|^2), q = P phi_i,
  c = gamma . q.

Mode tracking: at the start observed modes are paired with model modes by projected-mode MAC
(optimal assignment); afterwards each paired model mode is followed by the 3-D MAC
(phi_old^T M phi_new)^2 with the previous iteration's modes (``pairing="track"``), or
re-paired with the observations every iteration (``pairing="observed"``).

Mean anchor on w: the eigenvalues and mode shapes are invariant under (w, v) -> c (w, v), so
mean(w) = w_mean is imposed exactly by rescaling both fields at every evaluation; an anchor
row in J removes that null direction from the LM system. The start is the best uniform field
(the ``homogeneous`` solver).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field

import numpy as np
import scipy.sparse as sp

from vvtbench.problem import Estimate, InverseProblem

from .vvt import grid_laplacian

__all__ = ["SensitivityConfig", "SensitivitySolver"]


@dataclass
class SensitivityConfig:
    """Options of the FE model-updating solver."""

    max_iter: int = field(default=30, metadata={"help": "maximum number of LM iterations"})
    tol: float = field(default=1e-4, metadata={
        "help": "stop when an accepted step lowers the cost by less than this fraction"})
    weight_mac: float = field(default=1.0, metadata={
        "help": "weight of the (1 - MAC) residuals relative to the eigenvalue residuals"})
    regularization: str = field(default="laplacian", metadata={
        "help": "'laplacian' (graph Laplacian of log w, log v) or 'tikhonov' (to the start)"})
    alpha_reg: float = field(default=1e-4, metadata={"help": "regularization weight"})
    mu0: float = field(default=1e-2, metadata={"help": "initial Marquardt damping"})
    n_extra: int = field(default=20, metadata={
        "help": "model modes beyond the observed count (tracking, shape derivatives)"})
    gap_rtol: float = field(default=1e-6, metadata={
        "help": "skip mode pairs with |lam_i - lam_j| < gap_rtol lam_i in shape derivatives"})
    pairing: str = field(default="track", metadata={
        "help": "'track' (MAC with the previous iteration's modes) or 'observed' (re-pair by "
                "projected MAC every iteration)"})
    max_step: float = field(default=1.0, metadata={
        "help": "largest change of a log-parameter per step (trust region)"})
    w_mean: float | None = field(default=None, metadata={
        "help": "anchor for mean(w) (default: the problem's prior)"})


class _State:
    """Model quantities at one parameter vector."""

    __slots__ = ("theta", "w", "v", "lam", "phi", "pair", "mac", "q", "res", "cost")


class SensitivitySolver:
    """FE model updating: LM on eigenvalue and (1 - MAC) residuals, analytic sensitivities."""

    name = "sensitivity"
    version = "1.0.0"
    description = ("Classical FE model updating: Levenberg-Marquardt on eigenvalue and MAC "
                   "residuals with analytic eigen-sensitivities and mode tracking")
    Config = SensitivityConfig

    def __init__(self, config: SensitivityConfig | None = None) -> None:
        self.config = config if config is not None else SensitivityConfig()

    # ------------------------------------------------------------------ model evaluation
    def _setup(self, problem: InverseProblem) -> None:
        cfg = self.config
        if cfg.regularization not in ("laplacian", "tikhonov"):
            raise ValueError("regularization must be 'laplacian' or 'tikhonov', got "
                             f"{cfg.regularization!r}")
        if cfg.pairing not in ("track", "observed"):
            raise ValueError(f"pairing must be 'track' or 'observed', got {cfg.pairing!r}")
        self.problem = problem
        self.model = problem.model
        m = problem.n_params
        self.m = m
        self.k = problem.n_modes
        self.n_model = min(self.k + max(cfg.n_extra, 0), self.model.n_free - 1)
        self.w_mean = problem.w_mean if cfg.w_mean is None else cfg.w_mean
        if cfg.regularization == "laplacian":
            L = grid_laplacian(problem.voxel_map)
            self.R = np.sqrt(cfg.alpha_reg) * sp.block_diag([L, L]).toarray()
        else:
            self.R = np.sqrt(cfg.alpha_reg) * np.eye(2 * m)
        self.gamma = problem.gamma / np.linalg.norm(problem.gamma, axis=1, keepdims=True)
        mdl = self.model
        self._rows = mdl.free_index[mdl.element_dofs]  # (ne, nd), -1 on fixed DOFs
        self._param = mdl.voxel_map.element_param

    def _normalize(self, theta: np.ndarray) -> np.ndarray:
        """The anchor: shift log w and log v together so that mean(w) = w_mean."""
        m = self.m
        shift = np.log(self.w_mean / np.mean(np.exp(theta[:m])))
        return theta + shift

    def _element(self, X: np.ndarray) -> np.ndarray:
        """Free-DOF vectors (n, c) -> element arrays (ne, nd, c), zero on fixed DOFs."""
        full = np.zeros((self.model.mesh.n_dofs, X.shape[1]))
        full[self.model.free_dofs] = X
        return full[self.model.element_dofs]

    def _voxel_sum(self, values: np.ndarray) -> np.ndarray:
        """(ne, c) element values -> (m, c) per parameter."""
        out = np.zeros((self.m, values.shape[1]))
        np.add.at(out, self._param, values)
        return out

    def _evaluate(self, theta: np.ndarray, prev: _State | None) -> _State:
        from scipy.optimize import linear_sum_assignment

        from vvtbench.fem.modal import eigenmodes

        cfg = self.config
        theta = self._normalize(theta)
        m, k = self.m, self.k
        s = _State()
        s.theta = theta
        s.w, s.v = np.exp(theta[:m]), np.exp(theta[m:])
        K, M = self.model.K(s.w), self.model.M(s.v)
        modes = eigenmodes(K, M, self.n_model)
        s.lam, s.phi = modes.eigenvalues, modes.vectors
        Q = np.asarray(self.problem.P @ s.phi)  # (2 nv, n_model)
        qn = np.maximum(np.sum(Q * Q, axis=0), 1e-300)
        mac_obs = (self.gamma @ Q) ** 2 / qn[None, :]  # (k, n_model); |gamma| = 1
        if prev is None or cfg.pairing == "observed":
            _, cols = linear_sum_assignment(-mac_obs)
        else:  # follow each paired mode: 3-D MAC with the previous paired modes
            old = prev.phi[:, prev.pair]
            mac3 = (old.T @ (M @ s.phi)) ** 2  # both mass-normalized
            _, cols = linear_sum_assignment(-mac3)
        s.pair = np.asarray(cols)
        s.mac = mac_obs[np.arange(k), s.pair]
        s.q = Q[:, s.pair]
        lam_obs = self.problem.eigenvalues
        r_lam = (s.lam[s.pair] - lam_obs) / lam_obs
        r_mac = np.sqrt(cfg.weight_mac) * (1.0 - s.mac)
        if cfg.regularization == "laplacian":
            r_reg = self.R @ theta
        else:
            r_reg = self.R @ (theta - self.theta_start)
        s.res = np.concatenate([r_lam, r_mac, r_reg])
        s.cost = float(s.res @ s.res)
        return s

    def _jacobian(self, s: _State) -> np.ndarray:
        cfg = self.config
        mdl = self.model
        m, k = self.m, self.k
        lam_all = s.lam
        lam = lam_all[s.pair]
        phi = s.phi[:, s.pair]  # (n, k)
        ue = self._element(phi)  # (ne, nd, k)
        Kue = np.einsum("eij,ejk->eik", mdl.Ke, ue)
        Mue = np.einsum("eij,ejk->eik", mdl.Me, ue)
        # eigenvalue sensitivities per parameter: phi^T K_e phi, phi^T M_e phi
        dlam_w = self._voxel_sum(np.einsum("eik,eik->ek", Kue, ue))  # (m, k)
        dlam_v = -lam * self._voxel_sum(np.einsum("eik,eik->ek", Mue, ue))
        # MAC sensitivities by modal truncation
        gam = self.gamma.T  # (2 nv, k), unit columns
        q = s.q
        c = np.sum(gam * q, axis=0)
        qn = np.sum(q * q, axis=0)
        g = (2 * c / qn) * (gam - q * (c / qn))  # (2 nv, k)
        Qall = np.asarray(self.problem.P @ s.phi)  # (2 nv, n_model)
        S = g.T @ Qall  # (k, n_model): g_i^T P phi_j
        gap = lam[:, None] - lam_all[None, :]
        ok = np.abs(gap) > cfg.gap_rtol * np.abs(lam)[:, None]
        ok[np.arange(k), s.pair] = False
        C = np.where(ok, S / np.where(ok, gap, 1.0), 0.0)  # (k, n_model)
        T = s.phi @ C.T  # (n, k): sum_j phi_j S_ij / (lam_i - lam_j)
        te = self._element(T)
        dmac_w = self._voxel_sum(np.einsum("eik,eik->ek", Kue, te))
        dmac_v = -lam * self._voxel_sum(np.einsum("eik,eik->ek", Mue, te))
        lam_obs = self.problem.eigenvalues
        # d/dlog w_e = w_e d/dw_e
        J_lam = np.hstack([(dlam_w * s.w[:, None]).T, (dlam_v * s.v[:, None]).T]) / lam_obs[:, None]
        J_mac = -np.sqrt(cfg.weight_mac) * np.hstack([(dmac_w * s.w[:, None]).T,
                                                       (dmac_v * s.v[:, None]).T])
        anchor = np.zeros((1, 2 * m))
        anchor[0, :m] = s.w / (m * np.mean(s.w))  # d log(mean w) / d log w_e
        return np.vstack([J_lam, J_mac, self.R, anchor])

    # ------------------------------------------------------------------ the solver
    def solve(self, problem: InverseProblem, callback=None) -> Estimate:
        """Levenberg-Marquardt on log-parameters from the homogeneous start, fitting the
        eigenvalue and (1 - MAC) residuals of the paired modes.

        Parameters
        ----------
        problem : the inverse problem (no truth).
        callback : called with each iteration's history record.

        Returns
        -------
        Estimate
        """
        from .homogeneous import HomogeneousSolver

        t_start = time.perf_counter()
        cfg = self.config
        self._setup(problem)
        k = self.k
        start = HomogeneousSolver().solve(problem)
        theta = np.concatenate([np.log(start.w * self.w_mean / np.mean(start.w)),
                                np.log(start.v * self.w_mean / np.mean(start.w))])
        self.theta_start = theta.copy()
        state = self._evaluate(theta, None)
        mu = cfg.mu0
        history: list[dict] = []
        converged = False
        n_eval = 1
        for it in range(1, cfg.max_iter + 1):
            t0 = time.perf_counter()
            J = self._jacobian(state)
            r = np.concatenate([state.res, [0.0]])  # the anchor residual is 0 (exact)
            A = J.T @ J
            grad = J.T @ r
            dA = np.maximum(np.diag(A), 1e-12 * max(np.diag(A).max(), 1e-300))
            accepted = False
            for _ in range(12):
                delta = np.linalg.solve(A + mu * np.diag(dA), -grad)
                big = np.abs(delta).max()
                if big > cfg.max_step:
                    delta *= cfg.max_step / big
                trial = self._evaluate(state.theta + delta, state)
                n_eval += 1
                if trial.cost < state.cost:
                    accepted = True
                    break
                mu *= 4.0
            if not accepted:
                converged = True  # no descent direction left at any damping
                break
            decrease = (state.cost - trial.cost) / max(state.cost, 1e-300)
            state = trial
            mu = max(mu / 3.0, 1e-12)
            rec = {
                "iteration": it,
                "time_s": time.perf_counter() - t0,
                "cost": state.cost,
                "eig_rel_rms": float(np.sqrt(np.mean(state.res[:k] ** 2))),
                "mean_mac": float(np.mean(state.mac)),
                "mu": mu,
                "evaluations": n_eval,
            }
            history.append(rec)
            if callback is not None:
                callback(rec)
            if decrease < cfg.tol:
                converged = True
                break
        return Estimate(
            w=state.w, v=state.v, history=history, runtime_s=time.perf_counter() - t_start,
            config=asdict(cfg), solver=self.name, version=self.version, converged=converged,
            extra={"eigenvalues": state.lam[state.pair], "mac": state.mac,
                   "pairing": state.pair},
        )
