"""The stage bodies (generate, extract, observe, solve, evaluate) and :func:`execute_task`,
which runs one task into the cache atomically."""

from __future__ import annotations

import json
import os
import shutil
import time
import traceback
import uuid
from pathlib import Path

import numpy as np

from .._version import __version__
from ..io.files import jsonable, write_json, write_npz, write_text
from ..samples.reader import sha256_file
from ..solving.sealed import SealedError
from .graph import Task
from .suite import observation_kind


def _stage_generate(cache: Path, task: Task, out: Path, deps: dict) -> dict:
    from ..samples.generate import generate
    from ..scene.scene import parse_scene

    scene = parse_scene(task.payload["scene"], task.payload["scene"]["name"])
    video = bool(task.payload.get("video", True))
    # a filmed sample whose video no task of the run reads (its extractions come from a run
    # shard): the truth alone, its videos recorded as withheld (see execute_task)
    frames = bool(task.payload.get("frames", True))
    # generate() is itself atomic and resumable inside its own folder
    work = cache / "generate" / "_work" / task.key.split("/")[1]
    path = generate(scene, work, progress=False, overwrite=True, video=video, frames=frames)
    shutil.move(str(path), str(out / "sample"))
    shutil.rmtree(work, ignore_errors=True)
    if video and not frames:
        return {"sample": "sample", "video": video, "frames": False,
                WITHHELD: dict(task.payload.get("withheld") or {})}
    return {"sample": "sample", "video": video}


#: the result key of a generate task run without frames: ``{name: {"sha256", "bytes"}}`` of
#: the video files the sample would hold (recorded by the run that rendered them)
WITHHELD = "withheld"


def sample_path(cache: Path, gen_key: str) -> Path:
    """The sample folder a generate task wrote."""
    return cache / gen_key / "sample"


def _stage_extract(cache: Path, task: Task, out: Path, ctx: dict) -> dict:
    from ..samples.reader import open_sample
    from ..solving.sealed import extract_sealed

    sample = open_sample(sample_path(cache, task.deps[0]))
    opts = {k: v for k, v in task.payload["options"].items() if not k.startswith("merge_")}
    if opts.get("identifier") == "auto" and "excitation" not in opts:
        # how the scene set the object moving (a pluck: a free decay), for the identifier
        kind = getattr(getattr(sample.scene, "excitation", None), "kind", None)
        if isinstance(kind, str):
            opts["excitation"] = kind
    limits = ctx.get("limits") or {}
    field = task.payload.get("field")
    scratch = None
    view = int(task.payload.get("view", 0))
    video, extra = (sample.view(view).video_path if view else sample.video_path), {}
    try:
        if field is not None:  # the video as a camera writes it, read back by its reader
            # a temporary of the stage folder: a killed run's is removed by the next run
            scratch = cache / f"{_tmp_name(task.key)}.field"
            video, extra = _field_video(sample, field, scratch)
        result = extract_sealed(video, sample.fps, opts, out,
                                timeout=limits.get("timeout"),
                                memory_bytes=limits.get("memory_bytes"),
                                threads=ctx.get("threads"), folder=field is not None,
                                secrets=_secrets(cache, sample.path))
        if extra:
            write_json(out / "field_video.json", extra)
    finally:
        if scratch is not None:
            shutil.rmtree(scratch, ignore_errors=True)
    return {"n_modes": result["n_modes"], "frequencies_hz": result["frequencies_hz"],
            "sandbox": result["sandbox"], **({"field_video": extra} if extra else {})}


def _field_video(sample, field: dict, dest: Path) -> tuple[Path, dict]:
    """The sample's video re-encoded into ``dest`` as :func:`vvtbench.field.track.encode_video`
    writes it: (the path to open, what was written: format, bytes, sha256, frames)."""
    from ..field.invert import source_sha256
    from ..field.track import FieldSettings, encode_video
    from ..video.files import open_video

    settings = FieldSettings.from_mapping(field)
    stream = open_video(sample.video_path)
    path = encode_video(stream.frames, float(sample.fps), dest, settings)
    files = [f for f in dest.rglob("*") if f.is_file()]
    return path, {**settings.key()["video"], "file": path.relative_to(dest).as_posix(),
                  "files": len(files), "bytes": int(sum(f.stat().st_size for f in files)),
                  "sha256": source_sha256(path)}


