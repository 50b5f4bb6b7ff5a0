"""The in-process simulated rig: the model's plant inside a simulated drive, in virtual or real time."""

from __future__ import annotations

import time

import numpy as np

from model.feedforward import FeedForwardTrack
from model.params import HarmonicDriveModel, load_model
from model.plant import Plant
from rig.config import RigConfig
from rig.interface import SAMPLE_COLUMNS, Block, ControlMode, Rig
from sim_backend.simulated_drive import TRUTH_COLUMNS, SimulatedDrive


class SimRig(Rig):
    """`backend: sim`. Virtual time runs as fast as the compiled loop goes; realtime sleeps to match."""

    def __init__(
        self, config: RigConfig, model: HarmonicDriveModel | None = None, theta_m: float = 0.0
    ) -> None:
        """`model` overrides the config's `model:` file; `theta_m` is the motor angle it starts at [rad]."""
        super().__init__(config)
        self.model: HarmonicDriveModel = model if model is not None else load_model(config.model or "seed")
        self.plant = Plant(self.model)
        self.plant.reset(theta_m=theta_m)
        self.drive = SimulatedDrive(self.plant, config)
        self._wall_start: float | None = None

    source = "sim"

    @property
    def gear_ratio(self) -> float:
        return self.model.mechanics.r

    @property
    def torque_constant_nm_per_a(self) -> float:
        return self.model.motor.K_m

    def _enable(self) -> None:
        self.drive.reset_loops()
        self._wall_start = time.monotonic() - self.t_s

    def _disable(self) -> None:
        return None  # power removed: the plant coasts under friction when next stepped

    def _quick_stop(self) -> None:
        return None  # nothing runs between cycles; run_segment sees the stop request

    supports_feedforward = True

    def record_truth(self, on: bool = True) -> None:
        """Keep the plant's true states and torques of every cycle from now on, beside the samples
        (`truth()`); off by default, when the loop records nothing more. For tests."""
        self.drive.record_truth(on)

    def truth(self) -> dict[str, np.ndarray]:
        """The truth recorded since `record_truth`: TRUTH_COLUMNS of `sim_backend.simulated_drive`, one
        row per cycle run, `t` equal to the samples' `t` [SI units, motor side as the samples]."""
        if self.drive.truth is None:
            raise RuntimeError("truth is not being recorded: call record_truth() first")
        rows = np.concatenate([*self.drive.truth, np.empty((0, len(TRUTH_COLUMNS)))])
        return {name: rows[:, i] for i, name in enumerate(TRUTH_COLUMNS)}

    def _run_cycles(
        self,
        mode: ControlMode,
        setpoint: np.ndarray,
        tau_ext: np.ndarray,
        feedforward: FeedForwardTrack | None = None,
    ) -> tuple[Block, int]:
        rows, code = self.drive.run(mode, setpoint, tau_ext, self.t_s, feedforward)
        self.t_s += rows.shape[0] * self.period_s
        if self.config.pace == "realtime" and self._wall_start is not None:
            ahead = self._wall_start + self.t_s - time.monotonic()
            if ahead > 0:
                time.sleep(ahead)
        return {name: rows[:, i] for i, name in enumerate(SAMPLE_COLUMNS)}, code
