"""What an experiment is: validated parameters, a program of segments, an analysis, plots.

An experiment never touches a backend or the store: the runner (`rig.runner`) plays its program on
a rig, records the run, then hands the recorded run back to `analyze` and `plot`. So the same
experiment runs on the simulator, the twins and the hardware, and can be re-analyzed from a stored run.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Protocol

import numpy as np
from pydantic import BaseModel, ConfigDict, ValidationInfo

from model.errors import UserInputError
from model.run import Run
from rig.config import RigConfig, load_rig_config
from rig.interface import Block, ControlMode, Segment


class ProgramError(UserInputError):
    """The parameters are valid but do not fit this rig (its stroke, its limits); says which and why."""


def check_stroke(experiment: str, reach_rad: float, ctx: RigContext) -> None:
    """Refuse a program whose motor stroke `reach_rad` from the start passes the rig's upper travel limit."""
    top = ctx.config.limits.travel_max_out_rad / ctx.gear_ratio
    if ctx.theta_m0 + reach_rad > top:
        raise ProgramError(
            f"{experiment}: a stroke of {reach_rad:g} rad from θ_m = {ctx.theta_m0:.3g} rad passes the travel"
            f" limit ({top:.4g} rad at the motor)"
        )


LIST_MAX = 200
"""Most values in one list parameter (speeds, loads): a sweep of 200 speeds both ways is hours already."""
SPEED_MAX_RAD_S = 2000.0
"""Largest motor speed any parameter may name [rad/s] (~19,000 rpm); the rig's own saturation, which is
lower, is checked when a plan is made for a rig (`RIG_CONTEXT`)."""
LOAD_MAX_NM = 10_000.0
"""Largest torque a parameter may name [N·m]."""
RIG_CONTEXT = "rig"
"""Validation context key: the `RigConfig` a plan is made for, so speeds beyond its saturation are
refused at submit time, naming the field (`Params.model_validate(values, context={RIG_CONTEXT: config})`)."""


class ExperimentParams(BaseModel):
    """Base of every experiment's parameters: unknown keys are refused, values validated with units.

    Strict: a number is a JSON number (not `"0.5"`, not `true`), a flag is a JSON boolean (not `"yes"`);
    NaN and infinities are refused."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)


def distinct_speeds(speeds: list[float], at_least: int = 1) -> list[float]:
    """A list of motor speed magnitudes: `at_least` of them, each > 0, no repeats (a repeat would play the
    same segment twice under one label); sorted."""
    if len(speeds) < at_least or any(not (s > 0) for s in speeds):
        raise ValueError(f"needs {'one' if at_least == 1 else at_least} or more speed magnitudes, each > 0")
    if len(set(speeds)) != len(speeds):
        raise ValueError("speeds must be distinct (a repeat plays the same pass twice)")
    return sorted(speeds)


def rig_speeds(speeds: list[float], info: ValidationInfo, at_least: int = 1) -> list[float]:
    """`distinct_speeds`, each within the rig's speed saturation: a list validator."""
    for speed in speeds:
        within_rig_speed(speed, info)
    return distinct_speeds(speeds, at_least)


def speed_refusal(speed_rad_s: float, config: RigConfig, what: str = "speed") -> str | None:
    """Why a motor speed is beyond the rig's velocity saturation (None: it is within)."""
    limit = float(config.control.max_velocity_rad_s)
    if abs(speed_rad_s) <= limit:
        return None
    return (
        f"{what}: velocity set-point {speed_rad_s:g} rad/s beyond the rig's {limit:g} rad/s"
        f" (rig {config.name!r}'s speed saturation)"
    )


def within_rig_speed(speed_rad_s: float, info: ValidationInfo, what: str = "speed") -> float:
    """Refuse a motor speed beyond the velocity saturation of the rig the plan is made for (if any)."""
    config = (info.context or {}).get(RIG_CONTEXT)
    if config is not None and (refusal := speed_refusal(speed_rad_s, config, what)) is not None:
        raise ValueError(refusal)
    return speed_rad_s


@dataclass(frozen=True)
class RigContext:
    """What an experiment may know of the bench when it builds its program or analyzes a run."""

    config: RigConfig
    gear_ratio: float  # r, output/input
    torque_constant_nm_per_a: float  # K_m
    theta_m0: float  # motor position when the program starts [rad]

    @property
    def rate_hz(self) -> float:
        return self.config.sample_rate_hz

    def cycles(self, duration_s: float) -> int:
        """Whole control cycles in a duration (at least one)."""
        return max(1, round(duration_s * self.config.sample_rate_hz))


