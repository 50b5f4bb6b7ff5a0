"""The REST service (`hdrig serve`): routes over the application core, for one rig.

A thin shell: every route calls `rig.core` (actions, the rig worker, the analysis worker, access) and
answers with the core's documents; no experiment, fit or store logic lives here. Routes are plain
functions, so FastAPI runs them on its thread pool and a slow disk never holds the event loop; the
event stream is a coroutine (it polls the worker's event log with short sleeps), and so is the stop,
which must not wait for that pool: it stops the motor on the event loop and does the rest on threads
of its own (the stop lane).

Going away (`stop_service`, called by `hdrig serve` on SIGTERM, SIGINT or SIGHUP): the motor stops
first, the run playing is sealed `aborted`, then every event stream ends with a `closed` event saying why.
"""

from __future__ import annotations

import asyncio
import json
import shutil
import tempfile
import threading
from collections.abc import AsyncIterator, Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import asynccontextmanager
from functools import partial
from pathlib import Path
from typing import Annotated, Any, Literal, TypeVar
from urllib.parse import urlencode

import numpy as np
from fastapi import APIRouter, Depends, FastAPI, Header, Query, Request, Response
from fastapi import Path as PathParam
from fastapi.openapi.utils import get_openapi
from fastapi.responses import FileResponse, HTMLResponse, StreamingResponse
from fastapi.security import HTTPAuthorizationCredentials
from fastapi.staticfiles import StaticFiles
from starlette.background import BackgroundTask

from api import auth, guard, problems
from api.auth import Principal, Sessions
from api.paths import HideServerPaths, PathScrubber
from api.problems import FieldError, Problem, ProblemError
from api.schemas import (
    AnalysisRequest,
    FileList,
    Health,
    KeyRequest,
    ModelUpload,
    NewKey,
    RigStatus,
    RunListQuery,
    RunRequest,
    SessionInfo,
    SessionRequest,
)
from model.errors import UserInputError
from model.params import preset_names
from model.resources import package_folder
from rig.config import RigConfig
from rig.core import access, actions, operations
from rig.core.access import AuditEntry, KeyInfo, Role
from rig.core.actions import UnknownJobError
from rig.core.documents import ExperimentInfo, JobDocument, JobKind, RunDocument
from rig.core.events import Event, EventKind
from rig.core.rig_status import rig_status_of
from rig.core.worker import AnalysisWorker, Job, RigWorker
from rig.lab import ServedApp
from rig.status import RunStatus
from rig.store.catalog import MAX_PAGE
from rig.store.runs import ARTIFACTS_DIR, EXPORT_FORMATS, RunStore

API = "/api/v1"
STATIC_DIR = package_folder("api", "static")
STREAM_KINDS = frozenset(
    {EventKind.STATE, EventKind.PROGRESS, EventKind.SAMPLES, EventKind.ALARM, EventKind.RUN}
)
STREAM_POLL_S = 0.02  # the event stream's poll of the log: a live plot's latency, a negligible load
KEEP_ALIVE_S = 10.0  # a comment line this often keeps proxies and browsers from closing a quiet stream
STOP_LANE_THREADS = 2  # the stop's own threads: its key check and answer never queue behind others
SEAL_WAIT_S = 2.0  # going away: how long the stopped run may take to be sealed before streams end
CLOSE_WAIT_S = 1.0  # then how long the lifespan waits for each worker's thread (the process exits regardless)
QUEUE_MAX = 20  # jobs waiting for the rig: a working day of campaigns; more is a client gone wrong
AUDIT_PAGE_MAX = 1000  # audit lines in one answer
AUDIT_DETAIL_MAX = 2000  # characters of a start request kept in its audit line
MEDIA_TYPES = {
    "csv": "text/csv",
    "parquet": "application/vnd.apache.parquet",
    "mat": "application/x-matlab-data",
}

