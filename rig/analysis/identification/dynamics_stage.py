"""Staged identification, mechanics: motor constants, stiffness and load friction, FRF, kinematic error.

Each stage is a pure function of runs (model.run.Run with their metadata) and the current model, and
returns `Solved`: values with covariance-based standard errors and notes. Which parameters are then
believed, and the bookkeeping of the model, is `rig.analysis.identification.staged`'s business.
This module also
holds the small tools all stages share (least squares with standard errors, a run's context, window
averages).

The steady windows of `speed-sweep` and `load-variation` are the experiments' own: every average over
them is taken by `rig.experiments.speed_sweep.friction_table`, which averages K_m·i_a over each
constant-speed segment past its settle time; fed a column c/K_m in place of i_a, it averages c over the
very same rows (`SweepPart.mean`).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numba import njit
from scipy.interpolate import CubicSpline, make_lsq_spline
from scipy.optimize import least_squares
from scipy.stats import t as student_t

from model import kernel as k
from model.params import N_FOURIER, HarmonicDriveModel
from model.plant import kernel_vectors
from model.registry import FL
from model.run import Run
from rig.analysis.fit.parameters import get_values, with_values
from rig.analysis.fit.trajectory import SPEED_BAND_SIGMAS, position_noise, window_robust_covariance
from rig.config import RigConfig
from rig.experiments.base import RigContext, segments_of
from rig.experiments.chirp import ChirpParams, frf_tables
from rig.experiments.load_variation import load_prefix
from rig.experiments.position_friction import steady_samples
from rig.experiments.pulse import PulseParams
from rig.experiments.speed_sweep import friction_table

REVERSED_SHARE_MAX = 0.05
"""A steady window is dropped when the motor or the load runs against the set speed in more samples."""
COHERENCE_MIN = 0.9
"""FRF lines used by the dynamics fit: coherence γ² above this."""


# --- shared tools -----------------------------------------------------------------------------------------


@dataclass
class Solved:
    """A stage's answer: values and standard errors by parameter name, and what a person should read."""

    values: dict[str, float] = field(default_factory=dict)
    std_errors: dict[str, float] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    metrics: dict[str, float] = field(default_factory=dict)  # figures that are not model parameters
    undetermined: dict[str, str] = field(default_factory=dict)  # parameter: why these data cannot say
    joint: Held | None = None  # values the stage estimated together, with their full covariance

    def put(self, name: str, value: float, std_error: float) -> None:
        self.values[name] = float(value)
        self.std_errors[name] = float(std_error)


@dataclass(frozen=True)
class Held:
    """Parameters a stage holds at another stage's estimates, with their covariance (names' order)."""

    names: list[str]
    values: np.ndarray
    covariance: np.ndarray


def carry_held(solved: Solved, residual: Callable[[dict[str, float]], np.ndarray], held: Held) -> None:
    """Widen `solved`'s standard errors by the errors of the parameters it held (the delta method of a
    two-step estimate): at the solution x̂, dx̂/dh = −(JₓᵀJₓ)⁻¹JₓᵀJₕ from the residual's Jacobians, and
    var x̂ += diag(dx̂/dh · Σₕ · dx̂/dhᵀ). `residual` takes the fitted and held values by name.

    Both Jacobians by central differences over one standard error of each (the residuals are smooth at
    that scale, and it is the scale the answer is about)."""
    fitted = dict(solved.values)
    base = {**fitted, **dict(zip(held.names, held.values, strict=True))}

    def slopes(names: Sequence[str], steps: Sequence[float]) -> np.ndarray:
        columns = []
        for name, step in zip(names, steps, strict=True):
            up, down = dict(base), dict(base)
            up[name] += step
            down[name] -= step
            columns.append((residual(up) - residual(down)) / (2.0 * step))
        return np.column_stack(columns)

    names = list(fitted)
    steps = [
        solved.std_errors[n]
        if math.isfinite(solved.std_errors[n]) and solved.std_errors[n] > 0
        else 1e-6 * (abs(fitted[n]) or 1.0)
        for n in names
    ]
    held_steps = [
        max(math.sqrt(held.covariance[i, i]), 1e-12 * (abs(v) or 1.0)) for i, v in enumerate(held.values)
    ]
    moved = -np.linalg.lstsq(slopes(names, steps), slopes(held.names, held_steps), rcond=None)[0]
    added = np.einsum("ij,jk,ik->i", moved, held.covariance, moved)
    for name, extra in zip(names, added, strict=True):
        solved.std_errors[name] = math.sqrt(solved.std_errors[name] ** 2 + max(float(extra), 0.0))


BATCHES = 20
"""Contiguous batches of a long residual sequence, taken as independent clusters for its covariance."""


def covariance(design: np.ndarray, residual: np.ndarray, serial: bool = False) -> np.ndarray:
    """Covariance of a least-squares fit with design X and residual: s²·(XᵀX)⁻¹, or with `serial` the
    sandwich over BATCHES contiguous batches (`window_robust_covariance`), for residuals whose samples
    are not independent.

    The sandwich sums each batch's score x·e before squaring, so it sees the residual's spectrum where
    the regressors live, both ways: slow ripple a fit leaves widens it, and the drive's current
    chattering about its mean (anticorrelated from sample to sample on the position passes) narrows it.
    The scalar batch-means factor it replaces could only widen: it left s1 and s2 far wider than their
    spread over noise seeds (figures: docs/BENCHMARKS.md).
    """
    norms = np.linalg.norm(design, axis=0)
    norms[norms == 0] = 1.0
    scaled = design / norms
    dof = max(len(residual) - design.shape[1], 1)
    s2 = float(residual @ residual) / dof
    if serial and residual.size >= 2 * BATCHES:
        batches = np.arange(residual.size) * BATCHES // residual.size
        cov = window_robust_covariance(scaled, residual, batches, s2)
    else:
        cov = np.linalg.pinv(scaled.T @ scaled) * s2
    return np.asarray(cov / np.outer(norms, norms))


