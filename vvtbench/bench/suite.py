"""Benchmark suites: the suite file (``scenes/suites/*.toml``, docs/suites.md), validated by
pydantic models (unknown keys, wrong types and out-of-range or non-finite numbers are
:class:`SuiteError` one-liners naming the file, the key and what is allowed) and expanded into
:class:`Suite` / :class:`Track` / :class:`Variation`."""

from __future__ import annotations

import itertools
import json
import math
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from ..scene.scene import SCENES_DIR

SUITES_DIR = SCENES_DIR / "suites"
OBSERVATIONS = ("true", "extracted")
#: an observation source: "true", "extracted" (the default extractor, phase) or
#: "extracted:EXTRACTOR" (a registered extractor name, ``module:Class`` or ``path.py:Class``),
#: either extracted one optionally with "@VARIANT" (a named extraction variant,
#: ``[extract.variants.VARIANT]``)
OBSERVATION_PATTERN = r"^(true|extracted(:[^@\s]+)?(@[A-Za-z0-9_.-]+)?)$"
_OBSERVATION = ("'true', 'extracted' or 'extracted:EXTRACTOR' (a registered extractor name, "
                "module:Class or path/to/file.py:Class), an extracted one optionally with "
                "'@VARIANT' (a table [extract.variants.VARIANT])")
#: the name of an extraction variant (``[extract.variants.NAME]``, ``extracted@NAME``)
VARIANT_PATTERN = r"[A-Za-z0-9_.-]+"
SCENE_SECTIONS = ("seed", "description", "geometry", "material", "boundary", "damping",
                  "excitation", "simulation", "camera", "render")


def folder_name_problem(name: object) -> str | None:
    """Why ``name`` cannot name a folder vvtbench creates (a suite's run folder, a scene's
    sample folder): not letters, digits, '-', '_' and '.' only, or starting with '.' (hidden,
    '.' and '..'); None when it can.

    >>> folder_name_problem("paper"), folder_name_problem("../../victim") is not None
    (None, True)
    """
    if not isinstance(name, str) or not name:
        return "must be a non-empty string"
    if not all(c.isascii() and (c.isalnum() or c in "-_.") for c in name):
        return "may contain only letters, digits, '-', '_' and '.'"
    if name.startswith("."):
        return "must not start with '.' (no hidden folder, no '.' or '..')"
    return None


class SuiteError(ValueError):
    """A suite file is malformed; the message names the file, the key and what is allowed."""


# --------------------------------------------------------------------------- models

PositiveNumber = Annotated[float, Field(gt=0, allow_inf_nan=False)]
NonNegativeNumber = Annotated[float, Field(ge=0, allow_inf_nan=False)]
Fraction = Annotated[float, Field(ge=0, le=1, allow_inf_nan=False)]
Count = Annotated[int, Field(ge=1)]
ModeCount = Annotated[int, Field(ge=1, le=2000)]
Cells = Annotated[int, Field(ge=1, le=256)]
Frequency = Annotated[float, Field(gt=0, le=1e7, allow_inf_nan=False)]
SmallCount = Annotated[int, Field(ge=1, le=64)]
Name = Annotated[str, Field(min_length=1)]
Observation = Annotated[str, Field(pattern=OBSERVATION_PATTERN)]
Options = dict[str, Any]  # scene overrides and inference options, checked by _split_options


class _Strict(BaseModel):
    # strict: nothing is coerced ("5" is not 5, true is not 1), so what the runner hashes and
    # records is what the file says
    model_config = ConfigDict(extra="forbid", strict=True, frozen=True)


class InferenceOptions(_Strict):
    """The inference options of a variation (docs/suites.md)."""

    n_modes: ModeCount | None = Field(None, description="an integer >= 1 (at most 2000)")
    inference_shape: Annotated[list[Cells], Field(min_length=2, max_length=3)] | None = Field(
        None, description="a list of 3 integers >= 1 (at most 256; drums: 2)")
    geometry_scale: (PositiveNumber | Annotated[list[PositiveNumber],
                                                Field(min_length=3, max_length=3)] | None) = Field(
        None, description="a number > 0 (scales x), or [sx, sy, sz] of numbers > 0")
    nu: Annotated[float, Field(gt=-1, lt=0.5, allow_inf_nan=False)] | None = Field(
        None, description="a Poisson's ratio in (-1, 0.5)")
    inference_order: Literal[1, 2] | None = Field(None, description="1 (hex8) or 2 (hex27)")
    w0: PositiveNumber | None = Field(None, description="a number > 0 (Pa)")
    v0: PositiveNumber | None = Field(None, description="a number > 0 (kg/m^3)")
    w_mean: PositiveNumber | None = Field(None, description="a number > 0 (Pa)")
    visibility: Literal["depth", "normals"] | None = Field(
        None, description="'depth' (rest depth buffer) or 'normals' (facing the camera)")
    views: Annotated[int, Field(ge=1, le=16)] | None = Field(
        None, description="an integer in 1..16 (cameras on a ring around the object)")
    view_spread_deg: Annotated[float, Field(gt=0, le=360, allow_inf_nan=False)] | None = Field(
        None, description="a number in (0, 360] (degrees the ring of cameras spans)")


