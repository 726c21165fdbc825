"""sensitivity 2.x against vvt in one run: NC of w and v and wall time per solve.

    PYTHONPATH=. python benchmarks/bench_sensitivity.py --set validation   # own defect cubes
    PYTHONPATH=. python benchmarks/bench_sensitivity.py --set paper        # the paper's two
    PYTHONPATH=. python benchmarks/bench_sensitivity.py --set family --n 10  # cube_defects val

Validation cubes are the paper's Jello cube (10^3 hex8, bottom fixed) with one box defect of
our own making (position, size, contrast varied; in no suite): the only cubes the
hyperparameters were chosen on. The paper's two defect cubes are measured at the end only.
Every problem: true image-space modes, ``visibility="normals"``, inferred on 8^3 voxels.
The ``family`` set is the ``val`` split of ``cube_defects`` (instances without a defect are
skipped: NC is undefined on a constant truth).

``--degrade SEED`` replaces the true modes by extraction-like observations of them (what a
video gives, without rendering one; :func:`degrade`): clusters closer than the 6 s record's
resolution seen as one mixed mode, 20 % of the rest missed, shape noise of 35 % of the mode's
norm (MAC about 0.89), two spurious white-noise modes in the band, frequencies within 0.2 %.
``--sens KEY=VALUE`` overrides a sensitivity option (e.g. ``--sens min_mac=0``). The machine's
load average is printed with each row (solves share the cores), and the process CPU time of
each solve next to its wall time.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from vvtbench.observe import observe
from vvtbench.scene.families import draw
from vvtbench.scene.scene import load_scene
from vvtbench.scoring.metrics import interval_coverage, normalized_correlation

VALIDATION = {
    "v_mid_soft": dict(center=(0.02, 0.03, 0.025), size=(0.015, 0.015, 0.015), E=9.0e4,
                       rho=2000.0),
    "v_corner": dict(center=(0.035, 0.035, 0.04), size=(0.015, 0.015, 0.01), E=5.0e6,
                     rho=7620.0),
    "v_low_side": dict(center=(0.015, 0.025, 0.015), size=(0.02, 0.01, 0.015), E=5.0e5,
                       rho=3000.0),
    "v_slab_small": dict(center=(0.025, 0.015, 0.03), size=(0.01, 0.01, 0.01), E=2.0e6,
                         rho=5000.0),
}
PAPER = ("jello_cube_defect_top", "jello_cube_defect_bottom")


def validation_scene(name: str):
    """The paper's Jello cube with the defect ``VALIDATION[name]`` (a scene of our own)."""
    base = load_scene("jello_cube_defect_top")
    defect = base.material.defects[0].model_copy(update=VALIDATION[name])
    return base.model_copy(update={
        "name": name, "material": base.material.model_copy(update={"defects": [defect]})})


def degrade(problem, rng: np.random.Generator, resolution_hz: float = 1 / 6.0,
            miss: float = 0.2, noise: float = 0.35, n_spurious: int = 2,
            freq_rel: float = 2e-3):
    """Extraction-like observations of ``problem``'s true modes (module docstring)."""
    from dataclasses import replace

    f = problem.frequencies_hz
    g = problem.gamma
    order = np.argsort(f)
    cuts = np.flatnonzero(np.diff(f[order]) >= resolution_hz) + 1
    freqs, shapes = [], []
    for members in np.split(order, cuts):  # chains closer than the resolution: one peak
        if rng.random() < miss:
            continue
        c = rng.standard_normal(len(members))
        shapes.append(c @ g[members])
        freqs.append(float(np.mean(f[members])))
    for _ in range(n_spurious):
        shapes.append(rng.standard_normal(g.shape[1]))
        freqs.append(float(rng.uniform(min(freqs), max(freqs))))
    G = np.array(shapes)
    G /= np.linalg.norm(G, axis=1, keepdims=True)
    G += noise * rng.standard_normal(G.shape) / np.sqrt(G.shape[1])
    G /= np.linalg.norm(G, axis=1, keepdims=True)
    F = np.array(freqs) * (1 + freq_rel * rng.standard_normal(len(freqs)))
    order = np.argsort(F)
    return replace(problem, gamma=G[order], eigenvalues=(2 * np.pi * F[order]) ** 2,
                   meta=dict(problem.meta, degraded=True))


