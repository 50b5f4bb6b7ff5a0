"""Campaign benchmark (`make bench`): the whole characterization campaign on the simulated rig, virtual time.

Prints a table, asserts nothing. What it measures, in one process, into a throw-away run store:

1. Warm-up: a tiny speed sweep (two speeds, short holds) first. A fresh process loads (or, with an empty
   cache, compiles) the numba-compiled drive and plant loops on its first run, and imports matplotlib for
   the first plot; that one-off cost is reported on its own line, not charged to the campaign.
2. The campaign (`rig.core.actions.execute_plan` of `plan_run("campaign")`, CAMPAIGN_ORDER) on
   configs/rigs/sim.yaml as `make run` runs it: per experiment the wall time from its start to its
   outcome (rig, store, analysis, tables, plots), split at the experiment's last progress report into
   playing and analysis; and the simulated time, from the samples the run stored and the rig's rate.
3. The total wall time against the target: under 20 s for the whole campaign on these machines.
"""

from __future__ import annotations

import os
import platform
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
RIG_FILE = REPO / "configs" / "rigs" / "sim.yaml"
TARGET_WALL_S = 20.0
WARM_UP = {"speeds_rad_s": [1.0, 10.0], "settle_s": 0.05, "hold_s": 0.05}


@dataclass
class Row:
    experiment: str
    status: str
    samples: int
    sim_s: float
    play_s: float
    total_s: float


def main() -> int:
    home = tempfile.TemporaryDirectory(prefix="hdrig-bench-")
    os.environ["HDRIG_HOME"] = home.name  # nothing the benchmark stores outlives it
    started = time.perf_counter()
    from rig.config import load_rig_config
    from rig.core.actions import execute_plan, plan_run
    from rig.core.documents import RunDocument
    from rig.experiments import CAMPAIGN_ORDER
    from rig.runner import run_experiment
    from rig.store.runs import RunStore

    import_s = time.perf_counter() - started

    config = load_rig_config(RIG_FILE)
    if config.pace != "virtual":
        config = config.model_copy(update={"pace": "virtual"})
    store = RunStore(home.name)

    started = time.perf_counter()
    warm = run_experiment("speed-sweep", config, dict(WARM_UP), store)
    warm_up_s = time.perf_counter() - started

    last_report: dict[str, float] = {}
    landed: list[tuple[RunDocument, float]] = []

    def progress(label: str, fraction: float) -> None:
        last_report[label.split(":", 1)[0]] = time.perf_counter()

    def on_run(run: RunDocument) -> None:
        landed.append((run, time.perf_counter()))

    campaign_start = time.perf_counter()
    execute_plan(plan_run("campaign"), config, store, progress=progress, on_run=on_run)
    campaign_s = time.perf_counter() - campaign_start

    rows = []
    begin = campaign_start
    for outcome, end in landed:
        samples = outcome.samples
        played = last_report.get(outcome.experiment, end)
        rows.append(
            Row(
                outcome.experiment,
                outcome.status,
                samples,
                samples / config.sample_rate_hz,
                played - begin,
                end - begin,
            )
        )
        begin = end

    print(f"campaign benchmark: {', '.join(CAMPAIGN_ORDER)} on rig {config.name} ({config.backend}),")
    print(f"  {config.pace} time, {config.sample_rate_hz:g} Hz, integration step {config.sim_dt_s:g} s")
    print(f"  {platform.processor() or platform.machine()}, Python {platform.python_version()}, 1 process")
    print()
    print(f"imports (numpy, numba, scipy, pyarrow, matplotlib...): {import_s:6.2f} s")
    print(
        f"warm-up run (numba cache load or compile, first plot): {warm_up_s:6.2f} s"
        f"  ({warm.experiment} {WARM_UP['speeds_rad_s']} rad/s, {warm.status})"
    )
    print()
    header = (
        f"{'experiment':<20} {'status':<9} {'samples':>8} {'sim s':>8} {'play s':>8} {'analysis s':>10}"
        f" {'wall s':>8} {'sim/wall':>9}"
    )
    print(header)
    print("-" * len(header))
    for row in rows:
        ratio = row.sim_s / row.total_s if row.total_s > 0 else float("inf")
        print(
            f"{row.experiment:<20} {row.status:<9} {row.samples:>8} {row.sim_s:>8.2f} {row.play_s:>8.2f}"
            f" {row.total_s - row.play_s:>10.2f} {row.total_s:>8.2f} {ratio:>8.1f}x"
        )
    print("-" * len(header))
    sim_total = sum(row.sim_s for row in rows)
    verdict = "PASS" if campaign_s < TARGET_WALL_S else "MISS"
    print(
        f"{'campaign':<20} {'':<9} {sum(r.samples for r in rows):>8} {sim_total:>8.2f} {'':>8} {'':>10}"
        f" {campaign_s:>8.2f} {sim_total / campaign_s:>8.1f}x"
    )
    print()
    print(
        f"target: campaign wall time < {TARGET_WALL_S:g} s (warm-up excluded): {campaign_s:.2f} s  {verdict}"
    )
    incomplete = [row.experiment for row in rows if row.status != "complete"]
    if incomplete:
        print(f"note: not complete: {', '.join(incomplete)}")
    home.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