class ExtractVariant(_Strict):
    """A ``[extract.variants.NAME]`` table: extraction options over a track's (the options of
    :func:`vvtbench.modes.extract_modes` and merging; the same keys as ``[extract]``)."""

    fmin: Frequency | None = Field(None, description="a frequency > 0 (Hz, at most 1e7)")
    fmax: Frequency | None = Field(None, description="a frequency > 0 (Hz, at most 1e7)")
    prominence: NonNegativeNumber | None = Field(None, description="a number >= 0 (decades)")
    min_separation_hz: Frequency | None = Field(None,
                                                description="a frequency > 0 (Hz, at most 1e7)")
    max_modes: ModeCount | None = Field(None, description="an integer >= 1 (at most 2000)")
    min_power_ratio: NonNegativeNumber | None = Field(None, description="a number >= 0")
    n_scales: SmallCount | None = Field(None, description="an integer >= 1 (at most 64)")
    n_orientations: SmallCount | None = Field(None, description="an integer >= 1 (at most 64)")
    sigma: NonNegativeNumber | None = Field(None, description="a number >= 0 (pixels)")
    weighting: Literal["confidence", "none", "noise"] | None = Field(
        None, description="'confidence', 'none' or 'noise'")
    average: Count | None = Field(None, description="an integer >= 1 (frames)")
    detrend: Literal["mean", "linear", "none"] | None = Field(
        None, description="'mean', 'linear' or 'none'")
    reference: Literal["mean", "first"] | None = Field(
        None, description="'mean' or 'first' (what motion is measured against: the record's "
        "mean frame, the default, or its first frame)")
    shake_threshold: Fraction | None = Field(None, description="a MAC in [0, 1]")
    line_fit: bool | None = Field(None, description="true or false")
    product_roughness: Fraction | None = Field(
        None, description="a roughness in [0, 1] (distortion products above it are rejected)")
    faint_product_ratio: Fraction | None = Field(
        None, description="a power ratio in [0, 1] (fainter distortion products are rejected "
        "whatever their roughness; 0: off)")
    product_scaling: Literal["product", "weaker"] | None = Field(
        None, description="'product' or 'weaker' (what a faint product is measured against)")
    shape_attenuation: bool | None = Field(
        None, description="true or false (noisiest pixels of the mode shapes attenuated)")
    shape_fill: bool | None = Field(
        None, description="true or false (noisiest pixels of the mode shapes filled in from "
        "their neighbours)")
    reject_products: bool | None = Field(
        None, description="true or false (harmonics and intermodulation products of stronger "
        "modes rejected by phase and shape)")
    identifier: Literal["auto", "peaks", "era", "plscf"] | None = Field(
        None, description="'auto', 'peaks', 'era' or 'plscf' (how modes are identified; auto: "
        "ERA for a free decay, the peak picker for a driven record)")
    roughness_weighting: Literal["shape", "spectrum"] | None = Field(
        None, description="'shape' or 'spectrum' (pixel weights of the roughness tests)")
    min_reliable_fraction: NonNegativeNumber | None = Field(
        None, description="a number >= 0 (peaks with less of their energy on the reliable "
        "pixels are rejected)")
    merge_freq_tol: PositiveNumber | None = Field(
        None, description="a relative frequency tolerance > 0")
    merge_min_mac: Fraction | None = Field(None, description="a MAC in [0, 1]")


class ExtractOptions(ExtractVariant):
    """The ``[extract]`` table: options of :func:`vvtbench.modes.extract_modes` and merging,
    motion extractor overrides and named extraction variants."""

    extractor: dict[Name, Options] = Field(
        default_factory=dict, description="tables [extract.extractor.NAME] of motion extractor "
        "config overrides (key = value); the extractor of an observation 'extracted:NAME'")
    variants: dict[Name, ExtractVariant] = Field(
        default_factory=dict, description="tables [extract.variants.NAME] of extraction "
        "options over a track's; the extraction of an observation 'extracted@NAME'")


