"""Scene descriptions: pure data, validated, loaded from TOML.

A scene says what object vibrates (geometry, materials, boundary conditions, damping,
excitation), for how long it is simulated, and how it is seen (camera, rendering). It holds no
arrays and runs no physics: the backends in :mod:`vvtbench.fem` and :mod:`vvtbench.render`
consume it. Every key is documented with units and defaults in ``docs/scenes.md``.

>>> scene = Scene.model_validate({"name": "tiny", "geometry": {"kind": "box", "cells": [2, 2, 2]}})
>>> scene.geometry.size, scene.material.E, scene.fixed_sets
((0.05, 0.05, 0.05), 9000.0, ['bottom'])
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path
from typing import Annotated, Literal, get_args

import numpy as np
from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)


def _bound_text(gt, ge, lt, le, unit: str, integer: bool) -> str:
    """What a numeric key allows, e.g. 'a finite number > 0 and <= 1e+13 (Pa)'."""
    def fmt(v: float) -> str:
        return str(int(v)) if integer else f"{v:g}"

    parts = [f"> {fmt(gt)}" if gt is not None else None,
             f">= {fmt(ge)}" if ge is not None else None,
             f"< {fmt(lt)}" if lt is not None else None,
             f"<= {fmt(le)}" if le is not None else None]
    text = ("an integer" if integer else "a finite number") + (
        " " + " and ".join(p for p in parts if p) if any(parts) else "")
    return text + (f" ({unit})" if unit else "")


def _show(value) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def Number(  # noqa: N802 - a type factory, used like a type
    gt: float | None = None,
    ge: float | None = None,
    lt: float | None = None,
    le: float | None = None,
    unit: str = "",
    integer: bool = False,
):
    """A numeric scene value: finite, within the bounds, never a boolean. The bounds are pydantic
    ``Field`` constraints (so they show in the JSON schema); a check before them gives the
    one-line message 'got -5; allowed: a finite number > 0 (Pa)'."""
    allowed = _bound_text(gt, ge, lt, le, unit, integer)

    def check(value):
        if isinstance(value, bool):
            raise ValueError(f"got {str(value).lower()}; allowed: {allowed}")
        if isinstance(value, int | float):
            try:
                x = float(value)
            except OverflowError:
                x = math.inf
            bad = not math.isfinite(x) or (
                (gt is not None and not x > gt) or (ge is not None and not x >= ge)
                or (lt is not None and not x < lt) or (le is not None and not x <= le)
            )
            if not math.isfinite(x):
                raise ValueError(
                    f"Input should be a finite number, got {value}; allowed: {allowed}"
                )
            if bad or (integer and x != int(x)):
                raise ValueError(f"got {_show(value)}; allowed: {allowed}")
        return value

    field = Field(gt=gt, ge=ge, lt=lt, le=le) if integer else Field(
        gt=gt, ge=ge, lt=lt, le=le, allow_inf_nan=False)
    return Annotated[int if integer else float, BeforeValidator(check), field]


MIN_VECTOR = 1e-9


def _nonzero(vector: tuple[float, float, float]) -> tuple[float, float, float]:
    if not np.linalg.norm(vector) >= MIN_VECTOR:
        raise ValueError(
            f"got {list(vector)}; allowed: a non-zero vector (length >= {MIN_VECTOR:g})"
        )
    return vector


def _no_bool(value):
    if isinstance(value, bool):
        raise ValueError(f"got {str(value).lower()}; allowed: one of the integers listed")
    return value


Finite = Number()
Coordinate = Number(ge=-1e6, le=1e6)
Vec3 = tuple[Coordinate, Coordinate, Coordinate]
"""A point or vector: three finite numbers within +-1e6 (m, or m/s for velocities)."""
Direction = Annotated[Vec3, AfterValidator(_nonzero)]
"""A direction: three finite numbers, not all zero (normalized where used)."""

MAX_LENGTH = 1e3
MIN_LENGTH = 1e-6
Length = Number(ge=MIN_LENGTH, le=MAX_LENGTH, unit="m")
Poisson = Number(gt=-1.0, lt=0.5)
Seed = Number(ge=0, le=2**63 - 1, integer=True)
Youngs = Number(ge=1e-3, le=1e13, unit="Pa")
Density = Number(ge=1e-2, le=1e5, unit="kg/m^3")
Tension = Number(ge=1e-6, le=1e9, unit="N/m")
ArealDensity = Number(ge=1e-6, le=1e4, unit="kg/m^2")
Frequency = Number(ge=1e-3, le=1e9, unit="Hz")
Seconds = Number(ge=1e-9, le=1e6, unit="s")
StartTime = Number(ge=0, le=1e6, unit="s")
Force = Number(gt=0, le=1e9, unit="N")
BoxCells = Number(ge=1, le=10_000, integer=True)
Order = Annotated[Literal[1, 2], BeforeValidator(_no_bool)]
"""Element order: 1 (linear: hex8, tet4) or 2 (quadratic: hex27, tet10)."""
Pixels = Number(ge=8, le=16384, integer=True, unit="px")

_PACKAGE_DIR = Path(__file__).resolve().parent.parent
SCENES_DIR = next(
    (d for d in (_PACKAGE_DIR / "scenes", _PACKAGE_DIR.parent / "scenes") if d.is_dir()),
    _PACKAGE_DIR.parent / "scenes",
)
"""The shipped scenes (and ``suites/``): inside the installed package (a wheel), else the
source checkout's top-level ``scenes/`` (an editable install)."""
BUILTIN_MESHES = ("bunny",)


