"""The numbers labs compare: what a fitted model says in the terms catalogs and other tools use.

The article's parametrization hides them: its moving branch (docs/MODEL.md)

    F_m = sgn(ω_m)·[ C(θ_m)·(1 + k_v·(|ω_m| − v_c)) + P(θ_m) ] + b_m·ω_m,   C = s1·θ² + s2·θ + s3

is, at θ_m = 0 and over a whole motor turn (P averages to a0/2), a straight line in |ω_m| whose value
at rest is s3·(1 − k_v·v_c) + a0/2 and whose slope is s3·k_v + b_m; a lab's Coulomb-plus-viscous fit of
the same gear gives those two numbers, not s3 and k_v. The effects move them the way the kernel does:
`direction_asymmetry` adds +f_dir moving forward and −f_dir moving backward to the magnitude (so the
levels are per direction, the slope is not); `stribeck` adds f_st at rest only (so it is breakaway, not
Coulomb); the breakaway is the stuck branch's limit static_factor·(moving magnitude at rest) + f_st, ± f_dir.
Baseline laws read directly (f_cm, f_sm, b_m). Load side: f_cl, f_sl, b_l at the output. Figures hold
at zero transmitted torque (`load_dependent_friction`), at the run's start (`thermal_drift`,
`wear_drift`) and at T_ref (`thermal`), where the model's parameters are defined.

σ by first-order propagation of the fitted parameters' σ (central differences: every quantity here is
linear in each parameter alone, so they are exact): through the covariance when one is given, else
taking the parameters as independent. A parameter the fit did not move counts as exact; one the fit
moved without determining it (σ None) leaves every quantity it enters undetermined.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from model.params import HarmonicDriveModel
from model.registry import PARAMETERS

Values = Mapping[str, float]


@dataclass(frozen=True)
class LabQuantity:
    name: str  # e.g. coulomb_at_rest_forward_Nm
    value: float
    sigma: float | None  # 1 σ; None when a parameter it depends on was fitted but not determined
    unit: str
    meaning: str  # one line: what it is, in the model's parameters

    def as_json(self) -> dict[str, float | str | None]:
        return {"value": self.value, "sigma": self.sigma, "unit": self.unit, "meaning": self.meaning}


@dataclass(frozen=True)
class _Definition:
    name: str
    unit: str
    meaning: str
    formula: Callable[[Values], float]


def _article_level(v: Values) -> float:
    """The article's moving magnitude at rest, θ_m = 0, averaged over a motor turn."""
    return v["s3"] * (1.0 - v["k_v"] * v["v_c"]) + 0.5 * v["a0"]


def _directed(magnitude: Callable[[Values], float], sign: float) -> Callable[[Values], float]:
    """A magnitude moved by direction_asymmetry's ±f_dir (+ forward, − backward), as the kernel does."""
    return lambda v: magnitude(v) + sign * v["f_dir"]


Law = tuple[Callable[[Values], float], str]


def _motor_laws(model: HarmonicDriveModel) -> tuple[Law, Law, Law]:
    """The motor law's (level at rest, viscous slope, static level), each with its formula's text."""
    law = model.motor_friction.motor_law
    if law == "article":
        level, level_text = _article_level, "s3·(1 − k_v·v_c) + a0/2"
        slope, slope_text = (lambda v: v["s3"] * v["k_v"] + v["b_m"]), "s3·k_v + b_m"
        static, static_text = (
            (lambda v: v["static_factor"] * _article_level(v)),
            "static_factor·(" + level_text + ")",
        )
    else:
        level, level_text = (lambda v: v["f_cm"]), "f_cm"
        slope, slope_text = (lambda v: v["b_m"]), "b_m"
        if law == "dahl":
            static, static_text = level, "f_cm (Dahl: no stiction)"
        else:
            static, static_text = (lambda v: v["f_sm"]), "f_sm"
    return (level, level_text), (slope, slope_text), (static, static_text)


