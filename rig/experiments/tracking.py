"""Closed-loop position tracking, the article's validation tests: `step`, `sine` and `ramp`.

Set-points are given at the output, as the article reports them, and played on the rig's position loop
(motor encoder) as motor set-points θ_m = θ_m0 + θ_out/r. The response that counts is the load angle
θ_l measured at the output; the motor angle seen at the output, r·(θ_m − θ_m0), is shown beside it.
Every angle is taken relative to its value at the program start (the end of the runner's settle), so
the arbitrary zero of a load sensor does not matter.

- `step`: a step of `amp_out_rad` held, then back to the start and held. Per step: settling time
  (last exit from a ±`band_fraction` band around the new set-point), 10–90 % rise time, overshoot and
  steady-state error, for θ_l and for the motor.
- `sine`: θ_out = A·(1 − cos 2πft), i.e. a sine of amplitude A centred A above the start, starting at
  rest. RMS and maximum of θ_l − θ_out after the first `skip_periods`; gain and phase lag of θ_l
  against the set-point from a least-squares fit at f.
- `ramp`: a slow ramp of the output up, then down at the same speed. The ripple is the peak-to-peak of
  θ_l − θ_out after removing a straight line (the steady lag), over the steady part of each direction,
  averaged over both (`ripple_pp_rad`, RMS beside it): everything the output sees at that speed, as an
  output sensor on the article's bench would, and on the seed mostly the transmission's kinematic
  error. That error is estimated apart: the sinusoid in the motor angle (its cycles per motor turn
  found by a scan) that best fits the transmission error θ_l − r·θ_m of both directions
  (`kinematic_error_pp_rad`, `kinematic_error_cycles_per_turn`); the stick-slip is the ripple less it
  (`stick_slip_pp_rad`, `stick_slip_rms_rad`: the load's detrended tracking error less the kinematic
  error). Stick phases are counted apart on each side: spans of
  at least `min_stick_s` where the smoothed speed stays below `stick_speed_fraction` of the ramp
  speed. On the seed plant the motor sticks at the start and at the reversal (the integrator has to
  swing the current through the static friction band), while the load sticks and slips all along
  the ramp: the kinematic error makes the output speed swing through zero, and the load's static
  friction catches it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np
from matplotlib.axes import Axes
from pydantic import Field, ValidationInfo, field_validator
from scipy import signal

from model.errors import UserInputError
from model.run import Run
from rig.experiments.base import Experiment, ExperimentParams, Results, RigContext, segment_rows, segments_of
from rig.experiments.plots import new_figure, save_figure
from rig.interface import ControlMode, Segment

ZERO_WINDOW_S = 0.1
"""Stretch before the program averaged for the load angle's zero [s]: the end of the runner's settle, which
holds until the output is at rest over this window (rig.runner.REST_WINDOW_S); 0.1 s spans a full period
of the seed's 11 Hz load mode, so what is left of a ring averages out rather than biasing the zero."""


# --- shared by the three experiments ---------------------------------------------------------------------


def output_segment(ctx: RigContext, out_rad: np.ndarray, label: str) -> Segment:
    """A position segment from set-points at the output, relative to the start [rad]."""
    return Segment(ControlMode.POSITION, ctx.theta_m0 + np.asarray(out_rad) / ctx.gear_ratio, 0.0, label)


def check_stroke(
    ctx: RigContext, low_out_rad: float, high_out_rad: float, experiment: str, field: str
) -> None:
    """Refuse, naming `field`, set-points that would leave the stroke from where the output starts."""
    start = ctx.theta_m0 * ctx.gear_ratio
    limits = ctx.config.limits
    low, high = start + low_out_rad, start + high_out_rad
    if low < limits.travel_min_out_rad or high > limits.travel_max_out_rad:
        raise UserInputError(
            f"run {experiment}: field '{field}': set-points reach output angles [{low:.3g}, {high:.3g}] rad"
            f" from the start at {start:.3g} rad, outside the stroke"
            f" [{limits.travel_min_out_rad}, {limits.travel_max_out_rad}] rad"
        )


@dataclass(frozen=True)
class OutputTrack:
    """Rows of a run seen at the output, angles relative to the program start [s, rad]."""

    t_s: np.ndarray  # time since the first of the rows
    setpoint: np.ndarray  # r·(θ_sp − θ_m0)
    load: np.ndarray  # θ_l − θ_l0
    motor: np.ndarray  # r·(θ_m − θ_m0)


