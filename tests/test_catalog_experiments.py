"""The catalog's load-side tests on the simulated dynamometer (issue 26): the figures they measure on
`sim-catalog` against the plant's truth (the preset's values, the plant's own power balance), the load
drive and transducers of the simulated bench, and the one-line refusal on a bench without them."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from model.errors import UserInputError
from model.params import load_model
from model.run import Run
from rig.config import load_rig_config
from rig.experiments import EXPERIMENTS
from rig.experiments.base import Experiment, RigContext, segment_rows
from rig.experiments.efficiency_map import EfficiencyMap, EfficiencyMapParams, point_label
from rig.experiments.no_load_torque import NoLoadTorque, NoLoadTorqueParams
from rig.experiments.starting_torque import StartingTorque, StartingTorqueParams
from rig.experiments.torsional_stiffness import TorsionalStiffness, TorsionalStiffnessParams
from rig.experiments.transmission_accuracy import TransmissionAccuracy, TransmissionAccuracyParams
from rig.interface import ControlMode, Segment
from sim_backend.inprocess import SimRig


def play(
    experiment: Experiment, params: Any, rig_name: str = "sim-catalog"
) -> tuple[Run, RigContext, SimRig]:
    """Play the program on an in-process rig, recording the truth, and gather the Run as the runner does."""
    config = load_rig_config(rig_name)
    rig = SimRig(config)
    rig.record_truth(True)
    ctx = RigContext(config, rig.gear_ratio, rig.torque_constant_nm_per_a, 0.0)
    blocks: list[dict[str, np.ndarray]] = []
    segments, start = [], 0
    rig.enable()
    for seg in experiment.program(params, ctx):
        assert rig.run_segment(seg, blocks.append).aborted is None
        segments.append({"label": seg.label, "mode": str(seg.mode), "start": start, "cycles": seg.cycles})
        start += seg.cycles
    columns = {k: np.concatenate([b[k] for b in blocks]) for k in blocks[0]}
    return Run(columns, {"segments": segments, "sample_rate_hz": config.sample_rate_hz}), ctx, rig


def test_the_dyno_rig_files_load_with_their_load_drive_and_transducers() -> None:
    for name, model in (("sim-dyno", "seed-thermal"), ("sim-catalog", "catalog-cha-25a-100")):
        config = load_rig_config(name)
        assert config.model == model
        assert config.load_drive is not None and config.load_drive.torque_limit_nm > 0
        assert config.sensors.torque_transducers
    rig = SimRig(load_rig_config("sim-dyno"))
    assert set(rig.extra_columns) == {"temp_motor", "temp_gear", "tau_in", "tau_out"}


@pytest.mark.parametrize("name", ["torsional-stiffness", "efficiency-map", "starting-torque"])
def test_a_bench_without_a_load_drive_refuses_the_load_side_tests_in_one_line(name: str) -> None:
    config = load_rig_config("sim")
    experiment = EXPERIMENTS[name]
    ctx = RigContext(config, 0.01, 0.0302, 0.0)
    with pytest.raises(UserInputError) as err:
        experiment.program(experiment.Params(), ctx)
    message = str(err.value)
    assert "\n" not in message
    assert f"{name} needs a load drive" in message and "'sim'" in message
    if name != "starting-torque":  # its back-driving half needs the load drive only
        assert "torque transducers" in message


def test_the_load_drive_limits_and_lags_its_torque_and_adds_its_rotor() -> None:
    config = load_rig_config("sim-catalog")
    rig = SimRig(config)
    assert config.load_drive is not None
    gear_j_l = load_model("catalog-cha-25a-100").mechanics.J_l
    assert rig.model.mechanics.J_l == pytest.approx(gear_j_l + config.load_drive.inertia_kgm2)
    blocks: list[dict[str, np.ndarray]] = []
    rig.enable()
    # Asked beyond its 100 N·m limit, the load drive gives 100 N·m, reached through a 500 Hz first-order
    # current loop: after one cycle (1 ms) 1 − exp(−2π·500·0.001) = 95.7 % of the step.
    rig.run_segment(Segment(ControlMode.POSITION, np.zeros(50), 150.0, "limit"), blocks.append)
    applied = np.concatenate([b["tau_ext"] for b in blocks])
    assert applied[0] == pytest.approx(100.0 * (1 - np.exp(-2 * np.pi * 500 * 0.001)))
    assert applied[-1] == pytest.approx(100.0)


def test_torsional_stiffness_recovers_the_presets_stiffness_and_lost_motion() -> None:
    model = load_model("catalog-cha-25a-100")
    ns, hyst, load = model.nonlinear_stiffness, model.hysteresis, model.load_friction
    assert ns is not None and hyst is not None and load is not None
    params = TorsionalStiffnessParams()
    run, ctx, _ = play(TorsionalStiffness(), params)
    metrics = TorsionalStiffness().analyze(run, params, ctx).metrics
    # Done-when of issue 26: K1, K2, K3 within 5 %. Measured: within 1.5 % (docs/BENCHMARKS.md); the margin
    # covers the transducer's noise and the output moving slowly against its friction.
    for name, truth in (("K1", ns.K1), ("K2", ns.K2), ("K3", ns.K3)):
        assert metrics[f"{name}_nm_per_rad"] == pytest.approx(truth, rel=0.05), name
    # Lost motion: both branches are the spring curve shifted by ±(T_h + f_cl), saturated near zero
    # torque, so their midpoints at ±T_L lie on T/K1: 2·T_L/K1 (T_L = 3 % of T_R = 2.01 N·m, inside T1).
    # 10 %: the done-when.
    t_l = params.lost_motion_fraction * params.rated_torque_nm
    assert metrics["lost_motion_rad"] == pytest.approx(2 * t_l / ns.K1, rel=0.10)
    # Hysteresis loss: the branches' offsets at zero torque, ±(T_h + f_cl) (the Dahl element saturated, the
    # output bearing's Coulomb friction opposing the slow motion), apart by 2·(T_h + f_cl)/K1.
    assert load.f_cl is not None
    assert metrics["hysteresis_loss_rad"] == pytest.approx(2 * (hyst.T_h + load.f_cl) / ns.K1, rel=0.10)


def test_efficiency_map_agrees_with_the_plants_power_balance_at_every_point() -> None:
    params = EfficiencyMapParams()
    run, ctx, rig = play(EfficiencyMap(), params)
    table = EfficiencyMap().analyze(run, params, ctx).tables["efficiency_map"]
    truth = rig.truth()
    r = rig.gear_ratio
    gear_j_l = rig.gear_model.mechanics.J_l
    settle = ctx.cycles(params.settle_s)
    for k, (speed, load) in enumerate(zip(table["speed_rad_s"], table["load_nm"], strict=True)):
        i, j = sorted(params.speeds_rad_s).index(speed), sorted(params.loads_nm).index(load)
        rows = segment_rows(run, point_label(i, j))
        w = slice(rows.start + settle, rows.stop)
        t_s, f_m, f_l, w_m, w_l = (truth[c][w] for c in ("t_s", "f_m", "f_l", "omega_m", "omega_l"))
        # The plant's power balance: what the gear takes in, less what its friction on each side and its
        # transmission (spring, hysteresis element) dissipate, less the kinetic energy its output gains.
        p_in = np.mean((r * t_s + f_m) * w_m)
        kinetic = (
            0.5 * gear_j_l * (w_l[-1] ** 2 - w_l[0] ** 2) / (w_l.shape[0] * ctx.config.sample_rate_hz**-1)
        )
        losses = np.mean(f_m * w_m) + np.mean(f_l * w_l) + np.mean(t_s * (r * w_m - w_l)) + kinetic
        eta_truth = 1 - losses / p_in
        # Done-when of issue 26: within 1 percentage point at every grid point (measured: within 0.3).
        assert table["eta"][k] == pytest.approx(eta_truth, abs=0.01), (speed, load)
        assert 0 < table["eta_sigma"][k] < 0.01


def test_no_load_torque_follows_the_presets_friction_law() -> None:
    model = load_model("catalog-cha-25a-100")
    mf, lf, r = model.motor_friction, model.load_friction, model.mechanics.r
    config = load_rig_config("sim-catalog")
    ld = config.load_drive
    assert mf is not None and lf is not None and ld is not None
    assert mf.s3 is not None and mf.k_v is not None and mf.v_c is not None
    assert lf.f_cl is not None and lf.b_l is not None
    params = NoLoadTorqueParams()
    run, ctx, _ = play(NoLoadTorque(), params)
    table = NoLoadTorque().analyze(run, params, ctx).tables["no_load_torque"]
    for speed, fwd, bwd in zip(
        table["speed_rad_s"], table["torque_fwd_nm"], table["torque_bwd_nm"], strict=True
    ):
        # docs/MODEL.md's moving branch (s1 = s2 = 0, no Fourier part) plus the output's friction (the gear's
        # bearing and the load drive's) seen through r.
        motor = mf.s3 * (1 + mf.k_v * (speed - mf.v_c))
        output = lf.f_cl + lf.b_l * r * speed + ld.coulomb_nm + ld.viscous_nms * r * speed
        # 2 %: the transducer's noise averaged over a second, the kinematic error's ripple in the output.
        assert fwd == pytest.approx(motor + r * output, rel=0.02), speed
        assert -bwd == pytest.approx(motor + r * output, rel=0.02), speed


def test_starting_and_back_driving_torques_are_the_presets_breakaway_levels() -> None:
    model = load_model("catalog-cha-25a-100")
    mf, lf, r = model.motor_friction, model.load_friction, model.mechanics.r
    assert mf is not None and lf is not None
    assert mf.s3 is not None and mf.k_v is not None and mf.v_c is not None and lf.f_sl is not None
    assert mf.static_factor is not None
    params = StartingTorqueParams()
    run, ctx, _ = play(StartingTorque(), params)
    metrics = StartingTorque().analyze(run, params, ctx).metrics
    # docs/MODEL.md: the stuck input breaks away at f_sm = static_factor·C·(1 − k_v·v_c) (no Fourier part).
    f_sm = mf.static_factor * mf.s3 * (1 - mf.k_v * mf.v_c)
    # 5 %: the straight line through the stuck stretch still carries the transducer's noise (≈ 2 % of it).
    assert metrics["starting_torque_nm"] == pytest.approx(f_sm, rel=0.05)
    # Back-driving: the output's static friction, and the input's breakaway seen through the ratio.
    assert metrics["back_driving_torque_nm"] == pytest.approx(lf.f_sl + f_sm / r, rel=0.05)


def test_transmission_accuracy_measures_the_presets_kinematic_error() -> None:
    model = load_model("catalog-cha-25a-100")
    ke = model.kinematic_error
    assert ke is not None
    params = TransmissionAccuracyParams()
    run, ctx, _ = play(TransmissionAccuracy(), params)
    metrics = TransmissionAccuracy().analyze(run, params, ctx).metrics
    assert metrics["harmonic1_order"] == round(ke.k)
    # The fitted order's amplitude is A (3 %: the output's inertia follows the ripple at a few Hz, far below
    # its resonance); peak to peak is 2·A plus the output sensor's noise at the extremes (10 %).
    assert metrics["harmonic1_amplitude_rad"] == pytest.approx(ke.A, rel=0.03)
    assert metrics["error_pp_rad"] == pytest.approx(2 * ke.A, rel=0.10)
