"""Gap-workflow benchmark: hit rate, false alarms, gap shrinkage and time, beside a generic SINDy baseline.

Prints tables, asserts nothing. What it measures:

1. A suite of cases from `model.gaps.synthetic`: every vocabulary effect the simulator produces, hidden at
   a few strengths (a fraction of its nominal size) and rig noise seeds, plus null cases (the model is
   the truth, rigid and compliant). Data: the closed-loop probe on the simulated rig, `--duration` s.
2. The gap workflow (`model.gaps.find_gaps`) on each case: a hit is exactly the hidden effect named; a
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
"""

from __future__ import annotations

import argparse
import re
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hdrig_testing.hidden_effects import HIDDEN, Case, hidden_case, record_probe
from model.gaps import find_gaps
from model.gaps.effects import Context
from model.gaps.residual import Residual
from model.gaps.signals import Signals, prepare
from model.gaps.workflow import GapsResult, residuals_of
from model.run import Run

DT_S = 1e-4
MIN_SHRINK = 1.25


@dataclass
class Outcome:
    named: list[str]
    shrink_gap: float | None  # shooting gap before/after (workflow only)
    shrink_residual: float  # held-out one-step residual RMS before/after
    seconds: float


@dataclass
class Row:
    case: str
    effect: str  # hidden effect, or "null"
    ours: Outcome
    sindy: Outcome | None = None
    extra: dict[str, Any] = field(default_factory=dict)


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
    for compliant in (False, True):
        for seed in seeds + [s + 100 for s in seeds]:
            cases.append(
                ("null" + ("-compliant" if compliant else ""), hidden_case((), compliant=compliant), seed)
            )
    return cases


def _rates(pairs: list[tuple[str, Outcome]]) -> dict[str, float]:
    """Totals over (hidden effect or "null", outcome) pairs."""
    effects = [(e, o) for e, o in pairs if e != "null"]
    nulls = [o for e, o in pairs if e == "null"]
    hits = [o for e, o in effects if o.named == [e]]
    gaps = [o.shrink_gap for o in hits if o.shrink_gap is not None]
    return {
        "hit_rate": len(hits) / max(len(effects), 1),
        "wrong_names_per_case": sum(sum(n != e for n in o.named) for e, o in effects) / max(len(effects), 1),
        "false_alarm_rate": sum(bool(o.named) for o in nulls) / max(len(nulls), 1),
        "median_shrink_residual": statistics.median(o.shrink_residual for o in hits)
        if hits
        else float("nan"),
        "median_shrink_gap": statistics.median(gaps) if gaps else float("nan"),
        "median_seconds": statistics.median(o.seconds for _, o in pairs),
    }


def _times(x: float) -> str:
    return "—" if np.isnan(x) else f"{x:.1f}×"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=16.0, help="probe length per suite case [s]")
    parser.add_argument("--strengths", type=float, nargs="+", default=[0.3, 0.6, 1.0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2])
    parser.add_argument(
        "--timing-duration", type=float, default=60.0, help="data length of the timing cases [s]"
    )
    parser.add_argument("--quick", action="store_true", help="strength 1, one seed, one timing case")
    args = parser.parse_args()
    if args.quick:
        args.strengths, args.seeds = [1.0], [1]

    try:
        import pysindy  # noqa: F401

        have_sindy = True
    except ImportError:
        have_sindy = False
        print(
            "pysindy is not installed: the generic baseline is skipped (pip install pysindy).",
            file=sys.stderr,
        )

    rows: list[Row] = []
    for name, case, seed in suite(args.strengths, args.seeds):
        run = record_probe(case.truth, args.duration, seed=seed, load_sensor=case.load_sensor)
        effect = case.hidden[0] if case.hidden else "null"
        row = Row(name, effect, run_ours(case, run), run_sindy(case, run) if have_sindy else None)
        rows.append(row)
        sindy = f"  sindy {row.sindy.named or '-'}" if row.sindy else ""
        print(
            f"{name:34s} seed {seed:3d}  ours {row.ours.named or '-'} ({row.ours.seconds:.1f} s){sindy}",
            flush=True,
        )

    setup = f"strengths {args.strengths}, seeds {args.seeds}, {args.duration:g} s"
    print(f"\n## Per effect: hits / cases ({setup})\n")
    print("| effect | ours | SINDy | ours: gap shrink | ours: residual shrink | SINDy: residual shrink |")
    print("|---|---|---|---|---|---|")
    for effect in [*HIDDEN, "null"]:
        group = [r for r in rows if r.effect == effect]
        if effect == "null":
            ours = f"{sum(not r.ours.named for r in group)}/{len(group)} clean"
            sindy = (
                f"{sum(not r.sindy.named for r in group if r.sindy)}/{len(group)} clean"
                if have_sindy
                else "-"
            )
        else:
            ours = f"{sum(r.ours.named == [effect] for r in group)}/{len(group)}"
            sindy = (
                f"{sum(r.sindy.named == [effect] for r in group if r.sindy)}/{len(group)}"
                if have_sindy
                else "-"
            )
        gap = statistics.median(r.ours.shrink_gap or 1.0 for r in group)
        res = statistics.median(r.ours.shrink_residual for r in group)
        sres = (
            statistics.median(r.sindy.shrink_residual for r in group if r.sindy)
            if have_sindy
            else float("nan")
        )
        print(f"| {effect} | {ours} | {sindy} | {gap:.1f}× | {res:.1f}× | {sres:.1f}× |")

    print("\n## Totals (shrink: median over hits, gap / held-out residual)\n")
    print("| method | hit rate | wrong names / case | false alarms (null) | shrink | time / case |")
    print("|---|---|---|---|---|---|")
    table = [("gap workflow", _rates([(r.effect, r.ours) for r in rows]))]
    if have_sindy:
        table.append(("SINDy (generic)", _rates([(r.effect, r.sindy) for r in rows if r.sindy is not None])))
    for label, t in table:
        print(
            f"| {label} | {100 * t['hit_rate']:.0f} % | {t['wrong_names_per_case']:.2f} |"
            f" {100 * t['false_alarm_rate']:.0f} % | {_times(t['median_shrink_gap'])} /"
            f" {_times(t['median_shrink_residual'])} | {t['median_seconds']:.1f} s |"
        )
    if not have_sindy:
        print("| SINDy (generic) | skipped: pysindy not installed | | | | |")

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
