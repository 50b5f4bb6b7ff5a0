"""`warm-up`: a duty held until the gear's temperature settles, then the cool-down observed, with checkpoints
of running torque and temperature all along (issue 27 item 3).

Program: checkpoint 0 (the gear as found, usually cold), then blocks of duty (position mode: out and back
over `duty_stroke_rad`, no load) each followed by a checkpoint, for at most `warm_s` — the bound: a
program is built whole before it plays, so the duty cannot stop on the temperature itself; the analysis
says when (and whether) the gear settled within it. Then the cool-down: the motor held at rest in
blocks, a checkpoint after each, for `cool_s`. A checkpoint is each of `speeds_rad_s` held forward then
back (velocity mode), so it returns where it began and every checkpoint sees the same stretch of stroke.

Per checkpoint (table `checkpoints`): time, phase (0 warm, 1 cool), the gear and motor temperatures
(mean over its holds) and, per speed, the running torque |K_m·i_a| averaged over both directions' hold
windows with its standard error. Table `temperature`: the probes' readings against time, thinned to
about one a second. Metrics: whether the gear settled (its rate over the last `settle_window_s` of the
duty below `settle_rate_k_per_min`), when, its rise, and the running torque's fall from first to last
warm checkpoint. The thermal network and the friction's temperature law are fitted from such runs by
`rig.analysis.identification.thermal_stage`.

The run needs the temperature columns (`temp_gear`, `temp_motor`): a rig without them is refused by the
analysis in one line. On the simulated bench with the `seed-thermal` preset the gear's slowest time
constant is about 20 min, so it settles in hours; `seed-thermal-fast` scales the heat capacities down so
the default bounds (7 min of duty, 5 of cool-down) reach a settled gear (tests, benches).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated

import numpy as np
from pydantic import Field, ValidationInfo, field_validator

from model.errors import UserInputError
from model.run import Run
from rig.experiments.base import (
    LIST_MAX,
    SPEED_MAX_RAD_S,
    Experiment,
    ExperimentParams,
    Results,
    RigContext,
    check_stroke,
    rig_speeds,
    segments_of,
)
from rig.experiments.plots import new_figure, save_figure
from rig.interface import ControlMode, Segment

CHECKPOINT_PREFIX = "k"
TEMPERATURE_COLUMNS = ("temp_gear", "temp_motor")
WARM, COOL = 0, 1
"""The checkpoint's phase: during the duty, or during the cool-down."""
TEMPERATURE_TABLE_S = 1.0
"""Spacing of the thinned temperature table [s]: the thermal time constants are tens of seconds or more."""


class WarmUpParams(ExperimentParams):
    warm_s: float = Field(
        default=420.0, gt=0, le=86_400, description="duty held at most this long (the settling bound) [s]"
    )
    cool_s: float = Field(default=300.0, ge=0, le=86_400, description="cool-down observed after the duty [s]")
    checkpoint_every_s: float = Field(
        default=30.0, ge=5, le=86_400, description="duty (or rest) between two checkpoints [s]"
    )
    duty_stroke_rad: float = Field(
        default=250.0, gt=0, le=1e5, description="motor stroke of the duty motion [rad]"
    )
    duty_period_s: float = Field(default=4.0, ge=0.1, le=3600, description="one out-and-back duty motion [s]")
    # Low speeds by default: at 100 rad/s on the simulated bench most of the running torque is the output
    # side's (its kinematic error excites the load), which does not follow the grease's temperature.
    speeds_rad_s: list[Annotated[float, Field(gt=0, le=SPEED_MAX_RAD_S)]] = Field(
        default=[5.0, 20.0],
        min_length=1,
        max_length=LIST_MAX,
        description="checkpoint speeds, distinct, each held forward then back [rad/s]",
    )
    settle_s: float = Field(default=0.3, gt=0, le=10, description="time to reach a held speed [s]")
    hold_s: float = Field(default=1.0, gt=0, le=60, description="averaging window per held speed [s]")
    settle_rate_k_per_min: float = Field(
        default=0.2, gt=0, le=100, description="the gear counts as settled below this rate [K/min]"
    )
    settle_window_s: float = Field(
        default=60.0, gt=0, le=86_400, description="window over which the settling rate is measured [s]"
    )

    @field_validator("speeds_rad_s")
    @classmethod
    def _speeds(cls, speeds: list[float], info: ValidationInfo) -> list[float]:
        return rig_speeds(speeds, info)


