"""Pole-based identification (ERA, pLSCF, stabilisation, clustering, projection) and the
products test on poles.

Displacement fields are made here from known modes (smooth random shapes, damped free decays);
the products come from a memoryless pixel-dependent non-linearity applied to the motion
(``u + a(x) u**2 + b(x) u**3``), the model of the measured motion.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_combinations import smooth_shape, texture

from vvtbench.modes import ModeSet, modes_from_displacements
from vvtbench.modes.era import era_orders, poles_to_modal
from vvtbench.modes.plscf import half_spectra, lscf_orders
from vvtbench.modes.poles import decide_identifier, project_poles
from vvtbench.modes.products import explained_fraction, find_pole_products, phase_coherence
from vvtbench.modes.reduce import block_channels, channel_noise, decimate_frames
from vvtbench.modes.stabilization import cluster_poles, stable_poles

N = 32


def decay_field(freqs, zetas, amps, shapes, T, fps, phases=None):
    """``(T, n, n, 2)`` sum of damped free decays ``a exp(-zeta w t) cos(w_d t + phi) s``."""
    t = np.arange(T) / fps
    out = np.zeros((T, *shapes[0].shape))
    for k, (f, z, a) in enumerate(zip(freqs, zetas, amps, strict=True)):
        w = 2 * np.pi * f
        ph = 0.0 if phases is None else phases[k]
        q = a * np.exp(-z * w * t) * np.cos(w * np.sqrt(1 - z * z) * t + ph)
        out += q[:, None, None, None] * shapes[k][None]
    return out


def mac(a, b):
    a, b = np.ravel(a), np.ravel(b)
    return float(abs(np.vdot(a, b)) ** 2 / (np.vdot(a, a).real * np.vdot(b, b).real))


def test_era_and_lscf_recover_poles_of_a_noisy_multichannel_decay():
    rng = np.random.default_rng(0)
    fs, T, m = 500.0, 1500, 12
    t = np.arange(T) / fs
    f = np.array([5.65, 7.8, 13.3, 19.0])
    z = np.array([0.015, 0.015, 0.018, 0.023])
    a = np.array([1.0, 0.7, 0.05, 0.05])
    lam = 2 * np.pi * f * (-z + 1j * np.sqrt(1 - z**2))
    S = rng.standard_normal((f.size, m))
    y = sum(a[k] * np.exp(lam[k] * t).real[:, None] * S[k] for k in range(f.size))
    y = y + 1e-4 * rng.standard_normal(y.shape)
    (ps,) = era_orders(y, 1 / fs, [16])
    fe, ze = poles_to_modal(ps.lam)
    for k in range(f.size):
        j = np.argmin(np.abs(fe - f[k]))
        assert abs(fe[j] / f[k] - 1) < 1e-3 and abs(ze[j] / z[k] - 1) < 0.05
        assert mac(ps.shapes[j], S[k]) > 0.99
    # the monomial basis needs the band to fill the unit circle: frames averaged by 4 first
    # (a free decay again, with the poles z^4); a linearised least squares is biased by
    # noise near strong lines, so a quieter record
    yd = decimate_frames(sum(a[k] * np.exp(lam[k] * t).real[:, None] * S[k]
                             for k in range(f.size)) + 1e-6 * rng.standard_normal(y.shape), 4)
    X = np.fft.rfft(yd - yd.mean(0), axis=0)
    (pl,) = lscf_orders(X, np.fft.rfftfreq(len(yd), 4 / fs), 4 / fs, [12], band=(3, 60))
    fl, zl = pl.frequency_hz, pl.damping
    for k in range(f.size):
        j = np.argmin(np.abs(fl - f[k]))
        assert abs(fl[j] / f[k] - 1) < 2e-3 and abs(zl[j] / z[k] - 1) < 0.1


def test_plscf_on_half_spectra_of_a_random_response():
    """Output-only pLSCF: a two-mode system driven by white noise."""
    from scipy.signal import lfilter

    rng = np.random.default_rng(1)
    fs, T = 200.0, 40000
    f, z = np.array([12.0, 31.0]), np.array([0.02, 0.03])
    S = np.array([[1.0, 0.5, -0.3, 0.8], [0.2, -1.0, 0.7, 0.4]])
    y = np.zeros((T, 4))
    for k in range(2):
        p = np.exp(2 * np.pi * f[k] * (-z[k] + 1j * np.sqrt(1 - z[k] ** 2)) / fs)
        q = lfilter([1.0], [1.0, -2 * p.real, abs(p) ** 2], rng.standard_normal(T))
        y += q[:, None] * S[k]
    n_lags = 256
    Sh = half_spectra(y, [0, 1], n_lags)
    fr = np.fft.rfftfreq(2 * n_lags, 1 / fs)
    tau = -(n_lags - 1) / fs / np.log(0.01)
    poles = lscf_orders(Sh, fr, 1 / fs, [4, 6, 8, 10], band=(2, 90), exp_window=1 / tau)
    stable = stable_poles(poles, f_tol=0.01, z_tol=0.2, mac_tol=0.9, band_hz=(2, 90))
    clusters = cluster_poles(poles, stable, min_members=2)
    found = np.array([c.frequency_hz for c in clusters])
    for k in range(2):
        j = np.argmin(np.abs(found - f[k]))
        assert abs(found[j] / f[k] - 1) < 0.01
        assert abs(clusters[j].damping / z[k] - 1) < 0.3


def test_block_channels_stream_like_ram_and_noise_is_read_from_the_median():
    from vvtbench.modes.spectrum import DisplacementStore

    rng = np.random.default_rng(2)
    d = rng.standard_normal((40, 16, 16, 2)).astype(np.float32)
    w = rng.uniform(0, 1, (16, 16))
    ram = block_channels(d, weights=w, block=4)
    with DisplacementStore(memory_budget=0) as st:
        st.extend(np.split(d, 4))
        disk = block_channels(st, weights=w, block=4, block_bytes=1)
    assert np.allclose(ram.data, disk.data, atol=1e-5)
    tile = (w[:4, :4, None] * d[:, :4, :4, :]).sum((1, 2)) / w[:4, :4].sum()
    assert np.allclose(ram.data[:, :2], tile, atol=1e-5)
    y = np.cumsum(np.ones((12, 1)), axis=0)
    assert decimate_frames(y, 4).ravel().tolist() == [2.5, 6.5, 10.5]
    assert channel_noise(rng.standard_normal((8192, 1)) * 3.0)[0] == pytest.approx(3.0, rel=0.1)


def test_projection_on_poles_gives_each_mode_its_field():
    rng = np.random.default_rng(3)
    fps, T = 400.0, 800
    shapes = [smooth_shape(rng, 16) for _ in range(2)]
    f, z = [11.0, 23.0], [0.02, 0.01]
    d = decay_field(f, z, [0.3, 0.05], shapes, T, fps)
    lam = [2 * np.pi * fk * (-zk + 1j * np.sqrt(1 - zk * zk)) for fk, zk in zip(f, z, strict=True)]
    Z, noise = project_poles(d, fps, lam)
    for k in range(2):
        assert mac(2 * Z[k].real, shapes[k]) > 0.9999
    assert np.linalg.norm(2 * Z[0].real) == pytest.approx(0.3 * np.linalg.norm(shapes[0]),
                                                         rel=1e-3)
    assert noise.shape == (2,) and np.all(noise < 1e-6)


def test_decide_identifier_from_excitation_or_envelope():
    t = np.arange(2000) / 500.0
    assert decide_identifier(excitation="pluck")[0] == "era"
    assert decide_identifier(excitation="force")[0] == "peaks"
    used, why = decide_identifier(np.exp(-t)[:, None] * np.cos(70 * t)[:, None])
    assert used == "era" and "free decay" in why
    assert decide_identifier(np.cos(70 * t)[:, None])[0] == "peaks"
    # a pluck that does not decay within the record (undamped): the peak picker
    used, why = decide_identifier(np.cos(70 * t)[:, None], excitation="pluck")
    assert used == "peaks" and "pluck" in why
    assert decide_identifier(np.exp(-t)[:, None] * np.cos(70 * t)[:, None],
                             excitation="force")[0] == "peaks"


def _damped_record(seed=4, n=N, T=1500, fps=500.0, noise=1e-4):
    rng = np.random.default_rng(seed)
    shapes = [smooth_shape(rng, n) * n for _ in range(4)]
    f = [6.0, 9.5, 17.0, 26.0]
    z = [0.015, 0.015, 0.02, 0.025]
    a = [0.3, 0.2, 0.02, 0.01]
    d = decay_field(f, z, a, shapes, T, fps)
    d += noise * rng.standard_normal(d.shape)
    return d.astype(np.float32), f, z, shapes


def test_era_identifier_end_to_end_records_itself_and_round_trips(tmp_path):
    d, f, z, shapes = _damped_record()
    ms = modes_from_displacements(d, 500.0, identifier="auto",
                                  pole_options={"block": 4, "n_components": 16,
                                                "max_order": 48, "block_rows": 10})
    assert ms.identifier["used"] == "era" and ms.identifier["requested"] == "auto"
    assert "free decay" in ms.identifier["reason"]
    assert len(ms) == 4
    for k in range(4):
        j = int(np.argmin(np.abs(ms.frequencies_hz - f[k])))
        assert abs(ms.frequencies_hz[j] / f[k] - 1) < 2e-3
        assert abs(ms.damping[j] / z[k] - 1) < 0.1
        assert ms.damping_resolved()[j]
        assert mac(ms.shapes[j], shapes[k]) > 0.98
    assert np.all(np.isfinite(ms.frequency_std_hz()))
    diagram = ms.metadata["poles"]["diagram"]
    assert diagram["columns"][0] == "order" and len(diagram["poles"]) > 10
    back = ModeSet.load(ms.save(tmp_path / "m"))
    assert back.identifier == ms.identifier and back.pole_based
    assert np.allclose(back.frequencies_hz, ms.frequencies_hz)
    from vvtbench.modes.plots import plot_modes

    paths = plot_modes(back, tmp_path / "m")
    assert (tmp_path / "m" / "stabilization.png") in paths


def test_old_mode_files_load_as_peak_picked(tmp_path):
    d, *_ = _damped_record(T=400, noise=1e-3)
    ms = modes_from_displacements(d, 500.0)
    out = ms.save(tmp_path / "m")
    doc = json.loads((out / "modes.json").read_text())
    del doc["metadata"]["identifier"]
    (out / "modes.json").write_text(json.dumps(doc))
    back = ModeSet.load(out)
    assert back.identifier["used"] == "peaks" and not back.pole_based


# --------------------------------------------------------------------------- products
def _distorted(own_shape: bool, seed: int, zeta3: float | None = None):
    """Two plucked damped modes through ``u + a u**2 + b u**3`` and a third mode of its own
    exactly at ``f1 + f2``; ``own_shape`` False gives the third the products' shape instead."""
    rng = np.random.default_rng(seed)
    n, fps, T = 32, 500.0, 1500
    s1, s2 = smooth_shape(rng, n) * n, smooth_shape(rng, n) * n
    f1, f2, z1, z2 = 31.0, 47.0, 0.01, 0.008
    # the worst case: the mode at f1 + f2 decays at sigma_1 + sigma_2, like their product
    f3 = f1 + f2
    z3 = (z1 * f1 + z2 * f2) / f3 if zeta3 is None else zeta3
    s3 = smooth_shape(rng, n) * n if own_shape else texture(rng, n) * s1 * s2
    d = decay_field([f1, f2, f3], [z1, z2, z3], [0.3, 0.2, 0.01], [s1, s2, s3], T, fps)
    a2, a3 = 0.3 * texture(rng, n), 0.5 * texture(rng, n)
    d = d + a2 * d**2 + a3 * d**3
    d += 1e-5 * rng.standard_normal(d.shape)
    return d.astype(np.float32), fps, (f1, f2, f3)


