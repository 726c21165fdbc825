"""Harmonics and intermodulation products told apart from true modes by phase and shape.

The products are made by a memoryless pixel-dependent non-linearity applied to the motion
(``u' = u + a(x) u**2 + b(x) u**3``, the model of the measured motion), not by the code under
test; true modes have smooth shapes of their own.
"""

from __future__ import annotations

import numpy as np
import pytest

from vvtbench.modes import modes_from_displacements
from vvtbench.modes.combinations import (
    Combination,
    combination_phase_residual,
    envelope_correlation,
    find_combinations,
    reject_combinations,
)

N = 64


def smooth_shape(rng: np.random.Generator, n: int = N) -> np.ndarray:
    """A smooth ``(n, n, 2)`` field: two random plane waves per component."""
    y, x = np.mgrid[0:n, 0:n] / n
    out = np.zeros((n, n, 2))
    for c in range(2):
        for _ in range(2):
            kx, ky = rng.uniform(-1.5, 1.5, 2)
            out[..., c] += rng.standard_normal() * np.cos(
                2 * np.pi * (kx * x + ky * y) + rng.uniform(0, 2 * np.pi))
    return out / np.linalg.norm(out)


def texture(rng: np.random.Generator, n: int = N) -> np.ndarray:
    """A rough pixel-dependent non-linearity coefficient per pixel and component."""
    from scipy.ndimage import gaussian_filter

    return gaussian_filter(rng.standard_normal((n, n, 2)), (1.0, 1.0, 0))


def unit(a: np.ndarray) -> np.ndarray:
    return a / np.linalg.norm(a)


def test_label_kinds_and_phase_residual_of_a_third_order_product():
    f = [113.0, 96.0]
    assert Combination((0,), (3,)).label(f) == "3 x 113.0 Hz"
    assert Combination((0, 1), (1, 1)).label(f) == "113.0 + 96.0 Hz"
    assert Combination((0, 1), (1, -1)).kind == "difference"
    assert Combination((0,), (3,)).kind == "harmonic" and Combination((0,), (3,)).order == 3
    # 3 x 113 = 339 Hz sampled at 400 fps shows at 400 - 339 = 61 Hz, its phase negated
    ph = [0.3, 1.0, (-(3 * 0.3)) % np.pi]
    c = Combination((0,), (3,))
    assert abs(combination_phase_residual(ph, [113.0, 96.0, 61.0], 2, c, fps=400.0)) < 1e-12
    assert abs(combination_phase_residual(ph, [113.0, 96.0, 61.0], 2, c)) > 0.5


def test_envelope_correlation_monte_carlo_separates_products_from_own_shapes():
    """Over random draws, a parent-shaped product (any power law, rough texture) correlates
    with its parents' envelope, an independent smooth shape does not."""
    rng = np.random.default_rng(1)
    prod, own = [], []
    for _ in range(40):
        s1, s2 = smooth_shape(rng), smooth_shape(rng)
        a = texture(rng)
        prod.append(envelope_correlation(a * s1 * s2[..., ::-1], np.stack([s1, s2]), [1, 1]))
        own.append(envelope_correlation(smooth_shape(rng), np.stack([s1, s2]), [1, 1]))
    prod, own = np.array(prod), np.array(own)
    assert np.mean(prod >= 0.4) >= 0.9
    assert np.mean(own >= 0.4) <= 0.1
    assert abs(np.mean(own)) < 0.1


def _candidates(rng, *, product_shape: bool, phase_of_product: bool, harmonic3: bool = False):
    """Two parents (113 and 96 Hz, pluck-like phases) and a weak candidate at 209 Hz (f1 + f2)
    or at 339 Hz (3 x 113 Hz)."""
    s1, s2 = smooth_shape(rng), smooth_shape(rng)
    ph = np.array([0.2, 1.1])
    if harmonic3:
        f_k, shape = 339.0, texture(rng) * s1**3
        ph_k = 3 * ph[0]
    else:
        f_k, shape = 209.0, texture(rng) * s1 * s2
        ph_k = ph[0] + ph[1]
    if not product_shape:
        shape = smooth_shape(rng)
    if not phase_of_product:
        ph_k += 1.2
    f = np.array([113.0, 96.0, f_k])
    shapes = np.stack([s1, s2, unit(shape)])
    return f, np.array([1.0, 0.5, 1e-3]), np.append(ph, ph_k % np.pi), shapes


