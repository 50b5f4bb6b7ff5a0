"""The torque transducers in the identification and the gap workflow (issue 26 item 5), on the simulated
dynamometer bench `sim-dyno` (configs/rigs/sim-dyno.yaml: load drive with a 0.01 kg·m² rotor and bearings of
0.05 N·m + 0.002 N·m·s/rad, transducers of 0.02 N·m noise) playing the seed gear.

What is checked, and the tolerances:
- the output equation (`transducer_stage.output_equation`) recovers K_s, f_cl, b_l within K_SIGMA = 3 of the
  σ it reports (any single draw, one fixed noise seed so it cannot flake); that σ is no smaller than the
  transducer's white noise alone allows over the samples of the windows (σ_τ/√N: f_cl enters every window
  with weight ±1, the other parameters can only widen it), and small enough to be of use on this 45 s
  record (twice the figures measured: σ(K_s) 0.005 %, σ(f_cl) 0.43 %, σ(b_l) 2.8 %);
- with ideal sensors its error is the method's bias: within K_BIAS = 0.3 of the noisy σ (as
  tests/test_stiffness_stage.py);
- the load balance on the load drive's τ_ext (the stiffness stage without transducers) puts the drive's
  bearing friction into f_cl and b_l (within 3 of its σ); the transducer's f_cl is clear of it (the
  bearing's 0.05 N·m is ~40 of its σ; b_l's 0.002 N·m·s/rad, ~1.4σ on this record, is not resolved);
- a motor friction mis-set by 20 % (s3 × 0.8) leaves the transducer route bit for bit unchanged (it reads
  no motor friction), while the load friction the motor's current implies (K_m·i_a − F_m − r·tau_out
  − momenta = r·F_l, the motor law held) is off by what the equations predict: Δf_cl = 0.2·s3·(1 −
  k_v·v_c)/r, Δb_l = 0.2·s3·k_v/r² (within 10 %: the windows' ripple and momenta);
- the gap workflow, load friction hidden (f_cl = f_sl = b_l = 0 carried), tau_out recorded: the effect is
  found in the output's channel and named, its f_cl within half the load drive's bearing friction of the
  truth; on the same data without tau_out it takes up the bearing.
"""

from __future__ import annotations

import math
import tempfile

import numpy as np
import pytest

from hdrig_testing.hidden_effects import carried_at_zero_case, probe_profile
from model.params import HarmonicDriveModel
from model.run import Run
from rig.analysis.fit.parameters import get_values, with_values
from rig.analysis.gaps import find_gaps
from rig.analysis.identification.dynamics_stage import (
    context,
    nonlinear_fit,
    stiffness_and_load_friction,
    sweep_parts,
)
from rig.analysis.identification.friction_stage import WindowTorques
from rig.analysis.identification.staged import staged_estimates
from rig.analysis.identification.transducer_stage import output_equation, output_run
from rig.config import RigConfig, Sensors, load_rig_config
from rig.experiments.base import segments_of
from rig.interface import ControlMode, Segment
from rig.runner import run_experiment
from rig.store.runs import RunStore
from sim_backend.inprocess import SimRig

K_SIGMA = 3.0
K_BIAS = 0.3
LOADS = {"loads_nm": [0.0, 10.0], "speeds_rad_s": [5.0, 20.0, 100.0], "hold_s": 0.5}
"""A short load-variation: two loads (stiffness apart from friction), three speeds (b_l), 45 s of rig time."""
STIFFNESS = ("K_s", "f_cl", "b_l")
USEFUL_SIGMA = {"K_s": 1e-4, "f_cl": 0.009, "b_l": 0.06}
"""Largest σ/value of use on this record: twice what was measured (see the module)."""
MIS_SET = 0.8
GAP_S = 12.0  # the gap tests' probe length (tests/test_gaps.py's)


def bench_run(config: RigConfig, truth: HarmonicDriveModel) -> Run:
    store = RunStore(tempfile.mkdtemp(prefix="hdrig-tau-"))
    outcome = run_experiment("load-variation", config, LOADS, store, rig=SimRig(config, model=truth))
    assert outcome.status == "complete", outcome.reason
    return store.read(outcome.run_id)


@pytest.fixture(scope="module")
def noisy(seed: HarmonicDriveModel) -> Run:
    return bench_run(load_rig_config("sim-dyno"), seed)


