"""Truth on the inference grid: per-voxel averages of the simulation's material, and the
homogenised truth chosen by physics. Definitions: docs/metrics.md, "Truth on the inference
grid".

* :func:`voxel_means` -- the arithmetic (the benchmark's truth of record: ``Truth.w``),
  harmonic and geometric means of the simulation's per-element material over each voxel,
  weighted by the exact overlap volume of element and voxel.
* :func:`homogenise` -- the per-voxel stiffness and density whose inference model reproduces
  the simulation's modes as well as the inference mesh can: the field closest to the best
  voxel mean whose mode misfit D (:mod:`.ceiling`) against the true modes at every free DOF
  of the inference mesh (``Truth.modes_3d``, the simulation's modes sampled at the inference
  nodes) and their exact eigenvalues is at most the mesh's own discretisation floor.

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
    misfit: float                 # D_full of (w, v)
    anchor: str                   # the voxel mean it is closest to
    feasible: bool                # misfit <= the floor it was asked for
    distance: float               # mean squared log distance to the anchor / 2
    history: list = field(default_factory=list)
    evaluations: int = 0
    record: Any = None            # the search's Record (every evaluated field)


def homogenise(misfit: Misfit, means: dict[str, tuple[np.ndarray, np.ndarray]],
               floor: float, outer: int = 8, inner: int = 25, bounds=None,
               scores: dict | None = None, log=None) -> Homogenised:
    """The field closest to a voxel mean whose modes reproduce the data within ``floor``.

    The anchor is the voxel mean (of ``means``) with the lowest misfit. The homogenised field
    minimises the mean squared log distance to it, |theta - theta_anchor|^2 / (2 n), subject
    to D_full(theta) <= ``floor`` (augmented Lagrangian, :func:`.ceiling.constrained_minimum`,
    ``outer`` x ``inner`` L-BFGS-B iterations, started at the anchor). A minimum-misfit fit
    without the distance has no end point: its misfit keeps falling by fitting the
    representation error while the field drifts away from any average (on cube_defects test
    00000, 250 L-BFGS iterations from the geometric mean: D 0.0265 -> 0.0005, NC w with the
    arithmetic mean 0.93 -> 0.86, still falling). When no evaluated field reaches ``floor``
    the lowest misfit reached is returned (``feasible = False``).

    Parameters
    ----------
    misfit : :class:`.ceiling.Misfit` on the full-field data (:func:`full_field_data`).
    means : :func:`voxel_means`' output.
    floor : the misfit to reach: the inference mesh's own, D of the exact material on the same
        body without defects (the discretisation floor).
    scores : extra functions of theta recorded for every evaluated field (e.g. NC).

    Returns
    -------
    Homogenised
        ``w``, ``v`` scaled so that mean(w) equals the arithmetic mean's (the modes do not
        change under a common scale of w and v).
    """
    from .ceiling import Record, constrained_minimum, distance_objective

    m = len(next(iter(means.values()))[0])
    D0 = {k: misfit.value(np.concatenate([np.log(w), np.log(v)])) for k, (w, v) in
          means.items()}
    name = min(D0, key=D0.get)
    anchor = np.concatenate([np.log(means[name][0]), np.log(means[name][1])])
    rec = Record(scores=scores)
    history: list = []
    n0 = misfit.n_eval
    if D0[name] <= floor:  # the mean already reproduces the modes
        best, feasible = anchor, True
    else:
        res = constrained_minimum(misfit, distance_objective(anchor), anchor, floor,
                                  start=name, record=rec, outer=outer, inner=inner,
                                  bounds=bounds, log=log)
        history = res["history"]
        feasible = "eps" in rec.best
        best = rec.best["eps"][1] if feasible else rec.lowest[1]
    w, v = np.exp(best[:m]), np.exp(best[m:])
    c = float(np.mean(means["arithmetic"][0]) / np.mean(w))
    d = best - anchor
    return Homogenised(w=w * c, v=v * c, misfit=float(misfit.value(best)), anchor=name,
                       feasible=feasible, distance=float(d @ d) / (2 * len(d)),
                       history=history, evaluations=misfit.n_eval - n0, record=rec)