class FieldOptions(_Strict):
    """The ``[tracks.field]`` table: the track's videos reach the solver as a field user's do
    (:mod:`vvtbench.field.track`): re-encoded as a camera writes them, read back by the field
    readers, the camera estimated from noisy clicks, the object given as a surface mesh."""

    format: Literal["tiff", "mraw", "h264"] = Field(
        "tiff", description="'tiff' (an image sequence), 'mraw' (Photron .cih + packed .mraw) "
        "or 'h264' (an 8-bit .mp4)")
    bit_depth: Literal[8, 12, 16] = Field(
        12, description="8, 12 or 16 (bits of the TIFF or MRAW samples)")
    crf: Annotated[int, Field(ge=0, le=51)] = Field(
        23, description="an integer in 0..51 (H.264 constant rate factor; 'h264' only)")
    bitrate_mbps: Annotated[float, Field(gt=0, le=10000, allow_inf_nan=False)] | None = Field(
        None, description="a number in (0, 10000] (Mbit per second of recording at the "
        "capture rate; 'h264' only, instead of crf)")
    clicks: Annotated[int, Field(ge=6, le=1000)] = Field(
        10, description="an integer in 6..1000 (clicked correspondences)")
    click_noise_px: Annotated[float, Field(ge=0, le=100, allow_inf_nan=False)] = Field(
        0.5, description="a number in [0, 100] (px: Gaussian noise per click coordinate)")
    click_seed: Annotated[int, Field(ge=0, le=2**32 - 1)] | None = Field(
        None, description="an integer >= 0 (seed of the click noise; default: the row's seed)")
    object: Literal["stl", "scene"] = Field(
        "stl", description="'stl' (a surface mesh file of the object) or 'scene' (the scene "
        "file)")
    mesh: Literal["auto", "tet"] = Field(
        "auto", description="'auto' (an STL block meshed as its voxel grid, other surfaces in "
        "tetrahedra) or 'tet' (tetrahedra always)")
    max_error_px: Annotated[float, Field(gt=0, le=1000, allow_inf_nan=False)] = Field(
        2.0, description="a number in (0, 1000] (px: the largest click reprojection error "
        "accepted)")

    @model_validator(mode="after")
    def _one_encoding(self):
        given = self.model_fields_set
        if self.format == "h264" and "bit_depth" in given:
            raise ValueError("'bit_depth' applies to 'tiff' and 'mraw' (H.264 is 8-bit); "
                             "allowed with 'h264': crf")
        for key in ("crf", "bitrate_mbps"):
            if self.format != "h264" and key in given:
                raise ValueError(f"'{key}' applies to 'h264' only (format is "
                                 f"{self.format!r}); allowed: bit_depth")
        if {"crf", "bitrate_mbps"} <= given:
            raise ValueError("give 'crf' or 'bitrate_mbps', not both (allowed: one of them)")
        return self


SceneGroup = Name | Annotated[list[Name], Field(min_length=1)]
_SCENES = ("a list of scene names or paths (relative to the suite file), or of lists of them "
           "(videos of one object whose modes are merged)")
_SOLVER = "tables [solver.NAME] of solver config overrides (key = value)"


class TrackFile(_Strict):
    """One ``[[tracks]]`` table."""

    name: Name | None = Field(None, description="a non-empty string")
    description: str = Field("", description="a string")
    scenes: list[SceneGroup] = Field(default_factory=list, description=_SCENES)
    seeds: Annotated[list[Annotated[int, Field(ge=0)]], Field(min_length=1)] | None = Field(
        None, description="a non-empty list of integers >= 0")
    observations: Annotated[list[Observation], Field(min_length=1)] | None = Field(
        None, description=f"a non-empty list of {_OBSERVATION}")
    defaults: Options = Field(default_factory=dict, description="a table of options")
    variations: list[Options] = Field(default_factory=list,
                                      description="a list of tables of options")
    sweep: Options | None = Field(None, description="a table of key = [values]")
    solvers: list[Name] | None = Field(None, description="a list of solver names")
    solver: dict[Name, Options] = Field(default_factory=dict, description=_SOLVER)
    solver_sweep: dict[Name, dict[str, Annotated[list[Any], Field(min_length=1)]]] = Field(
        default_factory=dict, description="tables [solver_sweep.NAME] of key = [values]")
    family: Name | None = Field(None, description="a scene family (scenes/families/NAME.toml) "
                                "whose instances are the track's scenes")
    split: Literal["train", "val", "test"] = Field(
        "test", description="'train', 'val' or 'test' (the family's split)")
    count: Annotated[int, Field(ge=1, le=100000)] | None = Field(
        None, description="an integer in 1..100000 (instances of the family)")
    start: Annotated[int, Field(ge=0, le=2**32 - 1)] = Field(
        0, description="an integer >= 0 (the first instance index)")
    extract: ExtractOptions | None = Field(
        None, description="a table of extraction options over the suite's [extract] (motion "
        "extractors are configured in the suite's [extract.extractor.NAME] only)")
    field: FieldOptions | None = Field(
        None, description="a table of field-path settings (format, bit_depth, crf, "
        "bitrate_mbps, clicks, click_noise_px, click_seed, object, mesh, max_error_px)")