@pytest.mark.parametrize("seed", [0, 1])
def test_true_mode_on_a_sum_with_a_product_decay_is_kept_products_rejected(seed):
    d, fps, (f1, f2, f3) = _distorted(True, seed)
    opts = {"block": 4, "n_components": 24, "max_order": 60, "block_rows": 10}
    ms = modes_from_displacements(d, fps, identifier="era", pole_options=opts)
    found = np.round(ms.frequencies_hz).tolist()
    for f in (f1, f2, f3):
        assert round(f) in found, found
    prods = [r for r in ms.metadata["rejected"] if r["reason"] == "product"]
    named = {round(r["expected_hz"]): r["product"] for r in prods}
    assert named.get(round(2 * f1)) == "2 x 31.0 Hz", named
    assert all(abs(r["frequency_hz"] - f3) > 0.5 for r in prods)
    assert len(ms) <= 4


def test_a_product_at_the_sum_is_rejected_by_its_shape_not_its_frequency():
    """The same record with the third line made by the non-linearity's shape (texture times
    the parents' product): rejected; with frequency alone nothing tells them apart."""
    d, fps, (f1, f2, f3) = _distorted(False, 2)
    opts = {"block": 4, "n_components": 24, "max_order": 60, "block_rows": 10}
    ms = modes_from_displacements(d, fps, identifier="era", pole_options=opts)
    assert all(abs(f - f3) > 0.3 for f in ms.frequencies_hz), ms.frequencies_hz
    prods = {round(r["frequency_hz"]): r for r in ms.metadata["rejected"]
             if r["reason"] == "product"}
    assert round(f3) in prods
    assert prods[round(f3)]["product"] in ("31.0 + 47.0 Hz", "47.0 + 31.0 Hz")


