"""The hardware backend end to end: the real servo and DAQ drivers against their twins (`virtual-can`).

`configs/rigs/virtual-can.yaml` runs the seed model in the CiA 402 drive twin on a python-can
`virtual` channel of its own, measured by the DAQ twin on a pty; `drivers.hardware_rig` composes the
servo driver and the DAQ driver behind the rig interface. The speed sweep goes through the command
line as a user runs it; the stream checks run in this process, paced to the wall clock.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest
import yaml

from drivers.can_bus import open_bus
from drivers.canopen_config import CanopenSettings
from drivers.hardware_rig import RAW_CAN_LOG, BenchConstants, CycleLog, HardwareConfigError
from hdrig_testing.can_bus import TWIN_SYNC_TIMEOUT_S, bus_settings_for_test
from model.errors import UserInputError
from model.params import HarmonicDriveModel
from rig.config import RIG_DIR, RigConfig, load_rig_config
from rig.faults import DeviceFaultError
from rig.interface import ControlMode, Rig, RigError, RigFaultError, Segment, open_rig
from rig.runner import run_experiment
from rig.store.runs import RunStore
from sim_backend.cia402_twin import Cia402Twin
from sim_backend.virtual_bus import VirtualCanRig

REPO_ROOT = Path(__file__).resolve().parent.parent
VIRTUAL_CAN = RIG_DIR / "virtual-can.yaml"
NODE = 1  # virtual-can.yaml
SYNC, RPDO, TPDO1, TPDO2 = 0x080, 0x200 + NODE, 0x180 + NODE, 0x280 + NODE
PERIOD_S = 1e-3
R = 0.01  # the seed's gear ratio
# A load torque at the output the drive's 10 A cannot hold (10 A · K_m / r ≈ 30 N·m): it drives the arm
# backwards into the end of its travel (-0.5 rad at the output) within half a second.
RUNAWAY_LOAD = "tau_ext_nm=50"
# The two rigs run the same plant, loops and noise seed; what differs is how the drive's answers reach
# the host: current actual in ‰ of the twin's 5 A rated current (5 mA steps, 0.15 mN·m at K_m) and the
# few cycles of boot and enable that shift the noise sequence. Averaged over ≥ 400 samples of 5 mA
# noise these move a window's mean torque by a few µN·m (measured: ≤ 3 µN·m); the bound is one step.
TORQUE_TOLERANCE_NM = 1.5e-4
SPEED_TOLERANCE_RAD_S = 1e-3

# The rigs here run the drive and DAQ twins in this process, some paced to the 1 ms grid.
pytestmark = pytest.mark.usefixtures("quiet_heap")


def hdrig(home: Path, *args: str) -> subprocess.CompletedProcess[str]:
    """`hdrig ARGS` (as `python -m rig`) with its store in `home`."""
    return subprocess.run(
        [sys.executable, "-m", "rig", *args],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=REPO_ROOT,
        env={**os.environ, "HDRIG_HOME": str(home)},
    )


def no_new_threads(before: set[threading.Thread], wait_s: float = 1.0) -> set[threading.Thread]:
    """Threads started since `before` and still alive after up to `wait_s`."""
    deadline = time.monotonic() + wait_s
    while (left := set(threading.enumerate()) - before) and time.monotonic() < deadline:
        time.sleep(0.01)
    return left


def friction_table(run_dir: Path) -> dict[str, np.ndarray]:
    data = np.genfromtxt(run_dir / "artifacts" / "friction_vs_velocity.csv", delimiter=",", names=True)
    return {name: np.atleast_1d(data[name]) for name in data.dtype.names or ()}


# --- the speed sweep through the command line ------------------------------------------------------


@pytest.fixture(scope="module")
def sweep(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """`hdrig run speed-sweep --rig configs/rigs/virtual-can.yaml --json`, defaults, a store of its own."""
    home = tmp_path_factory.mktemp("virtual-can-home")
    result = hdrig(home, "run", "speed-sweep", "--rig", str(VIRTUAL_CAN), "--json", "-q")
    assert result.returncode == 0, result.stderr
    outcome: dict[str, Any] = json.loads(result.stdout)
    outcome["home"] = home
    return outcome


@pytest.fixture(scope="module")
def sim_sweep(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The same experiment on the in-process `sim` rig; its run folder."""
    outcome = run_experiment(
        "speed-sweep", load_rig_config("sim"), {}, RunStore(tmp_path_factory.mktemp("sim"))
    )
    assert outcome.status == "complete", outcome.reason
    assert outcome.run_dir is not None
    return outcome.run_dir


