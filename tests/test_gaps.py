"""The model-gap workflow on data with a hidden effect: it names the effect, adds it, the gap shrinks.

Data come from the simulated rig (closed loop: drive velocity loop, 17-bit encoder, 2 µrad output-sensor
noise) running `rig.analysis.gaps.synthetic`'s probe on a truth model; the model handed to the workflow lacks
the hidden effect(s). Tolerances: the gap (RMS shooting error over 20 ms windows, rad at the motor) must
shrink at least SHRINK = 3× after the hidden effect is added (the issue's requirement; the cases below
shrink 17–900× in practice), and a model that already matches the data must get no step at all.
"""

from __future__ import annotations

import functools
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hdrig_testing.hidden_effects import (
    HIDDEN,
    Case,
    carried_at_zero_case,
    hidden_case,
    record_open_loop,
    record_probe,
)
from hdrig_testing.independent_plant import IndependentRig, lab_profile
from model.params import load_model, save_model
from rig.analysis.gaps import METRIC, GapsResult, find_gaps
from rig.analysis.gaps.effects import SCREENS, SYSTEMATIC
from rig.analysis.gaps.workflow import GapOptions
from rig.core.actions import gaps_document
from rig.store.runfile import write_run

SHRINK = 3.0
DURATION_S = 12.0  # long enough for thermal drift (τ = 4 s) and a pass over the stroke, short for the suite


def _shrink(result: GapsResult) -> float:
    return result.initial_gap / result.final_gap


@pytest.mark.parametrize("effect", list(HIDDEN))
def test_a_hidden_effect_is_named_and_the_gap_shrinks(effect: str):
    case = hidden_case((effect,))
    run = record_probe(case.truth, DURATION_S, load_sensor=case.load_sensor)
    result = find_gaps([run], case.model)
    assert [s.effect for s in result.steps] == [effect], result.verdict
    assert _shrink(result) >= SHRINK, f"gap {result.initial_gap:.3g} → {result.final_gap:.3g} rad"
    assert result.steps[0].evidence


@pytest.mark.parametrize("compliant", [False, True], ids=["rigid", "compliant"])
def test_a_model_that_explains_the_data_gets_nothing_added(compliant: bool):
    case = hidden_case((), compliant=compliant)
    run = record_probe(case.truth, DURATION_S, load_sensor=compliant)
    result = find_gaps([run], case.model)
    assert result.steps == [], [s.effect for s in result.steps]
    assert result.final_gap == result.initial_gap
    assert result.verdict.startswith("the model explains the data")


def test_two_hidden_effects_are_both_found_one_per_step():
    case = hidden_case(("stribeck", "position_periodic_friction"))
    run = record_probe(case.truth, 16.0, load_sensor=False)
    result = find_gaps([run], case.model)
    assert sorted(s.effect for s in result.steps) == ["position_periodic_friction", "stribeck"]
    assert all(s.gap_after < s.gap_before for s in result.steps)
    assert _shrink(result) >= SHRINK


def test_a_real_single_axis_needs_only_time_current_and_motor_angle():
    # Closed loop, rigid model, no load actuator and no output sensor: an open-loop replay of the whole
    # run drifts away, the shooting windows and the one-step residual still judge the model.
    case = hidden_case(("stribeck",))
    run = record_probe(case.truth, DURATION_S, load_sensor=False, load_nm=0.0)
    assert set(run.columns) - {"omega_m"} == {"t", "i_cmd", "theta_m"}
    result = find_gaps([run], case.model)
    assert [s.effect for s in result.steps] == ["stribeck"]
    assert _shrink(result) >= SHRINK
    fitted = result.model.stribeck
    assert fitted is not None
    # The simulator fit recovers the truth's values within 10 % (f_st 0.04 N·m, ω_st 1.5 rad/s).
    assert fitted.f_st == pytest.approx(0.04, rel=0.1)
    assert fitted.omega_st == pytest.approx(1.5, rel=0.1)


def test_open_loop_voltage_data_work_too():
    case = hidden_case(("viscous_friction",))
    result = find_gaps([record_open_loop(case.truth, DURATION_S)], case.model)
    assert [s.effect for s in result.steps] == ["viscous_friction"]
    assert _shrink(result) >= SHRINK


