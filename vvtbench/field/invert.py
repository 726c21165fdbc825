"""From a video, its object and clicks to a material map: ``vvtbench invert``.

Stages, each cached in the output folder and keyed by the sha256 of its inputs and its
options (``stages.json``); a rerun with the same inputs reuses every finished stage, a changed
input redoes that stage and the solve (whose key holds the keys of the first two):

1. ``calibrate`` -- the object (:func:`~vvtbench.field.objects.resolve_object`) and the camera
   from the clicks (:func:`~vvtbench.field.calibrate.calibrate_camera`): ``camera.json``;
2. ``extract`` -- image-space modes of the video (:func:`extract_step`, one call of
   :func:`vvtbench.modes.extract_modes`): ``extract/``;
3. ``solve`` -- :func:`vvtbench.observe` of a :class:`~vvtbench.observe.RealVideo`, then the
   solver in its sandbox (:func:`solve_step`, :func:`vvtbench.solving.sealed.solve_sealed`):
   ``solve/``;
4. the report, rewritten every run: ``fields.npz`` (stiffness ``w`` and density ``v`` per
   voxel, ``w_std``/``v_std`` where the solver states them), ``fields.png``, ``modes.json``
   (the modes the solver used), ``report.md``.

An estimate that :func:`vvtbench.scoring.metrics.invalid_reason` rejects is never presented as a
result: ``report.md`` opens with the reason, no ``fields.npz`` is written, and
:func:`invert` returns it in :attr:`InvertResult.invalid`. One process writes a folder at a
time (:class:`vvtbench.io.lock.RunLock`); every file is written atomically and a stage's
folder appears whole or not at all.
"""

from __future__ import annotations

import glob
import hashlib
import json
import os
import re
import shutil
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..io.files import jsonable, write_json, write_npz, write_text

__all__ = ["InvertOptions", "InvertResult", "extract_step", "invert", "solve_step",
           "source_sha256"]

STAGES = ("calibrate", "extract", "solve")


@dataclass
class InvertOptions:
    """Options of :func:`invert`.

    Attributes
    ----------
    solver : solver name or ``path/file.py:Class``; solver_config: its overrides.
    n_modes : modes the solver uses (the lowest extracted ones).
    fps : frame rate (needed when the file does not state it).
    intrinsics : ``(fx, fy, cx, cy)`` pixels, or None to estimate them from the clicks.
    max_error : largest reprojection error of the clicks accepted (px).
    fmin, fmax, max_modes : the extraction's frequency band and mode count.
    nu, w0, v0 : Poisson's ratio and the priors (initial stiffness and density; default by
        kind: 1e4 Pa and 1000 kg/m^3 for solids, 40 N/m and 0.5 kg/m^2 for membranes).
    timeout, memory_bytes : limits of the sandboxed solve.
    """

    solver: str = "vvt"
    solver_config: dict[str, Any] = field(default_factory=dict)
    n_modes: int = 10
    fps: float | None = None
    intrinsics: tuple[float, float, float, float] | None = None
    max_error: float = 2.0
    fmin: float | None = None
    fmax: float | None = None
    max_modes: int | None = None
    nu: float = 0.3
    w0: float | None = None
    v0: float | None = None
    timeout: float | None = 1800.0
    memory_bytes: int | None = None


@dataclass
class InvertResult:
    """What :func:`invert` produced (``invalid``: why the estimate is not a result)."""

    out: Path
    report: Path
    invalid: str | None
    reused: list[str]
    rms_px: float
    max_px: float
    n_modes: int
    solver: str


def _file_digest(h, path: Path) -> None:
    h.update(f"{path.name}\0{path.stat().st_size}\0".encode())
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 22), b""):
            h.update(block)


