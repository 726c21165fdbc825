"""Ceilings per instance, the homogenised truth, and every solver scored against both truths.

    # modes-only samples of the standard suite's test instances (about 1 s each)
    vvtbench generate cube_defects --split test --n 50 --no-video -o runs/samples/cube
    # compute (resumable: each stage of each instance is cached in its JSON, keyed by the
    # inputs' sha256; run it again to continue), then summarise
    nice -n 10 python benchmarks/ceiling.py run runs/samples/cube --only 0-9
    python benchmarks/ceiling.py report

For each instance of the ``standard`` suite's cube_true / drums_true tracks (20 true modes,
the track's inference grid, one camera with depth visibility) the stages are:

``estimates``  every solver of the board, with the board row's config, on the problem; NC of
               each against the arithmetic truth (``Truth.w``; compared with the board's
               ``nc_w``) and the mode misfit D of each on both data (``view``: what the solver
               got; ``full``: the true modes at every free DOF).
``eps``        the discretisation floor: D of the exact material on the same scene without its
               defects (the inference mesh's own misfit on a body it can represent).
``homog``      the homogenised truth: the field closest (mean squared log distance) to the
               voxel mean with the lowest D_full whose D_full <= the floor (augmented
               Lagrangian); where no such field is found, the lowest D_full reached.
               eps_view / eps_full = its misfits: a field explains the data when it fits it at
               least as well as the homogenised truth does.
``ceil_*``     the ceiling: maximise NC(w or v, arithmetic truth) subject to D <= eps
               (augmented Lagrangian; starts: the homogenised truth, and the best solver
               estimate by that NC), then the max with every feasible field seen (estimates,
               voxel means, every point evaluated on the way).

Results: ``benchmarks/ceiling/<family>/<instance>.json`` (+ ``.npz``: the fields, float32).
``report`` reads whichever instances are committed and writes ``summary.txt`` and
``instances.csv`` beside them, the figures, and ``leaderboard/standard/ceilings.csv`` (one row
per instance and ceiling kind: the leaderboard's headroom reads it beside the board's results);
it checks every recomputed estimate and every board row against its instance's ceilings.
Definitions: docs/metrics.md ("Ceiling", "Truth on the inference grid"). The ceiling is the
best found by this search: a lower bound on the supremum over feasible fields.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "benchmarks" / "ceiling"
BOARD = ROOT / "leaderboard" / "standard" / "results.csv"
SOLVERS = ("homogeneous", "learned", "oracle", "sensitivity", "vvt")
TRACKS = {"cube_defects": ("cube_true", [8, 8, 8]), "drum_defects": ("drums_true", [20, 20])}
N_MODES = 20
#: budgets of the searches (augmented Lagrangian: outer x inner L-BFGS-B iterations)
BUDGET = {"homog": (8, 25), "ceil": (5, 25)}
#: version of each stage's method: a cached stage computed by another version is recomputed
METHOD = {"estimates": "1", "eps": "1", "homog": "1", "ceil": "2"}
STAGES = ("estimates", "eps", "homog", "ceil_w_view", "ceil_w_full", "ceil_v_view",
          "ceil_v_full")
DEFAULT_STAGES = ("estimates", "eps", "homog", "ceil_w_view", "ceil_w_full", "ceil_v_view")
#: a drum is seen whole (every free DOF in two image directions): its view is every DOF, so
#: the full-data searches would repeat the view's
SKIP = {"drum_defects": ("ceil_w_full", "ceil_v_full")}


# ------------------------------------------------------------------ inputs


def load(sample: Path):
    from vvtbench.observe import observe

    family = json.loads((sample / "family.json").read_text())["family"]
    track, shape = TRACKS[family]
    p, t = observe(str(sample), observation="true", n_modes=N_MODES, inference_shape=shape,
                   visibility="depth")
    return family, track, p, t


def inputs_sha256(p, t) -> str:
    """sha256 over everything the stages read: the data (both views), the model's size and the
    arithmetic truth."""
    import scipy.sparse as sp

    h = hashlib.sha256()
    P = sp.csr_matrix(p.P)
    for a in (p.gamma, p.eigenvalues, P.data, P.indices, P.indptr, t.modes_3d, t.eigenvalues,
              t.w, t.v, np.asarray([p.n_params, p.model.n_free])):
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def data_of(p, t):
    from vvtbench.scoring.ceiling import ModeData
    from vvtbench.scoring.homogenize import full_field_data

    return {"view": ModeData(p.gamma, p.eigenvalues, p.P, "view"), "full": full_field_data(t)}


def theta(w, v):
    return np.concatenate([np.log(np.asarray(w, float)), np.log(np.asarray(v, float))])


def defects_of(sample: Path) -> tuple[list, str]:
    """The instance's defects (shape, stiffness and density ratios to the base) and its class:
    ``no defect``, ``near-void`` (a defect below 1/100 of the base stiffness), ``stiff`` (every
    defect stiffer), ``soft`` (every defect softer) or ``mixed``."""
    from vvtbench.scene.scene import load_scene

    scene = load_scene(sample / "scene.toml")
    mat = scene.material
    drum = scene.geometry.kind == "drum"
    w0, v0 = (mat.tension, mat.areal_density) if drum else (mat.E, mat.rho)
    out = []
    for d in mat.defects:
        w = d.tension if drum else d.E
        v = d.areal_density if drum else d.rho
        out.append({"shape": d.shape, "w_ratio": None if w is None else w / w0,
                    "v_ratio": None if v is None else v / v0})
    r = [d["w_ratio"] for d in out if d["w_ratio"] is not None]
    if not r:
        kind = "no defect"
    elif min(r) < 0.01:
        kind = "near-void"
    elif min(r) > 1:
        kind = "stiff"
    elif max(r) < 1:
        kind = "soft"
    else:
        kind = "mixed"
    return out, kind


def board_configs(track: str, scene: str) -> dict:
    import pandas as pd

    if not BOARD.exists():
        return {}
    d = pd.read_csv(BOARD)
    rows = d[(d.track == track) & (d.scene == scene)]
    return {r.solver: {"config": json.loads(r.config), "version": r.solver_version,
                       "nc_w": r.nc_w, "nc_v": r.nc_v, "status": r.status}
            for r in rows.itertuples()}


# ------------------------------------------------------------------ stages


def stage_estimates(ctx) -> dict:
    from vvtbench.scoring.metrics import invalid_reason, normalized_correlation
    from vvtbench.solving.plugins import load_solver, run_solver

    p, t, fam = ctx["p"], ctx["t"], ctx["family"]
    board = board_configs(ctx["track"], ctx["instance"])
    out, arrays = {}, {}
    for name in SOLVERS:
        cls = load_solver(name)
        row = board.get(name, {})
        config = dict(row.get("config", {}))
        if row.get("version") != str(cls.version):
            # the board's row was made by another version: solve with today's defaults
            config = {"weights": fam} if name == "learned" else {}
        t0 = time.perf_counter()
        try:
            est, _ = run_solver(cls, config, p, t)
        except Exception as error:  # a failed solve is recorded, never fatal
            out[name] = {"status": "error", "error": f"{type(error).__name__}: {error}"}
            continue
        rec = {"version": str(cls.version), "config": config, "time_s": time.perf_counter() - t0,
               "board_version": row.get("version"), "board_nc_w": row.get("nc_w"),
               "board_status": row.get("status")}
        bad = invalid_reason(est.w, est.v, p.n_params)
        if bad:
            rec.update(status="invalid", error=bad)
        else:
            w32, v32 = est.w.astype(np.float32), est.v.astype(np.float32)
            arrays[f"est_{name}_w"], arrays[f"est_{name}_v"] = w32, v32
            rec.update(status="ok", nc_w=normalized_correlation(est.w, t.w),
                       nc_v=normalized_correlation(est.v, t.v))
            for k, mf in ctx["misfits"].items():
                rec[f"D_{k}"] = mf.value(theta(w32, v32))
        out[name] = rec
        print(f"  {name}: {rec.get('status')} nc_w {rec.get('nc_w', float('nan')):.4f} "
              f"(board {row.get('nc_w')}) {rec['time_s']:.0f} s", flush=True)
    means = {}
    for name, (w, v) in ctx["means"].items():
        means[name] = {"nc_w": normalized_correlation(w, t.w),
                       "nc_v": normalized_correlation(v, t.v),
                       **{f"D_{k}": mf.value(theta(w, v)) for k, mf in ctx["misfits"].items()}}
    return {"solvers": out, "means": means}, arrays


def stage_eps(ctx) -> dict:
    """D of the exact material on the scene without defects (view and full data)."""
    from vvtbench.observe import observe
    from vvtbench.scene.scene import load_scene
    from vvtbench.scoring.ceiling import Misfit

    scene = load_scene(ctx["sample"] / "scene.toml")
    plain = scene.model_copy(update={"material": scene.material.model_copy(
        update={"defects": []})})
    track, shape = TRACKS[ctx["family"]]
    p0, t0 = observe(plain, observation="true", n_modes=N_MODES, inference_shape=shape,
                     visibility="depth")
    th = theta(np.full(p0.n_params, p0.w0), np.full(p0.n_params, p0.v0))
    return {k: Misfit(p0.model, d).value(th) for k, d in data_of(p0, t0).items()}, {}


def stage_homog(ctx) -> dict:
    from vvtbench.scoring.homogenize import homogenise
    from vvtbench.scoring.metrics import normalized_correlation

    p, t = ctx["p"], ctx["t"]
    outer, inner = BUDGET["homog"]
    t0 = time.perf_counter()
    h = homogenise(ctx["misfits"]["full"], ctx["means"], ctx["result"]["eps"]["full"],
                   outer=outer, inner=inner, bounds=_bounds(ctx),
                   scores=_nc_scores(t, p.n_params),
                   log=lambda r: print("   homog", _short(r), flush=True))
    out = {"anchor": h.anchor, "floor": ctx["result"]["eps"]["full"], "feasible": h.feasible,
           "D_full": h.misfit, "D_view": ctx["misfits"]["view"].value(theta(h.w, h.v)),
           "distance": h.distance, "nc_w": normalized_correlation(h.w, t.w),
           "nc_v": normalized_correlation(h.v, t.v), "history": h.history,
           "evaluations": h.evaluations, "time_s": time.perf_counter() - t0}
    # every field evaluated on the way is a candidate of the full-data ceilings
    rec = h.record
    out["seen_full"] = ({k: rec.best_score(k, out["D_full"]) for k in rec.scores}
                        if rec.misfit else {})
    return out, {"homog_w": h.w, "homog_v": h.v}


def _bounds(ctx):
    """Search bounds: 100x beyond the range of the voxel means and the estimates."""
    from vvtbench.scoring.ceiling import log_bounds

    fields = list(ctx["means"].values())
    fields += [(ctx["arrays"][k], ctx["arrays"][k[:-1] + "v"]) for k in ctx["arrays"]
               if k.startswith("est_") and k.endswith("_w")]
    return log_bounds(fields, ctx["p"].n_params)


def _toward(mf, th_from, th_to, eps, alphas=(1.0, 0.5, 0.25, 0.125, 0.0625)):
    """The largest step alpha from a feasible field toward another field that stays feasible
    (D <= eps); the smallest alpha tried when none does. Returns (alpha, theta, D)."""
    for a in alphas:
        th = th_from + a * (th_to - th_from)
        D = mf.value(th)
        if D <= eps:
            return a, th, D
    return a, th, D


def _short(h: dict) -> dict:
    return {k: (round(x, 6) if isinstance(x, float) else x) for k, x in h.items()}


def _nc_scores(t, m: int) -> dict:
    """NC of w and of v against the arithmetic truth, as functions of theta."""
    from vvtbench.scoring.metrics import normalized_correlation

    return {"nc_w": lambda th: normalized_correlation(np.exp(th[:m]), t.w),
            "nc_v": lambda th: normalized_correlation(np.exp(th[m:]), t.v)}


def _thin(d, nc, n=40):
    if len(d) <= n:
        idx = np.arange(len(d))
    else:
        idx = np.unique(np.r_[np.round(np.linspace(0, len(d) - 1, n)).astype(int)])
    return [[float(d[i]), float(nc[i])] for i in idx]


def stage_ceiling(ctx, which: str, data: str) -> dict:
    """Maximise NC(which, arithmetic truth) subject to D_data <= eps_data."""
    from vvtbench.scoring.ceiling import Record, constrained_minimum, front, nc_objective
    from vvtbench.scoring.metrics import normalized_correlation

    p, t = ctx["p"], ctx["t"]
    m = p.n_params
    ref = t.w if which == "w" else t.v
    mf = ctx["misfits"][data]
    homog = ctx["result"]["homog"]
    eps = homog[f"D_{data}"]
    hw, hv = ctx["arrays"]["homog_w"], ctx["arrays"]["homog_v"]
    est = ctx["result"]["estimates"]["solvers"]
    # fields seen elsewhere: every valid estimate, every voxel mean, the homogenised truth
    seen = {"homogenised": (homog[f"nc_{which}"], eps)}
    for name, r in est.items():
        if r.get("status") == "ok":
            seen[f"estimate:{name}"] = (r[f"nc_{which}"], r[f"D_{data}"])
    for name, r in ctx["result"]["estimates"]["means"].items():
        seen[f"mean:{name}"] = (r[f"nc_{which}"], r[f"D_{data}"])
    if data == "full" and homog.get("seen_full"):
        seen["homogenisation path"] = (homog["seen_full"].get(f"nc_{which}", np.nan), eps)
    for stage, r in ctx["result"].items():  # the other searches on the same data
        if stage.startswith("ceil_") and isinstance(r, dict) and r.get("data") == data \
                and r.get("seen_other"):
            seen[f"search {stage}"] = (r["seen_other"].get(f"nc_{which}", np.nan), eps)
    starts = {"homogenised": theta(hw, hv)}
    ranked = sorted((r[f"nc_{which}"], name) for name, r in est.items()
                    if r.get("status") == "ok" and name != "homogeneous")
    toward = None
    if ranked:  # second start: from the homogenised truth toward the best estimate
        name = ranked[-1][1]
        target = theta(ctx["arrays"][f"est_{name}_w"], ctx["arrays"][f"est_{name}_v"])
        alpha, th, D = _toward(mf, starts["homogenised"], target, eps)
        starts[f"toward:{name}"] = th
        toward = {"estimate": name, "alpha": alpha, "D": D}
    rec = Record(scores={k: f for k, f in _nc_scores(t, m).items() if k != f"nc_{which}"})
    outer, inner = BUDGET["ceil"]
    tags = {"1": eps, "1.5": 1.5 * eps, "2": 2 * eps, "4": 4 * eps}
    by_start = {}
    t0 = time.perf_counter()
    n0 = mf.n_eval
    for name, th0 in starts.items():
        k0 = len(rec.misfit)
        res = constrained_minimum(mf, nc_objective(ref, which, m), th0, eps, start=name,
                                  record=rec, eps_tags=tags, outer=outer, inner=inner,
                                  bounds=_bounds(ctx),
                                  log=lambda h: print(f"   {which}/{data}", _short(h),
                                                      flush=True))
        vals = np.asarray(rec.value[k0:])
        ds = np.asarray(rec.misfit[k0:])
        ok = ds <= eps
        by_start[name] = {"best_nc": float(-vals[ok].min()) if ok.any() else None,
                          "start_D": float(ds[0]), "start_nc": float(-vals[0]),
                          "history": res["history"], "evaluations": int(len(ds))}
    search = -rec.best["1"][0] if "1" in rec.best else float("nan")
    seen_ok = {k: nc for k, (nc, d) in seen.items() if d <= eps and np.isfinite(nc)}
    best_seen = max(seen_ok.values()) if seen_ok else float("nan")
    value = float(np.nanmax([search, best_seen]))
    d, best = front(np.asarray(rec.misfit), -np.asarray(rec.value))
    out = {"which": which, "data": data, "eps": eps, "search": search, "toward": toward,
           "feasible_seen": seen_ok, "ceiling": value,
           "at": {k: (-v[0]) for k, v in rec.best.items()},
           "by_start": by_start, "front": _thin(d, best), "evaluations": mf.n_eval - n0,
           "seen_other": {k: rec.best_score(k, eps) for k in rec.scores},
           "time_s": time.perf_counter() - t0}
    arrays = {}
    if "1" in rec.best:
        th = rec.best["1"][1]
        arrays[f"ceil_{which}_{data}_w"] = np.exp(th[:m]).astype(np.float32)
        arrays[f"ceil_{which}_{data}_v"] = np.exp(th[m:]).astype(np.float32)
        out["check_nc"] = normalized_correlation(np.exp(th[:m] if which == "w" else th[m:]),
                                                 ref)
        out["check_D"] = mf.value(th)
    return out, arrays


# ------------------------------------------------------------------ report

RANKED = ("sensitivity", "vvt", "learned", "homogeneous")
CEILINGS = ("ceil_w_view", "ceil_w_full", "ceil_v_view", "ceil_v_full")
#: the keys every committed result holds, and every ceiling stage that reached a ceiling
RESULT_KEYS = ("instance", "family", "track", "has_contrast_w")
CEILING_KEYS = ("which", "data", "eps", "ceiling", "search", "by_start", "evaluations",
                "time_s", "method")
ESTIMATE_KEYS = ("nc_w", "nc_v", "D_view", "D_full")
HOMOG_KEYS = ("nc_w", "nc_v", "feasible", "D_view", "D_full", "anchor")
#: a board row's misfit is its recomputed estimate's when the recomputation (same solver
#: version, hence the board's config) reproduces the row's NC within this
NC_MATCH = 0.01
CLASSES = ("near-void", "soft", "mixed", "stiff", "no defect")
UNRECORDED = "class not recorded"


class BadInput(ValueError):
    """A committed result, a results table or an argument that cannot be used (the message is
    one line naming the file or key)."""


def _need(d, keys, where: str) -> None:
    if not isinstance(d, dict):
        raise BadInput(f"{where}: not a JSON object")
    for k in keys:
        if k not in d:
            raise BadInput(f"{where}: missing key {k!r}")


def check_result(r, where: str) -> None:
    """Raise :class:`BadInput` naming ``where`` and the key when the committed result ``r``
    lacks what the report reads (a stage still to be computed is simply absent)."""
    _need(r, RESULT_KEYS, where)
    est = r.get("estimates")
    if est is not None:
        _need(est, ("solvers", "means"), f"{where}: estimates")
        for name, s in est["solvers"].items():
            if isinstance(s, dict) and s.get("status") == "ok":
                _need(s, ESTIMATE_KEYS, f"{where}: estimates.solvers.{name}")
    h = r.get("homog")
    if isinstance(h, dict) and "nc_w" in h:
        _need(h, HOMOG_KEYS, f"{where}: homog")
    for stage in CEILINGS:
        c = r.get(stage)
        if isinstance(c, dict) and "ceiling" in c:
            _need(c, CEILING_KEYS, f"{where}: {stage}")
            if est is None or "homog" not in r:
                raise BadInput(f"{where}: {stage} without the estimates and homog stages")


def load_results(out_root: Path) -> list[tuple[Path, dict]]:
    """Every committed result under ``out_root`` (``<family>/<instance>.json``), checked."""
    out = []
    for path in sorted(out_root.glob("*/*.json")):
        try:
            r = json.loads(path.read_text())
        except (OSError, ValueError) as error:
            raise BadInput(f"{path}: cannot read: {error}") from None
        check_result(r, str(path))
        out.append((path, r))
    return out


def has_ceiling(r: dict, stage: str) -> bool:
    c = r.get(stage)
    return isinstance(c, dict) and "ceiling" in c and np.isfinite(_f(c["ceiling"]))


def _f(x) -> float:
    try:
        return float(x)
    except (TypeError, ValueError):
        return float("nan")


def table(results: list[tuple[Path, dict]]):
    """One row per instance from the committed results (pandas DataFrame)."""
    import pandas as pd

    rows = []
    for _, r in results:
        row = {"family": r["family"], "instance": r["instance"],
               "class": r.get("class") or UNRECORDED,
               "n_defects": len(r["defects"]) if "defects" in r else np.nan,
               "has_contrast": bool(r["has_contrast_w"])}
        if "eps" in r:
            row |= {"floor_view": r["eps"].get("view"), "floor_full": r["eps"].get("full")}
        h = r.get("homog", {})
        if "nc_w" in h:
            row |= {"homog_nc_w": h["nc_w"], "homog_nc_v": h["nc_v"],
                    "homog_feasible": h["feasible"], "eps_view": h["D_view"],
                    "eps_full": h["D_full"], "homog_anchor": h["anchor"]}
        for name, m in r.get("estimates", {}).get("means", {}).items():
            row |= {f"{name}_nc_w": m.get("nc_w"), f"{name}_D_full": m.get("D_full"),
                    f"{name}_D_view": m.get("D_view")}
        for name, e in r.get("estimates", {}).get("solvers", {}).items():
            row[f"{name}_status"] = e.get("status")
            if e.get("status") == "ok":
                row |= {f"{name}_nc_w": e["nc_w"], f"{name}_nc_v": e["nc_v"],
                        f"{name}_D_view": e["D_view"], f"{name}_D_full": e["D_full"],
                        f"{name}_board_nc_w": e.get("board_nc_w"),
                        f"{name}_version": e.get("version")}
        for stage in CEILINGS:
            if not has_ceiling(r, stage):
                continue
            c = r[stage]
            tag = stage[5:]
            row |= {f"ceiling_{tag}": c["ceiling"], f"search_{tag}": c["search"],
                    f"evals_{tag}": c["evaluations"], f"time_{tag}": c["time_s"]}
            starts = [b["best_nc"] for b in c["by_start"].values()
                      if b.get("best_nc") is not None]
            if len(starts) > 1:
                row[f"start_spread_{tag}"] = max(starts) - min(starts)
            hist = [b.get("history", []) for b in c["by_start"].values()]
            last = [hh[-1]["f"] - hh[-2]["f"] for hh in hist if len(hh) > 1]
            if last:  # change of -NC over the last outer iteration (0: flat)
                row[f"last_gain_{tag}"] = max(-x for x in last)
        rows.append(row)
    return pd.DataFrame(rows)


def _homog_nc(out_root: Path):
    """NC of every valid estimate against the homogenised truth, per instance."""
    from vvtbench.scoring.metrics import normalized_correlation

    out = {}
    for path in sorted(out_root.glob("*/*.npz")):
        try:
            z = dict(np.load(path, allow_pickle=False))
        except (OSError, ValueError) as error:
            raise BadInput(f"{path}: cannot read: {error}") from None
        if "homog_w" not in z or "homog_v" not in z:
            continue
        res = {}
        for name in SOLVERS:
            if f"est_{name}_w" in z and f"est_{name}_v" in z:
                res[name] = (normalized_correlation(z[f"est_{name}_w"], z["homog_w"]),
                             normalized_correlation(z[f"est_{name}_v"], z["homog_v"]))
        out[path.stem] = res
    return out


# ------------------------------------------------------------------ report: numbers as text


def fmt_interval(mean: float, low: float, high: float, n: int, sign: bool = False) -> str:
    """A mean with its interval and n, never an undefined number printed as one.

    >>> fmt_interval(0.5, 0.4, 0.6, 7)
    '0.500 [0.400, 0.600] (n = 7)'
    >>> fmt_interval(0.5, float("nan"), float("nan"), 1)
    '0.500 [–] (n = 1, no interval)'
    >>> fmt_interval(float("nan"), float("nan"), float("nan"), 0)
    '– (n = 0, no value)'
    """
    f = "+.3f" if sign else ".3f"
    if not n or not np.isfinite(mean):
        return "– (n = 0, no value)"
    if not (np.isfinite(low) and np.isfinite(high)):
        return f"{mean:{f}} [–] (n = {n}, no interval)"
    return f"{mean:{f}} [{low:{f}}, {high:{f}}] (n = {n})"


def fmt_mean(values) -> str:
    """The finite values' mean with its bootstrap interval (:func:`fmt_interval`)."""
    from vvtbench.scoring.stats import summarize

    s = summarize(np.asarray(values, dtype=float))
    return fmt_interval(s["mean"], s["mean_ci_low"], s["mean_ci_high"], s["n"])


