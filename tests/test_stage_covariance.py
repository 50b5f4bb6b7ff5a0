"""The staged identification's standard errors: the sandwich over contiguous batches for correlated
residuals (`covariance(serial=True)`), and a held parameter's errors carried into a stage's
(`carry_held`, the delta method of two-step estimates).

Each figure is derived from the equations of the noise or of the least squares; the Monte Carlo
tolerances are the sampling error of 300 replicas' standard deviation (±4 % at 1σ) plus the batch
estimator's own bias, stated per test.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from rig.analysis.identification.dynamics_stage import Held, Solved, carry_held, covariance, nonlinear_fit

SAMPLES = 20_000
REPLICAS = 300


def _spread_and_reported(noise: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fit [1, x, x²] to each replica's noise (the truth is 0): the estimates' spread over replicas and
    the median standard error `covariance(serial=True)` reports."""
    x = np.linspace(-1.0, 1.0, noise.shape[1])
    design = np.column_stack([np.ones_like(x), x, x**2])
    estimates, reported = [], []
    for e in noise:
        beta = np.linalg.lstsq(design, e, rcond=None)[0]
        estimates.append(beta)
        reported.append(np.sqrt(np.diag(covariance(design, e - design @ beta, serial=True))))
    return np.std(estimates, axis=0), np.median(reported, axis=0)


def test_a_current_chattering_about_its_mean_narrows_the_errors():
    """e = w + (v_t − v_{t−1}) with σ_w = 0.1, σ_v = 1: the samples' variance is 2.01, but the long-run
    variance (what a mean over many samples sees) is σ_w² = 0.01: white-noise errors would be √201 ≈
    14× too wide. The batch sums see 1000·0.01 + 2 per batch of 1000: ≤ 10 % wide (+ sampling 4 %)."""
    rng = np.random.default_rng(7)
    v = rng.standard_normal((REPLICAS, SAMPLES + 1))
    noise = 0.1 * rng.standard_normal((REPLICAS, SAMPLES)) + np.diff(v, axis=1)
    spread, reported = _spread_and_reported(noise)
    assert np.all(reported / spread > 0.88), reported / spread
    assert np.all(reported / spread < 1.2), reported / spread


def test_slow_correlated_noise_widens_the_errors():
    """AR(1) with φ = 0.9: the long-run variance is (1 + φ)/(1 − φ) = 19× the samples' (errors 4.4×
    wider than white noise's). Its correlation time (10 samples) is short beside a batch (1000), so
    the batch sums are nearly independent: within 12 %."""
    rng = np.random.default_rng(8)
    white = rng.standard_normal((REPLICAS, SAMPLES))
    noise = np.empty_like(white)
    noise[:, 0] = white[:, 0] / math.sqrt(1 - 0.81)
    for i in range(1, SAMPLES):
        noise[:, i] = 0.9 * noise[:, i - 1] + white[:, i]
    spread, reported = _spread_and_reported(noise)
    assert np.all(np.abs(reported / spread - 1.0) < 0.12), reported / spread


def test_white_noise_keeps_the_classical_errors():
    rng = np.random.default_rng(9)
    spread, reported = _spread_and_reported(rng.standard_normal((REPLICAS, SAMPLES)))
    assert np.all(np.abs(reported / spread - 1.0) < 0.1), reported / spread


def test_a_held_parameter_carries_its_error_into_the_fitted_one():
    """y = a·x + h·z + noise, a fitted with h held at ĥ ± σ_h: â moves by −(xᵀz/xᵀx)·δh, so its
    variance grows by (xᵀz/xᵀx)²·σ_h² (exact: the residual is linear in both)."""
    rng = np.random.default_rng(3)
    x = rng.standard_normal(500)
    z = 0.6 * x + rng.standard_normal(500)
    y = 2.0 * x + 0.5 * z + 0.01 * rng.standard_normal(500)
    h_hat, sigma_h = 0.48, 0.02
    a_hat = float(x @ (y - h_hat * z) / (x @ x))
    own = 0.001
    solved = Solved()
    solved.put("a", a_hat, own)
    carry_held(
        solved,
        lambda v: y - v["a"] * x - v["h"] * z,
        Held(["h"], np.array([h_hat]), np.array([[sigma_h**2]])),
    )
    expected = math.sqrt(own**2 + (x @ z / (x @ x)) ** 2 * sigma_h**2)
    assert solved.std_errors["a"] == pytest.approx(expected, rel=1e-9)
    assert solved.values["a"] == a_hat


def test_correlated_held_parameters_carry_their_covariance():
    """Two held parameters with correlation −0.9 whose effects on the fit cancel: their carried
    variance is gᵀΣg with the covariance, far below the sum of the two alone."""
    rng = np.random.default_rng(4)
    x = rng.standard_normal(400)
    z1 = 0.5 * x + rng.standard_normal(400)
    z2 = 0.5 * x + rng.standard_normal(400)
    cov = np.array([[1.0, -0.9], [-0.9, 1.0]]) * 1e-4
    solved = Solved()
    solved.put("a", 1.0, 0.0)
    carry_held(
        solved,
        lambda v: -v["a"] * x - v["h1"] * z1 - v["h2"] * z2,
        Held(["h1", "h2"], np.array([0.3, 0.3]), cov),
    )
    g = -np.array([x @ z1, x @ z2]) / (x @ x)
    assert solved.std_errors["a"] == pytest.approx(math.sqrt(g @ cov @ g), rel=1e-9)
    assert solved.std_errors["a"] < 0.5 * math.sqrt(g**2 @ np.diag(cov))


def _line_fit_coverage(points: int, replicas: int, seed: int) -> float:
    """Share of replicas of y = 1 + 2·x + N(0, 0.1²) at `points` points whose ±1σ of the slope (from
    `nonlinear_fit`) holds the truth."""
    rng = np.random.default_rng(seed)
    x = np.linspace(0.0, 1.0, points)
    covered = 0
    for _ in range(replicas):
        y = 1.0 + 2.0 * x + 0.1 * rng.standard_normal(points)
        solved = nonlinear_fit(lambda p, y=y: p[0] + p[1] * x - y, ["a", "b"], [0.5, 1.0], [1.0, 1.0])
        covered += abs(solved.values["b"] - 2.0) <= solved.std_errors["b"]
    return covered / replicas


def test_few_degrees_of_freedom_still_cover_68_percent():
    """Four points, two parameters: the slope's error over s²-based σ follows t₂, and ±1σ would cover
    P(|t₂| ≤ 1) = 57.7 %; widened by t₂(84.1 %) = 1.32 it covers 68.3 %. 1500 replicas: binomial sd
    1.2 points, tolerance 4 sd."""
    assert _line_fit_coverage(4, 1500, 11) == pytest.approx(0.683, abs=0.048)


def test_no_degree_of_freedom_left_is_no_standard_error():
    """Two points, two parameters: the line passes through both, the residual is zero and says nothing
    of the noise: the standard errors are infinite, not zero (a zero would count as determined)."""
    x = np.array([0.0, 1.0])
    solved = nonlinear_fit(
        lambda p: p[0] + p[1] * x - np.array([1.0, 3.1]), ["a", "b"], [0.0, 0.0], [1.0, 1.0]
    )
    assert solved.values["b"] == pytest.approx(2.1, rel=1e-6)
    assert math.isinf(solved.std_errors["a"]) and math.isinf(solved.std_errors["b"])
