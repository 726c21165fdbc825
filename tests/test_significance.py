"""Peak significance (noise floor, false-alarm rate, drift) and the extraction scores.

Synthetic videos: the band-limited speckle of ``tests/test_modes.py`` warped by smooth
sub-pixel modes; the scoring is checked on hand-made cases and on a tiny rendered cube.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from test_modes import Speckle, modeset, pattern, video  # noqa: E402

from vvtbench.modes import ModeSet, extract_modes, modes_from_displacements  # noqa: E402
from vvtbench.modes.peaks import pick_peaks  # noqa: E402
from vvtbench.modes.significance import noise_floor  # noqa: E402
from vvtbench.scoring.extraction import (  # noqa: E402
    clusters_by_resolution,
    score_extraction,
    subspace_mac,
)


# --------------------------------------------------------------------------- noise floor
@pytest.mark.parametrize("nu", [2, 16])
def test_false_alarm_rate_on_pure_noise(nu: int) -> None:
    """Chi-square spectra with a sloping level: the fraction of spectra with a bin above
    the threshold is at most the stated false-alarm probability (0.1 here, to measure it;
    the bounds on nu and the bin correlation allowance make it conservative, ~0.03-0.06)."""
    rng = np.random.default_rng(nu)
    F, trials, pfa = 400, 600, 0.1
    level = np.logspace(0, -2, F)
    hits, nus = 0, []
    for _ in range(trials):
        p = level * rng.chisquare(nu, F) / nu
        nf = noise_floor(p, false_alarm=pfa)
        nus.append(nf.nu)
        hits += bool(np.any(p[1:] > nf.threshold()[1:]))
    assert np.median(nus) == pytest.approx(nu, rel=0.35)
    assert 0.005 <= hits / trials <= 0.13, hits / trials


def test_exponential_threshold_formula() -> None:
    """nu = 2: threshold factor log2(1/p) with p = 1 - (1 - P_fa)**(1/N) for a known floor,
    raised for the scatter of a 65-bin running median (16.6 -> 22.4 for N = 1000)."""
    rng = np.random.default_rng(0)
    p = rng.exponential(size=1001)
    nf = noise_floor(p, false_alarm=0.01)
    assert nf.nu == 2.0 and nf.n_bins == 1000
    per_bin = 1 - (1 - 0.01) ** (1 / nf.n_bins)
    assert np.log2(1 / per_bin) == pytest.approx(16.6, abs=0.05)
    assert nf.factor == pytest.approx(22.4, abs=0.1)


def test_line_in_noise_kept_noise_peaks_dropped() -> None:
    rng = np.random.default_rng(3)
    F, fps = 513, 100.0
    f = np.linspace(0, fps / 2, F)
    p = rng.exponential(size=F)
    p[200] += 300.0
    off = pick_peaks(f, p, fps, prominence=0.3)
    on = pick_peaks(f, p, fps, prominence=0.3, false_alarm=0.01)
    assert len(off) > 5
    assert on.bins.tolist() == [200] and on.floor_ratio[0] > on.noise.factor


def test_drift_below_resolution_excluded() -> None:
    """A slow drift (power in the first bins) is no mode with the default min_bin = 3."""
    fps, T, n = 100.0, 300, 16
    t = np.arange(T)[:, None, None, None] / fps
    d = 0.05 * t / t.max() * pattern(n, "b") + 0.01 * np.cos(2 * np.pi * 20.0 * t) * pattern(
        n, "a")
    old = modes_from_displacements(d, fps, false_alarm=None, min_bin=1)
    new = modes_from_displacements(d, fps)
    assert np.any(old.frequencies_hz < 3 * fps / T)
    assert np.all(new.frequencies_hz >= 3 * fps / T)
    assert np.any(np.abs(new.frequencies_hz - 20.0) < fps / T)


@pytest.fixture(scope="module")
def sp128() -> Speckle:
    return Speckle(128, seed=5)


@pytest.mark.parametrize("amps", [(0.01, 0.005), (0.002, 0.001), (0.001, 0.001)])
def test_clean_video_at_most_one_false_mode(sp128: Speckle, amps) -> None:
    """Two smooth modes (0.01-0.001 px) in a speckle video with faint sensor noise (0.1 %
    of the intensity range): both kept, at most one false mode."""
    T, fps = 256, 100.0
    df = fps / T
    fa, fb = 21.3 * df, 52.6 * df
    frames = video(sp128, [(pattern(128, "a"), amps[0], fa), (pattern(128, "b"), amps[1], fb)],
                   T, fps)
    rng = np.random.default_rng(1)
    frames += (1e-3 * np.ptp(sp128.ref) * rng.standard_normal(frames.shape)).astype("f4")
    ms = extract_modes(frames, fps)
    f = ms.frequencies_hz
    assert all(np.any(np.abs(f - x) <= df) for x in (fa, fb)), f
    false = [x for x in f if min(abs(x - fa), abs(x - fb)) > df]
    assert len(false) <= 1, f
    assert ms.metadata["noise_floor"]["false_alarm"] == 0.01
    assert ms.metadata["weighting"] == "noise" and ms.metadata["shape_attenuation"] is None


# --------------------------------------------------------------------------- scoring
def _ms(freqs, shapes, damping=None) -> ModeSet:
    k = len(freqs)
    return modeset(freqs, np.asarray(shapes, np.float32).reshape(k, *np.shape(shapes)[1:]),
                   damping=damping)


def test_clusters_and_subspace_mac() -> None:
    assert clusters_by_resolution([5.0, 5.1, 7.0, 9.0, 9.4], 0.5) == [[0, 1], [2], [3, 4]]
    a, b = np.array([1.0, 0, 0]), np.array([0, 1.0, 0])
    assert subspace_mac(a + b, np.stack([a, b])) == pytest.approx(1.0)
    assert subspace_mac(a + b, a[None]) == pytest.approx(0.5)


def test_score_extraction_hand_made() -> None:
    n = 16
    pa, pb = pattern(n, "a"), pattern(n, "b")
    pc = np.stack([np.ones((n, n)), np.zeros((n, n))], -1)
    truth = np.stack([pa, pb, pc, pa])
    truth[:, :2] = np.nan  # off the object
    f_true = [5.0, 5.1, 8.0, 30.0]  # 5.0 and 5.1 closer than 1/T = 0.5 Hz; 30 Hz beyond fmax
    z_true = [0.01, 0.01, 0.02, 0.03]
    rng = np.random.default_rng(0)
    det = _ms(
        [5.05, 8.2, 12.0, 8.1],
        [0.6 * pa + 0.8 * pb, pc + 0.01 * rng.standard_normal(pc.shape), pa, pa],
        damping=[0.012, 0.018, 0.5, 0.0],
    )
    r = score_extraction(det, f_true, z_true, truth, duration_s=2.0, fmax=20.0)
    assert r["n_true_in_band"] == 3 and r["n_clusters_in_band"] == 2
    assert r["n_detected"] == 4 and r["n_matched"] == 2
    assert r["precision"] == pytest.approx(0.5)
    assert r["recall"] == pytest.approx(1.0) and r["recall_modes"] == pytest.approx(1.0)
    pairs = {m["detected"]: m["true"] for m in r["matching"]}
    assert pairs == {0: [0, 1], 1: [2]}  # one-to-one: the 8.1 Hz duplicate (MAC 0) is false
    assert sorted(u[1] for u in r["unmatched"]) == [2, 3]
    assert r["mean_abs_freq_error_hz"] == pytest.approx((0.05 + 0.2) / 2)
    # the 5.05 Hz mixture is closer in shape to the 5.1 Hz mode (MAC 0.64), its frequency error
    # is measured against that mode
    assert r["mean_rel_freq_error"] == pytest.approx((0.05 / 5.1 + 0.2 / 8.0) / 2)
    assert r["mean_abs_damping_error"] == pytest.approx((0.002 + 0.002) / 2)
    assert r["mean_mac"] > 0.99
    # a wrong shape at the right frequency is no match
    bad = _ms([8.0], [pa])
    r2 = score_extraction(bad, f_true, z_true, truth, 2.0, 20.0)
    assert r2["n_matched"] == 0 and r2["precision"] == 0.0 and r2["recall"] == 0.0
    # nothing detected: precision undefined, recall 0
    r3 = score_extraction(_ms([], np.zeros((0, n, n, 2))), f_true, z_true, truth, 2.0, 20.0)
    assert np.isnan(r3["precision"]) and r3["recall"] == 0.0
    # several sets pooled
    r4 = score_extraction([det, bad], f_true, z_true, truth, 2.0, 20.0)
    assert r4["n_detected"] == 5 and r4["n_matched"] == 2 and r4["recall"] == 1.0


def test_modes_closer_than_resolution_resolved_by_two_detections() -> None:
    """Two true modes a fraction of a bin apart (one cluster) found as two lines, each with its
    own mode's shape, are two true positives; a copy of either is not a third."""
    n = 16
    pa, pb = pattern(n, "a"), pattern(n, "b")
    x = np.arange(n)
    pc = np.stack(np.broadcast_arrays(np.cos(4 * np.pi * x / n)[None, :],
                                      np.sin(4 * np.pi * x / n)[:, None]), -1)
    truth = np.stack([pa, pb, pc])
    f_true = [5.0, 5.3, 5.55]  # gaps 0.3 and 0.25 Hz < 1/T = 0.5 Hz: one chained cluster
    r = score_extraction(_ms([5.02, 5.31], [pa, pb]), f_true, None, truth, 2.0, 20.0)
    assert r["n_clusters_in_band"] == 1
    assert r["n_matched"] == 2 and r["precision"] == 1.0 and r["recall"] == 1.0
    assert sorted(m["nearest_true"] for m in r["matching"]) == [0, 1]
    assert {m["kind"] for m in r["matching"]} == {"mode"}
    assert r["mean_abs_freq_error_hz"] == pytest.approx((0.02 + 0.01) / 2)
    dup = score_extraction(_ms([5.02, 5.31, 5.03], [pa, pb, pa]), f_true, None, truth, 2.0, 20.0)
    assert dup["n_matched"] == 2 and dup["precision"] == pytest.approx(2 / 3)
    # a mixture no single mode explains still matches the cluster, once
    mix = score_extraction(_ms([5.2, 5.25], [pa + pb + pc, pa + pb + pc]), f_true, None, truth,
                           2.0, 20.0)
    assert mix["n_matched"] == 1 and [m["kind"] for m in mix["matching"]] == ["cluster"]


