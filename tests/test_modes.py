"""Tests of mode identification (spectrum, peaks, damping, shake, merge, sampling, camera).

Synthetic videos are made here, not by the renderer: a seeded band-limited periodic speckle
image warped by known per-pixel sub-pixel displacement fields (third-order Taylor expansion
with exact spectral derivatives; error ~|u|**4, negligible at the amplitudes used).
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from vvtbench.cli.extract import main_extract
from vvtbench.modes import (
    DisplacementStore,
    ModeSet,
    check_band,
    damping_half_power,
    damping_lorentzian,
    estimate_camera,
    extract_modes,
    load_clicks,
    mac,
    merge_modesets,
    modes_from_displacements,
    motion_power_spectrum,
    observation_operator,
    open_video,
    pick_peaks,
    sample_field,
    sample_modes,
)
from vvtbench.modes.peaks import align_phase, distortion_products, roughness
from vvtbench.render.camera import Camera

BORDER = 10


class Speckle:
    """Band-limited periodic random image, warped by a Taylor expansion of exact derivatives."""

    def __init__(self, n: int, seed: int = 0, sigma: float = 1.0) -> None:
        rng = np.random.default_rng(seed)
        wy = 2 * np.pi * np.fft.fftfreq(n)[:, None]
        wx = 2 * np.pi * np.fft.fftfreq(n)[None, :]
        F = np.fft.fft2(rng.standard_normal((n, n)))
        F *= np.exp(-0.5 * (np.hypot(wx, wy) * sigma) ** 2)
        F[n // 2, :] = 0.0
        F[:, n // 2] = 0.0
        self.n = n
        self.der = {
            (i, j): np.fft.ifft2(F * (1j * wx) ** i * (1j * wy) ** j).real
            for i in range(4)
            for j in range(4 - i)
        }
        self.ref = self.der[(0, 0)]

    def warp(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """``I(x - u, y - v)``: content displaced by ``(u, v)`` (right, down)."""
        out = self.ref.copy()
        for (i, j), d in self.der.items():
            if i + j:
                out += (-1) ** (i + j) / (math.factorial(i) * math.factorial(j)) * u**i * v**j * d
        return out


def pattern(n: int, which: str) -> np.ndarray:
    """Smooth periodic ``(n, n, 2)`` displacement patterns with max |component| = 1."""
    x = np.arange(n)[None, :] * np.ones((n, 1))
    y = np.arange(n)[:, None] * np.ones((1, n))
    cx, sy = np.cos(2 * np.pi * x / n), np.sin(2 * np.pi * y / n)
    if which == "a":
        return np.stack([cx, 0.5 * sy], axis=-1)
    return np.stack([sy, cx], axis=-1)


def video(sp: Speckle, modes: list[tuple[np.ndarray, float, float]], T: int, fps: float):
    """Frames of the speckle displaced by ``sum_m amp_m * pattern_m * cos(2 pi f_m t)``."""
    t = np.arange(T) / fps
    out = np.empty((T, sp.n, sp.n), np.float32)
    for k in range(T):
        d = sum(a * p * np.cos(2 * np.pi * f * t[k]) for p, a, f in modes)
        out[k] = sp.warp(d[..., 0], d[..., 1])
    return out


def interior(ms: ModeSet) -> np.ndarray:
    n = ms.image_shape[0]
    m = np.zeros((n, n), bool)
    m[BORDER:-BORDER, BORDER:-BORDER] = True
    return m & (ms.confidence > 0.1 * np.median(ms.confidence))


def nearest(ms: ModeSet, f: float) -> int:
    return int(np.argmin(np.abs(ms.frequencies_hz - f)))


@pytest.fixture(scope="module")
def sp128() -> Speckle:
    return Speckle(128)


# --------------------------------------------------------------------------- accuracy on video
@pytest.mark.parametrize(
    "bins,noise", [(20.0, 0.0), (20.4, 0.0), (20.4, 0.005)], ids=["on-bin", "off-bin", "noisy"]
)
def test_amplitude_and_frequency_at_0p01_px(sp128: Speckle, bins: float, noise: float) -> None:
    """0.01 px at 20 bins, at 20.4 bins (0.4 bin scalloping) and with camera noise (white,
    0.5 % of the image's intensity range per pixel and frame, ~1.3 grey levels of 8 bits:
    -1.3 % here, -0.7 % without noise; with the first frame as the reference and no
    refinement of the phase it was -2.6 %)."""
    T, fps = 128, 100.0
    df = fps / T
    f0 = bins * df
    true = pattern(128, "a")
    frames = video(sp128, [(true, 0.01, f0)], T, fps)
    if noise:
        rng = np.random.default_rng(7)
        frames += (noise * np.ptp(sp128.ref) * rng.standard_normal(frames.shape)).astype("f4")
    ms = extract_modes(frames, fps, batch=32)
    if not noise:
        assert len(ms) == 1  # no spurious peaks in a noise-free video
    i = int(np.argmax(ms.amplitudes_px))
    assert abs(ms.frequencies_hz[i] - f0) <= df
    assert ms.peak_bins[i] == round(bins)
    rec = ms.amplitudes_px[i] * ms.shapes[i]
    m = interior(ms)
    ratio = np.sum(rec[m] * true[m]) / np.sum(true[m] * true[m]) / 0.01
    assert abs(abs(ratio) - 1.0) < 0.05, ratio
    assert mac(rec[m], true[m]) > (0.9 if noise else 0.98)
    assert not ms.camera_shake.any()


def test_the_reference_is_the_temporal_mean_of_the_record(tmp_path) -> None:
    """A first pass gives the extractor the mean frame: an array is read twice, a one-shot
    iterable is kept (here on disk) for the second pass, and both give the same modes."""
    T, fps = 64, 100.0
    sp = Speckle(64)
    frames = video(sp, [(pattern(64, "a"), 0.02, 10 * fps / T)], T, fps)
    frames += (0.005 * np.ptp(sp.ref)
               * np.random.default_rng(3).standard_normal(frames.shape)).astype("f4")
    a = extract_modes(frames, fps, batch=16)
    assert a.metadata["motion"]["reference"] == {"kind": "mean", "frames": T}
    b = extract_modes(iter(list(frames)), fps, batch=16, memory_budget=0, tmpdir=str(tmp_path))
    assert b.metadata["motion"]["reference"] == {"kind": "mean", "frames": T}
    assert np.array_equal(a.frequencies_hz, b.frequencies_hz)
    assert np.array_equal(a.shapes, b.shapes)
    assert not list(tmp_path.iterdir())  # the kept frames are deleted
    c = extract_modes(frames, fps, batch=16, reference="first")
    assert c.metadata["motion"]["reference"] == {"kind": "first", "frames": 1}
    with pytest.raises(ValueError, match="reference"):
        extract_modes(frames, fps, reference="median")


def test_frame_spool_keeps_the_order_in_ram_and_on_disk(tmp_path) -> None:
    from vvtbench.video.files import FrameSpool, mean_frame

    frames = np.random.default_rng(0).random((7, 5, 6)).astype("f4")
    for budget in (1 << 20, 3 * frames[0].nbytes, 0):
        with FrameSpool(budget, str(tmp_path), chunk_bytes=2 * frames[0].nbytes) as spool:
            mean, n = mean_frame(f for f in frames if spool.append(f) is None)
            assert n == 7 and np.allclose(mean, frames.mean(axis=0))
            assert spool.on_disk == (budget < frames.nbytes)
            assert np.array_equal(np.stack(list(spool)), frames)
            assert np.array_equal(np.stack(list(spool)), frames)  # read again
        assert not list(tmp_path.iterdir())
    with pytest.raises(ValueError, match="no frames"):
        mean_frame([])


def test_two_superposed_modes_are_separated(sp128: Speckle) -> None:
    T, fps = 128, 100.0
    df = fps / T
    pa, pb = pattern(128, "a"), pattern(128, "b")
    frames = video(sp128, [(pa, 0.02, 20 * df), (pb, 0.015, 33 * df)], T, fps)
    ms = extract_modes(frames, fps, max_modes=5)
    assert len(ms) == 2
    m = interior(ms)
    for p, f in ((pa, 20 * df), (pb, 33 * df)):
        i = nearest(ms, f)
        assert abs(ms.frequencies_hz[i] - f) <= df
        assert mac(ms.shapes[i][m], p[m]) >= 0.95


# --------------------------------------------------------------------------- spectra and peaks
def _decay(zeta: float, f0: float, T: int, fps: float, seed: int = 1) -> np.ndarray:
    t = np.arange(T) / fps
    w0 = 2 * np.pi * f0
    x = np.exp(-zeta * w0 * t) * np.cos(w0 * math.sqrt(1 - zeta**2) * t + 0.3)
    rng = np.random.default_rng(seed)
    d = np.zeros((T, 3, 3, 2))
    d[..., 0] = x[:, None, None] * rng.standard_normal((3, 3))
    return d + 1e-5 * rng.standard_normal(d.shape)


@pytest.mark.parametrize("zeta", [0.01, 0.02, 0.04])
def test_damping_of_decaying_sinusoid(zeta: float) -> None:
    fps, T = 200.0, 1000
    f, P = motion_power_spectrum(_decay(zeta, 20.0, T, fps), fps)
    pk = pick_peaks(f, P, fps, max_peaks=1)
    k = int(pk.bins[0])
    z_l, fd, _ = damping_lorentzian(f, P, k)
    assert abs(z_l / zeta - 1) < 0.10
    assert abs(fd - 20.0) < fps / T
    assert abs(damping_half_power(f, P, k) / zeta - 1) < 0.10


@pytest.mark.parametrize("window", ["none", "hann"])
@pytest.mark.parametrize("fill", [0.0, np.inf, np.nan])
def test_a_degenerate_spectrum_gives_no_damping_and_no_error(fill, window) -> None:
    f = np.linspace(0.0, 100.0, 501)
    with np.errstate(all="ignore"):
        zeta, fd, _ = damping_lorentzian(f, np.full(501, fill), 200, window=window,
                                         n_frames=1000)
    assert math.isnan(zeta) and fd == 40.0


@pytest.mark.parametrize("window", ["none", "hann"])
@pytest.mark.parametrize("nu, gamma, image", [(50.3, 0.7, 0j), (2.4, 0.3, 0.3 - 0.4j),
                                               (498.6, 0.05, -0.6 + 0.2j)])
def test_decay_power_derivatives_match_central_differences(nu, gamma, image, window) -> None:
    """The damping fit's analytic Jacobian against central differences of the model power,
    near a peak, near DC (where the negative-frequency image matters) and near Nyquist."""
    from vvtbench.modes.damping import _decay_power, _decay_power_grad

    T = 1000
    bins = np.arange(max(int(nu) - 8, 1), min(int(nu) + 9, T // 2 + 1)).astype(float)
    power, grad = _decay_power_grad(nu, gamma, bins, T, window, image)
    np.testing.assert_allclose(power, _decay_power(nu, gamma, bins, T, window, image),
                               rtol=1e-12)
    h = 1e-6
    steps = [(h, 0, 0), (0, h, 0), (0, 0, h), (0, 0, 1j * h)]
    for j, (a, b, c) in enumerate(steps):
        up = _decay_power(nu + a, gamma + b, bins, T, window, image + c)
        down = _decay_power(nu - a, gamma - b, bins, T, window, image - c)
        numeric = (up - down) / (2 * h)
        scale = np.abs(power).max()
        np.testing.assert_allclose(grad[:, j], numeric, rtol=0, atol=1e-5 * scale,
                                   err_msg=f"column {j}")


@pytest.mark.parametrize("zeta", [0.005, 0.01, 0.02, 0.04])
def test_damping_through_default_hann_path(zeta: float) -> None:
    """modes_from_displacements with its defaults (Hann window): a free decay half a bin
    off the bin centres, its decay from 1.6 s down to 0.2 s in a 5 s record."""
    fps, T, n, f0 = 200.0, 1000, 16, 20.3
    t = np.arange(T)[:, None, None, None] / fps
    w0 = 2 * np.pi * f0
    x = np.exp(-zeta * w0 * t) * np.cos(w0 * math.sqrt(1 - zeta**2) * t + 0.7)
    rng = np.random.default_rng(4)
    d = 0.05 * x * pattern(n, "a") + 2e-4 * rng.standard_normal((T, n, n, 2))
    ms = modes_from_displacements(d, fps)
    assert len(ms) == 1 and ms.metadata["window"] == "hann"
    fd = f0 * math.sqrt(1 - zeta**2)
    assert abs(ms.frequencies_hz[0] - fd) < fps / T
    assert abs(ms.damping[0] / zeta - 1) < 0.10, ms.damping[0]
    assert abs(ms.damping_half_power[0] / zeta - 1) < 0.15, ms.damping_half_power[0]


def test_power_spectrum_streamed_from_disk_matches_ram() -> None:
    rng = np.random.default_rng(0)
    d = rng.standard_normal((101, 17, 13, 2)).astype(np.float32)
    d64 = d.astype(np.float64)
    X = np.fft.rfft(d64 - d64.mean(0), axis=0)
    w = rng.uniform(0, 1, (17, 13))
    ref = np.einsum("fhwc,hw->f", np.abs(X) ** 2, w)
    with DisplacementStore(memory_budget=20_000, tile_columns=50) as st:
        for i in range(0, 101, 7):
            st.append(d[i : i + 7])
        assert st.on_disk
        f, P = motion_power_spectrum(st, 50.0, weights=w, block_bytes=1)
        np.testing.assert_allclose(P, ref, rtol=1e-10, atol=1e-9)
        np.testing.assert_allclose(f[1], 50.0 / 101)
        np.testing.assert_array_equal(st.array(), d)
    assert st.path is not None and not __import__("os").path.exists(st.path)


def test_nyquist_error() -> None:
    f = np.fft.rfftfreq(100, 1 / 100.0)
    with pytest.raises(ValueError, match="Nyquist"):
        pick_peaks(f, np.ones_like(f), 100.0, fmax=60.0)
    with pytest.raises(ValueError, match="Nyquist"):
        check_band(100.0, None, 50.1)
    frames = np.zeros((4, 16, 16), np.float32)
    with pytest.raises(ValueError, match="fps/2 = 25"):
        extract_modes(frames, 100.0, fmax=30.0, average=2)


def test_phase_alignment_not_blind_real_part() -> None:
    rng = np.random.default_rng(3)
    shape = rng.standard_normal((8, 8, 2))
    z = shape * np.exp(1j * 1.3)  # Re() alone would lose most of the energy (cos 1.3 = 0.27)
    real, _, coll = align_phase(z)
    assert mac(real, shape) > 1 - 1e-12
    assert coll == pytest.approx(1.0)
    assert np.linalg.norm(real) == pytest.approx(np.linalg.norm(shape))


def test_camera_shake_flagged_and_excluded() -> None:
    fps, T, n = 100.0, 256, 32
    t = np.arange(T) / fps
    rng = np.random.default_rng(0)
    local = pattern(n, "a")
    d = 0.05 * np.cos(2 * np.pi * 12.5 * t)[:, None, None, None] * np.array([0.8, 0.6])
    d = d + 0.02 * np.cos(2 * np.pi * 25.0 * t)[:, None, None, None] * local
    d = d + 1e-3 * rng.standard_normal((T, n, n, 2))
    ms = modes_from_displacements(d, fps)
    assert len(ms) == 1 and abs(ms.frequencies_hz[0] - 25.0) < fps / T
    assert [round(r["frequency_hz"], 1) for r in ms.metadata["rejected"]] == [12.5]
    allm = modes_from_displacements(d, fps, keep_camera_shake=True)
    assert len(allm) == 2
    i = nearest(allm, 12.5)
    assert allm.camera_shake[i] and allm.shake_mac[i] > 0.9
    assert not allm.camera_shake[1 - i] and allm.shake_mac[1 - i] < 0.5


def test_harmonics_of_camera_shake_are_no_modes() -> None:
    """A rigid sub-pixel translation measured with a texture-dependent error: the error's
    harmonics are smooth but not translations, so the shake test passes them; they are
    products of the shake and are rejected as such (a pure-shake video has no modes)."""
    from scipy.ndimage import gaussian_filter

    fps, T, n = 100.0, 512, 32
    t = np.arange(T) / fps
    rng = np.random.default_rng(1)
    err = gaussian_filter(rng.standard_normal((n, n, 2)), (6, 6, 0), mode="wrap")
    err *= 0.005 / np.sqrt(np.mean(err**2))            # 0.005 px rms: 1.7 % of the motion
    shake = 0.3 * np.cos(2 * np.pi * 7.0 * t)
    d = shake[:, None, None, None] * np.array([1.0, 0.0])
    d = d + (np.cos(2 * np.pi * 14.0 * t))[:, None, None, None] * err
    d = d + 1e-4 * rng.standard_normal((T, n, n, 2))
    ms = modes_from_displacements(d, fps, keep_camera_shake=True, reject_distortion=False)
    i = nearest(ms, 14.0)
    assert not ms.camera_shake[i] and roughness(ms.shapes[i]) < 0.1   # passes both tests
    ms = modes_from_displacements(d, fps)
    assert len(ms) == 0
    why = {round(r["frequency_hz"]): r for r in ms.metadata["rejected"]}
    assert why[7]["reason"] == "camera_shake"
    assert why[14]["reason"] == "distortion" and why[14]["kind"] == "harmonic"


@pytest.mark.parametrize("line_fit", [False, True])
def test_initial_displacement_undoes_the_decay(line_fit) -> None:
    """A free decay (0.02 px, zeta 0.03, 41 Hz, 3 s) shows as a 6e-5 px undamped line; its
    displacement at the record's start is read back, and an undamped mode's is its peak."""
    fps, T, n = 1000.0, 3000, 16
    t = np.arange(T)[:, None, None, None] / fps
    pa, pb = pattern(n, "a"), pattern(n, "b")
    pa, pb = pa / np.abs(pa).max(), pb / np.abs(pb).max()
    z, f = 0.03, 41.0
    d = (0.02 * np.exp(-z * 2 * np.pi * f * t) * np.cos(2 * np.pi * f * np.sqrt(1 - z * z) * t)
         * pa + 0.01 * np.cos(2 * np.pi * 17.0 * t) * pb)
    ms = modes_from_displacements(d, fps, line_fit=line_fit)
    i, j = nearest(ms, f), nearest(ms, 17.0)
    assert ms.damping_resolved()[i] and ms.damping[i] == pytest.approx(z, rel=0.02)
    assert ms.peak_displacement_px[i] < 1e-4
    assert ms.initial_displacement_px[i] == pytest.approx(0.02, rel=0.03)
    assert ms.initial_displacement_px[j] == ms.peak_displacement_px[j]
    assert ms.peak_displacement_px[j] == pytest.approx(0.01, rel=0.02)


def modeset(freqs, shapes, *, damping=None, damping_half_power=None, fps: float = 100.0,
            n_frames: int = 200, metadata: dict | None = None) -> ModeSet:
    """A hand-made ModeSet of ``freqs`` and ``shapes`` (damping NaN unless given; the peak
    statistics neutral). The test helper of every mode-set test."""
    k = len(freqs)
    return ModeSet(
        frequencies_hz=np.asarray(freqs, float),
        damping=np.full(k, np.nan) if damping is None else np.asarray(damping, float) * np.ones(k),
        damping_half_power=np.full(k, np.nan) if damping_half_power is None else (
            np.asarray(damping_half_power, float) * np.ones(k)),
        shapes=shapes,
        amplitudes_px=np.ones(k),
        peak_bins=np.arange(k),
        prominences=np.ones(k),
        collinearity=np.ones(k),
        shake_mac=np.zeros(k),
        camera_shake=np.zeros(k, bool),
        freqs_hz=np.zeros(0),
        power=np.zeros(0),
        fps=fps,
        n_frames=n_frames,
        **({"metadata": metadata} if metadata is not None else {}),
    )


def _modeset(freqs: list[float], shapes: np.ndarray, source: str) -> ModeSet:
    return modeset(freqs, shapes, damping=0.01, damping_half_power=0.01, n_frames=100,
                   metadata={"source": source})


def test_merge_two_mode_sets() -> None:
    rng = np.random.default_rng(0)
    a, b, c = (rng.standard_normal((16, 16, 2)) for _ in range(3))
    a, b, c = (x / np.linalg.norm(x) for x in (a, b, c))
    noisy_a = -(a + 0.05 * rng.standard_normal(a.shape) / 32)  # sign flipped duplicate
    s1 = _modeset([10.0, 20.0], np.stack([a, b]), "v1")
    s2 = _modeset([10.1, 30.0], np.stack([noisy_a, c]), "v2")
    m = merge_modesets([s1, s2])
    np.testing.assert_allclose(m.frequencies_hz, [10.05, 20.0, 30.0])
    assert m.metadata["n_sources"] == [2, 1, 1]
    assert float(np.sum(m.shapes[0] * a)) > 0.99  # sign aligned, averaged, unit norm
    assert np.linalg.norm(m.shapes[0]) == pytest.approx(1.0, rel=1e-6)
    # a different frequency or a dissimilar shape is not merged
    assert len(merge_modesets([s1, _modeset([10.0], c[None], "v3")])) == 3
    assert len(merge_modesets([s1, _modeset([15.0], a[None], "v3")])) == 3


# --------------------------------------------------------------------------- sampling and camera
def test_bilinear_sampling_exact_on_linear_field() -> None:
    H, W = 20, 30
    v, u = np.mgrid[0:H, 0:W].astype(float)
    shapes = np.stack(
        [np.stack([1 + 2 * u - 3 * v, 0.5 * u + v], -1), np.stack([u * 0 + 4, -u], -1)]
    )
    rng = np.random.default_rng(0)
    uv = np.c_[rng.uniform(-0.5, W - 1, 50), rng.uniform(-0.5, H - 1, 50)]
    uv[0] = [W - 1, H - 1]
    g = sample_modes(shapes, uv)
    assert g.shape == (2, 100)
    uc, vc = np.clip(uv[:, 0], 0, None), np.clip(uv[:, 1], 0, None)
    np.testing.assert_allclose(g[0, 0::2], 1 + 2 * uc - 3 * vc, atol=1e-12)
    np.testing.assert_allclose(g[0, 1::2], 0.5 * uc + vc, atol=1e-12)
    np.testing.assert_allclose(g[1, 0::2], 4.0)
    np.testing.assert_allclose(g[1, 1::2], -uc, atol=1e-12)
    with pytest.raises(ValueError, match="outside"):
        sample_field(shapes[0], [[W + 1.0, 0.0]])


def _camera() -> Camera:
    cam = Camera.look_at((2.0, -3.0, 1.5), (0, 0, 0), fx=400.0, width=320, height=240)
    K = cam.K.copy()
    K[0, 0], K[1, 2] = 410.0, 125.0
    return Camera(K=K, R=cam.R, t=cam.t, width=320, height=240)


def test_observation_operator_matches_finite_differences() -> None:
    cam = _camera()
    rng = np.random.default_rng(0)
    X = rng.uniform(-0.5, 0.5, (12, 3))
    vis = np.array([3, 1, 7, 11])
    P = observation_operator(cam, X, vis)
    assert P.shape == (8, 36)
    h = 1e-6
    for j in range(36):
        e = np.zeros(36)
        e[j] = h
        dX = e.reshape(12, 3)
        fd = (cam.project(X + dX) - cam.project(X - dX))[vis].ravel() / (2 * h)
        np.testing.assert_allclose(P[:, j].toarray().ravel(), fd, atol=1e-6)
    mask = np.zeros(12, bool)
    mask[[1, 3]] = True
    assert observation_operator(cam, X, mask).shape == (4, 36)


def test_dlt_camera_recovery() -> None:
    cam = _camera()
    rng = np.random.default_rng(0)
    X = rng.uniform(-0.5, 0.5, (10, 3))
    est, rms = estimate_camera(X, cam.project(X), 320, 240)
    assert rms < 1e-6
    np.testing.assert_allclose(est.K, cam.K, atol=1e-6)
    np.testing.assert_allclose(est.R, cam.R, atol=1e-9)
    # noisy clicks: residual at the noise level, held-out points predicted to ~noise
    X = rng.uniform(-0.5, 0.5, (30, 3))
    sigma = 0.3
    est, rms = estimate_camera(X, cam.project(X) + rng.normal(0, sigma, (30, 2)), 320, 240)
    assert 0.5 * sigma < rms < 1.6 * sigma
    Y = rng.uniform(-0.5, 0.5, (200, 3))
    err = np.linalg.norm(est.project(Y) - cam.project(Y), axis=1)
    assert np.sqrt(np.mean(err**2)) < 1.5 * sigma
    with pytest.raises(ValueError, match=">= 6"):
        estimate_camera(X[:5], cam.project(X[:5]), 320, 240)
    flat = X.copy()
    flat[:, 2] = 0.0
    with pytest.raises(ValueError, match="coplanar"):
        estimate_camera(flat, cam.project(flat), 320, 240)


def test_clicks_files(tmp_path) -> None:
    pts = [{"vertex": 4, "u": 10.5, "v": 20.25}, {"vertex": 7, "u": 1, "v": 2}]
    pj = tmp_path / "clicks.json"
    pj.write_text(json.dumps({"points": pts}))
    idx, uv = load_clicks(pj)
    assert idx.tolist() == [4, 7] and uv.tolist() == [[10.5, 20.25], [1.0, 2.0]]
    pc = tmp_path / "clicks.csv"
    pc.write_text("# clicks\nu,v,vertex\n10.5,20.25,4\n1,2,7\n")
    idx2, uv2 = load_clicks(pc)
    assert idx2.tolist() == [4, 7] and np.array_equal(uv, uv2)
    pj.write_text(json.dumps({"points": [{"vertex": 4, "v": 1.0}]}))
    with pytest.raises(ValueError, match=r"clicks\.json: points\[0\] is missing key 'u'"):
        load_clicks(pj)
    pc.write_text("vertex,u\n1,2\n")
    with pytest.raises(ValueError, match=r"clicks\.csv: CSV header lacks column 'v'"):
        load_clicks(pc)
    pc.write_text("vertex,u,v\n1,abc,2\n")
    with pytest.raises(ValueError, match=r"clicks\.csv: data line 1: 'u' must be a number"):
        load_clicks(pc)


def test_camera_from_clicks_on_mesh_vertices(tmp_path) -> None:
    """Clicked vertices of a mesh, projected by a known camera plus 0.2 px noise: the
    camera is recovered and predicts the other vertices to the noise level."""
    from vvtbench.fem.mesh import box_mesh
    from vvtbench.modes import camera_from_clicks

    cam = _camera()
    V = box_mesh((3, 3, 3), (1.0, 0.8, 0.6)).points - [0.5, 0.4, 0.3]
    rng = np.random.default_rng(2)
    idx = rng.choice(len(V), 8, replace=False)
    uv = cam.project(V[idx]) + rng.normal(0.0, 0.2, (8, 2))
    path = tmp_path / "clicks.json"
    pts = [
        {"vertex": int(i), "u": float(u), "v": float(v)} for i, (u, v) in zip(idx, uv, strict=True)
    ]
    path.write_text(json.dumps({"points": pts, "image_size": [320, 240]}))
    est, rms = camera_from_clicks(path, V, 320, 240)
    assert rms < 0.3 and (est.width, est.height) == (320, 240)
    err = np.linalg.norm(est.project(V) - cam.project(V), axis=1)
    assert np.sqrt(np.mean(err**2)) < 0.5
    csv = tmp_path / "clicks.csv"
    csv.write_text("vertex,u,v\n" + "".join(f"{p['vertex']},{p['u']},{p['v']}\n" for p in pts))
    assert np.allclose(camera_from_clicks(csv, V, 320, 240)[0].P, est.P)
    # too few pairs, an index outside the mesh, malformed entries: the file is named
    path.write_text(json.dumps({"points": pts[:5]}))
    with pytest.raises(ValueError, match=r"clicks\.json: camera estimation needs >= 6 .* got 5"):
        camera_from_clicks(path, V, 320, 240)
    path.write_text(json.dumps({"points": [*pts[:6], {"vertex": 64, "u": 1, "v": 2}]}))
    with pytest.raises(ValueError, match=r"clicks\.json: 'vertex' 64 out of range.*0 \.\. 63"):
        camera_from_clicks(path, V, 320, 240)
    path.write_text(json.dumps({"points": {"vertex": 1}}))
    with pytest.raises(ValueError, match=r"clicks\.json: 'points' must be a list"):
        camera_from_clicks(path, V, 320, 240)
    path.write_text(json.dumps({"points": [*pts[:6], pts[0]]}))
    with pytest.raises(ValueError, match=r"duplicate vertex indices \[" + str(pts[0]["vertex"])):
        camera_from_clicks(path, V, 320, 240)


# --------------------------------------------------------------------------- video files, CLI
def test_ffv1_gray16_roundtrip_through_extract(tmp_path) -> None:
    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")
    n, T, fps = 64, 64, 64.0
    sp = Speckle(n, seed=2)
    true = pattern(n, "a")
    frames = video(sp, [(true, 0.05, 8.0)], T, fps)
    lo, hi = frames.min(), frames.max()
    q = np.round((frames - lo) / (hi - lo) * 60000 + 2000).astype("<u2")
    path = tmp_path / "speckle.mkv"
    w = imageio_ffmpeg.write_frames(
        str(path),
        (n, n),
        pix_fmt_in="gray16le",
        pix_fmt_out="gray16le",
        codec="ffv1",
        quality=None,
        fps=fps,
        macro_block_size=1,
    )
    w.send(None)
    for f in q:
        w.send(f.tobytes())
    w.close()
    vs = open_video(path)
    back = np.stack(list(vs.frames))
    assert vs.meta["bits"] == 16 and vs.fps == fps
    np.testing.assert_array_equal(np.round(back * 65535).astype(np.uint16), q)  # bit exact
    ms = extract_modes(path)  # fps from the container
    i = nearest(ms, 8.0)
    assert abs(ms.frequencies_hz[i] - 8.0) <= fps / T
    m = np.zeros((n, n), bool)
    m[BORDER:-BORDER, BORDER:-BORDER] = True
    assert mac(ms.shapes[i][m], true[m]) > 0.95
    assert ms.metadata["decoded_pix_fmt"] == "gray16le"
    # CLI: files, plots and a faithful round trip of the saved set
    out = tmp_path / "modes"
    assert main_extract([str(path), "--fps", "64", "-o", str(out), "--quiet"]) == 0
    for name in ("modes.npz", "modes.json", "spectrum.png", "mode_00.png"):
        assert (out / name).is_file()
    loaded = ModeSet.load(out)
    assert len(loaded) == len(ms)
    np.testing.assert_array_equal(loaded.shapes, ms.shapes)
    np.testing.assert_array_equal(loaded.frequencies_hz, ms.frequencies_hz)
    np.testing.assert_array_equal(loaded.power, ms.power)
    assert loaded.metadata["motion"]["n_scales"] == 3
    # another extractor, and extractor options, from the command line (recorded in the set)
    assert main_extract([str(path), "--fps", "64", "-o", str(tmp_path / "fb"), "--quiet",
                         "--no-plots", "--extractor", "farneback", "--set", "winsize=9"]) == 0
    fb = ModeSet.load(tmp_path / "fb")
    assert fb.metadata["extractor"]["name"] == "farneback"
    assert fb.metadata["motion"]["winsize"] == 9
    assert abs(fb.frequencies_hz[nearest(fb, 8.0)] - 8.0) <= fps / T
    assert main_extract([str(path), "--fps", "64", "-o", str(tmp_path / "mid"), "--quiet",
                         "--no-plots", "--scales", "2", "--set", "frequency=midpoint"]) == 0
    motion = ModeSet.load(tmp_path / "mid").metadata["motion"]
    assert motion["n_scales"] == 2 and motion["frequency"] == "midpoint"


def _write_8bit(
    path,
    frames: np.ndarray,
    fps: float,
    pix_fmt_in: str,
    codec: str,
    pix_fmt_out: str,
    params: list[str],
) -> None:
    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")
    h, w = frames.shape[1:3]
    wr = imageio_ffmpeg.write_frames(
        str(path),
        (w, h),
        pix_fmt_in=pix_fmt_in,
        pix_fmt_out=pix_fmt_out,
        codec=codec,
        quality=None,
        fps=fps,
        macro_block_size=1,
        output_params=params,
    )
    wr.send(None)
    for f in frames:
        wr.send(np.ascontiguousarray(f).tobytes())
    wr.close()


@pytest.mark.parametrize("kind", ["colour-mp4", "gray-avi"])
def test_8bit_colour_mp4_and_gray_avi_through_extract(tmp_path, kind: str, capsys) -> None:
    """The 8-bit sources go through the reading path of the FFV1 gray16 test: ffmpeg's luma
    as 8-bit ``gray``, the container's fps, then the same extraction."""
    n, T, fps = 64, 64, 64.0
    true = pattern(n, "a")
    frames = video(Speckle(n, seed=2), [(true, 0.2, 8.0)], T, fps)
    lo, hi = frames.min(), frames.max()
    g8 = np.round((frames - lo) / (hi - lo) * 230 + 12).astype(np.uint8)
    if kind == "colour-mp4":
        rgb = np.stack([g8, (0.8 * g8).astype(np.uint8), 255 - g8], axis=-1)
        luma = rgb.astype(np.float64) @ np.array([0.299, 0.587, 0.114])
        path = tmp_path / "colour.mp4"
        _write_8bit(path, rgb, fps, "rgb24", "libx264", "yuv420p", ["-crf", "10"])
    else:
        luma = g8.astype(np.float64)
        path = tmp_path / "gray.avi"
        _write_8bit(path, g8, fps, "gray", "rawvideo", "gray", [])
    vs = open_video(path)
    back = np.stack(list(vs.frames))
    assert vs.meta["bits"] == 8 and vs.meta["decoded_pix_fmt"] == "gray" and vs.fps == fps
    assert back.shape == (T, n, n) and back.dtype == np.float32
    err = np.abs(back.astype(np.float64) * 255 - luma)
    if kind == "gray-avi":
        assert err.max() < 1e-3  # raw 8-bit gray: bit exact
    else:
        assert err.mean() < 2.0 and err.max() < 16  # lossy h264 yuv420p: luma kept
    ms = extract_modes(path)  # fps from the container
    assert ms.metadata["decoded_pix_fmt"] == "gray" and ms.metadata["fps_source"] == "container"
    i = nearest(ms, 8.0)
    assert abs(ms.frequencies_hz[i] - 8.0) <= fps / T
    m = np.zeros((n, n), bool)
    m[BORDER:-BORDER, BORDER:-BORDER] = True
    assert mac(ms.shapes[i][m], true[m]) > 0.95
    amp = ms.amplitudes_px[i] * np.abs(ms.shapes[i][m]).max()
    assert amp == pytest.approx(0.2, rel=0.2)
    if kind == "gray-avi":  # the CLI says which frame rate it took
        capsys.readouterr()
        out = tmp_path / "modes"
        assert main_extract([str(path), "-o", str(out), "--quiet", "--no-plots"]) == 0
        err_text = capsys.readouterr().err
        assert "container's frame rate, 64 fps" in err_text and "gray.avi" in err_text


