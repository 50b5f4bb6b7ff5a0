"""`load-variation`: the speed sweep repeated under several external load torques τ_ext at the output.

At constant speed docs/MODEL.md gives T_m = F_m + r·(τ_ext + F_l): the motor carries the load through the
gear as well as friction. The friction part is therefore K_m·i_a − r·τ_ext. With friction that does not
depend on the transmitted torque it is the same at every load; a level growing with |τ_ext| is the
signature of `load_dependent_friction` (c_Ts·|T_s| on the motor, T_s ≈ τ_ext at the output).

Each load's sweep is the speed sweep's same-place sweep (`same_place_program`): every speed at every load
is measured over whole motor turns about the same centre, so position-dependent friction is the same in
every figure and a change of level is load, not place. The level is the mean over the speeds at which
the output moved steadily along (where the kinematic error makes it stick or run back at low speed, the
load's friction averages to anything).
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
    Results,
    RigContext,
)
from rig.experiments.plots import new_figure, save_figure
from rig.experiments.speed_sweep import (
    SpeedSweepParams,
    coulomb_viscous_fit,
    same_place_program,
    same_place_table,
    sweep_centre,
)
from rig.interface import ControlMode, Segment


class LoadVariationParams(ExperimentParams):
    # Up to half the sim rig's 30 N·m at the output (10 A · K_m / r): friction, acceleration and the
    # torque ripple at speed need the rest, and a saturated velocity loop would bias the averages.
    loads_nm: list[float] = Field(
        default=[0.0, 5.0, 10.0, 15.0],
        max_length=LIST_MAX,
        description="external load torques τ_ext at the output, one sweep each, run in rising order [N·m]",
    )
    speeds_rad_s: list[Annotated[float, Field(gt=0, le=SPEED_MAX_RAD_S)]] = Field(
        default=[1.0, 5.0, 20.0, 100.0],
        max_length=LIST_MAX,
        description="motor speed magnitudes of each sweep; each is run forward and backward [rad/s]",
    )
    settle_s: float = Field(
        default=0.3, gt=0, le=10, description="time to reach steady speed, not averaged [s]"
    )
    hold_s: float = Field(
        default=0.7,
        gt=0,
        le=60,
        description="averaging time per speed and direction, as whole motor turns about the sweep's centre"
        " (the speed sweep's) [s]",
    )
    travel_fraction: float = Field(
        default=0.8, gt=0, le=1, description="share of the free stroke ahead a pass may use [–]"
    )
    ramp_s: float = Field(
        default=0.3,
        gt=0,
        le=10,
        description="time to change the load at standstill between sweeps, slow beside the load mode [s]",
    )

    @field_validator("loads_nm")
    @classmethod
    def _distinct_loads(cls, loads: list[float]) -> list[float]:
        if not loads:
            raise ValueError("needs one or more load torques")
        if len(set(loads)) != len(loads):
            raise ValueError("load torques must be distinct")
        if any(abs(tau) > LOAD_MAX_NM for tau in loads):
            raise ValueError(f"load torques must be within ±{LOAD_MAX_NM:g} N·m")
        return sorted(loads)

    @field_validator("speeds_rad_s")
    @classmethod
    def _positive_speeds(cls, speeds: list[float], info: ValidationInfo) -> list[float]:
        return SpeedSweepParams._positive_speeds(speeds, info)  # the sweep's own rule, one copy

    def sweep(self, tau_ext_nm: float) -> SpeedSweepParams:
        """The speed sweep run at one load."""
        return SpeedSweepParams(
            speeds_rad_s=self.speeds_rad_s,
            settle_s=self.settle_s,
            hold_s=self.hold_s,
            travel_fraction=self.travel_fraction,
            tau_ext_nm=tau_ext_nm,
        )


def load_prefix(tau_ext_nm: float) -> str:
    """Segment label prefix of the sweep at one load; the slash keeps `tau1/` apart from `tau10/`."""
    return f"tau{tau_ext_nm:g}/"


def load_ramp(ctx: RigContext, start_nm: float, end_nm: float, duration_s: float, label: str) -> Segment:
    """Hold the start position while the load torque moves linearly from start to end.

    Holding position (not speed) also brings the motor back to where the program began, so every
    load's sweep passes over the same positions and position-dependent friction compares like for like.
    """
    cycles = ctx.cycles(duration_s)
    hold = np.full(cycles, ctx.theta_m0)
    return Segment(ControlMode.POSITION, hold, np.linspace(start_nm, end_nm, cycles), label)


class LoadVariation(Experiment):
    name = "load-variation"
    summary = "the speed sweep under several external loads; friction level against load"
    Params = LoadVariationParams
    needs = frozenset({ControlMode.POSITION})

    def program(self, params: LoadVariationParams, ctx: RigContext) -> list[Segment]:
        segments = []
        previous = 0.0
        for tau in params.loads_nm:
            prefix = load_prefix(tau)
            # Changing the load at standstill, slowly, keeps the load mode's ringing out of the sweep.
            segments.append(load_ramp(ctx, previous, tau, params.ramp_s, prefix + "ramp"))
            segments += same_place_program(params.sweep(tau), ctx, prefix=prefix)
            previous = tau
        # Unload before the drive is disabled: a bench's load actuator must not back-drive a free arm.
        segments.append(load_ramp(ctx, previous, 0.0, params.ramp_s, "unload"))
        return segments

    def analyze(self, run: Run, params: LoadVariationParams, ctx: RigContext) -> Results:
        r = ctx.gear_ratio
        per_load = []
        levels: dict[str, list[float]] = {
            k: [] for k in ("tau_ext_nm", "level_nm", "level_pos_nm", "level_neg_nm", "viscous_nm_s_rad")
        }
        notes = []
        for tau in params.loads_nm:
            table = same_place_table(run, params.sweep(tau), ctx, prefix=load_prefix(tau))
            table["friction_nm"] = table["torque_nm"] - r * tau
            table["tau_ext_nm"] = np.full(len(table["omega_set"]), tau)
            per_load.append(table)
            steady = table["load_steady"] > 0.5
            if not np.any(steady & (table["omega_set"] > 0)) or not np.any(steady & (table["omega_set"] < 0)):
                notes.append(
                    f"τ_ext = {tau:g} N·m: no speed with the output moving steadily both ways; all used"
                )
                steady = np.ones_like(steady)
            friction = np.abs(table["friction_nm"])[steady]
            forward = table["omega_set"][steady] > 0
            fit = coulomb_viscous_fit(
                {name: column[steady] for name, column in table.items()}
                | {"torque_nm": table["friction_nm"][steady]}
            )
            levels["tau_ext_nm"].append(tau)
            levels["level_pos_nm"].append(float(np.mean(friction[forward])))
            levels["level_neg_nm"].append(float(np.mean(friction[~forward])))
            levels["level_nm"].append(float(np.mean(friction)))
            slopes = [fit[k] for k in ("viscous_pos_nm_s_rad", "viscous_neg_nm_s_rad") if k in fit]
            levels["viscous_nm_s_rad"].append(float(np.mean(slopes)) if slopes else float("nan"))
        columns = (
            "tau_ext_nm",
            "omega_set",
            "omega_m",
            "torque_nm",
            "friction_nm",
            "torque_std",
            "theta_m",
            "load_steady",
        )
        by_load = {name: np.concatenate([t[name] for t in per_load]) for name in columns}
        level_table = {name: np.asarray(values) for name, values in levels.items()}

        level = level_table["level_nm"]
        metrics: dict[str, float | int | str] = {
            "loads": len(params.loads_nm),
            "speeds": len(params.speeds_rad_s),
            "level_min_nm": float(level.min()),
            "level_max_nm": float(level.max()),
        }
        if len({abs(tau) for tau in params.loads_nm}) >= 2:
            # Motor-side friction per output torque: c_Ts of `load_dependent_friction` when |τ_ext| ≫ F_l.
            slope, intercept = np.polyfit(np.abs(level_table["tau_ext_nm"]), level, 1)
            metrics["friction_per_load_nm_per_nm"] = float(slope)
            metrics["level_at_no_load_nm"] = float(intercept)
        notes.append(
            "friction_nm = K_m·i_a − r·τ_ext (the load carried through the gear removed), each speed's at"
            f" θ_m = {sweep_centre(params.sweep(0.0), ctx):.4g} rad (the speed sweep's same place);"
            " level_nm = mean |friction_nm| over the speeds where the output moved steadily (load_steady)"
        )
        tables = {"friction_vs_velocity_by_load": by_load, "friction_level_by_load": level_table}
        return Results(metrics, tables, notes)

    def plot(
        self, run: Run, results: Results, params: LoadVariationParams, ctx: RigContext, out_dir: Path
    ) -> list[Path]:
        table = results.tables["friction_vs_velocity_by_load"]
        fig, ax = new_figure("Friction torque against motor speed, per external load", rows=2)
        for tau in params.loads_nm:
            pick = table["tau_ext_nm"] == tau
            ax.plot(
                table["omega_m"][pick], table["friction_nm"][pick], "o-", ms=4, label=f"τ_ext = {tau:g} N·m"
            )
        ax.set_xscale("symlog", linthresh=1.0)
        ax.set_xlabel("motor speed ω_m [rad/s]")
        ax.set_ylabel("friction K_m·i_a − r·τ_ext [N·m]")
        ax.axhline(0.0, color="0.6", lw=0.8)
        ax.legend()
        levels = results.tables["friction_level_by_load"]
        lower = fig.axes[1]
        lower.plot(levels["tau_ext_nm"], levels["level_pos_nm"], "o-", label="forward")
        lower.plot(levels["tau_ext_nm"], levels["level_neg_nm"], "s-", label="backward")
        lower.set_xlabel("external load τ_ext at the output [N·m]")
        lower.set_ylabel("mean |friction| over the speeds [N·m]")
        lower.set_ylim(bottom=0.0)  # the level against zero: a 1 % change must not look like a trend
        lower.legend()
        return [save_figure(fig, out_dir / "friction_vs_velocity_by_load.png")]
