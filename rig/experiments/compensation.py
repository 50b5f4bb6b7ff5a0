"""`compensation`: what a model's feed-forward buys in tracking, measured off and on with the same set-points.

The step, sine and low-speed ramp of the tracking experiments (their default parameters) are each played
without compensation, with the model's feed-forward (`model.compensator`: friction by the model's law
with its position terms, inertia, the transmission's twist, the kinematic error), and with the model's
friction deliberately off by each of `friction_errors` (−20 % and +20 %), one after the other, so the
variants meet the same bench in the same state. Each is preceded by an approach (the motor backs off by
`approach_rad` and returns, without feed-forward) and a hold at the start position. Every
variant's error is measured from the same zero, the run's (taken at rest before the program, as the
tracking experiments take it): where friction leaves a gear at rest is anywhere within a band, and a zero
taken at each variant's hold carried that variant's stuck twist into all of its error (after a warm-up it
made the ramp's `on` 2.5× worse than `on_no_temperature`, the feed-forward no worse). From the common zero
an earlier variant's residual stick counts only until the motion breaks it free.

Per motion: the RMS of the load's tracking error θ_l − r·θ_sp (sine: after the first period; ramp: after
`skip_s` in each direction, lag included) off and on, `rms_error_<motion>_<variant>_rad`, and for the sine
and the ramp their ratio `improvement_<motion>` (off over on), the same ratio per friction error. The
step's RMS error is mostly the step itself, the same with or without feed-forward, so its ratio would be
≈ 1 by construction; for the step the figures are what feed-forward can change, each the mean over the
two steps (`step-to`, `step-back`) of the load θ_l − θ_l(zero) against r·(θ_sp − θ_m0), by the `step`
experiment's `step_metrics` with its default band and steady window: `overshoot_pct_step_<variant>`
(how far past the new set-point the load goes, % of the step) and `settling_s_step_<variant>` (time after
which it stays within ±2 % of the step of it, NaN if it does not settle). For the ramp also the
stick-slip amplitude (peak-to-peak of the detrended error, as `ramp` computes it) off and on,
`improvement_stick_slip`. A variant that tracks worse than no
compensation is named in the notes.

Temperature (issue 27 item 7): with a model whose `thermal` law has beta_T ≠ 0 the compensated tracks
carry the law, and a rig that records `temp_gear` plays their friction at the gear's measured
temperature (`model.compensator`); `compare_temperature` (default on) adds the variant
`on_no_temperature`, the same feed-forward with the friction left at T_ref, and the metric
`temperature_gain_<motion>`: its RMS error over that of `on` (> 1: the measured temperature helps).

The approach and repeats: where friction leaves a gear at rest carries from one variant into the next,
and a sine's stick phases keep it, so two plays of the same feed-forward differed (on the seed held at
T_ref, where `on` and `on_no_temperature` plan the same, their sine RMS by 13 %, the same in six repeats:
`on` always followed `off`). The approach drags the gear into the same state before every variant (that
null then reads 1.000 ± 0.002). `repeats` plays every motion's variants that many times, each time in an
order rotated by one; the figures pool the repeats (the RMS of their RMS, the mean of the rest), and with
two or more `temperature_gain_<motion>_std` gives the spread of the repeats' own ratios as the σ of their
mean.

It needs a model file (`--set model=FILE`): on a simulated rig, one fitted (`hdrig fit`) on a campaign
recorded on that rig, not the plant's own parameters. It is not part of the campaign for that reason.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydantic import Field, field_validator

from model.compensator import Compensator
from model.errors import UserInputError
from model.feedforward import FF_LEVEL, FeedForwardTrack, min_measured_band_rad_s
from model.params import HarmonicDriveModel, load_model
from model.run import Run
from rig.experiments.base import Experiment, ExperimentParams, Results, RigContext, segment_rows
from rig.experiments.plots import new_figure, save_figure
from rig.experiments.tracking import (
    STEP_LABELS,
    Ramp,
    RampParams,
    Sine,
    SineParams,
    Step,
    StepParams,
    check_stroke,
    detrended,
    output_track,
    step_metrics,
)
from rig.interface import ControlMode, Segment

MOTIONS = ("step", "sine", "ramp")
MOTION_PARAMS = {"step": StepParams(), "sine": SineParams(), "ramp": RampParams()}
MOTION_PROGRAMS = {"step": Step(), "sine": Sine(), "ramp": Ramp()}


class CompensationParams(ExperimentParams):
    model: str = Field(
        description="model file (or preset name) whose feed-forward is tested; on a simulated rig, one fitted"
        " on a campaign recorded on that rig"
    )
    friction_errors: list[float] = Field(
        default=[-0.2, 0.2],
        max_length=4,
        description="errors put on the model's friction for extra compensated runs (−0.2: 20 % low) [–]",
    )
    measured_velocity: bool = Field(
        default=False,
        description="near zero planned speed, take the friction's direction from the measured speed"
        " (in a band twice the one that would undamp the velocity loop)",
    )
    jump_s: float = Field(
        default=0.016,
        ge=0.002,
        le=0.2,
        description="time the motor takes to jump over a fold of the kinematic error [s]",
    )
    smooth_s: float = Field(
        default=0.008,
        ge=0.001,
        le=0.2,
        description="smoothing of the planned twist (kinks, friction flips) [s]",
    )
    hold_s: float = Field(default=0.5, ge=0.1, le=10, description="hold at the start before each variant [s]")
    approach_rad: float = Field(
        default=2.0,
        ge=0,
        le=50,
        description="before each variant's hold the motor backs off this far and returns, without"
        " feed-forward, so that every variant starts from the same side [rad]",
    )
    repeats: int = Field(
        default=1,
        ge=1,
        le=8,
        description="times each motion's variants are played, each time in an order rotated by one; the"
        " figures pool the repeats, and the temperature gain gives its spread over them",
    )
    compare_temperature: bool = Field(
        default=True,
        description="with a model whose thermal law has beta_T ≠ 0: also play the compensation without the"
        " measured temperature (friction at T_ref), variant on_no_temperature",
    )

    @field_validator("model")
    @classmethod
    def _loads(cls, name: str) -> str:
        load_model(name)  # a missing or invalid file is told here, before the rig moves
        return name

    @field_validator("friction_errors")
    @classmethod
    def _plausible(cls, errors: list[float]) -> list[float]:
        for error in errors:
            if not -0.9 <= error <= 2.0 or error == 0.0:
                raise ValueError(f"each must be a nonzero share between -0.9 and 2 (got {error})")
        return errors


@dataclass(frozen=True)
class Variant:
    tag: str  # off, on, on_no_temperature, friction_minus_20pct, ...
    friction_scale: float | None  # None: no compensation
    temperature: bool = True  # the track's friction follows the measured gear temperature (if any)


NO_TEMPERATURE = "on_no_temperature"
APPROACH_S = 1.0
"""Time of the approach before each variant's hold (`approach_rad`) [s]."""


