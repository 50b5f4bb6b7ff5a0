"""What the CANopen servo driver is told (a rig config's `canopen:` section) and what it writes.

The configuration a drive receives at boot and at each mode change is computed offline, as a list of
SDO writes checked against the drive's EDS/DCF, before anything is sent. The same plan therefore
serves the driver, the tests (asserting the bytes) and a vendor EDS check with no drive attached.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Final, Literal

import canopen
from canopen.objectdictionary import ObjectDictionary, ODVariable
from canopen.objectdictionary.datatypes import SIGNED_TYPES
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from drivers.can_bus import BusSettings
from drivers.cia402 import TARGET_OBJECT, OperationMode
from drivers.drive_modes import TORQUE_OFFSET
from drivers.pdo_layout import PDO_MAX_BITS, PdoEntry, PdoLayout, od_variable
from model.errors import UserInputError, describe_validation_error
from model.resources import card_folder
from rig.config import RigConfig

EDS_DIR = card_folder("eds")

PDO_INVALID = 1 << 31
SYNCHRONOUS = 1  # transmission type: every SYNC (TPDO), applied at the next SYNC (RPDO)
RPDO_COMM, RPDO_MAP, TPDO_COMM, TPDO_MAP = 0x1400, 0x1600, 0x1800, 0x1A00

# What the driver reads back each cycle: statusword and mode display, torque and current (where the
# drive has them) in the first TPDO, position and velocity in the second.
TPDO1_OBJECTS = ((0x6041, 0), (0x6061, 0), (0x6077, 0), (0x6078, 0))
TPDO1_REQUIRED = {0x6041}
TPDO2_OBJECTS = ((0x6064, 0), (0x606C, 0))
REQUIRED_OBJECTS = {
    0x6040: "controlword",
    0x6041: "statusword",
    0x6060: "modes of operation",
    0x6064: "position actual value",
    0x606C: "velocity actual value",
    RPDO_COMM: "RPDO 1 communication",
    RPDO_MAP: "RPDO 1 mapping",
    TPDO_COMM: "TPDO 1 communication",
    TPDO_MAP: "TPDO 1 mapping",
    TPDO_COMM + 1: "TPDO 2 communication",
    TPDO_MAP + 1: "TPDO 2 mapping",
}


class CanopenConfigError(UserInputError):
    """The `canopen:` settings or the EDS cannot drive this servo; one line naming the field or object."""


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ScalingSettings(_Section):
    """From the drive's units to SI. Left empty, a value is read from the drive's object."""

    torque_constant_nm_per_a: float = Field(gt=0, description="motor torque per ampere, for CST targets")
    position_units_per_rev: float | None = Field(
        default=None,
        gt=0,
        description="position units per motor revolution; default: from the drive's factor group"
        " (0x608F, 0x6091, 0x6092, 0x6093, 0x60A8), else 0x608F:1 / 0x608F:2",
    )
    velocity_units_per_rad_s: float | None = Field(
        default=None,
        gt=0,
        description="velocity units per motor rad/s; default: from `velocity_unit`, else the drive's"
        " 0x60A9/0x6094/0x6096, else its DSP 402 v2 notation and dimension (0x608B/0x608C), else position"
        " units per second",
    )
    velocity_unit: Literal["increments_per_s", "rpm"] | None = Field(
        default=None,
        description="the drive's velocity unit, where its EDS has no 0x60A9 to say: position units per"
        " second, or motor revolutions per minute",
    )
    acceleration_units_per_rad_s2: float | None = Field(
        default=None,
        gt=0,
        description="acceleration units per motor rad/s²; default: the drive's 0x60AA/0x6097, else velocity"
        " units per second",
    )
    rated_torque_nm: float | None = Field(
        default=None, gt=0, description="motor rated torque, the 1000 ‰ of torque objects; default: 0x6076"
    )
    rated_current_a: float | None = Field(
        default=None, gt=0, description="motor rated current, the 1000 ‰ of current objects; default: 0x6075"
    )


class DriveEntry(_Section):
    """One more drive on the bus (`canopen.drives`): its role and what differs from the section's."""

    role: Literal["axis", "load"] = Field(description="`axis`: the drive under test; `load`: the dynamometer")
    node_id: int = Field(ge=1, le=127, description="the drive's node id")
    eds: str | None = Field(default=None, description="its EDS or DCF; default: the section's")
    scaling: ScalingSettings | None = Field(default=None, description="its units; default: the section's")
    drive_heartbeat_ms: int | None = Field(default=None, ge=1, le=65535, description="its heartbeat (0x1017)")
    drive_heartbeat_timeout_ms: int | None = Field(default=None, gt=0, description="host side: lost after")
    host_heartbeat_timeout_ms: int | None = Field(
        default=None, ge=1, le=65535, description="its watchdog on the host (0x1016)"
    )
    current_limit_a: float | None = Field(
        default=None, gt=0, description="load: its current saturation (0x6073), motor side [A]"
    )
    current_trip_a: float | None = Field(
        default=None, gt=0, description="load: every drive quick-stops when its |current| exceeds this [A]"
    )
    velocity_limit_rad_s: float | None = Field(
        default=None, gt=0, description="load: its speed saturation (0x607F/0x6080) [rad/s, its own shaft]"
    )
    velocity_trip_rad_s: float | None = Field(
        default=None, gt=0, description="load: every drive quick-stops when its |speed| exceeds this [rad/s]"
    )

    @model_validator(mode="after")
    def _load_limits(self) -> DriveEntry:
        if self.role == "load":
            missing = [
                name
                for name in (
                    "current_limit_a",
                    "current_trip_a",
                    "velocity_limit_rad_s",
                    "velocity_trip_rad_s",
                )
                if getattr(self, name) is None
            ]
            if missing:
                raise ValueError(f"the load drive needs {', '.join(missing)}")
            assert self.current_limit_a is not None and self.current_trip_a is not None
            assert self.velocity_limit_rad_s is not None and self.velocity_trip_rad_s is not None
            if self.current_limit_a >= self.current_trip_a:
                raise ValueError("the load drive's current_limit_a must be below its current_trip_a")
            if self.velocity_limit_rad_s >= self.velocity_trip_rad_s:
                raise ValueError(
                    "the load drive's velocity_limit_rad_s must be below its velocity_trip_rad_s"
                )
        return self

    def drive_limits(self) -> DriveLimits:
        """The saturation written to it (a load drive's)."""
        assert self.current_limit_a is not None and self.velocity_limit_rad_s is not None
        return DriveLimits(self.current_limit_a, self.velocity_limit_rad_s)


