"""The service as users run it: `python -m rig serve` in its own process on a free loopback port.

Keys come from `hdrig keys create`; a run's event stream is closed early and the run goes on; a service
killed with SIGKILL mid-run leaves the run `interrupted` with its data up to the last flush, and the
restarted service shows it and starts nothing by itself. Every wait is a deadline loop.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
import yaml

from rig.status import RunStatus
from rig.store.runs import RunStore

API = "/api/v1"
START_S = 60.0  # the service answers health within this on a loaded machine (imports, rig open)
WAIT_S = 120.0
REPO = Path(__file__).resolve().parents[1]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


def hdrig(home: Path, *args: str) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, HDRIG_HOME=str(home))
    return subprocess.run(
        [sys.executable, "-m", "rig", *args], capture_output=True, text=True, env=env, cwd=REPO, timeout=120
    )


def wait_until(what: str, probe: Callable[[], Any], deadline_s: float = WAIT_S) -> Any:
    deadline = time.monotonic() + deadline_s
    while time.monotonic() < deadline:
        value = probe()
        if value:
            return value
        time.sleep(0.1)
    raise AssertionError(f"{what}: not within {deadline_s} s")


class Server:
    def __init__(self, home: Path, rig: Path, log: Path) -> None:
        self.port = free_port()
        self.base = f"http://127.0.0.1:{self.port}"
        env = dict(os.environ, HDRIG_HOME=str(home))
        self.log_path = log
        self.log = log.open("ab")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "rig", "serve", "--rig", str(rig), "--port", str(self.port)],
            env=env,
            cwd=REPO,
            stdout=self.log,
            stderr=self.log,
        )
        wait_until("GET /api/v1/health answers", self._healthy, START_S)

    def _healthy(self) -> bool:
        if self.proc.poll() is not None:
            said = self.log_path.read_text(errors="replace")[-2000:]
            raise AssertionError(f"the service exited with {self.proc.returncode}:\n{said}")
        try:
            return httpx.get(f"{self.base}{API}/health", timeout=2).status_code == 200
        except httpx.TransportError:
            return False

    def stop(self, sig: int = signal.SIGTERM) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        self.log.close()


@pytest.fixture
def home(tmp_path: Path) -> Path:
    return tmp_path / "home"


@pytest.fixture
def realtime_rig(tmp_path: Path) -> Path:
    """configs/rigs/sim.yaml paced to the wall clock: a default speed sweep lasts ~53 s."""
    config = yaml.safe_load((REPO / "configs/rigs/sim.yaml").read_text())
    config.update(name="sim-realtime", pace="realtime")
    path = tmp_path / "sim-realtime.yaml"
    path.write_text(yaml.safe_dump(config))
    return path


@pytest.fixture
def servers(tmp_path: Path) -> Iterator[list[Server]]:
    started: list[Server] = []
    yield started
    for server in started:
        server.stop(signal.SIGKILL)


def operator_key(home: Path) -> str:
    result = hdrig(home, "keys", "create", "--role", "operator", "--name", "tester")
    assert result.returncode == 0, result.stderr
    key = result.stdout.strip()
    assert key and len(key.split()) == 1  # stdout holds the key alone
    return key


def test_keys_cli_lists_and_revokes_without_showing_keys(home: Path) -> None:
    key = operator_key(home)
    listed = hdrig(home, "keys", "list", "--json")
    assert listed.returncode == 0 and key not in listed.stdout
    (entry,) = json.loads(listed.stdout)
    assert entry["name"] == "tester" and entry["role"] == "operator" and entry["revoked"] is None
    assert hdrig(home, "keys", "revoke", "tester").returncode == 0
    assert json.loads(hdrig(home, "keys", "list", "--json").stdout)[0]["revoked"]
    assert hdrig(home, "keys", "revoke", "nobody").returncode == 2


def test_a_store_without_keys_gets_an_admin_key_printed_once(
    home: Path, servers: list[Server], tmp_path: Path
) -> None:
    log = tmp_path / "serve.log"
    servers.append(Server(home, REPO / "configs/rigs/sim.yaml", log))
    text = log.read_text()
    key = next(line.strip() for line in text.splitlines() if line.startswith("    "))
    auth = {"Authorization": f"Bearer {key}"}
    assert httpx.get(f"{servers[0].base}{API}/keys", headers=auth).status_code == 200
    assert "http://127.0.0.1:" in text and "localhost" not in text  # where it listens, as the README says
    # The request log: a line for the request above, none for the health polls that waited for the start.
    wait_until("the request logged", lambda: '"GET /api/v1/keys HTTP/1.1" 200' in log.read_text(), 5)
    assert "GET /api/v1/health" not in log.read_text()


def test_served_over_tcp_contract_shapes_and_closing_the_stream_early_keeps_the_run(
    home: Path, realtime_rig: Path, servers: list[Server], tmp_path: Path
) -> None:
    key = operator_key(home)
    server = Server(home, realtime_rig, tmp_path / "serve.log")
    servers.append(server)
    auth = {"Authorization": f"Bearer {key}"}
    with httpx.Client(base_url=server.base, headers=auth, timeout=30) as client:
        assert httpx.get(f"{server.base}{API}/runs").status_code == 401
        assert client.get(f"{API}/rig").json()["mode"] == "sim"
        assert client.get("/openapi.json").status_code == 200
        bad = client.post(f"{API}/runs", json={"experiment": "speed-sweep", "params": {"hold_s": -1}})
        assert bad.status_code == 422 and bad.headers["content-type"].startswith("application/problem+json")
        started = client.post(
            f"{API}/runs", json={"experiment": "speed-sweep", "params": {"speeds_rad_s": [2.0, 5.0]}}
        )
        assert started.status_code == 202 and started.headers["location"].endswith(started.json()["id"])
        run_id = started.json()["id"]
        seen: list[str] = []
        with client.stream("GET", f"{API}/runs/{run_id}/events") as stream:
            assert stream.headers["content-type"].startswith("text/event-stream")
            for line in stream.iter_lines():
                if line.startswith("event: samples"):
                    seen.append(line)
                    if len(seen) >= 3:
                        break  # the client goes away mid-run
        running = client.get(f"{API}/runs/{run_id}").json()
        assert running["status"] == "running"
        done = wait_until(
            "the run ends",
            lambda: (
                (d := client.get(f"{API}/runs/{run_id}").json())["status"] not in ("queued", "running") and d
            ),
        )
        assert done["status"] == "complete"
        csv = client.get(f"{API}/runs/{run_id}/data", params={"format": "csv", "columns": "theta_m"})
        assert csv.status_code == 200 and csv.text.split("\n", 1)[0] == "t,theta_m"
        assert client.post(f"{API}/rig/stop").status_code == 202


def test_a_service_killed_mid_run_leaves_it_interrupted_with_its_data_and_starts_nothing_again(
    home: Path, realtime_rig: Path, servers: list[Server], tmp_path: Path
) -> None:
    key = operator_key(home)
    auth = {"Authorization": f"Bearer {key}"}
    first = Server(home, realtime_rig, tmp_path / "serve-1.log")
    servers.append(first)
    with httpx.Client(base_url=first.base, headers=auth, timeout=30) as client:
        run_id = client.post(f"{API}/runs", json={"experiment": "speed-sweep"}).json()["id"]
        wait_until(
            "1000 samples flushed", lambda: client.get(f"{API}/runs/{run_id}").json()["samples"] >= 1000
        )
    first.proc.send_signal(signal.SIGKILL)
    first.proc.wait(30)

    second = Server(home, realtime_rig, tmp_path / "serve-2.log")
    servers.append(second)
    with httpx.Client(base_url=second.base, headers=auth, timeout=30) as client:
        (run,) = client.get(f"{API}/runs").json()
        assert run["id"] == run_id and run["status"] == "interrupted" and run["samples"] >= 1000
        data = client.get(f"{API}/runs/{run_id}/data", params={"format": "csv"})
        assert data.status_code == 200
        assert len(data.text.strip().split("\n")) - 1 == run["samples"]
        rig = client.get(f"{API}/rig").json()
        assert rig["state"] == "idle" and rig["current_run"] is None and rig["queued"] == []
        assert client.get(f"{API}/jobs").json() == []
        time.sleep(0.5)  # give a wrongly restarted run time to show itself in the catalog
        assert [r["id"] for r in client.get(f"{API}/runs").json()] == [run_id]


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGHUP])
def test_a_service_told_to_stop_mid_run_quick_stops_and_ends_the_run_aborted_with_its_data(
    home: Path, realtime_rig: Path, servers: list[Server], tmp_path: Path, signum: signal.Signals
) -> None:
    key = operator_key(home)
    server = Server(home, realtime_rig, tmp_path / "serve.log")
    servers.append(server)
    with httpx.Client(base_url=server.base, headers={"Authorization": f"Bearer {key}"}, timeout=30) as client:
        run_id = client.post(f"{API}/runs", json={"experiment": "speed-sweep"}).json()["id"]
        wait_until(
            "1000 samples flushed", lambda: client.get(f"{API}/runs/{run_id}").json()["samples"] >= 1000
        )
    server.proc.send_signal(signum)
    server.proc.wait(WAIT_S)  # a graceful shutdown: the worker quick-stops, then the run is sealed
    (entry,) = RunStore(home).list_runs()
    assert entry["id"] == run_id and entry["status"] == RunStatus.ABORTED, entry
    assert entry["reason"].startswith("aborted: quick stop") and entry["samples"] >= 1000
    assert len(RunStore(home).read(run_id)) == entry["samples"]
