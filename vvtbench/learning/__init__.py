"""Learned-solver building blocks (features of the observation for trainable solvers)."""
