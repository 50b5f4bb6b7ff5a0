"""What a user can do with hdrig, one function per action, for the command line and the service alike.

Each takes validated inputs and returns a document (`rig.core.documents`); neither the CLI nor the
service adds logic of its own. Bad input raises `model.errors.UserInputError` (one line); a device
fault ends the run `aborted: <fault>`; anything else is a bug and propagates.

Where fit and gaps write: each analysis has its own folder in the store, `$HDRIG_HOME/analyses/<id>/`,
holding `result.json` (the document) and the model it produced as `model.yaml`; `out=` writes the
model to that file instead, `report_dir=` writes the report (plots, tables, summary) into that folder
(the service always asks for one, inside the analysis folder).
"""

from __future__ import annotations

import json
import logging
import re
from collections.abc import Callable, Sequence
from dataclasses import replace
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml
from pydantic import ValidationError

from model.errors import UserInputError, describe_validation_error
from model.params import load_model, parse_model, preset_names
from model.run import Run
from rig.config import RigConfig
from rig.core.documents import (
    ExperimentInfo,
    FitDocument,
    FitError,
    FitParameter,
    GapsDocument,
    GapStepDocument,
    JobDocument,
    JobKind,
    JobStatus,
    LabQuantityDocument,
    ModelSummary,
    PlannedRun,
    RunDocument,
    RunPage,
    RunPlan,
    TrendDocument,
)
from rig.core.trend import plot_trend, trend_document
from rig.experiments import CAMPAIGN, CAMPAIGN_ORDER, EXPERIMENTS, experiment_named
from rig.experiments.base import RIG_CONTEXT, ExperimentParams, RigContext
from rig.experiments.endurance import EnduranceParams
from rig.faults import DeviceFaultError
from rig.interface import ModeRefusedError, Rig
from rig.runner import Progress, RunHooks, RunOutcome, analyze_stored, make_params, run_experiment
from rig.status import RunStatus
from rig.store.catalog import DEFAULT_PAGE, Cursor, page_of_runs
from rig.store.importmap import parse_mapping
from rig.store.runfile import json_text
from rig.store.runs import (
    ARTIFACTS_DIR,
    AnalysisState,
    RunQuery,
    RunStore,
    UnknownColumnError,
    check_tags,
    load_runs,
    new_run_id,
    query_of,
    run_filter,
)

if TYPE_CHECKING:
    from rig.analysis.gaps import GapsResult
    from rig.analysis.identification import Identification

logger = logging.getLogger(__name__)

ANALYSES_DIR = "analyses"
RESULT_FILE = "result.json"
MODEL_FILE = "model.yaml"
REPORT_DIR = "report"  # the service's analyses write their report here, inside their folder
JOB_FILE = "job.json"  # an analysis' job record: id, kind, created


# ---- models and experiments ---------------------------------------------------------------------


def list_models() -> list[ModelSummary]:
    """The presets in configs/models."""
    out = []
    for name in preset_names():
        model = load_model(name)
        out.append(ModelSummary(name=name, effects=list(model.effects), description=model.description))
    return out


def show_model(name_or_file: str) -> dict[str, Any]:
    """A model as a model file's content: every parameter by its docs/MODEL.md name."""
    return load_model(name_or_file).to_dict()


def list_experiments() -> list[ExperimentInfo]:
    """Each experiment with the JSON Schema of its parameters."""
    return [
        ExperimentInfo(name=e.name, summary=e.summary, params_schema=e.Params.model_json_schema())
        for e in EXPERIMENTS.values()
    ]


def kept_model(store: RunStore, name: str) -> str | None:
    """What the core loads for a model named over HTTP: a preset's name, or the file the store keeps for
    an uploaded one; None for anything else (no file of the server is named over HTTP)."""
    if name in preset_names():
        return name
    path = store.model_file(name)
    return str(path) if path is not None else None


