"""FFT-based complex steerable pyramid (Portilla--Simoncelli polar-separable filters).

The filters are built once per frame size (:func:`get_pyramid` caches them) and applied to
batches of frames ``(B, H, W)`` with :mod:`scipy.fft` in single precision.

Conventions
-----------
* Pixel coordinates: ``x`` = column index (to the right), ``y`` = row index (down).
* Spatial frequencies are angular, in radians per full-resolution pixel; the Nyquist
  frequency is ``pi``.  Band ``(s, k)`` (scale ``s = 0`` finest) has radial centre
  frequency ``pi / 2**(s + 1)`` (wavelength ``2**(s + 2)`` px) and passes only the half
  plane of frequencies within 90 degrees of its orientation ``theta_k = pi * k / K``, so its
  coefficients are complex (analytic along ``theta_k``).
* With ``downsample=True`` the spectrum of scale ``s`` is cropped to
  ``ceil(H / 2**s) x ceil(W / 2**s)`` (lossless: the band is zero outside), and the
  coefficients are scaled so that they equal the full-resolution coefficients sampled at
  full-resolution positions ``(row * stride[0], col * stride[1])``.
* With ``decimate=True`` (requires ``downsample`` and ``H``, ``W`` divisible by
  ``2**n_scales``) scale ``s`` is sampled every ``2**(s + 1)`` pixels: the cropped spectrum
  is folded (aliases summed) onto a grid half as large per axis, which gives the *exact*
  full-resolution coefficients at positions ``2**(s + 1) * (row, col)`` for half the FFT
  size.  This is the sampling of the dual-tree complex wavelet transform: a one-sided
  (analytic) band needs about half the samples of a real band of the same width.  Only the
  quadrants of the spectrum where a band's filter is non-zero are multiplied and summed.
* Boundaries are periodic (FFT).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import scipy.fft as sfft
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "Band",
    "SteerablePyramid",
    "angular_filter",
    "can_decimate",
    "get_pyramid",
    "max_scales",
    "radial_filter",
]


@dataclass(frozen=True)
class Band:
    """Description of one oriented sub-band.

    Attributes
    ----------
    scale : int
        Scale index, 0 = finest.
    orientation : int
        Orientation index ``k`` in ``0 .. n_orientations - 1``.
    theta : float
        Orientation ``pi * k / n_orientations`` in radians, measured from the +x (column)
        axis towards +y (rows, down).
    frequency : tuple of float
        Centre spatial-frequency vector ``(wx, wy)`` in radians per full-resolution pixel,
        i.e. ``pi / 2**(scale + 1) * (cos theta, sin theta)``.
    shape : tuple of int
        Shape ``(h, w)`` of the coefficient array of this band.
    stride : tuple of float
        Full-resolution pixels per coefficient sample ``(H / h, W / w)``.
    """

    scale: int
    orientation: int
    theta: float
    frequency: tuple[float, float]
    shape: tuple[int, int]
    stride: tuple[float, float]

    @property
    def direction(self) -> tuple[float, float]:
        """Unit vector ``(cos theta, sin theta)`` (x, y) of the band orientation."""
        return (math.cos(self.theta), math.sin(self.theta))

    @property
    def radial_frequency(self) -> float:
        """Radial centre frequency ``pi / 2**(scale + 1)`` in rad/pixel."""
        return math.pi / 2 ** (self.scale + 1)


def max_scales(shape: tuple[int, int]) -> int:
    """Largest number of scales allowed for a frame shape, ``floor(log2(min(H, W))) - 2``.

    The coarsest band then still has at least 8 samples per side (same rule as pyrtools).
    """
    return max(int(math.floor(math.log2(min(shape)))) - 2, 0)


def radial_filter(omega: NDArray[np.floating], scale: int) -> NDArray[np.float64]:
    """Radial transfer function of band ``scale`` (raised cosine in log2 frequency).

    Parameters
    ----------
    omega : ndarray
        Radial frequency ``|w|`` in radians per full-resolution pixel.
    scale : int
        Scale index, 0 = finest.

    Returns
    -------
    ndarray
        ``L_s(omega) * H_s(omega)``, which is 1 at ``pi / 2**(scale + 1)``, zero below
        ``pi / 2**(scale + 2)`` and above ``pi / 2**scale``.  Summed over scales (with the
        residual high- and low-pass bands) the squares tile the spectrum.
    """
    with np.errstate(divide="ignore"):
        x = np.log2(np.asarray(omega, dtype=np.float64) / np.pi)
    hi = np.cos(0.5 * np.pi * np.clip(-(scale + 1) - x, 0.0, 1.0))
    lo = np.sin(0.5 * np.pi * np.clip(-scale - x, 0.0, 1.0))
    return lo * hi


def angular_filter(
    angle: NDArray[np.floating], orientation: int, n_orientations: int
) -> NDArray[np.float64]:
    """One-sided angular transfer function (complex steerable pyramid).

    Parameters
    ----------
    angle : ndarray
        Frequency direction ``atan2(wy, wx)`` in radians.
    orientation : int
        Orientation index ``k``; the band is centred on ``theta_k = pi * k / n_orientations``.
    n_orientations : int
        Number of orientations ``K``; the filter order is ``K - 1``.

    Returns
    -------
    ndarray
        ``2 * alpha * cos(angle - theta_k)**(K - 1)`` where ``cos(angle - theta_k) > 0``,
        zero elsewhere, with ``alpha`` the steerable-pyramid normalisation.
    """
    order = n_orientations - 1
    const = (
        (2.0 ** (2 * order))
        * math.factorial(order) ** 2
        / (n_orientations * math.factorial(2 * order))
    )
    c = np.cos(np.asarray(angle, dtype=np.float64) - np.pi * orientation / n_orientations)
    return 2.0 * math.sqrt(const) * np.where(c > 0, c, 0.0) ** order


def _int_freqs(n: int) -> NDArray[np.intp]:
    """Integer DFT frequencies in FFT order (``fftfreq(n) * n``)."""
    return np.rint(np.fft.fftfreq(n) * n).astype(np.intp)


class SteerablePyramid:
    """Complex steerable pyramid for a fixed frame shape (filters precomputed).

    Prefer :func:`get_pyramid`, which caches instances by shape and parameters.

    Parameters
    ----------
    shape : tuple of int
        Frame shape ``(H, W)``.
    n_scales : int, default 3
        Number of octave scales, ``1 <= n_scales <= max_scales(shape)``.
    n_orientations : int, default 4
        Number of orientations, ``>= 2``.
    downsample : bool, default True
        Crop the spectrum of each scale (scale ``s`` sampled every ``~2**s`` pixels).
    decimate : bool, default False
        Sample scale ``s`` every ``2**(s + 1)`` pixels (spectrum folding, exact samples).
        Needs ``downsample`` and ``H``, ``W`` divisible by ``2**n_scales``.

    Attributes
    ----------
    bands : tuple of Band
        Bands in scale-major order ``(s, k)``.
    """

    def __init__(
        self,
        shape: tuple[int, int],
        n_scales: int = 3,
        n_orientations: int = 4,
        downsample: bool = True,
        decimate: bool = False,
    ) -> None:
        if len(shape) != 2:
            raise ValueError(f"shape must be (H, W), got {shape!r}")
        H, W = (int(n) for n in shape)
        if H < 8 or W < 8:
            raise ValueError(f"frames must be at least 8x8 pixels, got {H}x{W}")
        if int(n_orientations) != n_orientations or n_orientations < 2:
            raise ValueError(f"n_orientations must be an integer >= 2, got {n_orientations!r}")
        if int(n_scales) != n_scales or n_scales < 1:
            raise ValueError(f"n_scales must be an integer >= 1, got {n_scales!r}")
        if n_scales > max_scales((H, W)):
            raise ValueError(
                f"n_scales={n_scales} is too many for {H}x{W} frames: at most "
                f"{max_scales((H, W))} (floor(log2(min(H, W))) - 2)"
            )
        self.shape: tuple[int, int] = (H, W)
        self.n_scales = int(n_scales)
        self.n_orientations = int(n_orientations)
        self.downsample = bool(downsample)
        self.decimate = bool(decimate)
        if self.decimate and not can_decimate((H, W), self.n_scales, self.downsample):
            raise ValueError(
                f"decimate=True needs downsample=True and H, W divisible by 2**n_scales = "
                f"{2**self.n_scales}, got {H}x{W}"
            )
        wr = W // 2 + 1

        bands: list[Band] = []
        self._filters: list[NDArray[np.float32]] = []  # per scale (K, h, w), read-only
        self._index: list[NDArray[np.intp]] = []  # per scale flat index into rfft2 output
        self._conj: list[NDArray[np.bool_]] = []  # per scale: take the complex conjugate
        self._omega: list[tuple[NDArray[np.float32], NDArray[np.float32]]] = []
        for s in range(self.n_scales):
            if self.downsample:
                h, w = -(-H // 2**s), -(-W // 2**s)
            else:
                h, w = H, W
            ky, kx = _int_freqs(h)[:, None], _int_freqs(w)[None, :]
            neg = np.broadcast_to(kx < 0, (h, w))
            rows = np.where(neg, -ky, ky) % H
            cols = np.abs(np.broadcast_to(kx, (h, w)))
            self._index.append(np.ascontiguousarray(rows * wr + cols).ravel())
            self._conj.append(np.ascontiguousarray(neg))
            wy = 2.0 * np.pi * ky / H
            wx = 2.0 * np.pi * kx / W
            rad = radial_filter(np.hypot(wx, wy), s)
            ang = np.arctan2(wy, wx)
            # ifft of the cropped grid divides by h*w instead of H*W
            norm = (h * w) / (H * W)
            filt = np.stack(
                [
                    norm * rad * angular_filter(ang, k, self.n_orientations)
                    for k in range(self.n_orientations)
                ]
            ).astype(np.float32)
            filt.flags.writeable = False
            self._filters.append(filt)
            owx = np.broadcast_to(wx, (h, w)).astype(np.float32)
            owy = np.broadcast_to(wy, (h, w)).astype(np.float32)
            owx.flags.writeable = False
            owy.flags.writeable = False
            self._omega.append((owx, owy))
            wc = math.pi / 2 ** (s + 1)
            bh, bw = (h // 2, w // 2) if self.decimate else (h, w)
            for k in range(self.n_orientations):
                th = math.pi * k / self.n_orientations
                bands.append(
                    Band(
                        scale=s,
                        orientation=k,
                        theta=th,
                        frequency=(wc * math.cos(th), wc * math.sin(th)),
                        shape=(bh, bw),
                        stride=(H / bh, W / bw),
                    )
                )
        self.bands: tuple[Band, ...] = tuple(bands)
        if self.decimate:
            self._build_folding()

    def _build_folding(self) -> None:
        """Precompute, per scale, the quadrant sources and per band the non-zero blocks.

        Scale ``s`` crop ``(hc, wc) = (H, W) / 2**s`` is folded onto ``(h, w) = (hc, wc) / 2``.
        In FFT order the crop splits into quadrants ``(a, b)``: rows ``a = 0`` hold
        ``ky in [0, h)``, ``a = 1`` hold ``ky in [-h, 0)``; columns likewise with ``kx``.
        Quadrants with ``b = 0`` are views of the ``rfft2`` output; ``b = 1`` (``kx < 0``)
        come from its Hermitian mirror (one gather per scale).
        """
        H, W = self.shape
        self._neg_rows: list[NDArray[np.intp]] = []
        self._blocks: list[list[tuple[int, int, NDArray[np.float32], NDArray[np.float32]]]] = []
        self._block_omega: list[dict[tuple[int, int], tuple[NDArray, NDArray]]] = []
        for s in range(self.n_scales):
            hc, wc = H // 2**s, W // 2**s
            h, w = hc // 2, wc // 2
            i = np.arange(h)
            # kx < 0 quadrants: conj F[(-ky) mod H, -kx]; rows for a = 0 then a = 1
            self._neg_rows.append(np.concatenate([(-i) % H, h - i]).astype(np.intp))
            filt = self._filters[s] * np.float32(0.25)  # ifft over h*w, not hc*wc
            owx, owy = self._omega[s]
            omega = {}
            for a in (0, 1):
                for b in (0, 1):
                    sl = (slice(a * h, (a + 1) * h), slice(b * w, (b + 1) * w))
                    omega[(a, b)] = (owx[sl].copy(), owy[sl].copy())
            self._block_omega.append(omega)
            for k in range(self.n_orientations):
                blocks = []
                for a in (0, 1):
                    for b in (0, 1):
                        fb = np.ascontiguousarray(filt[k, a * h : (a + 1) * h, b * w : (b + 1) * w])
                        if np.any(fb != 0):
                            # interleaved (re, im) copy: complex * real as a float32 product
                            fb2 = np.repeat(fb, 2, axis=-1)
                            fb.flags.writeable = False
                            fb2.flags.writeable = False
                            blocks.append((a, b, fb, fb2))
                self._blocks.append(blocks)

    def _quadrants(
        self, spec: NDArray[np.complex64], scale: int
    ) -> dict[tuple[int, int], NDArray[np.complex64]]:
        """The four ``(B, h, w)`` quadrants of a scale's cropped two-sided spectrum."""
        H, W = self.shape
        h, w = H // 2 ** (scale + 1), W // 2 ** (scale + 1)
        # -kx = 1 .. w, gathered with contiguous rows, then reversed and conjugated
        g = np.take(spec[:, :, 1 : w + 1], self._neg_rows[scale], axis=1)
        neg = np.empty_like(g)
        np.conjugate(g[:, :, ::-1], out=neg)
        return {
            (0, 0): spec[:, :h, :w],
            (1, 0): spec[:, H - h :, :w],
            (0, 1): neg[:, :h],
            (1, 1): neg[:, h:],
        }

    def _iter_bands_decimated(
        self, frames: ArrayLike, gradient: bool, workers: int | None
    ) -> Iterator[tuple]:
        spec = self.spectrum(frames, workers=workers)
        B = spec.shape[0]
        i = 0
        tmp: NDArray[np.complex64] | None = None
        for s in range(self.n_scales):
            quad = self._quadrants(spec, s)
            h, w = self.bands[i].shape
            if tmp is None or tmp.shape != (B, h, w):
                tmp = np.empty((B, h, w), np.complex64)
            for _ in range(self.n_orientations):
                band = self.bands[i]
                blocks = self._blocks[i]
                i += 1
                X = np.empty((B, h, w), np.complex64)
                D = np.zeros((2, B, h, w), np.complex64) if gradient else None
                for j, (a, b, _, fb2) in enumerate(blocks):
                    q = quad[(a, b)].view(np.float32)
                    if j == 0:
                        np.multiply(q, fb2, out=X.view(np.float32))
                        if D is None:
                            continue
                        tmp[...] = X
                    else:
                        np.multiply(q, fb2, out=tmp.view(np.float32))
                        X += tmp
                    if D is not None:
                        wx, wy = self._block_omega[s][(a, b)]
                        D[0] += tmp * (1j * wx)
                        D[1] += tmp * (1j * wy)
                c = sfft.ifft2(X, axes=(-2, -1), workers=workers, overwrite_x=True)
                if D is None:
                    yield band, c
                else:
                    g = sfft.ifft2(D, axes=(-2, -1), workers=workers, overwrite_x=True)
                    yield band, c, g

    def __repr__(self) -> str:
        return (
            f"SteerablePyramid(shape={self.shape}, n_scales={self.n_scales}, "
            f"n_orientations={self.n_orientations}, downsample={self.downsample}, "
            f"decimate={self.decimate})"
        )

    # ------------------------------------------------------------------ helpers
    def _check_frames(self, frames: ArrayLike) -> NDArray[np.float32]:
        x = np.asarray(frames)
        if x.ndim == 2:
            x = x[None]
        if x.ndim != 3:
            raise ValueError(f"frames must have shape (B, H, W) or (H, W), got {x.shape}")
        if x.shape[1:] != self.shape:
            raise ValueError(f"frame size {x.shape[1:]} does not match the pyramid's {self.shape}")
        if np.iscomplexobj(x):
            raise ValueError("frames must be real-valued")
        return x.astype(np.float32, copy=False)

    def band_frequencies(self, scale: int) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """Angular frequency grids ``(wx, wy)`` (rad/full-res pixel) of a scale's spectrum."""
        return self._omega[scale]

    def filters(self, scale: int) -> NDArray[np.float32]:
        """Transfer functions ``(K, h, w)`` of a scale (FFT order, crop normalisation folded in)."""
        return self._filters[scale]

    def spectrum(self, frames: ArrayLike, workers: int | None = None) -> NDArray[np.complex64]:
        """``rfft2`` of a batch of frames, ``(B, H, W // 2 + 1)`` complex64."""
        x = self._check_frames(frames)
        return sfft.rfft2(x, axes=(-2, -1), workers=workers)

    def scale_spectrum(
        self, spec: NDArray[np.complexfloating], scale: int
    ) -> NDArray[np.complex64]:
        """Full (two-sided) spectrum of a scale's cropped grid from an ``rfft2`` spectrum.

        Parameters
        ----------
        spec : ndarray
            Output of :meth:`spectrum`, shape ``(B, H, W // 2 + 1)``.
        scale : int
            Scale index.

        Returns
        -------
        ndarray
            ``(B, h, w)`` complex64 in FFT order (Hermitian symmetry used for ``kx < 0``).
        """
        B = spec.shape[0]
        h, w = self._conj[scale].shape
        out = np.take(spec.reshape(B, -1), self._index[scale], axis=1).reshape(B, h, w)
        np.conjugate(out, out=out, where=self._conj[scale][None])
        return out.astype(np.complex64, copy=False)

    # ------------------------------------------------------------------ transforms
    def iter_bands(
        self,
        frames: ArrayLike,
        *,
        gradient: bool = False,
        workers: int | None = None,
    ) -> Iterator[
        tuple[Band, NDArray[np.complex64]]
        | tuple[Band, NDArray[np.complex64], NDArray[np.complex64]]
    ]:
        """Yield the bands one at a time (low memory).

        Parameters
        ----------
        frames : array_like
            ``(B, H, W)`` (or a single ``(H, W)`` frame) real images.
        gradient : bool, default False
            Also yield the spatial derivatives of the coefficients, ``(2, B, h, w)`` =
            ``(d/dx, d/dy)`` per full-resolution pixel, computed spectrally (exact).
        workers : int, optional
            Passed to :mod:`scipy.fft`.

        Yields
        ------
        band : Band
        coeffs : ndarray
            ``(B, h, w)`` complex64 coefficients.
        grad : ndarray
            Only if ``gradient``: ``(2, B, h, w)`` complex64.
        """
        if self.decimate:
            yield from self._iter_bands_decimated(frames, gradient, workers)
            return
        spec = self.spectrum(frames, workers=workers)
        i = 0
        for s in range(self.n_scales):
            S = self.scale_spectrum(spec, s)
            filt = self._filters[s]
            for k in range(self.n_orientations):
                band = self.bands[i]
                i += 1
                X = S * filt[k]
                if gradient:
                    wx, wy = self._omega[s]
                    D = np.stack([X * (1j * wx), X * (1j * wy)]).astype(np.complex64)
                    c = sfft.ifft2(X, axes=(-2, -1), workers=workers, overwrite_x=True)
                    g = sfft.ifft2(D, axes=(-2, -1), workers=workers, overwrite_x=True)
                    yield band, c, g
                else:
                    yield band, sfft.ifft2(X, axes=(-2, -1), workers=workers, overwrite_x=True)

    def decompose(
        self, frames: ArrayLike, workers: int | None = None
    ) -> list[NDArray[np.complex64]]:
        """All band coefficients of a batch.

        Parameters
        ----------
        frames : array_like
            ``(B, H, W)`` (or ``(H, W)``) real images.
        workers : int, optional
            Passed to :mod:`scipy.fft`.

        Returns
        -------
        list of ndarray
            One ``(B, h, w)`` complex64 array per band, in the order of :attr:`bands`.
        """
        return [c for _, c in self.iter_bands(frames, workers=workers)]


