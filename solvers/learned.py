"""``learned``: a learned per-voxel network on one linearized inversion step.

A learned baseline for the dataset generator's families: trained only on a family's train
split (``vvtbench train learned FAMILY``; its architecture chosen on the val split), scored on
its test split like every solver.

Model ("modal-step-mlp", :mod:`vvtbench.learning.modal_features`). A family's instances share
one inference mesh per geometry (drums: two), so the weights carry a modal basis per mesh: the
lowest homogeneous modes of its first few train instances. For a new instance a Rayleigh-Ritz
projection on that basis gives its own homogeneous modes in milliseconds (no eigensolve); the
observed modes are paired with them by MAC (a pair of MAC below 0.5 is dropped: a mode
beyond the paired slots, a false mode or a shape too noisy to place), and one linearized
(Born) inversion from the homogeneous model is solved for log(w / w_mean) per voxel, from the
eigenvalue misfits *and* the mixing of homogeneous modes in each observed shape, at three
smoothness weights, beside the eigenvalue-only and shape-only gradients. Per voxel, an
ensemble of small networks (numpy, two ReLU layers, :mod:`vvtbench.learning.mlp`) reads
these step maps, their means over the voxel's 3- and 5-voxel neighbourhood, their ranks
within the instance, the voxel's observability and position and the instance's eigenvalue
misfits, and predicts the truth's w standardized per instance (the least-squares surrogate of
the NC of w; instances with a uniform truth carry no target). w is a positive affine map of
that prediction (mean w_mean, the lowest voxel at half of it): its NC is the prediction's, its
contrast is not learned. v is the homogeneous density fitted to the eigenvalues.

Why this family of models: a global map from an instance's observation to the whole field
(ridge on 800 modal features) does not generalize from hundreds of instances (val NC w 0.03);
a per-voxel map shares one small model across all voxels and instances (each instance gives
hundreds of samples) and keeps the physics of the inversion in its inputs. A linear per-voxel
map (2.0, "modal-step-ridge") is flat from 100 instances on; the network, its neighbourhood
inputs and the NC-shaped target are what 3.0 adds. 3.1 pairs into 40 slots instead of 20 and
drops pairs of low MAC: the Born equations of a mispaired mode are wrong, not noisy (val NC w
from 10 true modes, 400 train instances: 0.288 without the gate, 0.347 with it; from the
extracted modes of 5 val videos: 0.09 and 0.20). Weights record their pairing
(:class:`Pairing`) and are solved with it. Cost per solve: one Ritz projection, one dense
solve per smoothness weight and three tiny networks (tens of ms on a quiet core).

Weights of the earlier models ("modal-step-ridge", and "ridge-sensitivity": ridge regression
on first-order eigenvalue-sensitivity features of the homogeneous modes, no shape
information) are still read and solved with their model.
"""

from __future__ import annotations

import json
import time
import zipfile
from collections.abc import Iterable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from vvtbench.api import Estimate, InverseProblem, sha256_file

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
    members: int = field(default=3, metadata={
        "help": "training only: networks in the ensemble (member i seeded with i)"})
    epochs: int = field(default=15, metadata={
        "help": "training only: passes of Adam over the train voxels per network"})
    max_steps: int = field(default=10000, metadata={
        "help": "training only: Adam steps per network at most (the epochs are cut short "
                "on a train set larger than this many minibatches of 2048 voxels: bounds "
                "the fit time)"})


def features(problem: InverseProblem) -> tuple[np.ndarray, float]:
    """(n_params, n_features) features of every voxel, and the homogeneous density v_hom."""
    from scipy.optimize import linear_sum_assignment

    from vvtbench.api import eigenmodes, mac_matrix

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


MODEL = "modal-step-mlp"
RIDGE_MODEL = "modal-step-ridge"
LEGACY_MODEL = "ridge-sensitivity"
N_SLOTS = 40  # homogeneous modes an observed mode may pair with (an extraction reaches ~36)
MAC_MIN = 0.5  # pairs kept: MAC at least this (chosen on val)
N_REFERENCE = 8  # train instances whose homogeneous modes span the basis
SMOOTH = (0.3, 1.0, 3.0)  # smoothness weights of the linearized steps (val-chosen range)
HIDDEN = (64, 32)  # chosen on val: wider (128, 64) and deeper (64, 64, 32) nets overfit
EPOCHS = 15
MEMBERS = 3
BATCH = 2048  # voxels per Adam step
MAX_STEPS = 10000  # Adam steps per network at most: 2.7 epochs of 20 000 cube instances
STORED_FEATURES = ("X", "w")  # what a feature store keeps of an instance_features item