def list_kept_models(store: RunStore) -> list[ModelSummary]:
    """The presets, then the models uploaded into the store (`GET /api/v1/models`)."""
    out = list_models()
    for name in store.model_names():
        path = store.model_file(name)
        if name in preset_names() or path is None:
            continue
        model = load_model(str(path))
        out.append(ModelSummary(name=name, effects=list(model.effects), description=model.description))
    return out


def keep_model(store: RunStore, name: str, content: dict[str, Any], where: str) -> dict[str, Any]:
    """Keep a model file's `content` in the store under `name` (`POST /api/v1/models`); the model as kept.
    A name in use is a ConflictError; a bad model a FieldInputError naming `model` (`where` is how the
    message names the content)."""
    if kept_model(store, name) is not None:
        raise ConflictError(f"model name {name!r} is taken (GET /api/v1/models lists them)")
    try:
        parsed = parse_model(content, where)
    except UserInputError as exc:
        raise FieldInputError("model", str(exc)[:500]) from None
    try:
        store.keep_model(name, yaml.safe_dump(parsed.to_dict(), sort_keys=False))
    except UserInputError as exc:  # taken meanwhile by another upload
        raise ConflictError(str(exc)) from None
    return parsed.to_dict()


# ---- planning and running -----------------------------------------------------------------------


def plan_run(
    experiment: str,
    params: dict[str, Any] | None = None,
    keep_going: bool = False,
    experiments: Sequence[str] = CAMPAIGN_ORDER,
    unit: str | None = None,
    tags: Sequence[str] = (),
    rig: Rig | None = None,
) -> RunPlan:
    """Validate a start request before the rig is touched.

    One experiment takes its parameters (`{"hold_s": 0.5}`); the campaign takes them per experiment
    (`{"speed-sweep": {"hold_s": 0.5}}`) and plays `experiments` in turn (all of them by default).
    Unknown experiments and bad values are one-line errors. `unit` (the gear on the bench, instead of
    the rig file's) and free `tags` go into the catalog with each run. Given the `rig` the plan is for,
    the whole plan is also checked against it (`check_plan`): speeds within its saturation, every segment
    within its limits and travel, before anything moves.
    """
    tags = check_tags(tags)
    if unit is not None:
        check_tags([unit])  # a serial number: the same characters as a tag
    given = dict(params or {})
    if experiment == CAMPAIGN:
        unknown = sorted(set(given) - set(CAMPAIGN_ORDER))
        if unknown:
            raise UserInputError(
                f"run campaign: params.{unknown[0]} is not an experiment (one of {', '.join(CAMPAIGN_ORDER)})"
            )
        for name in experiments:
            experiment_named(name)
        names: Sequence[str] = experiments
    else:
        experiment_named(experiment)
        names, given = [experiment], {experiment: given}
    runs = []
    for name in names:
        values = given.get(name) or {}
        if not isinstance(values, dict):
            raise UserInputError(f"run campaign: params.{name} must be an object of parameters")
        if rig is None:
            checked = make_params(EXPERIMENTS[name], values)
        else:
            checked = _params_for_rig(name, values, rig.config)
        runs.append(PlannedRun(experiment=name, params=checked.model_dump(mode="json")))
    plan = RunPlan(experiment=experiment, runs=runs, keep_going=keep_going, unit=unit, tags=list(tags))
    if rig is not None:
        check_plan(plan, rig)
    return plan


def _params_for_rig(name: str, values: dict[str, Any], config: RigConfig) -> ExperimentParams:
    """An experiment's parameters validated with the rig in the context (its saturation named per field)."""
    try:
        return EXPERIMENTS[name].Params.model_validate(values, context={RIG_CONTEXT: config})
    except ValidationError as exc:
        raise UserInputError(f"run {name}: {describe_validation_error(exc)}") from None


