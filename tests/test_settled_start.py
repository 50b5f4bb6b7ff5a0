"""Runs start from a settled gear (issue 31 item 2): the runner holds still until the output is at rest,
and the tracking experiments start on a whole motor turn, so a step or a sine played after other
experiments reports what it reports when played alone from rest.

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
from rig.store import RunStore
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


@pytest.mark.parametrize(
    ("name", "keys", "rel"),
    [
        ("sine", ("rms_error_rad", "gain", "phase_lag_deg"), 0.01),
        ("step", ("settling_s_1", "rise_s", "overshoot_pct"), 0.02),
    ],
)
def test_campaign_metrics_equal_the_standalone_ones(
    played: tuple[dict[str, Run], dict[str, Run]], name: str, keys: tuple[str, ...], rel: float
) -> None:
    """Within 1 % (the sine) or 2 % (the step): what is left of the start's difference — the approach ends
    within the position loop's friction-stalled error of the turn (measured 4 mrad at the motor before
    the campaign's step, where the kinematic error, A·k = 0.05, puts the load 0.15 mrad off the standalone
    start: the step's overshoot moved 1.4 %) and the load keeps the twist its static friction holds
    (≤ f_sl/K_s = 0.35 mrad); sensor noise alone moves these figures by < 0.01 %. Before
    the settle and the approach, the campaign's sine RMS was 2.7× the standalone one. (The step back's
    settling time is left out: its response peaks within 0.2 mrad of the 20 mrad band's edge, so that
    twist moves it by a lobe of the load mode, 0.42 s or 0.48 s; the sine's maximum error, one sample's
    extreme, moves by ~2 %.)"""
    campaign, alone = played
    got, want = _metrics(campaign[name]), _metrics(alone[name])
    for key in keys:
        assert got[key] == pytest.approx(want[key], rel=rel), f"{name}.{key}: {got[key]}, alone {want[key]}"
