"""Plays an experiment on a rig into the store, then analyzes it. The CLI and the service both call this.

Flow: open the rig named by the config → enable → a short settle segment to read where the motor is →
the experiment's program, segment by segment, each block of samples appended to the store as it comes
(flushed at least once a second) → on a breach the run is finished `aborted: <reason>` with its data →
otherwise `complete`, then the analysis writes tables, plots and metrics beside the run. A device fault
(`rig.faults.DeviceFaultError`) mid-run quick-stops the rig and ends the run `aborted: <fault>`, data kept.

The application core (`rig.core`) calls this for the command line and the service alike.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from pydantic import ValidationError

from model.errors import UserInputError, describe_validation_error
from model.run import Run
from rig.config import RigConfig
from rig.experiments import experiment_named
from rig.experiments.base import Experiment, ExperimentParams, Observer, Results, RigContext, context_from_run
from rig.experiments.tracking import ZERO_WINDOW_S
from rig.faults import DeviceFaultError
from rig.interface import SAMPLE_COLUMNS, Block, ControlMode, Rig, Segment, SegmentResult, open_rig
from rig.status import RunStatus
from rig.store.runfile import json_text
from rig.store.runs import PART_ROWS_MAX, AnalysisState, RunStore, RunWriter

logger = logging.getLogger(__name__)

SETTLE_S = 0.2
"""Shortest hold before a program [s]."""
SETTLE_MAX_S = 4.0
"""Longest hold waiting for the output to come to rest [s]: a gear that still moves then is said so in the
run's metadata (`settle`) and its results' notes, and the program starts anyway."""
REST_WINDOW_S = ZERO_WINDOW_S
"""The output is at rest when its motion over the last such window is at its noise; the same window the
tracking experiments average for their zero, so the zero is taken at rest."""
APPROACH_S = 0.5
"""Shortest time of the move to the stroke's origin before an experiment that starts there
(`start_on_turn`) [s]."""
APPROACH_SPEED_RAD_S = 10.0
"""Top motor speed of the approach's move; a longer move takes longer [rad/s]."""
APPROACH_HOLD_S = 0.05
"""After the move, the approach holds the turn in position mode in stretches of this length [s] ..."""
APPROACH_HOLD_MAX_S = 4.0
"""... until the motor is within APPROACH_COUNTS encoder counts of the turn, at most this long [s]: the
position loop's P stalls on the motor's friction a few mrad off, and the speed loop's integral, fed by
that error, takes it the rest of the way; a motor still off then is said so in the run's metadata
(`approach`) and the program starts anyway."""
UNLOAD_S = 0.2
"""Time of the speed set-point that unloads the speed loop's integral after the approach [s]."""
UNLOAD_WINDOW_S = 0.02
"""The motor is held still when its encoder did not move over this last stretch of the hold [s]."""
UNLOAD_SPEED_MAX_RAD_S = 1.0
"""Largest motor speed the unloading asks [rad/s]."""
APPROACH_COUNTS = 1.0
"""The turn is reached within this many motor encoder counts (what the encoder resolves; 2 µrad
when it is ideal) [counts]."""
REST_NOISE_FACTOR = 3.0
"""At rest: θ_l's spread over the window at most this many times its noise (1 σ each); pure noise has a
spread of 1 σ, a ring of amplitude a a spread of a/√2."""
Progress = Callable[[str, float], None]
"""Called with a label (experiment or segment) and the fraction of the whole job done, 0..1."""


@dataclass(frozen=True)
class RunHooks:
    """What a caller may watch while a run records (the rig worker's events). Each is called on the
    control loop's thread and must return at once."""

    on_start: Callable[[str], None] | None = None  # the run's id, once it is in the catalog
    on_block: Callable[[str, Block], None] | None = None  # each block of samples as it is recorded
    on_segment: Callable[[str, Segment], None] | None = None  # each segment as it begins
    run_id: str | None = None  # an id reserved beforehand (the service's queued runs)
    unit: str | None = None  # the gear on the bench, when not the rig file's `unit:`
    operator: str | None = None  # who started the run (an API key's name); None: this process' OS user
    tags: list[str] = field(default_factory=list)  # free tags for the catalog