def _motor_definitions(model: HarmonicDriveModel, laws: tuple[Law, Law, Law]) -> list[_Definition]:
    """The motor side's Coulomb at rest, viscous slope and breakaway, per direction."""
    (level, level_text), (slope, slope_text), (static, static_text) = laws
    out: list[_Definition] = []
    stribeck = model.stribeck is not None
    for sign, direction in ((1.0, "forward"), (-1.0, "backward")):
        dir_text = (" + f_dir" if sign > 0 else " − f_dir") if model.direction_asymmetry is not None else ""
        out.append(
            _Definition(
                f"coulomb_at_rest_{direction}_Nm",
                "N·m",
                f"motor side, moving {direction}: its straight line at |ω_m| → 0, {level_text}{dir_text}",
                _directed(level, sign),
            )
        )
        out.append(
            _Definition(
                f"viscous_slope_{direction}_Nms_per_rad",
                "N·m·s/rad",
                f"motor side, moving {direction}: dF_m/d|ω_m|, {slope_text}",
                slope,
            )
        )
        out.append(
            _Definition(
                f"breakaway_{direction}_Nm",
                "N·m",
                f"motor side, {direction}: torque beyond which a stuck motor moves, {static_text}"
                + (" + f_st" if stribeck else "")
                + dir_text,
                _directed(lambda v: static(v) + v["f_st"], sign),
            )
        )
    return out


def _output_definitions(model: HarmonicDriveModel, laws: tuple[Law, Law, Law]) -> list[_Definition]:
    """The load side's friction, both sides seen at the output, the inertias and the stiffness."""
    (level, _), (slope, _), _ = laws
    out: list[_Definition] = []
    if model.load_friction is not None:
        out += [
            _Definition("load_coulomb_Nm", "N·m", "output side: Coulomb level f_cl", lambda v: v["f_cl"]),
            _Definition(
                "load_viscous_Nms_per_rad", "N·m·s/rad", "output side: viscous b_l", lambda v: v["b_l"]
            ),
            _Definition("load_breakaway_Nm", "N·m", "output side: static level f_sl", lambda v: v["f_sl"]),
        ]
    out.append(
        _Definition(
            "coulomb_at_output_Nm",
            "N·m",
            "both sides' Coulomb at rest seen at the output (mean of the directions): level/r + f_cl",
            lambda v: level(v) / v["r"] + v["f_cl"],
        )
    )
    out.append(
        _Definition(
            "viscous_at_output_Nms_per_rad",
            "N·m·s/rad",
            "both sides' viscous slope seen at the output: slope/r² + b_l",
            lambda v: slope(v) / v["r"] ** 2 + v["b_l"],
        )
    )
    out.append(
        _Definition(
            "inertia_motor_side_kgm2",
            "kg·m²",
            "total inertia at the motor shaft: J_m + r²·J_l",
            lambda v: v["J_m"] + v["r"] ** 2 * v["J_l"],
        )
    )
    out.append(
        _Definition(
            "inertia_output_side_kgm2",
            "kg·m²",
            "total inertia at the output: J_l + J_m/r²",
            lambda v: v["J_l"] + v["J_m"] / v["r"] ** 2,
        )
    )
    if model.transmission.K_s is not None:
        out.append(
            _Definition(
                "stiffness_Nm_per_rad",
                "N·m/rad",
                "torsional stiffness at the output, K_s",
                lambda v: v["K_s"],
            )
        )
    return out


def _definitions(model: HarmonicDriveModel) -> list[_Definition]:
    laws = _motor_laws(model)
    return _motor_definitions(model, laws) + _output_definitions(model, laws)


def model_values(model: HarmonicDriveModel) -> dict[str, float]:
    """Every scalar parameter's value in `model`, with the kernel's default where the model has none."""
    values = {}
    for name, entry in PARAMETERS.items():
        value = entry.value(model)
        values[name] = entry.kernel_default if value is None else value
    if model.stribeck is None:
        values["f_st"] = 0.0
    if model.direction_asymmetry is None:
        values["f_dir"] = 0.0
    if model.load_friction is None:
        values["f_cl"] = values["f_sl"] = values["b_l"] = 0.0
    return values