def check_plan(plan: RunPlan, rig: Rig) -> None:
    """Build every run's program against `rig` as it plays from its home (θ_m = 0, or the nearest end of
    its travel) and refuse, before anything moves, one it could not play: segments beyond the rig's
    saturation or travel, a stroke that does not fit, repeated segments. The runner checks the program
    again from where the motor really is when the run starts."""
    limits = rig.config.limits
    lowest, highest = limits.travel_min_out_rad / rig.gear_ratio, limits.travel_max_out_rad / rig.gear_ratio
    home = min(max(0.0, lowest), highest)
    ctx = RigContext(rig.config, rig.gear_ratio, rig.torque_constant_nm_per_a, home)
    for planned in plan.runs:
        experiment = EXPERIMENTS[planned.experiment]
        params = make_params(experiment, planned.params)
        if isinstance(params, EnduranceParams):
            # Its program repeats one checkpoint and one duty stretch for hours (minutes to build for
            # 10,000 h): the first two checkpoints hold every kind of segment it plays.
            two = 2.0 * params.checkpoint_every_min / 60.0
            params = params.model_copy(update={"duration_h": min(params.duration_h, two)})
        where = f"run {planned.experiment}"
        try:
            rig.check_modes(experiment.needs)
        except ModeRefusedError:
            continue  # refused alone when its turn comes (a campaign goes on without it)
        try:
            program = experiment.program(params, ctx)
            labels = [seg.label for seg in program]
            if len(set(labels)) != len(labels):
                repeated = next(label for label in labels if labels.count(label) > 1)
                raise UserInputError(f"the program plays segment {repeated!r} twice: a value is repeated")
            for segment in program:
                rig.check_segment(segment)
        except UserInputError as exc:
            text = str(exc)
            raise UserInputError(text if text.startswith(where) else f"{where}: params: {text}") from None


def params_from_pairs(experiment: str, pairs: Sequence[str]) -> dict[str, Any]:
    """The command line's `--set key=value` pairs as `plan_run` params; values are YAML scalars or lists.

    A single experiment takes `key=value`; the campaign takes `experiment.key=value`.
    """
    params: dict[str, Any] = {}
    for pair in pairs:
        key, sep, text = pair.partition("=")
        if not sep or not key.strip():
            raise UserInputError(f"run {experiment}: --set {pair!r} is not key=value")
        try:
            value = _exponents(yaml.safe_load(text))
        except yaml.YAMLError:
            raise UserInputError(f"run {experiment}: --set {pair!r}: the value is not YAML") from None
        key = key.strip()
        if experiment != CAMPAIGN:
            params[key] = value
            continue
        name, dot, field = key.partition(".")
        if not dot or name not in CAMPAIGN_ORDER:
            raise UserInputError(
                f"run campaign: --set {pair!r} must be EXPERIMENT.key=value,"
                f" EXPERIMENT one of {', '.join(CAMPAIGN_ORDER)}"
            )
        params.setdefault(name, {})[field] = value
    return params


_EXPONENT = re.compile(r"[-+]?(\d+\.?\d*|\.\d+)[eE][-+]?\d+")


def _exponents(value: Any) -> Any:
    """YAML 1.1 reads `1e6` as text (it wants `1.0e+6`); on the command line it is the number it looks like
    (parameters are strict: text is never taken for a number)."""
    if isinstance(value, str) and _EXPONENT.fullmatch(value.strip()):
        return float(value)
    if isinstance(value, list):
        return [_exponents(v) for v in value]
    return value


