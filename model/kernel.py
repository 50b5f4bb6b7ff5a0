"""The compiled inner loop: fixed-step integration of the docs/MODEL.md plant with Karnopp stick-slip.

Scheme: semi-implicit (symplectic) Euler. Each step computes every torque from the state at the start
of the step, updates the velocities, then the positions with the new velocities. Stick-slip follows
Karnopp: inside a small velocity band the stuck branch of docs/MODEL.md applies and the velocity is held at
exactly zero while |ψ| ≤ f_s. The events are located inside the step (the torques are held over it, so
each part of the step has a constant acceleration): a moving body whose velocity would change sign stops
at the zero crossing and the stuck rule decides the step's remainder (stay at zero, or break away the
other way at once); a body breaking away takes the stuck branch's friction until its speed reaches the
band's edge and the moving law after that instant. So every reversal passes through stick, friction never
reverses the motion it opposes, and the new velocity is continuous in the parameters: no event moves by
a whole step when an inertia changes by a hair (tests/test_kernel_events.py), which the trajectory fit's
exact replay of sim runs needs for a smooth cost.
LuGre and Dahl are smooth laws: their bristle state is advanced with the exact solution of its linear
ODE over the step (it is far too stiff for explicit Euler at useful steps).

Parameters travel as one float64 vector `p` and one int64 vector `flags`, indexed by the constants
below (numba folds module-level ints into constants). `model.plant` builds both from a validated
`HarmonicDriveModel`; nothing else should index them.

Inside the loop the flags travel as a tuple (`structure`), so that a loop compiled for one model's
structure (`specialized_profiles_loop`) sees them as constants: the compiler then drops the branches of
the laws and effects the model does not use. The general loop reads the same tuple from `flags` at
run time; both are the one `_advance`, and give the same numbers bit for bit.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
from numba import njit

from model.inputs import (  # the profile vector's layout, evaluated by profile_value
    PROFILE_CHIRP,
    PROFILE_CONST,
    PROFILE_LOG_CHIRP,
    PROFILE_PULSE,
    PROFILE_RAMP,
    PROFILE_SINE,
    PROFILE_STAIRCASE,
    PROFILE_STEP,
    Q_A,
    Q_AMP,
    Q_B,
    Q_C,
    Q_KIND,
    Q_OFFSET,
)

# --- float parameter vector -------------------------------------------------------------------
J_M, J_L, R_GEAR, K_M, K_B, R_ARM, K_S, D_S = range(8)
S1, S2, S3 = 8, 9, 10
FOURIER_A = 11  # a0..a10 at 11..21
FOURIER_B = 22  # b1..b10 at 22..31
V_C, K_V, STATIC_FACTOR, B_M = 32, 33, 34, 35
F_CM, F_SM, OMEGA_SM, SIGMA0_M, SIGMA1_M = 36, 37, 38, 39, 40
F_CL, F_SL, OMEGA_SL, SIGMA0_L, SIGMA1_L, B_L = 41, 42, 43, 44, 45, 46
KE_A, KE_K, KE_PHI = 47, 48, 49
NS_K1, NS_K2, NS_K3, NS_T1, NS_T2, NS_D1, NS_D2 = 50, 51, 52, 53, 54, 55, 56
ST_F, ST_OMEGA, DIR_F, LOAD_C, HYS_T, HYS_DELTA, TH_D, TH_TAU = 57, 58, 59, 60, 61, 62, 63, 64
OMEGA_STICK_M, OMEGA_STICK_L = 65, 66
WEAR_K = 67
N_PARAMS = 68

# --- integer flags ----------------------------------------------------------------------------
FL_MOTOR_LAW, FL_LOAD_LAW, FL_RIGID, FL_NONLINEAR, FL_HYSTERESIS, FL_KINEMATIC, FL_HARMONICS = range(7)
FL_STRIBECK, FL_THERMAL, FL_WEAR = 7, 8, 9
N_FLAGS = 10

LAW_NONE, LAW_ARTICLE, LAW_COULOMB_VISCOUS, LAW_STRIBECK, LAW_LUGRE, LAW_DAHL = range(6)

Structure = tuple[int, int, int, int, int, int, int, int, int, int]
"""The flags as a tuple, indexed by the FL_ constants: what the loop branches on."""

# --- state vector -----------------------------------------------------------------------------
X_THETA_M, X_OMEGA_M, X_THETA_L, X_OMEGA_L, X_Z_M, X_Z_L, X_Z_H, X_TIME, X_TS, X_TRAVEL = range(10)
N_STATE = 10  # X_TRAVEL: motor travel accumulated since the start, ∫|ω_m|dt [rad] (wear_drift)

# --- input modes and output channels ------------------------------------------------------------
MODE_VOLTAGE, MODE_CURRENT, MODE_TORQUE = 0, 1, 2
(
    OUT_T,
    OUT_DRIVE,
    OUT_TAU_EXT,
    OUT_THETA_M,
    OUT_OMEGA_M,
    OUT_THETA_L,
    OUT_OMEGA_L,
    OUT_I_A,
    OUT_TAU_M,
    OUT_F_M,
    OUT_F_L,
    OUT_T_S,
) = range(12)
N_OUT = 12


@njit(cache=True, inline="always")
def _sign(x: float) -> float:
    return 1.0 if x > 0.0 else (-1.0 if x < 0.0 else 0.0)


@njit(cache=True, inline="always")
def structure_of(flags: np.ndarray) -> Structure:
    """The flags vector as the loop's `Structure` tuple (a tuple holds no reference to count per step)."""
    return (
        flags[0], flags[1], flags[2], flags[3], flags[4], flags[5], flags[6], flags[7], flags[8], flags[9]
    )  # fmt: skip


