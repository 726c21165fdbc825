"""Limits of the sealed children that run plug-ins (:mod:`vvtbench.solving.sealed`) in a suite run.

Every extract and solve task runs its plug-in in a sealed child with a time limit
(:data:`DEFAULT_TIMEOUT` seconds unless ``--timeout`` or the suite's ``timeout`` says
otherwise) and an address-space limit (:func:`default_memory_bytes`); the parent kills the
child's whole process group when the time is up and classifies what happened (``timeout``,
``crashed``, ``out of memory``) from the exit status and the response, never trusting a
response that is missing.
"""

from __future__ import annotations

import os

from ..solving.sealed import DEFAULT_TIMEOUT, SealedError
from ..solving.sealed import kill_running as _kill_sealed

__all__ = ["DEFAULT_TIMEOUT", "SealedError", "default_memory_bytes", "kill_running"]

DEFAULT_MEMORY_FRACTION = 0.75  # of the machine's memory, divided among the workers


def machine_memory_bytes() -> int | None:
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return None


def default_memory_bytes(workers: int = 1) -> int | None:
    """The default memory limit of one plug-in child: 75 % of the machine's memory /
    workers."""
    total = machine_memory_bytes()
    return None if total is None else int(total * DEFAULT_MEMORY_FRACTION / max(1, workers))


def kill_running() -> None:
    """End every plug-in child this process started (Ctrl-C, SIGTERM)."""
    _kill_sealed()
