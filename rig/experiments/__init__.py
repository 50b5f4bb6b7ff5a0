"""The article's experiments, by name. `campaign` runs them all in CAMPAIGN_ORDER."""

from __future__ import annotations

from rig.experiments.base import Experiment
from rig.experiments.speed_sweep import SpeedSweep

EXPERIMENTS: dict[str, Experiment] = {e.name: e for e in (SpeedSweep(),)}

CAMPAIGN_ORDER: tuple[str, ...] = tuple(EXPERIMENTS)