@njit(cache=True, inline="always")
def position_coulomb(p: np.ndarray, n_harmonics: int, theta_m: float) -> tuple[float, float]:
    """C(θ_m) and P(θ_m) of docs/MODEL.md; the harmonics by angle-addition recurrence (two trig calls)."""
    c = (p[S1] * theta_m + p[S2]) * theta_m + p[S3]
    periodic = 0.5 * p[FOURIER_A]
    if n_harmonics > 0:
        c1 = math.cos(theta_m)
        s1 = math.sin(theta_m)
        cn = c1
        sn = s1
        for n in range(1, n_harmonics + 1):
            periodic += p[FOURIER_A + n] * cn + p[FOURIER_B + n - 1] * sn
            cn, sn = cn * c1 - sn * s1, sn * c1 + cn * s1
    return c, periodic


@njit(cache=True, inline="always")
def motor_levels(
    p: np.ndarray,
    s: Structure,
    theta_m: float,
    speed: float,
    t_s: float,
    time_s: float,
    travel_rad: float = 0.0,
) -> tuple[float, float]:
    """Motor friction magnitudes (moving at |ω_m| = speed, static) before direction asymmetry, ≥ 0.

    `time_s` is the time since the run started (thermal_drift), `travel_rad` the motor travel
    accumulated since then (wear_drift)."""
    law = s[FL_MOTOR_LAW]
    if law == LAW_ARTICLE:
        c, periodic = position_coulomb(p, s[FL_HARMONICS], theta_m)
        moving = c * (1.0 + p[K_V] * (speed - p[V_C])) + periodic
        static = p[STATIC_FACTOR] * (c * (1.0 - p[K_V] * p[V_C]) + periodic)
    elif law == LAW_COULOMB_VISCOUS:
        moving = p[F_CM]
        static = p[F_SM]
    elif law == LAW_STRIBECK:
        x = speed / p[OMEGA_SM]
        moving = p[F_CM] + (p[F_SM] - p[F_CM]) * math.exp(-x * x)
        static = p[F_SM]
    else:
        return 0.0, 0.0
    if s[FL_STRIBECK]:
        x = speed / p[ST_OMEGA]
        moving += p[ST_F] * math.exp(-x * x)
        static += p[ST_F]
    extra = p[LOAD_C] * abs(t_s)
    moving += extra
    static += extra
    if s[FL_THERMAL]:
        scale = 1.0 + p[TH_D] * (1.0 - math.exp(-time_s / p[TH_TAU]))
        moving *= scale
        static *= scale
    if s[FL_WEAR]:
        wear = 1.0 + p[WEAR_K] * travel_rad
        moving *= wear
        static *= wear
    return max(moving, 0.0), max(static, 0.0)


