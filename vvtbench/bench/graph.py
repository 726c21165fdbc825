"""The task graph of a suite: one :class:`Task` per stage input, one :class:`Run` per row."""

from __future__ import annotations

import hashlib
import itertools
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._version import __version__
from ..modes.revision import extraction_revision
from .suite import (
    Suite,
    SuiteError,
    Track,
    apply_overrides,
    observation_extractor,
    observation_kind,
    observation_variant,
    scene_ref,
)

STAGES = ("generate", "extract", "observe", "solve", "evaluate")
#: seconds the sealed import describing a solver plug-in has at least, whatever the time limit:
#: starting a child and importing numpy takes seconds on a loaded machine
DESCRIBE_FLOOR = 30.0
# Bump when a stage's output format or meaning changes (part of every task key).
CACHE_FORMAT = 3  # 3: extraction scores and true-mode match; 2: samples are the contract, no pickle
#: revision of the observation of extracted modes (observe keys of extracted tracks only; the
#: extraction is reused). 2: each mode's spectral SNR (``InverseProblem.mode_snr``); 3: the
#: extraction scored with resolved modes matched one by one (a cluster of true modes closer
#: than the resolution holds as many detections as it has modes; docs/modes.md, "Matching")
OBSERVE_REVISION = 3
#: revision of the scoring of an estimate (evaluate keys only; solves are reused).
#: 2: an observed mode is matched to the span of a repeated model mode, not to one basis vector;
#: 3: every scored row states the fraction of DOFs its observation sees
EVALUATE_REVISION = 3
#: revision of the field path (``[tracks.field]``: its extract and observe keys only)
FIELD_REVISION = 1
#: inference options the field path cannot honour (a real video has one camera, its object's
#: own geometry and the reader's mesh)
FIELD_UNSUPPORTED = {"views": 1, "geometry_scale": 1.0, "inference_order": 1}


def extract_options(suite: Suite, observation: str,
                    track_extract: dict | None = None) -> tuple[dict, dict]:
    """(the ``extract_modes`` options of an observation source, their form in task keys).

    The suite's ``[extract]`` table with a track's ``[tracks.extract]`` over it, the options
    of the variant an ``"extracted@VARIANT"`` source names (``[extract.variants.VARIANT]``)
    over those, plus the extractor an ``"extracted:NAME"`` source names and its
    ``[extract.extractor.NAME]`` overrides; the default extractor with no overrides adds
    nothing, so such runs keep their cache. A variant's key is its options as they are: it
    is the key of the extraction without the variant that has the same options. Keys name
    the extractor by name and version (not by a path, which differs between machines)."""
    variant = observation_variant(observation)
    if variant is not None and variant not in suite.extract_variants:
        raise SuiteError(f"{suite.source or '<suite>'}: observation {observation!r}: no "
                         f"extraction variant {variant!r} (allowed: "
                         f"{', '.join(sorted(suite.extract_variants)) or 'none defined'})")
    opts = {**suite.extract, **(track_extract or {}),
            **(suite.extract_variants.get(variant, {}) if variant else {})}
    spec = observation_extractor(observation) or "phase"
    ext = suite.extractors.get(spec)
    if observation_kind(observation) != "extracted" or ext is None or (
            ext["name"] == "phase" and not ext["config"]):
        return opts, opts
    opts.update(extractor=ext["spec"], extractor_config=ext["config"])
    return opts, {**opts, "extractor": f"{ext['name']} {ext['version']}"}


def field_settings(track: Track, variation, seed: int, scene_dicts: list[dict],
                   source: str):
    """The :class:`~vvtbench.field.track.FieldSettings` of a row of a field track (the click
    seed resolved), or None; a variation or scene the field path cannot take is a
    :class:`SuiteError` naming the track."""
    if track.field is None:
        return None
    from ..field.track import FieldSettings

    where = f"{source or '<suite>'}: track {track.name!r} with [tracks.field]"
    for key, neutral in FIELD_UNSUPPORTED.items():
        value = variation.inference.get(key, neutral)
        if value != neutral and value != [neutral] * 3:
            raise SuiteError(f"{where}: key '{key}' = {value!r} is not allowed (allowed: "
                             f"{neutral!r}; the field path has one camera, the object's own "
                             "geometry and the mesh read from its file)")
    settings = FieldSettings.from_mapping(track.field).resolved(seed)
    if settings.object == "stl":
        drums = [d["name"] for d in scene_dicts if d["geometry"]["kind"] == "drum"]
        if drums:
            raise SuiteError(f"{where}: key 'field.object' = 'stl' is not allowed for the "
                             f"membrane {drums[0]!r} (allowed: 'scene': a drum head has no "
                             "closed surface)")
    return settings


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
    reference: bool = False  # a reference solver (uses_truth, e.g. the oracle)


def _resolve_scene(ref: str, source: str, overrides: dict, seed: int) -> dict:
    from ..scene.scene import load_scene, parse_scene

    if ref.startswith("family:"):  # instance INDEX of a family's SPLIT: family:NAME:SPLIT:INDEX
        from ..scene.families import draw

        _, family, split, index = ref.split(":")
        scene = draw(family, split, int(index))
        seed = scene.seed  # an instance keeps the seed it was drawn with
    else:
        scene = load_scene(scene_ref(ref, source))
    data = apply_overrides(scene.to_toml_dict(), {**overrides, "seed": seed})
    try:
        parsed = parse_scene(data, "(suite overrides)")
    except Exception as error:
        msg = str(error).removeprefix("(suite overrides): ")
        raise SuiteError(f"{source or '<suite>'}: scene {scene.name!r} with the suite's "
                         f"overrides (defaults, variations, sweep; seed {seed}): {msg}"
                         ) from None
    return parsed.to_toml_dict()


