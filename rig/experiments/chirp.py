"""`chirp`: frequency response of the axis, 0.5–20 Hz, with coherence (the article's Bode plots to 10 Hz).

Excitation: periodic multisines — one line every 1/period_s Hz from f_start to f_stop, each with a
random phase, the crest factor lowered by clipping — in the motor speed, riding on a mean speed, played in
closed-loop position mode (the set-point is the integral of that speed): out towards the side of the
stroke with more room, then after a smooth turn back over the same stretch, mirrored, `passes` times.
Every sweep plays its own realization of the phases (the amplitudes the same). Each sweep opens with one
period that fades the excitation in and is not analyzed (the loop's transient), then `periods` whole
periods are analyzed. Why so:
- the article's Bode plots are of the position system; the position loop keeps the axis inside the
  stroke (no drift of integrated speed errors) under the rig's following-error watch;
- with the excitation's peak below the mean speed the motor never reverses, so Coulomb friction keeps
  one sign: a bias, not the stick nonlinearity that would swamp the small signal;
- a periodic excitation analyzed over whole periods (rectangular windows of one period, no overlap)
  has no leakage and every window holds every line, so the coherence measures disturbance and
  nonlinearity, not the windowing of a one-shot sweep (which kept a linear plant's coherence low);
- line amplitudes fall as f^(−amp_exponent), by default f^(−3/4), between a logarithmic sweep's
  f^(−1/2) and constant acceleration's f^(−1): more excitation where the current it asks
  (~2π·f·J·amplitude) is small against friction, less at the load resonance, where the position loop
  drives an almost undamped load (on the seed the current asked stays under the drive's limit);
- the position-dependent friction is a torque that follows θ_m, which follows the reference: over
  periods that each span the same motor turns it would repeat with the excitation and bias every line
  in a way coherence cannot show (by several dB at low frequencies on the seed). So the mean speed is
  moved to the nearest at which a period spans whole motor turns plus 1/`periods` of a turn
  (`sweep_mean_speed`):
  each friction harmonic starts each period 1/`periods` of its cycle further on and its response sums
  to zero over the periods (harmonics that are multiples of `periods` excepted); the slow Coulomb
  level C(θ_m), quadratic in θ_m along the ramp, is taken out as a polynomial trend in time
  (`periodic_records`); and the sweep back over the same stretch flips the friction's sign, so its
  slope against position (a small spring) cancels between the sweeps;
- a nonlinearity the excitation drives (the seed's load swings at its mode by more than its mean
  speed, so its Coulomb friction reverses) distorts onto the excited lines; with one excitation that
  distortion repeats every period and averaging keeps it (the 10 Hz line 1.9 dB off with one Schroeder
  multisine). It differs between phase realizations like noise (Pintelon and Schoukens' robust method
  for the best linear approximation), so the sweeps' own realizations average it out, and the spread
  of their estimates measures what is left;
- a barely damped mode (the seed's load with its motor held by the loop, J_l/b_l = 4 s) still rings
  from the speed-up and the lead-in through the analyzed periods: not periodic, on no line, that ring
  leaks into every line of a period's DFT (by several dB on a linear plant; figures: docs/BENCHMARKS.md,
  "Campaign start and the chirp's ring"). It is fitted as a decaying sinusoid beside the trend and taken
  out with it (`periodic_records`, `ring_mode`).

Estimated at the excitation's lines from the DFTs of each analyzed period (trend taken out), the
reference r being the output set-point with the mean-speed ramp taken out (of it and of θ_l alike), so
that every analyzed signal is periodic:
- `frf_speed`: plant, motor current command i_cmd → measured motor speed ω_m [rad/s per A];
- `frf_load`: plant, i_cmd → load angle θ_l [rad per A];
- `frf_closed_loop`: position system, output set-point → θ_l [rad per rad].
In closed loop the plain H1 = P_uy/P_uu is biased wherever noise fed back through the controller is not
small against the excitation; the reference is uncorrelated with it, so the plant is estimated as
H = Σ R̄·Y / Σ R̄·U over the periods of every sweep (the indirect, "joint input–output" estimate), its
coherence the weaker of γ²(r, u) and γ²(r, y). Each table also carries the 1σ band of H from the data:
the spread of the sweeps' own estimates over √(sweeps) (`magnitude_std_db`, `phase_std_deg`), which
holds noise, the friction's per-period response that the average cancels, and the nonlinear distortion
that differs between realizations. The measured FRFs include the drive's sampling chain (command held one
cycle, speed from filtered encoder differences).

Metrics: `coherence_1_10hz_<frf>`: mean coherence over the lines from 1 to 10 Hz;
`antiresonance_hz`, `resonance_hz`: of i_cmd → ω_m (`resonance`), interpolated between the lines,
`resonance_resolution_hz` their stated resolution (twice the jackknife σ over the fitted lines, or the
line spacing when not interpolated); `line_spacing_hz`: 1/period; `sweep_mean_speed_rad_s`: the mean
motor speed used; `closed_loop_peak_hz`, `closed_loop_peak_db`: the highest coherent line of
set-point → θ_l; `closed_loop_bandwidth_hz`: its first coherent line below −3 dB.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from pydantic import Field, ValidationInfo, field_validator
from scipy import optimize

from model.errors import UserInputError
from model.run import Run
from rig.experiments.base import (
    Experiment,
    ExperimentParams,
    Results,
    RigContext,
    segment_rows,
    segments_of,
)
from rig.experiments.plots import new_figure, save_figure
from rig.experiments.tracking import check_stroke, output_segment
from rig.interface import ControlMode, Segment

SWEEPS = ("sweep-out", "sweep-back")
"""The first pass's sweeps; the k-th pass (k ≥ 2) labels them `sweep-out-k`, `sweep-back-k`."""
CREST_ITERATIONS = 40
"""Clipping iterations that bring a random-phase multisine's crest factor down (`excitation`)."""
COHERENCE_BAND_HZ = (1.0, 10.0)
"""Band of the mean-coherence metrics: the article's Bode range."""