class CanopenSettings(BusSettings):
    """A rig config's `canopen:` section: the bus, the node, its EDS, heartbeats, scaling."""

    eds: str = Field(description="the drive's EDS or DCF file: a path, or a file name in configs/eds")
    node_id: int = Field(ge=1, le=127, description="the drive's node id")
    host_node_id: int = Field(default=127, ge=1, le=127, description="node id of the host's heartbeat")
    drive_heartbeat_ms: int = Field(default=100, ge=1, le=65535, description="the drive's heartbeat (0x1017)")
    drive_heartbeat_timeout_ms: int = Field(
        default=350, gt=0, description="host side: the drive is lost after this long without a heartbeat"
    )
    host_heartbeat_ms: int = Field(default=50, gt=0, description="period of the host's own heartbeat")
    host_heartbeat_timeout_ms: int = Field(
        default=200, ge=1, le=65535, description="drive side (0x1016): it stops after this long without one"
    )
    loop_timeout_ms: int = Field(
        default=500,
        gt=0,
        description="a powered drive not cycled for this long (a hung control loop) gets no more host"
        " heartbeats or guarding, so its own watchdog stops it host_heartbeat_timeout_ms later",
    )
    sync_timeout_s: float | None = Field(
        default=None, gt=0, description="wait for the TPDOs answering a SYNC; default: 10 cycles, ≥ 20 ms"
    )
    sdo_timeout_s: float = Field(default=0.5, gt=0, description="SDO response timeout [s]")
    bus_load_max: float = Field(
        default=0.9,
        gt=0,
        le=1,
        description="share of the bit rate the cyclic frames (SYNC, RPDOs, TPDOs) may take, counted at"
        " worst-case bit stuffing; the rest carries heartbeats, EMCYs and SDOs [–]",
    )
    boot_timeout_s: float = Field(default=5.0, gt=0, description="wait for the boot-up message [s]")
    reset_on_boot: bool = Field(default=True, description="send NMT reset node at boot")
    pace: bool = Field(default=True, description="hold the SYNC period in cycle(); off: SYNC on demand")
    accept_drive_runs_on_if_host_dies: bool = Field(
        default=False,
        description="a drive with neither heartbeat consumer (0x1016) nor node guarding (0x100C/0x100D)"
        " keeps its last command when this host hangs or dies; true: the lab accepts that on this bench",
    )
    scaling: ScalingSettings
    drives: tuple[DriveEntry, ...] = Field(
        default=(),
        description="more drives on this bus, each with its role: `load` (a dynamometer drive at the"
        " output, driven in torque mode), `axis` (fields overriding the section's own for the drive under"
        " test); one SYNC for all, each with its own PDOs",
    )

    @model_validator(mode="after")
    def _consistent(self) -> CanopenSettings:
        if self.host_node_id == self.node_id:
            raise ValueError("host_node_id must differ from the drive's node_id")
        roles = [d.role for d in self.drives]
        for role in ("axis", "load"):
            if roles.count(role) > 1:
                raise ValueError(f"drives: more than one drive with role {role!r}")
        ids = [self.role_settings("axis").node_id] + [d.node_id for d in self.drives if d.role == "load"]
        if len(set(ids)) != len(ids):
            raise ValueError(f"drives: node ids {sorted(ids)} are not all different")
        if self.host_node_id in ids:
            raise ValueError(f"host_node_id {self.host_node_id} is also a drive's node_id")
        if self.host_heartbeat_timeout_ms <= self.host_heartbeat_ms:
            raise ValueError("host_heartbeat_timeout_ms must be longer than host_heartbeat_ms")
        if self.drive_heartbeat_timeout_ms <= self.drive_heartbeat_ms:
            raise ValueError("drive_heartbeat_timeout_ms must be longer than drive_heartbeat_ms")
        return self

    @classmethod
    def from_rig_config(cls, config: RigConfig) -> CanopenSettings:
        section = config.extra.get("canopen")
        if not isinstance(section, dict):
            raise CanopenConfigError(f"rig {config.name!r}: a `canopen:` section is needed for this backend")
        try:
            return cls.model_validate(section)
        except ValidationError as exc:
            where = f"rig {config.name!r}: canopen"
            raise CanopenConfigError(f"{where} {describe_validation_error(exc)}") from None

    @property
    def load_entry(self) -> DriveEntry | None:
        """The load drive's entry (its limits), None on a bench without one."""
        return next((d for d in self.drives if d.role == "load"), None)

    @property
    def load(self) -> CanopenSettings | None:
        """The load drive's settings (the bus's, its own node), None on a bench without one."""
        return self.role_settings("load") if any(d.role == "load" for d in self.drives) else None

    def role_settings(self, role: Literal["axis", "load"]) -> CanopenSettings:
        """The settings of the drive with `role`: this section's fields, overridden by its `drives` entry
        (the axis without an entry: the section itself)."""
        entry = next((d for d in self.drives if d.role == role), None)
        if entry is None:
            if role == "load":
                raise CanopenConfigError("canopen.drives: no drive with role 'load' on this bench")
            return self
        limits = {"role", "current_limit_a", "current_trip_a", "velocity_limit_rad_s", "velocity_trip_rad_s"}
        update = entry.model_dump(exclude=limits, exclude_none=True)
        update["scaling"] = entry.scaling if entry.scaling is not None else self.scaling
        return self.model_copy(update={**update, "drives": ()})

    def eds_path(self) -> Path:
        """The EDS/DCF file: as given, or by name from configs/eds."""
        path = Path(self.eds)
        if not path.exists() and not path.is_absolute() and (EDS_DIR / path).exists():
            path = EDS_DIR / path
        if not path.exists():
            raise CanopenConfigError(f"canopen.eds: no such file {self.eds!r} (nor in {EDS_DIR})")
        return path

    def object_dictionary(self) -> ObjectDictionary:
        path = self.eds_path()
        try:
            return canopen.import_od(str(path), self.node_id)
        except (OSError, ValueError, KeyError) as exc:
            raise CanopenConfigError(f"{path}: not a readable EDS/DCF file: {exc}") from None


