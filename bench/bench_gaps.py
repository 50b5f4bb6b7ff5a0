"""Gap-workflow benchmark: hit rate, false alarms, gap shrinkage and time, beside a generic SINDy baseline.

Prints tables, asserts nothing. What it measures:

1. Two suites, one per data generator:
   - the project's simulated rig (`hdrig_testing.hidden_effects`): every vocabulary effect the simulator
     produces, hidden at a few strengths (a fraction of its nominal size) and rig noise seeds, plus null
     cases (the model is the truth, rigid and compliant); the closed-loop probe, `--duration` s;
   - the independent generator (`hdrig_testing.independent_plant`: scipy RK45 with event-located
     sticking, 14-bit encoder, its own velocity PI and lab profile with load steps), sharing no code
     with the plant: every effect it implements, at `--independent-strengths`, the pair Stribeck +
     position-periodic friction, and null cases; `--independent-duration` s.
   Each case is judged on the gap in excess of its generator's null floor (the median initial gap of
   the null cases of the same rigidity): "excess removed" is (initial − final)/(initial − floor).
2. The gap workflow (`rig.analysis.gaps.find_gaps`) on each case: a hit is exactly the hidden effect named; a
   false alarm is any named effect that was not hidden (null cases: anything named). Shrinkage is the
   gap (shooting error) before/after, and the one-step residual's RMS on held-out blocks before/after.
3. The same cases through a generic sparse regression (PySINDy's STLSQ, pip install pysindy): the same
   one-step residual channels regressed on a library of polynomial (degree 2), Fourier (10 harmonics of
   θ_m), sign terms and sgn(ω)×(polynomial, Fourier) products of θ_m, ω_m, T_s, t (and ω_l, deflection
   rate when the output is measured), smoothed like the residual. It names the effect whose library
   terms carry most of the fitted variance (term → effect table below), if the fit shrinks the held-out
   residual RMS by 1.25× (the workflow's own threshold); its shrinkage is that held-out residual ratio.
   Skipped, with a message, when pysindy is not installed.
4. Time per case on `--timing-duration` s (default 60 s) of 1 kHz data, target < 60 s.
5. Slow friction factors (issue 27 item 5, `--generators slow`): the independent generator's thermal
   state, three records per case at several temperatures and travels (`hidden_effects.slow_case`):
   friction that follows only the gear temperature (the model without a thermal law), the two nulls
   (temperatures recorded, friction ignoring them; the model carrying the truth's law), wear with travel
   and drift with time. Per case: what is named, the gap before/after, the fitted strength against the
   truth's, the time. A hit is exactly the hidden slow effect among the slow factors named
   (temperature_dependence, thermal_drift, wear_drift); a false alarm is anything named on a null.
"""

from __future__ import annotations

import argparse
import math
import re
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hdrig_testing.hidden_effects import (
    BETA_T,
    HIDDEN,
    K_WEAR,
    SLOW_CASES,
    THERMAL_DRIFT,
    Case,
    carried_at_zero_case,
    hidden_case,
    record_probe,
    slow_case,
)
from hdrig_testing.independent_plant import IndependentRig, lab_profile
from model.run import Run
from rig.analysis.gaps import find_gaps
from rig.analysis.gaps.effects import Context
from rig.analysis.gaps.residual import Residual
from rig.analysis.gaps.signals import Signals, prepare
from rig.analysis.gaps.workflow import GapsResult, residuals_of

DT_S = 1e-4
MIN_SHRINK = 1.25


INDEPENDENT_EFFECTS = (
    "coulomb_friction",
    "viscous_friction",
    "stribeck",
    "static_friction",
    "position_periodic_friction",
    "position_quadratic_friction",
    "kinematic_error",
    "compliance",
    "load_side_friction",
)
"""The effects the independent generator implements (it refuses the others' model sections)."""
PAIR = ("stribeck", "position_periodic_friction")


