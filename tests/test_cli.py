"""The `hdrig` command line as docs/INTERFACE.md gives it, run as a user runs it (a separate process)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from rig.store.runfile import read_run


def hdrig(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "rig", *args], capture_output=True, text=True, timeout=300, cwd=cwd
    )


def test_model_list_names_the_presets():
    result = hdrig("model", "list", "--json")
    assert result.returncode == 0, result.stderr
    names = {row["name"] for row in json.loads(result.stdout)}
    assert {"seed", "seed-rigid"} <= names


def test_model_show_json_is_itself_a_model_file(tmp_path: Path):
    first = hdrig("model", "show", "seed", "--json")
    assert first.returncode == 0, first.stderr
    model = json.loads(first.stdout)
    model["transmission"]["K_s"] = 1234.0
    path = tmp_path / "edited.json"
    path.write_text(json.dumps(model))
    second = hdrig("model", "show", str(path), "--json")
    assert second.returncode == 0, second.stderr
    assert json.loads(second.stdout) == model


def test_simulate_writes_the_run_format_at_the_requested_rate(tmp_path: Path):
    out = tmp_path / "sim.csv"
    result = hdrig(
        "simulate", "--model", "seed", "--input", "sine:amp=2,freq=0.5", "--duration", "1",
        "--dt", "1e-4", "--rate", "1000", "--out", str(out),
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert result.stdout == ""
    run = read_run(out)
    assert {"t", "u", "theta_m", "omega_m", "theta_l", "omega_l", "i_a"} <= set(run.columns)
    assert len(run) == 1000
    np.testing.assert_allclose(np.diff(run.t), 1e-3, rtol=1e-9)
    assert run.meta["source"] == "sim" and run.meta["model"]["name"] == "seed"


def test_simulate_replays_a_run_file(tmp_path: Path):
    original = tmp_path / "orig.parquet"
    replayed = tmp_path / "replay.csv"
    assert hdrig(
        "simulate", "--model", "seed", "--input", "pulse:amp=3,width=0.05,period=0.5", "--duration", "1",
        "--rate", "10000", "--out", str(original),
    ).returncode == 0  # fmt: skip
    result = hdrig("simulate", "--model", "seed", "--input-file", str(original), "--out", str(replayed))
    assert result.returncode == 0, result.stderr
    a, b = read_run(original), read_run(replayed)
    np.testing.assert_array_equal(a.t, b.t)
    # Same model, same inputs at the integration step: the replay retraces the run.
    np.testing.assert_allclose(b["theta_m"], a["theta_m"], atol=1e-9)


def test_voltage_sine_on_seed_is_physically_sensible(tmp_path: Path):
    out = tmp_path / "sine.parquet"
    result = hdrig(
        "simulate", "--model", "seed", "--input", "sine:amp=2,freq=0.5", "--duration", "4",
        "--rate", "10000", "--diagnostics", "--out", str(out),
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    run = read_run(out)
    moving = run["omega_m"] != 0
    # The motor breaks away once R·i = R·u/R exceeds R·(its static friction + r·the load's)/K_m:
    # 0.299 Ω · (0.072 · 1.0388 + 0.01 · 0.35) N·m / 0.0302 N·m/A ≈ 0.78 V, so it moves wherever
    # |2 V · sin(πt)| > 0.78 V: 1 − 2·asin(0.39)/π ≈ 74.5 % of the time, and a little longer while it
    # coasts to each stop. 70 % leaves room for the static level's position ripple (a few %).
    assert np.count_nonzero(moving) > 0.70 * len(moving)
    # The back-EMF bounds the speed: |ω_m| ≤ u_max / K_b = 2 V / 0.0302 V·s/rad ≈ 66 rad/s.
    assert 0 < np.max(np.abs(run["omega_m"])) <= 2.0 / 0.0302
    # Friction opposes motion wherever the motor moves, and the motor sticks near each reversal.
    assert np.all(np.sign(run["F_m"][moving]) == np.sign(run["omega_m"][moving]))
    assert np.count_nonzero(~moving) > 100


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["model", "show", "nosuch"], "nosuch: no such model file or preset"),
        (["simulate", "--model", "seed", "--input", "sine:amp=1", "--duration", "1", "--out", "x.csv"],
         "sine needs freq"),
        (["simulate", "--model", "seed", "--input", "step:amp=1", "--out", "x.csv"], "needs --duration"),
        (["simulate", "--model", "seed", "--input", "step:amp=1", "--duration", "1", "--rate", "3000",
          "--out", "x.csv"], "whole multiple of dt"),
        (["simulate", "--model", "seed", "--input-file", "absent.csv", "--out", "x.csv"], "absent.csv"),
        (["simulate", "--model", "seed", "--input", "step:amp=1", "--duration", "1", "--out", "x.txt"],
         "x.txt"),
    ],
)  # fmt: skip
def test_bad_input_exits_2_with_one_line(tmp_path: Path, args: list[str], says: str):
    result = hdrig(*args, cwd=tmp_path)
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("hdrig: error:") and says in lines[0], result.stderr


def test_replay_of_a_run_without_input_column_is_refused(tmp_path: Path):
    path = tmp_path / "no_input.csv"
    path.write_text("t,theta_m\n0,0\n0.001,0.1\n0.002,0.2\n")
    result = hdrig("simulate", "--model", "seed", "--input-file", str(path), "--out", str(tmp_path / "o.csv"))
    assert result.returncode == 2 and "needs one of u, i_cmd, tau_m" in result.stderr


def test_export_to_a_missing_folder_is_one_line_exit_2(tmp_path: Path):
    env = {**os.environ, "HDRIG_HOME": str(tmp_path / "home")}
    made = subprocess.run(
        [sys.executable, "-m", "rig", "run", "speed-sweep", "--rig", "sim", "--set", "speeds_rad_s=[20]",
         "--set", "hold_s=0.1", "--quiet", "--json"],
        capture_output=True, text=True, timeout=300, env=env,
    )  # fmt: skip
    assert made.returncode == 0, made.stderr
    run_id = json.loads(made.stdout)["id"]
    out = tmp_path / "no" / "such" / "dir" / "x.csv"
    result = subprocess.run(
        [sys.executable, "-m", "rig", "runs", "export", run_id, "--format", "csv", "--out", str(out)],
        capture_output=True, text=True, timeout=300, env=env,
    )  # fmt: skip
    assert result.returncode == 2
    (line,) = result.stderr.strip().splitlines()
    assert line.startswith("hdrig: error:") and "does not exist" in line, line
    assert "Traceback" not in result.stderr


@pytest.mark.parametrize(
    ("value", "says"),
    [("[1, 1]", "speeds must be distinct"), ("[1e6]", "less than or equal to 2000"), ("['0.5']", "number")],
)
def test_run_checks_the_whole_plan_before_anything_moves(tmp_path: Path, value: str, says: str):
    env = {**os.environ, "HDRIG_HOME": str(tmp_path / "home")}
    result = subprocess.run(
        [sys.executable, "-m", "rig", "run", "speed-sweep", "--rig", "sim", "--set", f"speeds_rad_s={value}"],
        capture_output=True, text=True, timeout=300, env=env,
    )  # fmt: skip
    assert result.returncode == 2, result.stderr
    (line,) = result.stderr.strip().splitlines()
    assert "speeds_rad_s" in line and says in line, line
    runs = tmp_path / "home" / "runs"
    assert not runs.exists() or not any(runs.iterdir()), "a refused run left a run behind"