def lab_quantities(
    model: HarmonicDriveModel,
    sigma: Mapping[str, float | None],
    covariance: tuple[Sequence[str], np.ndarray] | None = None,
) -> list[LabQuantity]:
    """The lab's figures of `model`, each with its σ.

    `sigma`: the 1 σ of each parameter the fit moved (None: moved, not determined); parameters absent
    from it count as exact. `covariance`: (names, matrix) of parameters fitted together; where given it
    replaces the independent σ of those names."""
    values = model_values(model)
    cov_names = list(covariance[0]) if covariance is not None else []
    cov = np.asarray(covariance[1], dtype=float) if covariance is not None else np.zeros((0, 0))
    if cov.shape != (len(cov_names), len(cov_names)):
        raise ValueError(f"covariance is {cov.shape}, not the square of its {len(cov_names)} names")
    quantities = []
    for item in _definitions(model):
        value = float(item.formula(values))
        partials = _partials(item.formula, values, [*sigma, *cov_names])
        quantities.append(
            LabQuantity(
                item.name, value, _propagate(partials, sigma, cov_names, cov), item.unit, item.meaning
            )
        )
    return quantities


def _partials(
    formula: Callable[[Values], float], values: dict[str, float], names: list[str]
) -> dict[str, float]:
    """∂formula/∂name by central differences (exact here: each formula is linear in each parameter
    alone, except r, which fits never move); zero partials left out."""
    out = {}
    for name in dict.fromkeys(names):
        if name not in values:
            continue
        x = values[name]
        step = 1e-4 * abs(x) if x != 0.0 else 1e-4  # exact for linear terms; r's 1/r² to ~1e-8
        up = formula({**values, name: x + step})
        down = formula({**values, name: x - step})
        derivative = (up - down) / (2.0 * step)
        if derivative != 0.0:
            out[name] = derivative
    return out


def _propagate(
    partials: dict[str, float], sigma: Mapping[str, float | None], cov_names: list[str], cov: np.ndarray
) -> float | None:
    variance = 0.0
    if cov_names:
        g = np.array([partials.get(name, 0.0) for name in cov_names])
        variance += float(g @ cov @ g)
    for name, derivative in partials.items():
        if name in cov_names:
            continue
        s = sigma.get(name, 0.0)
        if s is None or not math.isfinite(s):
            return None
        variance += (derivative * s) ** 2
    return math.sqrt(max(variance, 0.0))


class _Row(Protocol):
    name: str
    start: float
    estimate: float
    uncertainty: float | None
    identifiable: bool


def fitted_sigmas(rows: Iterable[_Row]) -> dict[str, float | None]:
    """The σ map `lab_quantities` takes, from a fit's parameter rows: a determined row's σ; None for a
    row the fit moved without determining it; rows held at their start (given, or not determined and
    kept) are left out, so they count as exact: the figures are conditional on them."""
    out: dict[str, float | None] = {}
    for row in rows:
        if row.identifiable and row.uncertainty is not None:
            out[row.name] = row.uncertainty
        elif row.estimate != row.start:
            out[row.name] = None
    return out


def lab_table(quantities: Sequence[LabQuantity]) -> list[str]:
    """The Markdown table the fit report carries."""
    lines = ["## The numbers labs compare", "", "| quantity | value | 1 σ | unit | in the model's terms |"]
    lines.append("|---|---|---|---|---|")
    for q in quantities:
        s = f"{q.sigma:.3g}" if q.sigma is not None else "not determined"
        lines.append(f"| {q.name} | {q.value:.6g} | {s} | {q.unit} | {q.meaning} |")
    lines += [
        "",
        "σ propagated from the fitted parameters' σ; parameters held at their start count as exact.",
    ]
    return lines
