"""`efficiency-map`: the gear's efficiency over a grid of input speeds and output load torques.

At each grid point the input runs at a set speed in velocity mode while the load drive brakes the output
with the load torque; after `settle_s` the transducers' torques and the encoders' angles are read for
`hold_s`: η = P_out / P_in = τ̄_out·ω̄_l / (τ̄_in·ω̄_m), the speeds from the angles travelled over the window.
Its uncertainty: the hold is cut into `blocks` parts, η is worked out in each, and σ is their spread over
√blocks (the transducers' noise and the ripple of the kinematic error both show in it).
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import numpy as np
from pydantic import Field

from model.run import Run
from rig.experiments.base import (
    LIST_MAX,
    LOAD_MAX_NM,
    SPEED_MAX_RAD_S,
    Experiment,
    ExperimentParams,
    Results,
    RigContext,
    segment_rows,
)
from rig.experiments.load_side import require_bench, require_columns
from rig.experiments.plots import new_figure, save_figure
from rig.interface import ControlMode, Segment

NAME = "efficiency-map"


class EfficiencyMapParams(ExperimentParams):
    # Defaults span the catalog's efficiency curves (input 500 to 3000 rpm, loads to near the rated torque
    # of a size-25 gear) within what the sim-dyno motor gives (40 A · K_m / r ≈ 120 N·m less friction).
    speeds_rad_s: list[Annotated[float, Field(gt=0, le=SPEED_MAX_RAD_S)]] = Field(
        default=[50.0, 150.0, 300.0],
        min_length=1,
        max_length=LIST_MAX,
        description="input (motor) speeds [rad/s]",
    )
    loads_nm: list[Annotated[float, Field(gt=0, le=LOAD_MAX_NM)]] = Field(
        default=[10.0, 20.0, 40.0, 60.0],
        min_length=1,
        max_length=LIST_MAX,
        description="output load torques [N·m]",
    )
    settle_s: float = Field(default=0.6, gt=0, le=60, description="time to reach steady speed and load [s]")
    hold_s: float = Field(default=1.0, gt=0, le=600, description="averaging time per grid point [s]")
    blocks: int = Field(default=5, ge=2, le=100, description="parts of the hold for η's uncertainty [–]")


def point_label(i: int, j: int) -> str:
    return f"w{i}/tau{j}"


def efficiency_window(
    tau_in: np.ndarray, tau_out: np.ndarray, theta_m: np.ndarray, theta_l: np.ndarray
) -> tuple[float, float, float]:
    """P_in [W], P_out [W] over a window of samples at a constant period (per sample: the angle travelled
    over the window's length in samples, so the period cancels in η and is put back by the caller)."""
    n = theta_m.shape[0] - 1
    omega_m = (theta_m[-1] - theta_m[0]) / n
    omega_l = (theta_l[-1] - theta_l[0]) / n
    p_in = float(np.mean(tau_in) * omega_m)
    p_out = float(np.mean(tau_out) * omega_l)
    return p_in, p_out, p_out / p_in


class EfficiencyMap(Experiment):
    name = NAME
    summary = "η = P_out/P_in from the torque transducers over a grid of input speeds × output loads"
    Params = EfficiencyMapParams
    needs = frozenset({ControlMode.VELOCITY})

    def program(self, params: EfficiencyMapParams, ctx: RigContext) -> list[Segment]:
        require_bench(NAME, ctx.config, load_drive=True, transducers=True)
        cycles = ctx.cycles(params.settle_s + params.hold_s)
        program = []
        for i, speed in enumerate(sorted(params.speeds_rad_s)):
            for j, load in enumerate(sorted(params.loads_nm)):
                program.append(Segment(ControlMode.VELOCITY, np.full(cycles, speed), load, point_label(i, j)))
        # Unload, then stop: the load drive never brakes a stopped input nor drives a free one.
        stop = ctx.cycles(0.5)
        program.append(
            Segment(ControlMode.VELOCITY, np.full(stop, sorted(params.speeds_rad_s)[-1]), 0.0, "unload")
        )
        program.append(Segment(ControlMode.VELOCITY, np.zeros(stop), 0.0, "stop"))
        return program

    def analyze(self, run: Run, params: EfficiencyMapParams, ctx: RigContext) -> Results:
        require_columns(NAME, run, ("tau_in", "tau_out"))
        settle = ctx.cycles(params.settle_s)
        rate = ctx.rate_hz
        notes_: list[str] = []
        rows: dict[str, list[float]] = {
            k: [] for k in ("speed_rad_s", "load_nm", "p_in_w", "p_out_w", "eta", "eta_sigma")
        }
        for i, speed in enumerate(sorted(params.speeds_rad_s)):
            for j, load in enumerate(sorted(params.loads_nm)):
                rows_ = segment_rows(run, point_label(i, j))
                w = slice(rows_.start + settle, rows_.stop)
                tin, tout, tm, tl = (run[c][w] for c in ("tau_in", "tau_out", "theta_m", "theta_l"))
                held = (tm[-1] - tm[0]) / (tm.shape[0] - 1) * rate
                if not held > 0.5 * speed:
                    # The input could not carry this load at this speed (its current saturated): no power
                    # flows through, so no efficiency; said, and the rest of the map kept.
                    notes_.append(
                        f"{speed:g} rad/s with {load:g} N·m: the input held {held:.3g} rad/s, not its speed"
                        " (current saturated?): η not measured"
                    )
                    for key, value in (("speed_rad_s", speed), ("load_nm", load)):
                        rows[key].append(value)
                    for key in ("p_in_w", "p_out_w", "eta", "eta_sigma"):
                        rows[key].append(float("nan"))
                    continue
                p_in, p_out, eta = efficiency_window(tin, tout, tm, tl)
                parts = [
                    efficiency_window(a, b, c, d)[2]
                    for a, b, c, d in zip(
                        *(np.array_split(x, params.blocks) for x in (tin, tout, tm, tl)), strict=True
                    )
                ]
                rows["speed_rad_s"].append(speed)
                rows["load_nm"].append(load)
                rows["p_in_w"].append(p_in * rate)
                rows["p_out_w"].append(p_out * rate)
                rows["eta"].append(eta)
                rows["eta_sigma"].append(float(np.std(parts, ddof=1) / np.sqrt(params.blocks)))
        table = {k: np.asarray(v) for k, v in rows.items()}
        if np.all(np.isnan(table["eta"])):
            return Results(tables={"efficiency_map": table}, notes=notes_)
        best = int(np.nanargmax(table["eta"]))
        metrics: dict[str, float | int | str] = {
            "efficiency_max": float(table["eta"][best]),
            "efficiency_max_sigma": float(table["eta_sigma"][best]),
            "efficiency_max_speed_rad_s": float(table["speed_rad_s"][best]),
            "efficiency_max_load_nm": float(table["load_nm"][best]),
            "efficiency_min": float(np.nanmin(table["eta"])),
        }
        notes = [
            *notes_,
            f"η {table['eta'][best]:.3f} ± {table['eta_sigma'][best]:.3f} at best"
            f" ({table['speed_rad_s'][best]:g} rad/s input, {table['load_nm'][best]:g} N·m output)",
        ]
        return Results(metrics=metrics, tables={"efficiency_map": table}, notes=notes)

    def plot(
        self, run: Run, results: Results, params: EfficiencyMapParams, ctx: RigContext, out_dir: Path
    ) -> list[Path]:
        table = results.tables["efficiency_map"]
        speeds = sorted(params.speeds_rad_s)
        loads = sorted(params.loads_nm)
        eta = np.asarray(table["eta"]).reshape(len(speeds), len(loads)) * 100
        fig, ax = new_figure("efficiency map η = P_out / P_in [%]")
        if len(speeds) > 1 and len(loads) > 1:
            contour = ax.contourf(loads, speeds, eta, levels=12, cmap="viridis")
            fig.colorbar(contour, ax=ax, label="η [%]")
            ax.set_ylabel("input speed [rad/s]")
        else:
            ax.plot(loads if len(loads) > 1 else speeds, eta.ravel(), "o-")
            ax.set_ylabel("η [%]")
        ax.set_xlabel("output load torque [N·m]" if len(loads) > 1 else "input speed [rad/s]")
        return [save_figure(fig, out_dir / "efficiency_map.png")]
