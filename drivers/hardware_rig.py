"""The hardware rig: a CiA 402 servo on CANopen and the serial DAQ, composed behind the rig interface.

`backend: canopen`. The servo (`drivers.canopen_servo`) is cycled once per sample; the DAQ
(`drivers.serial_daq`) streams at its own rate on its own clock. Each row of the run is one SYNC:

- `t`: the host time the SYNC went out, from when the rig was opened (a `sample_clock` may replace it:
  the virtual backend gives the plant's own time);
- `theta_m`, `omega_m`, `i_a`: what the drive answered that SYNC (position and velocity actual,
  current actual, or torque actual / K_m where the drive has no current object);
- `theta_l`: the DAQ's output angle interpolated (`np.interp`) at the SYNC's host time. The DAQ's
  samples carry host times through its clock-offset estimate (refreshed every `daq.clock_every_s`
  by a thread of this rig, so a drifting board stays aligned). The samples decoded are taken after
  each cycle, in the period's slack, and interpolated at the chunk's end, once one after its last
  SYNC is in. Paced, that wait ends in time for the next SYNC: rows still past the newest sample
  then (at most EXTRAPOLATE_MAX_PERIODS; counted in `daq_tally.extrapolated`) are extrapolated
  along its last two samples. Without a DAQ, `hardware.theta_l_from_motor: true` must say so, and
  θ_l is then r·θ_m, a rigid stand-in (the rig file, recorded with every run, shows it);
- `u`: a CiA 402 drive does not report its voltage. It is estimated as u = R·i_a + K_b·ω_m (the
  terminal voltage that drives the measured current at the measured speed, inductance neglected),
  with R = `hardware.motor_resistance_ohm` and K_b = `hardware.back_emf_v_s_rad` (default: the
  torque constant, equal to K_b in SI units for a DC motor);
- `i_cmd`: the current target in current mode (CST); in velocity and position modes the drive's
  own current command is not on the bus, and the current it reports stands in for it;
- `setpoint`, `tau_ext`: as commanded. A bench without a load drive has no load actuator, so a segment
  asking for a load torque is refused (`load` is given only by the virtual backend, which sets the
  twin's load).

A dynamometer bench (`canopen.drives` with a `load` drive, `drivers.canopen_config.DriveEntry`): the
load drive shares the axis drive's bus and SYNC (`CanopenServo.follow`), runs in torque mode (CST, else
profile torque), and is given −τ_ext each cycle (the model's τ_ext opposes the output's motion); one
without a torque mode brakes instead (`brake`: CSV or PV holding the output's speed, `hold_output`),
and a segment asking it for a load torque is refused. The
bus load of both drives' cyclic frames is checked at opening, at each drive's worst mapping. It is
enabled after the axis and unloaded (torque 0, then disabled) before the axis disables, so it never
turns a free arm. A fault, EMCY, lost heartbeat or a breach of its own trips (`current_trip_a`,
`velocity_trip_rad_s`) on either drive quick-stops both in the next SYNC.

Modes: each program in the best mode the drive offers (`drivers.drive_modes`: CST, CSV, CSP first);
voltage is refused (CiA 402 has no voltage mode). A mode change between segments is disable →
configure → enable (the drive refuses a remap while powered); the cycles it takes are not recorded,
so `t` jumps over them.

Feed-forward (`Segment.feedforward`, a model's track: `model.feedforward`): the drive is sent the
track's planned motor angle θ_cmd instead of the set-point, and the track's torque every cycle
(`loop_torque_nm`). In CSP the torque goes in the torque offset 0x60B2 mapped beside the target, so
the drive's own loops close around it. A drive without 0x60B2 mappable plays the segment in CST with
the loops closed here (`rig.control`, the same compiled position P and velocity PI as the simulated
drive, with the rig file's `control:` gains, which are the drive's loop gains for the simulated
rigs: the same loop, moved to the host), fed by the position and velocity actual of the previous
SYNC, so the host loop runs one cycle behind a drive's own. The rate feed-forward passes the filter
the rig file's `sensors.velocity_filter_hz` says the speed measurement has, so an exact follower
meets zero speed error. Switching a track on or off is a mode change (RPDO 1 gains or loses 0x60B2).
`supports_feedforward` says whether the drive can do either; a segment with a track on a drive that
cannot is refused in one line naming what it lacks.

The rig does not touch the garbage collector, whose full collections would stall the loop for many
periods: that is a policy of the process that owns the loop (`rig.realtime.quiet_heap`).

Every cycle the rig envelope is checked (`rig.safety.envelope_breach`) with the measured values, and
the chunk ends at the first breach. A drive that faults or leaves OPERATION ENABLED on its own, or
goes silent, is stopped at once and its rows are kept; the fault (a `RigFaultError`, one line with its EMCYs)
is raised at the rig's next call, which `run_segment` makes straight away. What the rig file asks and
the bench cannot do (a voltage segment, a load torque, a field the drive refuses) is a `RigError` or
another `UserInputError`, raised before anything moves.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Collection
from dataclasses import dataclass, field
from pathlib import Path
from typing import Final

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from drivers.canopen_config import (
    BusLoad,
    CanopenConfigError,
    DriveEntry,
    PdoPlan,
    bus_load,
    check_bus_load,
    rpdo_layout,
    tpdo_layouts,
)
from drivers.canopen_servo import TORQUE_MODES, CanopenServo, CanopenServoError, DriveSettingError, Feedback
from drivers.cia402 import OperationMode, State
from drivers.daq_protocol import STATUS_CAP_RANGE, STATUS_ENCODER_FAULT, DecoderStats
from drivers.drive_modes import ModeChoice
from drivers.serial_daq import (
    ANALOG_QUANTITIES,
    DEFAULT_BAUDRATE,
    AnalogChannel,
    DaqError,
    SampleBlock,
    SerialDaq,
)
from model.errors import UserInputError, describe_validation_error
from model.feedforward import FeedForwardTrack, loop_torque_nm
from rig.config import RigConfig
from rig.control import N_CONTROL_STATE, S_PREV_POSITION_REF, S_RATE, gains_vector, position_p, velocity_pi
from rig.faults import DeviceFaultError
from rig.interface import (
    SAMPLE_COLUMNS,
    Block,
    ControlMode,
    ModeRefusedError,
    Rig,
    RigError,
    RigFaultError,
    Segment,
)
from rig.safety import NO_ABORT, envelope_breach, limits_vector

logger = logging.getLogger(__name__)

RAW_CAN_LOG: Final = "raw_can.blf"
"""The raw CAN traffic of a run, beside its data (`record_raw_to`)."""
CLOCK_EXCHANGES_AT_START: Final = 16
CLOCK_EXCHANGES_WHILE_STREAMING: Final = 4
DAQ_DRAIN_CYCLES: Final = 25
"""The samples decoded are taken every this many cycles, in the period's slack: making a block has a
fixed CPU cost however few frames it holds, and on a shared CPU the loop's own work is what delays the
drive's next answer (figures: docs/BENCHMARKS.md, "Figures behind design choices in the code")."""
DAQ_DRAIN_WITHIN_S: Final = 400e-6
"""Paced, the samples are taken only in a cycle answered within this of its SYNC (else in a later one,
or at the chunk's end): taking them costs a good part of the period on a loaded machine, and most of the
cycles late for the period were the ones that took them after a late answer (figures: docs/BENCHMARKS.md)."""
ALIGN_MARGIN_S: Final = 800e-6
"""Paced, what a chunk's end keeps of the period, after the wait for the DAQ, to interpolate: the work
after the wait needs most of it on top of the drive's answer, so the wait is short; the rows it misses
are extrapolated (no more than with a shorter margin: the DAQ's frames come every 2 ms; figures:
docs/BENCHMARKS.md, "Figures behind design choices in the code")."""
EXTRAPOLATE_MAX_PERIODS: Final = 2
"""Paced, rows at most this many periods past the newest DAQ sample are extrapolated, plus the time
between the DAQ's frames (the newest sample can be that old on arrival); further, the chunk's end
waits for the DAQ."""
_COLUMN = {name: i for i, name in enumerate(SAMPLE_COLUMNS)}

