"""`hdrig fit`: identify a model from runs — staged estimates, joint refinement, validation report.

The CLI and the service call `identify`, which composes three steps, each with a typed result:
`starting_point` (the staged stages' estimates, `staged.staged_estimates`, or what plain runs' columns
determine) gives a `Start`; `refine_jointly` (the joint refinement on trajectories, the model kept by
held-out windows) gives a `Choice`; `_finish` validates and writes the report. Every step and stage says
what it did as `pipeline.Note`s. Runs come from the store (by id; `latest` takes the newest complete run
of each experiment) or from run files.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from model.errors import UserInputError
from model.params import HarmonicDriveModel, save_model
from model.registry import JOINT_CANDIDATES, MOTOR
from model.run import Run
from rig.analysis.fit.parameters import get_values, with_values
from rig.analysis.fit.trajectory import (
    BLOCKS,
    CHANNELS,
    SIGNED,
    TrajectoryFit,
    TrajectoryProblem,
    block_of_residual,
    fit_problem,
    with_lifted_static,
)
from rig.analysis.identification.column_stage import axis_figures, plan_for_plain_runs, seeded_model
from rig.analysis.identification.pipeline import Note, note_lines
from rig.analysis.identification.staged import REQUIRED_META, staged_estimates
from rig.analysis.identification.validation import ValidationReport, validate
from rig.experiments.base import segments_of
from rig.experiments.pulse import STAIR_PREFIX

JOINT_EXPERIMENTS = ("pulse", "step", "sine")
"""Runs whose trajectories the joint refinement matches: open-loop transients and closed-loop tracking."""
JOINT_WINDOW_S = 0.1
FIT_METRIC = (
    "RMS of the shooting residual over 0.1 s windows of the pulse/step/sine runs (of every run with an"
    " input column, for runs without experiment metadata) (θ_m and θ_l, each scaled by its spread in the"
    " data; runs without metadata: what is left once each window's start speeds and load position are"
    " free) [–]"
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
    said: list[Note] = field(default_factory=list)  # each step's and stage's notes
    model_file: Path | None = None
    report_file: Path | None = None
    held_out: dict[str, Any] | None = (
        None  # the held-out windows' errors of each candidate, and which was kept
    )
    inverse_model: dict[str, Any] | None = (
        None  # runs without metadata: the inverse-model fit beside the model
    )
    imported: list[dict[str, Any]] = field(default_factory=list)  # the runs' column mappings (`--map`)

    @property
    def notes(self) -> list[str]:
        """The notes as the report and `--json` print them."""
        return note_lines(self.said)


def _joint_runs(runs: list[Run]) -> list[Run]:
    return [
        _without_staircase(r)
        for r in runs
        if r.meta.get("experiment") in JOINT_EXPERIMENTS and r.input_column is not None
    ]


def _without_staircase(run: Run) -> Run:
    """A pulse run up to its breakaway staircase: the stairs barely move the motor (the breakaway stage's
    matter, not the trajectories'), and the joint refinement keeps the pulse rows it always had."""
    stairs = segments_of(run, STAIR_PREFIX) if run.meta.get("experiment") == "pulse" else []
    if not stairs:
        return run
    stop = min(int(seg["start"]) for seg in stairs)
    return Run({name: values[:stop] for name, values in run.columns.items()}, run.meta)


def carries_stage_metadata(run: Run) -> bool:
    """Whether a run carries what the staged estimates read (experiment, segments, rig constants)."""
    return all(key in run.meta for key in REQUIRED_META)


HOLDOUT_EVERY = 4
"""Every fourth shooting window is held out: the joint step fits on the others, and the model kept is
the one best on these (start, staged, joint). The joint step carries the staged estimates as priors."""
STAGED, COLUMNS, JOINT = "staged", "columns", "joint"
"""`identify`'s own steps, as its notes name them: the staged start, the columns' start, the joint step."""


def identify(
    runs: list[Run],
    start: HarmonicDriveModel,
    joint: bool = True,
    report_dir: Path | None = None,
    progress: Progress | None = None,
) -> Identification:
    """Staged estimates where the runs carry what each stage needs, what the columns determine of the
    others, then (if `joint`) the determined parameters together on trajectories; the model returned is
    never worse than the start or the staged estimates on held-out windows."""
    say = progress or (lambda label, fraction: None)
    if not runs:
        raise UserInputError("fit needs at least one run (--data)")
    # Warm-up runs go to the thermal stage alone (issue 27), applied in _finish; the others as before.
    warm = [r for r in runs if r.meta.get("experiment") == WARM_UP]
    runs = [r for r in runs if r.meta.get("experiment") != WARM_UP]
    if not runs:
        return _finish(start, [], math.nan, math.nan, [], [], report_dir, say, warm)
    begun = starting_point(runs, start, joint, say)
    if not begun.trajectory_runs:
        text = f"no {'/'.join(JOINT_EXPERIMENTS)} run: no trajectory to refine on, fit error not measured"
        begun.said.append(Note(JOINT, text, named=False))
        rows = list(begun.rows.values())
        return _finish(begun.model, rows, math.nan, math.nan, begun.said, runs, report_dir, say, warm)
    chosen = refine_jointly(start, begun, joint, say)
    if chosen.kept == JOINT and chosen.refined is not None:
        _take_joint_values(begun.rows, chosen.refined, chosen.priors, begun.said)
    model = chosen.candidates[chosen.kept]
    _rows_follow(begun.rows, model, chosen.kept)
    if begun.inverse is not None:
        begun.inverse["trajectory"] = axis_figures(model, begun.trajectory_runs)
    before, after = chosen.cost["start"], chosen.cost[chosen.kept]
    result = _finish(model, list(begun.rows.values()), before, after, begun.said, runs, report_dir, say, warm)
    result.held_out = {"every": HOLDOUT_EVERY, "errors": chosen.held, "kept": chosen.kept}
    result.inverse_model = begun.inverse
    return result


@dataclass
class Start:
    """Where the joint step starts: what the staged (or the columns') estimates left."""

    model: HarmonicDriveModel
    rows: dict[str, ParameterRow]
    said: list[Note]
    trajectory_runs: list[Run]
    names: list[str]  # the parameters the joint step may move
    inverse: dict[str, Any] | None = None


def starting_point(runs: list[Run], start: HarmonicDriveModel, joint: bool, say: Progress) -> Start:
    """The staged estimates of the runs that carry what the stages read; else what the columns determine."""
    staged_runs = [r for r in runs if carries_stage_metadata(r)]
    plain = [r for r in runs if not carries_stage_metadata(r)]
    if staged_runs:
        say("staged estimates", 0.05)
        return _from_stages(staged_runs, plain, start)
    say("what the columns determine", 0.05)
    return _from_columns(plain, start, joint)


def _from_stages(staged_runs: list[Run], plain: list[Run], start: HarmonicDriveModel) -> Start:
    """The staged estimates of runs that carry what each stage needs; `plain` runs join the trajectories."""
    staged = staged_estimates(staged_runs, start)
    said = list(staged.said)
    if plain:
        said.append(
            Note(
                STAGED,
                f"{len(plain)} run(s) without experiment metadata: used by the joint refinement's"
                " trajectories only",
                named=False,
            )
        )
    rows = {
        e.name: ParameterRow(
            e.name, _start_value(start, e.name), e.value, e.std_error, e.identifiable, e.stage, e.note
        )
        for e in staged.estimates
    }
    staged_model = staged.model
    trajectory_runs = _joint_runs(staged_runs) + [r for r in plain if r.input_column is not None]
    names = [n for n in JOINT_CANDIDATES if n in rows and rows[n].identifiable]
    return Start(staged_model, rows, said, trajectory_runs, names)


def _from_columns(plain: list[Run], start: HarmonicDriveModel, joint: bool) -> Start:
    """What the columns of runs without experiment metadata determine, the rest held."""
    inverse: dict[str, Any] | None = None
    plan = plan_for_plain_runs(plain, start)
    said = [
        Note(COLUMNS, text, named=False)
        for text in (
            "no run carries experiment metadata: fitted by trajectory least squares on what the"
            " columns determine",
            *plan.notes,
        )
    ]
    rows = {
        name: ParameterRow(
            name, _start_value(start, name), _start_value(start, name), None, False, "columns", why
        )
        for name, why in plan.held.items()
        if not math.isnan(_start_value(start, name))
    }
    for name, (value, se) in plan.estimates.items():
        rows[name] = ParameterRow(name, _start_value(start, name), value, se, True, MOTOR)
    for name in plan.free:
        rows[name] = ParameterRow(
            name,
            _start_value(start, name),
            _start_value(plan.start, name),
            None,
            False,
            "trajectory",
            "not refined (--no-joint)"
            if not joint
            else "the joint refinement was not kept (notes): start value",
        )
    staged_model = plan.start
    trajectory_runs = [r for r in plain if r.input_column is not None]
    names = list(plan.free)
    others: dict[str, HarmonicDriveModel] = {}
    if plan.inverse is not None:
        inverse = {"fit": plan.inverse.as_json()}
        seeded = seeded_model(plan.start, plan.inverse)
        if seeded is not None:
            others["inverse-model"] = seeded
    if plan.two_sided:
        try:
            values = {n: v for n, (v, _) in plan.two_sided.items()}
            others["two-sided least-squares"] = with_lifted_static(plan.start, values)
        except UserInputError:
            pass
    if others:
        staged_model = _better_start(others, plan.start, trajectory_runs, said)
    return Start(staged_model, rows, said, trajectory_runs, names, inverse)


@dataclass
class Choice:
    """The joint step's outcome: the candidate models (start, staged, joint), their errors on every
    window and on the held-out ones, and the one kept."""

    candidates: dict[str, HarmonicDriveModel]
    cost: dict[str, float]
    held: dict[str, float]
    kept: str
    refined: TrajectoryFit | None  # the joint refinement, if it ran
    priors: dict[str, tuple[float, float]]


def refine_jointly(start: HarmonicDriveModel, begun: Start, joint: bool, say: Progress) -> Choice:
    """The joint refinement (if `joint` and any parameter may move) from the closer of the start and the
    staged model on the training windows; the model kept is the best on held-out windows of those no
    worse than the start on every window."""
    notes = begun.said
    problem = TrajectoryProblem(
        start,
        begun.trajectory_runs,
        [],
        JOINT_WINDOW_S,
        1e-4,
        fitted_channels(start),
        refine_voltage=_refine_voltage(begun.trajectory_runs),
    )
    # Runs without metadata: no stage checked any value on data made for it; σ also from blocks of windows.
    problem.block_sigma = not _refine_voltage(begun.trajectory_runs)
    train, _ = problem.split(HOLDOUT_EVERY)
    is_held = problem.window_of_residual % HOLDOUT_EVERY == HOLDOUT_EVERY - 1
    candidates = {"start": start, STAGED: begun.model}
    residual = {label: problem.residuals_of(m) for label, m in candidates.items()}
    refined = None
    priors: dict[str, tuple[float, float]] = {}
    if joint and begun.names:
        say("joint refinement", 0.3)
        # From whichever of the two is closer on the training windows: the staged values can be worse.
        base = min(candidates, key=lambda label: _rms(residual[label][~is_held]))
        priors = _priors(begun.rows, begun.names)
        if problem.block_sigma:  # a lab file: each window's start states free, the basis at the start
            problem = problem.with_free_starts(candidates[base])
            train, _ = problem.split(HOLDOUT_EVERY)
        first = _breakaway_start(train, candidates[base], begun.names, priors, notes)
        refined = fit_problem(train.for_parameters(first, begun.names).with_priors(priors))
        refined = _out_of_a_breakaway_minimum(train, refined, begun.names, priors, notes)
        if problem.block_sigma:
            problem, train, refined = _with_free_starts(problem, refined, begun.names, priors, notes)
            residual = {label: problem.residuals_of(m) for label, m in candidates.items()}
        notes += [Note(JOINT, text, named=False) for text in refined.notes]
        if base != STAGED:
            notes.append(Note(JOINT, f"joint refinement started from the {base} model", named=False))
        candidates[JOINT] = refined.model
        residual[JOINT] = problem.residuals_of(refined.model)
    cost = {label: _rms(r) for label, r in residual.items()}
    held = {label: _rms(r[is_held]) for label, r in residual.items()}
    # Never worse than the start: only models no worse on every window compete, on the held-out ones.
    fair = [label for label in candidates if cost[label] <= cost["start"]]
    chosen = Choice(candidates, cost, held, min(fair, key=lambda label: held[label]), refined, priors)
    if chosen.kept == JOINT and refined is not None:
        polished = _polish(problem, is_held, chosen, refined, begun.names, notes)
        if problem.block_sigma and chosen.refined is not None:
            _sigma_backed_by_cost(
                problem.for_parameters(chosen.refined.model, begun.names),
                chosen.refined,
                notes,
                residual[JOINT] if polished is None else polished,
            )
    _say_verdict(chosen, fair, notes)
    return chosen


def _with_free_starts(
    problem: TrajectoryProblem,
    refined: TrajectoryFit,
    names: list[str],
    priors: dict[str, tuple[float, float]],
    notes: list[Note],
) -> tuple[TrajectoryProblem, TrajectoryProblem, TrajectoryFit]:
    """A lab file's windows with their start states free (`TrajectoryProblem.with_free_starts`), the
    basis taken again at the first joint fit (the start's resonance and friction can be far enough from
    the truth's that the ringing it projects out is not the data's), and the joint fit again from there
    on them: (all windows, training windows, the fit)."""
    problem = problem.with_free_starts(refined.model)
    train, _ = problem.split(HOLDOUT_EVERY)
    again = fit_problem(train.for_parameters(refined.model, names).with_priors(priors))
    notes.append(
        Note(
            JOINT,
            f"each window's start speeds and load position left free ({problem.nuisance} degrees of"
            " freedom over the windows): the joint fit again on what they cannot explain",
            named=False,
        )
    )
    return problem, train, again


def _polish(
    problem: TrajectoryProblem,
    is_held: np.ndarray,
    chosen: Choice,
    refined: TrajectoryFit,
    names: list[str],
    notes: list[Note],
) -> np.ndarray | None:
    """Chosen on held-out windows, the joint values then use every window (a few breakaways more), kept
    only if that does not lose what was won: never worse than the start or the staged model held out.
    The polished model's residual on every window if it was kept."""
    polished = fit_problem(
        problem.for_parameters(refined.model, names).with_priors(chosen.priors, refined.prior_weight),
        max_evaluations=PLAIN_POLISH_EVALUATIONS if problem.block_sigma else POLISH_EVALUATIONS,
    )
    again = problem.residuals_of(polished.model)
    bar = min(chosen.held[label] for label in chosen.candidates if label != JOINT)
    if _rms(again) <= chosen.cost[JOINT] and _rms(again[is_held]) <= bar:
        chosen.refined, chosen.candidates[JOINT] = polished, polished.model
        chosen.cost[JOINT], chosen.held[JOINT] = _rms(again), _rms(again[is_held])
        notes.append(
            Note(
                JOINT,
                "joint refinement polished on every window after it won on the held-out ones",
                named=False,
            )
        )
        return again
    return None


CURVATURE_SIGMAS = (3.0, 9.0)
"""`_sigma_backed_by_cost` moves each parameter by these many of its σ, to either side."""
SUB_QUADRATIC = 9.0 / 1.2**2
"""A parabola's rise grows 9× per ×3 step; under this (the σ it implies grew by more than 20 %) the
profile is not yet quadratic there and `_rises_on_one_side` looks 3× further. Gear 2's static_factor
rose 5.3× and 5.6× from 3σ to 9σ (then 8.6× to 27σ), its other parameters 8.2–9.6×."""


def _sigma_backed_by_cost(
    problem: TrajectoryProblem, fit: TrajectoryFit, notes: list[Note], base: np.ndarray | None = None
) -> None:
    """Each σ checked against the cost itself (issue 25 item 2), a profile likelihood: moved by ±kσ
    along its valley floor (the others following `fit.profile_direction`, the linearized profile), a
    parameter must raise the residual's sum of squares on each side by what a quadratic cost with that
    σ would: k²·s²·(σ/σ_c)², s² the per-row variance at the optimum and σ_c the σ the Jacobian's
    curvature gives with white rows (`fit.curvature_sigma`; the σ reported is wider by the windows'
    and blocks' correlation, and the rise it must back scales with it). Where the straight walk
    flattens, and for a breakaway level, the others are re-fitted at each probed value (`_Profile`,
    `_rises_on_one_side`): a straight line leaves a curved valley and climbs its wall (a drawn gear's
    static_factor: 0.45 along the line at −27σ, 0.030 with the others re-fitted, 0.029 by a full fit
    of the other seven).

    Friction makes the cost a staircase in a breakaway level, and one-sided: the finite-difference
    Jacobian spans a stair's edge and promises a curvature the cost does not have (a drawn gear:
    f_cl ± 0.0002, 20σ from the truth, static_factor, its partner along the breakaway, 17σ); below a
    static_factor of 1 the cost can be flat on one side and steep on the other (a drawn gear fitted
    1.05 ± 0.0046 where the truth, 0.76, costs no more than 0.95: 63σ). Hence both sides, each on its
    own, and at 9σ as well as 3σ: a stair's edge passes at 3σ but a staircase does not keep rising as
    a parabola; where its rise grows slower than a parabola's, on by ×3 steps while it does. σ is
    widened to the largest half-width at which a side's measured rise would reach k²·s² (as if the cost
    were quadratic out to there, in units of σ_c); with no rise on a side, or σ wider than the value,
    the parameter is not determined, with the reason. Four residual evaluations per parameter, a few
    more where the cost flattens outward, and on a re-fitted side up to PROFILE_STEPS more per probed
    value (the Jacobian the re-fit uses comes from the ±3σ probes: `_Profile`)."""
    base = problem.residuals_of(fit.model) if base is None else base  # `base`: the caller's, if known
    rss0 = float(base @ base)
    s2 = rss0 / max(len(base) - len(problem.names) - problem.nuisance, 1)
    values = {p.name: p.estimate for p in fit.parameters}
    profile = _Profile(problem, values, base)
    cluster = _largest_cluster(problem)
    given = {p.name: p.std_error for p in fit.parameters if p.identifiable and (p.std_error or 0.0) > 0}
    checked = [p for p in fit.parameters if p.name in given]
    steps: dict[str, dict[str, float]] = {}  # per parameter, its move per σ along the valley floor
    for p in checked:
        direction = fit.profile_direction.get(p.name, {p.name: 1.0})
        steps[p.name] = {n: float(given[p.name] or 0.0) * direction.get(n, 0.0) for n in values}
        profile.pair(steps[p.name], CURVATURE_SIGMAS[0], abs(p.estimate) / float(given[p.name] or 1.0))
    widened: list[str] = []
    jackknifed: list[str] = []
    for p in checked:
        assert p.std_error is not None
        sigma_c = fit.curvature_sigma.get(p.name, p.std_error)
        # σ over σ_c: the rows' correlation, at most what one cluster of σ's rows all alike would give.
        inflation = min(p.std_error / sigma_c, cluster)
        sigma, flat = p.std_error, ""
        for sign in (1.0, -1.0):
            moves = {n: sign * d for n, d in steps[p.name].items()}  # per σ of p
            k_max = abs(p.estimate) / p.std_error or math.inf
            rises = _rises_on_one_side(problem, values, moves, k_max, rss0, (profile, p.name))
            for k, rise in rises.items():
                if rise <= 0:
                    side = "+" if sign > 0 else "−"
                    flat = f"the cost does not rise at {side}{k:g}σ of it (one-sided or flat)"
                    break
                # The half-width where this rise would reach k²·s² (how much flatter than the
                # curvature the cost is on this side), widened by the rows' correlation.
                sigma = max(sigma, k * p.std_error * math.sqrt(s2 / rise) * inflation)
            if flat:
                break
        if not flat and p.name in BREAKAWAY_LEVELS:
            reach = problem.diff_step * abs(p.estimate)  # the finite differences' span: σ says nothing inside
            spread = _grid_jackknife(problem, values, p.name, max(CURVATURE_SIGMAS[-1] * sigma, reach))
            if spread > sigma:
                sigma, jackknifed = spread, [*jackknifed, p.name]
        if not flat and sigma > abs(p.estimate) > 0:
            flat = f"its cost's rise allows σ {sigma:.3g}, wider than the value"
        if flat:
            p.identifiable, p.std_error = False, None
            p.note = f"{flat}: σ not backed by the data"
            widened.append(f"{p.name} undetermined")
        elif sigma > 1.01 * p.std_error:  # rounding alone widens a parabola's σ by ~1e-15
            widened.append(f"{p.name} ×{sigma / p.std_error:.3g}")
            p.std_error = sigma
    if widened:
        text = (
            "σ checked on the cost (each side, ±3σ and ±9σ along the valley floor, the others re-fitted"
            f" where it flattens and for a breakaway level): {', '.join(widened)}"
        )
        if jackknifed:
            text += f"; {', '.join(jackknifed)} by leaving out each window (and each block) in turn"
        notes.append(Note(JOINT, text, named=False))


def _vertices(grid: np.ndarray, costs: np.ndarray, at: np.ndarray) -> np.ndarray:
    """Per column of `costs` (values along `grid`), the vertex of the parabola through its lowest point
    `at` and its two neighbours (the grid point itself at an edge or where the three do not curve up):
    a smooth cost's optimum between grid points, so a jackknife of small moves is not the grid's step."""
    out = grid[at].astype(float)
    step = float(grid[1] - grid[0])
    inner = (at > 0) & (at < len(grid) - 1)
    cols = np.flatnonzero(inner)
    lo, mid, hi = (costs[at[cols] + k, cols] for k in (-1, 0, 1))
    curve = lo - 2 * mid + hi
    with np.errstate(invalid="ignore", divide="ignore"):
        shift = np.where(curve > 0, 0.5 * (lo - hi) / curve, 0.0)
    out[cols] += step * np.clip(np.nan_to_num(shift), -0.5, 0.5)
    return out


JACKKNIFE_POINTS = 25
"""Values of a breakaway level `_grid_jackknife` costs each window at (odd: the estimate is one)."""


def _grid_jackknife(
    problem: TrajectoryProblem, values: dict[str, float], name: str, half_width: float
) -> float:
    """σ of a breakaway level by the jackknife, each window left out in turn (and each block of windows,
    where `block_sigma`; the larger), its optimum found on a grid of JACKKNIFE_POINTS values over
    ±`half_width` with the others held: the cost per window at each value, so leaving a window out is a
    subtraction. The grid widens ×3 (twice at most) while an optimum lands on its edge.

    A breakaway level's cost is a staircase with cliffs (a window whose motor breaks loose, or not, at a
    hair's difference), which a Jacobian's curvature cannot see: on a drawn gear one window decided
    static_factor (its cost against the truth's 885 of the whole record's 681 in units of s²), the
    Jacobian gave σ 7e-5 and the error was 15σ; left out, the optimum moved 0.0016 (docs/BENCHMARKS.md).
    """
    groups = [problem.window_of_residual]  # each row's window; with `block_sigma` its block as well
    if problem.block_sigma:
        groups.append(block_of_residual(problem, BLOCKS))
    spread = 0.0
    for _ in range(3):
        grid = values[name] + half_width * np.linspace(-1.0, 1.0, JACKKNIFE_POINTS)
        costs = [np.full((len(grid), int(g.max()) + 1), np.inf) for g in groups]  # per value, per group
        for i, v in enumerate(grid):
            try:
                model = problem.model_with({**values, name: float(v)})
            except UserInputError:
                continue  # outside the model's valid region (a negative level): never an optimum
            squares = problem.residuals_of(model) ** 2
            for g, cost in zip(groups, costs, strict=True):
                cost[i] = np.bincount(g, weights=squares, minlength=cost.shape[1])
        spread, edge = 0.0, False
        for cost in costs:
            with np.errstate(invalid="ignore"):  # an invalid value's row: inf − inf, never the optimum
                without = cost.sum(axis=1)[:, None] - cost  # each group left out, at each value
                at = np.nanargmin(without, axis=0)
            left_out = _vertices(grid, without, at)
            n = len(left_out)
            spread = max(spread, math.sqrt((n - 1) / n * float(np.sum((left_out - left_out.mean()) ** 2))))
            edge |= bool(np.any((at == 0) | (at == len(grid) - 1)))
        if not edge:
            break
        half_width *= 3.0
    return spread


def _largest_cluster(problem: TrajectoryProblem) -> float:
    """√(rows of the largest cluster σ was computed over: a window, or a block of windows where
    `block_sigma`): the most the rows' correlation can widen σ over the white curvature's σ_c (those rows
    all alike: one sample). A sandwich σ wider still comes from leverage or a stair in the Jacobian, not
    from correlation, and asking the cost for that rise asks more than its rows can show (the open-loop
    sine of tests/test_fit_any_run.py: σ/σ_c = 400 on 6,000 rows, blocks of 600)."""
    windows = getattr(problem, "window_of_residual", None)
    if windows is None or not len(windows):
        return math.inf
    groups = block_of_residual(problem, BLOCKS) if problem.block_sigma else windows
    return math.sqrt(float(np.bincount(groups).max()))


PROFILE_STEPS = 4
"""Chord steps of `_Profile.settle` per probed value. Against `fit_problem` on the other seven (drawn
gears, docs/BENCHMARKS.md, issue 25): gear 2's static_factor at −3σ…−63σ within 3 % of the full
re-fit's rise after two steps; gear 16's at +9σ within 4 % after three, at −9σ 2× above it (still
falling): the chord overstates the rise where the valley bends most, so σ errs on the narrow side."""
PROFILE_SETTLED = 0.1
"""A chord step that lowers the rise by less than this share of it ends the re-fit."""


class _Profile:
    """The cost with one parameter held and the others re-fitted: chord (Gauss–Newton) steps on the
    others with one Jacobian of the optimum, reused at every probed value: one residual per step.

    The Jacobian costs no evaluation of its own: the straight walks' first probes, at ±3σ of every
    parameter along its valley floor, are central differences along directions that span the
    parameters (the covariance's columns), and their residuals are kept (`residual_at`); only where
    they do not span them is it a finite difference of each parameter (the relative step `fit_problem`
    uses)."""

    def __init__(self, problem: TrajectoryProblem, values: dict[str, float], base: np.ndarray) -> None:
        self.problem, self.values, self.base = problem, values, base
        self.scales = np.array([abs(v) or 1.0 for v in values.values()])
        self._jacobian: np.ndarray | None = None  # per parameter, ∂r/∂(value/|value|)
        self._floor: dict[str, float] = {}
        self._seen: dict[tuple[float, ...], np.ndarray] = {}
        self._pairs: list[tuple[np.ndarray, np.ndarray]] = []  # (scaled move, residual difference)

    def residual_at(self, point: dict[str, float]) -> np.ndarray:
        """The residual at `point` (UserInputError for an invalid model), each point evaluated once."""
        key = tuple(point.values())
        if key not in self._seen:
            self._seen[key] = self.problem.residuals_of(self.problem.model_with(point))
        return self._seen[key]

    def pair(self, move: dict[str, float], k: float, k_max: float) -> None:
        """Probe ±k·`move` (a straight walk's first points, evaluated here once) and keep the pair as a
        central difference for the Jacobian."""
        if k > k_max:
            return
        ends = []
        for sign in (1.0, -1.0):
            try:
                ends.append(self.residual_at({n: v + sign * k * move[n] for n, v in self.values.items()}))
            except UserInputError:
                return
        scaled = np.array([2.0 * k * move[n] for n in self.values]) / self.scales
        self._pairs.append((scaled, ends[0] - ends[1]))

    def rise(self, held: str, point: dict[str, float], residual: np.ndarray) -> float:
        """The profile's rise at `point` (`residual` there): the sum of squares with the others re-fitted,
        over the same at the optimum's value of `held` (the fit may have stopped short of its minimum
        along the others: a rise from there would count that stop)."""
        if held not in self._floor:
            settled = self.settle(held, self.values, self.base)
            self._floor[held] = float(settled @ settled)
        settled = self.settle(held, point, residual)
        return float(settled @ settled) - self._floor[held]

    def jacobian(self) -> np.ndarray:
        if self._jacobian is None and self._pairs:
            moves = np.column_stack([m for m, _ in self._pairs])  # parameters × pairs
            if np.linalg.matrix_rank(moves) == len(self.values):
                differences = np.column_stack([d for _, d in self._pairs])
                self._jacobian = differences @ np.linalg.pinv(moves)
        if self._jacobian is None:
            columns = []
            for name, value in self.values.items():
                scale = abs(value) or 1.0
                moved = self.problem.model_with({**self.values, name: value + PROFILE_DIFF_STEP * scale})
                columns.append((self.problem.residuals_of(moved) - self.base) / PROFILE_DIFF_STEP)
            self._jacobian = np.column_stack(columns)
        return self._jacobian

    def settle(self, held: str, point: dict[str, float], residual: np.ndarray) -> np.ndarray:
        """The residual at `point` with every parameter but `held` re-fitted (at most PROFILE_STEPS chord
        steps, each kept only if it lowers the sum of squares and leaves a valid model)."""
        names = [n for n in self.values if n != held]
        if not names:
            return residual
        index = [list(self.values).index(n) for n in names]
        columns = self.jacobian()[:, index]
        lsq = np.linalg.pinv(columns)
        floor = float(self.base @ self.base)
        for _ in range(PROFILE_STEPS):
            scaled = lsq @ residual
            before = float(residual @ residual)
            promised = float(np.sum((columns @ scaled) ** 2))  # the fall the linear model promises
            if promised <= PROFILE_SETTLED * max(before - floor, 0.0):
                break
            step = -scaled * self.scales[index]
            trial = {**point, **{n: point[n] + d for n, d in zip(names, step, strict=True)}}
            if any(trial[n] < 0 <= point[n] and not SIGNED.fullmatch(n) for n in names):
                break  # past a positive parameter's bound
            try:
                again = self.residual_at(trial)
            except UserInputError:
                break
            rss = float(again @ again)
            if rss >= before:
                break
            point, residual = trial, again
            if before - rss < PROFILE_SETTLED * max(before - floor, 0.0):
                break
        return residual


PROFILE_DIFF_STEP = 1e-2
"""`_Profile`'s finite-difference step, relative to each value: `fit_problem`'s (above the stick/slip
timing's jumps)."""


def _rises_on_one_side(
    problem: TrajectoryProblem,
    values: dict[str, float],
    moves: dict[str, float],
    k_max: float,
    rss0: float,
    profile: tuple[_Profile, str] | None = None,
) -> dict[float, float]:
    """The cost's rise from the optimum at k·`moves` for k in CURVATURE_SIGMAS, then on by ×3 while the
    rise grows less than SUB_QUADRATIC times per ×3 (the cost flattening or falling outward: a stair's
    edge near the optimum, a plateau or another valley past it), up to k_max (the move that would take
    the parameter past zero).

    With `profile` (the re-fit and the parameter held), the side is walked on the real profile, the
    others re-fitted at each value, once the straight walk rises slower than a parabola (it flattens:
    where the line leaves a curved valley it climbs the valley's wall instead, and the rise it shows
    there is the wall's) or from the start for a breakaway level (BREAKAWAY_LEVELS: its valley with the
    moving level curves through the sticks' timing)."""
    rises: dict[float, float] = {}
    seen: dict[float, tuple[dict[str, float], np.ndarray]] = {}
    refit = profile is not None and profile[1] in BREAKAWAY_LEVELS
    ks = list(CURVATURE_SIGMAS)
    while ks:
        k = ks.pop(0)
        if k > k_max:
            break  # a move past zero says nothing of σ; σ > value/k is wide already
        point = {n: v + k * moves.get(n, 0.0) for n, v in values.items()}
        try:
            r = (
                problem.residuals_of(problem.model_with(point))
                if profile is None
                else profile[0].residual_at(point)
            )
        except UserInputError:
            break
        seen[k], rises[k] = (point, r), float(r @ r) - rss0
        if rises[k] > 0 and profile is not None and refit:
            rises[k] = profile[0].rise(profile[1], point, r)
        if rises[k] <= 0:
            break
        if not ks and len(rises) > 1 and rises[k] < SUB_QUADRATIC * list(rises.values())[-2]:
            if profile is not None and not refit:  # the line flattens: the real profile from here on
                refit = True
                rises = {j: profile[0].rise(profile[1], *seen[j]) for j in rises}
                if min(rises.values()) <= 0:
                    break
                if rises[k] >= SUB_QUADRATIC * list(rises.values())[-2]:
                    continue  # the real profile is a parabola there: no further
            ks.append(3.0 * k)
    return rises


def _say_verdict(chosen: Choice, fair: list[str], notes: list[Note]) -> None:
    """Which model the held-out windows kept, and why the joint refinement's was not, if it was not."""
    kept, cost, held = chosen.kept, chosen.cost, chosen.held
    verdicts = ", ".join(f"{label} {held[label]:.4g}" for label in chosen.candidates)
    texts = [f"held-out windows (1 in {HOLDOUT_EVERY}): {verdicts}; kept the {kept} model"]
    if chosen.refined is not None and kept != JOINT and JOINT not in fair:
        texts.append(
            f"the joint refinement is worse than the start on all windows ({cost[JOINT]:.4g} against"
            f" {cost['start']:.4g}): {kept} values kept"
        )
    elif chosen.refined is not None and kept != JOINT:
        texts.append(
            f"the joint refinement did not improve on the {kept} model on held-out windows"
            f" ({held[JOINT]:.4g} against {held[kept]:.4g}): {kept} values kept"
        )
    notes += [Note(JOINT, text, named=False) for text in texts]


def _take_joint_values(
    rows: dict[str, ParameterRow],
    refined: TrajectoryFit,
    priors: dict[str, tuple[float, float]],
    notes: list[Note],
) -> None:
    """The rows take the kept joint refinement's values, σ widened where the methods disagree."""
    scale = disagreement_scales(priors, refined.data_only)
    widened = [f"{name} ×{factor:.2g}" for name, factor in scale.items() if factor > 1.0]
    if widened:
        text = (
            "σ widened where the staged estimate and the trajectories alone disagree beyond their σ"
            f" (Birge ratio): {', '.join(widened)}"
        )
        notes.append(Note(JOINT, text, named=False))
    for p in refined.parameters:
        row = rows[p.name]
        row.stage = "trajectory" if row.stage == "trajectory" else row.stage + " + joint"
        if p.identifiable:
            sigma = None if p.std_error is None else p.std_error * scale.get(p.name, 1.0)
            row.estimate, row.uncertainty, row.identifiable, row.note = p.estimate, sigma, True, ""
        elif row.stage == "trajectory":
            # `_sigma_backed_by_cost` drops σ but leaves the fitted value in the model the rows follow.
            kept = "start value kept" if p.estimate == p.start else "fitted value kept, without σ"
            row.note = f"joint: {p.note}; {kept}"
        else:
            row.note = (row.note + "; " if row.note else "") + f"joint: {p.note}, staged value kept"


def _rows_follow(rows: dict[str, ParameterRow], model: HarmonicDriveModel, kept: str) -> None:
    """The rows tell the model returned, whatever it was built from."""

    for row in rows.values():
        value = _start_value(model, row.name)
        if not math.isnan(value) and not math.isclose(value, row.estimate, rel_tol=1e-12, abs_tol=0.0):
            if row.stage != "trajectory":
                row.note = (row.note + "; " if row.note else "") + (
                    f"estimate {row.estimate:.6g} not kept: the {kept} model's value is the better on"
                    " held-out windows"
                )
                row.uncertainty, row.identifiable = None, False
            row.estimate = value


def fitted_channels(model: HarmonicDriveModel) -> tuple[str, ...]:
    """The measured angles the trajectories are fitted on: both, but only θ_m for a rigid model. Its θ_l
    is r·θ_m plus the kinematic error, nothing the dynamics add, and scaled by its small spread within a
    window it magnified the mismatch between a continuous input and its samples, enough to bias J_m by
    many σ on exact simulated data (docs/BENCHMARKS.md, "Figures behind design choices in the code")."""
    return ("theta_m",) if model.rigid else tuple(CHANNELS)


BREAKAWAY_LEVELS = {"static_factor": None, "f_sm": "f_cm"}
"""Breakaway levels, each with the moving level it is a multiple of (static_factor is the multiple)."""
BREAKAWAY_RATIOS = (1.0, 1.1, 1.25, 1.5)
"""Static over moving friction at which `_out_of_a_breakaway_minimum` looks: the range of real drives."""


def _breakaway_start(
    problem: TrajectoryProblem,
    model: HarmonicDriveModel,
    names: list[str],
    priors: dict[str, tuple[float, float]],
    notes: list[Note],
) -> HarmonicDriveModel:
    """The joint step's start with its breakaway level at whichever of BREAKAWAY_RATIOS (and its own)
    costs least on the training windows. From a level far from the truth's the fit can settle in a
    breakaway minimum (a drawn gear, static_factor 1.30: from the seed's 1.04 it sat at 1.304 with
    RMS 0.0051, and only `_out_of_a_breakaway_minimum`'s second fit found 0.00116), and the first fit's
    wandering cost more than the whole fit from 1.25. A few residual evaluations."""
    name = next((n for n in names if n in BREAKAWAY_LEVELS and n not in priors), None)
    if name is None:
        return model
    best, _ = _lowest_breakaway(problem, model, name, _rms(problem.residuals_of(model)))
    if best is None:
        return model
    level = get_values(best, [name])[name]
    notes.append(
        Note(
            JOINT, f"joint refinement starts from {name} {level:.4g} (the lowest cost of a few)", named=False
        )
    )
    return best


def _lowest_breakaway(
    problem: TrajectoryProblem, model: HarmonicDriveModel, name: str, bar: float
) -> tuple[HarmonicDriveModel | None, float]:
    """`model` with its breakaway level `name` at the one of BREAKAWAY_RATIOS of its moving level whose
    cost on `problem` is lowest and under `bar`, and that cost (None if none is under it)."""
    moving = BREAKAWAY_LEVELS[name]
    unit = 1.0 if moving is None else get_values(model, [moving])[moving]
    best, best_cost = None, bar
    for ratio in BREAKAWAY_RATIOS:
        try:
            trial = with_values(model, {name: ratio * unit})
        except UserInputError:
            continue
        cost = _rms(problem.residuals_of(trial))
        if cost < best_cost:
            best, best_cost = trial, cost
    return best, best_cost


def _out_of_a_breakaway_minimum(
    problem: TrajectoryProblem,
    refined: TrajectoryFit,
    names: list[str],
    priors: dict[str, tuple[float, float]],
    notes: list[Note],
) -> TrajectoryFit:
    """The fit again from a breakaway level whose cost is lower, when there is one.

    The breakaway level moves the trajectories only through when each stick ends, and with the other
    friction off at the start the fit can settle where a wrong level and a shifted stick compensate, at
    a higher cost than the truth's side (seen on a lab file's open-loop sine; figures in
    docs/BENCHMARKS.md). The level at BREAKAWAY_RATIOS of the moving level is
    tried at the other fitted values; from the best, if lower, the fit is run again and kept if it ends
    lower. Skipped when a staged estimate is the level's prior (it anchors it)."""
    name = next((n for n in names if n in BREAKAWAY_LEVELS and n not in priors), None)
    if name is None:
        return refined
    level = get_values(refined.model, [name])[name]
    best, _ = _lowest_breakaway(problem, refined.model, name, refined.cost_after)
    if best is None:
        return refined
    again = fit_problem(problem.for_parameters(best, names).with_priors(priors))
    if again.cost_after >= refined.cost_after:
        return refined
    text = (
        f"{name} {level:.4g} was a local minimum (training RMS {refined.cost_after:.4g}): fitted again from"
        f" {get_values(best, [name])[name]:.4g}, RMS {again.cost_after:.4g}"
    )
    notes.append(Note(JOINT, text, named=False))
    return again


def _priors(rows: dict[str, ParameterRow], names: list[str]) -> dict[str, tuple[float, float]]:
    """The staged estimates of the joint parameters, each with its σ, as priors of the joint step.

    They come from data made for them (a stage's own experiment), so their errors are close to
    independent of the trajectories': a breakaway level bracketed within 0.3 % by its stage should not
    be moved 5 % by trajectories that see it to 2 %. Values only the trajectories see get none."""
    out = {}
    for name in names:
        row = rows[name]
        if row.stage != "trajectory" and row.uncertainty is not None and row.uncertainty > 0:
            out[name] = (row.estimate, row.uncertainty)
    return out


POLISH_EVALUATIONS = 6
PLAIN_POLISH_EVALUATIONS = 2
"""The polish of runs without metadata: one Gauss–Newton step on every window (a Jacobian and a trial).
Six took a third of a 46 s lab record's fit (issue 25 item 5: 9.7 of 29 s); whether the five more steps
move any value by a share of its σ was not measured (docs/BENCHMARKS.md, issue 25 items 5, 6)."""
"""Iterations of the polish on every window, from the optimum on three in four: it moves little (20
iterations, with the 10 finite-difference evaluations of the Jacobian each, were a third of the time)."""


def disagreement_scales(
    priors: dict[str, tuple[float, float]], data_only: dict[str, tuple[float, float]]
) -> dict[str, float]:
    """Per parameter with a prior, the Birge ratio max(1, |μ − θ|/√(σ² + σ_T²)) of the two measurements.

    The staged estimate μ ± σ (its stage's own data) and the trajectories' alone θ ± σ_T (one
    Gauss–Newton step from the joint optimum without the priors) measure one parameter by two methods.
    A gap beyond their σ is a bias of one of them (a stage's method, the trajectories' replay) that
    neither σ carries; which one the data do not say. The joint σ is scaled by the ratio, as a
    combination of discrepant measurements is (the Particle Data Group's scale factor), so the σ
    reported carries the disagreement seen; the weights of the combination are unchanged."""
    out = {}
    for name, (mu, sigma) in priors.items():
        if name not in data_only:
            continue
        theta, sigma_t = data_only[name]
        spread = math.hypot(sigma, sigma_t)
        if math.isfinite(theta) and math.isfinite(spread) and spread > 0:
            out[name] = max(1.0, abs(mu - theta) / spread)
    return out


def _better_start(
    others: dict[str, HarmonicDriveModel], start: HarmonicDriveModel, runs: list[Run], notes: list[Note]
) -> HarmonicDriveModel:
    """Of the start model and the columns' estimates (`others`, by name), the one whose trajectories are
    closest to the data."""
    problem = TrajectoryProblem(start, runs, [], JOINT_WINDOW_S, 1e-4, refine_voltage=_refine_voltage(runs))
    mine = _rms(problem.residuals_of(start))
    theirs = {label: _rms(problem.residuals_of(model)) for label, model in others.items()}
    best = min(theirs, key=lambda label: theirs[label])
    if theirs[best] < mine:
        text = f"trajectory fit starts from the {best} estimates (error {theirs[best]:.4g} < {mine:.4g})"
        notes.append(Note(COLUMNS, text, named=False))
        return others[best]
    shown = ", ".join(f"{label} start: {cost:.4g}" for label, cost in theirs.items())
    text = f"trajectory fit starts from the start model ({mine:.4g}; {shown})"
    notes.append(Note(COLUMNS, text, named=False))
    return start


def _refine_voltage(runs: list[Run]) -> bool:
    """Whether the replay refines voltage steps (`TrajectoryProblem`'s `refine_voltage`): kept for
    campaigns; runs without metadata alone take the coarse step with the back-EMF's lag compensated,
    ten times cheaper (issue 25 item 5: a 46 s lab record in ≤ 20 s)."""
    return any(carries_stage_metadata(r) for r in runs)


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
    said: list[Note],
    runs: list[Run],
    report_dir: Path | None,
    say: Progress,
    warm: list[Run] | None = None,
) -> Identification:
    if warm:
        model, rows = _with_thermal(model, rows, said, warm)
    result = Identification(model, rows, before, after, said=said)
    result.imported = [run.meta["import_map"] for run in runs if "import_map" in run.meta]
    if report_dir is not None:
        say("validation", 0.8)
        report_dir.mkdir(parents=True, exist_ok=True)
        result.validation = validate(runs, model, report_dir)
        result.report_file = report_dir / "report.md"
        result.report_file.write_text(_report(result))
    say("done", 1.0)
    return result


