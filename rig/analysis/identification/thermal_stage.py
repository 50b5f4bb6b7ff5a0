"""Thermal identification (issue 27 item 4): the two-node network and the friction's temperature law from
`warm-up` runs (warm-up and cool-down), each estimate with its σ.

The network (docs/MODEL.md, section `thermal`):

    C_w·dT_w/dt = Q_w − (T_w − T_g)/R_wg − (T_w − T_amb)/R_wa
    C_g·dT_g/dt = Q_g + (T_w − T_g)/R_wg − (T_g − T_amb)/R_ga

Its inputs are measured, not modelled: the copper loss Q_w = R·i_a² (R the motor's resistance, from the
model being fitted) and the friction power Q_g = K_m·i_a·ω_m − dE_kin/dt (the shaft power that is neither
stored as the rotors' kinetic energy nor, the warm-up carrying no load, given to a load; the spring's
energy is neglected: it returns to zero at every rest). With both temperatures measured and both inputs
known, all five of C_w, C_g, R_wg, R_wa, R_ga are determined, and T_amb with them: the cool-down (no
input) fixes the network's two time constants, the warm-up's known powers fix the capacities that scale
them. A run with only `temp_gear` cannot separate the winding's node: refused in one line.

The fit is output-error: the network and the probes' first-order lag (the rig file's
`sensors.temperature_lag_s`) are simulated on 1 s bins (exact discretization, inputs held over each bin)
from each run's own initial temperatures and ambient, and the five parameters (as logarithms: positive)
fitted by least squares to both probes' bin means; starting values from an equation-error regression on
the lag-corrected temperatures. σ: the Gauss-Newton covariance scaled by the residuals' variance and
widened by n/n_eff for their correlation from bin to bin (a misfit that follows itself informs less than
independent noise would).

The friction law: at each warm-up checkpoint the running torque at each speed and the gear's measured
temperature; ln torque = ln F_ref(speed) − beta_T·(T_g − T_ref), one beta_T and one F_ref per speed,
weighted least squares on the checkpoints' standard errors, its covariance scaled by the residuals.
T_ref is a convention (the model file's, default 25 °C), not an estimate. The running torque includes
the output side's friction seen through the ratio, which the law does not scale: the model's own load
friction (r·(f_cl + b_l·r·ω)) is taken off before the law is fitted, else it biases beta_T low by about
its share (docs/BENCHMARKS.md, "Thermal identification").
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import expm
from scipy.optimize import least_squares

from model.errors import UserInputError
from model.params import HarmonicDriveModel, Thermal
from model.run import Run
from rig.experiments.base import context_from_run
from rig.experiments.warm_up import WarmUpParams, warm_up_checkpoints

BIN_S = 1.0
"""Bin of the network fit [s]: the thermal time constants are tens of seconds or more."""
NETWORK = ("C_w", "C_g", "R_wg", "R_wa", "R_ga")
START_SPAN = 7.0
T_REF_DEFAULT_C = 25.0


@dataclass
class Estimate:
    value: float
    sigma: float


@dataclass
class ThermalFit:
    """The network's parameters, its time constants (slow, fast) [s] and each run's ambient [°C]."""

    parameters: dict[str, Estimate]
    time_constants_s: tuple[Estimate, Estimate]
    ambient_c: list[float]
    rms_residual_c: float
    notes: list[str] = field(default_factory=list)


@dataclass
class FrictionLaw:
    """friction(T_g) = F_ref·exp(−beta_T·(T_g − T_ref)), one F_ref per checkpoint speed."""

    beta_per_k: Estimate
    t_ref_c: float
    reference_nm: dict[float, Estimate]
    temperature_span_c: tuple[float, float]


@dataclass
class _Bins:
    q_w: np.ndarray  # copper loss per bin [W]
    q_g: np.ndarray  # friction power per bin [W]
    temp_w: np.ndarray  # probe means per bin [°C]
    temp_g: np.ndarray
    lag_s: float


def _bins(run: Run, resistance_ohm: float, inertia: tuple[float, float], where: str) -> _Bins:
    missing = [c for c in ("temp_gear", "temp_motor", "i_a", "omega_m") if c not in run]
    if missing:
        raise UserInputError(
            f"{where}: thermal fit needs the columns temp_gear, temp_motor, i_a and omega_m; missing"
            f" {', '.join(missing)} (with only the gear's probe the winding's node is not determined)"
        )
    ctx = context_from_run(run, where)
    rows = max(1, round(BIN_S * ctx.rate_hz))
    n = len(run) // rows * rows
    if n < 10 * rows:
        raise UserInputError(f"{where}: thermal fit needs at least {10 * BIN_S:g} s of samples")
    i_a, omega_m = run["i_a"][:n], run["omega_m"][:n]
    shaft = ctx.torque_constant_nm_per_a * i_a * omega_m
    j_m, j_l = inertia
    omega_l = run["omega_l"][:n] if "omega_l" in run else ctx.gear_ratio * omega_m
    kinetic = 0.5 * j_m * omega_m**2 + 0.5 * j_l * omega_l**2
    # The kinetic energy's change over each bin, as a mean power: what the shaft stored, not dissipated.
    edges = kinetic[::rows]
    ends = np.append(edges[1:], kinetic[n - 1])
    stored = (ends - edges) / BIN_S
    return _Bins(
        q_w=resistance_ohm * (i_a**2).reshape(-1, rows).mean(axis=1),
        q_g=np.maximum(shaft.reshape(-1, rows).mean(axis=1) - stored, 0.0),
        temp_w=run["temp_motor"][:n].reshape(-1, rows).mean(axis=1),
        temp_g=run["temp_gear"][:n].reshape(-1, rows).mean(axis=1),
        lag_s=float(ctx.config.sensors.temperature_lag_s),
    )


def _matrices(log_params: np.ndarray, lag_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Continuous A (4×4: winding, gear, their probes) and B (4×3: Q_w, Q_g, T_amb)."""
    c_w, c_g, r_wg, r_wa, r_ga = np.exp(log_params)
    g_wg, g_wa, g_ga = 1.0 / r_wg, 1.0 / r_wa, 1.0 / r_ga
    a = np.zeros((4, 4))
    a[0, :2] = [-(g_wg + g_wa) / c_w, g_wg / c_w]
    a[1, :2] = [g_wg / c_g, -(g_wg + g_ga) / c_g]
    b = np.zeros((4, 3))
    b[0] = [1.0 / c_w, 0.0, g_wa / c_w]
    b[1] = [0.0, 1.0 / c_g, g_ga / c_g]
    if lag_s > 0:
        a[2, 0], a[2, 2] = 1.0 / lag_s, -1.0 / lag_s
        a[3, 1], a[3, 3] = 1.0 / lag_s, -1.0 / lag_s
    return a, b


