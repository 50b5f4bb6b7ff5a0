"""Experiments played on the in-process simulated rig and their runs read back: the campaigns the
identification tests fit."""

from __future__ import annotations

from collections.abc import Iterable

from model.params import HarmonicDriveModel
from model.run import Run
from rig.config import RigConfig
from rig.runner import run_experiment
from rig.store.runs import RunStore
from sim_backend.inprocess import SimRig


def play(
    experiments: Iterable[str], config: RigConfig, truth: HarmonicDriveModel, store: RunStore
) -> list[Run]:
    """Each experiment with its default parameters on a `SimRig` of `truth`; every one must complete."""
    runs = []
    for name in experiments:
        outcome = run_experiment(name, config, {}, store, rig=SimRig(config, model=truth))
        assert outcome.status == "complete", f"{name}: {outcome.reason}"
        runs.append(store.read(outcome.run_id))
    return runs
