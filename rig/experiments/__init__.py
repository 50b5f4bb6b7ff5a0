"""The article's experiments, by name. `campaign` runs them all in CAMPAIGN_ORDER."""

from __future__ import annotations

from rig.experiments.base import Experiment
from rig.experiments.chirp import Chirp
from rig.experiments.load_variation import LoadVariation
from rig.experiments.position_friction import PositionFriction
from rig.experiments.pulse import Pulse
from rig.experiments.speed_sweep import SpeedSweep
from rig.experiments.tracking import Ramp, Sine, Step

EXPERIMENTS: dict[str, Experiment] = {
    e.name: e
    for e in (SpeedSweep(), PositionFriction(), Pulse(), LoadVariation(), Step(), Sine(), Ramp(), Chirp())
}

CAMPAIGN_ORDER: tuple[str, ...] = tuple(EXPERIMENTS)