def has_thermal_law(params: CompensationParams) -> bool:
    """Whether the model's friction follows the gear's temperature (a thermal section, beta_T ≠ 0)."""
    law = load_model(params.model).thermal
    return law is not None and law.beta_T != 0.0


def variants(params: CompensationParams) -> list[Variant]:
    out = [Variant("off", None), Variant("on", 1.0)]
    if params.compare_temperature and has_thermal_law(params):
        out.append(Variant(NO_TEMPERATURE, 1.0, temperature=False))
    for error in params.friction_errors:
        sign = "minus" if error < 0 else "plus"
        out.append(Variant(f"friction_{sign}_{abs(error) * 100:.0f}pct", 1.0 + error))
    return out


def _prefix(motion: str, variant: Variant, repeat: int) -> str:
    """Labels' start for one play of a variant: `sine-on`, then `sine-on-r2`, ... for the repeats."""
    return f"{motion}-{variant.tag}" + (f"-r{repeat + 1}" if repeat else "")


def _hold_label(motion: str, variant: Variant, repeat: int = 0) -> str:
    return f"{_prefix(motion, variant, repeat)}-hold"


def _motion_labels(motion: str, variant: Variant, ctx: RigContext, repeat: int = 0) -> list[str]:
    return [f"{_prefix(motion, variant, repeat)}-{seg.label}" for seg in _motion_segments(motion, ctx)]