def issue_classes(strength: float) -> list[tuple[str, Case]]:
    """The two classes issue 25 adds, on both generators: load-side friction hidden while the model carries
    its section at zero (an effect at zero is a candidate), and the Stribeck + position-periodic pair on
    a flexible joint (Stribeck told from static friction when it comes with another effect)."""
    return [
        (f"load_side_friction(at zero)@{strength:g}", carried_at_zero_case(strength)),
        (f"{'+'.join(PAIR)}(compliant)@{strength:g}", hidden_case(PAIR, strength, compliant=True)),
    ]


MOST = 0.5
"""'Most of its excess gap removed': at least this share of the gap above the null floor."""


@dataclass
class Outcome:
    named: list[str]
    shrink_gap: float | None  # shooting gap before/after (workflow only)
    shrink_residual: float  # held-out one-step residual RMS before/after
    seconds: float
    initial_gap: float = math.nan  # workflow only [rad]
    final_gap: float = math.nan
    verdict: str = ""


@dataclass
class Row:
    case: str
    effect: str  # hidden effect(s) joined by "+", or "null"
    ours: Outcome
    sindy: Outcome | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    generator: str = "sim rig"
    label: str = ""  # the class the per-effect table groups by: the effect(s), or an issue's class
    compliant: bool = False
    floor: float = math.nan  # the null cases' median gap for this generator and rigidity [rad]

    @property
    def hidden(self) -> set[str]:
        return set() if self.effect == "null" else set(self.effect.split("+"))

    def removed(self) -> float:
        """Share of the gap in excess of the null floor that the workflow removed."""
        excess = self.ours.initial_gap - self.floor
        return (self.ours.initial_gap - self.ours.final_gap) / excess if excess > 0 else math.nan


# --- the workflow ------------------------------------------------------------------------------------


def _held_out_rms(y: np.ndarray, folds: np.ndarray) -> float:
    test = folds % 2 == 1
    return float(np.sqrt(np.mean(y[test] ** 2))) if np.any(test) else 0.0


def _residual_shrink(case: Case, result: GapsResult, run: Run) -> float:
    """Held-out one-step residual RMS, given vs final model, on the channel the effect is seen in."""
    signals = [prepare(run, case.model.numerics.omega_stick_m)]
    channel = "motor"
    if result.steps:
        chosen = next(t for t in result.steps[0].trials if t.candidate.effect == result.steps[0].effect)
        channel = chosen.candidate.channel
    before = Context(case.model, signals, residuals_of(case.model, signals, DT_S))
    after = Context(result.model, signals, residuals_of(result.model, signals, DT_S))
    if channel not in after.channels or channel not in before.channels:
        channel = "motor"
    return _held_out_rms(before.channels[channel], before.folds) / max(
        _held_out_rms(after.channels[channel], after.folds), 1e-300
    )


def run_ours(case: Case, run: Run) -> Outcome:
    start = time.perf_counter()
    result = find_gaps([run], case.model)
    seconds = time.perf_counter() - start
    return Outcome(
        [s.effect for s in result.steps],
        result.initial_gap / max(result.final_gap, 1e-300),
        _residual_shrink(case, result, run),
        seconds,
        result.initial_gap,
        result.final_gap,
        result.verdict,
    )


# --- the generic baseline: PySINDy -------------------------------------------------------------------

TOKEN = re.compile(r"(?:sin|cos)\(\d+ \w+\)|\S+")
FEATURES = ("th", "w", "Ts", "t")
LOAD_FEATURES = ("wl", "dd")
_CATEGORY = {
    "1": "bias",
    "w": "speed",
    "w^2": "speed",
    "th": "position",
    "th^2": "position",
    "Ts": "load",
    "Ts^2": "load",
    "sgn(Ts)": "load",
    "t": "time",
    "t^2": "time",
    "wl": "out_speed",
    "wl^2": "out_speed",
    "sgn(wl)": "out_speed",
    "dd": "deflection_rate",
    "dd^2": "deflection_rate",
    "sgn(dd)": "deflection_rate",
}