def test_fmin_at_or_above_nyquist_names_nyquist(tmp_path, capsys) -> None:
    with pytest.raises(ValueError, match=r"fmin = 60 Hz is not below the Nyquist frequency"):
        check_band(100.0, 60.0, None)
    with pytest.raises(ValueError, match="Nyquist"):
        check_band(100.0, 30.0, 20.0)
    with pytest.raises(ValueError, match="Nyquist"):
        extract_modes(np.zeros((4, 16, 16), np.float32), 100.0, fmin=55.0)
    np.save(tmp_path / "v.npy", np.zeros((4, 16, 16), np.float32))
    out = str(tmp_path / "out")
    assert main_extract([str(tmp_path / "v.npy"), "--fps", "10", "-o", out, "--fmin", "6"]) == 2
    assert "Nyquist frequency fps/2 = 5 Hz" in capsys.readouterr().err
    np.save(tmp_path / "short.npy", np.zeros((4, 32, 32), np.float32))
    assert main_extract([str(tmp_path / "short.npy"), "--fps", "10", "-o", out, "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()   # too short: one line naming the file
    assert err == [f"error: {tmp_path / 'short.npy'}: need at least 8 frames, got 4"]
    assert not (tmp_path / "out").exists()


# ---------------------------------------------------------------------------- leakage, distortion
def test_distortion_products_found_and_true_modes_kept() -> None:
    f = [5.21, 7.58, 2.37, 10.42, 12.2, 31.0, 23.75]
    p = [400.0, 120.0, 0.1, 0.2, 3.0, 0.2, 5.0]
    found = {d["index"]: d for d in distortion_products(f, p, 1 / 3)}
    assert sorted(found) == [2, 3]  # 7.58 - 5.21 and 2 * 5.21
    assert found[2]["kind"] == "difference" and found[3]["kind"] == "harmonic"
    # 31.0 is one bin from 23.75 + 7.58 = 31.33: a mode, not a product
    assert 5 not in found and 4 not in found
    # a strong peak is never a product of weaker ones; parents can be excluded
    assert distortion_products([5.0, 10.0], [1.0, 100.0], 0.1) == []
    assert distortion_products([5.0, 10.0], [100.0, 1.0], 0.1, parents=[False, True]) == []


def test_hann_window_and_distortion_rejection_in_mode_identification() -> None:
    """A strong undamped mode off-bin (leaks ~1/k without a window) next to a weak mode at
    1/300 of its amplitude; a weak, spatially incoherent harmonic of the 20.5 Hz mode (as
    phase non-linearity makes) is rejected, the smooth mode at twice 10.25 Hz is kept."""
    fps, T, n = 200.0, 400, 24
    t = np.arange(T)[:, None, None, None] / fps
    pa, pb = pattern(n, "a"), pattern(n, "b")
    sign = np.where(np.random.default_rng(0).random((n, n, 1)) < 0.5, -1.0, 1.0)
    d = 0.3 * np.cos(2 * np.pi * 10.25 * t) * pa + 1e-3 * np.cos(2 * np.pi * 31.0 * t) * pb
    d = d + 3e-3 * np.cos(2 * np.pi * 20.5 * t) * pb  # a true mode at 2 x 10.25 Hz
    d = d + 5e-4 * np.cos(2 * np.pi * 41.0 * t) * pb * sign  # incoherent harmonic
    # the roughness test alone (the default faint-product test would also drop the true mode
    # at 20.5 Hz: 1e-4 of its parent's power, as faint as a product; see the test below)
    hann = modes_from_displacements(d, fps, faint_product_ratio=0)
    assert sorted(np.round(hann.frequencies_hz, 2).tolist()) == [10.25, 20.5, 31.0]
    i = nearest(hann, 31.0)
    assert mac(hann.shapes[i], pb) > 0.99
    assert hann.amplitudes_px[i] * np.abs(hann.shapes[i]).max() == pytest.approx(1e-3, rel=0.05)
    (rej,) = hann.metadata["rejected"]
    assert rej["reason"] == "distortion" and rej["kind"] == "harmonic"
    assert rej["parents_hz"] == pytest.approx([20.5, 20.5], abs=0.01)
    assert abs(rej["frequency_hz"] - 41.0) < fps / T and rej["roughness"] > 0.3
    assert len(modes_from_displacements(d, fps, reject_distortion=False)) == 4
    default = modes_from_displacements(d, fps)
    assert sorted(np.round(default.frequencies_hz, 2).tolist()) == [10.25, 31.0]
    assert {round(r["frequency_hz"], 1) for r in default.metadata["rejected"]} == {20.5, 41.0}
    # without a window the 1/k leakage of the strong mode buries the weak one
    rect = modes_from_displacements(d, fps, window="none", reject_distortion=False)
    assert not np.any(np.abs(rect.frequencies_hz - 31.0) < 1.0)


@pytest.mark.parametrize("line_fit", [False, True])
def test_mode_phases_and_product_phase_residuals_known_answer(line_fit: bool) -> None:
    """Modes ``cos(2 pi f t + p)`` off-bin: ``metadata.phase_rad`` is ``p`` mod pi; the
    products of a per-pixel quadratic non-linearity (random sign, as a texture-locked one)
    are rejected with a phase residual near 0, since their phase is ``p_a +- p_b``."""
    fps, T, n = 100.0, 600, 24
    t = np.arange(T)[:, None, None, None] / fps
    pa, pb = pattern(n, "a"), pattern(n, "b")
    rng = np.random.default_rng(0)
    c = rng.normal(size=(n, n, 2))
    modes = {7.31: 0.3, 11.13: 2.0}
    u = (0.3 * np.cos(2 * np.pi * 7.31 * t + modes[7.31]) * pa
         + 0.2 * np.cos(2 * np.pi * 11.13 * t + modes[11.13]) * pb)
    d = u + 0.05 * c * u**2 + 1e-4 * rng.normal(size=u.shape)  # a noise floor
    every = modes_from_displacements(d, fps, fmax=45.0, line_fit=line_fit,
                                     reject_distortion=False)
    phase = np.asarray(every.metadata["phase_rad"])
    assert phase.shape == (len(every),) and len(every) >= 4
    for f0, p0 in modes.items():
        k = nearest(every, f0)
        assert abs(every.frequencies_hz[k] - f0) < 0.02
        # the peak picker's phase carries its parabolic frequency's error (pi rad per bin)
        assert abs((phase[k] - p0 + np.pi / 2) % np.pi - np.pi / 2) < (0.05, 0.002)[line_fit]
    ms = modes_from_displacements(d, fps, fmax=45.0, line_fit=line_fit)
    assert np.sort(ms.frequencies_hz) == pytest.approx([7.31, 11.13], abs=0.02)
    rejected = ms.metadata["rejected"]
    assert len(rejected) == len(every) - 2
    assert {r["kind"] for r in rejected} >= {"sum", "difference", "harmonic"}
    for r in rejected:
        assert r["reason"] == "distortion"
        assert abs(r["phase_residual_rad"]) < (0.15, 0.01)[line_fit], r


def test_faint_smooth_product_rejected_by_power_ratio_true_mode_kept() -> None:
    """A smooth product (a small object: as smooth as the modes) passes the roughness test;
    with ``faint_product_ratio`` it is rejected for being far fainter than its parents, while
    a true mode at another product frequency, 1/30 of its parent's power, is kept."""
    fps, T, n = 200.0, 400, 24
    t = np.arange(T)[:, None, None, None] / fps
    pa, pb = pattern(n, "a"), pattern(n, "b")
    pc = pb[..., ::-1]
    d = 0.3 * np.cos(2 * np.pi * 10.25 * t) * pa + 0.2 * np.cos(2 * np.pi * 17.5 * t) * pb
    d = d + 1e-3 * np.cos(2 * np.pi * 27.75 * t) * pc  # smooth, P ratio ~ 2.5e-5: a product
    d = d + 0.04 * np.cos(2 * np.pi * 7.25 * t) * pc  # 17.5 - 10.25, P ratio ~ 0.04: a mode
    kept = modes_from_displacements(d, fps, faint_product_ratio=None)
    assert np.sort(kept.frequencies_hz) == pytest.approx([7.25, 10.25, 17.5, 27.75], abs=0.05)
    ms = modes_from_displacements(d, fps)  # the default: 0.01
    assert np.sort(ms.frequencies_hz) == pytest.approx([7.25, 10.25, 17.5], abs=0.05)
    (rej,) = ms.metadata["rejected"]
    assert rej["reason"] == "distortion" and rej["kind"] == "sum"
    assert rej["parents_hz"] == pytest.approx([10.25, 17.5], abs=0.01)
    assert rej["power_ratio"] < 1e-3 and rej["roughness"] < 0.15
    assert ms.metadata["faint_product_ratio"] == 0.01
    assert len(modes_from_displacements(d, fps, faint_product_ratio=0.0)) == 4
    with pytest.raises(ValueError, match="faint_product_ratio"):
        modes_from_displacements(d, fps, faint_product_ratio=2.0)


def test_product_scaling_keeps_a_mode_at_the_sum_of_two_weaker_peaks() -> None:
    """A product's amplitude grows with the product of its parents' amplitudes.  A true mode
    at the sum of two 0.03 px peaks, 0.4 % of their power, passes for a faint product when
    compared with the weaker parent, but not against ``P_i P_j / P_max`` (0.3 px strongest
    peak); a product of the strongest peak is rejected either way."""
    fps, T, n = 200.0, 400, 24
    t = np.arange(T)[:, None, None, None] / fps
    pa, pb = pattern(n, "a"), pattern(n, "b")
    d = (0.3 * np.cos(2 * np.pi * 10.25 * t) * pa + 0.03 * np.cos(2 * np.pi * 17.5 * t) * pb
         + 0.03 * np.cos(2 * np.pi * 23.0 * t) * pa[..., ::-1])
    d = d + 2e-3 * np.cos(2 * np.pi * 40.5 * t) * pb[..., ::-1]  # a mode at 17.5 + 23
    d = d + 1e-3 * np.cos(2 * np.pi * 27.75 * t) * pa  # 10.25 + 17.5: a product
    weaker = modes_from_displacements(d, fps, product_scaling="weaker")
    assert np.sort(weaker.frequencies_hz) == pytest.approx([10.25, 17.5, 23.0], abs=0.05)
    ms = modes_from_displacements(d, fps)  # the default: "product"
    assert ms.metadata["product_scaling"] == "product"
    assert np.sort(ms.frequencies_hz) == pytest.approx([10.25, 17.5, 23.0, 40.5], abs=0.05)
    (rej,) = ms.metadata["rejected"]
    assert rej["kind"] == "sum" and rej["parents_hz"] == pytest.approx([10.25, 17.5], abs=0.01)
    with pytest.raises(ValueError, match="scaling"):
        distortion_products([1.0, 2.0], [1.0, 0.1], 0.1, scaling="cubic")


def test_summary_gives_each_mode_its_entries_of_the_candidate_lists(tmp_path) -> None:
    """``metadata["roughness"]`` and its kin list every analysed peak, rejected ones too; each
    kept mode's own entries are in its ``summary()`` (and so in ``modes.json``), through
    subsets, saving and loading, and not after merging (no such map)."""
    from vvtbench.modes import merge_modesets

    fps, T, n = 200.0, 400, 24
    t = np.arange(T)[:, None, None, None] / fps
    pa, pb = pattern(n, "a"), pattern(n, "b")
    d = (0.3 * np.cos(2 * np.pi * 10.25 * t) * pa + 0.03 * np.cos(2 * np.pi * 17.5 * t) * pb
         + 1e-3 * np.cos(2 * np.pi * 27.75 * t) * pa)   # a product of the two
    ms = modes_from_displacements(d, fps)
    assert np.sort(ms.frequencies_hz) == pytest.approx([10.25, 17.5], abs=0.05)
    (rej,) = ms.metadata["rejected"]
    meta, idx = ms.metadata, ms.analysed_index()
    assert len(meta["roughness"]) == 3 and len(set(idx)) == 2
    (other,) = set(range(3)) - set(idx)      # the rejected candidate
    assert meta["roughness"][other] == rej["roughness"]
    summary = ms.summary()
    for k, entry in enumerate(summary):
        for name in ("roughness", "roughness_shape", "reliable_fraction", "phase_rad"):
            assert entry[name] == meta[name][idx[k]]
    assert rej["frequency_hz"] == pytest.approx(27.75, abs=0.05)
    sub = ms.select([1, 0])
    assert sub.analysed_index() == [idx[1], idx[0]]
    assert sub.summary()[0]["roughness"] == summary[1]["roughness"]
    loaded = ModeSet.load(ms.save(tmp_path / "m"))
    assert loaded.summary() == summary
    assert json.loads((tmp_path / "m" / "modes.json").read_text())["modes"][0]["roughness"] == \
        summary[0]["roughness"]
    merged = merge_modesets([ms, ms])
    assert merged.analysed_index() is None and "roughness" not in merged.summary()[0]
    for odd in ([0, -1], [0, "1"], [0, 1.5], [0, 99]):   # an edited file: no map, no error
        ms.metadata["analysed_index"] = odd
        assert "roughness" not in ms.summary()[1]



@pytest.mark.parametrize("key, value", [("fps", -1.0), ("fps", float("nan")), ("fps", "30"),
                                        ("fps", True), ("n_frames", 0), ("n_frames", 2.5)])
def test_an_edited_modes_json_with_a_bad_rate_is_refused(tmp_path, key, value) -> None:
    """A hand-edited rate or record length is one error naming the file and key, not a
    mode set whose frequency resolution and start displacements are nonsense."""
    out = modeset([5.0], np.ones((1, 4, 4, 2), np.float32)).save(tmp_path / "m")
    path = tmp_path / "m" / "modes.json"
    doc = json.loads(path.read_text())
    doc[key] = value
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=f"modes.json: key '{key}' must be"):
        ModeSet.load(out)


@pytest.mark.parametrize("key, value", [("onset_amplitude_ratio", ["0.5"]),
                                        ("damping_lo", [[0.1]]), ("roughness", "0.2"),
                                        ("damping_unwindowed", {"0": 0.01})])
def test_an_edited_per_peak_list_in_modes_json_is_refused(tmp_path, key, value) -> None:
    """A hand-edited per-peak list (:data:`CANDIDATE_LISTS`) is one error naming the file and
    key, not a conversion error when a reading first needs it."""
    out = modeset([5.0], np.ones((1, 4, 4, 2), np.float32)).save(tmp_path / "m")
    path = tmp_path / "m" / "modes.json"
    doc = json.loads(path.read_text())
    doc["metadata"][key] = value
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=f"modes.json: key 'metadata.{key}' must be"):
        ModeSet.load(out)
    doc["metadata"][key] = [None]
    path.write_text(json.dumps(doc))
    assert len(ModeSet.load(out)) == 1


