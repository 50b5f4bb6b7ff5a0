"""Closed-loop benchmark (`python bench/bench_canopen.py`): 1 kHz SYNC on the virtual CAN bus for 60 s.

The `virtual-can` rig (configs/rigs/virtual-can.yaml) paced to the wall clock: the servo driver, the
DAQ driver and the rig's alignment, against the drive twin and the DAQ twin — all in this one
process, so the twins' threads share the interpreter with the loop (on a bench they are other
machines). One velocity segment, a slow sine ω = A·sin(2π·f·t) (default 20 rad/s at 0.1 Hz: the arm
sweeps 0.64 rad at the output, inside its stroke). Prints a table with the targets; asserts nothing.

- cycle time: from the SYNC going out to the loop being done with the cycle (the drive's answer
  decoded, the envelope checked, the DAQ's samples taken, and at each chunk's end θ_l interpolated)
  [ms]; the next SYNC is due one period after the last;
- within the period: the share of cycles whose cycle time is at most the 1 ms period (target ≥ 99.9 %);
- SYNC interval: time between consecutive SYNCs, and how many came later than 1.5 periods;
- samples lost, servo: cycles asked for less rows recorded, rows whose plant time does not follow the
  previous one by exactly a period, and SYNCs the drive twin took beyond the rows (target 0);
- samples lost, DAQ: by the frames' sequence numbers (the driver's decoder, the stream's tail
  included) and by the samples' indices (target 0);
- DAQ sustained rate: samples received / host time they span, against the configured rate; and
  the rows whose θ_l was extrapolated (a chunk's end that could not wait longer for the DAQ).

By default the process asks for the FIFO real-time class on one CPU (`rig.realtime.realtime_scheduling`;
its threads and the twins' child inherit both) and says what it got; `--scheduling ordinary` runs
without, `--cpu -1` on any CPU, `--twins-cpu N` puts the twins' child on CPU N (as a bench's drives
compute off the host; measured and kept off by default: docs/BENCHMARKS.md, issue 26's per-cycle cost).
The machine's load is printed with the figures: the 1-minute load average before and after, the share
of all CPUs busy during the run (/proc/stat), this process's CPU time over the wall time, and the CPU
time per cycle of this process and of the twins' child (/proc/PID/stat: all threads, user + system).
"""

from __future__ import annotations

import argparse
import fcntl
import math
import os
import platform
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import IO

import numpy as np

from drivers.hardware_rig import CycleLog
from rig.config import RIG_DIR, load_rig_config
from rig.interface import ControlMode, Segment
from rig.realtime import quiet_heap, realtime_scheduling
from sim_backend.virtual_bus import VirtualCanRig

RIG = RIG_DIR / "virtual-can.yaml"
WITHIN_PERIOD_TARGET = 0.999
LATE_SYNC_PERIODS = 1.5
PERCENTILES = (50, 90, 99, 99.9)


@dataclass(frozen=True)
class Line:
    metric: str
    measured: str
    target: str = ""
    ok: bool | None = None  # None: reported, no target

    @property
    def verdict(self) -> str:
        return "" if self.ok is None else ("PASS" if self.ok else "MISS")


def cpu_busy() -> tuple[int, int] | None:
    """(busy, total) jiffies of all CPUs since boot, from /proc/stat; None where there is none."""
    try:
        fields = [int(x) for x in Path("/proc/stat").read_text().splitlines()[0].split()[1:]]
    except (OSError, ValueError, IndexError):
        return None
    idle = fields[3] + (fields[4] if len(fields) > 4 else 0)  # idle + iowait
    return sum(fields) - idle, sum(fields)


