"""Where the command line's work is done: here, over the core (`LocalLab`), or on a service.

`hdrig` handlers ask a `Lab` for models, experiments, runs, fits and gap analyses and print what it
answers, so the same handler serves both places: `LocalLab` calls `rig.core` on this machine's store
and rigs; `hdrig --server URL` gives the handlers `api.remote_lab.RemoteLab`, the same operations over
HTTP (loaded by module name: the service's package sits above this one). Both answer with the core's
documents, so `--json` prints the same document either way.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from model.errors import UserInputError
from model.params import PRESET_DIR
from rig.core import actions
from rig.core.documents import (
    ExperimentInfo,
    FitDocument,
    GapsDocument,
    ModelSummary,
    RunDocument,
    RunPage,
)
from rig.faults import DeviceFaultError
from rig.runner import Progress
from rig.status import RunStatus
from rig.store.catalog import DEFAULT_PAGE

if TYPE_CHECKING:
    from rig.core.worker import Job, RigWorker

Landed = Callable[[RunDocument], None]
"""Told each run of a start as it ends, in order."""


class Lab(Protocol):
    """The operations of the command line, wherever they run. Bad input raises `UserInputError` (one
    line); a device fault before any run ends raises `DeviceFaultError`."""

    store_where: str  # where runs are kept: a store's folder, or a service's URL (told on stderr)
    presets_where: str  # where the model presets come from

    def list_models(self) -> list[ModelSummary]: ...

    def show_model(self, name_or_file: str) -> dict[str, Any]:
        """A model as a model file's content."""
        ...

    def list_experiments(self) -> list[ExperimentInfo]: ...

    def run(
        self,
        experiment: str,
        params: dict[str, Any],
        rig: str | None,
        keep_going: bool,
        progress: Progress,
        landed: Landed,
        unit: str | None = None,
        tags: Sequence[str] = (),
    ) -> list[RunDocument]:
        """Play an experiment (or the campaign) to its end; each run's document, also told to `landed`
        as it ends. On KeyboardInterrupt the motion is stopped first, the run lands `aborted` with its
        data, and KeyboardInterrupt is raised again."""
        ...

    def list_runs(
        self,
        unit: str | None = None,
        rig: str | None = None,
        tags: Sequence[str] = (),
        operator: str | None = None,
        experiment: str | None = None,
        status: str | None = None,
        limit: int | None = DEFAULT_PAGE,
    ) -> RunPage:
        """The newest `limit` runs of the catalog (every one when None), oldest first, with how many the
        filters select in all: a unit, rig, operator or experiment (exact or a glob), a status, all
        `tags`."""
        ...

    def run_document(self, run_id: str) -> RunDocument: ...

    def export_run(self, run_id: str, fmt: str, out: str | Path) -> Path: ...

    def fit(
        self,
        data: Sequence[str],
        model: str,
        *,
        out: str | Path,
        report_dir: str | Path | None,
        progress: Progress,
        mapping: Sequence[str] | None = None,
        joint: bool = True,
    ) -> FitDocument:
        """`mapping`: `--map` entries for files with other column names (`rig.store.importmap`)."""
        ...

    def find_gaps(
        self,
        data: Sequence[str],
        model: str,
        *,
        out: str | Path | None,
        report_dir: str | Path | None,
        progress: Progress,
        mapping: Sequence[str] | None = None,
    ) -> GapsDocument: ...


class LocalLab:
    """The core on this machine: the store under $HDRIG_HOME, rigs opened from their config files."""

    presets_where = str(PRESET_DIR)

    def __init__(self) -> None:
        from rig.store.runs import RunStore

        self.store = RunStore()
        self.store_where = str(self.store.home)

    def list_models(self) -> list[ModelSummary]:
        return actions.list_models()

    def show_model(self, name_or_file: str) -> dict[str, Any]:
        return actions.show_model(name_or_file)

    def list_experiments(self) -> list[ExperimentInfo]:
        return actions.list_experiments()

    def run(
        self,
        experiment: str,
        params: dict[str, Any],
        rig: str | None,
        keep_going: bool,
        progress: Progress,
        landed: Landed,
        unit: str | None = None,
        tags: Sequence[str] = (),
    ) -> list[RunDocument]:
        from rig.config import load_rig_config
        from rig.core.worker import RigWorker
        from rig.realtime import quiet_heap

        if rig is None:
            raise UserInputError(
                f"run {experiment}: --rig RIG is required (a rig file, or a name in configs/rigs)"
            )
        config = load_rig_config(rig)
        plan = actions.plan_run(experiment, params, keep_going=keep_going, unit=unit, tags=tags)
        runs: list[RunDocument] = []

        def land(run: RunDocument) -> None:
            runs.append(run)
            landed(run)

        # The full collection that quiet_heap makes holds the interpreter for up to ~0.5 s: make it before
        # the rig is opened and its drive's heartbeat watchdog is armed.
        with quiet_heap(), RigWorker(config, self.store) as worker:
            # The whole plan against the open rig (its saturation, travel), still before anything moves.
            plan = actions.plan_run(
                experiment, params, keep_going=keep_going, unit=unit, tags=tags, rig=worker.rig
            )
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

    def list_runs(
        self,
        unit: str | None = None,
        rig: str | None = None,
        tags: Sequence[str] = (),
        operator: str | None = None,
        experiment: str | None = None,
        status: str | None = None,
        limit: int | None = DEFAULT_PAGE,
    ) -> RunPage:
        return actions.list_runs(
            self.store, unit, rig, tags, operator, experiment=experiment, status=status, limit=limit
        )

    def run_document(self, run_id: str) -> RunDocument:
        return actions.run_document(self.store, run_id)

    def export_run(self, run_id: str, fmt: str, out: str | Path) -> Path:
        return actions.export_run(self.store, run_id, fmt, out)

    def fit(
        self,
        data: Sequence[str],
        model: str,
        *,
        out: str | Path,
        report_dir: str | Path | None,
        progress: Progress,
        mapping: Sequence[str] | None = None,
        joint: bool = True,
    ) -> FitDocument:
        return actions.fit(
            data,
            model,
            self.store,
            out=out,
            report_dir=report_dir,
            joint=joint,
            progress=progress,
            mapping=mapping,
        )

    def find_gaps(
        self,
        data: Sequence[str],
        model: str,
        *,
        out: str | Path | None,
        report_dir: str | Path | None,
        progress: Progress,
        mapping: Sequence[str] | None = None,
    ) -> GapsDocument:
        return actions.find_gaps(
            data, model, self.store, out=out, report_dir=report_dir, progress=progress, mapping=mapping
        )


class _Follower:
    """Tells a job's progress and each run as it lands, from the worker's events; resumable, so a
    follow after Ctrl-C goes on from the last event told."""

    def __init__(self, worker: RigWorker, job: Job, progress: Progress, landed: Landed) -> None:
        self.worker, self.job, self.progress, self.landed = worker, job, progress, landed
        self.seen = 0

    def until_done(self) -> None:
        from rig.core.events import EventKind

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
