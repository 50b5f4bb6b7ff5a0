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
from rig.interface import SAMPLE_COLUMNS, Block, ControlMode, Rig, Segment, open_rig
from rig.runfile import json_text
from rig.status import RunStatus
from rig.store import PART_ROWS_MAX, AnalysisState, RunStore, RunWriter

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
"""Time of the move to a whole motor turn before an experiment that starts on one (`start_on_turn`) [s]."""
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


def _approach_turn(rig: Rig, sink: Callable[[dict[str, np.ndarray]], None]) -> str | None:
    """Move the motor to its nearest whole turn and hold (`approach`), before the settle: an experiment
    whose metrics depend on the angle it starts at (through the kinematic error and the friction's
    ripple, both periodic in whole turns of the motor) then starts in the same place whatever ran
    before it. The abort reason, if it tripped."""
    rate_hz = rig.config.sample_rate_hz
    here: dict[str, float] = {}

    def keep(block: dict[str, np.ndarray]) -> None:
        here["theta_m"] = float(block["theta_m"][-1])
        sink(block)

    hold = Segment(ControlMode.VELOCITY, np.zeros(max(1, round(SETTLE_S * rate_hz))), 0.0, "settle-before")
    result = rig.run_segment(hold, keep)
    if result.aborted is not None or "theta_m" not in here:
        return result.aborted
    start = here["theta_m"]
    target = 2 * np.pi * round(start / (2 * np.pi))
    # Half a cosine: starts and ends at rest, at most π/2·(π rad)/APPROACH_S ≈ 10 rad/s at the motor.
    phase = np.linspace(0.0, np.pi, max(2, round(APPROACH_S * rate_hz)))
    path = start + (target - start) * (1.0 - np.cos(phase)) / 2
    move = Segment(ControlMode.POSITION, path, 0.0, "approach")
    rig.check_segment(move)
    return rig.run_segment(move, sink).aborted


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
    columns = list(SAMPLE_COLUMNS)
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
        aborted = _approach_turn(rig, sink)
        if aborted is not None:
            return aborted, RigContext(config, rig.gear_ratio, rig.torque_constant_nm_per_a, float("nan"))
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
