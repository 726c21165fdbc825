"""From a Scene to a simulated object: mesh, material fields, eigenmodes, transient response.

This is the simulation backend: it reads only the scene (pure data) and returns plain arrays.

>>> from vvtbench.scene.scene import parse_scene
>>> scene = parse_scene({"name": "t", "geometry": {"kind": "box", "cells": [3, 3, 3]},
...                      "simulation": {"n_modes": 4, "duration": 0.01}})
>>> result = simulate(scene)
>>> result.frequencies_hz.shape, result.displacements.shape[0]
((4,), 20)
"""

from __future__ import annotations

import functools
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..fem.assembly import ParametricModel
from ..fem.mesh import Mesh, box_mesh, drum_mesh, load_surface, tet_mesh
from ..fem.modal import Factorization, Modes, eigenmodes, single_threaded
from ..fem.transient import damping_ratios, modal_coordinates, modal_damping, newmark_response
from ..scene.scene import Chirp, ForceFile, Impulse, Scene, SceneError


@dataclass(frozen=True)
class MaterialFields:
    """Per-element material: stiffness is E (Pa) or tension (N/m); density is rho (kg/m^3) or
    areal density (kg/m^2); nu is Poisson's ratio (unused by membranes)."""

    stiffness: np.ndarray
    density: np.ndarray
    nu: np.ndarray


@dataclass
class SimulationResult:
    """Everything the simulator computed for one scene."""

    scene: Scene
    mesh: Mesh
    fields: MaterialFields
    model: ParametricModel
    modes: Modes
    alpha: float
    beta: float
    times: np.ndarray = field(default_factory=lambda: np.zeros(0))
    surface_nodes: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    modal_coordinates: np.ndarray | None = None
    observed_modes: np.ndarray | None = None
    direct_displacements: np.ndarray | None = None
    truncation_error: float | None = None
    timings: dict[str, float] = field(default_factory=dict)

    @property
    def has_transient(self) -> bool:
        return self.modal_coordinates is not None or self.direct_displacements is not None

    def displacement_frames(self, start: int = 0, stop: int | None = None) -> np.ndarray:
        """Surface-node displacements of frames ``start:stop``: (n, n_surface, dofs_per_node)
        float32 (m). Modal results keep only the modal coordinates (frames x modes), so any
        chunk of a long response costs memory for that chunk alone."""
        if not self.has_transient:
            raise ValueError("no transient response: the scene's excitation kind is 'none'")
        d = self.mesh.dofs_per_node
        if self.direct_displacements is not None:
            u = self.direct_displacements[start:stop]
        else:
            q = self.modal_coordinates[start:stop]
            u = (q @ self.observed_modes.T).astype(np.float32)
        return u.reshape(len(u), len(self.surface_nodes), d)

    @property
    def displacements(self) -> np.ndarray | None:
        """All frames of :meth:`displacement_frames`, or None without a transient."""
        return self.displacement_frames() if self.has_transient else None

    @property
    def frequencies_hz(self) -> np.ndarray:
        return self.modes.frequencies_hz

    @property
    def damping_ratios(self) -> np.ndarray:
        return damping_ratios(self.modes.omega, self.alpha, self.beta)


def build_mesh(scene: Scene) -> Mesh:
    """The simulation mesh of a scene, with its built-in and custom node sets."""
    g = scene.geometry
    if g.kind == "box":
        mesh = box_mesh(g.cells, g.size, g.order)
    elif g.kind == "drum":
        mesh = drum_mesh(g.shape, g.size, g.cells)
    else:
        path = g.path if g.path == "bunny" else str(scene.resolve_path(g.path))
        try:
            v, f = load_surface(path, g.up_axis, g.scale_to, g.target_faces)
        except (FileNotFoundError, ValueError) as error:
            raise SceneError(f"{scene.source}: key 'geometry.path': {error}") from None
        mesh = tet_mesh(v, f, g.edge_length_fac, g.epsilon, g.stop_energy, g.coarsen, g.order)
    extra = {}
    for name, region in scene.boundary.node_sets.items():
        if region.indices is not None:
            idx = np.asarray(region.indices, dtype=np.int64)
            if idx.size and idx.max() >= mesh.n_nodes:
                raise SceneError(
                    f"{scene.source}: key 'boundary.node_sets.{name}.indices': node index "
                    f"{idx.max()} out of range; the mesh has {mesh.n_nodes} nodes"
                )
        else:
            lo, hi = np.asarray(region.box_min), np.asarray(region.box_max)
            idx = np.flatnonzero(np.all((mesh.points >= lo) & (mesh.points <= hi), axis=1))
            if idx.size == 0:
                raise SceneError(
                    f"{scene.source}: key 'boundary.node_sets.{name}': the box "
                    f"{list(region.box_min)}..{list(region.box_max)} holds no mesh node; the "
                    f"body spans {_extent(mesh)}; allowed: a box around at least one node"
                )
        extra[name] = idx
    return mesh.with_node_sets(extra) if extra else mesh


