"""The run store: catalog lifecycle, timed flushes, exports, and runs left behind by dead writers."""

from __future__ import annotations

import json
import os
import re
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import scipy.io
import sqlalchemy as sa

import rig.store.runs as store_module
from model.run import RunFormatError
from rig.store import catalog as tables
from rig.store.runfile import read_run
from rig.store.runs import FIRST_FLUSH_S, RunStore, UnknownRunError, default_home

REPO_ROOT = Path(__file__).resolve().parents[1]
COLUMNS = ["t", "u", "theta_m"]
META = {"sample_rate_hz": 1000.0, "source": "sim", "notes": "store test"}


def block(first_sample: int, n: int) -> dict[str, np.ndarray]:
    t = (first_sample + np.arange(n)) / 1000.0
    return {"t": t, "u": np.sin(t), "theta_m": t**2}


@pytest.fixture
def store(tmp_path: Path) -> RunStore:
    return RunStore(tmp_path / "home")


def open_run(store: RunStore, flush_interval_s: float = 1.0) -> store_module.RunWriter:
    return store.open_run("speed-sweep", "sim", "seed", "3f2a9c", COLUMNS, dict(META), flush_interval_s)


def recorded(store: RunStore, n_blocks: int = 3, rows: int = 100) -> str:
    with open_run(store) as writer:
        for k in range(n_blocks):
            writer.append(block(k * rows, rows))
    return writer.run_id


class FakeClock:
    def __init__(self) -> None:
        self.now_s = 1000.0

    def __call__(self) -> float:
        return self.now_s


def dead_pid() -> int:
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


# ---- home and catalog ----------------------------------------------------------------------------