def linear_fit(design: np.ndarray, y: np.ndarray, serial: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Least squares y ≈ X·β: β and its covariance."""
    norms = np.linalg.norm(design, axis=0)
    norms[norms == 0] = 1.0
    beta = np.linalg.lstsq(design / norms, y, rcond=None)[0] / norms
    return beta, covariance(design, y - design @ beta, serial)


NORMAL_ONE_SIGMA = 0.8413447460685429
"""Φ(1): the share of the normal law below +1σ."""


def one_sigma_t(dof: int) -> float:
    """Student's t at the normal law's 1σ quantile (84.1 %): the factor that makes ±σ from an estimated
    variance with `dof` degrees of freedom cover 68.3 %."""
    return float(student_t.ppf(NORMAL_ONE_SIGMA, dof))


def nonlinear_fit(
    residual: Callable[[np.ndarray], np.ndarray],
    names: Sequence[str],
    x0: Sequence[float],
    scale: Sequence[float],
    lower: Sequence[float] | None = None,
    loss: str = "linear",
    f_scale: float = 1.0,
    unequal_rows: bool = False,
) -> Solved:
    """Least squares (scipy) over parameters in units of `scale`; standard errors from s²·(JᵀJ)⁻¹, or
    with `unequal_rows` (independent rows whose noise differs from row to row) the sandwich with each row
    its own cluster, in its leave-one-out form (`window_robust_covariance`; HC3 in econometrics).

    s² is estimated from the residual with m − n degrees of freedom, so the estimate's error over its
    standard error follows Student's t, not the normal law: with few (4 windows, 3 parameters: t₁) a
    ±1σ interval covers the truth 50 % of the time, not 68 %. The standard errors are widened by
    t_(m−n)(84.1 %) so that it does (×1.84 at one degree of freedom, ×1.02 at 30); with none left
    (m ≤ n) the residual says nothing of the noise, and they are infinite.
    """
    scales = np.asarray(scale, dtype=np.float64)
    low = np.full(len(names), -np.inf) if lower is None else np.asarray(lower) / scales
    start = np.maximum(np.asarray(x0, dtype=np.float64) / scales, low)
    result = least_squares(
        lambda z: residual(z * scales), start, bounds=(low, np.inf), loss=loss, f_scale=f_scale
    )
    m, n = result.jac.shape
    if m <= n:
        se = np.full(n, np.inf)
    else:
        s2 = 2.0 * float(result.cost) / (m - n)
        if unequal_rows and loss == "linear":
            cov = window_robust_covariance(result.jac, result.fun, np.arange(m), s2)
        else:
            cov = np.linalg.pinv(result.jac.T @ result.jac) * s2
        se = np.sqrt(np.clip(np.diag(cov), 0.0, None)) * scales * one_sigma_t(m - n)
    out = Solved()
    for name, value, err in zip(names, result.x * scales, se, strict=True):
        out.put(name, value, err)
    return out


def context(run: Run) -> RigContext:
    """The RigContext an experiment's analysis needs, from a stored run's metadata.

    A stored run knows its rate, gear ratio, torque constant and start; the analyses read nothing else of
    the rig (limits and loop gains only shape programs), so the config carries the rate alone.
    """
    fields: dict[str, Any] = {"sample_rate_hz": float(run.meta["sample_rate_hz"])}
    config = RigConfig.model_construct(**fields)
    return RigContext(
        config,
        float(run.meta["gear_ratio"]),
        float(run.meta["torque_constant_nm_per_a"]),
        float(run.meta.get("theta_m0", 0.0)),
    )


def as_torque(run: Run, ctx: RigContext, column: np.ndarray) -> Run:
    """The run with `column`/K_m as its current: an analysis that averages K_m·i_a then averages `column`."""
    return Run({**run.columns, "i_a": np.asarray(column) / ctx.torque_constant_nm_per_a}, run.meta)


def derivative(run: Run, column: str) -> np.ndarray:
    return np.asarray(np.gradient(run[column], run.t))


def deflection(run: Run, model: HarmonicDriveModel, offset_rad: float = 0.0) -> np.ndarray:
    """r·θ_m + A·sin(k·θ_m + φ) − θ_l − offset: the spring's deflection at the output [rad]."""
    return deflection_of(model, run["theta_m"], run["theta_l"]) - offset_rad


def deflection_of(model: HarmonicDriveModel, theta_m: np.ndarray, theta_l: np.ndarray) -> np.ndarray:
    """r·θ_m + A·sin(k·θ_m + φ) − θ_l at given positions (any shape) [rad]."""
    out = model.mechanics.r * theta_m - theta_l
    if (ke := model.kinematic_error) is not None:
        out = out + ke.A * np.sin(ke.k * theta_m + ke.phi)
    return np.asarray(out)


@njit(cache=True)
def _spring_torques(p: np.ndarray, nonlinear: int, deflections: np.ndarray) -> np.ndarray:
    out = np.empty_like(deflections)
    for i in range(deflections.shape[0]):
        out[i] = k._spring(p, nonlinear, deflections[i])
    return out


def spring_torque(model: HarmonicDriveModel, deflections: np.ndarray) -> np.ndarray:
    """The transmission's spring torque K_s·δ, or the catalog's piecewise law (the kernel's own), for
    deflections of any shape [N·m]."""
    p, flags = kernel_vectors(model)
    flat = np.ascontiguousarray(deflections, dtype=np.float64).reshape(-1)
    return np.asarray(_spring_torques(p, int(flags[FL.NONLINEAR]), flat)).reshape(np.shape(deflections))


@njit(cache=True)
def _load_moving_levels(p: np.ndarray, law: int, speeds: np.ndarray) -> np.ndarray:
    out = np.empty_like(speeds)
    for i in range(speeds.shape[0]):
        out[i] = k.load_levels(p, law, abs(speeds[i]))[0]
    return out


def load_friction_steady(model: HarmonicDriveModel, omega_l: np.ndarray) -> np.ndarray:
    """F_l of a load moving at ω_l ≠ 0 (any shape): sgn(ω_l)·level(|ω_l|) + b_l·ω_l (kernel levels) [N·m]."""
    omega_l = np.asarray(omega_l, dtype=np.float64)
    if model.load_friction is None:
        return np.zeros_like(omega_l)
    p, flags = kernel_vectors(model)
    flat = np.ascontiguousarray(omega_l).reshape(-1)
    levels = _load_moving_levels(p, int(flags[FL.LOAD_LAW]), flat).reshape(omega_l.shape)
    return np.asarray(np.sign(omega_l) * levels + model.load_friction.b_l * omega_l)


SPAN_PHASE_STEP_RAD = 0.5
"""Largest advance of the kinematic error's phase k·θ_m between the instants at which `span_instants`
looks inside one sample's span: its ripple runs at k·ω_m/2π (1.6 kHz at 200 rad/s, above a 1 kHz rate)."""
SPAN_INSTANTS_MIN, SPAN_INSTANTS_MAX = 8, 64
"""Instants per span, at least: where a ringing load reverses inside a span, the sign of its friction
changes there, and is placed to within 1/8 of a sample; at most: memory (rows × instants floats)."""
TAPER_S = 0.02
"""Each window's averages are taken with its edges ramped over this time (the first reaching back into
the settle time before it): the window's momentum term then reads the mean speed over its ramps, not
the speed at two instants, which a 2 µrad load sensor's noise made ±2 mN·m per window."""


def span_instants(run: Run, model: HarmonicDriveModel) -> tuple[np.ndarray, np.ndarray]:
    """Each sample's span of time, half-way to its neighbours: its edges (rows + 1) and equally spaced
    instants inside it (rows × n).

    A window of rows then covers one unbroken stretch of time: the mean over its rows of each span's
    mean is the stretch's time average, and a momentum term that telescopes across the spans
    (`SpanMotion.accel`) is exactly the change over the same stretch; as well for the columns each
    averaged over the last rows before it (`tapered`). Why not the samples themselves: after each
    reversal the load rings at its antiresonance (b_l alone damps it, over seconds), so a window's
    mean spring torque carries J_l·Δω_l/T of up to a few hundred mN·m, which cancels only if torque and
    speed change are taken over the very same stretch; the kinematic error's ripple in the spring
    torque (K_s·A = 1 N·m on the seed model) aliases in the samples at high motor speed; and where the
    ringing reverses the load, sgn(ω_l) averages differently from sgn(mean ω_l). Ideal sensors: each
    window's load balance at the true parameters closes to ≤ 0.4 mN·m (rms 0.11) instead of up to 8
    mN·m (rms 1.6).
    """
    t = run.t
    edges = np.concatenate([[1.5 * t[0] - 0.5 * t[1]], (t[:-1] + t[1:]) / 2, [1.5 * t[-1] - 0.5 * t[-2]]])
    instants = SPAN_INSTANTS_MIN
    if (ke := model.kinematic_error) is not None:
        phase_step_rad = ke.k * float(np.max(np.abs(np.diff(run["theta_m"]))))
        instants = min(max(instants, math.ceil(phase_step_rad / SPAN_PHASE_STEP_RAD)), SPAN_INSTANTS_MAX)
    at = edges[:-1, None] + np.diff(edges)[:, None] * ((np.arange(instants) + 0.5) / instants)
    return edges, at


@dataclass
class SpanMotion:
    """One body's motion over each sample's span (`span_instants`), from a cubic spline of its angle."""

    angle: np.ndarray  # (rows, instants) [rad]
    speed: np.ndarray  # (rows, instants): the spline's slope [rad/s]
    accel: np.ndarray  # (rows,): the speed change across the span / its length [rad/s²]


def span_motion(run: Run, column: str, edges: np.ndarray, at: np.ndarray) -> SpanMotion:
    spline = CubicSpline(run.t, run[column])
    return SpanMotion(
        np.asarray(spline(at)), np.asarray(spline(at, 1)), np.diff(spline(edges, 1)) / np.diff(edges)
    )


@functools.cache
def spline_speed_gain() -> float:
    """σ of `span_motion`'s speed per unit of white position noise per sample period: the rms, over the
    instants inside a span, of the norm of the cubic spline's derivative weights (1.57 on uniform
    samples; the measured speed noise of a 2 µrad load sensor at 1 kHz is 3.2 mrad/s)."""
    knots = np.arange(41, dtype=np.float64)
    spline = CubicSpline(knots, np.eye(knots.size))
    at = 19.5 + (np.arange(SPAN_INSTANTS_MAX) + 0.5) / SPAN_INSTANTS_MAX
    return float(np.sqrt(np.mean(np.sum(spline(at, 1) ** 2, axis=1))))


def sign_seen(part: SweepPart, load: SpanMotion) -> np.ndarray:
    """Per window: whether the load's speed stays clear of zero, by SPEED_BAND_SIGMAS of its noise, at
    every instant inside it. Where it does not, the noise flips the sign of F_l at some instants, and
    each flip takes 2·f_cl off the window's mean friction: on the seed model the load slows to
    0.5 mrad/s in the kinematic error's cycle at ±5 rad/s, and a 2 µrad sensor (3.2 mrad/s of speed
    noise) took those windows' mean F_l 1–1.8 mN·m low, in every noise seed (ideal: ≤ 0.05 mN·m)."""
    period_s = 1.0 / part.run.sample_rate_hz
    band = SPEED_BAND_SIGMAS * spline_speed_gain() * position_noise(part.run["theta_l"]) / period_s
    direction = np.sign(part.run["setpoint"])
    near = np.mean(direction[:, None] * load.speed < band, axis=1)
    return np.asarray(part.mean(near) == 0.0)


def tapered(column: np.ndarray, rows: int) -> np.ndarray:
    """Each row's value averaged with the rows − 1 before it (fewer at the start): a window's mean of
    this is the mean of `column` weighted by a ramp up over its first rows and down over its last."""
    sums = np.cumsum(np.concatenate([[0.0], column]))
    end = np.arange(1, len(column) + 1)
    count = np.minimum(end, rows)
    return np.asarray((sums[end] - sums[end - count]) / count)


@dataclass
class SweepPart:
    """The steady windows of one speed sweep in a run: `speed-sweep`'s, or one load's of `load-variation`."""

    run: Run
    ctx: RigContext
    settle_s: float
    prefix: str
    omega_set: np.ndarray  # per window [rad/s]
    steady: np.ndarray  # per window: neither motor nor load ran against the set speed

    def mean(self, column: np.ndarray) -> np.ndarray:
        """`column` averaged over each window (friction_table's rows)."""
        table = friction_table(as_torque(self.run, self.ctx, column), self.ctx, self.settle_s, self.prefix)
        return np.asarray(table["torque_nm"])

    @property
    def torque(self) -> np.ndarray:
        """Mean motor torque K_m·i_a per window [N·m]."""
        return self.mean(self.ctx.torque_constant_nm_per_a * self.run["i_a"])


def window_means(part: SweepPart, column: np.ndarray) -> np.ndarray:
    """`column` averaged over each of the part's windows, their edges ramped over TAPER_S (`tapered`)."""
    return part.mean(tapered(column, max(1, round(TAPER_S * part.run.sample_rate_hz))))


def sweep_parts(runs: Sequence[Run], model: HarmonicDriveModel) -> list[SweepPart]:
    """Every steady-speed sweep in the runs, windows marked steady where the formula F_m + r·F_l holds.

    At low speed a kinematic error larger than r makes a compliant output run backwards part of each
    error cycle (the load's friction then averages to anything); a window is steady when the motor and,
    on a compliant model, the load run with the set speed in all but REVERSED_SHARE_MAX of its samples.
    """
    parts = []
    for run in runs:
        experiment = run.meta.get("experiment")
        if experiment == "speed-sweep":
            prefixes = [""]
        elif experiment == "load-variation":
            prefixes = [load_prefix(float(tau)) for tau in run.meta["params"]["loads_nm"]]
        else:
            continue
        ctx = context(run)
        settle_s = float(run.meta["params"]["settle_s"])
        direction = np.sign(run["setpoint"])
        against = (direction * run["omega_m"] < 0).astype(np.float64)
        if "omega_l" in run and not model.rigid:
            against = np.maximum(against, (direction * run["omega_l"] < 0).astype(np.float64))
        for prefix in prefixes:
            table = friction_table(as_torque(run, ctx, against), ctx, settle_s, prefix)
            steady = np.asarray(table["torque_nm"]) <= REVERSED_SHARE_MAX
            parts.append(SweepPart(run, ctx, settle_s, prefix, np.asarray(table["omega_set"]), steady))
    return parts


def runs_of(runs: Sequence[Run], experiment: str) -> list[Run]:
    return [run for run in runs if run.meta.get("experiment") == experiment]


# --- stage: motor constants -------------------------------------------------------------------------------


KINK_GUARD_ROWS = 3
"""Rows either side of a jump of the voltage or a start or stop of the motor left out of u = R·i + K_b·ω:
the speed has a kink there (the acceleration jumps), and a difference of position samples spreads it over
its stencil; in sum the kink shifts the sampled speed by ~T·Δa/12 against the encoder's (0.4 % on R)."""


def encoder_speed(theta: np.ndarray, period_s: float) -> np.ndarray:
    """ω from equally spaced positions by the five-point stencil (error (ωT)⁴/30: 0.03 % at 50 Hz at 1 kHz,
    where the central difference loses 1.6 %); the central difference at the two rows of each end."""
    omega = np.gradient(theta, period_s)
    omega[2:-2] = (8.0 * (theta[3:-1] - theta[1:-3]) - (theta[4:] - theta[:-4])) / (12.0 * period_s)
    return np.asarray(omega)


def back_emf_fit(pieces: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray, float, np.ndarray]]) -> Solved:
    """R, K_b from u = R·i_a + K_b·(ω + δ·dω/dt) over pieces (u, i_a, θ_m, period, rows to use).

    The speed is the encoder's (`encoder_speed`; the drive's own speed is filtered and lags). δ is the
    skew between the instant the current is sampled and the instant the encoder's speed stands for: a
    drive samples them at different points of its cycle (a simulation's integrator offsets them by half
    its step), and unmodelled it moves R by ~K_b·δ·dω/dt/i (0.2 % at 50 µs). Rows within KINK_GUARD_ROWS
    of a jump of u or of a start or stop are left out, unless the command changes at nearly every row (a
    closed loop: no isolated kinks to avoid)."""
    out = Solved()
    rows_u, rows_i, rows_w, rows_a = [], [], [], []
    guarded = True
    for u, current, theta, period_s, pick in pieces:
        omega = encoder_speed(theta, period_s)
        accel = np.gradient(omega, period_s)
        moving = np.abs(np.gradient(theta)) > 0
        kinks = np.concatenate(
            [
                [0, len(u) - 1],  # the piece's ends: the stencil is short there, and what came before unknown
                np.flatnonzero(np.diff(u) != 0) + 1,
                np.flatnonzero(np.diff(moving.astype(np.int8)) != 0) + 1,
            ]
        )
        near = np.zeros(len(u), bool)
        for shift in range(-KINK_GUARD_ROWS, KINK_GUARD_ROWS + 1):
            near[np.clip(kinks + shift, 0, len(u) - 1)] = True
        use = pick & ~near
        if np.count_nonzero(use) < 0.5 * np.count_nonzero(pick):
            use, guarded = pick, False
        rows_u.append(u[use])
        rows_i.append(current[use])
        rows_w.append(omega[use])
        rows_a.append(accel[use])
    samples = sum(map(len, rows_u))
    if samples < 10:
        out.notes.append(f"skipped: {samples} samples of voltage, current and motion")
        return out
    design = np.column_stack([np.concatenate(rows_i), np.concatenate(rows_w), np.concatenate(rows_a)])
    beta, cov = linear_fit(design, np.concatenate(rows_u), serial=True)
    out.put("R", beta[0], math.sqrt(cov[0, 0]))
    out.put("K_b", beta[1], math.sqrt(cov[1, 1]))
    if beta[1] != 0:
        out.metrics["current_encoder_skew_s"] = float(beta[2] / beta[1])
    out.notes.append(
        f"u = R·i_a + K_b·(ω_m + δ·dω_m/dt) over {samples} samples"
        + (
            f" ({KINK_GUARD_ROWS} rows each side of the command's jumps and the motor's starts left out)"
            if guarded
            else ""
        )
        + f"; current/encoder skew δ = {out.metrics.get('current_encoder_skew_s', math.nan) * 1e6:.3g} µs"
    )
    return out


