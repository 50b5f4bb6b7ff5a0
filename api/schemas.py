"""Request and response bodies of the service that are not the core's documents (`rig.core.documents`)
nor the operations' request models (`rig.core.operations`, re-exported here)."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, StrictStr

from rig.core.access import Role
from rig.core.documents import RunDocument
from rig.core.operations import AnalysisRequest, KeyRequest, ModelUpload, Request, RunRequest
from rig.store.catalog import DEFAULT_PAGE, MAX_PAGE
from rig.store.runs import RunQuery


class RunListQuery(RunQuery):
    """`GET /api/v1/runs`: the run filters, and which page."""

    model_config = ConfigDict(extra="ignore")  # a query string may carry what is not ours (a cache-buster)

    limit: int = Field(
        default=DEFAULT_PAGE,
        ge=1,
        le=MAX_PAGE,
        description=f"runs in the page (the newest before `cursor`), 1-{MAX_PAGE}",
    )
    cursor: str | None = Field(
        default=None,
        max_length=1000,
        description='where the page begins: from the previous page\'s `Link: rel="next"`',
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


class NewKey(BaseModel):
    name: str
    role: Role
    key: str = Field(description="the key: shown only this once, stored hashed")


class FileList(BaseModel):
    files: list[str] = Field(description="paths relative to the folder, for the files route")


__all__ = [
    "AnalysisRequest",
    "FileList",
    "Health",
    "KeyRequest",
    "ModelUpload",
    "NewKey",
    "RigHealth",
    "RigStatus",
    "RunListQuery",
    "RunRequest",
    "SessionInfo",
    "SessionRequest",
]
