"""The catalog behind a database URL: the tables of runs, checkpoints, tags, keys, audit and batch fits.

SQLite in the store's home (`catalog.sqlite`) is the default, with nothing to install; `HDRIG_CATALOG`
(`postgresql://user@host/db`, or any SQLAlchemy URL) puts the catalog of many rigs in one database.
Queries are SQLAlchemy Core on the tables below; the schema is made and upgraded by Alembic migrations
(`rig/store/catalog_migrations/versions/`), run when a store opens a catalog older than this code,
under a lock
(an advisory lock on PostgreSQL, SQLite's write lock), so services starting together migrate once. A
catalog from before the migrations (no `alembic_version` table) is upgraded in place: the first migration
creates only what is missing.

Writes on SQLite take the write lock when they begin (`BEGIN IMMEDIATE`), so two writers wait for each
other (busy timeout 30 s) instead of one failing on a read-then-write; readers never wait (WAL mode).

The runs are listed in pages (`page_of_runs`): newest first by (`started`, `id`), a page the next `limit`
runs before a keyset cursor, read from the summary columns (never the `meta` JSON).
"""

from __future__ import annotations

import base64
import binascii
import contextlib
import json
import os
import sqlite3
import sys
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import sqlalchemy as sa
from sqlalchemy import event
from sqlalchemy.engine import URL, Connection, Engine, make_url

from model.errors import UserInputError
from model.resources import package_folder

MIGRATIONS = package_folder("rig.store", "catalog_migrations")
DEFAULT_PAGE = 100  # runs in a page when the caller does not say (the CLI's and the service's listing)
MAX_PAGE = 1000  # the service's largest page: one answer stays well under a second and a few MB
CATALOG_FILE = "catalog.sqlite"
BUSY_TIMEOUT_S = 30.0  # a writer waits this long for another's transaction before it fails

STORED_STATUSES = ("running", "complete", "aborted", "interrupted")
"""The statuses a run in the catalog can have (`queued` and `failed` runs never reach the store)."""

metadata = sa.MetaData()

runs = sa.Table(
    "runs",
    metadata,
    sa.Column("id", sa.Text, primary_key=True),
    sa.Column("experiment", sa.Text, nullable=False),
    sa.Column("rig", sa.Text, nullable=False),
    sa.Column("model_name", sa.Text),
    sa.Column("model_hash", sa.Text),
    sa.Column("status", sa.Text, nullable=False),
    sa.Column("reason", sa.Text),
    sa.Column("started", sa.Text, nullable=False),
    sa.Column("ended", sa.Text),
    sa.Column("samples", sa.BigInteger, nullable=False, server_default="0"),
    sa.Column("metrics", sa.Text, nullable=False, server_default="{}"),
    sa.Column("path", sa.Text, nullable=False),
    sa.Column("meta", sa.Text, nullable=False, server_default="{}"),
    sa.Column("pid", sa.Integer),
    sa.Column("host", sa.Text),
    sa.Column("pid_started", sa.Text),
    sa.Column("analysis", sa.Text),
    sa.Column("unit", sa.Text),  # the gear's serial number (the rig file's `unit:`, or the run's own)
    sa.Column("operator", sa.Text),  # the API key's name, or the OS user of a command line
    sa.Column("progress", sa.Float),  # fraction of the plan recorded, kept when a run ends early
)

checkpoints = sa.Table(
    "checkpoints",
    metadata,
    sa.Column("run_id", sa.Text, sa.ForeignKey("runs.id"), primary_key=True),
    sa.Column("idx", sa.Integer, primary_key=True),
    sa.Column("unit", sa.Text),
    sa.Column("t_s", sa.Float, nullable=False),
    sa.Column("estimates", sa.Text, nullable=False),
)

run_tags = sa.Table(
    "run_tags",
    metadata,
    sa.Column("run_id", sa.Text, sa.ForeignKey("runs.id"), primary_key=True),
    sa.Column("tag", sa.Text, primary_key=True),
)

