"""Stabilisation diagram and automatic clustering of poles over model orders.

A pole-based identifier (:mod:`.era`, :mod:`.plscf`) returns poles at every model order of a
scan.  A physical mode reappears at nearly the same frequency, damping and shape whatever the
order once the order is high enough; noise and computational poles wander.  The classical
stabilisation diagram marks a pole *stable* when a pole of the previous order lies within a
relative frequency step ``f_tol``, a damping step ``z_tol`` (relative, with an absolute floor)
and a shape MAC of at least ``mac_tol`` (:func:`stable_poles`).

The stable poles are then grouped by agglomerative clustering (average linkage) on the distance
``|lambda_a - lambda_b| / max(|lambda_a|, |lambda_b|) + (1 - MAC_ab)``: the complex pole
distance carries frequency and damping together, the MAC the shape
(:func:`cluster_poles`, in the spirit of the clustering of pyOMA2 and koma).  A cluster
holding poles of at least ``min_fraction`` of the orders is a mode.  Its frequency, damping and
shape are the medians over its members (one per order: the nearest to the median), and their
spread over the orders is its uncertainty: how much the answer depends on a choice of order
the data do not make.

:func:`..plots.plot_stabilization` draws the diagram (``stabilization.png`` of ``vvtbench
extract``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .era import PoleSet

__all__ = ["PoleCluster", "cluster_poles", "diagram", "stable_poles"]


def _mac_matrix(a: NDArray[np.complex128], b: NDArray[np.complex128]) -> NDArray[np.float64]:
    """``(len(a), len(b))`` MAC of complex unit-norm shapes."""
    if not len(a) or not len(b):
        return np.zeros((len(a), len(b)))
    num = np.abs(np.conj(a) @ b.T) ** 2
    den = np.outer(np.sum(np.abs(a) ** 2, 1), np.sum(np.abs(b) ** 2, 1))
    return np.divide(num, den, out=np.zeros_like(num), where=den > 0)


def stable_poles(poles: list[PoleSet], *, f_tol: float = 0.01, z_tol: float = 0.05,
                 z_floor: float = 0.002, mac_tol: float = 0.95,
                 band_hz: tuple[float, float] | None = None,
                 max_damping: float = 0.3) -> list[NDArray[np.bool_]]:
    """Per order, which poles are stable against the previous order of the scan.

    A pole is stable when the previous order has a pole with ``|df| <= f_tol f``, ``|dzeta| <=
    z_tol zeta + z_floor`` and MAC of the shapes at least ``mac_tol``; it must also lie in
    ``band_hz`` and have a damping in ``(-z_floor, max_damping)``.  The first order has no
    stable pole.
    """
    out: list[NDArray[np.bool_]] = []
    prev = None
    for ps in poles:
        f, z = ps.frequency_hz, ps.damping
        ok = (z > -z_floor) & (z < max_damping) & np.isfinite(f)
        if band_hz is not None:
            ok &= (f >= band_hz[0]) & (f <= band_hz[1])
        st = np.zeros(f.size, bool)
        if prev is not None and f.size and prev.lam.size:
            fp, zp = prev.frequency_hz, prev.damping
            df = np.abs(f[:, None] - fp[None, :]) <= f_tol * f[:, None]
            dz = np.abs(z[:, None] - zp[None, :]) <= z_tol * np.abs(z[:, None]) + z_floor
            mm = _mac_matrix(ps.shapes, prev.shapes) >= mac_tol
            st = ok & np.any(df & dz & mm, axis=1)
        out.append(st)
        prev = ps
    return out


@dataclass
class PoleCluster:
    """A mode: stable poles of several orders grouped together.

    Attributes
    ----------
    lam : complex
        Median continuous-time pole (rad/s).
    frequency_hz, damping : float
        Median undamped frequency (Hz) and damping ratio of the members.
    frequency_std_hz, damping_std : float
        Their standard deviations over the members (0 with one member).
    shape : ndarray
        ``(m,)`` complex reduced-channel shape of the member nearest the median, unit norm.
    amplitude : float
        Median amplitude of the members.
    members : list of (int, int)
        ``(position in the scan, pole index)`` of each member, one per order.
    orders : list of int
        Their model orders.
    mac_spread : float
        Smallest MAC of a member's shape with ``shape``.
    """

    lam: complex
    frequency_hz: float
    damping: float
    frequency_std_hz: float
    damping_std: float
    shape: NDArray[np.complex128]
    amplitude: float
    members: list[tuple[int, int]] = field(default_factory=list)
    orders: list[int] = field(default_factory=list)
    mac_spread: float = 1.0

    def summary(self) -> dict[str, Any]:
        """JSON-ready scalars."""
        return {"frequency_hz": float(self.frequency_hz), "damping": float(self.damping),
                "frequency_std_hz": float(self.frequency_std_hz),
                "damping_std": float(self.damping_std), "amplitude": float(self.amplitude),
                "n_orders": len(self.orders), "mac_spread": float(self.mac_spread)}


def cluster_poles(poles: list[PoleSet], stable: list[NDArray[np.bool_]], *,
                  threshold: float = 0.05, min_fraction: float = 0.3,
                  min_members: int = 3) -> list[PoleCluster]:
    """Modes from the stable poles of a scan (see the module docstring).

    Parameters
    ----------
    poles : list of PoleSet
        The scan, by increasing order.
    stable : list of ndarray
        :func:`stable_poles` of it.
    threshold : float, default 0.05
        Distance at which the average-linkage tree is cut.
    min_fraction, min_members : float, int
        A cluster is a mode when it holds poles of at least ``min_fraction`` of the orders
        with stable poles and at least ``min_members`` orders.

    Returns
    -------
    list of PoleCluster
        By increasing frequency.
    """
    from scipy.cluster.hierarchy import fcluster, linkage
    from scipy.spatial.distance import squareform

    idx = [(s, int(i)) for s, st in enumerate(stable) for i in np.flatnonzero(st)]
    if not idx:
        return []
    lam = np.array([poles[s].lam[i] for s, i in idx])
    shapes = np.stack([poles[s].shapes[i] for s, i in idx])
    amp = np.array([poles[s].amplitude[i] for s, i in idx])
    n_scan = sum(bool(st.any()) for st in stable) or 1
    if len(idx) == 1:
        labels = np.ones(1, int)
    else:
        scale = np.maximum(np.abs(lam)[:, None], np.abs(lam)[None, :])
        D = np.abs(lam[:, None] - lam[None, :]) / scale + (1.0 - _mac_matrix(shapes, shapes))
        D = np.clip((D + D.T) / 2, 0.0, None)
        np.fill_diagonal(D, 0.0)
        labels = fcluster(linkage(squareform(D, checks=False), method="average"),
                          t=threshold, criterion="distance")
    out: list[PoleCluster] = []
    for lab in np.unique(labels):
        sel = np.flatnonzero(labels == lab)
        f = np.abs(lam[sel]) / (2 * np.pi)
        fmed = float(np.median(f))
        # one member per order: the nearest to the median frequency
        best: dict[int, int] = {}
        for j in sel:
            s = idx[j][0]
            if s not in best or abs(abs(lam[j]) / (2 * np.pi) - fmed) < abs(
                    abs(lam[best[s]]) / (2 * np.pi) - fmed):
                best[s] = int(j)
        mem = np.array(sorted(best.values()))
        if len(mem) < max(int(min_members), int(np.ceil(min_fraction * n_scan))):
            continue
        lm = lam[mem]
        f = np.abs(lm) / (2 * np.pi)
        z = -lm.real / np.abs(lm)
        fm, zm = float(np.median(f)), float(np.median(z))
        centre = int(mem[np.argmin(np.abs(f - fm) / max(fm, 1e-12) + np.abs(z - zm))])
        sh = shapes[centre] / max(float(np.linalg.norm(shapes[centre])), 1e-300)
        macs = _mac_matrix(sh[None], shapes[mem])[0]
        w = 2 * np.pi * fm
        out.append(PoleCluster(
            lam=complex(-zm * w, w * np.sqrt(max(1.0 - zm * zm, 0.0))),
            frequency_hz=fm, damping=zm,
            frequency_std_hz=float(np.std(f, ddof=1)) if len(mem) > 1 else 0.0,
            damping_std=float(np.std(z, ddof=1)) if len(mem) > 1 else 0.0,
            shape=sh, amplitude=float(np.median(amp[mem])),
            members=[idx[j] for j in mem], orders=[poles[idx[j][0]].order for j in mem],
            mac_spread=float(macs.min())))
    out.sort(key=lambda c: c.frequency_hz)
    return out


def diagram(poles: list[PoleSet], stable: list[NDArray[np.bool_]],
            clusters: list[PoleCluster], band_hz: tuple[float, float] | None = None,
            max_poles: int = 20000) -> dict[str, Any]:
    """JSON-ready stabilisation diagram: every pole in the band as ``[order, frequency_hz,
    damping, stable, cluster]`` (``cluster`` the index in ``clusters`` or -1), at most
    ``max_poles`` of them (the highest orders first dropped)."""
    where = {m: k for k, c in enumerate(clusters) for m in c.members}
    rows: list[list] = []
    for s, ps in enumerate(poles):
        f, z = ps.frequency_hz, ps.damping
        for i in range(f.size):
            if band_hz is not None and not band_hz[0] <= f[i] <= band_hz[1]:
                continue
            rows.append([int(ps.order), round(float(f[i]), 6), round(float(z[i]), 6),
                         bool(stable[s][i]), int(where.get((s, i), -1))])
    rows = rows[:max_poles]
    return {"columns": ["order", "frequency_hz", "damping", "stable", "cluster"],
            "poles": rows}
