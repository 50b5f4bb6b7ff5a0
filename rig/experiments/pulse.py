"""`pulse`: open-loop voltage pulses of alternating polarity, as the article applied pulse inputs.

Each pulse applies `amp_v` for `width_s`, then 0 V (the drive's bridge shorts the winding: back-EMF
braking plus friction stop the motor) until the next pulse. Alternating signs bring the motor back near
its start. Per pulse the analysis reads how far and how fast the motor went, how long it took to start
(breakaway) and to stop. Times and speeds are the encoder's (θ_m and its differences), not the drive's
filtered speed.

Then a staircase finds the breakaway level: pulses of `width_s` at amplitudes from `stair_low_v` to
`stair_high_v` in steps of `stair_step_v`, each amplitude once each way (+, then −, so the motor stays
near its start), each followed by `stair_rest_s` at 0 V. A stair "moved" when the encoder shows the
motor more than `move_threshold_rad` from where the stair began, before the next stair starts. At
standstill the winding's current is u/R (no back-EMF), so the lowest amplitude that moves is the
static friction level (plus what the transmission's twist adds) seen through K_m/R, bracketed by the
amplitude below it.

Metrics (all from the encoder θ_m):
- `mean_displacement_rad`, `displacement_spread_rad`, `mean_displacement_pos_rad`/`_neg_rad`: |θ_m at
  the end of the pulse's rest − θ_m at its start|, mean (and standard deviation) over the pulses, or over
  those of one sign; `net_drift_rad`: the signed sum.
- `mean_peak_speed_rad_s`: mean over the pulses of the largest |encoder speed| (five-point difference of
  θ_m) during the pulse and its rest.
- `mean_peak_current_a`: mean over the pulses of the largest |i_a| during the pulse.
- `mean_breakaway_s`: mean over the pulses that moved of the time from the pulse's first row until
  |θ_m − θ_m(first row)| first exceeds `move_threshold_rad`, interpolated linearly between samples.
- `mean_stop_s`: mean over the pulses at rest of the time from the rest's first row to the end of the
  last sample interval in which the encoder speed exceeded `rest_speed_rad_s`.
- `breakaway_pos_v`, `breakaway_neg_v`: the lowest staircase amplitude that moved the motor, per
  direction; `breakaway_pos_below_v`, `breakaway_neg_below_v`: the amplitude below it (did not move;
  0 when the lowest stair moved): the bracket (below, level]; `breakaway_pos_theta_m_rad`,
  `breakaway_neg_theta_m_rad`: θ_m at the start of that stair; `breakaway_v`: the mean of the two
  brackets' midpoints.
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
    stair_low_v: float = Field(default=0.70, ge=0, le=100, description="lowest staircase amplitude [V]")
    stair_high_v: float = Field(default=1.00, gt=0, le=100, description="highest staircase amplitude [V]")
    stair_step_v: float = Field(
        default=0.02, gt=0, le=10, description="staircase step: the breakaway bracket's width [V]"
    )
    stair_rest_s: float = Field(default=0.1, gt=0, le=20, description="0 V after each staircase pulse [s]")

    @model_validator(mode="after")
    def _rest_after_pulse(self) -> PulseParams:
        if self.width_s >= self.period_s:
            raise ValueError(f"width_s ({self.width_s} s) must be shorter than period_s ({self.period_s} s)")
        if self.stair_high_v < self.stair_low_v:
            raise ValueError(f"stair_high_v ({self.stair_high_v} V) must not be below stair_low_v")
        if self.stair_levels().size > 200:
            raise ValueError("stair_step_v: more than 200 staircase levels; take a larger step")
        return self

    def stair_levels(self) -> np.ndarray:
        """The staircase's amplitudes, low to high [V]."""
        count = int(np.floor((self.stair_high_v - self.stair_low_v) / self.stair_step_v + 1e-9)) + 1
        return np.asarray(self.stair_low_v + self.stair_step_v * np.arange(count))


def pulse_labels(index: int) -> tuple[str, str]:
    """Labels of pulse `index` (from 0) and the rest after it; odd pulses are negative."""
    sign = "-" if index % 2 else "+"
    return f"pulse{index + 1}{sign}", f"rest{index + 1}"


STAIR_PREFIX = "stair"
"""Every staircase segment's label starts with it (and no other's)."""


def stair_labels(level: int, sign: str) -> tuple[str, str]:
    """Labels of staircase level `level` (from 0) in direction sign ("+" or "-") and the rest after it."""
    return f"{STAIR_PREFIX}{level + 1}{sign}", f"{STAIR_PREFIX}-rest{level + 1}{sign}"


