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
times with fresh noise.

Estimate and bound
------------------
The extractor is prepared on the noise-free rest image (the known texture the bound
assumes) and measures every frame.  Its estimate of a block's shift is the mean of its
displacement field over the grid samples inside the block (``block`` px; ``None`` = the whole
frame, which, being periodic, has no edges).  The bound is the ruler's
(:func:`vvtbench.render.crb.block_crb` of :func:`~vvtbench.render.crb.pixel_fisher` with
:func:`~vvtbench.render.crb.noise_variance_dn2`), on the rest image padded periodically so
its gradient has no reflected edges.  Per direction, block and axis the ``repeats`` errors
give the bias (``mean^2 - var / repeats``, unbiased) and the variance (``ddof = 1``), which
add up to the mean squared error.  Then

* ``eta = mean(sigma_CRB^2) / MSE`` (bias included) and ``eta_variance`` (bias left out);
* ``eta_se``: its Monte-Carlo standard error from the spread of the per-frame squared errors.

An unbiased estimator has ``eta <= 1``; :class:`KnownTextureShift` (Gauss-Newton on the
true texture) reaches it.  With a block smaller than the frame a windowed extractor also uses
pixels just outside the block, so its ``eta`` can exceed 1 by the share of its window that
spills over; the whole frame has no such spill.

:func:`band_information` says how much of the bound's Fisher information lies in the band
a steerable pyramid keeps.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..render import crb
from ..render.sensor import FULL_WELL_ELECTRONS, noise_rng, sensor_dn

__all__ = [
    "EfficiencySetting",
    "KnownTextureShift",
    "band_information",
    "extractor_efficiency",
    "rest_image",
    "true_shifts",
    "iter_frames",
]


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

    @property
    def block_px(self) -> int:
        return self.size if self.block is None else int(self.block)

    @property
    def n_frames(self) -> int:
        return self.directions * self.repeats


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


def iter_frames(setting: EfficiencySetting) -> Iterator[NDArray[np.float32]]:
    """The noisy frames (DN, float32), one at a time (memory independent of their number)."""
    dn_max = float(2 ** int(setting.bit_depth) - 1)
    spec = np.fft.fft2(rest_image(setting) / dn_max)
    for t, s in enumerate(true_shifts(setting)):
        clean = _shift(spec, s)
        dn = sensor_dn(clean[None], int(setting.bit_depth), setting.noise * dn_max,
                       setting.shot_noise, setting.full_well, noise_rng(setting.seed, t))
        yield dn.astype(np.float32)


def _crb_variance(rest_dn: NDArray[np.float64], setting: EfficiencySetting) -> NDArray:
    """``(nby, nbx, 2)`` squared per-axis bound (px^2) of each block."""
    var = crb.noise_variance_dn2(rest_dn / (2 ** int(setting.bit_depth) - 1), setting.bit_depth,
                                 setting.noise * (2 ** int(setting.bit_depth) - 1),
                                 setting.shot_noise, setting.full_well)
    pad = 2
    jp = crb.pixel_fisher(np.pad(rest_dn, pad, mode="wrap"), np.pad(var, pad, mode="wrap"))
    jp = jp[pad:-pad, pad:-pad]
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
        The setting, ``crb_px`` (RMS bound), ``rmse_px``, ``bias_px``, ``std_px`` (root of
        the mean bias^2, clipped at 0, and variance), ``bias2_px2`` (unclipped: may be slightly
        negative from noise; ``rmse^2 = bias2 + std^2``), ``eta``, ``eta_variance``,
        ``eta_se``, ``n_frames``, ``ms_frame`` (extraction wall time per frame).
    """
    from ..solving.extractors import make_extractor

    ext = make_extractor(extractor, config)
    rest = rest_image(setting)
    crb_var = _crb_variance(rest, setting)
    motion = ext.prepare(rest.astype(np.float32))
    truth = true_shifts(setting)
    K, R = setting.directions, setting.repeats
    nb = setting.size // setting.block_px
    s1 = np.zeros((K, nb, nb, 2))
    s2 = np.zeros((K, nb, nb, 2))
    frame_mse = np.empty(setting.n_frames)
    t0, elapsed = 0, 0.0
    frames = iter_frames(setting)
    while t0 < setting.n_frames:
        chunk = [next(frames) for _ in range(min(batch, setting.n_frames - t0))]
        tic = time.perf_counter()
        d = np.concatenate(list(motion.iter_displacements(iter(chunk), batch=len(chunk))))
        elapsed += time.perf_counter() - tic
        est = _block_means(np.asarray(d), (setting.size, setting.size), setting.block_px)
        err = est - truth[t0:t0 + len(chunk), None, None, :]
        k = np.arange(t0, t0 + len(chunk)) % K
        np.add.at(s1, k, err)
        np.add.at(s2, k, err**2)
        frame_mse[t0:t0 + len(chunk)] = np.mean(err**2, axis=(1, 2, 3))
        t0 += len(chunk)
    mean = s1 / R
    var = (s2 - R * mean**2) / (R - 1)
    bias2 = mean**2 - var / R
    mse = float(np.mean(s2 / R))
    bound = float(np.mean(crb_var))
    eta = bound / mse if mse > 0 else math.inf
    v = float(np.mean(var))
    return {
        **asdict(setting),
        "extractor": getattr(ext, "name", type(ext).__name__),
        "crb_px": math.sqrt(bound),
        "rmse_px": math.sqrt(mse),
        "bias_px": math.sqrt(max(float(np.mean(bias2)), 0.0)),
        "std_px": math.sqrt(v),
        "bias2_px2": float(np.mean(bias2)),
        "eta": eta,
        "eta_variance": bound / v if v > 0 else math.inf,
        "eta_se": eta * float(np.std(frame_mse, ddof=1)) / math.sqrt(frame_mse.size) / mse
        if mse > 0 else math.nan,
        "n_frames": setting.n_frames,
        "ms_frame": 1e3 * elapsed / setting.n_frames,
    }


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
