"""`chirp` on the simulated seed rig, position-dependent friction and all (issue 31, items 3 and 5).

The reference is the plant's linearized response, from docs/MODEL.md's two-inertia equations with code
of its own: J_m·θ̈_m = K_m·i − c_m·θ̇_m − r·K_s·(r·θ_m − θ_l), J_l·θ̈_l = K_s·(r·θ_m − θ_l) − b_l·θ̇_l,
c_m = dF_m/dω_m of the moving friction at the sweep's mean speed (k_v·C(θ_m) averaged over the positions
swept; the position-dependent levels themselves are a disturbance, not part of the linear plant), the
command held over each cycle (exact zero-order-hold discretization) and the speed the drive's: encoder
difference through its first-order filter.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import signal

from model.params import HarmonicDriveModel, save_model
from model.plant import Plant
from rig.config import load_rig_config
from rig.experiments.base import context_from_run, segment_rows
from rig.experiments.chirp import ChirpParams, frf_tables, sweep_labels
from rig.runner import RunOutcome, run_experiment
from rig.store.runs import RunStore

CFG = load_rig_config("sim")
RATE_HZ = CFG.sample_rate_hz
# 0.25 Hz lines need 4 s periods; at the default 25 rad/s three of them overrun the 3.5 rad stroke.
FINE_GRID = {"period_s": 4.0, "mean_speed_motor_rad_s": 18.0, "speed_amp_motor_rad_s": 12.0}


def _play(store: RunStore, overrides: dict[str, float]) -> tuple[RunOutcome, dict[str, np.ndarray], float]:
    outcome = run_experiment("chirp", CFG, overrides, store)
    assert outcome.status == "complete", outcome.reason
    run = store.read(outcome.run_id)
    table = next(p for p in outcome.artifacts if p.name == "frf_speed.csv")
    frf = np.genfromtxt(table, delimiter=",", names=True)
    labels = sweep_labels(ChirpParams.model_validate(overrides))
    theta = np.concatenate([run["theta_m"][segment_rows(run, label)] for label in labels])
    return outcome, {name: frf[name] for name in frf.dtype.names or ()}, float(np.mean(theta))


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> RunStore:
    return RunStore(tmp_path_factory.mktemp("chirp-runs"))


@pytest.fixture(scope="module")
def default(store: RunStore) -> tuple[RunOutcome, dict[str, np.ndarray], float]:
    return _play(store, {})


@pytest.fixture(scope="module")
def fine(store: RunStore) -> tuple[RunOutcome, dict[str, np.ndarray], float]:
    return _play(store, FINE_GRID)


def _linearized_speed_frf(
    model: HarmonicDriveModel, freq_hz: np.ndarray, mean_speed: float, theta_mid: float
) -> np.ndarray:
    """i_cmd → measured ω_m of the linearized plant, as the drive samples it (module docstring)."""
    J_m, J_l, r = model.mechanics.J_m, model.mechanics.J_l, model.mechanics.r
    K_s, K_m = model.transmission.K_s, model.motor.K_m
    assert K_s is not None and model.load_friction is not None
    b_l = model.load_friction.b_l
    plant = Plant(model)
    positions = theta_mid + np.linspace(-math.pi, math.pi, 64)  # a motor turn about the sweeps' middle
    c_m = float(
        np.mean(
            plant.steady_friction(positions, np.full(64, mean_speed + 0.5))
            - plant.steady_friction(positions, np.full(64, mean_speed - 0.5))
        )
    )
    a = np.array(
        [
            [0, 1, 0, 0],
            [-(r**2) * K_s / J_m, -c_m / J_m, r * K_s / J_m, 0],
            [0, 0, 0, 1],
            [r * K_s / J_l, 0, -K_s / J_l, -b_l / J_l],
        ]
    )
    b = np.array([[0.0], [K_m / J_m], [0.0], [0.0]])
    period_s = 1.0 / RATE_HZ
    ad, bd, *_ = signal.cont2discrete((a, b, np.eye(4)[:1], np.zeros((1, 1))), period_s, method="zoh")
    z = np.exp(2j * np.pi * freq_hz * period_s)
    theta = np.array([np.linalg.solve(zk * np.eye(4) - ad, bd)[0, 0] for zk in z])
    alpha = 1 - math.exp(-2 * math.pi * CFG.sensors.velocity_filter_hz * period_s)
    return np.asarray(theta * (1 - 1 / z) / period_s * alpha / (1 - (1 - alpha) / z))


def test_chirp_speed_frf_follows_the_linearized_plant_from_1_to_10_hz(
    default: tuple[RunOutcome, dict[str, np.ndarray], float], seed: HarmonicDriveModel
):
    outcome, frf, theta_mid = default
    band = (frf["freq_hz"] >= 1.0) & (frf["freq_hz"] <= 10.0)
    assert np.count_nonzero(band) == 19  # every line from 1 to 10 Hz, none dropped
    expected = _linearized_speed_frf(
        seed, frf["freq_hz"][band], float(outcome.metrics["sweep_mean_speed_rad_s"]), theta_mid
    )
    error_db = frf["magnitude_db"][band] - 20 * np.log10(np.abs(expected))
    sigma_db = frf["magnitude_std_db"][band]
    # Before issue 31 the position-dependent friction biased the lines 4–6 dB below 6 Hz; then, with one
    # Schroeder multisine, the 10 Hz line stayed 1.9 dB off: the load's Coulomb friction, reversing where
    # the load swings at its mode (11–11.5 Hz), distorts onto the excited lines, periodically, so averaging
    # periods kept it. Each sweep now plays its own random-phase realization, and that distortion, different
    # in each, averages out (issue 31: every line within 1 dB). The band from the sweeps' spread covers it.
    assert abs(float(np.mean(error_db))) < 0.3, error_db
    assert np.all(np.abs(error_db) <= 1.0), error_db
    assert np.all(np.abs(error_db) <= 4.0 * sigma_db), (error_db, sigma_db)  # 4 sweeps: σ from 3 dof


def test_chirp_modes_do_not_move_with_the_grid_beyond_the_stated_resolution(
    default: tuple[RunOutcome, dict[str, np.ndarray], float],
    fine: tuple[RunOutcome, dict[str, np.ndarray], float],
    seed: HarmonicDriveModel,
):
    coarse, narrow = default[0].metrics, fine[0].metrics
    assert coarse["line_spacing_hz"] == 0.5 and narrow["line_spacing_hz"] == 0.25
    # The linear plant's modes (docs/MODEL.md): antiresonance √(K_s/J_l), resonance √(K_s/J_red).
    mech, K_s = seed.mechanics, seed.transmission.K_s
    assert K_s is not None
    truth = {
        "antiresonance_hz": math.sqrt(K_s / mech.J_l) / (2 * math.pi),
        "resonance_hz": math.sqrt(K_s * (1 / mech.J_l + mech.r**2 / mech.J_m)) / (2 * math.pi),
    }
    for key, true_hz in truth.items():
        a, b = float(coarse[key]), float(narrow[key])
        worst = max(float(coarse["resonance_resolution_hz"]), float(narrow["resonance_resolution_hz"]))
        assert worst < float(narrow["line_spacing_hz"]), "interpolated: finer than either grid"
        assert abs(a - b) <= worst, f"{key}: {a:.3f} Hz on 0.5 Hz lines, {b:.3f} Hz on 0.25 Hz lines"
        for got, metrics in ((a, coarse), (b, narrow)):
            assert abs(got - true_hz) <= float(metrics["resonance_resolution_hz"]), (key, got, true_hz)


def test_chirp_of_a_linear_plant_with_a_barely_damped_load_is_exact(tmp_path, seed: HarmonicDriveModel):
    """The seed with no friction but viscous (b_m = 2e-4 N·m·s/rad, the load's b_l = 0.05 kept) and no
    kinematic error is linear: its chirp FRF equals the linearized response at every line from 1 to
    10 Hz within 0.05 dB (the encoder's quantization and the speed filter's rounding leave less). The
    load mode, its motor held by the loop, decays with J_l/b_l = 4 s: its ring from the speed-up and the
    lead-in runs through the analyzed periods, and before `periodic_records` took it out it leaked into
    every line (−2 to +8 dB over 1–10 Hz)."""
    data = seed.to_dict()
    data["load_friction"].update(f_cl=0.0, f_sl=0.0)
    data["kinematic_error"]["A"] = 0.0
    data["motor_friction"].update(
        a=[0.0] * len(data["motor_friction"]["a"]),
        b=[0.0] * len(data["motor_friction"]["b"]),
        s1=0.0,
        s2=0.0,
        s3=0.0,
        k_v=0.0,
        b_m=2e-4,
    )
    linear = HarmonicDriveModel.model_validate(data)
    config = CFG.model_copy(update={"model": str(save_model(linear, tmp_path / "linear.yaml"))})
    with RunStore(tmp_path / "runs") as store:
        outcome = run_experiment("chirp", config, {}, store)
        assert outcome.status == "complete", outcome.reason
        table = next(p for p in outcome.artifacts if p.name == "frf_speed.csv")
        frf = np.genfromtxt(table, delimiter=",", names=True)
    band = (frf["freq_hz"] >= 1.0) & (frf["freq_hz"] <= 10.0)
    expected = _linearized_speed_frf(
        linear, frf["freq_hz"][band], float(outcome.metrics["sweep_mean_speed_rad_s"]), 0.0
    )
    error_db = frf["magnitude_db"][band] - 20 * np.log10(np.abs(expected))
    assert np.all(np.abs(error_db) <= 0.05), error_db


def test_a_chirp_recorded_with_one_pass_is_analyzed_from_the_sweeps_it_has(store: RunStore) -> None:
    """A run recorded before `passes` existed has one pass and parameters without the field, which read
    back with today's default of two: the analysis takes the sweeps the run holds."""
    outcome = run_experiment("chirp", CFG, {"passes": 1, "f_stop_hz": 10.0}, store)
    assert outcome.status == "complete", outcome.reason
    run = store.read(outcome.run_id)
    recorded = {k: v for k, v in run.meta["params"].items() if k not in ("passes", "phase_seed")}
    old = ChirpParams.model_validate(recorded)
    assert old.passes == 2
    ctx = context_from_run(run)
    tables = frf_tables(run, old, ctx)
    expected = frf_tables(run, ChirpParams.model_validate(run.meta["params"]), ctx)
    for name, table in expected.items():
        for column, values in table.items():
            np.testing.assert_array_equal(tables[name][column], values, err_msg=f"{name}.{column}")
