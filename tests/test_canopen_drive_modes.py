"""Drives as they are: modes, units, limits and watchdogs from each drive's object dictionary.

The driver reads what a drive offers (0x6502, its target objects and whether they are PDO-mappable),
picks a mode for each kind of program, takes units from the drive (0x60A9) or the rig file, writes
limits within their declared ranges, and watches the host by heartbeat consumer or node guarding.
Checked against files nobody here wrote (the vendors' EDS files in ../shared/eds, skipped where absent)
and three small test files for what those miss (configs/eds/test-*): profile modes with node guarding
and no 0x1016; velocities in rpm with no 0x6502 value and small ranges; a position-only DCF.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import can
import pytest
import yaml

from drivers.can_bus import open_bus
from drivers.canopen_config import (
    EDS_DIR,
    CanopenConfigError,
    CanopenSettings,
    DriveLimits,
    boot_plan,
    check_plan,
    resolve_scaling,
)
from drivers.canopen_servo import CanopenServo, DriveSettingError
from drivers.cia402 import EMCY_HEARTBEAT, OperationMode, State
from drivers.drive_modes import DriveModes, ModeUnavailableError
from hdrig_testing.can_bus import TWIN_SYNC_TIMEOUT_S, bus_settings_for_test
from model.params import HarmonicDriveModel
from rig.config import RIG_DIR, RigConfig, load_rig_config
from rig.core.actions import execute_plan, plan_run
from rig.interface import ControlMode, ModeRefusedError
from rig.runner import run_experiment
from rig.status import RunStatus
from rig.store.runs import RunStore
from sim_backend.cia402_twin import TWIN_EDS, Cia402Twin

# Each test builds twins from an EDS (~63,000 objects each); a full collection of what earlier tests
# left behind held the interpreter past the twin's 200 ms host-heartbeat watch under two CPU hogs
# (test_canopen_units: heartbeat lost 596 ms, EMCY 0x8130, once in two runs of the CAN files). As the
# other CAN files do.
pytestmark = pytest.mark.usefixtures("quiet_heap")

NODE = 1
SHARED_EDS = Path(__file__).resolve().parents[2] / "shared" / "eds"
PROFILE_GUARDING = EDS_DIR / "test-profile-modes-guarding.eds"
RPM_SMALL = EDS_DIR / "test-rpm-small-ranges.eds"
POSITION_ONLY = EDS_DIR / "test-position-only.dcf"
# What the vendor EDS files leave to the rig file: the twin's units (17-bit encoder, 5 A rated).
VENDOR_SCALING = {"position_units_per_rev": 131072, "rated_torque_nm": 0.151, "rated_current_a": 5.0}
LIMITS = DriveLimits(current_a=10.0, velocity_rad_s=600.0)
SHORT_SWEEP = {"speeds_rad_s": [5.0, 20.0], "settle_s": 0.1, "hold_s": 0.1}
CSV, CSP, CST = (
    OperationMode.CYCLIC_SYNC_VELOCITY,
    OperationMode.CYCLIC_SYNC_POSITION,
    OperationMode.CYCLIC_SYNC_TORQUE,
)
PV, IP = OperationMode.PROFILE_VELOCITY, OperationMode.INTERPOLATED_POSITION


def vendor(name: str) -> Path:
    path = SHARED_EDS / name
    if not path.exists():
        pytest.skip(f"{path} is absent: the vendor EDS tests need ../shared/eds")
    return path


def settings_for(eds: Path, **fields: Any) -> CanopenSettings:
    scaling = {"torque_constant_nm_per_a": 0.0302, **fields.pop("scaling", {})}
    return CanopenSettings.model_validate(
        {
            "eds": str(eds),
            "node_id": NODE,
            "interface": "virtual",
            "sync_timeout_s": TWIN_SYNC_TIMEOUT_S,
            "scaling": scaling,
            **fields,
        }
    )


def virtual_can(eds: Path, **canopen: Any) -> RigConfig:
    """configs/rigs/virtual-can.yaml with the drive twin built from `eds`."""
    data = yaml.safe_load((RIG_DIR / "virtual-can.yaml").read_text())
    data["canopen"].update({"eds": str(eds), **canopen})
    return RigConfig.model_validate(data)


# --- the mode each program runs in, offline ------------------------------------------------------


@pytest.mark.parametrize(
    ("eds", "velocity", "position", "current"),
    [
        (TWIN_EDS, CSV, CSP, CST),
        (PROFILE_GUARDING, PV, IP, None),  # PP, PV, HM, IP: no torque mode at all
        (RPM_SMALL, CSV, CSP, CST),  # no 0x6502 value: the modes of its target objects
        (POSITION_ONLY, IP, IP, None),  # PP and IP only: speed integrated into positions
    ],
)
def test_each_program_takes_the_best_mode_the_eds_offers(
    eds: Path, velocity: OperationMode, position: OperationMode, current: OperationMode | None
) -> None:
    modes = DriveModes.of(settings_for(eds).object_dictionary())
    assert modes.choose(ControlMode.VELOCITY).mode == velocity
    assert modes.choose(ControlMode.POSITION).mode == position
    if current is None:
        with pytest.raises(ModeUnavailableError, match="no mode for current programs: it offers"):
            modes.choose(ControlMode.CURRENT)
    else:
        assert modes.choose(ControlMode.CURRENT).mode == current


@pytest.mark.parametrize("name", ["ZeroErrDriver.eds", "nanotec_C5-E-2-09.eds"])
def test_both_vendor_drives_run_every_program_cyclic_synchronous(name: str) -> None:
    modes = DriveModes.of(settings_for(vendor(name)).object_dictionary())
    chosen = [modes.choose(p).mode for p in (ControlMode.CURRENT, ControlMode.VELOCITY, ControlMode.POSITION)]
    assert chosen == [CST, CSV, CSP]


def test_a_refusal_names_what_the_drive_offers_in_one_line() -> None:
    modes = DriveModes.of(settings_for(PROFILE_GUARDING).object_dictionary())
    with pytest.raises(ModeUnavailableError) as refused:
        modes.choose(ControlMode.CURRENT)
    message = str(refused.value)
    assert "\n" not in message
    assert message == (
        "the drive has no mode for current programs: it offers profile position (1), profile velocity (3),"
        " homing (6), interpolated position (7); cycle by cycle only profile velocity, interpolated position"
        " (0x6502 of the EDS)"
    )


# --- units and limits -------------------------------------------------------------------------------


def eds_default(od: Any) -> Any:
    """Reads an object's EDS default: what a drive fresh from the factory answers."""

    def read(index: int, subindex: int) -> int:
        obj = od[index]
        return int((obj[subindex] if subindex or not hasattr(obj, "default") else obj).default)

    return read


