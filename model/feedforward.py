"""A feed-forward track: what a drive adds to its position loop, cycle by cycle, to follow a trajectory.

A track is planned from a model and a set-point trajectory by `model.compensator`; this module holds only
the plain arrays and the one compiled function every drive loop calls with them, so the simulated drive,
the CANopen twin and a real drive (as its torque offset 0x60B2) apply the same numbers. It imports no
simulator: a backend that has no model of its own can still carry a track.

Per cycle (motor side, SI units):

- `theta_cmd_rad`: the position the loop follows instead of the set-point. It differs from the
  set-point by the transmission's twist and kinematic error, so that the *output* follows r·set-point.
- `omega_cmd_rad_s`: the rate of `theta_cmd_rad`, whose sign says which way friction is expected to act.
- `torque_nm`: inertia and the torque the transmission must pass to move the load (r·T_s), N·m.
- `friction_nm`: the motor friction predicted at (theta_cmd, omega_cmd), signed, N·m.
- `friction_level_nm`: the motor friction magnitude at standstill there, for the measured-velocity blend.

`measured_band_rad_s` > 0 turns on the measured-velocity option: while the planned speed is inside the
band, the friction term is `friction_level · clip(ω_measured / band, −1, 1)` instead of the planned one,
so a motor that is stuck or creeping against the plan gets its friction cancelled in the direction it
actually moves. Feeding back the measured speed this way is negative damping of slope level/band; the
band must keep it below the velocity loop's own damping (K_m·K_p), or the loop chatters
(`min_measured_band_rad_s`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

FF_THETA, FF_OMEGA, FF_TORQUE, FF_FRICTION, FF_LEVEL = range(5)
N_FF_COLUMNS = 5


@dataclass(frozen=True)
class FeedForwardTrack:
    """One row per control cycle (columns FF_*), and the measured-velocity band (0: off) [rad/s]."""

    rows: np.ndarray
    measured_band_rad_s: float = 0.0
    label: str = "compensation"
    thermal: tuple[float, float] | None = None
    """(beta_T [1/K], T_ref [°C]) when the friction columns are planned at T_ref and follow the gear's
    measured temperature: the rig scales them by exp(−beta_T·(T_g − T_ref)) as it plays (`at_temperature`)."""

    def __post_init__(self) -> None:
        if self.rows.ndim != 2 or self.rows.shape[1] != N_FF_COLUMNS or not np.all(np.isfinite(self.rows)):
            raise ValueError(f"a feed-forward track is a finite (cycles, {N_FF_COLUMNS}) array")

    @property
    def cycles(self) -> int:
        return int(self.rows.shape[0])

    @property
    def theta_cmd_rad(self) -> np.ndarray:
        return self.rows[:, FF_THETA]

    @property
    def torque_planned_nm(self) -> np.ndarray:
        """Total torque planned per cycle (inertia, transmission, friction at the planned speed) [N·m]."""
        return self.rows[:, FF_TORQUE] + self.rows[:, FF_FRICTION]

    def part(self, start: int, stop: int) -> FeedForwardTrack:
        """Cycles start..stop of the track (a segment of a longer plan, or a chunk of a segment)."""
        return FeedForwardTrack(self.rows[start:stop], self.measured_band_rad_s, self.label, self.thermal)

    def at_temperature(self, temp_gear_c: float) -> FeedForwardTrack:
        """The track with its friction columns brought from T_ref to the gear's temperature (the thermal
        law of docs/MODEL.md); itself when it carries no law."""
        if self.thermal is None:
            return self
        beta_per_k, t_ref_c = self.thermal
        rows = self.rows.copy()
        rows[:, [FF_FRICTION, FF_LEVEL]] *= np.exp(-beta_per_k * (temp_gear_c - t_ref_c))
        return FeedForwardTrack(rows, self.measured_band_rad_s, self.label, self.thermal)


def min_measured_band_rad_s(
    friction_level_nm: float, torque_constant_nm_per_a: float, velocity_kp: float
) -> float:
    """The narrowest measured-velocity band that cannot undamp the velocity loop [rad/s].

    The blend adds a torque of slope level/band against the speed error; the velocity PI's proportional
    term damps with slope K_m·K_p. Below level/(K_m·K_p) the sum is negative damping: the motor chatters.
    """
    return friction_level_nm / (torque_constant_nm_per_a * velocity_kp)


@njit(cache=True)
def loop_torque_nm(ff: np.ndarray, c: int, band_rad_s: float, omega_meas_rad_s: float) -> float:
    """The feed-forward torque of cycle `c` [N·m]: planned torque plus friction, planned or blended."""
    friction = ff[c, FF_FRICTION]
    if band_rad_s > 0.0 and abs(ff[c, FF_OMEGA]) < band_rad_s:
        share = min(max(omega_meas_rad_s / band_rad_s, -1.0), 1.0)
        friction = ff[c, FF_LEVEL] * share
    return ff[c, FF_TORQUE] + friction