def _secrets(cache: Path, *more: Path) -> list[Path]:
    """What a plug-in must not see: the run folder (its cache holds every truth) and more."""
    return [cache.parent, cache, *more]


def observe_options(inference: dict, observation: str, extract: dict):
    """The :class:`~vvtbench.observe.ObserveOptions` of a suite variation."""
    from ..observe import ObserveOptions

    merge = {k: v for k, v in extract.items() if k.startswith("merge_")}
    rest = {k: v for k, v in extract.items() if not k.startswith("merge_")}
    return ObserveOptions.from_mapping({**inference, "observation": observation,
                                        "extract": rest, **merge})


def _stage_observe(cache: Path, task: Task, out: Path, deps: dict) -> dict:
    from ..observe import observe

    p = task.payload
    if p.get("field") is not None:
        return _field_observe(cache, task, out)
    kind = observation_kind(p["observation"])
    opts = observe_options(p["inference"], kind, p.get("extract") or {})
    sample, *extracted = task.deps
    if kind == "extracted":
        opts = opts.replace(modes=tuple(str(cache / k) for k in extracted))
    from ..samples.reader import open_sample

    opened = open_sample(sample_path(cache, sample))  # verified once, read twice
    problem, truth = observe(opened, opts)
    if kind == "extracted":
        scored = opts.modes[:1] if opts.views > 1 else opts.modes  # view 0: the sample's truth
        truth.meta["extraction"] = extraction_scores(opened, scored,
                                                     (p.get("extract") or {}).get("fmax"))
    _relative_source(truth, sample)
    problem.save(out)
    truth.save(out)
    return {"n_modes": problem.n_modes, "n_params": problem.n_params,
            "meta": {k: v for k, v in problem.meta.items() if k != "camera"}}


def _relative_source(truth, gen_key: str) -> None:
    """The truth names its sample relative to the run folder (``cache/generate/KEY/sample``),
    so an observation is the same bytes whichever folder the run has (the sha256 that results
    rows carry, compared when shards are merged)."""
    if isinstance(truth.meta.get("source"), str):
        truth.meta["source"] = f"cache/{gen_key}/sample"