def test_score_extraction_at_vertices() -> None:
    n = 16
    pa = pattern(n, "a")
    uv = np.array([[3.0, 4.0], [8.5, 2.25], [12.0, 12.0], [5.5, 10.0]])
    from vvtbench.modes import sample_modes

    gamma = sample_modes(pa[None], uv)
    r = score_extraction(_ms([7.0], [pa]), [7.1], None, gamma, 2.0, 20.0, uv=uv)
    assert r["n_matched"] == 1 and r["mean_mac"] == pytest.approx(1.0)
    assert np.isnan(r["mean_abs_damping_error"])


def test_score_extraction_on_rendered_cube(tmp_path_factory) -> None:
    """A tiny rendered cube (6^3 cells, 1.5 s at 200 fps, 256^2): the extracted modes are
    scored against the sample's truth."""
    from bench_motion_e2e import make_scene

    from vvtbench.samples import generate as gen
    from vvtbench.samples import reader as ds

    scene = make_scene("jello_cube_defect_top", duration=1.5, fps=200.0, resolution=256,
                       cells=6, n_modes=12)
    path = gen.generate(scene, tmp_path_factory.mktemp("cube"), progress=False)
    s = ds.open_sample(path)
    ms = extract_modes(s.video_path, s.fps, workers=2)
    fmax = float(np.max(s.frequencies_hz))
    r = score_extraction(ms, s.frequencies_hz, s.damping_ratios, s["image/modes"],
                         ms.n_frames / ms.fps, fmax)
    assert r["n_detected"] >= 4
    assert r["precision"] >= 0.8, r
    assert r["recall"] >= 0.5, r
    assert r["mean_mac"] >= 0.85
    assert r["mean_rel_freq_error"] < 0.02