ERROR_RESPONSES: dict[int | str, dict[str, Any]] = {
    status: {"model": Problem, "description": problems.TITLES[status]}
    for status in (400, 401, 403, 404, 409, 413, 415, 422, 429)  # 413/415/429: api.guard, any route
}

Viewer = Annotated[Principal, Depends(auth.viewer)]
Operator = Annotated[Principal, Depends(auth.operator)]
Admin = Annotated[Principal, Depends(auth.admin)]
RunId = Annotated[str, PathParam(description="a run id", max_length=200)]
JobId = Annotated[str, PathParam(description="a job id", max_length=200)]
JobsLimit = Annotated[
    int, Query(ge=1, le=MAX_PAGE, description=f"the newest jobs, oldest first, 1-{MAX_PAGE}")
]
AuditLimit = Annotated[int, Query(ge=1, le=AUDIT_PAGE_MAX, description=f"newest lines, 1-{AUDIT_PAGE_MAX}")]


# ---- what the routes share ------------------------------------------------------------------------


def _worker(request: Request) -> RigWorker:
    worker: RigWorker = request.app.state.worker
    return worker


def _analysis(request: Request) -> AnalysisWorker:
    analysis: AnalysisWorker = request.app.state.analysis
    return analysis


def _store(request: Request) -> RunStore:
    store: RunStore = request.app.state.store
    return store


def _audit(
    request: Request, who: Principal, action: str, target: str | None, detail: str | None = None
) -> None:
    access.audit(_store(request), who.name, who.role, action, target, detail)


def _run(request: Request, run_id: str) -> RunDocument:
    """A run: queued or recording from the worker, else from the store (404 when unknown)."""
    return _worker(request).run_document(run_id)


def _job(request: Request, job_id: str) -> Job:
    for worker in (_worker(request), _analysis(request)):
        try:
            return worker.job(job_id)
        except UnknownJobError:
            continue
    raise UnknownJobError(f"unknown job id {job_id!r}")


def _inside(folder: Path, relative: str) -> Path:
    """`folder/relative` if it is a file inside `folder` (no `..`, no links out), else 404."""
    base = folder.resolve()
    path = (base / relative).resolve()
    if not path.is_relative_to(base) or not path.is_file():
        raise ProblemError(404, f"no file {relative!r} here")
    return path


def _files(folder: Path) -> list[str]:
    if not folder.is_dir():
        return []
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file())


def _accepted(response: Response, location: str) -> None:
    response.status_code = 202
    response.headers["Location"] = location


# ---- the routes -------------------------------------------------------------------------------------

router = APIRouter(prefix=API, responses=ERROR_RESPONSES)
Route = TypeVar("Route", bound=Callable[..., Any])


def _route(name: str, **kwargs: Any) -> Callable[[Route], Route]:
    """Register a route of the operation `name` (`rig.core.operations`): its method, path, summary, tag
    and success status come from the action table."""
    operation = operations.operation(name)
    assert operation.rest is not None, f"operation {name} has no route"
    method, path = operation.rest
    decorate: Callable[[Route], Route] = router.api_route(
        path,
        methods=[method],
        summary=operation.summary,
        tags=[operation.tag],
        status_code=operation.status,
        **kwargs,
    )
    return decorate


@router.get("/health", response_model=Health, tags=["service"], summary="liveness (no key needed)")
def health() -> Health:
    return Health()


@router.post("/session", response_model=SessionInfo, tags=["service"], summary="log the browser page in")
def login(body: SessionRequest, request: Request, response: Response) -> SessionInfo:
    found = access.authenticate(_store(request), body.key)
    if found is None:
        raise ProblemError(401, "the API key is unknown or revoked")
    sessions: Sessions = request.app.state.sessions
    token, csrf = sessions.open(body.key)
    response.set_cookie(auth.SESSION_COOKIE, token, httponly=True, samesite="strict", path="/")
    response.set_cookie(auth.CSRF_COOKIE, csrf, httponly=False, samesite="strict", path="/")
    return SessionInfo(name=found[0], role=found[1], csrf=csrf)