@pytest.mark.parametrize("harmonic3", [False, True])
def test_product_with_predicted_shape_and_phase_is_rejected(harmonic3):
    rng = np.random.default_rng(2)
    f, a, ph, shapes = _candidates(rng, product_shape=True, phase_of_product=True,
                                   harmonic3=harmonic3)
    kept, products = find_combinations(f, a, shapes, 0.5, phases=ph, fps=1000.0)
    assert kept.tolist() == [True, True, False]
    (d,) = products
    assert d["product"] == ("3 x 113.0 Hz" if harmonic3 else "113.0 + 96.0 Hz")
    assert d["order"] == (3 if harmonic3 else 2) and d["reason"] == "product"
    assert abs(d["phase_residual_rad"]) < 1e-9 and d["envelope_correlation"] >= 0.4


def test_true_mode_at_a_combination_frequency_is_kept_by_its_shape():
    """Same frequency and phase as the product (a pluck), a shape of its own: kept."""
    kept_count = 0
    for seed in range(20):
        rng = np.random.default_rng(100 + seed)
        f, a, ph, shapes = _candidates(rng, product_shape=False, phase_of_product=True)
        kept, _ = find_combinations(f, a, shapes, 0.5, phases=ph, fps=1000.0)
        kept_count += bool(kept[2])
    assert kept_count >= 18


def test_product_shape_with_a_phase_of_its_own_is_kept():
    rng = np.random.default_rng(3)
    f, a, ph, shapes = _candidates(rng, product_shape=True, phase_of_product=False)
    kept, _ = find_combinations(f, a, shapes, 0.5, phases=ph, fps=1000.0)
    assert kept.all()
    # without phases the shape alone decides
    kept, _ = find_combinations(f, a, shapes, 0.5, fps=1000.0)
    assert kept.tolist() == [True, True, False]


def test_frequency_off_the_combination_is_kept_and_bad_input_raises():
    rng = np.random.default_rng(4)
    f, a, ph, shapes = _candidates(rng, product_shape=True, phase_of_product=True)
    f[2] += 0.6  # more than half a bin of 0.5 Hz... times 2
    kept, _ = find_combinations(f, a, shapes, 0.5, phases=ph, fps=1000.0)
    assert kept.all()
    with pytest.raises(ValueError, match="max_order"):
        find_combinations(f, a, shapes, 0.5, max_order=4)
    with pytest.raises(ValueError, match="do not agree"):
        find_combinations(f[:2], a, shapes, 0.5)


def test_extraction_of_distorted_motion_keeps_modes_and_rejects_products():
    """Displacements through ``u + a(x) u**2 + b(x) u**3`` (per pixel and component) of two
    modes at 113 and 96 Hz and a third mode of its own exactly at 113 + 96 Hz: the harmonics
    (226, 192, 339 Hz) and intermodulation products (17, 130, 79 Hz, ...) are rejected with
    the combination named; the three modes are kept."""
    rng = np.random.default_rng(5)
    n, fps, T = 40, 1000.0, 600
    t = np.arange(T) / fps
    shapes = [smooth_shape(rng, n) * n for _ in range(3)]
    freqs, amps = [113.0, 96.0, 209.0], [0.3, 0.2, 0.02]
    a2, a3 = texture(rng, n), 2.0 * texture(rng, n)
    u = sum(A * np.cos(2 * np.pi * f0 * t)[:, None, None, None] * s[None]
            for f0, A, s in zip(freqs, amps, shapes, strict=True))
    d = (u + a2 * u**2 + a3 * u**3).astype(np.float32)
    ms = modes_from_displacements(d, fps, reject_distortion=False, faint_product_ratio=None)
    assert len(ms) > 4  # the products are there
    out = reject_combinations(ms)
    assert sorted(np.round(out.frequencies_hz).tolist()) == [96.0, 113.0, 209.0]
    products = {round(r["frequency_hz"]): r["product"] for r in out.metadata["rejected"]
                if r["reason"] == "product"}
    assert products[226] == "2 x 113.0 Hz"
    assert products[339] == "3 x 113.0 Hz"
    assert products[17] == "113.0 - 96.0 Hz"
    assert out.metadata["combinations"]["phase_tested"]
    assert "combinations" not in ms.metadata  # the input is left as it was
    with pytest.raises(ValueError, match="confidence"):
        reject_combinations(ms, weights="texture")


