"""The inverse problem a solver receives, and the estimate it returns.

An :class:`InverseProblem` is plain data: an *inference* model (mesh, voxel map, Poisson's
ratio, fixed nodes -- a separate object from the simulation mesh: the paper simulates on
10x10x10 hex8 and infers on 8x8x8), the observed modes (image-space displacements ``gamma`` of
the visible inference-mesh vertices and eigenvalues ``lambda = (2 pi f)^2``), the observation
operator ``P`` (camera Jacobians of the visible vertices acting on the free DOFs), priors, and
optionally the truth (for metrics only; solvers must not read it).

Layouts
-------
* ``gamma[i]`` is ``[x0, y0, x1, y1, ...]`` in pixels, one (x, y) pair per entry of
  ``visible_nodes`` (membranes too: the image motion of the out-of-plane DOF).
* ``P`` is ``(2 * n_visible, n_free)``: ``P @ u`` is the image motion of a free-DOF vector u.
  For a perfect observation ``P @ modes_3d[:, i] == gamma[i]``.
* Material vectors ``w`` (Young's modulus / tension) and ``v`` (density / areal density) are
  per *parameter* (active voxel, ``voxel_map.active`` order); ``voxel_map.to_grid`` makes grids.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp

from .fem.assembly import ParametricModel
from .fem.elements import element_volumes
from .fem.mesh import Mesh, box_mesh
from .fem.voxels import VoxelMap

__all__ = [
    "InverseProblem",
    "Estimate",
    "interpolate_nodal",
    "visible_vertices",
    "observation_operator",
    "vertex_normals",
]


# --------------------------------------------------------------------------- data classes


@dataclass
class InverseProblem:
    """Observed modes + inference model + priors (+ truth for scoring).

    Attributes
    ----------
    model : inference :class:`ParametricModel` (mesh, voxel map, nu, fixed nodes).
    gamma : (k, 2 * n_visible) observed image-space modes, each of unit length.
    eigenvalues : (k,) observed ``(2 pi f)^2`` in (rad/s)^2.
    P : (2 * n_visible, n_free) sparse observation operator (pixels per metre).
    visible_nodes : (n_visible,) inference-mesh node indices observed, in ``gamma`` order.
    modes_3d : optional (n_free, k) full-field 3-D modes on the inference mesh (oracle only),
        scaled so that ``P @ modes_3d[:, i] ~ gamma[i]``.
    w0, v0 : initial (uniform) stiffness and density.
    w_mean : the prior mean of w (the anchor that fixes the w/v scale ambiguity).
    w_true, v_true : optional per-parameter truth, for metrics.
    kind : "solid" or "membrane".
    meta : provenance (scene, camera, geometry scale, source of the modes, ...).
    """

    model: ParametricModel
    gamma: np.ndarray
    eigenvalues: np.ndarray
    P: sp.csr_matrix
    visible_nodes: np.ndarray
    modes_3d: np.ndarray | None = None
    w0: float = 9000.0
    v0: float = 1270.0
    w_mean: float = 9000.0
    w_true: np.ndarray | None = None
    v_true: np.ndarray | None = None
    kind: str = "solid"
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.gamma = np.atleast_2d(np.asarray(self.gamma, dtype=float))
        self.eigenvalues = np.asarray(self.eigenvalues, dtype=float).ravel()
        self.P = sp.csr_matrix(self.P)
        k = len(self.eigenvalues)
        if self.gamma.shape != (k, self.P.shape[0]):
            raise ValueError(
                f"gamma needs shape ({k}, {self.P.shape[0]}) (modes x 2*visible), "
                f"got {self.gamma.shape}"
            )
        if self.P.shape[1] != self.model.n_free:
            raise ValueError(f"P has {self.P.shape[1]} columns, model has {self.model.n_free} "
                             "free DOFs")
        if self.modes_3d is not None and self.modes_3d.shape != (self.model.n_free, k):
            raise ValueError(f"modes_3d needs shape ({self.model.n_free}, {k}), "
                             f"got {self.modes_3d.shape}")
        for name in ("w_true", "v_true"):
            val = getattr(self, name)
            if val is not None and np.shape(val) != (self.n_params,):
                raise ValueError(f"{name} needs shape ({self.n_params},), got {np.shape(val)}")

    # -- convenience
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

    @property
    def has_truth(self) -> bool:
        return self.w_true is not None and self.v_true is not None

    def to_grid(self, values: np.ndarray, fill: float = np.nan) -> np.ndarray:
        return self.voxel_map.to_grid(values, fill)

    def select_modes(self, index) -> InverseProblem:
        """A copy observing only the modes ``index`` (an int n keeps the first n)."""
        idx = np.arange(index) if np.isscalar(index) else np.asarray(index)
        if len(idx) == 0 or idx.max() >= self.n_modes:
            raise ValueError(f"mode selection {index!r} out of range; {self.n_modes} modes")
        m3 = None if self.modes_3d is None else self.modes_3d[:, idx]
        return replace(self, gamma=self.gamma[idx], eigenvalues=self.eigenvalues[idx],
                       modes_3d=m3, meta=dict(self.meta))

    # -- constructor from a simulation
    @classmethod
    def from_simulation(
        cls,
        result,
        camera=None,
        inference_shape: tuple[int, ...] = (8, 8, 8),
        n_modes: int = 20,
        visible: np.ndarray | None = None,
        inference_mesh: Mesh | None = None,
        nu: float | None = None,
        geometry_scale: float | tuple[float, float, float] = 1.0,
        w0: float | None = None,
        v0: float | None = None,
        w_mean: float | None = None,
        full_field: bool = True,
        depth_buffer: np.ndarray | None = None,
    ) -> InverseProblem:
        """Observe the *true* modes of a :class:`~vvtbench.simulate.SimulationResult`.

        The simulation's 3-D modes are interpolated at the inference mesh's nodes (both meshes
        cover the same object), projected with the camera Jacobians at the visible vertices
        and normalized to unit length (as the authors do with extracted modes).

        Parameters
        ----------
        result : the simulation.
        camera : a :class:`~vvtbench.render.camera.Camera`; default the scene's camera.
        inference_shape : voxel grid (and, for boxes, inference-mesh cells): (8, 8, 8) as the
            paper; (20, 20) style 2-tuples for drums.
        n_modes : number of lowest modes observed.
        visible : inference-mesh node indices seen by the camera; default
            :func:`visible_vertices` (surface, facing the camera, inside the frame, not fixed;
            with ``depth_buffer`` also not occluded).
        inference_mesh : default: boxes get ``box_mesh(inference_shape)`` (hex8) of the
            (scaled) box; other geometries reuse the (scaled) simulation mesh.
        nu : Poisson's ratio assumed by the inference model (default: the scene's base nu).
        geometry_scale : inference mesh = true geometry scaled by this (a float scales x only,
            the paper's geometry-mismatch track; or an (sx, sy, sz) tuple). The observation
            pixels stay those of the true object: inference vertex X is seen where the true
            point X / s is, and ``P`` is the Jacobian of that fitted camera (J diag(1/s)).
        w0, v0, w_mean : priors; default the scene's base material (the paper's choice).
        full_field : also store ``modes_3d`` (for the oracle).
        depth_buffer : (H, W) rendered rest depth of the true object at the pixel centres;
            with the default ``visible``, occluded vertices are dropped
            (:func:`visible_vertices`).
        """
        from .render.camera import Camera
        from .simulate import fixed_nodes as scene_fixed_nodes

        scene = result.scene
        if camera is None:
            camera = Camera.from_spec(scene.camera)
        sim_mesh = result.mesh
        scale = np.ones(3)
        if np.isscalar(geometry_scale):
            scale[0] = float(geometry_scale)
        else:
            scale[:] = np.asarray(geometry_scale, dtype=float)
        if np.any(scale <= 0):
            raise ValueError(f"geometry_scale must be positive, got {geometry_scale}")
        membrane = sim_mesh.dofs_per_node == 1
        if n_modes > len(result.modes):
            raise ValueError(f"asked for {n_modes} modes; the simulation has {len(result.modes)}")

        # inference mesh (lowest corner at the origin, as all vvtbench meshes)
        if inference_mesh is None:
            g = scene.geometry
            if g.kind == "box":
                size = tuple(float(s) for s in np.asarray(g.size) * scale)
                inference_mesh = box_mesh(tuple(inference_shape), size, 1)
            else:
                inference_mesh = _scaled_mesh(sim_mesh, scale)
        fixed = _inference_fixed_nodes(scene, inference_mesh, scale, scene_fixed_nodes)
        if nu is None:
            nu = float(scene.material.nu)
        vmap = VoxelMap.from_mesh(inference_mesh, tuple(inference_shape))
        model = ParametricModel(inference_mesh, vmap, nu=nu, fixed_nodes=fixed)

        # true positions of the inference nodes, and the simulation's modes there
        true_points = inference_mesh.points / scale
        k = n_modes
        lam = np.asarray(result.modes.eigenvalues[:k], dtype=float)
        nodal = result.model.nodal(result.modes.vectors[:, :k])  # (k, n_nodes, d)
        d = sim_mesh.dofs_per_node
        values = np.moveaxis(nodal, 0, -1).reshape(sim_mesh.n_nodes, d * k)
        at_nodes = interpolate_nodal(sim_mesh, values, true_points).reshape(-1, d, k)
        at_nodes[fixed] = 0.0  # the inference model's boundary holds these at zero

        if visible is None:
            visible = visible_vertices(inference_mesh, camera, exclude=fixed,
                                       true_points=true_points, depth_buffer=depth_buffer)
        visible = np.asarray(visible, dtype=np.int64)
        if visible.size == 0:
            raise ValueError("no inference-mesh vertex is visible from the camera")
        P = observation_operator(model, camera, visible, scale=scale, true_points=true_points)
        # what the camera sees is the true motion J u; on the (stretched) inference mesh the
        # same motion is diag(s) u, and P = J diag(1/s) maps it back to the same pixels
        if d == 3:
            at_nodes = at_nodes * scale[None, :, None]
        full = at_nodes.reshape(-1, k)  # (n_nodes * d, k), node-major DOFs
        U = full[model.free_dofs]
        gamma = (P @ U).T  # (k, 2 n_vis)
        norms = np.linalg.norm(gamma, axis=1)
        if np.any(norms == 0):
            raise ValueError(f"modes {np.flatnonzero(norms == 0).tolist()} are invisible "
                             "(zero image motion at every visible vertex)")
        gamma = gamma / norms[:, None]
        U = U / norms

        # truth on the inference grid: volume-weighted average of the simulation's elements
        w_true = _voxel_truth(sim_mesh, result.fields.stiffness, vmap, scale)
        v_true = _voxel_truth(sim_mesh, result.fields.density, vmap, scale)
        m = scene.material
        base_w = m.tension if membrane else m.E
        base_v = m.areal_density if membrane else m.rho
        meta = {
            "scene": scene.name,
            "source": "simulation (true modes)",
            "camera": camera.to_dict(),
            "geometry_scale": scale.tolist(),
            "inference_shape": list(inference_shape),
            "inference_element": inference_mesh.element,
            "simulation_element": sim_mesh.element,
            "simulation_cells": sim_mesh.n_elements,
            "nu": nu,
            "n_visible": int(len(visible)),
        }
        return cls(
            model=model, gamma=gamma, eigenvalues=lam, P=P, visible_nodes=visible,
            modes_3d=U if full_field else None,
            w0=float(base_w if w0 is None else w0), v0=float(base_v if v0 is None else v0),
            w_mean=float(base_w if w_mean is None else w_mean),
            w_true=w_true, v_true=v_true, kind="membrane" if membrane else "solid", meta=meta,
        )

    def with_extracted_modes(
        self,
        modesets: list,
        camera=None,
        n_modes: int = 10,
        merge_freq_tol: float = 0.02,
        merge_min_mac: float = 0.8,
    ) -> InverseProblem:
        """This problem observing modes extracted from video instead of the true ones.

        The extracted image-space shapes are sampled at the pixels of the visible inference
        vertices (of the true object: positions divided by the geometry scale) and normalized;
        the ``n_modes`` lowest non-shake modes are kept. Each one is paired with a true mode by
        MAC (optimal assignment) to give the oracle its full-field 3-D mode and to record the
        extraction's quality in ``meta``.

        Parameters
        ----------
        modesets : one :class:`~vvtbench.modes.ModeSet` per video of the object (several are
            merged by frequency and MAC).
        camera : the camera of the video; default the one in ``meta["camera"]``.
        n_modes : number of lowest extracted modes kept.
        merge_freq_tol, merge_min_mac : merging tolerances for several videos.

        Returns
        -------
        InverseProblem
            A copy with ``gamma``, ``eigenvalues`` and ``modes_3d`` replaced.
        """
        from scipy.optimize import linear_sum_assignment

        from .metrics import mac_matrix
        from .modes import merge_modesets, sample_modes

        sets = list(modesets)
        if not sets:
            raise ValueError("no mode sets given")
        ms = sets[0] if len(sets) == 1 else merge_modesets(
            sets, freq_tol=merge_freq_tol, min_mac=merge_min_mac)
        if len(sets) == 1:
            ms = ms.select(~ms.camera_shake)
        order_f = np.argsort(ms.frequencies_hz)
        ms = ms.select(order_f[:n_modes])
        if len(ms) == 0:
            raise ValueError("no modes were extracted from the video")
        scale = np.asarray(self.meta["geometry_scale"], dtype=float)
        cam = camera
        if cam is None:
            from .render.camera import Camera

            cam = Camera.from_dict(self.meta["camera"])
        uv = cam.project(self.mesh.points[self.visible_nodes] / scale)
        gamma = sample_modes(ms.shapes, uv)
        norms = np.linalg.norm(gamma, axis=1)
        keep = norms > 0
        gamma = gamma[keep] / norms[keep, None]
        freqs = ms.frequencies_hz[keep]
        mac = mac_matrix(gamma, self.gamma)
        rows, cols = linear_sum_assignment(-mac)
        order_r = np.argsort(rows)
        rows, cols = rows[order_r], cols[order_r]
        U = self.modes_3d[:, cols] * np.sign(
            np.einsum("ij,ij->i", gamma[rows], self.gamma[cols]) + 1e-300)[None, :]
        gamma, freqs = gamma[rows], freqs[rows]
        meta = dict(self.meta)
        meta.update({
            "observation": "extracted", "source": "extracted from the rendered video",
            "n_modes_extracted": int(len(ms)), "extracted_frequencies_hz": freqs.tolist(),
            "matched_true_modes": cols.tolist(), "extraction_mac": mac[rows, cols].tolist(),
            "true_frequencies_hz": self.frequencies_hz[cols].tolist(),
        })
        return replace(self, gamma=gamma, eigenvalues=(2 * np.pi * freqs) ** 2, modes_3d=U,
                       meta=meta)

    @classmethod
    def from_sample(
        cls,
        sample,
        observation: str = "extracted",
        modesets: list | None = None,
        inference_shape: tuple[int, ...] | None = None,
        n_modes: int = 10,
        geometry_scale: float | tuple[float, float, float] = 1.0,
        extract_options: dict | None = None,
        depth_visibility: bool = True,
        clicks: str | Path | None = None,
        **priors,
    ) -> InverseProblem:
        """The problem of a sample written by ``vvtbench generate``.

        The sample's scene is simulated again (deterministic, modes only) to get the truth and
        the true modes on the inference mesh; with ``observation="extracted"`` the observed
        modes are those extracted from the sample's video (``modesets``, or
        :func:`vvtbench.modes.extract_modes` run on the video now with ``extract_options``).

        Parameters
        ----------
        sample : a :class:`~vvtbench.dataset.Sample` or its folder.
        observation : ``"true"`` (true image-space modes) or ``"extracted"``.
        modesets : extracted mode sets of the video (``ModeSet.load`` of an extract output).
        inference_shape : voxel grid; default (8, 8, 8), drums (20, 20).
        n_modes : number of observed modes.
        geometry_scale : inference mesh size / true size.
        extract_options : keyword arguments of ``extract_modes`` when extracting here.
        depth_visibility : visible vertices also pass the sample's rendered depth buffer
            (``image/depth``; self-occlusion), else only the normal-facing test.
        clicks : a clicks file (:mod:`vvtbench.modes.sampling`) pairing inference-mesh vertex
            indices (``problem.mesh.points``, seen where the true object's point
            ``points / geometry_scale`` is) with video pixels: the camera estimated from it
            (:func:`~vvtbench.modes.sampling.camera_from_clicks`, >= 6 non-coplanar pairs)
            replaces the sample's for ``P`` and the sampling of the extracted modes (the
            visible vertices stay the sample's, less any outside the frame); ``meta``
            records ``camera_source`` (``"sample"`` or ``"clicks"``), ``clicks_file``,
            ``clicks_rms_px`` and the ``camera``.
        **priors : ``nu``, ``w0``, ``v0``, ``w_mean``.

        Returns
        -------
        InverseProblem
        """
        from .dataset import open_sample
        from .simulate import simulate

        if observation not in ("true", "extracted"):
            raise ValueError(f"observation must be 'true' or 'extracted', got {observation!r}")
        if not hasattr(sample, "scene"):
            sample = open_sample(sample)
        scene = sample.scene
        if inference_shape is None:
            inference_shape = (20, 20) if scene.geometry.kind == "drum" else (8, 8, 8)
        result = simulate(scene, transient=False)
        n_true = len(result.modes)
        if observation == "true" and n_modes > n_true:
            raise ValueError(f"asked for {n_modes} modes; the scene simulates {n_true}")
        depth_buffer = None
        if depth_visibility:
            try:
                depth_buffer = sample["image/depth"]
            except KeyError:  # an older sample without dense image fields
                depth_buffer = None
        setup = dict(inference_shape=tuple(inference_shape),
                     n_modes=n_true if observation == "extracted" else n_modes,
                     geometry_scale=geometry_scale, depth_buffer=depth_buffer, **priors)
        camera = sample.camera
        problem = cls.from_simulation(result, camera=camera, **setup)
        camera_meta = {"camera_source": "sample"}
        if clicks is not None:
            from .modes.sampling import camera_from_clicks

            scale = np.asarray(problem.meta["geometry_scale"], dtype=float)
            camera, rms = camera_from_clicks(clicks, problem.mesh.points / scale,
                                             sample.camera.width, sample.camera.height)
            # the sample's visible vertices (its depth buffer belongs to its own camera, whose
            # distance the clicks fix only loosely), less those now outside the frame
            seen = problem.mesh.points[problem.visible_nodes] / scale
            uv = camera.project(seen)
            inside = ((camera.depth(seen) > 0) & (uv[:, 0] >= -0.5)
                      & (uv[:, 0] <= camera.width - 0.5) & (uv[:, 1] >= -0.5)
                      & (uv[:, 1] <= camera.height - 0.5))
            problem = cls.from_simulation(result, camera=camera,
                                          visible=problem.visible_nodes[inside], **setup)
            camera_meta = {"camera_source": "clicks", "clicks_file": str(clicks),
                           "clicks_rms_px": rms}
        problem.meta.update(camera_meta)
        problem.meta["visibility"] = "depth buffer" if depth_buffer is not None else "normals"
        problem.meta["sample"] = str(sample.path)
        if observation == "true":
            problem.meta["observation"] = "true"
            return problem
        if modesets is None:
            from .modes import extract_modes

            modesets = [extract_modes(sample.video_path, sample.fps, **(extract_options or {}))]
        return problem.with_extracted_modes(modesets, camera, n_modes)


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
    extra : optional arrays (e.g. the optimized 3-D modes ``U`` or eigenvalues).
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

    def extra_scalars(self) -> dict[str, Any]:
        """The entries of ``extra`` that are not arrays (written to estimate.json)."""
        return {k: x for k, x in self.extra.items() if not isinstance(x, np.ndarray)}


# --------------------------------------------------------------------------- geometry helpers


def _scaled_mesh(mesh: Mesh, scale: np.ndarray) -> Mesh:
    if np.allclose(scale, 1.0):
        return mesh
    return Mesh(mesh.points * scale, mesh.cells, mesh.element, dict(mesh.node_sets),
                mesh.surface)


def _inference_fixed_nodes(scene, mesh: Mesh, scale: np.ndarray, scene_fixed_nodes):
    """The scene's fixed node sets on the inference mesh (custom box regions scaled)."""
    extra = {}
    for name, region in scene.boundary.node_sets.items():
        if name not in scene.fixed_sets:
            continue
        if region.indices is not None:
            raise ValueError(
                f"boundary node set {name!r} is given by node indices of the simulation mesh; "
                "pass inference_mesh with that node set (and visible=...) explicitly"
            )
        lo = np.asarray(region.box_min) * scale
        hi = np.asarray(region.box_max) * scale
        extra[name] = np.flatnonzero(np.all((mesh.points >= lo) & (mesh.points <= hi), axis=1))
    if extra:
        mesh = mesh.with_node_sets(extra)
    return scene_fixed_nodes(scene, mesh)


