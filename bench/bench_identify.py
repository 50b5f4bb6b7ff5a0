"""Benchmark: full identification of the seed model from one campaign on the simulated rig.

Truth is `seed`; the rig is configs/rigs/sim.yaml (17-bit encoder, current and output-sensor noise,
filtered drive speed). The start model is 15–30 % off. Prints wall time per stage and each
parameter's error against the truth; target: identification (staged + joint) ≤ 30 s wall here.
"""

from __future__ import annotations

import math
import tempfile
import time

from model.fit.parameters import get_values, with_values
from model.params import load_model
from rig.config import load_rig_config
from rig.core.actions import execute_plan, plan_run
from rig.identification import identify
from rig.store import RunStore

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


def main() -> None:
    truth = load_model("seed")
    start = with_values(truth, START)
    with tempfile.TemporaryDirectory() as home:
        store = RunStore(home)
        t0 = time.perf_counter()
        documents = execute_plan(plan_run("campaign"), load_rig_config("sim"), store)
        campaign_s = time.perf_counter() - t0
        runs = [store.read(d.id) for d in documents]
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


if __name__ == "__main__":
    main()
