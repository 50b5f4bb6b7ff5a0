"""The action table: every operation a user can ask of hdrig, declared once.

Each row names the operation, the request model it takes, the core function that does it, the
document it answers with, the least role it needs over HTTP, whether it runs as a job, and the doors
it is offered through: the REST route (`api.app` registers its routes from these rows), the command
line's subcommand (`rig.cli`), the Python client's method (`api.client.HdrigClient`) and the
`rig.lab.Lab` method that both `LocalLab` and `api.remote_lab.RemoteLab` implement.
`tests/test_operations.py` fails when a door lacks an operation the table gives it, or offers one the
table does not know.

The request models the service and the command line share live here too (the service re-exports them
from `api.schemas`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal, TypeVar

from pydantic import BaseModel, ConfigDict, Field, StrictBool, StrictStr, ValidationError

from model.errors import UserInputError, describe_validation_error
from rig.core import access, actions
from rig.core.access import AuditEntry, KeyInfo, Role
from rig.core.documents import (
    ExperimentInfo,
    FitDocument,
    GapsDocument,
    JobDocument,
    JobKind,
    ModelSummary,
    RunDocument,
    RunPage,
    RunPlan,
    TrendDocument,
)
from rig.core.rig_status import RigStatus, rig_status_of
from rig.core.worker import AnalysisWorker, Job, RigWorker
from rig.interface import Rig
from rig.runner import Progress
from rig.store.runs import MODEL_NAME_PATTERN, RunQuery, RunStore

# ---- request models ---------------------------------------------------------------------------------


class Request(BaseModel):
    model_config = ConfigDict(extra="forbid")


class RunRequest(Request):
    """Start an experiment or the campaign (`hdrig run`, `POST /api/v1/runs`)."""

    experiment: StrictStr = Field(
        max_length=100, description="an experiment name (GET /api/v1/experiments), or `campaign`"
    )
    params: dict[str, Any] = Field(
        default_factory=dict,
        description="the experiment's parameters (defaults for those not given); for `campaign`, an object"
        " per experiment",
    )
    queue: StrictBool = Field(
        default=False,
        description="wait for the rig when it is busy, instead of 409 (429 when the queue is full)",
    )
    keep_going: StrictBool = Field(default=False, description="campaign: go on after a run aborts")
    unit: StrictStr | None = Field(
        default=None,
        max_length=100,
        description="the gear unit's serial number on the bench (default: the rig file's `unit:`)",
    )
    tags: list[StrictStr] = Field(
        default_factory=list, max_length=50, description="free tags put on each run, to search the catalog by"
    )


class AnalysisRequest(Request):
    """A fit or a gap analysis (`POST /api/v1/fits`, `POST /api/v1/gaps`)."""

    data: list[Annotated[StrictStr, Field(max_length=200)]] = Field(
        min_length=1, max_length=100, description="run ids in the store, or `latest`"
    )
    model: StrictStr = Field(
        min_length=1, max_length=200, description="the starting model: a preset name (GET /api/v1/models)"
    )


@dataclass(frozen=True)
class AnalysisOrder:
    """A fit or a gap analysis as the command line asks for it (`rig.lab.Lab.fit`, `find_gaps`): the
    request, and where its results go on this machine."""

    data: Sequence[str]
    model: str
    out: str | Path | None = None  # the model made: this file (default: the analysis' folder)
    report_dir: str | Path | None = None  # the report: this folder (default: none)
    mapping: Sequence[str] | None = None  # `--map` entries for files with other column names
    joint: bool = True  # fit: refine the determined parameters together


class ModelUpload(Request):
    """A model file's content, kept in the store under `name` for runs and fits to name."""

    name: str = Field(
        pattern=f"^{MODEL_NAME_PATTERN.pattern}$",
        max_length=64,
        description="1-64 letters, digits, '_' or '-': what runs (`params.model`) and fits (`model`) name",
    )
    model: dict[str, Any] = Field(description="the model file's content (as `GET /api/v1/models/{name}`)")


class KeyRequest(Request):
    role: Role = Field(
        description="viewer reads; operator also starts, aborts and stops; admin also manages keys"
    )
    name: StrictStr | None = Field(
        default=None, max_length=100, description="the key's name (default ROLE-N)"
    )


Asked = TypeVar("Asked", bound=BaseModel)


def asked(model: type[Asked], **fields: Any) -> Asked:
    """A request built on this machine (the command line's), its bad values one `UserInputError`."""
    try:
        return model(**fields)
    except ValidationError as exc:
        raise UserInputError(describe_validation_error(exc)) from None


def plan_of(request: RunRequest, rig: Rig | None = None) -> RunPlan:
    """`actions.plan_run` for a start request (and, given, the rig it is for)."""
    return actions.plan_run(
        request.experiment,
        request.params,
        keep_going=request.keep_going,
        unit=request.unit,
        tags=request.tags,
        rig=rig,
    )


