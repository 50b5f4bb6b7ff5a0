"""The fleet's benchmark (issue 16): catalog queries with 100,000 runs on SQLite and PostgreSQL, four writer
processes at once, and batch fit throughput for 200 units on 1, 2 and 4 local Dask workers.

Prints each figure beside its target. PostgreSQL is Debian's, started in a temporary folder on 127.0.0.1
with fsync on (hdrig_testing.fleet_services). The batch fit uses small runs per unit: a speed sweep of two
speeds (0.3 s holds) and a 4-pulse train recorded once on the simulated rig, copied into the store under
200 unit serials, fitted by the staged estimates (`--no-joint`; the joint refinement adds ~2 s a unit).
The listing: the first page and a page 90,000 runs deep (what `hdrig runs list` and GET /runs call, and
GET /runs itself through the app in-process), and every run (`runs list --all`). `--catalog`: the catalog
queries alone.
"""

from __future__ import annotations

import statistics
import subprocess
import sys
import tempfile
import textwrap
import time
from collections.abc import Callable
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import sqlalchemy as sa

from hdrig_testing.fleet_services import postgres_server
from rig.config import load_rig_config
from rig.core import access, actions, fleet
from rig.store import catalog as tables
from rig.store.catalog import Cursor
from rig.store.runs import RunStore

RUNS = 100_000
UNITS = 2_000  # 50 runs per gear unit
RIGS = 20
BATCH_UNITS = 200
EPOCH = datetime(2026, 1, 1, tzinfo=UTC)  # the synthetic runs start every 5 min from here
TARGETS_MS = {"one run by id": 10.0, "a unit's runs": 50.0, "a glob of 10 units": 100.0, "a tag": 250.0,
              "newest 100": 50.0, "first page": 50.0, "page 90,000 deep": 50.0,
              "first page, REST": 100.0}  # fmt: skip
DEEP = 90_000  # the deep page starts after this many newer runs


def timed_ms(action: Callable[[], Any], repeat: int = 20) -> float:
    """Median wall time of `action` [ms]."""
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        action()
        times.append((time.perf_counter() - start) * 1e3)
    return statistics.median(times)


def synthetic_run(n: int) -> tuple[str, str]:
    """The id and start of the n-th synthetic run (every 5 min from EPOCH)."""
    run_id = f"2026{n // 86400 % 12 + 1:02d}01-{n % 86400:06d}-pulse-{n:05x}"
    return run_id, (EPOCH + timedelta(seconds=300 * n)).isoformat(timespec="milliseconds")


def fill(store: RunStore) -> None:
    """100,000 complete runs: 20 rigs, 2,000 units, a tag on every tenth, as one bulk insert."""
    rows, tags = [], []
    for n in range(RUNS):
        run_id, started = synthetic_run(n)
        rows.append(
            {
                "id": run_id, "experiment": "pulse", "rig": f"bench-{n % RIGS:02d}", "status": "complete",
                "started": started,
                "samples": 4000, "metrics": "{}",
                "path": f"runs/{run_id}/data.parquet", "meta": '{"sample_rate_hz": 1000.0}',
                "unit": f"HD25-{n % UNITS:04d}", "operator": f"op{n % 7}",
            }
        )  # fmt: skip
        if n % 10 == 0:
            tags.append({"run_id": run_id, "tag": f"line={n % 3}"})
    with store.catalog.write() as db:
        db.execute(tables.runs.insert(), rows)
        db.execute(tables.run_tags.insert(), tags)


