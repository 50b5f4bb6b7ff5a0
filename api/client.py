"""A Python client of the REST service (`hdrig serve`), on httpx, for lab scripts and CI.

    from api.client import HdrigClient

    with HdrigClient("http://127.0.0.1:8000", key) as lab:
        run = lab.start_run("speed-sweep", {"hold_s": 0.5})
        run = lab.wait(run.id, timeout_s=120)  # follows the run's event stream to its end
        lab.download(run.id, "csv", columns=["omega_m", "i_a"], out="sweep.csv")
        fit = lab.fit([run.id], "seed")  # waits for the job; fit.result is `hdrig fit --json`'s document

Answers are the core's documents (`rig.core.documents`), the same the command line prints with
`--json`. An error answer (RFC 9457 problem+json) raises `ServiceError` with its status, title and
detail; a 4xx raises `ServiceInputError`, which is also a `UserInputError`, so the command line's edge
shows it as one line and exits 2. A service that cannot be reached raises `ServiceUnreachableError`
naming the URL.
"""

from __future__ import annotations

import json
import re
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import httpx

from model.errors import UserInputError
from rig.core.documents import (
    ExperimentInfo,
    JobDocument,
    JobKind,
    JobStatus,
    ModelSummary,
    RunDocument,
    RunPage,
)
from rig.core.operations import AnalysisRequest, RunRequest, operation
from rig.status import RunStatus
from rig.store.catalog import DEFAULT_PAGE, MAX_PAGE
from rig.store.runs import RunQuery, query_of

API = "/api/v1"
TIMEOUT_S = 30.0  # one request's connect/read limit; a download or a stream reads in pieces within it
STREAM_READ_S = 30.0  # the service sends a keep-alive every 10 s: a quiet stream longer than this is dead
POLL_S = 0.25  # a job's document is polled this often (jobs have no stream of their own)
Format = Literal["parquet", "csv", "mat"]


class ServiceError(Exception):
    """The service answered with an error (a problem+json document, or a bare HTTP error)."""

    def __init__(
        self,
        status: int,
        title: str,
        detail: str,
        body: dict[str, Any] | None = None,
        retry_after_s: float | None = None,
    ) -> None:
        super().__init__(detail)
        self.status, self.title, self.detail = status, title, detail
        self.body = body or {}  # the whole problem document (`errors`: each bad field)
        self.retry_after_s = retry_after_s  # 409 busy: when to ask again


class ServiceInputError(ServiceError, UserInputError):
    """A 4xx: the request was wrong (bad field, unknown run, no key, too low a role, rig busy)."""


class ServiceUnreachableError(UserInputError):
    """No service answers at the URL (refused, unknown host, timed out)."""


@dataclass(frozen=True)
class ServerEvent:
    """One Server-Sent Event of a run's stream."""

    id: int
    kind: str  # state, progress, samples, alarm, run
    data: dict[str, Any]


def _raise_for(response: httpx.Response) -> None:
    if response.is_success:
        return
    response.read()
    try:
        body = response.json()
    except ValueError:
        body = None
    if isinstance(body, dict) and "detail" in body and isinstance(body["detail"], str):
        title, detail = str(body.get("title", response.reason_phrase)), body["detail"]
    else:
        body = {}
        title = response.reason_phrase or "Error"
        detail = f"HTTP {response.status_code} {title} from {response.request.method} {response.request.url}"
    retry = response.headers.get("retry-after")
    kind = ServiceInputError if 400 <= response.status_code < 500 else ServiceError
    raise kind(response.status_code, title, detail, body, float(retry) if retry else None)


