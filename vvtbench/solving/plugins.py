"""Solver plug-ins: discovery and configuration (commands: :mod:`vvtbench.cli.solve`).

A solver is a class with::

    name: str                  # unique, lower-case
    version: str
    description: str           # one line, shown by `vvtbench solvers`
    Config: type               # a dataclass: every field has a default and
                               #   field(metadata={"help": "..."})
    def __init__(self, config: Config | None = None): ...
    def solve(self, problem: InverseProblem) -> Estimate: ...

A *reference* solver (an upper bound such as the oracle) sets ``uses_truth = True`` and is
called as ``solve(problem, truth)`` with the :class:`vvtbench.observe.Truth`; its rows are
marked as references in every table. Solvers are found in the ``vvtbench.solvers``
entry-point group, and a file can be named directly as ``path/to/file.py:ClassName``. See
docs/solvers.md.
"""

from __future__ import annotations

import dataclasses
import importlib
import importlib.util
import json
import sys
import time
import types
import typing
from collections.abc import Mapping
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any

ENTRY_POINT_GROUP = "vvtbench.solvers"
# Shipped solvers, known by name even before the package metadata lists their entry points.
BUILTIN = {
    "vvt": "solvers.vvt:VVTSolver",
    "oracle": "solvers.oracle:OracleSolver",
    "homogeneous": "solvers.homogeneous:HomogeneousSolver",
    "sensitivity": "solvers.sensitivity:SensitivitySolver",
    "learned": "solvers.learned:LearnedSolver",
}
REQUIRED = ("name", "version", "description", "Config", "solve")
# The shipped solvers that declare ``uses_truth`` (references): a results row of one of them
# must be marked as a reference (checked against the classes by the tests).
REFERENCE_BUILTINS = ("oracle",)


def name_problem(value: object, max_len: int = 80) -> str | None:
    """Why ``value`` cannot be a name in a results table, a CSV cell or a Markdown row (not a
    string; empty or too long; a control character or a space; a leading ``=``, ``+``, ``-``
    or ``@``, which spreadsheets read as a formula), or None when it can.

    >>> name_problem("vvt"), name_problem("=HYPERLINK(1)") is not None
    (None, True)
    """
    if not isinstance(value, str):
        return f"must be a string, got {type(value).__name__}"
    if not value or len(value) > max_len:
        return f"must have 1 to {max_len} characters"
    if not value.isprintable() or any(ch.isspace() for ch in value) or "|" in value:
        return "must be printable, without spaces, newlines or '|'"
    if value[0] in "=+-@":
        return "must not start with '=', '+', '-' or '@' (a spreadsheet formula)"
    return None


class PluginError(ValueError):
    """A solver cannot be found, loaded or configured; the message says what is allowed."""


SEALED_MARK = "VVTBENCH_SEALED"  # set in the environment of every sealed plug-in process


def refuse_when_sealed(what: str) -> None:
    """Raise :class:`PermissionError` inside a sealed plug-in process: ``what`` (making a
    problem's truth from a scene or a sample) is the evaluator's, never a plug-in's. A guard
    against the obvious route only: what keeps truth from a plug-in is that the sandbox shows
    it no scene, sample or truth (docs/explanation/sealed-evaluation.md)."""
    import os

    if os.environ.get(SEALED_MARK):
        raise PermissionError(f"{what} is not available to a sealed plug-in: a plug-in gets "
                              "its problem, never a scene, a sample or their truth")


def import_target(target: str, kind: str = "solver"):
    """The object ``target`` names: ``module:Attr`` or ``path/to/file.py:Attr`` (a file is
    imported as a module of its own); ``kind`` names it in errors."""
    module, _, attr = target.partition(":")
    if not attr:
        raise PluginError(f"{target!r}: expected 'module:Class' or 'path/to/file.py:Class'")
    if module.endswith(".py") or "/" in module or "\\" in module:
        path = Path(module)
        if not path.is_file():
            raise PluginError(f"{path}: {kind} file not found")
        mod_name = f"vvtbench_{kind}_{path.stem}_{abs(hash(str(path.resolve()))) % 10**8}"
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
        classes = [k for k, v in vars(mod).items() if isinstance(v, type)]
        raise PluginError(f"{module} has no attribute {attr!r}; classes there: "
                          f"{', '.join(classes) or 'none'}")
    return getattr(mod, attr)


