"""`hdrig --server URL`: the command line's operations (`rig.lab.Lab`) done by a service over HTTP.

The documents come back from the service as they are, except where a file is asked for on this
machine: `fit --out FILE` and `gaps --out FILE` download the model the analysis made into FILE (and
the document names FILE, as it does locally); `--report DIR` downloads the report into DIR;
`runs export` downloads the run as Parquet (metadata inside) and writes it here with the same writer
as a local export, so the files are the same. The service reads only its own store: `--data` takes
run ids or `latest`, `--model` a preset name.
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Literal

from api.client import POLL_S, HdrigClient, ServiceError, ServiceInputError
from model.errors import UserInputError
from model.run import Run
from rig.core import documents as doc
from rig.core.actions import MODEL_FILE, REPORT_DIR
from rig.core.operations import AnalysisOrder, AnalysisRequest, RunRequest
from rig.faults import DeviceFaultError
from rig.lab import Landed
from rig.store.catalog import DEFAULT_PAGE
from rig.store.runfile import read_parquet, write_run
from rig.store.runs import RunQuery, export_path

Progress = Callable[[str, float], None]  # rig.runner.Progress: (phase, fraction done)
INTERNAL_ERROR = "internal error"


class RemoteLab:
    """A `rig.lab.Lab` over the service at `base_url`, authenticated by `key`."""

    def __init__(self, base_url: str, key: str) -> None:
        self.client = HdrigClient(base_url, key)
        self.store_where = f"the service at {self.client.base_url}"
        self.presets_where = self.store_where

    # ---- models and experiments ---------------------------------------------------------------------

    def list_models(self) -> list[doc.ModelSummary]:
        return self.client.models()

    def show_model(self, name_or_file: str) -> dict[str, Any]:
        _not_a_file(name_or_file, "model")
        return self.client.model(name_or_file)

    def list_experiments(self) -> list[doc.ExperimentInfo]:
        return self.client.experiments()

    # ---- runs ---------------------------------------------------------------------------------------

    def run(
        self, request: RunRequest, rig: str | None, progress: Progress, landed: Landed
    ) -> list[doc.RunDocument]:
        if rig is not None:
            self._check_rig(rig)
        started = self.client.start(request)
        runs: list[doc.RunDocument] = []
        try:
            job = self._follow(started.id, progress, runs, landed)
        except KeyboardInterrupt:
            job = self.client.job(started.id)
            if job.runs and not job.status.finished:
                self._abort(job.runs[-1])  # the motor first; the run then ends `aborted` with its data
            self._follow(started.id, progress, runs, landed)
            raise
        if job.error is not None and not (runs and job.status == doc.JobStatus.ABORTED):
            raise _job_error(job)
        return runs

    def _check_rig(self, rig: str) -> None:
        """`--rig` is optional over --server (the service drives one rig); given, it must be that one."""
        served = str(self.client.rig()["name"])
        if rig not in (served, Path(rig).stem):
            raise UserInputError(f"--rig {rig}: {self.store_where} drives rig {served!r}")

    def _abort(self, run_id: str) -> None:
        try:
            self.client.abort(run_id)
        except ServiceInputError as exc:
            if exc.status != 409:  # 409: it had ended already
                raise

    def _follow(
        self, job_id: str, progress: Progress, runs: list[doc.RunDocument], landed: Landed
    ) -> doc.JobDocument:
        """Poll the job until it ends: its progress, and each of its runs once it has ended."""
        while True:
            job = self.client.job(job_id)
            progress(job.progress.phase, job.progress.fraction)
            told = {run.id for run in runs}
            for index, run_id in enumerate(job.runs):
                if run_id in told or (index == len(job.runs) - 1 and not job.status.finished):
                    continue  # the newest run of a job still playing may still be recording
                run = self.client.run(run_id)
                if run.status.finished:
                    runs.append(run)
                    landed(run)
            if job.status.finished:
                return job
            time.sleep(POLL_S)

    def list_runs(self, query: RunQuery, limit: int | None = DEFAULT_PAGE) -> doc.RunPage:
        return self.client.newest_runs(query, limit=limit)

    def run_document(self, run_id: str) -> doc.RunDocument:
        return self.client.run(run_id)

    def export_run(self, run_id: str, fmt: str, out: str | Path) -> Path:
        path = export_path(run_id, fmt, out)
        with tempfile.TemporaryDirectory(prefix="hdrig-export-") as scratch:
            native = self.client.download(run_id, "parquet", out=Path(scratch) / f"{run_id}.parquet")
            columns, meta = read_parquet(native)  # as stored: no columns derived on the way
            return write_run(Run(columns, meta).validate(where=f"run {run_id}"), path)

    # ---- fits and gap analyses ----------------------------------------------------------------------

    def fit(self, order: AnalysisOrder, progress: Progress) -> doc.FitDocument:
        if not order.joint:
            raise UserInputError(
                "fit --no-joint: the service always refines jointly; run it without --server"
            )
        job = self._analysis(doc.JobKind.FIT, order, progress)
        result = dict(job.result or {})
        result["fit_error"] = _nan_for_null(result.get("fit_error") or {}, "before", "after")
        document = doc.FitDocument.model_validate(result)
        assert order.out is not None, "fit --out is required (rig.cli)"
        document.model_file = str(self.client.download_file("fits", job.id, MODEL_FILE, order.out))
        if order.report_dir is not None and document.report is not None:
            document.report = str(self._report("fits", job.id, order.report_dir, [document.report])[0])
        return document

    def find_gaps(self, order: AnalysisOrder, progress: Progress) -> doc.GapsDocument:
        job = self._analysis(doc.JobKind.GAPS, order, progress)
        result = _nan_for_null(dict(job.result or {}), "initial_gap", "final_gap")
        result["steps"] = [_nan_for_null(step, "gap_before", "gap_after") for step in result.get("steps", [])]
        document = doc.GapsDocument.model_validate(result)
        if order.out is not None:
            document.final_model = str(self.client.download_file("gaps", job.id, MODEL_FILE, order.out))
        if order.report_dir is not None:
            report = self._report("gaps", job.id, order.report_dir, document.report)
            document.report = [str(p) for p in report]
        return document

    def _analysis(self, kind: doc.JobKind, order: AnalysisOrder, progress: Progress) -> doc.JobDocument:
        if order.mapping:
            raise UserInputError("--map: mapped files are read on this machine only: run it without --server")
        for ref in order.data:
            _not_a_file(ref, "data")
        _not_a_file(order.model, "model")
        job = self.client.analysis(kind, AnalysisRequest(data=list(order.data), model=order.model))
        while not job.status.finished:
            progress(job.progress.phase, job.progress.fraction)
            time.sleep(POLL_S)
            job = self.client.job(job.id)
        if job.status != doc.JobStatus.COMPLETE:
            raise _job_error(job)
        return job

    def _report(
        self, kind: Literal["fits", "gaps"], job_id: str, report_dir: str | Path, named: Sequence[str]
    ) -> list[Path]:
        """Download the analysis' report into `report_dir`; the local paths of the files `named` (the
        service's paths, as its document names them)."""
        target = Path(report_dir)
        prefix = f"{REPORT_DIR}/"
        for name in self.client.files(kind, job_id):
            if name.startswith(prefix):
                self.client.download_file(kind, job_id, name, target / name.removeprefix(prefix))
        return [target / _after(path, f"/{REPORT_DIR}/") for path in named]