def test_noisy_pixels_attenuated_in_the_shapes() -> None:
    """A strip of unreliable pixels (noise 0.02 px and the mode's motion read 5x too large
    there, as at a texture seam) dominates a 0.01 px mode's unit-norm shape; attenuating the
    noisiest 10 % of the pixels by their noise power restores it.  The frequencies are
    unchanged."""
    from vvtbench.modes.extract import noisy_pixel_attenuation
    from vvtbench.modes.spectrum import pixel_noise_power

    fps, T, n = 200.0, 400, 32
    t = np.arange(T)[:, None, None, None] / fps
    true = pattern(n, "a")
    d = 0.01 * np.cos(2 * np.pi * 20.25 * t) * true
    d[:, 10:12] *= 5.0
    d[:, 10:12] += 0.02 * np.random.default_rng(3).standard_normal((T, 2, n, 2))
    plain = modes_from_displacements(d, fps)
    noise = pixel_noise_power(d)
    fixed = modes_from_displacements(d, fps, shape_noise=noise)
    assert plain.frequencies_hz == pytest.approx(fixed.frequencies_hz)
    assert mac(plain.shapes[0], true) < 0.7 and mac(fixed.shapes[0], true) > 0.9
    att = fixed.metadata["shape_attenuation"]
    assert att["quantile"] == 0.9 and att["attenuated_fraction"] == pytest.approx(2 / n)
    assert plain.metadata["shape_attenuation"] is None
    assert att["mode"] == "attenuate"
    # filled in from the neighbours instead: as clean, and the strip reads the true motion
    filled = modes_from_displacements(d, fps, shape_noise=noise, shape_fill=True)
    assert filled.metadata["shape_attenuation"]["mode"] == "fill"
    shape = filled.shapes[0] * np.sign(np.sum(filled.shapes[0] * true))
    scale = np.sum(shape * true) / np.sum(true * true)
    assert mac(shape, true) > 0.99
    strip = np.abs(true[:, 10:12]) > 0.3
    ratio = shape[:, 10:12][strip] / (scale * true[:, 10:12][strip])
    assert np.median(ratio) == pytest.approx(1.0, abs=0.1)
    with pytest.raises(ValueError, match="grid"):
        modes_from_displacements(d, fps, shape_noise=noise[:-1])
    odd = np.array([1.0, 1.0, 1.0, np.nan, np.inf, 1e6])
    assert noisy_pixel_attenuation(odd, quantile=0.5).tolist() == [1, 1, 1, 0, 0, pytest.approx(
        np.sqrt(1e-5))]
    assert noisy_pixel_attenuation(np.full(4, np.nan)).tolist() == [1.0] * 4
    for bad in (0.0, -1.0, np.inf, np.nan):
        with pytest.raises(ValueError, match="factor"):
            noisy_pixel_attenuation(odd, factor=bad)


