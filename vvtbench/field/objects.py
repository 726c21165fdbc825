"""The object a field user filmed, from one ``--object`` argument.

Accepted forms (:func:`resolve_object`):

* ``box:LxWxH`` -- a solid block of that size in metres (``box:0.1x0.1x0.05``), base
  clamped (``box:0.1x0.1x0.05:fixed=none`` for a free block). Its inference mesh is the
  voxel grid itself, as for the shipped cube scenes (8x8x8 hexahedra).
* ``plate:LxW`` or ``plate:D:circle`` -- a membrane (drum head) in the plane z = 0, rim
  clamped; triangulated as the shipped drums are, inference grid 20x20.
* ``path/to/surface.stl`` (``.obj``, ``.ply``) -- a closed surface in metres,
  tetrahedralized as the shipped bunny is (:func:`vvtbench.fem.mesh.tet_mesh`), lowest
  corner moved to the origin, bottom nodes clamped; options ``:up=y``, ``:scale_to=0.1``,
  ``:fixed=none``, ``:mesh=auto`` (the default: a surface that is an axis-aligned
  rectangular block, its enclosed volume that of its bounding box, is meshed as that block's
  hexahedral voxel grid, as ``box:`` is; any other is tetrahedralized), ``:mesh=block`` (the
  same, an error when the surface is not a block), ``:mesh=tet`` (tetrahedralize every
  surface; on a block this costs accuracy: benchmarks/bench_field_path.py).
* ``path/to/scene.toml`` -- a scene file: its geometry and boundary, never its material.

Every object is in its own frame: metres, lowest corner at the origin, z up. Clicked 3-D
points (``x,y,z,u,v``) are given in that frame. An object more than
:data:`LARGEST_PLAUSIBLE_M` across is most likely given in millimetres (a 5 cm cube read as
50 m): :func:`resolve_object` then warns (:class:`UnitWarning`, also kept in
:attr:`FieldObject.warnings`), naming the unit and the size it would have in metres.
"""

from __future__ import annotations

import warnings as _warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..fem.mesh import Mesh, box_mesh, drum_mesh, load_surface, tet_mesh
from ..fem.voxels import default_voxel_shape
from ..observe import ObserveError
from ..samples.reader import sha256_file as _sha256

__all__ = ["LARGEST_PLAUSIBLE_M", "SURFACE_SUFFIXES", "FieldObject", "UnitWarning", "is_block",
           "resolve_object", "unit_problem"]

SURFACE_SUFFIXES = (".stl", ".obj", ".ply")
FORMS = ("box:LxWxH", "plate:LxW", "plate:D:circle", "a .stl/.obj/.ply surface",
         "a scene .toml")
LARGEST_PLAUSIBLE_M = 10.0
"""Objects filmed for vibration tomography are centimetres to a metre or two across; one
larger than this (metres) is taken for a size in millimetres and warned about."""


class UnitWarning(UserWarning):
    """An object (or clicked points) whose size says it is not in metres."""


def unit_problem(what: str, size_m: float, hint: str) -> str | None:
    """The warning for something ``size_m`` (as read, in metres) across, or None when that is
    a plausible size."""
    if not (np.isfinite(size_m) and size_m > LARGEST_PLAUSIBLE_M):
        return None
    return (f"{what} is {size_m:g} m across: lengths are read in metres, and this looks like "
            f"millimetres (it would be {size_m / 1000:g} m); {hint}")