class SceneError(ValueError):
    """A scene file is malformed: the message names the file, the key and what is allowed."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class BoxGeometry(_Strict):
    """Structured hexahedral grid of an axis-aligned box with its lowest corner at the origin."""

    kind: Literal["box"]
    size: tuple[Length, Length, Length] = (0.05, 0.05, 0.05)
    cells: tuple[BoxCells, BoxCells, BoxCells] = (10, 10, 10)
    order: Order = 1


class MeshGeometry(_Strict):
    """A closed surface mesh, tetrahedralized with pytetwild."""

    kind: Literal["mesh"]
    path: str = "bunny"
    up_axis: Literal["x", "y", "z"] = "z"
    scale_to: Length | None = None
    target_faces: Number(ge=100, le=10**7, integer=True) | None = 2000
    edge_length_fac: Number(gt=0, le=1) = 0.1
    epsilon: Number(gt=0, le=0.1) = 5e-3
    stop_energy: Number(gt=3, le=1e6) = 10.0
    coarsen: bool = False
    order: Order = 1


class DrumGeometry(_Strict):
    """A membrane on a rigid frame: square (side ``size``) or circular (diameter ``size``)."""

    kind: Literal["drum"]
    shape: Literal["square", "circle"] = "square"
    size: Length = 0.1016
    cells: Number(ge=2, le=100_000, integer=True) = 40


Geometry = Annotated[BoxGeometry | MeshGeometry | DrumGeometry, Field(discriminator="kind")]


class Defect(_Strict):
    """A region whose elements (by centroid) take other material values.

    ``size`` means: box -> full side lengths (3); sphere -> radius (1); cylinder -> radius and
    height (2), along ``axis``; ellipsoid -> semi-axes (3). For drums only x, y matter.
    """

    shape: Literal["box", "sphere", "cylinder", "ellipsoid"]
    center: Vec3
    size: tuple[Number(ge=1e-9, le=MAX_LENGTH, unit="m"), ...]
    axis: Literal["x", "y", "z"] = "z"
    E: Youngs | None = None
    rho: Density | None = None
    nu: Poisson | None = None
    tension: Tension | None = None
    areal_density: ArealDensity | None = None

    @field_validator("size")
    @classmethod
    def _size_matches_shape(cls, size: tuple[float, ...], info: ValidationInfo) -> tuple:
        shape = info.data.get("shape")
        expected = {"box": 3, "sphere": 1, "cylinder": 2, "ellipsoid": 3}.get(shape)
        if expected is not None and len(size) != expected:
            raise ValueError(
                f"a {shape} defect needs {expected} value(s), got {len(size)}; allowed: "
                "box 3 (side lengths), sphere 1 (radius), cylinder 2 (radius, height), "
                "ellipsoid 3 (semi-axes)"
            )
        return size

    def contains(self, points: np.ndarray) -> np.ndarray:
        """Which of ``points`` (N, 3) lie inside the region."""
        d = np.asarray(points, dtype=float) - np.asarray(self.center)
        s = np.asarray(self.size, dtype=float)
        if self.shape == "box":
            return np.all(np.abs(d) <= s / 2 + 1e-12, axis=1)
        if self.shape == "sphere":
            return np.linalg.norm(d, axis=1) <= s[0] + 1e-12
        if self.shape == "ellipsoid":
            return np.sum((d / s) ** 2, axis=1) <= 1 + 1e-12
        a = "xyz".index(self.axis)
        radial = np.delete(d, a, axis=1)
        return (np.linalg.norm(radial, axis=1) <= s[0] + 1e-12) & (np.abs(d[:, a]) <= s[1] / 2)


class Material(_Strict):
    """Base material plus defects. Solids use E, rho, nu; drums use tension, areal_density."""

    E: Youngs = 9000.0
    rho: Density = 1270.0
    nu: Poisson = 0.3
    tension: Tension = 40.0
    areal_density: ArealDensity = 0.5
    defects: list[Defect] = []
    field_file: str | None = None


class NodeRegion(_Strict):
    """Named node set: nodes inside an axis-aligned box, or listed by index."""

    box_min: Vec3 | None = None
    box_max: Vec3 | None = None
    indices: list[Number(ge=0, le=2**62, integer=True)] | None = None

    @model_validator(mode="after")
    def _one_kind(self) -> NodeRegion:
        has_box = self.box_min is not None or self.box_max is not None
        if has_box == (self.indices is not None):
            raise ValueError("give either box_min and box_max, or indices")
        if has_box and (self.box_min is None or self.box_max is None):
            missing = "box_max" if self.box_max is None else "box_min"
            raise ValueError(f"missing {missing}: box_min and box_max (3 floats, m) go together")
        if has_box and any(lo > hi for lo, hi in zip(self.box_min, self.box_max, strict=True)):
            raise ValueError(
                f"box_min {list(self.box_min)} exceeds box_max {list(self.box_max)} in some "
                "coordinate; allowed: box_min <= box_max in x, y and z"
            )
        return self


class Boundary(_Strict):
    """Fixed node sets. Built-in names depend on the geometry (see docs/scenes.md)."""

    fixed: list[str] | None = None
    node_sets: dict[str, NodeRegion] = {}


class Damping(_Strict):
    """Rayleigh damping C = alpha M + beta K, given directly or by two (frequency Hz, zeta)."""

    alpha: Number(ge=0, le=1e9, unit="1/s") = 0.0
    beta: Number(ge=0, le=1e3, unit="s") = 0.0
    pairs: list[tuple[Frequency, Number(ge=0, le=100)]] | None = None

    @field_validator("pairs")
    @classmethod
    def _two_feasible_pairs(
        cls, pairs: list[tuple[float, float]] | None
    ) -> list[tuple[float, float]] | None:
        if pairs is None:
            return pairs
        if len(pairs) != 2:
            raise ValueError("pairs needs exactly two [frequency_hz, zeta] pairs")
        if math.isclose(pairs[0][0], pairs[1][0]):
            raise ValueError("the two pairs need different frequencies")
        rayleigh_from_pairs(pairs)
        return pairs

    @model_validator(mode="after")
    def _pairs_or_coefficients(self) -> Damping:
        if self.pairs is not None and (self.alpha or self.beta):
            raise ValueError("give either alpha/beta or pairs, not both")
        return self

    def coefficients(self) -> tuple[float, float]:
        """(alpha, beta) in (1/s, s); from the pairs when given.

        >>> a, b = Damping(pairs=[(12.5, 0.01749), (15.5, 0.01999)]).coefficients()
        >>> round(float(rayleigh_zeta(a, b, 12.5)), 5), round(float(rayleigh_zeta(a, b, 15.5)), 5)
        (0.01749, 0.01999)
        """
        if self.pairs is None:
            return self.alpha, self.beta
        return rayleigh_from_pairs(self.pairs)


def rayleigh_from_pairs(pairs: list[tuple[float, float]]) -> tuple[float, float]:
    """Rayleigh (alpha, beta) giving damping ratio zeta_i at frequency f_i (Hz), i = 1, 2.

    Both are >= 0 only if zeta_2 / zeta_1 lies between f_1 / f_2 and f_2 / f_1; otherwise a
    ValueError says so.
    """
    (f1, z1), (f2, z2) = sorted((float(f), float(zeta)) for f, zeta in pairs)
    w = np.array([2 * np.pi * f1, 2 * np.pi * f2])
    a = np.column_stack([1 / (2 * w), w / 2])
    alpha, beta = np.linalg.solve(a, [z1, z2])
    tol = 1e-12 * max(z1, z2)
    if z2 * f1 > z1 * f2 + tol or z2 * f2 < z1 * f1 - tol:
        raise ValueError(
            f"the pairs [[{f1:g}, {z1:g}], [{f2:g}, {z2:g}]] need a negative Rayleigh "
            f"coefficient (alpha={alpha:.4g} 1/s, beta={beta:.4g} s); allowed: zeta at "
            f"{f2:g} Hz from {z1 * f1 / f2:.4g} to {z1 * f2 / f1:.4g} (zeta at {f1:g} Hz "
            f"times {f1:g}/{f2:g} to {f2:g}/{f1:g})"
        )
    return max(float(alpha), 0.0), max(float(beta), 0.0)


def rayleigh_zeta(alpha: float, beta: float, frequency_hz):
    """Damping ratio of Rayleigh damping at a frequency (Hz): alpha/(2w) + beta w/2."""
    w = 2 * np.pi * np.asarray(frequency_hz, dtype=float)
    return alpha / (2 * w) + beta * w / 2


class Chirp(_Strict):
    """Linear frequency sweep force, amplitude in N (a speaker's drive)."""

    kind: Literal["chirp"]
    f0: Frequency = 50.0
    f1: Frequency = 1000.0
    duration: Seconds = 3.5
    amplitude: Force = 1e-3
    start: StartTime = 0.0


class ForceFile(_Strict):
    """Force time series from a file: .npy/.npz/.csv with columns time (s), force (N)."""

    kind: Literal["file"]
    path: str


class Impulse(_Strict):
    """Half-sine force pulse (a tap), peak amplitude in N."""

    kind: Literal["impulse"]
    amplitude: Force = 1e-3
    width: Seconds = 1e-3
    start: StartTime = 0.0


Signal = Annotated[Chirp | ForceFile | Impulse, Field(discriminator="kind")]


class Excitation(_Strict):
    """How the object is set in motion.

    pluck: a static deflection under a point (``radius`` 0) or patch load at ``at`` along
    ``direction``, scaled so the loaded node(s) move by ``displacement`` (m) along it, released
    at rest. velocity: nodes within ``radius`` of ``at`` start with ``velocity`` (m/s).
    force: a load on the same nodes following ``signal``. For drums, direction is out of plane.
    """

    kind: Literal["pluck", "velocity", "force", "none"] = "pluck"
    at: Vec3 | None = None
    radius: Number(ge=0, le=MAX_LENGTH, unit="m") = 0.0
    direction: Direction = (1.0, 1.0, 1.0)
    displacement: Number(ge=1e-12, le=MAX_LENGTH, unit="m") = 0.005
    velocity: Vec3 = (0.0, 0.0, 0.01)
    signal: Signal | None = None

    @model_validator(mode="after")
    def _complete(self) -> Excitation:
        if self.kind != "none" and self.at is None:
            raise ValueError(f"excitation kind '{self.kind}' needs 'at' = [x, y, z] (m)")
        if self.kind == "force" and self.signal is None:
            raise ValueError("excitation kind 'force' needs a [excitation.signal] table")
        if self.kind == "velocity" and not any(self.velocity):
            raise ValueError(
                "excitation kind 'velocity' needs a non-zero 'velocity' = [vx, vy, vz] (m/s)"
            )
        return self


class Simulation(_Strict):
    """Modal analysis and transient sampling."""

    n_modes: Number(ge=1, le=2000, integer=True) = 50
    fps: Number(gt=0, le=1e7, unit="frames/s") = 2000.0
    duration: Seconds = 6.0
    method: Literal["modal", "newmark"] = "modal"
    newmark_substeps: Number(ge=1, le=1000, integer=True) = 4

    @model_validator(mode="after")
    def _at_least_one_frame(self) -> Simulation:
        if round(self.duration * self.fps) < 1:
            raise ValueError(
                f"duration {self.duration:g} s at {self.fps:g} frames/s gives no frame; allowed: "
                "duration * fps >= 0.5 (the frame count is rounded)"
            )
        return self


class PinholeSpec(_Strict):
    """Pinhole camera: pose by position/look_at/up; intrinsics by fov_y or focal lengths fx, fy
    (px), principal point cx, cy (px, pixel-centre convention; default the image centre)."""

    position: Vec3 = (0.15, -0.2, 0.15)
    look_at: Vec3 = (0.025, 0.025, 0.02)
    up: Direction = (0.0, 0.0, 1.0)
    fov_y_deg: Number(gt=0, lt=180, unit="degrees") | None = 20.0
    fx: Number(gt=0, le=1e7, unit="px") | None = None
    fy: Number(gt=0, le=1e7, unit="px") | None = None
    cx: Number(ge=-1e7, le=1e7, unit="px") | None = None
    cy: Number(ge=-1e7, le=1e7, unit="px") | None = None
    resolution: tuple[Pixels, Pixels] = (256, 256)

    @model_validator(mode="after")
    def _fy_needs_fx(self) -> PinholeSpec:
        if self.fy is not None and self.fx is None:
            raise ValueError("fy (px) needs fx (px); with fov_y_deg the pixels are square")
        view = np.subtract(self.look_at, self.position, dtype=float)
        if not np.linalg.norm(view) >= MIN_VECTOR:
            raise ValueError(
                f"look_at {list(self.look_at)} equals position {list(self.position)}; allowed: "
                f"two points at least {MIN_VECTOR:g} m apart"
            )
        up = np.asarray(self.up, dtype=float)
        cross = np.cross(view / np.linalg.norm(view), up / np.linalg.norm(up))
        if not np.linalg.norm(cross) >= 1e-9:
            raise ValueError(
                f"up {list(self.up)} is parallel to the viewing direction (look_at - position); "
                "allowed: any direction not parallel to it"
            )
        return self


MAX_VIEWS = 16
RIG_KINDS = ("ring", "cone")


class CameraRig(_Strict):
    """Several synchronised cameras made from the scene's camera (view 0).

    ring: view ``i`` is the camera turned by ``spread_deg * i / views`` about ``up`` through
    ``look_at``. cone: views 1..N-1 sit evenly around a cone of half-angle ``spread_deg / 2``
    about the line from ``look_at`` to the camera (view 0 on its axis). View ``i`` films
    ``i * time_offset_s`` later than view 0 (0: genlocked).
    """

    views: Number(ge=2, le=MAX_VIEWS, integer=True)
    spread_deg: Number(gt=0, le=360, unit="degrees") = 360.0
    kind: Literal["ring", "cone"] = "ring"
    time_offset_s: Number(ge=0, le=1, unit="s") = 0.0

    @model_validator(mode="after")
    def _cone_opens_less_than_a_half_turn(self) -> CameraRig:
        if self.kind == "cone" and not self.spread_deg < 180:
            raise ValueError(f"spread_deg {self.spread_deg:g} for kind 'cone'; allowed: a "
                             "finite number > 0 and < 180 (degrees, the cone's full opening)")
        return self


_CAMERA_KEYS = ("position", "look_at", "up", "fov_y_deg", "fx", "fy", "cx", "cy", "resolution")
_LENS_KEYS = ("fov_y_deg", "fx", "fy")


class CameraSpec(PinholeSpec):
    """The scene's camera (view 0), and optionally more synchronised views: a list
    ``[[camera.views]]`` of cameras (each key it does not give is the ``[camera]`` table's)
    or a ``[camera.rig]``."""

    views: list[PinholeSpec] | None = None
    rig: CameraRig | None = None

    @model_validator(mode="before")
    @classmethod
    def _views_inherit_the_camera(cls, data):
        if not (isinstance(data, dict) and isinstance(data.get("views"), list)):
            return data
        views = []
        for view in data["views"]:
            if isinstance(view, dict):
                own_lens = any(k in view for k in _LENS_KEYS)
                view = {**{k: data[k] for k in _CAMERA_KEYS if k in data
                           and not (own_lens and k in _LENS_KEYS)}, **view}
            views.append(view)
        return {**data, "views": views}

    @model_validator(mode="after")
    def _views_or_rig(self) -> CameraSpec:
        if self.views is not None and self.rig is not None:
            raise ValueError("give either [[camera.views]] or [camera.rig], not both")
        if self.views is not None and not 1 <= len(self.views) <= MAX_VIEWS - 1:
            raise ValueError(f"camera.views lists {len(self.views)} camera(s); allowed: 1 to "
                             f"{MAX_VIEWS - 1} (view 0 is the [camera] table itself)")
        return self

    @property
    def n_views(self) -> int:
        """Number of cameras filming the scene (1: the ``[camera]`` table alone)."""
        if self.rig is not None:
            return int(self.rig.views)
        return 1 + (len(self.views) if self.views is not None else 0)

    @property
    def time_offset_s(self) -> float:
        """Delay of view ``i`` behind view ``i - 1`` (s)."""
        return float(self.rig.time_offset_s) if self.rig is not None else 0.0


class RenderSpec(_Strict):
    """How frames are drawn and recorded (used by the renderer)."""

    supersample: Number(ge=1, le=8, integer=True) = 4
    texture_density: Number(gt=0, le=1) = 0.5
    texture_contrast: Number(gt=0, le=1) = 1.0
    texture_seed: Seed = 0
    motion_scale: Number(gt=0, le=1e6) = 1.0
    lighting: Literal["flat", "lit"] = "flat"
    bit_depth: Annotated[Literal[8, 12, 16], BeforeValidator(_no_bool)] = 16
    read_noise_dn: Number(ge=0, le=1e6, unit="DN") = 0.0
    shot_noise: bool = False
    frame_average: Number(ge=1, le=1000, integer=True) = 1
    full_well_electrons: Number(gt=0, le=1e9, unit="electrons") = 1e4
    consumer_crf: Number(ge=0, le=51, integer=True) | None = None


class Scene(_Strict):
    """A whole scene. See docs/scenes.md."""

    name: str
    description: str = ""
    seed: Seed = 0
    geometry: Geometry
    material: Material = Material()
    boundary: Boundary = Boundary()
    damping: Damping = Damping()
    excitation: Excitation = Excitation(kind="none")
    simulation: Simulation = Simulation()
    camera: CameraSpec = CameraSpec()
    render: RenderSpec = RenderSpec()
    source: str | None = Field(default=None, exclude=True)

    @field_validator("name")
    @classmethod
    def _name_is_a_slug(cls, name: str) -> str:
        if not name or not all(c.isalnum() or c in "-_." for c in name):
            raise ValueError("name may contain only letters, digits, '-', '_' and '.'")
        if name.startswith("."):  # it names the sample folder: no hidden folder, '.' or '..'
            raise ValueError("name must not start with '.'")
        return name

    @model_validator(mode="after")
    def _defects_fit_geometry(self) -> Scene:
        is_drum = self.geometry.kind == "drum"
        for i, d in enumerate(self.material.defects):
            solid_keys = [k for k in ("E", "rho", "nu") if getattr(d, k) is not None]
            drum_keys = [k for k in ("tension", "areal_density") if getattr(d, k) is not None]
            if is_drum and solid_keys:
                raise ValueError(
                    f"material.defects[{i}]: a drum defect takes tension and areal_density, "
                    f"not {', '.join(solid_keys)}"
                )
            if not is_drum and drum_keys:
                raise ValueError(
                    f"material.defects[{i}]: a solid defect takes E, rho and nu, "
                    f"not {', '.join(drum_keys)}"
                )
            if not (solid_keys or drum_keys):
                raise ValueError(f"material.defects[{i}] sets no material value")
        return self

    @property
    def fixed_sets(self) -> list[str]:
        if self.boundary.fixed is not None:
            return list(self.boundary.fixed)
        return ["rim"] if self.geometry.kind == "drum" else ["bottom"]

    def resolve_path(self, path: str) -> Path:
        """A path from the scene, relative to the scene file's folder when not absolute."""
        p = Path(path)
        if not p.is_absolute() and self.source is not None:
            p = Path(self.source).parent / p
        return p

    def to_toml_dict(self) -> dict:
        """The resolved scene (every default filled in) as TOML-ready data."""
        return _drop_none(self.model_dump(mode="json"))


def _drop_none(value):
    if isinstance(value, dict):
        return {k: _drop_none(v) for k, v in value.items() if v is not None}
    if isinstance(value, list):
        return [_drop_none(v) for v in value]
    return value


def _union_models(union) -> dict[str, type[BaseModel]]:
    members = get_args(get_args(union)[0])
    return {get_args(m.model_fields["kind"].annotation)[0]: m for m in members}


_TAGGED_UNIONS = {"geometry": _union_models(Geometry), "signal": _union_models(Signal)}


def _error_key(loc: tuple) -> tuple[str, type[BaseModel] | None]:
    """The dotted key of a pydantic error location without union tags, e.g.
    ``excitation.signal.f0`` for ``('excitation', 'signal', 'chirp', 'f0')``, and the union
    member the tag selected, if any."""
    parts: list[str] = []
    member = None
    for p in loc:
        s = str(p)
        if s.startswith("function-"):
            continue
        if parts and s in _TAGGED_UNIONS.get(parts[-1], {}):
            member = _TAGGED_UNIONS[parts[-1]][s]
        elif isinstance(p, int) and parts:
            parts[-1] += f"[{p}]"
        else:
            parts.append(s)
    return ".".join(parts), member


def _format_error(source: str, error: ValidationError) -> str:
    """One line: the file, then each problem as "key 'a.b': what is wrong; allowed: ..."."""
    problems = []
    for e in error.errors():
        key, member = _error_key(e["loc"])
        msg = e["msg"].removeprefix("Value error, ")
        if e["type"] == "extra_forbidden":
            parent = key.rsplit(".", 1)[0] if "." in key else ""
            allowed = ", ".join(member.model_fields) if member else _allowed_keys(parent)
            msg = f"unknown key; allowed keys here: {allowed}"
        elif e["type"] == "union_tag_invalid":
            key = f"{key}.kind"
        elif e["type"] == "union_tag_not_found":
            kinds = ", ".join(repr(k) for k in _TAGGED_UNIONS.get(key.rsplit(".", 1)[-1], {}))
            key, msg = f"{key}.kind", f"missing; allowed: {kinds}"
        elif e["type"] in ("missing", "model_type", "dict_type", "tuple_type", "list_type"):
            msg = f"{msg} (got {_show(e.get('input'))})" if e["type"] != "missing" else msg
        key = "".join(c if c.isprintable() else repr(c)[1:-1] for c in key)
        problems.append(f"key '{key or '<top level>'}': {' '.join(str(msg).split())}")
    if len(problems) == 1:
        return f"{source}: {problems[0]}"
    return f"{source}: {len(problems)} problems: " + "; ".join(problems)


def _allowed_keys(parent: str) -> str:
    models = {
        "": Scene, "material": Material, "boundary": Boundary, "damping": Damping,
        "excitation": Excitation, "simulation": Simulation, "camera": CameraSpec,
        "render": RenderSpec, "geometry": None,
    }
    head = parent.split(".")[0]
    if head == "material" and "defects" in parent:
        model = Defect
    elif head == "excitation" and "signal" in parent:
        return "kind, and per kind: " + "; ".join(
            f"{m.model_fields['kind'].annotation.__args__[0]}: "
            + ", ".join(k for k in m.model_fields if k != "kind")
            for m in (Chirp, ForceFile, Impulse)
        )
    elif head == "boundary" and "node_sets" in parent:
        model = NodeRegion
    elif head == "camera" and "views" in parent:
        model = PinholeSpec
    elif head == "camera" and "rig" in parent:
        model = CameraRig
    else:
        model = models.get(head)
    if model is None:
        return "; ".join(
            f"{m.model_fields['kind'].annotation.__args__[0]}: "
            + ", ".join(k for k in m.model_fields)
            for m in (BoxGeometry, MeshGeometry, DrumGeometry)
        )
    return ", ".join(k for k in model.model_fields if k != "source")


def parse_scene(data: dict, source: str = "<scene>") -> Scene:
    """Validate a scene dict; errors name ``source``, the key and what is allowed."""
    try:
        scene = Scene.model_validate(data)
    except ValidationError as error:
        raise SceneError(_format_error(source, error)) from None
    return scene.model_copy(update={"source": source})


def find_scene(name_or_path: str | Path) -> Path:
    """A scene file by path, or by name among the shipped scenes in ``scenes/``."""
    p = Path(name_or_path)
    if p.is_file():
        return p
    for candidate in (SCENES_DIR / f"{name_or_path}.toml", SCENES_DIR / str(name_or_path)):
        if candidate.is_file():
            return candidate
    shown = str(name_or_path) if str(name_or_path).isprintable() else repr(str(name_or_path))
    if not SCENES_DIR.is_dir():
        raise SceneError(
            f"{shown}: no such scene file, and the shipped scenes are not installed "
            f"(looked in {_PACKAGE_DIR / 'scenes'} and {SCENES_DIR}); give a path to a scene "
            "file, or install vvtbench from its source checkout (pip install -e .)"
        )
    known = sorted(q.stem for q in SCENES_DIR.glob("*.toml"))
    raise SceneError(
        f"{shown}: no such scene file, and not a shipped scene; shipped scenes: "
        + (", ".join(known) or "(none found in " + str(SCENES_DIR) + ")")
    )


def load_scene(name_or_path: str | Path) -> Scene:
    """Read and validate a scene TOML file (or a shipped scene by name)."""
    path = find_scene(name_or_path)
    try:
        data = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as error:
        raise SceneError(f"{path}: not valid TOML: {error}") from None
    except UnicodeDecodeError:
        raise SceneError(f"{path}: not a text (UTF-8 TOML) file") from None
    return parse_scene(data, str(path))


def with_overrides(
    scene: Scene,
    *,
    frames: int | None = None,
    duration: float | None = None,
    resolution: tuple[int, int] | None = None,
) -> Scene:
    """The scene with a different length (frames or seconds) or resolution (height, width; of
    every view)."""
    if frames is not None and duration is not None:
        raise SceneError("give either frames or duration, not both")
    data = scene.to_toml_dict()
    if frames is not None:
        if frames < 1:
            raise SceneError(f"frames must be >= 1, got {frames}")
        data["simulation"]["duration"] = frames / scene.simulation.fps
    if duration is not None:
        data["simulation"]["duration"] = float(duration)
    if resolution is not None:
        data["camera"]["resolution"] = [int(resolution[0]), int(resolution[1])]
        for view in data["camera"].get("views") or []:
            view["resolution"] = [int(resolution[0]), int(resolution[1])]
    return parse_scene(data, scene.source or scene.name)
