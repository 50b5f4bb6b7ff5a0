"""Least squares of model parameters on runs: parameter names and values (`parameters`), and the
trajectory (shooting) fit with its uncertainty (`trajectory`). The staged identification that reads the
experiments' analyses lives above, in `rig.analysis.identification`."""