def motor_constants(pulses: Sequence[Run]) -> Solved:
    """R, K_b from voltage-mode pulses (`back_emf_fit`) at every sample where the motor is driven or moves.

    K_m is the rig's."""
    pieces = []
    for run in pulses:
        if run.input_column != "u":
            continue
        theta, u = run["theta_m"], run["u"]
        period_s = 1.0 / run.sample_rate_hz
        rest = PulseParams.model_validate(run.meta["params"]).rest_speed_rad_s
        pick = (u != 0) | (np.abs(encoder_speed(theta, period_s)) > rest)
        pick[: int(segments_of(run)[0]["start"])] = False  # the program's rows only
        pieces.append((u, run["i_a"], theta, period_s, pick))
    if not pieces:
        out = Solved()
        out.notes.append("skipped: no voltage-mode pulse run")
        return out
    out = back_emf_fit(pieces)
    out.notes[-1] += f" of {len(pieces)} pulse run(s)"
    return out


# --- stage: static stiffness and load friction --------------------------------------------------------------


def stiffness_names(model: HarmonicDriveModel) -> list[str]:
    return ["K1", "K2", "K3"] if model.nonlinear_stiffness is not None else ["K_s"]


def load_friction_names(model: HarmonicDriveModel) -> list[str]:
    lf = model.load_friction
    return ["f_cl", "b_l"] if lf is not None and lf.load_law == "coulomb_viscous" else []