def _simulate(log_params: np.ndarray, bins: _Bins, ambient: float, start: tuple[float, float]) -> np.ndarray:
    """The probes' bin means predicted by the network: (bins, 2) [°C]."""
    a, b = _matrices(log_params, bins.lag_s)
    if bins.lag_s <= 0:
        a[2, :2], a[3, :2] = [1.0, 0.0], [0.0, 1.0]  # probes read the nodes: kept equal below
    big = np.zeros((7, 7))
    big[:4, :4], big[:4, 4:] = a, b
    step = expm(big * BIN_S)
    phi, gamma = step[:4, :4], step[:4, 4:]
    x = np.array([start[0], start[1], start[0], start[1]])
    out = np.empty((bins.q_w.shape[0], 2))
    for k in range(bins.q_w.shape[0]):
        nxt = phi @ x + gamma @ np.array([bins.q_w[k], bins.q_g[k], ambient])
        if bins.lag_s <= 0:
            nxt[2:] = nxt[:2]
        out[k] = 0.5 * (x[2:] + nxt[2:])  # the bin's mean, by the trapezoid
        x = nxt
    return out


def _equation_error_start(bins_list: list[_Bins]) -> np.ndarray:
    """Starting logarithms from the network's equations integrated over each run, on the lag-corrected
    temperatures: T(t) − T(0) = a·∫T_w + b·∫T_g + ∫Q/C + c·t, linear in a, b, 1/C, c. Integrals, not
    derivatives: the probes' noise enters once, not differenced (at the real scale, minutes of time
    constants, differenced noise swamps the slopes)."""
    rows_w, rows_g, dw, dg = [], [], [], []
    for bins in bins_list:
        temps = []
        for probe in (bins.temp_w, bins.temp_g):
            rate = np.gradient(probe, BIN_S)
            temps.append(probe + bins.lag_s * rate)  # a first-order probe: T = m + lag·dm/dt
        t_w, t_g = temps
        time_s = BIN_S * np.arange(t_w.shape[0])
        i_w, i_g = np.cumsum(t_w) * BIN_S, np.cumsum(t_g) * BIN_S
        rows_w.append(np.column_stack([i_w, i_g, np.cumsum(bins.q_w) * BIN_S, time_s]))
        rows_g.append(np.column_stack([i_w, i_g, np.cumsum(bins.q_g) * BIN_S, time_s]))
        dw.append(t_w - t_w[0])
        dg.append(t_g - t_g[0])
    cw = np.linalg.lstsq(np.vstack(rows_w), np.concatenate(dw), rcond=None)[0]
    cg = np.linalg.lstsq(np.vstack(rows_g), np.concatenate(dg), rcond=None)[0]
    c_w = 1.0 / max(cw[2], 1e-6)
    c_g = 1.0 / max(cg[2], 1e-6)
    g_wg = max(0.5 * (cw[1] * c_w + cg[0] * c_g), 1e-3)
    g_wa = max(-cw[0] * c_w - g_wg, 1e-3)
    g_ga = max(-cg[1] * c_g - g_wg, 1e-3)
    return np.log([c_w, c_g, 1.0 / g_wg, 1.0 / g_wa, 1.0 / g_ga])


