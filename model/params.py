"""Model parameters: validated pydantic models with the symbol names of docs/MODEL.md and units in each field.

A model file is YAML or JSON with the sections below. Sections named after an effect of the docs/MODEL.md
vocabulary (`kinematic_error`, `nonlinear_stiffness`, `stribeck`, ...) are optional: absent means the
effect is not in the model. Every leaf name is unique in a file, so `K_s` means one thing everywhere.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Iterable
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from model.errors import UserInputError, describe_validation_error
from model.resources import card_folder
from model.settings_file import read_settings

N_FOURIER = 10
"""Harmonics of the periodic Coulomb part: a0..a10 (11 values) and b1..b10 (10 values)."""


Finite = Annotated[float, Field(allow_inf_nan=False)]
Positive = Annotated[float, Field(gt=0, allow_inf_nan=False)]
NonNegative = Annotated[float, Field(ge=0, allow_inf_nan=False)]


class Section(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Mechanics(Section):
    J_m: Positive = Field(description="motor-side inertia: rotor + wave generator [kg·m²]")
    J_l: Positive = Field(description="load-side inertia: output flange + load [kg·m²]")
    r: float = Field(gt=0, le=1, description="gear ratio as output/input, 0 < r ≤ 1 (0.01 for 100:1) [–]")


class Motor(Section):
    K_m: Positive = Field(description="torque constant [N·m/A]")
    K_b: NonNegative = Field(description="back-EMF constant [V·s/rad]")
    R: Positive = Field(description="armature resistance [Ω]")


class Transmission(Section):
    K_s: Positive | None = Field(
        default=None,
        description="transmission stiffness at the output [N·m/rad]; null or absent: rigid transmission",
    )
    D_s: NonNegative = Field(default=0.0, description="transmission damping at the output [N·m·s/rad]")

    @model_validator(mode="after")
    def _damping_needs_compliance(self) -> Transmission:
        if self.K_s is None and self.D_s != 0:
            raise ValueError("D_s must be 0 when K_s is null (a rigid transmission has no damping)")
        return self


MotorLaw = Literal["article", "coulomb_viscous", "stribeck", "lugre", "dahl"]
LoadLaw = Literal["coulomb_viscous", "stribeck", "lugre", "dahl"]

# Which fields each friction law needs (beyond the viscous coefficient, which every law has).
_MOTOR_LAW_FIELDS: dict[str, tuple[str, ...]] = {
    "article": ("s3",),
    "coulomb_viscous": ("f_cm", "f_sm"),
    "stribeck": ("f_cm", "f_sm", "omega_sm"),
    "lugre": ("f_cm", "f_sm", "omega_sm", "sigma0_m", "sigma1_m"),
    "dahl": ("f_cm", "sigma0_m"),
}
_ARTICLE_ONLY = ("s1", "s2", "s3", "a", "b", "v_c", "k_v", "static_factor")
_LOAD_LAW_FIELDS: dict[str, tuple[str, ...]] = {
    "coulomb_viscous": ("f_cl", "f_sl"),
    "stribeck": ("f_cl", "f_sl", "omega_sl"),
    "lugre": ("f_cl", "f_sl", "omega_sl", "sigma0_l", "sigma1_l"),
    "dahl": ("f_cl", "sigma0_l"),
}


def _check_law_fields(
    section: BaseModel, law: str, needs: tuple[str, ...], optional: Iterable[str], law_field: str
) -> None:
    given = {name for name in type(section).model_fields if getattr(section, name) is not None}
    missing = [n for n in needs if n not in given]
    if missing:
        raise ValueError(f"{law_field}={law!r} needs {', '.join(missing)}")
    allowed = set(needs) | set(optional) | {law_field, "b_m", "b_l"}
    extra = sorted(given - allowed)
    if extra:
        raise ValueError(f"{', '.join(extra)} not used by {law_field}={law!r}: remove them or change the law")


class MotorFriction(Section):
    """Motor-side friction F_m. `article`: the position-dependent law of docs/MODEL.md; others: baselines."""

    motor_law: MotorLaw = Field(default="article", description="friction law on the motor side")
    s1: Finite | None = Field(default=None, description="quadratic coefficient of C(θ_m) [N·m/rad²]")
    s2: Finite | None = Field(default=None, description="linear coefficient of C(θ_m) [N·m/rad]")
    s3: Finite | None = Field(default=None, description="average Coulomb level, constant of C(θ_m) [N·m]")
    a: list[Finite] | None = Field(default=None, description="Fourier cosine coefficients a0..a10 [N·m]")
    b: list[Finite] | None = Field(default=None, description="Fourier sine coefficients b1..b10 [N·m]")
    v_c: NonNegative | None = Field(
        default=None, description="threshold velocity of the moving branch [rad/s]"
    )
    k_v: Finite | None = Field(default=None, description="velocity factor of the moving branch [s/rad]")
    static_factor: Positive | None = Field(
        default=None, description="static / Coulomb ratio at zero speed [–]"
    )
    f_cm: NonNegative | None = Field(default=None, description="baseline laws: Coulomb friction level [N·m]")
    f_sm: NonNegative | None = Field(default=None, description="baseline laws: static friction level [N·m]")
    omega_sm: Positive | None = Field(default=None, description="baseline laws: Stribeck velocity [rad/s]")
    sigma0_m: Positive | None = Field(default=None, description="LuGre/Dahl bristle stiffness [N·m/rad]")
    sigma1_m: NonNegative | None = Field(default=None, description="LuGre bristle damping [N·m·s/rad]")
    b_m: NonNegative = Field(default=0.0, description="viscous coefficient (LuGre σ2) [N·m·s/rad]")

    @field_validator("a")
    @classmethod
    def _eleven_cosines(cls, a: list[float] | None) -> list[float] | None:
        if a is not None and len(a) != N_FOURIER + 1:
            raise ValueError(f"needs {N_FOURIER + 1} values a0..a{N_FOURIER}, got {len(a)}")
        return a

    @field_validator("b")
    @classmethod
    def _ten_sines(cls, b: list[float] | None) -> list[float] | None:
        if b is not None and len(b) != N_FOURIER:
            raise ValueError(f"needs {N_FOURIER} values b1..b{N_FOURIER}, got {len(b)}")
        return b

    @model_validator(mode="after")
    def _fields_match_law(self) -> MotorFriction:
        law = self.motor_law
        optional = _ARTICLE_ONLY if law == "article" else ()
        if law == "coulomb_viscous" and self.f_sm is None and self.f_cm is not None:
            # static level defaults to the Coulomb level when not given
            object.__setattr__(self, "f_sm", self.f_cm)
        _check_law_fields(self, law, _MOTOR_LAW_FIELDS[law], optional, "motor_law")
        if law in ("stribeck", "lugre") and (self.f_sm or 0.0) < (self.f_cm or 0.0):
            raise ValueError("f_sm must be ≥ f_cm (static friction at least the Coulomb level)")
        return self

    def fourier_a(self) -> list[float]:
        return list(self.a) if self.a is not None else [0.0] * (N_FOURIER + 1)

    def fourier_b(self) -> list[float]:
        return list(self.b) if self.b is not None else [0.0] * N_FOURIER


class LoadFriction(Section):
    """Load-side friction F_l (docs/MODEL.md effect `load_side_friction`)."""

    load_law: LoadLaw = Field(default="coulomb_viscous", description="friction law on the load side")
    f_cl: NonNegative | None = Field(default=None, description="load-side Coulomb friction [N·m]")
    f_sl: NonNegative | None = Field(default=None, description="load-side static friction [N·m]")
    omega_sl: Positive | None = Field(default=None, description="load-side Stribeck velocity [rad/s]")
    sigma0_l: Positive | None = Field(default=None, description="load-side LuGre/Dahl stiffness [N·m/rad]")
    sigma1_l: NonNegative | None = Field(default=None, description="load-side LuGre damping [N·m·s/rad]")
    b_l: NonNegative = Field(default=0.0, description="load-side viscous coefficient [N·m·s/rad]")

    @model_validator(mode="after")
    def _fields_match_law(self) -> LoadFriction:
        if self.load_law == "coulomb_viscous" and self.f_sl is None and self.f_cl is not None:
            object.__setattr__(self, "f_sl", self.f_cl)
        _check_law_fields(self, self.load_law, _LOAD_LAW_FIELDS[self.load_law], (), "load_law")
        if self.load_law in ("coulomb_viscous", "stribeck", "lugre") and (self.f_sl or 0.0) < (
            self.f_cl or 0.0
        ):
            raise ValueError("f_sl must be ≥ f_cl (static friction at least the Coulomb level)")
        return self


class KinematicError(Section):
    """Effect `kinematic_error`: θ_err = A·sin(k·θ_m + phi) at the output."""

    A: NonNegative = Field(description="amplitude of the kinematic error at the output [rad]")
    k: Finite = Field(description="cycles of the error per motor revolution [–]")
    phi: Finite = Field(default=0.0, description="phase of the error [rad]")


class NonlinearStiffness(Section):
    """Effect `nonlinear_stiffness`: the catalog's piecewise-linear torsional stiffness at the output.

    Deflection grows with 1/K1 up to T1, then 1/K2 up to T2, then 1/K3; symmetric in the torque sign.
    The transmission's `K_s` must equal `K1` (it is the low-torque stiffness), so there is one truth.
    """

    K1: Positive = Field(description="stiffness from 0 to T1 [N·m/rad]")
    K2: Positive = Field(description="stiffness from T1 to T2 [N·m/rad]")
    K3: Positive = Field(description="stiffness above T2 [N·m/rad]")
    T1: Positive = Field(description="first breakpoint torque [N·m]")
    T2: Positive = Field(description="second breakpoint torque [N·m]")

    @model_validator(mode="after")
    def _ordered(self) -> NonlinearStiffness:
        if self.T2 <= self.T1:
            raise ValueError(f"T2 ({self.T2}) must be greater than T1 ({self.T1})")
        return self


class Stribeck(Section):
    """Effect `stribeck` on top of the motor law: extra friction f_st·exp(−(ω/ω_st)²) near zero speed."""

    f_st: NonNegative = Field(description="extra friction at zero speed [N·m]")
    omega_st: Positive = Field(description="Stribeck velocity of the extra friction [rad/s]")


class DirectionAsymmetry(Section):
    """Effect `direction_asymmetry`: friction magnitude + f_dir moving forward, − f_dir moving backward."""

    f_dir: Finite = Field(description="half the difference of friction between directions [N·m]")


class LoadDependentFriction(Section):
    """Effect `load_dependent_friction`: motor friction magnitude grows by c_Ts·|T_s|."""

    c_Ts: NonNegative = Field(description="motor-side friction per output torque transmitted [N·m/N·m]")


class Hysteresis(Section):
    """Effect `hysteresis`: a Dahl element in the transmission adds a torque bounded by ±T_h.

    dT_h/dt = (T_h/delta_h)·(δ̇ − |δ̇|·T_hyst/T_h), δ the transmission deflection: a loop of width ~2·T_h.
    """

    T_h: Positive = Field(description="saturation torque of the hysteresis element [N·m]")
    delta_h: Positive = Field(description="deflection over which the element saturates [rad]")


class ThermalDrift(Section):
    """Effect `thermal_drift`: motor friction scales by 1 + d_th·(1 − exp(−t/tau_th)) over the run."""

    d_th: Annotated[float, Field(gt=-1, allow_inf_nan=False)] = Field(
        description="relative friction change once warm (−0.2: 20 % less) [–]"
    )
    tau_th: Positive = Field(description="warm-up time constant [s]")


class WearDrift(Section):
    """Effect `wear_drift`: motor friction scales by 1 + k_wear·s_m, s_m the motor travel ∫|ω_m|dt
    accumulated since the start of the run (rises as the gear wears in service)."""

    k_wear: Annotated[float, Field(ge=0, allow_inf_nan=False)] = Field(
        description="relative friction rise per radian of motor travel [1/rad]"
    )


Celsius = Annotated[float, Field(gt=-273.15, allow_inf_nan=False)]


class Thermal(Section):
    """Effect `temperature_dependence`: a lumped thermal network of the motor winding and the gear, and
    the motor friction scaled by the gear's temperature T_g through the grease's viscosity law.

    C_w·dT_w/dt = i_a²·R − (T_w − T_g)/R_wg − (T_w − T_amb)/R_wa
    C_g·dT_g/dt = P_f + (T_w − T_g)/R_wg − (T_g − T_amb)/R_ga,  P_f = max(0, F_m·ω_m) + max(0, F_l·ω_l)
    motor friction (Karnopp laws: levels, f_dir and b_m) × exp(−beta_T·(T_g − T_ref))
    """

    T_amb: Celsius = Field(description="ambient temperature [°C]")
    T_ref: Celsius = Field(
        default=25.0, description="reference temperature: the motor friction parameters hold there [°C]"
    )
    beta_T: Finite = Field(
        description="friction's temperature coefficient: friction × exp(−beta_T·(T_g − T_ref)) [1/K]"
    )
    C_w: Positive = Field(description="heat capacity of the motor winding [J/K]")
    C_g: Positive = Field(description="heat capacity of the gear [J/K]")
    R_wg: Positive = Field(description="thermal resistance winding to gear [K/W]")
    R_wa: Positive = Field(description="thermal resistance winding to ambient [K/W]")
    R_ga: Positive = Field(description="thermal resistance gear to ambient [K/W]")
    T_motor0: Celsius | None = Field(
        default=None, description="winding temperature at the start; absent: T_amb [°C]"
    )
    T_gear0: Celsius | None = Field(
        default=None, description="gear temperature at the start; absent: T_amb [°C]"
    )

    @property
    def motor_start_c(self) -> float:
        return self.T_amb if self.T_motor0 is None else self.T_motor0

    @property
    def gear_start_c(self) -> float:
        return self.T_amb if self.T_gear0 is None else self.T_gear0


class Numerics(Section):
    omega_stick_m: Positive = Field(
        default=1e-3,
        description="motor stick band: |ω_m| below it counts as ω_m = 0 (Karnopp) [rad/s]",
    )
    omega_stick_l: Positive = Field(
        default=1e-5,
        description="load stick band: |ω_l| below it counts as ω_l = 0 (Karnopp) [rad/s]",
    )


EFFECT_SECTIONS = (
    "kinematic_error",
    "nonlinear_stiffness",
    "stribeck",
    "direction_asymmetry",
    "load_dependent_friction",
    "hysteresis",
    "thermal_drift",
    "wear_drift",
)


class HarmonicDriveModel(BaseModel):
    """The two-inertia flexible joint with DC motor and friction of docs/MODEL.md, one object for all uses."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = Field(default="unnamed", description="preset or model name")
    description: str = Field(default="", description="what this model is and where its values come from")
    mechanics: Mechanics
    motor: Motor
    transmission: Transmission = Field(default_factory=Transmission)
    motor_friction: MotorFriction
    load_friction: LoadFriction | None = Field(default=None, description="effect `load_side_friction`")
    kinematic_error: KinematicError | None = None
    nonlinear_stiffness: NonlinearStiffness | None = None
    stribeck: Stribeck | None = None
    direction_asymmetry: DirectionAsymmetry | None = None
    load_dependent_friction: LoadDependentFriction | None = None
    hysteresis: Hysteresis | None = None
    thermal_drift: ThermalDrift | None = None
    wear_drift: WearDrift | None = None
    thermal: Thermal | None = Field(default=None, description="effect `temperature_dependence`")
    numerics: Numerics = Field(default_factory=Numerics)

    @model_validator(mode="after")
    def _effects_fit_the_model(self) -> HarmonicDriveModel:
        rigid = self.transmission.K_s is None
        if rigid and self.nonlinear_stiffness is not None:
            raise ValueError("nonlinear_stiffness needs a compliant transmission: set transmission.K_s = K1")
        if rigid and self.hysteresis is not None:
            raise ValueError("hysteresis needs a compliant transmission: set transmission.K_s")
        ns = self.nonlinear_stiffness
        if ns is not None and not math.isclose(ns.K1, self.transmission.K_s or 0.0, rel_tol=1e-9):
            raise ValueError(
                f"transmission.K_s ({self.transmission.K_s}) must equal nonlinear_stiffness.K1 ({ns.K1})"
            )
        smooth = self.motor_friction.motor_law in ("lugre", "dahl")
        karnopp_only = (
            "stribeck",
            "direction_asymmetry",
            "load_dependent_friction",
            "thermal_drift",
            "wear_drift",
        )
        for effect in karnopp_only:
            if smooth and getattr(self, effect) is not None:
                raise ValueError(
                    f"{effect} applies to Karnopp-type motor laws,"
                    f" not motor_law={self.motor_friction.motor_law!r}"
                )
        if smooth and self.thermal is not None and self.thermal.beta_T != 0.0:
            raise ValueError(
                "thermal.beta_T scales Karnopp-type motor laws only: set it to 0 with"
                f" motor_law={self.motor_friction.motor_law!r}"
            )
        return self

    @property
    def rigid(self) -> bool:
        return self.transmission.K_s is None

    @property
    def effects(self) -> list[str]:
        """The vocabulary effects this model carries as sections."""
        present = [e for e in EFFECT_SECTIONS if getattr(self, e) is not None]
        if self.load_friction is not None:
            present.append("load_side_friction")
        if self.thermal is not None:
            present.append("temperature_dependence")
        if not self.rigid:
            present.append("compliance")
        return present

    def to_dict(self) -> dict[str, Any]:
        """Plain data that is itself a valid model file (absent sections and unset fields left out)."""
        return self.model_dump(mode="json", exclude_none=True)

    def content_hash(self) -> str:
        """sha256 of the canonical JSON of the parameters (name and description excluded)."""
        data = self.to_dict()
        data.pop("name", None)
        data.pop("description", None)
        blob = json.dumps(data, sort_keys=True, separators=(",", ":")).encode()
        return hashlib.sha256(blob).hexdigest()[:16]

    def with_updates(self, **sections: Any) -> HarmonicDriveModel:
        """A new validated model with whole sections or top-level fields replaced."""
        data = self.to_dict()
        for key, value in sections.items():
            data[key] = (
                value.model_dump(mode="json", exclude_none=True) if isinstance(value, BaseModel) else value
            )
        return HarmonicDriveModel.model_validate(data)


