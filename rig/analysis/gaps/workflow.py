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
accepted:
- pairs: effects that only explain the data together (each alone short of the rule) are tried two at a
  time, among the candidates that shrank the gap at all; a pair is accepted when it shrinks the held-out
  gap `min_shrink`× against the current model and against each of its members alone, both members'
  parameters determined; it adds two steps;
- else nothing is added, and the result still says what is left: the largest unexplained residual
  signature (`effects.signature`: a binned function of speed, angle, time, torque or rest) and why each
  candidate was rejected. The verdict says the model explains the data only when that signature is
  below `effects.SYSTEMATIC`.

Stribeck or static friction: both add friction near zero speed, and on closed-loop data a higher
breakaway alone can shorten the same stick-slip. What tells them apart is the decay with speed: a static
friction candidate, alone or in a pair, is rejected when its fitted model still leaves friction decaying
with |ω| while moving (Stribeck's signature explains `min_decay` or more of the motor residual beyond the
level); and neither is tried without the other.

Slow factors: `thermal_drift` (time since the run's start), `wear_drift` (motor travel since then) and
`temperature_dependence` (the recorded gear temperature) all scale the motor friction slowly; each is
scored by what it explains beyond the other two (`effects.slow_scores`), so runs at several temperatures
and travels tell them apart; the best of them is always fitted. Replays start from the measured
temperatures and travel (`shooting.started`, `residual._measured_states`).

Output transducer: a run with `tau_out` (a dynamometer bench) has the gear cut at the transducer: tau_out
is the torque beyond the output (`signals.output_boundary`), so the load channel is the output's own
balance, tau_out + J_l·α_l − (T_s − F_l), without the motor's friction or the load drive, and an effect
at the output (load friction hidden) is found there.

Effects at zero: a section the model carries with its strengths at zero (`effects.carried`: load friction
with f_cl = f_sl = b_l = 0, Stribeck with f_st = 0, ...) does nothing yet, so its effect is a candidate
like an absent one.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from model.errors import UserInputError
from model.params import HarmonicDriveModel, save_model
from model.run import Run
from rig.analysis.fit.parameters import get_values, with_values
from rig.analysis.fit.trajectory import ParameterEstimate
from rig.analysis.gaps.effects import (
    SLOW_EFFECTS,
    SYSTEMATIC,
    Candidate,
    Context,
    Signature,
    merge_sections,
    screen,
    screen_stribeck,
    signature,
)
from rig.analysis.gaps.residual import Residual, one_step_residual
from rig.analysis.gaps.shooting import METRIC, EffectFit, Shooting, fit_on_windows
from rig.analysis.gaps.signals import SMOOTHING_S, Signals, cut_windows, prepare

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
    min_decay: float = 0.05  # Stribeck's signature left by a static-friction fit that rejects it
    pairs: int = 3  # pairs tried when no single candidate passes (among the best partial shrinks)


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
    reason: str = ""  # why it was rejected (empty when accepted)
    partner: Candidate | None = None  # tried as a pair with this one

    @property
    def effects(self) -> list[str]:
        return [self.candidate.effect] + ([self.partner.effect] if self.partner else [])

    def line(self, gap_test: float) -> str:
        """One line: what was tried, its held-out shrink, and the verdict."""
        name = " + ".join(self.effects)
        if self.reason.startswith("held-out gap"):
            return f"{name}: {self.reason}"
        gain = gap_test / max(self.held_out_after, 1e-300)
        return f"{name}: held-out gap ×{gain:.2f}, {self.reason or 'accepted'}"


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
    unexplained: Signature | None = None  # the largest structure left in the final model's residual
    rejected: list[str] = field(default_factory=list)  # the last step's candidates and why each failed


def _undetermined(fit: EffectFit, own: list[str], min_t_ratio: float) -> str:
    """Why the fit's own parameters are not determined ('' when they are): one blind or confounded, or
    none clearly nonzero."""
    mine = [p for p in fit.parameters if p.name in own]
    for p in mine:
        if p.note and "exceeds" not in p.note:
            return f"{p.name}: {p.note}"
    if any(
        p.identifiable and p.std_error is not None and abs(p.estimate) >= min_t_ratio * p.std_error
        for p in mine
    ):
        return ""
    return f"none of {', '.join(own)} is {min_t_ratio:g} standard errors from zero"


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
        undetermined = _undetermined(fit, cand.own, opts.min_t_ratio)
        baseline = min(gap_test, baselines[key])
        why = undetermined
        if not why and baseline < opts.min_shrink * after:
            why = f"held-out gap ×{baseline / max(after, 1e-300):.2f}, needs ×{opts.min_shrink:g}" + (
                f" (against refitting {', '.join(sorted(key))} alone)" if baseline < gap_test else ""
            )
        trials.append(Trial(cand, names, fit, after, baseline, not undetermined, not why, why))
    return trials


def _leaves_decay(trial: Trial, signals: list[Signals], opts: GapOptions) -> float:
    """Stribeck's signature in the residual of a fitted model: the share of the motor residual that
    friction decaying with |ω| explains beyond the level (held out); 0 if it has none."""
    ctx = Context(trial.fit.model, signals, residuals_of(trial.fit.model, signals, opts.dt_s))
    left = screen_stribeck(ctx)
    return left.score if left is not None else 0.0


def _tell_static_from_stribeck(trials: list[Trial], signals: list[Signals], opts: GapOptions) -> None:
    """Reject an accepted static-friction trial whose model still leaves friction decaying with speed:
    that is Stribeck's, which a higher breakaway only imitates on closed-loop stick-slip."""
    for trial in trials:
        # A pair is checked too: with another effect beside it (position-periodic friction, issue 25),
        # static friction imitated Stribeck's share of a pair's shrink.
        if trial.accepted and "static_friction" in trial.effects:
            decay = _leaves_decay(trial, signals, opts)
            if decay >= opts.min_decay:
                trial.accepted = False
                trial.reason = (
                    f"its fit leaves friction that decays with speed ({100 * decay:.0f} % of the motor"
                    f" residual beyond the level, Stribeck's signature; needs < {100 * opts.min_decay:.0f} %)"
                )


def _try_pairs(
    current: HarmonicDriveModel,
    trials: list[Trial],
    shooting: Shooting,
    gap_test: float,
    prior: list[str],
    opts: GapOptions,
) -> list[Trial]:
    """Pairs of the candidates that shrank the held-out gap at all (the best `opts.pairs` of them),
    fitted together; accepted when the pair shrinks the gap `min_shrink`× against the current model
    and against each member alone, with both members' parameters determined."""
    helpful = sorted((t for t in trials if t.held_out_after < gap_test), key=lambda t: t.held_out_after)
    helpful = helpful[: opts.pairs]
    out = []
    for first, second in itertools.combinations(helpful, 2):
        a, b = first.candidate, second.candidate
        if set(a.own) & set(b.own):
            continue
        sections = dict(a.sections)
        for key, value in b.sections.items():
            both = sections.get(key)
            sections[key] = {**both, **value} if isinstance(both, dict) and isinstance(value, dict) else value
        names = list(dict.fromkeys(a.fit + b.fit + prior))
        fit = fit_on_windows(
            merge_sections(current, **sections),
            shooting,
            names,
            {**a.ties, **b.ties},
            opts.max_fit_windows,
            opts.max_iterations,
        )
        after = shooting.gap(fit.model, shooting.test)
        alone = min(gap_test, first.held_out_after, second.held_out_after)
        undetermined = _undetermined(fit, a.own, opts.min_t_ratio) or _undetermined(
            fit, b.own, opts.min_t_ratio
        )
        why = undetermined
        if not why and alone < opts.min_shrink * after:
            why = (
                f"held-out gap ×{alone / max(after, 1e-300):.2f} against the better member alone,"
                f" needs ×{opts.min_shrink:g}"
            )
        out.append(Trial(a, names, fit, after, alone, not undetermined, not why, why, partner=b))
    return out


def _shortlist(candidates: list[Candidate], count: int) -> list[Candidate]:
    """The best `count`, plus the best of each channel (channels are not comparable by score)."""
    chosen = candidates[:count]
    for channel in {c.channel for c in candidates}:
        best = next(c for c in candidates if c.channel == channel)
        if best not in chosen:
            chosen.append(best)
    # Stribeck and static friction both add friction near zero speed: one is tried only beside the other,
    # so that the decay with speed (`_tell_static_from_stribeck`) decides between them, not the screen's
    # ranking (with another effect in the residual, Stribeck's screen score fell out of the shortlist).
    # A slow factor's score is only what it explains beyond the other slow factors (effects.slow_scores),
    # a share no other screen is cut down to: the best of them is tried whatever its rank (wear at 1.5×
    # the nominal rate fell to fifth behind the level, load-dependent and static friction, and
    # load-dependent friction took its place).
    slow = next((c for c in candidates if c.effect in SLOW_EFFECTS), None)
    if slow is not None and slow not in chosen:
        chosen.append(slow)
    named = {c.effect for c in chosen}
    for one, other in (("static_friction", "stribeck"), ("stribeck", "static_friction")):
        partner = next((c for c in candidates if c.effect == other), None)
        if one in named and other not in named and partner is not None:
            chosen.append(partner)
            named.add(other)
    return chosen


@dataclass
class _Member:
    """One effect of an accepted trial, as a step: its model and values."""

    candidate: Candidate
    model: HarmonicDriveModel
    parameters: dict[str, float]
    evidence: str


def _members(chosen: Trial, current: HarmonicDriveModel, shooting: Shooting) -> list[_Member]:
    """A single trial's one step; a pair's two: first the member that alone (at the pair's fitted
    values) leaves the smaller gap, then the pair's model."""
    values = {p.name: p.estimate for p in chosen.fit.parameters}
    if chosen.partner is None:
        return [_Member(chosen.candidate, chosen.fit.model, values, chosen.candidate.evidence)]
    together = "; explains the data only together with {} (held-out gap ×{:.2f} together)"
    gain = chosen.baseline / max(chosen.held_out_after, 1e-300)
    alone = []
    for cand in (chosen.candidate, chosen.partner):
        names = [n for n in cand.fit if n in values]
        model = with_values(merge_sections(current, **cand.sections), {n: values[n] for n in names})
        model = with_values(model, {t: values[s] for t, s in cand.ties.items() if s in values})
        alone.append((shooting.gap(model, shooting.test), cand, model, {n: values[n] for n in names}))
    alone.sort(key=lambda a: a[0])
    (_, first, model, own), (_, second, _, _) = alone
    return [
        _Member(first, model, own, first.evidence + together.format(second.effect, gain)),
        _Member(second, chosen.fit.model, values, second.evidence + together.format(first.effect, gain)),
    ]


def residuals_of(model: HarmonicDriveModel, signals: list[Signals], dt_s: float) -> list[Residual]:
    """The one-step residual of `model` on every prepared run."""
    return [one_step_residual(model, s, dt_s) for s in signals]


def _choose_step(
    current: HarmonicDriveModel,
    signals: list[Signals],
    shooting: Shooting,
    gap_test: float,
    steps: list[GapStep],
    opts: GapOptions,
    say: Progress,
    number: int,
) -> tuple[Trial | None, list[Trial]]:
    """One step's screen and trials: the effect (or pair) accepted, if any, and every trial made."""
    base = number / opts.max_steps
    say(f"step {number + 1}: screening the residual", base)
    ctx = Context(current, signals, residuals_of(current, signals, opts.dt_s))
    shortlist = _shortlist(screen(ctx, skip={s.effect for s in steps}), opts.confirm)
    trials = _try(current, shortlist, shooting, gap_test, _prior(steps), opts, say, number, base)
    _tell_static_from_stribeck(trials, signals, opts)
    chosen = _choose(trials, current, gap_test, opts)
    if chosen is None:
        say(f"step {number + 1}: trying effects in pairs", base + 0.8 / opts.max_steps)
        pairs = _try_pairs(current, trials, shooting, gap_test, _prior(steps), opts)
        _tell_static_from_stribeck(pairs, signals, opts)
        trials += pairs
        chosen = min((t for t in pairs if t.accepted), key=lambda t: t.held_out_after, default=None)
    return chosen, trials


def _steps_of(
    chosen: Trial,
    current: HarmonicDriveModel,
    shooting: Shooting,
    gap_all: float,
    gap_test: float,
    trials: list[Trial],
) -> list[GapStep]:
    """The accepted trial as steps, one per effect (a pair gives two), each after the one before."""
    steps = []
    for member in _members(chosen, current, shooting):
        after_all = shooting.gap(member.model, shooting.everything)
        after_test = shooting.gap(member.model, shooting.test) if chosen.partner else chosen.held_out_after
        steps.append(
            GapStep(
                effect=member.candidate.effect,
                gap_before=gap_all,
                gap_after=after_all,
                held_out_before=gap_test,
                held_out_after=after_test,
                evidence=member.evidence,
                parameters=member.parameters,
                estimates=[p for p in chosen.fit.parameters if p.name in member.parameters],
                model_before=current,
                model_after=member.model,
                trials=trials,
            )
        )
        current, gap_all, gap_test = member.model, after_all, after_test
    return steps


def _verdict(
    steps: list[GapStep], initial: float, gap_all: float, rejected: list[str], left: Signature | None
) -> str:
    """The workflow's one-line answer: what was added, or why nothing was."""
    if steps:
        added = ", ".join(s.effect for s in steps)
        shrink = initial / max(gap_all, 1e-300)
        return f"added {added}: gap {initial:.3g} → {gap_all:.3g} rad ({shrink:.1f}× smaller)"
    tried = (
        "; tried " + "; ".join(rejected)
        if rejected
        else "; no effect's signature explains any of the residual"
    )
    where = f"; largest residual signature: {left.line()}" if left is not None else ""
    if left is not None and left.share >= SYSTEMATIC:
        return (
            f"nothing named, but the gap is systematic (gap {gap_all:.3g} rad): no effect of the"
            f" vocabulary explains it{where}{tried}"
        )
    return (
        f"the model explains the data: nothing significant is missing (gap {gap_all:.3g} rad{where}{tried})"
    )


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
        chosen, trials = _choose_step(current, signals, shooting, gap_test, steps, opts, say, number)
        if chosen is None:
            break
        taken = _steps_of(chosen, current, shooting, gap_all, gap_test, trials)
        steps += taken
        current, gap_all, gap_test = taken[-1].model_after, taken[-1].gap_after, taken[-1].held_out_after
        trials = []

    final_ctx = Context(current, signals, residuals_of(current, signals, opts.dt_s))
    left = signature(final_ctx)
    rejected = [t.line(gap_test) for t in trials]
    verdict = _verdict(steps, initial, gap_all, rejected, left)
    cut = sorted({s.boundary for s in signals} - {"tau_ext"})
    if cut:
        verdict += (
            f"; the gear was judged cut at its output transducer ({', '.join(cut)} as the output's torque:"
            " the output's residual needs no motor friction and no load drive)"
        )
    if steps:
        added = ", ".join(s.effect for s in steps)
        current = current.with_updates(
            name=f"{model.name}+gaps",
            description=f"{model.description} Effects added by `hdrig gaps`: {added}.".strip(),
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
        METRIC,
        initial,
        steps,
        gap_all,
        out,
        current,
        initial_test,
        gap_test,
        verdict,
        trials,
        unexplained=left,
        rejected=rejected,
    )
    if report_dir is not None:
        from rig.analysis.gaps.report import write_report

        say("writing the report", 0.98)
        result.report = write_report(result, signals, shooting, Path(report_dir), opts)
    say("done", 1.0)
    return result
