"""Camera sensor model of the generated videos: shot and read noise, quantisation to DN.

* :func:`sensor_dn`: average noisy sub-frame intensities into one frame of digital numbers.
* :func:`noise_rng`: the per-frame seeded noise generator (reproducible samples).
"""

from __future__ import annotations

import numpy as np

__all__ = ["FULL_WELL_ELECTRONS", "noise_rng", "sensor_dn"]

#: Default full-well capacity (electrons) of the simulated sensor, used by shot noise.
FULL_WELL_ELECTRONS = 10000.0
_NOISE_STREAM = 0x5EED_0001


def noise_rng(seed: int, frame: int) -> np.random.Generator:
    """The sensor-noise generator of video frame ``frame`` of a scene with ``seed``."""
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, _NOISE_STREAM, int(frame)])


def sensor_dn(
    subframes: np.ndarray, bit_depth: int, read_noise_dn: float, shot_noise: bool,
    full_well: float, rng: np.random.Generator | None,
) -> np.ndarray:
    """Average sub-frame intensities in [0, 1] (each with its own noise) into one frame of DN.

    Per sub-frame: electrons = I * full_well, Poisson when ``shot_noise``; DN = electrons *
    (2^bits - 1) / full_well + N(0, read_noise_dn^2). The sub-frames are averaged, then rounded
    and clipped to [0, 2^bits - 1].
    """
    dn_max = float(2**bit_depth - 1)
    x = np.asarray(subframes, dtype=np.float64)
    if shot_noise:
        x = rng.poisson(np.clip(x, 0.0, None) * full_well) / full_well
    x = x * dn_max
    if read_noise_dn > 0:
        x = x + rng.normal(0.0, read_noise_dn, size=x.shape)
    frame = x[0] if x.shape[0] == 1 else x.mean(axis=0)  # the mean of one is itself, bit-exact
    return np.clip(np.rint(frame), 0, dn_max).astype(np.uint16)
