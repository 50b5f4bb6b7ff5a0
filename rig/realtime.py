"""What a process that runs a 1 kHz control loop asks of the interpreter and the OS: a quiet heap, and
where the OS allows it, a real-time scheduling class.

CPython's cyclic garbage collector, in a full collection, walks every tracked object of the interpreter
with the GIL held. With numba, scipy and canopen's object dictionaries loaded that takes many periods of
the loop: long enough to stall the SYNC grid, time out the drive's answer (a `SyncTimeoutError`) and,
with the twins in the same process, let their heartbeat watch see a dead host. `quiet_heap()` collects
once and freezes what exists (`gc.freeze`), so that collections during the run walk only what the run
makes; on leaving, the frozen objects are handed back to the collector (`gc.unfreeze`).

It acts on the whole process, not on one rig: only the owner of the process enters it, around the
control loop it runs (the command line's `run`, a benchmark, a test through its fixture); never a
driver or a library. A service that hosts a rig among other work should run the loop in a process of
its own rather than freeze the heap under its requests. Entries nest and may come from any thread:
each one collects and freezes again (taking in what was built since, such as the rig just opened), and
the heap is unfrozen when the last one leaves.
"""

from __future__ import annotations

import gc
import os
import threading
from collections.abc import Iterator
from contextlib import contextmanager

_lock = threading.Lock()
_holders = [0]  # entries not yet left, process-wide


@contextmanager
def quiet_heap() -> Iterator[None]:
    """Collect, then keep the collector off every object that exists now, until the last entry leaves."""
    with _lock:
        _holders[0] += 1
        gc.collect()
        gc.freeze()
    try:
        yield
    finally:
        with _lock:
            _holders[0] -= 1
            if _holders[0] == 0:
                gc.unfreeze()


def freeze_built() -> None:
    """Inside `quiet_heap()`: collect, then keep the collector off what was built since it was entered.

    For a process that enters `quiet_heap()` first and builds what serves its loop inside it, such as
    the twins' process: a twin built from an EDS holds tens of thousands of tracked objects, and a full
    collection of them leaves SYNCs unanswered for tens of periods (figures: docs/BENCHMARKS.md, "Figures
    behind design choices in the code"). `quiet_heap()`'s last exit unfreezes them too.
    """
    with _lock:
        if not _holders[0]:
            raise RuntimeError("freeze_built() outside quiet_heap(): nothing would unfreeze what it froze")
        gc.collect()
        gc.freeze()


def realtime_scheduling(priority: int = 10, cpu: int | None = None) -> str:
    """Put the calling thread in the FIFO real-time class at `priority`, if the OS allows, and on `cpu`
    alone if given; say what it got.

    Call it first thing in the process that owns the loop, before it starts threads or children: on
    Linux they inherit both, so the bus's receive thread, the DAQ reader and a twins' child process run
    ahead of ordinary work too. A busy machine then no longer holds the loop back, where an ordinary
    thread's sleep may wake many periods late. One CPU for the loop and the twins spares each exchange
    the wake-up of another CPU, which shortens the drive's answer (figures: docs/BENCHMARKS.md, "Figures
    behind design choices in the code"). The kernel keeps 5 % of each second for ordinary work
    (sched_rt_runtime_us), so a thread that never blocks cannot freeze the machine. Never raises:
    without the permission (CAP_SYS_NICE or an rtprio limit) it says so and changes nothing.
    """
    said = []
    if cpu is not None and hasattr(os, "sched_setaffinity"):
        try:
            os.sched_setaffinity(0, {cpu})
            said.append(f"CPU {cpu}")
        except OSError as exc:
            said.append(f"any CPU (CPU {cpu} refused: {exc.strerror})")
    if not hasattr(os, "sched_setscheduler"):
        return ", ".join(["ordinary scheduling (no real-time class on this OS)", *said])
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except OSError as exc:
        return ", ".join([f"ordinary scheduling (SCHED_FIFO not allowed: {exc.strerror})", *said])
    return ", ".join([f"SCHED_FIFO priority {priority}", *said])