@dataclass(frozen=True)
class DriveLimits:
    """The saturation the drive is given (0x6072/0x6073/0x607F/0x6080), motor side, SI."""

    current_a: float
    velocity_rad_s: float
    travel_motor_rad: tuple[float, float] | None = None
    """Software position limits (0x607D) [motor rad], where the rig gives them: written only then, as
    a drive's position is where it was switched on unless it is homed."""

    @classmethod
    def from_rig_config(cls, config: RigConfig) -> DriveLimits:
        return cls(config.control.current_limit_a, config.control.max_velocity_rad_s)


@dataclass(frozen=True)
class Scaling:
    """Raw drive units ↔ motor-side SI units."""

    position_units_per_rad: float
    velocity_units_per_rad_s: float
    rated_torque_nm: float
    rated_current_a: float | None
    torque_constant_nm_per_a: float
    acceleration_units_per_rad_s2: float | None = None  # None: velocity units per second
    notes: tuple[str, ...] = ()
    """What the driver had to assume, one line each (an object the drive refused to read): logged."""

    def acceleration_raw(self, rad_s2: float) -> int:
        """An acceleration (0x6083/0x6084/0x6085) in the drive's acceleration units."""
        per_rad_s2 = self.acceleration_units_per_rad_s2
        return round(rad_s2 * (per_rad_s2 if per_rad_s2 is not None else self.velocity_units_per_rad_s))

    def position_rad(self, raw: int) -> float:
        return raw / self.position_units_per_rad

    def position_raw(self, rad: float) -> int:
        return round(rad * self.position_units_per_rad)

    def velocity_rad_s(self, raw: int) -> float:
        return raw / self.velocity_units_per_rad_s

    def velocity_raw(self, rad_s: float) -> int:
        return round(rad_s * self.velocity_units_per_rad_s)

    def torque_nm(self, permille: int) -> float:
        return permille * self.rated_torque_nm / 1000.0

    def torque_permille(self, torque_nm: float) -> int:
        return round(torque_nm / self.rated_torque_nm * 1000.0)

    def current_a(self, permille: int) -> float:
        if self.rated_current_a is None:
            raise ValueError("no rated current: current objects cannot be scaled")
        return permille * self.rated_current_a / 1000.0

    def current_permille(self, current_a: float) -> int:
        if self.rated_current_a is None:
            raise ValueError("no rated current: current objects cannot be scaled")
        return round(current_a / self.rated_current_a * 1000.0)


ObjectReader = Callable[[int, int], int | None]
"""Reads an object's value (index, sub-index) from the drive: SDO upload on a bus, a default offline;
None where the drive refuses the read (an optional object its EDS declares without a value)."""

UNIT_OF_OBJECT: Final = {
    **{index: "position_units_per_rev" for index in (0x608F, 0x6091, 0x6092, 0x6093, 0x60A8)},
    **{index: "velocity_units_per_rad_s" for index in (0x6094, 0x6096, 0x60A9, 0x608B, 0x608C)},
    **{index: "acceleration_units_per_rad_s2" for index in (0x6097, 0x60AA)},
}
"""Which rig setting stands in for a factor-group object the drive refuses to read."""


def resolve_scaling(settings: ScalingSettings, od: ObjectDictionary, read: ObjectReader) -> Scaling:
    """Scaling from the rig file's settings and the drive's objects (read with `read`, values not EDS
    defaults, on a bus). A setting wins where the drive cannot say; where the drive's factor group says
    too, both must agree (else one line naming the field, the objects and their values)."""

    def from_drive(field: str, index: int, sub: int, what: str) -> int:
        if not _has(od, index, sub):
            raise CanopenConfigError(
                f"canopen.scaling.{field} is needed: the EDS has no 0x{index:04X}:{sub:02X} ({what})"
            )
        value = read(index, sub)
        if value is None:
            raise CanopenConfigError(
                f"canopen.scaling.{field} is needed: the drive refused the read of 0x{index:04X}:{sub:02X}"
                f" ({what})"
            )
        if value <= 0:
            raise CanopenConfigError(
                f"canopen.scaling.{field} is needed: the drive's 0x{index:04X}:{sub:02X} ({what}) is {value}"
            )
        return value

    group = FactorGroup.read(od, read)
    notes = _refused_notes(settings, group)
    per_rev = _agreed(
        "position_units_per_rev", settings.position_units_per_rev, group.position_units_per_rev, group
    )
    if per_rev is None:  # the drive's units are its encoder's increments, and it has no resolution
        per_rev = from_drive("position_units_per_rev", 0x608F, 1, "encoder increments") / from_drive(
            "position_units_per_rev", 0x608F, 2, "motor revolutions"
        )
    position_per_rad = per_rev / (2 * math.pi)
    named = settings.velocity_units_per_rad_s is None and settings.velocity_unit is not None
    velocity_per_rad_s = _agreed(
        f"velocity_unit ({settings.velocity_unit})" if named else "velocity_units_per_rad_s",
        _velocity_setting(settings, position_per_rad),
        lambda: group.velocity_units_per_rad_s(position_per_rad),
        group,
    )
    velocity_per_rad_s = velocity_per_rad_s if velocity_per_rad_s is not None else position_per_rad
    acceleration_per_rad_s2 = _agreed(
        "acceleration_units_per_rad_s2",
        settings.acceleration_units_per_rad_s2,
        lambda: group.acceleration_units_per_rad_s2(velocity_per_rad_s),
        group,
    )
    rated_torque = settings.rated_torque_nm
    if rated_torque is None:
        rated_torque = from_drive("rated_torque_nm", 0x6076, 0, "motor rated torque, mN·m") / 1000.0
    rated_current = settings.rated_current_a
    if rated_current is None and _has(od, 0x6075, 0):
        rated_current = from_drive("rated_current_a", 0x6075, 0, "motor rated current, mA") / 1000.0
    return Scaling(
        position_units_per_rad=position_per_rad,
        velocity_units_per_rad_s=velocity_per_rad_s,
        rated_torque_nm=rated_torque,
        rated_current_a=rated_current,
        torque_constant_nm_per_a=settings.torque_constant_nm_per_a,
        acceleration_units_per_rad_s2=acceleration_per_rad_s2,
        notes=notes,
    )


