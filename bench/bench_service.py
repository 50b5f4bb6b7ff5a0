"""REST service benchmark (`python bench/bench_service.py`): the service as `hdrig serve` runs it, in a
child process on loopback (uvicorn, the app of `api.app.create_app`, the rig worker on its own thread),
on the simulated rig paced to the wall clock (configs/rigs/sim-live.yaml, 1 kHz). Clients are this
process (asyncio + httpx), so their parsing does not share the service's interpreter. Prints the
figures beside the targets (docs/BENCHMARKS.md); asserts nothing.

- Event latency: for every `samples` event a client reads over SSE, its arrival time (wall clock, read
  as the event's blank line arrives) minus the event's publish time in the service (`Event.time_s`,
  asked of the child when the run is over). A samples event is published in the runner's sink, right
  after the block is handed from the rig's loop to the run's writer: publish time is the block's
  hand-off plus the decimation to 25 points (tens of µs). Target: p99 < 100 ms.
- Event rate: events and decimated sample points a client receives per second during a run.
- `GET /api/v1/runs` with 1,000 runs in the catalog (recorded through `RunStore.open_run`/`RunWriter`,
  20 samples each): requests per second, one client in sequence and four at once.
- The loop's on-time share: the simulated rig computes each 0.25 s chunk (250 cycles) and then sleeps
  until the chunk's wall-clock deadline (`sim_backend.inprocess.SimRig._run_cycles`: start + t_s) before
  handing it over. A chunk is **on time** when that hand-over is at most ON_TIME_S after its deadline:
  one interpreter switch interval (`sys.getswitchinterval()`, 5 ms), the longest a thread that wants
  the GIL should wait when the others run Python. Measured in the service with 0 and with 20 clients
  streaming a run's events; the lateness distribution is printed too.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import multiprocessing
import os
import platform
import socket
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import httpx
import numpy as np

REPO = Path(__file__).resolve().parents[1]
RIG = REPO / "configs/rigs/sim-live.yaml"
API = "/api/v1"
ON_TIME_S = 0.005  # one GIL switch interval: see the module doc
LATENCY_TARGET_S = 0.100
RUN_PARAMS = {"speeds_rad_s": [5.0, 20.0, 50.0, 100.0], "hold_s": 2.5}  # ~25 s, ~100 chunks, per case
WARM_UP_PARAMS = {"speeds_rad_s": [5.0], "hold_s": 0.5}  # first run of the process: numba's cache, imports
CATALOG_RUNS = 1000
GET_SECONDS = 10.0
START_S = 60.0


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


# ---- the service, in its own process ---------------------------------------------------------------


def serve(conn: Connection, home: str, port: int) -> None:
    """The child: `hdrig serve`'s app, with the simulated rig's chunk hand-overs timed."""
    os.environ["HDRIG_HOME"] = home
    import uvicorn

    from api.app import create_app
    from rig.config import load_rig_config
    from rig.store.runs import RunStore
    from sim_backend.inprocess import SimRig

    lateness: list[tuple[float, float]] = []  # (wall clock at hand-over, seconds after the deadline)
    original = SimRig._run_cycles

    def timed(self: SimRig, mode: Any, setpoint: np.ndarray, tau_ext: np.ndarray) -> Any:
        out = original(self, mode, setpoint, tau_ext)
        if self._wall_start is not None:
            lateness.append((time.time(), time.monotonic() - (self._wall_start + self.t_s)))
        return out

    SimRig._run_cycles = timed  # type: ignore[method-assign]
    app = create_app(load_rig_config(str(RIG)), RunStore(home))

    def answer() -> None:
        while True:
            what = conn.recv()
            if what == "events":
                log = app.state.worker.events
                conn.send([(e.id, str(e.kind), e.run_id, e.time_s) for e in log.since(0, limit=10**9)])
            elif what == "chunks":
                conn.send(list(lateness))
                lateness.clear()

    threading.Thread(target=answer, daemon=True).start()
    uvicorn.run(app, host="127.0.0.1", port=port, log_level="warning")


# ---- clients ----------------------------------------------------------------------------------------


@dataclass
class Stream:
    """What one SSE client received: (event id, kind, arrival wall time, points)."""

    events: list[tuple[int, str, float, int]] = field(default_factory=list)


async def follow(client: httpx.AsyncClient, run_id: str, into: Stream) -> None:
    event_id, kind, points = 0, "", 0
    async with client.stream("GET", f"{API}/runs/{run_id}/events", timeout=60) as response:
        response.raise_for_status()
        async for line in response.aiter_lines():
            if line.startswith("id: "):
                event_id = int(line[4:])
            elif line.startswith("event: "):
                kind = line[7:]
            elif line.startswith("data: ") and kind == "samples":
                points = len(json.loads(line[6:])["t"])
            elif not line and event_id:
                into.events.append((event_id, kind, time.time(), points))
                event_id, kind, points = 0, "", 0


async def run_with_clients(
    base: str, key: str, clients: int, params: dict[str, Any] = RUN_PARAMS
) -> tuple[str, list[Stream]]:
    """Start a run, follow its events with `clients` streams until it ends; the run id and streams."""
    headers = {"Authorization": f"Bearer {key}"}
    async with httpx.AsyncClient(base_url=base, headers=headers, timeout=30) as http:
        started = await http.post(f"{API}/runs", json={"experiment": "speed-sweep", "params": params})
        started.raise_for_status()
        run_id = started.json()["id"]
        streams = [Stream() for _ in range(clients)]
        tasks = [asyncio.create_task(follow(http, run_id, s)) for s in streams]
        while True:  # the run's status, once a second: a light load beside the streams
            status = (await http.get(f"{API}/runs/{run_id}")).json()["status"]
            if status not in ("queued", "running"):
                break
            await asyncio.sleep(1.0)
        await asyncio.wait_for(asyncio.gather(*tasks), timeout=30)
        return run_id, streams


def get_throughput(base: str, key: str, parallel: int) -> tuple[float, list[float], int]:
    """GET /runs for GET_SECONDS with `parallel` clients in threads: requests/s, latencies, runs listed."""
    latencies: list[float] = []
    listed = [0]
    stop = time.monotonic() + GET_SECONDS

    def worker() -> None:
        with httpx.Client(base_url=base, headers={"Authorization": f"Bearer {key}"}, timeout=60) as http:
            while time.monotonic() < stop:
                t0 = time.perf_counter()
                answer = http.get(f"{API}/runs")
                latencies.append(time.perf_counter() - t0)
                answer.raise_for_status()
                listed[0] = len(answer.json())

    t_start = time.monotonic()
    threads = [threading.Thread(target=worker) for _ in range(parallel)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return len(latencies) / (time.monotonic() - t_start), latencies, listed[0]


def record_tiny_runs(home: Path, count: int) -> float:
    """`count` runs of 20 samples through the store's own API; seconds taken."""
    from rig.status import RunStatus
    from rig.store.runs import RunStore

    store = RunStore(home)
    t = np.arange(20) * 1e-3
    block = {"t": t, "u": np.zeros(20), "theta_m": np.sin(t)}
    t0 = time.perf_counter()
    for _ in range(count):
        writer = store.open_run(
            "speed-sweep", "sim-live", "seed", None, list(block), {"sample_rate_hz": 1000}
        )
        writer.append(block)
        writer.finish(RunStatus.COMPLETE)
    return time.perf_counter() - t0