def output_track(run: Run, ctx: RigContext, rows: slice) -> OutputTrack:
    """The rows `rows` (of position segments) as an OutputTrack."""
    program_start = min(int(seg["start"]) for seg in segments_of(run))
    zero = slice(max(0, program_start - ctx.cycles(ZERO_WINDOW_S)), program_start)
    theta_l0 = float(np.mean(run["theta_l"][zero])) if program_start > 0 else float(run["theta_l"][0])
    r = ctx.gear_ratio
    t = run.t[rows]
    return OutputTrack(
        t_s=t - t[0],
        setpoint=r * (run["setpoint"][rows] - ctx.theta_m0),
        load=run["theta_l"][rows] - theta_l0,
        motor=r * (run["theta_m"][rows] - ctx.theta_m0),
    )


def program_rows(run: Run) -> slice:
    """All rows of the program (the run's segments, without the runner's settle)."""
    segs = segments_of(run)
    return slice(int(segs[0]["start"]), int(segs[-1]["start"]) + int(segs[-1]["cycles"]))


SIDES = (("load", "θ_l"), ("motor", "r·θ_m"))
"""The two responses every metric is given for: the load angle (what the article reports) and the motor."""


# --- step ------------------------------------------------------------------------------------------------


class StepParams(ExperimentParams):
    amp_out_rad: float = Field(
        default=1.0,
        ge=-3.5,
        le=3.5,
        description="step height at the output; the article's test is 1 rad; negative steps go down [rad]",
    )
    hold_s: float = Field(default=1.5, ge=0.2, le=30, description="time each set-point is held [s]")
    band_fraction: float = Field(
        default=0.02, gt=0, lt=0.5, description="settling band, as a share of the step height (2 %) [–]"
    )
    steady_s: float = Field(
        default=0.2,
        gt=0,
        le=10,
        validate_default=True,
        description="end of each hold averaged for the steady-state error [s]",
    )

    @field_validator("amp_out_rad")
    @classmethod
    def _nonzero(cls, amp: float) -> float:
        if amp == 0:
            raise ValueError("must not be 0")
        return amp

    @field_validator("steady_s")
    @classmethod
    def _within_hold(cls, steady_s: float, info: ValidationInfo) -> float:
        hold_s = info.data.get("hold_s")
        if hold_s is not None and steady_s >= hold_s / 2:
            raise ValueError(f"must be under half of hold_s ({hold_s} s)")
        return steady_s


STEP_LABELS = ("step-to", "step-back")


def _first_crossing_s(t_s: np.ndarray, fraction: np.ndarray, level: float) -> float:
    """Time the normalized response first reaches `level`, interpolated between samples; NaN if never."""
    above = np.flatnonzero(fraction >= level)
    if above.size == 0:
        return float("nan")
    i = int(above[0])
    if i == 0:
        return float(t_s[0])
    f0, f1 = fraction[i - 1], fraction[i]
    return float(t_s[i - 1] + (level - f0) / (f1 - f0) * (t_s[i] - t_s[i - 1]))


def step_metrics(
    t_s: np.ndarray, y: np.ndarray, y_from: float, y_to: float, band_fraction: float, steady_cycles: int
) -> dict[str, float]:
    """Settling time, 10–90 % rise time, overshoot and steady-state error of one step response.

    `t_s` starts at the step. Settling: the time after which y stays within ±band_fraction·|step| of
    y_to (NaN if it is outside at the end). Steady-state error: y_to minus the mean of the last
    `steady_cycles` samples, signed along the step (positive: short of the set-point) [s, %, rad].
    """
    step = y_to - y_from
    fraction = (y - y_from) / step
    outside = np.flatnonzero(np.abs(fraction - 1.0) > band_fraction)
    if outside.size == 0:
        settling_s = 0.0
    elif outside[-1] == len(y) - 1:
        settling_s = float("nan")
    else:
        settling_s = float(t_s[outside[-1] + 1])
    return {
        "settling_s": settling_s,
        "rise_s": _first_crossing_s(t_s, fraction, 0.9) - _first_crossing_s(t_s, fraction, 0.1),
        "overshoot_pct": 100.0 * max(0.0, float(np.max(fraction)) - 1.0),
        "ss_error_rad": float((y_to - np.mean(y[-steady_cycles:])) * np.sign(step)),
    }


