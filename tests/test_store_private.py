"""The store is its user's and says what happened (issue 23 items 8 and 10): its folders 0700 and the
catalog's files 0600 (they hold the keys' hashes and the audit log); a run whose recording process died
is `interrupted` with a reason and the progress it had, not `reason: null` and 0."""

from __future__ import annotations

import sqlite3
import stat
from pathlib import Path

import pytest
from test_store import block, dead_pid, open_run

from rig.core import access, actions
from rig.store.runs import RunStore


@pytest.fixture
def store(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> RunStore:
    monkeypatch.delenv("HDRIG_CATALOG", raising=False)
    monkeypatch.delenv("HDRIG_DATA", raising=False)
    return RunStore(tmp_path / "home")


def mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def test_the_stores_folders_are_0700_and_the_catalogs_files_0600(store: RunStore) -> None:
    access.create_key(store, "admin")  # a write: the WAL and SHM exist
    with open_run(store) as writer:
        writer.append(block(0, 10))
    home = store.home
    for folder in (home, home / "runs", store.run_dir(writer.run_id)):
        assert mode(folder) == 0o700, folder
    for name in ("catalog.sqlite", "catalog.sqlite-wal", "catalog.sqlite-shm"):
        if (home / name).exists():
            assert mode(home / name) == 0o600, name


def test_an_older_world_readable_store_is_made_private_when_opened(tmp_path: Path) -> None:
    home = tmp_path / "old"
    home.mkdir(mode=0o755)
    with sqlite3.connect(home / "catalog.sqlite") as db:
        db.execute("CREATE TABLE t (x)")
    (home / "catalog.sqlite").chmod(0o644)
    home.chmod(0o755)
    RunStore(home, catalog=f"sqlite:///{home / 'catalog.sqlite'}")
    assert mode(home) == 0o700 and mode(home / "catalog.sqlite") == 0o600


def test_an_interrupted_run_says_why_and_keeps_its_progress(store: RunStore) -> None:
    writer = open_run(store)
    writer.update_meta({"segments": [{"label": "a", "mode": "velocity", "start": 0, "cycles": 100}]})
    writer.append(block(0, 30))
    writer.flush()
    with sqlite3.connect(store.catalog_path) as db:
        db.execute("UPDATE runs SET pid = ? WHERE id = ?", (dead_pid(), writer.run_id))
    document = actions.run_document(store, writer.run_id)
    assert document.status == "interrupted"
    assert document.reason and "interrupted" in document.reason and "kept" in document.reason
    assert document.progress == pytest.approx(0.3)  # 30 of the 100 planned samples
    (listed,) = actions.list_runs(store).runs
    assert listed.progress == pytest.approx(0.3) and listed.reason == document.reason
