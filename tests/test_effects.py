"""Each vocabulary effect a model file may carry is honoured by the simulator, with its formula."""

from __future__ import annotations

import math

import numpy as np
import pytest
from reference import article_friction, variant

from model.params import HarmonicDriveModel
from model.plant import Plant
from model.registry import OUT, X

DT = 1e-4


def _one_step(plant: Plant, theta_m: float, omega_m: float, deflection: float = 0.0, time_s: float = 0.0):
    """Friction and spring torque applied over one step from a chosen state (load at rest)."""
    r = plant.model.mechanics.r
    plant.reset(theta_m=theta_m, omega_m=omega_m, theta_l=r * theta_m - deflection, omega_l=r * omega_m)
    plant.x[X.TIME] = time_s
    return plant.advance(np.zeros(1), "torque", 0.0, DT, 1)[0]


def test_direction_asymmetry_shifts_friction_by_f_dir_per_direction(seed: HarmonicDriveModel):
    model = variant(seed, kinematic_error=None, direction_asymmetry={"f_dir": 0.01})
    plant = Plant(model)
    for omega in (2.0, -2.0):
        base = float(article_friction(seed, np.array(1.0), np.array(omega)))
        assert _one_step(plant, 1.0, omega)[OUT.F_M] == pytest.approx(base + 0.01, rel=1e-12)


def test_stribeck_effect_adds_friction_that_decays_with_speed(seed: HarmonicDriveModel):
    model = variant(seed, kinematic_error=None, stribeck={"f_st": 0.02, "omega_st": 1.5})
    plant = Plant(model)
    for omega in (0.2, 1.5, 6.0):
        base = float(article_friction(seed, np.array(3.0), np.array(omega)))
        extra = 0.02 * math.exp(-((omega / 1.5) ** 2))
        assert _one_step(plant, 3.0, omega)[OUT.F_M] == pytest.approx(base + extra, rel=1e-12)


def test_load_dependent_friction_grows_with_transmitted_torque(seed: HarmonicDriveModel):
    model = variant(seed, kinematic_error=None, load_dependent_friction={"c_Ts": 2e-3})
    plant = Plant(model)
    K_s = model.transmission.K_s
    assert K_s is not None
    deflection = 0.01  # T_s = 10 N·m
    row = _one_step(plant, 5.0, 4.0, deflection)
    assert row[OUT.T_S] == pytest.approx(K_s * deflection, rel=1e-12)
    base = float(article_friction(seed, np.array(5.0), np.array(4.0)))
    assert row[OUT.F_M] == pytest.approx(base + 2e-3 * K_s * deflection, rel=1e-12)


def test_thermal_drift_scales_friction_over_time(seed: HarmonicDriveModel):
    model = variant(seed, kinematic_error=None, thermal_drift={"d_th": -0.2, "tau_th": 100.0})
    plant = Plant(model)
    base = float(article_friction(seed, np.array(0.0), np.array(3.0)))
    for time_s in (0.0, 100.0, 1000.0):
        scale = 1 - 0.2 * (1 - math.exp(-time_s / 100.0))
        assert _one_step(plant, 0.0, 3.0, time_s=time_s)[OUT.F_M] == pytest.approx(base * scale, rel=1e-12)


def _piecewise_torque(deflection: float, K1: float, K2: float, K3: float, T1: float, T2: float) -> float:
    """Catalog curve: deflection = T/K1 up to T1, + (T−T1)/K2 up to T2, + (T−T2)/K3 beyond; inverted."""
    d1 = T1 / K1
    d2 = d1 + (T2 - T1) / K2
    d = abs(deflection)
    torque = K1 * d if d <= d1 else (T1 + K2 * (d - d1) if d <= d2 else T2 + K3 * (d - d2))
    return math.copysign(torque, deflection)


@pytest.mark.parametrize("deflection", [2e-4, -2e-4, 8e-4, -1.2e-3, 3e-3])
def test_nonlinear_stiffness_follows_the_catalog_curve(seed: HarmonicDriveModel, deflection: float):
    curve = {"K1": 3.1e4, "K2": 5.0e4, "K3": 5.7e4, "T1": 14.0, "T2": 48.0}
    model = variant(seed, kinematic_error=None, transmission={"K_s": 3.1e4}, nonlinear_stiffness=curve)
    row = _one_step(Plant(model), 0.0, 0.0, deflection)
    assert row[OUT.T_S] == pytest.approx(_piecewise_torque(deflection, **curve), rel=1e-12)


def test_hysteresis_adds_a_bounded_torque_loop(seed: HarmonicDriveModel):
    model = variant(seed, kinematic_error=None, hysteresis={"T_h": 2.0, "delta_h": 1e-4})
    plant = Plant(model)
    t = np.arange(int(2.0 / DT)) * DT
    # Hold the load with a large external torque swing: the transmission deflects back and forth.
    rows = plant.advance(np.zeros_like(t), "torque", 20.0 * np.sin(2 * np.pi * 1.0 * t), DT, 1)
    r = model.mechanics.r
    K_s = model.transmission.K_s
    assert K_s is not None
    deflection = r * rows[:, OUT.THETA_M] - rows[:, OUT.THETA_L]
    hysteretic = rows[:, OUT.T_S] - K_s * deflection
    assert np.max(np.abs(hysteretic)) <= 2.0 + 1e-9
    assert np.max(np.abs(hysteretic)) > 1.5, "the element saturates near T_h on large swings"
    late = t >= 1.0
    loop_area = np.sum(rows[late, OUT.T_S][:-1] * np.diff(deflection[late]))
    assert loop_area > 0, "a hysteresis loop dissipates energy"


def test_kinematic_error_offsets_the_rigid_output(seed_rigid: HarmonicDriveModel):
    ke = seed_rigid.kinematic_error
    assert ke is not None
    plant = Plant(seed_rigid)
    rows = plant.advance(np.full(5000, 3.0), "voltage", 0.0, DT, 1)
    theta_m = rows[:, OUT.THETA_M]
    expected = seed_rigid.mechanics.r * theta_m + ke.A * np.sin(ke.k * theta_m + ke.phi)
    np.testing.assert_allclose(rows[:, OUT.THETA_L], expected, rtol=0, atol=1e-15)


def test_kinematic_error_loads_the_flexible_transmission(seed: HarmonicDriveModel):
    # Motor held still at θ_m where sin(k·θ_m) = 1: the spring sees θ_err = A at the output.
    ke = seed.kinematic_error
    assert ke is not None and seed.transmission.K_s is not None
    theta_m = (math.pi / 2) / ke.k
    plant = Plant(seed)
    plant.reset(theta_m=theta_m, theta_l=seed.mechanics.r * theta_m)
    row = plant.advance(np.zeros(1), "torque", 0.0, DT, 1)[0]
    assert row[OUT.T_S] == pytest.approx(seed.transmission.K_s * ke.A, rel=1e-9)