def reference_basis(problems) -> np.ndarray:
    """The modal basis of one mesh: the low homogeneous modes of a few train instances
    (:func:`vvtbench.learning.modal_features.reference_basis`)."""
    from vvtbench.api import reference_basis as basis_of

    return basis_of(problems)


def mesh_key(problem: InverseProblem) -> str:
    """The mesh a basis belongs to (:func:`vvtbench.learning.modal_features.mesh_key`)."""
    from vvtbench.api import mesh_key as key_of

    return key_of(problem.model)


def basis_entries(bases: dict[str, np.ndarray]) -> dict:
    """What the weights keep of the bases of their meshes (``mesh_key: basis``, in the order
    the train split first showed each mesh): ``basis`` for one mesh, ``basis_0``,
    ``basis_1``... for several, and ``mesh_keys``."""
    keys = list(bases)
    if len(keys) == 1:
        return {"basis": bases[keys[0]], "mesh_keys": keys}
    return {"mesh_keys": keys, **{f"basis_{i}": bases[k] for i, k in enumerate(keys)}}


def basis_for(weights: dict, problem: InverseProblem) -> np.ndarray:
    """The weights' basis of the problem's mesh. Weights without ``mesh_keys`` carry one
    basis, checked only by its number of free DOFs (:func:`ritz_modes`)."""
    keys = weights.get("mesh_keys")
    if not keys:
        return weights["basis"]
    key = mesh_key(problem)
    if key not in keys:
        raise ValueError(f"learned: the problem's mesh ({key}) is none of the {len(keys)} "
                         f"the weights were trained on ({', '.join(keys)}): weights of another "
                         "family, or a mesh its train split never showed")
    name = "basis" if len(keys) == 1 else f"basis_{keys.index(key)}"
    if name not in weights:
        raise ValueError(f"learned: the weights name mesh {key} but hold no {name!r} array "
                         "(a damaged weights file)")
    return weights[name]


@dataclass(frozen=True)
class Pairing:
    """How observed modes are paired with homogeneous modes
    (:func:`vvtbench.learning.modal_features.pair_observed`). Weights record theirs and are
    solved with it: files without these keys (models before 3.1) paired into 20 slots and
    kept every pair."""

    n_slots: int = N_SLOTS
    mac_min: float = MAC_MIN

    @classmethod
    def of(cls, meta: dict, source: str | Path = "weights") -> Pairing:
        """The pairing a weights file's ``meta`` records; ``source`` names the file in the
        error a damaged or hand-edited value raises."""
        n_slots, mac_min = meta.get("n_slots", 20), meta.get("mac_min", 0.0)
        if isinstance(n_slots, bool) or not isinstance(n_slots, int) or n_slots < 1:
            raise ValueError(f"{source}: meta key 'n_slots' is {n_slots!r}; allowed: an "
                             "integer >= 1 (the pairing slots the weights were trained with)")
        if (isinstance(mac_min, bool) or not isinstance(mac_min, (int, float))
                or not 0.0 <= mac_min <= 1.0):
            raise ValueError(f"{source}: meta key 'mac_min' is {mac_min!r}; allowed: a number "
                             "in [0, 1] (the lowest MAC a kept pair may have)")
        return cls(n_slots, float(mac_min))


def voxel_features(problem: InverseProblem, basis: np.ndarray, pairing: Pairing = Pairing()
                   ) -> tuple[np.ndarray, float]:
    """(n_params, n_features) per-voxel inputs of the network
    (:func:`vvtbench.learning.modal_features.step_features`), and v_hom."""
    from threadpoolctl import threadpool_limits

    from vvtbench.api import step_features

    with threadpool_limits(limits=1, user_api="blas"):  # small dense algebra: threads only wait
        return step_features(problem, basis, pairing.n_slots, SMOOTH, N_MODES,
                             pairing.mac_min)


