"""Extractor efficiency: the machinery against the Cramér-Rao-achieving estimator."""

from __future__ import annotations

import numpy as np
import pytest

from vvtbench.render import crb
from vvtbench.scoring.efficiency import (
    EfficiencySetting,
    KnownTextureShift,
    band_information,
    extractor_efficiency,
    iter_frames,
    rest_image,
    true_shifts,
)


def test_frames_are_the_shifted_texture_with_the_sensor_noise():
    from scipy.ndimage import fourier_shift

    clean = EfficiencySetting(amplitude_px=0.7, noise=0.0, bit_depth=16, size=32, repeats=2,
                              directions=4, seed=3)
    rest = rest_image(clean)
    shifts = true_shifts(clean)
    assert np.allclose(np.hypot(*shifts.T), 0.7) and len(np.unique(shifts[:, 0])) == 4
    for frame, (dx, dy) in zip(iter_frames(clean), shifts, strict=True):
        moved = np.fft.ifft2(fourier_shift(np.fft.fft2(rest), (dy, dx))).real
        assert np.abs(frame - np.rint(moved)).max() <= 1.0
        assert np.abs(frame - rest).max() > 100  # it did move
    noisy = EfficiencySetting(amplitude_px=0.0, noise=0.01, bit_depth=12, size=64, repeats=4,
                              directions=2, seed=4)
    resid = np.stack(list(iter_frames(noisy))) - rest_image(noisy)[None]
    model = float(crb.noise_variance_dn2(0.5, 12, 0.01 * 4095, False, 1e4))
    assert resid.var() == pytest.approx(model, rel=0.05)


def test_known_texture_estimator_reaches_the_bound():
    """Gauss-Newton on the true texture is efficient: eta ~ 1 within Monte-Carlo error."""
    st = EfficiencySetting(amplitude_px=0.3, noise=0.02, bit_depth=12, size=32, block=8,
                           directions=2, repeats=24, seed=5)
    r = extractor_efficiency(KnownTextureShift, st, config={"block": 8})
    assert r["eta_se"] < 0.08
    assert abs(r["eta"] - 1.0) < 3 * r["eta_se"] + 0.03
    assert r["bias_px"] < 0.2 * r["crb_px"]


def test_whole_frame_estimate_from_block_estimates_is_efficient():
    """The mean of four independent efficient 16 px block estimates is efficient for the
    32 px frame (the bound adds information over blocks)."""
    st = EfficiencySetting(amplitude_px=0.05, noise=0.02, bit_depth=12, size=32, block=32,
                           directions=2, repeats=48, seed=6)
    quarters = KnownTextureShift(KnownTextureShift.Config(block=16))
    r = extractor_efficiency(quarters, st)
    assert abs(r["eta"] - 1.0) < 3 * r["eta_se"] + 0.03


def test_phase_efficiency_is_finite_and_plausible():
    st = EfficiencySetting(amplitude_px=0.003, noise=0.01, bit_depth=12, size=64,
                           directions=4, repeats=8, seed=1)
    r = extractor_efficiency("phase", st)
    assert np.isfinite(r["eta"]) and 0.0 < r["eta"] < 1.5
    assert r["rmse_px"] ** 2 == pytest.approx(r["bias2_px2"] + r["std_px"] ** 2, rel=1e-9)


def test_band_information_of_a_single_wave():
    n = 64
    y, x = np.mgrid[0:n, 0:n].astype(float)
    mid = 1000 + 100 * np.cos(2 * np.pi * 8 * x / n)  # pi / 4 rad/px: inside scale 1
    high = 1000 + 100 * np.cos(2 * np.pi * 30 * x / n)  # 2.95 rad/px: above the bands
    assert band_information(mid)["kept"] == pytest.approx(1.0, abs=1e-9)
    hi = band_information(high)
    w = 2 * np.pi * 30 / n  # scale 0 tapers as sin^2(pi / 2 * log2(pi / w)) towards pi
    assert hi["above_band"] == pytest.approx(1.0)
    assert hi["kept"] == pytest.approx(np.sin(np.pi / 2 * np.log2(np.pi / w)) ** 2, rel=1e-6)


def test_setting_rejects_a_block_that_does_not_divide():
    with pytest.raises(ValueError, match="block"):
        EfficiencySetting(amplitude_px=0.1, size=64, block=24)
