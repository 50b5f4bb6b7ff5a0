"""The CiA 402 drive profile: statusword states, controlword commands, the transition table, modes.

One copy, read both ways: the servo driver walks the table towards the state it wants
(`command_towards`), the simulated drive applies it to the controlword it receives (`next_state`).
"""

from __future__ import annotations

from collections import deque
from enum import IntEnum, StrEnum
from typing import Final


class State(StrEnum):
    """The power state machine of a CiA 402 drive (statusword 0x6041)."""

    NOT_READY_TO_SWITCH_ON = "NOT READY TO SWITCH ON"
    SWITCH_ON_DISABLED = "SWITCH ON DISABLED"
    READY_TO_SWITCH_ON = "READY TO SWITCH ON"
    SWITCHED_ON = "SWITCHED ON"
    OPERATION_ENABLED = "OPERATION ENABLED"
    QUICK_STOP_ACTIVE = "QUICK STOP ACTIVE"
    FAULT_REACTION_ACTIVE = "FAULT REACTION ACTIVE"
    FAULT = "FAULT"


# (mask, value) of the statusword's state bits 0-3, 5, 6, per CiA 402 table 30.
STATUSWORD_PATTERNS: Final[dict[State, tuple[int, int]]] = {
    State.NOT_READY_TO_SWITCH_ON: (0x4F, 0x00),
    State.SWITCH_ON_DISABLED: (0x4F, 0x40),
    State.READY_TO_SWITCH_ON: (0x6F, 0x21),
    State.SWITCHED_ON: (0x6F, 0x23),
    State.OPERATION_ENABLED: (0x6F, 0x27),
    State.QUICK_STOP_ACTIVE: (0x6F, 0x07),
    State.FAULT_REACTION_ACTIVE: (0x4F, 0x0F),
    State.FAULT: (0x4F, 0x08),
}

SW_VOLTAGE_ENABLED = 0x0010
SW_WARNING = 0x0080
SW_REMOTE = 0x0200
SW_TARGET_REACHED = 0x0400
SW_INTERNAL_LIMIT = 0x0800
SW_MODE_BIT12 = 0x1000  # CSx: drive follows the command value; PV: speed is zero
SW_MODE_BIT13 = 0x2000  # CSP: following error
_POWERED = {
    State.READY_TO_SWITCH_ON,
    State.SWITCHED_ON,
    State.OPERATION_ENABLED,
    State.QUICK_STOP_ACTIVE,
    State.FAULT_REACTION_ACTIVE,
}


def decode_statusword(statusword: int) -> State | None:
    """The state a statusword reports, or None for a bit pattern no state has."""
    for state, (mask, value) in STATUSWORD_PATTERNS.items():
        if statusword & mask == value:
            return state
    return None


def statusword_for(state: State, extra_bits: int = 0) -> int:
    """The statusword a drive in `state` reports: state bits, voltage enabled, remote, plus extras."""
    value = STATUSWORD_PATTERNS[state][1]
    if state in (State.READY_TO_SWITCH_ON, State.SWITCHED_ON, State.OPERATION_ENABLED):
        value |= 0x20  # quick stop bit is active-low: 1 = not quick-stopping
    if state in _POWERED:
        value |= SW_VOLTAGE_ENABLED
    return value | SW_REMOTE | extra_bits


class Command(StrEnum):
    """Device control commands of the controlword 0x6040."""

    SHUTDOWN = "shutdown"
    SWITCH_ON = "switch on"  # also "disable operation" from OPERATION ENABLED: the same bits
    ENABLE_OPERATION = "enable operation"
    DISABLE_VOLTAGE = "disable voltage"
    QUICK_STOP = "quick stop"
    FAULT_RESET = "fault reset"


