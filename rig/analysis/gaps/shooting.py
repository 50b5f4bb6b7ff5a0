"""The gap metric (multiple shooting) and the fit of an added effect on the training windows.

Each window restarts the model from the measured state and replays the measured input over it, so
closed-loop data do not drift; the error is the simulated minus the measured motor angle, and the
output angle divided by r when it is measured (both in radians at the motor). The gap is its RMS.

`model.simulate.replay_rows` does the replay, giving each window the run's clock (thermal drift is a
function of time since the run's start) and the unseen states (hysteresis element, bristles) tracked
along the data by the one-step pass. A window also starts from the states the run measured there
(`started`): the gear's and the winding's temperatures when the model has a `thermal` section and the
run recorded them (the friction follows the measured temperature, not a network started at ambient
at every window), and the motor travel since the run's start (`wear_drift`).

The fit is `rig.analysis.fit.trajectory`'s least squares and uncertainty on this residual: the cost is the
gap itself on the training windows (the held-out windows judge the result), with tied parameters
(`f_sl` follows `f_cl`) kept valid.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from model.errors import UserInputError
from model.params import HarmonicDriveModel
from model.plant import Plant
from model.registry import OUT, X
from model.simulate import replay_rows
from rig.analysis.fit.parameters import with_values
from rig.analysis.fit.trajectory import ParameterEstimate, TrajectoryProblem, solve
from rig.analysis.gaps.residual import one_step_residual
from rig.analysis.gaps.signals import Signals, Window

Starts = dict[int, float]
"""Kernel state slots (registry.X) set at a window's start from what the run measured there."""


class StartedPlant(Plant):
    """A plant whose reset also sets `starts`: `replay_rows` resets it at each window's first sample."""

    def __init__(self, model: HarmonicDriveModel) -> None:
        self.starts: Starts = {}
        super().__init__(model)

    def reset(
        self,
        theta_m: float = 0.0,
        omega_m: float = 0.0,
        theta_l: float | None = None,
        omega_l: float | None = None,
        time_s: float = 0.0,
        hidden: ArrayLike | None = None,
    ) -> None:
        super().reset(theta_m, omega_m, theta_l, omega_l, time_s, hidden)
        for slot, value in self.starts.items():
            self.x[slot] = value


def started(model: HarmonicDriveModel, window: Window) -> Starts:
    """The measured states a window of `model` starts from: the temperatures' rises above the
    network's ambient (a `thermal` section, temperatures recorded) and the travel (`wear_drift`)."""
    out: Starts = {}
    thermal = model.thermal
    if thermal is not None and window.temp_gear_c is not None:
        out[X.RISE_GEAR] = window.temp_gear_c - thermal.T_amb
        if window.temp_motor_c is not None:
            out[X.RISE_MOTOR] = window.temp_motor_c - thermal.T_amb
    if model.wear_drift is not None:
        out[X.TRAVEL] = window.travel_rad
    return out


METRIC = (
    "RMS error of the motor angle (and of the output angle / r, when measured) over shooting windows"
    " restarted from the measured state [rad at the motor]"
)


def _has_unseen_states(model: HarmonicDriveModel) -> bool:
    return (
        model.hysteresis is not None
        or model.motor_friction.motor_law in ("lugre", "dahl")
        or (model.load_friction is not None and model.load_friction.load_law in ("lugre", "dahl"))
    )


@dataclass
class Shooting:
    """The windows of the data and how to score a model on them."""

    signals: list[Signals]
    windows: list[Window]
    r: float
    dt_s: float

    def errors(self, model: HarmonicDriveModel, which: Sequence[int]) -> list[np.ndarray]:
        """Per window: the stacked errors (θ_m, then θ_l / r) [rad at the motor]."""
        plant = StartedPlant(model)
        internal = None
        if _has_unseen_states(model):
            internal = [one_step_residual(model, s, self.dt_s).internal for s in self.signals]
        out = []
        for i in which:
            w = self.windows[i]
            hidden = internal[w.signals][w.start] if internal is not None else None
            plant.starts = started(model, w)
            rows = replay_rows(
                plant, w.run, self.signals[w.signals].mode, self.dt_s, time_s=w.clock_s, hidden=hidden
            )
            parts = [rows[:, OUT.THETA_M] - w.theta_m]
            if w.theta_l is not None:
                parts.append((rows[:, OUT.THETA_L] - w.theta_l) / self.r)
            out.append(np.concatenate(parts))
        return out

    def gap(self, model: HarmonicDriveModel, which: Sequence[int]) -> float:
        errors = self.errors(model, which)
        total = np.concatenate(errors) if errors else np.zeros(0)
        return math.sqrt(float(np.mean(total**2))) if total.size else 0.0

    @property
    def train(self) -> list[int]:
        return [i for i, w in enumerate(self.windows) if not w.test]

    @property
    def test(self) -> list[int]:
        return [i for i, w in enumerate(self.windows) if w.test]

    @property
    def everything(self) -> list[int]:
        return list(range(len(self.windows)))


class _GapProblem(TrajectoryProblem):
    """`TrajectoryProblem` whose residual is the gap on the fitting windows, with tied parameters."""

    def __init__(
        self,
        model: HarmonicDriveModel,
        shooting: Shooting,
        names: list[str],
        ties: dict[str, str],
        fitting: list[int],
    ) -> None:
        super().__init__(model, [shooting.windows[i].run for i in fitting[:1]], names, 1e9, shooting.dt_s)
        self.shooting = shooting
        self.fitting = fitting
        self.ties = ties
        self._size = sum(len(e) for e in shooting.errors(model, fitting))

    def model_at(self, values: dict[str, float]) -> HarmonicDriveModel:
        tied = {target: values[source] for target, source in self.ties.items()}
        return with_values(self.model, {**values, **tied}, source="gaps fit")

    def residuals(self, x: np.ndarray) -> np.ndarray:
        try:
            model = self.model_at(self.values(x))
        except UserInputError:
            return np.full(self.size, 1e3)  # outside the model's valid region: large and flat
        return np.concatenate(self.shooting.errors(model, self.fitting))

    @property
    def size(self) -> int:
        return self._size


@dataclass
class EffectFit:
    model: HarmonicDriveModel
    parameters: list[ParameterEstimate]
    evaluations: int


def fit_on_windows(
    model: HarmonicDriveModel,
    shooting: Shooting,
    names: list[str],
    ties: dict[str, str] | None = None,
    max_windows: int = 150,
    max_iterations: int = 12,
) -> EffectFit:
    """Least squares of the named parameters on at most `max_windows` training windows: half where the
    model errs most (rare events such as breakaways live there), half spread evenly over the rest."""
    train = shooting.train
    if len(train) > max_windows:
        errors = [float(np.sum(e**2)) for e in shooting.errors(model, train)]
        worst = [train[i] for i in np.argsort(errors)[::-1][: max_windows // 2]]
        rest = [i for i in train if i not in set(worst)]
        step = max(1, math.ceil(len(rest) / (max_windows - len(worst))))
        train = sorted(worst + rest[::step])
    problem = _GapProblem(model, shooting, names, ties or {}, train)
    result, estimates = solve(problem, max_iterations)
    fitted = problem.model_at({p.name: p.estimate for p in estimates})
    return EffectFit(fitted, estimates, int(result.nfev) * (len(names) + 1))
