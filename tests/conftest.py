"""Shared fixtures: the presets."""

from __future__ import annotations

import pytest

from model.params import HarmonicDriveModel, load_model


@pytest.fixture(scope="session")
def seed() -> HarmonicDriveModel:
    return load_model("seed")


@pytest.fixture(scope="session")
def seed_rigid() -> HarmonicDriveModel:
    return load_model("seed-rigid")