def child_cpu_s(rig: VirtualCanRig) -> float | None:
    """CPU time [s] the twins' child has used so far (all its threads, user + system), from
    /proc/PID/stat; None with the twins in this process or without /proc."""
    if rig.child is None:
        return None
    try:
        fields = Path(f"/proc/{rig.child.pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime, stime


def pin_process(pid: int, cpu: int) -> str:
    """Every thread of process `pid` on `cpu` alone (threads it starts later inherit it); what it got."""
    try:
        for task in Path(f"/proc/{pid}/task").iterdir():
            os.sched_setaffinity(int(task.name), {cpu})
    except (OSError, AttributeError) as exc:
        return f"not pinned to CPU {cpu}: {exc}"
    return f"pinned to CPU {cpu}"


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def ms(values: np.ndarray) -> str:
    return (
        " / ".join(f"{np.percentile(values, p) * 1e3:.3f}" for p in PERCENTILES)
        + f" / {values.max() * 1e3:.3f}"
    )


def syncs_answered(rig: VirtualCanRig) -> int:
    """The SYNCs the drive twin has stepped the plant on, in this process or in the child."""
    if rig.twin is not None:
        return rig.twin.sync_count
    assert rig.child_plant_log is not None
    return rig.child_plant_log.count


def one_at_a_time() -> IO[str]:
    """Wait for any other run of this benchmark on the machine to end: two real-time loops on one CPU
    would each measure the other. Hold what it returns until the end: the lock is the kernel's, on that
    open file, and goes with it (or with the process)."""
    lock = open(Path(tempfile.gettempdir()) / "hdrig-bench-canopen.lock", "w")  # noqa: SIM115 (the caller holds it)
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        print("another bench_canopen run holds the real-time CPU: waiting for it to end", flush=True)
        fcntl.flock(lock, fcntl.LOCK_EX)
    return lock


def main() -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--duration", type=float, default=60.0, help="seconds of closed loop (default 60)")
    parser.add_argument("--amplitude", type=float, default=20.0, help="sine speed amplitude [rad/s] (20)")
    parser.add_argument("--frequency", type=float, default=0.1, help="sine frequency [Hz] (0.1)")
    parser.add_argument(
        "--rig", default=str(RIG), help="the virtual-can rig file (virtual-can-dyno: two drives)"
    )
    parser.add_argument(
        "--load-nm", type=float, default=0.0, help="τ_ext for the whole run: a load drive's [N·m]"
    )
    parser.add_argument("--daq-rate", type=float, help="DAQ sample rate [Hz] (default: the rig file's)")
    parser.add_argument("--daq-block", type=int, help="DAQ samples per frame (default: the rig file's)")
    parser.add_argument(
        "--twins",
        choices=("in-process", "process"),
        default="process",
        help="the twins in this process, or in a child on the loopback TCP bus (default: process)",
    )
    parser.add_argument(
        "--scheduling",
        choices=("realtime", "ordinary"),
        default="realtime",
        help="run the loop (and the twins' child) in the FIFO real-time class where the OS allows (default)",
    )
    parser.add_argument(
        "--cpu",
        type=int,
        default=(os.cpu_count() or 1) - 1,
        help="with realtime scheduling, the one CPU of the loop and the twins (default: the last); -1: any",
    )
    parser.add_argument(
        "--twins-cpu",
        type=int,
        default=None,
        help="with the twins in a child: pin all its threads to this CPU once it runs (default: --cpu's)",
    )
    args = parser.parse_args()
    lock = one_at_a_time()  # noqa: F841 (held until main returns)
    scheduling = "ordinary scheduling"
    if args.scheduling == "realtime":
        scheduling = realtime_scheduling(cpu=None if args.cpu < 0 else args.cpu)

    rig_file = load_rig_config(args.rig)
    config = rig_file
    daq = dict(config.extra.get("daq") or {})
    if args.daq_rate is not None:
        daq["rate_hz"] = args.daq_rate
    if args.daq_block is not None:
        daq["samples_per_frame"] = args.daq_block
    config = config.model_copy(update={"pace": "realtime", "daq": daq, "twins": args.twins})
    in_process = args.twins == "in-process"
    period = 1.0 / config.sample_rate_hz
    cycles = round(args.duration * config.sample_rate_hz)
    t = np.arange(cycles) * period
    setpoint = args.amplitude * np.sin(2 * math.pi * args.frequency * t)
    stroke_out = 2 * args.amplitude / (2 * math.pi * args.frequency) * 0.01
    print(
        f"Closed loop on {rig_file.name}, τ_ext {args.load_nm:g} N·m, paced:"
        f" {config.sample_rate_hz:g} Hz SYNC for {args.duration:g} s,"
        f" velocity ω = {args.amplitude:g}·sin(2π·{args.frequency:g}·t) rad/s (output sweeps"
        f" {stroke_out:.2f} rad)"
    )
    print(
        f"{platform.python_implementation()} {platform.python_version()}, {cpu_model()},"
        f" {os.cpu_count()} CPUs; twins {'in this process' if in_process else 'in a child process'};"
        f" {scheduling}\n"
    )

    load_before = os.getloadavg()[0]
    blocks: list[dict[str, np.ndarray]] = []
    opened_s = time.monotonic()
    rig = VirtualCanRig(config)
    opened_s = time.monotonic() - opened_s
    child = (
        "" if rig.child_start_s is None else f" (the twins' child answered after {rig.child_start_s:.2f} s)"
    )
    print(f"rig opened in {opened_s:.2f} s{child}")
    if args.twins_cpu is not None and rig.child is not None:
        print(f"the twins' child: {pin_process(rig.child.pid, args.twins_cpu)}")
    with rig, quiet_heap():  # this process owns the loop: its heap policy (rig.realtime)
        assert rig.daq is not None
        daq_rate = rig.daq.command("RATE?")
        rig.cycle_log = CycleLog()
        rig.enable()
        syncs_before = syncs_answered(rig)
        busy0, cpu0, wall0 = cpu_busy(), time.process_time(), time.monotonic()
        child0 = child_cpu_s(rig)
        result = rig.run_segment(Segment(ControlMode.VELOCITY, setpoint, args.load_nm, "sine"), blocks.append)
        busy1, cpu1, wall1 = cpu_busy(), time.process_time(), time.monotonic()
        child1 = child_cpu_s(rig)
        syncs = syncs_answered(rig) - syncs_before
        rig.disable()
        tally = rig.daq_tally
        log = rig.cycle_log.arrays()
    load_after = os.getloadavg()[0]

    rows = np.concatenate([b["t"] for b in blocks]) if blocks else np.empty(0)
    cycle_time = log["t_done_s"] - log["t_sync_s"]
    interval = np.diff(log["t_sync_s"])
    within = float(np.mean(cycle_time <= period))
    late = int(np.count_nonzero(interval > LATE_SYNC_PERIODS * period))
    missing_rows = cycles - len(rows)
    # Rows carry the plant's own time (from the child's plant log when the twins are in a child), and
    # the drive twin counts the SYNCs it stepped.
    broken = int(np.count_nonzero(np.abs(np.diff(rows) - period) > 1e-9))
    extra_syncs = syncs - len(rows)
    servo_lost = missing_rows + broken + abs(extra_syncs)
    seq_lost = sum(s.lost_samples for s in tally.streams)
    daq_lost = seq_lost + tally.index_gaps
    configured = float(daq_rate)
    sustained = (tally.samples - 1) / (tally.last_t_s - tally.first_t_s) if tally.samples > 1 else 0.0

    lines = [
        Line(
            "cycles run", f"{len(rows)} of {cycles}", f"{cycles}", len(rows) == cycles and not result.aborted
        ),
        Line("cycle time, ms: p50 / p90 / p99 / p99.9 / max", ms(cycle_time), f"≤ {period * 1e3:g}"),
        Line(
            "cycles completed within the period",
            f"{within:.4%}",
            f"≥ {WITHIN_PERIOD_TARGET:.1%}",
            within >= WITHIN_PERIOD_TARGET,
        ),
        Line("SYNC → answer latency, ms: p50 / p90 / p99 / p99.9 / max", ms(log["latency_s"])),
        Line("SYNC interval, ms: p50 / p90 / p99 / p99.9 / max", ms(interval)),
        Line(f"SYNCs later than {LATE_SYNC_PERIODS:g} periods", f"{late}"),
        Line(
            "samples lost, servo (missing rows + plant-time breaks + SYNC count mismatch)",
            f"{missing_rows} + {broken} + {abs(extra_syncs)} = {servo_lost}",
            "0",
            servo_lost == 0,
        ),
        Line(
            "samples lost, DAQ (by sequence number + by sample index)",
            f"{seq_lost} + {tally.index_gaps} = {daq_lost}",
            "0",
            daq_lost == 0,
        ),
        Line("rows with θ_l extrapolated past the newest DAQ sample", f"{tally.extrapolated}"),
        Line(
            "DAQ sustained rate, samples/s",
            f"{sustained:.1f} ({tally.samples} samples)",
            f"{configured:g} (± 0.1 %)",
            abs(sustained - configured) <= 1e-3 * configured,
        ),
    ]
    width = max(len(line.metric) for line in lines)
    mwidth = max(len(line.measured) for line in lines)
    header = f"{'metric':<{width}}  {'measured':<{mwidth}}  {'target':<12}  verdict"
    print(header)
    print("-" * len(header))
    for line in lines:
        print(f"{line.metric:<{width}}  {line.measured:<{mwidth}}  {line.target:<12}  {line.verdict}")

    wall = wall1 - wall0
    busy = ""
    if busy0 is not None and busy1 is not None and busy1[1] > busy0[1]:
        busy = f", all CPUs {100 * (busy1[0] - busy0[0]) / (busy1[1] - busy0[1]):.0f} % busy"
    print(
        f"\nmachine load: 1-min load average {load_before:.2f} before, {load_after:.2f} after{busy};"
        f" this process {100 * (cpu1 - cpu0) / wall:.0f} % of one CPU over {wall:.1f} s"
    )
    ran = max(len(rows), 1)
    per_cycle = f"CPU per cycle: this process (loop, bus and DAQ threads) {(cpu1 - cpu0) / ran * 1e6:.0f} µs"
    if child0 is not None and child1 is not None:
        per_cycle += f", the twins' child {(child1 - child0) / ran * 1e6:.0f} µs"
    print(per_cycle + f" (over {len(rows)} cycles)")
    if result.aborted:
        print(f"run aborted: {result.aborted}")


if __name__ == "__main__":
    main()