def _label(index: int, name: str) -> str:
    return f"{CHECKPOINT_PREFIX}{index:04d}/{name}"


def checkpoint_program(params: WarmUpParams, ctx: RigContext, index: int) -> list[Segment]:
    """One checkpoint: each speed held forward then back."""
    hold = ctx.cycles(params.settle_s + params.hold_s)
    segments = []
    for speed in params.speeds_rad_s:
        for sign in (1.0, -1.0):
            label = _label(index, f"v{sign * speed:+g}")
            segments.append(Segment(ControlMode.VELOCITY, np.full(hold, sign * speed), 0.0, label))
    return segments


def _duty(params: WarmUpParams, ctx: RigContext, block: int, seconds: float) -> Segment:
    """Whole out-and-back periods filling about `seconds`, from θ_m0 and back to it."""
    period = ctx.cycles(params.duty_period_s)
    periods = max(1, round(seconds / params.duty_period_s))
    phase = 2 * math.pi * np.arange(period) / period
    one = ctx.theta_m0 + 0.5 * params.duty_stroke_rad * (1.0 - np.cos(phase))
    return Segment(ControlMode.POSITION, np.tile(one, periods), 0.0, f"duty{block:04d}")


def _rest(params: WarmUpParams, ctx: RigContext, block: int, seconds: float) -> Segment:
    """The motor held at θ_m0 in position mode: a velocity loop held at zero can hunt around the stick
    band (seen on the simulated bench: amperes of limit cycle), which would heat what should cool."""
    return Segment(ControlMode.POSITION, np.full(ctx.cycles(seconds), ctx.theta_m0), 0.0, f"cool{block:04d}")


def _blocks(total_s: float, every_s: float) -> list[float]:
    """`total_s` cut into blocks of `every_s` (the last one shorter)."""
    count = math.ceil(total_s / every_s - 1e-9)
    return [min(every_s, total_s - i * every_s) for i in range(count)]


def _checkpoint_rows(run: Run, ctx: RigContext, params: WarmUpParams, prefix: str) -> dict[str, float]:
    """The running torque per speed and the temperatures over one checkpoint's hold windows."""
    row: dict[str, float] = {}
    temps: dict[str, list[np.ndarray]] = {c: [] for c in TEMPERATURE_COLUMNS}
    times = []
    for speed in params.speeds_rad_s:
        torques, spreads = [], []
        for seg in segments_of(run, prefix):
            if abs(abs(float(seg["label"].split("/v")[1])) - speed) > 1e-9 * speed:
                continue
            start = int(seg["start"]) + ctx.cycles(params.settle_s)
            rows = slice(start, int(seg["start"]) + int(seg["cycles"]))
            torque = np.abs(ctx.torque_constant_nm_per_a * run["i_a"][rows])
            torques.append(float(np.mean(torque)))
            spreads.append(float(np.std(torque)) / math.sqrt(max(1, torque.shape[0])))
            for column in TEMPERATURE_COLUMNS:
                temps[column].append(run[column][rows])
            times.append(run.t[rows])
        # Both directions' levels: their difference (asymmetry, position ripple) is part of the spread.
        mean = float(np.mean(torques))
        sigma = max(float(np.std(torques)) / math.sqrt(len(torques)), float(np.mean(spreads)))
        row[f"torque_{speed:g}_nm"] = mean
        row[f"torque_{speed:g}_sigma_nm"] = sigma
    row["t_s"] = float(np.mean(np.concatenate(times)))
    row["temp_gear_c"] = float(np.mean(np.concatenate(temps["temp_gear"])))
    row["temp_motor_c"] = float(np.mean(np.concatenate(temps["temp_motor"])))
    return row


