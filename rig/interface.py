"""The one rig interface. Every backend — simulated in-process, CANopen + serial DAQ, their twins on a
virtual bus — is a `Rig`; nothing above this module knows which one it has.

As python-can's `BusABC` does for `recv`, the public `run_segment` does the shared work (checking the
segment against the envelope, chunking, handing blocks to the sink, quick-stopping on a breach) and
calls one small hook, `_run_cycles`, that each backend implements. A rig config's `backend:` name finds
its backend in a table of module paths imported when named (`BUILTIN_BACKENDS`) or in the entry points
of `hdrig.backends`, never through `if` chains, and this module imports none of them.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import math
import threading
from abc import ABC, abstractmethod
from collections.abc import Callable, Collection
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path

import numpy as np

from model.errors import UserInputError
from model.feedforward import FeedForwardTrack
from model.params import HarmonicDriveModel
from rig.config import RigConfig
from rig.faults import DeviceFaultError
from rig.rig_lock import RigLock
from rig.safety import ABORT_REASONS, NO_ABORT


class ControlMode(StrEnum):
    """What a segment commands: motor voltage, motor current, motor speed or motor position."""

    VOLTAGE = "voltage"
    CURRENT = "current"
    VELOCITY = "velocity"
    POSITION = "position"


SETPOINT_UNIT = {"voltage": "V", "current": "A", "velocity": "rad/s", "position": "rad"}

SAMPLE_COLUMNS = ("t", "u", "i_cmd", "tau_ext", "theta_m", "omega_m", "theta_l", "i_a", "setpoint")
"""What a rig records each cycle. `u` is the motor voltage applied, `i_cmd` the current the drive
commanded (both always present: a drive knows both), `setpoint` the segment's set-point."""


class RigError(UserInputError):
    """A command the rig refuses before anything moves: a set-point beyond its limits, a mode or a load
    it has not, an unknown backend. The user can fix it in the experiment or the rig file."""


class ModeRefusedError(RigError):
    """The rig cannot play a kind of program an experiment needs (a CiA 402 drive without the mode):
    told before anything moves; a campaign skips that experiment and goes on."""


class RigFaultError(DeviceFaultError):
    """The bench failed during a segment (a drive fault, a silent drive or DAQ); the rig has quick-stopped
    and the rows up to the fault have reached the sink."""


@dataclass(frozen=True)
class Segment:
    """One stretch of an experiment: a mode, one set-point per cycle, the load torque per cycle.

    `feedforward` (position mode, rigs with `supports_feedforward`): a model's track, one row per cycle;
    the drive follows its planned angle and adds its torque (`model.feedforward`). The recorded
    `setpoint` stays the segment's own.
    """

    mode: ControlMode
    setpoint: np.ndarray
    tau_ext: np.ndarray | float = 0.0
    label: str = ""
    feedforward: FeedForwardTrack | None = None

    @property
    def cycles(self) -> int:
        return int(self.setpoint.shape[0])


@dataclass
class Health:
    """What the rig says of itself: enabled, faults, the reason of the last abort."""

    enabled: bool
    faults: list[str] = field(default_factory=list)
    last_abort: str | None = None

    @property
    def ok(self) -> bool:
        return not self.faults


Block = dict[str, np.ndarray]
BlockSink = Callable[[Block], None]
ProgressCallback = Callable[[float], None]
"""Called with the fraction of the segment done, 0..1."""


@dataclass(frozen=True)
class SegmentResult:
    cycles: int
    aborted: str | None = None