def term_effect(term: str, channel: str) -> str | None:
    """The vocabulary effect a library term stands for (docs/MODEL.md's signature column); None if mixed."""
    tokens = TOKEN.findall(term)
    kinds = set()
    for token in tokens:
        if token.startswith(("sin(", "cos(")):
            kinds.add("periodic")
        elif token != "sgn(w)":
            kinds.add(_CATEGORY.get(token, "other"))
    if len(kinds) > 1 or "other" in kinds:
        return None
    kind = next(iter(kinds), "sign")
    if channel == "motor":
        if kind == "speed":
            return "viscous_friction" if tokens == ["w"] else "stribeck"
        return {
            "sign": "coulomb_friction",
            "bias": "direction_asymmetry",
            "periodic": "position_periodic_friction",
            "position": "position_quadratic_friction",
            "load": "load_dependent_friction",
            "time": "thermal_drift",
        }.get(kind)
    if channel == "load":
        if kind == "load":
            return "compliance" if tokens == ["Ts"] else "nonlinear_stiffness"
        return {
            "periodic": "kinematic_error",
            "out_speed": "load_side_friction",
            "deflection_rate": "hysteresis",
        }.get(kind)
    return {"periodic": "kinematic_error", "load": "compliance"}.get(kind)


def _feature_columns(ctx: Context, load: bool) -> tuple[np.ndarray, list[str]]:
    r = ctx.model.mechanics.r
    features: list[Callable[[Signals, Residual], np.ndarray]] = [
        lambda s, res: s.theta_m,
        lambda s, res: s.omega_m,
        lambda s, res: res.torque_s,
        lambda s, res: s.t,
    ]
    names = list(FEATURES)
    if load:
        features += [
            lambda s, res: s.omega_l if s.omega_l is not None else np.zeros(s.n),
            lambda s, res: r * s.omega_m - (s.omega_l if s.omega_l is not None else 0.0),
        ]
        names += list(LOAD_FEATURES)
    return np.column_stack([ctx.raw(f) for f in features]), names


def _smooth_columns(ctx: Context, X: np.ndarray) -> np.ndarray:
    """Each column smoothed run by run with the workflow's smoother, as its regressors are."""
    parts = np.split(X, np.cumsum([s.n for s in ctx.signals])[:-1])
    return np.vstack(
        [np.column_stack([s.smooth(c) for c in p.T]) for s, p in zip(ctx.signals, parts, strict=True)]
    )


def run_sindy(case: Case, run: Run) -> Outcome | None:
    try:
        import pysindy as ps
    except ImportError:
        return None
    start = time.perf_counter()
    signals = [prepare(run, case.model.numerics.omega_stick_m)]
    ctx = Context(case.model, signals, residuals_of(case.model, signals, DT_S))
    load = signals[0].has_load
    X, names = _feature_columns(ctx, load)

    def sgn(x: np.ndarray) -> np.ndarray:
        return np.sign(x)

    def sign_library() -> Any:
        return ps.CustomLibrary(library_functions=[sgn], function_names=[lambda x: f"sgn({x})"])

    n = len(names)
    every = list(range(n))
    theta = [0] * n
    omega = [1] * n
    signed = [1, 2] + [4, 5] * load  # ω, T_s (and ω_l, deflection rate)
    signed = (signed + [signed[-1]] * n)[:n]
    library = ps.GeneralizedLibrary(
        [
            ps.PolynomialLibrary(degree=2),
            ps.FourierLibrary(n_frequencies=10),
            sign_library(),
            ps.PolynomialLibrary(degree=2, include_bias=False),
            ps.FourierLibrary(n_frequencies=10),
            sign_library(),
        ],
        tensor_array=[[0, 0, 0, 1, 0, 1], [0, 0, 0, 0, 1, 1]],
        inputs_per_library=[every, theta, signed, every, theta, omega],
        exclude_libraries=[3, 4, 5],
    )
    library.fit(X)
    terms = library.get_feature_names(names)
    theta_raw = library.transform(X)
    best: tuple[float, str | None, float] | None = None
    for channel, y in ctx.channels.items():
        columns = (
            np.asarray(theta_raw)
            if channel == "load_position"
            else _smooth_columns(ctx, np.asarray(theta_raw))
        )
        # Unit-RMS columns and residual: a coefficient is a term's share of the residual's RMS, so the
        # threshold drops terms worth less than 5 % of it; the ridge tames the library's collinearity.
        scale = np.sqrt(np.mean(columns**2, axis=0))
        keep = scale > 0
        Z = columns[:, keep] / scale[keep]
        train, test = ctx.folds % 2 == 0, ctx.folds % 2 == 1
        y_scale = float(np.sqrt(np.mean(y[train] ** 2))) or 1.0
        optimizer = ps.STLSQ(threshold=0.05, alpha=1e-3 * float(train.sum()), max_iter=50)
        optimizer.fit(Z[train], y[train] / y_scale)
        coef = np.asarray(optimizer.coef_).ravel() * y_scale
        fitted = Z @ coef
        shrink = float(
            np.sqrt(np.mean(y[test] ** 2)) / max(np.sqrt(np.mean((y[test] - fitted[test]) ** 2)), 1e-300)
        )
        groups: dict[str | None, float] = {}
        for term, c, column in zip(np.asarray(terms)[keep], coef, Z.T, strict=True):
            if c != 0.0:
                effect = term_effect(str(term), channel)
                groups[effect] = groups.get(effect, 0.0) + float(np.sum((c * column) ** 2))
        named = max(groups, key=lambda e: groups[e]) if groups else None
        if best is None or shrink > best[0]:
            best = (shrink, named, shrink)
    seconds = time.perf_counter() - start
    assert best is not None
    shrink, named, _ = best
    found = [named] if named is not None and shrink >= MIN_SHRINK else []
    return Outcome(found, None, shrink, seconds)