def test_default_home_is_hdrig_home_when_set(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv("HDRIG_HOME", str(tmp_path / "lab"))
    assert default_home() == tmp_path / "lab"


def test_default_home_is_dot_hdrig_in_the_user_folder(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.delenv("HDRIG_HOME", raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))
    assert default_home() == tmp_path / ".hdrig"


def test_catalog_is_in_wal_mode(store: RunStore) -> None:
    with sqlite3.connect(store.catalog_path) as db:
        assert db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"


# ---- lifecycle -----------------------------------------------------------------------------------


def test_open_run_is_listed_as_running_with_a_readable_id(store: RunStore) -> None:
    writer = open_run(store)
    (entry,) = store.list_runs()
    assert re.fullmatch(r"\d{8}-\d{6}-speed-sweep-[0-9a-f]{4}", writer.run_id)
    assert (entry["id"], entry["status"], entry["samples"]) == (writer.run_id, "running", 0)


def test_finished_run_is_listed_complete_with_all_samples(store: RunStore) -> None:
    run_id = recorded(store)
    (entry,) = store.list_runs()
    assert (entry["id"], entry["experiment"], entry["status"], entry["samples"]) == (
        run_id,
        "speed-sweep",
        "complete",
        300,
    )
    assert entry["ended"] >= entry["started"]


def test_read_returns_every_appended_sample(store: RunStore) -> None:
    run = store.read(recorded(store))
    expected = {c: np.concatenate([block(k * 100, 100)[c] for k in range(3)]) for c in COLUMNS}
    for name in COLUMNS:
        np.testing.assert_array_equal(run[name], expected[name])


def test_read_metadata_joins_writer_meta_and_catalog(store: RunStore) -> None:
    run_id = recorded(store)
    meta = store.read(run_id).meta
    assert meta["model"] == {"name": "seed", "hash": "3f2a9c"}
    assert (meta["experiment"], meta["rig"], meta["source"], meta["sample_rate_hz"]) == (
        "speed-sweep",
        "sim",
        "sim",
        1000.0,
    )
    assert meta["created"] == store.get(run_id)["started"]


def test_finish_seals_the_parts_into_one_parquet_run_file(store: RunStore) -> None:
    run_id = recorded(store)
    path = Path(store.get(run_id)["path"])
    assert path == store.run_dir(run_id) / "data.parquet"
    assert not list(store.run_dir(run_id).glob("part-*"))
    run = read_run(path)
    assert len(run) == 300 and run.meta["run_id"] == run_id


def test_read_while_recording_returns_the_flushed_rows(store: RunStore) -> None:
    writer = open_run(store)
    writer.append(block(0, 50))
    writer.flush()
    writer.append(block(50, 50))  # still buffered
    assert len(store.read(writer.run_id)) == 50


def test_error_inside_with_marks_aborted_with_the_text_and_keeps_data(store: RunStore) -> None:
    with pytest.raises(RuntimeError, match="limit switch"), open_run(store) as writer:
        writer.append(block(0, 20))
        raise RuntimeError("limit switch hit")
    entry = store.get(writer.run_id)
    reason = "aborted: limit switch hit"  # every stored abort reason says so (RunStatus, issue 15)
    assert (entry["status"], entry["reason"], entry["samples"]) == ("aborted", reason, 20)
    assert len(store.read(writer.run_id)) == 20


def test_finish_records_metrics(store: RunStore) -> None:
    writer = open_run(store)
    writer.append(block(0, 10))
    writer.finish(metrics={"rms_error_rad": 0.01})
    assert store.get(writer.run_id)["metrics"] == {"rms_error_rad": 0.01}


def test_set_metrics_replaces_them(store: RunStore) -> None:
    run_id = recorded(store)
    store.set_metrics(run_id, {"friction_nm": np.float64(0.2)})
    assert store.get(run_id)["metrics"] == {"friction_nm": 0.2}


def test_append_refuses_time_going_backwards(store: RunStore) -> None:
    writer = open_run(store)
    writer.append(block(10, 10))
    with pytest.raises(ValueError, match="t must be strictly increasing"):
        writer.append(block(0, 10))


def test_append_refuses_columns_the_run_was_not_opened_with(store: RunStore) -> None:
    writer = open_run(store)
    with pytest.raises(ValueError, match="block has columns"):
        writer.append({**block(0, 5), "i_a": np.zeros(5)})


def test_append_after_finish_is_refused(store: RunStore) -> None:
    writer = open_run(store)
    writer.finish()
    with pytest.raises(RuntimeError, match="is finished"):
        writer.append(block(0, 5))


def test_run_without_samples_reads_as_a_one_line_error(store: RunStore) -> None:
    writer = open_run(store)
    writer.finish("aborted", reason="operator stop")
    with pytest.raises(RunFormatError, match=f"run {writer.run_id}: no samples recorded yet"):
        store.read(writer.run_id)


# ---- timed flushes -------------------------------------------------------------------------------


def test_rows_stay_buffered_until_the_flush_interval_has_passed(
    store: RunStore, monkeypatch: pytest.MonkeyPatch
) -> None:
    clock = FakeClock()
    monkeypatch.setattr(store_module, "monotonic", clock)
    writer = open_run(store)
    writer.append(block(0, 10))
    clock.now_s += 0.2
    writer.append(block(10, 10))
    assert store.get(writer.run_id)["samples"] == 0
    clock.now_s += FIRST_FLUSH_S - 0.2  # the first rows go to disk early: a crash then loses little
    writer.append(block(20, 10))
    assert store.get(writer.run_id)["samples"] == 30
    clock.now_s += 0.9  # after the first flush, the interval (1 s)
    writer.append(block(30, 10))
    assert store.get(writer.run_id)["samples"] == 30
    assert [p.name for p in writer.run_dir.glob("part-*")] == ["part-000000.parquet"]


def test_append_flushes_once_the_interval_has_passed(
    store: RunStore, monkeypatch: pytest.MonkeyPatch
) -> None:
    clock = FakeClock()
    monkeypatch.setattr(store_module, "monotonic", clock)
    writer = open_run(store)
    writer.append(block(0, 10))
    clock.now_s += 1.0
    writer.append(block(10, 10))
    assert store.get(writer.run_id)["samples"] == 20
    assert [p.name for p in writer.run_dir.glob("part-*")] == ["part-000000.parquet"]


def test_a_background_writer_flushes_on_time_while_appends_pause(store: RunStore) -> None:
    writer = store.open_run("speed-sweep", "sim", "seed", "3f2a9c", COLUMNS, dict(META), 0.1, background=True)
    writer.append(block(0, 10))
    # No append follows: the writer thread must still put the rows on disk within a few intervals.
    deadline = time.monotonic() + 5.0
    while store.get(writer.run_id)["samples"] < 10 and time.monotonic() < deadline:
        time.sleep(0.05)
    assert store.get(writer.run_id)["samples"] == 10
    writer.append(block(10, 5))
    writer.finish()
    assert not [t for t in threading.enumerate() if t.name == f"run-writer-{writer.run_id}"]
    assert len(store.read(writer.run_id)) == 15


# ---- export and artifacts ------------------------------------------------------------------------


@pytest.mark.parametrize("fmt", ["csv", "parquet"])
def test_export_writes_a_run_file_that_reads_back(store: RunStore, tmp_path: Path, fmt: str) -> None:
    run_id = recorded(store)
    out = store.export(run_id, fmt, tmp_path / f"out.{fmt}")
    back = read_run(out)
    np.testing.assert_array_equal(back["theta_m"], store.read(run_id)["theta_m"])
    assert back.meta["run_id"] == run_id


def test_export_mat_opens_with_loadmat(store: RunStore, tmp_path: Path) -> None:
    run_id = recorded(store)
    mat = scipy.io.loadmat(store.export(run_id, "mat", tmp_path / "out.mat"), simplify_cells=True)
    np.testing.assert_array_equal(mat["t"], store.read(run_id)["t"])
    assert mat["meta"]["experiment"] == "speed-sweep"


def test_export_into_a_folder_names_the_file_after_the_run(store: RunStore, tmp_path: Path) -> None:
    run_id = recorded(store)
    assert store.export(run_id, "csv", tmp_path) == tmp_path / f"{run_id}.csv"


def test_export_refuses_a_suffix_that_contradicts_the_format(store: RunStore, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"suffix '\.csv' does not match the export format 'mat'"):
        store.export(recorded(store), "mat", tmp_path / "out.csv")


def test_artifact_path_is_inside_the_run_folder(store: RunStore) -> None:
    run_id = recorded(store)
    path = store.add_artifact(run_id, "plots/residual.png")
    assert path.is_relative_to(store.run_dir(run_id)) and path.parent.is_dir()


def test_artifact_name_may_not_leave_the_run_folder(store: RunStore) -> None:
    with pytest.raises(ValueError, match="relative path inside the run folder"):
        store.add_artifact(recorded(store), "../other/fit.json")


@pytest.mark.parametrize(
    "call",
    [
        lambda s: s.get("nope-1234"),
        lambda s: s.read("nope-1234"),
        lambda s: s.export("nope-1234", "csv", "x.csv"),
        lambda s: s.set_metrics("nope-1234", {}),
        lambda s: s.add_artifact("nope-1234", "a.png"),
    ],
    ids=["get", "read", "export", "set_metrics", "add_artifact"],
)
def test_unknown_run_id_is_a_one_line_error_naming_it(
    store: RunStore, call: Callable[[RunStore], object]
) -> None:
    with pytest.raises(UnknownRunError, match="unknown run id 'nope-1234'") as info:
        call(store)
    assert "\n" not in str(info.value)


# ---- runs left by dead writers -------------------------------------------------------------------


def test_running_run_of_a_dead_process_is_listed_interrupted(store: RunStore) -> None:
    writer = open_run(store)
    writer.append(block(0, 30))
    writer.flush()
    with sqlite3.connect(store.catalog_path) as db:
        db.execute("UPDATE runs SET pid = ? WHERE id = ?", (dead_pid(), writer.run_id))
    (entry,) = store.list_runs()
    assert (entry["status"], entry["samples"]) == ("interrupted", 30)
    assert len(store.read(writer.run_id)) == 30


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="pid start times come from /proc")
def test_running_run_whose_pid_was_reused_is_listed_interrupted(store: RunStore) -> None:
    writer = open_run(store)
    with sqlite3.connect(store.catalog_path) as db:
        db.execute("UPDATE runs SET pid_started = '1' WHERE id = ?", (writer.run_id,))
    assert store.get(writer.run_id)["status"] == "interrupted"


