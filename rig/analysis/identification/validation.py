"""The validation table of the article, model beside measurement.

For each measured validation run (`step`, `sine`, `ramp`, `chirp`), the same experiment with the
same parameters is played on a simulated rig that runs the model under test, with the measured run's
rig settings (rate, loops, sensors, the sensor-noise seed), from the measured run's first state
(positions, speeds, the twist they imply, the plant's clock; stuck or sliding follows from the speeds)
and holding still as long as the measured run held before its program: so the model is judged closed
loop, as the article judges it, on the same start. Both runs go through the same analysis, and the
table puts their metrics side by side with the error.

The table states its own noise floor: the same replay with NOISE_SEEDS other sensor-noise seeds, and
the largest error any of them makes against the replay itself. A perfect model scores at that floor;
an error above it (and above FLAG_MIN_PERCENT, below which no row is worth a flag) is the model's.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from model.errors import UserInputError
from model.params import HarmonicDriveModel
from model.plant import Plant
from model.run import Run
from rig.experiments import EXPERIMENTS
from rig.experiments.base import Results, RigContext, context_from_run
from rig.experiments.plots import new_figure, save_figure
from rig.interface import open_simulated_rig
from rig.runner import make_params, run_experiment
from rig.store.runs import RunStore

VALIDATION_EXPERIMENTS = ("step", "sine", "ramp", "chirp")

# (experiment, metric, the article's row name, unit, the article's measured figure). The article's ramp
# figure is what an output sensor sees, stick-slip and kinematic error together (the ripple); the
# stick-slip without the kinematic error has no article figure.
TABLE_ROWS: tuple[tuple[str, str, str, str, float | None], ...] = (
    ("step", "settling_s", "Step input (1 rad): settling time", "s", 0.24),
    ("sine", "rms_error_rad", "Sinusoidal input (0.5 Hz): position error RMS", "rad", 0.0021),
    ("ramp", "ripple_pp_rad", "Low-speed ramp: ripple p-p (stick-slip and kinematic error)", "rad", 0.0016),
    ("ramp", "stick_slip_pp_rad", "Low-speed ramp: stick-slip p-p (kinematic error removed)", "rad", None),
)
NOISE_SEEDS = 3
"""Replays with other sensor-noise seeds that make each row's noise floor."""
FLAG_MIN_PERCENT = 2.0
"""An error is flagged as the model's when above its noise floor and above this [%]."""
FLAG_MIN_DEG = 2.0
"""The same for the Bode phase's RMS error [°]."""
OMEGA_FIT_SAMPLES = 16
OMEGA_FIT_DEGREE = 4
"""The starting speeds: slopes at t = 0 of polynomials of this degree through the first samples of θ_m and
θ_l (the load's speed is not measured; the drive's filtered speed lags); a quadratic over fewer samples
was biased by the curvature of the load's ring (docs/BENCHMARKS.md)."""
BODE_TABLE = "frf_closed_loop"
BODE_MAX_HZ = 10.0


@dataclass
class ValidationRow:
    """One line of the table: a scalar metric (simulated, measured) or a curve's error (error_text)."""

    scenario: str
    unit: str
    simulated: float | None
    measured: float | None
    article: float | None = None
    error_percent: float = np.nan
    error_text: str = ""
    error_deg: float = np.nan  # a phase row's error, in degrees (it has no percent)
    floor: float = np.nan  # the largest error sensor noise alone makes (replays, other seeds), % or °

    def __post_init__(self) -> None:
        if self.simulated is not None and self.measured:
            self.error_percent = 100.0 * abs(self.simulated - self.measured) / abs(self.measured)
        if not self.error_text:
            self.error_text = f"{self.error_percent:.1f} %"

    @property
    def error_unit(self) -> tuple[float, str, float]:
        """(error, its unit, the least error flagged): in % where the row has one, else in degrees."""
        if np.isnan(self.error_percent) and not np.isnan(self.error_deg):
            return self.error_deg, "°", FLAG_MIN_DEG
        return self.error_percent, " %", FLAG_MIN_PERCENT

    @property
    def above_noise(self) -> bool:
        """Whether the error is the model's: above the noise floor and above the least error flagged."""
        error, _, least = self.error_unit
        if np.isnan(error):
            return False
        return bool(error > max(0.0 if np.isnan(self.floor) else self.floor, least))

    @property
    def floor_text(self) -> str:
        _, unit, _ = self.error_unit
        return "—" if np.isnan(self.floor) else f"{self.floor:.2g}{unit}"