# --- the suite ---------------------------------------------------------------------------------------


def suite(strengths: list[float], seeds: list[int]) -> list[tuple[str, Case, int]]:
    cases = []
    for effect in HIDDEN:
        for strength in strengths:
            for seed in seeds:
                cases.append((f"{effect}@{strength:g}", hidden_case((effect,), strength), seed))
    for strength in strengths:
        for seed in seeds:
            cases += [(name, case, seed) for name, case in issue_classes(strength)]
    for compliant in (False, True):
        for seed in seeds + [s + 100 for s in seeds]:
            cases.append(
                ("null" + ("-compliant" if compliant else ""), hidden_case((), compliant=compliant), seed)
            )
    return cases


def independent_suite(strengths: list[float], seeds: list[int]) -> list[tuple[str, Case, int]]:
    cases = []
    for effects in [(e,) for e in INDEPENDENT_EFFECTS] + [PAIR]:
        for strength in strengths:
            for seed in seeds:
                cases.append((f"{'+'.join(effects)}@{strength:g}", hidden_case(effects, strength), seed))
    for strength in strengths:
        for seed in seeds:
            cases += [(name, case, seed) for name, case in issue_classes(strength)]
    for compliant in (False, True):
        for seed in seeds + [s + 100 for s in seeds]:
            cases.append(
                ("null" + ("-compliant" if compliant else ""), hidden_case((), compliant=compliant), seed)
            )
    return cases


def record_independent(case: Case, duration_s: float, seed: int) -> Run:
    setpoint, load = lab_profile(duration_s)
    return IndependentRig(case.truth, seed=seed).record(setpoint, load, with_load=case.load_sensor)


def _rates(rows: list[Row], pick: Callable[[Row], Outcome | None]) -> dict[str, float]:
    """Totals over rows, for the outcomes `pick` takes (the workflow's or SINDy's)."""
    pairs = [(r, o) for r in rows if (o := pick(r)) is not None]
    effects = [(r, o) for r, o in pairs if r.hidden]
    nulls = [o for r, o in pairs if not r.hidden]
    hits = [(r, o) for r, o in effects if set(o.named) == r.hidden and len(o.named) == len(r.hidden)]
    gaps = [o.shrink_gap for _, o in hits if o.shrink_gap is not None]
    removed = [r.removed() for r, o in hits if o is r.ours]
    silent = [
        o for r, o in effects if o is r.ours and not o.named and o.initial_gap >= 2 * r.floor
    ]  # a gap over twice the floor and nothing named
    return {
        "hit_rate": len(hits) / max(len(effects), 1),
        "most_removed": sum(x >= MOST for x in removed) / max(len(effects), 1) if removed else math.nan,
        "wrong_names_per_case": sum(sum(n not in r.hidden for n in o.named) for r, o in effects)
        / max(len(effects), 1),
        "false_alarm_rate": sum(bool(o.named) for o in nulls) / max(len(nulls), 1),
        "median_shrink_residual": statistics.median(o.shrink_residual for _, o in hits)
        if hits
        else float("nan"),
        "median_shrink_gap": statistics.median(gaps) if gaps else float("nan"),
        "median_removed": statistics.median(removed) if removed else float("nan"),
        "silent": len(silent),
        "median_seconds": statistics.median(o.seconds for _, o in pairs),
    }