@dataclass
class FieldObject:
    """What :func:`vvtbench.observe` needs of a real object.

    Attributes
    ----------
    spec : the ``--object`` text it was made from.
    kind : ``"box"``, ``"plate"``, ``"mesh"`` or ``"scene"``.
    mesh : the inference mesh (metres, lowest corner at the origin).
    fixed_nodes : clamped node indices of ``mesh``.
    inference_shape : the voxel grid of the unknowns.
    source_sha256 : sha256 of the file it was read from (None for a size).
    """

    spec: str
    kind: str
    mesh: Mesh
    fixed_nodes: np.ndarray
    inference_shape: tuple[int, ...]
    source_sha256: str | None = None
    info: dict[str, Any] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)

    @property
    def is_membrane(self) -> bool:
        """True for a drum head or plate (one transverse DOF per node)."""
        return self.mesh.dofs_per_node == 1

    def corner_nodes(self) -> np.ndarray:
        """Nodes at the extremes of the mesh: the corners of a box, those of a plate's
        bounding box (or its extreme rim points), of a surface's bounding box nearest nodes."""
        pts = self.mesh.points
        lo, hi = pts.min(0), pts.max(0)
        dims = [a for a in range(3) if hi[a] - lo[a] > 1e-12]
        out = []
        for bits in range(1 << len(dims)):
            target = lo.copy()
            for i, a in enumerate(dims):
                if bits >> i & 1:
                    target[a] = hi[a]
            out.append(int(np.argmin(np.sum((pts - target) ** 2, axis=1))))
        return np.array(sorted(set(out)), dtype=np.int64)

    def describe(self) -> dict[str, Any]:
        """A JSON-serialisable description (for reports and stage keys)."""
        return {"spec": self.spec, "kind": self.kind, "element": self.mesh.element,
                "n_nodes": int(self.mesh.n_nodes), "n_elements": int(self.mesh.n_elements),
                "extent_m": (self.mesh.points.max(0) - self.mesh.points.min(0)).tolist(),
                "n_fixed": int(len(self.fixed_nodes)),
                "inference_shape": list(self.inference_shape),
                "source_sha256": self.source_sha256, **self.info}


def _bad(spec: str, why: str) -> ObserveError:
    return ObserveError(f"--object {spec!r}: {why}; allowed: {', '.join(FORMS)}")


def _sizes(spec: str, text: str, n: int) -> tuple[float, ...]:
    parts = text.lower().split("x")
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        raise _bad(spec, f"size {text!r} is not {n} numbers joined by 'x'") from None
    if len(values) != n or not all(np.isfinite(v) and v > 0 for v in values):
        raise _bad(spec, f"size {text!r} must be {n} positive numbers (metres) joined by 'x'")
    return values


def _options(spec: str, items: list[str], allowed: dict[str, tuple[str, ...] | None]
             ) -> dict[str, str]:
    out = {}
    for item in items:
        key, _, value = item.partition("=")
        if key not in allowed or not value:
            raise _bad(spec, f"unknown option {item!r} (options: "
                             f"{', '.join(k + '=...' for k in allowed)})")
        choices = allowed[key]
        if choices is not None and value not in choices:
            raise _bad(spec, f"option {key}={value!r}: allowed {', '.join(choices)}")
        out[key] = value
    return out


def resolve_object(spec: str, *, inference_shape: tuple[int, ...] | None = None
                   ) -> FieldObject:
    """The :class:`FieldObject` an ``--object`` argument names (module notes); a size that
    looks like millimetres is warned about (:class:`UnitWarning`, and in ``.warnings``).

    Raises
    ------
    ObserveError
        One line naming the argument and the allowed forms.
    """
    obj = _resolve(spec, inference_shape)
    pts = obj.mesh.points
    size = float(np.max(pts.max(0) - pts.min(0))) if len(pts) else 0.0
    surface = obj.kind == "mesh"
    hint = ("give :scale_to=METRES (the largest extent) or export the file in metres"
            if surface else "give the size in metres")
    problem = unit_problem(f"--object {str(spec).strip()!r}: the object", size, hint)
    if problem is not None:
        obj.warnings.append(problem)
        _warnings.warn(problem, UnitWarning, stacklevel=2)
    return obj


