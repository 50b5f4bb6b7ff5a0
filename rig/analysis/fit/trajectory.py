"""Joint refinement: all free parameters at once, by least squares on simulated-vs-measured trajectories.

Closed-loop rig data replayed open loop drift away (friction integrates any error), so the residual is
taken over short windows (multiple shooting): each window restarts the model from the measured state
and replays the measured input over it (a run without metadata: its start speeds and load position
left free, `TrajectoryProblem.with_free_starts`). The cost is the article's "Euclidean norm between
simulated and measured values", per channel scaled by the data's own spread so that radians and rad/s
weigh alike.

Uncertainty: the Gauss–Newton covariance at the optimum, windows taken as independent clusters (the
sandwich, `window_robust_covariance`). A parameter whose column of the scaled Jacobian is (nearly) a
combination of the others, or whose standard error exceeds its own size, is reported as not determined
by the data, and keeps its starting value.

Priors: estimates made elsewhere (the staged estimates, each from data made for it) can enter as extra
residual rows λ·(θ − μ)/σ, so a value its own experiment pins down is not pulled away by trajectories
that see it less well. λ puts a prior row on the scale of the trajectories' residual: λ = s·√c, with s
the residual's RMS and c how much the window clustering inflates the white covariance, both measured at
the optimum (`prior_weight`).
"""

from __future__ import annotations

import copy
import dataclasses
import itertools
import math
import os
import re
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import OptimizeResult, least_squares
from scipy.signal import savgol_coeffs, savgol_filter

from model.errors import UserInputError
from model.kernel import replay_windows
from model.params import HarmonicDriveModel
from model.plant import INPUT_COLUMN, MODES, InputMode, Plant
from model.registry import OUT, P
from model.run import Run
from model.simulate import replay_mode, replay_rows, substeps
from rig.analysis.fit.parameters import get_values, with_values

CHANNELS = {"theta_m": OUT.THETA_M, "theta_l": OUT.THETA_L}
"""Positions only: a drive's speed is a filtered encoder difference, which the true speed of the model
would be compared to with a lag and a bias; positions are only quantized and noisy."""
SIGNED = re.compile(r"s1|s2|a\d+|b\d+|k_v|phi|f_dir|d_th")
"""Parameters that may take either sign; every other parameter of docs/MODEL.md is positive."""


@dataclass
class ParameterEstimate:
    name: str
    start: float
    estimate: float
    std_error: float | None
    identifiable: bool
    note: str = ""


@dataclass
class TrajectoryFit:
    model: HarmonicDriveModel
    parameters: list[ParameterEstimate]
    cost_before: float  # RMS of the scaled residual at the start (trajectory rows only)
    cost_after: float
    residuals: int
    notes: list[str] = field(default_factory=list)
    prior_weight: float = 0.0  # λ of the prior rows at the optimum (0: no priors)
    data_only: dict[str, Prior] = field(default_factory=dict)  # `data_only_estimates` at the optimum
    # Per parameter, how far each free parameter moves per unit of it along the cost's valley floor
    # (`profile_directions`): where a profile of the cost walks.
    profile_direction: dict[str, dict[str, float]] = field(default_factory=dict)
    # Per parameter, σ as the cost's curvature gives it with white residuals (s² per row): the scale of
    # the cost's rise, before the clustering widens the σ reported (`profile_directions`).
    curvature_sigma: dict[str, float] = field(default_factory=dict)


def data_only_estimates(
    problem: TrajectoryProblem, jac: np.ndarray, fun: np.ndarray, x: np.ndarray
) -> dict[str, Prior]:
    """What the trajectories alone say of each free parameter near an optimum found with priors: one
    Gauss–Newton step without the prior rows, σ window-clustered (value, 1σ). Beside a prior, it tells
    whether the two disagree by more than their σ allow: a bias one of them carries."""
    m = problem.size
    data_jac, data_fun = jac[:m], fun[:m]
    n = data_jac.shape[1]
    step = -np.linalg.pinv(data_jac.T @ data_jac) @ (data_jac.T @ data_fun)
    s2 = float(data_fun @ data_fun) / max(m - n - problem.nuisance, 1)
    cov = window_robust_covariance(data_jac, data_fun, problem.window_of_residual, s2)
    se = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    return {
        name: (float((x[i] + step[i]) * problem.x_scale[i]), float(se[i] * abs(problem.x_scale[i])))
        for i, name in enumerate(problem.names)
    }


Prior = tuple[float, float]
"""An estimate made elsewhere: (value, 1σ)."""


@dataclass
class _Window:
    run: Run
    channels: list[str]
    scales: dict[str, float]
    time_s: float  # since the start of the run it was cut from
    step_s: float  # the longest integration step of its replay
    replay: _Replay | None = None  # the replay's inputs, prepared once (None: `replay_rows` each time)
    emf_step_s: float = 0.0  # a coarse voltage replay of a continuous process: its step (`emf_lag_inertia`)
    # Orthonormal columns over the window's residual: what errors of its measured start state make of
    # it, projected out of the residual (`TrajectoryProblem.with_free_starts`); None: the start is held.
    start_basis: np.ndarray | None = None


PLANT_SOURCE = "sim"
"""`meta["source"]` of runs the project's simulated plant made (`model.simulate`, the sim rigs)."""
EVENT_STEP_S = 2.5e-6
"""A continuous process's replay steps at most this long over the sample intervals where a body stops,
starts or reverses (see `_Replay`). Karnopp friction's error there is first order in this step, and
coarser steps biased J_l measurably on ideal-sensor data; this step buys most of the accuracy for a few
times the steps of a plain replay. Noisy sensors cost more: a still body's measured speed flips sign
with the noise, which `speed_bands` tells from a stop. Figures: docs/BENCHMARKS.md, "Figures behind
design choices in the code"."""
PLAIN_EVENT_STEP_S = 1e-5
"""`EVENT_STEP_S` for the coarse replay of runs without metadata (`TrajectoryProblem`'s `refine_voltage`
off: a lab file, its sensors' noise unknown): on 14-bit records the noise is far above the step's
error there, and the fit takes a third to a half of the time; on ideal-sensor data the 10 µs step leaves
J_l −0.026 % (figures: docs/BENCHMARKS.md, issue 25's fit speed)."""


def plant_step(run: Run) -> float | None:
    """The integration step of the project's simulated plant that made `run`, as its metadata say
    (`dt_s` of `model.simulate`, `sim_dt_s` of a sim rig's config); None for any other process."""
    if run.meta.get("source") != PLANT_SOURCE:
        return None
    rig_config = run.meta.get("rig_config")
    step = run.meta.get("dt_s") or (rig_config.get("sim_dt_s") if isinstance(rig_config, dict) else None)
    return float(step) if isinstance(step, int | float) and step > 0 else DEFAULT_PLANT_STEP_S


