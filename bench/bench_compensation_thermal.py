"""What the measured temperature buys the feed-forward (issue 27 item 7; prints figures, asserts nothing).

The `compensation` experiment with the plant's own model file, whose tracks carry the thermal law: variant
`on` plays the friction at the gear's measured temperature, `on_no_temperature` at T_ref (25 °C). Every
variant is played `REPEATS` times (order rotated, each after the same approach), so a ratio comes with
the spread of the repeats. Cases: (1) `seed-thermal-fast` after a 300 s warm-up (the gear ~31 °C, cooling
fast as the comparison runs); (2) `seed-thermal` at its real scale after a warm-up to a settled gear (it
stays warm through the comparison); (3) `seed-thermal-fast` held at fixed temperatures (ambient and
start there, heat capacities so large that nothing warms): 25 °C (= T_ref, where both variants plan the
same: the null, which must read 1 within its spread), 40 and 50 °C. Figure: `temperature_gain_<motion>`
= RMS error without the temperature over with it (> 1: it helps), ± the σ of the repeats' mean.
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

REPEATS = 6


def row(store: RunStore, what: str, rig: SimRig, model: str) -> None:
    config = load_rig_config("sim")
    start = rig.temp_gear_c
    params = {"model": model, "friction_errors": [-0.2], "repeats": REPEATS}
    outcome = run_experiment("compensation", config, params, store, rig=rig)
    m = store.get(outcome.run_id)["metrics"]
    cells = []
    for motion in ("sine", "ramp"):
        cells.append(
            f" {m[f'rms_error_{motion}_on_no_temperature_rad']:.3g} → {m[f'rms_error_{motion}_on_rad']:.3g} |"
            f" **{m[f'temperature_gain_{motion}']:.3f} ± {m[f'temperature_gain_{motion}_std']:.3f}** |"
        )
    print(f"| {what} | {start:.1f} → {rig.temp_gear_c:.1f} |{''.join(cells)}", flush=True)


def main() -> None:
    config = load_rig_config("sim")
    print(
        "| case | gear °C | sine RMS without → with [rad] | sine gain | ramp RMS without → with | ramp gain |"
    )
    print("|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as work:
        store = RunStore(Path(work))
        rig = SimRig(config, load_model("seed-thermal-fast"))
        run_experiment("warm-up", config, {"warm_s": 300.0, "cool_s": 0.0}, store, rig=rig)
        row(store, "seed-thermal-fast after a 300 s warm-up", rig, "seed-thermal-fast")
        rig = SimRig(config, load_model("seed-thermal"))
        run_experiment("warm-up", config, {"warm_s": 3600.0, "cool_s": 0.0}, store, rig=rig)
        row(store, "seed-thermal after a 1 h warm-up", rig, "seed-thermal")
        plant = load_model("seed-thermal-fast")
        assert plant.thermal is not None
        for temp in (25.0, 40.0, 50.0):
            held = plant.thermal.model_copy(update={"T_amb": temp, "C_w": 1e9, "C_g": 1e9})
            rig = SimRig(config, plant.model_copy(update={"thermal": held}))
            rig.temp_gear_c = temp
            row(store, f"held at {temp:g} °C", rig, "seed-thermal-fast")


if __name__ == "__main__":
    main()
