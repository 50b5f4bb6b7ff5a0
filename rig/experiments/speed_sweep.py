"""`speed-sweep`: steady motor speeds from negative to positive; friction torque from the current.

At constant speed the motor's torque K_m·i_a balances all friction seen from the motor: F_m + r·F_l
(+ r·τ_ext when a load is applied). The friction depends on position as well as speed (a slow, quadratic
trend along the stroke and a ripple every motor turn), so every speed is measured at the same place:
each pass, forward then backward, crosses the same whole motor turns about one centre
(`same_place_program`), and each window's figure is the friction's smooth part at that centre, fitted
beside the per-turn ripple (`friction_at_centre`). The fast speeds average more turns, so that their
windows also span several periods of the output's barely damped mode (its inertial torque r·J_l·α_l
does not average out of a window shorter than that); passes start and stop in slow raised-cosine ramps
that leave that mode nearly still. Windows where the output stuck or ran back against the motor (the
kinematic error at low speed) are reported and left out of the Coulomb/viscous line.
(`friction_table` is the plain mean over each constant-speed pass, whatever its place: the identification
reads the sweeps' windows with it, its model evaluated at every instant of them.)
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated

import numpy as np
from pydantic import Field, ValidationInfo, field_validator

from model.run import Run
from rig.experiments.base import (
    LIST_MAX,
    LOAD_MAX_NM,
    SPEED_MAX_RAD_S,
    Experiment,
    ExperimentParams,
    ProgramError,
    Results,
    RigContext,
    rig_speeds,
    segments_of,
    speed_refusal,
)
from rig.experiments.plots import new_figure, save_figure
from rig.interface import ControlMode, Segment


class SpeedSweepParams(ExperimentParams):
    speeds_rad_s: list[Annotated[float, Field(gt=0, le=SPEED_MAX_RAD_S)]] = Field(
        default=[0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0, 200.0],
        min_length=1,
        max_length=LIST_MAX,
        description="motor speed magnitudes, distinct; each is run forward and backward [rad/s]",
    )
    settle_s: float = Field(
        default=0.1, gt=0, le=10, description="time at speed before the window, not averaged [s]"
    )
    hold_s: float = Field(
        default=0.7,
        gt=0,
        le=60,
        description="averaging time per speed and direction, as whole motor turns about the sweep's centre:"
        " at least one turn, at most what the stroke holds at the fastest speed [s]",
    )
    travel_fraction: float = Field(
        default=0.8,
        gt=0,
        le=1,
        description="share of the free stroke ahead a pass may use; shortens holds [–]",
    )
    tau_ext_nm: float = Field(
        default=0.0,
        ge=-LOAD_MAX_NM,
        le=LOAD_MAX_NM,
        description="external load torque during the sweep [N·m]",
    )

    @field_validator("speeds_rad_s")
    @classmethod
    def _positive_speeds(cls, speeds: list[float], info: ValidationInfo) -> list[float]:
        return rig_speeds(speeds, info)


TURN_RAD = 2.0 * math.pi
RAMP_S = 0.5
"""Each fast pass reaches its speed, and stops from it, in a raised cosine of this duration: slow against
the load's barely damped mode (its ring decays over seconds and would not average out of a window)."""
RAMP_MIN_S = 0.2
"""The slow passes' ramps: the ring a ramp leaves grows with the speed it reaches, so below
RAMP_FULL_SPEED_RAD_S the ramp shortens in proportion, down to this (still two periods of a ~10 Hz mode)."""
RAMP_FULL_SPEED_RAD_S = 20.0
REST_S = 0.1
"""Rest between passes [s]."""
MOVE_SPEED_RAD_S = 20.0
"""Speed of the moves between the passes (not averaged)."""
FOURIER_HARMONICS = 6
"""Per-turn harmonics fitted beside the smooth friction in each window (the wave generator's ripple)."""
EDGE_TAPER_RAD = math.pi / 4
"""Each window's samples are weighted up from its edges over this motor angle (raised cosine): a torque
ripple faster than the fitted harmonics (the kinematic error's, k per turn, carrying the load through the
gear) then leaves no partial cycle at the edges in the figure."""
LOAD_SMOOTHING_S = 0.01
"""Half-width of the central difference that estimates the output's speed from θ_l (its noise averaged)."""
LOAD_UNSTEADY_SHARE = 0.05
"""A window whose output runs against the motor's direction, or stands, this often is load-unsteady."""


def margin_rad(speed_rad_s: float) -> float:
    """Slack before and after a window for where the motor lags its set-points' place [rad]."""
    return min(math.pi / 2, 0.2 + 0.01 * speed_rad_s)


