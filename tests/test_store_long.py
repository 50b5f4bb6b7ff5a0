"""The store at any length: parts compacted while recording, sealing and export streamed, and a window or
some columns read from the row groups that hold them only.

Expected values come from the rows the test appended (t = k/1000 s, u = sin t), never from the store;
files are read back with pyarrow and scipy's `loadmat`, which this project did not write.
"""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import scipy.io

import rig.store.runs as store_module
from rig.store.runfile import ROW_GROUP_ROWS, read_run
from rig.store.runs import MERGE_FANIN, PART_ROWS_MAX, RunStore, UnknownColumnError

COLUMNS = ["t", "u", "theta_m"]


def block(first: int, n: int) -> dict[str, np.ndarray]:
    t = (first + np.arange(n)) / 1000.0
    return {"t": t, "u": np.sin(t), "theta_m": t**2}


@pytest.fixture
def store(tmp_path: Path) -> RunStore:
    return RunStore(tmp_path / "home")


def record(store: RunStore, parts: int, rows: int, finish: bool = True) -> store_module.RunWriter:
    """A run of `parts` flushes of `rows` rows each (flushed by hand: no clock involved)."""
    writer = store.open_run("endurance", "sim", "seed", "abc", COLUMNS, {"sample_rate_hz": 1000.0}, 3600.0)
    for k in range(parts):
        writer.append(block(k * rows, rows))
        writer.flush()
    if finish:
        writer.finish()
    return writer


def files(writer: store_module.RunWriter) -> list[str]:
    return sorted(p.name for p in writer.run_dir.iterdir() if p.suffix == ".parquet")


def test_every_sixteen_parts_are_compacted_into_one_merged_file(store: RunStore) -> None:
    writer = record(store, 2 * MERGE_FANIN + 3, 50, finish=False)
    writer._compactor.join()
    assert files(writer) == [
        "merged-000000-000015.parquet",
        "merged-000016-000031.parquet",
        "part-000032.parquet",
        "part-000033.parquet",
        "part-000034.parquet",
    ]
    run = store.read(writer.run_id)  # while recording: every row once, in order
    np.testing.assert_array_equal(run.t, np.arange(35 * 50) / 1000.0)
    writer.finish()


def test_sixteen_merged_files_merge_again(store: RunStore) -> None:
    writer = record(store, MERGE_FANIN**2, 4, finish=False)
    writer._compactor.join()
    assert files(writer) == ["merged-000000-000255.parquet"]
    writer.finish()
    assert files(writer) == ["data.parquet"]
    assert len(store.read(writer.run_id)) == 256 * 4


def test_a_crash_between_merge_and_delete_counts_each_row_once(store: RunStore) -> None:
    writer = record(store, 3, 10, finish=False)
    # As if the process died after renaming a merged file into place, before deleting its sources.
    store_module._copy_rows(
        store.data,
        [str(writer.run_dir / f"part-{k:06d}.parquet") for k in range(2)],
        writer.run_id,
        "merged-000000-000001.parquet",
        {},
    )
    assert len(files(writer)) == 4
    np.testing.assert_array_equal(store.read(writer.run_id).t, np.arange(30) / 1000.0)
    writer.finish()
    np.testing.assert_array_equal(store.read(writer.run_id)["u"], np.sin(np.arange(30) / 1000.0))


def test_sealed_data_is_in_whole_row_groups_with_the_run_metadata(store: RunStore) -> None:
    writer = record(store, 40, 4000)  # 160,000 rows in parts of 4,000
    data = pq.ParquetFile(writer.run_dir / "data.parquet")
    assert [data.metadata.row_group(g).num_rows for g in range(data.num_row_groups)] == [
        ROW_GROUP_ROWS,
        ROW_GROUP_ROWS,
        160_000 - 2 * ROW_GROUP_ROWS,
    ]
    assert read_run(writer.run_dir / "data.parquet").meta["experiment"] == "endurance"


def test_a_window_of_some_columns_reads_only_the_row_groups_that_hold_it(
    store: RunStore, monkeypatch: pytest.MonkeyPatch
) -> None:
    writer = record(store, 40, 4000)
    groups_read: list[int] = []
    original = pq.ParquetFile.read_row_group

    def counting(self: pq.ParquetFile, i: int, *args: object, **kwargs: object) -> object:
        groups_read.append(i)
        return original(self, i, *args, **kwargs)

    monkeypatch.setattr(pq.ParquetFile, "read_row_group", counting)
    # 70.0..75.0 s is rows 70,000..75,000: all in the second row group (65,536..131,071).
    window = store.read(writer.run_id, columns=["u"], t0=70.0, t1=75.0)
    assert groups_read == [1]
    assert list(window.columns) == ["t", "u"]
    t = np.arange(70_000, 75_001) / 1000.0
    np.testing.assert_array_equal(window.t, t)
    np.testing.assert_array_equal(window["u"], np.sin(t))


def test_an_empty_window_is_an_empty_selection(store: RunStore) -> None:
    writer = record(store, 2, 100)
    window = store.read(writer.run_id, t0=50.0, t1=60.0)
    assert len(window) == 0 and list(window.columns) == COLUMNS