def test_shape_tests_on_reliable_pixels_keep_a_weak_mode_and_drop_an_edge_line() -> None:
    """A strip of unreliable pixels (broadband motion noise 0.05 px, as at an occlusion edge)
    carries a rough 0.015 px field at a weak smooth mode's frequency, which makes that mode
    rough on all pixels, and a line of its own.  Judged on all pixels (the default) the weak
    mode is rejected as incoherent; with ``roughness_weighting="spectrum"`` (noise weights:
    the strip left out) it is kept, and ``min_reliable_fraction`` drops the strip's line as
    ``"unreliable"``: its energy per unit noise weight is ~0 (0.3-0.9 for the modes) and it
    is rough on all pixels; a line smooth on all pixels would be kept however it lies."""
    from vvtbench.modes.extract import noise_weights
    from vvtbench.modes.spectrum import pixel_noise_power

    fps, T, n = 100.0, 1024, 32
    t = np.arange(T)[:, None, None, None] / fps
    rng = np.random.default_rng(3)
    strip = np.zeros((n, n, 1))
    strip[:, :4] = 1.0
    rough_field = strip * rng.choice([-1.0, 1.0], size=(n, n, 2))
    d = 0.05 * np.cos(2 * np.pi * 10.25 * t) * pattern(n, "a")
    d = d + np.cos(2 * np.pi * 23.5 * t) * (0.005 * pattern(n, "b") + 0.015 * rough_field)
    d = d + 0.05 * np.cos(2 * np.pi * 37.75 * t) * strip
    d = d + rng.normal(0.0, 1e-4, d.shape) + 0.05 * strip * rng.normal(0.0, 1.0, d.shape)
    ones = np.ones((n, n))
    sw = noise_weights(ones, pixel_noise_power(d))
    assert sw[:, :4].max() < 1e-3 < sw[:, 4:].min()

    plain = modes_from_displacements(d, fps, weights=ones, spectrum_weights=sw)
    assert np.sort(plain.frequencies_hz) == pytest.approx([10.25, 37.75], abs=0.05)
    (weak,) = [r for r in plain.metadata["rejected"] if abs(r["frequency_hz"] - 23.5) < 0.1]
    assert weak["reason"] == "incoherent" and weak["roughness"] > 0.3

    ms = modes_from_displacements(d, fps, weights=ones, spectrum_weights=sw,
                                  roughness_weighting="spectrum", min_reliable_fraction=0.1)
    assert np.sort(ms.frequencies_hz) == pytest.approx([10.25, 23.5], abs=0.05)
    (edge,) = ms.metadata["rejected"]
    assert edge["reason"] == "unreliable" and edge["frequency_hz"] == pytest.approx(37.75, abs=0.05)
    assert edge["reliable_fraction"] < 0.01 and edge["roughness_shape"] > 0.06
    gate = modes_from_displacements(d, fps, weights=ones, spectrum_weights=sw,
                                    roughness_weighting="spectrum", min_reliable_fraction=0.1,
                                    unreliable_roughness=1.0)
    assert all(r["reason"] != "unreliable" for r in gate.metadata["rejected"])
    fr = np.asarray(ms.metadata["reliable_fraction"])
    assert fr.size == 3 and np.sum(fr > 0.2) == 2  # the modes; the weak one 0.28
    assert ms.metadata["roughness_weighting"] == "spectrum"
    assert ms.metadata["min_reliable_fraction"] == 0.1
    # without spectrum weights there is nothing to tell reliable pixels by: no change
    same = modes_from_displacements(d, fps, weights=ones, roughness_weighting="spectrum",
                                    min_reliable_fraction=0.1)
    assert np.all(np.asarray(same.metadata["reliable_fraction"]) == 1.0)
    with pytest.raises(ValueError, match="roughness_weighting"):
        modes_from_displacements(d, fps, roughness_weighting="noise")
    with pytest.raises(ValueError, match="min_reliable_fraction"):
        modes_from_displacements(d, fps, min_reliable_fraction=float("nan"))
    with pytest.raises(ValueError, match="unreliable_roughness"):
        modes_from_displacements(d, fps, unreliable_roughness=-1.0)


