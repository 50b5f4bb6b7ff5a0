"""Runs carry their rig, gear unit, operator and free tags, and are found by them: the command line
(`hdrig run --unit --tag`, `hdrig runs list --unit --rig --tag --operator`) and REST (`GET /runs?unit=`)."""

from __future__ import annotations

import getpass
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from model.errors import UserInputError
from rig import cli
from rig.config import load_rig_config
from rig.core import access
from rig.store.runs import RunStore

REPO_ROOT = Path(__file__).resolve().parents[1]
SHORT = ["--set", "speeds_rad_s=[5,20]", "--set", "hold_s=0.3"]
WAIT_S = 120.0  # a short sweep on a loaded 2-core machine; a deadline, not a retry


def hdrig(home: Path, *args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "HDRIG_HOME": str(home)}
    env.pop("HDRIG_CATALOG", None)
    env.pop("HDRIG_DATA", None)
    return subprocess.run(
        [sys.executable, "-m", "rig", *args],
        capture_output=True,
        text=True,
        cwd=REPO_ROOT,
        env=env,
        timeout=300,
    )


def listed(home: Path, capsys: pytest.CaptureFixture[str], *filters: str) -> list[dict[str, object]]:
    """`hdrig runs list --json FILTERS`, in this process (a process per listing would cost seconds)."""
    capsys.readouterr()
    assert cli.main(["runs", "list", "--json", *filters]) == 0
    runs: list[dict[str, object]] = json.loads(capsys.readouterr().out)
    return runs


def test_runs_are_found_by_unit_rig_tag_and_operator_from_the_command_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    home = tmp_path / "home"
    args = ["--unit", "HD25-0001", "--tag", "line=3", "--tag", "batch:7", "-q", "--json"]
    result = hdrig(home, "run", "speed-sweep", "--rig", "sim", *SHORT, *args)
    assert result.returncode == 0, result.stderr
    document = json.loads(result.stdout)
    assert (document["unit"], document["tags"], document["rig"]) == (
        "HD25-0001",
        ["batch:7", "line=3"],
        "sim",
    )
    store = RunStore(home)  # two more runs as another bench's would land: the same catalog fields
    for unit, tags, rig in (("HD25-0002", ["line=3"], "sim"), ("HD32-0001", [], "bench-2")):
        with store.open_run("pulse", rig, None, None, ["t"], {}, unit=unit, tags=tags) as writer:
            writer.append({"t": [0.0, 0.001]})
    monkeypatch.setenv("HDRIG_HOME", str(home))
    for name in ("HDRIG_CATALOG", "HDRIG_DATA"):
        monkeypatch.delenv(name, raising=False)
    everyone = listed(home, capsys)
    assert {r["operator"] for r in everyone} == {getpass.getuser()}  # the OS user of the command line
    assert [r["unit"] for r in listed(home, capsys, "--unit", "HD25-*")] == ["HD25-0001", "HD25-0002"]
    assert [r["unit"] for r in listed(home, capsys, "--unit", "HD32-0001")] == ["HD32-0001"]
    assert [r["unit"] for r in listed(home, capsys, "--tag", "line=3")] == ["HD25-0001", "HD25-0002"]
    assert [r["unit"] for r in listed(home, capsys, "--tag", "line=3", "--tag", "batch:7")] == ["HD25-0001"]
    assert [r["unit"] for r in listed(home, capsys, "--rig", "bench-*")] == ["HD32-0001"]
    assert listed(home, capsys, "--operator", "someone-else") == []
    # a glob's other characters are literal: `_` and `%` match only themselves
    assert listed(home, capsys, "--unit", "HD25_*") == [] and listed(home, capsys, "--unit", "%") == []


def test_a_bad_tag_is_one_line_before_anything_runs(tmp_path: Path) -> None:
    result = hdrig(tmp_path / "home", "run", "speed-sweep", "--rig", "sim", "--tag", "two words", "-q")
    assert result.returncode == 2 and result.stderr.count("\n") == 1 and "tag 'two words'" in result.stderr
    with pytest.raises(UserInputError, match="tag ''"):
        RunStore(tmp_path / "other").open_run("pulse", "sim", None, None, ["t"], {}, tags=[""])


def test_runs_started_over_rest_carry_the_keys_name_and_are_searched_by_query(tmp_path: Path) -> None:
    store = RunStore(tmp_path / "home")
    token = access.create_key(store, "operator", "alice")
    auth = {"Authorization": f"Bearer {token}"}
    config = load_rig_config("configs/rigs/sim.yaml")
    with TestClient(create_app(config, store)) as client:
        for unit, tags in (("HD25-0007", ["shift=night"]), ("HD25-0008", [])):
            body = {
                "experiment": "speed-sweep",
                "params": {"speeds_rad_s": [5.0, 20.0], "hold_s": 0.3},
                "unit": unit,
                "tags": tags,
                "queue": True,
            }
            started = client.post("/api/v1/runs", json=body, headers=auth)
            assert started.status_code == 202, started.text
            run_id = started.json()["id"]
            deadline = time.monotonic() + WAIT_S
            while client.get(f"/api/v1/runs/{run_id}", headers=auth).json()["status"] in (
                "queued",
                "running",
            ):
                assert time.monotonic() < deadline, f"run {run_id} did not end within {WAIT_S} s"
                time.sleep(0.05)
        found = client.get("/api/v1/runs", params={"unit": "HD25-*"}, headers=auth).json()
        assert [(r["unit"], r["operator"]) for r in found] == [("HD25-0007", "alice"), ("HD25-0008", "alice")]
        night = client.get(
            "/api/v1/runs", params={"tag": "shift=night", "rig": config.name}, headers=auth
        ).json()
        assert [(r["unit"], r["tags"]) for r in night] == [("HD25-0007", ["shift=night"])]
        assert client.get("/api/v1/runs", params={"operator": "bob"}, headers=auth).json() == []
        bad = client.post("/api/v1/runs", json={"experiment": "pulse", "tags": ["a b"]}, headers=auth)
        assert bad.status_code == 422 and "tag 'a b'" in bad.json()["detail"]