@dataclass
class RunOutcome:
    """One experiment's run: where it is, how it ended, what it measured."""

    run_id: str
    experiment: str
    status: RunStatus
    reason: str | None = None
    metrics: dict[str, Any] = field(default_factory=dict)
    artifacts: list[Path] = field(default_factory=list)
    run_dir: Path | None = None
    fault: str | None = None  # the device fault that ended it, if one did


def parse_overrides(experiment: str, pairs: Sequence[str]) -> dict[str, Any]:
    """`--set key=value` pairs as a dict; values read as YAML scalars (numbers, lists, booleans)."""
    out: dict[str, Any] = {}
    for pair in pairs:
        key, sep, text = pair.partition("=")
        if not sep or not key.strip():
            raise UserInputError(f"run {experiment}: --set {pair!r} is not key=value")
        out[key.strip()] = yaml.safe_load(text)
    return out


def make_params(experiment: Experiment, overrides: dict[str, Any]) -> ExperimentParams:
    try:
        return experiment.Params.model_validate(overrides)
    except ValidationError as exc:
        raise UserInputError(f"run {experiment.name}: {describe_validation_error(exc)}") from None


def _virtual_time(rig: Rig) -> bool:
    """Whether the rig is the in-process simulation on a clock of its own (not paced to the wall clock):
    nothing is late when its control loop waits. Not a rig on a bus, simulated devices or not: their
    heartbeats and timeouts run on the wall clock."""
    return rig.config.backend == "sim" and rig.config.pace == "virtual"


@dataclass(frozen=True)
class Settled:
    """How the runner's settle ended: where the motor held, for how long, and whether the output came to
    rest (its motion over the last REST_WINDOW_S at its noise) within SETTLE_MAX_S."""

    theta_m_rad: float
    duration_s: float
    at_rest: bool
    motion_rad: float  # spread (1 σ) of θ_l over the last rest window
    noise_rad: float  # θ_l's noise (1 σ) estimated from its second differences over that window
    aborted: str | None = None

    def meta(self) -> dict[str, Any]:
        return {
            "duration_s": self.duration_s,
            "at_rest": self.at_rest,
            "motion_rad": self.motion_rad,
            "noise_rad": self.noise_rad,
            "max_s": SETTLE_MAX_S,
        }


def output_motion(theta_l: np.ndarray) -> tuple[float, float]:
    """(motion, noise) of a window of θ_l [rad, 1 σ]: its spread about its mean, and the noise that the
    second differences show (white noise of σ gives var(Δ²) = 6σ²; a ring at the load mode's 11 Hz
    barely shows in Δ² at 1 kHz, so the estimate is not swamped by the motion it is compared with)."""
    if theta_l.size == 0:  # a stop before the first sample: nothing seen, nothing at rest
        return float("nan"), float("nan")
    motion = float(np.std(theta_l))
    noise = float(np.std(np.diff(theta_l, 2)) / np.sqrt(6.0)) if theta_l.size > 3 else 0.0
    return motion, noise


def _at_rest(motion_rad: float, noise_rad: float) -> bool:
    return motion_rad <= REST_NOISE_FACTOR * noise_rad