def material_fields(scene: Scene, mesh: Mesh) -> MaterialFields:
    """Per-element material values: base, then defects in order (by element centroid), or
    read from ``material.field_file``."""
    from ..solving.plugins import refuse_when_sealed

    refuse_when_sealed("a scene's material fields")
    m = scene.material
    n = mesh.n_elements
    drum = scene.geometry.kind == "drum"
    if m.field_file is not None:
        return _fields_from_file(scene, n, drum)
    stiffness = np.full(n, m.tension if drum else m.E)
    density = np.full(n, m.areal_density if drum else m.rho)
    nu = np.full(n, m.nu)
    centroids = mesh.centroids
    for i, defect in enumerate(m.defects):
        inside = defect.contains(centroids)
        if not inside.any():
            raise SceneError(_empty_defect_message(scene, mesh, i))
        if drum:
            if defect.tension is not None:
                stiffness[inside] = defect.tension
            if defect.areal_density is not None:
                density[inside] = defect.areal_density
        else:
            if defect.E is not None:
                stiffness[inside] = defect.E
            if defect.rho is not None:
                density[inside] = defect.rho
            if defect.nu is not None:
                nu[inside] = defect.nu
    return MaterialFields(stiffness, density, nu)


def _fields_from_file(scene: Scene, n: int, drum: bool) -> MaterialFields:
    path = scene.resolve_path(scene.material.field_file)
    where = f"{path} (from key 'material.field_file')"
    try:
        data = np.load(path)
    except (OSError, ValueError) as error:
        raise SceneError(f"{where}: cannot read an .npz array file: {error}") from None
    keys = ("tension", "areal_density") if drum else ("E", "rho")
    allowed = ", ".join(keys + (() if drum else ("nu",)))
    out = {}
    for key in keys + (() if drum else ("nu",)):
        if key not in data:
            if key == "nu":
                out[key] = np.full(n, scene.material.nu)
                continue
            raise SceneError(f"{where}: missing array '{key}'; arrays read: {allowed}")
        arr = np.asarray(data[key], dtype=float).ravel()
        if arr.shape != (n,):
            raise SceneError(
                f"{where}: array '{key}' has {arr.size} values; the mesh has {n} elements"
            )
        if not np.all(np.isfinite(arr)) or (key != "nu" and np.any(arr <= 0)):
            raise SceneError(f"{where}: array '{key}' must be finite and positive")
        out[key] = arr
    nu = out.get("nu", np.full(n, scene.material.nu))
    return MaterialFields(out[keys[0]], out[keys[1]], nu)


def fixed_nodes(scene: Scene, mesh: Mesh) -> np.ndarray:
    """Union of the node sets named in ``boundary.fixed`` ("none" fixes nothing)."""
    names = [s for s in scene.fixed_sets if s != "none"]
    unknown = [s for s in names if s not in mesh.node_sets]
    if unknown:
        raise SceneError(
            f"{scene.source}: key 'boundary.fixed': unknown node set(s) {unknown}; allowed for "
            f"this geometry: none, {', '.join(sorted(mesh.node_sets))}"
        )
    if not names:
        return np.zeros(0, np.int64)
    return np.unique(np.concatenate([mesh.node_sets[s] for s in names]))


def build_model(scene: Scene, mesh: Mesh, fields: MaterialFields) -> ParametricModel:
    """Per-element parametric model (each element its own parameter)."""
    return ParametricModel(mesh, nu=fields.nu, fixed_nodes=fixed_nodes(scene, mesh))


