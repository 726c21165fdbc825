"""Uncertainty of peak-picked modes (the pixel-block jackknife of vvtbench.modes.jackknife)
against Monte-Carlo draws of damped sinusoids in noise."""

import json

import numpy as np
import pytest
from scipy.stats import binom

from vvtbench.modes import modes_from_displacements
from vvtbench.modes.damping import damping_lorentzian
from vvtbench.modes.jackknife import (
    METHOD,
    group_labels,
    group_spectra,
    jackknife_uncertainty,
    refine_bias_bins,
)
from vvtbench.modes.modeset import ModeSet
from vvtbench.modes.peaks import refine_frequency
from vvtbench.modes.spectrum import motion_power_spectrum

SEED = 20261128


def _hann(T):
    return 0.5 - 0.5 * np.cos(2 * np.pi * np.arange(T) / T)


def _binomial_range(n, p=0.95, tail=0.005):
    """Counts of ``n`` Bernoulli(p) draws outside which a count has probability ``2 tail``."""
    return binom.ppf(tail, n, p), binom.isf(tail, n, p)


def test_jackknife_std_and_intervals_match_a_monte_carlo():
    """Eight pixel groups, each with its own amplitude of one damped line and white noise:
    the jackknife's sigma_f (with the parabola's bias) and sigma_zeta against the spread of
    the estimates over draws, and the coverage of the truth by the 95 % intervals."""
    rng = np.random.default_rng(SEED)
    T, fps, G, f0, zeta = 256, 100.0, 8, 23.47, 0.012
    df = fps / T
    t = np.arange(T) / fps
    amps = rng.uniform(0.5, 1.5, G)
    line = np.exp(-2 * np.pi * f0 * zeta * t) * np.cos(2 * np.pi * f0 * np.sqrt(1 - zeta**2) * t)
    f_true = f0 * np.sqrt(1 - zeta**2)
    freqs = np.fft.rfftfreq(T, 1 / fps)
    est, cover_f, cover_z = [], 0, 0
    draws = 40
    for _ in range(draws):
        x = line[:, None] * amps[None, :] + 0.15 * rng.normal(size=(T, G))
        Pg = (np.abs(np.fft.rfft(_hann(T)[:, None] * (x - x.mean(0)), axis=0)) ** 2).T
        total = Pg.sum(axis=0)
        k = int(np.argmax(total[3:])) + 3
        f = refine_frequency(freqs, total, k)
        z = damping_lorentzian(freqs, total, k, window="hann", n_frames=T)[0]
        ju = jackknife_uncertainty(freqs, Pg, [k], window="hann", n_frames=T, damping=[z])
        q = ju["t95"][0]
        est.append((f, z, ju["frequency_std_hz"][0], ju["damping_std"][0]))
        cover_f += abs(f - f_true) <= q * ju["frequency_std_hz"][0]
        cover_z += ju["damping_lo"][0] <= zeta <= ju["damping_hi"][0]
    e = np.array(est)
    assert np.all(np.isfinite(e))
    rmse_f = np.sqrt(np.mean((e[:, 0] - f_true) ** 2))
    assert 1 / 1.5 < rmse_f / np.mean(e[:, 2]) < 1.5, rmse_f / np.mean(e[:, 2])
    assert rmse_f < 0.1 * df
    assert 1 / 1.5 < np.std(e[:, 1]) / np.mean(e[:, 3]) < 1.5, np.std(e[:, 1]) / e[:, 3].mean()
    lo, hi = _binomial_range(draws)
    assert lo <= cover_f <= hi, cover_f
    assert lo <= cover_z <= hi, cover_z


def test_refine_bias_is_the_parabola_error_on_a_noiseless_line():
    T, fps = 512, 100.0
    t = np.arange(T) / fps
    for f0, zeta in ((23.4, 0.01), (31.13, 0.002)):
        x = np.exp(-2 * np.pi * f0 * zeta * t) * np.cos(2 * np.pi * f0 * t)
        freqs, p = motion_power_spectrum(x[:, None, None, None] * np.ones((1, 1, 1, 2)), fps,
                                         window="hann")
        k = int(np.argmax(p))
        df = fps / T
        nu = refine_frequency(freqs, p, k) / df
        fd = f0 / df  # the damped frequency of this record
        bias = refine_bias_bins(p, k, nu, zeta * f0 / df, 0.0, T)
        assert abs(nu - fd) > 2e-3  # there is a bias to find
        assert abs((nu - bias) - fd) < 0.2 * abs(nu - fd)


