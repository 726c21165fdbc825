"""``learned``: ridge regression from features of the observed modes to the voxel contrast.

A learned baseline for the dataset generator's families: trained only on a family's train
split (``vvtbench train learned FAMILY``), scored on its test split like every solver.

Features (per voxel e, the same for every instance of a family, so one regression serves all
voxels and instances): the homogeneous model (w = w_mean, v fitted to the eigenvalues: the
``homogeneous`` solver) gives modes phi_j; each observed mode i is paired with one by the MAC
of its projection P phi_j. With r_i = lam_obs_i / lam_hom_i - 1 (the eigenvalue misfit) and the
fractions of the paired mode's strain and kinetic energy in voxel e,
s_ie = phi_i^T K_e phi_i / phi_i^T K phi_i and t_ie = phi_i^T M_e phi_i / phi_i^T M phi_i
(times the voxel count), the features are r_i s_ie and r_i t_ie of the first ``N_MODES``
modes (zero where fewer are observed), their sums over all modes, the mean energy fractions,
and the voxel's normalized position. These are the terms of a first-order eigenvalue
sensitivity step; the regression learns how to weigh them. Targets: log(w_e / mean w) and
log(v_e / mean v) of the truth. Prediction: w = w_mean exp(f_w - mean f_w), v = v_hom
exp(f_v - mean f_v).
"""

from __future__ import annotations

import json
import time
import zipfile
from collections.abc import Iterable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from vvtbench.dataset import sha256_file
from vvtbench.problem import Estimate, InverseProblem

N_MODES = 10
FORMAT = "vvtbench.learned-weights"
SHIPPED = Path(__file__).parent / "weights"


def weights_path(name_or_path: str) -> Path:
    """The weights file: a path to a ``.npz``, or the name of shipped weights
    (``solvers/weights/NAME.npz``, trained on family NAME's train split)."""
    text = str(name_or_path)
    if text.endswith(".npz") or "/" in text or "\\" in text:
        return Path(text)
    path = SHIPPED / f"{text}.npz"
    if not path.is_file():
        have = sorted(p.stem for p in SHIPPED.glob("*.npz"))
        raise ValueError(f"learned: no shipped weights {text!r} (shipped: "
                         f"{', '.join(have) or 'none'}; or give a .npz path)")
    return path


@dataclass
class LearnedConfig:
    """Options of the learned baseline."""

    weights: str = field(default="", metadata={
        "help": "weights file written by `vvtbench train learned FAMILY` (.npz), or the name "
                "of shipped weights (solvers/weights/NAME.npz: cube_defects, bunny_defects, "
                "drum_defects)"})
    ridge: float = field(default=1.0, metadata={
        "help": "training only: ridge penalty on the standardized features"})


def features(problem: InverseProblem) -> tuple[np.ndarray, float]:
    """(n_params, n_features) features of every voxel, and the homogeneous density v_hom."""
    from scipy.optimize import linear_sum_assignment

    from vvtbench.fem.modal import eigenmodes
    from vvtbench.mac import mac_matrix

    from .homogeneous import HomogeneousSolver

    model, k, m = problem.model, problem.n_modes, problem.n_params
    hom = HomogeneousSolver().solve(problem)
    w0, v0 = float(hom.w[0]), float(hom.v[0])
    n = min(k + 10, model.n_free - 1)
    modes = eigenmodes(model.K(w0), model.M(v0), n)
    mac = mac_matrix(problem.gamma, (problem.P @ modes.vectors).T)
    rows, cols = linear_sum_assignment(-mac)
    order = np.argsort(rows)
    rows, cols = rows[order], cols[order]
    r = problem.eigenvalues[rows] / modes.eigenvalues[cols] - 1.0
    s = np.zeros((m, N_MODES))
    t = np.zeros((m, N_MODES))
    s_all = np.zeros(m)
    t_all = np.zeros(m)
    es, et = np.zeros(m), np.zeros(m)
    for j, (i, c) in enumerate(zip(rows, cols, strict=True)):
        phi = modes.vectors[:, c]
        se = model.stiffness_columns(phi).T @ phi
        te = model.mass_columns(phi).T @ phi
        se, te = m * se / se.sum(), m * te / te.sum()
        s_all += r[j] * se
        t_all += r[j] * te
        es += se / len(rows)
        et += te / len(rows)
        if i < N_MODES:
            s[:, i], t[:, i] = r[j] * se, r[j] * te
    grid = problem.voxel_map.grid
    centers = grid.centers()[problem.voxel_map.active]
    pos = (centers - np.asarray(grid.origin)) / np.asarray(grid.size) - 0.5
    X = np.column_stack([s, t, s_all, t_all, es, et, pos, (pos**2).sum(axis=1)])
    return X, v0