def main() -> None:
    from solvers.sensitivity import SensitivitySolver
    from solvers.vvt import VVTSolver

    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--set", choices=("validation", "paper", "family"), default="validation")
    ap.add_argument("--n", type=int, default=10, help="family instances (val 0..n-1)")
    ap.add_argument("--modes", default="20,8,14,10,16,12,18")
    ap.add_argument("--scenes", nargs="*", help="a subset of the set's scenes")
    ap.add_argument("--no-vvt", action="store_true")
    ap.add_argument("--degrade", type=int, default=None, metavar="SEED",
                    help="extraction-like observations of the true modes (seeded)")
    ap.add_argument("--sens", action="append", default=[], metavar="KEY=VALUE",
                    help="sensitivity option override (repeatable)")
    a = ap.parse_args()
    from solvers.sensitivity import SensitivityConfig
    from vvtbench.solving.plugins import parse_overrides
    sens_cfg = parse_overrides(a.sens, SensitivityConfig)
    if a.scenes:
        names = a.scenes
    elif a.set == "family":
        names = [f"cube_defects-val-{i:05d}" for i in range(a.n)]
    else:
        names = list(VALIDATION) if a.set == "validation" else list(PAPER)
    ks = [int(x) for x in a.modes.split(",")]
    rows = []
    for name in names:
        src = validation_scene(name) if name in VALIDATION else name
        if name.startswith("cube_defects-val-"):
            src = draw("cube_defects", "val", int(name.rsplit("-", 1)[1]))
            if not src.material.defects:
                continue
        n_obs = max(ks) + (10 if a.degrade is not None else 0)
        pb_all, tr_all = observe(src, n_modes=n_obs, inference_shape=(8, 8, 8),
                                 visibility="normals")
        if a.degrade is not None:
            pb_all = degrade(pb_all, np.random.default_rng([a.degrade, len(rows)]))
        for k in ks:
            k = min(k, pb_all.n_modes)
            pb, tr = pb_all.select_modes(k), tr_all
            row = {"scene": name, "k": k}
            solvers = [("sens", SensitivitySolver(sens_cfg))]
            solvers += [] if a.no_vvt else [("vvt", VVTSolver())]
            for label, solver in solvers:
                t0, c0 = time.perf_counter(), time.process_time()
                est = solver.solve(pb)
                row[f"{label}_s"] = time.perf_counter() - t0
                row[f"{label}_cpu"] = time.process_time() - c0
                row[f"{label}_w"] = normalized_correlation(est.w, tr.w)
                row[f"{label}_v"] = normalized_correlation(est.v, tr.v)
                if "w_std" in est.extra:
                    row["cov95_w"] = interval_coverage(est.w, est.extra["w_std"], tr.w)
                    row["cov68_w"] = interval_coverage(est.w, est.extra["w_std"], tr.w, z=1.0)
                    row["cov95_v"] = interval_coverage(est.v, est.extra["v_std"], tr.v)
            row["load"] = os.getloadavg()[0]
            rows.append(row)
            print("  ".join(f"{x}={y:.3f}" if isinstance(y, float) else f"{x}={y}"
                            for x, y in row.items()), flush=True)
    for label in ("sens", "vvt"):
        if f"{label}_w" in rows[0]:
            for name in names:
                sel = [r for r in rows if r["scene"] == name]
                print(f"{label} {name}: mean NC w {np.mean([r[f'{label}_w'] for r in sel]):.3f} "
                      f"v {np.mean([r[f'{label}_v'] for r in sel]):.3f} "
                      f"time {np.mean([r[f'{label}_s'] for r in sel]):.1f} s "
                      f"(cpu {np.mean([r[f'{label}_cpu'] for r in sel]):.1f} s)")
            print(f"{label} all: mean NC w {np.mean([r[f'{label}_w'] for r in rows]):.3f} "
                  f"v {np.mean([r[f'{label}_v'] for r in rows]):.3f}")
    if "cov95_w" in rows[0]:
        print(f"sens coverage (mean over rows): 95% w {np.mean([r['cov95_w'] for r in rows]):.3f} "
              f"v {np.mean([r['cov95_v'] for r in rows]):.3f}; 68% w "
              f"{np.mean([r['cov68_w'] for r in rows]):.3f}")


if __name__ == "__main__":
    main()