class HdrigClient:
    """The service at `base_url` (`http://127.0.0.1:8000`), with an API key from `hdrig keys create`."""

    def __init__(self, base_url: str, key: str | None, timeout_s: float = TIMEOUT_S) -> None:
        self.base_url = base_url.rstrip("/")
        headers = {"Authorization": f"Bearer {key}"} if key else {}
        self._http = httpx.Client(base_url=self.base_url, headers=headers, timeout=timeout_s)

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> HdrigClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---- transport --------------------------------------------------------------------------------

    def _request(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        try:
            response = self._http.request(method, f"{API}{path}", **kwargs)
        except httpx.TransportError as exc:
            raise self._unreachable(exc) from None
        _raise_for(response)
        return response

    def _unreachable(self, exc: httpx.TransportError) -> ServiceUnreachableError:
        why = type(exc).__name__ if not str(exc) else str(exc)
        return ServiceUnreachableError(f"no hdrig service answers at {self.base_url}: {why}")

    def _get(self, path: str, **params: Any) -> Any:
        return self._request("GET", path, params={k: v for k, v in params.items() if v is not None}).json()

    def _post(self, path: str, body: dict[str, Any] | None = None) -> Any:
        return self._request("POST", path, json=body).json()

    def _object(self, method: str, path: str) -> dict[str, Any]:
        """A route's JSON object, no parameters asked."""
        answer: dict[str, Any] = self._request(method, path).json()
        return answer

    # ---- the rig and what it offers ---------------------------------------------------------------

    def health(self) -> dict[str, Any]:
        """`{"status": "ok"}` (needs no key)."""
        return self._object("GET", "/health")

    def rig(self) -> dict[str, Any]:
        """The rig: name, backend, mode (sim/hardware), state, health, limits, the current run."""
        return self._object("GET", _path("rig_status"))

    def experiments(self) -> list[ExperimentInfo]:
        return [ExperimentInfo.model_validate(e) for e in self._get(_path("list_experiments"))]

    def models(self) -> list[ModelSummary]:
        return [ModelSummary.model_validate(m) for m in self._get(_path("list_models"))]

    def model(self, name: str) -> dict[str, Any]:
        """A preset as a model file's content (`hdrig model show NAME --json`)."""
        return self._object("GET", _path("show_model", name=name))

    def stop(self) -> dict[str, Any]:
        """Stop everything now (the rig quick-stops, the queue is cancelled); always accepted."""
        return self._object("POST", _path("stop"))

    # ---- runs ---------------------------------------------------------------------------------------

    def reset(self) -> dict[str, Any]:
        """Leave the faulted state (operator)."""
        return self._object("POST", _path("reset"))

    # ---- runs ---------------------------------------------------------------------------------------

    def start(self, request: RunRequest) -> RunDocument | JobDocument:
        """Start an experiment: its run's document (status queued or running); the campaign answers with
        its job's document. A busy rig raises ServiceInputError 409 unless `request.queue`."""
        answer = self._post(_path("start_run"), request.model_dump(mode="json", exclude_none=True))
        if "kind" in answer:
            return JobDocument.model_validate(answer)
        return RunDocument.model_validate(answer)

    def start_run(
        self, experiment: str, params: dict[str, Any] | None = None, **options: Any
    ) -> RunDocument | JobDocument:
        """`start` with the request's fields by name: `queue`, `keep_going`, `unit` (the gear on the bench;
        default: the rig file's), `tags` (free tags for the catalog). The service judges the values."""
        fields = {"experiment": experiment, "params": params or {}, "tags": [], **options}
        return self.start(RunRequest.model_construct(**{**fields, "tags": list(fields["tags"])}))

    def runs_page(
        self,
        query: RunQuery | None = None,
        limit: int = DEFAULT_PAGE,
        cursor: str | None = None,
        **filters: Any,
    ) -> RunPage:
        """One page of the catalog (one request): the newest `limit` runs (1 to 1000) before `cursor` (a
        page's `next_cursor`; None: from the newest) that `query` (or its fields by name) selects, oldest
        first. Queued runs come on the first page of an unfiltered listing."""
        asked = query_of(query, filters).model_dump(by_alias=True, exclude_none=True)
        pairs: list[tuple[str, str | int]] = [("tag", t) for t in asked.pop("tag", [])]  # repeated
        pairs += [*asked.items(), ("limit", limit)] + ([("cursor", cursor)] if cursor is not None else [])
        response = self._request("GET", _path("list_runs"), params=pairs)
        runs = [RunDocument.model_validate(r) for r in response.json()]
        older = response.links.get("next", {}).get("url")
        return RunPage(
            runs=runs,
            total=int(response.headers.get("X-Total-Count", len(runs))),
            next_cursor=httpx.URL(older).params.get("cursor") if older else None,
        )

    def newest_runs(self, query: RunQuery | None = None, limit: int | None = None, **filters: Any) -> RunPage:
        """The newest `limit` runs of the catalog (every one when None) that `query` (or its fields by name)
        selects, oldest first, read a page at a time; `total` counts all it selects, `next_cursor` the
        older rest. Runs added meanwhile are newer than the first page: no run is listed twice or left out."""
        query = query_of(query, filters)
        pages: list[list[RunDocument]] = []
        total, cursor, got = 0, None, 0
        while limit is None or got < limit:
            size = MAX_PAGE if limit is None else min(MAX_PAGE, limit - got)
            page = self.runs_page(query, size, cursor)
            total = total if pages else page.total
            pages.append(page.runs)
            got += sum(run.status != RunStatus.QUEUED for run in page.runs)  # the queue is not paged
            cursor = page.next_cursor
            if cursor is None:
                break
        return RunPage(
            runs=[run for runs in reversed(pages) for run in runs], total=total, next_cursor=cursor
        )

    def runs(
        self, query: RunQuery | None = None, limit: int | None = None, **filters: Any
    ) -> list[RunDocument]:
        """The runs `query` (or its fields by name: `unit="HD25-*"`, `tags=[...]`) selects, oldest first:
        the newest `limit` (every one when None)."""
        return self.newest_runs(query, limit, **filters).runs

    def run(self, run_id: str) -> RunDocument:
        return RunDocument.model_validate(self._get(_path("show_run", run_id=run_id)))

    def abort(self, run_id: str) -> RunDocument:
        """Stop this run: the rig quick-stops; the data so far are kept and the run ends `aborted`."""
        return RunDocument.model_validate(self._post(_path("abort_run", run_id=run_id)))

    def events(self, run_id: str, last_event_id: int | None = None) -> Iterator[ServerEvent]:
        """The run's Server-Sent Events after `last_event_id`, until its final `run` event."""
        headers = {"Last-Event-ID": str(last_event_id)} if last_event_id else {}
        timeout = httpx.Timeout(TIMEOUT_S, read=STREAM_READ_S)
        try:
            with self._http.stream(
                "GET", f"{API}{_path('run_events', run_id=run_id)}", headers=headers, timeout=timeout
            ) as response:
                _raise_for(response)
                yield from _parse_sse(response.iter_lines())
        except httpx.TransportError as exc:
            raise self._unreachable(exc) from None

    def wait(self, run_or_job_id: str, timeout_s: float | None = None) -> RunDocument | JobDocument:
        """Block until the run (or job: fit, gaps, campaign) has ended; its final document.

        A run is followed on its event stream; should the stream end early, by polling. A job is
        polled. TimeoutError when it has not ended within `timeout_s`.
        """
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        try:
            run = self.run(run_or_job_id)
        except ServiceInputError as exc:
            if exc.status != 404:
                raise
            return self.wait_job(run_or_job_id, timeout_s)
        if not run.status.finished:
            for event in self._events_until(run.id, deadline):
                if event.kind == "run" and RunStatus(event.data["status"]).finished:
                    break
        while not (run := self.run(run.id)).status.finished:  # the stream ended early: poll
            _sleep_before(deadline, f"run {run.id} is still {run.status}")
        return run

    def _events_until(self, run_id: str, deadline: float | None) -> Iterator[ServerEvent]:
        for event in self.events(run_id):
            yield event
            if deadline is not None and time.monotonic() > deadline:
                raise TimeoutError(f"run {run_id} has not ended by the deadline")

    def download(
        self,
        run_id: str,
        format: Format = "parquet",
        columns: Sequence[str] | None = None,
        t0: float | None = None,
        t1: float | None = None,
        out: str | Path | None = None,
    ) -> Path:
        """Write the run's samples (optionally some columns, a time window [s]) to `out` (a file, or a
        folder for `<id>.<format>`; default: that name in the current folder); the path written."""
        params: dict[str, Any] = {"format": format, "t0": t0, "t1": t1}
        if columns:
            params["columns"] = ",".join(columns)
        path = Path(out) if out is not None else Path.cwd()
        if path.is_dir():
            path = path / f"{run_id}.{format}"
        self._save(
            _path("export_run", run_id=run_id), path, {k: v for k, v in params.items() if v is not None}
        )
        return path

    def _save(self, route: str, path: Path, params: dict[str, Any] | None = None) -> None:
        part = path.with_name(path.name + ".part")
        try:
            with self._http.stream("GET", f"{API}{route}", params=params) as response:
                _raise_for(response)
                path.parent.mkdir(parents=True, exist_ok=True)
                with part.open("wb") as f:
                    for piece in response.iter_bytes():
                        f.write(piece)
        except httpx.TransportError as exc:
            part.unlink(missing_ok=True)
            raise self._unreachable(exc) from None
        part.replace(path)  # a file is there whole or not at all

    def artifacts(self, run_id: str) -> list[str]:
        """The run's artifacts (tables, results.json, plots), relative to its artifacts folder."""
        files: list[str] = self._get(_path("run_artifacts", run_id=run_id))["files"]
        return files

    def download_artifact(self, run_id: str, name: str, out: str | Path) -> Path:
        path = Path(out)
        self._save(_path("run_artifact", run_id=run_id, path=name), path)
        return path

    # ---- jobs: fits and gap analyses ----------------------------------------------------------------

    def analysis(self, kind: JobKind, request: AnalysisRequest) -> JobDocument:
        """Start a fit or a gap analysis: its job's document (queued or running)."""
        return JobDocument.model_validate(self._post(_path(str(kind)), request.model_dump(mode="json")))

    def fit(
        self, data: Sequence[str], model: str, wait: bool = True, timeout_s: float | None = None
    ) -> JobDocument:
        """A fit of `model` (a preset) to runs (ids, or `latest`). With `wait`, the finished job:
        `.result` is `hdrig fit --json`'s document; `files("fits", id)` lists its model and report."""
        job = self.analysis(JobKind.FIT, AnalysisRequest.model_construct(data=list(data), model=model))
        return self.wait_job(job.id, timeout_s) if wait else job

    def gaps(
        self, data: Sequence[str], model: str, wait: bool = True, timeout_s: float | None = None
    ) -> JobDocument:
        """The model-gap workflow on runs; with `wait`, `.result` is `hdrig gaps --json`'s document."""
        job = self.analysis(JobKind.GAPS, AnalysisRequest.model_construct(data=list(data), model=model))
        return self.wait_job(job.id, timeout_s) if wait else job

    def jobs(self) -> list[JobDocument]:
        """Every job of this service's life: runs, campaigns, fits, gap analyses."""
        return [JobDocument.model_validate(j) for j in self._get(_path("list_jobs"))]

    def job(self, job_id: str) -> JobDocument:
        return JobDocument.model_validate(self._get(_path("show_job", job_id=job_id)))

    def wait_job(self, job_id: str, timeout_s: float | None = None) -> JobDocument:
        """Poll a job until it has ended (TimeoutError after `timeout_s`)."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while not (job := self.job(job_id)).status.finished:
            _sleep_before(deadline, f"job {job_id} is still {job.status}")
        return job

    def files(self, kind: Literal["fits", "gaps"], job_id: str) -> list[str]:
        """A fit's or gap analysis' files (result.json, model.yaml, report/...), relative to its folder."""
        files: list[str] = self._get(_path(f"{_job_kind(kind)}_files", job_id=job_id))["files"]
        return files

    def download_file(self, kind: Literal["fits", "gaps"], job_id: str, name: str, out: str | Path) -> Path:
        path = Path(out)
        self._save(_path(f"{_job_kind(kind)}_file", job_id=job_id, path=name), path)
        return path


def _path(name: str, /, **params: str) -> str:
    """The route of the operation `name` under /api/v1, from the action table, its `{...}` filled in."""
    route = operation(name).rest
    assert route is not None, f"operation {name} has no route"
    return re.sub(r"\{(\w+)(?::path)?\}", lambda found: params[found.group(1)], route[1])


def _job_kind(folder: Literal["fits", "gaps"]) -> JobKind:
    return JobKind.FIT if folder == "fits" else JobKind.GAPS


def _sleep_before(deadline: float | None, what: str) -> None:
    if deadline is not None and time.monotonic() + POLL_S > deadline:
        raise TimeoutError(f"{what} at the deadline")
    time.sleep(POLL_S)


def _parse_sse(lines: Iterator[str]) -> Iterator[ServerEvent]:
    """Server-Sent Events (the WHATWG format): `id:`, `event:`, `data:` lines, a blank line ends one;
    `:` lines are comments (keep-alives)."""
    event_id, kind, data = 0, "message", list[str]()
    for line in lines:
        if not line:
            if data:
                yield ServerEvent(event_id, kind, json.loads("\n".join(data)))
            kind, data = "message", []
            continue
        if line.startswith(":"):
            continue
        name, _, value = line.partition(":")
        value = value.removeprefix(" ")
        if name == "id":
            event_id = int(value)
        elif name == "event":
            kind = value
        elif name == "data":
            data.append(value)


__all__ = [
    "HdrigClient",
    "JobStatus",
    "ServerEvent",
    "ServiceError",
    "ServiceInputError",
    "ServiceUnreachableError",
]