def test_running_run_of_a_live_process_stays_running(store: RunStore) -> None:
    writer = open_run(store)
    assert store.get(writer.run_id)["status"] == "running"


CRASHING_WRITER = """
import sys, time
import numpy as np
from rig.store.runs import RunStore

writer = RunStore(sys.argv[1]).open_run("crash", "sim", "seed", "3f2a9c", ["t", "u", "theta_m"], {})
print(writer.run_id, flush=True)
rows = 0
while True:
    t = (rows + np.arange(20)) / 1000.0
    writer.append({"t": t, "u": np.sin(t), "theta_m": t**2})
    rows += 20
    print(time.monotonic(), rows, flush=True)
    time.sleep(0.02)
"""


def test_sigkill_mid_run_keeps_all_but_the_last_second(tmp_path: Path) -> None:
    home = tmp_path / "home"
    env = {**os.environ, "PYTHONPATH": str(REPO_ROOT)}
    child = subprocess.Popen(
        [sys.executable, "-c", CRASHING_WRITER, str(home)], env=env, stdout=subprocess.PIPE, text=True
    )
    assert child.stdout is not None
    run_id = child.stdout.readline().strip()
    # 2.5 s: at least two flushes even when a loaded machine makes an fsync take a good part of a second.
    time.sleep(2.5)
    child.send_signal(signal.SIGKILL)
    child.wait(timeout=10)
    progress = [(float(s), int(n)) for s, n in (line.split() for line in child.stdout.read().splitlines())]

    (entry,) = RunStore(home).list_runs()
    assert (entry["id"], entry["status"]) == (run_id, "interrupted")
    assert entry["samples"] > 0
    run = RunStore(home).read(run_id)
    assert len(run) == entry["samples"]
    assert np.all(np.diff(run.t) > 0)
    # Every row appended more than a flush interval (1 s, plus slack for a slow machine) before the
    # last append was on disk.
    last_s = progress[-1][0]
    assert entry["samples"] >= max((n for s, n in progress if s <= last_s - 1.3), default=0)


