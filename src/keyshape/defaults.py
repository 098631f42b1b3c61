"""Defaults shared by the API and the command line (kept import-light)."""

DEFAULT_SMOOTHNESS = 0.1  # zero-lag temporal smoothness of the solve (decompose.solve_weights)
DEFAULT_UPPER = 1.0  # upper bound of every key weight
