"""The learned solver against ``sensitivity`` and ``homogeneous`` on a family's test split.

    python benchmarks/bench_learned.py --data DIR [DIR ...] [--n-val 50] [--sizes 25 50 ...]
        [--reference ref.json] [--features feats.npz] [--previous old.npz]
        [--curve benchmarks/learning_curve.png]

DIR: folders (or exported datasets) of generated samples of the family (modes only), e.g. a
release's ``cube_defects-modes`` and extra train instances from ``vvtbench generate FAMILY
--split train --no-video``. The train split trains (nested subsets of the first N train
instances, one network ensemble per size), the val split selects (the architecture was chosen
on it), the test split is scored once per model. All solvers go through the normal plug-in
path (``load_solver``) on the same true-mode observations. ``--reference`` keeps the
per-instance scores and times of the slow reference solvers in a JSON file, so a second run
reuses them; ``--features`` keeps every instance's per-voxel features (and the basis) in an
``.npz``, so a second run trains without observing again. ``--previous`` scores an older
weights file of the linear model ("modal-step-ridge") on the same val and test instances.
Prints the learning-curve table (markdown) and writes the curve figure.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from vvtbench.data import iter_instances
from vvtbench.metrics import normalized_correlation

OBSERVE = {"n_modes": 10, "visibility": "depth"}


def _pairs(roots: list[Path], split: str, limit: int | None = None):
    count = 0
    for root in roots:
        for pair in iter_instances(root, split, **OBSERVE):
            if limit is not None and count >= limit:
                return
            count += 1
            yield pair


def reference_scores(roots: list[Path], solvers: list[str], cache: Path | None) -> dict:
    """Per-instance NC w and solve time of each reference solver on the test split."""
    from vvtbench.plugins import load_solver

    done = json.loads(cache.read_text()) if cache is not None and cache.is_file() else {}
    for name in solvers:
        if name in done:
            continue
        solver = load_solver(name)()
        nc, secs = [], []
        for problem, truth in _pairs(roots, "test"):
            t0 = time.perf_counter()
            est = solver.solve(problem)
            secs.append(time.perf_counter() - t0)
            nc.append(normalized_correlation(est.w, truth.w))
            print(f"{name}: {len(nc)} nc_w {nc[-1]:+.3f} {secs[-1]:.2f} s", flush=True)
        done[name] = {"nc_w": nc, "seconds": secs}
        if cache is not None:
            from vvtbench.io import write_json

            write_json(cache, done)
    return done


def mean_ci(values, n_boot: int = 2000, seed: int = 0) -> tuple[float, float, float]:
    """Mean and a 95 % bootstrap interval (seeded)."""
    x = np.asarray(values, dtype=float)
    rng = np.random.default_rng(seed)
    boots = x[rng.integers(0, len(x), (n_boot, len(x)))].mean(axis=1)
    return float(x.mean()), float(np.quantile(boots, 0.025)), float(np.quantile(boots, 0.975))


def split_features(roots: list[Path], split: str, limit: int | None, basis: np.ndarray
                   ) -> dict:
    """Per-voxel features, truth w and names of a split's instances."""
    from solvers.learned import voxel_features

    X, w, names = [], [], []
    for problem, truth in _pairs(roots, split, limit):
        X.append(voxel_features(problem, basis)[0])
        w.append(np.asarray(truth.w, dtype=float))
        names.append(str(problem.meta.get("name", len(names))))
    return {"X": np.array(X), "w": np.array(w), "names": np.array(names)}


