"""`endurance`: hours of a duty cycle with a short characterization every N minutes, to see friction drift.

Program: checkpoint 0, then blocks of duty cycle (position mode: out and back over `duty_stroke_rad`
under a constant output load), each followed by the next checkpoint. A checkpoint is the speed sweep in
small: each speed forward then back unloaded, every speed over the same motor turns about one centre (the
speed sweep's `same_place_program`), then each speed forward then back with `stiffness_load_nm` on the
output, then one slow position pass each way. Every checkpoint returns where it began, so each sees the
same stretch of the stroke and the estimates differ only by what changed in the gear.

Per checkpoint (catalog table `checkpoints`, `hdrig trend`):
- the friction level F_c and viscous slope b from |K_m·i_a| = F_c + b·|ω_m| over the unloaded holds (each
  hold's smooth friction at the checkpoint's one place), with standard errors from the regression residuals;
- the stiffness K_s from the deflection r·θ_m − θ_l each held speed shows with and without the load:
  at steady speed the transmitted torque grows by exactly the load, so K_s = load / Δdeflection; its
  uncertainty is the standard error over the speeds and directions.

While the run records, an online tracker (`model.recursive.FrictionTracker`, RLS with forgetting) follows
the friction level from every sample; its track is kept in the run's metadata (`observed`) beside the
motor travel and duty cycles at each checkpoint. The analysis reads only the checkpoints' rows (the
hours of duty cycle between are never loaded), so a run of any length is analyzed in bounded memory.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from pydantic import Field, ValidationInfo, field_validator, model_validator

from model.recursive import FrictionTracker
from model.run import Run
from rig.experiments.base import (
    LIST_MAX,
    LOAD_MAX_NM,
    SPEED_MAX_RAD_S,
    Experiment,
    ExperimentParams,
    Results,
    RigContext,
    SegmentReader,
    check_stroke,
    rig_speeds,
    segments_of,
    within_rig_speed,
)
from rig.experiments.plots import new_figure, save_figure
from rig.experiments.speed_sweep import SpeedSweepParams, same_place_program, same_place_table
from rig.interface import Block, ControlMode, Segment

DUTY_SEGMENT_S = 60.0  # duty blocks are cut into segments of about a minute that share one set-point array
CHECKPOINT_PREFIX = "c"
TRACK_POINTS_MAX = 512
"""Online track points kept in the metadata: past this, every other one goes and the spacing doubles, so
a run of any length keeps a track of 256–512 points (rewritten into the metadata at each new one)."""


CHECKPOINTS_MAX = 50_000
"""Most checkpoints in one run (10,000 h at one every 15 min is 40,000): the program is built whole."""


class EnduranceParams(ExperimentParams):
    duration_h: float = Field(default=1.0, gt=0, le=10_000, description="duty cycle in all [h]")
    checkpoint_every_min: float = Field(
        default=15.0, ge=1, le=10_000 * 60, description="duty cycle between two checkpoints [min]"
    )
    duty_stroke_rad: float = Field(
        default=150.0, gt=0, le=1e5, description="motor stroke of the duty motion [rad]"
    )
    duty_period_s: float = Field(
        default=10.0, ge=0.1, le=3600, description="one out-and-back duty motion [s]"
    )
    duty_load_nm: float = Field(
        default=2.0,
        ge=-LOAD_MAX_NM,
        le=LOAD_MAX_NM,
        description="external load on the output during duty [N·m]",
    )
    speeds_rad_s: list[Annotated[float, Field(gt=0, le=SPEED_MAX_RAD_S)]] = Field(
        default=[5.0, 20.0, 50.0],
        max_length=LIST_MAX,
        description="checkpoint speeds, distinct, each run forward and back [rad/s]",
    )
    settle_s: float = Field(default=0.3, gt=0, le=10, description="time to reach a held speed [s]")
    hold_s: float = Field(default=1.0, gt=0, le=60, description="averaging window per held speed [s]")
    stiffness_load_nm: float = Field(
        default=5.0,
        gt=0,
        le=LOAD_MAX_NM,
        description="output load of the loaded holds, for the stiffness [N·m]",
    )
    pass_speed_rad_s: float = Field(
        default=2.0, gt=0, le=SPEED_MAX_RAD_S, description="speed of the position pass [rad/s]"
    )
    pass_stroke_rad: float = Field(
        default=20.0, gt=0, le=1e5, description="motor stroke of the position pass [rad]"
    )
    track_memory_s: float = Field(
        default=60.0, ge=0.1, le=86_400, description="how far back the online friction tracker looks [s]"
    )
    track_every_s: float = Field(
        default=30.0,
        ge=0.1,
        le=86_400,
        description="run time between two kept track points [s] (doubled as the track grows long)",
    )

    @field_validator("speeds_rad_s")
    @classmethod
    def _positive(cls, speeds: list[float], info: ValidationInfo) -> list[float]:
        return rig_speeds(speeds, info, at_least=2)  # a level and a slope

    @field_validator("pass_speed_rad_s")
    @classmethod
    def _pass_within_rig(cls, speed: float, info: ValidationInfo) -> float:
        return within_rig_speed(speed, info, "pass speed")

    @model_validator(mode="after")
    def _checkpoints_bounded(self) -> EnduranceParams:
        count = self.duration_h * 60.0 / self.checkpoint_every_min
        if count > CHECKPOINTS_MAX:
            raise ValueError(
                f"checkpoint_every_min: {count:.0f} checkpoints over duration_h; at most {CHECKPOINTS_MAX}"
            )
        return self


def _label(checkpoint: int, name: str) -> str:
    return f"{CHECKPOINT_PREFIX}{checkpoint:04d}/{name}"


def _sweep(params: EnduranceParams) -> SpeedSweepParams:
    """The checkpoint's unloaded holds: the speed sweep's same-place passes at its speeds, settle and hold."""
    return SpeedSweepParams(speeds_rad_s=params.speeds_rad_s, settle_s=params.settle_s, hold_s=params.hold_s)


def checkpoint_program(params: EnduranceParams, ctx: RigContext, index: int) -> list[Segment]:
    """One checkpoint: the unloaded holds at one place (the speed sweep's `same_place_program`, so the
    friction against speed is not position against speed), the loaded holds, the position pass; each
    forward then back, ending where it began."""
    segments = same_place_program(_sweep(params), ctx, prefix=_label(index, ""), experiment="endurance")
    hold = ctx.cycles(params.settle_s + params.hold_s)
    for speed in params.speeds_rad_s:
        for sign in (1.0, -1.0):
            name = f"v{sign * speed:+g}L"
            segments.append(
                Segment(
                    ControlMode.VELOCITY,
                    np.full(hold, sign * speed),
                    params.stiffness_load_nm,
                    _label(index, name),
                )
            )
    passing = ctx.cycles(params.pass_stroke_rad / params.pass_speed_rad_s)
    for sign, mark in ((1.0, "+"), (-1.0, "-")):
        passes = np.full(passing, sign * params.pass_speed_rad_s)
        segments.append(Segment(ControlMode.VELOCITY, passes, 0.0, _label(index, f"pass{mark}")))
    return segments


def duty_setpoints(params: EnduranceParams, ctx: RigContext) -> np.ndarray:
    """The set-points of one full duty segment (whole periods, about DUTY_SEGMENT_S), read-only: every duty
    segment of a run shares them, so the program's memory does not grow with its hours."""
    period = ctx.cycles(params.duty_period_s)
    phase = 2 * math.pi * np.arange(period) / period
    one = ctx.theta_m0 + 0.5 * params.duty_stroke_rad * (1.0 - np.cos(phase))
    shared = np.tile(one, max(1, round(DUTY_SEGMENT_S / params.duty_period_s)))
    shared.flags.writeable = False
    return shared


