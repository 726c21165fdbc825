"""Figures shared by ``solve``, the leaderboard and the docs.

Material fields (:func:`plot_field_grids`, and :func:`plot_fields` for a problem and its
parameter vectors) are drawn like the paper's Fig. 4: every z layer of the voxel grid side by
side, bottom to top, the truth in the first row and each estimate below it; w on the left, v on
the right, each field with one colour scale shared by the truth and every estimate and a
labelled colour bar in SI units (Pa and kg/m³; N/m and kg/m² for membranes). Membranes (2-D
grids, or 3-D grids one voxel thick) are drawn as one 2-D image per source, sources side by side.

Two views: ``normalized=False`` shows the values (a log colour scale when the field spans more
than a factor of 10, e.g. clay in Jello, so that neither the defect nor the estimates' smaller
contrast disappears); ``normalized=True`` shows each field's contrast ratio to its own matrix
value (the median of the field) on a shared diverging log scale centred at 1: the scale covers
the estimates' contrast and a truth beyond it saturates (the arrows on the colour bar; its
largest ratio is written beside its row).

Curves (:func:`plot_sweep`, :func:`plot_intrinsic_resolution`) use :class:`Styles`: one colour
per solver, fixed from the sorted solver names (not a cycling palette), one line style per
observation source; legends sit outside the axes; with several instances per point the mean is
drawn with a 95 % bootstrap band, with one instance markers only.
"""

from __future__ import annotations

import json
import os
import textwrap
import uuid
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import numpy as np

__all__ = ["Styles", "bootstrap_band", "field_units", "grid_kind", "plot_field_grids",
           "plot_fields", "plot_intrinsic_resolution", "plot_sweep", "plot_views",
           "save_figure", "sweep_keys"]

#: Colours of the known solvers (the others get the next free colour of tab10, in sorted order).
_KNOWN_COLOURS = {"vvt": "#1f77b4", "sensitivity": "#ff7f0e", "homogeneous": "#7f7f7f",
                  "oracle": "#2ca02c"}
_OBS_STYLES = {"true": ("-", "o"), "extracted": ("--", "s")}
_EMPTY = "#c8c8c8"  # voxels without material
#: The smallest contrast a colour scale spans (a factor): a smaller one (round-off, 1 % noise)
#: would be shown as strong structure.
_MIN_RATIO = 1.1


def _mpl():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return matplotlib, plt


def save_figure(fig, path: str | Path, dpi: int = 100) -> Path:
    """Save ``fig`` atomically (temp file + rename; a symlink at ``path`` is replaced, not
    followed) and close it. The saved area is grown to hold every label (``bbox_inches=
    "tight"``), so no title or colour-bar label is clipped at the edge."""
    _, plt = _mpl()
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}-{uuid.uuid4().hex[:8]}.tmp{path.suffix}")
    try:
        fig.savefig(tmp, dpi=dpi, bbox_inches="tight", pad_inches=0.08)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
        plt.close(fig)
    return path


# --------------------------------------------------------------------------- styles
class Styles:
    """One colour per solver and one line style and marker per observation source, fixed once
    from the names (the same solver has the same colour in every figure built from one
    ``Styles``; known solvers always have the same colour)."""

    def __init__(self, solvers: Iterable[str], observations: Iterable[str] = ("true",
                                                                             "extracted")):
        _, _ = _mpl()
        import matplotlib

        names = sorted({str(s) for s in solvers})
        taken = set(_KNOWN_COLOURS.values())
        palette = [c for c in matplotlib.colormaps["tab10"].colors
                   if matplotlib.colors.to_hex(c) not in taken]
        palette += list(matplotlib.colormaps["tab20b"].colors)
        self.colours: dict[str, str] = {}
        free = iter(palette)
        for name in names:
            if name in _KNOWN_COLOURS:
                self.colours[name] = _KNOWN_COLOURS[name]
            else:
                c = next(free, None)
                self.colours[name] = matplotlib.colors.to_hex(
                    c if c is not None else matplotlib.colormaps["hsv"](
                        (hash(name) % 97) / 97))
        extra = [("-.", "^"), (":", "D"), ((0, (5, 1, 1, 1)), "v")]
        self.lines: dict[str, tuple] = {}
        for obs in sorted({str(o) for o in observations}):
            self.lines[obs] = _OBS_STYLES.get(obs) or extra[len(self.lines) % len(extra)]

    def colour(self, solver: str) -> str:
        return self.colours.get(solver, "#000000")

    def line(self, observation: str) -> tuple:
        """(line style, marker) of an observation source."""
        return self.lines.get(observation, (":", "x"))


