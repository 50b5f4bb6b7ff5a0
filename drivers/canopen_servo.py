"""A CiA 402 servo drive on CANopen, driven cycle by cycle from the host: one SYNC per cycle.

Built on canopen (SDO, NMT, EMCY, EDS) and python-can (the bus, the raw traffic log), and designed
around what canopen 2.4 leaves out: the PDOs are mapped from the driver's own plan and packed here
(no PDO upload over SDO, as `BaseNode402` does); the SYNC is sent by `cycle()` itself rather than by a
`SyncProducer` thread, so each cycle is one RPDO, one SYNC and the TPDOs answering that very SYNC;
the drive's heartbeat is watched here, since canopen's master has no heartbeat-consumer timeout.

The host's heartbeat (or node guarding) vouches for the control loop, not only for the process: while
the drive is powered, a period goes out only if a cycle was sent within `loop_timeout_ms`. A loop that
hangs in a live process (a stuck hook, a lock, a swap storm) so falls silent too, and the drive's own
watchdog stops it `host_heartbeat_timeout_ms` later, as if the host had died.

The driver knows nothing of the rig interface's segments: a rig backend pairs it with its sensors,
calls `configure(mode)` and then `cycle(target)` once per sample, and asks `faults()` for its health.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Final

import can
import canopen
from canopen.emcy import EmcyError
from canopen.sdo import SdoAbortedError, SdoCommunicationError

from drivers.can_bus import PeriodicFrame, RecordedNetwork, open_bus
from drivers.canopen_config import (
    BusLoad,
    CanopenSettings,
    DriveLimits,
    PdoPlan,
    Scaling,
    SdoWrite,
    Watchdog,
    boot_plan,
    bus_load,
    check_bus_load,
    check_plan,
    declared_range,
    guarding,
    host_watchdog,
    mode_plan,
    resolve_scaling,
    rpdo_layout,
    tpdo_layouts,
)
from drivers.cia402 import (
    CONTROLWORD,
    CW_ENABLE_IP_BIT,
    TARGET_OBJECT,
    Command,
    OperationMode,
    State,
    command_towards,
    decode_statusword,
)
from drivers.drive_modes import TORQUE_OFFSET, DriveModes, ModeChoice, ModeUnavailableError
from drivers.pdo_layout import od_variable
from model.errors import UserInputError
from rig.config import RigConfig
from rig.faults import DeviceFaultError
from rig.interface import ControlMode

logger = logging.getLogger(__name__)

SYNC_COB_ID: Final = 0x080
NMT_START, NMT_STOP, NMT_PRE_OPERATIONAL, NMT_RESET_NODE = 0x01, 0x02, 0x80, 0x81
NMT_OPERATIONAL_STATE: Final = 5
HOST_HEARTBEAT_STATE: Final = bytes([NMT_OPERATIONAL_STATE])

PROGRAM_OF: Final[dict[OperationMode, ControlMode]] = {
    OperationMode.CYCLIC_SYNC_TORQUE: ControlMode.CURRENT,
    OperationMode.PROFILE_TORQUE: ControlMode.CURRENT,
    OperationMode.CYCLIC_SYNC_VELOCITY: ControlMode.VELOCITY,
    OperationMode.PROFILE_VELOCITY: ControlMode.VELOCITY,
    OperationMode.CYCLIC_SYNC_POSITION: ControlMode.POSITION,
    OperationMode.INTERPOLATED_POSITION: ControlMode.POSITION,
}
"""What a drive mode named directly plays: current as torque (K_m · i), speed, position."""
TORQUE_MODES: Final = frozenset({OperationMode.CYCLIC_SYNC_TORQUE, OperationMode.PROFILE_TORQUE})
POSITION_MODES: Final = frozenset({OperationMode.CYCLIC_SYNC_POSITION, OperationMode.INTERPOLATED_POSITION})
_TPDO1_NAMES: Final = {0x6041: "statusword", 0x6061: "mode", 0x6077: "torque", 0x6078: "current"}
STANDSTILL_RAD_S: Final = 0.5
"""Below this motor speed an orderly stop removes power."""


class DriveSettingError(UserInputError):
    """The drive refused what the rig file asks of it (an SDO write or read aborted, a mode it has not);
    one line naming the node, the object and the drive's abort code."""


class CanopenServoError(DeviceFaultError):
    """The drive failed while working: it faulted, went silent, or did not reach a state or mode."""


class SyncTimeoutError(CanopenServoError):
    """No TPDO answered a SYNC in time."""


class DriveFaultError(CanopenServoError):
    """The drive is in FAULT (its emergency messages are in the text)."""


@dataclass(frozen=True)
class Feedback:
    """What the drive reported in answer to one SYNC, in motor-side SI units."""

    t_s: float
    """Host monotonic clock when the SYNC went out [s]."""
    latency_s: float
    """From the SYNC to the last TPDO answering it [s]."""
    statusword: int
    state: State | None
    mode: int | None
    """Modes of operation display (0x6061), None when the drive does not report it."""
    position_rad: float
    velocity_rad_s: float
    torque_nm: float
    current_a: float
    """Current actual (0x6078) when the drive reports it, else torque / K_m [A]."""

    @property
    def faulted(self) -> bool:
        return self.state in (State.FAULT, State.FAULT_REACTION_ACTIVE)