def _voxel_truth(sim_mesh: Mesh, values: np.ndarray, vmap: VoxelMap, scale) -> np.ndarray:
    """Per inference parameter: element-volume-weighted mean of the simulation elements whose
    (scaled) centroid falls in the voxel; voxels that catch no centroid take the nearest
    element's value."""
    cent = sim_mesh.centroids * scale
    vox = vmap.grid.voxel_of(cent)
    param_of_voxel = np.full(vmap.grid.n_voxels, -1)
    param_of_voxel[vmap.active] = np.arange(vmap.n_params)
    param = param_of_voxel[vox]
    vol = element_volumes(sim_mesh.element_type, sim_mesh.cell_coords)
    keep = param >= 0
    num = np.bincount(param[keep], vol[keep] * values[keep], minlength=vmap.n_params)
    den = np.bincount(param[keep], vol[keep], minlength=vmap.n_params)
    out = np.empty(vmap.n_params)
    has = den > 0
    out[has] = num[has] / den[has]
    if not has.all():
        from scipy.spatial import cKDTree

        centers = vmap.grid.centers()[vmap.active[~has]]
        _, nearest = cKDTree(cent).query(centers)
        out[~has] = values[nearest]
    return out


def vertex_normals(mesh: Mesh) -> np.ndarray:
    """Area-weighted outward normals of the surface nodes (zero for interior nodes)."""
    tri = mesh.surface
    p = mesh.points[tri]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    out = np.zeros_like(mesh.points)
    for c in range(3):
        np.add.at(out, tri[:, c], n)
    norm = np.linalg.norm(out, axis=1, keepdims=True)
    return np.divide(out, norm, out=np.zeros_like(out), where=norm > 0)