def test_product_tests_on_fields():
    rng = np.random.default_rng(5)
    n = 48
    p1 = smooth_shape(rng, n).astype(complex) * np.exp(0.4j)
    p2 = smooth_shape(rng, n).astype(complex) * np.exp(1.1j)
    tex = texture(rng, n)
    prod = tex * p1 * p2  # texture-locked sum product: phase 0.4 + 1.1 at every pixel
    smooth = 0.3 * p1[..., :1] * p2 + 0.1 * p1 * p2[..., 1:]
    own = smooth_shape(rng, n) * np.exp(0.2j)
    assert phase_coherence(prod, np.stack([p1, p2]), [1, 1]) > 0.99
    assert phase_coherence(own, np.stack([p1, p2]), [1, 1]) < 0.7
    assert explained_fraction(smooth, np.stack([p1, p2]), [1, 1]) > 0.99
    assert explained_fraction(own, np.stack([p1, p2]), [1, 1]) < 0.5
    f = np.array([31.0, 47.0, 78.0])
    fields = np.stack([p1, p2, prod])
    kept, out = find_pole_products(f, [0.01, 0.008, 0.0088], [1.0, 0.5, 0.01], fields,
                                   fps=500.0, bin_hz=1 / 3)
    assert kept.tolist() == [True, True, False] and out[0]["test"] == "envelope"
    # a phase of its own: kept, whatever its shape and frequency
    kept, _ = find_pole_products(f, [0.01, 0.008, 0.0088], [1.0, 0.5, 0.01],
                                 np.stack([p1, p2, prod * np.exp(0.8j)]), fps=500.0,
                                 bin_hz=1 / 3)
    assert kept.all()
    # a decay of its own (a free decay): kept
    kept, _ = find_pole_products(f, [0.01, 0.008, 0.03], [1.0, 0.5, 0.01], fields, fps=500.0,
                                 bin_hz=1 / 3)
    assert kept.all()
    # a smooth mode of its own that its would-be parents' monomials half explain (smooth
    # fields of an object span much of each other): kept; the smooth product itself is not
    unit = lambda x: x / np.linalg.norm(x)  # noqa: E731
    half = unit(smooth) + unit(own * np.exp(1.3j))
    assert 0.3 < explained_fraction(half, np.stack([p1, p2]), [1, 1]) < 0.8
    rough = [0.0, 0.0, 0.05]
    kept, _ = find_pole_products(f, [0.01, 0.008, 0.0088], [1.0, 0.5, 0.01],
                                 np.stack([p1, p2, half]), fps=500.0, bin_hz=1 / 3,
                                 roughness=rough, min_phase_coherence=-1.0)
    assert kept.all()
    kept, out = find_pole_products(f, [0.01, 0.008, 0.0088], [1.0, 0.5, 0.01],
                                   np.stack([p1, p2, smooth]), fps=500.0, bin_hz=1 / 3,
                                   roughness=rough)
    assert kept.tolist() == [True, True, False] and out[0]["test"] == "explained"
    # 7 x 113 Hz folded at 1000 fps shows at 209 Hz, its phase mirrored
    h = texture(rng, n) * p1 ** 7
    kept, out = find_pole_products([113.0, 47.0, 209.0], [0.0, 0.0, 0.0], [1.0, 0.8, 0.01],
                                   np.stack([p1, p2, np.conj(h)]), fps=1000.0, bin_hz=1.0,
                                   decay=False)
    assert kept.tolist() == [True, True, False] and out[0]["product"] == "7 x 113.0 Hz"