Load = Callable[[float], None]
"""Applies the load torque τ_ext [N·m] of the next cycle (the virtual backend's twin; no bench has one)."""
SampleClock = Callable[[Feedback], float]
"""The `t` of a row from the drive's answer [s]."""


class HardwareConfigError(UserInputError):
    """The `hardware:` or `daq:` section cannot drive this rig; one line naming the field."""


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class DaqStreamSettings(_Section):
    """How the DAQ streams (a rig config's `daq:` section, less the line)."""

    rate_hz: float = Field(default=5000.0, gt=0, le=20000, description="DAQ sample rate, ≥ the rig's [Hz]")
    samples_per_frame: int = Field(default=10, ge=1, le=100, description="samples per data frame (BLOCK)")
    timeout_s: float = Field(default=1.0, gt=0, description="wait for a reply or for samples [s]")
    clock_every_s: float = Field(
        default=2.0,
        ge=0,
        description="refresh the clock-offset estimate this often while streaming; 0: never",
    )
    channels: dict[str, AnalogChannel] = Field(
        default_factory=dict,
        description="the board's analog inputs by the run column they give (tau_in, tau_out, temp_gear,"
        " temp_motor): torque transducers and temperature probes, each with its gain, offset and range",
    )

    @model_validator(mode="after")
    def _channels(self) -> DaqStreamSettings:
        unknown = sorted(set(self.channels) - set(ANALOG_QUANTITIES))
        if unknown:
            raise ValueError(f"channels {unknown} are not among {', '.join(ANALOG_QUANTITIES)}")
        inputs = [channel.adc for channel in self.channels.values()]
        if len(set(inputs)) != len(inputs):
            raise ValueError(f"channels share an ADC input: {sorted(inputs)}")
        return self


class DaqSettings(DaqStreamSettings):
    """A rig config's `daq:` section for a bench: the serial line and the stream."""

    url: str = Field(description="pyserial URL: /dev/ttyACM0, COM3, socket://host:port...")
    baudrate: int = Field(default=DEFAULT_BAUDRATE, gt=0, description="line speed (UART) [baud]")


class HardwareSettings(_Section):
    """A rig config's `hardware:` section: what the bench is, beyond what the drive reports."""

    gear_ratio: float = Field(
        gt=0, le=1, description="output/input ratio r of the transmission (0.01: 100:1)"
    )
    motor_resistance_ohm: float = Field(gt=0, description="motor armature resistance R, for the u estimate")
    back_emf_v_s_rad: float | None = Field(
        default=None, gt=0, description="motor back-EMF constant K_b [V·s/rad]; default: the torque constant"
    )
    theta_l_from_motor: bool = Field(
        default=False, description="no DAQ: record r·θ_m as theta_l (a rigid stand-in); needs no `daq:`"
    )


def _section(config: RigConfig, name: str, schema: type[_Section], required: bool) -> _Section | None:
    data = config.extra.get(name)
    if data is None and not required:
        return None
    if not isinstance(data, dict):
        raise HardwareConfigError(f"rig {config.name!r}: a `{name}:` section is needed for this backend")
    try:
        return schema.model_validate(data)
    except ValidationError as exc:
        raise HardwareConfigError(f"rig {config.name!r}: {name} {describe_validation_error(exc)}") from None


