"""The experiments, by name. `campaign` runs the article's eight in CAMPAIGN_ORDER; `compensation` needs a
model file and tests it, and `endurance` runs for hours, so they stand outside the campaign."""

from __future__ import annotations

from model.errors import UserInputError
from rig.experiments.base import Experiment
from rig.experiments.chirp import Chirp
from rig.experiments.compensation import Compensation
from rig.experiments.efficiency_map import EfficiencyMap
from rig.experiments.endurance import Endurance
from rig.experiments.load_variation import LoadVariation
from rig.experiments.no_load_torque import NoLoadTorque
from rig.experiments.position_friction import PositionFriction
from rig.experiments.pulse import Pulse
from rig.experiments.speed_sweep import SpeedSweep
from rig.experiments.starting_torque import StartingTorque
from rig.experiments.torsional_stiffness import TorsionalStiffness
from rig.experiments.tracking import Ramp, Sine, Step
from rig.experiments.transmission_accuracy import TransmissionAccuracy
from rig.experiments.warm_up import WarmUp

CAMPAIGN_ORDER: tuple[str, ...] = (
    "speed-sweep",
    "position-friction",
    "pulse",
    "load-variation",
    "step",
    "sine",
    "ramp",
    "chirp",
)

EXPERIMENTS: dict[str, Experiment] = {
    e.name: e
    for e in (
        SpeedSweep(),
        PositionFriction(),
        Pulse(),
        LoadVariation(),
        Step(),
        Sine(),
        Ramp(),
        Chirp(),
        Compensation(),
        Endurance(),
        WarmUp(),
        TorsionalStiffness(),
        EfficiencyMap(),
        NoLoadTorque(),
        StartingTorque(),
        TransmissionAccuracy(),
    )
}

CAMPAIGN = "campaign"
"""The name that runs every experiment in CAMPAIGN_ORDER, each its own run."""


def experiment_named(name: str) -> Experiment:
    """The experiment called `name`; an unknown name is a one-line error listing the known ones."""
    try:
        return EXPERIMENTS[name]
    except KeyError:
        known = ", ".join([*EXPERIMENTS, CAMPAIGN])
        raise UserInputError(f"unknown experiment {name!r} (experiments: {known})") from None
