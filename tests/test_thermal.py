"""The `thermal` section (effect `temperature_dependence`): the two-node network of docs/MODEL.md and the
motor friction's law exp(−beta_T·(T_g − T_ref)), against numbers derived from the equations by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest
from reference import article_friction, variant

from model import kernel as k
from model.inputs import parse_input_spec
from model.params import HarmonicDriveModel, ModelFileError, load_model, parse_model, save_model
from model.plant import Plant
from model.registry import OUT, Mode, X
from model.simulate import simulate
from rig.config import RIG_DIR, load_rig_config
from rig.interface import ControlMode
from sim_backend.simulated_drive import TRUTH_COLUMNS, SimulatedDrive

DT = 1e-4
NETWORK = {"T_amb": 20.0, "T_ref": 25.0, "C_w": 0.5, "C_g": 2.0, "R_wg": 1.0, "R_wa": 4.0, "R_ga": 2.0}
"""Small capacities, so that the network settles within seconds of simulated time."""


def _frictionless(seed_rigid: HarmonicDriveModel, **thermal: float) -> HarmonicDriveModel:
    """The rigid seed with no friction at all, the network above and `thermal`'s changes."""
    return variant(
        seed_rigid,
        kinematic_error=None,
        load_friction=None,
        motor_friction={"motor_law": "coulomb_viscous", "f_cm": 0.0, "b_m": 0.0},
        thermal={**NETWORK, "beta_T": 0.0, **thermal},
    )


def _steady_rises(heat_w: float, heat_g: float, t: dict[str, float]) -> np.ndarray:
    """The network's steady rises above ambient [K], from G·rise = heat (nodal analysis)."""
    g_wg, g_wa, g_ga = 1 / t["R_wg"], 1 / t["R_wa"], 1 / t["R_ga"]
    conductance = np.array([[g_wg + g_wa, -g_wg], [-g_wg, g_wg + g_ga]])
    return np.linalg.solve(conductance, np.array([heat_w, heat_g]))


def _slowest_time_constant(t: dict[str, float]) -> float:
    g_wg, g_wa, g_ga = 1 / t["R_wg"], 1 / t["R_wa"], 1 / t["R_ga"]
    a = np.array([[(g_wg + g_wa) / t["C_w"], -g_wg / t["C_w"]], [-g_wg / t["C_g"], (g_wg + g_ga) / t["C_g"]]])
    return float(1 / np.min(np.linalg.eigvals(a).real))


def test_without_the_section_nothing_changes_and_beta_zero_changes_no_mechanics(seed: HarmonicDriveModel):
    """With beta_T = 0 the factor is exactly 1.0: every mechanical column is the seed's, bit for bit; the
    seed itself has no temperatures (NaN)."""
    plain = simulate(seed, "sine:amp=2,freq=0.5", 2.0, diagnostics=True)
    warm = simulate(
        variant(seed, thermal={**NETWORK, "beta_T": 0.0}), "sine:amp=2,freq=0.5", 2.0, diagnostics=True
    )
    for column in plain.columns:
        np.testing.assert_array_equal(warm[column], plain[column], err_msg=column)
    rows = Plant(seed).advance(np.full(10, 1.0))
    assert np.isnan(rows[:, OUT.TEMP_MOTOR]).all() and np.isnan(rows[:, OUT.TEMP_GEAR]).all()
    assert "temperature_dependence" not in seed.effects