keys = sa.Table(
    "keys",
    metadata,
    sa.Column("name", sa.Text, nullable=False, unique=True),
    sa.Column("role", sa.Text, nullable=False),
    sa.Column("hash", sa.Text, nullable=False),  # salted scrypt of the key's SHA-256 (rig.core.access)
    sa.Column("created", sa.Text, nullable=False),
    sa.Column("revoked", sa.Text),
    sa.Column("key_id", sa.Text, unique=True),  # the key's public prefix; None for keys made before 0004
)

audit = sa.Table(
    "audit",
    metadata,
    sa.Column("id", sa.BigInteger().with_variant(sa.Integer, "sqlite"), primary_key=True, autoincrement=True),
    sa.Column("time", sa.Text, nullable=False),
    sa.Column("who", sa.Text),
    sa.Column("role", sa.Text),
    sa.Column("action", sa.Text, nullable=False),
    sa.Column("target", sa.Text),
    sa.Column("detail", sa.Text),
)

unit_fits = sa.Table(
    "unit_fits",
    metadata,
    sa.Column("batch_id", sa.Text, primary_key=True),
    sa.Column("unit", sa.Text, primary_key=True),
    sa.Column("created", sa.Text, nullable=False),
    sa.Column("status", sa.Text, nullable=False),  # complete | failed
    sa.Column("runs", sa.Text, nullable=False),  # JSON list of the run ids fitted
    sa.Column("result", sa.Text),  # JSON: the fit document (`hdrig fit --json`)
    sa.Column("error", sa.Text),  # one line, when failed
)


class StoreError(UserInputError):
    """The store's folder, data or catalog cannot be used (not writable, unreachable, a damaged catalog, a
    bad URL): one line naming it."""


def default_url(home: Path) -> str:
    """The catalog's URL: `$HDRIG_CATALOG` when set, else SQLite in the store's home."""
    return os.environ.get("HDRIG_CATALOG") or f"sqlite:///{home / CATALOG_FILE}"


def _parse(url: str) -> URL:
    try:
        parsed = make_url(url)
    except sa.exc.ArgumentError:
        raise StoreError(
            f"catalog URL {url!r}: not a database URL (sqlite:///PATH, postgresql://...)"
        ) from None
    if parsed.drivername in ("postgresql", "postgres"):
        parsed = parsed.set(drivername="postgresql+psycopg")  # psycopg 3, not SQLAlchemy's psycopg2 default
    return parsed


_engines: dict[str, Engine] = {}
_engines_lock = threading.Lock()
_migrated: set[str] = set()


def _forget_engines() -> None:
    # A forked child must not share its parent's open connections: it opens its own.
    for engine in _engines.values():
        engine.dispose(close=False)
    _engines.clear()
    _migrated.clear()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_engines)


def _sqlite_engine(url: URL) -> Engine:
    engine = sa.create_engine(url, connect_args={"timeout": BUSY_TIMEOUT_S, "check_same_thread": False})

    @event.listens_for(engine, "connect")
    def _connect(dbapi: Any, _record: Any) -> None:
        dbapi.isolation_level = None  # transactions are begun below, with the lock they need
        dbapi.execute("PRAGMA journal_mode=WAL")  # readers never block the writer

    @event.listens_for(engine, "begin")
    def _begin(conn: Connection) -> None:
        write = conn.get_execution_options().get("catalog_write", False)
        conn.exec_driver_sql("BEGIN IMMEDIATE" if write else "BEGIN")

    return engine


def _engine(url: URL) -> Engine:
    key = url.render_as_string(hide_password=False)
    with _engines_lock:
        engine = _engines.get(key)
        if engine is None:
            if url.get_backend_name() == "sqlite":
                engine = _sqlite_engine(url)
            else:
                engine = sa.create_engine(url, pool_pre_ping=True)
            _engines[key] = engine
        return engine


