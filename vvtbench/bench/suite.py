"""Benchmark suites: the suite file (``scenes/suites/*.toml``, docs/suites.md) parsed into
:class:`Suite` / :class:`Track` / :class:`Variation`."""

from __future__ import annotations

import itertools
import json
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from ..scene import SCENES_DIR

SUITES_DIR = SCENES_DIR / "suites"
OBSERVATIONS = ("true", "extracted")
SCENE_SECTIONS = ("seed", "description", "geometry", "material", "boundary", "damping",
                  "excitation", "simulation", "camera", "render")
INFERENCE_KEYS = {
    "n_modes": int, "inference_shape": list, "geometry_scale": (float, list), "nu": float,
    "inference_order": int, "w0": float, "v0": float, "w_mean": float,
}
EXTRACT_KEYS = ("fmin", "fmax", "prominence", "min_separation_hz", "max_modes",
                "min_power_ratio", "n_scales", "n_orientations", "sigma", "weighting",
                "average", "detrend", "shake_threshold", "merge_freq_tol", "merge_min_mac")


class SuiteError(ValueError):
    """A suite file is malformed; the message names the file, the key and what is allowed."""


def _flatten(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict) and key.split(".")[0] in SCENE_SECTIONS:
            out.update(_flatten(v, key + "."))
        else:
            out[key] = v
    return out


def _split_options(opts: dict, where: str) -> tuple[dict, dict]:
    """Flat options -> (scene overrides by dotted key, inference options)."""
    scene_over, infer = {}, {}
    for key, value in _flatten(opts).items():
        head = key.split(".")[0]
        if head in SCENE_SECTIONS:
            scene_over[key] = value
        elif key in INFERENCE_KEYS:
            infer[key] = value
        else:
            raise SuiteError(
                f"{where}: unknown key {key!r}; allowed: scene keys as dotted paths under "
                f"{', '.join(SCENE_SECTIONS)} (e.g. 'simulation.duration'), or inference "
                f"options {', '.join(INFERENCE_KEYS)}")
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

    @property
    def scene_names(self) -> list[str]:
        seen = []
        for t in self.tracks:
            for group in t.scenes:
                for s in group:
                    if s not in seen:
                        seen.append(s)
        return seen


def _variations(tdata: dict, where: str, defaults: dict) -> list[Variation]:
    out = []
    base = dict(defaults)
    for i, v in enumerate(tdata.get("variations", [])):
        if not isinstance(v, dict):
            raise SuiteError(f"{where}.variations[{i}]: must be a table")
        v = dict(v)
        name = v.pop("name", None)
        so, inf = _split_options({**base, **v}, f"{where}.variations[{i}]")
        if name is None:
            name = ",".join(f"{k}={_fmt(val)}" for k, val in _flatten(v).items()) or "base"
        out.append(Variation(str(name), so, inf))
    sweep = tdata.get("sweep")
    if sweep:
        if not isinstance(sweep, dict):
            raise SuiteError(f"{where}.sweep: must be a table of key = [values]")
        flat = _flatten(sweep)
        for k, vals in flat.items():
            if not isinstance(vals, list) or not vals:
                raise SuiteError(f"{where}.sweep.{k}: must be a non-empty list of values")
        keys = list(flat)
        for combo in itertools.product(*(flat[k] for k in keys)):
            v = dict(zip(keys, combo, strict=True))
            so, inf = _split_options({**base, **v}, f"{where}.sweep")
            out.append(Variation(",".join(f"{k}={_fmt(x)}" for k, x in v.items()), so, inf))
    if not out:
        so, inf = _split_options(base, f"{where}")
        out.append(Variation("base", so, inf))
    names = [v.name for v in out]
    dup = {n for n in names if names.count(n) > 1}
    if dup:
        raise SuiteError(f"{where}: duplicate variation names {sorted(dup)}")
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


_TOP_KEYS = {"name", "description", "scenes", "solvers", "seeds", "observations", "defaults",
             "extract", "solver", "tracks", "variations", "sweep"}
_TRACK_KEYS = {"name", "description", "scenes", "seeds", "observations", "defaults",
               "variations", "sweep", "solvers", "solver", "solver_sweep"}


