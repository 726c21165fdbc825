"""Solving: the problem a solver gets, the truth it never sees, plug-ins and their sandbox.

* :mod:`vvtbench.solving.problem`: :class:`InverseProblem` and :class:`Estimate`, the
  contract between ``observe`` and a solver (imports only :mod:`vvtbench.fem`).
* :mod:`vvtbench.solving.truth`: :class:`Truth`, held by the evaluator.
* :mod:`vvtbench.solving.plugins`: solver plug-ins: discovery, configuration, set-up.
* :mod:`vvtbench.solving.extractors`: motion-extractor plug-ins: discovery, configuration.
* :mod:`vvtbench.solving.sealed`: every plug-in call runs in a sealed child process.

A plug-in author imports from :mod:`vvtbench.api`.
"""