def stiffness_and_load_friction(parts: Sequence[SweepPart], model: HarmonicDriveModel) -> Solved:
    """K_s (or K1..K3 at fixed T1, T2), f_cl, b_l and the load sensor's zero from steady windows.

    The load's momentum over a window's stretch of time: mean T_s = τ_ext + mean F_l + J_l·Δω_l/T, with
    T_s = spring(r·θ_m + A·sin(k·θ_m + φ) − θ_l − offset) and F_l = sgn(ω_l)·f_cl + b_l·ω_l averaged
    over the stretch inside every sample's span (`span_instants`). Windows at several loads separate the
    stiffness, both directions f_cl, several speeds b_l.

    The kinematic error's amplitude A is fitted here too, and only reported as a metric: at low speed
    the error's torque slows the motor through part of each cycle, and the window mean of K_s·A·sin(k·θ_m
    + φ) is far from zero (±140 mN·m at ±5 rad/s on the seed model, against f_cl = 300 mN·m) and odd in
    the direction, like f_cl. Held at the kinematic-error stage's A, that stage's error went into f_cl
    and b_l; fitted, it costs f_cl a wider σ instead. J_l likewise: the ringing load's J_l·Δω_l/T
    differs from window to window, held at the FRF's J_l it moved f_cl, and the windows see J_l far
    better than the FRF (figures: docs/BENCHMARKS.md, "Figures behind design choices in the code").

    Windows where the load's speed comes within its noise of zero are left out (`sign_seen`), and the
    standard errors are the rows' sandwich (`nonlinear_fit(unequal_rows=True)`): the windows' noise
    differs a lot (the ringing after a reversal, the ripple at speed), and s² over all of them had put
    f_cl's σ at 1.8× its spread over 20 noise seeds and K_s's at 2× (now 1.1×, 1.5×).
    """
    out = Solved()
    used = [part for part in parts if "theta_l" in part.run and np.any(part.steady)]
    if model.rigid or not used:
        out.notes.append("skipped: no steady sweep with a load angle on a compliant model")
        return out
    loads = {round(float(np.mean(part.mean(part.run["tau_ext"]))), 6) for part in used}
    skipped = _stiffness_skipped(model, loads)
    if skipped is not None:
        out.notes.append(skipped)
        return out
    names = _stiffness_seen(model, loads, out.undetermined) + load_friction_names(model)
    nuisance = _stiffness_nuisance(model)
    balance = WindowBalance(used, span_motions(used, model), model, names, nuisance)
    start = list(get_values(model, names).values())
    starts, scales, lows = zip(*nuisance.values(), strict=True)
    solved = nonlinear_fit(
        balance.residual,
        [*names, *nuisance],
        [*start, *starts],
        [*(abs(v) or 1.0 for v in start), *scales],
        lower=[1e-9 if name.startswith("K") else 0.0 for name in names] + list(lows),
        unequal_rows=True,
    )
    for name in nuisance:
        solved.metrics[name] = solved.values.pop(name)
        solved.metrics[name + "_std"] = solved.std_errors.pop(name)
    solved.notes.append(_stiffness_note(solved, nuisance, balance))
    return solved


