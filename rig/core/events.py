"""The rig worker's event log: what happened, numbered, for listeners that read at their own pace.

The control loop only appends (a lock held for an append); readers — the command line's progress
bar, the service's event streams — take what is newer than the last id they saw, so a slow or gone
reader never holds the loop, and a client that reconnects resumes from its `Last-Event-ID`.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

DEFAULT_CAPACITY = 5_000
"""Events kept: ~10 minutes of a run's decimated samples (8 a second), for a client resuming with its
Last-Event-ID; a sample event holds seven small arrays (~2 kB), so the log stays under ~10 MB on runs of
hours."""


class EventKind(StrEnum):
    STATE = "state"  # the worker's state changed
    PROGRESS = "progress"  # a job's progress: fraction, phase, ETA
    SAMPLES = "samples"  # decimated samples of the run recording
    ALARM = "alarm"  # an abort, a trip, a device fault, a quick stop
    RUN = "run"  # a run started or ended (its document)
    JOB = "job"  # a job was queued, started or ended (its document)
    CLOSED = "closed"  # the service is going away (a signal): the last event of every stream, saying why


@dataclass(frozen=True)
class Event:
    id: int
    kind: EventKind
    data: dict[str, Any]
    run_id: str | None = None
    job_id: str | None = None
    time_s: float = field(default_factory=time.time)  # wall clock when published [s since the epoch]


class EventLog:
    """A bounded, numbered log of events; ids start at 1 and only grow."""

    def __init__(self, capacity: int = DEFAULT_CAPACITY) -> None:
        self._events: deque[Event] = deque(maxlen=capacity)
        self._next_id = 1
        self._changed = threading.Condition()

    def publish(
        self, kind: EventKind, data: dict[str, Any], run_id: str | None = None, job_id: str | None = None
    ) -> Event:
        with self._changed:
            event = Event(self._next_id, kind, data, run_id, job_id)
            self._next_id += 1
            self._events.append(event)
            self._changed.notify_all()
        return event

    @property
    def last_id(self) -> int:
        return self._next_id - 1

    def since(self, after_id: int, run_id: str | None = None, limit: int = 1000) -> list[Event]:
        """Events newer than `after_id` (those of `run_id` and the run-less ones, when given)."""
        with self._changed:
            if not self._events or after_id >= self._events[-1].id:
                return []
            first = self._events[0].id
            start = max(0, after_id + 1 - first)  # ids are consecutive inside the deque
            picked = []
            for index in range(start, len(self._events)):
                event = self._events[index]
                if run_id is None or event.run_id in (None, run_id):
                    picked.append(event)
                    if len(picked) >= limit:
                        break
            return picked

    def start_of(self, run_id: str) -> int:
        """Where a new reader of one run's events starts: just before the run's first event (or its job's,
        whose id a single run shares), or at the end of the log if there is none yet (queued) — never in
        the rig-wide events of earlier runs."""
        with self._changed:
            for event in self._events:
                if run_id in (event.run_id, event.job_id):
                    return event.id - 1
            return self._next_id - 1

    def wait(self, after_id: int, timeout_s: float) -> bool:
        """Block until an event newer than `after_id` exists (True) or the timeout passes (False)."""
        with self._changed:
            return self._changed.wait_for(lambda: self._next_id - 1 > after_id, timeout=timeout_s)