def fmt_paired(a, b) -> str:
    """``a - b`` on the pairs where both are finite: mean, interval, n and a's wins."""
    from vvtbench.scoring.stats import paired_comparison

    s = paired_comparison(np.asarray(a, dtype=float), np.asarray(b, dtype=float))
    if not s["n"]:
        return "– (n = 0, no pair)"
    text = fmt_interval(s["mean_diff"], s["ci_low"], s["ci_high"], s["n"], sign=True)
    return text[:-1] + f", first higher on {s['wins']})"


def fmt_class_mean(values, size: int) -> str | None:
    """A class's mean of one column, with its n when some instances have no value; None when
    none has one."""
    x = np.asarray(values, dtype=float)
    x = x[np.isfinite(x)]
    if not x.size:
        return None
    return f"{x.mean():.3f}" + (f" (n = {x.size})" if x.size < size else "")


def column(d, name: str):
    """``d[name]``, or NaN on every row when the column is absent (no instance has it yet)."""
    import pandas as pd

    return d[name] if name in d else pd.Series(np.nan, index=d.index)


# ------------------------------------------------------------------ report: coverage, board


def split_sizes() -> dict[str, int]:
    """The number of instances of each ceiling track in the standard suite ({} when the
    suite cannot be read)."""
    from vvtbench.bench.suite import load_suite

    try:
        suite = load_suite("standard")
    except (OSError, ValueError):
        return {}
    tracks = {t for t, _ in TRACKS.values()}
    return {t.name: len(t.scenes) for t in suite.tracks if t.name in tracks}


