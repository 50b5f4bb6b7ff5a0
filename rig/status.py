"""How a run stands: one enum for the store, the runner, the command line and the service."""

from enum import StrEnum


class RunStatus(StrEnum):
    """A run's status in the catalog and in every document that shows it."""

    QUEUED = "queued"  # accepted by the service, waiting for the rig
    RUNNING = "running"  # recording
    COMPLETE = "complete"  # every segment played, data sealed and analyzed
    ABORTED = "aborted"  # stopped by a safety trip, a device fault, a quick stop or an abort: data kept
    INTERRUPTED = "interrupted"  # the recording process died: data up to its last flush kept
    FAILED = "failed"  # never started, or its analysis raised: the reason says why

    @property
    def finished(self) -> bool:
        return self not in (RunStatus.QUEUED, RunStatus.RUNNING)
