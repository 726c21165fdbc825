"""What the evaluator knows and a solver never sees: :class:`Truth`."""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["Truth"]


@dataclass
class Truth:
    """What the evaluator knows and a solver never sees.

    Attributes
    ----------
    w, v : (n_params,) true stiffness and density per active voxel of the problem's grid
        (volume-weighted mean over the voxel of the simulation's per-element material).
    modes_3d : (n_free, k) true 3-D modes on the inference mesh paired with the observed
        modes, scaled so that ``P @ modes_3d[:, i]`` is the unit-length true image mode.
    eigenvalues : (k,) exact eigenvalues of those true modes, (rad/s)^2.
    matched : (k,) index of the true mode paired with each observed mode.
    image_modes : (n_true, 2 n_visible) the true image-space modes at the visible vertices
        (unit length), and ``true_eigenvalues`` (n_true,) theirs.
    extraction_mac : (k,) MAC of each observed (extracted) mode with its pair; None for the
        true observation.
    meta : scene, sample, simulation mesh.
    """

    w: np.ndarray
    v: np.ndarray
    modes_3d: np.ndarray
    eigenvalues: np.ndarray
    matched: np.ndarray
    image_modes: np.ndarray
    true_eigenvalues: np.ndarray
    extraction_mac: np.ndarray | None = None
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def frequencies_hz(self) -> np.ndarray:
        return np.sqrt(np.clip(self.eigenvalues, 0, None)) / (2 * np.pi)

    def select_modes(self, index: Any) -> Truth:
        """The truth of ``problem.select_modes(index)``."""
        idx = np.arange(index) if np.isscalar(index) else np.asarray(index)
        mac = None if self.extraction_mac is None else self.extraction_mac[idx]
        return replace(self, modes_3d=self.modes_3d[:, idx], eigenvalues=self.eigenvalues[idx],
                       matched=self.matched[idx], extraction_mac=mac, meta=dict(self.meta))

    def save(self, folder: str | Path) -> None:
        """``truth.npz`` + ``truth.json`` in ``folder`` (no pickle)."""
        from ..io.files import write_json, write_npz

        folder = Path(folder)
        arrays = {k: getattr(self, k) for k in ("w", "v", "modes_3d", "eigenvalues", "matched",
                                                "image_modes", "true_eigenvalues")}
        if self.extraction_mac is not None:
            arrays["extraction_mac"] = self.extraction_mac
        write_npz(folder / "truth.npz", arrays)
        write_json(folder / "truth.json", {"meta": self.meta})

    @classmethod
    def load(cls, folder: str | Path) -> Truth:
        folder = Path(folder)
        with np.load(folder / "truth.npz", allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        meta = json.loads((folder / "truth.json").read_text())["meta"]
        return cls(**arrays, meta=meta)