def fit(pairs: Iterable, ridge: float = 1.0) -> dict:
    """Weights from ``(problem, truth)`` pairs (a family's train split)."""
    Xs, yw, yv = [], [], []
    for problem, truth in pairs:
        X, _ = features(problem)
        Xs.append(X)
        yw.append(np.log(truth.w / truth.w.mean()))
        yv.append(np.log(truth.v / truth.v.mean()))
    if not Xs:
        raise ValueError("no training instances")
    X = np.vstack(Xs)
    mu, sd = X.mean(axis=0), X.std(axis=0)
    sd[sd == 0] = 1.0
    Z = (X - mu) / sd
    A = Z.T @ Z + ridge * np.eye(Z.shape[1])
    coef = np.linalg.solve(A, Z.T @ np.column_stack([np.concatenate(yw), np.concatenate(yv)]))
    return {"coef_w": coef[:, 0], "coef_v": coef[:, 1], "mean": mu, "std": sd,
            "n_instances": len(Xs), "n_voxels": int(len(X)), "ridge": float(ridge)}


def save_weights(path: str | Path, weights: dict, meta: dict) -> Path:
    """The weights (.npz arrays) with their provenance (JSON in the same file)."""
    from vvtbench.io import write_npz

    arrays = {k: np.asarray(v) for k, v in weights.items() if isinstance(v, np.ndarray)}
    info = {k: v for k, v in weights.items() if not isinstance(v, np.ndarray)}
    doc = {"format": FORMAT, "n_modes_features": N_MODES,
           "solver_version": LearnedSolver.version, **info, **meta}
    arrays["meta_json"] = np.frombuffer(json.dumps(doc).encode(), dtype=np.uint8)
    write_npz(Path(path), arrays)
    return Path(path)


def load_weights(path: str | Path) -> tuple[dict, dict]:
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        meta = json.loads(arrays.pop("meta_json").tobytes().decode())
    except FileNotFoundError:
        raise
    except (OSError, ValueError, KeyError, AttributeError, UnicodeDecodeError,
            zipfile.BadZipFile, EOFError):
        meta = None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise ValueError(f"{path}: not a learned-weights file (an .npz written by "
                         "`vvtbench train learned FAMILY`)")
    return arrays, meta


class LearnedSolver:
    """Ridge regression from mode-sensitivity features to the voxel contrast."""

    name = "learned"
    version = "1.0.0"
    trainable = True  # module-level fit() and save_weights(): `vvtbench train learned FAMILY`
    description = ("Learned baseline: ridge regression from eigenvalue-sensitivity features of "
                   "the observed modes, trained on a family's train split")
    Config = LearnedConfig

    def __init__(self, config: LearnedConfig | None = None) -> None:
        self.config = config if config is not None else LearnedConfig()

    @staticmethod
    def cache_inputs(config: dict) -> dict:
        """The weights file's sha256 (the runner keys solves by it, not by the name)."""
        try:
            path = weights_path(config.get("weights", ""))
            return {"weights_sha256": sha256_file(path)} if path.is_file() else {}
        except ValueError:
            return {}  # solve() reports the missing weights

    def solve(self, problem: InverseProblem) -> Estimate:
        """Predict w and v from the features of the observed modes with the trained weights.

        Parameters
        ----------
        problem : the inverse problem (no truth).

        Returns
        -------
        Estimate
            ``extra`` names the weights file and the family and split it was trained on.
        """
        t0 = time.perf_counter()
        if not self.config.weights:
            raise ValueError("learned: give the weights file (--set weights=PATH), written by "
                             "`vvtbench train learned FAMILY`")
        path = weights_path(self.config.weights)
        wts, meta = load_weights(path)
        X, v_hom = features(problem)
        Z = (X - wts["mean"]) / wts["std"]
        fw, fv = Z @ wts["coef_w"], Z @ wts["coef_v"]
        w = problem.w_mean * np.exp(fw - fw.mean())
        w *= problem.w_mean / w.mean()
        v = v_hom * np.exp(fv - fv.mean())
        return Estimate(w=w, v=v, runtime_s=time.perf_counter() - t0, config=asdict(self.config),
                        solver=self.name, version=self.version, converged=True,
                        extra={"weights": str(path), "weights_sha256": sha256_file(path),
                               "trained_on": f"{meta.get('family')}/{meta.get('split')}"})
