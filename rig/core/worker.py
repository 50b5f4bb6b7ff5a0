"""The rig worker: owns one open rig and plays jobs on it one at a time, on its own thread.

The command line and the service both hand their runs to it, so the control loop never runs on a
thread that serves a terminal or HTTP. Its state follows `TRANSITIONS`; `quick_stop()` is accepted
in every state from every thread (it stops the motor first and asks questions later). Everything it
does is published to an `EventLog` (state, progress, decimated samples, alarms, runs, jobs).

Fits and gap analyses need no rig: `AnalysisWorker` plays them one at a time on a thread of its own,
with the same job documents and events.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from enum import StrEnum
from typing import Any

import numpy as np

from model.errors import UserInputError
from rig.config import RigConfig
from rig.core.actions import (
    ConflictError,
    UnknownJobError,
    execute_plan,
    list_runs,
    reserve_run_id,
    run_document,
)
from rig.core.documents import JobDocument, JobKind, JobStatus, Progress, RunDocument, RunPage, RunPlan
from rig.core.events import Event, EventKind, EventLog
from rig.faults import DeviceFaultError
from rig.interface import Block, ControlMode, Rig, Segment, open_rig
from rig.runner import RunHooks
from rig.status import RunStatus
from rig.store.runs import RunQuery, RunStore, new_run_id

log = logging.getLogger(__name__)

SAMPLE_POINTS_PER_EVENT = 25  # decimated rows per samples event: ~100 points/s for 0.25 s blocks
SAMPLE_EVENT_COLUMNS = ("t", "omega_m", "i_a", "theta_m", "theta_l", "setpoint")
PROGRESS_EVENT_PERIOD_S = 0.1  # at most ten progress events a second per job


class WorkerState(StrEnum):
    IDLE = "idle"  # rig open, nothing playing
    RUNNING = "running"  # a job is playing
    STOPPING = "stopping"  # a quick stop or an abort is bringing the motor to rest
    FAULTED = "faulted"  # a device fault ended the last job: queued jobs wait for `reset()`
    CLOSED = "closed"  # rig released; nothing more is accepted


TRANSITIONS: dict[WorkerState, frozenset[WorkerState]] = {
    WorkerState.IDLE: frozenset({WorkerState.RUNNING, WorkerState.STOPPING, WorkerState.CLOSED}),
    WorkerState.RUNNING: frozenset({WorkerState.IDLE, WorkerState.STOPPING, WorkerState.FAULTED}),
    WorkerState.STOPPING: frozenset({WorkerState.IDLE, WorkerState.FAULTED, WorkerState.CLOSED}),
    WorkerState.FAULTED: frozenset({WorkerState.IDLE, WorkerState.STOPPING, WorkerState.CLOSED}),
    WorkerState.CLOSED: frozenset(),
}
"""Which state may follow which: anything else is a bug in the worker (IllegalTransitionError)."""


class IllegalTransitionError(RuntimeError):
    pass


class RigBusyError(UserInputError):
    """The rig is playing a job and the request did not ask to queue (HTTP 409)."""


class QueueFullError(UserInputError):
    """The queue holds as many jobs as it may (HTTP 429: ask again when one has ended)."""


class WorkerClosedError(UserInputError):
    """The worker has released its rig and takes no more jobs."""


@dataclass
class Job:
    """One job's bookkeeping; `document()` is what the service returns."""

    id: str
    kind: JobKind
    request: dict[str, Any]
    work: Callable[[Job], Any]
    owner: str | None = None
    status: JobStatus = JobStatus.QUEUED
    created: datetime = field(default_factory=lambda: datetime.now(UTC))
    started: datetime | None = None
    ended: datetime | None = None
    fraction: float = 0.0
    phase: str = ""
    runs: list[str] = field(default_factory=list)
    result: Any = None
    error: str | None = None
    exception: BaseException | None = None  # what ended it, for a caller in the same process to raise
    partial: list[Any] = field(default_factory=list)  # documents of the parts done, should it fail
    abort_requested: threading.Event = field(default_factory=threading.Event)
    done: threading.Event = field(default_factory=threading.Event)
    _started_s: float = 0.0
    _last_progress_s: float = 0.0

    def eta_s(self) -> float | None:
        if self.status != JobStatus.RUNNING or self.fraction <= 0.01:
            return None
        elapsed = time.monotonic() - self._started_s
        return elapsed * (1.0 - self.fraction) / self.fraction

    def document(self) -> JobDocument:
        result = self.result
        if isinstance(result, list):
            result = [r.as_json() if hasattr(r, "as_json") else r for r in result]
        elif hasattr(result, "as_json"):
            result = result.as_json()
        return JobDocument(
            id=self.id,
            kind=self.kind,
            status=self.status,
            owner=self.owner,
            created=self.created,
            started=self.started,
            ended=self.ended,
            progress=Progress(
                fraction=min(1.0, max(0.0, self.fraction)), phase=self.phase, eta_s=self.eta_s()
            ),
            request=self.request,
            runs=list(self.runs),
            result=result,
            error=self.error,
        )


