"""The REST service in process (FastAPI's TestClient, lifespan on): auth and roles, runs started, queued,
aborted and downloaded over HTTP, problem+json errors, events, fits, CSRF.

The rig is the simulated one of configs/rigs/sim.yaml in a scratch store. Where a run must still be
moving when the test acts on it, the rig is paced to the wall clock; every wait is a deadline loop.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from api.app import create_app, iter_routes
from rig.config import RigConfig, load_rig_config
from rig.core import access, actions
from rig.core.documents import JobKind
from rig.store.runs import RunStore

API = "/api/v1"
WAIT_S = 120.0  # upper bound for a short simulated run on a loaded 2-core machine; never reached when well
SHORT_SWEEP = {"speeds_rad_s": [2.0, 20.0]}
PROBLEM = "application/problem+json"

PUBLIC = "public"
ROLE_OF_ROUTE: dict[tuple[str, str], str] = {
    ("GET", "/"): PUBLIC,
    ("GET", "/openapi.json"): PUBLIC,
    ("GET", "/docs"): PUBLIC,
    ("GET", "/docs/oauth2-redirect"): PUBLIC,
    ("GET", "/redoc"): PUBLIC,
    ("GET", f"{API}/health"): PUBLIC,
    ("POST", f"{API}/session"): PUBLIC,  # the login: it takes the key in its body
    ("GET", f"{API}/session"): "viewer",
    ("DELETE", f"{API}/session"): "viewer",
    ("GET", f"{API}/rig"): "viewer",
    ("POST", f"{API}/rig/stop"): "operator",
    ("POST", f"{API}/rig/reset"): "operator",
    ("GET", f"{API}/experiments"): "viewer",
    ("GET", f"{API}/models"): "viewer",
    ("GET", f"{API}/models/{{name}}"): "viewer",
    ("POST", f"{API}/models"): "operator",
    ("POST", f"{API}/runs"): "operator",
    ("GET", f"{API}/runs"): "viewer",
    ("GET", f"{API}/runs/{{run_id}}"): "viewer",
    ("POST", f"{API}/runs/{{run_id}}/abort"): "operator",
    ("GET", f"{API}/runs/{{run_id}}/data"): "viewer",
    ("GET", f"{API}/runs/{{run_id}}/artifacts"): "viewer",
    ("GET", f"{API}/runs/{{run_id}}/artifacts/{{path:path}}"): "viewer",
    ("GET", f"{API}/runs/{{run_id}}/events"): "viewer",
    ("GET", f"{API}/jobs"): "viewer",
    ("GET", f"{API}/jobs/{{job_id}}"): "viewer",
    ("POST", f"{API}/fits"): "operator",
    ("GET", f"{API}/fits/{{job_id}}"): "viewer",
    ("GET", f"{API}/fits/{{job_id}}/files"): "viewer",
    ("GET", f"{API}/fits/{{job_id}}/files/{{path:path}}"): "viewer",
    ("POST", f"{API}/gaps"): "operator",
    ("GET", f"{API}/gaps/{{job_id}}"): "viewer",
    ("GET", f"{API}/gaps/{{job_id}}/files"): "viewer",
    ("GET", f"{API}/gaps/{{job_id}}/files/{{path:path}}"): "viewer",
    ("GET", f"{API}/keys"): "admin",
    ("POST", f"{API}/keys"): "admin",
    ("DELETE", f"{API}/keys/{{name}}"): "admin",
    ("GET", f"{API}/audit"): "admin",
}
"""The least role each route needs (`public`: none). A route missing here fails the role-matrix test."""
RANK = {"none": 0, "viewer": 1, "operator": 2, "admin": 3}


def sim(pace: str = "virtual") -> RigConfig:
    return load_rig_config("configs/rigs/sim.yaml").model_copy(update={"pace": pace})


class Service:
    """A TestClient on a fresh store with one key of each role."""

    def __init__(self, client: TestClient, store: RunStore, keys: dict[str, str]) -> None:
        self.client, self.store, self.keys = client, store, keys

    def headers(self, role: str = "operator") -> dict[str, str]:
        return {"Authorization": f"Bearer {self.keys[role]}"} if role in self.keys else {}

    def get(self, path: str, role: str = "viewer", **kw: Any) -> Any:
        return self.client.get(path, headers={**self.headers(role), **kw.pop("headers", {})}, **kw)

    def post(self, path: str, body: Any = None, role: str = "operator", **kw: Any) -> Any:
        return self.client.post(
            path, json=body, headers={**self.headers(role), **kw.pop("headers", {})}, **kw
        )

    def start(self, experiment: str = "speed-sweep", params: dict[str, Any] | None = None, **kw: Any) -> Any:
        return self.post(f"{API}/runs", {"experiment": experiment, "params": params or {}, **kw})

    def wait_run(self, run_id: str, done: Callable[[dict[str, Any]], bool] | None = None) -> dict[str, Any]:
        done = done or (lambda d: d["status"] not in ("queued", "running"))
        deadline = time.monotonic() + WAIT_S
        while time.monotonic() < deadline:
            document: dict[str, Any] = self.get(f"{API}/runs/{run_id}").json()
            if done(document):
                return document
            time.sleep(0.05)
        raise AssertionError(f"run {run_id} did not get there within {WAIT_S} s: {document}")

    def wait_job(self, path: str) -> dict[str, Any]:
        deadline = time.monotonic() + WAIT_S * 3
        while time.monotonic() < deadline:
            document: dict[str, Any] = self.get(path).json()
            if document["status"] not in ("queued", "running"):
                return document
            time.sleep(0.1)
        raise AssertionError(f"{path} did not finish: {document}")


def _service(tmp_path: Path, config: RigConfig) -> Iterator[Service]:
    store = RunStore(tmp_path / "home")
    keys = {role: access.create_key(store, role, f"{role}-key") for role in ("viewer", "operator", "admin")}
    with TestClient(create_app(config, store)) as client:
        yield Service(client, store, keys)


@pytest.fixture
def service(tmp_path: Path) -> Iterator[Service]:
    yield from _service(tmp_path, sim())


@pytest.fixture
def live(tmp_path: Path) -> Iterator[Service]:
    """Paced to the wall clock: a default speed sweep lasts ~18 s."""
    yield from _service(tmp_path, sim("realtime"))


def assert_problem(response: Any, status: int) -> dict[str, Any]:
    assert response.status_code == status, response.text
    assert response.headers["content-type"].startswith(PROBLEM)
    body: dict[str, Any] = response.json()
    assert body["status"] == status and body["title"] and body["detail"] and body["type"]
    return body


# ---- auth ---------------------------------------------------------------------------------------


def test_health_needs_no_key(service: Service) -> None:
    response = service.client.get(f"{API}/health")
    assert response.status_code == 200 and response.json() == {"status": "ok"}


def test_no_key_is_401_problem_and_a_wrong_key_too(service: Service) -> None:
    body = assert_problem(service.client.get(f"{API}/runs"), 401)
    assert "Bearer" in body["detail"]
    assert_problem(service.client.get(f"{API}/runs", headers={"Authorization": "Bearer nope"}), 401)


def test_every_route_enforces_its_role(service: Service) -> None:
    """Walks app.routes: a route added without a row in ROLE_OF_ROUTE fails here."""
    routes = sorted(set(iter_routes(service.client.app)))  # type: ignore[arg-type]
    missing = [route for route in routes if route not in ROLE_OF_ROUTE]
    assert not missing, f"routes without a role in the table: {missing}"
    for method, path in routes:
        needed = ROLE_OF_ROUTE[(method, path)]
        url = path.replace("{run_id}", "no-such-run").replace("{job_id}", "no-such-job")
        url = url.replace("{path:path}", "x.csv").replace("{name}", "no-such-key")
        for role in ("none", "viewer", "operator", "admin"):
            # Bodies that fail validation: an allowed caller gets 422 (or 404), never the action itself.
            response = service.client.request(method, url, headers=service.headers(role), json={"bad": 1})
            code = response.status_code
            where = f"{method} {path} as {role}: {code}"
            if needed == PUBLIC:
                assert code not in (401, 403), where
            elif role == "none":
                assert code == 401, where
            elif RANK[role] < RANK[needed]:
                assert code == 403, where
            else:
                assert code not in (401, 403) and code < 500, where


def test_admin_manages_keys_and_a_revoked_key_is_refused(service: Service) -> None:
    created = service.post(f"{API}/keys", {"role": "viewer", "name": "guest"}, role="admin")
    assert created.status_code == 201
    token = created.json()["key"]
    assert service.client.get(f"{API}/runs", headers={"Authorization": f"Bearer {token}"}).status_code == 200
    listed = service.get(f"{API}/keys", role="admin").json()
    assert {"name": "guest", "role": "viewer"}.items() <= next(
        k for k in listed if k["name"] == "guest"
    ).items()
    assert "key" not in listed[0] and "hash" not in listed[0]
    assert service.client.delete(f"{API}/keys/guest", headers=service.headers("admin")).status_code == 200
    assert_problem(service.client.get(f"{API}/runs", headers={"Authorization": f"Bearer {token}"}), 401)
    actions = [(e["who"], e["action"], e["target"]) for e in service.get(f"{API}/audit", role="admin").json()]
    assert ("admin-key", "key.create", "guest") in actions and ("admin-key", "key.revoke", "guest") in actions


def test_cookie_session_needs_the_csrf_header_to_change_state(service: Service) -> None:
    client = TestClient(service.client.app)  # the same app, a browser of its own: no Authorization header
    client.cookies = service.client.cookies.__class__()
    login = client.post(f"{API}/session", json={"key": service.keys["operator"]})
    assert login.status_code == 200
    set_cookies = login.headers.get_list("set-cookie")
    session = next(c for c in set_cookies if c.startswith("hdrig_session="))
    assert "httponly" in session.lower() and "samesite=strict" in session.lower()
    csrf = client.cookies["hdrig_csrf"]
    assert client.get(f"{API}/runs").status_code == 200  # reads need no CSRF token
    body = assert_problem(client.post(f"{API}/rig/stop"), 403)
    assert "X-CSRF-Token" in body["detail"]
    assert_problem(client.post(f"{API}/rig/stop", headers={"X-CSRF-Token": "forged"}), 403)
    assert client.post(f"{API}/rig/stop", headers={"X-CSRF-Token": csrf}).status_code == 202
    assert client.delete(f"{API}/session", headers={"X-CSRF-Token": csrf}).status_code == 204
    client.cookies.set("hdrig_session", session.split(";")[0].split("=", 1)[1])
    assert_problem(client.get(f"{API}/runs"), 401)  # the session has ended


def test_a_viewer_cannot_move_the_motor(service: Service) -> None:
    assert_problem(service.post(f"{API}/runs", {"experiment": "pulse"}, role="viewer"), 403)
    assert_problem(service.post(f"{API}/rig/stop", role="viewer"), 403)


# ---- runs ----------------------------------------------------------------------------------------


def test_a_sweep_started_over_http_completes_and_its_csv_has_the_columns_and_window_asked(
    service: Service,
) -> None:
    started = service.start(params=SHORT_SWEEP)
    assert started.status_code == 202, started.text
    run_id = started.json()["id"]
    assert started.headers["location"] == f"{API}/runs/{run_id}"
    assert started.json()["status"] in ("queued", "running")
    done = service.wait_run(run_id)
    assert done["status"] == "complete" and done["samples"] > 0 and done["owner"] == "operator-key"
    assert done["metrics"] and done["artifacts"]
    response = service.get(
        f"{API}/runs/{run_id}/data", params={"format": "csv", "columns": "omega_m,i_a", "t0": 0.5, "t1": 1.0}
    )
    assert response.status_code == 200 and response.headers["content-type"].startswith("text/csv")
    lines = response.text.strip().split("\n")
    assert lines[0].split(",") == ["t", "omega_m", "i_a"]
    times = [float(line.split(",")[0]) for line in lines[1:]]
    assert 0.5 <= times[0] < 0.5 + 2e-3 and 1.0 - 2e-3 < times[-1] <= 1.0  # 1 kHz: one sample each 1 ms
    assert len(times) == pytest.approx(501, abs=1)
    parquet = service.get(f"{API}/runs/{run_id}/data", params={"format": "parquet"})
    assert parquet.status_code == 200 and parquet.content[:4] == b"PAR1"
    assert any(r["id"] == run_id for r in service.get(f"{API}/runs").json())
    files = service.get(f"{API}/runs/{run_id}/artifacts").json()["files"]
    assert "results.json" in files
    assert service.get(f"{API}/runs/{run_id}/artifacts/results.json").status_code == 200
    assert_problem(service.get(f"{API}/runs/{run_id}/artifacts/../../../catalog.sqlite"), 404)
    assert_problem(service.get(f"{API}/runs/{run_id}/artifacts/%2e%2e/%2e%2e/%2e%2e/catalog.sqlite"), 404)
    audit = service.get(f"{API}/audit", role="admin").json()
    assert any(e["action"] == "start" and e["target"] == run_id and e["who"] == "operator-key" for e in audit)


def test_an_unknown_column_is_422_naming_it(service: Service) -> None:
    run_id = service.start(params=SHORT_SWEEP).json()["id"]
    service.wait_run(run_id)
    body = assert_problem(
        service.get(f"{API}/runs/{run_id}/data", params={"format": "csv", "columns": "t,nope"}), 422
    )
    assert "nope" in body["detail"] and body["errors"][0]["field"] == "query.columns"


def test_bad_params_are_422_problem_naming_the_field(service: Service) -> None:
    body = assert_problem(service.start(params={"hold_s": -1}), 422)
    assert "hold_s" in body["detail"] and body["errors"][0]["field"] == "body.params.hold_s"
    body = assert_problem(service.start("no-such-experiment"), 422)
    assert "no-such-experiment" in body["detail"] and body["errors"][0]["field"] == "body.experiment"
    body = assert_problem(service.post(f"{API}/runs", {"params": {}}), 422)  # FastAPI's own validation
    assert "experiment" in body["detail"]
    assert service.get(f"{API}/runs").json() == []  # nothing was started


def test_an_unknown_run_is_404_problem(service: Service) -> None:
    body = assert_problem(service.get(f"{API}/runs/no-such-run"), 404)
    assert "no-such-run" in body["detail"]
    assert_problem(service.get(f"{API}/runs/no-such-run/data"), 404)
    assert_problem(service.get(f"{API}/runs/no-such-run/events"), 404)
    assert_problem(service.get(f"{API}/no-such-route"), 404)
    assert_problem(service.client.delete(f"{API}/health"), 405)


def test_a_busy_rig_is_409_with_retry_after_and_queue_waits_its_turn(live: Service) -> None:
    first = live.start(params={"speeds_rad_s": [2.0]}).json()
    busy = live.start(params={"speeds_rad_s": [3.0]})
    assert_problem(busy, 409)
    assert int(busy.headers["retry-after"]) > 0
    queued = live.start(params={"speeds_rad_s": [3.0]}, queue=True)
    assert queued.status_code == 202 and queued.json()["status"] == "queued"
    assert queued.json()["id"] in [r["id"] for r in live.get(f"{API}/runs").json()]
    second = live.wait_run(queued.json()["id"])
    assert second["status"] == "complete"
    assert live.get(f"{API}/runs/{first['id']}").json()["status"] == "complete"
    jobs = {j["id"]: j for j in live.get(f"{API}/jobs").json()}
    assert jobs[first["id"]]["status"] == jobs[second["id"]]["status"] == "complete"


def test_abort_ends_the_run_aborted_with_its_data(live: Service) -> None:
    run_id = live.start().json()["id"]
    live.wait_run(run_id, lambda d: d["status"] == "running" and d["progress"] > 0.02)
    aborted = live.post(f"{API}/runs/{run_id}/abort")
    assert aborted.status_code == 202
    done = live.wait_run(run_id)
    assert done["status"] == "aborted" and done["samples"] > 0
    assert live.get(f"{API}/runs/{run_id}/data", params={"format": "csv"}).status_code == 200
    assert_problem(live.post(f"{API}/runs/{run_id}/abort"), 409)  # it has ended already


def test_rig_stop_is_accepted_when_idle(service: Service) -> None:
    response = service.post(f"{API}/rig/stop")
    assert response.status_code == 202 and response.json()["state"] == "idle"
    rig = service.get(f"{API}/rig").json()
    assert rig["mode"] == "sim" and rig["name"] == "sim" and rig["limits"]["current_a"] > 0
    assert service.post(f"{API}/rig/reset").status_code == 200


def test_two_clients_starting_at_once_get_one_202_and_one_409(live: Service) -> None:
    barrier = threading.Barrier(2)
    codes: list[int] = []

    def start() -> None:
        barrier.wait()
        codes.append(live.start(params={"speeds_rad_s": [2.0]}).status_code)

    threads = [threading.Thread(target=start) for _ in range(2)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(WAIT_S)
    assert sorted(codes) == [202, 409]


# ---- events --------------------------------------------------------------------------------------


def parse_sse(text: str) -> list[dict[str, Any]]:
    events = []
    for block in text.split("\n\n"):
        fields = dict(
            line.split(": ", 1) for line in block.split("\n") if ": " in line and not line.startswith(":")
        )
        if "id" in fields:
            events.append(fields)
    return events


def test_events_carry_ids_end_with_the_run_and_resume_after_last_event_id(service: Service) -> None:
    run_id = service.start(params=SHORT_SWEEP).json()["id"]
    response = service.get(f"{API}/runs/{run_id}/events")  # ends after the run's final event
    assert response.status_code == 200 and response.headers["content-type"].startswith("text/event-stream")
    events = parse_sse(response.text)
    ids = [int(e["id"]) for e in events]
    assert ids == sorted(ids) and len(set(ids)) == len(ids)
    kinds = {e["event"] for e in events}
    assert {"state", "progress", "samples", "run"} <= kinds and "job" not in kinds
    assert events[-1]["event"] == "run" and '"complete"' in events[-1]["data"]
    middle = ids[len(ids) // 2]
    resumed = parse_sse(
        service.get(f"{API}/runs/{run_id}/events", headers={"Last-Event-ID": str(middle)}).text
    )
    assert resumed and all(int(e["id"]) > middle for e in resumed)
    assert [int(e["id"]) for e in resumed] == [i for i in ids if i > middle]


# ---- fits ----------------------------------------------------------------------------------------


def test_a_fit_over_http_on_runs_recorded_over_http_returns_the_fit_document(service: Service) -> None:
    campaign = service.start("campaign")
    assert campaign.status_code == 202, campaign.text
    job = service.wait_job(campaign.headers["location"])
    assert job["status"] == "complete", job
    runs = job["runs"]
    assert_problem(service.post(f"{API}/fits", {"data": runs, "model": "no-such-model"}), 422)
    assert_problem(service.post(f"{API}/fits", {"data": ["no-such-run"], "model": "seed"}), 404)
    started = service.post(f"{API}/fits", {"data": runs, "model": "seed"})
    assert started.status_code == 202, started.text
    location = started.headers["location"]
    assert location == f"{API}/fits/{started.json()['id']}"
    fit = service.wait_job(location)
    assert fit["status"] == "complete", fit["error"]
    result = fit["result"]
    assert result["parameters"] and result["fit_error"]["after"] <= result["fit_error"]["before"]
    files = service.get(f"{location}/files").json()["files"]
    assert "result.json" in files and any(f.startswith("report/") for f in files)
    assert service.get(f"{location}/files/result.json").json() == result
    assert_problem(service.get(f"{location}/files/../../catalog.sqlite"), 404)


def test_an_analysis_from_before_the_service_is_found_by_its_recorded_kind_not_its_id(
    service: Service,
) -> None:
    """A fit or gap analysis that ended before this service started answers from its folder's job record;
    its id says nothing (this gap analysis is named like a fit)."""
    store = service.store
    folder = actions._analysis_folder(store, JobKind.GAPS, "20260101-000000-fit-abcd")
    (folder / actions.RESULT_FILE).write_text(json.dumps({"verdict": "no gap"}))
    job = service.get(f"{API}/gaps/{folder.name}")
    assert job.status_code == 200, job.text
    assert job.json()["kind"] == "gaps" and job.json()["status"] == "complete"
    assert job.json()["result"] == {"verdict": "no gap"}
    assert "job.json" in service.get(f"{API}/gaps/{folder.name}/files").json()["files"]
    assert_problem(service.get(f"{API}/fits/{folder.name}"), 404)
    (folder / actions.JOB_FILE).unlink()  # no record, and a result that is neither a fit nor gaps
    assert_problem(service.get(f"{API}/gaps/{folder.name}"), 404)


def test_an_analysis_from_before_job_records_is_found_by_what_its_result_holds(service: Service) -> None:
    """Analyses a store kept before their folders had a job record (`job.json`) stay reachable: the kind is
    read from the result's own fields (a fit's parameters and fit error, a gap analysis' steps), never
    from the id; this fit is named like a gap analysis."""
    store = service.store
    folder = actions._analysis_folder(store, JobKind.FIT, "20250101-000000-gaps-abcd")
    (folder / actions.JOB_FILE).unlink()
    fit = {"parameters": {"s3": {"value": 0.07}}, "fit_error": {"before": 1.0, "after": 0.5}}
    (folder / actions.RESULT_FILE).write_text(json.dumps(fit))
    job = service.get(f"{API}/fits/{folder.name}")
    assert job.status_code == 200, job.text
    assert job.json()["kind"] == "fit" and job.json()["result"] == fit
    assert_problem(service.get(f"{API}/gaps/{folder.name}"), 404)
