"""``vvtbench challenge`` (problems out, truth kept) and ``vvtbench score`` (a submission of
estimates scored against truth the submitter does not hold)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .args import explain, positive_int


def main_challenge(argv: list[str] | None = None) -> int:
    """``vvtbench challenge SAMPLES -o DIR``: observe every sample under SAMPLES and write
    ``DIR/problems`` (to hand out) and ``DIR/truth`` (to keep)."""
    from ..bench.submission import SubmissionError, write_challenge
    from ..datasets.export import find_samples
    from ..observe import ObserveError, observe
    from ..samples.reader import DatasetError, open_sample

    p = argparse.ArgumentParser(prog="vvtbench challenge",
                                description="write a hidden-truth challenge from generated "
                                "samples: DIR/problems to hand out, DIR/truth to keep")
    p.add_argument("samples", help="a folder of samples (e.g. `vvtbench generate FAMILY "
                   "--split test -o DIR`)")
    p.add_argument("-o", "--output", required=True, help="a new folder")
    p.add_argument("--modes", type=positive_int, default=10, help="observed modes (10)")
    p.add_argument("--name", default=None, help="the challenge's name (default: the folder's)")
    args = p.parse_args(argv)
    found = find_samples(args.samples)
    if not found:
        print(f"error: {args.samples}: no sample folders (manifest.json + truth.json) under it",
              file=sys.stderr)
        return 2
    out = Path(args.output)
    name = args.name or Path(args.samples).resolve().name

    def instances():
        for path in found:
            problem, truth = observe(open_sample(path), observation="true", n_modes=args.modes)
            yield path.name, problem, truth

    try:
        n = write_challenge(instances(), out / "problems", out / "truth", name)
    except (SubmissionError, DatasetError, ObserveError) as error:
        print(f"error: {explain(error)}", file=sys.stderr)
        return 2
    print(f"{n} instances -> {out / 'problems'} (hand out) and {out / 'truth'} (keep private)")
    print(f"next: `vvtbench solve SOLVER {out / 'problems'} -o SUBMISSION`, then "
          f"`vvtbench score SUBMISSION --truth {out / 'truth'} -o SCORES`")
    return 0


def main_score(argv: list[str] | None = None) -> int:
    """``vvtbench score SUBMISSION --truth TRUTH -o OUT``: exit 0 when every instance was
    answered with a valid estimate, 1 otherwise, 2 for unreadable folders."""
    from ..bench.results import write_results
    from ..bench.submission import SubmissionError, score_submission
    from .run import format_table

    p = argparse.ArgumentParser(prog="vvtbench score",
                                description="score a submission (a folder of estimates with a "
                                "manifest) against the private truth of a challenge; the scores "
                                "are computed here from the estimates, never read from the "
                                "submission")
    p.add_argument("submission", help="the submission folder (manifest.json + estimates)")
    p.add_argument("--truth", required=True, help="the challenge's private truth folder")
    p.add_argument("-o", "--output", required=True,
                   help="folder for results.parquet and results.csv (not inside the "
                   "submission or the truth)")
    args = p.parse_args(argv)
    sub, truth, out = Path(args.submission), Path(args.truth), Path(args.output)
    for inside in (sub, truth):
        if out.resolve() == inside.resolve() or inside.resolve() in out.resolve().parents:
            print(f"error: -o {out}: inside {inside}; give another folder", file=sys.stderr)
            return 2
    try:
        df = score_submission(sub, truth)
    except SubmissionError as error:
        print(f"error: {explain(error)}", file=sys.stderr)
        return 2
    out.mkdir(parents=True, exist_ok=True)
    write_results(df, out)
    print(format_table(df))
    extra = df.attrs.get("extra_estimates") or []
    if extra:
        print(f"ignored: {len(extra)} estimate(s) for instances the truth does not have")
    bad = df[df.status != "ok"]
    print(f"\n{len(df)} instances scored from the estimates -> {out / 'results.parquet'}")
    if len(bad):
        print(f"error: {len(bad)} of {len(df)} instances not scored (missing, invalid or "
              "unreadable estimates); see above", file=sys.stderr)
        return 1
    return 0
