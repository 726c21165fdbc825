"""Tests of the steerable pyramid and phase-based motion on synthetic sub-pixel motion.

Frames are made from a seeded, band-limited random speckle image (periodic), translated
exactly in the Fourier domain (phase ramp); spatially varying warps use a third-order Taylor
expansion with spectral derivatives (error ~ |u|**4, negligible for |u| <= 0.04 px).
"""

from __future__ import annotations

import math
import tracemalloc
from collections.abc import Iterator

import numpy as np
import pytest

from vvtbench.motion.phase import (
    PhaseMotion,
    gaussian_smooth,
    iter_displacements,
    phase_difference,
    upsample_periodic,
)
from vvtbench.motion.pyramid import SteerablePyramid, get_pyramid, max_scales

N = 128
BORDER = 8


class Speckle:
    """Band-limited periodic random image with exact Fourier shifts and derivatives."""

    def __init__(self, n: int = N, seed: int = 0, sigma: float = 1.0) -> None:
        rng = np.random.default_rng(seed)
        self.wy = 2 * np.pi * np.fft.fftfreq(n)[:, None]
        self.wx = 2 * np.pi * np.fft.fftfreq(n)[None, :]
        r = np.hypot(self.wx, self.wy)
        F = np.fft.fft2(rng.standard_normal((n, n)))
        F *= np.exp(-0.5 * (r * sigma) ** 2) * (r < 0.9 * np.pi)
        F[n // 2, :] = 0.0  # Nyquist rows/cols: keeps shifted images exactly real
        F[:, n // 2] = 0.0
        self.F = F
        self.ref = self.shift(0.0, 0.0)

    def shift(self, dx: float, dy: float) -> np.ndarray:
        """Image translated by (dx, dy) pixels: content moves right/down for positive."""
        ramp = np.exp(-1j * (self.wx * dx + self.wy * dy))
        return np.fft.ifft2(self.F * ramp).real

    def _d(self, ax: int, ay: int) -> np.ndarray:
        return np.fft.ifft2(self.F * (1j * self.wx) ** ax * (1j * self.wy) ** ay).real

    def warp(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """``I(x - u(x), y - v(x))`` by a 3rd-order Taylor expansion (per-pixel shift)."""
        if not hasattr(self, "_der"):
            self._der = {(i, j): self._d(i, j) for i in range(4) for j in range(4 - i)}
        out = self.ref.copy()
        for i in range(4):
            for j in range(4 - i):
                if i + j == 0:
                    continue
                coef = (-1) ** (i + j) / (math.factorial(i) * math.factorial(j))
                out += coef * u**i * v**j * self._der[(i, j)]
        return out


@pytest.fixture(scope="module")
def speckle() -> Speckle:
    return Speckle()


@pytest.fixture(scope="module")
def motion(speckle: Speckle) -> PhaseMotion:
    return PhaseMotion(speckle.ref, n_scales=3, n_orientations=4)


def _interior(pm: PhaseMotion) -> np.ndarray:
    """Textured interior: away from the border and confidence above 10% of its median."""
    mask = np.zeros(pm.shape, bool)
    mask[BORDER:-BORDER, BORDER:-BORDER] = True
    return mask & (pm.confidence > 0.1 * np.median(pm.confidence))


def _mac(u: np.ndarray, p: np.ndarray) -> float:
    u, p = u.ravel(), p.ravel().astype(complex)
    return float(abs(np.vdot(u, p)) ** 2 / (np.vdot(u, u).real * np.vdot(p, p).real))


# ---------------------------------------------------------------------------- pyramid
def test_pyramid_cached_and_band_metadata() -> None:
    pyr = get_pyramid((64, 48), 3, 4)
    assert pyr is get_pyramid((64, 48), 3, 4)
    assert len(pyr.bands) == 12
    b = pyr.bands[4 + 1]  # scale 1, orientation 1 (45 degrees)
    assert (b.scale, b.orientation, b.shape, b.stride) == (1, 1, (32, 24), (2.0, 2.0))
    wc = np.pi / 4
    np.testing.assert_allclose(b.frequency, (wc / np.sqrt(2), wc / np.sqrt(2)))
    assert pyr.filters(0).dtype == np.float32 and not pyr.filters(0).flags.writeable


def test_pyramid_downsampled_bands_equal_subsampled_full_resolution() -> None:
    x = np.random.default_rng(1).standard_normal((2, 64, 48))
    down = get_pyramid((64, 48), 3, 5, downsample=True).decompose(x)
    full = get_pyramid((64, 48), 3, 5, downsample=False).decompose(x)
    for band, a, c in zip(get_pyramid((64, 48), 3, 5).bands, down, full, strict=True):
        sy, sx = (int(s) for s in band.stride)
        assert a.dtype == np.complex64 and a.shape == (2, *band.shape)
        np.testing.assert_allclose(a, c[:, ::sy, ::sx], atol=1e-5 * np.abs(c).max())


def test_decimated_pyramid_gives_exact_samples_at_double_stride() -> None:
    """Spectrum folding: scale s sampled every 2**(s+1) px, coefficients and gradients exact."""
    x = np.random.default_rng(2).standard_normal((2, 64, 48))
    dec = get_pyramid((64, 48), 3, 4, decimate=True)
    full = get_pyramid((64, 48), 3, 4, downsample=False)
    pairs = zip(dec.iter_bands(x, gradient=True), full.iter_bands(x, gradient=True), strict=True)
    for (band, c, g), (_, cf, gf) in pairs:
        s = 2 ** (band.scale + 1)
        assert band.stride == (s, s) and c.shape == (2, 64 // s, 48 // s)
        np.testing.assert_allclose(c, cf[:, ::s, ::s], atol=1e-5 * np.abs(cf).max())
        np.testing.assert_allclose(g, gf[:, :, ::s, ::s], atol=1e-5 * np.abs(gf).max())
    with pytest.raises(ValueError, match="divisible"):
        SteerablePyramid((60, 48), 3, 4, decimate=True)


def test_phase_difference_matches_numpy_angle() -> None:
    rng = np.random.default_rng(5)
    ang = np.concatenate([rng.normal(0, 0.1, 5000), rng.uniform(-np.pi, np.pi, 500)])
    ang = np.concatenate([ang, [0.0, 0.46, -0.47, np.pi / 2, np.pi, -3.0]])
    z = (rng.uniform(0.1, 10, ang.size) * np.exp(1j * ang)).astype(np.complex64)
    z[:3] = [0, 1e-30, -1]
    got = phase_difference(z)
    assert got.dtype == np.float32
    err = np.angle(np.exp(1j * (got - np.angle(z.astype(np.complex128)))))
    assert np.abs(err).max() < 1e-6


def test_pyramid_plane_wave_selects_band_and_phase_gradient() -> None:
    """A plane wave at a band's centre frequency lands in that band with phase w . x."""
    pyr = get_pyramid((64, 64), 3, 4, downsample=False)
    yy, xx = np.mgrid[:64, :64]
    target = pyr.bands[4 + 3]  # scale 1, theta = 135 deg
    wx, wy = (2 * np.pi * round(f * 64 / (2 * np.pi)) / 64 for f in target.frequency)
    img = np.cos(wx * xx + wy * yy)
    amps = [np.abs(c).mean() for c in pyr.decompose(img)]
    assert int(np.argmax(amps)) == 7
    band, c, grad = list(pyr.iter_bands(img, gradient=True))[7]
    g = (np.conj(c[0]) * grad[:, 0]).imag / np.abs(c[0]) ** 2
    np.testing.assert_allclose(g[0], wx, atol=1e-4)
    np.testing.assert_allclose(g[1], wy, atol=1e-4)
    # the (analytic) coefficient rotates with the wave: c ~ exp(i w . x)
    np.testing.assert_allclose(
        np.angle(c[0] * np.exp(-1j * (wx * xx + wy * yy))), np.angle(c[0, 0, 0]), atol=1e-4
    )


# ---------------------------------------------------------------------------- static shifts
def test_fourier_shift_helper_matches_roll(speckle: Speckle) -> None:
    np.testing.assert_allclose(speckle.shift(1, 0), np.roll(speckle.ref, 1, axis=1), atol=1e-12)
    np.testing.assert_allclose(speckle.shift(0, 1), np.roll(speckle.ref, 1, axis=0), atol=1e-12)


@pytest.mark.parametrize("decimate", [True, False])
@pytest.mark.parametrize("d", [0.5, 0.1, 0.01])
def test_static_shifts_recovered(
    speckle: Speckle, motion: PhaseMotion, d: float, decimate: bool
) -> None:
    shifts = [(d, 0.0), (0.0, d), (d, d), (d, -d)]
    frames = np.stack([speckle.shift(*s) for s in shifts])
    pm = motion if decimate else PhaseMotion(speckle.ref, decimate=False)
    disp = pm.displacement(frames)
    assert disp.shape == (4, N, N, 2) and disp.dtype == np.float32
    mask = _interior(motion)
    for est, true in zip(disp, shifts, strict=True):
        med = np.median(est[mask], axis=0)
        np.testing.assert_allclose(med, true, atol=0.05 * d, err_msg=f"shift {true}")


@pytest.mark.parametrize("kw", [{}, {"decimate": False}, {"downsample": False},
                                {"frequency": "midpoint"}, {"refine": 2}],
                         ids=["decimated", "full-grid", "no-downsample", "midpoint", "twice"])
def test_refinement_keeps_exact_shifts_exact(speckle: Speckle, kw: dict) -> None:
    """Without noise the refined estimate is the first one, on every pyramid layout (coarse
    bands sampled from the working grid), also for shifts whose finest phases wrap."""
    shifts = [(0.3, -0.2), (1.2, 0.4)]
    frames = np.stack([speckle.shift(*s) for s in shifts])
    refined = PhaseMotion(speckle.ref, **kw)
    first = PhaseMotion(speckle.ref, **{**kw, "refine": 0})
    assert refined.refine == kw.get("refine", 1)
    mask = _interior(refined)
    for est, est0, true in zip(refined.displacement(frames), first.displacement(frames), shifts,
                               strict=True):
        np.testing.assert_allclose(np.median(est[mask], axis=0), true, atol=0.03 * np.hypot(*true))
        assert np.sqrt(np.mean((est[mask] - true) ** 2)) <= \
            1.2 * np.sqrt(np.mean((est0[mask] - true) ** 2)) + 1e-4
    with pytest.raises(ValueError, match="refine"):
        PhaseMotion(speckle.ref, refine=-1)


def test_centre_frequency_fallback_is_roughly_right(speckle: Speckle) -> None:
    """Band-centre conversion is biased by the texture's spectrum (~10-15% here)."""
    pm = PhaseMotion(speckle.ref, frequency="centre")
    med = np.median(pm.displacement(speckle.shift(0.1, -0.1)[None])[0][_interior(pm)], axis=0)
    np.testing.assert_allclose(med, (0.1, -0.1), rtol=0.25)


def test_sign_conventions(speckle: Speckle, motion: PhaseMotion) -> None:
    right = np.roll(speckle.ref, 1, axis=1)  # content moves one column to the right
    down = np.roll(speckle.ref, 1, axis=0)  # content moves one row down
    d = motion.displacement(np.stack([right, down, speckle.shift(-0.2, -0.3)]))
    mask = _interior(motion)
    mr, md, mn = (np.median(di[mask], axis=0) for di in d)
    assert mr[0] > 0.9 and abs(mr[1]) < 0.05
    assert md[1] > 0.9 and abs(md[0]) < 0.05
    assert mn[0] < 0 and mn[1] < 0


def test_ambiguous_phases_dropped_for_large_shifts(speckle: Speckle) -> None:
    """At 2 px the finest scale's phase differences approach +-pi; dropping those beyond
    pi/2 (default) reduces the underestimate (keeping all: ~13 % low)."""
    frames = np.stack([speckle.shift(2.0, 0.0), speckle.shift(0.0, -2.0)])
    est = {}
    for mp in (np.pi / 2, np.pi):
        pm = PhaseMotion(speckle.ref, max_phase=mp)
        d = pm.displacement(frames)
        m = _interior(pm)
        est[mp] = (np.median(d[0][m, 0]), -np.median(d[1][m, 1]))
    assert all(v > 1.78 for v in est[np.pi / 2])
    assert all(a > b for a, b in zip(est[np.pi / 2], est[np.pi], strict=True))
    with pytest.raises(ValueError, match="max_phase"):
        PhaseMotion(speckle.ref, max_phase=0.0)


def test_no_motion_gives_zero(speckle: Speckle, motion: PhaseMotion) -> None:
    d = motion.displacement(speckle.ref[None])
    assert np.abs(d).max() < 1e-4


# ---------------------------------------------------------------------------- vibration
def _tone(x: np.ndarray, at: float | None = None, pad: int = 16) -> tuple[float, float]:
    """Frequency (bins) and amplitude of the strongest sinusoid in ``x`` (or of the one at
    ``at`` bins): peak of the zero-padded DFT (no window; exact amplitude at any frequency up
    to the ~1/(2 pi f) leakage of the negative-frequency image)."""
    T = x.size
    X = np.abs(np.fft.rfft(x - x.mean(), n=pad * T))
    k = int(np.argmax(X[1:])) + 1 if at is None else int(round(at * pad))
    return k / pad, 2 * X[k] / T


@pytest.mark.parametrize(
    "f,noise", [(10.0, 0.0), (10.4, 0.0), (10.4, 0.005)], ids=["on-bin", "off-bin", "noisy"]
)
def test_sinusoidal_translation_amplitude_and_frequency(
    speckle: Speckle, motion: PhaseMotion, f: float, noise: float
) -> None:
    """0.01 px translation at 10 bins, at 10.4 bins and with camera noise (white, 0.5 % of
    the intensity range per pixel and frame, ~1.3 grey levels of 8 bits)."""
    T, amp = 128, 0.01
    rng = np.random.default_rng(5)
    sd = noise * np.ptp(speckle.ref)
    frames = np.stack(
        [
            speckle.shift(amp * np.sin(2 * np.pi * f * k / T + 0.3), 0.0)
            + sd * rng.standard_normal(speckle.ref.shape)
            for k in range(T)
        ]
    )
    disp = motion.displacement(frames)
    mean = disp[:, _interior(motion)].mean(axis=1)  # (T, 2)
    f_x, a_x = _tone(mean[:, 0])
    assert abs(f_x - f) < 1.0
    assert a_x == pytest.approx(amp, rel=0.05)
    if f == round(f):
        spec = np.abs(np.fft.rfft(mean, axis=0)) * 2 / T
        assert int(np.argmax(spec[1:, 0])) + 1 == f
        assert spec[int(f), 0] == pytest.approx(amp, rel=0.05)
    assert _tone(mean[:, 1], at=f_x)[1] < 0.05 * amp


@pytest.mark.parametrize("pattern", ["smooth", "halves"])
def test_two_modes_at_two_frequencies_are_separable(
    speckle: Speckle, motion: PhaseMotion, pattern: str
) -> None:
    T, f1, f2, a = 64, 5, 12, 0.02
    yy, xx = np.mgrid[:N, :N] / N
    if pattern == "smooth":
        p1 = np.stack([np.cos(2 * np.pi * yy), 0.5 * np.sin(2 * np.pi * xx)])
        p2 = np.stack([0.5 * np.sin(2 * np.pi * (xx + yy)), np.cos(2 * np.pi * xx)])
    else:  # left half moves in x at f1, right half in y at f2
        left = xx < 0.5
        p1 = np.stack([left, np.zeros_like(left)]).astype(float)
        p2 = np.stack([np.zeros_like(left), ~left]).astype(float)
    t = np.arange(T)[:, None, None, None]
    u = a * (p1 * np.sin(2 * np.pi * f1 * t / T) + p2 * np.sin(2 * np.pi * f2 * t / T))
    frames = np.stack([speckle.warp(uk[0], uk[1]) for uk in u])
    spec = np.fft.rfft(motion.displacement(frames), axis=0)  # (T//2+1, H, W, 2)
    mask = _interior(motion)
    for f, p, other in ((f1, p1, p2), (f2, p2, p1)):
        field = spec[f][mask]  # (n, 2)
        assert _mac(field, np.moveaxis(p, 0, -1)[mask]) >= 0.95
        assert _mac(field, np.moveaxis(other, 0, -1)[mask]) < 0.05


# ---------------------------------------------------------------------------- batching, streams
def test_batch_equals_one_at_a_time_and_threads(speckle: Speckle, motion: PhaseMotion) -> None:
    frames = np.stack([speckle.shift(0.07 * k, -0.03 * k) for k in range(5)])
    whole = motion.displacement(frames)
    single = np.concatenate([motion.displacement(f[None]) for f in frames])
    np.testing.assert_array_equal(whole, single)
    threaded = PhaseMotion(speckle.ref, workers=2).displacement(frames)
    np.testing.assert_array_equal(whole, threaded)
    chunked = PhaseMotion(speckle.ref, workers=2, chunk_frames=2).displacement(frames)
    np.testing.assert_array_equal(whole, chunked)
    # the working grid (decimated by default) is what the full-resolution output upsamples
    assert motion.decimate and motion.grid_shape == (N // 2, N // 2)
    grid = motion.displacement(frames, full_resolution=False)
    assert grid.shape == (5, N // 2, N // 2, 2)
    np.testing.assert_allclose(whole[:, ::2, ::2], grid, atol=1e-6)


def test_streaming_equals_whole_array(speckle: Speckle, motion: PhaseMotion) -> None:
    frames = np.stack([speckle.shift(0.05 * np.sin(k), 0.02 * k) for k in range(7)])
    whole = motion.displacement(frames)
    batches = list(motion.iter_displacements(iter(frames), batch=3))
    assert [b.shape[0] for b in batches] == [3, 3, 1]
    np.testing.assert_array_equal(np.concatenate(batches), whole)
    # chunks of different sizes are re-batched
    chunks = [frames[:2], frames[2:6], frames[6]]
    np.testing.assert_array_equal(
        np.concatenate(list(motion.iter_displacements(chunks, batch=4))), whole
    )
    # module-level generator: first frame is the reference by default
    stream = np.concatenate([speckle.ref[None], frames])
    got = np.concatenate(list(iter_displacements(iter(stream), batch=3)))
    np.testing.assert_array_equal(got, motion.displacement(stream))


def test_streaming_memory_does_not_grow_with_length() -> None:
    sp = Speckle(64, seed=3)
    pm = PhaseMotion(sp.ref, n_scales=2)

    def video(T: int) -> Iterator[np.ndarray]:
        for k in range(T):
            yield sp.shift(0.01 * np.sin(0.3 * k), 0.0).astype(np.float32)

    def peak(T: int) -> int:
        tracemalloc.start()
        n = 0
        for d in pm.iter_displacements(video(T), batch=4):
            n += d.shape[0]
        _, p = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        assert n == T
        return p

    short, long = peak(8), peak(80)
    assert long < 1.2 * short


# ---------------------------------------------------------------------------- bad input
def test_bad_input_raises(speckle: Speckle, motion: PhaseMotion) -> None:
    with pytest.raises(ValueError, match="2-D"):
        PhaseMotion(np.zeros((2, 32, 32)))
    with pytest.raises(ValueError, match="3-D"):
        motion.displacement(speckle.ref)
    with pytest.raises(ValueError, match="3-D"):
        motion.displacement(np.zeros((1, 1, N, N)))
    with pytest.raises(ValueError, match="does not match"):
        motion.displacement(np.zeros((2, N, N - 1)))
    with pytest.raises(ValueError, match="too many"):
        PhaseMotion(np.zeros((32, 64)), n_scales=4)
    assert max_scales((32, 64)) == 3
    with pytest.raises(ValueError, match="too many"):
        get_pyramid((N, N), n_scales=6)
    with pytest.raises(ValueError, match="n_orientations"):
        SteerablePyramid((N, N), n_orientations=1)
    with pytest.raises(ValueError, match="frequency"):
        PhaseMotion(speckle.ref, frequency="global")
    with pytest.raises(ValueError, match="chunk_frames"):
        PhaseMotion(speckle.ref, chunk_frames=0)
    with pytest.raises(ValueError, match="streamed frames"):
        list(motion.iter_displacements([speckle.ref, np.zeros((N, N + 2))], batch=2))
    with pytest.raises(ValueError, match="real"):
        motion.displacement(np.zeros((1, N, N), complex))


def test_upsample_periodic_is_exact_on_linear_interpolants() -> None:
    a = np.arange(8, dtype=np.float32).reshape(2, 4)
    up = upsample_periodic(a, (4, 8))
    np.testing.assert_array_equal(up[::2, ::2], a)
    np.testing.assert_allclose(up[0, 1], 0.5)
    np.testing.assert_allclose(up[0, 7], (3 + 0) / 2)  # periodic wrap


@pytest.mark.parametrize("shape,sigma", [((2, 3, 40, 33), 1.0), ((5, 7), 1.0), ((4, 4), 1.0)])
def test_gaussian_smooth_matches_ndimage(shape: tuple[int, ...], sigma: float) -> None:
    from scipy.ndimage import gaussian_filter

    a = np.random.default_rng(4).random(shape).astype(np.float32)
    want = gaussian_filter(a, sigma, axes=(-2, -1), mode="reflect", truncate=3.0)
    np.testing.assert_allclose(gaussian_smooth(a, sigma), want, atol=1e-6)


@pytest.mark.parametrize("fraction", [0.01, 0.6])
def test_smoothing_of_kept_samples_sparse_and_dense_agree(speckle: Speckle, fraction) -> None:
    """The two ways of smoothing the normal matrix with samples taken out (a scatter of the
    kernel around each removed sample, or dense smoothing of what is kept) agree, whether
    few samples are removed (the scatter is used) or most (dense)."""
    pm = PhaseMotion(speckle.ref, n_scales=3, n_orientations=4)
    rng = np.random.default_rng(0)
    h, w = pm.grid_shape
    B = 3
    removed = rng.random((B, h, w)) < fraction
    idx = rng.integers(0, B * h * w, size=int(fraction * B * h * w))
    vals = (0.1 * rng.random((3, len(idx)))).astype(np.float32)
    dense = pm._smooth_kept(removed, (idx, vals))
    sparse = pm._smooth_removed(removed, (idx, vals), dense=False)
    assert np.array_equal(pm._smooth_removed(removed, (idx, vals)), dense if fraction > 0.1
                          else sparse)  # the automatic choice
    scale = float(np.abs(pm._m_smooth).max())
    np.testing.assert_allclose(dense, sparse, atol=2e-5 * scale)
    # and against scipy, on the kept samples alone
    from scipy.ndimage import gaussian_filter

    keep = pm._m[:, None] * ~removed[None]
    ref = gaussian_filter(keep.astype(np.float64), pm.sigma / pm.grid_stride, axes=(-2, -1),
                          mode="reflect", truncate=3.0)
    if fraction < 0.1:  # without extra samples
        np.testing.assert_allclose(pm._smooth_kept(removed), ref, atol=2e-5 * scale)


# ---------------------------------------------------------------------------- midpoint
@pytest.mark.parametrize("d", [0.1, 0.3])
def test_midpoint_frequency_removes_the_second_order_error(speckle: Speckle, d: float) -> None:
    """Exact Fourier shifts: ``"local"`` is off by 1.3e-3 / 3.8e-3 of the shift at 0.1 /
    0.3 px (relative error growing with the shift: second order); the midpoint's trapezoid
    cancels that term (2.1e-4 / 9.6e-4 measured)."""
    shifts = [(d, 0.0), (0.0, -d), (0.7 * d, 0.7 * d)]
    frames = np.stack([speckle.shift(*s) for s in shifts])
    err = {}
    for freq in ("local", "midpoint"):
        pm = PhaseMotion(speckle.ref, frequency=freq)
        est = pm.displacement(frames)[:, _interior(pm)]
        true = np.asarray(shifts)[:, None, :]
        err[freq] = float(np.sqrt(((est - true) ** 2).mean()) / d)
    assert err["midpoint"] < err["local"] / 3


def test_midpoint_frequency_lowers_the_harmonic_of_a_vibration(speckle: Speckle) -> None:
    """A 0.3 px sinusoidal translation: the measured second harmonic (a distortion product,
    absent from the motion) drops at least 4x; the fundamental's amplitude is unchanged."""
    T, f, amp = 64, 5, 0.3
    frames = np.stack(
        [speckle.shift(amp * np.sin(2 * np.pi * f * k / T), 0.0) for k in range(T)]
    )
    out = {}
    for freq in ("local", "midpoint"):
        pm = PhaseMotion(speckle.ref, frequency=freq)
        d = pm.displacement(frames)[:, _interior(pm), 0]  # (T, P)
        spec = np.abs(np.fft.rfft(d - d.mean(0), axis=0)) * 2 / T  # per pixel
        out[freq] = (spec[f].mean(), np.sqrt((spec[2 * f] ** 2).mean()))
    assert out["midpoint"][0] == pytest.approx(amp, rel=0.01)
    assert out["local"][0] == pytest.approx(amp, rel=0.01)
    assert out["midpoint"][1] < out["local"][1] / 4


def test_midpoint_without_motion_and_in_the_extractor_config(speckle: Speckle) -> None:
    from vvtbench.solving.extractors import make_extractor

    pm = PhaseMotion(speckle.ref, frequency="midpoint")
    assert np.abs(pm.displacement(speckle.ref[None])).max() < 1e-4
    ext = make_extractor("phase", {"frequency": "midpoint"})
    stream = ext.prepare(speckle.ref.astype(np.float32))
    assert stream.pm.frequency == "midpoint" and stream.describe()["frequency"] == "midpoint"
    with pytest.raises(ValueError, match="midpoint"):
        PhaseMotion(speckle.ref, frequency="mid")
