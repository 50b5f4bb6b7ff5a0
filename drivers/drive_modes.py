"""Which CiA 402 mode of operation runs each kind of program, chosen from what the drive offers.

A drive says what it offers in 0x6502 (supported drive modes) and in its object dictionary: a mode is
usable here only if its target object is there and PDO-mappable, since the driver sends a target every
SYNC. Each program the rig plays (current, velocity, position: `rig.interface.ControlMode`) takes the
first usable mode of its preference list:

- current: cyclic synchronous torque, else profile torque (both take 0x6071 in ‰ of rated torque);
- velocity: cyclic synchronous velocity; else cyclic synchronous position with the speed integrated
  by the host; else profile velocity (the drive ramps at 0x6083/0x6084); else interpolated position
  paced by SYNC (the speed integrated by the host);
- position: cyclic synchronous position, else interpolated position paced by SYNC.

Profile position is not chosen: it takes a set-point per handshake (controlword bit 4, acknowledged
by statusword bit 12), one every second SYNC at best, and plans its own trajectory between them.

A position program with a model's feed-forward torque (`model.feedforward`) needs a way to add a torque
every SYNC: cyclic synchronous position with the torque offset 0x60B2 mapped beside the target (the
drive's own loops close, the host adds the torque), else cyclic synchronous torque with the position
and speed loops closed on the host (`drivers.hardware_rig`). Cyclic synchronous velocity with 0x60B2 is
not chosen: the twin's speed loop takes no offset, so that path could not be tested here.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Final

from canopen.objectdictionary import ObjectDictionary

from drivers.cia402 import SUPPORTED_MODE_BIT, TARGET_OBJECT, OperationMode
from drivers.pdo_layout import od_variable
from model.errors import UserInputError
from rig.interface import ControlMode

PREFERENCE: Final[dict[ControlMode, tuple[OperationMode, ...]]] = {
    ControlMode.CURRENT: (OperationMode.CYCLIC_SYNC_TORQUE, OperationMode.PROFILE_TORQUE),
    ControlMode.VELOCITY: (
        OperationMode.CYCLIC_SYNC_VELOCITY,
        OperationMode.CYCLIC_SYNC_POSITION,
        OperationMode.PROFILE_VELOCITY,
        OperationMode.INTERPOLATED_POSITION,
    ),
    ControlMode.POSITION: (OperationMode.CYCLIC_SYNC_POSITION, OperationMode.INTERPOLATED_POSITION),
}
"""Per program, the drive modes that can play it, best first."""

WHY: Final[dict[tuple[ControlMode, OperationMode], str]] = {
    (ControlMode.CURRENT, OperationMode.CYCLIC_SYNC_TORQUE): "the torque target every SYNC",
    (ControlMode.CURRENT, OperationMode.PROFILE_TORQUE): "no CST: the torque target, ramped at 0x6087",
    (ControlMode.VELOCITY, OperationMode.CYCLIC_SYNC_VELOCITY): "the speed target every SYNC",
    (ControlMode.VELOCITY, OperationMode.CYCLIC_SYNC_POSITION): "no CSV: the speed integrated to positions",
    (ControlMode.VELOCITY, OperationMode.PROFILE_VELOCITY): "no cyclic mode: the drive ramps at 0x6083",
    (ControlMode.VELOCITY, OperationMode.INTERPOLATED_POSITION): (
        "no cyclic or profile velocity mode: the speed integrated to positions, interpolated per SYNC"
    ),
    (ControlMode.POSITION, OperationMode.CYCLIC_SYNC_POSITION): "the position target every SYNC",
    (ControlMode.POSITION, OperationMode.INTERPOLATED_POSITION): "no CSP: positions interpolated per SYNC",
}

BRAKE_MODES: Final = (OperationMode.CYCLIC_SYNC_VELOCITY, OperationMode.PROFILE_VELOCITY)
"""A load drive without a torque mode brakes in these, best first: its own speed loop holds the speed."""
BRAKE_WHY: Final = "it cannot apply a set torque; its speed loop gives whatever torque holds the speed"

TORQUE_OFFSET: Final = (0x60B2, 0)
"""CiA 402 torque offset, ‰ of the motor rated torque (0x6076), added to the drive's torque demand."""
FEEDFORWARD_WHY: Final[dict[OperationMode, str]] = {
    OperationMode.CYCLIC_SYNC_POSITION: "the planned angle every SYNC, the model's torque in 0x60B2",
    OperationMode.CYCLIC_SYNC_TORQUE: (
        "no 0x60B2 mappable in CSP: the torque every SYNC, position and speed loops closed on the host"
    ),
}