class _JobThread:
    """Jobs one at a time, FIFO, on one thread; the shared part of both workers."""

    def __init__(self, name: str, events: EventLog) -> None:
        self.events = events
        self._jobs: dict[str, Job] = {}
        self._queue: deque[Job] = deque()
        self._lock = threading.RLock()
        self._wake = threading.Condition(self._lock)
        self._current: Job | None = None
        self._closing = False
        self._thread = threading.Thread(target=self._loop, name=name, daemon=True)

    # ---- jobs -------------------------------------------------------------------------------------

    def job(self, job_id: str) -> Job:
        with self._lock:
            try:
                return self._jobs[job_id]
            except KeyError:
                raise UnknownJobError(f"unknown job id {job_id!r}") from None

    def jobs(self) -> list[Job]:
        with self._lock:
            return list(self._jobs.values())

    @property
    def busy(self) -> bool:
        with self._lock:
            return self._current is not None or bool(self._queue)

    def _enqueue(self, job: Job, queue: bool) -> Job:
        with self._lock:
            if self._closing:
                raise WorkerClosedError("the worker is closed: it takes no more jobs")
            if not queue and not self._may_start_now():
                raise RigBusyError(self._busy_message())
            self._jobs[job.id] = job
            self._queue.append(job)
            self._wake.notify_all()
        self._publish_job(job)
        return job

    def _may_start_now(self) -> bool:
        return self._current is None and not self._queue

    def _busy_message(self) -> str:
        current = self._current.id if self._current else self._queue[0].id
        return f"busy with job {current}; ask to queue, or try again when it ends"

    def wait(self, job_id: str, timeout_s: float | None = None) -> Job:
        job = self.job(job_id)
        job.done.wait(timeout_s)
        return job

    def _cancel_queued(self, job: Job, why: str) -> None:
        """Under the lock: a queued job leaves the queue as aborted."""
        self._queue.remove(job)
        job.status, job.error, job.ended = JobStatus.ABORTED, why, datetime.now(UTC)
        job.done.set()

    def _publish_job(self, job: Job) -> None:
        self.events.publish(EventKind.JOB, job.document().as_json(), job_id=job.id)

    def progress(self, job: Job) -> Callable[[str, float], None]:
        def report(phase: str, fraction: float) -> None:
            job.phase, job.fraction = phase, max(job.fraction, fraction)
            now = time.monotonic()
            if now - job._last_progress_s >= PROGRESS_EVENT_PERIOD_S or fraction >= 1.0:
                job._last_progress_s = now
                run_id = job.runs[-1] if job.runs else None
                data = {"fraction": job.fraction, "phase": phase, "eta_s": job.eta_s()}
                self.events.publish(EventKind.PROGRESS, data, run_id=run_id, job_id=job.id)

        return report

    # ---- the thread -------------------------------------------------------------------------------

    def start(self) -> None:
        self._thread.start()

    def _next(self) -> Job | None:
        with self._lock:
            while not self._closing and not (self._queue and self._ready()):
                self._wake.wait()
            if self._closing:
                return None
            job = self._queue.popleft()
            self._current = job
            return job

    def _ready(self) -> bool:
        return True

    def _loop(self) -> None:
        while (job := self._next()) is not None:
            job.status, job.started, job._started_s = JobStatus.RUNNING, datetime.now(UTC), time.monotonic()
            self._publish_job(job)
            self._before(job)
            try:
                job.result = job.work(job)
                job.status = self._status_of(job)
            except UserInputError as exc:  # found only once the job ran (a file, a run id...)
                job.status, job.error, job.exception = JobStatus.FAILED, str(exc), exc
            except DeviceFaultError as exc:
                job.status, job.error, job.exception = JobStatus.ABORTED, f"aborted: {exc}", exc
                if job.result is None:
                    job.result = list(job.partial)
                self._faulted(job, exc)
            except Exception as exc:  # a bug: told in the job, logged with its traceback, worker lives on
                log.exception("job %s failed", job.id)
                job.status, job.exception = JobStatus.FAILED, exc
                job.error = f"internal error: {type(exc).__name__}: {exc}"
            finally:
                job.ended = datetime.now(UTC)
                if job.status == JobStatus.COMPLETE:
                    job.fraction = 1.0
                with self._lock:
                    self._current = None
                self._after(job)
                job.done.set()
                self._publish_job(job)

    def _before(self, job: Job) -> None:
        return None

    def _after(self, job: Job) -> None:
        return None

    def _faulted(self, job: Job, fault: DeviceFaultError) -> None:
        return None

    def _status_of(self, job: Job) -> JobStatus:
        return JobStatus.COMPLETE

    def _close_thread(self, timeout_s: float) -> None:
        with self._lock:
            self._closing = True
            for job in list(self._queue):
                self._cancel_queued(job, "the worker closed before it began")
            self._wake.notify_all()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout_s)


