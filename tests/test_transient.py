"""Transient response: modal superposition vs Newmark, analytic decay, damping pairs."""

import numpy as np
import pytest

from vvtbench.fem.mesh import box_mesh
from vvtbench.fem.modal import eigenmodes
from vvtbench.fem.transient import (
    damping_ratios,
    forced_modal_coordinates,
    free_modal_coordinates,
    modal_damping,
    modal_response,
    newmark_response,
)
from vvtbench.scene.scene import Damping, parse_scene, rayleigh_from_pairs, rayleigh_zeta
from vvtbench.simulation.simulate import simulate


def _ode_reference(t, omega, c, q0, qd0, force=None):
    from scipy.integrate import solve_ivp

    def rhs(tt, y):
        f = force(tt) if force is not None else 0.0
        return [y[1], f - c * y[1] - omega**2 * y[0]]

    sol = solve_ivp(rhs, (t[0], t[-1]), [q0, qd0], t_eval=t, rtol=1e-11, atol=1e-13,
                    method="DOP853")
    return sol.y[0]


@pytest.mark.parametrize("zeta", [0.0, 0.05, 1.0, 3.0])
def test_free_response_matches_ode_solver(zeta):
    omega = 2 * np.pi * 7.0
    c = 2 * zeta * omega
    t = np.linspace(0, 0.5, 400)
    q = free_modal_coordinates(t, np.array([omega]), np.array([c]), np.array([0.3]),
                               np.array([-2.0]))[:, 0]
    ref = _ode_reference(t, omega, c, 0.3, -2.0)
    assert np.abs(q - ref).max() < 1e-8 * max(1.0, np.abs(ref).max())


def test_rigid_mode_free_response_is_linear_motion():
    t = np.linspace(0, 1, 5)
    q = free_modal_coordinates(t, np.zeros(1), np.zeros(1), np.ones(1), np.full(1, 2.0))
    np.testing.assert_allclose(q[:, 0], 1 + 2 * t)


def test_forced_response_matches_ode_solver():
    omega, zeta = 2 * np.pi * 20.0, 0.02
    c = 2 * zeta * omega
    dt = 1e-4
    t = np.arange(3000) * dt

    def force(tt):
        return np.sin(2 * np.pi * (30 * tt + 200 * tt**2))

    q = forced_modal_coordinates(dt, force(t)[:, None], np.array([omega]), np.array([c]))[:, 0]
    ref = _ode_reference(t, omega, c, 0.0, 0.0, force)
    assert np.abs(q - ref).max() < 2e-3 * np.abs(ref).max()


def test_damped_mode_decays_at_analytic_rate():
    alpha, beta = rayleigh_from_pairs([(12.5, 0.01749), (15.5, 0.01999)])
    omega = 2 * np.pi * np.array([12.5, 15.5, 40.0])
    zeta = damping_ratios(omega, alpha, beta)
    np.testing.assert_allclose(zeta[:2], [0.01749, 0.01999], rtol=1e-12)
    t = np.arange(0, 3, 1 / 2000)
    q = free_modal_coordinates(t, omega, modal_damping(omega, alpha, beta), np.ones(3),
                               np.zeros(3))
    for i in range(3):
        wd = omega[i] * np.sqrt(1 - zeta[i] ** 2)
        periods = np.arange(0, t[-1], 2 * np.pi / wd)
        peaks = np.interp(periods, t, q[:, i])
        rate = -np.polyfit(periods, np.log(np.abs(peaks)), 1)[0]
        assert rate == pytest.approx(zeta[i] * omega[i], rel=2e-3)


def _envelope_decay_rate(t: np.ndarray, q: np.ndarray) -> float:
    """Decay rate s of q(t) ~ A exp(-s t) cos(w t + phi), from its positive peaks (each refined
    by a parabola through three samples): the slope of log(peak) against peak time."""
    k = np.flatnonzero((q[1:-1] > q[:-2]) & (q[1:-1] >= q[2:]) & (q[1:-1] > 0)) + 1
    y0, y1, y2 = q[k - 1], q[k], q[k + 1]
    shift = 0.5 * (y0 - y2) / (y0 - 2 * y1 + y2)
    peaks = y1 - 0.25 * (y0 - y2) * shift
    times = t[k] + shift * (t[1] - t[0])
    assert len(k) >= 5
    return -np.polyfit(times, np.log(peaks), 1)[0]


