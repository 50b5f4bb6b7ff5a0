"""The run store: a catalog of runs (`rig.store.catalog`: SQLite in the home folder, or a database URL)
plus their time series as Parquet files (`rig.store.datastore`: the home folder, or object storage), and
each run's artifacts in the home folder.

Layout under the home folder (the data files under `$HDRIG_DATA` instead, when set):

    catalog.sqlite                  table `runs`, one row per run (WAL mode: readers never block the writer);
                                    table `checkpoints`, the estimates of each checkpoint of an endurance run;
                                    `run_tags`, `unit_fits`, `keys`, `audit` (or at `$HDRIG_CATALOG`)
    runs/<id>/part-000000.parquet   while recording: one small file per flush
    runs/<id>/merged-000000-000015.parquet   while recording: parts 0..15 compacted into one file
    runs/<id>/data.parquet          once sealed: all rows in one file (row groups of 65,536 rows), with the
                                    run metadata
    runs/<id>/artifacts/            derived results and plots

Crash safety: a flush writes its rows as a new part file under a temporary name and renames it into place,
so every part on disk is a complete Parquet file and a SIGKILL loses only the rows not yet flushed (at most
`flush_interval_s` of data; the first rows reach the disk within `FIRST_FLUSH_S`, and the runner asks for a
flush at every segment's end, so a run recorded in virtual time, faster than any interval, is kept too).
A run whose writer process has died is found by its pid when runs are listed, marked `interrupted`, and
sealed from the parts it left; an analysis whose process died is listed `analysis: interrupted`.

Any length: while recording, every MERGE_FANIN parts are compacted (on a thread of their own, so flushes
stay on time) into one merged file, and every MERGE_FANIN merged files of one size into one of the next, so
a day at one flush a second leaves a few dozen files, not 86,400. A merged file is named by the parts it
holds and renamed into place before its sources are deleted; a reader skips any file whose parts another
file holds, so a crash between the two loses and doubles nothing. Sealing, reading and export stream one
row group at a time: memory does not grow with the run, and a time window or some columns of a long run
are read from the row groups that hold them only.
"""

from __future__ import annotations

import errno
import getpass
import json
import math
import os
import queue
import re
import secrets
import socket
import threading
from collections.abc import Iterator, Sequence
from datetime import UTC, datetime
from enum import StrEnum
from pathlib import Path
from time import monotonic
from types import TracebackType
from typing import Any

import numpy as np
import pyarrow as pa
import sqlalchemy as sa
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from model.errors import UserInputError, describe_validation_error
from model.run import Run, RunFormatError
from rig.faults import StorageFaultError
from rig.status import RunStatus
from rig.store import catalog as tables
from rig.store.catalog import STORED_STATUSES as _STORED
from rig.store.catalog import Catalog, StoreError, default_url
from rig.store.datastore import RunData, default_data_url
from rig.store.importmap import MAPPED_SUFFIXES, ColumnSource, read_mapped
from rig.store.runfile import (
    READ_SUFFIXES,
    ROW_GROUP_ROWS,
    RunFileWriter,
    json_text,
    ordered_columns,
    read_run,
    write_parquet,
)

STORED_STATUSES = tuple(RunStatus(s) for s in _STORED)
"""The statuses a run in the catalog can have (`queued` and `failed` runs never reached the store)."""
EXPORT_FORMATS = ("csv", "parquet", "mat")
DATA_FILE = "data.parquet"
ARTIFACTS_DIR = "artifacts"
FIRST_FLUSH_S = 0.25  # the first rows of a run reach the disk this soon, however long the flush interval


class AnalysisState(StrEnum):
    """Where a run's analysis (tables, plots, metrics) stands, in the catalog's `analysis` column."""

    RUNNING = "running"  # begun by the process in the run's `pid` column
    DONE = "done"
    INTERRUPTED = "interrupted"  # that process died first: `hdrig runs analyze RUN` runs it again
    FAILED = "failed"  # it raised (the run's reason says why)


_CHUNK = re.compile(r"(?:part-(\d+)|merged-(\d+)-(\d+))\.parquet")
MERGE_FANIN = 16
"""Parts per merged file, and merged files of one size per file of the next (16, 256, 4096 parts...)."""
_MERGE_LEVELS = 5  # up to 16**5 parts: 12 days at one flush a second


class UnknownRunError(UserInputError):
    """No run with this id in the catalog."""


def default_home() -> Path:
    """The store's home folder: `$HDRIG_HOME` when set, else `~/.hdrig`."""
    env = os.environ.get("HDRIG_HOME")
    return Path(env).expanduser() if env else Path.home() / ".hdrig"


def _utc(moment: datetime | None = None) -> str:
    return (moment or datetime.now(UTC)).isoformat(timespec="milliseconds")


def new_run_id(experiment: str, moment: datetime | None = None) -> str:
    """A fresh run id: UTC time, the experiment, a random suffix (`20261121-080824-speed-sweep-7173`)."""
    slug = re.sub(r"[^a-z0-9]+", "-", experiment.lower()).strip("-")[:40] or "run"
    return f"{(moment or datetime.now(UTC)):%Y%m%d-%H%M%S}-{slug}-{secrets.token_hex(2)}"


MODELS_DIR = "models"  # models uploaded to the service (`POST /api/v1/models`), one `<name>.yaml` each
MODEL_NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9_-]{0,63}")  # a file name: no '/', no '.'
TAG_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9._:=@/+-]{0,99}")


def check_tags(tags: Sequence[str]) -> list[str]:
    """Free tags, each 1-100 letters, digits or `._:=@/+-` (e.g. `line=3`, `batch:2026-07`), once each."""
    for tag in tags:
        if not isinstance(tag, str) or not TAG_PATTERN.fullmatch(tag):
            raise UserInputError(
                f"tag {tag!r}: 1-100 letters, digits, '.', '_', ':', '=', '@', '/', '+' or '-',"
                " starting with a letter or digit"
            )
    return list(dict.fromkeys(tags))


def os_user() -> str | None:
    """Who runs this process, as the operator of the runs it starts from the command line."""
    try:
        return getpass.getuser()
    except (KeyError, OSError):  # no passwd entry and no LOGNAME/USER: say nothing rather than guess
        return None