class Catalog:
    """One catalog database, by URL; `write()` and `read()` are its transactions."""

    def __init__(self, url: str) -> None:
        self.url = _parse(url)
        self.is_sqlite = self.url.get_backend_name() == "sqlite"
        self.where = self.url.database if self.is_sqlite else self.url.render_as_string(hide_password=True)
        """The catalog as told in messages: SQLite's file, else the URL without its password."""
        if self.is_sqlite and self.url.database not in (None, "", ":memory:"):
            Path(str(self.url.database)).parent.mkdir(parents=True, exist_ok=True)
            _private(Path(str(self.url.database)))
        self.engine = _engine(self.url)
        self._migrate()
        if self.is_sqlite and self.url.database not in (None, "", ":memory:"):
            _guard(Path(str(self.url.database)))

    @contextlib.contextmanager
    def _transaction(self, write: bool) -> Iterator[Connection]:
        try:
            conn = self.engine.connect()
        except sa.exc.DBAPIError as exc:
            raise self._told(exc, connecting=True) from None
        try:
            if write:
                conn = conn.execution_options(catalog_write=True)
            with conn.begin():
                yield conn
        except sa.exc.DBAPIError as exc:
            told = self._told(exc, connecting=False)
            if told is None:
                raise  # integrity, locking...: the caller's to handle, or a bug
            raise told from None
        finally:
            conn.close()

    def close(self) -> None:
        """Close this catalog's connections (and its files), e.g. before its folder is deleted. Every
        `Catalog` of the same URL in this process shares them: close only a catalog nothing else uses."""
        key = self.url.render_as_string(hide_password=False)
        with _engines_lock:
            engine = _engines.pop(key, None)
            _migrated.discard(key)
        if engine is not None:
            engine.dispose()
        if self.is_sqlite and self.url.database not in (None, "", ":memory:"):
            identity = _identity(str(self.url.database))
            if identity is not None:
                _own_files.pop(identity, None)

    def write(self) -> contextlib.AbstractContextManager[Connection]:
        """A transaction that writes: committed at the end of the block, rolled back on an exception."""
        return self._transaction(write=True)

    def read(self) -> contextlib.AbstractContextManager[Connection]:
        """A transaction that only reads (on SQLite, it never waits for a writer)."""
        return self._transaction(write=False)

    def _told(self, exc: sa.exc.DBAPIError, connecting: bool) -> Any:
        """The one-line StoreError for a catalog that cannot be used; None for any other error."""
        orig = exc.orig
        if self.is_sqlite and type(orig) is sqlite3.DatabaseError:
            # A damaged file: told as such; the runs' data stay in runs/<id>/ (Parquet, with their metadata).
            return StoreError(
                f"{self.where}: the run catalog is damaged ({orig}); move it aside and the store"
                " starts a new one (the runs' data files in runs/ are untouched)"
            )
        if connecting or (
            not self.is_sqlite and isinstance(exc, sa.exc.OperationalError) and exc.connection_invalidated
        ):
            first = str(orig).strip().splitlines()[0] if str(orig).strip() else type(orig).__name__
            return StoreError(f"{self.where}: cannot open the run catalog ({first})")
        return None

    # ---- migrations ---------------------------------------------------------------------------

    def _version(self) -> str | None:
        with self.read() as conn:
            if not sa.inspect(conn).has_table("alembic_version"):
                return None
            return conn.execute(sa.text("SELECT version_num FROM alembic_version")).scalar()

    def _migrate(self) -> None:
        """Bring the catalog's schema to this code's (once per process and URL; a no-op when current)."""
        key = self.url.render_as_string(hide_password=False)
        if key in _migrated:
            return
        head = head_revision()
        if self._version() != head:
            from alembic import command

            config = _alembic_config()
            with self.write() as conn:
                if not self.is_sqlite:
                    # One migrating process at a time; the others wait, then find the schema current.
                    conn.execute(sa.text("SELECT pg_advisory_xact_lock(:k)"), {"k": _MIGRATION_LOCK})
                config.attributes["connection"] = conn
                command.upgrade(config, "head")
        _migrated.add(key)


# ---- the catalog's own files: opened by SQLite only --------------------------------------------------
#
# SQLite holds POSIX (fcntl) locks on its file; POSIX drops every lock a process holds on a file when that
# process closes *any* descriptor of it. One open()/close() of `catalog.sqlite` by this process (a model
# file, a run file, an export named as the catalog) silently dropped this process's locks, the next
# process to close the catalog believed itself its last user and deleted the WAL and SHM under us, and
# from then on this process and the others wrote to different catalogs. So this process refuses to open
# the files of a catalog it has open, whoever asks: an audit hook on every Python `open` (builtins, io,
# os), and `refuse_own_file` for the readers that open files outside Python (pyarrow).

