"""The shipped motion extractors (plug-ins of the ``vvtbench.extractors`` group).

An extractor turns a video into per-pixel displacement fields relative to a reference image:
:func:`vvtbench.modes.extract_modes` gives it the temporal mean of the record (a first pass
over the frames; ``reference="first"``: the first frame), so that the reference holds almost
none of the sensor noise of a single frame.  Contract (checked by
:func:`vvtbench.solving.extractors.validate_extractor_class`)::

    name: str                  # unique, lower-case
    version: str
    description: str           # one line
    Config: type               # dataclass, every field has a default and help metadata
    def __init__(self, config: Config | None = None): ...
    def prepare(self, reference: ndarray (H, W) float32) -> Motion

and the returned ``Motion`` object has

* ``shape`` ``(H, W)``, ``grid_shape`` ``(h, w)`` of the fields it yields (``(H, W)`` or a
  coarser grid whose sample ``(i, j)`` sits at pixel ``(i H / h, j W / w)``; modes are
  upsampled bilinearly to ``(H, W)`` at the end);
* ``confidence`` ``(H, W)`` and ``grid_confidence`` ``(h, w)``: non-negative per-pixel
  reliability of the reference frame (e.g. texture strength), or ``None`` for uniform;
* ``iter_displacements(frames, batch) -> Iterator[(B, h, w, 2) float32]``: the frames
  (an iterable of ``(H, W)`` arrays, the record in order), displacement of each relative to
  the reference, ``[..., 0] = dx`` (right), ``[..., 1] = dy`` (down) in full-resolution
  pixels, in batches, in order;
* ``describe() -> dict``: JSON-ready parameters stored in the result's metadata.

This streams: the mode stage stores the batches (:class:`vvtbench.modes.DisplacementStore`)
and never needs the whole video in memory.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .phase import PhaseMotion

__all__ = ["FarnebackExtractor", "FarnebackMotion", "PhaseExtractor"]


@dataclass
class PhaseConfig:
    n_scales: int = field(default=3, metadata={"help": "pyramid scales"})
    n_orientations: int = field(default=4, metadata={"help": "pyramid orientations (>= 2)",
                                                     "ge": 2})
    sigma: float = field(default=2.0, metadata={
        "ge": 0, "help": "Gaussian smoothing of the phase normal equations (px); >= 1.5 decimates"})
    outlier_fraction: float = field(default=0.01, metadata={
        "ge": 0, "lt": 1,
        "help": "fraction of largest per-frame displacements discarded before smoothing"})
    workers: int | None = field(default=None, metadata={"help": "threads (-1 = all CPUs)"})
    frequency: str = field(default="local", metadata={
        "choices": ("local", "centre", "midpoint"),
        "help": "phase-to-pixels frequency: 'local' (reference), 'centre' (band centre) or "
                "'midpoint' (mean of reference and current frame; second-order accurate)"})
    refine: int = field(default=1, metadata={
        "ge": 0, "le": 10,
        "help": "passes solving again with the phases unwrapped, dropped and cleaned of "
                "outliers about the estimate (not about zero, which pulls noisy motion low)"})


class PhaseExtractor:
    """Phase-based motion from a complex steerable pyramid (:class:`PhaseMotion`), default."""

    name = "phase"
    version = "2"
    description = "phase-based motion, complex steerable pyramid (Wadhwa/Davis; default)"
    Config = PhaseConfig

    def __init__(self, config: PhaseConfig | None = None) -> None:
        self.config = config or PhaseConfig()

    def prepare(self, reference: ArrayLike) -> _PhaseStream:
        c = self.config
        pm = PhaseMotion(
            reference,
            c.n_scales,
            c.n_orientations,
            sigma=c.sigma,
            outlier_fraction=c.outlier_fraction,
            workers=c.workers,
            frequency=c.frequency,
            refine=c.refine,
        )
        return _PhaseStream(pm, c)


class _PhaseStream:
    """Adapter: a :class:`PhaseMotion` yielding its working grid (4x fewer samples)."""

    def __init__(self, pm: PhaseMotion, config: PhaseConfig) -> None:
        self.pm = pm
        self.config = config
        self.shape = pm.shape
        self.grid_shape = pm.grid_shape
        self.confidence = pm.confidence
        self.grid_confidence = pm.grid_confidence

    def iter_displacements(self, frames: Iterable[ArrayLike], batch: int = 32) -> Iterator:
        return self.pm.iter_displacements(frames, batch=batch, full_resolution=False)

    def describe(self) -> dict[str, Any]:
        return {**asdict(self.config), "decimate": self.pm.decimate,
                "grid_shape": list(self.pm.grid_shape)}


@dataclass
class FarnebackConfig:
    pyr_scale: float = field(default=0.5, metadata={"help": "pyramid scale between levels",
                                                    "gt": 0, "lt": 1})
    levels: int = field(default=3, metadata={"help": "pyramid levels", "ge": 0, "le": 32})
    winsize: int = field(default=15, metadata={"help": "averaging window (px)", "ge": 1,
                                               "le": 100_000})
    iterations: int = field(default=3, metadata={"help": "iterations per level", "ge": 1,
                                                 "le": 10_000})
    poly_n: int = field(default=5, metadata={"help": "neighbourhood of the polynomial fit (5/7)",
                                             "ge": 3, "le": 15})
    poly_sigma: float = field(default=1.1, metadata={
        "gt": 0, "help": "Gaussian sigma of the polynomial fit (1.1 for poly_n 5, 1.5 for 7)"})
    gaussian: bool = field(default=True, metadata={
        "help": "Gaussian instead of box window (OPTFLOW_FARNEBACK_GAUSSIAN)"})


class FarnebackExtractor:
    """Dense optical flow of every frame against the reference, OpenCV's Farneback method.

    Frames are scaled to [0, 255] float32 with the reference's range (no 8-bit
    quantisation: OpenCV accepts float images).  Confidence = the smallest eigenvalue of the
    reference's structure tensor smoothed over the window (texture strength).
    """

    name = "farneback"
    version = "1"
    description = "dense optical flow vs the reference, OpenCV calcOpticalFlowFarneback"
    Config = FarnebackConfig

    def __init__(self, config: FarnebackConfig | None = None) -> None:
        self.config = config or FarnebackConfig()

    def prepare(self, reference: ArrayLike) -> FarnebackMotion:
        return FarnebackMotion(reference, self.config)


class FarnebackMotion:
    """Streaming Farneback flow relative to a reference frame (see the extractor)."""

    def __init__(self, reference: ArrayLike, config: FarnebackConfig) -> None:
        import cv2

        self._cv2 = cv2
        ref = np.asarray(reference, dtype=np.float64)
        if ref.ndim != 2:
            raise ValueError(f"reference must be a 2-D (H, W) image, got shape {ref.shape}")
        self.config = config
        self.shape = tuple(int(s) for s in ref.shape)
        self.grid_shape = self.shape
        self._lo = float(ref.min())
        span = float(ref.max()) - self._lo
        self._scale = 255.0 / span if span > 0 else 1.0  # the 8-bit range OpenCV tunes for
        self._ref = self._norm(ref)
        gy, gx = np.gradient(self._ref.astype(np.float64))
        k = (max(3, config.winsize | 1),) * 2
        sxx = cv2.GaussianBlur(gx * gx, k, 0)
        syy = cv2.GaussianBlur(gy * gy, k, 0)
        sxy = cv2.GaussianBlur(gx * gy, k, 0)
        tr, det = sxx + syy, sxx * syy - sxy * sxy
        lam = 0.5 * tr - np.sqrt(np.maximum(0.25 * tr * tr - det, 0.0))
        self.confidence = np.maximum(lam, 0.0).astype(np.float32)
        self.grid_confidence = self.confidence

    def _norm(self, frame: ArrayLike) -> NDArray[np.float32]:
        return ((np.asarray(frame, dtype=np.float64) - self._lo) * self._scale).astype(np.float32)

    def flow(self, frame: ArrayLike) -> NDArray[np.float32]:
        """``(H, W, 2)`` displacement of ``frame`` relative to the reference (px)."""
        c = self.config
        flags = self._cv2.OPTFLOW_FARNEBACK_GAUSSIAN if c.gaussian else 0
        return self._cv2.calcOpticalFlowFarneback(
            self._ref, self._norm(frame), None, c.pyr_scale, c.levels, c.winsize,
            c.iterations, c.poly_n, c.poly_sigma, flags,
        )

    def iter_displacements(
        self, frames: Iterable[ArrayLike], batch: int = 32
    ) -> Iterator[NDArray[np.float32]]:
        buf: list[NDArray[np.float32]] = []
        for fr in frames:
            buf.append(self.flow(fr))
            if len(buf) >= batch:
                yield np.stack(buf)
                buf = []
        if buf:
            yield np.stack(buf)

    def describe(self) -> dict[str, Any]:
        return {**asdict(self.config), "grid_shape": list(self.grid_shape)}
