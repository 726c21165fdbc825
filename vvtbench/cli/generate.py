"""``vvtbench generate``: render scenes into sample folders."""

# temporary shim; replaced when dataset/export CLI moves here
from ..dataset import build_generate_parser as build_parser
from ..dataset import main_generate as main
from ..dataset import run_generate as run

__all__ = ["build_parser", "main", "run"]
