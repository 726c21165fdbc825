"""The paper's findings, checked on a `paper` suite run.

    .venv/bin/python benchmarks/paper_findings.py [runs/paper/results.parquet] [--solver vvt]

Prints, from the results table and the evaluated fields it points to:

1. NC of w and v against the number of observed modes (8 ... 20), per defect cube and
   observation source (paper Fig. 5: NC rises with the number of modes);
2. top vs bottom defect: NC averaged over the mode sweep (the small bottom defect is harder);
3. damping: how many distinct modes the damped cubes' two plucks yield, against the undamped
   cubes' videos (paper: 7-15 modes from two plucks), and the NC reached;
4. geometry mismatch: NC and the localization error -- the distance, in voxels, between the
   centroid of the estimate's stiffest voxels and the true defect's centroid -- for inference
   widths x1.0 ... x1.4 (paper: a 30 % error still localizes the defect);
5. intrinsic resolution sigma* of w at 10 modes (paper: 1.4 voxels);
6. the other tracks (bunny, Poisson and element-order mismatch, regularization, drums) as
   NC tables;
7. the field path: NC w of the field tracks (the video re-encoded as a camera writes it, the
   camera from noisy clicks, the object as an STL) against the same samples through the
   modes track at 10 extracted modes (lossless video, true camera), paired per scene;
8. with ``--before OLD.csv`` (an earlier board's results table): per solver, how many rows
   changed status (invalid -> scored, scored -> invalid) and how the NC w of rows valid in both
   moved.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pandas as pd


def localization_error(fields_path: Path) -> float:
    """Voxel distance between the centroids of the true defect (w_true above its mean) and of
    as many of the estimate's stiffest voxels."""
    f = np.load(fields_path)
    w, t = f["w"], f["w_true"]
    ok = np.isfinite(w) & np.isfinite(t)
    defect = ok & (t > np.nanmean(t[ok]))
    n = int(defect.sum())
    if n == 0:
        return float("nan")
    order = np.argsort(np.where(ok, w, -np.inf), axis=None)[::-1][:n]
    est = np.array(np.unravel_index(order, w.shape)).T.mean(axis=0)
    true = np.argwhere(defect).mean(axis=0)
    return float(np.linalg.norm(est - true))


def _fmt(df: pd.DataFrame) -> str:
    return df.to_string(float_format=lambda x: f"{x:.3f}")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("results", nargs="?", default="runs/paper/results.parquet")
    ap.add_argument("--solver", default="vvt", help="solver for the findings (default vvt)")
    ap.add_argument("--before", help="an earlier board's results table (.csv/.parquet) to "
                    "compare every row with")
    a = ap.parse_args(argv)
    path = Path(a.results)
    df = pd.read_parquet(path)
    root = path.parent
    ok = df[df.status == "ok"]
    print(f"{path}: {len(df)} runs, {int((df.status != 'ok').sum())} not ok (failed or invalid); "
          f"vvtbench {df.vvtbench_version.iloc[0]}, dataset {df.dataset_revision.iloc[0]}")

    modes = ok[ok.track == "modes"]
    print("\n1. NC against the number of observed modes (rows: solver, scene, observation)")
    for col in ("nc_w", "nc_v"):
        tab = modes.pivot_table(index=["solver", "scene", "observation"], columns="n_modes",
                                values=col)
        print(f"\n{col}:\n{_fmt(tab)}")
    mine = modes[modes.solver == a.solver]
    for (scene, obs), g in mine.groupby(["scene", "observation"]):
        g = g.sort_values("n_modes")
        r = np.corrcoef(g.n_modes, g.nc_w)[0, 1] if len(g) > 2 else float("nan")
        print(f"  {a.solver} {scene} {obs}: NC w {g.nc_w.iloc[0]:.3f} at {g.n_modes.iloc[0]} "
              f"-> {g.nc_w.iloc[-1]:.3f} at {g.n_modes.iloc[-1]} modes "
              f"(correlation with the mode count {r:+.2f}); observed modes "
              f"{g.n_modes_observed.tolist()}")

    print("\n2. top vs bottom defect: NC averaged over the mode sweep")
    print(_fmt(modes.pivot_table(index=["solver", "observation"], columns="scene",
                                 values=["nc_w", "nc_v"])))

    damp = ok[ok.track == "damping"]
    print("\n3. damping: distinct modes found in two plucks merged (asked for n_modes)")
    if len(damp):
        tab = damp.pivot_table(index=["scene", "n_modes"], columns="solver",
                               values="nc_w")
        seen = damp.groupby(["scene", "n_modes"]).n_modes_observed.max()
        print(_fmt(tab.assign(modes_observed=seen)))
        und = modes[(modes.observation == "extracted")].groupby("scene").n_modes_observed.max()
        print(f"  undamped videos (6 s), modes kept at the largest request: {und.to_dict()}")

    geo = ok[(ok.track == "geometry")].copy()
    print("\n4. geometry mismatch: NC w and localization error (voxels) per width scale")
    if len(geo):
        geo["scale"] = [json.loads(o).get("geometry_scale") for o in geo.variation_options]
        geo["loc_err_vox"] = [localization_error(root / p) for p in geo.estimate_path]
        print(_fmt(geo.pivot_table(index="scale", columns="solver",
                                   values=["nc_w", "loc_err_vox"])))

    print("\n5. intrinsic resolution of w at 10 modes (sigma* in voxels, NC there)")
    ten = ok[(ok.track == "modes") & (ok.n_modes == 10)]
    print(_fmt(ten.pivot_table(index=["solver", "scene", "observation"],
                               values=["sigma_star_w", "nc_at_sigma_star_w", "nc_w"])))

    print("\n6. other tracks (NC w / NC v)")
    for track in ("bunny", "poisson", "element_order", "regularization", "drums"):
        t = ok[ok.track == track]
        if len(t):
            tab = t.pivot_table(index=["scene", "variation", "observation"], columns="solver",
                                values=["nc_w", "nc_v"])
            print(f"\n{track}:\n{_fmt(tab)}")

    field_findings(df)
    if a.before:
        before = Path(a.before)
        old = pd.read_csv(before) if before.suffix == ".csv" else pd.read_parquet(before)
        changes(old, df, str(before))


