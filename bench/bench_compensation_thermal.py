"""What the measured temperature buys the feed-forward (issue 27 item 7; prints figures, asserts nothing).

The `compensation` experiment with the plant's own `seed-thermal-fast` model file, whose tracks carry the
thermal law: variant `on` plays the friction at the gear's measured temperature, `on_no_temperature` at
T_ref (25 °C). Cases: (1) a warm-up run first (300 s of duty, the gear ~31 °C), then the compensation on
the warm gear as it cools; (2) the gear held at fixed temperatures (ambient and start there, heat
capacities so large that nothing warms): 25 °C (= T_ref, where both variants plan the same and the
difference is the run-to-run spread of playing variants one after another), 40 and 50 °C. Figure:
`temperature_gain_<motion>` = RMS error without the temperature over with it (> 1: it helps).
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from model.params import load_model  # noqa: E402
from rig.config import load_rig_config  # noqa: E402
from rig.runner import run_experiment  # noqa: E402
from rig.store.runs import RunStore  # noqa: E402
from sim_backend.inprocess import SimRig  # noqa: E402

MODEL = "seed-thermal-fast"
PARAMS = {"model": MODEL, "friction_errors": [-0.2]}


def row(store: RunStore, what: str, rig: SimRig) -> None:
    config = load_rig_config("sim")
    start = rig.temp_gear_c
    outcome = run_experiment("compensation", config, PARAMS, store, rig=rig)
    m = store.get(outcome.run_id)["metrics"]
    print(
        f"| {what} | {start:.1f} → {rig.temp_gear_c:.1f} |"
        f" {m['rms_error_sine_on_no_temperature_rad']:.3g} → {m['rms_error_sine_on_rad']:.3g} |"
        f" **{m['temperature_gain_sine']:.2f}×** |"
        f" {m['rms_error_ramp_on_no_temperature_rad']:.3g} → {m['rms_error_ramp_on_rad']:.3g} |"
        f" **{m['temperature_gain_ramp']:.2f}×** |"
    )


def main() -> None:
    config = load_rig_config("sim")
    plant = load_model(MODEL)
    assert plant.thermal is not None
    print(
        "| case | gear °C | sine RMS without → with [rad] | sine gain | ramp RMS without → with | ramp gain |"
    )
    print("|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as work:
        store = RunStore(Path(work))
        rig = SimRig(config, plant)
        run_experiment("warm-up", config, {"warm_s": 300.0, "cool_s": 0.0}, store, rig=rig)
        row(store, "after a 300 s warm-up", rig)
        for temp in (25.0, 40.0, 50.0):
            held = plant.thermal.model_copy(update={"T_amb": temp, "C_w": 1e9, "C_g": 1e9})
            rig = SimRig(config, plant.model_copy(update={"thermal": held}))
            rig.temp_gear_c = temp
            row(store, f"held at {temp:g} °C", rig)


if __name__ == "__main__":
    main()