def test_speed_sweep_on_virtual_can_completes_as_a_simulated_run(sweep: dict[str, Any]) -> None:
    entry = RunStore(sweep["home"]).read(sweep["id"])
    assert sweep["status"] == "complete"
    assert entry.meta["source"] == "sim" and entry.meta["rig"] == "virtual-can"


def test_its_friction_curve_matches_the_sim_rig(sweep: dict[str, Any], sim_sweep: Path) -> None:
    twins, sim = friction_table(Path(sweep["run_dir"])), friction_table(sim_sweep)
    np.testing.assert_array_equal(twins["omega_set"], sim["omega_set"])
    np.testing.assert_allclose(twins["omega_m"], sim["omega_m"], rtol=0, atol=SPEED_TOLERANCE_RAD_S)
    np.testing.assert_allclose(twins["torque_nm"], sim["torque_nm"], rtol=0, atol=TORQUE_TOLERANCE_NM)


def test_the_raw_can_log_beside_the_run_has_one_exchange_per_sample(sweep: dict[str, Any]) -> None:
    run_dir = Path(sweep["run_dir"])
    samples = len(RunStore(sweep["home"]).read(sweep["id"]))
    frames = [m.arbitration_id for m in can.LogReader(run_dir / RAW_CAN_LOG)]
    counts = {cob_id: frames.count(cob_id) for cob_id in (SYNC, RPDO, TPDO1, TPDO2)}
    # Every recorded sample is one RPDO + SYNC answered by both TPDOs; disabling at the end adds a few.
    assert len(set(counts.values())) == 1, counts
    assert samples <= counts[SYNC] <= samples + 100


def test_a_breach_through_the_twins_aborts_the_run_with_its_reason(tmp_path: Path) -> None:
    result = hdrig(tmp_path, "run", "speed-sweep", "--rig", str(VIRTUAL_CAN), "--set", RUNAWAY_LOAD, "--json")
    assert result.stdout, result.stderr
    outcome = json.loads(result.stdout)
    assert result.returncode == 3, result.stderr
    assert outcome["status"] == "aborted"
    assert outcome["reason"].startswith("aborted: travel limit: output angle -0.5")


# --- the streams, paced to the wall clock ---------------------------------------------------------


@dataclass
class PacedRun:
    rows: dict[str, np.ndarray]
    cycles: dict[str, np.ndarray]  # CycleLog
    plant: dict[str, np.ndarray]  # the drive twin's own samples: the truth
    clock_uncertainty_s: float  # the DAQ clock estimates' largest ± (half the quickest round trip)


PACED_SPEED_RAD_S = 20.0  # slow enough that a cycle's motion is small beside the kinematic error


@pytest.fixture(scope="module")
def paced(quiet_heap: None) -> PacedRun:
    """1.5 s at 20 rad/s on virtual-can held to the 1 ms SYNC grid, with the timing and the plant kept."""
    config = load_rig_config(VIRTUAL_CAN).model_copy(update={"pace": "realtime"})
    rig = VirtualCanRig(config)
    with rig:
        rig.cycle_log, rig.plant_log = CycleLog(), []
        rig.enable()
        blocks: list[dict[str, np.ndarray]] = []
        result = rig.run_segment(
            Segment(ControlMode.VELOCITY, np.full(1500, PACED_SPEED_RAD_S)), blocks.append
        )
        assert result.aborted is None
        rig.disable()
        assert rig.daq is not None
        uncertainty = max(e.uncertainty_s for e in rig.daq.clock_model.estimates)
        rows = {name: np.concatenate([b[name] for b in blocks]) for name in blocks[0]}
        plant = {name: np.array([s[name] for s in rig.plant_log]) for name in rig.plant_log[0]}
        return PacedRun(rows, rig.cycle_log.arrays(), plant, uncertainty)