def _stiffness_skipped(model: HarmonicDriveModel, loads: set[float]) -> str | None:
    """Why the windows' loads cannot part the stiffness from the load's friction, if they cannot."""
    if len(loads) < 2:
        # One load: the deflection is F_l/K_s, and only the windows' momentum (through the held J_l)
        # would part K_s from the friction; that is no measurement of either.
        return "skipped: steady windows under one load only (no load-variation run)"
    if model.hysteresis is not None:
        return "skipped: the spring torque carries the hysteresis element's ±T_h (not modelled)"
    return None


def _stiffness_seen(model: HarmonicDriveModel, loads: set[float], undetermined: dict[str, str]) -> list[str]:
    """The stiffness parameters the loads reach; each segment not reached goes into `undetermined`."""
    names = stiffness_names(model)
    if (ns := model.nonlinear_stiffness) is not None:
        # A segment's stiffness is seen only if some load passes into it (by 10 % of its breakpoint).
        reach = max(abs(tau) for tau in loads)
        for name, breakpoint in (("K2", ns.T1), ("K3", ns.T2)):
            if reach < 1.1 * breakpoint:
                names.remove(name)
                undetermined[name] = (
                    f"loads up to {reach:g} N·m do not pass its breakpoint {breakpoint:g} N·m"
                )
    return names


