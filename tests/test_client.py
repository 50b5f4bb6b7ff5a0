"""The Python client (`api.client`) and `hdrig --server URL` against a real `hdrig serve` on loopback.

The remote command line must print the documents the local one prints (same fields, same values where
the simulated rig is deterministic), keep its exit codes (2: bad input told by the service, 3: a run
aborted), and the client's `wait` must follow a run to its end. Every wait is a deadline.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from test_api_server import REPO, START_S, WAIT_S, Server, free_port, operator_key, wait_until

from api.client import HdrigClient, ServiceInputError, ServiceUnreachableError
from model.errors import UserInputError
from rig.core.documents import JobStatus, RunDocument
from rig.store.runfile import read_run

SHORT_SWEEP = "speeds_rad_s=[2,20]"
SIM = str(REPO / "configs/rigs/sim.yaml")


def hdrig(home: Path, *args: str, key: str | None = None) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, HDRIG_HOME=str(home))
    env.pop("HDRIG_KEY", None)
    if key is not None:
        env["HDRIG_KEY"] = key
    return subprocess.run(
        [sys.executable, "-m", "rig", *args],
        capture_output=True,
        text=True,
        env=env,
        cwd=REPO,
        timeout=WAIT_S,
    )


class Remote:
    """A service on the simulated rig (as fast as it goes), its store, an operator key."""

    def __init__(self, home: Path, rig: Path | str, log: Path) -> None:
        self.home = home
        self.key = operator_key(home)
        self.server = Server(home, Path(rig), log)
        self.url = self.server.base

    def cli(self, *args: str) -> subprocess.CompletedProcess[str]:
        return hdrig(self.home, "--server", self.url, *args, key=self.key)


@pytest.fixture(scope="module")
def remote(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Remote]:
    folder = tmp_path_factory.mktemp("remote")
    service = Remote(folder / "home", SIM, folder / "serve.log")
    yield service
    service.server.stop()


@pytest.fixture(scope="module")
def local_home(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("local") / "home"


def ok(result: subprocess.CompletedProcess[str]) -> str:
    assert result.returncode == 0, result.stderr
    return result.stdout


def same_fields(remote: dict[str, Any], local: dict[str, Any], where: str) -> None:
    assert set(remote) == set(local), f"{where}: {set(remote) ^ set(local)}"


def test_run_runs_and_export_print_the_same_documents_over_http(
    remote: Remote, local_home: Path, tmp_path: Path
) -> None:
    here = json.loads(
        ok(hdrig(local_home, "run", "speed-sweep", "--rig", SIM, "--set", SHORT_SWEEP, "--json"))
    )
    there = json.loads(ok(remote.cli("run", "speed-sweep", "--set", SHORT_SWEEP, "--json")))
    same_fields(there, here, "run --json")
    assert there["status"] == here["status"] == "complete"
    # The same seeded plant and program: the same samples and the same metrics, to the last digit.
    assert there["samples"] == here["samples"] and there["metrics"] == here["metrics"]
    assert there["owner"] == "tester" and here["owner"] is None  # the key's name, over HTTP

    (listed_here,) = json.loads(ok(hdrig(local_home, "runs", "list", "--json")))
    listed_there = json.loads(ok(remote.cli("runs", "list", "--json")))
    assert [r["id"] for r in listed_there][-1] == there["id"]
    same_fields(listed_there[-1], listed_here, "runs list --json")

    text_here = ok(hdrig(local_home, "runs", "list")).splitlines()
    text_there = ok(remote.cli("runs", "list")).splitlines()
    assert text_there[0] == text_here[0]  # the header
    assert text_there[-1].split()[1:3] == text_here[-1].split()[1:3] == ["speed-sweep", "complete"]

    shown_there = json.loads(ok(remote.cli("runs", "show", there["id"], "--json")))
    assert shown_there["artifacts"] and set(shown_there) == set(there)

    ok(
        hdrig(
            local_home, "runs", "export", here["id"], "--format", "csv", "--out", str(tmp_path / "here.csv")
        )
    )
    ok(remote.cli("runs", "export", there["id"], "--format", "csv", "--out", str(tmp_path / "there.csv")))
    a, b = read_run(tmp_path / "here.csv"), read_run(tmp_path / "there.csv")
    assert len(a) == len(b) == here["samples"]
    for name in a.columns:  # the exported file holds every recorded column, value for value
        assert (a.columns[name] == b.columns[name]).all(), name
    assert (tmp_path / "there.csv.json").is_file()  # the metadata beside the CSV, as locally


def test_fit_over_http_prints_the_fit_document_and_writes_the_model_here(
    remote: Remote, local_home: Path, tmp_path: Path
) -> None:
    runs_here = json.loads(ok(hdrig(local_home, "runs", "list", "--json")))
    runs_there = json.loads(ok(remote.cli("runs", "list", "--json")))
    assert runs_here and runs_there, "the test above records a run in each store"
    out_here, out_there = tmp_path / "here.yaml", tmp_path / "there.yaml"
    args = ["--model", "seed", "--json", "-q"]
    here = json.loads(ok(hdrig(local_home, "fit", "--data", "latest", "--out", str(out_here), *args)))
    there = json.loads(ok(remote.cli("fit", "--data", "latest", "--out", str(out_there), *args)))
    same_fields(there, here, "fit --json")
    assert set(there["parameters"]) == set(here["parameters"])
    same_fields(there["fit_error"], here["fit_error"], "fit_error")
    assert there["model_file"] == str(out_there) and out_there.is_file()  # downloaded, named as locally
    assert out_there.read_text() == out_here.read_text()  # the same runs, the same fit


def test_bad_input_over_http_is_one_line_and_exit_2(remote: Remote, tmp_path: Path) -> None:
    bad = remote.cli("run", "speed-sweep", "--set", "hold_s=-1")
    assert bad.returncode == 2 and bad.stdout == ""
    assert bad.stderr.count("\n") == 1 and "hold_s" in bad.stderr, bad.stderr
    unknown = remote.cli("runs", "show", "20990101-000000-nothing-0000")
    assert unknown.returncode == 2 and "unknown run" in unknown.stderr and unknown.stderr.count("\n") == 1
    a_file = remote.cli("fit", "--data", SIM, "--model", "seed", "--out", str(tmp_path / "m.yaml"))
    assert a_file.returncode == 2 and "file on this machine" in a_file.stderr
    no_key = hdrig(remote.home, "--server", remote.url, "runs", "list")
    assert no_key.returncode == 2 and "HDRIG_KEY" in no_key.stderr
    wrong_key = hdrig(remote.home, "--server", remote.url, "runs", "list", key="not-a-key")
    assert wrong_key.returncode == 2 and "unknown or revoked" in wrong_key.stderr
    nobody = f"http://127.0.0.1:{free_port()}"
    refused = hdrig(remote.home, "--server", nobody, "runs", "list", key="k")
    assert refused.returncode == 2 and refused.stderr.count("\n") == 1 and nobody in refused.stderr


def test_client_errors_are_problems_with_status_title_and_detail(remote: Remote) -> None:
    with HdrigClient(remote.url, remote.key) as client:
        with pytest.raises(ServiceInputError) as bad:
            client.start_run("speed-sweep", {"hold_s": -1})
        assert isinstance(bad.value, UserInputError)
        assert bad.value.status == 422 and bad.value.title == "Invalid input" and "hold_s" in bad.value.detail
        with pytest.raises(ServiceInputError) as missing:
            client.run("20990101-000000-nothing-0000")
        assert missing.value.status == 404
    with (
        HdrigClient(f"http://127.0.0.1:{free_port()}", "k") as nobody,
        pytest.raises(ServiceUnreachableError),
    ):
        nobody.health()


# ---- on a rig paced to the wall clock: runs that last long enough to act on -------------------------


@pytest.fixture
def live(tmp_path: Path) -> Iterator[Remote]:
    import yaml

    config = yaml.safe_load(Path(SIM).read_text())
    config.update(name="sim-realtime", pace="realtime")
    rig = tmp_path / "sim-realtime.yaml"
    rig.write_text(yaml.safe_dump(config))
    service = Remote(tmp_path / "home", rig, tmp_path / "serve.log")
    yield service
    service.server.stop()


def test_client_wait_follows_a_run_to_its_end_and_a_busy_rig_is_409(live: Remote) -> None:
    with HdrigClient(live.url, live.key) as client:
        started = client.start_run("speed-sweep", {"speeds_rad_s": [2.0, 5.0], "hold_s": 0.5})
        assert isinstance(started, RunDocument) and started.status in ("queued", "running")
        with pytest.raises(ServiceInputError) as busy:
            client.start_run("pulse")
        assert busy.value.status == 409 and busy.value.retry_after_s is not None
        kinds = [event.kind for event in client.events(started.id)]
        assert "samples" in kinds and kinds[-1] == "run"  # the stream ends with the run's final document
        done = client.wait(started.id, timeout_s=WAIT_S)
        assert isinstance(done, RunDocument) and done.status == "complete" and done.samples > 0
        assert done == client.run(started.id)
        path = client.download(done.id, "csv", columns=["omega_m"], t0=0.0, t1=1.0, out=live.home)
        assert path.read_text().split("\n", 1)[0] == "t,omega_m"
        fit = client.fit([done.id], "seed", timeout_s=WAIT_S)
        assert fit.status == JobStatus.COMPLETE and fit.result is not None and "parameters" in fit.result
        assert "model.yaml" in client.files("fits", fit.id)


def test_a_remote_run_aborted_exits_3_with_its_reason(live: Remote) -> None:
    env = dict(os.environ, HDRIG_KEY=live.key)
    child = subprocess.Popen(
        [sys.executable, "-m", "rig", "--server", live.url, "run", "speed-sweep", "--json", "-q"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        cwd=REPO,
    )
    try:
        with HdrigClient(live.url, live.key) as client:
            run_id = wait_until(
                "the remote run is recording",
                lambda: next((r.id for r in client.runs() if r.status == "running" and r.samples > 0), None),
                START_S,
            )
            client.abort(run_id)
        stdout, stderr = child.communicate(timeout=WAIT_S)
    finally:
        if child.poll() is None:
            child.kill()
    assert child.returncode == 3, stderr
    document = json.loads(stdout)
    assert document["id"] == run_id and document["status"] == "aborted" and document["samples"] > 0
    assert f"run {run_id} aborted" in stderr
