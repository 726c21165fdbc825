"""What every video reader shares: :class:`VideoError` and frames as float32 gray."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["VideoError", "to_gray"]

_LUMA = np.array([0.299, 0.587, 0.114])


class VideoError(ValueError):
    """A video cannot be decoded or encoded, or is not what the caller expects."""


def to_gray(frame: ArrayLike) -> NDArray[np.float32]:
    """``(H, W)`` or ``(H, W, C)`` frame to float32 gray.

    Integer frames are scaled to ``[0, 1]`` by their dtype's maximum; ``C = 3`` or ``4``
    (alpha ignored) uses Rec. 601 luma weights, ``C = 1`` is squeezed.
    """
    a = np.asarray(frame)
    scale = 1.0
    if np.issubdtype(a.dtype, np.integer):
        scale = 1.0 / float(np.iinfo(a.dtype).max)
    elif a.dtype == np.bool_:
        a = a.astype(np.float32)
    if a.ndim == 3:
        if a.shape[-1] == 1:
            a = a[..., 0]
        elif a.shape[-1] in (3, 4):
            a = a[..., :3].astype(np.float32) @ _LUMA.astype(np.float32)
        else:
            raise ValueError(f"colour frames must have 1, 3 or 4 channels, got {a.shape}")
    if a.ndim != 2:
        raise ValueError(f"frames must be (H, W) or (H, W, C), got {a.shape}")
    out = a.astype(np.float32)
    if scale != 1.0:
        out *= np.float32(scale)
    return out
