"""The trajectory fit replays data as the process that made them: the project's simulated plant exactly
(its own semi-implicit Euler at its own step), anything else as a continuous plant.

The continuous case is checked on the sim rig's plant stepped at 1 µs, a hundred times finer than the
replay's 0.1 ms, with ideal sensors (no encoder quantization, no current or output-sensor noise): its
own Euler error is 1 % of the replay's, so it stands for a continuous plant. Replayed at 0.1 ms as if
it were the plant's own discretization, the inertias came out J_l −0.35 % (6σ of the fit's own σ,
0.055 %) and J_m +0.13 % (1.9σ); this is what a rig's real data would see.

Checked the other way too: fitted with the old replay, `test_inertias_from_a_continuous_plant_are_unbiased`
fails on J_l (−0.3479 % at σ 0.0553 %).
"""

from __future__ import annotations

import math

import campaign
import numpy as np
import pytest

from model.params import HarmonicDriveModel
from model.run import Run
from rig.analysis.fit.parameters import get_values
from rig.analysis.fit.trajectory import (
    SPEED_BAND_SIGMAS,
    VOLTAGE_REFINE,
    _event_intervals,
    fit_trajectories,
    replay_scheme,
    speed_bands,
    with_smooth_velocities,
)
from rig.analysis.identification.identify import JOINT_EXPERIMENTS, JOINT_WINDOW_S
from rig.config import load_rig_config
from rig.store.runs import RunStore

FINE_STEP_S = 1e-6
REPLAY_STEP_S = 1e-4


@pytest.fixture(scope="module")
def near_continuous_runs(seed: HarmonicDriveModel, tmp_path_factory: pytest.TempPathFactory) -> list[Run]:
    """Pulse, step and sine runs of the sim rig with ideal sensors, its plant stepped at 1 µs (~3 s)."""
    store = RunStore(tmp_path_factory.mktemp("fine"))
    config = load_rig_config("sim").model_copy(update={"sim_dt_s": FINE_STEP_S})
    ideal = {"encoder_counts_per_rev": 0, "current_noise_a": 0.0, "load_sensor_noise_rad": 0.0}
    config = config.model_copy(update={"sensors": config.sensors.model_copy(update=ideal)})
    return campaign.play(JOINT_EXPERIMENTS, config, seed, store)


def test_the_replay_follows_the_process_that_made_the_run(near_continuous_runs: list[Run]):
    pulse, step = near_continuous_runs[0], near_continuous_runs[1]
    assert pulse.input_column == "u" and step.input_column == "i_cmd"
    # A plant stepped at 1 µs is near-continuous: the replay's step, a tenth of it in voltage mode.
    assert replay_scheme(step, REPLAY_STEP_S) == (REPLAY_STEP_S, True)
    assert replay_scheme(pulse, REPLAY_STEP_S) == (REPLAY_STEP_S / VOLTAGE_REFINE, True)
    for run in (pulse, step):  # our plant at a step the replay can take: exactly that step
        at_plant_step = Run(run.columns, {**run.meta, "rig_config": {"sim_dt_s": 5e-5}})
        assert replay_scheme(at_plant_step, REPLAY_STEP_S) == (5e-5, False)
        simulated = Run(run.columns, {"source": "sim", "dt_s": 1e-4})  # `model.simulate`'s metadata
        assert replay_scheme(simulated, REPLAY_STEP_S) == (1e-4, False)
        assert replay_scheme(Run(run.columns, {"source": "sim"}), REPLAY_STEP_S) == (1e-4, False)
    for source in ({}, {"source": "hardware"}, {"source": "hdrig_testing.independent_plant"}):
        other = Run(step.columns, {**source, "input_column": "i_cmd"})
        assert replay_scheme(other, REPLAY_STEP_S) == (REPLAY_STEP_S, True)


FLOOR = 2e-4
"""A relative error that no longer matters: under half the 1σ (~0.05 %) the rig's noisy sensors give J_m
and J_l in bench_identify, so such a bias moves their 1σ coverage by a few percent at most. Ideal
sensors shrink the fit's own σ to ~0.002 %, where the replay's last first-order remainders show."""


