"""``vvtbench solvers`` (list the installed inverse solvers) and ``vvtbench solve`` (run one on
a scene or a sample and score it)."""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

from .._version import __version__
from ..solving.plugins import PluginError
from .args import bounded, explain, one_line, positive_float, positive_int


def main_solvers(argv: list[str] | None = None) -> int:
    """``vvtbench solvers [-v]``: list registered solvers (with their options under -v)."""
    p = argparse.ArgumentParser(prog="vvtbench solvers", description="list inverse solvers")
    p.add_argument("-v", "--verbose", action="store_true", help="also list config options")
    args = p.parse_args(argv)
    return _list("solver", args.verbose)


def main_extractors(argv: list[str] | None = None) -> int:
    """``vvtbench extractors [-v]``: list registered motion extractors (options under -v)."""
    p = argparse.ArgumentParser(prog="vvtbench extractors",
                                description="list motion extractors (for `extract --extractor` "
                                "and a suite's 'extracted:NAME' observations)")
    p.add_argument("-v", "--verbose", action="store_true", help="also list config options")
    args = p.parse_args(argv)
    return _list("extractor", args.verbose)


def _list(kind: str, verbose: bool) -> int:
    """The registered plug-ins of ``kind``, each described by a sealed child (never imported
    here); one that cannot be imported is listed with its error."""
    from ..solving.sealed import list_sealed

    for name, d in list_sealed(kind).items():
        if "error" in d:
            print(f"{name:14s} {'-':8s} cannot be loaded: {d['error']}")
            continue
        print(f"{name:14s} {d['version']:8s} {d['description']}")
        if verbose:
            for key, default, help_ in d["fields"]:
                print(f"    {key:18s} = {default:10s} {help_}")
    return 0


def overrides_mapping(items: list[str] | None) -> dict[str, str]:
    """``["key=value", ...]`` (``--set``) as a mapping, read against the plug-in's Config in
    its sealed child."""
    values = {}
    for item in items or []:
        key, sep, text = item.partition("=")
        if not sep:
            raise PluginError(f"--set {item!r}: expected key=value")
        values[key.strip()] = text.strip()
    return values