def test_velocity_in_rpm_is_read_from_0x60a9() -> None:
    settings = settings_for(RPM_SMALL)
    od = settings.object_dictionary()
    scaling = resolve_scaling(settings.scaling, od, eds_default(od))
    assert scaling.velocity_units_per_rad_s == pytest.approx(60 / (2 * math.pi), rel=1e-12)  # rpm per rad/s
    assert scaling.velocity_raw(600.0) == 5730  # 600 rad/s = 5729.6 rpm


def test_the_rig_file_names_the_unit_the_eds_cannot_say() -> None:
    settings = settings_for(TWIN_EDS, scaling={"velocity_unit": "rpm"})
    od = settings.object_dictionary()
    assert resolve_scaling(settings.scaling, od, eds_default(od)).velocity_raw(2 * math.pi) == 60


def test_limits_within_the_declared_ranges_are_written() -> None:
    settings = settings_for(RPM_SMALL)
    od = settings.object_dictionary()
    plan = boot_plan(od, settings, LIMITS, resolve_scaling(settings.scaling, od, eds_default(od)), 0.001)
    written = {(w.index, w.subindex): w.value for w in plan}
    assert written[(0x607F, 0)] == 5730 and written[(0x6080, 0)] == 5730  # rpm, within [0, 6000]
    assert check_plan(od, plan) == []


def test_a_limit_beyond_the_declared_range_is_refused_in_one_line_naming_it() -> None:
    settings = settings_for(RPM_SMALL)
    od = settings.object_dictionary()
    scaling = resolve_scaling(settings.scaling, od, eds_default(od))
    too_fast = DriveLimits(current_a=10.0, velocity_rad_s=700.0)  # 6685 rpm; the drive declares 6000
    with pytest.raises(CanopenConfigError) as refused:
        boot_plan(od, settings, too_fast, scaling, 0.001)
    assert str(refused.value) == (
        "0x6080 (Max motor speed) = 6685 is outside its declared range [0, 6000]: max motor speed, rpm"
        " = 700 rad/s; lower `control:` or check `canopen.scaling`"
    )


# --- watchdogs ------------------------------------------------------------------------------------


def test_a_drive_without_heartbeat_consumer_is_guarded() -> None:
    settings = settings_for(PROFILE_GUARDING)
    od = settings.object_dictionary()
    plan = boot_plan(od, settings, LIMITS, resolve_scaling(settings.scaling, od, eds_default(od)), 0.001)
    written = {(w.index, w.subindex): w.value for w in plan}
    # Guarded every host heartbeat period (50 ms), life time factor 4: stopped 200 ms after the last.
    assert (written[(0x100C, 0)], written[(0x100D, 0)]) == (50, 4)
    assert (0x1016, 1) not in written


def without_watchdog(tmp_path: Path) -> Path:
    """The twin's EDS less its heartbeat consumer (and with no node guarding): a drive that runs on."""
    text = TWIN_EDS.read_text()
    kept = [s for s in text.split("\n[") if not s.startswith("1016")]
    path = tmp_path / "no-watchdog.eds"
    path.write_text("\n[".join(kept))
    return path