def cached_features(roots: list[Path], n_train: int, n_val: int, cache: Path | None) -> dict:
    """Basis and the features of train (first ``n_train``), val (``n_val``) and test."""
    from solvers.learned import N_REFERENCE, reference_basis

    if cache is not None and cache.is_file():
        with np.load(cache, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    t0 = time.perf_counter()
    basis = reference_basis([pr for pr, _ in _pairs(roots, "train", N_REFERENCE)])
    out = {"basis": basis}
    for split, limit in (("train", n_train), ("val", n_val), ("test", None)):
        for key, value in split_features(roots, split, limit, basis).items():
            out[f"{split}_{key}"] = value
        print(f"features of {len(out[f'{split}_X'])} {split} instances: "
              f"{time.perf_counter() - t0:.0f} s", flush=True)
    if cache is not None:
        from vvtbench.io import write_npz

        write_npz(cache, out)
    return out


def ridge_inputs(X: np.ndarray) -> np.ndarray:
    """The linear model's per-voxel inputs (steps, unit steps, squared position) from the
    network's (:func:`vvtbench.learning.modal_features.step_features` column order)."""
    return np.column_stack([X[:, :10], X[:, -3:]])


def items_of(feats: dict, split: str) -> list[dict]:
    from solvers.learned import standardized

    return [{"X": X, "w": w, "y": standardized(w)}
            for X, w in zip(feats[f"{split}_X"], feats[f"{split}_w"], strict=True)]


def main(argv: list[str] | None = None) -> int:
    from solvers.learned import (
        LearnedConfig,
        fit_features,
        load_weights,
        mean_nc,
        predict_w,
        save_weights,
    )
    from vvtbench.plugins import load_solver

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, nargs="+", required=True)
    p.add_argument("--n-val", type=int, default=50)
    p.add_argument("--sizes", type=int, nargs="+", default=[25, 50, 100, 200, 400, 800, 1600])
    p.add_argument("--reference", type=Path, default=None)
    p.add_argument("--references", nargs="*", default=["homogeneous", "sensitivity"])
    p.add_argument("--features", type=Path, default=None)
    p.add_argument("--previous", type=Path, default=None,
                   help="weights of the linear model to score on the same val and test")
    p.add_argument("--curve", type=Path, default=Path("benchmarks/learning_curve.png"))
    p.add_argument("--tmp", type=Path, default=Path("/tmp/bench_learned"))
    p.add_argument("--rows", type=Path, default=None,
                   help="JSON of the learning-curve rows: written after training; with "
                   "--replot read instead (table and figure again, e.g. with more references)")
    p.add_argument("--replot", action="store_true")
    args = p.parse_args(argv)
    if args.replot:
        ref = json.loads(args.reference.read_text())
        report(json.loads(args.rows.read_text()), ref, args.curve)
        return 0

    ref = reference_scores(args.data, args.references, args.reference)
    feats = cached_features(args.data, max(args.sizes), args.n_val, args.features)
    basis = feats["basis"]
    train, val, test = (items_of(feats, s) for s in ("train", "val", "test"))
    sizes = [s for s in args.sizes if s <= len(train)]
    if len(train) not in sizes:
        sizes.append(len(train))
    rows = []
    args.tmp.mkdir(parents=True, exist_ok=True)
    if args.previous is not None:
        old, meta = load_weights(args.previous)
        old = {**old, "model": meta.get("model")}
        for split, items in (("val", val), ("test", test)):
            nc = [normalized_correlation(predict_w(old, ridge_inputs(it["X"]), 1.0), it["w"])
                  for it in items]
            print(f"previous ({meta.get('model')} {meta.get('solver_version')}, "
                  f"{meta.get('n_instances')} train) {split} NC w {mean_ci(nc)}", flush=True)
        ref = {**ref, f"learned {meta.get('solver_version')}": {"nc_w": nc, "seconds": []}}
    for size in sizes:
        t0 = time.perf_counter()
        weights = fit_features(train[:size], basis)
        fit_s = time.perf_counter() - t0
        val_nc = mean_nc(weights, val)
        nc = [normalized_correlation(predict_w(weights, it["X"], 1.0), it["w"]) for it in test]
        rows.append({"n_train": size, "val_nc_w": val_nc, "nc_w": nc, "test": mean_ci(nc),
                     "fit_seconds": fit_s})
        print(f"n={size}: fit {fit_s:.0f} s val {val_nc:+.3f} test {rows[-1]['test'][0]:+.3f}",
              flush=True)
    # the largest model once more through the plug-in path: same scores, and the solve time
    path = save_weights(args.tmp / "learned.npz", weights, {"family": "bench",
                                                             "split": "train"})
    solver = load_solver("learned")(LearnedConfig(weights=str(path)))
    secs, cpu = [], []
    for (problem, truth), expected in zip(_pairs(args.data, "test"), rows[-1]["nc_w"],
                                          strict=True):
        t, c = time.perf_counter(), time.process_time()
        est = solver.solve(problem)
        secs.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
        assert abs(normalized_correlation(est.w, truth.w) - expected) < 1e-9
    print(f"plug-in solve of the {rows[-1]['n_train']}-instance model: median "
          f"{np.median(secs):.3f} s wall, {np.median(cpu):.3f} s CPU", flush=True)
    for row in rows:
        row["seconds"] = float(np.median(secs))
        row["cpu_seconds"] = float(np.median(cpu))
    if args.rows is not None:
        from vvtbench.io import write_json

        write_json(args.rows, rows)
    report(rows, ref, args.curve)
    return 0