def build_solve_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="vvtbench solve",
                                description="run an inverse solver on a sample or a scene and "
                                "score it")
    p.add_argument("solver", help="registered name or path/to/file.py:Class")
    p.add_argument("target", help="a sample folder written by `vvtbench generate` (observed as "
                   "it is, never simulated), a scene name or .toml (simulated now; true "
                   "image-space modes), or a challenge's problems folder (`vvtbench "
                   "challenge`: every problem is solved into a submission in OUTPUT)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="solver config override (repeatable)")
    p.add_argument("--modes", type=positive_int, default=10,
                   help="number of observed modes, >= 1 (10)")
    p.add_argument("--grid", type=bounded(int, ge=1, le=256), nargs="+", default=None,
                   help="inference voxel grid, 3 integers in 1..256 (default 8 8 8), drums 2 "
                   "(default 20 20)")
    p.add_argument("--geometry-scale", type=positive_float, default=1.0,
                   help="inference mesh width / true width (x), geometry-mismatch track")
    p.add_argument("--visibility", choices=("depth", "normals"), default="depth",
                   help="visible vertices: facing the camera and not occluded in the rest "
                   "depth buffer (default), or facing the camera only")
    p.add_argument("-o", "--output", required=True, help="output directory")
    p.add_argument("--no-mode-match", action="store_true", help="skip the mode-match metric")
    p.add_argument("--observation", choices=("true", "extracted"), default=None,
                   help="observe the true image-space modes or those extracted from the video "
                   "(default: extracted for a sample with a video, else true)")
    p.add_argument("--modes-file", default=None,
                   help="samples only: an extract output folder (modes.json + modes.npz); "
                   "default: extract from the sample's video into OUTPUT/modes (reused)")
    p.add_argument("--clicks", default=None, metavar="FILE",
                   help="samples only: a clicks file (JSON or CSV of inference-mesh vertex, u, "
                   "v; >= 6 non-coplanar vertices, format in docs/modes.md): the camera is "
                   "estimated from it instead of taken from the sample")
    p.add_argument("--timeout", type=positive_float, default=None,
                   help="seconds the solver may run (default 3600), then it is stopped")
    p.add_argument("--memory-gb", type=positive_float, default=None,
                   help="memory the solver may hold in GB, all its processes and its /dev/shm "
                   "together (default 75 %% of the machine's memory)")
    p.add_argument("--disk-gb", type=positive_float, default=None,
                   help="disk the solver may fill in GB: its /tmp, its output and what it "
                   "prints (default half the free space of the temporary folder)")
    p.add_argument("-v", "--verbose", action="store_true",
                   help="show what the solver printed (it is also kept: solver.log in OUTPUT, "
                   "or OUTPUT/ID/solver.log for a challenge's problems)")
    return p


def _fail(message: str | BaseException) -> int:
    print(f"error: {explain(message)}", file=sys.stderr)
    return 2


def _field_score(metrics: dict, field: str) -> str:
    """``NC w 0.412``, or the false contrast where the truth is constant (NC undefined)."""
    nc = metrics.get(f"nc_{field}")
    cov = metrics.get(f"interval_coverage_{field}")
    cov = "" if cov is None else f" (95 % interval coverage {cov:.2f})"
    if nc is not None:
        return f"NC {field} {nc:.3f}{cov}"
    return (f"{field}: constant truth, false contrast "
            f"{metrics[f'false_contrast_{field}']:.3f}{cov}")


SHOWN_LINES = 20  # lines of a failed plug-in's output shown on the terminal


def _show_output(output: str, where: Path | None, failed: bool, verbose: bool,
                 indent: str = "") -> None:
    """What the plug-in printed: all that was kept with ``verbose``, its last
    :data:`SHOWN_LINES` lines when it failed; ``where`` is the file that keeps it."""
    lines = output.splitlines()
    if not lines or not (failed or verbose):
        return
    shown = lines if verbose else lines[-SHOWN_LINES:]
    kept = f"; all it printed that was kept: {where}" if where is not None else ""
    head = ("what it printed" if len(shown) == len(lines)
            else f"the last {len(shown)} lines it printed")
    stream = sys.stderr if failed else sys.stdout
    print(f"{indent}--- {head}{kept} ---", file=stream)
    for line in shown:
        print(f"{indent}| {line}", file=stream)


def _keep_output(folder: Path, output: str) -> Path | None:
    """``folder/solver.log``: what the plug-in printed (the kept tail), or None."""
    if not output:
        return None
    from ..io.files import write_text

    try:
        folder.mkdir(parents=True, exist_ok=True)
        write_text(folder / "solver.log", output)
    except OSError:
        return None
    return folder / "solver.log"


def _sandbox_note(sinfo: dict) -> str:
    return " [UNSANDBOXED: the solver could read any file you can]" \
        if sinfo.get("sandbox") == "none" else ""


def _check_output(out: Path, target: Path) -> str | None:
    """The output folder may not be a file, nor the target sample or inside it."""
    if out.exists() and not out.is_dir():
        return f"-o {out}: exists and is not a folder"
    if target.is_dir() and (target / "manifest.json").is_file():
        o, t = out.resolve(), target.resolve()
        if o == t or t in o.parents:
            return (f"-o {out}: inside the sample {target} (it would change the sample and "
                    "break its manifest); give another folder")
    return None


def main_solve(argv: list[str] | None = None) -> int:
    """``vvtbench solve SOLVER TARGET [--set k=v] [--modes K] -o DIR``: observe the target
    (:func:`vvtbench.observe.observe`), solve, score against the truth, write the outputs."""
    from ..observe import ObserveError, ObserveOptions, observe
    from ..samples.reader import DatasetError, open_sample
    from ..scene.scene import SceneError, load_scene

    args = build_solve_parser().parse_args(argv)
    if args.grid is not None and len(args.grid) not in (2, 3):
        return _fail(f"--grid: give 3 integers (boxes: nx ny nz) or 2 (drums), got "
                     f"{len(args.grid)}")
    from ..bench.child import DEFAULT_TIMEOUT, default_memory_bytes
    from ..solving.sealed import SealedError, describe_sealed, solve_sealed

    timeout = args.timeout or DEFAULT_TIMEOUT
    try:  # imported and configured in a sealed child; an unknown name gets a "did you mean"
        overrides = overrides_mapping(args.overrides)
        desc = describe_sealed("solver", args.solver, overrides, timeout=min(timeout, 600.0))
    except PluginError as error:
        return _fail(error)
    name = desc["name"]
    target, out = Path(args.target), Path(args.output)
    if _is_problems(target):
        return _solve_problems(args, desc, overrides, target, out, timeout)
    message = _check_output(out, target)
    if message:
        return _fail(message)
    t0 = time.perf_counter()
    options = dict(n_modes=args.modes, geometry_scale=args.geometry_scale,
                   inference_shape=tuple(args.grid) if args.grid else None,
                   visibility=args.visibility, clicks=args.clicks)
    try:  # the options are checked before any work
        ObserveOptions(**options)
    except (ObserveError, ValueError) as error:
        return _fail(error)
    info: dict = {"target": str(target)}
    if target.exists() and not target.is_dir():
        if target.suffix.lower() != ".toml":
            return _fail(f"{target}: not a sample folder nor a scene .toml file")
    if target.is_dir():
        try:
            source = open_sample(target)
        except DatasetError as error:
            return _fail(error)
        observation = args.observation or ("extracted" if source.has_video else "true")
        if args.clicks is not None:
            n_clicks, message = _check_clicks(args.clicks)
            if message:
                return _fail(message)
        if observation == "extracted":
            modes_dir, message = _modes(source, args.modes_file, out)
            if message:
                return _fail(message)
            options["modes"] = (str(modes_dir),)
            info["modes_dir"] = str(modes_dir)
        elif args.modes_file is not None:
            return _fail("--modes-file needs --observation extracted")
    else:
        if args.clicks is not None:
            return _fail(f"--clicks needs a sample folder; {args.target} is a scene, filmed "
                         "by its own camera")
        observation = args.observation or "true"
        if observation == "extracted":
            return _fail(f"--observation extracted needs a sample folder with a video; "
                         f"{args.target} is a scene (generate a sample first)")
        try:
            source = load_scene(args.target)
        except SceneError as error:
            return _fail(error)
    try:
        problem, truth = observe(source, observation=observation, **options)
    except (ObserveError, DatasetError, SceneError, ValueError) as error:
        text = explain(error)
        return _fail(text if text.startswith(str(target)) else f"{target}: {text}")
    if args.clicks is not None:
        print(f"camera from {n_clicks} clicks ({args.clicks}): reprojection rms "
              f"{problem.meta['clicks_rms_px']:.3f} px")
    t_setup = time.perf_counter() - t0
    memory = (int(args.memory_gb * 2**30) if args.memory_gb else default_memory_bytes())
    disk = int(args.disk_gb * 2**30) if args.disk_gb else None
    secrets = [out, *([target] if target.is_dir() else [])]
    try:
        estimate, wall, sinfo = solve_sealed(args.solver, overrides, problem, truth=truth,
                                             timeout=timeout, memory_bytes=memory,
                                             secrets=secrets, disk_bytes=disk)
    except SealedError as error:
        print(f"error: {name} failed on {target}: {one_line(str(error))}", file=sys.stderr)
        _show_output(error.output, _keep_output(out, error.output), True, args.verbose)
        return 1
    _show_output(sinfo["log"], None, False, args.verbose)
    out.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=".solve-", dir=out))
    try:  # everything is written aside, then moved into place: never a half-written folder
        from ..io.files import write_text

        write_text(stage / "solver.log", sinfo["log"])  # empty too: never an earlier one
        ev = _write_solve(stage, args, estimate, wall, sinfo, problem, truth, info, observation,
                          t_setup, target)
        _publish(stage, out, invalid=bool(ev.get("invalid")))
    except OSError as error:
        shutil.rmtree(stage, ignore_errors=True)
        return _fail(f"{out}: cannot write the results: {error.strerror or error} (nothing "
                     "was changed there)")
    if ev.get("invalid"):
        print(f"INVALID ESTIMATE, not a result: {name} on {target}: {ev['invalid']} "
              f"(an estimate must be finite and positive in every voxel; nothing is drawn "
              f"or scored) -> {out / 'solve.json'}", file=sys.stderr)
        return 1
    score = ", ".join(_field_score(ev["metrics"], f) for f in "wv")
    print(f"{name}{' (reference: reads the truth)' if sinfo['reference'] else ''} on {target} "
          f"({observation} modes, {problem.n_modes}): {len(estimate.history)} iterations, "
          f"{estimate.runtime_s:.2f} s; {score} -> {out}{_sandbox_note(sinfo)}")
    print("  NC: normalized correlation of the estimated and true fields per voxel (1 = same "
          "pattern, 0 = none); details in docs/metrics.md. Next: open "
          f"{out / 'slices.png'}, or compare solvers with `vvtbench run`.")
    return 0


