"""The article's baseline friction laws, selectable per side, against their formulas."""

from __future__ import annotations

import numpy as np
import pytest
from reference import variant
from scipy.optimize import brentq

from model.params import HarmonicDriveModel
from model.plant import Plant
from model.registry import OUT

DT = 1e-4
F_C, F_S, OMEGA_S = 0.05, 0.08, 2.0
# Viscous per side, so that each side's steady speed is reached within seconds on a rigid axis.
B = {"m": 1e-3, "l": 1.0}

LAWS = {
    "coulomb_viscous": {"f_c": F_C, "f_s": F_S},
    "stribeck": {"f_c": F_C, "f_s": F_S, "omega_s": OMEGA_S},
    "lugre": {"f_c": F_C, "f_s": F_S, "omega_s": OMEGA_S, "sigma0": 200.0, "sigma1": 0.05},
    "dahl": {"f_c": F_C, "sigma0": 200.0},
}


def _steady_level(law: str, omega: float, side: str = "m") -> float:
    """Each law's friction at constant speed (LuGre's steady state is its Stribeck curve)."""
    level = F_C + (F_S - F_C) * np.exp(-((omega / OMEGA_S) ** 2)) if law in ("stribeck", "lugre") else F_C
    return float(np.sign(omega) * level + B[side] * omega)


def _side_section(law: str, side: str) -> dict[str, object]:
    """A friction section for `side` ('m' or 'l') with the law's parameters under their unique names."""
    names = {"f_c": f"f_c{side}", "f_s": f"f_s{side}", "omega_s": f"omega_s{side}"}
    names |= {"sigma0": f"sigma0_{side}", "sigma1": f"sigma1_{side}"}
    section: dict[str, object] = {f"{'motor' if side == 'm' else 'load'}_law": law, f"b_{side}": B[side]}
    section |= {names[key]: value for key, value in LAWS[law].items()}
    return section


def _rigid_with(seed_rigid: HarmonicDriveModel, law: str) -> HarmonicDriveModel:
    return variant(
        seed_rigid, motor_friction=_side_section(law, "m"), load_friction=None, kinematic_error=None
    )


@pytest.mark.parametrize("law", ["coulomb_viscous", "stribeck"])
@pytest.mark.parametrize("omega", [0.1, 1.0, 3.0, 20.0, -0.5, -4.0])
def test_karnopp_laws_friction_at_speed_equals_formula(
    seed_rigid: HarmonicDriveModel, law: str, omega: float
):
    plant = Plant(_rigid_with(seed_rigid, law))
    assert plant.steady_friction(np.array([0.0]), np.array([omega]))[0] == pytest.approx(
        _steady_level(law, omega), rel=1e-12
    )


@pytest.mark.parametrize("law", list(LAWS))
@pytest.mark.parametrize("side", ["m", "l"])
def test_constant_torque_reaches_the_speed_where_friction_balances_it(
    seed_rigid: HarmonicDriveModel, law: str, side: str
):
    # Rigid axis, friction on one side only: τ = F(ω) on the motor, or τ = r·F_l(r·ω) on the load side.
    r = seed_rigid.mechanics.r
    if side == "m":
        model = _rigid_with(seed_rigid, law)
        torque = 0.09
        expected = brentq(lambda w: _steady_level(law, w) - torque, 1e-6, 1e3)
    else:
        frictionless = {"motor_law": "coulomb_viscous", "f_cm": 0.0, "f_sm": 0.0, "b_m": 0.0}
        model = variant(
            seed_rigid,
            motor_friction=frictionless,
            load_friction=_side_section(law, "l"),
            kinematic_error=None,
        )
        torque = 0.09 * r
        expected = brentq(lambda w: r * _steady_level(law, r * w, "l") - torque, 1e-6, 1e5)
    plant = Plant(model)
    plant.advance(np.full(int(6.0 / DT), torque), "torque", 0.0, DT, 1000)
    # Tolerance 2e-3: the slowest approach, the load side's J/(r²·b_l) = 0.75 s, has decayed to e^-8
    # after 6 s; the bristle states of LuGre/Dahl settle within milliseconds.
    assert plant.state.omega_m == pytest.approx(expected, rel=2e-3)


def test_lugre_presliding_is_bounded_below_breakaway_and_slides_above(seed_rigid: HarmonicDriveModel):
    sigma0 = LAWS["lugre"]["sigma0"]
    plant = Plant(_rigid_with(seed_rigid, "lugre"))
    torque = 0.5 * F_C
    plant.advance(np.full(int(0.5 / DT), torque), "torque", 0.0, DT, 1)
    first = plant.state.theta_m
    plant.advance(np.full(int(0.5 / DT), torque), "torque", 0.0, DT, 1)
    # Presliding: a micro-displacement of the order of τ/σ0 (the bristles bend), then it stays.
    assert torque / sigma0 < first < 5 * torque / sigma0
    assert abs(plant.state.theta_m - first) < 0.05 * first
    plant = Plant(_rigid_with(seed_rigid, "lugre"))
    plant.advance(np.full(int(0.5 / DT), 1.1 * F_S), "torque", 0.0, DT, 1)
    assert plant.state.theta_m > 1.0, "above F_s it slides"


def test_dahl_torque_displacement_loop_has_hysteresis(seed_rigid: HarmonicDriveModel):
    plant = Plant(_rigid_with(seed_rigid, "dahl"))
    t = np.arange(int(2.0 / DT)) * DT
    rows = plant.advance(0.04 * np.sin(2 * np.pi * 1.0 * t), "torque", 0.0, DT, 1)
    second_cycle = t >= 1.0
    theta = rows[second_cycle, OUT.THETA_M]
    friction = rows[second_cycle, OUT.F_M]
    # The friction–displacement loop encloses an area: energy dissipated per cycle > 0.
    area = np.sum(friction[:-1] * np.diff(theta))
    assert area > 1e-6
    assert np.max(np.abs(friction)) <= F_C + B["m"] * np.max(np.abs(rows[:, OUT.OMEGA_M])) + 1e-9
