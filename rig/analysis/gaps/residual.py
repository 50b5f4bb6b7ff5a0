"""The torque-equivalent residual: what the model misses, sample by sample, from the measured motion.

For every sample the kernel starts from the measured state (motor angle, smoothed speed, output angle
and speed when measured), applies the measured input over one sample interval, and predicts the
acceleration. Inertia × (measured − predicted acceleration) is the torque the model would need to
follow the data: an inverse-dynamics residual that means the same on open- and closed-loop data,
because it never integrates the model over more than one sample. The simulator itself makes the
prediction, so every effect the model carries is in it, with one copy of the physics.

Channels (each smoothed by `Signals.smooth`, the same filter as the regressors of `effects`):
- `motor` [N·m at the motor]: J·(α_m measured − predicted), J = J_m + r²·J_l for a rigid model.
- `load` [N·m at the output], compliant model with the output measured: J_l·(α_l measured − predicted).
  With the output transducer (`signals.output_boundary`: tau_out in place of τ_ext) it is
  tau_out + J_l·α_l − (T_s − F_l), the model's J_l the gear's own: the output's balance, without the
  motor's friction or the load drive.
- `load_position` [rad at the output], rigid model with the output measured: θ_l − (r·θ_m + θ_err).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from model import kernel as k
from model.params import HarmonicDriveModel
from model.plant import MODES, Plant, kernel_vectors
from model.registry import N_OUT, N_STATE, OUT, X
from rig.analysis.gaps.signals import Signals

MEASURED = (X.RISE_GEAR, X.RISE_MOTOR, X.TRAVEL)
"""Kernel states a run can measure beside the motion: the gear's and the winding's temperatures above
the network's ambient (recorded temp_gear, temp_motor) and the motor travel since the start."""
_MEASURED_SLOTS = np.array(
    [int(slot) for slot in MEASURED], dtype=np.int64
)  # as the compiled pass reads them


@njit(cache=True)
def _one_step_pass(
    p: np.ndarray,
    flags: np.ndarray,
    mode: int,
    t: np.ndarray,
    drive: np.ndarray,
    tau_ext: np.ndarray,
    theta_m: np.ndarray,
    omega_m: np.ndarray,
    theta_l: np.ndarray,
    omega_l: np.ndarray,
    load_known: bool,
    start: np.ndarray,
    measured: np.ndarray,
    dt_max: float,
    rows: np.ndarray,
    end: np.ndarray,
    internal: np.ndarray,
) -> None:
    """Per sample: reset to the measured state, integrate one interval; rows, end speeds, internal states.

    `start` is the state the others start from (the thermal rises: the network runs along the data
    from there); `measured[:, j]` sets slot j of MEASURED at each sample where it is finite."""
    n = t.shape[0]
    x = start.copy()
    buf = np.empty((1, N_OUT))
    load = np.empty(1)
    for i in range(n):
        h = t[i + 1] - t[i] if i < n - 1 else t[i] - t[i - 1]
        steps = max(1, math.ceil(h / dt_max - 1e-9))
        x[X.THETA_M] = theta_m[i]
        x[X.OMEGA_M] = omega_m[i]
        if load_known:
            x[X.THETA_L] = theta_l[i]
            x[X.OMEGA_L] = omega_l[i]
        x[X.TIME] = t[i]
        for j in range(_MEASURED_SLOTS.shape[0]):
            if not math.isnan(measured[i, j]):
                x[_MEASURED_SLOTS[j]] = measured[i, j]
        internal[i, 0] = x[X.Z_M]
        internal[i, 1] = x[X.Z_L]
        internal[i, 2] = x[X.Z_H]
        load[0] = tau_ext[i]
        k.integrate(p, flags, x, mode, np.full(steps, drive[i]), load, h / steps, steps, buf)
        rows[i] = buf[0]
        end[i, 0] = x[X.OMEGA_M]
        end[i, 1] = x[X.OMEGA_L]


def judged_model(model: HarmonicDriveModel, sig: Signals) -> HarmonicDriveModel:
    """The model the residual is taken with: a compliant model without a measured output is judged as
    rigid, since its spring state cannot be set from the data (the rigid limit holds below resonance)."""
    if model.rigid or sig.has_load:
        return model
    return model.with_updates(
        transmission={"K_s": None, "D_s": 0.0}, nonlinear_stiffness=None, hysteresis=None
    )