def test_newmark_pluck_decays_at_the_rayleigh_rate_of_each_mode():
    from scipy.sparse.linalg import spsolve

    from vvtbench.fem.assembly import ParametricModel

    mesh = box_mesh((3, 3, 3), (0.05, 0.05, 0.05))
    model = ParametricModel(mesh, fixed_nodes=mesh.node_sets["bottom"])
    K, M = model.K(9000.0), model.M(1270.0)
    modes = eigenmodes(K, M, 4, method="dense")
    alpha, beta = 0.5, 4e-4
    corner = np.flatnonzero(np.all(mesh.points == 0.05, axis=1))
    load = np.zeros(mesh.n_dofs)
    load[mesh.dofs_of(corner)] = 1.0
    u0 = spsolve(K.tocsc(), model.restrict(load))
    times = np.arange(1200) / 1000.0
    u = newmark_response(K, M, alpha, beta, times, u0=u0, substeps=2)
    q = u @ (M @ modes.vectors)
    for n in (0, 3):
        omega = modes.omega[n]
        zeta = alpha / (2 * omega) + beta * omega / 2
        assert abs(q[0, n]) > 0.1 * np.abs(q[0]).max()
        assert _envelope_decay_rate(times, q[:, n]) == pytest.approx(zeta * omega, rel=0.01)


def test_zeta_pairs_round_trip_and_bad_pairs():
    d = Damping(pairs=[(10.0, 0.02), (50.0, 0.03)])
    a, b = d.coefficients()
    assert rayleigh_zeta(a, b, 10.0) == pytest.approx(0.02)
    assert rayleigh_zeta(a, b, 50.0) == pytest.approx(0.03)
    with pytest.raises(ValueError, match="negative Rayleigh"):
        rayleigh_from_pairs([(10.0, 0.1), (50.0, 0.001)])


def test_modal_superposition_agrees_with_newmark_on_damped_pluck():
    scene = parse_scene({
        "name": "small_damped_pluck",
        "geometry": {"kind": "box", "cells": [3, 3, 3]},
        "damping": {"pairs": [[5.0, 0.03], [60.0, 0.2]]},
        "excitation": {"kind": "pluck", "at": [0.05, 0.0, 0.05], "displacement": 1e-3},
        "simulation": {"n_modes": 144, "fps": 500.0, "duration": 0.4},
    })
    modal = simulate(scene, method="modal")
    newmark = simulate(
        scene.model_copy(update={"simulation": scene.simulation.model_copy(
            update={"newmark_substeps": 16})}),
        method="newmark",
    )
    assert modal.truncation_error < 1e-3
    a, b = modal.displacements, newmark.displacements
    assert np.abs(a).max() > 1e-4
    assert np.linalg.norm(a - b) / np.linalg.norm(a) < 1e-3


def test_modal_response_forced_chirp_agrees_with_newmark():
    mesh = box_mesh((2, 2, 2), (0.05, 0.05, 0.05))
    from vvtbench.fem.assembly import ParametricModel

    model = ParametricModel(mesh, fixed_nodes=mesh.node_sets["bottom"])
    K, M = model.K(9000.0), model.M(1270.0)
    modes = eigenmodes(K, M, model.n_free, method="dense")
    alpha, beta = 1.0, 1e-4
    shape = np.zeros(model.n_free)
    shape[-1] = 1.0
    times = np.arange(400) / 400.0

    def force(t):
        return 1e-3 * np.sin(2 * np.pi * (5 * t + 20 * t**2))

    c = modal_damping(modes.omega, alpha, beta)
    u_modal = modal_response(modes.vectors, modes.omega, c, M, times, force=force,
                             force_shape=shape, force_dt=1 / 8000)
    u_newmark = newmark_response(K, M, alpha, beta, times, force=force, force_shape=shape,
                                 substeps=80)
    assert np.linalg.norm(u_modal - u_newmark) / np.linalg.norm(u_modal) < 1e-3
