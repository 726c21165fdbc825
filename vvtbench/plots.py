"""Figures shared by ``solve``, the leaderboard and the docs.

:func:`plot_fields` draws material fields like the paper's Fig. 4: every horizontal layer of
the voxel grid side by side (drums: the one 2-D image), the truth in the first row and each
estimate below it, one colour scale per field shared by truth and estimates, with a labelled
colour bar in SI units.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

__all__ = ["field_units", "plot_fields"]


def field_units(kind: str) -> tuple[str, str]:
    """Colour-bar labels of w and v for a ``"solid"`` or a ``"membrane"`` problem."""
    if kind == "membrane":
        return "tension (N/m)", "areal density (kg/m²)"
    return "Young's modulus E (Pa)", "density ρ (kg/m³)"


def _layers(grid: np.ndarray) -> list[np.ndarray]:
    """(x, y) images of the grid's z layers, bottom to top (a 2-D grid: itself)."""
    g = np.asarray(grid, dtype=float)
    if g.ndim == 2:
        return [g.T]
    if g.shape[2] == 1:
        return [g[:, :, 0].T]
    return [g[:, :, k].T for k in range(g.shape[2])]


def _limits(grids: list[np.ndarray]) -> tuple[float, float]:
    values = np.concatenate([g[np.isfinite(g)].ravel() for g in grids] or [np.zeros(1)])
    if values.size == 0:
        return 0.0, 1.0
    lo, hi = float(values.min()), float(values.max())
    if hi - lo <= 1e-9 * max(abs(hi), 1e-300):  # a constant field: a visible, centred band
        pad = 0.05 * max(abs(hi), 1e-300)
        return lo - pad, hi + pad
    return lo, hi


def plot_fields(path: str | Path, problem, estimates: Mapping[str, tuple], truth=None,
                title: str | None = None) -> Path:
    """Voxel fields of ``estimates`` (label -> (w, v) per parameter) beside ``truth``.

    One row per field source (the truth first), one column per z layer; w on the left block,
    v on the right, each with one colour scale shared by truth and estimates and a colour bar
    in SI units (:func:`field_units`). Empty voxels are blank.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows: list[tuple[str, np.ndarray, np.ndarray]] = []
    if truth is not None:
        rows.append(("truth", problem.to_grid(truth.w), problem.to_grid(truth.v)))
    for label, (w, v) in estimates.items():
        w, v = np.asarray(w, dtype=float), np.asarray(v, dtype=float)
        if w.shape != (problem.n_params,) or v.shape != (problem.n_params,):
            continue
        rows.append((label, problem.to_grid(w), problem.to_grid(v)))
    w_label, v_label = field_units(problem.kind)
    n_layers = len(_layers(rows[0][1])) if rows else 1
    limits = [_limits([r[1] for r in rows]), _limits([r[2] for r in rows])]
    size = 1.25 if n_layers > 1 else 2.6
    fig, axes = plt.subplots(len(rows), 2 * n_layers,
                             figsize=(2 * n_layers * size + 1.6, len(rows) * size + 0.9),
                             squeeze=False)
    images = [None, None]
    for r, (label, wg, vg) in enumerate(rows):
        for f, grid in enumerate((wg, vg)):
            for k, img in enumerate(_layers(grid)):
                ax = axes[r, f * n_layers + k]
                cmap = matplotlib.colormaps["viridis"].with_extremes(bad="white")
                images[f] = ax.imshow(np.ma.masked_invalid(img), origin="lower", cmap=cmap,
                                      vmin=limits[f][0], vmax=limits[f][1],
                                      interpolation="nearest")
                ax.set_xticks([])
                ax.set_yticks([])
                if r == 0 and n_layers > 1:
                    ax.set_title(f"{'wv'[f]}: layer z{k}", fontsize=7)
                if f == 0 and k == 0:
                    ax.set_ylabel(label, fontsize=8)
    for f, lab in enumerate((w_label, v_label)):
        if images[f] is not None:
            bar = fig.colorbar(images[f], ax=axes[:, f * n_layers:(f + 1) * n_layers].ravel()
                               .tolist(), orientation="horizontal", fraction=0.05, pad=0.04,
                               aspect=40)
            bar.set_label(lab, fontsize=8)
            bar.ax.tick_params(labelsize=7)
    if title:
        fig.suptitle(title, fontsize=9)
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
