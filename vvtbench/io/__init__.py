"""Files, the one place they are written: atomic writes, JSON and NumPy files, folder locks.

* :mod:`vvtbench.io.files`: atomic (temp file + rename), JSON-safe writing; no pickle.
* :mod:`vvtbench.io.lock`: one writer per output folder.

Every other stage imports from here; this package imports nothing of vvtbench.
"""

from .._aliases import forward

#: ``from vvtbench.io import NAME`` (the module before it became this package) still works,
#: with a DeprecationWarning naming vvtbench.io.files
__getattr__ = forward("vvtbench.io", "vvtbench.io.files", globals())