def load_nodes(scene: Scene, mesh: Mesh) -> np.ndarray:
    """Nodes within ``excitation.radius`` of ``excitation.at`` (the nearest node if none).

    ``at`` must lie on or in the body: within ``radius`` plus one element size (the largest
    element's bounding-box diagonal) of a node; farther away is a SceneError, not a snap."""
    at = np.asarray(scene.excitation.at, dtype=float)
    dist = np.linalg.norm(mesh.points - at, axis=1)
    nodes = np.flatnonzero(dist <= scene.excitation.radius)
    if nodes.size:
        return nodes
    nearest = int(np.argmin(dist))
    h = element_size(mesh)
    if dist[nearest] > scene.excitation.radius + h:
        raise SceneError(
            f"{scene.source}: key 'excitation.at': {list(scene.excitation.at)} is "
            f"{dist[nearest]:.3g} m from the body (nearest node at "
            f"{[round(float(x), 6) for x in mesh.points[nearest]]}); allowed: a point within "
            f"radius + one element size ({scene.excitation.radius:g} + {h:.3g} m) of a node; "
            f"the body spans {_extent(mesh)}"
        )
    return np.array([nearest])


def element_size(mesh: Mesh) -> float:
    """The largest element's bounding-box diagonal (m): every point of the body lies within
    this distance of a node."""
    corners = mesh.points[mesh.cells]
    return float(np.linalg.norm(np.ptp(corners, axis=1), axis=1).max())


def _extent(mesh: Mesh) -> str:
    lo, hi = mesh.points.min(axis=0), mesh.points.max(axis=0)
    return ", ".join(f"{c} {a:.4g}..{b:.4g}" for c, a, b in zip("xyz", lo, hi, strict=True)) + " m"


def _defect_bounds(defect) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned bounding box of a defect region."""
    c, s = np.asarray(defect.center, dtype=float), np.asarray(defect.size, dtype=float)
    if defect.shape == "box":
        half = s / 2
    elif defect.shape == "sphere":
        half = np.full(3, s[0])
    elif defect.shape == "ellipsoid":
        half = s
    else:
        half = np.full(3, s[0])
        half["xyz".index(defect.axis)] = s[1] / 2
    return c - half, c + half


def _empty_defect_message(scene: Scene, mesh: Mesh, i: int) -> str:
    defect = scene.material.defects[i]
    lo, hi = _defect_bounds(defect)
    body_lo, body_hi = mesh.points.min(axis=0), mesh.points.max(axis=0)
    where = f"{scene.source}: key 'material.defects[{i}]'"
    what = f"the {defect.shape} defect at {list(defect.center)} (size {list(defect.size)} m)"
    if np.any(hi < body_lo) or np.any(lo > body_hi):
        return (
            f"{where}: {what} lies entirely outside the body, which spans {_extent(mesh)}; "
            "allowed: a region containing at least one element centroid"
        )
    return (
        f"{where}: {what} contains no element centroid (elements are up to "
        f"{element_size(mesh):.3g} m across, or it falls outside the body's surface); allowed: "
        "a region containing at least one element centroid"
    )


def load_vector(
    scene: Scene, mesh: Mesh, model: ParametricModel
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(load over the free DOFs: unit total along the direction, load nodes, direction)."""
    nodes = load_nodes(scene, mesh)
    d = mesh.dofs_per_node
    direction = np.asarray(scene.excitation.direction, dtype=float)
    direction = direction / np.linalg.norm(direction)
    if d == 1:
        direction = np.array([1.0 if direction[2] >= 0 else -1.0])
    full = np.zeros(mesh.n_dofs)
    full[mesh.dofs_of(nodes)] = np.tile(direction / len(nodes), len(nodes))
    f = model.restrict(full)
    if not np.any(f):
        raise SceneError(
            f"{scene.source}: key 'excitation.at': every loaded node is fixed; "
            "move the load off the fixed boundary"
        )
    return f, nodes, direction


def force_signal(scene: Scene):
    """(f(t), suggested integration step) for a force excitation."""
    s = scene.excitation.signal
    if isinstance(s, Chirp):
        rate = (s.f1 - s.f0) / s.duration

        def f(t):
            tau = np.asarray(t) - s.start
            on = (tau >= 0) & (tau <= s.duration)
            phase = 2 * np.pi * (s.f0 * tau + rate * tau**2 / 2)
            return np.where(on, s.amplitude * np.sin(phase), 0.0)

        return f, 1.0 / (20 * max(s.f0, s.f1))
    if isinstance(s, Impulse):

        def f(t):
            tau = np.asarray(t) - s.start
            on = (tau >= 0) & (tau <= s.width)
            return np.where(on, s.amplitude * np.sin(np.pi * tau / s.width), 0.0)

        return f, s.width / 20
    assert isinstance(s, ForceFile)
    path = scene.resolve_path(s.path)
    ts, fs = _read_force_file(path)
    return (lambda t: np.interp(t, ts, fs, left=0.0, right=0.0)), float(np.min(np.diff(ts)))