def execute_plan(
    plan: RunPlan,
    config: RigConfig,
    store: RunStore,
    rig: Rig | None = None,
    progress: Progress | None = None,
    hooks: RunHooks | None = None,
    on_run: Callable[[RunDocument], None] | None = None,
    should_continue: Callable[[], bool] = lambda: True,
    on_skip: Callable[[str, str], None] | None = None,
) -> list[RunDocument]:
    """Play a plan's runs in turn on `rig` (or on a fresh rig per run from `config`); each run's document.

    An experiment the rig cannot play (`ModeRefusedError`, before anything moves) is refused alone and
    skipped in a campaign: logged and told to `on_skip` (experiment, reason).
    A run that ends aborted stops a campaign unless the plan says keep_going; `should_continue` is asked
    before each run (an abort of the whole job). A device fault always stops it: once the run it ended
    is recorded and told (`on_run`), the fault is raised again for the caller to see.
    """
    documents: list[RunDocument] = []
    count = len(plan.runs)
    for index, planned in enumerate(plan.runs):
        if index and not should_continue():
            break
        report = None
        if progress is not None:
            report = _share_of(progress, index, count)
        run_hooks = replace(hooks or RunHooks(), unit=plan.unit, tags=list(plan.tags))
        if index:
            run_hooks = replace(run_hooks, run_id=None)
        try:
            outcome = run_experiment(
                planned.experiment, config, planned.params, store, report, rig, run_hooks
            )
        except ModeRefusedError as exc:
            if count == 1:
                raise
            # A campaign skips what this rig cannot play (told before anything moved) and goes on.
            logger.warning("campaign: %s skipped: %s", planned.experiment, exc)
            if on_skip is not None:
                on_skip(planned.experiment, str(exc))
            continue
        document = run_document(store, outcome.run_id, outcome)
        documents.append(document)
        if on_run is not None:
            on_run(document)
        if outcome.fault is not None:
            raise DeviceFaultError(outcome.fault)
        if outcome.status == RunStatus.ABORTED and not plan.keep_going:
            break
    return documents


def _share_of(progress: Progress, index: int, count: int) -> Progress:
    def report(label: str, fraction: float) -> None:
        progress(label, (index + fraction) / count)

    return report


def reserve_run_id(plan: RunPlan) -> str:
    """An id for the plan's first run before it starts (the service names queued runs)."""
    return new_run_id(plan.runs[0].experiment)


# ---- the catalog --------------------------------------------------------------------------------


def _artifacts(run_dir: Path) -> list[str]:
    folder = run_dir / ARTIFACTS_DIR
    return sorted(str(p) for p in folder.rglob("*") if p.is_file()) if folder.is_dir() else []


def _document(store: RunStore, entry: dict[str, Any], with_artifacts: bool) -> RunDocument:
    run_dir = store.run_dir(entry["id"])
    status = RunStatus(entry["status"])
    return RunDocument(
        id=entry["id"],
        experiment=entry["experiment"],
        status=status,
        reason=entry["reason"],
        rig=entry["rig"],
        model_name=entry["model_name"],
        model_hash=entry["model_hash"],
        started=entry["started"],
        ended=entry["ended"],
        samples=entry["samples"],
        progress=1.0 if status == RunStatus.COMPLETE else float(entry.get("progress") or 0.0),
        metrics=entry["metrics"],
        meta=entry["meta"],
        path=entry["path"],
        run_dir=str(run_dir),
        artifacts=_artifacts(run_dir) if with_artifacts else [],
        analysis=entry.get("analysis"),
        unit=entry.get("unit"),
        operator=entry.get("operator"),
        tags=entry.get("tags", []),
    )


def list_runs(
    store: RunStore,
    query: RunQuery | None = None,
    limit: int | None = DEFAULT_PAGE,
    cursor: str | None = None,
    **filters: Any,
) -> RunPage:
    """A page of the catalog: the newest `limit` runs (every one when None) before `cursor` (a page's
    `next_cursor`; from the newest when None) that `query` selects (or its fields given by name), oldest
    first, with the count of all it selects. A page is read from the catalog's summary columns (no
    metadata: `run_document` has it; no artifacts: `show_run` lists them)."""
    where = run_filter(query_of(query, filters))
    page = page_of_runs(store.catalog, where, limit, Cursor.decode(cursor) if cursor else None)
    documents = []
    for row in page.rows:
        if row["status"] == RunStatus.RUNNING or row["analysis"] == AnalysisState.RUNNING:
            # The store marks a run (or analysis) whose process has died `interrupted` when it reads it.
            entry = store.get(row["id"]) | {"meta": {}}
        else:
            entry = row | {
                "metrics": json.loads(row["metrics"]),
                "meta": {},
                "path": store.data.display(row["path"]),
                "tags": page.tags.get(row["id"], []),
            }
        documents.append(_document(store, entry, with_artifacts=False))
    older = page.older.encode() if page.older is not None else None
    return RunPage(runs=documents, total=page.total, next_cursor=older)


