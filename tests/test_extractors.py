"""Contract test of every registered motion extractor (``vvtbench.extractors`` group).

Each extractor runs on a tiny synthetic video: a band-limited periodic speckle translated by
a known sub-pixel sinusoid (exact Fourier shift); the displacements it yields must have the
right shape and follow the motion, and ``extract_modes`` must find the mode with it.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from vvtbench.modes import extract_modes
from vvtbench.solving.extractors import (
    PluginError,
    describe_config,
    list_extractors,
    load_extractor,
    make_extractor,
)

N = 64


def speckle_video(T: int = 48, amp: float = 0.3, f_bins: float = 6.0, seed: int = 0):
    rng = np.random.default_rng(seed)
    wy = 2 * np.pi * np.fft.fftfreq(N)[:, None]
    wx = 2 * np.pi * np.fft.fftfreq(N)[None, :]
    F = np.fft.fft2(rng.standard_normal((N, N))) * np.exp(-0.5 * np.hypot(wx, wy) ** 2)
    F[N // 2, :] = 0
    F[:, N // 2] = 0
    t = np.arange(T)
    dx = amp * np.sin(2 * np.pi * f_bins * t / T)
    frames = np.stack([np.fft.ifft2(F * np.exp(-1j * wx * d)).real for d in dx])
    return frames.astype(np.float32), dx


def test_builtins_registered() -> None:
    reg = list_extractors()
    assert {"phase", "farneback"} <= set(reg)


@pytest.mark.parametrize("name", sorted(list_extractors()))
def test_extractor_contract(name: str) -> None:
    cls = load_extractor(name)
    assert cls.name == name and isinstance(cls.version, str) and cls.description
    assert dataclasses.is_dataclass(cls.Config)
    for fname, _, help_ in describe_config(cls.Config):
        assert help_, f"{name}.Config.{fname} has no help metadata"
    frames, dx = speckle_video()
    motion = make_extractor(name).prepare(frames[0])
    assert tuple(motion.shape) == (N, N)
    h, w = motion.grid_shape
    batches = list(motion.iter_displacements(iter(frames), batch=20))
    assert [b.shape[0] for b in batches] == [20, 20, 8]
    d = np.concatenate(batches)
    assert d.shape == (len(frames), h, w, 2) and d.dtype == np.float32
    assert np.all(np.isfinite(d))
    assert motion.confidence is None or motion.confidence.shape == (N, N)
    assert motion.grid_confidence is None or motion.grid_confidence.shape == (h, w)
    inner = d[:, h // 4 : -h // 4, w // 4 : -w // 4]
    mx = inner[..., 0].mean(axis=(1, 2))
    assert np.abs(mx - dx).max() < 0.05 * 0.3 + 0.01, np.abs(mx - dx).max()
    assert np.abs(inner[..., 1]).mean() < 0.02
    assert isinstance(motion.describe(), dict)
    ms = extract_modes(frames, 48.0, extractor=name, keep_camera_shake=True)
    assert len(ms) >= 1 and ms.metadata["extractor"]["name"] == name
    i = int(np.argmax(ms.amplitudes_px))
    assert abs(ms.frequencies_hz[i] - 6.0) <= 1.0


def test_config_overrides_and_errors() -> None:
    ext = make_extractor("farneback", {"winsize": "9"})
    assert ext.config.winsize == 9
    with pytest.raises(PluginError, match="unknown key"):
        make_extractor("phase", {"nope": 1})
    with pytest.raises(PluginError, match="unknown extractor"):
        load_extractor("no-such-extractor")
