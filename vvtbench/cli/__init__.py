"""The ``vvtbench`` command: every argparse parser and command of vvtbench lives in this package.

One module per command group: :mod:`.simulate` (``simulate``, ``scenes``), :mod:`.generate`,
:mod:`.extract`, :mod:`.run` (``run``, ``merge-shards``, ``check-results``), :mod:`.solve`
(``solvers``, ``solve``), :mod:`.leaderboard`, :mod:`.export` and :mod:`.verify`. Library
modules hold no parsers.

Errors. :func:`main` turns every error a user can fix (the project's error types, bad
option values, missing or unreadable files) into one line on stderr, ``error: ...``, and exit
status 2; anything else is a bug and prints one line ``internal error: ...`` with exit
status 1. ``vvtbench --debug COMMAND ...`` (or ``VVTBENCH_DEBUG=1``) shows the traceback
instead. Usage errors of every parser are one line too. A misspelt command, scene, suite or
solver name gets a suggestion (:func:`explain`).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import traceback
from collections.abc import Iterator

from .._version import __version__
from .args import (
    MAX_INSTANCES,
    bounded,
    explain,
    finite_float,
    instance_count,
    nonnegative_float,
    nonnegative_int,
    one_line,
    positive_float,
    positive_int,
    suggest,
)
from .simulate import DEFAULT_SCENE, build_simulate_parser, run_scenes, run_simulate


@contextlib.contextmanager
def _one_line_usage() -> Iterator[None]:
    """Every argparse usage error (of every command's parser) as one line, exit 2."""
    original = argparse.ArgumentParser.error

    def error(self: argparse.ArgumentParser, message: str) -> None:
        self.exit(2, f"{self.prog}: error: {one_line(message)} (see {self.prog} --help)\n")

    argparse.ArgumentParser.error = error  # type: ignore[method-assign]
    try:
        yield
    finally:
        argparse.ArgumentParser.error = original  # type: ignore[method-assign]



__all__ = ["DEFAULT_SCENE", "DELEGATED", "MAX_INSTANCES", "bounded", "build_parser", "explain",
           "finite_float", "instance_count", "main", "nonnegative_float", "nonnegative_int",
           "one_line", "positive_float", "positive_int", "suggest"]


# Commands that parse their own arguments, each imported only when it runs.
def _extract(argv: list[str]) -> int:
    from .extract import main_extract

    return main_extract(argv)


def _run(argv: list[str]) -> int:
    from .run import main_run

    return main_run(argv)


def _merge_shards(argv: list[str]) -> int:
    from .run import main_merge_shards

    return main_merge_shards(argv)


def _check_results(argv: list[str]) -> int:
    from .run import main_check_results

    return main_check_results(argv)


def _leaderboard(argv: list[str]) -> int:
    from .leaderboard import main_leaderboard

    return main_leaderboard(argv)


def _export(argv: list[str]) -> int:
    from .export import main

    return main(argv)


def _solvers(argv: list[str]) -> int:
    from .solve import main_solvers

    return main_solvers(argv)


def _solve(argv: list[str]) -> int:
    from .solve import main_solve

    return main_solve(argv)


def _verify(argv: list[str]) -> int:
    from .verify import main_verify

    return main_verify(argv)


def _extractors(argv: list[str]) -> int:
    from .solve import main_extractors

    return main_extractors(argv)


def _train(argv: list[str]) -> int:
    from .train import main_train

    return main_train(argv)


def _calibrate(argv: list[str]) -> int:
    from .calibrate import main_calibrate

    return main_calibrate(argv)


def _invert(argv: list[str]) -> int:
    from .invert import main_invert

    return main_invert(argv)


def _score(argv: list[str]) -> int:
    from .score import main_score

    return main_score(argv)


def _release(argv: list[str]) -> int:
    from .release import main_release

    return main_release(argv, run=main)


def _challenge(argv: list[str]) -> int:
    from .score import main_challenge

    return main_challenge(argv)


DELEGATED = {
    "extract": (_extract,
                "motion, spectrum and image-space modes of a video (see `extract --help`)"),
    "run": (_run,
            "run a suite: generate -> extract -> solve -> evaluate, cached (see `run --help`)"),
    "merge-shards": (_merge_shards, "merge the shards of a suite (`run --shard K/N`) into one "
                                    "table, every score recomputed (see `merge-shards --help`)"),
    "check-results": (_check_results, "validate a results table (Parquet/CSV) against the schema"),
    "leaderboard": (_leaderboard, "Markdown + static HTML leaderboard from a results table"),
    "export": (_export, "pack generated samples into one zarr/hdf5 dataset with a dataset card"),
    "solvers": (_solvers, "list the installed inverse solvers"),
    "extractors": (_extractors, "list the installed motion extractors"),
    "solve": (_solve, "run an inverse solver on a scene (see `solve --help`)"),
    "train": (_train, "fit a learned solver on a scene family's train split"),
    "verify": (_verify, "check a sample, a run folder or an exported dataset against its "
                        "recorded sha256 and shapes"),
    "calibrate": (_calibrate, "estimate a camera from clicked points and draw the mesh over "
                              "the first frame (see `calibrate --help`)"),
    "invert": (_invert, "from your video, object and clicks to a material map: extract -> "
                        "observe -> solve -> report (see `invert --help`)"),
    "release": (_release, "build a frozen dataset release, verify a copy byte for byte, or "
                          "freeze a build (see `release --help`)"),
    "challenge": (_challenge, "write a hidden-truth challenge: problems to hand out, truth to "
                              "keep (from a family: a challenge of record, drawn from a secret)"),
    "score": (_score, "score a folder of estimates against truth the submitter does not hold"),
}
COMMANDS = ("simulate", "generate", "scenes", *DELEGATED)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="vvtbench", description="Visual vibration tomography benchmark and data generator.",
        epilog="--debug (before the command) shows the traceback of an error.")
    parser.add_argument("--version", action="version", version=f"vvtbench {__version__}")
    parser.add_argument("--debug", action="store_true",
                        help="show the traceback of an error (also VVTBENCH_DEBUG=1)")
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("simulate", help="modal analysis (and transient) of a scene")
    build_simulate_parser(p)
    p.set_defaults(func=run_simulate)
    from .generate import build_parser as build_generate_parser
    from .generate import run as run_generate

    p = sub.add_parser("generate", help="render scenes into sample folders (video + ground truth)")
    build_generate_parser(p)
    p.set_defaults(func=run_generate)
    p = sub.add_parser("scenes", help="list the shipped scenes")
    p.set_defaults(func=run_scenes)
    for name, (_, help_text) in DELEGATED.items():
        sub.add_parser(name, help=help_text, add_help=False)
    return parser