def bootstrap_band(values: Sequence[float], level: float = 0.95, n_boot: int = 2000,
                   seed: int = 0) -> tuple[float, float]:
    """Percentile bootstrap interval of the mean of ``values`` (NaN, NaN with < 2 values):
    :func:`vvtbench.scoring.stats.bootstrap_ci`, the one bootstrap of the leaderboard."""
    from ..scoring.stats import bootstrap_ci

    return bootstrap_ci(values, np.mean, n_boot=n_boot, level=level, seed=seed)


# --------------------------------------------------------------------------- material fields
def field_units(kind: str) -> tuple[str, str]:
    """Colour-bar labels of w and v for a ``"solid"`` or a ``"membrane"`` problem."""
    if kind == "membrane":
        return "tension (N/m)", "areal density (kg/m²)"
    return "Young's modulus E (Pa)", "density ρ (kg/m³)"


def grid_kind(grid: np.ndarray) -> str:
    """``"membrane"`` for a 2-D grid or a 3-D grid one voxel thick, else ``"solid"``."""
    g = np.asarray(grid)
    return "membrane" if g.ndim == 2 or (g.ndim == 3 and g.shape[2] == 1) else "solid"


def _layers(grid: np.ndarray) -> list[np.ndarray]:
    """(y, x) images of the grid's z layers, bottom to top (a 2-D grid: itself)."""
    g = np.asarray(grid, dtype=float)
    if g.ndim == 2:
        return [g.T]
    return [g[:, :, k].T for k in range(g.shape[2])]


def _finite(grids: Iterable[np.ndarray]) -> np.ndarray:
    parts = [np.asarray(g, dtype=float) for g in grids]
    parts = [g[np.isfinite(g)].ravel() for g in parts]
    return np.concatenate(parts) if parts else np.zeros(0)


def _matrix_value(grid: np.ndarray) -> float:
    """The field's matrix (background) value: its median over the voxels with material."""
    v = _finite([grid])
    return float(np.median(v)) if v.size else float("nan")


def _value_norm(grids: list[np.ndarray], scale: str):
    """Shared colour norm and colour-bar ``extend`` of one field over truth and estimates."""
    matplotlib, _ = _mpl()
    v = _finite(grids)
    if v.size == 0:
        return matplotlib.colors.Normalize(0.0, 1.0), "linear"
    lo, hi = float(v.min()), float(v.max())
    if scale == "log" or (scale == "auto" and lo > 0 and hi / lo > 10.0):
        if lo <= 0:
            raise ValueError("a log colour scale needs positive values")
        return matplotlib.colors.LogNorm(lo, hi), "log"
    mid = float(np.median(v))
    half = 0.5 * (_MIN_RATIO - 1) * abs(mid)  # at least +-5 % of the typical value
    if hi - lo < 2 * half:
        lo, hi = min(lo, mid - half), max(hi, mid + half)
    return matplotlib.colors.Normalize(lo, hi), "linear"


def _nice_ratio_ticks(limit: float) -> list[float]:
    cands = [1e-4, 1e-3, 0.01, 0.1, 0.2, 0.5, 0.8, 0.9, 0.95, 1.0, 1.05, 1.1, 1.25, 1.5, 2,
             5, 10, 100, 1000, 1e4]
    inside = [c for c in cands if 1 / limit / 1.0001 <= c <= limit * 1.0001]
    gap = 0.2 * np.log(limit)  # ticks at least a fifth of the half-bar apart
    ticks = [1.0]
    for side in ([c for c in inside if c > 1], [c for c in inside if c < 1][::-1]):
        last = 0.0
        for c in side:
            if abs(np.log(c)) - last >= gap:
                ticks.append(c)
                last = abs(np.log(c))
    return sorted(ticks)


def _ratio_limit(ratios: list[np.ndarray]) -> float:
    """Symmetric log limit (a factor >= 1.02) from the 99th percentile of |log ratio|."""
    v = _finite(ratios)
    v = v[v > 0]
    if v.size == 0:
        return 1.1
    return float(np.exp(max(np.quantile(np.abs(np.log(v)), 0.99), np.log(_MIN_RATIO))))


