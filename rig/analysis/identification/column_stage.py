"""Runs without experiment metadata: what their columns determine, and a starting point for them.

A lab's file has no segment table, no experiment name, no rig constants: no stage of `staged` can
read it. Its columns still say a lot:

- the input (`u`, `i_cmd` or `tau_m`) says what drives the motor; with `u` and `i_a` together, the
  motor stage's equation u = R·i_a + K_b·ω_m holds at every sample and gives R and K_b directly;
- `theta_l` says whether the load side is seen: without it a flexible model's J_l, K_s and load
  friction do not show in θ_m well enough to be told apart from the motor side's, and are held;
- the motor torque, known from the input (K_m·i, or τ_m), against the filtered motion gives the plain
  inverse-model least squares (`rig.analysis.fit.inverse`): the axis' inertia and its Coulomb and viscous
  friction, a starting point near the truth for an axis the start model knows nothing about.

The trajectory least squares then refines the parameters `free_parameters` lists on shooting windows.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.signal import filtfilt

from model.errors import UserInputError
from model.params import HarmonicDriveModel
from model.run import Run
from rig.analysis.fit.inverse import MIN_SPEED_SHARE, InverseFit, filtered_derivatives, inverse_model_fit
from rig.analysis.fit.parameters import get_values, with_values
from rig.analysis.identification.dynamics_stage import back_emf_fit

LAW_FRICTION = {
    "article": ["s3", "k_v", "static_factor"],
    "coulomb_viscous": ["f_cm", "b_m", "f_sm"],
    "stribeck": ["f_cm", "f_sm", "omega_sm", "b_m"],
    "lugre": ["f_cm", "b_m"],
    "dahl": ["f_cm", "b_m"],
}
"""Motor friction parameters a trajectory fit can move, per law: the level, its speed slope and the
breakaway. Position-dependent terms (s1, s2, a_n, b_n) need the position-friction passes' coverage."""


@dataclass
class ColumnPlan:
    """What the plain runs determine: free parameters for the trajectory fit, held ones with reasons."""

    free: list[str]
    held: dict[str, str]
    start: HarmonicDriveModel  # the start model, with any closed-form estimates (R, K_b) put in
    estimates: dict[str, tuple[float, float]] = field(default_factory=dict)  # closed-form value, 1σ
    inverse: InverseFit | None = None
    notes: list[str] = field(default_factory=list)
    two_sided: dict[str, tuple[float, float]] | None = None  # `two_sided_start`, for the free parameters


def motor_torque(run: Run, model: HarmonicDriveModel) -> np.ndarray | None:
    """T_m from the columns: τ_m, K_m·i_cmd, K_m·i_a; None from a voltage alone (it needs R, K_b)."""
    column = run.input_column
    if column == "tau_m":
        return run["tau_m"]
    if column == "i_cmd":
        return model.motor.K_m * run["i_cmd"]
    if "i_a" in run:
        return model.motor.K_m * run["i_a"]
    return None


def _load_seen(runs: list[Run]) -> bool:
    return all("theta_l" in run for run in runs)


def free_parameters(runs: list[Run], model: HarmonicDriveModel) -> tuple[list[str], dict[str, str]]:
    """The parameters the columns of `runs` let a trajectory fit move, and why each other one is held."""
    held: dict[str, str] = {
        "K_m": "the motor's torque constant scales every torque the data show: given (the start model's)",
        "r": "the gear ratio is structural: given (the start model's)",
    }
    free = ["J_m"]
    columns = {run.input_column for run in runs}
    if "u" in columns and not all("i_a" in run for run in runs if run.input_column == "u"):
        free += ["R", "K_b"]  # only the trajectories can tell them; the covariance says whether they do
    elif "u" not in columns:
        for name in ("R", "K_b"):
            held[name] = f"the input is {'/'.join(sorted(c for c in columns if c))}, not a voltage: not seen"
    law = model.motor_friction.motor_law
    free += LAW_FRICTION[law]
    if law == "article":
        held["v_c"] = "absorbed by s3 and k_v (C·(1 + k_v(|ω| − v_c))): held"
        held["b_m"] = "grows ∝ ω like C·k_v: held (MODEL.md note 3)"
        for name in ("s1", "s2"):
            held[name] = "the slow level over the stroke needs the position-friction passes: held"
    if model.rigid:
        held["J_l"] = "a rigid axis shows J_m + r²·J_l only: J_m carries the sum"
        if model.load_friction is not None:
            held["f_cl"] = "a rigid axis' load friction adds r·F_l to the motor's: inseparable, held"
    elif not _load_seen(runs):
        why = "no theta_l column: the load side is not seen apart from the motor's; held"
        for name in ("J_l", "K_s", "D_s", "f_cl", "b_l"):
            held[name] = why
    else:
        free += ["J_l", "K_s"]
        if model.load_friction is not None and model.load_friction.load_law == "coulomb_viscous":
            free += ["f_cl", "b_l"]
    if model.kinematic_error is not None:
        held["A"] = "the motion error needs the position-friction passes' slow constant speed: held"
    present = get_values_or_none(model, free)
    free = [n for n in free if n in present and n not in held]
    return free, held


