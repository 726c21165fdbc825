"""Compare identified image-space modes with a rendered sample's ground truth.

The truth of a sample (docs/dataset.md) holds the eigenfrequencies of the simulation model
(``truth.json -> modes.frequencies_hz``) and the true image-space modes as dense fields
(``truth.zarr: image/modes``, ``(m, H, W, 2)`` in ``(u, v)`` = (right, down), NaN on the
background).  Only the modes the excitation actually drives appear in the video, and modes
closer than the frequency resolution cannot be told apart, so the comparison is:

* **frequencies**: every identified peak should lie within one FFT bin (``fps / T``) of a
  true eigenfrequency;
* **shapes**: for each true mode, the identified mode nearest in frequency (within one bin)
  is compared by MAC on the foreground pixels (eroded by ``erode`` px: silhouettes mix
  object and background motion); for *clusters* of true modes closer than
  ``cluster_bins`` bins, the subspace MAC (fraction of the identified shape's energy in the
  span of the cluster's true shapes) is reported too;
* **well-separated** modes: no other true mode within ``separation_bins`` bins (the Hann
  main lobe is 2 bins wide on each side).  The lowest ``n_lowest`` of them must be found
  with MAC >= ``mac_min``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.ndimage import binary_erosion

from .modeset import ModeSet

__all__ = ["ModeCheck", "compare_to_truth", "format_table"]


@dataclass
class ModeCheck:
    """Result of :func:`compare_to_truth`.

    Attributes
    ----------
    rows : list of dict
        One per true mode up to the analysed band: ``index``, ``f_true``, ``cluster``
        (indices of true modes within ``cluster_bins``), ``separated``, ``f_found`` (or
        None), ``error_bins``, ``mac``, ``mac_subspace``, ``amplitude_px``.
    unmatched : list of float
        Identified frequencies with no true eigenfrequency within one bin.
    bin_hz : float
        Frequency resolution ``fps / T``.
    lowest_separated : list of dict
        The rows of the lowest ``n_lowest`` well-separated true modes.
    ok_frequencies, ok_shapes : bool
        All identified peaks within one bin of a true mode; the lowest well-separated modes
        all found with MAC >= ``mac_min``.
    """

    rows: list[dict[str, Any]]
    unmatched: list[float]
    bin_hz: float
    lowest_separated: list[dict[str, Any]]
    ok_frequencies: bool
    ok_shapes: bool
    params: dict[str, Any] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        """Both checks passed."""
        return self.ok_frequencies and self.ok_shapes


def _mac(a: NDArray, b: NDArray) -> float:
    den = float(a @ a) * float(b @ b)
    return float((a @ b) ** 2 / den) if den > 0 else 0.0


def compare_to_truth(
    ms: ModeSet,
    true_frequencies: ArrayLike,
    true_modes: ArrayLike,
    *,
    erode: int = 2,
    cluster_bins: float = 1.0,
    separation_bins: float = 3.0,
    n_lowest: int = 3,
    mac_min: float = 0.9,
    fmax: float | None = None,
) -> ModeCheck:
    """Match identified modes to true eigenfrequencies and image-space modes.

    Parameters
    ----------
    ms : ModeSet
        Identified modes (shapes ``(k, H, W, 2)``, ``[..., 0]`` = right, ``[..., 1]`` = down).
    true_frequencies : array_like
        ``(m,)`` eigenfrequencies (Hz).
    true_modes : array_like
        ``(m, H, W, 2)`` true image-space modes, NaN on the background.
    erode : int, default 2
        Foreground erosion (px) before computing MACs.
    cluster_bins, separation_bins : float
        See the module notes (in bins of ``fps / T``).
    n_lowest : int, default 3
        Number of lowest well-separated modes that must reach ``mac_min``.
    mac_min : float, default 0.9
    fmax : float, optional
        Highest frequency considered (default: the analysed band's upper limit).

    Returns
    -------
    ModeCheck
    """
    f_true = np.asarray(true_frequencies, dtype=np.float64)
    modes = np.asarray(true_modes)
    if modes.ndim != 4 or modes.shape[0] != f_true.size or modes.shape[-1] != 2:
        raise ValueError(
            f"true_modes must be (m, H, W, 2) with m = {f_true.size}, got {modes.shape}"
        )
    if len(ms) and ms.shapes.shape[1:] != modes.shape[1:]:
        raise ValueError(f"shape mismatch: modes {ms.shapes.shape[1:]} vs truth {modes.shape[1:]}")
    df = ms.fps / ms.n_frames
    if fmax is None:
        band = ms.metadata.get("band_hz")
        fmax = float(band[1]) if band else ms.fps / 2
    fg = np.all(np.isfinite(modes[0]), axis=-1)
    mask = binary_erosion(fg, iterations=erode) if erode > 0 else fg
    truth = np.nan_to_num(modes[:, mask].reshape(f_true.size, -1))  # (m, 2 * n_px)
    found = ms.shapes[:, mask].reshape(len(ms), -1).astype(np.float64)
    f_found = ms.frequencies_hz

    rows = []
    for i in np.flatnonzero(f_true <= fmax):
        cluster = np.flatnonzero(np.abs(f_true - f_true[i]) <= cluster_bins * df)
        others = np.abs(np.delete(f_true, i) - f_true[i])
        separated = bool(others.size == 0 or others.min() > separation_bins * df)
        row: dict[str, Any] = {
            "index": int(i),
            "f_true": float(f_true[i]),
            "cluster": cluster.tolist(),
            "separated": separated,
            "f_found": None,
            "error_bins": None,
            "mac": None,
            "mac_subspace": None,
            "amplitude_px": None,
        }
        if len(ms):
            j = int(np.argmin(np.abs(f_found - f_true[i])))
            err = (f_found[j] - f_true[i]) / df
            if abs(err) <= 1.0:
                a = found[j]
                q, _ = np.linalg.qr(truth[cluster].T)
                row.update(
                    f_found=float(f_found[j]),
                    error_bins=float(err),
                    mac=_mac(a, truth[i]),
                    mac_subspace=float(np.sum((q.T @ a) ** 2) / (a @ a)) if a @ a > 0 else 0.0,
                    amplitude_px=float(ms.amplitudes_px[j]),
                )
        rows.append(row)
    unmatched = [float(f) for f in f_found if np.min(np.abs(f_true - f)) > df]
    sep = [r for r in rows if r["separated"]][:n_lowest]
    ok_shapes = len(sep) == n_lowest and all(
        r["mac"] is not None and r["mac"] >= mac_min for r in sep
    )
    return ModeCheck(
        rows=rows,
        unmatched=unmatched,
        bin_hz=float(df),
        lowest_separated=sep,
        ok_frequencies=not unmatched and len(ms) > 0,
        ok_shapes=ok_shapes,
        params={
            "erode": erode,
            "cluster_bins": cluster_bins,
            "separation_bins": separation_bins,
            "n_lowest": n_lowest,
            "mac_min": mac_min,
            "fmax": fmax,
            "n_foreground_px": int(mask.sum()),
        },
    )


def format_table(check: ModeCheck) -> str:
    """Markdown table of :func:`compare_to_truth` (one row per true mode) and a verdict."""

    def fmt(v: Any, spec: str) -> str:
        return "–" if v is None else format(v, spec)

    lines = [
        "| # | f true (Hz) | cluster | separated | f found (Hz) | error (bins) | MAC | "
        "subspace MAC | amplitude (px) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in check.rows:
        cl = "" if len(r["cluster"]) == 1 else ",".join(str(c) for c in r["cluster"])
        lines.append(
            f"| {r['index']} | {r['f_true']:.3f} | {cl} | {'yes' if r['separated'] else ''} | "
            f"{fmt(r['f_found'], '.3f')} | {fmt(r['error_bins'], '+.2f')} | "
            f"{fmt(r['mac'], '.3f')} | {fmt(r['mac_subspace'], '.3f')} | "
            f"{fmt(r['amplitude_px'], '.3g')} |"
        )
    sep = ", ".join(
        f"{r['f_true']:.2f} Hz: " + ("not found" if r["mac"] is None else f"MAC {r['mac']:.3f}")
        for r in check.lowest_separated
    )
    p = check.params
    lines += [
        "",
        f"bin = {check.bin_hz:.4f} Hz; foreground pixels (eroded {p['erode']} px): "
        f"{p['n_foreground_px']}",
        f"identified peaks not within one bin of a true eigenfrequency: "
        f"{[round(f, 3) for f in check.unmatched]} -> "
        f"{'PASS' if check.ok_frequencies else 'FAIL'}",
        f"lowest {p['n_lowest']} well-separated modes (> {p['separation_bins']:g} bins from "
        f"any other): {sep} -> MAC >= {p['mac_min']:g}: "
        f"{'PASS' if check.ok_shapes else 'FAIL'}",
    ]
    return "\n".join(lines)
