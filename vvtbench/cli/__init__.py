"""The ``vvtbench`` command: every argparse parser and command of vvtbench lives in this package.

One module per command group: :mod:`.simulate` (``simulate``, ``scenes``), :mod:`.generate`,
:mod:`.extract`, :mod:`.run` (``run``, ``check-results``), :mod:`.solve` (``solvers``,
``solve``), :mod:`.leaderboard` and :mod:`.export`. Library modules hold no parsers.
"""

from __future__ import annotations

import argparse
import sys

from .._version import __version__
from .simulate import DEFAULT_SCENE, build_simulate_parser, run_scenes, run_simulate

__all__ = ["DEFAULT_SCENE", "DELEGATED", "build_parser", "main"]


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


DELEGATED = {
    "extract": (_extract,
                "motion, spectrum and image-space modes of a video (see `extract --help`)"),
    "run": (_run,
            "run a suite: generate -> extract -> solve -> evaluate, cached (see `run --help`)"),
    "check-results": (_check_results, "validate a results table (Parquet/CSV) against the schema"),
    "leaderboard": (_leaderboard, "Markdown + static HTML leaderboard from a results table"),
    "export": (_export, "pack generated samples into one zarr/hdf5 dataset with a dataset card"),
    "solvers": (_solvers, "list the installed inverse solvers"),
    "solve": (_solve, "run an inverse solver on a scene (see `solve --help`)"),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="vvtbench", description="Visual vibration tomography benchmark and data generator."
    )
    parser.add_argument("--version", action="version", version=f"vvtbench {__version__}")
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


def main(argv: list[str] | None = None) -> int:
    from ..scene import SceneError

    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] in DELEGATED:
        return int(DELEGATED[argv[0]][0](argv[1:]) or 0)
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except SceneError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
