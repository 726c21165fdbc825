"""``vvtbench challenge`` (problems out, truth kept) and ``vvtbench score`` (a submission of
estimates scored against truth the submitter does not hold)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .args import explain, positive_int


def _fail(message) -> int:
    print(f"error: {explain(message)}", file=sys.stderr)
    return 2


def main_challenge(argv: list[str] | None = None) -> int:
    """``vvtbench challenge FAMILY --n N -o DIR``: a challenge of record, drawn from a new
    secret; ``vvtbench challenge SAMPLES -o DIR``: a public one from generated samples. Both
    write ``DIR/problems`` (to hand out) and ``DIR/truth`` (to keep)."""
    from ..bench.submission import SubmissionError, challenge_of_record, write_challenge
    from ..datasets.export import find_samples
    from ..observe import ObserveError, observe
    from ..samples.reader import DatasetError, open_sample
    from ..scene.families import is_family
    from ..scene.scene import SceneError

    p = argparse.ArgumentParser(
        prog="vvtbench challenge",
        description="write a hidden-truth challenge: DIR/problems to hand out, DIR/truth to "
        "keep. From a FAMILY, a challenge of record: --n instances drawn from a new secret "
        "kept only in DIR/truth, opaque ids, nothing in a problem that regenerates its scene. "
        "From a folder of SAMPLES, a public one (anyone can regenerate those instances: for "
        "development only)")
    p.add_argument("source", help="a family (shipped name or .toml: a challenge of record), or "
                   "a folder of samples (`vvtbench generate ...`: public instances)")
    p.add_argument("-o", "--output", required=True, help="a new folder")
    p.add_argument("--n", type=positive_int, default=None,
                   help="instances to draw from the family (required with a family)")
    p.add_argument("--modes", type=positive_int, default=10, help="observed modes (10)")
    p.add_argument("--name", default=None, help="the challenge's name, its rows' track "
                   "(default: the family's, or the samples folder's)")
    args = p.parse_args(argv)
    out = Path(args.output)
    if out.is_symlink() or (out.exists() and (not out.is_dir() or any(out.iterdir()))):
        return _fail(f"-o {out}: exists and is not an empty folder; give a new folder")
    source = Path(args.source)
    if not source.is_dir():
        if not is_family(args.source):
            return _fail(f"{args.source}: neither a folder of samples nor a family (a shipped "
                         "family name or a family .toml)")
        if args.n is None:
            return _fail("--n: a challenge of record needs the number of instances to draw "
                         "(e.g. --n 50)")
        try:
            n = challenge_of_record(
                args.source, args.n, out, name=args.name,
                observe_options={"n_modes": args.modes},
                progress=lambda k, total: print(f"  drawn and observed {k}/{total}",
                                                flush=True))
        except (SubmissionError, SceneError, ObserveError, ValueError) as error:
            return _fail(error)
        print(f"{n} instances drawn from a new secret -> {out / 'problems'} (hand out) and "
              f"{out / 'truth'} (keep private: it holds the secret, secret.key)")
        _next(out)
        return 0
    if args.n is not None:
        return _fail("--n: only with a family (a folder of samples gives every sample in it)")
    found = find_samples(args.source)
    if not found:
        return _fail(f"{args.source}: no sample folders (manifest.json + truth.json) under it")
    name = args.name or source.resolve().name
    existed = out.exists()

    def instances():
        for path in found:
            problem, truth = observe(open_sample(path), observation="true", n_modes=args.modes)
            yield path.name, problem, truth

    try:
        n = write_challenge(instances(), out / "problems", out / "truth", name)
    except (SubmissionError, DatasetError, ObserveError) as error:
        if not existed and out.is_dir() and not any(out.iterdir()):
            out.rmdir()
        return _fail(error)
    print(f"{n} instances -> {out / 'problems'} (hand out) and {out / 'truth'} (keep private)")
    print("note: these instances are public (anyone can regenerate them from the repository); "
          "their rows say split_kind=public. For a result of record give a family: "
          "`vvtbench challenge FAMILY --n N -o DIR`")
    _next(out)
    return 0


def _next(out: Path) -> None:
    print(f"next: `vvtbench solve SOLVER {out / 'problems'} -o SUBMISSION`, then "
          f"`vvtbench score SUBMISSION --truth {out / 'truth'} -o SCORES`")


def main_score(argv: list[str] | None = None) -> int:
    """``vvtbench score SUBMISSION --truth TRUTH -o OUT``: exit 0 when every instance was
    answered with a valid estimate, 1 otherwise, 2 for unreadable folders."""
    from ..bench.results import write_results
    from ..bench.submission import SubmissionError, score_submission
    from ..io.outputs import OutputError, claim_output
    from .run import format_table

    p = argparse.ArgumentParser(prog="vvtbench score",
                                description="score a submission (a folder of estimates with a "
                                "manifest) against the private truth of a challenge; the scores "
                                "are computed here from the estimates, never read from the "
                                "submission")
    p.add_argument("submission", help="the submission folder (manifest.json + estimates)")
    p.add_argument("--truth", required=True, help="the challenge's private truth folder")
    p.add_argument("-o", "--output", required=True,
                   help="folder for results.parquet and results.csv: new, empty, or one "
                   "`vvtbench score` wrote before (not inside the submission or the truth)")
    args = p.parse_args(argv)
    sub, truth, out = Path(args.submission), Path(args.truth), Path(args.output)
    for inside in (sub, truth):
        if out.resolve() == inside.resolve() or inside.resolve() in out.resolve().parents:
            return _fail(f"-o {out}: inside {inside}; give another folder")
    try:
        claim_output(out, "score", create=False)
        df = score_submission(sub, truth)
        claim_output(out, "score")
    except (SubmissionError, OutputError) as error:
        return _fail(error)
    write_results(df, out)
    print(format_table(df))
    extra = df.attrs.get("extra_estimates") or []
    if extra:
        print(f"ignored: {len(extra)} estimate(s) for instances the truth does not have")
    kind = str(df["split_kind"].iloc[0]) if len(df) else "public"
    print(f"\n{len(df)} instances scored from the estimates -> {out / 'results.parquet'} "
          f"(split_kind={kind}; runtimes are not measured by score: NaN)")
    if kind == "public":
        print("note: public instances (anyone can regenerate them and their truth): not a "
              "result of record")
    bad = df[df.status != "ok"]
    if len(bad):
        print(f"error: {len(bad)} of {len(df)} instances not scored (missing, invalid or "
              "unreadable estimates); see above", file=sys.stderr)
        return 1
    return 0