def start_analysis(
    worker: AnalysisWorker,
    store: RunStore,
    kind: JobKind,
    request: AnalysisRequest,
    model: str,
    owner: str | None = None,
) -> Job:
    """A fit or gap analysis of runs of `store` started on `worker` (the service's), `model` as the core
    loads it (`actions.kept_model`); its report goes into the analysis' folder (`actions.REPORT_DIR`).
    Every run is looked up first (UnknownRunError naming it): the service reads only its own store."""
    for ref in request.data:
        if ref != "latest":
            store.get(ref)
    call = operation(str(kind)).call
    data = list(request.data)

    def work(progress: Progress, job_id: str) -> Any:
        report = actions.analysis_folder(store, job_id) / actions.REPORT_DIR
        return call(data, model, store, report_dir=report, progress=progress, analysis_id=job_id)

    return worker.submit(kind, request.model_dump(mode="json"), work, owner=owner)


# ---- the table ----------------------------------------------------------------------------------------

Method = Literal["GET", "POST", "DELETE"]


@dataclass(frozen=True)
class Operation:
    """One operation and the doors it is offered through (None: not through that door)."""

    name: str
    summary: str
    request: type[BaseModel] | type[RunQuery] | type[AnalysisOrder] | None
    call: Callable[..., Any]  # the core function (or worker method) that does it
    document: Any  # what it answers with
    role: Role  # the least role over HTTP
    job: JobKind | None = None  # it runs as a job of this kind (its request is accepted with 202)
    rest: tuple[Method, str] | None = None  # (method, path under /api/v1)
    cli: str | None = None  # the subcommand: "runs list"
    client: str | None = None  # the HdrigClient method
    lab: str | None = None  # the rig.lab.Lab method
    tag: str = "runs"  # the OpenAPI tag its route is listed under
    status: int = 200  # the route's success status
    notes: tuple[str, ...] = field(default=())


def _analysis_rows(kind: JobKind, call: Callable[..., Any], document: type[BaseModel]) -> list[Operation]:
    """A fit and a gap analysis are offered alike: start, the job, its files, one file."""
    noun = "fit" if kind == JobKind.FIT else "gap analysis"
    root = "/fits" if kind == JobKind.FIT else "/gaps"
    name = str(kind)
    return [
        Operation(
            name,
            f"start a {noun}",
            AnalysisRequest,
            call,
            document,
            Role.OPERATOR,
            job=kind,
            rest=("POST", root),
            cli=name,
            client=name,
            lab="fit" if kind == JobKind.FIT else "find_gaps",
            tag=name,
            status=202,
        ),
        Operation(
            f"{name}_job",
            f"a {'fit' if kind == JobKind.FIT else 'gap'} job and its result",
            None,
            actions.finished_analysis,
            JobDocument,
            Role.VIEWER,
            rest=("GET", f"{root}/{{job_id}}"),
            tag=name,
        ),
        Operation(
            f"{name}_files",
            f"a {noun}'s files",
            None,
            actions.analysis_folder,
            list[str],
            Role.VIEWER,
            rest=("GET", f"{root}/{{job_id}}/files"),
            client="files",
            tag=name,
        ),
        Operation(
            f"{name}_file",
            f"one file of a {noun}",
            None,
            actions.analysis_folder,
            Path,
            Role.VIEWER,
            rest=("GET", f"{root}/{{job_id}}/files/{{path:path}}"),
            client="download_file",
            tag=name,
        ),
    ]