def ridge_voxel_features(problem: InverseProblem, basis: np.ndarray,
                         pairing: Pairing = Pairing(20, 0.0)
                         ) -> tuple[np.ndarray, float]:
    """Per-voxel features of the 2.0 model ("modal-step-ridge", still read)."""
    from threadpoolctl import threadpool_limits

    from vvtbench.api import linear_step

    with threadpool_limits(limits=1, user_api="blas"):
        steps, info = linear_step(problem, basis, pairing.n_slots, smooth=SMOOTH,
                                  mac_min=pairing.mac_min)
    unit = steps / (np.sqrt(np.mean(steps**2, axis=0)) + 1e-12)
    grid = problem.voxel_map.grid
    centers = grid.centers()[problem.voxel_map.active]
    pos = (centers - np.asarray(grid.origin)) / np.asarray(grid.size) - 0.5
    return np.column_stack([steps, unit, pos**2]), info["v_hom"]


def standardized(w: np.ndarray) -> np.ndarray | None:
    """(w - mean) / std of one instance's truth; None for a uniform field (no NC defined:
    :func:`vvtbench.scoring.metrics.is_constant`, the leaderboard's test)."""
    from vvtbench.api import is_constant

    w = np.asarray(w, dtype=float)
    if is_constant(w):
        return None
    return (w - w.mean()) / float(w.std())


def feature_item(X: np.ndarray, w: np.ndarray) -> dict:
    """A train or val item from an instance's per-voxel features ``X`` and its truth's
    ``w``: the target ``y`` is the standardized w (None for a uniform truth)."""
    w = np.asarray(w, dtype=float)
    return {"X": X, "y": standardized(w), "w": w}


def instance_features(problem: InverseProblem, truth, basis: np.ndarray) -> dict:
    """Features and target of one train or val instance (``truth``: its Truth): the target
    is the instance's standardized w (None for a uniform truth). A feature store keeps its
    ``STORED_FEATURES`` (:mod:`vvtbench.learning.feature_store`)."""
    return feature_item(voxel_features(problem, basis)[0], truth.w)


def bounded_steps(n_voxels: int, epochs: int = EPOCHS, max_steps: int = MAX_STEPS) -> int:
    """Adam steps a network is trained for on ``n_voxels`` samples: ``epochs`` passes of
    minibatches, or ``max_steps`` if fewer (the last pass then cut short).

    >>> bounded_steps(500 * 512), bounded_steps(20000 * 381)  # the shipped cube fit; 20 000
    (1875, 10000)
    """
    return min(int(epochs) * _steps_per_epoch(n_voxels), int(max_steps))


