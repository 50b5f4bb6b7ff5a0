"""The run store: a SQLite catalog of runs plus their time series as Parquet, under one home folder.

Layout under the home folder:

    catalog.sqlite                  table `runs`, one row per run (WAL mode: readers never block the writer);
                                    table `checkpoints`, the estimates of each checkpoint of an endurance run
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

import contextlib
import json
import math
import os
import re
import secrets
import socket
import sqlite3
import threading
from collections.abc import Iterator
from datetime import UTC, datetime
from enum import StrEnum
from pathlib import Path
from time import monotonic
from types import TracebackType
from typing import Any

import numpy as np
import pyarrow.parquet as pq

from model.errors import UserInputError
from model.run import Run, RunFormatError
from rig.importmap import MAPPED_SUFFIXES, ColumnSource, read_mapped
from rig.runfile import (
    READ_SUFFIXES,
    RunFileWriter,
    json_text,
    ordered_columns,
    read_run,
    write_parquet,
)
from rig.status import RunStatus

STORED_STATUSES = (RunStatus.RUNNING, RunStatus.COMPLETE, RunStatus.ABORTED, RunStatus.INTERRUPTED)
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

_SCHEMA = """
CREATE TABLE IF NOT EXISTS runs (
    id          TEXT PRIMARY KEY,
    experiment  TEXT NOT NULL,
    rig         TEXT NOT NULL,
    model_name  TEXT,
    model_hash  TEXT,
    status      TEXT NOT NULL CHECK (status IN (STATUSES)),
    reason      TEXT,
    started     TEXT NOT NULL,
    ended       TEXT,
    samples     INTEGER NOT NULL DEFAULT 0,
    metrics     TEXT NOT NULL DEFAULT '{}',
    path        TEXT NOT NULL,
    meta        TEXT NOT NULL DEFAULT '{}',
    pid         INTEGER,
    host        TEXT,
    pid_started TEXT,
    analysis    TEXT
);
CREATE INDEX IF NOT EXISTS runs_started ON runs (started);
CREATE TABLE IF NOT EXISTS checkpoints (
    run_id      TEXT NOT NULL REFERENCES runs (id),
    idx         INTEGER NOT NULL,
    unit        TEXT,
    t_s         REAL NOT NULL,
    estimates   TEXT NOT NULL,
    PRIMARY KEY (run_id, idx)
);
CREATE INDEX IF NOT EXISTS checkpoints_unit ON checkpoints (unit);
""".replace("STATUSES", ", ".join(f"'{s}'" for s in STORED_STATUSES))


class UnknownRunError(UserInputError):
    """No run with this id in the catalog."""


class StoreError(UserInputError):
    """The store's folder or catalog cannot be used (not writable, a damaged catalog): one line."""


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


def _part_range(path: Path) -> tuple[int, int] | None:
    """(first, last) part number a part or merged file holds; None for any other file."""
    m = _CHUNK.fullmatch(path.name)
    if m is None:
        return None
    if m.group(1) is not None:
        return int(m.group(1)), int(m.group(1))
    return int(m.group(2)), int(m.group(3))


def _chunks(run_dir: Path) -> list[Path]:
    """A recording run's part and merged files in row order, each row once: a file whose parts another
    file also holds (a compaction's sources not yet deleted) is left out."""
    found = sorted(
        (span[0], -span[1], path) for path in run_dir.iterdir() if (span := _part_range(path)) is not None
    )
    kept: list[Path] = []
    covered = -1
    for _, neg_last, path in found:  # by first part, the widest file first
        if -neg_last > covered:
            kept.append(path)
            covered = -neg_last
    return kept


def _copy_rows(sources: list[Path], target: Path, meta: dict[str, Any]) -> int:
    """Stream the rows of Parquet files, in order, into one file of whole row groups; rows copied."""
    names = ordered_columns(pq.ParquetFile(sources[0]).schema_arrow.names)
    with RunFileWriter(target, names, meta, as_run=False, checked=False) as writer:
        for source in sources:
            parquet = pq.ParquetFile(source)
            for group in range(parquet.num_row_groups):
                table = parquet.read_row_group(group, columns=names)
                writer.write({c: table.column(c).to_numpy() for c in names})
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