def test_groups_keep_pixel_tiles_together_and_span_the_image():
    labels, G, block = group_labels((64, 48, 2), 16)
    assert (G, block) == (16, 8)
    lab = labels.reshape(64, 48, 2)
    assert np.all(lab[..., 0] == lab[..., 1])
    assert np.all(lab[:8, :8, 0] == lab[0, 0, 0])
    for g in range(G):
        rows = np.flatnonzero((lab[..., 0] == g).any(axis=1))
        assert rows.max() - rows.min() > 32
    labels, G, block = group_labels((12, 12, 2), 16)
    assert G == 16 and block == 2 and labels.max() == 15
    disp = np.random.default_rng(SEED).normal(size=(64, 12, 12, 2))
    Pg, Ps = group_spectra(disp, labels, G, window="hann")
    _, p = motion_power_spectrum(disp, 1.0, window="hann")
    np.testing.assert_allclose(Pg.sum(axis=0), p, rtol=1e-10)
    np.testing.assert_allclose(Ps, p, rtol=1e-10)


def _damped_field(rng, T=512, H=16, W=16, fps=100.0, f0=23.4, zeta=0.01, noise=4e-3):
    t = np.arange(T) / fps
    yy, xx = np.mgrid[0:H, 0:W]
    shape = np.stack([np.sin(np.pi * (xx + 0.5) / W), np.cos(np.pi * (yy + 0.5) / H)], -1)
    sig = np.exp(-2 * np.pi * f0 * zeta * t) * np.cos(2 * np.pi * f0 * t)
    return (0.05 * sig[:, None, None, None] * shape[None]
            + noise * rng.normal(size=(T, H, W, 2))).astype(np.float32)


def test_peak_picked_modes_carry_the_uncertainty_fields(tmp_path):
    rng = np.random.default_rng(SEED + 1)
    fps, f0, zeta = 100.0, 23.4, 0.01
    ms = modes_from_displacements(_damped_field(rng), fps, fmax=45)
    assert ms.metadata["uncertainty_method"] == METHOD
    assert ms.metadata["uncertainty_groups"]["groups"] == 16
    i = int(np.argmin(np.abs(ms.frequencies_hz - f0)))
    lo, hi = ms.damping_interval()
    assert lo[i] < zeta < hi[i] and hi[i] < 2 * lo[i]
    assert ms.damping_resolved()[i]
    sf = ms.frequency_std_hz()[i]
    assert 0 < sf < 0.05 and abs(ms.frequencies_hz[i] - f0) < 3 * sf
    ms.save(tmp_path)
    row = json.loads((tmp_path / "modes.json").read_text())["modes"][i]
    assert 0.9 < row["shape_mac_expected"] <= 1.0
    assert row["close_mode_bias"] is False and 0.5 < row["line_misfit"] < 2.0
    back = ModeSet.load(tmp_path)
    np.testing.assert_allclose(back.damping_interval()[1], hi)
    assert back.metadata["uncertainty_method"] == METHOD


def test_a_noise_peak_next_to_a_mode_is_not_resolved():
    """Two lines 2 bins apart under one peak picker: both flagged close, neither resolved."""
    rng = np.random.default_rng(SEED + 2)
    fps, T = 100.0, 512
    a = _damped_field(rng, T=T, f0=23.4, zeta=0.003)
    b = _damped_field(rng, T=T, f0=23.4 + 2.5 * fps / T, zeta=0.003, noise=0.0)
    ms = modes_from_displacements(a + 0.8 * b[:, ::-1], fps, fmax=45, prominence=0.05,
                                  shoulder_prominence=None)
    near = np.abs(ms.frequencies_hz - 23.4) < 4 * fps / T
    assert near.sum() >= 2
    assert ms.close_mode_bias()[near].all()
    assert not ms.damping_resolved()[near].any()