SQLITE_SIDE_FILES = ("-wal", "-shm", "-journal")
_own_files: dict[tuple[int, int], str] = {}
"""(st_dev, st_ino) of each SQLite catalog this process opened → its path."""


class OwnFileError(StoreError):
    """A file named as input (a model, a run, an export) is a file of the run catalog itself."""


def _identity(path: str) -> tuple[int, int] | None:
    try:
        found = os.stat(path)  # a stat opens nothing, so it drops no lock
    except (OSError, ValueError):
        return None
    return (found.st_dev, found.st_ino)


def _private(path: Path) -> None:
    """The catalog's file made 0600 before SQLite first opens it (SQLite gives its WAL, SHM and journal
    the database file's mode), and an older catalog's files made so. Created only when absent: a file
    of a catalog this process may have open is never opened here (chmod opens nothing)."""
    if not path.exists():
        with contextlib.suppress(FileExistsError):  # another process made it meanwhile: chmod below
            os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
    for name in (str(path), *(str(path) + suffix for suffix in SQLITE_SIDE_FILES)):
        with contextlib.suppress(FileNotFoundError):
            if os.stat(name).st_mode & 0o077:
                os.chmod(name, 0o600)


def _guard(path: Path) -> None:
    identity = _identity(str(path))
    if identity is not None:
        _own_files[identity] = str(path)


def own_catalog_file(path: str | bytes | os.PathLike[Any]) -> str | None:
    """The catalog (open in this process) that `path` is, or whose WAL/SHM/journal it is; else None. By
    the file's identity, so a link or another spelling of the path is found too."""
    if not _own_files:
        return None
    name = os.fsdecode(path)
    candidates = [name] + [name[: -len(s)] for s in SQLITE_SIDE_FILES if name.endswith(s)]
    for candidate in candidates:
        identity = _identity(candidate)
        registered = _own_files.get(identity) if identity is not None else None
        if identity is None or registered is None:
            continue
        if _identity(registered) != identity:  # that catalog is gone and its inode reused: not ours
            _own_files.pop(identity, None)
            continue
        return registered
    return None


def refuse_own_file(path: str | os.PathLike[str], what: str) -> None:
    """A one-line error when `path` (given as `what`: a model file, a run file...) is a file of a catalog
    this process has open: reading it would drop SQLite's locks."""
    if own_catalog_file(path) is not None:
        raise OwnFileError(f"{path}: a file of the run catalog, not a {what}")


def _refuse_opening_own_files(event: str, args: tuple[Any, ...]) -> None:
    if event != "open" or not _own_files:
        return
    path = args[0] if args else None
    if isinstance(path, (str, bytes, os.PathLike)) and own_catalog_file(path) is not None:
        raise OwnFileError(
            f"{os.fsdecode(path)}: a file of the run catalog; it is opened only as the catalog"
            " (name a model, a run or an export file outside it)"
        )


sys.addaudithook(_refuse_opening_own_files)


_MIGRATION_LOCK = 0x68647269  # 'hdri': the advisory lock key of hdrig's migrations
_head: list[str] = []


def _alembic_config() -> Any:
    from alembic.config import Config

    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS))
    return config


def head_revision() -> str:
    """The newest migration's revision: the schema this code reads and writes."""
    if not _head:
        from alembic.script import ScriptDirectory

        head = ScriptDirectory.from_config(_alembic_config()).get_current_head()
        assert head is not None, f"no migrations in {MIGRATIONS}"
        _head.append(head)
    return _head[0]


def is_unique_violation(exc: BaseException) -> bool:
    """Whether an error is a duplicate key (a run id or key name taken), on any database."""
    return isinstance(exc, sa.exc.IntegrityError)


# ---- pages of the run list ------------------------------------------------------------------------

