"""Simulation: a scene becomes a mesh, material fields, eigenmodes and a transient response.

* :mod:`vvtbench.simulation.simulate`: the forward model, on the finite elements of
  :mod:`vvtbench.fem`.
"""