def _play_order(params: CompensationParams, repeat: int) -> list[Variant]:
    """The variants of one repeat in the order played: rotated by one per repeat, so that no variant
    always follows the same other (what the gear was left in by the variant before carries over)."""
    every = variants(params)
    shift = repeat % len(every)
    return every[shift:] + every[:shift]


def _motion_segments(motion: str, ctx: RigContext) -> list[Segment]:
    return MOTION_PROGRAMS[motion].program(MOTION_PARAMS[motion], ctx)


def _track(
    model: HarmonicDriveModel,
    variant: Variant,
    setpoints: np.ndarray,
    params: CompensationParams,
    ctx: RigContext,
) -> FeedForwardTrack:
    assert variant.friction_scale is not None
    track = Compensator(model, variant.friction_scale, variant.temperature).plan(
        setpoints,
        1.0 / ctx.rate_hz,
        ctx.theta_m0,
        ctx.config.control.max_velocity_rad_s,
        jump_s=params.jump_s,
        smooth_s=params.smooth_s,
        label=variant.tag,
    )
    if not params.measured_velocity:
        return track
    level = float(np.max(track.rows[:, FF_LEVEL]))
    band = 2.0 * min_measured_band_rad_s(level, model.motor.K_m, ctx.config.control.velocity_kp)
    return FeedForwardTrack(track.rows, band, variant.tag, track.thermal)


