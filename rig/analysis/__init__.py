"""Analysis of recorded runs: everything that fits a model to data, in one home.

- `fit/`: parameters by name, inverse-model least squares, and the joint multiple-shooting least squares
  on trajectories with its uncertainty (pure numerics on runs and models).
- `identification/`: the staged estimates read through the experiments' analyses, `identify` (what
  `hdrig fit` runs) and the validation table.
- `gaps/`: the model-gap workflow (`hdrig gaps`): what the model still gets wrong, named as effects.
"""
