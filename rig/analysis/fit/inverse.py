"""Plain inverse-model least squares of a single axis: torque = M·a + F_v·v + F_c·sgn v + offset.

This is how published benchmarks of positioning axes identify mass and friction (IDIM-LS): the
position is low-pass filtered forwards and backwards (no phase lag), differentiated twice, the torque
goes through the same filter (so both sides of the equation see the same gain), samples too slow for
the sign of v to be trusted are dropped, and the four coefficients come from one linear least squares
with the usual covariance. `hdrig fit` uses it as a starting point for a single axis it knows nothing
about, and reports it beside the trajectory fit as the textbook comparison.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.signal import butter, filtfilt

from model.errors import UserInputError

CUTOFF_HZ = 20.0
"""Default low-pass corner: above a positioning axis' mechanical bandwidth, below where a 14-bit
encoder's quantization, differentiated twice at 1 kHz, swamps the acceleration."""
MIN_SPEED_SHARE = 0.05
"""Samples slower than this share of the run's top speed are dropped: their sign is not known."""


@dataclass(frozen=True)
class InverseFit:
    """Coefficients of torque = M·a + F_v·v + F_c·sgn v + offset, each with its 1σ standard error."""

    mass: float  # [kg·m²] (or kg for a linear axis: the units of the data)
    viscous: float  # [N·m·s/rad]
    coulomb: float  # [N·m]
    offset: float  # [N·m]: gravity, a sensor zero
    std_errors: dict[str, float]
    samples: int
    cutoff_hz: float

    def as_json(self) -> dict[str, object]:
        return {
            "mass": self.mass,
            "viscous": self.viscous,
            "coulomb": self.coulomb,
            "offset": self.offset,
            "std_errors": {k: (v if math.isfinite(v) else None) for k, v in self.std_errors.items()},
            "samples": self.samples,
            "cutoff_hz": self.cutoff_hz,
        }


def filtered_derivatives(
    t: np.ndarray, position: np.ndarray, cutoff_hz: float = CUTOFF_HZ
) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """Speed and acceleration of the zero-phase filtered position, and the filter (b, a) used."""
    dt = float(np.median(np.diff(t)))
    nyquist_hz = 0.5 / dt
    if not 0 < cutoff_hz < nyquist_hz:
        raise UserInputError(f"inverse model: cutoff {cutoff_hz} Hz must lie in (0, {nyquist_hz:g}) Hz")
    b, a = butter(4, cutoff_hz / nyquist_hz)
    smooth = filtfilt(b, a, position)
    speed = np.gradient(smooth, t)
    return speed, np.gradient(speed, t), (b, a)


def inverse_model_fit(
    t: np.ndarray, position: np.ndarray, torque: np.ndarray, cutoff_hz: float = CUTOFF_HZ
) -> InverseFit:
    """Mass, viscous and Coulomb friction and a torque offset of one axis from its torque and position."""
    if len(t) < 30:
        raise UserInputError(f"inverse model: needs at least 30 samples, has {len(t)}")
    speed, accel, (b, a) = filtered_derivatives(t, position, cutoff_hz)
    torque_f = filtfilt(b, a, torque)
    edge = max(1, len(t) // 50)  # filtfilt's start and end transients
    keep = np.zeros(len(t), bool)
    keep[edge:-edge] = np.abs(speed[edge:-edge]) > MIN_SPEED_SHARE * np.max(np.abs(speed))
    if keep.sum() < 10:
        raise UserInputError("inverse model: the axis hardly moves (fewer than 10 samples at speed)")
    sign = np.sign(speed[keep])
    one_way = bool(np.all(sign == sign[0]))
    # Moving one way only, sgn v is a constant: Coulomb and offset are one column, the offset is 0.
    columns = [accel[keep], speed[keep], sign] + ([] if one_way else [np.ones(keep.sum())])
    design = np.column_stack(columns)
    beta, *_ = np.linalg.lstsq(design, torque_f[keep], rcond=None)
    residual = torque_f[keep] - design @ beta
    dof = max(len(residual) - design.shape[1], 1)
    cov = np.linalg.pinv(design.T @ design) * float(residual @ residual) / dof
    se = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    if one_way:
        beta, se = np.append(beta, 0.0), np.append(se, math.inf)
    names = ("mass", "viscous", "coulomb", "offset")
    return InverseFit(
        float(beta[0]),
        float(beta[1]),
        float(beta[2]),
        float(beta[3]),
        {n: float(s) if math.isfinite(s) else math.inf for n, s in zip(names, se, strict=True)},
        int(keep.sum()),
        cutoff_hz,
    )