def _rendered_clip(n: int = 64, T: int = 300, fps: float = 400.0) -> np.ndarray:
    """A speckle warped exactly (third-order Taylor expansion with the image's Fourier
    derivatives) by modes at 37 and 52 Hz (0.4 and 0.25 px) and one of its own exactly at
    37 + 52 = 89 Hz (0.03 px), all plucked (phase 0)."""
    import math

    rng = np.random.default_rng(0)
    wy = 2 * np.pi * np.fft.fftfreq(n)[:, None]
    wx = 2 * np.pi * np.fft.fftfreq(n)[None, :]
    F = np.fft.fft2(rng.standard_normal((n, n))) * np.exp(-0.5 * (np.hypot(wx, wy) * 1.5) ** 2)
    ders = {(i, j): np.fft.ifft2(F * (1j * wx) ** i * (1j * wy) ** j).real
            for i in range(4) for j in range(4 - i)}
    y, x = np.mgrid[0:n, 0:n] / n
    fields = [np.stack([np.sin(np.pi * x) * np.cos(np.pi * y), 0.5 * np.sin(2 * np.pi * y)], -1),
              np.stack([0.6 * np.cos(2 * np.pi * x), np.sin(np.pi * x) * np.sin(np.pi * y)], -1),
              np.stack([np.cos(np.pi * y), np.sin(2 * np.pi * x) * np.cos(np.pi * x)], -1)]
    t = np.arange(T) / fps
    frames = np.empty((T, n, n), np.float32)
    for k in range(T):
        d = sum(A * np.cos(2 * np.pi * f0 * t[k]) * s
                for f0, A, s in zip((37.0, 52.0, 89.0), (0.4, 0.25, 0.03), fields, strict=True))
        img = ders[(0, 0)].copy()
        for (i, j), der in ders.items():
            if i + j:
                img += ((-1) ** (i + j) / (math.factorial(i) * math.factorial(j))
                        * d[..., 0] ** i * d[..., 1] ** j * der)
        frames[k] = img
    return frames


def test_rendered_clip_products_rejected_plucked_mode_at_their_sum_kept(tmp_path):
    from vvtbench.modes import ModeSet, extract_modes

    ms = extract_modes(_rendered_clip(), 400.0, faint_product_ratio=None,
                       reject_distortion=False)
    assert {15, 74, 104} <= set(np.round(ms.frequencies_hz).astype(int).tolist())
    out = reject_combinations(ms)
    assert np.round(out.frequencies_hz).tolist() == [37.0, 52.0, 89.0]
    named = {round(r["frequency_hz"]): r["product"] for r in out.metadata["rejected"]}
    assert named == {15: "52.0 - 37.0 Hz", 74: "2 x 37.0 Hz", 104: "2 x 52.0 Hz"}
    back = ModeSet.load(out.save(tmp_path / "modes"))
    assert [r["product"] for r in back.metadata["rejected"]] == list(named.values())
    assert all(r["reason"] == "product" and r["parents_hz"] for r in back.metadata["rejected"])


def test_sibling_product_shape_decides_at_the_difference_frequency():
    """``a(x) u1 u2`` puts the same field at ``f1 + f2`` and ``f1 - f2``: two such candidates
    are both rejected (sibling MAC 1); a mode of its own at ``f1 - f2`` whose smooth shape
    follows its would-be parents' envelope (so the envelope test alone would reject it) is
    kept because it is unlike the product at ``f1 + f2``."""
    rng = np.random.default_rng(6)
    s1, s2 = smooth_shape(rng), smooth_shape(rng)
    prod = unit(texture(rng) * s1 * s2)
    f = np.array([113.0, 96.0, 209.0, 17.0])
    a = np.array([1.0, 0.5, 1e-3, 1e-3])
    ph = np.array([0.2, 1.1, 1.3, 0.2 - 1.1 + np.pi])
    kept, products = find_combinations(f, a, np.stack([s1, s2, prod, prod]), 0.5, phases=ph)
    assert kept.tolist() == [True, True, False, False]
    assert all(d["sibling_mac"] > 0.99 for d in products)
    assert {d["product"] for d in products} == {"113.0 + 96.0 Hz", "113.0 - 96.0 Hz"}

    own = unit(s1 * s2[..., ::-1])  # smooth, shaped like the parents' envelope
    assert envelope_correlation(own, np.stack([s1, s2]), [1, 1]) >= 0.4
    shapes = np.stack([s1, s2, prod, own])
    a[3] = 3e-3  # the mode, stronger than the product: it says nothing about the product
    kept, products = find_combinations(f, a, shapes, 0.5, phases=ph)
    assert kept.tolist() == [True, True, False, True]
    assert products[0]["sibling_mac"] is None  # the product is judged by its envelope
    # without the product at f1 + f2 the envelope alone decides, and takes the mode for one
    kept, _ = find_combinations(f[[0, 1, 3]], a[[0, 1, 3]], shapes[[0, 1, 3]], 0.5,
                                phases=ph[[0, 1, 3]])
    assert not kept[2]


