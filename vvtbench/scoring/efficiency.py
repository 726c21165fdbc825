r"""Extractor efficiency against the Cramér-Rao bound: ``eta = sigma_CRB^2 / MSE``.

Setting
-------
The rest image is the project's speckle (:func:`vvtbench.render.texture.speckle_texture`,
periodic, ``grain`` in image pixels, intensities ``0.5 +- contrast / 2``).  Frame ``t`` is
that image translated by a known sub-pixel shift ``s_t`` (exact Fourier phase ramp of the
periodic image, content moving right/down for positive ``dx``/``dy``) and passed through the
sensor model (:func:`vvtbench.render.sensor.sensor_dn`: read noise ``noise`` times full scale, shot
noise optional, rounding to whole DN at ``bit_depth``), its noise drawn from
:func:`vvtbench.render.sensor.noise_rng` ``(seed, t)``.  The shifts have magnitude ``amplitude_px``
along ``directions`` directions ``pi / 8 + 2 pi k / directions``, each filmed ``repeats``
times with fresh noise: a record of ``T = directions x repeats`` frames, ``clips`` records
with independent noise (record ``c`` draws frame ``t``'s from ``(seed, c (T + 1) + t)``).
:meth:`EfficiencySetting.at_ratio` sets the noise for a texture-to-noise ratio (the rest
image's standard deviation over the read noise's).

Reference
---------
The extractor is prepared, per record, on (``reference``) the noise-free rest image
(``"clean"``: the known texture the bound assumes), one noisy frame at rest drawn like the
record's (``"first"``: how extractors were used before the mean reference) or the temporal
mean of the record (``"mean"``, a first pass: what :func:`vvtbench.modes.extract_modes` gives
them), and measures every frame.  The truth is the shift relative to the reference's
position (the mean shift, zero here, for ``"mean"``).  A noisy reference adds an error common
to all frames of a record, which modal analysis never sees (the spectrum removes the mean):
with ``remove_offset`` each record's mean error is removed (its RMS is ``offset_px``) and the
squared errors scaled by ``T / (T - 1)``; what a noisy reference does to the *gain* stays in.

Estimate and bound
------------------
Its estimate of a block's shift is the mean of its
displacement field over the grid samples inside the block (``block`` px; ``None`` = the whole
frame, which, being periodic, has no edges).  The bound is the ruler's
(:func:`vvtbench.render.crb.block_crb` of :func:`~vvtbench.render.crb.pixel_fisher` with
:func:`~vvtbench.render.crb.noise_variance_dn2`), on the rest image padded periodically so
its gradient has no reflected edges.  Per direction, block and axis the ``repeats`` errors
give the bias (``mean^2 - var / repeats``, unbiased) and the variance (``ddof = 1``), which
add up to the mean squared error.  Then

* ``eta = mean(sigma_CRB^2) / MSE`` (bias included) and ``eta_variance`` (bias left out);
* ``eta_se``: its Monte-Carlo standard error from the spread of the per-frame squared errors
  (frames of a record share its reference: with a noisy one this understates it);
* ``gain``: the least-squares slope of the estimates on the true shifts (1: no amplitude
  bias), its standard error from the records' slopes (from the frames for one record).

An unbiased estimator has ``eta <= 1``; :class:`KnownTextureShift` (Gauss-Newton on the
true texture) reaches it.  The block bound is the bound of the block's own pixels, and an
extractor that pools the pixels around the block (a smoothing window, the support of its
filters) holds more information than that: per 8 px block the phase extractor "beats" it
about 6x.  With ``bound = "footprint"`` a block is compared with the bound of the area the
extractor pools instead (:func:`vvtbench.scoring.crb.footprint_crb`, the window measured as
the extractor's response to motion varying across the frame, :func:`motion_transfer`); the
whole frame, being periodic, is the same either way.

:func:`band_information` says how much of the bound's Fisher information lies in the band
a steerable pyramid keeps.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..render import crb
from ..render.sensor import FULL_WELL_ELECTRONS, noise_rng, sensor_dn

__all__ = [
    "REFERENCES",
    "EfficiencySetting",
    "KnownTextureShift",
    "band_information",
    "extractor_efficiency",
    "reference_frame",
    "rest_image",
    "texture_std",
    "true_shifts",
    "iter_frames",
    "motion_transfer",
]


#: what the extractor is prepared on (module docstring, "Reference")
REFERENCES = ("clean", "first", "mean")


@dataclass(frozen=True)
class EfficiencySetting:
    """One point of the efficiency sweep (module docstring)."""

    amplitude_px: float
    noise: float = 0.01
    bit_depth: int = 12
    size: int = 128
    grain: float = 2.0
    contrast: float = 0.8
    directions: int = 4
    repeats: int = 32
    block: int | None = None
    shot_noise: bool = False
    full_well: float = FULL_WELL_ELECTRONS
    seed: int = 0
    reference: str = "clean"
    clips: int = 1
    remove_offset: bool = False
    bound: str = "block"

    def __post_init__(self) -> None:
        if not self.amplitude_px >= 0:
            raise ValueError(f"amplitude_px must be >= 0, got {self.amplitude_px}")
        if not self.noise >= 0 or not 1 <= int(self.bit_depth) <= 16:
            raise ValueError(f"need noise >= 0 and 1 <= bit_depth <= 16, got {self.noise}, "
                             f"{self.bit_depth}")
        if self.directions < 1 or self.repeats < 2:
            raise ValueError("need directions >= 1 and repeats >= 2")
        b = self.size if self.block is None else int(self.block)
        if b < 1 or self.size % b:
            raise ValueError(f"block {self.block} must divide the frame size {self.size}")
        if self.reference not in REFERENCES:
            raise ValueError(f"reference must be one of {REFERENCES}, got {self.reference!r}")
        if self.bound not in ("block", "footprint"):
            raise ValueError(f"bound must be 'block' or 'footprint', got {self.bound!r}")
        if int(self.clips) < 1:
            raise ValueError(f"clips must be >= 1, got {self.clips}")

    @property
    def block_px(self) -> int:
        return self.size if self.block is None else int(self.block)

    @property
    def n_frames(self) -> int:
        return self.directions * self.repeats

    def at_ratio(self, ratio: float) -> EfficiencySetting:
        """This setting with the read noise for a texture-to-noise ratio ``ratio``: the
        standard deviation of the rest image over that of the noise (:func:`texture_std`)."""
        if not ratio > 0:
            raise ValueError(f"ratio must be > 0, got {ratio}")
        return replace(self, noise=texture_std(self) / float(ratio))


def texture_std(setting: EfficiencySetting) -> float:
    """Standard deviation of the rest image as a fraction of full scale (the ``noise`` unit)."""
    return float(np.std(rest_image(setting))) / float(2 ** int(setting.bit_depth) - 1)


def rest_image(setting: EfficiencySetting) -> NDArray[np.float64]:
    """Noise-free rest image (DN, float) of a setting: speckle intensity times full scale."""
    from ..render.texture import speckle_texture

    tex = speckle_texture(setting.size, grain=setting.grain, contrast=setting.contrast,
                          seed=setting.seed).astype(np.float64)
    return tex * float(2 ** int(setting.bit_depth) - 1)


def true_shifts(setting: EfficiencySetting) -> NDArray[np.float64]:
    """``(T, 2)`` shift ``(dx, dy)`` (px) of every frame; frame ``t`` has direction
    ``t % directions``."""
    k = np.arange(setting.n_frames) % setting.directions
    th = math.pi / 8 + 2 * math.pi * k / setting.directions
    return setting.amplitude_px * np.stack([np.cos(th), np.sin(th)], axis=-1)


def _shift(spectrum: NDArray[np.complex128], s: NDArray[np.float64]) -> NDArray[np.float64]:
    h, w = spectrum.shape
    wy = 2 * np.pi * np.fft.fftfreq(h)[:, None]
    wx = 2 * np.pi * np.fft.fftfreq(w)[None, :]
    return np.fft.ifft2(spectrum * np.exp(-1j * (wx * s[0] + wy * s[1]))).real


def iter_frames(setting: EfficiencySetting, clip: int = 0) -> Iterator[NDArray[np.float32]]:
    """The noisy frames (DN, float32) of clip ``clip``, one at a time (memory independent of
    their number); clip ``c``'s frame ``t`` draws its noise from ``noise_rng(seed, c (T + 1)
    + t)``, so clip 0 is the same for any ``clips``."""
    dn_max = float(2 ** int(setting.bit_depth) - 1)
    spec = np.fft.fft2(rest_image(setting) / dn_max)
    base = int(clip) * (setting.n_frames + 1)
    for t, s in enumerate(true_shifts(setting)):
        clean = _shift(spec, s)
        dn = sensor_dn(clean[None], int(setting.bit_depth), setting.noise * dn_max,
                       setting.shot_noise, setting.full_well, noise_rng(setting.seed, base + t))
        yield dn.astype(np.float32)


def reference_frame(setting: EfficiencySetting, clip: int = 0) -> NDArray[np.float32]:
    """What the extractor is prepared on in clip ``clip`` (DN, float32): the noise-free rest
    image (``"clean"``), one noisy frame at rest drawn like the clip's (``"first"``; noise
    ``noise_rng(seed, c (T + 1) + T)``) or the temporal mean of the clip's frames
    (``"mean"``, a first pass over them)."""
    rest = rest_image(setting)
    if setting.reference == "clean":
        return rest.astype(np.float32)
    if setting.reference == "first":
        dn_max = float(2 ** int(setting.bit_depth) - 1)
        rng = noise_rng(setting.seed, int(clip) * (setting.n_frames + 1) + setting.n_frames)
        return sensor_dn(rest[None] / dn_max, int(setting.bit_depth), setting.noise * dn_max,
                         setting.shot_noise, setting.full_well, rng).astype(np.float32)
    acc = np.zeros(rest.shape)
    for f in iter_frames(setting, clip):
        acc += f
    return (acc / setting.n_frames).astype(np.float32)


def _crb_variance(rest_dn: NDArray[np.float64], setting: EfficiencySetting,
                  transfer: NDArray[np.float64] | None = None) -> NDArray:
    """``(nby, nbx, 2)`` squared per-axis bound (px^2) of each block: of the block's own
    pixels, or (``bound = "footprint"``) of the block pooled by the window of motion
    transfer function ``transfer`` (:func:`vvtbench.scoring.crb.footprint_crb`)."""
    var = crb.noise_variance_dn2(rest_dn / (2 ** int(setting.bit_depth) - 1), setting.bit_depth,
                                 setting.noise * (2 ** int(setting.bit_depth) - 1),
                                 setting.shot_noise, setting.full_well)
    pad = 2
    jp = crb.pixel_fisher(np.pad(rest_dn, pad, mode="wrap"), np.pad(var, pad, mode="wrap"))
    jp = jp[pad:-pad, pad:-pad]
    if setting.bound == "footprint":
        return crb.footprint_crb(jp, setting.block_px, transfer=transfer,
                                 periodic=True)["std_px"] ** 2
    return crb.block_crb(jp, block=setting.block_px)["std_px"] ** 2


def _block_means(d: NDArray, shape: tuple[int, int], block: int) -> NDArray[np.float64]:
    """``(B, nby, nbx, 2)`` mean of grid fields ``d`` ``(B, h, w, 2)`` over each block."""
    H, W = shape
    h, w = d.shape[1:3]
    rows = (np.arange(h) * H // h) // block
    cols = (np.arange(w) * W // w) // block
    nby, nbx = H // block, W // block
    out = np.zeros((d.shape[0], nby, nbx, 2))
    np.add.at(out, (slice(None), rows[:, None], cols[None, :]), d.astype(np.float64))
    counts = np.zeros((nby, nbx))
    np.add.at(counts, (rows[:, None], cols[None, :]), 1.0)
    if np.any(counts == 0):
        raise ValueError(f"block {block} px holds no sample of the {h}x{w} grid")
    return out / counts[None, :, :, None]


def extractor_efficiency(extractor: Any, setting: EfficiencySetting, *,
                         config: Any = None, batch: int = 32) -> dict[str, Any]:
    """Efficiency of one extractor at one setting (module docstring).

    Parameters
    ----------
    extractor : str, type or instance
        Anything :func:`vvtbench.solving.extractors.make_extractor` takes.
    setting : EfficiencySetting
    config : mapping or Config, optional
        Overrides of the extractor's configuration.
    batch : int, default 32
        Frames per batch.

    Returns
    -------
    dict
        The setting, ``texture_noise_ratio``, ``crb_px`` (RMS bound), ``rmse_px``,
        ``bias_px``, ``std_px`` (root of the mean bias^2, clipped at 0, and variance),
        ``bias2_px2`` (unclipped: may be slightly negative from noise; ``rmse^2 = bias2 +
        std^2``), ``eta``, ``eta_variance``, ``eta_se``, ``gain`` (least-squares slope of the
        estimate against the true shift relative to the reference's position) and
        ``gain_se``, ``offset_px`` (RMS of the clips' mean errors, removed with
        ``remove_offset``), ``pooled_px`` (with the footprint bound: the side of the area the
        extractor pools into a block, :func:`vvtbench.scoring.crb.footprint_crb`), ``n_frames``
        (over all clips), ``ms_frame`` (extraction wall time per frame).
    """
    from ..solving.extractors import make_extractor

    ext = make_extractor(extractor, config)
    rest = rest_image(setting)
    shifts = true_shifts(setting)
    K, R, T, C = setting.directions, setting.repeats, setting.n_frames, int(setting.clips)
    nb = setting.size // setting.block_px
    s1 = np.zeros((K, nb, nb, 2))
    s2 = np.zeros((K, nb, nb, 2))
    frame_mse = np.empty(T * C)
    clip_gain = np.empty(C)
    offsets = np.empty(C)
    num = den = 0.0
    elapsed = 0.0
    for c in range(C):
        motion = ext.prepare(reference_frame(setting, c))
        # the truth relative to the reference's position: the rest, or the clip's mean shift
        truth = shifts - shifts.mean(axis=0) if setting.reference == "mean" else shifts
        err = np.empty((T, nb, nb, 2))
        frames = iter_frames(setting, c)
        t0 = 0
        while t0 < T:
            chunk = [next(frames) for _ in range(min(batch, T - t0))]
            tic = time.perf_counter()
            d = np.concatenate(list(motion.iter_displacements(iter(chunk), batch=len(chunk))))
            elapsed += time.perf_counter() - tic
            est = _block_means(np.asarray(d), (setting.size, setting.size), setting.block_px)
            err[t0:t0 + len(chunk)] = est - truth[t0:t0 + len(chunk), None, None, :]
            t0 += len(chunk)
        offset = err.mean(axis=0)
        offsets[c] = math.sqrt(float(np.mean(offset**2)))
        if setting.remove_offset:  # harmless downstream (the spectrum removes the mean)
            err = (err - offset) * math.sqrt(T / (T - 1))
        k = np.arange(T) % K
        np.add.at(s1, k, err)
        np.add.at(s2, k, err**2)
        frame_mse[c * T:(c + 1) * T] = np.mean(err**2, axis=(1, 2, 3))
        proj = np.einsum("tijc,tc->t", err, truth) / (nb * nb)
        n_c, d_c = float(proj.sum()), float(np.sum(truth**2))
        clip_gain[c] = 1.0 + n_c / d_c if d_c > 0 else math.nan
        num, den = num + n_c, den + d_c
    transfer = pooled = None
    if setting.bound == "footprint":
        transfer = motion_transfer(ext, setting)
        pooled = crb.footprint_crb(np.zeros((setting.size, setting.size, 3)), setting.block_px,
                                   transfer=transfer, periodic=True)["pooled_px"]
    crb_var = _crb_variance(rest, setting, transfer)
    n = R * C
    mean = s1 / n
    var = (s2 - n * mean**2) / (n - 1)
    bias2 = mean**2 - var / n
    mse = float(np.mean(s2 / n))
    bound = float(np.mean(crb_var))
    eta = bound / mse if mse > 0 else math.inf
    v = float(np.mean(var))
    gain = 1.0 + num / den if den > 0 else math.nan
    if C > 1:
        gain_se = float(np.std(clip_gain, ddof=1)) / math.sqrt(C)
    elif den > 0:  # frames of one clip share its reference: a lower bound of the error
        gain_se = float(np.std(proj, ddof=1)) * math.sqrt(T) / den
    else:
        gain_se = math.nan
    dn_max = float(2 ** int(setting.bit_depth) - 1)
    return {
        **asdict(setting),
        "extractor": getattr(ext, "name", type(ext).__name__),
        "texture_noise_ratio": float(np.std(rest)) / (setting.noise * dn_max)
        if setting.noise > 0 else math.inf,
        "crb_px": math.sqrt(bound),
        "rmse_px": math.sqrt(mse),
        "bias_px": math.sqrt(max(float(np.mean(bias2)), 0.0)),
        "std_px": math.sqrt(v),
        "bias2_px2": float(np.mean(bias2)),
        "eta": eta,
        "eta_variance": bound / v if v > 0 else math.inf,
        "eta_se": eta * float(np.std(frame_mse, ddof=1)) / math.sqrt(frame_mse.size) / mse
        if mse > 0 else math.nan,
        "gain": gain,
        "gain_se": gain_se,
        "offset_px": math.sqrt(float(np.mean(offsets**2))),
        "pooled_px": pooled,
        "n_frames": T * C,
        "ms_frame": 1e3 * elapsed / (T * C),
    }


def motion_transfer(extractor: Any, setting: EfficiencySetting, *, config: Any = None,
                    eps_px: float = 0.01) -> NDArray[np.float64]:
    """An extractor's response to motion that varies across the frame, ``(size // 2 + 1,)``.

    Frames are the noise-free rest image moved by ``dx = +-eps_px cos(2 pi m x / N)`` (to
    first order, ``I - dx dI/dx`` with the exact spectral derivative), the extractor prepared
    on the rest image; ``T(m)`` is the projection of the difference of its two ``dx`` fields
    on that cosine over ``2 eps_px`` (a constant offset of the extractor cancels): 1 for a
    uniform motion read without bias, falling with ``m`` as the extractor pools pixels (its
    spatial support is the inverse transform).  Wave numbers its grid cannot hold (from
    half the grid's samples on) are 0.
    """
    from ..solving.extractors import make_extractor

    ext = make_extractor(extractor, config)
    rest = rest_image(setting)
    n = setting.size
    spec = np.fft.fft2(rest)
    wx = 2 * np.pi * np.fft.fftfreq(n)[None, :]
    grad_x = np.fft.ifft2(spec * (1j * wx)).real
    x = np.arange(n)
    motion = ext.prepare(rest.astype(np.float32))
    frames = [rest - sign * eps_px * np.cos(2 * np.pi * m * x / n)[None, :] * grad_x
              for m in range(n // 2 + 1) for sign in (1.0, -1.0)]
    d = np.concatenate(list(motion.iter_displacements(
        iter([f.astype(np.float32) for f in frames]), batch=len(frames))))
    d = (d[0::2, ..., 0].astype(np.float64) - d[1::2, ..., 0]) / 2.0
    w = d.shape[2]
    xs = np.arange(w) * n / w
    out = np.zeros(n // 2 + 1)
    for m in range(min(n // 2, w // 2) + 1):
        c = np.cos(2 * np.pi * m * xs / n)
        if m == w // 2 and m > 0:  # the grid's Nyquist: only half the motion is seen
            continue
        out[m] = float(np.mean(d[m].mean(axis=0) * c) / np.mean(c * c)) / eps_px
    return out


def band_information(rest_dn: ArrayLike, n_scales: int = 3) -> dict[str, float]:
    r"""Share of the shift's Fisher information in a steerable pyramid's radial band.

    With white noise the information of a rigid shift is ``sum_w |w|^2 |F(w)|^2 / sigma^2``
    over the image spectrum ``F``.  The pyramid's ``n_scales`` bands pass
    ``W(w) = sum_s radial_s(|w|)^2`` (1 in the middle octaves, tapering to 0 at ``pi`` and
    below ``pi / 2^(n_scales + 1)``).  Returns ``kept`` ``= sum W g^2 / sum g^2`` (``g^2 =
    |w|^2 |F|^2``) and ``weighted`` ``= (sum W g^2)^2 / (sum W^2 g^2 sum g^2)``: the
    efficiency of a linear least-squares shift from the band-filtered image treated as white
    noise, and ``above_band``, ``below_band``: the shares at ``|w| > pi / 2`` and ``|w| < pi /
    2^(n_scales + 1)``.  A description of the texture's spectrum against the band, not a bound
    on the phase extractor (which is not that linear estimator: on coarse speckle it measures
    above ``kept``).
    """
    from ..motion.pyramid import radial_filter

    f = np.asarray(rest_dn, dtype=np.float64)
    spec = np.abs(np.fft.fft2(f - f.mean())) ** 2
    wy = 2 * np.pi * np.fft.fftfreq(f.shape[0])[:, None]
    wx = 2 * np.pi * np.fft.fftfreq(f.shape[1])[None, :]
    rad = np.hypot(wx, wy)
    g2 = rad**2 * spec
    wgt = sum(radial_filter(rad, s) ** 2 for s in range(int(n_scales)))
    total = float(g2.sum())
    return {
        "kept": float((wgt * g2).sum()) / total,
        "weighted": float((wgt * g2).sum()) ** 2 / (float((wgt**2 * g2).sum()) * total),
        "above_band": float(g2[rad > np.pi / 2].sum()) / total,
        "below_band": float(g2[rad < np.pi / 2 ** (n_scales + 1)].sum()) / total,
    }


@dataclass
class KnownTextureConfig:
    block: int = field(default=8, metadata={"help": "block side (px); one shift per block",
                                            "ge": 1})
    iterations: int = field(default=4, metadata={"help": "Gauss-Newton iterations", "ge": 1})


class KnownTextureShift:
    """The Cramér-Rao-achieving estimator: per block, Gauss-Newton on the known texture.

    The reference given to ``prepare`` is taken as the noise-free, band-limited periodic
    texture; the model of a block is that texture shifted by the block's ``s``, evaluated
    exactly from its spectrum (separable DFT at the block's pixels), with its exact spectral
    gradient as the Jacobian.  Yields one sample per block at the block's corner.
    """

    name = "known-texture"
    version = "1"
    description = "Gauss-Newton shift per block on the known noise-free texture (ideal)"
    Config = KnownTextureConfig

    def __init__(self, config: KnownTextureConfig | None = None) -> None:
        self.config = config or KnownTextureConfig()

    def prepare(self, reference: ArrayLike) -> _KnownTextureMotion:
        return _KnownTextureMotion(np.asarray(reference, dtype=np.float64), self.config)


class _KnownTextureMotion:
    def __init__(self, reference: NDArray[np.float64], config: KnownTextureConfig) -> None:
        if reference.ndim != 2:
            raise ValueError(f"reference must be 2-D, got shape {reference.shape}")
        H, W = reference.shape
        b = int(config.block)
        if H % b or W % b:
            raise ValueError(f"block {b} must divide the frame size {H}x{W}")
        self.config = config
        self.shape = (H, W)
        self.grid_shape = (H // b, W // b)
        self.confidence = None
        self.grid_confidence = None
        self._spec = np.fft.fft2(reference) / (H * W)
        self._wy = 2 * np.pi * np.fft.fftfreq(H)
        self._wx = 2 * np.pi * np.fft.fftfreq(W)
        by, bx = self.grid_shape
        self._ys = (np.arange(by)[:, None] * b + np.arange(b)[None, :]).astype(np.float64)
        self._xs = (np.arange(bx)[:, None] * b + np.arange(b)[None, :]).astype(np.float64)

    def _model(self, s: NDArray[np.float64]) -> tuple[NDArray, NDArray, NDArray]:
        """Texture shifted by ``s`` ``(by, bx, 2)`` at each block's pixels and its x/y
        gradients, each ``(by, bx, b, b)``."""
        if self.grid_shape == (1, 1):  # one block: the whole periodic frame, by FFT
            H, W = self.shape
            ramp = self._spec * np.exp(-1j * (self._wx[None, :] * s[0, 0, 0]
                                              + self._wy[:, None] * s[0, 0, 1])) * (H * W)
            out = [np.fft.ifft2(ramp * f).real[None, None]
                   for f in (1.0, 1j * self._wx[None, :], 1j * self._wy[:, None])]
            return out[0], out[1], out[2]
        ey = np.exp(1j * self._wy[None, None, None, :]
                    * (self._ys[:, None, :, None] - s[..., 1, None, None]))  # (by, bx, b, H)
        ex = np.exp(1j * self._wx[None, None, None, :]
                    * (self._xs[None, :, :, None] - s[..., 0, None, None]))  # (by, bx, b, W)
        rows = ey @ self._spec  # (by, bx, b, W)
        rows_dy = (ey * (1j * self._wy)) @ self._spec
        ext = np.swapaxes(ex, -1, -2)
        val = (rows @ ext).real
        gx = (rows @ (ext * (1j * self._wx)[:, None])).real
        gy = (rows_dy @ ext).real
        return val, gx, gy

    def estimate(self, frame: ArrayLike) -> NDArray[np.float64]:
        """``(by, bx, 2)`` shift of each block of one frame (px)."""
        y = np.asarray(frame, dtype=np.float64)
        b = int(self.config.block)
        by, bx = self.grid_shape
        obs = y.reshape(by, b, bx, b).transpose(0, 2, 1, 3)
        s = np.zeros((by, bx, 2))
        for _ in range(int(self.config.iterations)):
            val, gx, gy = self._model(s)
            r = obs - val
            jx, jy = -gx, -gy  # d model / d s
            a = np.stack([(jx * jx).sum((-2, -1)), (jx * jy).sum((-2, -1)),
                          (jy * jy).sum((-2, -1))])
            rhs = np.stack([(jx * r).sum((-2, -1)), (jy * r).sum((-2, -1))])
            det = a[0] * a[2] - a[1] ** 2
            with np.errstate(divide="ignore", invalid="ignore"):
                step = np.stack([(a[2] * rhs[0] - a[1] * rhs[1]) / det,
                                 (a[0] * rhs[1] - a[1] * rhs[0]) / det], axis=-1)
            s = s + np.nan_to_num(step)
        return s

    def iter_displacements(self, frames, batch: int = 32) -> Iterator[NDArray[np.float32]]:
        buf = []
        for fr in frames:
            buf.append(self.estimate(fr).astype(np.float32))
            if len(buf) >= batch:
                yield np.stack(buf)
                buf = []
        if buf:
            yield np.stack(buf)

    def describe(self) -> dict[str, Any]:
        return {**asdict(self.config), "reference": "known noise-free texture",
                "grid_shape": list(self.grid_shape)}
