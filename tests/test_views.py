"""Several cameras: the observation operator stacks the views, the solvers take the stacked
problem unchanged, and each added view raises the fraction of DOFs observed."""

from __future__ import annotations

import numpy as np
import pytest

from vvtbench.observe import ObserveError, observe, observed_dof_fraction, turned_camera
from vvtbench.render import Camera
from vvtbench.scene.scene import load_scene

SMALL = dict(n_modes=6, inference_shape=(3, 3, 3))


@pytest.fixture(scope="module")
def cube():
    from vvtbench.simulation.simulate import simulate

    return simulate(load_scene("jello_cube_defect_top"), transient=False)


def test_a_turned_camera_sees_the_same_point_from_the_other_side():
    cam = Camera.look_at((0.3, -0.1, 0.2), (0.02, 0.03, 0.01), fov_y_deg=20.0, width=64,
                         height=48)
    centre = np.array([0.02, 0.03, 0.01])
    for angle in (0.3, np.pi, 5.0):
        t = turned_camera(cam, angle, np.array([0, 0, 1.0]), centre)
        assert np.allclose(t.project(centre), cam.project(centre))
        c0, c1 = -cam.R.T @ cam.t, -t.R.T @ t.t
        assert np.linalg.norm(c1 - centre) == pytest.approx(np.linalg.norm(c0 - centre))
        assert c1[2] == pytest.approx(c0[2])  # same height: turned about the vertical
    full = turned_camera(cam, 2 * np.pi, np.array([0, 0, 1.0]), centre)
    assert np.allclose(full.R, cam.R) and np.allclose(full.t, cam.t)


def test_views_stack_the_observation_of_one_set_of_modes(cube):
    one, truth1 = observe(cube, **SMALL)
    two, truth2 = observe(cube, **SMALL, views=2)
    assert two.P.shape[0] == sum(two.meta["n_visible_per_view"]) * 2
    assert np.allclose(two.P[: one.P.shape[0]].toarray(), one.P.toarray())
    # every mode is one vector over both views, from the same 3-D mode
    for i in range(two.n_modes):
        g = two.P @ truth2.modes_3d[:, i]
        assert np.allclose(g, two.gamma[i]) and np.linalg.norm(g) == pytest.approx(1.0)
        u1, u2 = truth1.modes_3d[:, i], truth2.modes_3d[:, i]
        assert abs(u1 @ u2) / np.linalg.norm(u1) / np.linalg.norm(u2) == pytest.approx(1.0)
    assert np.allclose(truth1.w, truth2.w) and np.allclose(one.eigenvalues, two.eigenvalues)


def test_each_view_observes_more_of_the_body(cube):
    fractions = [observe(cube, **SMALL, views=v)[0].meta["observed_dof_fraction"]
                 for v in (1, 2, 4)]
    assert 0 < fractions[0] < fractions[1] < fractions[2] <= 1
    # one view sees each visible vertex along two directions
    one = observe(cube, **SMALL)[0]
    assert fractions[0] == pytest.approx(2 * len(np.unique(one.visible_nodes)) / one.model.n_free)


def test_the_dof_fraction_is_the_rank_of_the_operator(cube):
    p, _ = observe(cube, **SMALL, views=3)
    assert observed_dof_fraction(p.P, p.model) == pytest.approx(
        np.linalg.matrix_rank(p.P.toarray()) / p.model.n_free)


@pytest.mark.parametrize("solver", ["sensitivity", "vvt"])
def test_the_solvers_take_the_stacked_problem_unchanged(cube, solver):
    from vvtbench.scoring.metrics import invalid_reason
    from vvtbench.solving.sealed import solve_sealed

    problem, truth = observe(cube, **SMALL, views=2)
    config = {"max_iter": 3} if solver == "vvt" else {}
    est, _, info = solve_sealed(solver, config, problem, timeout=300)
    assert est.w.shape == (problem.n_params,) and info["sandbox"] in ("bwrap", "none")
    assert invalid_reason(est.w, est.v, problem.n_params) is None or solver == "vvt"


def test_extracted_views_need_a_video_per_view_and_no_clicks():
    with pytest.raises(ObserveError, match=r"holds 1 view\(s\).*\[camera.rig\]"):
        observe("jello_cube_defect_top", observation="extracted", views=2)
    with pytest.raises(ObserveError, match="clicks"):
        observe("jello_cube_defect_top", views=2, clicks="x.csv")
    with pytest.raises(ObserveError, match="views"):
        observe("jello_cube_defect_top", views=0)