# ------------------------------------------------------------------ noise weighting
def _strip_video(seed: int, amp: float) -> np.ndarray:
    """16^2 px, 512 frames at 200 fps: a smooth 23.3 Hz mode of ``amp`` px everywhere, white
    motion noise of 0.002 px, and 0.2 px in a 4-px strip (like an occlusion edge)."""
    T, H, W, fps = 512, 16, 16, 200.0
    t = np.arange(T) / fps
    y, x = np.mgrid[0:H, 0:W] / 15.0
    shape = np.stack([np.sin(np.pi * x) * np.sin(np.pi * y),
                      0.5 * np.cos(np.pi * x) * np.sin(np.pi * y)], -1)
    sd = np.full((H, W), 0.002)
    sd[:, :4] = 0.2
    rng = np.random.default_rng(seed)
    return (amp * np.sin(2 * np.pi * 23.3 * t)[:, None, None, None] * shape[None]
            + sd[None, :, :, None] * rng.standard_normal((T, H, W, 2)))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_noise_weighting_finds_a_mode_that_noisy_pixels_hide(seed):
    from vvtbench.modes.extract import modes_from_displacements, noise_weights
    from vvtbench.modes.spectrum import pixel_noise_power

    d = _strip_video(seed, 0.001)
    noise = pixel_noise_power(d)
    assert noise[:, :4].mean() > 1000 * noise[:, 4:].mean()
    w = noise_weights(np.ones(noise.shape), noise)
    uniform = modes_from_displacements(d, 200.0, max_modes=10)
    weighted = modes_from_displacements(d, 200.0, weights=w, max_modes=10)
    assert len(uniform.frequencies_hz) == 0
    assert len(weighted.frequencies_hz) == 1
    assert abs(weighted.frequencies_hz[0] - 23.3) < 0.4
    # spectrum_weights pick the peak; the coherence test then uses ``weights`` (uniform
    # here), under which the noisy strip makes the field rough
    split = modes_from_displacements(d, 200.0, spectrum_weights=w, max_modes=10)
    (rejected,) = split.metadata["rejected"]
    assert abs(rejected["frequency_hz"] - 23.3) < 0.4 and rejected["reason"] == "incoherent"
    empty = _strip_video(seed, 0.0)
    ws = noise_weights(np.ones(noise.shape), pixel_noise_power(empty))
    assert len(modes_from_displacements(empty, 200.0, weights=ws, max_modes=10)
               .frequencies_hz) == 0
