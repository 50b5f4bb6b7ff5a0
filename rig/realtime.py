"""What a process that runs a 1 kHz control loop asks of the interpreter: a quiet heap.

CPython's cyclic garbage collector, in a full collection, walks every tracked object of the interpreter
with the GIL held. With numba, scipy and canopen's object dictionaries loaded that is ~10⁵ objects and
50-80 ms: long enough to stall the SYNC grid, time out the drive's answer (a `SyncTimeoutError`) and,
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