def report(rows: list[dict], ref: dict, curve: Path) -> None:
    """The learning-curve table (markdown, stdout) and figure."""
    print("\n| train instances | fit (s) | val NC w | test NC w [95 % CI] | s / instance |")
    print("|---|---|---|---|---|")
    for r in rows:
        m, lo, hi = r["test"]
        print(f"| {r['n_train']} | {r['fit_seconds']:.0f} | {r['val_nc_w']:+.3f} | "
              f"{m:+.3f} [{lo:+.3f}, {hi:+.3f}] | {r['seconds']:.3f} |")
    for name, d in ref.items():
        m, lo, hi = mean_ci(d["nc_w"])
        k = len(d["nc_w"])
        t = f"{np.median(d['seconds']):.3f}" if d["seconds"] else ""
        print(f"| `{name}` ({k} test instances) | | | {m:+.3f} [{lo:+.3f}, "
              f"{hi:+.3f}] | {t} |")
        if rows and k < len(rows[-1]["nc_w"]):
            m, lo, hi = mean_ci(rows[-1]["nc_w"][:k])
            print(f"| learned ({rows[-1]['n_train']}) on the same {k} | | | {m:+.3f} "
                  f"[{lo:+.3f}, {hi:+.3f}] | |")
    plot_curve(rows, ref, curve)
    print(f"figure: {curve}")


def plot_curve(rows: list[dict], ref: dict, path: Path) -> None:
    """NC w on the test split against the number of train instances."""
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    n = [r["n_train"] for r in rows]
    m = np.array([r["test"] for r in rows])
    ax.errorbar(n, m[:, 0], yerr=[m[:, 0] - m[:, 1], m[:, 2] - m[:, 0]], marker="o",
                capsize=3, label="learned (test, 95 % CI)")
    ax.plot(n, [r["val_nc_w"] for r in rows], "s--", color="0.5", label="learned (val)")
    colors = {"sensitivity": "C3", "homogeneous": "k", "learned 2.0.0": "C2"}
    for name, d in ref.items():
        mean, lo, hi = mean_ci(d["nc_w"])
        c = colors.get(name, "C2")
        ax.axhline(mean, color=c, lw=1.2, label=f"{name} (test)")
        ax.axhspan(lo, hi, color=c, alpha=0.12)
    ax.set_xscale("log")
    ax.set_xticks(n, [str(k) for k in n])
    ax.xaxis.set_minor_locator(matplotlib.ticker.NullLocator())
    ax.set_xlabel("train instances")
    ax.set_ylabel("mean NC of w (test split, true modes)")
    ax.set_title("learned solver: cube_defects learning curve")
    ax.legend(fontsize=8, loc="best")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
