"""One catalog, whoever writes: the service and command lines on one store never end up on two catalogs.

Issue 23 item 2: one request naming `<HDRIG_HOME>/catalog.sqlite` as a model made the service open() and
close() the catalog's file; POSIX then dropped every SQLite lock the service held on it, the next
`hdrig keys create` believed itself the catalog's last user and deleted the service's WAL and SHM, and
from then on the two wrote to different catalogs (a key made by one unknown to the other, one lost at
shutdown). The process holding a catalog now refuses to open its files as anything but the catalog.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from model.errors import UserInputError
from model.params import load_model
from rig.config import load_rig_config
from rig.core import access
from rig.store.catalog import OwnFileError, refuse_own_file
from rig.store.runs import RunStore

API = "/api/v1"
REPO = Path(__file__).resolve().parents[1]
CLI_TIMEOUT_S = 300.0  # a command line's imports and a pulse run on a machine shared by many test jobs


def hdrig(home: Path, *args: str) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, HDRIG_HOME=str(home))
    env.pop("HDRIG_CATALOG", None)
    return subprocess.run(
        [sys.executable, "-m", "rig", *args],
        capture_output=True,
        text=True,
        env=env,
        cwd=REPO,
        timeout=CLI_TIMEOUT_S,
    )


def catalog_descriptors() -> list[str]:
    """What this process's open descriptors on catalog files point to (`... (deleted)` once unlinked)."""
    found = []
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:  # the descriptor listdir itself used, closed since
            continue
        if "catalog.sqlite" in target:
            found.append(target)
    return found


def cli_keys(home: Path) -> set[str]:
    listed = hdrig(home, "keys", "list", "--json")
    assert listed.returncode == 0, listed.stderr
    return {key["name"] for key in json.loads(listed.stdout)}


@pytest.fixture
def home(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.delenv("HDRIG_CATALOG", raising=False)
    return tmp_path / "home"


def test_reading_the_catalog_as_a_model_leaves_one_catalog_for_service_and_cli(home: Path) -> None:
    store = RunStore(home)
    access.create_key(store, "admin", "service-admin")
    with pytest.raises(UserInputError):  # the 422 path of the service: the catalog named as a model file
        load_model(str(home / "catalog.sqlite"))

    made = hdrig(home, "keys", "create", "--role", "viewer", "--name", "from-cli")
    assert made.returncode == 0, made.stderr
    # The service's WAL and SHM are still the ones on disk: the command line did not delete them.
    assert catalog_descriptors() and not [d for d in catalog_descriptors() if d.endswith("(deleted)")]
    assert {"service-admin", "from-cli"} <= {k.name for k in access.list_keys(store)}
    access.create_key(store, "operator", "from-service")
    assert {"service-admin", "from-cli", "from-service"} <= cli_keys(home)
    # ...and the key the command line made authenticates here.
    assert access.authenticate(store, made.stdout.strip()) == ("from-cli", access.Role.VIEWER)


def test_every_spelling_of_the_catalogs_files_is_refused_before_it_is_opened(home: Path) -> None:
    store = RunStore(home)
    access.create_key(store, "admin")
    link = home.parent / "innocent.yaml"
    link.symlink_to(home / "catalog.sqlite")
    hard = home.parent / "also-innocent.yaml"
    os.link(home / "catalog.sqlite", hard)
    spellings = (home / "catalog.sqlite", home / "catalog.sqlite-wal", home / "runs/../catalog.sqlite")
    for path in (*spellings, link, hard):
        with pytest.raises(OwnFileError, match="a file of the run catalog"):
            open(path, "rb").close()  # the open itself is refused
        with pytest.raises(OwnFileError):
            refuse_own_file(path, "run file")
    assert not [d for d in catalog_descriptors() if d.endswith("(deleted)")]
    other = home.parent / "model.yaml"
    other.write_text("not a catalog")
    with open(other) as f:  # any other file opens as before
        assert f.read() == "not a catalog"


# ---- soak: the service and four command lines write keys and runs into one store at once ------------

CLI_WORKER = """
import sys
from rig.cli import main
name, keys, runs = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
for n in range(max(keys, runs)):
    if n < keys:
        assert main(["keys", "create", "--role", "viewer", "--name", f"{name}-{n}"]) == 0
    if n < runs:
        assert main(["run", "pulse", "--rig", "sim"]) == 0
"""


def soak(home: Path, clis: int, keys_each: int, runs_each: int, api_keys: int) -> dict[str, Any]:
    """The service (in process) making `api_keys` keys and a run between them while `clis` command-line
    processes each make `keys_each` keys and `runs_each` runs; what each side made and what is found."""
    store = RunStore(home)
    admin = access.create_key(store, "admin", "soak-admin")
    operator = access.create_key(store, "operator", "soak-operator")
    env = dict(os.environ, HDRIG_HOME=str(home))
    env.pop("HDRIG_CATALOG", None)
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", CLI_WORKER, f"cli{n}", str(keys_each), str(runs_each)],
            env=env,
            cwd=REPO,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        for n in range(clis)
    ]
    config = load_rig_config("configs/rigs/sim.yaml").model_copy(update={"pace": "virtual"})
    api_made: list[str] = []
    api_runs: list[str] = []
    with TestClient(create_app(config, store)) as client:
        admin_h = {"Authorization": f"Bearer {admin}"}
        op_h = {"Authorization": f"Bearer {operator}"}
        for n in range(api_keys):
            made = client.post(f"{API}/keys", json={"role": "viewer", "name": f"api-{n}"}, headers=admin_h)
            assert made.status_code == 201, made.text
            api_made.append(f"api-{n}")
            if n % 5 == 0:
                started = client.post(
                    f"{API}/runs", json={"experiment": "pulse", "params": {}, "queue": True}, headers=op_h
                )
                assert started.status_code == 202, started.text
                api_runs.append(started.json()["id"])
        for proc in procs:
            _, err = proc.communicate(timeout=CLI_TIMEOUT_S * max(1, runs_each))
            assert proc.returncode == 0, err[-2000:]
        for run_id in api_runs:
            done = threading.Event()
            while not done.is_set():
                status = client.get(f"{API}/runs/{run_id}", headers=op_h).json()["status"]
                if status not in ("queued", "running"):
                    done.set()
                else:
                    done.wait(0.1)
    # The service has shut down cleanly: what each side made must be in the catalog, for a fresh reader.
    cli_made = {f"cli{n}-{k}" for n in range(clis) for k in range(keys_each)}
    return {
        "keys": cli_keys(home),
        "expected_keys": cli_made | set(api_made) | {"soak-admin", "soak-operator"},
        "runs": [r["id"] for r in RunStore(home).list_runs()],
        "api_runs": api_runs,
        "cli_runs": clis * runs_each,
        "integrity": sqlite_integrity(home),
    }


def sqlite_integrity(home: Path) -> str:
    import sqlite3

    with sqlite3.connect(f"file:{home / 'catalog.sqlite'}?mode=ro", uri=True) as db:
        return str(db.execute("PRAGMA integrity_check").fetchone()[0])


def test_service_and_four_command_lines_lose_no_key_and_no_run(home: Path) -> None:
    # Counts, not a duration: bench/bench_soak.py runs the same for a minute.
    found = soak(home, clis=4, keys_each=4, runs_each=1, api_keys=10)
    assert found["expected_keys"] <= found["keys"], found["expected_keys"] - found["keys"]
    assert set(found["api_runs"]) <= set(found["runs"])
    assert len(found["runs"]) == len(found["api_runs"]) + found["cli_runs"]
    assert found["integrity"] == "ok"
