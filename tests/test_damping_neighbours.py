"""Damping of a peak with its neighbouring lines modelled (vvtbench.modes.damping).

Sums of damped lines at the damped paper cube's spacing (zeta 0.02, 3 s at 2000 FPS, 4-10
bins apart): the truth is the decay rate the records are made with, and each spectrum is
computed by numpy's FFT of the sampled decays, not by the fitted model.
"""

import numpy as np
import pytest
from scipy.stats import binom

from vvtbench.modes.damping import damping_lorentzian, modelled_neighbours
from vvtbench.modes.jackknife import jackknife_uncertainty

SEED = 20261129
T, FPS = 6000, 2000.0
DF = FPS / T


def _taper(window):
    n = np.arange(T)
    return 0.5 - 0.5 * np.cos(2 * np.pi * n / T) if window == "hann" else np.ones(T)


def _line(f0, zeta, amp, phase):
    t = np.arange(T) / FPS
    return amp * np.exp(-2 * np.pi * f0 * zeta * t) * np.cos(
        2 * np.pi * f0 * np.sqrt(1 - zeta**2) * t + phase)


def _power(x, window):
    """Power of each column's windowed, mean-removed record, summed over columns."""
    x = x - x.mean(axis=0)
    X = np.fft.rfft(_taper(window)[:, None] * x, axis=0)
    return np.sum(X.real**2 + X.imag**2, axis=1)


def _peak_bins(power, freqs_hz):
    out = []
    for f in freqs_hz:
        c = int(round(f / DF))
        out.append(c - 2 + int(np.argmax(power[c - 2:c + 3])))
    return out


# (frequencies in Hz, amplitudes): 2-4 lines 4-10 bins apart (one bin is 1/3 Hz); the first
# three are the paper cube's 5.65/7.8, 23.3/25.2/27.2 and 12.2/14.7 Hz groups, the last four
# lines 5-8 bins apart
SETS = [
    ([5.65, 7.8], [1.0, 0.8]),
    ([23.3, 25.2, 27.2], [1.0, 0.5, 1.2]),
    ([12.2, 14.7], [0.25, 1.0]),
    ([17.0, 19.5, 22.2, 24.0], [1.0, 0.6, 0.9, 0.5]),
]


@pytest.mark.parametrize("window", ["hann", "none"])
@pytest.mark.parametrize("freqs_hz, amps", SETS)
def test_neighbouring_lines_are_fitted_jointly(freqs_hz, amps, window):
    """Each line (its own column: the modes' fields do not interfere) within 3 % with the
    neighbours modelled; the single-line fit on the same spectrum is off by more than 10 % on
    at least one line of every set."""
    zeta = 0.02
    lines = zip(freqs_hz, amps, strict=True)
    x = np.stack([_line(f, zeta, a, 0.4 * j) for j, (f, a) in enumerate(lines)], axis=1)
    power = _power(x, window)
    freqs = np.fft.rfftfreq(T, 1 / FPS)
    bins = _peak_bins(power, freqs_hz)
    joint = [damping_lorentzian(freqs, power, k, window=window, n_frames=T,
                                neighbours=bins)[0] for k in bins]
    alone = [damping_lorentzian(freqs, power, k, window=window, n_frames=T)[0] for k in bins]
    err_joint = np.abs(np.array(joint) / zeta - 1)
    err_alone = np.abs(np.array(alone) / zeta - 1)
    assert np.all(err_joint < 0.03), err_joint
    assert np.max(err_alone) > 0.10, err_alone


@pytest.mark.parametrize("window", ["hann", "none"])
def test_an_isolated_line_is_fitted_as_before(window):
    """No neighbour within reach: the same fit as without neighbours, and exact."""
    zeta, f0 = 0.02, 31.4
    power = _power(_line(f0, zeta, 1.0, 0.3)[:, None], window)
    freqs = np.fft.rfftfreq(T, 1 / FPS)
    k = _peak_bins(power, [f0])[0]
    far = [k - 60, k + 70]
    assert modelled_neighbours(power, k, far, 8) == []
    one = damping_lorentzian(freqs, power, k, window=window, n_frames=T)
    with_far = damping_lorentzian(freqs, power, k, window=window, n_frames=T, neighbours=far)
    assert one == with_far
    assert abs(one[0] / zeta - 1) < 0.01


def test_modelled_neighbours_are_those_within_reach_nearest_first():
    power = np.ones(200)
    near = modelled_neighbours(power, 50, [50, 30, 62, 45, 71, 32, 68, 199, 0], 8)
    assert near == [45, 62, 32, 68]  # within 2 * 8 + 2 bins


