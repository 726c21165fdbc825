"""Rendering: pinhole camera, speckle textures and a float-precision pyrender backend.

``Renderer`` (and the rest of :mod:`vvtbench.render.pyrender_backend`) is
imported lazily so that the camera and texture tools work without OpenGL.
"""

from __future__ import annotations

from typing import Any

from .camera import Camera
from .texture import TexturedMesh, speckle_texture, triplanar_mapping

__all__ = [
    "Camera",
    "EGLUnavailableError",
    "Renderer",
    "TexturedMesh",
    "speckle_texture",
    "triplanar_mapping",
]


def __getattr__(name: str) -> Any:
    if name in ("Renderer", "EGLUnavailableError"):
        from . import pyrender_backend

        return getattr(pyrender_backend, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
