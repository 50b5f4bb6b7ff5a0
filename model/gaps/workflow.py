"""The model-gap workflow: find where simulation and measurement disagree, name the missing effect, add
it, show the gap shrink — and go on until nothing significant is left.

Each step:
1. find: the one-step residual of the current model on the data (`residual`), and the gap (`shooting`);
2. name: every vocabulary effect's signature is scored on held-out blocks (`effects.screen`);
3. add: the best few candidates are added as model sections and fitted by the simulator on the
   training windows (`shooting.fit_on_windows`);
4. show: the gap on the held-out windows, before and after.

Significance rule: a candidate is accepted only if the held-out gap shrinks by at least `min_shrink`
(1.25×) — against the current model and against refitting only the parameters it interacts with, so
that its own parameters must earn their place — AND its own parameters are determined (none blind or
confounded, at least one with |estimate| ≥ 3 standard errors). Among accepted candidates the smallest
held-out gap wins, except that one with fewer parameters within 10 % of it is preferred. When none is
accepted, the model explains the data and nothing is added.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from model.errors import UserInputError
from model.fit.parameters import get_values
from model.fit.trajectory import ParameterEstimate
from model.gaps.effects import Candidate, Context, merge_sections, screen
from model.gaps.residual import Residual, one_step_residual
from model.gaps.shooting import METRIC, EffectFit, Shooting, fit_on_windows
from model.gaps.signals import SMOOTHING_S, Signals, cut_windows, prepare
from model.params import HarmonicDriveModel, save_model
from model.run import Run

Progress = Callable[[str, float], None]
"""Called with what is being done and the fraction of the job done, 0..1 (as `rig.runner.Progress`)."""


@dataclass(frozen=True)
class GapOptions:
    window_s: float = 0.02  # shooting window [s]: short, as open-loop friction dynamics can be unstable
    smoothing_s: float = SMOOTHING_S  # width of the one smoother [s]
    dt_s: float = 1e-4  # integration step of replays [s]
    min_shrink: float = 1.25  # held-out gap before/after an accepted effect, at least
    min_t_ratio: float = 3.0  # |estimate| / standard error of at least one own parameter
    occam: float = 1.10  # a simpler candidate within this factor of the best is preferred
    max_steps: int = 4
    confirm: int = 3  # candidates fitted by the simulator per step
    max_fit_windows: int = 150
    max_iterations: int = 12


@dataclass
class Trial:
    """One candidate added and fitted: how it did on the held-out windows."""

    candidate: Candidate
    fit_names: list[str]  # the candidate's parameters and those of the effects added before it
    fit: EffectFit
    held_out_after: float
    baseline: float  # held-out gap to beat: current model, or its interacting parameters refitted
    determined: bool
    accepted: bool


@dataclass
class GapStep:
    """One effect added: the gap before/after (all windows, held-out windows), why, and the fit."""

    effect: str
    gap_before: float
    gap_after: float
    held_out_before: float
    held_out_after: float
    evidence: str
    parameters: dict[str, float]
    estimates: list[ParameterEstimate]
    model_before: HarmonicDriveModel
    model_after: HarmonicDriveModel
    trials: list[Trial]


@dataclass
class GapsResult:
    """What the workflow found (`rig.core.actions.gaps_document` makes the `--json` document of it)."""

    metric: str
    initial_gap: float
    steps: list[GapStep]
    final_gap: float
    final_model: Path | None
    model: HarmonicDriveModel
    held_out_initial: float
    held_out_final: float
    verdict: str  # one line: what was found, or that the model explains the data
    last_trials: list[Trial] = field(default_factory=list)  # the step that found nothing
    report: list[Path] = field(default_factory=list)


def _determined(fit: EffectFit, own: list[str], min_t_ratio: float) -> bool:
    """No own parameter blind or confounded, and at least one clearly nonzero."""
    mine = [p for p in fit.parameters if p.name in own]
    if any(p.note and "exceeds" not in p.note for p in mine):
        return False  # blind or confounded
    return any(
        p.identifiable and p.std_error is not None and abs(p.estimate) >= min_t_ratio * p.std_error
        for p in mine
    )


def _choose(
    trials: list[Trial], current: HarmonicDriveModel, gap_test: float, opts: GapOptions
) -> Trial | None:
    """The accepted trial with the smallest held-out gap (a simpler one within `occam` preferred); but
    when its fit moved a parameter it interacts with by more than a quarter, refitting those alone was
    itself significant, and that refit is a trial of its own (coulomb_friction refits the level), that
    one goes first: one effect per step."""
    accepted = sorted((t for t in trials if t.accepted), key=lambda t: t.held_out_after)
    if not accepted:
        return None
    best = accepted[0]
    simpler = [t for t in accepted if len(t.candidate.fit) < len(best.candidate.fit)]
    simpler = [t for t in simpler if t.held_out_after <= opts.occam * best.held_out_after]
    chosen = min(simpler, key=lambda t: t.held_out_after) if simpler else best
    others = set(chosen.fit_names) - set(chosen.candidate.own)
    if others and chosen.baseline * opts.min_shrink <= gap_test:
        was = get_values(current, sorted(others))
        now = {p.name: p.estimate for p in chosen.fit.parameters}
        moved = any(abs(now[n] - v) > 0.25 * abs(v) for n, v in was.items())
        first = [t for t in accepted if set(t.fit_names) == others]
        if moved and first:
            return first[0]
    return chosen


def _prior(steps: list[GapStep]) -> list[str]:
    """The parameters of the effects added so far: refitted with each new one, as they interact."""
    names: list[str] = []
    for step in steps:
        names += [n for n in step.parameters if n not in names]
    return names


def _try(
    current: HarmonicDriveModel,
    shortlist: list[Candidate],
    shooting: Shooting,
    gap_test: float,
    prior: list[str],
    opts: GapOptions,
    say: Progress,
    number: int,
    base: float,
) -> list[Trial]:
    """Add and fit each candidate; judge it against the current model and against refitting only the
    parameters it interacts with (the effect's own parameters must earn the shrink)."""
    fits: list[tuple[Candidate, list[str], EffectFit, float]] = []
    for i, cand in enumerate(shortlist):
        say(
            f"step {number + 1}: adding {cand.effect}", base + (i + 1) / (len(shortlist) + 2) / opts.max_steps
        )
        names = cand.fit + [n for n in prior if n not in cand.fit]
        fit = fit_on_windows(
            merge_sections(current, **cand.sections),
            shooting,
            names,
            cand.ties,
            opts.max_fit_windows,
            opts.max_iterations,
        )
        fits.append((cand, names, fit, shooting.gap(fit.model, shooting.test)))
    baselines: dict[frozenset[str], float] = {frozenset(): gap_test}
    for _, names, _, after in fits:  # a trial that refits exactly a set of parameters is its baseline
        key = frozenset(names)
        baselines[key] = min(baselines.get(key, gap_test), after)
    trials = []
    for cand, names, fit, after in fits:
        key = frozenset(n for n in names if n not in cand.own)
        if key not in baselines:
            # Refit from the current values; one at zero cannot start (the trust region scales with it).
            start = [n for n, v in get_values(current, sorted(key)).items() if v != 0.0]
            refit = fit_on_windows(current, shooting, start, {}, opts.max_fit_windows, opts.max_iterations)
            baselines[key] = min(gap_test, shooting.gap(refit.model, shooting.test)) if start else gap_test
        determined = _determined(fit, cand.own, opts.min_t_ratio)
        accepted = determined and min(gap_test, baselines[key]) >= opts.min_shrink * after
        trials.append(Trial(cand, names, fit, after, min(gap_test, baselines[key]), determined, accepted))
    return trials


def _shortlist(candidates: list[Candidate], count: int) -> list[Candidate]:
    """The best `count`, plus the best of each channel (channels are not comparable by score)."""
    chosen = candidates[:count]
    for channel in {c.channel for c in candidates}:
        best = next(c for c in candidates if c.channel == channel)
        if best not in chosen:
            chosen.append(best)
    return chosen


def residuals_of(model: HarmonicDriveModel, signals: list[Signals], dt_s: float) -> list[Residual]:
    """The one-step residual of `model` on every prepared run."""
    return [one_step_residual(model, s, dt_s) for s in signals]


def find_gaps(
    runs: list[Run],
    model: HarmonicDriveModel,
    report_dir: str | Path | None = None,
    progress: Progress | None = None,
    model_out: str | Path | None = None,
    options: GapOptions | None = None,
) -> GapsResult:
    """Run the gap workflow on validated runs; write the model with the effects added (and a report).

    The model file goes to `model_out`, else `report_dir/model.yaml`, else nowhere (final_model None).
    """
    opts = options or GapOptions()
    if not runs:
        raise UserInputError("gaps: no data given")
    say = progress or (lambda label, fraction: None)
    signals = [prepare(run, model.numerics.omega_stick_m, opts.smoothing_s) for run in runs]
    shooting = Shooting(signals, cut_windows(signals, opts.window_s), model.mechanics.r, opts.dt_s)
    if not shooting.test or not shooting.train:
        raise UserInputError("gaps: the data are too short for held-out shooting windows (need ≥ 3 windows)")

    current = model
    gap_all = shooting.gap(current, shooting.everything)
    gap_test = shooting.gap(current, shooting.test)
    initial, initial_test = gap_all, gap_test
    steps: list[GapStep] = []
    trials: list[Trial] = []
    for number in range(opts.max_steps):
        base = number / opts.max_steps
        say(f"step {number + 1}: screening the residual", base)
        ctx = Context(current, signals, residuals_of(current, signals, opts.dt_s))
        shortlist = _shortlist(screen(ctx, skip={s.effect for s in steps}), opts.confirm)
        trials = _try(current, shortlist, shooting, gap_test, _prior(steps), opts, say, number, base)
        chosen = _choose(trials, current, gap_test, opts)
        if chosen is None:
            break
        after_all = shooting.gap(chosen.fit.model, shooting.everything)
        steps.append(
            GapStep(
                effect=chosen.candidate.effect,
                gap_before=gap_all,
                gap_after=after_all,
                held_out_before=gap_test,
                held_out_after=chosen.held_out_after,
                evidence=chosen.candidate.evidence,
                parameters={p.name: p.estimate for p in chosen.fit.parameters},
                estimates=chosen.fit.parameters,
                model_before=current,
                model_after=chosen.fit.model,
                trials=trials,
            )
        )
        current, gap_all, gap_test = chosen.fit.model, after_all, chosen.held_out_after
        trials = []

    if steps:
        added = ", ".join(s.effect for s in steps)
        shrink = initial / max(gap_all, 1e-300)
        verdict = f"added {added}: gap {initial:.3g} → {gap_all:.3g} rad ({shrink:.1f}× smaller)"
        current = current.with_updates(
            name=f"{model.name}+gaps",
            description=f"{model.description} Effects added by `hdrig gaps`: {added}.".strip(),
        )
    else:
        best = min(trials, key=lambda t: t.held_out_after, default=None)
        tried = (
            f"; best candidate {best.candidate.effect}: held-out gap"
            f" ×{best.baseline / max(best.held_out_after, 1e-300):.2f}, needs ×{opts.min_shrink:g}"
            if best is not None
            else "; no effect's signature explains any of the residual"
        )
        verdict = (
            f"the model explains the data: nothing significant is missing (gap {gap_all:.3g} rad{tried})"
        )
    out = (
        Path(model_out)
        if model_out is not None
        else (Path(report_dir) / "model.yaml" if report_dir else None)
    )
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        save_model(current, out)
    result = GapsResult(
        METRIC, initial, steps, gap_all, out, current, initial_test, gap_test, verdict, trials
    )
    if report_dir is not None:
        from model.gaps.report import write_report

        say("writing the report", 0.98)
        result.report = write_report(result, signals, shooting, Path(report_dir), opts)
    say("done", 1.0)
    return result