STEP_QUANTITIES = ("settling_s", "rise_s", "overshoot_pct", "ss_error_rad")


class Step(Experiment):
    name = "step"
    start_on_turn: ClassVar[bool] = True  # the runner starts it at θ_m = 0 (rig.runner._approach_turn)
    summary = "output position step (1 rad) and back; settling, rise, overshoot of the load angle"
    Params = StepParams
    needs = frozenset({ControlMode.POSITION})

    def program(self, params: StepParams, ctx: RigContext) -> list[Segment]:
        check_stroke(
            ctx, min(0.0, params.amp_out_rad), max(0.0, params.amp_out_rad), self.name, "amp_out_rad"
        )
        following = ctx.config.limits.following_error_out_rad
        if abs(params.amp_out_rad) >= following:
            raise UserInputError(
                f"run {self.name}: field 'amp_out_rad': a step of {params.amp_out_rad} rad would trip"
                f" the rig's following-error limit of {following} rad at the output"
            )
        cycles = ctx.cycles(params.hold_s)
        return [
            output_segment(ctx, np.full(cycles, params.amp_out_rad), STEP_LABELS[0]),
            output_segment(ctx, np.zeros(cycles), STEP_LABELS[1]),
        ]

    def analyze(self, run: Run, params: StepParams, ctx: RigContext) -> Results:
        steady = ctx.cycles(params.steady_s)
        set_from = 0.0
        table: dict[str, list[float]] = {"step": [], "amp_out_rad": []}
        for index, label in enumerate(STEP_LABELS, start=1):
            track = output_track(run, ctx, segment_rows(run, label))
            set_to = float(track.setpoint[0])
            table["step"].append(index)
            table["amp_out_rad"].append(set_to - set_from)
            for side, _ in SIDES:
                values = step_metrics(
                    track.t_s, getattr(track, side), set_from, set_to, params.band_fraction, steady
                )
                for quantity, value in values.items():
                    table.setdefault(f"{side}_{quantity}", []).append(value)
            set_from = set_to
        columns = {name: np.asarray(values) for name, values in table.items()}
        metrics: dict[str, float | int | str] = {"band_fraction": params.band_fraction}
        notes = []
        for side, _ in SIDES:
            prefix = "" if side == "load" else "motor_"
            for quantity in STEP_QUANTITIES:
                per_step = columns[f"{side}_{quantity}"]
                if np.all(np.isfinite(per_step)):
                    metrics[f"{prefix}{quantity}"] = float(np.mean(per_step))
                    if side == "load":
                        metrics.update({f"{quantity}_{i + 1}": float(v) for i, v in enumerate(per_step)})
                else:
                    notes.append(f"{side}: {quantity} undefined in some step (not settled or not reached)")
        return Results(metrics, {"steps": columns}, notes)

    def plot(
        self, run: Run, results: Results, params: StepParams, ctx: RigContext, out_dir: Path
    ) -> list[Path]:
        fig, _ = new_figure(f"Position step of {params.amp_out_rad:g} rad at the output, and back", 1, 2)
        table = results.tables["steps"]
        set_from = 0.0
        for ax, label, settling in zip(fig.axes, STEP_LABELS, table["load_settling_s"], strict=True):
            track = output_track(run, ctx, segment_rows(run, label))
            set_to = float(track.setpoint[0])
            band = params.band_fraction * abs(set_to - set_from)
            ax.plot(track.t_s, track.setpoint, color="0.3", lw=1, label="set-point")
            ax.plot(track.t_s, track.load, label="load θ_l")
            ax.plot(track.t_s, track.motor, lw=0.8, label="motor r·θ_m")
            ax.axhspan(set_to - band, set_to + band, color="C2", alpha=0.15, label=f"±{band:.3g} rad band")
            if np.isfinite(settling):
                ax.axvline(settling, color="C2", ls="--", lw=0.8, label=f"settled {settling:.3f} s")
            ax.set_xlabel(f"time since the step ({label}) [s]")
            ax.set_ylabel("output angle from the start [rad]")
            ax.legend(fontsize=8)
            set_from = set_to
        return [save_figure(fig, out_dir / "step_response.png")]


# --- sine ------------------------------------------------------------------------------------------------