class Rig(ABC):
    """A test bench seen by the experiments: commands in, timestamped samples out, within limits."""

    def __init__(self, config: RigConfig) -> None:
        self.config = config
        self.period_s = 1.0 / config.sample_rate_hz
        self._enabled = False
        self._last_abort: str | None = None
        self._stop_requested = threading.Event()
        self._stop_why: str | None = None  # who asked for the pending quick stop, for the abort reason
        self.t_s = 0.0  # rig clock: time of the next sample [s]
        self._lock: RigLock | None = None  # a hardware rig's, taken by open_rig

    # --- the promises every backend keeps ---------------------------------------------------------

    def enable(self) -> None:
        """Power the drive (CiA 402: OPERATION ENABLED). Clears a previous quick stop."""
        self._stop_requested.clear()
        self._stop_why = None
        self._enable()
        self._enabled = True

    def disable(self) -> None:
        """Orderly stop: ramp to zero and remove power."""
        if self._enabled:
            self._disable()
        self._enabled = False

    def quick_stop(self, why: str | None = None) -> None:
        """Defensive stop: always safe to call, from any thread, any number of times, in any state.

        `why` (e.g. "quick stop by alice") becomes the aborted segment's reason, `aborted: <why>`; the
        first stop asked since `enable()` names it (default: `aborted: quick stop requested`)."""
        if why is not None and not self._stop_requested.is_set():
            self._stop_why = why
        self._stop_requested.set()
        self._quick_stop()
        self._enabled = False

    def health(self) -> Health:
        return Health(enabled=self._enabled, faults=self._faults(), last_abort=self._last_abort)

    def close(self) -> None:
        """Release the bus/port/plant; quick-stops first if still enabled."""
        if self._enabled:
            self.quick_stop()
        self._close()
        if self._lock is not None:
            self._lock.release()

    def __enter__(self) -> Rig:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def run_segment(
        self,
        segment: Segment,
        sink: BlockSink,
        progress: ProgressCallback | None = None,
        chunk_s: float = 0.25,
    ) -> SegmentResult:
        """Run a segment cycle by cycle; each block of samples goes to `sink` as it is taken.

        A breach of the envelope quick-stops the rig and returns the reason in `aborted` (the samples
        up to and including the breaching one have already reached the sink). `quick_stop()` from
        another thread ends the segment the same way, and so does one that came before the segment
        (between two segments, or an earlier abort): nothing moves until `enable()`. A device fault
        (`DeviceFaultError`) quick-stops the rig, is kept as its last abort, and is raised.
        """
        if self._stop_requested.is_set():
            return self._abort(SegmentResult(0, self._stop_reason()))
        if not self._enabled:  # never enabled: the caller's bug, neither bad input nor a device fault
            raise RuntimeError(f"rig {self.config.name!r} is not enabled: call enable() first")
        self.check_segment(segment)
        tau = np.broadcast_to(np.asarray(segment.tau_ext, dtype=np.float64), (segment.cycles,))
        chunk = max(1, round(chunk_s / self.period_s))
        done = 0
        while done < segment.cycles:
            if self._stop_requested.is_set():
                return self._abort(SegmentResult(done, self._stop_reason()))
            n = min(chunk, segment.cycles - done)
            try:
                if segment.feedforward is None:
                    block, code = self._run_cycles(
                        segment.mode, segment.setpoint[done : done + n], tau[done : done + n]
                    )
                else:  # only backends with supports_feedforward take it (check_segment saw to that)
                    with_track: Callable[..., tuple[Block, int]] = self._run_cycles
                    part = segment.feedforward.part(done, done + n)
                    if self.temp_gear_c is not None:  # the friction at the gear's last measured temperature
                        part = part.at_temperature(self.temp_gear_c)
                    setpoint = segment.setpoint[done : done + n]
                    block, code = with_track(segment.mode, setpoint, tau[done : done + n], feedforward=part)
            except DeviceFaultError as fault:
                self._abort(SegmentResult(done, f"aborted: {fault}"))
                raise
            got = len(block["t"])
            done += got
            if got and "temp_gear" in block:
                self.temp_gear_c = float(block["temp_gear"][-1])
            if got:
                sink(block)
            if progress is not None:
                progress(done / segment.cycles)
            if code != NO_ABORT:
                return self._abort(SegmentResult(done, "aborted: " + self._describe_breach(code, block)))
        return SegmentResult(done)

    # --- what a backend implements ------------------------------------------------------------------

    @abstractmethod
    def _run_cycles(self, mode: ControlMode, setpoint: np.ndarray, tau_ext: np.ndarray) -> tuple[Block, int]:
        """Run len(setpoint) cycles; return the samples taken (SAMPLE_COLUMNS) and an abort code.

        Must check the envelope every cycle with `rig.safety.envelope_breach` and stop at the first
        breach, returning the samples up to and including it. A backend with `supports_feedforward`
        also takes `feedforward=` (a FeedForwardTrack of these cycles) for position segments that carry one.
        """

    @abstractmethod
    def _enable(self) -> None: ...

    @abstractmethod
    def _disable(self) -> None: ...

    @abstractmethod
    def _quick_stop(self) -> None:
        """Must not raise and must be safe to call again; the drive must end without torque."""

    def _faults(self) -> list[str]:
        return []

    def record_raw_to(self, run_dir: Path) -> None:
        """Where to keep the backend's raw traffic for the run being recorded (hardware: the CAN log).

        The runner calls it before each run with the run's folder; backends without raw traffic ignore it.
        """
        return None

    def _close(self) -> None:
        return None

    # --- shared helpers ---------------------------------------------------------------------------------

    def _stop_reason(self) -> str:
        return f"aborted: {self._stop_why or 'quick stop requested'}"

    def _abort(self, result: SegmentResult) -> SegmentResult:
        self.quick_stop()
        self._last_abort = result.aborted
        return result

    def _describe_breach(self, code: int, block: Block) -> str:
        last = {name: float(values[-1]) for name, values in block.items() if len(values)}
        limits = self.config.limits
        what = {
            "current": f"|i_a| = {abs(last.get('i_a', math.nan)):.3g} A > {limits.current_a} A",
            "voltage": f"|u| = {abs(last.get('u', math.nan)):.3g} V > {limits.voltage_v} V",
            "velocity": f"|omega_m| = {abs(last.get('omega_m', math.nan)):.4g} rad/s"
            f" > {limits.velocity_rad_s} rad/s",
            "travel": f"output angle {last.get('theta_m', math.nan) * self.gear_ratio:.4g} rad outside"
            f" [{limits.travel_min_out_rad}, {limits.travel_max_out_rad}]",
            "following": f"position error beyond {limits.following_error_out_rad} rad at the output",
        }[ABORT_REASONS[code]]
        return f"{ABORT_REASONS[code]} limit: {what} at t = {last.get('t', math.nan):.4f} s"

    @property
    @abstractmethod
    def gear_ratio(self) -> float:
        """Output/input ratio r of the transmission on the bench (0.01 for 100:1)."""

    @property
    @abstractmethod
    def torque_constant_nm_per_a(self) -> float:
        """Motor torque per ampere, to turn measured current into torque [N·m/A]."""

    source: str = "hardware"
    """What docs/INTERFACE.md's `source` metadata says of this rig's runs: `sim` or `hardware`."""

    model: HarmonicDriveModel | None = None
    """The model a simulated rig runs (None on hardware): recorded with each run."""

    supports_feedforward: bool = False
    """Whether `_run_cycles` takes a feed-forward track (`Segment.feedforward`)."""

    extra_columns: tuple[str, ...] = ()
    """Optional run-format columns this rig records beside SAMPLE_COLUMNS in every block (docs/INTERFACE.md:
    `temp_gear`, `temp_motor`, `tau_in`, `tau_out`), when it has the sensors."""

    temp_gear_c: float | None = None
    """The gear's last measured temperature (a rig recording `temp_gear`): a feed-forward track with a
    thermal law plays its friction at it (`FeedForwardTrack.at_temperature`) [°C]."""

    def check_modes(self, modes: Collection[ControlMode]) -> list[str]:
        """Before anything moves: how this rig plays programs of `modes`, one line each (none: as
        asked). A mode it cannot play is a UserInputError in one line saying what the rig offers."""
        return []

    def check_segment(self, segment: Segment) -> None:
        """Refuse a segment whose set-points the rig cannot or must not follow (RigError)."""
        sp = np.asarray(segment.setpoint)
        if sp.ndim != 1 or sp.shape[0] == 0 or not np.all(np.isfinite(sp)):
            raise RigError(f"segment {segment.label!r}: set-points must be a non-empty finite 1-D array")
        limits, control = self.config.limits, self.config.control
        peak = float(np.max(np.abs(sp)))
        bound = {
            ControlMode.VOLTAGE: control.supply_voltage_v,
            ControlMode.CURRENT: control.current_limit_a,
            ControlMode.VELOCITY: control.max_velocity_rad_s,
        }.get(segment.mode)
        if bound is not None and peak > bound:
            unit = SETPOINT_UNIT[segment.mode]
            raise RigError(
                f"segment {segment.label!r}: {segment.mode} set-point {peak:g} {unit}"
                f" beyond the rig's {bound:g} {unit}"
            )
        if segment.feedforward is not None:
            if segment.mode != ControlMode.POSITION or not self.supports_feedforward:
                raise RigError(
                    f"segment {segment.label!r}: a feed-forward track needs a position segment on a rig"
                    f" whose drive takes one; rig {self.config.name!r} ({self.config.backend}) with"
                    f" {segment.mode} set-points does not"
                )
            if segment.feedforward.cycles != segment.cycles:
                raise RigError(
                    f"segment {segment.label!r}: feed-forward track of {segment.feedforward.cycles} cycles"
                    f" for {segment.cycles} set-points"
                )
        if segment.mode == ControlMode.POSITION:
            out = sp * self.gear_ratio
            if out.min() < limits.travel_min_out_rad or out.max() > limits.travel_max_out_rad:
                raise RigError(
                    f"segment {segment.label!r}: position set-points reach output angles"
                    f" [{out.min():.3g}, {out.max():.3g}] rad, outside the travel"
                    f" [{limits.travel_min_out_rad}, {limits.travel_max_out_rad}]"
                )