def can_decimate(shape: tuple[int, int], n_scales: int, downsample: bool = True) -> bool:
    """Whether ``decimate=True`` is possible: ``downsample`` and ``H``, ``W`` divisible by
    ``2**n_scales``."""
    m = 2 ** int(n_scales)
    return bool(downsample) and shape[0] % m == 0 and shape[1] % m == 0


@lru_cache(maxsize=8)
def _cached(
    shape: tuple[int, int], n_scales: int, n_orientations: int, downsample: bool, decimate: bool
) -> SteerablePyramid:
    return SteerablePyramid(shape, n_scales, n_orientations, downsample, decimate)


def get_pyramid(
    shape: tuple[int, int],
    n_scales: int = 3,
    n_orientations: int = 4,
    downsample: bool = True,
    decimate: bool = False,
) -> SteerablePyramid:
    """Cached :class:`SteerablePyramid` for a frame shape and parameters.

    Parameters
    ----------
    shape : tuple of int
        Frame shape ``(H, W)``.
    n_scales, n_orientations, downsample, decimate
        See :class:`SteerablePyramid`.

    Returns
    -------
    SteerablePyramid
        Shared instance (its filter arrays are read-only).
    """
    return _cached(
        tuple(int(n) for n in shape), n_scales, n_orientations, bool(downsample), bool(decimate)
    )