def _write_solve(stage: Path, args, estimate, wall, sinfo, problem, truth, info, observation,
                 t_setup, target) -> dict:
    from ..bench.stages import write_evaluation
    from ..io.files import write_json
    from ..reporting.plots import contrast_first, plot_fields, plot_uncertainty

    name = sinfo["name"]
    estimate.save(stage, problem, wall_s=wall)
    stds = (estimate.std("w_std"), estimate.std("v_std"))
    ev = write_evaluation(stage, problem, truth, estimate.w, estimate.v,
                          modes=not args.no_mode_match, w_std=stds[0], v_std=stds[1])
    write_json(stage / "solve.json", {
        **info, "scene": truth.meta.get("scene"), "observation": observation,
        "solver": name, "solver_version": sinfo["version"], "config": sinfo["config"],
        "sandbox": sinfo["sandbox"], "reference": bool(sinfo["reference"]),
        "n_modes": problem.n_modes, "setup_s": t_setup, "vvtbench": __version__,
        "problem": problem.meta, "status": "invalid" if ev.get("invalid") else "ok",
        "invalid": ev.get("invalid"), "metrics": ev["metrics"],
        "extraction": None if truth.extraction_mac is None else {
            "matched_true_modes": truth.matched, "extraction_mac": truth.extraction_mac,
            "true_frequencies_hz": truth.frequencies_hz}})
    if ev.get("invalid"):
        return ev
    scene = truth.meta.get("scene") or target.name
    metrics = ev.get("metrics") or {}
    plot_fields(stage / "slices.png", problem, {name: (estimate.w, estimate.v)}, truth,
                scene=scene, observation=observation, solver=name,
                score={"NC w": metrics.get("nc_w"), "NC v": metrics.get("nc_v")},
                normalized=contrast_first(problem.to_grid(truth.w),
                                          [problem.to_grid(estimate.w)]))
    if any(sd is not None for sd in stds):
        plot_uncertainty(stage / "uncertainty.png", problem, (estimate.w, estimate.v), stds,
                         truth, title=f"{name} on {scene} ({observation} modes): stated "
                                      "uncertainty")
    return ev