def test_products_folded_by_sampling_are_recognised() -> None:
    """A product above Nyquist appears where sampling folds it: at 200 fps the harmonic of
    a 77.25 Hz mode (154.5 Hz) is seen at 45.5 Hz, the sum 77.25 + 52 Hz at 70.75 Hz.  Both
    are rejected as products (rough, and faint), a true mode at 30 Hz is kept."""
    assert distortion_products([77.25, 45.5], [1.0, 1e-4], 0.5) == []
    (d,) = distortion_products([77.25, 45.5], [1.0, 1e-4], 0.5, fps=200.0)
    assert d["kind"] == "harmonic" and d["expected_hz"] == pytest.approx(45.5)
    fps, T, n = 200.0, 400, 24
    t = np.arange(T)[:, None, None, None] / fps
    pa, pb = pattern(n, "a"), pattern(n, "b")
    sign = np.where(np.random.default_rng(2).random((n, n, 1)) < 0.5, -1.0, 1.0)
    d = 0.3 * np.cos(2 * np.pi * 77.25 * t) * pa + 0.2 * np.cos(2 * np.pi * 52.0 * t) * pb
    d = d + 2e-3 * np.cos(2 * np.pi * 30.0 * t) * pb[..., ::-1]  # a true mode
    d = d + 5e-4 * np.cos(2 * np.pi * 45.5 * t) * pa * sign  # 2 x 77.25 folded: rough
    d = d + 4e-4 * np.cos(2 * np.pi * 70.75 * t) * pa[..., ::-1]  # 77.25 + 52 folded: smooth
    ms = modes_from_displacements(d, fps, faint_product_ratio=0.01)
    assert np.sort(ms.frequencies_hz) == pytest.approx([30.0, 52.0, 77.25], abs=0.05)
    rejected = {round(r["frequency_hz"], 1): r for r in ms.metadata["rejected"]}
    assert set(rejected) == {45.5, 70.8}
    assert rejected[45.5]["kind"] == "harmonic" and rejected[70.8]["kind"] == "sum"


