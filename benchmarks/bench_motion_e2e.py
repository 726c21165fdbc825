"""End-to-end check of mode identification on a rendered cube.

Renders a sample with ``vvtbench.samples.reader.generate`` (or uses ``--sample DIR``), runs the
streaming extraction (``vvtbench.modes.extract_modes``: phase-based motion, Hann-windowed
spectrum, peak picking, distortion / camera-shake rejection) on its video, and compares the
result with the sample's ground truth (``vvtbench.modes.validate.compare_to_truth``): every
identified frequency within one FFT bin of a true eigenfrequency, and the lowest
well-separated modes with MAC >= 0.9 against the true projected image-space modes.

Examples::

    python benchmarks/bench_motion_e2e.py          # jello_cube_defect_top, 4 s, 500 fps, 256^2
    python benchmarks/bench_motion_e2e.py --tiny   # 6^3 cube, 128^2, 1.5 s, 200 fps
    python benchmarks/bench_motion_e2e.py --sample DIR [--max-frames N] [--average A]

Exit status 0 when both checks pass, 1 otherwise.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from vvtbench.modes import extract_modes
from vvtbench.modes.validate import compare_to_truth, format_table
from vvtbench.samples import generate as gen
from vvtbench.samples import reader as ds
from vvtbench.scene.scene import load_scene, parse_scene

TINY = {"cells": 6, "resolution": 128, "duration": 1.5, "fps": 200.0, "n_modes": 12}


def make_scene(
    name: str,
    *,
    duration: float,
    fps: float,
    resolution: int,
    cells: int | None = None,
    n_modes: int | None = None,
) -> object:
    """A shipped scene with a shorter video, another frame rate, size or mesh."""
    data = json.loads(json.dumps(load_scene(name).model_dump(mode="json", exclude={"source"})))
    data["simulation"]["duration"] = duration
    data["simulation"]["fps"] = fps
    data["camera"]["resolution"] = [resolution, resolution]
    if cells is not None:
        data["geometry"]["cells"] = [cells] * 3
    if n_modes is not None:
        data["simulation"]["n_modes"] = n_modes
    tag = f"{name}_{cells or 'x'}c_{resolution}px_{duration:g}s_{fps:g}fps"
    data["name"] = tag
    return parse_scene(data, tag)


def run(
    sample_dir: Path,
    *,
    max_frames: int | None = None,
    average: int = 1,
    fmax: float | None = None,
    n_lowest: int = 3,
    workers: int = -1,
) -> tuple[object, object, float]:
    """Extract modes from a sample and compare them with its truth; returns (check, ms, s)."""
    s = ds.open_sample(sample_dir)
    if fmax is None:  # the video holds only the simulated modes: no mode can lie above them
        fmax = min(float(np.max(s.info["modes"]["frequencies_hz"])) + 1.0, s.fps / average / 2)
    t0 = time.perf_counter()
    ms = extract_modes(
        s.video_path,
        s.fps,
        max_frames=max_frames,
        average=average,
        fmax=fmax,
        workers=workers,
    )
    dt = time.perf_counter() - t0
    check = compare_to_truth(
        ms,
        s.info["modes"]["frequencies_hz"],
        np.asarray(s["image/modes"]),
        n_lowest=n_lowest,
    )
    return check, ms, dt


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sample", type=Path, default=None, help="use an existing sample folder")
    ap.add_argument("--scene", default="jello_cube_defect_top")
    ap.add_argument("--duration", type=float, default=4.0)
    ap.add_argument("--fps", type=float, default=500.0)
    ap.add_argument("--resolution", type=int, default=256)
    ap.add_argument("--cells", type=int, default=None, help="mesh cells per side")
    ap.add_argument("--n-modes", type=int, default=None)
    ap.add_argument("--tiny", action="store_true", help=f"small and fast: {TINY}")
    ap.add_argument("--out", type=Path, default=None, help="where to render (default: temp)")
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--average", type=int, default=1)
    ap.add_argument(
        "--fmax",
        type=float,
        default=None,
        help="highest mode frequency (Hz); default 1 Hz above the highest simulated mode",
    )
    ap.add_argument("--n-lowest", type=int, default=3)
    args = ap.parse_args(argv)

    tmp = None
    if args.sample is not None:
        sample = args.sample
        t_gen = 0.0
    else:
        opts = dict(
            duration=args.duration,
            fps=args.fps,
            resolution=args.resolution,
            cells=args.cells,
            n_modes=args.n_modes,
        )
        if args.tiny:
            opts.update(TINY)
        scene = make_scene(args.scene, **opts)
        if args.out is None:
            tmp = tempfile.TemporaryDirectory(prefix="vvt_e2e_")
            out = Path(tmp.name)
        else:
            out = args.out
        t0 = time.perf_counter()
        sample = out / scene.name
        if not (sample / "manifest.json").is_file():
            sample = gen.generate(scene, out, progress=False)
        t_gen = time.perf_counter() - t0
    try:
        s = ds.open_sample(sample)
        check, ms, dt = run(
            sample,
            max_frames=args.max_frames,
            average=args.average,
            fmax=args.fmax,
            n_lowest=args.n_lowest,
        )
        v = s.info["video"]
        print(
            f"sample {sample}: {v['frames']} frames of {v['height']}x{v['width']} at "
            f"{v['fps']:g} fps; analysed {ms.n_frames} frames at {ms.fps:g} fps "
            f"(bin {ms.fps / ms.n_frames:.4f} Hz)"
        )
        print(
            f"render {t_gen:.1f} s, extraction {dt:.1f} s (motion "
            f"{ms.metadata['timing_s']['motion']:.1f} s); {len(ms)} modes identified, "
            f"rejected: "
            + ", ".join(
                f"{r['frequency_hz']:.3f} Hz ({r['reason']}"
                + (f" {r['kind']}" if "kind" in r else "")
                + ")"
                for r in ms.metadata["rejected"]
            )
        )
        print()
        print(format_table(check))
        return 0 if check.ok else 1
    finally:
        if tmp is not None:
            tmp.cleanup()


if __name__ == "__main__":
    raise SystemExit(main())