DEFAULT_PLANT_STEP_S = 1e-4
"""The simulated plant's step when a sim run does not record one (`simulate`'s and the rigs' default)."""
EXACT_COST_MAX = 10
"""A sim run is replayed exactly (at its plant's step) when that costs at most this many times the
replay's own step; a plant integrated finer than that is near-continuous, and replayed as continuous."""


VOLTAGE_REFINE = 10
"""A continuous process driven by voltage is replayed at a tenth of the step: the back-EMF torque is
taken at the speed half a step old, which acts as an inertia c_e·h/2 (c_e = K_m·K_b/R): +0.28 % of the
seed's J_m at 0.1 ms, first order in the step, and the one error of the kind left that is not
negligible (viscous friction and spring damping are two orders smaller on the seed joint). A tenth of the
step brought the bias within about one σ on ideal-sensor runs (docs/BENCHMARKS.md)."""


def replay_scheme(run: Run, dt_s: float, refine_voltage: bool = True) -> tuple[float, bool]:
    """(step, continuous) of a run's replay: its plant's own step if the project's plant made it (exact),
    else `dt_s` (a tenth of it in voltage mode, unless `refine_voltage` is off: see `emf_lag_inertia`)
    with the continuous process's refinements (`_Replay`)."""
    step = plant_step(run)
    if step is not None and step * EXACT_COST_MAX >= dt_s:
        return step, False
    if refine_voltage and run.input_column is not None and replay_mode(run) == "voltage":
        return dt_s / VOLTAGE_REFINE, True
    return dt_s, True


def emf_lag_inertia(model: HarmonicDriveModel, step_s: float) -> float:
    """The inertia [kg·m²] a voltage-driven replay of a continuous process at `step_s` must add to J_m so
    that its back-EMF, taken at the speed a step starts with, does not bias the fit: c_e·h/2,
    c_e = K_m·K_b/R.

    The semi-implicit Euler step takes the back-EMF torque at the step's first speed, half a step behind
    the step's mean: −c_e·ω(t − h/2) ≈ −c_e·ω(t) + c_e·(h/2)·α acts as an inertia −c_e·h/2. J_m's
    optimum with the others at the truth (three drawn gears, both generators, windows' starts held or
    free): −0.20…−0.44 % with c_e·h added, −0.12…+0.07 % with c_e·h/2, +0.22 % with none (the figures:
    docs/BENCHMARKS.md, issue 25)."""
    motor = model.motor
    if not motor.R:
        return 0.0
    return motor.K_m * motor.K_b / motor.R * step_s / 2


@dataclass
class _Replay:
    """A window's replay on a regular time base, with the inputs laid out once: the fit replays every
    window hundreds of times, and laying them out each time (the sub-step count of every sample
    interval, in Python) cost ten times the integration itself.

    Two ways to replay, after the process that made the data (`replay_scheme`):
    - the project's simulated plant: its own semi-implicit Euler at its own step, each sample's input
      held over its interval, which reproduces it exactly;
    - any other process, taken as continuous (hardware, another integrator): against it, that Euler is
      first order, which biased both inertias measurably. Its speed lives half a step behind its
      position (leapfrog), so the step that starts on a sample boundary spans half of each neighbouring
      interval and takes the mean of their inputs, not the new one. Karnopp friction is first order at
      every stop, start and reversal (a whole step at zero speed, the static level for a whole step):
      the intervals where a measured speed changes sign are stepped at `EVENT_STEP_S`, the speeds moved
      to the new step's half-step at each change of step. Last, the back-EMF (`VOLTAGE_REFINE`). With
      the 5-sample starting speeds (`SMOOTHING_WINDOW_S`) the inertias come out within a few σ of an
      ideal-sensor plant's, for several times the steps of the plain replay (figures:
      docs/BENCHMARKS.md, "Figures behind design choices in the code").
    """

    state: dict[str, float | None]  # `Plant.reset` keywords: the window's first measured state
    mode: InputMode
    drive: np.ndarray  # per integration step
    load: np.ndarray
    segments: list[tuple[int, int, float]]  # (steps, substeps per sample, step [s]) run one after another
    measured: np.ndarray  # (samples, channels) the measured CHANNELS
    scales: np.ndarray  # per channel
    outputs: list[int]  # the kernel's OUT_ columns of the channels

    @classmethod
    def of(
        cls,
        run: Run,
        channels: list[str],
        scales: dict[str, float],
        dt_s: float,
        continuous: bool = False,
        bands: dict[str, float] | None = None,
        event_step_s: float = EVENT_STEP_S,
    ) -> _Replay | None:
        """`bands`: the whole run's `speed_bands` (a window alone is too short to tell its noise)."""
        mode = replay_mode(run)
        intervals = np.diff(run.t)
        counts = np.maximum(1, np.ceil(intervals / dt_s - 1e-9)).astype(int)
        steps = intervals / counts
        if not (np.all(counts == counts[0]) and np.allclose(steps, steps[0], rtol=1e-9, atol=0.0)):
            return None  # an irregular time base: `replay_rows` cuts each interval on its own
        if continuous:
            refined = _event_intervals(run, bands)
            refined[0] = False  # the window's start speed is lagged by the base step's half
            fine = np.maximum(1, np.ceil(intervals / event_step_s - 1e-9)).astype(int)
            counts = np.where(refined, np.maximum(counts, fine), counts)
        steps = intervals / counts
        drive = run[INPUT_COLUMN[mode]]
        load = run["tau_ext"] if "tau_ext" in run else np.zeros(len(run))
        drive_steps = np.append(np.repeat(drive[:-1], counts), drive[-1])
        load_steps = np.append(np.repeat(load[:-1], counts), load[-1])
        if continuous:
            first = np.cumsum(counts)[:-1]  # each interval's first step, from the second interval on
            drive_steps[first] = _boundary_mean(drive, steps)
            load_steps[first] = _boundary_mean(load, steps)
        segments = []
        done = 0
        for n, group in itertools.groupby(counts):
            samples = len(list(group))
            segments.append((samples * int(n), int(n), float(intervals[done] / n)))
            done += samples
        last_steps, last_n, last_h = segments[-1]
        # The row of the last sample is the state reached, with the last input applied over one step.
        segments[-1] = (last_steps + 1, last_n, last_h)
        return cls(
            state={
                "theta_m": float(run["theta_m"][0]),
                "omega_m": float(run["omega_m"][0]) if "omega_m" in run else 0.0,
                "theta_l": float(run["theta_l"][0]) if "theta_l" in run else None,
                "omega_l": float(run["omega_l"][0]) if "omega_l" in run else None,
            },
            mode=mode,
            drive=np.ascontiguousarray(drive_steps),
            load=np.ascontiguousarray(load_steps),
            segments=segments,
            measured=np.column_stack([run[c] for c in channels]),
            scales=np.array([scales[c] for c in channels]),
            outputs=[CHANNELS[c] for c in channels],
        )


