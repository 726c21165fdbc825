"""Samples on disk, the contract between stages: generate a sample folder, read one back.

* :mod:`vvtbench.samples.generate`: simulate, render and write one sample folder.
* :mod:`vvtbench.samples.jobs`: one sample per worker process (local pool or Dask).
* :mod:`vvtbench.samples.progress`: per-stage progress of a generation.
* :mod:`vvtbench.samples.reader`: open, check and read a sample folder (docs/dataset.md).
* :mod:`vvtbench.samples.compare`: two samples of one scene compared value by value within
  stated tolerances (a regenerated release instance against the frozen one).
"""
