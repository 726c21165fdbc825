"""Truth on the inference grid: per-voxel averages of the simulation's material, and the
homogenised truth chosen by physics. Definitions: docs/metrics.md, "Truth on the inference
grid".

* :func:`voxel_means` -- the arithmetic (the benchmark's truth of record: ``Truth.w``),
  harmonic and geometric means of the simulation's per-element material over each voxel,
  weighted by the exact overlap volume of element and voxel.
* :func:`homogenise` -- the per-voxel stiffness and density whose inference model best
  reproduces the simulation's modes: minimize the mode misfit D (:mod:`.ceiling`) against the
  true modes at every free DOF of the inference mesh (``Truth.modes_3d``, the simulation's
  modes sampled at the inference nodes) and their exact eigenvalues, by L-BFGS-B on log w,
  log v from each of the voxel means, keeping the lowest misfit.

A sub-voxel void or stiff inclusion is not its arithmetic mean: a voxel half void has about
half the stiffness of the arithmetic mean in bending and far less in shear. The homogenised
field is the one the inference model can reproduce the object's vibration with; it also
absorbs the coarser mesh's own discretisation error (an 8^3 hex8 mesh is stiffer than the
10^3 one), which shows as false contrast on a cube with no defect.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .ceiling import Misfit, ModeData

__all__ = ["voxel_means", "full_field_data", "homogenise", "Homogenised"]


def voxel_means(sample: Any, problem) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """``{"arithmetic" | "harmonic" | "geometric": (w, v)}`` per active voxel of ``problem``.

    ``sample`` is a sample folder or an open :class:`~vvtbench.samples.reader.Sample` (the
    simulation mesh and its per-element ``material/stiffness``, ``material/density``).
    The overlap volumes are :func:`vvtbench.fem.voxels.overlap_matrix`'s, with the problem's
    geometry scale, as ``observe`` computes the arithmetic truth.
    """
    from ..fem.mesh import Mesh
    from ..fem.voxels import overlap_matrix
    from ..samples.reader import open_sample

    s = open_sample(sample) if not hasattr(sample, "require") else sample
    mesh = Mesh(np.asarray(s.require("mesh/points")), np.asarray(s.require("mesh/cells")),
                s.info["mesh"]["element"], {}, np.asarray(s.require("mesh/surface")))
    scale = np.asarray(problem.meta.get("geometry_scale", [1.0, 1.0, 1.0]), dtype=float)
    vmap = problem.model.voxel_map
    overlap = overlap_matrix(mesh, vmap.grid, scale=scale).tocsr()[vmap.active]
    vol = np.asarray(overlap.sum(axis=1)).ravel()
    if np.any(vol <= 0):
        raise ValueError("an active voxel holds no simulation element; voxel means need the "
                         "inference grid inside the body")
    out: dict[str, list[np.ndarray]] = {"arithmetic": [], "harmonic": [], "geometric": []}
    for name in ("material/stiffness", "material/density"):
        x = np.asarray(s.require(name), dtype=float)
        out["arithmetic"].append(overlap @ x / vol)
        out["harmonic"].append(vol / (overlap @ (1.0 / x)))
        out["geometric"].append(np.exp(overlap @ np.log(x) / vol))
    return {k: (val[0], val[1]) for k, val in out.items()}


def full_field_data(truth, label: str = "every DOF") -> ModeData:
    """The true modes at every free DOF of the inference mesh and their exact eigenvalues."""
    U = np.asarray(truth.modes_3d, dtype=float)
    return ModeData((U / np.linalg.norm(U, axis=0)).T, truth.eigenvalues, None, label)


@dataclass
class Homogenised:
    """The homogenised field and how it was found."""

    w: np.ndarray
    v: np.ndarray
    misfit: float
    start: str
    misfits: dict[str, float] = field(default_factory=dict)  # per start: start, end
    history: list = field(default_factory=list)


def homogenise(problem, truth, means: dict[str, tuple[np.ndarray, np.ndarray]],
               iters: int = 150, misfit: Misfit | None = None, log=None) -> Homogenised:
    """Minimize the full-field mode misfit from each voxel mean; keep the lowest.

    Parameters
    ----------
    problem, truth : from ``observe`` (true observation); ``truth.modes_3d`` are the data.
    means : :func:`voxel_means`' output (the starts).
    iters : L-BFGS-B iterations per start.
    misfit : a :class:`Misfit` on the full-field data (default: made here).

    Returns
    -------
    Homogenised
        ``w``, ``v`` scaled so that mean(w) equals the arithmetic mean's (the modes do not
        change under a common scale of w and v).
    """
    from scipy.optimize import minimize

    mf = misfit if misfit is not None else Misfit(problem.model, full_field_data(truth))
    m = problem.n_params
    best = None
    misfits: dict[str, float] = {}
    history: list = []
    for name, (w0, v0) in means.items():
        theta0 = np.concatenate([np.log(w0), np.log(v0)])
        trace: list[float] = []

        def f(th, trace=trace):
            D, g, _ = mf(th)
            trace.append(D)
            return D, g

        D0 = mf.value(theta0)
        out = minimize(f, theta0, jac=True, method="L-BFGS-B",
                       options={"maxiter": iters, "maxcor": 20})
        D1 = mf.value(out.x)
        misfits[f"{name}:start"] = float(D0)
        misfits[f"{name}:end"] = float(D1)
        rec = {"start": name, "D0": float(D0), "D": float(D1), "iterations": int(out.nit),
               "evaluations": len(trace), "message": str(out.message),
               "trace": [float(x) for x in trace[:: max(1, len(trace) // 50)]]}
        history.append(rec)
        if log is not None:
            log(rec)
        if best is None or D1 < best[0]:
            best = (D1, out.x, name)
    D, theta, name = best
    w, v = np.exp(theta[:m]), np.exp(theta[m:])
    c = np.mean(means["arithmetic"][0]) / np.mean(w)
    return Homogenised(w=w * c, v=v * c, misfit=float(D), start=name, misfits=misfits,
                       history=history)