def _steps_per_epoch(n_voxels: int) -> int:
    return max(1, -(-int(n_voxels) // BATCH))


def fit_arrays(X: np.ndarray, y: np.ndarray, basis: np.ndarray | dict[str, np.ndarray],
               n_instances: int, n_used: int, members: int = MEMBERS, epochs: int = EPOCHS,
               max_steps: int = MAX_STEPS) -> dict:
    """Weights of the per-voxel network ensemble from stacked per-voxel features ``X`` and
    targets ``y`` of ``n_used`` instances (of ``n_instances``; member i seeded with i),
    trained for :func:`bounded_steps` Adam steps. ``basis``: one basis, or the basis of
    each mesh (:func:`basis_entries`)."""
    from vvtbench.api import fit_mlp

    if members < 1 or epochs < 1 or max_steps < 1:
        raise ValueError("learned: members, epochs and max_steps must be >= 1, got "
                         f"{members}, {epochs}, {max_steps}")
    steps = bounded_steps(len(X), epochs, max_steps)
    bases = basis_entries(basis) if isinstance(basis, dict) else {"basis": basis}
    weights = {"model": MODEL, **bases, "n_instances": int(n_instances),
               "n_used": int(n_used), "n_voxels": int(len(X)), "members": int(members),
               "hidden": list(HIDDEN), "epochs": round(steps / _steps_per_epoch(len(X)), 3),
               "steps": steps, "epochs_asked": int(epochs),
               "max_steps": int(max_steps), **asdict(Pairing()),
               "target": "standardized w per instance"}
    for i in range(members):
        params = fit_mlp(X, y, hidden=HIDDEN, batch=BATCH, seed=i, steps=steps)
        weights.update({f"m{i}_{k}": np.asarray(v) for k, v in params.items()})
    return weights


def fit_features(items: list[dict], basis: np.ndarray | dict[str, np.ndarray],
                 members: int = MEMBERS,
                 epochs: int = EPOCHS, max_steps: int = MAX_STEPS) -> dict:
    """Weights of the per-voxel network ensemble from :func:`instance_features` items
    (:func:`fit_arrays`); instances with a uniform truth carry no target and are left out."""
    used = [it for it in items if it["y"] is not None]
    if not used:
        raise ValueError("learned: no training instance with a non-uniform w (all "
                         f"{len(items)} are homogeneous)")
    X = np.vstack([it["X"] for it in used])
    y = np.concatenate([it["y"] for it in used])
    return fit_arrays(X, y, basis, len(items), len(used), members, epochs, max_steps)


def fit_store(store, train: list, val: list = (), members: int = MEMBERS,
              epochs: int = EPOCHS, max_steps: int = MAX_STEPS) -> dict:
    """Weights from the features of a feature store
    (:class:`vvtbench.learning.feature_store.FeatureStore`): its ``train`` entries, in
    index order, stacked into one array (memory: the features, never the instances), and the
    mean NC w on its ``val`` entries recorded. The same instances give the weights
    :func:`fit` gives from the instances themselves."""
    if not train:
        raise ValueError(f"{store.root}: no train instances in the feature store")
    targets = []
    for _, arrays in store.iter_arrays(train, ("w",)):
        targets.append(standardized(arrays["w"]))
    rows = sum(len(t) for t in targets if t is not None)
    if not rows:
        raise ValueError("learned: no training instance with a non-uniform w (all "
                         f"{len(train)} are homogeneous)")
    X, y, at = None, np.empty(rows), 0
    for (_, arrays), target in zip(store.iter_arrays(train, ("X",)), targets, strict=True):
        if target is None:
            continue
        if X is None:
            X = np.empty((rows, arrays["X"].shape[1]))
        X[at:at + len(target)] = arrays["X"]
        y[at:at + len(target)] = target
        at += len(target)
    n_used = sum(t is not None for t in targets)
    key = store.meta.get("mesh_key")
    basis = {key: store.basis} if key else store.basis
    weights = fit_arrays(X, y, basis, len(train), n_used, members, epochs, max_steps)
    del X, y
    held = [feature_item(a["X"], a["w"]) for _, a in store.iter_arrays(list(val), ("X", "w"))]
    _record_val(weights, held)
    return weights


def _record_val(weights: dict, held: list[dict]) -> None:
    """``n_val`` (val instances), ``n_val_scored`` (those with a contrast) and ``val_nc_w``
    (their mean NC w, :func:`mean_nc`)."""
    weights["n_val"] = len(held)
    weights["n_val_scored"] = sum(_has_contrast(it) for it in held)
    weights["val_nc_w"] = mean_nc(weights, held)


def _has_contrast(item: dict) -> bool:
    from vvtbench.api import is_constant

    return not is_constant(item["w"])


def _members(weights: dict) -> list[dict]:
    n = int(np.asarray(weights["members"]))
    return [{k.split("_", 1)[1]: v for k, v in weights.items() if k.startswith(f"m{i}_")}
            for i in range(n)]


def predict_field(weights: dict, X: np.ndarray) -> np.ndarray:
    """The ensemble's mean prediction of the standardized w, per voxel."""
    from vvtbench.api import mlp_predict

    return np.mean([mlp_predict(params, X) for params in _members(weights)], axis=0)


def field_to_w(field: np.ndarray, w_mean: float) -> np.ndarray:
    """Positive w of mean ``w_mean`` from a predicted standardized field: a positive affine
    map (NC unchanged), the lowest voxel at half the mean."""
    d = field - field.mean()
    low = float(-d.min())
    scale = 0.5 / low if low > 1e-12 else 0.0
    return w_mean * (1.0 + scale * d)


def predict_w(weights: dict, X: np.ndarray, w_mean: float) -> np.ndarray:
    """w of one instance from its per-voxel features (mean w = w_mean)."""
    if str(weights.get("model")) == RIDGE_MODEL:
        f = ((X - weights["mean"]) / weights["std"]) @ weights["coef_w"]
        w = np.exp(np.clip(f - f.mean(), -30.0, 30.0))
        return w * (w_mean / w.mean())
    return field_to_w(predict_field(weights, X), w_mean)


def mean_nc(weights: dict, items: list[dict]) -> float | None:
    """Mean NC w of the weights on feature items (their ``X`` and truth ``w``) whose truth
    has a contrast: NC is undefined for a uniform truth, so those items are left out (None
    when every item's truth is uniform)."""
    from vvtbench.api import normalized_correlation

    scored = [it for it in items if _has_contrast(it)]
    if not scored:
        return None
    return float(np.mean([normalized_correlation(predict_w(weights, it["X"], 1.0), it["w"])
                          for it in scored]))


def featurize_by_mesh(pairs: Iterable) -> tuple[list[dict], dict[str, np.ndarray]]:
    """Features of every ``(problem, truth)`` pair in order, and the basis of every mesh
    among them (in the order the pairs first show each mesh). A mesh's basis is fixed by its
    first ``N_REFERENCE`` instances (all of them if fewer), which wait unfeaturized until
    then: for a family of one mesh, its first ``N_REFERENCE`` instances; of several (square
    and circular drums), each mesh's own."""
    bases: dict[str, np.ndarray] = {}
    waiting: dict[str, list] = {}
    items: dict[int, dict] = {}

    def fix(key: str) -> None:
        group = waiting.pop(key)
        bases[key] = reference_basis([problem for _, problem, _ in group])
        for i, problem, truth in group:
            items[i] = instance_features(problem, truth, bases[key])

    first: dict[str, int] = {}
    for i, (problem, truth) in enumerate(pairs):
        key = mesh_key(problem)
        first.setdefault(key, i)
        if key in bases:
            items[i] = instance_features(problem, truth, bases[key])
            continue
        waiting.setdefault(key, []).append((i, problem, truth))
        if len(waiting[key]) == N_REFERENCE:
            fix(key)
    for key in list(waiting):
        fix(key)
    return [items[i] for i in sorted(items)], {k: bases[k] for k in sorted(bases, key=first.get)}


def fit(pairs: Iterable, members: int = MEMBERS, epochs: int = EPOCHS,
        val: Iterable = (), max_steps: int = MAX_STEPS) -> dict:
    """Weights from ``(problem, truth)`` pairs of a family's train split; the mean NC w on
    the ``val`` pairs is recorded (the architecture was chosen on the val split). A family
    of several meshes gets one basis per mesh (:func:`featurize_by_mesh`)."""
    if members < 1 or epochs < 1 or max_steps < 1:
        raise ValueError("learned: members, epochs and max_steps must be >= 1, got "
                         f"{members}, {epochs}, {max_steps}")
    train, bases = featurize_by_mesh(pairs)
    if not train:
        raise ValueError("no training instances")
    weights = fit_features(train, bases, members, epochs, max_steps)
    held = [instance_features(p, t, basis_for(weights, p)) for p, t in val]
    _record_val(weights, held)
    return weights


def save_weights(path: str | Path, weights: dict, meta: dict) -> Path:
    """The weights (.npz arrays) with their provenance (JSON in the same file)."""
    from vvtbench.api import write_npz

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
    """A learned per-voxel network on one linearized inversion step."""

    name = "learned"
    version = "3.1.0"
    trainable = True  # module-level fit() and save_weights(): `vvtbench train learned FAMILY`;
    # fit_store() and the feature hooks: `--drop-instances` (vvtbench.learning.feature_store)
    description = ("Learned baseline: a per-voxel network on one linearized inversion step "
                   "(eigenvalue misfits and mode mixing on a Ritz basis) and its "
                   "neighbourhood, trained on a family's train split")
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
        model = meta.get("model", LEGACY_MODEL)
        if model in (MODEL, RIDGE_MODEL):
            pairing = Pairing.of(meta, path)
            wts = {**wts, "model": model, "members": meta.get("members", 0),
                   "mesh_keys": meta.get("mesh_keys")}
            featurize = voxel_features if model == MODEL else ridge_voxel_features
            X, v_hom = featurize(problem, basis_for(wts, problem), pairing)
            w = predict_w(wts, X, problem.w_mean)
            v = np.full(problem.n_params, v_hom)
        else:
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