class SuiteFile(_Strict):
    """A suite file (docs/suites.md); with no ``[[tracks]]`` its scenes, variations and sweep
    make one track, ``main``."""

    name: Name | None = Field(None, description="a non-empty string")
    description: str = Field("", description="a string")
    scenes: list[SceneGroup] = Field(default_factory=list, description=_SCENES)
    solvers: list[Name] = Field(default_factory=list, description="a list of solver names")
    seeds: Annotated[list[Annotated[int, Field(ge=0)]], Field(min_length=1)] = Field(
        [0], description="a non-empty list of integers >= 0")
    observations: Annotated[list[Observation], Field(min_length=1)] = Field(
        ["true"], description=f"a non-empty list of {_OBSERVATION}")
    defaults: Options = Field(default_factory=dict, description="a table of options")
    extract: ExtractOptions = Field(default_factory=ExtractOptions,
                                    description="a table of extraction options")
    solver: dict[Name, Options] = Field(default_factory=dict, description=_SOLVER)
    tracks: list[TrackFile] | None = Field(None, description="[[tracks]] tables")
    variations: list[Options] | None = Field(None, description="a list of tables of options")
    sweep: Options | None = Field(None, description="a table of key = [values]")
    timeout: Annotated[float, Field(gt=0, le=30 * 86400, allow_inf_nan=False)] | None = Field(
        None, description="seconds > 0 (at most 30 days): the time limit of one solve")
    memory_gb: Annotated[float, Field(gt=0, le=1e6, allow_inf_nan=False)] | None = Field(
        None, description="GB > 0: the memory limit of one solve")


INFERENCE_KEYS = tuple(InferenceOptions.model_fields)
EXTRACT_KEYS = tuple(ExtractOptions.model_fields)
_PARENTS = {"": SuiteFile, "tracks": TrackFile, "extract": ExtractOptions,
            "field": FieldOptions, "variants": ExtractVariant}
_DESCRIPTIONS = {name: f.description for model in (SuiteFile, TrackFile, ExtractOptions,
                                                   InferenceOptions, FieldOptions)
                 for name, f in model.model_fields.items()}
_TYPE_TAGS = {"str", "int", "float", "bool", "list", "dict", "none"}


def _path(loc: tuple, prefix: str = "") -> tuple[str, str]:
    """(dotted key path of a pydantic error location, the last model field on it), e.g.
    ``tracks[0].seeds[1]`` and ``seeds`` for ``('tracks', 0, 'seeds', 1)``; union-member tags
    such as ``constrained-float`` are left out."""
    out, field_name = prefix, ""
    for p in loc:
        if isinstance(p, int):
            out += f"[{p}]"
            continue
        s = str(p)
        if s in _TYPE_TAGS or "[" in s or s.startswith(("constrained-", "function-")):
            continue
        out = f"{out}.{s}" if out else s
        if s in _DESCRIPTIONS:
            field_name = s
    return out, field_name


def _format(source: str, error: ValidationError, prefix: str = "", root=None,
            index: int | None = None) -> str:
    """One line: the file, then each key with its problem and what is allowed. ``prefix``: the
    key path of what was validated; ``index``: of the value in a sweep's list of values."""

    def loc(e):
        return e["loc"] if index is None else (e["loc"][0], index, *e["loc"][1:])

    errors = [(*_path(loc(e), prefix), e) for e in error.errors()]

    def mismatch(key, e):  # a union member of the wrong type, when another one says more
        return e["type"].endswith("_type") and any(
            (k == key or k.startswith((f"{key}[", f"{key}."))) and not o["type"].endswith("_type")
            for k, _, o in errors if o is not e)

    problems: dict[str, tuple[str, list[str]]] = {}
    for key, name, e in errors:
        if mismatch(key, e):
            continue
        msgs = problems.setdefault(key, (name, []))[1]
        if e["type"] == "extra_forbidden":
            parent = _path(e["loc"][:-1])[1]
            model = root if root is not None and not parent else _PARENTS.get(parent)
            allowed = ", ".join(model.model_fields) if model is not None else "(none)"
            msgs.append(f"unknown key; allowed keys here: {allowed}")
        elif e["type"] == "finite_number":
            msgs.append(f"{e.get('input')!r} is not a finite number")
        else:
            msgs.append(e["msg"].removeprefix("Value error, "))
    parts = []
    for key, (name, msgs) in problems.items():
        allowed = _DESCRIPTIONS.get(name)
        if msgs[0].startswith("unknown key"):
            msg = msgs[0]
        elif len(msgs) > 1 and allowed:  # a union reports one error per member
            msg = f"invalid value (allowed: {allowed})"
        else:
            msg = "; ".join(msgs) + (f" (allowed: {allowed})" if allowed else "")
        parts.append(f"key '{key or '<top level>'}': {msg}")
    return f"{source}: " + "; ".join(parts)


