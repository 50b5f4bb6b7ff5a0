"""The parameter registry: every model parameter once, with what the rest of the code needs to know of it.

For each scalar parameter of `model.params` (a Fourier vector counts as one per element: `a0`..`a10`,
`b1`..`b10`): its name, section and field, unit and bounds (read from the pydantic field, so they have
one home: the schema), its slot in the kernel's float vector, the law or effect that owns it, and the
identification stage that determines it. The kernel's vector layouts are the `IntEnum`s below, numbered
by declaration order (numba reads an `IntEnum` member as a compile-time constant, so `p[P.S3]` costs
what a literal index costs); nothing else numbers a slot.

The parameter and flag tables name each slot once; tests/test_registry.py checks that they cover every
field of the schema and every slot exactly once.
"""

from __future__ import annotations

import re
import typing
from dataclasses import dataclass
from enum import auto
from functools import cache
from typing import Any

import annotated_types
from pydantic.fields import FieldInfo

from model.errors import UserInputError
from model.params import (
    _ARTICLE_ONLY,
    _LOAD_LAW_FIELDS,
    _MOTOR_LAW_FIELDS,
    EFFECT_SECTIONS,
    N_FOURIER,
    HarmonicDriveModel,
    Section,
)
from model.slots import Slots


class P(Slots):
    """Slots of the kernel's float parameter vector `p`."""

    J_M = auto()
    J_L = auto()
    R_GEAR = auto()
    K_M = auto()
    K_B = auto()
    R_ARM = auto()
    K_S = auto()
    D_S = auto()
    S1 = auto()
    S2 = auto()
    S3 = auto()
    A0 = auto()  # the Fourier cosines a0..a10 follow each other: the kernel reads p[A0 + n]
    A1 = auto()
    A2 = auto()
    A3 = auto()
    A4 = auto()
    A5 = auto()
    A6 = auto()
    A7 = auto()
    A8 = auto()
    A9 = auto()
    A10 = auto()
    B1 = auto()  # the sines b1..b10 likewise: p[B1 + n - 1]
    B2 = auto()
    B3 = auto()
    B4 = auto()
    B5 = auto()
    B6 = auto()
    B7 = auto()
    B8 = auto()
    B9 = auto()
    B10 = auto()
    V_C = auto()
    K_V = auto()
    STATIC_FACTOR = auto()
    B_M = auto()
    F_CM = auto()
    F_SM = auto()
    OMEGA_SM = auto()
    SIGMA0_M = auto()
    SIGMA1_M = auto()
    F_CL = auto()
    F_SL = auto()
    OMEGA_SL = auto()
    SIGMA0_L = auto()
    SIGMA1_L = auto()
    B_L = auto()
    KE_A = auto()
    KE_K = auto()
    KE_PHI = auto()
    NS_K1 = auto()
    NS_K2 = auto()
    NS_K3 = auto()
    NS_T1 = auto()
    NS_T2 = auto()
    NS_D1 = auto()  # derived: the deflection at T1 (no field; see DERIVED)
    NS_D2 = auto()  # derived: the deflection at T2
    ST_F = auto()
    ST_OMEGA = auto()
    DIR_F = auto()
    LOAD_C = auto()
    HYS_T = auto()
    HYS_DELTA = auto()
    TH_D = auto()
    TH_TAU = auto()
    OMEGA_STICK_M = auto()
    OMEGA_STICK_L = auto()
    WEAR_K = auto()
    T_AMB = auto()  # thermal (temperature_dependence): the network's ambient [°C]
    T_REF = auto()
    BETA_T = auto()
    C_W = auto()
    C_G = auto()
    R_WG = auto()
    R_WA = auto()
    R_GA = auto()
    T_MOTOR0 = auto()  # the starting temperatures: read by model.plant's reset, not by the loop
    T_GEAR0 = auto()


