"""The truth harness: every metric an experiment reports, checked against the simulated plant's truth.

A run is played on the in-process simulated rig with truth recording on (`SimRig.record_truth`): beside
every sample the plant's true states and torques (`sim_backend.simulated_drive.TRUTH_COLUMNS`). Each
metric key of each experiment has a registered `Check`: a function that computes the metric's value by
the metric's own definition from the truth (true angles instead of sensor readings, the plant's true
friction torque instead of the current, the plant's law where the metric names a plant property), and a
tolerance with its reason. `uncovered` names the metric keys of a run no check covers, so a new metric
without a check fails the completeness test (tests/test_truth_harness.py).

Two kinds of truth are used, and each check says which:
- *same definition, true signals*: the metric's formula applied to the truth in the same rows (what the
  sensors, the current as a torque proxy and the sampling do to the figure);
- *plant law*: the property the metric names, from the model's parameters at the conditions of the run
  (what the experiment's design does to the figure: e.g. friction against speed measured at other places).
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from model import kernel as k
from model.params import HarmonicDriveModel
from model.registry import FL, Law, P
from model.run import Run
from rig.config import RigConfig, load_rig_config
from rig.experiments import experiment_named
from rig.experiments.base import (
    Results,
    RigContext,
    context_from_run,
    segment_rows,
    segments_of,
)
from rig.runner import make_params, run_experiment
from rig.store.runs import RunStore
from sim_backend.inprocess import SimRig

CFG: RigConfig = load_rig_config("sim")


@dataclass
class TruthRun:
    """One experiment's run on the simulated rig with the plant's truth aligned to its rows."""

    name: str
    run: Run
    truth: dict[str, np.ndarray]  # TRUTH_COLUMNS, row i = the truth of the run's row i
    params: Any
    ctx: RigContext
    results: Results
    metrics: dict[str, Any]
    model: HarmonicDriveModel
    p: np.ndarray  # the plant's parameter vector (model.kernel layout)
    flags: np.ndarray
    cache: dict[str, Any] = field(default_factory=dict)  # truths computed once per run

    @property
    def r(self) -> float:
        return self.ctx.gear_ratio

    @property
    def quantum_rad(self) -> float:
        """The motor encoder's step [rad]."""
        counts = self.ctx.config.sensors.encoder_counts_per_rev
        return 2 * math.pi / counts if counts else 0.0

    def friction(self, rows: slice | np.ndarray) -> np.ndarray:
        """The plant's true friction seen from the motor, F_m + r·F_l, per cycle [N·m]."""
        return self.truth["f_m"][rows] + self.r * self.truth["f_l"][rows]


def play(
    name: str,
    overrides: dict[str, Any],
    store: RunStore,
    model: HarmonicDriveModel | None = None,
    config: RigConfig = CFG,
    rig: SimRig | None = None,
) -> TruthRun:
    """Run `name` on a simulated rig recording the truth; the run, its analysis and the aligned truth."""
    if rig is None:
        rig = SimRig(config, model=model)
    rig.record_truth()
    outcome = run_experiment(name, config, overrides, store, rig=rig)
    assert outcome.status == "complete", outcome.reason
    run = store.read(outcome.run_id)
    truth = rig.truth()
    # The run's clock starts at its first sample (the runner's settle), the rig's at its first cycle.
    period = 1.0 / config.sample_rate_hz
    at = np.rint((run["t"] - run["t"][0]) / period).astype(np.int64)
    assert at[0] == 0 and at[-1] < len(truth["t"]), "truth rows do not line up with the run's samples"
    np.testing.assert_allclose(truth["t"][at] - truth["t"][0], run["t"] - run["t"][0], atol=1e-6 * period)
    aligned = {column: values[at] for column, values in truth.items()}
    experiment = experiment_named(name)
    params = make_params(experiment, overrides)
    ctx = context_from_run(run)
    results = experiment.analyze(run, params, ctx)
    return TruthRun(
        name,
        run,
        aligned,
        params,
        ctx,
        results,
        dict(outcome.metrics),
        rig.model,
        rig.plant.p,
        rig.plant.flags,
    )


TruthOf = Callable[[TruthRun, str], float]
"""The value the truth gives for a metric key, by the metric's own definition."""


@dataclass(frozen=True)
class Check:
    """How one metric (or a family of keys, by regular expression) is checked against the truth."""

    pattern: str  # a regular expression the whole metric key matches
    truth: TruthOf
    abs_tol: float = 0.0
    rel_tol: float = 0.0
    reason: str = ""  # why the tolerance is what it is
    run_tol: Callable[[TruthRun], float] | None = None  # a tolerance the run's settings set, added
    bounds: Callable[[TruthRun, str], tuple[float, float]] | None = None
    """For a metric that is itself a bound (a bracket's end, a stated resolution): the interval (lo, hi]
    in which the *truth* must lie for this measured value, instead of a tolerance around the truth."""

    def tolerance(self, truth_value: float) -> float:
        return self.abs_tol + self.rel_tol * abs(truth_value)


@dataclass
class Outcome:
    key: str
    measured: float
    truth: float
    tolerance: float
    check: Check
    bounds: tuple[float, float] | None = None
    ok: bool = field(init=False)

    def __post_init__(self) -> None:
        if self.bounds is not None:
            self.ok = self.bounds[0] < self.truth <= self.bounds[1]
            return
        both_nan = math.isnan(self.measured) and math.isnan(self.truth)
        self.ok = both_nan or abs(self.measured - self.truth) <= self.tolerance

    def line(self) -> str:
        if self.bounds is not None:
            return (
                f"{self.key}: measured {self.measured:.6g}, truth {self.truth:.6g} not in"
                f" ({self.bounds[0]:.6g}, {self.bounds[1]:.6g}] ({self.check.reason})"
            )
        return (
            f"{self.key}: measured {self.measured:.6g}, truth {self.truth:.6g}, |diff| "
            f"{abs(self.measured - self.truth):.3g} > {self.tolerance:.3g} ({self.check.reason})"
        )


CHECKS: dict[str, list[Check]] = {}


def check_for(experiment: str, key: str) -> Check | None:
    for check in CHECKS.get(experiment, []):
        if re.fullmatch(check.pattern, key):
            return check
    return None


