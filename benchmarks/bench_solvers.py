"""vvt solver performance: sparse (this package) vs a dense baseline doing what the authors'
code does (dense np.linalg.solve per mode for the u-update, dense z-system), one run.

    python benchmarks/bench_solvers.py [--quick] [--json out.json]

Reports: seconds per vvt iteration on 8^3 and 16^3 voxel grids with 20 modes, the ratio to the
dense baseline (8^3; the dense 16^3 iteration is extrapolated by n^3), peak memory (RSS, in a
fresh subprocess per grid) vs voxels, iterations to convergence and NC vs iteration (8^3).
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time

import numpy as np

SCENE = "jello_cube_defect_top"


def _observed(grid: int, n_modes: int):
    """(problem, truth) of the benchmark scene's true modes on a grid^3 voxel grid."""
    from vvtbench.observe import observe

    return observe(SCENE, inference_shape=(grid,) * 3, n_modes=n_modes, visibility="normals")


def _problem(grid: int, n_modes: int):
    return _observed(grid, n_modes)[0]


def dense_iteration(problem, alpha_u=10.0, alpha_w=1e-10, alpha_v=1e-7) -> dict:
    """One iteration the way the authors' code does it (dense linear algebra)."""
    from solvers.vvt import grid_laplacian

    model = problem.model
    k, m, n = problem.n_modes, problem.n_params, model.n_free
    P = problem.P / abs(problem.P).max()
    w = np.full(m, problem.w0)
    v = np.full(m, problem.v0)
    y = np.ones(k)
    lam = problem.eigenvalues
    K, M = model.K(w), model.M(v)
    PtP = (P.T @ P).toarray()
    t0 = time.perf_counter()
    U = np.empty((n, k))
    for i in range(k):
        D = (K - lam[i] * M).toarray()
        A = y[i] * D.T @ D + alpha_u * PtP
        U[:, i] = np.linalg.solve(A, alpha_u * (P.T @ problem.gamma[i]))
    t1 = time.perf_counter()
    L = grid_laplacian(problem.voxel_map).toarray()
    A_constr = np.zeros((k * n, 2 * m))
    for i in range(k):
        G = model.stiffness_columns(U[:, i]).toarray()
        H = model.mass_columns(U[:, i]).toarray()
        A_constr[i * n:(i + 1) * n] = np.sqrt(y[i] / k) * np.hstack([G, -lam[i] * H])
    Z = np.zeros((m, m))
    A_reg = np.block([[np.sqrt(alpha_w / m) * L, Z], [Z, np.sqrt(alpha_v / m) * L]])
    A_mean = np.zeros((1, 2 * m))
    A_mean[0, :m] = 1.0 / m
    A_full = np.vstack([A_constr, A_reg, A_mean])
    z = np.linalg.solve(A_full.T @ A_full, A_mean.T @ [problem.w_mean])
    t2 = time.perf_counter()
    return {"u_s": t1 - t0, "z_s": t2 - t1, "total_s": t2 - t0, "n_free": n,
            "finite": bool(np.all(np.isfinite(z)))}


def sparse_run(grid: int, n_modes: int, max_iter: int,
               overrides: list[str] | None = None) -> dict:
    """A vvt run; ``overrides``: ``key=value`` config items as for ``vvtbench solve --set``."""
    from dataclasses import replace

    from solvers.vvt import VVTConfig, VVTSolver
    from vvtbench.scoring.metrics import normalized_correlation as nc
    from vvtbench.solving.plugins import parse_overrides

    t0 = time.perf_counter()
    problem, truth = _observed(grid, n_modes)
    setup = time.perf_counter() - t0
    cfg = replace(parse_overrides(overrides, VVTConfig), max_iter=max_iter)
    est = VVTSolver(cfg).solve(problem)
    times = [h["time_s"] for h in est.history]
    return {
        "grid": grid, "voxels": problem.n_params, "n_free": problem.model.n_free,
        "n_modes": n_modes, "setup_s": setup, "iterations": len(times),
        "converged": est.converged, "first_iteration_s": times[0],
        "mean_iteration_s": float(np.mean(times)),
        "mean_iteration_after_first_s": float(np.mean(times[1:])) if len(times) > 1 else None,
        "median_iteration_s": float(np.median(times)),
        "nc_w": [nc(est.w, truth.w)], "nc_v": [nc(est.v, truth.v)],
        "factorizations": est.history[-1]["factorizations"],
        "pcg_iterations": est.history[-1]["pcg_iterations"],
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "w": est.w.tolist(), "v": est.v.tolist(),
    }