def _user_errors() -> tuple[type[BaseException], ...]:
    """Errors a user can fix: exit 2 with their one-line message."""
    from ..bench.suite import SuiteError
    from ..datasets.packed import ExportError
    from ..observe import ObserveError
    from ..samples.reader import DatasetError
    from ..scene.scene import SceneError
    from ..solving.plugins import PluginError
    from ..video.files import VideoError

    return (SceneError, SuiteError, DatasetError, ObserveError, PluginError, ExportError,
            VideoError, ValueError, FileNotFoundError, PermissionError, IsADirectoryError,
            NotADirectoryError, FileExistsError)


def _dispatch(argv: list[str]) -> int:
    try:
        return _command(argv)
    except SystemExit as done:  # argparse's usage errors and --help: a status, not a raise
        if done.code is None or isinstance(done.code, int):
            return int(done.code or 0)
        print(one_line(str(done.code)), file=sys.stderr)
        return 1


def _command(argv: list[str]) -> int:
    if argv and argv[0] in DELEGATED:
        return int(DELEGATED[argv[0]][0](argv[1:]) or 0)
    if argv and not argv[0].startswith("-") and argv[0] not in COMMANDS:
        print(f"vvtbench: error: unknown command {argv[0]!r}{suggest(argv[0], COMMANDS)} "
              f"(commands: {', '.join(COMMANDS)})", file=sys.stderr)
        return 2
    args = build_parser().parse_args(argv)
    return int(args.func(args) or 0)


def main(argv: list[str] | None = None) -> int:
    """Run ``vvtbench ARGV``; returns the exit status: 0 done, 1 failed (or, for ``verify``
    and ``check-results``, problems found), 2 bad input (one line on stderr), 130
    interrupted."""
    argv = sys.argv[1:] if argv is None else list(argv)
    debug = os.environ.get("VVTBENCH_DEBUG", "") not in ("", "0")
    while argv and argv[0] == "--debug":  # global option, before the command
        debug = True
        argv = argv[1:]
    with _one_line_usage():
        if debug:
            return _dispatch(argv)
        try:
            return _dispatch(argv)
        except KeyboardInterrupt:
            print("interrupted", file=sys.stderr)
            return 130
        except _user_errors() as error:
            print(f"error: {explain(error)}", file=sys.stderr)
            return 2
        except MemoryError:
            print("error: out of memory (use a smaller scene, grid or video, or run with "
                  "--debug for the traceback)", file=sys.stderr)
            return 1
        except OSError as error:  # a full disk, a broken pipe, ...: not bad input
            print(f"error: {explain(error)}", file=sys.stderr)
            return 1
        except Exception as error:  # noqa: BLE001 -- a bug: one line, the traceback on demand
            where = traceback.extract_tb(error.__traceback__)[-1]
            print(f"internal error: {type(error).__name__}: {one_line(str(error))} "
                  f"(at {os.path.basename(where.filename)}:{where.lineno}; run with --debug "
                  "for the traceback)", file=sys.stderr)
            return 1
