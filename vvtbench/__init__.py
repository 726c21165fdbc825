"""vvtbench: an open benchmark and dataset generator for visual vibration tomography."""

__version__ = "0.1.0"