def _refused_notes(settings: ScalingSettings, group: FactorGroup) -> tuple[str, ...]:
    """A line per unit object the drive refused to read, where the rig file gives that unit; a refused
    object whose unit the rig file leaves to the drive is an error naming the setting."""
    notes = []
    for index, sub in group.refused:
        field = UNIT_OF_OBJECT.get(index)
        given = field is not None and (
            getattr(settings, field) is not None
            or (field == "velocity_units_per_rad_s" and settings.velocity_unit is not None)
        )
        what = f"0x{index:04X}:{sub:02X} ({FACTOR_OBJECTS.get(index, 'unit object')})"
        if not given:
            needed = field or "position_units_per_rev"
            raise CanopenConfigError(
                f"canopen.scaling.{needed} is needed: the drive refused the read of {what}"
            )
        notes.append(f"the drive refused the read of {what}: its unit is taken from canopen.scaling.{field}")
    return tuple(notes)


UNITS_REL_TOL: Final = 1e-6
"""Two statements of a unit agree within this: a drive's integer ratios agree exactly; a rig file's
value written to 7 significant digits (83443.0 for 524288 / 2π) is within it."""


def _agreed(
    field: str, setting: float | None, drive_says: Callable[[], float | None], group: FactorGroup
) -> float | None:
    """The setting (it wins), checked against what the drive's objects say where they say it."""
    try:
        drive = drive_says()
    except UnitUnreadError as exc:
        if setting is None:
            raise CanopenConfigError(f"canopen.scaling.{field} is needed: {exc}") from None
        return setting  # the drive's unit is one the driver cannot read: the setting says it
    if setting is None or drive is None:
        return setting if setting is not None else drive
    if not math.isclose(setting, drive, rel_tol=UNITS_REL_TOL):
        raise CanopenConfigError(
            f"canopen.scaling.{field} = {setting:.7g} contradicts the drive: {group.said()} give {drive:.7g}"
            " (per motor revolution, rad/s or rad/s²)"
        )
    return setting


VELOCITY_UNITS_PER_RAD_S: Final[dict[str, float | None]] = {
    "increments_per_s": None,  # the position units' own, per second
    "rpm": 60.0 / (2 * math.pi),
}


def _velocity_setting(settings: ScalingSettings, position_per_rad: float) -> float | None:
    """What the settings say of velocity units: the number, else the unit named, else nothing."""
    if settings.velocity_units_per_rad_s is not None:
        return settings.velocity_units_per_rad_s
    if settings.velocity_unit is None:
        return None
    per_rad_s = VELOCITY_UNITS_PER_RAD_S[settings.velocity_unit]
    return per_rad_s if per_rad_s is not None else position_per_rad


# --- the drive's units: the CiA 402 factor group -------------------------------------------------

SI_ANGLES_PER_TURN: Final = {
    0xB4: ("revolution", 1.0),
    0x41: ("degree", 360.0),
    0x10: ("radian", 2 * math.pi),
    0x40: ("gon", 400.0),
    0x42: ("arcminute", 21_600.0),
    0x43: ("arcsecond", 1_296_000.0),
}
"""CiA 303-2 unit codes of angles, and how many make one turn."""
SI_INCREMENT: Final = 0xB5
SI_SECONDS: Final = {0x03: ("s", 1.0), 0x47: ("min", 60.0), 0x48: ("h", 3600.0)}
SI_SECONDS_SQUARED: Final = 0x57
REVOLUTIONS_PER_TIME: Final = {0xA3: ("rev/s", 1.0), 0xA4: ("rpm", 60.0), 0xA5: ("rev/h", 3600.0)}
"""DSP 402 v2 velocity dimension indices (0x608C) this driver reads, and the seconds of their time unit."""
FACTOR_OBJECTS: Final = {
    0x608F: "position encoder resolution",
    0x6091: "gear ratio",
    0x6092: "feed constant",
    0x6093: "position factor",
    0x6094: "velocity encoder factor",
    0x6096: "velocity factor",
    0x6097: "acceleration factor",
    0x60A8: "SI unit position",
    0x60A9: "SI unit velocity",
    0x60AA: "SI unit acceleration",
    0x608B: "velocity notation index",
    0x608C: "velocity dimension index",
}
"""The objects that set a drive's units: a write to any of them changes what its numbers mean."""


class UnitUnreadError(CanopenConfigError):
    """The drive states a unit the driver cannot turn into radians (a length with no feed constant, a
    code it does not know): a rig setting must say it."""


@dataclass(frozen=True)
class SiUnit:
    """A CiA 402 SI unit object (0x60A8-0x60AA): byte 3 a power of ten (signed), byte 2 the numerator's
    unit, byte 1 the denominator's (CiA 303-2 codes; 0 for none)."""

    index: int
    code: int

    @property
    def exponent(self) -> int:
        prefix = self.code >> 24 & 0xFF
        return prefix - 256 if prefix >= 128 else prefix

    @property
    def numerator(self) -> int:
        return self.code >> 16 & 0xFF

    @property
    def denominator(self) -> int:
        return self.code >> 8 & 0xFF

    def angle_per_turn(self) -> float | None:
        """Units per turn of the driving shaft where the numerator is an angle (10^exponent each)."""
        if self.numerator not in SI_ANGLES_PER_TURN:
            return None
        return SI_ANGLES_PER_TURN[self.numerator][1] * 10.0**-self.exponent

    def __str__(self) -> str:
        return f"0x{self.index:04X} ({FACTOR_OBJECTS[self.index]}) = 0x{self.code:08X}"


