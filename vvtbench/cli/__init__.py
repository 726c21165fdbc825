"""The ``vvtbench`` command: every argparse parser and command of vvtbench lives in this package.

One module per command group: :mod:`.simulate` (``simulate``, ``scenes``), :mod:`.generate`,
:mod:`.extract`, :mod:`.run` (``run``, ``check-results``), :mod:`.solve` (``solvers``,
``solve``), :mod:`.leaderboard`, :mod:`.export` and :mod:`.verify`. Library modules hold no
parsers.

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
import difflib
import math
import os
import re
import sys
import traceback
from collections.abc import Callable, Iterable, Iterator

# The option types below are defined before the command modules are imported: they import
# them from this package.


def _number(kind: type, text: str) -> float:
    try:
        value = kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{text!r} is not {'an integer' if kind is int else 'a number'}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
    return value


def bounded(kind: type = float, *, gt: float | None = None, ge: float | None = None,
            le: float | None = None, also: tuple = ()) -> Callable[[str], float]:
    """An argparse ``type`` reading an int or a finite float within bounds, saying what is
    allowed when not (``also``: extra allowed values, e.g. ``-1`` for "all CPUs")."""
    parts = [f"> {gt:g}" if gt is not None else "", f">= {ge:g}" if ge is not None else "",
             f"<= {le:g}" if le is not None else ""]
    allowed = " and ".join(p for p in parts if p) or "finite"
    allowed = ("an integer " if kind is int else "a number ") + allowed + "".join(
        f" (or {a})" for a in also)

    def parse(text: str) -> float:
        value = _number(kind, text)
        if value in also:
            return value
        if (gt is not None and not value > gt) or (ge is not None and not value >= ge) \
                or (le is not None and not value <= le):
            raise argparse.ArgumentTypeError(f"{text!r}: must be {allowed}")
        return value

    parse.__name__ = kind.__name__  # argparse names the type in its messages
    return parse


positive_int = bounded(int, ge=1)
#: family instances one command may ask for
MAX_INSTANCES = 1_000_000
instance_count = bounded(int, ge=1, le=MAX_INSTANCES)
nonnegative_int = bounded(int, ge=0)
positive_float = bounded(float, gt=0)
nonnegative_float = bounded(float, ge=0)
finite_float = bounded(float)


def suggest(word: str, known: Iterable[str]) -> str:
    """``"; did you mean 'x'?"`` for the close matches of ``word`` among ``known``, else
    ``""``."""
    matches = difflib.get_close_matches(str(word), sorted(set(known)), n=3, cutoff=0.6)
    if not matches:
        return ""
    return "; did you mean " + " or ".join(repr(m) for m in matches) + "?"


def _scene_names() -> list[str]:
    from ..scene import SCENES_DIR

    return sorted(p.stem for p in SCENES_DIR.glob("*.toml")) if SCENES_DIR.is_dir() else []


def _suite_names() -> list[str]:
    from ..bench import SUITES_DIR

    return sorted(p.stem for p in SUITES_DIR.glob("*.toml")) if SUITES_DIR.is_dir() else []


def _solver_names() -> list[str]:
    from ..plugins import SOLVERS

    return sorted(SOLVERS.registry())  # names only: plug-ins are imported in sealed children


_UNKNOWN = (  # message pattern -> the names the unknown one is compared with
    (re.compile(r"^(?P<name>[^:\n]+): no such scene file"), _scene_names),
    (re.compile(r"^(?P<name>[^:\n]+): no such suite file"), _suite_names),
    (re.compile(r"unknown solver '(?P<name>[^']+)'"), _solver_names),
)


def one_line(message: str) -> str:
    """A message on one line (line breaks become ``"; "``)."""
    return "; ".join(part.strip() for part in str(message).splitlines() if part.strip())


def explain(error: BaseException | str) -> str:
    """The one-line message of ``error``, with a "did you mean" for a misspelt scene, suite
    or solver name, and the path for an OS error that has one."""
    if isinstance(error, OSError) and error.filename is not None and error.strerror:
        text = f"{error.filename}: {error.strerror}"
    else:
        text = str(error) or type(error).__name__
    text = one_line(text)
    for pattern, names in _UNKNOWN:
        m = pattern.search(text)
        if m and "did you mean" not in text:
            try:
                hint = suggest(m.group("name").strip(), names())
            except Exception:  # noqa: BLE001 -- a hint must never hide the error
                hint = ""
            text += hint
            break
    return text


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


from .._version import __version__  # noqa: E402
from .simulate import DEFAULT_SCENE, build_simulate_parser, run_scenes, run_simulate  # noqa: E402

__all__ = ["DEFAULT_SCENE", "DELEGATED", "bounded", "build_parser", "explain", "main",
           "suggest"]


# Commands that parse their own arguments, each imported only when it runs.
def _extract(argv: list[str]) -> int:
    from .extract import main_extract

    return main_extract(argv)


def _run(argv: list[str]) -> int:
    from .run import main_run

    return main_run(argv)


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

    return main_release(argv)


def _challenge(argv: list[str]) -> int:
    from .score import main_challenge

    return main_challenge(argv)


DELEGATED = {
    "extract": (_extract,
                "motion, spectrum and image-space modes of a video (see `extract --help`)"),
    "run": (_run,
            "run a suite: generate -> extract -> solve -> evaluate, cached (see `run --help`)"),
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
    "challenge": (_challenge, "write a hidden-truth challenge from samples: problems to hand "
                              "out, truth to keep"),
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
    from ..dataset import DatasetError
    from ..observe import ObserveError
    from ..packed import ExportError
    from ..plugins import PluginError
    from ..scene import SceneError
    from ..video import VideoError

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