def ramp_s(speed_rad_s: float) -> float:
    """Duration of the raised-cosine ramp to or from `speed_rad_s` [s]."""
    return min(RAMP_S, max(RAMP_MIN_S, RAMP_S * speed_rad_s / RAMP_FULL_SPEED_RAD_S))


def window_turns(speed_rad_s: float, params: SpeedSweepParams, room_rad: float) -> float:
    """Motor turns averaged at a speed about the centre: the travel of hold_s, rounded up to whole turns
    where that is at least one (always at the fastest speed), at most as many as a pass of the fastest
    speed fits in the stroke ahead, `room_rad` (every speed's run-up is shorter than its). A slower speed
    covers less than a turn in hold_s: its window is that part of a turn, and its figure takes the
    per-turn ripple from the whole-turn windows (`same_place_table`) instead of a whole turn at a crawl."""
    fastest = max(params.speeds_rad_s)
    travel_turns = params.hold_s * speed_rad_s / TURN_RAD
    if travel_turns < 1.0 and speed_rad_s < fastest:
        return travel_turns
    fit = math.floor((room_rad / 2 - _run_up_rad(fastest, params)) / math.pi)
    return float(max(1, min(math.ceil(travel_turns - 1e-9), fit)))


def room_ahead_rad(params: SpeedSweepParams, ctx: RigContext) -> float:
    """Motor travel the sweep may use ahead of where it starts [rad]."""
    limits = ctx.config.limits
    return (limits.travel_max_out_rad / ctx.gear_ratio - ctx.theta_m0) * params.travel_fraction


def _run_up_rad(speed_rad_s: float, params: SpeedSweepParams) -> float:
    """Motor angle a pass travels before its window: its ramp, settling at its speed, a margin."""
    return speed_rad_s * (ramp_s(speed_rad_s) / 2 + params.settle_s) + margin_rad(speed_rad_s)


def sweep_centre(params: SpeedSweepParams, ctx: RigContext) -> float:
    """The motor angle every speed's friction is measured about [rad]: the fastest pass starts where the
    sweep starts, its run-up and half its window before it."""
    fastest = max(params.speeds_rad_s)
    turns = window_turns(fastest, params, room_ahead_rad(params, ctx))
    return ctx.theta_m0 + _run_up_rad(fastest, params) + turns * math.pi


def _ramped(speed: float, distance_rad: float, dt_s: float, ramp_cycles: int) -> tuple[np.ndarray, ...]:
    """(up, flat, down) speed magnitudes of a rest-to-rest move over `distance_rad`: raised-cosine ramps
    (each covers half its time at full speed), a flat part of whole cycles between."""
    ramp = 0.5 - 0.5 * np.cos(np.pi * (np.arange(ramp_cycles) + 0.5) / ramp_cycles)
    flat = max(1, round((distance_rad / speed - ramp_cycles * dt_s) / dt_s))
    return speed * ramp, np.full(flat, speed), speed * ramp[::-1]