class RigWorker(_JobThread):
    """One open rig, its jobs, its state. `submit` a plan; `abort` a job; `quick_stop` everything."""

    def __init__(
        self,
        config: RigConfig,
        store: RunStore,
        rig: Rig | None = None,
        events: EventLog | None = None,
    ) -> None:
        super().__init__(f"rig-worker-{config.name}", events or EventLog())
        self.config = config
        self.store = store
        self.rig = rig if rig is not None else open_rig(config)
        self.state = WorkerState.IDLE
        self.closing_reason: str | None = None  # set by shutdown(): the service is going away, and why
        self.closed: Event | None = None  # shutdown()'s `closed` event, once published
        self._mode: dict[str, ControlMode] = {}
        self._live: dict[str, RunDocument] = {}
        self.start()

    # ---- state ------------------------------------------------------------------------------------

    def _set_state(self, new: WorkerState, why: str = "", job_id: str | None = None) -> None:
        with self._lock:
            old = self.state
            if new == old:
                return
            if new not in TRANSITIONS[old]:
                raise IllegalTransitionError(f"worker state {old} cannot become {new}")
            self.state = new
        data = {"state": new.value, "previous": old.value, "why": why}
        self.events.publish(EventKind.STATE, data, job_id=job_id)

    def _ready(self) -> bool:
        return self.state == WorkerState.IDLE

    def _may_start_now(self) -> bool:
        return super()._may_start_now() and self.state == WorkerState.IDLE

    def _busy_message(self) -> str:
        if self.state != WorkerState.IDLE and self._current is None and not self._queue:
            return (
                f"the rig is {self.state}; reset it first"
                if self.state == WorkerState.FAULTED
                else (f"the rig is {self.state}")
            )
        return super()._busy_message()

    # ---- what callers do ----------------------------------------------------------------------------

    def submit(
        self, plan: RunPlan, owner: str | None = None, queue: bool = False, queue_max: int | None = None
    ) -> Job:
        """Accept a validated plan. The job's id is its first run's id; it starts when the rig is free
        (`queue=True`: QueueFullError when `queue_max` jobs wait already) or now (else RigBusyError)."""
        waiting = sum(job.status == JobStatus.QUEUED for job in self.jobs())
        if queue and queue_max is not None and waiting >= queue_max:
            raise QueueFullError(
                f"the queue holds {waiting} jobs already (at most {queue_max}); try again when one has ended"
            )
        first = reserve_run_id(plan)
        kind = JobKind.CAMPAIGN if len(plan.runs) > 1 else JobKind.RUN
        job_id = first if kind == JobKind.RUN else new_run_id("campaign")

        def work(job: Job) -> list[RunDocument]:
            return execute_plan(
                plan,
                self.config,
                self.store,
                rig=self.rig,
                progress=self.progress(job),
                hooks=self._hooks(job, first),
                on_run=lambda doc: self._run_ended(job, doc),
                should_continue=lambda: not job.abort_requested.is_set(),
            )

        job = Job(job_id, kind, plan.as_json(), work, owner=owner)
        if kind == JobKind.RUN:
            job.runs.append(first)  # named before it starts, so GET /runs/{id} finds it queued
        return self._enqueue(job, queue)

    def abort_run(self, run_id: str) -> Job:
        """Stop the job that plays (or waits to play) this run; ConflictError when it has ended."""
        job = next((j for j in self.jobs() if run_id in j.runs and not j.status.finished), None)
        if job is None:
            document = self.run_document(run_id)  # UnknownRunError when unknown
            raise ConflictError(f"run {run_id} is {document.status}: nothing to abort")
        return self.abort(job.id)

    def abort(self, job_id: str) -> Job:
        """Stop one job: a queued job leaves the queue; a running one quick-stops the rig (data kept)."""
        job = self.job(job_id)
        with self._lock:
            if job.status == JobStatus.QUEUED and job in self._queue:
                self._cancel_queued(job, "aborted before it began")
                queued = True
            else:
                queued = False
                if not job.status.finished:
                    job.abort_requested.set()
        if queued:
            self._publish_job(job)
        elif not job.status.finished:
            self._stop_motion(f"job {job_id} aborted")
        return job

    def quick_stop(self, why: str = "quick stop") -> None:
        """Stop everything now: the motor first, then the queue. Any state, any thread, never refused.
        A run it ends is `aborted: <why>`."""
        self.rig.quick_stop(why)  # before any lock: the motor must not wait for bookkeeping
        with self._lock:
            cancelled = list(self._queue)
            for job in cancelled:
                self._cancel_queued(job, f"cancelled by {why}")
            if self._current is not None:
                self._current.abort_requested.set()
        for job in cancelled:
            self._publish_job(job)
        self._stop_motion(why, why)

    def shutdown(self, why: str, wait_s: float = 0.0) -> None:
        """The service is going away (a signal): stop for good. The motor first, then the queue; no job is
        accepted from now on; then wait up to `wait_s` for the job playing to end (its run sealed
        `aborted: <why>`) and publish the `closed` event that ends every event stream, saying why.
        Safe from any thread, and to call again (the first `why` stays)."""
        self.rig.quick_stop(why)
        with self._lock:
            first = self.closing_reason is None
            if first:
                self.closing_reason = why
                self._closing = True  # _enqueue refuses from now on; the thread ends after its job
                self._wake.notify_all()
        self.quick_stop(why)
        current = self._current
        if current is not None:
            current.done.wait(wait_s)
        if first:
            self.closed = self.events.publish(EventKind.CLOSED, {"why": why})

    def _stop_motion(self, why: str, rig_why: str | None = None) -> None:
        self.rig.quick_stop(rig_why)
        self.events.publish(EventKind.ALARM, {"alarm": "quick_stop", "why": why})
        with self._lock:
            running = self._current is not None
            if self.state in (WorkerState.IDLE, WorkerState.RUNNING):
                self._set_state(WorkerState.STOPPING, why)
                if not running:  # nothing was moving: the stop is done already
                    self._set_state(WorkerState.IDLE, "stopped")

    def reset(self) -> None:
        """Leave FAULTED once a person has looked: the next job enables the drive again."""
        with self._lock:
            if self.state == WorkerState.FAULTED:
                self._set_state(WorkerState.IDLE, "reset")
                self._wake.notify_all()

    def close(self, timeout_s: float = 30.0) -> None:
        """Stop, finish (waiting up to `timeout_s` for the job playing to seal its run), release the rig.
        Safe to call twice."""
        if self.state == WorkerState.CLOSED:
            return
        if self.busy:
            self.quick_stop(self.closing_reason or "quick stop: the rig worker is closing")
        self._close_thread(timeout_s)
        self.rig.close()
        with self._lock:
            if self.state == WorkerState.RUNNING:
                self.state = WorkerState.STOPPING
            self._set_state(WorkerState.CLOSED, "closed")

    def __enter__(self) -> RigWorker:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def live_run(self, run_id: str) -> RunDocument | None:
        """A run this worker has queued or is recording, with its progress (None: ask the store)."""
        with self._lock:
            for job in [*self._queue, *([self._current] if self._current else [])]:
                if run_id in job.runs:
                    document = self._live.get(run_id)
                    if document is None:  # queued: not in the store yet
                        return RunDocument(
                            id=run_id,
                            experiment=str(job.request.get("runs", [{}])[0].get("experiment", "")),
                            status=RunStatus.QUEUED,
                            rig=self.config.name,
                            owner=job.owner,
                        )
                    return document.model_copy(update={"progress": min(1.0, job.fraction)})
        return None

    def owner_of(self, run_id: str) -> str | None:
        return next((job.owner for job in self.jobs() if run_id in job.runs), None)

    def run_document(self, run_id: str) -> RunDocument:
        """A run: queued or recording from this worker, else from the store (UnknownRunError when unknown)."""
        live = self.live_run(run_id)
        if live is not None:
            if live.status == RunStatus.RUNNING:  # the worker knows the progress, the store what is on disk
                live.samples = self.store.get(run_id)["samples"]
            return live
        document = run_document(self.store, run_id)
        document.owner = self.owner_of(run_id)
        return document

    def runs_page(self, query: RunQuery, limit: int | None = None, cursor: str | None = None) -> RunPage:
        """A page of the catalog (`actions.list_runs`) with what this worker knows that the catalog does
        not: each recording run's progress, each run's owner, and, on the first page of a listing not
        narrowed by a field a queued run lacks, the runs waiting for the rig (they have no catalog entry
        to search or page through yet: the newest runs). `total` counts those too."""
        page = list_runs(self.store, query, limit=limit, cursor=cursor)
        owners = {run_id: job.owner for job in self.jobs() for run_id in job.runs}
        listed: dict[str, RunDocument] = {}
        for document in page.runs:
            live = self.live_run(document.id) if document.status == RunStatus.RUNNING else None
            if live is not None:
                live.samples = document.samples
            listed[document.id] = live or document
            listed[document.id].owner = owners.get(document.id)
        waiting: list[RunDocument] = []
        if not query.searched and query.status in (None, RunStatus.QUEUED):
            for job in self.jobs():
                if job.status == JobStatus.QUEUED:
                    found = (self.live_run(run_id) for run_id in job.runs if run_id not in listed)
                    waiting += [run for run in found if run is not None]
        if cursor is None:
            listed.update((run.id, run) for run in waiting)
        return RunPage(
            runs=list(listed.values()), total=page.total + len(waiting), next_cursor=page.next_cursor
        )

    # ---- the job thread's side ------------------------------------------------------------------

    def _before(self, job: Job) -> None:
        self._set_state(WorkerState.RUNNING, f"job {job.id}", job_id=job.id)

    def _after(self, job: Job) -> None:
        # A run begun and never told ended (the job failed on what the run found, e.g. a program that does
        # not fit the stroke left, before anything moved): its final document still goes to its stream,
        # or a page following it says `running` for ever.
        with self._lock:
            untold = [run_id for run_id in job.runs if run_id in self._live]
        for run_id in untold:
            document = run_document(self.store, run_id)
            if document.status.finished:
                self._run_ended(job, document)
        with self._lock:
            if self.state in (WorkerState.RUNNING, WorkerState.STOPPING):
                self._set_state(WorkerState.IDLE, f"job {job.id} {job.status}")
            self._live.clear()
            self._wake.notify_all()

    def _faulted(self, job: Job, fault: DeviceFaultError) -> None:
        self.rig.quick_stop()  # the runner has stopped it already; a fault before any run has not
        self.events.publish(EventKind.ALARM, {"alarm": "device_fault", "why": str(fault)}, job_id=job.id)
        with self._lock:
            if self.state == WorkerState.RUNNING:
                self.state = WorkerState.STOPPING  # the motor is stopped; now say why
            self._set_state(WorkerState.FAULTED, str(fault))
            # A faulted rig plays nothing more until a person has looked (reset): the queue is cancelled.
            for queued in list(self._queue):
                self._cancel_queued(queued, f"cancelled: the rig faulted ({fault})")

    def _status_of(self, job: Job) -> JobStatus:
        documents: list[RunDocument] = job.result or []
        if job.abort_requested.is_set() or any(d.status == RunStatus.ABORTED for d in documents):
            return JobStatus.ABORTED
        return JobStatus.COMPLETE

    def _hooks(self, job: Job, first_run_id: str) -> RunHooks:
        def started(run_id: str) -> None:
            if job.abort_requested.is_set():
                # A stop that came between the campaign's check and this run's enable() was cleared by
                # enable(): the drive is powered now, so stop it again before a cycle is played.
                self.rig.quick_stop(self.closing_reason)
            if run_id not in job.runs:
                job.runs.append(run_id)
            entry = self.store.get(run_id)
            document = RunDocument(
                id=run_id,
                experiment=entry["experiment"],
                status=RunStatus.RUNNING,
                rig=entry["rig"],
                model_name=entry["model_name"],
                model_hash=entry["model_hash"],
                started=entry["started"],
                meta=entry["meta"],
                owner=job.owner,
            )
            with self._lock:
                self._live[run_id] = document
            self.events.publish(EventKind.RUN, document.as_json(), run_id=run_id, job_id=job.id)

        def segment(run_id: str, seg: Segment) -> None:
            self._mode[run_id] = seg.mode

        def block(run_id: str, rows: Block) -> None:
            self.events.publish(
                EventKind.SAMPLES, _decimated(rows, self._mode.get(run_id)), run_id=run_id, job_id=job.id
            )

        return RunHooks(
            on_start=started, on_block=block, on_segment=segment, run_id=first_run_id, operator=job.owner
        )

    def _run_ended(self, job: Job, document: RunDocument) -> None:
        document.owner = job.owner
        job.partial.append(document)
        self._mode.pop(document.id, None)
        with self._lock:
            self._live.pop(document.id, None)
        if document.status == RunStatus.ABORTED:
            self.events.publish(
                EventKind.ALARM,
                {"alarm": "aborted", "why": document.reason},
                run_id=document.id,
                job_id=job.id,
            )
        self.events.publish(EventKind.RUN, document.as_json(), run_id=document.id, job_id=job.id)