class SineParams(ExperimentParams):
    amp_out_rad: float = Field(
        default=0.5,
        gt=0,
        le=1.75,
        description="sine amplitude at the output; centred this far above the start [rad]",
    )
    freq_hz: float = Field(
        default=0.5, gt=0, le=5, description="sine frequency; the article's test is 0.5 Hz [Hz]"
    )
    periods: int = Field(default=4, ge=2, le=100, description="periods played [–]")
    skip_periods: int = Field(
        default=1,
        ge=0,
        validate_default=True,
        description="first periods left out of the analysis (start transient) [–]",
    )

    @field_validator("skip_periods")
    @classmethod
    def _fewer_than_periods(cls, skip: int, info: ValidationInfo) -> int:
        periods = info.data.get("periods")
        if periods is not None and skip >= periods:
            raise ValueError(f"must be less than periods ({periods})")
        return skip


def fit_phasor(t_s: np.ndarray, y: np.ndarray, freq_hz: float) -> complex:
    """Least-squares C with y ≈ c0 + Re(C·exp(j2πft)): the component of y at freq_hz."""
    w = 2 * np.pi * freq_hz * t_s
    basis = np.column_stack([np.ones_like(t_s), np.cos(w), np.sin(w)])
    coef, *_ = np.linalg.lstsq(basis, y, rcond=None)
    return complex(coef[1], -coef[2])


class Sine(Experiment):
    name = "sine"
    start_on_turn: ClassVar[bool] = True  # the runner starts it at θ_m = 0 (rig.runner._approach_turn)
    summary = "sinusoidal output position (0.5 Hz); RMS tracking error, gain and phase of the load angle"
    Params = SineParams
    needs = frozenset({ControlMode.POSITION})

    def program(self, params: SineParams, ctx: RigContext) -> list[Segment]:
        check_stroke(ctx, 0.0, 2 * params.amp_out_rad, self.name, "amp_out_rad")
        t_s = np.arange(ctx.cycles(params.periods / params.freq_hz)) / ctx.rate_hz
        # 1 − cos starts at rest where the output is, so the loop is not kicked at the start.
        out = params.amp_out_rad * (1.0 - np.cos(2 * np.pi * params.freq_hz * t_s))
        return [output_segment(ctx, out, "sine")]

    @staticmethod
    def analyzed(run: Run, params: SineParams, ctx: RigContext) -> OutputTrack:
        """The sine segment after the skipped periods."""
        rows = segment_rows(run, "sine")
        skip = ctx.cycles(params.skip_periods / params.freq_hz) if params.skip_periods else 0
        return output_track(run, ctx, slice(rows.start + skip, rows.stop))

    def analyze(self, run: Run, params: SineParams, ctx: RigContext) -> Results:
        track = self.analyzed(run, params, ctx)
        set_phasor = fit_phasor(track.t_s, track.setpoint, params.freq_hz)
        metrics: dict[str, float | int | str] = {"freq_hz": params.freq_hz}
        for side, _ in SIDES:
            prefix = "" if side == "load" else "motor_"
            y = getattr(track, side)
            error = y - track.setpoint
            phasor = fit_phasor(track.t_s, y, params.freq_hz)
            metrics[f"{prefix}rms_error_rad"] = float(np.sqrt(np.mean(error**2)))
            metrics[f"{prefix}max_error_rad"] = float(np.max(np.abs(error)))
            metrics[f"{prefix}gain"] = abs(phasor) / abs(set_phasor)
            metrics[f"{prefix}phase_lag_deg"] = float(np.degrees(np.angle(set_phasor * phasor.conjugate())))
        return Results(metrics)

    def plot(
        self, run: Run, results: Results, params: SineParams, ctx: RigContext, out_dir: Path
    ) -> list[Path]:
        fig, ax = new_figure(
            f"Sine tracking at {params.freq_hz:g} Hz, {params.amp_out_rad:g} rad at the output", 2
        )
        track = output_track(run, ctx, segment_rows(run, "sine"))
        start_s = params.skip_periods / params.freq_hz
        ax.plot(track.t_s, track.setpoint, color="0.3", lw=1, label="set-point")
        ax.plot(track.t_s, track.load, lw=0.8, label="load θ_l")
        ax.set_ylabel("output angle from the start [rad]")
        ax.legend(fontsize=8)
        err_ax = fig.axes[1]
        rms = results.metrics["rms_error_rad"]
        err_ax.plot(track.t_s, track.load - track.setpoint, lw=0.8, label=f"load θ_l (RMS {rms:.2g} rad)")
        err_ax.plot(track.t_s, track.motor - track.setpoint, lw=0.8, label="motor r·θ_m")
        err_ax.axvspan(start_s, track.t_s[-1], color="C2", alpha=0.08, label="analyzed")
        err_ax.set_xlabel("time [s]")
        err_ax.set_ylabel("tracking error [rad]")
        err_ax.legend(fontsize=8)
        return [save_figure(fig, out_dir / "sine_tracking.png")]