@dataclass(frozen=True)
class FactorGroup:
    """What a drive's factor group holds (each None where its dictionary lacks the object), and the units
    it defines, as CiA 402 (IEC 61800-7-201) has them:

    - position: increments = position units × position factor, the position factor being 0x6093, or
      encoder resolution 0x608F (increments : motor turns) × gear ratio 0x6091 (motor turns : driving
      shaft turns) / feed constant 0x6092 (position units : driving shaft turns). So a turn of the motor
      is feed / gear position units. Where 0x60A8 names an angle, the feed follows from it (0.1° is
      3600 per turn); a feed constant left at 1/1 is then not applied, as drives that take the unit from
      0x60A8 do (Nanotec C5-E: feed constant for lengths only). 0x60A8 = increments: the encoder's own.
    - velocity: where 0x60A9 names an angle or increments per time, that unit (angles at the driving
      shaft, after the gear); else 0x6094 (DSP 402 2.0: increments/s per velocity unit); else position
      units per second × velocity factor 0x6096.
    - acceleration: 0x60AA (angle or increments per s²); else velocity units per second × 0x6097.
    - where none of the velocity objects is there, DSP 402 v2's notation and dimension indices: 0x608C
      names revolutions per second, minute or hour (0xA3, 0xA4, 0xA5) and 0x608B its power of ten
      (maxon's EPOS2 says rpm so). Other dimension codes are not read: a rig setting must say them.

    Objects that state one unit twice must agree, else one line naming them and their values.
    """

    resolution: Fraction | None = None  # 0x608F; None also where it holds no positive value
    gear: Fraction | None = None  # 0x6091
    feed: Fraction | None = None  # 0x6092
    position_factor: Fraction | None = None  # 0x6093
    velocity_encoder_factor: Fraction | None = None  # 0x6094
    velocity_factor: Fraction | None = None  # 0x6096
    acceleration_factor: Fraction | None = None  # 0x6097
    si_position: SiUnit | None = None
    si_velocity: SiUnit | None = None
    si_acceleration: SiUnit | None = None
    velocity_dimension: int | None = None  # 0x608C (DSP 402 v2)
    velocity_notation: int = 0  # 0x608B: the power of ten of 0x608C's unit
    refused: tuple[tuple[int, int], ...] = ()
    """Objects the dictionary has whose read the drive refused: (index, sub-index)."""

    @classmethod
    def read(cls, od: ObjectDictionary, read: ObjectReader) -> FactorGroup:
        """The objects the dictionary has, their values read with `read` (from the drive on a bus)."""

        refused: list[tuple[int, int]] = []

        def value(index: int, sub: int) -> int | None:
            if not _has(od, index, sub):
                return None
            read_value = read(index, sub)
            if read_value is None:
                refused.append((index, sub))
            return read_value

        def ratio(index: int) -> Fraction | None:
            numerator, divisor = value(index, 1), value(index, 2)
            if numerator is None or divisor is None:
                return None
            if numerator <= 0 or divisor <= 0:
                if index == 0x608F:
                    return None  # no resolution set: a setting must give it (resolve_scaling says so)
                name = FACTOR_OBJECTS[index]
                raise CanopenConfigError(
                    f"the drive's 0x{index:04X} ({name}) = {numerator}/{divisor} is not a ratio"
                )
            return Fraction(numerator, divisor)

        def si(index: int) -> SiUnit | None:
            code = value(index, 0)
            return SiUnit(index, code & 0xFFFFFFFF) if code else None  # 0: no unit stated

        notation = value(0x608B, 0)
        return cls(
            resolution=ratio(0x608F),
            gear=ratio(0x6091),
            feed=ratio(0x6092),
            position_factor=ratio(0x6093),
            velocity_encoder_factor=ratio(0x6094),
            velocity_factor=ratio(0x6096),
            acceleration_factor=ratio(0x6097),
            si_position=si(0x60A8),
            si_velocity=si(0x60A9),
            si_acceleration=si(0x60AA),
            velocity_dimension=value(0x608C, 0) or None,
            velocity_notation=notation if notation is not None else 0,
            refused=tuple(refused),
        )

    def said(self) -> str:
        """The objects read and their values, for messages."""
        ratios = {
            0x608F: self.resolution,
            0x6091: self.gear,
            0x6092: self.feed,
            0x6093: self.position_factor,
            0x6094: self.velocity_encoder_factor,
            0x6096: self.velocity_factor,
            0x6097: self.acceleration_factor,
        }
        parts = [f"0x{i:04X} = {_ratio_text(r)}" for i, r in ratios.items() if r is not None]
        parts += [str(u) for u in (self.si_position, self.si_velocity, self.si_acceleration) if u is not None]
        if self.velocity_dimension is not None:
            parts.append(f"0x608C = 0x{self.velocity_dimension:02X}, 0x608B = {self.velocity_notation}")
        return ", ".join(parts) if parts else "no factor group"

    def _contradiction(self, what: str) -> CanopenConfigError:
        return CanopenConfigError(f"the drive's units contradict each other: {what}")

    def _feed(self) -> Fraction | float | None:
        """Position units per driving shaft turn: 0x6092, or as 0x60A8's angle says."""
        angle = self.si_position.angle_per_turn() if self.si_position is not None else None
        if angle is None:
            return self.feed
        if self.feed is not None and self.feed != 1 and not _close(self.feed, angle):
            raise self._contradiction(
                f"{self.si_position} is {angle:g} per shaft turn but 0x6092 (feed constant)"
                f" = {_ratio_text(self.feed)}"
            )
        return angle

    def position_units_per_rev(self) -> float | None:
        """Position units per motor turn; None where the drive cannot say (no resolution, no feed)."""
        gear = self.gear if self.gear is not None else Fraction(1)
        increments = self.si_position is not None and self.si_position.numerator == SI_INCREMENT
        if increments:
            if self.position_factor is not None and self.position_factor != 1:
                raise self._contradiction(
                    f"{self.si_position} (increments) but 0x6093 (position factor) ="
                    f" {_ratio_text(self.position_factor)}"
                )
            return _float(self.resolution)
        feed = self._feed()
        if feed is not None:
            per_rev = float(feed / gear)
            if self.position_factor is not None and self.resolution is not None:
                implied = float(self.resolution * gear / feed)  # increments per position unit
                if not _close(self.position_factor, implied):
                    raise self._contradiction(
                        f"0x6093 (position factor) = {_ratio_text(self.position_factor)} but 0x608F ×"
                        f" 0x6091 / feed = {_ratio_text(self.resolution)} × {_ratio_text(gear)}"
                        f" / {_ratio_text(feed)} = {implied:.7g}"
                    )
            return per_rev
        if self.position_factor is not None:
            return _float(self.resolution / self.position_factor if self.resolution is not None else None)
        if self.si_position is not None:
            raise UnitUnreadError(
                f"{self.si_position} names no angle and the drive has no feed constant (0x6092)"
            )
        return _float(self.resolution)

    def velocity_units_per_rad_s(self, position_per_rad: float) -> float | None:
        """Velocity units per motor rad/s; None where the drive has no velocity unit objects (then they
        are position units per second). `position_per_rad`: position units per motor radian."""
        implied = self._si_rate(self.si_velocity, SI_SECONDS)
        if implied is None and self.velocity_encoder_factor is not None:
            if self.resolution is None:
                return None  # increments per turn unknown: 0x6094 cannot be turned into radians
            return float(self.resolution) / (2 * math.pi) / float(self.velocity_encoder_factor)
        if implied is None and self.si_velocity is not None and not self._position_units_per_second():
            raise UnitUnreadError(
                f"{self.si_velocity} is not a unit the driver reads (an angle or increments per s, min or h)"
            )
        if implied is None and self.velocity_factor is None and self.si_velocity is None:
            return self._notation_rate()
        if implied is None:
            return (
                position_per_rad * float(self.velocity_factor) if self.velocity_factor is not None else None
            )
        factor = self.velocity_factor
        if factor is not None and factor != 1 and not _close(factor, implied / position_per_rad):
            raise self._contradiction(
                f"{self.si_velocity} is {implied:.7g} per motor rad/s but position units per second ×"
                f" 0x6096 (velocity factor) = {position_per_rad:.7g} × {_ratio_text(factor)}"
            )
        encoder = self.velocity_encoder_factor
        if encoder is not None and self.resolution is not None:
            per_rad_s = float(self.resolution) / (2 * math.pi)
            if not _close(encoder, per_rad_s / implied):
                raise self._contradiction(
                    f"{self.si_velocity} is {implied:.7g} per motor rad/s but 0x6094 (velocity encoder"
                    f" factor) = {_ratio_text(encoder)} increments/s per unit"
                )
        return implied

    def acceleration_units_per_rad_s2(self, velocity_per_rad_s: float) -> float | None:
        """Acceleration units per motor rad/s²; None where the drive has no acceleration unit objects
        (then they are velocity units per second)."""
        implied = self._si_rate(self.si_acceleration, {SI_SECONDS_SQUARED: ("s²", 1.0)})
        factor = self.acceleration_factor
        if implied is None and self.si_acceleration is not None:
            raise UnitUnreadError(
                f"{self.si_acceleration} is not a unit the driver reads (an angle or increments per s²)"
            )
        if implied is None:
            return velocity_per_rad_s * float(factor) if factor is not None else None
        if factor is not None and factor != 1 and not _close(factor, implied / velocity_per_rad_s):
            raise self._contradiction(
                f"{self.si_acceleration} is {implied:.7g} per motor rad/s² but velocity units per second ×"
                f" 0x6097 (acceleration factor) = {velocity_per_rad_s:.7g} × {_ratio_text(factor)}"
            )
        return implied

    def _notation_rate(self) -> float | None:
        """Velocity units per motor rad/s from 0x608B/0x608C (revolutions per time, 10^0x608B each)."""
        if self.velocity_dimension is None:
            return None
        if self.velocity_dimension not in REVOLUTIONS_PER_TIME:
            raise UnitUnreadError(
                f"0x608C (velocity dimension index) = 0x{self.velocity_dimension:02X} is not a unit the"
                " driver reads (revolutions per s, min or h: 0xA3, 0xA4, 0xA5)"
            )
        seconds = REVOLUTIONS_PER_TIME[self.velocity_dimension][1]
        gear = float(self.gear) if self.gear is not None else 1.0
        return seconds / (2 * math.pi) / gear * 10.0**-self.velocity_notation

    def _position_units_per_second(self) -> bool:
        """0x60A9 names the position unit of 0x60A8 per second (a length, say): position units/s."""
        velocity, position = self.si_velocity, self.si_position
        if velocity is None or position is None or velocity.denominator != 0x03:
            return False
        return (velocity.numerator, velocity.exponent) == (position.numerator, position.exponent)

    def _si_rate(self, unit: SiUnit | None, times: dict[int, tuple[str, float]]) -> float | None:
        """Units per motor rad/s (or rad/s²) of an angle or increments per time unit; None for others."""
        if unit is None or unit.denominator not in times:
            return None
        per_time = times[unit.denominator][1]  # seconds in the time unit (its square for accelerations)
        angle = unit.angle_per_turn()
        if angle is not None:  # at the driving shaft: a motor turn is 1/gear of one
            gear = float(self.gear) if self.gear is not None else 1.0
            return angle * per_time / gear / (2 * math.pi)
        if unit.numerator == SI_INCREMENT and self.resolution is not None:
            return float(self.resolution) * 10.0**-unit.exponent * per_time / (2 * math.pi)
        return None