def get_values_or_none(model: HarmonicDriveModel, names: list[str]) -> dict[str, float]:
    out = {}
    for name in names:
        try:
            out[name] = get_values(model, [name])[name]
        except UserInputError:
            continue
    return out


def _motor_constants(runs: list[Run]) -> tuple[dict[str, tuple[float, float]], str] | None:
    """R, K_b by the motor stage's u = R·i_a + K_b·ω_m (`back_emf_fit`) over every sample of the voltage
    runs that also log i_a."""
    pieces = [
        (r["u"], r["i_a"], r["theta_m"], float(np.median(np.diff(r.t))), np.ones(len(r), bool))
        for r in runs
        if r.input_column == "u" and "i_a" in r and len(r) >= 5
    ]
    if not pieces:
        return None
    solved = back_emf_fit(pieces)
    if not ("R" in solved.values and solved.values["R"] > 0 and solved.values["K_b"] > 0):
        return None
    values = {n: (solved.values[n], solved.std_errors[n]) for n in ("R", "K_b")}
    return values, f"{solved.notes[-1]} of {len(pieces)} run(s)"


def inverse_start(runs: list[Run], model: HarmonicDriveModel) -> InverseFit | None:
    """The plain inverse-model least squares on the motor axis of the runs whose torque is known."""
    t, theta, torque = [], [], []
    offset_s = 0.0
    for run in runs:
        motor = motor_torque(run, model)
        if motor is None:
            continue
        net = motor - model.mechanics.r * run["tau_ext"] if "tau_ext" in run else motor
        # Runs laid end to end with a gap of a second: the filter's transients stay within each.
        t.append(run.t - run.t[0] + offset_s)
        theta.append(run["theta_m"])
        torque.append(net)
        offset_s = t[-1][-1] + 1.0
    if not t:
        return None
    try:
        fits = [inverse_model_fit(ti, th, tq) for ti, th, tq in zip(t, theta, torque, strict=True)]
    except UserInputError:
        return None
    if len(fits) == 1:
        return fits[0]
    weights = np.array([f.samples for f in fits], float)
    mean = {
        k: float(np.average([getattr(f, k) for f in fits], weights=weights))
        for k in ("mass", "viscous", "coulomb", "offset")
    }
    return InverseFit(
        mean["mass"],
        mean["viscous"],
        mean["coulomb"],
        mean["offset"],
        {k: min(f.std_errors[k] for f in fits) for k in fits[0].std_errors},
        int(weights.sum()),
        fits[0].cutoff_hz,
    )


