"""The plant: a validated model turned into the compiled kernel's vectors, with its state.

`Plant` is the one object that the simulator, the simulated rig backends, the fitter and the gap
workflow step forward. It knows nothing of files, buses or time pacing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike

from model import kernel as k
from model.params import N_FOURIER, HarmonicDriveModel
from model.registry import EFFECT_FLAGS, FL, LAW_CODES, OUT, PARAMETERS, Law, Mode, P, X

InputMode = Literal["voltage", "current", "torque"]
MODES: dict[str, int] = {
    "voltage": int(Mode.VOLTAGE),
    "current": int(Mode.CURRENT),
    "torque": int(Mode.TORQUE),
}
"""The kernel's mode codes, as plain ints: numba types an enum argument slowly at each call."""
INPUT_COLUMN: dict[str, str] = {"voltage": "u", "current": "i_cmd", "torque": "tau_m"}
MODE_OF_COLUMN: dict[str, InputMode] = {"u": "voltage", "i_cmd": "current", "tau_m": "torque"}

HIDDEN_STATES = (X.Z_M, X.Z_L, X.Z_H)
"""Kernel states no sensor measures: motor and load bristle deflections, the hysteresis torque."""


def _in_kernel(model: HarmonicDriveModel, section: str) -> bool:
    """Whether a section's parameters reach the kernel: present, and (the kinematic error) not null."""
    if getattr(model, section) is None:
        return False
    return section != "kinematic_error" or model.kinematic_error is None or model.kinematic_error.A > 0.0


def kernel_vectors(model: HarmonicDriveModel) -> tuple[np.ndarray, np.ndarray]:
    """The float parameter vector and int flag vector that `model.kernel` reads, filled from the registry.

    A parameter of an absent section reads 0 (its law or effect is off, the kernel never reads it); an
    unset field of a present section reads its `kernel_default`."""
    p = np.zeros(len(P))
    flags = np.zeros(len(FL), dtype=np.int64)
    for param in PARAMETERS.values():
        if _in_kernel(model, param.section):
            value = param.value(model)
            p[param.slot] = param.kernel_default if value is None else value
    if (ns := model.nonlinear_stiffness) is not None:  # DERIVED: the deflections at the breakpoints
        p[P.NS_D1] = ns.T1 / ns.K1
        p[P.NS_D2] = p[P.NS_D1] + (ns.T2 - ns.T1) / ns.K2

    mf, lf = model.motor_friction, model.load_friction
    flags[FL.RIGID] = int(model.transmission.K_s is None)
    flags[FL.MOTOR_LAW] = LAW_CODES[mf.motor_law]
    flags[FL.LOAD_LAW] = Law.NONE if lf is None else LAW_CODES[lf.load_law]
    a, b = mf.fourier_a(), mf.fourier_b()
    used = [n for n in range(1, N_FOURIER + 1) if a[n] != 0.0 or b[n - 1] != 0.0]
    flags[FL.HARMONICS] = max(used, default=0)
    for effect, flag in EFFECT_FLAGS.items():
        flags[flag] = int(_in_kernel(model, effect))
    return p, flags


@dataclass(frozen=True)
class PlantState:
    """A readable snapshot of the plant's mechanical state [rad, rad/s] and its clock [s]."""

    theta_m: float
    omega_m: float
    theta_l: float
    omega_l: float
    time_s: float


class Plant:
    """The model ready to integrate: parameters compiled once, state kept between calls."""

    def __init__(self, model: HarmonicDriveModel) -> None:
        self.model = model
        self.p, self.flags = kernel_vectors(model)
        self.x = np.zeros(len(X))
        self.reset()

    def kinematic_error(self, theta_m: float) -> float:
        """θ_err = A·sin(k·θ_m + phi) at the output [rad]."""
        ke = self.model.kinematic_error
        return 0.0 if ke is None else ke.A * math.sin(ke.k * theta_m + ke.phi)

    def reset(
        self,
        theta_m: float = 0.0,
        omega_m: float = 0.0,
        theta_l: float | None = None,
        omega_l: float | None = None,
        time_s: float = 0.0,
        hidden: ArrayLike | None = None,
    ) -> None:
        """Set the state. An unknown load position means the spring is relaxed (zero deflection).

        `hidden` sets the states no sensor sees (HIDDEN_STATES: bristles, hysteresis element); zero
        by default. `time_s` is the time since the run started (thermal drift depends on it). The
        temperatures (a `thermal` section) start at its T_motor0 and T_gear0, ambient when unset.
        """
        r = self.model.mechanics.r
        self.x[:] = 0.0
        self.x[X.THETA_M] = theta_m
        self.x[X.OMEGA_M] = omega_m
        rigid_l = r * theta_m + self.kinematic_error(theta_m)
        self.x[X.THETA_L] = rigid_l if theta_l is None or self.model.rigid else theta_l
        self.x[X.OMEGA_L] = r * omega_m if omega_l is None or self.model.rigid else omega_l
        self.x[X.TIME] = time_s
        if (thermal := self.model.thermal) is not None:  # the temperatures at the start (thermal section)
            self.x[X.RISE_MOTOR] = thermal.motor_start_c - thermal.T_amb
            self.x[X.RISE_GEAR] = thermal.gear_start_c - thermal.T_amb
        if hidden is not None:
            self.x[list(HIDDEN_STATES)] = np.asarray(hidden, dtype=np.float64)

    @property
    def state(self) -> PlantState:
        x = self.x
        return PlantState(x[X.THETA_M], x[X.OMEGA_M], x[X.THETA_L], x[X.OMEGA_L], x[X.TIME])

    def advance(
        self,
        drive: ArrayLike,
        mode: InputMode = "voltage",
        tau_ext: ArrayLike = 0.0,
        dt_s: float = 1e-4,
        decim: int = 1,
        out: np.ndarray | None = None,
    ) -> np.ndarray:
        """Integrate len(drive) steps of dt_s; return the recorded rows (registry.OUT channels)."""
        drive = np.ascontiguousarray(drive, dtype=np.float64)
        load = np.ascontiguousarray(np.atleast_1d(np.asarray(tau_ext, dtype=np.float64)))
        if load.shape[0] not in (1, drive.shape[0]):
            raise ValueError(f"tau_ext has {load.shape[0]} values for {drive.shape[0]} steps")
        n_rows = -(-drive.shape[0] // decim)
        if out is None:
            out = np.empty((n_rows, len(OUT)))
        rows = k.integrate(self.p, self.flags, self.x, MODES[mode], drive, load, dt_s, decim, out)
        return out[:rows]

    def steady_friction(self, theta_m: ArrayLike, omega_m: ArrayLike) -> np.ndarray:
        """Moving-branch motor friction F_m [N·m] at positions [rad] and nonzero velocities [rad/s].

        Evaluated with no transmitted torque and at time zero (load-dependent and thermal effects off).
        """
        theta = np.ascontiguousarray(np.broadcast_to(theta_m, np.shape(omega_m)), dtype=np.float64)
        omega = np.ascontiguousarray(omega_m, dtype=np.float64)
        return k.steady_motor_friction(self.p, self.flags, theta.ravel(), omega.ravel(), 0.0, 0.0).reshape(
            omega.shape
        )

    def breakaway_friction(self, theta_m: ArrayLike, direction: float = 1.0) -> np.ndarray:
        """Static motor friction f_sm [N·m] at positions [rad], for a push in `direction`."""
        theta = np.ascontiguousarray(np.atleast_1d(theta_m), dtype=np.float64)
        return k.static_motor_friction(self.p, self.flags, theta, float(direction), 0.0, 0.0)