# --- ramp ------------------------------------------------------------------------------------------------


class RampParams(ExperimentParams):
    # 0.002 rad/s at the output is 0.2 rad/s at the motor: slow enough that the kinematic error's speed
    # (A·k·ω_m, 5× the ramp's on the seed) makes the output stick and slip, fast enough for the encoder
    # (≈ 4 counts per cycle at 17 bits) to see the motor's speed.
    speed_out_rad_s: float = Field(
        default=0.002, gt=0, le=0.1, description="ramp speed at the output, up then down [rad/s]"
    )
    duration_s: float = Field(default=4.0, ge=1.0, le=60, description="time of each direction [s]")
    skip_s: float = Field(
        default=0.5,
        ge=0,
        le=10,
        validate_default=True,
        description="start of each direction left out of the amplitude [s]",
    )
    # Stuck means still, not slow: 5 % of the ramp speed is 1e-4 rad/s at the output, ~4 σ of the speed
    # that the 41-sample derivative makes of 2 µrad load-sensor noise, and far below the dips of a
    # frictionless motor rocked by the load mode (figures: docs/BENCHMARKS.md, "Figures behind design
    # choices in the code").
    stick_speed_fraction: float = Field(
        default=0.05, gt=0, lt=1, description="a side is stuck below this share of its ramp speed [–]"
    )
    min_stick_s: float = Field(
        default=0.02, gt=0, le=1, description="shortest span counted as a stick phase [s]"
    )
    speed_window_s: float = Field(
        default=0.041,
        ge=0.005,
        le=0.5,
        description="window of the smoothing derivative (Savitzky–Golay) that gives the speeds [s]",
    )

    @field_validator("skip_s")
    @classmethod
    def _within_duration(cls, skip_s: float, info: ValidationInfo) -> float:
        duration_s = info.data.get("duration_s")
        if duration_s is not None and skip_s >= duration_s / 2:
            raise ValueError(f"must be under half of duration_s ({duration_s} s)")
        return skip_s


RAMP_LABELS = ("ramp-up", "ramp-down")


def detrended(t_s: np.ndarray, y: np.ndarray) -> np.ndarray:
    """y less its least-squares straight line."""
    return y - np.polyval(np.polyfit(t_s, y, 1), t_s)


def stuck_spans(speed: np.ndarray, threshold: float, min_cycles: int) -> tuple[np.ndarray, np.ndarray]:
    """Start and end rows (end exclusive) of the spans of at least min_cycles where |speed| < threshold."""
    stuck = np.concatenate([[0], (np.abs(speed) < threshold).astype(np.int8), [0]])
    edges = np.diff(stuck)
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    keep = ends - starts >= min_cycles
    return starts[keep], ends[keep]


def smoothed_speed(y: np.ndarray, params: RampParams, ctx: RigContext, deriv: int = 1) -> np.ndarray:
    """dy/dt (d²y/dt² with deriv=2) from a quadratic Savitzky–Golay fit over speed_window_s: quiets
    encoder steps and noise."""
    window = max(5, ctx.cycles(params.speed_window_s) | 1)
    return np.asarray(signal.savgol_filter(y, window, 2, deriv=deriv, delta=1.0 / ctx.rate_hz))


KE_MAX_CYCLES_PER_TURN = 500
"""Highest cycles per motor turn the kinematic error is looked for at (whole numbers: the error repeats
with the wave generator's turn) [1/turn]."""