def catalog_queries(name: str, store: RunStore) -> dict[str, float]:
    start = time.perf_counter()
    fill(store)
    fill_s = time.perf_counter() - start
    some = store.list_runs(unit="HD25-0042")[0]["id"]
    deep = Cursor(*reversed(synthetic_run(RUNS - DEEP)))  # the page holds the 100 runs before it
    assert actions.list_runs(store, cursor=deep.encode()).runs[-1].id == synthetic_run(RUNS - DEEP - 1)[0]
    figures = {
        "one run by id": timed_ms(lambda: store.get(some)),
        "a unit's runs": timed_ms(lambda: store.list_runs(unit="HD25-0042")),
        "a glob of 10 units": timed_ms(lambda: store.list_runs(unit="HD25-004*")),
        "a tag": timed_ms(lambda: store.list_runs(tags=["line=1"], rig="bench-07"), repeat=5),
        "newest 100": timed_ms(lambda: store.list_runs(limit=100)),
        # what `hdrig runs list` and GET /runs call: a page of 100 documents from the summary columns
        "first page": timed_ms(lambda: actions.list_runs(store)),
        "page 90,000 deep": timed_ms(lambda: actions.list_runs(store, cursor=deep.encode())),
        "first page, REST": rest_first_page_ms(store),
    }
    every = timed_ms(lambda: actions.list_runs(store, limit=None), repeat=1)
    print(
        f"\n{name}: 100,000 runs inserted in {fill_s:.1f} s; every run listed (`runs list --all`,"
        f" summaries) in {every / 1e3:.2f} s"
    )
    for what, ms in figures.items():
        verdict = "ok" if ms <= TARGETS_MS[what] else "MISS"
        print(f"  {what:<20} {ms:8.2f} ms   target <= {TARGETS_MS[what]:.0f} ms  {verdict}")
    return figures


def rest_first_page_ms(store: RunStore) -> float:
    """GET /api/v1/runs (the default page of 100) through the service's app in this process (TestClient:
    routing, auth, validation and JSON of the documents; no socket)."""
    from fastapi.testclient import TestClient

    from api.app import create_app

    token = access.create_key(store, "viewer", f"bench-{time.monotonic_ns()}")
    with TestClient(create_app(load_rig_config("sim"), store)) as client:
        client.headers["Authorization"] = f"Bearer {token}"
        answer = client.get("/api/v1/runs")
        assert answer.status_code == 200 and len(answer.json()) == 100, answer.text
        assert answer.headers["X-Total-Count"] == str(RUNS)
        return timed_ms(lambda: client.get("/api/v1/runs"))


WRITER = textwrap.dedent(
    """
    import sys, time, numpy as np
    from rig.store.runs import RunStore
    store = RunStore(sys.argv[1], catalog=sys.argv[2])
    runs, latencies = int(sys.argv[3]), []
    start = time.perf_counter()
    for k in range(runs):
        began = time.perf_counter()
        with store.open_run("pulse", "w", None, None, ["t", "u"], {}, 0.0, unit=f"U{k}") as w:
            for b in range(4):  # four flushes: four catalog updates, then the seal's
                t = (b * 250 + np.arange(250)) / 1000.0
                w.append({"t": t, "u": t})
        latencies.append(time.perf_counter() - began)
    print(runs / (time.perf_counter() - start), max(latencies), sorted(latencies)[len(latencies) // 2])
    """
)


def writers(name: str, catalog: str, folder: Path, runs_each: int = 40) -> None:
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", WRITER, str(folder / f"w{n}"), catalog, str(runs_each)],
            stdout=subprocess.PIPE,
            text=True,
        )
        for n in range(4)
    ]
    start = time.perf_counter()
    answers = [p.communicate()[0].split() for p in procs]
    wall = time.perf_counter() - start
    assert all(p.returncode == 0 for p in procs), "a writer failed"
    total = 4 * runs_each / wall
    worst = max(float(a[1]) for a in answers)
    median = statistics.median(float(a[2]) for a in answers)
    print(
        f"  4 writers at once ({name}): {total:.1f} runs/s together (each run: open, 4 flushes, seal),"
        f" median run {median * 1e3:.0f} ms, slowest {worst * 1e3:.0f} ms; target: no error, slowest"
        " < 2000 ms"
        f"  {'ok' if worst < 2.0 else 'MISS'}"
    )


