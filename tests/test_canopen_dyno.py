"""A dynamometer bench on one CAN bus (issue 26 items 1-3): the axis drive and a load drive in one rig
file, both driven by the real CiA 402 driver, one SYNC for both, against an axis twin and a load twin.

`configs/rigs/virtual-can-dyno.yaml` puts both twins in the child process; the in-process tests here use
python-can's `virtual` interface on a channel of their own (never udp_multicast).
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Iterator
from typing import Any

import canopen
import numpy as np
import pytest

from drivers.can_bus import open_bus
from drivers.canopen_config import CanopenConfigError, CanopenSettings
from drivers.cia402 import EMCY_OVERCURRENT, State, decode_statusword
from drivers.daq_protocol import ANALOG_SAMPLE_DTYPE, DataFrame, cobs_decode, decode_frame, encode_data_frame
from drivers.hardware_rig import CycleLog, worst_bus_load
from hdrig_testing.can_bus import bus_settings_for_test
from model.errors import UserInputError
from model.params import HarmonicDriveModel, load_model
from rig.config import RIG_DIR, RigConfig, load_rig_config
from rig.interface import ControlMode, RigFaultError, Segment
from rig.runner import run_experiment
from rig.store.runs import RunStore
from sim_backend.cia402_twin import AMBIENT_C, TWIN_EDS, Cia402Twin, LoadTwin
from sim_backend.inprocess import TORQUE_COLUMNS as TRANSDUCERS
from sim_backend.inprocess import SimRig
from sim_backend.simulated_drive import TRUTH_COLUMNS
from sim_backend.virtual_bus import VirtualCanRig

pytestmark = pytest.mark.usefixtures("quiet_heap")

DYNO = RIG_DIR / "virtual-can-dyno.yaml"
LOADS_NM = [0.0, 5.0, 10.0]
SPEEDS_RAD_S = [5.0, 20.0]
LOAD_FRICTION_C_TS = 2e-3  # effect load_dependent_friction: motor friction + c_Ts·|T_s|
SLOPE_REL_TOL = 0.10  # issue 26: the friction-against-load slope within 10 % of the sim run's


def in_process(config: RigConfig, **canopen: Any) -> RigConfig:
    """The rig file with its twins in this process on a `virtual` channel (the rig adds a suffix)."""
    extra = dict(config.extra)
    extra["twins"] = "in-process"
    extra["canopen"] = {**extra["canopen"], "interface": "virtual", "channel": "hdrig-dyno-test", **canopen}
    return RigConfig.model_validate({**config.model_dump(), **extra})


@pytest.fixture
def dyno() -> Iterator[VirtualCanRig]:
    rig = VirtualCanRig(in_process(load_rig_config(DYNO)))
    rig.plant_log = []
    try:
        yield rig
    finally:
        rig.close()


def test_the_rig_file_declares_an_axis_and_a_load_drive() -> None:
    settings = CanopenSettings.from_rig_config(load_rig_config(DYNO))
    load = settings.load
    assert load is not None and settings.load_entry is not None
    assert (settings.role_settings("axis").node_id, load.node_id) == (1, 2)
    assert load.scaling.torque_constant_nm_per_a != settings.scaling.torque_constant_nm_per_a
    assert load.channel == settings.channel and load.bitrate == settings.bitrate  # one bus


def test_a_load_drive_without_its_trips_is_refused_in_one_line() -> None:
    data = load_rig_config(DYNO).extra["canopen"]
    entry = {k: v for k, v in data["drives"][0].items() if k != "current_trip_a"}
    with pytest.raises(CanopenConfigError, match="needs current_trip_a") as info:
        CanopenSettings.from_rig_config(
            RigConfig.model_validate(
                {**load_rig_config(DYNO).model_dump(), "canopen": {**data, "drives": [entry]}}
            )
        )
    assert "\n" not in str(info.value)


def test_two_drives_on_one_node_id_are_refused() -> None:
    data = load_rig_config(DYNO).extra["canopen"]
    entry = {**data["drives"][0], "node_id": data["node_id"]}
    with pytest.raises(CanopenConfigError, match="node ids"):
        CanopenSettings.from_rig_config(
            RigConfig.model_validate(
                {**load_rig_config(DYNO).model_dump(), "canopen": {**data, "drives": [entry]}}
            )
        )


def test_the_bus_load_of_both_drives_is_computed_and_logged(
    dyno: VirtualCanRig, caplog: pytest.LogCaptureFixture
) -> None:
    assert dyno.bus_load is not None
    one = worst_bus_load([dyno.servo], dyno.period_s)
    both = dyno.bus_load
    # One SYNC for both: the second drive adds its RPDO and TPDOs, not another SYNC.
    assert one.bits_per_cycle < both.bits_per_cycle < 2 * one.bits_per_cycle
    logging.getLogger(__name__).info("two drives at 1 kHz, 1 Mbit/s: %s", both)
    print(f"two drives: {both}")
    assert 0.5 < both.share < 0.9


def test_a_bus_too_slow_for_both_drives_is_refused_in_one_line() -> None:
    config = in_process(load_rig_config(DYNO), bitrate=500_000)
    with pytest.raises(UserInputError, match="bus_load_max") as info:
        VirtualCanRig(config)
    assert "\n" not in str(info.value)


def test_the_load_drive_puts_the_segments_load_torque_on_the_output(dyno: VirtualCanRig) -> None:
    dyno.enable()
    tau = np.concatenate([np.zeros(50), np.full(150, 5.0)])
    result = dyno.run_segment(
        Segment(ControlMode.VELOCITY, np.full(200, 10.0), tau, "loaded"), lambda b: None
    )
    assert result.aborted is None
    assert dyno.plant_log is not None
    applied = np.array([sample["tau_ext"] for sample in dyno.plant_log])
    # The torque staged before a cycle's SYNC acts in that very cycle.
    np.testing.assert_allclose(applied[-200:], tau, atol=0.011)  # 1 ‰ of the load drive's 10 N·m
    load = dyno.load_servo
    assert load is not None and load.last_feedback is not None
    assert load.last_feedback.torque_nm == pytest.approx(-5.0, abs=0.011)
    dyno.disable()


def test_disable_unloads_the_load_drive_before_the_axis(dyno: VirtualCanRig) -> None:
    dyno.enable()
    dyno.run_segment(
        Segment(ControlMode.VELOCITY, np.full(50, 5.0), np.full(50, 3.0), "loaded"), lambda b: None
    )
    load_twin, twin = dyno.load_twin, dyno.twin
    assert load_twin is not None and twin is not None
    seen: list[tuple[State, State, float]] = []
    twin.on_sample = lambda sample: seen.append((twin.state, load_twin.state, load_twin.torque_nm))
    dyno.disable()
    twin.on_sample = None
    axis_off = next(i for i, (axis, _, _) in enumerate(seen) if axis != State.OPERATION_ENABLED)
    load_off = next(i for i, (_, load, _) in enumerate(seen) if load != State.OPERATION_ENABLED)
    assert load_off < axis_off
    assert all(torque == 0.0 for _, _, torque in seen[load_off:])


def test_a_fault_on_the_load_drive_stops_both_drives_within_one_cycle(dyno: VirtualCanRig) -> None:
    dyno.enable()
    load_twin, twin = dyno.load_twin, dyno.twin
    assert load_twin is not None and twin is not None
    n = 400
    states: list[tuple[int, State, State]] = []
    fault_at = 100

    def watch(sample: dict[str, float]) -> None:
        if twin.sync_count == fault_at:
            load_twin.inject_fault(EMCY_OVERCURRENT)  # in the SYNC's own handling: its answer shows it
        states.append((twin.sync_count, twin.state, load_twin.state))

    start = twin.sync_count
    fault_at = start + 100
    twin.on_sample = watch
    with pytest.raises(RigFaultError, match="load drive") as info:
        dyno.run_segment(
            Segment(ControlMode.VELOCITY, np.full(n, 20.0), np.full(n, 2.0), "fault"), lambda b: None
        )
    twin.on_sample = None
    assert "EMCY 0x2310" in str(info.value) or "FAULT" in str(info.value)
    after = [(count, axis) for count, axis, _load in states if count > fault_at]
    # The SYNC after the one whose answer showed the fault carries the quick stop to both drives.
    assert after and after[0][1] != State.OPERATION_ENABLED, after[:3]
    assert load_twin.state == State.FAULT and load_twin.torque_nm == 0.0


@pytest.fixture(scope="module")
def load_runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """`load-variation` through the real drivers on virtual-can-dyno (twins in the child process) and on
    the simulated dynamometer sim-dyno (its load drive modelled), same model, loads and speeds."""
    params = {"loads_nm": LOADS_NM, "speeds_rad_s": SPEEDS_RAD_S}
    # The seed's friction does not follow the load (its slope is noise about 0): a friction that grows
    # with the transmitted torque gives the slope to compare.
    model = load_model("seed").to_dict()
    model["load_dependent_friction"] = {"c_Ts": LOAD_FRICTION_C_TS}
    model_file = tmp_path_factory.mktemp("model") / "seed-load-friction.json"
    model_file.write_text(json.dumps(model))
    outcomes = {}
    for name in ("dyno", "sim-dyno"):
        config = load_rig_config(DYNO if name == "dyno" else name)
        config = config.model_copy(update={"model": str(model_file)})
        outcome = run_experiment("load-variation", config, params, RunStore(tmp_path_factory.mktemp(name)))
        assert outcome.status == "complete", outcome.reason
        outcomes[name] = outcome
    return outcomes


def test_load_variation_runs_through_both_drives_and_matches_the_sim_dyno_slope(
    load_runs: dict[str, Any],
) -> None:
    dyno = load_runs["dyno"].metrics["friction_per_load_nm_per_nm"]
    sim = load_runs["sim-dyno"].metrics["friction_per_load_nm_per_nm"]
    apart = abs(dyno / sim - 1)
    print(f"friction per load: virtual-can-dyno {dyno:.5g}, sim-dyno {sim:.5g} ({apart:.2%} apart)")
    assert dyno == pytest.approx(sim, rel=SLOPE_REL_TOL)


# --- the DAQ's analog inputs: torque transducers and temperature probes (issue 26 item 2) ----------------


def test_an_analog_frame_round_trips_through_the_protocol() -> None:
    samples = np.zeros(3, ANALOG_SAMPLE_DTYPE)
    samples["encoder"] = [1, 2, 3]
    samples["adc"] = [[10, -20, 30, 2**31 - 1], [0, 0, 0, 0], [-(2**31), 5, 6, 7]]
    frame = decode_frame(cobs_decode(encode_data_frame(7, 1000, 500, samples)[:-1]))
    assert isinstance(frame, DataFrame) and frame.samples.dtype == ANALOG_SAMPLE_DTYPE
    np.testing.assert_array_equal(frame.samples["adc"], samples["adc"])


@pytest.mark.parametrize(
    ("channels", "match"),
    [
        ({"torque": {"adc": 0, "gain": 1.0, "min": -1.0, "max": 1.0}}, "not among"),
        (
            {
                "tau_in": {"adc": 1, "gain": 1.0, "min": -1.0, "max": 1.0},
                "tau_out": {"adc": 1, "gain": 1.0, "min": -1.0, "max": 1.0},
            },
            "share an ADC input",
        ),
        ({"tau_in": {"adc": 0, "gain": 0.0, "min": -1.0, "max": 1.0}}, "gain"),
    ],
)
def test_a_bad_analog_channel_is_refused_in_one_line(channels: dict[str, Any], match: str) -> None:
    config = load_rig_config(DYNO)
    daq = {**config.extra["daq"], "channels": channels}
    with pytest.raises(UserInputError, match=match) as info:
        VirtualCanRig(RigConfig.model_validate({**config.model_dump(), "daq": daq}))
    assert "\n" not in str(info.value)


def loaded_blocks(rig: VirtualCanRig, load_nm: float) -> dict[str, np.ndarray]:
    blocks: list[dict[str, np.ndarray]] = []
    rig.cycle_log = CycleLog()
    rig.enable()
    n = 600
    result = rig.run_segment(
        Segment(ControlMode.VELOCITY, np.full(n, 10.0), load_nm, "loaded"), blocks.append
    )
    assert result.aborted is None
    rig.disable()
    return {name: np.concatenate([b[name] for b in blocks]) for name in blocks[0]}


def mean_tolerance(sigma: float, rows: int) -> float:
    """4 σ of the mean of `rows` rows whose noise is drawn once a SYNC: a row interpolates the DAQ's
    samples around its SYNC, which may carry the readings of two SYNCs, so neighbours share draws
    (rows / 2 independent ones at worst)."""
    return 4 * sigma / math.sqrt(rows / 2)


def test_the_transducers_and_probes_are_recorded_from_the_plant(dyno: VirtualCanRig) -> None:
    assert dyno.extra_columns == ("tau_in", "tau_out", "temp_gear", "temp_motor")
    run = loaded_blocks(dyno, 5.0)
    assert dyno.twin is not None and dyno.cycle_log is not None
    held = slice(len(run["t"]) // 2, None)
    rows = len(run["t"]) - len(run["t"]) // 2
    t_sync = dyno.cycle_log.arrays()["t_sync_s"][-len(run["t"]) :]
    recorded = np.array(dyno.twin.measured.truths(t_sync[held].tolist()))
    # Means over the steady half: the DAQ's samples are aligned to the SYNCs within a cycle.
    assert np.mean(run["tau_out"][held]) == pytest.approx(np.mean(recorded[:, 1]), rel=0.01)
    sensors = dyno.config.sensors
    torque_tol = mean_tolerance(sensors.torque_noise_nm, rows)
    # τ_out: the output shaft beyond the gear's inertia, i.e. the load drive's 5 N·m (within 1 ‰ of its
    # rated torque, 0.01 N·m) in steady motion.
    assert np.mean(run["tau_out"][held]) == pytest.approx(5.0, abs=0.01 + torque_tol)
    # τ_in = r·T_s + F_m = K_m·i_a − J_m·dω_m/dt, whose mean is K_m·i_a's at a steady speed.
    k_m = dyno.model.motor.K_m
    assert np.mean(run["tau_in"][held]) == pytest.approx(k_m * np.mean(run["i_a"][held]), abs=torque_tol)
    temp_tol = mean_tolerance(sensors.temperature_noise_c, rows)
    for probe in ("temp_gear", "temp_motor"):  # the seed has no thermal section: the room's, with noise
        assert np.mean(run[probe][held]) == pytest.approx(AMBIENT_C, abs=temp_tol)
        assert 0.5 * sensors.temperature_noise_c < np.std(run[probe][held]) < sensors.temperature_noise_c
    assert dyno.daq_tally.out_of_range == 0


def test_the_twins_transducer_readings_are_the_simulated_benchs_definitions(dyno: VirtualCanRig) -> None:
    """The twin computes a SYNC's readings with plain floats: the same numbers as TorqueTransducers.truth
    (noise off), for rows of any values."""
    twin = dyno.twin
    assert twin is not None and twin.drive.truth is not None
    twin._transducers.noise_nm = 0.0
    rows = np.random.default_rng(7).normal(size=(20, len(TRUTH_COLUMNS))) * 10
    expected = twin._transducers.truth(rows)
    for k, row in enumerate(rows):
        twin.drive.truth.append(row[None, :])
        tau_in, tau_out, _, _ = twin._truths()
        assert (tau_in, tau_out) == pytest.approx((expected["tau_in"][k], expected["tau_out"][k]), rel=1e-12)


def test_the_twins_transducers_read_as_the_simulated_benchs_for_the_same_motion(
    dyno: VirtualCanRig,
) -> None:
    """The same velocity segment under the same load on the twins (through the real drivers and the
    DAQ) and on the simulated rig with the same plant and sensors: τ_in and τ_out (docs/CATALOG_TESTS.md's
    definitions) agree in the mean over whole motor turns within their noise."""
    speed_rad_s, load_nm, n = 4 * math.pi, 5.0, 2000  # two motor turns a second; the last second averaged
    segment = Segment(ControlMode.VELOCITY, np.full(n, speed_rad_s), load_nm, "loaded")
    blocks: list[dict[str, np.ndarray]] = []
    dyno.enable()
    assert dyno.run_segment(segment, blocks.append).aborted is None
    dyno.disable()
    twin = {name: np.concatenate([b[name] for b in blocks])[n // 2 :] for name in TRANSDUCERS}
    data = {k: v for k, v in dyno.config.model_dump().items() if k not in ("canopen", "daq", "twins")}
    data["backend"] = "sim"
    data["sensors"] = {**data["sensors"], "torque_transducers": True}
    sim_rig = SimRig(RigConfig.model_validate(data))
    sim_blocks: list[dict[str, np.ndarray]] = []
    sim_rig.enable()
    assert sim_rig.run_segment(segment, sim_blocks.append).aborted is None
    sim_rig.close()
    sim = {name: np.concatenate([b[name] for b in sim_blocks])[n // 2 :] for name in TRANSDUCERS}
    # Each mean has noise of at most 4 σ/√(rows/2) (the sim's rows draw afresh each: less); the difference
    # of two, √2 times that.
    tol = math.sqrt(2) * mean_tolerance(dyno.config.sensors.torque_noise_nm, n // 2)
    for name in TRANSDUCERS:
        print(f"{name}: twin {np.mean(twin[name]):.5f}, sim {np.mean(sim[name]):.5f} N·m (tol {tol:.5f})")
        assert np.mean(twin[name]) == pytest.approx(np.mean(sim[name]), abs=tol), name


def test_a_reading_outside_its_sensors_range_is_recorded_nan_and_counted() -> None:
    config = in_process(load_rig_config(DYNO))
    daq = dict(config.extra["daq"])
    daq["channels"] = {**daq["channels"], "tau_out": {**daq["channels"]["tau_out"], "max": 1.0}}
    rig = VirtualCanRig(RigConfig.model_validate({**config.model_dump(), "daq": daq}))
    try:
        run = loaded_blocks(rig, 5.0)
    finally:
        rig.close()
    assert np.isnan(run["tau_out"][-100:]).all()
    assert rig.daq_tally.out_of_range >= 100


# --- canopen's own master against both twins on one bus ----------------------------------------------


def test_canopens_own_master_drives_the_load_twin_beside_the_axis_twin(
    request: pytest.FixtureRequest, seed: HarmonicDriveModel
) -> None:
    """Software nobody here wrote as the master: canopen's BaseNode402 puts the load twin (node 2) in
    CST with its own SYNC producer, beside the axis twin (node 1) on the same bus."""
    bus = bus_settings_for_test(request.node.name)
    twin = Cia402Twin(open_bus(bus), 1, seed, load_rig_config(RIG_DIR / "sim.yaml"))
    load = LoadTwin(twin, 2, torque_constant_nm_per_a=2.0)
    network = canopen.Network()
    network.NOTIFIER_CYCLE = 0.05
    network.connect(interface=bus.interface, channel=bus.channel)
    axis_node = canopen.RemoteNode(1, str(TWIN_EDS))
    load_node = canopen.BaseNode402(2, str(TWIN_EDS))
    for node in (axis_node, load_node):
        network.add_node(node)
        node.sdo.RESPONSE_TIMEOUT = 2.0  # it reads its PDO layout over SDO: give it the time it needs
    permille = 300
    try:
        load_node.nmt.state = "PRE-OPERATIONAL"
        load_node.nmt.wait_for_heartbeat(timeout=1.0)
        load_node.setup_402_state_machine()
        load_node.nmt.state = "OPERATIONAL"
        network.sync.start(0.01)  # once: SyncProducer.start() twice would leak a thread
        try:
            load_node.state = "OPERATION ENABLED"
            load_node.op_mode = "CYCLIC SYNCHRONOUS TORQUE"
            load_node.sdo[0x6071].raw = permille
            deadline = time.monotonic() + 5.0  # 500 SYNCs at 10 ms: the torque is applied at the next one
            while twin.tau_ext_nm == 0.0 and time.monotonic() < deadline:
                time.sleep(0.01)
            axis_status = axis_node.sdo[0x6041].raw
            state, mode = load_node.state, load_node.op_mode
        finally:
            network.sync.stop()
    finally:
        network.disconnect()
        load.close()
        twin.close()
    assert (state, mode) == ("OPERATION ENABLED", "CYCLIC SYNCHRONOUS TORQUE")
    assert twin.tau_ext_nm == pytest.approx(-permille / 1000 * load.rated_torque_nm)
    assert decode_statusword(axis_status) == State.SWITCH_ON_DISABLED  # the axis answered beside it


def test_a_trip_of_the_load_drive_quick_stops_both() -> None:
    """The load drive's own envelope, checked by the host every cycle: its shaft (the output) turning
    at 0.05 rad/s (the axis at 5 rad/s through 100:1), above a 0.04 rad/s trip."""
    config = in_process(load_rig_config(DYNO))
    data = config.extra["canopen"]
    entry = {**data["drives"][0], "velocity_limit_rad_s": 0.03, "velocity_trip_rad_s": 0.04}
    rig = VirtualCanRig(
        RigConfig.model_validate({**config.model_dump(), "canopen": {**data, "drives": [entry]}})
    )
    try:
        rig.enable()
        tau = np.concatenate([np.zeros(50), np.full(150, 5.0)])
        with pytest.raises(RigFaultError, match="velocity_trip_rad_s") as info:
            rig.run_segment(Segment(ControlMode.VELOCITY, np.full(200, 5.0), tau, "trip"), lambda b: None)
        assert "\n" not in str(info.value)
        assert rig.twin is not None and rig.load_twin is not None
        assert rig.twin.state != State.OPERATION_ENABLED
        assert rig.load_twin.state != State.OPERATION_ENABLED and rig.load_twin.torque_nm == 0.0
    finally:
        rig.close()
