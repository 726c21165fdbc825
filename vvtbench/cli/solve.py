"""``vvtbench solvers`` (list the installed inverse solvers) and ``vvtbench solve`` (run one on
a scene or a sample and score it)."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from .._version import __version__
from ..plugins import PluginError, describe_config, list_solvers, load_solver, parse_overrides


def main_solvers(argv: list[str] | None = None) -> int:
    """``vvtbench solvers [-v]``: list registered solvers (with their options under -v)."""
    p = argparse.ArgumentParser(prog="vvtbench solvers", description="list inverse solvers")
    p.add_argument("-v", "--verbose", action="store_true", help="also list config options")
    args = p.parse_args(argv)
    for name, cls in list_solvers().items():
        print(f"{name:14s} {cls.version:8s} {cls.description}")
        if args.verbose:
            for key, default, help_ in describe_config(cls.Config):
                print(f"    {key:14s} = {default:10s} {help_}")
    return 0


def build_solve_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="vvtbench solve",
                                description="run an inverse solver on a scene and score it")
    p.add_argument("solver", help="registered name or path/to/file.py:Class")
    p.add_argument("target", help="scene name or .toml (simulated; true image-space modes), "
                   "or a sample folder written by `vvtbench generate`")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="solver config override (repeatable)")
    p.add_argument("--modes", type=int, default=10, help="number of observed modes (10)")
    p.add_argument("--grid", type=int, nargs="+", default=None,
                   help="inference voxel grid (default 8 8 8; drums 20 20)")
    p.add_argument("--geometry-scale", type=float, default=1.0,
                   help="inference mesh width / true width (x), geometry-mismatch track")
    p.add_argument("-o", "--output", required=True, help="output directory")
    p.add_argument("--no-mode-match", action="store_true", help="skip the mode-match metric")
    p.add_argument("--observation", choices=("true", "extracted"), default="extracted",
                   help="samples only: observe the true image-space modes or those extracted "
                   "from the video (default)")
    p.add_argument("--modes-file", default=None,
                   help="samples only: an extract output folder (modes.json + modes.npz); "
                   "default: extract from the sample's video into OUTPUT/modes (reused)")
    p.add_argument("--clicks", default=None, metavar="FILE",
                   help="samples only: a clicks file (JSON or CSV of inference-mesh vertex, u, "
                   "v; >= 6 non-coplanar vertices, format in docs/modes.md): the camera is "
                   "estimated from it instead of taken from the sample")
    return p


def main_solve(argv: list[str] | None = None) -> int:
    """``vvtbench solve SOLVER SCENE [--set k=v] [--modes K] -o DIR``."""
    args = build_solve_parser().parse_args(argv)
    try:
        cls = load_solver(args.solver)
        config = parse_overrides(args.overrides, cls.Config)
    except PluginError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    from ..metrics import score
    from ..problem import InverseProblem
    from ..scene import load_scene
    from ..simulate import simulate

    target = Path(args.target)
    out = Path(args.output)
    if target.is_dir():
        return _solve_sample(args, cls, config, target, out)
    if args.clicks is not None:
        print(f"error: --clicks needs a sample folder; {args.target} is a scene, filmed by its "
              "own camera", file=sys.stderr)
        return 2
    scene = load_scene(args.target)
    grid = tuple(args.grid) if args.grid else ((20, 20) if scene.geometry.kind == "drum"
                                               else (8, 8, 8))
    t0 = time.perf_counter()
    result = simulate(scene, transient=False)
    problem = InverseProblem.from_simulation(result, inference_shape=grid, n_modes=args.modes,
                                             geometry_scale=args.geometry_scale)
    t_setup = time.perf_counter() - t0
    estimate = cls(config).solve(problem)
    metrics = score(problem, estimate.w, estimate.v, modes=not args.no_mode_match)
    out.mkdir(parents=True, exist_ok=True)
    save_estimate(out, problem, estimate, metrics, extra={
        "scene": scene.name, "n_modes": args.modes, "setup_s": t_setup, "vvtbench": __version__})
    print(f"{cls.name} on {scene.name}: {len(estimate.history)} iterations, "
          f"{estimate.runtime_s:.2f} s; NC w {metrics.get('nc_w', float('nan')):.3f}, "
          f"v {metrics.get('nc_v', float('nan')):.3f} -> {out}")
    return 0


def _solve_sample(args, cls, config, target: Path, out: Path) -> int:
    """``vvtbench solve SOLVER SAMPLE_DIR``: the problem of a generated sample, observing the
    modes extracted from its video (or the true ones), solved and written like a scene's."""
    from ..dataset import DatasetError, open_sample
    from ..metrics import score
    from ..problem import InverseProblem

    try:
        sample = open_sample(target)
    except DatasetError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    if args.clicks is not None:
        from ..modes import load_clicks

        try:  # fail before the simulation; vertex indices are checked against the mesh later
            n_clicks = len(load_clicks(args.clicks)[0])
        except (OSError, ValueError) as error:
            print(f"error: --clicks: {error}", file=sys.stderr)
            return 2
        if n_clicks < 6:
            print(f"error: --clicks: {args.clicks}: camera estimation needs >= 6 vertex <-> "
                  f"pixel pairs (non-coplanar vertices), got {n_clicks}", file=sys.stderr)
            return 2
    modesets = None
    modes_dir = None
    t0 = time.perf_counter()
    if args.observation == "extracted":
        from ..modes import ModeSet, extract_modes

        if args.modes_file is not None:
            modes_dir = Path(args.modes_file)
            if modes_dir.is_file():
                modes_dir = modes_dir.parent
            try:
                modesets = [ModeSet.load(modes_dir)]
            except (FileNotFoundError, ValueError) as error:
                print(f"error: --modes-file: {error}", file=sys.stderr)
                return 2
        else:
            modes_dir = out / "modes"
            if (modes_dir / "modes.json").is_file():
                modesets = [ModeSet.load(modes_dir)]
            else:
                ms = extract_modes(sample.video_path, sample.fps)
                ms.save(modes_dir)
                modesets = [ms]
    elif args.modes_file is not None:
        print("error: --modes-file needs --observation extracted", file=sys.stderr)
        return 2
    grid = tuple(args.grid) if args.grid else None
    try:
        problem = InverseProblem.from_sample(
            sample, args.observation, modesets, inference_shape=grid, n_modes=args.modes,
            geometry_scale=args.geometry_scale, clicks=args.clicks)
    except ValueError as error:
        print(f"error: {target}: {error}", file=sys.stderr)
        return 2
    if args.clicks is not None:
        print(f"camera from {n_clicks} clicks ({args.clicks}): reprojection rms "
              f"{problem.meta['clicks_rms_px']:.3f} px")
    t_setup = time.perf_counter() - t0
    estimate = cls(config).solve(problem)
    metrics = score(problem, estimate.w, estimate.v, modes=not args.no_mode_match)
    out.mkdir(parents=True, exist_ok=True)
    save_estimate(out, problem, estimate, metrics, extra={
        "scene": sample.scene.name, "sample": str(target), "observation": args.observation,
        "modes_dir": None if modes_dir is None else str(modes_dir),
        "n_modes": problem.n_modes, "setup_s": t_setup, "vvtbench": __version__})
    print(f"{cls.name} on {target} ({args.observation} modes, {problem.n_modes}): "
          f"{len(estimate.history)} iterations, {estimate.runtime_s:.2f} s; "
          f"NC w {metrics.get('nc_w', float('nan')):.3f}, "
          f"v {metrics.get('nc_v', float('nan')):.3f} -> {out}")
    return 0


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    return x


