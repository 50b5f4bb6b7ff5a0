"""Files by name, not by path, over HTTP (issue 23 item 4): a client names models (presets, or uploaded
with `POST /api/v1/models`) and runs by id; the server never reads a file a request names, and never
says where its files are (run documents, job results, error messages)."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from model.params import load_model
from rig.config import load_rig_config
from rig.core import access
from rig.store.runs import RunStore

API = "/api/v1"


class Client:
    def __init__(self, client: TestClient, store: RunStore, keys: dict[str, str]) -> None:
        self.client, self.store, self.keys = client, store, keys

    def call(self, method: str, path: str, role: str = "operator", **kw: Any) -> Any:
        return self.client.request(method, path, headers={"Authorization": f"Bearer {self.keys[role]}"}, **kw)


@pytest.fixture
def api(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Client]:
    monkeypatch.delenv("HDRIG_CATALOG", raising=False)
    store = RunStore(tmp_path / "home")
    keys = {role: access.create_key(store, role, f"{role}-key") for role in ("viewer", "operator", "admin")}
    config = load_rig_config("configs/rigs/sim.yaml").model_copy(update={"pace": "virtual"})
    with TestClient(create_app(config, store)) as client:
        yield Client(client, store, keys)


def no_server_path(text: str, *paths: Path) -> None:
    for path in paths:
        assert str(path) not in text and str(path.resolve()) not in text, f"{path} in {text[:300]}"


def test_a_path_named_as_a_model_is_refused_without_reading_the_file(api: Client, tmp_path: Path) -> None:
    secret = tmp_path / "planted.yaml"
    secret.write_text('mechanics: {r: "FAKE-SECRET-5678"}\n')
    for model in (str(secret), str(api.store.home / "catalog.sqlite"), "/etc", "/no/such/file.yaml", "../x"):
        run = api.call("POST", f"{API}/runs", json={"experiment": "compensation", "params": {"model": model}})
        fit = api.call("POST", f"{API}/fits", json={"data": ["latest"], "model": model})
        for answer, field in ((run, "body.params.model"), (fit, "body.model")):
            assert answer.status_code == 422, answer.text
            assert "FAKE-SECRET" not in answer.text and "no such" not in answer.text
            assert answer.json()["errors"][0]["field"] == field
            assert "unknown model" in answer.json()["detail"]


def test_an_uploaded_model_is_named_by_runs_and_fits(api: Client) -> None:
    seed = api.call("GET", f"{API}/models/seed", role="viewer").json()
    seed["mechanics"]["J_m"] *= 1.1  # a lab's own unit: the preset with its own motor inertia
    made = api.call("POST", f"{API}/models", json={"name": "lab-unit-7", "model": seed})
    assert made.status_code == 201, made.text
    assert made.headers["location"] == f"{API}/models/lab-unit-7"
    assert api.call("POST", f"{API}/models", json={"name": "lab-unit-7", "model": seed}).status_code == 409
    assert api.call("POST", f"{API}/models", json={"name": "seed", "model": seed}).status_code == 409
    assert api.call("POST", f"{API}/models", json={"name": "../x", "model": seed}).status_code == 422
    as_viewer = api.call("POST", f"{API}/models", json={"name": "m", "model": seed}, role="viewer")
    assert as_viewer.status_code == 403
    bad = api.call("POST", f"{API}/models", json={"name": "broken", "model": {"mechanics": {"r": "x"}}})
    assert bad.status_code == 422 and bad.json()["errors"][0]["field"] == "body.model"
    assert "lab-unit-7" in [m["name"] for m in api.call("GET", f"{API}/models", role="viewer").json()]
    shown = api.call("GET", f"{API}/models/lab-unit-7", role="viewer")
    kept = api.store.model_file("lab-unit-7")
    assert kept is not None and shown.status_code == 200 and shown.json() == load_model(kept).to_dict()
    assert (kept.stat().st_mode & 0o077) == 0  # readable by the service only
    body = {"experiment": "compensation", "params": {"model": "lab-unit-7"}}
    run = api.call("POST", f"{API}/runs", json=body)
    assert run.status_code == 202, run.text
    no_server_path(run.text, api.store.home)
    assert api.call("GET", f"{API}/models/{api.store.home}/catalog.sqlite", role="viewer").status_code == 404


def test_run_documents_and_errors_carry_no_server_path(api: Client) -> None:
    started = api.call("POST", f"{API}/runs", json={"experiment": "pulse", "params": {}})
    assert started.status_code == 202, started.text
    run_id = started.json()["id"]
    done = ("complete", "aborted", "interrupted", "failed")
    while (doc := api.call("GET", f"{API}/runs/{run_id}", role="viewer").json())["status"] not in done:
        time.sleep(0.05)
    home = api.store.home
    for text in (
        json.dumps(doc),
        api.call("GET", f"{API}/runs", role="viewer").text,
        api.call("GET", f"{API}/runs/no-such-run", role="viewer").text,
        api.call("GET", f"{API}/runs/{run_id}/artifacts/nothing.png", role="viewer").text,
    ):
        no_server_path(text, home)
    assert doc["path"] and not doc["path"].startswith("/") and doc["run_dir"] == f"runs/{run_id}"
    assert all(not a.startswith("/") for a in doc["artifacts"])
