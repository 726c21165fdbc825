"""PNG plots of a :class:`ModeSet` (matplotlib, Agg backend)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .modeset import ModeSet

__all__ = ["plot_mode", "plot_modes", "plot_spectrum"]


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def plot_spectrum(ms: ModeSet, path: str | Path) -> Path:
    """Motion power spectrum (log scale) with picked peaks marked and labelled.

    Kept modes are red triangles labelled ``#i f Hz``; rejected peaks (camera shake,
    distortion products, incoherent; ``metadata["rejected"]``) are grey crosses.
    """
    plt = _plt()
    fig, ax = plt.subplots(figsize=(9, 4), dpi=110)
    if ms.power.size:
        ax.semilogy(ms.freqs_hz[1:], np.maximum(ms.power[1:], 1e-300), lw=0.8, color="k")
        for i, (k, f) in enumerate(zip(ms.peak_bins, ms.frequencies_hz, strict=True)):
            if 0 <= k < ms.power.size:
                ax.plot(ms.freqs_hz[k], ms.power[k], "v", color="tab:red", ms=7)
                ax.annotate(
                    f"#{i} {f:.2f} Hz",
                    (ms.freqs_hz[k], ms.power[k]),
                    textcoords="offset points",
                    xytext=(0, 8),
                    ha="center",
                    fontsize=7,
                    color="tab:red",
                )
        for r in ms.metadata.get("rejected", []):
            k = r.get("bin", -1)
            if 0 <= k < ms.power.size:
                ax.plot(ms.freqs_hz[k], ms.power[k], "x", color="0.5", ms=8)
        band = ms.metadata.get("band_hz")
        if band:
            ax.axvspan(band[0], band[1], color="tab:blue", alpha=0.05)
    ax.set_xlabel("frequency (Hz)")
    ax.set_ylabel("motion power (px$^2$, unnormalised DFT)")
    ax.set_title(f"Motion power spectrum: {len(ms)} modes, fps {ms.fps:g}, T = {ms.n_frames}")
    ax.grid(True, which="both", alpha=0.2)
    fig.tight_layout()
    out = Path(path)
    fig.savefig(out)
    plt.close(fig)
    return out


def plot_mode(ms: ModeSet, i: int, path: str | Path, max_arrows: int = 32) -> Path:
    """Mode ``i``: ``dx`` and ``dy`` images (shared symmetric colour scale) and a quiver."""
    plt = _plt()
    s = ms.shapes[i]
    H, W = s.shape[:2]
    vmax = float(np.max(np.abs(s))) or 1.0
    fig, axes = plt.subplots(1, 3, figsize=(12, 4), dpi=100)
    for ax, c, name in ((axes[0], 0, "dx"), (axes[1], 1, "dy")):
        im = ax.imshow(s[..., c], cmap="RdBu_r", vmin=-vmax, vmax=vmax)
        ax.set_title(name)
        ax.axis("off")
    fig.colorbar(im, ax=axes[:2], shrink=0.8)
    step = max(1, int(np.ceil(max(H, W) / max_arrows)))
    yy, xx = np.mgrid[step // 2 : H : step, step // 2 : W : step]
    ax = axes[2]
    ax.imshow(np.hypot(s[..., 0], s[..., 1]), cmap="gray_r")
    ax.quiver(xx, yy, s[yy, xx, 0], s[yy, xx, 1], color="tab:red", angles="xy", pivot="mid")
    ax.set_title("shape (arrows, image y down)")
    ax.axis("off")
    z = ms.damping[i]
    fig.suptitle(
        f"mode #{i}: {ms.frequencies_hz[i]:.3f} Hz, zeta = {z:.4f}, "
        f"amplitude {ms.amplitudes_px[i]:.3g} px"
        + ("  [camera shake]" if ms.camera_shake[i] else "")
    )
    out = Path(path)
    fig.savefig(out)
    plt.close(fig)
    return out


def plot_modes(ms: ModeSet, directory: str | Path) -> list[Path]:
    """``spectrum.png`` and ``mode_XX.png`` for every mode into ``directory``."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    paths = [plot_spectrum(ms, d / "spectrum.png")]
    paths += [plot_mode(ms, i, d / f"mode_{i:02d}.png") for i in range(len(ms))]
    return paths
