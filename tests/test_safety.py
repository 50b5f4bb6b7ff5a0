"""The safety envelope and the stop paths of the rig interface, on the in-process simulated rig.

Each limit gets a segment built to breach it (and only it) after a stretch inside the envelope. The
envelope is checked on the measured values a cycle records, so the recorded samples are the evidence:
the run must end on the first sample beyond the limit, and every sample before it must be inside.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
import yaml

from model.errors import UserInputError
from rig.config import RIG_DIR, RigConfig
from rig.faults import DeviceFaultError
from rig.interface import Block, ControlMode, Rig, RigError, Segment, SegmentResult, open_rig
from sim_backend.inprocess import SimRig

RATE_HZ = 1000.0  # configs/rigs/sim.yaml
HOLD_CYCLES = 100  # a still stretch inside the envelope before each breach


def sim_config(**sections: Any) -> RigConfig:
    """configs/rigs/sim.yaml with some settings replaced, e.g. `limits={"travel_max_out_rad": 0.5}`."""
    data = yaml.safe_load((RIG_DIR / "sim.yaml").read_text())
    for key, value in sections.items():
        if isinstance(value, dict):
            data[key].update(value)
        else:
            data[key] = value
    return RigConfig.model_validate(data)


class Recorder:
    """A block sink that keeps every block it is given."""

    def __init__(self) -> None:
        self.blocks: list[Block] = []

    def __call__(self, block: Block) -> None:
        self.blocks.append({name: values.copy() for name, values in block.items()})

    def column(self, name: str) -> np.ndarray:
        return np.concatenate([b[name] for b in self.blocks]) if self.blocks else np.empty(0)


def hold_then(mode: ControlMode, then: np.ndarray, label: str, hold_value: float = 0.0) -> Segment:
    return Segment(mode, np.concatenate([np.full(HOLD_CYCLES, hold_value), then]), 0.0, label)


def play(rig: Rig, segment: Segment) -> tuple[SegmentResult, Recorder]:
    sink = Recorder()
    rig.enable()
    return rig.run_segment(segment, sink), sink


# Each case: the rig, the segment, and the per-sample measure that the limit bounds (from the recording).
Case = tuple[RigConfig, Segment, Callable[[Recorder], np.ndarray], float]


def current_case() -> Case:
    # 6 V on a stalled motor drives 6 V / R = 20 A (R = 0.299 Ω) through it: beyond the 12 A trip at once.
    config = sim_config()
    segment = hold_then(ControlMode.VOLTAGE, np.full(500, 6.0), "6 V step")
    return config, segment, lambda rec: np.abs(rec.column("i_a")), config.limits.current_a


def voltage_case() -> Case:
    # A valid rig file keeps the trip level at or above the bus voltage, so the simulated drive can never
    # reach it; the check is still there for a drive whose bus rises. Lower it below what accelerating to
    # 100 rad/s takes (R·10 A + K_b·ω ≈ 3 V), bypassing the file's validation.
    config = sim_config()
    limits = config.limits.model_copy(update={"voltage_v": 2.0})
    config = config.model_copy(update={"limits": limits})
    segment = hold_then(ControlMode.VELOCITY, np.full(1000, 100.0), "to 100 rad/s")
    return config, segment, lambda rec: np.abs(rec.column("u")), 2.0


def velocity_case() -> Case:
    # The seed plant's friction keeps it below ~330 rad/s on the 24 V bus, short of the 700 rad/s trip; a
    # rig with a 150 rad/s trip (its speed loop saturating at 100 rad/s) is passed by a voltage ramp to
    # 8 V, which the motor follows at ~30 rad/s per volt and a few amperes, near 5 V.
    config = sim_config(limits={"velocity_rad_s": 150.0}, control={"max_velocity_rad_s": 100.0})
    segment = hold_then(ControlMode.VOLTAGE, np.linspace(0.0, 8.0, 2000), "8 V ramp")
    return config, segment, lambda rec: np.abs(rec.column("omega_m")), config.limits.velocity_rad_s


def travel_case() -> Case:
    # 50 rad/s at the motor is 0.5 rad/s at the output: the 0.5 rad stroke ends after about a second.
    config = sim_config(limits={"travel_max_out_rad": 0.5})
    segment = hold_then(ControlMode.VELOCITY, np.full(3000, 50.0), "50 rad/s")
    return config, segment, lambda rec: 0.01 * rec.column("theta_m"), config.limits.travel_max_out_rad


def following_case() -> Case:
    # A position ramp at 1000 rad/s (motor) while the drive may only go 600 rad/s: the error grows by at
    # least 400 rad/s and passes 0.05 rad at the output (5 rad at the motor) within a few cycles.
    config = sim_config(limits={"following_error_out_rad": 0.05})
    ramp = np.arange(1, 201) * (1000.0 / RATE_HZ)  # 200 rad motor = 2 rad output, inside the travel
    segment = hold_then(ControlMode.POSITION, ramp, "1000 rad/s ramp")

    def error_out(rec: Recorder) -> np.ndarray:
        # What the drive compares: the set-point against the measured (recorded) motor angle.
        return 0.01 * np.abs(rec.column("setpoint") - rec.column("theta_m"))

    return config, segment, error_out, 0.05


CASES = {
    "current": current_case,
    "voltage": voltage_case,
    "velocity": velocity_case,
    "travel": travel_case,
    "following": following_case,
}


@pytest.mark.parametrize("which", list(CASES))
def test_breach_aborts_on_the_first_sample_beyond_the_limit(which: str) -> None:
    config, segment, measure, limit = CASES[which]()
    with open_rig(config) as rig:
        result, sink = play(rig, segment)
        health = rig.health()

    assert result.aborted is not None and result.aborted.startswith(f"aborted: {which} limit"), result.aborted
    # Quick-stopped: disabled, and the reason kept.
    assert not health.enabled and health.last_abort == result.aborted
    # Every sample up to and including the breach reached the sink, and nothing after it.
    values = measure(sink)
    assert len(values) == result.cycles == len(sink.column("t"))
    assert HOLD_CYCLES < result.cycles < segment.cycles
    assert np.all(np.diff(sink.column("t")) > 0)
    # Exact comparisons, no tolerance: the check reads the very values that were recorded.
    assert values[-1] > limit and np.all(values[:-1] <= limit), (values[-3:], limit)


def test_no_motion_after_an_abort_until_enabled_again() -> None:
    config, segment, _, _ = travel_case()
    with open_rig(config) as rig:
        play(rig, segment)
        sink = Recorder()
        after = rig.run_segment(Segment(ControlMode.VELOCITY, np.zeros(10)), sink)
        assert after == SegmentResult(0, "aborted: quick stop requested") and sink.blocks == []
        rig.enable()  # clears the quick stop; the travel is still breached, so holding still aborts again
        result = rig.run_segment(Segment(ControlMode.VELOCITY, np.zeros(10), label="hold"), Recorder())
        assert result.cycles == 1 and result.aborted and result.aborted.startswith("aborted: travel limit")


def test_a_segment_on_a_rig_never_enabled_is_a_bug_of_the_caller() -> None:
    with open_rig(sim_config()) as rig, pytest.raises(RuntimeError, match="not enabled") as info:
        rig.run_segment(Segment(ControlMode.VELOCITY, np.zeros(10)), Recorder())
    assert not isinstance(info.value, DeviceFaultError | UserInputError)


def test_a_quick_stop_between_two_segments_ends_the_next_one_before_it_moves() -> None:
    with open_rig(sim_config()) as rig:
        assert isinstance(rig, SimRig)
        rig.enable()
        rig.quick_stop()  # e.g. from another thread, while the caller was between segments
        state = rig.plant.x.copy()
        result = rig.run_segment(Segment(ControlMode.VELOCITY, np.full(10, 5.0), label="next"), Recorder())
        assert result == SegmentResult(0, "aborted: quick stop requested")
        np.testing.assert_array_equal(rig.plant.x, state)


# ---- quick stop --------------------------------------------------------------------------------------


def test_quick_stop_is_safe_before_enable_and_twice() -> None:
    with open_rig(sim_config()) as rig:
        rig.quick_stop()
        rig.quick_stop()
        assert not rig.health().enabled
        rig.enable()
        rig.quick_stop()
        rig.quick_stop()
        assert not rig.health().enabled
        rig.enable()  # and the rig can be used again afterwards
        result = rig.run_segment(Segment(ControlMode.VELOCITY, np.zeros(50), label="hold"), Recorder())
        assert result == SegmentResult(50)


def test_quick_stop_from_another_thread_ends_a_realtime_segment() -> None:
    stop_after_s = 0.5
    with open_rig(sim_config(pace="realtime")) as rig:
        segment = Segment(ControlMode.VELOCITY, np.zeros(int(10 * RATE_HZ)), label="hold 10 s")
        sink = Recorder()
        rig.enable()
        timer = threading.Timer(stop_after_s, rig.quick_stop)
        started = time.monotonic()
        timer.start()
        try:
            result = rig.run_segment(segment, sink)
        finally:
            timer.cancel()
        wall_s = time.monotonic() - started
        health = rig.health()

    assert result.aborted == "aborted: quick stop requested"
    assert not health.enabled and health.last_abort == result.aborted
    # The segment checks for a stop between chunks of 0.25 s: it ends within one chunk of the request
    # (plus 0.5 s for a loaded machine's scheduling), far short of its 10 s.
    assert stop_after_s <= wall_s < stop_after_s + 0.25 + 0.5
    assert result.cycles == len(sink.column("t")) < segment.cycles


# ---- set-points the rig refuses -----------------------------------------------------------------------


@pytest.mark.parametrize(
    ("mode", "setpoint", "says"),
    [
        (ControlMode.VOLTAGE, 24.5, "voltage set-point 24.5 V beyond the rig's 24 V"),
        (ControlMode.CURRENT, -10.5, "current set-point 10.5 A beyond the rig's 10 A"),
        (ControlMode.VELOCITY, 650.0, "velocity set-point 650 rad/s beyond the rig's 600 rad/s"),
        (ControlMode.POSITION, 350.0, "outside the travel"),  # 3.5 rad at the output; travel ends at 3
        (ControlMode.VELOCITY, float("nan"), "non-empty finite"),
    ],
)
def test_set_point_beyond_saturation_is_refused_before_anything_moves(
    mode: ControlMode, setpoint: float, says: str
) -> None:
    with open_rig(sim_config()) as rig:
        assert isinstance(rig, SimRig)
        rig.enable()
        state = rig.plant.x.copy()
        sink = Recorder()
        # The offending value comes late in the segment: the whole segment is checked before it starts.
        values = np.concatenate([np.zeros(500), [setpoint]])
        with pytest.raises(RigError, match=says):
            rig.run_segment(Segment(mode, values, label="bad"), sink)
        assert sink.blocks == [] and rig.t_s == 0.0
        np.testing.assert_array_equal(rig.plant.x, state)
        assert rig.health().enabled and rig.health().last_abort is None


def test_a_trip_while_settling_ends_the_run_aborted_with_its_reason(tmp_path: Any) -> None:
    from rig.runner import run_experiment
    from rig.store.runs import RunStore

    # The rig starts at output angle 0, outside a travel that begins at 0.1 rad: the settle step trips.
    config = sim_config(limits={"travel_min_out_rad": 0.1})
    outcome = run_experiment("speed-sweep", config, {}, RunStore(tmp_path))
    assert outcome.status == "aborted"
    assert outcome.reason is not None and outcome.reason.startswith("aborted: travel limit")
    assert RunStore(tmp_path).get(outcome.run_id)["status"] == "aborted"


def test_a_program_beyond_the_rig_is_refused_before_anything_moves(tmp_path: Any) -> None:
    from rig.runner import run_experiment
    from rig.store.runs import RunStore

    # A speed the drive cannot reach: refused for the whole program, not when its segment comes up.
    with pytest.raises(UserInputError, match="beyond the rig's"):
        run_experiment("speed-sweep", sim_config(), {"speeds_rad_s": [1.0, 650.0]}, RunStore(tmp_path))
    (entry,) = RunStore(tmp_path).list_runs()
    assert entry["samples"] == round(0.2 * 1000), "only the settle step ran"