@njit(cache=True, inline="always")
def load_levels(p: np.ndarray, law: int, speed: float) -> tuple[float, float]:
    """Load friction magnitudes (moving at |ω_l| = speed, static) for a Karnopp-type load law."""
    if law == LAW_COULOMB_VISCOUS:
        return p[F_CL], p[F_SL]
    if law == LAW_STRIBECK:
        x = speed / p[OMEGA_SL]
        return p[F_CL] + (p[F_SL] - p[F_CL]) * math.exp(-x * x), p[F_SL]
    return 0.0, 0.0


@njit(cache=True, inline="always")
def _breakaway(
    omega: float,
    psi: float,
    direction: float,
    limit: float,
    level: float,
    viscous: float,
    inertia: float,
    span: float,
    band: float,
) -> tuple[float, bool]:
    """The velocity after `span` [s] of breaking away in `direction` from ω inside the band; whether the
    speed left the band on the way.

    The stuck branch's friction direction·limit applies until the speed along `direction` reaches the
    band's edge, the moving law (`level` + viscous) after it. The edge is located inside the span (the
    acceleration is constant on each side of it), so the switch of law moves continuously with the
    parameters instead of by a whole step.
    """
    new = omega + span * (psi - direction * limit) / inertia
    speed = direction * omega
    speed_new = direction * new
    if speed_new < band:
        return new, False
    to_edge = span * (band - speed) / (speed_new - speed)
    at_edge = omega + to_edge * (psi - direction * limit) / inertia
    friction = direction * level + viscous * at_edge
    return at_edge + (span - to_edge) * (psi - friction) / inertia, True


@njit(cache=True, inline="always")
def _karnopp(
    omega: float,
    psi: float,
    moving: float,
    static: float,
    asym: float,
    viscous: float,
    inertia: float,
    dt: float,
    band: float,
) -> tuple[float, float]:
    """One velocity update under Karnopp friction. Returns (new velocity, friction actually applied).

    `moving`/`static` are magnitudes; `asym` is added to them in the direction of motion (or of ψ when
    stuck). The friction returned is the one consistent with the velocity change (ψ − J·Δω/dt), so
    that the energy it dissipates can be accounted for exactly.

    Events are located inside the step, not at its start: a reversal stops at its zero crossing and
    the stuck rule decides the rest of the step (stay, or break away); a breakaway switches from the
    static to the moving law where the speed crosses the band's edge. The new velocity is then
    continuous in the parameters: no event jumps by a whole step when a parameter moves a little.
    """
    start = omega  # the velocity the stuck rule starts from, over `span`
    span = dt
    if abs(omega) >= band:
        direction = _sign(omega)
        friction = direction * max(moving + asym * direction, 0.0) + viscous * omega
        new = omega + dt * (psi - friction) / inertia
        if new * omega >= 0.0:
            return new, friction
        # A reversal passes through stick: stopped at the zero crossing, at rest for the step's remainder.
        start = 0.0
        span = dt * new / (new - omega)
    direction = _sign(psi)
    limit = max(static + asym * direction, 0.0)
    if abs(psi) <= limit:
        return 0.0, psi + inertia * omega / dt
    level = max(moving + asym * direction, 0.0)
    new, left_band = _breakaway(start, psi, direction, limit, level, viscous, inertia, span, band)
    if span == dt and not left_band:
        return new, direction * limit
    return new, psi - inertia * (new - omega) / dt


