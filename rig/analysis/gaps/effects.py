"""The vocabulary effects as candidates: each one's signature in the residual, scored on held-out data.

A screen regresses a residual channel on the effect's signature regressor(s) — smoothed like the
residual — with cross-validation over interleaved half-second blocks, so a score is the fraction of the
channel's variance the effect explains on data it was not fitted on. The regression coefficients give
the starting values of the section that adds the effect; the simulator fit then refines them.

Sign convention: the motor channel is −ΔF (ΔF = friction the model lacks), so a coefficient β on a
regressor φ means the model lacks −β·φ of friction.
"""

from __future__ import annotations

import functools
import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from model.params import N_FOURIER, HarmonicDriveModel, load_model
from model.registry import OUT, SECTION_OWNERS, owned_by, parameter
from rig.analysis.fit.parameters import get_values
from rig.analysis.gaps.locate import CHANNEL_UNITS
from rig.analysis.gaps.residual import Residual
from rig.analysis.gaps.signals import Signals

FOLDS = 5
FOLD_BLOCK_S = 0.5
MIN_SCORE = 0.02
"""A candidate whose signature explains less than this share of its channel on held-out data is not tried."""


def merge_sections(model: HarmonicDriveModel, **sections: Any) -> HarmonicDriveModel:
    """The model with sections merged (a dict into an existing section), replaced, or removed (None)."""
    data = model.to_dict()
    for key, value in sections.items():
        if value is None:
            data.pop(key, None)
        elif isinstance(value, dict) and isinstance(data.get(key), dict):
            data[key] = {**data[key], **value}
        else:
            data[key] = value
    return HarmonicDriveModel.model_validate(data)


@dataclass
class Candidate:
    """An effect that may explain the residual, with what adding it means."""

    effect: str
    channel: str  # motor, load or load_position
    score: float  # held-out share of the channel's variance explained
    evidence: str  # one line: where the residual is and why this effect
    sections: dict[str, Any]  # merged into the model to add the effect, at the regression's values
    fit: list[str]  # parameters the simulator fit refines: the effect's own, then those it interacts with
    own: list[str]  # the effect's own parameters (every new one): they must come out determined
    ties: dict[str, str] = field(default_factory=dict)  # parameter ← parameter it follows

    def __post_init__(self) -> None:
        # The names are the registry's, and an effect's own parameters are those the registry gives it
        # (the friction effects that are no section of their own share the motor friction's).
        owner = self.effect if self.effect in SECTION_OWNERS.values() else "motor_friction"
        for name in (*self.fit, *self.ties, *self.ties.values()):
            parameter(name)
        strangers = [name for name in self.own if parameter(name).owner != owner]
        if strangers:
            raise ValueError(f"{self.effect}: the registry gives it no parameter {', '.join(strangers)}")


def cv_regression(y: np.ndarray, X: np.ndarray, folds: np.ndarray) -> tuple[float, np.ndarray]:
    """Held-out share of Σy² explained by least squares on the columns of X, and the full-data fit."""
    X = X.reshape(len(y), -1)
    norms = np.linalg.norm(X, axis=0)
    if not np.all(norms > 0) or not np.any(y):
        return 0.0, np.zeros(X.shape[1])
    Xs = X / norms
    sse = 0.0
    for f in range(FOLDS):
        train, test = folds != f, folds == f
        beta = np.linalg.lstsq(Xs[train], y[train], rcond=None)[0]
        sse += float(np.sum((y[test] - Xs[test] @ beta) ** 2))
    beta = np.linalg.lstsq(Xs, y, rcond=None)[0] / norms
    return 1.0 - sse / float(np.sum(y**2)), beta


Feature = Callable[[Signals, Residual], np.ndarray]


