"""Simulator performance: modes, transient, bunny, scaling and peak memory.

Each case runs in its own process so that its peak RSS is its own. Prints a Markdown table.

    .venv/bin/python benchmarks/bench_fem.py            # all cases (~3-5 min on 2 cores)
    .venv/bin/python benchmarks/bench_fem.py --quick    # skip 32^3 and the baseline
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time

import numpy as np


def _peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def case_cube(n: int, k: int = 50, method: str = "auto") -> dict:
    from vvtbench.fem.assembly import ParametricModel
    from vvtbench.fem.mesh import box_mesh
    from vvtbench.fem.modal import eigenmodes

    t0 = time.perf_counter()
    mesh = box_mesh((n, n, n), (0.05, 0.05, 0.05))
    model = ParametricModel(mesh, fixed_nodes=mesh.node_sets["bottom"])
    K, M = model.K(9000.0), model.M(1270.0)
    t1 = time.perf_counter()
    if method == "baseline":
        import scipy.sparse.linalg as spla

        lam, _ = spla.eigsh(K.tocsc(), k=k, M=M.tocsc(), sigma=-1e-3)
        f1 = float(np.sqrt(np.sort(lam)[0]) / 2 / np.pi)
    else:
        f1 = float(eigenmodes(K, M, k, method=method).frequencies_hz[0])
    t2 = time.perf_counter()
    return {"dofs": model.n_free, "assembly_s": t1 - t0, "modes_s": t2 - t1,
            "total_s": t2 - t0, "f1_hz": f1}


def case_transient() -> dict:
    from vvtbench.scene.scene import load_scene
    from vvtbench.simulation.simulate import simulate

    scene = load_scene("jello_cube_damped_top_front")
    scene = scene.model_copy(update={"simulation": scene.simulation.model_copy(
        update={"duration": 6.0, "fps": 2000.0})})
    t0 = time.perf_counter()
    result = simulate(scene)
    t1 = time.perf_counter()
    u = result.displacements
    t2 = time.perf_counter()
    return {"frames": len(result.times), "surface_nodes": len(result.surface_nodes),
            "transient_s": result.timings["transient"] + t2 - t1, "total_s": t2 - t0,
            "output_mib": u.nbytes / 2**20}


def case_bunny() -> dict:
    """The bunny scene with an empty tet-mesh cache, so pytetwild always runs."""
    from vvtbench.scene.scene import load_scene
    from vvtbench.simulation.simulate import simulate

    scene = load_scene("bunny_defect")
    with tempfile.TemporaryDirectory(prefix="vvtbench-bench-cache-") as cache:
        os.environ["VVTBENCH_CACHE"] = cache
        t0 = time.perf_counter()
        result = simulate(scene, transient=False)
        total = time.perf_counter() - t0
    return {"tets": result.mesh.n_elements, "dofs": result.model.n_free,
            "mesh_s": result.timings["mesh"], "modes_s": result.timings["modes"],
            "total_s": total, "f1_hz": float(result.frequencies_hz[0])}


CASES = {"cube": case_cube, "transient": case_transient, "bunny": case_bunny}


def run_case(name: str, *args: str) -> dict:
    cmd = [sys.executable, __file__, "--case", name, *args]
    out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--case")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("args", nargs="*")
    a = parser.parse_args()
    if a.case:
        args = [int(x) if x.isdigit() else x for x in a.args]
        result = CASES[a.case](*args)
        result["peak_rss_mib"] = _peak_rss_mib()
        print(json.dumps(result))
        return
    print(f"# vvtbench FEM benchmark — {time.strftime('%Y-%m-%d')}, {platform.node()}, "
          f"{platform.processor() or platform.machine()}, Python {platform.python_version()}")
    from vvtbench.fem.modal import Factorization  # noqa: F401

    try:
        import sksparse  # noqa: F401
        backend = "CHOLMOD (scikit-sparse)"
    except ImportError:
        backend = "SuperLU (MMD_AT_PLUS_A); install vvtbench[fast] for CHOLMOD"
    print(f"sparse factorization: {backend}\n")
    print("## Hex8 cube, bottom fixed, 50 lowest modes (goal: 10^3 <= 1 s, 24^3 <= 20 s)\n")
    print("| grid | free DOFs | assembly s | modes s | total s | peak RSS MiB | f1 Hz |")
    print("|---|---|---|---|---|---|---|")
    sizes = [8, 10, 12, 16, 20, 24] + ([] if a.quick else [32])
    for n in sizes:
        r = run_case("cube", str(n))
        print(f"| {n}^3 | {r['dofs']} | {r['assembly_s']:.2f} | {r['modes_s']:.2f} | "
              f"{r['total_s']:.2f} | {r['peak_rss_mib']:.0f} | {r['f1_hz']:.4f} |", flush=True)
    if not a.quick:
        print("\nBaseline: scipy eigsh shift-invert with its default SuperLU factorization\n")
        print("| grid | free DOFs | modes s | total s | peak RSS MiB |")
        print("|---|---|---|---|---|")
        for n in [10, 16]:
            r = run_case("cube", str(n), "50", "baseline")
            print(f"| {n}^3 | {r['dofs']} | {r['modes_s']:.2f} | {r['total_s']:.2f} | "
                  f"{r['peak_rss_mib']:.0f} |", flush=True)
    r = run_case("transient")
    print("\n## Transient: damped 10^3 cube, 6 s at 2000 FPS, all surface nodes (goal <= 2 s)\n")
    print(f"{r['frames']} frames x {r['surface_nodes']} surface nodes "
          f"({r['output_mib']:.0f} MiB float32): transient {r['transient_s']:.2f} s, whole "
          f"simulate {r['total_s']:.2f} s, peak RSS {r['peak_rss_mib']:.0f} MiB")
    r = run_case("bunny")
    print("\n## Bunny: simplify + tetrahedralize (no mesh cache) + 50 modes (goal <= 60 s)\n")
    print(f"{r['tets']} tets, {r['dofs']} free DOFs: mesh {r['mesh_s']:.1f} s, modes "
          f"{r['modes_s']:.1f} s, total {r['total_s']:.1f} s, peak RSS {r['peak_rss_mib']:.0f} "
          f"MiB, f1 {r['f1_hz']:.3f} Hz")


if __name__ == "__main__":
    main()