def test_two_modes_under_one_peak_are_flagged_by_the_blend_misfit():
    """A line of one mode gives a misfit near 1; a second mode of another shape a bin away,
    under the same peak, biases zeta and is flagged, so its damping is not resolved."""
    rng = np.random.default_rng(SEED + 4)
    T, H, W, fps = 512, 16, 16, 100.0
    t = np.arange(T) / fps
    yy, xx = np.mgrid[0:H, 0:W]
    sa = np.stack([np.sin(np.pi * (xx + 0.5) / W), np.cos(np.pi * (yy + 0.5) / H)], -1)
    sb = np.stack([np.cos(2 * np.pi * (yy + 0.5) / H), np.sin(2 * np.pi * (xx + 0.5) / W)], -1)

    def mode(f, amp, shape):
        sig = np.exp(-2 * np.pi * f * 0.01 * t) * np.cos(2 * np.pi * f * t)
        return amp * sig[:, None, None, None] * shape[None]

    noise = 1e-3 * rng.normal(size=(T, H, W, 2))
    one = modes_from_displacements((mode(23.4, 0.05, sa) + noise).astype(np.float32), fps,
                                   fmax=45)
    blend = modes_from_displacements(
        (mode(23.4, 0.05, sa) + mode(23.4 + fps / T, 0.04, sb) + noise).astype(np.float32),
        fps, fmax=45)
    assert len(one) == 1 and len(blend) == 1
    assert 0.7 < one.mode_list("line_misfit")[0] < 1.6
    assert not one.close_mode_bias()[0] and one.damping_resolved()[0]
    assert blend.damping[0] > 0.0105  # the blend's line is broader
    assert blend.mode_list("line_misfit")[0] > 3 and blend.close_mode_bias()[0]
    assert not blend.damping_resolved()[0]


def test_a_neighbour_within_the_damping_fit_flags_the_mode():
    """Damped lines at 5.65 and 7.8 Hz (zeta 0.02, 3 s at 2000 FPS): 6.5 bins apart, inside
    the bins the Lorentzian fit of each reaches, whose zeta the neighbour's flank biases;
    the 7.8 Hz line alone is measured and not flagged."""
    rng = np.random.default_rng(SEED + 5)
    T, fps = 6000, 2000.0
    t = np.arange(T) / fps
    yy, xx = np.mgrid[0:16, 0:16]
    sa = np.stack([np.sin(np.pi * (xx + 0.5) / 16), np.cos(np.pi * (yy + 0.5) / 16)], -1)
    sb = np.stack([np.cos(2 * np.pi * (yy + 0.5) / 16), np.sin(2 * np.pi * (xx + 0.5) / 16)], -1)

    def mode(f, shape):
        sig = np.exp(-2 * np.pi * f * 0.02 * t) * np.cos(2 * np.pi * f * t)
        return 0.05 * sig[:, None, None, None] * shape[None]

    noise = 1e-4 * rng.normal(size=(T, 16, 16, 2))
    alone = modes_from_displacements((mode(7.8, sb) + noise).astype(np.float32), fps, fmax=20)
    pair = modes_from_displacements((mode(5.65, sa) + mode(7.8, sb) + noise).astype(np.float32),
                                    fps, fmax=20)
    i = int(np.argmin(np.abs(alone.frequencies_hz - 7.8)))
    j = int(np.argmin(np.abs(pair.frequencies_hz - 7.8)))
    assert abs(alone.damping[i] / 0.02 - 1) < 0.05
    assert not alone.close_mode_bias()[i]
    assert abs(pair.damping[j] / 0.02 - 1) > 0.05  # the bias the flag is for
    assert pair.close_mode_bias()[j] and not pair.damping_resolved()[j]


def test_extract_prints_the_interval_of_peak_picked_modes(tmp_path, capsys):
    from scipy.ndimage import gaussian_filter, map_coordinates

    from vvtbench.cli import main

    rng = np.random.default_rng(SEED + 3)
    n, T, fps, f0, zeta = 32, 256, 100.0, 17.3, 0.02
    tex = gaussian_filter(rng.standard_normal((3 * n, 3 * n)), 1.5)
    tex = (tex - tex.min()) / (tex.max() - tex.min())
    y, x = np.mgrid[0:n, 0:n].astype(float)
    shape = np.stack([np.cos(2 * np.pi * x / n), 0.5 * np.sin(2 * np.pi * y / n)])
    frames = np.empty((T, n, n), np.uint8)
    for k in range(T):
        t = k / fps
        d = 0.4 * shape * np.exp(-2 * np.pi * f0 * zeta * t) * np.cos(2 * np.pi * f0 * t)
        img = map_coordinates(tex, [y + n - d[1], x + n - d[0]], order=3, mode="wrap")
        frames[k] = np.clip(np.round(img * 220 + 18 + rng.normal(0, 1.0, img.shape)), 0, 255)
    np.save(tmp_path / "clip.npy", frames)
    out = tmp_path / "m"
    assert main(["extract", str(tmp_path / "clip.npy"), "--fps", str(fps), "-o", str(out),
                 "--no-plots", "--quiet", "--fmax", "45"]) == 0
    printed = capsys.readouterr().out
    ms = ModeSet.load(out)
    i = int(np.argmin(np.abs(ms.frequencies_hz - f0)))
    assert abs(ms.frequencies_hz[i] - f0) < 0.2
    line = next(s for s in printed.splitlines() if s.strip().startswith(f"#{i:2d}".strip()))
    assert " +- " in line and "[" in line, line
    lo, hi = ms.damping_interval()
    assert np.isfinite(lo[i]) and np.isfinite(hi[i])