class _Compactor:
    """Merges a recording run's parts on a thread of its own, so the flushes that write parts stay on time."""

    def __init__(self, run_dir: Path) -> None:
        self.run_dir = run_dir
        self._lock = threading.Lock()
        self._queue: list[tuple[int, int]] = []
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None

    def part_written(self, part: int) -> None:
        due = _merges_due(part)
        if not due:
            return
        with self._lock:
            self._queue += due
            if self._thread is None:
                self._thread = threading.Thread(target=self._work, name=f"compact-{self.run_dir.name}")
                self._thread.daemon = True
                self._thread.start()

    def _work(self) -> None:
        while True:
            with self._lock:
                if not self._queue or self._error is not None:
                    self._thread = None
                    return
                first, last = self._queue.pop(0)
            try:
                self._merge(first, last)
            except BaseException as exc:  # raised again by join(): a failed merge is a bug or a full disk
                with self._lock:
                    self._error = exc

    def _merge(self, first: int, last: int) -> None:
        sources = []
        for path in _chunks(self.run_dir):
            span = _part_range(path)
            if span is not None and first <= span[0] and span[1] <= last:
                sources.append(path)
        _copy_rows(sources, self.run_dir / f"merged-{first:06d}-{last:06d}.parquet", {})
        for source in sources:  # only once the merged file is in place
            source.unlink()

    def join(self) -> None:
        """Wait for the merges asked so far; raise the error of one that failed."""
        while True:
            with self._lock:
                thread = self._thread
            if thread is None:
                break
            thread.join()
        if self._error is not None:
            raise self._error