def test_metadata_updates_are_one_write_of_a_size_that_does_not_grow(
    store: RunStore, monkeypatch: pytest.MonkeyPatch
) -> None:
    # An observer updates a recording run's metadata many times an hour; each is one encoding and one
    # write of what the writer holds (no read of the catalog's row), and the same summary writes the same
    # size whatever came before.
    writer = store.open_run("endurance", "sim", "seed", "3f2a9c", COLUMNS, dict(META))
    writer.update_meta({"segments": [{"label": f"s{k}", "start": k, "cycles": 1} for k in range(100)]})

    def no_read(*args: object) -> None:
        raise AssertionError("update_meta read the catalog's row")

    monkeypatch.setattr(store, "_row", no_read)
    sizes = []
    for update in range(5):
        writer.update_meta({"observed": {"track": [float(update)] * 50, "travel_rad": 10.0 + update}})
        with store.catalog.read() as db:
            text = db.execute(sa.select(tables.runs.c.meta).where(tables.runs.c.id == writer.run_id)).scalar()
        sizes.append(len(text))
        meta = json.loads(text)
        assert meta["observed"]["travel_rad"] == 10.0 + update and len(meta["segments"]) == 100
        assert meta["notes"] == "store test"  # what open_run wrote is kept
    assert len(set(sizes)) == 1
    monkeypatch.undo()
    writer.finish()
