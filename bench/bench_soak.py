"""One store, many writers, for a minute (issue 23 item 2's target): the service (in process, its
routes through FastAPI's TestClient) making keys and queued pulse runs while 4 `hdrig` processes make
keys and pulse runs into the same store; at the end every key and run of every side must be found by a
fresh reader, and the catalog's integrity check must be ok. Prints the counts beside the target
(nothing lost). `--seconds S` (default 60).
"""

from __future__ import annotations

import argparse
import os
import sqlite3
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from fastapi.testclient import TestClient

from api.app import create_app
from rig.config import load_rig_config
from rig.core import access
from rig.store.runs import RunStore

API = "/api/v1"
REPO = Path(__file__).resolve().parents[1]
CLI_WORKER = """
import sys, time
from rig.cli import main
name, until = sys.argv[1], float(sys.argv[2])
n = 0
while time.time() < until:
    assert main(["keys", "create", "--role", "viewer", "--name", f"{name}-{n}"]) == 0
    if n % 3 == 0:
        assert main(["run", "pulse", "--rig", "sim"]) == 0
    n += 1
print(n)
"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seconds", type=float, default=60.0)
    args = parser.parse_args()
    home = Path(tempfile.mkdtemp(prefix="hdrig-soak-")) / "home"
    os.environ.pop("HDRIG_CATALOG", None)
    store = RunStore(home)
    admin = access.create_key(store, "admin", "soak-admin")
    operator = access.create_key(store, "operator", "soak-operator")
    until = time.time() + args.seconds
    env = dict(os.environ, HDRIG_HOME=str(home))
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", CLI_WORKER, f"cli{n}", str(until)],
            env=env,
            cwd=REPO,
            stdout=subprocess.PIPE,
            text=True,
        )
        for n in range(4)
    ]
    config = load_rig_config("configs/rigs/sim.yaml").model_copy(update={"pace": "virtual"})
    api_keys: list[str] = []
    api_runs: list[str] = []
    with TestClient(create_app(config, store)) as client:
        as_admin = {"Authorization": f"Bearer {admin}"}
        as_operator = {"Authorization": f"Bearer {operator}"}
        while time.time() < until:
            name = f"api-{len(api_keys)}"
            made_key = client.post(f"{API}/keys", json={"role": "viewer", "name": name}, headers=as_admin)
            assert made_key.status_code == 201, made_key.text
            api_keys.append(name)
            if len(api_keys) % 20 == 1 and len(api_runs) < 10:
                body = {"experiment": "pulse", "params": {}, "queue": True}
                started = client.post(f"{API}/runs", json=body, headers=as_operator)
                assert started.status_code == 202, started.text
                api_runs.append(started.json()["id"])
            time.sleep(0.05)
        made = {}
        for n, proc in enumerate(procs):
            out, _ = proc.communicate(timeout=600)
            assert proc.returncode == 0
            made[f"cli{n}"] = int(out.strip().splitlines()[-1])
        for run_id in api_runs:
            waiting = ("queued", "running")
            while client.get(f"{API}/runs/{run_id}", headers=as_operator).json()["status"] in waiting:
                time.sleep(0.1)
    reader = RunStore(home)
    keys = {k.name for k in access.list_keys(reader)}
    runs = {r["id"] for r in reader.list_runs()}
    cli_keys = {f"{name}-{k}" for name, count in made.items() for k in range(count)}
    cli_runs = sum((count + 2) // 3 for count in made.values())
    with sqlite3.connect(f"file:{home / 'catalog.sqlite'}?mode=ro", uri=True) as db:
        integrity = db.execute("PRAGMA integrity_check").fetchone()[0]
    lost_keys = (cli_keys | set(api_keys)) - keys
    print(
        f"{args.seconds:.0f} s: service made {len(api_keys)} keys, {len(api_runs)} runs; 4 CLIs made "
        f"{len(cli_keys)} keys, {cli_runs} runs"
    )
    print(
        f"found {len(keys)} keys, {len(runs)} runs; lost keys {len(lost_keys)} (target 0), runs missing "
        f"{len(api_runs) + cli_runs - len(runs)} (target 0); integrity_check {integrity}"
    )


if __name__ == "__main__":
    main()
