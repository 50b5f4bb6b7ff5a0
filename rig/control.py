"""The drive's loops: velocity PI + torque feed-forward → current, position P + rate feed-forward → velocity.

Compiled, so the simulated drive's cycle loop and a host-side loop over a real drive in torque mode
run the same code. Gains and state are small float vectors laid out by the constants below.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from rig.config import Control

# Gains vector.
G_VEL_KP, G_VEL_KI, G_POS_KP, G_CURRENT_LIMIT, G_MAX_VELOCITY = range(5)
# State vector: the velocity integrator [A], the previous position set-point [rad], the set-point's
# rate as filtered for the feed-forward [rad/s].
S_INTEGRAL, S_PREV_POSITION_REF, S_RATE = range(3)
N_CONTROL_STATE = 3


def gains_vector(control: Control) -> np.ndarray:
    return np.array(
        [
            control.velocity_kp,
            control.velocity_ki,
            control.position_kp,
            control.current_limit_a,
            control.max_velocity_rad_s,
        ]
    )


@njit(cache=True)
def velocity_pi(
    gains: np.ndarray, state: np.ndarray, omega_ref: float, omega: float, dt: float, offset_a: float = 0.0
) -> float:
    """Current command [A] for a speed error plus a feed-forward `offset_a`, saturated at the limit.

    Anti-windup by conditional integration: the integrator only moves when the output is not
    saturated, or when the error would bring it back out of saturation. The offset (a model's torque
    feed-forward, as CiA 402's torque offset 0x60B2) counts towards saturation like the PI's own share.
    """
    error = omega_ref - omega
    limit = gains[G_CURRENT_LIMIT]
    unsaturated = gains[G_VEL_KP] * error + state[S_INTEGRAL] + offset_a
    trial = state[S_INTEGRAL] + gains[G_VEL_KI] * error * dt
    if abs(unsaturated) < limit or unsaturated * error < 0.0:
        state[S_INTEGRAL] = min(max(trial, -limit), limit)
    command = gains[G_VEL_KP] * error + state[S_INTEGRAL] + offset_a
    return min(max(command, -limit), limit)


@njit(cache=True)
def position_p(
    gains: np.ndarray, state: np.ndarray, theta_ref: float, theta: float, dt: float, rate_alpha: float = 1.0
) -> float:
    """Speed command [rad/s]: P on the position error plus the set-point's own rate as feed-forward.

    `rate_alpha` < 1 passes that rate through the same first-order filter as the measured speed, so a
    motor that follows exactly meets a speed error of zero (the rate is then matched, not ahead).
    """
    state[S_RATE] += rate_alpha * ((theta_ref - state[S_PREV_POSITION_REF]) / dt - state[S_RATE])
    state[S_PREV_POSITION_REF] = theta_ref
    command = gains[G_POS_KP] * (theta_ref - theta) + state[S_RATE]
    limit = gains[G_MAX_VELOCITY]
    return min(max(command, -limit), limit)
