"""Camera sensor model of the generated videos: shot and read noise, quantisation to DN.

* :func:`sensor_dn`: average noisy sub-frame intensities into one frame of digital numbers.
* :func:`noise_rng`: the per-frame seeded noise generator (reproducible samples).
* :func:`electrons_to_dn`, :func:`is_noise_free`, :func:`describe_sensor`: the scene's camera
  in physical units and in words ("noise-free sensor" for a camera without noise).

The camera of the shipped scenes
--------------------------------
The shipped scenes (``scenes/*.toml``) film with a typical monochrome high-speed CMOS camera
(docs/scenes.md, "Camera noise"): full well :data:`FULL_WELL_ELECTRONS` (10 000 e-), read
noise :data:`HIGH_SPEED_READ_NOISE_ELECTRONS` (15 e- rms per frame) and shot noise.  The
renderer writes 16-bit DN with full well at full scale, a gain of ``65535 / 10000 = 6.55``
DN/e-, so the read noise is :data:`HIGH_SPEED_READ_NOISE_DN` (98.3 DN) in the scene files.
These are typical values of the class, not those of a particular product.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "FULL_WELL_ELECTRONS",
    "HIGH_SPEED_READ_NOISE_DN",
    "HIGH_SPEED_READ_NOISE_ELECTRONS",
    "describe_sensor",
    "electrons_to_dn",
    "is_noise_free",
    "noise_rng",
    "sensor_dn",
]

#: Default full-well capacity (electrons) of the simulated sensor, used by shot noise.
FULL_WELL_ELECTRONS = 10000.0
#: Read noise (electrons rms per frame) of the shipped scenes' camera: typical of a
#: monochrome high-speed CMOS at full frame rate (10-20 e-).
HIGH_SPEED_READ_NOISE_ELECTRONS = 15.0
#: The same read noise in 16-bit DN at :data:`FULL_WELL_ELECTRONS` to full scale, to the
#: 0.1 DN the scene files give (``render.read_noise_dn = 98.3``).
HIGH_SPEED_READ_NOISE_DN = 98.3
_NOISE_STREAM = 0x5EED_0001


def noise_rng(seed: int, frame: int) -> np.random.Generator:
    """The sensor-noise generator of video frame ``frame`` of a scene with ``seed``."""
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, _NOISE_STREAM, int(frame)])


def electrons_to_dn(electrons: float, full_well: float = FULL_WELL_ELECTRONS,
                    bit_depth: int = 16) -> float:
    """Electrons as DN of a ``bit_depth`` video whose full scale is the full well.

    Parameters
    ----------
    electrons : float
        A charge or a noise level (electrons).
    full_well : float, default :data:`FULL_WELL_ELECTRONS`
        Full-well capacity (electrons), mapped to ``2^bit_depth - 1`` DN.
    bit_depth : int, default 16
        Bits of the video.

    Returns
    -------
    float
        ``electrons * (2^bit_depth - 1) / full_well`` (DN).
    """
    if not full_well > 0:
        raise ValueError(f"full_well must be > 0, got {full_well}")
    return float(electrons) * float(2 ** int(bit_depth) - 1) / float(full_well)


def is_noise_free(read_noise_dn: float, shot_noise: bool) -> bool:
    """True for a camera without shot or read noise: its frames are the rounded render."""
    return not shot_noise and not float(read_noise_dn) > 0


def describe_sensor(read_noise_dn: float, shot_noise: bool,
                    full_well: float = FULL_WELL_ELECTRONS, bit_depth: int = 16) -> str:
    """The camera noise in words, e.g. ``"noise-free sensor (rounding to whole DN only)"`` or
    ``"shot noise (full well 10000 e-) + read noise 98.3 DN (15.0 e-)"``.

    Parameters
    ----------
    read_noise_dn : float
        Read-noise standard deviation per sub-frame (DN), ``render.read_noise_dn``.
    shot_noise : bool
        Poisson shot noise, ``render.shot_noise``.
    full_well : float, default :data:`FULL_WELL_ELECTRONS`
        Full-well capacity (electrons), ``render.full_well_electrons``.
    bit_depth : int, default 16
        Bits of the video, ``render.bit_depth``.

    Returns
    -------
    str
        One line; it starts with ``"noise-free sensor"`` exactly when :func:`is_noise_free`.
    """
    if is_noise_free(read_noise_dn, shot_noise):
        return "noise-free sensor (rounding to whole DN only)"
    parts = []
    if shot_noise:
        parts.append(f"shot noise (full well {float(full_well):g} e-)")
    r = float(read_noise_dn)
    if r > 0:
        e = r / electrons_to_dn(1.0, full_well, bit_depth)
        parts.append(f"read noise {r:g} DN ({e:.3g} e-)")
    return " + ".join(parts) + ("" if shot_noise else ", no shot noise")


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
