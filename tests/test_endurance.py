"""Endurance: a known wear drift given to the simulated plant is recovered by the checkpoints, they land in
the catalog, `hdrig trend` shows them; the online tracker follows a drifting level with the lag its
memory implies.

The truth comes from docs/MODEL.md's `wear_drift`: every motor friction magnitude scales by
s = 1 + k_wear·s_m (s_m the motor travel), the load side's does not. The checkpoint's level is linear in
the hold torques, so F_c(k) = s_k·M + L with M the motor part and L = r·f_cl the load part (the load
side's Coulomb level seen at the motor). Checkpoint 0 comes before any travel (s_0 = 1 to 1e-4), so
F_c(k) = L + (F_c(0) − L)·s_k.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from model.params import load_model
from model.recursive import FrictionTracker
from model.run import Run
from rig.config import load_rig_config
from rig.core import actions
from rig.experiments.base import RigContext, context_from_run
from rig.experiments.endurance import (
    TRACK_POINTS_MAX,
    Endurance,
    EnduranceObserver,
    EnduranceParams,
    checkpoint_program,
)
from rig.interface import Segment, open_simulated_rig
from rig.runner import analyze_stored, make_params, run_experiment
from rig.store.runs import RunStore

K_WEAR = 2e-5  # per rad: +10 % in 5,000 rad, a few simulated minutes of the duty cycle
UNIT = "TEST-UNIT-7"


@pytest.fixture(scope="module")
def endurance(tmp_path_factory: pytest.TempPathFactory) -> tuple[RunStore, str]:
    store = RunStore(tmp_path_factory.mktemp("home"))
    model = load_model("seed").with_updates(wear_drift={"k_wear": K_WEAR})
    config = load_rig_config("sim").model_copy(update={"unit": UNIT})
    rig = open_simulated_rig(config, model)
    try:
        outcome = run_experiment(
            "endurance",
            config,
            {"duration_h": 0.05, "checkpoint_every_min": 1.0},  # 3 min of duty, 4 checkpoints
            store,
            rig=rig,
        )
    finally:
        rig.close()
    assert outcome.status == "complete", outcome.reason
    return store, outcome.run_id


def test_the_wear_given_to_the_plant_is_recovered_within_the_stated_uncertainty(
    endurance: tuple[RunStore, str],
) -> None:
    store, run_id = endurance
    points = store.checkpoints(run_id=run_id)
    assert [p["index"] for p in points] == [0, 1, 2, 3]
    seed = load_model("seed")
    assert seed.load_friction is not None and seed.load_friction.f_cl is not None
    load_part = seed.mechanics.r * seed.load_friction.f_cl
    first = points[0]
    assert first["travel_rad"] * K_WEAR < 0.02  # checkpoint 0 is (nearly) before any wear
    s0 = 1 + K_WEAR * first["travel_rad"]
    for point in points[1:]:
        expected = load_part + (first["coulomb_nm"] - load_part) * (1 + K_WEAR * point["travel_rad"]) / s0
        sigma = np.hypot(point["coulomb_sigma_nm"], first["coulomb_sigma_nm"])
        assert abs(point["coulomb_nm"] - expected) <= 2 * sigma, point
    # The test can fail: the drift by the last checkpoint is many times the uncertainty.
    last = points[-1]
    assert last["coulomb_nm"] - first["coulomb_nm"] > 4 * np.hypot(
        last["coulomb_sigma_nm"], first["coulomb_sigma_nm"]
    )


def test_stiffness_is_the_plant_s_within_three_sigma(endurance: tuple[RunStore, str]) -> None:
    store, run_id = endurance
    for point in store.checkpoints(run_id=run_id):
        assert abs(point["stiffness_nm_rad"] - 1000.0) <= 3 * point["stiffness_sigma_nm_rad"] + 0.5, point


def test_the_analysis_reads_only_the_checkpoints(endurance: tuple[RunStore, str]) -> None:
    store, run_id = endurance
    entry = store.get(run_id)
    checkpoint_rows = sum(
        int(s["cycles"]) for s in entry["meta"]["segments"] if str(s["label"]).startswith("c")
    )
    duty_rows = sum(int(s["cycles"]) for s in entry["meta"]["segments"] if str(s["label"]).startswith("duty"))
    run = store.read(run_id, segments=[s["label"] for s in entry["meta"]["segments"] if s["label"][0] == "c"])
    assert len(run) == checkpoint_rows
    # 3 min of duty beside 4 checkpoints of ~50 s: none of it read
    assert checkpoint_rows + duty_rows <= entry["samples"] and duty_rows > entry["samples"] / 3


def test_the_analysis_holds_one_checkpoint_at_a_time_and_agrees_with_all_at_once(
    endurance: tuple[RunStore, str],
) -> None:
    store, run_id = endurance
    labels = [str(s["label"]) for s in store.get(run_id)["meta"]["segments"]]
    experiment = Endurance()
    first = store.read(run_id, segments=experiment.analyzed_segments(None, labels))  # type: ignore[arg-type]
    params = make_params(experiment, dict(first.meta["params"]))
    assert isinstance(params, EnduranceParams)
    ctx = context_from_run(first)
    reads: list[int] = []

    def read(chosen: list[str]) -> Run:
        part = store.read(run_id, segments=chosen)
        reads.append(len(part))
        return part

    parts = experiment.analyze_parts(read, first, params, ctx)
    # Checkpoint 0 came with `first`; each other one was read alone, none larger than checkpoint 0.
    assert len(reads) == 3 and max(reads) == len(first)
    together = experiment.analyze(
        store.read(run_id, segments=[x for x in labels if x[0] == "c"]), params, ctx
    )
    assert parts.checkpoints == together.checkpoints
    stored = store.checkpoints(run_id=run_id)  # what the runner's analysis put in the catalog
    assert [p["coulomb_nm"] for p in stored] == [p["coulomb_nm"] for p in parts.checkpoints]


def test_the_online_track_stays_bounded_on_a_run_of_hours() -> None:
    # 10 h of 1 s blocks with a track point asked every second: the track keeps between half and all of
    # TRACK_POINTS_MAX points, spread over the whole run (every other one dropped, the spacing doubled).
    ctx = RigContext(load_rig_config("sim"), 0.01, 0.0302, 0.0)
    observer = EnduranceObserver(EnduranceParams(track_every_s=1.0), ctx, [])
    run_s, n = 10 * 3600, 100
    for second in range(run_s):
        t = second + np.arange(n) / n
        observer.feed({"t": t, "omega_m": np.full(n, 20.0), "i_a": np.full(n, 3.0), "tau_ext": np.zeros(n)})
    track = np.asarray(observer.summary()["track"]["t_s"])
    assert TRACK_POINTS_MAX // 2 <= len(track) <= TRACK_POINTS_MAX
    spacing = np.diff(track)
    assert np.all(spacing > 0) and spacing.max() <= 2 * run_s / TRACK_POINTS_MAX
    assert track[0] < 2.0 and track[-1] > run_s - spacing.max()


def test_trend_of_the_unit_lists_the_checkpoints_with_the_online_track(
    endurance: tuple[RunStore, str], tmp_path: Path
) -> None:
    store, run_id = endurance
    document = actions.trend(store, unit=UNIT, plot_dir=tmp_path)
    assert document.run_ids == [run_id]
    assert [p.index for p in document.points] == [0, 1, 2, 3]
    assert [p.duty_cycles for p in document.points] == [0.0, 6.0, 12.0, 18.0]  # 10 s cycles, 1 min apart
    assert len(document.track) >= 10
    assert sorted(Path(p).name for p in document.plots) == ["friction_trend.png", "stiffness_trend.png"]


def test_trend_of_an_unknown_unit_is_a_one_line_error(endurance: tuple[RunStore, str]) -> None:
    store, _ = endurance
    from model.errors import UserInputError

    with pytest.raises(UserInputError, match="unit 'NOPE' has no checkpoints"):
        actions.trend(store, unit="NOPE")


def test_the_tracker_follows_a_ramp_with_the_lag_of_its_memory() -> None:
    # Synthetic drive, independent of the plant: y = F_c(t)·sgn ω + b·ω + J·dω/dt + noise, F_c rising
    # linearly. For RLS with forgetting λ on a steady ramp, the estimate trails by the effective memory
    # 1/(1 − λ) samples, i.e. memory_s (Ljung §11.2); the noise averages over the same memory.
    rate_hz, memory_s, hours = 1000.0, 30.0, 0.1
    t = np.arange(int(hours * 3600 * rate_hz)) / rate_hz
    omega = 40.0 * np.sin(2 * np.pi * t / 10.0)
    alpha = 40.0 * 2 * np.pi / 10.0 * np.cos(2 * np.pi * t / 10.0)
    slope_nm_s = 1e-5
    level = 0.07 + slope_nm_s * t
    rng = np.random.default_rng(3)
    torque = level * np.sign(omega) + 3e-5 * omega + 7.5e-5 * alpha + rng.normal(0.0, 1.5e-4, t.size)
    k_m = 0.0302
    tracker = FrictionTracker(rate_hz, k_m, 0.01, memory_s=memory_s)
    estimate = np.concatenate(
        [
            tracker.feed(torque[i : i + 250] / k_m, np.zeros(250), omega[i : i + 250])
            for i in range(0, t.size, 250)
        ]
    )
    settled = t > 5 * memory_s
    lag_s = np.mean((level[settled] - estimate[settled]) / slope_nm_s)
    # Samples below 1 rad/s are skipped (~2 % of a sine's), which stretches the memory in time a little.
    assert 0.8 * memory_s < lag_s < 1.2 * memory_s
    noise = np.std(estimate[settled] - (level[settled] - slope_nm_s * lag_s))
    # The scatter about the lagged level is not white noise averaged over the memory (~1e-6 N·m): the
    # duty's speed, and so what each sample says of F_c, swings over each 10 s period, and the estimate
    # wobbles with it. 5e-5 N·m is 0.07 % of the level, well below a checkpoint's uncertainty (~1e-3).
    assert noise < 5e-5


def test_analyzing_a_stored_run_again_reads_only_its_checkpoints(
    endurance: tuple[RunStore, str], monkeypatch: pytest.MonkeyPatch
) -> None:
    store, run_id = endurance
    before = store.checkpoints(run_id=run_id)
    checkpoint_rows = sum(
        int(s["cycles"]) for s in store.get(run_id)["meta"]["segments"] if str(s["label"]).startswith("c")
    )
    reads: list[tuple[list[str] | None, int]] = []
    read = store.read

    def counted(run: str, *args: Any, **kwargs: Any) -> Run:
        got = read(run, *args, **kwargs)
        reads.append((kwargs.get("segments"), len(got)))
        return got

    monkeypatch.setattr(store, "read", counted)
    outcome = analyze_stored(store, run_id)
    assert outcome.status == "complete"
    # Every read named its segments (never the whole run, hours of duty cycle on a long one), and they
    # held the checkpoints' rows only, each once.
    assert reads and all(segments is not None for segments, _ in reads)
    assert sum(rows for _, rows in reads) == checkpoint_rows
    assert store.checkpoints(run_id=run_id) == before  # the same numbers as the first analysis


def test_the_program_s_set_points_do_not_grow_with_its_hours() -> None:
    ctx = RigContext(load_rig_config("sim-endurance"), 0.01, 0.0302, 0.0)
    experiment = Endurance()

    def distinct_bytes(hours: float) -> tuple[int, list[Segment]]:
        program = experiment.program(EnduranceParams(duration_h=hours), ctx)
        return sum({id(seg.setpoint): seg.setpoint.nbytes for seg in program}.values()), program

    short, _ = distinct_bytes(1.0)
    long, program = distinct_bytes(10.0)
    assert long == short < 1 << 20  # one duty minute and one checkpoint's arrays, shared
    # Checkpoint 7 of the long run is still the checkpoint program, under its own labels.
    mine = [seg for seg in program if seg.label.startswith("c0007/")]
    own = checkpoint_program(EnduranceParams(duration_h=10.0), ctx, 7)
    assert [seg.label for seg in mine] == [seg.label for seg in own]
    for a, b in zip(mine, own, strict=True):
        assert a.mode == b.mode and a.tau_ext == b.tau_ext
        np.testing.assert_array_equal(a.setpoint, b.setpoint)