def duty_program(
    params: EnduranceParams, ctx: RigContext, block: int, minutes: float, shared: np.ndarray
) -> list[Segment]:
    """`minutes` of duty motion as segments of whole periods on `shared` (`duty_setpoints`)."""
    period = ctx.cycles(params.duty_period_s)
    periods_total = max(1, round(minutes * 60.0 / params.duty_period_s))
    per_segment = shared.shape[0] // period
    segments: list[Segment] = []
    done = 0
    while done < periods_total:
        n = min(per_segment, periods_total - done)
        setpoint = shared if n == per_segment else shared[: n * period]
        label = f"duty{block:04d}.{len(segments):04d}"
        segments.append(Segment(ControlMode.POSITION, setpoint, params.duty_load_nm, label))
        done += n
    return segments


def checkpoints_due(params: EnduranceParams) -> int:
    """Checkpoints in the run: one at the start and one after each duty block."""
    return math.ceil(params.duration_h * 60.0 / params.checkpoint_every_min - 1e-9) + 1


@dataclass
class _Estimate:
    value: float
    sigma: float


def _hold_window(run: Run, seg: dict[str, Any], ctx: RigContext, settle_s: float) -> slice:
    start = int(seg["start"]) + ctx.cycles(settle_s)
    return slice(start, int(seg["start"]) + int(seg["cycles"]))