@pytest.mark.parametrize("name", ["J_m", "J_l"])
def test_inertias_from_a_continuous_plant_are_unbiased(
    near_continuous_runs: list[Run], seed: HarmonicDriveModel, name: str
):
    """J_m and J_l fitted with every other parameter true. Measured: J_l −0.0035 % at σ 0.0015 %, J_m
    +0.0070 % at σ 0.0035 %; with the plain replay, J_l −0.35 % at σ 0.055 % (6σ, 17× the floor).
    Bound: 3 of the fit's own σ (which with ideal sensors comes only from the windows' starting speeds;
    the data have no noise seed, so the outcome does not vary), and not under `FLOOR`. The plant's own
    1 µs Euler error (~0.004 % of J_l) is inside it."""
    truth = get_values(seed, [name])[name]
    fit = fit_trajectories(seed, near_continuous_runs, ["J_m", "J_l"], JOINT_WINDOW_S, REPLAY_STEP_S)
    estimate = next(p for p in fit.parameters if p.name == name)
    assert estimate.identifiable and estimate.std_error is not None, estimate.note
    error = estimate.estimate - truth
    assert abs(error) <= max(3 * estimate.std_error, FLOOR * truth), (
        f"{name}: {100 * error / truth:+.4f} % at σ {100 * estimate.std_error / truth:.4f} %"
    )


def _savgol_gain(dt_s: float) -> float:
    """‖weights‖ of the 5-point cubic's derivative (5 ms at 1 kHz): (1, −8, 0, 8, −1)/(12·dt)."""
    return math.sqrt(1 + 64 + 64 + 1) / (12 * dt_s)


def test_speed_bands_are_the_sensors_noise_seen_through_the_smoothing():
    """A 14-bit encoder's count q gives white-ish noise q/√12; a capacitive sensor's Gaussian noise σ;
    ideal data none. The band is SPEED_BAND_SIGMAS × that noise × the derivative weights' norm: the
    quantizer's exactly, the Gaussian's within 5 % (the median of 8,000 third differences scatters
    ~1.5 %), an ideal smooth motion under 1 % of either."""
    dt = 1e-3
    t = np.arange(8000) * dt
    motion = 0.2 * np.sin(2 * np.pi * 0.5 * t)
    q = 2 * np.pi / 2**14
    sigma = 2e-6
    rng = np.random.default_rng(1)
    run = Run(
        {"t": t, "u": np.zeros_like(t), "theta_m": np.round(motion / q) * q},
        {},
    )
    run.columns["theta_l"] = motion / 50 + rng.normal(0.0, sigma, t.size)
    bands = speed_bands(run)
    assert bands["omega_m"] == pytest.approx(
        SPEED_BAND_SIGMAS * _savgol_gain(dt) * q / math.sqrt(12), rel=1e-9
    )
    assert bands["omega_l"] == pytest.approx(SPEED_BAND_SIGMAS * _savgol_gain(dt) * sigma, rel=0.05)
    ideal = speed_bands(Run({"t": t, "u": np.zeros_like(t), "theta_m": motion, "theta_l": motion / 50}, {}))
    assert ideal["omega_m"] < 0.01 * bands["omega_m"] and ideal["omega_l"] < 0.01 * bands["omega_l"]


def test_a_noisy_body_at_rest_is_one_stop_not_a_reversal_every_sample():
    """A still load read by a noisy sensor: its smoothed speed flips sign about every other sample, and
    every flip was an event stepped at EVENT_STEP_S (on the independent generator's 8 s lab run, 2,074
    of 7,999 intervals; 524 with the bands, and a residual 0.93 M steps, not 1.38 M). Within the noise
    band it is one stop: the intervals around the motion's real stop and start only, and a real
    reversal is still seen."""
    dt = 1e-3
    t = np.arange(600) * dt
    moving = np.clip(t - 0.4, 0.0, None) * 0.5  # still for 0.4 s, then 0.5 rad/s (50× the band)
    rng = np.random.default_rng(2)
    run = Run({"t": t, "u": np.zeros_like(t), "theta_l": moving + rng.normal(0.0, 2e-6, t.size)}, {})
    smoothed = with_smooth_velocities(run)
    bands = speed_bands(run)
    assert np.count_nonzero(_event_intervals(smoothed)) > 100  # without bands: flips all through the rest
    events = np.flatnonzero(_event_intervals(smoothed, bands))
    assert len(events) > 0 and np.all(np.abs(events - 400) <= 4), events  # the start, ±2 samples of smoothing
    reversal = Run({"t": t, "u": np.zeros_like(t), "theta_l": 0.05 * np.sin(2 * np.pi * t / 0.6)}, {})
    events = np.flatnonzero(_event_intervals(with_smooth_velocities(reversal), speed_bands(reversal)))
    assert np.any(np.abs(events - 150) <= 1) and np.any(np.abs(events - 450) <= 1), events