@dataclass
class Residual:
    """The one-step residual of one run, with the model's view of the measured states."""

    motor: np.ndarray  # N·m at the motor, smoothed
    load: np.ndarray | None  # N·m at the output, smoothed (compliant model, output measured)
    load_position: np.ndarray | None  # rad at the output, raw (rigid model, output measured)
    rows: np.ndarray  # kernel rows (OUT_*) at each measured state
    predicted: np.ndarray  # the model's motor acceleration from each measured state [rad/s²], raw
    internal: np.ndarray  # (n, 3) bristle/hysteresis states tracked along the data
    torque_s: np.ndarray  # transmitted torque estimate T_s [N·m at the output]
    deflection: np.ndarray | None  # r·θ_m + θ_err − θ_l [rad], output measured
    inertia: float  # the motor channel's inertia [kg·m²]
    rigid: bool


def _measured_states(model: HarmonicDriveModel, sig: Signals) -> tuple[np.ndarray, np.ndarray]:
    """The kernel state the pass starts from and the MEASURED slots per sample (NaN: not measured).

    With a `thermal` section the temperatures start where the model says (its T_motor0, T_gear0) and are
    replaced by the recorded ones when the run has them; the travel is the measured one."""
    start = np.zeros(N_STATE)
    measured = np.full((sig.n, len(MEASURED)), np.nan)
    thermal = model.thermal
    if thermal is not None:
        start[X.RISE_MOTOR] = thermal.motor_start_c - thermal.T_amb
        start[X.RISE_GEAR] = thermal.gear_start_c - thermal.T_amb
        if sig.temp_gear is not None:
            measured[:, 0] = sig.temp_gear - thermal.T_amb
        if sig.temp_motor is not None:
            measured[:, 1] = sig.temp_motor - thermal.T_amb
    measured[:, 2] = sig.travel
    return start, measured


def one_step_residual(model: HarmonicDriveModel, sig: Signals, dt_s: float) -> Residual:
    """The residual channels of `model` on one prepared run."""
    judged = judged_model(model, sig)
    p, flags = kernel_vectors(judged)
    n = sig.n
    rows = np.empty((n, len(OUT)))
    end = np.empty((n, 2))
    internal = np.empty((n, 3))
    load_known = sig.has_load and not judged.rigid
    zeros = np.zeros(n)
    start, measured = _measured_states(judged, sig)
    _one_step_pass(
        p,
        flags,
        MODES[sig.mode],
        sig.t,
        sig.drive,
        sig.tau_ext,
        sig.theta_m,
        sig.omega_m,
        sig.theta_l_smooth if load_known and sig.theta_l_smooth is not None else zeros,
        sig.omega_l if load_known and sig.omega_l is not None else zeros,
        load_known,
        start,
        measured,
        dt_s,
        rows,
        end,
        internal,
    )
    mech = judged.mechanics
    inertia = mech.J_m + mech.r**2 * mech.J_l if judged.rigid else mech.J_m
    h = np.append(np.diff(sig.t), sig.t[-1] - sig.t[-2])

    def centred(predicted_end: np.ndarray, start: np.ndarray) -> np.ndarray:
        # Predicted mean acceleration over [t_i, t_i+1], moved to t_i like the central second difference.
        a = (predicted_end - start) / h
        return np.concatenate([a[:1], 0.5 * (a[1:] + a[:-1])])

    alpha_m = sig.acceleration(sig.theta_m)
    predicted = centred(end[:, 0], sig.omega_m)
    motor = inertia * sig.smooth(alpha_m - predicted)
    load = load_position = deflection = None
    if load_known and sig.theta_l is not None and sig.omega_l is not None:
        load = mech.J_l * sig.smooth(sig.acceleration(sig.theta_l) - centred(end[:, 1], sig.omega_l))
        torque_s = rows[:, OUT.T_S]
    else:
        # Rigid: what the output needs, from its measured acceleration and the model's load friction.
        torque_s = sig.tau_ext + rows[:, OUT.F_L] + mech.J_l * mech.r * sig.smooth(alpha_m)
        if sig.theta_l is not None:
            load_position = sig.theta_l - rows[:, OUT.THETA_L]
    if sig.theta_l is not None:
        plant = Plant(judged)
        error = np.array([plant.kinematic_error(v) for v in sig.theta_m]) if judged.kinematic_error else 0.0
        deflection = mech.r * sig.theta_m + error - sig.theta_l
    return Residual(
        motor, load, load_position, rows, predicted, internal, torque_s, deflection, inertia, judged.rigid
    )
