"""The ``invert`` command (being built: it raises a clear error until it is)."""

from __future__ import annotations

import sys


def main_invert(argv: list[str] | None = None) -> int:
    print("error: `vvtbench invert` is not built yet", file=sys.stderr)
    return 2