def test_faint_ratio_rejects_tiny_products_unless_phase_or_sibling_says_otherwise():
    """A candidate 1e-4 of its parents' product power whose shape follows nothing (the
    quantisation's products): rejected with ``faint_ratio`` only, and kept when its phase is
    not the product's."""
    rng = np.random.default_rng(7)
    s1, s2 = smooth_shape(rng), smooth_shape(rng)
    noise_like = unit(rng.standard_normal((N, N, 2)))
    f = np.array([113.0, 96.0, 226.0])
    a = np.array([1.0, 0.5, 1e-2])  # P = 1e-4 of the harmonic's reference P_0^2 / P_0
    ph = np.array([0.2, 1.1, 0.4])
    shapes = np.stack([s1, s2, noise_like])
    kept, _ = find_combinations(f, a, shapes, 0.5, phases=ph)
    assert kept.all()  # shape and phase alone: the envelope does not follow
    kept, products = find_combinations(f, a, shapes, 0.5, phases=ph, faint_ratio=0.01)
    assert kept.tolist() == [True, True, False]
    assert products[0]["test"] == "faint" and products[0]["product"] == "2 x 113.0 Hz"
    kept, _ = find_combinations(f, a, shapes, 0.5, phases=ph + [0, 0, 1.0], faint_ratio=0.01)
    assert kept.all()  # a phase of its own
    a[2] = 0.2  # 0.04 of the reference: not faint
    kept, _ = find_combinations(f, a, shapes, 0.5, phases=ph, faint_ratio=0.01)
    assert kept.all()


def test_extract_modes_applies_the_product_test_when_asked():
    from vvtbench.modes import extract_modes

    clip = _rendered_clip()
    plain = extract_modes(clip, 400.0, faint_product_ratio=None)
    assert {15.0, 104.0} <= set(np.round(plain.frequencies_hz).tolist())
    ms = extract_modes(clip, 400.0, faint_product_ratio=None, reject_products=True)
    assert np.round(ms.frequencies_hz).tolist() == [37.0, 52.0, 89.0]
    rejected = {round(r["frequency_hz"]): r["reason"] for r in ms.metadata["rejected"]}
    assert {f for f, why in rejected.items() if why == "product"} >= {15, 104}
    # 2 x 37 Hz: rough enough for the distortion test against the first frame, named by the
    # product test against the mean frame (the extractor's harmonic is smoother about it)
    assert rejected[74] in ("distortion", "product")


def test_high_order_harmonic_folded_at_nyquist_is_a_product_by_phase_and_envelope():
    """``7 x 113 = 791`` Hz sampled at 1000 fps shows at 209 Hz with its phase mirrored: a
    field shaped like its parent to the 7th power is rejected; one of its own is kept."""
    rng = np.random.default_rng(11)
    s1, s2 = smooth_shape(rng), smooth_shape(rng)
    ph = np.array([0.3, 1.0])
    f = np.array([113.0, 47.0, 209.0])
    a = np.array([1.0, 0.8, 1e-3])
    ph_k = (-(7 * ph[0])) % np.pi
    harmonic = unit(texture(rng) * s1**7)
    kept, out = find_combinations(f, a, np.stack([s1, s2, harmonic]), 1.0,
                                  phases=np.append(ph, ph_k), fps=1000.0)
    assert kept.tolist() == [True, True, False] and out[0]["product"] == "7 x 113.0 Hz"
    kept, _ = find_combinations(f, a, np.stack([s1, s2, harmonic]), 1.0,
                                phases=np.append(ph, ph_k), fps=1000.0, max_harmonic=3)
    assert kept.all()  # not looked for
    kept, _ = find_combinations(f, a, np.stack([s1, s2, smooth_shape(rng)]), 1.0,
                                phases=np.append(ph, ph_k), fps=1000.0)
    assert kept.all()