@router.get("/session", response_model=SessionInfo, tags=["service"], summary="who is asking")
def whoami(who: Viewer) -> SessionInfo:
    return SessionInfo(name=who.name, role=who.role)


@router.delete("/session", status_code=204, tags=["service"], summary="log the browser page out")
def logout(request: Request, who: Viewer) -> Response:
    token = request.cookies.get(auth.SESSION_COOKIE)
    if token:
        sessions: Sessions = request.app.state.sessions
        sessions.close(token)
    response = Response(status_code=204)
    response.delete_cookie(auth.SESSION_COOKIE, path="/")
    response.delete_cookie(auth.CSRF_COOKIE, path="/")
    return response


@_route("rig_status", response_model=RigStatus)
def rig_status(request: Request, who: Viewer) -> RigStatus:
    return rig_status_of(_worker(request))


async def _on_stop_lane(request: Request, call: Callable[..., Any], *args: Any) -> Any:
    lane: ThreadPoolExecutor = request.app.state.stop_lane
    return await asyncio.get_running_loop().run_in_executor(lane, partial(call, *args))


async def _operator_now(
    request: Request,
    bearer: Annotated[HTTPAuthorizationCredentials | None, Depends(auth.bearer_scheme)],
    cookie: Annotated[str | None, Depends(auth.cookie_scheme)],
) -> Principal:
    """`auth.operator` on the stop lane: a thread pool saturated by slow requests must not hold a stop."""
    who: Principal = await _on_stop_lane(request, auth.principal, request, bearer, cookie)
    return auth.require(Role.OPERATOR)(who)


@_route("stop", response_model=RigStatus)
async def rig_stop(request: Request, who: Annotated[Principal, Depends(_operator_now)]) -> RigStatus:
    worker = _worker(request)
    why = f"quick stop by {who.name}"
    worker.rig.quick_stop(why)  # the motor now, on the event loop: any thread may, no lock of ours
    await _on_stop_lane(request, worker.quick_stop, why)  # then the queue and the state
    await _on_stop_lane(request, _audit, request, who, "stop", worker.config.name)
    status: RigStatus = await _on_stop_lane(request, rig_status, request, who)
    return status


@_route("reset", response_model=RigStatus)
def rig_reset(request: Request, who: Operator) -> RigStatus:
    _worker(request).reset()
    _audit(request, who, "reset", _worker(request).config.name)
    return rig_status(request, who)


@_route("list_experiments", response_model=list[ExperimentInfo])
def experiments(who: Viewer) -> list[ExperimentInfo]:
    return actions.list_experiments()


@_route("list_models")
def models(request: Request, who: Viewer) -> list[dict[str, Any]]:
    return [m.as_json() for m in actions.list_kept_models(_store(request))]


@_route("show_model")
def model(
    name: Annotated[str, PathParam(description="a preset's or an uploaded model's name", max_length=200)],
    request: Request,
    who: Viewer,
) -> dict[str, Any]:
    ref = actions.kept_model(_store(request), name)
    if ref is None:  # names only: a path would read files of the server
        raise ProblemError(404, f"unknown model {name[:80]!r} (GET /api/v1/models lists them)")
    return actions.show_model(ref)


@_route("upload_model")
def upload_model(body: ModelUpload, request: Request, response: Response, who: Operator) -> dict[str, Any]:
    try:
        kept = actions.keep_model(_store(request), body.name, body.model, "body.model")
    except actions.FieldInputError as exc:
        raise _field_problem(exc, "body") from None
    _audit(request, who, "model.upload", body.name)
    response.headers["Location"] = f"{API}/models/{body.name}"
    return kept