def visible_vertices(
    mesh: Mesh, camera, exclude: np.ndarray | None = None, true_points: np.ndarray | None = None,
    depth_buffer: np.ndarray | None = None, depth_tol: float = 0.01,
) -> np.ndarray:
    """Surface nodes seen by ``camera``: on a surface triangle that faces the camera (outward
    normal towards the camera centre), in front of the camera and inside the frame.

    Without ``depth_buffer`` this is exact for convex objects only. ``depth_buffer`` (H, W),
    the rendered rest depth at the pixel centres (a sample's ``image/depth``, ``inf`` on the
    background), also removes self-occluded nodes as the dataset's visibility ground truth
    does: a node is kept when its depth is at most ``depth_tol`` times the bounding-box
    diagonal behind the buffer at its (nearest) pixel.
    ``true_points`` (default the mesh's) are where the nodes really are (geometry mismatch).
    """
    pts = mesh.points if true_points is None else true_points
    tri = mesh.surface
    p = pts[tri]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    to_cam = camera.center - p.mean(axis=1)
    facing = np.einsum("ij,ij->i", n, to_cam) > 0
    nodes = np.unique(tri[facing])
    uv = camera.project(pts[nodes])
    depth = camera.depth(pts[nodes])
    inside = (
        (depth > 0) & (uv[:, 0] >= -0.5) & (uv[:, 0] <= camera.width - 0.5)
        & (uv[:, 1] >= -0.5) & (uv[:, 1] <= camera.height - 0.5)
    )
    nodes = nodes[inside]
    if depth_buffer is not None and nodes.size:
        buf = np.asarray(depth_buffer, dtype=float)
        px = np.clip(np.rint(uv[inside]).astype(int), 0, [buf.shape[1] - 1, buf.shape[0] - 1])
        diag = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))
        nodes = nodes[depth[inside] <= buf[px[:, 1], px[:, 0]] + depth_tol * diag]
    if exclude is not None and len(exclude):
        nodes = np.setdiff1d(nodes, exclude)
    return nodes