def warm_up_checkpoints(run: Run, ctx: RigContext, params: WarmUpParams) -> dict[str, np.ndarray]:
    """The table `checkpoints` of a warm-up run: index, phase, t_s, temperatures, torque per speed."""
    missing = [c for c in TEMPERATURE_COLUMNS if c not in run]
    if missing:
        raise UserInputError(
            f"warm-up: the run has no {', '.join(missing)} column (the rig records no temperatures):"
            " a warm-up needs the gear and motor temperature probes"
        )
    names = sorted({str(seg["label"]).split("/")[0] for seg in segments_of(run, CHECKPOINT_PREFIX)})
    cool_starts = [int(seg["start"]) for seg in segments_of(run, "cool")]
    first_cool = min(cool_starts) if cool_starts else math.inf
    rows = []
    for name in names:
        own = segments_of(run, name + "/")
        if len(own) < 2 * len(params.speeds_rad_s):
            continue  # not finished (aborted)
        row = _checkpoint_rows(run, ctx, params, name + "/")
        row["index"] = float(int(name[len(CHECKPOINT_PREFIX) :]))
        row["phase"] = float(COOL if int(own[0]["start"]) > first_cool else WARM)
        rows.append(row)
    if not rows:
        return {}
    return {key: np.asarray([r[key] for r in rows], dtype=np.float64) for key in rows[0]}


def settling(
    t_s: np.ndarray, temp_c: np.ndarray, end_s: float, params: WarmUpParams
) -> tuple[bool, float, float]:
    """(settled, when [s], rate at the end of the duty [K/min]): the gear's rate, fitted over each window
    of `settle_window_s` ending at a sample, first below the bound; NaN time if never."""
    keep = t_s <= end_s
    t, temp = t_s[keep], temp_c[keep]
    when, last_rate = math.nan, math.nan
    for i in range(t.shape[0]):
        window = (t > t[i] - params.settle_window_s) & (t <= t[i])
        if t[i] - t[0] < params.settle_window_s or np.count_nonzero(window) < 3:
            continue
        rate = 60.0 * float(np.polyfit(t[window], temp[window], 1)[0])
        last_rate = rate
        if math.isnan(when) and abs(rate) < params.settle_rate_k_per_min:
            when = float(t[i])
    return not math.isnan(when), when, last_rate


def temperature_table(run: Run) -> dict[str, np.ndarray]:
    """The probes' readings averaged over bins of TEMPERATURE_TABLE_S."""
    bins = max(1, round(TEMPERATURE_TABLE_S / float(np.median(np.diff(run.t[:100])))))
    n = run.t.shape[0] // bins * bins
    table = {"t_s": run.t[:n].reshape(-1, bins).mean(axis=1)}
    for column in TEMPERATURE_COLUMNS:
        table[f"{column}_c"] = run[column][:n].reshape(-1, bins).mean(axis=1)
    return table


