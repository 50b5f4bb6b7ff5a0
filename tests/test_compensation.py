"""Model-based feed-forward (`model.compensator`, `model.feedforward`) and the `compensation` experiment.

The planner's numbers are checked against the equations of docs/MODEL.md written out here by hand; the
gain it buys is checked on the simulated rig with a model that `hdrig fit` made from a campaign recorded
on that rig (never the plant's own parameters), played through the command line as a user would.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy.optimize import brentq

from model.compensator import Compensator, fold_window_rad
from model.errors import UserInputError
from model.feedforward import (
    FF_FRICTION,
    FF_OMEGA,
    FF_TORQUE,
    loop_torque_nm,
    min_measured_band_rad_s,
)
from model.params import HarmonicDriveModel, load_model, save_model
from rig.analysis.fit.parameters import get_values, with_values
from rig.config import load_rig_config
from rig.core import actions
from rig.experiments import CAMPAIGN_ORDER
from rig.experiments.base import RigContext
from rig.experiments.compensation import Compensation, CompensationParams
from rig.interface import ControlMode, RigError, Segment, open_rig
from rig.store.runs import RunStore

REPO_ROOT = Path(__file__).resolve().parents[1]
DT_S = 1e-3  # the sim rig's 1 kHz cycle


def article_friction(model: HarmonicDriveModel, theta: float, omega: float) -> float:
    """docs/MODEL.md's moving branch, written out: sgn(ω)·[C(θ)(1 + k_v(|ω| − v_c)) + P(θ)] + b_m·ω."""
    mf = model.motor_friction
    c = (mf.s1 or 0.0) * theta**2 + (mf.s2 or 0.0) * theta + (mf.s3 or 0.0)
    a, b = mf.fourier_a(), mf.fourier_b()
    p = a[0] / 2 + sum(a[n] * math.cos(n * theta) + b[n - 1] * math.sin(n * theta) for n in range(1, 11))
    return (
        math.copysign(c * (1 + (mf.k_v or 0.0) * (abs(omega) - (mf.v_c or 0.0))) + p, omega) + mf.b_m * omega
    )


# --- the kinematic error's inverse ------------------------------------------------------------------------


def test_fold_windows_join_end_to_start_on_the_seed() -> None:
    # Seed: A = 1e-3 rad, k = 50, r = 0.01, so A·k = 5·r and the output map folds back.
    A, k, r = 1e-3, 50.0, 0.01
    w = fold_window_rad(A, k, r)
    assert A * math.sin(w) + r * w / k == pytest.approx(math.pi * r / k, abs=1e-15)
    assert 0 < w < math.acos(-r / (A * k))  # inside the rising part of each error cycle
    comp = Compensator(load_model("seed"))
    for n in (-3, 0, 7):
        end_n = (2 * math.pi * n + w) / k
        start_next = (2 * math.pi * (n + 1) - w) / k
        # The end of one window gives the same output as the start of the next, to rounding (1e-15 rad).
        assert comp.output_of(np.array([end_n]))[0] == pytest.approx(
            comp.output_of(np.array([start_next]))[0], abs=1e-15
        )
    assert comp.jump_rad == pytest.approx((2 * math.pi - 2 * w) / k)


def test_a_monotonic_error_has_one_window_and_no_jump() -> None:
    assert fold_window_rad(1e-4, 50.0, 0.01) == math.pi  # A·k = 0.5·r: the output map only rises
    comp = Compensator(load_model("catalog-cha-25a-100"))  # A = 1.2e-4 at k = 2
    assert comp.jump_rad == 0.0


def test_inverse_puts_the_output_where_asked_and_agrees_with_an_independent_root() -> None:
    seed = load_model("seed")
    comp = Compensator(seed)
    y = np.linspace(-0.02, 0.03, 2001)
    theta, window = comp.invert_output(y)
    # Bisection to 60 halvings: the output agrees to rounding of θ (1e-12 rad at the output is ample).
    np.testing.assert_allclose(comp.output_of(theta), y, rtol=0, atol=1e-12)
    w, k, r, A = comp.window_rad, 50.0, 0.01, 1e-3
    for i in range(0, 2001, 97):  # scipy's brentq on the same window: the same root
        lo, hi = (2 * math.pi * window[i] - w) / k, (2 * math.pi * window[i] + w) / k
        root = brentq(lambda t, i=i: r * t + A * math.sin(k * t) - y[i], lo, hi, xtol=1e-14)
        assert theta[i] == pytest.approx(root, abs=1e-12)