class FL(Slots):
    """Slots of the kernel's integer flag vector (the model's structure: laws and effects present)."""

    MOTOR_LAW = auto()
    LOAD_LAW = auto()
    RIGID = auto()
    NONLINEAR = auto()
    HYSTERESIS = auto()
    KINEMATIC = auto()
    HARMONICS = auto()
    STRIBECK = auto()
    THERMAL = auto()
    WEAR = auto()
    TEMPERATURE = auto()


class X(Slots):
    """Slots of the kernel's state vector."""

    THETA_M = auto()
    OMEGA_M = auto()
    THETA_L = auto()
    OMEGA_L = auto()
    Z_M = auto()
    Z_L = auto()
    Z_H = auto()
    TIME = auto()
    TS = auto()
    TRAVEL = auto()  # motor travel accumulated since the start, ∫|ω_m|dt [rad] (wear_drift)
    RISE_MOTOR = auto()  # the winding's temperature above ambient, T_w − T_amb [K] (thermal)
    RISE_GEAR = auto()  # the gear's, T_g − T_amb [K]: a zeroed state is a plant at ambient


class OUT(Slots):
    """Columns of the kernel's output rows."""

    T = auto()
    DRIVE = auto()
    TAU_EXT = auto()
    THETA_M = auto()
    OMEGA_M = auto()
    THETA_L = auto()
    OMEGA_L = auto()
    I_A = auto()
    TAU_M = auto()
    F_M = auto()
    F_L = auto()
    T_S = auto()
    TEMP_MOTOR = auto()  # T_w [°C]; NaN without a thermal section
    TEMP_GEAR = auto()  # T_g [°C]; NaN without a thermal section


class Law(Slots):
    """Codes of the friction laws in FL.MOTOR_LAW and FL.LOAD_LAW (NONE: no load friction)."""

    NONE = auto()
    ARTICLE = auto()
    COULOMB_VISCOUS = auto()
    STRIBECK = auto()
    LUGRE = auto()
    DAHL = auto()


class Mode(Slots):
    """What the kernel's drive input is: a voltage [V], a current [A] or a motor torque [N·m]."""

    VOLTAGE = auto()
    CURRENT = auto()
    TORQUE = auto()


N_STATE = len(X)
N_OUT = len(OUT)
"""The state's and the output rows' sizes, for compiled code (numba cannot take the len of an enum)."""

LAW_CODES: dict[str, Law] = {
    "article": Law.ARTICLE,
    "coulomb_viscous": Law.COULOMB_VISCOUS,
    "stribeck": Law.STRIBECK,
    "lugre": Law.LUGRE,
    "dahl": Law.DAHL,
}

# --- identification stages ----------------------------------------------------------------------------

GIVEN = "given"  # a rig constant from the run's metadata (K_m, r)
MOTOR = "motor"
STIFFNESS = "stiffness"
FRF = "frf"
KINEMATIC = "kinematic-error"
POSITION = "friction-position"
VELOCITY = "friction-velocity"
BREAKAWAY = "breakaway"
STRUCTURAL = "structural"  # not estimated by the staged fit: held at the start value
NUMERICS = "numerics"  # the integrator's settings, not a property of the drive

STAGES = (GIVEN, MOTOR, STIFFNESS, FRF, KINEMATIC, POSITION, VELOCITY, BREAKAWAY, STRUCTURAL, NUMERICS)
"""The staged identification's stages (rig.analysis.identification.staged), in the order they run."""

# --- the table: one row per scalar parameter ------------------------------------------------------------

_FOURIER_A = tuple((f"a{n}", "motor_friction", "a", n, P.A0 + n, POSITION) for n in range(N_FOURIER + 1))
_FOURIER_B = tuple(
    (f"b{n}", "motor_friction", "b", n - 1, P.B1 + n - 1, POSITION) for n in range(1, N_FOURIER + 1)
)

