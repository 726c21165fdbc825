"""Motion extractor plug-ins: discovery and configuration.

An extractor turns video frames into per-pixel displacement fields relative to the first
frame (the contract is in :mod:`vvtbench.motion.extractors`).  Extractors are found in the
``vvtbench.extractors`` entry-point group (like solvers in ``vvtbench.solvers``), and a file
can be named directly as ``path/to/file.py:ClassName``.  Shipped: ``phase`` (default) and
``farneback`` (OpenCV dense optical flow).  Configuration reuses the solvers' helpers
(:func:`vvtbench.plugins.config_from_mapping`, :func:`vvtbench.plugins.describe_config`).
"""

from __future__ import annotations

import dataclasses
from importlib.metadata import entry_points
from typing import Any

from .plugins import PluginError, config_from_mapping, describe_config

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


def validate_extractor_class(cls: Any, where: str = "") -> Any:
    """Check the extractor contract (attributes, Config dataclass with defaults); return cls."""
    missing = [a for a in REQUIRED if not hasattr(cls, a)]
    if missing:
        raise PluginError(f"{where or cls}: not an extractor: missing {', '.join(missing)} "
                          f"(an extractor needs {', '.join(REQUIRED)})")
    if not dataclasses.is_dataclass(cls.Config):
        raise PluginError(f"{where or cls}: Config must be a dataclass")
    for f in dataclasses.fields(cls.Config):
        if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise PluginError(f"{where or cls}: Config field {f.name!r} has no default")
    return cls


def _import(target: str) -> Any:
    from .plugins import import_target

    return validate_extractor_class(import_target(target, "extractor"), target)

def _registry() -> dict[str, str]:
    found = dict(BUILTIN)
    try:
        for ep in entry_points(group=ENTRY_POINT_GROUP):
            found[ep.name] = ep.value
    except Exception:  # broken metadata must not hide the built-ins
        pass
    return found


def list_extractors() -> dict[str, type]:
    """name -> extractor class, for every registered extractor that imports cleanly."""
    out = {}
    for name, target in sorted(_registry().items()):
        try:
            out[name] = _import(target)
        except PluginError:
            continue
    return out


def load_extractor(name_or_path: str) -> type:
    """An extractor class by registered name, ``module:Class`` or ``path/to/file.py:Class``."""
    reg = _registry()
    if name_or_path in reg:
        return _import(reg[name_or_path])
    if ":" in name_or_path:
        return _import(name_or_path)
    raise PluginError(f"unknown extractor {name_or_path!r}; registered: "
                      f"{', '.join(sorted(reg))}; or give path/to/file.py:ClassName")


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
