"""The catalog behind a URL: SQLite by default, upgraded in place from a catalog made before migrations;
PostgreSQL (a real server on loopback, started by the fixture); writers of several processes at once."""

from __future__ import annotations

import json
import sqlite3
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import sqlalchemy as sa

from rig.core import access
from rig.store.catalog import StoreError, head_revision
from rig.store.runs import RunStore

COLUMNS = ["t", "u", "theta_m"]

# The catalog as the store made it before migrations (commit 9892774..d563516), `keys` and `audit` as
# rig/core/access.py made them on first use: copied here so the upgrade is tested against what was.
LEGACY_SCHEMA = """
CREATE TABLE runs (
    id TEXT PRIMARY KEY, experiment TEXT NOT NULL, rig TEXT NOT NULL, model_name TEXT, model_hash TEXT,
    status TEXT NOT NULL CHECK (status IN ('running', 'complete', 'aborted', 'interrupted')),
    reason TEXT, started TEXT NOT NULL, ended TEXT, samples INTEGER NOT NULL DEFAULT 0,
    metrics TEXT NOT NULL DEFAULT '{}', path TEXT NOT NULL, meta TEXT NOT NULL DEFAULT '{}',
    pid INTEGER, host TEXT, pid_started TEXT
);
CREATE INDEX runs_started ON runs (started);
CREATE TABLE checkpoints (
    run_id TEXT NOT NULL REFERENCES runs (id), idx INTEGER NOT NULL, unit TEXT, t_s REAL NOT NULL,
    estimates TEXT NOT NULL, PRIMARY KEY (run_id, idx)
);
CREATE INDEX checkpoints_unit ON checkpoints (unit);
CREATE TABLE keys (name TEXT NOT NULL UNIQUE, role TEXT NOT NULL, hash TEXT NOT NULL, created TEXT NOT NULL,
    revoked TEXT);
CREATE TABLE audit (time TEXT NOT NULL, who TEXT, role TEXT, action TEXT NOT NULL, target TEXT, detail TEXT);
"""


def legacy_catalog(home: Path) -> None:
    """A catalog of the old schema (no `analysis` column yet) with two runs, a key and three audit lines
    whose times tie, so only their row order says which came first."""
    home.mkdir(parents=True)
    with sqlite3.connect(home / "catalog.sqlite") as db:
        db.executescript(LEGACY_SCHEMA)
        for run_id, unit in (
            ("20250101-000000-pulse-0001", "HD25-0007"),
            ("20250101-000001-step-0002", None),
        ):
            meta = {"rig_config": {"name": "sim", "unit": unit}, "sample_rate_hz": 1000.0}
            db.execute(
                "INSERT INTO runs (id, experiment, rig, status, started, samples, metrics, path, meta)"
                " VALUES (?, ?, 'sim', 'complete', ?, 100, '{\"x\": 1.5}', ?, ?)",
                (run_id, run_id.split("-")[2], run_id[:15], f"runs/{run_id}/data.parquet", json.dumps(meta)),
            )
        db.execute(
            "INSERT INTO checkpoints VALUES (?, 0, 'HD25-0007', 900.0, '{\"index\": 0}')",
            ("20250101-000000-pulse-0001",),
        )
        db.execute("INSERT INTO keys VALUES ('lab', 'operator', ?, '2025-01-01T00:00:00', NULL)", ("0" * 64,))
        for action in ("start", "abort", "stop"):
            db.execute(
                "INSERT INTO audit VALUES ('2025-01-01T00:00:00.000', 'lab', 'operator', ?, NULL, NULL)",
                (action,),
            )


def test_a_catalog_from_before_migrations_is_upgraded_without_loss(tmp_path: Path) -> None:
    legacy_catalog(tmp_path / "home")
    store = RunStore(tmp_path / "home")
    listed = store.list_runs()
    assert [r["id"] for r in listed] == ["20250101-000000-pulse-0001", "20250101-000001-step-0002"]
    assert [r["metrics"] for r in listed] == [{"x": 1.5}, {"x": 1.5}]
    # the unit comes from the rig file the run recorded; the new columns are empty, not invented
    assert [(r["unit"], r["operator"], r["tags"], r["analysis"]) for r in listed] == [
        ("HD25-0007", None, [], None),
        (None, None, [], None),
    ]
    assert [c["index"] for c in store.checkpoints(unit="HD25-0007")] == [0]
    assert [k.name for k in access.list_keys(store)] == ["lab"]
    # the rows' order kept (the legacy key was written straight into the table: no line of its own)
    assert [e.action for e in access.audit_log(store)] == ["start", "abort", "stop"]
    with sqlite3.connect(tmp_path / "home" / "catalog.sqlite") as db:
        assert db.execute("SELECT version_num FROM alembic_version").fetchall() == [(head_revision(),)]
        assert db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"