def run_document(store: RunStore, run_id: str, outcome: RunOutcome | None = None) -> RunDocument:
    """One run with its metrics and artifacts (`hdrig runs show`)."""
    document = _document(store, store.get(run_id), with_artifacts=True)
    if outcome is not None and outcome.reason and not document.reason:
        document.reason = outcome.reason
    return document


def analyze_run(store: RunStore, run_id: str) -> RunDocument:
    """Analyze a complete run again (`hdrig runs analyze`): tables, plots and metrics from its data, e.g.
    after an analysis was interrupted; the run's document with them."""
    outcome = analyze_stored(store, run_id)
    return run_document(store, outcome.run_id, outcome)


def export_run(store: RunStore, run_id: str, fmt: str, out: str | Path) -> Path:
    """Write a run as csv, parquet or mat (a folder gets `<id>.<fmt>`)."""
    store.get(run_id)  # an unknown id is told as such; a run whose writer died is sealed first
    target = Path(out)
    if not target.is_dir() and not target.parent.is_dir():
        raise UserInputError(f"--out {out}: the folder {target.parent} does not exist")
    return store.export(run_id, fmt, out)


class UnknownJobError(UserInputError):
    """No job with this id (HTTP 404)."""


class ConflictError(UserInputError):
    """The request conflicts with the present state: a name in use, a run that has ended (HTTP 409)."""


class FieldInputError(UserInputError):
    """Bad input that names the request's field it came from (`columns`, `t1`), for the service's 422."""

    def __init__(self, field: str, message: str) -> None:
        super().__init__(message)
        self.field = field


def download_run(
    store: RunStore,
    run_id: str,
    fmt: str,
    folder: Path,
    columns: Sequence[str] | None = None,
    t0: float | None = None,
    t1: float | None = None,
) -> Path:
    """Write some columns (`t` always) of a run's samples with t0 ≤ t ≤ t1 [s] as `folder/<id>.<fmt>`, a
    selection not checked as a run (`GET /api/v1/runs/{id}/data`); streamed from the row groups that hold
    them. An unknown column or t1 before t0 is a FieldInputError naming `columns` or `t1`."""
    if t0 is not None and t1 is not None and t1 < t0:
        raise FieldInputError("t1", f"t1={t1} is before t0={t0}")
    store.get(run_id)  # an unknown id is told as such; a run whose writer died is sealed first
    try:
        return store.export(run_id, fmt, folder, list(columns) if columns else None, t0, t1)
    except UnknownColumnError as exc:
        raise FieldInputError("columns", f"columns: {exc}") from None


# ---- identification and the gap workflow --------------------------------------------------------


def _analysis_folder(store: RunStore, kind: JobKind, analysis_id: str | None) -> Path:
    """A new analysis' folder, with its job record (`job.json`: its id, kind and when it began), so the
    kind of a finished analysis is read, not guessed from its id."""
    now = datetime.now(UTC)
    name = analysis_id or f"{now:%Y%m%d-%H%M%S}-{kind}-{new_run_id(kind)[-4:]}"
    folder = analysis_folder(store, name)
    folder.mkdir(parents=True, exist_ok=True)
    record = {"id": name, "kind": str(kind), "created": now.isoformat()}
    (folder / JOB_FILE).write_text(json.dumps(record, indent=2) + "\n")
    return folder


def analysis_folder(store: RunStore, job_id: str) -> Path:
    """Where the analysis `job_id` keeps its files (the folder need not exist)."""
    if not job_id or Path(job_id).name != job_id or job_id in (".", ".."):
        raise UnknownJobError(f"unknown job id {job_id[:80]!r}")
    return store.home / ANALYSES_DIR / job_id


