"""Uncertainty of identified modes (vvtbench.modes.uncertainty) against Monte-Carlo draws."""

import json

import numpy as np
import pytest

from vvtbench.modes import modes_from_displacements
from vvtbench.modes.lines import bin_gram, clean_lines, fit_group
from vvtbench.modes.modeset import ModeSet
from vvtbench.modes.uncertainty import damping_interval, line_uncertainty

SEED = 20261127


def _hann(T):
    t = np.arange(T)
    return 0.5 - 0.5 * np.cos(2 * np.pi * t / T)


def _record(T, P, lines, noise, rng, envelope=None):
    """``(T, P)`` sum of damped cosines ``a s_p cos(2 pi kappa t / T + phi) exp(-2 pi h t / T)``
    plus white noise; ``envelope`` replaces the exponential of the last line."""
    t = np.arange(T)
    x = noise * rng.normal(size=(T, P))
    for j, (kappa, h, amp, shape) in enumerate(lines):
        env = np.exp(-2 * np.pi * h * t / T)
        if envelope is not None and j == len(lines) - 1:
            env = envelope(t)
        x += np.outer(amp * env * np.cos(2 * np.pi * kappa * t / T + 0.7 * j), shape)
    return x


def test_sigma_f_and_damping_interval_match_a_monte_carlo():
    rng = np.random.default_rng(SEED)
    T, P, kappa, zeta = 256, 16, 30.3, 0.012
    h = zeta * kappa
    shape = rng.normal(size=P)
    bins = np.arange(27, 34)
    w = _hann(T)[:, None]
    k_fit, k_std, covered = [], [], 0
    draws = 200
    for _ in range(draws):
        x = _record(T, P, [(kappa, h, 1.0, shape)], 0.4, rng)
        Z = np.fft.fft(w * x, axis=0)[bins]
        f = fit_group(bin_gram(Z), bins, [kappa], T, half_width0=[h], max_half_width=8.0)
        u = line_uncertainty(Z, bins, f.kappa, f.half_width, T)
        lo, hi = damping_interval(f.kappa, f.half_width, u.half_width_std)
        k_fit.append(f.kappa[0])
        k_std.append(u.kappa_std[0])
        covered += bool(lo[0] <= zeta <= hi[0])
    ratio = np.std(k_fit) / np.mean(k_std)
    assert 1 / 1.5 < ratio < 1.5, ratio
    assert 0.80 <= covered / draws <= 0.99, covered / draws


