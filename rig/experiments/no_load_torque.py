"""`no-load-torque`: the catalog's no-load running torque. Unloaded, the input runs at each speed in
turn, forward then backward (so the output comes back), and the torque it takes is averaged once steady:
the input transducer's `tau_in` where the bench has one, else K_m·i_a. Where the run records the gear's
temperature, each point carries its mean temperature, so runs at several temperatures group by it
(the catalog gives the curves from −10 to +40 °C).
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import numpy as np
from pydantic import Field

from model.run import Run
from rig.experiments.base import (
    LIST_MAX,
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

NAME = "no-load-torque"


class NoLoadTorqueParams(ExperimentParams):
    # Defaults: the catalog's 500 to 3000 rpm input range, as rad/s (52 to 314).
    speeds_rad_s: list[Annotated[float, Field(gt=0, le=SPEED_MAX_RAD_S)]] = Field(
        default=[50.0, 100.0, 200.0, 300.0],
        min_length=1,
        max_length=LIST_MAX,
        description="input speeds [rad/s]",
    )
    settle_s: float = Field(default=0.5, gt=0, le=60, description="time to reach steady speed [s]")
    hold_s: float = Field(default=1.0, gt=0, le=600, description="averaging time per speed and direction [s]")


def input_torque(run: Run, ctx: RigContext) -> np.ndarray:
    """The torque the input delivers: the input transducer's, else the motor's K_m·i_a [N·m]."""
    return run["tau_in"] if "tau_in" in run else ctx.torque_constant_nm_per_a * run["i_a"]


class NoLoadTorque(Experiment):
    name = NAME
    summary = "no-load running torque at the input against input speed, both directions (and temperature)"
    Params = NoLoadTorqueParams
    needs = frozenset({ControlMode.VELOCITY})

    def program(self, params: NoLoadTorqueParams, ctx: RigContext) -> list[Segment]:
        cycles = ctx.cycles(params.settle_s + params.hold_s)
        reach_out = ctx.gear_ratio * max(params.speeds_rad_s) * (params.settle_s + params.hold_s)
        limits = ctx.config.limits
        if ctx.gear_ratio * ctx.theta_m0 + reach_out > limits.travel_max_out_rad:
            raise ProgramError(
                f"{NAME}: a pass at {max(params.speeds_rad_s):g} rad/s turns the output {reach_out:.3g} rad,"
                f" past rig {ctx.config.name!r}'s travel limit: shorten hold_s or use a bench such as"
                " sim-dyno"
            )
        program = []
        for speed in sorted(params.speeds_rad_s):
            for sign, way in ((1.0, "fwd"), (-1.0, "bwd")):
                program.append(
                    Segment(ControlMode.VELOCITY, np.full(cycles, sign * speed), 0.0, f"{way}{speed:g}")
                )
        program.append(Segment(ControlMode.VELOCITY, np.zeros(ctx.cycles(0.5)), 0.0, "stop"))
        return program

    def analyze(self, run: Run, params: NoLoadTorqueParams, ctx: RigContext) -> Results:
        settle = ctx.cycles(params.settle_s)
        torque = input_torque(run, ctx)
        table: dict[str, list[float]] = {"speed_rad_s": [], "torque_fwd_nm": [], "torque_bwd_nm": []}
        if "temp_gear" in run:
            table["temp_gear_c"] = []
        for speed in sorted(params.speeds_rad_s):
            table["speed_rad_s"].append(speed)
            temps = []
            for way in ("fwd", "bwd"):
                rows = segment_rows(run, f"{way}{speed:g}")
                w = slice(rows.start + settle, rows.stop)
                table[f"torque_{way}_nm"].append(float(np.mean(torque[w])))
                if "temp_gear" in run:
                    temps.append(float(np.mean(run["temp_gear"][w])))
            if temps:
                table["temp_gear_c"].append(float(np.mean(temps)))
        arrays = {k: np.asarray(v) for k, v in table.items()}
        magnitude = 0.5 * (arrays["torque_fwd_nm"] - arrays["torque_bwd_nm"])
        metrics: dict[str, float | int | str] = {
            "no_load_torque_min_speed_nm": float(magnitude[0]),
            "no_load_torque_max_speed_nm": float(magnitude[-1]),
            "source": "tau_in" if "tau_in" in run else "K_m·i_a",
        }
        if "temp_gear_c" in arrays:
            metrics["temp_gear_c"] = float(np.mean(arrays["temp_gear_c"]))
        return Results(metrics=metrics, tables={"no_load_torque": arrays})

    def plot(
        self, run: Run, results: Results, params: NoLoadTorqueParams, ctx: RigContext, out_dir: Path
    ) -> list[Path]:
        t = results.tables["no_load_torque"]
        fig, ax = new_figure("no-load running torque at the input")
        ax.plot(t["speed_rad_s"], t["torque_fwd_nm"], "o-", label="forward")
        ax.plot(t["speed_rad_s"], -np.asarray(t["torque_bwd_nm"]), "s-", label="backward (magnitude)")
        ax.set_xlabel("input speed [rad/s]")
        ax.set_ylabel("running torque [N·m]")
        ax.legend()
        return [save_figure(fig, out_dir / "no_load_torque.png")]
