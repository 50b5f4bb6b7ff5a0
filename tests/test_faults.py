"""Fault injection: however a run ends, the motor stops first, the data are kept, the status is true,
and no traceback reaches the user (issue 15; docs/RELIABILITY.md lists each fault and what happens).

In-process tests use the simulated rig `sim` in virtual time; the process tests run `hdrig` as a user
does, on a realtime copy of it (a run then lasts seconds of wall time, long enough to be hit mid-run)
or on the virtual-can rig, whose raw CAN log shows what the drive was told last.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from rig.config import RigConfig, load_rig_config
from rig.interface import Block
from rig.runner import RunHooks, run_experiment
from rig.status import RunStatus
from rig.store import RunStore
from sim_backend.inprocess import SimRig

REPO_ROOT = Path(__file__).resolve().parents[1]


def sim_config(pace: str = "virtual") -> RigConfig:
    return load_rig_config("sim").model_copy(update={"pace": pace})


# ---- one stop path: the motor first, then the data ------------------------------------------------


class _Recorder:
    """Notes, in order, when the rig was quick-stopped and when the store sealed a run."""

    def __init__(self, rig: SimRig, store: RunStore, monkeypatch: pytest.MonkeyPatch) -> None:
        self.order: list[str] = []
        stop, seal = rig.quick_stop, store._seal

        def quick_stop() -> None:
            self.order.append("quick_stop")
            stop()

        def sealed(run_id: str) -> Any:
            self.order.append("seal")
            return seal(run_id)

        monkeypatch.setattr(rig, "quick_stop", quick_stop)
        monkeypatch.setattr(store, "_seal", sealed)


class _LoopBug(Exception):
    pass


def test_an_exception_mid_run_quick_stops_before_the_data_are_sealed(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    store = RunStore(tmp_path / "home")
    rig = SimRig(sim_config())
    recorder = _Recorder(rig, store, monkeypatch)
    blocks: list[int] = []

    def on_block(run_id: str, block: Block) -> None:
        blocks.append(len(block["t"]))
        if len(blocks) == 3:  # mid-program, the drive enabled and moving
            raise _LoopBug("a bug in a block consumer")

    with pytest.raises(_LoopBug):
        run_experiment("speed-sweep", rig.config, store=store, rig=rig, hooks=RunHooks(on_block=on_block))

    assert recorder.order[:2] == ["quick_stop", "seal"], recorder.order
    (entry,) = store.list_runs()
    assert entry["status"] == RunStatus.ABORTED
    assert entry["reason"] == "aborted: a bug in a block consumer"
    assert entry["samples"] == sum(blocks)  # every block handed out was kept
    assert np.all(np.diff(store.read(entry["id"]).t) > 0)