def test_the_json_document_has_exactly_the_contract_shape(tmp_path: Path):
    case = hidden_case(("direction_asymmetry",))
    result = find_gaps(
        [record_probe(case.truth, 6.0, load_sensor=False)], case.model, model_out=tmp_path / "m.yaml"
    )
    doc = json.loads(json.dumps(gaps_document(result).as_json()))
    assert {"metric", "initial_gap", "steps", "final_gap", "final_model"} <= set(doc)
    assert doc["metric"] == METRIC
    (step,) = doc["steps"]
    assert {"effect", "gap_before", "gap_after", "evidence", "parameters"} <= set(step)
    assert step["effect"] == "direction_asymmetry" and "f_dir" in step["parameters"]
    assert doc["final_gap"] == step["gap_after"] < step["gap_before"] == doc["initial_gap"]
    written = load_model(doc["final_model"])
    assert written.direction_asymmetry is not None
    assert written.direction_asymmetry.f_dir == pytest.approx(0.012, rel=0.1)  # the truth's 0.012 N·m


def test_the_report_has_a_summary_and_the_plots(tmp_path: Path):
    case = hidden_case(("kinematic_error",))
    run = record_probe(case.truth, 6.0, load_sensor=True)
    result = find_gaps([run], case.model, report_dir=tmp_path)
    names = {p.name for p in result.report}
    assert {"summary.md", "gaps.png", "window.png", "step1-kinematic_error.png"} <= names
    assert all(p.stat().st_size > 0 for p in result.report)
    summary = (tmp_path / "summary.md").read_text()
    assert "kinematic_error" in summary and "k = 2 per motor turn" in summary
    assert result.final_model == tmp_path / "model.yaml" and result.final_model.exists()


def _hdrig(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "HDRIG_HOME": str(cwd / "store")}
    return subprocess.run(
        [sys.executable, "-m", "rig", *args], capture_output=True, text=True, timeout=300, cwd=cwd, env=env
    )