def synthetic_units(store: RunStore) -> None:
    """A sweep and a pulse train recorded once, copied under BATCH_UNITS serials (meta and samples as
    recorded: the fit reads the same segments and parameters)."""
    config = load_rig_config("sim")
    plans = [("speed-sweep", {"speeds_rad_s": [5.0, 30.0], "hold_s": 0.3}), ("pulse", {"count": 4})]
    originals = [actions.execute_plan(actions.plan_run(e, p), config, store)[0].id for e, p in plans]
    recorded = [(store.get(i), store.read(i)) for i in originals]
    for n in range(BATCH_UNITS):
        for entry, run in recorded:
            meta = {k: v for k, v in entry["meta"].items()}
            with store.open_run(
                entry["experiment"], entry["rig"], entry["model_name"], entry["model_hash"],
                list(run.columns), meta, unit=f"HD25-{n:04d}",
            ) as writer:  # fmt: skip
                writer.append({c: run[c] for c in run.columns})
    with store.catalog.write() as db:  # the originals are no unit's
        db.execute(tables.runs.update().where(tables.runs.c.id.in_(originals)).values(unit=None))


def batch(store: RunStore) -> None:
    from distributed import Client, LocalCluster

    synthetic_units(store)
    print(
        f"\nbatch fit of {BATCH_UNITS} units (staged fits of a 2-speed sweep and a 4-pulse train each),"
        " 2 cores:"
    )
    base = None
    for workers in (1, 2, 4):
        with (
            LocalCluster(
                n_workers=workers,
                threads_per_worker=1,
                processes=True,
                host="127.0.0.1",
                dashboard_address=None,
            ) as cluster,
            Client(cluster) as client,
        ):
            # warm-up: each worker fits one unit first (imports, numba's compiled code), not timed
            warm = store.list_runs(unit="HD25-0000")
            client.run(
                fleet.fit_unit, fleet.StoreAddress.of(store), "warm-up", "HD25-0000", [r["id"] for r in warm],
                "seed", False,
            )  # fmt: skip
            start = time.perf_counter()
            report = fleet.batch_fit(store, ["unit=HD25-*"], "seed", joint=False, client=client)
            wall = time.perf_counter() - start
        assert len(report.units) == BATCH_UNITS and all(u.status == "complete" for u in report.units)
        rate = BATCH_UNITS / wall
        base = base or rate
        print(
            f"  {workers} worker(s): {wall:6.1f} s, {rate:5.2f} units/s, speed-up {rate / base:.2f}x"
            f" (target on 2 cores: 2 workers >= 1.6x, 4 workers no better than 2)"
        )


def main() -> None:
    only_batch = sys.argv[1:] == ["--batch"]  # the batch fit alone
    only_catalog = sys.argv[1:] == ["--catalog"]  # the catalog queries alone (SQLite, PostgreSQL)
    with tempfile.TemporaryDirectory(prefix="hdrig-bench-fleet-") as scratch:
        folder = Path(scratch)
        if only_batch:
            batch(RunStore(folder / "fleet"))
            return
        sqlite_url = f"sqlite:///{folder / 'catalog.sqlite'}"
        catalog_queries("SQLite", RunStore(folder / "a", catalog=sqlite_url))
        with postgres_server(fsync=True) as server:
            pg_url = server.new_database()
            catalog_queries("PostgreSQL", RunStore(folder / "b", catalog=pg_url))
            if only_catalog:
                return
            writers("PostgreSQL", server.new_database(), folder)
        writers("SQLite", f"sqlite:///{folder / 'writers.sqlite'}", folder)
        batch(RunStore(folder / "fleet"))
        with sa.create_engine(sqlite_url).connect() as db:
            size = db.execute(
                sa.text("SELECT page_count * page_size FROM pragma_page_count(), pragma_page_size()")
            )
            print(f"\nSQLite catalog of 100,000 runs: {size.scalar() / 2**20:.1f} MiB")


if __name__ == "__main__":
    main()