def _resolve(spec: str, inference_shape: tuple[int, ...] | None) -> FieldObject:
    """The object ``spec`` names, unchecked for its unit.

    Parameters
    ----------
    spec : ``box:LxWxH``, ``plate:LxW``, ``plate:D:circle``, a surface mesh file or a scene.
    inference_shape : voxel grid of the unknowns (default 8x8x8 solids, 20x20 plates).
    """
    text = str(spec).strip()
    head, _, rest = text.partition(":")
    if head == "box" and rest:
        size_text, *items = rest.split(":")
        size = _sizes(text, size_text, 3)
        opts = _options(text, items, {"fixed": ("bottom", "none")})
        shape = tuple(inference_shape or default_voxel_shape("box"))
        if len(shape) != 3:
            raise _bad(text, f"a box takes a 3-D inference grid, got {shape}")
        mesh = box_mesh(shape, size)
        fixed = mesh.node_sets["bottom"] if opts.get("fixed", "bottom") == "bottom" \
            else np.zeros(0, np.int64)
        return FieldObject(text, "box", mesh, fixed, shape)
    if head == "plate" and rest:
        size_text, *items = rest.split(":")
        circle = "circle" in items
        items = [i for i in items if i != "circle"]
        opts = _options(text, items, {"cells": None})
        size = _sizes(text, size_text, 1 if circle else 2)
        if not circle and abs(size[0] - size[1]) > 1e-9 * max(size):
            raise _bad(text, "a rectangular plate must be square (LxL) for now")
        try:
            cells = int(opts.get("cells", 20))
        except ValueError:
            raise _bad(text, "option cells must be an integer >= 2") from None
        if cells < 2:
            raise _bad(text, "option cells must be an integer >= 2")
        shape = tuple(inference_shape or default_voxel_shape("drum"))
        if len(shape) != 2:
            raise _bad(text, f"a plate takes a 2-D inference grid, got {shape}")
        mesh = drum_mesh("circle" if circle else "square", size[0], cells)
        return FieldObject(text, "plate", mesh, mesh.node_sets["rim"], shape)
    path_text, *items = text.split(":") if not Path(text).exists() else (text,)
    path = Path(path_text)
    suffix = path.suffix.lower()
    if suffix == ".toml":
        return _from_scene(text, path, inference_shape)
    if suffix in SURFACE_SUFFIXES:
        if not path.is_file():
            raise _bad(text, f"{path}: no such file")
        opts = _options(text, items, {"up": ("x", "y", "z"), "scale_to": None,
                                      "fixed": ("bottom", "none"),
                                      "mesh": ("tet", "auto", "block")})
        scale_to = None
        if "scale_to" in opts:
            try:
                scale_to = float(opts["scale_to"])
            except ValueError:
                scale_to = -1.0
            if not (np.isfinite(scale_to) and scale_to > 0):
                raise _bad(text, "option scale_to must be a positive length (metres)")
        shape = tuple(inference_shape or default_voxel_shape("box"))
        try:
            v, f = load_surface(path, opts.get("up", "z"), scale_to, target_faces=3000)
            how = opts.get("mesh", "auto")
            block = how != "tet" and len(shape) == 3 and is_block(v, f)
            if how == "block" and not block:
                raise ValueError(f"{path}: option mesh=block, but the surface is not an "
                                 "axis-aligned rectangular block (allowed: mesh=auto or tet)")
            mesh = box_mesh(shape, tuple(float(x) for x in v.max(0))) if block else \
                tet_mesh(v, f, edge_length_fac=0.1, coarsen=True)
        except (FileNotFoundError, ValueError) as error:
            raise _bad(text, str(error)) from None
        fixed = mesh.node_sets["bottom"] if opts.get("fixed", "bottom") == "bottom" \
            else np.zeros(0, np.int64)
        return FieldObject(text, "mesh", mesh, fixed, shape, _sha256(path),
                           {"meshed_as": "block" if block else "tetrahedra"})
    raise _bad(text, "not a known form")


def is_block(vertices: np.ndarray, faces: np.ndarray, rtol: float = 1e-6) -> bool:
    """True when the closed surface ``(vertices, faces)`` is an axis-aligned rectangular block:
    the volume it encloses equals that of its bounding box (anything else encloses less).

    >>> import trimesh
    >>> b, s = trimesh.creation.box(extents=(1.0, 2.0, 3.0)), trimesh.creation.icosphere()
    >>> bool(is_block(b.vertices, b.faces)), bool(is_block(s.vertices, s.faces))
    (True, False)
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    volume = abs(float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum()) / 6.0)
    extent = v.max(0) - v.min(0)
    box = float(np.prod(extent))
    return box > 0 and abs(volume - box) <= rtol * box


def _from_scene(text: str, path: Path, inference_shape: tuple[int, ...] | None
                ) -> FieldObject:
    from ..scene.scene import load_scene
    from ..simulation.simulate import build_mesh, fixed_nodes

    if not path.is_file():
        raise _bad(text, f"{path}: no such file")
    scene = load_scene(path)
    geom = scene.geometry
    shape = tuple(inference_shape or default_voxel_shape(geom.kind))
    if geom.kind == "box":
        mesh = box_mesh(shape, tuple(geom.size))
        extra = {}
        for name, region in scene.boundary.node_sets.items():
            if region.indices is None:
                lo, hi = np.asarray(region.box_min), np.asarray(region.box_max)
                extra[name] = np.flatnonzero(np.all((mesh.points >= lo) & (mesh.points <= hi),
                                                    axis=1))
        mesh = mesh.with_node_sets(extra) if extra else mesh
    else:
        mesh = build_mesh(scene)
    return FieldObject(text, "scene", mesh, fixed_nodes(scene, mesh), shape, _sha256(path),
                       {"geometry": geom.kind})
