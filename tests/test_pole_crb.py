"""The Cramér-Rao bound of a mode's frequency and damping (:mod:`vvtbench.render.pole_crb`)
against Kay's closed form and a Monte Carlo maximum-likelihood estimator, and the extraction
efficiency built on it (:func:`vvtbench.scoring.extraction.parameter_efficiency`)."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import least_squares

sys.path.insert(0, str(Path(__file__).parent))

from test_extraction_recall import _FakeSample, _ms, _truth  # noqa: E402

from vvtbench.render.pole_crb import FREE_DECAY_RESIDUAL, free_decay_bound  # noqa: E402
from vvtbench.scoring.extraction import (  # noqa: E402
    parameter_efficiency,
    score_sample_extraction,
)


def _decay(f, zeta, t, c=0.8 + 0.3j):
    lam = 2 * np.pi * f * complex(-zeta, math.sqrt(1 - zeta**2))
    return (c * np.exp(lam * t)).real


def test_an_undamped_line_meets_kays_bound() -> None:
    """Kay, Fundamentals of Statistical Signal Processing I, Example 3.14: a real sinusoid of
    amplitude A in white noise of variance s^2, N samples: var(f) >= 12 / ((2 pi)^2 eta N (N^2 - 1))
    (cycles per sample), eta = A^2 / (2 s^2).  The bound here also leaves the damping free, which
    at zeta = 0 is nearly orthogonal to the frequency."""
    n, fs, f, a, s = 1000, 1000.0, 37.3, 1.0, 0.5
    t = np.arange(n) / fs
    q = a * np.cos(2 * np.pi * f * t + 0.3)
    b = free_decay_bound(t, q, math.sqrt(q @ q) / s, f, 0.0)
    eta = a * a / (2 * s * s)
    kay = math.sqrt(12 / ((2 * np.pi) ** 2 * eta * n * (n * n - 1))) * fs
    assert b["frequency_std_hz"] == pytest.approx(kay, rel=0.01)
    assert b["fit_residual"] < 1e-9


def test_maximum_likelihood_reaches_the_bound_on_a_damped_mode() -> None:
    """Nonlinear least squares (the ML estimate in white Gaussian noise) of (f, zeta, C) on 200
    noisy records: its spread matches the bound (the estimate of a standard deviation from 200
    draws is within 5 % at 1 sigma; the tolerance is 3 sigma)."""
    f, zeta, n, fs, s = 21.0, 0.03, 1000, 1000.0, 0.05
    t = np.arange(n) / fs
    q = _decay(f, zeta, t)
    b = free_decay_bound(t, q, math.sqrt(q @ q) / s, f, zeta)
    rng = np.random.default_rng(7)

    def model(p):
        return _decay(p[0], p[1], t, complex(p[2], p[3]))

    est = []
    for _ in range(200):
        y = q + s * rng.standard_normal(n)
        r = least_squares(lambda p, y=y: model(p) - y, [f, zeta, 0.8, 0.3],
                          x_scale=[0.01, 0.001, 0.1, 0.1])
        est.append(r.x[:2])
    est = np.asarray(est)
    ratio = est.std(axis=0) / [b["frequency_std_hz"], b["damping_std"]]
    assert np.all(np.abs(ratio - 1) < 0.15), ratio
    assert np.all(np.abs(est.mean(axis=0) - [f, zeta])
                  < 3 * np.array([b["frequency_std_hz"], b["damping_std"]]) / math.sqrt(200))


def test_the_bound_scales_with_the_snr_and_needs_a_free_vibration() -> None:
    t = np.arange(2000) / 2000.0
    q = _decay(12.0, 0.02, t)
    lo, hi = (free_decay_bound(t, q, snr, 12.0, 0.02) for snr in (10.0, 100.0))
    assert lo["frequency_std_hz"] == pytest.approx(10 * hi["frequency_std_hz"], rel=1e-9)
    assert lo["damping_std"] == pytest.approx(10 * hi["damping_std"], rel=1e-9)
    # the coordinate of a swept, forced response is no free vibration: stated by its misfit
    sweep = np.sin(2 * np.pi * (5.0 * t + 10.0 * t * t))
    assert free_decay_bound(t, sweep, 100.0, 12.0, 0.02)["fit_residual"] > FREE_DECAY_RESIDUAL
    assert math.isnan(free_decay_bound(t, 0 * q, 100.0, 12.0, 0.02)["frequency_std_hz"])
    with pytest.raises(ValueError, match="damping_ratio"):
        free_decay_bound(t, q, 10.0, 12.0, 1.0)


def test_efficiency_of_a_sample_extraction_is_bound_over_squared_error() -> None:
    from vvtbench.render.crb import detection_snr_threshold

    s = _FakeSample(a=(1e-3, 1e-3), zeta=(0.0, 0.05))
    s.info["video"]["frames"] = s.T
    th = detection_snr_threshold(s.T)
    s.data["modes/crb_snr"] = np.array([20 * th, 20 * th])
    truth = _truth()
    df, dz = 0.01, 0.004
    ms = _ms([5.0 + df, 12.0 - df], truth[:2])
    ms.damping[:] = [0.0, 0.05 + dz]
    r = score_sample_extraction(s, ms, fmax=None)
    t = np.arange(s.T) / s.fps
    b = [free_decay_bound(t, _decay(fi, zi, t, 1.0), 20 * th, fi, zi)
         for fi, zi in zip(s.f, s.zeta, strict=True)]
    nse = [df**2 / bi["frequency_std_hz"] ** 2 for bi in b]
    assert r["n_frequency_efficiency"] == 2
    assert r["frequency_efficiency"] == pytest.approx(1 / np.mean(nse), rel=1e-3)
    # damping: only the mode whose true damping is above 0
    assert r["n_damping_efficiency"] == 1
    assert r["damping_efficiency"] == pytest.approx(b[1]["damping_std"] ** 2 / dz**2, rel=1e-3)
    assert r["efficiency_note"] == ""
    # several views pooled, or no ruler: no number, a reason
    pooled = score_sample_extraction(s, [ms, ms], fmax=None)
    assert math.isnan(pooled["frequency_efficiency"]) and "views" in pooled["efficiency_note"]
    del s.data["modes/crb_snr"]
    bare = score_sample_extraction(s, ms, fmax=None)
    assert math.isnan(bare["damping_efficiency"]) and "ruler" in bare["efficiency_note"]


def test_efficiency_leaves_out_forced_responses_and_undetectable_modes() -> None:
    t = np.arange(2000) / 1000.0
    sweep = np.sin(2 * np.pi * (5.0 * t + 10.0 * t * t))
    q = np.stack([sweep, np.cos(2 * np.pi * 30.0 * t)], axis=1)
    m = [{"kind": "mode", "nearest_true": 0, "frequency_hz": 10.1, "damping": 0.01},
         {"kind": "mode", "nearest_true": 1, "frequency_hz": 30.01, "damping": 0.0}]
    out = parameter_efficiency(m, [10.0, 30.0], [0.01, 0.0], t, q, [50.0, 5.0], 10.0)
    assert out["n_frequency_efficiency"] == 0 and math.isnan(out["frequency_efficiency"])
    assert "forced" in out["efficiency_note"]
    assert "frequency_crb_hz" not in m[0] and "frequency_crb_hz" not in m[1]
