"""Does a new run reproduce a committed results table, row by row?

    python benchmarks/reproduce_leaderboard.py leaderboard/results.csv runs/paper [--tol 1e-6]

For every row of the new run (``RUN/results.parquet``) with a partner in the old table (same
track, solver, scene, variation, seed, observation and number of modes), the estimate is
scored twice:

* against the truth of the *old* definition (before 2026-11-23: each simulation element
  assigned to the voxel holding its centroid, volume-weighted mean, empty voxels from the
  nearest element) -- recomputed here from the sample and the problem in the run's cache; this
  NC must equal the old table's within ``--tol`` if the refactor changed nothing but the
  truth's definition;
* against the truth of the new definition (volume-weighted overlap): the run's own NC. The
  difference is the effect of the definition alone, printed per track.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

KEY = ["track", "solver", "scene", "variation", "seed", "observation", "n_modes"]


def centroid_truth(sample, vmap, scale: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The old voxel truth: per parameter, the volume-weighted mean over the simulation
    elements whose (scaled) centroid lies in the voxel; empty voxels take the nearest one."""
    from scipy.spatial import cKDTree

    from vvtbench.fem.elements import element_volumes
    from vvtbench.fem.mesh import Mesh

    mesh = Mesh(sample["mesh/points"], sample["mesh/cells"], sample.info["mesh"]["element"],
                {}, sample["mesh/surface"])
    cent = mesh.centroids * scale
    param_of_voxel = np.full(vmap.grid.n_voxels, -1)
    param_of_voxel[vmap.active] = np.arange(vmap.n_params)
    param = param_of_voxel[vmap.grid.voxel_of(cent)]
    vol = element_volumes(mesh.element_type, mesh.cell_coords)
    keep = param >= 0
    out = []
    for values in (sample["material/stiffness"], sample["material/density"]):
        num = np.bincount(param[keep], vol[keep] * values[keep], minlength=vmap.n_params)
        den = np.bincount(param[keep], vol[keep], minlength=vmap.n_params)
        res = np.full(vmap.n_params, np.nan)
        has = den > 0
        res[has] = num[has] / den[has]
        if not has.all():
            _, nearest = cKDTree(cent).query(vmap.grid.centers()[vmap.active[~has]])
            res[~has] = values[nearest]
        out.append(res)
    return out[0], out[1]


def main(argv: list[str] | None = None) -> int:
    import pandas as pd

    from vvtbench.bench import read_results
    from vvtbench.samples.reader import open_sample
    from vvtbench.scoring.metrics import normalized_correlation as nc
    from vvtbench.solving.problem import InverseProblem

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("old", help="the committed results table (CSV or Parquet)")
    p.add_argument("run", help="the new run folder")
    p.add_argument("--tol", type=float, default=1e-6)
    p.add_argument("--suite", default=None,
                   help="score every finished solve of a run still in progress: the suite's "
                   "task graph maps solve tasks to rows (run with the run's vvtbench)")
    args = p.parse_args(argv)
    old = read_results(args.old)
    cache = Path(args.run) / "cache"
    rows = []
    samples: dict[str, object] = {}

    def score(obs_key: str, w: np.ndarray, v: np.ndarray, r: dict) -> None:
        obs_dir = cache / obs_key
        gen_key = json.loads((obs_dir / "task.json").read_text())["deps"][0]
        if gen_key not in samples:
            # the truth only: a run with --prune-videos has no videos to check
            samples[gen_key] = open_sample(cache / gen_key / "sample", verify=False)
        problem = InverseProblem.load(obs_dir)
        scale = np.asarray(problem.meta["geometry_scale"], dtype=float)
        tw, tv = centroid_truth(samples[gen_key], problem.voxel_map, scale)
        with np.load(obs_dir / "truth.npz") as t:
            nw, nv = nc(w, t["w"]), nc(v, t["v"])
        rows.append({**{k: r[k] for k in KEY},
                     "d_old_w": abs(nc(w, tw) - r["nc_w_old"]),
                     "d_old_v": abs(nc(v, tv) - r["nc_v_old"]),
                     "defn_w": nw - nc(w, tw), "defn_v": nv - nc(v, tv)})

    if args.suite:
        from vvtbench.bench import build_graph, load_suite

        suite = load_suite(args.suite)
        _, runs = build_graph(suite, suite.solvers)
        oldk = old.set_index(KEY)
        for run in runs:
            key = (run.track, run.solver_name, run.scene, run.variation, run.seed,
                   run.observation, run.n_modes)
            if run.solve_key is None or not (cache / run.solve_key / "task.json").is_file() \
                    or key not in oldk.index:
                continue
            o = oldk.loc[key]
            with np.load(cache / run.solve_key / "estimate.npz") as e:
                w, v = e["w_params"], e["v_params"]
            if not (np.all(np.isfinite(w)) and np.all(w > 0) and np.all(v > 0)):
                continue
            score(run.observe_key, w, v, dict(zip(KEY, key, strict=True)) | {
                "nc_w_old": float(o["nc_w"]), "nc_v_old": float(o["nc_v"])})
        new = old.iloc[:0]
    else:
        new = read_results(Path(args.run) / "results.parquet")
        new = new[new.status == "ok"]
        for r in new.merge(old, on=KEY, suffixes=("", "_old")).to_dict("records"):
            ev_dir = Path(args.run) / Path(r["estimate_path"]).parent
            observe_key = json.loads((ev_dir / "task.json").read_text())["deps"][1]
            f = np.load(ev_dir / "fields.npz")
            active = InverseProblem.load(cache / observe_key).voxel_map.active
            score(observe_key, f["w"].ravel()[active], f["v"].ravel()[active], r)
    df = pd.DataFrame(rows)
    if df.empty:
        print("no rows in common")
        return 1
    print(f"{len(df)} rows matched ({len(new)} ok rows in the new run, {len(old)} in the old "
          f"table)")
    print(f"{'track':16s} {'rows':>5s} {'max|dNC w|':>11s} {'max|dNC v|':>11s} "
          f"{'> tol':>6s}   truth definition: NC w new - old (min, mean, max)")
    for track, g in df.groupby("track", sort=False):
        bad = int(((g.d_old_w > args.tol) | (g.d_old_v > args.tol)).sum())
        print(f"{track:16s} {len(g):5d} {g.d_old_w.max():11.2e} {g.d_old_v.max():11.2e} "
              f"{bad:6d}   {g.defn_w.min():+.3f} {g.defn_w.mean():+.3f} {g.defn_w.max():+.3f}")
    bad = df[(df.d_old_w > args.tol) | (df.d_old_v > args.tol)]
    for r in bad.itertuples():
        print(f"  differs: {r.track} {r.solver} {r.scene} {r.variation} {r.observation}: "
              f"|dNC w| {r.d_old_w:.2e}, |dNC v| {r.d_old_v:.2e}")
    return 0 if bad.empty else 1


if __name__ == "__main__":
    sys.exit(main())
