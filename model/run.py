"""A run in memory: the one table format for measured, simulated and imported data (docs/INTERFACE.md).

Columns are SI-unit numpy arrays of equal length, one row per sample. Files (Parquet, CSV) are read
and written by `rig.runfile`; this module knows nothing of files.
"""

from __future__ import annotations

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
}
"""The docs/INTERFACE.md columns and their units. Runs may carry further columns."""


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
        for name, values in self.columns.items():
            arr = np.asarray(values, dtype=np.float64)
            if arr.shape != (n,):
                raise RunFormatError(f"{where}: column '{name}' has {arr.shape[0]} rows, 't' has {n}")
            bad = np.flatnonzero(~np.isfinite(arr))
            if bad.size:
                raise RunFormatError(
                    f"{where}: column '{name}' has a non-finite value at row {int(bad[0])} ({arr[bad[0]]})"
                )
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