def test_extract_modes_passes_the_product_roughness_on(monkeypatch, tmp_path) -> None:
    import vvtbench.modes.extract as ex

    seen = {}
    real = ex.modes_from_displacements

    def spy(*args, **kwargs):
        seen.update(kwargs)
        return real(*args, **kwargs)

    monkeypatch.setattr(ex, "modes_from_displacements", spy)
    frames = np.random.default_rng(0).random((32, 32, 32)).astype(np.float32)
    np.save(tmp_path / "v.npy", frames)
    extract_modes(tmp_path / "v.npy", 64.0, product_roughness=0.08, faint_product_ratio=0.02)
    assert seen["product_roughness"] == 0.08 and seen["faint_product_ratio"] == 0.02
    assert seen["shape_noise"] is None and seen["product_scaling"] == "product"
    extract_modes(tmp_path / "v.npy", 64.0, shape_attenuation=True, product_scaling="weaker")
    assert seen["shape_noise"].shape == (16, 16) and seen["product_scaling"] == "weaker"
    extract_modes(tmp_path / "v.npy", 64.0, shape_attenuation=True, weighting="confidence")
    assert seen["shape_noise"].shape == (16, 16) and seen["spectrum_weights"] is None
    assert seen["roughness_weighting"] == "shape" and seen["min_reliable_fraction"] is None
    extract_modes(tmp_path / "v.npy", 64.0, roughness_weighting="spectrum",
                  min_reliable_fraction=0.1)
    assert seen["roughness_weighting"] == "spectrum" and seen["min_reliable_fraction"] == 0.1
    assert seen["shape_fill"] is False
    extract_modes(tmp_path / "v.npy", 64.0, shape_fill=True)
    assert seen["shape_fill"] is True and seen["shape_noise"].shape == (16, 16)


def test_roughness_separates_smooth_modes_from_incoherent_fields() -> None:
    n = 48
    smooth = pattern(n, "a")
    sign = np.where(np.random.default_rng(1).random((n, n, 1)) < 0.5, -1.0, 1.0)
    assert roughness(smooth) < 0.01
    assert roughness(smooth * sign) > 0.5


@pytest.mark.parametrize("offset", [0.0, 0.25, 0.5])
def test_amplitude_corrected_for_scalloping_off_bin(offset: float) -> None:
    """Halfway between bins the Hann peak bin holds 85 % of the amplitude; the refined
    frequency tells by how much, so the reported amplitude is corrected."""
    fps, T, n = 100.0, 256, 16
    t = np.arange(T)[:, None, None, None] / fps
    f = (40 + offset) * fps / T
    d = 0.01 * np.cos(2 * np.pi * f * t + 0.4) * pattern(n, "a")
    ms = modes_from_displacements(d, fps)
    assert abs(ms.frequencies_hz[0] - f) < 0.05 * fps / T
    amp = ms.amplitudes_px[0] * np.abs(ms.shapes[0]).max()
    assert amp == pytest.approx(0.01, rel=0.01)