def _read_force_file(path: Path) -> tuple[np.ndarray, np.ndarray]:
    where = f"{path} (from key 'excitation.signal.path')"
    try:
        if path.suffix == ".csv":
            arr = np.loadtxt(path, delimiter=",", ndmin=2)
        elif path.suffix == ".npz":
            z = np.load(path)
            arr = np.column_stack([z["time"], z["force"]])
        else:
            arr = np.load(path)
    except (OSError, ValueError, KeyError) as error:
        raise SceneError(
            f"{where}: cannot read a force series (.csv/.npy with columns time, force, or .npz "
            f"with arrays time and force): {error}"
        ) from None
    if arr.ndim != 2 or arr.shape[1] != 2 or len(arr) < 2:
        raise SceneError(f"{where}: need at least two rows of (time s, force N); got {arr.shape}")
    bad = ~np.isfinite(arr)
    if bad.any():
        row, col = np.argwhere(bad)[0]
        raise SceneError(
            f"{where}: {int(bad.sum())} non-finite value(s), the first {arr[row, col]} in row "
            f"{row} ({('time', 'force')[col]}); allowed: finite times (s) and forces (N)"
        )
    if np.any(np.diff(arr[:, 0]) <= 0):
        raise SceneError(f"{where}: times must be strictly increasing")
    return arr[:, 0], arr[:, 1]


# Peak memory of a modal analysis, fitted to measured peaks (ru_maxrss over the interpreter's;
# hex8, hex27 and square-drum meshes of 900 to 160k DOFs, 10 to 400 modes, CHOLMOD
# factorization; within 15 % above 200 MiB): the per-element matrices and the assembly pattern
# cost ~B_ENTRY bytes per element-matrix entry, the block eigen-solver ~B_MODE bytes per DOF
# and mode, the sparse factorization ~B_FILL_3D N^(4/3) bytes in 3-D (nested-dissection fill)
# and ~B_FILL_2D N log2 N in 2-D. SuperLU (no scikit-sparse) fills in more.
B_ENTRY = 110.0
B_MODE = 140.0
B_FILL_3D = 40.0
B_FILL_2D = 70.0
GIB = 2.0**30
_ELEMENT_DOFS = {"hex8": 24, "hex27": 81, "tet4": 12, "tet10": 30, "tri3": 3}


def mesh_counts(scene: Scene, mesh: Mesh | None = None) -> tuple[str, int, int, int]:
    """(element type, elements, nodes, DOFs) of the scene's simulation mesh: from the geometry
    alone for boxes and drums (nothing is built), else from the given tetrahedral mesh."""
    g = scene.geometry
    if mesh is not None:
        return mesh.element, mesh.n_elements, mesh.n_nodes, mesh.n_dofs
    if g.kind == "box":
        o = g.order
        nodes = math.prod(o * c + 1 for c in g.cells)
        return ("hex8" if o == 1 else "hex27"), math.prod(g.cells), nodes, 3 * nodes
    if g.kind == "drum":
        c = g.cells
        if g.shape == "square":
            return "tri3", 2 * c * c, (c + 1) ** 2, (c + 1) ** 2
        nodes = 1 + 3 * c * (c + 1)
        return "tri3", 6 * c * c, nodes, nodes
    raise ValueError("a mesh geometry's size is known only after tetrahedralization")


def estimate_memory(element: str, n_elements: int, n_dofs: int, n_modes: int) -> float:
    """About how many bytes building the model and solving for ``n_modes`` modes needs."""
    nd = _ELEMENT_DOFS.get(element, 81)
    n = float(n_dofs)
    fill = B_FILL_2D * n * math.log2(max(n, 2.0)) if element == "tri3" else B_FILL_3D * n ** (4 / 3)
    return B_ENTRY * n_elements * nd * nd + B_MODE * n * n_modes + fill