def _field_observe(cache: Path, task: Task, out: Path) -> dict:
    """The observe stage of a field track: the object from its surface file (``object.stl``)
    or scene, the camera from simulated clicks (``clicks.csv``, ``calibration.json``), the
    problem from these alone (:func:`vvtbench.field.track.field_observe`)."""
    from ..field.calibrate import calibrate_from_file
    from ..field.objects import resolve_object
    from ..field.track import (
        FieldSettings,
        clicks_csv,
        field_observe,
        reprojection_error,
        simulate_clicks,
        write_object_surface,
    )
    from ..modes import ModeSet
    from ..observe import _read
    from ..samples.reader import open_sample

    p = task.payload
    settings = FieldSettings.from_mapping(p["field"])
    sample, *extracted = task.deps
    opened = open_sample(sample_path(cache, sample))
    inference = p["inference"]
    shape = inference.get("inference_shape")
    shape = tuple(shape) if shape else None
    if settings.object == "stl":
        from ..fem.mesh import Mesh

        sim = Mesh(_read(opened, "mesh/points"), _read(opened, "mesh/cells"),
                   opened.info["mesh"]["element"], {}, _read(opened, "mesh/surface"))
        spec = f"{write_object_surface(opened.scene, out / 'object.stl', sim)}:mesh={settings.mesh}"
    else:
        spec = str(opened.path / "scene.toml")
    obj = resolve_object(spec, inference_shape=shape)
    import dataclasses

    if settings.object == "stl":  # recorded as the task folder's file, not its temporary path
        obj = dataclasses.replace(obj, spec=f"object.stl:mesh={settings.mesh}")
    else:  # and the scene relative to the run folder, wherever it is
        obj = dataclasses.replace(obj, spec=f"cache/{sample}/sample/scene.toml")
    true_camera = opened.camera
    width, height = int(true_camera.width), int(true_camera.height)
    vertices, X, uv = simulate_clicks(obj.mesh.points, obj.mesh.surface, obj.corner_nodes(),
                                      true_camera, settings.clicks, settings.click_noise_px,
                                      int(settings.click_seed))
    write_text(out / "clicks.csv", clicks_csv(X, uv))
    cal = calibrate_from_file(out / "clicks.csv", obj.mesh.points, width, height,
                              max_error=settings.max_error_px)
    modes = [str(cache / k) for k in extracted]
    problem, truth = field_observe(opened, obj, cal.camera, [ModeSet.load(m) for m in modes],
                                   inference, width, height)
    camera_error = reprojection_error(cal.camera, true_camera,
                                      obj.mesh.points[problem.visible_nodes])
    record = {"settings": settings.to_dict(), "object": obj.describe(),
              "clicked_vertices": vertices.tolist(), "calibration": cal.to_dict(),
              "camera_error_px": camera_error}
    write_json(out / "calibration.json", record)
    problem.meta["field"] = {"settings": settings.to_dict(), "clicks_rms_px": cal.rms_px,
                             "camera_error_px": camera_error}
    truth.meta["extraction"] = extraction_scores(opened, tuple(modes),
                                                 (p.get("extract") or {}).get("fmax"))
    _relative_source(truth, sample)
    problem.save(out)
    truth.save(out)
    return {"n_modes": problem.n_modes, "n_params": problem.n_params,
            "meta": {k: v for k, v in problem.meta.items() if k != "camera"}}


EXTRACTION_KEYS = ("precision", "recall", "recall_all", "n_detectable", "mean_rel_freq_error",
                   "mean_abs_damping_error", "median_rel_damping_error", "mean_mac", "n_detected", "n_true_in_band",
                   "detectability", "n_below_limit", "crb_threshold", "frequency_efficiency",
                   "damping_efficiency", "n_frequency_efficiency", "n_damping_efficiency",
                   "efficiency_note")


def extraction_scores(s, modes: tuple, fmax: float | None) -> dict:
    """The extraction's detected modes scored against the true ones of the opened sample
    ``s``, pooled over the views: :func:`vvtbench.scoring.extraction.score_sample_extraction`
    (recall over the true modes detectable in the video, ``recall_all`` over all in band)."""
    from ..modes import ModeSet
    from ..scoring.extraction import score_sample_extraction

    sc = score_sample_extraction(s, [ModeSet.load(m) for m in modes],
                                 float(fmax) if fmax else None)
    return {k: sc[k] for k in EXTRACTION_KEYS if k in sc}


def load_observation(cache: Path, observe_key: str, truth: bool = False):
    """The problem an observe task wrote (and its truth with ``truth=True``)."""
    from ..observe import Truth
    from ..solving.problem import InverseProblem

    problem = InverseProblem.load(cache / observe_key)
    return (problem, Truth.load(cache / observe_key)) if truth else problem


def _stage_solve(cache: Path, task: Task, out: Path, ctx: dict) -> dict:
    from ..solving.sealed import describe_sealed, solve_sealed

    spec, config = task.payload["solver"], task.payload["config"]
    named = task.payload.get("named", ())  # the keys the user gave: their files are shown
    limits = ctx.get("limits") or {}
    reference = bool(describe_sealed("solver", spec, config, named=named)["uses_truth"])
    if reference:  # only a declared reference is handed the truth
        problem, truth = load_observation(cache, task.deps[0], truth=True)
    else:
        problem, truth = load_observation(cache, task.deps[0]), None
    est, wall, info = solve_sealed(spec, config, problem, truth=truth,
                                   timeout=limits.get("timeout"),
                                   memory_bytes=limits.get("memory_bytes"),
                                   threads=ctx.get("threads"), secrets=_secrets(cache),
                                   dest=out, named=named)
    return {"runtime_s": est.runtime_s or wall, "iterations": len(est.history),
            "reference": info["reference"], "sandbox": info["sandbox"]}