def coverage_lines(results: list[tuple[Path, dict]], family: str, sizes: dict) -> list[str]:
    """How many of the split's instances each ceiling kind covers, for ``family``."""
    track = TRACKS.get(family, (None,))[0]
    mine = [r for _, r in results if r["family"] == family]
    total = sizes.get(track)
    of = f"of the {total} instances of the test split ({track})" if total else \
        f"of the instances of {track} (split size unknown)"
    flat = sum(1 for r in mine if not r["has_contrast_w"])
    lines = [f"committed: {len(mine)} {of}; {flat} without contrast in w (NC undefined, no "
             "ceiling)"]
    for stage in CEILINGS:
        if stage in SKIP.get(family, ()):
            lines.append(f"  {stage[5:]}: not computed for this family (its view is every DOF)")
            continue
        k = sum(has_ceiling(r, stage) for r in mine)
        if not k and stage not in DEFAULT_STAGES:
            lines.append(f"  {stage[5:]}: not computed (not a default stage of `run`)")
            continue
        lines.append(f"  ceiling {stage[5:]}: {k} " + (f"of {total}" if total else "instances"))
    return lines


def ceiling_rows(results: list[tuple[Path, dict]]) -> list[dict]:
    """One row per instance and ceiling kind (:data:`vvtbench.reporting.headroom.COLUMNS`):
    the table the leaderboard reads beside the standard board's results."""
    out = []
    for _, r in results:
        for stage in CEILINGS:
            if not has_ceiling(r, stage):
                continue
            c = r[stage]
            out.append({"instance": r["instance"], "track": r["track"], "observation": "true",
                        "n_modes": int(r.get("n_modes", N_MODES)), "kind": stage[5:],
                        "ceiling": float(c["ceiling"]), "eps": float(c["eps"]),
                        "homog_nc": float(r["homog"][f"nc_{c['which']}"]),
                        "method": str(c["method"]), "inputs_sha256": r.get("inputs_sha256", "")})
    return out