def available_memory() -> float | None:
    """Bytes this process may still allocate: the system's available memory, lowered by a
    cgroup limit or an address-space rlimit when set; None when unknown."""
    limits = []
    try:
        import psutil

        limits.append(float(psutil.virtual_memory().available))
    except Exception:  # noqa: BLE001 - psutil is optional
        try:
            limits.append(float(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")))
        except (ValueError, OSError, AttributeError):
            pass
    try:
        text = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if text != "max":
            used = float(Path("/sys/fs/cgroup/memory.current").read_text())
            limits.append(float(text) - used)
    except (OSError, ValueError):
        pass
    try:
        import resource

        soft = resource.getrlimit(resource.RLIMIT_AS)[0]
        if soft != resource.RLIM_INFINITY:
            pages = int(Path("/proc/self/statm").read_text().split()[0])
            limits.append(float(soft - pages * os.sysconf("SC_PAGE_SIZE")))
    except (ImportError, OSError, ValueError):
        pass
    return max(min(limits), 0.0) if limits else None


def _transient_memory(scene: Scene, n_dofs: int) -> tuple[float, str]:
    """(bytes, the key to reduce) of the transient response's arrays."""
    sim = scene.simulation
    frames = int(round(sim.duration * sim.fps))
    k = sim.n_modes
    if sim.method == "newmark":
        return 4.0 * frames * n_dofs + 8.0 * 6 * n_dofs, "simulation.duration"
    sub = 1
    if scene.excitation.kind == "force":
        _, force_dt = force_signal(scene)
        sub = max(1, math.ceil((1 / sim.fps) / force_dt - 1e-9))
    fine = (frames - 1) * sub + 1
    key = "simulation.duration" if sub == 1 else "excitation.signal (its time step)"
    return 8.0 * frames * k * 2 + 8.0 * fine * (3 * k + 2), key


def check_problem_size(
    scene: Scene, mesh: Mesh | None = None, transient: bool = True, available=None
) -> float:
    """Estimated peak bytes of simulating the scene; a SceneError when it exceeds the memory
    this machine has available (``available`` bytes, default :func:`available_memory`), so a
    too-large problem fails in a second instead of with a MemoryError after minutes."""
    element, n_el, _, n_dofs = mesh_counts(scene, mesh)
    k = scene.simulation.n_modes
    model = estimate_memory(element, n_el, n_dofs, k)
    need, key = model, "geometry.cells" if scene.geometry.kind != "mesh" else "geometry"
    if B_MODE * n_dofs * k > model / 2:
        key += " or simulation.n_modes"
    if transient and scene.excitation.kind != "none":
        extra, tkey = _transient_memory(scene, n_dofs)
        if extra > need:
            key = tkey
        need += extra
    avail = available_memory() if available is None else available
    if avail is not None and need > avail:
        size = (
            "x".join(map(str, scene.geometry.cells)) if scene.geometry.kind == "box"
            else f"{n_el}-element"
        )
        raise SceneError(
            f"{scene.source}: key '{key.split(' ')[0]}': a {size} {element} mesh ({n_dofs} DOFs, "
            f"{k} modes{', transient' if transient and scene.excitation.kind != 'none' else ''}) "
            f"needs about {need / GIB:.3g} GiB, this machine has {avail / GIB:.3g} GiB "
            f"available; reduce {key}"
        )
    return need


def frame_times(scene: Scene) -> np.ndarray:
    n = int(round(scene.simulation.duration * scene.simulation.fps))
    return np.arange(n) / scene.simulation.fps


def _single_threaded(fn):
    """``fn`` run with one BLAS and OpenMP thread (:func:`vvtbench.fem.modal.single_threaded`):
    a scene simulated here, inside ``generate`` or anywhere else, gives the same bits whatever
    the number of cores."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with single_threaded():
            return fn(*args, **kwargs)

    return wrapper


@_single_threaded
def simulate(scene: Scene, transient: bool = True, method: str | None = None) -> SimulationResult:
    """Mesh, materials, the lowest ``simulation.n_modes`` modes and (optionally) the transient
    response at every surface node, sampled at the scene's frame rate. BLAS and OpenMP run on
    one thread, so the result does not depend on the number of cores."""
    timings: dict[str, float] = {}
    transient = transient and scene.excitation.kind != "none"
    if scene.geometry.kind != "mesh":
        check_problem_size(scene, transient=transient)
    t0 = time.perf_counter()
    mesh = build_mesh(scene)
    timings["mesh"] = time.perf_counter() - t0
    if scene.geometry.kind == "mesh":
        check_problem_size(scene, mesh, transient=transient)
    fields = material_fields(scene, mesh)
    t0 = time.perf_counter()
    model = build_model(scene, mesh, fields)
    K, M = model.K(fields.stiffness), model.M(fields.density)
    timings["assembly"] = time.perf_counter() - t0
    n_modes = scene.simulation.n_modes
    limit = model.n_free if model.n_free <= 600 else model.n_free - 1
    if n_modes > limit:
        raise SceneError(
            f"{scene.source}: key 'simulation.n_modes': {n_modes} modes asked, but the mesh has "
            f"only {model.n_free} free DOFs; allowed: 1..{limit}"
        )
    t0 = time.perf_counter()
    try:
        modes = eigenmodes(K, M, n_modes, seed=scene.seed)
    except np.linalg.LinAlgError as error:
        raise SceneError(
            f"{scene.source}: the eigen-solve failed ({error}); the scene's values are "
            "numerically degenerate: check the extremes among material, geometry.size and "
            "boundary; allowed: values whose combination stays finite"
        ) from None
    timings["modes"] = time.perf_counter() - t0
    alpha, beta = scene.damping.coefficients()
    result = SimulationResult(scene, mesh, fields, model, modes, alpha, beta, timings=timings)
    _check_finite(scene, "frequencies", modes.omega)
    if not transient:
        return result
    t0 = time.perf_counter()
    _transient(result, K, M, method or scene.simulation.method)
    timings["transient"] = time.perf_counter() - t0
    _check_finite(scene, "transient response", result.modal_coordinates
                  if result.modal_coordinates is not None else result.direct_displacements)
    return result


def _check_finite(scene: Scene, what: str, values: np.ndarray) -> None:
    """A last guard: values in range one by one can still overflow together (E / rho at the
    extremes of their ranges); say so instead of returning NaN."""
    if not np.all(np.isfinite(values)):
        raise SceneError(
            f"{scene.source}: the scene's values give a non-finite {what} (overflow); check "
            "the extremes among material (E/rho or tension/areal_density), geometry.size, "
            "damping and excitation; allowed: values whose combination stays finite"
        )


def initial_conditions(scene: Scene, result: SimulationResult, K, M):
    """(u0, v0, force, force_shape, force_dt) over the free DOFs for the scene's excitation."""
    mesh, model = result.mesh, result.model
    ex = scene.excitation
    f, nodes, direction = load_vector(scene, mesh, model)
    u0 = v0 = force = None
    force_dt = None
    if ex.kind == "pluck":
        if len(model.fixed_dofs) == 0:
            raise SceneError(
                f"{scene.source}: key 'excitation.kind': a pluck (static deflection) needs a "
                "fixed boundary; set boundary.fixed or use 'velocity'"
            )
        static = Factorization(K)(f)
        moved = model.nodal(static)[0][nodes] @ direction
        u0 = static * (ex.displacement / float(np.mean(moved)))
    elif ex.kind == "velocity":
        full = np.zeros(mesh.n_dofs)
        vel = np.asarray(ex.velocity, dtype=float)
        vel = vel[2:] if mesh.dofs_per_node == 1 else vel
        full[mesh.dofs_of(nodes)] = np.tile(vel, len(nodes))
        v0 = model.restrict(full)
    elif ex.kind == "force":
        force, force_dt = force_signal(scene)
    return u0, v0, force, f, force_dt


def _transient(result: SimulationResult, K, M, method: str) -> None:
    scene, mesh, model, modes = result.scene, result.mesh, result.model, result.modes
    u0, v0, force, shape, force_dt = initial_conditions(scene, result, K, M)
    times = frame_times(scene)
    surface = mesh.surface_nodes
    d = mesh.dofs_per_node
    rows = model.free_index[mesh.dofs_of(surface)]
    observed = np.zeros((len(rows), len(modes)))
    observed[rows >= 0] = modes.vectors[rows[rows >= 0]]
    if u0 is not None:
        residual = u0 - modes.vectors @ (modes.vectors.T @ (M @ u0))
        result.truncation_error = float(
            np.sqrt((residual @ (M @ residual)) / (u0 @ (M @ u0)))
        )
    if method == "modal":
        c = modal_damping(modes.omega, result.alpha, result.beta)
        result.modal_coordinates = modal_coordinates(
            modes.vectors, modes.omega, c, M, times, u0, v0, force, shape, force_dt
        )
        result.observed_modes = observed.astype(np.float32)
    elif method == "newmark":
        obs = np.where(rows >= 0, rows, 0)
        u = newmark_response(
            K, M, result.alpha, result.beta, times, u0, v0, force, shape,
            scene.simulation.newmark_substeps, obs,
        ).astype(np.float32)
        u[:, rows < 0] = 0.0
        result.direct_displacements = u.reshape(len(times), len(surface), d)
    else:
        raise ValueError(f"transient method must be 'modal' or 'newmark', got {method!r}")
    result.times = times
    result.surface_nodes = surface