# ---- figures ----------------------------------------------------------------------------------------


def pct(values: list[float] | np.ndarray, q: float) -> float:
    return float(np.percentile(np.asarray(values), q)) if len(values) else float("nan")


def latencies_ms(streams: list[Stream], published: dict[int, float]) -> list[float]:
    return [
        (arrived - published[event_id]) * 1e3
        for s in streams
        for event_id, kind, arrived, _ in s.events
        if kind == "samples" and event_id in published
    ]


def on_time(lateness: list[tuple[float, float]]) -> tuple[float, list[float]]:
    late = [d for _, d in lateness]
    share = sum(d <= ON_TIME_S for d in late) / len(late) if late else float("nan")
    return share, late


def rate(stream: Stream) -> tuple[float, float]:
    """Events/s and sample points/s between the stream's first and last samples event."""
    samples = [(arrived, points) for _, kind, arrived, points in stream.events if kind == "samples"]
    if len(samples) < 2:
        return float("nan"), float("nan")
    span = samples[-1][0] - samples[0][0]
    inside = [e for e in stream.events if samples[0][0] <= e[2] <= samples[-1][0]]
    return (len(inside) - 1) / span, sum(p for _, p in samples[1:]) / span


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--clients", type=int, default=20, help="streaming clients in the loaded case")
    args = parser.parse_args()
    print(f"# REST service benchmark — {platform.processor() or platform.machine()}, {os.cpu_count()} cores,")
    print(f"# Python {platform.python_version()}, switch interval {sys.getswitchinterval() * 1e3:.0f} ms")

    with tempfile.TemporaryDirectory(prefix="hdrig-bench-service-") as scratch:
        home = Path(scratch) / "home"
        os.environ["HDRIG_HOME"] = str(home)
        from rig.core import access
        from rig.store.runs import RunStore

        key = access.create_key(RunStore(home), "operator", "bench")
        port = _free_port()
        base = f"http://127.0.0.1:{port}"
        context = multiprocessing.get_context("spawn")
        ours, theirs = context.Pipe()
        child = context.Process(target=serve, args=(theirs, str(home), port), daemon=True)
        child.start()
        try:
            deadline = time.monotonic() + START_S
            while True:
                try:
                    if httpx.get(f"{base}{API}/health", timeout=2).status_code == 200:
                        break
                except httpx.TransportError:
                    pass
                if time.monotonic() > deadline or not child.is_alive():
                    raise SystemExit("the service did not start")
                time.sleep(0.2)
            report(base, key, home, ours, args.clients)
        finally:
            child.terminate()
            child.join(10)