def context_from_run(run: Run, where: str = "run") -> RigContext:
    """The rig context a recorded run was made in, from its metadata (for re-analysis and validation)."""
    meta = run.meta
    missing = [k for k in ("gear_ratio", "torque_constant_nm_per_a", "theta_m0") if k not in meta]
    if missing or ("rig_config" not in meta and "rig" not in meta):
        raise UserInputError(
            f"{where}: lacks the rig metadata ({', '.join(missing) or 'rig'}) that re-analysis needs:"
            " use runs recorded by `hdrig run`, or their Parquet/CSV export with its metadata"
        )
    if "rig_config" in meta:
        config = RigConfig.model_validate(meta["rig_config"])
    else:
        config = load_rig_config(str(meta["rig"]))
    return RigContext(
        config, float(meta["gear_ratio"]), float(meta["torque_constant_nm_per_a"]), float(meta["theta_m0"])
    )


@dataclass
class Results:
    """What an analysis derives from a run.

    `metrics`: scalar figures (stored in the catalog, printed by the CLI); `tables`: named columns of
    equal length (each saved as `<name>.csv` beside the run); `notes`: lines a person should read.
    """

    metrics: dict[str, float | int | str] = field(default_factory=dict)
    tables: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    checkpoints: list[dict[str, float]] = field(default_factory=list)
    """Estimates made at points along a long run (endurance), each a row of the catalog's `checkpoints`
    table with its `index` and `t_s` [s]; `hdrig trend` shows them against time across runs."""


class Observer(Protocol):
    """Watches a run's samples as they are recorded (an online estimator): what an experiment learns from
    hours of samples its analysis never loads."""

    def feed(self, block: Block) -> bool:
        """Take one block of samples as recorded; True when `summary()` has news worth keeping now."""
        ...

    def summary(self) -> dict[str, Any]:
        """Small JSON-able results so far, kept in the run's metadata under `observed`."""
        ...


def segment_rows(run: Run, label: str) -> slice:
    """Rows of `run` recorded during the segment named `label` (from the run's `segments` metadata)."""
    for seg in run.meta.get("segments", []):
        if seg["label"] == label:
            return slice(int(seg["start"]), int(seg["start"]) + int(seg["cycles"]))
    raise KeyError(f"run has no segment {label!r}")


def segments_of(run: Run, prefix: str = "") -> list[dict[str, Any]]:
    """The run's segment records (label, mode, start row, cycles), those whose label starts with prefix."""
    return [seg for seg in run.meta.get("segments", []) if str(seg["label"]).startswith(prefix)]


SegmentReader = Callable[[list[str]], Run]
"""Reads the rows of the named segments of the run being analyzed, and its metadata, from the store."""


class Experiment(ABC):
    """One of the article's experiments. Subclasses set `name`, `Params`, and implement the three steps."""

    name: ClassVar[str]
    summary: ClassVar[str]
    Params: ClassVar[type[ExperimentParams]]
    needs: ClassVar[frozenset[ControlMode]]
    """The kinds of program (segment modes) it plays: a rig that cannot play one refuses it up front."""

    @abstractmethod
    def program(self, params: Any, ctx: RigContext) -> list[Segment]:
        """The segments to play, in order, from rest at ctx.theta_m0. Labels must be unique."""

    @abstractmethod
    def analyze(self, run: Run, params: Any, ctx: RigContext) -> Results:
        """Derived results from the recorded run (its `segments` metadata says which rows are which)."""

    def plot(self, run: Run, results: Results, params: Any, ctx: RigContext, out_dir: Path) -> list[Path]:
        """PNG files a person wants to look at; written into out_dir. Default: none."""
        return []

    def observer(self, params: Any, ctx: RigContext, program: list[Segment]) -> Observer | None:
        """What watches the samples while the program plays (the runner feeds it). Default: nothing."""
        return None

    def analyzed_segments(self, params: Any, labels: list[str]) -> list[str] | None:
        """The segments `analyze` reads, of those recorded (None: the whole run). A run of hours names
        the few it needs, so the store never loads the rest."""
        return None

    def analyze_parts(self, read: SegmentReader, run: Run, params: Any, ctx: RigContext) -> Results | None:
        """The analysis of a run too long to hold even its analyzed segments at once: `read(labels)`
        returns only those segments' rows (with the run's metadata), so it can go a part at a time;
        `run` is what `analyzed_segments` names. None (the default): `analyze(run)` is the analysis."""
        return None
