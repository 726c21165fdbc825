"""Modes identified jointly in several synchronised views of one vibrating object.

Each view is extracted on its own by the single-view extractor
(:func:`vvtbench.modes.extract_modes`); this module joins the results into one mode set:

1. **Frequencies.** A mode found in any view is a joint mode; the modes of the views are
   paired by frequency (one-to-one, relative difference at most ``freq_tol``).
2. **Phasors.** A single-view shape is real, of unit norm, and its sign is an arbitrary
   convention of its view (largest entry positive), so shapes of different views cannot be
   stacked as they are. :func:`modal_phasors` measures, per view and mode, the complex
   amplitude ``z`` of the motion along the shape at the mode's frequency (a windowed DFT of
   the projection of each frame on the shape): ``z = sign * ||Psi|| * q``, with ``Psi`` the
   view's image-space motion field of the mode (px), ``sign`` the view's sign convention and
   ``q`` the complex modal coordinate, the same in every synchronised view.
3. **A common complex scale per view.** Views whose clocks differ by a constant (a trigger
   delay shorter than a quarter period) see every mode rotated by one common phase ``c_v``;
   it is fitted on the modes the view shares with an already aligned view, on doubled angles
   (so the unknown per-mode signs drop out): ``c_v^2 ~ sum_i w_i (rho_i / |rho_i|)^2`` with
   ``rho_i = z_i^v / z_i^r``, ``w_i = |z_i^v| |z_i^r|``, choosing the root with a positive
   real part. A known delay (``time_offsets_s``, e.g. ``[camera.rig] time_offset_s``) is
   removed exactly first, ``z e^{-i omega tau}``.
4. **Signed scales.** With the views aligned, the phasors of one mode are collinear; its
   common phase is that of ``sum_v z_v^2`` and ``scale[i, v] = Re(z_v e^{-i phi_i})`` is the
   signed amplitude (px) of view ``v``'s unit shape. ``scale[i, v] * shape_v`` is then the
   mode's image motion in view ``v`` for one modal coordinate common to all views, so the
   views' sampled shapes stack into one vector (:meth:`JointModes.stack`).

Weighting: every stacked row (one image axis of one vertex in one view) has the same weight:
the rows are image displacements in px and a pixel's motion noise is of the same order in
every view. A vertex seen by two views contributes both views' rows: its 3-D motion is then
observed along up to three directions instead of two. A view that did not find a mode
contributes zeros to that mode's rows (its motion there was below that view's noise floor);
``JointModes.members`` says which views saw which mode.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .modeset import ModeSet

__all__ = ["JointModes", "extract_joint", "frame_range", "joint_modes", "modal_phasors"]


@dataclass
class JointModes:
    """One mode set over several views.

    Attributes
    ----------
    frequencies_hz : ndarray
        ``(K,)`` joint frequencies (Hz): the amplitude-weighted mean of the views' estimates.
    damping : ndarray
        ``(K,)`` mean damping ratio of the views' estimates (``nan`` if none).
    members : ndarray
        ``(K, V)`` int64 index of the mode in view ``v``'s mode set, ``-1`` where not found.
    scales : ndarray
        ``(K, V)`` float64 signed amplitude (px) of view ``v``'s unit shape for a modal
        coordinate common to the views; 0 where not found.
    view_phase : ndarray
        ``(V,)`` complex unit phasors ``c_v`` (view 0: 1) fitted on shared modes.
    snr : ndarray
        ``(K,)`` sum of the views' line SNRs (independent noise); ``nan`` if none is known.
    modesets : list of ModeSet
        The single-view mode sets (camera-shake modes removed).
    metadata : dict
        ``freq_tol``, ``time_offsets_s``, per view ``phase_deg`` and ``n_shared`` (modes the
        fit of its phase used; 0 for view 0 and for a view that shares none: phase 0).
    """

    frequencies_hz: NDArray[np.float64]
    damping: NDArray[np.float64]
    members: NDArray[np.int64]
    scales: NDArray[np.float64]
    view_phase: NDArray[np.complex128]
    snr: NDArray[np.float64]
    modesets: list[ModeSet]
    metadata: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.frequencies_hz.size)

    @property
    def n_views(self) -> int:
        return int(self.members.shape[1])

    def stack(self, per_view: Sequence[ArrayLike]) -> NDArray[np.float64]:
        """``(K, sum_v r_v)`` the views' sampled shapes stacked per joint mode, unit rows.

        ``per_view[v]`` is ``(k_v, r_v)``: view ``v``'s unit shapes sampled at its visible
        vertices (:func:`vvtbench.modes.sample_modes` of ``modesets[v].shapes``), row ``j``
        for its mode ``j``. Row ``i`` of the result is ``[scale[i, 0] g_0; scale[i, 1] g_1;
        ...]`` normalized (zeros where a view did not find the mode; an all-zero row stays
        zero).
        """
        if len(per_view) != self.n_views:
            raise ValueError(f"stack needs one array per view ({self.n_views}), got "
                             f"{len(per_view)}")
        blocks = []
        for v, g in enumerate(per_view):
            g = np.asarray(g, dtype=np.float64)
            idx = self.members[:, v]
            if g.ndim != 2 or (len(idx) and g.shape[0] <= idx.max(initial=-1)):
                raise ValueError(f"view {v}: sampled shapes {g.shape} do not hold the "
                                 f"{len(self.modesets[v])} modes of its mode set")
            block = np.zeros((len(self), g.shape[1]))
            seen = idx >= 0
            block[seen] = self.scales[seen, v, None] * g[idx[seen]]
            blocks.append(block)
        out = np.hstack(blocks) if blocks else np.zeros((len(self), 0))
        norms = np.linalg.norm(out, axis=1)
        out[norms > 0] /= norms[norms > 0, None]
        return out


def modal_phasors(
    source: str | Path | ArrayLike,
    fps: float,
    modeset: ModeSet,
    *,
    kind: str = "frames",
    start: int = 0,
    stop: int | None = None,
) -> NDArray[np.complex128]:
    """``(k,)`` complex amplitude of the motion along each unit shape at its frequency.

    The projection ``p_i(t)`` of frame ``t`` on shape ``i`` is a time series of the mode's
    coordinate: for displacement fields ``(T, H, W, 2)`` (``kind="displacements"``, px) it is
    ``<d_t, shape_i>``; for video frames (``kind="frames"``: a path, an array ``(T, H, W)`` or
    anything :func:`vvtbench.video.files.open_video` reads) it is the first-order brightness
    change, ``-<I_t - I_0, g_i> / <g_i, g_i>`` with ``g_i = grad(I_0) . shape_i`` (px), so
    one streamed pass over the video. The result is ``2 sum_t w_t p_i(t) e^{-2 pi i f_i t /
    fps} / sum_t w_t`` with a Hann window ``w`` (the mean removed first): a sinusoid
    ``A cos(2 pi f_i t / fps + phi)`` gives about ``A e^{i phi}``.
    """
    from ..video.files import open_video

    if kind not in ("frames", "displacements"):
        raise ValueError(f"kind must be 'frames' or 'displacements', got {kind!r}")
    shapes = np.nan_to_num(np.asarray(modeset.shapes, dtype=np.float64))
    k = len(modeset)
    H, W = shapes.shape[1:3]
    if kind == "displacements":
        disp = np.asarray(source)[start:stop]
        if disp.ndim != 4 or disp.shape[1:] != (H, W, 2):
            raise ValueError(f"displacements must be (T, {H}, {W}, 2), got {disp.shape}")
        series = np.einsum("thwc,khwc->tk", disp, shapes, optimize=True)
    else:
        stream = open_video(source, start=start, stop=stop)
        if tuple(stream.shape) != (H, W):
            raise ValueError(f"frames are {stream.shape[1]}x{stream.shape[0]} px, the mode "
                             f"shapes {W}x{H} px (extract from the whole frame)")
        rows, templates, gain, ref = [], None, None, None
        for frame in stream.frames:
            frame = np.asarray(frame, dtype=np.float64)
            if frame.ndim == 3:
                frame = frame.mean(axis=2)
            if ref is None:
                ref = frame
                gy, gx = np.gradient(ref)
                templates = (gx[None] * shapes[..., 0] + gy[None] * shapes[..., 1]
                             ).reshape(k, -1)
                gain = np.einsum("kp,kp->k", templates, templates)
                gain[gain == 0] = np.inf
            rows.append(-(templates @ (frame - ref).ravel()) / gain)
        series = np.array(rows).reshape(-1, k)
    T = series.shape[0]
    if T < 2:
        raise ValueError(f"modal_phasors needs at least 2 frames, got {T}")
    series = series - series.mean(axis=0)
    window = np.hanning(T + 2)[1:-1]
    t = np.arange(T)
    kernel = np.exp(-2j * np.pi * np.outer(t, modeset.frequencies_hz) / float(fps))
    return 2.0 * np.einsum("t,tk,tk->k", window, series, kernel) / window.sum()


def _pair_by_frequency(joint_f: list[float], f: NDArray[np.float64], tol: float
                       ) -> dict[int, int]:
    """{mode of the view: joint mode} for one-to-one pairs within ``tol`` (relative)."""
    from scipy.optimize import linear_sum_assignment

    if not joint_f or f.size == 0:
        return {}
    a = np.asarray(joint_f)
    cost = np.abs(f[:, None] - a[None, :]) / np.maximum(np.abs(a[None, :]), 1e-300)
    rows, cols = linear_sum_assignment(np.where(cost <= tol, cost, 1e6))
    return {int(r): int(c) for r, c in zip(rows, cols, strict=True) if cost[r, c] <= tol}


def _fit_phase(zv: NDArray[np.complex128], zr: NDArray[np.complex128]) -> complex:
    """The unit phasor ``c`` with ``zv ~ +-|.| c zr`` (doubled angles; Re c >= 0)."""
    rho = zv * np.conj(zr)
    ok = np.abs(rho) > 0
    e = np.sum(np.abs(rho[ok]) * (rho[ok] / np.abs(rho[ok])) ** 2)
    if abs(e) == 0:
        return 1.0 + 0.0j
    return complex(np.exp(0.5j * np.angle(e)))


def joint_modes(
    modesets: Sequence[ModeSet],
    phasors: Sequence[ArrayLike],
    *,
    freq_tol: float = 0.01,
    time_offsets_s: Sequence[float] | None = None,
) -> JointModes:
    """Join single-view mode sets into one (module notes).

    Parameters
    ----------
    modesets : one ModeSet per view (camera-shake modes are left out).
    phasors : per view, ``(k_v,)`` complex amplitudes of its modes (:func:`modal_phasors`).
    freq_tol : largest relative frequency difference of one mode seen in two views.
    time_offsets_s : per view, how much later it films than view 0 (s); default 0.
    """
    V = len(modesets)
    if V == 0 or len(phasors) != V:
        raise ValueError(f"joint_modes needs one mode set and one phasor array per view, got "
                         f"{V} and {len(phasors)}")
    offsets = np.zeros(V) if time_offsets_s is None else np.asarray(time_offsets_s, float)
    if offsets.shape != (V,):
        raise ValueError(f"time_offsets_s needs {V} values, got {offsets.size}")
    sets, zs = [], []
    for v, (ms, z) in enumerate(zip(modesets, phasors, strict=True)):
        z = np.asarray(z, dtype=np.complex128)
        if z.shape != (len(ms),):
            raise ValueError(f"view {v}: {z.size} phasors for {len(ms)} modes")
        keep = ~ms.camera_shake
        ms, z = ms.select(keep), z[keep]
        z = z * np.exp(-2j * np.pi * ms.frequencies_hz * offsets[v])
        sets.append(ms)
        zs.append(z)
    # 1. pair modes across views by frequency
    joint_f: list[float] = []
    members: list[list[int]] = []
    for v, ms in enumerate(sets):
        pairs = _pair_by_frequency(joint_f, ms.frequencies_hz, freq_tol)
        for j in range(len(ms)):
            if j in pairs:
                members[pairs[j]][v] = j
            else:
                members.append([-1] * V)
                members[-1][v] = j
                joint_f.append(float(ms.frequencies_hz[j]))
        for i, row in enumerate(members):  # amplitude-weighted joint frequency so far
            w = np.array([abs(zs[u][j]) for u, j in enumerate(row) if j >= 0])
            f = np.array([sets[u].frequencies_hz[j] for u, j in enumerate(row) if j >= 0])
            joint_f[i] = float(np.sum(w * f) / w.sum()) if w.sum() > 0 else float(f.mean())
    K = len(members)
    member = np.array(members, dtype=np.int64).reshape(K, V)
    Z = np.zeros((K, V), dtype=np.complex128)
    for v in range(V):
        seen = member[:, v] >= 0
        Z[seen, v] = zs[v][member[seen, v]]
    # 2. a common phase per view, fitted on the modes shared with an aligned view
    phase = np.ones(V, dtype=np.complex128)
    shared = np.zeros(V, dtype=np.int64)
    aligned = [0]
    todo = list(range(1, V))
    while todo:
        best = max(((v, r, int(np.sum((member[:, v] >= 0) & (member[:, r] >= 0))))
                    for v in todo for r in aligned), key=lambda x: x[2])
        v, r, n = best
        if n > 0:
            both = (member[:, v] >= 0) & (member[:, r] >= 0)
            phase[v] = phase[r] * _fit_phase(Z[both, v], Z[both, r])
        shared[v] = n
        aligned.append(v)
        todo.remove(v)
    Za = Z * np.conj(phase)[None, :]
    # 3. the signed real scale of every view's unit shape
    common = np.exp(0.5j * np.angle(np.sum(Za**2, axis=1)))
    scales = np.real(Za * np.conj(common)[:, None])
    scales[member < 0] = 0.0
    if K:  # a mode's overall sign is free: its largest scale positive
        lead = scales[np.arange(K), np.argmax(np.abs(scales), axis=1)]
        scales = scales * np.where(lead < 0, -1.0, 1.0)[:, None]
    snr = np.full(K, np.nan)
    damping = np.full(K, np.nan)
    line = [ms.line_snr() for ms in sets]
    for i in range(K):
        s = [line[v][j] for v, j in enumerate(member[i]) if j >= 0]
        d = [sets[v].damping[j] for v, j in enumerate(member[i]) if j >= 0]
        if np.isfinite(s).any():
            snr[i] = float(np.nansum(s))
        if np.isfinite(d).any():
            damping[i] = float(np.nanmean(d))
    order = np.argsort(joint_f, kind="stable")
    return JointModes(
        frequencies_hz=np.asarray(joint_f, dtype=np.float64)[order],
        damping=damping[order], members=member[order], scales=scales[order],
        view_phase=phase, snr=snr[order], modesets=sets,
        metadata={"freq_tol": float(freq_tol), "time_offsets_s": offsets.tolist(),
                  "phase_deg": np.degrees(np.angle(phase)).tolist(),
                  "n_shared": shared.tolist(),
                  "n_views_seen": (member[order] >= 0).sum(axis=1).tolist()},
    )


def extract_joint(
    sources: Sequence[str | Path | ArrayLike],
    fps: float,
    *,
    time_offsets_s: Sequence[float] | None = None,
    freq_tol: float = 0.01,
    **extract: Any,
) -> JointModes:
    """Extract each view with :func:`vvtbench.modes.extract_modes` (``**extract`` its
    options) and join the views (:func:`joint_modes`); each source is read a second time for
    its phasors (:func:`modal_phasors`), so it must be a path or an array, not a one-shot
    iterator."""
    from .extract import extract_modes

    start, stop = frame_range(extract)
    sets, phasors = [], []
    for v, source in enumerate(sources):
        if not isinstance(source, (str, Path, np.ndarray)):
            raise ValueError(f"view {v}: extract_joint reads each source twice; give a path or "
                             f"an array, not a {type(source).__name__}")
        ms = extract_modes(source, fps, **extract)
        sets.append(ms)
        phasors.append(modal_phasors(source, fps, ms, start=start, stop=stop))
    return joint_modes(sets, phasors, freq_tol=freq_tol, time_offsets_s=time_offsets_s)


def frame_range(extract: dict[str, Any]) -> tuple[int, int | None]:
    """The frames ``start:stop`` that :func:`vvtbench.modes.extract_modes` with the options
    ``extract`` reads (``start``, ``stop``, ``max_frames``)."""
    start, stop = int(extract.get("start", 0)), extract.get("stop")
    if extract.get("max_frames") is not None:
        last = start + int(extract["max_frames"])
        stop = last if stop is None else min(int(stop), last)
    return start, (None if stop is None else int(stop))
