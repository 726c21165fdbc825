"""The learned solver against ``sensitivity`` and ``homogeneous`` on a family's test split.

    python benchmarks/bench_learned.py --store STORE --data TEST_DIR [--n-val 50]
        [--sizes 25 50 ...] [--reference ref.json] [--test-features test.npz]
        [--choose-steps 1000 2500] [--time-at 20000] [--rows R.json]
        [--curve benchmarks/learning_curve.png]
    python benchmarks/bench_learned.py --data DIR [DIR ...] [--features feats.npz] ...

STORE: a feature store of the family (``vvtbench train learned FAMILY --drop-instances
--features STORE``): the train instances (nested subsets of the first N, one network ensemble
per size, every size up to the largest stored) and the val instances come from it, featurized
against its basis; TEST_DIR holds the test split's samples (modes only, e.g. a release's
``cube_defects-modes``), featurized against the same basis. Without ``--store``, DIR folders
hold all three splits as samples and ``--features`` keeps their features in an ``.npz``.

The val split selects (the architecture and ``--choose-steps``: the bounded training cost,
scored on val only), the test split is scored once per size, each mean with a bootstrap 95 %
interval over the test instances. All solvers go through the normal plug-in path
(``load_solver``) on the same true-mode observations. ``--reference`` keeps the per-instance
scores and times of the slow reference solvers in a JSON file, so a second run reuses them.
``--time-at N`` times one network's epoch on the stored train voxels repeated to N instances'
worth (the fit time and peak memory at that size). ``--previous`` scores an older weights file
of the linear model ("modal-step-ridge") on the same val and test instances. Prints the
learning-curve table (markdown) and writes the curve figure. An instance whose truth is uniform
(no defect) has no NC: its per-instance value is null and it is in no mean.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from vvtbench.datasets.instances import iter_instances
from vvtbench.scoring.metrics import normalized_correlation

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
    from vvtbench.solving.plugins import load_solver

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
            nc.append(instance_nc(est.w, truth.w))
            print(f"{name}: {len(nc)} nc_w {nc[-1]} {secs[-1]:.2f} s", flush=True)
        done[name] = {"nc_w": nc, "seconds": secs}
        if cache is not None:
            from vvtbench.io.files import write_json

            write_json(cache, done)
    return done


def instance_nc(estimate, truth) -> float | None:
    """NC w of one instance; None for a uniform truth (NC undefined: never scored as 0)."""
    from vvtbench.scoring.metrics import is_constant

    return None if is_constant(truth) else normalized_correlation(estimate, truth)


def mean_ci(values) -> tuple[float, float, float]:
    """Mean and its 95 % bootstrap interval (the leaderboard's, :mod:`vvtbench.scoring.stats`) of
    the
    defined values (None left out)."""
    from vvtbench.scoring.stats import bootstrap_ci

    x = np.array([v for v in values if v is not None], dtype=float)
    return (float(x.mean()), *bootstrap_ci(x))


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
        from vvtbench.io.files import write_npz

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


def store_features(store_dir: Path, roots: list[Path], n_val: int, cache: Path | None
                   ) -> tuple:
    """The store, its train and val entries, and the test split's features against the
    store's basis (kept in ``cache``, keyed by the basis)."""
    from vvtbench.learning.feature_store import FeatureStore

    store = FeatureStore.open(store_dir)
    basis_sha = store.meta["basis_sha256"]
    test = None
    if cache is not None and cache.is_file():
        with np.load(cache, allow_pickle=False) as z:
            if str(z["basis_sha256"]) == basis_sha:
                test = {k: z[k] for k in ("X", "w", "names")}
    if test is None:
        t0 = time.perf_counter()
        test = split_features(roots, "test", None, store.basis)
        print(f"features of {len(test['X'])} test instances: {time.perf_counter() - t0:.0f} s",
              flush=True)
        if cache is not None:
            from vvtbench.io.files import write_npz

            write_npz(cache, {**test, "basis_sha256": np.array(basis_sha)})
    return store, store.entries("train"), store.select("val", 0, n_val), test


def time_at_scale(store, n_instances: int, members: int = 1) -> dict:
    """One network trained for one epoch on the stored train voxels repeated to
    ``n_instances`` instances' worth: seconds per epoch and Adam step, and peak memory."""
    import resource

    from solvers.learned import BATCH, HIDDEN, standardized
    from vvtbench.learning.mlp import fit_mlp

    X, y = [], []
    entries = store.entries("train")
    for _, a in store.iter_arrays(entries, ("X", "w")):
        t = standardized(a["w"])
        if t is not None:  # a uniform truth has no target: as many left out as in the store
            X.append(a["X"])
            y.append(t)
    rows = int(n_instances * sum(len(t) for t in y) / len(entries))
    reps = -(-rows // sum(len(t) for t in y))
    X = np.tile(np.vstack(X), (reps, 1))[:rows]
    y = np.tile(np.concatenate(y), reps)[:rows]
    t0, c0 = time.perf_counter(), time.process_time()
    for seed in range(members):
        fit_mlp(X, y, hidden=HIDDEN, epochs=1, batch=BATCH, seed=seed)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    steps = members * -(-rows // BATCH)
    return {"n_instances": n_instances, "rows": rows, "features_gb": X.nbytes / 2**30,
            "epoch_seconds": wall / members, "epoch_cpu_seconds": cpu / members,
            "seconds_per_step": wall / steps,
            "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20}


def main(argv: list[str] | None = None) -> int:
    from solvers.learned import (
        EPOCHS,
        MAX_STEPS,
        MEMBERS,
        LearnedConfig,
        fit_features,
        fit_store,
        load_weights,
        mean_nc,
        predict_w,
        save_weights,
    )
    from vvtbench.solving.plugins import load_solver

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, nargs="+", required=True)
    p.add_argument("--store", type=Path, default=None,
                   help="feature store: train and val from it, test from --data")
    p.add_argument("--test-features", type=Path, default=None,
                   help="with --store: keep the test split's features in this .npz")
    p.add_argument("--choose-steps", type=int, nargs="*", default=[],
                   help="max_steps values fitted at the largest size and scored on val only")
    p.add_argument("--time-at", type=int, nargs="*", default=[],
                   help="instances' worth of voxels to time one epoch of one network on")
    p.add_argument("--only-time", action="store_true", help="stop after --time-at")
    p.add_argument("--plugin", type=int, default=5,
                   help="test instances solved again through load_solver (0: none)")
    p.add_argument("--n-val", type=int, default=50)
    p.add_argument("--sizes", type=int, nargs="*", default=None,
                   help="train-set sizes to fit (default: 25 to 20 000, those the data "
                   "holds, and every instance it holds; none with --score-weights alone)")
    p.add_argument("--score-weights", type=Path, nargs="*", default=[],
                   help="with --store: weights files written by `vvtbench train` from the "
                   "same store, each scored on the test split as one more row of the curve "
                   "(its size, fit time and val score from its training record)")
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
    p.add_argument("--label", default="learned", help="the model's name in the figure")
    p.add_argument("--earlier", nargs=2, metavar=("ROWS", "LABEL"), default=None,
                   help="with --replot: another model's rows (JSON), drawn beside")
    args = p.parse_args(argv)
    if args.score_weights and args.store is None:
        p.error("--score-weights needs --store")
    try:
        scored = {path: load_weights(path) for path in args.score_weights}
    except (OSError, ValueError) as err:
        p.error(str(err))
    if args.replot:
        ref = json.loads(args.reference.read_text())
        earlier = ((args.earlier[1], json.loads(Path(args.earlier[0]).read_text()))
                   if args.earlier else None)
        report(json.loads(args.rows.read_text()), ref, args.curve, args.label, earlier)
        return 0

    if args.store is not None:
        for n in args.time_at:
            from vvtbench.learning.feature_store import FeatureStore

            timing = time_at_scale(FeatureStore.open(args.store), n)
            print(f"one network, one epoch at {n} instances' voxels ({timing['rows']} rows, "
                  f"{timing['features_gb']:.2f} GB of features): {timing['epoch_seconds']:.0f}"
                  f" s wall, {timing['epoch_cpu_seconds']:.0f} s CPU, "
                  f"{1000 * timing['seconds_per_step']:.1f} ms per step, peak RSS "
                  f"{timing['peak_rss_gb']:.2f} GB", flush=True)
        if args.only_time:
            return 0
    ref = reference_scores(args.data, args.references, args.reference)
    if args.store is not None:
        store, train_entries, val_entries, test_feats = store_features(
            args.store, args.data, args.n_val, args.test_features)
        n_train, basis = len(train_entries), store.basis

        def fitted(size: int, max_steps: int = MAX_STEPS) -> dict:
            return fit_store(store, train_entries[:size], val_entries, MEMBERS, EPOCHS,
                             max_steps)

        test = items_of({"test_X": test_feats["X"], "test_w": test_feats["w"]}, "test")
        val = None
    else:
        feats = cached_features(args.data, max(args.sizes), args.n_val, args.features)
        basis = feats["basis"]
        train, val, test = (items_of(feats, s) for s in ("train", "val", "test"))
        n_train = len(train)

        def fitted(size: int, max_steps: int = MAX_STEPS) -> dict:
            weights = fit_features(train[:size], basis, MEMBERS, EPOCHS, max_steps)
            weights["val_nc_w"] = mean_nc(weights, val)
            return weights

    if args.sizes is None:
        sizes = [s for s in (25, 50, 100, 200, 400, 1000, 2000, 5000, 10000, 20000)
                 if s < n_train] + [n_train]
    else:
        sizes = [s for s in args.sizes if s <= n_train]
        if len(sizes) < len(args.sizes):
            print(f"sizes above the {n_train} train instances left out", flush=True)
    rows = []
    args.tmp.mkdir(parents=True, exist_ok=True)
    if args.previous is not None and val is not None:
        old, meta = load_weights(args.previous)
        old = {**old, "model": meta.get("model")}
        for split, items in (("val", val), ("test", test)):
            nc = [instance_nc(predict_w(old, ridge_inputs(it["X"]), 1.0), it["w"])
                  for it in items]
            print(f"previous ({meta.get('model')} {meta.get('solver_version')}, "
                  f"{meta.get('n_instances')} train) {split} NC w {mean_ci(nc)}", flush=True)
        ref = {**ref, f"learned {meta.get('solver_version')}": {"nc_w": nc, "seconds": []}}
    models = {}
    for size in sizes:
        t0 = time.perf_counter()
        weights = models[size] = fitted(size)
        fit_s = time.perf_counter() - t0
        nc = [instance_nc(predict_w(weights, it["X"], 1.0), it["w"]) for it in test]
        rows.append({"n_train": size, "val_nc_w": weights["val_nc_w"], "nc_w": nc,
                     "test": mean_ci(nc), "fit_seconds": fit_s,
                     "epochs": float(weights["epochs"]), "steps": int(weights["steps"]),
                     "n_voxels": int(weights["n_voxels"])})
        print(f"n={size}: fit {fit_s:.0f} s ({weights['epochs']} epochs) val "
              f"{weights['val_nc_w']:+.3f} test {rows[-1]['test'][0]:+.3f}", flush=True)
        if args.rows is not None:
            from vvtbench.io.files import write_json

            write_json(args.rows, rows)
    for path, (arrays, meta) in scored.items():
        weights = models[int(meta["n_instances"])] = {**meta, **arrays}
        if not np.array_equal(arrays.get("basis"), basis):
            p.error(f"{path}: trained against another basis than {args.store}'s")
        nc = [instance_nc(predict_w(weights, it["X"], 1.0), it["w"]) for it in test]
        rows.append({"n_train": int(meta["n_instances"]), "val_nc_w": meta.get("val_nc_w"),
                     "nc_w": nc, "test": mean_ci(nc), "fit_seconds": meta.get("fit_seconds"),
                     "epochs": float(weights["epochs"]), "steps": int(weights["steps"]),
                     "n_voxels": int(weights["n_voxels"]), "weights": str(path)})
        print(f"n={rows[-1]['n_train']} ({path}): val {rows[-1]['val_nc_w']:+.3f} test "
              f"{rows[-1]['test'][0]:+.3f}", flush=True)
    rows.sort(key=lambda r: r["n_train"])
    if not rows:
        p.error("no size to fit and no weights to score")
    choices = []
    for max_steps in args.choose_steps if sizes else []:  # val only: test is not scored
        t0 = time.perf_counter()
        alt = fitted(sizes[-1], max_steps)
        choices.append({"n_train": sizes[-1], "max_steps": max_steps,
                        "epochs": float(alt["epochs"]), "steps": int(alt["steps"]),
                        "val_nc_w": alt["val_nc_w"],
                        "fit_seconds": time.perf_counter() - t0})
        print(f"n={sizes[-1]} max_steps={max_steps}: {alt['epochs']} epochs, fit "
              f"{choices[-1]['fit_seconds']:.0f} s, val {alt['val_nc_w']:+.3f}", flush=True)
    # the largest model once more through the plug-in path: same scores, and the solve time
    if rows[-1].get("weights"):
        path = Path(rows[-1]["weights"])
    else:
        path = save_weights(args.tmp / "learned.npz", models[rows[-1]["n_train"]],
                            {"family": "bench", "split": "train"})
    solver = load_solver("learned")(LearnedConfig(weights=str(path)))
    secs, cpu = [], []
    for (problem, truth), expected in zip(_pairs(args.data, "test", args.plugin),
                                          rows[-1]["nc_w"], strict=False):
        t, c = time.perf_counter(), time.process_time()
        est = solver.solve(problem)
        secs.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
        got = instance_nc(est.w, truth.w)
        assert (got is None) == (expected is None) and (got is None or abs(got - expected) < 1e-9)
    if secs:
        print(f"plug-in solve of the {rows[-1]['n_train']}-instance model ({len(secs)} test "
              f"instances): median {np.median(secs):.3f} s wall, {np.median(cpu):.3f} s CPU",
              flush=True)
    for row in rows:
        row["seconds"] = float(np.median(secs)) if secs else None
        row["cpu_seconds"] = float(np.median(cpu)) if cpu else None
    if args.rows is not None:
        from vvtbench.io.files import write_json

        write_json(args.rows, rows)
        if choices:
            write_json(args.rows.with_name(args.rows.stem + "-choices.json"), choices)
    report(rows, ref, args.curve)
    return 0


def report(rows: list[dict], ref: dict, curve: Path, label: str = "learned",
           earlier: tuple[str, list[dict]] | None = None) -> None:
    """The learning-curve table (markdown, stdout) and figure; ``earlier``: (label, rows) of
    another model's curve drawn beside it."""
    print("\n| train instances | epochs | fit (s) | val NC w | test NC w [95 % CI] | "
          "s / instance |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        m, lo, hi = r["test"]
        t = f"{r['cpu_seconds']:.3f} CPU" if r.get("cpu_seconds") is not None else ""
        fit = f"{r['fit_seconds']:.0f}" if r.get("fit_seconds") is not None else ""
        print(f"| {r['n_train']} | {r.get('epochs', '')} | {fit} | "
              f"{r['val_nc_w']:+.3f} | {m:+.3f} [{lo:+.3f}, {hi:+.3f}] | {t} |")
    for name, d in ref.items():
        m, lo, hi = mean_ci(d["nc_w"])
        k = sum(v is not None for v in d["nc_w"])
        t = f"{np.median(d['seconds']):.3f}" if d["seconds"] else ""
        print(f"| `{name}` ({k} test instances with a defect) | | | | {m:+.3f} [{lo:+.3f}, "
              f"{hi:+.3f}] | {t} |")
        if rows and len(d["nc_w"]) < len(rows[-1]["nc_w"]):
            m, lo, hi = mean_ci(rows[-1]["nc_w"][:len(d["nc_w"])])
            print(f"| learned ({rows[-1]['n_train']}) on the same {k} | | | | {m:+.3f} "
                  f"[{lo:+.3f}, {hi:+.3f}] | |")
    plot_curve(rows, ref, curve, label, earlier)
    print(f"figure: {curve}")


def plot_curve(rows: list[dict], ref: dict, path: Path, label: str = "learned",
               earlier: tuple[str, list[dict]] | None = None) -> None:
    """NC w on the test split against the number of train instances (and ``earlier``'s: a
    (label, rows) pair of another model, its test means with their intervals)."""
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 5))
    n = [r["n_train"] for r in rows]
    m = np.array([r["test"] for r in rows])
    k = sum(v is not None for v in rows[-1]["nc_w"]) if rows else 0
    ax.fill_between(n, m[:, 1], m[:, 2], color="C0", alpha=0.18, lw=0)
    ax.errorbar(n, m[:, 0], yerr=[m[:, 0] - m[:, 1], m[:, 2] - m[:, 0]], marker="o",
                capsize=3, color="C0", label=f"{label} (test mean, {k} instances with a defect)")
    ax.plot(n, [r["val_nc_w"] for r in rows], "s--", color="0.5", label=f"{label} (val mean)")
    ticks = set(n)
    if earlier is not None:
        name, old = earlier
        n0 = [r["n_train"] for r in old]
        m0 = np.array([r["test"] for r in old])
        ax.errorbar(n0, m0[:, 0], yerr=[m0[:, 0] - m0[:, 1], m0[:, 2] - m0[:, 0]], marker="^",
                    capsize=3, color="C1", alpha=0.8, label=f"{name} (test mean)")
        ticks |= set(n0)
    colors = {"sensitivity": "C3", "homogeneous": "k", "learned 2.0.0": "C2"}
    for name, d in ref.items():
        mean, lo, hi = mean_ci(d["nc_w"])
        c = colors.get(name, "C2")
        ax.axhline(mean, color=c, lw=1.2, label=f"{name} (test)")
        ax.axhspan(lo, hi, color=c, alpha=0.12)
        if name == "sensitivity":
            ax.axhline(mean - 0.05, color=c, lw=1.0, ls=":",
                       label="target: sensitivity's mean - 0.05")
    ax.set_xscale("log")
    ax.set_xticks(sorted(ticks), [str(k) for k in sorted(ticks)])
    ax.xaxis.set_minor_locator(matplotlib.ticker.NullLocator())
    ax.set_xlabel("train instances\nbars and bands: bootstrap 95 % interval of the mean over "
                  "the test instances (2000 resamples)", fontsize=9)
    ax.set_ylabel("mean NC of w (test split, true modes)")
    ax.set_title("learned solver: cube_defects learning curve")
    ax.legend(fontsize=8, loc="upper left")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