def write_ceilings(rows: list[dict], path: Path) -> None:
    """``rows`` (:func:`ceiling_rows`) as ``path``, atomically, checked as the leaderboard
    checks it."""
    import pandas as pd

    from vvtbench.io.files import write_text
    from vvtbench.reporting.headroom import COLUMNS, check_ceilings

    df = pd.DataFrame(rows, columns=list(COLUMNS))
    problem = check_ceilings(df, str(path))
    if problem:
        raise BadInput(problem)
    write_text(path, df.to_csv(index=False, lineterminator="\n"))


def read_board(path: Path):
    """The results table at ``path`` (None when there is none), typed as written (a CSV's
    observation ``true`` stays a string)."""
    from vvtbench.bench import read_results

    if not path.exists():
        return None
    try:
        d = read_results(path)
    except (OSError, ValueError) as error:
        raise BadInput(f"{path}: cannot read: {error}") from None
    for col in ("track", "scene", "solver", "status", "observation", "nc_w", "nc_v"):
        if col not in d.columns:
            raise BadInput(f"{path}: missing column {col!r}")
    return d


def board_rows_above(r: dict, board) -> dict:
    """The board's rows of the instance ``r`` (its track and scene, true modes, its number of
    modes) against each of its ceilings.

    A row's misfit is that of the instance's recomputed estimate of the same solver when the
    recomputation ran the row's solver version and reproduces its NC within
    :data:`NC_MATCH`; otherwise it is unknown.

    Returns
    -------
    dict
        ``checked``: (row, ceiling) pairs compared; ``feasible_above``: (solver, stage) of rows
        above a ceiling that explain the data (D <= eps: each contradicts the ceiling);
        ``unknown_above``: (solver, stage, why) of rows above a ceiling whose misfit is not
        known; ``infeasible_above``: (solver, stage, NC, ceiling, D / eps) of rows above it
        that do not explain the data.
    """
    from vvtbench.scoring.ceiling import rows_above_ceiling

    out = {"checked": 0, "feasible_above": [], "unknown_above": [], "infeasible_above": []}
    if board is None:
        return out
    rows = board[(board.track == r["track"]) & (board.scene == r["instance"])
                 & (board.observation == "true") & (board.status == "ok")]
    if "n_modes" in rows:
        rows = rows[rows.n_modes.astype(float) == float(r.get("n_modes", N_MODES))]
    est = r.get("estimates", {}).get("solvers", {})
    for stage in CEILINGS:
        if not has_ceiling(r, stage):
            continue
        c = r[stage]
        which, data = c["which"], c["data"]
        for row in rows.itertuples():
            nc = _f(getattr(row, f"nc_{which}"))
            if not np.isfinite(nc):
                continue
            out["checked"] += 1
            e = est.get(row.solver, {})
            same = (e.get("status") == "ok"
                    and str(e.get("version")) == str(getattr(row, "solver_version", None))
                    and abs(_f(e.get(f"nc_{which}")) - nc) <= NC_MATCH)
            D = _f(e.get(f"D_{data}")) if same else float("nan")
            res = rows_above_ceiling(c, {row.solver: {"nc": nc, "D": D}})
            if res["feasible_above"]:
                out["feasible_above"].append((row.solver, stage))
            elif res["unknown_above"]:
                why = ("no recomputed estimate of this version" if not same else "no misfit")
                out["unknown_above"].append((row.solver, stage, why))
            elif res["infeasible_above"]:
                out["infeasible_above"].append((row.solver, stage, nc, float(c["ceiling"]),
                                                D / float(c["eps"])))
    return out


