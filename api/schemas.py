"""Request and response bodies of the service that are not the core's documents (`rig.core.documents`)
nor the operations' request models (`rig.core.operations`) and the rig's status (`rig.core.rig_status`),
re-exported here."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, StrictStr

from rig.core.access import Role
from rig.core.operations import AnalysisRequest, KeyRequest, ModelUpload, Request, RunRequest
from rig.core.rig_status import RigHealth, RigStatus
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