def friction_estimate(
    run: Run, ctx: RigContext, prefix: str, params: EnduranceParams
) -> dict[str, _Estimate]:
    """F_c and b with standard errors from the unloaded holds of one checkpoint: each hold's friction at
    the checkpoint's one place (`same_place_table`), regressed on its speed."""
    table = same_place_table(run, _sweep(params), ctx, prefix=prefix)
    speeds, torques = np.abs(table["omega_m"]), np.abs(table["torque_nm"])
    x = np.column_stack([np.ones(len(speeds)), speeds])
    coef, *_ = np.linalg.lstsq(x, torques, rcond=None)
    residual = torques - x @ coef
    dof = max(1, len(torques) - 2)
    cov = float(residual @ residual) / dof * np.linalg.inv(x.T @ x)
    return {
        "coulomb_nm": _Estimate(float(coef[0]), math.sqrt(cov[0, 0])),
        "viscous_nm_s_rad": _Estimate(float(coef[1]), math.sqrt(cov[1, 1])),
    }


def stiffness_estimate(run: Run, ctx: RigContext, prefix: str, params: EnduranceParams) -> _Estimate:
    """K_s from the deflection change the load makes at each held speed and direction."""
    estimates = []
    for seg in segments_of(run, prefix):
        name = seg["label"][len(prefix) :]
        if not name.startswith("v") or name.endswith("L"):
            continue
        loaded = next(s for s in segments_of(run, prefix) if s["label"] == seg["label"] + "L")
        deflection = []
        for s in (seg, loaded):
            rows = _hold_window(run, s, ctx, params.settle_s)
            deflection.append(float(np.mean(ctx.gear_ratio * run["theta_m"][rows] - run["theta_l"][rows])))
        estimates.append(params.stiffness_load_nm / (deflection[1] - deflection[0]))
    values = np.asarray(estimates)
    return _Estimate(float(np.mean(values)), float(np.std(values, ddof=1) / math.sqrt(len(values))))


class EnduranceObserver:
    """Sees every recorded block: motor travel, duty cycles, and the online friction track."""

    def __init__(self, params: EnduranceParams, ctx: RigContext, program: list[Segment]) -> None:
        self.params = params
        self.period_s = 1.0 / ctx.rate_hz
        self.tracker = FrictionTracker(
            ctx.rate_hz, ctx.torque_constant_nm_per_a, ctx.gear_ratio, memory_s=params.track_memory_s
        )
        self.rows = 0
        self.travel_rad = 0.0
        # Where each checkpoint starts (program row) and how many duty periods come before it.
        period_rows = ctx.cycles(params.duty_period_s)
        self._starts: list[tuple[int, str, float]] = []
        row = duty_rows = 0
        for seg in program:
            if seg.label.startswith("duty"):
                duty_rows += seg.cycles
            name = seg.label.split("/")[0]
            if seg.label.startswith(CHECKPOINT_PREFIX) and not any(n == name for _, n, _ in self._starts):
                self._starts.append((row, name, duty_rows / period_rows))
            row += seg.cycles
        self._next = 0
        self.checkpoints: dict[str, dict[str, float]] = {}
        self.track: dict[str, list[float]] = {"t_s": [], "level_nm": [], "travel_rad": []}
        self._track_every_s = params.track_every_s
        self._next_track_s = params.track_every_s

    def feed(self, block: Block) -> bool:
        """Take a block of samples as recorded; True when the summary has a new track point."""
        n = len(block["t"])
        speed = np.abs(block["omega_m"])
        news = False
        while self._next < len(self._starts) and self._starts[self._next][0] < self.rows + n:
            start, name, cycles = self._starts[self._next]
            before = max(0, start - self.rows)  # the checkpoint's first row within this block
            self.checkpoints[name] = {
                "travel_rad": self.travel_rad + float(np.sum(speed[:before])) * self.period_s,
                "duty_cycles": cycles,
                "t_s": float(block["t"][before]),
            }
            self._next += 1
            news = True
        self.travel_rad += float(np.sum(speed)) * self.period_s
        self.rows += n
        level = self.tracker.feed(block["i_a"], block["tau_ext"], block["omega_m"])
        if n and block["t"][-1] >= self._next_track_s:
            self.track["t_s"].append(float(block["t"][-1]))
            self.track["level_nm"].append(float(level[-1]))
            self.track["travel_rad"].append(self.travel_rad)
            if len(self.track["t_s"]) > TRACK_POINTS_MAX:
                self.track = {key: values[::2] for key, values in self.track.items()}
                self._track_every_s *= 2.0
            while self._next_track_s <= block["t"][-1]:
                self._next_track_s += self._track_every_s
            news = True
        return news

    def summary(self) -> dict[str, Any]:
        return {
            "checkpoints": self.checkpoints,
            "track": self.track,
            "track_memory_s": self.params.track_memory_s,
            "travel_rad": self.travel_rad,
        }