CONTROLWORD: Final[dict[Command, int]] = {
    Command.SHUTDOWN: 0x0006,
    Command.SWITCH_ON: 0x0007,
    Command.ENABLE_OPERATION: 0x000F,
    Command.DISABLE_VOLTAGE: 0x0000,
    Command.QUICK_STOP: 0x0002,
    Command.FAULT_RESET: 0x0080,
}

# Decoding order matters: the first (mask, value) that matches bits 0-3 names the command.
_COMMAND_PATTERNS: Final[tuple[tuple[Command, int, int], ...]] = (
    (Command.DISABLE_VOLTAGE, 0x02, 0x00),
    (Command.QUICK_STOP, 0x06, 0x02),
    (Command.SHUTDOWN, 0x07, 0x06),
    (Command.SWITCH_ON, 0x0F, 0x07),
    (Command.ENABLE_OPERATION, 0x0F, 0x0F),
)
CW_FAULT_RESET_BIT = 0x0080
CW_HALT_BIT = 0x0100


def decode_controlword(controlword: int) -> Command:
    """The command a controlword carries; bit 7 set means fault reset (acted on at its rising edge)."""
    if controlword & CW_FAULT_RESET_BIT:
        return Command.FAULT_RESET
    for command, mask, value in _COMMAND_PATTERNS:
        if controlword & mask == value:
            return command
    raise AssertionError(f"controlword 0x{controlword:04X} matched no command")  # the patterns cover all


# The transition table of CiA 402 figure 23 (numbers in comments), commands only; the automatic ones
# (0, 1, 13, 14 and the end of a quick stop) are the drive's own business.
TRANSITIONS: Final[dict[tuple[State, Command], State]] = {
    (State.SWITCH_ON_DISABLED, Command.SHUTDOWN): State.READY_TO_SWITCH_ON,  # 2
    (State.READY_TO_SWITCH_ON, Command.SWITCH_ON): State.SWITCHED_ON,  # 3
    (State.SWITCHED_ON, Command.ENABLE_OPERATION): State.OPERATION_ENABLED,  # 4
    (State.OPERATION_ENABLED, Command.SWITCH_ON): State.SWITCHED_ON,  # 5 (disable operation)
    (State.SWITCHED_ON, Command.SHUTDOWN): State.READY_TO_SWITCH_ON,  # 6
    (State.READY_TO_SWITCH_ON, Command.DISABLE_VOLTAGE): State.SWITCH_ON_DISABLED,  # 7
    (State.READY_TO_SWITCH_ON, Command.QUICK_STOP): State.SWITCH_ON_DISABLED,  # 7
    (State.OPERATION_ENABLED, Command.SHUTDOWN): State.READY_TO_SWITCH_ON,  # 8
    (State.OPERATION_ENABLED, Command.DISABLE_VOLTAGE): State.SWITCH_ON_DISABLED,  # 9
    (State.SWITCHED_ON, Command.DISABLE_VOLTAGE): State.SWITCH_ON_DISABLED,  # 10
    (State.SWITCHED_ON, Command.QUICK_STOP): State.SWITCH_ON_DISABLED,  # 10
    (State.OPERATION_ENABLED, Command.QUICK_STOP): State.QUICK_STOP_ACTIVE,  # 11
    (State.QUICK_STOP_ACTIVE, Command.DISABLE_VOLTAGE): State.SWITCH_ON_DISABLED,  # 12
    (State.FAULT, Command.FAULT_RESET): State.SWITCH_ON_DISABLED,  # 15
}
"""Transition 16 (QUICK STOP ACTIVE → OPERATION ENABLED) is left out: it exists only for quick stop
option codes 5-8, and the way back through SWITCH ON DISABLED works on every drive."""


def next_state(state: State, command: Command) -> State:
    """Where `command` takes a drive in `state`; a command with no transition leaves it where it is."""
    return TRANSITIONS.get((state, command), state)


