"""`position-friction`: constant-speed passes over the stroke both ways; friction against motor position.

At constant speed the motor's torque K_m·i_a balances the friction seen from the motor, F_m + r·F_l.
Passing the stroke forward then backward at one speed, `cycles` times, gives two things:

- friction against position on a grid over the stroke (bins of one motor turn by default, so the
  periodic part averages out): the slow level C(θ_m) of docs/MODEL.md, per direction;
- friction against motor angle modulo one turn: the periodic part P(θ_m), and its Fourier
  coefficients a_n, b_n from one least-squares fit of `c0 + c1·θ + c2·θ² + Σ a_n cos nθ + b_n sin nθ`
  to the friction magnitude sgn(ω)·K_m·i_a of every steady sample (the quadratic gives s1..s3).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from numpy.polynomial import Polynomial
from pydantic import Field

from model.run import Run
from rig.experiments.base import (
    Experiment,
    ExperimentParams,
    ProgramError,
    Results,
    RigContext,
    segments_of,
)
from rig.experiments.plots import new_figure, save_figure
from rig.interface import ControlMode, Segment

TURN_RAD = 2.0 * math.pi


class PositionFrictionParams(ExperimentParams):
    # Slow, so that the ripple's harmonics (n·speed, n ≤ 10) stay well inside the velocity loop's
    # bandwidth and below the load resonance (~80 rad/s on the seed): the current then follows friction.
    speed_rad_s: float = Field(
        default=5.0, gt=0, le=100, description="motor speed of every pass, forward and backward [rad/s]"
    )
    travel_fraction: float = Field(
        default=0.5, gt=0, le=1, description="share of the free stroke ahead of the start a pass covers [–]"
    )
    max_pass_out_rad: float = Field(
        default=2 * math.pi,
        gt=0,
        le=1000,
        description="longest pass, at the output: one turn on a bench that turns without end [rad]",
    )
    cycles: int = Field(default=1, ge=1, le=20, description="forward+backward pass pairs, averaged [–]")
    settle_s: float = Field(
        default=1.0, gt=0, le=10, description="time after each start or reversal left out of averages [s]"
    )
    bin_rad: float = Field(
        default=TURN_RAD,
        gt=0,
        le=100,
        description="width of the position grid's bins; one motor turn averages the periodic part out [rad]",
    )
    # 50 bins span one period each of a kinematic-error ripple at k = 50 per turn (the article's), which
    # then averages out of every bin instead of showing as scatter around the Fourier curve.
    angle_bins: int = Field(
        default=50, ge=8, le=720, description="bins over one motor turn for friction against angle [–]"
    )
    harmonics: int = Field(
        default=10, ge=1, le=10, description="Fourier harmonics of one motor turn fitted (1..harmonics) [–]"
    )


def pass_program(params: PositionFrictionParams, ctx: RigContext) -> list[Segment]:
    """`cycles` pairs of passes `pass<k>+` / `pass<k>-` over the same stretch, ending where they began."""
    room_m = (ctx.config.limits.travel_max_out_rad / ctx.gear_ratio - ctx.theta_m0) * params.travel_fraction
    # A dynamometer bench's stroke is unbounded (±10,000 rad out): half of it was days of passes.
    room_m = min(room_m, params.max_pass_out_rad / ctx.gear_ratio)
    duration_s = room_m / params.speed_rad_s
    if duration_s <= 2 * params.settle_s:
        raise ProgramError(
            f"position-friction: travel_fraction {params.travel_fraction:g} leaves {room_m:.3g} rad of stroke"
            f" ahead: too short for passes at {params.speed_rad_s:g} rad/s, settle_s {params.settle_s:g} s"
        )
    both_ways_rad = room_m - 2 * params.settle_s * params.speed_rad_s  # seen by both directions
    if both_ways_rad < params.bin_rad:
        raise ProgramError(
            f"position-friction: bin_rad {params.bin_rad:g} is wider than the {both_ways_rad:.3g} rad"
            " both directions pass over: lower bin_rad or settle_s, or raise travel_fraction"
        )
    cycles = ctx.cycles(duration_s)
    return [
        Segment(ControlMode.VELOCITY, np.full(cycles, sign * params.speed_rad_s), 0.0, f"pass{k + 1}{mark}")
        for k in range(params.cycles)
        for sign, mark in ((1.0, "+"), (-1.0, "-"))
    ]


def steady_samples(run: Run, ctx: RigContext, settle_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Motor position, direction (±1) and motor torque K_m·i_a of every sample past each pass's settle."""
    skip = ctx.cycles(settle_s)
    rows = [
        np.arange(int(s["start"]) + skip, int(s["start"]) + int(s["cycles"]))
        for s in segments_of(run, "pass")
    ]
    index = np.concatenate(rows)
    direction = np.sign(run["setpoint"][index])
    return run["theta_m"][index], direction, ctx.torque_constant_nm_per_a * run["i_a"][index]