def _field_problem(exc: actions.FieldInputError, where: Literal["body", "query"]) -> ProblemError:
    """A 422 naming the request's field the core named (`body.model`, `query.columns`)."""
    message = str(exc)
    return ProblemError(422, message, [FieldError(field=f"{where}.{exc.field}", message=message)])


def model_ref(store: RunStore, name: str, field: str) -> str:
    """What the core loads for a model a client named (`actions.kept_model`); anything else (a path above
    all) is a 422 naming the field; no file is looked at."""
    ref = actions.kept_model(store, name)
    if ref is not None:
        return ref
    message = (
        f"{field}: unknown model {name[:80]!r}: name a preset ({', '.join(preset_names())}) or a model"
        " uploaded with POST /api/v1/models (files on the server are not named over HTTP)"
    )
    raise ProblemError(422, message, [FieldError(field=field, message=message)])


@_route("start_run", response_model=RunDocument | JobDocument)
def start_run(
    body: RunRequest, request: Request, response: Response, who: Operator
) -> RunDocument | JobDocument:
    params = body.params
    if isinstance(params.get("model"), str):  # a model by name only (compensation's `params.model`)
        params = {**params, "model": model_ref(_store(request), params["model"], "body.params.model")}
    worker = _worker(request)
    try:  # the whole plan, built against this rig, before anything moves
        plan = operations.plan_of(body.model_copy(update={"params": params}), worker.rig)
    except UserInputError as exc:
        raise _named(exc, body) from None
    job = worker.submit(plan, owner=who.name, queue=body.queue, queue_max=QUEUE_MAX)
    started = json.dumps({"experiment": body.experiment, "params": body.params})
    _audit(request, who, "start", job.id, problems.excerpt(started, AUDIT_DETAIL_MAX))
    if job.kind == JobKind.RUN:
        _accepted(response, f"{API}/runs/{job.id}")
        return _run(request, job.id)
    _accepted(response, f"{API}/jobs/{job.id}")
    return job.document()


def _named(exc: UserInputError, body: RunRequest) -> ProblemError:
    """A plan's one-line error as a 422 naming the field (`body.params.hold_s`, `body.experiment`)."""
    message = str(exc)
    field = "body.experiment"
    for name in sorted(body.params, key=len, reverse=True):
        if f"'{name}" in message or f".{name}" in message or f"params.{name}" in message:
            field = f"body.params.{name}"
            break
    else:
        if "field '" in message:
            inner = message.split("field '", 1)[1].split("'", 1)[0]
            field = f"body.params.{inner}"
    return ProblemError(422, message, [FieldError(field=field, message=message)])


PAGE_HEADERS: dict[str, Any] = {
    "X-Total-Count": {
        "description": "the runs the filters select in the whole catalog (and the queue)",
        "schema": {"type": "integer"},
    },
    "Link": {
        "description": '`<URL>; rel="next"`: the next, older page (same filters), absent on the last page',
        "schema": {"type": "string"},
    },
}


@_route(
    "list_runs",
    response_model=list[RunDocument],
    responses={200: {"description": "a page of runs, oldest first", "headers": PAGE_HEADERS}},
)
def runs(
    request: Request, response: Response, who: Viewer, query: Annotated[RunListQuery, Query()]
) -> list[RunDocument]:
    page = _worker(request).runs_page(query, limit=query.limit, cursor=query.cursor)
    response.headers["X-Total-Count"] = str(page.total)
    if page.next_cursor is not None:
        params = [(k, v) for k, v in request.query_params.multi_items() if k != "cursor"]
        older = request.url.replace(query=urlencode([*params, ("cursor", page.next_cursor)]))
        response.headers["Link"] = f'<{older}>; rel="next"'
    return page.runs


@_route("show_run", response_model=RunDocument)
def run(run_id: RunId, request: Request, who: Viewer) -> RunDocument:
    return _run(request, run_id)


@_route("abort_run", response_model=RunDocument)
def abort_run(run_id: RunId, request: Request, who: Operator) -> RunDocument:
    _worker(request).abort_run(run_id)
    _audit(request, who, "abort", run_id)
    return _run(request, run_id)