def test_clusters_widen_the_interval_of_spatially_correlated_noise():
    """Noise shared by blocks of channels: treating channels as independent is overconfident;
    clusters of the blocks recover the Monte-Carlo spread."""
    rng = np.random.default_rng(SEED + 1)
    T, P, block = 256, 64, 8
    shape = 1.0 + 0.3 * rng.normal(size=P)
    bins = np.arange(36, 45)
    lab = np.arange(P) // block
    w = _hann(T)[:, None]
    ks, naive, clustered = [], [], []
    for _ in range(50):
        x = _record(T, P, [(40.4, 0.3, 1.0, shape)], 0.0, rng)
        x += np.repeat(0.3 * rng.normal(size=(T, P // block)), block, axis=1)
        Z = np.fft.fft(w * x, axis=0)[bins]
        f = fit_group(bin_gram(Z), bins, [40.4], T, half_width0=[0.3])
        ks.append(f.kappa[0])
        naive.append(line_uncertainty(Z, bins, f.kappa, f.half_width, T).kappa_std[0])
        clustered.append(line_uncertainty(Z, bins, f.kappa, f.half_width, T,
                                          clusters=lab).kappa_std[0])
    spread = np.std(ks)
    assert np.mean(naive) < 0.6 * spread
    assert 1 / 1.5 < spread / np.mean(clustered) < 1.5


def test_uncertainty_in_blocks_of_channels_equals_one_block(monkeypatch):
    """A field of many channels is read in blocks (bounded memory); the blocks change no
    value: the same covariance as one block over every channel, with clusters or without."""
    import vvtbench.modes.uncertainty as unc

    rng = np.random.default_rng(SEED + 3)
    T, P = 256, 3000
    shapes = rng.normal(size=(3, P))
    x = _record(T, P, [(30.3, 0.4, 1.0, shapes[0]), (33.1, 0.5, 0.7, shapes[1]),
                       (37.8, 0.3, 0.5, shapes[2])], 0.3, rng)
    bins = np.arange(25, 44)
    Z = np.fft.fft(_hann(T)[:, None] * x, axis=0)[bins]
    f = fit_group(bin_gram(Z), bins, [30.3, 33.1, 37.8], T, half_width0=[0.4, 0.5, 0.3])
    w = rng.uniform(0.2, 1.0, P)
    lab = np.arange(P) // 16
    blocks = []
    for step in (P, 960, 7):
        monkeypatch.setattr(unc, "_channel_block", lambda m, b, step=step: step)
        blocks.append([line_uncertainty(Z, bins, f.kappa, f.half_width, T, weights=w,
                                        clusters=c) for c in (None, lab)])
    for other in blocks[1:]:
        for one, many in zip(blocks[0], other, strict=True):
            for name in ("kappa_std", "half_width_std", "cov_kappa_half_width",
                         "max_correlation", "shape_mac"):
                np.testing.assert_allclose(getattr(many, name), getattr(one, name),
                                           rtol=1e-10, atol=0, err_msg=name)


def _close_pair(rng, envelope=None):
    T, P = 512, 32
    s1, s2 = rng.normal(size=P), rng.normal(size=P)
    lines = [(60.0, 0.004 * 60.0, 1.0, s1), (62.6, 0.004 * 62.6, 0.6, s2)]
    x = _record(T, P, lines, 0.02, rng, envelope)
    Z = np.fft.rfft(_hann(T)[:, None] * x, axis=0)
    power = np.sum(np.abs(Z) ** 2, axis=1)
    return clean_lines(Z[40:85], 40, power, [60.0, 62.6], T, band=(45, 80), max_lines=2)


def test_a_close_pair_that_misfits_is_flagged_and_a_clean_one_is_not():
    from vvtbench.modes.uncertainty import mode_uncertainty

    rng = np.random.default_rng(SEED + 2)
    clean = mode_uncertainty(_close_pair(rng), 100.0, 512)
    assert not any(clean["close_mode_bias"])
    # the weaker mode beats (two unresolved components): not one exponential line
    beating = mode_uncertainty(
        _close_pair(rng, envelope=lambda t: 1.0 + 0.8 * np.cos(2 * np.pi * 0.9 * t / 512)),
        100.0, 512)
    assert any(beating["close_mode_bias"])


def test_extraction_writes_and_reloads_the_uncertainty(tmp_path):
    rng = np.random.default_rng(SEED + 3)
    T, H, W, fps = 256, 12, 12, 100.0
    t = np.arange(T) / fps
    yy, xx = np.mgrid[0:H, 0:W]
    shape = np.stack([np.sin(np.pi * xx / W), np.cos(np.pi * yy / H)], -1)
    f0, zeta = 23.4, 0.01
    sig = np.exp(-2 * np.pi * f0 * zeta * t) * np.cos(2 * np.pi * f0 * t)
    disp = (0.05 * sig[:, None, None, None] * shape[None]
            + 2e-3 * rng.normal(size=(T, H, W, 2))).astype(np.float32)
    ms = modes_from_displacements(disp, fps, fmax=45, line_fit=True)
    i = int(np.argmin(np.abs(ms.frequencies_hz - f0)))
    lo, hi = ms.damping_interval()
    assert lo[i] < zeta < hi[i]
    assert 0 < ms.frequency_std_hz()[i] < 0.05
    ms.save(tmp_path)
    doc = json.loads((tmp_path / "modes.json").read_text())
    row = doc["modes"][i]
    assert {"frequency_std_hz", "damping_lo", "damping_hi", "shape_mac_expected",
            "close_mode_bias"} <= set(row)
    assert 0.9 < row["shape_mac_expected"] <= 1.0
    back = ModeSet.load(tmp_path)
    np.testing.assert_allclose(back.damping_interval()[0], lo)
    # a set without the fields (older files, no line fit) still loads and reports nan
    for name in ("frequency_std_hz", "damping_lo", "damping_hi", "close_mode_bias"):
        doc["metadata"].pop(name)
    (tmp_path / "modes.json").write_text(json.dumps(doc))
    old = ModeSet.load(tmp_path)
    assert np.isnan(old.damping_interval()[0]).all()
    assert not old.close_mode_bias().any()


@pytest.mark.parametrize("lo_hi, ok", [((0.004, 0.007), True), ((0.002, 0.007), False),
                                       ((-0.001, 0.01), False)])
def test_damping_resolved_needs_an_interval_within_a_factor_two(lo_hi, ok):
    z = np.zeros((1, 2, 2, 2), np.float32)
    one = np.ones(1)
    f = np.arange(129.0)
    ms = ModeSet(one * 40.0, one * 0.005, one * 0.005, z, one, np.array([40]), one, one,
                 0 * one, np.zeros(1, bool), f, np.ones(129), 256.0, 256,
                 metadata={"analysed_index": [0], "damping_lo": [lo_hi[0]],
                           "damping_hi": [lo_hi[1]]})
    assert bool(ms.damping_resolved()[0]) is ok


def test_stability_search_finds_a_mode_at_every_record_length(tmp_path):
    from vvtbench.modes.plots import plot_modes
    from vvtbench.modes.stability import record_stability

    rng = np.random.default_rng(SEED + 4)
    T, H, W, fps = 512, 8, 8, 100.0
    t = np.arange(T) / fps
    yy, xx = np.mgrid[0:H, 0:W]
    shape = np.stack([np.sin(np.pi * xx / W), np.cos(np.pi * yy / H)], -1)
    sig = np.exp(-2 * np.pi * 23.4 * 0.005 * t) * np.cos(2 * np.pi * 23.4 * t)
    disp = (0.05 * sig[:, None, None, None] * shape[None]
            + 2e-3 * rng.normal(size=(T, H, W, 2))).astype(np.float32)
    st = record_stability(disp, fps, fmax=45)
    assert st["n_frames"] == [128, 256, 384, 512]
    for n, peaks in zip(st["n_frames"], st["peaks_hz"], strict=True):
        assert np.min(np.abs(np.asarray(peaks) - 23.4)) <= fps / n
    with pytest.raises(ValueError, match="fractions"):
        record_stability(disp, fps, fractions=(0.0, 1.0))
    ms = modes_from_displacements(disp, fps, fmax=45, line_fit=True)
    ms.metadata["stability"] = st
    names = {p.name for p in plot_modes(ms, tmp_path)}
    assert {"spectrum.png", "uncertainty.png", "stability.png"} <= names
