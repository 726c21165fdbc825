r"""The Cramér-Rao bound of a mode's frequency and damping ratio, from the ruler's SNR.

The ruler (:mod:`vvtbench.render.crb`) gives each true mode's CRB-limited SNR, ``snr_i =
sqrt(K'_i sum_t q_i(t)^2)``: ``q_i(t)`` the mode's modal coordinate in each frame and ``K'_i =
sum_p Psi_i(p)^T J_p Psi_i(p)`` the Fisher information a frame holds on it (the matched filter
of its image-space shape ``Psi_i`` through the pixels' Fisher matrices ``J_p``).  So the
video measures the coordinate as ``q_i(t) + e(t)``, ``e`` white with variance ``1 / K'_i``,
and the Fisher matrix of any parameters ``theta`` of the coordinate's waveform is

.. math::  \mathcal{J}(\theta) = K'_i\, G^T G,\qquad G_{t k} = \partial q_i(t) / \partial\theta_k,
           \qquad K'_i = \mathrm{snr}_i^2 \Big/ \sum_t q_i(t)^2 .

For a free vibration (a pluck released before the first frame, undamped or damped) the
coordinate is ``q(t) = Re(C exp(lambda t))`` with ``lambda = 2 pi f (-zeta + i sqrt(1 -
zeta^2))`` and an unknown complex ``C`` (amplitude and phase): four parameters ``(f, zeta,
Re C, Im C)``.  The bound of ``(f, zeta)`` is the top-left 2 x 2 block of ``J^{-1}``: ``f``
is the undamped natural frequency, as a sample's ``frequencies_hz`` and a mode set's
frequencies are.

Assumptions beyond the ruler's: the other modes known (a bound for the mode alone: it is a
valid lower bound with them unknown, loose where modes lie within a few ``1 / T`` of each
other) and the image-space shape known (an extractor that estimates it does no better).  A
coordinate that is not a free vibration (a forced or swept response) is reported by its fit
residual: :func:`free_decay_bound` states it, and callers leave such modes out.

>>> import numpy as np
>>> t = np.arange(4000) / 2000.0
>>> q = np.exp(-0.02 * 2 * np.pi * 12.0 * t) * np.cos(2 * np.pi * 12.0 * np.sqrt(1 - 0.02**2) * t)
>>> b = free_decay_bound(t, q, snr=100.0, frequency_hz=12.0, damping_ratio=0.02)
>>> b["fit_residual"] < 1e-12, 0 < b["frequency_std_hz"] < 0.01, 0 < b["damping_std"] < 1e-3
(True, True, True)
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["FREE_DECAY_RESIDUAL", "free_decay_bound"]

#: largest relative RMS misfit of a coordinate by a free vibration for which the free-decay
#: bound is taken as the mode's (a modal simulation's free vibration fits to about 1e-7)
FREE_DECAY_RESIDUAL = 1e-3


def free_decay_bound(times: ArrayLike, coordinate: ArrayLike, snr: float,
                     frequency_hz: float, damping_ratio: float) -> dict[str, float]:
    """CRB standard deviations of a freely vibrating mode's frequency and damping ratio.

    Parameters
    ----------
    times : array_like
        ``(T,)`` frame times (s).
    coordinate : array_like
        ``(T,)`` the mode's modal coordinate in each frame (any unit: only its shape and
        ``snr`` matter).
    snr : float
        The mode's CRB-limited SNR in the record (``modes/crb_snr`` of a sample).
    frequency_hz, damping_ratio : float
        The mode's undamped natural frequency (Hz) and damping ratio (0 for an undamped one).

    Returns
    -------
    dict
        ``frequency_std_hz`` and ``damping_std``: the square roots of the bound's diagonal
        (NaN when the SNR is 0 or the coordinate vanishes); ``fit_residual``: relative RMS
        misfit of the coordinate by the best free vibration at ``(f, zeta)`` (the bound is
        that of a free vibration: above :data:`FREE_DECAY_RESIDUAL` the record is something
        else, for example a forced response).
    """
    t = np.asarray(times, dtype=np.float64)
    q = np.asarray(coordinate, dtype=np.float64)
    if t.shape != q.shape or t.ndim != 1:
        raise ValueError(f"times {t.shape} and coordinate {q.shape} must be equal 1-D shapes")
    f, z = float(frequency_hz), float(damping_ratio)
    if not (f > 0 and 0 <= z < 1):
        raise ValueError(f"need frequency_hz > 0 and 0 <= damping_ratio < 1, got {f}, {z}")
    nan = {"frequency_std_hz": math.nan, "damping_std": math.nan, "fit_residual": math.nan}
    energy = float(q @ q)
    if not (energy > 0 and snr > 0):
        return nan
    root = math.sqrt(1.0 - z * z)
    lam = 2.0 * math.pi * f * complex(-z, root)
    e = np.exp(lam * t)  # exp(lambda t): its real and imaginary parts span the free vibrations
    basis = np.stack([e.real, -e.imag], axis=1)  # q = A Re(e) - B Im(e), C = A + iB
    ab, *_ = np.linalg.lstsq(basis, q, rcond=None)
    fit = basis @ ab
    residual = float(np.sqrt(np.sum((q - fit) ** 2) / energy))
    c = complex(ab[0], ab[1])
    dlam_df = 2.0 * math.pi * complex(-z, root)
    dlam_dz = 2.0 * math.pi * f * complex(-1.0, -z / root)
    g = np.stack([(c * t * e * dlam_df).real, (c * t * e * dlam_dz).real,
                  basis[:, 0], basis[:, 1]], axis=1)
    scale = np.linalg.norm(g, axis=0)
    if not np.all(scale > 0):
        return nan
    information = snr**2 / energy  # K' per frame (module docstring)
    gn = g / scale
    cov = np.linalg.inv(gn.T @ gn) / information / np.outer(scale, scale)
    return {"frequency_std_hz": float(math.sqrt(cov[0, 0])),
            "damping_std": float(math.sqrt(cov[1, 1])),
            "fit_residual": residual}
