"""Multi-channel line fit (vvtbench.modes.lines) against exact DFTs of synthetic lines."""

import numpy as np
import pytest

from vvtbench.modes import modes_from_displacements
from vvtbench.modes.lines import bin_gram, clean_lines, fit_group, line_kernel, line_shapes
from vvtbench.modes.spectrum import bin_fields, motion_power_spectrum


def _hann(T):
    t = np.arange(T)
    return 0.5 - 0.5 * np.cos(2 * np.pi * t / T)


@pytest.mark.parametrize("window", ["hann", "none"])
def test_kernel_is_the_dft_of_a_windowed_damped_line(window):
    T = 1000
    t = np.arange(T)
    bins = np.arange(30, 60)
    for kappa, h in [(41.37, 0.0), (44.0, 0.0), (50.5, 0.8)]:
        x = np.exp((2j * np.pi * kappa - 2 * np.pi * h) * t / T)
        w = _hann(T) if window == "hann" else np.ones(T)
        X = np.fft.fft(w * x)[bins]
        K = line_kernel([kappa], [h], bins, T, window)[:, 0]
        np.testing.assert_allclose(K, X, rtol=1e-9, atol=1e-9 * np.abs(X).max())


def _signal(T, lines, P, rng, noise):
    """Real multi-channel record: sum of a cos(2 pi kappa t / T + phi) exp(-2 pi h t / T)."""
    t = np.arange(T)
    x = np.zeros((T, P))
    shapes = []
    for kappa, h, amp in lines:
        s = rng.normal(size=P)
        s /= np.linalg.norm(s)
        shapes.append(s)
        x += np.outer(amp * np.cos(2 * np.pi * kappa * t / T + rng.uniform(0, 6))
                      * np.exp(-2 * np.pi * h * t / T), s)
    return x + noise * rng.normal(size=x.shape), np.array(shapes)


def test_fit_group_separates_two_lines_a_bin_apart():
    rng = np.random.default_rng(0)
    T, P = 4000, 200
    truth = [(200.3, 0.0, 1.0), (201.5, 0.3, 0.1)]
    x, shapes = _signal(T, truth, P, rng, 1e-4)
    Z = np.fft.rfft(_hann(T)[:, None] * x, axis=0)
    bins = np.arange(195, 207)
    f = fit_group(bin_gram(Z[bins]), bins, [200.1, 201.8], T)
    np.testing.assert_allclose(f.kappa, [200.3, 201.5], atol=2e-3)
    np.testing.assert_allclose(f.half_width, [0.0, 0.3], atol=5e-3)
    A = line_shapes(Z[bins], bins, f.kappa, f.half_width, T)
    for a, s, (_, _, amp) in zip(A, shapes, truth, strict=True):
        mac = abs(np.vdot(a, s)) ** 2 / np.vdot(a, a).real
        assert mac > 0.999
        assert np.linalg.norm(a) == pytest.approx(amp / 2, rel=0.01)
    assert f.mac(0, 1) < 0.1