def _stage_evaluate(cache: Path, task: Task, out: Path, deps: dict) -> dict:
    solve_key, observe_key = task.deps
    hashes = scored_inputs(cache, solve_key, observe_key)
    problem, truth = load_observation(cache, observe_key, truth=True)
    w, v, std = load_estimate_arrays(cache / solve_key / "estimate.npz")
    return {**write_evaluation(out, problem, truth, w, v, **std), **hashes}


def load_estimate_arrays(path: Path) -> tuple[np.ndarray, np.ndarray, dict]:
    """``(w, v, {"w_std": ..., "v_std": ...})`` of an ``estimate.npz`` (stds where stated)."""
    with np.load(path, allow_pickle=False) as est:
        w, v = est["w_params"], est["v_params"]
        std = {f"{n}_std": est[f"{n}_std_params"] for n in ("w", "v")
               if f"{n}_std_params" in est.files}
    return w, v, std


def observation_sha256(folder: Path) -> str:
    """One sha256 of an observe output (problem and truth): over its files' names and
    sha256, in name order."""
    import hashlib

    h = hashlib.sha256()
    for name, digest in file_hashes(folder).items():
        h.update(f"{name}\0{digest}\n".encode())
    return h.hexdigest()


def scored_inputs(cache: Path, solve_key: str, observe_key: str) -> dict:
    """The sha256 of the estimate and of the observation an evaluation scores: an evaluation
    is reused only while both are unchanged, and every results row carries them."""
    return {"estimate_sha256": sha256_file(cache / solve_key / "estimate.npz"),
            "observation_sha256": observation_sha256(cache / observe_key)}


def write_evaluation(out: Path, problem, truth, w, v, modes: bool = True,
                     w_std=None, v_std=None) -> dict:
    """Score an estimate and write ``metrics.json`` and ``fields.npz`` (grids ``w``, ``v``,
    ``w_true``, ``v_true``, and ``w_std``, ``v_std`` when the solver stated them) into
    ``out``; an invalid estimate (non-finite, not positive, wrong shape) is not scored:
    ``{"invalid": reason}``. The evaluator of ``run`` and ``solve``."""
    from ..scoring.metrics import evaluate, invalid_reason

    out = Path(out)
    reason = invalid_reason(w, v, problem.n_params, w_std, v_std)
    fields = {"w_true": problem.to_grid(truth.w), "v_true": problem.to_grid(truth.v)}
    if reason is not None:
        write_npz(out / "fields.npz", fields)
        doc = {"invalid": reason, "metrics": {}, "notes": [], "n_modes_observed": problem.n_modes}
        write_json(out / "metrics.json", doc)
        return doc
    ev = evaluate(problem, truth, w, v, modes=modes, w_std=w_std, v_std=v_std)
    for name, std in (("w_std", w_std), ("v_std", v_std)):
        if std is not None:
            fields[name] = problem.to_grid(np.asarray(std, dtype=float))
    write_npz(out / "fields.npz", {"w": problem.to_grid(w), "v": problem.to_grid(v), **fields})
    write_json(out / "metrics.json", {"metrics": ev["metrics"],
                                      "intrinsic_resolution": ev["curves"],
                                      "notes": ev["notes"], "n_modes_observed": problem.n_modes})
    return {"metrics": ev["metrics"], "notes": ev["notes"], "n_modes_observed": problem.n_modes}


SEALED = ("extract", "solve")  # the stages that run plug-ins
STAGE_FUNCS = {"generate": _stage_generate, "extract": _stage_extract,
               "observe": _stage_observe, "solve": _stage_solve, "evaluate": _stage_evaluate}


