"""The observe stage: data -> the inverse problem a solver gets, and the truth kept apart.

:func:`observe` is the one bridge from data to an :class:`~vvtbench.solving.problem.InverseProblem`:

* a **sample folder** written by ``vvtbench generate`` (or an opened
  :class:`~vvtbench.samples.reader.Sample`), or an **entry of an exported dataset**
  (:func:`vvtbench.open_dataset`): everything is read from the sample (mesh, modes, free DOFs,
  per-element material, camera, rest depth buffer); the simulator is never run;
* a **scene** (:class:`~vvtbench.scene.scene.Scene`, a scene file or a shipped scene name):
simulated
  on the fly (modes only) -- the only source that simulates -- or a simulation already run
  (:class:`~vvtbench.simulation.simulate.SimulationResult`); the rest depth buffer is rasterized;
* a **real video** (:class:`RealVideo`): modes extracted from it, the object's mesh, and a
  camera or clicked reference points; there is no truth.

It returns ``(problem, truth)``. The problem holds only what an experimenter would have: the
observed image-space modes and frequencies, the observation operator, the inference mesh and
voxel grid, and priors. The :class:`Truth` (material per voxel, the true 3-D modes paired with
the observed ones, the true image-space modes, the scene and sample it came from) is for the
evaluator and for reference solvers that declare ``uses_truth`` (the oracle).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from .fem.assembly import ParametricModel
from .fem.interpolate import interpolate_nodal
from .fem.mesh import Mesh, box_mesh
from .fem.voxels import VoxelMap, default_voxel_shape
from .solving.problem import InverseProblem
from .solving.truth import Truth

__all__ = ["ObserveError", "ObserveOptions", "RealVideo", "Truth", "observe", "sample_truth"]

OBSERVATIONS = ("true", "extracted")
VISIBILITY = ("depth", "normals")


class ObserveError(ValueError):
    """Bad observe options or a source that cannot be observed (one line, names the key)."""


# --------------------------------------------------------------------------- options


@dataclass(frozen=True)
class ObserveOptions:
    """How a source is turned into an inverse problem.

    Attributes
    ----------
    observation : ``"true"`` (the true image-space modes at the visible vertices) or
        ``"extracted"`` (modes extracted from the video, sampled at the visible vertices).
    n_modes : number of observed modes (the lowest ones).
    inference_shape : voxel grid of the unknowns (boxes: also the inference mesh's cells);
        default (8, 8, 8), drums (20, 20).
    inference_order : element order of a box inference mesh (1: hex8, 2: hex27).
    geometry_scale : inference geometry = true geometry scaled by this (a float scales x only,
        the paper's geometry-mismatch track; or (sx, sy, sz)).
    nu : Poisson's ratio of the inference model (default: the scene's base material).
    w0, v0, w_mean : priors: initial stiffness and density, and the anchor of mean(w)
        (default: the scene's base material, the paper's choice).
    visibility : ``"depth"`` (facing the camera and not occluded in the rest depth buffer) or
        ``"normals"`` (facing the camera only; exact for convex objects).
    extract : keyword arguments of :func:`vvtbench.modes.extract_modes` when modes are
        extracted here.
    modes : extracted mode sets to use instead of extracting: ModeSet objects or folders
        written by ``vvtbench extract`` (several videos of one view are merged; with
        ``views > 1``: one set per view, view 0 first, joined with each view's video).
    merge_freq_tol, merge_min_mac : merging tolerances for several videos of one view.
    views : number of synchronised cameras (1: the sample's own, view 0). With ``views > 1``
        the cameras are the sample's first ``views`` views when it holds that many (a sample
        generated with ``[camera.rig]`` or ``[[camera.views]]``, docs/dataset.md "Several
        views"); otherwise (true modes only) the sample's camera is turned about the scene's
        up axis through the object's centre in ``view_spread_deg / views`` steps (a ring of
        identical cameras; 360 puts 2 views on opposite sides). Each view sees its own visible
        vertices (its own rest depth), and the observation operator stacks the views:
        ``P = [P_1; P_2; ...]``, every mode one vector over all views' rows, normalized once.
        A vertex seen by two views contributes both views' rows: its 3-D motion is then
        observed along up to three directions instead of two; every row has the same weight
        (the image noise is the same per pixel in every view). With ``observation
        "extracted"`` the modes are extracted from every view's video and joined
        (:mod:`vvtbench.modes.joint`: paired by frequency, phases aligned across views, each
        view's shape scaled to one common modal coordinate); a view that did not find a mode
        contributes zeros to its rows. ``problem.meta["observed_dof_fraction"]`` is the rank
        of ``P`` over the free DOFs.
    view_spread_deg : degrees the ring of cameras spans (360: all around).
    clicks : a clicks file (vertex index of the inference mesh, u, v; see docs/modes.md):
        the camera is estimated from it (DLT + refinement) instead of taken from the sample.
    """

    observation: str = "true"
    n_modes: int = 10
    inference_shape: tuple[int, ...] | None = None
    inference_order: int = 1
    geometry_scale: float | tuple[float, float, float] = 1.0
    nu: float | None = None
    w0: float | None = None
    v0: float | None = None
    w_mean: float | None = None
    visibility: str = "depth"
    extract: Mapping[str, Any] = field(default_factory=dict)
    modes: tuple = ()
    merge_freq_tol: float = 0.02
    merge_min_mac: float = 0.8
    views: int = 1
    view_spread_deg: float = 360.0
    clicks: str | None = None

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        _choice("observation", self.observation, OBSERVATIONS)
        _choice("visibility", self.visibility, VISIBILITY)
        _integer("n_modes", self.n_modes, 1)
        _integer("inference_order", self.inference_order, 1, 2)
        if self.inference_shape is not None:
            shape = tuple(self.inference_shape)
            if len(shape) not in (2, 3):
                raise ObserveError(f"inference_shape must have 2 (drums) or 3 entries, "
                                   f"got {list(shape)}")
            for n in shape:
                _integer("inference_shape", n, 1, 256)
            set_(self, "inference_shape", tuple(int(n) for n in shape))
        gs = self.geometry_scale
        if isinstance(gs, Sequence) and not isinstance(gs, str):
            if len(gs) != 3:
                raise ObserveError(f"geometry_scale must be a number or 3 numbers, got {gs!r}")
            set_(self, "geometry_scale", tuple(_number("geometry_scale", x, 0.0) for x in gs))
        else:
            set_(self, "geometry_scale", _number("geometry_scale", gs, 0.0))
        if self.nu is not None:
            nu = _number("nu", self.nu, -1.0)
            if nu >= 0.5:
                raise ObserveError(f"nu must be in (-1, 0.5), got {nu}")
        for key in ("w0", "v0", "w_mean"):
            if getattr(self, key) is not None:
                _number(key, getattr(self, key), 0.0)
        _integer("views", self.views, 1, 16)
        spread = _number("view_spread_deg", self.view_spread_deg, 0.0)
        if spread > 360.0:
            raise ObserveError(f"view_spread_deg must be in (0, 360], got {spread}")
        modes_given = self.modes if isinstance(self.modes, (list, tuple)) else (self.modes,)
        if (self.views > 1 and self.observation != "true" and self.modes
                and len(modes_given) != self.views):
            raise ObserveError(f"modes: with views = {self.views} give one mode set per view "
                               f"(view 0 first), got {len(modes_given)}")
        if self.views > 1 and self.clicks is not None:
            raise ObserveError("views > 1 with clicks is not built yet (one clicks file "
                               "calibrates one camera)")
        _number("merge_freq_tol", self.merge_freq_tol, 0.0)
        if not 0.0 <= float(self.merge_min_mac) <= 1.0:
            raise ObserveError(f"merge_min_mac must be in [0, 1], got {self.merge_min_mac}")
        if not isinstance(self.extract, Mapping):
            raise ObserveError("extract must be a table of extract_modes options")
        set_(self, "extract", dict(self.extract))
        modes = self.modes
        if isinstance(modes, (str, Path)) or not isinstance(modes, Sequence):
            modes = (modes,)
        set_(self, "modes", tuple(modes))

    @classmethod
    def resolve(cls, options: ObserveOptions | Mapping[str, Any] | None = None,
                **overrides: Any) -> ObserveOptions:
        """``options`` (an instance, a mapping of fields or None for the defaults) with the
        fields ``overrides`` replaced."""
        if options is None:
            return cls.from_mapping(overrides)
        base = options if isinstance(options, cls) else cls.from_mapping(options)
        return base.replace(**overrides) if overrides else base

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any], where: str = "observe options"
                     ) -> ObserveOptions:
        """Options from a plain mapping (a suite's ``[defaults]``, JSON); unknown keys are an
        error naming the allowed ones."""
        allowed = [f.name for f in fields(cls)]
        unknown = sorted(set(data) - set(allowed))
        if unknown:
            raise ObserveError(f"{where}: unknown key(s) {unknown}; allowed: "
                               f"{', '.join(allowed)}")
        try:
            return cls(**dict(data))
        except ObserveError as error:
            raise ObserveError(f"{where}: {error}") from None

    def replace(self, **changes: Any) -> ObserveOptions:
        return ObserveOptions.from_mapping({**self.to_dict(raw=True), **changes})

    def to_dict(self, raw: bool = False) -> dict[str, Any]:
        """Plain data (JSON-ready unless ``raw``: mode sets are given as their folders)."""
        out = {f.name: getattr(self, f.name) for f in fields(self)}
        if not raw:
            out["modes"] = [str(m) if isinstance(m, (str, Path)) else repr(m)
                            for m in self.modes]
            out["inference_shape"] = (None if self.inference_shape is None
                                      else list(self.inference_shape))
            if isinstance(self.geometry_scale, tuple):
                out["geometry_scale"] = list(self.geometry_scale)
        return out


def _choice(key: str, value: Any, allowed: Sequence[str]) -> None:
    if value not in allowed:
        raise ObserveError(f"{key} must be one of {', '.join(allowed)}; got {value!r}")


def _integer(key: str, value: Any, lo: int, hi: int | None = None) -> None:
    ok = isinstance(value, (int, np.integer)) and not isinstance(value, bool)
    if not ok or value < lo or (hi is not None and value > hi):
        rng = f">= {lo}" if hi is None else f"in {lo}..{hi}"
        raise ObserveError(f"{key} must be an integer {rng}, got {value!r}")


def _number(key: str, value: Any, above: float) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ObserveError(f"{key} must be a number, got {value!r}") from None
    if isinstance(value, bool) or not np.isfinite(x) or x <= above:
        raise ObserveError(f"{key} must be a finite number > {above:g}, got {value!r}")
    return x


# --------------------------------------------------------------------------- sources


@dataclass
class RealVideo:
    """A real recording: extracted modes, the object's inference mesh, a camera or clicks.

    Attributes
    ----------
    modes : ModeSet objects or folders written by ``vvtbench extract`` (one per view).
    mesh : the inference mesh of the object (metres; lowest corner at the origin).
    camera : the camera of the video, or None with ``clicks``.
    clicks : a clicks file pairing mesh vertices with pixels (>= 6, non-coplanar).
    fixed_nodes : node indices of ``mesh`` held fixed (the clamped base).
    width, height : the video's size in pixels (needed with ``clicks``).
    nu, w0, v0 : the material priors (no scene gives them).
    """

    modes: Sequence[Any]
    mesh: Mesh
    camera: Any = None
    clicks: str | Path | None = None
    fixed_nodes: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    width: int | None = None
    height: int | None = None
    nu: float = 0.3
    w0: float = 1e4
    v0: float = 1000.0


@dataclass
class _Record:
    """What observation reads from a sample: the simulation's mesh, modes and material."""

    origin: str
    scene: Any
    camera: Any
    mesh: Mesh
    free_dofs: np.ndarray
    eigenvalues: np.ndarray
    vectors: np.ndarray
    stiffness: np.ndarray
    density: np.ndarray
    depth: np.ndarray | None
    video: Any = None            # () -> (frames source, fps), for extraction; or None
    packed_modes: Any = None     # () -> mode sets packed with a dataset entry; or None
    views: list | None = None    # every view of a multi-view sample (view 0 first); or None
    time_offset_s: float = 0.0   # how much later than view 0 this view films (s)

    @property
    def fixed_nodes(self) -> np.ndarray:
        d = self.mesh.dofs_per_node
        free = np.zeros(self.mesh.n_nodes * d, bool)
        free[self.free_dofs] = True
        return np.flatnonzero(~free.reshape(-1, d).any(axis=1))


def _read(sample: Any, name: str) -> np.ndarray:
    require = getattr(sample, "require", None)
    if require is not None:
        return np.asarray(require(name))
    try:
        return np.asarray(sample[name])
    except KeyError:
        from .samples.reader import DatasetError

        where = getattr(sample, "path", getattr(sample, "name", "sample"))
        raise DatasetError(f"{where}: truth.zarr has no array '{name}'; regenerate the sample "
                           "with this vvtbench") from None


def _record_from_sample(sample: Any) -> _Record:
    info = sample.info
    mesh_info = info["mesh"]
    mesh = Mesh(_read(sample, "mesh/points"), _read(sample, "mesh/cells"),
                mesh_info["element"], {}, _read(sample, "mesh/surface"))
    depth = None
    try:
        depth = _read(sample, "image/depth")
    except (KeyError, ValueError):
        depth = None
    origin = str(getattr(sample, "path", None) or getattr(sample, "name", "sample"))
    video = None
    has_video = getattr(sample, "has_video", None)
    if has_video is None:
        has_video = bool(info.get("video", {}).get("frames"))
    if has_video:  # read only if modes are extracted here
        path = getattr(sample, "video_path", None)
        video = ((lambda: (path, sample.fps)) if path is not None
                 else (lambda: (sample.read_frames(), sample.fps)))
    packed = getattr(sample, "extracted_modes", None)
    rec = _Record(
        origin=origin, scene=sample.scene, camera=sample.camera, mesh=mesh,
        free_dofs=_read(sample, "modes/free_dofs"),
        eigenvalues=_read(sample, "modes/eigenvalues").astype(float),
        vectors=_read(sample, "modes/vectors"),
        stiffness=_read(sample, "material/stiffness"),
        density=_read(sample, "material/density"), depth=depth, video=video,
        packed_modes=packed,
    )
    n_views = int(getattr(sample, "n_views", 1))
    if n_views > 1:
        rec.views = [rec] + [_view_record(rec, sample.view(i)) for i in range(1, n_views)]
    return rec


def _view_record(rec: _Record, view: Any) -> _Record:
    """View ``view`` (a :meth:`~vvtbench.samples.reader.Sample.view`) of the sample of ``rec``."""
    video = None
    if view.has_video:
        path = getattr(view, "video_path", None)
        video = ((lambda: (path, view.fps)) if path is not None  # noqa: E731
                 else (lambda: (view.read_frames(), view.fps)))
    return replace(rec, camera=view.camera, depth=_read(view, "image/depth"), video=video,
                   packed_modes=None, views=None,
                   time_offset_s=float(view.info.get("view", {}).get("time_offset_s", 0.0)))


def _record_from_result(result: Any) -> _Record:
    """From a :class:`~vvtbench.simulation.simulate.SimulationResult` (its rest depth
    rasterized)."""
    from .render import Camera
    from .render.raster import rasterize

    scene, mesh = result.scene, result.mesh
    camera = Camera.from_spec(scene.camera)
    nodes = mesh.surface_nodes
    lut = np.full(mesh.n_nodes, -1, dtype=np.int64)
    lut[nodes] = np.arange(len(nodes))
    depth = rasterize(camera, mesh.points[nodes], lut[mesh.surface]).depth
    return _Record(
        origin=f"scene {scene.name} (simulated)", scene=scene, camera=camera, mesh=mesh,
        free_dofs=result.model.free_dofs,
        eigenvalues=np.asarray(result.modes.eigenvalues, dtype=float),
        vectors=result.modes.vectors, stiffness=result.fields.stiffness,
        density=result.fields.density, depth=depth,
    )


def _as_record(source: Any) -> _Record:
    from .scene.scene import Scene, load_scene
    from .simulation.simulate import simulate

    if isinstance(source, _Record):
        return source
    if isinstance(source, Scene):
        return _record_from_result(simulate(source, transient=False))
    if hasattr(source, "modes") and hasattr(source, "model") and hasattr(source, "scene"):
        return _record_from_result(source)  # a SimulationResult
    if isinstance(source, (str, Path)):
        path = Path(source)
        if path.is_dir():
            from .samples.reader import open_sample

            return _record_from_sample(open_sample(path))
        return _record_from_result(simulate(load_scene(source), transient=False))
    if hasattr(source, "scene") and hasattr(source, "info"):
        return _record_from_sample(source)
    raise ObserveError(f"cannot observe a {type(source).__name__}: give a sample folder, a "
                       "dataset entry, a scene (name, file or Scene) or a RealVideo")


# --------------------------------------------------------------------------- observe


def observe(source: Any, options: ObserveOptions | Mapping[str, Any] | None = None,
            **overrides: Any) -> tuple[InverseProblem, Truth | None]:
    """The inverse problem of ``source`` and its truth.

    Parameters
    ----------
    source : a sample folder or :class:`~vvtbench.samples.reader.Sample`; an entry of an exported
        dataset; a :class:`~vvtbench.scene.scene.Scene`, scene file or shipped scene name
        (simulated now); or a :class:`RealVideo`.
    options : :class:`ObserveOptions` (or a mapping of its fields).
    **overrides : fields of :class:`ObserveOptions` replacing those of ``options``.

    Returns
    -------
    (InverseProblem, Truth)
        The truth is None for a :class:`RealVideo`.

    Examples
    --------
    >>> problem, truth = observe("jello_cube_defect_top", n_modes=4)  # doctest: +SKIP
    >>> problem.gamma.shape[0], truth.w.shape == (problem.n_params,)  # doctest: +SKIP
    (4, True)
    """
    from .solving.plugins import refuse_when_sealed

    refuse_when_sealed("observe()")
    opts = ObserveOptions.resolve(options, **overrides)
    if isinstance(source, RealVideo):
        return _observe_real(source, opts), None
    return _observe_record(_as_record(source), opts)


def _scale_vector(geometry_scale: float | tuple[float, ...]) -> np.ndarray:
    scale = np.ones(3)
    if np.isscalar(geometry_scale):
        scale[0] = float(geometry_scale)
    else:
        scale[:] = np.asarray(geometry_scale, dtype=float)
    return scale


def _inference_model(rec: _Record, opts: ObserveOptions, scale: np.ndarray
                     ) -> ParametricModel:
    from .simulation.simulate import fixed_nodes as scene_fixed_nodes

    scene = rec.scene
    geom = scene.geometry
    shape = opts.inference_shape or default_voxel_shape(geom.kind)
    if geom.kind == "box":
        if len(shape) != 3:
            raise ObserveError(f"inference_shape must have 3 entries for a box, got {shape}")
        size = tuple(float(s) for s in np.asarray(geom.size) * scale)
        mesh = box_mesh(tuple(shape), size, opts.inference_order)
        extra = {}
        for name, region in scene.boundary.node_sets.items():
            if name not in scene.fixed_sets:
                continue
            if region.indices is not None:
                raise ObserveError(f"boundary node set {name!r} is given by node indices of "
                                   "the simulation mesh; a box inference mesh cannot map it")
            lo, hi = np.asarray(region.box_min) * scale, np.asarray(region.box_max) * scale
            extra[name] = np.flatnonzero(np.all((mesh.points >= lo) & (mesh.points <= hi), 1))
        if extra:
            mesh = mesh.with_node_sets(extra)
        fixed = scene_fixed_nodes(scene, mesh)
    else:
        if opts.inference_order != 1:
            raise ObserveError("inference_order applies to box geometries only")
        sim = rec.mesh
        mesh = sim if np.allclose(scale, 1.0) else Mesh(
            sim.points * scale, sim.cells, sim.element, dict(sim.node_sets), sim.surface)
        fixed = rec.fixed_nodes
    nu = float(scene.material.nu if opts.nu is None else opts.nu)
    vmap = VoxelMap.from_mesh(mesh, tuple(shape))
    return ParametricModel(mesh, vmap, nu=nu, fixed_nodes=fixed)


RIGID_RTOL = 1e-8  # an eigenvalue below this fraction of the largest is a rigid-body mode


def _without_rigid_body_modes(rec: _Record) -> tuple[_Record, int]:
    """The record without its rigid-body modes (a free body's six zero eigenvalues: they move
    the body without deforming it and carry no stiffness), and how many there were."""
    from dataclasses import replace

    lam = np.asarray(rec.eigenvalues, dtype=float)
    if lam.size == 0:
        return rec, 0
    keep = lam > RIGID_RTOL * float(np.max(np.abs(lam)))
    if keep.all():
        return rec, 0
    return replace(rec, eigenvalues=lam[keep], vectors=rec.vectors[:, keep]), int((~keep).sum())


def _true_modes(rec: _Record, model: ParametricModel, scale: np.ndarray, k: int) -> np.ndarray:
    """(n_nodes, d, k) the simulation's first ``k`` modes at the inference nodes (fixed 0),
    in inference coordinates (stretched with the geometry)."""
    sim = rec.mesh
    d = sim.dofs_per_node
    full = np.zeros((sim.n_nodes * d, k))
    full[rec.free_dofs] = rec.vectors[:, :k]
    values = full.reshape(sim.n_nodes, d * k)
    at_nodes = interpolate_nodal(sim, values, model.mesh.points / scale).reshape(-1, d, k)
    at_nodes[model.fixed_nodes] = 0.0
    if d == 3:
        at_nodes = at_nodes * scale[None, :, None]
    return at_nodes


def _observed_views(rec: _Record, model: ParametricModel, opts: ObserveOptions,
                    scale: np.ndarray):
    """:func:`_observed_view` of every view, stacked (one view: the sample's); returns
    (cameras, visible nodes, P, meta, the view records)."""
    import scipy.sparse as sp

    if opts.views == 1:
        camera, visible, P, meta = _observed_view(rec, model, opts, scale)
        cameras, views = [camera], [rec]
    else:
        if rec.views is not None and len(rec.views) >= opts.views:
            views, source = rec.views[: opts.views], "sample"
        elif opts.observation == "true":
            views, source = _ring_records(rec, opts.views, opts.view_spread_deg), "ring"
        else:
            held = len(rec.views) if rec.views else 1
            raise ObserveError(f"views: {rec.origin} holds {held} view(s) and observation "
                               f"'extracted' needs {opts.views} videos; generate the sample "
                               "with [camera.rig] or [[camera.views]] (docs/dataset.md, "
                               "'Several views'), or observe true modes")
        parts = [_observed_view(view, model, opts, scale) for view in views]
        cameras = [p[0] for p in parts]
        visible = np.concatenate([p[1] for p in parts])
        P = sp.vstack([p[2] for p in parts]).tocsr()
        meta = {**parts[0][3], "views": opts.views, "view_source": source,
                "cameras": [p[3]["camera"] for p in parts],
                "n_visible_per_view": [int(len(p[1])) for p in parts]}
        if source == "ring":
            meta["view_spread_deg"] = opts.view_spread_deg
    meta["observed_dof_fraction"] = observed_dof_fraction(P, model)
    return cameras, visible, P, meta, views


def _ring_records(rec: _Record, n: int, spread_deg: float) -> list[_Record]:
    """The record seen by ``n`` cameras: its own turned about the scene's up axis through the
    centre of the object's bounding box, each with its own rasterized rest depth."""
    from dataclasses import replace

    from .render.raster import rasterize

    mesh = rec.mesh
    nodes = mesh.surface_nodes
    lut = np.full(mesh.n_nodes, -1, dtype=np.int64)
    lut[nodes] = np.arange(len(nodes))
    centre = 0.5 * (mesh.points.min(axis=0) + mesh.points.max(axis=0))
    axis = np.asarray(getattr(rec.scene.camera, "up", (0.0, 0.0, 1.0)), dtype=float)
    if mesh.points.shape[1] == 2:  # a drum head lies in z = 0: turn about its normal
        axis = np.array([0.0, 0.0, 1.0])
    out = []
    for i in range(n):
        camera = turned_camera(rec.camera, np.radians(spread_deg * i / n), axis, centre)
        depth = rasterize(camera, _points3(mesh.points[nodes]), lut[mesh.surface]).depth
        out.append(replace(rec, camera=camera, depth=depth))
    return out


def _points3(points: np.ndarray) -> np.ndarray:
    return points if points.shape[1] == 3 else np.column_stack([points,
                                                                np.zeros(len(points))])


def turned_camera(camera, angle: float, axis: np.ndarray, centre: np.ndarray):
    """``camera`` carried around the object: turned by ``angle`` (radians) about ``axis``
    through ``centre`` (the same intrinsics; it keeps looking at the same point of the object
    turned with it).

    >>> from vvtbench.render import Camera
    >>> cam = Camera.look_at((1.0, 0, 0), (0, 0, 0), fx=100.0, width=64, height=64)
    >>> back = turned_camera(cam, np.pi, np.array([0, 0, 1.0]), np.zeros(3))
    >>> back.project([0.0, 0.0, 0.0]).round(6).tolist(), (-back.R.T @ back.t).round(6).tolist()
    ([31.5, 31.5], [-1.0, 0.0, 0.0])
    """
    from scipy.spatial.transform import Rotation

    from .render import Camera

    axis = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    Q = Rotation.from_rotvec(angle * axis).as_matrix()
    R = camera.R @ Q.T
    t = camera.t + camera.R @ centre - R @ centre
    return Camera(camera.K, R, t, camera.width, camera.height)


def observed_dof_fraction(P, model: ParametricModel) -> float:
    """The fraction of the inference model's free DOFs the observation operator sees: the rank
    of ``P`` over ``n_free`` (each row moves one vertex: the rank is the sum over vertices of
    the rank of their rows; a vertex seen in one view has rank 2 for a solid, one seen from
    two directions 3)."""
    import scipy.sparse as sp

    P = sp.csr_matrix(P)
    d = model.mesh.dofs_per_node
    node_of_col = np.asarray(model.free_dofs) // d
    coo = P.tocoo()
    rows_by_node: dict[int, set[int]] = {}
    for r, c in zip(coo.row, coo.col, strict=True):
        rows_by_node.setdefault(int(node_of_col[c]), set()).add(int(r))
    rank = 0
    for node, rows in rows_by_node.items():
        cols = np.flatnonzero(node_of_col == node)
        block = P[sorted(rows)][:, cols].toarray()
        rank += int(np.linalg.matrix_rank(block))
    return rank / max(1, model.n_free)


def _observed_view(rec: _Record, model: ParametricModel, opts: ObserveOptions,
                   scale: np.ndarray):
    """(camera, visible nodes, P, camera meta) of the inference mesh seen in the video."""
    from .modes.sampling import camera_from_clicks, observation_operator, visible_vertices

    mesh = model.mesh
    true_points = mesh.points / scale
    depth = rec.depth if opts.visibility == "depth" else None
    if opts.visibility == "depth" and depth is None:
        raise ObserveError(f"{rec.origin}: visibility 'depth' needs the rest depth buffer "
                           "(image/depth), which this source lacks; use visibility='normals'")
    camera = rec.camera
    visible = visible_vertices(true_points, mesh.surface, camera, exclude=model.fixed_nodes,
                               depth_buffer=depth)
    meta: dict[str, Any] = {"camera_source": "sample", "visibility": opts.visibility}
    if opts.clicks is not None:
        camera, rms = camera_from_clicks(opts.clicks, true_points, camera.width, camera.height)
        seen = true_points[visible]
        uv = camera.project(seen)
        inside = ((camera.depth(seen) > 0) & (uv[:, 0] >= -0.5)
                  & (uv[:, 0] <= camera.width - 0.5) & (uv[:, 1] >= -0.5)
                  & (uv[:, 1] <= camera.height - 0.5))
        visible = visible[inside]
        meta.update(camera_source="clicks", clicks_file=str(opts.clicks), clicks_rms_px=rms)
    if visible.size == 0:
        raise ObserveError(f"{rec.origin}: no inference-mesh vertex is visible from the camera")
    d = mesh.dofs_per_node
    P = observation_operator(camera, true_points, visible, dofs_per_node=d,
                             dof_index=model.free_index, n_columns=model.n_free, scale=scale)
    meta["camera"] = camera.to_dict()
    return camera, np.asarray(visible, dtype=np.int64), P, meta


def _observe_record(rec: _Record, opts: ObserveOptions) -> tuple[InverseProblem, Truth]:
    scene = rec.scene
    scale = _scale_vector(opts.geometry_scale)
    rec, n_rigid = _without_rigid_body_modes(rec)
    n_true = len(rec.eigenvalues)
    if opts.observation == "true" and opts.n_modes > n_true:
        raise ObserveError(f"n_modes: asked for {opts.n_modes} modes; {rec.origin} holds "
                           f"{n_true} (simulation.n_modes)")
    k = n_true if opts.observation == "extracted" else opts.n_modes
    model = _inference_model(rec, opts, scale)
    cameras, visible, P, cam_meta, views = _observed_views(rec, model, opts, scale)
    camera = cameras[0]
    U = _true_modes(rec, model, scale, k).reshape(-1, k)[model.free_dofs]
    gamma = (P @ U).T
    norms = np.linalg.norm(gamma, axis=1)
    if np.any(norms == 0):
        raise ObserveError(f"{rec.origin}: true modes {np.flatnonzero(norms == 0).tolist()} "
                           "are invisible (zero image motion at every visible vertex)")
    gamma = gamma / norms[:, None]
    U = U / norms
    lam = rec.eigenvalues[:k]

    membrane = rec.mesh.dofs_per_node == 1
    m = scene.material
    base_w = m.tension if membrane else m.E
    base_v = m.areal_density if membrane else m.rho
    w_true, v_true = _voxel_truth(rec, model, scale)
    meta = {
        "observation": opts.observation,
        "geometry_scale": scale.tolist(),
        "inference_shape": list(opts.inference_shape or default_voxel_shape(scene.geometry.kind)),
        "inference_element": model.mesh.element,
        "nu": model.nu if np.isscalar(model.nu) else float(np.mean(model.nu)),
        "n_visible": int(len(visible)),
        "rigid_body_modes_left_out": n_rigid,
        **cam_meta,
    }
    truth_meta = {"scene": scene.name, "source": rec.origin,
                  "simulation_element": rec.mesh.element,
                  "simulation_cells": int(rec.mesh.n_elements)}
    problem = InverseProblem(
        model=model, gamma=gamma, eigenvalues=lam, P=P, visible_nodes=visible,
        w0=float(base_w if opts.w0 is None else opts.w0),
        v0=float(base_v if opts.v0 is None else opts.v0),
        w_mean=float(base_w if opts.w_mean is None else opts.w_mean),
        kind="membrane" if membrane else "solid", meta=meta)
    truth = Truth(w=w_true, v=v_true, modes_3d=U, eigenvalues=lam, matched=np.arange(k),
                  image_modes=gamma, true_eigenvalues=lam, meta=truth_meta)
    if opts.observation == "true":
        return problem, truth
    if opts.views > 1:
        return _with_joint_extracted(problem, truth, views, cameras, opts)
    return _with_extracted(problem, truth, _modesets(rec, opts), camera, opts)


def _modesets(rec: _Record, opts: ObserveOptions) -> list:
    from .modes import ModeSet, extract_modes

    if opts.modes:
        return [m if isinstance(m, ModeSet) else ModeSet.load(m) for m in opts.modes]
    packed = list(rec.packed_modes()) if rec.packed_modes is not None else []
    if packed:
        return packed
    if rec.video is None:
        raise ObserveError(f"{rec.origin}: observation 'extracted' needs a video or extracted "
                           "modes (ObserveOptions.modes); this source has neither")
    frames, fps = rec.video()
    return [extract_modes(frames, fps, **opts.extract)]


def _with_extracted(problem: InverseProblem, truth: Truth, modesets: list, camera: Any,
                    opts: ObserveOptions) -> tuple[InverseProblem, Truth]:
    """The problem observing extracted modes; each is paired with a true mode by MAC."""
    gamma, freqs, snr, info = _sample_extracted(problem, modesets, camera, opts)
    return _matched(problem, truth, gamma, freqs, snr, info)


def _matched(problem: InverseProblem, truth: Truth, gamma: np.ndarray, freqs: np.ndarray,
             snr: np.ndarray, info: dict) -> tuple[InverseProblem, Truth]:
    """The problem observing the modes ``gamma`` (unit rows), each paired with a true mode by
    MAC (the truth's 3-D modes signed and ordered to match)."""
    from scipy.optimize import linear_sum_assignment

    from .modes.mac import mac_matrix

    mac = mac_matrix(gamma, truth.image_modes)
    rows, cols = linear_sum_assignment(-mac)
    order = np.argsort(rows)
    rows, cols = rows[order], cols[order]
    sign = np.sign(np.einsum("ij,ij->i", gamma[rows], truth.image_modes[cols]) + 1e-300)
    gamma, freqs, snr = gamma[rows], freqs[rows], snr[rows]
    true_f = np.sqrt(np.clip(truth.true_eigenvalues[cols], 0, None)) / (2 * np.pi)
    meta = {**problem.meta, **info, "extracted_frequencies_hz": freqs.tolist()}
    problem = replace(problem, gamma=gamma, eigenvalues=(2 * np.pi * freqs) ** 2, meta=meta,
                      mode_snr=snr)
    truth = replace(truth, modes_3d=truth.modes_3d[:, cols] * sign[None, :],
                    eigenvalues=(2 * np.pi * true_f) ** 2, matched=cols,
                    extraction_mac=mac[rows, cols], meta=dict(truth.meta))
    return problem, truth


def _with_joint_extracted(problem: InverseProblem, truth: Truth, views: list[_Record],
                          cameras: list, opts: ObserveOptions) -> tuple[InverseProblem, Truth]:
    """The problem observing modes extracted from every view's video and joined
    (:func:`vvtbench.modes.joint.extract_joint`), sampled at each view's visible vertices and
    stacked like ``P``."""
    from .modes import ModeSet, extract_modes, sample_modes
    from .modes.joint import frame_range, joint_modes, modal_phasors

    sources, rates = [], []
    for view in views:
        if view.video is None:
            raise ObserveError(f"{view.origin}: observation 'extracted' with views > 1 needs "
                               "every view's video; this sample has none (modes-only)")
        source, fps = view.video()
        sources.append(source)
        rates.append(float(fps))
    offsets = [v.time_offset_s for v in views]
    if opts.modes:  # one mode set per view, extracted elsewhere
        sets = [m if isinstance(m, ModeSet) else ModeSet.load(m) for m in opts.modes]
    else:  # as vvtbench.modes.joint.extract_joint does, each view's modes checked first
        sets = [extract_modes(src, rates[0], **opts.extract) for src in sources]
    empty = [v for v, ms in enumerate(sets) if len(ms) == 0]
    if len(empty) == len(sets):
        raise ObserveError(f"no modes were extracted from the views' videos (none in any of "
                           f"the {len(sets)} views)")
    if empty:
        which = (f"the video of view {empty[0]}" if len(empty) == 1 else
                 f"the videos of views {', '.join(map(str, empty))}")
        raise ObserveError(f"no modes were extracted from {which} (of views 0 to "
                           f"{len(sets) - 1}); joined views need modes in every view")
    start, stop = frame_range(opts.extract)  # each view's phasors, to join the views
    phasors = [modal_phasors(src, fps, ms, start=start, stop=stop)
               for src, fps, ms in zip(sources, rates, sets, strict=True)]
    joint = joint_modes(sets, phasors, freq_tol=opts.merge_freq_tol / 2,
                        time_offsets_s=offsets)
    scale = np.asarray(problem.meta["geometry_scale"], dtype=float)
    counts = np.cumsum([0, *problem.meta["n_visible_per_view"]])
    points = problem.mesh.points[problem.visible_nodes] / scale
    sampled = [sample_modes(joint.modesets[v].shapes, cameras[v].project(
        points[counts[v]:counts[v + 1]])) for v in range(len(views))]
    gamma = joint.stack(sampled)
    keep = np.flatnonzero(np.linalg.norm(gamma, axis=1) > 0)
    lowest = keep[np.argsort(joint.frequencies_hz[keep], kind="stable")][: opts.n_modes]
    if lowest.size == 0:
        raise ObserveError("no modes were extracted from the views' videos")
    info = {"source": "extracted from every view's video and joined",
            "n_modes_extracted": int(len(joint)),
            "n_modes_extracted_per_view": [len(m) for m in joint.modesets],
            "views_seen": (joint.members[lowest] >= 0).sum(axis=1).tolist(),
            "view_phase_deg": joint.metadata["phase_deg"]}
    return _matched(problem, truth, gamma[lowest], joint.frequencies_hz[lowest],
                    joint.snr[lowest], info)


def _sample_extracted(problem: InverseProblem, modesets: list, camera: Any,
                      opts: ObserveOptions):
    """(gamma (k, 2 n_vis) unit rows, frequencies (k,), spectral SNR (k,), meta) of the
    lowest extracted modes sampled at the visible vertices' pixels. A mode merged from
    several videos has the sum of its sources' SNRs (independent noise)."""
    from .modes import merge_modesets, sample_modes

    sets = list(modesets)
    if not sets:
        raise ObserveError("no mode sets given")
    if len(sets) == 1:
        ms = sets[0].select(~sets[0].camera_shake)
        snr = ms.line_snr()
    else:
        ms = merge_modesets(sets, freq_tol=opts.merge_freq_tol, min_mac=opts.merge_min_mac)
        source_snr = [s.line_snr()[~s.camera_shake] for s in sets]  # merge drops shake
        snr = np.array([sum(source_snr[i][j] for i, j in members)
                        for members in ms.metadata["members"]], dtype=float)
    n_extracted = len(ms)
    lowest = np.argsort(ms.frequencies_hz)[: opts.n_modes]
    ms, snr = ms.select(lowest), snr[lowest]
    if len(ms) == 0:
        raise ObserveError("no modes were extracted from the video")
    scale = np.asarray(problem.meta["geometry_scale"], dtype=float)
    uv = camera.project(problem.mesh.points[problem.visible_nodes] / scale)
    gamma = sample_modes(ms.shapes, uv)
    norms = np.linalg.norm(gamma, axis=1)
    keep = norms > 0
    info = {"source": "extracted from the video", "n_modes_extracted": int(n_extracted)}
    return gamma[keep] / norms[keep, None], ms.frequencies_hz[keep], snr[keep], info


def _voxel_truth(rec: _Record, model: ParametricModel, scale: np.ndarray):
    """Per parameter of ``model``: the mean of the simulation's per-element material over each
    voxel, weighted by the volume of overlap of element and voxel (the simulation mesh mapped
    onto the inference geometry); an active voxel that no simulation element reaches (only
    possible when the inference mesh covers more than the body) takes the nearest element's
    value."""
    from .fem.voxels import overlap_matrix, voxel_average

    vmap = model.voxel_map
    overlap = overlap_matrix(rec.mesh, vmap.grid, scale=scale)
    out = []
    for values in (rec.stiffness, rec.density):
        res = np.asarray(voxel_average(overlap, values), dtype=float)[vmap.active]
        empty = ~np.isfinite(res)
        if empty.any():
            from scipy.spatial import cKDTree

            centers = vmap.grid.centers()[vmap.active[empty]]
            _, nearest = cKDTree(rec.mesh.centroids * scale).query(centers)
            res[empty] = values[nearest]
        out.append(res)
    return out[0], out[1]


# --------------------------------------------------------------------------- truth of a sample


def sample_truth(sample: Any, problem: InverseProblem) -> tuple[InverseProblem, Truth]:
    """The truth of ``sample`` on a problem built without it, and that problem's modes paired.

    For a problem observed from what a field user has (typically :func:`observe` of a
    :class:`RealVideo` whose video, camera and object come from the sample), this is what
    :func:`observe` of the sample itself returns as truth, computed on ``problem``'s
    inference mesh instead of one built from the scene.

    Parameters
    ----------
    sample : a sample folder or :class:`~vvtbench.samples.reader.Sample`, or an entry of an
        exported dataset.
    problem : an :class:`~vvtbench.solving.problem.InverseProblem` whose inference mesh lies in the
        sample's coordinates (metres, no geometry scale) and whose ``gamma`` rows are unit
        image-space modes.

    Returns
    -------
    (InverseProblem, Truth)
        ``problem`` with its modes ordered and signed to match the truth (``mode_snr``
        missing is NaN); the truth holds the sample's material averaged over each voxel of
        the problem's grid, its rigid-body-free modes at the problem's nodes seen through
        ``problem.P`` (the modes ``P`` does not see at all left out), and each observed
        mode paired with a true one by MAC (``matched``, ``extraction_mac``).

    Raises
    ------
    DatasetError
        When the sample lacks an array the truth needs.
    ObserveError
        When ``sample`` cannot be read as a sample.
    """
    if isinstance(sample, (str, Path)) and Path(sample).is_dir():
        from .samples.reader import open_sample

        sample = open_sample(Path(sample))
    if not (hasattr(sample, "scene") and hasattr(sample, "info")):
        raise ObserveError(f"cannot take the truth of a {type(sample).__name__} ({sample}): "
                           "give a sample folder, a Sample or an entry of an exported dataset")
    rec, _ = _without_rigid_body_modes(_record_from_sample(sample))
    scene = rec.scene
    model = problem.model
    unit = np.ones(3)
    k = len(rec.eigenvalues)
    U = _true_modes(rec, model, unit, k).reshape(-1, k)[model.free_dofs]
    gamma = (problem.P @ U).T
    norms = np.linalg.norm(gamma, axis=1)
    seen = norms > 0
    U, gamma = U[:, seen] / norms[seen], gamma[seen] / norms[seen, None]
    lam = rec.eigenvalues[:k][seen]
    w_true, v_true = _voxel_truth(rec, model, unit)
    truth = Truth(w=w_true, v=v_true, modes_3d=U, eigenvalues=lam, matched=np.arange(len(lam)),
                  image_modes=gamma, true_eigenvalues=lam,
                  meta={"scene": scene.name, "source": rec.origin,
                        "simulation_element": rec.mesh.element,
                        "simulation_cells": int(rec.mesh.n_elements)})
    freqs = np.sqrt(np.asarray(problem.eigenvalues, dtype=float)) / (2 * np.pi)
    snr = problem.mode_snr if problem.mode_snr is not None else np.full(len(freqs), np.nan)
    info = {key: problem.meta[key] for key in ("source", "n_modes_extracted")
            if key in problem.meta}
    return _matched(problem, truth, np.asarray(problem.gamma), freqs, np.asarray(snr), info)


# --------------------------------------------------------------------------- real videos


def _observe_real(real: RealVideo, opts: ObserveOptions) -> InverseProblem:
    """The problem of a real video: no truth, modes extracted, camera given or clicked."""
    from .modes import ModeSet
    from .modes.sampling import camera_from_clicks, observation_operator, visible_vertices

    if opts.observation != "extracted":
        raise ObserveError("a real video has no true modes: use observation='extracted'")
    if not np.allclose(_scale_vector(opts.geometry_scale), 1.0):
        raise ObserveError("geometry_scale applies to synthetic samples only")
    mesh = real.mesh
    kind = "membrane" if mesh.dofs_per_node == 1 else "solid"
    shape = opts.inference_shape or default_voxel_shape("drum" if kind == "membrane" else "box")
    vmap = VoxelMap.from_mesh(mesh, tuple(shape))
    nu = float(real.nu if opts.nu is None else opts.nu)
    model = ParametricModel(mesh, vmap, nu=nu, fixed_nodes=np.asarray(real.fixed_nodes))
    camera = real.camera
    meta: dict[str, Any] = {"camera_source": "given"}
    clicks = opts.clicks or real.clicks
    if clicks is not None:
        if real.width is None or real.height is None:
            raise ObserveError("RealVideo with clicks needs width and height (video pixels)")
        camera, rms = camera_from_clicks(clicks, mesh.points, real.width, real.height)
        meta.update(camera_source="clicks", clicks_file=str(clicks), clicks_rms_px=rms)
    if camera is None:
        raise ObserveError("RealVideo needs a camera or a clicks file")
    visible = visible_vertices(mesh.points, mesh.surface, camera, exclude=model.fixed_nodes)
    if visible.size == 0:
        raise ObserveError("no mesh vertex is visible from the camera")
    P = observation_operator(camera, mesh.points, visible, dofs_per_node=mesh.dofs_per_node,
                             dof_index=model.free_index, n_columns=model.n_free)
    sets = [m if isinstance(m, ModeSet) else ModeSet.load(m)
            for m in (opts.modes or real.modes)]
    stub = InverseProblem(model=model, gamma=np.zeros((1, P.shape[0])), eigenvalues=[1.0], P=P,
                          visible_nodes=visible, meta={"geometry_scale": [1.0, 1.0, 1.0]})
    gamma, freqs, snr, info = _sample_extracted(stub, sets, camera, opts)
    meta.update(info, observation="extracted", n_visible=int(len(visible)),
                inference_shape=list(shape), inference_element=mesh.element, nu=nu,
                camera=camera.to_dict(), geometry_scale=[1.0, 1.0, 1.0],
                extracted_frequencies_hz=freqs.tolist())
    return InverseProblem(model=model, gamma=gamma, eigenvalues=(2 * np.pi * freqs) ** 2, P=P,
                          visible_nodes=visible, w0=real.w0, v0=real.v0, w_mean=real.w0,
                          kind=kind, meta=meta, mode_snr=snr)
