"""The twins in a process of their own, on the loopback TCP bus (`hdrig twin`, `twins: process`).

What one process could not show: canopen's own master in another process drives the twin; a host
killed with SIGKILL mid-run is stopped by the drive's watchdog within its timeout, and the twin says
so; a twin killed mid-run leaves the host quick-stopped and the run `aborted` with the reason.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can
import canopen
import numpy as np
import pytest
import yaml

from drivers.cia402 import EMCY_HEARTBEAT
from rig.config import RIG_DIR, RigConfig
from rig.interface import SAMPLE_COLUMNS, ControlMode, Segment
from rig.runner import RunHooks, run_experiment
from rig.status import RunStatus
from rig.store.runs import RunStore
from sim_backend import virtual_bus
from sim_backend.cia402_twin import TWIN_EDS
from sim_backend.virtual_bus import VirtualCanRig

REPO_ROOT = Path(__file__).resolve().parent.parent
VIRTUAL_CAN = RIG_DIR / "virtual-can.yaml"
NODE = 1
HOST_HEARTBEAT_TIMEOUT_MS = 1000  # virtual-can.yaml's canopen.host_heartbeat_timeout_ms
WATCH_PERIOD_MS = 5  # the twin checks its consumers this often
# From SIGKILL to the EMCY seen here: the timeout after the last heartbeat (sent ≤ 50 ms before the
# kill), one watch period, and the frame's way through the hub; 200 ms covers a busy 2-core machine.
KILL_MARGIN_MS = 200


def process_rig(twins: str = "process") -> RigConfig:
    data = yaml.safe_load(VIRTUAL_CAN.read_text())
    data["twins"] = twins
    return RigConfig.model_validate(data)


def test_a_child_that_does_not_answer_in_time_is_ended_in_one_clear_error(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(virtual_bus, "CHILD_START_TIMEOUT_S", 0.001)  # no child starts in 1 ms
    made: list[str] = []
    mkdtemp = tempfile.mkdtemp
    monkeypatch.setattr(tempfile, "mkdtemp", lambda **kw: made.append(mkdtemp(**kw)) or made[-1])
    with pytest.raises(RuntimeError, match=r"^the twins' process did not start: no answer in 0.001 s$"):
        VirtualCanRig(process_rig())
    assert len(made) == 1 and not Path(made[0]).exists()  # its plant log removed


@pytest.mark.usefixtures("quiet_heap")
def test_a_child_s_run_has_every_column_and_the_plant_log_of_an_in_process_run() -> None:
    """The child hands its plant log back: rows carry the plant's time and `plant_log` the truth."""
    runs = {}
    for twins in ("process", "in-process"):
        rig = VirtualCanRig(process_rig(twins))
        with rig:
            rig.plant_log = []
            rig.enable()
            blocks: list[dict[str, np.ndarray]] = []
            result = rig.run_segment(Segment(ControlMode.VELOCITY, np.full(400, 20.0)), blocks.append)
            assert result.aborted is None
            rows = {name: np.concatenate([b[name] for b in blocks]) for name in SAMPLE_COLUMNS}
            plant = {name: np.array([s[name] for s in rig.plant_log]) for name in SAMPLE_COLUMNS}
        runs[twins] = rows, plant
    (rows, plant), (rows_in, plant_in) = runs["process"], runs["in-process"]
    np.testing.assert_array_equal(rows["t"], plant["t"])  # each row its own SYNC's sample
    # In virtual time the plant steps once per SYNC with seeded noise and the host's commands do not
    # depend on the wall clock: the child runs the very same plant, bit for bit. A sample handed back a
    # SYNC late or early would shift every column by a cycle (ω·T = 0.02 rad of θ_m).
    for name in SAMPLE_COLUMNS:
        np.testing.assert_array_equal(plant[name], plant_in[name], err_msg=name)
        if name != "theta_l":
            np.testing.assert_array_equal(rows[name], rows_in[name], err_msg=name)
    # θ_l is the DAQ twin's, aligned on the wall clock: test_virtual_can_rig's paced run checks it
    # against this truth (virtual-can.yaml runs its twins in a child).


