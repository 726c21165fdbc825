"""The stable public surface: what a solver plug-in, an extractor plug-in or a learner imports.

>>> from vvtbench.api import Estimate, InverseProblem, eigenmodes
>>> Estimate.__module__
'vvtbench.solving.problem'

Import from here, not from the modules that define these names: the package's modules are
grouped by pipeline stage and may move; the names below stay, and one that must go is
deprecated here first. Each name is loaded when it is first used, so importing this module
costs nothing (a sealed plug-in pays only for what it touches).

Solver plug-ins (docs/solvers.md)
    :class:`InverseProblem` (what a solver gets), :class:`Estimate` (what it returns), and
    helpers that need no truth: :func:`eigenmodes`, :class:`Factorization`,
    :func:`cluster_frequencies` (the forward model's modes), :func:`mac_matrix`,
    :func:`mode_match`, :func:`normalized_correlation`, :func:`is_constant`,
    :func:`invalid_reason`; :class:`Truth` is handed only to a reference solver that declares
    ``uses_truth``.
Learned solvers
    :func:`reference_basis`, :func:`mesh_key`, :func:`step_features`, :func:`linear_step`
    (modal features of a problem), :func:`fit_mlp`, :func:`mlp_predict`.
Extractor plug-ins (docs/how-to/add-an-extractor.md)
    :func:`validate_extractor_class`, the contract a motion extractor is checked against.
Learners and data (docs/tutorials/train-on-the-data.md)
    :func:`open_sample`, :func:`open_dataset`, :func:`iter_instances`,
    :class:`InstanceDataset`, :func:`load_release`, :func:`verify_copy`, :func:`observe`.
Files
    :func:`write_npz`, :func:`write_json` (atomic), :func:`sha256_file`.
"""

from __future__ import annotations

import importlib
from typing import Any

#: public name -> the module that defines it
NAMES: dict[str, str] = {
    "InverseProblem": "vvtbench.solving.problem",
    "Estimate": "vvtbench.solving.problem",
    "Truth": "vvtbench.solving.truth",
    "eigenmodes": "vvtbench.fem.modal",
    "Factorization": "vvtbench.fem.modal",
    "cluster_frequencies": "vvtbench.fem.modal",
    "mac_matrix": "vvtbench.modes.mac",
    "mode_match": "vvtbench.scoring.metrics",
    "normalized_correlation": "vvtbench.scoring.metrics",
    "is_constant": "vvtbench.scoring.metrics",
    "invalid_reason": "vvtbench.scoring.metrics",
    "reference_basis": "vvtbench.learning.modal_features",
    "mesh_key": "vvtbench.learning.modal_features",
    "step_features": "vvtbench.learning.modal_features",
    "linear_step": "vvtbench.learning.modal_features",
    "fit_mlp": "vvtbench.learning.mlp",
    "mlp_predict": "vvtbench.learning.mlp",
    "validate_extractor_class": "vvtbench.solving.extractors",
    "open_sample": "vvtbench.samples.reader",
    "open_dataset": "vvtbench.datasets.packed",
    "iter_instances": "vvtbench.datasets.instances",
    "InstanceDataset": "vvtbench.datasets.loaders",
    "load_release": "vvtbench.datasets.release",
    "verify_copy": "vvtbench.datasets.release",
    "observe": "vvtbench.observe",
    "write_npz": "vvtbench.io.files",
    "write_json": "vvtbench.io.files",
    "sha256_file": "vvtbench.samples.reader",
}

__all__ = sorted(NAMES)


def __getattr__(name: str) -> Any:
    module = NAMES.get(name)
    if module is None:
        raise AttributeError(f"module 'vvtbench.api' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(NAMES))