def uncovered(tr: TruthRun) -> list[str]:
    """The run's metric keys that no registered check covers."""
    return [key for key in tr.metrics if check_for(tr.name, key) is None]


def evaluate(tr: TruthRun) -> list[Outcome]:
    """Every covered metric of the run against its truth."""
    out = []
    for key, value in tr.metrics.items():
        check = check_for(tr.name, key)
        if check is None or isinstance(value, str):
            continue
        truth_value = float(check.truth(tr, key))
        bounds = check.bounds(tr, key) if check.bounds is not None else None
        tolerance = check.tolerance(truth_value) + (check.run_tol(tr) if check.run_tol is not None else 0.0)
        out.append(Outcome(key, float(value), truth_value, tolerance, check, bounds))
    return out


def _add(experiment: str, *checks: Check) -> None:
    CHECKS.setdefault(experiment, []).extend(checks)


def _param(name: str) -> TruthOf:
    """A metric that echoes a parameter: its truth is the parameter."""
    return lambda tr, key: float(getattr(tr.params, name))


def _count(name: str) -> TruthOf:
    return lambda tr, key: float(len(getattr(tr.params, name)))


ECHO = "a parameter echoed: exact"


def true_run(tr: TruthRun) -> Run:
    """The run with its sensors replaced by the truth: θ_m, ω_m, θ_l true, and i_a the current that
    holds the plant's true friction and load, (F_m + r·(F_l + τ_ext))/K_m (K_m·i_a less the inertial
    torque). The analysis of it is each metric's own definition applied to the truth."""
    current = (tr.truth["f_m"] + tr.r * (tr.truth["f_l"] + tr.truth["tau_ext"])) / tr.p[P.K_M]
    columns = {"theta_m": tr.truth["theta_m"], "omega_m": tr.truth["omega_m"], "theta_l": tr.truth["theta_l"]}
    return _replaced(tr.run, {**columns, "i_a": current})


def _same_analysis(tr: TruthRun, key: str) -> float:
    """The metric from the experiment's own analysis of the true run (`true_run`)."""
    if "same_analysis" not in tr.cache:
        tr.cache["same_analysis"] = experiment_named(tr.name).analyze(true_run(tr), tr.params, tr.ctx).metrics
    return float(tr.cache["same_analysis"].get(key, math.nan))


# --- speed-sweep, load-variation: friction against speed ------------------------------------------------


def _windows(tr: TruthRun, prefix: str, settle_s: float) -> list[tuple[float, slice]]:
    """(set speed, averaged rows) of each constant-speed segment, as `friction_table` takes them."""
    skip = tr.ctx.cycles(settle_s)
    out = []
    for seg in segments_of(tr.run, prefix + "v"):
        rows = slice(int(seg["start"]) + skip, int(seg["start"]) + int(seg["cycles"]))
        out.append((float(tr.run["setpoint"][rows.start]), rows))
    return out


def _centre(tr: TruthRun, windows: list[tuple[float, slice]]) -> float:
    """The place a sweep reports friction at: its `centre_rad` when it reports one (checked on its own),
    else the median of its windows' true mean θ_m."""
    if "centre_rad" in tr.metrics:
        return float(tr.metrics["centre_rad"])
    return float(np.median([np.mean(tr.truth["theta_m"][rows]) for _, rows in windows]))


def _law_friction_vs_speed(
    tr: TruthRun, windows: list[tuple[float, slice]], centre: float
) -> tuple[np.ndarray, np.ndarray]:
    """(true mean ω_m, the plant's steady moving friction F_m + r·F_l) per window, at one place: the
    motor's law averaged over one motor turn about `centre` (its per-turn ripple averages out, as it does
    over whole turns), the load's law at ω_l = r·ω_m (no position dependence). The law, not the true
    torques: the seed's load sticks and slips at low speed (its kinematic error's speed A·k·ω_m exceeds
    r·ω_m), which lowers its mean friction; that is neither Coulomb nor viscous friction."""
    places = centre + np.linspace(-np.pi, np.pi, 720, endpoint=False)
    load_law = int(tr.flags[FL.LOAD_LAW])
    b_l = tr.p[P.B_L] if load_law != Law.NONE else 0.0
    speeds, friction = [], []
    for _, rows in windows:
        omega = float(np.mean(tr.truth["omega_m"][rows]))
        t_s = float(np.mean(tr.truth["t_s"][rows]))
        time_s = float(np.mean(tr.truth["t"][rows]))
        motor = k.steady_motor_friction(tr.p, tr.flags, places, np.full(places.shape, omega), t_s, time_s)
        omega_l = tr.r * omega
        moving_l, _ = k.load_levels(tr.p, load_law, abs(omega_l))
        speeds.append(omega)
        friction.append(float(np.mean(motor)) + tr.r * (math.copysign(moving_l, omega) + b_l * omega_l))
    return np.asarray(speeds), np.asarray(friction)


def _line_fit(speeds: np.ndarray, friction: np.ndarray, sign: float) -> tuple[float, float]:
    """(level, slope) of |friction| = level + slope·|ω| over the windows of one direction."""
    pick = np.sign(speeds) == sign
    slope, level = np.polyfit(np.abs(speeds[pick]), np.abs(friction[pick]), 1)
    return float(level), float(slope)


def _sweep_law(tr: TruthRun, key: str) -> float:
    windows = _windows(tr, "", tr.params.settle_s)
    speeds, friction = _law_friction_vs_speed(tr, windows, _centre(tr, windows))
    sign = 1.0 if "_pos_" in key else -1.0
    level, slope = _line_fit(speeds, friction, sign)
    return level if key.startswith("coulomb") else slope


