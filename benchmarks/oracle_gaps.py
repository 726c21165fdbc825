"""Why the oracle is below a ranked solver, row by row.

    .venv/bin/python benchmarks/oracle_gaps.py RUN/results.parquet

For every instance (track, scene, variation, observation) where the reference oracle's NC w is
below the best ranked solver's, both estimates are scored by the oracle's own selection score
(:func:`solvers.oracle.fit_score`: (1 - mean MAC) + mean relative frequency error of the
forward model against the true full-field 3-D modes, lower is better) and each row gets a
verdict:

* ``optimizer`` -- the ranked estimate reproduces the oracle's own data (the complete 3-D modes)
  better than the oracle's pick: the oracle's candidates stop short of the best fit, a stronger
  oracle candidate would close the gap;
* ``identifiability`` -- the oracle's field reproduces the complete data at least as well, yet
  correlates less with the voxelized truth: at this voxel resolution the complete modes do not
  single out the truth (the prior decides), so no bound on NC exists there;
* ``tie`` -- the NC margin is below 0.01.

Reads the run's cache (the solve folders' ``estimate.npz``, the observe folders); writes nothing.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path

import numpy as np

from solvers.oracle import fit_score, full_field_problem
from vvtbench.bench import read_results
from vvtbench.bench.stages import load_observation

TIE = 0.01


def solve_and_observe_keys(cache: Path, estimate_path: str) -> tuple[str, str]:
    """The cache keys of the solve and observe tasks behind a results row's estimate."""
    evaluate = json.loads((cache.parent / Path(estimate_path).parent / "task.json").read_text())
    solve = next(d for d in evaluate["deps"] if d.startswith("solve/"))
    task = json.loads((cache / solve / "task.json").read_text())
    return solve, next(d for d in task["deps"] if d.startswith("observe/"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("results")
    args = ap.parse_args()
    df = read_results(args.results)
    cache = Path(args.results).parent / "cache"
    ok = df[(df.status == "ok") & df.nc_w.notna()]
    ref = ok[ok.reference.astype(bool)]
    ranked = ok[~ok.reference.astype(bool)]
    keys = ["track", "scene", "variation", "observation"]
    verdicts: dict[str, int] = {}
    print("| track | instance | variation | modes | oracle NC w | best ranked | NC w | "
          "oracle fit score | ranked fit score | verdict |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    n_rows = 0
    for key, r in ref.groupby(keys):
        o = r.iloc[0]
        others = ranked.set_index(keys).sort_index()
        if key not in others.index:
            continue
        cand = others.loc[[key]].reset_index()
        best = cand.loc[cand.nc_w.astype(float).idxmax()]
        n_rows += 1
        if not best.nc_w > o.nc_w:
            continue
        problem, truth = load_observation(cache, solve_and_observe_keys(cache, o.estimate_path)[1],
                                          truth=True)
        full = full_field_problem(
            replace(problem, eigenvalues=np.asarray(truth.eigenvalues, dtype=float)),
            np.asarray(truth.modes_3d))
        scores = []
        for row in (o, best):
            f = np.load(cache / solve_and_observe_keys(cache, row.estimate_path)[0]
                        / "estimate.npz")
            scores.append(fit_score(full, f["w_params"], f["v_params"]))
        margin = best.nc_w - o.nc_w
        verdict = ("tie" if margin < TIE else "optimizer" if scores[1] < scores[0]
                   else "identifiability")
        verdicts[verdict] = verdicts.get(verdict, 0) + 1
        print(f"| {o.track} | {o.scene} | {o.variation or '-'} | {o.observation} "
              f"{o.n_modes} | {o.nc_w:.3f} | {best.solver} | {best.nc_w:.3f} | "
              f"{scores[0]:.4f} | {scores[1]:.4f} | {verdict} |", flush=True)
    print(f"\noracle below the best ranked solver on {sum(verdicts.values())} of {n_rows} "
          f"instances: " + ", ".join(f"{v} {k}" for k, v in sorted(verdicts.items())))


if __name__ == "__main__":
    main()