def same_place_program(
    params: SpeedSweepParams, ctx: RigContext, prefix: str = "", experiment: str = "speed-sweep"
) -> list[Segment]:
    """For each speed, fastest first, a pass forward then one backward across the same whole motor turns
    about `sweep_centre`, from rest to rest: `<prefix>ramp`, the constant speed `<prefix>v+<speed>` (or
    `v-<speed>`), `<prefix>ramp`, `<prefix>rest`; between speeds a move to the next pass's start, and a
    move back to the start at the end (`<prefix>move`). The windows all lie about one place, so the
    friction's dependence on position is the same in every speed's figure."""
    room_m = room_ahead_rad(params, ctx)
    speeds = sorted(params.speeds_rad_s, reverse=True)
    # The rig's speed first: a pass's travel at a speed the drive cannot reach says nothing useful.
    if (refusal := speed_refusal(speeds[0], ctx.config, f"{experiment}: speeds_rad_s")) is not None:
        raise ProgramError(refusal)
    centre = sweep_centre(params, ctx)
    span_rad = 2 * (centre - ctx.theta_m0)
    if span_rad > room_m:
        raise ProgramError(
            f"{experiment}: at {speeds[0]} rad/s a pass needs {span_rad:.3g} rad of motor travel (its ramps,"
            f" settle_s = {params.settle_s} s and one turn), the stroke ahead has {room_m:.3g}"
        )
    dt_s = 1.0 / ctx.rate_hz
    tau = params.tau_ext_nm
    segments: list[Segment] = []
    here = ctx.theta_m0  # where the set-points leave the motor

    def move(to_rad: float, speed: float, name: str, flat_label: str) -> None:
        # Labels unique in the run; only the constant-speed part of a pass starts with `<prefix>v`.
        nonlocal here
        distance = abs(to_rad - here)
        if distance < 1e-9:
            return
        sign = 1.0 if to_rad > here else -1.0
        for _ in range(2):  # a short move: slower, with the slower speed's ramps
            ramp_cycles = ctx.cycles(ramp_s(speed))
            speed = min(speed, distance / (ramp_cycles * dt_s))
        up, flat, down = _ramped(speed, distance, dt_s, ramp_cycles)
        for profile, label in ((up, f"{name}:up"), (flat, flat_label), (down, f"{name}:down")):
            segments.append(Segment(ControlMode.VELOCITY, sign * profile, tau, label))
            here += sign * float(np.sum(profile)) * dt_s
        segments.append(Segment(ControlMode.VELOCITY, np.zeros(ctx.cycles(REST_S)), tau, f"{name}:rest"))

    moves = 0

    def reposition(to_rad: float) -> None:
        nonlocal moves
        moves += 1
        name = f"{prefix}move{moves}"
        move(to_rad, MOVE_SPEED_RAD_S, name, name)

    for speed in speeds:
        reach = _run_up_rad(speed, params) + window_turns(speed, params, room_m) * math.pi
        reposition(centre - reach)
        for sign in (1.0, -1.0):
            move(
                centre + sign * reach, speed, f"{prefix}pass{sign * speed:+g}", f"{prefix}v{sign * speed:+g}"
            )
    reposition(ctx.theta_m0)
    return segments


def _load_steady(theta_l: np.ndarray, rows: np.ndarray, direction: float, ctx: RigContext) -> bool:
    """Whether the output moves along with the motor through a window: its speed from a central
    difference of θ_l over ±LOAD_SMOOTHING_S runs against the motor, or stands, in few of the rows."""
    h = ctx.cycles(LOAD_SMOOTHING_S)
    inner = rows[(rows >= h) & (rows < len(theta_l) - h)]
    if inner.size == 0:
        return True
    moved = (theta_l[inner + h] - theta_l[inner - h]) * direction
    return bool(np.mean(moved <= 0.0) <= LOAD_UNSTEADY_SHARE)


def _harmonics(theta_m: np.ndarray) -> list[np.ndarray]:
    """cos(nθ_m), sin(nθ_m) for the per-turn harmonics n = 1..FOURIER_HARMONICS."""
    columns = []
    for n in range(1, FOURIER_HARMONICS + 1):
        columns += [np.cos(n * theta_m), np.sin(n * theta_m)]
    return columns


def _edge_weight(x: np.ndarray, half_rad: float) -> np.ndarray:
    """Square root of the raised-cosine weight up from a window's edges (EDGE_TAPER_RAD, or a quarter of
    a short window)."""
    taper = min(EDGE_TAPER_RAD, half_rad / 2)
    edge = np.clip((half_rad - np.abs(x)) / taper, 0.0, 1.0)
    return np.asarray(np.sqrt(0.5 - 0.5 * np.cos(math.pi * edge)))


def friction_at_centre(
    theta_m: np.ndarray, torque: np.ndarray, centre: float, turns: float, ripple: np.ndarray | None = None
) -> tuple[float, np.ndarray | None]:
    """The smooth part of the torque at `centre`, and the per-turn harmonics' coefficients fitted beside
    it (None for a window under a turn).

    Whole turns: least squares of torque = c0 + c1·x (+ c2·x² over more than one turn) + per-turn
    harmonics, x = θ_m − centre, weighted up from the edges (EDGE_TAPER_RAD); c0. Windows of more turns
    (the fast speeds) would otherwise average a wider stretch of the friction's slow, quadratic dependence
    on position. Under a turn the harmonics cannot be told from the smooth part: `ripple` (the torque's
    harmonics in this direction, from whole-turn windows) is taken out and c0 + c1·x fitted to the rest."""
    x = theta_m - centre
    half_rad = turns * math.pi
    root_weight = _edge_weight(x, half_rad)
    harmonics = _harmonics(theta_m)
    if turns >= 1.0:
        columns = [np.ones_like(x), x] + ([x * x] if turns > 1 else []) + harmonics
        design = np.column_stack(columns) * root_weight[:, None]
        coef, *_ = np.linalg.lstsq(design, torque * root_weight, rcond=None)
        return float(coef[0]), coef[len(columns) - len(harmonics) :]
    rest = torque - (np.column_stack(harmonics) @ ripple if ripple is not None else 0.0)
    design = np.column_stack([np.ones_like(x), x]) * root_weight[:, None]
    coef, *_ = np.linalg.lstsq(design, rest * root_weight, rcond=None)
    return float(coef[0]), None


