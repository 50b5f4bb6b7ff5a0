"""Temperatures recorded (issue 27 item 2, the simulated bench): a sim rig whose model has a `thermal`
section records `temp_motor` and `temp_gear` [°C] beside its samples, as its probes see the plant.

The reference is the plant's own temperatures of every cycle (the truth record of
`SimRig.record_truth`), turned into what a probe reads by the probe's stated law: a first-order lag of
`sensors.temperature_lag_s` and white noise of `sensors.temperature_noise_c`. Ideal probes read the
plant's temperatures exactly; lagged ones the discrete first-order filter of them, to rounding.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.signal import lfilter

from model.params import load_model
from rig.config import load_rig_config
from rig.runner import run_experiment
from rig.status import RunStatus
from rig.store.runs import RunStore
from sim_backend.inprocess import SimRig

SWEEP = {"speeds_rad_s": [100.0, 200.0], "settle_s": 0.2, "hold_s": 2.0}


def _played(tmp_path: Path, **sensors: float) -> tuple[RunStore, str, dict[str, np.ndarray], SimRig]:
    config = load_rig_config("sim")
    config = config.model_copy(update={"sensors": config.sensors.model_copy(update=sensors)})
    rig = SimRig(config, load_model("seed-thermal"))
    rig.record_truth()
    store = RunStore(tmp_path)
    outcome = run_experiment("speed-sweep", config, SWEEP, store, rig=rig)
    assert outcome.status == RunStatus.COMPLETE, outcome.reason
    return store, outcome.run_id, rig.truth(), rig


def test_ideal_probes_read_the_plants_temperatures(tmp_path: Path) -> None:
    store, run_id, truth, _ = _played(tmp_path, temperature_noise_c=0.0, temperature_lag_s=0.0)
    run = store.read(run_id)
    n = len(run["t"])
    for column in ("temp_motor", "temp_gear"):
        recorded, plant = run[column], truth[column][-n:]  # the run's rows are the last n cycles played
        assert np.all(np.isfinite(recorded))
        assert np.array_equal(recorded, plant), column
    # Friction power and copper loss warm both from the ambient 22 °C over the run.
    assert run["temp_motor"][-1] > run["temp_motor"][0] > 21.99
    assert run["temp_gear"][-1] > run["temp_gear"][0] > 21.99


def test_probes_lag_by_their_time_constant_and_carry_their_noise(tmp_path: Path) -> None:
    lag_s, noise_c = 2.0, 0.05
    store, run_id, truth, rig = _played(tmp_path, temperature_noise_c=noise_c, temperature_lag_s=lag_s)
    run = store.read(run_id)
    n = len(run["t"])
    alpha = 1.0 - np.exp(-rig.period_s / lag_s)
    for column in ("temp_motor", "temp_gear"):
        plant = truth[column]
        # The probe's law over every cycle the rig played (it started at the plant's temperature).
        lagged = lfilter([alpha], [1.0, alpha - 1.0], plant, zi=[(1.0 - alpha) * plant[0]])[0][-n:]
        residual = run[column] - lagged
        # White noise of the stated σ: its mean within 4σ/√n of 0, its spread within 5 % (n ≈ 7,000).
        assert abs(float(np.mean(residual))) < 4 * noise_c / np.sqrt(n), column
        assert float(np.std(residual)) == pytest.approx(noise_c, rel=0.05), column


def test_a_model_without_thermal_records_no_temperature(tmp_path: Path) -> None:
    config = load_rig_config("sim")
    store = RunStore(tmp_path)
    outcome = run_experiment("speed-sweep", config, SWEEP, store)
    assert outcome.status == RunStatus.COMPLETE, outcome.reason
    assert not {"temp_motor", "temp_gear"} & set(store.columns(outcome.run_id))