FRFS = {
    # name: (input signal, output signal, what, unit)
    "frf_speed": ("current", "speed", "i_cmd → ω_m", "rad/s/A"),
    "frf_load": ("current", "load", "i_cmd → θ_l", "rad/A"),
    "frf_closed_loop": ("reference", "load", "set-point → θ_l", "rad/rad"),
}


class ChirpParams(ExperimentParams):
    f_start_hz: float = Field(default=0.5, gt=0, le=50, description="lowest line of the excitation [Hz]")
    f_stop_hz: float = Field(
        default=20.0, gt=0, le=200, validate_default=True, description="highest line of the excitation [Hz]"
    )
    period_s: float = Field(
        default=2.0,
        ge=0.2,
        le=30,
        validate_default=True,
        description="period of the excitation; lines every 1/period_s [s]",
    )
    periods: int = Field(
        default=3, ge=2, le=30, description="periods analyzed per sweep, after a lead-in [–]"
    )
    mean_speed_motor_rad_s: float = Field(
        default=25.0,
        gt=0,
        le=300,
        description="motor speed the sweep rides on, so friction keeps its sign [rad/s]",
    )
    speed_amp_motor_rad_s: float = Field(
        default=15.0,
        gt=0,
        validate_default=True,
        le=300,
        description="peak motor speed of the excitation; below the mean speed [rad/s]",
    )
    amp_exponent: float = Field(
        default=0.75, ge=0, le=1.5, description="line amplitudes fall as f^-amp_exponent; 0: flat [–]"
    )
    ramp_s: float = Field(
        default=0.5, gt=0, le=5, description="smooth speed-up and slow-down; the turn takes twice this [s]"
    )
    # A lightly damped resonance loses coherence to the loop's nonlinearity near it: 0.5 keeps its peak
    # (half the output power still linear in the reference) and drops the points friction swamps.
    passes: int = Field(
        default=2,
        ge=1,
        le=8,
        description="out-and-back passes over one stretch; each sweep its own random-phase multisine [–]",
    )
    phase_seed: int = Field(default=0, ge=0, description="seed of the sweeps' random phases [–]")
    coherence_min: float = Field(
        default=0.5, gt=0, lt=1, description="points below it are not used for resonance and bandwidth [–]"
    )

    @field_validator("f_stop_hz")
    @classmethod
    def _above_start(cls, f_stop: float, info: ValidationInfo) -> float:
        f_start = info.data.get("f_start_hz")
        if f_start is not None and f_stop <= f_start:
            raise ValueError(f"must be above f_start_hz ({f_start} Hz)")
        return f_stop

    @field_validator("period_s")
    @classmethod
    def _holds_lowest_line(cls, period_s: float, info: ValidationInfo) -> float:
        f_start = info.data.get("f_start_hz")
        if f_start is not None and period_s * f_start < 1.0 - 1e-9:
            raise ValueError(f"must hold one period of f_start_hz, at least {1.0 / f_start:.4g} s")
        return period_s

    @field_validator("speed_amp_motor_rad_s")
    @classmethod
    def _below_mean(cls, amp: float, info: ValidationInfo) -> float:
        mean = info.data.get("mean_speed_motor_rad_s")
        if mean is not None and amp >= mean:
            raise ValueError(
                f"must be below mean_speed_motor_rad_s ({mean} rad/s): the motor must not reverse"
            )
        return amp


