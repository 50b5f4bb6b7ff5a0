"""`hdrig fit`: identify a model from runs — staged estimates, joint refinement, validation report.

The CLI and the service call `identify`. Runs come from the store (by id; `latest` takes the newest
complete run of each experiment) or from run files.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from model.errors import UserInputError
from model.fit.parameters import get_values
from model.fit.trajectory import TrajectoryProblem, fit_trajectories
from model.params import HarmonicDriveModel, save_model
from model.run import Run
from rig.identification.staged import staged_estimates
from rig.identification.validation import ValidationReport, validate

JOINT_CANDIDATES = ("s3", "k_v", "static_factor", "K_s", "J_m", "J_l", "f_cl", "b_l", "R", "K_b")
"""Parameters the joint refinement may move (when the staged fit found them determined): those that
shape trajectories most. The Fourier and quadratic coefficients keep their staged values, which come
from data made for them."""
JOINT_EXPERIMENTS = ("pulse", "step", "sine")
"""Runs whose trajectories the joint refinement matches: open-loop transients and closed-loop tracking."""
JOINT_WINDOW_S = 0.1
FIT_METRIC = (
    "RMS of the shooting residual over 0.1 s windows of the pulse/step/sine runs"
    " (θ_m and θ_l, each scaled by its spread in the data) [–]"
)

Progress = Callable[[str, float], None]


@dataclass
class ParameterRow:
    name: str
    start: float
    estimate: float
    uncertainty: float | None
    identifiable: bool
    stage: str
    note: str = ""


@dataclass
class Identification:
    model: HarmonicDriveModel
    parameters: list[ParameterRow]
    fit_error_before: float
    fit_error_after: float
    validation: ValidationReport | None = None
    notes: list[str] = field(default_factory=list)
    model_file: Path | None = None
    report_file: Path | None = None


def _joint_runs(runs: list[Run]) -> list[Run]:
    return [r for r in runs if r.meta.get("experiment") in JOINT_EXPERIMENTS and r.input_column is not None]


def identify(
    runs: list[Run],
    start: HarmonicDriveModel,
    joint: bool = True,
    report_dir: Path | None = None,
    progress: Progress | None = None,
) -> Identification:
    """Staged estimates, then (if `joint`) all determined parameters together on trajectories."""
    say = progress or (lambda label, fraction: None)
    if not runs:
        raise UserInputError("fit needs at least one run (--data)")
    say("staged estimates", 0.05)
    staged = staged_estimates(runs, start)
    notes = list(staged.notes)
    rows = {
        e.name: ParameterRow(
            e.name,
            _start_value(start, e.name),
            e.value,
            e.std_error,
            e.identifiable,
            e.stage,
            e.note,
        )
        for e in staged.estimates
    }
    model = staged.model
    trajectory_runs = _joint_runs(runs)
    if not trajectory_runs:
        notes.append(
            f"no {'/'.join(JOINT_EXPERIMENTS)} run: no trajectory to refine on, fit error not measured"
        )
        return _finish(model, list(rows.values()), math.nan, math.nan, notes, runs, report_dir, say)
    problem = TrajectoryProblem(start, trajectory_runs, [], JOINT_WINDOW_S, 1e-4)
    before = _rms(problem.residuals_of(start))
    if joint:
        names = [n for n in JOINT_CANDIDATES if n in rows and rows[n].identifiable]
        if names:
            say("joint refinement", 0.3)
            refined = fit_trajectories(model, trajectory_runs, names, window_s=JOINT_WINDOW_S)
            notes += refined.notes
            staged_cost = _rms(problem.residuals_of(model))
            if _rms(problem.residuals_of(refined.model)) < staged_cost:
                model = refined.model
                for p in refined.parameters:
                    row = rows[p.name]
                    row.stage += " + joint"
                    if p.identifiable:
                        row.estimate, row.uncertainty = p.estimate, p.std_error
                    else:
                        row.note = (
                            row.note + "; " if row.note else ""
                        ) + f"joint: {p.note}, staged value kept"
            else:
                notes.append("joint refinement did not lower the trajectory error: staged values kept")
    after = _rms(problem.residuals_of(model))
    return _finish(model, list(rows.values()), before, after, notes, runs, report_dir, say)


def _start_value(model: HarmonicDriveModel, name: str) -> float:
    """The starting model's value, or NaN for a parameter the stage added (a new section's)."""
    try:
        return get_values(model, [name])[name]
    except UserInputError:
        return math.nan


def _rms(residual: np.ndarray) -> float:
    return float(np.sqrt(np.mean(residual**2)))


def _finish(
    model: HarmonicDriveModel,
    rows: list[ParameterRow],
    before: float,
    after: float,
    notes: list[str],
    runs: list[Run],
    report_dir: Path | None,
    say: Progress,
) -> Identification:
    result = Identification(model, rows, before, after, notes=notes)
    if report_dir is not None:
        say("validation", 0.8)
        report_dir.mkdir(parents=True, exist_ok=True)
        result.validation = validate(runs, model, report_dir)
        result.report_file = report_dir / "report.md"
        result.report_file.write_text(_report(result))
    say("done", 1.0)
    return result


def save_identified(result: Identification, path: Path) -> Path:
    result.model_file = save_model(result.model, path)
    return result.model_file


def _report(result: Identification) -> str:
    lines = [result.validation.markdown(result.model.name) if result.validation else "", "## Parameters", ""]
    lines += ["| name | estimate | uncertainty (1 σ) | start | stage | note |", "|---|---|---|---|---|---|"]
    for row in result.parameters:
        sigma = f"{row.uncertainty:.3g}" if row.uncertainty is not None else "not determined"
        lines.append(
            f"| {row.name} | {row.estimate:.6g} | {sigma} | {row.start:.6g} | {row.stage} | {row.note} |"
        )
    lines += [
        "",
        f"Fit error ({FIT_METRIC}): before {result.fit_error_before:.4g}, after {result.fit_error_after:.4g}",
        "",
    ]
    lines += [f"- {n}" for n in result.notes]
    return "\n".join(lines) + "\n"