def test_cli_gaps_json_is_one_document_on_stdout(tmp_path: Path):
    case = hidden_case(("coulomb_friction",))
    data = write_run(record_probe(case.truth, 6.0, load_sensor=False), tmp_path / "probe.parquet")
    model = save_model(case.model, tmp_path / "model.yaml")
    result = _hdrig("gaps", "--data", str(data), "--model", str(model), "--json", "-q", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    doc = json.loads(result.stdout)
    assert [s["effect"] for s in doc["steps"]] == ["coulomb_friction"]
    assert np.isclose(doc["steps"][0]["parameters"]["s3"], 0.072, rtol=0.05)  # the truth's level
    assert Path(tmp_path / doc["final_model"]).exists()


def test_cli_gaps_names_a_missing_run_in_one_line(tmp_path: Path):
    result = _hdrig("gaps", "--data", "no-such-run", "--model", "seed", cwd=tmp_path)
    assert result.returncode == 2
    assert result.stderr.count("\n") == 1 and "no-such-run" in result.stderr


# --- data nobody here generated: the independent generator -------------------------------------------
# hdrig_testing.independent_plant shares no code with the plant: scipy RK45 with event-located sticking,
# a 14-bit motor encoder, its own velocity PI and lab profile with load steps. Each case is judged on the
# gap in excess of the null floor (the gap of the same generator with nothing hidden): the hidden effect
# must be named, alone, and remove at least half of that excess (the issue's "most of its excess gap").

INDEPENDENT_S = 12.0  # a pass of each part of the lab profile; ~15 s to generate, ~10 s to analyse
MOST_OF_EXCESS = 0.5


@functools.cache
def _independent(effects: tuple[str, ...], compliant: bool = False) -> tuple[Case, GapsResult]:
    """The workflow's result on the independent generator's record of a case (made once per module)."""
    case = hidden_case(effects, compliant=compliant)
    setpoint, load = lab_profile(INDEPENDENT_S)
    run = IndependentRig(case.truth, seed=1).record(setpoint, load, with_load=case.load_sensor)
    return case, find_gaps([run], case.model)


@pytest.fixture(scope="module")
def independent_floor() -> dict[bool, float]:
    """The null floor of the independent data, rigid and compliant: nothing hidden, nothing named."""
    floors = {}
    for compliant in (False, True):
        _, result = _independent((), compliant)
        assert result.steps == [], result.verdict
        assert result.verdict.startswith("the model explains the data"), result.verdict
        floors[compliant] = result.initial_gap
    return floors


@pytest.mark.parametrize(
    "effects",
    [("stribeck",), ("load_side_friction",), ("stribeck", "position_periodic_friction")],
    ids=["stribeck", "load_side_friction", "stribeck+periodic"],
)
def test_independent_data_name_the_hidden_effects_and_remove_most_of_the_excess_gap(
    effects: tuple[str, ...], independent_floor: dict[bool, float]
):
    case, result = _independent(effects)
    floor = independent_floor[not case.model.rigid]
    assert sorted(s.effect for s in result.steps) == sorted(effects), result.verdict
    excess = result.initial_gap - floor
    assert excess > floor, (
        f"the hidden effect must stand out: gap {result.initial_gap:.3g}, floor {floor:.3g}"
    )
    removed = (result.initial_gap - result.final_gap) / excess
    assert removed >= MOST_OF_EXCESS, f"{removed:.0%} of the excess removed"


def test_stribeck_is_told_from_static_friction_by_its_decay_with_speed():
    # Both add friction near zero speed; a higher breakaway shortens the same stick-slip. The static
    # friction candidate's fit leaves friction that decays with |ω| while moving: it is rejected for that.
    _, result = _independent(("stribeck",))
    static = [t for t in result.steps[0].trials if t.candidate.effect == "static_friction"]
    assert static and not static[0].accepted
    assert "decays with speed" in static[0].reason


def test_a_large_gap_no_effect_explains_is_reported_not_left_unsaid(monkeypatch: pytest.MonkeyPatch):
    # An effect outside the vocabulary: Stribeck friction hidden, and the vocabulary cut down to effects
    # that cannot explain it (Coulomb, viscous, direction offset). Nothing can be named; the result must
    # still say the gap is systematic, where the residual lives (low speeds), and why each candidate tried
    # was rejected.
    kept = ("coulomb_friction", "viscous_friction", "direction_asymmetry")
    monkeypatch.setattr("rig.analysis.gaps.effects.SCREENS", {name: SCREENS[name] for name in kept})
    case = hidden_case(("stribeck",))
    result = find_gaps([record_probe(case.truth, DURATION_S, load_sensor=False)], case.model)
    assert result.steps == []
    assert result.verdict.startswith("nothing named, but the gap is systematic"), result.verdict
    assert result.unexplained is not None and "speed" in result.unexplained.axis
    assert result.unexplained.share >= SYSTEMATIC
    assert result.rejected and all(": " in line for line in result.rejected)
    doc = gaps_document(result).as_json()
    assert doc["unexplained"] == result.unexplained.line() and doc["rejected"] == result.rejected


def test_effects_that_only_explain_the_data_together_are_found_as_a_pair():
    # Stribeck and position-periodic friction hidden together, and a bar (2×) that each alone misses on
    # these data (×1.8 and ×1.6 held out): fitted together they pass it against the better one alone
    # (×2.3), and both are added, one step each, the evidence saying they go together.
    case = hidden_case(("stribeck", "position_periodic_friction"))
    run = record_probe(case.truth, DURATION_S, load_sensor=False)
    result = find_gaps([run], case.model, options=GapOptions(min_shrink=2.0))
    assert sorted(s.effect for s in result.steps) == ["position_periodic_friction", "stribeck"], (
        result.verdict
    )
    assert all("only together with" in s.evidence for s in result.steps)
    assert result.steps[0].gap_after < result.steps[0].gap_before
    assert result.steps[1].gap_after < result.steps[1].gap_before
    assert result.initial_gap / result.final_gap >= 2.0


# --- issue 25's two classes, on both generators ----------------------------------------------------------


def _issue_case(name: str) -> Case:
    if name == "at_zero":
        return carried_at_zero_case()
    return hidden_case(("stribeck", "position_periodic_friction"), compliant=True)


@pytest.mark.parametrize("generator", ["sim", "independent"])
@pytest.mark.parametrize("name", ["at_zero", "pair_compliant"])
def test_issue_25_classes_are_named_on_both_generators(name: str, generator: str):
    """Load-side friction hidden while the model carries f_cl = f_sl = b_l = 0 (an effect at zero is a
    candidate; it was never tried before), and Stribeck with position-periodic friction on a flexible
    joint (Stribeck, not static friction, named beside the periodic part)."""
    case = _issue_case(name)
    if generator == "sim":
        run = record_probe(case.truth, DURATION_S, load_sensor=case.load_sensor)
    else:
        setpoint, load = lab_profile(INDEPENDENT_S)
        run = IndependentRig(case.truth, seed=1).record(setpoint, load, with_load=case.load_sensor)
    result = find_gaps([run], case.model)
    assert sorted(s.effect for s in result.steps) == sorted(case.hidden), result.verdict
    assert result.final_gap < result.initial_gap