def command_towards(state: State, target: State) -> Command | None:
    """The first command on the shortest path of the table from `state` to `target`.

    None when already there or when no command leads there (NOT READY TO SWITCH ON and FAULT REACTION
    ACTIVE end by themselves: wait).
    """
    if state == target:
        return None
    first: dict[State, Command] = {}
    queue = deque([state])
    seen = {state}
    while queue:
        here = queue.popleft()
        for (source, command), result in TRANSITIONS.items():
            if source != here or result in seen:
                continue
            first[result] = first.get(here, command)
            if result == target:
                return first[result]
            seen.add(result)
            queue.append(result)
    return None


class OperationMode(IntEnum):
    """Modes of operation (0x6060/0x6061) of CiA 402; those with a target in TARGET_OBJECT are driven."""

    NO_MODE = 0
    PROFILE_POSITION = 1
    PROFILE_VELOCITY = 3
    PROFILE_TORQUE = 4
    HOMING = 6
    INTERPOLATED_POSITION = 7
    CYCLIC_SYNC_POSITION = 8
    CYCLIC_SYNC_VELOCITY = 9
    CYCLIC_SYNC_TORQUE = 10


SUPPORTED_MODE_BIT: Final[dict[OperationMode, int]] = {
    OperationMode.PROFILE_POSITION: 1 << 0,
    OperationMode.PROFILE_VELOCITY: 1 << 2,
    OperationMode.PROFILE_TORQUE: 1 << 3,
    OperationMode.HOMING: 1 << 5,
    OperationMode.INTERPOLATED_POSITION: 1 << 6,
    OperationMode.CYCLIC_SYNC_POSITION: 1 << 7,
    OperationMode.CYCLIC_SYNC_VELOCITY: 1 << 8,
    OperationMode.CYCLIC_SYNC_TORQUE: 1 << 9,
}
"""Bits of 0x6502 (supported drive modes); bit 1 (velocity mode, vl) is a frequency-inverter mode."""

TARGET_OBJECT: Final[dict[OperationMode, tuple[int, int]]] = {
    OperationMode.PROFILE_VELOCITY: (0x60FF, 0),
    OperationMode.PROFILE_TORQUE: (0x6071, 0),
    OperationMode.INTERPOLATED_POSITION: (0x60C1, 1),
    OperationMode.CYCLIC_SYNC_POSITION: (0x607A, 0),
    OperationMode.CYCLIC_SYNC_VELOCITY: (0x60FF, 0),
    OperationMode.CYCLIC_SYNC_TORQUE: (0x6071, 0),
}
"""The object (index, sub-index) each mode the driver runs cycle by cycle takes its set-point from:
target torque, velocity, position, or the interpolation data record's first set-point."""

CW_ENABLE_IP_BIT = 0x0010
"""Controlword bit 4 in interpolated position mode: interpolation runs while it is set."""


# Emergency error codes (CiA 301 table 21, CiA 402 annex) and the error register bits they set (0x1001).
EMCY_OVERCURRENT: Final = 0x2310
EMCY_OVERVOLTAGE: Final = 0x3210
EMCY_SPEED: Final = 0x8400
EMCY_FOLLOWING_ERROR: Final = 0x8611
EMCY_POSITION_LIMIT: Final = 0x8612
EMCY_HEARTBEAT: Final = 0x8130
EMCY_COMMUNICATION: Final = 0x8100
ERROR_REGISTER_BITS: Final[tuple[tuple[int, int, int], ...]] = (
    (0xF000, 0x2000, 0x02),  # current
    (0xF000, 0x3000, 0x04),  # voltage
    (0xF000, 0x4000, 0x08),  # temperature
    (0xFF00, 0x8100, 0x10),  # communication (heartbeat, life guard, overrun)
    (0xF000, 0x8000, 0x20),  # device profile specific: speed, following error, limits
)


def error_register_for(code: int) -> int:
    """The error register (0x1001) an emergency error code sets: generic error plus its class's bit."""
    for mask, value, bit in ERROR_REGISTER_BITS:
        if code & mask == value:
            return 0x01 | bit
    return 0x01