def plot_field_grids(path: str | Path, truth_w: np.ndarray | None, truth_v: np.ndarray | None,
                     estimates: Mapping[str, tuple[np.ndarray, np.ndarray]],
                     kind: str | None = None, *, normalized: bool = False,
                     scale: str = "auto", title: str | None = None,
                     notes: Mapping[str, str] | None = None, dpi: int = 100) -> Path:
    """Draw voxel grids of w and v: the truth (if given) and each estimate (label -> (w, v)).

    Grids are (nx, ny, nz) arrays (NaN: no material) or 2-D (nx, ny) for membranes; ``kind``
    (``"solid"`` or ``"membrane"``) picks the units and defaults to :func:`grid_kind`.
    ``scale`` (values view): ``"auto"`` (log when the field spans a factor > 10), ``"linear"``
    or ``"log"``. ``notes``: text under a row's label (e.g. its NC). Returns ``path``.
    """
    matplotlib, plt = _mpl()
    rows: list[tuple[str, np.ndarray, np.ndarray]] = []
    if truth_w is not None and truth_v is not None:
        rows.append(("truth", np.asarray(truth_w, float), np.asarray(truth_v, float)))
    for label, (w, v) in estimates.items():
        rows.append((str(label), np.asarray(w, float), np.asarray(v, float)))
    if not rows:
        raise ValueError("plot_field_grids: nothing to draw")
    shape = rows[0][1].shape
    rows = [r for r in rows if r[1].shape == shape and r[2].shape == shape]
    kind = kind or grid_kind(rows[0][1])
    labels = field_units(kind)
    has_truth = rows[0][0] == "truth" and truth_w is not None
    notes = dict(notes or {})

    fields: list[list[np.ndarray]] = [[r[1] for r in rows], [r[2] for r in rows]]
    norms, extends, cbar_labels, cmaps, tick_sets = [], [], [], [], []
    for f in range(2):
        grids = fields[f]
        if normalized:
            ratios = [g / _matrix_value(g) for g in grids]
            fields[f] = ratios
            est = ratios[1:] if has_truth and len(ratios) > 1 else ratios
            lim = _ratio_limit(est)
            norms.append(matplotlib.colors.LogNorm(1 / lim, lim))
            over = _finite(ratios)
            extends.append("both" if over.size and (over.max() > lim * 1.0001
                                                    or over.min() < 1 / lim / 1.0001)
                           else "neither")
            cbar_labels.append(labels[f].split(" (")[0] + " / matrix value (median)")
            cmaps.append(matplotlib.colormaps["RdBu_r"].with_extremes(bad=_EMPTY))
            tick_sets.append(_nice_ratio_ticks(lim))
            if has_truth:
                t = _finite([ratios[0]])
                if t.size and (t.max() > lim * 1.0001 or t.min() < 1 / lim / 1.0001):
                    notes.setdefault("truth", f"×{t.min():.3g} … ×{t.max():.3g}\n(saturated)")
        else:
            norm, how = _value_norm(grids, scale)
            norms.append(norm)
            extends.append("neither")
            cbar_labels.append(labels[f] + (", log scale" if how == "log" else ""))
            cmaps.append(matplotlib.colormaps["viridis"].with_extremes(bad=_EMPTY))
            tick_sets.append(None)

    membrane = kind == "membrane" or len(_layers(rows[0][1])) == 1
    n_rows = len(rows)
    if membrane:  # sources side by side: one row of w images and one of v images
        n_img = n_rows
        panel = 2.0
        fig = plt.figure(figsize=(n_img * panel + 1.6, 2 * panel + 1.0))
        gs = fig.add_gridspec(2, n_img + 1, width_ratios=[1] * n_img + [0.08],
                              left=0.02, right=0.86, top=0.86, bottom=0.04,
                              wspace=0.08, hspace=0.18)
        for f in range(2):
            im = None
            for i, (label, *_rest) in enumerate(rows):
                ax = fig.add_subplot(gs[f, i])
                img = _layers(fields[f][i])[0]
                im = ax.imshow(np.ma.masked_invalid(img), origin="lower", cmap=cmaps[f],
                               norm=norms[f], interpolation="nearest")
                ax.set_xticks([])
                ax.set_yticks([])
                if f == 0:
                    txt = _wrap(label) + (f"\n{notes[label]}" if label in notes else "")
                    ax.set_title(txt, fontsize=8, fontweight="bold" if i == 0 and has_truth
                                 else "normal")
                if i == 0:
                    ax.set_ylabel("w" if f == 0 else "v", fontsize=9)
            cax = fig.add_subplot(gs[f, n_img])
            _colourbar(fig, im, cax, cbar_labels[f], extends[f], tick_sets[f])
    else:
        layers = len(_layers(rows[0][1]))
        panel = 0.78
        label_w = 1.9
        widths = [label_w] + [1] * layers + [0.12, 1.1] + [1] * layers + [0.12]
        fig_w = panel * (2 * layers + 0.24 + label_w + 1.1) + 1.2
        fig = plt.figure(figsize=(fig_w, n_rows * panel * 1.08 + 1.3))
        gs = fig.add_gridspec(n_rows, len(widths), width_ratios=widths, left=0.01,
                              right=1 - 0.9 / fig_w, top=1 - 0.8 / (n_rows * panel * 1.08 + 1.3),
                              bottom=0.04, wspace=0.06, hspace=0.08)
        for f in range(2):
            c0 = 1 if f == 0 else layers + 3
            im = None
            for i, (label, *_rest) in enumerate(rows):
                for k, img in enumerate(_layers(fields[f][i])):
                    ax = fig.add_subplot(gs[i, c0 + k])
                    im = ax.imshow(np.ma.masked_invalid(img), origin="lower", cmap=cmaps[f],
                                   norm=norms[f], interpolation="nearest")
                    ax.set_xticks([])
                    ax.set_yticks([])
                    for s in ax.spines.values():
                        s.set_linewidth(0.4)
                    if i == 0:
                        name = f"z{k + 1}" + (" bottom" if k == 0 else " top"
                                              if k == layers - 1 else "")
                        ax.set_title(name, fontsize=7)
                if f == 0:
                    lax = fig.add_subplot(gs[i, 0])
                    lax.axis("off")
                    txt = _wrap(label) + (f"\n{notes[label]}" if label in notes else "")
                    lax.text(1.0, 0.5, txt, ha="right", va="center", fontsize=8,
                             fontweight="bold" if i == 0 and has_truth else "normal",
                             transform=lax.transAxes)
            cax = fig.add_subplot(gs[:, c0 + layers])
            _colourbar(fig, im, cax, cbar_labels[f], extends[f], tick_sets[f])
            top = fig.add_subplot(gs[0, c0:c0 + layers], frame_on=False)
            top.set_xticks([])
            top.set_yticks([])
            top.set_title(("w: " if f == 0 else "v: ") + labels[f].split(" (")[0]
                          + " — layers of the voxel grid, bottom to top", fontsize=8, pad=16)
            top.patch.set_alpha(0)
    what = "contrast to the matrix value" if normalized else "values"
    head = title + f" ({what})" if title else f"Material fields: {what}"
    fig.suptitle(head + ("; grey: no material" if any(np.isnan(fields[0][0]).ravel())
                         else ""), fontsize=9)
    return save_figure(fig, path, dpi=dpi)