def _close(a: Fraction | float, b: Fraction | float) -> bool:
    return math.isclose(float(a), float(b), rel_tol=UNITS_REL_TOL)


def _float(value: Fraction | None) -> float | None:
    return float(value) if value is not None else None


def _ratio_text(value: Fraction | float) -> str:
    if isinstance(value, Fraction):
        return f"{value.numerator}/{value.denominator}"
    return f"{value:.7g}"


Watchdog = Literal["heartbeat consumer", "node guarding", "none"]


def host_watchdog(od: ObjectDictionary) -> Watchdog:
    """How the drive can notice this host is gone: 0x1016 where it has one, else node guarding."""
    if _has(od, 0x1016, 1):
        return "heartbeat consumer"
    if _has(od, 0x100C) and _has(od, 0x100D):
        return "node guarding"
    return "none"


def guarding(settings: CanopenSettings) -> tuple[int, int]:
    """Node guarding: (guard time 0x100C [ms], life time factor 0x100D) for the host's heartbeat
    period and timeout: the host guards every period, the drive stops after about the timeout."""
    factor = max(2, min(255, math.ceil(settings.host_heartbeat_timeout_ms / settings.host_heartbeat_ms)))
    return settings.host_heartbeat_ms, factor


def _has(od: ObjectDictionary, index: int, subindex: int = 0) -> bool:
    try:
        od_variable(od, index, subindex)
    except KeyError:
        return False
    return True


@dataclass(frozen=True)
class SdoWrite:
    """One expedited SDO download of the configuration: where, what value, and why."""

    index: int
    subindex: int
    value: int
    why: str

    def data(self, od: ObjectDictionary) -> bytes:
        """The bytes of the download, sized by the object's data type."""
        return od_variable(od, self.index, self.subindex).encode_raw(self.value)

    def __str__(self) -> str:
        return f"0x{self.index:04X}:{self.subindex:02X} = {self.value} ({self.why})"


def frame_bits(data_bytes: int) -> int:
    """Bits on the wire of a CAN 2.0A data frame of `data_bytes` bytes, at worst: 47 of frame and
    interframe space, 8 a byte, and the stuff bits its 34 + 8n stuffed bits can need (one every 4)."""
    return 47 + 8 * data_bytes + (34 + 8 * data_bytes - 1) // 4