def test_copper_loss_settles_at_the_networks_steady_state(seed_rigid: HarmonicDriveModel):
    model = _frictionless(seed_rigid)
    current_a = 3.0
    r = model.mechanics.r
    plant = Plant(model)
    # The load torque balances the motor's, so the joint stays at rest: only i²R heats.
    tau_ext = model.motor.K_m * current_a / r
    duration_s = 40 * _slowest_time_constant(NETWORK)
    n = round(duration_s / DT)
    rows = plant.advance(np.full(n, current_a), "current", tau_ext, DT, decim=n // 10)
    assert np.all(rows[:, OUT.OMEGA_M] == 0.0)
    expected = _steady_rises(current_a**2 * model.motor.R, 0.0, NETWORK)
    got = np.array([plant.x[X.RISE_MOTOR], plant.x[X.RISE_GEAR]])
    # Explicit Euler's fixed point is the ODE's steady state; what is left is e^−40 of the transient.
    np.testing.assert_allclose(got, expected, rtol=1e-9)
    assert rows[-1, OUT.TEMP_MOTOR] == pytest.approx(20.0 + expected[0], rel=1e-6)


def test_one_node_warms_with_time_constant_c_times_r(seed_rigid: HarmonicDriveModel):
    """Winding cut off from the gear (R_wg huge): rise(t) = P·R_wa·(1 − e^(−t/τ)), τ = C_w·R_wa = 2 s."""
    model = _frictionless(seed_rigid, R_wg=1e12)
    current_a = 2.0
    heat_w = current_a**2 * model.motor.R
    tau_s = NETWORK["C_w"] * NETWORK["R_wa"]
    n = round(3 * tau_s / DT)
    decim = round(0.1 / DT)
    plant = Plant(model)
    rows = plant.advance(
        np.full(n, current_a), "current", model.motor.K_m * current_a / model.mechanics.r, DT, decim
    )
    rise = rows[1:, OUT.TEMP_MOTOR] - NETWORK["T_amb"]
    t = rows[1:, OUT.T]
    fitted_tau = -t / np.log(1 - rise / (heat_w * NETWORK["R_wa"]))
    # Explicit Euler's error on τ is dt/(2τ) relative = 2.5e-5.
    np.testing.assert_allclose(fitted_tau, tau_s, rtol=5e-5)
    assert not np.allclose(fitted_tau, tau_s, rtol=1e-6)  # the integrator's error is there, and small
    np.testing.assert_allclose(rows[:, OUT.TEMP_GEAR], NETWORK["T_amb"], rtol=0, atol=1e-9)  # cut off


def test_friction_power_heats_the_gear_to_the_hand_solved_steady_state(seed_rigid: HarmonicDriveModel):
    """Torque mode, τ_m = 0.07 N·m against f_cm = 0.05 N·m and b_m = 0.001 N·m·s/rad: the joint settles
    at ω* = 20 rad/s, all of τ_m·ω* = 1.4 W is friction heat in the gear, (τ_m/K_m)²·R copper loss in
    the winding."""
    model = variant(
        _frictionless(seed_rigid),
        motor_friction={"motor_law": "coulomb_viscous", "f_cm": 0.05, "b_m": 0.001},
    )
    torque_nm = 0.07
    omega_star = (torque_nm - 0.05) / 0.001
    heat_g = torque_nm * omega_star
    heat_w = (torque_nm / model.motor.K_m) ** 2 * model.motor.R
    plant = Plant(model)
    n = round(40 * _slowest_time_constant(NETWORK) / DT)
    rows = plant.advance(np.full(n, torque_nm), "torque", 0.0, DT, decim=n // 10)
    assert rows[-1, OUT.OMEGA_M] == pytest.approx(omega_star, rel=1e-9)
    assert rows[-1, OUT.F_M] * rows[-1, OUT.OMEGA_M] == pytest.approx(heat_g, rel=1e-9)
    expected = _steady_rises(heat_w, heat_g, NETWORK)
    np.testing.assert_allclose([plant.x[X.RISE_MOTOR], plant.x[X.RISE_GEAR]], expected, rtol=1e-6)
    assert expected[1] > 2.0  # the friction's share is the larger part of the gear's rise
    assert _steady_rises(heat_w, 0.0, NETWORK)[1] < 0.5 * expected[1]


@pytest.mark.parametrize("delta_k", [-35.0, -10.0, 0.0, 15.0])
@pytest.mark.parametrize("omega", [3.0, -2.0])
def test_motor_friction_scales_by_exp_minus_beta_delta_t(
    seed: HarmonicDriveModel, delta_k: float, omega: float
):
    """The catalog's no-load torque falls ~4× from −10 to +40 °C: beta_T = ln 4 / 50 K. Levels, f_dir and
    b_m all scale, so the whole F_m does: F_m(T_g) = F_m(T_ref)·exp(−beta_T·(T_g − T_ref))."""
    beta = math.log(4.0) / 50.0
    base = variant(
        seed, kinematic_error=None, direction_asymmetry={"f_dir": 0.004}, motor_friction={"b_m": 2e-4}
    )
    gear_c = 25.0 + delta_k
    warm = variant(base, thermal={**NETWORK, "beta_T": beta, "T_gear0": gear_c})
    reference = float(article_friction(seed, np.array(1.0), np.array(omega)))
    reference += 0.004 + 2e-4 * omega  # f_dir: a magnitude +f_dir forward, −f_dir backward
    plant = Plant(warm)
    r = seed.mechanics.r
    plant.reset(theta_m=1.0, omega_m=omega, theta_l=r * 1.0, omega_l=r * omega)
    row = plant.advance(np.zeros(1), "torque", 0.0, DT, 1)[0]
    assert row[OUT.TEMP_GEAR] == gear_c
    assert row[OUT.F_M] == pytest.approx(reference * math.exp(-beta * delta_k), rel=1e-12)
    if delta_k == -35.0:  # −10 °C against +40 °C: the stated 4×
        assert math.exp(-beta * delta_k) / math.exp(-beta * 15.0) == pytest.approx(4.0, rel=1e-12)


def test_thermal_drift_still_loads_and_applies_beside_the_thermal_section(seed: HarmonicDriveModel):
    """Old files keep `thermal_drift` (a factor of the time since the start); with `thermal` both apply."""
    old = load_model("seed-wear")
    assert old.thermal is None and old.thermal_drift is not None
    beta = 0.02
    both = variant(
        seed,
        kinematic_error=None,
        thermal_drift={"d_th": -0.2, "tau_th": 100.0},
        thermal={**NETWORK, "beta_T": beta, "T_gear0": 45.0},
    )
    assert {"thermal_drift", "temperature_dependence"} <= set(both.effects)
    plant = Plant(both)
    plant.reset(theta_m=0.0, omega_m=3.0, theta_l=0.0, omega_l=0.03, time_s=100.0)
    row = plant.advance(np.zeros(1), "torque", 0.0, DT, 1)[0]
    base = float(article_friction(seed, np.array(0.0), np.array(3.0)))
    drift = 1 - 0.2 * (1 - math.exp(-1.0))
    assert row[OUT.F_M] == pytest.approx(base * drift * math.exp(-beta * 20.0), rel=1e-12)


@pytest.mark.parametrize("suffix", [".yaml", ".json"])
def test_a_model_with_a_thermal_section_round_trips(tmp_path, suffix: str):
    model = load_model("seed-thermal")
    assert model.thermal is not None and "temperature_dependence" in model.effects
    again = load_model(save_model(model, tmp_path / f"m{suffix}"))
    assert again == model and again.content_hash() == model.content_hash()
    data = {**model.to_dict(), "thermal": {**model.to_dict()["thermal"], "T_gear0": 60.0}}
    assert load_model(save_model(parse_model(data), tmp_path / f"n{suffix}")).thermal.T_gear0 == 60.0  # type: ignore[union-attr]


def test_the_preset_warms_from_ambient():
    model = load_model("seed-thermal")
    assert model.thermal is not None
    plant = Plant(model)
    rows = plant.advance(np.full(round(30.0 / DT), 6.0), "voltage", 0.0, DT, 1000)
    assert np.all(np.diff(rows[:, OUT.TEMP_GEAR]) >= 0.0) and rows[-1, OUT.TEMP_GEAR] > rows[0, OUT.TEMP_GEAR]
    assert np.all(np.diff(rows[:, OUT.TEMP_MOTOR]) >= 0.0)


@pytest.mark.parametrize(
    "change, message",
    [
        ({"C_g": 0.0}, "C_g"),
        ({"R_wa": -1.0}, "R_wa"),
        ({"T_amb": -300.0}, "T_amb"),
        ({"beta_T": float("nan")}, "beta_T"),
        ({"kappa": 1.0}, "kappa"),
    ],
)
def test_bad_thermal_values_are_refused_in_one_line(seed: HarmonicDriveModel, change, message: str):
    data = {**seed.to_dict(), "thermal": {**NETWORK, "beta_T": 0.02, **change}}
    with pytest.raises(ModelFileError, match=message) as info:
        parse_model(data)
    assert "\n" not in str(info.value)


def test_beta_needs_a_karnopp_motor_law(seed: HarmonicDriveModel):
    lugre = {
        "motor_law": "lugre",
        "f_cm": 0.05,
        "f_sm": 0.07,
        "omega_sm": 1.0,
        "sigma0_m": 100.0,
        "sigma1_m": 0.1,
    }
    data = {**variant(seed, motor_friction=lugre).to_dict(), "thermal": {**NETWORK, "beta_T": 0.02}}
    with pytest.raises(ModelFileError, match="beta_T scales Karnopp-type motor laws only"):
        parse_model(data)
    parse_model({**data, "thermal": {**NETWORK, "beta_T": 0.0}})  # the network alone is fine


def test_the_specialized_loop_integrates_the_network_as_the_general_one_bit_for_bit():
    plant = Plant(load_model("seed-thermal"))
    steps, decim = 20_000, 10
    drive_q = parse_input_spec("sine:amp=6,freq=0.5").vector(steps * DT)
    load_q = parse_input_spec("const:value=0").vector(steps * DT)
    results = []
    for specialized in (False, True):
        plant.reset(theta_m=0.3)
        out = np.empty((steps // decim, len(OUT)))
        loop = k.profiles_loop(plant.flags, specialized)
        rows = loop(plant.p, plant.x, Mode.VOLTAGE, drive_q, load_q, 0.0, steps, DT, decim, out)
        results.append((out[:rows].copy(), plant.x.copy()))
    np.testing.assert_array_equal(results[1][0], results[0][0])
    np.testing.assert_array_equal(results[1][1], results[0][1])
    assert results[0][1][X.RISE_GEAR] > 0.0 and results[0][1][X.RISE_MOTOR] > results[0][1][X.RISE_GEAR]


def test_the_simulated_drive_steps_the_temperatures_and_keeps_them_in_its_truth():
    """The sim rig's drive steps the plant's whole state, the network included; its opt-in truth carries the
    temperatures at each cycle's start (NaN for a model without the section)."""
    config = load_rig_config(RIG_DIR / "sim.yaml")
    temps = {}
    for name in ("seed", "seed-thermal"):
        plant = Plant(load_model(name))
        drive = SimulatedDrive(plant, config)
        drive.record_truth()
        cycles = 2000
        drive.run(ControlMode.VELOCITY, np.full(cycles, 50.0), np.zeros(cycles), 0.0)
        assert drive.truth is not None
        truth = np.concatenate(drive.truth)
        temps[name] = truth[:, TRUTH_COLUMNS.index("temp_gear")], truth[:, TRUTH_COLUMNS.index("temp_motor")]
    assert np.isnan(temps["seed"][0]).all() and np.isnan(temps["seed"][1]).all()
    gear, motor = temps["seed-thermal"]
    assert gear[0] == motor[0] == 22.0
    assert np.all(np.diff(gear) >= 0.0) and gear[-1] > 22.0 and motor[-1] > gear[-1]