# --------------------------------------------------------------------------- clips
@pytest.mark.parametrize("zeta", [0.0, 0.01])
def test_clean_two_mode_clip_gives_its_two_modes_and_at_most_one_more(zeta):
    """A speckle warped by two smooth modes (47 Hz at 0.002 px, 113 Hz at 0.001 px, 1000 fps):
    ringing on (the peak picker, chosen by the envelope) or decaying (ERA)."""
    from test_modes import Speckle, pattern

    from vvtbench.modes import extract_modes

    n, T, fps = 48, 500, 1000.0
    sp = Speckle(n, seed=5)
    t = np.arange(T) / fps
    frames = np.empty((T, n, n), np.float32)
    pa, pb = pattern(n, "a"), pattern(n, "b")
    for k in range(T):
        d = sum(a * p * np.exp(-zeta * 2 * np.pi * f * t[k]) * np.cos(2 * np.pi * f * t[k])
                for p, a, f in ((pa, 0.002, 47.0), (pb, 0.001, 113.0)))
        frames[k] = sp.warp(d[..., 0], d[..., 1])
    ms = extract_modes(frames, fps, identifier="auto",
                       pole_options={"max_order": 40, "n_components": 16, "block_rows": 10})
    assert ms.identifier["used"] == ("era" if zeta else "peaks"), ms.identifier
    f = ms.frequencies_hz
    assert all(np.any(np.abs(f - x) < 1.0) for x in (47.0, 113.0)), f
    assert len(ms) <= 3, f
    if zeta:  # the noise-level poles at about 2 x 47 and 47 + 113 Hz do not settle
        assert all(r["reason"] in ("unstable", "faint", "product")
                   for r in ms.metadata["rejected"])
        for x in (47.0, 113.0):
            assert ms.damping[np.argmin(np.abs(f - x))] == pytest.approx(zeta, rel=0.1)


