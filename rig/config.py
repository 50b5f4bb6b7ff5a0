"""Rig configuration files (`configs/rigs/*.yaml`): backend, rate, limits, controller gains, sensors.

All angles and speeds here are motor-side (what the encoder and the drive see) unless the name says
`_out` (output side, after the gear).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from model.errors import UserInputError, describe_validation_error
from model.resources import card_folder
from model.settings_file import read_settings

RIG_DIR = card_folder("rigs")


class RigConfigError(UserInputError):
    """A rig file cannot be read or breaks the schema; one line naming the file and the field."""


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Limits(_Section):
    """The safety envelope, checked every cycle: a breach quick-stops the rig and aborts the run."""

    current_a: float = Field(gt=0, description="trip when |measured current| exceeds this [A]")
    voltage_v: float = Field(gt=0, description="trip when |motor voltage| exceeds this [V]")
    velocity_rad_s: float = Field(gt=0, description="trip when |motor speed| exceeds this [rad/s]")
    travel_min_out_rad: float = Field(description="lowest allowed output angle r·θ_m [rad]")
    travel_max_out_rad: float = Field(description="highest allowed output angle r·θ_m [rad]")
    following_error_out_rad: float = Field(
        gt=0, description="trip when the position error at the output exceeds this, position mode [rad]"
    )

    @model_validator(mode="after")
    def _ordered(self) -> Limits:
        if self.travel_max_out_rad <= self.travel_min_out_rad:
            raise ValueError("travel_max_out_rad must be greater than travel_min_out_rad")
        return self


class Control(_Section):
    """The drive's loops: a velocity PI giving current, a position P (+ feed-forward) giving speed."""

    current_limit_a: float = Field(gt=0, description="the drive's current command saturation [A]")
    supply_voltage_v: float = Field(gt=0, description="the drive's bus voltage: the most it can apply [V]")
    max_velocity_rad_s: float = Field(gt=0, description="speed command saturation in position mode [rad/s]")
    velocity_kp: float = Field(ge=0, description="velocity loop proportional gain [A/(rad/s)]")
    velocity_ki: float = Field(ge=0, description="velocity loop integral gain [A/rad]")
    position_kp: float = Field(ge=0, description="position loop gain [(rad/s)/rad]")


class Sensors(_Section):
    """What the measurement chain does to the truth (simulated backends apply it; hardware has it)."""

    encoder_counts_per_rev: int = Field(default=0, ge=0, description="motor encoder counts; 0: ideal")
    velocity_filter_hz: float = Field(
        default=0.0, ge=0, description="low-pass on the encoder-difference speed; 0: none [Hz]"
    )
    current_noise_a: float = Field(default=0.0, ge=0, description="current sensor noise, 1 σ [A]")
    load_sensor_noise_rad: float = Field(default=0.0, ge=0, description="output angle noise, 1 σ [rad]")
    temperature_noise_c: float = Field(
        default=0.0, ge=0, description="temperature probes' noise, 1 σ (a model with `thermal`) [°C]"
    )
    temperature_lag_s: float = Field(
        default=0.0, ge=0, description="temperature probes' first-order time constant; 0: none [s]"
    )
    torque_transducers: bool = Field(
        default=False,
        description="in-line torque transducers at the input and output shafts: the run records "
        "tau_in and tau_out (a bench with a load drive)",
    )
    torque_noise_nm: float = Field(default=0.0, ge=0, description="torque transducers' noise, 1 σ [N·m]")
    seed: int = Field(default=0, description="noise generator seed, for reproducible runs")


class LoadDrive(_Section):
    """The dynamometer's load drive on the output shaft: a torque-controlled motor whose current loop
    follows the segment's load torque within its bandwidth and limit; its rotor adds inertia and
    friction at the output."""

    inertia_kgm2: float = Field(default=0.0, ge=0, description="load rotor inertia at the output [kg·m²]")
    viscous_nms: float = Field(default=0.0, ge=0, description="load bearing viscous friction [N·m·s/rad]")
    coulomb_nm: float = Field(default=0.0, ge=0, description="load bearing Coulomb friction [N·m]")
    torque_constant_nm_a: float = Field(gt=0, description="load motor torque constant at the output [N·m/A]")
    current_bandwidth_hz: float = Field(
        default=0.0, ge=0, description="load drive current loop bandwidth (first order); 0: ideal [Hz]"
    )
    torque_limit_nm: float = Field(gt=0, description="the most torque the load drive applies [N·m]")


class RigConfig(BaseModel):
    """One bench: which backend drives it, at what rate, within which limits."""

    model_config = ConfigDict(extra="allow", frozen=True)

    name: str = Field(description="rig name, recorded with every run")
    unit: str | None = Field(
        default=None,
        description="serial number of the gear unit on the bench: `hdrig trend --unit` follows it",
    )
    backend: str = Field(description="backend registry name: `sim`, `virtual-can`, `canopen`...")
    sample_rate_hz: float = Field(gt=0, le=20000, description="control and sample rate [Hz]")
    model: str | None = Field(default=None, description="model preset or file the simulated plant runs")
    pace: Literal["virtual", "realtime"] = Field(
        default="virtual", description="simulated backends: as fast as possible, or paced to the wall clock"
    )
    sim_dt_s: float = Field(default=1e-4, gt=0, description="simulated backends: integration step [s]")
    limits: Limits
    control: Control
    sensors: Sensors = Field(default_factory=Sensors)
    load_drive: LoadDrive | None = Field(
        default=None, description="a dynamometer's load drive on the output shaft; none: a free output"
    )

    @model_validator(mode="after")
    def _saturation_inside_the_envelope(self) -> RigConfig:
        if self.control.current_limit_a >= self.limits.current_a:
            raise ValueError("control.current_limit_a must be below limits.current_a (the trip level)")
        if self.control.max_velocity_rad_s >= self.limits.velocity_rad_s:
            raise ValueError("control.max_velocity_rad_s must be below limits.velocity_rad_s")
        if self.control.supply_voltage_v > self.limits.voltage_v:
            raise ValueError("control.supply_voltage_v must not exceed limits.voltage_v")
        return self

    @property
    def extra(self) -> dict[str, Any]:
        """Backend-specific sections (bus settings for hardware...), validated by the backend."""
        return dict(self.model_extra or {})


def load_rig_config(path_or_name: str | Path) -> RigConfig:
    """Load a rig file by path, or by name from configs/rigs (`sim`)."""
    path = Path(path_or_name)
    if not path.exists() and (RIG_DIR / f"{path_or_name}.yaml").exists():
        path = RIG_DIR / f"{path_or_name}.yaml"
    if not path.exists():
        known = ", ".join(sorted(p.stem for p in RIG_DIR.glob("*.yaml")))
        raise RigConfigError(f"{path_or_name}: no such rig file (rigs in configs/rigs: {known})")
    data = read_settings(path, "rig", RigConfigError)
    if not isinstance(data, dict):
        raise RigConfigError(f"{path}: a rig file must be a mapping of settings")
    try:
        return RigConfig.model_validate(data)
    except ValidationError as exc:
        raise RigConfigError(f"{path}: {describe_validation_error(exc)}") from None
