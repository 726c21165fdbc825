"""The Cramér-Rao ruler of a paper scene with its camera noise and with a noise-free sensor.

Generates the truth of the filmed sample of a shipped scene (default the paper's damped
top-front cube) without rendering its frames (``generate(..., frames=False)``: the rest
render, image-space modes, transient and the ruler), then evaluates the ruler
(:meth:`vvtbench.samples.reader.Sample.ruler`) for the scene's own camera (docs/scenes.md,
"Camera noise": shot noise, 10 000 e- full well, 15 e- read noise) and for a noise-free sensor
(no shot or read noise, rounding to whole DN only: the scenes' camera before the noise model).
Prints the per-mode CRB-limited SNR under both, the detection SNR and how many of the true
modes each makes detectable, with the machine and its load.

Usage: ``python benchmarks/bench_noise_model.py [--scene jello_cube_damped_top_front]
[--resolution 256x256] [--duration 3] [--out DIR]``.
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="jello_cube_damped_top_front")
    ap.add_argument("--resolution", default=None, help="HxW (default: the scene's)")
    ap.add_argument("--duration", type=float, default=None, help="s (default: the scene's)")
    ap.add_argument("--out", type=Path, default=None, help="sample folder's parent (temp)")
    args = ap.parse_args()

    from vvtbench.samples.generate import generate
    from vvtbench.samples.reader import open_sample
    from vvtbench.scene.scene import load_scene, with_overrides

    scene = load_scene(args.scene)
    res = None if args.resolution is None else tuple(int(x) for x in args.resolution.split("x"))
    scene = with_overrides(scene, duration=args.duration, resolution=res)
    out = args.out or Path(tempfile.mkdtemp(prefix="noise_model_"))
    t0 = time.perf_counter()
    path = generate(scene, out, frames=False, progress=False, overwrite=True)
    took = time.perf_counter() - t0
    s = open_sample(path)
    own, free = s.ruler(), s.ruler(read_noise_dn=0.0, shot_noise=False)
    stored = np.asarray(s.crb_snr, dtype=np.float64)
    assert np.allclose(own["snr"], stored, rtol=1e-9), "ruler() differs from modes/crb_snr"
    f = s.frequencies_hz
    print(f"# {datetime.now(UTC):%Y-%m-%d %H:%M} UTC, {platform.node()}, "
          f"{os.cpu_count()} cores, load {os.getloadavg()[0]:.2f}; generate (no frames) "
          f"{took:.0f} s")
    print(f"# scene {scene.name}: {s.shape[0]}x{s.shape[1]} px, {s.n_frames} frames at "
          f"{s.fps:g} fps, {len(f)} modes, peak image motion "
          f"{s.info['peak_image_motion_px']:.3f} px")
    print(f"# detection SNR {own['detection_snr']:.3f} ({s.n_frames // 2} bins, "
          "false alarm 0.01 per spectrum)")
    for name, r in (("camera", own), ("noise-free", free)):
        snr = r["snr"]
        print(f"{name:>10}: {r['sensor']}: {r['n_detectable']}/{len(snr)} detectable, SNR "
              f"min {snr.min():.3g}, median {np.median(snr):.3g}, max {snr.max():.3g}")
    ratio = free["snr"] / np.maximum(own["snr"], 1e-300)
    print(f"noise-free / camera SNR: median {np.median(ratio):.3g} "
          f"[{ratio.min():.3g}, {ratio.max():.3g}]")
    print("\n| mode | f (Hz) | zeta | SNR camera | SNR noise-free |")
    print("|---:|---:|---:|---:|---:|")
    z = s.damping_ratios
    for i in range(len(f)):
        mark = "" if own["snr"][i] >= own["detection_snr"] else " (below)"
        print(f"| {i} | {f[i]:.3f} | {z[i]:.4f} | {own['snr'][i]:.3g}{mark} | "
              f"{free['snr'][i]:.3g} |")


if __name__ == "__main__":
    main()
