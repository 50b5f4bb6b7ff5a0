"""Run data on object storage (`HDRIG_DATA=s3://bucket/prefix`, through fsspec/s3fs) against a real S3 API
on loopback (moto's server, started by the fixture): parts, compaction, sealing, reads while recording,
downloads, and a writer killed mid-run left `interrupted` with its flushed parts readable."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from hdrig_testing.fleet_services import S3Server
from rig.store.runfile import read_run
from rig.store.runs import MERGE_FANIN, RunStore

REPO_ROOT = Path(__file__).resolve().parents[1]
COLUMNS = ["t", "u", "theta_m"]


def block(first: int, n: int) -> dict[str, np.ndarray]:
    t = (first + np.arange(n)) / 1000.0
    return {"t": t, "u": np.sin(t), "theta_m": t**2}


def keys_of(store: RunStore, run_id: str) -> list[str]:
    return sorted(store.data.names(run_id))


def test_parts_merges_and_the_sealed_file_are_objects_and_read_back_exactly(
    tmp_path: Path, s3_data: str
) -> None:
    store = RunStore(tmp_path / "home", data=s3_data)
    assert not store.data.is_local
    writer = store.open_run("endurance", "sim", None, None, COLUMNS, {"sample_rate_hz": 1000.0}, 0.0)
    parts = MERGE_FANIN + 2  # one compaction into a merged object, and two parts after it
    for k in range(parts):
        writer.append(block(k * 100, 100))
        writer.flush()
    writer._compactor.join()
    assert keys_of(store, writer.run_id) == [
        f"merged-000000-{MERGE_FANIN - 1:06d}.parquet",
        f"part-{MERGE_FANIN:06d}.parquet",
        f"part-{MERGE_FANIN + 1:06d}.parquet",
    ]
    assert not any((tmp_path / "home" / "runs" / writer.run_id).glob("*.parquet"))  # nothing on local disk
    live = store.read(writer.run_id)  # while recording: from the objects
    np.testing.assert_array_equal(live["theta_m"], (np.arange(parts * 100) / 1000.0) ** 2)
    writer.finish()
    assert keys_of(store, writer.run_id) == ["data.parquet"]
    entry = store.get(writer.run_id)
    assert entry["path"] == f"{s3_data}/runs/{writer.run_id}/data.parquet" and entry["samples"] == parts * 100
    window = store.read(writer.run_id, columns=["u"], t0=0.5, t1=0.6)
    np.testing.assert_array_equal(window.t, np.arange(500, 601) / 1000.0)
    exported = store.export(writer.run_id, "csv", tmp_path / "download.csv")
    np.testing.assert_allclose(read_run(exported)["u"], np.sin(np.arange(parts * 100) / 1000.0), rtol=1e-15)


CRASHING_WRITER = """
import sys, time
import numpy as np
from rig.store.runs import RunStore

store = RunStore(sys.argv[1], data=sys.argv[2])
writer = store.open_run("crash", "sim", None, None, ["t", "u", "theta_m"], {}, 0.2)
print(writer.run_id, flush=True)
rows = 0
while True:
    t = (rows + np.arange(20)) / 1000.0
    writer.append({"t": t, "u": np.sin(t), "theta_m": t})
    rows += 20
    print(writer.samples, flush=True)
    time.sleep(0.01)
"""


def test_a_writer_killed_mid_run_is_interrupted_and_its_flushed_parts_are_read(
    tmp_path: Path, s3: S3Server, s3_data: str
) -> None:
    home = tmp_path / "home"
    env = {**os.environ, **s3.env, "PYTHONPATH": str(REPO_ROOT)}
    child = subprocess.Popen(
        [sys.executable, "-c", CRASHING_WRITER, str(home), s3_data],
        env=env,
        stdout=subprocess.PIPE,
        text=True,
    )
    assert child.stdout is not None
    run_id = child.stdout.readline().strip()
    deadline = time.monotonic() + 60.0  # a loaded machine: a deadline on the flushes seen, not a sleep
    flushed = 0
    while flushed < 400 and time.monotonic() < deadline:
        flushed = int(child.stdout.readline())
    assert flushed >= 400, "the writer did not flush 400 rows within 60 s"
    child.send_signal(signal.SIGKILL)  # wherever it is: appending, writing a part, uploading it
    child.wait(timeout=10)

    store = RunStore(home, data=s3_data)
    (entry,) = store.list_runs()
    assert (entry["id"], entry["status"]) == (run_id, "interrupted")
    assert entry["samples"] >= flushed  # every row the writer had flushed when last heard of
    run = store.read(run_id)
    assert len(run) == entry["samples"]
    np.testing.assert_array_equal(run.t, np.arange(len(run)) / 1000.0)  # no row lost or doubled
    assert keys_of(store, run_id) == ["data.parquet"]  # sealed on the object store