@dataclass
class _Batch:
    """Windows replayed together by one compiled call (`model.kernel.replay_windows`): their `_Replay`s'
    inputs, segments and measurements laid end to end, and where each window's residual goes. A window
    is (first input step, first segment, segment stop, first row, rows, first residual element)."""

    windows: list[_Window]
    emf_step_s: float
    mode: InputMode
    table: np.ndarray  # (windows, 6) int64
    drive: np.ndarray
    load: np.ndarray
    seg_steps: np.ndarray
    seg_decim: np.ndarray
    seg_dt: np.ndarray
    measured: np.ndarray  # (rows, channels)
    scales: np.ndarray  # (windows, channels)
    outputs: np.ndarray  # the kernel's OUT columns of the channels
    steps_per_window: np.ndarray  # integration steps of each window (`_chunks` balances them)

    @classmethod
    def of(cls, windows: list[tuple[_Window, int]], emf_step_s: float) -> _Batch:
        """`windows`: each with its replay and the first element of its residual in the whole residual."""
        replays = [w.replay for w, _ in windows if w.replay is not None]
        steps = np.cumsum([0] + [len(r.drive) for r in replays])
        segments = np.cumsum([0] + [len(r.segments) for r in replays])
        rows = np.cumsum([0] + [len(r.measured) for r in replays])
        table = np.column_stack(
            [steps[:-1], segments[:-1], segments[1:], rows[:-1], np.diff(rows), [at for _, at in windows]]
        ).astype(np.int64)
        flat = [s for r in replays for s in r.segments]
        return cls(
            [w for w, _ in windows],
            emf_step_s,
            replays[0].mode,
            table,
            np.concatenate([r.drive for r in replays]),
            np.concatenate([r.load for r in replays]),
            np.array([n for n, _, _ in flat], np.int64),
            np.array([d for _, d, _ in flat], np.int64),
            np.array([h for _, _, h in flat]),
            np.concatenate([r.measured for r in replays]),
            np.array([r.scales for r in replays]),
            np.array(replays[0].outputs, np.int64),
            np.array([sum(n for n, _, _ in r.segments) for r in replays], np.int64),
        )

    def replay_into(self, model: HarmonicDriveModel, residual: np.ndarray) -> None:
        """Each window's scaled residual under `model`, written in place; the windows split among
        threads (the compiled replay releases the GIL; each window is replayed alone, so the numbers do
        not depend on the split)."""
        plant = Plant(model)
        plant.p[P.J_M] += emf_lag_inertia(model, self.emf_step_s) if self.emf_step_s else 0.0
        starts = np.empty((len(self.windows), len(plant.x)))
        for i, w in enumerate(self.windows):
            plant.reset(**w.replay.state, time_s=w.time_s)  # type: ignore[union-attr]
            starts[i] = plant.x
        mode = MODES[self.mode]

        def part(chunk: slice) -> None:
            work = np.empty((int(self.table[chunk, 4].max()) + 2, len(OUT)))
            replay_windows(
                plant.p,
                plant.flags,
                mode,
                starts[chunk],
                self.drive,
                self.load,
                self.table[chunk],
                self.seg_steps,
                self.seg_decim,
                self.seg_dt,
                self.measured,
                self.scales[chunk],
                self.outputs,
                residual,
                work,
            )

        chunks = _chunks(self.steps_per_window, REPLAY_THREADS)  # the same split at every evaluation
        if len(chunks) == 1:
            part(chunks[0])
            return
        with ThreadPoolExecutor(len(chunks)) as pool:
            for done in [pool.submit(part, c) for c in chunks]:
                done.result()


REPLAY_THREADS = max(1, min(len(os.sched_getaffinity(0)), 8))
"""Threads the windows' replay is split among: the machine's cores, up to 8."""
MIN_STEPS_PER_THREAD = 20_000
"""Fewer integration steps than this per thread are replayed on one: a thread's start costs more."""


