"""The service against its own OpenAPI document (schemathesis): generated requests to every operation, as an
operator, never get a 5xx and every answer matches the documented schema for its status and media type.

Bounded: 20 examples an operation. The event stream is left out (it streams until its run ends).
"""

from __future__ import annotations

import tempfile
from collections.abc import Iterator

import pytest
import schemathesis
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, settings
from schemathesis.checks import (
    content_type_conformance,
    not_a_server_error,
    response_schema_conformance,
    status_code_conformance,
)

from api.app import create_app
from rig.config import load_rig_config
from rig.core import access
from rig.store.runs import RunStore

STORE = RunStore(tempfile.mkdtemp(prefix="hdrig-schemathesis-"))
KEY = access.create_key(STORE, "operator", "schemathesis")
APP = create_app(load_rig_config("configs/rigs/sim.yaml"), STORE)
schema = schemathesis.openapi.from_asgi("/openapi.json", APP).exclude(path_regex=r".*/events$")


@pytest.fixture(scope="module", autouse=True)
def running_service() -> Iterator[None]:
    with TestClient(APP):  # the lifespan: the rig worker and the analysis worker
        yield


@schema.parametrize()
@settings(max_examples=20, deadline=None, suppress_health_check=list(HealthCheck))
def test_no_server_error_and_every_answer_as_documented(case: schemathesis.Case) -> None:
    case.call_and_validate(
        headers={"Authorization": f"Bearer {KEY}"},
        checks=[
            not_a_server_error,
            response_schema_conformance,
            content_type_conformance,
            status_code_conformance,
        ],
    )
