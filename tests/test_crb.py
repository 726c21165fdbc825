"""The Cramér-Rao ruler against Monte-Carlo runs of ideal estimators and the sensor model."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import ncx2

from vvtbench.render import crb
from vvtbench.render.sensor import sensor_dn


def _texture(rng: np.random.Generator, n_waves: int = 6):
    """A smooth random texture (DN) and its analytic gradient, as functions of (x, y)."""
    k = rng.uniform(0.15, 0.6, n_waves)
    th = rng.uniform(0, 2 * np.pi, n_waves)
    kx, ky = k * np.cos(th), k * np.sin(th)
    ph = rng.uniform(0, 2 * np.pi, n_waves)
    amp = rng.uniform(20.0, 60.0, n_waves)

    def value(x, y):
        arg = kx * x[..., None] + ky * y[..., None] + ph
        return 500.0 + np.sum(amp * np.sin(arg), axis=-1)

    def grad(x, y):
        c = amp * np.cos(kx * x[..., None] + ky * y[..., None] + ph)
        return np.stack([np.sum(c * kx, -1), np.sum(c * ky, -1)], axis=-1)

    return value, grad


def test_gradient_filter_matches_analytic_gradient():
    value, grad = _texture(np.random.default_rng(1))
    y, x = np.mgrid[0:40, 0:40].astype(float)
    g = crb.image_gradient(value(x, y))
    inner = (slice(4, -4), slice(4, -4))
    err = np.abs(g[inner] - grad(x, y)[inner]).max()
    assert err < 0.01 * np.abs(grad(x, y)).max()


def test_shift_estimate_variance_reaches_the_bound():
    """Gauss-Newton on the known texture: the shift's covariance over noise draws is J^-1."""
    rng = np.random.default_rng(7)
    value, grad = _texture(rng)
    n, sigma, shift = 20, 4.0, np.array([0.31, -0.22])
    y, x = np.mgrid[0:n, 0:n].astype(float)
    clean = value(x - shift[0], y - shift[1])
    jp = crb.pixel_fisher(value(x, y), sigma**2)
    bound = crb.block_crb(jp, block=n)
    cov = np.linalg.inv(np.array([[bound["fisher"][0, 0, 0], bound["fisher"][0, 0, 1]],
                                  [bound["fisher"][0, 0, 1], bound["fisher"][0, 0, 2]]]))
    draws = 800
    obs = clean[None] + rng.normal(0.0, sigma, (draws, n, n))
    s = np.zeros((draws, 2))
    for _ in range(6):
        xs, ys = x[None] - s[:, :1, None], y[None] - s[:, 1:, None]
        r = (obs - value(xs, ys)).reshape(draws, -1)
        jac = -grad(xs, ys).reshape(draws, -1, 2)  # d model / d s
        jtj = np.einsum("dpi,dpj->dij", jac, jac)
        s = s + np.linalg.solve(jtj, np.einsum("dpi,dp->di", jac, r)[..., None])[..., 0]
    assert np.allclose(s.mean(axis=0), shift, atol=4 * np.sqrt(np.diag(cov) / draws))
    var = s.var(axis=0)
    assert np.allclose(var, np.diag(cov), rtol=0.15)
    assert np.allclose(np.sqrt(np.diag(cov)), bound["std_px"][0, 0], rtol=1e-12)


