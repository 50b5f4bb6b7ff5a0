"""Staged identification, motor friction: against position, against velocity, and at breakaway.

Pure functions of runs and the current model, each returning `Solved` (values, standard errors, notes);
`rig.analysis.identification.staged` decides what to believe. The model's own friction
(`Plant.steady_friction`,
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
from model.params import N_FOURIER, HarmonicDriveModel
from model.plant import Plant
from model.registry import FOURIER_NAMES
from model.run import Run
from rig.analysis.fit.parameters import get_values, with_values
from rig.analysis.identification.dynamics_stage import (
    Held,
    Solved,
    SpanMotion,
    SweepPart,
    as_torque,
    carry_held,
    context,
    covariance,
    deflection,
    load_friction_steady,
    nonlinear_fit,
    span_instants,
    span_motion,
    spring_torque,
    window_means,
)
from rig.experiments.position_friction import fourier_basis, quadratic_fourier_fit, steady_samples

MIN_STUCK_S = 0.02
"""Shortest span of an unchanged motor encoder reading that counts as stuck [s]."""
BRACKET_MAX = 0.02
"""A breakaway counts when ψ rose by at most this share of its level in the cycle it broke away."""


def without_position_part(model: HarmonicDriveModel) -> HarmonicDriveModel:
    """The model with C(θ) = P(θ) = 0: its steady friction is what the article law adds to C·(1 + k_v(|ω| −
    v_c)) + P (b_m·ω, a Stribeck bump, direction asymmetry)."""
    zeros = {name: 0.0 for name in ["s1", "s2", "s3", "a0", *FOURIER_NAMES]}
    return with_values(model, zeros)


# --- stage: friction against position ---------------------------------------------------------------------


def momentum(run: Run, model: HarmonicDriveModel) -> np.ndarray:
    """J_m·dω_m/dt + r·J_l·dω_l/dt over each sample's span (`span_instants`): the torque, seen at the
    motor, that speeds up the motor and the load [N·m]. The load's only on a compliant model with θ_l."""
    edges, at = span_instants(run, model)
    mech = model.mechanics
    out = mech.J_m * span_motion(run, "theta_m", edges, at).accel
    if "theta_l" in run and not model.rigid:
        out = out + mech.r * mech.J_l * span_motion(run, "theta_l", edges, at).accel
    return np.asarray(out)


