"""Benchmark suites and the runner: generate -> extract -> observe -> solve -> evaluate.

A *suite* (``scenes/suites/*.toml``, format in docs/suites.md) expands into *runs*: one per
track x scene x variation x seed x observation source x solver. Each run is a chain of stage
tasks; tasks shared between runs (the same video, the same extracted modes, the same inverse
problem) are computed once:

    generate(scene)            -> sample folder (video.mkv + truth), vvtbench.dataset.generate
    extract(generate)          -> modes.npz/json, vvtbench.modes.extract_modes
    observe(scene, options, [extract...]) -> problem.pkl, the InverseProblem a solver sees
    solve(observe, solver, config)         -> estimate.npz/json
    evaluate(solve, observe)               -> metrics.json + fields.npz (estimate and truth grids)

Every task's output lives in ``OUT/cache/<stage>/<key>/`` where ``key`` is a content hash of
the task's inputs (resolved scene dict, stage options, vvtbench version, upstream keys): a
rerun finds the folder and recomputes nothing; a changed parameter changes the keys of the
tasks that depend on it only. A task writes into ``<key>.tmp-<random>/`` and renames it to
``<key>/`` at the end, so a crash leaves no half result. A failing task writes
``OUT/cache/<stage>/<key>.error/`` (error.json, traceback.txt) and its dependants are skipped;
the failure becomes a row with ``status = "error"`` and is retried on the next run.

Execution: in process (``workers=1``), on a local process pool (``workers=N``), or on an
existing Dask distributed cluster (``scheduler="tcp://host:port"``; the cache folder must be
on a file system the workers share).
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import itertools
import json
import os
import pickle
import shutil
import sys
import time
import tomllib
import traceback
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from . import __version__
from .scene import SCENES_DIR

SUITES_DIR = SCENES_DIR / "suites"
STAGES = ("generate", "extract", "observe", "solve", "evaluate")
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
METRIC_COLUMNS = ("nc_w", "nc_v", "nc_w_uncentered", "nc_v_uncentered", "sigma_star_w",
                  "sigma_star_v", "nc_at_sigma_star_w", "nc_at_sigma_star_v", "mode_mac",
                  "freq_err_raw", "freq_err_scaled")
# Bump when a stage's output format or meaning changes (part of every task key).
CACHE_FORMAT = 1


class SuiteError(ValueError):
    """A suite file is malformed; the message names the file, the key and what is allowed."""


# --------------------------------------------------------------------------- hashing / io


def _canon(x):
    if isinstance(x, dict):
        return {str(k): _canon(v) for k, v in sorted(x.items(), key=lambda kv: str(kv[0]))}
    if isinstance(x, (list, tuple)):
        return [_canon(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, Path):
        return str(x)
    return x


def content_hash(*parts, n: int = 16) -> str:
    """sha256 (first ``n`` hex digits) of the canonical JSON of ``parts``."""
    text = json.dumps(_canon(list(parts)), sort_keys=True, default=str, allow_nan=True)
    return hashlib.sha256(text.encode()).hexdigest()[:n]


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, float) and not np.isfinite(x):
        return None
    return x


def _write_json(path: Path, data) -> None:
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.tmp")
    tmp.write_text(json.dumps(_jsonable(data), indent=1, default=str))
    os.replace(tmp, path)


# --------------------------------------------------------------------------- suites


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
    from .scene import SceneError, find_scene

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
                    find_scene(_scene_ref(g, source))
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


def _scene_ref(name: str, source: str) -> str:
    q = Path(source).parent / name
    return str(q) if q.is_file() else name


# --------------------------------------------------------------------------- task graph


@dataclass
class Task:
    stage: str
    key: str
    deps: list[str]
    payload: dict
    label: str = ""


@dataclass
class Run:
    """One row of the results table."""

    track: str
    scene: str
    variation: str
    seed: int
    observation: str
    solver: str            # spec as given (name or file.py:Class)
    n_modes: int
    variation_options: dict
    dataset_revision: str
    solve_key: str | None = None
    evaluate_key: str | None = None
    observe_key: str | None = None
    config: dict | None = None
    config_hash: str = ""
    solver_name: str = ""
    solver_version: str = ""
    setup_error: str | None = None


def _resolve_scene(ref: str, source: str, overrides: dict, seed: int) -> dict:
    from .scene import load_scene, parse_scene

    scene = load_scene(_scene_ref(ref, source))
    data = apply_overrides(scene.to_toml_dict(), {**overrides, "seed": seed})
    try:
        parsed = parse_scene(data, f"{scene.source} (suite overrides)")
    except Exception as error:
        raise SuiteError(str(error)) from None
    return parsed.to_toml_dict()


def solver_setup(spec: str, overrides: dict | None):
    """(class, config dict) for a solver spec with suite/CLI overrides."""
    from .plugins import load_solver, parse_overrides

    cls = load_solver(spec)
    items = [f"{k}={json.dumps(v) if not isinstance(v, str) else v}"
             for k, v in (overrides or {}).items()]
    cfg = parse_overrides(items, cls.Config)
    return cls, dataclasses.asdict(cfg)


def build_graph(suite: Suite, solvers: list[str], solver_config: dict | None = None,
                until: str = "evaluate") -> tuple[dict[str, Task], list[Run]]:
    """All tasks (by key) and runs (rows) of a suite."""
    tasks: dict[str, Task] = {}
    runs: list[Run] = []
    cfgs = {**suite.solver_config}
    for k, v in (solver_config or {}).items():
        cfgs[k] = {**cfgs.get(k, {}), **v}
    solver_info: dict = {}

    def info(spec: str, extra: dict | None = None):
        ck = (spec, json.dumps(_canon(extra or {}), sort_keys=True))
        if ck not in solver_info:
            try:
                from .plugins import load_solver

                name = load_solver(spec).name
                over = {**(cfgs.get(spec) or cfgs.get(name) or {}), **(extra or {})}
                cls, cfg = solver_setup(spec, over)
                solver_info[ck] = (cls.name, str(cls.version), cfg, None)
            except Exception as error:  # a broken plug-in becomes error rows
                solver_info[ck] = (spec, "", {}, f"setup: {type(error).__name__}: {error}")
        return solver_info[ck]

    stop = STAGES.index(until)

    def add(stage, key_parts, deps, payload, label, register=True):
        key = content_hash(stage, CACHE_FORMAT, __version__, *key_parts, deps)
        k = f"{stage}/{key}"
        if register and k not in tasks:
            tasks[k] = Task(stage, k, deps, payload, label)
        return k

    for track in suite.tracks:
        for group, var, seed in itertools.product(track.scenes, track.variations, track.seeds):
            scene_dicts = [_resolve_scene(s, suite.source, var.scene_overrides, seed)
                           for s in group]
            scene_label = "+".join(d["name"] for d in scene_dicts)
            needed = stop < 1 or "extracted" in track.observations
            gen_keys = [add("generate", [d], [], {"scene": d}, d["name"], register=needed)
                        for d in scene_dicts]
            dataset_revision = content_hash(*gen_keys)
            if stop < 1:
                continue
            extract_opts = {k: v for k, v in suite.extract.items()}
            n_modes = int(var.inference.get("n_modes", 10))
            for obs in track.observations:
                ext_keys = []
                if obs == "extracted":
                    ext_keys = [add("extract", [extract_opts], [g], {"options": extract_opts},
                                    name) for g, name in zip(gen_keys, [d["name"] for d in
                                                                        scene_dicts],
                                                             strict=True)]
                if stop < 2:
                    continue
                inf = {"n_modes": n_modes, **var.inference}
                obs_payload = {"scene": scene_dicts[0], "inference": inf, "observation": obs,
                               "extract": extract_opts}
                obs_key = add("observe", [scene_dicts[0], inf, obs,
                                          extract_opts if obs == "extracted" else {}],
                              ext_keys, obs_payload, scene_label)
                if stop < 3:
                    continue
                for spec, vlabel, extra in _track_solvers(track, solvers, info):
                    name, version, cfg, err = info(spec, extra)
                    cfg_hash = content_hash(name, cfg)
                    vname = var.name if not vlabel else (
                        vlabel if var.name == "base" else f"{var.name},{vlabel}")
                    run = Run(track.name, scene_label, vname, seed, obs, spec, n_modes,
                              {**var.scene_overrides, **var.inference,
                               **{f"{name}.{k}": x for k, x in (extra or {}).items()}},
                              dataset_revision,
                              observe_key=obs_key, config=cfg, config_hash=cfg_hash,
                              solver_name=name, solver_version=version, setup_error=err)
                    if err is None:
                        sk = add("solve", [name, version, cfg], [obs_key],
                                 {"solver": spec, "config": cfg}, f"{name}:{scene_label}")
                        ek = add("evaluate", [], [sk, obs_key], {}, f"{name}:{scene_label}")
                        run.solve_key, run.evaluate_key = sk, ek
                    runs.append(run)
    return tasks, runs


# --------------------------------------------------------------------------- stage bodies


def _track_solvers(track: Track, solvers: list[str], info):
    """(spec, variation label, config overrides) of each solver run in a track."""
    out = []
    for spec in solvers:
        name = info(spec)[0]
        if track.solvers is not None and name not in track.solvers and spec not in track.solvers:
            continue
        base = dict(track.solver_config.get(name, {}))
        sweep = track.solver_sweep.get(name)
        if sweep:
            out.extend((spec, label, {**base, **over}) for label, over in sweep)
        else:
            out.append((spec, "", base))
    return out


def _stage_generate(cache: Path, task: Task, out: Path, deps: dict) -> dict:
    from .generate import generate
    from .scene import parse_scene

    scene = parse_scene(task.payload["scene"], task.payload["scene"]["name"])
    # generate() is itself atomic and resumable inside its own folder
    work = cache / "generate" / "_work" / task.key.split("/")[1]
    path = generate(scene, work, progress=False, overwrite=True)
    shutil.move(str(path), str(out / "sample"))
    shutil.rmtree(work, ignore_errors=True)
    return {"sample": "sample"}


def _sample_path(cache: Path, gen_key: str) -> Path:
    return cache / gen_key / "sample"


def _stage_extract(cache: Path, task: Task, out: Path, deps: dict) -> dict:
    from .dataset import open_sample
    from .modes import extract_modes

    sample = open_sample(_sample_path(cache, task.deps[0]))
    opts = {k: v for k, v in task.payload["options"].items() if not k.startswith("merge_")}
    ms = extract_modes(sample.video_path, sample.fps, **opts)
    ms.save(out)
    return {"n_modes": len(ms), "frequencies_hz": ms.frequencies_hz.tolist()}


def build_problem(scene_dict: dict, inference: dict, observation: str,
                  modesets: list | None = None, camera=None, extract_opts: dict | None = None):
    """The InverseProblem of a scene under inference options, observing true image-space modes
    or extracted ones (``modesets``: one ModeSet per video of the object, merged)."""
    from .fem.mesh import box_mesh
    from .problem import InverseProblem
    from .scene import parse_scene
    from .simulate import simulate

    scene = parse_scene(scene_dict, scene_dict["name"])
    inf = dict(inference)
    n_modes = int(inf.pop("n_modes", 10))
    shape = tuple(inf.pop("inference_shape", (20, 20) if scene.geometry.kind == "drum"
                          else (8, 8, 8)))
    order = int(inf.pop("inference_order", 1))
    gscale = inf.pop("geometry_scale", 1.0)
    if isinstance(gscale, list):
        gscale = tuple(gscale)
    result = simulate(scene, transient=False)
    n_true = len(result.modes)
    k_true = n_true if observation == "extracted" else min(n_modes, n_true)
    if observation == "true" and n_modes > n_true:
        raise ValueError(f"asked for {n_modes} modes; the scene simulates "
                         f"{n_true} (simulation.n_modes)")
    mesh = None
    if order != 1:
        if scene.geometry.kind != "box":
            raise ValueError("inference_order applies to box geometries only")
        s = np.ones(3)
        if np.isscalar(gscale):
            s[0] = gscale
        else:
            s[:] = gscale
        mesh = box_mesh(shape, tuple(float(x) for x in np.asarray(scene.geometry.size) * s),
                        order)
    problem = InverseProblem.from_simulation(
        result, camera=camera, inference_shape=shape, n_modes=k_true, geometry_scale=gscale,
        inference_mesh=mesh, **{k: inf[k] for k in ("nu", "w0", "v0", "w_mean") if k in inf})
    if observation == "true":
        problem.meta["observation"] = "true"
        return problem
    # extracted modes: sampled at the visible vertices' pixels (of the true object)
    opts = extract_opts or {}
    return problem.with_extracted_modes(
        modesets, camera, n_modes, merge_freq_tol=opts.get("merge_freq_tol", 0.02),
        merge_min_mac=opts.get("merge_min_mac", 0.8))


def _stage_observe(cache: Path, task: Task, out: Path, deps: dict) -> dict:
    from .dataset import open_sample
    from .modes import ModeSet

    p = task.payload
    modesets, camera = None, None
    if p["observation"] == "extracted":
        modesets = [ModeSet.load(cache / k) for k in task.deps]
        gen_key = json.loads((cache / task.deps[0] / "task.json").read_text())["deps"][0]
        camera = open_sample(_sample_path(cache, gen_key)).camera
    problem = build_problem(p["scene"], p["inference"], p["observation"], modesets, camera,
                            p.get("extract"))
    with open(out / "problem.pkl", "wb") as f:
        pickle.dump(problem, f, protocol=pickle.HIGHEST_PROTOCOL)
    return {"n_modes": problem.n_modes, "n_params": problem.n_params,
            "meta": {k: v for k, v in problem.meta.items() if k != "camera"}}


def load_problem(cache: Path, observe_key: str):
    with open(cache / observe_key / "problem.pkl", "rb") as f:
        return pickle.load(f)


TRUTH_META_KEYS = ("matched_true_modes", "extraction_mac", "true_frequencies_hz")


def blind_problem(problem, reference: bool = False):
    """What a solver sees: no true material; unless it is a ``reference`` solver (class
    attribute ``uses_truth = True``, e.g. the oracle) also no full-field 3-D modes and none of
    the truth-derived provenance in ``meta`` (``TRUTH_META_KEYS``)."""
    from dataclasses import replace

    meta = dict(problem.meta)
    if reference:
        return replace(problem, w_true=None, v_true=None, meta=meta)
    for key in TRUTH_META_KEYS:
        meta.pop(key, None)
    return replace(problem, w_true=None, v_true=None, modes_3d=None, meta=meta)


def _stage_solve(cache: Path, task: Task, out: Path, deps: dict) -> dict:

    from .plugins import load_solver, parse_overrides

    problem = load_problem(cache, task.deps[0])
    cls, _ = load_solver(task.payload["solver"]), None
    blind = blind_problem(problem, reference=getattr(cls, "uses_truth", False))
    cfg_dict = task.payload["config"]
    cfg = parse_overrides([], cls.Config)
    cfg = dataclasses.replace(cfg, **cfg_dict) if cfg_dict else cfg
    t0 = time.perf_counter()
    est = cls(cfg).solve(blind)
    wall = time.perf_counter() - t0
    np.savez_compressed(out / "estimate.npz", w_params=est.w, v_params=est.v,
                        w=problem.to_grid(est.w), v=problem.to_grid(est.v),
                        active=problem.voxel_map.active)
    doc = {"solver": est.solver or cls.name, "solver_version": est.version or cls.version,
           "config": est.config or cfg_dict, "runtime_s": est.runtime_s or wall,
           "wall_s": wall, "converged": est.converged, "iterations": len(est.history),
           "history": est.history,
           "extra": est.extra_scalars()}
    _write_json(out / "estimate.json", doc)
    return {"runtime_s": doc["runtime_s"], "iterations": len(est.history)}


def _stage_evaluate(cache: Path, task: Task, out: Path, deps: dict) -> dict:
    from .metrics import intrinsic_resolution, mode_match, score

    solve_key, observe_key = task.deps
    problem = load_problem(cache, observe_key)
    est = np.load(cache / solve_key / "estimate.npz")
    w, v = est["w_params"], est["v_params"]
    m = score(problem, w, v, modes=False)
    metrics = {k: m.get(k) for k in ("nc_w", "nc_v", "nc_w_uncentered", "nc_v_uncentered",
                                     "sigma_star_w", "sigma_star_v")}
    metrics["nc_at_sigma_star_w"] = m.get("nc_w_at_sigma_star")
    metrics["nc_at_sigma_star_v"] = m.get("nc_v_at_sigma_star")
    curves = {}
    for name, e, t in (("w", w, problem.w_true), ("v", v, problem.v_true)):
        ir = intrinsic_resolution(problem.to_grid(e), problem.to_grid(t))
        curves[name] = {"sigmas": ir["sigmas"], "nc": ir["nc"]}
    notes = []
    try:
        if not (np.all(np.isfinite(w)) and np.all(np.isfinite(v)) and np.all(v > 0)):
            raise ValueError("estimate has non-positive or non-finite density")
        mm = mode_match(problem, w, v)
        metrics.update(mode_mac=mm["mean_mac"], freq_err_raw=mm["freq_rel_error"],
                       freq_err_scaled=mm["freq_rel_error_scaled"])
    except Exception as error:
        metrics.update(mode_mac=None, freq_err_raw=None, freq_err_scaled=None)
        notes.append(f"mode match not computed: {type(error).__name__}: {error}")
    np.savez_compressed(out / "fields.npz", w=problem.to_grid(w), v=problem.to_grid(v),
                        w_true=problem.to_grid(problem.w_true),
                        v_true=problem.to_grid(problem.v_true))
    _write_json(out / "metrics.json", {"metrics": metrics, "intrinsic_resolution": curves,
                                       "notes": notes, "n_modes_observed": problem.n_modes})
    return {"metrics": metrics, "notes": notes, "n_modes_observed": problem.n_modes}


STAGE_FUNCS = {"generate": _stage_generate, "extract": _stage_extract,
               "observe": _stage_observe, "solve": _stage_solve, "evaluate": _stage_evaluate}


def execute_task(cache: str, task: Task, threads: int | None = None) -> dict:
    """Run one task unless its output exists; never raises. Returns a status dict:
    ``{"key", "status": ok|error|skipped, "computed": bool, "seconds", "result"|"error"}``."""
    cache = Path(cache)
    final = cache / task.key
    done = final / "task.json"
    if done.is_file():
        try:
            info = json.loads(done.read_text())
            return {"key": task.key, "status": "ok", "computed": False, "seconds": 0.0,
                    "result": info.get("result", {})}
        except (OSError, ValueError):
            shutil.rmtree(final, ignore_errors=True)
    for dep in task.deps:
        if not (cache / dep / "task.json").is_file():
            err_file = cache / f"{dep}.error" / "error.json"
            msg = "upstream task failed"
            if err_file.is_file():
                msg = json.loads(err_file.read_text()).get("error", msg)
            return {"key": task.key, "status": "skipped", "computed": False, "seconds": 0.0,
                    "error": msg, "upstream": dep}
    tmp = cache / f"{task.key}.tmp-{uuid.uuid4().hex[:8]}"
    tmp.mkdir(parents=True)
    err_dir = cache / f"{task.key}.error"
    t0 = time.perf_counter()
    try:
        if threads:
            from threadpoolctl import threadpool_limits

            with threadpool_limits(limits=threads):
                result = STAGE_FUNCS[task.stage](cache, task, tmp, {})
        else:
            result = STAGE_FUNCS[task.stage](cache, task, tmp, {})
        seconds = time.perf_counter() - t0
        _write_json(tmp / "task.json", {"stage": task.stage, "key": task.key,
                                        "deps": task.deps, "payload": task.payload,
                                        "result": result, "seconds": seconds,
                                        "vvtbench": __version__})
        if final.exists():  # a concurrent duplicate finished first
            shutil.rmtree(tmp, ignore_errors=True)
        else:
            os.replace(tmp, final)
        shutil.rmtree(err_dir, ignore_errors=True)
        return {"key": task.key, "status": "ok", "computed": True, "seconds": seconds,
                "result": _jsonable(result)}
    except BaseException as error:  # noqa: BLE001 -- a task must never stop the suite
        if isinstance(error, KeyboardInterrupt):
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        shutil.rmtree(tmp, ignore_errors=True)
        msg = f"{task.stage}: {type(error).__name__}: {error}"
        err_dir.mkdir(parents=True, exist_ok=True)
        (err_dir / "traceback.txt").write_text(traceback.format_exc())
        _write_json(err_dir / "error.json", {"error": msg, "task": task.key})
        return {"key": task.key, "status": "error", "computed": True,
                "seconds": time.perf_counter() - t0, "error": msg,
                "traceback": f"{task.key}.error/traceback.txt"}


# --------------------------------------------------------------------------- executors


class _Inline:
    class _Done:
        def __init__(self, value):
            self._v = value

        def result(self):
            return self._v

    def submit(self, fn, *args):
        return self._Done(fn(*args))

    def wait_any(self, futures):
        return set(futures)

    def close(self):
        pass


class _Pool:
    def __init__(self, workers: int):
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        ctx = mp.get_context("spawn" if sys.platform == "darwin" else "forkserver")
        self.ex = ProcessPoolExecutor(max_workers=workers, mp_context=ctx)

    def submit(self, fn, *args):
        return self.ex.submit(fn, *args)

    def wait_any(self, futures):
        from concurrent.futures import FIRST_COMPLETED, wait

        done, _ = wait(futures, return_when=FIRST_COMPLETED)
        return done

    def close(self):
        self.ex.shutdown(wait=True, cancel_futures=True)


class _Dask:
    def __init__(self, scheduler):
        from distributed import Client

        if isinstance(scheduler, str):
            self.client, self.own = Client(scheduler), True
        else:  # a Client or a cluster object
            self.client = scheduler if hasattr(scheduler, "submit") else Client(scheduler)
            self.own = not hasattr(scheduler, "submit")

    def submit(self, fn, *args):
        return self.client.submit(fn, *args, pure=False)

    def wait_any(self, futures):
        from distributed import wait

        done, _ = wait(list(futures), return_when="FIRST_COMPLETED")
        return set(done)

    def close(self):
        if self.own:
            self.client.close()


def _execute(tasks: dict[str, Task], cache: Path, executor, progress: bool,
             threads: int | None) -> dict[str, dict]:
    from tqdm import tqdm

    remaining = dict(tasks)
    done: dict[str, dict] = {}
    bars = {}
    for stage in STAGES:
        n = sum(t.stage == stage for t in tasks.values())
        if n:
            bars[stage] = tqdm(total=n, desc=f"{stage:9s}", position=len(bars), leave=True,
                               disable=not progress, file=sys.stderr, unit="task")
    running: dict[Any, str] = {}
    try:
        while remaining or running:
            ready = [k for k, t in remaining.items() if all(d in done for d in t.deps)]
            for k in ready:
                task = remaining.pop(k)
                try:
                    running[executor.submit(execute_task, str(cache), task, threads)] = k
                except Exception as error:  # e.g. a broken process pool
                    done[k] = {"key": k, "status": "error", "computed": True, "seconds": 0.0,
                               "error": f"{task.stage}: cannot submit: "
                                        f"{type(error).__name__}: {error}"}
            if not running:
                break
            for fut in executor.wait_any(list(running)):
                k = running.pop(fut)
                try:
                    res = fut.result()
                except Exception as error:  # worker died etc.
                    res = {"key": k, "status": "error", "computed": True, "seconds": 0.0,
                           "error": f"{tasks[k].stage}: worker failure: "
                                    f"{type(error).__name__}: {error}"}
                done[k] = res
                bar = bars.get(tasks[k].stage)
                if bar is not None:
                    bar.update(1)
                    bar.set_postfix_str(tasks[k].label[:30])
    finally:
        for b in bars.values():
            b.close()
    return done


# --------------------------------------------------------------------------- results table

COLUMNS = ("track", "solver", "solver_version", "config_hash", "config", "scene", "variation",
           "variation_options", "seed", "observation", "n_modes", "n_modes_observed",
           *METRIC_COLUMNS, "runtime_s", "status", "error", "vvtbench_version",
           "dataset_revision", "estimate_path", "traceback_path")


def _row(run: Run, results: dict[str, dict], cache_rel: str) -> dict:
    row = {c: None for c in COLUMNS}
    row.update(track=run.track, solver=run.solver_name or run.solver,
               solver_version=run.solver_version, config_hash=run.config_hash,
               config=json.dumps(_jsonable(run.config or {}), sort_keys=True),
               scene=run.scene, variation=run.variation,
               variation_options=json.dumps(_jsonable(run.variation_options), sort_keys=True),
               seed=int(run.seed), observation=run.observation, n_modes=int(run.n_modes),
               vvtbench_version=__version__, dataset_revision=run.dataset_revision,
               status="ok", error="")
    for m in METRIC_COLUMNS:
        row[m] = float("nan")
    row["runtime_s"] = float("nan")
    row["n_modes_observed"] = -1
    if run.setup_error:
        row.update(status="error", error=run.setup_error)
        return row
    ev = results.get(run.evaluate_key, {})
    if ev.get("status") != "ok":
        # find the first failing task on the chain
        for k in (run.observe_key, run.solve_key, run.evaluate_key):
            r = results.get(k, {})
            if r.get("status") == "error":
                row.update(status="error", error=r.get("error", ""),
                           traceback_path=f"{cache_rel}/{r['traceback']}"
                           if r.get("traceback") else None)
                break
            if r.get("status") == "skipped" and r.get("upstream"):
                up = results.get(r["upstream"], {})
                if up.get("status") == "error":
                    row.update(status="error", error=up.get("error", r.get("error", "")),
                               traceback_path=f"{cache_rel}/{up['traceback']}"
                               if up.get("traceback") else None)
                    break
        else:
            row.update(status="error", error=ev.get("error") or "not run")
        if row["status"] != "error":
            row.update(status="error", error=ev.get("error") or "not run")
        return row
    res = ev["result"]
    for m in METRIC_COLUMNS:
        val = res["metrics"].get(m)
        row[m] = float("nan") if val is None else float(val)
    row["n_modes_observed"] = int(res.get("n_modes_observed", -1))
    sres = results.get(run.solve_key, {}).get("result", {})
    row["runtime_s"] = float(sres.get("runtime_s", float("nan")))
    row["estimate_path"] = f"{cache_rel}/{run.evaluate_key}/fields.npz"
    return row


def results_table(runs: list[Run], results: dict[str, dict], cache_rel: str = "cache"):
    import pandas as pd

    df = pd.DataFrame([_row(r, results, cache_rel) for r in runs], columns=list(COLUMNS))
    return _coerce(df)


def _coerce(df):
    for c in METRIC_COLUMNS + ("runtime_s",):
        df[c] = df[c].astype("float64")
    for c in ("seed", "n_modes", "n_modes_observed"):
        df[c] = df[c].astype("int64")
    for c in COLUMNS:
        if c not in METRIC_COLUMNS and c not in ("seed", "n_modes", "n_modes_observed",
                                                 "runtime_s"):
            df[c] = df[c].astype(object).where(df[c].notna(), None)
    return df


def write_results(df, out_dir: Path) -> tuple[Path, Path]:
    """results.parquet and results.csv in ``out_dir`` (atomic writes)."""
    out_dir = Path(out_dir)
    pq = out_dir / "results.parquet"
    csv = out_dir / "results.csv"
    tmp = out_dir / f".results.{uuid.uuid4().hex[:8]}"
    df.to_parquet(f"{tmp}.parquet", index=False)
    os.replace(f"{tmp}.parquet", pq)
    df.to_csv(f"{tmp}.csv", index=False)
    os.replace(f"{tmp}.csv", csv)
    return pq, csv


def read_results(path: str | Path):
    import pandas as pd

    path = Path(path)
    if path.is_dir():
        path = path / "results.parquet"
    if path.suffix == ".parquet":
        return pd.read_parquet(path)
    if path.suffix == ".csv":
        return pd.read_csv(path, keep_default_na=True)
    raise ValueError(f"{path}: results must be .parquet or .csv")


# --------------------------------------------------------------------------- run_suite


def run_suite(suite: Suite | str | Path, solvers: list[str] | None = None,
              out_dir: str | Path = "runs", workers: int = 1, scheduler=None, *,
              solver_config: dict | None = None, progress: bool = True,
              until: str = "evaluate", threads: int | None = None):
    """Run a suite; return the results table (a pandas DataFrame).

    ``solvers``: names or ``path/file.py:Class`` (default: the suite's ``solvers``);
    ``solver_config``: ``{solver: {key: value}}`` overrides on top of the suite's
    ``[solver.NAME]`` tables; ``workers`` local processes; ``scheduler``: a Dask scheduler
    address (or a ``distributed.Client``) to run on instead; ``until``: last stage to run.
    ``df.attrs["stats"]`` holds, per stage, the number of tasks computed, found in the cache,
    failed and skipped. Writes ``OUT/results.parquet``, ``OUT/results.csv`` and ``OUT/run.json``.
    """
    if not isinstance(suite, Suite):
        suite = load_suite(suite)
    solvers = list(suite.solvers if solvers is None else solvers)
    out_dir = Path(out_dir)
    cache = out_dir / "cache"
    cache.mkdir(parents=True, exist_ok=True)
    tasks, runs = build_graph(suite, solvers, solver_config, until)
    if threads is None and workers > 1 and scheduler is None:
        threads = max(1, (os.cpu_count() or 1) // workers)
    if scheduler is not None:
        executor = _Dask(scheduler)
    elif workers > 1:
        executor = _Pool(workers)
    else:
        executor = _Inline()
    t0 = time.perf_counter()
    try:
        results = _execute(tasks, cache, executor, progress, threads)
    finally:
        executor.close()
    wall = time.perf_counter() - t0
    stats = {s: {"tasks": 0, "computed": 0, "cached": 0, "failed": 0, "skipped": 0}
             for s in STAGES}
    for k, r in results.items():
        st = stats[tasks[k].stage]
        st["tasks"] += 1
        if r["status"] == "error":
            st["failed"] += 1
        elif r["status"] == "skipped":
            st["skipped"] += 1
        elif r["computed"]:
            st["computed"] += 1
        else:
            st["cached"] += 1
    df = results_table(runs, results) if until == "evaluate" else None
    if df is not None:
        write_results(df, out_dir)
        df.attrs["stats"] = stats
        df.attrs["wall_s"] = wall
    _write_json(out_dir / "run.json", {
        "suite": suite.name, "suite_source": suite.source, "solvers": solvers,
        "vvtbench": __version__, "workers": workers,
        "scheduler": scheduler if isinstance(scheduler, str) else (None if scheduler is None
                                                                    else "client"),
        "wall_s": wall, "stats": stats, "n_runs": len(runs),
        "generated_samples": sorted(k for k in tasks if k.startswith("generate/")
                                    and results.get(k, {}).get("status") == "ok"),
    })
    if df is None:
        return {"stats": stats, "wall_s": wall, "results": results, "tasks": tasks}
    return df


# --------------------------------------------------------------------------- check-results

_ALLOWED = {"status": ("ok", "error"), "observation": OBSERVATIONS}
_RANGES = {**{c: (-1.0, 1.0) for c in ("nc_w", "nc_v", "nc_w_uncentered", "nc_v_uncentered",
                                       "nc_at_sigma_star_w", "nc_at_sigma_star_v")},
           "sigma_star_w": (0.0, None), "sigma_star_v": (0.0, None), "mode_mac": (0.0, 1.0),
           "freq_err_raw": (0.0, None), "freq_err_scaled": (0.0, None),
           "runtime_s": (0.0, None)}
REQUIRED = ("solver", "solver_version", "config_hash", "config", "scene", "variation", "seed",
            "observation", "n_modes", *METRIC_COLUMNS, "runtime_s", "status", "error",
            "vvtbench_version", "dataset_revision")
_STRINGS = ("solver", "solver_version", "config_hash", "scene", "variation",
            "vvtbench_version", "dataset_revision")


def check_results(path_or_df, max_errors: int = 50) -> list[str]:
    """Validate a results table (file or DataFrame) against docs/results.md.

    Returns a list of problems, each naming the column, the row (0-based, as in the file's data
    rows) and what is allowed; empty when the table is valid.
    """
    import pandas as pd

    if isinstance(path_or_df, pd.DataFrame):
        df = path_or_df
    else:
        try:
            df = read_results(path_or_df)
        except Exception as error:
            return [f"{path_or_df}: cannot read: {type(error).__name__}: {error}"]
    errors: list[str] = []

    def err(msg):
        errors.append(msg)

    missing = [c for c in REQUIRED if c not in df.columns]
    if missing:
        err(f"missing column(s): {', '.join(missing)} (required: {', '.join(REQUIRED)})")
    if len(df) == 0:
        err("the table has no rows")
    for c in _STRINGS:
        if c not in df.columns:
            continue
        for i, val in df[c].items():
            if not isinstance(val, str) or not val.strip():
                err(f"column {c!r}, row {i}: {val!r} must be a non-empty string")
    for c, allowed in _ALLOWED.items():
        if c not in df.columns:
            continue
        for i, val in df[c].items():
            if val not in allowed:
                err(f"column {c!r}, row {i}: {val!r} not allowed; allowed values: "
                    f"{', '.join(allowed)}")
    for c in ("seed", "n_modes"):
        if c not in df.columns:
            continue
        for i, val in df[c].items():
            ok = isinstance(val, (int, np.integer)) or (
                isinstance(val, (float, np.floating)) and float(val).is_integer())
            if not ok or (c == "n_modes" and val < 1):
                err(f"column {c!r}, row {i}: {val!r} must be an integer"
                    + (" >= 1" if c == "n_modes" else ""))
    if "config" in df.columns:
        for i, val in df["config"].items():
            try:
                if not isinstance(json.loads(val), dict):
                    raise ValueError
            except (TypeError, ValueError):
                err(f"column 'config', row {i}: must be a JSON object (the solver config), "
                    f"got {str(val)[:40]!r}")
    if "config_hash" in df.columns:
        for i, val in df["config_hash"].items():
            if isinstance(val, str) and not all(ch in "0123456789abcdef" for ch in val):
                err(f"column 'config_hash', row {i}: {val!r} must be lower-case hex")
    for c, (lo, hi) in _RANGES.items():
        if c not in df.columns:
            continue
        col = pd.to_numeric(df[c], errors="coerce")
        for i, (raw, val) in enumerate(zip(df[c], col, strict=True)):
            if pd.isna(val):
                if raw is not None and not pd.isna(raw):
                    err(f"column {c!r}, row {df.index[i]}: {raw!r} is not a number")
                continue
            if (lo is not None and val < lo - 1e-9) or (hi is not None and val > hi + 1e-9):
                rng = f"[{lo}, {hi if hi is not None else 'inf'}]"
                err(f"column {c!r}, row {df.index[i]}: {val!r} outside the allowed range {rng}")
    if "status" in df.columns:
        for i, row in df.iterrows():
            if row["status"] == "ok":
                for c in ("nc_w", "nc_v", "runtime_s"):
                    if c in df.columns and pd.isna(pd.to_numeric(row[c], errors="coerce")):
                        err(f"column {c!r}, row {i}: rows with status 'ok' need a number")
            elif row["status"] == "error" and "error" in df.columns:
                if not isinstance(row["error"], str) or not row["error"].strip():
                    err(f"column 'error', row {i}: rows with status 'error' need the error "
                        "message")
    key = [c for c in ("track", "solver", "config_hash", "scene", "variation", "seed",
                       "observation") if c in df.columns]
    if len(key) >= 6:
        dup = df.duplicated(subset=key, keep="first")
        for i in df.index[dup]:
            err(f"row {i}: duplicate of an earlier row in columns {', '.join(key)}")
    if len(errors) > max_errors:
        errors = errors[:max_errors] + [f"... and {len(errors) - max_errors} more problem(s)"]
    return errors


def main_check_results(argv: list[str] | None = None) -> int:
    """``vvtbench check-results FILE``: exit 0 when valid, 1 with the problems listed."""
    p = argparse.ArgumentParser(prog="vvtbench check-results",
                                description="validate a results table (docs/results.md)")
    p.add_argument("file", help="results .parquet or .csv (or a run folder)")
    args = p.parse_args(argv)
    problems = check_results(args.file)
    if problems:
        print(f"{args.file}: {len(problems)} problem(s)", file=sys.stderr)
        for msg in problems:
            print(f"  {msg}", file=sys.stderr)
        return 1
    df = read_results(args.file)
    print(f"{args.file}: valid ({len(df)} rows, {df['solver'].nunique()} solver(s))")
    return 0


# --------------------------------------------------------------------------- CLI


def _parse_set(items: list[str]) -> dict[str, dict]:
    out: dict[str, dict] = {}
    for item in items:
        key, sep, value = item.partition("=")
        solver, dot, opt = key.partition(".")
        if not sep or not dot:
            raise SuiteError(f"--set {item!r}: expected SOLVER.KEY=VALUE (e.g. vvt.max_iter=5)")
        try:
            val = json.loads(value)
        except ValueError:
            val = value
        out.setdefault(solver, {})[opt] = val
    return out


def format_table(df) -> str:
    cols = ["track", "scene", "variation", "seed", "observation", "solver", "n_modes_observed",
            "nc_w", "nc_v", "sigma_star_w", "mode_mac", "runtime_s", "status"]
    view = df[[c for c in cols if c in df.columns]].copy()
    with_err = df["status"] != "ok"
    text = view.to_string(index=False, float_format=lambda x: f"{x:.3f}")
    if with_err.any():
        text += "\n\nerrors:\n" + "\n".join(
            f"  {r.solver} on {r.scene} [{r.variation}, {r.observation}]: {r.error}"
            for r in df[with_err].itertuples())
    return text


def main_run(argv: list[str] | None = None) -> int:
    """``vvtbench run SUITE [--solvers a,b] [--workers N] [--scheduler ADDR] -o DIR``."""
    p = argparse.ArgumentParser(prog="vvtbench run", description=(
        "run a benchmark suite: generate -> extract -> solve -> evaluate, cached"))
    p.add_argument("suite", help="suite name (scenes/suites/NAME.toml) or file")
    p.add_argument("--solvers", default=None,
                   help="comma-separated solver names or path/file.py:Class "
                        "(default: the suite's list)")
    p.add_argument("--set", dest="overrides", action="append", default=[],
                   metavar="SOLVER.KEY=VALUE", help="solver config override (repeatable)")
    p.add_argument("--workers", type=int, default=1, help="local worker processes (1)")
    p.add_argument("--scheduler", default=None,
                   help="address of a Dask distributed scheduler, e.g. tcp://host:8786")
    p.add_argument("-o", "--output", default=None, help="run folder (default runs/SUITE)")
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    try:
        suite = load_suite(args.suite)
        solvers = None if args.solvers is None else [s for s in args.solvers.split(",") if s]
        overrides = _parse_set(args.overrides)
    except SuiteError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    out = Path(args.output or f"runs/{suite.name}")
    df = run_suite(suite, solvers, out, workers=args.workers, scheduler=args.scheduler,
                   solver_config=overrides, progress=not args.no_progress)
    print(format_table(df))
    st = df.attrs.get("stats", {})
    summary = ", ".join(f"{s} {v['computed']} new/{v['cached']} cached"
                        + (f"/{v['failed']} failed" if v["failed"] else "")
                        for s, v in st.items() if v["tasks"])
    print(f"\n{len(df)} rows in {df.attrs.get('wall_s', 0):.1f} s ({summary}) -> "
          f"{out / 'results.parquet'}, {out / 'results.csv'}")
    return 0