_TABLE: tuple[tuple[str, str, str, int | None, int, str], ...] = (
    # name, section, field, index in a vector field, kernel slot, identification stage
    ("J_m", "mechanics", "J_m", None, P.J_M, FRF),
    ("J_l", "mechanics", "J_l", None, P.J_L, FRF),
    ("r", "mechanics", "r", None, P.R_GEAR, GIVEN),
    ("K_m", "motor", "K_m", None, P.K_M, GIVEN),
    ("K_b", "motor", "K_b", None, P.K_B, MOTOR),
    ("R", "motor", "R", None, P.R_ARM, MOTOR),
    ("K_s", "transmission", "K_s", None, P.K_S, STIFFNESS),
    ("D_s", "transmission", "D_s", None, P.D_S, FRF),
    ("s1", "motor_friction", "s1", None, P.S1, POSITION),
    ("s2", "motor_friction", "s2", None, P.S2, POSITION),
    ("s3", "motor_friction", "s3", None, P.S3, VELOCITY),
    *_FOURIER_A,
    *_FOURIER_B,
    ("v_c", "motor_friction", "v_c", None, P.V_C, VELOCITY),
    ("k_v", "motor_friction", "k_v", None, P.K_V, VELOCITY),
    ("static_factor", "motor_friction", "static_factor", None, P.STATIC_FACTOR, BREAKAWAY),
    ("b_m", "motor_friction", "b_m", None, P.B_M, VELOCITY),
    ("f_cm", "motor_friction", "f_cm", None, P.F_CM, VELOCITY),
    ("f_sm", "motor_friction", "f_sm", None, P.F_SM, BREAKAWAY),
    ("omega_sm", "motor_friction", "omega_sm", None, P.OMEGA_SM, VELOCITY),
    ("sigma0_m", "motor_friction", "sigma0_m", None, P.SIGMA0_M, STRUCTURAL),
    ("sigma1_m", "motor_friction", "sigma1_m", None, P.SIGMA1_M, STRUCTURAL),
    ("f_cl", "load_friction", "f_cl", None, P.F_CL, STIFFNESS),
    ("f_sl", "load_friction", "f_sl", None, P.F_SL, STIFFNESS),
    ("omega_sl", "load_friction", "omega_sl", None, P.OMEGA_SL, STRUCTURAL),
    ("sigma0_l", "load_friction", "sigma0_l", None, P.SIGMA0_L, STRUCTURAL),
    ("sigma1_l", "load_friction", "sigma1_l", None, P.SIGMA1_L, STRUCTURAL),
    ("b_l", "load_friction", "b_l", None, P.B_L, STIFFNESS),
    ("A", "kinematic_error", "A", None, P.KE_A, KINEMATIC),
    ("k", "kinematic_error", "k", None, P.KE_K, KINEMATIC),
    ("phi", "kinematic_error", "phi", None, P.KE_PHI, KINEMATIC),
    ("K1", "nonlinear_stiffness", "K1", None, P.NS_K1, STIFFNESS),
    ("K2", "nonlinear_stiffness", "K2", None, P.NS_K2, STIFFNESS),
    ("K3", "nonlinear_stiffness", "K3", None, P.NS_K3, STIFFNESS),
    ("T1", "nonlinear_stiffness", "T1", None, P.NS_T1, STIFFNESS),
    ("T2", "nonlinear_stiffness", "T2", None, P.NS_T2, STIFFNESS),
    ("f_st", "stribeck", "f_st", None, P.ST_F, VELOCITY),
    ("omega_st", "stribeck", "omega_st", None, P.ST_OMEGA, VELOCITY),
    ("f_dir", "direction_asymmetry", "f_dir", None, P.DIR_F, VELOCITY),
    ("c_Ts", "load_dependent_friction", "c_Ts", None, P.LOAD_C, VELOCITY),
    ("T_h", "hysteresis", "T_h", None, P.HYS_T, STRUCTURAL),
    ("delta_h", "hysteresis", "delta_h", None, P.HYS_DELTA, STRUCTURAL),
    ("d_th", "thermal_drift", "d_th", None, P.TH_D, STRUCTURAL),
    ("tau_th", "thermal_drift", "tau_th", None, P.TH_TAU, STRUCTURAL),
    ("k_wear", "wear_drift", "k_wear", None, P.WEAR_K, STRUCTURAL),
    ("T_amb", "thermal", "T_amb", None, P.T_AMB, GIVEN),
    ("T_ref", "thermal", "T_ref", None, P.T_REF, GIVEN),
    ("beta_T", "thermal", "beta_T", None, P.BETA_T, STRUCTURAL),
    ("C_w", "thermal", "C_w", None, P.C_W, STRUCTURAL),
    ("C_g", "thermal", "C_g", None, P.C_G, STRUCTURAL),
    ("R_wg", "thermal", "R_wg", None, P.R_WG, STRUCTURAL),
    ("R_wa", "thermal", "R_wa", None, P.R_WA, STRUCTURAL),
    ("R_ga", "thermal", "R_ga", None, P.R_GA, STRUCTURAL),
    ("T_motor0", "thermal", "T_motor0", None, P.T_MOTOR0, GIVEN),
    ("T_gear0", "thermal", "T_gear0", None, P.T_GEAR0, GIVEN),
    ("omega_stick_m", "numerics", "omega_stick_m", None, P.OMEGA_STICK_M, NUMERICS),
    ("omega_stick_l", "numerics", "omega_stick_l", None, P.OMEGA_STICK_L, NUMERICS),
)

