"""The service under a hostile or careless client (issue 23 items 1, 5, 6, 8): bodies, lists, numbers,
types, queue, pages, control characters, failed logins and the page's headers all have limits, and each
breach is a short 4xx problem, decided before anything moves.

In process (FastAPI's TestClient) on the simulated rig of configs/rigs/sim.yaml in a scratch store.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from api import app as app_module
from api import guard
from api.app import create_app
from api.problems import DETAIL_MAX
from rig.config import load_rig_config
from rig.core import access
from rig.store.runs import RunStore

API = "/api/v1"
PROBLEM = "application/problem+json"


class Client:
    def __init__(self, client: TestClient, keys: dict[str, str]) -> None:
        self.client, self.keys = client, keys

    def auth(self, role: str = "operator") -> dict[str, str]:
        return {"Authorization": f"Bearer {self.keys[role]}"}

    def start(self, params: dict[str, Any], experiment: str = "speed-sweep", **kw: Any) -> Any:
        body = {"experiment": experiment, "params": params, **kw}
        return self.client.post(f"{API}/runs", json=body, headers=self.auth())

    def jobs(self) -> list[dict[str, Any]]:
        answer: list[dict[str, Any]] = self.client.get(f"{API}/jobs", headers=self.auth()).json()
        return answer


@pytest.fixture
def service(tmp_path: Path) -> Iterator[Client]:
    store = RunStore(tmp_path / "home")
    keys = {role: access.create_key(store, role, f"{role}-key") for role in ("viewer", "operator", "admin")}
    config = load_rig_config("configs/rigs/sim.yaml").model_copy(update={"pace": "realtime"})
    with TestClient(create_app(config, store)) as client:
        yield Client(client, keys)


def problem(response: Any, status: int) -> dict[str, Any]:
    assert response.status_code == status, response.text[:500]
    assert response.headers["content-type"].startswith(PROBLEM)
    body: dict[str, Any] = response.json()
    assert body["status"] == status and body["detail"]
    return body


def named(body: dict[str, Any]) -> set[str]:
    return {error["field"] for error in body.get("errors", [])}


# ---- bodies ----------------------------------------------------------------------------------------

SPEEDS_BODY_BYTES = 3 << 20  # three times the cap: a list of speeds no experiment could play


def _speeds_body(size: int) -> bytes:
    count = size // 4
    return b'{"experiment": "speed-sweep", "params": {"speeds_rad_s": [' + b"1.0," * count + b"1.0]}}"


def test_a_body_over_the_cap_is_413_before_it_is_parsed(service: Client) -> None:
    body = problem(
        service.client.post(
            f"{API}/runs",
            content=_speeds_body(SPEEDS_BODY_BYTES),
            headers={**service.auth(), "Content-Type": "application/json"},
        ),
        413,
    )
    assert str(guard.BODY_MAX_BYTES) in body["detail"]
    assert service.jobs() == []


def test_a_chunked_body_over_the_cap_is_413_too(service: Client) -> None:
    whole = _speeds_body(SPEEDS_BODY_BYTES)

    def chunks() -> Iterator[bytes]:  # no Content-Length: the cap counts the bytes as they stream in
        for start in range(0, len(whole), 64 << 10):
            yield whole[start : start + (64 << 10)]

    response = service.client.post(
        f"{API}/runs", content=chunks(), headers={**service.auth(), "Content-Type": "application/json"}
    )
    problem(response, 413)
    assert service.jobs() == []


def test_a_body_that_is_not_json_is_415(service: Client) -> None:
    text = json.dumps({"experiment": "speed-sweep", "params": {}})
    response = service.client.post(
        f"{API}/runs", content=text, headers={**service.auth(), "Content-Type": "text/plain"}
    )
    problem(response, 415)
    assert service.jobs() == []


# ---- parameters, validated whole before anything moves -----------------------------------------------


@pytest.mark.parametrize(
    ("params", "field"),
    [
        ({"speeds_rad_s": [1, 1]}, "body.params.speeds_rad_s"),  # repeated: the same pass twice
        ({"speeds_rad_s": [1e6]}, "body.params.speeds_rad_s"),  # beyond any motor
        ({"speeds_rad_s": [700.0]}, "body.params.speeds_rad_s"),  # beyond this rig's 600 rad/s saturation
        ({"speeds_rad_s": [float(s) for s in range(1, 300)]}, "body.params.speeds_rad_s"),  # too many
        ({"hold_s": True}, "body.params.hold_s"),
        ({"hold_s": "0.5"}, "body.params.hold_s"),
        ({"tau_ext_nm": 1e9}, "body.params.tau_ext_nm"),
    ],
)
def test_bad_parameters_are_422_naming_the_field_and_nothing_starts(
    service: Client, params: dict[str, Any], field: str
) -> None:
    body = problem(service.start(params), 422)
    assert field in named(body), body
    assert service.jobs() == []


def test_a_program_that_does_not_fit_the_travel_is_refused_at_submit(service: Client) -> None:
    body = problem(service.start({"duty_stroke_rad": 1e4}, experiment="endurance"), 422)
    assert "travel" in body["detail"]
    assert service.jobs() == []


@pytest.mark.parametrize("flag", ["queue", "keep_going"])
def test_flags_are_json_booleans(service: Client, flag: str) -> None:
    body = problem(service.start({}, **{flag: "yes"}), 422)
    assert f"body.{flag}" in named(body)
    assert service.jobs() == []


def test_an_error_quotes_only_an_excerpt_of_the_input(service: Client) -> None:
    huge = "a" * 900_000  # just under the body cap
    response = service.start({"speeds_rad_s": huge})
    body = problem(response, 422)
    assert len(response.content) < 4 * DETAIL_MAX + 1000, len(response.content)
    assert len(body["detail"]) <= DETAIL_MAX


# ---- queue and pages ---------------------------------------------------------------------------------


def test_the_queue_is_bounded_429_with_retry_after(service: Client, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(app_module, "QUEUE_MAX", 2)
    sweep = {"speeds_rad_s": [2.0, 20.0]}  # paced to the wall clock: seconds, while the queue fills
    try:
        assert service.start(sweep).status_code == 202
        assert service.start(sweep, queue=True).status_code == 202
        assert service.start(sweep, queue=True).status_code == 202
        response = service.start(sweep, queue=True)
        problem(response, 429)
        assert int(response.headers["Retry-After"]) > 0
        assert len(service.jobs()) == 3
    finally:
        service.client.post(f"{API}/rig/stop", headers=service.auth())


def test_pages_are_bounded(service: Client) -> None:
    for path, role in (("audit", "admin"), ("jobs", "operator"), ("runs", "operator")):
        refused = problem(service.client.get(f"{API}/{path}?limit=100000", headers=service.auth(role)), 422)
        assert any("limit" in field for field in named(refused)), (path, refused)


# ---- control characters --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "url",
    [
        f"{API}/runs/x/artifacts/results.json%00",
        f"{API}/runs/x%01y",
        f"{API}/fits/x/files/a%7Fb",
        f"{API}/runs?unit=a%00b",
        f"{API}/models/seed%0a",
    ],
)
def test_control_characters_are_400_and_never_reach_the_log(
    service: Client, url: str, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.DEBUG):
        problem(service.client.get(url, headers=service.auth()), 400)
    assert not any("\x00" in record.getMessage() for record in caplog.records)


# ---- failed logins, the page's headers --------------------------------------------------------------------


def test_failed_key_checks_are_limited_per_client_and_key(service: Client) -> None:
    app = service.client.app
    limit: guard.LoginLimit = app.state.login_limit  # type: ignore[attr-defined]
    now = [1000.0]
    limit.clock = lambda: now[0]
    operator = service.keys["operator"]
    guessed = operator.partition(".")[0] + ".not-the-secret"  # the key's public id, a wrong secret
    for _ in range(limit.failures_max // 2):
        problem(service.client.post(f"{API}/session", json={"key": guessed}), 401)
    for _ in range(limit.failures_max - limit.failures_max // 2):
        problem(service.client.get(f"{API}/runs", headers={"Authorization": f"Bearer {guessed}"}), 401)
    refused = service.client.post(f"{API}/session", json={"key": operator})  # that key, even right
    problem(refused, 429)
    assert 0 < int(refused.headers["Retry-After"]) <= limit.window_s
    problem(service.client.get(f"{API}/runs", headers={"Authorization": f"Bearer {operator}"}), 429)
    # Another key from the same address is not held back (on loopback every client shares one address).
    assert service.client.get(f"{API}/runs", headers=service.auth("viewer")).status_code == 200
    # Made-up keys share one bucket: after as many failures they are refused too.
    for _ in range(limit.failures_max):
        problem(service.client.post(f"{API}/session", json={"key": "made-up"}), 401)
    problem(service.client.post(f"{API}/session", json={"key": "made-up-too"}), 429)
    now[0] += limit.window_s + 1  # the window has passed: keys are checked again
    assert service.client.post(f"{API}/session", json={"key": operator}).status_code == 200


@pytest.mark.parametrize("path", ["/", "/static/app.js"])
def test_the_page_is_served_with_csp_and_no_framing(service: Client, path: str) -> None:
    response = service.client.get(path)
    assert response.status_code == 200
    csp = response.headers["Content-Security-Policy"]
    assert "script-src 'self'" in csp and "frame-ancestors 'none'" in csp and "unsafe-inline" not in csp
    assert response.headers["X-Frame-Options"] == "DENY"
    assert response.headers["X-Content-Type-Options"] == "nosniff"
    api = service.client.get(f"{API}/health")
    assert api.headers["X-Content-Type-Options"] == "nosniff"