class CanopenServo:
    """One CiA 402 drive: boot, configure a mode, enable, cycle, stop; raw traffic to a log file."""

    def __init__(self, settings: CanopenSettings, limits: DriveLimits, period_s: float) -> None:
        self.settings = settings
        self.limits = limits
        self.period_s = period_s
        self.od = settings.object_dictionary()
        self._tpdo = tpdo_layouts(self.od)
        self._tpdo1_names = [_TPDO1_NAMES[e.index] for e in self._tpdo[0].entries]
        # Where each of TPDO 1's objects sits in its values (None: not mapped): no dict per answer.
        self._tpdo1_at = {
            name: self._tpdo1_names.index(name) if name in self._tpdo1_names else None
            for name in _TPDO1_NAMES.values()
        }
        self._plan: PdoPlan | None = None
        self.sync_timeout_s = settings.sync_timeout_s or max(10 * period_s, 0.02)
        self.network: RecordedNetwork | None = None
        self.node: canopen.RemoteNode | None = None
        self.scaling: Scaling | None = None
        self.modes: DriveModes | None = None
        """What the drive offers, read at boot."""
        self.choice: ModeChoice | None = None
        self.bus_load: BusLoad | None = None  # of the mode configured last
        self.mode: OperationMode | None = None
        self.watchdog: Watchdog = host_watchdog(self.od)
        """How the drive notices this host is gone: heartbeat consumer, node guarding, or none."""
        self._heartbeat: PeriodicFrame | None = None
        self._guard: PeriodicFrame | None = None
        self._target_range = (0, 0)
        self._offset_range = (0, 0)  # of 0x60B2, when RPDO 1 carries it
        self._integrated_rad = 0.0  # a velocity program played in a position mode: the position so far
        # Receive side, filled by the network's notifier thread.
        self._rx = threading.Condition()
        self._tpdo_values: list[tuple[int, ...] | None] = [None, None]
        self._tpdo_counts = [0, 0]
        self._awaited: list[int] | None = None  # the counts a cycle waits to see exceeded
        self._tpdo_t_s = [0.0, 0.0]
        self._drive_heartbeat_t_s: float | None = None
        self._drive_nmt_state: int | None = None
        self._started_t_s: float | None = None  # when NMT START was last sent
        self._silent = False  # the last cycle went unanswered
        self._booted = threading.Event()
        self._emcy_active: list[str] = []
        self._emcy_lock = threading.Lock()
        # Cycle side.
        self._cycle_lock = threading.Lock()
        self._controlword = CONTROLWORD[Command.DISABLE_VOLTAGE]
        self._hold_raw = 0
        self._quick_stop_latched = False
        self._next_sync_t_s: float | None = None
        self._last: Feedback | None = None
        self._cycled_t_s: float | None = None  # when the last cycle went out: the loop's "alive" stamp
        self._stalled_s = 0.0  # the longest gap between cycles of the powered drive beyond loop_timeout
        # Several drives on one bus: the leader sends the one SYNC of each cycle, and its followers'
        # RPDOs before it; a follower's own cycles are the leader's.
        self.leader: CanopenServo | None = None
        self.followers: list[CanopenServo] = []
        self._staged: tuple[int, int, int] | None = (
            None  # a follower's next RPDO 1: controlword, target, offset
        )
        self._last_target_raw = 0  # the leader's last target: held in its followers' walks (position modes)

    @classmethod
    def from_rig_config(cls, config: RigConfig) -> CanopenServo:
        """The servo a rig config's `canopen:` section describes, limited by its `control:` section."""
        settings = CanopenSettings.from_rig_config(config).role_settings("axis")
        return cls(settings, DriveLimits.from_rig_config(config), 1.0 / config.sample_rate_hz)

    def follow(self, leader: CanopenServo) -> None:
        """Share the `leader`'s bus (connected, not booted yet): it sends the one SYNC of every cycle,
        this drive's RPDO just before it, and waits for both drives' TPDOs. Its host heartbeat vouches
        for this drive too (the same loop cycles both)."""
        if self.network is not None:
            raise RuntimeError(f"node {self.settings.node_id}: already connected")
        if leader.network is None:
            raise RuntimeError(f"node {leader.settings.node_id}: connect the leader first")
        self.leader = leader
        leader.followers.append(self)
        self._attach(leader.network)

    # --- connection and boot ----------------------------------------------------------------------

    def connect(self, bus: can.BusABC | None = None, log_path: Path | None = None) -> None:
        """Open the bus (or use `bus`), start the raw traffic log at `log_path` (.blf/.asc), if given."""
        if self.network is not None:
            raise RuntimeError(f"node {self.settings.node_id}: already connected")
        network = RecordedNetwork(bus if bus is not None else open_bus(self.settings))
        network.recorder.record_to(log_path)
        network.connect()
        self._attach(network)

    def _attach(self, network: RecordedNetwork) -> None:
        node = canopen.RemoteNode(self.settings.node_id, self.od)
        network.add_node(node)
        node.sdo.RESPONSE_TIMEOUT = self.settings.sdo_timeout_s
        node.nmt.add_heartbeat_callback(self._on_heartbeat)
        node.emcy.add_callback(self._on_emcy)
        node_id = self.settings.node_id
        for n, cob_id in enumerate((0x180 + node_id, 0x280 + node_id)):
            network.subscribe(cob_id, self._tpdo_callback(n))
        self.network, self.node = network, node

    def boot(self) -> None:
        """Reset the node, configure heartbeats, limits and feedback PDOs, start it (NMT OPERATIONAL)."""
        network, node = self._connected()
        if self.settings.reset_on_boot:
            self._booted.clear()
            self._nmt(NMT_RESET_NODE)
            if not self._booted.wait(self.settings.boot_timeout_s):
                timeout = self.settings.boot_timeout_s
                raise CanopenServoError(f"node {node.id}: no boot-up message within {timeout} s of NMT reset")
        else:
            self._nmt(NMT_PRE_OPERATIONAL)
        if self.watchdog == "none" and not self.settings.accept_drive_runs_on_if_host_dies:
            raise DriveSettingError(
                f"node {node.id}: the EDS has neither heartbeat consumer (0x1016) nor node guarding"
                " (0x100C/0x100D): the drive would run on if this host died; set"
                " canopen.accept_drive_runs_on_if_host_dies: true only if the lab accepts that"
            )
        if self._heartbeat is None and self.leader is None:
            # From a thread of this process: if it hangs or dies, the drive's consumer stops the drive.
            period_s = self.settings.host_heartbeat_ms / 1000.0
            cob_id = 0x700 + self.settings.host_node_id
            self._heartbeat = network.send_periodic(
                cob_id, HOST_HEARTBEAT_STATE, period_s, gate=self._loop_alive
            )
        self.scaling = resolve_scaling(self.settings.scaling, self.od, self._read_or_none)
        for note in self.scaling.notes:
            logger.warning("node %d: %s", node.id, note)
        self.modes = DriveModes.of(self.od, self._read_or_none)
        self._plan, self.mode, self.choice = None, None, None  # RPDO 1 is off until configure()
        self._last = None
        self._write(boot_plan(self.od, self.settings, self.limits, self.scaling, self.period_s))
        if self.watchdog == "node guarding" and self._guard is None:
            # Guarding requests (RTR) from this process: without them the drive's life guard trips.
            guard_s = guarding(self.settings)[0] / 1000.0
            guard_id = 0x700 + self.settings.node_id
            self._guard = network.send_periodic(guard_id, b"", guard_s, remote=True, gate=self._loop_alive)
        self._start_node()

    def choose(self, program: ControlMode) -> ModeChoice:
        """The drive mode a program runs in (`drivers.drive_modes`); DriveSettingError in one line naming
        what the drive offers when none can."""
        if program == ControlMode.VOLTAGE:
            raise DriveSettingError(
                f"node {self.settings.node_id}: a CiA 402 drive has no voltage mode; it offers {self.offer()}"
            )
        modes = self._modes()
        try:
            return modes.choose(program)
        except ModeUnavailableError as exc:
            raise DriveSettingError(f"node {self.settings.node_id}: {exc}") from None

    def choose_feedforward(self) -> ModeChoice:
        """The drive mode a position program with a model's torque runs in (`DriveModes.choose_feedforward`:
        CSP with 0x60B2, else CST); DriveSettingError in one line naming what the drive lacks."""
        try:
            return self._modes().choose_feedforward()
        except ModeUnavailableError as exc:
            raise DriveSettingError(f"node {self.settings.node_id}: {exc}") from None

    def choose_load(self) -> ModeChoice:
        """A load drive's mode (`DriveModes.choose_load`: a torque mode, else a velocity mode to brake by
        holding speed); DriveSettingError in one line naming what the drive offers."""
        try:
            return self._modes().choose_load()
        except ModeUnavailableError as exc:
            raise DriveSettingError(f"node {self.settings.node_id}: {exc}") from None

    def offer(self) -> str:
        """What the drive offers, in words (its modes and where that was read)."""
        return self._modes().offer()

    def configure(self, mode: OperationMode | ControlMode | ModeChoice) -> None:
        """Switch to a program's mode (`choose`), a choice made before (`choose_feedforward`) or a drive
        mode named directly: remap RPDO 1 (with 0x60B2 for a torque offset), set 0x6060, confirm it
        from 0x6061.

        The drive must not be OPERATION ENABLED: disable it first (a remap while powered is refused).
        """
        _network, node = self._connected()
        choice = self._choice(mode)
        op_mode = choice.mode
        if self._last is not None and self._last.state == State.OPERATION_ENABLED:
            raise RuntimeError(f"node {node.id}: disable the drive before switching to {op_mode.name}")
        self._nmt(NMT_PRE_OPERATIONAL)
        self._started_t_s = None
        offset = choice.torque_offset
        self._write(mode_plan(self.od, self.settings.node_id, op_mode, offset))
        tpdo1, tpdo2 = self._tpdo
        self._plan = PdoPlan(rpdo_layout(self.od, op_mode, offset), tpdo1, tpdo2, self.settings.node_id)
        self.bus_load = bus_load(self._bus_plans(), self.period_s, self.settings.bitrate)
        ids = [str(plan.node_id) for plan in self._bus_plans()]
        where = f"node {ids[0]}" if len(ids) == 1 else f"nodes {', '.join(ids)}"
        check_bus_load(self.bus_load, self.settings.bus_load_max, where)
        logger.info("node %d: %s", node.id, self.bus_load)
        self._target_range = declared_range(od_variable(self.od, *TARGET_OBJECT[op_mode]))
        self._offset_range = declared_range(od_variable(self.od, *TORQUE_OFFSET)) if offset else (0, 0)
        self.mode, self.choice = op_mode, choice
        logger.info("node %d: %s", node.id, choice)
        self._start_node()
        feedback = self._first_answer()
        self._hold_raw = self._hold_target(feedback)
        if "mode" in self._tpdo1_names:
            for _ in range(10):
                if feedback.mode == int(op_mode):
                    break
                feedback = self._exchange(self._controlword, self._hold_raw)
            else:
                raise CanopenServoError(
                    f"node {node.id}: mode {op_mode.name} not confirmed (0x6061 reads {feedback.mode})"
                )

    def _first_answer(self) -> Feedback:
        """The first cycle after NMT START: a drive may take a few ms before its PDOs run."""
        deadline = time.monotonic() + self.settings.boot_timeout_s
        while True:
            try:
                return self._exchange(self._controlword, 0)
            except SyncTimeoutError:
                if time.monotonic() > deadline:
                    raise

    def set_profile(self, acceleration_rad_s2: float, deceleration_rad_s2: float | None = None) -> None:
        """Profile velocity ramps (0x6083/0x6084) [rad/s²], for PV."""
        scaling = self._scaling()
        decel = deceleration_rad_s2 if deceleration_rad_s2 is not None else acceleration_rad_s2
        self._write(
            [
                SdoWrite(0x6083, 0, scaling.acceleration_raw(acceleration_rad_s2), "profile acceleration"),
                SdoWrite(0x6084, 0, scaling.acceleration_raw(decel), "profile deceleration"),
            ]
        )

    # --- the state machine ------------------------------------------------------------------------

    def enable(self, timeout_s: float = 1.0) -> Feedback:
        """Walk the drive to OPERATION ENABLED (holding position in CSP, zero otherwise).

        Clears a previous quick stop; a drive in FAULT is not reset here (`reset_fault()`).
        """
        self._plan_or_raise()
        self._quick_stop_latched = False
        self._stalled_s = 0.0
        feedback = self._walk_to(State.OPERATION_ENABLED, timeout_s)
        self._controlword = CONTROLWORD[Command.ENABLE_OPERATION]
        return feedback

    def disable(self, timeout_s: float = 1.0) -> Feedback:
        """Orderly stop: bring the speed to zero in velocity modes, then remove power (SWITCH ON DISABLED)."""
        self._plan_or_raise()
        if self.mode in (OperationMode.CYCLIC_SYNC_VELOCITY, OperationMode.PROFILE_VELOCITY):
            # Speed to zero first; position modes hold where they are as they are disabled.
            deadline = time.monotonic() + timeout_s
            feedback = self._exchange(self._controlword, 0)
            moving = abs(feedback.velocity_rad_s) > STANDSTILL_RAD_S
            while feedback.state == State.OPERATION_ENABLED and moving and time.monotonic() < deadline:
                feedback = self._exchange(self._controlword, 0)
                moving = abs(feedback.velocity_rad_s) > STANDSTILL_RAD_S
        feedback = self._walk_to(State.SWITCH_ON_DISABLED, timeout_s)
        self._controlword = CONTROLWORD[Command.DISABLE_VOLTAGE]
        return feedback

    def quick_stop(self) -> None:
        """Defensive stop, from any thread, in any state, any number of times; never raises.

        Latches the quick-stop controlword (every later cycle sends it until `enable()`), sees a cycle
        carry it, and sends NMT STOP when the drive does not confirm.
        """
        self._quick_stop_latched = True
        followers = list(self.followers)
        for follower in followers:  # every drive of the bus, in the same next SYNC
            follower._quick_stop_latched = True
        confirmed = False
        try:
            confirmed = self._plan is not None and self._confirm_quick_stop()
        except Exception as exc:  # the defensive path must go on to NMT STOP whatever failed here
            logger.warning("quick stop: controlword not confirmed: %s", exc)
        stop = [self] if not confirmed else []
        stop += [f for f in followers if f._last is not None and f._last.state == State.OPERATION_ENABLED]
        for servo in stop:
            if servo.node is None:
                continue
            try:
                servo.node.nmt.send_command(NMT_STOP)
            except Exception as exc:  # a dead bus: nothing more this host can do
                logger.error("quick stop: NMT STOP not sent: %s", exc)

    def _confirm_quick_stop(self) -> bool:
        """Send the quick stop in a cycle of our own or, while another thread is cycling (it holds the
        bus and sends the latched controlword in its next cycle), see one of its answers confirm it."""
        deadline = time.monotonic() + self.sync_timeout_s + 2 * self.period_s
        seen = self._last
        while time.monotonic() < deadline:
            if self._cycle_lock.acquire(timeout=self.period_s):
                try:
                    stop = CONTROLWORD[Command.QUICK_STOP]
                    return (
                        self._exchange_locked(stop, self._hold_raw, pace=False).state
                        != State.OPERATION_ENABLED
                    )
                finally:
                    self._cycle_lock.release()
            last = self._last
            if last is not seen and last is not None and last.state != State.OPERATION_ENABLED:
                return True
        return False

    def reset_fault(self, timeout_s: float = 1.0) -> Feedback:
        """Fault reset (rising edge of controlword bit 7) to SWITCH ON DISABLED; clears the EMCY list."""
        self._plan_or_raise()
        feedback = self._exchange(CONTROLWORD[Command.DISABLE_VOLTAGE], self._hold_raw)
        deadline = time.monotonic() + timeout_s
        while feedback.faulted:
            if time.monotonic() > deadline:
                faults = "; ".join(self.faults())
                raise DriveFaultError(f"node {self.settings.node_id}: fault not reset: {faults}")
            feedback = self._exchange(CONTROLWORD[Command.FAULT_RESET], self._hold_raw)
        self._controlword = CONTROLWORD[Command.DISABLE_VOLTAGE]
        feedback = self._exchange(self._controlword, self._hold_raw)
        with self._emcy_lock:
            self._emcy_active.clear()
        return feedback

    # --- the cycle --------------------------------------------------------------------------------

    def cycle(self, target: float, torque_offset_nm: float = 0.0) -> Feedback:
        """One control cycle: the target (SI, per mode) in RPDO 1, one SYNC, the answering TPDOs.

        CST: motor current [A] (sent as torque K_m·i in ‰ of rated torque); CSV/PV: motor speed
        [rad/s]; CSP: motor angle [rad]. `torque_offset_nm` goes in 0x60B2 (‰ of rated torque, within
        its declared range) where the mode was configured with it, and must be 0 otherwise. Paced to
        the period unless `pace` is off. Raises SyncTimeoutError when the drive does not answer within
        `sync_timeout_s`.
        """
        self._plan_or_raise()
        if self._quick_stop_latched:
            return self._exchange(CONTROLWORD[Command.QUICK_STOP], self._hold_raw)
        offset_raw = 0
        if torque_offset_nm:
            if self.choice is None or not self.choice.torque_offset:
                node = self.settings.node_id
                raise RuntimeError(f"node {node}: a torque offset needs a mode configured with it")
            offset_raw = _clamp(self._scaling().torque_permille(torque_offset_nm), self._offset_range)
        return self._exchange(self._controlword, self._target_raw(target), offset_raw)

    def _target_raw(self, target: float) -> int:
        """The target in the drive's units, within the target object's declared range."""
        scaling, mode = self._scaling(), self.mode
        if mode in TORQUE_MODES:
            raw = scaling.torque_permille(target * scaling.torque_constant_nm_per_a)
        elif mode in POSITION_MODES:
            if self.choice is not None and self.choice.integrates_speed:
                self._integrated_rad += target * self.period_s
                target = self._integrated_rad
            raw = scaling.position_raw(target)
        else:
            raw = scaling.velocity_raw(target)
        return _clamp(raw, self._target_range)

    def _hold_target(self, feedback: Feedback) -> int:
        """The target that asks for no change: where the motor is in position modes, zero otherwise."""
        if self.mode in POSITION_MODES:
            self._integrated_rad = feedback.position_rad
            return _clamp(self._scaling().position_raw(feedback.position_rad), self._target_range)
        return 0

    def _walk_to(self, target: State, timeout_s: float) -> Feedback:
        """Send the table's commands towards `target`, one cycle each, until the statusword shows it.

        The first command follows the last state seen; every step is confirmed by a fresh answer.
        A drive in FAULT is already without torque: walking to SWITCH ON DISABLED leaves it there
        (`reset_fault()` is the way out), walking elsewhere raises DriveFaultError.
        """
        deadline = time.monotonic() + timeout_s
        controlword = self._controlword
        last = self._last
        while True:
            state = last.state if last is not None else None
            if last is not None and last.faulted:
                if target == State.SWITCH_ON_DISABLED:
                    return last
                raise DriveFaultError(f"node {self.settings.node_id} is in FAULT: {'; '.join(self.faults())}")
            command = command_towards(state, target) if state is not None else None
            if command is not None:
                controlword = CONTROLWORD[command]
            if last is not None:
                self._hold_raw = self._hold_target(last)
            feedback = self._exchange(controlword, self._hold_raw)
            if feedback.state == target:
                self._controlword = controlword
                return feedback
            if time.monotonic() > deadline:
                raise CanopenServoError(
                    f"node {self.settings.node_id}: still {feedback.state} after {timeout_s} s"
                    f" (statusword 0x{feedback.statusword:04X}) on the way to {target}"
                )
            last = feedback

    def _exchange(self, controlword: int, target_raw: int, offset_raw: int = 0) -> Feedback:
        with self._cycle_lock:
            return self._exchange_locked(controlword, target_raw, self.settings.pace, offset_raw)

    def _exchange_locked(
        self, controlword: int, target_raw: int, pace: bool, offset_raw: int = 0
    ) -> Feedback:
        """One RPDO 1 + SYNC and its answer. The torque offset (0 in walks and stops: the drive's own
        loops alone) goes only where RPDO 1 maps it. A follower's goes out in its leader's next cycle,
        the leader holding its own last command (its hold target, outside a segment)."""
        leader = self.leader
        if leader is not None:
            self._staged = (controlword, target_raw, offset_raw)
            if leader._plan is None:
                raise RuntimeError(
                    f"node {leader.settings.node_id}: configure the leader before its followers"
                )
            # The leader holds: its quick stop if latched, where it is in position modes, no torque or
            # speed otherwise (a follower's walk comes between segments).
            stop = leader._quick_stop_latched
            held = leader._last_target_raw if leader.mode in POSITION_MODES else leader._hold_raw
            leader._exchange(CONTROLWORD[Command.QUICK_STOP] if stop else leader._controlword, held)
            last = self._last
            assert last is not None  # the leader's exchange waited for this drive's answer
            return last
        network, _node = self._connected()
        if pace:
            self._wait_for_period()
        self._last_target_raw = target_raw
        payload = self._rpdo_payload(controlword, target_raw, offset_raw)
        plan = self._plan_or_raise()
        sent = [(follower, follower._stage_payload()) for follower in self.followers]
        with self._rx:
            before = list(self._tpdo_counts)
        frames = [(plan.rpdo_cob_id, payload)]
        frames += [(cob_id, data) for _follower, (cob_id, data, _counts) in sent if data is not None]
        frames.append((SYNC_COB_ID, b""))
        try:
            t_sync = network.send_messages(frames)  # one write where the bus allows: the same frames
        except can.CanError as exc:  # the bus failed under a working drive: a fault, not a setting
            raise CanopenServoError(f"node {self.settings.node_id}: cycle not sent: {exc}") from exc
        self._stamp_cycle(t_sync)
        for follower, _sent in sent:
            follower._stamp_cycle(t_sync)
        feedback = self._answer(network, t_sync, before)
        for follower, (_cob_id, data, counts) in sent:
            if data is not None:
                follower._answer(network, t_sync, counts)
        return feedback

    def _rpdo_payload(self, controlword: int, target_raw: int, offset_raw: int) -> bytes:
        plan = self._plan_or_raise()
        if self.mode == OperationMode.INTERPOLATED_POSITION and controlword & 0x0F == 0x0F:
            controlword |= CW_ENABLE_IP_BIT  # interpolation runs while enabled
        values = (controlword, target_raw, offset_raw)[: len(plan.rpdo.entries)]
        return bytes(plan.rpdo.encode(values))

    def _stage_payload(self) -> tuple[int, bytes | None, list[int]]:
        """A follower's RPDO 1 for the leader's next SYNC (None before it is configured: it is not
        waited for then), and its TPDO counts before it."""
        with self._rx:
            counts = list(self._tpdo_counts)
        if self._plan is None:
            return 0, None, counts
        if self._staged is None:
            self._staged = (self._controlword, self._hold_raw, 0)
        controlword, target_raw, offset_raw = self._staged
        if self._quick_stop_latched:
            controlword = CONTROLWORD[Command.QUICK_STOP]
        return self._plan.rpdo_cob_id, self._rpdo_payload(controlword, target_raw, offset_raw), counts

    def stage(self, target: float) -> None:
        """A follower's target (SI, as `cycle`) for the leader's next cycle; it holds it until staged
        again. Its answer is `last_feedback` once the leader's cycle is back."""
        self._plan_or_raise()
        self._staged = (self._controlword, self._target_raw(target), 0)

    def _answer(self, network: RecordedNetwork, t_sync: float, before: list[int]) -> Feedback:
        """Wait for this drive's TPDOs answering the SYNC sent at `t_sync`."""
        with self._rx:
            self._awaited = before  # the receive thread wakes this one only once all have come
            try:
                answered = self._rx.wait_for(
                    lambda: all(c > b for c, b in zip(self._tpdo_counts, before, strict=True)),
                    timeout=self.sync_timeout_s,
                )
            finally:
                self._awaited = None
            self._silent = not answered
            if not answered:
                failure = network.receive_failure.error
                why = f"CAN receive failed: {failure}" if failure is not None else None
                raise SyncTimeoutError(
                    f"node {self.settings.node_id}: no TPDO answered the SYNC within"
                    f" {self.sync_timeout_s * 1e3:.1f} ms"
                    f" ({why or '; '.join(self.faults()) or 'no fault reported'})"
                )
            values1, values2 = self._tpdo_values
            t_answer = max(self._tpdo_t_s)
        assert values1 is not None and values2 is not None  # set before the counts moved
        feedback = self._feedback(t_sync, t_answer - t_sync, values1, values2)
        self._last = feedback
        return feedback

    def _bus_plans(self) -> list[PdoPlan]:
        """The PDO plans of every drive on this bus configured so far (this one's included)."""
        head = self.leader if self.leader is not None else self
        return [s._plan for s in (head, *head.followers) if s._plan is not None]

    # --- the loop's watchdog ------------------------------------------------------------------------

    def _powered(self) -> bool:
        """Whether the host holds the drive in OPERATION ENABLED (and has not latched a quick stop)."""
        return self._controlword == CONTROLWORD[Command.ENABLE_OPERATION] and not self._quick_stop_latched

    def _loop_alive(self) -> bool:
        """The host heartbeat's gate: always open for an unpowered drive; for a powered one, only while
        the control loop has sent a cycle within `loop_timeout_ms` (its followers' too: one heartbeat
        vouches for every drive the loop cycles)."""
        return self._own_loop_alive() and all(f._own_loop_alive() for f in self.followers)

    def _own_loop_alive(self) -> bool:
        cycled = self._cycled_t_s
        if not self._powered() or cycled is None:
            return True
        return time.monotonic() - cycled <= self.settings.loop_timeout_ms / 1000.0

    def _stamp_cycle(self, t_s: float) -> None:
        """The loop is alive at `t_s`; a gap beyond `loop_timeout_ms` under power is kept for `faults()`."""
        before, self._cycled_t_s = self._cycled_t_s, t_s
        if before is not None and self._powered() and t_s - before > self.settings.loop_timeout_ms / 1000.0:
            self._stalled_s = max(self._stalled_s, t_s - before)
            logger.error(
                "node %d: control loop stalled %.0f ms under power",
                self.settings.node_id,
                (t_s - before) * 1e3,
            )

    def _wait_for_period(self) -> None:
        now = time.monotonic()
        if self._next_sync_t_s is None or now - self._next_sync_t_s > self.period_s:
            self._next_sync_t_s = now  # first cycle, or late by a period: restart the grid, no burst
        elif self._next_sync_t_s > now:
            time.sleep(self._next_sync_t_s - now)
        self._next_sync_t_s += self.period_s

    def _feedback(
        self, t_sync: float, latency_s: float, values1: tuple[int, ...], values2: tuple[int, ...]
    ) -> Feedback:
        scaling = self._scaling()
        at = self._tpdo1_at
        statusword_at, torque_at, current_at = at["statusword"], at["torque"], at["current"]
        mode_at = at["mode"]
        assert statusword_at is not None  # TPDO 1 always maps the statusword (tpdo_layouts)
        statusword = values1[statusword_at]
        torque_nm = scaling.torque_nm(values1[torque_at]) if torque_at is not None else math.nan
        if current_at is not None and scaling.rated_current_a is not None:
            current_a = scaling.current_a(values1[current_at])
        else:
            current_a = torque_nm / scaling.torque_constant_nm_per_a
        return Feedback(
            t_s=t_sync,
            latency_s=latency_s,
            statusword=statusword,
            state=decode_statusword(statusword),
            mode=values1[mode_at] if mode_at is not None else None,
            position_rad=scaling.position_rad(values2[0]),
            velocity_rad_s=scaling.velocity_rad_s(values2[1]),
            torque_nm=torque_nm,
            current_a=current_a,
        )

    # --- health -----------------------------------------------------------------------------------

    def faults(self) -> list[str]:
        """What is wrong now: active EMCYs, a FAULT state, a lost or non-operational drive."""
        with self._emcy_lock:
            faults = list(self._emcy_active)
        last = self._last
        if last is not None and last.faulted:
            faults.append(f"drive in {last.state} (statusword 0x{last.statusword:04X})")
        if self._stalled_s:
            faults.append(
                f"host control loop stalled for {self._stalled_s * 1e3:.0f} ms under power (its heartbeat"
                f" withheld after loop_timeout_ms {self.settings.loop_timeout_ms})"
            )
        heard = self._drive_heartbeat_t_s
        if heard is not None:
            silent_ms = (time.monotonic() - heard) * 1e3
            if silent_ms > self.settings.drive_heartbeat_timeout_ms:
                faults.append(f"drive heartbeat lost: none for {silent_ms:.0f} ms")
            elif self._started_t_s is not None and heard > self._started_t_s and not self._operational():
                state = canopen.nmt.NMT_STATES.get(self._drive_nmt_state or 0, str(self._drive_nmt_state))
                faults.append(f"drive NMT state is {state}")
        return faults

    @property
    def last_feedback(self) -> Feedback | None:
        return self._last

    @property
    def log_path(self) -> Path | None:
        """Where the raw CAN traffic is being written (None: not recorded)."""
        return self.network.recorder.path if self.network is not None else None

    def record_to(self, path: Path | None) -> None:
        """Start a new raw CAN log (.blf or .asc) for the next run; None stops recording."""
        network, _node = self._connected()
        network.recorder.record_to(path)

    def close(self) -> None:
        """Stop the drive if powered, release its heartbeat watch, close the log and the bus."""
        if self.network is None:
            return
        if self._last is not None and self._last.state == State.OPERATION_ENABLED:
            self.quick_stop()
        node = self.node
        watch = {"heartbeat consumer": (0x1016, 1), "node guarding": (0x100C, 0)}.get(self.watchdog)
        if node is not None and watch is not None and self._heartbeat is not None and not self._silent:
            try:  # let the drive stop watching a host that is leaving on purpose
                node.sdo.download(*watch, od_variable(self.od, *watch).encode_raw(0))
            except (SdoAbortedError, SdoCommunicationError, can.CanError) as exc:
                logger.warning("close: %s of node %d not cleared: %s", self.watchdog, node.id, exc)
        for frame in (self._guard, self._heartbeat):
            if frame is not None:
                frame.stop()
        self._guard, self._heartbeat = None, None
        if self.leader is not None:  # the bus is the leader's, closed with it
            self.leader.followers.remove(self)
            self.network, self.node, self.leader = None, None, None
            return
        for follower in list(self.followers):
            follower.close()
        try:
            self.network.disconnect()  # the bus is shut down before canopen re-raises a receive error
        except can.CanError as exc:  # the bus died under a working drive: the cycle has already told
            logger.warning("close: node %d: the bus had failed: %s", self.settings.node_id, exc)
        self.network, self.node = None, None

    def __enter__(self) -> CanopenServo:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- plumbing ---------------------------------------------------------------------------------

    def _tpdo_callback(self, n: int) -> Callable[[int, bytearray, float], None]:
        layout = self._tpdo[n]

        def on_tpdo(can_id: int, data: bytearray, timestamp: float) -> None:
            values = layout.decode(data)
            with self._rx:
                self._tpdo_values[n] = values
                self._tpdo_t_s[n] = time.monotonic()
                counts = self._tpdo_counts
                counts[n] += 1
                awaited = self._awaited
                if awaited is None or (counts[0] > awaited[0] and counts[1] > awaited[1]):
                    self._rx.notify_all()  # not before the answer is whole: one wake-up, not one a TPDO

        return on_tpdo

    def _on_heartbeat(self, state: int) -> None:
        self._drive_heartbeat_t_s = time.monotonic()
        self._drive_nmt_state = state
        if state == 0:
            self._booted.set()

    def _on_emcy(self, entry: EmcyError) -> None:
        with self._emcy_lock:
            if entry.code == 0:
                self._emcy_active.clear()
            else:
                self._emcy_active.append(
                    f"EMCY 0x{entry.code:04X} ({entry.get_desc()}), error register 0x{entry.register:02X}"
                )

    def _start_node(self) -> None:
        self._nmt(NMT_START)
        self._started_t_s = time.monotonic()

    def _nmt(self, command: int) -> None:
        _network, node = self._connected()
        try:
            node.nmt.send_command(command)
        except can.CanError as exc:
            raise CanopenServoError(f"node {node.id}: NMT command 0x{command:02X} not sent: {exc}") from exc

    def _operational(self) -> bool:
        return self._drive_nmt_state == NMT_OPERATIONAL_STATE

    def _read_or_none(self, index: int, subindex: int) -> int | None:
        """The object's value, None when the drive refuses the read (it holds none)."""
        try:
            return self._read(index, subindex)
        except DriveSettingError:
            return None

    def _read(self, index: int, subindex: int) -> int:
        _network, node = self._connected()
        where = f"node {node.id}: SDO read of 0x{index:04X}:{subindex:02X}"
        try:
            data = node.sdo.upload(index, subindex)
        except SdoAbortedError as exc:  # the drive has not what its EDS, or the rig file, says it has
            raise DriveSettingError(f"{where} refused: {exc}") from None
        except (SdoCommunicationError, can.CanError) as exc:
            raise CanopenServoError(f"{where} failed: {exc}") from exc
        return int(od_variable(self.od, index, subindex).decode_raw(data))

    def _write(self, plan: list[SdoWrite]) -> None:
        _network, node = self._connected()
        problems = check_plan(self.od, plan)  # before the first write: no drive left half configured
        if problems:
            more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
            raise DriveSettingError(
                f"node {node.id}: the rig file asks what the drive's EDS refuses: {problems[0]}{more}"
            )
        for write in plan:
            try:
                node.sdo.download(write.index, write.subindex, write.data(self.od))
            except SdoAbortedError as exc:  # a value of the rig file the drive cannot take
                raise DriveSettingError(f"node {node.id}: SDO write {write} refused: {exc}") from None
            except (SdoCommunicationError, can.CanError) as exc:
                raise CanopenServoError(f"node {node.id}: SDO write {write} failed: {exc}") from exc

    def _connected(self) -> tuple[RecordedNetwork, canopen.RemoteNode]:
        if self.network is None or self.node is None:
            raise RuntimeError(f"node {self.settings.node_id}: not connected: call connect() first")
        return self.network, self.node

    def _plan_or_raise(self) -> PdoPlan:
        if self._plan is None:
            raise RuntimeError(f"node {self.settings.node_id}: no mode set: call configure() first")
        return self._plan

    def _modes(self) -> DriveModes:
        if self.modes is None:
            raise RuntimeError(f"node {self.settings.node_id}: not booted: call boot() first")
        return self.modes

    def _choice(self, mode: OperationMode | ControlMode | ModeChoice) -> ModeChoice:
        if isinstance(mode, ModeChoice):
            return mode
        if isinstance(mode, ControlMode):
            return self.choose(mode)
        program = PROGRAM_OF.get(mode)
        if program is None:
            raise DriveSettingError(f"configure: {mode.name} takes no target every cycle: not driven here")
        return ModeChoice(program, mode, "named by the caller")

    def _scaling(self) -> Scaling:
        if self.scaling is None:
            raise RuntimeError(f"node {self.settings.node_id}: not booted: call boot() first")
        return self.scaling


def _clamp(value: int, bounds: tuple[int, int]) -> int:
    return min(max(value, bounds[0]), bounds[1])
