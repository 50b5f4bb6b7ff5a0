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

InputMode = Literal["voltage", "current", "torque"]
MODES: dict[str, int] = {"voltage": k.MODE_VOLTAGE, "current": k.MODE_CURRENT, "torque": k.MODE_TORQUE}
INPUT_COLUMN: dict[str, str] = {"voltage": "u", "current": "i_cmd", "torque": "tau_m"}
MODE_OF_COLUMN: dict[str, InputMode] = {"u": "voltage", "i_cmd": "current", "tau_m": "torque"}

HIDDEN_STATES = (k.X_Z_M, k.X_Z_L, k.X_Z_H)
"""Kernel states no sensor measures: motor and load bristle deflections, the hysteresis torque."""

_LAW_CODES = {
    "article": k.LAW_ARTICLE,
    "coulomb_viscous": k.LAW_COULOMB_VISCOUS,
    "stribeck": k.LAW_STRIBECK,
    "lugre": k.LAW_LUGRE,
    "dahl": k.LAW_DAHL,
}


def kernel_vectors(model: HarmonicDriveModel) -> tuple[np.ndarray, np.ndarray]:
    """The float parameter vector and int flag vector that `model.kernel` reads."""
    p = np.zeros(k.N_PARAMS)
    flags = np.zeros(k.N_FLAGS, dtype=np.int64)
    mech, motor, trans, mf = model.mechanics, model.motor, model.transmission, model.motor_friction
    p[k.J_M], p[k.J_L], p[k.R_GEAR] = mech.J_m, mech.J_l, mech.r
    p[k.K_M], p[k.K_B], p[k.R_ARM] = motor.K_m, motor.K_b, motor.R
    p[k.K_S] = trans.K_s or 0.0
    p[k.D_S] = trans.D_s
    flags[k.FL_RIGID] = int(trans.K_s is None)

    flags[k.FL_MOTOR_LAW] = _LAW_CODES[mf.motor_law]
    p[k.S1], p[k.S2], p[k.S3] = mf.s1 or 0.0, mf.s2 or 0.0, mf.s3 or 0.0
    a, b = mf.fourier_a(), mf.fourier_b()
    p[k.FOURIER_A : k.FOURIER_A + N_FOURIER + 1] = a
    p[k.FOURIER_B : k.FOURIER_B + N_FOURIER] = b
    used = [n for n in range(1, N_FOURIER + 1) if a[n] != 0.0 or b[n - 1] != 0.0]
    flags[k.FL_HARMONICS] = max(used, default=0)
    p[k.V_C] = mf.v_c if mf.v_c is not None else 0.0
    p[k.K_V] = mf.k_v or 0.0
    p[k.STATIC_FACTOR] = mf.static_factor if mf.static_factor is not None else 1.0
    p[k.B_M] = mf.b_m
    p[k.F_CM], p[k.F_SM] = mf.f_cm or 0.0, mf.f_sm or 0.0
    p[k.OMEGA_SM], p[k.SIGMA0_M], p[k.SIGMA1_M] = mf.omega_sm or 0.0, mf.sigma0_m or 1.0, mf.sigma1_m or 0.0

    lf = model.load_friction
    flags[k.FL_LOAD_LAW] = k.LAW_NONE if lf is None else _LAW_CODES[lf.load_law]
    if lf is not None:
        p[k.F_CL], p[k.F_SL], p[k.B_L] = lf.f_cl or 0.0, lf.f_sl or 0.0, lf.b_l
        p[k.OMEGA_SL], p[k.SIGMA0_L], p[k.SIGMA1_L] = (
            lf.omega_sl or 0.0,
            lf.sigma0_l or 1.0,
            lf.sigma1_l or 0.0,
        )

    if (ke := model.kinematic_error) is not None and ke.A > 0.0:
        flags[k.FL_KINEMATIC] = 1
        p[k.KE_A], p[k.KE_K], p[k.KE_PHI] = ke.A, ke.k, ke.phi
    if (ns := model.nonlinear_stiffness) is not None:
        flags[k.FL_NONLINEAR] = 1
        p[k.NS_K1], p[k.NS_K2], p[k.NS_K3], p[k.NS_T1], p[k.NS_T2] = ns.K1, ns.K2, ns.K3, ns.T1, ns.T2
        p[k.NS_D1] = ns.T1 / ns.K1
        p[k.NS_D2] = p[k.NS_D1] + (ns.T2 - ns.T1) / ns.K2
    if (st := model.stribeck) is not None:
        flags[k.FL_STRIBECK] = 1
        p[k.ST_F], p[k.ST_OMEGA] = st.f_st, st.omega_st
    if model.direction_asymmetry is not None:
        p[k.DIR_F] = model.direction_asymmetry.f_dir
    if model.load_dependent_friction is not None:
        p[k.LOAD_C] = model.load_dependent_friction.c_Ts
    if (hy := model.hysteresis) is not None:
        flags[k.FL_HYSTERESIS] = 1
        p[k.HYS_T], p[k.HYS_DELTA] = hy.T_h, hy.delta_h
    if (th := model.thermal_drift) is not None:
        flags[k.FL_THERMAL] = 1
        p[k.TH_D], p[k.TH_TAU] = th.d_th, th.tau_th
    if (wear := model.wear_drift) is not None:
        flags[k.FL_WEAR] = 1
        p[k.WEAR_K] = wear.k_wear
    p[k.OMEGA_STICK_M] = model.numerics.omega_stick_m
    p[k.OMEGA_STICK_L] = model.numerics.omega_stick_l
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
        self.x = np.zeros(k.N_STATE)
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
        by default. `time_s` is the time since the run started (thermal drift depends on it).
        """
        r = self.model.mechanics.r
        self.x[:] = 0.0
        self.x[k.X_THETA_M] = theta_m
        self.x[k.X_OMEGA_M] = omega_m
        rigid_l = r * theta_m + self.kinematic_error(theta_m)
        self.x[k.X_THETA_L] = rigid_l if theta_l is None or self.model.rigid else theta_l
        self.x[k.X_OMEGA_L] = r * omega_m if omega_l is None or self.model.rigid else omega_l
        self.x[k.X_TIME] = time_s
        if hidden is not None:
            self.x[list(HIDDEN_STATES)] = np.asarray(hidden, dtype=np.float64)

    @property
    def state(self) -> PlantState:
        x = self.x
        return PlantState(x[k.X_THETA_M], x[k.X_OMEGA_M], x[k.X_THETA_L], x[k.X_OMEGA_L], x[k.X_TIME])

    def advance(
        self,
        drive: ArrayLike,
        mode: InputMode = "voltage",
        tau_ext: ArrayLike = 0.0,
        dt_s: float = 1e-4,
        decim: int = 1,
        out: np.ndarray | None = None,
    ) -> np.ndarray:
        """Integrate len(drive) steps of dt_s; return the recorded rows (kernel.OUT_* channels)."""
        drive = np.ascontiguousarray(drive, dtype=np.float64)
        load = np.ascontiguousarray(np.atleast_1d(np.asarray(tau_ext, dtype=np.float64)))
        if load.shape[0] not in (1, drive.shape[0]):
            raise ValueError(f"tau_ext has {load.shape[0]} values for {drive.shape[0]} steps")
        n_rows = -(-drive.shape[0] // decim)
        if out is None:
            out = np.empty((n_rows, k.N_OUT))
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
