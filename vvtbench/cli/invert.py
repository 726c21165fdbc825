"""The ``invert`` command: from a video, its object and clicks to a material map.

``vvtbench invert VIDEO --object OBJ --clicks CSV [--solver NAME] [--modes N] [--fps F]
-o OUT`` runs :func:`vvtbench.field.invert.invert` (calibrate, extract, observe, solve,
report) and prints where ``OUT/report.md`` is. Exit status 0 with a valid estimate, 1 when
the solver's estimate is invalid (the reason is printed and heads the report), 2 for bad
input.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
from pathlib import Path

from .args import nonnegative_float, positive_float, positive_int

__all__ = ["build_parser", "main_invert", "unit_warnings_on_stderr"]


def build_parser(prog: str = "vvtbench invert") -> argparse.ArgumentParser:
    """Argument parser of :func:`main_invert`."""
    ap = argparse.ArgumentParser(
        prog=prog,
        description="From your video, object and clicks to a material map: extract -> "
        "observe -> solve -> a report folder (report.md first). Finished stages are reused "
        "when their inputs are unchanged (docs/tutorials/your-own-video.md).")
    ap.add_argument("video", type=Path, help="video or camera file (anything `extract` reads)")
    ap.add_argument("--object", required=True, metavar="OBJ",
                    help="box:LxWxH, plate:LxW, plate:D:circle (metres), a .stl/.obj/.ply "
                         "surface or a scene .toml")
    ap.add_argument("--clicks", type=Path, required=True, metavar="CSV",
                    help="clicked points: CSV with header vertex,u,v or x,y,z,u,v")
    ap.add_argument("--solver", default="vvt", help="solver name or path/file.py:Class "
                    "(default vvt; `vvtbench solvers` lists them)")
    ap.add_argument("--set", dest="solver_set", action="append", default=[],
                    metavar="KEY=VALUE", help="solver configuration override (repeatable)")
    ap.add_argument("--modes", type=positive_int, default=10, metavar="N",
                    help="modes the solver uses, the lowest extracted (default 10)")
    ap.add_argument("--fps", type=positive_float, help="frame rate, when the file states none")
    ap.add_argument("--fmin", type=positive_float, help="lowest frequency to extract (Hz)")
    ap.add_argument("--fmax", type=positive_float, help="highest frequency to extract (Hz)")
    ap.add_argument("--intrinsics", metavar="FX,FY,CX,CY",
                    help="known intrinsics in pixels (default: estimated from the clicks)")
    ap.add_argument("--max-error", type=nonnegative_float, default=2.0, metavar="PX",
                    help="largest reprojection error of the clicks accepted (default 2 px)")
    ap.add_argument("--nu", type=positive_float, default=0.3, help="Poisson's ratio (0.3)")
    ap.add_argument("--w0", type=positive_float,
                    help="initial stiffness (Pa; N/m for plates): default 1e4 / 40")
    ap.add_argument("--v0", type=positive_float,
                    help="initial density (kg/m^3; kg/m^2 for plates): default 1000 / 0.5")
    ap.add_argument("--timeout", type=positive_float, default=1800.0,
                    help="seconds the solver may take (default 1800)")
    ap.add_argument("-o", "--out", type=Path, required=True,
                    help="report folder: new, empty, or one `vvtbench invert` wrote before "
                    "(its finished stages are reused)")
    return ap


@contextlib.contextmanager
def unit_warnings_on_stderr():
    """Each :class:`vvtbench.field.objects.UnitWarning` raised inside (an object or clicks
    that look like millimetres) printed at once as one ``warning: ...`` line on stderr."""
    import warnings

    from ..field.objects import UnitWarning

    shown = warnings.showwarning

    def show(message, category, *args, **kwargs):
        if issubclass(category, UnitWarning):
            print(f"warning: {message}", file=sys.stderr, flush=True)
        else:
            shown(message, category, *args, **kwargs)

    with warnings.catch_warnings():
        warnings.simplefilter("always", UnitWarning)
        warnings.showwarning = show
        yield


def main_invert(argv: list[str] | None = None) -> int:
    """``vvtbench invert VIDEO --object OBJ --clicks CSV -o OUT``; the exit status."""
    from ..field.calibrate import parse_intrinsics
    from ..field.invert import InvertOptions, invert
    from ..solving.plugins import load_solver, parse_overrides

    args = build_parser().parse_args(argv)
    if args.fmin is not None and args.fmax is not None and args.fmin >= args.fmax:
        raise ValueError(f"--fmin {args.fmin:g} must be below --fmax {args.fmax:g}")
    from ..io.outputs import claim_output

    claim_output(args.out, "invert", create=False)  # checked before any stage runs
    config = {}
    if args.solver_set:
        checked = parse_overrides(args.solver_set, load_solver(args.solver).Config)
        config = {key: getattr(checked, key) for key in
                  (item.partition("=")[0].strip() for item in args.solver_set)}
    opts = InvertOptions(solver=args.solver, solver_config=config, n_modes=args.modes,
                         fps=args.fps, intrinsics=parse_intrinsics(args.intrinsics),
                         max_error=args.max_error, fmin=args.fmin, fmax=args.fmax,
                         nu=args.nu, w0=args.w0, v0=args.v0, timeout=args.timeout)
    from ..solving.sealed import SealedError

    try:
        with unit_warnings_on_stderr():
            result = invert(args.video, args.object, args.clicks, args.out, opts)
    except SealedError as error:
        print(f"error: solver {args.solver}: {error}", file=sys.stderr)
        return 1
    if result.reused:
        print(f"reused finished stages: {', '.join(result.reused)}")
    if result.invalid is not None:
        print(f"NO RESULT: the estimate of {result.solver} is invalid: {result.invalid} "
              f"(see {result.report})", file=sys.stderr)
        return 1
    print(f"{result.solver}: material map from {result.n_modes} modes; camera reprojection "
          f"RMS {result.rms_px:.3f} px, max {result.max_px:.3f} px")
    print(f"read {result.report} first; fields in {args.out / 'fields.npz'} and "
          f"{args.out / 'fields.png'}")
    return 0
