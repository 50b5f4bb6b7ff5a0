"""The breakaway stage with few events: one tightly bracketed breakaway is still an estimate, its σ
from its bracket; none is a skip that says so.

With the kernel's events located inside the step (model/kernel.py), the stage's 2 % bracket keeps the
truer events and fewer of them: 2 of 20 bench campaigns (seeds 105 and 115) had one each. The stage
then skipped, and static_factor stayed at the start's value (+25 %) with no σ; with one event's
estimate it came out −0.24 % (σ 0.37 %) and −0.11 % (σ 0.28 %) after the joint step.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from model.params import HarmonicDriveModel, load_model
from model.plant import Plant
from model.run import Run
from rig.analysis.fit.parameters import with_values
from rig.analysis.identification import friction_stage


@pytest.fixture(scope="module")
def seed() -> HarmonicDriveModel:
    return load_model("seed")


def _runs() -> list[Run]:
    t = np.arange(3) * 1e-3
    return [Run({"t": t, "theta_m": np.zeros(3), "i_a": np.zeros(3), "u": np.zeros(3)}, {})]


def test_one_breakaway_gives_static_factor_with_the_bracket_as_its_sigma(seed, monkeypatch):
    """The level a breakaway measures is f_s = factor·M(θ) + E(θ) (`Plant.breakaway_friction`); the
    stage inverts that at the event's θ and direction, and a level known to a bracket of width w has
    σ = w/√12 (uniform within it), w/M in factor units."""
    theta, direction, factor = 0.37, 1.0, 1.0466
    plant = Plant(with_values(seed, {"static_factor": factor}))
    level = plant.breakaway_friction(theta, direction)[0]
    moving = (
        Plant(with_values(seed, {"static_factor": 2.0})).breakaway_friction(theta, direction)[0]
        - Plant(with_values(seed, {"static_factor": 1.0})).breakaway_friction(theta, direction)[0]
    )
    width = 0.015 * level
    monkeypatch.setattr(
        friction_stage, "breakaway_levels", lambda run, m, o: [(level, width, theta, direction)]
    )
    solved = friction_stage.breakaway(_runs(), seed, 0.0)
    assert solved.values["static_factor"] == pytest.approx(factor, rel=1e-9)
    assert solved.std_errors["static_factor"] == pytest.approx(width / moving / math.sqrt(12), rel=1e-9)
    assert "1 breakaway" in solved.notes[-1]


def test_no_breakaway_is_a_skip_that_says_so(seed, monkeypatch):
    monkeypatch.setattr(friction_stage, "breakaway_levels", lambda run, m, o: [])
    solved = friction_stage.breakaway(_runs(), seed, 0.0)
    assert "static_factor" not in solved.values
    assert solved.notes == ["skipped: no tightly bracketed breakaway in the runs"]


def _events_at(seed: HarmonicDriveModel, factors: list[float], share: float) -> tuple[list, float]:
    """Events whose levels are the given factors' at θ = 0.37 forward, each bracketed to `share` of its
    level; with the moving magnitude M there (the level's change per unit of factor)."""
    theta, direction = 0.37, 1.0
    level = {
        f: Plant(with_values(seed, {"static_factor": f})).breakaway_friction(theta, direction)[0]
        for f in factors
    }
    once, twice = (
        Plant(with_values(seed, {"static_factor": f})).breakaway_friction(theta, direction)[0]
        for f in (1.0, 2.0)
    )
    return [(level[f], share * level[f], theta, direction) for f in factors], twice - once


def test_tight_events_cannot_claim_less_than_their_brackets(seed, monkeypatch):
    """Four events within 0.01 % of each other, each bracketed to 1.8 %: each level is known only to
    its bracket (uniform, σ = w/√12), so the mean's σ is that over √4, not the spread's over √4 (which
    is ~40× smaller here; a bench campaign missed by 5σ so)."""
    factors = [1.0340, 1.0341, 1.0342, 1.0343]
    events, moving = _events_at(seed, factors, 0.018)
    monkeypatch.setattr(friction_stage, "breakaway_levels", lambda run, m, o: events)
    solved = friction_stage.breakaway(_runs(), seed, 0.0)
    bracket = math.sqrt(np.mean([(w / moving) ** 2 for _, w, _, _ in events]) / 12.0)
    assert solved.values["static_factor"] == pytest.approx(np.mean(factors), rel=1e-9)
    assert solved.std_errors["static_factor"] == pytest.approx(bracket / 2.0, rel=1e-9)
    assert solved.std_errors["static_factor"] > 20 * np.std(factors, ddof=1) / 2.0


def test_scattered_events_keep_their_spread(seed, monkeypatch):
    """Events that disagree by more than their brackets say so through their spread: σ = s/√n."""
    factors = [1.00, 1.04, 1.08]
    events, _ = _events_at(seed, factors, 0.002)
    monkeypatch.setattr(friction_stage, "breakaway_levels", lambda run, m, o: events)
    solved = friction_stage.breakaway(_runs(), seed, 0.0)
    assert solved.std_errors["static_factor"] == pytest.approx(0.04 / math.sqrt(3), rel=1e-6)
