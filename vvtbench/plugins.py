"""Solver plug-ins: discovery and configuration (commands: :mod:`vvtbench.cli.solve`).

A solver is a class with::

    name: str                  # unique, lower-case
    version: str
    description: str           # one line, shown by `vvtbench solvers`
    Config: type               # a dataclass: every field has a default and
                               #   field(metadata={"help": "..."})
    def __init__(self, config: Config | None = None): ...
    def solve(self, problem: InverseProblem) -> Estimate: ...

Solvers are found in the ``vvtbench.solvers`` entry-point group, and a file can be named
directly as ``path/to/file.py:ClassName``. See docs/solvers.md.
"""

from __future__ import annotations

import dataclasses
import importlib
import importlib.util
import json
import sys
import types
import typing
from importlib.metadata import entry_points
from pathlib import Path

ENTRY_POINT_GROUP = "vvtbench.solvers"
# Shipped solvers, known by name even before the package metadata lists their entry points.
BUILTIN = {
    "vvt": "solvers.vvt:VVTSolver",
    "oracle": "solvers.oracle:OracleSolver",
    "homogeneous": "solvers.homogeneous:HomogeneousSolver",
    "sensitivity": "solvers.sensitivity:SensitivitySolver",
}
REQUIRED = ("name", "version", "description", "Config", "solve")


class PluginError(ValueError):
    """A solver cannot be found, loaded or configured; the message says what is allowed."""


def _import(target: str):
    module, _, attr = target.partition(":")
    if not attr:
        raise PluginError(f"{target!r}: expected 'module:Class' or 'path/to/file.py:Class'")
    if module.endswith(".py") or "/" in module or "\\" in module:
        path = Path(module)
        if not path.is_file():
            raise PluginError(f"{path}: solver file not found")
        mod_name = f"vvtbench_plugin_{path.stem}_{abs(hash(str(path.resolve()))) % 10**8}"
        spec = importlib.util.spec_from_file_location(mod_name, path)
        mod = importlib.util.module_from_spec(spec)
        sys.modules[mod_name] = mod
        try:
            spec.loader.exec_module(mod)
        except Exception as error:
            raise PluginError(f"{path}: error while importing: {error}") from error
    else:
        try:
            mod = importlib.import_module(module)
        except ImportError as error:
            raise PluginError(f"{module}: cannot import: {error}") from error
    if not hasattr(mod, attr):
        classes = [k for k, v in vars(mod).items() if isinstance(v, type) and hasattr(v, "solve")]
        raise PluginError(f"{module} has no attribute {attr!r}; solver classes there: "
                          f"{', '.join(classes) or 'none'}")
    return validate_solver_class(getattr(mod, attr), target)


def validate_solver_class(cls, where: str = ""):
    """Check the plug-in contract; return the class."""
    missing = [a for a in REQUIRED if not hasattr(cls, a)]
    if missing:
        raise PluginError(f"{where or cls}: not a solver: missing {', '.join(missing)} "
                          f"(a solver needs {', '.join(REQUIRED)})")
    if not dataclasses.is_dataclass(cls.Config):
        raise PluginError(f"{where or cls}: Config must be a dataclass")
    for f in dataclasses.fields(cls.Config):
        if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise PluginError(f"{where or cls}: Config field {f.name!r} has no default")
    return cls


def _registry() -> dict[str, str]:
    found = dict(BUILTIN)
    try:
        for ep in entry_points(group=ENTRY_POINT_GROUP):
            found[ep.name] = ep.value
    except Exception:  # broken metadata must not hide the built-ins
        pass
    return found


def list_solvers() -> dict[str, type]:
    """name -> solver class, for every registered solver that imports cleanly."""
    out = {}
    for name, target in sorted(_registry().items()):
        try:
            out[name] = _import(target)
        except PluginError:
            continue
    return out


def load_solver(name_or_path: str):
    """A solver class by registered name, ``module:Class`` or ``path/to/file.py:Class``."""
    reg = _registry()
    if name_or_path in reg:
        return _import(reg[name_or_path])
    if ":" in name_or_path:
        return _import(name_or_path)
    raise PluginError(f"unknown solver {name_or_path!r}; registered: {', '.join(sorted(reg))}"
                      "; or give path/to/file.py:ClassName")


def _base_types(tp) -> list[type]:
    if isinstance(tp, str):
        tp = {"float": float, "int": int, "bool": bool, "str": str}.get(tp.split("|")[0].strip(),
                                                                          str)
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        return [t for t in typing.get_args(tp) if t is not type(None)]
    return [tp]


def _convert(text: str, tp, key: str):
    allows_none = False
    hints = tp
    if isinstance(tp, str):
        allows_none = "None" in tp
    elif typing.get_origin(tp) in (typing.Union, types.UnionType):
        allows_none = type(None) in typing.get_args(tp)
    if allows_none and text.lower() in ("none", "null"):
        return None
    for t in _base_types(hints):
        try:
            if t is bool:
                low = text.lower()
                if low in ("1", "true", "yes", "on"):
                    return True
                if low in ("0", "false", "no", "off"):
                    return False
                raise ValueError
            if t in (int, float, str):
                return t(text)
            return json.loads(text)
        except (ValueError, TypeError, json.JSONDecodeError):
            continue
    names = "/".join(getattr(t, "__name__", str(t)) for t in _base_types(hints))
    raise PluginError(f"--set {key}={text}: cannot read {text!r} as {names}"
                      + (" (or none)" if allows_none else ""))


def parse_overrides(items: list[str] | None, config_cls):
    """A ``config_cls`` instance from defaults and ``["key=value", ...]`` overrides."""
    fields = {f.name: f for f in dataclasses.fields(config_cls)}
    hints = typing.get_type_hints(config_cls) if fields else {}
    values = {}
    for item in items or []:
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep:
            raise PluginError(f"--set {item!r}: expected key=value; keys: {', '.join(fields)}")
        if key not in fields:
            raise PluginError(f"--set {key}: unknown key for {config_cls.__name__}; allowed "
                              f"keys: {', '.join(fields)}")
        values[key] = _convert(text.strip(), hints.get(key, fields[key].type), key)
    return config_cls(**values)


def describe_config(config_cls) -> list[tuple[str, str, str]]:
    """(name, default, help) of every config field."""
    out = []
    for f in dataclasses.fields(config_cls):
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        out.append((f.name, repr(default), f.metadata.get("help", "")))
    return out
