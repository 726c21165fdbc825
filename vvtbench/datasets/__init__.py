"""Datasets for learning and for release: many samples as one portable, checkable thing.

* :mod:`vvtbench.datasets.export`, :mod:`~vvtbench.datasets.card`,
  :mod:`~vvtbench.datasets.croissant`: pack samples into Zarr or HDF5 with a dataset card
  and a Croissant description; :mod:`vvtbench.datasets.packed` reads them back.
* :mod:`vvtbench.datasets.release`: frozen releases (a definition, a build, a check).
* :mod:`vvtbench.datasets.instances`, :mod:`~vvtbench.datasets.loaders`,
  :mod:`~vvtbench.datasets.extracted`: ``(problem, truth)`` instances and fixed-shape items
  for learners, with the modes extracted from a sample's video kept beside it.
"""
