"""The article's experiments, by name. `campaign` runs them all in CAMPAIGN_ORDER."""

from __future__ import annotations

from model.errors import UserInputError
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

CAMPAIGN = "campaign"
"""The name that runs every experiment in CAMPAIGN_ORDER, each its own run."""


def experiment_named(name: str) -> Experiment:
    """The experiment called `name`; an unknown name is a one-line error listing the known ones."""
    try:
        return EXPERIMENTS[name]
    except KeyError:
        known = ", ".join([*EXPERIMENTS, CAMPAIGN])
        raise UserInputError(f"unknown experiment {name!r} (experiments: {known})") from None
