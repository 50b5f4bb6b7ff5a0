"""`torsional-stiffness`: the catalog's torsion test. The input is held in position mode while the load
drive ramps the output torque 0 → +T_R → 0 → −T_R → 0 (`cycles` times; the first conditions the gear),
and the twist at the output, r·θ_m − θ_l, is measured against the output transducer's torque.

The last cycle gives two branches: loading (from −T_R up to +T_R) and unloading (from +T_R down to −T_R).
Each is the gear's spring curve shifted in torque by its branch's friction and hysteresis, so both are
fitted at once with the catalog's piecewise-linear law (slopes K1 up to T1, K2 up to T2, K3 above, symmetric
in sign) and a torque offset per branch; the stretch just after each reversal, where the loop is still
turning over, is left out (`reversal_margin`). Hysteresis loss: the twist between the branches at zero
torque. Lost motion: the twist between the loop's midpoints at ±`lost_motion_fraction`·T_R.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pydantic import Field, model_validator
from scipy.optimize import least_squares

from model.run import Run
from rig.experiments.base import (
    LOAD_MAX_NM,
    Experiment,
    ExperimentParams,
    Results,
    RigContext,
    segment_rows,
)
from rig.experiments.load_side import line_at, require_bench, require_columns
from rig.experiments.plots import new_figure, save_figure
from rig.interface import ControlMode, Segment

NAME = "torsional-stiffness"


class TorsionalStiffnessParams(ExperimentParams):
    # Defaults: the size-25, 100:1 gear of the catalog-cha-25a-100 preset (its breakpoints from the
    # catalog's table; rated torque chosen at the size-25 component sets' 67 N·m class). Set your gear's.
    rated_torque_nm: float = Field(
        default=67.0, gt=0, le=LOAD_MAX_NM, description="T_R, the peak of the ramps [N·m]"
    )
    T1_nm: float = Field(default=14.0, gt=0, description="the catalog's first breakpoint torque [N·m]")
    T2_nm: float = Field(default=48.0, gt=0, description="the catalog's second breakpoint torque [N·m]")
    ramp_s: float = Field(default=3.0, gt=0, le=600, description="time of each quarter ramp (0 → T_R) [s]")
    cycles: int = Field(default=2, ge=2, le=10, description="full cycles played; the last is analyzed [–]")
    settle_s: float = Field(default=0.5, gt=0, le=60, description="hold unloaded before the ramps [s]")
    lost_motion_fraction: float = Field(
        default=0.03, gt=0, lt=0.5, description="lost motion is read at ± this share of T_R [–]"
    )
    reversal_margin: float = Field(
        default=0.3, ge=0, lt=1, description="share of T_R after each reversal left out of the fit [–]"
    )

    @model_validator(mode="after")
    def _ordered(self) -> TorsionalStiffnessParams:
        if not self.T1_nm < self.T2_nm < self.rated_torque_nm:
            raise ValueError("needs T1_nm < T2_nm < rated_torque_nm (K3 is measured above T2)")
        return self


def torsion_profile(params: TorsionalStiffnessParams, cycles_per_quarter: int) -> np.ndarray:
    """One cycle of output torque: 0 → +T_R → 0 → −T_R → 0 in four equal linear ramps [N·m]."""
    up = np.linspace(0.0, 1.0, cycles_per_quarter, endpoint=False)
    unit = np.concatenate([up, 1.0 - up, -up, up - 1.0])
    return params.rated_torque_nm * unit


def compliance_twist(torque: np.ndarray, k: np.ndarray, t1: float, t2: float) -> np.ndarray:
    """The catalog's twist for a spring torque: |T|/K1 to T1, then 1/K2 to T2, then 1/K3; odd in T [rad]."""
    mag = np.abs(torque)
    twist = (
        np.minimum(mag, t1) / k[0] + np.clip(mag - t1, 0.0, t2 - t1) / k[1] + np.maximum(mag - t2, 0.0) / k[2]
    )
    return np.sign(torque) * twist


def fit_branches(
    up: tuple[np.ndarray, np.ndarray], down: tuple[np.ndarray, np.ndarray], t1: float, t2: float, k0: float
) -> tuple[np.ndarray, np.ndarray, float, float, float]:
    """Fit both branches (torque, twist): twist = δ0 + D(torque − c_branch). Returns K (3), their 1 σ,
    δ0, c_up, c_down."""
    (tu, du), (td, dd) = up, down
    scale = float(np.std(np.concatenate([du, dd]))) or 1.0

    def residual(x: np.ndarray) -> np.ndarray:
        k = k0 * np.exp(x[:3])
        ru = x[3] + compliance_twist(tu - x[4], k, t1, t2) - du
        rd = x[3] + compliance_twist(td - x[5], k, t1, t2) - dd
        return np.concatenate([ru, rd]) / scale

    start = np.array([0.0, 0.0, 0.0, float(np.mean(np.concatenate([du, dd]))), 0.0, 0.0])
    fit = least_squares(residual, start, x_scale=np.array([1, 1, 1, scale, 1, 1]))
    k = k0 * np.exp(fit.x[:3])
    dof = max(1, fit.fun.size - fit.x.size)
    sigma2 = float(fit.fun @ fit.fun) / dof
    try:
        cov = np.linalg.inv(fit.jac.T @ fit.jac) * sigma2
        k_sigma = k * np.sqrt(np.diag(cov)[:3])
    except np.linalg.LinAlgError:
        k_sigma = np.full(3, np.nan)
    return k, k_sigma, float(fit.x[3]), float(fit.x[4]), float(fit.x[5])