def _stiffness_nuisance(model: HarmonicDriveModel) -> dict[str, tuple[float, float, float]]:
    """Fitted with the stiffness, reported as metrics only (see `stiffness_and_load_friction`): the load
    sensor's zero, J_l, A; each with its start, scale and lower bound."""
    ke = model.kinematic_error
    J_l = model.mechanics.J_l
    nuisance = {"theta_l_offset": (0.0, 1e-5, -np.inf), "J_l": (J_l, J_l, 0.0)}
    if ke is not None:
        nuisance["A"] = (ke.A, ke.A, 0.0)
    return nuisance


Spans = dict[int, tuple[np.ndarray, np.ndarray, SpanMotion]]
"""By run (`id`): the deflection and the kinematic error's wave over each sample's span, and the load's
motion."""


def span_motions(used: Sequence[SweepPart], model: HarmonicDriveModel) -> Spans:
    """By run (a load-variation run holds one part per load): the motions over each sample's span."""
    ke = model.kinematic_error
    spans: Spans = {}
    for part in used:
        if id(part.run) not in spans:
            edges, at = span_instants(part.run, model)
            motor, load = (span_motion(part.run, column, edges, at) for column in ("theta_m", "theta_l"))
            wave = np.zeros_like(at) if ke is None else np.sin(ke.k * motor.angle + ke.phi)
            spans[id(part.run)] = (deflection_of(model, motor.angle, load.angle), wave, load)
    return spans


class WindowBalance:
    """The load's momentum balance of every clear steady window, as a residual of the fitted values
    (`names`, then the nuisance's) in mN·m."""

    SCALE_NM = 1e-3  # residuals in mN·m: the unit of the fit's conditioning, not of its result

    def __init__(
        self,
        used: list[SweepPart],
        spans: Spans,
        model: HarmonicDriveModel,
        names: list[str],
        nuisance: dict[str, tuple[float, float, float]],
    ) -> None:
        self.used, self.spans, self.model, self.names, self.nuisance = used, spans, model, names, nuisance
        self.clear = [part.steady & sign_seen(part, spans[id(part.run)][2]) for part in used]
        self.unseen = sum(
            int(np.count_nonzero(part.steady & ~ok)) for part, ok in zip(used, self.clear, strict=True)
        )
        self.windows = sum(int(np.count_nonzero(ok)) for ok in self.clear)
        self.loads_nm = [window_means(part, part.run["tau_ext"]) for part in used]
        self.accels = [window_means(part, spans[id(part.run)][2].accel) for part in used]
        self.f_sl = model.load_friction.f_sl if model.load_friction is not None else None

    def residual(self, x: np.ndarray) -> np.ndarray:
        names, ke = self.names, self.model.kinematic_error
        values = dict(zip(names, x[: len(names)], strict=True))
        if "f_cl" in values and self.f_sl is not None:
            values["f_sl"] = max(self.f_sl, values["f_cl"])  # the schema keeps static ≥ Coulomb
        trial = with_values(self.model, values)
        extra = dict(zip(self.nuisance, x[len(names) :], strict=True))
        error_change = extra["A"] - ke.A if ke is not None else 0.0
        balance = {
            run: spring_torque(trial, bent + error_change * wave - extra["theta_l_offset"]).mean(axis=1)
            - load_friction_steady(trial, load.speed).mean(axis=1)
            for run, (bent, wave, load) in self.spans.items()
        }
        rows = zip(self.used, self.loads_nm, self.accels, self.clear, strict=True)
        return np.concatenate(
            [
                ((window_means(part, balance[id(part.run)]) - tau - extra["J_l"] * accel) / self.SCALE_NM)[ok]
                for part, tau, accel, ok in rows
            ]
        )


def _stiffness_note(
    solved: Solved, nuisance: dict[str, tuple[float, float, float]], balance: WindowBalance
) -> str:
    seen = ", ".join(
        f"{name} = {solved.metrics[name]:.4g} ± {solved.metrics[name + '_std']:.2g}" for name in nuisance
    )
    return (
        f"mean spring torque = τ_ext + F_l + J_l·Δω_l/T over {balance.windows} steady windows, each sample's"
        f" span seen at instants between samples, the windows' edges ramped over {TAPER_S * 1e3:g} ms;"
        f" fitted with them, not used: {seen}"
        + (
            f"; {balance.unseen} window(s) left out where the load's speed came within {SPEED_BAND_SIGMAS:g}σ"
            " of its noise of zero (the sign of its friction is not seen there)"
            if balance.unseen
            else ""
        )
    )


# --- stage: frequency response ------------------------------------------------------------------------------


def speed_filter(run: Run) -> float | None:
    """α of the drive's speed estimate ω[k] = ω[k−1] + α·((θ[k] − θ[k−1])/T − ω[k−1]), from the run's own
    θ_m and ω_m columns by least squares; None when the columns do not follow that law."""
    period = 1.0 / run.sample_rate_hz
    raw = np.diff(run["theta_m"]) / period
    omega = run["omega_m"]
    x, y = raw - omega[:-1], np.diff(omega)
    if not np.any(x):
        return None
    alpha = float(x @ y / (x @ x))
    misfit = float(np.sqrt(np.mean((y - alpha * x) ** 2) / max(np.mean(y**2), 1e-300)))
    return alpha if misfit < 1e-3 and 0.0 < alpha <= 1.0 else None