def file_hashes(folder: Path) -> dict[str, str]:
    """sha256 of every file under ``folder`` (relative POSIX paths), ``task.json`` excepted."""
    out = {}
    for f in sorted(folder.rglob("*")):
        if f.is_file() and f.name != "task.json":
            out[f.relative_to(folder).as_posix()] = sha256_file(f)
    return out


def verify_cached(folder: Path, info: dict) -> str | None:
    """Why a cached task output cannot be reused (a file edited, truncated or deleted since its
    ``task.json`` recorded its sha256; no hashes recorded), or None when it is intact. A file
    the ``task.json`` records as pruned with the same sha256 (a video deleted by
    ``--prune-videos``, :mod:`.prune`) may be absent; present, it must still match."""
    from .pruned import excused

    files = info.get("files")
    if not isinstance(files, dict) or not files:
        return "no recorded sha256 (written by an older vvtbench)"
    pruned = excused(info)
    for rel, digest in files.items():
        f = folder / rel
        if not f.is_file():
            if rel in pruned:
                continue
            return f"{rel}: deleted"
        if sha256_file(f) != digest:
            return f"{rel}: sha256 mismatch (edited or truncated)"
    return None


def _scored_inputs_changed(cache: Path, task: Task, result: dict) -> str | None:
    """Why a cached evaluation no longer scores what its dependencies hold, or None."""
    try:
        now = scored_inputs(cache, *task.deps)
    except OSError:
        return None  # a dependency is missing: the dependency check below reports it
    for key, digest in now.items():
        if result.get(key) != digest:
            return f"{key.removesuffix('_sha256')} changed since it was scored"
    return None