def test_an_unknown_column_is_a_one_line_error_listing_the_run_s(store: RunStore) -> None:
    writer = record(store, 1, 10)
    with pytest.raises(UnknownColumnError, match=r"no column 'omega' \(it has t, u, theta_m\)"):
        store.read(writer.run_id, columns=["omega"])


def test_reading_segments_renumbers_their_rows(store: RunStore) -> None:
    writer = store.open_run("endurance", "sim", None, None, COLUMNS, {}, 3600.0)
    writer.update_meta(
        {
            "segments": [
                {"label": "duty-0", "mode": "position", "start": 0, "cycles": 500},
                {"label": "c0/v+1", "mode": "velocity", "start": 500, "cycles": 100},
                {"label": "duty-1", "mode": "position", "start": 600, "cycles": 300},
                {"label": "c1/v+1", "mode": "velocity", "start": 900, "cycles": 100},
            ]
        }
    )
    writer.append(block(0, 1000))
    writer.finish()
    run = store.read(writer.run_id, segments=["c0/v+1", "c1/v+1"])
    np.testing.assert_array_equal(run.t, np.r_[np.arange(500, 600), np.arange(900, 1000)] / 1000.0)
    assert [(s["label"], s["start"]) for s in run.meta["segments"]] == [("c0/v+1", 0), ("c1/v+1", 100)]


@pytest.mark.parametrize("fmt", ["parquet", "csv"])
def test_export_streams_the_whole_run(store: RunStore, tmp_path: Path, fmt: str) -> None:
    writer = record(store, 20, 5000)
    path = store.export(writer.run_id, fmt, tmp_path / f"all.{fmt}")
    run = read_run(path)
    t = np.arange(100_000) / 1000.0
    np.testing.assert_array_equal(run.t, t)
    np.testing.assert_array_equal(run["theta_m"], t**2)
    assert run.meta["run_id"] == writer.run_id


def test_export_of_a_selection_as_mat(store: RunStore, tmp_path: Path) -> None:
    writer = record(store, 20, 5000)
    path = store.export(writer.run_id, "mat", tmp_path / "sel.mat", columns=["theta_m"], t0=10.0, t1=90.0)
    data = scipy.io.loadmat(path, squeeze_me=True)
    t = np.arange(10_000, 90_001) / 1000.0
    np.testing.assert_array_equal(data["t"], t)
    np.testing.assert_array_equal(data["theta_m"], t**2)
    assert "u" not in data


def compaction_threads(writer: store_module.RunWriter) -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == f"compact-{writer.run_id}"]


def test_one_compaction_thread_serves_every_burst_of_merges(store: RunStore) -> None:
    # Each thread brings its own malloc arena and pyarrow heap: one per burst, for hours, added up.
    writer = record(store, MERGE_FANIN, 10, finish=False)
    writer._compactor.join()
    first = compaction_threads(writer)
    assert len(first) == 1  # still there between bursts
    for burst in range(1, 4):
        for k in range(MERGE_FANIN):
            writer.append(block((burst * MERGE_FANIN + k) * 10, 10))
            writer.flush()
        writer._compactor.join()
        assert compaction_threads(writer) == first
    assert files(writer) == [f"merged-{16 * b:06d}-{16 * b + 15:06d}.parquet" for b in range(4)]
    writer.finish()
    assert compaction_threads(writer) == []  # ends with the run
    np.testing.assert_array_equal(store.read(writer.run_id).t, np.arange(64 * 10) / 1000.0)


def test_a_flush_of_many_rows_writes_parts_of_about_one_row_group(store: RunStore) -> None:
    writer = store.open_run("endurance", "sim", "seed", "abc", COLUMNS, {}, 3600.0)
    rows, per_block = 3 * PART_ROWS_MAX + PART_ROWS_MAX // 2, 250
    for first in range(0, rows, per_block):
        writer.append(block(first, min(per_block, rows - first)))
    writer.flush()
    sizes = [pq.ParquetFile(writer.run_dir / name).metadata.num_rows for name in files(writer)]
    assert len(sizes) == 4 and sum(sizes) == rows  # ceil(3.5) parts of about equal rows
    assert max(sizes) <= PART_ROWS_MAX + per_block  # a part may pass it by part of one block
    writer.finish()
    np.testing.assert_array_equal(store.read(writer.run_id).t, np.arange(rows) / 1000.0)


@pytest.mark.parametrize("max_pending", [1000, None])
def test_append_flushes_itself_only_past_max_pending_rows(
    store: RunStore, monkeypatch: pytest.MonkeyPatch, max_pending: int | None
) -> None:
    # No flush by the clock here, and no writer thread (it writes a run's first rows at once): the
    # appender alone decides.
    monkeypatch.setattr(store_module, "FIRST_FLUSH_S", 3600.0)
    writer = store.open_run(
        "endurance", "sim", "seed", "abc", COLUMNS, {}, 3600.0, max_pending_rows=max_pending
    )
    for k in range(3):
        writer.append(block(k * 300, 300))
    assert writer.samples == 0  # 900 rows wait: not past 1000
    writer.append(block(900, 300))
    # In virtual time (a bound) the appender wrote them itself; in real time (None) it never waits.
    assert writer.samples == (1200 if max_pending is not None else 0)
    writer.finish()
    assert len(store.read(writer.run_id)) == 1200
