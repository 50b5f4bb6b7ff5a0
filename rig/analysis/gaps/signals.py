"""Measured runs prepared for the gap workflow: smoothed states, one linear smoother, shooting windows.

A drive's velocity column is often a lagged filter of the encoder, so velocities are always derived here
from the positions (Savitzky–Golay, zero phase). Every signal that is compared with another (measured
and predicted accelerations, the regressors of the effects) passes through the same smoother `smooth`,
so the smoothing blurs both sides of a comparison alike and leaves no trace in their difference.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import convolve1d
from scipy.signal import savgol_filter

from model.errors import UserInputError
from model.plant import INPUT_COLUMN, InputMode
from model.run import Run
from model.simulate import replay_mode

SMOOTHING_S = 0.015
"""Width of the smoother: long enough to average encoder quantization out of accelerations, short
against the motion (a 1 kHz run smooths over 15 samples)."""
TEMPERATURE_S = 0.5
"""Width of the moving average on a recorded temperature: the probe's noise (hundredths of a kelvin)
averages out, while the gear's thermal time constants (tens of seconds and more) are untouched."""


def _odd(n: float, least: int) -> int:
    m = max(least, round(n))
    return m if m % 2 else m + 1


@dataclass
class Signals:
    """One run, ready for the residuals: raw positions, smoothed states, inputs held per sample."""

    run: Run
    mode: InputMode
    t: np.ndarray  # s, from the run's first sample
    drive: np.ndarray  # u [V], i_cmd [A] or tau_m [N·m] by mode
    tau_ext: np.ndarray  # N·m at the output: the torque beyond the gear's output (`boundary`)
    theta_m: np.ndarray  # rad, as measured
    omega_m: np.ndarray  # rad/s, smoothed derivative of theta_m
    theta_l: np.ndarray | None  # rad, as measured (None: no output sensor)
    theta_l_smooth: np.ndarray | None
    omega_l: np.ndarray | None
    width: int  # samples of the smoother
    stuck: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))  # motor at rest in the data
    temp_gear: np.ndarray | None = None  # °C, measured, averaged over TEMPERATURE_S (None: not recorded)
    temp_motor: np.ndarray | None = None  # °C, likewise
    travel: np.ndarray = field(default_factory=lambda: np.zeros(0))  # ∫|ω_m|dt since the start [rad]
    boundary: str = "tau_ext"  # the column `tau_ext` holds: the load's torque, or the output transducer's

    @property
    def n(self) -> int:
        return len(self.t)

    @property
    def has_load(self) -> bool:
        return self.theta_l is not None

    def smooth(self, x: np.ndarray) -> np.ndarray:
        """The one smoother of the workflow: a Hann window of `width` samples, zero phase."""
        w = np.hanning(self.width + 2)[1:-1]
        return np.asarray(convolve1d(x, w / w.sum(), mode="nearest"))

    def acceleration(self, theta: np.ndarray) -> np.ndarray:
        """Raw second difference of a position on the (possibly irregular) time base [rad/s²]."""
        v = np.diff(theta) / np.diff(self.t)
        a = np.zeros_like(theta)
        a[1:-1] = 2 * np.diff(v) / (self.t[2:] - self.t[:-2])
        a[0], a[-1] = a[1], a[-2]
        return a


TEMPERATURES = ("temp_gear", "temp_motor")


def _temperature(run: Run, column: str, samples: int) -> np.ndarray | None:
    """A recorded temperature [°C] under a centred moving average; None when not recorded (or not
    throughout: a NaN anywhere)."""
    if column not in run:
        return None
    values = np.asarray(run[column], dtype=np.float64)
    if not np.all(np.isfinite(values)):
        return None
    width = max(1, samples)
    return np.asarray(convolve1d(values, np.full(width, 1.0 / width), mode="nearest"))


OUTPUT_TRANSDUCER = "tau_out"


def output_boundary(run: Run) -> str:
    """The column whose torque stands at the gear's output: the output transducer's where the run has it.

    `tau_out` reads what the gear passes on (T_s − F_l less what accelerates the gear's own output
    inertia), so with it as the torque beyond the output the gear's model is judged alone, cut at the
    transducer: the output's residual and the replays need neither the load drive (its rotor's inertia,
    its bearings' friction, which its `tau_ext` column lacks) nor the motor's friction, and an effect at
    the output shows in the output's channel directly (docs/CATALOG_TESTS.md, "The bench")."""
    if OUTPUT_TRANSDUCER in run and np.all(np.isfinite(run[OUTPUT_TRANSDUCER])):
        return OUTPUT_TRANSDUCER
    return "tau_ext"