def _checkpoint(
    run: Run, prefix: str, seen: dict[str, Any], params: EnduranceParams, ctx: RigContext
) -> dict[str, float] | None:
    """The catalog row of the checkpoint whose segments start with `prefix` (None: the run did not
    finish it); `seen` is what the observer noted while recording."""
    own = segments_of(run, prefix)
    if len(own) < len(checkpoint_program(params, ctx, 0)):
        return None  # a checkpoint the run did not finish (aborted)
    friction = friction_estimate(run, ctx, prefix, params)
    stiffness = stiffness_estimate(run, ctx, prefix, params)
    span = slice(int(own[0]["start"]), int(own[-1]["start"]) + int(own[-1]["cycles"]))
    # At the checkpoint's middle: the gear drifts a little while it is measured.
    t_mid = 0.5 * (run.t[span.start] + run.t[span.stop - 1])
    travel_half = 0.5 * float(np.sum(np.abs(run["omega_m"][span]))) / ctx.rate_hz
    name = prefix.rstrip("/")
    where = seen.get(name, {})
    # The gear's temperature over the checkpoint (issue 27): `hdrig trend` normalizes the friction to T_ref.
    temperature = {"temp_gear_c": float(np.mean(run["temp_gear"][span]))} if "temp_gear" in run else {}
    return {
        **temperature,
        "index": int(name[len(CHECKPOINT_PREFIX) :]),
        "t_s": float(t_mid),
        "duty_cycles": float(where.get("duty_cycles", math.nan)),
        "travel_rad": float(where.get("travel_rad", math.nan)) + travel_half,
        "coulomb_nm": friction["coulomb_nm"].value,
        "coulomb_sigma_nm": friction["coulomb_nm"].sigma,
        "viscous_nm_s_rad": friction["viscous_nm_s_rad"].value,
        "viscous_sigma_nm_s_rad": friction["viscous_nm_s_rad"].sigma,
        "stiffness_nm_rad": stiffness.value,
        "stiffness_sigma_nm_rad": stiffness.sigma,
    }


CHECKPOINT_COLUMNS = (
    "index",
    "t_s",
    "duty_cycles",
    "travel_rad",
    "coulomb_nm",
    "coulomb_sigma_nm",
    "viscous_nm_s_rad",
    "viscous_sigma_nm_s_rad",
    "stiffness_nm_rad",
    "stiffness_sigma_nm_rad",
)


def _results(
    checkpoints: list[dict[str, float]], observed: dict[str, Any], params: EnduranceParams
) -> Results:
    """Metrics, the checkpoint table and the online track, from the checkpoints' catalog rows."""
    table = {
        key: np.asarray([entry[key] for entry in checkpoints], dtype=np.float64) for key in CHECKPOINT_COLUMNS
    }
    metrics: dict[str, float | int | str] = {"checkpoints": len(checkpoints)}
    if checkpoints:
        first_c, last_c = checkpoints[0], checkpoints[-1]
        metrics["coulomb_first_nm"] = first_c["coulomb_nm"]
        metrics["coulomb_last_nm"] = last_c["coulomb_nm"]
        metrics["coulomb_change_pct"] = 100.0 * (last_c["coulomb_nm"] / first_c["coulomb_nm"] - 1.0)
        metrics["stiffness_last_nm_rad"] = last_c["stiffness_nm_rad"]
    notes = [
        f"online tracker: RLS with forgetting, memory {params.track_memory_s:g} s: it lags a steady drift"
        " by about that, and its level is the duty cycle's, not the checkpoints' speeds and positions"
    ]
    results = Results(metrics, {"checkpoints": table}, notes)
    results.checkpoints = checkpoints
    track = observed.get("track")
    if track and track.get("t_s"):
        results.tables["friction_track"] = {k: np.asarray(v, dtype=np.float64) for k, v in track.items()}
    return results


