"""Scene families: a base scene plus distributions, drawn by seed into ordinary scenes.

A family file (TOML, pure data, ``docs/families.md``) names a base scene and says what varies:
defects (count, shape, position, size, aspect, stiffness and density contrast), the pluck
(position, direction, amplitude), the camera (a cone around the base viewpoint), the box aspect
ratio and any other scene key (sensor noise, ...). :func:`draw` turns ``(family, split,
index)`` into a :class:`~vvtbench.scene.scene.Scene` named ``FAMILY-SPLIT-00042``,
deterministically;
the scene is an ordinary scene (``scene.to_toml_dict()`` round-trips through ``parse_scene``).

Splits never share an instance, by construction:

* every instance's random stream is ``SeedSequence(entropy=family hash, spawn_key=(split id,
  index))``, so train, val and test draw from separate streams; and
* the drawn *physical* scene (everything but name, description and seed) is hashed, and a draw
  is kept for split ``s`` only if ``sha256(content) mod 3 == id(s)``; otherwise it is re-drawn
  from the same stream. Two identical scenes have the same hash, so they can only ever belong
  to the same split, whatever the streams produce.

A *challenge of record* draws from the same distributions with :func:`draw_secret`: its
streams are keyed by an HMAC of a secret only the host holds, not by the family name, so none
of its instances can be recomputed from the repository, and no public split uses its streams.

Draws that the mesh checks of :mod:`vvtbench.simulation.simulate` would reject (a defect catching no
element centroid, a pluck off the body) are re-drawn from the same stream, a bounded number of
times (``attempts``), so a valid family always resolves every instance.

Because the content hash decides the split, a drawn value that differed in its last bit
between machines would give another instance, not a rounded one. The draw therefore uses only
arithmetic that is the same everywhere: IEEE operations element by element and vector lengths
by :func:`length3` (exact pure-Python arithmetic), never a BLAS kernel, whose sums differ
between CPUs. The C library's ``exp``, ``log``, ``sin`` and ``cos`` remain: glibc gives the
same bits on every x86-64 CPU with FMA instructions, but its code for CPUs without them rounds
about one result in a thousand the other way (9 of the 900 modes-only instances of
``vvtbench-v1`` are drawn differently there; docs/dataset.md, "Same answer on every machine").

>>> scene = draw("cube_defects", "test", 42)
>>> scene.name
'cube_defects-test-00042'
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from pydantic import AfterValidator, BaseModel, ConfigDict, Field, ValidationError

from .scene import SCENES_DIR, Scene, SceneError, _format_error, _show, load_scene, parse_scene

__all__ = [
    "FAMILIES_DIR",
    "SPLITS",
    "Family",
    "FamilyError",
    "draw",
    "draw_secret",
    "family_info",
    "find_family",
    "instance_seed",
    "list_families",
    "load_family",
    "parse_family",
    "split_of_content",
]

FAMILIES_DIR = SCENES_DIR / "families"
"""The shipped families (``scenes/families/*.toml``)."""
SPLITS = ("train", "val", "test")
SPLIT_IDS = {s: i for i, s in enumerate(SPLITS)}
MAX_INDEX = 2**32 - 1
SHAPES = ("box", "sphere", "ellipsoid", "cylinder")


class FamilyError(SceneError):
    """A family file is malformed or cannot be drawn: one line naming the file, key, allowed."""


def check_index_range(start: int, n: int) -> None:
    """Refuse instances ``start .. start + n - 1`` beyond a split's last index
    (:data:`MAX_INDEX`)."""
    if int(start) + int(n) - 1 > MAX_INDEX:
        raise FamilyError(f"--start {start} --n {n}: the last instance would be "
                          f"{int(start) + int(n) - 1}; allowed: indices 0..{MAX_INDEX}")


# --------------------------------------------------------------------------- distributions
@dataclass(frozen=True)
class Dist:
    """One scalar distribution: ``fixed`` (a plain value), ``uniform``, ``loguniform`` (both
    over [low, high]), ``int`` (integers low..high inclusive) or ``choice`` (equal weights)."""

    kind: str
    args: tuple

    def sample(self, rng: np.random.Generator):
        k, a = self.kind, self.args
        if k == "fixed":
            return a[0]
        if k == "uniform":
            return float(rng.uniform(a[0], a[1]))
        if k == "loguniform":
            return float(math.exp(rng.uniform(math.log(a[0]), math.log(a[1]))))
        if k == "int":
            return int(rng.integers(a[0], a[1] + 1))
        return a[int(rng.integers(len(a)))]

    def values(self) -> list:
        """The extreme (or every) value this distribution can take, for range checks."""
        return list(self.args)


_KINDS = ("uniform", "loguniform", "int", "choice")


def _number(x) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)


def _parse_dist(value) -> Dist:
    if isinstance(value, dict):
        if len(value) != 1 or next(iter(value)) not in _KINDS:
            raise ValueError(
                f"got {_show(value)}; allowed: a value, or a table with one key of "
                f"{', '.join(_KINDS)}, e.g. {{ uniform = [0.1, 0.9] }}"
            )
        kind, args = next(iter(value.items()))
        if kind == "choice":
            if not isinstance(args, list) or not args:
                raise ValueError(f"choice: got {_show(args)}; allowed: a non-empty list")
            return Dist("choice", tuple(args))
        if not (isinstance(args, list) and len(args) == 2 and all(_number(x) for x in args)):
            raise ValueError(f"{kind}: got {_show(args)}; allowed: [low, high], two finite "
                             "numbers")
        lo, hi = args
        if lo > hi:
            raise ValueError(f"{kind}: low {lo} > high {hi}; allowed: low <= high")
        if kind == "loguniform" and lo <= 0:
            raise ValueError(f"loguniform: got [{lo}, {hi}]; allowed: 0 < low <= high")
        if kind == "int" and not all(isinstance(x, int) for x in args):
            raise ValueError(f"int: got {_show(args)}; allowed: [low, high], two integers")
        return Dist(kind, (lo, hi))
    if isinstance(value, list):
        raise ValueError(f"got {_show(value)}; allowed: a single value or a distribution table")
    if isinstance(value, float) and not math.isfinite(value):
        raise ValueError(f"got {value}; allowed: a finite number")
    return Dist("fixed", (value,))


def D(ge: float | None = None, le: float | None = None, gt: float | None = None,  # noqa: N802
      options: tuple | None = None, integer: bool = False):
    """A distribution field whose every possible value satisfies the bounds (or is one of
    ``options``)."""
    if options is not None:
        allowed = "one of " + ", ".join(repr(o) for o in options)
    else:
        bits = [f">= {ge:g}" if ge is not None else "", f"> {gt:g}" if gt is not None else "",
                f"<= {le:g}" if le is not None else ""]
        allowed = ("integers" if integer else "numbers") + " " + " and ".join(b for b in bits if b)

    def check(value) -> Dist:
        dist = value if isinstance(value, Dist) else _parse_dist(value)
        for v in dist.values():
            if options is not None:
                ok = v in options
            else:
                ok = _number(v) and (not integer or isinstance(v, int)) and not (
                    (ge is not None and v < ge) or (le is not None and v > le)
                    or (gt is not None and v <= gt))
            if not ok:
                raise ValueError(f"value {_show(v)} is not allowed; allowed: {allowed.strip()}")
        return dist

    return Annotated[Any, AfterValidator(check)]


Fraction = D(ge=0.0, le=1.0)
Positive = D(gt=0.0, le=1e6)
AnyNumber = D(ge=-1e6, le=1e6)
FracVec = tuple[Fraction, Fraction, Fraction]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, arbitrary_types_allowed=True)


class DefectsSpec(_Strict):
    """``[defects]``: the drawn defects replace the base scene's defects."""

    count: D(ge=0, le=16, integer=True) = Dist("int", (0, 3))
    shape: D(options=SHAPES) = Dist("choice", SHAPES)
    position: FracVec = (Dist("uniform", (0.0, 1.0)),) * 3
    size: D(gt=0.0, le=1.0) = Dist("loguniform", (0.06, 0.25))
    aspect: D(gt=0.0, le=100.0) = Dist("fixed", (1.0,))
    axis: D(options=("x", "y", "z")) = Dist("choice", ("x", "y", "z"))
    E_ratio: D(gt=0.0, le=1e9) = Dist("loguniform", (1e-3, 500.0))
    rho_ratio: D(gt=0.0, le=1e6) = Dist("fixed", (1.0,))
    nu: D(gt=-1.0, le=0.499) | None = None
    tension_ratio: D(gt=0.0, le=1e9) = Dist("loguniform", (0.05, 20.0))
    areal_density_ratio: D(gt=0.0, le=1e6) = Dist("fixed", (1.0,))


class ExcitationSpec(_Strict):
    """``[excitation]``: keys left out keep the base scene's value."""

    kind: D(options=("pluck", "velocity", "force", "none")) | None = None
    at: FracVec | None = None
    direction: tuple[AnyNumber, AnyNumber, AnyNumber] | None = None
    radius: D(ge=0.0, le=1e3) | None = None
    displacement: D(ge=1e-12, le=1e3) | None = None


class CameraVary(_Strict):
    """``[camera]``: the viewpoint turned about ``look_at`` within a cone around the base
    viewing direction (uniform over the spherical cap), at a scaled distance."""

    cone_deg: D(ge=0.0, le=89.0) = Dist("fixed", (0.0,))
    distance_scale: D(gt=0.0, le=100.0) = Dist("fixed", (1.0,))


class GeometryVary(_Strict):
    """``[geometry]`` (box bases only): per-axis multipliers of the base box size."""

    aspect: tuple[Positive, Positive, Positive] | None = None


class Family(_Strict):
    """A parsed family file (docs/families.md)."""

    name: str
    description: str = ""
    base: Annotated[Any, Field(description="scene name/path, inline table or {choice=[...]}")]
    attempts: int = Field(200, ge=1, le=10_000)
    defects: DefectsSpec | None = None
    excitation: ExcitationSpec | None = None
    camera: CameraVary | None = None
    geometry: GeometryVary | None = None
    vary: dict[str, Annotated[Any, AfterValidator(_parse_dist)]] = {}
    source: str | None = Field(default=None, exclude=True)


# --------------------------------------------------------------------------- loading
def find_family(name_or_path: str | Path) -> Path:
    """A family file by path, or by name among the shipped families."""
    p = Path(name_or_path)
    if p.is_file():
        return p
    q = FAMILIES_DIR / f"{name_or_path}.toml"
    if q.is_file():
        return q
    raise FamilyError(f"{name_or_path}: no such family file, and not a shipped family; shipped "
                      f"families: {', '.join(list_families()) or '(none)'}")


def list_families() -> list[str]:
    """Names of the shipped families."""
    return sorted(p.stem for p in FAMILIES_DIR.glob("*.toml"))


def is_family(spec: str | Path) -> bool:
    """Whether ``spec`` names a shipped family or is a TOML file with a top-level ``base``."""
    p = Path(spec)
    if p.is_file():
        try:
            return "base" in tomllib.loads(p.read_text())
        except (tomllib.TOMLDecodeError, UnicodeDecodeError, OSError):
            return False
    return (FAMILIES_DIR / f"{spec}.toml").is_file()


@functools.lru_cache(maxsize=32)
def _load_cached(path: str, mtime: float) -> Family:
    p = Path(path)
    try:
        data = tomllib.loads(p.read_text())
    except tomllib.TOMLDecodeError as error:
        raise FamilyError(f"{p}: not valid TOML: {error}") from None
    except UnicodeDecodeError:
        raise FamilyError(f"{p}: not a text (UTF-8 TOML) file") from None
    return parse_family(data, str(p))


def load_family(name_or_path: str | Path | Family) -> Family:
    """Read and validate a family (a file path or a shipped family name)."""
    if isinstance(name_or_path, Family):
        return name_or_path
    p = find_family(name_or_path).resolve()
    return _load_cached(str(p), p.stat().st_mtime)


def parse_family(data: dict, source: str = "<family>") -> Family:
    """Validate a family dict; errors are one line naming ``source``, the key and what is
    allowed. The base scene is loaded and checked too."""
    try:
        fam = Family.model_validate(data)
    except ValidationError as error:
        msg = _format_error(source, error)
        if "allowed keys here" in msg:  # _format_error knows scene keys, not family keys
            msg = _family_extra_keys(source, error) or msg
        raise FamilyError(msg) from None
    if not fam.name or not all(c.isalnum() or c in "_." for c in fam.name):
        raise FamilyError(f"{source}: key 'name': got {fam.name!r}; allowed: letters, digits, "
                          "'_' and '.' (no '-': it separates family, split and index)")
    fam = fam.model_copy(update={"source": source})
    for ref in _base_refs(fam):
        _base_scene(fam, ref)  # raises on a bad base
    for key in fam.vary:
        if key.split(".")[0] not in Scene.model_fields or key.split(".")[0] in ("name", "seed"):
            raise FamilyError(f"{source}: key 'vary.\"{key}\"': not a scene key; allowed: dotted "
                              "scene keys such as \"render.read_noise_dn\" (docs/scenes.md), "
                              "not name or seed")
    if fam.geometry is not None and fam.geometry.aspect is not None:
        for ref in _base_refs(fam):
            if _base_scene(fam, ref).geometry.kind != "box":
                raise FamilyError(f"{source}: key 'geometry.aspect': the base scene is not a "
                                  "box; allowed: only with box base scenes")
    return fam


def _family_extra_keys(source: str, error: ValidationError) -> str | None:
    sections = {"": Family, "defects": DefectsSpec, "excitation": ExcitationSpec,
                "camera": CameraVary, "geometry": GeometryVary}
    for e in error.errors():
        if e["type"] == "extra_forbidden":
            loc = [str(x) for x in e["loc"]]
            parent = ".".join(loc[:-1])
            model = sections.get(parent)
            if model is not None:
                allowed = ", ".join(k for k in model.model_fields if k != "source")
                return (f"{source}: key '{'.'.join(loc)}': unknown key; allowed keys here: "
                        f"{allowed}")
    return None


def _base_refs(fam: Family) -> list:
    b = fam.base
    if isinstance(b, dict) and set(b) == {"choice"}:
        if not isinstance(b["choice"], list) or not b["choice"]:
            raise FamilyError(f"{fam.source}: key 'base.choice': allowed: a non-empty list of "
                              "scene names or paths")
        return list(b["choice"])
    return [b]


def _base_scene(fam: Family, ref) -> Scene:
    if isinstance(ref, dict):
        data = {"name": fam.name, **ref}
        try:
            return parse_scene(data, f"{fam.source} (key 'base')")
        except SceneError as error:
            raise FamilyError(str(error)) from None
    if not isinstance(ref, str):
        raise FamilyError(f"{fam.source}: key 'base': got {_show(ref)}; allowed: a shipped "
                          "scene name, a scene path (relative to the family file), an inline "
                          "scene table or {choice = [names]}")
    q = Path(fam.source).parent / ref if fam.source else Path(ref)
    try:
        return load_scene(q if q.is_file() else ref)
    except SceneError as error:
        raise FamilyError(f"{fam.source}: key 'base': {error}") from None


# --------------------------------------------------------------------------- seeds
def _family_entropy(name: str) -> int:
    return int.from_bytes(hashlib.sha256(f"vvtbench-family:{name}".encode()).digest()[:16],
                          "little")


def _check_split(split: str, index: int) -> None:
    if split not in SPLIT_IDS:
        raise FamilyError(f"split {split!r}: allowed: {', '.join(SPLITS)}")
    if isinstance(index, bool) or not isinstance(index, int | np.integer) or not (
            0 <= int(index) <= MAX_INDEX):
        raise FamilyError(f"index {index!r}: allowed: an integer 0..{MAX_INDEX}")


def _seed_sequence(family: str, split: str, index: int) -> np.random.SeedSequence:
    return np.random.SeedSequence(_family_entropy(family),
                                  spawn_key=(SPLIT_IDS[split], int(index)))


def instance_seed(family: str, split: str, index: int) -> int:
    """The scene ``seed`` of instance ``index`` of ``split`` (63 bits, from its stream)."""
    _check_split(split, index)
    state = _seed_sequence(family, split, index).spawn(2)[1].generate_state(1, np.uint64)
    return int(state[0]) & (2**63 - 1)


def content_hash(scene_dict: dict) -> str:
    """sha256 of the physical scene: everything but name, description and seed."""
    body = {k: v for k, v in scene_dict.items() if k not in ("name", "description", "seed")}
    return hashlib.sha256(json.dumps(body, sort_keys=True).encode()).hexdigest()


def split_of_content(scene_dict: dict) -> str:
    """The only split a physical scene may belong to: sha256(content) mod 3."""
    return SPLITS[int(content_hash(scene_dict), 16) % len(SPLITS)]


# --------------------------------------------------------------------------- drawing
@functools.lru_cache(maxsize=8)
def _mesh_of(geometry_json: str):
    """The mesh of a geometry (paths absolute), its centroids and bounding box; cached."""
    from ..simulation.simulate import build_mesh

    g = json.loads(geometry_json)
    scene = parse_scene({"name": "mesh", "geometry": g}, "<family draw>")
    mesh = build_mesh(scene)
    return mesh, mesh.centroids, mesh.points.min(axis=0), mesh.points.max(axis=0)


def _set(d: dict, dotted: str, value) -> None:
    parts = dotted.split(".")
    node = d
    for p in parts[:-1]:
        node = node[int(p)] if isinstance(node, list) else node.setdefault(p, {})
    if isinstance(node, list):
        node[int(parts[-1])] = value
    else:
        node[parts[-1]] = value


def _fma(a: float, b: float, c: float) -> float:
    """``a * b + c`` rounded once (exactly, as a fused multiply-add does)."""
    from fractions import Fraction

    return float(Fraction(a) * Fraction(b) + Fraction(c))


def length3(v) -> float:
    """The length of a 3-vector as ``sqrt(fma(z, z, fma(y, y, x * x)))``, exactly: the same
    bits on every machine. (This is how the BLAS of the machine ``vvtbench-v1`` was drawn on
    summed it; a draw with another rounding would hash to other instances.)"""
    x, y, z = (float(c) for c in v)
    return math.sqrt(_fma(z, z, _fma(y, y, x * x)))


def _cone(rng, axis: np.ndarray, max_deg: float) -> np.ndarray:
    """A unit vector uniform over the spherical cap of half-angle ``max_deg`` around ``axis``."""
    a = axis / length3(axis)
    cos_t = 1.0 - rng.uniform() * (1.0 - math.cos(math.radians(max_deg)))
    phi = rng.uniform(0.0, 2 * math.pi)
    helper = np.array([1.0, 0, 0]) if abs(a[0]) < 0.9 else np.array([0, 1.0, 0])
    e1 = np.cross(a, helper)
    e1 /= length3(e1)
    e2 = np.cross(a, e1)
    sin_t = math.sqrt(max(0.0, 1.0 - cos_t**2))
    return cos_t * a + sin_t * (math.cos(phi) * e1 + math.sin(phi) * e2)


def _draw_defect(spec: DefectsSpec, rng, lo, hi, centroids, base_mat: dict,
                 drum: bool) -> dict:
    ext = hi - lo
    scale = float(np.min(ext[ext > 0]))
    shape = spec.shape.sample(rng)
    pos = lo + np.array([spec.position[i].sample(rng) for i in range(3)]) * ext
    r = spec.size.sample(rng) * scale
    asp = np.array([spec.aspect.sample(rng) for _ in range(3)])
    axis = spec.axis.sample(rng)
    if shape == "box":
        size = list(2 * r * asp)
    elif shape == "sphere":
        size = [r]
    elif shape == "ellipsoid":
        size = list(r * asp)
    else:
        size = [r, 2 * r * asp["xyz".index(axis)]]
    d: dict[str, Any] = {"shape": shape, "center": [float(x) for x in pos],
                         "size": [float(x) for x in size]}
    if shape == "cylinder":
        d["axis"] = "z" if drum else axis
    if drum:
        d["tension"] = base_mat["tension"] * spec.tension_ratio.sample(rng)
        d["areal_density"] = base_mat["areal_density"] * spec.areal_density_ratio.sample(rng)
    else:
        d["E"] = base_mat["E"] * spec.E_ratio.sample(rng)
        d["rho"] = base_mat["rho"] * spec.rho_ratio.sample(rng)
        if spec.nu is not None:
            d["nu"] = spec.nu.sample(rng)
    return d


def _catches_centroid(defect: dict, centroids: np.ndarray) -> bool:
    from .scene import Defect

    try:
        return bool(Defect.model_validate(defect).contains(centroids).any())
    except ValidationError:
        return False


def _absolute_paths(base: Scene, data: dict) -> None:
    """Files the base scene names relative to its own file, made absolute: the drawn scene
    lives elsewhere."""
    from .scene import BUILTIN_MESHES

    g = data["geometry"]
    if g.get("kind") == "mesh" and g.get("path") not in BUILTIN_MESHES:
        g["path"] = str(base.resolve_path(g["path"]))
    if data.get("material", {}).get("field_file"):
        data["material"]["field_file"] = str(base.resolve_path(data["material"]["field_file"]))
    signal = data.get("excitation", {}).get("signal") or {}
    if signal.get("kind") == "file":
        signal["path"] = str(base.resolve_path(signal["path"]))


def _draw_once(fam: Family, rng: np.random.Generator, attempts: int) -> dict:
    refs = _base_refs(fam)
    ref = refs[int(rng.integers(len(refs)))] if len(refs) > 1 else refs[0]
    base = _base_scene(fam, ref)
    data = base.to_toml_dict()
    drum = base.geometry.kind == "drum"
    _absolute_paths(base, data)
    base_view = np.subtract(data["camera"]["position"], data["camera"]["look_at"], dtype=float)
    # geometry: box aspect
    stretch = np.ones(3)
    if fam.geometry is not None and fam.geometry.aspect is not None:
        stretch = np.array([a.sample(rng) for a in fam.geometry.aspect], dtype=float)
        data["geometry"]["size"] = [float(s * k) for s, k in
                                    zip(data["geometry"]["size"], stretch, strict=True)]
        if "at" in data.get("excitation", {}):
            data["excitation"]["at"] = [float(a * k) for a, k in
                                        zip(data["excitation"]["at"], stretch, strict=True)]
        data["camera"]["look_at"] = [float(a * k) for a, k in
                                     zip(data["camera"]["look_at"], stretch, strict=True)]
    mesh, centroids, lo, hi = _mesh_of(json.dumps(data["geometry"], sort_keys=True))
    # generic keys first (noise, damping, ...), so the sections below win on overlaps
    for key, dist in fam.vary.items():
        _set(data, key, dist.sample(rng))
    # defects
    if fam.defects is not None:
        spec = fam.defects
        defects = []
        for _ in range(int(spec.count.sample(rng))):
            for _attempt in range(attempts):
                d = _draw_defect(spec, rng, lo, hi, centroids, data["material"], drum)
                if _catches_centroid(d, centroids):
                    defects.append(d)
                    break
            else:
                raise FamilyError(f"{fam.source}: key 'defects': no drawn defect caught an "
                                  f"element centroid in {attempts} attempts; allowed: sizes "
                                  "and positions that reach inside the body")
        data["material"]["defects"] = defects
    # excitation
    if fam.excitation is not None:
        ex = fam.excitation
        exd = data.setdefault("excitation", {})
        if ex.kind is not None:
            exd["kind"] = ex.kind.sample(rng)
        if ex.radius is not None:
            exd["radius"] = float(ex.radius.sample(rng))
        if ex.displacement is not None:
            exd["displacement"] = float(ex.displacement.sample(rng))
        if ex.direction is not None:
            for _attempt in range(attempts):
                v = np.array([c.sample(rng) for c in ex.direction], dtype=float)
                if length3(v) > 1e-3 * max(1.0, float(np.abs(v).max())):
                    break
            exd["direction"] = [float(x) for x in v / length3(v)]
        if ex.at is not None:
            radius = float(exd.get("radius", 0.0))
            pts = mesh.points
            from ..simulation.simulate import element_size

            h = element_size(mesh)
            for _attempt in range(attempts):
                at = lo + np.array([c.sample(rng) for c in ex.at]) * (hi - lo)
                if float(np.min(np.linalg.norm(pts - at, axis=1))) <= radius + h:
                    break
            else:
                raise FamilyError(f"{fam.source}: key 'excitation.at': no drawn point lay on "
                                  f"the body in {attempts} attempts")
            exd["at"] = [float(x) for x in at]
    # camera
    if fam.camera is not None:
        cam = data["camera"]
        look = np.asarray(cam["look_at"], dtype=float)
        dist = length3(base_view) * float(fam.camera.distance_scale.sample(rng))
        dist *= float(stretch.max())
        direction = _cone(rng, base_view, float(fam.camera.cone_deg.sample(rng)))
        cam["position"] = [float(x) for x in look + dist * direction]
    return data


def draw(family: str | Path | Family, split: str, index: int) -> Scene:
    """Instance ``index`` of ``split`` of ``family``: an ordinary scene named
    ``FAMILY-SPLIT-INDEX`` (index zero-padded to 5 digits) with its seed recorded.

    Deterministic in (family name, split, index). The draw is repeated from the same stream
    (at most ``attempts`` times) until the scene is valid (parses, every defect catches an
    element centroid, the pluck is on the body) and its content belongs to ``split``
    (:func:`split_of_content`); FamilyError if that never happens.
    """
    fam = load_family(family)
    _check_split(split, index)
    index = int(index)
    draw_ss, _ = _seed_sequence(fam.name, split, index).spawn(2)
    description = (f"instance {index} of split {split} of scene family {fam.name}"
                   + (f": {fam.description}" if fam.description else ""))
    return _draw_valid(fam, np.random.default_rng(draw_ss), f"{fam.name}-{split}-{index:05d}",
                       instance_seed(fam.name, split, index), description, split,
                       f"instance {index} of split {split}")


SECRET_BYTES = 32
"""The length of a challenge secret (:func:`draw_secret`): 256 random bits."""


def _secret_stream(fam: Family, secret: bytes, index: int) -> np.random.SeedSequence:
    import hmac

    key = hmac.new(bytes(secret), f"vvtbench-challenge-draw:{fam.name}".encode(),
                   hashlib.sha256).digest()
    return np.random.SeedSequence(int.from_bytes(key, "little"), spawn_key=(int(index),))


def draw_secret(family: str | Path | Family, secret: bytes, index: int, name: str) -> Scene:
    """Instance ``index`` of ``family`` drawn from ``secret`` (at least
    :data:`SECRET_BYTES` random bytes that only the host of a challenge holds), named ``name``.

    The same distributions as :func:`draw`, from a stream keyed by HMAC-SHA256(secret, family
    name): without the secret neither the material, the geometry, the pluck, the camera nor
    the scene ``seed`` can be recomputed, and no public split is drawn from such a stream. The
    scene's description names no family, split or index. Deterministic in (secret, family,
    index), so the host can draw the same instances again from the kept secret.
    """
    fam = load_family(family)
    if not isinstance(secret, bytes | bytearray) or len(secret) < SECRET_BYTES:
        raise FamilyError(f"challenge secret: allowed: at least {SECRET_BYTES} random bytes")
    if isinstance(index, bool) or not isinstance(index, int | np.integer) or not (
            0 <= int(index) <= MAX_INDEX):
        raise FamilyError(f"index {index!r}: allowed: an integer 0..{MAX_INDEX}")
    draw_ss, seed_ss = _secret_stream(fam, secret, index).spawn(2)
    seed = int(seed_ss.generate_state(1, np.uint64)[0]) & (2**63 - 1)
    return _draw_valid(fam, np.random.default_rng(draw_ss), name, seed,
                       "an instance of a challenge of record", None,
                       f"secret instance {int(index)}")


def _draw_valid(fam: Family, rng: np.random.Generator, name: str, seed: int,
                description: str, split: str | None, what: str) -> Scene:
    """The first valid draw from ``rng`` (in ``split`` when one is given)."""
    from ..simulation.simulate import load_nodes, material_fields

    attempts = fam.attempts
    last_error = "its content hashed to another split every time"
    for _ in range(attempts):
        data = _draw_once(fam, rng, attempts)
        data.update(name=name, seed=seed, description=description)
        try:
            scene = parse_scene(data, name)
        except SceneError as error:
            last_error = str(error)
            continue
        if split is not None and split_of_content(scene.to_toml_dict()) != split:
            continue
        try:
            mesh = _mesh_of(json.dumps(data["geometry"], sort_keys=True))[0]
            material_fields(scene, mesh)
            if scene.excitation.kind != "none":
                load_nodes(scene, mesh)
        except SceneError as error:
            last_error = str(error)
            continue
        return scene
    raise FamilyError(f"{fam.source}: {what}: no valid draw in {attempts} attempts (last: "
                      f"{last_error}); allowed: distributions that give valid scenes")


def family_info(family: str | Path | Family, split: str, index: int) -> dict:
    """What ``family.json`` records beside a drawn sample."""
    from .._version import __version__

    fam = load_family(family)
    src = Path(fam.source) if fam.source else None
    return {
        "family": fam.name,
        "split": split,
        "index": int(index),
        "seed": instance_seed(fam.name, split, index),
        "family_sha256": (hashlib.sha256(src.read_bytes()).hexdigest()
                          if src is not None and src.is_file() else None),
        "vvtbench": __version__,
    }

