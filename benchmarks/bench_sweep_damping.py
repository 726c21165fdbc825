"""Damping fitted with and without the Hann window on a mode a sweep reaches mid-record.

One mode at a time, as the drum scenes drive it: the loudspeaker's linear sweep 50-1000 Hz over
3.5 s at 3000 FPS (``scenes/drum_homogeneous.toml``) through a single-degree-of-freedom
oscillator (``scipy.signal.lsim``), against the same mode plucked at the first frame. The
damping is :func:`vvtbench.modes.damping.damping_lorentzian` on the power spectrum with each
window; both fits model a free decay from the first frame.

    .venv/bin/python benchmarks/bench_sweep_damping.py
"""

from __future__ import annotations

import numpy as np
from scipy.signal import chirp, lsim

from vvtbench.modes.damping import damping_lorentzian
from vvtbench.modes.spectrum import window_weights

FPS, DURATION = 3000.0, 3.5
MODES = [(50.53, 0.0114), (75.82, 0.0085), (106.38, 0.0072), (130.13, 0.0068), (155.0, 0.0067),
         (250.0, 0.0070)]


def fitted(x: np.ndarray, f0: float, window: str) -> float:
    n = x.size
    w = window_weights(n, window)
    x = x - x.mean()
    p = np.abs(np.fft.rfft(x if w is None else x * w)) ** 2
    f = np.fft.rfftfreq(n, 1 / FPS)
    k = int(np.argmin(np.abs(f - f0)))
    k += int(np.argmax(p[k - 3:k + 4])) - 3
    return damping_lorentzian(f, p, k, window=window, n_frames=n)[0]


def main() -> None:
    t = np.arange(int(FPS * DURATION)) / FPS
    force = chirp(t, 50.0, DURATION, 1000.0)
    print("f0 Hz  true zeta  reached s | swept: Hann  plain | plucked: Hann  plain")
    for f0, zeta in MODES:
        w = 2 * np.pi * f0
        _, swept, _ = lsim(([1.0], [1.0, 2 * zeta * w, w * w]), force, t)
        plucked = np.exp(-zeta * w * t) * np.cos(w * np.sqrt(1 - zeta**2) * t)
        reached = (f0 - 50.0) / (950.0 / DURATION)
        print(f"{f0:6.2f}  {zeta:.4f}     {reached:5.2f}     | {fitted(swept, f0, 'hann'):.4f}  "
              f"{fitted(swept, f0, 'none'):.4f} | {fitted(plucked, f0, 'hann'):.4f}  "
              f"{fitted(plucked, f0, 'none'):.4f}")


if __name__ == "__main__":
    main()