def daq_section(config: RigConfig, schema: type[DaqStreamSettings]) -> DaqStreamSettings | None:
    """The rig's `daq:` section read with `schema` (None when there is none), checked against its rate."""
    section = _section(config, "daq", schema, required=False)
    assert section is None or isinstance(section, DaqStreamSettings)
    if section is not None and section.rate_hz < config.sample_rate_hz:
        raise HardwareConfigError(
            f"rig {config.name!r}: daq.rate_hz {section.rate_hz:g} is below the rig's"
            f" {config.sample_rate_hz:g} Hz: theta_l would be interpolated over more than a cycle"
        )
    return section


@dataclass(frozen=True)
class BenchConstants:
    """What the rig needs to know of the bench that the drive does not tell."""

    gear_ratio: float
    torque_constant_nm_per_a: float
    resistance_ohm: float
    back_emf_v_s_rad: float
    daq: DaqStreamSettings | None
    theta_l_from_motor: bool = False

    @classmethod
    def from_rig_config(cls, config: RigConfig, torque_constant_nm_per_a: float) -> BenchConstants:
        hardware = _section(config, "hardware", HardwareSettings, required=True)
        assert isinstance(hardware, HardwareSettings)
        daq = daq_section(config, DaqSettings)
        if daq is None and not hardware.theta_l_from_motor:
            raise HardwareConfigError(
                f"rig {config.name!r}: no `daq:` section: give the DAQ's url, or set"
                " hardware.theta_l_from_motor: true to record r·θ_m as theta_l"
            )
        if daq is not None and hardware.theta_l_from_motor:
            raise HardwareConfigError(
                f"rig {config.name!r}: hardware.theta_l_from_motor is for a rig without a `daq:` section"
            )
        return cls(
            gear_ratio=hardware.gear_ratio,
            torque_constant_nm_per_a=torque_constant_nm_per_a,
            resistance_ohm=hardware.motor_resistance_ohm,
            back_emf_v_s_rad=hardware.back_emf_v_s_rad or torque_constant_nm_per_a,
            daq=daq,
            theta_l_from_motor=hardware.theta_l_from_motor,
        )


@dataclass
class CycleLog:
    """Per-cycle timing, kept when a caller sets `rig.cycle_log` (benchmarks, tests): host clock [s]."""

    t_sync_s: list[float] = field(default_factory=list)
    """When the SYNC went out."""
    latency_s: list[float] = field(default_factory=list)
    """From the SYNC to the drive's last TPDO answering it."""
    t_done_s: list[float] = field(default_factory=list)
    """When the loop was done with the cycle: the row checked against the envelope, the DAQ's samples
    taken (every DAQ_DRAIN_CYCLES) and, at a chunk's end, θ_l interpolated."""
    daq_theta_m_rad: list[float] = field(default_factory=list)
    """The DAQ's own motor angle at the SYNC (NaN without a DAQ): its encoder against the drive's
    shows how well the two streams are aligned."""

    def arrays(self) -> dict[str, np.ndarray]:
        return {name: np.asarray(values) for name, values in vars(self).items()}


@dataclass
class DaqTally:
    """What the DAQ delivered to this rig across its streams."""

    samples: int = 0
    index_gaps: int = 0
    """Samples missing between consecutive sample indices (lost on the line or in the board)."""
    flagged: int = 0
    """Samples with an encoder fault or a clipped capacitive reading."""
    extrapolated: int = 0
    out_of_range: int = 0
    """Analog readings (`daq.channels`) outside their sensor's range, recorded NaN."""
    """Rows whose θ_l was extrapolated past the newest sample rather than interpolated (paced)."""
    first_t_s: float = math.nan
    last_t_s: float = math.nan
    streams: list[DecoderStats] = field(default_factory=list)
    """The decoder's counts at the end of each stream (lost frames and samples by sequence number)."""
    _gaps_before: int = 0  # of the streams before this one
    _span: tuple[int, int] | None = None  # lowest and highest sample index of this stream
    _stream_samples: int = 0

    def add(self, block: SampleBlock) -> None:
        n = len(block)
        if not n:
            return
        # From the stream's index span, not block to block: a late frame fills a gap counted before.
        first, last = int(block.index[0]), int(block.index[-1])  # a block is in device-time order
        if self._span is not None:
            first, last = min(first, self._span[0]), max(last, self._span[1])
        self._span, self._stream_samples = (first, last), self._stream_samples + n
        self.index_gaps = self._gaps_before + last - first + 1 - self._stream_samples
        if block.status.any():
            self.flagged += int(np.count_nonzero(block.status & (STATUS_ENCODER_FAULT | STATUS_CAP_RANGE)))
        if self.samples == 0:
            self.first_t_s = float(block.t_host_s[0])
        self.last_t_s = float(block.t_host_s[-1])
        self.samples += n

    def new_stream(self) -> None:
        self._gaps_before, self._span, self._stream_samples = self.index_gaps, None, 0