SUMMARY_COLUMNS = tuple(c for c in runs.c if c.name not in ("meta", "pid", "host", "pid_started"))
"""What a run's line in a listing needs: every column but the metadata JSON and the writer's process."""


@dataclass(frozen=True)
class Cursor:
    """A position in the run list (newest first by `started`, then `id`): a page holds the runs before it.

    A run's (`started`, `id`) never changes, so pages walked with the cursors they hand out list every run
    that was in the catalog when the walk began once and only once, whatever is added meanwhile (new runs
    are newer than the first page: they show on the next walk's first page)."""

    started: str
    run_id: str

    def encode(self) -> str:
        """The opaque token a client passes back (`cursor=`): URL-safe, no padding."""
        raw = json.dumps([self.started, self.run_id], separators=(",", ":")).encode()
        return base64.urlsafe_b64encode(raw).decode().rstrip("=")

    @classmethod
    def decode(cls, token: str) -> Cursor:
        """The cursor a token stands for; a token this code did not make is a one-line error naming it."""
        try:
            fields = json.loads(base64.urlsafe_b64decode(token + "=" * (-len(token) % 4)))
        except (binascii.Error, ValueError):  # not base64, not UTF-8 or not JSON
            fields = None
        if not (isinstance(fields, list) and len(fields) == 2 and all(isinstance(f, str) for f in fields)):
            raise UserInputError(
                f"cursor {token[:40]!r}: not a cursor of this catalog (pass the one a listing gave)"
            )
        return cls(fields[0], fields[1])


@dataclass(frozen=True)
class RunRows:
    """One page of the run list, read in one transaction."""

    rows: list[dict[str, Any]]
    """The summary columns of each run (`SUMMARY_COLUMNS`, `metrics` still JSON text), oldest first."""
    tags: dict[str, list[str]]
    """Each listed run's tags, sorted (runs without tags absent)."""
    total: int
    """The runs the filters select in the whole catalog."""
    older: Cursor | None
    """Where the next (older) page begins; None when this page reaches the oldest run."""


def check_limit(limit: int | None) -> None:
    """A page's size is a count of runs: at least 1 (None: no limit)."""
    if limit is not None and (isinstance(limit, bool) or not isinstance(limit, int) or limit < 1):
        raise UserInputError(f"limit {limit!r}: a page holds at least 1 run")


def page_of_runs(catalog: Catalog, where: list[Any], limit: int | None, before: Cursor | None) -> RunRows:
    """The newest `limit` runs (every one when None) that `where` selects and that come before `before`
    (from the newest when None), oldest first; with the count of all runs `where` selects."""
    check_limit(limit)
    selected = list(where)
    if before is not None:
        key = sa.tuple_(runs.c.started, runs.c.id)
        selected.append(key < sa.tuple_(sa.literal(before.started), sa.literal(before.run_id)))
    newest_first = (runs.c.started.desc(), runs.c.id.desc())
    query = sa.select(*SUMMARY_COLUMNS).where(*selected).order_by(*newest_first)
    ids = sa.select(runs.c.id).where(*selected).order_by(*newest_first)
    if limit is not None:
        query = query.limit(limit + 1)  # one more than asked tells whether an older page exists
        ids = ids.limit(limit)
    tags_query = (
        sa.select(run_tags.c.run_id, run_tags.c.tag)
        .where(run_tags.c.run_id.in_(ids.scalar_subquery()))
        .order_by(run_tags.c.run_id, run_tags.c.tag)
    )
    count = sa.select(sa.func.count()).select_from(runs).where(*where)
    with catalog.read() as db:  # one transaction (on SQLite one snapshot: page, tags and count agree)
        rows = [dict(r._mapping) for r in db.execute(query)]
        tags: dict[str, list[str]] = {}
        for run_id, tag in db.execute(tags_query):
            tags.setdefault(run_id, []).append(tag)
        total = int(db.execute(count).scalar_one())
    more = limit is not None and len(rows) > limit
    rows = rows[:limit]
    older = Cursor(rows[-1]["started"], rows[-1]["id"]) if more else None
    rows.reverse()
    return RunRows(rows, tags, total, older)