def _publish(stage: Path, out: Path, invalid: bool) -> None:
    """Move the staged outputs into ``out``; an earlier solve's figures go when this estimate
    is invalid (they would be read as its result)."""
    for f in sorted(stage.iterdir()):
        os.replace(f, out / f.name)
    stage.rmdir()
    if invalid:
        for stale in ("slices.png", "uncertainty.png"):
            p = out / stale
            if p.is_file() and not p.is_symlink():
                p.unlink()


def _is_problems(target: Path) -> bool:
    from ..bench.submission import PROBLEMS

    try:
        return json.loads((target / "manifest.json").read_text()).get("format") == PROBLEMS
    except (OSError, ValueError, AttributeError):
        return False


def _solve_problems(args, desc: dict, overrides: dict, problems: Path, out: Path,
                    timeout: float) -> int:
    """Every problem of a challenge's problems folder, solved sealed, into a submission."""
    from ..bench.child import default_memory_bytes
    from ..bench.submission import SubmissionError, read_manifest, write_submission
    from ..scoring.metrics import invalid_reason
    from ..solving.problem import InverseProblem
    from ..solving.sealed import SealedError, solve_sealed

    if desc["uses_truth"]:
        return _fail(f"{desc['name']} reads the truth (a reference); a challenge has none")
    if out.exists() and any(out.iterdir()):
        return _fail(f"-o {out}: exists and is not empty; give a new folder")
    try:
        man = read_manifest(problems, "vvtbench-problems")
    except SubmissionError as error:
        return _fail(error)
    memory = int(args.memory_gb * 2**30) if args.memory_gb else default_memory_bytes()
    disk = int(args.disk_gb * 2**30) if args.disk_gb else None
    estimates, failed, sandbox = {}, [], set()
    for instance in sorted(man["instances"]):
        problem = InverseProblem.load(problems / instance)
        try:
            est, _, sinfo = solve_sealed(args.solver, overrides, problem, timeout=timeout,
                                         memory_bytes=memory, secrets=[out], disk_bytes=disk)
        except SealedError as error:
            failed.append(instance)
            print(f"  {instance}: {one_line(str(error))}", file=sys.stderr)
            _show_output(error.output, _keep_output(out / instance, error.output), True,
                         args.verbose, "    ")
            continue
        sandbox.add(sinfo["sandbox"])
        kept = _keep_output(out / instance, sinfo["log"])
        reason = invalid_reason(est.w, est.v, problem.n_params, *(
            est.extra.get(k) if isinstance(est.extra, dict) else None for k in ("w_std", "v_std")))
        if reason is not None:  # the reason `score` would give: refused here, not submitted
            failed.append(instance)
            print(f"  {instance}: INVALID ESTIMATE, not submitted: {reason}", file=sys.stderr)
            _show_output(sinfo["log"], kept, True, args.verbose, "    ")
            continue
        estimates[instance] = est
        print(f"  {instance}: {len(est.history)} iterations, {est.runtime_s:.2f} s")
        _show_output(sinfo["log"], kept, False, args.verbose, "    ")
    n = len(man["instances"])
    if not estimates:
        print(f"error: {desc['name']} solved none of the {n} problems of {problems} (each "
              f"one's error is above): no submission was written", file=sys.stderr)
        return 1
    write_submission(estimates, problems, out, desc["name"], desc["version"])
    note = _sandbox_note({"sandbox": "none"}) if "none" in sandbox else ""
    print(f"{len(estimates)} of {n} problems solved by {desc['name']} -> "
          f"{out} (a submission: score it with `vvtbench score {out} --truth TRUTH -o DIR`)"
          f"{note}")
    return 1 if failed else 0


