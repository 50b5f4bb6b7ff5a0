"""Where the command line's work is done: here, over the core (`LocalLab`), or on a service.

`hdrig` handlers ask a `Lab` for models, experiments, runs, fits and gap analyses and print what it
answers, so the same handler serves both places: `LocalLab` calls `rig.core` on this machine's store
and rigs; `hdrig --server URL` gives the handlers the service's `RemoteLab`, the same operations over
HTTP. Both answer with the core's documents, so `--json` prints the same document either way.

The service's package sits above this one (it imports `rig.core`), so the command line does not import
it: the service offers its doors here instead, as backends offer theirs to `rig.interface` — a
`ServiceDoor` per name in the entry points of `hdrig.service`, or in `BUILTIN_SERVICE_DOORS` (where
this package's own service is), loaded only when `hdrig serve` or `--server` asks.
"""

from __future__ import annotations

import importlib.metadata
from collections.abc import Callable
from importlib.metadata import EntryPoint
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from model.errors import UserInputError
from model.params import PRESET_DIR
from rig.config import RigConfig, load_rig_config
from rig.core import actions
from rig.core.documents import (
    ExperimentInfo,
    FitDocument,
    GapsDocument,
    ModelSummary,
    RunDocument,
    RunPage,
)
from rig.core.events import EventKind
from rig.core.operations import AnalysisOrder, RunRequest, plan_of
from rig.core.worker import RigWorker
from rig.faults import DeviceFaultError
from rig.realtime import quiet_heap
from rig.runner import Progress
from rig.status import RunStatus
from rig.store.catalog import DEFAULT_PAGE
from rig.store.runs import RunQuery, RunStore

if TYPE_CHECKING:
    from rig.core.worker import Job

Landed = Callable[[RunDocument], None]
"""Told each run of a start as it ends, in order."""


class ServedApp(Protocol):
    """What `hdrig serve` needs of the service: an ASGI app for one rig, and how to stop it going away."""

    def create_app(self, config: RigConfig, store: RunStore) -> Any: ...

    def stop_service(self, app: Any, why: str) -> None: ...


RemoteLabFactory = Callable[[str, str], "Lab"]
"""`hdrig --server URL`: a `Lab` over the service at URL with an API key."""

SERVICE_ENTRY_POINTS = "hdrig.service"
BUILTIN_SERVICE_DOORS = {
    "serve": "api.app:SERVED_APP",  # a ServedApp
    "remote-lab": "api.remote_lab:RemoteLab",  # a RemoteLabFactory
}


def service_door(name: str) -> Any:
    """The service's door `name` (`serve`, `remote-lab`), imported now: an `hdrig.service` entry point's,
    else this package's own (`BUILTIN_SERVICE_DOORS`)."""
    found = [ep for ep in importlib.metadata.entry_points(group=SERVICE_ENTRY_POINTS) if ep.name == name]
    door = found[0] if found else EntryPoint(name, BUILTIN_SERVICE_DOORS[name], SERVICE_ENTRY_POINTS)
    return door.load()


def served_app() -> ServedApp:
    served: ServedApp = service_door("serve")
    return served


def remote_lab(url: str, key: str) -> Lab:
    factory: RemoteLabFactory = service_door("remote-lab")
    return factory(url, key)


class Lab(Protocol):
    """The operations of the command line, wherever they run (their rows in `rig.core.operations` name
    these methods). Bad input raises `UserInputError` (one line); a device fault before any run ends
    raises `DeviceFaultError`."""

    store_where: str  # where runs are kept: a store's folder, or a service's URL (told on stderr)
    presets_where: str  # where the model presets come from

    def list_models(self) -> list[ModelSummary]: ...

    def show_model(self, name_or_file: str) -> dict[str, Any]:
        """A model as a model file's content."""
        ...

    def list_experiments(self) -> list[ExperimentInfo]: ...

    def run(
        self, request: RunRequest, rig: str | None, progress: Progress, landed: Landed
    ) -> list[RunDocument]:
        """Play an experiment (or the campaign) to its end on `rig` (a rig file or name); each run's
        document, also told to `landed` as it ends. On KeyboardInterrupt the motion is stopped first, the
        run lands `aborted` with its data, and KeyboardInterrupt is raised again."""
        ...

    def list_runs(self, query: RunQuery, limit: int | None = DEFAULT_PAGE) -> RunPage:
        """The newest `limit` runs `query` selects (every one when None), oldest first, with how many it
        selects in all."""
        ...

    def run_document(self, run_id: str) -> RunDocument: ...

    def export_run(self, run_id: str, fmt: str, out: str | Path) -> Path: ...

    def fit(self, order: AnalysisOrder, progress: Progress) -> FitDocument: ...

    def find_gaps(self, order: AnalysisOrder, progress: Progress) -> GapsDocument: ...