@dataclass
class ValidationReport:
    rows: list[ValidationRow] = field(default_factory=list)
    plots: list[Path] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    def table(self) -> list[dict[str, float | str | None]]:
        """One row per scenario, for the fit document."""
        return [
            {
                "scenario": r.scenario,
                "unit": r.unit,
                "simulated": r.simulated,
                "measured": r.measured,
                "error_percent": None if np.isnan(r.error_percent) else r.error_percent,
                "error": r.error_text,
                "noise_floor": None if np.isnan(r.floor) else r.floor,
                "noise_floor_unit": r.error_unit[1].strip(),
                "above_noise": r.above_noise,
                "article_measured": r.article,
            }
            for r in self.rows
        ]

    def markdown(self, model_name: str) -> str:
        lines = [
            f"# Validation of `{model_name}`",
            "",
            "Each measured validation run was played again, same parameters, rig settings and starting",
            "state, on a simulated rig running the model; both went through the same analysis. Noise floor:",
            f"the largest error the same replay makes with {NOISE_SEEDS} other sensor-noise seeds. Verdict:",
            f"an error above its floor and above {FLAG_MIN_PERCENT:g} % ({FLAG_MIN_DEG:g}° in phase) is the"
            " model's (**above noise**).",
            "",
            "| Test scenario | Simulation | Measurement | Error | Noise floor | Verdict"
            " | Article (measured) |",
            "|---|---|---|---|---|---|---|",
        ]
        for r in self.rows:
            article = f"{r.article:.4g} {r.unit}" if r.article is not None else "—"
            sim = f"{r.simulated:.4g} {r.unit}" if r.simulated is not None else "(plot)"
            meas = f"{r.measured:.4g} {r.unit}" if r.measured is not None else "(plot)"
            verdict = "**above noise**" if r.above_noise else "at noise"
            lines.append(
                f"| {r.scenario} | {sim} | {meas} | {r.error_text} | {r.floor_text} | {verdict} | {article} |"
            )
        lines += ["", *[f"- {note}" for note in self.notes], ""]
        lines += [f"![{p.stem}]({p.name})" for p in self.plots]
        return "\n".join(lines) + "\n"


@dataclass(frozen=True)
class StartState:
    """Where a measured run's plant started, from its first samples (motor side, SI units)."""

    theta_m: float
    omega_m: float
    theta_l: float | None  # None: not comparable to the model's (a sensor with its own zero): relaxed
    omega_l: float | None
    time_s: float


def start_state(run: Run) -> StartState:
    """The state at the run's first sample. Positions are measured; the speeds are the slopes at t = 0 of
    polynomials through the first samples of θ_m and θ_l (OMEGA_FIT_*). The load angle is
    taken as measured only from a run our simulated plant recorded (its sensor shares the plant's zero,
    so θ_l − r·θ_m is the twist plus the kinematic error); elsewhere the spring starts relaxed. Stuck or
    sliding follows from the speeds (the plant's stick band). Bristle states are not observed: zero."""
    time_s = float(run.meta.get("rig_time_origin_s", 0.0))
    if len(run) < OMEGA_FIT_SAMPLES:
        return StartState(float(run["theta_m"][0]), float(run["omega_m"][0]), None, None, time_s)
    t_s = run.t[:OMEGA_FIT_SAMPLES] - run.t[0]

    def start(name: str) -> tuple[float, float]:
        coef = np.polyfit(t_s, run[name][:OMEGA_FIT_SAMPLES], OMEGA_FIT_DEGREE)
        return float(run[name][0]), float(coef[-2])

    theta_m, omega_m = start("theta_m")
    if run.meta.get("source") != "sim":
        return StartState(theta_m, omega_m, None, None, time_s)
    theta_l, omega_l = start("theta_l")
    return StartState(theta_m, omega_m, theta_l, omega_l, time_s)


def _replay_experiment(
    run: Run, model: HarmonicDriveModel, store: RunStore, seed: int | None = None
) -> tuple[Run, RigContext]:
    """The same experiment, same parameters, on a simulated rig running `model` from the measured run's
    first state (`start_state`) and with its settle; its run and context. `seed`: another sensor-noise
    seed than the measured run's."""
    name = str(run.meta["experiment"])
    ctx = context_from_run(run, f"run {run.meta.get('run_id', name)}")
    config = ctx.config.model_copy(update={"pace": "virtual", "model": None})
    if seed is not None:
        config = config.model_copy(update={"sensors": config.sensors.model_copy(update={"seed": seed})})
    start = start_state(run)
    rig = open_simulated_rig(config, model, theta_m=start.theta_m)
    plant = getattr(rig, "plant", None)  # the simulated backend's plant (`rig` imports no backend)
    if isinstance(plant, Plant):
        plant.reset(start.theta_m, start.omega_m, start.theta_l, start.omega_l, start.time_s)
    settle = run.meta.get("settle") or {}
    settle_s = float(settle["duration_s"]) if "duration_s" in settle else None
    try:
        outcome = run_experiment(
            name, config, dict(run.meta.get("params", {})), store, rig=rig, settle_s=settle_s
        )
    finally:
        rig.close()
    if outcome.status != "complete":
        raise UserInputError(
            f"validation of {name}: the model's run ended {outcome.reason or outcome.status}"
        )
    return store.read(outcome.run_id), ctx


def _analysis(run: Run, ctx: RigContext) -> Results:
    experiment = EXPERIMENTS[str(run.meta["experiment"])]
    params = make_params(experiment, dict(run.meta.get("params", {})))
    return experiment.analyze(run, params, ctx)


