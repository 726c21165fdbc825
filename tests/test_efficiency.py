"""Extractor efficiency: the machinery against the Cramér-Rao-achieving estimator."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from vvtbench.render import crb
from vvtbench.scoring.efficiency import (
    EfficiencySetting,
    KnownTextureShift,
    band_information,
    extractor_efficiency,
    iter_frames,
    motion_transfer,
    reference_frame,
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


# --------------------------------------------------------------------------- reference
# A speckle of contrast 0.2 moved 0.1 px in 4 directions by exact Fourier shifts, at a
# texture-to-noise ratio of 5 (its standard deviation over the read noise's): the phase
# extractor's amplitude (the slope of measured on true motion, each record's mean error
# removed) within 2 % of the truth (0.6 % low here, its standard error 0.6 %).  Before the
# temporal-mean reference and the refinement it read 14 % low; with the mean reference alone
# 2.8 % low.
NOISY = EfficiencySetting(amplitude_px=0.1, size=64, contrast=0.2, repeats=16, clips=4,
                          seed=11, remove_offset=True).at_ratio(5.0)


def test_phase_amplitude_is_unbiased_at_texture_to_noise_5():
    r = extractor_efficiency("phase", replace(NOISY, reference="mean"))
    assert r["texture_noise_ratio"] == pytest.approx(5.0, rel=1e-6)
    assert abs(r["gain"] - 1.0) < 0.02, r["gain"]
    assert r["gain_se"] < 0.01
    assert r["eta"] > 0.6


def test_a_noisy_first_frame_reference_reads_amplitudes_low():
    """The test above fails with the reference and extractor as they were."""
    old = extractor_efficiency("phase", replace(NOISY, reference="first"),
                               config={"refine": 0})
    assert old["gain"] < 0.92
    # the wrapping and outliers about zero motion (same frames: a paired difference)
    unrefined = extractor_efficiency("phase", replace(NOISY, reference="mean"),
                                     config={"refine": 0})
    refined = extractor_efficiency("phase", replace(NOISY, reference="mean"))
    assert refined["gain"] - unrefined["gain"] > 0.015


def test_reference_frames():
    st = EfficiencySetting(amplitude_px=0.2, noise=0.01, size=32, repeats=2, seed=2)
    rest = rest_image(st)
    assert np.array_equal(reference_frame(replace(st, reference="clean")), rest.astype("f4"))
    first = reference_frame(replace(st, reference="first"), clip=1)
    assert 0 < np.std(first - rest) < 2 * 0.01 * 4095
    mean = reference_frame(replace(st, reference="mean"), clip=1)
    assert np.allclose(mean, np.mean(list(iter_frames(st, clip=1)), axis=0), atol=1e-3)
    # clip 0 is the frames of a single-clip setting
    assert np.array_equal(next(iter_frames(st)), next(iter_frames(replace(st, clips=3), 0)))


def test_the_footprint_bound_is_a_bound_for_a_pooling_extractor():
    """Per 8 px block the phase extractor "beats" the block's own bound by pooling the pixels
    around it; against the bound of the area it pools (its measured motion transfer
    function) it does not."""
    st = EfficiencySetting(amplitude_px=0.1, size=64, contrast=0.2, repeats=12, block=8,
                           seed=12, reference="clean").at_ratio(5.0)
    box = extractor_efficiency("phase", st)
    fp = extractor_efficiency("phase", replace(st, bound="footprint"))
    assert box["eta"] > 2.0
    assert fp["eta"] < 0.9 and fp["pooled_px"] > 12.0
    assert fp["rmse_px"] == pytest.approx(box["rmse_px"])


def test_motion_transfer_of_the_ideal_and_of_phase():
    st = EfficiencySetting(amplitude_px=0.1, size=32, seed=3)
    t = motion_transfer("phase", st)
    assert t.shape == (17,) and t[0] == pytest.approx(1.0, abs=0.01)
    assert np.all(np.diff(t[:6]) < 0)  # pooling: finer motion is seen less


def test_footprint_crb_reduces_to_the_block_bound():
    rng = np.random.default_rng(0)
    jp = crb.pixel_fisher(1000 + 100 * rng.standard_normal((32, 48)), 4.0)
    box = crb.block_crb(jp, 8)["std_px"]
    for periodic in (False, True):
        out = crb.footprint_crb(jp, 8, 0.0, periodic=periodic)
        assert np.allclose(out["std_px"], box, rtol=1e-9) and out["pooled_px"] == 8.0
    pooled = crb.footprint_crb(jp, 8, 2.0)
    # a uniform texture: the bound of the pooled area, 11.1^2 px instead of 8^2
    assert pooled["pooled_px"] == pytest.approx(11.1, abs=0.1)
    ratio = np.mean(box**2) / np.mean(pooled["std_px"] ** 2)
    assert ratio == pytest.approx((pooled["pooled_px"] / 8) ** 2, rel=0.1)
    flat = crb.footprint_crb(jp[:, :32], 8, transfer=np.ones(17), periodic=True)
    assert np.allclose(flat["std_px"], crb.block_crb(jp[:, :32], 8)["std_px"], rtol=1e-9)
    with pytest.raises(ValueError, match="divide"):
        crb.footprint_crb(jp, 5, 1.0)
