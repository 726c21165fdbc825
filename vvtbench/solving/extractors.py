"""Motion extractor plug-ins: discovery and configuration.

An extractor turns video frames into per-pixel displacement fields relative to a reference
image, the temporal mean of the record in the pipeline (the contract is in
:mod:`vvtbench.motion.extractors`).  Extractors are found in the
``vvtbench.extractors`` entry-point group (like solvers in ``vvtbench.solvers``), and a file
can be named directly as ``path/to/file.py:ClassName``.  Shipped: ``phase`` (default) and
``farneback`` (OpenCV dense optical flow).  Configuration reuses the solvers' helpers
(:func:`vvtbench.solving.plugins.config_from_mapping`,
:func:`vvtbench.solving.plugins.describe_config`).
"""

from __future__ import annotations

import dataclasses
from typing import Any

from .plugins import Kind, PluginError, config_from_mapping, describe_config

__all__ = [
    "ENTRY_POINT_GROUP",
    "PluginError",
    "describe_config",
    "list_extractors",
    "load_extractor",
    "make_extractor",
    "validate_extractor_class",
]

ENTRY_POINT_GROUP = "vvtbench.extractors"
BUILTIN = {
    "phase": "vvtbench.motion.extractors:PhaseExtractor",
    "farneback": "vvtbench.motion.extractors:FarnebackExtractor",
}
REQUIRED = ("name", "version", "description", "Config", "prepare")


EXTRACTORS = Kind("extractor", ENTRY_POINT_GROUP, BUILTIN, REQUIRED)


def validate_extractor_class(cls: Any, where: str = "") -> Any:
    """Check the extractor contract (attributes, Config dataclass with defaults); return cls."""
    return EXTRACTORS.validate(cls, where)


def list_extractors() -> dict[str, type]:
    """name -> extractor class, for every registered extractor that imports cleanly."""
    return EXTRACTORS.list()


def load_extractor(name_or_path: str) -> type:
    """An extractor class by registered name, ``module:Class`` or ``path/to/file.py:Class``."""
    return EXTRACTORS.load(name_or_path)


def make_extractor(spec: Any = "phase", config: Any = None) -> Any:
    """An extractor instance from a name/path, a class or an instance, and a config.

    ``config`` is the class's ``Config`` instance or a mapping of overrides of its defaults
    (strings are read as the field's type, as for solvers); ignored for an instance.
    """
    if isinstance(spec, str):
        cls = load_extractor(spec)
    elif isinstance(spec, type):
        cls = validate_extractor_class(spec)
    else:
        validate_extractor_class(type(spec))
        return spec
    if config is None or not dataclasses.is_dataclass(config) or isinstance(config, type):
        config = config_from_mapping(cls.Config, config)
    return cls(config)
