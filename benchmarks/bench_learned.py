"""The learned solver against ``sensitivity`` and ``homogeneous`` on a family's test split.

    python benchmarks/bench_learned.py --data DIR [DIR ...] [--n-val 50] [--sizes 25 50 ...]
        [--reference ref.json] [--curve benchmarks/learning_curve.png]

DIR: folders (or exported datasets) of generated samples of the family (modes only), e.g. a
release's ``cube_defects-modes`` and extra train instances from ``vvtbench generate FAMILY
--split train --no-video``. The train split trains (nested subsets of the first N train
instances, one model per size, ridge chosen on val), the val split selects, the test split is
scored once per model. All solvers go through the normal plug-in path (``load_solver``) on
the same true-mode observations. ``--reference`` keeps the per-instance scores and times of
the slow reference solvers in a JSON file, so a second run (more train data) reuses them.
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


def main(argv: list[str] | None = None) -> int:
    from solvers.learned import (
        N_REFERENCE,
        LearnedConfig,
        fit_features,
        instance_features,
        predict_w,
        reference_basis,
        save_weights,
        select_ridge,
        voxel_features,
    )
    from vvtbench.plugins import load_solver

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, nargs="+", required=True)
    p.add_argument("--n-val", type=int, default=50)
    p.add_argument("--sizes", type=int, nargs="+", default=[25, 50, 100, 200, 400, 800, 1600])
    p.add_argument("--reference", type=Path, default=None)
    p.add_argument("--references", nargs="*", default=["homogeneous", "sensitivity"])
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
    train, val = [], []
    t0 = time.perf_counter()
    basis = reference_basis([pr for pr, _ in _pairs(args.data, "train", N_REFERENCE)])
    for problem, truth in _pairs(args.data, "train", max(args.sizes)):
        train.append(instance_features(problem, truth, basis))
    for problem, truth in _pairs(args.data, "val", args.n_val):
        val.append(instance_features(problem, truth, basis))
    print(f"features of {len(train)} train + {len(val)} val instances: "
          f"{time.perf_counter() - t0:.0f} s", flush=True)
    test = [(problem, truth, voxel_features(problem, basis)[0])
            for problem, truth in _pairs(args.data, "test")]
    sizes = [s for s in args.sizes if s <= len(train)]
    if len(train) not in sizes:
        sizes.append(len(train))
    rows = []
    args.tmp.mkdir(parents=True, exist_ok=True)
    for size in sizes:
        ridge, val_nc = select_ridge(train[:size], val)
        weights = fit_features(train[:size], basis, ridge)
        nc = [normalized_correlation(predict_w(weights, X, problem.w_mean), truth.w)
              for problem, truth, X in test]
        rows.append({"n_train": size, "ridge": ridge, "val_nc_w": val_nc, "nc_w": nc,
                     "test": mean_ci(nc)})
        print(f"n={size}: ridge {ridge:g} val {val_nc:+.3f} test {rows[-1]['test'][0]:+.3f}",
              flush=True)
    # the largest model once more through the plug-in path: same scores, and the solve time
    path = save_weights(args.tmp / "learned.npz", weights, {"family": "bench",
                                                             "split": "train"})
    solver = load_solver("learned")(LearnedConfig(weights=str(path)))
    secs = []
    for (problem, truth, _), expected in zip(test, rows[-1]["nc_w"], strict=True):
        t = time.perf_counter()
        est = solver.solve(problem)
        secs.append(time.perf_counter() - t)
        assert abs(normalized_correlation(est.w, truth.w) - expected) < 1e-9
    for row in rows:
        row["seconds"] = float(np.median(secs))
    if args.rows is not None:
        from vvtbench.io import write_json

        write_json(args.rows, rows)
    report(rows, ref, args.curve)
    return 0


def report(rows: list[dict], ref: dict, curve: Path) -> None:
    """The learning-curve table (markdown, stdout) and figure."""
    print("\n| train instances | ridge (val) | val NC w | test NC w [95 % CI] | s / instance |")
    print("|---|---|---|---|---|")
    for r in rows:
        m, lo, hi = r["test"]
        print(f"| {r['n_train']} | {r['ridge']:g} | {r['val_nc_w']:+.3f} | "
              f"{m:+.3f} [{lo:+.3f}, {hi:+.3f}] | {r['seconds']:.3f} |")
    for name, d in ref.items():
        m, lo, hi = mean_ci(d["nc_w"])
        k = len(d["nc_w"])
        print(f"| `{name}` ({k} test instances) | | | {m:+.3f} [{lo:+.3f}, "
              f"{hi:+.3f}] | {np.median(d['seconds']):.3f} |")
        if rows and k < len(rows[-1]["nc_w"]):
            m, lo, hi = mean_ci(rows[-1]["nc_w"][:k])
            print(f"| learned ({rows[-1]['n_train']}) on the same {k} | | | {m:+.3f} "
                  f"[{lo:+.3f}, {hi:+.3f}] | |")
    plot_curve(rows, ref, curve)
    print(f"figure: {curve}")


def plot_curve(rows: list[dict], ref: dict, path: Path) -> None:
    """NC w on the test split against the number of train instances."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    n = [r["n_train"] for r in rows]
    m = np.array([r["test"] for r in rows])
    ax.errorbar(n, m[:, 0], yerr=[m[:, 0] - m[:, 1], m[:, 2] - m[:, 0]], marker="o",
                capsize=3, label="learned (test, 95 % CI)")
    ax.plot(n, [r["val_nc_w"] for r in rows], "s--", color="0.5", label="learned (val)")
    colors = {"sensitivity": "C3", "homogeneous": "k"}
    for name, d in ref.items():
        mean, lo, hi = mean_ci(d["nc_w"])
        c = colors.get(name, "C2")
        ax.axhline(mean, color=c, lw=1.2, label=f"{name} (test)")
        ax.axhspan(lo, hi, color=c, alpha=0.12)
    ax.set_xscale("log")
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