def _correlation_widening(residual: np.ndarray, lengths: list[int]) -> float:
    """n/n_eff of the residuals, from their lag-1 autocorrelation within each series (at least 1)."""
    pairs, energy, start = 0.0, 0.0, 0
    for length in lengths:
        for half in (slice(start, start + length // 2), slice(start + length // 2, start + length)):
            r = residual[half] - np.mean(residual[half])
            pairs += float(r[1:] @ r[:-1])
            energy += float(r @ r)
        start += length
    rho = min(max(pairs / energy, 0.0), 0.999) if energy > 0 else 0.0
    return (1.0 + rho) / (1.0 - rho)


def _time_constants(log_params: np.ndarray) -> np.ndarray:
    a, _ = _matrices(log_params, 0.0)
    rates = np.sort(-np.linalg.eigvals(a[:2, :2]).real)
    return 1.0 / rates  # slow first


def fit_network(runs: list[Run], resistance_ohm: float, inertia: tuple[float, float]) -> ThermalFit:
    """The network from warm-up runs (their whole records), shared by the runs; each run its own ambient
    and initial temperatures."""
    if not runs:
        raise UserInputError("thermal fit: needs at least one warm-up run")
    bins_list = [_bins(run, resistance_ohm, inertia, f"run {i + 1}") for i, run in enumerate(runs)]
    start = _equation_error_start(bins_list)
    x0 = [*start]
    for bins in bins_list:
        x0 += [float(bins.temp_g[0]), float(bins.temp_w[0]), float(bins.temp_g[0])]

    def residual(x: np.ndarray) -> np.ndarray:
        out = []
        for i, bins in enumerate(bins_list):
            ambient, t_w0, t_g0 = x[5 + 3 * i : 8 + 3 * i]
            predicted = _simulate(x[:5], bins, ambient, (t_w0, t_g0))
            out += [bins.temp_w - predicted[:, 0], bins.temp_g - predicted[:, 1]]
        return np.concatenate(out)

    # Bounded: each logarithm within START_SPAN of its start (e^7 ≈ 1100×), so a parameter the data do not
    # determine ends on a bound (said in the notes) instead of running off to infinity.
    lower = np.concatenate([start - START_SPAN, np.full(len(x0) - 5, -np.inf)])
    upper = np.concatenate([start + START_SPAN, np.full(len(x0) - 5, np.inf)])
    solution = least_squares(residual, np.asarray(x0), bounds=(lower, upper), x_scale="jac")
    jac, res = solution.jac, solution.fun
    dof = max(1, res.shape[0] - solution.x.shape[0])
    s2 = float(res @ res) / dof
    # Residuals that follow each other from bin to bin (a misfit, not the probes' white noise) carry less
    # information than their count: the covariance is widened by n/n_eff, n_eff = n·(1 − ρ)/(1 + ρ) with
    # ρ their lag-1 autocorrelation (within each probe's series).
    widen = _correlation_widening(res, [2 * b.q_w.shape[0] for b in bins_list])
    cov = s2 * widen * np.linalg.pinv(jac.T @ jac)
    values = np.exp(solution.x[:5])
    parameters = {
        name: Estimate(float(values[i]), float(values[i] * math.sqrt(max(cov[i, i], 0.0))))
        for i, name in enumerate(NETWORK)
    }
    taus = _time_constants(solution.x[:5])
    grads = np.empty((2, 5))
    for j in range(5):  # the time constants' σ by the delta method, central differences in log space
        dx = np.zeros(5)
        dx[j] = 1e-5
        grads[:, j] = (_time_constants(solution.x[:5] + dx) - _time_constants(solution.x[:5] - dx)) / 2e-5
    tau_cov = grads @ cov[:5, :5] @ grads.T
    time_constants = (
        Estimate(float(taus[0]), math.sqrt(max(tau_cov[0, 0], 0.0))),
        Estimate(float(taus[1]), math.sqrt(max(tau_cov[1, 1], 0.0))),
    )
    ambient = [float(solution.x[5 + 3 * i]) for i in range(len(runs))]
    notes = [
        "thermal network: σ from the Gauss-Newton covariance, widened ×"
        f"{math.sqrt(widen):.3g} for the residuals' correlation from bin to bin (RMS {math.sqrt(s2):.3g} °C)"
    ]
    for i, name in enumerate(NETWORK):
        on_bound = min(solution.x[i] - lower[i], upper[i] - solution.x[i]) < 1e-3
        if on_bound or parameters[name].sigma > values[i]:
            notes.append(f"thermal network: {name} is not determined by these runs (σ ≥ value or on a bound)")
    return ThermalFit(parameters, time_constants, ambient, math.sqrt(s2), notes)


def output_share_nm(model: HarmonicDriveModel, speed_rad_s: float) -> float:
    """The output side's friction at a motor speed, seen at the motor (r·(f_cl + b_l·r·ω)) [N·m]: the
    part of the running torque the grease's law does not scale (docs/MODEL.md)."""
    load = model.load_friction
    if load is None:
        return 0.0
    r = model.mechanics.r
    return r * ((load.f_cl or 0.0) + load.b_l * r * speed_rad_s)


def fit_friction_law(
    tables: list[dict[str, np.ndarray]],
    speeds_rad_s: list[float],
    t_ref_c: float = T_REF_DEFAULT_C,
    unscaled_nm: dict[float, float] | None = None,
) -> FrictionLaw:
    """beta_T and the running torque at T_ref per speed from warm-up checkpoint tables
    (`warm_up_checkpoints`). `unscaled_nm`: per speed, the share of the running torque that does not
    follow the temperature (`output_share_nm`): taken off before the law is fitted and added back to
    the reference torque, so that neither is biased by it."""
    unscaled = unscaled_nm or {}
    xs, ys, ws = [], [], []
    for table in tables:
        for j, speed in enumerate(speeds_rad_s):
            torque = table[f"torque_{speed:g}_nm"] - unscaled.get(speed, 0.0)
            sigma = table[f"torque_{speed:g}_sigma_nm"]
            for temp, level, err in zip(table["temp_gear_c"], torque, sigma, strict=True):
                row = np.zeros(len(speeds_rad_s) + 1)
                row[j] = 1.0
                row[-1] = -(temp - t_ref_c)
                xs.append(row)
                ys.append(math.log(level))
                ws.append((level / err) ** 2)  # σ of ln τ is σ_τ/τ
    x, y, w = np.asarray(xs), np.asarray(ys), np.asarray(ws)
    temps = -x[:, -1] + t_ref_c
    if np.ptp(temps) < 1.0:
        raise UserInputError(
            f"thermal fit: the checkpoints span {np.ptp(temps):.2g} K of gear temperature; the friction's"
            " temperature law needs a warm-up that warms the gear by a few kelvin at least"
        )
    sw = np.sqrt(w)
    coef, *_ = np.linalg.lstsq(x * sw[:, None], y * sw, rcond=None)
    residual = (y - x @ coef) * sw
    dof = max(1, y.shape[0] - coef.shape[0])
    cov = max(1.0, float(residual @ residual) / dof) * np.linalg.inv((x * w[:, None]).T @ x)
    reference = {
        speed: Estimate(
            float(math.exp(coef[j]) + unscaled.get(speed, 0.0)),
            float(math.exp(coef[j]) * math.sqrt(cov[j, j])),
        )
        for j, speed in enumerate(speeds_rad_s)
    }
    beta = Estimate(float(coef[-1]), math.sqrt(float(cov[-1, -1])))
    return FrictionLaw(beta, t_ref_c, reference, (float(np.min(temps)), float(np.max(temps))))


@dataclass
class ThermalIdentification:
    section: Thermal
    network: ThermalFit
    law: FrictionLaw


def identify_thermal(runs: list[Run], model: HarmonicDriveModel) -> ThermalIdentification:
    """The `thermal` section from warm-up runs: the network (with the model's R, J_m, J_l) and the law at
    the model's T_ref (25 °C if it has no thermal section)."""
    tables, speeds = [], None
    for i, run in enumerate(runs):
        if run.meta.get("experiment") != "warm-up":
            raise UserInputError(f"thermal fit: run {i + 1} is not a warm-up run")
        params = WarmUpParams.model_validate(run.meta.get("params", {}), strict=False)
        if speeds is not None and params.speeds_rad_s != speeds:
            raise UserInputError("thermal fit: the warm-up runs' checkpoint speeds differ")
        speeds = params.speeds_rad_s
        tables.append(warm_up_checkpoints(run, context_from_run(run), params))
    assert speeds is not None
    t_ref = model.thermal.T_ref if model.thermal is not None else T_REF_DEFAULT_C
    network = fit_network(runs, model.motor.R, (model.mechanics.J_m, model.mechanics.J_l))
    law = fit_friction_law(tables, speeds, t_ref, {v: output_share_nm(model, v) for v in speeds})
    p = network.parameters
    section = Thermal(
        T_amb=float(np.mean(network.ambient_c)),
        T_ref=t_ref,
        beta_T=law.beta_per_k.value,
        C_w=p["C_w"].value,
        C_g=p["C_g"].value,
        R_wg=p["R_wg"].value,
        R_wa=p["R_wa"].value,
        R_ga=p["R_ga"].value,
    )
    return ThermalIdentification(section, network, law)