def test_a_new_default_catalog_is_sqlite_in_the_home_at_the_newest_schema(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("HDRIG_CATALOG", raising=False)
    monkeypatch.delenv("HDRIG_DATA", raising=False)
    store = RunStore(tmp_path / "home")
    assert store.catalog_path == tmp_path / "home" / "catalog.sqlite" and store.catalog.is_sqlite
    assert store.data.is_local and Path(store.data.root) == tmp_path / "home"
    with sqlite3.connect(store.catalog_path) as db:
        assert db.execute("SELECT version_num FROM alembic_version").fetchall() == [(head_revision(),)]


def test_a_catalog_url_that_is_not_one_or_not_reachable_is_one_line(tmp_path: Path) -> None:
    with pytest.raises(StoreError, match="not a database URL") as bad:
        RunStore(tmp_path / "a", catalog="no such thing")
    assert "\n" not in str(bad.value)
    with pytest.raises(StoreError, match=r"cannot open the run catalog \(.*\)") as down:
        RunStore(tmp_path / "b", catalog="postgresql://nobody:secret@127.0.0.1:1/none")
    assert "\n" not in str(down.value) and "secret" not in str(down.value)


def record(store: RunStore, unit: str, rows: int = 50) -> str:
    with store.open_run("pulse", "bench-a", None, None, COLUMNS, {"sample_rate_hz": 1000.0}, unit=unit) as w:
        t = np.arange(rows) / 1000.0
        w.append({"t": t, "u": np.sin(t), "theta_m": t})
    return w.run_id


def test_the_store_works_the_same_on_postgresql(tmp_path: Path, pg_url: str) -> None:
    store = RunStore(tmp_path / "home", catalog=pg_url)
    assert not store.catalog.is_sqlite and store.catalog_path is None
    run_id = record(store, "HD25-0001")
    (entry,) = store.list_runs()
    assert (entry["id"], entry["status"], entry["samples"], entry["unit"]) == (
        run_id,
        "complete",
        50,
        "HD25-0001",
    )
    np.testing.assert_array_equal(store.read(run_id)["u"], np.sin(np.arange(50) / 1000.0))
    store.set_checkpoints(run_id, "HD25-0001", [{"index": 0, "t_s": 1.0}, {"index": 1, "t_s": 2.0}])
    assert [c["t_s"] for c in store.checkpoints(unit="HD25-0001")] == [1.0, 2.0]
    token = access.create_key(store, "operator", "alice")
    assert access.authenticate(store, token) == ("alice", access.Role.OPERATOR)
    for action in ("start", "abort", "stop"):
        access.audit(store, "alice", "operator", action)
    assert [e.action for e in access.audit_log(store)] == ["key.create", "start", "abort", "stop"]
    with sa.create_engine(pg_url.replace("postgresql://", "postgresql+psycopg://")).connect() as db:
        assert db.execute(sa.text("SELECT version_num FROM alembic_version")).scalar() == head_revision()


WRITER = textwrap.dedent(
    """
    import sys, numpy as np
    from rig.store.runs import RunStore
    from rig.core import access
    home, catalog, name, runs = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4])
    store = RunStore(home, catalog=catalog)  # all start together: the first migrates, the others wait
    access.create_key(store, "operator", name)
    for k in range(runs):
        with store.open_run("pulse", name, None, None, ["t", "u"], {}, flush_interval_s=0.0,
                            unit=f"{name}-{k % 3}", tags=[f"writer={name}"]) as w:
            for b in range(4):  # a flush, so a catalog update, per block
                t = (b * 25 + np.arange(25)) / 1000.0
                w.append({"t": t, "u": t})
        store.set_metrics(w.run_id, {"k": k})
        access.audit(store, name, "operator", "start", w.run_id)
        store.list_runs(unit=f"{name}-*")
    """
)


@pytest.mark.parametrize("database", ["sqlite", "postgresql"])
def test_four_writer_processes_at_once_lose_and_double_nothing(
    tmp_path: Path, database: str, request: pytest.FixtureRequest
) -> None:
    catalog = (
        f"sqlite:///{tmp_path / 'shared.sqlite'}"
        if database == "sqlite"
        else request.getfixturevalue("pg_url")
    )
    runs_each = 15
    writers = [
        subprocess.Popen(
            [sys.executable, "-c", WRITER, str(tmp_path / f"home-{n}"), catalog, f"rig{n}", str(runs_each)],
            stderr=subprocess.PIPE,
            text=True,
        )
        for n in range(4)
    ]
    for writer in writers:
        _, err = writer.communicate(timeout=240)
        assert writer.returncode == 0, err
    store = RunStore(tmp_path / "reader", catalog=catalog)
    listed = store.list_runs()
    assert len(listed) == 4 * runs_each and len({r["id"] for r in listed}) == 4 * runs_each
    assert all(r["status"] == "complete" and r["samples"] == 100 for r in listed)
    for n in range(4):
        mine = store.list_runs(tags=[f"writer=rig{n}"])
        assert sorted(r["metrics"]["k"] for r in mine) == list(range(runs_each))
        assert {r["rig"] for r in mine} == {f"rig{n}"}
    assert sorted(k.name for k in access.list_keys(store)) == ["rig0", "rig1", "rig2", "rig3"]
    log = access.audit_log(store)  # each writer's key made (audited with it), then its runs' lines
    assert len(log) == 4 + 4 * runs_each and sum(e.action == "key.create" for e in log) == 4