class RunStore:
    """The catalog and data of all runs under `home` (default: `default_home()`)."""

    def __init__(self, home: str | os.PathLike[str] | None = None) -> None:
        self.home = Path(home) if home is not None else default_home()
        try:
            (self.home / "runs").mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise StoreError(
                f"{self.home}: cannot hold the run store ({exc.strerror});"
                " set HDRIG_HOME to a writable folder"
            ) from None
        self.catalog_path = self.home / "catalog.sqlite"
        with self._db() as db:
            db.execute("PRAGMA journal_mode=WAL")
            db.executescript(_SCHEMA)
            if "analysis" not in {row["name"] for row in db.execute("PRAGMA table_info(runs)")}:
                db.execute("ALTER TABLE runs ADD COLUMN analysis TEXT")  # a catalog from before the column

    @contextlib.contextmanager
    def _db(self) -> Iterator[sqlite3.Connection]:
        # One short connection per operation: writers, listers and the service may be different threads.
        try:
            db = sqlite3.connect(self.catalog_path, timeout=30.0)
        except sqlite3.OperationalError as exc:
            raise StoreError(f"{self.catalog_path}: cannot open the run catalog ({exc})") from None
        db.row_factory = sqlite3.Row
        try:
            with db:  # commits, or rolls back on an exception
                yield db
        except sqlite3.DatabaseError as exc:
            if type(exc) is not sqlite3.DatabaseError:  # integrity, locking...: the caller's to handle
                raise
            # A damaged file: told as such; the runs' data stay in runs/<id>/ (Parquet, with their metadata).
            raise StoreError(
                f"{self.catalog_path}: the run catalog is damaged ({exc}); move it aside and the store"
                " starts a new one (the runs' data files in runs/ are untouched)"
            ) from None
        finally:
            db.close()

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
    ) -> RunWriter:
        """Start a run in the catalog (status `running`) and return its writer (see RunWriter).

        `run_id`: an id from `new_run_id`, reserved by a caller that had to name the run before it began.
        """
        if "t" not in columns:
            raise ValueError(f"run columns {columns} lack the time column 't'")
        if len(set(columns)) != len(columns):
            raise ValueError(f"run columns {columns} name a column twice")
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
        }
        for _ in range(10):
            chosen = run_id or new_run_id(experiment, now)
            row.update(id=chosen, path=f"runs/{chosen}")
            try:
                with self._db() as db:
                    db.execute(
                        f"INSERT INTO runs ({', '.join(row)}) VALUES ({', '.join(':' + k for k in row)})", row
                    )
                break
            except sqlite3.IntegrityError:
                if run_id is not None:
                    raise ValueError(f"run id {run_id!r} is already in {self.catalog_path}") from None
                # the random suffix collided within the same second: draw another
        else:
            raise RuntimeError(f"could not find a free run id for {experiment!r} in {self.catalog_path}")
        run_id = chosen
        self.run_dir(run_id).mkdir()
        return RunWriter(self, run_id, columns, flush_interval_s, background)

    def _seal(self, run_id: str) -> tuple[int, str]:
        """Stream a run's part and merged files into `data.parquet`; return (samples, catalog path)."""
        run_dir = self.run_dir(run_id)
        chunks = _chunks(run_dir)
        data = run_dir / DATA_FILE
        if not chunks:
            if not data.exists():
                return 0, f"runs/{run_id}"  # nothing was ever flushed
            return pq.ParquetFile(data).metadata.num_rows, f"runs/{run_id}/{DATA_FILE}"
        with self._db() as db:
            row = self._row(db, run_id)
        samples = _copy_rows(chunks, data, self._run_meta(row))
        # Chunks go only after the data file is in place; a reader meanwhile prefers the data file. A writer
        # killed mid-flush or mid-merge also leaves a temporary file behind.
        for leftover in list(run_dir.iterdir()):
            temporary = leftover.name.startswith(".") and leftover.suffix == ".tmp"
            if temporary or _part_range(leftover) is not None:
                leftover.unlink(missing_ok=True)
        return samples, f"runs/{run_id}/{DATA_FILE}"

    # ---- catalog --------------------------------------------------------------------------------

    def _row(self, db: sqlite3.Connection, run_id: str) -> sqlite3.Row:
        row = db.execute("SELECT * FROM runs WHERE id = ?", (run_id,)).fetchone()
        if row is None:
            raise UnknownRunError(f"unknown run id {run_id!r} (not in {self.catalog_path})")
        return row

    def _reconcile(self, rows: list[sqlite3.Row]) -> bool:
        """Mark `running` runs, and running analyses, whose process has died as `interrupted`; True if any
        changed."""
        changed = False
        for row in rows:
            if row["analysis"] == AnalysisState.RUNNING and not _process_alive(
                row["pid"], row["host"], row["pid_started"]
            ):
                with self._db() as db:
                    db.execute(
                        "UPDATE runs SET analysis = ? WHERE id = ? AND analysis = ?",
                        (AnalysisState.INTERRUPTED.value, row["id"], AnalysisState.RUNNING.value),
                    )
                changed = True
            if row["status"] != RunStatus.RUNNING or _process_alive(
                row["pid"], row["host"], row["pid_started"]
            ):
                continue
            with self._db() as db:
                # Only the lister whose update lands seals the run, so two listers never seal it together.
                claimed = db.execute(
                    "UPDATE runs SET status = ? WHERE id = ? AND status = ?",
                    (RunStatus.INTERRUPTED.value, row["id"], RunStatus.RUNNING.value),
                ).rowcount
            if not claimed:
                continue
            chunks = _chunks(self.run_dir(row["id"]))
            last_write = max((c.stat().st_mtime for c in chunks), default=None)
            samples, path = self._seal(row["id"])
            ended = _utc(datetime.fromtimestamp(last_write, UTC)) if last_write else row["started"]
            with self._db() as db:
                db.execute(
                    "UPDATE runs SET samples = ?, path = ?, ended = ? WHERE id = ?",
                    (samples, path, ended, row["id"]),
                )
            changed = True
        return changed

    def _public(self, row: sqlite3.Row) -> dict[str, Any]:
        entry = dict(row)
        entry["metrics"] = json.loads(entry["metrics"])
        entry["meta"] = json.loads(entry["meta"])
        entry["path"] = str(self.home / entry["path"])
        return entry

    def list_runs(self) -> list[dict[str, Any]]:
        """All runs, oldest first, each a dict of its catalog fields (metrics and meta decoded)."""
        query = "SELECT * FROM runs ORDER BY started, id"
        with self._db() as db:
            rows = db.execute(query).fetchall()
        if self._reconcile(rows):
            with self._db() as db:
                rows = db.execute(query).fetchall()
        return [self._public(row) for row in rows]

    def get(self, run_id: str) -> dict[str, Any]:
        """One run's catalog fields, as in `list_runs`."""
        with self._db() as db:
            row = self._row(db, run_id)
        if self._reconcile([row]):
            with self._db() as db:
                row = self._row(db, run_id)
        return self._public(row)

    def set_metrics(self, run_id: str, metrics: dict[str, Any]) -> None:
        """Replace a run's metrics (a JSON-serializable dict)."""
        with self._db() as db:
            self._row(db, run_id)
            db.execute("UPDATE runs SET metrics = ? WHERE id = ?", (json_text(metrics), run_id))

    def set_checkpoints(self, run_id: str, unit: str | None, checkpoints: list[dict[str, Any]]) -> None:
        """Replace a run's checkpoint estimates (each with `index` and `t_s` [s]) for the gear `unit`."""
        with self._db() as db:
            self._row(db, run_id)
            db.execute("DELETE FROM checkpoints WHERE run_id = ?", (run_id,))
            db.executemany(
                "INSERT INTO checkpoints (run_id, idx, unit, t_s, estimates) VALUES (?, ?, ?, ?, ?)",
                [(run_id, int(c["index"]), unit, float(c["t_s"]), json_text(c)) for c in checkpoints],
            )

    def checkpoints(self, run_id: str | None = None, unit: str | None = None) -> list[dict[str, Any]]:
        """Checkpoint estimates of one run, or of every run of a gear unit, in order of the runs' start
        and then of the checkpoints; each with its run's `run_id`, `started` and `unit`."""
        if (run_id is None) == (unit is None):
            raise ValueError("checkpoints: give a run id or a unit, not both")
        query = (
            "SELECT c.run_id, c.unit, c.estimates, r.started"
            " FROM checkpoints c JOIN runs r ON r.id = c.run_id"
            f" WHERE {'c.run_id' if run_id is not None else 'c.unit'} = ? ORDER BY r.started, c.run_id, c.idx"
        )
        with self._db() as db:
            if run_id is not None:
                self._row(db, run_id)
            rows = db.execute(query, (run_id if run_id is not None else unit,)).fetchall()
        return [
            {
                **json.loads(row["estimates"]),
                "run_id": row["run_id"],
                "unit": row["unit"],
                "started": row["started"],
            }
            for row in rows
        ]

    def set_analysis(self, run_id: str, state: AnalysisState) -> None:
        """Record where a run's analysis stands; `running` names this process as the one doing it, so
        a listing finds it `interrupted` should this process die first."""
        with self._db() as db:
            self._row(db, run_id)
            if state == AnalysisState.RUNNING:
                stat = _process_start(os.getpid())
                db.execute(
                    "UPDATE runs SET analysis = ?, pid = ?, host = ?, pid_started = ? WHERE id = ?",
                    (state.value, os.getpid(), socket.gethostname(), stat[1] if stat else None, run_id),
                )
            else:
                db.execute("UPDATE runs SET analysis = ? WHERE id = ?", (AnalysisState(state).value, run_id))

    # ---- data -----------------------------------------------------------------------------------

    def run_dir(self, run_id: str) -> Path:
        """The folder holding a run's data and artifacts."""
        return self.home / "runs" / run_id

    def add_artifact(self, run_id: str, name: str) -> Path:
        """A path in the run's artifacts folder to write a derived result or plot to (not created)."""
        with self._db() as db:
            self._row(db, run_id)
        relative = Path(name)
        if not name or relative.is_absolute() or ".." in relative.parts:
            raise ValueError(f"artifact name {name!r} must be a relative path inside the run folder")
        path = self.run_dir(run_id) / ARTIFACTS_DIR / relative
        path.parent.mkdir(parents=True, exist_ok=True)
        return path

    @staticmethod
    def _run_meta(row: sqlite3.Row) -> dict[str, Any]:
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

    def _sources(self, run_id: str) -> list[Path]:
        run_dir = self.run_dir(run_id)
        data = run_dir / DATA_FILE
        return [data] if data.exists() else _chunks(run_dir)

    def columns(self, run_id: str) -> list[str]:
        """The names of a run's columns, from a file's schema (no rows read); empty before the first flush."""
        with self._db() as db:
            self._row(db, run_id)
        while True:
            sources = self._sources(run_id)
            if not sources:
                return []
            try:
                return ordered_columns(pq.ParquetFile(sources[0]).schema_arrow.names)
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
            parquet = pq.ParquetFile(source)
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
        with self._db() as db:
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
        with self._db() as db:
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
        catalog = target.parent == home and target.name.startswith(self.catalog_path.name)
        if target.is_relative_to(home / "runs") or catalog:
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