ALSO_DETERMINED: dict[str, tuple[str, ...]] = {"f_sm": (VELOCITY,)}
"""Stages that estimate a parameter beside its own: the Stribeck and LuGre laws' static level is part
of the velocity curve the velocity stage fits; the breakaway stage then times it where it can."""

DERIVED: dict[P, str] = {
    P.NS_D1: "nonlinear_stiffness: deflection at T1, T1/K1 [rad]",
    P.NS_D2: "nonlinear_stiffness: deflection at T2, T1/K1 + (T2 − T1)/K2 [rad]",
}
"""Kernel slots that hold no field of their own but a value computed from others (model.plant)."""

KERNEL_DEFAULTS: dict[str, float] = {"static_factor": 1.0, "sigma0_m": 1.0, "sigma0_l": 1.0}
"""What the kernel reads for an unset field (or an absent section) when 0 would not do: a harmless
static ratio and a bristle stiffness that divides nothing by zero (the law that reads them sets them)."""

FLAG_SOURCES: dict[FL, str] = {
    FL.MOTOR_LAW: "motor_friction.motor_law",
    FL.LOAD_LAW: "load_friction.load_law (Law.NONE when the section is absent)",
    FL.RIGID: "transmission.K_s is null",
    FL.NONLINEAR: "section nonlinear_stiffness",
    FL.HYSTERESIS: "section hysteresis",
    FL.KINEMATIC: "section kinematic_error with A > 0",
    FL.HARMONICS: "the highest nonzero Fourier harmonic of motor_friction.a, .b",
    FL.STRIBECK: "section stribeck",
    FL.THERMAL: "section thermal_drift",
    FL.WEAR: "section wear_drift",
    FL.TEMPERATURE: "section thermal (effect temperature_dependence)",
}
"""What sets each flag slot: the law selectors and the effect sections."""

EFFECT_FLAGS: dict[str, FL] = {
    "nonlinear_stiffness": FL.NONLINEAR,
    "hysteresis": FL.HYSTERESIS,
    "kinematic_error": FL.KINEMATIC,
    "stribeck": FL.STRIBECK,
    "thermal_drift": FL.THERMAL,
    "wear_drift": FL.WEAR,
    "thermal": FL.TEMPERATURE,
}
"""The effect sections the kernel branches on, each with its flag (the others only set parameters)."""

SECTION_OWNERS: dict[str, str] = {
    "mechanics": "plant",
    "motor": "plant",
    "transmission": "compliance",
    "motor_friction": "motor_friction",
    "load_friction": "load_side_friction",
    "numerics": "numerics",
    **{effect: effect for effect in EFFECT_SECTIONS},
    "thermal": "temperature_dependence",
}
"""The docs/MODEL.md effect (or the plant's core, or its numerics) each section's parameters belong to."""