def _chunks(steps: np.ndarray, threads: int) -> list[slice]:
    """Windows cut into at most `threads` contiguous runs of about equal integration steps (a window
    with stops and reversals steps finer, `EVENT_STEP_S`, and costs several times another)."""
    n = max(1, min(threads, int(steps.sum()) // MIN_STEPS_PER_THREAD))
    cumulative = np.cumsum(steps)
    edges = [0, *np.searchsorted(cumulative, cumulative[-1] * np.arange(1, n) / n).tolist(), len(steps)]
    return [slice(int(a), int(b)) for a, b in itertools.pairwise(edges) if b > a]


def _event_intervals(run: Run, bands: dict[str, float] | None = None) -> np.ndarray:
    """Per sample interval: whether a body's measured speed changes sign (or leaves or reaches zero)
    across it or its neighbours: where Karnopp friction stops, starts or reverses a body.

    A speed within its body's `bands` entry (`speed_bands`: what the sensor's noise alone makes of a
    still body) counts as zero, so a body at rest or crawling is one stop, not a flip every sample.
    """
    event = np.zeros(len(run) - 1, bool)
    for speed in ("omega_m", "omega_l"):
        if speed in run:
            omega = run[speed]
            band = (bands or {}).get(speed, 0.0)
            sign = np.where(np.abs(omega) > band, np.sign(omega), 0.0)
            event |= sign[1:] != sign[:-1]
    return event | np.append(event[1:], False) | np.insert(event[:-1], 0, False)


def _boundary_mean(values: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """The input over the step that starts each sample boundary (from the second), when the speed is
    half a step behind the position: half of the step before, at the old value, and half of this
    one, at the new one, as one step of this one's length."""
    return 0.5 * (values[:-2] + values[1:-1])


def shooting_windows(run: Run, window_s: float, quiet_rows: int = 6, calm: bool = False) -> list[Run]:
    """Cut a run into consecutive windows of about `window_s`, each a run of its own.

    Each cut is moved (by up to a quarter window) to where the input has been steady for `quiet_rows`
    each side, so a window never starts on a jump of the input, where no smoothed speed is right.

    `calm` (a continuous process, `replay_scheme`): of those places, the nearest where neither body
    accelerates beyond what its sensor's noise makes of a steady one, else where they accelerate least
    (`_acceleration_excess`), an input that changes every sample (a velocity loop's voltage) counting as
    never quiet: in a fast transient the local cubic's speed is off, and each window starting there
    replays the error (a velocity loop's set-point reversals: J_m +2.7 %, on ideal data too). Runs of our
    own plant, replayed exactly, keep the plain cuts: moved, they raised the campaign's error at the
    truth on its pulse run (docs/BENCHMARKS.md).
    """
    t = run.t
    edges = np.searchsorted(t, np.arange(t[0], t[-1], window_s))
    column = run.input_column
    drive = run[column] if column is not None else np.zeros(len(t))
    jumps = np.flatnonzero(np.abs(np.diff(drive)) > 1e-9 * (np.max(np.abs(drive)) + 1e-300)) + 1
    excess = _acceleration_excess(run) if calm else np.zeros(len(t))
    reach = max(1, int(0.25 * window_s / float(np.median(np.diff(t)))))
    for i, edge in enumerate(edges[1:], start=1):
        shifts = sorted(range(-reach, reach + 1), key=abs)
        inside = [edge + s for s in shifts if 0 < edge + s < len(t)]
        quiet = [e for e in inside if not np.any((jumps > e - quiet_rows) & (jumps <= e + quiet_rows))]
        # An input that changes every sample (a velocity loop's output) is never quiet: any place will do.
        allowed = quiet if quiet or not calm or jumps.size < len(t) // 2 else inside
        steady = [e for e in allowed if excess[e] <= 1.0]
        if steady or allowed:
            edges[i] = steady[0] if steady else min(allowed, key=lambda e: excess[e])
    edges = np.unique(np.append(edges, len(t)))
    out = []
    for start, stop in itertools.pairwise(edges):
        if stop - start >= 3:
            out.append(Run({c: v[start:stop] for c, v in run.columns.items()}, run.meta))
    return out


def _acceleration_excess(run: Run) -> np.ndarray:
    """Per sample: the larger over the bodies of |α| from the local cubic of its position (the one the
    windows' starting speeds come from, `SMOOTHING_WINDOW_S`) over SPEED_BAND_SIGMAS of what the
    sensor's noise alone gives it (`position_noise`); over 1, the body is accelerating. Noise-free
    data: |α| itself."""
    out = np.zeros(len(run))
    dt = float(np.median(np.diff(run.t))) if len(run) > 1 else 0.0
    length = _smoothing_length(SMOOTHING_WINDOW_S, dt) if dt > 0 else 0
    if not length or len(run) <= length:
        return out
    gain = float(np.linalg.norm(savgol_coeffs(length, 3, deriv=2, delta=dt)))
    for pos in ("theta_m", "theta_l"):
        if pos in run:
            alpha = np.abs(savgol_filter(run[pos], length, 3, deriv=2, delta=dt))
            band = SPEED_BAND_SIGMAS * gain * position_noise(run[pos])
            out = np.maximum(out, alpha / band if band > 0 else alpha)
    return out


SMOOTHING_WINDOW_S = 0.005
"""The local cubic the windows' starting speeds come from spans 5 samples at 1 kHz: the shortest a cubic
fits. What the samples barely resolve (the kinematic error's ripple at k·ω_m and the joint's response to
it) a longer fit smooths away, and every window then starts with a speed error tied to the state, the
same in every run: the fit absorbs it in friction and inertia, which a longer fit biased measurably on
ideal-sensor data. The price is noise, random from window to window, which the window-clustered σ
carries. Figures: docs/BENCHMARKS.md, "Figures behind design choices in the code"."""


def _smoothing_length(window_s: float, dt_s: float) -> int:
    """Samples of the local cubic over `window_s`: odd, and at least the 5 a cubic's derivative needs."""
    return max(5, round(window_s / dt_s) | 1)


def with_smooth_velocities(run: Run, window_s: float = SMOOTHING_WINDOW_S, lag_s: float = 0.0) -> Run:
    """The run with ω_m, ω_l from a centred local cubic fit of the positions (Savitzky–Golay), taken
    `lag_s` before each sample: ω(t − lag) ≈ ω̂ − lag·α̂, α̂ from the same fit.

    Each shooting window starts from the measured state; a drive's own speed is filtered, so it lags
    by a millisecond or more, and starting from it biases every window during accelerations. The lag:
    the replay's semi-implicit Euler (θ ← θ + h·ω_new) holds a speed half a step h behind its position,
    so a window that starts with the speed at the position's instant runs h/2·α ahead all window long.
    Every window starts so during accelerations, and a larger inertia hides it: the inertias came out
    biased by several σ on noise-free data without the lag h/2 (docs/BENCHMARKS.md).
    """
    dt = float(np.median(np.diff(run.t)))
    length = _smoothing_length(window_s, dt)
    columns = dict(run.columns)
    for pos, vel in (("theta_m", "omega_m"), ("theta_l", "omega_l")):
        if pos in columns and len(columns[pos]) > length:
            theta = columns[pos]
            omega = savgol_filter(theta, length, 3, deriv=1, delta=dt)
            if lag_s:
                omega -= lag_s * savgol_filter(theta, length, 3, deriv=2, delta=dt)
            # An encoder at rest reads the same count: that is zero speed, not quantization noise.
            still = np.zeros(len(theta), bool)
            still[1:-1] = (theta[:-2] == theta[1:-1]) & (theta[1:-1] == theta[2:])
            omega[still] = 0.0
            columns[vel] = omega
    return Run(columns, run.meta)


SPEED_BAND_SIGMAS = 3.0
"""A measured speed within this many of its own noise's σ of zero may be a still body (`speed_bands`)."""


def speed_bands(run: Run, window_s: float = SMOOTHING_WINDOW_S) -> dict[str, float]:
    """Per body, the speed the sensor's noise alone gives the smoothed speed (`with_smooth_velocities`),
    times SPEED_BAND_SIGMAS: 0 for ideal data.

    Position noise: a quantizer's, q/√12, when every step is a whole number of the smallest step q (an
    encoder's count); else white noise's, from the third differences' median absolute value (they are
    20σ² in variance and nearly free of the motion at 1 kHz). Seen through the local cubic's derivative
    weights. On a noisy lab run it spared most of the finely stepped intervals and moved the estimates
    by well under their σ (figures: docs/BENCHMARKS.md).
    """
    dt = float(np.median(np.diff(run.t)))
    length = _smoothing_length(window_s, dt)
    gain = float(np.linalg.norm(savgol_coeffs(length, 3, deriv=1, delta=dt)))
    bands = {}
    for pos, vel in (("theta_m", "omega_m"), ("theta_l", "omega_l")):
        if pos not in run or len(run[pos]) <= length:
            continue
        bands[vel] = SPEED_BAND_SIGMAS * gain * position_noise(run[pos])
    return bands


def position_noise(angle: np.ndarray) -> float:
    """The σ of a sampled angle's noise [rad]: a quantizer's q/√12 when every step is a whole number of
    the smallest step q (an encoder's count); else white noise's, from the third differences' median
    absolute value (they are 20σ² in variance and nearly free of the motion at 1 kHz). 0 when it never
    moves or has fewer than four samples."""
    steps = np.abs(np.diff(angle))
    steps = steps[steps > 0]
    q = float(steps.min()) if len(steps) else 0.0
    if q > 0 and np.allclose(steps / q, np.round(steps / q), rtol=0.0, atol=1e-3):
        return q / math.sqrt(12.0)
    if len(angle) < 4:
        return 0.0
    return 1.4826 * float(np.median(np.abs(np.diff(angle, 3)))) / math.sqrt(20.0)


def replay_step(run: Run, dt_s: float) -> float:
    """The integration step a replay of `run` takes: its typical sample interval cut into equal steps
    of at most `dt_s` (as `_Replay` and `model.simulate.replay_rows` cut each interval)."""
    interval = float(np.median(np.diff(run.t))) if len(run) > 1 else dt_s
    return interval / substeps(interval, dt_s)


def _channel_scales(run: Run, channels: list[str], windows: list[Run]) -> dict[str, float]:
    scales = {}
    for ch in channels:
        if ch == "omega_m":
            spread = float(np.sqrt(np.mean(run[ch] ** 2)))
        else:  # positions: how far they move within a window, not where they are
            spread = float(np.sqrt(np.mean(np.concatenate([(w[ch] - w[ch][0]) ** 2 for w in windows]))))
        scales[ch] = spread if spread > 0 else 1.0
    return scales


DIFF_STEP = 1e-2
"""`solve`'s relative finite-difference step (see there)."""
FREE_START_DIFF_STEP = 1e-3
"""`solve`'s relative step on windows with free starts: their residual no longer carries the starts'
ringing, σ shrink to 0.01–0.1 % of the inertias and the stiffness, and a step of 1 % spans tens of σ
(its secant stopped the fit short: drawn gears' costs fell at −3σ of the result)."""
FREE_START_STATES = ("omega_m", "theta_l", "omega_l")
"""The start states `with_free_starts` frees: the speeds (5-sample differences of quantized, noisy
positions) and the load's position, whose error against the motor's is the spring's twist. The motor's
position is the encoder's own reading, its error a fraction of a count."""
START_RANK_RTOL = 1e-8
"""A freed state whose unit sensitivity column adds less than this (QR) to a window's basis is one its
residual does not depend on there (a rigid model's load) or the others already span."""


def _start_step(w: _Window, state: str) -> float:
    """The central-difference step of a window's start `state`: about the noise the measured value
    carries (`position_noise` and the local cubic's gain for speeds), a millionth of the window's
    motion on ideal data; 0 when the window cannot move it (no replay, no such sensor)."""
    if w.replay is None or w.replay.state.get(state) is None:
        return 0.0
    angle = "theta_l" if state.endswith("_l") else "theta_m"
    if angle not in w.run:
        return 0.0
    noise = position_noise(w.run[angle]) or 1e-6 * w.scales.get(angle, 1.0)
    if state.startswith("theta"):
        return noise
    dt = float(np.median(np.diff(w.run.t)))
    length = _smoothing_length(SMOOTHING_WINDOW_S, dt)
    return noise * float(np.linalg.norm(savgol_coeffs(length, 3, deriv=1, delta=dt)))


def _with_start(w: _Window, state: str, delta: float) -> _Window:
    assert w.replay is not None and w.replay.state[state] is not None
    moved = {**w.replay.state, state: float(w.replay.state[state]) + delta}  # type: ignore[arg-type]
    return dataclasses.replace(w, replay=dataclasses.replace(w.replay, state=moved))


class TrajectoryProblem:
    """Residuals of a model against runs over shooting windows, for a set of free parameters."""

    def __init__(
        self,
        model: HarmonicDriveModel,
        runs: list[Run],
        names: list[str],
        window_s: float,
        dt_s: float,
        channels: Sequence[str] = tuple(CHANNELS),
        refine_voltage: bool = True,
    ) -> None:
        """`refine_voltage` off (runs without metadata): a continuous process driven by voltage is
        replayed at `dt_s`, its back-EMF's lag taken out by `emf_lag_inertia`, instead of at a tenth of
        the step, and its stops and reversals at `PLAIN_EVENT_STEP_S`."""
        event_step = EVENT_STEP_S if refine_voltage else PLAIN_EVENT_STEP_S
        self.model = model
        self.names = names
        self.dt_s = dt_s
        self.start = get_values(model, names)
        self.windows: list[_Window] = []
        for run in runs:
            step, continuous = replay_scheme(run, dt_s, refine_voltage)
            coarse_voltage = continuous and run.input_column is not None and replay_mode(run) == "voltage"
            emf_step = 0.0 if refine_voltage or not coarse_voltage else step
            bands = speed_bands(run) if continuous else None
            run = with_smooth_velocities(run, lag_s=replay_step(run, step) / 2)
            seen = [c for c in channels if c in run]
            pieces = shooting_windows(run, window_s, calm=continuous)
            scales = _channel_scales(run, seen, pieces)
            self.windows += [
                _Window(
                    piece,
                    seen,
                    scales,
                    float(piece.t[0] - run.t[0]),
                    step,
                    _Replay.of(piece, seen, scales, step, continuous, bands, event_step)
                    if piece.input_column is not None
                    else None,
                    emf_step,
                )
                for piece in pieces
            ]
        if not self.windows:
            raise UserInputError("no data long enough to fit on (windows of at least 3 samples)")
        # Work in units of each parameter's own starting size, so steps and bounds are comparable.
        self.x_scale = np.array([abs(v) if v != 0 else 1.0 for v in self.start.values()])
        self.priors: dict[str, Prior] = {}
        self.block_sigma = False  # σ also from contiguous blocks of windows (`block_of_residual`)
        self._batched: tuple[list[_Window], list[_Batch]] | None = None  # (of these windows, `_batches`)
        self.prior_weight = 0.0  # λ; 0 with priors: `fit_problem` measures it
        self.diff_step = DIFF_STEP

    def with_priors(self, priors: dict[str, Prior], weight: float = 0.0) -> TrajectoryProblem:
        """The same problem with a prior row λ·(θ − μ)/σ for each free parameter given one (σ > 0)."""
        other = copy.copy(self)
        other.priors = {n: priors[n] for n in self.names if n in priors and priors[n][1] > 0}
        other.prior_weight = weight
        return other

    def prior_rows(self, x: np.ndarray) -> np.ndarray:
        values = self.values(x)
        return np.array([self.prior_weight * (values[n] - mu) / sd for n, (mu, sd) in self.priors.items()])

    def values(self, x: np.ndarray) -> dict[str, float]:
        return {name: float(xi * s) for name, xi, s in zip(self.names, x, self.x_scale, strict=True)}

    def model_with(self, values: dict[str, float]) -> HarmonicDriveModel:
        """The base model with `values` put in (`with_lifted_static`)."""
        return with_lifted_static(self.model, values)

    def residuals(self, x: np.ndarray) -> np.ndarray:
        try:
            model = self.model_with(self.values(x))
        except UserInputError:
            # Outside the model's valid region (e.g. a negative inertia): a large, smooth penalty.
            return np.full(self.size + len(self.priors), 1e3)
        return np.concatenate([self.residuals_of(model), self.prior_rows(x)])

    def residuals_of(self, model: HarmonicDriveModel) -> np.ndarray:
        """The scaled residual of any model on these windows (the same scales, so costs compare)."""
        residual = np.empty(self.size)
        for batch in self._batches():
            batch.replay_into(model, residual)
        at = 0
        plant = None
        for w in self.windows:
            size = len(w.run) * len(w.channels)
            if w.replay is None:  # an irregular time base: `replay_rows` cuts each interval on its own
                plant = plant or Plant(model)
                rows = replay_rows(plant, w.run, replay_mode(w.run), w.step_s, time_s=w.time_s)
                residual[at : at + size] = np.concatenate(
                    [(rows[:, CHANNELS[ch]] - w.run[ch]) / w.scales[ch] for ch in w.channels]
                )
            elif w.start_basis is not None:
                part = residual[at : at + size]
                part -= w.start_basis @ (w.start_basis.T @ part)
            at += size
        return residual

    def with_free_starts(
        self, model: HarmonicDriveModel, states: Sequence[str] = FREE_START_STATES
    ) -> TrajectoryProblem:
        """The same problem with each window's measured start `states` left free: the directions its
        residual takes under small errors of those states (central differences under `model`) are
        projected out of it (variable projection, the basis held), so no parameter is fitted to what a
        noisy start alone makes of a window.

        A window starts from measured positions and 5-sample speeds: the load's position to a few
        encoder counts and its speed to ~1e-3 rad/s, which ring the spring's resonance through the whole
        window; at a drawn gear's truth that ringing was 2/3 of the residual and the joint fit traded
        b_l for f_cl against it (docs/BENCHMARKS.md). Each freed state costs one degree of freedom per
        window (`nuisance`)."""
        windows = [dataclasses.replace(w, start_basis=None) for w in self.windows]
        plain = copy.copy(self)
        plain.windows = windows
        columns: list[np.ndarray] = []
        for state in states:
            step = [_start_step(w, state) for w in windows]
            if not any(step):
                continue
            moved = [plain._moved(model, windows, state, sign, step) for sign in (1.0, -1.0)]
            sizes = [len(w.run) * len(w.channels) for w in windows]
            delta = np.repeat(np.array([h or 1.0 for h in step]), sizes)
            columns.append((moved[0] - moved[1]) / (2 * delta))
        at = 0
        for i, w in enumerate(windows):
            size = len(w.run) * len(w.channels)
            if w.replay is not None and columns:
                sens = np.column_stack([c[at : at + size] for c in columns])
                norms = np.linalg.norm(sens, axis=0)
                q, r = np.linalg.qr(sens / np.where(norms > 0, norms, 1.0))  # radians and rad/s alike
                diag = np.abs(np.diag(r))
                keep = diag > START_RANK_RTOL
                if np.any(keep):
                    windows[i] = dataclasses.replace(w, start_basis=np.ascontiguousarray(q[:, keep]))
            at += size
        other = copy.copy(self)
        other.windows = windows
        other._batched = None
        other.diff_step = FREE_START_DIFF_STEP
        return other

    def _moved(
        self, model: HarmonicDriveModel, windows: list[_Window], state: str, sign: float, step: list[float]
    ) -> np.ndarray:
        """`model`'s residual with each window's start `state` moved by sign × its step (0: left)."""
        moved = copy.copy(self)
        moved.windows = [
            _with_start(w, state, sign * h) if h else w for w, h in zip(windows, step, strict=True)
        ]
        moved._batched = None
        return moved.residuals_of(model)

    @property
    def nuisance(self) -> int:
        """Degrees of freedom the freed start states take (`with_free_starts`): the residual's rows less
        these and the parameters are what its variance is measured over."""
        return sum(w.start_basis.shape[1] for w in self.windows if w.start_basis is not None)

    def _batches(self) -> list[_Batch]:
        """The windows with a prepared replay, batched by what their replays share (the plant's emf
        inertia, the input mode, the channels), built once per set of windows."""
        if self._batched is not None and self._batched[0] is self.windows:
            return self._batched[1]
        groups: dict[tuple[float, str, tuple[int, ...]], list[tuple[_Window, int]]] = {}
        at = 0
        for w in self.windows:
            if w.replay is not None:
                key = (w.emf_step_s, w.replay.mode, tuple(w.replay.outputs))
                groups.setdefault(key, []).append((w, at))
            at += len(w.run) * len(w.channels)
        batches = [_Batch.of(members, key[0]) for key, members in groups.items()]
        self._batched = (self.windows, batches)
        return batches

    @property
    def size(self) -> int:
        return sum(len(w.run) * len(w.channels) for w in self.windows)

    @property
    def window_of_residual(self) -> np.ndarray:
        """For each element of the residual, the index of its window (the clusters of the covariance)."""
        sizes = [len(w.run) * len(w.channels) for w in self.windows]
        return np.repeat(np.arange(len(sizes)), sizes)

    def split(self, every: int) -> tuple[TrajectoryProblem, TrajectoryProblem]:
        """(training, held-out): every `every`-th window is held out, so both span every run."""
        train, test = copy.copy(self), copy.copy(self)
        train.windows = [w for i, w in enumerate(self.windows) if i % every != every - 1]
        test.windows = [w for i, w in enumerate(self.windows) if i % every == every - 1]
        if not train.windows or not test.windows:
            raise UserInputError(f"too little data for held-out windows: {len(self.windows)} window(s)")
        return train, test

    def for_parameters(self, model: HarmonicDriveModel, names: list[str]) -> TrajectoryProblem:
        """The same windows and scales, with another base model and free parameters (priors dropped)."""
        other = copy.copy(self)
        other.model, other.names = model, names
        other.start = get_values(model, names)
        other.x_scale = np.array([abs(v) if v != 0 else 1.0 for v in other.start.values()])
        other.priors, other.prior_weight = {}, 0.0
        return other


STATIC_OF = {"f_cl": "f_sl", "f_cm": "f_sm"}
"""A Coulomb level and the static level the schema keeps at or above it."""


def with_lifted_static(model: HarmonicDriveModel, values: dict[str, float]) -> HarmonicDriveModel:
    """`with_values`, a static level not among `values` raised to its Coulomb level where that passes it.

    A fit that frees f_cl but not f_sl (a lab file: nothing tells the load's breakaway apart) met the
    schema's f_sl ≥ f_cl as a wall at the start's f_sl, sat on it with a σ of 1e-8 N·m and traded the
    rest of the load's Coulomb friction for viscous friction (issue 25's gear: f_cl 0.349 at f_sl 0.35,
    truth 2.16). Wherever the values alone make a valid model, nothing changes."""
    try:
        return with_values(model, values)
    except UserInputError:
        lifted = dict(values)
        for coulomb, static in STATIC_OF.items():
            if coulomb in values and static not in values:
                held = get_values_or_nan(model, static)
                if values[coulomb] > held:
                    lifted[static] = values[coulomb]
        if lifted == values:
            raise
        return with_values(model, lifted)


def get_values_or_nan(model: HarmonicDriveModel, name: str) -> float:
    try:
        return get_values(model, [name])[name]
    except UserInputError:
        return math.nan


def fit_trajectories(
    model: HarmonicDriveModel,
    runs: list[Run],
    names: list[str],
    window_s: float = 0.1,
    dt_s: float = 1e-4,
    max_evaluations: int = 60,
) -> TrajectoryFit:
    """Refine the named parameters of `model` on the runs; estimates with standard errors."""
    if not names:
        raise UserInputError("a trajectory fit needs at least one free parameter")
    return fit_problem(TrajectoryProblem(model, runs, names, window_s, dt_s), max_evaluations)


def fit_problem(problem: TrajectoryProblem, max_evaluations: int = 60) -> TrajectoryFit:
    """Refine the problem's free parameters of its model on its windows; estimates with standard errors.

    With priors and no λ given, λ is first guessed from the start's residual as if it were white, then
    measured at the optimum; when the two differ by more than a quarter, the fit goes on from there with
    the measured λ (a few evaluations: the optimum moves little)."""
    r0 = problem.residuals_of(problem.model)
    x0 = start_point(problem)
    notes = []
    if problem.priors and problem.prior_weight <= 0:
        problem = problem.with_priors(problem.priors, _rms(r0))
        result, estimates = solve(problem, max_evaluations, x0)
        weight = prior_weight(problem, result.jac, result.fun)
        if not 0.8 <= weight / problem.prior_weight <= 1.25:
            notes.append(f"least_squares: {result.message} ({result.nfev} evaluations, λ guessed)")
            problem = problem.with_priors(problem.priors, weight)
            result, estimates = solve(problem, max(max_evaluations // 3, 10), result.x)
    else:
        result, estimates = solve(problem, max_evaluations, x0)
    final = {p.name: p.estimate for p in estimates}
    fitted = problem.model_with(final)
    x_final = np.array([final[n] for n in problem.names]) / problem.x_scale
    notes.append(f"least_squares: {result.message} ({result.nfev} evaluations)")
    if problem.priors:
        notes.append(
            f"priors on {', '.join(problem.priors)} (the staged estimates, each with its σ),"
            f" weighed λ = {problem.prior_weight:.3g}"
        )
    after = _rms(problem.residuals(x_final)[: problem.size])
    data_only = data_only_estimates(problem, result.jac, result.fun, result.x) if problem.priors else {}
    fit = TrajectoryFit(fitted, estimates, _rms(r0), after, len(r0), notes, problem.prior_weight, data_only)
    fit.profile_direction, fit.curvature_sigma = profile_directions(problem, result.jac, result.fun)
    return fit


def profile_directions(
    problem: TrajectoryProblem, jac: np.ndarray, fun: np.ndarray
) -> tuple[dict[str, dict[str, float]], dict[str, float]]:
    """For each free parameter p, the move of every free parameter per unit move of p that keeps the
    others at their best (the linearized profile: column p of the trajectory rows' covariance over its
    diagonal, in natural units), and p's σ from that covariance with white residuals. Correlated
    parameters (a breakaway's f_cl and static_factor) share a valley; moving one alone climbs its wall
    and overstates how well the data pin it."""
    m = problem.size
    data_jac = jac[:m]
    s2 = float(fun[:m] @ fun[:m]) / max(m - jac.shape[1] - problem.nuisance, 1)
    cov = np.linalg.pinv(data_jac.T @ data_jac) * np.outer(problem.x_scale, problem.x_scale)
    directions: dict[str, dict[str, float]] = {}
    sigmas: dict[str, float] = {}
    for i, name in enumerate(problem.names):
        if cov[i, i] > 0 and np.all(np.isfinite(cov[:, i])):
            directions[name] = {other: float(cov[j, i] / cov[i, i]) for j, other in enumerate(problem.names)}
            sigmas[name] = math.sqrt(float(cov[i, i]) * s2)
    return directions, sigmas


def prior_weight(problem: TrajectoryProblem, jac: np.ndarray, fun: np.ndarray) -> float:
    """λ = s·√c at an optimum: the trajectory rows' RMS s, and c, the median over parameters of the
    window-clustered variance over the white one (how many samples' worth one correlated window is).
    Then a prior row carries the weight its σ gives it beside the trajectories' own information."""
    m = problem.size
    data_jac, data_fun = jac[:m], fun[:m]
    s2 = float(data_fun @ data_fun) / max(m - jac.shape[1] - problem.nuisance, 1)
    white = np.diag(np.linalg.pinv(data_jac.T @ data_jac)) * s2
    # The plain sandwich: c measures the windows' correlation, not how few windows see a parameter
    # (with the jackknife c took in the leverage of parameters few windows see; docs/BENCHMARKS.md).
    groups = problem.window_of_residual
    clustered = np.diag(window_robust_covariance(data_jac, data_fun, groups, s2, leave_one_out=False))
    ok = (white > 0) & np.isfinite(clustered) & (clustered > 0)
    inflation = float(np.median(clustered[ok] / white[ok])) if np.any(ok) else 1.0
    return math.sqrt(s2 * max(inflation, 1.0))


def start_point(problem: TrajectoryProblem) -> np.ndarray:
    """The scaled start, nudged strictly inside the bounds (positive parameters stay positive)."""
    x0 = np.array([problem.start[n] for n in problem.names]) / problem.x_scale
    return np.maximum(x0, np.where(np.isfinite(_lower_bounds(problem.names)), 1e-9, -np.inf))


def _lower_bounds(names: list[str]) -> np.ndarray:
    return np.array([-np.inf if SIGNED.fullmatch(n) else 0.0 for n in names])


def solve(
    problem: TrajectoryProblem, max_evaluations: int, x0: np.ndarray | None = None
) -> tuple[OptimizeResult, list[ParameterEstimate]]:
    """Bounded least squares on the problem's residual, then the estimates with their uncertainty.

    Friction makes the residual piecewise smooth in the parameters: a relative step of 1e-2 keeps
    finite differences above the jumps that stick/slip timing adds (1e-3 stalls on them), and short
    windows keep those jumps few (0.5 s windows stall, 0.1 s windows recover exact values).
    """
    names = problem.names
    result = least_squares(
        problem.residuals,
        start_point(problem) if x0 is None else x0,
        bounds=(_lower_bounds(names), np.full(len(names), np.inf)),
        method="trf",
        diff_step=problem.diff_step,
        x_scale=1.0,
        max_nfev=max_evaluations,
    )
    return result, _uncertainty(problem, result.x, result.jac, result.fun)


def _rms(residual: np.ndarray) -> float:
    return float(np.sqrt(np.mean(residual**2)))


def window_robust_covariance(
    jac: np.ndarray,
    fun: np.ndarray,
    groups: np.ndarray,
    s2: float,
    prior_jac: np.ndarray | None = None,
    prior_variance: float = 0.0,
    leave_one_out: bool = True,
) -> np.ndarray:
    """Covariance of the estimates, windows taken as independent clusters (the sandwich estimator).

    Within a window the residual is one smooth curve (it starts from a noisy measured state and the
    replay integrates every error), so its samples are far from independent and s²·(JᵀJ)⁻¹ is several
    times overconfident. Windows restart from the measurement, so they are nearly independent of each
    other: the sandwich (JᵀJ)⁻¹·Σ_w (J_wᵀr_w)(J_wᵀr_w)ᵀ·(JᵀJ)⁻¹ with the G/(G−1) small-sample factor;
    for the estimates' σ in its leave-one-window-out form (`_jackknife_moves`), since the residual at
    the optimum understates a window's own noise by as much as the window pulled the fit. With fewer
    than 10 windows the sandwich is itself too noisy, and the white-residual form is kept. Prior rows
    (`prior_jac`, each of variance λ²) add their information to the bread and to the meat.
    """
    n = jac.shape[1]
    info = np.zeros((n, n)) if prior_jac is None else prior_jac.T @ prior_jac
    bread = np.linalg.pinv(jac.T @ jac + info)
    count = int(groups.max()) + 1 if groups.size else 0
    if count < 10 or len(groups) != len(fun):
        return bread @ (s2 * (jac.T @ jac) + prior_variance * info) @ bread
    scores = np.zeros((count, n))
    np.add.at(scores, groups, jac * fun[:, None])
    if leave_one_out:
        moves = _jackknife_moves(jac, groups, scores, jac.T @ jac + info, bread)
        return moves.T @ moves * (count - 1) / count + bread @ (prior_variance * info) @ bread
    meat = scores.T @ scores * count / (count - 1) + prior_variance * info
    return bread @ meat @ bread


def _jackknife_moves(
    jac: np.ndarray, groups: np.ndarray, scores: np.ndarray, whole: np.ndarray, bread: np.ndarray
) -> np.ndarray:
    """Per window, how far leaving it out would move the estimates: (A − J_wᵀJ_w)⁻¹·J_wᵀr_w, with its
    score J_wᵀr_w from `scores` and A (`whole`) the information of all windows and priors (the cluster
    jackknife, CR3 in econometrics).

    The plain sandwich takes A⁻¹·J_wᵀr_w, but a window that carries a good share h of a parameter's
    information has pulled the fit towards itself, and its residual at the optimum holds only about
    (1 − h) of its noise's score, and on the bench campaign single windows carry a good share of the
    inertias' information (docs/BENCHMARKS.md). Where leaving a window out leaves the rest singular
    (only it sees a parameter), its plain score is taken: the data do not say more."""
    gram = np.zeros((len(scores), jac.shape[1], jac.shape[1]))
    np.add.at(gram, groups, jac[:, :, None] * jac[:, None, :])
    out = np.empty_like(scores)
    for w in range(len(scores)):
        try:
            out[w] = np.linalg.solve(whole - gram[w], scores[w])
        except np.linalg.LinAlgError:
            out[w] = bread @ scores[w]
    return out


BLOCKS = 10
"""Contiguous blocks of windows for the block jackknife of σ (`block_of_residual`): the fewest the
sandwich takes (`window_robust_covariance` keeps the white form under 10 groups)."""


def block_of_residual(problem: TrajectoryProblem, blocks: int) -> np.ndarray:
    """For each element of the residual, its block: the windows cut into `blocks` runs of consecutive
    windows (in time order within each run).

    The window jackknife sees windows as independent draws of one behaviour; a model that misses part
    of the behaviour (issue 25's gear: J_m −3.8 % from the slow reversals alone, +0.2 % from the moves)
    is right within σ nowhere: the estimates of neighbouring windows move together, and only leaving
    out a stretch of the record shows it. The σ reported is the larger of the two."""
    windows = problem.window_of_residual
    count = int(windows.max()) + 1 if windows.size else 0
    return (windows * blocks) // max(count, 1)


def _uncertainty(
    problem: TrajectoryProblem, x: np.ndarray, jac: np.ndarray, fun: np.ndarray
) -> list[ParameterEstimate]:
    n = jac.shape[1]
    m = len(fun) - len(problem.priors)  # trajectory rows; the prior rows follow them
    s2 = float(fun[:m] @ fun[:m]) / max(m - n - problem.nuisance, 1)
    # Column-normalized Jacobian: its conditioning says which directions the data cannot see.
    norms = np.linalg.norm(jac, axis=0)
    blind = norms == 0
    jn = jac / np.where(blind, 1.0, norms)
    _, sv, vt = np.linalg.svd(jn, full_matrices=False)
    weak = sv < 1e-6 * sv[0] if sv.size and sv[0] > 0 else np.ones(n, bool)
    confounded = np.zeros(n, bool)
    for row, is_weak in zip(vt, weak, strict=True):
        if is_weak:
            confounded |= np.abs(row) > 0.3
    try:
        cov = window_robust_covariance(
            jac[:m], fun[:m], problem.window_of_residual, s2, jac[m:], problem.prior_weight**2
        )
        se = np.sqrt(np.clip(np.diag(cov), 0.0, None))
        if problem.block_sigma:
            blocks = block_of_residual(problem, BLOCKS)
            by_block = window_robust_covariance(
                jac[:m], fun[:m], blocks, s2, jac[m:], problem.prior_weight**2
            )
            se = np.maximum(se, np.sqrt(np.clip(np.diag(by_block), 0.0, None)))
    except np.linalg.LinAlgError:
        se = np.full(n, math.inf)
    out = []
    for i, name in enumerate(problem.names):
        start = problem.start[name]
        value = float(x[i] * problem.x_scale[i])
        std = float(se[i] * problem.x_scale[i])
        note = ""
        if blind[i]:
            note = "the data do not depend on it"
        elif confounded[i]:
            note = "confounded with other parameters in these data"
        elif not math.isfinite(std) or (std > abs(value) and abs(value) > 0):
            note = f"standard error {std:.3g} exceeds the estimate"
        identifiable = not note
        out.append(
            ParameterEstimate(
                name,
                start,
                value if identifiable else start,
                std if identifiable else None,
                identifiable,
                note,
            )
        )
    return out
