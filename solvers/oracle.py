"""``oracle``: material from full-field 3-D modes and exact eigenvalues -- the upper bound.

Paper Eq. 2 with the modes known: one convex sparse least-squares problem in z = [w; v],

    min (1/k) sum_i ||G_i w - lam_i H_i v||^2 + (alpha_w/m)||L w||^2 + (alpha_v/m)||L v||^2
        + 2 alpha_mean (mean(w) - wbar)^2 ... (the same normal equations as vvt's z-update,
        with y_i = 1; see solvers/vvt.py and docs/solvers.md)

G_i = stiffness_columns(u_i), H_i = mass_columns(u_i). The modes are scaled as vvt's u are
(P / max|P| applied to u_i gives the unit-length gamma_i), so weights mean the same thing.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field

import numpy as np

from vvtbench.problem import Estimate, InverseProblem

from .vvt import ZSystem


@dataclass
class OracleConfig:
    """Options of the oracle."""

    alpha_w: float = field(default=1e-12, metadata={
        "help": "Laplacian smoothing of w / voxel count (vvt's form; exact data needs less)"})
    alpha_v: float = field(default=1e-9, metadata={
        "help": "Laplacian smoothing of v / voxel count (enough to tame the interpolation "
                "error of the true modes on a coarser inference mesh)"})
    alpha_mean: float = field(default=1.0, metadata={"help": "weight of the mean anchor on w"})
    w_mean: float | None = field(default=None, metadata={
        "help": "anchor for mean(w) (default: the problem's prior)"})
    positive: bool = field(default=True, metadata={
        "help": "enforce w, v > 0 (a negative density has no forward model to score)"})


class OracleSolver:
    """Convex least squares with the true full-field 3-D modes and exact eigenvalues."""

    name = "oracle"
    version = "1.1.0"
    description = "Upper bound: convex least squares with true full-field 3-D modes (Eq. 2)"
    Config = OracleConfig

    def __init__(self, config: OracleConfig | None = None) -> None:
        self.config = config if config is not None else OracleConfig()

    def solve(self, problem: InverseProblem) -> Estimate:
        t0 = time.perf_counter()
        cfg = self.config
        if problem.modes_3d is None:
            raise ValueError("the oracle needs full-field 3-D modes (problem.modes_3d); "
                             "build the problem with InverseProblem.from_simulation")
        U = problem.modes_3d * abs(problem.P).max()
        w_mean = problem.w_mean if cfg.w_mean is None else cfg.w_mean
        zsys = ZSystem(problem, cfg.alpha_w, cfg.alpha_v, cfg.alpha_mean, w_mean)
        z, _ = zsys.solve(U, problem.eigenvalues, np.ones(problem.n_modes), cfg.positive)
        m = problem.n_params
        return Estimate(w=z[:m], v=z[m:], history=[], runtime_s=time.perf_counter() - t0,
                        config=asdict(cfg), solver=self.name, version=self.version,
                        converged=True)
