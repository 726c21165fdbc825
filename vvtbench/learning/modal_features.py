"""A linearized inversion step of the observed modes on a family's modal basis.

The ``learned`` solver's inputs (solvers/learned.py). Every instance of a family shares its
mesh topology (the family varies defects, the box aspect, the camera and the pluck, never the
cells), so one basis of free-DOF vectors serves all instances: the span of the low
homogeneous modes of a few train instances (:func:`reference_basis`; their geometries differ,
so the union covers any instance's aspect). For one instance a Rayleigh-Ritz projection of
its homogeneous model (w = v = 1 on its own geometry) onto that basis gives its homogeneous
modes psi_c and eigenvalues mu_c in milliseconds, without a sparse eigensolve
(:func:`ritz_modes`). Each observed mode is paired (Hungarian, on the MAC of its image-space
shape with P psi_c) with one of the first ``n_slots`` homogeneous modes and expanded on the
projected basis P psi (:func:`pair_observed`); a pairing of low MAC, which the linearization
cannot use, is dropped. :func:`linear_step` then solves the first-order
(Born) equations of the eigenvalue misfits and of the mode mixing in each observed shape for
log(w / w_mean) per voxel. Only the observation enters: eigenvalues, image-space shapes at
visible vertices, the observation operator P and the mesh; never the truth.
"""

from __future__ import annotations

import hashlib

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
from scipy.optimize import linear_sum_assignment

from vvtbench.solving.problem import InverseProblem


def mesh_key(model) -> str:
    """Fingerprint of a model's mesh: its free DOFs and element connectivity, not its node
    coordinates (a family varies the aspect of one mesh; a basis serves every aspect).

    Instances with the same key can share one modal basis (:func:`reference_basis`)."""
    digest = hashlib.sha256()
    for part in (model.free_dofs, model.element_dofs):
        part = np.ascontiguousarray(part, dtype=np.int64)
        digest.update(repr(part.shape).encode())
        digest.update(part.tobytes())
    return digest.hexdigest()[:16]


def reference_basis(problems, n_modes: int = 30, n_basis: int = 120) -> np.ndarray:
    """(n_free, <= n_basis) orthonormal basis spanning the ``n_modes`` lowest homogeneous
    modes (w = v = 1) of each of ``problems`` (instances of one family: their geometries
    differ, e.g. in aspect, so the union spans every instance's low modes far better than
    one instance's modes)."""
    from vvtbench.fem.modal import eigenmodes

    problems = [problems] if isinstance(problems, InverseProblem) else list(problems)
    blocks = []
    for problem in problems:
        model = problem.model
        if blocks and model.n_free != blocks[0].shape[0]:
            raise ValueError("learned: the reference instances differ in mesh (free DOFs "
                             f"{blocks[0].shape[0]} and {model.n_free})")
        vectors = eigenmodes(model.K(1.0), model.M(1.0), min(n_modes, model.n_free - 1)).vectors
        blocks.append(vectors / np.linalg.norm(vectors, axis=0))
    U, sv, _ = np.linalg.svd(np.hstack(blocks), full_matrices=False)
    keep = min(n_basis, int(np.sum(sv > 1e-6 * sv[0])))
    return U[:, :keep]