_add(
    "speed-sweep",
    Check("speeds", _count("speeds_rad_s"), reason=ECHO),
    Check(
        "centre_rad",
        _same_analysis,
        abs_tol=2 * 2 * math.pi / 131072,
        reason="the same windows on the true θ_m: the encoder's rounding",
    ),
    Check(
        "coverage_min",
        _same_analysis,
        abs_tol=2 * 2 * math.pi / 131072 / (2 * math.pi),
        reason="the share of its whole turns a window covers, on the true θ_m: the encoder's rounding at"
        " both ends",
    ),
    Check(
        "windows_load_unsteady",
        _same_analysis,
        abs_tol=1.0,
        reason="the same rule on the true θ_l; 2 µrad noise can tip one window at the 5 % edge",
    ),
    Check(
        r"coulomb_(pos|neg)_nm",
        _sweep_law,
        rel_tol=0.02,
        reason="plant law at the sweep's centre (one turn about it): issue 30's 2 %",
    ),
    Check(
        r"viscous_(pos|neg)_nm_s_rad",
        _sweep_law,
        rel_tol=0.10,
        reason="plant law at the sweep's centre: issue 30's 10 % (C·k_v + b_m + r²·b_l on the seed)",
    ),
)


# --- position-friction ----------------------------------------------------------------------------------


def _steady_rows(tr: TruthRun) -> np.ndarray:
    skip = tr.ctx.cycles(tr.params.settle_s)
    return np.concatenate(
        [
            np.arange(int(s["start"]) + skip, int(s["start"]) + int(s["cycles"]))
            for s in segments_of(tr.run, "pass")
        ]
    )


def _pf_true_grid(tr: TruthRun) -> dict[str, np.ndarray]:
    from rig.experiments.position_friction import position_grid

    rows = _steady_rows(tr)
    direction = np.sign(tr.run["setpoint"][rows])
    return position_grid(tr.truth["theta_m"][rows], direction, tr.friction(rows), tr.params.bin_rad)


def _pf_grid_metric(tr: TruthRun, key: str) -> float:
    grid = _pf_true_grid(tr)
    column = "mean_nm" if key.startswith("asymmetry") else "half_diff_nm"
    values = grid[column]
    return float({"mean": np.mean(values), "min": np.min(values), "max": np.max(values)}[key.split("_")[1]])


def _speed_factor(tr: TruthRun) -> float:
    """1 + k_v·(|ω| − v_c) of the article law at the passes' speed."""
    return 1.0 + tr.p[P.K_V] * (tr.params.speed_rad_s - tr.p[P.V_C])


def _pf_quad(tr: TruthRun, key: str) -> float:
    """The article law's quadratic at the passes' speed, plus what does not depend on position: the
    periodic part's mean a0/2, the motor's viscous b_m·|ω| and the load's friction r·|F_l| (true)."""
    factor = _speed_factor(tr)
    if key.startswith("quad_s1"):
        return float(tr.p[P.S1] * factor)
    if key.startswith("quad_s2"):
        return float(tr.p[P.S2] * factor)
    rows = _steady_rows(tr)
    load = tr.r * float(np.mean(np.abs(tr.truth["f_l"][rows])))
    return float(tr.p[P.S3] * factor + 0.5 * tr.p[P.A0] + tr.p[P.B_M] * tr.params.speed_rad_s + load)


def _true_fourier(tr: TruthRun) -> tuple[np.ndarray, np.ndarray]:
    n = tr.params.harmonics
    return tr.p[P.A0 + 1 : P.A0 + 1 + n], tr.p[P.B1 : P.B1 + n]


def _pf_ripple(tr: TruthRun, key: str) -> float:
    """Peak-to-peak of the plant's periodic part P(θ_m) (harmonics 1..N) on the analysis' angle grid."""
    from rig.experiments.position_friction import TURN_RAD, fourier_basis

    a, b = _true_fourier(tr)
    centres = (np.arange(tr.params.angle_bins) + 0.5) * TURN_RAD / tr.params.angle_bins
    return float(np.ptp(fourier_basis(centres, len(a)) @ np.column_stack([a, b]).ravel()))


def _pf_dominant(tr: TruthRun, key: str) -> float:
    a, b = _true_fourier(tr)
    return float(np.argmax(np.hypot(a, b)) + 1)


def _pf_stroke(tr: TruthRun, key: str) -> float:
    return float(np.ptp(tr.truth["theta_m"][_steady_rows(tr)]))


_add(
    "position-friction",
    Check("speed_rad_s", _param("speed_rad_s"), reason=ECHO),
    Check("stroke_rad", _pf_stroke, abs_tol=2 * 2 * math.pi / 131072, reason="encoder rounding at both ends"),
    Check(
        r"friction_(mean|min|max)_nm",
        _pf_grid_metric,
        rel_tol=2e-3,
        reason="true F_m + r·F_l in the same bins; current noise (5 mA) and the loop's inertial torque"
        " average out over a bin of whole turns",
    ),
    Check(
        "asymmetry_mean_nm",
        _pf_grid_metric,
        abs_tol=2e-4,
        reason="true friction's direction-independent part in the same bins (0 on the seed); the"
        " inertial torque of the loop's speed ripple, a few 1e-5 N·m, bounds it",
    ),
    Check(
        r"quad_s1_nm_rad2",
        _pf_quad,
        rel_tol=0.02,
        reason="plant law: s1 is 1.6e-6 N·m/rad², 2 % of it is 1e-4 N·m over a 150 rad stroke",
    ),
    Check(r"quad_s2_nm_rad", _pf_quad, rel_tol=0.01, reason="plant law; 1 % as s1's"),
    Check(r"quad_s3_nm", _pf_quad, rel_tol=0.005, reason="plant law; 0.5 %: the level, best determined"),
    Check(
        "ripple_pp_nm",
        _pf_ripple,
        rel_tol=0.03,
        reason="plant law P(θ); the velocity loop does not hold the speed exactly, so J·dω/dt at each"
        " harmonic adds a few % in quadrature",
    ),
    Check("dominant_harmonic", _pf_dominant, reason="plant law: the largest |a_n + j·b_n|, exact"),
)


# --- pulse ----------------------------------------------------------------------------------------------


def _pulse_rows(tr: TruthRun) -> list[tuple[slice, slice]]:
    from rig.experiments.pulse import pulse_labels

    out = []
    for index in range(tr.params.count):
        on_label, off_label = pulse_labels(index)
        out.append((segment_rows(tr.run, on_label), segment_rows(tr.run, off_label)))
    return out