@dataclass(frozen=True)
class Bounds:
    """A parameter's admissible range, as the schema validates it (None: unbounded that side)."""

    lower: float | None = None
    upper: float | None = None
    lower_inclusive: bool = True
    upper_inclusive: bool = True

    def admits(self, value: float) -> bool:
        if self.lower is not None and (
            value < self.lower or (value == self.lower and not self.lower_inclusive)
        ):
            return False
        return not (
            self.upper is not None
            and (value > self.upper or (value == self.upper and not self.upper_inclusive))
        )

    def __str__(self) -> str:
        low = "(-inf" if self.lower is None else ("[" if self.lower_inclusive else "(") + f"{self.lower:g}"
        high = "inf)" if self.upper is None else f"{self.upper:g}" + ("]" if self.upper_inclusive else ")")
        return f"{low}, {high}"


@dataclass(frozen=True)
class Parameter:
    """One scalar model parameter."""

    name: str  # as the fit, the gaps and the reports name it: the field, or a0..a10, b1..b10
    section: str  # the model file's section
    field: str  # the field in that section
    index: int | None  # the element of a vector field (a, b), else None
    slot: P  # where the kernel reads it
    owner: str  # the effect (SECTION_OWNERS) it belongs to
    laws: tuple[str, ...]  # the friction laws that use it ((): not a law's parameter)
    stage: str  # the identification stage that determines it (STAGES)
    unit: str  # from the field's description
    bounds: Bounds  # from the field's constraints
    description: str
    kernel_default: float  # what the kernel reads when the field is unset or its section absent

    def determined_in(self, stage: str) -> bool:
        """Whether `stage` estimates this parameter (its own stage, or one of ALSO_DETERMINED)."""
        return stage == self.stage or stage in ALSO_DETERMINED.get(self.name, ())

    def value(self, model: HarmonicDriveModel) -> float | None:
        """The parameter's value in `model`; None when its section is absent or the field unset."""
        section = getattr(model, self.section)
        if section is None:
            return None
        value = getattr(section, self.field)
        if value is None:
            return None
        return float(value if self.index is None else value[self.index])


_UNIT = re.compile(r"\[([^\]]*)\]")


def _section_classes() -> dict[str, type[Section]]:
    out: dict[str, type[Section]] = {}
    for name, info in HarmonicDriveModel.model_fields.items():
        for candidate in (info.annotation, *typing.get_args(info.annotation)):
            if isinstance(candidate, type) and issubclass(candidate, Section):
                out[name] = candidate
    return out


def _constraints(info: FieldInfo) -> list[Any]:
    """The annotated_types constraints on a field, including those inside `X | None` and `list[X]`."""
    found = list(info.metadata)
    stack: list[Any] = [info.annotation]
    while stack:
        annotation = stack.pop()
        if typing.get_origin(annotation) is typing.Annotated:
            for meta in annotation.__metadata__:
                found += meta.metadata if isinstance(meta, FieldInfo) else [meta]
        stack += typing.get_args(annotation)
    return found


def _bounds(info: FieldInfo) -> Bounds:
    lower = upper = None
    lower_inclusive = upper_inclusive = True
    for c in _constraints(info):
        if isinstance(c, annotated_types.Gt):
            lower, lower_inclusive = float(c.gt), False  # type: ignore[arg-type]
        elif isinstance(c, annotated_types.Ge):
            lower, lower_inclusive = float(c.ge), True  # type: ignore[arg-type]
        elif isinstance(c, annotated_types.Lt):
            upper, upper_inclusive = float(c.lt), False  # type: ignore[arg-type]
        elif isinstance(c, annotated_types.Le):
            upper, upper_inclusive = float(c.le), True  # type: ignore[arg-type]
    return Bounds(lower, upper, lower_inclusive, upper_inclusive)


def _laws(section: str, field: str) -> tuple[str, ...]:
    if section == "motor_friction":
        if field == "b_m":
            return tuple(_MOTOR_LAW_FIELDS)
        return tuple(
            law
            for law, needs in _MOTOR_LAW_FIELDS.items()
            if field in needs or (law == "article" and field in _ARTICLE_ONLY)
        )
    if section == "load_friction":
        if field == "b_l":
            return tuple(_LOAD_LAW_FIELDS)
        return tuple(law for law, needs in _LOAD_LAW_FIELDS.items() if field in needs)
    return ()


