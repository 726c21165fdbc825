"""Metrics on hand-made fields: exact values the definitions imply (docs/metrics.md)."""

from __future__ import annotations

import numpy as np
import pytest

from vvtbench.scoring.metrics import (
    gaussian_blur,
    intrinsic_resolution,
    mac_matrix,
    normalized_correlation,
)


@pytest.fixture
def field():
    rng = np.random.default_rng(0)
    x = np.full((8, 8, 8), 9000.0)
    x[4:6, 2:5, 5:7] = 5e4
    return x + rng.normal(0, 50, x.shape)


def test_nc_identities(field):
    assert normalized_correlation(field, field) == pytest.approx(1.0)
    assert normalized_correlation(-field, field) == pytest.approx(-1.0)
    assert normalized_correlation(3 * field + 7, field) == pytest.approx(1.0)  # affine-invariant
    assert normalized_correlation(np.full_like(field, 4.0), field) == 0.0
    assert normalized_correlation(field, field, centered=False) == pytest.approx(1.0)
    assert normalized_correlation(-field, field, centered=False) == pytest.approx(-1.0)
    # uncentered is not offset-invariant
    assert normalized_correlation(field - 9000, field, centered=False) < 0.99


def test_nc_ignores_empty_voxels(field):
    a, b = field.copy(), field.copy()
    a[0] = np.nan
    b[0] = 1e9  # ignored where the estimate is NaN
    assert normalized_correlation(a, b) == pytest.approx(1.0)


def test_blur_is_nan_aware_and_mean_preserving():
    g = np.full((6, 6, 6), 2.0)
    g[0, 0, 0] = np.nan
    b = gaussian_blur(g, 1.5)
    assert np.isnan(b[0, 0, 0])
    assert np.allclose(b[np.isfinite(b)], 2.0)  # constants stay constant, also at the borders


@pytest.mark.parametrize("sigma", [0.0, 0.8, 1.4, 2.0])
def test_sigma_star_of_a_blurred_field_is_its_blur(field, sigma):
    estimate = gaussian_blur(field, sigma)
    ir = intrinsic_resolution(estimate, field)
    assert ir["sigma_star"] == pytest.approx(sigma, abs=0.1)
    assert ir["nc_at_sigma_star"] > 0.999


def test_mac():
    a = np.array([[1.0, 0, 0], [0, 1, 1]])
    m = mac_matrix(a, np.array([[2.0, 0, 0], [0, -1, -1], [1, 1, 0]]))
    assert m[0, 0] == pytest.approx(1) and m[1, 1] == pytest.approx(1)
    assert m[0, 1] == 0 and m[1, 2] == pytest.approx(0.25)


def test_constant_truth_is_scored_by_false_contrast_not_nc():
    from types import SimpleNamespace

    from vvtbench.scoring.metrics import evaluate, false_contrast, is_constant

    flat = np.full(27, 9000.0) + np.random.default_rng(0).normal(0, 5e-12, 27)
    assert is_constant(flat) and not is_constant(flat * np.linspace(1, 1.01, 27))
    grid = lambda x, fill=np.nan: np.asarray(x, dtype=float).reshape(3, 3, 3)  # noqa: E731
    problem = SimpleNamespace(to_grid=grid, n_params=27)
    truth = SimpleNamespace(w=flat, v=np.linspace(1000.0, 2000.0, 27), meta={})
    est_w = 9000.0 * (1 + 0.1 * np.sin(np.arange(27)))
    ev = evaluate(problem, truth, est_w, truth.v.copy(), modes=False)["metrics"]
    assert ev["nc_w"] is None and ev["false_contrast_w"] == pytest.approx(false_contrast(est_w))
    assert ev["nc_v"] == pytest.approx(1.0) and ev["false_contrast_v"] is None


def test_stated_uncertainty_is_saved_with_the_estimate_and_scored_by_coverage(tmp_path):
    from types import SimpleNamespace

    from vvtbench.bench.stages import write_evaluation
    from vvtbench.solving.problem import Estimate

    rng = np.random.default_rng(1)
    grid = lambda x: np.asarray(x, dtype=float).reshape(3, 3, 3)  # noqa: E731
    problem = SimpleNamespace(to_grid=grid, n_params=27, n_modes=0,
                              voxel_map=SimpleNamespace(active=np.ones((3, 3, 3), bool)))
    truth = SimpleNamespace(w=np.linspace(1e4, 2e4, 27), v=np.linspace(1e3, 2e3, 27), meta={})
    w = truth.w + rng.normal(0, 500.0, 27)
    w_std = np.where(np.arange(27) < 9, 1e-3, 1e6)  # a third overconfident, the rest not
    est = Estimate(w=w, v=truth.v.copy(), extra={"w_std": w_std})
    for name in ("solve", "eval", "bad"):
        (tmp_path / name).mkdir()
    est.save(tmp_path / "solve", problem)
    with np.load(tmp_path / "solve" / "estimate.npz") as z:
        assert np.array_equal(z["w_std_params"], w_std) and "v_std_params" not in z.files
        assert z["w_std"].shape == (3, 3, 3)
    ev = write_evaluation(tmp_path / "eval", problem, truth, est.w, est.v, modes=False,
                          w_std=w_std)["metrics"]
    assert ev["interval_coverage_w"] == pytest.approx(18 / 27)
    assert ev["interval_coverage_v"] is None
    with np.load(tmp_path / "eval" / "fields.npz") as z:
        assert np.array_equal(z["w_std"].ravel(), w_std)
    with pytest.raises(ValueError, match="w_std"):
        Estimate(w=w, v=w, extra={"w_std": w_std[:3]}).save(tmp_path / "bad", problem)
    from vvtbench.reporting.plots import plot_uncertainty

    png = plot_uncertainty(tmp_path / "u.png", problem, (est.w, est.v), (w_std, None), truth)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(ValueError, match="no standard deviation"):
        plot_uncertainty(tmp_path / "none.png", problem, (est.w, est.v), (None, None))


@pytest.mark.parametrize("std,why", [
    (np.array([0.1, -0.2, 0.1]), "w_std is negative in 1 of 3 voxels"),
    (np.array([0.1, np.nan, 0.1]), "w_std is not finite in 1 of 3 voxels"),
    (np.array([0.1, 0.1]), "w_std has shape (2,), the problem has 3 parameters"),
])
def test_a_stated_uncertainty_that_is_not_one_makes_the_estimate_invalid(std, why):
    """A negative or NaN standard deviation would count as covering the truth; it is refused
    like a negative stiffness, on every path (run, solve, check-results, score)."""
    from vvtbench.scoring.metrics import invalid_reason

    assert invalid_reason(np.ones(3), np.ones(3), 3) is None
    assert invalid_reason(np.ones(3), np.ones(3), 3, w_std=np.full(3, 0.1)) is None
    assert invalid_reason(np.ones(3), np.ones(3), 3, w_std=std) == why