def _pulse_displacements(tr: TruthRun) -> np.ndarray:
    theta = tr.truth["theta_m"]
    return np.asarray([theta[off.stop - 1] - theta[on.start] for on, off in _pulse_rows(tr)])


def _pulse_displacement(tr: TruthRun, key: str) -> float:
    d = _pulse_displacements(tr)
    forward = np.arange(len(d)) % 2 == 0
    if key == "net_drift_rad":
        return float(np.sum(d))
    if key == "displacement_spread_rad":
        return float(np.std(np.abs(d)))
    pick = {"mean_displacement_rad": slice(None), "mean_displacement_pos_rad": forward,
            "mean_displacement_neg_rad": ~forward}[key]  # fmt: skip
    return float(np.mean(np.abs(d[pick])))


def _pulse_peak_speed(tr: TruthRun, key: str) -> float:
    """Mean over pulses of the true motor speed's peak |ω_m| over pulse and rest."""
    omega = tr.truth["omega_m"]
    return float(np.mean([np.max(np.abs(omega[on.start : off.stop])) for on, off in _pulse_rows(tr)]))


def _pulse_peak_current(tr: TruthRun, key: str) -> float:
    """Mean over pulses of the peak |(u − K_b·ω_m)/R| at the samples, with the true ω_m."""
    u, omega = tr.run["u"], tr.truth["omega_m"]
    peaks = []
    for on, _ in _pulse_rows(tr):
        current = (u[on] - tr.p[P.K_B] * omega[on]) / tr.p[P.R_ARM]
        peaks.append(float(np.max(np.abs(current))))
    return float(np.mean(peaks))


def _pulse_breakaway(tr: TruthRun, key: str) -> float:
    """Mean over pulses of the time the true θ_m first departs by move_threshold_rad (between samples)."""
    theta, rate = tr.truth["theta_m"], tr.ctx.rate_hz
    times = []
    for on, off in _pulse_rows(tr):
        moved = np.abs(theta[on.start : off.stop] - theta[on.start])
        i = int(np.flatnonzero(moved > tr.params.move_threshold_rad)[0])
        fraction = (tr.params.move_threshold_rad - moved[i - 1]) / (moved[i] - moved[i - 1])
        times.append((i - 1 + fraction) / rate)
    return float(np.mean(times))


def _pulse_stop(tr: TruthRun, key: str) -> float:
    """Mean over pulses of the time from the pulse's end until the motor is stuck for good (true)."""
    stuck = tr.truth["stuck_m"]
    times = []
    for _, off in _pulse_rows(tr):
        moving = np.flatnonzero(stuck[off] < 1.0)
        times.append(0.0 if not len(moving) else (moving[-1] + 1) / tr.ctx.rate_hz)
    return float(np.mean(times))


def _pulse_counts(tr: TruthRun, key: str) -> float:
    theta, omega = tr.truth["theta_m"], tr.truth["omega_m"]
    count = 0
    for on, off in _pulse_rows(tr):
        if key == "pulses_not_moving":
            count += not np.any(
                np.abs(theta[on.start : off.stop] - theta[on.start]) > tr.params.move_threshold_rad
            )
        else:
            count += abs(omega[off.stop - 1]) > tr.params.rest_speed_rad_s
    return float(count)


def _stair(tr: TruthRun, key: str) -> slice:
    """Rows of the stair whose amplitude the key's direction reports (its pulse and rest)."""
    from rig.experiments.pulse import stair_labels

    direction = "pos" if "_pos_" in key else "neg"
    level_v = float(tr.metrics[f"breakaway_{direction}_v"])
    index = int(np.argmin(np.abs(tr.params.stair_levels() - level_v)))
    labels = stair_labels(index, "+" if direction == "pos" else "-")
    on, off = (segment_rows(tr.run, label) for label in labels)
    return slice(on.start, off.stop)


def _static_v(tr: TruthRun, row: int, direction: float) -> float:
    """The voltage that just breaks the motor away at rest at `row`: K_m·u/R must exceed the static
    friction there plus the twist torque it pushes against, f_s(θ_m) + d·r·T_s (true)."""
    theta = np.asarray([tr.truth["theta_m"][row]])
    t_s, time_s = float(tr.truth["t_s"][row]), float(tr.truth["t"][row])
    f_s = float(k.static_motor_friction(tr.p, tr.flags, theta, direction, t_s, time_s)[0])
    return tr.p[P.R_ARM] / tr.p[P.K_M] * (f_s + direction * tr.r * float(tr.truth["t_s"][row]))


def _stair_static_v(tr: TruthRun, key: str) -> float:
    direction = 1.0 if "_pos_" in key or key.endswith("_pos_v") else -1.0
    return _static_v(tr, _stair(tr, key).start, direction)


def _stair_theta(tr: TruthRun, key: str) -> float:
    return float(tr.truth["theta_m"][_stair(tr, key).start])


def _stair_static_mean_v(tr: TruthRun, key: str) -> float:
    return 0.5 * (_stair_static_v(tr, "breakaway_pos_v") + _stair_static_v(tr, "breakaway_neg_v"))


def _stair_spread_v(tr: TruthRun) -> float:
    return 0.5 * abs(_stair_static_v(tr, "breakaway_pos_v") - _stair_static_v(tr, "breakaway_neg_v"))