class Compensation(Experiment):
    name = "compensation"
    summary = "step, sine and slow ramp without and with the model's feed-forward (and its friction ±20 %)"
    Params = CompensationParams
    needs = frozenset({ControlMode.POSITION})

    def program(self, params: CompensationParams, ctx: RigContext) -> list[Segment]:
        model = load_model(params.model)
        if abs(model.mechanics.r - ctx.gear_ratio) > 1e-9 * ctx.gear_ratio:
            raise UserInputError(
                f"run {self.name}: field 'model': gear ratio r = {model.mechanics.r}"
                f" is not the rig's {ctx.gear_ratio}"
            )
        hold = np.full(ctx.cycles(params.hold_s), ctx.theta_m0)
        back = np.arange(ctx.cycles(APPROACH_S)) / ctx.cycles(APPROACH_S)
        approach = ctx.theta_m0 - params.approach_rad * (1 - np.cos(2 * np.pi * back)) / 2
        check_stroke(ctx, -ctx.gear_ratio * params.approach_rad, 0.0, self.name, "approach_rad")
        program = []
        for motion in MOTIONS:
            pieces = _motion_segments(motion, ctx)
            setpoints = np.concatenate([hold, *[seg.setpoint for seg in pieces]])
            bounds = np.cumsum([0, hold.shape[0], *[seg.cycles for seg in pieces]])
            tracks = {
                v.tag: None if v.friction_scale is None else _track(model, v, setpoints, params, ctx)
                for v in variants(params)
            }
            for repeat in range(params.repeats):
                for variant in _play_order(params, repeat):
                    track = tracks[variant.tag]
                    if params.approach_rad > 0:
                        label = f"{_prefix(motion, variant, repeat)}-approach"
                        program.append(Segment(ControlMode.POSITION, approach, 0.0, label))
                    labels = [
                        _hold_label(motion, variant, repeat),
                        *_motion_labels(motion, variant, ctx, repeat),
                    ]
                    for i, label in enumerate(labels):
                        part = None if track is None else track.part(int(bounds[i]), int(bounds[i + 1]))
                        program.append(
                            Segment(
                                ControlMode.POSITION, setpoints[bounds[i] : bounds[i + 1]], 0.0, label, part
                            )
                        )
        return program

    # --- analysis ----------------------------------------------------------------------------------------

    @staticmethod
    def _error(run: Run, ctx: RigContext, label: str) -> tuple[np.ndarray, np.ndarray]:
        """(time since the segment's start [s], θ_l − r·θ_sp [rad]) from the run's zero (module docstring)."""
        track = output_track(run, ctx, segment_rows(run, label))
        return track.t_s, track.load - track.setpoint

    def _figures(
        self, run: Run, ctx: RigContext, motion: str, variant: Variant, repeats: int
    ) -> dict[str, float]:
        """A variant's figures pooled over its repeats (RMS of the RMS, means of the rest); `rms_<k>` each
        repeat's own RMS."""
        each = [self._play_figures(run, ctx, motion, variant, k) for k in range(repeats)]
        pooled = {key: float(np.mean([f[key] for f in each])) for key in each[0] if key != "rms"}
        pooled["rms"] = float(np.sqrt(np.mean([f["rms"] ** 2 for f in each])))
        pooled.update({f"rms_{k}": f["rms"] for k, f in enumerate(each)})
        return pooled

    def _play_figures(
        self, run: Run, ctx: RigContext, motion: str, variant: Variant, repeat: int
    ) -> dict[str, float]:
        labels = _motion_labels(motion, variant, ctx, repeat)
        if motion == "sine":
            t, e = self._error(run, ctx, labels[0])
            sine = MOTION_PARAMS["sine"]
            assert isinstance(sine, SineParams)
            keep = t >= sine.skip_periods / sine.freq_hz
            return {"rms": float(np.sqrt(np.mean(e[keep] ** 2)))}
        if motion == "ramp":
            ramp = MOTION_PARAMS["ramp"]
            assert isinstance(ramp, RampParams)
            rms, pp = [], []
            for label in labels:
                t, e = self._error(run, ctx, label)
                keep = t >= ramp.skip_s
                rms.append(np.mean(e[keep] ** 2))
                pp.append(np.ptp(detrended(t[keep], e[keep])))
            return {"rms": float(np.sqrt(np.mean(rms))), "stick_slip": float(np.mean(pp))}
        errors = np.concatenate([self._error(run, ctx, label)[1] for label in labels])
        figures = {"rms": float(np.sqrt(np.mean(errors**2)))}
        step = MOTION_PARAMS["step"]
        assert isinstance(step, StepParams)
        steps = []
        for label in labels:
            if label.removeprefix(f"{_prefix(motion, variant, repeat)}-") not in STEP_LABELS:
                continue
            t, e = self._error(run, ctx, label)
            rows = segment_rows(run, label)
            target = ctx.gear_ratio * (run["setpoint"][rows] - ctx.theta_m0)
            before = ctx.gear_ratio * (run["setpoint"][rows.start - 1] - ctx.theta_m0)
            steps.append(
                step_metrics(
                    t, target + e, before, float(target[0]), step.band_fraction, ctx.cycles(step.steady_s)
                )
            )
        figures["overshoot_pct"] = float(np.mean([m["overshoot_pct"] for m in steps]))
        figures["settling_s"] = float(np.mean([m["settling_s"] for m in steps]))
        return figures

    def analyze(self, run: Run, params: CompensationParams, ctx: RigContext) -> Results:
        metrics: dict[str, float | int | str] = {}
        notes: list[str] = []
        table: dict[str, list[float]] = {
            "motion": [],
            "friction_scale": [],
            "rms_error_rad": [],
            "stick_slip_pp_rad": [],
        }
        for index, motion in enumerate(MOTIONS):
            figures = {v.tag: self._figures(run, ctx, motion, v, params.repeats) for v in variants(params)}
            off = figures["off"]
            for variant in variants(params):
                got = figures[variant.tag]
                metrics[f"rms_error_{motion}_{variant.tag}_rad"] = got["rms"]
                for quantity in ("overshoot_pct", "settling_s"):
                    if quantity in got:
                        metrics[f"{quantity}_{motion}_{variant.tag}"] = got[quantity]
                table["motion"].append(index)
                table["friction_scale"].append(
                    0.0 if variant.friction_scale is None else variant.friction_scale
                )
                table["rms_error_rad"].append(got["rms"])
                table["stick_slip_pp_rad"].append(got.get("stick_slip", float("nan")))
                if variant.friction_scale is None:
                    continue
                suffix = "" if variant.tag == "on" else f"_{variant.tag}"
                if motion != "step":
                    metrics[f"improvement_{motion}{suffix}"] = off["rms"] / got["rms"]
                if variant.tag == NO_TEMPERATURE:
                    # What the measured temperature buys: the error without it over the error with it.
                    metrics[f"temperature_gain_{motion}"] = got["rms"] / figures["on"]["rms"]
                    if params.repeats > 1:  # the spread of the repeats' own ratios, as σ of their mean
                        ratios = [got[f"rms_{k}"] / figures["on"][f"rms_{k}"] for k in range(params.repeats)]
                        spread = float(np.std(ratios, ddof=1) / np.sqrt(params.repeats))
                        metrics[f"temperature_gain_{motion}_std"] = spread
                if got["rms"] > off["rms"]:
                    notes.append(
                        f"{motion}, {variant.tag}: RMS error {got['rms']:.4g} rad is worse than without"
                        f" compensation ({off['rms']:.4g} rad) by {100 * (got['rms'] / off['rms'] - 1):.2g} %"
                    )
                if "stick_slip" in got:
                    metrics[f"stick_slip_pp_{variant.tag}_rad"] = got["stick_slip"]
                    metrics[f"improvement_stick_slip{suffix}"] = off["stick_slip"] / got["stick_slip"]
                    if got["stick_slip"] > off["stick_slip"]:
                        notes.append(
                            f"ramp, {variant.tag}: stick-slip {got['stick_slip']:.3g} rad is worse than"
                            f" without compensation ({off['stick_slip']:.3g} rad)"
                        )
            if "stick_slip" in off:
                metrics["stick_slip_pp_off_rad"] = off["stick_slip"]
        columns = {name: np.asarray(values) for name, values in table.items()}
        return Results(metrics, {"compensation": columns}, notes)

    def plot(
        self, run: Run, results: Results, params: CompensationParams, ctx: RigContext, out_dir: Path
    ) -> list[Path]:
        paths = []
        for motion in MOTIONS:
            if motion == "step":
                m = results.metrics
                gain = (
                    f"overshoot {float(m['overshoot_pct_step_off']):.3g} →"
                    f" {float(m['overshoot_pct_step_on']):.3g} %, settling"
                    f" {float(m['settling_s_step_off']):.3g} → {float(m['settling_s_step_on']):.3g} s"
                )
            else:
                gain = f"RMS {float(results.metrics.get(f'improvement_{motion}', float('nan'))):.3g}× lower"
            fig, ax = new_figure(
                f"{motion}: load tracking error without and with the model's feed-forward ({gain})", 2
            )
            for variant in variants(params):
                labels = _motion_labels(motion, variant, ctx)
                t_parts, e_parts, offset = [], [], 0.0
                for label in labels:
                    t, e = self._error(run, ctx, label)
                    t_parts.append(t + offset)
                    e_parts.append(e)
                    offset += t[-1] + 1.0 / ctx.rate_hz
                t_all, e_all = np.concatenate(t_parts), np.concatenate(e_parts)
                main = variant.tag in ("off", "on")
                target = ax if main else fig.axes[1]
                rms = results.metrics[f"rms_error_{motion}_{variant.tag}_rad"]
                target.plot(
                    t_all, e_all, lw=0.8 if main else 0.6, label=f"{variant.tag} (RMS {float(rms):.2g} rad)"
                )
            for axis in fig.axes:
                axis.set_ylabel("θ_l − r·θ_sp [rad]")
                if axis.get_legend_handles_labels()[0]:  # no friction errors asked: the lower axes stay empty
                    axis.legend(fontsize=8)
            fig.axes[1].set_title("model's friction off by the set errors", fontsize=9)
            fig.axes[1].set_xlabel(f"time since the {motion} started [s]")
            paths.append(save_figure(fig, out_dir / f"compensation_{motion}.png"))
        return paths