def _check_finite(value, source: str, key: str) -> None:
    """Every number anywhere in the file is finite (TOML allows nan and inf)."""
    if isinstance(value, float) and not math.isfinite(value):
        raise SuiteError(f"{source}: key '{key}': {value!r} is not a finite number (allowed: "
                         "finite numbers only)")
    if isinstance(value, dict):
        for k, v in value.items():
            _check_finite(v, source, f"{key}.{k}" if key else str(k))
    elif isinstance(value, list):
        for i, v in enumerate(value):
            _check_finite(v, source, f"{key}[{i}]")


def _check_inference(values: dict, source: str, path: str, index: int | None = None) -> None:
    """Validate inference option values (``index``: of a sweep's list of values)."""
    try:
        InferenceOptions.model_validate(values)
    except ValidationError as error:
        raise SuiteError(_format(source, error, path, InferenceOptions, index)) from None


def _join(path: str, key: str) -> str:
    return f"{path}.{key}" if path else key


def _flatten(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict) and v and key.split(".")[0] in SCENE_SECTIONS:
            out.update(_flatten(v, key + "."))
        else:
            out[key] = v
    return out


def _split_options(opts: dict, source: str, path: str) -> tuple[dict, dict]:
    """Flat options -> (scene overrides by dotted key, inference options); ``path`` is the
    options' key path in the suite file, for errors."""
    scene_over, infer = {}, {}
    for key, value in _flatten(opts).items():
        head = key.split(".")[0]
        if head in SCENE_SECTIONS:
            scene_over[key] = value
        elif key in INFERENCE_KEYS:
            infer[key] = value
        else:
            raise SuiteError(
                f"{source}: key '{_join(path, key)}': unknown key; allowed: scene keys as dotted "
                f"paths under {', '.join(SCENE_SECTIONS)} (e.g. 'simulation.duration'), or "
                f"inference options {', '.join(INFERENCE_KEYS)}")
    _check_inference(infer, source, path)
    return scene_over, infer


def apply_overrides(scene_dict: dict, overrides: dict) -> dict:
    """A deep copy of ``scene_dict`` with dotted keys set (``"camera.resolution": [128, 128]``;
    list items by index: ``"material.defects.0.E": 1e6``)."""
    out = json.loads(json.dumps(scene_dict))
    for key, value in overrides.items():
        parts = key.split(".")
        node = out
        for p in parts[:-1]:
            if isinstance(node, list):
                node = node[int(p)]
            else:
                node = node.setdefault(p, {})
        last = parts[-1]
        if isinstance(node, list):
            node[int(last)] = value
        else:
            node[last] = value
    return out


@dataclass
class Variation:
    name: str
    scene_overrides: dict = field(default_factory=dict)
    inference: dict = field(default_factory=dict)


@dataclass
class Track:
    name: str
    scenes: list[list[str]]          # each entry: one scene, or videos of one object to merge
    variations: list[Variation]
    seeds: list[int]
    observations: list[str]
    description: str = ""
    solvers: list[str] | None = None            # restricts the run's solvers to these names
    solver_config: dict[str, dict] = field(default_factory=dict)
    solver_sweep: dict[str, list[tuple[str, dict]]] = field(default_factory=dict)
    #: ``[tracks.extract]``: extraction options over the suite's ``[extract]``
    extract: dict = field(default_factory=dict)
    #: ``[tracks.field]`` as written (None: the sample's lossless video and true camera)
    field: dict | None = None


