"""The base of the compiled loops' vector layouts: an `IntEnum` numbered by declaration order, from 0.

numba reads a member of a global `IntEnum` as a compile-time constant, so `p[P.S3]` costs what a
literal index costs; a tuple, though, must be indexed with `.value` (numba 0.68 cannot lower a tuple's
static index of an enum member). The layouts: `model.registry` (parameters, flags, state, outputs, laws,
modes) and `model.inputs` (profile vectors)."""

from __future__ import annotations

import enum
from typing import Any


class Slots(enum.IntEnum):
    """A vector layout: members numbered 0, 1, 2... in the order they are declared (`enum.auto()`)."""

    @staticmethod
    def _generate_next_value_(name: str, start: int, count: int, last_values: list[Any]) -> int:
        return count