def encoder_speed(theta: np.ndarray, period_s: float) -> np.ndarray:
    """ω from the encoder's positions by the five-point stencil; central differences at the two rows of
    each end."""
    omega = np.gradient(theta, period_s) if theta.size > 1 else np.zeros_like(theta)
    omega[2:-2] = (8.0 * (theta[3:-1] - theta[1:-3]) - (theta[4:] - theta[:-4])) / (12.0 * period_s)
    return np.asarray(omega)


def crossing_s(distance: np.ndarray, threshold: float, rate_hz: float) -> float:
    """Time [s] from row 0 at which `distance` first exceeds `threshold` (linear between samples), or NaN."""
    over = np.flatnonzero(distance > threshold)
    if not over.size:
        return float("nan")
    k = int(over[0])
    if k == 0:
        return 0.0
    before, after = distance[k - 1], distance[k]
    return float((k - 1 + (threshold - before) / (after - before)) / rate_hz)


def stair_table(run: Run, params: PulseParams) -> dict[str, np.ndarray]:
    """Per staircase pulse: amplitude (signed) [V], θ_m at its start [rad], moved (1/0), travel [rad]."""
    theta = run["theta_m"]
    rows: dict[str, list[float]] = {"amp_v": [], "theta_m_rad": [], "moved": [], "travel_rad": []}
    for level, amp in enumerate(params.stair_levels()):
        for sign in ("+", "-"):
            on_label, rest_label = stair_labels(level, sign)
            on, off = segment_rows(run, on_label), segment_rows(run, rest_label)
            start = theta[on.start]
            travel = float(np.max(np.abs(theta[on.start : off.stop] - start)))
            rows["amp_v"].append(float(amp if sign == "+" else -amp))
            rows["theta_m_rad"].append(float(start))
            rows["moved"].append(float(travel > params.move_threshold_rad))
            rows["travel_rad"].append(travel)
    return {name: np.asarray(values) for name, values in rows.items()}


def breakaway(table: dict[str, np.ndarray], sign: float) -> tuple[float, float, float] | None:
    """(amplitude below, lowest amplitude that moved, θ_m there) of one direction, or None if none moved."""
    mine = np.flatnonzero(np.sign(table["amp_v"]) == sign)
    moved = mine[table["moved"][mine] > 0]
    if not moved.size:
        return None
    first = int(moved[0])
    level = abs(float(table["amp_v"][first]))
    before = mine[mine < first]
    below = abs(float(table["amp_v"][before[-1]])) if before.size else 0.0
    return below, level, float(table["theta_m_rad"][first])


def pulse_table(run: Run, params: PulseParams, ctx: RigContext) -> dict[str, np.ndarray]:
    """Per pulse: start time, polarity, displacement, peaks, breakaway delay, stop time, rest check.

    Speeds are the encoder's (`encoder_speed` of θ_m), times from the encoder's θ_m (module docstring)."""
    t, theta, current = run["t"], run["theta_m"], run["i_a"]
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
        # The pulse's own rows only: a stencil reaching into the next pulse would see it start.
        omega = np.zeros(theta.shape)
        omega[whole] = encoder_speed(theta[whole], 1.0 / ctx.rate_hz)
        theta0 = theta[on.start]
        breakaway_s = crossing_s(np.abs(theta[whole] - theta0), params.move_threshold_rad, ctx.rate_hz)
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
        rows["breakaway_s"].append(breakaway_s)
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
        stair_rest = ctx.cycles(params.stair_rest_s)
        for level, amp in enumerate(params.stair_levels()):
            for sign in ("+", "-"):
                on_label, rest_label = stair_labels(level, sign)
                volts = amp if sign == "+" else -amp
                segments.append(Segment(ControlMode.VOLTAGE, np.full(on, volts), 0.0, on_label))
                segments.append(Segment(ControlMode.VOLTAGE, np.zeros(stair_rest), 0.0, rest_label))
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
        stairs = stair_table(run, params)
        midpoints = []
        for sign, name in ((1.0, "pos"), (-1.0, "neg")):
            found = breakaway(stairs, sign)
            if found is None:
                notes.append(f"no staircase pulse moved the motor ({name}): raise stair_high_v")
                continue
            below, level, theta_m = found
            metrics[f"breakaway_{name}_v"], metrics[f"breakaway_{name}_below_v"] = level, below
            metrics[f"breakaway_{name}_theta_m_rad"] = theta_m
            midpoints.append((below + level) / 2)
            if below == 0.0:
                notes.append(f"the lowest staircase pulse moved the motor ({name}): lower stair_low_v")
        if midpoints:
            metrics["breakaway_v"] = float(np.mean(midpoints))
        return Results(metrics, {"pulses": table, "staircase": stairs}, notes)

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
