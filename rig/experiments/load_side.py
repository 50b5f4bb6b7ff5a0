"""What the catalog's load-side tests share: a bench with a load drive and torque transducers, and the
refusal in one line when a bench lacks them; a program played on a rig and gathered into a Run (tests)."""

from __future__ import annotations

from typing import Any

import numpy as np

from rig.config import RigConfig
from rig.experiments.base import ProgramError

TRANSDUCER_COLUMNS = ("tau_in", "tau_out")


def has_load_drive(config: RigConfig) -> bool:
    """A load drive at the output: a simulated bench's `load_drive` section, or a CANopen drive whose
    role is `load` (`canopen.drives`)."""
    if config.load_drive is not None:
        return True
    canopen = config.extra.get("canopen")
    drives = canopen.get("drives", []) if isinstance(canopen, dict) else []
    return any(isinstance(d, dict) and d.get("role") == "load" for d in drives)


def has_transducers(config: RigConfig) -> bool:
    """Torque transducers at the input and output: a simulated bench's `sensors.torque_transducers`, or
    DAQ inputs named `tau_in` and `tau_out`."""
    if config.sensors.torque_transducers:
        return True
    daq = str(config.extra.get("daq", ""))
    return all(name in daq for name in TRANSDUCER_COLUMNS)


def require_bench(name: str, config: RigConfig, load_drive: bool, transducers: bool) -> None:
    """Refuse, in one line naming what is missing, a test the bench cannot run."""
    missing = []
    if load_drive and not has_load_drive(config):
        missing.append(
            "a load drive at the output (`load_drive`, or a `canopen.drives` entry with role load)"
        )
    if transducers and not has_transducers(config):
        missing.append(
            "torque transducers at input and output (`sensors.torque_transducers`, or DAQ tau_in/tau_out)"
        )
    if missing:
        raise ProgramError(
            f"{name} needs {' and '.join(missing)}; rig {config.name!r} has none: use a dynamometer bench"
            " such as sim-dyno"
        )


def require_columns(name: str, columns: Any, needed: tuple[str, ...]) -> None:
    """Refuse to analyze a run that lacks the columns a test reads."""
    absent = [c for c in needed if c not in columns]
    if absent:
        raise ProgramError(
            f"{name}: the run has no {', '.join(absent)} column (recorded by torque transducers)"
        )


def line_at(x: np.ndarray, y: np.ndarray, at: float, half_width: float) -> float:
    """y at x = `at` from a straight line fitted to the points with |x − at| ≤ half_width (NaN if < 3)."""
    near = np.abs(x - at) <= half_width
    if np.count_nonzero(near) < 3:
        return float("nan")
    slope, intercept = np.polyfit(x[near], y[near], 1)
    return float(slope * at + intercept)