@pytest.mark.parametrize("n_groups", [1, 0])
def test_group_count_below_two_is_refused(n_groups):
    with pytest.raises(ValueError, match="n_groups"):
        group_labels((16, 16, 2), n_groups)


@pytest.mark.parametrize("T", [2, 3, 10, 11, 64])
def test_the_hann_transform_derived_from_the_plain_one_is_numpys(T):
    from vvtbench.modes.spectrum import hann_from_unwindowed, window_weights

    x = np.random.default_rng(T).standard_normal((T, 3))
    np.testing.assert_allclose(hann_from_unwindowed(np.fft.rfft(x, axis=0), T),
                               np.fft.rfft(x * window_weights(T, "hann")[:, None], axis=0),
                               atol=1e-12)


def test_group_spectra_without_window_come_from_the_same_pass():
    rng = np.random.default_rng(SEED + 6)
    disp = rng.normal(size=(96, 16, 16, 2)).astype(np.float32)
    labels, G, _ = group_labels(disp.shape[1:], 8)
    Pg, Ps, Pu = group_spectra(disp, labels, G, window="hann", unwindowed=True)
    np.testing.assert_allclose(Pg, group_spectra(disp, labels, G, window="hann")[0],
                               rtol=1e-10)
    _, plain = motion_power_spectrum(disp, 1.0, window="none")
    np.testing.assert_allclose(Pu.sum(axis=0), plain, rtol=1e-10)


def _swept_field(rng, fps, T, modes, swept, H=12, W=12, noise=1e-4):
    """Modes ``(f0, zeta)`` driven by a linear sweep 20-400 Hz over the record (``swept``)
    or plucked at its first frame, each with its own smooth shape."""
    from scipy.signal import chirp, lsim

    t = np.arange(int(fps * T)) / fps
    yy, xx = np.mgrid[0:H, 0:W] / H
    out = noise * rng.normal(size=(t.size, H, W, 2))
    for j, (f0, zeta) in enumerate(modes):
        w = 2 * np.pi * f0
        if swept:
            _, q, _ = lsim(([1.0], [1.0, 2 * zeta * w, w * w]), chirp(t, 20, T, 400), t)
        else:
            q = np.exp(-zeta * w * t) * np.cos(w * np.sqrt(1 - zeta**2) * t)
        shape = np.stack([np.cos(np.pi * (j + 1) * xx / 2), np.sin(np.pi * (j + 2) * yy / 2)],
                         -1)
        out += 0.05 * (q / np.abs(q).max())[:, None, None, None] * shape[None]
    return out.astype(np.float32)


def test_a_mode_a_sweep_reaches_mid_record_has_an_interval_that_covers_its_damping():
    """The Hann fit models a free decay from the first frame; a mode a sweep passes through
    later decays under the window's fall and reads up to three times too damped. The interval
    spans the fit without window (near the truth): it covers the true damping or is wider than
    a factor 2 (not resolved). A plucked mode keeps its narrow resolved interval.

    The displacement at onset is the largest the mode had (every mode of the field peaks at
    0.05 px): the Hann fit's extrapolation to the first frame alone reads a swept mode 4x
    too large; the two fits' amplitude ratio brings it back, and is 1 for a pluck."""
    modes = [(60.0, 0.010), (150.0, 0.008), (260.0, 0.006)]
    for swept in (False, True):
        rng = np.random.default_rng(SEED + 7)
        ms = modes_from_displacements(_swept_field(rng, 1000.0, 2.0, modes, swept), 1000.0,
                                      fmax=400)
        lo, hi = ms.damping_interval()
        plain = ms.mode_list("damping_unwindowed")
        ratio = ms.mode_list("onset_amplitude_ratio")
        onset = ms.initial_displacement_px
        resolved = ms.damping_resolved()
        for f0, zeta in modes:
            i = int(np.argmin(np.abs(ms.frequencies_hz - f0)))
            assert abs(ms.frequencies_hz[i] - f0) < 0.1
            assert abs(plain[i] / zeta - 1) < 0.15
            if swept and f0 > 100:
                assert ms.damping[i] > 1.5 * zeta  # the Hann fit alone is far off
            assert (lo[i] <= zeta <= hi[i]) or not resolved[i]
            assert resolved[i] or swept
            if resolved[i]:
                assert abs(onset[i] / 0.05 - 1) < 0.15
            if not swept:
                assert abs(ratio[i] - 1) < 0.05