def parse_suite(data: dict, source: str = "<suite>") -> Suite:
    from ..scene import SceneError, find_scene

    unknown = set(data) - _TOP_KEYS
    if unknown:
        raise SuiteError(f"{source}: unknown key(s) {sorted(unknown)}; allowed: "
                         f"{', '.join(sorted(_TOP_KEYS))}")
    name = data.get("name") or Path(source).stem
    defaults = data.get("defaults", {})
    if not isinstance(defaults, dict):
        raise SuiteError(f"{source}: 'defaults' must be a table")
    _split_options(defaults, f"{source}: defaults")  # validate keys early
    extract = dict(data.get("extract", {}))
    bad = set(extract) - set(EXTRACT_KEYS)
    if bad:
        raise SuiteError(f"{source}: extract: unknown key(s) {sorted(bad)}; allowed: "
                         f"{', '.join(EXTRACT_KEYS)}")
    solver_config = data.get("solver", {})
    if not isinstance(solver_config, dict) or not all(isinstance(v, dict)
                                                      for v in solver_config.values()):
        raise SuiteError(f"{source}: [solver.NAME] tables hold solver config overrides")
    solvers = data.get("solvers", [])
    seeds = data.get("seeds", [0])
    observations = data.get("observations", ["true"])
    raw_tracks = data.get("tracks")
    if raw_tracks is None:
        raw_tracks = [{"name": "main", "scenes": data.get("scenes", []),
                       **{k: data[k] for k in ("variations", "sweep") if k in data}}]
    tracks = []
    for i, t in enumerate(raw_tracks):
        where = f"{source}: tracks[{i}]"
        if not isinstance(t, dict):
            raise SuiteError(f"{where}: must be a table")
        unknown = set(t) - _TRACK_KEYS
        if unknown:
            raise SuiteError(f"{where}: unknown key(s) {sorted(unknown)}; allowed: "
                             f"{', '.join(sorted(_TRACK_KEYS))}")
        tname = t.get("name", f"track{i}")
        where = f"{source}: track {tname!r}"
        scenes = []
        for s in t.get("scenes", []):
            group = [s] if isinstance(s, str) else s
            if not isinstance(group, list) or not group or not all(isinstance(g, str)
                                                                   for g in group):
                raise SuiteError(f"{where}: scenes entries are names/paths, or lists of "
                                 "names (videos of one object whose modes are merged)")
            for g in group:
                try:
                    find_scene(scene_ref(g, source))
                except SceneError as error:
                    raise SuiteError(f"{where}: {error}") from None
            scenes.append(group)
        if not scenes:
            raise SuiteError(f"{where}: no scenes")
        obs = t.get("observations", observations)
        bad = [o for o in obs if o not in OBSERVATIONS]
        if bad:
            raise SuiteError(f"{where}: observations {bad} not allowed; allowed: "
                             f"{', '.join(OBSERVATIONS)}")
        tseeds = t.get("seeds", seeds)
        if not all(isinstance(s, int) for s in tseeds):
            raise SuiteError(f"{where}: seeds must be integers")
        tdefaults = {**defaults, **t.get("defaults", {})}
        ssweep = {}
        for sname, table in t.get("solver_sweep", {}).items():
            if not isinstance(table, dict) or not all(isinstance(v, list) and v
                                                      for v in table.values()):
                raise SuiteError(f"{where}: [tracks.solver_sweep.{sname}] holds key = [values]")
            keys = list(table)
            ssweep[sname] = [
                (",".join(f"{sname}.{k}={_fmt(x)}" for k, x in zip(keys, combo, strict=True)),
                 dict(zip(keys, combo, strict=True)))
                for combo in itertools.product(*(table[k] for k in keys))]
        tsolvers = t.get("solvers")
        if tsolvers is not None and not all(isinstance(x, str) for x in tsolvers):
            raise SuiteError(f"{where}: solvers must be a list of solver names")
        tracks.append(Track(tname, scenes, _variations(t, where, tdefaults), list(tseeds),
                            list(obs), t.get("description", ""), tsolvers,
                            dict(t.get("solver", {})), ssweep))
    names = [t.name for t in tracks]
    if len(set(names)) != len(names):
        raise SuiteError(f"{source}: duplicate track names")
    return Suite(name, tracks, list(solvers), solver_config, extract,
                 data.get("description", ""), source, data)


def scene_ref(name: str, source: str) -> str:
    q = Path(source).parent / name
    return str(q) if q.is_file() else name