def excitation(params: ChirpParams, ctx: RigContext, realization: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """One period of the speed excitation [rad/s] (peak speed_amp) and its line frequencies [Hz]: the
    `realization`-th random-phase multisine of the lines' amplitudes (phases seeded by `phase_seed`), its
    crest factor lowered by clipping it and restoring the amplitudes, CREST_ITERATIONS times."""
    cycles = ctx.cycles(params.period_s)
    lines = excited_lines(params, ctx)
    freq_hz = lines / (cycles / ctx.rate_hz)
    amps = freq_hz**-params.amp_exponent
    phases = np.random.default_rng([params.phase_seed, realization]).uniform(0.0, 2 * np.pi, lines.size)
    spectrum = np.zeros(cycles // 2 + 1, dtype=complex)
    for _ in range(CREST_ITERATIONS):
        spectrum[lines] = amps * np.exp(1j * phases)
        wave = np.fft.irfft(spectrum, cycles)
        limit = 0.8 * np.max(np.abs(wave))
        phases = np.angle(np.fft.rfft(np.clip(wave, -limit, limit))[lines])
    spectrum[lines] = amps * np.exp(1j * phases)
    wave = np.fft.irfft(spectrum, cycles)
    return params.speed_amp_motor_rad_s * wave / np.max(np.abs(wave)), freq_hz


def excited_lines(params: ChirpParams, ctx: RigContext) -> np.ndarray:
    """The excitation's lines as DFT bins of one period (whole cycles: each a whole number per period)."""
    period_s = ctx.cycles(params.period_s) / ctx.rate_hz
    return np.arange(
        math.ceil(params.f_start_hz * period_s - 1e-9), math.floor(params.f_stop_hz * period_s + 1e-9) + 1
    )


def recorded_sweeps(run: Run, params: ChirpParams) -> list[str]:
    """The sweeps `run` holds, in the order played (a run recorded before `passes` existed has one pass,
    while its parameters read back with today's default)."""
    held = {str(seg["label"]) for seg in segments_of(run)}
    return [label for label in sweep_labels(params) if label in held]


def sweep_labels(params: ChirpParams) -> list[str]:
    """Every sweep's label, in the order played: out, back, out, back, ... (SWEEPS)."""
    return [f"{label}{f'-{k + 1}' if k else ''}" for k in range(params.passes) for label in SWEEPS]


def sweep_mean_speed(params: ChirpParams, ctx: RigContext) -> float:
    """The mean motor speed the sweeps ride on [rad/s]: `mean_speed_motor_rad_s` moved to the nearest
    speed at which one period spans a whole number of motor turns plus 1/`periods` of a turn.

    Then a friction harmonic n·θ_m (n cycles per motor turn) starts each analyzed period 2π·n/periods
    further on, so its response, however the excitation modulates it, sums to zero over the periods
    (n not a multiple of `periods`): the average over periods keeps the response to the excitation
    alone. Never at or below the excitation's peak, so the motor still never reverses.
    """
    period_s = ctx.cycles(params.period_s) / ctx.rate_hz
    turn_rad, step = 2 * np.pi, 1.0 / params.periods
    turns = max(0, round(params.mean_speed_motor_rad_s * period_s / turn_rad - step))
    while turn_rad * (turns + step) / period_s <= params.speed_amp_motor_rad_s:
        turns += 1
    return float(turn_rad * (turns + step) / period_s)


def speed_profile(params: ChirpParams, ctx: RigContext) -> list[tuple[str, np.ndarray]]:
    """Motor speed per cycle of each segment: speed up, then per pass sweep out, turn, sweep back (a turn
    between passes), slow down. Each sweep plays its own realization of the excitation (`excitation`)."""

    def times(duration_s: float) -> np.ndarray:
        return np.arange(ctx.cycles(duration_s)) / ctx.rate_hz

    limits, start_out = ctx.config.limits, ctx.theta_m0 * ctx.gear_ratio
    # Out towards the side with more room, so that the stroke used is the larger free one.
    ahead, behind = limits.travel_max_out_rad - start_out, start_out - limits.travel_min_out_rad
    mean = sweep_mean_speed(params, ctx) * (1.0 if ahead >= behind else -1.0)
    lead = times(params.period_s)
    ramp, turn = times(params.ramp_s), times(2 * params.ramp_s)
    fade_in = (1 - np.cos(np.pi * lead / params.period_s)) / 2  # over the lead-in, not analyzed
    # Sweeps end on whole periods, so the excitation fading out over a turn continues from wave[0].
    fade_turn = (1 + np.cos(np.pi * turn / (2 * params.ramp_s))) / 2
    fade_ramp = (1 + np.cos(np.pi * ramp / params.ramp_s)) / 2
    profile = [("accel", mean * (1 - fade_ramp))]
    labels = sweep_labels(params)
    for k, label in enumerate(labels):
        wave, _ = excitation(params, ctx, k)
        sweep = np.tile(wave, params.periods + 1)
        sweep[: len(lead)] *= fade_in
        sign = 1.0 if k % 2 == 0 else -1.0  # out, then back over the same stretch
        profile.append((label, sign * (mean + sweep)))
        if k + 1 < len(labels):
            turning = mean * (2 * fade_turn - 1) + np.resize(wave, turn.size) * fade_turn
            profile.append(("turn" if k == 0 else f"turn-{k + 1}", sign * turning))
        else:
            profile.append(("decel", sign * (mean + np.resize(wave, ramp.size)) * fade_ramp))
    return profile


def analyzed_rows(run: Run, label: str, params: ChirpParams, ctx: RigContext) -> slice:
    """Rows of a sweep's analyzed periods: after the lead-in, whole periods."""
    rows, cycles = segment_rows(run, label), ctx.cycles(params.period_s)
    return slice(rows.start + cycles, rows.start + cycles * (1 + params.periods))


TREND_DEGREE = 3
"""Degree of the polynomial trend taken out of each sweep before its periods are averaged: the slow
Coulomb level C(θ_m) is quadratic in the position, which rides on a ramp; one degree to spare."""
RING_MODES = 1
"""Decaying rings taken out of each sweep beside the trend (`periodic_records`)."""


def _off_periodic(v: np.ndarray, cycles: int, periods: int) -> np.ndarray:
    """Columns of `v` less their average over the periods (a component repeating every period: zero)."""
    w = v.reshape(periods, cycles, -1)
    return np.asarray((w - w.mean(axis=0)).reshape(cycles * periods, -1))


def _ring_basis(n: np.ndarray, decay: float, omega: float) -> np.ndarray:
    """exp(−decay·n)·cos, sin(omega·n) over samples n [1/sample, rad/sample]."""
    envelope = np.exp(-decay * n)
    return np.stack([envelope * np.cos(omega * n), envelope * np.sin(omega * n)], axis=1)


def ring_mode(
    residual: np.ndarray, trend: np.ndarray, cycles: int, periods: int
) -> tuple[float, float] | None:
    """(decay, frequency) of the strongest decaying ring in what the periodic part and the trend leave
    [1/sample, rad/sample], or None: its frequency first from the residual's zero-padded spectrum, then
    both refined by least squares (variable projection)."""
    rows = residual.size
    spectrum = np.abs(np.fft.rfft(residual, 8 * rows))
    spectrum[: 8 * periods] = 0.0  # below one line: the trend's
    omega0 = 2 * np.pi * int(np.argmax(spectrum)) / (8 * rows)
    n = np.arange(rows, dtype=float)

    def cost(x: np.ndarray) -> float:
        decay, omega = float(np.exp(x[0])), float(x[1])
        basis = _off_periodic(np.column_stack([trend, _ring_basis(n, decay, omega)]), cycles, periods)
        coef, *_ = np.linalg.lstsq(basis, residual, rcond=None)
        return float(np.sum((residual - basis @ coef) ** 2))

    found = optimize.minimize(cost, np.array([np.log(1.0 / rows), omega0]), method="Nelder-Mead")
    decay, omega = float(np.exp(found.x[0])), float(found.x[1])
    if not found.success or not 0 < omega < np.pi or decay * rows > 20:
        return None
    return decay, omega


def periodic_records(x: np.ndarray, cycles: int, periods: int) -> np.ndarray:
    """`x` over whole periods as a (periods × cycles) array, a polynomial trend in time and the ring of a
    lightly damped mode taken out.

    The trend (degree TREND_DEGREE, no constant) is fitted by least squares to what the periodic part
    leaves: both x and the trend's regressors have their average over periods taken out first, so a
    component repeating every period is never mistaken for trend. The ring (RING_MODES decaying
    sinusoids, `ring_mode`, each found in what the fit before it left) is fitted beside the trend the
    same way: a mode barely damped (the seed's load, J_l/b_l = 4 s, with the motor held by the loop)
    still rings from the speed-up and the lead-in through the analyzed periods, and that ring, on no
    line, leaks into every line of a period's DFT.
    """
    rows = cycles * periods
    t = np.linspace(-1.0, 1.0, rows)
    basis = np.stack([t**degree for degree in range(1, TREND_DEGREE + 1)], axis=1)
    target = _off_periodic(x[:, None], cycles, periods)[:, 0]
    n = np.arange(rows, dtype=float)
    for _ in range(RING_MODES):
        coef, *_ = np.linalg.lstsq(_off_periodic(basis, cycles, periods), target, rcond=None)
        mode = ring_mode(target - _off_periodic(basis, cycles, periods) @ coef, basis, cycles, periods)
        if mode is None:
            break
        basis = np.column_stack([basis, _ring_basis(n, *mode)])
    coef, *_ = np.linalg.lstsq(_off_periodic(basis, cycles, periods), target, rcond=None)
    return np.asarray((x - basis @ coef).reshape(periods, cycles))


def frf_tables(run: Run, params: ChirpParams, ctx: RigContext) -> dict[str, dict[str, np.ndarray]]:
    """The FRFs of FRFS at the excitation's lines.

    Columns: freq_hz; magnitude_db, phase_deg (H = Σ R̄·Y / Σ R̄·U over every analyzed period of both
    sweeps, each sweep's polynomial trend taken out first, see `periodic_records`); coherence (the weaker
    of γ²(r, u) and γ²(r, y) over those periods); magnitude_std_db, phase_std_deg (1σ of H from the
    spread of the sweeps' own estimates: their standard deviation over √(number of sweeps), linearized
    in dB and degrees: the confidence band from the data).
    """
    cycles = ctx.cycles(params.period_s)
    bins = excited_lines(params, ctx)
    lines_hz = bins / (cycles / ctx.rate_hz)
    sweeps = recorded_sweeps(run, params)
    spectra: dict[str, list[np.ndarray]] = {name: [] for name in ("reference", "current", "speed", "load")}
    for label in sweeps:
        rows = analyzed_rows(run, label, params, ctx)
        set_out = ctx.gear_ratio * run["setpoint"][rows.start - 1 : rows.stop]
        # The mean-speed ramp of the set-point, exact over whole periods (the excitation sums to zero).
        ramp = (set_out[-1] - set_out[0]) / (rows.stop - rows.start) * np.arange(1, set_out.size)
        x = {
            "reference": set_out[1:] - ramp,
            "current": run["i_cmd"][rows],
            "speed": run["omega_m"][rows],
            "load": run["theta_l"][rows] - ramp,
        }
        for name, values in x.items():
            records = periodic_records(np.asarray(values, dtype=float), cycles, params.periods)
            spectra[name].append(np.fft.rfft(records, axis=1)[:, bins])
    per_period = {name: np.concatenate(parts) for name, parts in spectra.items()}  # (records × lines)
    reference = per_period["reference"]

    def cross(a: str) -> np.ndarray:
        return np.asarray(np.sum(np.conj(reference) * per_period[a], axis=0))

    def coherence(a: str) -> np.ndarray:
        power = np.sum(np.abs(per_period[a]) ** 2, axis=0) * np.sum(np.abs(reference) ** 2, axis=0)
        return np.asarray(np.abs(cross(a)) ** 2 / power)

    tables = {}
    for name, (u, y, _, _) in FRFS.items():
        h = cross(y) / cross(u)
        # The band: the spread of the sweeps' own estimates. Each sweep plays its own realization, so
        # the nonlinear distortion, the same in every period of a sweep, differs between sweeps like noise.
        each = np.array([_sweep_frf(per_period, u, y, k, params.periods) for k in range(len(sweeps))])
        spread = np.sqrt(np.sum(np.abs(each - each.mean(axis=0)) ** 2, axis=0) / (len(each) - 1) / len(each))
        relative = spread / np.abs(h)
        tables[name] = {
            "freq_hz": lines_hz,
            "magnitude_db": 20 * np.log10(np.abs(h)),
            "phase_deg": np.degrees(np.unwrap(np.angle(h))),
            "coherence": np.minimum(coherence(u), coherence(y)),
            "magnitude_std_db": 20 / np.log(10) * relative,
            "phase_std_deg": np.degrees(relative),
        }
    return tables


def _sweep_frf(per_period: dict[str, np.ndarray], u: str, y: str, sweep: int, periods: int) -> np.ndarray:
    """One sweep's estimate Σ R̄·Y / Σ R̄·U over its periods (rows sweep·periods … of `per_period`)."""
    rows = slice(sweep * periods, (sweep + 1) * periods)
    reference = np.conj(per_period["reference"][rows])
    return np.asarray(
        np.sum(reference * per_period[y][rows], axis=0) / np.sum(reference * per_period[u][rows], axis=0)
    )


def resonance(table: dict[str, np.ndarray], coherence_min: float) -> tuple[float, float, float] | None:
    """(antiresonance, resonance, resolution) of a current → speed FRF, or None if not seen [Hz].

    Found on the lines: the integrator of the rigid body is taken out (|H|·f is flat at low frequency);
    the antiresonance is its deepest coherent dip, the resonance its highest coherent peak above the dip,
    if the peak stands 10 dB over the dip and is not the last coherent point (a peak must come back
    down). Then interpolated between the lines (`interpolated_modes`) when that fit holds; the
    resolution is then twice the larger jackknife σ of the two, else the line spacing.
    """
    coherent = table["coherence"] >= coherence_min
    freq = table["freq_hz"][coherent]
    level_db = table["magnitude_db"][coherent] + 20 * np.log10(freq)
    if freq.size < 3:
        return None
    dip = int(np.argmin(level_db))
    if dip == freq.size - 1:
        return None
    peak = dip + 1 + int(np.argmax(level_db[dip + 1 :]))
    if peak == freq.size - 1 or level_db[peak] - level_db[dip] < 10.0:
        return None
    on_lines = float(freq[dip]), float(freq[peak])
    between = interpolated_modes(table, coherent, on_lines)
    if between is None:
        return *on_lines, float(np.min(np.diff(table["freq_hz"])))
    anti, res, sigma_anti, sigma_res = between
    return anti, res, 2.0 * max(sigma_anti, sigma_res)


MODE_SPAN = 0.25
"""Lines from (1 − MODE_SPAN)·antiresonance to (1 + MODE_SPAN)·resonance enter the interpolation."""


def _levy_modes(freq: np.ndarray, g: np.ndarray) -> tuple[float, float] | None:
    """(f_a, f_r) of g ≈ c·(f_a² − f²)/(f_r² − f²) by Levy's linear least squares, or None [Hz]."""
    design = np.stack([g, -np.ones_like(g), freq**2], axis=1)
    (pole, zero_times_c, c), *_ = np.linalg.lstsq(design, g * freq**2, rcond=None)
    if c == 0:
        return None
    anti_sq, res_sq = (zero_times_c / c).real, pole.real
    if anti_sq <= 0 or res_sq <= 0:
        return None
    return math.sqrt(anti_sq), math.sqrt(res_sq)


def interpolated_modes(
    table: dict[str, np.ndarray], coherent: np.ndarray, on_lines: tuple[float, float]
) -> tuple[float, float, float, float] | None:
    """(antiresonance, resonance, their jackknife σ each) [Hz] between the lines, or None when the fit
    does not hold.

    Near its modes a current → speed FRF is H·f ≈ c·(f_a² − f²)/(f_r² − f²) (two-inertia, the integrator
    taken out; f_a², f_r² complex with the damping). Multiplied out this is linear in c, c·f_a² and f_r²
    (Levy's method), solved by complex least squares over the coherent lines around the modes; the
    frequencies are √Re f_a², √Re f_r². Kept only if the antiresonance stays below the resonance and both
    inside the lines fitted. Their σ is the jackknife's over the fitted lines (each left out in turn):
    how much the answer depends on the lines the grid happens to offer.
    """
    low, high = on_lines
    pick = (
        coherent & (table["freq_hz"] >= (1 - MODE_SPAN) * low) & (table["freq_hz"] <= (1 + MODE_SPAN) * high)
    )
    if np.count_nonzero(pick) < 5:
        return None
    freq = table["freq_hz"][pick]
    g = 10 ** (table["magnitude_db"][pick] / 20) * np.exp(1j * np.radians(table["phase_deg"][pick])) * freq
    found = _levy_modes(freq, g)
    if found is None or not freq[0] < found[0] < found[1] < freq[-1]:
        return None
    left_out = []
    for drop in range(freq.size):
        keep = np.arange(freq.size) != drop
        again = _levy_modes(freq[keep], g[keep])
        if again is None:
            return None
        left_out.append(again)
    spread = np.asarray(left_out)
    n = freq.size
    sigma = np.sqrt((n - 1) / n * np.sum((spread - spread.mean(axis=0)) ** 2, axis=0))
    return found[0], found[1], float(sigma[0]), float(sigma[1])


class Chirp(Experiment):
    name = "chirp"
    summary = "periodic sweep 0.5–20 Hz on a mean speed; plant and position FRFs with coherence (Bode)"
    Params = ChirpParams
    needs = frozenset({ControlMode.POSITION})

    def program(self, params: ChirpParams, ctx: RigContext) -> list[Segment]:
        nyquist_hz = ctx.rate_hz / 2
        if params.f_stop_hz > nyquist_hz / 2:
            raise UserInputError(
                f"run {self.name}: field 'f_stop_hz': above a quarter of the rig's {ctx.rate_hz:g} Hz rate"
            )
        profile = speed_profile(params, ctx)
        speeds = np.concatenate([speed for _, speed in profile])
        out_rad = ctx.gear_ratio * np.cumsum(speeds) / ctx.rate_hz  # the set-point's own rate is the speed
        low, high = min(0.0, float(out_rad.min())), max(0.0, float(out_rad.max()))
        check_stroke(ctx, low, high, self.name, "mean_speed_motor_rad_s")
        ends = np.cumsum([len(speed) for _, speed in profile])
        return [
            output_segment(ctx, part, label)
            for (label, _), part in zip(profile, np.split(out_rad, ends[:-1]), strict=True)
        ]

    def analyze(self, run: Run, params: ChirpParams, ctx: RigContext) -> Results:
        tables = frf_tables(run, params, ctx)
        low, high = COHERENCE_BAND_HZ
        metrics: dict[str, float | int | str] = {}
        for name, table in tables.items():
            in_band = (table["freq_hz"] >= low) & (table["freq_hz"] <= high)
            metrics[f"coherence_1_10hz_{name.removeprefix('frf_')}"] = float(
                np.mean(table["coherence"][in_band])
            )
        metrics["line_spacing_hz"] = float(ctx.rate_hz / ctx.cycles(params.period_s))
        metrics["sweep_mean_speed_rad_s"] = sweep_mean_speed(params, ctx)
        notes = []
        found = resonance(tables["frf_speed"], params.coherence_min)
        if found is None:
            notes.append("no resonance seen in i_cmd → ω_m among the coherent points")
        else:
            metrics["antiresonance_hz"], metrics["resonance_hz"], metrics["resonance_resolution_hz"] = found
        closed = tables["frf_closed_loop"]
        coherent = closed["coherence"] >= params.coherence_min
        if np.any(coherent):
            peak = int(np.argmax(np.where(coherent, closed["magnitude_db"], -np.inf)))
            metrics["closed_loop_peak_hz"] = float(closed["freq_hz"][peak])
            metrics["closed_loop_peak_db"] = float(closed["magnitude_db"][peak])
        below = np.flatnonzero((closed["magnitude_db"] < -3.0) & coherent)
        if below.size:
            metrics["closed_loop_bandwidth_hz"] = float(closed["freq_hz"][below[0]])
        else:
            notes.append("closed loop stays above −3 dB over the coherent sweep")
        return Results(metrics, tables, notes)

    def plot(
        self, run: Run, results: Results, params: ChirpParams, ctx: RigContext, out_dir: Path
    ) -> list[Path]:
        fig, _ = new_figure("Frequency response (periodic sweep on a mean speed, closed loop)", 3)
        mag_ax, phase_ax, coh_ax = fig.axes
        for colour, (name, (_, _, what, unit)) in zip(("C0", "C1", "C2"), FRFS.items(), strict=True):
            table = results.tables[name]
            freq = table["freq_hz"]
            mag_ax.semilogx(freq, table["magnitude_db"], colour, label=f"{what} [dB {unit}] ±2σ")
            low_db, high_db = (table["magnitude_db"] + k * table["magnitude_std_db"] for k in (-2, 2))
            mag_ax.fill_between(freq, low_db, high_db, color=colour, alpha=0.2)
            phase_ax.semilogx(freq, table["phase_deg"], colour)
            coh_ax.semilogx(freq, table["coherence"], colour)
        for frequency in (results.metrics.get("antiresonance_hz"), results.metrics.get("resonance_hz")):
            if isinstance(frequency, float):
                for each in fig.axes:
                    each.axvline(frequency, color="0.5", ls=":", lw=0.8)
        mag_ax.set_ylabel("magnitude [dB]")
        mag_ax.legend(fontsize=8)
        phase_ax.set_ylabel("phase [°]")
        coh_ax.axhline(params.coherence_min, color="0.5", ls="--", lw=0.8)
        coh_ax.set_ylim(0, 1.05)
        coh_ax.set_ylabel("coherence γ² [–]")
        coh_ax.set_xlabel("frequency [Hz]")
        return [save_figure(fig, out_dir / "bode.png")]