@dataclass
class Suite:
    """A parsed suite file (see docs/suites.md)."""

    name: str
    tracks: list[Track]
    solvers: list[str]
    solver_config: dict[str, dict] = field(default_factory=dict)
    extract: dict = field(default_factory=dict)
    description: str = ""
    source: str = ""
    raw: dict = field(default_factory=dict)
    timeout: float | None = None     # seconds per solve (None: the runner's default)
    memory_gb: float | None = None   # memory limit per solve (None: the runner's default)
    #: extractor as written -> {"spec" (loadable), "name", "version", "config" (overrides)}, for
    #: every extractor an observation names or ``[extract.extractor.NAME]`` configures
    extractors: dict[str, dict] = field(default_factory=dict)
    #: ``[extract.variants.NAME]``: NAME -> extraction options over a track's (the extraction
    #: of an observation ``"extracted@NAME"``)
    extract_variants: dict[str, dict] = field(default_factory=dict)

    @property
    def scene_names(self) -> list[str]:
        seen = []
        for t in self.tracks:
            for group in t.scenes:
                for s in group:
                    if s not in seen:
                        seen.append(s)
        return seen


def _variations(tdata: dict, source: str, path: str, defaults: dict) -> list[Variation]:
    out = []
    base = dict(defaults)
    for i, v in enumerate(tdata.get("variations", [])):
        where = f"{_join(path, 'variations')}[{i}]"
        v = dict(v)
        name = v.pop("name", None)
        if name is not None and not (isinstance(name, str) and name):
            raise SuiteError(f"{source}: key '{where}.name': {name!r} is not allowed (allowed: "
                             "a non-empty string)")
        so, inf = _split_options({**base, **v}, source, where)
        if name is None:
            name = ",".join(f"{k}={_fmt(val)}" for k, val in _flatten(v).items()) or "base"
        out.append(Variation(str(name), so, inf))
    sweep = tdata.get("sweep")
    if sweep:
        where = _join(path, "sweep")
        flat = _flatten(sweep)
        for k, vals in flat.items():
            if not isinstance(vals, list) or not vals:
                raise SuiteError(f"{source}: key '{where}.{k}': {vals!r} is not allowed "
                                 "(allowed: a non-empty list of values)")
            if k in INFERENCE_KEYS:
                for n, val in enumerate(vals):
                    _check_inference({k: val}, source, where, index=n)
        keys = list(flat)
        for combo in itertools.product(*(flat[k] for k in keys)):
            v = dict(zip(keys, combo, strict=True))
            so, inf = _split_options({**base, **v}, source, where)
            out.append(Variation(",".join(f"{k}={_fmt(x)}" for k, x in v.items()), so, inf))
    if not out:
        so, inf = _split_options(base, source, _join(path, "defaults"))
        out.append(Variation("base", so, inf))
    names = [v.name for v in out]
    dup = {n for n in names if names.count(n) > 1}
    if dup:
        raise SuiteError(f"{source}: key '{path or '<top level>'}': duplicate variation names "
                         f"{sorted(dup)} (allowed: distinct names)")
    return out


def _fmt(x) -> str:
    if isinstance(x, float):
        return f"{x:g}"
    if isinstance(x, list):
        return "x".join(_fmt(v) for v in x)
    return str(x)


def find_suite(name_or_path: str | Path) -> Path:
    p = Path(name_or_path)
    if p.is_file():
        return p
    q = SUITES_DIR / f"{name_or_path}.toml"
    if q.is_file():
        return q
    known = sorted(x.stem for x in SUITES_DIR.glob("*.toml"))
    raise SuiteError(f"{name_or_path}: no such suite file, and not a shipped suite; shipped "
                     f"suites: {', '.join(known) or '(none)'}")


def load_suite(name_or_path: str | Path) -> Suite:
    """Read and validate a suite TOML (a file or a shipped suite name)."""
    path = find_suite(name_or_path)
    try:
        data = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as error:
        raise SuiteError(f"{path}: not valid TOML: {error}") from None
    return parse_suite(data, str(path))


