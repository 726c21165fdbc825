"""``oracle``: material from full-field 3-D modes and exact eigenvalues -- the upper bound.

Two ways to fit the voxel model to the true modes, and the one whose forward model reproduces
them best (``method="select"``, the default):

* ``strong`` -- paper Eq. 2 with the modes known: one convex sparse least-squares problem in
  z = [w; v] (vvt's z-update with y_i = 1)::

      min (1/k) sum_i ||G_i w - lam_i H_i v||^2 + (alpha_w/m)||L w||^2 + (alpha_v/m)||L v||^2
          + 2 alpha_mean (mean(w) - wbar)^2

  G_i = stiffness_columns(u_i), H_i = mass_columns(u_i). Exact when the true fields are voxel
  fields; biased when they are not (sharp defect edges inside voxels, a coarser inference
  mesh): the true modes are then not eigenvectors of any voxel model, and the strong-form
  residual weighs that mismatch, not the material.
* ``fitted`` -- errors in variables: vvt's alternating method with every free DOF observed
  (P = I, the true 3-D modes as data, unit length) and the exact eigenvalues held
  (alpha_e = 0), positivity on, for each data weight in ``alpha_u``: the modes may move off
  the data to become eigenvectors of the voxel model.

For modes extracted from video the oracle's modes are the true ones paired with them (by
MAC) and its eigenvalues theirs (``meta["true_frequencies_hz"]``), not the extracted ones.

Selection uses only the oracle's own inputs: for every candidate the forward model's k + 10
lowest modes are matched to the true 3-D modes (Hungarian on MAC); the score is
(1 - mean MAC) + mean |f_pred / f_true - 1|, lowest wins.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field, replace

import numpy as np
import scipy.sparse as sp

from vvtbench.problem import Estimate, InverseProblem

from .vvt import VVTConfig, VVTSolver, ZSystem


@dataclass
class OracleConfig:
    """Options of the oracle."""

    method: str = field(default="select", metadata={
        "help": "'strong' (Eq. 2 least squares), 'fitted' (vvt on the full field, exact "
                "eigenvalues) or 'select' (all, keep the best 3-D mode match)"})
    alpha_w: float = field(default=1e-12, metadata={
        "help": "strong: Laplacian smoothing of w / voxel count (vvt's form)"})
    alpha_v: float = field(default=1e-9, metadata={
        "help": "strong: Laplacian smoothing of v / voxel count (tames the interpolation "
                "error of the true modes on a coarser inference mesh)"})
    alpha_mean: float = field(default=1.0, metadata={"help": "weight of the mean anchor on w"})
    w_mean: float | None = field(default=None, metadata={
        "help": "anchor for mean(w) (default: the problem's prior)"})
    positive: bool = field(default=True, metadata={
        "help": "enforce w, v > 0 (a negative density has no forward model to score)"})
    alpha_u: tuple[float, ...] = field(default=(100.0, 1000.0), metadata={
        "help": "fitted: data weights tried (vvt's alpha_u on the full field)"})
    max_iter: int = field(default=100, metadata={"help": "fitted: vvt iterations"})

    def __post_init__(self) -> None:
        if self.method not in ("strong", "fitted", "select"):
            raise ValueError(f"oracle method must be 'strong', 'fitted' or 'select', "
                             f"got {self.method!r}")
        if np.isscalar(self.alpha_u):
            self.alpha_u = (float(self.alpha_u),)
        self.alpha_u = tuple(float(a) for a in self.alpha_u)


def full_field_problem(problem: InverseProblem) -> InverseProblem:
    """The problem with every free DOF observed: P = I, the true 3-D modes (unit length) as
    data."""
    n = problem.model.n_free
    U = problem.modes_3d
    gamma = (U / np.linalg.norm(U, axis=0)).T
    return replace(problem, P=sp.identity(n, format="csr"), gamma=gamma,
                   visible_nodes=np.arange(n), meta=dict(problem.meta))


def fit_score(full: InverseProblem, w: np.ndarray, v: np.ndarray) -> float:
    """(1 - mean MAC) + mean relative frequency error of the forward model against the true
    full-field modes (lower is better; inf when the forward solve fails)."""
    from vvtbench.metrics import mode_match

    try:
        mm = mode_match(full, w, v)
    except Exception:
        return float("inf")
    return float((1.0 - mm["mean_mac"]) + mm["freq_rel_error"])


class OracleSolver:
    """Material from the true full-field 3-D modes and exact eigenvalues."""

    name = "oracle"
    version = "2.1.0"
    uses_truth = True  # a reference: the runner lets it see the full-field 3-D modes
    description = ("Upper bound: true full-field 3-D modes and exact eigenvalues; Eq. 2 least "
                   "squares or vvt on the full field, whichever fits the modes best")
    Config = OracleConfig

    def __init__(self, config: OracleConfig | None = None) -> None:
        self.config = config if config is not None else OracleConfig()

    def solve(self, problem: InverseProblem) -> Estimate:
        t0 = time.perf_counter()
        cfg = self.config
        if problem.modes_3d is None:
            raise ValueError("the oracle needs full-field 3-D modes (problem.modes_3d); "
                             "build the problem with InverseProblem.from_simulation")
        true_f = problem.meta.get("true_frequencies_hz")
        if true_f is not None and len(true_f) == problem.n_modes:
            # observed modes extracted from video: the oracle keeps the exact eigenvalues of
            # the true modes they were paired with (a spurious peak paired with a far-off
            # true mode would otherwise give it an inconsistent mode / eigenvalue pair)
            lam = (2 * np.pi * np.asarray(true_f, dtype=float)) ** 2
            problem = replace(problem, eigenvalues=lam, meta=dict(problem.meta))
        w_mean = problem.w_mean if cfg.w_mean is None else cfg.w_mean
        candidates: dict[str, tuple[np.ndarray, np.ndarray, list]] = {}
        if cfg.method in ("strong", "select"):
            U = problem.modes_3d * abs(problem.P).max()
            zsys = ZSystem(problem, cfg.alpha_w, cfg.alpha_v, cfg.alpha_mean, w_mean)
            z, _ = zsys.solve(U, problem.eigenvalues, np.ones(problem.n_modes), cfg.positive)
            m = problem.n_params
            candidates["strong"] = (z[:m], z[m:], [])
        full = full_field_problem(problem) if cfg.method != "strong" else None
        if full is not None:
            for a in cfg.alpha_u:
                vcfg = VVTConfig(alpha_e=0.0, alpha_u=a, positive=cfg.positive,
                                 max_iter=cfg.max_iter, w_mean=w_mean,
                                 alpha_mean=cfg.alpha_mean, track_nc=False)
                est = VVTSolver(vcfg).solve(full)
                candidates[f"fitted(alpha_u={a:g})"] = (est.w, est.v, est.history)
        scores = ({k: fit_score(full, w, v) for k, (w, v, _) in candidates.items()}
                  if len(candidates) > 1 else {k: float("nan") for k in candidates})
        best = min(candidates, key=lambda k: (np.nan_to_num(scores[k], nan=0.0), k))
        w, v, history = candidates[best]
        return Estimate(w=w, v=v, history=history, runtime_s=time.perf_counter() - t0,
                        config=asdict(cfg), solver=self.name, version=self.version,
                        converged=True, extra={"chosen": best, "fit_scores": scores})
