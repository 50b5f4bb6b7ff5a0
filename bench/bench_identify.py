"""Benchmark: full identification of the seed model from one campaign on the simulated rig, and the
coverage of its reported uncertainty over repeated campaigns.

Truth is `seed`; the rig is configs/rigs/sim.yaml (17-bit encoder, current and output-sensor noise,
filtered drive speed). The start model is 15–30 % off.

1. One campaign: wall time per stage and each parameter's error against the truth; target:
   identification (staged + joint) ≤ 30 s wall here.
2. Coverage (`--seeds`, default 20): the same campaign with the rig's sensor-noise seed changed, fitted
   each time; per main parameter, how often |estimate − truth| ≤ 1σ (target about 68 %) and ≤ 2σ
   (about 95 %), and the RMS of z = (estimate − truth)/σ (1 when σ means what it says; above 1:
   overconfident), with the σ relative to the value and the error's mean and spread over the seeds.
   `--seeds 0` skips it; `--seeds 3` is a quick look before the 20-seed run.
3. Replay of a continuous plant: the joint step's runs (pulse, step, sine) with ideal sensors from the
   sim rig's plant stepped at 1 µs (near-continuous: 1 % of the replay's own Euler error), J_m and J_l
   fitted with all else true, replayed as continuous (the default for such a run) and, for comparison,
   as if our plant had made them at 0.1 ms; CPU time of one residual over all windows each way.
"""

from __future__ import annotations

import argparse
import math
import statistics
import tempfile
import time

from model.params import HarmonicDriveModel, load_model
from model.run import Run
from rig.analysis.fit.parameters import get_values, with_values
from rig.analysis.fit.trajectory import TrajectoryProblem, fit_problem
from rig.analysis.identification import identify
from rig.analysis.identification.identify import JOINT_EXPERIMENTS, JOINT_WINDOW_S
from rig.config import load_rig_config
from rig.core.actions import execute_plan, plan_run
from rig.runner import run_experiment
from rig.store.runs import RunStore
from sim_backend.inprocess import SimRig

TARGET_S = 30.0
START = {
    "s3": 0.06,
    "k_v": 3e-4,
    "K_s": 1300.0,
    "J_m": 4e-5,
    "J_l": 0.25,
    "R": 0.35,
    "f_cl": 0.2,
    "static_factor": 1.3,
    "K_b": 0.025,
    "b_l": 0.08,
}


MAIN = ("J_m", "J_l", "K_s", "s3", "k_v", "static_factor", "R", "K_b", "f_cl", "b_l")
"""The parameters the joint refinement moves: the coverage table's rows."""
COVERAGE_1SIGMA = 0.68


def campaign(seed: int | None = None) -> tuple[list[Run], float]:
    """One campaign on the simulated rig (its sensor-noise seed changed when given); runs, wall time."""
    config = load_rig_config("sim")
    if seed is not None:
        config = config.model_copy(update={"sensors": config.sensors.model_copy(update={"seed": seed})})
    with tempfile.TemporaryDirectory() as home:
        store = RunStore(home)
        t0 = time.perf_counter()
        documents = execute_plan(plan_run("campaign"), config, store)
        wall = time.perf_counter() - t0
        return [store.read(d.id) for d in documents], wall


def coverage(truth: HarmonicDriveModel, start: HarmonicDriveModel, seeds: int) -> None:
    """Fit `seeds` campaigns that differ only in sensor noise; print how often 1σ and 2σ cover the truth.

    Beside the coverage: RMS z (1 when σ means what it says), mean z (a bias repeated seed to seed),
    the mean reported σ relative to the truth, and the error's mean and spread over the seeds [%]."""
    true = get_values(truth, list(MAIN))
    z: dict[str, list[float]] = {name: [] for name in MAIN}
    errors: dict[str, list[float]] = {name: [] for name in MAIN}
    sigmas: dict[str, list[float]] = {name: [] for name in MAIN}
    undetermined = dict.fromkeys(MAIN, 0)
    walls: list[float] = []
    t0 = time.perf_counter()
    for seed in range(1, seeds + 1):
        runs, _ = campaign(seed=100 + seed)
        fit_t0 = time.perf_counter()
        result = identify(runs, start)
        walls.append(time.perf_counter() - fit_t0)
        for row in result.parameters:
            if row.name not in z:
                continue
            errors[row.name].append(100 * (row.estimate - true[row.name]) / true[row.name])
            if row.uncertainty is None or row.uncertainty <= 0:
                undetermined[row.name] += 1
            else:
                z[row.name].append((row.estimate - true[row.name]) / row.uncertainty)
                sigmas[row.name].append(100 * row.uncertainty / abs(true[row.name]))
        print(f"  seed {seed:2d} done ({time.perf_counter() - t0:.0f} s; fit {walls[-1]:.1f} s)", flush=True)
    print()
    print(f"Coverage of the reported 1σ over {seeds} campaigns (sensor-noise seeds 101..{100 + seeds})")
    print(
        f"  identification wall time per campaign: median {statistics.median(walls):.1f} s,"
        f" max {max(walls):.1f} s"
    )
    head = ("≤ 1σ", "≤ 2σ", "RMS z", "mean z", "σ/value", "bias", "spread", "no σ")
    print(f"  {'parameter':<14s}" + "".join(f" {h:>8s}" for h in head))
    target = ("~68 %", "~95 %", "~1", "~0", "", "", "", "0")
    print(f"  {'target':<14s}" + "".join(f" {h:>8s}" for h in target))
    for name in MAIN:
        values = z[name]
        bias = statistics.fmean(errors[name])
        spread = statistics.stdev(errors[name]) if len(errors[name]) > 1 else math.nan
        if not values:
            print(f"  {name:<14s}" + "".join(f" {'—':>8s}" for _ in range(5)), end="")
            print(f" {bias:>+7.3f}% {spread:>7.3f}% {undetermined[name]:>8d}")
            continue
        within1 = sum(abs(v) <= 1 for v in values) / len(values)
        within2 = sum(abs(v) <= 2 for v in values) / len(values)
        rms = math.sqrt(statistics.fmean(v * v for v in values))
        print(
            f"  {name:<14s} {100 * within1:>7.0f}% {100 * within2:>7.0f}% {rms:>8.2f}"
            f" {statistics.fmean(values):>+8.2f} {statistics.fmean(sigmas[name]):>7.3f}% {bias:>+7.3f}%"
            f" {spread:>7.3f}% {undetermined[name]:>8d}"
        )


