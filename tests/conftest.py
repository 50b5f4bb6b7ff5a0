"""Shared fixtures: the presets, and the heap policy of a process that runs a control loop."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from model.params import HarmonicDriveModel, load_model
from rig import realtime

# The fleet's real parts on loopback: PostgreSQL, an S3 API, a Dask LocalCluster (skipped, or failed in CI).
pytest_plugins = ["hdrig_testing.fleet_fixtures"]


@pytest.fixture(scope="session")
def seed() -> HarmonicDriveModel:
    return load_model("seed")


@pytest.fixture(scope="session")
def seed_rigid() -> HarmonicDriveModel:
    return load_model("seed-rigid")


@pytest.fixture(scope="module")
def quiet_heap() -> Iterator[None]:
    """The heap frozen for the module's tests (`rig.realtime.quiet_heap`), as the command line's `run`
    freezes it for its process: for tests whose rig holds a 1 kHz SYNC grid in this process, where a
    full collection of the heap would stall the loop long enough to time out the drive."""
    with realtime.quiet_heap():
        yield