def _child(args) -> None:
    kind, grid, modes, iters = args[0], int(args[1]), int(args[2]), int(args[3])
    if kind == "sparse":
        out = sparse_run(grid, modes, iters, overrides=args[4:])
    else:
        out = dense_iteration(_problem(grid, modes))
        out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print("RESULT " + json.dumps(out))


def _run(kind, grid, modes, iters, *overrides: str) -> dict:
    p = subprocess.run([sys.executable, __file__, "--child", kind, str(grid), str(modes),
                        str(iters), *overrides], capture_output=True, text=True, check=True)
    line = [x for x in p.stdout.splitlines() if x.startswith("RESULT ")][-1]
    return json.loads(line[7:])


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="fewer iterations")
    ap.add_argument("--json", default=None)
    ap.add_argument("--child", nargs="+", default=None, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child:
        _child(a.child)
        return
    res = {}
    res["dense_8"] = _run("dense", 8, 20, 1)
    print(f"dense baseline 8^3, 20 modes: {res['dense_8']['total_s']:.2f} s/iteration "
          f"(u {res['dense_8']['u_s']:.2f}, z {res['dense_8']['z_s']:.2f}), "
          f"{res['dense_8']['peak_rss_mb']:.0f} MiB", flush=True)
    res["sparse_8_20"] = _run("sparse", 8, 20, 30 if a.quick else 100)
    r = res["sparse_8_20"]
    print(f"sparse 8^3, 20 modes: mean {r['mean_iteration_s']:.3f} s/iteration (first "
          f"{r['first_iteration_s']:.2f}, median {r['median_iteration_s']:.3f}); "
          f"{r['iterations']} iterations, converged={r['converged']}; "
          f"{res['dense_8']['total_s'] / r['mean_iteration_s']:.1f}x faster than dense; "
          f"{r['peak_rss_mb']:.0f} MiB", flush=True)
    print("  NC v by iteration (every 5th):", [round(x, 3) for x in r["nc_v"][::5]], flush=True)
    exact = res["sparse_8_20_exact"] = _run("sparse", 8, 20, r["iterations"], "u_solver=direct")
    dw = np.linalg.norm(np.subtract(r["w"], exact["w"])) / np.linalg.norm(exact["w"])
    dv = np.linalg.norm(np.subtract(r["v"], exact["v"])) / np.linalg.norm(exact["v"])
    print(f"  same run with exact u-solves (one Cholesky per mode and iteration): mean "
          f"{exact['mean_iteration_s']:.3f} s/iteration; final w differs by {dw:.1e}, v by "
          f"{dv:.1e} (relative); NC w {r['nc_w'][-1]:.6f} vs {exact['nc_w'][-1]:.6f}",
          flush=True)
    res["sparse_8_10"] = _run("sparse", 8, 10, 30 if a.quick else 100)
    r = res["sparse_8_10"]
    print(f"sparse 8^3, 10 modes: mean {r['mean_iteration_s']:.3f} s/iteration, "
          f"{r['iterations']} iterations, converged={r['converged']}, final NC w "
          f"{r['nc_w'][-1]:.3f} v {r['nc_v'][-1]:.3f}", flush=True)
    res["sparse_8_20_rss"] = res["sparse_8_20"]
    for g in (6, 12, 16):
        res[f"sparse_{g}_20"] = r = _run("sparse", g, 20, 3 if a.quick else 25)
        print(f"sparse {g}^3 ({r['voxels']} voxels, {r['n_free']} DOF), 20 modes, "
              f"{r['iterations']} iterations: mean {r['mean_iteration_s']:.2f} s/iteration "
              f"(median {r['median_iteration_s']:.2f}, first {r['first_iteration_s']:.2f}), "
              f"peak RSS {r['peak_rss_mb']:.0f} MiB", flush=True)
    print("peak RSS vs voxels (20 modes):", ", ".join(
        f"{g}^3 ({res[f'sparse_{g}_20']['voxels']} voxels) "
        f"{res[f'sparse_{g}_20']['peak_rss_mb']:.0f} MiB" for g in (6, 8, 12, 16)), flush=True)
    n8, n16 = res["dense_8"]["n_free"], res["sparse_16_20"]["n_free"]
    res["dense_16_extrapolated_s"] = res["dense_8"]["u_s"] * (n16 / n8) ** 3
    print(f"dense 16^3 u-update extrapolated (n^3): {res['dense_16_extrapolated_s']:.0f} s"
          "/iteration")
    if a.json:
        with open(a.json, "w") as f:
            json.dump(res, f, indent=1)


if __name__ == "__main__":
    main()