def test_theta_l_is_the_daq_measurement_of_the_plant(paced: PacedRun) -> None:
    steady = slice(300, None)  # past the speed step
    truth = paced.plant["theta_l"][steady]
    error = np.abs(paced.rows["theta_l"][steady] - truth)
    stand_in_error = np.abs(R * paced.rows["theta_m"][steady] - truth)  # what r·θ_m would have given
    # θ_l is interpolated at each SYNC between DAQ samples 0.5 ms apart, read from a plant the twin
    # steps at each SYNC: within the output's motion over two cycles (ripple included), plus noise, plus
    # the motion over the DAQ clock's stated uncertainty (on a busy machine its quickest exchange can be
    # slow: the rig promises alignment within it, not better).
    speed = np.max(np.abs(np.diff(truth))) / PERIOD_S
    motion = np.max(np.abs(truth[2:] - truth[:-2])) + speed * paced.clock_uncertainty_s + 5 * 2e-6
    np.testing.assert_array_equal(paced.plant["t"], paced.rows["t"])  # the same samples, row by row
    assert np.percentile(error, 99) <= motion
    # And better than the rigid stand-in. (Not the bound: on a busy machine the clock's stated
    # uncertainty took it past the stand-in's error once, at load 11, the error itself within both.)
    assert np.percentile(error, 99) < np.percentile(stand_in_error, 99)


def test_the_daq_stream_is_aligned_with_the_servo_by_host_time(paced: PacedRun) -> None:
    steady = slice(300, None)
    # The DAQ's own encoder, interpolated at the SYNC times, against the drive's. The twin's plant moves
    # in steps at each SYNC, and interpolating between DAQ samples 0.5 ms apart blends the step: half a
    # cycle of motion on average (measured 0.5-0.8 ω·T, 99 % within 1.0-1.6 ω·T; ω·T = 0.02 rad). A clock
    # error of 2 ms (measured: median 2.8 ω·T) fails; one of a chunk would be 250 ω·T.
    # The clock estimate's stated uncertainty (half its quickest round trip) widens both bounds.
    offset = (paced.cycles["daq_theta_m_rad"] - paced.rows["theta_m"])[steady]
    step = PACED_SPEED_RAD_S * PERIOD_S
    clock = PACED_SPEED_RAD_S * paced.clock_uncertainty_s
    assert abs(np.median(offset)) <= 1.5 * step + clock
    assert np.percentile(np.abs(offset), 99) <= 3 * step + clock


# --- refusals and life cycle -------------------------------------------------------------------------


@pytest.fixture
def rig() -> Iterator[VirtualCanRig]:
    rig = VirtualCanRig(load_rig_config(VIRTUAL_CAN))
    with rig:
        yield rig


def test_a_voltage_segment_is_refused_in_one_line(rig: VirtualCanRig) -> None:
    rig.enable()
    with pytest.raises(RigError, match="no voltage mode") as info:
        rig.run_segment(Segment(ControlMode.VOLTAGE, np.full(10, 1.0), label="pulse"), lambda block: None)
    assert "\n" not in str(info.value)


def test_close_leaves_no_thread_behind() -> None:
    before = set(threading.enumerate())
    rig = open_rig(load_rig_config(VIRTUAL_CAN))
    rig.enable()
    rig.run_segment(Segment(ControlMode.VELOCITY, np.full(300, 10.0)), lambda block: None)
    rig.close()
    assert not no_new_threads(before)


# --- the canopen backend, on a drive twin without a DAQ -----------------------------------------------


def example_data() -> dict[str, Any]:
    data: dict[str, Any] = yaml.safe_load((RIG_DIR / "hardware-example.yaml").read_text())
    return data


def test_the_hardware_example_rig_file_validates() -> None:
    config = load_rig_config(RIG_DIR / "hardware-example.yaml")
    settings = CanopenSettings.from_rig_config(config)
    constants = BenchConstants.from_rig_config(config, settings.scaling.torque_constant_nm_per_a)
    assert (settings.interface, settings.channel) == ("socketcan", "can0")
    assert constants.daq is not None and constants.gear_ratio == 0.01


def test_a_bench_without_a_daq_must_say_where_theta_l_comes_from() -> None:
    data = example_data()
    del data["daq"]
    with pytest.raises(HardwareConfigError, match="theta_l_from_motor") as info:
        BenchConstants.from_rig_config(RigConfig.model_validate(data), 0.0302)
    assert "\n" not in str(info.value)