def _frozen(values: Any) -> np.ndarray:
    """A copy that no longer views the recording's block, and that no reader can change."""
    array = np.array(values, dtype=float)
    array.flags.writeable = False
    return array


def _decimated(rows: Block, mode: ControlMode | None) -> dict[str, Any]:
    """At most SAMPLE_POINTS_PER_EVENT rows of the columns a live plot shows, plus the tracking error
    (set-point minus the measured quantity the segment's mode commands; None in voltage/current mode)."""
    n = len(rows["t"])
    step = max(1, math.ceil(n / SAMPLE_POINTS_PER_EVENT))
    picked = {name: rows[name][::step] for name in SAMPLE_EVENT_COLUMNS if name in rows}
    measured = {ControlMode.POSITION: "theta_m", ControlMode.VELOCITY: "omega_m"}.get(mode) if mode else None
    # Small read-only arrays, not lists of floats: the log keeps thousands of these on runs of hours, and
    # 25 boxed floats a column cost ~4x the memory (and scatter it over the allocator's arenas).
    data: dict[str, Any] = {name: _frozen(values) for name, values in picked.items()}
    if measured is not None and measured in picked:
        data["error"] = _frozen(picked["setpoint"] - picked[measured])
    data["mode"] = str(mode) if mode is not None else None
    return data


class AnalysisWorker(_JobThread):
    """Fits and gap analyses, one at a time on their own thread (they need no rig)."""

    def __init__(self, events: EventLog | None = None) -> None:
        super().__init__("analysis-worker", events or EventLog())
        self.start()

    def submit(
        self,
        kind: JobKind,
        request: dict[str, Any],
        work: Callable[[Callable[[str, float], None], str], Any],
        owner: str | None = None,
    ) -> Job:
        """Queue an analysis; `work(progress, job_id)` returns its document. Analyses always queue."""
        job = Job(new_run_id(kind.value), kind, request, lambda job: work(self.progress(job), job.id), owner)
        return self._enqueue(job, queue=True)

    def close(self, timeout_s: float = 30.0) -> None:
        self._close_thread(timeout_s)