@pytest.fixture(scope="module")
def ideal(seed: HarmonicDriveModel) -> Run:
    bench = load_rig_config("sim-dyno")
    return bench_run(bench.model_copy(update={"sensors": Sensors(torque_transducers=True)}), seed)


@pytest.fixture(scope="module")
def from_tau_out(noisy: Run, seed: HarmonicDriveModel):
    return output_equation([noisy], seed)


def window_samples(run: Run) -> int:
    """Samples inside the load-variation's steady windows (past each settle time)."""
    skip = context(run).cycles(float(run.meta["params"]["settle_s"]))
    return sum(max(int(seg["cycles"]) - skip, 0) for seg in segments_of(run) if "/v" in str(seg["label"]))


def test_the_output_equation_recovers_stiffness_and_load_friction_within_its_sigma(
    from_tau_out, noisy: Run, seed: HarmonicDriveModel
):
    truth = get_values(seed, list(STIFFNESS))
    floor_nm = load_rig_config("sim-dyno").sensors.torque_noise_nm / math.sqrt(window_samples(noisy))
    assert from_tau_out.std_errors["f_cl"] >= floor_nm, "σ below the transducer's own white noise"
    for name in STIFFNESS:
        value, sigma = from_tau_out.values[name], from_tau_out.std_errors[name]
        assert abs(value - truth[name]) <= K_SIGMA * sigma, f"{name} {value:.6g} ± {sigma:.2g}"
        assert sigma <= USEFUL_SIGMA[name] * truth[name], f"{name}: σ {sigma:.2g}"
    assert "J_l_gear" in from_tau_out.metrics and "J_l" not in from_tau_out.metrics


def test_the_output_equation_of_ideal_sensors_is_unbiased(from_tau_out, ideal: Run, seed: HarmonicDriveModel):
    clean = output_equation([ideal], seed)
    for name, value in get_values(seed, list(STIFFNESS)).items():
        bias = clean.values[name] - value
        assert abs(bias) <= K_BIAS * from_tau_out.std_errors[name], f"{name}: bias {bias:.3g}"


def test_the_load_drives_torque_takes_its_bearing_into_f_cl_and_the_transducer_does_not(
    from_tau_out, noisy: Run, seed: HarmonicDriveModel
):
    drive = load_rig_config("sim-dyno").load_drive
    assert drive is not None
    old = stiffness_and_load_friction(sweep_parts([noisy], seed), seed)
    truth = get_values(seed, ["f_cl", "b_l"])
    for name, bearing in (("f_cl", drive.coulomb_nm), ("b_l", drive.viscous_nms)):
        taken = old.values[name] - truth[name]
        assert abs(taken - bearing) <= K_SIGMA * old.std_errors[name], f"{name} took {taken:.3g}"
        assert abs(from_tau_out.values[name] - truth[name]) <= K_SIGMA * from_tau_out.std_errors[name]
    # f_cl's bearing (0.05 N·m) is ~40σ of the transducer's f_cl: it must be clear of it. (b_l's, 0.002,
    # is ~1.4σ of the transducer's b_l on this record: not resolved, so not asked.)
    assert abs(from_tau_out.values["f_cl"] - truth["f_cl"]) <= 0.2 * drive.coulomb_nm


def motor_route(run: Run, model: HarmonicDriveModel) -> dict[str, float]:
    """f_cl, b_l from the motor's balance with its friction held at `model`'s: what a bench without the
    load angle's stage (or a joint fit with the motor law wrong) has to go on."""
    parts = [part for part in sweep_parts([output_run(run)], model) if np.any(part.steady)]
    misfit = WindowTorques(parts, model)
    f_sl = get_values(model, ["f_sl"])["f_sl"]
    names = ["f_cl", "b_l", "J_l"]

    def residual(x: np.ndarray) -> np.ndarray:
        values = dict(zip(names, x, strict=True))
        return misfit({**values, "f_sl": max(f_sl, values["f_cl"])}) / WindowTorques.SCALE_NM

    start = list(get_values(model, names).values())
    solved = nonlinear_fit(residual, names, start, start)
    return {name: solved.values[name] for name in ("f_cl", "b_l")}


