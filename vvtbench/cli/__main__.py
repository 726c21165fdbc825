"""``python -m vvtbench.cli``: the ``vvtbench`` command."""

import sys

from . import main

sys.exit(main())