@_route(
    "export_run",
    response_class=FileResponse,
    responses={200: {"content": {t: {} for t in MEDIA_TYPES.values()}, "description": "the samples"}},
)
def run_data(
    run_id: RunId,
    request: Request,
    who: Viewer,
    format: Annotated[Literal["parquet", "csv", "mat"], Query(description="file format")] = "parquet",
    columns: Annotated[
        str | None, Query(description="comma-separated column names (t is always included)", max_length=2000)
    ] = None,
    t0: Annotated[float | None, Query(description="first time to include [s]", allow_inf_nan=False)] = None,
    t1: Annotated[float | None, Query(description="last time to include [s]", allow_inf_nan=False)] = None,
) -> FileResponse:
    assert format in EXPORT_FORMATS
    _run(request, run_id)  # 404 when unknown (a queued run too: it has no samples yet)
    asked = [c.strip() for c in columns.split(",") if c.strip()] if columns else None
    folder = Path(tempfile.mkdtemp(prefix="hdrig-download-"))
    try:
        path = actions.download_run(_store(request), run_id, format, folder, asked, t0, t1)
    except UserInputError as exc:
        shutil.rmtree(folder, ignore_errors=True)
        if isinstance(exc, actions.FieldInputError):
            raise _field_problem(exc, "query") from None
        raise
    return FileResponse(
        path,
        media_type=MEDIA_TYPES[format],
        filename=path.name,
        background=BackgroundTask(shutil.rmtree, folder, ignore_errors=True),
    )


@_route("run_artifacts", response_model=FileList)
def run_artifacts(run_id: RunId, request: Request, who: Viewer) -> FileList:
    _run(request, run_id)
    return FileList(files=_files(_store(request).run_dir(run_id) / ARTIFACTS_DIR))


@_route("run_artifact", response_class=FileResponse)
def run_artifact(run_id: RunId, path: str, request: Request, who: Viewer) -> FileResponse:
    _run(request, run_id)
    return FileResponse(_inside(_store(request).run_dir(run_id) / ARTIFACTS_DIR, path))


@_route(
    "run_events",
    response_class=StreamingResponse,
    responses={200: {"content": {"text/event-stream": {}}, "description": "the event stream"}},
)
def run_events(
    run_id: RunId,
    request: Request,
    who: Viewer,
    last_event_id: Annotated[
        str | None, Header(alias="Last-Event-ID", description="resume after this event id", max_length=20)
    ] = None,
) -> StreamingResponse:
    document = _run(request, run_id)  # 404 before the stream starts
    worker = _worker(request)
    try:
        after = max(0, int(last_event_id)) if last_event_id else worker.events.start_of(run_id)
    except ValueError:
        raise ProblemError(422, f"Last-Event-ID {last_event_id!r} is not an event id") from None
    return StreamingResponse(
        _event_stream(worker, run_id, after, document, resumed=bool(last_event_id)),
        media_type="text/event-stream",
        headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"},
    )


def _sse(event_id: int, kind: str, data: dict[str, Any]) -> str:
    return f"id: {event_id}\nevent: {kind}\ndata: {json.dumps(data, allow_nan=False, default=str)}\n\n"


def _final(event: Event, run_id: str) -> bool:
    return event.kind == EventKind.RUN and event.run_id == run_id and RunStatus(event.data["status"]).finished


