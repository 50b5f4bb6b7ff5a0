"""`identify` end to end: a campaign on a simulated rig with realistic sensors, fitted from a wrong start.

Truth is the seed model. The rig (configs/rigs/sim.yaml) quantizes the motor encoder to 17 bits, adds
5 mA of current noise and 2 µrad of output-sensor noise, and filters its speed estimate, as a drive
does. The start model is 15–30 % off in the parameters the fit must recover.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

from model.params import HarmonicDriveModel, load_model
from model.run import Run
from rig.analysis.fit.parameters import get_values, with_values
from rig.analysis.identification import identify
from rig.config import load_rig_config
from rig.core.actions import execute_plan, plan_run
from rig.store.runs import RunStore

EXPERIMENTS = ("speed-sweep", "position-friction", "pulse", "load-variation", "step", "sine", "ramp", "chirp")

# Relative tolerance per parameter after staged + joint fitting, with noise, and why.
TOLERANCE = {
    "J_m": 0.02,  # the FRF and the trajectories both see it; 1 % seen, noise and FRF leakage
    "J_l": 0.02,
    "K_s": 0.01,  # static windows under four loads: 0.05 % seen
    "s3": 0.01,  # steady windows, thousands of samples each: 0.02 % seen
    "k_v": 0.08,  # a slope over 5–200 rad/s that friction ripple blurs: 3 % seen
    "static_factor": 0.04,  # a handful of breakaway events, each bracketed within 2 %: 2 % seen
    "R": 0.005,  # voltage pulses: u = R·i + K_b·(ω + δ·dω/dt), ≤ 0.05 % seen over 20 seeds (σ 0.04 %)
    "K_b": 0.005,
    "f_cl": 0.02,  # load-side spring torque at steady speeds: 0.1 % seen
    "b_l": 0.2,  # a small viscous term (0.05 N·m·s/rad at the output): 8 % seen
}


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> RunStore:
    store = RunStore(tmp_path_factory.mktemp("store"))
    runs = execute_plan(plan_run("campaign", experiments=EXPERIMENTS), load_rig_config("sim"), store)
    assert all(run.status == "complete" for run in runs)
    return store


@pytest.fixture(scope="module")
def campaign(store: RunStore) -> list[Run]:
    return [store.read(entry["id"]) for entry in store.list_runs()]


@pytest.fixture(scope="module")
def start() -> HarmonicDriveModel:
    wrong = {"s3": 0.06, "k_v": 3e-4, "K_s": 1300.0, "J_m": 4e-5, "J_l": 0.25, "R": 0.35, "f_cl": 0.2}
    return with_values(load_model("seed"), wrong | {"static_factor": 1.3, "K_b": 0.025, "b_l": 0.08})


@pytest.fixture(scope="module")
def fitted(campaign: list[Run], start: HarmonicDriveModel, tmp_path_factory: pytest.TempPathFactory):
    return identify(campaign, start, report_dir=tmp_path_factory.mktemp("report"))


@pytest.mark.parametrize("name", sorted(TOLERANCE))
def test_each_identifiable_parameter_is_recovered(fitted, name: str):
    truth = get_values(load_model("seed"), [name])[name]
    row = next(r for r in fitted.parameters if r.name == name)
    assert row.identifiable, f"{name}: {row.note}"
    assert row.estimate == pytest.approx(truth, rel=TOLERANCE[name])
    assert row.uncertainty is not None and row.uncertainty >= 0


def test_parameters_the_data_cannot_determine_are_flagged_not_returned_as_known(fitted, start):
    rows = {r.name: r for r in fitted.parameters}
    for name in ("v_c", "a0", "b_m"):
        assert not rows[name].identifiable and rows[name].note, name
        assert rows[name].uncertainty is None
        assert rows[name].estimate == get_values(start, [name])[name], "kept at its start value"


def test_the_fit_error_shrinks(fitted):
    assert math.isfinite(fitted.fit_error_before) and math.isfinite(fitted.fit_error_after)
    # From a start 15–30 % off, the trajectories must match at least ten times better after the fit.
    assert fitted.fit_error_after < fitted.fit_error_before / 10


def test_the_validation_report_sits_beside_the_articles_table(fitted):
    assert fitted.report_file is not None and fitted.report_file.exists()
    text = fitted.report_file.read_text()
    for scenario in ("Step input (1 rad)", "Sinusoidal input (0.5 Hz)", "Low-speed ramp", "Bode"):
        assert scenario in text
    rows = {r.scenario: r for r in fitted.validation.rows}
    step = rows["Step input (1 rad): settling time"]
    # The fitted model, played on the same rig, settles like the measurement: within 10 %.
    assert step.error_percent < 10
    assert all(Path(p).exists() for p in fitted.validation.plots)


def test_a_parameter_made_unidentifiable_on_purpose_is_flagged(campaign, start):
    # Without load-variation and speed-sweep runs nothing separates the load friction from s3.
    few = [r for r in campaign if r.meta["experiment"] in ("pulse", "step", "sine")]
    result = identify(few, start, joint=False)
    rows = {r.name: r for r in result.parameters}
    assert not rows["f_cl"].identifiable
    assert rows["f_cl"].estimate == get_values(start, ["f_cl"])["f_cl"]


def test_fit_command_writes_the_model_and_its_json(store: RunStore, tmp_path: Path):
    out = tmp_path / "fitted.json"
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "rig",
            "fit",
            "--data",
            "latest",
            "--model",
            "seed",
            "--out",
            str(out),
            "--json",
        ],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "HDRIG_HOME": str(store.home)},
    )
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert load_model(out).motor_friction.s3 == pytest.approx(report["parameters"]["s3"]["estimate"])
    for entry in report["parameters"].values():
        assert {"estimate", "uncertainty", "identifiable"} <= set(entry)
    assert {"before", "after", "metric"} <= set(report["fit_error"])


def test_fit_command_names_a_bad_run_reference(tmp_path: Path):
    result = subprocess.run(
        [sys.executable, "-m", "rig", "fit", "--data", "nosuch-run", "--model", "seed", "--out", "x.yaml"],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "HDRIG_HOME": str(tmp_path)},
    )
    assert result.returncode == 2
    assert result.stderr.count("\n") == 1 and "nosuch-run" in result.stderr