def _settle(
    rig: Rig, sink: Callable[[dict[str, np.ndarray]], None], duration_s: float | None = None
) -> Settled:
    """Hold still (velocity 0) for at least SETTLE_S and until the output is at rest, at most SETTLE_MAX_S;
    `duration_s` holds exactly that long instead (a replay of a run holds as long as the run did)."""
    rate_hz = rig.config.sample_rate_hz
    window = max(4, round(REST_WINDOW_S * rate_hz))
    tail: dict[str, np.ndarray] = {"theta_m": np.empty(0), "theta_l": np.empty(0)}

    def keep(block: dict[str, np.ndarray]) -> None:
        for name in tail:
            tail[name] = np.concatenate([tail[name], np.asarray(block[name])])[-window:]
        sink(block)

    if duration_s is not None:
        plan = [max(1, round(duration_s * rate_hz))]
    else:
        first = max(window, round(SETTLE_S * rate_hz))
        plan = [first] + [window] * max(0, (round(SETTLE_MAX_S * rate_hz) - first) // window)
    cycles = 0
    motion, noise, aborted = float("nan"), float("nan"), None
    for n in plan:
        result = rig.run_segment(Segment(ControlMode.VELOCITY, np.zeros(n), 0.0, "settle"), keep)
        cycles += n
        aborted = result.aborted
        motion, noise = output_motion(tail["theta_l"])
        if aborted is not None or (duration_s is None and _at_rest(motion, noise)):
            break
    theta_m = float(tail["theta_m"][-1]) if tail["theta_m"].size else float("nan")
    return Settled(theta_m, cycles / rate_hz, _at_rest(motion, noise), motion, noise, aborted)


@dataclass(frozen=True)
class Approached:
    """How the approach to the stroke's origin ended: the turn aimed at, how far off the motor stopped,
    how long the hold after the move took, whether it came within APPROACH_COUNTS encoder counts, and the
    current the speed loop's integral held before it was unloaded."""

    target_rad: float
    error_rad: float
    hold_s: float
    within: bool
    tolerance_rad: float
    held_current_a: float = 0.0
    aborted: str | None = None

    def meta(self) -> dict[str, Any]:
        return {
            "target_rad": self.target_rad,
            "error_rad": self.error_rad,
            "hold_s": self.hold_s,
            "within": self.within,
            "tolerance_rad": self.tolerance_rad,
            "hold_max_s": APPROACH_HOLD_MAX_S,
            "held_current_a": self.held_current_a,
        }


def approach_tolerance_rad(rig: Rig) -> float:
    """How close to the turn the approach brings the motor [rad]: APPROACH_COUNTS encoder counts (an ideal
    encoder: the load sensor's noise)."""
    counts = rig.config.sensors.encoder_counts_per_rev
    return APPROACH_COUNTS * 2 * np.pi / counts if counts else rig.config.sensors.load_sensor_noise_rad


class _Tail:
    """A sink that keeps the last samples of the motor's angle, speed and current command."""

    def __init__(self, sink: Callable[[dict[str, np.ndarray]], None], length: int) -> None:
        self.sink, self.length = sink, length
        self.rows: dict[str, np.ndarray] = {name: np.empty(0) for name in ("theta_m", "omega_m", "i_cmd")}

    def __call__(self, block: dict[str, np.ndarray]) -> None:
        for name, kept in self.rows.items():
            self.rows[name] = np.concatenate([kept, np.asarray(block[name], dtype=float)])[-self.length :]
        self.sink(block)

    @property
    def theta_m(self) -> float:
        return float(self.rows["theta_m"][-1]) if self.rows["theta_m"].size else float("nan")


def _approach_turn(rig: Rig, sink: Callable[[dict[str, np.ndarray]], None]) -> Approached:
    """Move the motor to the stroke's origin, θ_m = 0 (a whole turn), and hold it there (`approach`),
    before the settle: an experiment whose metrics depend on the angle it starts at then starts where a
    freshly started rig does, whatever ran before it. Not only the turn's phase counts (the kinematic
    error and the friction's ripple repeat every motor turn), also which turn: the friction's slow level
    C(θ_m) is a polynomial over the stroke, and a step started one turn up (the nearest turn after the
    campaign's earlier experiments) overshot measurably more than one started at 0 (figures:
    docs/BENCHMARKS.md, "Figures behind design choices in the code"). The move is half a
    cosine, at most APPROACH_SPEED_RAD_S; then the position loop holds the turn, in stretches of
    APPROACH_HOLD_S, until the motor is within `approach_tolerance_rad` of it (at most
    APPROACH_HOLD_MAX_S, what is left said in the run's metadata); then the current left in the speed
    loop's integral is unloaded (`_unload_speed_integral`), so the program starts as on a freshly
    enabled drive."""
    rate_hz = rig.config.sample_rate_hz
    tolerance = approach_tolerance_rad(rig)
    tail = _Tail(sink, max(4, round(UNLOAD_WINDOW_S * rate_hz)))

    def ended(target: float, hold_s: float, held_a: float, aborted: str | None) -> Approached:
        error = tail.theta_m - target
        return Approached(target, error, hold_s, bool(abs(error) <= tolerance), tolerance, held_a, aborted)

    hold = Segment(ControlMode.VELOCITY, np.zeros(max(1, round(SETTLE_S * rate_hz))), 0.0, "settle-before")
    result = rig.run_segment(hold, tail)
    if result.aborted is not None or not np.isfinite(tail.theta_m):
        return ended(float("nan"), 0.0, 0.0, result.aborted)
    start = tail.theta_m
    target = 0.0
    # Half a cosine: starts and ends at rest, at most APPROACH_SPEED_RAD_S at the motor.
    duration_s = max(APPROACH_S, np.pi / 2 * abs(target - start) / APPROACH_SPEED_RAD_S)
    phase = np.linspace(0.0, np.pi, max(2, round(duration_s * rate_hz)))
    path = start + (target - start) * (1.0 - np.cos(phase)) / 2
    move = Segment(ControlMode.POSITION, path, 0.0, "approach")
    rig.check_segment(move)
    result = rig.run_segment(move, tail)
    stretch = max(1, round(APPROACH_HOLD_S * rate_hz))
    still = Segment(ControlMode.POSITION, np.full(stretch, target), 0.0, "approach")
    cycles = 0
    # At least one stretch, even where the move ended within the tolerance: the unload reads the current
    # the hold leaves, from a window in which the motor was held, not the move's last rows (a move ending
    # on the turn left its integral, 2.7 A, unread and unloaded).
    while (
        result.aborted is None
        and (cycles == 0 or abs(tail.theta_m - target) > tolerance)
        and cycles + stretch <= round(APPROACH_HOLD_MAX_S * rate_hz)
    ):
        result = rig.run_segment(still, tail)
        cycles += stretch
    held_a = 0.0
    if result.aborted is None:
        held_a, result = _unload_speed_integral(rig, tail)
    return ended(target, cycles / rate_hz, held_a, result.aborted)


def _unload_speed_integral(rig: Rig, tail: _Tail) -> tuple[float, SegmentResult]:
    """Bring the speed loop's integral back to zero while the motor's friction holds it still; the
    current held before (0 if nothing was done) and how the segment ended.

    The approach's hold leaves the motor stuck with the current that broke it free still in the
    integral (near the static friction's level), where a run on a freshly enabled drive starts from 0;
    a step started so overshot measurably more. At rest (ω = 0 over UNLOAD_WINDOW_S) that
    integral is the commanded current i, and a speed set-point ω_ref moves it by K_i·∫ω_ref dt while the
    motor stays stuck: a half-sine of speed against i, of area −i/K_i over UNLOAD_S, takes it to 0
    (`unload`). The current then moves only towards zero, away from the breakaway level, so the motor
    stays where it is; the speed asked is at most UNLOAD_SPEED_MAX_RAD_S (an integral beyond what that
    unloads is unloaded that far)."""
    control, rate_hz = rig.config.control, rig.config.sample_rate_hz
    angle, current = tail.rows["theta_m"], tail.rows["i_cmd"]
    if control.velocity_ki <= 0 or angle.size == 0 or np.ptp(angle) >= approach_tolerance_rad(rig):
        return 0.0, SegmentResult(0)  # no integral, or the motor is not held still: nothing to unload
    held_a = float(np.mean(current))
    cycles = max(2, round(UNLOAD_S * rate_hz))
    shape = np.sin(np.pi * (np.arange(cycles) + 0.5) / cycles)
    area = -held_a / control.velocity_ki  # ∫ω_ref dt [rad]
    peak = float(np.clip(area * rate_hz / np.sum(shape), -UNLOAD_SPEED_MAX_RAD_S, UNLOAD_SPEED_MAX_RAD_S))
    unload = Segment(ControlMode.VELOCITY, peak * shape, 0.0, "unload")
    rig.check_segment(unload)
    return held_a, rig.run_segment(unload, tail)


def _save_results(store: RunStore, run_id: str, results: Results) -> list[Path]:
    paths = []
    for name, table in results.tables.items():
        path = store.add_artifact(run_id, f"{name}.csv")
        names = list(table)
        rows = np.column_stack([np.asarray(table[n], dtype=np.float64) for n in names])
        np.savetxt(path, rows, delimiter=",", header=",".join(names), comments="", fmt="%.10g")
        paths.append(path)
    summary = store.add_artifact(run_id, "results.json")
    summary.write_text(json_text({"metrics": results.metrics, "notes": results.notes}, indent=2) + "\n")
    paths.append(summary)
    return paths


def run_experiment(
    name: str,
    config: RigConfig,
    overrides: dict[str, Any] | None = None,
    store: RunStore | None = None,
    progress: Progress | None = None,
    rig: Rig | None = None,
    hooks: RunHooks | None = None,
    settle_s: float | None = None,
) -> RunOutcome:
    """Run one experiment on the rig `config` names (or on `rig`), store it, analyze it. The settle before
    the program lasts until the output is at rest, or exactly `settle_s` if given (a replay)."""
    experiment = experiment_named(name)
    params = make_params(experiment, overrides or {})
    store = store or RunStore()
    own_rig = rig is None
    rig = rig or open_rig(config)
    try:
        # Up front, before anything moves: a mode the rig cannot play is refused (ModeRefusedError).
        modes = rig.check_modes(sorted({ControlMode.VELOCITY, *experiment.needs}))  # VELOCITY: the settle
        for line in modes:
            logger.info("%s: %s", experiment.name, line)
        return _play(experiment, params, rig, store, progress, hooks or RunHooks(), modes, settle_s)
    finally:
        if own_rig:
            rig.close()


def _play(
    experiment: Experiment,
    params: ExperimentParams,
    rig: Rig,
    store: RunStore,
    progress: Progress | None,
    hooks: RunHooks,
    modes: list[str],
    settle_s: float | None = None,
) -> RunOutcome:
    config = rig.config
    rig.enable()
    # A run's clock starts at its own first sample, also on a rig kept open across runs (the rig worker).
    t_origin_s = rig.t_s
    columns = [*SAMPLE_COLUMNS, *rig.extra_columns]
    model = rig.model
    meta: dict[str, Any] = {
        "sample_rate_hz": config.sample_rate_hz,
        "source": rig.source,
        "experiment": experiment.name,
        "rig": config.name,
        "params": params.model_dump(mode="json"),
        "rig_config": config.model_dump(mode="json"),
        "gear_ratio": rig.gear_ratio,
        "torque_constant_nm_per_a": rig.torque_constant_nm_per_a,
        "rig_modes": modes,  # how the rig plays each kind of program, and why (a drive's chosen modes)
        "rig_time_origin_s": t_origin_s,  # the rig clock at the run's t = 0
    }
    writer = store.open_run(
        experiment=experiment.name,
        rig=config.name,
        model_name=model.name if model else None,
        model_hash=model.content_hash() if model else None,
        columns=columns,
        meta=meta,
        background=True,  # the control loop appends; a writer thread takes the disk's time
        # In virtual time the simulation would outrun a busy writer thread: the loop waits for the disk
        # once a part's worth of rows is pending, so a run's memory does not depend on the machine's load.
        max_pending_rows=PART_ROWS_MAX if _virtual_time(rig) else None,
        run_id=hooks.run_id,
        unit=hooks.unit or config.unit,
        operator=hooks.operator,
        tags=hooks.tags,
    )
    if hooks.on_start is not None:
        hooks.on_start(writer.run_id)
    tap, run_id = hooks.on_block, writer.run_id

    def sink(block: Block) -> None:
        block = {**block, "t": block["t"] - t_origin_s}
        writer.append(block)
        if tap is not None:
            tap(run_id, block)

    rig.record_raw_to(writer.run_dir)
    with writer:
        fault = None
        try:
            reason, ctx = _record(experiment, params, rig, writer, sink, progress, hooks, settle_s)
        except DeviceFaultError as exc:
            rig.quick_stop()  # first the motor, then the bookkeeping
            fault = str(exc)
            reason = f"aborted: {fault}"
        except BaseException:
            # One stop path: a bug, a signal or Ctrl-C stops the motor before the writer seals (sealing a
            # long run takes a second or more of motion otherwise); the writer then ends it `aborted`.
            rig.quick_stop()
            raise
        if reason is not None:
            writer.finish(RunStatus.ABORTED, reason=reason)
            return RunOutcome(
                writer.run_id, experiment.name, RunStatus.ABORTED, reason, run_dir=writer.run_dir, fault=fault
            )
        rig.disable()
        writer.finish(RunStatus.COMPLETE)
    if writer.final_status == RunStatus.ABORTED:  # the store could not keep it all (a full disk)
        reason = writer.final_reason or "aborted"
        return RunOutcome(
            writer.run_id, experiment.name, RunStatus.ABORTED, reason, run_dir=writer.run_dir,
            fault=reason.removeprefix("aborted: "),
        )  # fmt: skip
    return _analyze(store, writer.run_id, experiment, params, ctx)


def _analyze(
    store: RunStore, run_id: str, experiment: Experiment, params: ExperimentParams, ctx: RigContext
) -> RunOutcome:
    """Tables, plots and metrics of a complete run, its analysis state kept in the catalog throughout."""
    store.set_analysis(run_id, AnalysisState.RUNNING)  # a process killed from here on leaves it `interrupted`
    try:
        run = _read_for_analysis(store, run_id, experiment, params)
        results = experiment.analyze_parts(
            lambda labels: store.read(run_id, segments=labels), run, params, ctx
        )
        if results is None:
            results = experiment.analyze(run, params, ctx)
        settle = store.get(run_id)["meta"].get("settle")
        if settle and not settle.get("at_rest", True):
            results.notes.append(
                f"the output was still moving when the program started: after {settle['duration_s']:.3g} s"
                f" of holding still its motion was {settle['motion_rad']:.3g} rad against its noise of"
                f" {settle['noise_rad']:.3g} rad (1 σ); a zero taken then is off by up to that motion"
            )
        artifacts = _save_results(store, run_id, results)
        plot_dir = store.add_artifact(run_id, "plots")
        plot_dir.mkdir(parents=True, exist_ok=True)
        artifacts += experiment.plot(run, results, params, ctx, plot_dir)
        store.set_metrics(run_id, results.metrics)
        if results.checkpoints:
            # the gear the run recorded (its own unit, else the rig file's), so the trend follows the gear
            store.set_checkpoints(run_id, store.get(run_id)["unit"] or ctx.config.unit, results.checkpoints)
    except Exception:
        store.set_analysis(run_id, AnalysisState.FAILED)
        raise
    store.set_analysis(run_id, AnalysisState.DONE)
    return RunOutcome(
        run_id, experiment.name, RunStatus.COMPLETE, None, results.metrics, artifacts, store.run_dir(run_id)
    )


def analyze_stored(store: RunStore, run_id: str) -> RunOutcome:
    """Analyze a complete run in the store again, from its data and metadata (an analysis that was
    interrupted or failed, or one made with older code)."""
    entry = store.get(run_id)
    if entry["status"] != RunStatus.COMPLETE:
        raise UserInputError(
            f"run {run_id} is {entry['reason'] or entry['status']}: only a complete run has an analysis"
        )
    experiment = experiment_named(entry["experiment"])
    params = make_params(experiment, dict(entry["meta"].get("params") or {}))
    # The rig context from the catalog's metadata alone: _analyze reads only the rows the analysis needs
    # (a long run's checkpoints, not its hours of duty cycle).
    ctx = context_from_run(Run({}, entry["meta"]), where=f"run {run_id}")
    return _analyze(store, run_id, experiment, params, ctx)


def _record(
    experiment: Experiment,
    params: ExperimentParams,
    rig: Rig,
    writer: RunWriter,
    sink: Callable[[Block], None],
    progress: Progress | None,
    hooks: RunHooks,
    settle_s: float | None = None,
) -> tuple[str | None, RigContext]:
    """Settle, then play the program; (abort reason or None, the rig context the program ran in)."""
    config = rig.config
    if getattr(experiment, "start_on_turn", False):
        approached = _approach_turn(rig, sink)
        writer.update_meta({"approach": approached.meta()})
        if approached.aborted is not None:
            nan = float("nan")
            return approached.aborted, RigContext(config, rig.gear_ratio, rig.torque_constant_nm_per_a, nan)
    settled = _settle(rig, sink, settle_s)
    theta_m0 = settled.theta_m_rad
    writer.flush_soon()  # each segment's rows on disk as it ends (a virtual-time run outpaces the interval)
    writer.update_meta({"settle": settled.meta()})
    ctx = RigContext(config, rig.gear_ratio, rig.torque_constant_nm_per_a, theta_m0)
    if settled.aborted is not None:
        return settled.aborted, ctx
    program = experiment.program(params, ctx)
    labels = [seg.label for seg in program]
    if len(set(labels)) != len(labels):
        raise ValueError(f"experiment {experiment.name}: segment labels must be unique, got {labels}")
    for seg in program:
        rig.check_segment(seg)  # refuse the whole program before any of it moves the motor
    start = writer.appended
    segments = []
    for seg in program:
        segments.append({"label": seg.label, "mode": str(seg.mode), "start": start, "cycles": seg.cycles})
        start += seg.cycles
    input_column = "u" if all(seg.mode == ControlMode.VOLTAGE for seg in program) else "i_cmd"
    writer.update_meta({"segments": segments, "input_column": input_column, "theta_m0": theta_m0})
    observer = experiment.observer(params, ctx, program)
    if observer is not None:
        sink = _observed(sink, observer, writer)
    total = sum(seg.cycles for seg in program)
    done = 0
    for seg in program:
        report = None
        if progress is not None:
            report = _segment_progress(progress, experiment.name, seg, done, total)
        if hooks.on_segment is not None:
            hooks.on_segment(writer.run_id, seg)
        result = rig.run_segment(seg, sink, report)
        writer.flush_soon()
        done += seg.cycles
        if result.aborted is not None:
            return result.aborted, ctx
    return None, ctx


def _observed(
    sink: Callable[[Block], None], observer: Observer, writer: RunWriter
) -> Callable[[Block], None]:
    """A sink that also feeds the experiment's observer, whose summary goes into the run's metadata each
    time it has news (so an interrupted run keeps what was observed until then)."""

    def observed(block: Block) -> None:
        sink(block)
        if observer.feed(block):
            writer.update_meta({"observed": observer.summary()})

    return observed


def _read_for_analysis(store: RunStore, run_id: str, experiment: Experiment, params: ExperimentParams) -> Run:
    """The rows the experiment's analysis reads: the whole run, or only the segments it names (a long
    run's checkpoints, never its hours of duty cycle)."""
    labels = [str(seg["label"]) for seg in store.get(run_id)["meta"].get("segments", [])]
    return store.read(run_id, segments=experiment.analyzed_segments(params, labels))


def _segment_progress(
    progress: Progress, name: str, seg: Segment, done: int, total: int
) -> Callable[[float], None]:
    def report(fraction: float) -> None:
        progress(f"{name}: {seg.label}", (done + fraction * seg.cycles) / total)

    return report