def _check_clicks(path: str) -> tuple[int, str | None]:
    from ..modes import load_clicks

    try:  # vertex indices are checked against the inference mesh later
        n_clicks = len(load_clicks(path)[0])
    except (OSError, ValueError) as error:
        return 0, f"--clicks: {error}"
    if n_clicks < 6:
        return n_clicks, (f"--clicks: {path}: camera estimation needs >= 6 vertex <-> pixel "
                          f"pairs (non-coplanar vertices), got {n_clicks}")
    return n_clicks, None


def _modes(sample, modes_file: str | None, out: Path) -> tuple[Path | None, str | None]:
    """The extract output folder to observe: ``--modes-file``, or OUTPUT/modes (extracted from
    the sample's video now unless already there)."""
    from ..modes import ModeSet

    if modes_file is not None:
        modes_dir = Path(modes_file)
        if modes_dir.is_file():
            modes_dir = modes_dir.parent
        try:
            ModeSet.load(modes_dir)
        except (FileNotFoundError, ValueError) as error:
            return None, f"--modes-file: {error}"
        return modes_dir, None
    if not sample.has_video:
        return None, (f"{sample.path}: a modes-only sample has no video to extract from; use "
                      "--observation true")
    modes_dir = out / "modes"
    if not (modes_dir / "modes.json").is_file():
        from ..solving.sealed import SealedError, extract_sealed

        try:
            extract_sealed(sample.video_path, sample.fps, {}, modes_dir,
                           secrets=[sample.path, out])
        except SealedError as error:
            return None, f"{sample.video_path}: extraction failed: {error}"
    return modes_dir, None
