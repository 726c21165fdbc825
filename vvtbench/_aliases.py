"""Import paths from before the package was grouped by pipeline stage, kept one release.

``import vvtbench.problem`` (and every other path in :data:`MOVED`) still works: it gives a
module that forwards each name to the module's new home and warns once per name with a
:class:`DeprecationWarning` naming the new path. Plug-ins should import from
:mod:`vvtbench.api`. The three modules that became packages of the same name
(``vvtbench.io``, ``vvtbench.scene``, ``vvtbench.video``) forward their old names through
:func:`forward` in their ``__init__``.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import sys
import types
import warnings
from typing import Any

#: old module path -> new module path
MOVED: dict[str, str] = {
    "vvtbench.bench.lock": "vvtbench.io.lock",
    "vvtbench.families": "vvtbench.scene.families",
    "vvtbench.scenes_resolve": "vvtbench.bench.resolve",
    "vvtbench.simulate": "vvtbench.simulation.simulate",
    "vvtbench.sensor": "vvtbench.render.sensor",
    "vvtbench.scoring.crb": "vvtbench.render.crb",
    "vvtbench.field.readers": "vvtbench.video.cameras",
    "vvtbench.dataset": "vvtbench.samples.reader",
    "vvtbench.generate": "vvtbench.samples.generate",
    "vvtbench.generate_jobs": "vvtbench.samples.jobs",
    "vvtbench.mac": "vvtbench.modes.mac",
    "vvtbench.problem": "vvtbench.solving.problem",
    "vvtbench.truth": "vvtbench.solving.truth",
    "vvtbench.plugins": "vvtbench.solving.plugins",
    "vvtbench.extractors": "vvtbench.solving.extractors",
    "vvtbench.sealed": "vvtbench.solving.sealed",
    "vvtbench.metrics": "vvtbench.scoring.metrics",
    "vvtbench.extraction_scores": "vvtbench.scoring.extraction",
    "vvtbench.stats": "vvtbench.scoring.stats",
    "vvtbench.packed": "vvtbench.datasets.packed",
    "vvtbench.export": "vvtbench.datasets.export",
    "vvtbench.export_card": "vvtbench.datasets.card",
    "vvtbench.croissant": "vvtbench.datasets.croissant",
    "vvtbench.release": "vvtbench.datasets.release",
    "vvtbench.data": "vvtbench.datasets.instances",
    "vvtbench.loaders": "vvtbench.datasets.loaders",
    "vvtbench.leaderboard": "vvtbench.reporting.leaderboard",
    "vvtbench.plots": "vvtbench.reporting.plots",
}


def _warn(old: str, new: str, stacklevel: int = 3) -> None:
    warnings.warn(f"{old} has moved to {new}; import it from there (plug-ins: from "
                  "vvtbench.api)", DeprecationWarning, stacklevel=stacklevel)


def forward(old: str, new: str, namespace: dict[str, Any]) -> Any:
    """A module ``__getattr__`` that serves ``old``'s names from ``new``, warning once per name
    (the name is then kept in ``namespace``, the module's own globals)."""

    def __getattr__(name: str) -> Any:
        if name.startswith("__"):
            raise AttributeError(name)
        target = importlib.import_module(new)
        try:
            value = getattr(target, name)
        except AttributeError:
            raise AttributeError(f"module {old!r} has no attribute {name!r}") from None
        _warn(f"{old}.{name}", f"{new}.{name}")
        namespace[name] = value
        return value

    return __getattr__


class _Finder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    def find_spec(self, fullname: str, path: Any = None, target: Any = None):
        if fullname not in MOVED:
            return None
        return importlib.machinery.ModuleSpec(fullname, self)

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> types.ModuleType:
        module = types.ModuleType(spec.name, f"Moved to {MOVED[spec.name]}.")
        module.__getattr__ = forward(spec.name, MOVED[spec.name], vars(module))  # type: ignore
        return module

    def exec_module(self, module: types.ModuleType) -> None:
        _warn(module.__name__, MOVED[module.__name__], stacklevel=4)


def install() -> None:
    """Put the finder on ``sys.meta_path`` once."""
    if not any(isinstance(f, _Finder) for f in sys.meta_path):
        sys.meta_path.append(_Finder())