def _shown(path: Path) -> str:
    """``path`` relative to the repository when inside it (the summary reads the same on every
    machine)."""
    try:
        return str(path.resolve().relative_to(ROOT))
    except ValueError:
        return str(path)


def check_lines(results: list[tuple[Path, dict]], board, board_path: Path) -> list[str]:
    """The checks: no recomputed estimate and no board row above its instance's ceiling
    while explaining the data."""
    from vvtbench.scoring.ceiling import rows_above_ceiling

    lines = ["== rows above their instance's ceiling", "recomputed estimates:"]
    n_checked, bad, over = 0, [], []
    for _, r in results:
        for stage in CEILINGS:
            if not has_ceiling(r, stage):
                continue
            c = r[stage]
            which, data = c["which"], c["data"]
            rows = {n: {"nc": s[f"nc_{which}"], "D": s[f"D_{data}"]}
                    for n, s in r["estimates"]["solvers"].items() if s.get("status") == "ok"}
            res = rows_above_ceiling(c, rows)
            n_checked += len(rows)
            bad += [(r["instance"], stage, n) for n in res["feasible_above"]]
            over += [(r["instance"], stage, n, rows[n]["nc"], c["ceiling"],
                      rows[n]["D"] / c["eps"]) for n in res["infeasible_above"]]
    lines.append(f"  {n_checked} (estimate, ceiling) pairs checked; above the ceiling and "
                 f"explaining the data: {len(bad)} {bad if bad else ''}".rstrip())
    lines.append(f"  above the ceiling, not explaining the data (D > eps): {len(over)}")
    for inst, stage, n, nc, top, ratio in over:
        lines.append(f"    {inst} {stage} {n}: NC {nc:.3f} > ceiling {top:.3f}, "
                     f"its misfit {ratio:.1f} x eps")
    if board is None:
        lines.append(f"board rows: no table at {_shown(board_path)}")
        return lines
    lines.append(f"board rows ({_shown(board_path)}, true modes):")
    tot = {"checked": 0, "feasible_above": [], "unknown_above": [], "infeasible_above": []}
    for _, r in results:
        res = board_rows_above(r, board)
        tot["checked"] += res["checked"]
        for k in ("feasible_above", "unknown_above", "infeasible_above"):
            tot[k] += [(r["instance"], *x) for x in res[k]]
    lines.append(f"  {tot['checked']} (row, ceiling) pairs checked; above the ceiling and "
                 f"explaining the data: {len(tot['feasible_above'])}")
    lines += [f"    {i} {st} {s}" for i, s, st in tot["feasible_above"]]
    lines.append(f"  above the ceiling, misfit unknown: {len(tot['unknown_above'])}")
    lines += [f"    {i} {st} {s}: {why}" for i, s, st, why in tot["unknown_above"]]
    lines.append(f"  above the ceiling, not explaining the data: {len(tot['infeasible_above'])}")
    lines += [f"    {i} {st} {s}: NC {nc:.3f} > ceiling {top:.3f}, its misfit {q:.1f} x eps"
              for i, s, st, nc, top, q in tot["infeasible_above"]]
    return lines