class WarmUp(Experiment):
    name = "warm-up"
    summary = "a duty held until the gear's temperature settles, then the cool-down, with torque checkpoints"
    Params = WarmUpParams
    needs = frozenset({ControlMode.VELOCITY, ControlMode.POSITION})

    def program(self, params: WarmUpParams, ctx: RigContext) -> list[Segment]:
        reach = max(params.duty_stroke_rad, max(params.speeds_rad_s) * (params.settle_s + params.hold_s))
        check_stroke("warm-up", reach, ctx)
        program = checkpoint_program(params, ctx, 0)
        index = 1
        for block, seconds in enumerate(_blocks(params.warm_s, params.checkpoint_every_s)):
            program += [_duty(params, ctx, block, seconds), *checkpoint_program(params, ctx, index)]
            index += 1
        if params.cool_s > 0:
            for block, seconds in enumerate(_blocks(params.cool_s, params.checkpoint_every_s)):
                program += [_rest(params, ctx, block, seconds), *checkpoint_program(params, ctx, index)]
                index += 1
        return program

    def analyze(self, run: Run, params: WarmUpParams, ctx: RigContext) -> Results:
        table = warm_up_checkpoints(run, ctx, params)
        temperature = temperature_table(run)
        cool = segments_of(run, "cool")
        end_warm_s = float(run.t[int(cool[0]["start"])]) if cool else float(run.t[-1])
        settled, when, rate = settling(temperature["t_s"], temperature["temp_gear_c"], end_warm_s, params)
        metrics: dict[str, float | int | str] = {
            "checkpoints": len(table.get("t_s", [])),
            "settled": int(settled),
            "settled_at_s": when,
            "gear_rate_end_k_per_min": rate,
            "warm_bound_s": params.warm_s,
            "temp_gear_start_c": float(temperature["temp_gear_c"][0]),
            "temp_gear_max_c": float(np.max(temperature["temp_gear_c"])),
            "temp_gear_end_c": float(temperature["temp_gear_c"][-1]),
        }
        notes = [
            f"the duty was held for its bound, {params.warm_s:g} s: the gear "
            + (
                f"settled (below {params.settle_rate_k_per_min:g} K/min over {params.settle_window_s:g} s)"
                f" at {when:.0f} s"
                if settled
                else f"did not settle (still {rate:.3g} K/min at the end): raise warm_s"
            )
        ]
        if table:
            warm = table["phase"] == WARM
            for speed in params.speeds_rad_s:
                column = table[f"torque_{speed:g}_nm"][warm]
                metrics[f"torque_{speed:g}_first_nm"] = float(column[0])
                metrics[f"torque_{speed:g}_warm_nm"] = float(column[-1])
                metrics[f"torque_{speed:g}_change_pct"] = 100.0 * float(column[-1] / column[0] - 1.0)
        tables = {"checkpoints": table, "temperature": temperature} if table else {"temperature": temperature}
        return Results(metrics, tables, notes)

    def plot(
        self, run: Run, results: Results, params: WarmUpParams, ctx: RigContext, out_dir: Path
    ) -> list[Path]:
        temperature = results.tables["temperature"]
        fig, ax = new_figure("Temperatures during the warm-up and the cool-down")
        for column, label in (("temp_gear_c", "gear"), ("temp_motor_c", "motor winding")):
            ax.plot(temperature["t_s"], temperature[column], lw=1.0, label=f"{label} (measured)")
        cool = segments_of(run, "cool")
        if cool:
            ax.axvline(float(run.t[int(cool[0]["start"])]), color="grey", ls="--", lw=0.8, label="cool-down")
        ax.set_xlabel("time [s]")
        ax.set_ylabel("temperature [°C]")
        ax.legend()
        paths = [save_figure(fig, out_dir / "temperature.png")]
        table = results.tables.get("checkpoints")
        if table:
            fig, ax = new_figure("Running torque against the gear's temperature")
            for speed in params.speeds_rad_s:
                for phase, mark, what in ((WARM, "o", "warming"), (COOL, "s", "cooling")):
                    keep = table["phase"] == phase
                    if not np.any(keep):
                        continue
                    ax.errorbar(
                        table["temp_gear_c"][keep],
                        table[f"torque_{speed:g}_nm"][keep],
                        yerr=table[f"torque_{speed:g}_sigma_nm"][keep],
                        fmt=mark,
                        capsize=2,
                        label=f"{speed:g} rad/s, {what}",
                    )
            ax.set_xlabel("gear temperature [°C]")
            ax.set_ylabel("running torque |K_m·i_a| [N·m]")
            ax.legend(fontsize=8)
            paths.append(save_figure(fig, out_dir / "friction_vs_temperature.png"))
        return paths