def test_plscf_identifier_on_a_random_response_field():
    """Two modes driven by white noise (a stationary record): pLSCF over the channels' power
    spectra finds both, with their damping; the spurious cluster between them does not
    settle."""
    from scipy.signal import lfilter

    rng = np.random.default_rng(1)
    n, fps, T = 24, 200.0, 8000
    f, z = [12.0, 31.0], [0.02, 0.03]
    shapes = [smooth_shape(rng, n) * n for _ in f]
    d = np.zeros((T, n, n, 2))
    for k in range(2):
        p = np.exp(2 * np.pi * f[k] * (-z[k] + 1j * np.sqrt(1 - z[k] ** 2)) / fps)
        q = lfilter([1.0], [1.0, -2 * p.real, abs(p) ** 2], rng.standard_normal(T)) * 1e-3
        d += q[:, None, None, None] * shapes[k][None]
    d += 1e-5 * rng.standard_normal(d.shape)
    ms = modes_from_displacements(d.astype(np.float32), fps, identifier="plscf",
                                  pole_options={"block": 4, "n_components": 8,
                                                "max_order": 40})
    assert ms.identifier["used"] == "plscf" and len(ms) == 2
    for k in range(2):
        assert ms.frequencies_hz[k] == pytest.approx(f[k], rel=5e-3)  # a linearised fit
        assert ms.damping[k] == pytest.approx(z[k], rel=0.15)
        assert mac(ms.shapes[k], shapes[k]) > 0.98
