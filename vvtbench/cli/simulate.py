"""``vvtbench simulate`` (modal analysis and transient of a scene) and ``vvtbench scenes``."""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from .._version import __version__
from .args import positive_int

DEFAULT_SCENE = "jello_cube_defect_top"


def build_simulate_parser(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options of ``vvtbench simulate`` added to ``p``."""
    p.add_argument("scene", nargs="?", default=DEFAULT_SCENE,
                   help=f"scene file or shipped scene name (default: {DEFAULT_SCENE})")
    p.add_argument("--modes", type=positive_int, default=None,
                   help="number of modes, >= 1 (overrides the scene)")
    p.add_argument("--transient", action="store_true", help="also run the transient response")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    return p


def run_simulate(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.table import Table

    from ..scene.scene import load_scene, parse_scene
    from ..simulation.simulate import simulate

    scene = load_scene(args.scene)
    if args.modes is not None:  # validated like the scene file's simulation.n_modes
        data = scene.to_toml_dict()
        data.setdefault("simulation", {})["n_modes"] = args.modes
        scene = parse_scene(data, f"{scene.source} with --modes {args.modes}")
    t0 = time.perf_counter()
    result = simulate(scene, transient=args.transient)
    elapsed = time.perf_counter() - t0
    freqs, zetas = result.frequencies_hz, result.damping_ratios
    if args.json:
        out = {
            "scene": scene.name,
            "vvtbench": __version__,
            "element": result.mesh.element,
            "n_elements": result.mesh.n_elements,
            "n_free_dofs": result.model.n_free,
            "frequencies_hz": freqs.tolist(),
            "damping_ratios": [float(z) for z in zetas],
            "rayleigh": {"alpha": result.alpha, "beta": result.beta},
            "timings_s": result.timings,
        }
        print(json.dumps(out, indent=2))
        return 0
    console = Console()
    mesh = result.mesh
    console.print(
        f"[bold]{scene.name}[/]: {mesh.n_elements} {mesh.element} elements, "
        f"{result.model.n_free} free DOFs, Rayleigh alpha={result.alpha:.4g} 1/s, "
        f"beta={result.beta:.4g} s"
    )
    table = Table(title=f"Natural frequencies ({len(freqs)} lowest modes)")
    table.add_column("mode", justify="right")
    table.add_column("f (Hz)", justify="right")
    table.add_column("zeta", justify="right")
    for i, (f, z) in enumerate(zip(freqs, zetas, strict=True), 1):
        table.add_row(str(i), f"{f:.4f}", "inf" if not np.isfinite(z) else f"{z:.5f}")
    console.print(table)
    times = ", ".join(f"{k} {v:.2f} s" for k, v in result.timings.items())
    console.print(f"done in {elapsed:.2f} s ({times})")
    if result.displacements is not None:
        peak = float(np.abs(result.displacements).max())
        console.print(
            f"transient: {len(result.times)} frames at {scene.simulation.fps:g} FPS of "
            f"{len(result.surface_nodes)} surface nodes, peak |u| = {peak:.3g} m"
            + (
                f", modal truncation error {result.truncation_error:.2%}"
                if result.truncation_error is not None
                else ""
            )
        )
    return 0


def run_scenes(args: argparse.Namespace) -> int:
    from ..scene.scene import SCENES_DIR, load_scene

    for path in sorted(SCENES_DIR.glob("*.toml")):
        scene = load_scene(path)
        print(f"{path.stem:36s} {scene.geometry.kind:5s} {scene.description}")
    return 0