def source_sha256(source: str | Path) -> str:
    """sha256 of a video source: a file (a Photron ``.cih``/``.cihx`` with its ``.mraw``), a
    folder of frames (every file in it, by name), or a glob / printf pattern (the files it
    matches). Read in blocks: memory stays bounded."""
    text = str(source)
    path = Path(text)
    h = hashlib.sha256()
    if path.is_file():
        files = [path]
        if path.suffix.lower() in (".cih", ".cihx"):
            files += [p for p in (path.with_suffix(".mraw"),) if p.is_file()]
    elif path.is_dir():
        files = sorted(p for p in path.iterdir() if p.is_file())
    else:
        pattern = re.sub(r"%0?\d*d", "*", text)
        files = sorted(Path(p) for p in glob.glob(pattern) if Path(p).is_file())
        if not files:
            raise FileNotFoundError(f"{text}: no such video file, folder or pattern")
    for f in files:
        _file_digest(h, f)
    return h.hexdigest()


def _key(inputs: Mapping[str, Any]) -> str:
    return hashlib.sha256(json.dumps(jsonable(dict(inputs)), sort_keys=True).encode()
                          ).hexdigest()


class _Stages:
    """``stages.json``: per stage its inputs, their key and whether it finished."""

    def __init__(self, out: Path):
        self.path = out / "stages.json"
        try:
            self.records = json.loads(self.path.read_text())
            if not isinstance(self.records, dict):
                self.records = {}
        except (OSError, ValueError):
            self.records = {}

    def done(self, stage: str, key: str, *outputs: Path) -> bool:
        rec = self.records.get(stage)
        return bool(rec and rec.get("key") == key and all(p.exists() for p in outputs))

    def finish(self, stage: str, key: str, inputs: Mapping[str, Any]) -> None:
        self.records[stage] = {"key": key, "inputs": jsonable(dict(inputs))}
        write_json(self.path, self.records, sort_keys=True)


def _replace_dir(tmp: Path, final: Path) -> None:
    if final.exists():
        old = final.with_name(final.name + ".old")
        shutil.rmtree(old, ignore_errors=True)
        os.replace(final, old)
        os.replace(tmp, final)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(tmp, final)