def seeded_model(model: HarmonicDriveModel, fit: InverseFit) -> HarmonicDriveModel | None:
    """The model with its inertia and motor friction set from an inverse-model fit (None if the fit is
    not physical: a negative mass or friction)."""
    if not (fit.mass > 0 and fit.coulomb > 0 and fit.viscous >= 0):
        return None
    r = model.mechanics.r
    load = model.load_friction
    load_coulomb = r * (load.f_cl or 0.0) if load is not None and model.rigid else 0.0
    coulomb = fit.coulomb - load_coulomb
    if coulomb <= 0:
        return None
    values: dict[str, float] = {}
    if model.rigid:
        j_l = model.mechanics.J_l
        values["J_m"] = max(fit.mass - r * r * j_l, 0.5 * fit.mass)
        if values["J_m"] + r * r * j_l != fit.mass:
            values["J_l"] = (fit.mass - values["J_m"]) / (r * r)
    else:
        values["J_m"] = max(fit.mass - r * r * model.mechanics.J_l, 0.1 * fit.mass)
    law = model.motor_friction.motor_law
    mf = model.motor_friction
    if law == "article":
        v_c = mf.v_c or 0.0
        s3 = coulomb + fit.viscous * v_c  # s3·(1 − k_v·v_c) = F_c and s3·k_v = F_v
        values |= {"s3": s3, "k_v": fit.viscous / s3}
    else:
        values |= {"f_cm": coulomb, "b_m": fit.viscous}
        if law in ("coulomb_viscous", "stribeck") and mf.f_sm is not None and mf.f_cm:
            values["f_sm"] = coulomb * max(mf.f_sm / mf.f_cm, 1.0)
    try:
        return with_values(model, values, "inverse-model start")
    except UserInputError:
        return None


SIDES_CUTOFF_HZ = 50.0
"""Low-pass corner of `two_sided_start`: above a flexible joint's first modes (the seed's ~13 Hz, with
room for stiffer and lighter gears), below where a 14-bit encoder's second difference swamps the motor's
acceleration (about 1e-3 N·m of noise per sample on the seed's J_m, against 0.07 N·m of friction)."""