def validate(runs: list[Run], model: HarmonicDriveModel, out_dir: Path | None = None) -> ValidationReport:
    """The validation table for the validation runs among `runs`; plots into `out_dir` if given."""
    report = ValidationReport()
    chosen = {
        str(r.meta.get("experiment")): r for r in runs if r.meta.get("experiment") in VALIDATION_EXPERIMENTS
    }
    missing = [e for e in VALIDATION_EXPERIMENTS if e not in chosen]
    if missing:
        report.notes.append(f"no measured run of {', '.join(missing)}: those rows are left out")
    # The store is closed before its folder is removed: its catalog's files stay open otherwise.
    with (
        tempfile.TemporaryDirectory(prefix="hdrig-validation-") as home,
        RunStore(home, catalog=f"sqlite:///{home}/catalog.sqlite", data=home) as store,
    ):
        for name, measured in chosen.items():
            simulated, ctx = _replay_experiment(measured, model, store)
            mine, theirs = _analysis(simulated, ctx), _analysis(measured, ctx)
            base_seed = ctx.config.sensors.seed
            noisy = [
                _analysis(_replay_experiment(measured, model, store, seed=base_seed + k)[0], ctx)
                for k in range(1, NOISE_SEEDS + 1)
            ]
            for experiment, metric, scenario, unit, article in TABLE_ROWS:
                if experiment == name and metric in theirs.metrics:
                    row = ValidationRow(
                        scenario, unit, float(mine.metrics[metric]), float(theirs.metrics[metric]), article
                    )
                    if row.measured:
                        spread = [abs(float(r.metrics[metric]) - float(mine.metrics[metric])) for r in noisy]
                        row.floor = 100.0 * max(spread) / abs(row.measured)
                    report.rows.append(row)
            if name == "chirp":
                rows = _bode_rows(mine, theirs)
                # The same curve error between each noisy replay and the replay: what noise alone makes.
                floors = [_bode_rows(r, mine) for r in noisy]
                for index, row in enumerate(rows):
                    errors = [f[index].error_unit[0] for f in floors if len(f) > index]
                    row.floor = max(errors, default=np.nan)
                report.rows += rows
            if out_dir is not None:
                report.plots.append(_overlay(name, measured, simulated, mine, theirs, out_dir))
    return report


def _bode_rows(model: Results, measured: Results) -> list[ValidationRow]:
    a, b = model.tables.get(BODE_TABLE), measured.tables.get(BODE_TABLE)
    if a is None or b is None:
        return []
    pick = (b["freq_hz"] <= BODE_MAX_HZ) & (b["coherence"] > 0.9)
    if not np.any(pick):
        return []
    # Both on the measured frequencies (the analyses share the excitation, so the grids agree).
    db = np.interp(b["freq_hz"][pick], a["freq_hz"], a["magnitude_db"]) - b["magnitude_db"][pick]
    deg = np.interp(b["freq_hz"][pick], a["freq_hz"], a["phase_deg"]) - b["phase_deg"][pick]
    magnitude_percent = float(np.sqrt(np.mean((10 ** (db / 20) - 1) ** 2)) * 100)
    phase_deg = float(np.sqrt(np.mean(deg**2)))
    where = f"{np.count_nonzero(pick)} points to {BODE_MAX_HZ:g} Hz with coherence > 0.9"
    return [
        ValidationRow(
            "Frequency response: Bode magnitude",
            "",
            None,
            None,
            error_percent=magnitude_percent,
            error_text=f"{magnitude_percent:.1f} % RMS ({where})",
        ),
        ValidationRow(
            "Frequency response: Bode phase",
            "°",
            None,
            None,
            error_deg=phase_deg,
            error_text=f"{phase_deg:.2f}° RMS ({where})",
        ),
    ]


def _overlay(name: str, measured: Run, simulated: Run, mine: Results, theirs: Results, out_dir: Path) -> Path:
    out_dir.mkdir(parents=True, exist_ok=True)
    if name == "chirp" and BODE_TABLE in theirs.tables and BODE_TABLE in mine.tables:
        fig, ax = new_figure("Closed-loop Bode, set-point → θ_l: model and measurement", rows=2)
        phase_ax = fig.axes[1]
        for label, table, style in (
            ("measured", theirs.tables[BODE_TABLE], "o"),
            ("model", mine.tables[BODE_TABLE], "-"),
        ):
            ax.semilogx(table["freq_hz"], table["magnitude_db"], style, label=label)
            phase_ax.semilogx(table["freq_hz"], table["phase_deg"], style, label=label)
        ax.set_ylabel("magnitude [dB]")
        phase_ax.set_ylabel("phase [°]")
        phase_ax.set_xlabel("frequency [Hz]")
        ax.legend()
    else:
        fig, ax = new_figure(f"{name}: load angle, model and measurement")
        for label, run in (("measured", measured), ("model", simulated)):
            ax.plot(run.t - run.t[0], run["theta_l"] - run["theta_l"][0], label=label, lw=1.0)
        ax.set_xlabel("time [s]")
        ax.set_ylabel("θ_l from start [rad]")
        ax.legend()
    return save_figure(fig, out_dir / f"validation_{name}.png")