class HardwareRig(Rig):
    """`backend: canopen`: a CiA 402 servo and, optionally, the serial DAQ for the output angle.

    Opened from a rig config's `canopen:`, `hardware:` and `daq:` sections, or on devices given by a
    backend that builds them, as the virtual one does (`servo` not yet booted, `daq` open). The servo
    is connected (if it is not) and booted here, the DAQ set to its rate; a failure releases both.
    """

    source = "hardware"

    def __init__(
        self,
        config: RigConfig,
        *,
        constants: BenchConstants | None = None,
        servo: CanopenServo | None = None,
        daq: SerialDaq | None = None,
        load: Load | None = None,
        sample_clock: SampleClock | None = None,
        load_servo: CanopenServo | None = None,
    ) -> None:
        super().__init__(config)
        # Load the compiled envelope check before the bus is up: compiling it on the first cycle would
        # stall the loop (and the heartbeats of a twin in this process) for many periods.
        envelope_breach(limits_vector(config.limits, 1.0), 0.0, 0.0, 0.0, 0.0, 0.0)
        self.servo = servo if servo is not None else CanopenServo.from_rig_config(config)
        self.daq = daq
        self.load_entry: DriveEntry | None = None
        self.load_servo: CanopenServo | None = None
        """The load drive (the dynamometer), on the axis drive's bus and SYNC; None without one."""
        self.bus_load: BusLoad | None = None
        """The bus load of every drive's cyclic frames, each at its worst mapping (checked at opening)."""
        try:
            self.load_entry = self.servo.settings.load_entry
            if self.load_entry is not None:
                load_settings = self.servo.settings.load
                assert load_settings is not None
                self.load_servo = load_servo or CanopenServo(
                    load_settings, self.load_entry.drive_limits(), 1.0 / config.sample_rate_hz
                )
            self.constants = constants or BenchConstants.from_rig_config(
                config, self.servo.settings.scaling.torque_constant_nm_per_a
            )
            if self.servo.network is None:
                self.servo.connect()
            if self.load_servo is not None:
                self.load_servo.follow(self.servo)
                self.bus_load = worst_bus_load([self.servo, self.load_servo], self.period_s)
                check_bus_load(self.bus_load, self.servo.settings.bus_load_max, f"rig {config.name!r}")
                logger.info("rig %s: two drives: %s", config.name, self.bus_load)
            if self.daq is None and isinstance(self.constants.daq, DaqSettings):
                settings = self.constants.daq
                self.daq = SerialDaq(
                    settings.url,
                    baudrate=settings.baudrate,
                    timeout_s=settings.timeout_s,
                    clock=time.monotonic,
                )
            if self.daq is not None:
                stream = self.constants.daq or DaqStreamSettings()
                self.daq.set_rate(stream.rate_hz, samples_per_frame=stream.samples_per_frame)
                self.daq.calibration()
                if stream.channels:
                    self.daq.set_analog(True)
            self.servo.boot()
            if self.load_servo is not None:
                self.load_servo.boot()
                self._load_choice = self.load_servo.choose_load()
                node = self.load_servo.settings.node_id
                logger.info("rig %s: load drive: node %d: %s", config.name, node, self._load_choice)
        except BaseException:
            self._release()
            raise
        self.brake = self.load_servo is not None and self._load_choice.program == ControlMode.VELOCITY
        """The load drive has no torque mode: it brakes by holding the output's speed (`hold_output`)."""
        self._brake_speed_rad_s: float | None = None  # released until `hold_output` says otherwise
        if self.load_servo is not None and load is None and not self.brake:
            load = self._stage_load
        self._load = load
        self._sample_clock = sample_clock
        self._epoch_s = time.monotonic()
        self._lim = limits_vector(config.limits, self.constants.gear_ratio)
        self._pending_error: RigFaultError | None = None
        self._cycling: threading.Thread | None = None  # the thread inside _run_cycles, if any
        self._streaming = False
        # Device time and, per sample, θ_l, θ_m and the readings of the `daq.channels` inputs (in order).
        self._daq_samples: list[tuple[np.ndarray, np.ndarray]] = []
        self._channels = self.constants.daq.channels if self.constants.daq is not None else {}
        self.extra_columns = tuple(self._channels)
        channels = list(self._channels.values())
        self._channel_adc = [c.adc for c in channels]
        # Each channel's gain, offset and range as a row, for all channels' values in one pass.
        self._channel_gain, self._channel_offset, self._channel_min, self._channel_max = (
            np.array([getattr(c, f) for c in channels]) for f in ("gain", "offset", "min", "max")
        )
        self._analog_rows: dict[str, np.ndarray] = {}
        self._clock_stop = threading.Event()
        self._clock_thread: threading.Thread | None = None
        self.cycle_log: CycleLog | None = None
        self.daq_tally = DaqTally()
        self.supports_feedforward = self._feedforward_refusal() is None
        # The host's loops for a track in CST (rig.control's layout): gains, state, the rate filter.
        self._host_gains = gains_vector(config.control)
        self._host_state = np.zeros(N_CONTROL_STATE)
        self._host_loop_fresh = True
        filter_hz = config.sensors.velocity_filter_hz
        self._rate_alpha = 1.0 - math.exp(-2 * math.pi * filter_hz * self.period_s) if filter_hz else 1.0

    @property
    def gear_ratio(self) -> float:
        return self.constants.gear_ratio

    @property
    def torque_constant_nm_per_a(self) -> float:
        return self.constants.torque_constant_nm_per_a

    def check_segment(self, segment: Segment) -> None:
        if segment.mode == ControlMode.VOLTAGE:
            raise RigError(
                f"rig {self.config.name!r}: segment {segment.label!r} commands the motor voltage, and a"
                " CiA 402 drive has no voltage mode: use current, velocity or position"
            )
        if segment.feedforward is not None:
            refusal = self._feedforward_refusal()
            if refusal is not None:
                raise RigError(f"rig {self.config.name!r}: segment {segment.label!r}: {refusal}")
        super().check_segment(segment)
        if segment.feedforward is None:
            self.servo.choose(segment.mode)  # a mode the drive cannot play: refused before anything moves
        if self.brake and np.any(np.asarray(segment.tau_ext) != 0.0):
            assert self.load_entry is not None
            raise RigError(
                f"rig {self.config.name!r}: segment {segment.label!r} asks for a load torque τ_ext, and the"
                f" load drive (node {self.load_entry.node_id}) has no torque mode: it brakes by holding the"
                " output's speed (hold_output) and cannot apply a set torque: run it with tau_ext 0"
            )
        if self._load is None and np.any(np.asarray(segment.tau_ext) != 0.0):
            raise RigError(
                f"rig {self.config.name!r}: segment {segment.label!r} asks for a load torque τ_ext, and"
                " this bench has no load actuator (a `load` drive in canopen.drives): run it with tau_ext 0"
            )

    def check_modes(self, modes: Collection[ControlMode]) -> list[str]:
        """The drive mode each program runs in and why (`CanopenServo.choose`), or the refusal."""
        lines = []
        for mode in modes:
            try:
                lines.append(f"node {self.servo.settings.node_id}: {self.servo.choose(mode)}")
            except DriveSettingError as exc:
                raise ModeRefusedError(f"rig {self.config.name!r}: {exc}") from None
        return lines

    def _feedforward_refusal(self) -> str | None:
        """Why the drive cannot take a feed-forward torque (one line), None when it can."""
        try:
            self.servo.choose_feedforward()
        except DriveSettingError as exc:
            return str(exc)
        return None

    def record_raw_to(self, run_dir: Path) -> None:
        self.servo.record_to(run_dir / RAW_CAN_LOG)

    # --- power ------------------------------------------------------------------------------------

    def _enable(self) -> None:
        self._pending_error = None
        self._host_loop_fresh = True
        self._start_daq()
        if self.servo.mode is None:
            self.servo.configure(ControlMode.VELOCITY)  # holds still until a segment says otherwise
        self.servo.enable()
        self._enable_load()

    def hold_output(self, speed_rad_s: float | None) -> None:
        """On a bench whose load drive brakes (`brake`): hold the output at `speed_rad_s` [rad/s, the
        output's own, within the load drive's velocity_limit_rad_s] while the axis is powered, from now
        (between segments) or from `enable`; None releases it (speed 0, then disabled: no torque).

        The axis then gives the torque (a current program) and the brake's speed loop takes it: what
        it brakes with is read from its current and from τ_out; no set load torque."""
        entry = self.load_entry
        if not self.brake or entry is None:
            raise RigError(
                f"rig {self.config.name!r}: hold_output needs a load drive that brakes by holding speed (one"
                " without a torque mode); "
                + ("this one applies the load torque τ_ext" if entry else "this bench has no load drive")
            )
        assert entry.velocity_limit_rad_s is not None
        if speed_rad_s is not None and not abs(speed_rad_s) <= entry.velocity_limit_rad_s:
            raise RigError(
                f"rig {self.config.name!r}: hold_output({speed_rad_s:g} rad/s) is beyond the load drive's"
                f" velocity_limit_rad_s {entry.velocity_limit_rad_s:g} rad/s"
            )
        self._brake_speed_rad_s = speed_rad_s
        axis = self.servo.last_feedback
        if self._cycling is None and axis is not None and axis.state == State.OPERATION_ENABLED:
            self._enable_load() if speed_rad_s is not None else self._unload()

    def _enable_load(self) -> None:
        """The load drive after the axis (the arm is held): in torque mode with no torque; a brake holding
        the speed `hold_output` gave, or left disabled while released."""
        load = self.load_servo
        if load is None:
            return
        if load.mode is None:
            load.configure(self._load_choice)  # its answers come every cycle from then on, enabled or not
        if self.brake and self._brake_speed_rad_s is None:
            return
        answer = load.last_feedback
        if answer is None or answer.state != State.OPERATION_ENABLED:
            load.enable()
        load.stage(self._brake_speed_rad_s if self.brake and self._brake_speed_rad_s is not None else 0.0)

    def _unload(self) -> None:
        """The load drive before the axis disables: torque (or the brake's speed) 0, then disabled (never
        turning a free arm)."""
        load = self.load_servo
        if load is None or load.mode is None:
            return
        answer = load.last_feedback
        if self.brake and (answer is None or answer.state != State.OPERATION_ENABLED):
            return  # a released brake: already off
        load.stage(0.0)
        load.disable()

    def _disable(self) -> None:
        try:
            try:
                self._unload()
            finally:
                self.servo.disable()
        finally:
            self._stop_daq()
        self._raise_pending()

    def _stage_load(self, tau_ext_nm: float) -> None:
        """The load drive's torque for the next SYNC: −τ_ext, as its current target."""
        load = self.load_servo
        assert load is not None and load.scaling is not None
        load.stage(-tau_ext_nm / load.scaling.torque_constant_nm_per_a)

    def _quick_stop(self) -> None:
        try:
            self.servo.quick_stop()
        except Exception as exc:  # never raises, by contract; the servo's own path already tried NMT STOP
            logger.error("quick stop: %s", exc)
        if self._cycling is None or self._cycling is threading.current_thread():
            # From another thread while cycling, the cycling thread stops the DAQ when it sees the request.
            try:
                self._stop_daq()
            except Exception as exc:
                logger.warning("quick stop: DAQ not stopped: %s", exc)

    def _faults(self) -> list[str]:
        faults = self.servo.faults()
        if self.load_servo is not None:
            faults += [f"load drive: {fault}" for fault in self.load_servo.faults()]
        if self.daq_tally.flagged:
            faults.append(f"DAQ: {self.daq_tally.flagged} samples with an encoder fault or a clipped θ_l")
        return faults

    def _close(self) -> None:
        self._release()

    def _release(self) -> None:
        """Stop the DAQ's stream and clock thread, close the servo (it quick-stops if powered) and the
        DAQ; each is tried whatever the others do."""
        try:
            if getattr(self, "_streaming", False):
                self._stop_daq()
        except Exception as exc:
            logger.warning("close: DAQ stream not stopped: %s", exc)
        try:
            self.servo.close()
        finally:
            if self.daq is not None:
                self.daq.close()

    # --- the cycle --------------------------------------------------------------------------------

    def _run_cycles(
        self,
        mode: ControlMode,
        setpoint: np.ndarray,
        tau_ext: np.ndarray,
        feedforward: FeedForwardTrack | None = None,
    ) -> tuple[Block, int]:
        self._raise_pending()
        self._cycling = threading.current_thread()
        try:
            self._enter_mode(mode, feedforward is not None)
            rows, t_sync, code = self._cycle_through(setpoint, tau_ext, feedforward)
            self._analog_rows = {name: np.empty(0) for name in self._channels}
            self._fill_theta_l(rows, t_sync)
        except DeviceFaultError as exc:
            self._quick_stop()
            raise RigFaultError(f"rig {self.config.name!r}: {exc}") from exc
        except BaseException:  # a refused setting, a bug: still no torque left behind
            self._quick_stop()
            raise
        finally:
            self._cycling = None
        if self._pending_error is not None and not len(rows):
            self._raise_pending()
        if len(rows):
            self.t_s = float(rows[-1, _COLUMN["t"]]) + self.period_s
        block = {name: rows[:, i] for i, name in enumerate(SAMPLE_COLUMNS)}
        block.update(self._analog_rows)
        return block, code

    def _enter_mode(self, mode: ControlMode, feedforward: bool = False) -> None:
        """Configure the drive for `mode` (with a track: `choose_feedforward`) if it plays another
        program now: disable, remap, enable."""
        if mode == ControlMode.VOLTAGE:
            raise RigError(f"rig {self.config.name!r}: a CiA 402 drive has no {mode} mode")
        choice: ModeChoice = self.servo.choose_feedforward() if feedforward else self.servo.choose(mode)
        if self.servo.choice is not None and self.servo.choice == choice:
            return
        self._unload()
        self.servo.disable()
        self.servo.configure(choice)
        self.servo.enable()
        self._enable_load()
        self._host_loop_fresh = True

    def _cycle_through(
        self, setpoint: np.ndarray, tau_ext: np.ndarray, feedforward: FeedForwardTrack | None = None
    ) -> tuple[np.ndarray, np.ndarray, int]:
        """One servo cycle per set-point; rows (θ_l still unset), SYNC host times, abort code.

        With a track, the drive is sent its planned angle and torque (`_feedforward_target`); the
        recorded set-point and the envelope's position error stay the segment's own.
        """
        n = setpoint.shape[0]
        rows = np.empty((n, len(SAMPLE_COLUMNS)))
        t_sync = np.empty(n)
        constants = self.constants
        current_mode = self.servo.mode in TORQUE_MODES
        choice = self.servo.choice
        position_mode = choice is not None and choice.program == ControlMode.POSITION
        log = self.cycle_log
        code = NO_ABORT
        done = undrained = 0
        paced = self.servo.settings.pace
        for k in range(n):
            if self._stop_requested.is_set():
                break
            target = float(setpoint[k])
            load = float(tau_ext[k])
            if self._load is not None:
                self._load(load)
            try:
                sent, offset_nm = (
                    (target, 0.0) if feedforward is None else self._feedforward_target(feedforward, k)
                )
                feedback = self.servo.cycle(sent, offset_nm)
            except CanopenServoError as exc:  # silent drive, lost bus: stop, keep the rows so far
                self._defer(f"drive lost: {exc}")
                break
            theta_m, omega_m, i_a = feedback.position_rad, feedback.velocity_rad_s, feedback.current_a
            u = constants.resistance_ohm * i_a + constants.back_emf_v_s_rad * omega_m
            row = rows[k]
            row[_COLUMN["t"]] = (
                self._sample_clock(feedback)
                if self._sample_clock is not None
                else feedback.t_s - self._epoch_s
            )
            row[_COLUMN["u"]] = u
            row[_COLUMN["i_cmd"]] = sent if current_mode else i_a
            row[_COLUMN["tau_ext"]] = load
            row[_COLUMN["theta_m"]] = theta_m
            row[_COLUMN["omega_m"]] = omega_m
            row[_COLUMN["i_a"]] = i_a
            row[_COLUMN["setpoint"]] = target
            t_sync[k] = feedback.t_s
            done = k + 1
            position_error = target - theta_m if position_mode else 0.0
            code = envelope_breach(self._lim, u, i_a, omega_m, theta_m, position_error)
            undrained += 1
            if (
                code == NO_ABORT
                and self.daq is not None
                and self._streaming
                and done < n
                and undrained >= DAQ_DRAIN_CYCLES
                and (not paced or time.monotonic() - feedback.t_s <= DAQ_DRAIN_WITHIN_S)
            ):
                # In the period's slack; the chunk's last cycle takes its samples in _fill_theta_l.
                self._take_daq(self.daq.read_samples(timeout_s=0))
                undrained = 0
            if log is not None:
                log.t_sync_s.append(feedback.t_s)
                log.latency_s.append(feedback.latency_s)
                log.t_done_s.append(time.monotonic())
            if code != NO_ABORT:
                break
            if feedback.state != State.OPERATION_ENABLED and not self._stop_requested.is_set():
                faults = "; ".join(self.servo.faults()) or f"statusword 0x{feedback.statusword:04X}"
                self._defer(f"drive left OPERATION ENABLED: {feedback.state} ({faults})")
                break
            if self.load_servo is not None and not self._stop_requested.is_set():
                trouble = self._load_trouble()
                if trouble is not None:
                    self._defer(f"load drive (node {self.load_servo.settings.node_id}): {trouble}")
                    break
        return rows[:done], t_sync[:done], code

    def _load_trouble(self) -> str | None:
        """What is wrong with the load drive after this cycle (its state, EMCYs, trips), None if nothing."""
        load, entry = self.load_servo, self.load_entry
        assert load is not None and entry is not None
        answer = load.last_feedback
        released = self.brake and self._brake_speed_rad_s is None  # disabled on purpose: no torque
        if answer is None or (answer.state != State.OPERATION_ENABLED and not released):
            state = answer.state if answer is not None else "no answer"
            return f"left OPERATION ENABLED: {state} ({'; '.join(load.faults()) or 'no fault reported'})"
        faults = load.faults()
        if faults:
            return "; ".join(faults)
        assert entry.current_trip_a is not None and entry.velocity_trip_rad_s is not None
        if abs(answer.current_a) > entry.current_trip_a:
            return f"|current| {abs(answer.current_a):.3g} A above current_trip_a {entry.current_trip_a:g} A"
        if abs(answer.velocity_rad_s) > entry.velocity_trip_rad_s:
            return (
                f"|speed| {abs(answer.velocity_rad_s):.3g} rad/s above velocity_trip_rad_s"
                f" {entry.velocity_trip_rad_s:g} rad/s"
            )
        return None

    def _feedforward_target(self, track: FeedForwardTrack, k: int) -> tuple[float, float]:
        """Cycle k of a track: (the servo's target, the torque offset [N·m]).

        CSP with 0x60B2: the planned angle and the track's torque. CST: the current of the host's
        position P and velocity PI (rig.control) around the planned angle, the torque added as the
        velocity loop's offset, as the simulated drive adds it, and no separate offset.
        """
        last = self.servo.last_feedback
        assert last is not None  # enable() has had its answers
        omega_rad_s = last.velocity_rad_s
        torque_nm = loop_torque_nm(track.rows, k, track.measured_band_rad_s, omega_rad_s)
        theta_cmd = float(track.theta_cmd_rad[k])
        choice = self.servo.choice
        if choice is None or not choice.host_position_loop:
            return theta_cmd, torque_nm
        state, gains = self._host_state, self._host_gains
        if self._host_loop_fresh:  # as a drive does on enable: loops cleared, the rate from the plan
            state[:] = 0.0
            state[S_PREV_POSITION_REF] = theta_cmd
            state[S_RATE] = 0.0
            self._host_loop_fresh = False
        # The answer is a cycle old: it is compared with the plan of its own cycle (angle and speed
        # advanced by the plan's last step), or the loop would settle with the motor a cycle ahead.
        theta_rad = last.position_rad + theta_cmd - state[S_PREV_POSITION_REF]
        rate_before = state[S_RATE]
        period = self.period_s
        omega_ref = position_p(gains, state, theta_cmd, theta_rad, period, self._rate_alpha)
        omega_rad_s += state[S_RATE] - rate_before
        offset_a = torque_nm / self.constants.torque_constant_nm_per_a
        return velocity_pi(gains, state, omega_ref, omega_rad_s, period, offset_a), 0.0

    def _defer(self, what: str) -> None:
        """Stop the drive now; the error ends the segment at the next call, after the rows so far (the
        DAQ streams on to align them, and stops with the rig's quick stop or close)."""
        self.servo.quick_stop()
        self._pending_error = RigFaultError(f"rig {self.config.name!r}: {what}")

    def _raise_pending(self) -> None:
        error, self._pending_error = self._pending_error, None
        if error is not None:
            raise error

    # --- the DAQ ----------------------------------------------------------------------------------

    def _fill_theta_l(self, rows: np.ndarray, t_sync: np.ndarray) -> None:
        """θ_l of each row: the DAQ's output angle at the row's SYNC time (or r·θ_m without a DAQ).

        Interpolated between the DAQ samples around each SYNC. Paced, the wait for a sample after the
        chunk's last SYNC ends in time for the next SYNC; rows still beyond the newest sample then
        (at most EXTRAPOLATE_MAX_PERIODS) are extrapolated along its last two samples, and counted.
        """
        if not len(rows):
            return
        log = self.cycle_log
        if self.daq is None:
            rows[:, _COLUMN["theta_l"]] = self.constants.gear_ratio * rows[:, _COLUMN["theta_m"]]
            if log is not None:
                log.daq_theta_m_rad.extend([math.nan] * len(rows))
            return
        t_last = float(t_sync[-1])
        if self.servo.settings.pace:
            budget = t_last + self.period_s - ALIGN_MARGIN_S - time.monotonic()
            try:
                # No time left (the usual case): what there is, without raising and formatting a timeout.
                block = self.daq.read_until(t_last, timeout_s=budget) if budget > 0 else None
            except DaqError:  # not in yet, or a dead line: take what there is, judge below
                block = None
            self._take_daq(block if block is not None else self.daq.read_samples(timeout_s=0))
        else:
            self._take_daq(self.daq.read_until(t_last))
        t_device, values = self._merged_daq()
        t_host = self.daq.host_time_s(t_device)  # one clock model for old and new samples alike
        stream = self.constants.daq or DaqStreamSettings()
        reach_s = EXTRAPOLATE_MAX_PERIODS * self.period_s + stream.samples_per_frame / stream.rate_hz
        if not len(t_host) or t_host[-1] < t_last - reach_s:
            self._take_daq(self.daq.read_until(t_last))  # too far behind to extrapolate: wait (or fail)
            t_device, values = self._merged_daq()
            t_host = self.daq.host_time_s(t_device)
        self.daq_tally.extrapolated += int(np.count_nonzero(t_sync > t_host[-1]))
        aligned = _interpolate_rows(t_sync, t_host, values)  # θ_l, θ_m, the channels' readings
        rows[:, _COLUMN["theta_l"]] = aligned[:, 0]
        keep = max(0, int(np.searchsorted(t_host, t_last, side="right")) - 1)
        if self._channels:
            self._analog_rows = self._analog_values(aligned[:, 2:])
        self._daq_samples = [(t_device[keep:], values[keep:])]
        if log is not None:
            log.t_done_s[-1] = time.monotonic()  # the chunk's last cycle waited for the alignment
            # The log's own check, not the loop's work: after the cycle is done.
            log.daq_theta_m_rad.extend(aligned[:, 1].tolist())

    def _analog_values(self, readings: np.ndarray) -> dict[str, np.ndarray]:
        """Each `daq.channels` column from its readings at the SYNC times (rows × channels), as
        `AnalogChannel.value` gives it (NaN outside the sensor's range, counted): all channels in one
        pass of array operations, at a chunk's end, in its last cycle."""
        value = readings * self._channel_gain + self._channel_offset
        value[(value < self._channel_min) | (value > self._channel_max)] = np.nan  # NaN stays NaN
        self.daq_tally.out_of_range += int(np.count_nonzero(np.isnan(value)))
        by_channel = np.ascontiguousarray(value.T)  # each channel's column contiguous
        return dict(zip(self._channels, by_channel, strict=True))

    def _merged_daq(self) -> tuple[np.ndarray, np.ndarray]:
        """The samples kept so far as one array each (device time; θ_l, θ_m, readings a row), kept so."""
        if not self._daq_samples:
            return np.empty(0), np.empty((0, 2 + len(self._channel_adc)))
        if len(self._daq_samples) > 1:
            t_device = np.concatenate([part[0] for part in self._daq_samples])
            values = np.concatenate([part[1] for part in self._daq_samples])
            if np.any(t_device[1:] <= t_device[:-1]):  # a late frame read after its successors: into place
                t_device, keep = np.unique(t_device, return_index=True)
                values = values[keep]
            self._daq_samples = [(t_device, values)]
        return self._daq_samples[0]

    def _take_daq(self, block: SampleBlock) -> None:
        self.daq_tally.add(block)
        if not len(block):
            return
        if self._channel_adc:
            if block.adc is None:
                name = next(iter(self._channels))
                raise DaqError(f"DAQ: samples without the analog inputs that daq.channels.{name} reads")
            values = np.column_stack((block.theta_l_rad, block.theta_m_rad, block.adc[:, self._channel_adc]))
        else:
            values = np.column_stack((block.theta_l_rad, block.theta_m_rad))
        self._daq_samples.append((block.t_device_s, values))
        self._merged_daq()  # each take, in the slack it is taken in: not all at the chunk's end

    def _start_daq(self) -> None:
        if self.daq is None or self._streaming:
            return
        stream = self.constants.daq or DaqStreamSettings()
        self.daq.estimate_clock_offset(CLOCK_EXCHANGES_AT_START)
        self.daq.start()
        self._streaming = True
        self.daq_tally.new_stream()
        self._daq_samples = []
        if stream.clock_every_s > 0:
            self._clock_stop.clear()
            self._clock_thread = threading.Thread(
                target=self._keep_clock, args=(stream.clock_every_s,), name="hdrig daq clock", daemon=True
            )
            self._clock_thread.start()

    def _keep_clock(self, every_s: float) -> None:
        daq = self.daq
        assert daq is not None
        while not self._clock_stop.wait(every_s):
            try:
                daq.estimate_clock_offset(CLOCK_EXCHANGES_WHILE_STREAMING)
            except DaqError as exc:  # the cycling thread meets a dead line itself
                logger.warning("DAQ clock estimate failed: %s", exc)

    def _stop_daq(self) -> None:
        if self.daq is None or not self._streaming:
            return
        self._streaming = False
        self._clock_stop.set()
        if self._clock_thread is not None:
            self._clock_thread.join()
            self._clock_thread = None
        self.daq_tally.streams.append(self.daq.stop())
        self.daq_tally.add(self.daq.read_samples(timeout_s=0))  # the stream's tail: delivered, unused
        self._daq_samples = []