async def _event_stream(
    worker: RigWorker, run_id: str, after: int, document: RunDocument, resumed: bool
) -> AsyncIterator[str]:
    """The run's events newer than `after`, until its final `run` event, or the `closed` event of a
    service going away (its last word, saying why). A client that goes away only ends this generator:
    the run goes on."""
    loop = asyncio.get_running_loop()
    quiet_since = loop.time()
    if document.status.finished and not any(
        _final(e, run_id) for e in worker.events.since(0, run_id, limit=10**9)
    ):
        # Recorded before this service started (or its events have left the log): say how it ended.
        if not resumed or after < worker.events.last_id:
            yield _sse(worker.events.last_id, EventKind.RUN, _clean(document.as_json()))
        return
    while True:
        events = worker.events.since(after, run_id)
        for event in events:
            after = event.id
            if event.kind == EventKind.CLOSED:
                yield _sse(event.id, event.kind, event.data)
                return
            if event.kind not in STREAM_KINDS:
                continue
            yield _sse(event.id, event.kind, _clean(event.data))
            quiet_since = loop.time()
            if _final(event, run_id) and worker.closing_reason is None:
                return  # (a service going away still says so: its `closed` event follows shortly)
        if not events and worker.closed is not None:  # closed before this stream began
            yield _sse(worker.closed.id, EventKind.CLOSED, worker.closed.data)
            return
        if not events:
            if loop.time() - quiet_since >= KEEP_ALIVE_S:
                quiet_since = loop.time()
                yield ": keep-alive\n\n"
            await asyncio.sleep(STREAM_POLL_S)