def position_friction(passes: Sequence[Run], model: HarmonicDriveModel) -> Solved:
    """s1, s2, a1..a10, b1..b10 (and s3 as a check) from constant-speed passes both ways.

    At pass speed v every steady sample gives the friction magnitude
    sgn(ω)·(K_m·i_a − J_m·dω_m/dt − r·J_l·dω_l/dt) − sgn(ω)·E(θ, ω) − r·|F_l(r·v)| = C(θ)·f + P(θ),
    f = 1 + k_v·(v − v_c), E the rest of the model's moving friction. The experiment's quadratic +
    Fourier least squares gives C·f and P; C's coefficients are divided by f. a0 is held (a constant,
    like s3). The momentum terms matter: the velocity loop lets each friction harmonic ripple the speed
    a little, and without them the torque that ripple takes came out in a_n, b_n and moved the velocity
    stage's k_v (figures: docs/BENCHMARKS.md, "Figures behind design choices in the code").
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
        drive = ctx.torque_constant_nm_per_a * run["i_a"] - momentum(run, model)
        theta, direction, torque = steady_samples(
            as_torque(run, ctx, drive), ctx, float(run.meta["params"]["settle_s"])
        )
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
    cov = covariance(design, magnitude - fitted, serial=True)
    se = np.sqrt(np.diag(cov))
    out.metrics["span_rad"] = float(np.ptp(theta))
    for index, name in enumerate(("s1", "s2", "s3")):
        out.put(name, quad[index] / factor, se[index] / factor)
    # s1 and s2 are estimated together (correlated): the velocity stage carries their errors (`Held`).
    out.joint = Held(["s1", "s2"], quad[:2] / factor, cov[:2, :2] / factor**2)
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
FRICTION_INSTANTS = 4
"""Instants per sample span at which the velocity stage evaluates the motor friction (at least)."""


def held_over_spans(command: np.ndarray) -> np.ndarray:
    """A command a drive holds from each sample to the next, averaged over each sample's span
    (`span_instants`: half-way to its neighbours): half of the cycle before it, half of its own."""
    return np.asarray(0.5 * (np.concatenate([command[:1], command[:-1]]) + command))


def velocity_friction(
    parts: Sequence[SweepPart], model: HarmonicDriveModel, held: Held | None = None
) -> Solved:
    """The motor law's velocity parameters (article: s3, k_v) from the steady windows of the sweeps.

    Per window, over the stretch of time inside its samples' spans (`span_instants`, edges ramped over
    TAPER_S): mean K_m·i_a = mean F_m(θ_m, ω_m) + r·mean F_l(ω_l) + r·τ_ext + (J_m·Δω_m + r·J_l·Δω_l)/T,
    F_m the model's moving friction at every instant (s1, s2, a, b held). The last term is the window's
    change of momentum, taken over the same stretch as the torques: fast windows ring, and the sampled
    speeds at a window's ends (the momentum taken before) put s3 low, which the load stage's f_cl
    error had hidden. The windows weigh alike: what is left at the truth is the current noise's.

    `held`: the position stage's s1 and s2 with their covariance, carried into the standard errors
    (`carry_held`). The windows at each speed see their own stretch of θ_m, so an error of C(θ)'s
    curvature reads as a change with speed, a large share of k_v's spread over noise seeds that its σ
    had not carried (docs/BENCHMARKS.md).
    """
    out = Solved()
    used = [part for part in parts if np.any(part.steady)]
    if not used:
        out.notes.append("skipped: no steady window in a speed sweep")
        return out
    names = velocity_names(model)
    misfit = WindowTorques(used, model)
    mech = model.mechanics
    nuisance = misfit.nuisance
    start = get_values(model, names)
    fitted = [*names, *nuisance]
    scale = [abs(v) if v else 1e-3 for v in start.values()] + [mech.J_l] * len(nuisance)
    lower = [-np.inf if n in SIGNED else 0.0 for n in names] + [0.0] * len(nuisance)
    x0 = list(start.values()) + [mech.J_l] * len(nuisance)
    scale_nm = WindowTorques.SCALE_NM
    out = nonlinear_fit(
        lambda x: misfit(dict(zip(fitted, x, strict=True))) / scale_nm, fitted, x0, scale, lower=lower
    )
    if held is not None:
        carry_held(out, lambda values: misfit(values) / scale_nm, held)
        out.notes.append(f"standard errors carry the held {', '.join(held.names)}'s covariance")
    for name in nuisance:
        out.metrics[name] = out.values.pop(name)
        out.metrics[name + "_std"] = out.std_errors.pop(name)
    out.notes.append(_windows_note(used, misfit.count))
    left = misfit({**{n: out.values[n] for n in names}, **{n: out.metrics[n] for n in nuisance}})
    direction = np.concatenate([np.sign(p.omega_set[p.steady]) for p, _, _, _ in misfit.fixed])
    if np.any(direction > 0) and np.any(direction < 0):
        # What the fitted law leaves, forward against backward: direction asymmetry, as a metric.
        out.metrics["asymmetry_nm"] = 0.5 * float(np.mean(left[direction > 0]) + np.mean(left[direction < 0]))
    return out


class WindowTorques:
    """Measured minus model motor torque per steady window [N·m], a function of the law's values (and
    J_l's, when the load's angle is seen: `nuisance`)."""

    SCALE_NM = 1e-5  # residuals in 10 µN·m: the unit of the fit's conditioning, not of its result

    def __init__(self, used: list[SweepPart], model: HarmonicDriveModel) -> None:
        self.model = model
        mech = model.mechanics
        # by run: a load-variation run has 4 parts
        self.spans: dict[int, tuple[SpanMotion, SpanMotion | None]] = {}
        self.fixed: list[tuple[SweepPart, np.ndarray, np.ndarray, float]] = []  # a window's measured rows
        for part in used:
            run = part.run
            if id(run) not in self.spans:
                edges, at = span_instants(run, model)
                load_seen = "theta_l" in run and not model.rigid
                self.spans[id(run)] = (
                    span_motion(run, "theta_m", edges, at),
                    span_motion(run, "theta_l", edges, at) if load_seen else None,
                )
            motor, load = self.spans[id(run)]
            drive = held_over_spans(part.ctx.torque_constant_nm_per_a * run["i_a"])
            tau = window_means(part, run["tau_ext"])
            t_s = float(
                np.mean(tau)
            )  # what a load-dependent friction sees: T_s ≈ τ_ext (F_l is small beside it)
            measured = window_means(part, drive - mech.J_m * motor.accel) - mech.r * tau
            load_accel = window_means(part, mech.r * load.accel) if load is not None else np.zeros_like(tau)
            self.fixed.append((part, measured, load_accel, t_s))
        # J_l, fitted with the windows and not reported (as in the stiffness stage): the FRF's is too far
        # off for r·J_l·Δω_l/T of the ringing load, which biased k_v by several σ (docs/BENCHMARKS.md).
        self.nuisance = ["J_l"] if any(load is not None for _, load in self.spans.values()) else []
        self.count = sum(int(np.count_nonzero(p.steady)) for p in used)

    def __call__(self, values: dict[str, float]) -> np.ndarray:
        law = {name: value for name, value in values.items() if name != "J_l"}
        J_l = values.get("J_l", 0.0)
        try:
            trial = with_values(self.model, law)
        except UserInputError:
            return np.full(self.count, 1.0)
        plant = Plant(trial)
        pieces = []
        totals: dict[tuple[int, float], np.ndarray] = {}  # by run and T_s (when the friction depends on it)
        for part, measured, load_accel, t_s in self.fixed:
            key = (id(part.run), abs(t_s) if trial.load_dependent_friction is not None else 0.0)
            if key not in totals:
                totals[key] = self._friction(plant, trial, key)
            pieces.append((measured - J_l * load_accel - window_means(part, totals[key]))[part.steady])
        return np.concatenate(pieces)

    def _friction(self, plant: Plant, trial: HarmonicDriveModel, key: tuple[int, float]) -> np.ndarray:
        """F_m + r·F_l of one run at each sample, averaged over its span's instants (at T_s = key[1])."""
        mech = self.model.mechanics
        motor, load = self.spans[key[0]]
        # F_m is smooth at the instants' scale (its 10th harmonic at 200 rad/s: 2 rad a sample),
        # so every `stride`-th instant, still evenly spread, is enough for it.
        instants = motor.angle.shape[1]
        stride = max(1, instants // FRICTION_INSTANTS)
        pick = slice(stride // 2, None, stride)
        angle, speed = motor.angle[:, pick], motor.speed[:, pick]
        friction = k.steady_motor_friction(
            plant.p, plant.flags, angle.ravel(), speed.ravel(), key[1], 0.0
        ).reshape(angle.shape)
        load_speed = load.speed if load is not None else mech.r * motor.speed
        return np.asarray(
            friction.mean(axis=1) + mech.r * load_friction_steady(trial, load_speed).mean(axis=1)
        )


def _windows_note(used: list[SweepPart], count: int) -> str:
    """The windows' speeds, and those dropped."""
    speeds = sorted({abs(float(w)) for p in used for w in p.omega_set[p.steady]})
    dropped = sorted({abs(float(w)) for p in used for w in p.omega_set[~p.steady]})
    return f"{count} steady windows at {', '.join(f'{s:g}' for s in speeds)} rad/s" + (
        f"; dropped (motor or load running backwards): {', '.join(f'{s:g}' for s in dropped)} rad/s"
        if dropped
        else ""
    )


# --- stage: breakaway -------------------------------------------------------------------------------------


Event = tuple[float, float, float, float]


def breakaway_levels(run: Run, model: HarmonicDriveModel, offset_rad: float) -> list[Event]:
    """(level, bracket width, θ_m, direction) of every breakaway after a stick, where the cycle brackets
    it tightly.

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
            out.append((level - load_static, high - low, float(theta[b - 1]), direction))
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
    if not events:
        out.notes.append("skipped: no tightly bracketed breakaway in the runs")
        return out
    level, width, theta, direction = (np.array(column) for column in zip(*events, strict=True))
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
    # Each level is known only within its bracket (uniform: σ = width/√12), so a few events whose spread
    # happens to be small cannot claim less. On 20 noise seeds (1–6 events each) the spread alone gave
    # RMS z 1.71 (one campaign's four events within 0.17 %, 5σ from the truth); with this floor 0.98.
    scale = np.abs(moving) if name == "static_factor" else np.ones_like(width)
    bracket = math.sqrt(float(np.mean((width / scale) ** 2)) / 12.0)
    spread = float(np.std(ratio, ddof=1)) if ratio.size > 1 else 0.0
    out.put(name, float(np.mean(ratio)), max(spread, bracket) / math.sqrt(ratio.size))
    if ratio.size == 1:
        out.notes.append(
            f"1 breakaway (ψ_m bracketed within {BRACKET_MAX:.0%}): {name} {ratio[0]:.4g}, σ from its"
            " bracket (uniform within it)"
        )
        return out
    out.metrics["spread"] = spread
    out.notes.append(
        f"{ratio.size} breakaways (ψ_m bracketed within {BRACKET_MAX:.0%}); {name} per event"
        f" {ratio.min():.4g}..{ratio.max():.4g}, spread {spread:.2g}, bracket σ {bracket:.2g}"
        f" (the larger, ÷√{ratio.size}, is the standard error)"
    )
    return out