def observation_operator(
    model: ParametricModel,
    camera,
    visible: np.ndarray,
    scale: np.ndarray | float = 1.0,
    true_points: np.ndarray | None = None,
) -> sp.csr_matrix:
    """Sparse (2 n_visible, n_free) map from free DOFs to image motion of ``visible`` nodes.

    Rows 2j, 2j+1 hold the camera Jacobian at node ``visible[j]`` (at its true position),
    times diag(1/scale) (the camera fitted to a scaled inference geometry). Membranes (one
    out-of-plane DOF per node) use the Jacobian's z column. Fixed DOFs drop out.
    """
    mesh = model.mesh
    visible = np.asarray(visible, dtype=np.int64)
    pts = mesh.points if true_points is None else true_points
    J = camera.jacobian(pts[visible]) / np.broadcast_to(np.asarray(scale, float), (3,))
    d = mesh.dofs_per_node
    if d == 1:
        J = J[:, :, 2:3]
    nv = len(visible)
    rows = np.broadcast_to(np.arange(2 * nv).reshape(nv, 2, 1), (nv, 2, d))
    dofs = visible[:, None] * d + np.arange(d)  # (nv, d)
    cols = np.broadcast_to(model.free_index[dofs][:, None, :], (nv, 2, d))
    keep = cols >= 0
    return sp.csr_matrix((J[keep], (rows[keep], cols[keep])), shape=(2 * nv, model.n_free))