def test_a_motor_friction_mis_set_by_20_percent_biases_the_current_route_not_the_transducers(
    from_tau_out, noisy: Run, seed: HarmonicDriveModel
):
    s3 = seed.motor_friction.s3
    mf = seed.motor_friction
    assert s3 is not None and mf.k_v is not None and mf.v_c is not None
    wrong = with_values(seed, {"s3": MIS_SET * s3})
    unchanged = output_equation([noisy], wrong)
    assert unchanged.values == from_tau_out.values  # it reads no motor friction at all

    r = seed.mechanics.r
    truth = get_values(seed, ["f_cl", "b_l"])
    predicted = {
        "f_cl": (1 - MIS_SET) * s3 * (1 - mf.k_v * mf.v_c) / r,
        "b_l": (1 - MIS_SET) * s3 * mf.k_v / r**2,
    }
    right, biased = motor_route(noisy, seed), motor_route(noisy, wrong)
    for name in ("f_cl", "b_l"):
        assert abs(right[name] - truth[name]) <= K_SIGMA * from_tau_out.std_errors[name], (name, right)
        bias = biased[name] - truth[name]
        assert abs(bias - predicted[name]) <= 0.1 * predicted[name], f"{name}: {bias:.4g} vs {predicted}"
        assert abs(bias) > 10 * K_SIGMA * from_tau_out.std_errors[name]


def test_the_staged_identification_takes_the_transducers_and_says_so(noisy: Run, seed: HarmonicDriveModel):
    start = with_values(seed, {"s3": MIS_SET * (seed.motor_friction.s3 or 0.0)})
    result = staged_estimates([noisy], start)
    truth = get_values(seed, [*STIFFNESS, "s3"])
    for name, value in truth.items():
        estimate = result.estimate(name)
        assert estimate.identifiable and estimate.std_error is not None, estimate
        assert abs(estimate.value - value) <= K_SIGMA * estimate.std_error, estimate
    assert "stiffness: K_s, f_cl, b_l from tau_out (output transducer)" in result.notes
    assert "friction-velocity: s3, k_v from K_m·i_a − r·tau_out" in result.notes
    checks = [line for line in result.notes if line.startswith("friction-velocity: s3 from tau_in")]
    assert len(checks) == 1 and checks[0].endswith("agrees"), checks


def probe_on_the_bench(truth: HarmonicDriveModel, with_tau_out: bool) -> Run:
    """The gap workflow's probe (`hidden_effects.probe_profile`) on sim-dyno, as a single-axis bench
    records it, with the output transducer's column or without it."""
    config = load_rig_config("sim-dyno")
    rig = SimRig(config, model=truth)
    rig.enable()
    blocks: list[dict[str, np.ndarray]] = []
    setpoint, load = probe_profile(GAP_S, config.sample_rate_hz)
    result = rig.run_segment(Segment(ControlMode.VELOCITY, setpoint, load, "probe"), blocks.append)
    assert result.aborted is None
    keep = ["t", "i_cmd", "theta_m", "tau_ext", "theta_l"] + (["tau_out"] if with_tau_out else [])
    columns = {name: np.concatenate([b[name] for b in blocks]) for name in keep}
    meta = {"sample_rate_hz": config.sample_rate_hz, "source": "sim", "input_column": "i_cmd"}
    return Run(columns, meta).validate("bench probe")


@pytest.mark.parametrize("with_tau_out", [True, False], ids=["tau_out", "load-drive-torque"])
def test_hidden_load_friction_is_found_at_the_output_with_the_transducer(with_tau_out: bool):
    case = carried_at_zero_case()
    drive = load_rig_config("sim-dyno").load_drive
    assert drive is not None
    result = find_gaps([probe_on_the_bench(case.truth, with_tau_out)], case.model)
    assert [step.effect for step in result.steps] == ["load_side_friction"], result.verdict
    step = result.steps[0]
    chosen = [t for t in step.trials if t.accepted and t.candidate.effect == "load_side_friction"]
    assert chosen and chosen[0].candidate.channel == "load"  # the output's balance
    error = step.parameters["f_cl"] - get_values(case.truth, ["f_cl"])["f_cl"]
    if with_tau_out:
        assert abs(error) <= 0.5 * drive.coulomb_nm, f"f_cl off by {error:.3g} N·m"
        assert "output transducer" in result.verdict
    else:
        assert error > 0.5 * drive.coulomb_nm, f"f_cl off by {error:.3g} N·m: the bearing not taken up?"