@dataclasses.dataclass(frozen=True)
class Kind:
    """A kind of plug-in: its entry-point group, shipped built-ins and required attributes."""

    noun: str
    group: str
    builtin: dict
    required: tuple[str, ...]

    def validate(self, cls, where: str = ""):
        """Check the contract (attributes, a Config dataclass whose fields have defaults);
        return the class."""
        missing = [a for a in self.required if not hasattr(cls, a)]
        if missing:
            raise PluginError(f"{where or cls}: not a {self.noun}: missing "
                              f"{', '.join(missing)} (a {self.noun} needs "
                              f"{', '.join(self.required)})")
        for attr in ("name", "version"):
            problem = name_problem(getattr(cls, attr))
            if problem:
                raise PluginError(f"{where or cls}: {attr} {getattr(cls, attr)!r}: {problem}")
        if not dataclasses.is_dataclass(cls.Config):
            raise PluginError(f"{where or cls}: Config must be a dataclass")
        for f in dataclasses.fields(cls.Config):
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise PluginError(f"{where or cls}: Config field {f.name!r} has no default")
        return cls

    def registry(self) -> dict[str, str]:
        found = dict(self.builtin)
        try:
            for ep in entry_points(group=self.group):
                found[ep.name] = ep.value
        except Exception:  # broken metadata must not hide the built-ins
            pass
        return found

    def import_class(self, target: str):
        return self.validate(import_target(target, self.noun), target)

    def list(self) -> dict[str, type]:
        """name -> class, for every registered plug-in that imports cleanly."""
        out = {}
        for name, target in sorted(self.registry().items()):
            try:
                out[name] = self.import_class(target)
            except PluginError:
                continue
        return out

    def load(self, name_or_path: str):
        """A class by registered name, ``module:Class`` or ``path/to/file.py:Class``."""
        reg = self.registry()
        if name_or_path in reg:
            return self.import_class(reg[name_or_path])
        if ":" in name_or_path:
            return self.import_class(name_or_path)
        raise PluginError(f"unknown {self.noun} {name_or_path!r}; registered: "
                          f"{', '.join(sorted(reg))}; or give path/to/file.py:ClassName")


SOLVERS = Kind("solver", ENTRY_POINT_GROUP, BUILTIN, REQUIRED)


def validate_solver_class(cls, where: str = ""):
    """Check the solver contract; return the class."""
    return SOLVERS.validate(cls, where)


def list_solvers() -> dict[str, type]:
    """name -> solver class, for every registered solver that imports cleanly."""
    return SOLVERS.list()


def load_solver(name_or_path: str):
    """A solver class by registered name, ``module:Class`` or ``path/to/file.py:Class``."""
    return SOLVERS.load(name_or_path)


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
    """A ``config_cls`` instance from defaults and command-line ``["key=value", ...]``."""
    fields = {f.name: f for f in dataclasses.fields(config_cls)}
    values = {}
    for item in items or []:
        key, sep, text = item.partition("=")
        if not sep:
            raise PluginError(f"--set {item!r}: expected key=value; keys: {', '.join(fields)}")
        values[key.strip()] = text.strip()
    return config_from_mapping(config_cls, values)


def config_from_mapping(config_cls, values: Mapping[str, Any] | None):
    """A ``config_cls`` instance from defaults and a mapping of overrides (a suite's
    ``[solver.NAME]`` table, JSON). Strings are read as the field's type (``"1e-3"`` for a
    float, ``"none"`` for an optional field); numbers for float fields become floats."""
    fields = {f.name: f for f in dataclasses.fields(config_cls)}
    hints = typing.get_type_hints(config_cls) if fields else {}
    out = {}
    for key, value in (values or {}).items():
        if key not in fields:
            raise PluginError(f"--set {key}: unknown key for {config_cls.__name__}; allowed "
                              f"keys: {', '.join(fields)}")
        tp = hints.get(key, fields[key].type)
        if isinstance(value, str):
            out[key] = _convert(value, tp, key)
        elif isinstance(value, (int, float)) and not isinstance(value, bool) \
                and float in _base_types(tp) and int not in _base_types(tp):
            out[key] = float(value)
        else:
            out[key] = value
    try:
        config = config_cls(**out)
    except (TypeError, ValueError) as error:
        raise PluginError(f"{config_cls.__name__}: {error}") from None
    _check_values(config, set(out))
    return config


_BOUNDS = {"ge": (">=", lambda x, b: x >= b), "gt": (">", lambda x, b: x > b),
           "le": ("<=", lambda x, b: x <= b), "lt": ("<", lambda x, b: x < b)}