def _nan_for_null(document: Any, *names: str) -> dict[str, Any]:
    """JSON has no NaN: the service sends null for a figure that could not be computed (a fit error
    with no trajectory runs); the document holds NaN again, as the local one does."""
    out = dict(document)
    for name in names:
        if out.get(name, 0.0) is None:
            out[name] = float("nan")
    return out


def _after(path: str, marker: str) -> str:
    """The part of a service-side path after its report folder (`.../report/plots/a.png` → `plots/a.png`)."""
    return path.rsplit(marker, 1)[-1] if marker in path else Path(path).name


def _not_a_file(ref: str, what: str) -> None:
    if Path(ref).is_file():
        raise UserInputError(
            f"{what} {ref}: a file on this machine; the service reads only its own store and presets"
            " (run ids, `latest`, preset names): run it without --server"
        )


def _job_error(job: doc.JobDocument) -> Exception:
    """What a local run of the job would have raised: a device fault, bad input found late, or a bug."""
    why = job.error or f"job {job.id} ended {job.status}"
    if job.status == doc.JobStatus.ABORTED and why.startswith("aborted: "):
        return DeviceFaultError(why.removeprefix("aborted: "))
    if why.startswith(INTERNAL_ERROR):
        return ServiceError(500, "Internal server error", f"job {job.id}: {why}")
    return UserInputError(why)
