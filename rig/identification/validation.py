"""The validation table of the article, model beside measurement.

For each measured validation run (`step`, `sine`, `ramp`, `chirp`), the same experiment with the
same parameters is played on a simulated rig that runs the model under test, with the measured run's
rig settings (rate, loops, sensors): so the model is judged closed loop, as the article judges it.
Both runs go through the same analysis, and the table puts their metrics side by side with the error.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from model.errors import UserInputError
from model.params import HarmonicDriveModel
from model.run import Run
from rig.experiments import EXPERIMENTS
from rig.experiments.base import Results, RigContext, context_from_run
from rig.experiments.plots import new_figure, save_figure
from rig.interface import open_simulated_rig
from rig.runner import make_params, run_experiment
from rig.store import RunStore

VALIDATION_EXPERIMENTS = ("step", "sine", "ramp", "chirp")

# (experiment, metric, the article's row name, unit, the article's measured figure)
TABLE_ROWS = (
    ("step", "settling_s", "Step input (1 rad): settling time", "s", 0.24),
    ("sine", "rms_error_rad", "Sinusoidal input (0.5 Hz): position error RMS", "rad", 0.0021),
    ("ramp", "stick_slip_pp_rad", "Low-speed ramp: stick-slip amplitude", "rad", 0.0016),
)
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

    def __post_init__(self) -> None:
        if self.simulated is not None and self.measured:
            self.error_percent = 100.0 * abs(self.simulated - self.measured) / abs(self.measured)
        if not self.error_text:
            self.error_text = f"{self.error_percent:.1f} %"


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
                "article_measured": r.article,
            }
            for r in self.rows
        ]

    def markdown(self, model_name: str) -> str:
        lines = [
            f"# Validation of `{model_name}`",
            "",
            "Each measured validation run was played again, same parameters and rig settings, on a simulated",
            "rig running the model; both went through the same analysis.",
            "",
            "| Test scenario | Simulation | Measurement | Error | Article (measured) |",
            "|---|---|---|---|---|",
        ]
        for r in self.rows:
            article = f"{r.article:.4g} {r.unit}" if r.article is not None else "—"
            sim = f"{r.simulated:.4g} {r.unit}" if r.simulated is not None else "(plot)"
            meas = f"{r.measured:.4g} {r.unit}" if r.measured is not None else "(plot)"
            lines.append(f"| {r.scenario} | {sim} | {meas} | {r.error_text} | {article} |")
        lines += ["", *[f"- {note}" for note in self.notes], ""]
        lines += [f"![{p.stem}]({p.name})" for p in self.plots]
        return "\n".join(lines) + "\n"


def _replay_experiment(run: Run, model: HarmonicDriveModel, store: RunStore) -> tuple[Run, RigContext]:
    """The same experiment, same parameters, on a simulated rig running `model`; its run and context."""
    name = str(run.meta["experiment"])
    ctx = context_from_run(run, f"run {run.meta.get('run_id', name)}")
    config = ctx.config.model_copy(update={"pace": "virtual", "model": None})
    # A simulated rig whatever measured; it starts where the measurement started, so position-dependent
    # friction meets the same positions.
    rig = open_simulated_rig(config, model, theta_m=float(run["theta_m"][0]))
    outcome = run_experiment(name, config, dict(run.meta.get("params", {})), store, rig=rig)
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
            for experiment, metric, scenario, unit, article in TABLE_ROWS:
                if experiment == name and metric in theirs.metrics:
                    report.rows.append(
                        ValidationRow(
                            scenario,
                            unit,
                            float(mine.metrics[metric]),
                            float(theirs.metrics[metric]),
                            article,
                        )
                    )
            if name == "chirp":
                report.rows += _bode_rows(mine, theirs)
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
