"""`hdrig trend` with a thermal law (issue 27 item 6): each endurance checkpoint's friction brought to the
law's T_ref, beside the raw. On a plant that warms and does not wear (seed-thermal-fast: the gear warms
by ~3 K over the first minutes of duty) the raw friction level falls with the temperature; normalized
with the plant's own law it stays flat. The 10 h check with wear and pauses is a bench
(bench/bench_thermal_trend.py).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from model.errors import UserInputError
from model.params import load_model
from rig.config import load_rig_config
from rig.core import actions
from rig.core.trend import normalized_friction, trend_document
from rig.runner import run_experiment
from rig.status import RunStatus
from rig.store.runs import RunStore
from sim_backend.inprocess import SimRig

PLANT = "seed-thermal-fast"


@pytest.fixture(scope="module")
def endurance(tmp_path_factory: pytest.TempPathFactory) -> tuple[RunStore, str]:
    config = load_rig_config("sim")
    store = RunStore(tmp_path_factory.mktemp("trend"))
    params = {"duration_h": 0.1, "checkpoint_every_min": 1.0}
    outcome = run_experiment("endurance", config, params, store, rig=SimRig(config, load_model(PLANT)))
    assert outcome.status == RunStatus.COMPLETE, outcome.reason
    return store, outcome.run_id


def test_the_normalized_trend_is_flat_where_the_raw_one_falls(endurance: tuple[RunStore, str]) -> None:
    store, run_id = endurance
    law = load_model(PLANT).thermal
    assert law is not None
    document = trend_document(store, run_id=run_id, law=law)
    assert document.t_ref_c == law.T_ref and document.beta_per_k == law.beta_T
    temps = np.array([p.temp_gear_c for p in document.points], dtype=float)
    raw = np.array([p.coulomb_estimate for p in document.points])
    normalized = np.array([p.coulomb_normalized_estimate for p in document.points], dtype=float)
    assert len(raw) == 7 and temps[-1] > temps[0] + 2.0
    assert raw[-1] / raw[0] - 1.0 < -0.05  # warming: 7 % less friction
    assert np.ptp(normalized) / np.mean(normalized) < 0.005
    for p in document.points:
        assert p.coulomb_normalized_sigma == pytest.approx(
            p.coulomb_sigma * math.exp(law.beta_T * (float(p.temp_gear_c or 0.0) - law.T_ref))
        )


def test_without_a_law_the_temperature_is_shown_and_nothing_normalized(
    endurance: tuple[RunStore, str],
) -> None:
    store, run_id = endurance
    document = trend_document(store, run_id=run_id)
    assert all(p.temp_gear_c is not None for p in document.points)
    assert all(p.coulomb_normalized_estimate is None for p in document.points)
    assert document.t_ref_c is None


def test_normalization_is_the_law_inverted() -> None:
    law = load_model(PLANT).thermal
    assert law is not None
    at_ref = 0.07
    for temp in (10.0, 25.0, 40.0):
        measured = at_ref * math.exp(-law.beta_T * (temp - law.T_ref))
        value, sigma = normalized_friction(measured, 0.001, temp, law)
        assert value == pytest.approx(at_ref, rel=1e-12)
        assert sigma == pytest.approx(0.001 * at_ref / measured, rel=1e-12)


def test_a_model_without_a_thermal_section_is_refused(endurance: tuple[RunStore, str]) -> None:
    store, run_id = endurance
    with pytest.raises(UserInputError, match="no thermal section"):
        actions.trend(store, run_id=run_id, model="seed")


def test_the_output_share_is_left_as_measured() -> None:
    """The law scales the motor friction only (docs/MODEL.md): with u, the output side's share seen at the
    motor, a level measured warm comes back to the motor part at T_ref plus u, not u warmed as well."""
    law = load_model(PLANT).thermal
    assert law is not None
    motor_at_ref, share = 0.05, 0.02
    for temp in (10.0, 25.0, 40.0):
        measured = motor_at_ref * math.exp(-law.beta_T * (temp - law.T_ref)) + share
        value, _ = normalized_friction(measured, 0.001, temp, law, unscaled_nm=share)
        assert value == pytest.approx(motor_at_ref + share, rel=1e-12)