_add(
    "pulse",
    Check("pulses", _param("count"), reason=ECHO),
    Check(
        r"mean_displacement(_pos|_neg)?_rad|displacement_spread_rad",
        _pulse_displacement,
        abs_tol=2 * math.pi / 131072,
        reason="true θ_m at the same rows; the encoder rounds each end by half a count",
    ),
    Check(
        "net_drift_rad",
        _pulse_displacement,
        abs_tol=2 * math.pi / 131072,
        reason="true θ_m; the sum telescopes to one count at most when pulses follow each other",
    ),
    Check(
        "mean_peak_speed_rad_s",
        _pulse_peak_speed,
        rel_tol=0.005,
        reason="true peak |ω_m|; an encoder difference over one 1 ms cycle rounds the peak by < 0.5 %",
    ),
    Check(
        "mean_peak_current_a",
        _pulse_peak_current,
        abs_tol=0.02,
        reason="the plant's current (u − K_b·ω_m)/R at the samples; the max picks the noise's top,"
        " ≤ 4σ of 5 mA",
    ),
    Check(
        "mean_breakaway_s",
        _pulse_breakaway,
        abs_tol=1.5e-3,
        reason="true θ_m interpolated; a sampled, quantized crossing lags it by up to one 1 ms cycle",
    ),
    Check(
        "mean_stop_s",
        _pulse_stop,
        abs_tol=1.5e-3,
        reason="true stuck flag; the last moving sample is within a cycle, and 0.1 rad/s → 0 takes < 0.2 ms",
    ),
    Check(r"pulses_not_(moving|at_rest)", _pulse_counts, reason="counted on the true θ_m, ω_m: exact"),
    Check(
        r"breakaway_(pos|neg)_v",
        _stair_static_v,
        bounds=lambda tr, key: (float(tr.metrics[key[:-2] + "_below_v"]), float(tr.metrics[key])),
        reason="plant law: the static level at the stair's start, R/K_m·(f_s(θ_m) + d·r·T_s), lies in"
        " (below, level]",
    ),
    Check(
        r"breakaway_(pos|neg)_below_v",
        _stair_static_v,
        bounds=lambda tr, key: (float(tr.metrics[key]), float(tr.metrics[key.replace("_below_v", "_v")])),
        reason="plant law: the static level lies above the highest stair that did not move",
    ),
    Check(
        r"breakaway_(pos|neg)_theta_m_rad",
        _stair_theta,
        abs_tol=math.pi / 131072,
        reason="true θ_m at the stair's start; the encoder rounds by half a count",
    ),
    Check(
        "breakaway_v",
        _stair_static_mean_v,
        bounds=lambda tr, key: (
            float(tr.metrics[key]) - 0.5 * tr.params.stair_step_v - _stair_spread_v(tr),
            float(tr.metrics[key]) + 0.5 * tr.params.stair_step_v + _stair_spread_v(tr),
        ),
        reason="plant law: the mean of the two directions' static levels within half a stair of the mean"
        " midpoint, widened by half their difference (the two stairs start at other places)",
    ),
)


# --- load-variation -------------------------------------------------------------------------------------


def _lv_levels(tr: TruthRun) -> tuple[np.ndarray, np.ndarray]:
    """(τ_ext, mean over the sweep's windows of the plant's steady |friction| at the sweep's centre) per
    load; the law includes friction that grows with the transmitted torque (c_Ts·|T_s|, true T_s). The
    windows the level averages: those the analysis marks load-steady (checked apart, as the speed
    sweep's `windows_load_unsteady`)."""
    from rig.experiments.load_variation import load_prefix
    from rig.experiments.speed_sweep import sweep_centre

    table = tr.results.tables["friction_vs_velocity_by_load"]
    levels = []
    for tau in tr.params.loads_nm:
        mine = table["tau_ext_nm"] == tau
        steady = set(table["omega_set"][mine & (table["load_steady"] > 0.5)].tolist())
        windows = [w for w in _windows(tr, load_prefix(tau), tr.params.settle_s) if w[0] in steady]
        centre = sweep_centre(tr.params.sweep(tau), tr.ctx)
        _, friction = _law_friction_vs_speed(tr, windows, centre)
        levels.append(float(np.mean(np.abs(friction))))
    return np.asarray(tr.params.loads_nm, dtype=float), np.asarray(levels)


def _lv_metric(tr: TruthRun, key: str) -> float:
    loads, levels = _lv_levels(tr)
    if key == "level_min_nm":
        return float(levels.min())
    if key == "level_max_nm":
        return float(levels.max())
    slope, intercept = np.polyfit(np.abs(loads), levels, 1)
    return float(slope if key == "friction_per_load_nm_per_nm" else intercept)


_add(
    "load-variation",
    Check("loads", _count("loads_nm"), reason=ECHO),
    Check("speeds", _count("speeds_rad_s"), reason=ECHO),
    Check(
        r"level_(min|max)_nm|level_at_no_load_nm",
        _lv_metric,
        rel_tol=0.02,
        reason="plant law at the sweep's centre (as the speed sweep's Coulomb level, issue 30: 2 %)",
    ),
    Check(
        "friction_per_load_nm_per_nm",
        _lv_metric,
        abs_tol=1e-4,
        reason="plant law (c_Ts, 0 on the seed); 1e-4 N·m per N·m is 2 % of the level over 15 N·m of load",
    ),
)


# --- step, sine, ramp: tracking at the output -------------------------------------------------------------


def _true_track(tr: TruthRun, rows: slice, kinematic_free: bool = False) -> Any:
    """The experiment's OutputTrack with the true angles, zeroed as the experiment zeroes (true θ_l
    averaged over the same window); `kinematic_free`: the load angle less the kinematic error."""
    from rig.experiments.tracking import ZERO_WINDOW_S, OutputTrack

    program_start = min(int(seg["start"]) for seg in segments_of(tr.run))
    zero = slice(max(0, program_start - tr.ctx.cycles(ZERO_WINDOW_S)), program_start)
    load = tr.truth["theta_l"]
    if kinematic_free:
        load = load - _kinematic_error(tr, tr.truth["theta_m"])
    theta_l0 = float(np.mean(load[zero]))
    t = tr.run.t[rows]
    return OutputTrack(
        t_s=t - t[0],
        setpoint=tr.r * (tr.run["setpoint"][rows] - tr.ctx.theta_m0),
        load=load[rows] - theta_l0,
        motor=tr.r * (tr.truth["theta_m"][rows] - tr.ctx.theta_m0),
    )


def _kinematic_error(tr: TruthRun, theta_m: np.ndarray) -> np.ndarray:
    if not tr.model.kinematic_error:
        return np.zeros_like(theta_m)
    return tr.p[P.KE_A] * np.sin(tr.p[P.KE_K] * theta_m + tr.p[P.KE_PHI])


def _side_and_name(key: str) -> tuple[str, str]:
    return ("motor", key.removeprefix("motor_")) if key.startswith("motor_") else ("load", key)