def report(base: str, key: str, home: Path, conn: Connection, clients: int) -> None:
    cases: dict[str, tuple[list[Stream], list[tuple[float, float]]]] = {}
    asyncio.run(run_with_clients(base, key, 0, WARM_UP_PARAMS))
    for label, n in (("0 clients", 0), ("1 client", 1), (f"{clients} clients", clients)):
        conn.send("chunks")
        conn.recv()  # forget the chunks of runs before
        _, streams = asyncio.run(run_with_clients(base, key, n))
        conn.send("chunks")
        cases[label] = (streams, conn.recv())
    conn.send("events")
    published = {event_id: t for event_id, _, _, t in conn.recv()}

    print("\n## Event latency: sample block handed over in the rig loop → client has read it over SSE")
    print("| clients | events | p50 | p99 | max | target p99 |")
    print("|---|---|---|---|---|---|")
    for label, (streams, _) in cases.items():
        if streams:
            lat = latencies_ms(streams, published)
            verdict = "PASS" if pct(lat, 99) < LATENCY_TARGET_S * 1e3 else "MISS"
            print(
                f"| {label} | {len(lat)} | {pct(lat, 50):.1f} ms | {pct(lat, 99):.1f} ms | {max(lat):.1f} ms"
                f" | < 100 ms: {verdict} |"
            )

    print("\n## Sustained event rate, one client, during a 1 kHz run (paced to the wall clock)")
    streams = cases["1 client"][0]
    events_s, points_s = rate(streams[0])
    kinds: dict[str, int] = {}
    for _, kind, _, _ in streams[0].events:
        kinds[kind] = kinds.get(kind, 0) + 1
    print(f"{events_s:.1f} events/s ({points_s:.0f} decimated sample points/s); events of the run: {kinds}")

    print("\n## The rig loop's on-time share (0.25 s chunks handed over ≤ 5 ms after their deadline)")
    print("| streaming clients | chunks | on time | late p50 | late p99 | late max | ≤ 1 ms | ≤ 20 ms |")
    print("|---|---|---|---|---|---|---|---|")
    for label, (_, lateness) in cases.items():
        share, late = on_time(lateness)
        ms = [d * 1e3 for d in late]
        print(
            f"| {label} | {len(late)} | **{share * 100:.1f} %** | {pct(ms, 50):.2f} ms | {pct(ms, 99):.2f} ms"
            f" | {max(ms):.2f} ms | {sum(d <= 0.001 for d in late) / len(late) * 100:.0f} %"
            f" | {sum(d <= 0.020 for d in late) / len(late) * 100:.0f} % |"
        )

    print(f"\n## GET {API}/runs with {CATALOG_RUNS} runs in the catalog")
    took = record_tiny_runs(home, CATALOG_RUNS)
    print(f"(recorded {CATALOG_RUNS} runs of 20 samples through RunStore in {took:.1f} s)")
    print("| clients | requests/s | p50 | p99 | runs listed |")
    print("|---|---|---|---|---|")
    for parallel in (1, 4):
        per_s, lat, listed = get_throughput(base, key, parallel)
        ms = [x * 1e3 for x in lat]
        print(f"| {parallel} | {per_s:.1f} | {pct(ms, 50):.0f} ms | {pct(ms, 99):.0f} ms | {listed} |")
    print(
        "\nThe rig worker is a thread of the service process (rig.core.worker.RigWorker); the on-time rows"
        " above say whether HTTP work in the same interpreter delays it."
    )


# ---- an oversized request (issue 23): a real `hdrig serve` child, its memory read from /proc ----------

ABUSE_SPEEDS = 12_600_000  # the request: {"speeds_rad_s": [1.0,1.0,...]}, ~50 MB
ABUSE_TARGET_S = 1.0
ABUSE_RSS_TARGET_MB = 100.0
RSS_POLL_S = 0.005
SEND_CHUNK_BYTES = 1 << 16


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    raise RuntimeError(f"no VmRSS for {pid}")


def _abuse_body() -> bytes:
    head = b'{"experiment": "speed-sweep", "params": {"speeds_rad_s": ['
    return head + b"1.0," * (ABUSE_SPEEDS - 1) + b"1.0]}}"


