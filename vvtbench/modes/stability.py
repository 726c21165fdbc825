"""Stability of candidate modes against record length.

A physical mode is found at the same frequency in the first quarter, half, three quarters and
the whole record (its line only narrows as the record grows); a noise peak or an artefact of one
stretch of the record is not.  :func:`record_stability` repeats the peak search
(:func:`.peaks.pick_peaks`, with its noise-floor significance test) on the leading part of the
record for several fractions, reading every pixel block once; :func:`.plots.plot_stability`
draws the result (``stability.png`` of ``vvtbench extract``).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from .peaks import pick_peaks, refine_frequency
from .spectrum import DisplacementStore, _as_store, _detrend, window_weights

__all__ = ["DEFAULT_FRACTIONS", "record_stability"]

#: leading fractions of the record searched by :func:`record_stability`
DEFAULT_FRACTIONS = (0.25, 0.5, 0.75, 1.0)


def record_stability(disp: DisplacementStore | ArrayLike, fps: float, *,
                     fractions: tuple[float, ...] = DEFAULT_FRACTIONS,
                     weights: ArrayLike | None = None, fmin: float | None = None,
                     fmax: float | None = None, false_alarm: float | None = 0.01,
                     min_bin: int = 3, max_peaks: int | None = 200,
                     block_bytes: int = 64 << 20) -> dict:
    """Significant peaks of the Hann-windowed motion spectrum of leading parts of the record.

    Parameters
    ----------
    disp : DisplacementStore or array_like
        ``(T, H, W, 2)`` displacements (px).
    fps : float
        Frame rate (Hz).
    fractions : tuple of float
        Leading fractions of the record in ``(0, 1]``.
    weights : array_like, optional
        ``(H, W)`` pixel weights of the spectrum.
    fmin, fmax, false_alarm, min_bin, max_peaks :
        As :func:`.peaks.pick_peaks` (``prominence`` 0: the significance test decides).

    Returns
    -------
    dict
        JSON-ready: ``fractions``, ``n_frames`` (frames of each part) and ``peaks_hz`` (one
        list of peak frequencies, Hz, sub-bin refined, per part).
    """
    fr = [float(f) for f in fractions]
    if not fr or any(not 0.0 < f <= 1.0 for f in fr):
        raise ValueError(f"fractions must lie in (0, 1], got {fractions}")
    store = _as_store(disp)
    T = int(store.n_frames)
    lengths = [max(8, int(round(f * T))) for f in fr]
    w = None if weights is None else np.repeat(np.asarray(weights, np.float64).reshape(-1), 2)
    spectra = [np.zeros(n // 2 + 1) for n in lengths]
    tapers = [window_weights(n, "hann") for n in lengths]
    P = store.block_size(block_bytes)
    C = store.n_columns
    for c0 in range(0, C, P):
        x = np.asarray(store.column_block(c0, min(c0 + P, C)), np.float64)
        for n, taper, S in zip(lengths, tapers, spectra, strict=True):
            X = np.fft.rfft(_detrend(x[:n].copy(), "mean") * taper[:, None], axis=0)
            p = np.abs(X) ** 2
            S += p.sum(axis=1) if w is None else p @ w[c0:c0 + x.shape[1]]
    peaks = []
    for n, S in zip(lengths, spectra, strict=True):
        freqs = np.fft.rfftfreq(n, 1.0 / fps)
        pk = pick_peaks(freqs, S, fps, fmin=fmin, fmax=fmax, prominence=0.0,
                        false_alarm=false_alarm, min_bin=min_bin, max_peaks=max_peaks)
        peaks.append([float(refine_frequency(freqs, S, int(k))) for k in pk.bins])
    return {"fractions": fr, "n_frames": lengths, "peaks_hz": peaks}
