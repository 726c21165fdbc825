"""``vvtbench generate``: render scenes into sample folders (argparse front end of
:func:`vvtbench.generate.generate`). To become ``vvtbench/cli/generate.py``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

__all__ = ["build_parser", "main", "run"]


def _resolution(text: str) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"resolution must be HxW, e.g. 256x256; got {text!r}"
                                         ) from None
    return h, w


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    """The ``generate`` parser (fills ``parser`` if given, e.g. a sub-command's)."""
    p = parser or argparse.ArgumentParser(
        prog="vvtbench generate", description="Render scenes into sample folders "
        "(video + ground truth); see docs/dataset.md.")
    p.add_argument("scene", metavar="SCENE_OR_SUITE",
                   help="scene file or shipped scene name, a folder of scene TOMLs, or a suite "
                        "TOML with scenes = [...]")
    p.add_argument("-o", "--out", required=True, type=Path, help="output folder")
    length = p.add_mutually_exclusive_group()
    length.add_argument("--frames", type=int, help="number of video frames (overrides duration)")
    length.add_argument("--duration", type=float, help="video length in seconds")
    p.add_argument("--resolution", type=_resolution, help="HxW output size, e.g. 256x256")
    p.add_argument("--overwrite", action="store_true", help="replace existing sample folders")
    p.add_argument("--consumer-crf", type=int, default=None,
                   help="write an 8-bit H.264 video at this CRF instead of lossless 16-bit")
    p.add_argument("--no-video", action="store_true",
                   help="modes-only sample: the ground truth without video or transient")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    return p


def run(args: argparse.Namespace) -> int:
    """Run parsed arguments; returns the exit code (0 ok, 2 bad input)."""
    from ..dataset import DatasetError
    from ..generate import generate, resolve_scenes, with_overrides
    from ..scene import SceneError

    try:
        scenes = resolve_scenes(args.scene)
        scenes = [with_overrides(s, frames=args.frames, duration=args.duration,
                                 resolution=args.resolution) for s in scenes]
        for scene in scenes:
            path = generate(scene, args.out, video=not getattr(args, "no_video", False),
                            progress=not args.no_progress, overwrite=args.overwrite,
                            consumer_crf=args.consumer_crf)
            print(f"{scene.name}: {path}")
    except (SceneError, DatasetError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    return 0


def main(argv: list[str] | None = None) -> int:
    """``vvtbench generate``: returns the exit code (0 ok, 2 bad input, 1 failure)."""
    return run(build_parser().parse_args(argv))
