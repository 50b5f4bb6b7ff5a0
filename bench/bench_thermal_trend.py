"""Warm-up, thermal fit and a 10 h endurance that tells wear from warm-up (issue 27 items 3, 4, 6; `make
bench`-style: prints figures beside targets, asserts nothing).

1. `warm-up` on the simulated bench with the `seed-thermal` preset at its real scale (gear ~20 min time
   constant; 1 h of duty bound, 30 min of cool-down), then the thermal fit (`thermal_stage.identify_thermal`):
   each network parameter, the two time constants and beta_T against the plant's (target 10 %), the
   running torque at T_ref against the same checkpoint on the plant held at T_ref (target 5 %).
2. A 10 h endurance on `seed-thermal` plus `wear_drift` (k_wear of seed-wear, 2.8e-7 1/rad), its duty
   harder than the default (period 3 s: ~10 W of friction, the gear ~15 K above ambient) and paused
   30 min after every hour so the gear cools; a checkpoint every 15 min. The wear drift is fitted from
   the checkpoints' F_c against travel, F_c = u + F_0·(1 + k_wear·s) (u the output side's share, neither
   warmed nor worn, from the plant's load friction), from the raw and from the normalized trend (the law
   of step 1), each with its σ: the normalized one should hold k_wear within its σ, the raw one not.

The pauses are the bench's own subclass of the endurance experiment (rest segments, the motor held in
position, between a duty block and its checkpoint), registered under the same name for the run, so the
stored run analyzes as any endurance run does.
"""

from __future__ import annotations

import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from model.params import HarmonicDriveModel, WearDrift, load_model  # noqa: E402
from rig import experiments  # noqa: E402
from rig.analysis.identification.thermal_stage import identify_thermal, output_share_nm  # noqa: E402
from rig.config import load_rig_config  # noqa: E402
from rig.core.trend import trend_document  # noqa: E402
from rig.experiments.base import RigContext, context_from_run  # noqa: E402
from rig.experiments.endurance import CHECKPOINT_PREFIX, Endurance, EnduranceParams  # noqa: E402
from rig.experiments.warm_up import WarmUpParams, warm_up_checkpoints  # noqa: E402
from rig.interface import ControlMode, Segment  # noqa: E402
from rig.runner import run_experiment  # noqa: E402
from rig.store.runs import RunStore  # noqa: E402
from sim_backend.inprocess import SimRig  # noqa: E402

K_WEAR = 2.8e-7  # seed-wear's: +30 % after 10 h of the default duty
PAUSE_EVERY = 4  # duty blocks (of 15 min) between two pauses
PAUSE_MIN = 30.0
WARM_UP = {"warm_s": 3600.0, "cool_s": 1800.0, "checkpoint_every_s": 300.0, "settle_window_s": 600.0}
ENDURANCE = {"duration_h": 10.0, "checkpoint_every_min": 15.0, "duty_period_s": 3.0}


class PausedEndurance(Endurance):
    """Endurance with a rest (motor held at θ_m0) before every PAUSE_EVERY-th checkpoint."""

    def program(self, params: EnduranceParams, ctx: RigContext) -> list[Segment]:
        rest = np.full(ctx.cycles(PAUSE_MIN * 60.0), ctx.theta_m0)
        rest.flags.writeable = False
        out: list[Segment] = []
        previous = -1  # the checkpoint the last segment belonged to
        for seg in super().program(params, ctx):
            index = int(seg.label[1:5]) if seg.label.startswith(CHECKPOINT_PREFIX) else previous
            if index != previous and index > 0 and index % PAUSE_EVERY == 0:
                out.append(Segment(ControlMode.POSITION, rest, 0.0, f"rest{index:04d}"))
            previous = index
            out.append(seg)
        return out


def plant() -> HarmonicDriveModel:
    model = load_model("seed-thermal")
    return model.model_copy(update={"wear_drift": WearDrift(k_wear=K_WEAR), "name": "seed-thermal-wear"})


