"""The rig a service drives, as `GET /api/v1/rig` (and the stop and reset routes) answer: its config's
name, backend and envelope, the worker's state, the devices' health, the run in progress and the queue."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, Field

from rig.core.documents import JobStatus, RunDocument
from rig.core.worker import RigWorker


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


def rig_status_of(worker: RigWorker) -> RigStatus:
    """The rig `worker` drives, now."""
    config = worker.config
    state = worker.rig.health()
    jobs = worker.jobs()
    running = next((job for job in jobs if job.status == JobStatus.RUNNING), None)
    current = None
    if running is not None and running.runs:
        current = worker.live_run(running.runs[-1])
    simulated = worker.rig.source == "sim"
    return RigStatus(
        name=config.name,
        backend=config.backend,
        mode="sim" if simulated else "hardware",
        pace=config.pace if simulated else None,
        state=str(worker.state),
        health=RigHealth(enabled=state.enabled, faults=list(state.faults), last_abort=state.last_abort),
        limits=config.limits.model_dump(mode="json"),
        sample_rate_hz=config.sample_rate_hz,
        current_run=current,
        queued=[job.id for job in jobs if job.status == JobStatus.QUEUED],
    )
