"""Identification: a model fitted to the campaign's runs, then judged against them.

It sits beside the experiments that made the runs, because it reads them through the experiments' own
analyses (steady windows, FRFs, segment labels) and replays validation runs on a simulated rig:

- `pipeline`: what a stage is (`Stage`: name, the experiments it reads, the parameters it gives) and
  what it says (`Note`);
- `staged`: the stages as objects, run in the order its `PIPELINE` declares, and the book that believes
  or holds their values; `dynamics_stage`, `friction_stage`: their least squares, one MODEL.md equation
  per stage, on the runs, to a starting point with standard errors; `column_stage`: what runs without
  metadata determine;
- `identify`: the starting point, the joint refinement on trajectories (`rig.analysis.fit.trajectory`),
  the report; what `hdrig fit` and the service call;
- `validation`: the article's validation table, model beside measurement.

The pure least squares on runs (`rig.analysis.fit.parameters`, `rig.analysis.fit.trajectory`) lives beside
it, in `rig.analysis.fit`.
"""

from rig.analysis.identification.identify import Identification, ParameterRow, identify, save_identified

__all__ = ["Identification", "ParameterRow", "identify", "save_identified"]