def two_inertia_frf(
    model: HarmonicDriveModel, freq_hz: np.ndarray, c_m: float, period_s: float, alpha: float | None
) -> tuple[np.ndarray, np.ndarray]:
    """i_cmd → measured ω_m and i_cmd → θ_l of the linear two-inertia model, through the rig's sampling.

    (J_m s² + c_m s + r²Z)·θ_m − r·Z·θ_l = K_m·i,  −r·Z·θ_m + (J_l s² + b_l s + Z)·θ_l = 0,  Z = K_s + D_s·s;
    the command is held one cycle (e^(−sT/2)), the speed is the encoder difference (1 − z⁻¹)/T through
    the drive's first-order filter α/(1 − (1 − α)·z⁻¹) (ideal derivative s when α is unknown).
    """
    mech, trans = model.mechanics, model.transmission
    s = 2j * np.pi * freq_hz
    b_l = model.load_friction.b_l if model.load_friction is not None else 0.0
    hold = np.exp(-s * period_s / 2)
    if trans.K_s is None:
        theta_m = model.motor.K_m / (s * s * (mech.J_m + mech.r**2 * mech.J_l) + s * (c_m + mech.r**2 * b_l))
        theta_l = mech.r * theta_m
    else:
        z = trans.K_s + trans.D_s * s
        motor = mech.J_m * s * s + c_m * s + mech.r**2 * z
        load = mech.J_l * s * s + b_l * s + z
        det = motor * load - (mech.r * z) ** 2
        theta_m = model.motor.K_m * load / det
        theta_l = model.motor.K_m * mech.r * z / det
    chain: np.ndarray = s
    if alpha is not None:
        delay = np.exp(-s * period_s)
        chain = (1 - delay) / period_s * alpha / (1 - (1 - alpha) * delay)
    return theta_m * hold * chain, theta_l * hold


def frequency_response(chirp: Run, model: HarmonicDriveModel, fit_stiffness: bool, c_m: float) -> Solved:
    """J_m, J_l, D_s (and K_s if no static value) from the chirp's FRFs, i_cmd → ω_m and i_cmd → θ_l.

    Complex least squares of log(H_model/H_measured) over the lines with coherence > COHERENCE_MIN, with a
    soft-L1 loss: the friction harmonics and the slow friction trend leak into a few lines of a short
    periodic record, and those should not steer the fit. c_m (the motor friction's slope) is held.
    """
    ctx = context(chirp)
    params = ChirpParams.model_validate(chirp.meta["params"])
    tables = frf_tables(chirp, params, ctx)
    alpha = speed_filter(chirp)
    out = Solved()
    used = ["frf_speed"] if model.rigid or "theta_l" not in chirp else ["frf_speed", "frf_load"]
    measured = {}
    for name in used:
        table = tables[name]
        keep = table["coherence"] > COHERENCE_MIN
        h = 10 ** (table["magnitude_db"][keep] / 20) * np.exp(1j * np.radians(table["phase_deg"][keep]))
        measured[name] = (table["freq_hz"][keep], h)
    lines = sum(len(f) for f, _ in measured.values())
    if lines < 6:
        out.notes.append(f"skipped: only {lines} coherent FRF lines in the chirp")
        return out
    stiffness = stiffness_names(model)[:1]  # K_s, or K1 (= K_s) of a piecewise spring
    names = ["J_m"] if model.rigid else ["J_m", "J_l", "D_s"] + (stiffness if fit_stiffness else [])
    period_s = 1.0 / ctx.rate_hz

    def residual(x: np.ndarray) -> np.ndarray:
        trial = with_values(model, dict(zip(names, x, strict=True)))  # rigid: J_l held, J_m the rest
        pieces = []
        for name, (freq, h) in measured.items():
            speed, load = two_inertia_frf(trial, freq, c_m, period_s, alpha)
            error = np.log((speed if name == "frf_speed" else load) / h)
            pieces += [error.real, error.imag]
        return np.concatenate(pieces)

    start = list(get_values(model, names).values())
    scale = [abs(v) if v else 1.0 for v in start]
    lower = [1e-12] * len(names)
    out = nonlinear_fit(residual, names, start, scale, lower=lower, loss="soft_l1", f_scale=0.1)
    out.notes.append(
        f"two-inertia model fitted to {lines} coherent lines of {', '.join(used)}"
        f" (speed filter α = {alpha:.4g})"
        if alpha is not None
        else f"two-inertia model fitted to {lines} coherent lines; speed column not a first-order filter"
        " of encoder differences, taken as the true speed"
    )
    if not model.rigid:
        line_hz = 1.0 / params.period_s
        fitted = with_values(model, {n: out.values[n] for n in names})
        mech, trans = fitted.mechanics, fitted.transmission
        assert trans.K_s is not None
        reduced = 1.0 / (1.0 / mech.J_l + mech.r**2 / mech.J_m)
        zeta = trans.D_s / (2.0 * math.sqrt(trans.K_s * reduced))
        f_r = math.sqrt(trans.K_s / reduced) / (2 * math.pi)
        f_a = math.sqrt(trans.K_s / mech.J_l) / (2 * math.pi)
        band_hz = max(float(freq.max()) for freq, _ in measured.values())
        out.metrics.update(zeta=zeta, f_r_hz=f_r, f_a_hz=f_a, line_hz=line_hz)
        if f_a > band_hz:
            # No antiresonance in the band: the FRF sees the rigid body J_m + r²·J_l alone.
            held = model.mechanics.J_l
            out.values["J_m"] += mech.r**2 * (mech.J_l - held)
            why = f"the antiresonance ({f_a:.3g} Hz) lies above the coherent band (≤ {band_hz:.3g} Hz)"
            out.undetermined["J_l"] = why + ": only J_m + r²·J_l is seen, J_m carries it"
            out.undetermined["D_s"] = why
            for name in stiffness if fit_stiffness else []:
                out.undetermined[name] = why
        elif 2 * zeta * f_r < 2 * line_hz or f_r > band_hz:
            out.undetermined["D_s"] = (
                f"fitted {trans.D_s:.3g} N·m·s/rad gives the resonance ({f_r:.3g} Hz) a half-power width"
                f" of {2 * zeta * f_r:.2g} Hz: not resolved by FRF lines {line_hz:g} Hz apart"
                f" up to {band_hz:.3g} Hz"
            )
    return out


# --- stage: kinematic error --------------------------------------------------------------------------------


def load_response(model: HarmonicDriveModel, omega_rad_s: np.ndarray) -> np.ndarray:
    """G(jΩ) = (K_s + jΩ·D_s)/(K_s + jΩ·(D_s + b_l) − J_l·Ω²): how the load follows a motion imposed at
    the spring's motor end at Ω [rad/s]; 1 for a rigid transmission."""
    trans, J_l = model.transmission, model.mechanics.J_l
    if trans.K_s is None:
        return np.ones_like(omega_rad_s, dtype=np.complex128)
    b_l = model.load_friction.b_l if model.load_friction is not None else 0.0
    jw = 1j * omega_rad_s
    spring = trans.K_s + jw * trans.D_s
    return np.asarray(spring / (spring + jw * b_l - J_l * omega_rad_s**2))


