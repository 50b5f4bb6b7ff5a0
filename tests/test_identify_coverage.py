"""The identification's reported uncertainty means what it says: over repeated noisy runs the estimates
scatter about the truth by their 1σ.

Truth: the seed model. Runs: the same experiment on the sim rig's sensors (17-bit encoder, 5 mA current
noise, 2 µrad output noise), only the sensor-noise seed changed. For an unbiased estimate with an honest
σ, z = (estimate − truth)/σ is N(0, 1) and independent seed to seed, so Σz² over N seeds follows χ²
with N degrees of freedom. The test takes the central 99.8 % of that law (chi2.ppf at 0.001 and 0.999):
above it the σ is overconfident or the estimate biased (the motor stage's former R bias, −0.36 % at a
σ of 0.02 %, gives Σz² ≈ 2,600 over 8 seeds); below it the σ is inflated (a σ 2.5× too large puts Σz² of
8 seeds under 1.3 most of the time, beside the bound's 1.24 — so the lower bound only catches gross
inflation). The seeds are fixed: the outcome does not vary from run to run.
"""

from __future__ import annotations

import pytest
from scipy.stats import chi2

from model.fit.parameters import get_values
from model.params import HarmonicDriveModel
from model.run import Run
from rig.config import load_rig_config
from rig.identification.dynamics_stage import motor_constants
from rig.runner import run_experiment
from rig.store import RunStore
from sim_backend.inprocess import SimRig

SEEDS = range(1, 9)
"""Eight pulse runs of 4.2 s each: ~1 s of simulation apiece."""
TAIL = 0.001


def sum_z2_bounds(n: int) -> tuple[float, float]:
    """The central 1 − 2·TAIL interval of χ² with n degrees of freedom."""
    return float(chi2.ppf(TAIL, n)), float(chi2.ppf(1 - TAIL, n))


@pytest.fixture(scope="module")
def pulses(seed: HarmonicDriveModel, tmp_path_factory: pytest.TempPathFactory) -> list[Run]:
    store = RunStore(tmp_path_factory.mktemp("pulses"))
    runs = []
    for noise_seed in SEEDS:
        config = load_rig_config("sim")
        config = config.model_copy(update={"sensors": config.sensors.model_copy(update={"seed": noise_seed})})
        outcome = run_experiment("pulse", config, {}, store, rig=SimRig(config, model=seed))
        assert outcome.status == "complete", outcome.reason
        runs.append(store.read(outcome.run_id))
    return runs


@pytest.mark.parametrize("name", ["R", "K_b"])
def test_motor_constants_scatter_by_their_sigma(pulses: list[Run], seed: HarmonicDriveModel, name: str):
    truth = get_values(seed, [name])[name]
    z = []
    for run in pulses:
        solved = motor_constants([run])
        z.append((solved.values[name] - truth) / solved.std_errors[name])
    low, high = sum_z2_bounds(len(z))
    total = sum(v * v for v in z)
    assert low <= total <= high, (
        f"{name}: Σz² = {total:.3g} over {len(z)} seeds, χ² bounds {low:.3g}..{high:.3g}; z = {[round(v, 2) for v in z]}"
    )
