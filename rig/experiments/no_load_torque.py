"""`no-load-torque`: the catalog's no-load running torque. Unloaded, the input runs at each speed in
turn, forward then backward, and the torque it takes is read once steady: the input transducer's `tau_in`
where the bench has one, else K_m·i_a. Every speed is measured at the same place, as the speed sweep
measures it (`rig.experiments.speed_sweep.same_place_program`: passes across the same whole input turns
about one centre, the smooth part at the centre fitted beside the per-turn ripple), so a friction that
depends on the input's position reads the same in every speed's figure and the curve is speed alone.
Where the run records the gear's temperature, each point carries its mean temperature, so runs at
several temperatures group by it (the catalog gives the curves from −10 to +40 °C).
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
    Results,
    RigContext,
    segment_rows,
)
from rig.experiments.plots import new_figure, save_figure
from rig.experiments.speed_sweep import SpeedSweepParams, same_place_program, same_place_table, sweep_centre
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
    # Bounds: the speed sweep's, whose same-place passes this runs.
    settle_s: float = Field(default=0.5, gt=0, le=10, description="time to reach steady speed [s]")
    hold_s: float = Field(
        default=1.0,
        gt=0,
        le=60,
        description="averaging time per speed and direction, as whole input turns about one centre [s]",
    )


def sweep_of(params: NoLoadTorqueParams) -> SpeedSweepParams:
    """The same-place passes of the speed sweep at these speeds, settle and hold, unloaded."""
    return SpeedSweepParams(speeds_rad_s=params.speeds_rad_s, settle_s=params.settle_s, hold_s=params.hold_s)


def input_torque(run: Run, ctx: RigContext) -> np.ndarray:
    """The torque the input delivers: the input transducer's, else the motor's K_m·i_a [N·m]."""
    return run["tau_in"] if "tau_in" in run else ctx.torque_constant_nm_per_a * run["i_a"]


class NoLoadTorque(Experiment):
    name = NAME
    summary = "no-load running torque at the input against input speed, both directions (and temperature)"
    Params = NoLoadTorqueParams
    needs = frozenset({ControlMode.VELOCITY})

    def program(self, params: NoLoadTorqueParams, ctx: RigContext) -> list[Segment]:
        return same_place_program(sweep_of(params), ctx, experiment=NAME)

    def analyze(self, run: Run, params: NoLoadTorqueParams, ctx: RigContext) -> Results:
        sweep = sweep_of(params)
        passes = same_place_table(run, sweep, ctx, torque=input_torque(run, ctx))
        settle = ctx.cycles(params.settle_s)
        table: dict[str, list[float]] = {"speed_rad_s": [], "torque_fwd_nm": [], "torque_bwd_nm": []}
        if "temp_gear" in run:
            table["temp_gear_c"] = []
        for speed in sorted(params.speeds_rad_s):
            table["speed_rad_s"].append(speed)
            for sign, way in ((1.0, "fwd"), (-1.0, "bwd")):
                (at,) = np.flatnonzero(passes["omega_set"] == sign * speed)
                table[f"torque_{way}_nm"].append(float(passes["torque_nm"][at]))
            if "temp_gear" in run:
                rows = [segment_rows(run, f"v{sign * speed:+g}") for sign in (1.0, -1.0)]
                temps = [np.mean(run["temp_gear"][w.start + settle : w.stop]) for w in rows]
                table["temp_gear_c"].append(float(np.mean(temps)))
        arrays = {k: np.asarray(v) for k, v in table.items()}
        magnitude = 0.5 * (arrays["torque_fwd_nm"] - arrays["torque_bwd_nm"])
        metrics: dict[str, float | int | str] = {
            "no_load_torque_min_speed_nm": float(magnitude[0]),
            "no_load_torque_max_speed_nm": float(magnitude[-1]),
            "centre_rad": sweep_centre(sweep, ctx),
            "source": "tau_in" if "tau_in" in run else "K_m·i_a",
        }
        if "temp_gear_c" in arrays:
            metrics["temp_gear_c"] = float(np.mean(arrays["temp_gear_c"]))
        notes = [
            f"every speed's torque at one place, input angle θ_m = {metrics['centre_rad']:.6g} rad: the"
            " smooth part over whole input turns about it, fitted beside the per-turn ripple"
        ]
        return Results(metrics=metrics, tables={"no_load_torque": arrays}, notes=notes)

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