def _post_raw(port: int, key: str, body: bytes, chunked: bool) -> tuple[str, float]:
    """POST the body over a plain socket, sending on a thread of its own while this one waits for the
    answer: (status line, seconds from the first byte sent to the status line read). The answer's time,
    not the client's: a client that writes the whole body before it reads would time its own sending."""
    head = (
        f"POST {API}/runs HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nAuthorization: Bearer {key}\r\n"
        "Content-Type: application/json\r\n"
        + ("Transfer-Encoding: chunked\r\n" if chunked else f"Content-Length: {len(body)}\r\n")
        + "\r\n"
    ).encode()
    sock = socket.create_connection(("127.0.0.1", port))

    def send() -> None:
        try:
            sock.sendall(head)
            for i in range(0, len(body), SEND_CHUNK_BYTES):
                part = body[i : i + SEND_CHUNK_BYTES]
                sock.sendall(b"%x\r\n%s\r\n" % (len(part), part) if chunked else part)
            if chunked:
                sock.sendall(b"0\r\n\r\n")
        except OSError:
            pass  # the server answered and closed: the rest is not wanted

    sender = threading.Thread(target=send, daemon=True)
    started = time.perf_counter()
    sender.start()
    received = b""
    while b"\r\n" not in received:
        got = sock.recv(4096)
        if not got:
            break
        received += got
    took = time.perf_counter() - started
    sock.close()
    sender.join(10)
    return received.split(b"\r\n", 1)[0].decode(errors="replace"), took


def oversized_request() -> None:
    """The 12.6 M-speed request against `hdrig serve --rig sim` on 127.0.0.1, sent with a Content-Length
    and chunked: the time to its answer, and the server's RSS peak (polled every 5 ms) against its idle
    RSS."""
    import subprocess

    from rig.core import access
    from rig.store.runs import RunStore

    body = _abuse_body()
    print(f"\n## An oversized request: {ABUSE_SPEEDS:,} speeds, {len(body) / 1e6:.1f} MB, to `hdrig serve`")
    with tempfile.TemporaryDirectory(prefix="hdrig-bench-abuse-") as scratch:
        home = Path(scratch) / "home"
        key = access.create_key(RunStore(home), "operator", "bench")
        port = _free_port()
        base = f"http://127.0.0.1:{port}"
        command = [sys.executable, "-m", "rig", "serve", "--rig", "sim", "--host", "127.0.0.1"]
        child = subprocess.Popen(
            [*command, "--port", str(port)],
            env={**os.environ, "HDRIG_HOME": str(home)},
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        try:
            deadline = time.monotonic() + START_S
            while True:
                try:
                    if httpx.get(f"{base}{API}/health", timeout=2).status_code == 200:
                        break
                except httpx.TransportError:
                    pass
                if time.monotonic() > deadline or child.poll() is not None:
                    raise SystemExit("the service did not start")
                time.sleep(0.2)
            headers = {"Authorization": f"Bearer {key}"}
            httpx.get(f"{base}{API}/rig", headers=headers, timeout=10)  # warm: imports, first answers
            time.sleep(1.0)
            print("| sent as | answer | time to answer | idle RSS | peak RSS | peak − idle | targets |")
            print("|---|---|---|---|---|---|---|")
            for chunked in (False, True):
                idle = _rss_mb(child.pid)
                peak = [idle]
                done = threading.Event()

                def poll(peak: list[float] = peak, done: threading.Event = done) -> None:
                    while not done.is_set():
                        peak[0] = max(peak[0], _rss_mb(child.pid))
                        time.sleep(RSS_POLL_S)

                watcher = threading.Thread(target=poll, daemon=True)
                watcher.start()
                status, took = _post_raw(port, key, body, chunked)
                time.sleep(0.5)  # whatever the server does after answering shows in its RSS too
                done.set()
                watcher.join()
                grown = peak[0] - idle
                verdict = "PASS" if took < ABUSE_TARGET_S and grown < ABUSE_RSS_TARGET_MB else "MISS"
                print(
                    f"| {'chunked' if chunked else 'Content-Length'} | {status} | {took * 1e3:.0f} ms"
                    f" | {idle:.0f} MB | {peak[0]:.0f} MB | {grown:.1f} MB | < 1 s, < 100 MB: {verdict} |"
                )
            jobs = httpx.get(f"{base}{API}/jobs", headers=headers, timeout=10).json()
            health = httpx.get(f"{base}{API}/health", timeout=10).status_code
            print(f"jobs the service took: {len(jobs)}; health afterwards: {health}")
        finally:
            child.terminate()
            child.wait(10)


if __name__ == "__main__":
    if "--oversized-only" in sys.argv:
        oversized_request()
    else:
        main()
        oversized_request()
