"""The CAN bus load of a control cycle, computed from the mapped frames and the bit rate, and refused in
one line above `canopen.bus_load_max` before a drive is enabled (issue 26 item 1).

The frame sizes are CAN 2.0A's, worked by hand at worst-case bit stuffing (one stuff bit every four of
the 34 + 8n stuffed bits): 47 + 8n + ⌊(33 + 8n)/4⌋ bits for n data bytes, so a SYNC without data is 55
bits and a full 8-byte frame 135. The driver's cycle in CSV on the project's sim drive is one SYNC, RPDO 1
(controlword 16 + target velocity 32 bits: 6 bytes, 115 bits), TPDO 1 (statusword 16, mode display 8,
torque 16, current 16: 7 bytes, 125 bits) and TPDO 2 (position 32, velocity 32: 8 bytes, 135 bits):
430 bits a cycle, 43 % of 1 Mbit/s at 1 kHz; two such drives 80.5 %.
"""

from __future__ import annotations

import pytest

from drivers.can_bus import open_bus
from drivers.canopen_config import (
    EDS_DIR,
    BusLoad,
    CanopenConfigError,
    CanopenSettings,
    DriveLimits,
    PdoPlan,
    bus_load,
    check_bus_load,
    frame_bits,
    rpdo_layout,
    tpdo_layouts,
)
from drivers.canopen_servo import CanopenServo
from drivers.cia402 import OperationMode, State
from hdrig_testing.can_bus import TWIN_SYNC_TIMEOUT_S, bus_settings_for_test
from model.params import HarmonicDriveModel
from rig.config import RIG_DIR, load_rig_config
from sim_backend.cia402_twin import Cia402Twin

pytestmark = pytest.mark.usefixtures("quiet_heap")

SIM_EDS = EDS_DIR / "hdrig-sim-drive.eds"


def settings(**update: object) -> CanopenSettings:
    return CanopenSettings.model_validate(
        {
            "eds": str(SIM_EDS),
            "node_id": 3,
            "interface": "virtual",
            "sync_timeout_s": TWIN_SYNC_TIMEOUT_S,
            "scaling": {"torque_constant_nm_per_a": 0.0302},
            **update,
        }
    )


def csv_plan(node_id: int) -> PdoPlan:
    od = settings().object_dictionary()
    tpdo1, tpdo2 = tpdo_layouts(od)
    return PdoPlan(rpdo_layout(od, OperationMode.CYCLIC_SYNC_VELOCITY), tpdo1, tpdo2, node_id)


def test_frame_bits_at_worst_case_stuffing() -> None:
    assert [frame_bits(n) for n in (0, 6, 7, 8)] == [55, 115, 125, 135]


def test_one_and_two_drives_in_csv_at_1_khz() -> None:
    plan = csv_plan(3)
    assert (plan.rpdo.length, plan.tpdo1.length, plan.tpdo2.length) == (6, 7, 8)
    one = bus_load([plan], 0.001, 1_000_000)
    assert one.bits_per_cycle == 430
    assert one.share == pytest.approx(0.43)
    two = bus_load([plan, csv_plan(4)], 0.001, 1_000_000)
    assert two.bits_per_cycle == 55 + 2 * 375
    assert str(two) == "bus load 80% (805 bits a cycle at 1000 Hz, 1000 kbit/s)"
    check_bus_load(two, 0.9, "bench")  # within the default limit: no error


def test_a_cycle_the_bus_cannot_carry_is_refused_in_one_line() -> None:
    load = BusLoad(430, 0.001, 250_000)  # 172 %
    with pytest.raises(CanopenConfigError) as refused:
        check_bus_load(load, 0.9, "node 3")
    assert str(refused.value) == (
        "node 3: bus load 172% (430 bits a cycle at 1000 Hz, 250 kbit/s) is above canopen.bus_load_max ="
        " 90%: lower the rig's sample_rate_hz, raise canopen.bitrate or drive fewer nodes on this bus"
    )


def test_the_servo_refuses_the_mode_before_anything_moves(
    request: pytest.FixtureRequest, seed: HarmonicDriveModel
) -> None:
    bus = bus_settings_for_test(request.node.name)
    twin = Cia402Twin(open_bus(bus), 3, seed, load_rig_config(RIG_DIR / "sim.yaml"), eds_path=SIM_EDS)
    slow = settings(interface=bus.interface, channel=bus.channel, pace=False, bitrate=250_000)
    servo = CanopenServo(slow, DriveLimits(current_a=10.0, velocity_rad_s=600.0), period_s=0.001)
    with twin, servo:
        servo.connect()
        servo.boot()
        with pytest.raises(CanopenConfigError, match=r"^node 3: bus load 172% "):
            servo.configure(OperationMode.CYCLIC_SYNC_VELOCITY)
        assert twin.state != State.OPERATION_ENABLED


def test_the_servo_says_its_bus_load_when_it_fits(
    request: pytest.FixtureRequest, seed: HarmonicDriveModel
) -> None:
    bus = bus_settings_for_test(request.node.name)
    twin = Cia402Twin(open_bus(bus), 3, seed, load_rig_config(RIG_DIR / "sim.yaml"), eds_path=SIM_EDS)
    fast = settings(interface=bus.interface, channel=bus.channel, pace=False)
    servo = CanopenServo(fast, DriveLimits(current_a=10.0, velocity_rad_s=600.0), period_s=0.001)
    with twin, servo:
        servo.connect()
        servo.boot()
        servo.configure(OperationMode.CYCLIC_SYNC_VELOCITY)
        assert servo.bus_load is not None and servo.bus_load.bits_per_cycle == 430