# --- the plan's torques and angles ------------------------------------------------------------------------


def frictionless(model: HarmonicDriveModel) -> HarmonicDriveModel:
    return model.with_updates(
        motor_friction={"motor_law": "coulomb_viscous", "f_cm": 0.0, "f_sm": 0.0, "b_m": 0.0},
        load_friction=None,
        kinematic_error=None,
    )


def test_rigid_frictionless_sine_needs_inertia_times_acceleration(seed_rigid: HarmonicDriveModel) -> None:
    model = frictionless(seed_rigid)
    amp_rad, w_rad_s = 20.0, 2 * math.pi * 0.5
    t = np.arange(4000) * DT_S
    theta = amp_rad * (1.0 - np.cos(w_rad_s * t))  # from rest, as the sine experiment starts
    rows = Compensator(model).plan(theta, DT_S, 0.0, 600.0).rows
    j_total = model.mechanics.J_m + model.mechanics.r**2 * model.mechanics.J_l
    # The torque is held over the cycle that follows: the acceleration at its middle, t + dt/2.
    expected = j_total * amp_rad * w_rad_s**2 * np.cos(w_rad_s * (t + DT_S / 2))
    inner = slice(50, -50)  # clear of the start (the acceleration steps from 0) and the one-sided end
    # Central differences err by ω²·dt²/12 of the peak (8e-7); the 8 ms smoothing of the load's share
    # (r²·J_l/J_total = 27 %) by about ω²σ²/2 with σ² = T²/28 of the min-jerk bell (3e-6): 2e-5 is ample.
    peak = j_total * amp_rad * w_rad_s**2
    np.testing.assert_allclose(rows[inner, FF_TORQUE], expected[inner], rtol=0, atol=2e-5 * peak)
    np.testing.assert_allclose(rows[:, 0], theta, rtol=0, atol=1e-12)  # rigid, no error: the set-point
    assert np.all(rows[:, FF_FRICTION] == 0.0)


def test_flexible_ramp_twists_by_load_friction_and_cancels_the_articles_friction(
    seed: HarmonicDriveModel,
) -> None:
    model = seed.with_updates(kinematic_error=None)
    speed_rad_s, r = 5.0, model.mechanics.r
    theta_ref = 1.0 + speed_rad_s * np.arange(1, 2001) * DT_S
    rows = Compensator(model).plan(theta_ref, DT_S, 1.0, 600.0).rows
    mid = slice(500, 1500)  # clear of the smoothing at the ends
    lf, k_s = model.load_friction, float(model.transmission.K_s or 0)
    assert lf is not None
    t_s = lf.f_cl + lf.b_l * r * speed_rad_s  # the load's friction at r·ω, what the spring must pass
    # θ_cmd = θ_ref + T_s/(K_s·r): the output then stands where asked (1e-12 rad: rounding of angles ~11 rad).
    np.testing.assert_allclose(rows[mid, 0] - theta_ref[mid], t_s / (k_s * r), rtol=0, atol=1e-9)
    np.testing.assert_allclose(rows[mid, FF_TORQUE], r * t_s, rtol=1e-9)
    np.testing.assert_allclose(rows[mid, FF_OMEGA], speed_rad_s, rtol=1e-9)
    by_hand = [article_friction(model, th, speed_rad_s) for th in rows[mid, 0]]
    np.testing.assert_allclose(rows[mid, FF_FRICTION], by_hand, rtol=1e-12)