def ritz_modes(problem: InverseProblem, basis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues (n_basis,) and free-DOF modes (n_free, n_basis) of the instance's
    homogeneous model (w = v = 1) in the span of ``basis``."""
    model = problem.model
    if basis.shape[0] != model.n_free:
        raise ValueError(f"learned: the modal basis has {basis.shape[0]} free DOFs, the "
                         f"problem's model {model.n_free}: a basis of another mesh")
    Kb = model.K(1.0) @ basis
    Mb = model.M(1.0) @ basis
    Kr = basis.T @ Kb
    Mr = basis.T @ Mb
    mu, Q = sla.eigh((Kr + Kr.T) / 2, (Mr + Mr.T) / 2)
    return mu, basis @ Q


N_FIT = 40  # Ritz modes an observed shape is expanded on (higher ones are poorly resolved)


def pair_observed(problem: InverseProblem, mu: np.ndarray, psi: np.ndarray, n_slots: int,
                  mac_min: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Observed modes paired with homogeneous modes: (observed index, homogeneous index,
    least-squares coefficients (n_basis, n_pairs) of each observed shape on P psi, and the
    log of the fitted homogeneous density ratio v_hom / w_mean).

    The pairing is a one-to-one assignment maximizing the total MAC; a pair is kept when its
    MAC is at least ``mac_min``. A mode the slots do not hold, a false mode or a shape too
    noisy to place still gets *some* slot from the assignment, at a low MAC: its first-order
    equations would be wrong, not just noisy.
    """
    from vvtbench.modes.mac import mac_matrix

    n_basis = min(psi.shape[1], N_FIT)
    A = np.asarray(problem.P @ psi[:, :n_basis])
    gamma = np.asarray(problem.gamma, dtype=float)
    lam = np.asarray(problem.eigenvalues, dtype=float)
    slots = min(n_slots, n_basis)
    mac = mac_matrix(gamma, A[:, :slots].T)
    rows, cols = linear_sum_assignment(-mac)
    ok = (lam[rows] > 0) & (mu[cols] > 0) & (mac[rows, cols] >= mac_min)
    rows, cols = rows[ok], cols[ok]
    log_v = float(np.mean(np.log(problem.w_mean * mu[cols] / lam[rows]))) if len(rows) else 0.0
    scale = np.linalg.norm(A, axis=0)
    scale[scale == 0] = 1.0
    An = A / scale
    coef = np.linalg.solve(An.T @ An + 1e-6 * np.eye(n_basis), An.T @ gamma[rows].T)
    return rows, cols, coef / scale[:, None], log_v


def voxel_couplings(problem: InverseProblem, psi: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """(n_pairs, n_basis, n_params) psi_d^T K_e psi_c of the unit model for c in ``cols``:
    how a stiffness change in voxel e moves eigenvalue c (d = c) and mixes mode d into c."""
    model = problem.model
    full = np.zeros((model.mesh.n_dofs, psi.shape[1]))
    full[model.free_dofs] = psi
    U = full[model.element_dofs]                          # (n_el, n_dof_el, n_basis)
    KU = np.matmul(model.Ke, U[:, :, cols])               # (n_el, n_dof_el, n_pairs)
    G = np.matmul(np.transpose(KU, (0, 2, 1)), U)         # (n_el, n_pairs, n_basis)
    param = model.voxel_map.element_param
    n_el = len(param)
    to_voxel = sp.csr_matrix((np.ones(n_el), (param, np.arange(n_el))),
                             shape=(model.n_params, n_el))
    out = (to_voxel @ G.reshape(n_el, -1)).reshape(model.n_params, len(cols), psi.shape[1])
    return np.transpose(out, (1, 2, 0))


def voxel_laplacian(voxel_map) -> np.ndarray:
    """Dense graph Laplacian (nearest neighbours along each axis) of the active voxels."""
    shape = tuple(voxel_map.grid.shape)
    active = np.asarray(voxel_map.active)
    n = len(active)
    where = np.full(int(np.prod(shape)), -1)
    where[active] = np.arange(n)
    ijk = np.array(np.unravel_index(active, shape)).T
    L = np.zeros((n, n))
    for axis in range(len(shape)):
        nb = ijk.copy()
        nb[:, axis] += 1
        ok = nb[:, axis] < shape[axis]
        j = np.full(n, -1)
        j[ok] = where[np.ravel_multi_index(nb[ok].T, shape)]
        i = np.flatnonzero(j >= 0)
        j = j[i]
        L[i, j] -= 1
        L[j, i] -= 1
        L[i, i] += 1
        L[j, j] += 1
    return L


def linear_step(problem: InverseProblem, basis: np.ndarray, n_slots: int,
                smooth: tuple[float, ...] = (0.1, 1.0, 10.0), gap: float = 0.02,
                mac_min: float = 0.0) -> tuple[np.ndarray, dict]:
    """One linearized (Born) inversion from the homogeneous model, per voxel.

    Unknown theta_e = log(w_e / w_mean). Equations: the eigenvalue misfits
    log(lam_obs v_hom / (w_mean mu_c)) = sum_e theta_e psi_c^T K_e psi_c / mu_c, and the
    observed shapes' mixing coefficients a_d / a_c = sum_e theta_e psi_d^T K_e psi_c /
    (mu_c - mu_d) for homogeneous modes d whose eigenvalue differs from mu_c by more than
    ``gap`` (relative; nearer ones mix beyond first order). Solved with a smoothness penalty
    (voxel Laplacian) of each weight in ``smooth``. Only the pairs :func:`pair_observed`
    keeps (MAC at least ``mac_min``) enter.

    Returns
    -------
    steps : (n_params, len(smooth) + 2) the smoothed steps, then the eigenvalue-only and the
        shape-only gradients (J^T y of each group, scaled to unit RMS).
    info : ``v_hom`` (homogeneous density), ``n_eq`` (number of equations), ``y_eig`` (k,)
        the eigenvalue misfit of each observed mode in the observation's order (0 where a mode
        is not paired) and ``observability`` (n_params,) the diagonal of J^T J over its mean:
        how strongly the paired modes see each voxel.
    """
    mu, psi = ritz_modes(problem, basis)
    rows, cols, coef, log_v = pair_observed(problem, mu, psi, n_slots, mac_min)
    lam = np.asarray(problem.eigenvalues, dtype=float)
    m = problem.n_params
    if len(cols) == 0:
        return np.zeros((m, len(smooth) + 2)), {"v_hom": float(problem.w_mean), "n_eq": 0,
                                                "y_eig": np.zeros(len(lam)),
                                                "observability": np.zeros(m)}
    G = voxel_couplings(problem, psi, cols)               # (n_pairs, n_basis, m)
    ar = np.arange(len(cols))
    J_eig = G[ar, cols, :] / mu[cols, None]
    J_eig = J_eig - J_eig.mean(axis=0)   # v_hom absorbs a common shift of all eigenvalues
    y_eig = np.log(lam[rows]) + log_v - np.log(problem.w_mean * mu[cols])
    J_shape, y_shape = [], []
    for j, c in enumerate(cols):
        a = coef[:, j]
        if a[c] == 0:
            continue
        a = a / a[c]
        far = np.flatnonzero(np.abs(mu[:len(a)] - mu[c]) > gap * mu[c])
        J_shape.append(G[j, far, :] / (mu[c] - mu[far])[:, None])
        y_shape.append(np.clip(a[far], -1.0, 1.0))
    J = np.vstack([J_eig, *J_shape])
    y = np.concatenate([y_eig, *y_shape])
    scale = np.sqrt(np.mean(J**2)) or 1.0
    J, y = J / scale, y / scale
    JTJ = J.T @ J
    JTy = J.T @ y
    L = voxel_laplacian(problem.voxel_map)
    steps = []
    tr = np.trace(JTJ) / m
    for alpha in smooth:
        A = JTJ + alpha * tr * L + 1e-3 * tr * np.eye(m)
        steps.append(np.linalg.solve(A, JTy))
    for Jg, yg in ((J_eig, y_eig), (np.vstack(J_shape) if J_shape else np.zeros((0, m)),
                                   np.concatenate(y_shape) if y_shape else np.zeros(0))):
        g = Jg.T @ yg
        steps.append(g / (np.sqrt(np.mean(g**2)) or 1.0))
    v_hom = float(problem.w_mean * np.exp(log_v))
    misfit = np.zeros(len(lam))
    misfit[rows] = y_eig - y_eig.mean()
    return np.column_stack(steps), {"v_hom": v_hom, "n_eq": len(y), "y_eig": misfit,
                                    "observability": np.diag(JTJ) / (tr or 1.0)}


def neighbourhood_means(voxel_map, values: np.ndarray, sizes: tuple[int, ...] = (3, 5)
                        ) -> np.ndarray:
    """(n_params, n_maps * len(sizes)) mean of each column of ``values`` (n_params, n_maps)
    over the active voxels of a cube of ``size`` voxels around each voxel (voids and the
    outside of the grid left out of the mean)."""
    from scipy.ndimage import uniform_filter

    shape = tuple(voxel_map.grid.shape)
    active = np.asarray(voxel_map.active)
    values = np.asarray(values, dtype=float)
    n_maps = values.shape[1]
    grid = np.zeros((int(np.prod(shape)), n_maps))
    grid[active] = values
    grid = grid.reshape(*shape, n_maps)
    mask = np.zeros(int(np.prod(shape)))
    mask[active] = 1.0
    mask = mask.reshape(shape)
    out = []
    for size in sizes:
        window = (size,) * len(shape)
        num = uniform_filter(grid, size=(*window, 1), mode="constant")
        den = uniform_filter(mask, size=window, mode="constant")[..., None]
        out.append((num / np.maximum(den, 1e-12)).reshape(-1, n_maps)[active])
    return np.hstack(out)


def within_instance_rank(values: np.ndarray) -> np.ndarray:
    """Rank of each entry within its column, scaled to [0, 1] (ties in index order)."""
    values = np.asarray(values, dtype=float)
    n = len(values)
    return np.argsort(np.argsort(values, axis=0, kind="stable"), axis=0) / max(n - 1, 1)


def step_features(problem: InverseProblem, basis: np.ndarray, n_slots: int,
                  smooth: tuple[float, ...], n_misfits: int, mac_min: float = 0.0
                  ) -> tuple[np.ndarray, float]:
    """(n_params, n_features) per-voxel inputs of the ``learned`` solver's network, and v_hom.

    Per voxel: the linearized steps (:func:`linear_step`) as solved and scaled to unit RMS
    over the instance, the means of the unit steps over the 3- and 5-voxel neighbourhood, the
    rank of each unit step within the instance, the log observability, the eigenvalue misfits
    of the first ``n_misfits`` observed modes (the same for every voxel of an instance: they
    tell a soft defect from a stiff one) and the voxel's position and its square (grid units
    about the centre).
    """
    steps, info = linear_step(problem, basis, n_slots, smooth=smooth, mac_min=mac_min)
    unit = steps / (np.sqrt(np.mean(steps**2, axis=0)) + 1e-12)
    near = neighbourhood_means(problem.voxel_map, unit)
    rank = within_instance_rank(unit)
    observability = np.log(info["observability"] + 1e-9)[:, None]
    misfit = np.zeros(n_misfits)
    k = min(n_misfits, len(info["y_eig"]))
    misfit[:k] = info["y_eig"][:k]
    grid = problem.voxel_map.grid
    centers = grid.centers()[problem.voxel_map.active]
    pos = (centers - np.asarray(grid.origin)) / np.asarray(grid.size) - 0.5
    m = problem.n_params
    X = np.column_stack([steps, unit, near, rank, observability,
                         np.broadcast_to(misfit, (m, n_misfits)), pos, pos**2])
    return X, info["v_hom"]
