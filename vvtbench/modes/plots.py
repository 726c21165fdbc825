"""PNG plots of a :class:`ModeSet` (matplotlib, Agg backend)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from .modeset import ModeSet
from .uncertainty import Z95

__all__ = ["plot_mode", "plot_modes", "plot_spectrum", "plot_stabilization"]


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def _floor(ms: ModeSet):
    """The noise floor model the peaks were tested against (recomputed from the power)."""
    from .significance import noise_floor

    nf = ms.metadata.get("noise_floor")
    band = ms.metadata.get("band_hz")
    if not nf or not band or ms.power.size < 3:
        return None
    f = ms.freqs_hz
    first = max(1, int(ms.metadata.get("min_bin", 1)))
    inb = np.flatnonzero((f >= band[0]) & (f <= band[1]) & (np.arange(f.size) >= first))
    if not inb.size:
        return None
    return noise_floor(ms.power, slice(int(inb[0]), int(inb[-1]) + 1),
                       false_alarm=nf["false_alarm"], half_width_bins=nf["half_width_bins"])


def _xmax(ms: ModeSet) -> float:
    """Right end of the spectrum plot: the band's, or when the band is the whole Nyquist
    range (no fmax given) 2.5 times the highest kept mode (the rest is noise)."""
    nyq = ms.fps / 2.0
    band = ms.metadata.get("band_hz") or [0.0, nyq]
    hi = float(band[1])
    if hi >= nyq * (1 - 1e-9) and len(ms):
        hi = min(hi, max(2.5 * float(np.max(ms.frequencies_hz)), 20 * ms.fps / ms.n_frames))
    return hi


def plot_spectrum(ms: ModeSet, path: str | Path) -> Path:
    """Motion power spectrum (log scale) over the analysed band, with the noise floor.

    Kept modes are red triangles labelled ``#i f Hz`` (labels staggered over three heights
    so neighbours do not overlap), rejected peaks (camera shake, distortion products,
    incoherent; ``metadata["rejected"]``) are grey crosses without labels; the noise
    floor (running median) and the significance threshold (docs/modes.md) are drawn.
    """
    plt = _plt()
    fig, ax = plt.subplots(figsize=(10, 4.5), dpi=110)
    band = ms.metadata.get("band_hz") or [0.0, ms.fps / 2.0]
    x0, x1 = float(band[0]), _xmax(ms)
    if ms.power.size:
        sel = (ms.freqs_hz >= x0) & (ms.freqs_hz <= x1)
        sel[0] = False
        f, p = ms.freqs_hz[sel], np.maximum(ms.power[sel], 1e-300)
        ax.semilogy(f, p, lw=0.8, color="k", label="motion power")
        nf = _floor(ms)
        if nf is not None:
            ax.semilogy(f, nf.floor[sel], color="tab:blue", lw=0.8, alpha=0.8,
                        label="noise floor (running median)")
            ax.semilogy(f, nf.threshold()[sel], "--", color="tab:blue", lw=0.8,
                        label=f"threshold (false alarm {nf.false_alarm:g}/spectrum)")
        first = int(ms.metadata.get("min_bin", 0))
        if first > 1:
            ax.axvspan(x0, first * ms.fps / ms.n_frames, color="0.85", alpha=0.5, lw=0,
                       label="below resolution (drift)")
        for r in ms.metadata.get("rejected", []):
            k = r.get("bin", -1)
            if 0 <= k < ms.power.size and x0 <= ms.freqs_hz[k] <= x1:
                ax.plot(ms.freqs_hz[k], ms.power[k], "x", color="0.5", ms=7)
        order = np.argsort(ms.frequencies_hz)
        small = len(ms) > 12
        sf = ms.frequency_std_hz()
        for j, i in enumerate(order):
            k = int(ms.peak_bins[i])
            if not (0 <= k < ms.power.size and x0 <= ms.freqs_hz[k] <= x1):
                continue
            ax.plot(ms.freqs_hz[k], ms.power[k], "v", color="tab:red", ms=6)
            if np.isfinite(sf[i]):
                ax.errorbar(ms.frequencies_hz[i], ms.power[k] * 1.6, xerr=Z95 * sf[i],
                            fmt="none", ecolor="tab:red", elinewidth=1.2, capsize=2)
            # labels in three staggered rows along the top, a leader line to each peak
            ax.annotate(
                f"#{i} {ms.frequencies_hz[i]:.{1 if small else 2}f}",
                xy=(ms.freqs_hz[k], ms.power[k]),
                xytext=(ms.freqs_hz[k], 0.965 - 0.055 * (j % 3)),
                textcoords=("data", "axes fraction"),
                ha="center",
                va="top",
                fontsize=6.5 if small else 7.5,
                color="tab:red",
                arrowprops={"arrowstyle": "-", "color": "tab:red", "lw": 0.4, "alpha": 0.5,
                            "shrinkA": 0, "shrinkB": 4},
            )
        if sel.any():
            lo = max(float(np.min(p)), float(np.max(p)) * 1e-14)
            # head room for the label rows (~20 % of the height)
            span = math.log10(float(np.max(p)) / lo) + 0.5
            ax.set_ylim(lo / 3, float(np.max(p)) * 10 ** (0.3 * span))
    ax.plot([], [], "v", color="tab:red", label="mode (#index, Hz)")
    if ms.metadata.get("rejected"):
        ax.plot([], [], "x", color="0.5", label="rejected peak")
    ax.set_xlim(x0, x1)
    ax.set_xlabel("frequency (Hz)")
    ax.set_ylabel("motion power (px$^2$, unnormalised DFT)")
    shown = "" if x1 >= float(band[1]) * (1 - 1e-9) else f", shown to {x1:.3g} Hz"
    ax.set_title(f"Motion power spectrum: {len(ms)} modes, fps {ms.fps:g}, T = {ms.n_frames}, "
                 f"band {band[0]:.3g}-{band[1]:.4g} Hz{shown}", fontsize=9)
    ax.grid(True, which="both", alpha=0.2)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    out = Path(path)
    from ..io.files import atomic_file

    with atomic_file(out) as f:  # never through a link at ``out``
        fig.savefig(f, format=out.suffix[1:] or "png")
    plt.close(fig)
    return out


def plot_mode(ms: ModeSet, i: int, path: str | Path, max_arrows: int = 32) -> Path:
    """Mode ``i``: ``dx`` and ``dy`` images (shared symmetric colour scale) and a quiver.

    The colour scale ends at the 99.5 % quantile of ``|shape|`` (the colour bar marks clipped
    values), so that a few pixels at depth or texture seams do not wash out the mode.
    """
    plt = _plt()
    s = ms.shapes[i]
    H, W = s.shape[:2]
    vmax = float(np.quantile(np.abs(s), 0.995)) or float(np.max(np.abs(s))) or 1.0
    fig, axes = plt.subplots(1, 3, figsize=(12, 4), dpi=100)
    fig.subplots_adjust(top=0.8)
    for ax, c, name in ((axes[0], 0, "dx"), (axes[1], 1, "dy")):
        im = ax.imshow(s[..., c], cmap="RdBu_r", vmin=-vmax, vmax=vmax)
        ax.set_title(name)
        ax.axis("off")
    fig.colorbar(im, ax=axes[:2], shrink=0.8, extend="both")
    step = max(1, int(np.ceil(max(H, W) / max_arrows)))
    yy, xx = np.mgrid[step // 2 : H : step, step // 2 : W : step]
    ax = axes[2]
    ax.imshow(np.hypot(s[..., 0], s[..., 1]), cmap="gray_r", vmin=0.0, vmax=vmax * np.sqrt(2))
    ax.quiver(xx, yy, s[yy, xx, 0], s[yy, xx, 1], color="tab:red", angles="xy", pivot="mid")
    ax.set_title("shape (arrows, image y down)")
    ax.axis("off")
    lo, hi = ms.damping_interval()
    sf = ms.frequency_std_hz()[i]
    zeta = (f", zeta = {ms.damping[i]:.4f}" if ms.damping_resolved()[i]
            else ", zeta not resolved")
    if np.isfinite(lo[i]):
        zeta += f" [{lo[i]:.4f}, {hi[i]:.4f}]"
    if ms.close_mode_bias()[i]:
        zeta += " (biased by a close mode)"
    peak, start = ms.peak_displacement_px[i], ms.initial_displacement_px[i]
    fig.suptitle(
        f"mode #{i}: {ms.frequencies_hz[i]:.3f}"
        + (f" +- {sf:.2g}" if np.isfinite(sf) else "")
        + f" Hz{zeta},\npeak displacement {peak:.3g} px"
        + (f" ({start:.3g} px at onset)" if start > 1.05 * peak else "")
        + " (unit-norm shape shown)"
        + ("  [camera shake]" if ms.camera_shake[i] else "")
    )
    out = Path(path)
    from ..io.files import atomic_file

    with atomic_file(out) as f:  # never through a link at ``out``
        fig.savefig(f, format=out.suffix[1:] or "png")
    plt.close(fig)
    return out


def _modes_xmax(ms: ModeSet) -> float:
    """Right edge of the per-mode figures: past the highest mode, within :func:`_xmax`."""
    if not len(ms):
        return _xmax(ms)
    top = float(np.max(ms.frequencies_hz))
    return min(_xmax(ms), max(1.5 * top, top + 20.0 * ms.fps / max(ms.n_frames, 1)))


def plot_uncertainty(ms: ModeSet, path: str | Path) -> Path:
    """Damping ratio against frequency with the 95 % intervals of both (line fit only):
    resolved dampings in blue, unresolved in grey, modes biased by a close neighbour
    ringed in red."""
    plt = _plt()
    lo, hi = ms.damping_interval()
    sf = ms.frequency_std_hz()
    resolved, biased = ms.damping_resolved(), ms.close_mode_bias()
    fig, ax = plt.subplots(figsize=(9, 4.5), dpi=110)
    for i in range(len(ms)):
        f, z = float(ms.frequencies_hz[i]), float(ms.damping[i])
        if not np.isfinite(z):
            continue
        color = "tab:blue" if resolved[i] else "0.55"
        yerr = ([[max(z - lo[i], 0.0)], [max(hi[i] - z, 0.0)]] if np.isfinite(lo[i])
                else None)
        xerr = Z95 * sf[i] if np.isfinite(sf[i]) else None
        ax.errorbar(f, max(z, 1e-5), yerr=yerr, xerr=xerr, fmt="o", color=color, ms=4,
                    capsize=3, lw=1)
        if biased[i]:
            ax.plot(f, max(z, 1e-5), "o", mfc="none", mec="tab:red", ms=11, mew=1.5)
        ax.annotate(f"#{i}", (f, max(z, 1e-5)), textcoords="offset points", xytext=(4, 4),
                    fontsize=7)
    ax.errorbar([], [], yerr=[], fmt="o", color="tab:blue", label="damping resolved")
    ax.errorbar([], [], yerr=[], fmt="o", color="0.55", label="not resolved")
    ax.plot([], [], "o", mfc="none", mec="tab:red", label="biased by a close mode")
    ax.set_yscale("log")
    z = np.asarray(ms.damping, np.float64)
    top = np.concatenate([z[np.isfinite(z)], hi[np.isfinite(hi)]])
    bottom = np.concatenate([z[np.isfinite(z) & (z > 0)], lo[np.isfinite(lo) & (lo > 0)]])
    ax.set_ylim(max(float(bottom.min()) / 2 if bottom.size else 1e-4, 1e-5),
                max(float(top.max()) * 2 if top.size else 1.0, 1e-3))
    ax.set_xlim(float(ms.metadata.get("band_hz", [0, 0])[0]), _modes_xmax(ms))
    ax.set_xlabel("frequency (Hz)")
    ax.set_ylabel("damping ratio zeta (95 % interval)")
    ax.set_title("Identified modes with their 95 % intervals")
    ax.grid(True, which="both", alpha=0.2)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    out = Path(path)
    from ..io.files import atomic_file

    with atomic_file(out) as fh:
        fig.savefig(fh, format=out.suffix[1:] or "png")
    plt.close(fig)
    return out


def plot_stability(ms: ModeSet, path: str | Path) -> Path:
    """Stability diagram: the significant peaks of the first quarter, half, three quarters
    and the whole record (``metadata["stability"]``, :func:`.stability.record_stability`)
    against frequency, each identified mode a red line with its 95 % frequency interval
    shaded.  A mode is stable when its column of peaks lines up at every record length."""
    st = ms.metadata.get("stability")
    if not isinstance(st, dict) or not st.get("peaks_hz"):
        raise ValueError("the mode set has no stability search (metadata 'stability')")
    plt = _plt()
    fig, ax = plt.subplots(figsize=(10, 4.5), dpi=110)
    sf = ms.frequency_std_hz()
    for i, f in enumerate(ms.frequencies_hz):
        ax.axvline(f, color="tab:red", lw=0.6, alpha=0.6)
        if np.isfinite(sf[i]):
            ax.axvspan(f - Z95 * sf[i], f + Z95 * sf[i], color="tab:red", alpha=0.15, lw=0)
    for frac, n, peaks in zip(st["fractions"], st["n_frames"], st["peaks_hz"], strict=True):
        p = np.asarray(peaks, np.float64)
        one_bin = ms.fps / n
        near = np.array([np.min(np.abs(ms.frequencies_hz - x)) <= max(one_bin, 1e-12)
                         if len(ms) else False for x in p], bool)
        ax.plot(p[near], np.full(near.sum(), frac), "o", color="tab:blue", ms=4)
        ax.plot(p[~near], np.full((~near).sum(), frac), "x", color="0.5", ms=4)
    ax.plot([], [], "o", color="tab:blue", label="peak at an identified mode")
    ax.plot([], [], "x", color="0.5", label="other significant peak")
    ax.plot([], [], "-", color="tab:red", label="identified mode (95 % interval)")
    ax.set_yticks(st["fractions"])
    ax.set_yticklabels([f"{f:g} ({n / ms.fps:.3g} s)"
                        for f, n in zip(st["fractions"], st["n_frames"], strict=True)])
    ax.set_ylim(0, 1.1)
    ax.set_xlim(float(ms.metadata.get("band_hz", [0, 0])[0]), _modes_xmax(ms))
    ax.set_xlabel("frequency (Hz)")
    ax.set_ylabel("leading part of the record")
    ax.set_title("Stability: peaks found in the leading part of the record")
    ax.grid(True, alpha=0.2)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    out = Path(path)
    from ..io.files import atomic_file

    with atomic_file(out) as fh:
        fig.savefig(fh, format=out.suffix[1:] or "png")
    plt.close(fig)
    return out


def plot_stabilization(ms: ModeSet, path: str | Path) -> Path:
    """Stabilisation diagram of a pole-based identification (``metadata["poles"]["diagram"]``):
    every pole of the model-order scan at its frequency (x) and order (y), stable poles (their
    frequency, damping and shape repeat from the previous order) in blue, the members of a
    cluster in black, each identified mode a red line with its 95 % frequency interval shaded,
    and the clusters rejected as products or otherwise a dashed grey line."""
    poles = (ms.metadata.get("poles") or {}).get("diagram")
    if not isinstance(poles, dict) or "poles" not in poles:
        raise ValueError("the mode set has no stabilisation diagram (metadata 'poles')")
    plt = _plt()
    fig, ax = plt.subplots(figsize=(10, 5), dpi=110)
    rows = np.asarray(poles["poles"], dtype=np.float64).reshape(-1, 5)
    if rows.size:
        order, f, stable, cl = rows[:, 0], rows[:, 1], rows[:, 3] > 0, rows[:, 4]
        ax.plot(f[~stable], order[~stable], ".", color="0.75", ms=2.5, label="pole")
        ax.plot(f[stable & (cl < 0)], order[stable & (cl < 0)], "o", mfc="none",
                color="tab:blue", ms=3.5, mew=0.7, label="stable pole")
        ax.plot(f[cl >= 0], order[cl >= 0], "o", color="k", ms=2.5, label="in a cluster")
    sf = ms.frequency_std_hz()
    for i, fi in enumerate(ms.frequencies_hz):
        ax.axvline(fi, color="tab:red", lw=0.7, alpha=0.7)
        if np.isfinite(sf[i]):
            ax.axvspan(fi - Z95 * sf[i], fi + Z95 * sf[i], color="tab:red", alpha=0.15, lw=0)
    for r in ms.metadata.get("rejected", []):
        ax.axvline(r["frequency_hz"], color="0.4", lw=0.7, ls="--")
    ax.plot([], [], "-", color="tab:red", label="identified mode (95 % interval)")
    if ms.metadata.get("rejected"):
        ax.plot([], [], "--", color="0.4", label="rejected (product, shake, ...)")
    band = ms.metadata.get("band_hz", [0, 0])
    ax.set_xlim(float(band[0]), _modes_xmax(ms))
    ax.set_xlabel("frequency (Hz)")
    ax.set_ylabel("model order")
    used = ms.identifier["used"].upper() if ms.identifier["used"] == "era" else "pLSCF"
    ax.set_title(f"Stabilisation diagram ({used}): {len(ms)} modes")
    ax.grid(True, alpha=0.2)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    out = Path(path)
    from ..io.files import atomic_file

    with atomic_file(out) as fh:
        fig.savefig(fh, format=out.suffix[1:] or "png")
    plt.close(fig)
    return out


def plot_modes(ms: ModeSet, directory: str | Path) -> list[Path]:
    """``spectrum.png``, ``mode_XX.png`` for every mode and, where the modes carry
    intervals (line fit), ``uncertainty.png``, with a stability search ``stability.png``,
    and for a pole-based identification ``stabilization.png``, into ``directory``."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    paths = [plot_spectrum(ms, d / "spectrum.png")]
    if len(ms) and np.isfinite(ms.damping_interval()[0]).any():
        paths.append(plot_uncertainty(ms, d / "uncertainty.png"))
    if isinstance(ms.metadata.get("stability"), dict):
        paths.append(plot_stability(ms, d / "stability.png"))
    if isinstance((ms.metadata.get("poles") or {}).get("diagram"), dict):
        paths.append(plot_stabilization(ms, d / "stabilization.png"))
    paths += [plot_mode(ms, i, d / f"mode_{i:02d}.png") for i in range(len(ms))]
    return paths
