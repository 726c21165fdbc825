"""Sub-pixel motion extraction from video (phase-based, complex steerable pyramid)."""

from .phase import PhaseMotion, iter_displacements
from .pyramid import Band, SteerablePyramid, get_pyramid, max_scales

__all__ = [
    "Band",
    "PhaseMotion",
    "SteerablePyramid",
    "get_pyramid",
    "iter_displacements",
    "max_scales",
]