MODE_NAMES: Final[dict[OperationMode, str]] = {
    OperationMode.PROFILE_POSITION: "profile position",
    OperationMode.PROFILE_VELOCITY: "profile velocity",
    OperationMode.PROFILE_TORQUE: "profile torque",
    OperationMode.HOMING: "homing",
    OperationMode.INTERPOLATED_POSITION: "interpolated position",
    OperationMode.CYCLIC_SYNC_POSITION: "cyclic synchronous position",
    OperationMode.CYCLIC_SYNC_VELOCITY: "cyclic synchronous velocity",
    OperationMode.CYCLIC_SYNC_TORQUE: "cyclic synchronous torque",
}

ObjectReader = Callable[[int, int], int | None]
"""Reads an object from the drive (index, sub-index); None when the drive holds no value for it."""


@dataclass(frozen=True)
class ModeChoice:
    """The drive mode a program runs in, and why."""

    program: ControlMode
    mode: OperationMode
    why: str
    feedforward: bool = False
    """The program carries a model's torque: 0x60B2 mapped in CSP, or the host's loops in CST."""

    @property
    def torque_offset(self) -> bool:
        """RPDO 1 carries the torque offset 0x60B2 after the target."""
        return self.feedforward and self.mode != OperationMode.CYCLIC_SYNC_TORQUE

    @property
    def host_position_loop(self) -> bool:
        """A position program played as torques: the host closes the position and speed loops."""
        return self.program == ControlMode.POSITION and self.mode == OperationMode.CYCLIC_SYNC_TORQUE

    @property
    def integrates_speed(self) -> bool:
        """A velocity program played in a position mode: the host sums speed · period into targets."""
        return self.program == ControlMode.VELOCITY and self.mode in POSITION_MODES

    def __str__(self) -> str:
        what = f"{self.program} programs{' with feed-forward' if self.feedforward else ''}"
        return f"{what} in {MODE_NAMES[self.mode]} (mode {int(self.mode)}): {self.why}"


POSITION_MODES: Final = frozenset({OperationMode.CYCLIC_SYNC_POSITION, OperationMode.INTERPOLATED_POSITION})


class ModeUnavailableError(UserInputError):
    """No mode of the drive plays a program; the message names what the drive offers."""