@pytest.mark.parametrize("zeta", [0.0, 0.02])
def test_mode_snr_matches_least_squares_amplitude(zeta):
    """A mode's amplitude by least squares at its known frequency: std a / SNR."""
    rng = np.random.default_rng(11)
    value, grad = _texture(rng)
    n, T, fps, f, sigma, a = 20, 96, 100.0, 13.0, 6.0, 0.04
    y, x = np.mgrid[0:n, 0:n].astype(float)
    psi = np.stack([np.cos(0.2 * y) + 0.3, 0.5 * np.sin(0.15 * x)], axis=-1)  # px per unit
    psi_hat = psi / np.sqrt((psi**2).sum(-1)).max()
    t = np.arange(T) / fps
    w = 2 * np.pi * f
    env = np.exp(-zeta * w * t)
    basis = np.stack([env * np.cos(w * t), env * np.sin(w * t)], axis=1)  # (T, 2)
    phi = 0.7
    c = a * env * np.cos(w * t + phi)  # motion at the largest pixel (px)
    frames = value(x[None] - c[:, None, None] * psi_hat[..., 0],
                   y[None] - c[:, None, None] * psi_hat[..., 1])  # (T, n, n)
    rest = value(x, y)
    jp = crb.pixel_fisher(rest, sigma**2)
    info, gain = crb.mode_information(jp, [psi])
    assert gain[0] == pytest.approx(np.sqrt((psi**2).sum(-1)).max())
    energy = crb.decaying_sinusoid_energy(a, f, zeta, T, fps)
    snr = float(crb.mode_snr(info, energy)[0])
    # pattern of the mode in the image: -g . psi_hat; LS of the two quadratures
    pattern = -(grad(x, y) * psi_hat).sum(-1).ravel()
    design = np.einsum("tk,p->tpk", basis, pattern).reshape(T * n * n, 2)
    pinv = np.linalg.pinv(design)
    draws = 400
    amps = np.empty(draws)
    for d in range(draws):
        obs = frames + rng.normal(0.0, sigma, frames.shape) - rest[None]
        amps[d] = np.hypot(*(pinv @ obs.ravel()))
    assert 5 < snr < 40
    assert amps.std() == pytest.approx(a / snr, rel=0.15)
    assert amps.mean() == pytest.approx(a, rel=0.05)


def test_noise_variance_matches_the_sensor():
    rng = np.random.default_rng(3)
    for intensity, bits, read, shot, fw, avg in [(0.5, 12, 2.0, True, 10000.0, 1),
                                                 (0.2, 10, 1.5, True, 5000.0, 4),
                                                 (0.7, 8, 1.0, False, 10000.0, 2)]:
        subs = np.full((avg, 200, 200), intensity)
        dn = sensor_dn(subs, bits, read, shot, fw, rng).astype(float)
        model = float(crb.noise_variance_dn2(intensity, bits, read, shot, fw, avg))
        assert dn.var() == pytest.approx(model, rel=0.05)


def test_detection_threshold_is_the_median_detection():
    """At the threshold SNR the ideal statistic exceeds the false-alarm level half the time."""
    T, pfa = 500, 0.01
    snr = crb.detection_snr_threshold(T, pfa)
    per_bin = 1 - (1 - pfa) ** (1 / (T // 2))
    level = 2 * np.log(1 / per_bin)
    rng = np.random.default_rng(5)
    z = rng.normal(size=(200000, 2)) + np.array([snr, 0.0])
    assert np.mean((z**2).sum(1) > level) == pytest.approx(0.5, abs=0.01)
    assert ncx2.sf(level, 2, snr**2) == pytest.approx(0.5, abs=1e-6)
    assert crb.detection_snr_threshold(2000) > snr > crb.detection_snr_threshold(100)


def test_block_crb_shapes_and_textureless_blocks():
    jp = np.zeros((20, 17, 3))
    jp[:8, :8, 0] = 1.0
    jp[:8, :8, 2] = 4.0
    out = crb.block_crb(jp, block=8)
    assert out["fisher"].shape == (3, 3, 3) and out["std_px"].shape == (3, 3, 2)
    assert np.allclose(out["std_px"][0, 0], [1 / 8, 1 / 16])
    assert out["std_min_px"][0, 0] == pytest.approx(1 / 16)
    assert np.all(np.isinf(out["std_px"][1:, :])) and np.isinf(out["std_min_px"][2, 2])


def test_sample_check_requires_the_ruler_arrays_only_when_reported(tmp_path):
    from vvtbench.samples.reader import RULER_ARRAYS, check_sample

    listed = {f"truth.zarr/{name}/zarr.json": {"sha256": "0" * 64} for name in RULER_ARRAYS}
    older = check_sample(tmp_path, {"files": {}}, {"video": {}})
    assert not [p for p in older if "Cramér-Rao" in p]
    missing = check_sample(tmp_path, {"files": {}}, {"video": {}, "crb": {"detection_snr": 4.7}})
    assert sum("Cramér-Rao" in p for p in missing) == len(RULER_ARRAYS)
    whole = check_sample(tmp_path, {"files": listed}, {"video": {}, "crb": {"detection_snr": 4.7}})
    assert not [p for p in whole if "reports the Cramér-Rao" in p]
    bad = check_sample(tmp_path, {"files": listed}, {"video": {}, "crb": {"n_bins": 3}})
    assert any("detection_snr" in p for p in bad)
