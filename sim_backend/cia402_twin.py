"""A simulated CiA 402 servo drive on a CAN bus: the plant model behind a canopen `LocalNode`.

It wraps `SimulatedDrive` (the plant, the drive's loops, sensors and envelope) and steps it once per
SYNC, so a master sees a drive: NMT boot-up and heartbeat, SDO access to its object dictionary (its
own EDS, `configs/eds/hdrig-sim-drive.eds`, or a vendor's), RPDOs applied and TPDOs answered on SYNC,
the CiA 402 state machine of `drivers.cia402`, EMCY and FAULT on overcurrent, following error and the
other envelope limits, and on losing the host's heartbeat (0x1016).

The torque offset 0x60B2 (‰ of 0x6076) is added to the torque demand in CST, and in CSP while a master
maps it into an RPDO: the position target and the offset then go to the simulated drive as a
feed-forward track (`model.feedforward`), as the simulated rig's compensated segments do, whose
velocity loop takes it as a current offset. (In CSV the simulated drive's speed loop takes none.)

What canopen 2.4's `LocalNode` leaves to us is done here: it neither copies RPDO data into its object
dictionary nor sends TPDOs on SYNC, and it does not watch heartbeats.

Time is virtual: each SYNC advances the plant by the communication cycle period (0x1006; one rig
period when 0x1006 is 0), so the twin runs as fast as the master sends SYNC. Everything happens on the
bus's receive thread, except the heartbeat watch (one thread) and the heartbeat producer (python-can's).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Final, NamedTuple, cast

import can
import canopen
import numpy as np
from canopen.objectdictionary import INTEGER_TYPES, ODVariable
from canopen.sdo import SdoAbortedError

from drivers.can_bus import RecordedNetwork
from drivers.canopen_config import (
    EDS_DIR,
    FACTOR_OBJECTS,
    PDO_INVALID,
    RPDO_COMM,
    RPDO_MAP,
    TPDO_COMM,
    TPDO_MAP,
    CanopenConfigError,
    CanopenSettings,
    FactorGroup,
    is_mapping_object,
)
from drivers.cia402 import (
    CW_ENABLE_IP_BIT,
    EMCY_COMMUNICATION,
    EMCY_FOLLOWING_ERROR,
    EMCY_HEARTBEAT,
    EMCY_OVERCURRENT,
    EMCY_OVERVOLTAGE,
    EMCY_POSITION_LIMIT,
    EMCY_SPEED,
    SUPPORTED_MODE_BIT,
    SW_MODE_BIT12,
    SW_MODE_BIT13,
    SW_TARGET_REACHED,
    TARGET_OBJECT,
    Command,
    OperationMode,
    State,
    decode_controlword,
    error_register_for,
    next_state,
    statusword_for,
)
from drivers.drive_modes import TORQUE_OFFSET
from drivers.pdo_layout import PdoEntry, PdoLayout, od_variable
from model.feedforward import FF_THETA, FF_TORQUE, N_FF_COLUMNS, FeedForwardTrack
from model.params import HarmonicDriveModel
from model.plant import Plant
from model.registry import X
from rig.config import RigConfig
from rig.interface import SAMPLE_COLUMNS, ControlMode
from rig.safety import (
    ABORT_CURRENT,
    ABORT_FOLLOWING,
    ABORT_TRAVEL,
    ABORT_VELOCITY,
    ABORT_VOLTAGE,
    NO_ABORT,
)
from sim_backend.daq_twin import PlantStateSource
from sim_backend.inprocess import TemperatureProbes, TorqueTransducers
from sim_backend.simulated_drive import (
    T_F_L,
    T_F_M,
    T_T_S,
    T_TAU_EXT,
    T_TEMP_GEAR,
    T_TEMP_MOTOR,
    SimulatedDrive,
)

logger = logging.getLogger(__name__)

TWIN_EDS: Final = EDS_DIR / "hdrig-sim-drive.eds"

EMCY_FOR_ABORT: Final = {
    ABORT_CURRENT: EMCY_OVERCURRENT,
    ABORT_VOLTAGE: EMCY_OVERVOLTAGE,
    ABORT_VELOCITY: EMCY_SPEED,
    ABORT_TRAVEL: EMCY_POSITION_LIMIT,
    ABORT_FOLLOWING: EMCY_FOLLOWING_ERROR,
}
"""The emergency code a breach of the drive's envelope sends."""

NMT_OPERATIONAL, NMT_STOPPED = "OPERATIONAL", "STOPPED"
AMBIENT_C: Final = 25.0
"""The temperatures a plant without a thermal section reads: a room's, steady [°C]."""
LOAD_COB_ID: Final = 0x6E0
"""A sim-only frame (unused in CiA 301's predefined set): the load torque τ_ext [N·m] as a little-endian
float64, applied from the next SYNC. A host in another process sets the load with it."""
WATCH_PERIOD_S: Final = 0.005  # heartbeat consumer resolution
WATCH_STALLED_S: Final = 0.1
"""A watch wake-up this late means the watch itself was held: about 10 × the p99 lateness of a 1 ms
sleep with both cores busy (figures: docs/BENCHMARKS.md, "Figures behind design choices in the code"),
so a starved but running twin still judges."""
STANDSTILL_RAD_S: Final = 0.5  # a quick stop ends, PV reports zero speed, below this [rad/s]
PV_REACHED_RAD_S: Final = 2.0  # PV target reached within this [rad/s]
_INT16, _INT32 = (1 << 15) - 1, (1 << 31) - 1
_MODES: Final = {int(m): m for m in OperationMode}  # a dict look-up costs less than the enum's call


_NO_DATA: Final[dict[int, bytes]] = {}
_ZERO_SAMPLE: Final = dict.fromkeys(SAMPLE_COLUMNS, 0.0)
BRAKE_BANDWIDTH_HZ: Final = 5.0
"""A load twin's speed loop in a velocity mode: well under the seed's gear resonance (~13 Hz: K_s with J_l
and the motor's reflected inertia), so the brake holds the output without exciting it."""


