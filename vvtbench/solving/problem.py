"""The inverse problem a solver receives, and the estimate it returns.

An :class:`InverseProblem` is plain data, built by :func:`vvtbench.observe.observe`: an
*inference* model (mesh, voxel map, Poisson's ratio, fixed nodes -- a separate object from the
simulation mesh: the paper simulates on 10x10x10 and infers on 8x8x8), the observed modes
(image-space displacements ``gamma`` of the visible inference-mesh vertices and eigenvalues
``lambda = (2 pi f)^2``), the observation operator ``P`` (camera Jacobians of the visible
vertices acting on the free DOFs) and priors. It holds no truth: the material, the true 3-D
modes and everything derived from them live in :class:`vvtbench.observe.Truth`, which only the
evaluator (and a reference solver that declares ``uses_truth``) receives.

Layouts
-------
* ``gamma[i]`` is ``[x0, y0, x1, y1, ...]`` in pixels, one (x, y) pair per entry of
  ``visible_nodes`` (membranes too: the image motion of the out-of-plane DOF).
* ``P`` is ``(2 * n_visible, n_free)``: ``P @ u`` is the image motion of a free-DOF vector u.
* Material vectors ``w`` (Young's modulus / tension) and ``v`` (density / areal density) are
  per *parameter* (active voxel, ``voxel_map.active`` order); ``voxel_map.to_grid`` makes grids.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp

from ..fem.assembly import ParametricModel
from ..fem.mesh import Mesh
from ..fem.voxels import VoxelGrid, VoxelMap

__all__ = ["InverseProblem", "Estimate"]


@dataclass
class InverseProblem:
    """Observed modes + inference model + priors (never the truth).

    Attributes
    ----------
    model : inference :class:`ParametricModel` (mesh, voxel map, nu, fixed nodes).
    gamma : (k, 2 * n_visible) observed image-space modes, each of unit length.
    eigenvalues : (k,) observed ``(2 pi f)^2`` in (rad/s)^2.
    P : (2 * n_visible, n_free) sparse observation operator (pixels per metre).
    visible_nodes : (n_visible,) inference-mesh node indices observed, in ``gamma`` order.
    w0, v0 : initial (uniform) stiffness and density.
    w_mean : the prior mean of w (the anchor that fixes the w/v scale ambiguity).
    kind : "solid" or "membrane".
    meta : provenance of the observation (camera, geometry scale, inference grid, source
        of the modes, extracted frequencies); never the scene or the truth.
    mode_snr : (k,) spectral signal-to-noise ratio of each observed mode (power at its peak
        over the motion spectrum's noise floor, :meth:`ModeSet.line_snr`; about
        ``1 / (1 + snr)`` of a shape's energy is noise), ``nan`` where unknown; ``None`` for
        noise-free (true) modes and for problems written before it existed.
    """

    model: ParametricModel
    gamma: np.ndarray
    eigenvalues: np.ndarray
    P: sp.csr_matrix
    visible_nodes: np.ndarray
    w0: float = 9000.0
    v0: float = 1270.0
    w_mean: float = 9000.0
    kind: str = "solid"
    meta: dict[str, Any] = field(default_factory=dict)
    mode_snr: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.gamma = np.atleast_2d(np.asarray(self.gamma, dtype=float))
        self.eigenvalues = np.asarray(self.eigenvalues, dtype=float).ravel()
        if self.mode_snr is not None:
            self.mode_snr = np.asarray(self.mode_snr, dtype=float).ravel()
            if self.mode_snr.shape != self.eigenvalues.shape:
                raise ValueError(f"mode_snr needs shape ({len(self.eigenvalues)},) (one per "
                                 f"mode), got {self.mode_snr.shape}")
            if np.any(self.mode_snr <= 0):
                raise ValueError("mode_snr must be positive (or nan where unknown)")
        self.P = sp.csr_matrix(self.P)
        self.visible_nodes = np.asarray(self.visible_nodes, dtype=np.int64)
        k = len(self.eigenvalues)
        if self.gamma.shape != (k, self.P.shape[0]):
            raise ValueError(
                f"gamma needs shape ({k}, {self.P.shape[0]}) (modes x 2*visible), "
                f"got {self.gamma.shape}"
            )
        if self.P.shape[1] != self.model.n_free:
            raise ValueError(f"P has {self.P.shape[1]} columns, model has {self.model.n_free} "
                             "free DOFs")

    @property
    def mesh(self) -> Mesh:
        return self.model.mesh

    @property
    def voxel_map(self) -> VoxelMap:
        return self.model.voxel_map

    @property
    def n_modes(self) -> int:
        return len(self.eigenvalues)

    @property
    def n_params(self) -> int:
        return self.model.n_params

    @property
    def frequencies_hz(self) -> np.ndarray:
        return np.sqrt(np.clip(self.eigenvalues, 0, None)) / (2 * np.pi)

    def to_grid(self, values: np.ndarray, fill: float = np.nan) -> np.ndarray:
        return self.voxel_map.to_grid(values, fill)

    def select_modes(self, index) -> InverseProblem:
        """A copy observing only the modes ``index`` (an int n keeps the first n)."""
        idx = np.arange(index) if np.isscalar(index) else np.asarray(index)
        if len(idx) == 0 or idx.max() >= self.n_modes:
            raise ValueError(f"mode selection {index!r} out of range; {self.n_modes} modes")
        return replace(self, gamma=self.gamma[idx], eigenvalues=self.eigenvalues[idx],
                       meta=dict(self.meta),
                       mode_snr=None if self.mode_snr is None else self.mode_snr[idx])

    def save(self, folder: str | Path) -> None:
        """``problem.npz`` + ``problem.json`` in ``folder`` (plain arrays and JSON, no pickle;
        :meth:`load` rebuilds the same problem)."""
        from ..io.files import write_json, write_npz

        folder = Path(folder)
        m, mesh = self.model, self.model.mesh
        arrays = {"points": mesh.points, "cells": mesh.cells, "surface": mesh.surface,
                  "fixed_nodes": m.fixed_nodes, "nu": np.asarray(m.nu, dtype=float),
                  "gamma": self.gamma, "eigenvalues": self.eigenvalues,
                  "visible_nodes": self.visible_nodes, "P_data": self.P.data,
                  "P_indices": self.P.indices, "P_indptr": self.P.indptr}
        if self.mode_snr is not None:
            arrays["mode_snr"] = self.mode_snr
        write_npz(folder / "problem.npz", arrays)
        write_json(folder / "problem.json", {
            "element": mesh.element, "grid": m.voxel_map.grid.to_dict(),
            "P_shape": list(self.P.shape), "w0": self.w0, "v0": self.v0,
            "w_mean": self.w_mean, "kind": self.kind, "meta": self.meta})

    @classmethod
    def load(cls, folder: str | Path) -> InverseProblem:
        folder = Path(folder)
        doc = json.loads((folder / "problem.json").read_text())
        with np.load(folder / "problem.npz", allow_pickle=False) as z:
            a = {k: z[k] for k in z.files}
        mesh = Mesh(a["points"], a["cells"], doc["element"], {}, a["surface"])
        g = doc["grid"]
        grid = VoxelGrid(tuple(g["origin"]), tuple(g["size"]), tuple(g["shape"]))
        nu = a["nu"].item() if a["nu"].ndim == 0 else a["nu"]
        model = ParametricModel(mesh, VoxelMap.from_grid(mesh, grid), nu=nu,
                                fixed_nodes=a["fixed_nodes"])
        P = sp.csr_matrix((a["P_data"], a["P_indices"], a["P_indptr"]),
                          shape=tuple(doc["P_shape"]))
        return cls(model=model, gamma=a["gamma"], eigenvalues=a["eigenvalues"], P=P,
                   visible_nodes=a["visible_nodes"], w0=doc["w0"], v0=doc["v0"],
                   w_mean=doc["w_mean"], kind=doc["kind"], meta=doc["meta"],
                   mode_snr=a.get("mode_snr"))


@dataclass
class Estimate:
    """A solver's answer.

    Attributes
    ----------
    w, v : (n_params,) estimated stiffness and density per active voxel.
    history : one dict per iteration (free-form; iterative solvers record at least
        ``iteration``, ``time_s`` and, when the problem carries truth, ``nc_w``/``nc_v``).
    runtime_s : wall time of ``solve``.
    config : the solver's configuration (a plain dict).
    solver, version : solver name and version.
    converged : whether the solver's own stopping rule was met.
    extra : optional arrays (e.g. the optimized 3-D modes ``U`` or eigenvalues); a solver
        that states its uncertainty puts per-parameter standard deviations in ``w_std`` and
        ``v_std`` (saved with the estimate and scored by the interval coverage).
    """

    w: np.ndarray
    v: np.ndarray
    history: list[dict] = field(default_factory=list)
    runtime_s: float = 0.0
    config: dict = field(default_factory=dict)
    solver: str = ""
    version: str = ""
    converged: bool | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.w = np.asarray(self.w, dtype=float).ravel()
        self.v = np.asarray(self.v, dtype=float).ravel()
        if self.w.shape != self.v.shape:
            raise ValueError(f"w and v differ in shape: {self.w.shape} vs {self.v.shape}")

    def save(self, folder: str | Path, problem: InverseProblem,
             wall_s: float | None = None) -> None:
        """``estimate.npz`` (per-parameter ``w_params``, ``v_params``; grids ``w``, ``v``;
        ``active`` voxels) and ``estimate.json`` (solver, version, config, runtimes, history,
        scalar extras) in ``folder``: the one estimate writer of ``run`` and ``solve``."""
        from ..io.files import write_json, write_npz

        folder = Path(folder)
        arrays = {"w_params": self.w, "v_params": self.v,
                  "active": problem.voxel_map.active}
        if self.w.shape == (problem.n_params,):
            arrays.update(w=problem.to_grid(self.w), v=problem.to_grid(self.v))
            for name in ("w_std", "v_std"):
                std = self.std(name)
                if std is not None:
                    arrays[f"{name}_params"] = std
                    arrays[name] = problem.to_grid(std)
        write_npz(folder / "estimate.npz", arrays)
        write_json(folder / "estimate.json", {
            "solver": self.solver, "solver_version": self.version, "config": self.config,
            "runtime_s": self.runtime_s or wall_s, "wall_s": wall_s,
            "converged": self.converged, "iterations": len(self.history),
            "history": self.history, "extra": self.extra_scalars()})

    @classmethod
    def load(cls, folder: str | Path, problem: InverseProblem | None = None) -> Estimate:
        """The estimate :meth:`save` wrote into ``folder`` (arrays without pickle; the
        per-parameter fields, stated standard deviations and scalar extras)."""
        folder = Path(folder)
        doc = json.loads((folder / "estimate.json").read_text())
        if not isinstance(doc, dict):
            raise ValueError(f"{folder / 'estimate.json'}: not a JSON object")
        with np.load(folder / "estimate.npz", allow_pickle=False) as z:
            w, v = z["w_params"], z["v_params"]
            extra = {f"{n}_std": z[f"{n}_std_params"] for n in ("w", "v")
                     if f"{n}_std_params" in z.files}
        scalars = doc.get("extra") if isinstance(doc.get("extra"), dict) else {}
        history = doc.get("history") if isinstance(doc.get("history"), list) else []
        config = doc.get("config") if isinstance(doc.get("config"), dict) else {}
        runtime = doc.get("runtime_s")
        return cls(w=w, v=v, history=history,
                   runtime_s=float(runtime) if isinstance(runtime, (int, float)) else 0.0,
                   config=config, solver=str(doc.get("solver") or ""),
                   version=str(doc.get("solver_version") or ""),
                   converged=doc.get("converged") if isinstance(doc.get("converged"), bool)
                   else None, extra={**scalars, **extra})

    def std(self, name: str) -> np.ndarray | None:
        """The stated per-parameter standard deviation ``extra[name]`` (``"w_std"`` or
        ``"v_std"``) as a float array of the estimate's shape, or None when not given."""
        value = self.extra.get(name)
        if value is None:
            return None
        value = np.asarray(value, dtype=float).ravel()
        if value.shape != self.w.shape:
            raise ValueError(f"extra[{name!r}] has shape {value.shape}, the estimate "
                             f"{self.w.shape}")
        return value

    def extra_scalars(self) -> dict[str, Any]:
        """The entries of ``extra`` that are not arrays (written to estimate.json)."""
        return {k: x for k, x in self.extra.items() if not isinstance(x, np.ndarray)}