def _build() -> dict[str, Parameter]:
    classes = _section_classes()
    out: dict[str, Parameter] = {}
    for name, section, field, index, slot, stage in _TABLE:
        info = classes[section].model_fields[field]
        description = info.description or ""
        units = _UNIT.findall(description)
        if not units:
            raise RuntimeError(f"{section}.{field}: its description names no unit in [...]")
        if name in out:
            raise RuntimeError(f"parameter {name} is declared twice")
        out[name] = Parameter(
            name=name,
            section=section,
            field=field,
            index=index,
            slot=P(slot),
            owner=SECTION_OWNERS[section],
            laws=_laws(section, field),
            stage=stage,
            unit=units[-1],
            bounds=_bounds(info),
            description=description,
            kernel_default=KERNEL_DEFAULTS.get(name, 0.0),
        )
    return dict(sorted(out.items(), key=lambda item: item[1].slot))


PARAMETERS: dict[str, Parameter] = _build()
"""Every scalar model parameter by name, in kernel slot order."""

SELECTORS: dict[str, FL] = {"motor_law": FL.MOTOR_LAW, "load_law": FL.LOAD_LAW}
"""The schema's law fields: each selects a law code in a flag slot, not a number."""


def parameter(name: str) -> Parameter:
    """The registry's entry for `name`; a one-line error naming the known ones otherwise."""
    try:
        return PARAMETERS[name]
    except KeyError:
        raise UserInputError(
            f"parameter {name!r} is not a model parameter (known: {', '.join(PARAMETERS)})"
        ) from None


@cache
def owned_by(owner: str) -> tuple[str, ...]:
    """The parameters of an effect (SECTION_OWNERS' values), in slot order."""
    return tuple(p.name for p in PARAMETERS.values() if p.owner == owner)


@cache
def determined_by(stage: str) -> tuple[str, ...]:
    """The parameters a stage of the staged identification determines, in slot order."""
    if stage not in STAGES:
        raise ValueError(f"unknown stage {stage!r} (stages: {', '.join(STAGES)})")
    return tuple(p.name for p in PARAMETERS.values() if p.stage == stage)


def of_section(section: str) -> tuple[str, ...]:
    """The parameters of a model file section, in slot order."""
    return tuple(p.name for p in PARAMETERS.values() if p.section == section)


JOINT_CANDIDATES = ("s3", "k_v", "static_factor", "K_s", "J_m", "J_l", "f_cl", "b_l")
"""Parameters the joint trajectory refinement (rig.analysis.identification.identify) may move, when the
staged fit found them determined, in the order of its parameter vector: those that shape trajectories
most. The Fourier and quadratic coefficients keep their staged values, which come from data made for
them; so do R and K_b: the motor stage's u = R·i_a + K_b·(ω + δ·dω/dt) is exact sample by sample, where
the trajectories, free to move them, pulled K_b by a bias of their own replay (docs/BENCHMARKS.md)."""
if not set(JOINT_CANDIDATES) <= set(PARAMETERS):
    raise RuntimeError(f"JOINT_CANDIDATES names no parameter: {set(JOINT_CANDIDATES) - set(PARAMETERS)}")

FOURIER_NAMES = tuple(name for name, *_ in (*_FOURIER_A[1:], *_FOURIER_B))
"""a1..a10 then b1..b10: the harmonics (a0, a constant, is collinear with s3)."""


def slot_defines() -> list[str]:
    """P's slots as C preprocessor definitions (-DJ_M=0 ... -DN_PARAMS=68): a C mirror of the kernel
    (bench/seed_loop.c) is built with them, so it numbers no slot itself."""
    return [f"-D{slot.name}={int(slot)}" for slot in P] + [f"-DN_PARAMS={len(P)}"]