def _withheld_record(withheld: dict | None, files: dict[str, str]) -> dict:
    """The videos a sample generated without frames withholds, as a pruned record
    (:mod:`.prune`): listed in ``files`` with the sha256 the rendering run recorded and
    excused as absent, so a later run that needs them renders them and checks them against
    it. Updates ``files``; returns the ``task.json`` entries to add."""
    from .pruned import PRUNED

    entries = []
    for name, e in sorted((withheld or {}).items()):
        if name in files or not isinstance(e, dict) or not isinstance(e.get("sha256"), str):
            continue
        files[name] = e["sha256"]
        entries.append({"name": name, "bytes": e.get("bytes"), "sha256": e["sha256"]})
    if not entries:
        return {}
    return {PRUNED: {"at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                     "files": entries, "why": "regenerated without frames"}}


def _tmp_name(key: str) -> str:
    return f"{key}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}"


# the task this process is writing (for a SIGTERM handler: see executors)
CURRENT: dict[str, Path | None] = {"tmp": None}


def cached_state(cache: Path, task: Task) -> tuple[dict | None, str | None]:
    """(the ``task.json`` of a task's cached output, why it cannot be reused): ``(info,
    None)`` when it is intact, ``(None, None)`` when there is none."""
    done = Path(cache) / task.key / "task.json"
    if not done.is_file():
        return None, None
    try:
        info = json.loads(done.read_text())
        why = verify_cached(done.parent, info)
    except (OSError, ValueError, AttributeError, TypeError):
        return None, "task.json unreadable"
    if why is None and task.stage == "evaluate":
        why = _scored_inputs_changed(Path(cache), task, info.get("result") or {})
    return info, why


def execute_task(cache: str, task: Task, threads: int | None = None,
                 limits: dict | None = None, force: str | None = None) -> dict:
    """Run one task unless its output exists and is intact; never raises (but for Ctrl-C).
    Returns a status dict: ``{"key", "status": ok|error|skipped, "computed": bool,
    "seconds", "result"|"error"}``; ``"recomputed"``: why a cached output was not reused.

    ``limits``: ``{"timeout": s, "memory_bytes": n}`` for the extract and solve tasks, which
    run their plug-ins in a sealed child (:mod:`vvtbench.solving.sealed`). ``force``: why an intact
    cached output is computed again anyway (a pruned video needed again, an input that
    changed; :mod:`.prune`); it is replaced only once the new one is complete, and the status
    dict says ``"forced"``."""
    cache = Path(cache)
    limits = limits or {}
    final = cache / task.key
    info, recomputed = cached_state(cache, task)
    if info is not None and recomputed is None and not force:
        return {"key": task.key, "status": "ok", "computed": False, "seconds": 0.0,
                "result": info.get("result", {})}
    if recomputed is not None:  # never reuse it: move it aside atomically, then delete
        trash = cache / f"{_tmp_name(task.key)}.stale"
        try:
            os.replace(final, trash)
        except OSError:
            pass
        shutil.rmtree(trash, ignore_errors=True)
    for dep in task.deps:
        if not (cache / dep / "task.json").is_file():
            err_file = cache / f"{dep}.error" / "error.json"
            msg = "upstream task failed"
            if err_file.is_file():
                try:
                    msg = json.loads(err_file.read_text()).get("error", msg)
                except (OSError, ValueError):
                    pass
            return {"key": task.key, "status": "skipped", "computed": False, "seconds": 0.0,
                    "error": msg, "upstream": dep}
    tmp = cache / _tmp_name(task.key)
    tmp.mkdir(parents=True)
    CURRENT["tmp"] = tmp
    err_dir = cache / f"{task.key}.error"
    t0 = time.perf_counter()
    try:
        if task.stage in SEALED:  # plug-ins: a sealed child with the limits
            result = STAGE_FUNCS[task.stage](cache, task, tmp,
                                             {"limits": limits, "threads": threads})
            if task.stage == "solve" and not (tmp / "estimate.npz").is_file():
                raise SealedError("crashed", "the solver reported success but wrote no "
                                             "estimate.npz")
        elif threads:
            from threadpoolctl import threadpool_limits

            with threadpool_limits(limits=threads):
                result = STAGE_FUNCS[task.stage](cache, task, tmp, {})
        else:
            result = STAGE_FUNCS[task.stage](cache, task, tmp, {})
        seconds = time.perf_counter() - t0
        files = file_hashes(tmp)
        record = _withheld_record(result.pop(WITHHELD, None), files)
        write_json(tmp / "task.json", {"stage": task.stage, "key": task.key,
                                        "deps": task.deps, "payload": task.payload,
                                        "result": result, "seconds": seconds,
                                        "vvtbench": __version__, "files": files, **record})
        if final.exists() and force:  # the intact output it replaces goes only now
            trash = cache / f"{_tmp_name(task.key)}.stale"
            os.replace(final, trash)
            os.replace(tmp, final)
            shutil.rmtree(trash, ignore_errors=True)
        elif final.exists():  # a concurrent duplicate finished first
            shutil.rmtree(tmp, ignore_errors=True)
        else:
            os.replace(tmp, final)
        shutil.rmtree(err_dir, ignore_errors=True)
        out = {"key": task.key, "status": "ok", "computed": True, "seconds": seconds,
               "result": jsonable(result)}
        if recomputed:
            out["recomputed"] = recomputed
        elif force:
            out["forced"] = force
        return out
    except BaseException as error:  # noqa: BLE001 -- a task must never stop the suite
        shutil.rmtree(tmp, ignore_errors=True)
        if isinstance(error, KeyboardInterrupt):
            raise
        if isinstance(error, SealedError):
            msg, tb = f"{task.stage}: {error}", f"{task.stage}: {error}\n{error.log}"
        else:
            msg, tb = f"{task.stage}: {type(error).__name__}: {error}", traceback.format_exc()
        err_dir.mkdir(parents=True, exist_ok=True)
        write_text(err_dir / "traceback.txt", tb)
        write_json(err_dir / "error.json", {"error": msg, "task": task.key})
        out = {"key": task.key, "status": "error", "computed": True,
               "seconds": time.perf_counter() - t0, "error": msg,
               "traceback": f"{task.key}.error/traceback.txt"}
        if recomputed:
            out["recomputed"] = recomputed
        return out
    finally:
        CURRENT["tmp"] = None