def worst_bus_load(servos: list[CanopenServo], period_s: float) -> BusLoad:
    """The bus load of the servos' cyclic frames, each at the largest RPDO 1 of the cyclic modes its
    dictionary can map (a torque offset included), so that no later mode change goes over the limit."""
    plans = []
    for servo in servos:
        tpdo1, tpdo2 = tpdo_layouts(servo.od)
        layouts = []
        for mode in (
            OperationMode.CYCLIC_SYNC_TORQUE,
            OperationMode.CYCLIC_SYNC_VELOCITY,
            OperationMode.CYCLIC_SYNC_POSITION,
        ):
            for offset in (False, True):
                try:
                    layouts.append(rpdo_layout(servo.od, mode, offset))
                except (CanopenConfigError, KeyError, ValueError):
                    continue  # a mode or offset the drive cannot map: never sent
        if layouts:
            rpdo = max(layouts, key=lambda layout: layout.length)
            plans.append(PdoPlan(rpdo, tpdo1, tpdo2, servo.settings.node_id))
    bitrate = servos[0].settings.bitrate
    return bus_load(plans, period_s, bitrate)


def _interpolate_rows(t: np.ndarray, t_samples: np.ndarray, values: np.ndarray) -> np.ndarray:
    """`values` (samples × columns) at times `t` (rows × columns): linear between the samples around each
    time, along the last two past the newest one, the first sample's before it (as np.interp). The
    samples' times increase strictly. One search and one weight for all columns."""
    n = len(t_samples)
    if n < 2:
        return np.repeat(values[:1], len(t), axis=0)
    j = np.searchsorted(t_samples, t, side="right") - 1
    np.clip(j, 0, n - 2, out=j)
    t0 = t_samples[j]
    weight = (t - t0) / (t_samples[j + 1] - t0)
    np.maximum(weight, 0.0, out=weight)
    below = values[j]
    return below + weight[:, None] * (values[j + 1] - below)
