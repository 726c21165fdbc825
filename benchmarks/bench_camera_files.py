"""Peak memory of reading a Photron recording larger than memory is bounded.

Makes a large 16-bit ``.mraw`` (a sparse file: only the frames and rows analysed hold a moving
texture; the rest reads as zeros) with its ``.cih`` header, then in fresh child processes:

1. extracts modes from a region of interest and a frame range of it (``extract_modes`` with
   ``roi``, ``start``, ``stop``), and
2. streams every full frame of the file once (``open_video`` without a ROI),

and prints each child's peak resident memory (``ru_maxrss``) next to the file size, and the
peak of a child that extracts the same ROI from an in-memory array (the baseline cost of
the extraction itself).

Usage::

    python benchmarks/bench_camera_files.py [--gib 4] [--dir /tmp]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

H = W = 1024
FPS = 2000
ROI = (448, 576, 448, 576)  # 128 x 128
START, STOP = 1000, 1512
MODES = ((0.4, 37.0), (0.25, 91.0))


def _texture_rows(k: int, n: int, rng_seed: int = 3) -> np.ndarray:
    """The ROI of frame ``k``: a smooth texture moved by two modes (uint16, 12 bits)."""
    from scipy.ndimage import gaussian_filter, map_coordinates

    rng = np.random.default_rng(rng_seed)
    tex = gaussian_filter(rng.standard_normal((3 * n, 3 * n)), 1.5)
    tex = (tex - tex.min()) / (tex.max() - tex.min())
    y, x = np.mgrid[0:n, 0:n].astype(float)
    t = k / FPS
    u = MODES[0][0] * np.cos(2 * np.pi * x / n) * np.cos(2 * np.pi * MODES[0][1] * t)
    v = MODES[1][0] * np.sin(2 * np.pi * y / n) * np.cos(2 * np.pi * MODES[1][1] * t)
    img = map_coordinates(tex, [y + n - v, x + n - u], order=3, mode="wrap")
    return np.round(img * 3800 + 100).astype("<u2")


def make_recording(folder: Path, gib: float) -> Path:
    """A sparse ``rec.mraw`` of about ``gib`` GiB and its ``rec.cih``; returns the header."""
    frame_bytes = H * W * 2
    n_frames = int(gib * (1 << 30)) // frame_bytes
    mraw, cih = folder / "rec.mraw", folder / "rec.cih"
    with open(mraw, "wb") as fh:
        fh.truncate(n_frames * frame_bytes)
    fd = os.open(mraw, os.O_WRONLY)
    try:
        n = ROI[1] - ROI[0]
        for k in range(START, STOP):
            rows = np.zeros((n, W), "<u2")
            rows[:, ROI[2]:ROI[3]] = _texture_rows(k, n)
            os.pwrite(fd, rows.tobytes(), k * frame_bytes + ROI[0] * W * 2)
    finally:
        os.close(fd)
    header = {"Record Rate(fps)": FPS, "Shutter Speed(s)": "0.000100",
              "Total Frame": n_frames, "Original Total Frame": n_frames, "Start Frame": 0,
              "Image Width": W, "Image Height": H, "Color Type": "Mono", "Color Bit": 16,
              "File Format": "MRaw", "EffectiveBit Depth": 12, "EffectiveBit Side": "Lower",
              "Comment Text": "vvtbench benchmark"}
    cih.write_text("#Camera Information Header\n"
                   + "".join(f"{k} : {v}\n" for k, v in header.items()))
    return cih


_CHILD = r"""
import json, resource, sys, time
import numpy as np
mode, path = sys.argv[1], sys.argv[2]
roi, start, stop = json.loads(sys.argv[3])
t0 = time.perf_counter()
out = {}
if mode == "extract":
    from vvtbench.modes.extract import extract_modes
    ms = extract_modes(path, roi=tuple(roi), start=start, stop=stop)
    out["modes_hz"] = [round(float(f), 2) for f in ms.frequencies_hz]
    out["fps"] = ms.fps
elif mode == "baseline":
    from vvtbench.modes.extract import extract_modes
    frames = np.load(path)
    ms = extract_modes(frames, 2000.0)
    out["modes_hz"] = [round(float(f), 2) for f in ms.frequencies_hz]
else:
    from vvtbench.video.files import open_video
    vs = open_video(path)
    n = 0
    for f in vs.frames:
        n += 1
    out["frames"] = n
out["seconds"] = round(time.perf_counter() - t0, 1)
out["peak_rss_mib"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)
print(json.dumps(out))
"""


def _child(mode: str, path: Path) -> dict:
    args = json.dumps([list(ROI), START, STOP])
    proc = subprocess.run([sys.executable, "-c", _CHILD, mode, str(path), args],
                          capture_output=True, text=True, check=True)
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gib", type=float, default=4.0, help="size of the .mraw (GiB)")
    ap.add_argument("--dir", default=None, help="where the sparse file is made")
    ap.add_argument("--skip-full-pass", action="store_true",
                    help="do not stream every full frame")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(dir=args.dir, prefix="vvtbench-mraw-") as tmp:
        folder = Path(tmp)
        t0 = time.perf_counter()
        cih = make_recording(folder, args.gib)
        size = (folder / "rec.mraw").stat().st_size
        print(f".mraw: {size / (1 << 30):.2f} GiB, {size // (H * W * 2)} frames of {W}x{H} "
              f"16-bit (12 significant), made in {time.perf_counter() - t0:.1f} s")
        roi_frames = np.stack([_texture_rows(k, ROI[1] - ROI[0]) for k in range(START, STOP)])
        np.save(folder / "roi.npy", roi_frames.astype(np.float32) / 4095)
        base = _child("baseline", folder / "roi.npy")
        print(f"baseline (the same ROI from an array in memory): peak RSS "
              f"{base['peak_rss_mib']} MiB, modes {base['modes_hz']} Hz, {base['seconds']} s")
        res = _child("extract", cih)
        print(f"extract ROI {ROI} frames {START}:{STOP} of the .mraw: peak RSS "
              f"{res['peak_rss_mib']} MiB, modes {res['modes_hz']} Hz at {res['fps']:g} fps, "
              f"{res['seconds']} s")
        if not args.skip_full_pass:
            full = _child("stream", cih)
            print(f"stream all {full['frames']} full frames: peak RSS {full['peak_rss_mib']} "
                  f"MiB, {full['seconds']} s")
    print(f"(this process: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