def family_lines(fam: str, d) -> list[str]:
    """The summary of one family's instances with contrast (``d``: :func:`table`'s rows)."""
    lines = [f"== {fam}: {len(d)} instances with contrast in w", ""]
    for tag in ("w_view", "w_full", "v_view", "v_full"):
        col = column(d, f"ceiling_{tag}")
        if col.notna().any():
            lines.append(f"ceiling {tag}: {fmt_mean(col)}")
    feas = column(d, "homog_feasible")
    lines.append(f"homogenised truth, NC w with the arithmetic: "
                 f"{fmt_mean(column(d, 'homog_nc_w'))}; reaches the floor on "
                 f"{int(feas.dropna().astype(bool).sum())} of {int(feas.notna().sum())}")
    for name in ("sensitivity", "oracle", "vvt"):
        if f"{name}_nc_w" in d:
            lines.append(f"ceiling w (view) - {name} NC w: "
                         f"{fmt_paired(column(d, 'ceiling_w_view'), d[f'{name}_nc_w'])}")
    lines += ["", "mean NC w against the arithmetic | against the homogenised truth "
              "(same instances):"]
    for name in SOLVERS:
        if f"{name}_nc_w" in d:
            a, h = d[f"{name}_nc_w"], column(d, f"{name}_nc_w_homog")
            ok = a.notna() & h.notna()
            lines.append(f"  {name:12s} {fmt_mean(a[ok])} | {fmt_mean(h[ok])}")
    for a, b in (("sensitivity", "oracle"), ("sensitivity", "vvt")):
        if f"{a}_nc_w" in d and f"{b}_nc_w" in d:
            arith = fmt_paired(d[f"{a}_nc_w"], d[f"{b}_nc_w"])
            homog = fmt_paired(column(d, f"{a}_nc_w_homog"), column(d, f"{b}_nc_w_homog"))
            lines.append(f"  {a} - {b}: arithmetic {arith}; homogenised {homog}")
    lines += ["", "per class (mean NC w; ceiling w view; homogenised truth vs arithmetic):"]
    order = {k: i for i, k in enumerate((*CLASSES, UNRECORDED))}
    for kind in sorted(set(d["class"]), key=lambda k: (order.get(k, len(order)), k)):
        g = d[d["class"] == kind]
        parts = [f"{kind} ({len(g)})"]
        for col in ("ceiling_w_view", "ceiling_w_full", "homog_nc_w", "sensitivity_nc_w",
                    "sensitivity_nc_w_homog", "oracle_nc_w", "oracle_nc_w_homog"):
            text = fmt_class_mean(column(g, col), len(g))
            if text is not None:
                parts.append(f"{col} {text}")
        lines.append("  " + "; ".join(parts))
    lines.append("")
    return lines


def report(out_root: Path, figures: Path | None = None, board: Path = BOARD,
           ceilings: Path | None = None) -> str:
    """The summary printed and written to ``out_root / summary.txt``; the per-instance table
    to ``out_root / instances.csv``; the ceilings table to ``ceilings`` (when given: the
    leaderboard's headroom reads it beside the board's results table); figures to
    ``figures``.

    Raises
    ------
    BadInput
        A committed result or the board's table cannot be used (the message names it).
    """
    from vvtbench.io.files import write_text

    results = load_results(out_root)
    board_df = read_board(board)
    df = table(results)
    if df.empty:
        text = f"no committed result under {out_root}\n"
        if ceilings is not None:
            write_ceilings([], ceilings)
        return text
    hn = _homog_nc(out_root)
    for name in SOLVERS:
        df[f"{name}_nc_w_homog"] = [hn.get(i, {}).get(name, (np.nan, np.nan))[0]
                                    for i in df.instance]
        df[f"{name}_nc_v_homog"] = [hn.get(i, {}).get(name, (np.nan, np.nan))[1]
                                    for i in df.instance]
    write_text(out_root / "instances.csv", df.to_csv(index=False, float_format="%.6g"))
    sizes = split_sizes()
    lines: list[str] = []
    for fam, d in df.groupby("family"):
        lines += [f"== {fam}: coverage"] + coverage_lines(results, fam, sizes) + [""]
        lines += family_lines(fam, d[d.has_contrast])
    lines += check_lines(results, board_df, board)
    if ceilings is not None:
        rows = ceiling_rows(results)
        write_ceilings(rows, ceilings)
        lines.append(f"ceilings table: {len(rows)} rows -> {_shown(ceilings)}")
    text = "\n".join(lines) + "\n"
    write_text(out_root / "summary.txt", text)
    if figures is not None:
        plot(df, out_root, figures)
    return text