@dataclass(frozen=True)
class BusLoad:
    """What the cyclic frames of one control cycle take of the bus."""

    bits_per_cycle: int
    period_s: float
    bitrate: int

    @property
    def share(self) -> float:
        """Of the bit rate [–]."""
        return self.bits_per_cycle / self.period_s / self.bitrate

    def __str__(self) -> str:
        return (
            f"bus load {self.share:.0%} ({self.bits_per_cycle} bits a cycle at {1 / self.period_s:g} Hz,"
            f" {self.bitrate / 1000:g} kbit/s)"
        )


def bus_load(plans: Sequence[PdoPlan], period_s: float, bitrate: int) -> BusLoad:
    """The bus load of one SYNC (no data) and each node's RPDO and TPDOs every cycle, at worst-case bit
    stuffing. Heartbeats, guarding and SDOs (a few frames a second) are left to the margin the limit keeps.
    """
    bits = frame_bits(0)
    for plan in plans:
        bits += sum(
            frame_bits(layout.length) for layout in (plan.rpdo, plan.tpdo1, plan.tpdo2) if layout.entries
        )
    return BusLoad(bits, period_s, bitrate)


def check_bus_load(load: BusLoad, limit: float, where: str) -> None:
    """One line when the cyclic frames would take more of the bus than `limit` (canopen.bus_load_max)."""
    if load.share > limit:
        raise CanopenConfigError(
            f"{where}: {load} is above canopen.bus_load_max = {limit:.0%}: lower the rig's sample_rate_hz,"
            " raise canopen.bitrate or drive fewer nodes on this bus"
        )


@dataclass(frozen=True)
class PdoPlan:
    """The mapping the driver gives the drive: COB-ID and layout of RPDO 1 and TPDOs 1-2."""

    rpdo: PdoLayout
    tpdo1: PdoLayout
    tpdo2: PdoLayout
    node_id: int

    @property
    def rpdo_cob_id(self) -> int:
        return 0x200 + self.node_id

    @property
    def tpdo_cob_ids(self) -> tuple[int, int]:
        return 0x180 + self.node_id, 0x280 + self.node_id


def tpdo_layouts(od: ObjectDictionary) -> tuple[PdoLayout, PdoLayout]:
    """The feedback TPDOs: the objects of TPDO1_OBJECTS/TPDO2_OBJECTS the drive has."""
    missing = sorted(i for i in REQUIRED_OBJECTS if i not in od)
    if missing:
        names = ", ".join(f"0x{i:04X} ({REQUIRED_OBJECTS[i]})" for i in missing)
        raise CanopenConfigError(f"the EDS lacks what a CiA 402 servo needs here: {names}")
    tpdo1 = PdoLayout.of_objects(od, [o for o in TPDO1_OBJECTS if _has(od, *o)])
    return tpdo1, PdoLayout.of_objects(od, list(TPDO2_OBJECTS))


def rpdo_layout(od: ObjectDictionary, mode: OperationMode, torque_offset: bool = False) -> PdoLayout:
    """RPDO 1 for a mode: controlword + the mode's target (+ the torque offset 0x60B2, for a model's
    feed-forward: 16 + 32 + 16 bits in CSP)."""
    if mode not in TARGET_OBJECT:
        raise CanopenConfigError(f"{mode.name} takes no target every cycle: it is not driven here")
    objects = [(0x6040, 0), TARGET_OBJECT[mode], *([TORQUE_OFFSET] if torque_offset else [])]
    for index, sub in objects[1:]:
        if not _has(od, index, sub):
            where = f"0x{index:04X}:{sub:02X}"
            raise CanopenConfigError(f"the EDS has no {where}, needed in RPDO 1 for {mode.name}")
    return PdoLayout.of_objects(od, objects)


def _pdo_writes(
    od: ObjectDictionary, comm: int, mapping: int, cob_id: int, layout: PdoLayout
) -> list[SdoWrite]:
    """Remap one PDO the CiA 301 way: invalidate, set type, clear, fill, count, validate."""
    name = f"{'RPDO' if comm < TPDO_COMM else 'TPDO'} {comm % 0x200 + 1}"
    writes = [SdoWrite(comm, 1, cob_id | PDO_INVALID, f"{name} off while remapped")]
    if _has(od, comm, 2):
        writes.append(SdoWrite(comm, 2, SYNCHRONOUS, f"{name} synchronous"))
    writes.append(SdoWrite(mapping, 0, 0, f"{name} mapping cleared"))
    writes += [
        SdoWrite(mapping, n, entry.mapping_value, f"{name} maps {entry}")
        for n, entry in enumerate(layout.entries, start=1)
    ]
    writes.append(SdoWrite(mapping, 0, len(layout.entries), f"{name} has {len(layout.entries)} objects"))
    writes.append(SdoWrite(comm, 1, cob_id, f"{name} on at COB-ID 0x{cob_id:03X}"))
    return writes


def _pdo_numbers(od: ObjectDictionary, comm_base: int) -> list[int]:
    return [n for n in range(512) if comm_base + n in od]


def boot_plan(
    od: ObjectDictionary,
    settings: CanopenSettings,
    limits: DriveLimits,
    scaling: Scaling,
    period_s: float,
) -> list[SdoWrite]:
    """Everything written at boot (in PRE-OPERATIONAL), in order; objects the drive lacks are skipped.

    Heartbeats both ways, the SYNC period, the limits, every PDO off, then the two feedback TPDOs on.
    RPDO 1 follows the mode (`mode_plan`).
    """
    writes: list[SdoWrite] = []
    if _has(od, 0x1017):
        writes.append(SdoWrite(0x1017, 0, settings.drive_heartbeat_ms, "drive heartbeat period, ms"))
    watchdog = host_watchdog(od)
    if watchdog == "heartbeat consumer":
        consumer = settings.host_node_id << 16 | settings.host_heartbeat_timeout_ms
        writes.append(SdoWrite(0x1016, 1, consumer, f"stop without host {settings.host_node_id}'s heartbeat"))
    elif watchdog == "node guarding":
        guard_ms, factor = guarding(settings)
        writes.append(SdoWrite(0x100C, 0, guard_ms, "guard time, ms: the host guards this often"))
        life = f"life time factor: stop after {guard_ms * factor} ms unguarded"
        writes.append(SdoWrite(0x100D, 0, factor, life))
    if _has(od, 0x1006):
        writes.append(SdoWrite(0x1006, 0, round(period_s * 1e6), "SYNC period, µs"))
    writes += _limit_writes(od, limits, scaling)
    tpdo1, tpdo2 = tpdo_layouts(od)
    unused = [RPDO_COMM + n for n in _pdo_numbers(od, RPDO_COMM)]
    unused += [TPDO_COMM + n for n in _pdo_numbers(od, TPDO_COMM)[2:]]
    for comm in unused:
        name = f"{'RPDO' if comm < TPDO_COMM else 'TPDO'} {comm % 0x200 + 1}"
        writes.append(SdoWrite(comm, 1, _default_cob_id(od, comm) | PDO_INVALID, f"{name} off"))
    writes += _pdo_writes(od, TPDO_COMM, TPDO_MAP, 0x180 + settings.node_id, tpdo1)
    writes += _pdo_writes(od, TPDO_COMM + 1, TPDO_MAP + 1, 0x280 + settings.node_id, tpdo2)
    return writes


