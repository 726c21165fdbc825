"""Scoring: every number a board shows is made here, from estimates and truth.

* :mod:`vvtbench.scoring.metrics`: NC, intrinsic resolution, mode match, validity
  (docs/metrics.md).
* :mod:`vvtbench.scoring.extraction`: extracted modes against the true ones (precision,
  recall over detectable modes, frequency, damping and shape errors).
* :mod:`vvtbench.scoring.efficiency`: a motion extractor's efficiency against the
  Cramér-Rao ruler (:mod:`vvtbench.render.crb`, which generation writes into each sample).
* :mod:`vvtbench.scoring.stats`: bootstrap intervals and paired comparisons over instances.
* :mod:`vvtbench.scoring.ceiling`: the mode misfit of a voxel field and the ceiling search
  (the highest NC among fields that explain the data; docs/metrics.md, "Ceiling").
* :mod:`vvtbench.scoring.homogenize`: voxel means and the homogenised truth on the inference
  grid (docs/metrics.md, "Truth on the inference grid").
"""