def kinematic_error_fit(
    tracks: list[OutputTrack],
    r: float,
    sliding: list[np.ndarray],
    direction: list[np.ndarray],
    acceleration: list[np.ndarray],
) -> tuple[float, list[np.ndarray]]:
    """The kinematic error as a sinusoid in the motor angle, from the transmission error θ_l − r·θ_m
    (= kinematic error − twist) of the ramp's directions, on the samples where the load slides (`sliding`,
    one mask per track): a stuck load holds θ_l while the error turns, the spring taking it up, which
    would bias the fit low. Sliding, the twist is the load friction's level over K_s on the side the
    load slides (`direction`, ±1), plus J_l/K_s times the load's `acceleration` (its slips and the load
    mode), plus a constant per track: all fitted beside the sinusoid. Cycles
    per motor turn k: the whole number whose sinusoid fits best. Returns k and the fitted error along
    each track [1/turn, rad]."""
    angles = [track.motor / r for track in tracks]  # motor angle from the start [rad]
    errors = [track.load - track.motor for track in tracks]
    n_tracks = len(tracks)
    theta = np.concatenate([a[m] for a, m in zip(angles, sliding, strict=True)])
    e = np.concatenate([x[m] for x, m in zip(errors, sliding, strict=True)])
    side = np.concatenate([d[m] for d, m in zip(direction, sliding, strict=True)])
    accel = np.concatenate([a[m] for a, m in zip(acceleration, sliding, strict=True)])
    which = np.concatenate([np.full(int(np.sum(m)), i) for i, m in enumerate(sliding)])
    rest = np.column_stack([side, accel, *[(which == i).astype(float) for i in range(n_tracks)]])

    def fit(k: float) -> tuple[float, np.ndarray]:
        basis = np.column_stack([np.cos(k * theta), np.sin(k * theta), rest])
        coef, residual, *_ = np.linalg.lstsq(basis, e, rcond=None)
        return float(residual[0]) if residual.size else float(np.sum((basis @ coef - e) ** 2)), coef

    if theta.size < 8:
        return float("nan"), [np.zeros_like(a) for a in angles]
    # Coarse: the projection on cos/sin at each whole k, then the best few refitted with the rest.
    ks = np.arange(1, KE_MAX_CYCLES_PER_TURN + 1, dtype=float)
    centred = e - np.mean(e)
    power = np.array([abs(np.exp(-1j * k * theta) @ centred) for k in ks])
    candidates = ks[np.argsort(power)[-5:]]
    k = float(min(candidates, key=lambda c: fit(c)[0]))
    coef = fit(k)[1]
    return k, [coef[0] * np.cos(k * a) + coef[1] * np.sin(k * a) for a in angles]


