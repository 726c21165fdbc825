"""Recall over the true modes detectable in a video: the per-mode amplitudes a sample's truth
implies (:func:`true_mode_amplitudes`), the detectable set (by the Cramér-Rao ruler's SNR or
the amplitude floor) and the ``recall`` / ``recall_all`` keys of :func:`score_extraction`
and :func:`score_sample_extraction`."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))

from test_modes import modeset, pattern  # noqa: E402

from vvtbench.modes import ModeSet  # noqa: E402
from vvtbench.scoring.extraction import (  # noqa: E402
    DEFAULT_FLOOR_PX,
    score_extraction,
    score_sample_extraction,
    true_mode_amplitudes,
)

N = 16


def _ms(freqs, shapes, fps: float = 100.0, n_frames: int = 200) -> ModeSet:
    k = len(freqs)
    return modeset(freqs, np.asarray(shapes, np.float32).reshape(k, N, N, 2), fps=fps,
                   n_frames=n_frames)


def _truth() -> np.ndarray:
    pa, pb = pattern(N, "a"), pattern(N, "b")
    pc = np.stack([np.ones((N, N)), np.zeros((N, N))], -1)
    t = np.stack([pa, pb, pc])
    t[:, :2] = np.nan  # off the object
    return t


def test_mode_below_floor_not_expected_above_floor_expected() -> None:
    truth = _truth()
    f, z = [5.0, 8.0, 12.0], [0.0, 0.0, 0.0]
    amps = [0.01, 0.5 * DEFAULT_FLOOR_PX, 2 * DEFAULT_FLOOR_PX]  # 8 Hz is below the floor
    one = _ms([5.0], truth[:1])
    r = score_extraction(one, f, z, truth, 2.0, 20.0, amplitudes_px=amps)
    assert r["n_clusters_in_band"] == 3 and r["n_detectable"] == 2
    assert r["n_detectable_modes"] == 2 and r["n_matched_detectable"] == 1
    assert r["recall"] == pytest.approx(0.5) and r["recall_all"] == pytest.approx(1 / 3)
    assert r["amplitude_floor_px"] == DEFAULT_FLOOR_PX
    missed = {tuple(m["true"]): m for m in r["missed"]}
    assert set(missed) == {(1,), (2,)}
    assert not missed[(1,)]["detectable"] and missed[(2,)]["detectable"]
    assert missed[(1,)]["amplitude_px"] == pytest.approx(amps[1])
    # detecting the one above the floor completes the recall; the one below only adds to
    # recall_all
    two = _ms([5.0, 12.0], truth[[0, 2]])
    r2 = score_extraction(two, f, z, truth, 2.0, 20.0, amplitudes_px=amps)
    assert r2["recall"] == 1.0 and r2["recall_all"] == pytest.approx(2 / 3)
    assert r2["precision"] == 1.0 and r2["f1"] == pytest.approx(1.0)
    # a detection of the undetectable mode is still a true positive
    three = _ms([5.0, 8.0, 12.0], truth)
    r3 = score_extraction(three, f, z, truth, 2.0, 20.0, amplitudes_px=amps)
    assert r3["precision"] == 1.0 and r3["recall"] == 1.0 and r3["recall_all"] == 1.0
    # the floor is a parameter
    r4 = score_extraction(one, f, z, truth, 2.0, 20.0, amplitudes_px=amps, floor_px=0.005)
    assert r4["n_detectable"] == 1 and r4["recall"] == 1.0


def test_cluster_detectable_when_a_member_is_and_defaults() -> None:
    truth = _truth()
    f = [5.0, 5.2, 12.0]  # 5.0 and 5.2 closer than 1 / 2 s: one cluster
    amps = [1e-4, 0.02, 1e-4]
    r = score_extraction(_ms([5.1], truth[1:2]), f, None, truth, 2.0, 20.0,
                         amplitudes_px=amps)
    assert r["n_clusters_in_band"] == 2 and r["n_detectable"] == 1
    assert r["recall"] == 1.0 and r["recall_all"] == pytest.approx(0.5)
    # without amplitudes every cluster is expected: recall == recall_all (the old recall)
    r0 = score_extraction(_ms([5.1], truth[1:2]), f, None, truth, 2.0, 20.0)
    assert r0["recall"] == r0["recall_all"] == pytest.approx(0.5)
    assert r0["n_detectable"] == 2 and np.isnan(r0["amplitude_floor_px"])
    # nothing detectable: recall undefined, recall_all defined
    r5 = score_extraction(_ms([], np.zeros((0, N, N, 2))), f, None, truth, 2.0, 20.0,
                          amplitudes_px=[0.0, 0.0, 0.0])
    assert r5["n_detectable"] == 0 and np.isnan(r5["recall"]) and r5["recall_all"] == 0.0
    with pytest.raises(ValueError, match="amplitudes_px"):
        score_extraction(_ms([5.1], truth[1:2]), f, None, truth, 2.0, 20.0,
                         amplitudes_px=[1.0])


class _FakeSample:
    """The arrays of a sample with video that the amplitude measurement reads: two modes of
    four surface nodes, the first undamped, the second decaying, filmed at ``fps``."""

    def __init__(self, a=(2e-5, 3e-5), f=(5.0, 12.0), zeta=(0.0, 0.05), fps=100.0,
                 T=200, motion_scale=2.0) -> None:
        rng = np.random.default_rng(3)
        self.surface = rng.standard_normal((2, 4, 3))
        t = np.arange(T) / fps
        q = np.stack([ai * np.exp(-2 * np.pi * fi * zi * t)
                      * np.cos(2 * np.pi * fi * np.sqrt(1 - zi**2) * t)
                      for ai, fi, zi in zip(a, f, zeta, strict=True)], 1)  # (T, 2)
        im = _truth()[:2] * np.array([100.0, 300.0])[:, None, None, None]  # px per unit q
        self.data = {
            "modes/surface": self.surface,
            "transient/displacements": np.einsum("tn,nsc->tsc", q, self.surface)
            .astype(np.float32),
            "transient/times": t,
            "image/modes": im.astype(np.float32),
            "modes/frequencies_hz": np.asarray(f, float),
            "modes/damping_ratios": np.asarray(zeta, float),
        }
        self.info = {"video": {"motion_scale": motion_scale}}
        self.a, self.f, self.zeta, self.T, self.fps = a, f, zeta, T, fps
        self.scale = motion_scale

    def __contains__(self, name: str) -> bool:
        return name in self.data

    def __getitem__(self, name: str) -> np.ndarray:
        return np.asarray(self.data[name])

    @property
    def frequencies_hz(self) -> np.ndarray:
        return self.data["modes/frequencies_hz"]

    @property
    def damping_ratios(self) -> np.ndarray:
        return self.data["modes/damping_ratios"]


def test_true_mode_amplitudes_from_transient() -> None:
    s = _FakeSample()
    amp = true_mode_amplitudes(s, chunk_frames=64)
    g_true = s.scale * np.array([100.0, 300.0]) * np.sqrt(
        np.nanmax(np.sum(_truth()[:2] ** 2, -1).reshape(2, -1), axis=1))
    assert np.allclose(amp["gain_px"], g_true)
    assert amp["fit_residual"] < 1e-6
    assert np.allclose(amp["peak_px"], g_true * np.asarray(s.a), rtol=1e-5)
    # undamped: the line amplitude is the peak amplitude (to the leakage of a record of
    # whole periods: none); decaying: (1 - exp(-s T)) / (s T) of it
    assert amp["line_px"][0] == pytest.approx(amp["peak_px"][0], rel=1e-3)
    sT = 2 * np.pi * s.f[1] * s.zeta[1] * s.T / s.fps
    assert amp["line_px"][1] == pytest.approx(amp["peak_px"][1] * (1 - np.exp(-sT)) / sT,
                                              rel=0.05)


def test_score_sample_extraction_keys_and_detectable_set() -> None:
    # the second mode decays fast: 0.085 px at first, but its spectral line is weak
    s = _FakeSample(a=(1e-3, 1e-4), zeta=(0.0, 0.3))
    amp = true_mode_amplitudes(s)
    assert amp["peak_px"][1] > 10 * DEFAULT_FLOOR_PX
    floor = 0.5 * (amp["line_px"][1] + amp["peak_px"][1])
    truth = _truth()
    r = score_sample_extraction(s, _ms([5.0], truth[:1]), fmax=None, floor_px=floor)
    for k in ("precision", "recall", "recall_all", "n_detectable", "mean_rel_freq_error",
              "mean_mac", "n_detected", "n_true_in_band", "amplitudes_px"):
        assert k in r
    assert r["n_detectable"] == 1 and r["recall"] == 1.0
    assert r["recall_all"] == pytest.approx(0.5) and r["precision"] == 1.0
    assert r["amplitudes_px"] == pytest.approx(list(amp["line_px"]))
    # a lower floor expects the decaying mode too; precomputed amplitudes are reused
    r2 = score_sample_extraction(s, [_ms([5.0], truth[:1])], 20.0, floor_px=0.0,
                                 amplitudes=amp)
    assert r2["n_detectable"] == 2 and r2["recall"] == pytest.approx(0.5)
    with pytest.raises(ValueError, match="transient"):
        bare = _FakeSample()
        del bare.data["transient/displacements"]
        true_mode_amplitudes(bare)


def test_crb_snr_defines_detectability() -> None:
    """With the Cramér-Rao ruler the SNR, not the amplitude floor, decides what is expected."""
    from vvtbench.render.crb import detection_snr_threshold

    truth = _truth()
    f, z = [5.0, 8.0, 12.0], [0.0, 0.0, 0.0]
    amps = [0.01, 0.01, 1e-4]  # above, above, below the 0.001 px floor
    th = detection_snr_threshold(200)
    snr = [50.0, 0.5 * th, 2.0 * th]  # the 8 Hz mode is below the limit, 12 Hz above
    one = _ms([5.0], truth[:1])
    r = score_extraction(one, f, z, truth, 2.0, 20.0, amplitudes_px=amps, crb_snr=snr,
                         crb_threshold=th)
    assert r["detectability"] == "crb" and r["crb_threshold"] == th
    assert r["n_detectable"] == 2 and r["n_below_limit"] == 1
    assert r["recall"] == pytest.approx(0.5) and r["recall_all"] == pytest.approx(1 / 3)
    assert np.isnan(r["amplitude_floor_px"])
    missed = {tuple(m["true"]): m for m in r["missed"]}
    assert not missed[(1,)]["detectable"] and missed[(2,)]["detectable"]
    assert missed[(1,)]["crb_snr"] == pytest.approx(0.5 * th)
    old = score_extraction(one, f, z, truth, 2.0, 20.0, amplitudes_px=amps)
    assert old["detectability"] == "amplitude_floor" and old["n_detectable"] == 2
    assert old["recall"] == pytest.approx(0.5) and old["n_below_limit"] == 0
    assert score_extraction(one, f, z, truth, 2.0, 20.0)["detectability"] == "all"
    with pytest.raises(ValueError, match="crb_threshold"):
        score_extraction(one, f, z, truth, 2.0, 20.0, crb_snr=snr)


def test_score_sample_extraction_uses_the_ruler_when_the_sample_has_it() -> None:
    from vvtbench.render.crb import detection_snr_threshold

    s = _FakeSample(a=(1e-3, 1e-4), zeta=(0.0, 0.3))
    truth = _truth()
    old = score_sample_extraction(s, _ms([5.0], truth[:1]), fmax=None)
    assert old["detectability"] == "amplitude_floor"
    s.info["video"]["frames"] = s.T
    th = detection_snr_threshold(s.T)
    s.data["modes/crb_snr"] = np.array([2 * th, 1.01 * th])
    r = score_sample_extraction(s, _ms([5.0], truth[:1]), fmax=None)
    assert r["detectability"] == "crb" and r["crb_threshold"] == pytest.approx(th)
    assert r["n_detectable"] == 2 and r["recall"] == pytest.approx(0.5)
    s.data["modes/crb_snr"] = np.array([2 * th, 0.99 * th])
    r = score_sample_extraction(s, _ms([5.0], truth[:1]), fmax=None)
    assert r["n_detectable"] == 1 and r["recall"] == 1.0 and r["n_below_limit"] == 1
    r = score_sample_extraction(s, _ms([5.0], truth[:1]), fmax=None, use_crb=False)
    assert r["detectability"] == "amplitude_floor"


# --------------------------------------------------------------------------- shoulders
def _two_modes(f1: float, f2: float, a2: float, zeta: float = 0.0, seed: int = 0):
    fps, T, n = 200.0, 400, 24
    t = np.arange(T)[:, None, None, None] / fps
    rng = np.random.default_rng(seed)
    d = 0.3 * np.exp(-2 * np.pi * f1 * zeta * t) * np.cos(2 * np.pi * f1 * t) * pattern(n, "a")
    d = d + a2 * np.cos(2 * np.pi * f2 * t + 0.7) * pattern(n, "b")
    return d + 1e-3 * rng.standard_normal((T, n, n, 2)), fps


@pytest.mark.parametrize("f1, f2, a2", [(20.1, 21.5, 0.03), (20.25, 21.5, 0.1),
                                        (20.25, 22.0, 0.01)])
def test_resolved_shoulder_is_a_mode(f1: float, f2: float, a2: float) -> None:
    """A weak mode 1.3-1.9 Hz (2.5-3.5 bins) from a strong one stands on its flank with a
    prominence of 0.25-0.42 decades (< 0.5): kept as a resolved shoulder (its own shape)."""
    from vvtbench.modes import modes_from_displacements

    d, fps = _two_modes(f1, f2, a2)
    old = modes_from_displacements(d, fps, shoulder_prominence=None)
    assert len(old) == 1
    new = modes_from_displacements(d, fps)
    assert len(new) == 2
    i = int(np.argmin(np.abs(new.frequencies_hz - f2)))
    assert abs(new.frequencies_hz[i] - f2) < fps / 400
    s, pb = new.shapes[i].ravel(), pattern(24, "b").ravel()
    assert (s @ pb) ** 2 / ((s @ s) * (pb @ pb)) > 0.95
    (log,) = new.metadata["shoulders"]
    assert log["kept"] and log["mac"] < 0.1


@pytest.mark.parametrize("zeta", [0.0, 0.01, 0.03])
def test_flanks_and_sidelobes_are_no_modes(zeta: float) -> None:
    """A single strong mode, on and between bins, undamped or decaying: no second mode."""
    from vvtbench.modes import modes_from_displacements

    for k, f1 in enumerate(np.arange(20.0, 20.5, 0.1)):
        d, fps = _two_modes(f1, 30.0, 0.0, zeta=zeta, seed=k)
        ms = modes_from_displacements(d, fps)
        assert len(ms) == 1, (f1, ms.frequencies_hz, ms.metadata["shoulders"])


def test_doctests():
    import doctest

    from vvtbench.modes import peaks
    from vvtbench.scoring import extraction as extraction_scores

    for module in (extraction_scores, peaks):
        result = doctest.testmod(module)
        assert result.attempted > 0 and result.failed == 0, module.__name__