def position_grid(
    theta: np.ndarray, direction: np.ndarray, torque: np.ndarray, bin_rad: float
) -> dict[str, np.ndarray]:
    """Mean torque per direction on bins of `bin_rad` covering the stretch both directions saw."""
    fwd, bwd = direction > 0, direction < 0
    lo = max(theta[fwd].min(), theta[bwd].min())
    hi = min(theta[fwd].max(), theta[bwd].max())
    count = int((hi - lo) // bin_rad)
    if count < 1:
        raise ValueError(f"the passes overlap over {hi - lo:.3g} rad, less than one bin of {bin_rad:.3g} rad")
    index = np.floor((theta - lo) / bin_rad).astype(np.int64)
    inside = (index >= 0) & (index < count)
    means = {}
    for name, pick in (("fwd", fwd & inside), ("bwd", bwd & inside)):
        sums = np.bincount(index[pick], torque[pick], minlength=count)
        means[name] = sums / np.bincount(index[pick], minlength=count)
    return {
        "theta_m": lo + (np.arange(count) + 0.5) * bin_rad,
        "torque_fwd_nm": means["fwd"],
        "torque_bwd_nm": means["bwd"],
        "mean_nm": 0.5 * (means["fwd"] + means["bwd"]),  # what does not change sign: asymmetry, gravity
        "half_diff_nm": 0.5 * (means["fwd"] - means["bwd"]),  # the friction magnitude
    }


def fourier_basis(theta: np.ndarray, harmonics: int) -> np.ndarray:
    """Columns cos nθ, sin nθ for n = 1..harmonics (interleaved: cos 1, sin 1, cos 2, ...)."""
    n_theta = np.multiply.outer(theta, np.arange(1, harmonics + 1))
    return np.stack([np.cos(n_theta), np.sin(n_theta)], axis=-1).reshape(len(theta), 2 * harmonics)


def quadratic_fourier_fit(
    theta: np.ndarray, magnitude: np.ndarray, harmonics: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least squares of magnitude = s1·θ² + s2·θ + s3 + Σ a_n cos nθ + b_n sin nθ.

    Returns ([s1, s2, s3], a_1..a_N, b_1..b_N). The quadratic is fitted in x = (θ − mid)/half ∈ [−1, 1]
    (θ² over the stroke would swamp the harmonics' ±1), which keeps the small normal equations
    well conditioned: they solve in milliseconds where an SVD of all the samples takes a fifth of a second.
    """
    mid, half = 0.5 * (theta.max() + theta.min()), max(0.5 * float(np.ptp(theta)), 1e-9)
    x = (theta - mid) / half
    design = np.column_stack([np.ones_like(x), x, x**2, fourier_basis(theta, harmonics)])
    coef = np.linalg.lstsq(design.T @ design, design.T @ magnitude, rcond=None)[0]
    in_theta = Polynomial(coef[:3])(Polynomial([-mid / half, 1.0 / half]))
    quad = np.zeros(3)
    quad[3 - len(in_theta.coef) :] = in_theta.coef[::-1]  # highest power first, as np.polyval wants
    return quad, coef[3::2], coef[4::2]


def angle_table(
    theta: np.ndarray, periodic: np.ndarray, bins: int, a: np.ndarray, b: np.ndarray
) -> dict[str, np.ndarray]:
    """The periodic friction averaged on `bins` over one motor turn, beside the fitted series."""
    angle = np.mod(theta, TURN_RAD)
    index = np.minimum((angle / TURN_RAD * bins).astype(np.int64), bins - 1)
    counts = np.bincount(index, minlength=bins)
    centres = (np.arange(bins) + 0.5) * TURN_RAD / bins
    with np.errstate(invalid="ignore"):  # a bin no sample reached stays NaN, visibly
        torque = np.bincount(index, periodic, minlength=bins) / counts
    series = fourier_basis(centres, len(a)) @ np.column_stack([a, b]).ravel()
    return {"angle_rad": centres, "torque_nm": torque, "fourier_nm": series}


class PositionFriction(Experiment):
    name = "position-friction"
    summary = "constant-speed passes over the stroke both ways; friction against position and angle"
    Params = PositionFrictionParams
    needs = frozenset({ControlMode.VELOCITY})

    def program(self, params: PositionFrictionParams, ctx: RigContext) -> list[Segment]:
        return pass_program(params, ctx)

    def analyze(self, run: Run, params: PositionFrictionParams, ctx: RigContext) -> Results:
        theta, direction, torque = steady_samples(run, ctx, params.settle_s)
        grid = position_grid(theta, direction, torque, params.bin_rad)
        magnitude = direction * torque
        quad, a, b = quadratic_fourier_fit(theta, magnitude, params.harmonics)
        slow = np.polyval(quad, theta)
        angles = angle_table(theta, magnitude - slow, params.angle_bins, a, b)
        amplitude = np.hypot(a, b)
        metrics: dict[str, float | int | str] = {
            "speed_rad_s": params.speed_rad_s,
            "stroke_rad": float(theta.max() - theta.min()),
            "friction_mean_nm": float(np.mean(grid["half_diff_nm"])),
            "friction_min_nm": float(np.min(grid["half_diff_nm"])),
            "friction_max_nm": float(np.max(grid["half_diff_nm"])),
            "asymmetry_mean_nm": float(np.mean(grid["mean_nm"])),
            "quad_s1_nm_rad2": float(quad[0]),
            "quad_s2_nm_rad": float(quad[1]),
            "quad_s3_nm": float(quad[2]),
            "ripple_pp_nm": float(np.ptp(angles["fourier_nm"])),
            "dominant_harmonic": int(np.argmax(amplitude)) + 1,
        }
        notes = [
            "half_diff_nm is the friction magnitude (F_m + r·F_l); mean_nm what does not change with"
            " direction (asymmetry, gravity, offset)",
            f"quad_s1..s3 fit C(θ)·(1 + k_v·(|ω| − v_c)) + r·F_l at {params.speed_rad_s:g} rad/s;"
            " a_n, b_n fit P(θ) directly",
        ]
        fourier = {"n": np.arange(1, params.harmonics + 1), "a_nm": a, "b_nm": b}
        tables = {"friction_vs_position": grid, "friction_vs_angle": angles, "fourier": fourier}
        return Results(metrics, tables, notes)

    def plot(
        self, run: Run, results: Results, params: PositionFrictionParams, ctx: RigContext, out_dir: Path
    ) -> list[Path]:
        grid = results.tables["friction_vs_position"]
        fig, ax = new_figure("Friction torque against motor position (position friction)")
        ax.plot(grid["theta_m"], grid["torque_fwd_nm"], "o-", ms=3, label="forward")
        ax.plot(grid["theta_m"], -grid["torque_bwd_nm"], "s-", ms=3, label="backward (sign flipped)")
        ax.plot(grid["theta_m"], grid["mean_nm"], "-", color="0.5", label="mean of both (offset)")
        ax.set_xlabel("motor position θ_m [rad]")
        ax.set_ylabel("motor torque K_m·i_a [N·m]")
        ax.legend()
        paths = [save_figure(fig, out_dir / "friction_vs_position.png")]

        angles = results.tables["friction_vs_angle"]
        fig, ax = new_figure("Periodic friction over one motor turn (slow part removed)")
        ax.plot(angles["angle_rad"], angles["torque_nm"], "o", ms=3, label="measured, binned")
        ax.plot(angles["angle_rad"], angles["fourier_nm"], "-", label=f"Fourier fit, n ≤ {params.harmonics}")
        ax.set_xlabel("motor angle θ_m mod 2π [rad]")
        ax.set_ylabel("periodic friction P(θ_m) [N·m]")
        ax.legend()
        paths.append(save_figure(fig, out_dir / "friction_vs_angle.png"))
        return paths