def continuous_replay(truth: HarmonicDriveModel) -> None:
    """Part 3: J_m, J_l from a near-continuous plant, replayed as continuous and as our 0.1 ms plant."""
    config = load_rig_config("sim").model_copy(update={"sim_dt_s": 1e-6})
    ideal = {"encoder_counts_per_rev": 0, "current_noise_a": 0.0, "load_sensor_noise_rad": 0.0}
    config = config.model_copy(update={"sensors": config.sensors.model_copy(update=ideal)})
    with tempfile.TemporaryDirectory() as home:
        store = RunStore(home)
        runs = []
        for experiment in JOINT_EXPERIMENTS:
            outcome = run_experiment(experiment, config, {}, store, rig=SimRig(config, model=truth))
            runs.append(store.read(outcome.run_id))
    names = ["J_m", "J_l"]
    true = get_values(truth, names)
    print("Replay of a near-continuous plant (sim rig stepped at 1 µs, ideal sensors; J_m, J_l free)")
    for label, meta in (("as continuous", {}), ("as our 0.1 ms plant", {"rig_config": {"sim_dt_s": 1e-4}})):
        these = [Run(r.columns, {**r.meta, **meta}) for r in runs]
        problem = TrajectoryProblem(truth, these, names, JOINT_WINDOW_S, 1e-4)
        problem.residuals_of(truth)  # compiled
        c0 = time.process_time()
        problem.residuals_of(truth)
        cpu_ms = 1e3 * (time.process_time() - c0)
        fit = fit_problem(problem)
        errors = "  ".join(
            f"{p.name} {100 * (p.estimate - true[p.name]) / true[p.name]:+.4f} %"
            f" (σ {100 * (p.std_error or math.nan) / true[p.name]:.4f} %)"
            for p in fit.parameters
        )
        print(f"  {label:<22s} {errors}   one residual {cpu_ms:.0f} CPU-ms")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=20, help="campaigns for the coverage table (0: skip)")
    args = parser.parse_args()
    truth = load_model("seed")
    start = with_values(truth, START)
    runs, campaign_s = campaign()
    stages: list[tuple[str, float]] = []
    t0 = time.perf_counter()
    result = identify(runs, start, progress=lambda label, _: stages.append((label, time.perf_counter())))
    fit_s = time.perf_counter() - t0
    print("Identification of the seed model from one campaign (simulated rig, realistic sensors)")
    print(f"  campaign on the simulated rig: {campaign_s:6.2f} s wall ({len(runs)} runs)")
    for label, moment in stages:
        print(f"  {label:<30s} starts at {moment - t0:6.2f} s")
    print()
    print(f"  {'parameter':<14s} {'truth':>12s} {'start':>12s} {'estimate':>12s} {'error':>9s}  1σ / flag")
    for row in result.parameters:
        try:
            true_value = get_values(truth, [row.name])[row.name]
        except Exception:  # a parameter of an effect the truth does not have
            true_value = math.nan
        error = (row.estimate - true_value) / true_value * 100 if true_value else math.nan
        sigma = (
            f"{row.uncertainty:.2g}" if row.uncertainty is not None else f"not determined: {row.note[:40]}"
        )
        print(
            f"  {row.name:<14s} {true_value:>12.5g} {row.start:>12.5g} {row.estimate:>12.5g}"
            f" {error:>8.2f}%  {sigma}"
        )
    print()
    print(f"  fit error {result.fit_error_before:.4g} → {result.fit_error_after:.4g}")
    verdict = "PASS" if fit_s <= TARGET_S else "MISS"
    print(f"  identification wall time {fit_s:.2f} s   target ≤ {TARGET_S:g} s   {verdict}")
    print()
    continuous_replay(truth)
    if args.seeds > 0:
        print()
        coverage(truth, start, args.seeds)


if __name__ == "__main__":
    main()