@pytest.fixture
def twin_server() -> Iterator[tuple[subprocess.Popen[str], dict[str, Any]]]:
    """`hdrig twin --rig virtual-can.yaml` and the JSON line saying where its twins are."""
    child = subprocess.Popen(
        [sys.executable, "-m", "rig", "twin", "--rig", str(VIRTUAL_CAN)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=REPO_ROOT,
    )
    assert child.stdout is not None
    where = json.loads(child.stdout.readline())
    try:
        yield child, where
    finally:
        child.send_signal(signal.SIGTERM)
        child.communicate(timeout=10)


def test_canopen_base_node_402_in_this_process_drives_the_twin_in_another(
    twin_server: tuple[subprocess.Popen[str], dict[str, Any]],
) -> None:
    _child, where = twin_server
    network = canopen.Network()
    network.connect(interface="hdrig-tcp", channel=where["can"])
    node = canopen.BaseNode402(where["node_id"], str(TWIN_EDS))
    network.add_node(node)
    node.sdo.RESPONSE_TIMEOUT = 2.0
    try:
        node.nmt.state = "PRE-OPERATIONAL"
        node.nmt.wait_for_heartbeat(timeout=2.0)
        node.setup_402_state_machine()
        node.sdo[0x1006].raw = 10_000  # SYNC every 10 ms: the twin simulates 10 ms per SYNC
        node.nmt.state = "OPERATIONAL"
        network.sync.start(0.01)
        try:
            node.state = "OPERATION ENABLED"
            state = node.state
        finally:
            network.sync.stop()
    finally:
        network.disconnect()
    assert state == "OPERATION ENABLED"


HOST = """
import sys, time
from drivers.canopen_config import CanopenSettings, DriveLimits
from drivers.canopen_servo import CanopenServo
from rig.interface import ControlMode
settings = CanopenSettings.model_validate({"eds": "hdrig-sim-drive.eds", "node_id": 1,
    "interface": "hdrig-tcp", "channel": sys.argv[1], "host_heartbeat_timeout_ms": 1000,
    "drive_heartbeat_timeout_ms": 1000, "scaling": {"torque_constant_nm_per_a": 0.0302}})
servo = CanopenServo(settings, DriveLimits(10.0, 600.0), 0.001)
servo.connect(); servo.boot(); servo.configure(ControlMode.VELOCITY); servo.enable()
print("cycling", flush=True)
while True:
    servo.cycle(20.0)
"""


def test_a_host_killed_mid_run_is_stopped_by_the_drive_watchdog_which_says_so(
    twin_server: tuple[subprocess.Popen[str], dict[str, Any]],
) -> None:
    child, where = twin_server
    host = subprocess.Popen(
        [sys.executable, "-c", HOST, where["can"]], stdout=subprocess.PIPE, text=True, cwd=REPO_ROOT
    )
    assert host.stdout is not None
    assert host.stdout.readline().strip() == "cycling"
    with can.Bus(interface="hdrig-tcp", channel=where["can"]) as watch:
        time.sleep(0.2)  # mid-run: 200 cycles at 20 rad/s
        host.send_signal(signal.SIGKILL)
        killed = time.monotonic()
        host.wait()
        emcy = watch.recv(timeout=3.0)
        while emcy is not None and emcy.arbitration_id != 0x80 + NODE:
            emcy = watch.recv(timeout=3.0)
        seen_ms = (time.monotonic() - killed) * 1e3
    assert emcy is not None, "the twin sent no EMCY within 3 s of the host's death"
    assert int.from_bytes(emcy.data[:2], "little") == EMCY_HEARTBEAT
    assert seen_ms <= HOST_HEARTBEAT_TIMEOUT_MS + KILL_MARGIN_MS
    child.send_signal(signal.SIGTERM)
    _out, err = child.communicate(timeout=10)
    said = [line for line in err.splitlines() if "heartbeat of node 127 lost" in line]
    assert said and "(timeout 1000 ms): EMCY 0x8130, FAULT, torque off" in said[0], err


def test_a_twin_killed_mid_run_quick_stops_the_host_and_aborts_the_run(tmp_path: Path) -> None:
    rig = VirtualCanRig(process_rig())
    assert rig.child is not None
    child_pid = rig.child.pid
    started = threading.Event()

    def kill_twin_mid_run() -> None:
        # Mid-run: once rows are recorded. (A fixed delay after the run's start could land in enable()
        # on a busy machine, where a dead drive is a device fault of its own words, not `drive lost`.)
        started.wait(60)
        time.sleep(0.1)
        os.kill(child_pid, signal.SIGKILL)

    killer = threading.Thread(target=kill_twin_mid_run, daemon=True)
    killer.start()
    quick_stops: list[float] = []
    real_quick_stop = rig.servo.quick_stop

    def counted_quick_stop() -> None:
        quick_stops.append(time.monotonic())
        real_quick_stop()

    rig.servo.quick_stop = counted_quick_stop  # type: ignore[method-assign]
    sweep = {"speeds_rad_s": [20.0], "settle_s": 0.5, "hold_s": 5.0}
    with rig:
        outcome = run_experiment(
            "speed-sweep",
            rig.config,
            sweep,
            RunStore(tmp_path),
            rig=rig,
            hooks=RunHooks(on_block=lambda _id, _block: started.set()),
        )
    killer.join()
    assert outcome.status == RunStatus.ABORTED
    # The drive and the DAQ board die together: whichever the loop meets first is the reason.
    assert outcome.reason is not None
    assert outcome.reason.startswith(
        ("aborted: rig 'virtual-can': drive lost", "aborted: rig 'virtual-can': DAQ")
    )
    assert quick_stops, "the host did not quick-stop"
