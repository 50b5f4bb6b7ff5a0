"""What the model's feed-forward buys on the simulated rig (issue 14), printed beside the targets.

1. The campaign on configs/rigs/sim.yaml into a fresh store, then `fit` from the seed (rig.core.actions):
   the model used is the fitted one, never the plant's own parameters.
2. `compensation` with that model file, and again with the measured-velocity option.

Targets: sine RMS error and ramp stick-slip each ≥ 3× lower with compensation; the runs with the
model's friction 20 % low and high reported, and never worse than no compensation.
"""

from __future__ import annotations

import json
import sys
import tempfile
import time
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT))

from rig.config import load_rig_config  # noqa: E402
from rig.core import actions  # noqa: E402
from rig.store.runs import RunStore  # noqa: E402

TARGET = 3.0


def main() -> None:
    config = load_rig_config(str(REPO_ROOT / "configs" / "rigs" / "sim.yaml"))
    with tempfile.TemporaryDirectory() as home:
        store = RunStore(Path(home))
        start = time.perf_counter()
        actions.execute_plan(actions.plan_run("campaign"), config, store)
        model_file = Path(home) / "fitted.yaml"
        actions.fit(["latest"], "seed", store, out=model_file)
        took_s = time.perf_counter() - start
        print(f"compensation benchmark: campaign + fit on rig {config.name} in {took_s:.1f} s")
        for label, extra in (("planned speed", {}), ("measured speed near 0", {"measured_velocity": True})):
            start = time.perf_counter()
            (run,) = actions.execute_plan(
                actions.plan_run("compensation", {"model": str(model_file), **extra}), config, store
            )
            m = run.metrics
            print(f"\nfriction direction from the {label} ({time.perf_counter() - start:.1f} s wall):")
            print(f"{'figure':<34}{'off':>12}{'on':>12}{'ratio':>9}{'−20 %':>9}{'+20 %':>9}  target")
            for motion in ("sine", "ramp"):
                ratio = m[f"improvement_{motion}"]
                verdict = (
                    "" if motion == "step" else f"≥ {TARGET:g}×: {'PASS' if ratio >= TARGET else 'MISS'}"
                )
                if motion == "ramp":
                    verdict = "—"
                print(
                    f"{motion + ' RMS error [rad]':<34}{m[f'rms_error_{motion}_off_rad']:>12.3g}"
                    f"{m[f'rms_error_{motion}_on_rad']:>12.3g}{ratio:>8.2f}×"
                    f"{m[f'improvement_{motion}_friction_minus_20pct']:>8.2f}×"
                    f"{m[f'improvement_{motion}_friction_plus_20pct']:>8.2f}×  {verdict}"
                )
            for quantity, unit in (("overshoot_pct", "%"), ("settling_s", "s")):
                print(
                    f"{'step ' + quantity + ' [' + unit + ']':<34}{m[f'{quantity}_step_off']:>12.3g}"
                    f"{m[f'{quantity}_step_on']:>12.3g}{'':>9}{m[f'{quantity}_step_friction_minus_20pct']:>9.3g}"
                    f"{m[f'{quantity}_step_friction_plus_20pct']:>9.3g}"
                )
            ratio = m["improvement_stick_slip"]
            print(
                f"{'ramp stick-slip p-p [rad]':<34}{m['stick_slip_pp_off_rad']:>12.3g}"
                f"{m['stick_slip_pp_on_rad']:>12.3g}"
                f"{ratio:>8.2f}×{m['improvement_stick_slip_friction_minus_20pct']:>8.2f}×"
                f"{m['improvement_stick_slip_friction_plus_20pct']:>8.2f}×"
                f"  ≥ {TARGET:g}×: {'PASS' if ratio >= TARGET else 'MISS'}"
            )
            results = json.loads((Path(run.run_dir) / "artifacts" / "results.json").read_text())
            for note in results["notes"]:
                print(f"  note: {note}")


if __name__ == "__main__":
    main()
