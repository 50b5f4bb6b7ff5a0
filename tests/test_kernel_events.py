"""Karnopp events located inside the step (model/kernel.py `_karnopp`): the trajectory is continuous in
the parameters, and with constant torque each event lands where the equations put it.

The kernel steps at a fixed dt with the torques held over the step. Before, a stick/slip event (a
reversal's stop, the switch from the static to the moving law where a breaking-away shaft leaves the
stick band) took effect at the start of the step after it happened, so a tiny change of an inertia could
move it by a whole step: the replayed trajectory, and the trajectory fit's cost, were staircases in J_m
and J_l (/tmp/notes/h-sigma.md). Now each is located inside its step.
"""

from __future__ import annotations

import numpy as np
import pytest
from reference import variant

from model.params import HarmonicDriveModel, load_model
from model.plant import Plant
from model.registry import X

DT_S = 1e-4
F_C = 0.05  # N·m: Coulomb level of the test axis
F_S = 0.08  # N·m: its static level (well above F_C, so a law switch a step late is a large error)


def _coulomb_axis() -> tuple[Plant, float, float]:
    """A rigid axis with Coulomb and static friction only (no viscous, no load friction, no ripple):
    under constant torque each phase has a constant acceleration. Returns the plant, J [kg·m²] and the
    stick band [rad/s]."""
    seed = load_model("seed-rigid")
    motor = {"motor_law": "coulomb_viscous", "f_cm": F_C, "f_sm": F_S, "b_m": 0.0}
    model = variant(seed, motor_friction=motor, load_friction=None, kinematic_error=None)
    mech = model.mechanics
    return Plant(model), mech.J_m + mech.r**2 * mech.J_l, model.numerics.omega_stick_m


def _speed_at(plant: Plant, torque_nm: float, steps: int) -> float:
    plant.advance(np.full(steps, torque_nm), mode="torque", dt_s=DT_S)
    return float(plant.x[X.OMEGA_M])


# Rounding is all that is left when every phase's acceleration is constant and every event is located
# exactly: ~1e-16 relative per operation over a few hundred steps of ~10 rad/s is ~1e-13 rad/s, i.e.
# ~1e-16 s of event time. A millionth of a step is far above that and far below the up-to-one-step error
# of an event taken at the next step's start.
EVENT_TOLERANCE_S = 1e-6 * DT_S


@pytest.mark.parametrize("excess_nm", np.linspace(2e-4, 1e-3, 9))
def test_breakaway_leaves_the_band_where_the_equations_say(excess_nm: float):
    """From rest under a constant torque ψ = F_S + excess: the stuck branch's friction F_S holds until the
    speed reaches the band ε at t_e = ε·J/excess (a few steps in, at a different phase of the step for
    each excess), then the moving law F_C: ω(T) = ε + (ψ − F_C)·(T − t_e)/J. The t_e read back from the
    kernel's ω(T) must be the analytic one."""
    plant, inertia, band = _coulomb_axis()
    psi = F_S + excess_nm
    steps = 200
    omega_end = _speed_at(plant, psi, steps)
    t_exit = band * inertia / excess_nm
    assert t_exit < steps * DT_S / 2
    t_exit_kernel = steps * DT_S - (omega_end - band) * inertia / (psi - F_C)
    assert abs(t_exit_kernel - t_exit) <= EVENT_TOLERANCE_S, (
        f"band exit at {t_exit_kernel / DT_S:.6f} steps, analytic {t_exit / DT_S:.6f}"
    )


@pytest.mark.parametrize("omega0", np.linspace(0.5, 0.62, 9))
def test_reversal_stops_at_its_zero_crossing_and_breaks_away_in_the_same_step(omega0: float):
    """Moving at ω0 > 0 against a constant torque ψ < −F_S: braked by ψ and F_C until ω = 0 at
    t_z = ω0·J/(|ψ| + F_C); then stuck, and since |ψ| > F_S it breaks away backwards under F_S until −ε
    at t_e = t_z + ε·J/(|ψ| − F_S); the moving law after: ω(T) = −ε − (|ψ| − F_C)·(T − t_e)/J."""
    plant, inertia, band = _coulomb_axis()
    psi = -0.1
    plant.reset(omega_m=omega0)
    steps = 100
    omega_end = _speed_at(plant, psi, steps)
    t_exit = omega0 * inertia / (-psi + F_C) + band * inertia / (-psi - F_S)
    assert t_exit < steps * DT_S / 2
    t_exit_kernel = steps * DT_S + (omega_end + band) * inertia / (-psi - F_C)
    assert abs(t_exit_kernel - t_exit) <= EVENT_TOLERANCE_S, (
        f"reverse band exit at {t_exit_kernel / DT_S:.6f} steps, analytic {t_exit / DT_S:.6f}"
    )


def _end_positions(model: HarmonicDriveModel, field: str, relative: np.ndarray) -> np.ndarray:
    """θ_m after 2 s of a 2 Hz torque sine that stops the axis and breaks it away at every reversal,
    for the inertia `field` scaled by (1 + each relative change)."""
    t = np.arange(20_000) * DT_S
    torque = 0.12 * np.sin(2 * np.pi * 2.0 * t)  # N·m; the seed's breakaway is ~0.08 N·m with the load's
    ends = []
    for rel in relative:
        mech = model.mechanics
        plant = Plant(variant(model, mechanics={field: getattr(mech, field) * (1 + rel)}))
        plant.advance(torque, mode="torque", dt_s=DT_S)
        ends.append(plant.x[X.THETA_M])
    return np.array(ends)


@pytest.mark.parametrize("field", ["J_m", "J_l"])
def test_trajectory_is_continuous_in_the_inertias(field: str):
    """The seed's rigid axis (position-dependent article friction, load friction), 2 s with 8 stops and
    breakaways: its end position over 61 inertias 1e-5 apart (±0.03 %, the trajectory fit's σ scale).

    A smooth function's differences between neighbours are its slope times the spacing, nearly equal over
    so small a range (measured within 6 %); an event moved by a whole step adds that step's travel
    (~|ω|·dt, 10-100× the smooth difference here; the old kernel: up to 140× the median). Bound: no
    difference above 1.5× the median."""
    relative = np.linspace(-3e-4, 3e-4, 61)
    steps = np.abs(np.diff(_end_positions(load_model("seed-rigid"), field, relative)))
    median = float(np.median(steps))
    assert median > 0.0
    assert steps.max() <= 1.5 * median, f"largest difference {steps.max():.3g} rad, median {median:.3g} rad"