class Endurance(Experiment):
    name = "endurance"
    summary = "hours of duty cycle with a friction and stiffness checkpoint every N minutes"
    Params = EnduranceParams
    needs = frozenset({ControlMode.VELOCITY, ControlMode.POSITION})

    def program(self, params: EnduranceParams, ctx: RigContext) -> list[Segment]:
        reach = max(params.duty_stroke_rad, params.pass_stroke_rad)
        check_stroke("endurance", reach, ctx)
        count = checkpoints_due(params)
        total_min = params.duration_h * 60.0
        first = checkpoint_program(params, ctx, 0)
        for seg in first:
            seg.setpoint.flags.writeable = False  # shared by every checkpoint, as the duty arrays are
        program = list(first)
        shared = duty_setpoints(params, ctx)
        for index in range(1, count):
            minutes = min(params.checkpoint_every_min, total_min - (index - 1) * params.checkpoint_every_min)
            program += duty_program(params, ctx, index, minutes, shared)
            # The same set-points under the checkpoint's own labels: ~285 kB per checkpoint otherwise, a
            # program whose memory grew with the run's hours.
            program += [replace(seg, label=_label(index, seg.label.split("/", 1)[1])) for seg in first]
        return program

    def observer(self, params: EnduranceParams, ctx: RigContext, program: list[Segment]) -> EnduranceObserver:
        return EnduranceObserver(params, ctx, program)

    def analyzed_segments(self, params: EnduranceParams, labels: list[str]) -> list[str]:
        return [label for label in labels if label.startswith(_label(0, ""))]

    def analyze_parts(
        self, read: SegmentReader, run: Run, params: EnduranceParams, ctx: RigContext
    ) -> Results:
        """One checkpoint's rows at a time (~37,000 rows), so memory does not grow with the run's hours;
        `run` holds checkpoint 0."""
        seen = run.meta.get("observed", {}).get("checkpoints", {})
        checkpoints = []
        for index in range(checkpoints_due(params)):
            part = run if index == 0 else read([seg.label for seg in checkpoint_program(params, ctx, index)])
            entry = _checkpoint(part, _label(index, ""), seen, params, ctx)
            if entry is not None:
                checkpoints.append(entry)
        return _results(checkpoints, run.meta.get("observed", {}), params)

    def analyze(self, run: Run, params: EnduranceParams, ctx: RigContext) -> Results:
        """All checkpoints from one run holding their rows (the whole run, or its checkpoints)."""
        seen = run.meta.get("observed", {}).get("checkpoints", {})
        names = sorted({str(seg["label"]).split("/")[0] for seg in segments_of(run, CHECKPOINT_PREFIX)})
        checkpoints = [_checkpoint(run, name + "/", seen, params, ctx) for name in names]
        found = [entry for entry in checkpoints if entry is not None]
        return _results(found, run.meta.get("observed", {}), params)

    def plot(
        self, run: Run, results: Results, params: EnduranceParams, ctx: RigContext, out_dir: Path
    ) -> list[Path]:
        table = results.tables["checkpoints"]
        if not len(table["t_s"]):
            return []
        fig, ax = new_figure("Friction level over the endurance run: checkpoints and online tracker")
        ax.errorbar(
            table["t_s"] / 3600.0,
            table["coulomb_nm"],
            yerr=table["coulomb_sigma_nm"],
            fmt="o",
            capsize=3,
            label="checkpoint fit F_c (±1σ)",
        )
        track = results.tables.get("friction_track")
        if track is not None:
            ax.plot(track["t_s"] / 3600.0, track["level_nm"], lw=1.0, label="online RLS level")
        ax.set_xlabel("run time [h]")
        ax.set_ylabel("friction level [N·m]")
        ax.legend()
        return [save_figure(fig, out_dir / "friction_trend.png")]