def _times(x: float) -> str:
    return "—" if np.isnan(x) else f"{x:.1f}×"


def _floors(rows: list[Row]) -> None:
    """Each row's null floor: the median initial gap of its generator's null cases of its rigidity."""
    for row in rows:
        nulls = [
            r.ours.initial_gap
            for r in rows
            if not r.hidden and r.generator == row.generator and r.compliant == row.compliant
        ]
        row.floor = statistics.median(nulls) if nulls else math.nan


def _per_effect(rows: list[Row], have_sindy: bool) -> None:
    print(
        "| generator | effect | ours | SINDy | ours: gap shrink | ours: excess removed |"
        " ours: residual shrink | SINDy: residual shrink |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for generator in dict.fromkeys(r.generator for r in rows):
        mine = [r for r in rows if r.generator == generator]
        for effect in dict.fromkeys([*(r.label or r.effect for r in mine if r.hidden), "null"]):
            group = [r for r in mine if (r.label or r.effect) == effect]
            if effect == "null":
                ours = f"{sum(not r.ours.named for r in group)}/{len(group)} clean"
                sindy = f"{sum(not r.sindy.named for r in group if r.sindy)}/{len(group)} clean"
            else:
                ours = f"{sum(set(r.ours.named) == r.hidden for r in group)}/{len(group)}"
                sindy = f"{sum(set(r.sindy.named) == r.hidden for r in group if r.sindy)}/{len(group)}"
            gap = statistics.median(r.ours.shrink_gap or 1.0 for r in group)
            removed = [r.removed() for r in group if r.hidden and not math.isnan(r.removed())]
            rem = f"{100 * statistics.median(removed):.0f} %" if removed else "—"
            res = statistics.median(r.ours.shrink_residual for r in group)
            sres = (
                statistics.median(r.sindy.shrink_residual for r in group if r.sindy)
                if have_sindy
                else float("nan")
            )
            print(
                f"| {generator} | {effect} | {ours} | {sindy if have_sindy else '-'} | {gap:.1f}× | {rem} |"
                f" {res:.1f}× | {sres:.1f}× |"
            )


SLOW = ("temperature_dependence", "thermal_drift", "wear_drift")


def _slow_strength(result: GapsResult, effect: str) -> tuple[float | None, str]:
    """The fitted strength of a slow effect and its parameter's name (None: not in the final model)."""
    m = result.model
    if effect == "temperature_dependence":
        return (m.thermal.beta_T if m.thermal is not None else None), "beta_T"
    if effect == "wear_drift":
        return (m.wear_drift.k_wear if m.wear_drift is not None else None), "k_wear"
    return (m.thermal_drift.d_th if m.thermal_drift is not None else None), "d_th"


def slow_suite(strengths: list[float], seeds: list[int], duration_s: float) -> None:
    """Section 5: each slow case at each strength and seed (nulls at strength 1 only: the carried null's
    law at the others too), a line per case and the totals."""
    truth = {"temperature_dependence": BETA_T, "wear_drift": K_WEAR, "thermal_drift": THERMAL_DRIFT["d_th"]}
    print(f"\n## Slow friction factors: 3 records × {duration_s:g} s per case, independent generator\n")
    print("| case | strength | seed | hidden | named | gap before → after [rad] | fitted / truth | time |")
    print("|---|---|---|---|---|---|---|---|")
    hits = cases = alarms = nulls = 0
    errors: list[float] = []
    for name in SLOW_CASES:
        for strength in strengths if name not in ("temperature_flat",) else [1.0]:
            for seed in seeds:
                case = slow_case(name, duration_s, strength, seed)
                start = time.perf_counter()
                result = find_gaps(case.runs, case.model)
                seconds = time.perf_counter() - start
                named = [step.effect for step in result.steps]
                ratio = "—"
                if case.hidden:
                    (effect,) = case.hidden
                    cases += 1
                    hit = [e for e in named if e in SLOW] == [effect]
                    hits += hit
                    value, parameter = _slow_strength(result, effect)
                    if hit and value is not None:
                        ratio = f"{parameter} {value / (strength * truth[effect]):.3f}"
                        errors.append(abs(value / (strength * truth[effect]) - 1))
                else:
                    nulls += 1
                    alarms += bool(named)
                print(
                    f"| {name} | {strength:g} | {seed} | {', '.join(case.hidden) or 'null'} |"
                    f" {', '.join(named) or '-'} | {result.initial_gap:.3g} → {result.final_gap:.3g} |"
                    f" {ratio} | {seconds:.1f} s |",
                    flush=True,
                )
    worst = f"{100 * max(errors):.1f} %" if errors else "—"
    # One record alone (the one warming from 5 °C): the three clocks rise together and cannot be told
    # apart; the measured temperature is named by default, right for the first, wrong for the second.
    for name in ("temperature", "time"):
        case = slow_case(name, duration_s)
        start = time.perf_counter()
        result = find_gaps(case.runs[1:2], case.model)
        seconds = time.perf_counter() - start
        names = ", ".join(step.effect for step in result.steps) or "-"
        print(
            f"| {name}, one run | 1 | 1 | {case.hidden[0]} | {names} |"
            f" {result.initial_gap:.3g} → {result.final_gap:.3g} | (not told apart) | {seconds:.1f} s |",
            flush=True,
        )
    print(
        f"\nslow factors: hits {hits}/{cases}, false alarms on nulls {alarms}/{nulls},"
        f" worst strength error of the hits {worst}"
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=16.0, help="probe length per suite case [s]")
    parser.add_argument("--strengths", type=float, nargs="+", default=[0.3, 0.6, 1.0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--independent-duration", type=float, default=16.0, help="lab profile length [s]")
    parser.add_argument("--independent-strengths", type=float, nargs="+", default=[0.5, 1.0])
    parser.add_argument("--independent-seeds", type=int, nargs="+", default=[1])
    parser.add_argument(
        "--generators",
        nargs="+",
        default=["sim", "independent", "slow"],
        choices=["sim", "independent", "slow"],
    )
    parser.add_argument("--slow-strengths", type=float, nargs="+", default=[0.5, 1.0])
    # One seed: it draws only the current and temperature noise, which the workflow does not read or
    # averages out (seeds 1 and 11 gave the same figures to three digits).
    parser.add_argument("--slow-seeds", type=int, nargs="+", default=[1])
    parser.add_argument("--slow-duration", type=float, default=6.0, help="length of each slow record [s]")
    parser.add_argument(
        "--timing-duration", type=float, default=60.0, help="data length of the timing cases [s]"
    )
    parser.add_argument("--quick", action="store_true", help="strength 1, one seed, one timing case")
    args = parser.parse_args()
    if args.quick:
        args.strengths, args.seeds = [1.0], [1]
        args.independent_strengths, args.independent_seeds = [1.0], [1]
        args.slow_strengths, args.slow_seeds = [1.0], [1]
    if "slow" in args.generators:
        slow_suite(args.slow_strengths, args.slow_seeds, args.slow_duration)
        if set(args.generators) == {"slow"}:
            return 0

    try:
        import pysindy  # noqa: F401

        have_sindy = True
    except ImportError:
        have_sindy = False
        print(
            "pysindy is not installed: the generic baseline is skipped (pip install pysindy).",
            file=sys.stderr,
        )

    plan: list[tuple[str, str, Case, int, Callable[[Case, int], Run]]] = []
    if "sim" in args.generators:
        plan += [
            (
                "sim rig",
                name,
                case,
                seed,
                lambda c, s: record_probe(c.truth, args.duration, seed=s, load_sensor=c.load_sensor),
            )
            for name, case, seed in suite(args.strengths, args.seeds)
        ]
    if "independent" in args.generators:
        plan += [
            (
                "independent",
                name,
                case,
                seed,
                lambda c, s: record_independent(c, args.independent_duration, s),
            )
            for name, case, seed in independent_suite(args.independent_strengths, args.independent_seeds)
        ]
    rows: list[Row] = []
    for generator, name, case, seed, record in plan:
        run = record(case, seed)
        effect = "+".join(case.hidden) if case.hidden else "null"
        row = Row(name, effect, run_ours(case, run), run_sindy(case, run) if have_sindy else None)
        row.generator, row.compliant = generator, not case.model.rigid
        row.label = name.rsplit("@", 1)[0] if "(" in name else ""
        rows.append(row)
        sindy = f"  sindy {row.sindy.named or '-'}" if row.sindy else ""
        print(
            f"{generator:11s} {name:42s} seed {seed:3d}  ours {row.ours.named or '-'}"
            f" gap {row.ours.initial_gap:.3g} → {row.ours.final_gap:.3g} ({row.ours.seconds:.1f} s){sindy}",
            flush=True,
        )
        if not row.ours.named and case.hidden:
            print(f"    verdict: {row.ours.verdict}", flush=True)
    _floors(rows)

    setup = (
        f"sim rig: strengths {args.strengths}, seeds {args.seeds}, {args.duration:g} s; independent:"
        f" strengths {args.independent_strengths}, seeds {args.independent_seeds},"
        f" {args.independent_duration:g} s"
    )
    print(f"\n## Per effect: hits / cases ({setup})\n")
    _per_effect(rows, have_sindy)

    print("\n## Null floors (median initial gap of the null cases)\n")
    for generator in dict.fromkeys(r.generator for r in rows):
        for compliant in (False, True):
            floor = [r.floor for r in rows if r.generator == generator and r.compliant == compliant]
            if floor:
                print(f"- {generator}, {'compliant' if compliant else 'rigid'}: {floor[0]:.3g} rad")

    print(
        f"\n## Totals (targets: every effect named, most (≥ {100 * MOST:.0f} %) of its excess gap removed,"
        " no false alarms, no large gap left unsaid)\n"
    )
    print(
        "| generator | method | hit rate | most excess removed | wrong names / case | false alarms (null) |"
        " gap > 2× floor, nothing named | shrink (gap / residual) | time / case |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for generator in dict.fromkeys(r.generator for r in rows):
        mine = [r for r in rows if r.generator == generator]
        methods: list[tuple[str, Callable[[Row], Outcome | None]]] = [("gap workflow", lambda r: r.ours)]
        if have_sindy:
            methods.append(("SINDy (generic)", lambda r: r.sindy))
        for label, pick in methods:
            t = _rates(mine, pick)
            most = "—" if math.isnan(t["most_removed"]) else f"{100 * t['most_removed']:.0f} %"
            silent = str(t["silent"]) if label == "gap workflow" else "—"
            print(
                f"| {generator} | {label} | {100 * t['hit_rate']:.0f} % | {most} |"
                f" {t['wrong_names_per_case']:.2f} | {100 * t['false_alarm_rate']:.0f} % | {silent} |"
                f" {_times(t['median_shrink_gap'])} / {_times(t['median_shrink_residual'])} |"
                f" {t['median_seconds']:.1f} s |"
            )
    if not have_sindy:
        print("| | SINDy (generic) | skipped: pysindy not installed | | | | | | |")

    print(f"\n## Time per case on {args.timing_duration:g} s of 1 kHz data (target < 60 s)\n")
    print("| case | samples | named | time |")
    print("|---|---|---|---|")
    timing = ["stribeck", "hysteresis", "null"] if not args.quick else ["stribeck"]
    for name in timing:
        case = hidden_case(() if name == "null" else (name,))
        run = record_probe(case.truth, args.timing_duration, seed=1, load_sensor=case.load_sensor)
        out = run_ours(case, run)
        print(f"| {name} | {len(run)} | {out.named or '-'} | {out.seconds:.1f} s |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