def test_clean_finds_the_weak_line_under_a_strong_one_with_at_most_one_false_line():
    T, P = 4000, 300
    truth = [(100.2, 0.0, 1.0), (101.6, 0.0, 0.03), (140.4, 0.0, 0.5)]
    n_false = []
    for seed in range(3):
        rng = np.random.default_rng(seed)
        x, _ = _signal(T, truth, P, rng, 3e-3)
        x = x.reshape(T, P // 2, 1, 2)
        _, S = motion_power_spectrum(x, 1.0, window="hann")
        first, last = 2, 400
        F = bin_fields(x, np.arange(first, last + 1), window="hann").reshape(last - first + 1,
                                                                              -1)
        lines = clean_lines(F, first, S, [100.2, 140.4], T, band=(5, 395))
        d = np.abs(lines.kappa[:, None] - np.array([k for k, _, _ in truth])[None, :])
        assert np.all(d.min(axis=0) < 0.02)  # every true line found, 101.6 added
        assert lines.added[np.argmin(d[:, 1])]
        n_false.append(int(np.sum(d.min(axis=1) >= 0.02)))
        # in the strong line's own peak the weak one is invisible
        assert S[101] < S[100] and S[102] < S[101]
    assert max(n_false) <= 1, n_false


_FPS, _T = 512.0, 2048
_F1, _F2 = 40.0 + 0.3 * _FPS / _T, 40.0 + 1.6 * _FPS / _T  # 1.3 bins apart


def _shapes(H=24, W=24):
    yy, xx = np.mgrid[0:H, 0:W] / H
    return (np.stack([np.sin(np.pi * xx), np.zeros_like(xx)], -1),
            np.stack([np.zeros_like(yy), np.cos(np.pi * yy)], -1))


def _two_close_lines(s1, s2, rng):
    """A strong line of shape ``s1`` and one 5x weaker 1.3 bins above it, shape ``s2``."""
    t = np.arange(_T) / _FPS
    disp = (0.05 * np.cos(2 * np.pi * _F1 * t)[:, None, None, None] * s1
            + 0.01 * np.cos(2 * np.pi * _F2 * t + 1.0)[:, None, None, None] * s2)
    return (disp + 1e-4 * rng.normal(size=disp.shape)).astype(np.float32)


@pytest.mark.parametrize("h", [2.0, 6.0])
def test_a_line_wider_than_its_group_keeps_its_damping(h):
    """A heavily damped line (half width up to 2 x the fit radius) is fitted exactly: the
    width bound must not be what the fit returns (a 3-bin bound read zeta 0.025 for 0.05)."""
    rng = np.random.default_rng(4)
    T, P = 3000, 64
    x, _ = _signal(T, [(120.0, h, 1.0)], P, rng, 1e-5)
    Z = np.fft.rfft(_hann(T)[:, None] * x, axis=0)
    power = np.sum(np.abs(Z) ** 2, axis=1)
    lines = clean_lines(Z[60:181], 60, power, [120.0], T, band=(70, 170))
    i = int(np.argmin(np.abs(lines.kappa - 120.0)))
    assert lines.half_width[i] == pytest.approx(h, rel=5e-3)
    assert lines.kappa[i] == pytest.approx(120.0, abs=0.01)


def test_line_fit_mode_extraction_resolves_close_modes():
    s1, s2 = _shapes()
    disp = _two_close_lines(s1, s2, np.random.default_rng(2))
    plain = modes_from_displacements(disp, _FPS, fmax=100)
    fitted = modes_from_displacements(disp, _FPS, fmax=100, line_fit=True)
    assert len(plain) == 1
    assert len(fitted) == 2
    np.testing.assert_allclose(np.sort(fitted.frequencies_hz), [_F1, _F2], rtol=1e-4)
    np.testing.assert_allclose(fitted.damping, 0.0, atol=1e-3)
    order = np.argsort(fitted.frequencies_hz)
    np.testing.assert_allclose(fitted.amplitudes_px[order] / [np.linalg.norm(s1) * 0.05,
                                                             np.linalg.norm(s2) * 0.01],
                               1.0, rtol=0.02)


def test_added_roughness_rejects_only_rough_lines_the_residual_search_added():
    from vvtbench.modes.peaks import roughness

    rng = np.random.default_rng(5)
    s1, smooth = _shapes()
    rough = smooth + 0.35 * rng.choice([-1.0, 1.0], size=smooth.shape)
    assert roughness(smooth) < 0.02 and 0.1 < roughness(rough) < 0.3
    found = {}
    for name, s2 in (("smooth", smooth), ("rough", rough)):
        disp = _two_close_lines(s1, s2, rng)
        for ar in (None, 0.1):
            ms = modes_from_displacements(disp, _FPS, fmax=100, line_fit=True, added_roughness=ar)
            found[name, ar] = (len(ms), [r["reason"] for r in ms.metadata["rejected"]])
    assert found["smooth", None][0] == found["smooth", 0.1][0] == 2
    assert found["rough", None][0] == 2
    assert found["rough", 0.1] == (1, ["weak_incoherent"])


@pytest.mark.parametrize("bad", [{"line_radius": 0}, {"line_radius": 2.5},
                                 {"added_roughness": float("nan")}, {"added_roughness": -0.1}])
def test_line_fit_options_are_checked(bad):
    s1, s2 = _shapes(8, 8)
    disp = _two_close_lines(s1, s2, np.random.default_rng(0))[:256]
    with pytest.raises(ValueError, match=next(iter(bad))):
        modes_from_displacements(disp, _FPS, fmax=100, line_fit=True, **bad)