CARRIER_TURNS = 2.0
"""Knot spacing, in motor turns, of the slow motion the kinematic-error stage locks its waves to."""


def slow_motion(t: np.ndarray, theta: np.ndarray, knot_spacing_s: float) -> np.ndarray:
    """θ_m's slow part: a least-squares cubic spline with knots `knot_spacing_s` apart (a straight
    line when the stretch is shorter). At a knot spacing of two motor turns it follows the speed's
    drift over a pass (the friction's quadratic part through the velocity loop) and none of the ripple
    at one or more cycles per turn."""
    inner = np.arange(t[0] + knot_spacing_s, t[-1] - 0.5 * knot_spacing_s, knot_spacing_s)
    if inner.size == 0:
        return np.asarray(np.polyval(np.polyfit(t, theta, 1), t))
    knots = np.concatenate([[t[0]] * 4, inner, [t[-1]] * 4])
    return np.asarray(make_lsq_spline(t, theta, knots, k=3)(t))


KINEMATIC_HARMONICS = 3
"""Time harmonics n = −3..3 of the error's wave over a pass, each taken through the load at its own
frequency: the motor's speed dips where the error's torque opposes it, so e^(jk·θ_m) is no pure tone."""


def kinematic_error(passes: Sequence[Run], model: HarmonicDriveModel) -> Solved:
    """A, φ from θ_l − r·θ_m over constant-speed passes: the kinematic error seen through the load.

    At motor speed ω the spring's motor end moves by r·θ_m + A·sin(k·θ_m + φ), rippling at Ω = k·ω (the
    error, and the motor's own ripple r·θ̃_m that the error's torque causes); the load follows each time
    harmonic e^(jnΩt) of it by G(jnΩ), so θ_l − r·θ_m = c + Im(A·e^(jφ)·Σ_n w_n·G(jnΩ)·e^(jnΩt)) +
    r·Σ_n (G(jnΩ) − 1)·m_n·e^(jnΩt), with w_n and m_n the harmonics of the measured e^(jk·θ_m) and θ̃_m.
    Linear in A·e^(jφ): least squares, an offset per pass direction, with K_s, J_l, D_s, b_l from the
    earlier stages. (Taking e^(jk·θ_m) through G(jΩ) whole put A low on the seed's slow passes: there
    the error's torque slows the motor through part of each cycle, and w_{±2}, w_{−1} are not small.)

    The waves are locked to θ_m's slow motion (`slow_motion`), not to a straight line, and include the
    sidebands n·k ± m of the friction's harmonics m: the speed drifts over a pass and ripples with the
    friction, and both moved the error's phase against waves that did not have them. What they left,
    well above the load sensor's noise, inflated σ(A) far beyond the spread over noise seeds; with them
    what is left is the load's free ringing at its antiresonance, which no wave of the error's matches
    (figures: docs/BENCHMARKS.md).
    """
    out = Solved()
    ke = model.kinematic_error
    if ke is None:
        out.notes.append("skipped: no kinematic_error in the model")
        return out
    r = model.mechanics.r
    # Per motor turn: the error's harmonics n·k and, around each, the sidebands n·k ± m of the motor's
    # speed ripple at the friction's harmonics m (the ripple phase-modulates the error's wave).
    sidebands = np.arange(-N_FOURIER, N_FOURIER + 1)
    harmonics = np.arange(-KINEMATIC_HARMONICS, KINEMATIC_HARMONICS + 1) * ke.k
    order = np.unique(np.round((harmonics[:, None] + sidebands[None, :]).ravel(), 9))
    columns, targets = [], []
    for run in passes:
        if "theta_l" not in run:
            continue
        ctx = context(run)
        settle_s = float(run.meta["params"]["settle_s"])
        theta, direction, _ = steady_samples(run, ctx, settle_s)
        _, _, theta_l = steady_samples(as_torque(run, ctx, run["theta_l"]), ctx, settle_s)
        _, _, t_s = steady_samples(as_torque(run, ctx, run.t), ctx, settle_s)
        for sign in (1.0, -1.0):  # Frisch–Waugh: an offset per direction, taken out by centring
            pick = direction == sign
            if not np.any(pick):
                continue
            speed = float(np.polyfit(t_s[pick], theta[pick], 1)[0])
            mean_motion = slow_motion(t_s[pick], theta[pick], 2.0 * CARRIER_TURNS * math.pi / abs(speed))
            waves = np.exp(1j * np.outer(mean_motion, order))  # e^(jnωt), phase-locked to θ_m
            response = load_response(model, order * speed)
            error_wave = np.linalg.lstsq(waves, np.exp(1j * ke.k * theta[pick]), rcond=None)[0]
            ripple = (theta[pick] - mean_motion).astype(np.complex128)
            motor_wave = np.linalg.lstsq(waves, ripple, rcond=None)[0]
            basis = waves @ (error_wave * response)
            motor = r * (waves @ (motor_wave * (response - 1))).real
            design = np.column_stack([basis.imag, basis.real])
            y = theta_l[pick] - r * theta[pick] - motor
            columns.append(design - design.mean(axis=0))
            targets.append(y - y.mean())
    if not columns:
        out.notes.append("skipped: no position-friction run with a load angle")
        return out
    beta, cov = linear_fit(np.concatenate(columns), np.concatenate(targets), serial=True)
    amplitude = float(np.hypot(*beta))
    radial = beta / amplitude
    tangential = np.array([-radial[1], radial[0]])
    out.put("A", amplitude, math.sqrt(float(radial @ cov @ radial)))
    out.put("phi", math.atan2(beta[1], beta[0]), math.sqrt(float(tangential @ cov @ tangential)) / amplitude)
    out.notes.append(
        f"θ_l − r·θ_m at k = {ke.k:g} per motor turn over {sum(map(len, targets))} samples,"
        f" harmonics n = ±{KINEMATIC_HARMONICS} of the error's wave each through the load's response G(jnΩ)"
    )
    return out