def _board_video() -> dict:
    """The board's sensitivity NC w from video (phase extractor), per instance."""
    import pandas as pd

    if not BOARD.exists():
        return {}
    d = pd.read_csv(BOARD)
    d = d[d.track.isin(["cube_video", "drums_video"]) & (d.solver == "sensitivity")
          & (d.observation == "extracted") & (d.status == "ok")]
    return dict(zip(d.scene, d.nc_w, strict=True))


def plot(df, out_root: Path, figures: Path) -> None:
    """docs/gallery/ceiling_*.png."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figures.mkdir(parents=True, exist_ok=True)
    colors = {"near-void": "tab:red", "soft": "tab:orange", "mixed": "tab:purple",
              "stiff": "tab:blue"}
    fams = [f for f in ("cube_defects", "drum_defects") if f in set(df.family)]
    # 1. per instance: ceiling, homogenised truth, solvers
    fig, axes = plt.subplots(len(fams), 1, figsize=(11, 3.6 * len(fams)), squeeze=False)
    for ax, fam in zip(axes[:, 0], fams, strict=True):
        d = df[(df.family == fam) & df.has_contrast & column(df, "ceiling_w_view").notna()]
        d = d.sort_values("ceiling_w_view")
        x = np.arange(len(d))
        ax.bar(x, d.ceiling_w_view, color=[colors.get(k, "grey") for k in d["class"]],
               alpha=0.35, label="ceiling (20 true modes, the board's view)")
        if "ceiling_w_full" in d:
            ax.plot(x, d.ceiling_w_full, "k_", ms=12, mew=2, label="ceiling, every DOF")
        ax.plot(x, d.homog_nc_w, "ks", mfc="none", label="homogenised truth")
        for name, mk in (("sensitivity", "o"), ("oracle", "^"), ("vvt", "x")):
            if f"{name}_nc_w" in d:
                ax.plot(x, d[f"{name}_nc_w"], mk, label=name, ms=5)
        ax.set_xticks(x)
        ax.set_xticklabels([i.split("-")[-1] for i in d.instance], rotation=90, fontsize=7)
        ax.set_ylabel("NC w (against the arithmetic truth)")
        ax.set_ylim(-0.3, 1.02)
        ax.set_title(f"{fam} test: ceiling per instance (bar colour: class; red near-void, "
                     "orange soft, purple mixed, blue stiff)", fontsize=9)
        ax.legend(fontsize=7, ncol=3, loc="lower right")
    fig.tight_layout()
    fig.savefig(figures / "ceiling_per_instance.png", dpi=110)
    plt.close(fig)
    # 2. what limits each class: the ladder from the truth to the solvers
    video = _board_video()
    fig, axes = plt.subplots(1, len(fams), figsize=(6.2 * len(fams), 3.9), squeeze=False)
    steps = [("homog_nc_w", "homogenised truth"), ("ceiling_w_full", "ceiling, every DOF"),
             ("ceiling_w_view", "ceiling, the board's view"), ("oracle_nc_w", "oracle"),
             ("sensitivity_nc_w", "sensitivity, true modes"),
             ("video_sensitivity", "sensitivity, video (board)")]
    for ax, fam in zip(axes[0], fams, strict=True):
        d = df[(df.family == fam) & df.has_contrast].copy()
        d["video_sensitivity"] = [video.get(i, np.nan) for i in d.instance]
        kinds = [k for k in ("near-void", "soft", "mixed", "stiff") if k in set(d["class"])]
        width = 0.8 / len(steps)
        for j, (col, label) in enumerate(steps):
            if col not in d:
                continue
            vals = [d[d["class"] == k][col].mean() for k in kinds]
            ns = [int(d[d["class"] == k][col].notna().sum()) for k in kinds]
            xs = np.arange(len(kinds)) + (j - len(steps) / 2 + 0.5) * width
            ax.bar(xs, vals, width, label=label)
            for xx, vv, nn in zip(xs, vals, ns, strict=True):
                if np.isfinite(vv):
                    ax.text(xx, max(vv, 0) + 0.01, str(nn), ha="center", fontsize=5)
        ax.set_xticks(np.arange(len(kinds)))
        ax.set_xticklabels([f"{k} ({int((d['class'] == k).sum())})" for k in kinds])
        ax.set_ylabel("mean NC w (arithmetic truth)")
        ax.set_ylim(0, 1.05)
        ax.set_title(f"{fam} test: from the truth to the solvers (n over each bar)",
                     fontsize=9)
        ax.legend(fontsize=6, loc="lower left")
    fig.tight_layout()
    fig.savefig(figures / "ceiling_ladder.png", dpi=110)
    plt.close(fig)
    # 3. NC against the two truths
    fig, axes = plt.subplots(1, len(fams), figsize=(5.2 * len(fams), 4.6), squeeze=False)
    for ax, fam in zip(axes[0], fams, strict=True):
        d = df[(df.family == fam) & df.has_contrast]
        for name, mk in (("sensitivity", "o"), ("oracle", "^"), ("vvt", "x"),
                         ("learned", "d")):
            if f"{name}_nc_w" in d:
                ax.plot(d[f"{name}_nc_w"], d[f"{name}_nc_w_homog"], mk, label=name, ms=5)
        ax.plot([-1, 1], [-1, 1], "k:", lw=0.8)
        ax.set_xlim(-0.4, 1.02)
        ax.set_ylim(-0.4, 1.02)
        ax.set_xlabel("NC w against the arithmetic truth")
        ax.set_ylabel("NC w against the homogenised truth")
        ax.set_title(fam, fontsize=9)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(figures / "ceiling_truths.png", dpi=110)
    plt.close(fig)
    # 4. misfit fronts of a few instances, with the estimates
    picks = []
    for fam in fams:
        d = df[(df.family == fam) & df.has_contrast & column(df, "ceiling_w_view").notna()]
        for kind in ("near-void", "soft", "stiff", "mixed"):
            g = d[d["class"] == kind]
            if len(g):
                picks.append(g.instance.iloc[0])
    picks = picks[:6]
    if picks:
        fig, axes = plt.subplots(1, len(picks), figsize=(3.3 * len(picks), 3.4),
                                 squeeze=False)
        for ax, inst in zip(axes[0], picks, strict=True):
            fam = df[df.instance == inst].family.iloc[0]
            r = json.loads((out_root / fam / f"{inst}.json").read_text())
            c = r["ceil_w_view"]
            fr = np.asarray(c["front"])
            if len(fr):
                ax.step(fr[:, 0] / c["eps"], fr[:, 1], where="post", color="k",
                        label="best NC found at misfit")
            ax.axvline(1.0, color="grey", ls=":")
            for name, mk in (("sensitivity", "o"), ("oracle", "^"), ("vvt", "x")):
                e = r["estimates"]["solvers"].get(name, {})
                if e.get("status") == "ok":
                    ax.plot(e["D_view"] / c["eps"], e["nc_w"], mk, label=name)
            m = r["estimates"]["means"]
            ax.plot(m["arithmetic"]["D_view"] / c["eps"], 1.0, "k*", label="arithmetic truth")
            ax.plot(1.0, r["homog"]["nc_w"], "ks", mfc="none", label="homogenised")
            ax.set_xscale("log")
            ax.set_xlim(0.1, 3e3)
            ax.set_xticks([0.1, 1, 10, 100, 1000])
            ax.set_xticklabels(["0.1", "1", "10", "100", "1000"])
            ax.set_title(f"{inst.split('-')[0][:4]} {inst[-5:]} ({r['class']})", fontsize=8)
            ax.set_xlabel("misfit D / eps (view)", fontsize=8)
            ax.set_ylim(min(0.0, ax.get_ylim()[0]), 1.02)
        axes[0, 0].set_ylabel("NC w")
        axes[0, 0].legend(fontsize=6)
        fig.tight_layout()
        fig.savefig(figures / "ceiling_fronts.png", dpi=110)
        plt.close(fig)


# ------------------------------------------------------------------ driver


def run_instance(sample: Path, stages, out_root: Path) -> None:
    from threadpoolctl import threadpool_limits

    from vvtbench.io.files import write_json, write_npz
    from vvtbench.scoring.ceiling import Misfit
    from vvtbench.scoring.homogenize import voxel_means

    family, track, p, t = load(sample)
    instance = sample.name
    folder = out_root / family
    folder.mkdir(parents=True, exist_ok=True)
    jpath, npath = folder / f"{instance}.json", folder / f"{instance}.npz"
    sha = inputs_sha256(p, t)
    result = json.loads(jpath.read_text()) if jpath.exists() else {}
    if result.get("inputs_sha256") != sha:
        result = {}
    arrays = dict(np.load(npath)) if npath.exists() and result else {}
    from vvtbench.scoring.metrics import is_constant

    defects, kind = defects_of(sample)
    result.update({
        "defects": defects, "class": kind,
        "instance": instance, "family": family, "track": track, "n_modes": N_MODES,
        "observation": {"view": "20 true modes, one camera, depth visibility (the board's)",
                        "full": "20 true modes at every free DOF of the inference mesh"},
        "inputs_sha256": sha, "n_params": int(p.n_params), "n_free": int(p.model.n_free),
        "has_contrast_w": not is_constant(t.w), "has_contrast_v": not is_constant(t.v),
        "budget": BUDGET, "seed": 0})
    ctx = {"sample": sample, "family": family, "track": track, "instance": instance, "p": p,
           "t": t, "result": result, "arrays": arrays,
           "misfits": {k: Misfit(p.model, d) for k, d in data_of(p, t).items()},
           "means": voxel_means(sample, p)}
    with threadpool_limits(limits=1, user_api="blas"):
        for stage in stages:
            if stage in SKIP.get(family, ()):
                continue
            method = METHOD["ceil" if stage.startswith("ceil") else stage]
            if stage in result and result[stage].get("method") == method:
                continue
            if stage.startswith("ceil") and not result.get(
                    "has_contrast_" + stage.split("_")[1], True):
                result[stage] = {"skipped": "the arithmetic truth is constant: NC undefined",
                                 "method": method}
                continue
            print(f"{instance}: {stage}", flush=True)
            t0 = time.perf_counter()
            if stage == "estimates":
                res, arr = stage_estimates(ctx)
            elif stage == "eps":
                res, arr = stage_eps(ctx)
            elif stage == "homog":
                res, arr = stage_homog(ctx)
            else:
                _, which, data = stage.split("_")
                res, arr = stage_ceiling(ctx, which, data)
            res = {**res, "method": method, "wall_s": time.perf_counter() - t0}
            result[stage] = res
            arrays.update(arr)
            write_npz(npath, arrays)
            write_json(jpath, result)
    write_json(jpath, result)  # the instance's description, even when every stage was cached


def parse_only(text: str | None, n: int) -> list[int]:
    if not text:
        return list(range(n))
    out: list[int] = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        out += list(range(int(a), int(b) + 1)) if b else [int(a)]
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run", help="compute (resumable)")
    r.add_argument("samples", type=Path, help="folder of sample folders (vvtbench generate)")
    r.add_argument("--only", help="instance indices, e.g. 0-9,12")
    r.add_argument("--stages", default=",".join(DEFAULT_STAGES))
    r.add_argument("-o", "--out", type=Path, default=OUT)
    rep = sub.add_parser("report", help="tables and checks from the committed results")
    rep.add_argument("-o", "--out", type=Path, default=OUT)
    rep.add_argument("--figures", type=Path, default=ROOT / "docs" / "gallery")
    rep.add_argument("--board", type=Path, default=BOARD,
                     help="the results table whose rows are checked against the ceilings")
    rep.add_argument("--ceilings", type=Path, default=BOARD.parent / "ceilings.csv",
                     help="where the ceilings table is written (beside the board's results: "
                          "the leaderboard's headroom reads it there)")
    args = ap.parse_args(argv)
    try:
        if args.cmd == "run":
            run(args.samples, args.only, args.stages, args.out)
        else:
            print(report(args.out, args.figures, args.board, args.ceilings), end="")
    except BadInput as error:
        print(f"error: {error}", file=sys.stderr)
        sys.exit(2)


def run(samples_dir: Path, only: str | None, stages_text: str, out: Path) -> None:
    """``run``: every stage of the chosen samples (resumable)."""
    if not samples_dir.is_dir():
        raise BadInput(f"{samples_dir}: no such folder of samples")
    samples = sorted(d for d in samples_dir.iterdir() if (d / "family.json").exists())
    stages = [s for s in stages_text.split(",") if s]
    for s in stages:
        if s not in STAGES:
            raise BadInput(f"--stages: unknown stage {s!r} (stages: {', '.join(STAGES)})")
    try:
        picked = parse_only(only, len(samples))
    except ValueError:
        raise BadInput(f"--only: {only!r} is not a list of indices such as 0-9,12") from None
    wrong = [i for i in picked if not 0 <= i < len(samples)]
    if wrong:
        raise BadInput(f"--only: index {wrong[0]} is not one of the {len(samples)} samples "
                       f"in {samples_dir}")
    for i in picked:
        t0 = time.perf_counter()
        run_instance(samples[i], stages, out)
        print(f"{samples[i].name}: done in {time.perf_counter() - t0:.0f} s", flush=True)


if __name__ == "__main__":
    main()
