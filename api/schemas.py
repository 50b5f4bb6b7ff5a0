"""Request and response bodies of the service that are not the core's documents (`rig.core.documents`)."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, StrictBool, StrictStr

from rig.core.access import Role
from rig.core.documents import RunDocument


class Request(BaseModel):
    model_config = ConfigDict(extra="forbid")


class RunRequest(Request):
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
    data: list[Annotated[StrictStr, Field(max_length=200)]] = Field(
        min_length=1, max_length=100, description="run ids in the store, or `latest`"
    )
    model: StrictStr = Field(
        min_length=1, max_length=200, description="the starting model: a preset name (GET /api/v1/models)"
    )


class Health(BaseModel):
    status: Literal["ok"] = "ok"


class RigHealth(BaseModel):
    enabled: bool = Field(description="the drive is enabled (the motor may move)")
    faults: list[str] = Field(description="the faults the devices report now")
    last_abort: str | None = Field(description="why the last run aborted, if one did")


class RigStatus(BaseModel):
    """The rig this service drives."""

    name: str = Field(description="the rig config's name")
    backend: str = Field(description="the backend from the rig config (`sim`, `canopen`...)")
    mode: Literal["sim", "hardware"] = Field(description="a simulated plant or real hardware")
    pace: str | None = Field(default=None, description="sim: `virtual` (as fast as it can) or `realtime`")
    state: str = Field(description="the worker: idle, running, stopping, faulted, closed")
    health: RigHealth
    limits: dict[str, Any] = Field(description="the safety envelope (trip levels) from the rig config")
    sample_rate_hz: float = Field(description="the control and sampling rate [Hz]")
    current_run: RunDocument | None = Field(description="the run in progress, if any")
    queued: list[str] = Field(description="ids of the jobs waiting for the rig, oldest first")


class SessionRequest(Request):
    key: StrictStr = Field(min_length=1, max_length=200, description="an API key")


class SessionInfo(BaseModel):
    name: str = Field(description="the key's name")
    role: Role
    csrf: str | None = Field(
        default=None, description="send as X-CSRF-Token with POST/DELETE made with the session cookie"
    )


class KeyRequest(Request):
    role: Role = Field(
        description="viewer reads; operator also starts, aborts and stops; admin also manages keys"
    )
    name: StrictStr | None = Field(
        default=None, max_length=100, description="the key's name (default ROLE-N)"
    )


class NewKey(BaseModel):
    name: str
    role: Role
    key: str = Field(description="the key: shown only this once, stored hashed")


class FileList(BaseModel):
    files: list[str] = Field(description="paths relative to the folder, for the files route")