BenchRigFactory = Callable[..., Rig]


@pytest.fixture
def make_bench_rig(request: pytest.FixtureRequest, seed: HarmonicDriveModel) -> Iterator[BenchRigFactory]:
    """`backend: canopen` as a bench without a DAQ (hardware-example.yaml, θ_l from the motor), its
    drive a twin on a virtual channel of the test's own; `drive_limits` replace the twin's envelope."""
    before = set(threading.enumerate())
    built: list[tuple[Cia402Twin, Rig]] = []

    def build(drive_limits: dict[str, float] | None = None) -> Rig:
        bus = bus_settings_for_test(request.node.name)
        data = example_data()
        del data["daq"]
        data["hardware"]["theta_l_from_motor"] = True
        data["canopen"] = {
            "eds": "hdrig-sim-drive.eds",
            "node_id": NODE,
            "interface": bus.interface,
            "channel": bus.channel,
            "scaling": {"torque_constant_nm_per_a": seed.motor.K_m},
            # The drive is a twin on this machine: its answers wait for the CPU (the file's 20 ms, for a
            # drive of its own, ran out once at load 12; measured > 250 ms with two CPU hogs).
            "sync_timeout_s": TWIN_SYNC_TIMEOUT_S,
        }
        config = RigConfig.model_validate(data)
        limits = config.limits.model_copy(update=drive_limits or {})
        twin = Cia402Twin(open_bus(bus), NODE, seed, config.model_copy(update={"limits": limits}))
        try:
            rig = open_rig(config)
        except BaseException:
            twin.close()
            raise
        built.append((twin, rig))
        return rig

    yield build
    for twin, rig in built:
        rig.close()
        twin.close()
    assert not no_new_threads(before)


@pytest.fixture
def bench_rig(make_bench_rig: BenchRigFactory) -> Rig:
    return make_bench_rig()


def test_a_bench_without_a_daq_records_r_theta_m_as_theta_l(bench_rig: Rig) -> None:
    bench_rig.enable()
    blocks: list[dict[str, np.ndarray]] = []
    bench_rig.run_segment(Segment(ControlMode.VELOCITY, np.full(200, 10.0)), blocks.append)
    theta_m = np.concatenate([b["theta_m"] for b in blocks])
    theta_l = np.concatenate([b["theta_l"] for b in blocks])
    assert bench_rig.source == "hardware" and np.ptp(theta_m) > 1.0
    np.testing.assert_array_equal(theta_l, R * theta_m)


def test_a_bench_refuses_a_load_torque(bench_rig: Rig) -> None:
    bench_rig.enable()
    with pytest.raises(RigError, match="no load actuator"):
        bench_rig.run_segment(Segment(ControlMode.VELOCITY, np.zeros(10), 5.0, "loaded"), lambda block: None)


def test_a_drive_fault_the_host_does_not_see_ends_the_segment_after_its_rows(
    make_bench_rig: BenchRigFactory,
) -> None:
    rig = make_bench_rig({"velocity_rad_s": 50.0})  # the drive trips at 50 rad/s, the host at 700
    rig.enable()
    blocks: list[dict[str, np.ndarray]] = []
    with pytest.raises(RigFaultError, match=r"drive left OPERATION ENABLED: FAULT \(EMCY 0x8400"):
        rig.run_segment(Segment(ControlMode.VELOCITY, np.full(500, 100.0)), blocks.append)
    speeds = np.concatenate([b["omega_m"] for b in blocks])
    assert speeds[-1] > 50.0 and np.all(speeds[:-1] <= 50.0)  # every row up to the tripping one


def test_a_drive_emcy_mid_segment_is_a_device_fault_not_bad_input(make_bench_rig: BenchRigFactory) -> None:
    rig = make_bench_rig({"velocity_rad_s": 50.0})
    rig.enable()
    with pytest.raises(DeviceFaultError, match="EMCY 0x8400") as info:
        rig.run_segment(Segment(ControlMode.VELOCITY, np.full(500, 100.0)), lambda block: None)
    health = rig.health()
    assert not isinstance(info.value, UserInputError)
    # The rig quick-stopped and keeps the fault as its last abort, for the run to end `aborted: <fault>`.
    assert not health.enabled and health.last_abort == f"aborted: {info.value}"
