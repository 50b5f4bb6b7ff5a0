"""Issue 25 items 1, 2, 5, 6: `fit` without metadata on a flexible closed-loop record of the independent
generator (hdrig_testing.independent_plant: its own integrator, 14-bit encoder, voltage-mode PI), the
issue's gear: the seed with J_m ×1.3, s3 ×0.8, K_s ×0.7, J_l ×1.2 and a load Coulomb friction of 2.16 N·m
(f_sl at the seed's ratio). The 20 drawn gears are bench/bench_fit_drawn.py's (docs/BENCHMARKS.md)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hdrig_testing.independent_plant import IndependentRig, lab_profile
from model.errors import UserInputError
from model.params import load_model
from model.run import Run
from rig.analysis.fit.parameters import get_values, with_values
from rig.analysis.fit.trajectory import emf_lag_inertia, with_lifted_static
from rig.analysis.identification import identify
from rig.analysis.identification.column_stage import two_sided_start

TRUTH = {"J_m": 7.15e-5, "s3": 0.0576, "K_s": 700.0, "J_l": 0.24, "f_cl": 2.16, "f_sl": 2.52}
DURATION_S = 16.0
STEP_NM = 7.55  # 25 % of K_m·10 A reflected through r = 0.01, as bench_fit_drawn's profile


@pytest.fixture(scope="module")
def lab_record() -> Run:
    """16 s of the lab profile at 1 kHz, a +7.55 N·m load step at 13.2–13.9 s and −7.55 N·m at
    14.6–15.3 s (the issue's 38–40 s and 42–44 s of 46 s, scaled); columns t, u, tau_ext, θ_m, θ_l, i_a."""
    truth = with_values(load_model("seed"), TRUTH)
    speed, _ = lab_profile(DURATION_S)
    t = np.arange(len(speed)) / 1000.0
    at = DURATION_S / 46.0
    load = STEP_NM * (((t >= 38 * at) & (t < 40 * at)).astype(float) - ((t >= 42 * at) & (t < 44 * at)))
    run = IndependentRig(truth, drive="voltage", seed=5).record(speed, load)
    return Run({c: run[c] for c in ("t", "u", "tau_ext", "theta_m", "theta_l", "i_a")}, {}).validate()


def test_a_load_coulomb_level_above_the_held_static_level_lifts_it():
    """f_cl 2.16 past the seed's f_sl 0.35 (the schema wants f_sl ≥ f_cl): f_sl follows it, which was a
    wall the fit sat on before (f_cl 0.349, σ 8.8e-9); below f_sl nothing else changes."""
    seed = load_model("seed")
    lifted = with_lifted_static(seed, {"f_cl": 2.16})
    assert get_values(lifted, ["f_cl", "f_sl"]) == {"f_cl": 2.16, "f_sl": 2.16}
    assert get_values(with_lifted_static(seed, {"f_cl": 0.2}), ["f_sl"]) == {"f_sl": 0.35}
    with pytest.raises(UserInputError):
        with_lifted_static(seed, {"J_m": -1.0})


def test_the_back_emf_lag_inertia_is_k_m_k_b_over_r_times_half_the_step():
    """0.0302 · 0.0302 / 0.299 · 1e-4 s / 2 = 1.5251e-7 kg·m² on the seed (0.28 % of its J_m)."""
    assert emf_lag_inertia(load_model("seed"), 1e-4) == pytest.approx(
        0.0302 * 0.0302 / 0.299 * 1e-4 / 2, rel=1e-12
    )


def test_the_two_sided_least_squares_lands_near_the_load_side(lab_record: Run):
    """The load equation alone (τ_ext = K_s·δ − J_l·α_l − f_cl·sgn ω_l − b_l·ω_l, 50 Hz zero-phase filter)
    from the seed's values: K_s, J_l, f_cl within 5 % (one 16 s record; on the 46 s one they came within
    0.3 %), J_m within 15 % (its equation carries the motor's position ripple, held at the seed's)."""
    start = two_sided_start(lab_record, load_model("seed"))
    assert start is not None
    for name, tol in {"K_s": 0.05, "J_l": 0.05, "f_cl": 0.05, "J_m": 0.15}.items():
        assert start[name][0] == pytest.approx(TRUTH[name], rel=tol), (name, start[name])


def test_the_issue_gear_is_fitted_from_the_seed_within_10_percent_and_10_sigma(lab_record: Run):
    """The issue's case (f_cl −84 % at 2×10⁸ σ, b_l ×40 before): from the seed, K_s, J_l, s3 and f_cl
    within 10 % of the truth, and no determined parameter farther than 10 of its σ from it."""
    result = identify([lab_record], load_model("seed"))
    rows = {row.name: row for row in result.parameters}
    for name in ("K_s", "J_l", "s3", "f_cl"):
        assert rows[name].estimate == pytest.approx(TRUTH[name], rel=0.10), (name, rows[name])
    truth = get_values(with_values(load_model("seed"), TRUTH), ["J_m", "J_l", "K_s", "s3", "f_cl", "b_l"])
    for name, want in truth.items():
        row = rows[name]
        if row.identifiable and row.uncertainty is not None:
            z = abs(row.estimate - want) / row.uncertainty
            assert z <= 10.0, (name, row.estimate, want, row.uncertainty)
    assert result.fit_error_after < 0.1 * result.fit_error_before
    assert not math.isnan(result.fit_error_after)
