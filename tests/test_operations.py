"""The action table (`rig.core.operations`) against every door: the REST routes, the command line, the
Python client and the `Lab` both the local core and the remote lab implement. A door that lacks an
operation the table gives it, or offers one the table does not know, fails here."""

from __future__ import annotations

import argparse
import inspect
from pathlib import Path
from typing import Any

import pytest
from fastapi.routing import APIRoute

from api import auth
from api.app import API, _operator_now, router
from api.client import HdrigClient
from api.remote_lab import RemoteLab
from model.errors import UserInputError
from rig.cli import build_parser
from rig.core import actions
from rig.core.access import Role
from rig.core.actions import UnknownJobError
from rig.core.documents import JobKind
from rig.core.operations import OPERATIONS, Operation
from rig.lab import Lab, LocalLab
from rig.store.runs import RunQuery, RunStore

SERVICE_ONLY = {("GET", f"{API}/health"), ("POST", f"{API}/session"), ("GET", f"{API}/session")}
SERVICE_ONLY |= {("DELETE", f"{API}/session")}  # the page's login and liveness: no operation of the lab
CLI_ONLY = {"serve", "twin"}  # the service itself and a device twin: processes, not operations
CLIENT_HELPERS = {
    "close": "the HTTP connection",
    "health": "liveness",
    "wait": "follows a run or job to its end (on show_run / show_job)",
    "wait_job": "polls show_job",
    "start": "start_run with its request model",
    "analysis": "fit and gaps with their request model",
    "newest_runs": "list_runs a page at a time",
    "runs": "list_runs a page at a time, the documents only",
}
ROLE_OF_DEPENDENCY: dict[Any, Role] = {
    auth.viewer: Role.VIEWER,
    auth.operator: Role.OPERATOR,
    auth.admin: Role.ADMIN,
    _operator_now: Role.OPERATOR,
}


def _with(door: str) -> list[Operation]:
    return [op for op in OPERATIONS if getattr(op, door) is not None]


def test_every_operation_is_named_once() -> None:
    names = [op.name for op in OPERATIONS]
    assert len(names) == len(set(names))
    for door in ("rest", "cli", "client", "lab"):
        offered = [getattr(op, door) for op in _with(door) if door != "client" or op.client != "files"]
        offered = [o for o in offered if o != "download_file"]  # fits and gaps share the files methods
        assert len(offered) == len(set(offered)), door


def _routes() -> dict[tuple[str, str], APIRoute]:
    routes = [route for route in router.routes if isinstance(route, APIRoute)]
    return {(method, route.path): route for route in routes for method in route.methods or ()}


def test_the_routes_are_the_tables_and_need_its_roles() -> None:
    routes = _routes()
    declared = {(op.rest[0], f"{API}{op.rest[1]}"): op for op in _with("rest") if op.rest is not None}
    assert set(routes) - SERVICE_ONLY == set(declared), "a route without an operation, or the reverse"
    for key, op in declared.items():
        route = routes[key]
        who = [d.call for d in route.dependant.dependencies if d.name == "who" and d.call is not None]
        assert len(who) == 1, f"{key}: no `who` dependency"
        role = ROLE_OF_DEPENDENCY.get(who[0])
        assert role == op.role, f"{key}: needs {role}, not {op.role}"
        assert route.status_code in (op.status, None), key
        assert route.summary == op.summary, key


def _leaves(parser: argparse.ArgumentParser, prefix: str = "") -> set[str]:
    actions = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not actions:
        return {prefix.strip()}
    found: set[str] = set()
    for name, sub in actions[0].choices.items():
        found |= _leaves(sub, f"{prefix} {name}")
    return found


def test_the_command_line_offers_the_tables_commands() -> None:
    leaves = _leaves(build_parser())
    declared = {op.cli for op in _with("cli")}
    assert leaves - CLI_ONLY == declared


def test_the_client_offers_the_tables_methods() -> None:
    public = {
        name for name, _ in inspect.getmembers(HdrigClient, inspect.isfunction) if not name.startswith("_")
    }
    declared = {op.client for op in _with("client")}
    assert declared <= public, f"the client lacks {declared - public}"
    assert public - declared == set(CLIENT_HELPERS), "a client method the table does not know"


def test_both_labs_implement_the_tables_lab_methods_alike() -> None:
    declared = {op.lab for op in _with("lab")}
    protocol = {name for name, _ in inspect.getmembers(Lab, inspect.isfunction) if not name.startswith("_")}
    assert protocol == declared
    for name in declared:
        assert name is not None
        wanted = list(inspect.signature(getattr(Lab, name)).parameters)
        for lab in (LocalLab, RemoteLab):
            assert list(inspect.signature(getattr(lab, name)).parameters) == wanted, f"{lab.__name__}.{name}"


def test_the_run_filters_are_one_query_everywhere() -> None:
    """`hdrig runs list` takes exactly the query's fields (`--tag` repeated for `tags`), as the route does."""
    (runs_list,) = [
        sub
        for a in build_parser()._actions
        if isinstance(a, argparse._SubParsersAction)
        for name, group in a.choices.items()
        if name == "runs"
        for b in group._actions
        if isinstance(b, argparse._SubParsersAction)
        for leaf, sub in b.choices.items()
        if leaf == "list"
    ]
    options = {a.dest for a in runs_list._actions if a.option_strings} - {"help", "json", "limit", "all"}
    fields = {"tag" if name == "tags" else name for name in RunQuery.model_fields}
    assert options == fields
    route = _routes()[("GET", f"{API}/runs")]
    (query,) = route.dependant.query_params
    model = query.field_info.annotation
    assert isinstance(model, type) and issubclass(model, RunQuery)
    assert set(model.model_fields) - set(RunQuery.model_fields) == {"limit", "cursor"}  # which page


def test_an_analysis_folder_is_named_by_a_job_id_only(tmp_path: Path) -> None:
    store = RunStore(tmp_path / "home")
    for bad in ("..", ".", "", "a/b"):
        with pytest.raises(UnknownJobError, match=r"^unknown job id"):
            actions.analysis_folder(store, bad)
    assert actions.finished_analysis(store, "20260101-000000-fit-abcd", JobKind.FIT) is None


def test_a_download_names_the_field_it_refuses(tmp_path: Path) -> None:
    store = RunStore(tmp_path / "home")
    with pytest.raises(actions.FieldInputError, match=r"^t1=1\.0 is before t0=2\.0$") as late:
        actions.download_run(store, "no-such-run", "csv", tmp_path, None, 2.0, 1.0)
    assert late.value.field == "t1"
    with pytest.raises(UserInputError, match="no-such-run"):  # the run is looked up before its columns
        actions.download_run(store, "no-such-run", "csv", tmp_path, ["omega_m"])