def _wrap(label: str) -> str:
    """Long row labels on two lines (at the first ", ")."""
    return label.replace(", ", ",\n", 1) if len(label) > 16 else label


def _colourbar(fig, im, cax, label: str, extend: str, ticks) -> None:
    _, _ = _mpl()
    import matplotlib.ticker as mticker

    bar = fig.colorbar(im, cax=cax, extend=extend)
    bar.set_label(label, fontsize=8)
    bar.ax.tick_params(which="both", labelsize=7)
    if ticks is not None:
        bar.set_ticks(ticks)
        bar.ax.yaxis.set_major_formatter(mticker.FuncFormatter(lambda x, _: f"×{x:.3g}"))
        bar.ax.yaxis.set_minor_formatter(mticker.NullFormatter())


#: a field's values view flattens the estimates when the truth's span (max - min) is more than
#: this many times the widest estimate's span: the contrast view is then shown first
CONTRAST_FIRST_RATIO = 10.0


def contrast_first(truth: np.ndarray | None, estimates: Iterable[np.ndarray],
                   ratio: float = CONTRAST_FIRST_RATIO) -> bool:
    """Whether the contrast view (each field against its own matrix value) should come before
    the values view (one colour scale shared with the truth): True when the truth's span
    (max - min over finite voxels) exceeds ``ratio`` times the largest span of ``estimates``.

    >>> contrast_first(np.array([1.0, 186.0]), [np.array([1.0, 3.0])])
    True
    >>> contrast_first(np.array([1.0, 5.0]), [np.array([1.0, 3.0])])
    False
    """
    if truth is None:
        return False
    t = _finite([np.asarray(truth, float)])
    spans = [np.ptp(e) for e in (_finite([np.asarray(g, float)]) for g in estimates) if e.size]
    if t.size == 0 or not spans:
        return False
    widest = max(spans)
    return bool(np.ptp(t) > ratio * widest) if widest > 0 else bool(np.ptp(t) > 0)