def _step_truth(tr: TruthRun, key: str) -> float:
    from rig.experiments.tracking import STEP_LABELS, step_metrics

    side, name = _side_and_name(key)
    match = re.fullmatch(r"(.*)_(\d)", name)
    quantity, which = (match.group(1), int(match.group(2))) if match else (name, None)
    values, set_from = [], 0.0
    for label in STEP_LABELS:
        track = _true_track(tr, segment_rows(tr.run, label))
        set_to = float(track.setpoint[0])
        got = step_metrics(
            track.t_s,
            getattr(track, side),
            set_from,
            set_to,
            tr.params.band_fraction,
            tr.ctx.cycles(tr.params.steady_s),
        )
        values.append(got[quantity])
        set_from = set_to
    return float(values[which - 1]) if which else float(np.mean(values))


_add(
    "step",
    Check("band_fraction", _param("band_fraction"), reason=ECHO),
    Check(
        r"(motor_)?settling_s(_\d)?",
        _step_truth,
        abs_tol=2e-3,
        reason="true angle; 2 µrad of sensor noise can move the last exit from the band by a sample or two",
    ),
    Check(
        r"(motor_)?rise_s(_\d)?",
        _step_truth,
        abs_tol=1e-4,
        reason="true angle; noise moves an interpolated 10 %/90 % crossing by µs at ~6 rad/s",
    ),
    Check(
        r"(motor_)?overshoot_pct(_\d)?",
        _step_truth,
        abs_tol=2e-3,
        reason="true angle; the max picks the noise's top, ≤ 5σ = 10 µrad of a 1 rad step = 1e-3 %",
    ),
    Check(
        r"(motor_)?ss_error_rad(_\d)?",
        _step_truth,
        abs_tol=3e-6,
        reason="true angle and zero; sensor noise 2 µrad averaged over 50+ samples, encoder r·q = 0.5 µrad",
    ),
)


def _sine_truth(tr: TruthRun, key: str) -> float:
    from rig.experiments.tracking import Sine, fit_phasor

    rows = segment_rows(tr.run, "sine")
    skip = tr.ctx.cycles(tr.params.skip_periods / tr.params.freq_hz) if tr.params.skip_periods else 0
    track = _true_track(tr, slice(rows.start + skip, rows.stop))
    assert isinstance(experiment_named("sine"), Sine)
    side, name = _side_and_name(key)
    y = getattr(track, side)
    error = y - track.setpoint
    if name == "rms_error_rad":
        return float(np.sqrt(np.mean(error**2)))
    if name == "max_error_rad":
        return float(np.max(np.abs(error)))
    phasor = fit_phasor(track.t_s, y, tr.params.freq_hz)
    set_phasor = fit_phasor(track.t_s, track.setpoint, tr.params.freq_hz)
    if name == "gain":
        return abs(phasor) / abs(set_phasor)
    return float(np.degrees(np.angle(set_phasor * phasor.conjugate())))


_add(
    "sine",
    Check("freq_hz", _param("freq_hz"), reason=ECHO),
    Check(r"(motor_)?rms_error_rad", _sine_truth, abs_tol=3e-6, reason="true angle and zero; 2 µrad noise"),
    Check(
        r"(motor_)?max_error_rad", _sine_truth, abs_tol=1e-5, reason="true angle; the max adds ≤ 5σ of noise"
    ),
    Check(r"(motor_)?gain", _sine_truth, abs_tol=1e-5, reason="true angle; noise on a 0.5 rad phasor"),
    Check(
        r"(motor_)?phase_lag_deg", _sine_truth, abs_tol=1e-3, reason="true angle; noise on a 0.5 rad phasor"
    ),
)


def _ramp_residuals(tr: TruthRun, side: str, kinematic_free: bool) -> tuple[list[float], list[float]]:
    from rig.experiments.tracking import RAMP_LABELS, detrended

    skip = tr.ctx.cycles(tr.params.skip_s)
    pp, rms = [], []
    for label in RAMP_LABELS:
        rows = segment_rows(tr.run, label)
        track = _true_track(tr, slice(rows.start + skip, rows.stop), kinematic_free)
        residual = detrended(track.t_s, getattr(track, side) - track.setpoint)
        pp.append(float(np.ptp(residual)))
        rms.append(float(np.sqrt(np.mean(residual**2))))
    return pp, rms


def _ramp_stick_slip(tr: TruthRun, key: str) -> float:
    """Stick-slip by its name: the load's detrended tracking error *less the kinematic error*, which is a
    property of the gear's geometry, not of friction (issue 31 item 3)."""
    pp, rms = _ramp_residuals(tr, "load", kinematic_free=True)
    return float(np.mean(pp if key.endswith("pp_rad") else rms))


def _ramp_ripple(tr: TruthRun, key: str) -> float:
    """The load's whole ripple (kinematic error and stick-slip together) on the true θ_l."""
    pp, rms = _ramp_residuals(tr, "load", kinematic_free=False)
    return float(np.mean(pp if key.endswith("pp_rad") else rms))


def _ramp_kinematic_pp(tr: TruthRun, key: str) -> float:
    """Plant law: the peak-to-peak of the kinematic error A·sin(k·θ_m + φ) along each direction's
    analyzed rows (2A when the motor turns through a whole period of it), averaged over both."""
    from rig.experiments.tracking import RAMP_LABELS

    skip = tr.ctx.cycles(tr.params.skip_s)
    spans = [segment_rows(tr.run, label) for label in RAMP_LABELS]
    theta = tr.truth["theta_m"]
    return float(np.mean([np.ptp(_kinematic_error(tr, theta[s.start + skip : s.stop])) for s in spans]))


def _ramp_motor_pp(tr: TruthRun, key: str) -> float:
    pp, _ = _ramp_residuals(tr, "motor", kinematic_free=False)
    return float(np.mean(pp))


def _ramp_stuck(tr: TruthRun, key: str) -> float:
    from rig.experiments.tracking import Ramp, program_rows

    side = key.rsplit("_", 1)[1]
    track = _true_track(tr, program_rows(tr.run))
    starts, ends = Ramp.stuck(track, side, tr.params, tr.ctx)
    if key.startswith("stick_phases"):
        return float(len(starts))
    return float(np.sum(ends - starts) / len(track.t_s))


