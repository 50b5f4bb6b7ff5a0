"""The heap policy of a process that runs a control loop (`rig.realtime.quiet_heap`)."""

from __future__ import annotations

import gc

from rig.realtime import quiet_heap


def test_the_heap_stays_frozen_until_the_last_entry_leaves() -> None:
    assert gc.get_freeze_count() == 0
    with quiet_heap():
        frozen = gc.get_freeze_count()
        assert frozen > 0
        built_since = [[n] for n in range(1000)]  # a rig opened inside the outer entry, say
        with quiet_heap():
            assert gc.get_freeze_count() >= frozen + len(built_since)  # the inner entry takes them in
        assert gc.get_freeze_count() > 0  # the outer entry still holds
    assert gc.get_freeze_count() == 0  # handed back to the collector


def test_the_heap_is_handed_back_when_the_loop_fails() -> None:
    try:
        with quiet_heap():
            raise RuntimeError("the loop failed")
    except RuntimeError:
        pass
    assert gc.get_freeze_count() == 0
