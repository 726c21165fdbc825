"""vvtbench: an open benchmark and dataset generator for visual vibration tomography."""

from . import _aliases
from ._version import __version__

_aliases.install()

__all__ = ["__version__", "open_dataset", "open_sample"]


def __getattr__(name: str):
    if name == "open_sample":
        from .samples.reader import open_sample

        return open_sample
    if name == "open_dataset":
        from .datasets.packed import open_dataset

        return open_dataset
    raise AttributeError(f"module 'vvtbench' has no attribute {name!r}")