KE_TOL = 0.05
"""The kinematic error's amplitude is estimated within 5 %: what the transmission error θ_l − r·θ_m shows
differs from A by J_l·(k·ω_m)²/K_s (the load's inertia, 2 % at the seed ramp's 0.2 rad/s), plus 3 %."""


def _ke_amplitude(tr: TruthRun) -> float:
    return float(tr.p[P.KE_A]) if tr.model.kinematic_error else 0.0


_add(
    "ramp",
    Check(
        "stick_slip_pp_rad",
        _ramp_stick_slip,
        abs_tol=2e-5,
        run_tol=lambda tr: 2 * KE_TOL * _ke_amplitude(tr),
        reason="true θ_l less the true kinematic error; what the experiment subtracts is its estimate, whose"
        " p-p is allowed 5 % of 2A (kinematic_error_pp_rad), plus 5σ of noise at each end",
    ),
    Check(
        "stick_slip_rms_rad",
        _ramp_stick_slip,
        abs_tol=3e-6,
        run_tol=lambda tr: KE_TOL * _ke_amplitude(tr) / math.sqrt(2),
        reason="as the p-p: the RMS of the kinematic estimate's allowed error, 5 % of A/√2, plus noise",
    ),
    Check(
        r"ripple_pp_rad",
        _ramp_ripple,
        abs_tol=2e-5,
        reason="true θ_l; the peak-to-peak adds up to 5σ of the 2 µrad noise at each end",
    ),
    Check(r"ripple_rms_rad", _ramp_ripple, abs_tol=3e-6, reason="true θ_l; 2 µrad noise adds in quadrature"),
    Check(
        "kinematic_error_pp_rad",
        _ramp_kinematic_pp,
        rel_tol=KE_TOL,
        reason="plant law 2A (the p-p of A·sin(k·θ_m + φ) over the rows): 5 %, of which 2 % the load's"
        " inertia J_l·(k·ω_m)²/K_s adds to what θ_l − r·θ_m shows",
    ),
    Check(
        "kinematic_error_cycles_per_turn",
        lambda tr, key: float(tr.p[P.KE_K]) if tr.model.kinematic_error else math.nan,
        reason="plant law k: a whole number, exact",
    ),
    Check(
        "motor_stick_slip_pp_rad",
        _ramp_motor_pp,
        abs_tol=2 * 0.01 * 2 * math.pi / 131072,
        reason="true θ_m; the encoder's rounding, r·q = 0.48 µrad at the output, at both extremes",
    ),
    Check(
        r"stick_phases_(load|motor)",
        _ramp_stuck,
        abs_tol=1.0,
        reason="the same threshold on the true angles' smoothed speed; noise can split or join one span",
    ),
    Check(
        r"stuck_fraction_(load|motor)",
        _ramp_stuck,
        abs_tol=0.02,
        reason="the same threshold on the true angles' smoothed speed; noise moves span edges by a few"
        " samples",
    ),
)


# --- chirp ------------------------------------------------------------------------------------------------


def _replaced(run: Run, columns: dict[str, np.ndarray]) -> Run:
    """A copy of `run` with some columns replaced."""
    return Run({**run.columns, **columns}, dict(run.meta))


def _chirp_same_definition(tr: TruthRun, key: str) -> float:
    from rig.experiments.chirp import Chirp

    true_run = _replaced(tr.run, {"omega_m": tr.truth["omega_m"], "theta_l": tr.truth["theta_l"]})
    results = Chirp().analyze(true_run, tr.params, tr.ctx)
    return float(results.metrics.get(key, math.nan))


def _linear_plant(tr: TruthRun) -> tuple[float, float]:
    """(antiresonance, resonance) of the plant linearized about its mean speed [Hz]: i → ω_m has zeros at
    J_l·s² + b_l·s + K_s (the load's own mode) and poles where the motor's inertia joins it."""
    j_m, j_l, r, k_s = tr.p[P.J_M], tr.p[P.J_L], tr.r, tr.p[P.K_S]
    anti = math.sqrt(k_s / j_l) / (2 * math.pi)
    res = math.sqrt(k_s * (1.0 / j_l + r * r / j_m)) / (2 * math.pi)
    return anti, res


def _chirp_law(tr: TruthRun, key: str) -> float:
    anti, res = _linear_plant(tr)
    return anti if key == "antiresonance_hz" else res


def _line_spacing(tr: TruthRun) -> float:
    return 1.0 / (tr.ctx.cycles(tr.params.period_s) / tr.ctx.rate_hz)


def _chirp_mean_speed(tr: TruthRun, key: str) -> float:
    """The true motor speed's mean magnitude over the analyzed periods of every sweep."""
    from rig.experiments.chirp import analyzed_rows, sweep_labels

    means = [
        abs(float(np.mean(tr.truth["omega_m"][analyzed_rows(tr.run, s, tr.params, tr.ctx)])))
        for s in sweep_labels(tr.params)
    ]
    return float(np.mean(means))


def _chirp_frequency_error(tr: TruthRun, key: str) -> float:
    """The larger true error of the two reported frequencies [Hz]."""
    return max(
        abs(float(tr.metrics[name]) - _chirp_law(tr, name)) for name in ("antiresonance_hz", "resonance_hz")
    )


_add(
    "chirp",
    Check("line_spacing_hz", _same_analysis, reason="1/period from the same rows: exact"),
    Check(
        "sweep_mean_speed_rad_s",
        _chirp_mean_speed,
        rel_tol=1e-3,
        reason="true ω_m over whole periods; the position loop's following error differs by < 1e-3 of the"
        " travel between a period's ends",
    ),
    Check(
        "resonance_resolution_hz",
        _chirp_frequency_error,
        bounds=lambda tr, key: (-math.inf, float(tr.metrics[key])),
        reason="a stated resolution must cover the true error of both frequencies (plant law, linearized)",
    ),
    Check(
        r"coherence_1_10hz_(speed|load|closed_loop)",
        _chirp_same_definition,
        abs_tol=0.01,
        reason="the same estimate on the true ω_m, θ_l: what the sensors' noise takes from the coherence",
    ),
    Check(
        r"(anti)?resonance_hz",
        _chirp_law,
        run_tol=lambda tr: 0.5 * _line_spacing(tr),
        reason="plant law, linearized (K_s, J_m, J_l, r); half a line of the excitation (0.25 Hz at the"
        " default 2 s period): no worse than the nearest line; the stated resolution is checked apart",
    ),
    Check(
        r"closed_loop_(peak_hz|bandwidth_hz)",
        _chirp_same_definition,
        abs_tol=1e-9,
        reason="the same estimate on the true θ_l: the same line",
    ),
    Check(
        "closed_loop_peak_db",
        _chirp_same_definition,
        abs_tol=0.05,
        reason="the same estimate on the true θ_l: 2 µrad noise on the output's spectrum",
    ),
)