class _Codec(NamedTuple):
    """An object's variable and the struct functions that stand for its decode_raw / encode_raw."""

    var: ODVariable
    pack: Callable[..., bytes] | None
    unpack: Callable[[bytes], tuple[int, ...]] | None
    size: int
    """Bytes of a value the struct unpacks."""
    low: float
    high: float


@dataclass
class _Pdo:
    cob_id: int
    transmission: int
    layout: PdoLayout


class _HeartbeatWatch(can.Listener):
    """The time each node's heartbeat was last heard, and node guarding requests to this node (canopen's
    listener drops remote frames); fed by the bus's receive thread."""

    def __init__(self, node_id: int, on_guard: Callable[[], None]) -> None:
        self.heard_s: dict[int, float] = {}
        self.guarded_s: float | None = None
        self.guard_cob_id = 0x700 + node_id
        self._on_guard = on_guard

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_remote_frame:
            if msg.arbitration_id == self.guard_cob_id:
                self.guarded_s = time.monotonic()
                self._on_guard()
        elif 0x701 <= msg.arbitration_id <= 0x77F and len(msg.data) == 1:
            self.heard_s[msg.arbitration_id - 0x700] = time.monotonic()


class Cia402Twin:
    """A CiA 402 drive around the plant, on its own connection to the bus; `close()` ends it all."""

    def __init__(
        self,
        bus: can.BusABC,
        node_id: int,
        model: HarmonicDriveModel,
        config: RigConfig,
        eds_path: Path = TWIN_EDS,
        rated_current_a: float = 5.0,
        network: RecordedNetwork | None = None,
    ) -> None:
        """`bus` becomes the twin's (closed by `close()`). `rated_current_a` is used when the EDS gives
        no motor rated current (0x6075). With `network` (another twin's, on the same bus), the twin
        shares it instead (`bus` unused) and takes SYNCs from its owner (`LoadTwin`)."""
        self.model = model
        self.config = config
        self.plant = Plant(model)
        self.drive = SimulatedDrive(self.plant, config)
        self.drive.record_truth(True)  # the shaft torque and temperatures the DAQ's analog inputs read
        self.measured = PlantStateSource(self.plant)
        """The plant's state after each SYNC, by the host time the SYNC was taken: a DAQ twin's source."""
        # Load the compiled loop now, not on the first SYNC: a master would wait for it and time out.
        SimulatedDrive(Plant(model), config).run(ControlMode.CURRENT, np.zeros(1), np.zeros(1), 0.0)
        self.period_s = 1.0 / config.sample_rate_hz
        # The bench's sensors as the simulated rig has them (its plant is the gear's own: no load rotor).
        self._transducers = TorqueTransducers(config, model, model)
        probes = TemperatureProbes(config, np.full(2, AMBIENT_C))
        lag_s = config.sensors.temperature_lag_s
        self._probe_alpha = 1.0 - math.exp(-self.period_s / lag_s) if lag_s > 0 else 1.0
        self._probe_c: list[float] | None = None  # winding, gear: from the first reading's temperatures
        self._torque_noise = _NoiseStream(self._transducers.rng)
        self._temp_noise = _NoiseStream(probes.rng)
        self.tau_ext_nm = 0.0
        """Load torque on the output during the next cycles [N·m], as the rig's tau_ext."""
        self.t_s = 0.0
        self.last_sample: dict[str, float] = {}
        self.on_sample: Callable[[dict[str, float]], None] | None = None
        """Given `last_sample` after each SYNC's step, before its TPDOs go out (the twins' process hands
        its plant log to the host with it: the host, answered, finds the sample already there)."""
        self.state = State.NOT_READY_TO_SWITCH_ON
        self._rated_current_default_a = rated_current_a
        self._lock = threading.RLock()
        self._closing = threading.Event()
        self._vars: dict[tuple[int, int], ODVariable] = {}
        self._codecs: dict[tuple[int, int], _Codec] = {}
        self._decoded: dict[tuple[int, int], tuple[bytes | None, int]] = {}  # (stored bytes, value)
        self._absent: dict[tuple[int, int], tuple[object, ...]] = {}  # lacking: the KeyError's args
        self._eds_values: dict[tuple[int, int], bytes] = {}  # of objects with no value stored
        self._rpdos: dict[int, _Pdo] = {}
        self._tpdos: list[_Pdo] = []
        self._pdos_stale = True
        self._offset_mapped = False  # a master drives 0x60B2 through an RPDO
        self._pending: dict[int, bytes] = {}
        self._applying_sync_rpdos = False
        self._tpdo_sent: dict[int, bytes] = {}
        self._sync_count = 0
        self._controlword = 0
        self._position_target_rad: float | None = None
        self._pv_reference_rad_s = 0.0
        self._fault_bits = 0
        self._lost: set[int] = set()
        self._guard_lost = False
        self._guard_toggle = 0
        self._supported_bits = 0
        self._torque_reference_permille = 0.0  # profile torque: the ramped target
        self._units: tuple[float, float, float] | None = None  # per motor rad, rad/s, rad/s²
        self.followers: list[LoadTwin] = []
        """Twins on this one's network that take its SYNCs: their torque before its step, their
        answers after it."""
        self._owns_network = network is None

        self.network = network if network is not None else RecordedNetwork(bus)
        self._watch = _HeartbeatWatch(node_id, self._answer_guard)
        cast(list[can.Listener], self.network.listeners).append(self._watch)
        self.node = canopen.LocalNode(node_id, str(eds_path))
        self.network.add_node(self.node)
        self.node.add_write_callback(self._on_write)
        self.network.subscribe(0, self._on_nmt)
        self._sync_cob_id = self._get(0x1005) & 0x7FF if self._has(0x1005) else 0x080
        if self._owns_network:
            self.network.subscribe(self._sync_cob_id, self._on_sync)
            self.network.subscribe(LOAD_COB_ID, self._on_load)
        self._reset_application()
        if self._owns_network:
            self.network.connect()
        self._boot()
        self._watch_thread = threading.Thread(
            target=self._watch_heartbeats, name=f"twin {node_id} heartbeat watch", daemon=True
        )
        self._watch_thread.start()

    # --- object dictionary access -----------------------------------------------------------------

    def _var(self, index: int, subindex: int = 0) -> ODVariable:
        key = (index, subindex)
        var = self._vars.get(key)
        if var is None:  # looked up once: the dictionary never changes
            if key in self._absent:
                raise KeyError(*self._absent[key])  # the same error, without the look-up (read each SYNC)
            try:
                var = self._vars[key] = od_variable(self.node.object_dictionary, index, subindex)
            except KeyError as exc:
                self._absent[key] = exc.args
                raise
        return var

    def _has(self, index: int, subindex: int = 0) -> bool:
        try:
            self._var(index, subindex)
        except KeyError:
            return False
        return True

    def _codec(self, index: int, subindex: int) -> _Codec:
        """The object's variable and, for an integer one, its struct's pack and unpack and the range
        `encode_raw` warns outside of; KeyError when the dictionary lacks it. Looked up once."""
        codec = self._codecs.get((index, subindex))
        if codec is None:
            var = self._var(index, subindex)
            packing = var.STRUCT_TYPES.get(var.data_type) if var.data_type in INTEGER_TYPES else None
            low = var.min if var.min is not None else -math.inf
            high = var.max if var.max is not None else math.inf
            if packing is None:
                codec = _Codec(var, None, None, 0, low, high)
            else:
                codec = _Codec(var, packing.pack, packing.unpack, packing.size, low, high)
            self._codecs[index, subindex] = codec
        return codec

    def _get(self, index: int, subindex: int = 0) -> int:
        # What LocalNode.get_data returns (it has no read callbacks here) without its look-ups, as each
        # SYNC reads ~20 objects: the stored value, else the EDS's value or default, which never change;
        # decoded by the variable's struct, as decode_raw does for integers, without its type tests.
        # The value decoded last is kept with the very bytes it came from: stored bytes never change,
        # so while the store holds that same object the value stands (writes store new objects).
        key = (index, subindex)
        data = self.node.data_store.get(index, _NO_DATA).get(subindex)
        decoded = self._decoded.get(key)
        if decoded is not None and decoded[0] is data:
            return decoded[1]
        codec = self._codecs.get(key) or self._codec(index, subindex)  # KeyError: none
        stored = data
        if data is None:
            data = self._eds_values.get(key)
            if data is None:
                data = self.node.get_data(index, subindex)  # an SDO abort when the EDS has no value
                self._eds_values[key] = data
        if codec.unpack is not None and len(data) == codec.size:
            value = int(codec.unpack(data)[0])
        else:
            value = int(codec.var.decode_raw(data))  # its own error for a value of the wrong size
        self._decoded[key] = (stored, value)
        return value

    def _store(self, index: int, subindex: int, value: int) -> None:
        """Set an object as the drive itself does: no write callbacks, no access check."""
        codec = self._codecs.get((index, subindex))
        if codec is None:
            if not self._has(index, subindex):
                return
            codec = self._codec(index, subindex)
        if codec.pack is not None and codec.low <= value <= codec.high:
            data = codec.pack(int(value))  # as encode_raw, which only warns outside the range
        else:
            data = codec.var.encode_raw(value)
        store = self.node.data_store
        values = store.get(index)
        if values is None:
            values = store[index] = {}
        values[subindex] = data

    def _get_or(self, index: int, default: int, subindex: int = 0) -> int:
        """The object's value, or `default` when the dictionary lacks it or it holds no value."""
        try:
            return self._get(index, subindex)
        except (KeyError, SdoAbortedError):
            return default

    def _get_or_none(self, index: int, subindex: int = 0) -> int | None:
        """The object's value, None when it holds none (a master's read of it is refused)."""
        try:
            return self._get(index, subindex)
        except (KeyError, SdoAbortedError):
            return None

    # --- boot, NMT, resets ------------------------------------------------------------------------

    def _boot(self) -> None:
        """Boot-up message, then PRE-OPERATIONAL (which starts the heartbeat of 0x1017)."""
        self.node.nmt.send_command(0x81)
        self.node.nmt.send_command(0x80)

    def _reset_application(self) -> None:
        """Power-on values of the drive's own objects; the 402 state machine to SWITCH ON DISABLED."""
        self.node.data_store.clear()
        self._units = None
        if self._get_or(0x608F, 0, 1) <= 0 or self._get_or(0x608F, 0, 2) <= 0:  # no resolution in the EDS
            self._store(0x608F, 1, self._encoder_counts_per_rev())
            self._store(0x608F, 2, 1)
        rated_ma = self._get_or(0x6075, 0)
        if rated_ma <= 0:
            rated_ma = round(self._rated_current_default_a * 1000)
            self._store(0x6075, 0, rated_ma)
        self.rated_current_a = rated_ma / 1000.0
        self.rated_torque_nm = self.model.motor.K_m * self.rated_current_a
        self._store(0x6076, 0, round(self.rated_torque_nm * 1000))
        for index in (0x6040, 0x603F, 0x1001, 0x6060, 0x6061, 0x6064, 0x606C, 0x6071, 0x6077, 0x6078, 0x60B2):
            self._store(index, 0, 0)
        self._store(0x607A, 0, 0)
        self._store(0x60FF, 0, 0)
        self._store(0x60C1, 1, 0)
        self._supported_bits = self._get_or(0x6502, -1)
        if self._supported_bits < 0:  # the EDS gives no value: the modes whose target objects it has
            self._supported_bits = sum(
                bit
                for m, bit in SUPPORTED_MODE_BIT.items()
                if m in TARGET_OBJECT and self._has(*TARGET_OBJECT[m])
            )
            self._store(0x6502, 0, self._supported_bits)
        self._torque_reference_permille = 0.0
        self._controlword = 0
        self._fault_bits = 0
        self._pending.clear()
        self._pdos_stale = True
        self._enter(State.SWITCH_ON_DISABLED)
        self._publish()

    def _on_nmt(self, can_id: int, data: bytearray, timestamp: float) -> None:
        command, node_id = data[0], data[1]
        if node_id not in (0, self.node.id):
            return
        with self._lock:
            if command in (0x81, 0x82):  # reset node / communication: LocalNode only sets the state
                if command == 0x81:
                    self._reset_application()
                else:
                    for index in [i for i in self.node.data_store if 0x1000 <= i < 0x2000]:
                        del self.node.data_store[index]
                    self._pdos_stale = True
                self._boot()
                return
            if self.node.nmt.state == NMT_OPERATIONAL:
                self._refresh_pdos()
                return
            self._pending.clear()
            if self.state in (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE):
                self._abort_connection()

    def _abort_connection(self) -> None:
        """The master left OPERATIONAL under a powered drive: 0x6007 says what to do (default 2)."""
        option = self._get_or(0x6007, 2)
        if option == 1:
            self._fault(EMCY_COMMUNICATION)
        elif option == 3:
            self._enter(State.QUICK_STOP_ACTIVE)
        elif option != 0:
            self._enter(State.SWITCH_ON_DISABLED)
        self._publish()

    # --- PDOs -------------------------------------------------------------------------------------

    def _on_write(self, index: int, subindex: int, od: ODVariable, data: bytes) -> None:
        # Called before the value is stored: PDO settings are re-read at the next SYNC or NMT start.
        if RPDO_COMM <= index < 0x1C00:
            if is_mapping_object(index) and subindex > 0:
                self._check_mappable(int(od.decode_raw(data)))
            self._pdos_stale = True
        elif index in FACTOR_OBJECTS:
            self._units = None  # a unit changes: re-read the factor group at its next use
        elif index == 0x6040:
            with self._lock:
                self._apply_controlword(int(od.decode_raw(data)))
                if not self._applying_sync_rpdos:  # those are published once, after the SYNC's step
                    self._publish()  # the statusword answers at once, for SDO masters too

    def _check_mappable(self, value: int) -> None:
        """Refuse, as a drive does (SDO abort 0x06040041), to map what is not a mappable object."""
        entry = PdoEntry.from_mapping_value(value)
        known = self._has(entry.index, entry.subindex)
        if value and not (known and self._var(entry.index, entry.subindex).pdo_mappable):
            raise SdoAbortedError(0x06040041)

    def _refresh_pdos(self) -> None:
        if not self._pdos_stale:
            return
        for cob_id in self._rpdos:
            self.network.unsubscribe(cob_id, self._on_rpdo)
        self._rpdos = {p.cob_id: p for p in self._read_pdos(RPDO_COMM, RPDO_MAP)}
        self._offset_mapped = any(
            (e.index, e.subindex) == TORQUE_OFFSET for p in self._rpdos.values() for e in p.layout.entries
        )
        for cob_id in self._rpdos:
            self.network.subscribe(cob_id, self._on_rpdo)
        self._tpdos = self._read_pdos(TPDO_COMM, TPDO_MAP)
        self._tpdo_sent.clear()
        self._pdos_stale = False

    def _read_pdos(self, comm: int, mapping: int) -> list[_Pdo]:
        pdos = []
        for n in range(512):
            if not self._has(comm + n, 1):
                continue
            cob_id = self._get(comm + n, 1)
            count = self._get(mapping + n, 0)
            if cob_id & PDO_INVALID or count == 0:
                continue
            entries = [PdoEntry.from_mapping_value(self._get(mapping + n, k)) for k in range(1, count + 1)]
            transmission = self._get(comm + n, 2) if self._has(comm + n, 2) else 255
            layout = PdoLayout.of(self.node.object_dictionary, entries)
            pdos.append(_Pdo(cob_id & 0x7FF, transmission, layout))
        return pdos

    def _on_rpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        with self._lock:
            pdo = self._rpdos.get(can_id)
            if pdo is None or self.node.nmt.state != NMT_OPERATIONAL:
                return
            if pdo.transmission >= 254:
                self._apply_rpdo(pdo, bytes(data))
            else:
                self._pending[can_id] = bytes(data)  # synchronous: takes effect at the next SYNC

    def _apply_rpdo(self, pdo: _Pdo, data: bytes) -> None:
        try:
            values = pdo.layout.decode(data)
        except ValueError:
            logger.warning("twin %d: RPDO 0x%03X of %d bytes ignored", self.node.id, pdo.cob_id, len(data))
            return
        for entry, value in zip(pdo.layout.entries, values, strict=True):
            var = self._var(entry.index, entry.subindex)
            self.node.set_data(entry.index, entry.subindex, var.encode_raw(value))

    def _send_tpdos(self) -> None:
        frames: list[tuple[int, bytes]] = []
        for pdo in self._tpdos:
            try:
                payload = pdo.layout.encode([self._get(e.index, e.subindex) for e in pdo.layout.entries])
            except SdoAbortedError:  # maps an object that holds no value: a mapping error of the master
                logger.warning("twin %d: TPDO 0x%03X maps an object with no value", self.node.id, pdo.cob_id)
                continue
            if 1 <= pdo.transmission <= 240 and self._sync_count % pdo.transmission != 0:
                continue
            if pdo.transmission >= 254 and self._tpdo_sent.get(pdo.cob_id) == payload:
                continue  # event-driven: sent when it changes (checked at each SYNC)
            self._tpdo_sent[pdo.cob_id] = payload
            frames.append((pdo.cob_id, payload))
        if frames:
            self.network.send_messages(frames)  # in one go where the bus takes a batch: the same frames

    # --- the cycle --------------------------------------------------------------------------------

    def _on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        taken_s = time.monotonic()  # a drive latches at the SYNC; the step after it is its state from then
        with self._lock:
            operational = self.node.nmt.state == NMT_OPERATIONAL
            if operational:
                self._refresh_pdos()
                pending, self._pending = self._pending, {}
                self._applying_sync_rpdos = True
                try:
                    for cob_id, payload in pending.items():
                        self._apply_rpdo(self._rpdos[cob_id], payload)
                finally:
                    self._applying_sync_rpdos = False
            for follower in self.followers:
                follower.before_step()
            self._step(self._cycles_per_sync())
            self._sync_count += 1  # after the step: a SYNC counted is one whose plant time has passed
            if self.on_sample is not None:
                self.on_sample(self.last_sample)
            self._publish()
            if operational:
                self._send_tpdos()
            # The DAQ's state of this SYNC, after the answer is sent (in this process's bus; the child's hub
            # sends it once this handler returns): its sensors' readings are the DAQ board's work.
            self.measured.record(taken_s, self._truths())
        for follower in self.followers:
            follower.after_step()

    def _on_load(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if len(data) == 8:
            self.tau_ext_nm = float(np.frombuffer(bytes(data), "<f8")[0])

    def _truths(self) -> tuple[float, float, float, float]:
        """What the DAQ's analog inputs read (`daq_twin.TRUTHS`) after this SYNC's last cycle, as the
        simulated bench's sensors read it (docs/CATALOG_TESTS.md): the torque transducers
        (`inprocess.TorqueTransducers`: τ_in = r·T_s + F_m, τ_out the output shaft's torque beyond the
        gear's own inertia) and the temperature probes (`inprocess.TemperatureProbes`: gear, winding;
        AMBIENT_C without a `thermal` section), each with the rig file's seeded noise [N·m, °C]."""
        truth = self.drive.truth
        assert truth is not None  # kept on from the start, emptied here
        if not truth:
            return 0.0, 0.0, AMBIENT_C, AMBIENT_C
        row = truth[-1][-1].tolist()  # plain floats: a SYNC's one reading costs less without arrays
        truth.clear()
        # TorqueTransducers' definitions, one cycle at a time, with its noise stream.
        transducers = self._transducers
        tau_in, tau_out = transducers.torques(row[T_T_S], row[T_F_M], row[T_F_L], row[T_TAU_EXT])
        plant_c = (
            (row[T_TEMP_MOTOR], row[T_TEMP_GEAR]) if self.model.thermal is not None else (AMBIENT_C,) * 2
        )
        if self._probe_c is None:
            self._probe_c = list(plant_c)
        probe = self._probe_c  # TemperatureProbes' first-order lag, a cycle at a time
        for i in (0, 1):
            probe[i] += self._probe_alpha * (plant_c[i] - probe[i])
        noise_nm, noise_c = transducers.noise_nm, self.config.sensors.temperature_noise_c
        torque_noise = self._torque_noise.take(2) if noise_nm > 0 else (0.0, 0.0)
        temp_noise = self._temp_noise.take(2) if noise_c > 0 else (0.0, 0.0)
        return (
            tau_in + noise_nm * torque_noise[0],
            tau_out + noise_nm * torque_noise[1],
            probe[1] + noise_c * temp_noise[1],
            probe[0] + noise_c * temp_noise[0],
        )

    def _cycles_per_sync(self) -> int:
        period_us = self._get_or(0x1006, 0)
        return max(1, round(period_us * 1e-6 / self.period_s)) if period_us else 1

    def _step(self, n: int) -> None:
        """Advance the plant n cycles in the current state and mode; a breach while powered faults."""
        powered = self.state in (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE)
        mode, setpoint = self._command(n) if powered else (ControlMode.CURRENT, np.zeros(n))
        track = self._offset_track(setpoint) if powered and mode == ControlMode.POSITION else None
        tau = np.full(n, self.tau_ext_nm)
        done = 0
        while done < n:
            part = track.part(done, n) if track is not None else None
            rows, code = self.drive.run(mode, setpoint[done:], tau[done:], self.t_s, part)
            done += rows.shape[0]
            self.t_s += rows.shape[0] * self.period_s
            self._remember(rows[-1])
            if code == NO_ABORT:
                continue
            if powered:
                self._fault(EMCY_FOR_ABORT[code])
                if code == ABORT_FOLLOWING:
                    self._fault_bits |= SW_MODE_BIT13
                mode, setpoint, track = ControlMode.CURRENT, np.zeros(n), None
                powered = False
        stopped = abs(self.last_sample["omega_m"]) < STANDSTILL_RAD_S
        if self.state == State.QUICK_STOP_ACTIVE and stopped and not 5 <= self._get_or(0x605A, 2) <= 8:
            self._enter(State.SWITCH_ON_DISABLED)  # quick stop option codes 1-4: done, power off

    def _command(self, n: int) -> tuple[ControlMode, np.ndarray]:
        """What the drive's loops are given for the next n cycles, from the targets in its dictionary."""
        if self.state == State.QUICK_STOP_ACTIVE:
            return ControlMode.VELOCITY, np.zeros(n)
        mode = self._active_mode()
        units = self._position_units_per_rad()
        if mode in (OperationMode.CYCLIC_SYNC_TORQUE, OperationMode.PROFILE_TORQUE):
            permille = float(self._get_or(0x6071, 0))
            if mode == OperationMode.PROFILE_TORQUE:
                permille = self._torque_ramp(permille, n)
            else:
                permille += self._get_or(0x60B2, 0)  # CST: the torque offset adds to the target
            limit = self._get_or(0x6072, _INT16)  # max torque, ‰
            permille = min(max(permille, -limit), limit)
            current = permille * self.rated_torque_nm / 1000.0 / self.model.motor.K_m
            limit_a = self._get_or(0x6073, _INT16) * self.rated_current_a / 1000.0  # max current
            current = min(max(current, -limit_a), limit_a)
            return ControlMode.CURRENT, np.full(n, current)
        if mode in (OperationMode.CYCLIC_SYNC_POSITION, OperationMode.INTERPOLATED_POSITION):
            if mode == OperationMode.CYCLIC_SYNC_POSITION:
                target = self._get_or(0x607A, 0) / units
            elif self._controlword & CW_ENABLE_IP_BIT:
                target = self._get_or(0x60C1, 0, 1) / units
            else:  # interpolation not enabled: hold the last position
                held = self._position_target_rad
                target = held if held is not None else self.last_sample.get("theta_m", 0.0)
            start = self._position_target_rad if self._position_target_rad is not None else target
            self._position_target_rad = target
            return ControlMode.POSITION, np.linspace(start, target, n + 1)[1:]  # interpolated over the SYNC
        velocity_units = self._velocity_units_per_rad_s()
        if mode == OperationMode.CYCLIC_SYNC_VELOCITY:
            return ControlMode.VELOCITY, np.full(n, self._velocity_target_rad_s(velocity_units))
        if mode == OperationMode.PROFILE_VELOCITY:
            target = self._velocity_target_rad_s(velocity_units)
            return ControlMode.VELOCITY, self._profile(n, target)
        return ControlMode.CURRENT, np.zeros(n)  # no mode, or one the drive lacks: no torque

    def _offset_track(self, positions_rad: np.ndarray) -> FeedForwardTrack | None:
        """CSP with 0x60B2 mapped: the targets and the offset torque as the simulated drive's track."""
        if not self._offset_mapped or self._active_mode() != OperationMode.CYCLIC_SYNC_POSITION:
            return None
        rows = np.zeros((positions_rad.shape[0], N_FF_COLUMNS))
        rows[:, FF_THETA] = positions_rad
        rows[:, FF_TORQUE] = self._get_or(0x60B2, 0) * self.rated_torque_nm / 1000.0
        return FeedForwardTrack(rows, label="0x60B2")

    def _torque_ramp(self, target_permille: float, n: int) -> float:
        """Profile torque: the torque reference moves to the target at the torque slope 0x6087 [‰/s]."""
        slope = self._get_or(0x6087, 0) * n * self.period_s
        step = target_permille - self._torque_reference_permille
        if slope > 0:
            step = min(max(step, -slope), slope)
        self._torque_reference_permille += step
        return self._torque_reference_permille

    def _velocity_target_rad_s(self, units: float) -> float:
        target = self._get_or(0x60FF, 0) / units
        limit = self._get_or(0x607F, _INT32) / units  # max profile velocity
        limit = min(limit, self._get_or(0x6080, _INT32) * 2 * math.pi / 60)  # max motor speed, rpm
        return min(max(target, -limit), limit)

    def _profile(self, n: int, target: float) -> np.ndarray:
        """Profile velocity: the reference ramps to the target at 0x6083 (speeding up), 0x6084 (slowing)."""
        accel = self._get_or(0x6083, 0) / self._drive_units()[2]
        decel = self._get_or(0x6084, 0) / self._drive_units()[2]
        out = np.empty(n)
        reference = self._pv_reference_rad_s
        for k in range(n):
            speeding_up = abs(target) > abs(reference) and target * reference >= 0.0
            step = (accel if speeding_up else decel) * self.period_s
            step = step if step > 0 else math.inf  # a zero ramp: a step (as the drive's loops allow)
            reference += min(max(target - reference, -step), step)
            out[k] = reference
        self._pv_reference_rad_s = reference
        return out

    def _remember(self, row: np.ndarray) -> None:
        self.last_sample = dict(zip(SAMPLE_COLUMNS, row.tolist(), strict=True))

    # --- the state machine ------------------------------------------------------------------------

    def _active_mode(self) -> OperationMode | None:
        mode = _MODES.get(self._get_or(0x6060, 0))
        if mode is None:
            return None
        usable = mode in TARGET_OBJECT and self._supported_bits & SUPPORTED_MODE_BIT[mode]
        return mode if usable else None

    def _apply_controlword(self, controlword: int) -> None:
        command = decode_controlword(controlword)
        rising_reset = command == Command.FAULT_RESET and not self._controlword & 0x80
        self._controlword = controlword
        if command == Command.FAULT_RESET and not rising_reset:
            return
        if command == Command.FAULT_RESET and self.state == State.FAULT:
            self._clear_fault()
        self._enter(next_state(self.state, command))

    def _enter(self, state: State) -> None:
        if state == self.state:
            return
        if state == State.OPERATION_ENABLED:
            self.drive.reset_loops()
            self._position_target_rad = None
            self._pv_reference_rad_s = self.last_sample.get("omega_m", 0.0)  # the ramp starts from here
        self.state = state

    def _fault(self, code: int) -> None:
        """FAULT at once (the fault reaction is: torque off), the error code and register, one EMCY."""
        if self.state == State.FAULT:
            return
        register = error_register_for(code)
        self._store(0x603F, 0, code)
        self._store(0x1001, 0, register)
        self._enter(State.FAULT)
        self._publish()
        if self.node.nmt.state != NMT_STOPPED:
            self.node.emcy.send(code, register)

    def _clear_fault(self) -> None:
        self._store(0x603F, 0, 0)
        self._store(0x1001, 0, 0)
        self._fault_bits = 0
        if self.node.nmt.state != NMT_STOPPED:
            self.node.emcy.reset()

    def _publish(self) -> None:
        """Statusword, mode display and actual values into the dictionary (what TPDOs and SDO read)."""
        extra = self._fault_bits
        mode = self._active_mode()
        if self.state == State.OPERATION_ENABLED and mode is not None:
            omega = self.last_sample.get("omega_m", 0.0)
            if mode == OperationMode.PROFILE_VELOCITY:
                target = self._velocity_target_rad_s(self._velocity_units_per_rad_s())
                ramped = abs(self._pv_reference_rad_s - target) < 1e-9
                if ramped and abs(omega - target) < PV_REACHED_RAD_S:
                    extra |= SW_TARGET_REACHED
                if abs(omega) < STANDSTILL_RAD_S:
                    extra |= SW_MODE_BIT12
            else:
                extra |= SW_MODE_BIT12  # cyclic modes: the drive follows the command value
        self._store(0x6041, 0, statusword_for(self.state, extra))
        self._store(0x6061, 0, int(mode) if mode is not None else 0)
        if not self.last_sample:
            return
        position_units, velocity_units, _ = self._units or self._drive_units()
        sample = self.last_sample
        theta, omega, current = sample["theta_m"], sample["omega_m"], sample["i_a"]
        self._store(0x6064, 0, _saturate(round(theta * position_units), _INT32))
        self._store(0x606C, 0, _saturate(round(omega * velocity_units), _INT32))
        torque = current * self.model.motor.K_m
        self._store(0x6077, 0, _saturate(round(torque / self.rated_torque_nm * 1000), _INT16))
        self._store(0x6078, 0, _saturate(round(current / self.rated_current_a * 1000), _INT16))

    def _position_units_per_rad(self) -> float:
        return self._drive_units()[0]

    def _velocity_units_per_rad_s(self) -> float:
        return self._drive_units()[1]

    def _drive_units(self) -> tuple[float, float, float]:
        """Position, velocity and acceleration units per motor rad, rad/s, rad/s², as the factor group
        of the twin's dictionary defines them (`FactorGroup`: the driver's own reading of CiA 402), with
        the values a master wrote; increments of its encoder (0x608F) where the group says nothing."""
        if self._units is None:
            group = FactorGroup.read(self.node.object_dictionary, self._get_or_none)
            resolution = self._get_or(0x608F, 0, 1) / max(1, self._get_or(0x608F, 1, 2))
            increments = (resolution if resolution > 0 else self._encoder_counts_per_rev()) / (2 * math.pi)
            try:
                per_rev = group.position_units_per_rev()
                position = per_rev / (2 * math.pi) if per_rev is not None else increments
                velocity = group.velocity_units_per_rad_s(position)
                velocity = velocity if velocity is not None else position
                acceleration = group.acceleration_units_per_rad_s2(velocity)
                acceleration = acceleration if acceleration is not None else velocity
            except CanopenConfigError as exc:  # as a drive whose firmware ignores what it cannot use
                logger.warning("twin %d: %s: in encoder increments instead", self.node.id, exc)
                position = velocity = acceleration = increments
            self._units = (position, velocity, acceleration)
        return self._units

    def _encoder_counts_per_rev(self) -> int:
        return self.config.sensors.encoder_counts_per_rev or 1 << 17  # ideal sensors: a 17-bit encoder

    # --- heartbeat consumer and life guarding -----------------------------------------------------

    def _answer_guard(self) -> None:
        """A node guarding request: the NMT state with the toggle bit, alternating from 0."""
        codes = {name: code for code, name in canopen.nmt.NMT_STATES.items()}
        state = codes.get(self.node.nmt.state, 0)
        self.network.send_message(self._watch.guard_cob_id, bytes([state | self._guard_toggle]))
        self._guard_toggle ^= 0x80

    def _watch_heartbeats(self) -> None:
        woke_s = time.monotonic()
        while not self._closing.wait(WATCH_PERIOD_S):
            now = time.monotonic()
            slept_s, woke_s = now - woke_s, now
            if slept_s > WATCH_STALLED_S:
                # This thread was held itself (the machine busy, or the interpreter it may share with
                # the host): whatever held it held the host's heartbeat sender too. A drive's watchdog
                # runs on a CPU of its own; the twin judges on its next wake-up, when the sender has run.
                continue
            with self._lock:
                for node_id, timeout_s in self._consumers():
                    heard = self._watch.heard_s.get(node_id)
                    if heard is None:
                        continue  # monitoring starts with the first heartbeat heard
                    if now - heard <= timeout_s:
                        self._lost.discard(node_id)
                    elif node_id not in self._lost:
                        self._lost.add(node_id)
                        self._say_lost(f"heartbeat of node {node_id}", now - heard, timeout_s)
                self._watch_life_guard(now)

    def _watch_life_guard(self, now: float) -> None:
        """Life guarding: no guarding request for guard time 0x100C × life time factor 0x100D."""
        guarded = self._watch.guarded_s
        life_s = self._get_or(0x100C, 0) * self._get_or(0x100D, 0) / 1000.0
        if guarded is None or life_s <= 0:
            return  # guarding starts with the first request, and is off while either object is 0
        if now - guarded <= life_s:
            self._guard_lost = False
        elif not self._guard_lost:
            self._guard_lost = True
            self._say_lost("node guarding by the host", now - guarded, life_s)

    def _say_lost(self, what: str, silent_s: float, timeout_s: float) -> None:
        powered = self.state in (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE)
        logger.warning(
            "twin %d: %s lost: none for %.0f ms (timeout %.0f ms): EMCY 0x%04X, FAULT%s",
            self.node.id,
            what,
            silent_s * 1e3,
            timeout_s * 1e3,
            EMCY_HEARTBEAT,
            ", torque off" if powered else "",
        )
        self._fault(EMCY_HEARTBEAT)

    def _consumers(self) -> list[tuple[int, float]]:
        if not self._has(0x1016, 0):
            return []
        consumers = []
        for sub in range(1, self._get(0x1016, 0) + 1):
            try:
                value = self._get(0x1016, sub)
            except (KeyError, SdoAbortedError):
                continue
            node_id, time_ms = value >> 16 & 0x7F, value & 0xFFFF
            if node_id and time_ms:
                consumers.append((node_id, time_ms / 1000.0))
        return consumers

    @property
    def sync_count(self) -> int:
        """SYNCs taken so far (each one stepped the plant)."""
        return self._sync_count

    # --- life cycle -------------------------------------------------------------------------------

    def close(self) -> None:
        """Stop the heartbeat watch, the heartbeat producer and the bus; no thread is left behind."""
        self._closing.set()
        self._watch_thread.join()
        self.node.nmt.stop_heartbeat()
        if self._owns_network:
            self.network.disconnect()

    def __enter__(self) -> Cia402Twin:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class _NoiseStream:
    """Standard normal draws from a generator, taken a few at a time from blocks drawn ahead (one call per
    thousand SYNCs instead of one per SYNC)."""

    BLOCK: Final = 2048

    def __init__(self, rng: np.random.Generator) -> None:
        self._rng = rng
        self._drawn: list[float] = []
        self._next = 0

    def take(self, n: int) -> list[float]:
        if self._next + n > len(self._drawn):
            self._drawn, self._next = self._rng.standard_normal(self.BLOCK).tolist(), 0
        self._next += n
        return self._drawn[self._next - n : self._next]


def _saturate(value: int, bound: int) -> int:
    return min(max(value, -bound - 1), bound)


class LoadTwin(Cia402Twin):
    """The load drive of a dynamometer bench: a CiA 402 drive in torque mode (CST or profile torque) on
    the output shaft of the axis twin's plant, on the axis twin's network (the same bus). In a velocity
    mode (CSV, PV: an EDS without torque modes) it brakes: its speed loop holds the output's speed.

    Each SYNC the axis twin takes, this drive's torque T_load (its target, within its limits; none while
    not OPERATION ENABLED, and none in quick stop: a load drive unloads) is applied to the plant's
    output as τ_ext = −T_load (the model's τ_ext opposes the output's motion: J_l·dω_l/dt = T_s − τ_ext)
    for the cycle, and its answer reports the output's angle and speed, its shaft being the output.
    Its motor is direct-drive: `torque_constant_nm_per_a` turns its current into output torque.
    """

    def __init__(
        self,
        axis: Cia402Twin,
        node_id: int,
        eds_path: Path = TWIN_EDS,
        torque_constant_nm_per_a: float = 1.0,
        rated_current_a: float = 5.0,
    ) -> None:
        motor = axis.model.motor.model_copy(update={"K_m": torque_constant_nm_per_a})
        model = axis.model.model_copy(update={"motor": motor})
        self.axis = axis
        self.torque_nm = 0.0
        """The torque the drive applies to the output this cycle [N·m]."""
        self._speed_integral_nm = 0.0  # a velocity mode's speed loop
        super().__init__(
            cast(can.BusABC, None), node_id, model, axis.config, eds_path, rated_current_a, axis.network
        )
        axis.followers.append(self)

    def inject_fault(self, code: int) -> None:
        """FAULT now with the EMCY `code`, as the drive's own protection would (tests)."""
        with self._lock:
            self._fault(code)

    def before_step(self) -> None:
        """At the axis's SYNC, before its step: this drive's RPDOs, then its torque on the output."""
        with self._lock:
            operational = self.node.nmt.state == NMT_OPERATIONAL
            if operational:
                self._refresh_pdos()
                pending, self._pending = self._pending, {}
                self._applying_sync_rpdos = True  # published once, after the axis's step
                try:
                    for cob_id, payload in pending.items():
                        self._apply_rpdo(self._rpdos[cob_id], payload)
                finally:
                    self._applying_sync_rpdos = False
            self._sync_count += 1
            torque = 0.0
            if self.state == State.OPERATION_ENABLED:
                mode, setpoint = self._command(1)
                if mode == ControlMode.CURRENT:
                    torque = float(setpoint[-1]) * self.model.motor.K_m
                elif mode == ControlMode.VELOCITY:
                    torque = self._hold_speed(float(setpoint[-1]))
            elif self.state == State.QUICK_STOP_ACTIVE:
                self._enter(State.SWITCH_ON_DISABLED)  # unloaded at once: torque off
            if self.state != State.OPERATION_ENABLED:
                self._speed_integral_nm = 0.0  # off: its speed loop starts afresh when enabled
            self.torque_nm = torque
            self.axis.tau_ext_nm = -torque

    def _hold_speed(self, target_rad_s: float) -> float:
        """A velocity mode (CSV, PV): its speed loop on the output, a PI tuned on the inertia it moves (the
        output's and the motor's through the gear, J_l + J_m/r²) for BRAKE_BANDWIDTH_HZ, within its
        current limit (0x6073): the torque it applies [N·m]."""
        omega_rad_s = float(self.axis.plant.x[X.OMEGA_L])
        mechanics = self.axis.model.mechanics
        inertia = mechanics.J_l + mechanics.J_m / mechanics.r**2
        kp = inertia * 2 * math.pi * BRAKE_BANDWIDTH_HZ  # N·m per rad/s
        ki = kp * 2 * math.pi * BRAKE_BANDWIDTH_HZ / 3  # integral corner a third of the bandwidth
        limit_nm = self._get_or(0x6073, _INT16) * self.rated_current_a / 1000.0 * self.model.motor.K_m
        error = target_rad_s - omega_rad_s
        integral = min(max(self._speed_integral_nm + ki * error * self.period_s, -limit_nm), limit_nm)
        self._speed_integral_nm = integral  # clamped: no wind-up against the limit
        return min(max(kp * error + integral, -limit_nm), limit_nm)

    def after_step(self) -> None:
        """After the axis's step: the output's state as this drive's actual values, its TPDOs."""
        with self._lock:
            x = self.axis.plant.x
            self.t_s = self.axis.t_s
            self.last_sample = {
                **_ZERO_SAMPLE,
                "t": self.t_s,
                "theta_m": float(x[X.THETA_L]),
                "omega_m": float(x[X.OMEGA_L]),
                "i_a": self.torque_nm / self.model.motor.K_m,
                "tau_ext": -self.torque_nm,
            }
            self._publish()
            if self.node.nmt.state == NMT_OPERATIONAL:
                self._send_tpdos()

    def _step(self, n: int) -> None:  # the axis steps the plant
        raise AssertionError("a load twin takes its SYNCs from its axis twin")


def load_twin_for(twin: Cia402Twin, settings: CanopenSettings) -> LoadTwin | None:
    """The load drive's twin on `twin`'s bus, where the `canopen:` section has a `load` drive."""
    load = settings.load
    if load is None:
        return None
    rated = load.scaling.rated_current_a or 5.0
    return LoadTwin(twin, load.node_id, load.eds_path(), load.scaling.torque_constant_nm_per_a, rated)