def prepare(run: Run, stick_band_rad_s: float, smoothing_s: float = SMOOTHING_S) -> Signals:
    """Signals of one validated run; an error naming the column if it cannot drive a replay."""
    mode = replay_mode(run)
    t = run.t - run.t[0]
    n = len(t)
    if n < 50:
        raise UserInputError(
            f"run {run.meta.get('run_id', '')!s}: {n} samples are too few for the gap workflow"
        )
    h = float(np.median(np.diff(t)))
    width = _odd(smoothing_s / h, 5)
    sg = _odd(width, 7)

    def derivative(x: np.ndarray) -> np.ndarray:
        return np.asarray(savgol_filter(x, sg, 3, deriv=1, delta=h, mode="interp"))

    theta_m = np.asarray(run["theta_m"], dtype=np.float64)
    theta_l = np.asarray(run["theta_l"], dtype=np.float64) if "theta_l" in run else None
    boundary = output_boundary(run)
    tau = np.asarray(run[boundary], dtype=np.float64) if boundary in run else np.zeros(n)
    sig = Signals(
        run=run,
        mode=mode,
        t=t,
        drive=np.asarray(run[INPUT_COLUMN[mode]], dtype=np.float64),
        tau_ext=tau,
        theta_m=theta_m,
        omega_m=derivative(theta_m),
        theta_l=theta_l,
        theta_l_smooth=None if theta_l is None else np.asarray(savgol_filter(theta_l, sg, 3, mode="interp")),
        omega_l=None if theta_l is None else derivative(theta_l),
        width=width,
        boundary=boundary,
    )
    sig.temp_gear, sig.temp_motor = (_temperature(run, c, round(TEMPERATURE_S / h)) for c in TEMPERATURES)
    steps = np.abs(np.diff(theta_m))
    quantum = float(steps[steps > 0].min()) if np.any(steps > 0) else 0.0
    # At rest in the data: slower than one encoder count per smoother width, or inside the stick band.
    threshold = max(stick_band_rad_s, 2.0 * quantum / (width * h))
    sig.stuck = np.abs(sig.omega_m) < threshold
    # Travel from the smoothed speed while moving: an encoder count dithering at rest adds none.
    speed = np.where(sig.stuck, 0.0, np.abs(sig.omega_m))
    sig.travel = np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * np.diff(t))])
    return sig


@dataclass
class Window:
    """One shooting window: a short run that starts from the estimated state at its first sample."""

    run: Run  # inputs, raw theta_m (start and comparison), smoothed omega_m / theta_l / omega_l (start)
    signals: int  # index of the Signals it was cut from
    start: int  # first row in those signals
    clock_s: float  # time since the run's start at the first sample
    theta_m: np.ndarray  # measured, for comparison
    theta_l: np.ndarray | None
    test: bool  # held out from fitting
    temp_gear_c: float | None = None  # measured at the first sample (None: not recorded)
    temp_motor_c: float | None = None
    travel_rad: float = 0.0  # motor travel since the run's start at the first sample


def _clear_edges(sig: Signals, nominal: np.ndarray) -> np.ndarray:
    """Window starts moved forward (by less than half a window) to a sample whose state is clear:
    no rest/motion change within a smoother width, so the estimated speed is not a blend of both."""
    changes = np.flatnonzero(np.diff(sig.stuck.astype(np.int8))) + 1
    near = np.zeros(sig.n, bool)
    for c in changes:
        near[max(0, c - sig.width) : c + sig.width] = True
    edges = nominal.copy()
    for i in range(1, len(nominal)):
        limit = nominal[i] + (nominal[i] - nominal[i - 1]) // 2
        clear = np.flatnonzero(~near[nominal[i] : limit])
        if clear.size:
            edges[i] = nominal[i] + clear[0]
    return edges


def cut_windows(signals: list[Signals], window_s: float, test_every: int = 3) -> list[Window]:
    """Consecutive windows of about `window_s`; every `test_every`-th is held out from fitting."""
    out: list[Window] = []
    for index, sig in enumerate(signals):
        edges = _clear_edges(sig, np.searchsorted(sig.t, np.arange(0.0, sig.t[-1], window_s)))
        edges = np.append(edges, sig.n)
        for a, b in itertools.pairwise(edges):
            if b - a < 3:
                continue
            cols: dict[str, np.ndarray] = {
                "t": sig.t[a:b],
                INPUT_COLUMN[sig.mode]: sig.drive[a:b],
                "tau_ext": sig.tau_ext[a:b],
                "theta_m": sig.theta_m[a:b],
                "omega_m": sig.omega_m[a:b],
            }
            if sig.theta_l_smooth is not None and sig.omega_l is not None:
                cols["theta_l"] = sig.theta_l_smooth[a:b]
                cols["omega_l"] = sig.omega_l[a:b]
            run = Run(cols, {"input_column": INPUT_COLUMN[sig.mode]})
            theta_l = None if sig.theta_l is None else sig.theta_l[a:b]
            test = len(out) % test_every == test_every - 1
            gear, motor = (None if v is None else float(v[a]) for v in (sig.temp_gear, sig.temp_motor))
            out.append(
                Window(
                    run,
                    index,
                    int(a),
                    float(sig.t[a]),
                    sig.theta_m[a:b],
                    theta_l,
                    test,
                    gear,
                    motor,
                    float(sig.travel[a]),
                )
            )
    if not out:
        raise UserInputError("no data long enough for a shooting window")
    return out


def spread(values: np.ndarray) -> float:
    """RMS of an array; 0 for an empty one."""
    return math.sqrt(float(np.mean(values**2))) if values.size else 0.0