def solve_title(scene: str | None = None, observation: str | None = None,
                solver: str | None = None, score: Mapping[str, float] | None = None) -> str:
    """``vvt on cube_top (true modes): NC w 0.41, NC v 0.12``: what a figure shows and how it
    scored; the parts not given are left out."""
    head = solver or "estimate"
    if scene:
        head += f" on {scene}"
    if observation:
        head += f" ({observation} modes)"
    parts = []
    for name, value in (score or {}).items():
        ok = isinstance(value, (int, float)) and np.isfinite(value)
        parts.append(f"{name} {value:.2f}" if ok else f"{name} undefined")
    return head + (": " + ", ".join(parts) if parts else "")


def plot_fields(path: str | Path, problem, estimates: Mapping[str, tuple], truth=None,
                title: str | None = None, *, normalized: bool = False,
                scene: str | None = None, observation: str | None = None,
                solver: str | None = None,
                score: Mapping[str, float] | None = None) -> Path:
    """Voxel fields of ``estimates`` (label -> (w, v) per parameter) beside ``truth`` (an
    object with ``w`` and ``v`` per parameter), drawn by :func:`plot_field_grids`.

    ``scene``, ``observation``, ``solver`` and ``score`` (e.g. ``{"NC w": 0.41, "NC v":
    0.12}``) make the title when ``title`` is not given (:func:`solve_title`).
    """
    grids = {}
    for label, (w, v) in estimates.items():
        w, v = np.asarray(w, dtype=float), np.asarray(v, dtype=float)
        if w.shape != (problem.n_params,) or v.shape != (problem.n_params,):
            continue
        grids[label] = (problem.to_grid(w), problem.to_grid(v))
    tw = problem.to_grid(truth.w) if truth is not None else None
    tv = problem.to_grid(truth.v) if truth is not None else None
    kind = "membrane" if getattr(problem, "kind", "solid") == "membrane" else "solid"
    if title is None and any(x is not None for x in (scene, observation, solver, score)):
        title = solve_title(scene, observation, solver, score)
    return plot_field_grids(path, tw, tv, grids, kind, normalized=normalized, title=title)