def mode_plan(
    od: ObjectDictionary, node_id: int, mode: OperationMode, torque_offset: bool = False
) -> list[SdoWrite]:
    """What a mode change writes: RPDO 1 remapped to controlword + target (+ 0x60B2), then the mode."""
    layout = rpdo_layout(od, mode, torque_offset)
    writes = _pdo_writes(od, RPDO_COMM, RPDO_MAP, 0x200 + node_id, layout)
    writes.append(SdoWrite(0x6060, 0, int(mode), f"mode of operation {mode.name}"))
    return writes


def _default_cob_id(od: ObjectDictionary, comm: int) -> int:
    default = od_variable(od, comm, 1).default
    return int(default) & 0x7FF if isinstance(default, int) else 0


def _limit_writes(od: ObjectDictionary, limits: DriveLimits, scaling: Scaling) -> list[SdoWrite]:
    """The rig's saturation in the drive's units, each within the object's declared range or refused."""
    writes = _unchecked_limit_writes(od, limits, scaling)
    for write in writes:
        var = od_variable(od, write.index, write.subindex)
        low, high = declared_range(var)
        if not low <= write.value <= high:
            where = f"0x{write.index:04X}" + (f":{write.subindex:02X}" if write.subindex else "")
            raise CanopenConfigError(
                f"{where} ({var.name}) = {write.value} is outside its declared range"
                f" [{low}, {high}]: {write.why}; lower `control:` or check `canopen.scaling`"
            )
    return writes


def declared_range(var: ODVariable) -> tuple[int, int]:
    """The values an object takes: its EDS LowLimit/HighLimit, within what its data type holds."""
    bits = len(var)
    signed = var.data_type in SIGNED_TYPES
    low, high = (-(1 << bits - 1), (1 << bits - 1) - 1) if signed else (0, (1 << bits) - 1)
    if isinstance(var.min, int):
        low = max(low, var.min)
    if isinstance(var.max, int):
        high = min(high, var.max)
    return low, high


def _unchecked_limit_writes(od: ObjectDictionary, limits: DriveLimits, scaling: Scaling) -> list[SdoWrite]:
    writes = []
    if _has(od, 0x6072):
        torque = scaling.torque_permille(limits.current_a * scaling.torque_constant_nm_per_a)
        writes.append(SdoWrite(0x6072, 0, torque, f"max torque ‰ = {limits.current_a:g} A"))
    if _has(od, 0x6073) and scaling.rated_current_a is not None:
        current = scaling.current_permille(limits.current_a)
        writes.append(SdoWrite(0x6073, 0, current, f"max current ‰ = {limits.current_a:g} A"))
    if _has(od, 0x607F):
        velocity = scaling.velocity_raw(limits.velocity_rad_s)
        writes.append(SdoWrite(0x607F, 0, velocity, f"max profile velocity, {limits.velocity_rad_s:g} rad/s"))
    if limits.travel_motor_rad is not None and _has(od, 0x607D, 2):
        low_rad, high_rad = limits.travel_motor_rad
        for sub, rad, which in ((1, low_rad, "min"), (2, high_rad, "max")):
            raw = scaling.position_raw(rad)
            writes.append(SdoWrite(0x607D, sub, raw, f"{which} position limit = {rad:g} rad at the motor"))
    if _has(od, 0x6080):
        rpm = round(limits.velocity_rad_s * 60 / (2 * math.pi))
        writes.append(SdoWrite(0x6080, 0, rpm, f"max motor speed, rpm = {limits.velocity_rad_s:g} rad/s"))
    return writes


def check_plan(od: ObjectDictionary, plan: Sequence[SdoWrite]) -> list[str]:
    """What in a plan the object dictionary refuses: missing, read-only, out of range, unmappable.

    An empty list means every write names an existing writable object with a value its type holds and
    every mapping entry a PDO-mappable object, within 64 bits per PDO.
    """
    problems: list[str] = []
    mapped_bits: dict[int, int] = {}
    for write in plan:
        try:
            var = od_variable(od, write.index, write.subindex)
        except KeyError:
            problems.append(f"{write}: no such object")
            continue
        if not var.writable:
            problems.append(f"{write}: not writable ({var.access_type})")
        problems += _range_problems(var, write)
        if is_mapping_object(write.index) and write.subindex > 0:
            entry = PdoEntry.from_mapping_value(write.value)
            try:
                mapped = od_variable(od, entry.index, entry.subindex)
            except KeyError:
                problems.append(f"{write}: maps an object the EDS lacks")
                continue
            if not mapped.pdo_mappable:
                problems.append(f"{write}: 0x{entry.index:04X} is not PDO-mappable")
            mapped_bits[write.index] = mapped_bits.get(write.index, 0) + entry.bits
    problems += [
        f"0x{index:04X}: {bits} bits mapped, more than {PDO_MAX_BITS}"
        for index, bits in mapped_bits.items()
        if bits > PDO_MAX_BITS
    ]
    return problems


def is_mapping_object(index: int) -> bool:
    """An RPDO (0x1600-0x17FF) or TPDO (0x1A00-0x1BFF) mapping parameter."""
    return RPDO_MAP <= index < RPDO_MAP + 0x200 or TPDO_MAP <= index < TPDO_MAP + 0x200


def _range_problems(var: ODVariable, write: SdoWrite) -> list[str]:
    try:
        var.encode_raw(write.value)
    except Exception as exc:  # struct.error, OverflowError, ValueError: what canopen raises per type
        return [f"{write}: does not fit {var.name!r}: {exc}"]
    low, high = var.min, var.max
    if (low is not None and write.value < low) or (high is not None and write.value > high):
        return [f"{write}: outside [{low}, {high}] of {var.name!r}"]
    return []