def _cell(row) -> str:
    return f"{row.nc_w:.3f}" if row.status == "ok" else row.status


def field_findings(df: pd.DataFrame) -> None:
    """Section 7: field tracks against the modes track's lossless rows at 10 modes."""
    tracks = [t for t in dict.fromkeys(df.track) if str(t).startswith("field")]
    if not tracks:
        return
    print("\n7. the field path: NC w through each field track against the modes track at 10 "
          "extracted modes (lossless video, true camera); 'invalid' rows are never scored")
    ref = df[(df.track == "modes") & (df.observation == "extracted") & (df.n_modes == 10)]
    ref = ref.set_index(["solver", "scene"])
    for track in tracks:
        rows = []
        for r in df[df.track == track].itertuples(index=False):
            base = ref.loc[(r.solver, r.scene)] if (r.solver, r.scene) in ref.index else None
            diff = (f"{r.nc_w - base.nc_w:+.3f}" if base is not None and r.status == "ok"
                    and base.status == "ok" else "--")
            rows.append({"solver": r.solver, "scene": r.scene,
                         "lossless": _cell(base) if base is not None else "--",
                         track: _cell(r), "difference": diff,
                         "modes observed": r.n_modes_observed})
        print(f"\n{track}:\n{pd.DataFrame(rows).to_string(index=False)}")


def changes(old: pd.DataFrame, new: pd.DataFrame, name: str) -> None:
    """Section 8: every row present in both tables, per solver."""
    keys = ["track", "solver", "scene", "variation", "observation", "seed"]
    both = old.merge(new, on=keys, suffixes=("_old", "_new"))
    print(f"\n8. against {name}: {len(both)} rows in both tables "
          f"({len(new) - len(both)} new, {len(old) - len(both)} gone)")
    for solver, g in both.groupby("solver"):
        ok_old, ok_new = g.status_old == "ok", g.status_new == "ok"
        same = ok_old & ok_new
        d = (g.nc_w_new - g.nc_w_old)[same]
        moved = int((d.abs() > 5e-4).sum())
        line = (f"  {solver}: {int((~ok_old & ok_new).sum())} invalid -> scored, "
                f"{int((ok_old & ~ok_new).sum())} scored -> not scored, {int(same.sum())} "
                f"scored in both ({int(same.sum()) - moved} within 0.0005")
        if moved:
            line += (f"; {moved} moved, mean {d[d.abs() > 5e-4].mean():+.3f}, "
                     f"range [{d.min():+.3f}, {d.max():+.3f}]")
        print(line + ")")
        for r in g[~ok_old & ok_new].itertuples(index=False):
            print(f"    now scored: {r.track} {r.scene} {r.variation} {r.observation}: "
                  f"NC w {r.nc_w_new:.3f}")


if __name__ == "__main__":
    main()
