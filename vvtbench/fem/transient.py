"""Transient response with Rayleigh damping C = alpha M + beta K.

Two independent integrators:

* :func:`modal_response`: modal superposition. Each mode obeys
  q'' + c q' + omega^2 q = p(t) with c = alpha + beta omega^2 = 2 zeta omega; free response is
  the exact closed form (under-, critically and over-damped, rigid modes too); forced response
  is exact for a force that is linear between its samples (discrete state transition).
* :func:`newmark_response`: direct average-acceleration Newmark-beta on the full system, with
  substeps, to cross-check the modal result.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import scipy.linalg
import scipy.sparse as sp

from .modal import Factorization


def modal_damping(omega: np.ndarray, alpha: float, beta: float) -> np.ndarray:
    """Modal damping coefficient c_n = alpha + beta omega_n^2 (1/s); zeta_n = c_n / (2 omega_n)."""
    return alpha + beta * np.asarray(omega) ** 2


def damping_ratios(omega: np.ndarray, alpha: float, beta: float) -> np.ndarray:
    """zeta_n = alpha / (2 omega_n) + beta omega_n / 2 (inf for rigid modes with alpha > 0)."""
    omega = np.asarray(omega, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = modal_damping(omega, alpha, beta) / (2 * omega)
    return np.where(omega > 0, z, np.where(alpha > 0, np.inf, 0.0))


def free_modal_coordinates(
    t: np.ndarray, omega: np.ndarray, c: np.ndarray, q0: np.ndarray, qd0: np.ndarray
) -> np.ndarray:
    """Exact free response q_n(t) of q'' + c q' + omega^2 q = 0: shape (len(t), n_modes).

    >>> t = np.array([0.0, 0.25, 0.5])
    >>> free_modal_coordinates(t, np.array([2 * np.pi]), np.zeros(1), np.ones(1), np.zeros(1))
    array([[ 1.],
           [ 0.],
           [-1.]])
    """
    t = np.asarray(t, dtype=float)[:, None]
    omega, c = np.asarray(omega, float), np.asarray(c, float)
    q0, qd0 = np.asarray(q0, float), np.asarray(qd0, float)
    disc = c**2 / 4 - omega**2
    scale = np.maximum(omega, np.abs(c) / 2)
    critical = np.abs(disc) <= 1e-10 * np.maximum(scale**2, 1e-300)
    root = np.sqrt(np.abs(disc))
    decay = np.exp(-c / 2 * t)
    out = np.empty((t.shape[0], omega.shape[0]))
    under = (~critical) & (disc < 0)
    if under.any():
        wd = root[under]
        b = (qd0[under] + c[under] / 2 * q0[under]) / wd
        out[:, under] = decay[:, under] * (q0[under] * np.cos(wd * t) + b * np.sin(wd * t))
    over = (~critical) & (disc > 0)
    if over.any():
        s1 = -c[over] / 2 + root[over]
        s2 = -c[over] / 2 - root[over]
        a1 = (qd0[over] - s2 * q0[over]) / (s1 - s2)
        a2 = q0[over] - a1
        out[:, over] = a1 * np.exp(s1 * t) + a2 * np.exp(s2 * t)
    if critical.any():
        s = -c[critical] / 2
        out[:, critical] = np.exp(s * t) * (q0[critical] + (qd0[critical] - s * q0[critical]) * t)
    return out


def forced_modal_coordinates(
    dt: float,
    p: np.ndarray,
    omega: np.ndarray,
    c: np.ndarray,
    q0: np.ndarray | None = None,
    qd0: np.ndarray | None = None,
) -> np.ndarray:
    """Modal coordinates at t_j = j dt under modal forces ``p`` (n_steps, n_modes).

    Exact when each p_n is linear between samples (first-order-hold state transition).
    """
    p = np.asarray(p, dtype=float)
    n_steps, n = p.shape
    a = np.zeros((n, 4, 4))
    a[:, 0, 1] = 1.0
    a[:, 1, 0] = -np.asarray(omega, float) ** 2
    a[:, 1, 1] = -np.asarray(c, float)
    a[:, 1, 2] = 1.0
    a[:, 2, 3] = 1.0 / dt
    phi = scipy.linalg.expm(a * dt)
    transition = phi[:, :2, :2]
    g_ramp = phi[:, :2, 3]
    g_hold = phi[:, :2, 2] - g_ramp
    x = np.zeros((n, 2))
    if q0 is not None:
        x[:, 0] = q0
    if qd0 is not None:
        x[:, 1] = qd0
    out = np.empty((n_steps, n))
    out[0] = x[:, 0]
    for j in range(n_steps - 1):
        x = (
            np.einsum("nij,nj->ni", transition, x)
            + g_hold * p[j][:, None]
            + g_ramp * p[j + 1][:, None]
        )
        out[j + 1] = x[:, 0]
    return out


def modal_coordinates(
    vectors: np.ndarray,
    omega: np.ndarray,
    c: np.ndarray,
    M: sp.spmatrix,
    times: np.ndarray,
    u0: np.ndarray | None = None,
    v0: np.ndarray | None = None,
    force: Callable[[np.ndarray], np.ndarray] | None = None,
    force_shape: np.ndarray | None = None,
    force_dt: float | None = None,
) -> np.ndarray:
    """Modal coordinates q(t) (len(times), k) of the response; see :func:`modal_response`."""
    times = np.asarray(times, dtype=float)
    k = vectors.shape[1]
    q0 = vectors.T @ (M @ u0) if u0 is not None else np.zeros(k)
    qd0 = vectors.T @ (M @ v0) if v0 is not None else np.zeros(k)
    if force is None:
        return free_modal_coordinates(times, omega, c, q0, qd0)
    frame_dt = times[1] - times[0] if len(times) > 1 else 1.0
    sub = max(1, int(np.ceil(frame_dt / force_dt - 1e-9))) if force_dt else 1
    fine_t = np.arange((len(times) - 1) * sub + 1) * (frame_dt / sub)
    p = np.outer(force(fine_t), vectors.T @ force_shape)
    return forced_modal_coordinates(frame_dt / sub, p, omega, c, q0, qd0)[::sub]


def modal_response(
    vectors: np.ndarray,
    omega: np.ndarray,
    c: np.ndarray,
    M: sp.spmatrix,
    times: np.ndarray,
    u0: np.ndarray | None = None,
    v0: np.ndarray | None = None,
    force: Callable[[np.ndarray], np.ndarray] | None = None,
    force_shape: np.ndarray | None = None,
    force_dt: float | None = None,
    observe: np.ndarray | None = None,
    dtype=np.float32,
) -> np.ndarray:
    """Displacements u(t) = Phi q(t) at ``times`` (uniform, starting at 0).

    Parameters
    ----------
    vectors : (n_free, k) mass-normalized modes Phi; omega, c : (k,) per mode.
    M : mass matrix (free DOFs), to project initial conditions: q0 = Phi^T M u0.
    u0, v0 : initial displacement and velocity over the free DOFs.
    force : scalar signal f(t) (N); the load vector is ``force_shape`` * f(t).
    force_dt : integration step for the forced part (default: the frame step); outputs are
        taken every frame.
    observe : (n_observed, k) rows of the mode matrix to return, e.g. the modes expanded to
        all DOFs and taken at surface nodes (default: ``vectors``, all free DOFs).

    Returns
    -------
    (len(times), n_observed) array of ``dtype``.
    """
    q = modal_coordinates(vectors, omega, c, M, times, u0, v0, force, force_shape, force_dt)
    obs = vectors if observe is None else observe
    return (q @ obs.T).astype(dtype, copy=False)


def newmark_response(
    K: sp.spmatrix,
    M: sp.spmatrix,
    alpha: float,
    beta: float,
    times: np.ndarray,
    u0: np.ndarray | None = None,
    v0: np.ndarray | None = None,
    force: Callable[[np.ndarray], np.ndarray] | None = None,
    force_shape: np.ndarray | None = None,
    substeps: int = 4,
    observe: np.ndarray | None = None,
) -> np.ndarray:
    """Average-acceleration Newmark (gamma 1/2, beta 1/4) on M u'' + C u' + K u = f(t).

    Unconditionally stable, second-order, no numerical damping; its period error
    (omega h)^2 / 12 is made small with ``substeps`` steps per frame.
    """
    times = np.asarray(times, dtype=float)
    n = K.shape[0]
    h = (times[1] - times[0]) / substeps if len(times) > 1 else 1.0
    C = alpha * M + beta * K
    u = np.zeros(n) if u0 is None else np.asarray(u0, float).copy()
    v = np.zeros(n) if v0 is None else np.asarray(v0, float).copy()

    def load(t: float) -> np.ndarray:
        return force_shape * float(force(np.array([t]))[0]) if force is not None else 0.0

    acc = Factorization(M)(load(0.0) - C @ v - K @ u)
    effective = Factorization(M + (h / 2) * C + (h * h / 4) * K)
    obs = np.arange(n) if observe is None else observe
    out = np.empty((len(times), len(obs)))
    out[0] = u[obs]
    t = 0.0
    for frame in range(1, len(times)):
        for _ in range(substeps):
            t += h
            u_pred = u + h * v + (h * h / 4) * acc
            v_pred = v + (h / 2) * acc
            acc = effective(load(t) - C @ v_pred - K @ u_pred)
            u = u_pred + (h * h / 4) * acc
            v = v_pred + (h / 2) * acc
        out[frame] = u[obs]
    return out
