"""Inverse-solver plug-ins shipped with vvtbench.

Each module defines one solver class (see docs/solvers.md for the interface):

* ``vvt`` -- the paper's alternating closed-form / dual-ascent method (Feng et al. 2022);
* ``oracle`` -- convex least squares with full-field 3-D modes and exact eigenvalues;
* ``homogeneous`` -- the best uniform field (the floor);
* ``sensitivity`` -- classical FE model updating (Gauss-Newton on eigenvalues and MAC).

They are registered under the ``vvtbench.solvers`` entry-point group; ``vvtbench.solving.plugins``
also knows them by name when the package metadata is not (yet) installed.
"""