def _match(column: Any, pattern: str) -> Any:
    """An exact match, or a glob's (`*`, `?`) as SQL LIKE with the other LIKE characters escaped."""
    if not any(ch in pattern for ch in "*?"):
        return column == pattern
    escaped = pattern.replace("\\", "\\\\").replace("%", "\\%").replace("_", "\\_")
    return column.like(escaped.replace("*", "%").replace("?", "_"), escape="\\")


class RunQuery(BaseModel):
    """Which runs of the catalog: the one declaration of the run filters, for the store, the core, the
    command line (`hdrig runs list --unit ...`), the service (`GET /api/v1/runs?unit=...`) and its client.
    Each text field matches exactly or as a glob (`HD25-*`); a run must carry every one of `tags`."""

    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True)

    unit: str | None = Field(
        default=None, max_length=100, description="gear unit serial, exact or a glob (HD25-*)"
    )
    rig: str | None = Field(default=None, max_length=100, description="rig name, exact or a glob")
    tags: list[str] = Field(
        default_factory=list,
        alias="tag",
        max_length=100,
        description="a tag every run listed carries (repeated: every one of them)",
    )
    operator: str | None = Field(default=None, max_length=100, description="who started it, exact or a glob")
    experiment: str | None = Field(
        default=None, max_length=100, description="the experiment, exact or a glob"
    )
    status: RunStatus | None = Field(
        default=None, description="only runs with this status (`queued`: those waiting for the rig)"
    )

    @property
    def searched(self) -> bool:
        """Some field other than the status narrows the runs (queued runs have none of them yet)."""
        return bool(self.tags) or any(
            v is not None for v in (self.unit, self.rig, self.operator, self.experiment)
        )


def run_filter(query: RunQuery) -> list[Any]:
    """The catalog conditions selecting the runs `query` asks for."""
    runs, run_tags = tables.runs, tables.run_tags
    where = [
        _match(column, value)
        for column, value in (
            (runs.c.unit, query.unit),
            (runs.c.rig, query.rig),
            (runs.c.operator, query.operator),
            (runs.c.experiment, query.experiment),
            (runs.c.status, query.status),
        )
        if value is not None
    ]
    for tag in query.tags:
        where.append(runs.c.id.in_(sa.select(run_tags.c.run_id).where(_match(run_tags.c.tag, tag))))
    return where


def query_of(query: RunQuery | None, filters: dict[str, Any]) -> RunQuery:
    """`query`, or a query of the `filters` given by name (`unit="HD25-*"`, `tags=[...]`)."""
    if query is not None and filters:
        raise TypeError(f"a RunQuery or its fields by name, not both: {sorted(filters)}")
    if query is not None:
        return query
    try:
        return RunQuery(**filters)
    except ValidationError as exc:
        raise UserInputError(describe_validation_error(exc)) from None


