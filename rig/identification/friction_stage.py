"""Staged identification, motor friction: against position, against velocity, and at breakaway.

Pure functions of runs and the current model, each returning `Solved` (values, standard errors, notes);
`rig.identification.staged` decides what to believe. The model's own friction (`Plant.steady_friction`,
`Plant.breakaway_friction`) is evaluated for every sample, so every law and effect the kernel knows is
fitted with the kernel's equations, not a second copy of them.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

import numpy as np

from model import kernel as k
from model.errors import UserInputError
from model.fit.parameters import get_values, with_values
from model.params import N_FOURIER, HarmonicDriveModel
from model.plant import Plant
from model.run import Run
from rig.experiments.position_friction import fourier_basis, quadratic_fourier_fit, steady_samples
from rig.identification.dynamics_stage import (
    Solved,
    SweepPart,
    context,
    covariance,
    deflection,
    derivative,
    load_friction_steady,
    nonlinear_fit,
    spring_torque,
)

MIN_STUCK_S = 0.02
"""Shortest span of an unchanged motor encoder reading that counts as stuck [s]."""
BRACKET_MAX = 0.02
"""A breakaway counts when ψ rose by at most this share of its level in the cycle it broke away."""

FOURIER_NAMES = [f"a{n}" for n in range(1, N_FOURIER + 1)] + [f"b{n}" for n in range(1, N_FOURIER + 1)]


def without_position_part(model: HarmonicDriveModel) -> HarmonicDriveModel:
    """The model with C(θ) = P(θ) = 0: its steady friction is what the article law adds to C·(1 + k_v(|ω| −
    v_c)) + P (b_m·ω, a Stribeck bump, direction asymmetry)."""
    zeros = {name: 0.0 for name in ["s1", "s2", "s3", "a0", *FOURIER_NAMES]}
    return with_values(model, zeros)


# --- stage: friction against position ---------------------------------------------------------------------


def position_friction(passes: Sequence[Run], model: HarmonicDriveModel) -> Solved:
    """s1, s2, a1..a10, b1..b10 (and s3 as a check) from constant-speed passes both ways.

    At pass speed v every steady sample gives the friction magnitude
    sgn(ω)·K_m·i_a − sgn(ω)·E(θ, ω) − r·|F_l(r·v)| = C(θ)·f + P(θ),  f = 1 + k_v·(v − v_c),
    E the rest of the model's moving friction. The experiment's quadratic + Fourier least squares
    gives C·f and P; C's coefficients are divided by f. a0 is held (a constant, like s3).
    """
    out = Solved()
    mf = model.motor_friction
    if mf.motor_law != "article":
        out.notes.append(f"skipped: motor_law {mf.motor_law!r} has no position dependence")
        return out
    assert mf.k_v is not None and mf.v_c is not None
    thetas, magnitudes, speeds = [], [], []
    other = Plant(without_position_part(model))
    r = model.mechanics.r
    for run in passes:
        ctx = context(run)
        pass_speed = float(run.meta["params"]["speed_rad_s"])
        theta, direction, torque = steady_samples(run, ctx, float(run.meta["params"]["settle_s"]))
        rest = other.steady_friction(theta, direction * pass_speed)
        load = r * abs(float(load_friction_steady(model, np.array([r * pass_speed]))[0]))
        thetas.append(theta)
        magnitudes.append(direction * (torque - rest) - load - 0.5 * mf.fourier_a()[0])
        speeds.append(np.full(theta.shape, pass_speed))
    if not thetas:
        out.notes.append("skipped: no position-friction run")
        return out
    theta, magnitude, speed = np.concatenate(thetas), np.concatenate(magnitudes), np.concatenate(speeds)
    factor = 1.0 + mf.k_v * (float(np.mean(speed)) - mf.v_c)
    quad, a, b = quadratic_fourier_fit(theta, magnitude, N_FOURIER)
    fitted = np.polyval(quad, theta) + fourier_basis(theta, N_FOURIER) @ np.column_stack([a, b]).ravel()
    design = np.column_stack([theta**2, theta, np.ones_like(theta), fourier_basis(theta, N_FOURIER)])
    se = np.sqrt(np.diag(covariance(design, magnitude - fitted, serial=True)))
    out.metrics["span_rad"] = float(np.ptp(theta))
    for index, name in enumerate(("s1", "s2", "s3")):
        out.put(name, quad[index] / factor, se[index] / factor)
    for n in range(N_FOURIER):
        out.put(f"a{n + 1}", a[n], se[3 + 2 * n])
        out.put(f"b{n + 1}", b[n], se[4 + 2 * n])
    out.notes.append(
        f"quadratic + {N_FOURIER} harmonics over {theta.size} steady samples,"
        f" θ_m {theta.min():.3g}..{theta.max():.3g} rad; speed factor 1 + k_v·(v − v_c) = {factor:.6f}"
    )
    return out


# --- stage: friction against velocity ---------------------------------------------------------------------


def velocity_names(model: HarmonicDriveModel) -> list[str]:
    """What the steady-speed windows fit, per motor law and effect."""
    law = model.motor_friction.motor_law
    names = {
        "article": ["s3", "k_v"],
        "coulomb_viscous": ["f_cm", "b_m"],
        "stribeck": ["f_cm", "f_sm", "omega_sm", "b_m"],
        "lugre": ["f_cm", "f_sm", "omega_sm", "b_m"],
        "dahl": ["f_cm", "b_m"],
    }[law]
    if model.stribeck is not None:
        names += ["f_st", "omega_st"]
    if model.direction_asymmetry is not None:
        names.append("f_dir")
    if model.load_dependent_friction is not None:
        names.append("c_Ts")
    return names


SIGNED = {"s1", "s2", "k_v", "f_dir"}


def velocity_friction(parts: Sequence[SweepPart], model: HarmonicDriveModel) -> Solved:
    """The motor law's velocity parameters (article: s3, k_v) from the steady windows of the sweeps.

    Per window: mean K_m·i_a = mean F_m(θ_m, ω_set) + r·F_l(r·ω_set) + r·τ_ext + J_m·mean(dω_m/dt)
    + r·J_l·mean(dω_l/dt), F_m the model's moving friction at every sample (s1, s2, a, b held). The last
    two terms are the window's change of momentum: without them fast windows, where the transmission
    rings, look like friction. What the sampled speed cannot say of the momentum at a window's ends
    weighs each window: σ = (J_m + r²·J_l)·std(ω_m)/T_window + 10 µN·m.
    """
    out = Solved()
    used = [part for part in parts if np.any(part.steady)]
    if not used:
        out.notes.append("skipped: no steady window in a speed sweep")
        return out
    names = velocity_names(model)
    mech = model.mechanics
    fixed = []
    for part in used:
        run = part.run
        inertial = mech.J_m * derivative(run, "omega_m")
        if "omega_l" in run and not model.rigid:
            inertial = inertial + mech.r * mech.J_l * derivative(run, "omega_l")
        tau = part.mean(run["tau_ext"])
        known = part.mean(inertial) + mech.r * tau
        t_s = float(np.mean(tau))  # what a load-dependent friction sees: T_s ≈ τ_ext (F_l is small beside it)
        spread = np.sqrt(np.maximum(part.mean(run["omega_m"] ** 2) - part.mean(run["omega_m"]) ** 2, 0.0))
        window_s = np.sqrt(12.0 * (part.mean(run.t**2) - part.mean(run.t) ** 2))  # uniform samples
        sigma = (mech.J_m + mech.r**2 * mech.J_l) * spread / window_s + 1e-5
        fixed.append((part, part.torque - known, t_s, sigma))
    count = sum(int(np.count_nonzero(p.steady)) for p in used)

    def misfit(x: np.ndarray) -> np.ndarray:
        """Measured minus model torque per steady window [N·m]."""
        try:
            trial = with_values(model, dict(zip(names, x, strict=True)))
        except UserInputError:
            return np.full(count, 1.0)
        plant = Plant(trial)
        pieces = []
        for part, measured, t_s, _ in fixed:
            theta = np.ascontiguousarray(part.run["theta_m"])
            omega = np.ascontiguousarray(part.run["setpoint"], dtype=np.float64)
            load = mech.r * load_friction_steady(trial, mech.r * part.omega_set)
            friction = k.steady_motor_friction(plant.p, plant.flags, theta, omega, abs(t_s), 0.0)
            pieces.append((measured - part.mean(friction) - load)[part.steady])
        return np.concatenate(pieces)

    sigma = np.concatenate([s[p.steady] for p, _, _, s in fixed])

    start = get_values(model, names)
    scale = [abs(v) if v else 1e-3 for v in start.values()]
    lower = [-np.inf if n in SIGNED else 0.0 for n in names]
    out = nonlinear_fit(lambda x: misfit(x) / sigma, names, list(start.values()), scale, lower=lower)
    speeds = sorted({abs(float(w)) for p in used for w in p.omega_set[p.steady]})
    dropped = sorted({abs(float(w)) for p in used for w in p.omega_set[~p.steady]})
    out.notes.append(
        f"{count} steady windows at {', '.join(f'{s:g}' for s in speeds)} rad/s"
        + (
            f"; dropped (motor or load running backwards): {', '.join(f'{s:g}' for s in dropped)} rad/s"
            if dropped
            else ""
        )
    )
    left = misfit(np.array([out.values[n] for n in names]))
    direction = np.concatenate([np.sign(p.omega_set[p.steady]) for p, _, _, _ in fixed])
    if np.any(direction > 0) and np.any(direction < 0):
        # What the fitted law leaves, forward against backward: direction asymmetry, as a metric.
        out.metrics["asymmetry_nm"] = 0.5 * float(np.mean(left[direction > 0]) + np.mean(left[direction < 0]))
    return out


# --- stage: breakaway -------------------------------------------------------------------------------------


Event = tuple[float, float, float]


def breakaway_levels(run: Run, model: HarmonicDriveModel, offset_rad: float) -> list[Event]:
    """(level, θ_m, direction) of every breakaway after a stick, where the cycle brackets it tightly.

    Stuck, the motor's encoder reads one value; the drive holds the current over a cycle, so the motor
    breaks away in the cycle whose ψ_m = K_m·i_a − r·T_s first exceeds f_sm, and the reading changes at
    the next sample b: f_sm lies between ψ_m(b−2) and ψ_m(b−1). T_s is the spring's torque from the
    measured deflection. A rigid axis breaks away as one body, load and all: ψ = K_m·i_a − r·τ_ext, and
    the load's static friction r·f_sl (held) is taken off the level.
    """
    ctx = context(run)
    theta = run["theta_m"]
    r = model.mechanics.r
    load_static = 0.0
    if model.rigid or "theta_l" not in run:
        transmitted = run["tau_ext"]
        lf = model.load_friction
        load_static = r * (lf.f_sl or 0.0) if model.rigid and lf is not None else 0.0
    else:
        transmitted = spring_torque(model, deflection(run, model, offset_rad))
    psi = ctx.torque_constant_nm_per_a * run["i_a"] - r * transmitted
    moved = np.flatnonzero(np.diff(theta) != 0) + 1  # first sample of each new reading
    min_cycles = ctx.cycles(MIN_STUCK_S)
    out = []
    for previous, b in itertools.pairwise(moved):
        if b - previous < min_cycles or b < 2:
            continue
        direction = math.copysign(1.0, theta[b] - theta[b - 1])
        low, high = direction * psi[b - 2], direction * psi[b - 1]
        level = 0.5 * (low + high)
        if level > 0 and 0 <= high - low <= BRACKET_MAX * level:
            out.append((level - load_static, float(theta[b - 1]), direction))
    return out


def breakaway(runs: Sequence[Run], model: HarmonicDriveModel, offset_rad: float) -> Solved:
    """static_factor (article law) or f_sm (baseline laws) from the motor's breakaways after sticking.

    static_factor = f_sm / [C(θ)·(1 − k_v·v_c) + P(θ)] per event (the moving magnitude at zero speed,
    the model's breakaway level with a factor of 1), averaged; its standard error from the spread.
    """
    out = Solved()
    events = [e for run in runs if "i_a" in run for e in breakaway_levels(run, model, offset_rad)]
    law = model.motor_friction.motor_law
    if law not in ("article", "coulomb_viscous", "stribeck"):
        out.notes.append(f"skipped: motor_law {law!r} breaks away by its bristles, not at a level")
        return out
    if len(events) < 2:
        out.notes.append(f"skipped: {len(events)} tightly bracketed breakaway(s) in the runs")
        return out
    level, theta, direction = (np.array(column) for column in zip(*events, strict=True))
    name = "static_factor" if law == "article" else "f_sm"

    def static_levels(trial: HarmonicDriveModel) -> np.ndarray:
        plant = Plant(trial)
        return np.array([plant.breakaway_friction(t, d)[0] for t, d in zip(theta, direction, strict=True)])

    if name == "static_factor":
        # f_s = factor·M(θ) + E: the level at factors 1 and 2 gives M and the rest E (f_st, f_dir).
        once = static_levels(with_values(model, {"static_factor": 1.0}))
        moving = static_levels(with_values(model, {"static_factor": 2.0})) - once
        extra = once - moving
        ratio = (level - extra) / moving
    else:
        extra = static_levels(model) - float(get_values(model, ["f_sm"])["f_sm"])
        ratio = level - extra
    if np.any(np.abs(extra) > 1e-12):
        out.notes.append(
            f"the breakaway measures the whole static level; the model's other static terms"
            f" (mean {np.mean(extra):.3g} N·m: Stribeck, asymmetry) are held"
        )
    out.put(name, float(np.mean(ratio)), float(np.std(ratio, ddof=1) / math.sqrt(ratio.size)))
    out.metrics["spread"] = float(np.std(ratio, ddof=1))
    out.notes.append(
        f"{ratio.size} breakaways (ψ_m bracketed within {BRACKET_MAX:.0%}); {name} per event"
        f" {ratio.min():.4g}..{ratio.max():.4g}, spread {np.std(ratio, ddof=1):.2g}"
    )
    return out