def _least_squares(design: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Coefficients of target ≈ design·β and their white-residual standard errors."""
    beta, *_ = np.linalg.lstsq(design, target, rcond=None)
    residual = target - design @ beta
    dof = max(len(target) - design.shape[1], 1)
    cov = np.linalg.pinv(design.T @ design) * float(residual @ residual) / dof
    return beta, np.sqrt(np.clip(np.diag(cov), 0.0, None))


def two_sided_start(run: Run, model: HarmonicDriveModel) -> dict[str, tuple[float, float]] | None:
    """A flexible joint's parameters from the two equations of motion by linear least squares (issue
    25 item 1: a global start, not the seed's corner), on zero-phase filtered derivatives:

    - the load: τ_ext = K_s·δ − J_l·α_l − f_cl·sgn ω_l − b_l·ω_l, δ = r·θ_m + e(θ_m) − θ_l (e the start
      model's kinematic error): K_s, J_l, f_cl, b_l, their scale set by the load's own torque;
    - the motor: T_m − r·K_s·δ = J_m·α_m + F_c·sgn ω_m + F_v·ω_m + offset, T_m from the input or i_a;
      the article law's s3 = F_c + F_v·v_c and k_v = F_v/s3 (its level at v_c and slope).

    Each side keeps the samples moving faster than 5 % of its top speed (the sign is known there).
    None without θ_l, τ_ext or a known motor torque, or when a value comes out unphysical."""
    torque = motor_torque(run, model)
    if torque is None or "theta_l" not in run or "tau_ext" not in run or len(run) < 200:
        return None
    t, r = run.t, model.mechanics.r
    ke = model.kinematic_error
    error = 0.0 if ke is None else ke.A * np.sin(ke.k * run["theta_m"] + ke.phi)
    try:
        w_m, a_m, (b, a) = filtered_derivatives(t, run["theta_m"], SIDES_CUTOFF_HZ)
        w_l, a_l, _ = filtered_derivatives(t, run["theta_l"], SIDES_CUTOFF_HZ)
    except UserInputError:
        return None
    twist = filtfilt(b, a, r * run["theta_m"] + error - run["theta_l"])
    load = filtfilt(b, a, run["tau_ext"])
    edge = max(1, len(t) // 50)
    inner = np.zeros(len(t), bool)
    inner[edge:-edge] = True
    on_l = inner & (np.abs(w_l) > MIN_SPEED_SHARE * np.max(np.abs(w_l[inner])))
    design = np.column_stack([twist, -a_l, -np.sign(w_l), -w_l])[on_l]
    (k_s, j_l, f_cl, b_l), se_l = _least_squares(design, load[on_l])
    on_m = inner & (np.abs(w_m) > MIN_SPEED_SHARE * np.max(np.abs(w_m[inner])))
    net = filtfilt(b, a, torque) - r * k_s * twist
    design = np.column_stack([a_m, np.sign(w_m), w_m, np.ones(len(t))])[on_m]
    (j_m, coulomb, viscous, _), se_m = _least_squares(design, net[on_m])
    values = {"K_s": (k_s, se_l[0]), "J_l": (j_l, se_l[1]), "J_m": (j_m, se_m[0])}
    if model.load_friction is not None and model.load_friction.load_law == "coulomb_viscous":
        values |= {"f_cl": (f_cl, se_l[2]), "b_l": (max(b_l, 0.0), se_l[3])}
    if model.motor_friction.motor_law == "article":
        s3 = coulomb + viscous * (model.motor_friction.v_c or 0.0)
        values |= {"s3": (s3, se_m[1]), "k_v": (viscous / s3 if s3 > 0 else math.nan, math.nan)}
    positive = ("K_s", "J_l", "J_m", "f_cl", "s3")
    if any(not value > 0 for name, (value, _) in values.items() if name in positive):
        return None
    if not all(math.isfinite(value) for value, _ in values.values()):
        return None
    return values


def plan_for_plain_runs(runs: list[Run], model: HarmonicDriveModel) -> ColumnPlan:
    """Free and held parameters, closed-form motor constants and the inverse-model fit for these runs."""
    driven = [run for run in runs if run.input_column is not None]
    if not driven:
        raise UserInputError(
            "fit: no run has an input column (u, i_cmd or tau_m), and none carries experiment metadata"
        )
    free, held = free_parameters(driven, model)
    plan = ColumnPlan(free, held, model)
    constants = _motor_constants(driven)
    if constants is not None:
        values, how = constants
        good = {n: v for n, (v, se) in values.items() if math.isfinite(se) and se < 0.25 * v}
        if good:
            plan.start = with_values(model, good, "motor constants")
            plan.estimates.update({n: values[n] for n in good})
        plan.notes.append(f"motor: {how}")
    plan.inverse = inverse_start(driven, plan.start)
    if len(driven) == 1 and not model.rigid:
        sides = two_sided_start(driven[0], plan.start)
        if sides is not None:
            plan.two_sided = {n: v for n, v in sides.items() if n in free}
            shown = ", ".join(f"{n} = {v:.4g}" for n, (v, _) in plan.two_sided.items())
            plan.notes.append(
                f"two-sided least squares (load and motor equations, {SIDES_CUTOFF_HZ:g} Hz zero-phase"
                f" filter): {shown}"
            )
    if plan.inverse is not None:
        inv = plan.inverse
        plan.notes.append(
            f"inverse model (torque = M·a + F_v·v + F_c·sgn v + offset, {inv.cutoff_hz:g} Hz zero-phase"
            f" filter, {inv.samples} samples): M = {inv.mass:.4g}, F_v = {inv.viscous:.4g},"
            f" F_c = {inv.coulomb:.4g}, offset = {inv.offset:.3g}"
        )
    return plan


def axis_figures(model: HarmonicDriveModel, runs: list[Run]) -> dict[str, float]:
    """The model seen as one axis, in the inverse model's terms: inertia at the motor, and the Coulomb
    level and viscous slope of its steady friction (motor plus load seen through r), over the speeds
    and positions of the runs."""
    from model.plant import Plant

    speeds = np.concatenate([np.abs(np.gradient(r["theta_m"], r.t)) for r in runs])
    top = float(np.percentile(speeds, 95)) if speeds.size else 1.0
    grid = np.linspace(0.2 * top, top, 9)
    theta = np.concatenate([r["theta_m"] for r in runs])
    theta = theta[:: max(1, len(theta) // 200)]
    plant = Plant(model)
    level = np.array([np.mean(plant.steady_friction(theta, np.full(theta.shape, w))) for w in grid])
    slope, coulomb = np.polyfit(grid, level, 1)
    r = model.mechanics.r
    load = model.load_friction
    if load is not None and load.load_law == "coulomb_viscous":
        coulomb += r * (load.f_cl or 0.0)
        slope += r * r * (load.b_l or 0.0)
    return {
        "mass": model.mechanics.J_m + r * r * model.mechanics.J_l,
        "viscous": float(slope),
        "coulomb": float(coulomb),
    }