def _clean(value: Any) -> Any:
    """JSON has no NaN or infinity (they travel as null) and no arrays (they travel as lists)."""
    if isinstance(value, float):
        return value if value == value and abs(value) != float("inf") else None
    if isinstance(value, dict):
        return {k: _clean(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_clean(v) for v in value]
    if isinstance(value, np.ndarray):  # the worker's decimated samples
        return _clean(value.tolist())
    return value


# ---- jobs, fits and gaps ------------------------------------------------------------------------------


@_route("list_jobs", response_model=list[JobDocument])
def jobs(
    request: Request,
    who: Viewer,
    limit: JobsLimit = MAX_PAGE,
) -> list[JobDocument]:
    every = sorted([*_worker(request).jobs(), *_analysis(request).jobs()], key=lambda job: job.created)
    return [job.document() for job in every[-limit:]]


@_route("show_job", response_model=JobDocument)
def job(job_id: JobId, request: Request, who: Viewer) -> JobDocument:
    return _job(request, job_id).document()


def _start_analysis(
    request: Request, response: Response, who: Principal, kind: JobKind, body: AnalysisRequest
) -> JobDocument:
    store = _store(request)
    model = model_ref(store, body.model, "body.model")  # a name: presets and uploaded models only
    job = operations.start_analysis(_analysis(request), store, kind, body, model, owner=who.name)
    _audit(request, who, str(kind), job.id, json.dumps(body.model_dump(mode="json")))
    route = operations.operation(kind).rest
    assert route is not None
    _accepted(response, f"{API}{route[1]}/{job.id}")
    return job.document()


def _analysis_job(request: Request, job_id: str, kind: JobKind) -> JobDocument:
    """The job of this service, or an analysis of this kind that ended before it started (404 if neither)."""
    try:
        found = _analysis(request).job(job_id)
    except UnknownJobError:
        finished = actions.finished_analysis(_store(request), job_id, kind)
        if finished is not None:
            return finished
    else:
        if found.kind == kind:
            return found.document()
    raise ProblemError(404, f"unknown {kind} job id {job_id!r}")


def _analysis_routes(kind: JobKind) -> None:
    """The routes of a fit and of a gap analysis, alike: start one, its job, its files, one file."""

    def start(body: AnalysisRequest, request: Request, response: Response, who: Operator) -> JobDocument:
        return _start_analysis(request, response, who, kind, body)

    def job(job_id: JobId, request: Request, who: Viewer) -> JobDocument:
        return _analysis_job(request, job_id, kind)

    def files(job_id: JobId, request: Request, who: Viewer) -> FileList:
        _analysis_job(request, job_id, kind)
        return FileList(files=_files(actions.analysis_folder(_store(request), job_id)))

    def file(job_id: JobId, path: str, request: Request, who: Viewer) -> FileResponse:
        _analysis_job(request, job_id, kind)
        return FileResponse(_inside(actions.analysis_folder(_store(request), job_id), path))

    # Named as the routes were when written out one by one: their OpenAPI operation ids stay the same.
    for route, name, options in (
        (start, f"start_{kind}", {"response_model": JobDocument}),
        (job, f"{kind}_job", {"response_model": JobDocument}),
        (files, f"{kind}_files", {"response_model": FileList}),
        (file, f"{kind}_file", {"response_class": FileResponse}),
    ):
        route.__name__ = name
        _route(str(kind) if name.startswith("start_") else name, **options)(route)


for _kind in (JobKind.FIT, JobKind.GAPS):
    _analysis_routes(_kind)


# ---- keys and the audit log (admin) -------------------------------------------------------------------


@_route(
    "list_keys",
    response_model=list[KeyInfo],
    responses={
        200: {
            "description": "every key, live and revoked, oldest first",
            # The oldest key (the first start's admin key, often) revoked by name: 409 while it is the
            # last live admin key. Stateful clients (and schemathesis) follow this.
            "links": {
                "RevokeOldestKey": {
                    "operationRef": "#/paths/~1api~1v1~1keys~1{name}/delete",
                    "parameters": {"name": "$response.body#/0/name"},
                }
            },
        }
    },
)
def keys(request: Request, who: Admin) -> list[KeyInfo]:
    return access.list_keys(_store(request))


@_route(
    "create_key",
    response_model=NewKey,
    responses={
        201: {
            "description": "the key, shown this once",
            # The key made can be revoked by its name: stateful clients (and schemathesis) follow this.
            "links": {
                "RevokeKey": {
                    "operationRef": "#/paths/~1api~1v1~1keys~1{name}/delete",
                    "parameters": {"name": "$response.body#/name"},
                }
            },
        }
    },
)
def create_key(body: KeyRequest, request: Request, who: Admin) -> NewKey:
    name, token = access.make_key(_store(request), body.role, body.name, who.name, who.role, door="api")
    return NewKey(name=name, role=body.role, key=token)  # audited by make_key, in its transaction


@_route("revoke_key", response_model=KeyInfo)
def revoke_key(name: Annotated[str, PathParam(max_length=200)], request: Request, who: Admin) -> KeyInfo:
    store = _store(request)
    if name not in {key.name for key in access.list_keys(store)}:
        raise ProblemError(404, f"unknown key name {name[:80]!r}")
    try:  # audited by revoke_key, in its transaction
        return access.revoke_key(store, name, who.name, who.role, door="api")
    except access.KeyConflictError as exc:
        raise ProblemError(409, str(exc)) from None


@_route("audit", response_model=list[AuditEntry])
def audit(
    request: Request,
    who: Admin,
    limit: AuditLimit = 100,
) -> list[AuditEntry]:
    return access.audit_log(_store(request), limit)


# ---- the application --------------------------------------------------------------------------------


def _page() -> HTMLResponse | FileResponse:
    index = STATIC_DIR / "index.html"
    if index.is_file():
        return FileResponse(index, media_type="text/html")
    return HTMLResponse(
        "<!doctype html><title>hdrig</title><p>hdrig: the page is not installed; the API is at"
        " <a href='/docs'>/docs</a>.</p>"
    )


def stop_service(app: FastAPI, why: str) -> None:
    """The service is going away (`hdrig serve` calls this on SIGTERM, SIGINT or SIGHUP, before uvicorn
    waits on anything): the motor stops now, on the calling thread; then, on a thread of its own, the
    queue is cancelled, no job is taken any more, the run playing is sealed `aborted: <why>` (up to
    SEAL_WAIT_S) and every event stream ends with a `closed` event saying why. Safe to call again."""
    worker: RigWorker | None = getattr(app.state, "worker", None)
    if worker is None:  # still opening the rig: nothing can be moving yet
        return
    worker.rig.quick_stop(why)
    threading.Thread(
        target=worker.shutdown, args=(why, SEAL_WAIT_S), name="hdrig-service-stop", daemon=True
    ).start()


def create_app(rig_config: RigConfig, store: RunStore) -> FastAPI:
    """The service for one rig: the lifespan opens the rig (RigWorker) and the analysis worker and
    closes them at shutdown (a run still playing is quick-stopped and kept, `aborted`), waiting at most
    CLOSE_WAIT_S for each worker's thread."""

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        app.state.stop_lane = ThreadPoolExecutor(STOP_LANE_THREADS, thread_name_prefix="hdrig-stop")
        worker = await asyncio.to_thread(RigWorker, rig_config, store)
        app.state.worker = worker
        app.state.analysis = AnalysisWorker(worker.events)
        try:
            yield
        finally:
            app.state.analysis.close(CLOSE_WAIT_S)  # a fit still running is left to die with the process
            await asyncio.to_thread(worker.close, CLOSE_WAIT_S)
            app.state.stop_lane.shutdown(wait=False)

    app = FastAPI(
        title="hdrig",
        summary="Experiments, runs, fits and model gaps on one harmonic-drive test bench",
        version="1",
        lifespan=lifespan,
    )
    app.state.store = store
    app.state.sessions = Sessions()
    problems.install(app)
    app.state.login_limit = guard.LoginLimit()
    app.add_middleware(guard.Guard, limit=app.state.login_limit)
    app.include_router(router)
    app.add_api_route("/", _page, include_in_schema=False, response_model=None)
    app.mount("/static", StaticFiles(directory=STATIC_DIR, check_dir=False), name="static")
    app.openapi = lambda: _openapi(app)  # type: ignore[method-assign]
    # Outermost: every JSON answer, errors included, leaves without the server's paths.
    app.add_middleware(HideServerPaths, scrubber=PathScrubber(store.home, store.models_dir))
    return app


class _Served:
    """This service, as `hdrig serve` finds it (`rig.lab.BUILTIN_SERVICE_DOORS`)."""

    def create_app(self, config: RigConfig, store: RunStore) -> FastAPI:
        return create_app(config, store)

    def stop_service(self, app: Any, why: str) -> None:
        stop_service(app, why)


SERVED_APP: ServedApp = _Served()


def _openapi(app: FastAPI) -> dict[str, Any]:
    """FastAPI's document, with errors told as what they are: application/problem+json."""
    if app.openapi_schema:
        return app.openapi_schema
    schema = get_openapi(title=app.title, version=app.version, summary=app.summary, routes=app.routes)
    for path in schema.get("paths", {}).values():
        for operation in path.values():
            for status, answer in operation.get("responses", {}).items():
                if status.startswith(("4", "5")):
                    answer["content"] = {
                        problems.PROBLEM_MEDIA_TYPE: {"schema": {"$ref": "#/components/schemas/Problem"}}
                    }
    components = schema.setdefault("components", {}).setdefault("schemas", {})
    components.pop("HTTPValidationError", None)
    components.pop("ValidationError", None)
    if "Problem" not in components:
        components["Problem"] = Problem.model_json_schema(ref_template="#/components/schemas/{model}")
    app.openapi_schema = schema
    return schema


def iter_routes(app: FastAPI) -> Iterator[tuple[str, str]]:
    """(method, path) of every route the app answers (the tests walk them all)."""
    yield from _routes(app.routes)


def _routes(routes: list[Any]) -> Iterator[tuple[str, str]]:
    for route in routes:
        included = getattr(route, "original_router", None)  # FastAPI ≥ 0.120 keeps included routers whole
        if included is not None:
            yield from _routes(included.routes)
            continue
        for method in sorted(getattr(route, "methods", None) or []):
            if method != "HEAD":
                yield method, route.path
