"""The run store: a SQLite catalog of runs plus their time series as Parquet, under one home folder.

Layout under the home folder:

    catalog.sqlite                  table `runs`, one row per run (WAL mode: readers never block the writer)
    runs/<id>/part-000000.parquet   while recording: one small file per flush
    runs/<id>/data.parquet          once sealed: all parts in one file, with the run metadata
    runs/<id>/artifacts/            derived results and plots

Crash safety: a flush writes its rows as a new part file under a temporary name and renames it into place,
so every part on disk is a complete Parquet file and a SIGKILL loses only the rows not yet flushed (at most
`flush_interval_s` of data). A run whose writer process has died is found by its pid when runs are listed,
marked `interrupted`, and sealed from the parts it left.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import secrets
import socket
import sqlite3
import threading
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path
from time import monotonic
from types import TracebackType
from typing import Any

import numpy as np
import pyarrow.parquet as pq

from model.errors import UserInputError
from model.run import Run, RunFormatError
from rig.runfile import (
    READ_SUFFIXES,
    json_text,
    ordered_columns,
    read_parquet,
    read_run,
    write_parquet,
    write_run,
)
from rig.status import RunStatus

STORED_STATUSES = (RunStatus.RUNNING, RunStatus.COMPLETE, RunStatus.ABORTED, RunStatus.INTERRUPTED)
"""The statuses a run in the catalog can have (`queued` and `failed` runs never reached the store)."""
EXPORT_FORMATS = ("csv", "parquet", "mat")
DATA_FILE = "data.parquet"
ARTIFACTS_DIR = "artifacts"
_PART = re.compile(r"part-(\d+)\.parquet")

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
    pid_started TEXT
);
CREATE INDEX IF NOT EXISTS runs_started ON runs (started);
""".replace("STATUSES", ", ".join(f"'{s}'" for s in STORED_STATUSES))


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


def _parts(run_dir: Path) -> list[Path]:
    found = [(int(m.group(1)), p) for p in run_dir.iterdir() if (m := _PART.fullmatch(p.name))]
    return [p for _, p in sorted(found)]


class RunStore:
    """The catalog and data of all runs under `home` (default: `default_home()`)."""

    def __init__(self, home: str | os.PathLike[str] | None = None) -> None:
        self.home = Path(home) if home is not None else default_home()
        (self.home / "runs").mkdir(parents=True, exist_ok=True)
        self.catalog_path = self.home / "catalog.sqlite"
        with self._db() as db:
            db.execute("PRAGMA journal_mode=WAL")
            db.executescript(_SCHEMA)

    @contextlib.contextmanager
    def _db(self) -> Iterator[sqlite3.Connection]:
        # One short connection per operation: writers, listers and the service may be different threads.
        db = sqlite3.connect(self.catalog_path, timeout=30.0)
        db.row_factory = sqlite3.Row
        try:
            with db:  # commits, or rolls back on an exception
                yield db
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
        """Merge a run's part files into `data.parquet`; return (samples, catalog path)."""
        run_dir = self.run_dir(run_id)
        parts = _parts(run_dir)
        if not parts:
            data = run_dir / DATA_FILE
            if not data.exists():
                return 0, f"runs/{run_id}"  # nothing was ever flushed
            return pq.ParquetFile(data).metadata.num_rows, f"runs/{run_id}/{DATA_FILE}"
        columns, _ = self._load(run_dir)
        with self._db() as db:
            row = self._row(db, run_id)
        write_parquet(columns, self._run_meta(row), run_dir / DATA_FILE)
        # Parts go only after the data file is in place; a reader meanwhile prefers the data file. A writer
        # killed mid-flush also leaves its temporary part behind.
        for part in [*parts, *run_dir.glob(".part-*.tmp")]:
            part.unlink(missing_ok=True)
        return len(columns["t"]), f"runs/{run_id}/{DATA_FILE}"

    # ---- catalog --------------------------------------------------------------------------------

    def _row(self, db: sqlite3.Connection, run_id: str) -> sqlite3.Row:
        row = db.execute("SELECT * FROM runs WHERE id = ?", (run_id,)).fetchone()
        if row is None:
            raise UnknownRunError(f"unknown run id {run_id!r} (not in {self.catalog_path})")
        return row

    def _reconcile(self, rows: list[sqlite3.Row]) -> bool:
        """Mark `running` runs whose writer process has died as `interrupted`; True if any changed."""
        changed = False
        for row in rows:
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
            parts = _parts(self.run_dir(row["id"]))
            last_write = parts[-1].stat().st_mtime if parts else None
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
    def _load(run_dir: Path) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        data = run_dir / DATA_FILE
        if not data.exists():
            try:
                blocks = [read_parquet(part)[0] for part in _parts(run_dir)]
            except FileNotFoundError:
                blocks = []  # sealed while we read: the data file now holds every part
            else:
                if not blocks:
                    return {}, {}
                names = ordered_columns(blocks[0])
                return {c: np.concatenate([b[c] for b in blocks]) for c in names}, {}
        return read_parquet(data)

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

    def read(self, run_id: str) -> Run:
        """A run's samples so far (also while it is recording) and its metadata, validated."""
        with self._db() as db:
            row = self._row(db, run_id)
        columns, _ = self._load(self.run_dir(run_id))
        if not columns:
            raise RunFormatError(f"run {run_id}: no samples recorded yet (status {row['status']})")
        try:
            return Run(columns, self._run_meta(row)).validate(where=f"run {run_id}")
        except RunFormatError as e:
            raise RunFormatError(f"{e} (status {row['status']}, {row['samples']} samples)") from e

    def export(self, run_id: str, fmt: str, out_path: str | os.PathLike[str]) -> Path:
        """Write a run as csv, parquet or mat; a folder as `out_path` gets `<id>.<fmt>` inside it."""
        if fmt not in EXPORT_FORMATS:
            raise UserInputError(f"unknown export format {fmt!r}; use one of {', '.join(EXPORT_FORMATS)}")
        out = Path(out_path)
        if out.is_dir():
            out = out / f"{run_id}.{fmt}"
        elif not out.suffix:
            out = out.with_suffix(f".{fmt}")
        elif out.suffix.lower() != f".{fmt}":
            raise UserInputError(f"{out}: suffix {out.suffix!r} does not match the export format {fmt!r}")
        return write_run(self.read(run_id), out)


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
        self._buffer_lock = threading.Lock()  # the buffer, between appender and writer thread
        self._write_lock = threading.Lock()  # one flush at a time, so parts are numbered in order
        self._stop = threading.Event()
        self._flusher: threading.Thread | None = None
        if background:
            self._flusher = threading.Thread(
                target=self._flush_loop, name=f"run-writer-{run_id}", daemon=True
            )
            self._flusher.start()

    def _flush_loop(self) -> None:
        while not self._stop.wait(self.flush_interval_s):
            self.flush()

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
        if self._flusher is None and monotonic() - self._last_flush_s >= self.flush_interval_s:
            self.flush()

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
            self._flusher.join()
        self.flush()
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


def load_runs(refs: list[str], store: RunStore | None = None) -> list[Run]:
    """Runs by store id, by file path, or `latest` (newest complete run of each experiment)."""
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
        elif Path(ref).suffix.lower() in READ_SUFFIXES or Path(ref).exists():
            runs.append(read_run(ref))
        else:
            runs.append(store.read(ref))
    return runs
