"""The documents hdrig answers with: what `--json` prints and what the REST service returns.

One pydantic model per kind of answer, so the command line and the service say the same thing in the
same shape, and the service's OpenAPI schema is these models' field descriptions.
"""

from __future__ import annotations

from datetime import datetime
from enum import StrEnum
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from rig.status import RunStatus


class Document(BaseModel):
    """Base of every answer: `as_json()` is exactly what `--json` prints and the service returns."""

    model_config = ConfigDict(extra="forbid")

    def as_json(self) -> dict[str, Any]:
        return self.model_dump(mode="json")


class ModelSummary(Document):
    name: str = Field(description="preset name, usable as --model")
    effects: list[str] = Field(description="effect sections the model carries (docs/MODEL.md vocabulary)")
    description: str


class ExperimentInfo(Document):
    name: str = Field(description="experiment name, as in `hdrig run NAME`")
    summary: str = Field(description="what it plays and what it derives")
    params_schema: dict[str, Any] = Field(
        description="JSON Schema of its parameters: defaults, units, ranges"
    )


class PlannedRun(Document):
    experiment: str
    params: dict[str, Any] = Field(description="the experiment's parameters, validated, defaults filled in")


class RunPlan(Document):
    """What a start request asks for, validated before the rig is touched."""

    experiment: str = Field(description="an experiment name, or `campaign` for all of them in turn")
    runs: list[PlannedRun] = Field(description="the runs to play, in order")
    keep_going: bool = Field(default=False, description="campaign: go on after a run aborts")
    unit: str | None = Field(
        default=None, description="the gear unit's serial number on the bench (default: the rig file's)"
    )
    tags: list[str] = Field(default_factory=list, description="free tags put on each run, to search by")


class RunDocument(Document):
    """One run of the catalog (`hdrig runs show --json`, `GET /api/v1/runs/{id}`)."""

    id: str
    experiment: str
    status: RunStatus
    reason: str | None = Field(default=None, description="why it ended as it did (`aborted: ...`)")
    rig: str | None = None
    model_name: str | None = Field(default=None, description="the simulated plant's model (None on hardware)")
    model_hash: str | None = None
    started: str | None = Field(default=None, description="UTC, ISO 8601")
    ended: str | None = None
    samples: int = Field(default=0, description="samples on disk")
    progress: float = Field(default=0.0, ge=0.0, le=1.0, description="fraction of the run done")
    metrics: dict[str, Any] = Field(default_factory=dict, description="the analysis' scalar results")
    meta: dict[str, Any] = Field(
        default_factory=dict,
        description="the run's metadata (params, segments...); left out of listings (empty there): one"
        " run's document has it",
    )
    path: str | None = Field(default=None, description="the run's data file")
    run_dir: str | None = Field(default=None, description="the run's folder (data, artifacts/)")
    artifacts: list[str] = Field(default_factory=list, description="tables, results.json and plots")
    owner: str | None = Field(default=None, description="who started it (the API key's name; None: CLI)")
    unit: str | None = Field(default=None, description="the gear unit's serial number, as the run has it")
    operator: str | None = Field(
        default=None, description="who started it, as the catalog keeps it: an API key's name or the OS user"
    )
    tags: list[str] = Field(default_factory=list, description="free tags (`hdrig runs list --tag`)")
    analysis: str | None = Field(
        default=None,
        description="its analysis: running, done, interrupted (the process died: `hdrig runs analyze RUN`"
        " runs it again) or failed; None for a run that was not analyzed (aborted, or older)",
    )


class RunPage(Document):
    """A page of the catalog (`hdrig runs list`; `GET /api/v1/runs` answers with `runs` as its body, `total`
    as `X-Total-Count` and `next_cursor` in its `Link: <...>; rel="next"`)."""

    runs: list[RunDocument] = Field(
        description="the newest runs before the cursor (from the newest when none), oldest first; each"
        " without its `meta` and `artifacts`"
    )
    total: int = Field(ge=0, description="the runs the filters select in the whole catalog")
    next_cursor: str | None = Field(
        default=None, description="pass as `cursor` for the next, older page; None on the last page"
    )


class FitParameter(Document):
    estimate: float
    uncertainty: float | None = Field(description="1 σ; None when the data do not determine it")
    start: float = Field(description="the starting model's value")
    identifiable: bool
    stage: str = Field(description="the identification stage that set it")
    note: str = ""


class FitError(Document):
    metric: str
    before: float
    after: float


class LabQuantityDocument(Document):
    value: float
    sigma: float | None = Field(description="1 σ; None when a parameter it depends on is not determined")
    unit: str
    meaning: str = Field(description="what it is, in the model's parameters")


class FitDocument(Document):
    """`hdrig fit --json`; the result of a fit job."""

    model_file: str | None
    parameters: dict[str, FitParameter]
    fit_error: FitError
    validation: list[dict[str, Any]] | None = Field(description="the validation table, with a report")
    report: str | None = Field(description="report.md, when a report was asked for")
    notes: list[str]
    folder: str | None = Field(default=None, description="the analysis folder holding its files")
    held_out: dict[str, Any] | None = Field(
        default=None,
        description="fit error of each candidate model (start, staged, joint) on held-out shooting windows,"
        " and which one was kept (never worse than the start)",
    )
    inverse_model: dict[str, Any] | None = Field(
        default=None,
        description="runs without metadata: the plain inverse-model least squares (torque = M·a + F_v·v +"
        " F_c·sgn v + offset) and the fitted model's figures in the same terms",
    )
    imported: list[dict[str, Any]] = Field(
        default_factory=list, description="the column mappings (`--map`) the runs were read through"
    )
    lab_quantities: dict[str, LabQuantityDocument] = Field(
        default_factory=dict,
        description="the numbers labs compare (Coulomb at rest and viscous slope per direction, breakaway,"
        " total inertia at each side, stiffness), derived from the parameters with σ by propagation",
    )


