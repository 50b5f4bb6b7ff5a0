"""`warm-up` and the thermal identification (issue 27 items 3 and 4) on the simulated bench.

The plant is `seed-thermal-fast` (seed-thermal with its heat capacities scaled down, stated in the
preset, so the gear settles within the experiment's default bounds). Done when: warm-up then the thermal
fit recover the network's parameters and time constants and the friction's temperature law within 10 %,
and the running torque at the reference temperature within 5 %. The reference truth is measured, not
computed: the same checkpoint on the same plant held at T_ref (ambient and start at T_ref, heat
capacities so large that nothing warms).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from model.errors import UserInputError
from model.params import HarmonicDriveModel, load_model
from model.run import Run
from rig.analysis.identification.thermal_stage import identify_thermal
from rig.config import load_rig_config
from rig.experiments.base import context_from_run
from rig.experiments.warm_up import WarmUpParams, warm_up_checkpoints
from rig.runner import run_experiment
from rig.status import RunStatus
from rig.store.runs import RunStore
from sim_backend.inprocess import SimRig

PLANT = "seed-thermal-fast"


def _warm_up(store: RunStore, model: HarmonicDriveModel, **params: object) -> Run:
    config = load_rig_config("sim")
    outcome = run_experiment("warm-up", config, dict(params), store, rig=SimRig(config, model))
    assert outcome.status == RunStatus.COMPLETE, outcome.reason
    return store.read(outcome.run_id)


@pytest.fixture(scope="module")
def played(tmp_path_factory: pytest.TempPathFactory) -> tuple[RunStore, Run]:
    store = RunStore(tmp_path_factory.mktemp("warm"))
    return store, _warm_up(store, load_model(PLANT))


def test_warm_up_settles_within_its_bound_and_cools(played: tuple[RunStore, Run]) -> None:
    store, run = played
    doc = store.get(run.meta["run_id"])
    metrics = doc["metrics"]
    params = WarmUpParams()
    assert metrics["settled"] == 1
    assert 0 < metrics["settled_at_s"] < params.warm_s
    # 15 warm checkpoints (the first cold), 10 in the cool-down.
    assert metrics["checkpoints"] == 1 + 14 + 10
    assert metrics["temp_gear_max_c"] > metrics["temp_gear_start_c"] + 5.0
    assert metrics["temp_gear_end_c"] < metrics["temp_gear_max_c"] - 5.0
    # The grease's law: warmer, less friction (seed-thermal-fast: beta_T 0.025 1/K).
    assert metrics["torque_20_change_pct"] < -10.0
    artifacts = store.run_dir(run.meta["run_id"]) / "artifacts"
    for name in ("plots/temperature.png", "plots/friction_vs_temperature.png", "checkpoints.csv"):
        assert (artifacts / name).is_file(), name


def test_a_short_bound_is_said_not_settled(tmp_path: Path) -> None:
    store = RunStore(tmp_path)
    run = _warm_up(store, load_model(PLANT), warm_s=60.0, cool_s=0.0, settle_window_s=30.0)
    metrics = store.get(run.meta["run_id"])["metrics"]
    assert metrics["settled"] == 0 and math.isnan(float(metrics["settled_at_s"]))
    assert metrics["gear_rate_end_k_per_min"] > WarmUpParams().settle_rate_k_per_min


def test_warm_up_then_fit_recovers_the_thermal_law(played: tuple[RunStore, Run]) -> None:
    store, run = played
    truth = load_model(PLANT)
    assert truth.thermal is not None
    found = identify_thermal([run], truth)
    for name, estimate in found.network.parameters.items():
        expected = getattr(truth.thermal, name)
        assert estimate.value == pytest.approx(expected, rel=0.10), name
        assert estimate.sigma > 0, name
    # The time constants of the true network, from its matrix.
    t = truth.thermal
    a = np.array(
        [
            [-(1 / t.R_wg + 1 / t.R_wa) / t.C_w, 1 / (t.R_wg * t.C_w)],
            [1 / (t.R_wg * t.C_g), -(1 / t.R_wg + 1 / t.R_ga) / t.C_g],
        ]
    )
    taus = sorted(1.0 / -np.linalg.eigvals(a).real, reverse=True)
    for estimate, expected in zip(found.network.time_constants_s, taus, strict=True):
        assert estimate.value == pytest.approx(expected, rel=0.10)
    assert found.network.ambient_c[0] == pytest.approx(t.T_amb, abs=0.2)
    law = found.law
    assert law.beta_per_k.value == pytest.approx(t.beta_T, rel=0.10)
    assert abs(law.beta_per_k.value - t.beta_T) < 4 * law.beta_per_k.sigma
    assert found.section.T_ref == t.T_ref

    # The reference: the plant held at T_ref, its first checkpoint's running torque.
    held = t.model_copy(update={"T_amb": t.T_ref, "C_w": 1e9, "C_g": 1e9})
    isothermal = truth.model_copy(update={"thermal": held})
    ref_run = _warm_up(store, isothermal, warm_s=10.0, cool_s=0.0, settle_window_s=5.0)
    params = WarmUpParams.model_validate(ref_run.meta["params"], strict=False)
    table = warm_up_checkpoints(ref_run, context_from_run(ref_run), params)
    assert np.ptp(table["temp_gear_c"]) < 0.05
    for speed, estimate in law.reference_nm.items():
        assert estimate.value == pytest.approx(float(table[f"torque_{speed:g}_nm"][0]), rel=0.05), speed


def test_a_run_without_temperatures_is_refused_in_one_line() -> None:
    run = Run({"t": np.arange(3.0), "theta_m": np.zeros(3), "i_a": np.zeros(3)}, {})
    with pytest.raises(UserInputError, match="temp_gear, temp_motor") as caught:
        warm_up_checkpoints(run, None, WarmUpParams())  # type: ignore[arg-type]
    assert "\n" not in str(caught.value)


def test_fit_takes_warm_up_runs_to_the_thermal_stage(played: tuple[RunStore, Run]) -> None:
    from rig.analysis.identification.identify import THERMAL, identify

    _, run = played
    truth = load_model(PLANT)
    assert truth.thermal is not None
    result = identify([run], load_model("seed"))  # a start without a thermal section
    assert result.model.thermal is not None
    assert result.model.thermal.beta_T == pytest.approx(truth.thermal.beta_T, rel=0.10)
    assert result.model.thermal.C_g == pytest.approx(truth.thermal.C_g, rel=0.10)
    rows = {row.name: row for row in result.parameters if row.stage == THERMAL}
    assert {"C_w", "C_g", "R_wg", "R_wa", "R_ga", "beta_T", "T_amb"} <= set(rows)
    assert rows["beta_T"].uncertainty is not None and rows["beta_T"].identifiable
    assert any(note.startswith(f"{THERMAL}: friction law") for note in result.notes)
