"""`starting-torque`: the catalog's no-load starting and back-driving torques.

Starting torque (at the input): from rest and unloaded, the input is asked for a slow speed in velocity
mode; the drive's speed loop raises the torque steadily (its integral) until the gear breaks away. The
torque at the row where the input has moved `moved_rad` is read from a straight line fitted to the input
torque over the whole stuck stretch before it, so the transducer's noise averages out and is no peak (each
direction; the metric is their mean magnitude).

Back-driving torque (at the output): the input is left free (no current) and the load drive ramps the
output torque up slowly; the output torque at which the input starts to turn (its encoder moves
by `moved_rad`) is the torque that back-drives the gear. That half needs a load drive.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pydantic import Field

from model.run import Run
from rig.experiments.base import (
    LOAD_MAX_NM,
    Experiment,
    ExperimentParams,
    Results,
    RigContext,
    segment_rows,
)
from rig.experiments.load_side import require_bench
from rig.experiments.no_load_torque import input_torque
from rig.experiments.plots import new_figure, save_figure
from rig.interface import ControlMode, Segment

NAME = "starting-torque"


class StartingTorqueParams(ExperimentParams):
    start_speed_rad_s: float = Field(
        default=0.1, gt=0, le=50, description="the slow input speed asked [rad/s]"
    )
    window_s: float = Field(
        default=1.5, gt=0, le=60, description="time from rest in which the input must start [s]"
    )
    back_drive_max_nm: float = Field(
        default=12.0,
        gt=0,
        le=LOAD_MAX_NM,
        description="the output torque the back-driving ramp reaches [N·m]",
    )
    ramp_s: float = Field(default=5.0, gt=0, le=600, description="time of the back-driving ramp [s]")
    moved_rad: float = Field(
        default=2e-4, gt=0, description="input travel that tells the input has started to turn [rad]"
    )


class StartingTorque(Experiment):
    name = NAME
    summary = "no-load starting torque at the input and back-driving torque at the output"
    Params = StartingTorqueParams
    needs = frozenset({ControlMode.VELOCITY, ControlMode.CURRENT})

    def program(self, params: StartingTorqueParams, ctx: RigContext) -> list[Segment]:
        require_bench(NAME, ctx.config, load_drive=True, transducers=False)
        window = ctx.cycles(params.window_s)
        rest = ctx.cycles(0.3)
        ramp = ctx.cycles(params.ramp_s)
        # The back-driving ramp drops to zero quickly once at its top, so the free input, once turning,
        # is not driven up to the rig's speed trip.
        drop = ctx.cycles(0.2)
        load = np.concatenate(
            [
                np.linspace(0.0, -params.back_drive_max_nm, ramp),
                np.linspace(-params.back_drive_max_nm, 0.0, drop),
            ]
        )
        return [
            Segment(ControlMode.VELOCITY, np.zeros(rest), 0.0, "rest-fwd"),
            Segment(ControlMode.VELOCITY, np.full(window, params.start_speed_rad_s), 0.0, "start-fwd"),
            Segment(ControlMode.VELOCITY, np.zeros(rest), 0.0, "rest-bwd"),
            Segment(ControlMode.VELOCITY, np.full(window, -params.start_speed_rad_s), 0.0, "start-bwd"),
            Segment(ControlMode.VELOCITY, np.zeros(rest), 0.0, "rest-back"),
            Segment(ControlMode.CURRENT, np.zeros(ramp + drop), load, "back-drive"),
            Segment(ControlMode.CURRENT, np.zeros(ctx.cycles(1.5)), 0.0, "coast"),
        ]

    def back_drive(self, run: Run, params: StartingTorqueParams) -> tuple[np.ndarray, np.ndarray, int | None]:
        """Output torque [N·m] and input travel [rad] over the ramp, and the row where the input moved."""
        rows = segment_rows(run, "back-drive")
        torque = -(run["tau_out"][rows] if "tau_out" in run else run["tau_ext"][rows])
        travel = np.abs(run["theta_m"][rows] - run["theta_m"][rows.start])
        moved = np.flatnonzero(travel > params.moved_rad)
        return torque, travel, int(moved[0]) if moved.size else None

    def analyze(self, run: Run, params: StartingTorqueParams, ctx: RigContext) -> Results:
        torque = input_torque(run, ctx)
        notes = []
        start = {}
        for way, sign in (("fwd", 1.0), ("bwd", -1.0)):
            rows = segment_rows(run, f"start-{way}")
            travel = np.abs(run["theta_m"][rows] - run["theta_m"][rows.start])
            moved = np.flatnonzero(travel > params.moved_rad)
            if moved.size == 0 or moved[0] < 3:
                notes.append(f"the input did not start {way} within window_s: no starting torque that way")
                continue
            k = int(moved[0])
            slope, intercept = np.polyfit(np.arange(k), torque[rows][:k], 1)
            start[way] = sign * float(slope * k + intercept)
        metrics: dict[str, float | int | str] = {f"starting_torque_{w}_nm": v for w, v in start.items()}
        if start:
            metrics["starting_torque_nm"] = float(np.mean(list(start.values())))
        out, _, turned = self.back_drive(run, params)
        if turned is None:
            notes.append(
                f"the input did not turn under {params.back_drive_max_nm:g} N·m at the output:"
                " raise back_drive_max_nm"
            )
        else:
            metrics["back_driving_torque_nm"] = float(out[turned])
        return Results(metrics=metrics, notes=notes)

    def plot(
        self, run: Run, results: Results, params: StartingTorqueParams, ctx: RigContext, out_dir: Path
    ) -> list[Path]:
        out, travel, _ = self.back_drive(run, params)
        fig, ax = new_figure("back-driving: input travel against output torque")
        ax.plot(out, travel, lw=0.8)
        ax.set_xlabel("output torque [N·m]")
        ax.set_ylabel("input travel [rad]")
        return [save_figure(fig, out_dir / "starting_torque.png")]