class Context:
    """The residual channels of every run side by side, and the means to build smoothed regressors."""

    def __init__(self, model: HarmonicDriveModel, signals: list[Signals], residuals: list[Residual]) -> None:
        self.model = model
        self.signals = signals
        self.residuals = residuals
        self.channels: dict[str, np.ndarray] = {"motor": np.concatenate([r.motor for r in residuals])}
        for name in ("load", "load_position"):
            parts = [getattr(r, name) for r in residuals]
            if all(p is not None for p in parts):
                self.channels[name] = np.concatenate(parts)
        self.folds = np.concatenate([(s.t // FOLD_BLOCK_S).astype(np.int64) % FOLDS for s in signals])
        self.duration_s = max(float(s.t[-1]) for s in signals)
        self._level: tuple[np.ndarray, float] | None = None
        self.slow: dict[str, float] | None = None  # `slow_scores`, computed once

    def smooth(self, values: np.ndarray) -> np.ndarray:
        """A column of every run side by side, smoothed run by run like the residual."""
        parts = np.split(values, np.cumsum([s.n for s in self.signals])[:-1])
        return np.concatenate([s.smooth(p) for s, p in zip(self.signals, parts, strict=True)])

    def smoothed(self, feature: Feature) -> np.ndarray:
        return np.concatenate(
            [s.smooth(feature(s, r)) for s, r in zip(self.signals, self.residuals, strict=True)]
        )

    def raw(self, feature: Feature) -> np.ndarray:
        return np.concatenate([feature(s, r) for s, r in zip(self.signals, self.residuals, strict=True)])

    def regressors(self, channel: str, *features: Feature) -> np.ndarray:
        """Columns for a channel: raw for the output position (a function of θ_m), smoothed otherwise."""
        build = self.raw if channel == "load_position" else self.smoothed
        return np.column_stack([build(f) for f in features])

    def level_regression(self, *features: Feature) -> tuple[float, np.ndarray, float]:
        """For an effect that interacts with the friction level: its held-out gain over refitting the
        level alone, its coefficients and the level's, from one joint regression on the motor channel."""
        y = self.channels["motor"]
        if self._level is None:
            column = self.regressors("motor", _speed_factor(self.model))
            self._level = (column, cv_regression(y, column, self.folds)[0])
        column, alone = self._level
        joint, beta = cv_regression(
            y, np.column_stack([self.regressors("motor", *features), column]), self.folds
        )
        return joint - alone, beta[:-1], float(beta[-1])

    def beyond(self, own: Feature, rivals: list[Feature]) -> float:
        """Held-out share of the motor channel `own` explains beyond `rivals` and the friction level: one
        regression with all of them, less the same without `own` (nested models, both held out)."""
        y = self.channels["motor"]
        level = self.regressors("motor", _speed_factor(self.model))
        others = np.column_stack([self.regressors("motor", *rivals), level]) if rivals else level
        joint = cv_regression(y, np.column_stack([self.regressors("motor", own), others]), self.folds)[0]
        return joint - cv_regression(y, others, self.folds)[0]

    def with_level(self, sections: dict[str, Any], beta_level: float) -> dict[str, Any]:
        """Sections plus the friction level moved by the joint regression."""
        if not self.karnopp:
            return sections
        level = max(self.value(self.level) - beta_level, 1e-6)
        friction = {**sections.get("motor_friction", {}), self.level: level}
        return {**sections, "motor_friction": friction}

    @property
    def friction_law(self) -> str:
        return self.model.motor_friction.motor_law

    @property
    def karnopp(self) -> bool:
        return self.friction_law in ("article", "coulomb_viscous", "stribeck")

    @property
    def level(self) -> str:
        """The parameter holding the constant friction level under this law."""
        return "s3" if self.friction_law == "article" else "f_cm"

    def value(self, name: str) -> float:
        return get_values(self.model, [name])[name]


STRENGTHS: dict[str, tuple[str, ...]] = {
    "stribeck": ("f_st",),
    "direction_asymmetry": ("f_dir",),
    "load_dependent_friction": ("c_Ts",),
    "thermal_drift": ("d_th",),
    "wear_drift": ("k_wear",),
    "thermal": ("beta_T",),
    "load_friction": ("f_cl", "f_sl", "b_l"),
}
"""The fields that make a section act: with all of them at zero the section is there but does nothing."""


def carried(model: HarmonicDriveModel, section: str) -> bool:
    """Whether the model carries the effect of `section` at work: present, and (for a section with
    STRENGTHS) one of them nonzero. A section carried at zero is no effect yet: its screen makes it a
    candidate like an absent one (a model file often lists load friction with f_cl = f_sl = b_l = 0).
    The load friction counts as carried under any law but Coulomb-viscous, whose fields the candidate
    sets."""
    value = getattr(model, section)
    if value is None:
        return False
    if section == "load_friction" and value.load_law != "coulomb_viscous":
        return True
    return any(getattr(value, name) for name in STRENGTHS.get(section, ())) or section not in STRENGTHS


def direction(s: Signals, _: Residual) -> np.ndarray:
    """sgn ω_m while moving, 0 at rest in the data."""
    return np.where(s.stuck, 0.0, np.sign(s.omega_m))


def _speed_factor(model: HarmonicDriveModel) -> Feature:
    """How the level enters the moving friction: (1 + k_v·(|ω| − v_c)) under the article law, else 1."""
    mf = model.motor_friction

    def feature(s: Signals, r: Residual) -> np.ndarray:
        if mf.motor_law != "article":
            return direction(s, r)
        return direction(s, r) * (1 + (mf.k_v or 0.0) * (np.abs(s.omega_m) - (mf.v_c or 0.0)))

    return feature


def _wave(cycles: int, wave: Callable[[np.ndarray], np.ndarray], signed: bool) -> Feature:
    """cos or sin of `cycles` per motor turn; times sgn ω_m for a friction (`signed`)."""

    def feature(s: Signals, r: Residual) -> np.ndarray:
        values = wave(cycles * s.theta_m)
        return direction(s, r) * values if signed else values

    return feature


def _pct(x: float) -> str:
    return f"{100 * max(x, 0.0):.0f} %"


# --- motor-side friction -------------------------------------------------------------------------


def screen_coulomb(ctx: Context) -> Candidate | None:
    y = ctx.channels["motor"]
    score, beta = cv_regression(y, ctx.regressors("motor", _speed_factor(ctx.model)), ctx.folds)
    level = ctx.value(ctx.level)
    new = max(level - beta[0], 0.0)
    evidence = (
        f"residual torque steps with the direction of motion: sgn ω_m explains {_pct(score)} of it"
        f" (held out); friction level {level:.3g} → {new:.3g} N·m"
    )
    return Candidate(
        "coulomb_friction",
        "motor",
        score,
        evidence,
        {"motor_friction": {ctx.level: new}},
        [ctx.level],
        [ctx.level],
    )


def screen_viscous(ctx: Context) -> Candidate | None:
    score, beta, level = ctx.level_regression(lambda s, r: np.where(s.stuck, 0.0, s.omega_m))
    b_m = ctx.model.motor_friction.b_m - beta[0]
    if b_m <= 0:
        return None
    top = max(float(np.max(np.abs(s.omega_m))) for s in ctx.signals)
    evidence = (
        f"residual torque grows with speed up to {top:.0f} rad/s: ω_m explains {_pct(score)} more of it than"
        f" the friction level alone (held out);"
        f" b_m ≈ {b_m:.2e} N·m·s/rad"
    )
    names = ["b_m", ctx.level] if ctx.karnopp else ["b_m"]
    sections = ctx.with_level({"motor_friction": {"b_m": b_m}}, level)
    return Candidate("viscous_friction", "motor", score, evidence, sections, names, ["b_m"])


def screen_stribeck(ctx: Context) -> Candidate | None:
    if not ctx.karnopp or carried(ctx.model, "stribeck"):
        return None
    best: tuple[float, float, float, float] | None = None
    for omega_s in np.geomspace(0.1, 10.0, 15):

        def decay(s: Signals, r: Residual, w: float = float(omega_s)) -> np.ndarray:
            return direction(s, r) * np.exp(-((s.omega_m / w) ** 2))

        score, beta, level = ctx.level_regression(decay)
        if beta[0] < 0 and (best is None or score > best[0]):
            best = (score, float(omega_s), -float(beta[0]), level)
    if best is None:
        return None
    score, omega_s, f_st, level = best
    evidence = (
        f"residual torque decays with |ω_m| over ~{omega_s:.2g} rad/s: exp(−(ω/ω_s)²)·sgn ω explains"
        f" {_pct(score)} of it (held out); {f_st:.3g} N·m extra near zero speed"
    )
    sections = ctx.with_level({"stribeck": {"f_st": f_st, "omega_st": omega_s}}, level)
    return Candidate(
        "stribeck",
        "motor",
        score,
        evidence,
        sections,
        [*owned_by("stribeck"), ctx.level],
        [*owned_by("stribeck")],
    )


def screen_static(ctx: Context) -> Candidate | None:
    """Stick phases longer in the data: at rest in the data while the model breaks away."""
    if not ctx.karnopp:
        return None
    y = ctx.channels["motor"]

    def breakaway(s: Signals, r: Residual) -> np.ndarray:
        return np.where(s.stuck, -r.inertia * r.predicted, 0.0)

    score, beta = cv_regression(y, ctx.regressors("motor", breakaway), ctx.folds)
    if beta[0] <= 0:
        return None
    ratios = []
    for s, r in zip(ctx.signals, ctx.residuals, strict=True):
        rows = r.rows[s.stuck]
        # ψ: everything but friction. Where the model breaks away, the friction it applies is its static
        # level, so |ψ| / |friction| > 1 says how much more the data held; where it holds, the ratio is 1.
        push = rows[:, OUT.TAU_M] - ctx.model.mechanics.r * (
            rows[:, OUT.TAU_EXT] if r.rigid else rows[:, OUT.T_S]
        )
        limit = np.abs(rows[:, OUT.F_M] + (ctx.model.mechanics.r * rows[:, OUT.F_L] if r.rigid else 0.0))
        ok = limit > 0
        ratios.append(np.abs(push[ok]) / limit[ok])
    ratio = np.concatenate(ratios)
    ratio = ratio[ratio > 1 + 1e-9]
    if ratio.size == 0:
        return None
    factor = max(float(np.quantile(ratio, 0.9)), 1.05)
    name = "static_factor" if ctx.friction_law == "article" else "f_sm"
    new = ctx.value(name) * factor
    evidence = (
        f"data stay at rest where the model breaks away ({ratio.size} samples): breakaway needs"
        f" ~{factor:.2f}× the model's static level; this explains {_pct(score)} of the residual"
    )
    return Candidate(
        "static_friction", "motor", score, evidence, {"motor_friction": {name: new}}, [name], [name]
    )


def screen_periodic(ctx: Context) -> Candidate | None:
    if ctx.friction_law != "article":
        return None
    y = ctx.channels["motor"]
    features = [_wave(n, wave, signed=True) for n in range(1, N_FOURIER + 1) for wave in (np.cos, np.sin)]
    X = ctx.regressors("motor", *features)
    score, beta = cv_regression(y, X, ctx.folds)
    total = float(np.sum(y**2))
    share = np.array(
        [float(np.sum((X[:, 2 * i : 2 * i + 2] @ beta[2 * i : 2 * i + 2]) ** 2)) for i in range(N_FOURIER)]
    )
    share = share / total if total > 0 else share
    order = [int(i) for i in np.argsort(share)[::-1] if share[i] > 0.01]  # ≥ 1 % of the channel
    if not order:
        return None
    mf = ctx.model.motor_friction
    a, b = mf.fourier_a(), mf.fourier_b()
    for i in order:
        a[i + 1] -= float(beta[2 * i])
        b[i] -= float(beta[2 * i + 1])
    fitted = [name for i in order[:3] for name in (f"a{i + 1}", f"b{i + 1}")]
    top = order[0] + 1
    evidence = (
        f"residual torque periodic in θ_m: harmonic {top} of one motor turn carries {_pct(share[top - 1])}"
        f" of its variance (all harmonics: {_pct(score)} held out)"
    )
    return Candidate(
        "position_periodic_friction",
        "motor",
        score,
        evidence,
        {"motor_friction": {"a": a, "b": b}},
        fitted,
        fitted,
    )


def screen_quadratic(ctx: Context) -> Candidate | None:
    if ctx.friction_law != "article":
        return None
    speed = _speed_factor(ctx.model)
    span = max(float(np.max(np.abs(s.theta_m))) for s in ctx.signals) or 1.0
    score, beta, level = ctx.level_regression(
        lambda s, r: speed(s, r) * (s.theta_m / span) ** 2, lambda s, r: speed(s, r) * s.theta_m / span
    )
    s1, s2 = ctx.value("s1") - beta[0] / span**2, ctx.value("s2") - beta[1] / span
    lo = min(float(s.theta_m.min()) for s in ctx.signals)
    hi = max(float(s.theta_m.max()) for s in ctx.signals)
    evidence = (
        f"residual torque varies smoothly over the stroke θ_m ∈ [{lo:.0f}, {hi:.0f}] rad: θ_m and θ_m²"
        f" explain {_pct(score)} more of it than the friction level alone (held out)"
    )
    return Candidate(
        "position_quadratic_friction",
        "motor",
        score,
        evidence,
        ctx.with_level({"motor_friction": {"s1": s1, "s2": s2}}, level),
        ["s1", "s2", "s3"],
        ["s1", "s2"],
    )


def screen_direction(ctx: Context) -> Candidate | None:
    if not ctx.karnopp or carried(ctx.model, "direction_asymmetry"):
        return None
    y = ctx.channels["motor"]
    score, beta, level = ctx.level_regression(lambda s, r: (~s.stuck).astype(float))
    f_dir = -float(beta[0])
    s = np.concatenate([direction(sig, res) for sig, res in zip(ctx.signals, ctx.residuals, strict=True)])
    forward, backward = (
        float(np.mean(y[s > 0])) if np.any(s > 0) else 0.0,
        (float(np.mean(y[s < 0])) if np.any(s < 0) else 0.0),
    )
    evidence = (
        f"residual mean differs by direction: {forward:+.3g} N·m moving forward, {backward:+.3g} N·m backward"
        f" (a direction offset explains {_pct(score)}, held out)"
    )
    sections = ctx.with_level({"direction_asymmetry": {"f_dir": f_dir}}, level)
    return Candidate(
        "direction_asymmetry",
        "motor",
        score,
        evidence,
        sections,
        [*owned_by("direction_asymmetry"), ctx.level],
        [*owned_by("direction_asymmetry")],
    )


def screen_load_dependent(ctx: Context) -> Candidate | None:
    if not ctx.karnopp or carried(ctx.model, "load_dependent_friction"):
        return None
    score, beta, level = ctx.level_regression(lambda s, r: direction(s, r) * np.abs(r.torque_s))
    c_ts = -float(beta[0])
    if c_ts <= 0:
        return None
    top = max(float(np.max(np.abs(r.torque_s))) for r in ctx.residuals)
    evidence = (
        f"residual torque grows with the transmitted torque |T_s| (up to {top:.2g} N·m): |T_s|·sgn ω explains"
        f" {_pct(score)} more of it than the friction level alone (held out); c_Ts ≈ {c_ts:.2g}"
    )
    sections = ctx.with_level({"load_dependent_friction": {"c_Ts": c_ts}}, level)
    return Candidate(
        "load_dependent_friction",
        "motor",
        score,
        evidence,
        sections,
        [*owned_by("load_dependent_friction"), ctx.level],
        [*owned_by("load_dependent_friction")],
    )


# --- friction that drifts: with time, with travel, with the measured temperature ------------------------
# Three effects scale the whole motor friction by a slow factor: `thermal_drift` by the time since the
# run's start, `wear_drift` by the motor travel since then, `temperature_dependence` by the gear's
# measured temperature. Within one warm-up run all three rise together; runs at several temperatures and
# travels tell them apart. So each is scored by what it explains of the motor residual BEYOND the others
# the data offer (`slow_scores`, `Context.beyond`: one held-out regression with all of them and the
# friction level, less the same without it): the share only that factor explains. An effect the model
# carries is no rival.


def _slow(factor: Callable[[Signals], np.ndarray]) -> Feature:
    """sgn ω · |F_m| · factor: the model's motor friction scaled by a slow factor of the run."""

    def feature(s: Signals, r: Residual) -> np.ndarray:
        friction = np.where(s.stuck, 0.0, np.abs(r.rows[:, OUT.F_M]))
        return direction(s, r) * friction * factor(s)

    return feature


def _warming(tau_s: float) -> Feature:
    return _slow(lambda s: 1 - np.exp(-s.t / tau_s))


def _best_warming(ctx: Context) -> tuple[float, float, float, float] | None:
    """(held-out gain, τ, d_th, level coefficient) of the best warm-up time constant (d_th > −1)."""
    best: tuple[float, float, float, float] | None = None
    for tau in np.geomspace(ctx.duration_s / 30, 2 * ctx.duration_s, 12):
        score, beta, level = ctx.level_regression(_warming(float(tau)))
        if beta[0] < 1 and (best is None or score > best[0]):
            best = (score, float(tau), -float(beta[0]), level)
    return best


def _reference_c(ctx: Context) -> float:
    """The measured gear temperature's mean over every run [°C, to 0.1 °C]: the reference the fitted
    friction level then holds at."""
    values = [s.temp_gear for s in ctx.signals if s.temp_gear is not None]
    return round(float(np.mean(np.concatenate(values))), 1)


def _temperature_feature(t_ref_c: float) -> Feature:
    # exp(−beta_T·(T_g − T_ref)) ≈ 1 − beta_T·(T_g − T_ref): the lacking friction is −beta_T·this.
    def above(s: Signals) -> np.ndarray:
        return np.zeros(s.n) if s.temp_gear is None else s.temp_gear - t_ref_c

    return _slow(above)


_travel: Feature = _slow(lambda s: s.travel)


def _drift_features(ctx: Context) -> dict[str, Feature]:
    """The slow factors the data offer and the model does not carry yet, by effect."""
    if not ctx.karnopp:
        return {}
    out: dict[str, Feature] = {}
    if not carried(ctx.model, "thermal_drift"):
        best = _best_warming(ctx)
        if best is not None:
            out["thermal_drift"] = _warming(best[1])
    if not carried(ctx.model, "wear_drift"):
        out["wear_drift"] = _travel
    if not carried(ctx.model, "thermal") and all(s.temp_gear is not None for s in ctx.signals):
        out["temperature_dependence"] = _temperature_feature(_reference_c(ctx))
    return out


def slow_scores(ctx: Context) -> dict[str, float]:
    """Each slow factor's held-out share of the motor residual beyond all the others the data offer.

    When one of them explains something beyond the rest, the data tell them apart and each is scored
    by that. When none does (one run with a repeated profile travels in proportion to time, and its
    temperature rises with both), one keeps its own score (inf here, so the screen's own gain stands):
    the measured temperature when the runs recorded it (the measured cause, and one parameter against
    thermal_drift's two), else time, the plain explanation of a trend within a run; its evidence says
    that the data could not tell them apart."""
    if ctx.slow is None:
        features = _drift_features(ctx)
        ctx.slow = {
            name: ctx.beyond(f, [g for other, g in features.items() if other != name])
            for name, f in features.items()
        }
        default = next((n for n in ("temperature_dependence", "thermal_drift") if n in ctx.slow), None)
        if default is not None and all(v < MIN_SCORE for v in ctx.slow.values()):
            ctx.slow[default] = math.inf
    return ctx.slow


SLOW_EFFECTS = ("temperature_dependence", "thermal_drift", "wear_drift")
"""The effects scored by `slow_scores`: friction scaled by a slow factor of the run."""
CLOCKS = {
    "thermal_drift": "time",
    "wear_drift": "travel",
    "temperature_dependence": "the measured temperature",
}


def _untold(ctx: Context, effect: str) -> str:
    """The evidence's note when `effect` is named by default: the slow factors were not told apart."""
    if math.isfinite(slow_scores(ctx)[effect]) or len(slow_scores(ctx)) < 2:
        return ""
    clocks = [CLOCKS[n] for n in slow_scores(ctx)]
    return (
        f"; {', '.join(clocks[:-1])} and {clocks[-1]} rise together in these data and cannot be told apart"
        " (runs at several temperatures and travels can)"
    )


def screen_thermal(ctx: Context) -> Candidate | None:
    if not ctx.karnopp or carried(ctx.model, "thermal_drift"):
        return None
    best = _best_warming(ctx)
    if best is None:
        return None
    score, tau, d_th, level = best
    apart = math.isfinite(slow_scores(ctx)["thermal_drift"])
    score = min(score, slow_scores(ctx)["thermal_drift"])
    evidence = (
        f"residual torque trends over the run: friction × {1 + d_th:.2f} once warm, time constant"
        f" ~{tau:.2g} s ({_pct(score)} more explained than by the friction level"
        f"{' and the other slow factors' if apart else ''} alone, held out){_untold(ctx, 'thermal_drift')}"
    )
    sections = ctx.with_level({"thermal_drift": {"d_th": d_th, "tau_th": tau}}, level)
    names = [*owned_by("thermal_drift"), ctx.level]
    return Candidate("thermal_drift", "motor", score, evidence, sections, names, [*owned_by("thermal_drift")])


def screen_wear(ctx: Context) -> Candidate | None:
    if not ctx.karnopp or carried(ctx.model, "wear_drift"):
        return None
    gain, beta, level = ctx.level_regression(_travel)
    k_wear = -float(beta[0])
    if k_wear <= 0:
        return None
    score = min(gain, slow_scores(ctx)["wear_drift"])
    top = max(float(s.travel[-1]) for s in ctx.signals)
    evidence = (
        f"residual torque grows with the motor travel (up to {top:.3g} rad): friction × (1 + {k_wear:.2g}/rad"
        f" · travel) explains {_pct(score)} more of it than the friction level and the other slow factors"
        f" (time, and the measured temperature when recorded), held out"
    )
    sections = ctx.with_level({"wear_drift": {"k_wear": k_wear}}, level)
    names = [*owned_by("wear_drift"), ctx.level]
    return Candidate("wear_drift", "motor", score, evidence, sections, names, [*owned_by("wear_drift")])


@functools.cache
def _network() -> dict[str, float]:
    """The thermal network a `temperature_dependence` candidate carries: `seed-thermal`'s capacities and
    resistances. The gap workflow replays from the measured temperatures, so they do not enter its gap;
    identify them from warm-up and cool-down runs (the thermal stage)."""
    thermal = load_model("seed-thermal").thermal
    assert thermal is not None
    return {name: float(getattr(thermal, name)) for name in ("C_w", "C_g", "R_wg", "R_wa", "R_ga")}


def screen_temperature(ctx: Context) -> Candidate | None:
    """Friction that follows the run's measured gear temperature (a model without a thermal law)."""
    if "temperature_dependence" not in _drift_features(ctx):
        return None
    t_ref = _reference_c(ctx)
    gain, beta, level = ctx.level_regression(_temperature_feature(t_ref))
    beta_t = float(beta[0])
    score = min(gain, slow_scores(ctx)["temperature_dependence"])
    lo = min(float(s.temp_gear.min()) for s in ctx.signals if s.temp_gear is not None)
    hi = max(float(s.temp_gear.max()) for s in ctx.signals if s.temp_gear is not None)
    evidence = (
        f"residual torque follows the measured gear temperature ({lo:.1f}–{hi:.1f} °C): friction ×"
        f" exp(−{beta_t:.3g}/K·(T_g − {t_ref:g} °C)) explains {_pct(score)} more of it than the friction"
        f" level and the other slow factors (time, travel), held out{_untold(ctx, 'temperature_dependence')}"
    )
    thermal = {"T_amb": t_ref, "T_ref": t_ref, "beta_T": beta_t, **_network()}
    sections = ctx.with_level({"thermal": thermal}, level)
    return Candidate(
        "temperature_dependence", "motor", score, evidence, sections, ["beta_T", ctx.level], ["beta_T"]
    )


# --- the transmission and the output side (need the output angle) ------------------------------------


def screen_kinematic(ctx: Context) -> Candidate | None:
    ke = ctx.model.kinematic_error
    if ke is not None and ke.A > 0:
        return None
    channel = "load_position" if "load_position" in ctx.channels else "load"
    if channel not in ctx.channels:
        return None
    y = ctx.channels[channel]
    best: tuple[float, int, np.ndarray] | None = None
    for cycles in range(1, 101):
        X = ctx.regressors(channel, _wave(cycles, np.sin, signed=False), _wave(cycles, np.cos, signed=False))
        score, beta = cv_regression(y, X, ctx.folds)
        if best is None or score > best[0]:
            best = (score, cycles, beta)
    assert best is not None
    score, cycles, beta = best
    gain = 1.0 if channel == "load_position" else float(ctx.model.transmission.K_s or 1.0)
    amplitude, phase = float(math.hypot(beta[0], beta[1])) / gain, float(math.atan2(beta[1], beta[0]))
    where = "output-position residual" if channel == "load_position" else "output-torque residual"
    evidence = (
        f"{where} periodic in θ_m at k = {cycles} per motor turn: {_pct(score)} of its variance (held out),"
        f" amplitude {amplitude:.2g} rad at the output"
    )
    sections = {"kinematic_error": {"A": amplitude, "k": float(cycles), "phi": phase}}
    return Candidate("kinematic_error", channel, score, evidence, sections, ["A", "phi"], ["A", "phi"])


def screen_compliance(ctx: Context) -> Candidate | None:
    if not ctx.model.rigid or "load_position" not in ctx.channels:
        return None
    y = ctx.channels["load_position"]
    score, beta = cv_regression(y, ctx.regressors("load_position", lambda s, r: r.torque_s), ctx.folds)
    if beta[0] >= 0:
        return None
    stiffness = -1.0 / float(beta[0])
    evidence = (
        f"the output lags the motor in proportion to the transmitted torque: T_s explains {_pct(score)} of"
        f" the output-position residual (held out); K_s ≈ {stiffness:.3g} N·m/rad"
    )
    sections = {"transmission": {"K_s": stiffness, "D_s": 0.0}}
    return Candidate("compliance", "load_position", score, evidence, sections, ["K_s"], ["K_s"])


def _spring_torque(ctx: Context) -> Feature:
    stiffness = float(ctx.model.transmission.K_s or 0.0)

    def feature(s: Signals, r: Residual) -> np.ndarray:
        assert r.deflection is not None
        return stiffness * r.deflection

    return feature


def screen_nonlinear(ctx: Context) -> Candidate | None:
    if ctx.model.rigid or ctx.model.nonlinear_stiffness is not None or "load" not in ctx.channels:
        return None
    y = ctx.channels["load"]
    linear = _spring_torque(ctx)
    torque = np.abs(ctx.raw(linear))
    best: tuple[float, float, float] | None = None
    for knee in np.quantile(torque, np.linspace(0.2, 0.9, 8)):

        def beyond(s: Signals, r: Residual, knee: float = float(knee)) -> np.ndarray:
            t = linear(s, r)
            return np.sign(t) * np.maximum(np.abs(t) - knee, 0.0)

        score, beta = cv_regression(y, ctx.regressors("load", beyond), ctx.folds)
        if beta[0] > -1 and (best is None or score > best[0]):
            best = (score, float(knee), float(beta[0]))
    if best is None or best[1] <= 0:
        return None
    score, knee, slope = best
    k1 = float(ctx.model.transmission.K_s or 0.0)
    k2 = k1 * (1 + slope)
    top = float(torque.max())
    evidence = (
        f"output-torque residual grows beyond |T_s| ≈ {knee:.2g} N·m: stiffness {k1:.3g} → {k2:.3g} N·m/rad"
        f" explains {_pct(score)} of it (held out)"
    )
    sections = {
        "nonlinear_stiffness": {"K1": k1, "K2": k2, "K3": k2, "T1": knee, "T2": max(2 * top, 2 * knee)}
    }
    return Candidate("nonlinear_stiffness", "load", score, evidence, sections, ["K2", "T1"], ["K2", "T1"])


def screen_hysteresis(ctx: Context) -> Candidate | None:
    if ctx.model.rigid or ctx.model.hysteresis is not None or "load" not in ctx.channels:
        return None
    y = ctx.channels["load"]
    r_gear = ctx.model.mechanics.r

    def deflection_direction(s: Signals, _: Residual) -> np.ndarray:
        assert s.omega_l is not None
        return np.sign(r_gear * s.omega_m - s.omega_l)

    score, beta = cv_regression(y, ctx.regressors("load", deflection_direction), ctx.folds)
    if beta[0] <= 0:
        return None
    t_h = float(beta[0])
    k_s = float(ctx.model.transmission.K_s or 1.0)
    evidence = (
        f"transmitted torque depends on the direction of deflection: a ±{t_h:.2g} N·m loop"
        f" ({2 * t_h / k_s:.2g} rad wide) explains {_pct(score)} of the output-torque residual (held out)"
    )
    sections = {"hysteresis": {"T_h": t_h, "delta_h": 0.1 * t_h / k_s}}
    own = [*owned_by("hysteresis")]
    return Candidate("hysteresis", "load", score, evidence, sections, own, own)


def screen_load_side(ctx: Context) -> Candidate | None:
    if ctx.model.rigid or carried(ctx.model, "load_friction") or "load" not in ctx.channels:
        return None
    y = ctx.channels["load"]

    def load_direction(s: Signals, _: Residual) -> np.ndarray:
        assert s.omega_l is not None
        return np.sign(s.omega_l)

    def load_speed(s: Signals, _: Residual) -> np.ndarray:
        assert s.omega_l is not None
        return s.omega_l

    score, beta = cv_regression(y, ctx.regressors("load", load_direction, load_speed), ctx.folds)
    f_cl, b_l = -float(beta[0]), max(-float(beta[1]), 0.0)
    if f_cl <= 0:
        return None
    evidence = (
        f"the output needs {f_cl:.2g} N·m of friction opposing ω_l: sgn ω_l and ω_l explain {_pct(score)}"
        f" of the output-torque residual (held out)"
    )
    sections = {"load_friction": {"load_law": "coulomb_viscous", "f_cl": f_cl, "f_sl": f_cl, "b_l": b_l}}
    return Candidate(
        "load_side_friction",
        "load",
        score,
        evidence,
        sections,
        ["f_cl", "b_l"],
        ["f_cl", "b_l"],
        {"f_sl": "f_cl"},
    )


SCREENS: dict[str, Callable[[Context], Candidate | None]] = {
    "coulomb_friction": screen_coulomb,
    "viscous_friction": screen_viscous,
    "stribeck": screen_stribeck,
    "static_friction": screen_static,
    "position_periodic_friction": screen_periodic,
    "position_quadratic_friction": screen_quadratic,
    "direction_asymmetry": screen_direction,
    "load_dependent_friction": screen_load_dependent,
    "kinematic_error": screen_kinematic,
    "compliance": screen_compliance,
    "nonlinear_stiffness": screen_nonlinear,
    "hysteresis": screen_hysteresis,
    "load_side_friction": screen_load_side,
    "thermal_drift": screen_thermal,
    "wear_drift": screen_wear,
    "temperature_dependence": screen_temperature,
}
"""Every effect of the docs/MODEL.md vocabulary, by name, with its screen."""


def screen(ctx: Context, skip: set[str]) -> list[Candidate]:
    """Candidates that explain at least MIN_SCORE of their channel, best first."""
    found = [c for name, f in SCREENS.items() if name not in skip and (c := f(ctx)) is not None]
    return sorted((c for c in found if c.score >= MIN_SCORE), key=lambda c: -c.score)


# --- what is left when no effect is named --------------------------------------------------------

SPEED_BINS = (0.0, 0.3, 1.0, 3.0, 10.0, 30.0, 100.0, math.inf)
"""|ω_m| bins [rad/s] of the generic speed signature."""
SYSTEMATIC = 0.15
"""A residual whose best generic signature explains at least this share of its channel on held-out
blocks is systematic: something the model lacks, named or not (null cases of both data generators
stay below it; see docs/BENCHMARKS.md)."""


@dataclass(frozen=True)
class Signature:
    """The largest structure left in a residual: along which axis, how much of it, and where it peaks."""

    channel: str
    axis: str
    share: float  # held-out share of the channel's variance a binned function of the axis explains
    where: str  # the bin with the largest mean, and that mean

    def line(self) -> str:
        return (
            f"{_pct(self.share)} of the {self.channel} residual (held out) varies with {self.axis};"
            f" largest {self.where}"
        )


def _bins(values: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """The bin of each value among `edges` (the last bin takes what lies beyond)."""
    return np.clip(np.digitize(values, edges) - 1, 0, len(edges) - 2)


def signature(ctx: Context) -> Signature | None:
    """The generic signature that explains most of a residual channel on held-out blocks: binned
    functions of speed, motor angle, time and transmitted torque (each times sgn ω on the motor
    channel, as a friction), and of rest. Binned, not a vocabulary effect: it says where an unnamed
    residual lives."""
    speed = np.concatenate([s.omega_m for s in ctx.signals])
    stuck = np.concatenate([s.stuck for s in ctx.signals])
    sign = np.where(stuck, 0.0, np.sign(speed))
    angle = np.mod(np.concatenate([s.theta_m for s in ctx.signals]), 2 * math.pi)
    offsets = np.cumsum([0.0] + [float(s.t[-1]) for s in ctx.signals[:-1]])
    clock = np.concatenate([s.t + o for s, o in zip(ctx.signals, offsets, strict=True)])
    torque = np.abs(np.concatenate([r.torque_s for r in ctx.residuals]))
    torque_edges = np.unique(np.quantile(torque, np.linspace(0, 1, 7)))
    if torque_edges.size < 2:
        torque_edges = np.array([0.0, math.inf])
    time_edges = np.arange(0.0, float(clock.max()) + 2.5, 2.5)
    axes: dict[str, tuple[np.ndarray, list[str]]] = {
        "speed": (
            _bins(np.abs(speed), np.array(SPEED_BINS)),
            [f"at |ω_m| in [{a:g}, {b:g}) rad/s" for a, b in itertools.pairwise(SPEED_BINS)],
        ),
        "motor angle": (
            _bins(angle, np.linspace(0, 2 * math.pi, 25)),
            [f"at θ_m mod 2π ≈ {15 * i + 7.5:.0f}°" for i in range(24)],
        ),
        "time": (_bins(clock, time_edges), [f"around t = {a + 1.25:g} s" for a in time_edges[:-1]]),
        "transmitted torque": (
            _bins(torque, torque_edges),
            [f"at |T_s| in [{a:.2g}, {b:.2g}) N·m" for a, b in itertools.pairwise(torque_edges)],
        ),
        "rest": (np.where(stuck, 0, -1), ["at rest in the data"]),
    }
    best: Signature | None = None
    for channel, y in ctx.channels.items():
        unit = CHANNEL_UNITS[channel]
        for axis, (index, labels) in axes.items():
            signed = channel == "motor" and axis != "rest"
            factor = sign if signed else np.ones(len(y))
            used = [b for b in range(len(labels)) if np.any((index == b) & (factor != 0))]
            if not used:
                continue
            columns = [np.where(index == b, factor, 0.0) for b in used]
            X = np.column_stack(columns if channel == "load_position" else [ctx.smooth(c) for c in columns])
            score, beta = cv_regression(y, X, ctx.folds)
            if best is None or score > best.share:
                top = int(np.argmax(np.abs(beta)))
                what = f"{labels[used[top]]}: residual {beta[top]:+.3g} {unit}{' × sgn ω' if signed else ''}"
                best = Signature(channel, f"{axis}{' (× sgn ω)' if signed else ''}", score, what)
    return best
