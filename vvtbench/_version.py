"""The vvtbench version, in its own module so that no module imports the package back."""

__version__ = "0.1.0"
