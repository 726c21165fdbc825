"""The ``calibrate`` command: a camera from clicked points, and a picture to click on.

``vvtbench calibrate VIDEO --object OBJ [--clicks CSV] -o DIR`` writes ``DIR/calibration.png``
(the first frame beside the mesh, numbered candidate vertices to pair with pixels),
``DIR/candidates.csv`` (those vertices: id, position, pixel in the current camera) and, with
``--clicks``, ``DIR/calibration.json`` (the camera and its reprojection error), and prints
the candidates and the error. Clicks whose largest reprojection error is above
``--max-error`` still get their picture (to find the bad click), then exit status 2.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from .args import nonnegative_float

__all__ = ["build_parser", "main_calibrate"]


def build_parser(prog: str = "vvtbench calibrate") -> argparse.ArgumentParser:
    """Argument parser of :func:`main_calibrate`."""
    ap = argparse.ArgumentParser(
        prog=prog,
        description="Estimate the camera of a video from clicked object points and draw the "
        "mesh over its first frame, with numbered vertices to click (docs/how-to/calibrate.md).")
    ap.add_argument("video", type=Path, help="video or camera file (anything `extract` reads)")
    ap.add_argument("--object", required=True, metavar="OBJ",
                    help="box:LxWxH, plate:LxW, plate:D:circle (metres), a .stl/.obj/.ply "
                         "surface or a scene .toml")
    ap.add_argument("--clicks", type=Path, metavar="CSV",
                    help="clicked points: CSV with header vertex,u,v or x,y,z,u,v")
    ap.add_argument("--intrinsics", metavar="FX,FY,CX,CY",
                    help="known intrinsics in pixels (default: estimated)")
    ap.add_argument("--max-error", type=nonnegative_float, default=2.0, metavar="PX",
                    help="largest reprojection error accepted, pixels (default 2)")
    ap.add_argument("--camera", type=Path, metavar="JSON",
                    help="a known camera (camera.json of a generated sample): draw and list "
                         "the candidates' pixels in it instead of the default view")
    ap.add_argument("-o", "--out", type=Path, required=True, help="output folder")
    return ap


def _first_frame(video: Path) -> np.ndarray:
    from ..video.files import VideoError, open_video

    stream = open_video(video, max_frames=1)
    frame = next(iter(stream.frames), None)
    if frame is None:
        raise VideoError(f"{video}: holds no frame")
    return np.asarray(frame, dtype=np.float32)


def main_calibrate(argv: list[str] | None = None) -> int:
    """``vvtbench calibrate VIDEO --object OBJ [--clicks CSV] -o DIR``; the exit status."""
    import json

    from ..field.calibrate import (
        CalibrationError,
        calibrate_camera,
        candidate_vertices,
        default_camera,
        draw_calibration,
        load_clicks_csv,
        parse_intrinsics,
    )
    from ..field.objects import resolve_object
    from ..io.files import write_json, write_text
    from ..render.camera import Camera
    from .invert import unit_warnings_on_stderr

    args = build_parser().parse_args(argv)
    intrinsics = parse_intrinsics(args.intrinsics)
    with unit_warnings_on_stderr():  # an object or clicks in millimetres: one line each
        obj = resolve_object(args.object)
    frame = _first_frame(args.video)
    height, width = frame.shape[:2]
    pts, surface = obj.mesh.points, obj.mesh.surface
    with unit_warnings_on_stderr():
        clicks = load_clicks_csv(args.clicks, pts) if args.clicks is not None else None
    cal = None
    if clicks is not None:
        cal = calibrate_camera(clicks.X, clicks.uv, width, height, intrinsics=intrinsics,
                               max_error=None, source=str(args.clicks))
        camera = cal.camera
        view = "the camera from the clicks"
    elif args.camera is not None:
        try:
            camera = Camera.from_dict(json.loads(args.camera.read_text()))
        except (OSError, ValueError, KeyError, TypeError) as error:
            raise ValueError(f"{args.camera}: not a camera JSON (keys K, R, t, width, "
                             f"height): {error}") from None
        if (camera.width, camera.height) != (width, height):
            raise ValueError(f"{args.camera}: camera is {camera.width}x{camera.height} px, "
                             f"the video {width}x{height}")
        view = f"the camera of {args.camera}"
    else:
        camera = default_camera(pts, width, height)
        view = "a default view (not your camera: pair the numbers with what you see)"
    candidates = candidate_vertices(pts, surface, camera, obj.corner_nodes())
    uv = camera.project(pts[candidates]) if len(candidates) else np.zeros((0, 2))
    args.out.mkdir(parents=True, exist_ok=True)
    caption = (f"{cal.method}: reprojection RMS {cal.rms_px:.2f} px, max {cal.max_px:.2f} px "
               f"over {cal.n_points} clicks" if cal else f"candidates in {view.split(' (')[0]}")
    png = draw_calibration(args.out / "calibration.png", frame, camera, pts, surface,
                           candidates, calibrated=cal is not None or args.camera is not None,
                           clicks=clicks, caption=caption)
    rows = ["vertex,x,y,z,u,v"] + [
        f"{v},{x:.6g},{y:.6g},{z:.6g},{u:.2f},{w:.2f}"
        for v, (x, y, z), (u, w) in zip(candidates, pts[candidates], uv, strict=True)]
    write_text(args.out / "candidates.csv", "\n".join(rows) + "\n")
    print(f"{obj.kind} {args.object}: {obj.mesh.n_nodes} nodes; video {width}x{height} px")
    print(f"candidate vertices, pixels in {view}:")
    print("  vertex        x        y        z        u        v")
    for v, (x, y, z), (u, w) in zip(candidates, pts[candidates], uv, strict=True):
        print(f"  {v:6d} {x:8.4f} {y:8.4f} {z:8.4f} {u:8.1f} {w:8.1f}")
    print(f"wrote {png} and {args.out / 'candidates.csv'}")
    if cal is None:
        print("next: write a clicks CSV (vertex,u,v) pairing at least 6 vertices (4 on one "
              "plane) with their pixels in the first frame, then rerun with --clicks")
        return 0
    write_json(args.out / "calibration.json", {**cal.to_dict(), "clicks": str(args.clicks),
                                               "object": obj.describe(),
                                               "max_error_px": args.max_error})
    print(f"camera: {cal.method}, intrinsics {cal.intrinsics}; reprojection error RMS "
          f"{cal.rms_px:.3f} px, max {cal.max_px:.3f} px over {cal.n_points} clicks "
          f"(bound {args.max_error:g} px)")
    if cal.max_px > args.max_error:
        worst = int(np.argmax(cal.residuals_px))
        (args.out / "calibration.json").unlink()
        raise CalibrationError(
            f"{args.clicks}: reprojection error {cal.max_px:.2f} px is above the bound "
            f"{args.max_error:g} px (--max-error); worst: data line {worst + 1}; see {png}")
    print(f"wrote {args.out / 'calibration.json'}")
    return 0