class ModelFileError(UserInputError):
    """A model file cannot be read or breaks the schema; the message is one line naming file and field."""


PRESET_DIR = card_folder("models")


def preset_names() -> list[str]:
    return sorted(p.stem for p in PRESET_DIR.glob("*.yaml"))


def parse_model(data: Any, source: str = "model") -> HarmonicDriveModel:
    """Validate plain data as a model; errors name `source` and the field."""
    if not isinstance(data, dict):
        raise ModelFileError(
            f"{source}: a model file must be a mapping of sections, got {type(data).__name__}"
        )
    try:
        return HarmonicDriveModel.model_validate(data)
    except ValidationError as exc:
        raise ModelFileError(f"{source}: {describe_validation_error(exc)}") from None


def load_model(name_or_path: str | Path) -> HarmonicDriveModel:
    """Load a preset by name (`seed`) or a YAML/JSON model file by path."""
    path = Path(name_or_path)
    if not path.exists():
        preset = PRESET_DIR / f"{name_or_path}.yaml"
        if preset.exists() and path.suffix == "" and "/" not in str(name_or_path):
            path = preset
        else:
            known = ", ".join(preset_names())
            raise ModelFileError(f"{name_or_path}: no such model file or preset (presets: {known})")
    return parse_model(read_settings(path, "model", ModelFileError), str(path))


def save_model(model: HarmonicDriveModel, path: str | Path) -> Path:
    """Write a model file: JSON for a .json path, YAML otherwise."""
    path = Path(path)
    data = model.to_dict()
    if path.suffix == ".json":
        path.write_text(json.dumps(data, indent=2) + "\n")
    else:
        path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path