def _check_values(config, keys: set[str]) -> None:
    """The values given for ``keys`` must be finite and within the bounds the field declares
    in its metadata (``ge``, ``gt``, ``le``, ``lt``) or be one of its ``choices``; an integer
    iteration or count limit (``max_*``, ``n_*``, ``*_iter``) must be >= 1."""
    import math

    for f in dataclasses.fields(config):
        if f.name not in keys:
            continue
        value = getattr(config, f.name)
        choices = f.metadata.get("choices")
        if choices is not None and value not in choices:
            raise PluginError(f"--set {f.name}={value!r}: {type(config).__name__}.{f.name} "
                              f"must be one of {', '.join(map(repr, choices))}")
        for x in value if isinstance(value, (tuple, list)) else (value,):
            if isinstance(x, bool) or not isinstance(x, (int, float)):
                continue
            where = f"--set {f.name}={x!r}: {type(config).__name__}.{f.name}"
            if not math.isfinite(x):
                raise PluginError(f"{where} must be a finite number")
            bounds = [(op, f.metadata[op]) for op in _BOUNDS if op in f.metadata]
            if isinstance(x, int) and not bounds and (
                    f.name.startswith(("max_", "n_")) or f.name.endswith(("_iter", "_iters"))):
                bounds = [("ge", 1)]
            for op, bound in bounds:
                sign, ok = _BOUNDS[op]
                if not ok(x, bound):
                    raise PluginError(f"{where} must be {sign} {bound}")


def run_solver(cls, config, problem, truth=None):
    """Solve ``problem`` with solver class ``cls`` and ``config`` (a Config instance or a
    mapping of overrides); a reference solver (``uses_truth = True``) also gets ``truth``.

    Returns ``(estimate, wall seconds)``.
    """
    from .problem import Estimate

    if not dataclasses.is_dataclass(config) or isinstance(config, type):
        config = config_from_mapping(cls.Config, config)
    solver = cls(config)
    t0 = time.perf_counter()
    if getattr(cls, "uses_truth", False):
        if truth is None:
            raise PluginError(f"{cls.name} is a reference solver (uses_truth): it needs the "
                              "truth, which this source does not have")
        est = solver.solve(problem, truth)
    else:
        est = solver.solve(problem)
    wall = time.perf_counter() - t0
    if not isinstance(est, Estimate):
        raise PluginError(f"{cls.name}.solve returned {type(est).__name__}, not an Estimate")
    est.solver = est.solver or cls.name
    est.version = est.version or str(cls.version)
    est.config = est.config or dataclasses.asdict(config)
    return est, wall


def describe_config(config_cls) -> list[tuple[str, str, str]]:
    """(name, default, help) of every config field."""
    out = []
    for f in dataclasses.fields(config_cls):
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        out.append((f.name, repr(default), f.metadata.get("help", "")))
    return out


def solver_setup(spec: str, overrides: dict | None):
    """(class, config dict) for a solver spec with suite/CLI overrides."""
    cls = load_solver(spec)
    config = config_from_mapping(cls.Config, overrides)
    _check_types(cls, config, overrides or {})
    return cls, dataclasses.asdict(config)


def _check_types(cls, config, overrides: dict) -> None:
    """A suite's solver config value has its field's type (a table is not an int; true is not
    a number); numbers are finite."""
    import math
    import types
    import typing

    hints = typing.get_type_hints(cls.Config)
    for key in overrides:
        value = getattr(config, key)
        tp = hints.get(key)
        if tp is None:
            continue
        args = typing.get_args(tp) if typing.get_origin(tp) in (typing.Union,
                                                                types.UnionType) else (tp,)
        plain = [a for a in args if a in (int, float, str, bool, type(None))]
        if not plain or len(plain) != len(args):
            continue  # a list, a dict or a custom type: the solver checks it
        if value is None and type(None) in plain:
            continue
        ok = any(isinstance(value, a) and not (isinstance(value, bool) and a is not bool)
                 for a in plain if a is not type(None))
        if isinstance(value, int) and not isinstance(value, bool) and float in plain:
            ok = True
        names = " or ".join(a.__name__ if a is not type(None) else "none" for a in plain)
        if not ok:
            raise PluginError(f"{cls.name} config {key!r}: {value!r} is not allowed (allowed: "
                              f"{names})")
        if isinstance(value, float) and not math.isfinite(value):
            raise PluginError(f"{cls.name} config {key!r}: {value!r} is not a finite number")


def solver_inputs(cls, config: dict) -> dict:
    """Content hashes of the files a solver's config names (its ``cache_inputs(config)``, e.g.
    the learned baseline's weights): they join the solve task's key, so that a replaced file
    is never served from the cache under the same name."""
    hook = getattr(cls, "cache_inputs", None)
    return dict(hook(config)) if callable(hook) else {}
