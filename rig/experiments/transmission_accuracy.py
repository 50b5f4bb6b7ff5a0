"""`transmission-accuracy`: the catalog's angle-transmission error. Unloaded, the input turns slowly and
steadily through `output_turns` turns of the output; the error is the output angle against the angle the
ratio promises, θ_l − r·θ_m, less its mean. `error_pp_rad` is its peak to peak (the catalog's figure:
the largest positive plus the largest negative deviation); its spectrum is given in multiples of the wave
generator's (input's) turn, each order's amplitude from a least-squares fit of cos and sin of n·θ_m.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from pydantic import Field

from model.run import Run
from rig.experiments.base import (
    SPEED_MAX_RAD_S,
    Experiment,
    ExperimentParams,
    ProgramError,
    Results,
    RigContext,
    segment_rows,
)
from rig.experiments.plots import new_figure, save_figure
from rig.interface import ControlMode, Segment

NAME = "transmission-accuracy"


class TransmissionAccuracyParams(ExperimentParams):
    speed_rad_s: float = Field(
        default=10.0, gt=0, le=SPEED_MAX_RAD_S, description="input speed, slow and steady [rad/s]"
    )
    output_turns: float = Field(default=1.0, gt=0, le=100, description="output turns measured [turns]")
    settle_s: float = Field(default=0.5, gt=0, le=60, description="time to reach steady speed [s]")
    # 64 orders: a harmonic drive's error is at order 2 of the wave generator; the seed model's article
    # value k = 50 per motor turn must be inside the range too.
    orders: int = Field(default=64, ge=1, le=200, description="harmonics of the input turn fitted [–]")


def order_amplitudes(theta_m: np.ndarray, error: np.ndarray, orders: int) -> np.ndarray:
    """Amplitude of each order n = 1..orders per input turn in `error`, by least squares [rad]."""
    basis = [np.ones_like(theta_m)]
    for n in range(1, orders + 1):
        basis += [np.cos(n * theta_m), np.sin(n * theta_m)]
    coef, *_ = np.linalg.lstsq(np.stack(basis, axis=1), error, rcond=None)
    return np.hypot(coef[1::2], coef[2::2])


class TransmissionAccuracy(Experiment):
    name = NAME
    summary = (
        "output angle error against the input over one output turn, unloaded: peak to peak and harmonics"
    )
    Params = TransmissionAccuracyParams
    needs = frozenset({ControlMode.VELOCITY})

    def program(self, params: TransmissionAccuracyParams, ctx: RigContext) -> list[Segment]:
        turn_s = params.output_turns * 2 * math.pi / ctx.gear_ratio / params.speed_rad_s
        reach_out = ctx.gear_ratio * (ctx.theta_m0 + params.speed_rad_s * (params.settle_s + turn_s + 0.5))
        if reach_out > ctx.config.limits.travel_max_out_rad:
            raise ProgramError(
                f"{NAME} turns the output {params.output_turns:g} turn(s) (to {reach_out:.3g} rad), past rig"
                f" {ctx.config.name!r}'s travel limit {ctx.config.limits.travel_max_out_rad:g} rad: use a"
                " bench whose output turns freely, such as sim-dyno"
            )
        settle = ctx.cycles(params.settle_s)
        measure = ctx.cycles(turn_s)
        stop = ctx.cycles(0.5)
        return [
            Segment(ControlMode.VELOCITY, np.full(settle, params.speed_rad_s), 0.0, "settle"),
            Segment(ControlMode.VELOCITY, np.full(measure, params.speed_rad_s), 0.0, "measure"),
            Segment(ControlMode.VELOCITY, np.zeros(stop), 0.0, "stop"),
        ]

    def error(self, run: Run, ctx: RigContext) -> tuple[np.ndarray, np.ndarray]:
        """Input angle [rad] and transmission error (mean removed) [rad] over the measured turn."""
        rows = segment_rows(run, "measure")
        theta_m = run["theta_m"][rows]
        error = run["theta_l"][rows] - ctx.gear_ratio * theta_m
        return theta_m, error - np.mean(error)

    def analyze(self, run: Run, params: TransmissionAccuracyParams, ctx: RigContext) -> Results:
        theta_m, error = self.error(run, ctx)
        amplitudes = order_amplitudes(theta_m, error, params.orders)
        leading = np.argsort(amplitudes)[::-1][:3]
        metrics: dict[str, float | int | str] = {
            "error_pp_rad": float(np.ptp(error)),
            "error_pp_arcmin": float(np.ptp(error) * 180 * 60 / math.pi),
        }
        for rank, index in enumerate(leading, start=1):
            metrics[f"harmonic{rank}_order"] = int(index + 1)
            metrics[f"harmonic{rank}_amplitude_rad"] = float(amplitudes[index])
        table = {"order_per_input_turn": np.arange(1, params.orders + 1), "amplitude_rad": amplitudes}
        notes = [
            f"transmission error {metrics['error_pp_rad']:.3g} rad peak to peak"
            f" ({metrics['error_pp_arcmin']:.3g} arcmin); leading order {leading[0] + 1} per input turn"
        ]
        return Results(metrics=metrics, tables={"harmonics": table}, notes=notes)

    def plot(
        self, run: Run, results: Results, params: TransmissionAccuracyParams, ctx: RigContext, out_dir: Path
    ) -> list[Path]:
        theta_m, error = self.error(run, ctx)
        fig, ax = new_figure("transmission error over the measured output turn")
        ax.plot(ctx.gear_ratio * (theta_m - theta_m[0]), error * 1e6, lw=0.6)
        ax.set_xlabel("output angle r·θ_m [rad]")
        ax.set_ylabel("θ_l − r·θ_m [µrad]")
        return [save_figure(fig, out_dir / "transmission_accuracy.png")]
