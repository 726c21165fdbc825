"""``vvtbench export``: pack generated samples into one zarr/hdf5 dataset."""

# temporary shim; replaced when dataset/export CLI moves here
from ..export import main_export as main

__all__ = ["main"]