class TorsionalStiffness(Experiment):
    name = NAME
    summary = (
        "input held, output torque cycled ±T_R by the load drive: K1, K2, K3, hysteresis loss, lost motion"
    )
    Params = TorsionalStiffnessParams
    needs = frozenset({ControlMode.POSITION})

    def program(self, params: TorsionalStiffnessParams, ctx: RigContext) -> list[Segment]:
        require_bench(NAME, ctx.config, load_drive=True, transducers=True)
        quarter = ctx.cycles(params.ramp_s)
        profile = torsion_profile(params, quarter)
        hold = np.full(profile.shape[0], ctx.theta_m0)
        settle = ctx.cycles(params.settle_s)
        program = [Segment(ControlMode.POSITION, np.full(settle, ctx.theta_m0), 0.0, "settle")]
        for c in range(params.cycles):
            program.append(Segment(ControlMode.POSITION, hold, profile, f"cycle{c + 1}"))
        program.append(Segment(ControlMode.POSITION, np.full(settle, ctx.theta_m0), 0.0, "unloaded"))
        return program

    def branches(self, run: Run, params: TorsionalStiffnessParams, ctx: RigContext) -> dict[str, np.ndarray]:
        """The last cycle's loading and unloading branches: torque [N·m] and twist [rad] per sample."""
        require_columns(NAME, run, ("tau_out",))
        last = segment_rows(run, f"cycle{params.cycles}")
        before = segment_rows(run, f"cycle{params.cycles - 1}")
        n = last.stop - last.start
        q = n // 4
        twist = ctx.gear_ratio * run["theta_m"] - run["theta_l"]
        torque = run["tau_out"]
        up = np.r_[before.start + 3 * q : before.stop, last.start : last.start + q]
        down = np.r_[last.start + q : last.start + 3 * q]
        return {
            "up_torque": torque[up],
            "up_twist": twist[up],
            "down_torque": torque[down],
            "down_twist": twist[down],
        }

    def analyze(self, run: Run, params: TorsionalStiffnessParams, ctx: RigContext) -> Results:
        b = self.branches(run, params, ctx)
        margin = params.reversal_margin * params.rated_torque_nm
        tr = params.rated_torque_nm
        keep_up = b["up_torque"] > -tr + margin
        keep_down = b["down_torque"] < tr - margin
        up = (b["up_torque"][keep_up], b["up_twist"][keep_up])
        down = (b["down_torque"][keep_down], b["down_twist"][keep_down])
        # Starting slope: the secant of the whole loop (its tips), a value of the right order for any gear.
        span = float(np.ptp(np.concatenate([b["up_twist"], b["down_twist"]]))) or 1e-9
        k, k_sigma, _, c_up, c_down = fit_branches(up, down, params.T1_nm, params.T2_nm, 2 * tr / span)
        half = max(
            0.02 * tr, 0.5
        )  # torque half-width of the local line fits: a few transducer σ over many samples
        at_zero_up = line_at(b["up_torque"], b["up_twist"], 0.0, half)
        at_zero_down = line_at(b["down_torque"], b["down_twist"], 0.0, half)
        t_l = params.lost_motion_fraction * tr
        mid = [
            0.5
            * (
                line_at(b["up_torque"], b["up_twist"], t, half)
                + line_at(b["down_torque"], b["down_twist"], t, half)
            )
            for t in (t_l, -t_l)
        ]
        metrics: dict[str, float | int | str] = {
            "K1_nm_per_rad": float(k[0]),
            "K2_nm_per_rad": float(k[1]),
            "K3_nm_per_rad": float(k[2]),
            "K1_sigma_nm_per_rad": float(k_sigma[0]),
            "K2_sigma_nm_per_rad": float(k_sigma[1]),
            "K3_sigma_nm_per_rad": float(k_sigma[2]),
            "hysteresis_loss_rad": float(at_zero_down - at_zero_up),
            "lost_motion_rad": float(mid[0] - mid[1]),
            "lost_motion_torque_nm": float(t_l),
            "branch_offset_up_nm": c_up,
            "branch_offset_down_nm": c_down,
        }
        notes = [
            f"K1 {k[0]:.4g}, K2 {k[1]:.4g}, K3 {k[2]:.4g} N·m/rad over T1 {params.T1_nm:g},"
            f" T2 {params.T2_nm:g} N·m; hysteresis loss {metrics['hysteresis_loss_rad']:.3g} rad,"
            f" lost motion {metrics['lost_motion_rad']:.3g} rad at ±{t_l:.3g} N·m"
        ]
        tables = {
            "loop": {
                "torque_nm": np.r_[b["up_torque"], b["down_torque"]],
                "twist_rad": np.r_[b["up_twist"], b["down_twist"]],
            }
        }
        return Results(metrics=metrics, tables=tables, notes=notes)

    def plot(
        self, run: Run, results: Results, params: TorsionalStiffnessParams, ctx: RigContext, out_dir: Path
    ) -> list[Path]:
        b = self.branches(run, params, ctx)
        fig, ax = new_figure("torsional stiffness: the hysteresis loop (input held)")
        ax.plot(b["up_twist"] * 1e3, b["up_torque"], ".", ms=1, label="loading")
        ax.plot(b["down_twist"] * 1e3, b["down_torque"], ".", ms=1, label="unloading")
        ax.set_xlabel("twist at the output r·θ_m − θ_l [mrad]")
        ax.set_ylabel("output torque τ_out [N·m]")
        ax.legend()
        return [save_figure(fig, out_dir / "torsional_stiffness.png")]