def plot_uncertainty(path: str | Path, problem, estimate: tuple, std: tuple, truth=None,
                     title: str | None = None) -> Path:
    """A solver's stated uncertainty beside its estimate, per field (w, v) and voxel layer:
    the estimate, its relative standard deviation ``std / value`` and, with ``truth``, the
    error in units of the stated deviation ``|estimate - truth| / std`` (above 1.96: the
    truth lies outside the 95 % interval; the fraction at most 1.96 is the interval coverage).

    ``estimate`` and ``std`` are ``(w, v)`` per parameter (``std`` entries may be None: that
    field is not drawn). Returns ``path``.
    """
    from ..scoring.metrics import COVERAGE_Z, interval_coverage

    matplotlib, plt = _mpl()
    kind = "membrane" if getattr(problem, "kind", "solid") == "membrane" else "solid"
    units = field_units(kind)
    rows: list[tuple[str, np.ndarray, str, object]] = []
    for f, (name, est, sd) in enumerate(zip("wv", estimate, std, strict=True)):
        if sd is None:
            continue
        est, sd = np.asarray(est, dtype=float), np.asarray(sd, dtype=float)
        viridis = matplotlib.colormaps["viridis"].with_extremes(bad=_EMPTY)
        g_est = problem.to_grid(est)
        rows.append((f"{name} estimate", g_est, units[f], _value_norm([g_est], "auto")[0],
                     viridis))
        rel = problem.to_grid(np.abs(sd) / np.abs(est))
        hi = float(np.nanmax(rel)) if np.isfinite(rel).any() else 1.0
        rows.append((f"{name} std / {name}", rel, "std / value",
                     matplotlib.colors.Normalize(0.0, max(hi, 1e-6)),
                     matplotlib.colormaps["magma"].with_extremes(bad=_EMPTY)))
        if truth is not None:
            tru = np.asarray(getattr(truth, name), dtype=float)
            z = problem.to_grid(np.abs(est - tru) / np.maximum(np.abs(sd), 1e-300))
            cov = interval_coverage(est, sd, tru, z=COVERAGE_Z)
            rows.append((f"|{name} - truth| / std\n(95 % coverage {cov:.2f})", z,
                         "|error| / std",
                         matplotlib.colors.Normalize(0.0, 4.0),
                         matplotlib.colormaps["RdYlBu_r"].with_extremes(bad=_EMPTY,
                                                                        over="#67001f")))
    if not rows:
        raise ValueError("plot_uncertainty: no standard deviation to draw")
    layers = len(_layers(rows[0][1]))
    panel = 0.9
    fig_w, fig_h = 2.2 + panel * layers + 1.6, len(rows) * panel * 1.1 + 1.1
    fig = plt.figure(figsize=(fig_w, fig_h))
    gs = fig.add_gridspec(len(rows), layers + 2, width_ratios=[2.2] + [1] * layers + [0.12],
                          left=0.01, right=1 - 1.2 / fig_w, top=1 - 0.8 / fig_h,
                          bottom=0.03, wspace=0.06, hspace=0.25)
    for i, (label, grid, bar_label, norm, cmap) in enumerate(rows):
        im = None
        for k, img in enumerate(_layers(grid)):
            ax = fig.add_subplot(gs[i, 1 + k])
            im = ax.imshow(np.ma.masked_invalid(img), origin="lower", cmap=cmap, norm=norm,
                           interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if i == 0 and layers > 1:
                ax.set_title(f"z{k + 1}" + (" bottom" if k == 0 else " top"
                                            if k == layers - 1 else ""), fontsize=7)
        lax = fig.add_subplot(gs[i, 0])
        lax.axis("off")
        lax.text(1.0, 0.5, label, ha="right", va="center", fontsize=8,
                 transform=lax.transAxes)
        bar = fig.colorbar(im, cax=fig.add_subplot(gs[i, layers + 1]),
                           extend="max" if "truth" in label else "neither")
        bar.set_label(bar_label, fontsize=7)
        bar.ax.tick_params(labelsize=6)
    fig.suptitle((title or "Stated uncertainty") + "\nlayers of the voxel grid, bottom to top; "
                 "|error| / std above 1.96: the truth is outside the 95 % interval", fontsize=8)
    return save_figure(fig, path)


# --------------------------------------------------------------------------- curves
def sweep_keys(df) -> list[str]:
    """Keys of ``variation_options`` (JSON) holding more than one numeric value in ``df``."""
    if "variation_options" not in df.columns:
        return []
    values: dict[str, set] = {}
    for text in df["variation_options"].dropna().unique():
        try:
            opts = json.loads(text)
        except (TypeError, ValueError):
            continue
        for k, v in opts.items():
            if isinstance(v, (int, float)) and not isinstance(v, bool):
                values.setdefault(k, set()).add(float(v))
    return [k for k, s in values.items() if len(s) > 1]


def _option(text, key: str) -> float:
    try:
        v = json.loads(text).get(key)
    except (TypeError, ValueError, AttributeError):
        return float("nan")
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else float("nan")


_KEY_LABELS = {"n_modes": "number of modes", "geometry_scale": "inference mesh width / true width",
               "nu": "Poisson's ratio ν of the inference model"}


def _key_label(key: str) -> str:
    if key in _KEY_LABELS:
        return _KEY_LABELS[key]
    if key.endswith("alpha_v"):
        return f"α_v ({key})"
    if key.endswith("alpha_w"):
        return f"α_w ({key})"
    return key


def _draw_curve(ax, x, groups, colour, ls, marker, label):
    """Mean per x; a 95 % bootstrap band where a point has several instances."""
    means, lo, hi, many = [], [], [], False
    for vals in groups:
        means.append(np.nanmean(vals) if np.isfinite(vals).any() else np.nan)
        a, b = bootstrap_band(vals)
        lo.append(a)
        hi.append(b)
        many |= np.isfinite(vals).sum() > 1
    if many:
        ax.plot(x, means, linestyle=ls, marker=marker, ms=3.5, color=colour, label=label)
        ax.fill_between(x, lo, hi, color=colour, alpha=0.15, linewidth=0)
    else:
        ax.plot(x, means, linestyle="none" if len(x) == 1 else ls, marker=marker, ms=5,
                color=colour, label=label, alpha=0.9)


def plot_sweep(path: str | Path, df, key: str, styles: Styles, title: str = "",
               fields: Sequence[str] = ("w", "v"), dpi: int = 100) -> bool:
    """NC of each field against the sweep value ``key`` of ``variation_options``: one panel
    per scene and field, one colour per solver, one line style per observation source; mean
    over instances (seeds) with a 95 % bootstrap band when a point has several. Only rows with
    status ok are drawn. Returns False when there is nothing to draw. A swept value that is
    a whole number everywhere (a count: modes, cameras) gets integer ticks only."""
    _, plt = _mpl()
    from matplotlib.ticker import MaxNLocator

    d = df.copy()
    d["_x"] = [_option(t, key) for t in d["variation_options"]]
    d = d[np.isfinite(d["_x"])]
    swept = {scene: np.sort(g["_x"].unique()) for scene, g in d.groupby("scene", sort=False)}
    d = d[d.status == "ok"]
    if d.empty or d["_x"].nunique() < 2:
        return False
    scenes = list(dict.fromkeys(d["scene"]))
    fig, axes = plt.subplots(len(scenes), len(fields), figsize=(4.3 * len(fields) + 2.6,
                                                                 3.0 * len(scenes) + 0.5),
                             squeeze=False, sharex=True, sharey=True)
    xs = d["_x"].to_numpy()
    log = bool(xs.min() > 0 and xs.max() / xs.min() >= 100)
    counts = bool(np.all(xs == np.round(xs)))  # a count (modes, cameras): integer ticks
    for i, scene in enumerate(scenes):
        ds = d[d.scene == scene]
        for j, field in enumerate(fields):
            ax = axes[i, j]
            for (solver, obs), g in ds.groupby(["solver", "observation"], sort=True):
                # every swept value of the scene: a value with no valid run is a gap
                x = swept[scene]
                vals = [g[g["_x"] == v][f"nc_{field}"].to_numpy(float) for v in x]
                ls, marker = styles.line(obs)
                ref = " (reference)" if "reference" in g and g["reference"].astype(bool).any() \
                    else ""
                _draw_curve(ax, x, vals, styles.colour(solver), ls, marker,
                            f"{solver}{ref}, {obs} modes")
            if log:
                ax.set_xscale("log")
            elif counts:
                ax.xaxis.set_major_locator(MaxNLocator(integer=True))
            ax.axhline(0, color="k", lw=0.5, alpha=0.4)
            ax.grid(alpha=0.3)
            sub = f"{scene}: NC of {field}".replace("+", " + ")
            ax.set_title(textwrap.fill(sub, 50) if len(scenes) > 1 else f"NC of {field}",
                         fontsize=8)
            if i == len(scenes) - 1:
                ax.set_xlabel(_key_label(key), fontsize=8)
            if j == 0:
                ax.set_ylabel("NC (Pearson)", fontsize=8)
            ax.tick_params(labelsize=7)
    _legend_outside(fig, axes)
    n = d.groupby(["scene", "solver", "observation", "_x"]).size().max()
    how = (f"mean of up to {n} instances, band: 95 % bootstrap interval" if n > 1
           else "one instance per point, no band")
    fig.suptitle(f"{title or 'NC against ' + _key_label(key)} ({how})", fontsize=9)
    return bool(save_figure(fig, path, dpi=dpi))


def plot_views(path: str | Path, df, styles: Styles, title: str = "", dpi: int = 100) -> bool:
    """What more cameras buy, pooled over the instances of a track that sweeps ``views``.

    Left: NC w against the number of views, per solver and observation source, the mean over
    the instances with a valid row at every number of views (paired, so the curve's steps
    are within-instance gains) and its 95 % bootstrap band. Right: NC w against the fraction of
    the DOFs observed (column ``observed_dof_fraction``), one thin line per instance and solver
    joining its numbers of views. Instances without a defect have no NC and are left out.
    Returns False when there is nothing to draw."""
    _, plt = _mpl()
    from matplotlib.ticker import MaxNLocator

    d = df.copy()
    d["_x"] = [_option(t, "views") for t in d["variation_options"]]
    d = d[np.isfinite(d["_x"]) & (d.status == "ok")]
    d = d[np.isfinite(d["nc_w"].to_numpy(float))]
    if d.empty or d["_x"].nunique() < 2:
        return False
    has_dof = "observed_dof_fraction" in d and np.isfinite(
        d["observed_dof_fraction"].to_numpy(float)).any()
    fig, axes = plt.subplots(1, 2 if has_dof else 1, figsize=(11.5 if has_dof else 6.5, 3.8),
                             squeeze=False, sharey=True)
    left = axes[0, 0]
    x = np.sort(d["_x"].unique())
    n_paired = []
    for (solver, obs), g in d.groupby(["solver", "observation"], sort=True):
        table = g.pivot_table(index=["scene", "seed"], columns="_x", values="nc_w",
                              aggfunc="first").reindex(columns=x).dropna()
        if table.empty:
            continue
        n_paired.append(len(table))
        ls, marker = styles.line(obs)
        ref = " (reference)" if "reference" in g and g["reference"].astype(bool).any() else ""
        label = f"{solver}{ref}, {obs} modes"
        _draw_curve(left, x, [table[v].to_numpy(float) for v in x], styles.colour(solver), ls,
                    marker, f"{label} (n={len(table)})")
        if has_dof:
            right = axes[0, 1]
            for _, inst in g.sort_values("_x").groupby(["scene", "seed"], sort=False):
                dof = inst["observed_dof_fraction"].to_numpy(float)
                right.plot(dof, inst["nc_w"].to_numpy(float), linestyle=ls, marker=marker,
                           ms=3, lw=0.8, alpha=0.55, color=styles.colour(solver))
    if not n_paired:
        plt.close(fig)
        return False
    left.xaxis.set_major_locator(MaxNLocator(integer=True))
    left.set_xlabel("number of camera views", fontsize=8)
    left.set_ylabel("NC of w (Pearson)", fontsize=8)
    left.set_title("mean over the instances valid at every number of views\n"
                   "(band: 95 % bootstrap interval)", fontsize=8)
    panels = [left]
    if has_dof:
        right = axes[0, 1]
        right.set_xlabel("fraction of the model's DOFs observed", fontsize=8)
        right.set_title("one line per instance and solver,\nfrom 1 view (left end) to the "
                        "most", fontsize=8)
        panels.append(right)
    for ax in panels:
        ax.axhline(0, color="k", lw=0.5, alpha=0.4)
        ax.grid(alpha=0.3)
        ax.tick_params(labelsize=7)
    _legend_outside(fig, axes)
    fig.suptitle(title or "NC of w against the number of views", fontsize=9)
    return bool(save_figure(fig, path, dpi=dpi))


def _legend_outside(fig, axes) -> None:
    handles, labels = {}, []
    for ax in np.ravel(axes):
        for h, lab in zip(*ax.get_legend_handles_labels(), strict=True):
            if lab not in handles:
                handles[lab] = h
                labels.append(lab)
    width, height = fig.get_size_inches()
    axes_width = 0.78 * width
    # the legend's own width (7 pt text, about 0.055 in a character, plus the line sample), so
    # long labels ("sensitivity, extracted:farneback modes (n=16)") are never cut at the edge
    legend_width = 0.055 * max((len(k) for k in labels), default=0) + 0.6
    if axes_width + legend_width > width:
        width = axes_width + legend_width
        fig.set_size_inches(width, height)
    right = axes_width / width
    fig.tight_layout(rect=(0, 0, right, 0.95))
    if labels:
        fig.legend([handles[k] for k in labels], labels, loc="center left",
                   bbox_to_anchor=(right + 0.01, 0.5), fontsize=7, frameon=False)


def plot_intrinsic_resolution(path: str | Path, curves: Mapping[tuple[str, str], dict],
                              styles: Styles, title: str = "", dpi: int = 100) -> bool:
    """NC of the estimate with the Gaussian-blurred truth against the blur σ (voxels).

    ``curves``: (solver, observation) -> {"sigmas": (s,), "w": [(s,) per instance],
    "v": [...]}; mean with a 95 % bootstrap band over instances (one instance: the curve and
    its peak σ* marked)."""
    _, plt = _mpl()
    if not curves:
        return False
    fig, axes = plt.subplots(1, 2, figsize=(11.2, 3.6), sharey=True, squeeze=False)
    for j, field in enumerate(("w", "v")):
        ax = axes[0, j]
        for (solver, obs), c in sorted(curves.items()):
            arr = np.asarray(c.get(field, []), dtype=float)
            if arr.size == 0:
                continue
            s = np.asarray(c["sigmas"], dtype=float)
            ls, marker = styles.line(obs)
            colour = styles.colour(solver)
            mean = arr.mean(axis=0)
            label = f"{solver}, {obs} modes (n={len(arr)})"
            ax.plot(s, mean, linestyle=ls, color=colour, label=label)
            if len(arr) > 1:
                band = np.array([bootstrap_band(arr[:, k]) for k in range(arr.shape[1])])
                ax.fill_between(s, band[:, 0], band[:, 1], color=colour, alpha=0.15, lw=0)
            k = int(np.nanargmax(mean)) if np.isfinite(mean).any() else 0
            ax.plot([s[k]], [mean[k]], marker=marker, color=colour, ms=5)
        ax.axhline(0, color="k", lw=0.5, alpha=0.4)
        ax.set_xlabel("σ of the Gaussian blur of the truth (voxels)", fontsize=8)
        ax.set_title(f"NC of {field} with the blurred truth (marker: peak σ*)", fontsize=8)
        ax.grid(alpha=0.3)
        ax.tick_params(labelsize=7)
    axes[0, 0].set_ylabel("NC (Pearson)", fontsize=8)
    _legend_outside(fig, axes)
    fig.suptitle(title or "intrinsic resolution", fontsize=9)
    return bool(save_figure(fig, path, dpi=dpi))