def test_friction_scale_scales_every_friction_and_nothing_else(seed: HarmonicDriveModel) -> None:
    model = seed.with_updates(kinematic_error=None)
    lf = model.load_friction
    assert lf is not None
    speed_rad_s, r = 5.0, model.mechanics.r
    theta_ref = 1.0 + speed_rad_s * np.arange(1, 2001) * DT_S
    low = Compensator(model, 0.8).plan(theta_ref, DT_S, 1.0, 600.0).rows
    mid = slice(500, 1500)
    by_hand = [0.8 * article_friction(model, th, speed_rad_s) for th in low[mid, 0]]
    np.testing.assert_allclose(low[mid, FF_FRICTION], by_hand, rtol=1e-12)
    np.testing.assert_allclose(low[mid, FF_TORQUE], r * 0.8 * (lf.f_cl + lf.b_l * r * speed_rad_s), rtol=1e-9)


def test_measured_velocity_blend_is_linear_in_the_band_and_planned_outside() -> None:
    ff = np.array([[0.0, 0.5, 0.01, 0.07, 0.08], [0.0, 30.0, 0.01, 0.07, 0.08]])
    band = 10.0
    assert loop_torque_nm(ff, 0, band, 2.5) == pytest.approx(0.01 + 0.08 * 0.25)
    assert loop_torque_nm(ff, 0, band, -50.0) == pytest.approx(0.01 - 0.08)
    assert loop_torque_nm(ff, 1, band, -50.0) == pytest.approx(0.01 + 0.07)  # outside: the plan's sign
    assert loop_torque_nm(ff, 0, 0.0, -50.0) == pytest.approx(0.01 + 0.07)  # option off
    # The seed's velocity loop (K_m 0.0302 N·m/A, K_p 0.3 A·s/rad) is undamped below 0.08/0.00906 rad/s.
    assert min_measured_band_rad_s(0.08, 0.0302, 0.3) == pytest.approx(8.83, rel=1e-3)


# --- the rig ----------------------------------------------------------------------------------------------


def test_a_track_on_a_velocity_segment_is_refused(seed: HarmonicDriveModel) -> None:
    rig = open_rig(load_rig_config("sim"))
    track = Compensator(seed).plan(np.zeros(10), DT_S, 0.0, 600.0)
    with pytest.raises(RigError, match="feed-forward track needs a position segment"):
        rig.check_segment(Segment(ControlMode.VELOCITY, np.zeros(10), 0.0, "v", track))
    with pytest.raises(RigError, match="9 cycles for 10 set-points"):
        rig.check_segment(Segment(ControlMode.POSITION, np.zeros(10), 0.0, "p", track.part(0, 9)))


def test_compensation_without_a_model_is_a_one_line_error() -> None:
    with pytest.raises(UserInputError, match="model") as info:
        actions.plan_run("compensation", {})
    assert "\n" not in str(info.value)
    with pytest.raises(UserInputError, match="no-such-model"):
        actions.plan_run("compensation", {"model": "no-such-model.yaml"})


def test_an_approach_that_would_leave_the_stroke_is_refused_before_anything_moves(
    seed: HarmonicDriveModel,
) -> None:
    config = load_rig_config("sim")
    r = seed.mechanics.r
    # The output starts 0.01 rad above the stroke's low end; the approach backs off 2 rad (0.02 rad out).
    ctx = RigContext(config, r, seed.motor.K_m, (config.limits.travel_min_out_rad + 0.01) / r)
    params = CompensationParams(model="seed", friction_errors=[])
    with pytest.raises(UserInputError, match="field 'approach_rad'") as info:
        Compensation().program(params, ctx)
    assert "\n" not in str(info.value)
    assert Compensation().program(params.model_copy(update={"approach_rad": 0.5}), ctx)


def test_the_campaign_still_plays_the_articles_eight() -> None:
    eight = ("speed-sweep", "position-friction", "pulse", "load-variation", "step", "sine", "ramp", "chirp")
    assert eight == CAMPAIGN_ORDER
    assert [run.experiment for run in actions.plan_run("campaign").runs] == list(eight)


# --- what it buys, on the simulated rig, with a model fitted there ---------------------------------------