def warm_up_and_fit(store: RunStore) -> HarmonicDriveModel:
    config = load_rig_config("sim")
    truth = load_model("seed-thermal")
    assert truth.thermal is not None
    start = time.perf_counter()
    outcome = run_experiment("warm-up", config, WARM_UP, store, rig=SimRig(config, truth))
    run = store.read(outcome.run_id)
    wall = time.perf_counter() - start
    metrics = store.get(outcome.run_id)["metrics"]
    print("## warm-up then thermal fit (seed-thermal, real scale)\n")
    print(
        f"warm-up: {WARM_UP['warm_s'] / 3600:g} h duty bound + {WARM_UP['cool_s'] / 3600:g} h cool-down,"
        f" {wall:.0f} s wall; settled {bool(metrics['settled'])} at {metrics['settled_at_s']:.0f} s,"
        f" gear {metrics['temp_gear_start_c']:.2f} → {metrics['temp_gear_max_c']:.2f} °C"
    )
    start = time.perf_counter()
    found = identify_thermal([run], truth)
    print(f"thermal fit: {time.perf_counter() - start:.1f} s wall\n")
    print("| quantity | plant | fitted ± σ | error | target |")
    print("|---|---|---|---|---|")
    t = truth.thermal
    for name, estimate in found.network.parameters.items():
        expected = getattr(t, name)
        print(
            f"| {name} | {expected:g} | {estimate.value:.4g} ± {estimate.sigma:.2g} |"
            f" {100 * (estimate.value / expected - 1):+.2f} % | 10 % |"
        )
    a = np.array(
        [
            [-(1 / t.R_wg + 1 / t.R_wa) / t.C_w, 1 / (t.R_wg * t.C_w)],
            [1 / (t.R_wg * t.C_g), -(1 / t.R_wg + 1 / t.R_ga) / t.C_g],
        ]
    )
    taus = sorted(1.0 / -np.linalg.eigvals(a).real, reverse=True)
    for what, estimate, expected in zip(("slow", "fast"), found.network.time_constants_s, taus, strict=True):
        print(
            f"| τ {what} [s] | {expected:.1f} | {estimate.value:.1f} ± {estimate.sigma:.2g} |"
            f" {100 * (estimate.value / expected - 1):+.2f} % | 10 % |"
        )
    law = found.law
    print(
        f"| beta_T [1/K] | {t.beta_T:g} | {law.beta_per_k.value:.4g} ± {law.beta_per_k.sigma:.2g} |"
        f" {100 * (law.beta_per_k.value / t.beta_T - 1):+.2f} % | 10 % |"
    )
    held = t.model_copy(update={"T_amb": t.T_ref, "C_w": 1e9, "C_g": 1e9})
    reference = run_experiment(
        "warm-up",
        config,
        {"warm_s": 10.0, "cool_s": 0.0, "settle_window_s": 5.0},
        store,
        rig=SimRig(config, truth.model_copy(update={"thermal": held})),
    )
    ref_run = store.read(reference.run_id)
    params = WarmUpParams.model_validate(ref_run.meta["params"], strict=False)
    table = warm_up_checkpoints(ref_run, context_from_run(ref_run), params)
    for speed, estimate in law.reference_nm.items():
        expected = float(table[f"torque_{speed:g}_nm"][0])
        print(
            f"| running torque at {law.t_ref_c:g} °C, {speed:g} rad/s [N·m] | {expected:.5f} |"
            f" {estimate.value:.5f} ± {estimate.sigma:.1g} | {100 * (estimate.value / expected - 1):+.2f} % |"
            " 5 % |"
        )
    low, high = law.temperature_span_c
    print(f"\ncheckpoints span {low:.1f}–{high:.1f} °C of gear temperature; notes: {found.network.notes}")
    return truth.model_copy(update={"thermal": found.section})


def wear_fit(s: np.ndarray, f: np.ndarray, sigma: np.ndarray, share: float) -> tuple[float, float]:
    """k_wear and its σ from F = share + F_0·(1 + k·s), weighted least squares on (F − share)."""
    x = np.column_stack([np.ones_like(s), s])
    w = 1.0 / sigma**2
    cov = np.linalg.inv((x * w[:, None]).T @ x)
    coef = cov @ (x * w[:, None]).T @ (f - share)
    residual = (f - share - x @ coef) / sigma
    cov *= max(1.0, float(residual @ residual) / max(1, len(f) - 2))
    k = coef[1] / coef[0]
    # The ratio's σ by the delta method.
    grad = np.array([-coef[1] / coef[0] ** 2, 1.0 / coef[0]])
    return float(k), float(math.sqrt(grad @ cov @ grad))


def endurance(store: RunStore, fitted: HarmonicDriveModel) -> None:
    config = load_rig_config("sim").model_copy(update={"unit": "SIM-THERMAL-0001"})
    model = plant()
    experiments.EXPERIMENTS["endurance"] = PausedEndurance()
    start = time.perf_counter()
    outcome = run_experiment("endurance", config, ENDURANCE, store, rig=SimRig(config, model))
    wall = time.perf_counter() - start
    print(f"\n## 10 h endurance with wear and pauses ({outcome.status.value}, {wall:.0f} s wall)\n")
    assert fitted.thermal is not None
    # As `hdrig trend --model <fitted>` does: the fitted model's output share left as measured.
    share = output_share_nm(fitted, 0.0)
    document = trend_document(store, run_id=outcome.run_id, law=fitted.thermal, unscaled_nm=share)
    points = document.points
    s = np.array([p.travel_rad for p in points])
    temps = np.array([p.temp_gear_c or math.nan for p in points])
    raw = np.array([p.coulomb_estimate for p in points])
    raw_sigma = np.array([p.coulomb_sigma for p in points])
    norm = np.array([p.coulomb_normalized_estimate or math.nan for p in points])
    norm_sigma = np.array([p.coulomb_normalized_sigma or math.nan for p in points])
    law = fitted.thermal
    # For comparison: the whole F_c scaled by the law (the output share warmed too).
    whole = raw * np.exp(law.beta_T * (temps - law.T_ref))
    print(
        f"checkpoints: {len(points)}; gear {np.nanmin(temps):.1f}–{np.nanmax(temps):.1f} °C; travel"
        f" {s[-1]:.3g} rad; raw F_c {raw[0]:.4f} → {raw[-1]:.4f} N·m,"
        f" normalized {norm[0]:.4f} → {norm[-1]:.4f}; output share {share:.4g} N·m"
    )
    print("\n| wear drift k_wear [1/rad] from | estimate ± σ | against the plant's 2.8e-7 |")
    print("|---|---|---|")
    for what, f, u in (
        ("raw trend", raw, 0.0),
        ("whole F_c normalized (u = 0)", whole, 0.0),
        ("`hdrig trend --model`: normalized, output share as measured", norm, share),
    ):
        k, k_sigma = wear_fit(s, f, raw_sigma if f is raw else norm_sigma, u)
        off = f"{(k - K_WEAR) / k_sigma:+.1f} σ ({100 * (k / K_WEAR - 1):+.1f} %)"
        print(f"| {what} | {k:.3g} ± {k_sigma:.2g} | {off} |")


def main() -> None:
    with tempfile.TemporaryDirectory() as work:
        store = RunStore(Path(work))
        fitted = warm_up_and_fit(store)
        endurance(store, fitted)


if __name__ == "__main__":
    main()
