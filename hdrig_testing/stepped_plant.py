"""A plant that moves under a script, for the DAQ twin to measure on its own (no drive twin stepping it).

`DaqTwin.from_sensors(SteppedPlantSource(Plant(model), drive), sensors)`: a standalone board whose
readings follow real plant motion, with the truth at hand (`source(t_device_s)`) to compare against.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from model.plant import InputMode, Plant
from model.registry import X


class SteppedPlantSource:
    """A plant this source steps itself, under `drive(t)` (vectorized over step times [s]), from the
    device time of its first call: a standalone twin with real plant motion."""

    def __init__(
        self,
        plant: Plant,
        drive: Callable[[np.ndarray], np.ndarray],
        mode: InputMode = "voltage",
        dt_s: float = 1e-4,
    ) -> None:
        self.plant, self.drive, self.mode, self.dt_s = plant, drive, mode, dt_s
        self._device_minus_plant_s: float | None = None

    def __call__(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x = self.plant.x
        if self._device_minus_plant_s is None:
            self._device_minus_plant_s = float(t_s[0]) - float(x[X.TIME])
        theta_m, theta_l = np.empty(t_s.shape), np.empty(t_s.shape)
        for i, t in enumerate(t_s):
            steps = round((t - self._device_minus_plant_s - x[X.TIME]) / self.dt_s)
            if steps > 0:
                step_times = self._device_minus_plant_s + x[X.TIME] + self.dt_s * np.arange(steps)
                self.plant.advance(self.drive(step_times), self.mode, dt_s=self.dt_s, decim=steps)
            theta_m[i], theta_l[i] = x[X.THETA_M], x[X.THETA_L]
        return theta_m, theta_l