class Ramp(Experiment):
    name = "ramp"
    start_on_turn: ClassVar[bool] = True  # the runner starts it at θ_m = 0 (rig.runner._approach_turn)
    summary = (
        "slow output ramp up and down; ripple of the load angle, its kinematic error and stick-slip apart,"
        " stick phases"
    )
    Params = RampParams
    needs = frozenset({ControlMode.POSITION})

    def program(self, params: RampParams, ctx: RigContext) -> list[Segment]:
        travel = params.speed_out_rad_s * params.duration_s
        check_stroke(ctx, 0.0, travel, self.name, "duration_s")
        k = np.arange(1, ctx.cycles(params.duration_s) + 1)
        up = params.speed_out_rad_s * k / ctx.rate_hz
        return [output_segment(ctx, up, RAMP_LABELS[0]), output_segment(ctx, up[-1] - up, RAMP_LABELS[1])]

    def analyze(self, run: Run, params: RampParams, ctx: RigContext) -> Results:
        skip = ctx.cycles(params.skip_s)
        table: dict[str, list[float]] = {"direction": []}
        tracks, sliding, direction, acceleration = [], [], [], []
        for label in RAMP_LABELS:
            rows = segment_rows(run, label)
            track = output_track(run, ctx, slice(rows.start + skip, rows.stop))
            speed = smoothed_speed(track.load, params, ctx)
            tracks.append(track)
            sliding.append(np.abs(speed) >= params.stick_speed_fraction * params.speed_out_rad_s)
            direction.append(np.sign(speed))
            acceleration.append(smoothed_speed(track.load, params, ctx, deriv=2))
        cycles_per_turn, kinematic = kinematic_error_fit(
            tracks, ctx.gear_ratio, sliding, direction, acceleration
        )
        for label, track, ke in zip(RAMP_LABELS, tracks, kinematic, strict=True):
            table["direction"].append(1.0 if label == RAMP_LABELS[0] else -1.0)
            for side, _ in SIDES:
                residual = detrended(track.t_s, getattr(track, side) - track.setpoint)
                table.setdefault(f"{side}_pp_rad", []).append(float(np.ptp(residual)))
                table.setdefault(f"{side}_rms_rad", []).append(float(np.sqrt(np.mean(residual**2))))
            stick = detrended(track.t_s, track.load - ke - track.setpoint)
            table.setdefault("load_stick_slip_pp_rad", []).append(float(np.ptp(stick)))
            table.setdefault("load_stick_slip_rms_rad", []).append(float(np.sqrt(np.mean(stick**2))))
            table.setdefault("kinematic_error_pp_rad", []).append(float(np.ptp(ke)))
        columns = {name: np.asarray(values) for name, values in table.items()}
        metrics: dict[str, float | int | str] = {
            "ripple_pp_rad": float(np.mean(columns["load_pp_rad"])),
            "ripple_rms_rad": float(np.mean(columns["load_rms_rad"])),
            "kinematic_error_pp_rad": float(np.mean(columns["kinematic_error_pp_rad"])),
            "kinematic_error_cycles_per_turn": cycles_per_turn,
            "stick_slip_pp_rad": float(np.mean(columns["load_stick_slip_pp_rad"])),
            "stick_slip_rms_rad": float(np.mean(columns["load_stick_slip_rms_rad"])),
            "motor_stick_slip_pp_rad": float(np.mean(columns["motor_pp_rad"])),
        }
        track = output_track(run, ctx, program_rows(run))
        for side, _ in SIDES:
            starts, ends = self.stuck(track, side, params, ctx)
            metrics[f"stick_phases_{side}"] = len(starts)
            metrics[f"stuck_fraction_{side}"] = float(np.sum(ends - starts) / len(track.t_s))
        return Results(metrics, {"ramp_directions": columns})

    @staticmethod
    def stuck(
        track: OutputTrack, side: str, params: RampParams, ctx: RigContext
    ) -> tuple[np.ndarray, np.ndarray]:
        """Stick phases of one side over a track: spans slower than the threshold (rows, end exclusive)."""
        speed = smoothed_speed(getattr(track, side), params, ctx)
        threshold = params.stick_speed_fraction * params.speed_out_rad_s  # both sides seen at the output
        return stuck_spans(speed, threshold, ctx.cycles(params.min_stick_s))

    def plot(
        self, run: Run, results: Results, params: RampParams, ctx: RigContext, out_dir: Path
    ) -> list[Path]:
        fig, ax = new_figure(
            f"Low-speed ramp, {params.speed_out_rad_s:g} rad/s at the output, up and down", 2
        )
        track = output_track(run, ctx, program_rows(run))
        pp, stick = results.metrics["ripple_pp_rad"], results.metrics["stick_slip_pp_rad"]
        ax.plot(
            track.t_s,
            track.load - track.setpoint,
            lw=0.8,
            label=f"load θ_l (ripple {pp:.2g} rad p-p, of which stick-slip {stick:.2g})",
        )
        ax.plot(track.t_s, track.motor - track.setpoint, lw=0.8, label="motor r·θ_m")
        ax.set_ylabel("tracking error [rad]")
        ax.legend(fontsize=8)
        speed_ax: Axes = fig.axes[1]
        for colour, (side, symbol) in zip(("C0", "C1"), SIDES, strict=True):
            speed_ax.plot(
                track.t_s, smoothed_speed(getattr(track, side), params, ctx), colour, lw=0.8, label=symbol
            )
            starts, ends = self.stuck(track, side, params, ctx)
            for start, end in zip(starts, ends, strict=True):
                speed_ax.axvspan(track.t_s[start], track.t_s[end - 1], color=colour, alpha=0.15, lw=0)
        speed_ax.axhline(params.speed_out_rad_s, color="0.5", lw=0.8, ls="--")
        speed_ax.axhline(-params.speed_out_rad_s, color="0.5", lw=0.8, ls="--")
        speed_ax.set_xlabel("time [s]")
        speed_ax.set_ylabel("speed at the output [rad/s] (stuck spans shaded)")
        speed_ax.legend(fontsize=8)
        return [save_figure(fig, out_dir / "ramp_stick_slip.png")]
