"""Physical yardsticks of the benchmark's scores.

* :mod:`vvtbench.scoring.crb`: the Cramér-Rao bound of image motion in a sample's video and
  the detectability of its true modes by it.
* :mod:`vvtbench.scoring.efficiency`: a motion extractor's efficiency
  ``eta = sigma_CRB^2 / MSE`` against that bound, and the known-texture ideal estimator.
"""
