"""``vvtbench train SOLVER FAMILY``: fit a learned solver on a family's train split."""

from __future__ import annotations

import argparse
import hashlib
import importlib
import sys
import time
from pathlib import Path

from .._version import __version__
from . import bounded, positive_int


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="vvtbench train", description=(
        "generate the train split of a scene family (modes only, resumable) and fit a "
        "learned solver on it; the weights file records the family, split, instances and "
        "seeds it saw (docs/learning.md)"))
    p.add_argument("solver", help="a solver whose module has fit() and save_weights() "
                   "(shipped: learned)")
    p.add_argument("family", help="a scene family (scenes/families/NAME.toml) or its file")
    p.add_argument("-o", "--output", required=True, type=Path, help="the weights file (.npz)")
    p.add_argument("--n", type=positive_int, default=200, help="train instances (200)")
    p.add_argument("--start", type=bounded(int, ge=0), default=0, help="first instance (0)")
    p.add_argument("--data", type=Path, default=None,
                   help="where the train instances are generated (default data/FAMILY/train)")
    p.add_argument("--modes", type=positive_int, default=20, help="observed modes (20)")
    p.add_argument("--grid", type=bounded(int, ge=1, le=256), nargs="+", default=None,
                   help="inference voxel grid (default 8 8 8; drums 20 20)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="training option of the solver (e.g. ridge=1.0)")
    p.add_argument("--workers", type=positive_int, default=1, help="generation workers (1)")
    return p


def main_train(argv: list[str] | None = None) -> int:
    from ..data import instances, iter_instances
    from ..families import load_family
    from ..plugins import load_solver, parse_overrides
    from .generate import main as generate_main

    args = build_parser().parse_args(argv)
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
    data = args.data or Path("data") / family.name / "train"
    t0 = time.perf_counter()
    rc = generate_main([str(family.source), "--split", "train", "--n", str(args.n),
                        "--start", str(args.start), "-o", str(data), "--no-video",
                        "--workers", str(args.workers), "--no-progress"])
    if rc:
        return rc
    wanted = set(range(args.start, args.start + args.n))
    chosen = [(name, src) for name, src in instances(data, "train")
              if name.startswith(f"{family.name}-train-") and int(name.rsplit("-", 1)[1])
              in wanted]
    options = {"n_modes": args.modes, "visibility": "depth",
               **({"inference_shape": tuple(args.grid)} if args.grid else {})}
    weights = module.fit((pair for _, src in chosen
                          for pair in iter_instances(src, None, **options)),
                         **{k: v for k, v in vars(config).items() if k != "weights"})
    digest = hashlib.sha256(Path(family.source).read_bytes()).hexdigest()
    meta = {"family": family.name, "family_sha256": digest, "split": "train",
            "indices": [args.start, args.start + args.n - 1],
            "instances": [name for name, _ in chosen], "observe": options,
            "vvtbench": __version__, "solver": cls.name, "generated_in": str(data)}
    args.output.parent.mkdir(parents=True, exist_ok=True)
    module.save_weights(args.output, weights, meta)
    print(f"{cls.name}: trained on {len(chosen)} {family.name} train instances in "
          f"{time.perf_counter() - t0:.0f} s -> {args.output} (use: --set "
          f"weights={args.output})")
    return 0
