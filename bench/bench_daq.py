"""DAQ stream benchmark (`python bench/bench_daq.py`): the sustained sample rate, end to end.

Twin → pty (or socket://) → `SerialDaq` → numpy. The twin runs in a child process — its own
interpreter, as the board is its own machine — so the figures are the host driver's, not two Python
threads sharing one interpreter (`--in-process` runs it as the tests do, in a thread). For each rate:
RATE and BLOCK, START, `read_samples()` every 10 ms for the duration, STOP, then the frames still
queued. Prints a table, asserts nothing:

- delivered: samples received / wall time from START's reply to STOP's reply [samples/s];
- lost: samples missing by sequence number, including the tail (STOP's count); CRC: frames dropped;
- latency: arrival of each read − host time of its newest sample (median, 99th percentile) [ms]:
  the age of the freshest sample the host holds, with frames of BLOCK samples;
- host CPU: the driver process's CPU time / wall time over the stream [%].
"""

from __future__ import annotations

import argparse
import math
import multiprocessing
import platform
import time
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Literal

import numpy as np

from drivers.serial_daq import SerialDaq
from sim_backend.daq_twin import DaqTwin

Transport = Literal["pty", "socket"]
CASES: list[tuple[float, int]] = [(1000, 10), (5000, 10), (10000, 10), (20000, 20), (20000, 1)]
"""(rate [Hz], samples per frame): a frame every 10 ms at 1 kHz, every 1 ms from 10 kHz; the last
row is the frame-rate stress case: 20 000 frames/s of one sample."""
READ_EVERY_S = 0.01


def wave(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    s = np.sin(2 * math.pi * 0.7 * t)
    return 40.0 * s, 0.4 * s


def serve_twin(conn: Connection, transport: Transport) -> None:
    """The child process: a twin until the parent says stop."""
    with DaqTwin(wave, transport=transport, load_noise_rad=2e-6) as twin:
        conn.send(twin.url)
        conn.recv()


@dataclass
class Result:
    rate_hz: float
    block: int
    transport: str
    received: int
    delivered_hz: float
    lost: int
    crc_errors: int
    latency_ms: tuple[float, float]
    cpu_percent: float


def measure(url: str, rate_hz: float, block: int, duration_s: float, transport: str) -> Result:
    with SerialDaq(url, timeout_s=5.0) as daq:
        daq.set_rate(rate_hz, samples_per_frame=block)
        daq.estimate_clock_offset(n=16)
        received, ages = 0, []
        cpu0 = time.process_time()
        daq.start()
        t_start = time.monotonic()
        while time.monotonic() - t_start < duration_s:
            time.sleep(READ_EVERY_S)
            samples = daq.read_samples()
            if len(samples):
                ages.append(time.monotonic() - samples.t_host_s[-1])
                received += len(samples)
        stats = daq.stop()
        t_stop = time.monotonic()
        cpu = time.process_time() - cpu0
        received += len(daq.read_samples())
    wall = t_stop - t_start
    return Result(
        rate_hz,
        block,
        transport,
        received,
        received / wall,
        stats.lost_samples,
        stats.crc_errors,
        (float(np.median(ages)) * 1e3, float(np.percentile(ages, 99)) * 1e3),
        100 * cpu / wall,
    )


def run_case(rate_hz: float, block: int, duration_s: float, transport: Transport, in_process: bool) -> Result:
    if in_process:
        with DaqTwin(wave, transport=transport, load_noise_rad=2e-6) as twin:
            return measure(twin.url, rate_hz, block, duration_s, transport + " (thread)")
    parent, child = multiprocessing.get_context("spawn").Pipe()
    process = multiprocessing.get_context("spawn").Process(target=serve_twin, args=(child, transport))
    process.start()
    try:
        url = parent.recv()
        return measure(url, rate_hz, block, duration_s, transport)
    finally:
        parent.send("stop")
        process.join(timeout=10)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=10.0, help="seconds per rate (default 10)")
    parser.add_argument("--transport", choices=["pty", "socket"], action="append", help="default: pty")
    parser.add_argument("--in-process", action="store_true", help="twin in a thread of this process")
    args = parser.parse_args()
    transports: list[Transport] = args.transport or ["pty"]
    print(f"DAQ stream, twin → line → SerialDaq → numpy, {args.duration:g} s per rate")
    print(f"{platform.python_implementation()} {platform.python_version()}, {platform.machine()}\n")
    header = (
        f"{'transport':<16}{'rate Hz':>9}{'block':>6}{'received':>10}{'delivered/s':>13}"
        f"{'lost':>6}{'CRC':>5}{'latency ms (med/p99)':>22}{'host CPU':>10}"
    )
    print(header)
    print("-" * len(header))
    for transport in transports:
        for rate_hz, block in CASES:
            r = run_case(rate_hz, block, args.duration, transport, args.in_process)
            print(
                f"{r.transport:<16}{r.rate_hz:>9.0f}{r.block:>6}{r.received:>10}{r.delivered_hz:>13.1f}"
                f"{r.lost:>6}{r.crc_errors:>5}{r.latency_ms[0]:>12.2f} / {r.latency_ms[1]:<7.2f}"
                f"{r.cpu_percent:>9.1f}%"
            )


if __name__ == "__main__":
    main()