@pytest.fixture(scope="module")
def fitted_on_the_sim_rig(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A campaign on configs/rigs/sim.yaml (the seed plant) into a fresh store, then `fit` from a start
    whose friction is 20 % off the plant's, as a lab's first guess would be: (home, model). (From the
    seed itself the fit rightly keeps its start, which is the plant: nothing would then be learnt.)"""
    home = tmp_path_factory.mktemp("hdrig-home")
    store = RunStore(home)
    config = load_rig_config(str(REPO_ROOT / "configs" / "rigs" / "sim.yaml"))
    runs = actions.execute_plan(actions.plan_run("campaign"), config, store)
    assert [run.status.value for run in runs] == ["complete"] * 8
    plant = load_model("seed")
    start_file = save_model(with_values(plant, _friction_off(plant)), home / "start.yaml")
    model_file = home / "fitted.yaml"
    actions.fit(["latest"], str(start_file), store, out=model_file)
    return home, model_file


OFF = {"f_cl": 0.8, "k_v": 1.2, "s3": 1.2}
"""The start's friction against the plant's: the load side's Coulomb level low (it must stay below the
static level f_sl), the motor side's viscous and position-dependent friction high."""
FRICTION = tuple(OFF)


def _friction_off(model: HarmonicDriveModel) -> dict[str, float]:
    return {name: value * OFF[name] for name, value in get_values(model, list(FRICTION)).items()}


@pytest.fixture(scope="module")
def compensation_metrics(fitted_on_the_sim_rig: tuple[Path, Path]) -> dict[str, Any]:
    home, model_file = fitted_on_the_sim_rig
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "rig",
            "run",
            "compensation",
            "--rig",
            "sim",
            "--set",
            f"model={model_file}",
            "--json",
        ],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=REPO_ROOT,
        env={**os.environ, "HDRIG_HOME": str(home)},
    )
    assert result.returncode == 0, result.stderr
    document = json.loads(result.stdout)
    run = document[0] if isinstance(document, list) else document
    if "runs" in run:
        run = run["runs"][0]
    assert run["status"] == "complete"
    assert sorted(Path(p).name for p in run["artifacts"] if p.endswith(".png")) == [
        "compensation_ramp.png",
        "compensation_sine.png",
        "compensation_step.png",
    ]
    metrics: dict[str, Any] = run["metrics"]
    return metrics


def test_the_model_used_is_the_fitted_one_not_the_plants(fitted_on_the_sim_rig: tuple[Path, Path]) -> None:
    _, model_file = fitted_on_the_sim_rig
    fitted, plant = load_model(model_file), load_model("seed")
    assert fitted.content_hash() != plant.content_hash()
    # The fit learnt the friction back from the 20 % start: within 5 % of the plant's (the campaign
    # determines these to ~1 %, docs/BENCHMARKS.md, identification), so far from the start.
    learnt, truth = get_values(fitted, list(FRICTION)), get_values(plant, list(FRICTION))
    assert all(abs(learnt[n] / truth[n] - 1) < 0.05 for n in FRICTION), learnt


def test_sine_rms_error_drops_at_least_threefold(compensation_metrics: dict[str, Any]) -> None:
    assert compensation_metrics["improvement_sine"] >= 3.0  # issue 14's target


def test_ramp_stick_slip_drops_at_least_threefold(compensation_metrics: dict[str, Any]) -> None:
    assert compensation_metrics["improvement_stick_slip"] >= 3.0  # issue 14's target
    assert compensation_metrics["improvement_ramp"] >= 3.0


@pytest.mark.parametrize("tag", ["friction_minus_20pct", "friction_plus_20pct"])
def test_friction_twenty_percent_off_keeps_most_of_the_gain_on_sine_and_ramp(
    compensation_metrics: dict[str, Any], tag: str
) -> None:
    # Reported for both signs; on the sine and the ramp never worse than no compensation, and on the
    # simulated rig at least 2× better still (measured: 2.7–2.8× sine, 5–6× stick-slip).
    assert compensation_metrics[f"improvement_sine_{tag}"] >= 2.0
    assert compensation_metrics[f"improvement_stick_slip_{tag}"] >= 2.0
    # The step's RMS ratio was ≈ 1 by construction (issue 31): the step reports overshoot and settling.
    assert f"improvement_step_{tag}" not in compensation_metrics
    assert np.isfinite(compensation_metrics[f"overshoot_pct_step_{tag}"])