# --------------------------------------------------------------------------- interpolation


def interpolate_nodal(mesh: Mesh, values: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Interpolate nodal ``values`` (n_nodes, ...) with the mesh's shape functions at
    ``points`` (N, 3) -> (N, ...).

    hex8/hex27: structured axis-aligned grids (box meshes): the containing cell is found by
    bisection on the grid lines, local coordinates are affine. tet4/tet10/tri3: barycentric
    coordinates in candidate cells (nearest centroids by cKDTree); points outside the mesh use
    the best candidate with clipped barycentrics (nearest-cell extrapolation).
    """
    values = np.asarray(values)
    pts = np.atleast_2d(np.asarray(points, dtype=float))
    el = mesh.element_type
    if mesh.element.startswith("hex"):
        cell, xi = _locate_hex(mesh, pts)
    else:
        cell, xi = _locate_simplex(mesh, pts)
    N = el.shape(xi)  # (N, nn)
    vals = values[mesh.cells[cell]]  # (N, nn, ...)
    return np.einsum("pn,pn...->p...", N, vals)


def _locate_hex(mesh: Mesh, pts: np.ndarray):
    el = mesh.element_type
    corners = mesh.points[mesh.cells[:, el.vertex_index]]  # (ne, 8, 3)
    lo, hi = corners.min(axis=1), corners.max(axis=1)
    scale = max(float(np.ptp(mesh.points, axis=0).max()), 1e-300)
    idx = []
    lines = []
    for a in range(3):
        g = np.unique(np.round(lo[:, a] / scale, 9))
        lines.append(g)
        idx.append(np.searchsorted(g, np.round(lo[:, a] / scale, 9)))
    shape = tuple(len(g) for g in lines)
    table = np.full(shape, -1, dtype=np.int64)
    table[idx[0], idx[1], idx[2]] = np.arange(mesh.n_elements)
    ijk = [np.clip(np.searchsorted(lines[a], pts[:, a] / scale + 1e-12, side="right") - 1,
                   0, shape[a] - 1) for a in range(3)]
    cell = table[ijk[0], ijk[1], ijk[2]]
    if np.any(cell < 0):
        raise ValueError("interpolate_nodal: hex meshes must be structured box grids "
                         "(a point falls in a grid cell without an element)")
    xi = 2.0 * (pts - lo[cell]) / (hi[cell] - lo[cell]) - 1.0
    return cell, np.clip(xi, -1.0, 1.0)


def _locate_simplex(mesh: Mesh, pts: np.ndarray, n_candidates: int = 24):
    from scipy.spatial import cKDTree

    el = mesh.element_type
    verts = mesh.points[mesh.cells[:, el.vertex_index]]  # (ne, nv, 3)
    dim = el.rdim
    if dim == 2:
        verts = verts[:, :, :2]
        pts_d = pts[:, :2]
    else:
        pts_d = pts
    tree = cKDTree(verts.mean(axis=1))
    cell = np.zeros(len(pts), dtype=np.int64)
    xi = np.zeros((len(pts), dim))
    todo = np.arange(len(pts))
    kc = min(n_candidates, mesh.n_elements)
    while todo.size:
        _, cand = tree.query(pts_d[todo], k=kc)
        cand = cand.reshape(len(todo), kc)
        V = verts[cand]  # (N, kc, dim+1, dim)
        T = np.swapaxes(V[:, :, 1:] - V[:, :, :1], -1, -2)  # (N, kc, dim, dim)
        rhs = (pts_d[todo][:, None, :] - V[:, :, 0])[..., None]
        lam_rest = np.linalg.solve(T, rhs)[..., 0]  # (N, kc, dim)
        bary = np.concatenate([1 - lam_rest.sum(-1, keepdims=True), lam_rest], axis=-1)
        worst = bary.min(axis=-1)
        best = np.argmax(worst, axis=1)
        rows = np.arange(len(todo))
        inside = worst[rows, best] >= -1e-9
        done = inside | (kc >= mesh.n_elements)  # outside the mesh: nearest cell, clipped
        b = np.clip(bary[rows, best], 0.0, None)
        b /= b.sum(axis=1, keepdims=True)
        cell[todo[done]] = cand[rows, best][done]
        xi[todo[done]] = b[done, 1:]
        todo = todo[~done]
        kc = min(4 * kc, mesh.n_elements)
    return cell, xi
