"""A CAN bus of its own for each test: python-can's in-process `virtual` interface, or a real one.

`HDRIG_TEST_CAN=socketcan:vcan0` moves the very same tests onto a Linux vcan bus
(`ip link add dev vcan0 type vcan && ip link set up vcan0`).
"""

from __future__ import annotations

import os
import uuid
from typing import Any

import numpy as np

from drivers.can_bus import BusSettings, CanBusError

TEST_BUS_ENV = "HDRIG_TEST_CAN"
TWIN_SYNC_TIMEOUT_S = 2.0
"""`sync_timeout_s` for a drive twin on this machine, as configs/rigs/virtual-can.yaml's: a busy machine
holds its answer back (measured > 250 ms with two CPU hogs beside the tests on 2 cores), which is no lost
drive. The driver's default (10 cycles, ≥ 20 ms) is for a drive on a bus of its own."""


def bus_settings_for_test(name: str) -> BusSettings:
    """A bus for one test: `virtual` on a channel no other test uses, or `$HDRIG_TEST_CAN`.

    `HDRIG_TEST_CAN` is `interface:channel`, e.g. `socketcan:vcan0`.
    """
    spec = os.environ.get(TEST_BUS_ENV, "").strip()
    if not spec:
        return BusSettings(interface="virtual", channel=f"hdrig-{name}-{uuid.uuid4().hex[:8]}")
    interface, sep, channel = spec.partition(":")
    if not sep or not interface or not channel:
        raise CanBusError(f"{TEST_BUS_ENV}={spec!r}: expected interface:channel, e.g. socketcan:vcan0")
    return BusSettings(interface=interface, channel=channel)


def held_speed_errors(run: Any, speeds: set[float], abs_tol_rad_s: float) -> list[str]:
    """The constant-speed segments of a recorded speed sweep whose second half's mean motor speed is not
    within `abs_tol_rad_s` of its set-point (or whose set-point is not one of `speeds`), one line each.
    Those are the segments labelled `v+<speed>`/`v-<speed>` (speed_sweep's passes); the ramps and
    moves between them are not held speeds."""
    errors = []
    held_segments = [s for s in run.meta["segments"] if s["label"].startswith(("v+", "v-"))]
    if not held_segments:
        return ["no held-speed segment (v+<speed>, v-<speed>) in the run"]
    for segment in held_segments:
        held = slice(segment["start"] + segment["cycles"] // 2, segment["start"] + segment["cycles"])
        speed = float(np.mean(run["setpoint"][held]))
        measured = float(np.mean(run["omega_m"][held]))
        if abs(speed) not in speeds or abs(measured - speed) > abs_tol_rad_s:
            errors.append(f"{segment['label']}: set {speed:g}, held {measured:.3f} rad/s")
    return errors