def _may_hold(stats: Any, lo: float, hi: float) -> bool:
    """Whether a row group whose `t` has these Parquet statistics may hold samples in [lo, hi]."""
    if stats is None or not stats.has_min_max:
        return True
    return bool(stats.max >= lo and stats.min <= hi)


class RunWriter:
    """Records one run: buffers appended rows and writes them as a new Parquet part at least every
    `flush_interval_s` seconds of wall time.

    By default the check is made on `append`, in the caller's thread. With `background=True` a writer
    thread does the flushing, so a control loop that appends never waits on the disk (a flush costs a
    few ms), and rows are flushed on time even when appends pause. Append from one thread.
    """

    def __init__(
        self,
        store: RunStore,
        run_id: str,
        columns: list[str],
        flush_interval_s: float,
        background: bool = False,
    ) -> None:
        self.store = store
        self.run_id = run_id
        self.columns = list(columns)
        self.flush_interval_s = flush_interval_s
        self.samples = 0  # rows flushed to disk so far
        self.appended = 0  # rows appended so far, flushed or not: the row index of the next one
        self.closed = False
        self._buffer: list[dict[str, np.ndarray]] = []
        self._last_t: float | None = None
        self._last_flush_s = monotonic()
        self._next_part = 0
        self._compactor = _Compactor(store.run_dir(run_id))
        self._buffer_lock = threading.Lock()  # the buffer, between appender and writer thread
        self._write_lock = threading.Lock()  # one flush at a time, so parts are numbered in order
        self._stop = threading.Event()
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
            self.flush()

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
        """Add rows: one equal-length array (or scalar) per run column, `t` continuing to increase."""
        if self.closed:
            raise RuntimeError(f"run {self.run_id} is finished; cannot append")
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
            self.appended += int(t.size)
        if self._flusher is None and monotonic() - self._last_flush_s >= self._interval_s():
            self.flush()
        elif self._flusher is not None and self.samples == 0:
            self._wake.set()  # the first rows go to disk at once, not an interval after the run opened

    def flush(self) -> None:
        """Write the buffered rows as a new part file and update the catalog's sample count."""
        with self._write_lock:
            with self._buffer_lock:
                pending, self._buffer = self._buffer, []
                self._last_flush_s = monotonic()
            if not pending:
                return
            columns = {c: np.concatenate([b[c] for b in pending]) for c in self.columns}
            write_parquet(columns, {}, self.run_dir / f"part-{self._next_part:06d}.parquet")
            self._compactor.part_written(self._next_part)
            self._next_part += 1
            self.samples += len(columns["t"])
            with self.store._db() as db:
                db.execute("UPDATE runs SET samples = ? WHERE id = ?", (self.samples, self.run_id))

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
        self.flush()
        self._compactor.join()
        samples, path = self.store._seal(self.run_id)
        with self.store._db() as db:
            db.execute(
                "UPDATE runs SET status = ?, reason = ?, ended = ?, samples = ?, path = ?,"
                " metrics = COALESCE(?, metrics) WHERE id = ?",
                (
                    RunStatus(status).value,
                    reason,
                    _utc(),
                    samples,
                    path,
                    None if metrics is None else json_text(metrics),
                    self.run_id,
                ),
            )
        self.closed = True

    def update_meta(self, extra: dict[str, Any]) -> None:
        """Merge keys into the run's metadata (e.g. what is known only once the run has started)."""
        with self.store._db() as db:
            meta = json.loads(self.store._row(db, self.run_id)["meta"])
            meta.update(extra)
            db.execute("UPDATE runs SET meta = ? WHERE id = ?", (json_text(meta), self.run_id))

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

    Files are read through a column `mapping` (`rig.importmap`) when one is given, and `.mat` files
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