def finished_analysis(store: RunStore, job_id: str, kind: JobKind) -> JobDocument | None:
    """The document of an analysis of this `kind` that ended before this process began (from its folder's
    job record and result), or None."""
    folder = analysis_folder(store, job_id)
    record, result = folder / JOB_FILE, folder / RESULT_FILE
    if not result.is_file():
        return None
    body = json.loads(result.read_text())
    if record.is_file():
        job = json.loads(record.read_text())
        recorded, created = job.get("kind"), datetime.fromisoformat(job["created"])
    else:  # made before analyses kept a job record: what its result holds says what it is
        recorded, created = _kind_of_result(body), datetime.fromtimestamp(folder.stat().st_mtime, UTC)
    if recorded != kind:
        return None
    ended = datetime.fromtimestamp(result.stat().st_mtime, UTC)
    return JobDocument(
        id=job_id, kind=kind, status=JobStatus.COMPLETE, created=created, ended=ended, result=body
    )


def _kind_of_result(body: Any) -> JobKind | None:
    """A fit's or a gap analysis' result by the fields its document always has; None for neither."""
    if not isinstance(body, dict):
        return None
    if {"parameters", "fit_error"} <= body.keys():
        return JobKind.FIT
    if {"steps", "initial_gap", "final_gap"} <= body.keys():
        return JobKind.GAPS
    return None


def _runs_for(data: Sequence[str], store: RunStore, mapping: Sequence[str] | None = None) -> list[Run]:
    if not data:
        raise UserInputError("data: name at least one run id, run file or `latest`")
    return load_runs(list(data), store, parse_mapping(mapping))


def _check_out(out: str | Path | None) -> None:
    """Before an analysis runs: its `--out` file can be written where it is asked for."""
    if out is not None and not Path(out).parent.is_dir():
        raise UserInputError(f"--out {out}: the folder {Path(out).parent} does not exist")


def _complete_only(runs: list[Run], store: RunStore, action: str) -> list[Run]:
    """Runs of the store that did not end complete lack segments the staged estimates read: refused."""
    for run in runs:
        run_id = run.meta.get("run_id")
        try:
            entry = store.get(str(run_id)) if run_id else None
        except UserInputError:  # a file from another store: its content is all there is to go by
            entry = None
        if entry is not None and entry["status"] != RunStatus.COMPLETE:
            raise UserInputError(
                f"{action}: run {run_id} is {entry['reason'] or entry['status']}:"
                f" {action} reads complete runs (an aborted or interrupted run lacks segments)"
            )
    return runs


def fit(
    data: Sequence[str],
    model: str,
    store: RunStore,
    out: str | Path | None = None,
    report_dir: str | Path | None = None,
    joint: bool = True,
    progress: Progress | None = None,
    analysis_id: str | None = None,
    mapping: Sequence[str] | None = None,
) -> FitDocument:
    """Identify the model's parameters from runs (store ids, files or `latest`); see the module doc.
    `mapping`: `--map` entries or mapping files for files with other column names (`rig.store.importmap`)."""
    from rig.analysis.identification import identify, save_identified  # numba, SciPy: paid by analyses only

    start = load_model(model)
    _check_out(out)
    runs = _complete_only(_runs_for(data, store, mapping), store, "fit")
    folder = _analysis_folder(store, JobKind.FIT, analysis_id)
    report = Path(report_dir) if report_dir is not None else None
    result = identify(runs, start, joint=joint, report_dir=report, progress=progress)
    save_identified(result, Path(out) if out is not None else folder / MODEL_FILE)
    document = fit_document(result, folder)
    (folder / RESULT_FILE).write_text(json_text(document.as_json(), indent=2) + "\n")
    return document