def extract_step(video: str | Path, fps: float | None, dest: Path, *,
                 timeout: float | None = None, **options: Any):
    """The one extraction of ``invert``: :func:`vvtbench.modes.extract_modes` in a sealed child
    (:func:`vvtbench.solving.sealed.extract_sealed`: the extractor sees the camera's files and its
    output only); the modes of ``video`` saved into ``dest`` (written beside it, then moved
    into place)."""
    from ..modes import ModeSet
    from ..solving.sealed import SealedError, extract_sealed
    from ..video.files import VideoError

    tmp = dest.with_name(dest.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        extract_sealed(video, fps, {k: v for k, v in options.items() if v is not None}, tmp,
                       secrets=[dest.parent], folder=True,
                       **({} if timeout is None else {"timeout": timeout}))
    except SealedError as error:
        shutil.rmtree(tmp, ignore_errors=True)
        text = str(error)
        if error.kind == "error" and text.partition(":")[0] in ("ValueError", "VideoError"):
            raise VideoError(f"{video}: {text.partition(': ')[2]}") from None
        raise VideoError(f"{video}: the extraction failed: {text}") from None
    _replace_dir(tmp, dest)
    return ModeSet.load(dest)


def solve_step(target: str, config: Mapping[str, Any], problem, dest: Path, *,
               timeout: float | None = None, memory_bytes: int | None = None):
    """The one solver call of ``invert``: the solver ``target`` in its sandbox
    (:func:`vvtbench.solving.sealed.solve_sealed`, no truth: a real video has none); the estimate is
    kept in ``dest``. Returns ``(estimate, wall seconds, info)``."""
    from ..solving.sealed import solve_sealed

    tmp = dest.with_name(dest.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    estimate, wall, info = solve_sealed(target, dict(config), problem, truth=None,
                                        timeout=timeout, memory_bytes=memory_bytes, dest=tmp)
    write_json(tmp / "solver.json", {**jsonable(info), "wall_s": wall})
    _replace_dir(tmp, dest)
    return estimate, wall, info


def _video_size(video: str | Path) -> tuple[int, int, float | None]:
    from ..video.files import VideoError, open_video

    stream = open_video(video, max_frames=1)
    frame = next(iter(stream.frames), None)
    if frame is None:
        raise VideoError(f"{video}: holds no frame")
    h, w = np.asarray(frame).shape[:2]
    return int(w), int(h), stream.fps


def invert(video: str | Path, object_spec: str, clicks: str | Path, out: str | Path,
           options: InvertOptions | None = None,
           log: Callable[[str], None] = print) -> InvertResult:
    """Extract, observe, solve and report (module notes) into the folder ``out``.

    ``out`` must be a new or empty folder, or one an earlier ``invert`` wrote
    (:func:`vvtbench.io.outputs.claim_output`): a folder holding the user's own files is
    refused before anything is written, so no ``report.md`` or ``fields.npz`` of theirs is
    replaced or removed.

    Raises
    ------
    ObserveError, CalibrationError, VideoError, PluginError, ValueError
        Bad input, one line (the CLI exits with status 2); an ``OutputError`` (a ValueError)
        for an output folder that is not the command's.
    """
    from ..io.lock import RunLock, RunLocked
    from ..io.outputs import claim_output

    opts = options or InvertOptions()
    out = claim_output(Path(out), "invert")  # new, empty, or an earlier invert's; else refused
    lock = RunLock(out, name=".invert.lock")
    try:
        lock.acquire()
    except RunLocked as error:
        raise ValueError(str(error)) from None
    try:
        return _invert(video, object_spec, clicks, out, opts, log)
    finally:
        lock.release()


def _invert(video, object_spec, clicks, out: Path, opts: InvertOptions, log) -> InvertResult:
    from ..modes import ModeSet
    from ..observe import ObserveOptions, RealVideo, observe
    from ..scoring.metrics import invalid_reason
    from ..solving.problem import Estimate
    from .calibrate import calibrate_from_file
    from .objects import resolve_object

    stages = _Stages(out)
    reused: list[str] = []
    obj = resolve_object(object_spec)
    if not Path(clicks).is_file():
        raise FileNotFoundError(f"{clicks}: clicks file not found")
    width, height, file_fps = _video_size(video)
    fps = opts.fps if opts.fps is not None else file_fps
    if fps is None:
        raise ValueError(f"{video}: the file states no frame rate; give --fps")

    # 1. calibrate
    cal_inputs = {"object": obj.describe(), "clicks_sha256": source_sha256(clicks),
                  "video_size": [width, height], "intrinsics": opts.intrinsics,
                  "max_error": opts.max_error}
    cal_key = _key(cal_inputs)
    cal = calibrate_from_file(clicks, obj.mesh.points, width, height,
                              intrinsics=opts.intrinsics, max_error=opts.max_error)
    if stages.done("calibrate", cal_key, out / "camera.json"):
        reused.append("calibrate")
    else:
        write_json(out / "camera.json", {**cal.to_dict(), "clicks": str(clicks),
                                         "object": obj.describe()})
        stages.finish("calibrate", cal_key, cal_inputs)
    log(f"camera: {cal.method}; reprojection error RMS {cal.rms_px:.3f} px, max "
        f"{cal.max_px:.3f} px over {cal.n_points} clicks")

    # 2. extract
    extract_options = {"fmin": opts.fmin, "fmax": opts.fmax, "max_modes": opts.max_modes}
    ext_inputs = {"video_sha256": source_sha256(video), "fps": fps, **extract_options}
    ext_key = _key(ext_inputs)
    if stages.done("extract", ext_key, out / "extract" / "modes.json"):
        reused.append("extract")
        modes = ModeSet.load(out / "extract")
    else:
        log(f"extracting modes from {video} at {fps:g} fps ...")
        modes = extract_step(video, fps, out / "extract", **extract_options)
        stages.finish("extract", ext_key, ext_inputs)
    log(f"modes: {len(modes)} extracted")
    if len(modes) == 0:
        raise ValueError(f"{video}: no mode was extracted; check the frame rate, the band "
                         "(--fmin/--fmax) and that the object vibrates in the clip")

    # 3. observe + solve
    kind = "membrane" if obj.is_membrane else "solid"
    w0 = opts.w0 if opts.w0 is not None else (40.0 if obj.is_membrane else 1e4)
    v0 = opts.v0 if opts.v0 is not None else (0.5 if obj.is_membrane else 1000.0)
    real = RealVideo(modes=[modes], mesh=obj.mesh, camera=cal.camera,
                     fixed_nodes=obj.fixed_nodes, width=width, height=height, nu=opts.nu,
                     w0=w0, v0=v0)
    n_modes = min(opts.n_modes, len(modes))
    problem, _ = observe(real, ObserveOptions(observation="extracted", n_modes=n_modes,
                                              inference_shape=obj.inference_shape))
    solve_inputs = {"calibrate": cal_key, "extract": ext_key, "solver": opts.solver,
                    "solver_config": opts.solver_config, "n_modes": n_modes, "nu": opts.nu,
                    "w0": w0, "v0": v0, "inference_shape": obj.inference_shape}
    solve_key = _key(solve_inputs)
    if stages.done("solve", solve_key, out / "solve" / "estimate.npz"):
        reused.append("solve")
        estimate = Estimate.load(out / "solve", problem)
        info = json.loads((out / "solve" / "solver.json").read_text())
        wall = float(info.get("wall_s", 0.0))
    else:
        log(f"solving with {opts.solver} ({problem.n_params} voxels, {problem.gamma.shape[0]} "
            "modes) ...")
        estimate, wall, info = solve_step(opts.solver, opts.solver_config, problem,
                                          out / "solve", timeout=opts.timeout,
                                          memory_bytes=opts.memory_bytes)
        stages.finish("solve", solve_key, solve_inputs)

    # 4. report
    invalid = invalid_reason(estimate.w, estimate.v, problem.n_params)
    used = problem.meta.get("extracted_frequencies_hz", [])
    snr = getattr(problem, "mode_snr", None)
    write_json(out / "modes.json", {
        "n_modes_used": int(problem.gamma.shape[0]), "frequencies_hz": used,
        "snr": None if snr is None else np.asarray(snr).tolist(),
        "n_modes_extracted": len(modes), "fps": fps, "n_visible_vertices":
        int(problem.meta.get("n_visible", 0)), "extract": str(out / "extract")})
    report = out / "report.md"
    std = {k: np.asarray(estimate.extra[k], dtype=float) for k in ("w_std", "v_std")
           if k in estimate.extra}
    for stale in ("fields.npz", "fields.png", "uncertainty.png"):
        (out / stale).unlink(missing_ok=True)
    if invalid is None:
        write_npz(out / "fields.npz", {
            "w": estimate.w, "v": estimate.v, "w_grid": problem.to_grid(estimate.w),
            "v_grid": problem.to_grid(estimate.v),
            "active": np.asarray(problem.model.voxel_map.active), **std,
            **{f"{k}_grid": problem.to_grid(s) for k, s in std.items()
               if s.shape == (problem.n_params,)}})
        from ..reporting.plots import plot_fields, plot_uncertainty

        plot_fields(out / "fields.png", problem, {opts.solver: (estimate.w, estimate.v)},
                    title=f"{Path(str(video)).name}: {opts.solver}")
        if {"w_std", "v_std"} <= set(std):
            plot_uncertainty(out / "uncertainty.png", problem, (estimate.w, estimate.v),
                             (std["w_std"], std["v_std"]))
    write_text(report, _report_md(video, obj, cal, modes, problem, estimate, opts, fps, wall,
                                  info, invalid, reused, std, kind, out))
    return InvertResult(out, report, invalid, reused, cal.rms_px, cal.max_px,
                        int(problem.gamma.shape[0]), opts.solver)


def _stats(x: np.ndarray) -> str:
    return f"median {np.median(x):.4g}, range {np.min(x):.4g} .. {np.max(x):.4g}"


def _report_md(video, obj, cal, modes, problem, estimate, opts, fps, wall, info, invalid,
               reused, std, kind, out: Path) -> str:
    units = ("N/m", "kg/m^2") if kind == "membrane" else ("Pa", "kg/m^3")
    names = ("tension", "areal density") if kind == "membrane" else \
        ("Young's modulus", "density")
    lines = []
    if invalid is not None:
        lines += [f"# NO RESULT: the estimate is invalid: {invalid}", "",
                  "The solver returned an estimate that is not a material map (see "
                  "`solve/estimate.json`); nothing below is a result.", ""]
    else:
        lines += [f"# Material map of `{Path(str(video)).name}`", ""]
    lines += [f"**Warning:** {w}" for w in obj.warnings] + ([""] if obj.warnings else [])
    freqs = problem.meta.get("extracted_frequencies_hz", [])
    lines += [
        "| | |", "|---|---|",
        f"| video | `{video}` ({problem_size(cal)}, {fps:g} fps) |",
        f"| object | `{obj.spec}` ({obj.kind}, {obj.mesh.n_nodes} nodes, "
        f"{len(obj.fixed_nodes)} clamped) |",
        f"| camera | {cal.method}, intrinsics {cal.intrinsics} |",
        f"| reprojection error | RMS {cal.rms_px:.3f} px, max {cal.max_px:.3f} px over "
        f"{cal.n_points} clicks (bound {opts.max_error:g} px) |",
        f"| modes | {len(freqs)} used of {len(modes)} extracted: "
        f"{', '.join(f'{f:.2f}' for f in freqs)} Hz |",
        f"| visible vertices | {problem.meta.get('n_visible')} |",
        f"| voxels | {problem.n_params} active of grid {list(obj.inference_shape)} |",
        f"| solver | {info.get('name', opts.solver)} {info.get('version', '')}, "
        f"{wall:.1f} s, sandbox {info.get('sandbox', '?')} |",
        f"| priors | nu {opts.nu:g}, initial {names[0]} {problem.w0:g} {units[0]}, "
        f"{names[1]} {problem.v0:g} {units[1]} |",
        f"| reused stages | {', '.join(reused) or 'none'} |", ""]
    if invalid is None:
        lines += ["## Result", "",
                  f"* {names[0]} ({units[0]}): {_stats(estimate.w)}",
                  f"* {names[1]} ({units[1]}): {_stats(estimate.v)}", "",
                  "Absolute values rest on the priors: the modes fix the material only up to "
                  "a common scale, which the solver anchors at the initial stiffness. Read "
                  "the map as relative contrast.", "",
                  "![fields](fields.png)", ""]
        if std:
            lines += [f"Per-voxel standard deviations stated by the solver: "
                      f"{', '.join(sorted(std))} (in `fields.npz`).", ""]
            if (out / "uncertainty.png").exists():
                lines += ["![uncertainty](uncertainty.png)", ""]
        else:
            lines += ["The solver states no per-voxel uncertainty.", ""]
    lines += ["## Files", "",
              "* `fields.npz` -- `w`, `v` per active voxel, `*_grid` on the voxel grid, "
              "`active`, standard deviations where stated" if invalid is None else
              "* `fields.npz` -- not written: the estimate is invalid",
              "* `camera.json` -- the camera and the reprojection error of each click",
              "* `modes.json` -- the modes used; `extract/` -- all extracted modes",
              "* `solve/` -- the solver's estimate as it returned it",
              "* `stages.json` -- each stage's inputs (sha256) and options", ""]
    return "\n".join(lines)


def problem_size(cal) -> str:
    """``WxH px`` of a calibration's camera."""
    return f"{cal.camera.width}x{cal.camera.height} px"


def options_dict(opts: InvertOptions) -> dict[str, Any]:
    """The options as JSON-serialisable data."""
    return jsonable(asdict(opts))