# --- compensation ---------------------------------------------------------------------------------------


_comp_truth = _same_analysis  # the same figures on the true θ_l (zeroed on it in the same window)


_add(
    "compensation",
    Check(r"rms_error_(step|sine|ramp)_.*_rad", _comp_truth, abs_tol=3e-6, reason="true θ_l; 2 µrad noise"),
    Check(
        r"overshoot_pct_(step|sine|ramp)_.*",
        _comp_truth,
        abs_tol=2e-3,
        reason="true angle; as the step's overshoot: ≤ 5σ of 2 µrad noise on a 1 rad step",
    ),
    Check(
        r"settling_s_(step|sine|ramp)_.*",
        _comp_truth,
        abs_tol=2e-3,
        reason="true angle; as the step's settling: noise moves the band's last exit by a sample or two",
    ),
    Check(
        r"stick_slip_pp_.*_rad",
        _comp_truth,
        abs_tol=1.5e-5,
        reason="true θ_l; the peak-to-peak adds up to ±5σ of the 2 µrad noise at each end",
    ),
    Check(
        r"improvement_.*",
        _comp_truth,
        rel_tol=0.02,
        reason="a ratio of the figures above; their tolerance relative to the ramp's ~1e-3 rad",
    ),
    Check(
        r"temperature_gain_(step|sine|ramp)(_std)?",
        _comp_truth,
        rel_tol=0.05,
        reason="a ratio of two RMS errors of ~1e-4 rad, each within 3 µrad (above): ±3 % each",
    ),
)


# --- endurance ------------------------------------------------------------------------------------------


def _endurance_truth(tr: TruthRun, key: str) -> float:
    """Checkpoint count; the Coulomb level by the plant's law at each checkpoint's place (its unloaded
    holds' centre, as the speed sweep's: friction against speed at one place); the stiffness K_s."""
    from rig.experiments.endurance import CHECKPOINT_PREFIX, checkpoints_due

    if key == "checkpoints":
        return float(checkpoints_due(tr.params))
    if key == "stiffness_last_nm_rad":
        return float(tr.p[P.K_S])
    names = sorted({str(seg["label"]).split("/")[0] for seg in segments_of(tr.run, CHECKPOINT_PREFIX)})
    levels = []
    for name in names:
        skip = tr.ctx.cycles(tr.params.settle_s)
        windows = [
            (0.0, slice(int(seg["start"]) + skip, int(seg["start"]) + int(seg["cycles"])))
            for seg in segments_of(tr.run, name + "/v")
            if not str(seg["label"]).endswith("L")
        ]
        centre = float(np.median([np.mean(tr.truth["theta_m"][rows]) for _, rows in windows]))
        speeds, friction = _law_friction_vs_speed(tr, windows, centre)
        x = np.column_stack([np.ones(len(speeds)), np.abs(speeds)])
        levels.append(float(np.linalg.lstsq(x, np.abs(friction), rcond=None)[0][0]))
    if key == "coulomb_first_nm":
        return levels[0]
    if key == "coulomb_last_nm":
        return levels[-1]
    return 100.0 * (levels[-1] / levels[0] - 1.0)


_add(
    "endurance",
    Check("checkpoints", _endurance_truth, reason="checkpoints due for the duration: exact"),
    Check(
        r"coulomb_(first|last)_nm",
        _endurance_truth,
        rel_tol=0.02,
        reason="plant law at the checkpoint's centre: the speed sweep's 2 % (issue 30 item 2)",
    ),
    Check(
        "coulomb_change_pct", _endurance_truth, abs_tol=0.5, reason="from the two levels above, 0.3 % each"
    ),
    Check(
        "stiffness_last_nm_rad",
        _endurance_truth,
        rel_tol=0.02,
        reason="plant law K_s (linear spring); the kinematic error averages over whole periods of a hold"
        " only to within ~1 % of the 5 mrad deflection change",
    ),
)


def linearized_speed_frf(tr: TruthRun, freq_hz: np.ndarray) -> np.ndarray:
    """The plant's current → motor speed response, linearized about the chirp's mean speed: the motor's
    friction as its slope there (C·k_v + b_m, C at the passes' mean position), the load's viscous b_l,
    the spring K_s; H = K_m / (J_m·s + c_m + r²·K_s·(J_l·s + b_l)/(J_l·s² + b_l·s + K_s)) [rad/s per A].
    The drive's sampling chain (command held a cycle, 150 Hz speed filter) changes |H| by < 0.05 dB to
    10 Hz and is left out."""
    s = 2j * np.pi * np.asarray(freq_hz)
    p, r = tr.p, tr.r
    mean_speed = float(tr.params.mean_speed_motor_rad_s)
    theta = tr.truth["theta_m"]
    places = np.linspace(float(theta.min()), float(theta.max()), 2001)
    delta = 1e-3 * mean_speed
    up = k.steady_motor_friction(p, tr.flags, places, np.full(places.shape, mean_speed + delta), 0.0, 0.0)
    down = k.steady_motor_friction(p, tr.flags, places, np.full(places.shape, mean_speed - delta), 0.0, 0.0)
    c_m = float(np.mean(up - down)) / (2 * delta)
    load_law = int(tr.flags[FL.LOAD_LAW])
    b_l = p[P.B_L] if load_law != Law.NONE else 0.0
    j_m, j_l, k_s = p[P.J_M], p[P.J_L], p[P.K_S]
    load = r * r * k_s * (j_l * s + b_l) / (j_l * s * s + b_l * s + k_s)
    return np.asarray(p[P.K_M] / (j_m * s + c_m + load))