def save_estimate(out: Path, problem, estimate, metrics: dict, extra: dict | None = None):
    """estimate.npz (grids of w, v and the truth), estimate.json (config, history, runtime,
    versions, metrics) and slices.png (w and v beside the truth)."""
    out = Path(out)
    arrays = {"w": problem.to_grid(estimate.w), "v": problem.to_grid(estimate.v),
              "w_params": estimate.w, "v_params": estimate.v,
              "active": problem.voxel_map.active}
    if problem.has_truth:
        arrays["w_true"] = problem.to_grid(problem.w_true)
        arrays["v_true"] = problem.to_grid(problem.v_true)
    np.savez_compressed(out / "estimate.npz", **arrays)
    doc = {
        "solver": estimate.solver, "solver_version": estimate.version,
        "config": estimate.config, "runtime_s": estimate.runtime_s,
        "converged": estimate.converged, "iterations": len(estimate.history),
        "history": estimate.history, "metrics": metrics, "problem": problem.meta,
        "extra": estimate.extra_scalars(),
        **(extra or {}),
    }
    (out / "estimate.json").write_text(json.dumps(_jsonable(doc), indent=1, default=str))
    plot_slices(out / "slices.png", problem, estimate)


def plot_slices(path: Path, problem, estimate) -> None:
    """Middle slices (along y) of w and v, each beside the truth (if known), with matplotlib."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [("w (estimate)", problem.to_grid(estimate.w))]
    if problem.has_truth:
        rows.append(("w (truth)", problem.to_grid(problem.w_true)))
    rows.append(("v (estimate)", problem.to_grid(estimate.v)))
    if problem.has_truth:
        rows.append(("v (truth)", problem.to_grid(problem.v_true)))
    ny = rows[0][1].shape[1]
    cols = sorted({0, ny // 4, ny // 2, (3 * ny) // 4, ny - 1})
    fig, axes = plt.subplots(len(rows), len(cols), figsize=(2.2 * len(cols), 2.2 * len(rows)),
                             squeeze=False)
    for r, (label, grid) in enumerate(rows):
        for c, j in enumerate(cols):
            ax = axes[r, c]
            im = ax.imshow(grid[:, j, :].T, origin="lower", cmap="viridis")
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(f"y slice {j}", fontsize=8)
            if c == 0:
                ax.set_ylabel(label, fontsize=8)
        fig.colorbar(im, ax=axes[r, :].tolist(), fraction=0.02)
    fig.savefig(path, dpi=90)
    plt.close(fig)