@njit(cache=True, inline="always")
def _bristle(
    z: float, omega: float, f_c: float, f_s: float, omega_s: float, sigma0: float, dt: float
) -> float:
    """LuGre/Dahl bristle state after one step, from the exact solution at constant ω."""
    if omega == 0.0:
        return z
    if omega_s > 0.0:
        x = omega / omega_s
        g = f_c + (f_s - f_c) * math.exp(-x * x)
    else:
        g = f_c
    if g <= 0.0:
        return 0.0
    rate = sigma0 * abs(omega) / g
    z_ss = g * _sign(omega) / sigma0
    return z_ss + (z - z_ss) * math.exp(-rate * dt)


@njit(cache=True, inline="always")
def _spring(p: np.ndarray, nonlinear: int, deflection: float) -> float:
    """Transmitted spring torque for a deflection at the output: linear K_s or catalog piecewise."""
    if not nonlinear:
        return p[K_S] * deflection
    d = abs(deflection)
    if d <= p[NS_D1]:
        torque = p[NS_K1] * d
    elif d <= p[NS_D2]:
        torque = p[NS_T1] + p[NS_K2] * (d - p[NS_D1])
    else:
        torque = p[NS_T2] + p[NS_K3] * (d - p[NS_D2])
    return torque if deflection >= 0.0 else -torque


Profile = tuple[float, float, float, float, float, float]
"""A profile vector (model.inputs' layout) as a tuple: read in the loop without reference counting."""


@njit(cache=True, inline="always")
def profile_of(q: np.ndarray) -> Profile:
    """The profile vector `q` as a `Profile` tuple."""
    return (q[0], q[1], q[2], q[3], q[4], q[5])


