"""The service as a sequence of calls (schemathesis' stateful phase, issue 23 item 6): keys made and
revoked (`POST /keys` and `GET /keys` link to `DELETE /keys/{name}`), models and the audit log, as an admin.
No call gets a 5xx, and after each scenario a live admin key is left (the last one is refused with 409)
and the scenario's admin key, unless it revoked it with another admin made, still works.

Bounded: a few scenarios of a few steps each (schemathesis' stateful settings below); the routes that
move the motor are left to test_api_schema.py (one call each, as an operator).
"""

from __future__ import annotations

import shutil
import tempfile
from typing import Any

import schemathesis
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, settings
from schemathesis.checks import not_a_server_error

from api.app import create_app
from rig.config import load_rig_config
from rig.core import access
from rig.store import catalog as tables
from rig.store.runs import RunStore

STORE = RunStore(tempfile.mkdtemp(prefix="hdrig-stateful-"))
ADMIN = access.create_key(STORE, "admin", "stateful-admin")
APP = create_app(load_rig_config("configs/rigs/sim.yaml"), STORE)
schema = schemathesis.openapi.from_asgi("/openapi.json", APP).include(
    path_regex=r"^/api/v1/(keys|audit|models|health)"
)


def test_the_openapi_document_links_a_made_key_to_its_revoke() -> None:
    links = APP.openapi()["paths"]["/api/v1/keys"]["post"]["responses"]["201"]["links"]
    assert links["RevokeKey"]["parameters"] == {"name": "$response.body#/name"}


class KeyScenarios(schema.as_state_machine()):  # type: ignore[misc]
    client: TestClient | None = None

    def setup(self) -> None:
        if KeyScenarios.client is None:  # the lifespan once (rig worker, analysis worker) for all scenarios
            KeyScenarios.client = TestClient(APP).__enter__()
        # Each scenario starts from the same store (hypothesis replays scenarios: the answers must not
        # depend on what an earlier one did): the one admin key, live; no other key, no audit lines.
        with STORE.catalog.write() as db:
            db.execute(tables.keys.delete().where(tables.keys.c.name != "stateful-admin"))
            db.execute(tables.keys.update().values(revoked=None))
            db.execute(tables.audit.delete())
        shutil.rmtree(STORE.models_dir, ignore_errors=True)
        # The service's memory too: a scenario that revoked its own key (another admin made first) left
        # failed checks in the login limit, which would answer 429 in the next scenario.
        APP.state.login_limit.forget()

    def get_call_kwargs(self, case: schemathesis.Case) -> dict[str, Any]:
        return {"headers": {"Authorization": f"Bearer {ADMIN}"}}

    def validate_response(self, response: Any, case: schemathesis.Case, **kwargs: Any) -> None:
        case.validate_response(response, checks=[not_a_server_error])

    def teardown(self) -> None:
        live_admins = [k for k in access.list_keys(STORE) if k.role == "admin" and k.revoked is None]
        assert live_admins, "no live admin key is left"
        # A scenario may revoke its own key once it has made another admin.
        if "stateful-admin" in {k.name for k in live_admins}:
            still = TestClient(APP).get("/api/v1/keys", headers={"Authorization": f"Bearer {ADMIN}"})
            assert still.status_code == 200, f"a live admin key is refused: {still.status_code} {still.text}"


TestKeyScenarios = KeyScenarios.TestCase
TestKeyScenarios.settings = settings(
    max_examples=25, stateful_step_count=8, deadline=None, suppress_health_check=list(HealthCheck)
)
