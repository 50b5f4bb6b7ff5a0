"""The gap report: a Markdown page a person reads in a minute, and the plots it points to.

- `summary.md`: verdict, the table of steps (gap before/after, held out), the evidence, the parameters,
  where the residual was before each step, what else was tried.
- `gaps.png`: the gap after each step, on all and on held-out windows.
- `step<N>-<effect>.png` (or `residual.png` when nothing was added): the residual before and after,
  against time, speed, motor angle and direction, on the channel the effect was seen in.
- `window.png`: the worst shooting window of the first model, measured vs simulated before and after.

Figures use matplotlib's object-oriented API (`Figure` + `savefig`), not pyplot: saving to a file needs no
GUI backend, so importing this module leaves a notebook's backend alone.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from model.params import HarmonicDriveModel
from model.registry import OUT
from model.simulate import replay_rows
from rig.analysis.gaps.locate import ANGLE_BINS, CHANNEL_UNITS, SPEED_EDGES, Where, locate
from rig.analysis.gaps.residual import one_step_residual
from rig.analysis.gaps.shooting import Shooting, StartedPlant, started
from rig.analysis.gaps.signals import Signals
from rig.analysis.gaps.workflow import GapOptions, GapsResult


def _where(model: HarmonicDriveModel, signals: list[Signals], channel: str, dt_s: float) -> Where:
    return locate(signals, [one_step_residual(model, s, dt_s) for s in signals], channel)


def _panels(title: str, wheres: dict[str, Where], path: Path) -> Path:
    fig = Figure(figsize=(11, 7))
    axes = fig.subplots(2, 2)
    unit = CHANNEL_UNITS[next(iter(wheres.values())).channel]
    labels = [f"{SPEED_EDGES[i]:g}–{SPEED_EDGES[i + 1]:g}" for i in range(len(SPEED_EDGES) - 1)]
    angles = (np.arange(ANGLE_BINS) + 0.5) * 360 / ANGLE_BINS
    width = 0.8 / len(wheres)
    for j, (label, w) in enumerate(wheres.items()):
        axes[0, 0].plot(w.time_s, w.time_rms, label=label)
        axes[0, 1].bar(np.arange(len(labels)) + j * width, w.speed_rms, width, label=label)
        axes[1, 0].plot(angles, w.angle_mean, marker=".", label=label)
        axes[1, 1].bar(np.arange(3) + j * width, [w.forward, w.backward, w.at_rest], width, label=label)
    axes[0, 0].set(xlabel="time [s]", ylabel=f"RMS per 0.5 s [{unit}]", title="over time")
    axes[0, 1].set(xlabel="|ω_m| [rad/s]", ylabel=f"RMS [{unit}]", title="over speed")
    axes[0, 1].set_xticks(np.arange(len(labels)) + 0.4 - width / 2, labels, rotation=30, fontsize=8)
    what = "mean residual·sgn ω" if next(iter(wheres.values())).channel == "motor" else "mean residual"
    axes[1, 0].set(xlabel="θ_m mod 2π [deg]", ylabel=f"{what} [{unit}]", title="over one motor turn")
    axes[1, 1].set(ylabel=f"mean [{unit}]", title="by direction")
    axes[1, 1].set_xticks(np.arange(3) + 0.4 - width / 2, ["forward", "backward", "at rest"])
    for ax in axes.flat:
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    return path


def _gaps_plot(result: GapsResult, path: Path) -> Path:
    names = ["initial"] + [s.effect for s in result.steps]
    every = [result.initial_gap] + [s.gap_after for s in result.steps]
    held = [result.held_out_initial] + [s.held_out_after for s in result.steps]
    x = np.arange(len(names))
    fig = Figure(figsize=(8, 4.5))
    ax = fig.subplots()
    ax.bar(x - 0.2, every, 0.4, label="all windows")
    ax.bar(x + 0.2, held, 0.4, label="held-out windows")
    ax.set_yscale("log")
    ax.set_xticks(x, [f"+{n}" if i else n for i, n in enumerate(names)], rotation=15)
    ax.set(ylabel="gap [rad at the motor]", title="the gap after each step")
    ax.grid(True, alpha=0.3, which="both")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    return path


def _window_plot(result: GapsResult, shooting: Shooting, path: Path) -> Path:
    first = result.steps[0].model_before if result.steps else result.model
    errors = shooting.errors(first, shooting.everything)
    worst = int(np.argmax([float(np.sum(e**2)) for e in errors]))
    w = shooting.windows[worst]
    fig = Figure(figsize=(8, 4.5))
    ax = fig.subplots()
    ax.plot(w.run.t, w.theta_m, "k.", label="measured", markersize=4)
    for label, model in (("model given", first), ("model with the effects", result.model)):
        plant = StartedPlant(model)
        plant.starts = started(model, w)
        rows = replay_rows(plant, w.run, shooting.signals[w.signals].mode, shooting.dt_s, w.clock_s)
        ax.plot(w.run.t, rows[:, OUT.THETA_M], label=label)
    ax.set(xlabel="time [s]", ylabel="θ_m [rad]", title="the worst shooting window of the given model")
    ax.grid(True, alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    return path


def _fmt(value: float) -> str:
    return f"{value:.4g}"


def write_report(
    result: GapsResult, signals: list[Signals], shooting: Shooting, out_dir: Path, opts: GapOptions
) -> list[Path]:
    """Write the plots and `summary.md` into out_dir; return the files written."""
    dt_s = opts.dt_s
    out_dir.mkdir(parents=True, exist_ok=True)
    files = [_gaps_plot(result, out_dir / "gaps.png"), _window_plot(result, shooting, out_dir / "window.png")]
    duration = sum(float(s.t[-1]) for s in signals)
    columns = sorted(set().union(*(s.run.columns for s in signals)))
    first = result.steps[0].model_before if result.steps else result.model
    lines = [
        f"# Model gaps: {first.name}",
        "",
        f"**{result.verdict[0].upper() + result.verdict[1:]}.**",
        "",
        f"Data: {len(signals)} run(s), {duration:.1f} s, columns {', '.join(columns)}.",
        f"Gap: {result.metric}; {len(shooting.windows)} windows, every third held out from fitting.",
        "",
        "| step | effect | gap before | gap after | held out before | held out after |",
        "|---|---|---|---|---|---|",
        f"| 0 | (model as given) | | {_fmt(result.initial_gap)} | | {_fmt(result.held_out_initial)} |",
    ]
    for i, s in enumerate(result.steps, 1):
        lines.append(
            f"| {i} | {s.effect} | {_fmt(s.gap_before)} | {_fmt(s.gap_after)} |"
            f" {_fmt(s.held_out_before)} | {_fmt(s.held_out_after)} |"
        )
    lines += ["", "![gap per step](gaps.png)", ""]
    for i, s in enumerate(result.steps, 1):
        chosen = next(t for t in s.trials if t.candidate.effect == s.effect)
        channel = chosen.candidate.channel
        residuals = [one_step_residual(s.model_after, sig, dt_s) for sig in signals]
        if any(getattr(r, channel) is None for r in residuals):
            channel = "motor"  # the effect changed the channels (compliance): compare where both have one
        before = _where(s.model_before, signals, channel, dt_s)
        after = locate(signals, residuals, channel)
        name = f"step{i}-{s.effect}.png"
        title = f"step {i}: {s.effect} ({channel} residual)"
        files.append(_panels(title, {"before": before, "after": after}, out_dir / name))
        lines += [f"## Step {i}: {s.effect}", "", f"Evidence: {s.evidence}.", "", "Where the residual was:"]
        lines += [f"- {line}" for line in before.lines()]
        lines += ["", "Parameters (fitted on the training windows; ± one standard error):"]
        for p in s.estimates:
            error = f" ± {p.std_error:.2g}" if p.std_error is not None else f" (kept: {p.note})"
            lines.append(f"- `{p.name}` = {p.estimate:.5g}{error}")
        tried = [
            f"{t.candidate.effect} (held out ×{s.held_out_before / max(t.held_out_after, 1e-300):.2f}"
            f"{'' if t.determined else ', parameters not determined'})"
            for t in s.trials
            if t.candidate.effect != s.effect
        ]
        if tried:
            lines += ["", f"Also tried: {'; '.join(tried)}."]
        lines += ["", f"![{s.effect}]({name})", ""]
    if not result.steps:
        where = _where(result.model, signals, "motor", dt_s)
        files.append(_panels("residual of the model (motor)", {"model": where}, out_dir / "residual.png"))
        lines += ["## Where the residual is", ""] + [f"- {line}" for line in where.lines()]
        lines += ["", "![residual](residual.png)", ""]
    if result.rejected:
        rule = f"needs ×{opts.min_shrink:g} held out and determined parameters"
        lines += [f"Not accepted at the end ({rule}):", ""] + [f"- {line}" for line in result.rejected]
        lines.append("")
    if result.unexplained is not None:
        lines += [f"Largest residual signature left: {result.unexplained.line()}.", ""]
    lines += ["![worst window](window.png)", ""]
    if result.final_model is not None:
        what = "with the effects added" if result.steps else "(unchanged: nothing was added)"
        lines.append(f"Model file {what}: `{result.final_model}`")
    summary = out_dir / "summary.md"
    summary.write_text("\n".join(lines) + "\n")
    return [summary, *files]