class GapStepDocument(Document):
    effect: str = Field(description="the effect added, from the docs/MODEL.md vocabulary")
    gap_before: float
    gap_after: float
    evidence: str
    parameters: dict[str, float]


class GapsDocument(Document):
    """`hdrig gaps --json` (docs/INTERFACE.md); the result of a gap job."""

    metric: str
    initial_gap: float
    steps: list[GapStepDocument]
    final_gap: float
    final_model: str | None
    verdict: str = Field(default="", description="one line: what was found")
    unexplained: str | None = Field(
        default=None,
        description="the largest structure left in the final model's residual: the share a binned function"
        " of speed, motor angle, time, transmitted torque or rest explains (held out), and where it peaks",
    )
    rejected: list[str] = Field(
        default_factory=list,
        description="the last step's candidates (single effects and pairs), each with its held-out shrink"
        " and why it was not accepted",
    )
    report: list[str] = Field(default_factory=list, description="the report's files, with --report")
    folder: str | None = Field(default=None, description="the analysis folder holding its files")


class JobKind(StrEnum):
    RUN = "run"
    CAMPAIGN = "campaign"
    FIT = "fit"
    GAPS = "gaps"


class JobStatus(StrEnum):
    QUEUED = "queued"
    RUNNING = "running"
    COMPLETE = "complete"
    ABORTED = "aborted"  # a run of it ended aborted (trip, fault, quick stop, abort)
    FAILED = "failed"  # it raised: bad input found late, or a bug (the detail says)

    @property
    def finished(self) -> bool:
        return self not in (JobStatus.QUEUED, JobStatus.RUNNING)


class Progress(Document):
    fraction: float = Field(default=0.0, ge=0.0, le=1.0)
    phase: str = Field(default="", description="what is being done")
    eta_s: float | None = Field(default=None, description="seconds left, estimated from the pace so far")


class JobDocument(Document):
    """One job: an experiment, a campaign, a fit or a gap analysis."""

    id: str
    kind: JobKind
    status: JobStatus
    owner: str | None = None
    created: datetime
    started: datetime | None = None
    ended: datetime | None = None
    progress: Progress = Field(default_factory=Progress)
    request: dict[str, Any] = Field(default_factory=dict, description="what was asked")
    runs: list[str] = Field(default_factory=list, description="ids of the runs it recorded")
    result: dict[str, Any] | list[Any] | None = Field(default=None, description="the finished job's document")
    error: str | None = Field(default=None, description="why it failed, one line")


class TrendPoint(Document):
    """One checkpoint of an endurance run: where in the gear's life, and what it measured (±1σ)."""

    run_id: str
    index: int = Field(description="the checkpoint's number within its run")
    time_s: float = Field(description="time since the first run's start, at the checkpoint's middle [s]")
    duty_cycles: float = Field(description="duty cycles done before it, over the runs listed [–]")
    travel_rad: float = Field(description="motor travel in its run up to its middle [rad]")
    coulomb_estimate: float = Field(description="friction level F_c at the motor [N·m]")
    coulomb_sigma: float = Field(description="its standard error [N·m]")
    viscous_estimate: float = Field(description="viscous slope b at the motor [N·m·s/rad]")
    viscous_sigma: float = Field(description="its standard error [N·m·s/rad]")
    stiffness_estimate: float = Field(description="transmission stiffness K_s at the output [N·m/rad]")
    stiffness_sigma: float = Field(description="its standard error [N·m/rad]")
    temp_gear_c: float | None = Field(
        default=None, description="the gear's mean temperature over the checkpoint, if recorded [°C]"
    )
    coulomb_normalized_estimate: float | None = Field(
        default=None,
        description="F_c brought to the reference temperature by the thermal law (absent: no law or no"
        " temperature) [N·m]",
    )
    coulomb_normalized_sigma: float | None = Field(
        default=None, description="its standard error, the checkpoint's alone (the law's σ is common) [N·m]"
    )


class TrackPoint(Document):
    """The online tracker's friction level at one moment of a run (RLS with forgetting)."""

    run_id: str
    time_s: float = Field(description="time since the first run's start [s]")
    level_nm: float = Field(description="friction level F_c the tracker follows [N·m]")


class TrendDocument(Document):
    """`hdrig trend --json`: checkpoint estimates of one run or of every run of one gear unit, in order."""

    unit: str | None = Field(default=None, description="the gear unit's serial number, from the rig file")
    run_ids: list[str]
    points: list[TrendPoint]
    track: list[TrackPoint] = Field(default_factory=list, description="the online tracker's level")
    t_ref_c: float | None = Field(
        default=None, description="reference temperature the normalized friction is brought to [°C]"
    )
    beta_per_k: float | None = Field(
        default=None, description="the thermal law's beta_T: friction × exp(−beta_T·(T_g − T_ref)) [1/K]"
    )
    plots: list[str] = Field(default_factory=list, description="PNG files written (--plot DIR)")
