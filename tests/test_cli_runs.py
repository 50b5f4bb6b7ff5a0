"""`hdrig run` and `hdrig runs`, run as a user runs them (a separate process, the store in HDRIG_HOME).

The simulated rig `sim` (configs/rigs/sim.yaml) runs in virtual time with a fixed noise seed, so a run is
deterministic and takes well under a second of simulation; the crash test uses a realtime copy of it.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import scipy.io
import yaml

from rig.config import RIG_DIR
from rig.experiments import CAMPAIGN_ORDER
from rig.store.runfile import read_run
from rig.store.runs import RunStore

REPO_ROOT = Path(__file__).resolve().parents[1]
GEAR_RATIO = 0.01  # seed preset's r: output angle = r · θ_m
SIM_TRAVEL_MIN_OUT_RAD = -0.5  # configs/rigs/sim.yaml
# A load torque at the output the drive's 10 A cannot hold (10 A · K_m / r ≈ 30 N·m): it drives the arm
# backwards into the end of its travel within half a second (virtual time).
RUNAWAY_LOAD = "tau_ext_nm=50"


def hdrig(home: Path, *args: str, timeout_s: float = 300) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "HDRIG_HOME": str(home)}
    return subprocess.run(
        [sys.executable, "-m", "rig", *args],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        cwd=REPO_ROOT,
        env=env,
    )


def runs_json(home: Path) -> list[dict[str, Any]]:
    result = hdrig(home, "runs", "list", "--json")
    assert result.returncode == 0, result.stderr
    runs: list[dict[str, Any]] = json.loads(result.stdout)
    return runs


def one_error_line(result: subprocess.CompletedProcess[str]) -> str:
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    return lines[0]


@pytest.fixture(scope="module")
def swept(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, subprocess.CompletedProcess[str]]:
    """One speed sweep on `sim` with its defaults, in a store of its own."""
    home = tmp_path_factory.mktemp("home")
    return home, hdrig(home, "run", "speed-sweep", "--rig", "sim")


@pytest.fixture(scope="module")
def run_id(swept: tuple[Path, subprocess.CompletedProcess[str]]) -> str:
    home, result = swept
    assert result.returncode == 0, result.stderr
    (entry,) = runs_json(home)
    return str(entry["id"])


# ---- hdrig run ------------------------------------------------------------------------------------


def test_run_prints_one_line_with_id_status_metrics_and_results_folder(
    swept: tuple[Path, subprocess.CompletedProcess[str]], run_id: str
) -> None:
    home, result = swept
    (line,) = result.stdout.splitlines()
    artifacts = home / "runs" / run_id / "artifacts"
    assert line.startswith(f"{run_id}  speed-sweep  complete  ")
    assert "coulomb_pos_nm=" in line and line.endswith(f"results: {artifacts}")
    assert result.stderr == ""  # no terminal: no progress bar, and nothing went wrong
    assert {"friction_vs_velocity.csv", "results.json"} <= {p.name for p in artifacts.iterdir()}
    assert list((artifacts / "plots").glob("*.png"))


def test_runs_list_json_has_the_run_complete_with_samples(
    swept: tuple[Path, subprocess.CompletedProcess[str]], run_id: str
) -> None:
    home, _ = swept
    (entry,) = runs_json(home)
    assert {"id", "experiment", "status", "started", "samples"} <= set(entry)
    assert (entry["id"], entry["experiment"], entry["status"]) == (run_id, "speed-sweep", "complete")
    assert entry["samples"] > 0


def test_runs_list_table_has_a_row_per_run(
    swept: tuple[Path, subprocess.CompletedProcess[str]], run_id: str
) -> None:
    home, _ = swept
    result = hdrig(home, "runs", "list")
    assert result.returncode == 0, result.stderr
    header, row = result.stdout.splitlines()
    assert header.split() == ["id", "experiment", "status", "started", "(UTC)", "samples"]
    cells = row.split()
    assert cells[:3] == [run_id, "speed-sweep", "complete"] and int(cells[-1]) > 0


@pytest.mark.parametrize("fmt", ["csv", "parquet", "mat"])
def test_runs_export_reads_back_the_stored_samples(
    swept: tuple[Path, subprocess.CompletedProcess[str]], run_id: str, tmp_path: Path, fmt: str
) -> None:
    home, _ = swept
    stored = read_run(home / "runs" / run_id / "data.parquet")
    out = tmp_path / f"export.{fmt}"
    result = hdrig(home, "runs", "export", run_id, "--format", fmt, "--out", str(out))
    assert result.returncode == 0, result.stderr
    if fmt == "mat":
        mat = scipy.io.loadmat(out)
        columns = {name: mat[name].ravel() for name in ("t", "theta_m", "i_a")}
    else:
        run = read_run(out)
        assert run.meta["run_id"] == run_id and run.meta["experiment"] == "speed-sweep"
        columns = {name: run[name] for name in ("t", "theta_m", "i_a")}
    for name, values in columns.items():
        # Every format stores float64 exactly (CSV in shortest round-trip form): equal, not close.
        np.testing.assert_array_equal(values, stored[name], err_msg=name)


def test_runs_export_into_a_folder_names_the_file_after_the_run(
    swept: tuple[Path, subprocess.CompletedProcess[str]], run_id: str, tmp_path: Path
) -> None:
    home, _ = swept
    result = hdrig(home, "runs", "export", run_id, "--format", "parquet", "--out", str(tmp_path))
    assert result.returncode == 0, result.stderr
    assert len(read_run(tmp_path / f"{run_id}.parquet")) == runs_json(home)[0]["samples"]


def test_runs_show_json_has_entry_metrics_and_artifacts(
    swept: tuple[Path, subprocess.CompletedProcess[str]], run_id: str
) -> None:
    home, _ = swept
    result = hdrig(home, "runs", "show", run_id, "--json")
    assert result.returncode == 0, result.stderr
    shown = json.loads(result.stdout)
    assert (shown["id"], shown["status"], shown["rig"], shown["model_name"]) == (
        run_id,
        "complete",
        "sim",
        "seed",
    )
    assert shown["metrics"]["speeds"] == 9 and "coulomb_pos_nm" in shown["metrics"]
    names = {Path(p).name for p in shown["artifacts"]}
    assert {"friction_vs_velocity.csv", "results.json", "friction_vs_velocity.png"} <= names
    assert all(Path(p).is_file() for p in shown["artifacts"])


def test_runs_show_prints_status_metrics_and_artifacts(
    swept: tuple[Path, subprocess.CompletedProcess[str]], run_id: str
) -> None:
    home, _ = swept
    result = hdrig(home, "runs", "show", run_id)
    assert result.returncode == 0, result.stderr
    assert f"id          {run_id}" in result.stdout and "status      complete" in result.stdout
    assert "coulomb_pos_nm" in result.stdout and "results.json" in result.stdout


def test_run_json_is_one_object_and_set_reaches_the_parameters(tmp_path: Path) -> None:
    result = hdrig(tmp_path, "run", "speed-sweep", "--rig", "sim", "--set", "speeds_rad_s=[1, 10]", "--json")
    assert result.returncode == 0, result.stderr
    outcome = json.loads(result.stdout)  # the whole of stdout is the document
    assert (outcome["experiment"], outcome["status"], outcome["reason"]) == ("speed-sweep", "complete", None)
    assert outcome["metrics"]["speeds"] == 2
    (entry,) = runs_json(tmp_path)
    assert entry["id"] == outcome["id"] and entry["meta"] == {}  # a listing is a summary: no metadata
    shown = hdrig(tmp_path, "runs", "show", outcome["id"], "--json")
    assert json.loads(shown.stdout)["meta"]["params"]["speeds_rad_s"] == [1.0, 10.0]


def test_campaign_runs_every_experiment_in_order_with_dotted_set(tmp_path: Path) -> None:
    result = hdrig(
        tmp_path, "run", "campaign", "--rig", "configs/rigs/sim.yaml",
        "--set", "speed-sweep.speeds_rad_s=[2, 20]", "--json",
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    outcomes = json.loads(result.stdout)
    assert [o["experiment"] for o in outcomes] == list(CAMPAIGN_ORDER)
    assert all(o["status"] == "complete" for o in outcomes), outcomes
    assert [entry["id"] for entry in runs_json(tmp_path)] == [o["id"] for o in outcomes]  # oldest first
    sweep = next(o for o in outcomes if o["experiment"] == "speed-sweep")
    shown = json.loads(hdrig(tmp_path, "runs", "show", sweep["id"], "--json").stdout)
    assert shown["meta"]["params"]["speeds_rad_s"] == [2.0, 20.0]


# ---- bad input: one line, exit 2 ------------------------------------------------------------------


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["run", "nosuch", "--rig", "sim"], "unknown experiment 'nosuch'"),
        (["run", "speed-sweep", "--rig", "nosuch.yaml"], "nosuch.yaml: no such rig file"),
        (["run", "speed-sweep", "--rig", "sim", "--set", "hold_s"], "'hold_s' is not key=value"),
        (["run", "speed-sweep", "--rig", "sim", "--set", "hold=1"], "field 'hold'"),
        (["run", "speed-sweep", "--rig", "sim", "--set", "hold_s=-1"], "field 'hold_s'"),
        (["run", "campaign", "--rig", "sim", "--set", "hold_s=1"], "must be EXPERIMENT.key=value"),
        (["run", "campaign", "--rig", "sim", "--set", "nosuch.hold_s=1"], "must be EXPERIMENT.key=value"),
        (["run", "campaign", "--rig", "sim", "--set", "speed-sweep.hold=1"], "field 'hold'"),
        (["run", "speed-sweep"], "--rig"),
        (["runs", "show", "nosuch"], "unknown run id 'nosuch'"),
        (["runs", "export", "nosuch", "--format", "csv", "--out", "x.csv"], "unknown run id 'nosuch'"),
        (["runs", "export", "nosuch", "--format", "xls", "--out", "x.xls"], "invalid choice: 'xls'"),
    ],
)  # fmt: skip
def test_bad_input_exits_2_with_one_line(tmp_path: Path, args: list[str], says: str) -> None:
    result = hdrig(tmp_path, *args)
    assert result.returncode == 2, result.stderr
    line = one_error_line(result)
    assert line.startswith("hdrig: error:") and says in line, line
    assert result.stdout == ""
    runs = tmp_path / "runs"
    assert not runs.exists() or not any(runs.iterdir()), "a refused command left a run behind"


def test_export_suffix_other_than_the_format_exits_2(
    swept: tuple[Path, subprocess.CompletedProcess[str]], run_id: str, tmp_path: Path
) -> None:
    home, _ = swept
    result = hdrig(home, "runs", "export", run_id, "--format", "mat", "--out", str(tmp_path / "x.csv"))
    assert result.returncode == 2
    assert "does not match the export format 'mat'" in one_error_line(result)


def test_set_point_beyond_the_drive_saturation_exits_2_naming_it(tmp_path: Path) -> None:
    # 650 rad/s passes the experiment's own checks; the rig refuses it (600 rad/s) before that segment.
    result = hdrig(tmp_path, "run", "speed-sweep", "--rig", "sim", "--set", "speeds_rad_s=[650]")
    assert result.returncode == 2
    assert "velocity set-point 650 rad/s beyond the rig's 600 rad/s" in one_error_line(result)


# ---- a run the safety envelope aborts: exit 3, kept and readable ----------------------------------


def test_aborted_run_exits_3_and_is_kept_with_its_reason(tmp_path: Path) -> None:
    result = hdrig(tmp_path, "run", "speed-sweep", "--rig", "sim", "--set", RUNAWAY_LOAD)
    assert result.returncode == 3, result.stderr
    (entry,) = runs_json(tmp_path)
    assert entry["status"] == "aborted" and entry["samples"] > 0
    assert entry["reason"].startswith("aborted: travel limit: output angle"), entry["reason"]
    assert one_error_line(result) == f"hdrig: run {entry['id']} {entry['reason']}"
    (line,) = result.stdout.splitlines()
    assert line.startswith(f"{entry['id']}  speed-sweep  {entry['reason']}  {entry['samples']} samples")

    out = tmp_path / "aborted.parquet"
    assert (
        hdrig(tmp_path, "runs", "export", entry["id"], "--format", "parquet", "--out", str(out)).returncode
        == 0
    )
    run = read_run(out)
    assert len(run) == entry["samples"]
    output_angle = GEAR_RATIO * run["theta_m"]
    # The last sample recorded is the breach; every one before it was inside the travel.
    assert output_angle[-1] < SIM_TRAVEL_MIN_OUT_RAD <= output_angle[:-1].min()


def test_aborted_run_json_says_aborted_and_exits_3(tmp_path: Path) -> None:
    result = hdrig(tmp_path, "run", "speed-sweep", "--rig", "sim", "--set", RUNAWAY_LOAD, "--json")
    assert result.returncode == 3
    outcome = json.loads(result.stdout)
    assert outcome["status"] == "aborted" and outcome["reason"].startswith("aborted: travel limit")
    assert one_error_line(result) == f"hdrig: run {outcome['id']} {outcome['reason']}"


# ---- crash safety: a SIGKILLed run is listed interrupted, its data readable -----------------------


AS_FROM_A_TERMINAL = (
    "import runpy, signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler);"
    " sys.argv[0] = 'hdrig'; runpy.run_module('rig', run_name='__main__', alter_sys=True)"
)
"""`python -m rig` with Ctrl-C raising KeyboardInterrupt, as at a terminal. A runner that starts the tests
in the background without job control (`nohup make test &`) hands its children SIGINT ignored, and
Python then keeps it ignored: the Ctrl-C test's run went on to its end and exited 0 (seen twice, in
fresh-clone CI runs started so here)."""


def start_realtime_sweep(tmp_path: Path, *options: str, **popen: Any) -> tuple[subprocess.Popen[str], Path]:
    """`hdrig run speed-sweep` on a realtime copy of the sim rig (~18 s of wall time); (process, home)."""
    config = yaml.safe_load((RIG_DIR / "sim.yaml").read_text())
    config["pace"] = "realtime"
    rig_file = tmp_path / "realtime.yaml"
    rig_file.write_text(yaml.safe_dump(config))
    home = tmp_path / "home"
    child = subprocess.Popen(
        [sys.executable, "-c", AS_FROM_A_TERMINAL, "run", "speed-sweep", "--rig", str(rig_file), *options],
        env={**os.environ, "HDRIG_HOME": str(home)},
        cwd=REPO_ROOT,
        text=True,
        **popen,
    )
    return child, home


def wait_for_flushed_samples(child: subprocess.Popen[str], home: Path, samples: int = 1000) -> int:
    """Wait until `samples` are on disk (the writer flushes every second), no earlier than 2.5 s after
    the start; give up after 60 s (a loaded machine starts slowly). The samples flushed."""
    started = time.monotonic()
    flushed = 0
    while time.monotonic() - started < 60 and (flushed < samples or time.monotonic() - started < 2.5):
        time.sleep(0.1)
        if (home / "catalog.sqlite").exists():
            flushed = max((r["samples"] for r in RunStore(home).list_runs()), default=0)
    assert child.poll() is None, "the realtime run ended before it could be stopped"
    assert flushed >= samples, f"{samples} samples did not reach the store within 60 s"
    return flushed


def test_killed_run_is_listed_interrupted_with_its_samples(tmp_path: Path) -> None:
    child, home = start_realtime_sweep(tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        flushed = wait_for_flushed_samples(child, home)
        child.send_signal(signal.SIGKILL)
        child.wait(timeout=10)
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()

    (entry,) = runs_json(home)
    assert entry["status"] == "interrupted" and entry["samples"] >= flushed
    out = tmp_path / "killed.csv"
    result = hdrig(home, "runs", "export", entry["id"], "--format", "csv", "--out", str(out))
    assert result.returncode == 0, result.stderr
    run = read_run(out)
    assert len(run) == entry["samples"]
    assert np.all(np.diff(run.t) > 0)


# ---- Ctrl-C: the rig quick-stops, the run ends aborted with its data -------------------------------


def test_ctrl_c_quick_stops_and_leaves_the_run_aborted_with_its_data(tmp_path: Path) -> None:
    child, home = start_realtime_sweep(tmp_path, "-q", stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        flushed = wait_for_flushed_samples(child, home)
        child.send_signal(signal.SIGINT)
        _, stderr = child.communicate(timeout=60)
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()

    assert child.returncode == 130, stderr
    (entry,) = runs_json(home)
    assert entry["status"] == "aborted" and entry["reason"] == "aborted: Ctrl-C"
    assert entry["samples"] >= flushed and len(RunStore(home).read(entry["id"])) == entry["samples"]
    assert f"run {entry['id']} kept" in stderr
