"""``vvtbench train SOLVER FAMILY``: fit a learned solver on a family's train split."""

from __future__ import annotations

import argparse
import hashlib
import importlib
import sys
import time
from pathlib import Path

from .._version import __version__
from .args import MAX_INSTANCES, bounded, instance_count, positive_int


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="vvtbench train", description=(
        "generate the train split of a scene family (modes only, resumable) and fit a "
        "learned solver on it, or (--drop-instances) keep only each instance's training "
        "features in a resumable store; the weights file records the family, split, "
        "instances and seeds it saw (docs/learning.md)"))
    p.add_argument("solver", help="a solver whose module has fit() and save_weights() "
                   "(shipped: learned)")
    p.add_argument("family", help="a scene family (scenes/families/NAME.toml) or its file")
    p.add_argument("-o", "--output", required=True, type=Path, help="the weights file (.npz)")
    from ..scene.families import MAX_INDEX

    p.add_argument("--n", type=instance_count, default=200, help="train instances (200)")
    p.add_argument("--start", type=bounded(int, ge=0, le=MAX_INDEX), default=0,
                   help="first instance (0)")
    p.add_argument("--val", type=bounded(int, ge=0, le=MAX_INSTANCES), default=50,
                   help="val instances for model selection (50; 0: none)")
    p.add_argument("--data", type=Path, default=None,
                   help="where the train instances are generated (default data/FAMILY/train)")
    p.add_argument("--modes", type=positive_int, default=20, help="observed modes (20)")
    p.add_argument("--grid", type=bounded(int, ge=1, le=256), nargs="+", default=None,
                   help="inference voxel grid (default 8 8 8; drums 20 20)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="training option of the solver (e.g. members=3)")
    p.add_argument("--workers", type=positive_int, default=1,
                   help="generation workers, with --drop-instances also featurizing (1)")
    p.add_argument("--drop-instances", action="store_true",
                   help="featurize and drop: generate each train and val instance into the "
                   "feature store's scratch folder, keep only its training features (a "
                   "resumable store of shards) and delete the instance; for tens of thousands "
                   "of instances (docs/learning.md)")
    p.add_argument("--features", type=Path, default=None, metavar="DIR",
                   help="the feature store with --drop-instances (default "
                   "data/FAMILY/train-features)")
    return p


def main_train(argv: list[str] | None = None) -> int:
    from ..datasets.instances import iter_instances
    from ..scene.families import check_index_range, load_family
    from ..solving.plugins import load_solver, parse_overrides
    from .generate import main as generate_main

    args = build_parser().parse_args(argv)
    check_index_range(args.start, args.n)
    cls = load_solver(args.solver)
    module = importlib.import_module(cls.__module__)
    if not (hasattr(module, "fit") and hasattr(module, "save_weights")):
        print(f"error: solver {cls.name!r} is not trainable (its module has no fit() and "
              "save_weights())", file=sys.stderr)
        return 2
    config = parse_overrides(args.overrides, cls.Config)
    family = load_family(args.family)
    if args.output.suffix != ".npz":
        print(f"error: -o {args.output}: the weights file must end in .npz", file=sys.stderr)
        return 2
    options = {"n_modes": args.modes, "visibility": "depth",
               **({"inference_shape": tuple(args.grid)} if args.grid else {})}
    kwargs = {k: v for k, v in vars(config).items() if k != "weights"}
    digest = hashlib.sha256(Path(family.source).read_bytes()).hexdigest()
    meta = {"family": family.name, "family_sha256": digest, "split": "train",
            "indices": [args.start, args.start + args.n - 1], "observe": options,
            "vvtbench": __version__, "solver": cls.name, "seed": "instance i of a split is "
            "drawn from (family, split, i) alone (docs/families.md)"}
    if args.drop_instances:
        return _train_from_store(args, cls, module, family, options, kwargs, meta)
    if args.features is not None:
        print(f"error: --features {args.features}: the feature store is written with "
              "--drop-instances", file=sys.stderr)
        return 2
    data = args.data or Path("data") / family.name / "train"
    t0 = time.perf_counter()
    rc = generate_main([str(family.source), "--split", "train", "--n", str(args.n),
                        "--start", str(args.start), "-o", str(data), "--no-video",
                        "--workers", str(args.workers), "--no-progress"])
    if rc:
        return rc
    val_data = data.parent / "val" if data.name == "train" else data.parent / f"{data.name}-val"
    if args.val:
        rc = generate_main([str(family.source), "--split", "val", "--n", str(args.val),
                            "-o", str(val_data), "--no-video", "--workers", str(args.workers),
                            "--no-progress"])
        if rc:
            return rc
    chosen = _chosen(data, family.name, "train", args.start, args.n)
    held = _chosen(val_data, family.name, "val", 0, args.val) if args.val else []
    if held:
        kwargs["val"] = (pair for _, src in held for pair in iter_instances(src, None, **options))
    t_fit = time.perf_counter()
    weights = module.fit((pair for _, src in chosen
                          for pair in iter_instances(src, None, **options)), **kwargs)
    fit_seconds = time.perf_counter() - t_fit
    meta.update({"instances": [name for name, _ in chosen], "generated_in": str(data),
                 "train_sha256": _split_digest(chosen), "fit_seconds": fit_seconds})
    if held:
        meta.update({"val_split": "val", "val_instances": [name for name, _ in held],
                     "val_sha256": _split_digest(held)})
    return _save(args, cls, module, weights, meta,
                 f"{len(chosen)} {family.name} train instances", t0)


def _save(args, cls, module, weights, meta: dict, what: str, t0: float) -> int:
    args.output.parent.mkdir(parents=True, exist_ok=True)
    module.save_weights(args.output, weights, meta)
    print(f"{cls.name}: trained on {what} in {time.perf_counter() - t0:.0f} s -> "
          f"{args.output} (use: --set weights={args.output})")
    return 0


def _train_from_store(args, cls, module, family, options: dict, kwargs: dict, meta: dict
                      ) -> int:
    """``--drop-instances``: build (or resume) the feature store, then fit from it."""
    from ..learning.feature_store import StoreSpec, build_store

    hooks = ("fit_store", "instance_features", "reference_basis", "N_REFERENCE",
             "STORED_FEATURES")
    missing = [h for h in hooks if not hasattr(module, h)]
    if missing:
        print(f"error: solver {cls.name!r} cannot train from a feature store (its module has "
              f"no {', '.join(missing)}); train without --drop-instances", file=sys.stderr)
        return 2
    if args.data is not None:
        print(f"error: --data {args.data}: with --drop-instances the instances are generated "
              "into the feature store's own scratch folder and deleted; give the store with "
              "--features DIR", file=sys.stderr)
        return 2
    root = args.features or Path("data") / family.name / "train-features"
    spec = StoreSpec(solver=cls.name, module=cls.__module__, solver_version=cls.version,
                     model=str(getattr(module, "MODEL", cls.version)),
                     family=str(family.source), family_name=family.name, observe=options,
                     reference_start=args.start)
    plan = {**({"val": (0, args.val)} if args.val else {}), "train": (args.start, args.n)}
    t0 = time.perf_counter()
    try:
        store = build_store(root, spec, plan, workers=args.workers,
                            log=lambda line: print(line, flush=True))
    except RuntimeError as error:
        print(f"error: {error}", file=sys.stderr)
        return 1
    train = store.select("train", args.start, args.n)
    held = store.select("val", 0, args.val) if args.val else []
    t_fit = time.perf_counter()
    weights = module.fit_store(store, train, held, **kwargs)
    meta.update({"instances": [e.name for e in train], "train_store": store.record(train),
                 "fit_seconds": time.perf_counter() - t_fit})
    if held:
        meta.update({"val_split": "val", "val_instances": [e.name for e in held],
                     "val_store": store.record(held)})
    return _save(args, cls, module, weights, meta,
                 f"{len(train)} {family.name} train instances from the feature store {root}", t0)


def _chosen(data: Path, family: str, split: str, start: int, n: int) -> list:
    from ..datasets.instances import instances

    wanted = set(range(start, start + n))
    return [(name, src) for name, src in instances(data, split)
            if name.startswith(f"{family}-{split}-") and int(name.rsplit("-", 1)[1]) in wanted]


def _split_digest(chosen: list) -> str:
    """sha256 over the instances' names and manifests (each sample's files and their sha256)."""
    digest = hashlib.sha256()
    for name, src in chosen:
        digest.update(name.encode())
        manifest = Path(src) / "manifest.json" if isinstance(src, Path) else None
        if manifest is not None and manifest.is_file():
            digest.update(manifest.read_bytes())
    return digest.hexdigest()