def test_a_drive_with_no_watchdog_is_refused_unless_the_rig_file_accepts_it(
    request: pytest.FixtureRequest, seed: HarmonicDriveModel, tmp_path: Path
) -> None:
    eds = without_watchdog(tmp_path)
    bus = bus_settings_for_test(request.node.name)
    config = load_rig_config(RIG_DIR / "sim.yaml")
    settings = settings_for(eds, interface=bus.interface, channel=bus.channel, pace=False)
    with Cia402Twin(open_bus(bus), NODE, seed, config, eds_path=eds):
        with CanopenServo(settings, LIMITS, 0.001) as servo:
            servo.connect()
            with pytest.raises(DriveSettingError, match=r"canopen\.accept_drive_runs_on_if_host_dies: true"):
                servo.boot()
        accepted = settings.model_copy(update={"accept_drive_runs_on_if_host_dies": True})
        with CanopenServo(accepted, LIMITS, 0.001) as servo:
            servo.connect()
            servo.boot()
            servo.configure(ControlMode.VELOCITY)
            assert servo.enable().state == State.OPERATION_ENABLED


def test_the_twin_stops_when_node_guarding_ends(
    request: pytest.FixtureRequest, seed: HarmonicDriveModel
) -> None:
    """The host guards every 50 ms with life time factor 4: once it stops, the twin faults within
    200 ms plus its 5 ms watch, with EMCY 0x8130 (life guard)."""
    bus = bus_settings_for_test(request.node.name)
    config = load_rig_config(RIG_DIR / "sim.yaml")
    settings = settings_for(PROFILE_GUARDING, interface=bus.interface, channel=bus.channel, pace=False)
    with Cia402Twin(open_bus(bus), NODE, seed, config, eds_path=PROFILE_GUARDING) as twin:
        servo = CanopenServo(settings, LIMITS, 0.001)
        servo.connect()
        servo.boot()
        servo.configure(ControlMode.VELOCITY)
        servo.enable()
        for _ in range(50):
            servo.cycle(10.0)
        assert servo._guard is not None
        servo._guard.stop()  # the host goes silent (its heartbeat thread too)
        assert servo._heartbeat is not None
        servo._heartbeat.stop()
        with can.Bus(interface=bus.interface, channel=bus.channel) as listener:
            message = listener.recv(timeout=1.0)
            while message is not None and message.arbitration_id != 0x80 + NODE:
                message = listener.recv(timeout=1.0)
        servo._silent = True  # nothing to say goodbye to
        servo.close()
        assert message is not None, "no EMCY within 1 s of the last guarding request"
        assert int.from_bytes(message.data[:2], "little") == EMCY_HEARTBEAT
        assert twin.state == State.FAULT


# --- the speed sweep through the virtual-can rig, on twins built from each file --------------------


@pytest.mark.parametrize(
    ("eds", "scaling", "mode"),
    [
        (PROFILE_GUARDING, {}, PV),
        (RPM_SMALL, {}, CSV),
        (POSITION_ONLY, {}, IP),
        (Path("ZeroErrDriver.eds"), VENDOR_SCALING, CSV),
        # Nanotec's 0x60A8 says its positions are 0.1° (3600 a turn): the drive's units, not the rig's.
        (Path("nanotec_C5-E-2-09.eds"), {**VENDOR_SCALING, "position_units_per_rev": None}, CSV),
    ],
    ids=["profile-modes-guarding", "rpm-small-ranges", "position-only", "zeroerr", "nanotec"],
)
def test_the_speed_sweep_runs_on_a_twin_built_from_each_file(
    eds: Path, scaling: dict[str, float | None], mode: OperationMode, tmp_path: Path
) -> None:
    path = eds if eds.is_absolute() else vendor(eds.name)
    config = virtual_can(path, scaling={"torque_constant_nm_per_a": 0.0302, **scaling})
    outcome = run_experiment("speed-sweep", config, SHORT_SWEEP, RunStore(tmp_path))
    assert outcome.status == RunStatus.COMPLETE, outcome.reason
    meta = RunStore(tmp_path).get(outcome.run_id)["meta"]
    assert any(f"(mode {int(mode)})" in line for line in meta["rig_modes"]), meta["rig_modes"]
    table = outcome.metrics
    assert table, "the sweep was analyzed"


def test_an_experiment_the_drive_cannot_play_is_refused_before_anything_moves(tmp_path: Path) -> None:
    store = RunStore(tmp_path)
    with pytest.raises(ModeRefusedError) as refused:
        run_experiment("pulse", virtual_can(POSITION_ONLY), {}, store)
    assert "\n" not in str(refused.value)
    assert (
        "a CiA 402 drive has no voltage mode; it offers profile position (1), interpolated position (7)"
        in str(refused.value)
    )
    assert store.list_runs() == []  # no run was opened


def test_a_campaign_skips_what_the_drive_cannot_play_and_goes_on(tmp_path: Path) -> None:
    plan = plan_run(
        "campaign",
        {"speed-sweep": SHORT_SWEEP, "pulse": {}},
        experiments=["pulse", "speed-sweep"],
    )
    skipped: list[tuple[str, str]] = []
    documents = execute_plan(
        plan, virtual_can(POSITION_ONLY), RunStore(tmp_path), on_skip=lambda e, r: skipped.append((e, r))
    )
    assert [(d.experiment, d.status) for d in documents] == [("speed-sweep", RunStatus.COMPLETE)]
    assert [e for e, _ in skipped] == ["pulse"] and "no voltage mode" in skipped[0][1]