def parse_suite(data: dict, source: str = "<suite>") -> Suite:
    """Validate a suite dict (the parsed TOML) and expand it; errors are :class:`SuiteError`
    one-liners naming ``source``, the key path and what is allowed."""
    from ..scene.scene import SceneError, find_scene

    _check_finite(data, source, "")
    try:
        SuiteFile.model_validate(data)
    except ValidationError as error:
        raise SuiteError(_format(source, error)) from None
    # The validated file is expanded from ``data`` itself: strict validation coerced nothing,
    # and the runner hashes and records the values as written (1, not 1.0).
    name = data.get("name") or Path(source).stem
    problem = folder_name_problem(name)
    if problem:  # the name becomes the default run folder, runs/NAME
        raise SuiteError(f"{source}: key 'name': {name!r} {problem}")
    defaults = data.get("defaults", {})
    _split_options(defaults, source, "defaults")  # validate keys early
    extract = dict(data.get("extract", {}))
    extractors = {name: _check_extractor(name, table, source, f"extract.extractor.{name}")
                  for name, table in extract.pop("extractor", {}).items()}
    variants = {name: dict(table) for name, table in extract.pop("variants", {}).items()}
    for vname in variants:
        if not re.fullmatch(VARIANT_PATTERN, vname):
            raise SuiteError(f"{source}: key 'extract.variants.{vname}': {vname!r} is not "
                             "allowed (allowed: a name of letters, digits, '-', '_' and '.')")
    solver_config = data.get("solver", {})
    solvers = data.get("solvers", [])
    seeds = data.get("seeds", [0])
    observations = data.get("observations", ["true"])
    raw_tracks = data.get("tracks")
    if raw_tracks is None:
        raw_tracks = [{"name": "main", "scenes": data.get("scenes", []),
                       **{k: data[k] for k in ("variations", "sweep") if k in data}}]
    tracks = []
    for i, t in enumerate(raw_tracks):
        path = f"tracks[{i}]" if "tracks" in data else ""
        tname = t.get("name", f"track{i}")
        scenes = []
        if t.get("family") is not None:
            if t.get("scenes") or t.get("count") is None:
                raise SuiteError(f"{source}: key '{_join(path, 'family')}': a family track "
                                 "gives 'count' (and optionally 'split', 'start') instead of "
                                 "'scenes'")
            from ..scene.families import FamilyError, load_family

            try:
                load_family(t["family"])
            except (FamilyError, SceneError) as error:
                raise SuiteError(f"{source}: key '{_join(path, 'family')}': {error}") from None
            first = int(t.get("start", 0))
            scenes = [[f"family:{t['family']}:{t.get('split', 'test')}:{i}"]
                      for i in range(first, first + int(t["count"]))]
        for j, s in enumerate(t.get("scenes", [])):
            group = [s] if isinstance(s, str) else s
            for g in group:
                try:
                    find_scene(scene_ref(g, source))
                except SceneError as error:
                    raise SuiteError(f"{source}: key '{_join(path, 'scenes')}[{j}]': {error}"
                                     ) from None
            scenes.append(group)
        if not scenes:
            raise SuiteError(f"{source}: key '{_join(path, 'scenes')}': track {tname!r} has no "
                             f"scenes (allowed: {_SCENES})")
        obs = t.get("observations", observations)
        if len(set(obs)) != len(obs):
            key = _join(path, "observations") if "observations" in t else "observations"
            raise SuiteError(f"{source}: key '{key}': duplicate observation sources "
                             f"{sorted({o for o in obs if obs.count(o) > 1})} (allowed: "
                             "distinct sources)")
        for j, o in enumerate(obs):
            _check_variant(o, variants, source, f"{_join(path, 'observations')}[{j}]"
                           if "observations" in t else f"observations[{j}]")
            ext_name = observation_extractor(o)
            if ext_name is not None and ext_name not in extractors:
                extractors[ext_name] = _check_extractor(
                    ext_name, {}, source, f"{_join(path, 'observations')}[{j}]")
        tseeds = t.get("seeds", seeds)
        tdefaults = {**defaults, **t.get("defaults", {})}
        if "defaults" in t:
            _split_options(t["defaults"], source, _join(path, "defaults"))
        ssweep = {}
        for sname, table in t.get("solver_sweep", {}).items():
            keys = list(table)
            ssweep[sname] = [
                (",".join(f"{sname}.{k}={_fmt(x)}" for k, x in zip(keys, combo, strict=True)),
                 dict(zip(keys, combo, strict=True)))
                for combo in itertools.product(*(table[k] for k in keys))]
        tsolvers = t.get("solvers")
        textract = dict(t.get("extract") or {})
        if "extractor" in textract:
            raise SuiteError(f"{source}: key '{_join(path, 'extract.extractor')}': motion "
                             "extractors are configured in the suite's [extract.extractor.NAME] "
                             "(allowed here: the extraction options of [extract])")
        if "variants" in textract:
            raise SuiteError(f"{source}: key '{_join(path, 'extract.variants')}': extraction "
                             "variants are named in the suite's [extract.variants.NAME] "
                             "(allowed here: the extraction options of [extract])")
        for j, o in enumerate(obs):
            _check_variant_differs(o, {**extract, **textract}, variants, source,
                                   f"{_join(path, 'observations')}[{j}]" if "observations" in t
                                   else f"observations[{j}]", tname)
        tfield = t.get("field")
        if tfield is not None:
            _check_field_track(obs, source, path, "observations" in t)
        tracks.append(Track(tname, scenes, _variations(t, source, path, tdefaults),
                            list(tseeds), list(obs), t.get("description", ""), tsolvers,
                            dict(t.get("solver", {})), ssweep, textract,
                            None if tfield is None else dict(tfield)))
    names = [t.name for t in tracks]
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise SuiteError(f"{source}: key 'tracks': duplicate track names {dup} (allowed: "
                         "distinct names)")
    timeout, memory_gb = data.get("timeout"), data.get("memory_gb")
    return Suite(name, tracks, list(solvers), solver_config, extract,
                 data.get("description", ""), source, data,
                 None if timeout is None else float(timeout),
                 None if memory_gb is None else float(memory_gb), extractors, variants)