def test_jackknife_intervals_with_neighbours_cover_in_noise():
    """Two lines 6 bins apart (23.3 and 25.3 Hz, zeta 0.02, the weaker one 0.4 of the other)
    seen by eight pixel groups, each with its own share of each mode (a column per mode: the
    fields do not interfere) and white noise, in seeded draws: the weaker line's 95 % zeta
    intervals cover the truth inside the binomial 99 % band of 95 %, with its neighbour
    modelled; intervals of the same width around the single-line fit do not."""
    rng = np.random.default_rng(SEED)
    zeta, G, draws = 0.02, 8, 20
    fs = [23.3, 25.3]
    shares = rng.uniform(0.5, 1.5, (2, G)) * np.array([[1.0], [0.4]])
    clean = np.stack([_line(f, zeta, 1.0, 0.5 * j) for j, f in enumerate(fs)], axis=1)
    freqs = np.fft.rfftfreq(T, 1 / FPS)
    w = _taper("hann")[:, None]
    covered, covered_alone, est = 0, 0, []
    for _ in range(draws):
        x = (clean[:, :, None] * shares[None]).reshape(T, 2 * G)
        x = x + 0.01 * rng.normal(size=x.shape)
        X = np.fft.rfft(w * (x - x.mean(axis=0)), axis=0)
        Pg = (X.real**2 + X.imag**2).reshape(-1, 2, G).sum(axis=1).T
        total = Pg.sum(axis=0)
        bins = _peak_bins(total, fs)
        ju = jackknife_uncertainty(freqs, Pg, bins, window="hann", n_frames=T)
        lo, hi = ju["damping_lo"][1], ju["damping_hi"][1]
        z = damping_lorentzian(freqs, total, bins[1], window="hann", n_frames=T,
                               neighbours=bins)[0]
        alone = damping_lorentzian(freqs, total, bins[1], window="hann", n_frames=T)[0]
        est.append(z)
        covered += lo <= zeta <= hi
        covered_alone += abs(alone - zeta) <= 0.5 * (hi - lo)
    band = binom.ppf(0.005, draws, 0.95), binom.isf(0.005, draws, 0.95)
    assert band[0] <= covered <= band[1], covered
    assert abs(np.mean(est) / zeta - 1) < 0.03, np.mean(est)
    assert covered_alone < band[0], covered_alone


def _pair(rng, overlap=0.0):
    """Peak-picked modes of damped modes at 5.65 and 7.8 Hz (zeta 0.02, 3 s at 2000 FPS,
    6.5 bins apart) in pixel noise; the second shape is orthogonal to the first plus
    ``overlap`` times it."""
    from vvtbench.modes import modes_from_displacements

    t = np.arange(T) / FPS
    yy, xx = np.mgrid[0:16, 0:16] + 0.5
    sa = np.stack([np.sin(np.pi * xx / 16), np.cos(np.pi * yy / 16)], -1)
    sb = np.stack([np.cos(2 * np.pi * yy / 16), np.sin(2 * np.pi * xx / 16)], -1) + overlap * sa

    def mode(f, shape):
        sig = np.exp(-2 * np.pi * f * 0.02 * t) * np.cos(2 * np.pi * f * t)
        return 0.05 * sig[:, None, None, None] * shape[None]

    noise = 1e-4 * rng.normal(size=(T, 16, 16, 2))
    return modes_from_displacements((mode(5.65, sa) + mode(7.8, sb) + noise).astype(np.float32),
                                    FPS, fmax=20)


def test_extraction_measures_a_mode_beside_its_neighbour_and_does_not_flag_it():
    """Orthogonal shapes: the peak picker's 7.8 Hz damping is within 3 %, as alone,
    unflagged, and its interval covers the truth."""
    pair = _pair(np.random.default_rng(SEED + 1))
    j = int(np.argmin(np.abs(pair.frequencies_hz - 7.8)))
    assert abs(pair.damping[j] / 0.02 - 1) < 0.03, pair.damping[j]
    assert not pair.close_mode_bias()[j]
    lo, hi = pair.damping_interval()
    assert lo[j] <= 0.02 <= hi[j]
    assert pair.damping_resolved()[j]


def test_a_neighbour_whose_shape_overlaps_is_flagged():
    """Overlapping shapes put a cross term between the lines that the fit's sum of powers
    has not: the 7.8 Hz mode is flagged and not resolved."""
    pair = _pair(np.random.default_rng(SEED + 2), overlap=0.6)
    j = int(np.argmin(np.abs(pair.frequencies_hz - 7.8)))
    lo, hi = pair.damping_interval()
    assert not np.all((lo <= 0.02) & (0.02 <= hi))  # the bias the flag is for
    assert pair.close_mode_bias()[j]
    assert not pair.damping_resolved()[j]
