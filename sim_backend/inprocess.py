"""The in-process simulated rig: the model's plant inside a simulated drive, in virtual or real time."""

from __future__ import annotations

import time
from typing import TypeVar

import numpy as np

from model.feedforward import FeedForwardTrack
from model.params import HarmonicDriveModel, load_model
from model.plant import Plant
from model.registry import X
from rig.config import RigConfig
from rig.interface import SAMPLE_COLUMNS, Block, ControlMode, Rig
from sim_backend.simulated_drive import TRUTH_COLUMNS, SimulatedDrive

Torque = TypeVar("Torque", float, np.ndarray)
"""A torque per row, or one cycle's [N·m]."""


class SimRig(Rig):
    """`backend: sim`. Virtual time runs as fast as the compiled loop goes; realtime sleeps to match."""

    def __init__(
        self, config: RigConfig, model: HarmonicDriveModel | None = None, theta_m: float = 0.0
    ) -> None:
        """`model` overrides the config's `model:` file; `theta_m` is the motor angle it starts at [rad]."""
        super().__init__(config)
        chosen = model if model is not None else load_model(config.model or "seed")
        self.gear_model = chosen
        """The gear's model as given; `model` is what the plant runs (a load drive's rotor added)."""
        self.model: HarmonicDriveModel = with_load_drive(chosen, config)
        self.plant = Plant(self.model)
        self.plant.reset(theta_m=theta_m)
        self.drive = SimulatedDrive(self.plant, config)
        self._wall_start: float | None = None
        self._keep_truth = False
        extra: tuple[str, ...] = ()
        if self.model.thermal is not None:
            # The probes read the plant's temperature of every cycle, which the drive's truth record
            # carries: kept on, and emptied after each block unless a test asked for the truth.
            extra += TEMPERATURE_COLUMNS
            self._probes = TemperatureProbes(config, self._temperatures_c())
        if config.sensors.torque_transducers:
            extra += TORQUE_COLUMNS
            self._transducers = TorqueTransducers(config, self.model, chosen)
        if extra:
            self.extra_columns = extra
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
        # Power removed: the plant coasts under friction when next stepped, the load drive unloaded.
        self.drive.load_state[:] = 0.0

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
            if not self._keep_truth:
                self.drive.truth.clear()
            if TEMPERATURE_COLUMNS[0] in self.extra_columns:
                plant_c = np.stack([cycles[:, TRUTH_COLUMNS.index(name)] for name in TEMPERATURE_COLUMNS])
                block.update(self._probes.read(plant_c, self.period_s))
            if TORQUE_COLUMNS[0] in self.extra_columns:
                block.update(self._transducers.read(cycles))
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
                from scipy.signal import lfilter  # here, not above: the twins' process imports this module

                alpha = 1.0 - np.exp(-period_s / self.lag_s)  # seen[k] = seen[k-1] + α·(truth[k] − seen[k-1])
                seen, _ = lfilter([alpha], [1.0, alpha - 1.0], truth, zi=[(1.0 - alpha) * self.state_c[i]])
            else:
                seen = truth.copy()
            if n:
                self.state_c[i] = seen[-1]
            out[name] = seen + self.noise_c * self.rng.standard_normal(n) if self.noise_c > 0 else seen
        return out


def with_load_drive(model: HarmonicDriveModel, config: RigConfig) -> HarmonicDriveModel:
    """The model the plant runs on a bench with a load drive: the drive's rotor inertia adds to the
    output's `J_l` (its bearing friction is applied by the simulated drive, beside the load torque)."""
    if config.load_drive is None or config.load_drive.inertia_kgm2 == 0.0:
        return model
    mechanics = model.mechanics.model_copy(
        update={"J_l": model.mechanics.J_l + config.load_drive.inertia_kgm2}
    )
    return model.model_copy(update={"mechanics": mechanics})


TORQUE_COLUMNS = ("tau_in", "tau_out")


class TorqueTransducers:
    """In-line torque transducers (`sensors.torque_transducers`), each with white noise of
    `sensors.torque_noise_nm`, read from the plant's torques averaged over every cycle.

    `tau_in` sits on the input shaft, between the motor (with the wave generator: the model's `J_m`) and
    the gear: the torque the gear takes in, r·T_s + F_m. `tau_out` sits on the output shaft, between the
    gear's output (its bearing and the model's `J_l`) and the load drive's rotor: T_s − F_l less what
    accelerates the gear's output inertia. In steady motion these are the motor's torque and the load's.
    The shafts are taken as stiff beside the gear (K_s): their twist is not modelled.
    """

    def __init__(
        self, config: RigConfig, plant_model: HarmonicDriveModel, gear_model: HarmonicDriveModel
    ) -> None:
        self.noise_nm = config.sensors.torque_noise_nm
        self.rng = np.random.default_rng([config.sensors.seed, 0x70])  # its own stream: other noise unchanged
        self.r = plant_model.mechanics.r
        # Share of the output's net torque that accelerates the gear's own output inertia (the rest
        # accelerates the load drive's rotor, beyond the transducer).
        self.gear_share = gear_model.mechanics.J_l / plant_model.mechanics.J_l

    def truth(self, cycles: np.ndarray) -> dict[str, np.ndarray]:
        """The transducers' true torques for truth rows (TRUTH_COLUMNS) [N·m]."""
        t_s = cycles[:, TRUTH_COLUMNS.index("t_s")]
        f_m = cycles[:, TRUTH_COLUMNS.index("f_m")]
        f_l = cycles[:, TRUTH_COLUMNS.index("f_l")]
        tau_ext = cycles[:, TRUTH_COLUMNS.index("tau_ext")]
        tau_in, tau_out = self.torques(t_s, f_m, f_l, tau_ext)
        return {"tau_in": tau_in, "tau_out": tau_out}

    def torques(self, t_s: Torque, f_m: Torque, f_l: Torque, tau_ext: Torque) -> tuple[Torque, Torque]:
        """(τ_in, τ_out) from the plant's shaft torque, motor and load friction and load torque, per row or
        for one cycle's floats (the CANopen twin's DAQ reads one a SYNC) [N·m]."""
        return self.r * t_s + f_m, t_s - f_l - self.gear_share * (t_s - f_l - tau_ext)

    def read(self, cycles: np.ndarray) -> dict[str, np.ndarray]:
        """What the transducers read over a block of truth rows [N·m]."""
        out = self.truth(cycles)
        if self.noise_nm > 0:
            for name in TORQUE_COLUMNS:
                out[name] = out[name] + self.noise_nm * self.rng.standard_normal(out[name].shape[0])
        return out