def find_gaps(
    data: Sequence[str],
    model: str,
    store: RunStore,
    out: str | Path | None = None,
    report_dir: str | Path | None = None,
    progress: Progress | None = None,
    analysis_id: str | None = None,
    mapping: Sequence[str] | None = None,
) -> GapsDocument:
    """The model-gap workflow on runs; the model with the effects added (if any) is written as the
    module says."""
    from rig.analysis.gaps import find_gaps as workflow  # numba, SciPy: paid by analyses only

    start = load_model(model)
    runs = _runs_for(data, store, mapping)
    folder = _analysis_folder(store, JobKind.GAPS, analysis_id)
    _check_out(out)
    model_out = Path(out) if out is not None else folder / MODEL_FILE
    result = workflow(runs, start, report_dir=report_dir, progress=progress, model_out=model_out)
    document = gaps_document(result, folder)
    (folder / RESULT_FILE).write_text(json_text(document.as_json(), indent=2) + "\n")
    return document


def fit_document(result: Identification, folder: Path | None = None) -> FitDocument:
    """The `fit --json` document of an identification."""
    from rig.analysis.identification.identify import FIT_METRIC  # numba, SciPy: paid by analyses only
    from rig.analysis.identification.lab_quantities import fitted_sigmas, lab_quantities

    return FitDocument(
        model_file=str(result.model_file),
        parameters={
            row.name: FitParameter(
                estimate=row.estimate,
                uncertainty=row.uncertainty,
                start=row.start,
                identifiable=row.identifiable,
                stage=row.stage,
                note=row.note,
            )
            for row in result.parameters
        },
        fit_error=FitError(metric=FIT_METRIC, before=result.fit_error_before, after=result.fit_error_after),
        validation=result.validation.table() if result.validation else None,
        report=str(result.report_file) if result.report_file else None,
        notes=list(result.notes),
        folder=str(folder) if folder else None,
        held_out=result.held_out,
        inverse_model=result.inverse_model,
        imported=list(result.imported),
        lab_quantities={
            q.name: LabQuantityDocument(**q.as_json())
            for q in lab_quantities(result.model, fitted_sigmas(result.parameters))
        },
    )


def gaps_document(result: GapsResult, folder: Path | None = None) -> GapsDocument:
    """The `gaps --json` document of a gap workflow's result."""
    return GapsDocument(
        metric=result.metric,
        initial_gap=result.initial_gap,
        steps=[
            GapStepDocument(
                effect=step.effect,
                gap_before=step.gap_before,
                gap_after=step.gap_after,
                evidence=step.evidence,
                parameters=dict(step.parameters),
            )
            for step in result.steps
        ],
        final_gap=result.final_gap,
        final_model=str(result.final_model) if result.final_model else None,
        verdict=result.verdict,
        unexplained=result.unexplained.line() if result.unexplained is not None else None,
        rejected=list(result.rejected),
        report=[str(p) for p in result.report],
        folder=str(folder) if folder else None,
    )


# ---- trends ---------------------------------------------------------------------------------------


def trend(
    store: RunStore,
    run_id: str | None = None,
    unit: str | None = None,
    plot_dir: str | Path | None = None,
    model: str | None = None,
) -> TrendDocument:
    """`hdrig trend`: the checkpoints of an endurance run, or of every run of a gear unit, against time
    and duty cycles, with the online tracker's level; `plot_dir` also gets the plots. `model`: a model
    file (or preset) whose `thermal` law brings each checkpoint's friction to its T_ref (issue 27)."""
    law, unscaled_nm = None, 0.0
    if model is not None:
        from rig.analysis.identification.thermal_stage import output_share_nm

        gear = load_model(model)
        law = gear.thermal
        if law is None:
            raise UserInputError(f"trend: model {model!r} has no thermal section (fit one from warm-up runs)")
        # The output side's share of F_c is neither warmed nor worn by the law: left as measured.
        unscaled_nm = output_share_nm(gear, 0.0)
    document = trend_document(store, run_id=run_id, unit=unit, law=law, unscaled_nm=unscaled_nm)
    if plot_dir is not None:
        document.plots = [str(p) for p in plot_trend(document, Path(plot_dir))]
    return document
