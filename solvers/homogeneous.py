"""``homogeneous``: the best uniform field -- the floor every solver should beat.

w = w_mean everywhere (the scale anchor); v uniform from the eigenvalues: for a uniform
material the model's eigenvalues are lam_j = w mu_j / v with mu_j those of K(1), M(1).
Predicted modes are matched to the observed ones by MAC of their projections (optimal
assignment), and v minimizes sum_j (log lam_obs_j - log(w mu_j / v))^2 over the matches:
log v = mean_j log(w mu_j / lam_obs_j).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field

import numpy as np

from vvtbench.api import Estimate, InverseProblem


@dataclass
class HomogeneousConfig:
    """Options of the homogeneous baseline."""

    w_mean: float | None = field(default=None, metadata={
        "help": "the uniform w (default: the problem's prior mean)"})
    match: str = field(default="mac", metadata={
        "help": "pair observed and model modes by 'mac' (projected-mode MAC) or 'order'"})
    n_extra: int = field(default=10, metadata={
        "help": "extra model modes computed for MAC matching"})


class HomogeneousSolver:
    """Best uniform (w, v): w at the anchor, v fitted to the observed eigenvalues."""

    name = "homogeneous"
    version = "1.0.0"
    description = "Floor: best uniform field (w at the mean anchor, v from the eigenvalues)"
    Config = HomogeneousConfig

    def __init__(self, config: HomogeneousConfig | None = None) -> None:
        self.config = config if config is not None else HomogeneousConfig()

    def solve(self, problem: InverseProblem) -> Estimate:
        """Uniform w = w_mean and the uniform v whose forward model best matches the observed
        frequencies (the floor every solver should beat).

        Parameters
        ----------
        problem : the inverse problem (no truth).

        Returns
        -------
        Estimate
            Constant fields; ``extra["matched_model_modes"]`` pairs the observed modes with
            the homogeneous model's.
        """
        from vvtbench.api import eigenmodes, mac_matrix

        t0 = time.perf_counter()
        cfg = self.config
        if cfg.match not in ("mac", "order"):
            raise ValueError(f"match must be 'mac' or 'order', got {cfg.match!r}")
        model = problem.model
        w = problem.w_mean if cfg.w_mean is None else cfg.w_mean
        k = problem.n_modes
        n = min(k + (cfg.n_extra if cfg.match == "mac" else 0), model.n_free - 1)
        modes = eigenmodes(model.K(1.0), model.M(1.0), n)
        mu = modes.eigenvalues
        if cfg.match == "mac":
            from scipy.optimize import linear_sum_assignment

            mac = mac_matrix(problem.gamma, (problem.P @ modes.vectors).T)
            rows, cols = linear_sum_assignment(-mac)
        else:
            rows = cols = np.arange(k)
        lam = problem.eigenvalues[rows]
        ok = (lam > 0) & (mu[cols] > 0)
        v = float(np.exp(np.mean(np.log(w * mu[cols][ok] / lam[ok]))))
        m = problem.n_params
        return Estimate(w=np.full(m, float(w)), v=np.full(m, v), history=[],
                        runtime_s=time.perf_counter() - t0, config=asdict(cfg),
                        solver=self.name, version=self.version, converged=True,
                        extra={"matched_model_modes": np.asarray(cols)})
