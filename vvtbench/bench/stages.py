"""The stage bodies (generate, extract, observe, solve, evaluate) and :func:`execute_task`,
which runs one task into the cache atomically."""

from __future__ import annotations

import dataclasses
import json
import os
import pickle
import shutil
import time
import traceback
import uuid
from pathlib import Path

import numpy as np

from .._version import __version__
from ..io import jsonable, write_json
from .graph import Task


def _stage_generate(cache: Path, task: Task, out: Path, deps: dict) -> dict:
    from ..dataset import generate
    from ..scene import parse_scene

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
    from ..dataset import open_sample
    from ..modes import extract_modes

    sample = open_sample(_sample_path(cache, task.deps[0]))
    opts = {k: v for k, v in task.payload["options"].items() if not k.startswith("merge_")}
    ms = extract_modes(sample.video_path, sample.fps, **opts)
    ms.save(out)
    return {"n_modes": len(ms), "frequencies_hz": ms.frequencies_hz.tolist()}


def build_problem(scene_dict: dict, inference: dict, observation: str,
                  modesets: list | None = None, camera=None, extract_opts: dict | None = None):
    """The InverseProblem of a scene under inference options, observing true image-space modes
    or extracted ones (``modesets``: one ModeSet per video of the object, merged)."""
    from ..fem.mesh import box_mesh
    from ..problem import InverseProblem
    from ..scene import parse_scene
    from ..simulate import simulate

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
    from ..dataset import open_sample
    from ..modes import ModeSet

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

    from ..plugins import load_solver, parse_overrides

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
    write_json(out / "estimate.json", doc)
    return {"runtime_s": doc["runtime_s"], "iterations": len(est.history)}


def _stage_evaluate(cache: Path, task: Task, out: Path, deps: dict) -> dict:
    from ..metrics import intrinsic_resolution, mode_match, score

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
    write_json(out / "metrics.json", {"metrics": metrics, "intrinsic_resolution": curves,
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
        write_json(tmp / "task.json", {"stage": task.stage, "key": task.key,
                                        "deps": task.deps, "payload": task.payload,
                                        "result": result, "seconds": seconds,
                                        "vvtbench": __version__})
        if final.exists():  # a concurrent duplicate finished first
            shutil.rmtree(tmp, ignore_errors=True)
        else:
            os.replace(tmp, final)
        shutil.rmtree(err_dir, ignore_errors=True)
        return {"key": task.key, "status": "ok", "computed": True, "seconds": seconds,
                "result": jsonable(result)}
    except BaseException as error:  # noqa: BLE001 -- a task must never stop the suite
        if isinstance(error, KeyboardInterrupt):
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        shutil.rmtree(tmp, ignore_errors=True)
        msg = f"{task.stage}: {type(error).__name__}: {error}"
        err_dir.mkdir(parents=True, exist_ok=True)
        (err_dir / "traceback.txt").write_text(traceback.format_exc())
        write_json(err_dir / "error.json", {"error": msg, "task": task.key})
        return {"key": task.key, "status": "error", "computed": True,
                "seconds": time.perf_counter() - t0, "error": msg,
                "traceback": f"{task.key}.error/traceback.txt"}
