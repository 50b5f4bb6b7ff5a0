"""The safety envelope, one compiled check that every backend calls every cycle.

It is compiled so that the simulated backend's compiled cycle loop and the hardware backends' Python
cycle loops call the very same code.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from rig.config import Limits

NO_ABORT, ABORT_CURRENT, ABORT_VOLTAGE, ABORT_VELOCITY, ABORT_TRAVEL, ABORT_FOLLOWING = range(6)
ABORT_REASONS = {
    ABORT_CURRENT: "current",
    ABORT_VOLTAGE: "voltage",
    ABORT_VELOCITY: "velocity",
    ABORT_TRAVEL: "travel",
    ABORT_FOLLOWING: "following",
}

# Layout of the limits vector.
LIM_CURRENT, LIM_VOLTAGE, LIM_VELOCITY, LIM_TRAVEL_MIN, LIM_TRAVEL_MAX, LIM_FOLLOWING, LIM_RATIO = range(7)


def limits_vector(limits: Limits, gear_ratio: float) -> np.ndarray:
    """The envelope as the float vector `envelope_breach` reads; output angles via the gear ratio."""
    return np.array(
        [
            limits.current_a,
            limits.voltage_v,
            limits.velocity_rad_s,
            limits.travel_min_out_rad,
            limits.travel_max_out_rad,
            limits.following_error_out_rad,
            gear_ratio,
        ]
    )


@njit(cache=True)
def envelope_breach(
    lim: np.ndarray, u: float, i_a: float, omega_m: float, theta_m: float, position_error_m: float
) -> int:
    """The first limit breached by this cycle's measurements (ABORT_*), or NO_ABORT.

    `position_error_m` is the motor-side position error in position mode (0 otherwise).
    """
    if abs(i_a) > lim[LIM_CURRENT]:
        return ABORT_CURRENT
    if abs(u) > lim[LIM_VOLTAGE]:
        return ABORT_VOLTAGE
    if abs(omega_m) > lim[LIM_VELOCITY]:
        return ABORT_VELOCITY
    out = theta_m * lim[LIM_RATIO]
    if out < lim[LIM_TRAVEL_MIN] or out > lim[LIM_TRAVEL_MAX]:
        return ABORT_TRAVEL
    if abs(position_error_m) * lim[LIM_RATIO] > lim[LIM_FOLLOWING]:
        return ABORT_FOLLOWING
    return NO_ABORT
