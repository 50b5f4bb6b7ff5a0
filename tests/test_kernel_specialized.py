"""The loop compiled for one model structure gives the general loop's numbers, bit for bit.

`model.kernel.specialized_profiles_loop` compiles `_advance` with the model's flags as constants, so the
compiler drops the branches the model never takes; no floating-point operation may change (no fastmath),
so equality is exact, not within a tolerance. Each structure below is one compile (~3-7 s the first time,
then numba's disk cache): the presets plus variants that take the branches the presets leave out (the
smooth laws on either side, the Stribeck law and effect, direction asymmetry, a rigid axis with a smooth law).
"""

from __future__ import annotations

import numpy as np
import pytest
from reference import variant

import model.simulate as simulate_module
from model import kernel as k
from model.inputs import parse_input_spec
from model.params import HarmonicDriveModel, load_model
from model.plant import Plant
from model.registry import FL, OUT, Mode
from model.simulate import simulate

DT_S = 1e-4
STEPS = 30_000  # 3 s: two reversals of the 0.5 Hz drive, through stick
DECIM = 7  # not a divisor of the chunk below: a chunk boundary falls between output rows
CHUNK = 10_003


def _stribeck_with_effects(seed: HarmonicDriveModel) -> HarmonicDriveModel:
    motor = {"motor_law": "stribeck", "f_cm": 0.05, "f_sm": 0.08, "omega_sm": 2.0, "b_m": 1e-3}
    return variant(
        seed,
        motor_friction=motor,
        stribeck={"f_st": 0.02, "omega_st": 1.5},
        direction_asymmetry={"f_dir": 0.01},
    )


def _lugre_both_sides(seed: HarmonicDriveModel) -> HarmonicDriveModel:
    motor = {"motor_law": "lugre", "f_cm": 0.05, "f_sm": 0.08, "omega_sm": 2.0}
    motor |= {"sigma0_m": 200.0, "sigma1_m": 0.05, "b_m": 1e-3}
    load = {"load_law": "lugre", "f_cl": 0.5, "f_sl": 0.8, "omega_sl": 0.02}
    load |= {"sigma0_l": 2000.0, "sigma1_l": 0.5, "b_l": 1.0}
    return variant(seed, motor_friction=motor, load_friction=load)


def _rigid_dahl(seed_rigid: HarmonicDriveModel) -> HarmonicDriveModel:
    motor = {"motor_law": "dahl", "f_cm": 0.05, "sigma0_m": 200.0, "b_m": 1e-3}
    return variant(seed_rigid, motor_friction=motor, load_friction=None)


STRUCTURES = {
    "seed": lambda: load_model("seed"),
    "seed-rigid": lambda: load_model("seed-rigid"),
    "seed-wear (thermal, wear)": lambda: load_model("seed-wear"),
    "catalog (nonlinear spring, hysteresis, no harmonics)": lambda: load_model("catalog-cha-25a-100"),
    "Stribeck law, Stribeck and direction effects": lambda: _stribeck_with_effects(load_model("seed")),
    "LuGre on both sides": lambda: _lugre_both_sides(load_model("seed")),
    "rigid, Dahl motor, no load friction": lambda: _rigid_dahl(load_model("seed-rigid")),
}


def _run(loop: k.ProfilesLoop, plant: Plant) -> tuple[np.ndarray, np.ndarray]:
    """Rows and final state of STEPS steps in chunks, from θ_m = 0.3 rad at rest."""
    plant.reset(theta_m=0.3)
    drive_q = parse_input_spec("sine:amp=2,freq=0.5").vector(STEPS * DT_S)
    load_q = parse_input_spec("sine:amp=0.3,freq=0.7").vector(STEPS * DT_S)
    out = np.empty((-(-STEPS // DECIM), len(OUT)))
    rows = 0
    for first in range(0, STEPS, CHUNK):
        n = min(CHUNK, STEPS - first)
        rows += loop(
            plant.p, plant.x, Mode.VOLTAGE, drive_q, load_q, float(first), n, DT_S, DECIM, out[rows:]
        )
    return out[:rows], plant.x.copy()


@pytest.mark.parametrize("name", list(STRUCTURES))
def test_specialized_loop_equals_the_general_loop_bit_for_bit(name: str) -> None:
    model = STRUCTURES[name]()
    plant = Plant(model)
    general_rows, general_x = _run(k.profiles_loop(plant.flags, specialized=False), plant)
    special_rows, special_x = _run(k.specialized_profiles_loop(plant.flags), plant)
    assert general_rows.shape[0] == -(-STEPS // DECIM)
    # The run must move and reverse, or the friction branches under test were never taken.
    omega = general_rows[:, OUT.OMEGA_M]
    assert omega.max() > 0.1 and omega.min() < -0.1, name
    np.testing.assert_array_equal(special_rows, general_rows)
    np.testing.assert_array_equal(special_x, general_x)


def test_one_compile_per_structure_and_flags_checked() -> None:
    flags = Plant(load_model("seed")).flags
    assert k.specialized_profiles_loop(flags) is k.specialized_profiles_loop(flags.copy())
    with pytest.raises(ValueError, match=f"flags has {len(FL) - 1} entries"):
        k.specialized_profiles_loop(flags[:-1])


def test_simulate_takes_the_specialized_loop_for_long_runs_with_the_same_numbers(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    seed = load_model("seed")
    general = simulate(seed, "sine:amp=2,freq=0.5", 2.0, DT_S, 100.0)
    taken: list[bool] = []
    choose = k.profiles_loop

    def spy(flags: np.ndarray, specialized: bool) -> k.ProfilesLoop:
        taken.append(specialized)
        return choose(flags, specialized)

    monkeypatch.setattr(k, "profiles_loop", spy)
    monkeypatch.setattr(simulate_module, "SPECIALIZE_STEPS", 20_000)  # 2 s at 1e-4 s is 20,000 steps
    special = simulate(seed, "sine:amp=2,freq=0.5", 2.0, DT_S, 100.0)
    assert taken == [True]
    for column in general.columns:
        np.testing.assert_array_equal(special[column], general[column])
