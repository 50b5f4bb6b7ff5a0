"""`pulse`: open-loop voltage pulses of alternating polarity, as the article applied pulse inputs.

Each pulse applies `amp_v` for `width_s`, then 0 V (the drive's bridge shorts the winding: back-EMF
braking plus friction stop the motor) until the next pulse. Alternating signs bring the motor back near
its start. Per pulse the analysis reads how far and how fast the motor went, how long it took to start
(breakaway) and to stop.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pydantic import Field, model_validator

from model.run import Run
from rig.experiments.base import Experiment, ExperimentParams, Results, RigContext, segment_rows
from rig.experiments.plots import new_figure, save_figure
from rig.interface import ControlMode, Segment


class PulseParams(ExperimentParams):
    amp_v: float = Field(
        default=2.0,
        gt=0,
        le=100,
        description="pulse voltage; the current starts near amp_v/R: keep that under the current trip [V]",
    )
    width_s: float = Field(default=0.05, gt=0, le=5, description="time each pulse is on [s]")
    period_s: float = Field(
        default=0.5,
        gt=0,
        le=20,
        description="time from one pulse's start to the next's; the rest stops it [s]",
    )
    count: int = Field(default=8, ge=1, le=200, description="pulses, alternating +, −, +... [–]")
    move_threshold_rad: float = Field(
        default=1e-3, gt=0, le=1, description="motor displacement that counts as moving (breakaway) [rad]"
    )
    rest_speed_rad_s: float = Field(
        default=0.1, gt=0, le=10, description="motor speed below which the motor counts as stopped [rad/s]"
    )

    @model_validator(mode="after")
    def _rest_after_pulse(self) -> PulseParams:
        if self.width_s >= self.period_s:
            raise ValueError(f"width_s ({self.width_s} s) must be shorter than period_s ({self.period_s} s)")
        return self


def pulse_labels(index: int) -> tuple[str, str]:
    """Labels of pulse `index` (from 0) and the rest after it; odd pulses are negative."""
    sign = "-" if index % 2 else "+"
    return f"pulse{index + 1}{sign}", f"rest{index + 1}"


def pulse_table(run: Run, params: PulseParams, ctx: RigContext) -> dict[str, np.ndarray]:
    """Per pulse: start time, polarity, displacement, peaks, breakaway delay, stop time, rest check."""
    t, theta, omega, current = run["t"], run["theta_m"], run["omega_m"], run["i_a"]
    columns = (
        "t_start",
        "polarity",
        "displacement_rad",
        "peak_speed_rad_s",
        "peak_current_a",
        "breakaway_s",
        "stop_s",
        "at_rest",
    )
    rows: dict[str, list[float]] = {name: [] for name in columns}
    for index in range(params.count):
        pulse_label, rest_label = pulse_labels(index)
        on, off = segment_rows(run, pulse_label), segment_rows(run, rest_label)
        whole = slice(on.start, off.stop)
        theta0 = theta[on.start]
        moved = np.flatnonzero(np.abs(theta[whole] - theta0) > params.move_threshold_rad)
        moving_after = np.flatnonzero(np.abs(omega[off]) > params.rest_speed_rad_s)
        at_rest = abs(omega[off.stop - 1]) <= params.rest_speed_rad_s
        stop_s = 0.0 if not len(moving_after) else (moving_after[-1] + 1) / ctx.rate_hz
        peak_speed = int(np.argmax(np.abs(omega[whole])))
        peak_current = int(np.argmax(np.abs(current[on])))
        rows["t_start"].append(float(t[on.start]))
        rows["polarity"].append(-1.0 if index % 2 else 1.0)
        rows["displacement_rad"].append(float(theta[off.stop - 1] - theta0))
        rows["peak_speed_rad_s"].append(float(omega[whole][peak_speed]))
        rows["peak_current_a"].append(float(current[on][peak_current]))
        rows["breakaway_s"].append(float(moved[0]) / ctx.rate_hz if len(moved) else np.nan)
        rows["stop_s"].append(stop_s if at_rest else np.nan)
        rows["at_rest"].append(float(at_rest))
    return {name: np.asarray(values) for name, values in rows.items()}


class Pulse(Experiment):
    name = "pulse"
    summary = "open-loop voltage pulses both ways; displacement, peak speed, breakaway and stop per pulse"
    Params = PulseParams
    needs = frozenset({ControlMode.VOLTAGE})

    def program(self, params: PulseParams, ctx: RigContext) -> list[Segment]:
        on, rest = ctx.cycles(params.width_s), ctx.cycles(params.period_s - params.width_s)
        segments = []
        for index in range(params.count):
            pulse_label, rest_label = pulse_labels(index)
            volts = -params.amp_v if index % 2 else params.amp_v
            segments.append(Segment(ControlMode.VOLTAGE, np.full(on, volts), 0.0, pulse_label))
            segments.append(Segment(ControlMode.VOLTAGE, np.zeros(rest), 0.0, rest_label))
        return segments

    def analyze(self, run: Run, params: PulseParams, ctx: RigContext) -> Results:
        table = pulse_table(run, params, ctx)
        distance = np.abs(table["displacement_rad"])
        forward = table["polarity"] > 0
        moved = ~np.isnan(table["breakaway_s"])
        rested = table["at_rest"] > 0
        metrics: dict[str, float | int | str] = {
            "pulses": params.count,
            "mean_displacement_rad": float(np.mean(distance)),
            "displacement_spread_rad": float(np.std(distance)),
            "mean_displacement_pos_rad": float(np.mean(distance[forward])),
            "mean_peak_speed_rad_s": float(np.mean(np.abs(table["peak_speed_rad_s"]))),
            "mean_peak_current_a": float(np.mean(np.abs(table["peak_current_a"]))),
            "net_drift_rad": float(np.sum(table["displacement_rad"])),
            "pulses_not_moving": int(np.count_nonzero(~moved)),
            "pulses_not_at_rest": int(np.count_nonzero(~rested)),
        }
        if np.any(~forward):
            metrics["mean_displacement_neg_rad"] = float(np.mean(distance[~forward]))
        if np.any(moved):
            metrics["mean_breakaway_s"] = float(np.mean(table["breakaway_s"][moved]))
        if np.any(rested):
            metrics["mean_stop_s"] = float(np.mean(table["stop_s"][rested]))
        notes = []
        if not np.all(rested):
            notes.append(
                f"{np.count_nonzero(~rested)} pulse(s) still moving when the next began: lengthen period_s"
            )
        if not np.all(moved):
            notes.append(f"{np.count_nonzero(~moved)} pulse(s) did not break away: raise amp_v or width_s")
        return Results(metrics, {"pulses": table}, notes)

    def plot(
        self, run: Run, results: Results, params: PulseParams, ctx: RigContext, out_dir: Path
    ) -> list[Path]:
        fig, _ = new_figure(f"Voltage pulses of ±{params.amp_v:g} V, {params.width_s * 1e3:g} ms", rows=3)
        t = run["t"]
        traces = (
            ("theta_m", "motor position θ_m [rad]"),
            ("omega_m", "motor speed ω_m [rad/s]"),
            ("i_a", "motor current i_a [A]"),
        )
        table = results.tables["pulses"]
        for ax, (column, label) in zip(fig.axes, traces, strict=True):
            ax.plot(t, run[column], lw=0.8)
            ax.set_ylabel(label)
            for start, polarity in zip(table["t_start"], table["polarity"], strict=True):
                ax.axvspan(start, start + params.width_s, color="C1" if polarity > 0 else "C2", alpha=0.25)
        fig.axes[-1].set_xlabel("time t [s] (pulses shaded: orange +, green −)")
        return [save_figure(fig, out_dir / "pulse_response.png")]
