"""`speed-sweep`: steady motor speeds from negative to positive; friction torque from the current.

At constant speed the motor's torque K_m·i_a balances all friction seen from the motor: F_m + r·F_l
(+ r·τ_ext when a load is applied). Each speed is run forward then backward over the same stretch of
the stroke, so the program returns to where it started and both directions see the same positions.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import numpy as np
from pydantic import Field, ValidationInfo, field_validator

from model.run import Run
from rig.experiments.base import (
    LIST_MAX,
    LOAD_MAX_NM,
    SPEED_MAX_RAD_S,
    Experiment,
    ExperimentParams,
    ProgramError,
    Results,
    RigContext,
    rig_speeds,
    segments_of,
)
from rig.experiments.plots import new_figure, save_figure
from rig.interface import ControlMode, Segment


class SpeedSweepParams(ExperimentParams):
    speeds_rad_s: list[Annotated[float, Field(gt=0, le=SPEED_MAX_RAD_S)]] = Field(
        default=[0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0, 200.0],
        min_length=1,
        max_length=LIST_MAX,
        description="motor speed magnitudes, distinct; each is run forward and backward [rad/s]",
    )
    settle_s: float = Field(
        default=0.3, gt=0, le=10, description="time to reach steady speed, not averaged [s]"
    )
    hold_s: float = Field(
        default=0.7, gt=0, le=60, description="averaging window per speed and direction [s]"
    )
    travel_fraction: float = Field(
        default=0.8,
        gt=0,
        le=1,
        description="share of the free stroke ahead a pass may use; shortens holds [–]",
    )
    tau_ext_nm: float = Field(
        default=0.0,
        ge=-LOAD_MAX_NM,
        le=LOAD_MAX_NM,
        description="external load torque during the sweep [N·m]",
    )

    @field_validator("speeds_rad_s")
    @classmethod
    def _positive_speeds(cls, speeds: list[float], info: ValidationInfo) -> list[float]:
        return rig_speeds(speeds, info)


def sweep_program(params: SpeedSweepParams, ctx: RigContext, prefix: str = "") -> list[Segment]:
    """Forward/backward constant-speed passes for each speed; labels `<prefix>v+<speed>`/`v-<speed>`."""
    limits = ctx.config.limits
    room_m = (limits.travel_max_out_rad / ctx.gear_ratio - ctx.theta_m0) * params.travel_fraction
    segments = []
    for speed in params.speeds_rad_s:
        duration = min(params.settle_s + params.hold_s, room_m / speed)
        if duration <= params.settle_s:
            raise ProgramError(
                f"speed-sweep: at {speed} rad/s the stroke ahead ({room_m:.3g} rad motor) is too short"
                f" to settle in settle_s = {params.settle_s} s"
            )
        cycles = ctx.cycles(duration)
        for sign in (1.0, -1.0):
            segments.append(
                Segment(
                    ControlMode.VELOCITY,
                    np.full(cycles, sign * speed),
                    params.tau_ext_nm,
                    f"{prefix}v{sign * speed:+g}",
                )
            )
    return segments


def friction_table(run: Run, ctx: RigContext, settle_s: float, prefix: str = "") -> dict[str, np.ndarray]:
    """Per constant-speed segment: the speed held and the motor torque that held it (mean and spread)."""
    skip = ctx.cycles(settle_s)
    rows: dict[str, list[float]] = {
        k: [] for k in ("omega_set", "omega_m", "torque_nm", "torque_std", "theta_m")
    }
    for seg in segments_of(run, prefix + "v"):
        window = slice(int(seg["start"]) + skip, int(seg["start"]) + int(seg["cycles"]))
        torque = ctx.torque_constant_nm_per_a * run["i_a"][window]
        rows["omega_set"].append(float(run["setpoint"][window][0]))
        rows["omega_m"].append(float(np.mean(run["omega_m"][window])))
        rows["torque_nm"].append(float(np.mean(torque)))
        rows["torque_std"].append(float(np.std(torque)))
        rows["theta_m"].append(float(np.mean(run["theta_m"][window])))
    order = np.argsort(rows["omega_set"])
    return {name: np.asarray(values)[order] for name, values in rows.items()}


def coulomb_viscous_fit(table: dict[str, np.ndarray]) -> dict[str, float]:
    """Least squares of |torque| = F_c + b·|ω| per direction: the Coulomb level and the viscous slope."""
    out: dict[str, float] = {}
    for sign, name in ((1.0, "pos"), (-1.0, "neg")):
        pick = np.sign(table["omega_set"]) == sign
        if np.count_nonzero(pick) >= 2:
            slope, level = np.polyfit(np.abs(table["omega_m"][pick]), np.abs(table["torque_nm"][pick]), 1)
            out[f"coulomb_{name}_nm"] = float(level)
            out[f"viscous_{name}_nm_s_rad"] = float(slope)
    return out


class SpeedSweep(Experiment):
    name = "speed-sweep"
    summary = "steady speeds both ways; friction torque against velocity from the current"
    Params = SpeedSweepParams
    needs = frozenset({ControlMode.VELOCITY})

    def program(self, params: SpeedSweepParams, ctx: RigContext) -> list[Segment]:
        return sweep_program(params, ctx)

    def analyze(self, run: Run, params: SpeedSweepParams, ctx: RigContext) -> Results:
        table = friction_table(run, ctx, params.settle_s)
        metrics: dict[str, float | int | str] = {"speeds": len(params.speeds_rad_s)}
        metrics.update(coulomb_viscous_fit(table))
        return Results(metrics, {"friction_vs_velocity": table})

    def plot(
        self, run: Run, results: Results, params: SpeedSweepParams, ctx: RigContext, out_dir: Path
    ) -> list[Path]:
        table = results.tables["friction_vs_velocity"]
        fig, ax = new_figure("Friction torque against motor speed (speed sweep)")
        ax.errorbar(table["omega_m"], table["torque_nm"], yerr=table["torque_std"], fmt="o-", capsize=3)
        ax.set_xscale("symlog", linthresh=1.0)
        ax.set_xlabel("motor speed ω_m [rad/s]")
        ax.set_ylabel("motor torque K_m·i_a [N·m]")
        ax.axhline(0.0, color="0.6", lw=0.8)
        return [save_figure(fig, out_dir / "friction_vs_velocity.png")]