def build_graph(suite: Suite, solvers: list[str], solver_config: dict | None = None,
                until: str = "evaluate", timeout: float | None = None
                ) -> tuple[dict[str, Task], list[Run]]:
    """All tasks (by key) and runs (rows) of a suite; ``timeout`` (default: the suite's)
    bounds the sealed import that describes each solver plug-in."""
    tasks: dict[str, Task] = {}
    runs: list[Run] = []
    cfgs = {**suite.solver_config}
    for k, v in (solver_config or {}).items():
        cfgs[k] = {**cfgs.get(k, {}), **v}
    solver_info: dict = {}
    from ..solving.sealed import forget_descriptions

    forget_descriptions()
    # a plug-in whose import hangs becomes an error row within the suite's time limit
    limit = timeout if timeout is not None else suite.timeout
    describe_timeout = min(max(float(limit), DESCRIBE_FLOOR), 600.0) if limit else 600.0

    def info(spec: str, extra: dict | None = None):
        ck = (spec, json.dumps(_canon(extra or {}), sort_keys=True))
        if ck not in solver_info:
            try:  # the plug-in is imported in a sealed child, never here
                from ..solving.sealed import describe_sealed

                name = describe_sealed("solver", spec, timeout=describe_timeout)["name"]
                over = {**(cfgs.get(spec) or cfgs.get(name) or {}), **(extra or {})}
                d = describe_sealed("solver", spec, over, timeout=describe_timeout)
                solver_info[ck] = (d["name"], d["version"], d["config"], None,
                                   d["uses_truth"], d["inputs"])
            except Exception as error:  # a broken plug-in becomes error rows
                solver_info[ck] = (spec, "", {}, f"setup: {type(error).__name__}: {error}",
                                   False, {})
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
            # true modes only: no video rendered
            video = any(observation_kind(o) == "extracted" for o in track.observations)
            gen_keys = [add("generate", [d, {"video": video}], [], {"scene": d, "video": video},
                            d["name"]) for d in scene_dicts]
            dataset_revision = content_hash(*gen_keys)
            fs = field_settings(track, var, seed, scene_dicts, suite.source)
            field_key = {} if fs is None else {**fs.key(), "revision": FIELD_REVISION}
            if stop < 1:
                continue
            n_modes = int(var.inference.get("n_modes", 10))
            for obs in track.observations:
                ext_keys = []
                extract_opts, extract_key = extract_options(suite, obs, track.extract)
                ext_rev = extraction_revision(extract_opts)
                n_views = int(var.inference.get("views", 1))
                if observation_kind(obs) == "extracted" and n_views > 1:
                    if len(gen_keys) > 1:
                        raise SuiteError(f"{suite.source}: track {track.name!r}: key 'views' = "
                                         f"{n_views} with a group of {len(gen_keys)} videos; "
                                         "allowed: 1, or one scene per group (its views are "
                                         "joined, not merged)")
                    ext_keys = [add("extract", [extract_key, ext_rev,
                                                *([{"view": i}] if i else [])], [gen_keys[0]],
                                    {"options": extract_opts, "view": i},
                                    f"{scene_dicts[0]['name']} view {i}")
                                for i in range(n_views)]
                elif observation_kind(obs) == "extracted":
                    ext_keys = [add("extract", [extract_key, ext_rev,
                                                *([field_key["video"], FIELD_REVISION]
                                                  if fs else [])], [g],
                                    {"options": extract_opts,
                                     **({"field": fs.to_dict()} if fs else {})},
                                    name) for g, name in zip(gen_keys, [d["name"] for d in
                                                                        scene_dicts],
                                                             strict=True)]
                if stop < 2:
                    continue
                inf = {"n_modes": n_modes, **var.inference}
                obs_payload = {"scene": scene_dicts[0], "inference": inf, "observation": obs,
                               "extract": extract_opts,
                               **({"field": fs.to_dict()} if fs else {})}
                obs_key = add("observe", [scene_dicts[0], inf, obs,
                                          {**extract_key, "revision": ext_rev,
                                           "observe_revision": OBSERVE_REVISION}
                                          if ext_keys else {},
                                          *([field_key] if fs else [])],
                              [gen_keys[0], *ext_keys], obs_payload, scene_label)
                if stop < 3:
                    continue
                for spec, vlabel, extra in _track_solvers(track, solvers, info):
                    name, version, cfg, err, reference, inputs = info(spec, extra)
                    cfg_hash = content_hash(name, cfg)
                    vname = var.name if not vlabel else (
                        vlabel if var.name == "base" else f"{var.name},{vlabel}")
                    run = Run(track.name, scene_label, vname, seed, obs, spec, n_modes,
                              {**var.scene_overrides, **var.inference,
                               **{f"{name}.{k}": x for k, x in (extra or {}).items()},
                               **({f"field.{k}": x for k, x in fs.to_dict().items()}
                                  if fs else {})},
                              dataset_revision,
                              observe_key=obs_key, config=cfg, config_hash=cfg_hash,
                              solver_name=name, solver_version=version, setup_error=err,
                              reference=reference)
                    if err is None:
                        # the keys the user gave (suite tables, --set): only the files
                        # they name are shown to the sandbox, never the plug-in's defaults
                        named = sorted({**(cfgs.get(spec) or cfgs.get(name) or {}),
                                        **(extra or {})})
                        sk = add("solve", [name, version, cfg, *([inputs] if inputs else [])],
                                 [obs_key],
                                 {"solver": spec, "config": cfg, "named": named},
                                 f"{name}:{scene_label}")
                        ek = add("evaluate", [EVALUATE_REVISION], [sk, obs_key], {},
                                 f"{name}:{scene_label}")
                        run.solve_key, run.evaluate_key = sk, ek
                    runs.append(run)
    return tasks, runs


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