def _check_field_track(observations: list[str], source: str, path: str, own: bool) -> None:
    """A field track observes extracted modes only (true modes never pass through a video)."""
    bad = [o for o in observations if observation_kind(o) != "extracted"]
    if bad:
        key = _join(path, "observations") if own else "observations"
        raise SuiteError(f"{source}: key '{key}': {bad[0]!r} in a track with [tracks.field] "
                         "(allowed: 'extracted' or 'extracted:EXTRACTOR': the field path "
                         "observes the modes of its video)")


def observation_kind(observation: str) -> str:
    """``"true"`` or ``"extracted"`` (for ``"extracted:NAME"`` too).

    >>> observation_kind("extracted:farneback")
    'extracted'
    """
    return "extracted" if observation.startswith("extracted") else observation


def observation_extractor(observation: str) -> str | None:
    """The extractor an observation names (``"extracted:NAME"`` -> ``NAME``), else None.

    >>> observation_extractor("extracted:path/to/flow.py:Flow"), observation_extractor("true")
    ('path/to/flow.py:Flow', None)
    >>> observation_extractor("extracted:farneback@picker"), observation_extractor("extracted@a")
    ('farneback', None)
    """
    head, _, name = observation_base(observation).partition(":")
    return name if head == "extracted" and name else None


def observation_variant(observation: str) -> str | None:
    """The extraction variant an observation names (``"extracted@NAME"``,
    ``"extracted:EXTRACTOR@NAME"`` -> ``NAME``), else None.

    >>> observation_variant("extracted:farneback@picker"), observation_variant("extracted")
    ('picker', None)
    """
    if not observation.startswith("extracted"):
        return None
    _, at, name = observation.rpartition("@")
    return name if at and name else None


def observation_base(observation: str) -> str:
    """The source an observation's variant is paired with: the observation without its
    ``@VARIANT`` (the same extractor with the track's own extraction options).

    >>> observation_base("extracted:farneback@picker"), observation_base("true")
    ('extracted:farneback', 'true')
    """
    variant = observation_variant(observation)
    return observation[:-len(variant) - 1] if variant else observation


def _check_variant(observation: str, variants: dict, source: str, key: str) -> None:
    """An observation's ``@VARIANT`` names a table ``[extract.variants.VARIANT]``."""
    name = observation_variant(observation)
    if name is not None and name not in variants:
        raise SuiteError(f"{source}: key '{key}': {observation!r} names the extraction variant "
                         f"{name!r}, which the suite does not define (allowed: "
                         f"{', '.join(sorted(variants)) or 'none defined'}; a variant is a "
                         "table [extract.variants.NAME])")


def _check_variant_differs(observation: str, base: dict, variants: dict, source: str,
                           key: str, track: str) -> None:
    """A variant changes the extraction of ``track``: the same options as the track's base
    would repeat its extraction under another name."""
    name = observation_variant(observation)
    if name is None:
        return
    over = variants[name]
    if {**base, **over} == base:
        raise SuiteError(f"{source}: key '{key}': the extraction variant {name!r} sets the "
                         f"options track {track!r} already extracts with "
                         f"({', '.join(f'{k} = {v!r}' for k, v in over.items()) or 'none'}); "
                         "allowed: a variant that changes an extraction option")


def _check_extractor(name: str, table: dict, source: str, key: str) -> dict:
    """``{"spec", "name", "version", "config"}`` of the extractor ``name`` with the overrides
    ``table`` (validated now: a missing extractor or a bad option is a one-line error)."""
    from ..solving.plugins import PluginError
    from ..solving.sealed import describe_sealed

    file, _, cls_name = name.rpartition(":")
    spec = f"{scene_ref(file, source)}:{cls_name}" if file.endswith(".py") else name
    try:  # imported and configured in a sealed child, never here
        d = describe_sealed("extractor", spec, table)
    except PluginError as error:
        raise SuiteError(f"{source}: key '{key}': {error}") from None
    return {"spec": spec, "name": d["name"], "version": d["version"],
            "config": {k: v for k, v in d["config"].items() if k in table}}


def scene_ref(name: str, source: str) -> str:
    q = Path(source).parent / name
    return str(q) if q.is_file() else name