@njit(cache=True, inline="always")
def profile_value(q: Profile, t: float) -> float:
    """The input profile `q` at time `t` [s] (docs/INTERFACE.md's kinds; chirps as scipy.signal.chirp)."""
    kind = int(q[Q_KIND])
    offset = q[Q_OFFSET]
    amp = q[Q_AMP]
    if kind == PROFILE_SINE:
        return offset + amp * math.sin(2.0 * math.pi * q[Q_A] * t + q[Q_B])
    if kind == PROFILE_CONST:
        return offset
    if kind == PROFILE_STEP:
        return offset + (amp if t >= q[Q_A] else 0.0)
    if kind == PROFILE_RAMP:
        return offset + amp * max(t - q[Q_A], 0.0)
    if kind == PROFILE_CHIRP:
        f0 = q[Q_A]
        phase = 2.0 * math.pi * (f0 * t + 0.5 * ((q[Q_B] - f0) / q[Q_C]) * t * t)
        return offset + amp * math.sin(phase)  # a sine start: continuous from rest
    if kind == PROFILE_LOG_CHIRP:
        f0 = q[Q_A]
        f1 = q[Q_B]
        if f0 == f1:
            phase = 2.0 * math.pi * f0 * t
        else:
            beta = q[Q_C] / math.log(f1 / f0)
            phase = 2.0 * math.pi * beta * f0 * ((f1 / f0) ** (t / q[Q_C]) - 1.0)
        return offset + amp * math.sin(phase)
    if kind == PROFILE_PULSE:
        on = t >= q[Q_C] and (t - q[Q_C]) % q[Q_B] < q[Q_A]
        return offset + (amp if on else 0.0)
    if kind == PROFILE_STAIRCASE:
        steps = int(q[Q_A])
        index = min(max(t // q[Q_B], 0.0), steps - 1.0)
        # np.linspace(-amp, amp, steps)[index], its last level exactly +amp
        level = amp if index == steps - 1 else -amp + index * (2.0 * amp / (steps - 1))
        return offset + level
    raise ValueError("unknown input profile kind")


@njit(cache=True)
def profile_values(q: np.ndarray, t: np.ndarray) -> np.ndarray:
    """`profile_value` at each of the times `t` [s]."""
    out = np.empty(t.shape[0])
    profile = profile_of(q)
    for i in range(t.shape[0]):
        out[i] = profile_value(profile, t[i])
    return out


@njit(cache=True)
def integrate(
    p: np.ndarray,
    flags: np.ndarray,
    x: np.ndarray,
    mode: int,
    drive: np.ndarray,
    tau_ext: np.ndarray,
    dt: float,
    decim: int,
    out: np.ndarray,
) -> int:
    """Advance the state `x` in place by len(drive) steps of `dt`; return rows written to `out`.

    `drive` holds the input per step (u in V, i_cmd in A or τ_m in N·m by `mode`), held over the step;
    `tau_ext` has one value per step or a single value for all. Every `decim`-th step (from the first)
    writes one row of `out` with the state at the start of that step and the torques applied over it.
    """
    return _advance_general(
        p,
        structure_of(flags),
        x,
        mode,
        drive,
        tau_ext,
        drive[:0],
        drive[:0],
        0.0,
        drive.shape[0],
        dt,
        decim,
        out,
    )


@njit(cache=True)
def integrate_profiles(
    p: np.ndarray,
    flags: np.ndarray,
    x: np.ndarray,
    mode: int,
    drive_q: np.ndarray,
    load_q: np.ndarray,
    first_step: float,
    n_steps: int,
    dt: float,
    decim: int,
    out: np.ndarray,
) -> int:
    """`integrate` with the drive and the load given as profiles (`profile_value` vectors), evaluated
    at each step's time (first_step + i)·dt: no per-step input arrays, so a run of any length streams
    through the loop at the loop's own pace."""
    return _advance_general(
        p,
        structure_of(flags),
        x,
        mode,
        drive_q[:0],
        load_q[:0],
        drive_q,
        load_q,
        first_step,
        n_steps,
        dt,
        decim,
        out,
    )


ProfilesLoop = Callable[
    [np.ndarray, np.ndarray, int, np.ndarray, np.ndarray, float, int, float, int, np.ndarray], int
]
"""`integrate_profiles` without its `flags` argument: (p, x, mode, drive_q, load_q, first_step, n_steps,
dt, decim, out) -> rows."""
_SPECIALIZED: dict[Structure, ProfilesLoop] = {}


def profiles_loop(flags: np.ndarray, specialized: bool) -> ProfilesLoop:
    """`integrate_profiles` for the model structure `flags`: compiled for it (`specialized_profiles_loop`)
    or the general loop, which reads the flags at run time."""
    if specialized:
        return specialized_profiles_loop(flags)

    def general(p: np.ndarray, x: np.ndarray, *rest: Any) -> int:
        rows: int = integrate_profiles(p, flags, x, *rest)
        return rows

    return general


def specialized_profiles_loop(flags: np.ndarray) -> ProfilesLoop:
    """`integrate_profiles` compiled for the model structure `flags` (laws, effects, harmonics as constants).

    Same numbers as `integrate_profiles`, bit for bit, ~15 % fewer ns a step on the seed preset
    (docs/BENCHMARKS.md, long runs); the price is one compile per structure (3-7 s, then in numba's
    on-disk cache, keyed by the structure), so it pays for long runs only.
    """
    key: Structure = tuple(int(f) for f in flags)  # type: ignore[assignment]
    if len(key) != N_FLAGS:
        raise ValueError(f"flags has {len(key)} entries, the kernel's layout {N_FLAGS}")
    loop = _SPECIALIZED.get(key)
    if loop is None:
        loop = _SPECIALIZED[key] = _compile_profiles_loop(key)
    return loop


def _compile_profiles_loop(structure: Structure) -> ProfilesLoop:
    # `structure` is a closure variable, which numba compiles as a constant (and keys its cache by).
    def loop(
        p: np.ndarray,
        x: np.ndarray,
        mode: int,
        drive_q: np.ndarray,
        load_q: np.ndarray,
        first_step: float,
        n_steps: int,
        dt: float,
        decim: int,
        out: np.ndarray,
    ) -> int:
        return _advance_inlined(
            p,
            structure,
            x,
            mode,
            drive_q[:0],
            load_q[:0],
            drive_q,
            load_q,
            first_step,
            n_steps,
            dt,
            decim,
            out,
        )

    compiled: ProfilesLoop = njit(cache=True)(loop)
    return compiled


def _advance(
    p: np.ndarray,
    s: Structure,
    x: np.ndarray,
    mode: int,
    drive: np.ndarray,
    tau_ext: np.ndarray,
    drive_q: np.ndarray,
    load_q: np.ndarray,
    first_step: float,
    n_steps: int,
    dt: float,
    decim: int,
    out: np.ndarray,
) -> int:
    """The loop of `integrate` and `integrate_profiles`: inputs from arrays, or from profiles when
    `drive_q` is not empty (then `drive` and `tau_ext` are). Compiled twice below: `_advance_general`
    and `_advance_inlined`."""
    profiles = drive_q.shape[0] > 0
    const_load = tau_ext.shape[0] == 1
    # Profiles as tuples: an array read inside the loop would cost two atomic reference counts a step.
    drive_profile = profile_of(drive_q) if profiles else (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    load_profile = profile_of(load_q) if profiles else (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    # A constant load profile (the usual case) is read once, not evaluated at every step.
    fixed_load = profiles and load_profile[Q_KIND] == PROFILE_CONST
    load_value = load_profile[Q_OFFSET] if fixed_load else 0.0
    motor_law = s[FL_MOTOR_LAW]
    load_law = s[FL_LOAD_LAW]
    rigid = s[FL_RIGID]
    nonlinear = s[FL_NONLINEAR]
    hysteresis = s[FL_HYSTERESIS]
    kinematic = s[FL_KINEMATIC]
    # The kinematic error's rate costs a cos per step; only damping, hysteresis and a rigid output use it.
    needs_deflection_rate = rigid or hysteresis or p[D_S] != 0.0
    motor_smooth = motor_law in (LAW_LUGRE, LAW_DAHL)
    load_smooth = load_law in (LAW_LUGRE, LAW_DAHL)
    r = p[R_GEAR]
    j_m = p[J_M]
    j_l = p[J_L]
    j_rigid = j_m + r * r * j_l
    b_load = p[B_L] if load_law != LAW_NONE else 0.0
    theta_m = x[X_THETA_M]
    omega_m = x[X_OMEGA_M]
    theta_l = x[X_THETA_L]
    omega_l = x[X_OMEGA_L]
    z_m = x[X_Z_M]
    z_l = x[X_Z_L]
    z_h = x[X_Z_H]
    time_s = x[X_TIME]
    t_s_prev = x[X_TS]
    travel = x[X_TRAVEL]
    rows = 0
    until_row = 0  # steps until the next output row (a countdown: no integer division a step)
    for i in range(n_steps):
        if profiles:
            t_input = (first_step + i) * dt  # from the step index: no drift of a summed clock
            value = profile_value(drive_profile, t_input)
            load_torque = load_value if fixed_load else profile_value(load_profile, t_input)
        else:
            load_torque = tau_ext[0] if const_load else tau_ext[i]
            value = drive[i]
        if mode == MODE_VOLTAGE:
            i_a = (value - p[K_B] * omega_m) / p[R_ARM]
            torque_m = p[K_M] * i_a
        elif mode == MODE_CURRENT:
            i_a = value
            torque_m = p[K_M] * i_a
        else:
            torque_m = value
            i_a = value / p[K_M]

        theta_err = 0.0
        omega_err = 0.0
        if kinematic:
            phase = p[KE_K] * theta_m + p[KE_PHI]
            theta_err = p[KE_A] * math.sin(phase)
            if needs_deflection_rate:
                omega_err = p[KE_A] * p[KE_K] * math.cos(phase) * omega_m

        if rigid:
            t_s = t_s_prev
        else:
            deflection = r * theta_m + theta_err - theta_l
            deflection_rate = r * omega_m + omega_err - omega_l
            t_s = _spring(p, nonlinear, deflection) + p[D_S] * deflection_rate + z_h
            if hysteresis and deflection_rate != 0.0:
                rate = abs(deflection_rate) / p[HYS_DELTA]
                z_ss = p[HYS_T] * _sign(deflection_rate)
                z_h = z_ss + (z_h - z_ss) * math.exp(-rate * dt)

        # Smooth (bristle) friction first; the Karnopp part then sees it as a known torque.
        f_smooth_m = 0.0
        if motor_smooth:
            z_new = _bristle(z_m, omega_m, p[F_CM], p[F_SM], p[OMEGA_SM], p[SIGMA0_M], dt)
            f_smooth_m = p[SIGMA0_M] * z_new + p[SIGMA1_M] * (z_new - z_m) / dt + p[B_M] * omega_m
            z_m = z_new
        f_smooth_l = 0.0
        omega_l_now = r * omega_m + omega_err if rigid else omega_l
        if load_smooth:
            z_new = _bristle(z_l, omega_l_now, p[F_CL], p[F_SL], p[OMEGA_SL], p[SIGMA0_L], dt)
            f_smooth_l = p[SIGMA0_L] * z_new + p[SIGMA1_L] * (z_new - z_l) / dt + b_load * omega_l_now
            z_l = z_new

        speed_m = abs(omega_m)
        moving_m, static_m = motor_levels(p, s, theta_m, speed_m, t_s, time_s, travel)
        asym_m = p[DIR_F]
        viscous_m = 0.0 if motor_smooth else p[B_M]
        moving_l, static_l = load_levels(p, load_law, abs(omega_l_now))
        viscous_l = 0.0 if load_smooth else b_load

        if rigid:
            psi = torque_m - f_smooth_m - r * (load_torque + f_smooth_l)
            new_omega, f_total = _karnopp(
                omega_m,
                psi,
                moving_m + r * moving_l,
                static_m + r * static_l,
                asym_m,
                viscous_m + r * r * viscous_l,
                j_rigid,
                dt,
                p[OMEGA_STICK_M],
            )
            # Split the common friction for the record: the load share in proportion to the levels.
            share_l = r * moving_l / (moving_m + r * moving_l) if moving_m + r * moving_l > 0.0 else 0.0
            f_l = f_smooth_l + share_l * f_total / r if r > 0.0 else f_smooth_l
            f_m = f_smooth_m + (1.0 - share_l) * f_total
            new_omega_l = r * new_omega
            t_s = load_torque + f_l + j_l * r * (new_omega - omega_m) / dt
            t_s_prev = t_s
        else:
            psi_m = torque_m - r * t_s - f_smooth_m
            if motor_law == LAW_NONE or motor_smooth:
                new_omega = omega_m + dt * psi_m / j_m
                f_m = f_smooth_m
            else:
                new_omega, f_k = _karnopp(
                    omega_m, psi_m, moving_m, static_m, asym_m, viscous_m, j_m, dt, p[OMEGA_STICK_M]
                )
                f_m = f_smooth_m + f_k
            psi_l = t_s - load_torque - f_smooth_l
            if load_law == LAW_NONE or load_smooth:
                new_omega_l = omega_l + dt * psi_l / j_l
                f_l = f_smooth_l
            else:
                new_omega_l, f_k = _karnopp(
                    omega_l, psi_l, moving_l, static_l, 0.0, viscous_l, j_l, dt, p[OMEGA_STICK_L]
                )
                f_l = f_smooth_l + f_k

        if until_row == 0:
            until_row = decim
            out[rows, OUT_T] = time_s
            out[rows, OUT_DRIVE] = value
            out[rows, OUT_TAU_EXT] = load_torque
            out[rows, OUT_THETA_M] = theta_m
            out[rows, OUT_OMEGA_M] = omega_m
            out[rows, OUT_THETA_L] = r * theta_m + theta_err if rigid else theta_l
            out[rows, OUT_OMEGA_L] = omega_l_now
            out[rows, OUT_I_A] = i_a
            out[rows, OUT_TAU_M] = torque_m
            out[rows, OUT_F_M] = f_m
            out[rows, OUT_F_L] = f_l
            out[rows, OUT_T_S] = t_s
            rows += 1
        until_row -= 1

        omega_m = new_omega
        theta_m += dt * omega_m
        travel += dt * abs(omega_m)
        if not rigid:
            omega_l = new_omega_l
            theta_l += dt * omega_l
        time_s += dt

    if rigid:
        # Keep the load states meaningful for whoever reads the state after a chunk.
        omega_l = r * omega_m
        theta_l = r * theta_m
        if kinematic:
            theta_l += p[KE_A] * math.sin(p[KE_K] * theta_m + p[KE_PHI])
    x[X_THETA_M] = theta_m
    x[X_OMEGA_M] = omega_m
    x[X_THETA_L] = theta_l
    x[X_OMEGA_L] = omega_l
    x[X_Z_M] = z_m
    x[X_Z_L] = z_l
    x[X_Z_H] = z_h
    x[X_TIME] = time_s
    x[X_TS] = t_s_prev
    x[X_TRAVEL] = travel
    return rows


# The one loop, compiled twice: once on its own, called by `integrate` and `integrate_profiles` (inlined
# into both, their first compile took ~17 s of CPU instead of ~4.5 s), and inlined into each specialized
# loop, where inlining is what makes its constant structure reach the branches.
_advance_general = njit(cache=True)(_advance)
_advance_inlined = njit(inline="always")(_advance)


@njit(cache=True)
def steady_motor_friction(
    p: np.ndarray, flags: np.ndarray, theta_m: np.ndarray, omega_m: np.ndarray, t_s: float, time_s: float
) -> np.ndarray:
    """Moving-branch motor friction F_m at given positions and (nonzero) velocities, for Karnopp laws.

    The same level functions as the integrator, so tests and the fitter use one copy of the physics.
    Smooth laws (LuGre, Dahl) give their steady state: g(ω)·sgn(ω) + b_m·ω.
    """
    n = theta_m.shape[0]
    out = np.empty(n)
    s = structure_of(flags)
    law = s[FL_MOTOR_LAW]
    for i in range(n):
        w = omega_m[i]
        direction = _sign(w)
        if law in (LAW_LUGRE, LAW_DAHL):
            g = p[F_CM]
            if law == LAW_LUGRE:
                x = w / p[OMEGA_SM]
                g = p[F_CM] + (p[F_SM] - p[F_CM]) * math.exp(-x * x)
            out[i] = direction * g + p[B_M] * w
            continue
        moving, _ = motor_levels(p, s, theta_m[i], abs(w), t_s, time_s)
        out[i] = direction * max(moving + p[DIR_F] * direction, 0.0) + p[B_M] * w
    return out


@njit(cache=True)
def static_motor_friction(
    p: np.ndarray, flags: np.ndarray, theta_m: np.ndarray, direction: float, t_s: float, time_s: float
) -> np.ndarray:
    """Breakaway level f_sm at given positions for a push in `direction` (+1 or −1), Karnopp laws."""
    n = theta_m.shape[0]
    out = np.empty(n)
    s = structure_of(flags)
    for i in range(n):
        _, static = motor_levels(p, s, theta_m[i], 0.0, t_s, time_s)
        out[i] = max(static + p[DIR_F] * direction, 0.0)
    return out
