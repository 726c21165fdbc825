"""sensitivity 2.x against vvt in one run: NC of w and v and wall time per solve.

    PYTHONPATH=. python benchmarks/bench_sensitivity.py --set validation   # own defect cubes
    PYTHONPATH=. python benchmarks/bench_sensitivity.py --set paper        # the paper's two
    PYTHONPATH=. python benchmarks/bench_sensitivity.py --set family --n 10  # cube_defects val

Validation cubes are the paper's Jello cube (10^3 hex8, bottom fixed) with one box defect of
our own making (position, size, contrast varied; in no suite): the only cubes the
hyperparameters were chosen on. The paper's two defect cubes are measured at the end only.
Every problem: true image-space modes, ``visibility="normals"``, inferred on 8^3 voxels.
The ``family`` set is the ``val`` split of ``cube_defects`` (instances without a defect are
skipped: NC is undefined on a constant truth). The machine's load average is printed with each
row (solves share the cores), and the process CPU time of each solve next to its wall time.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from vvtbench.families import draw
from vvtbench.metrics import interval_coverage, normalized_correlation
from vvtbench.observe import observe
from vvtbench.scene import load_scene

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


def main() -> None:
    from solvers.sensitivity import SensitivitySolver
    from solvers.vvt import VVTSolver

    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--set", choices=("validation", "paper", "family"), default="validation")
    ap.add_argument("--n", type=int, default=10, help="family instances (val 0..n-1)")
    ap.add_argument("--modes", default="20,8,14,10,16,12,18")
    ap.add_argument("--scenes", nargs="*", help="a subset of the set's scenes")
    ap.add_argument("--no-vvt", action="store_true")
    a = ap.parse_args()
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
        pb_all, tr_all = observe(src, n_modes=max(ks), inference_shape=(8, 8, 8),
                                 visibility="normals")
        for k in ks:
            pb, tr = pb_all.select_modes(k), tr_all.select_modes(k)
            row = {"scene": name, "k": k}
            solvers = [("sens", SensitivitySolver())] + ([] if a.no_vvt else [("vvt", VVTSolver())])
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