BUILTIN_BACKENDS = {
    "sim": "sim_backend.inprocess:SimRig",
    "virtual-can": "sim_backend.virtual_bus:VirtualCanRig",
    "canopen": "drivers.hardware_rig:HardwareRig",
}
"""A rig config's `backend:` name → "module:Class", imported only when a config names it (python-can's
`BACKENDS` table): `rig` imports no backend, and a backend's CAN or serial stack loads only when used."""

ENTRY_POINT_GROUP = "hdrig.backends"
"""Where a lab's own backend is found without editing hdrig: in its package's metadata,
`[project.entry-points."hdrig.backends"] my-bench = "my_lab.bench:MyBenchRig"`. The entry point's name is
the `backend:` name; a built-in name wins over an entry point of the same name."""


def backend_names() -> list[str]:
    """Every backend a rig config may name: the built-in ones and those installed as entry points."""
    return sorted({*BUILTIN_BACKENDS, *(ep.name for ep in _entry_points())})


def backend_class(name: str) -> type[Rig]:
    """The class of the backend called `name`, imported now; RigError naming the known ones if none is."""
    target = BUILTIN_BACKENDS.get(name)
    if target is None:
        target = next((ep.value for ep in _entry_points() if ep.name == name), None)
    if target is None:
        raise RigError(f"unknown backend {name!r} (backends: {', '.join(backend_names())})")
    module_name, _, class_name = target.partition(":")
    # A backend that fails to import is a bug or a broken install, not a user's mistake: not caught.
    found = getattr(importlib.import_module(module_name), class_name)
    if not (isinstance(found, type) and issubclass(found, Rig)):
        raise TypeError(f"backend {name!r}: {target} is not a Rig subclass")
    return found


def _entry_points() -> importlib.metadata.EntryPoints:
    return importlib.metadata.entry_points(group=ENTRY_POINT_GROUP)


def open_rig(config: RigConfig) -> Rig:
    """The backend a rig config names, constructed on it."""
    try:
        cls = backend_class(config.backend)
    except RigError as error:
        raise RigError(f"rig {config.name!r}: {error}") from None
    # A hardware bench takes one process at a time (a second would command the same drive).
    lock = RigLock.take(config.name) if cls.source == "hardware" else None
    try:
        rig = cls(config)
    except BaseException:
        if lock is not None:
            lock.release()
        raise
    rig._lock = lock
    return rig


def open_simulated_rig(config: RigConfig, model: HarmonicDriveModel, theta_m: float = 0.0) -> Rig:
    """The in-process simulated rig (`sim`) on `config`'s settings, running `model` (an object, not a
    file) from motor angle `theta_m` [rad]: what validation replays a measured run on."""
    simulated: Callable[..., Rig] = backend_class("sim")
    return simulated(config.model_copy(update={"backend": "sim"}), model=model, theta_m=theta_m)