OPERATIONS: tuple[Operation, ...] = (
    # ---- the rig
    Operation(
        "rig_status",
        "the rig, its state and health",
        None,
        rig_status_of,
        RigStatus,
        Role.VIEWER,
        rest=("GET", "/rig"),
        client="rig",
        tag="rig",
    ),
    Operation(
        "stop",
        "stop everything now",
        None,
        RigWorker.quick_stop,
        RigStatus,
        Role.OPERATOR,
        rest=("POST", "/rig/stop"),
        client="stop",
        tag="rig",
        status=202,
    ),
    Operation(
        "reset",
        "leave the faulted state",
        None,
        RigWorker.reset,
        RigStatus,
        Role.OPERATOR,
        rest=("POST", "/rig/reset"),
        client="reset",
        tag="rig",
    ),
    # ---- models and experiments
    Operation(
        "list_experiments",
        "the experiments",
        None,
        actions.list_experiments,
        list[ExperimentInfo],
        Role.VIEWER,
        rest=("GET", "/experiments"),
        client="experiments",
        lab="list_experiments",
    ),
    Operation(
        "list_models",
        "the models a run or a fit can name: presets and uploaded",
        None,
        actions.list_models,
        list[ModelSummary],
        Role.VIEWER,
        rest=("GET", "/models"),
        cli="model list",
        client="models",
        lab="list_models",
        tag="fits",
    ),
    Operation(
        "show_model",
        "one model as a model file (`hdrig model show --json`)",
        None,
        actions.show_model,
        dict[str, Any],
        Role.VIEWER,
        rest=("GET", "/models/{name}"),
        cli="model show",
        client="model",
        lab="show_model",
        tag="fits",
    ),
    Operation(
        "upload_model",
        "upload a model (kept by name; 409 when the name is taken)",
        ModelUpload,
        RunStore.keep_model,
        dict[str, Any],
        Role.OPERATOR,
        rest=("POST", "/models"),
        tag="fits",
        status=201,
    ),
    Operation(
        "simulate",
        "simulate or replay a model open loop",
        None,
        actions.show_model,  # the model is read by the core; the simulator is the model's own
        None,
        Role.VIEWER,
        cli="simulate",
    ),
    # ---- runs
    Operation(
        "start_run",
        "start an experiment (or the campaign)",
        RunRequest,
        actions.plan_run,
        RunDocument | JobDocument,
        Role.OPERATOR,
        job=JobKind.RUN,
        rest=("POST", "/runs"),
        cli="run",
        client="start_run",
        lab="run",
        status=202,
    ),
    Operation(
        "list_runs",
        "the catalog, a page at a time, and queued runs",
        RunQuery,
        RigWorker.runs_page,
        RunPage,
        Role.VIEWER,
        rest=("GET", "/runs"),
        cli="runs list",
        client="runs_page",
        lab="list_runs",
    ),
    Operation(
        "show_run",
        "one run",
        None,
        RigWorker.run_document,
        RunDocument,
        Role.VIEWER,
        rest=("GET", "/runs/{run_id}"),
        cli="runs show",
        client="run",
        lab="run_document",
    ),
    Operation(
        "abort_run",
        "stop a run",
        None,
        RigWorker.abort,
        RunDocument,
        Role.OPERATOR,
        rest=("POST", "/runs/{run_id}/abort"),
        client="abort",
        status=202,
    ),
    Operation(
        "analyze_run",
        "analyze a complete run again",
        None,
        actions.analyze_run,
        RunDocument,
        Role.OPERATOR,
        cli="runs analyze",
    ),
    Operation(
        "export_run",
        "the run's samples as a file",
        None,
        actions.download_run,
        Path,
        Role.VIEWER,
        rest=("GET", "/runs/{run_id}/data"),
        cli="runs export",
        client="download",
        lab="export_run",
    ),
    Operation(
        "run_artifacts",
        "the run's artifacts",
        None,
        actions.run_document,
        list[str],
        Role.VIEWER,
        rest=("GET", "/runs/{run_id}/artifacts"),
        client="artifacts",
    ),
    Operation(
        "run_artifact",
        "one artifact (a table, results.json, a plot)",
        None,
        actions.run_document,
        Path,
        Role.VIEWER,
        rest=("GET", "/runs/{run_id}/artifacts/{path:path}"),
        client="download_artifact",
    ),
    Operation(
        "run_events",
        "Server-Sent Events of a run: state, progress, samples, alarm, run",
        None,
        RigWorker.live_run,
        None,
        Role.VIEWER,
        rest=("GET", "/runs/{run_id}/events"),
        client="events",
    ),
    Operation(
        "trend",
        "the checkpoints of an endurance run or a gear unit against time",
        None,
        actions.trend,
        TrendDocument,
        Role.VIEWER,
        cli="trend",
    ),
    # ---- jobs, fits and gaps
    Operation(
        "list_jobs",
        "every job: runs, campaigns, fits, gaps",
        None,
        AnalysisWorker.jobs,
        list[JobDocument],
        Role.VIEWER,
        rest=("GET", "/jobs"),
        client="jobs",
        tag="jobs",
    ),
    Operation(
        "show_job",
        "one job",
        None,
        AnalysisWorker.job,
        JobDocument,
        Role.VIEWER,
        rest=("GET", "/jobs/{job_id}"),
        client="job",
        tag="jobs",
    ),
    *_analysis_rows(JobKind.FIT, actions.fit, FitDocument),
    *_analysis_rows(JobKind.GAPS, actions.find_gaps, GapsDocument),
    # ---- keys and the audit log
    Operation(
        "list_keys",
        "every API key (never the key), oldest first",
        None,
        access.list_keys,
        list[KeyInfo],
        Role.ADMIN,
        rest=("GET", "/keys"),
        cli="keys list",
        tag="admin",
    ),
    Operation(
        "create_key",
        "make a key (shown once)",
        KeyRequest,
        access.make_key,
        "NewKey",
        Role.ADMIN,
        rest=("POST", "/keys"),
        cli="keys create",
        tag="admin",
        status=201,
    ),
    Operation(
        "revoke_key",
        "revoke a key (409: the last admin key)",
        None,
        access.revoke_key,
        KeyInfo,
        Role.ADMIN,
        rest=("DELETE", "/keys/{name}"),
        cli="keys revoke",
        tag="admin",
    ),
    Operation(
        "audit",
        "who did what, when",
        None,
        access.audit_log,
        list[AuditEntry],
        Role.ADMIN,
        rest=("GET", "/audit"),
        tag="admin",
    ),
)

BY_NAME = {operation.name: operation for operation in OPERATIONS}


def operation(name: str) -> Operation:
    """The row called `name` (a KeyError names a typo in a door's own declaration: a bug)."""
    return BY_NAME[name]