WARM_UP = "warm-up"
THERMAL = "thermal"
"""The thermal stage's name in notes and rows (`thermal_stage`: network and friction law from warm-ups)."""


def _with_thermal(
    model: HarmonicDriveModel, rows: list[ParameterRow], said: list[Note], warm: list[Run]
) -> tuple[HarmonicDriveModel, list[ParameterRow]]:
    """The model with the `thermal` section fitted on the warm-up runs, and its rows (issue 27 item 4).
    The other parameters stay as fitted: on the other runs, without their temperatures."""
    from rig.analysis.identification.thermal_stage import identify_thermal

    found = identify_thermal(warm, model)
    old = model.thermal
    estimates = {name: (e.value, e.sigma) for name, e in found.network.parameters.items()}
    estimates["beta_T"] = (found.law.beta_per_k.value, found.law.beta_per_k.sigma)
    estimates["T_amb"] = (found.section.T_amb, math.nan)
    fitted = [
        ParameterRow(
            name,
            float(getattr(old, name)) if old is not None else math.nan,
            value,
            None if math.isnan(sigma) else sigma,
            not math.isnan(sigma),
            THERMAL,
            "" if name != "T_amb" else "the warm-up runs' mean ambient, from the network fit",
        )
        for name, (value, sigma) in estimates.items()
    ]
    said += [Note(THERMAL, text) for text in found.network.notes]
    said.append(
        Note(
            THERMAL,
            f"friction law from {len(warm)} warm-up run(s) at T_ref = {found.law.t_ref_c:g} °C over"
            f" {found.law.temperature_span_c[0]:.1f}–{found.law.temperature_span_c[1]:.1f} °C; the other"
            " parameters are fitted on the other runs without their temperatures",
        )
    )
    kept = [row for row in rows if row.name not in estimates]
    return model.model_copy(update={"thermal": found.section}), kept + fitted


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
    from rig.analysis.identification.lab_quantities import fitted_sigmas, lab_quantities, lab_table

    lines += [*lab_table(lab_quantities(result.model, fitted_sigmas(result.parameters))), ""]
    lines += [f"- {n}" for n in result.notes]
    return "\n".join(lines) + "\n"