class LocalLab:
    """The core on this machine: the store under $HDRIG_HOME, rigs opened from their config files."""

    presets_where = str(PRESET_DIR)

    def __init__(self) -> None:
        self.store = RunStore()
        self.store_where = str(self.store.home)

    def list_models(self) -> list[ModelSummary]:
        return actions.list_models()

    def show_model(self, name_or_file: str) -> dict[str, Any]:
        return actions.show_model(name_or_file)

    def list_experiments(self) -> list[ExperimentInfo]:
        return actions.list_experiments()

    def run(
        self, request: RunRequest, rig: str | None, progress: Progress, landed: Landed
    ) -> list[RunDocument]:
        if rig is None:
            raise UserInputError(
                f"run {request.experiment}: --rig RIG is required (a rig file, or a name in configs/rigs)"
            )
        config = load_rig_config(rig)
        plan = plan_of(request)
        runs: list[RunDocument] = []

        def land(run: RunDocument) -> None:
            runs.append(run)
            landed(run)

        # The full collection that quiet_heap makes holds the interpreter for up to ~0.5 s: make it before
        # the rig is opened and its drive's heartbeat watchdog is armed.
        with quiet_heap(), RigWorker(config, self.store) as worker:
            # The whole plan against the open rig (its saturation, travel), still before anything moves.
            plan = plan_of(request, worker.rig)
            job = worker.submit(plan)
            follower = _Follower(worker, job, progress, land)
            try:
                follower.until_done()
            except KeyboardInterrupt as stop:  # Ctrl-C, or SIGTERM/SIGHUP (the command line's StopSignal)
                worker.quick_stop(str(stop) or "Ctrl-C")  # the motor first; the run then ends `aborted`
                job.done.wait()
                follower.until_done()
                raise
        if job.exception is not None and not (runs and isinstance(job.exception, DeviceFaultError)):
            raise job.exception  # bad input found late, a fault before any run, or a bug (its traceback)
        return runs

    def list_runs(self, query: RunQuery, limit: int | None = DEFAULT_PAGE) -> RunPage:
        return actions.list_runs(self.store, query, limit=limit)

    def run_document(self, run_id: str) -> RunDocument:
        return actions.run_document(self.store, run_id)

    def export_run(self, run_id: str, fmt: str, out: str | Path) -> Path:
        return actions.export_run(self.store, run_id, fmt, out)

    def fit(self, order: AnalysisOrder, progress: Progress) -> FitDocument:
        document: FitDocument = self._analyze(actions.fit, order, progress, joint=order.joint)
        return document

    def find_gaps(self, order: AnalysisOrder, progress: Progress) -> GapsDocument:
        document: GapsDocument = self._analyze(actions.find_gaps, order, progress)
        return document

    def _analyze(
        self, action: Callable[..., Any], order: AnalysisOrder, progress: Progress, **more: Any
    ) -> Any:
        where = {"out": order.out, "report_dir": order.report_dir, "mapping": order.mapping}
        return action(order.data, order.model, self.store, progress=progress, **where, **more)


class _Follower:
    """Tells a job's progress and each run as it lands, from the worker's events; resumable, so a
    follow after Ctrl-C goes on from the last event told."""

    def __init__(self, worker: RigWorker, job: Job, progress: Progress, landed: Landed) -> None:
        self.worker, self.job, self.progress, self.landed = worker, job, progress, landed
        self.seen = 0

    def until_done(self) -> None:
        while True:
            done = (
                self.job.done.is_set()
            )  # read before the events, so none published before the end is missed
            for event in self.worker.events.since(self.seen):
                self.seen = event.id
                if event.job_id != self.job.id:
                    continue
                if event.kind == EventKind.PROGRESS:
                    self.progress(str(event.data["phase"]), float(event.data["fraction"]))
                elif event.kind == EventKind.RUN and RunStatus(event.data["status"]).finished:
                    self.landed(RunDocument.model_validate(event.data))
            if done:
                return
            self.worker.events.wait(self.seen, timeout_s=0.5)
