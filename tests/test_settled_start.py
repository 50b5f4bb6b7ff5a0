"""Runs start from a settled gear (issue 31 item 2): the runner holds still until the output is at rest,
and the tracking experiments start at the stroke's origin (θ_m = 0, a whole motor turn, the speed loop's
integral unloaded), so a step or a sine played after other experiments reports what it reports when
played alone from rest.

The campaign's experiments up to the sine are played one after the other on one simulated rig (as
`hdrig run campaign` keeps its rig open); the step and the sine are compared with the same experiments
played alone on a fresh rig.
"""

from __future__ import annotations

import numpy as np
import pytest

from model.run import Run
from rig.config import load_rig_config
from rig.experiments import CAMPAIGN_ORDER, EXPERIMENTS
from rig.experiments.base import context_from_run
from rig.runner import REST_NOISE_FACTOR, SETTLE_MAX_S, make_params, output_motion, run_experiment
from rig.store.runs import RunStore
from sim_backend.inprocess import SimRig

CFG = load_rig_config("sim")


def _play(names: tuple[str, ...], store: RunStore) -> dict[str, Run]:
    rig = SimRig(CFG)
    runs = {}
    try:
        for name in names:
            outcome = run_experiment(name, CFG, {}, store, rig=rig)
            assert outcome.status == "complete", outcome.reason
            runs[name] = store.read(outcome.run_id)
    finally:
        rig.close()
    return runs


@pytest.fixture(scope="module")
def played(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict[str, Run], dict[str, Run]]:
    """(the campaign's runs through the sine, the step and the sine each alone on a fresh rig)."""
    order = CAMPAIGN_ORDER[: CAMPAIGN_ORDER.index("sine") + 1]
    with RunStore(tmp_path_factory.mktemp("runs")) as store:
        campaign = _play(order, store)
        alone = {name: _play((name,), store)[name] for name in ("step", "sine")}
    return campaign, alone


def _metrics(run: Run) -> dict[str, float]:
    experiment = EXPERIMENTS[str(run.meta["experiment"])]
    params = make_params(experiment, dict(run.meta["params"]))
    return {k: float(v) for k, v in experiment.analyze(run, params, context_from_run(run)).metrics.items()}


def test_every_run_of_the_campaign_starts_at_rest(played: tuple[dict[str, Run], dict[str, Run]]) -> None:
    campaign, _ = played
    for name, run in campaign.items():
        settle = run.meta["settle"]
        assert settle["at_rest"], f"{name}: {settle}"
        assert settle["duration_s"] <= SETTLE_MAX_S
        # Recount from the samples: the last 0.1 s before the program is at the load sensor's noise.
        start = min(int(seg["start"]) for seg in run.meta["segments"])
        motion, noise = output_motion(run["theta_l"][start - 100 : start])
        assert motion <= REST_NOISE_FACTOR * noise
        assert motion < 3 * CFG.sensors.load_sensor_noise_rad, f"{name}: {motion} rad over the zero window"


def test_the_campaign_rings_before_it_settles(played: tuple[dict[str, Run], dict[str, Run]]) -> None:
    """The premise: in the campaign a tracking run begins with the load still ringing from the experiment
    before (the approach and the settle then bring it to rest); alone, none rings."""
    campaign, alone = played
    ringing = {name: float(np.ptp(campaign[name]["theta_l"][:100])) for name in ("step", "sine")}
    assert max(ringing.values()) > 100 * CFG.sensors.load_sensor_noise_rad, ringing
    assert all(
        float(np.ptp(run["theta_l"][:100])) < 10 * CFG.sensors.load_sensor_noise_rad for run in alone.values()
    )


def test_tracking_runs_start_at_the_origin_with_no_current_held(
    played: tuple[dict[str, Run], dict[str, Run]],
) -> None:
    """The approach's end, from the samples: the motor at θ_m = 0 within what its hold reached (said in
    the metadata, at most 2 mrad: 0.12 mrad at the load through r and the kinematic error's A·k; the
    sine after the step stays 1.49 mrad off when the hold's 4 s end with the motor stuck short of its
    breakaway, which `within` says; the campaign's metrics equal the standalone ones all the same), and
    the current the drive commands there at most 0.05 A (the 2.6 A the hold leaves in the speed loop's
    integral unloaded; a fresh drive starts at 0)."""
    campaign, _ = played
    for name in ("step", "sine"):
        run = campaign[name]
        approach = run.meta["approach"]
        start = min(int(seg["start"]) for seg in run.meta["segments"])
        assert approach["target_rad"] == 0.0
        theta_m = run["theta_m"][start - 100 : start]
        assert np.all(np.abs(theta_m - approach["error_rad"]) < approach["tolerance_rad"]), name
        assert abs(approach["error_rad"]) <= 2e-3 or approach["within"], approach
        assert np.max(np.abs(run["i_cmd"][start - 100 : start])) < 0.05, name


@pytest.mark.parametrize("name", ["step", "sine"])
def test_campaign_metrics_equal_the_standalone_ones(
    played: tuple[dict[str, Run], dict[str, Run]], name: str
) -> None:
    """Within 1 %: the step's settling_s_1, rise_s and overshoot_pct, the sine's RMS error, gain and phase
    lag (measured: ≤ 0.12 % and ≤ 0.02 %). What is left of the start's difference: the load keeps the
    twist its static friction holds (≤ f_sl/K_s = 0.35 mrad) and a hold may end a few encoder counts off
    the origin (≤ 0.4 mrad at the motor measured); sensor noise alone moves these figures by < 0.01 %.
    The step was 1.4 % off while the approach went to the nearest turn (one turn up, where the slow
    friction level C(θ_m) differs) and left the breakaway current in the speed loop; before the settle
    and the approach, the campaign's sine RMS was 2.7× the standalone one. (The step back's settling
    time is left out: its response peaks within 0.2 mrad of the 20 mrad band's edge, so that twist moves
    it by a lobe of the load mode, 0.42 s or 0.48 s; the sine's maximum error, one sample's extreme,
    moves by ~1 %.)"""
    keys = {
        "step": ("settling_s_1", "rise_s", "overshoot_pct"),
        "sine": ("rms_error_rad", "gain", "phase_lag_deg"),
    }
    campaign, alone = played
    got, want = _metrics(campaign[name]), _metrics(alone[name])
    for key in keys[name]:
        assert got[key] == pytest.approx(want[key], rel=0.01), f"{name}.{key}: {got[key]}, alone {want[key]}"