def _ripple(windows: list[tuple[float, np.ndarray | None]]) -> np.ndarray | None:
    """The per-turn ripple of the friction as it opposes forward motion, from (set speed, harmonics) of
    the whole-turn windows: the slowest ones' harmonics, each times its direction (the position-dependent
    friction turns with the motion's sign), averaged. The slowest, because their harmonics lie farthest
    below the output's mode."""
    whole = [(abs(speed), np.sign(speed) * coef) for speed, coef in windows if coef is not None]
    if not whole:
        return None
    slowest = min(speed for speed, _ in whole)
    return np.asarray(np.mean([coef for speed, coef in whole if speed == slowest], axis=0))


def _is_pass(label: str, prefix: str) -> bool:
    """Whether `label` is a constant-speed pass `<prefix>v<signed speed>` of `same_place_program`."""
    try:
        float(label[len(prefix) + 1 :])
    except ValueError:
        return False
    return True


def same_place_table(
    run: Run, params: SpeedSweepParams, ctx: RigContext, prefix: str = "", torque: np.ndarray | None = None
) -> dict[str, np.ndarray]:
    """Per pass: the speed held and the friction at the centre (`friction_at_centre` of K_m·i_a over the
    pass's turns about `sweep_centre`, once settled; a window under a turn with the whole-turn windows'
    ripple taken out); the plain mean and spread over the window; how much of its planned angle the pass
    covered; whether the output moved steadily along. `torque`: the torque column to read [N·m] (default
    K_m·i_a)."""
    centre = sweep_centre(params, ctx)
    if torque is None:
        torque = ctx.torque_constant_nm_per_a * run["i_a"]
    theta_m = run["theta_m"]
    names = ("omega_set", "omega_m", "torque_nm", "torque_mean_nm", "torque_std", "theta_m", "turns")
    rows_of: dict[str, list[float]] = {k: [] for k in (*names, "load_steady")}
    skip = ctx.cycles(params.settle_s)
    room_rad = room_ahead_rad(params, ctx)
    passes = []
    for seg in segments_of(run, prefix + "v"):
        if not _is_pass(str(seg["label"]), prefix):
            continue  # another segment under the prefix (an endurance checkpoint's loaded `v+5L`)
        set_speed = float(run["setpoint"][int(seg["start"])])
        turns = window_turns(abs(set_speed), params, room_rad)
        rows = np.arange(int(seg["start"]) + skip, int(seg["start"]) + int(seg["cycles"]))
        rows = rows[np.abs(theta_m[rows] - centre) < turns * math.pi]
        if rows.size < 2 * (4 + 2 * FOURIER_HARMONICS):  # a pass cut short (an aborted run)
            continue
        passes.append((set_speed, turns, rows))
    # Whole-turn windows first: their figures, and the harmonics the windows under a turn take out.
    whole = {
        i: friction_at_centre(theta_m[rows], torque[rows], centre, turns)
        for i, (_, turns, rows) in enumerate(passes)
        if turns >= 1.0
    }
    ripple = _ripple([(passes[i][0], coef) for i, (_, coef) in whole.items()])
    for i, (set_speed, turns, rows) in enumerate(passes):
        held = torque[rows]
        direction = np.sign(set_speed)
        if i in whole:
            figure = whole[i][0]
        else:
            signed_ripple = direction * ripple if ripple is not None else None
            figure, _ = friction_at_centre(theta_m[rows], held, centre, turns, signed_ripple)
        rows_of["omega_set"].append(set_speed)
        rows_of["omega_m"].append(float(np.mean(run["omega_m"][rows])))
        rows_of["torque_nm"].append(figure)
        rows_of["torque_mean_nm"].append(float(np.mean(held)))
        rows_of["torque_std"].append(float(np.std(held)))
        rows_of["theta_m"].append(float(np.mean(theta_m[rows])))
        rows_of["turns"].append(float(np.ptp(theta_m[rows])) / TURN_RAD / turns)
        rows_of["load_steady"].append(float(_load_steady(run["theta_l"], rows, direction, ctx)))
    order = np.argsort(rows_of["omega_set"], kind="stable")
    return {name: np.asarray(values)[order] for name, values in rows_of.items()}


