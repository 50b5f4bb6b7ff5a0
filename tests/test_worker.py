"""The rig worker: its state table, submit/queue/busy, abort and quick stop, events, device faults.

Runs use the simulated rig in process. Where a run must still be moving when it is stopped, the rig is
paced to the wall clock (a speed sweep then lasts ~18 s), and the test waits on events, not on time.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from model.errors import UserInputError
from rig.config import RigConfig, load_rig_config
from rig.core.actions import plan_run
from rig.core.documents import JobStatus
from rig.core.events import EventKind, EventLog
from rig.core.worker import (
    SAMPLE_POINTS_PER_EVENT,
    TRANSITIONS,
    IllegalTransitionError,
    RigBusyError,
    RigWorker,
    WorkerState,
)
from rig.faults import DeviceFaultError
from rig.interface import Block, ControlMode
from rig.status import RunStatus
from rig.store.runs import RunStore
from sim_backend.inprocess import SimRig

WAIT_S = 120.0  # upper bound for a short simulated run on a loaded 2-core machine; never reached when well


def sim_config(pace: str = "virtual") -> RigConfig:
    return load_rig_config("sim").model_copy(update={"pace": pace})


@pytest.fixture
def store(tmp_path: Path) -> RunStore:
    return RunStore(tmp_path / "home")


def wait_for_event(events: EventLog, kind: EventKind, after: int = 0) -> int:
    """The id of the first event of `kind` newer than `after` (fails after WAIT_S)."""
    seen = after
    while events.wait(seen, WAIT_S):
        for event in events.since(seen):
            seen = event.id
            if event.kind == kind:
                return event.id
    raise AssertionError(f"no {kind} event within {WAIT_S} s")


def test_every_state_has_a_row_and_closed_is_final() -> None:
    assert set(TRANSITIONS) == set(WorkerState)
    assert TRANSITIONS[WorkerState.CLOSED] == frozenset()
    # The stop path exists from every live state: a quick stop is never refused.
    for state in (WorkerState.IDLE, WorkerState.RUNNING, WorkerState.FAULTED):
        assert WorkerState.STOPPING in TRANSITIONS[state]


def test_a_transition_outside_the_table_is_a_bug(store: RunStore) -> None:
    with RigWorker(sim_config(), store) as worker, pytest.raises(IllegalTransitionError):
        worker._set_state(WorkerState.FAULTED)  # idle → faulted is not in the table


def test_quick_stop_when_idle_is_accepted_and_returns_to_idle(store: RunStore) -> None:
    with RigWorker(sim_config(), store) as worker:
        worker.quick_stop()
        states = [e.data["state"] for e in worker.events.since(0) if e.kind == EventKind.STATE]
        alarms = [e.data["alarm"] for e in worker.events.since(0) if e.kind == EventKind.ALARM]
        assert states == ["stopping", "idle"] and alarms == ["quick_stop"]
        assert worker.state == WorkerState.IDLE
    assert worker.state == WorkerState.CLOSED
    worker.quick_stop()  # also after close: always safe


def test_a_run_job_completes_with_its_document_and_decimated_samples(store: RunStore) -> None:
    plan = plan_run("speed-sweep", {"speeds_rad_s": [2.0, 20.0]})
    with RigWorker(sim_config(), store) as worker:
        job = worker.wait(worker.submit(plan).id, WAIT_S)
        assert job.status == JobStatus.COMPLETE, job.error
        (run,) = job.result
        assert run.id == job.id == job.runs[0] and run.status == RunStatus.COMPLETE
        assert store.get(run.id)["samples"] == run.samples > 0
        events = worker.events.since(0, run_id=run.id, limit=10**6)
    samples = [e for e in events if e.kind == EventKind.SAMPLES]
    assert samples and all(len(e.data["t"]) <= SAMPLE_POINTS_PER_EVENT for e in samples)
    # Kept as small read-only copies (the log holds thousands on runs of hours), not views of the block.
    assert all(isinstance(e.data["t"], np.ndarray) and not e.data["t"].flags.writeable for e in samples)
    assert all(e.data["t"].base is None for e in samples)
    ids = [e.id for e in samples]
    assert ids == sorted(ids) and len(set(ids)) == len(ids)
    # Velocity segments carry the tracking error: set-point minus measured speed, row by row.
    velocity = [e for e in samples if e.data["mode"] == ControlMode.VELOCITY]
    assert velocity
    data = velocity[-1].data
    assert np.allclose(data["error"], np.subtract(data["setpoint"], data["omega_m"]))


def test_a_busy_rig_refuses_unless_asked_to_queue_then_plays_in_order(store: RunStore) -> None:
    plan = plan_run("speed-sweep", {"speeds_rad_s": [2.0]})
    with RigWorker(sim_config("realtime"), store) as worker:
        first = worker.submit(plan)
        with pytest.raises(RigBusyError):
            worker.submit(plan)
        second = worker.submit(plan_run("speed-sweep", {"speeds_rad_s": [3.0]}), queue=True)
        assert second.status == JobStatus.QUEUED
        worker.wait(second.id, WAIT_S)
        assert (first.status, second.status) == (JobStatus.COMPLETE, JobStatus.COMPLETE)
        assert first.ended is not None and second.started is not None and first.ended <= second.started


def test_abort_of_a_running_job_quick_stops_and_keeps_the_data(store: RunStore) -> None:
    with RigWorker(sim_config("realtime"), store) as worker:
        job = worker.submit(plan_run("speed-sweep"))
        wait_for_event(worker.events, EventKind.SAMPLES)
        worker.abort(job.id)
        worker.wait(job.id, WAIT_S)
        assert job.status == JobStatus.ABORTED
        entry = store.get(job.id)
        assert entry["status"] == RunStatus.ABORTED and entry["reason"] == "aborted: quick stop requested"
        assert entry["samples"] > 0 and len(store.read(job.id)) == entry["samples"]
        assert worker.state == WorkerState.IDLE


def test_abort_of_a_queued_job_removes_it_without_touching_the_rig(store: RunStore) -> None:
    with RigWorker(sim_config("realtime"), store) as worker:
        running = worker.submit(plan_run("speed-sweep", {"speeds_rad_s": [2.0]}))
        queued = worker.submit(plan_run("speed-sweep"), queue=True)
        worker.abort(queued.id)
        assert queued.status == JobStatus.ABORTED and queued.done.is_set()
        worker.wait(running.id, WAIT_S)
        assert running.status == JobStatus.COMPLETE
    assert [r["id"] for r in store.list_runs()] == [running.id]


def test_quick_stop_cancels_the_queue_and_stops_the_running_run(store: RunStore) -> None:
    with RigWorker(sim_config("realtime"), store) as worker:
        running = worker.submit(plan_run("speed-sweep"))
        queued = worker.submit(plan_run("pulse"), queue=True)
        wait_for_event(worker.events, EventKind.SAMPLES)
        worker.quick_stop()
        worker.wait(running.id, WAIT_S)
        assert (running.status, queued.status) == (JobStatus.ABORTED, JobStatus.ABORTED)
        assert store.get(running.id)["status"] == RunStatus.ABORTED


class FaultingRig(SimRig):
    """The simulated rig, whose drive reports a fault once `fault_after` cycles have run."""

    fault_after = 500

    def _run_cycles(self, mode: ControlMode, setpoint: np.ndarray, tau_ext: np.ndarray) -> tuple[Block, int]:
        if self.t_s * self.config.sample_rate_hz >= self.fault_after:
            raise DeviceFaultError("node 1: EMCY 0x7300 (sensor fault)")
        return super()._run_cycles(mode, setpoint, tau_ext)


def test_a_device_fault_mid_run_ends_it_aborted_with_its_data_not_as_bad_input(store: RunStore) -> None:
    config = sim_config()
    assert not issubclass(DeviceFaultError, UserInputError)
    with RigWorker(config, store, rig=FaultingRig(config)) as worker:
        job = worker.wait(worker.submit(plan_run("speed-sweep")).id, WAIT_S)
        assert job.status == JobStatus.ABORTED
        entry = store.get(job.id)
        assert entry["status"] == RunStatus.ABORTED
        assert entry["reason"] == "aborted: node 1: EMCY 0x7300 (sensor fault)"
        assert entry["samples"] >= 250  # every block before the fault was recorded (0.25 s blocks)
        assert worker.state == WorkerState.FAULTED


def test_a_device_fault_faults_the_worker_until_reset_and_cancels_the_queue(store: RunStore) -> None:
    config = sim_config()
    with RigWorker(config, store, rig=FaultingRig(config)) as worker:
        worker.rig.t_s = 10.0  # past the fault: the first cycle of the next run faults
        job = worker.submit(plan_run("speed-sweep"))
        queued = worker.submit(plan_run("pulse"), queue=True)
        worker.wait(job.id, WAIT_S)
        assert worker.state == WorkerState.FAULTED and queued.status == JobStatus.ABORTED
        with pytest.raises(RigBusyError, match="faulted"):
            worker.submit(plan_run("pulse"))
        worker.reset()
        assert worker.state == WorkerState.IDLE


def test_a_new_reader_of_a_run_starts_at_its_job_not_in_earlier_rig_wide_events(store: RunStore) -> None:
    with RigWorker(sim_config(), store) as worker:
        worker.quick_stop()  # an alarm and two state events that belong to no run
        before = worker.events.last_id
        job = worker.wait(worker.submit(plan_run("speed-sweep", {"speeds_rad_s": [2.0]})).id, WAIT_S)
        start = worker.events.start_of(job.id)
        first = next(e for e in worker.events.since(start, job.id) if e.kind != EventKind.JOB)
    assert start == before  # the job's own events (queued, then its state change to running) come next
    assert (first.kind, first.data["state"]) == (EventKind.STATE, "running")
    assert worker.events.start_of("queued-but-not-begun") == worker.events.last_id


def test_each_run_on_a_rig_kept_open_has_its_own_clock_from_zero(store: RunStore) -> None:
    plan = plan_run("speed-sweep", {"speeds_rad_s": [2.0]})
    with RigWorker(sim_config(), store) as worker:
        first = worker.wait(worker.submit(plan).id, WAIT_S)
        second = worker.wait(worker.submit(plan).id, WAIT_S)
    period_s = 1.0 / sim_config().sample_rate_hz
    for job in (first, second):
        t = store.read(job.id).t
        assert t[0] == pytest.approx(0.0, abs=period_s)  # the first sample is the run's t = 0
    # The rig's clock went on: the second run began where the first left it.
    # Half a period of slack: the origin is a sum of float periods, the bound a product.
    assert store.get(second.id)["meta"]["rig_time_origin_s"] >= (len(store.read(first.id)) - 0.5) * period_s


def test_a_run_that_fails_on_what_it_finds_still_tells_its_stream_how_it_ended(store: RunStore) -> None:
    """A sweep whose fastest pass does not fit the stroke ahead fails once it has begun (the program is
    planned from where the motor is): its run is sealed `aborted`, and its final `run` event follows the
    `running` one (without it a page following the run said `running` for ever: test_browser's second run)."""
    plan = plan_run("speed-sweep", {"speeds_rad_s": [500.0], "travel_fraction": 0.02})
    with RigWorker(sim_config(), store) as worker:
        job = worker.wait(worker.submit(plan).id, WAIT_S)
        events = worker.events.since(0, run_id=job.id, limit=10**6)
    runs = [e.data["status"] for e in events if e.kind == EventKind.RUN]
    assert job.status == JobStatus.FAILED and "stroke" in (job.error or ""), job.error
    assert runs == [RunStatus.RUNNING, RunStatus.ABORTED], runs
