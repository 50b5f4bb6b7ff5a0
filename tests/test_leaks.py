"""No handle or memory leak per job: twenty fits in a row leave the process's descriptors and memory
where the first fits left them (issue 23 item 9: each fit left 3 descriptors on the deleted temporary
catalog of its validation, `hdrig-validation-*/catalog.sqlite`, `-wal`, `-shm`).

The fits run in a fresh interpreter (this file run as a script): in the test session's own process the
threads and arenas that earlier tests left behind move the resident size by a hundred megabytes either
way, which says nothing about the fits.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

FITS = 20
WARM_UP_FITS = 5  # imports, compiled kernels, font and plot caches come with the first fits
# Measured in a fresh interpreter after 5 warm-up fits: RSS +6 MB over the next 25 fits, levelling off
# (the allocator's arenas; Python's own heap grew 0.04 MB). A leak of a megabyte a fit would break it.
RSS_SLACK_BYTES = 16 * 1024 * 1024
REPO = Path(__file__).resolve().parents[1]


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
        return int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def measure(folder: Path) -> dict[str, Any]:
    """One step run, then WARM_UP_FITS + FITS fits of it; the descriptors and RSS around the last FITS."""
    from rig.config import load_rig_config
    from rig.core import actions
    from rig.runner import run_experiment
    from rig.store.runs import RunStore

    store = RunStore(folder / "home")
    config = load_rig_config("configs/rigs/sim.yaml").model_copy(update={"pace": "virtual"})
    step = run_experiment("step", config, {}, store)  # a validation experiment: the fit replays it
    assert step.status == "complete", step.reason
    validated = []
    for n in range(WARM_UP_FITS + FITS):
        if n == WARM_UP_FITS:
            fds_before, rss_before = descriptors(), rss_bytes()
        document = actions.fit([step.run_id], "seed", store, report_dir=folder / f"report-{n}")
        validated.append(bool(document.validation))
    return {
        "validated": validated,
        "fds_before": fds_before,
        "fds_after": descriptors(),
        "rss_grown_bytes": rss_bytes() - rss_before,
    }


@pytest.mark.skipif(not Path("/proc/self/fd").is_dir(), reason="reads /proc (Linux)")
def test_twenty_fits_leak_no_descriptor_and_no_memory(tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if k not in ("HDRIG_CATALOG", "HDRIG_DATA")}
    child = subprocess.run(
        [sys.executable, __file__, str(tmp_path)], cwd=REPO, env=env, capture_output=True, text=True
    )
    assert child.returncode == 0, child.stderr
    found = json.loads(child.stdout.splitlines()[-1])
    assert all(found["validated"]), "a fit ran no validation: this test would test nothing"
    on_deleted_catalogs = [d for d in found["fds_after"] if "catalog.sqlite" in d and d.endswith("(deleted)")]
    assert not on_deleted_catalogs, on_deleted_catalogs
    # Exactly flat: a leak of one descriptor per fit would show as 20.
    assert len(found["fds_after"]) == len(found["fds_before"]), sorted(found["fds_after"])
    grown = found["rss_grown_bytes"]
    assert grown < RSS_SLACK_BYTES, f"RSS grew {grown / 2**20:.1f} MiB over {FITS} fits"


if __name__ == "__main__":
    sys.path.insert(0, str(REPO))
    print(json.dumps(measure(Path(sys.argv[1]))))
