"""No handle or memory leak per job: twenty fits in a row leave the process's descriptors and memory
where the first fits left them (issue 23 item 9: each fit left 3 descriptors on the deleted temporary
catalog of its validation, `hdrig-validation-*/catalog.sqlite`, `-wal`, `-shm`)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from rig.config import load_rig_config
from rig.core import actions
from rig.runner import run_experiment
from rig.store import RunStore

FITS = 20
WARM_UP_FITS = 5  # imports, compiled kernels, font and plot caches come with the first fits
PAGE_BYTES = os.sysconf("SC_PAGE_SIZE")


def descriptors() -> list[str]:
    found = []
    for fd in os.listdir("/proc/self/fd"):
        try:
            found.append(os.readlink(f"/proc/self/fd/{fd}"))
        except OSError:  # listdir's own descriptor, gone by now
            continue
    return found


def rss_bytes() -> int:
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * PAGE_BYTES


@pytest.mark.skipif(not Path("/proc/self/fd").is_dir(), reason="reads /proc (Linux)")
def test_twenty_fits_leak_no_descriptor_and_no_memory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("HDRIG_CATALOG", raising=False)
    monkeypatch.delenv("HDRIG_DATA", raising=False)
    store = RunStore(tmp_path / "home")
    config = load_rig_config("configs/rigs/sim.yaml").model_copy(update={"pace": "virtual"})
    step = run_experiment("step", config, {}, store)  # a validation experiment: the fit replays it
    assert step.status == "complete", step.reason

    def fit(n: int) -> None:
        document = actions.fit([step.run_id], "seed", store, report_dir=tmp_path / f"report-{n}")
        assert document.validation, "the fit ran no validation: this test would test nothing"

    for n in range(WARM_UP_FITS):
        fit(n)
    fds_before, rss_before = len(descriptors()), rss_bytes()
    for n in range(FITS):
        fit(WARM_UP_FITS + n)
    on_deleted_catalogs = [d for d in descriptors() if "catalog.sqlite" in d and d.endswith("(deleted)")]
    assert not on_deleted_catalogs, on_deleted_catalogs
    # Exactly flat: a leak of one descriptor per fit would show as 20.
    assert len(descriptors()) == fds_before, sorted(descriptors())
    # Measured after 5 warm-up fits: RSS +6 MB over the next 25 fits, levelling off (the allocator's
    # arenas; Python's own heap grew 0.04 MB). A leak of a megabyte a fit would break this bound.
    grown = rss_bytes() - rss_before
    assert grown < RSS_SLACK_BYTES, f"RSS grew {grown / 2**20:.1f} MiB over {FITS} fits"


RSS_SLACK_BYTES = 16 * 1024 * 1024