@dataclass(frozen=True)
class DriveModes:
    """What a drive offers: its supported modes, those usable cycle by cycle, and where that was read."""

    supported: frozenset[OperationMode]
    usable: frozenset[OperationMode]
    source: str
    """Where `supported` came from: the drive's 0x6502, the EDS default, or the target objects."""
    torque_offset: bool = False
    """The torque offset 0x60B2 is there and PDO-mappable."""

    @classmethod
    def of(cls, od: ObjectDictionary, read: ObjectReader | None = None) -> DriveModes:
        """From 0x6502 read from the drive (`read`), else its EDS default, else the target objects."""
        bits, source = None, ""
        if _has(od, 0x6502):
            if read is not None:
                bits, source = read(0x6502, 0), "0x6502 read from the drive"
            if bits is None:
                default = od_variable(od, 0x6502).default
                bits, source = (default, "0x6502 of the EDS") if isinstance(default, int) else (None, "")
        if bits is None:
            supported = frozenset(m for m, target in TARGET_OBJECT.items() if _has(od, *target))
            source = "no 0x6502 value: the modes whose target objects the EDS has"
        else:
            supported = frozenset(m for m, bit in SUPPORTED_MODE_BIT.items() if bits & bit)
        usable = frozenset(m for m in supported if m in TARGET_OBJECT and _mappable(od, *TARGET_OBJECT[m]))
        return cls(supported, usable, source, _mappable(od, *TORQUE_OFFSET))

    def choose(self, program: ControlMode) -> ModeChoice:
        """The best usable mode for `program`; ModeUnavailableError naming what the drive offers if none."""
        for mode in PREFERENCE.get(program, ()):
            if mode in self.usable:
                return ModeChoice(program, mode, WHY[(program, mode)])
        raise ModeUnavailableError(f"the drive has no mode for {program} programs: it offers {self.offer()}")

    def choose_feedforward(self) -> ModeChoice:
        """The mode a position program with a model's torque runs in: CSP with 0x60B2 mappable, else CST
        (the host closes the loops); ModeUnavailableError naming what is missing if neither."""
        csp, cst = OperationMode.CYCLIC_SYNC_POSITION, OperationMode.CYCLIC_SYNC_TORQUE
        if csp in self.usable and self.torque_offset:
            return ModeChoice(ControlMode.POSITION, csp, FEEDFORWARD_WHY[csp], feedforward=True)
        if cst in self.usable:
            return ModeChoice(ControlMode.POSITION, cst, FEEDFORWARD_WHY[cst], feedforward=True)
        missing = [
            *(["the torque offset 0x60B2 PDO-mappable"] if not self.torque_offset else []),
            *(["cyclic synchronous position"] if csp not in self.usable else []),
            "cyclic synchronous torque",
        ]
        raise ModeUnavailableError(
            f"a feed-forward torque needs cyclic synchronous position with the torque offset 0x60B2"
            f" PDO-mappable, or cyclic synchronous torque; the drive lacks {_listed(missing)}:"
            f" it offers {self.offer()}"
        )

    def choose_load(self) -> ModeChoice:
        """A load drive's mode: a torque mode (CST, else profile torque) to apply the load torque; without
        one, a velocity mode (CSV, else PV) to brake by holding its shaft's speed; ModeUnavailableError
        naming what the drive offers if neither."""
        for mode in PREFERENCE[ControlMode.CURRENT]:
            if mode in self.usable:
                return ModeChoice(ControlMode.CURRENT, mode, WHY[(ControlMode.CURRENT, mode)])
        for mode in BRAKE_MODES:
            if mode in self.usable:
                return ModeChoice(
                    ControlMode.VELOCITY, mode, f"no torque mode: a brake holding speed ({BRAKE_WHY})"
                )
        raise ModeUnavailableError(
            "a load drive needs a torque mode (CST, profile torque) or, to brake by holding speed, cyclic"
            f" synchronous or profile velocity: it offers {self.offer()}"
        )

    def offer(self) -> str:
        """What the drive offers, for a one-line refusal."""
        names = [f"{MODE_NAMES.get(m, m.name.lower())} ({int(m)})" for m in sorted(self.supported)]
        unusable = sorted(self.supported - self.usable)
        text = ", ".join(names) or "no mode"
        if unusable:
            text += f"; cycle by cycle only {', '.join(MODE_NAMES[m] for m in sorted(self.usable)) or 'none'}"
        return f"{text} ({self.source})"

    def refusal(self, programs: Iterable[ControlMode]) -> str | None:
        """Why the drive cannot play all of `programs`, in one line; None when it can."""
        for program in programs:
            try:
                self.choose(program)
            except ModeUnavailableError as exc:
                return str(exc)
        return None


def _listed(items: list[str]) -> str:
    return " and ".join(items) if len(items) < 3 else f"{', '.join(items[:-1])} and {items[-1]}"


def _has(od: ObjectDictionary, index: int, subindex: int = 0) -> bool:
    try:
        od_variable(od, index, subindex)
    except KeyError:
        return False
    return True


def _mappable(od: ObjectDictionary, index: int, subindex: int) -> bool:
    return _has(od, index, subindex) and bool(od_variable(od, index, subindex).pdo_mappable)
