"""A run in memory: the one table format for measured, simulated and imported data (docs/INTERFACE.md).

Columns are SI-unit numpy arrays of equal length, one row per sample. Files (Parquet, CSV) are read
and written by `rig.store.runfile`; this module knows nothing of files.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from model.errors import UserInputError

INPUT_COLUMNS = ("u", "i_cmd", "tau_m")
"""Input columns in order of preference when a run is replayed: voltage, current, torque."""

KNOWN_COLUMNS = {
    "t": "s",
    "u": "V",
    "i_cmd": "A",
    "tau_m": "N·m",
    "tau_ext": "N·m",
    "theta_m": "rad",
    "omega_m": "rad/s",
    "theta_l": "rad",
    "omega_l": "rad/s",
    "i_a": "A",
    "tau_in": "N·m",
    "tau_out": "N·m",
    "temp_gear": "°C",
    "temp_motor": "°C",
}
"""The docs/INTERFACE.md columns and their units. Runs may carry further columns."""

PLAUSIBLE_MAGNITUDE = {
    "t": 1e10,  # s: Unix-epoch time stamps (1.7e9 s) pass
    "u": 1e4,  # V
    "i_cmd": 1e4,  # A
    "i_a": 1e4,  # A
    "tau_m": 1e5,  # N·m
    "tau_ext": 1e6,  # N·m: the largest harmonic drives hold ~1e4 N·m at the output
    "theta_m": 1e9,  # rad: 10 h at 600 rad/s is 2e7 rad
    "theta_l": 1e9,  # rad
    "omega_m": 1e5,  # rad/s: ~1 million rpm
    "omega_l": 1e5,  # rad/s
    "tau_in": 1e5,  # N·m, as tau_m
    "tau_out": 1e6,  # N·m, as tau_ext
    "temp_gear": 1e4,  # °C: beyond any grease; a unit error (mK, K·1000) lands above
    "temp_motor": 1e4,  # °C
}
"""Beyond these magnitudes a known column's value is no measurement of a rig but a unit error or a
damaged cell (a current of 1e300 A): refused, not fitted. Far above any rig, so no real run trips them."""
MAX_SAMPLE_RATE_HZ = 1e7
"""A `sample_rate_hz` in a run's metadata must lie in (0, this]."""


class RunFormatError(UserInputError):
    """A run table breaks the run format; the message names the column and what is wrong."""


@dataclass
class Run:
    """One run: named columns of equal length plus metadata (docs/INTERFACE.md keys and free extras)."""

    columns: dict[str, np.ndarray]
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def t(self) -> np.ndarray:
        return self.columns["t"]

    def __len__(self) -> int:
        return len(self.columns["t"]) if "t" in self.columns else 0

    def __getitem__(self, name: str) -> np.ndarray:
        return self.columns[name]

    def __contains__(self, name: object) -> bool:
        return name in self.columns

    @property
    def input_column(self) -> str | None:
        """The column that drives the plant (`u`, `i_cmd` or `tau_m`), or None if there is none.

        A run that records several (a rig logs both the voltage and the current command) names the
        one that drove it in its `input_column` metadata; otherwise the first present in INPUT_COLUMNS.
        """
        named = self.meta.get("input_column")
        if named in INPUT_COLUMNS and named in self.columns:
            return str(named)
        return next((c for c in INPUT_COLUMNS if c in self.columns), None)

    @property
    def sample_rate_hz(self) -> float:
        if "sample_rate_hz" in self.meta:
            return float(self.meta["sample_rate_hz"])
        return float(1.0 / np.median(np.diff(self.t)))

    def validate(self, where: str = "run") -> Run:
        """Check the format and fill in missing velocities; raise RunFormatError naming `where`."""
        if "t" not in self.columns:
            raise RunFormatError(f"{where}: required column 't' is missing")
        if "theta_m" not in self.columns:
            raise RunFormatError(f"{where}: required column 'theta_m' is missing")
        n = len(self.columns["t"])
        if n < 2:
            raise RunFormatError(f"{where}: needs at least 2 samples, has {n}")
        check_sample_rate(self.meta, where)
        for name, values in self.columns.items():
            arr = np.asarray(values, dtype=np.float64)
            if arr.shape != (n,):
                raise RunFormatError(f"{where}: column '{name}' has {arr.shape[0]} rows, 't' has {n}")
            check_values(where, name, arr)
            self.columns[name] = arr
        steps = np.diff(self.columns["t"])
        bad = np.flatnonzero(steps <= 0)
        if bad.size:
            i = int(bad[0]) + 1
            raise RunFormatError(
                f"{where}: column 't' must be strictly increasing; row {i} has t={self.columns['t'][i]!r}"
                f" after t={self.columns['t'][i - 1]!r}"
            )
        self._derive_velocities()
        return self

    def _derive_velocities(self) -> None:
        # Central differences: second-order accurate and without the half-sample lag of a backward one.
        t = self.columns["t"]
        for pos, vel in (("theta_m", "omega_m"), ("theta_l", "omega_l")):
            if pos in self.columns and vel not in self.columns:
                self.columns[vel] = np.gradient(self.columns[pos], t)


def check_values(
    where: str, name: str, values: np.ndarray, first_row: int = 0, plausible: bool = True
) -> None:
    """Refuse a column's non-finite values and (with `plausible`, as a run is read) a known column's
    values beyond its PLAUSIBLE_MAGNITUDE; one line naming the column, the row (counted from
    `first_row`) and the limit."""
    bad = np.flatnonzero(~np.isfinite(values))
    if bad.size:
        row = first_row + int(bad[0])
        raise RunFormatError(
            f"{where}: column '{name}' has a non-finite value at row {row} ({values[bad[0]]})"
        )
    limit = PLAUSIBLE_MAGNITUDE.get(name) if plausible else None
    if limit is not None:
        bad = np.flatnonzero(np.abs(values) > limit)
        if bad.size:
            row, unit = first_row + int(bad[0]), KNOWN_COLUMNS[name]
            raise RunFormatError(
                f"{where}: column '{name}' row {row} is {values[bad[0]]:g} {unit}, beyond any rig"
                f" (|{name}| ≤ {limit:g} {unit}): a unit error or a damaged value"
            )


def check_sample_rate(meta: dict[str, Any], where: str) -> None:
    """A `sample_rate_hz` in the metadata, if any, is a number in (0, MAX_SAMPLE_RATE_HZ] Hz."""
    if "sample_rate_hz" not in meta:
        return
    rate = meta["sample_rate_hz"]
    number = isinstance(rate, (int, float)) and not isinstance(rate, bool)
    if not (number and math.isfinite(rate) and 0 < rate <= MAX_SAMPLE_RATE_HZ):
        raise RunFormatError(
            f"{where}: metadata sample_rate_hz is {rate!r}; it must be a number of Hz in"
            f" (0, {MAX_SAMPLE_RATE_HZ:g}]"
        )