def _process_start(pid: int) -> tuple[str, str] | None:
    """(state, start time in clock ticks since boot) from Linux /proc; None where there is no /proc."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = stat[stat.rindex(")") + 2 :].split()  # the command name may itself hold spaces and ')'
    return fields[0], fields[19]


def _process_alive(pid: int | None, host: str | None, pid_started: str | None) -> bool:
    """Whether the process that wrote a run may still be writing it; when unsure, say alive."""
    if pid is None or host != socket.gethostname() or os.name != "posix":
        # Another machine's processes cannot be seen; on Windows os.kill(pid, 0) would terminate the process.
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass  # exists, belongs to another user
    stat = _process_start(pid)
    if stat is None:
        return True
    state, started = stat
    # A zombie has exited; a different start time means the pid was reused by another process.
    return state != "Z" and (pid_started is None or started == pid_started)


class UnknownColumnError(UserInputError):
    """A column asked for that the run does not have; the message lists the ones it has."""


def _part_range(name: str) -> tuple[int, int] | None:
    """(first, last) part number a part or merged file holds; None for any other file."""
    m = _CHUNK.fullmatch(name.rsplit("/", 1)[-1])
    if m is None:
        return None
    if m.group(1) is not None:
        return int(m.group(1)), int(m.group(1))
    return int(m.group(2)), int(m.group(3))


def _chunks(data: RunData, run_id: str) -> list[str]:
    """A recording run's part and merged files (paths) in row order, each row once: a file whose parts
    another file also holds (a compaction's sources not yet deleted) is left out."""
    found = sorted(
        (span[0], -span[1], name) for name in data.names(run_id) if (span := _part_range(name)) is not None
    )
    kept: list[str] = []
    covered = -1
    for _, neg_last, name in found:  # by first part, the widest file first
        if -neg_last > covered:
            kept.append(data.path(run_id, name))
            covered = -neg_last
    return kept


def _copy_rows(data: RunData, sources: list[str], run_id: str, target: str, meta: dict[str, Any]) -> int:
    """Stream the rows of a run's Parquet files, in order, into its file `target` of whole row groups;
    rows copied."""
    with data.parquet(sources[0]) as first:
        names = ordered_columns(first.schema_arrow.names)
    with (
        data.writing(run_id, target) as local,
        RunFileWriter(local, names, meta, as_run=False, checked=False) as writer,
    ):
        for source in sources:
            with data.parquet(source) as parquet:
                for group in range(parquet.num_row_groups):
                    table = parquet.read_row_group(group, columns=names)
                    writer.write({c: table.column(c).to_numpy() for c in names})
            _release_pool()
    return writer.check.rows


def _merges_due(part: int) -> list[tuple[int, int]]:
    """The (first, last) part ranges to compact once part number `part` is on disk, smallest first."""
    due = []
    span = MERGE_FANIN
    for _ in range(_MERGE_LEVELS):
        if (part + 1) % span:
            break
        due.append((part + 1 - span, part))
        span *= MERGE_FANIN
    return due


def _release_pool() -> None:
    """Hand what pyarrow's pool (mimalloc) holds freed back to the OS. It keeps what one file's reading or
    writing freed and does not reuse it for the next: reading 16 parts of 60,000 rows peaked at +32 MB
    without this after each file, +16 MB with it. It frees the calling thread's cache only."""
    pa.default_memory_pool().release_unused()


class _Compactor:
    """Merges a recording run's parts on one thread of its own, so the flushes that write parts stay on
    time. One thread for the whole run, not one per burst of merges (threads, each with its own malloc
    arena and pyarrow heap, came and went for hours)."""

    def __init__(self, data: RunData, run_id: str) -> None:
        self.data = data
        self.run_id = run_id
        self._queue: queue.Queue[tuple[int, int] | None] = queue.Queue()
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None

    def part_written(self, part: int) -> None:
        due = _merges_due(part)
        if not due:
            return
        if self._thread is None:  # started by the first merge: a short run never has one
            self._thread = threading.Thread(target=self._work, name=f"compact-{self.run_id}", daemon=True)
            self._thread.start()
        for span in due:
            self._queue.put(span)

    def _work(self) -> None:
        while (span := self._queue.get()) is not None:
            try:
                if self._error is None:  # after a failure the rest are skipped; join() raises it
                    self._merge(*span)
            except BaseException as exc:  # raised again by join(): a failed merge is a bug or a full disk
                self._error = exc
            finally:
                self._queue.task_done()
        self._queue.task_done()

    def _merge(self, first: int, last: int) -> None:
        sources = []
        for path in _chunks(self.data, self.run_id):
            span = _part_range(path)
            if span is not None and first <= span[0] and span[1] <= last:
                sources.append(path)
        _copy_rows(self.data, sources, self.run_id, f"merged-{first:06d}-{last:06d}.parquet", {})
        for source in sources:  # only once the merged file is in place
            self.data.delete(source)

    def join(self) -> None:
        """Wait for the merges asked so far; raise the error of one that failed."""
        self._queue.join()
        if self._error is not None:
            raise self._error

    def close(self) -> None:
        """Let the thread end once the merges asked so far are done (the writer is finished)."""
        if self._thread is not None:
            self._queue.put(None)
            self._thread.join()
            self._thread = None


class RunStore:
    """The catalog and data of all runs under `home` (default: `default_home()`).

    `catalog`: a database URL (default `$HDRIG_CATALOG`, else SQLite `catalog.sqlite` in `home`); `data`:
    where the runs' sample files live (default `$HDRIG_DATA`, else `home`), a folder or an fsspec URL
    such as `s3://bucket/prefix`. Artifacts and analyses stay in `home`.
    """

    def __init__(
        self,
        home: str | os.PathLike[str] | None = None,
        catalog: str | None = None,
        data: str | os.PathLike[str] | None = None,
    ) -> None:
        self.home = Path(home) if home is not None else default_home()
        try:
            # The store is this user's: its folders 0700 (a run's files, the keys' hashes and the audit
            # log are nobody else's to read), the catalog's files 0600 (`Catalog`).
            if self.home.exists() and not self.home.is_dir():
                raise NotADirectoryError(errno.ENOTDIR, os.strerror(errno.ENOTDIR))
            self.home.mkdir(mode=0o700, parents=True, exist_ok=True)
            (self.home / "runs").mkdir(mode=0o700, exist_ok=True)
            for folder in (self.home, self.home / "runs"):
                if folder.stat().st_mode & 0o077:
                    folder.chmod(0o700)
        except OSError as exc:
            raise StoreError(
                f"{self.home}: cannot hold the run store ({exc.strerror});"
                " set HDRIG_HOME to a writable folder"
            ) from None
        self.catalog = Catalog(catalog or default_url(self.home))
        self.catalog_path: Path | None = (
            Path(str(self.catalog.url.database)) if self.catalog.is_sqlite else None
        )
        """The SQLite file of the catalog; None for a catalog on a database server (see `catalog.where`)."""
        self.data = RunData(data if data is not None else default_data_url(self.home))

    # ---- models kept by name (the service's clients name models, never paths) --------------------

    @property
    def models_dir(self) -> Path:
        return self.home / MODELS_DIR

    def model_names(self) -> list[str]:
        """The models kept in the store, by name."""
        folder = self.models_dir
        return sorted(p.stem for p in folder.glob("*.yaml") if MODEL_NAME_PATTERN.fullmatch(p.stem))

    def model_file(self, name: str) -> Path | None:
        """The file of the model kept as `name`; None when there is none (a name is never a path)."""
        if not MODEL_NAME_PATTERN.fullmatch(name):
            return None
        path = self.models_dir / f"{name}.yaml"
        return path if path.is_file() else None

    def keep_model(self, name: str, text: str) -> Path:
        """Keep a model file's text (already validated by the caller) as `name`: written whole (a
        temporary file renamed), readable by this user only; a name already kept is refused."""
        if not MODEL_NAME_PATTERN.fullmatch(name):
            raise UserInputError(
                f"model name {name[:80]!r}: 1-64 letters, digits, '_' or '-', starting with a letter or digit"
            )
        folder = self.models_dir
        folder.mkdir(mode=0o700, exist_ok=True)
        path = folder / f"{name}.yaml"
        temporary = folder / f".{name}.{secrets.token_hex(4)}.tmp"
        fd = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w") as out:
            out.write(text)
        try:
            os.link(temporary, path)  # fails if the name is taken, so two uploads cannot both win
        except FileExistsError:
            raise UserInputError(f"model name {name!r} is taken") from None
        finally:
            temporary.unlink()
        return path

    def close(self) -> None:
        """Close the catalog's connections and files: a store made for a while (the validation's
        temporary one) is closed before its folder goes, or each leaves its catalog's descriptors open."""
        self.catalog.close()

    def __enter__(self) -> RunStore:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    # ---- recording ------------------------------------------------------------------------------

    def open_run(
        self,
        experiment: str,
        rig: str,
        model_name: str | None,
        model_hash: str | None,
        columns: list[str],
        meta: dict[str, Any],
        flush_interval_s: float = 1.0,
        background: bool = False,
        run_id: str | None = None,
        max_pending_rows: int | None = None,
        unit: str | None = None,
        operator: str | None = None,
        tags: Sequence[str] = (),
    ) -> RunWriter:
        """Start a run in the catalog (status `running`) and return its writer (see RunWriter).

        `run_id`: an id from `new_run_id`, reserved by a caller that had to name the run before it began.
        `max_pending_rows`: see RunWriter (a rig in virtual time; None for one in real time).
        `unit`: the gear's serial number; `operator`: who started it (default: this process' OS user);
        `tags`: free tags to search the run by (`check_tags`).
        """
        if "t" not in columns:
            raise ValueError(f"run columns {columns} lack the time column 't'")
        if len(set(columns)) != len(columns):
            raise ValueError(f"run columns {columns} name a column twice")
        tag_list = check_tags(tags)
        now = datetime.now(UTC)
        stat = _process_start(os.getpid())
        row: dict[str, Any] = {
            "experiment": experiment,
            "rig": rig,
            "model_name": model_name,
            "model_hash": model_hash,
            "status": RunStatus.RUNNING.value,
            "started": _utc(now),
            "meta": json_text(meta),
            "pid": os.getpid(),
            "host": socket.gethostname(),
            "pid_started": stat[1] if stat else None,
            "unit": unit,
            "operator": operator or os_user(),
        }
        for _ in range(10):
            chosen = run_id or new_run_id(experiment, now)
            row.update(id=chosen, path=f"runs/{chosen}")
            try:
                with self.catalog.write() as db:
                    db.execute(tables.runs.insert().values(**row))
                    if tag_list:
                        db.execute(tables.run_tags.insert(), [{"run_id": chosen, "tag": t} for t in tag_list])
                break
            except sa.exc.IntegrityError:
                if run_id is not None:
                    raise ValueError(f"run id {run_id!r} is already in {self.catalog.where}") from None
                # the random suffix collided within the same second: draw another
        else:
            raise RuntimeError(f"could not find a free run id for {experiment!r} in {self.catalog.where}")
        run_id = chosen
        self.run_dir(run_id).mkdir(mode=0o700)
        self.data.make_run_folder(run_id)
        return RunWriter(self, run_id, columns, flush_interval_s, background, max_pending_rows, meta)

    def _seal(self, run_id: str) -> tuple[int, str]:
        """Stream a run's part and merged files into `data.parquet`; return (samples, catalog path)."""
        chunks = _chunks(self.data, run_id)
        data = self.data.path(run_id, DATA_FILE)
        if not chunks:
            if not self.data.exists(data):
                return 0, f"runs/{run_id}"  # nothing was ever flushed
            with self.data.parquet(data) as parquet:
                return parquet.metadata.num_rows, f"runs/{run_id}/{DATA_FILE}"
        with self.catalog.read() as db:
            row = self._row(db, run_id)
        samples = _copy_rows(self.data, chunks, run_id, DATA_FILE, self._run_meta(row))
        # Chunks go only after the data file is in place; a reader meanwhile prefers the data file. A writer
        # killed mid-flush or mid-merge also leaves a temporary file behind (on disk; an object store keeps
        # no partial uploads under a name).
        for leftover in self.data.names(run_id):
            temporary = leftover.startswith(".") and leftover.endswith(".tmp")
            if temporary or _part_range(leftover) is not None:
                self.data.delete(self.data.path(run_id, leftover))
        return samples, f"runs/{run_id}/{DATA_FILE}"

    # ---- catalog --------------------------------------------------------------------------------

    def _row(self, db: sa.Connection, run_id: str) -> dict[str, Any]:
        row = db.execute(sa.select(tables.runs).where(tables.runs.c.id == run_id)).first()
        if row is None:
            raise UnknownRunError(f"unknown run id {run_id!r} (not in {self.catalog.where})")
        return dict(row._mapping)

    def _reconcile(self, rows: list[dict[str, Any]]) -> bool:
        """Mark `running` runs, and running analyses, whose process has died as `interrupted`; True if any
        changed."""
        runs = tables.runs
        changed = False
        for row in rows:
            if row["analysis"] == AnalysisState.RUNNING and not _process_alive(
                row["pid"], row["host"], row["pid_started"]
            ):
                with self.catalog.write() as db:
                    db.execute(
                        runs.update()
                        .where(runs.c.id == row["id"], runs.c.analysis == AnalysisState.RUNNING.value)
                        .values(analysis=AnalysisState.INTERRUPTED.value)
                    )
                changed = True
            if row["status"] != RunStatus.RUNNING or _process_alive(
                row["pid"], row["host"], row["pid_started"]
            ):
                continue
            with self.catalog.write() as db:
                # Only the lister whose update lands seals the run, so two listers never seal it together.
                where = f" on {row['host']}" if row.get("host") else ""
                claimed = db.execute(
                    runs.update()
                    .where(runs.c.id == row["id"], runs.c.status == RunStatus.RUNNING.value)
                    .values(
                        status=RunStatus.INTERRUPTED.value,
                        reason=f"interrupted: the recording process (pid {row['pid']}{where}) ended before"
                        " the run did; its samples up to the last flush are kept",
                    )
                ).rowcount
            if not claimed:
                continue
            chunks = _chunks(self.data, row["id"])
            last_write = max((self.data.modified_s(c) for c in chunks), default=None)
            samples, path = self._seal(row["id"])
            ended = _utc(datetime.fromtimestamp(last_write, UTC)) if last_write else row["started"]
            with self.catalog.write() as db:
                db.execute(
                    runs.update()
                    .where(runs.c.id == row["id"])
                    .values(samples=samples, path=path, ended=ended)
                )
                meta = db.execute(sa.select(runs.c.meta).where(runs.c.id == row["id"])).scalar()
                db.execute(
                    runs.update().where(runs.c.id == row["id"]).values(progress=_progress(meta, samples))
                )
            changed = True
        return changed

    def _public(self, row: dict[str, Any], tags: list[str]) -> dict[str, Any]:
        entry = dict(row)
        entry["metrics"] = json.loads(entry["metrics"])
        entry["meta"] = json.loads(entry["meta"])
        entry["path"] = self.data.display(entry["path"])
        entry["tags"] = tags
        return entry

    @staticmethod
    def _ids(where: list[Any], limit: int | None) -> Any:
        """The ids the filter selects (the newest `limit` of them), as a subquery; None: every run."""
        runs = tables.runs
        if not where and limit is None:
            return None
        ids = sa.select(runs.c.id).where(*where)
        if limit is not None:
            ids = ids.order_by(runs.c.started.desc(), runs.c.id.desc()).limit(limit)
        return ids

    def _select(self, where: list[Any], limit: int | None = None) -> list[dict[str, Any]]:
        runs = tables.runs
        query = sa.select(runs).order_by(runs.c.started, runs.c.id)
        ids = self._ids(where, limit)
        if ids is not None:
            query = query.where(runs.c.id.in_(ids.scalar_subquery()))
        with self.catalog.read() as db:
            return [dict(r._mapping) for r in db.execute(query)]

    def _tags_of(self, where: list[Any], limit: int | None = None) -> dict[str, list[str]]:
        tags = tables.run_tags
        query = sa.select(tags.c.run_id, tags.c.tag).order_by(tags.c.run_id, tags.c.tag)
        ids = self._ids(where, limit)
        if ids is not None:
            query = query.where(tags.c.run_id.in_(ids.scalar_subquery()))
        found: dict[str, list[str]] = {}
        with self.catalog.read() as db:
            for run_id, tag in db.execute(query):
                found.setdefault(run_id, []).append(tag)
        return found

    def list_runs(
        self, query: RunQuery | None = None, limit: int | None = None, **filters: Any
    ) -> list[dict[str, Any]]:
        """The runs `query` (or the same fields given as `filters`) selects, oldest first, each a dict of
        its catalog fields (metrics and meta decoded, `tags` a list); `limit`: only the newest so many."""
        where = run_filter(query_of(query, filters))
        rows = self._select(where, limit)
        if self._reconcile(rows):
            rows = self._select(where, limit)
        tags_of = self._tags_of(where, limit)
        return [self._public(row, tags_of.get(row["id"], [])) for row in rows]

    def get(self, run_id: str) -> dict[str, Any]:
        """One run's catalog fields, as in `list_runs`."""
        with self.catalog.read() as db:
            row = self._row(db, run_id)
        if self._reconcile([row]):
            with self.catalog.read() as db:
                row = self._row(db, run_id)
        return self._public(row, self._tags_of([tables.runs.c.id == run_id]).get(run_id, []))

    def add_tags(self, run_id: str, tags: Sequence[str]) -> list[str]:
        """Put free tags on a run (those it has already are kept once); the run's tags after."""
        tag_list = check_tags(tags)
        run_tags = tables.run_tags
        with self.catalog.write() as db:
            self._row(db, run_id)
            have = set(db.execute(sa.select(run_tags.c.tag).where(run_tags.c.run_id == run_id)).scalars())
            new = [t for t in tag_list if t not in have]
            if new:
                db.execute(run_tags.insert(), [{"run_id": run_id, "tag": t} for t in new])
        return sorted(have | set(new))

    def set_metrics(self, run_id: str, metrics: dict[str, Any]) -> None:
        """Replace a run's metrics (a JSON-serializable dict)."""
        with self.catalog.write() as db:
            self._row(db, run_id)
            db.execute(
                tables.runs.update().where(tables.runs.c.id == run_id).values(metrics=json_text(metrics))
            )

    def set_checkpoints(self, run_id: str, unit: str | None, checkpoints: list[dict[str, Any]]) -> None:
        """Replace a run's checkpoint estimates (each with `index` and `t_s` [s]) for the gear `unit`."""
        table = tables.checkpoints
        with self.catalog.write() as db:
            self._row(db, run_id)
            db.execute(table.delete().where(table.c.run_id == run_id))
            if checkpoints:
                db.execute(
                    table.insert(),
                    [
                        {
                            "run_id": run_id,
                            "idx": int(c["index"]),
                            "unit": unit,
                            "t_s": float(c["t_s"]),
                            "estimates": json_text(c),
                        }
                        for c in checkpoints
                    ],
                )

    def checkpoints(self, run_id: str | None = None, unit: str | None = None) -> list[dict[str, Any]]:
        """Checkpoint estimates of one run, or of every run of a gear unit, in order of the runs' start
        and then of the checkpoints; each with its run's `run_id`, `started` and `unit`."""
        if (run_id is None) == (unit is None):
            raise ValueError("checkpoints: give a run id or a unit, not both")
        c, r = tables.checkpoints, tables.runs
        query = (
            sa.select(c.c.run_id, c.c.unit, c.c.estimates, r.c.started)
            .join(r, r.c.id == c.c.run_id)
            .where(c.c.run_id == run_id if run_id is not None else c.c.unit == unit)
            .order_by(r.c.started, c.c.run_id, c.c.idx)
        )
        with self.catalog.read() as db:
            if run_id is not None:
                self._row(db, run_id)
            rows = db.execute(query).fetchall()
        return [
            {
                **json.loads(row.estimates),
                "run_id": row.run_id,
                "unit": row.unit,
                "started": row.started,
            }
            for row in rows
        ]

    def set_analysis(self, run_id: str, state: AnalysisState) -> None:
        """Record where a run's analysis stands; `running` names this process as the one doing it, so
        a listing finds it `interrupted` should this process die first."""
        runs = tables.runs
        with self.catalog.write() as db:
            self._row(db, run_id)
            update = runs.update().where(runs.c.id == run_id)
            if state == AnalysisState.RUNNING:
                stat = _process_start(os.getpid())
                db.execute(
                    update.values(
                        analysis=state.value,
                        pid=os.getpid(),
                        host=socket.gethostname(),
                        pid_started=stat[1] if stat else None,
                    )
                )
            else:
                db.execute(update.values(analysis=AnalysisState(state).value))

    # ---- data -----------------------------------------------------------------------------------

    def run_dir(self, run_id: str) -> Path:
        """The folder holding a run's artifacts (and its data files, when the data live in the home)."""
        return self.home / "runs" / run_id

    def add_artifact(self, run_id: str, name: str) -> Path:
        """A path in the run's artifacts folder to write a derived result or plot to (not created)."""
        with self.catalog.read() as db:
            self._row(db, run_id)
        relative = Path(name)
        if not name or relative.is_absolute() or ".." in relative.parts:
            raise ValueError(f"artifact name {name!r} must be a relative path inside the run folder")
        path = self.run_dir(run_id) / ARTIFACTS_DIR / relative
        path.parent.mkdir(parents=True, exist_ok=True)
        return path

    @staticmethod
    def _run_meta(row: dict[str, Any]) -> dict[str, Any]:
        # The catalog is the authority on what, where and with which model; the rest is the writer's meta.
        meta: dict[str, Any] = json.loads(row["meta"])
        meta.update(
            run_id=row["id"],
            experiment=row["experiment"],
            rig=row["rig"],
            model={"name": row["model_name"], "hash": row["model_hash"]},
            created=row["started"],
        )
        return meta

    def _sources(self, run_id: str) -> list[str]:
        data = self.data.path(run_id, DATA_FILE)
        return [data] if self.data.exists(data) else _chunks(self.data, run_id)

    def columns(self, run_id: str) -> list[str]:
        """The names of a run's columns, from a file's schema (no rows read); empty before the first flush."""
        with self.catalog.read() as db:
            self._row(db, run_id)
        while True:
            sources = self._sources(run_id)
            if not sources:
                return []
            try:
                with self.data.parquet(sources[0]) as parquet:
                    return ordered_columns(parquet.schema_arrow.names)
            except FileNotFoundError:
                continue  # merged or sealed away since the listing: the new file is there

    def _selected(self, run_id: str, columns: list[str] | None) -> list[str]:
        have = self.columns(run_id)
        if columns is None:
            return have
        unknown = [c for c in columns if c not in have]
        if unknown:
            raise UnknownColumnError(
                f"run {run_id}: no column {unknown[0]!r} (it has {', '.join(have) or 'no samples yet'})"
            )
        return ["t", *[c for c in dict.fromkeys(columns) if c != "t"]]

    def iter_blocks(
        self,
        run_id: str,
        columns: list[str] | None = None,
        t0: float | None = None,
        t1: float | None = None,
        rows: list[tuple[int, int]] | None = None,
    ) -> Iterator[dict[str, np.ndarray]]:
        """A run's samples, one row group at a time (also while it records): `columns` (every one when
        None; `t` always, first), the samples with t0 ≤ t ≤ t1 [s], and with `rows` only those in these
        half-open ranges of row numbers. Only the row groups that may hold such samples are read (their
        `t` statistics), and of those only the columns asked for."""
        names = self._selected(run_id, columns)
        if not names:
            return
        lo = -math.inf if t0 is None else t0
        hi = math.inf if t1 is None else t1
        passed = 0  # rows of the run passed, to go on from there should the files change under us
        while True:
            try:
                for row_end, block in self._scan(run_id, names, lo, hi, rows, passed):
                    passed = row_end
                    if len(block["t"]):
                        yield block
                return
            except FileNotFoundError:
                continue  # merged or sealed while read: list the files again, go on after row `passed`

    def _scan(
        self,
        run_id: str,
        names: list[str],
        lo: float,
        hi: float,
        rows: list[tuple[int, int]] | None,
        skip_to: int,
    ) -> Iterator[tuple[int, dict[str, np.ndarray]]]:
        """(row number after the group, its selected samples) for each row group past row `skip_to`."""
        offset = 0
        for source in self._sources(run_id):
            with self.data.parquet(source) as parquet:
                t_index = parquet.schema_arrow.get_field_index("t")
                for group in range(parquet.num_row_groups):
                    meta = parquet.metadata.row_group(group)
                    start, offset = offset, offset + meta.num_rows
                    if offset <= skip_to or not _may_hold(meta.column(t_index).statistics, lo, hi):
                        continue
                    if rows is not None and not any(a < offset and b > start for a, b in rows):
                        continue
                    table = parquet.read_row_group(group, columns=names)
                    block = {c: np.asarray(table.column(c).to_numpy(), dtype=np.float64) for c in names}
                    keep = (block["t"] >= lo) & (block["t"] <= hi)
                    keep[: max(0, skip_to - start)] = False
                    if rows is not None:
                        index = np.arange(start, offset)
                        keep &= np.logical_or.reduce([(index >= a) & (index < b) for a, b in rows])
                    yield offset, {c: v[keep] for c, v in block.items()}

    def read(
        self,
        run_id: str,
        columns: list[str] | None = None,
        t0: float | None = None,
        t1: float | None = None,
        segments: list[str] | None = None,
    ) -> Run:
        """A run's samples so far (also while it is recording) and its metadata.

        With no selection: every sample, validated as a run. `columns` and `t0`/`t1` [s]: only those
        columns (`t` always) and the samples with t0 ≤ t ≤ t1, read from the row groups that hold them; a
        selection, not checked as a run (it may lack `theta_m` or have fewer than two rows; an unknown
        column is an UnknownColumnError). `segments`: only the rows of the segments with these labels,
        with the `segments` metadata renumbered to match (`segment_rows` works on it), validated as a
        run: what an analysis of a long run reads instead of all of it.
        """
        with self.catalog.read() as db:
            row = self._row(db, run_id)
        meta = self._run_meta(row)
        ranges = None
        if segments is not None:
            wanted = set(segments)
            kept = [dict(seg) for seg in meta.get("segments", []) if seg["label"] in wanted]
            ranges = [(int(seg["start"]), int(seg["start"]) + int(seg["cycles"])) for seg in kept]
            start = 0
            for seg in kept:
                seg["start"] = start
                start += int(seg["cycles"])
            meta["segments"] = kept
        names = self._selected(run_id, columns)
        blocks = list(self.iter_blocks(run_id, columns, t0, t1, ranges))
        data = {c: np.concatenate([b[c] for b in blocks]) if blocks else np.empty(0) for c in names}
        if columns is not None or t0 is not None or t1 is not None:
            return Run(data, meta)
        if not blocks:
            raise RunFormatError(f"run {run_id}: no samples recorded yet (status {row['status']})")
        try:
            return Run(data, meta).validate(where=f"run {run_id}")
        except RunFormatError as e:
            raise RunFormatError(f"{e} (status {row['status']}, {row['samples']} samples)") from e

    def export(
        self,
        run_id: str,
        fmt: str,
        out_path: str | os.PathLike[str],
        columns: list[str] | None = None,
        t0: float | None = None,
        t1: float | None = None,
    ) -> Path:
        """Write a run as csv, parquet or mat; a folder as `out_path` gets `<id>.<fmt>` inside it.

        Streamed a row group at a time, so a run of any length exports in bounded memory. With `columns`
        (`t` always comes too) or a time window t0 ≤ t ≤ t1 [s], only that selection is written (a
        download), not checked as a run.
        """
        out = export_path(run_id, fmt, out_path)
        self._refuse_own_files(out)
        with self.catalog.read() as db:
            row = self._row(db, run_id)
        selection = columns is not None or t0 is not None or t1 is not None
        names = self._selected(run_id, columns)
        if not names:
            raise RunFormatError(f"run {run_id}: no samples recorded yet (status {row['status']})")
        with RunFileWriter(out, names, self._run_meta(row), as_run=not selection) as writer:
            for block in self.iter_blocks(run_id, columns, t0, t1):
                writer.write(block)
        return out

    def _refuse_own_files(self, path: Path) -> None:
        """An export never lands in the store's own files: a run's folder or the catalog (it would replace
        a run's samples behind the catalog's back)."""
        target, home = path.resolve(), self.home.resolve()  # resolved: `..` and links do not get round it
        own = [home / "runs"]
        if self.data.is_local:
            own.append(Path(self.data.root).resolve() / "runs")
        catalog = self.catalog_path is not None and (
            target.parent == self.catalog_path.resolve().parent
            and target.name.startswith(self.catalog_path.name)
        )
        if any(target.is_relative_to(folder) for folder in own) or catalog:
            raise UserInputError(f"{path}: inside the run store's own files ({home}); export outside them")


def export_path(run_id: str, fmt: str, out_path: str | os.PathLike[str]) -> Path:
    """Where an export of a run goes: `out_path`, `<id>.<fmt>` inside it if a folder, `.<fmt>` added to a
    bare name; a suffix that is not the format's is a one-line error."""
    if fmt not in EXPORT_FORMATS:
        raise UserInputError(f"unknown export format {fmt!r}; use one of {', '.join(EXPORT_FORMATS)}")
    out = Path(out_path)
    if out.is_dir():
        out = out / f"{run_id}.{fmt}"
    elif not out.suffix:
        out = out.with_suffix(f".{fmt}")
    elif out.suffix.lower() != f".{fmt}":
        raise UserInputError(f"{out}: suffix {out.suffix!r} does not match the export format {fmt!r}")
    return out


def _progress(meta_json: str | None, samples: int) -> float | None:
    """How far a run that ended early got: its samples against the end of its planned segments (the
    runner writes the segment table into the metadata before the first segment plays); None unknown."""
    try:
        segments = json.loads(meta_json or "{}").get("segments") or []
        planned = max(int(seg["start"]) + int(seg["cycles"]) for seg in segments)
    except (ValueError, TypeError, KeyError, AttributeError):
        return None
    return min(1.0, samples / planned) if planned > 0 else None


def _may_hold(stats: Any, lo: float, hi: float) -> bool:
    """Whether a row group whose `t` has these Parquet statistics may hold samples in [lo, hi]."""
    if stats is None or not stats.has_min_max:
        return True
    return bool(stats.max >= lo and stats.min <= hi)


PART_ROWS_MAX = ROW_GROUP_ROWS
"""Rows per part file, about (one row group): a flush of more writes several parts."""


def _part_groups(blocks: list[dict[str, np.ndarray]]) -> Iterator[list[dict[str, np.ndarray]]]:
    """Appended blocks as consecutive groups of about equal rows, as few as keep each near PART_ROWS_MAX
    rows or fewer (a group may pass it by part of one block)."""
    total = sum(len(block["t"]) for block in blocks)
    target = math.ceil(total / max(1, math.ceil(total / PART_ROWS_MAX)))
    group: list[dict[str, np.ndarray]] = []
    rows = 0
    for block in blocks:
        group.append(block)
        rows += len(block["t"])
        if rows >= target:
            yield group
            group, rows = [], 0
    if group:
        yield group


class RunWriter:
    """Records one run: buffers appended rows and writes them as a new Parquet part at least every
    `flush_interval_s` seconds of wall time.

    By default the check is made on `append`, in the caller's thread. With `background=True` a writer
    thread does the flushing, so a control loop that appends never waits on the disk (a flush costs a
    few ms), and rows are flushed on time even when appends pause. Append from one thread.

    `max_pending_rows`: once more rows than this wait for the disk, `append` flushes them itself (waiting
    for the disk): for a rig in virtual time, which would otherwise outrun a busy writer thread and pile
    up rows without bound (475,000 rows, ~34 MB, in one flush of a 1 h endurance run on a loaded
    machine). None (the default): never, as a control loop in real time must not wait on the disk.
    However many rows wait, a flush writes them as parts of about PART_ROWS_MAX rows or fewer, so the copy
    it makes of them is bounded.
    """

    def __init__(
        self,
        store: RunStore,
        run_id: str,
        columns: list[str],
        flush_interval_s: float,
        background: bool = False,
        max_pending_rows: int | None = None,
        meta: dict[str, Any] | None = None,
    ) -> None:
        self.store = store
        self._meta = dict(meta or {})  # as open_run put it in the catalog
        self.run_id = run_id
        self.columns = list(columns)
        self.flush_interval_s = flush_interval_s
        self.samples = 0  # rows flushed to disk so far
        self.appended = 0  # rows appended so far, flushed or not: the row index of the next one
        self.closed = False
        self._buffer: list[dict[str, np.ndarray]] = []
        self._pending_rows = 0  # rows in the buffer
        self.max_pending_rows = max_pending_rows
        self._last_t: float | None = None
        self._last_flush_s = monotonic()
        self._next_part = 0
        self._compactor = _Compactor(store.data, run_id)
        self._buffer_lock = threading.Lock()  # the buffer, between appender and writer thread
        self._write_lock = threading.Lock()  # one flush at a time, so parts are numbered in order
        self._stop = threading.Event()
        self._failure: StorageFaultError | None = None  # a write the writer thread could not make
        self.final_status: RunStatus | None = None  # how finish() recorded it (a full disk aborts it)
        self.final_reason: str | None = None
        self._wake = threading.Event()  # the writer thread flushes now (a segment's end, the finish)
        self._flusher: threading.Thread | None = None
        if background:
            self._flusher = threading.Thread(
                target=self._flush_loop, name=f"run-writer-{run_id}", daemon=True
            )
            self._flusher.start()

    def _interval_s(self) -> float:
        return FIRST_FLUSH_S if self._next_part == 0 else self.flush_interval_s

    def _flush_loop(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(self._interval_s())
            self._wake.clear()
            try:
                self.flush()
            except StorageFaultError as exc:
                self._failure = exc  # the control loop hears of it at its next append
                return

    def flush_soon(self) -> None:
        """Put the rows appended so far on disk without waiting for the interval: at once without a
        writer thread, else the writer thread does it now (the caller does not wait on the disk)."""
        if self._flusher is None:
            self.flush()
        else:
            self._wake.set()

    @property
    def run_dir(self) -> Path:
        return self.store.run_dir(self.run_id)

    def append(self, block: dict[str, Any]) -> None:
        """Add rows: one equal-length array (or scalar) per run column, `t` continuing to increase.

        Raises StorageFaultError once a write of the writer thread has failed (the disk is full...)."""
        if self.closed:
            raise RuntimeError(f"run {self.run_id} is finished; cannot append")
        if self._failure is not None:
            raise self._failure
        if set(block) != set(self.columns):
            raise ValueError(
                f"run {self.run_id}: block has columns {sorted(block)}, the run has {self.columns}"
            )
        arrays = {c: np.atleast_1d(np.asarray(block[c], dtype=np.float64)) for c in self.columns}
        t = arrays["t"]
        for name, values in arrays.items():
            if values.ndim != 1 or values.shape != t.shape:
                raise ValueError(
                    f"run {self.run_id}: column {name!r} has shape {values.shape}, 't' has {t.shape}"
                )
        if t.size:
            if np.any(np.diff(t) <= 0) or (self._last_t is not None and t[0] <= self._last_t):
                raise ValueError(
                    f"run {self.run_id}: t must be strictly increasing; block starts at t={t[0]!r}"
                    f" after t={self._last_t!r}"
                )
            self._last_t = float(t[-1])
            with self._buffer_lock:
                self._buffer.append(arrays)
                self._pending_rows += int(t.size)
                pending = self._pending_rows
            self.appended += int(t.size)
            if self.max_pending_rows is not None and pending > self.max_pending_rows:
                self.flush()
                return
        if self._flusher is None and monotonic() - self._last_flush_s >= self._interval_s():
            self.flush()
        elif self._flusher is not None and self.samples == 0:
            self._wake.set()  # the first rows go to disk at once, not an interval after the run opened

    def flush(self) -> None:
        """Write the buffered rows as new part files (about PART_ROWS_MAX rows or fewer each) and update
        the catalog's sample count."""
        with self._write_lock:
            with self._buffer_lock:
                pending, self._buffer = self._buffer, []
                self._pending_rows = 0
                self._last_flush_s = monotonic()
            if not pending:
                return
            for group in _part_groups(pending):
                self._write_part({c: np.concatenate([b[c] for b in group]) for c in self.columns})
            del pending, group  # on disk: their memory goes back to the pool before it is released
            _release_pool()
            runs = tables.runs
            with self.store.catalog.write() as db:
                db.execute(runs.update().where(runs.c.id == self.run_id).values(samples=self.samples))

    def _write_part(self, columns: dict[str, np.ndarray]) -> None:
        name = f"part-{self._next_part:06d}.parquet"
        try:
            with self.store.data.writing(self.run_id, name) as local:
                write_parquet(columns, {}, local)
        except OSError as exc:
            raise StorageFaultError(f"run store: cannot write {name} of run {self.run_id}: {exc}") from exc
        self._compactor.part_written(self._next_part)
        self._next_part += 1
        self.samples += len(columns["t"])

    def finish(
        self,
        status: RunStatus = RunStatus.COMPLETE,
        reason: str | None = None,
        metrics: dict[str, Any] | None = None,
    ) -> None:
        """Flush, seal the data into one Parquet file and record the final status (`complete`/`aborted`)."""
        if self.closed:
            raise RuntimeError(f"run {self.run_id} is already finished")
        if status not in (RunStatus.COMPLETE, RunStatus.ABORTED):
            raise ValueError(
                f"run {self.run_id}: finish status must be 'complete' or 'aborted', not {status!r}"
            )
        if self._flusher is not None:
            self._stop.set()
            self._wake.set()
            self._flusher.join()
        try:
            self.flush()
            self._compactor.join()
            samples, path = self.store._seal(self.run_id)
        except (StorageFaultError, OSError) as exc:
            # The disk refused: what reached it stays (the parts, unsealed), and the run says why.
            status = RunStatus.ABORTED
            reason = reason or f"aborted: {exc}"
            samples, path = self.samples, f"runs/{self.run_id}"
        finally:
            self._compactor.close()
        runs = tables.runs
        values: dict[str, Any] = {
            "status": RunStatus(status).value,
            "reason": reason,
            "ended": _utc(),
            "samples": samples,
            "path": path,
        }
        if metrics is not None:
            values["metrics"] = json_text(metrics)
        with self.store.catalog.write() as db:
            db.execute(runs.update().where(runs.c.id == self.run_id).values(**values))
        self.closed = True
        self.final_status, self.final_reason = RunStatus(status), reason

    def update_meta(self, extra: dict[str, Any]) -> None:
        """Merge keys into the run's metadata (e.g. what is known only once the run has started).

        The writer keeps the metadata it wrote (only it writes a recording run's): an observer's update,
        many an hour, costs one encoding and one write, not a read and decoding of the catalog's row too."""
        runs = tables.runs
        self._meta.update(extra)
        with self.store.catalog.write() as db:
            db.execute(runs.update().where(runs.c.id == self.run_id).values(meta=json_text(self._meta)))

    def __enter__(self) -> RunWriter:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if self.closed:
            return
        if exc is None:
            self.finish(RunStatus.COMPLETE)
        else:
            # The rows recorded up to the failure are kept; the exception goes on to the caller.
            self.finish(RunStatus.ABORTED, reason=f"aborted: {str(exc) or type(exc).__name__}")


def load_runs(
    refs: list[str], store: RunStore | None = None, mapping: dict[str, ColumnSource] | None = None
) -> list[Run]:
    """Runs by store id, by file path, or `latest` (newest complete run of each experiment).

    Files are read through a column `mapping` (`rig.store.importmap`) when one is given, and `.mat` files
    always (with an empty mapping, their run-format columns as they are)."""
    store = store or RunStore()
    runs: list[Run] = []
    for ref in refs:
        if ref == "latest":
            newest: dict[str, str] = {}
            for entry in store.list_runs():
                if entry["status"] == RunStatus.COMPLETE:
                    newest[entry["experiment"]] = entry["id"]
            if not newest:
                raise UserInputError(f"--data latest: no complete run in the store at {store.home}")
            runs += [store.read(run_id) for run_id in newest.values()]
        elif (mapping or Path(ref).suffix.lower() == ".mat") and Path(ref).suffix.lower() in MAPPED_SUFFIXES:
            runs.append(read_mapped(ref, mapping or {}))
        elif Path(ref).suffix.lower() in READ_SUFFIXES or Path(ref).exists():
            runs.append(read_run(ref))
        else:
            runs.append(store.read(ref))
    return runs
