"""The in-process simulated rig: the model's plant inside a simulated drive, in virtual or real time."""

from __future__ import annotations

import time

import numpy as np
from scipy.signal import lfilter

from model.feedforward import FeedForwardTrack
from model.params import HarmonicDriveModel, load_model
from model.plant import Plant
from model.registry import X
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
        self._keep_truth = False
        if self.model.thermal is not None:
            # The probes read the plant's temperature of every cycle, which the drive's truth record
            # carries: kept on, and emptied after each block unless a test asked for the truth.
            self.extra_columns = TEMPERATURE_COLUMNS
            self._probes = TemperatureProbes(config, self._temperatures_c())
            self.drive.record_truth(True)

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
        self._keep_truth = on
        if not self.extra_columns or on:
            self.drive.record_truth(on)

    def truth(self) -> dict[str, np.ndarray]:
        """The truth recorded since `record_truth`: TRUTH_COLUMNS of `sim_backend.simulated_drive`, one
        row per cycle run, `t` equal to the samples' `t` [SI units, motor side as the samples]."""
        if self.drive.truth is None or not self._keep_truth:
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
        block = {name: rows[:, i] for i, name in enumerate(SAMPLE_COLUMNS)}
        if self.extra_columns and self.drive.truth is not None:
            cycles = self.drive.truth[-1]
            plant_c = np.stack([cycles[:, TRUTH_COLUMNS.index(name)] for name in TEMPERATURE_COLUMNS])
            if not self._keep_truth:
                self.drive.truth.clear()
            block.update(self._probes.read(plant_c, self.period_s))
        return block, code

    def _temperatures_c(self) -> np.ndarray:
        """The plant's winding and gear temperatures now [°C] (its states are rises above ambient)."""
        assert self.model.thermal is not None
        ambient = self.model.thermal.T_amb
        return np.array([ambient + self.plant.x[X.RISE_MOTOR], ambient + self.plant.x[X.RISE_GEAR]])


TEMPERATURE_COLUMNS = ("temp_motor", "temp_gear")


class TemperatureProbes:
    """The rig's temperature probes on the winding and the gear housing: each a first-order lag of
    `sensors.temperature_lag_s` behind the plant's temperature, with white noise of
    `sensors.temperature_noise_c`, read from the plant's temperature of every cycle."""

    def __init__(self, config: RigConfig, start_c: np.ndarray) -> None:
        self.lag_s = config.sensors.temperature_lag_s
        self.noise_c = config.sensors.temperature_noise_c
        self.rng = np.random.default_rng([config.sensors.seed, 0x7E])  # its own stream: other noise unchanged
        self.state_c = start_c.astype(float)

    def read(self, plant_c: np.ndarray, period_s: float) -> dict[str, np.ndarray]:
        """What the probes read over a block whose plant temperatures were `plant_c` (a row per column of
        TEMPERATURE_COLUMNS, a value per cycle) [°C]."""
        out = {}
        n = plant_c.shape[1]
        for i, name in enumerate(TEMPERATURE_COLUMNS):
            truth = plant_c[i]
            if self.lag_s > 0.0 and n:
                alpha = 1.0 - np.exp(-period_s / self.lag_s)  # seen[k] = seen[k-1] + α·(truth[k] − seen[k-1])
                seen, _ = lfilter([alpha], [1.0, alpha - 1.0], truth, zi=[(1.0 - alpha) * self.state_c[i]])
            else:
                seen = truth.copy()
            if n:
                self.state_c[i] = seen[-1]
            out[name] = seen + self.noise_c * self.rng.standard_normal(n) if self.noise_c > 0 else seen
        return out
