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

Parameters travel as one float64 vector `p` and one int64 vector `flags`, laid out by `model.registry`'s
`P` and `FL` (`IntEnum`s, which numba folds into constants), the state by `X`, the output rows by `OUT`.
`model.plant` builds the vectors from a validated `HarmonicDriveModel`; nothing else should fill them.

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

from model.inputs import Kind, Q  # the profile vector's layout, evaluated by profile_value
from model.registry import FL, OUT, Law, Mode, P, X

Structure = tuple[int, int, int, int, int, int, int, int, int, int, int]
"""The flags as a tuple, indexed by `FL` (read `s[FL.RIGID.value]`: numba cannot index a tuple by an
`IntEnum` member itself): what the loop branches on."""


@njit(cache=True, inline="always")
def _sign(x: float) -> float:
    return 1.0 if x > 0.0 else (-1.0 if x < 0.0 else 0.0)


@njit(cache=True, inline="always")
def structure_of(flags: np.ndarray) -> Structure:
    """The flags vector as the loop's `Structure` tuple (a tuple holds no reference to count per step)."""
    return (
        flags[0], flags[1], flags[2], flags[3], flags[4], flags[5], flags[6], flags[7], flags[8], flags[9],
        flags[10],
    )  # fmt: skip


@njit(cache=True, inline="always")
def position_coulomb(p: np.ndarray, n_harmonics: int, theta_m: float) -> tuple[float, float]:
    """C(θ_m) and P(θ_m) of docs/MODEL.md; the harmonics by angle-addition recurrence (two trig calls)."""
    c = (p[P.S1] * theta_m + p[P.S2]) * theta_m + p[P.S3]
    periodic = 0.5 * p[P.A0]
    if n_harmonics > 0:
        c1 = math.cos(theta_m)
        s1 = math.sin(theta_m)
        cn = c1
        sn = s1
        for n in range(1, n_harmonics + 1):
            periodic += p[P.A0 + n] * cn + p[P.B1 + n - 1] * sn
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
    law = s[FL.MOTOR_LAW.value]
    if law == Law.ARTICLE:
        c, periodic = position_coulomb(p, s[FL.HARMONICS.value], theta_m)
        moving = c * (1.0 + p[P.K_V] * (speed - p[P.V_C])) + periodic
        static = p[P.STATIC_FACTOR] * (c * (1.0 - p[P.K_V] * p[P.V_C]) + periodic)
    elif law == Law.COULOMB_VISCOUS:
        moving = p[P.F_CM]
        static = p[P.F_SM]
    elif law == Law.STRIBECK:
        x = speed / p[P.OMEGA_SM]
        moving = p[P.F_CM] + (p[P.F_SM] - p[P.F_CM]) * math.exp(-x * x)
        static = p[P.F_SM]
    else:
        return 0.0, 0.0
    if s[FL.STRIBECK.value]:
        x = speed / p[P.ST_OMEGA]
        moving += p[P.ST_F] * math.exp(-x * x)
        static += p[P.ST_F]
    extra = p[P.LOAD_C] * abs(t_s)
    moving += extra
    static += extra
    if s[FL.THERMAL.value]:
        scale = 1.0 + p[P.TH_D] * (1.0 - math.exp(-time_s / p[P.TH_TAU]))
        moving *= scale
        static *= scale
    if s[FL.WEAR.value]:
        wear = 1.0 + p[P.WEAR_K] * travel_rad
        moving *= wear
        static *= wear
    return max(moving, 0.0), max(static, 0.0)