def friction_table(run: Run, ctx: RigContext, settle_s: float, prefix: str = "") -> dict[str, np.ndarray]:
    """Per constant-speed segment: the speed held and the motor torque that held it (mean and spread)."""
    skip = ctx.cycles(settle_s)
    rows: dict[str, list[float]] = {
        k: [] for k in ("omega_set", "omega_m", "torque_nm", "torque_std", "theta_m")
    }
    for seg in segments_of(run, prefix + "v"):
        window = slice(int(seg["start"]) + skip, int(seg["start"]) + int(seg["cycles"]))
        torque = ctx.torque_constant_nm_per_a * run["i_a"][window]
        rows["omega_set"].append(float(run["setpoint"][window][0]))
        rows["omega_m"].append(float(np.mean(run["omega_m"][window])))
        rows["torque_nm"].append(float(np.mean(torque)))
        rows["torque_std"].append(float(np.std(torque)))
        rows["theta_m"].append(float(np.mean(run["theta_m"][window])))
    order = np.argsort(rows["omega_set"])
    return {name: np.asarray(values)[order] for name, values in rows.items()}


def coulomb_viscous_fit(table: dict[str, np.ndarray]) -> dict[str, float]:
    """Least squares of |torque| = F_c + b·|ω| per direction: the Coulomb level and the viscous slope."""
    out: dict[str, float] = {}
    for sign, name in ((1.0, "pos"), (-1.0, "neg")):
        pick = np.sign(table["omega_set"]) == sign
        if np.count_nonzero(pick) >= 2:
            slope, level = np.polyfit(np.abs(table["omega_m"][pick]), np.abs(table["torque_nm"][pick]), 1)
            out[f"coulomb_{name}_nm"] = float(level)
            out[f"viscous_{name}_nm_s_rad"] = float(slope)
    return out


class SpeedSweep(Experiment):
    name = "speed-sweep"
    summary = "steady speeds both ways; friction torque against velocity from the current"
    Params = SpeedSweepParams
    needs = frozenset({ControlMode.VELOCITY})

    def program(self, params: SpeedSweepParams, ctx: RigContext) -> list[Segment]:
        return same_place_program(params, ctx)

    def analyze(self, run: Run, params: SpeedSweepParams, ctx: RigContext) -> Results:
        table = same_place_table(run, params, ctx)
        steady = table["load_steady"] > 0.5
        notes = []
        for sign in (1.0, -1.0):
            side = np.sign(table["omega_set"]) == sign
            if np.count_nonzero(side & steady) < 2:
                notes.append(
                    f"fewer than 2 passes at {'positive' if sign > 0 else 'negative'} speeds had the output"
                    " moving steadily along: the line is fitted through all of them"
                )
                steady = steady | side
        metrics: dict[str, float | int | str] = {
            "speeds": len(params.speeds_rad_s),
            "centre_rad": sweep_centre(params, ctx),
            "coverage_min": float(np.min(table["turns"])) if table["turns"].size else math.nan,
            "windows_load_unsteady": int(np.count_nonzero(table["load_steady"] < 0.5)),
        }
        metrics.update(coulomb_viscous_fit({name: column[steady] for name, column in table.items()}))
        notes.append(
            f"friction at one place: each speed's smooth friction at θ_m = {metrics['centre_rad']:.4g} rad,"
            " fitted over whole motor turns about it (more at high speed) beside the per-turn ripple, or over"
            " the part of a turn a slow speed covers with that ripple taken out;"
            " passes where the output stuck or ran back (its kinematic error at low speed) are left out of"
            " the Coulomb/viscous line"
        )
        return Results(metrics, {"friction_vs_velocity": table}, notes)

    def plot(
        self, run: Run, results: Results, params: SpeedSweepParams, ctx: RigContext, out_dir: Path
    ) -> list[Path]:
        table = results.tables["friction_vs_velocity"]
        centre = float(results.metrics["centre_rad"])
        fig, ax = new_figure(f"Friction torque against motor speed, at θ_m = {centre:.4g} rad")
        ax.errorbar(table["omega_m"], table["torque_nm"], yerr=table["torque_std"], fmt="o-", capsize=3)
        ax.set_xscale("symlog", linthresh=1.0)
        ax.set_xlabel("motor speed ω_m [rad/s]")
        ax.set_ylabel("motor torque K_m·i_a [N·m]")
        ax.axhline(0.0, color="0.6", lw=0.8)
        return [save_figure(fig, out_dir / "friction_vs_velocity.png")]
