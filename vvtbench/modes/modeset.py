"""The :class:`ModeSet` container of identified image-space modes, its file format and merging.

The file format is described in ``docs/modes.md``: a directory with ``modes.npz`` (arrays)
and ``modes.json`` (scalars, per-mode summary and metadata).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .merging import merge_modes

__all__ = ["CANDIDATE_LISTS", "FORMAT_VERSION", "ModeSet", "merge_modesets"]

FORMAT_VERSION = 1

_PER_MODE = (
    "frequencies_hz",
    "damping",
    "damping_half_power",
    "amplitudes_px",
    "peak_bins",
    "prominences",
    "collinearity",
    "shake_mac",
    "camera_shake",
)

# metadata lists with one entry per analysed peak (kept and rejected), in the order analysed
CANDIDATE_LISTS = ("roughness", "roughness_shape", "reliable_fraction", "phase_rad",
                   "frequency_std_hz", "damping_lo", "damping_hi", "shape_mac_expected",
                   "close_mode_bias", "line_misfit", "damping_unwindowed",
                   "onset_amplitude_ratio", "frequency_std_noise_hz")


@dataclass
class ModeSet:
    """Image-space modes identified in one (or several merged) videos.

    Attributes
    ----------
    frequencies_hz : ndarray
        ``(k,)`` float64 peak frequencies (Hz), sub-bin refined (parabola on log power).
    damping : ndarray
        ``(k,)`` float64 damping ratios from the Lorentzian fit (``nan`` if it failed).
    damping_half_power : ndarray
        ``(k,)`` float64 damping ratios from the half-power bandwidth.
    shapes : ndarray
        ``(k, H, W, 2)`` float32 real modes (``[..., 0] = dx`` right, ``[..., 1] = dy`` down),
        phase aligned, unit L2 norm over all pixels and both components.
    amplitudes_px : ndarray
        ``(k,)`` float64: ``amplitudes_px[i] * shapes[i]`` is the peak displacement field (px)
        of the mode for a stationary sinusoid on a bin (``2 |X| / T``; less with leakage).
    peak_bins : ndarray
        ``(k,)`` int64 DFT bin of each peak (``-1`` after merging).
    prominences : ndarray
        ``(k,)`` float64 peak prominence in decades of power.
    collinearity : ndarray
        ``(k,)`` float64 in ``[0, 1]``, 1 for a standing (synchronous) mode.
    shake_mac : ndarray
        ``(k,)`` float64 MAC of the complex mode with the best rigid translation.
    camera_shake : ndarray
        ``(k,)`` bool, ``shake_mac > threshold``.
    freqs_hz, power : ndarray
        ``(F,)`` float64 frequency axis and motion power spectrum (empty after merging).
    fps : float
        Frame rate (Hz) after frame averaging.
    n_frames : int
        Frames in the spectrum (``T``).
    confidence : ndarray or None
        ``(H, W)`` float32 motion confidence of the reference frame.
    metadata : dict
        JSON-serialisable provenance (source, parameters, rejected peaks, ...).
    """

    frequencies_hz: NDArray[np.float64]
    damping: NDArray[np.float64]
    damping_half_power: NDArray[np.float64]
    shapes: NDArray[np.float32]
    amplitudes_px: NDArray[np.float64]
    peak_bins: NDArray[np.int64]
    prominences: NDArray[np.float64]
    collinearity: NDArray[np.float64]
    shake_mac: NDArray[np.float64]
    camera_shake: NDArray[np.bool_]
    freqs_hz: NDArray[np.float64]
    power: NDArray[np.float64]
    fps: float
    n_frames: int
    confidence: NDArray[np.float32] | None = None
    metadata: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.shapes = np.asarray(self.shapes, dtype=np.float32)
        if self.shapes.ndim != 4 or self.shapes.shape[-1] != 2:
            raise ValueError(f"shapes must be (k, H, W, 2), got {self.shapes.shape}")
        k = self.shapes.shape[0]
        for name in _PER_MODE:
            dtype = {"peak_bins": np.int64, "camera_shake": np.bool_}.get(name, np.float64)
            a = np.atleast_1d(np.asarray(getattr(self, name), dtype=dtype))
            if a.shape != (k,):
                raise ValueError(f"{name} must have shape ({k},), got {a.shape}")
            setattr(self, name, a)
        self.freqs_hz = np.asarray(self.freqs_hz, dtype=np.float64)
        self.power = np.asarray(self.power, dtype=np.float64)
        if self.freqs_hz.shape != self.power.shape:
            raise ValueError("freqs_hz and power must have the same shape")
        if self.confidence is not None:
            self.confidence = np.asarray(self.confidence, dtype=np.float32)

    def __len__(self) -> int:
        return int(self.shapes.shape[0])

    @property
    def lossy(self) -> dict[str, Any] | None:
        """The lossy compression of the source video (``metadata["lossy"]``: codec, bit depth,
        keyframe interval ``gop``), or None for a lossless source and for mode sets written
        before the key existed."""
        value = self.metadata.get("lossy")
        return value if isinstance(value, dict) else None

    @property
    def image_shape(self) -> tuple[int, int]:
        """``(H, W)``."""
        return int(self.shapes.shape[1]), int(self.shapes.shape[2])

    @property
    def peak_displacement_px(self) -> NDArray[np.float64]:
        """``(k,)`` peak displacement of each mode (px): the largest ``|dx|`` or ``|dy|`` of
        ``amplitudes_px[i] * shapes[i]`` over the image (``amplitudes_px`` is the L2 norm of
        the whole field, which grows with the object's size in pixels)."""
        if not len(self):
            return np.zeros(0)
        return self.amplitudes_px * np.abs(self.shapes).reshape(len(self), -1).max(axis=1)

    @property
    def initial_displacement_px(self) -> NDArray[np.float64]:
        """``(k,)`` peak displacement when the mode's free decay began (px): at the record's
        start for a mode plucked before it, when the drive reached it otherwise (a sweep).

        ``amplitudes_px`` is the amplitude of the *undamped* sinusoid with the same windowed
        spectral line, so a mode that decays within the record shows far less than it first
        moved (ζ 0.03 at 41 Hz in 3 s: 0.3 % of it with the Hann window).  Where the damping
        is resolved (:meth:`damping_resolved`) this undoes it: ``peak_displacement_px`` times
        the window's response to an undamped line over its response to a line of that half
        width (:func:`.lines.peak_gain`), exact for a free decay from the first frame.  A
        decay that began at frame ``t0`` has, without window, the spectrum of one from the
        first frame with the amplitude it had at ``t0`` (the shift is a phase); with the
        Hann window it does not.  Where the set carries the ratio of the two fits' amplitudes
        (``onset_amplitude_ratio``, peak-picked modes, docs/modes.md) the result is scaled
        by it: 1 within noise for a pluck, below 1 for a mode a sweep reached mid-record.
        Elsewhere it equals ``peak_displacement_px``.
        """
        from .lines import peak_gain

        peak = self.peak_displacement_px
        if not len(self) or not self.n_frames or not self.fps:
            return peak
        window = self.metadata.get("window", "hann")
        window = window if window in ("hann", "none") else "hann"
        resolved = self.damping_resolved()
        h = np.where(resolved, self.damping * self.frequencies_hz * self.n_frames / self.fps,
                     0.0)
        gain = peak_gain(h, self.n_frames, window)
        ratio = self.mode_list("onset_amplitude_ratio")
        ratio = np.where(resolved & np.isfinite(ratio) & (ratio > 0), ratio, 1.0)
        return peak * peak_gain(np.zeros(1), self.n_frames, window)[0] / gain * ratio

    def damping_resolved(self) -> NDArray[np.bool_]:
        """``(k,)`` whether the damping ratio was measured, not just fitted to noise.

        True when the fit gave a finite ``zeta`` in ``(0, 0.3)``, its half width
        ``zeta f`` is at least 0.05 bin (``fps / n_frames``; narrower is not told from an
        undamped peak, docs/modes.md) and the half-power estimate agrees within a factor 2.
        An undamped scene's peaks fail it (half-power NaN or far off), so no ``zeta`` is
        shown for them.

        A pole-based identifier's damping (:attr:`pole_based`) has no half-power estimate; its
        interval decides.

        Where the set carries the damping's 95 % interval (line fit, :meth:`damping_interval`)
        it must also be tighter than a factor 2 (``lo > 0`` and ``hi / lo <= 2``), and a mode
        flagged ``close_mode_bias`` (a close pair whose fit residual or parameter correlation
        says the two lines bias each other) is not resolved. A peak-picked damping's interval
        spans the fits with and without the window (:mod:`.jackknife`), so a mode that did
        not decay freely from the record's start (a sweep passed through it mid-record) is
        resolved only where the two readings lie within a factor 2.
        """
        z, zh, f = self.damping, self.damping_half_power, self.frequencies_hz
        df = self.fps / self.n_frames if self.n_frames else np.inf
        with np.errstate(invalid="ignore", divide="ignore"):
            ok = np.isfinite(z) & (z > 0) & (z < 0.3) & (z * f >= 0.05 * df)
            # a pole's damping has no half-power cross-check: its interval (the spread over
            # the model orders) decides
            ok &= (np.isfinite(zh) & (zh > 0.5 * z) & (zh < 2.0 * z)) | self.pole_based
            lo, hi = self.damping_interval()
            known = np.isfinite(lo) & np.isfinite(hi)
            ok &= ~known | ((lo > 0) & (hi <= 2.0 * lo))
        ok &= ~self.close_mode_bias()
        return ok

    @property
    def identifier(self) -> dict[str, Any]:
        """How the modes were identified (``metadata["identifier"]``: ``requested``, ``used``
        (``"peaks"``, ``"era"`` or ``"plscf"``), ``reason``); the peak picker for sets written
        before the key existed."""
        value = self.metadata.get("identifier")
        if isinstance(value, dict) and isinstance(value.get("used"), str):
            return value
        return {"requested": "peaks", "used": "peaks", "reason": "recorded before the "
                "identifier was", "excitation": None}

    @property
    def pole_based(self) -> bool:
        """Whether a pole-based identifier (ERA, pLSCF) found the modes."""
        return self.identifier["used"] in ("era", "plscf")

    def mode_list(self, name: str, default: float = np.nan) -> NDArray[np.float64]:
        """``(k,)`` each mode's entry of a per-candidate metadata list
        (:data:`CANDIDATE_LISTS`), ``default`` where the set has none (older files, no line
        fit, merged sets)."""
        out = np.full(len(self), default, dtype=np.float64)
        analysed = self.analysed_index()
        values = self.metadata.get(name)
        if analysed is None or not isinstance(values, list):
            return out
        for i, a in enumerate(analysed):
            if a < len(values) and values[a] is not None:
                out[i] = float(values[a])
        return out

    def frequency_std_hz(self) -> NDArray[np.float64]:
        """``(k,)`` standard error of each frequency (Hz), ``nan`` where not computed (the method:
        ``metadata["uncertainty_method"]``)."""
        return self.mode_list("frequency_std_hz")

    def damping_interval(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``(lo, hi)`` 95 % interval of each damping ratio, ``nan`` where not computed (the
        method: ``metadata["uncertainty_method"]``)."""
        return self.mode_list("damping_lo"), self.mode_list("damping_hi")

    def close_mode_bias(self) -> NDArray[np.bool_]:
        """``(k,)`` whether a mode's line fit is biased by a close neighbour."""
        return self.mode_list("close_mode_bias", 0.0) > 0

    def line_snr(self) -> NDArray[np.float64]:
        """``(k,)`` power at each mode's peak bin over the spectrum's noise floor there.

        The floor is :func:`.significance.noise_floor` over the extraction band
        (``metadata["band_hz"]``, ``min_bin``, ``noise_floor.half_width_bins``), the model the
        peaks were tested against; ``1 / (1 + snr)`` is about the fraction of a mode shape's
        energy that is noise. ``nan`` where the set has no spectrum (merged sets) or a mode
        no peak bin.

        >>> f = np.arange(129.0); p = np.ones(129); p[40] = 1e3
        >>> z = np.zeros((1, 2, 2, 2), np.float32); one = np.ones(1)
        >>> ms = ModeSet(one * 40.0, one, one, z, one, np.array([40]), one, one, 0 * one,
        ...              np.zeros(1, bool), f, p, 256.0, 256)
        >>> ms.line_snr().round()
        array([1000.])
        """
        from .significance import noise_floor

        out = np.full(len(self), np.nan)
        ok = (self.peak_bins >= 0) & (self.peak_bins < self.power.size)
        if not ok.any() or self.power.size < 3:
            return out
        f = self.freqs_hz
        lo, hi = self.metadata.get("band_hz", (f[1], f[-1]))
        first = max(1, int(self.metadata.get("min_bin", 1)))
        band = np.flatnonzero((f >= lo) & (f <= hi) & (np.arange(f.size) >= first))
        sl = slice(int(band[0]), int(band[-1]) + 1) if band.size else slice(1, f.size)
        half = int((self.metadata.get("noise_floor") or {}).get("half_width_bins", 32))
        floor = noise_floor(self.power, sl, half_width_bins=half).floor
        b = self.peak_bins[ok]
        with np.errstate(divide="ignore", invalid="ignore"):
            out[ok] = self.power[b] / floor[b]
        return out

    @property
    def omegas(self) -> NDArray[np.float64]:
        """Angular frequencies ``2 pi f`` (rad/s); ``lambda = omega**2``."""
        return 2.0 * np.pi * self.frequencies_hz

    def select(self, index: Any) -> ModeSet:
        """Subset of modes (boolean mask or indices); spectrum and metadata are kept
        (``metadata["analysed_index"]``, when it maps the modes to the per-candidate lists,
        is subset with them)."""
        idx = np.arange(len(self))[index]
        kw = {f.name: getattr(self, f.name) for f in fields(self)}
        for name in (*_PER_MODE, "shapes"):
            kw[name] = kw[name][idx]
        kw["metadata"] = dict(self.metadata)
        analysed = self.analysed_index()
        if analysed is not None:
            kw["metadata"]["analysed_index"] = [analysed[i] for i in np.atleast_1d(idx)]
        return ModeSet(**kw)

    def analysed_index(self) -> list[int] | None:
        """Each mode's position in the per-candidate metadata lists (``roughness``,
        ``phase_rad``, ... of every analysed peak, kept and rejected), or None when the
        metadata has no such map for these modes (e.g. after merging)."""
        a = self.metadata.get("analysed_index")
        if not isinstance(a, list) or len(a) != len(self) or not all(
                isinstance(i, int | np.integer) and not isinstance(i, bool) and i >= 0
                for i in a):
            return None
        return [int(i) for i in a]

    def summary(self) -> list[dict[str, Any]]:
        """Per-mode scalars as a list of dicts (JSON-ready), with each mode's entry of the
        per-candidate metadata lists (:data:`CANDIDATE_LISTS`) when the modes are mapped to
        them (:meth:`analysed_index`)."""
        analysed = self.analysed_index()
        out = []
        for i in range(len(self)):
            d: dict[str, Any] = {"index": i}
            for name in _PER_MODE:
                d[name] = _finite_or_none(getattr(self, name)[i].item())
            for name in CANDIDATE_LISTS if analysed is not None else ():
                values = self.metadata.get(name)
                if isinstance(values, list) and analysed[i] < len(values):
                    d[name] = _finite_or_none(values[analysed[i]])
            out.append(d)
        return out

    # ---------------------------------------------------------------- persistence
    def save(self, directory: str | Path) -> Path:
        """Write ``modes.npz`` and ``modes.json`` into ``directory`` (created if needed).

        Every entry of ``modes.json``'s ``modes`` also carries (from the line fit's covariance
        or the peak picker's jackknife, named by ``metadata["uncertainty_method"]``; and
        ``metadata`` holds the same as per-candidate lists, one entry per analysed peak, mapped
        by ``analysed_index``), each a scalar per mode, ``null`` where not computed:

        - ``frequency_std_hz`` (float64, Hz): standard error of the frequency (the peak
          picker's never below a tenth of a bin, ``metadata["frequency_floor_hz"]``;
          ``frequency_std_noise_hz`` is its jackknife's own);
        - ``damping_lo``, ``damping_hi`` (float64, dimensionless): 95 % interval of the
          damping ratio;
        - ``shape_mac_expected`` (float64 in ``[0, 1]``): expected MAC of the shape with the
          noiseless shape, ``signal / (signal + noise)`` energy;
        - ``close_mode_bias`` (bool): a line within 4 bins of another whose residual (over 3
          times the noise floor around it) or parameter correlation (over 0.8) says the two
          bias each other; its damping is then not resolved;
        - ``line_misfit`` (float64): residual power in the five bins around the line over the
          noise floor there (about 1 for a clean fit);
        - ``damping_unwindowed`` (float64, dimensionless; peak picker with the Hann window):
          the damping ratio fitted to the spectrum without window;
        - ``onset_amplitude_ratio`` (float64, dimensionless; the same): the amplitude that
          fit finds over the one the Hann fit puts at the first frame (about 1 for a pluck;
          :attr:`initial_displacement_px`).

        ``metadata["stability"]`` (with ``extract_modes(stability=True)``) holds
        ``fractions``, ``n_frames`` and ``peaks_hz`` of the peak search on leading parts of
        the record.  Files without these keys load; the accessors then return ``nan`` /
        ``False``.
        """
        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        arrays = {name: getattr(self, name) for name in (*_PER_MODE, "shapes", "freqs_hz", "power")}
        if self.confidence is not None:
            arrays["confidence"] = self.confidence
        from ..io.files import write_npz, write_text

        write_npz(d / "modes.npz", arrays, compressed=False)
        doc = {
            "format": "vvtbench.modes",
            "version": FORMAT_VERSION,
            "n_modes": len(self),
            "image_shape": list(self.image_shape),
            "fps": float(self.fps),
            "n_frames": int(self.n_frames),
            "modes": self.summary(),
            "metadata": self.metadata,
        }
        write_text(d / "modes.json", json.dumps(doc, indent=2, default=_json_default) + "\n")
        return d

    @classmethod
    def load(cls, directory: str | Path) -> ModeSet:
        """Read a directory written by :meth:`save`."""
        d = Path(directory)
        jpath, npath = d / "modes.json", d / "modes.npz"
        for p in (jpath, npath):
            if not p.is_file():
                raise FileNotFoundError(f"missing {p} (not a mode directory?)")
        doc = json.loads(jpath.read_text())
        if doc.get("format") != "vvtbench.modes":
            raise ValueError(f"{jpath}: key 'format' must be 'vvtbench.modes'")
        if int(doc.get("version", -1)) > FORMAT_VERSION:
            raise ValueError(
                f"{jpath}: format version {doc.get('version')} is newer than supported"
            )
        with np.load(npath) as z:
            arrays = {k: z[k] for k in z.files}
        missing = [k for k in (*_PER_MODE, "shapes", "freqs_hz", "power") if k not in arrays]
        if missing:
            raise ValueError(f"{npath}: missing arrays {missing}")
        try:
            fps, n_frames = doc["fps"], doc["n_frames"]
        except KeyError as e:
            raise ValueError(f"{jpath}: missing key {e}") from None
        if isinstance(fps, bool) or not isinstance(fps, int | float) or not 0 < fps < np.inf:
            raise ValueError(f"{jpath}: key 'fps' must be a finite number > 0, got {fps!r}")
        if isinstance(n_frames, bool) or not isinstance(n_frames, int) or n_frames < 1:
            raise ValueError(f"{jpath}: key 'n_frames' must be an integer >= 1, got "
                             f"{n_frames!r}")
        fps = float(fps)
        metadata = doc.get("metadata", {})
        if not isinstance(metadata, dict):
            raise ValueError(f"{jpath}: key 'metadata' must be an object")
        for name in CANDIDATE_LISTS:
            values = metadata.get(name)
            if values is not None and not (
                    isinstance(values, list)
                    and all(v is None or isinstance(v, int | float) for v in values)):
                raise ValueError(f"{jpath}: key 'metadata.{name}' must be a list of numbers "
                                 "or null, one per analysed peak")
        return cls(**arrays, fps=fps, n_frames=n_frames, metadata=metadata)


def _finite_or_none(v: Any) -> Any:
    """A per-mode JSON value: NaN and infinities become ``None`` (``null``)."""
    return None if isinstance(v, float) and not np.isfinite(v) else v


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def merge_modesets(sets: list[ModeSet], *, freq_tol: float = 0.02, min_mac: float = 0.8) -> ModeSet:
    """Merge the modes of several videos of the same view (see :func:`merging.merge_modes`).

    Duplicates (frequency within ``freq_tol`` relative, MAC >= ``min_mac``) are averaged
    with amplitude weights after sign alignment; ``metadata["n_sources"]`` gives, per merged
    mode, the number of sets it was found in and ``metadata["members"]`` the
    ``(set, mode)`` pairs.  Camera-shake modes are dropped.  The merged set has no spectrum.
    """
    if not sets:
        raise ValueError("nothing to merge")
    kept = [s.select(~s.camera_shake) for s in sets]
    m = merge_modes(
        [s.frequencies_hz for s in kept],
        [s.shapes for s in kept],
        damping=[s.damping for s in kept],
        weights=[s.amplitudes_px for s in kept],
        freq_tol=freq_tol,
        min_mac=min_mac,
    )

    def avg(name: str) -> NDArray[np.float64]:
        vals = []
        for members in m.members:
            v = np.array([getattr(kept[i], name)[j] for i, j in members], dtype=np.float64)
            vals.append(np.nanmean(v) if np.isfinite(v).any() else np.nan)
        return np.array(vals)

    k = len(m.frequencies_hz)
    return ModeSet(
        frequencies_hz=m.frequencies_hz,
        damping=m.damping,
        damping_half_power=avg("damping_half_power"),
        shapes=m.shapes,
        amplitudes_px=avg("amplitudes_px"),
        peak_bins=np.full(k, -1),
        prominences=avg("prominences"),
        collinearity=avg("collinearity"),
        shake_mac=avg("shake_mac"),
        camera_shake=np.zeros(k, bool),
        freqs_hz=np.zeros(0),
        power=np.zeros(0),
        fps=float(min(s.fps for s in sets)),
        n_frames=int(sum(s.n_frames for s in sets)),
        confidence=sets[0].confidence,
        metadata={
            "merged_from": [s.metadata.get("source") for s in sets],
            "freq_tol": freq_tol,
            "min_mac": min_mac,
            "n_sources": m.n_sources.tolist(),
            "members": [[list(p) for p in g] for g in m.members],
        },
    )