@njit(cache=True, inline="always")
def load_levels(p: np.ndarray, law: int, speed: float) -> tuple[float, float]:
    """Load friction magnitudes (moving at |ω_l| = speed, static) for a Karnopp-type load law."""
    if law == Law.COULOMB_VISCOUS:
        return p[P.F_CL], p[P.F_SL]
    if law == Law.STRIBECK:
        x = speed / p[P.OMEGA_SL]
        return p[P.F_CL] + (p[P.F_SL] - p[P.F_CL]) * math.exp(-x * x), p[P.F_SL]
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
        return p[P.K_S] * deflection
    d = abs(deflection)
    if d <= p[P.NS_D1]:
        torque = p[P.NS_K1] * d
    elif d <= p[P.NS_D2]:
        torque = p[P.NS_T1] + p[P.NS_K2] * (d - p[P.NS_D1])
    else:
        torque = p[P.NS_T2] + p[P.NS_K3] * (d - p[P.NS_D2])
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
    kind = int(q[Q.KIND.value])
    offset = q[Q.OFFSET.value]
    amp = q[Q.AMP.value]
    if kind == Kind.SINE:
        return offset + amp * math.sin(2.0 * math.pi * q[Q.A.value] * t + q[Q.B.value])
    if kind == Kind.CONST:
        return offset
    if kind == Kind.STEP:
        return offset + (amp if t >= q[Q.A.value] else 0.0)
    if kind == Kind.RAMP:
        return offset + amp * max(t - q[Q.A.value], 0.0)
    if kind == Kind.CHIRP:
        f0 = q[Q.A.value]
        phase = 2.0 * math.pi * (f0 * t + 0.5 * ((q[Q.B.value] - f0) / q[Q.C.value]) * t * t)
        return offset + amp * math.sin(phase)  # a sine start: continuous from rest
    if kind == Kind.LOG_CHIRP:
        f0 = q[Q.A.value]
        f1 = q[Q.B.value]
        if f0 == f1:
            phase = 2.0 * math.pi * f0 * t
        else:
            beta = q[Q.C.value] / math.log(f1 / f0)
            phase = 2.0 * math.pi * beta * f0 * ((f1 / f0) ** (t / q[Q.C.value]) - 1.0)
        return offset + amp * math.sin(phase)
    if kind == Kind.PULSE:
        on = t >= q[Q.C.value] and (t - q[Q.C.value]) % q[Q.B.value] < q[Q.A.value]
        return offset + (amp if on else 0.0)
    if kind == Kind.STAIRCASE:
        steps = int(q[Q.A.value])
        index = min(max(t // q[Q.B.value], 0.0), steps - 1.0)
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
    if len(key) != len(FL):
        raise ValueError(f"flags has {len(key)} entries, the kernel's layout {len(FL)}")
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
    fixed_load = profiles and load_profile[Q.KIND.value] == Kind.CONST.value
    load_value = load_profile[Q.OFFSET.value] if fixed_load else 0.0
    motor_law = s[FL.MOTOR_LAW.value]
    load_law = s[FL.LOAD_LAW.value]
    rigid = s[FL.RIGID.value]
    nonlinear = s[FL.NONLINEAR.value]
    hysteresis = s[FL.HYSTERESIS.value]
    kinematic = s[FL.KINEMATIC.value]
    temperature = s[FL.TEMPERATURE.value]
    # The kinematic error's rate costs a cos per step; only damping, hysteresis and a rigid output use it.
    needs_deflection_rate = rigid or hysteresis or p[P.D_S] != 0.0
    motor_smooth = motor_law in (Law.LUGRE, Law.DAHL)
    load_smooth = load_law in (Law.LUGRE, Law.DAHL)
    r = p[P.R_GEAR]
    j_m = p[P.J_M]
    j_l = p[P.J_L]
    j_rigid = j_m + r * r * j_l
    b_load = p[P.B_L] if load_law != Law.NONE else 0.0
    theta_m = x[X.THETA_M]
    omega_m = x[X.OMEGA_M]
    theta_l = x[X.THETA_L]
    omega_l = x[X.OMEGA_L]
    z_m = x[X.Z_M]
    z_l = x[X.Z_L]
    z_h = x[X.Z_H]
    time_s = x[X.TIME]
    t_s_prev = x[X.TS]
    travel = x[X.TRAVEL]
    # The thermal network (section thermal): explicit Euler on the two rises above ambient; its time
    # constants (minutes) dwarf any usable step, so the scheme is far inside its stability limit.
    rise_w = x[X.RISE_MOTOR]
    rise_g = x[X.RISE_GEAR]
    t_amb = p[P.T_AMB]
    heat_w = dt / p[P.C_W] if temperature else 0.0
    heat_g = dt / p[P.C_G] if temperature else 0.0
    g_wg = 1.0 / p[P.R_WG] if temperature else 0.0
    g_wa = 1.0 / p[P.R_WA] if temperature else 0.0
    g_ga = 1.0 / p[P.R_GA] if temperature else 0.0
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
        if mode == Mode.VOLTAGE:
            i_a = (value - p[P.K_B] * omega_m) / p[P.R_ARM]
            torque_m = p[P.K_M] * i_a
        elif mode == Mode.CURRENT:
            i_a = value
            torque_m = p[P.K_M] * i_a
        else:
            torque_m = value
            i_a = value / p[P.K_M]

        theta_err = 0.0
        omega_err = 0.0
        if kinematic:
            phase = p[P.KE_K] * theta_m + p[P.KE_PHI]
            theta_err = p[P.KE_A] * math.sin(phase)
            if needs_deflection_rate:
                omega_err = p[P.KE_A] * p[P.KE_K] * math.cos(phase) * omega_m

        if rigid:
            t_s = t_s_prev
        else:
            deflection = r * theta_m + theta_err - theta_l
            deflection_rate = r * omega_m + omega_err - omega_l
            t_s = _spring(p, nonlinear, deflection) + p[P.D_S] * deflection_rate + z_h
            if hysteresis and deflection_rate != 0.0:
                rate = abs(deflection_rate) / p[P.HYS_DELTA]
                z_ss = p[P.HYS_T] * _sign(deflection_rate)
                z_h = z_ss + (z_h - z_ss) * math.exp(-rate * dt)

        # Smooth (bristle) friction first; the Karnopp part then sees it as a known torque.
        f_smooth_m = 0.0
        if motor_smooth:
            z_new = _bristle(z_m, omega_m, p[P.F_CM], p[P.F_SM], p[P.OMEGA_SM], p[P.SIGMA0_M], dt)
            f_smooth_m = p[P.SIGMA0_M] * z_new + p[P.SIGMA1_M] * (z_new - z_m) / dt + p[P.B_M] * omega_m
            z_m = z_new
        f_smooth_l = 0.0
        omega_l_now = r * omega_m + omega_err if rigid else omega_l
        if load_smooth:
            z_new = _bristle(z_l, omega_l_now, p[P.F_CL], p[P.F_SL], p[P.OMEGA_SL], p[P.SIGMA0_L], dt)
            f_smooth_l = p[P.SIGMA0_L] * z_new + p[P.SIGMA1_L] * (z_new - z_l) / dt + b_load * omega_l_now
            z_l = z_new

        speed_m = abs(omega_m)
        moving_m, static_m = motor_levels(p, s, theta_m, speed_m, t_s, time_s, travel)
        asym_m = p[P.DIR_F]
        viscous_m = 0.0 if motor_smooth else p[P.B_M]
        if temperature:
            # The grease's viscosity law: the whole Karnopp motor friction scales with the gear's temperature.
            scale = math.exp(-p[P.BETA_T] * (rise_g + t_amb - p[P.T_REF]))
            moving_m *= scale
            static_m *= scale
            asym_m *= scale
            viscous_m *= scale
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
                p[P.OMEGA_STICK_M],
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
            if motor_law == Law.NONE or motor_smooth:
                new_omega = omega_m + dt * psi_m / j_m
                f_m = f_smooth_m
            else:
                new_omega, f_k = _karnopp(
                    omega_m, psi_m, moving_m, static_m, asym_m, viscous_m, j_m, dt, p[P.OMEGA_STICK_M]
                )
                f_m = f_smooth_m + f_k
            psi_l = t_s - load_torque - f_smooth_l
            if load_law == Law.NONE or load_smooth:
                new_omega_l = omega_l + dt * psi_l / j_l
                f_l = f_smooth_l
            else:
                new_omega_l, f_k = _karnopp(
                    omega_l, psi_l, moving_l, static_l, 0.0, viscous_l, j_l, dt, p[P.OMEGA_STICK_L]
                )
                f_l = f_smooth_l + f_k

        if until_row == 0:
            until_row = decim
            out[rows, OUT.T] = time_s
            out[rows, OUT.DRIVE] = value
            out[rows, OUT.TAU_EXT] = load_torque
            out[rows, OUT.THETA_M] = theta_m
            out[rows, OUT.OMEGA_M] = omega_m
            out[rows, OUT.THETA_L] = r * theta_m + theta_err if rigid else theta_l
            out[rows, OUT.OMEGA_L] = omega_l_now
            out[rows, OUT.I_A] = i_a
            out[rows, OUT.TAU_M] = torque_m
            out[rows, OUT.F_M] = f_m
            out[rows, OUT.F_L] = f_l
            out[rows, OUT.T_S] = t_s
            out[rows, OUT.TEMP_MOTOR] = t_amb + rise_w if temperature else math.nan
            out[rows, OUT.TEMP_GEAR] = t_amb + rise_g if temperature else math.nan
            rows += 1
        until_row -= 1

        if temperature:
            # Friction power at the step's mean speed (the friction is held over the step); copper loss
            # at the step's current.
            power_f = max(f_m * 0.5 * (omega_m + new_omega), 0.0)
            power_f += max(f_l * 0.5 * (omega_l_now + new_omega_l), 0.0)
            flow_wg = (rise_w - rise_g) * g_wg
            rise_w += heat_w * (i_a * i_a * p[P.R_ARM] - flow_wg - rise_w * g_wa)
            rise_g += heat_g * (power_f + flow_wg - rise_g * g_ga)

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
            theta_l += p[P.KE_A] * math.sin(p[P.KE_K] * theta_m + p[P.KE_PHI])
    x[X.THETA_M] = theta_m
    x[X.OMEGA_M] = omega_m
    x[X.THETA_L] = theta_l
    x[X.OMEGA_L] = omega_l
    x[X.Z_M] = z_m
    x[X.Z_L] = z_l
    x[X.Z_H] = z_h
    x[X.TIME] = time_s
    x[X.TS] = t_s_prev
    x[X.TRAVEL] = travel
    x[X.RISE_MOTOR] = rise_w
    x[X.RISE_GEAR] = rise_g
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
    law = s[FL.MOTOR_LAW.value]
    for i in range(n):
        w = omega_m[i]
        direction = _sign(w)
        if law in (Law.LUGRE, Law.DAHL):
            g = p[P.F_CM]
            if law == Law.LUGRE:
                x = w / p[P.OMEGA_SM]
                g = p[P.F_CM] + (p[P.F_SM] - p[P.F_CM]) * math.exp(-x * x)
            out[i] = direction * g + p[P.B_M] * w
            continue
        moving, _ = motor_levels(p, s, theta_m[i], abs(w), t_s, time_s)
        out[i] = direction * max(moving + p[P.DIR_F] * direction, 0.0) + p[P.B_M] * w
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
        out[i] = max(static + p[P.DIR_F] * direction, 0.0)
    return out


@njit(cache=True, nogil=True)
def replay_windows(
    p: np.ndarray,
    flags: np.ndarray,
    mode: int,
    starts: np.ndarray,
    drive: np.ndarray,
    tau_ext: np.ndarray,
    windows: np.ndarray,
    seg_steps: np.ndarray,
    seg_decim: np.ndarray,
    seg_dt: np.ndarray,
    measured: np.ndarray,
    scales: np.ndarray,
    outputs: np.ndarray,
    residual: np.ndarray,
    work: np.ndarray,
) -> None:
    """Replay shooting windows, each from its own start state, and write (replayed − measured)/scale of
    each window's channels, channel after channel, into `residual` (the trajectory fit's inner loop,
    `rig.analysis.fit.trajectory`). Without the GIL: callers may replay disjoint windows on threads.

    Row w of `windows`: [first input step, first segment, segment stop, first measured row, rows, first
    residual element]; `starts[w]` the state it starts from. A window's segments run one after another
    (`seg_steps` steps of `seg_dt`, a row every `seg_decim` steps); where the step changes, the speeds move
    from half the old step behind the positions to half the new one, at the old step's last acceleration,
    a stuck or stopping body staying at zero. The last segment's final step writes the last sample's row.
    `work`: rows of `OUT` columns, two more than the longest window's.
    """
    n_windows = windows.shape[0]
    rows_out, last = work[:-1], work[-1:]  # a step change's last step is written apart, then copied
    x = np.empty(starts.shape[1])
    for w in range(n_windows):
        x[:] = starts[w]
        first, rows = windows[w, 0], 0
        last_segment = windows[w, 2] - 1
        for i in range(windows[w, 1], windows[w, 2]):
            stop = first + seg_steps[i]
            dt, decim = seg_dt[i], seg_decim[i]
            if i == last_segment:
                rows += integrate(
                    p, flags, x, mode, drive[first:stop], tau_ext[first:stop], dt, decim, rows_out[rows:]
                )
                break
            rows += integrate(
                p,
                flags,
                x,
                mode,
                drive[first : stop - 1],
                tau_ext[first : stop - 1],
                dt,
                decim,
                rows_out[rows:],
            )
            before_m, before_l = x[X.OMEGA_M], x[X.OMEGA_L]
            integrate(p, flags, x, mode, drive[stop - 1 : stop], tau_ext[stop - 1 : stop], dt, 1, last)
            if (seg_steps[i] - 1) % decim == 0:  # the last step starts a sample: its row is recorded
                rows_out[rows] = last[0]
                rows += 1
            shift = 0.5 * (dt - seg_dt[i + 1]) / dt
            if before_m != 0.0 and x[X.OMEGA_M] != 0.0:
                x[X.OMEGA_M] += shift * (x[X.OMEGA_M] - before_m)
            if before_l != 0.0 and x[X.OMEGA_L] != 0.0:
                x[X.OMEGA_L] += shift * (x[X.OMEGA_L] - before_l)
            first = stop
        if rows != windows[w, 4]:
            raise ValueError("a window's replay wrote another number of rows than it measured")
        row0, element = windows[w, 3], windows[w, 5]
        for c in range(outputs.shape[0]):
            for j in range(rows):
                residual[element] = (rows_out[j, outputs[c]] - measured[row0 + j, c]) / scales[w, c]
                element += 1
