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

import importlib
import math

import campaign
import numpy as np
import pytest
from scipy.stats import chi2
from test_replay_continuous import FLOOR

from model.params import HarmonicDriveModel
from model.run import Run
from rig.analysis.fit.parameters import get_values, with_values
from rig.analysis.fit.trajectory import (
    ParameterEstimate,
    TrajectoryFit,
    fit_trajectories,
    window_robust_covariance,
)
from rig.analysis.identification.dynamics_stage import motor_constants
from rig.analysis.identification.identify import (
    JOINT_EXPERIMENTS,
    JOINT_WINDOW_S,
    _breakaway_start,
    _grid_jackknife,
    _sigma_backed_by_cost,
    disagreement_scales,
)
from rig.config import load_rig_config
from rig.runner import run_experiment
from rig.store.runs import RunStore
from sim_backend.inprocess import SimRig

identify_module = importlib.import_module("rig.analysis.identification.identify")
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
        f"{name}: Σz² = {total:.3g} over {len(z)} seeds, χ² bounds {low:.3g}..{high:.3g};"
        f" z = {[round(v, 2) for v in z]}"
    )


def test_the_joint_sigma_widens_by_the_disagreement_of_the_two_methods():
    # Consistent within their σ: unchanged. Apart by 3 of their combined σ: scaled by 3.
    assert disagreement_scales({"K_s": (1000.0, 1.0)}, {"K_s": (1001.0, 1.0)}) == {"K_s": 1.0}
    scale = disagreement_scales({"K_s": (1000.0, 0.6)}, {"K_s": (1003.0, 0.8)})["K_s"]
    assert scale == pytest.approx(3.0)


def test_scaled_sigma_covers_a_combination_with_one_biased_method():
    """Two measurements of one value, σ = 1 each, one biased by 3σ (as the breakaway stage's static_factor
    is beside the trajectories'): their weighted mean is off by 1.5 at a σ of 0.71, RMS z 2.3 and 1σ
    covering the truth 13 % of the time. Scaled by the Birge ratio of the one gap seen, RMS z is 1.41 and
    the coverage 50 % over these 2,000 draws: better, not whole (a ratio from a single gap is itself
    noisy). Bounds 1.5 and 45 %: a scaling that did nothing, or half as much, fails them."""
    rng = np.random.default_rng(7)
    draws = 2000
    staged = 3.0 + rng.standard_normal(draws)
    trajectories = rng.standard_normal(draws)
    combined = 0.5 * (staged + trajectories)
    sigma = np.full(draws, np.sqrt(0.5))
    scale = np.array(
        [
            disagreement_scales({"x": (s, 1.0)}, {"x": (t, 1.0)})["x"]
            for s, t in zip(staged, trajectories, strict=True)
        ]
    )
    plain = combined / sigma
    scaled = combined / (sigma * scale)
    assert np.sqrt(np.mean(plain**2)) > 2.0  # the case the scaling is for
    assert np.sqrt(np.mean(scaled**2)) < 1.5
    assert np.mean(np.abs(scaled) <= 1.0) > 0.45


def test_window_sigma_covers_a_parameter_few_windows_see():
    """A linear fit whose third parameter only 3 of 40 windows see (as a few windows of sharp accelerations
    carry up to 15–19 % of J_m's and J_l's information on the bench campaign each): every window's error
    is one smooth curve (a random offset and drift, as a noisy start state makes) plus white noise. Those
    3 windows pull the fit towards themselves, and the plain window-clustered sandwich, from residuals at
    the optimum, gives the third parameter a σ that covers the truth 47.6 % of the time over these 2,000
    draws (RMS z 1.95). Leaving each window out (the cluster jackknife) gives 65.6 % — its σ comes from 3
    windows' scatter, so z has heavy tails (RMS 1.44) — and leaves the evenly seen parameters at
    67–68 %. Bounds: 60 % for the third (the plain sandwich fails it), 63–73 % for the others (4.5 binomial
    σ of 2,000 draws about 68 %: over-conservative would fail too)."""
    rng = np.random.default_rng(7)
    windows, per = 40, 25
    groups = np.repeat(np.arange(windows), per)
    t = np.tile(np.linspace(0.0, 1.0, per), windows)
    few = np.isin(groups, [3, 17, 29])
    jac = np.column_stack(
        [np.ones(windows * per), t, np.where(few, t**2 * rng.uniform(0.5, 2.0, windows)[groups], 0.0)]
    )
    z = []
    for _ in range(2000):
        error = (
            rng.normal(0, 1, windows)[groups]
            + rng.normal(0, 1, windows)[groups] * t
            + 0.3 * rng.normal(0, 1, windows * per)
        )
        estimate, *_ = np.linalg.lstsq(jac, error, rcond=None)  # the truth is 0
        cov = window_robust_covariance(jac, error - jac @ estimate, groups, 1.0)
        z.append(estimate / np.sqrt(np.diag(cov)))
    covered = np.mean(np.abs(np.array(z)) <= 1.0, axis=0)
    assert covered[2] > 0.60
    assert np.all((covered[:2] > 0.63) & (covered[:2] < 0.73))


@pytest.fixture(scope="module")
def ideal_joint_runs(seed: HarmonicDriveModel, tmp_path_factory: pytest.TempPathFactory) -> list[Run]:
    """The joint step's experiments (pulse, step, sine) on the sim rig with ideal sensors: no encoder
    quantization, no current or output-sensor noise. The plant integrates at 1e-4 s, as the replay does."""
    store = RunStore(tmp_path_factory.mktemp("ideal"))
    config = load_rig_config("sim")
    ideal = {"encoder_counts_per_rev": 0, "current_noise_a": 0.0, "load_sensor_noise_rad": 0.0}
    config = config.model_copy(update={"sensors": config.sensors.model_copy(update=ideal)})
    assert config.sim_dt_s == 1e-4
    return campaign.play(JOINT_EXPERIMENTS, config, seed, store)


@pytest.mark.parametrize("name", ["J_m", "J_l"])
def test_inertias_from_trajectories_of_ideal_sensors_are_unbiased(
    ideal_joint_runs: list[Run], seed: HarmonicDriveModel, name: str
):
    """With every other parameter true and nothing measured imperfectly, the trajectory fit's only
    error is its own: the replay's step, and the windows' starting states. The replay integrates at the
    plant's step, so what is left is how the windows start. Starting each window with the speed at its
    first position's instant (not half a replay step earlier, where the semi-implicit Euler holds it)
    gave J_l +0.18 % at a σ of 0.021 % (9σ) and J_m +0.13 % at 0.042 % (3.2σ); with the lag, −0.000 %
    at 0.011 % and −0.015 % at 0.021 % (0.7σ), from 11-sample starting speeds. From 5-sample ones
    (`rig.analysis.fit.trajectory.SMOOTHING_WINDOW_S`), J_l −0.0105 % at 0.0028 %, J_m −0.0017 % at 0.0076 %.
    Bound: 3 of the fit's own σ (its σ here comes from the smoothed starting speeds' error alone, the
    only imperfection left), and not under `FLOOR` (tests/test_replay_continuous.py: under half the σ
    the rig's noisy sensors give; the lag's error is 9× it)."""
    truth = get_values(seed, [name])[name]
    fit = fit_trajectories(seed, ideal_joint_runs, ["J_m", "J_l"], window_s=JOINT_WINDOW_S)
    estimate = next(p for p in fit.parameters if p.name == name)
    assert estimate.identifiable and estimate.std_error is not None, estimate.note
    error = estimate.estimate - truth
    assert abs(error) <= max(3 * estimate.std_error, FLOOR * truth), (
        f"{name}: {100 * error / truth:+.4f} % at σ {100 * estimate.std_error / truth:.4f} %"
    )


def _noise() -> np.ndarray:
    noise = np.random.default_rng(3).standard_normal(1000)
    noise[0] = 0.0
    return noise


NOISE_S = math.sqrt(float(_noise() @ _noise()) / (1000 - 1))
"""s, the residual's per-row RMS at the optimum as the check computes it (1000 rows, 1 parameter)."""


class _OneParameterCost:
    """A stand-in for a TrajectoryProblem whose residual is fixed noise n plus g(x) on a row n is zero
    on: the sum of squares is n·n + g(x)², so the rise from the optimum (g = 0) is g(x)² exactly."""

    def __init__(self, g):
        self.names = ["f_cl"]
        self.noise = _noise()
        self.g = g
        self.nuisance = 0  # no window's start is free

    def model_with(self, values):
        return values

    def residuals_of(self, model):
        r = self.noise.copy()
        r[0] = self.g(model["f_cl"])
        return r


def _checked(g, estimate: float, sigma: float):
    problem = _OneParameterCost(g)
    p = ParameterEstimate("f_cl", estimate, estimate, sigma, True)
    fit = TrajectoryFit({"f_cl": estimate}, [p], 1.0, 1.0, 1000, profile_direction={"f_cl": {"f_cl": 1.0}})  # type: ignore[arg-type]
    fit.curvature_sigma = {"f_cl": sigma}  # white rows: the reported σ is the curvature's
    notes: list = []
    _sigma_backed_by_cost(problem, fit, notes)  # type: ignore[arg-type]
    s = math.sqrt(float(problem.noise @ problem.noise) / (1000 - 1))
    return p, notes, s


def test_a_sigma_the_cost_backs_on_both_sides_is_kept():
    # A parabola of exactly that σ: the rise at ±3σ and ±9σ is 9·s² and 81·s², what the check asks.
    s = NOISE_S
    p, notes, _ = _checked(lambda x: (x - 0.3) / 0.002 * s, 0.3, 0.002)
    assert p.identifiable and p.std_error == pytest.approx(0.002, rel=1e-9)
    assert notes == []


def test_a_cost_flat_on_one_side_leaves_the_parameter_undetermined():
    # Flat below the optimum (the drawn gear 2's static_factor below 1), steep above: the σ of the
    # steep side alone is no σ; the reason names the flat side.
    p, notes, _ = _checked(lambda x: max(x - 0.3, 0.0) * 1e4, 0.3, 0.002)
    assert not p.identifiable and p.std_error is None
    assert "−3σ" in p.note and "one-sided" in p.note
    assert notes and "f_cl undetermined" in notes[0].text


def test_a_cost_that_stops_rising_past_a_stair_widens_sigma():
    # A stair's edge at the optimum, then a plateau to 9σ, then a parabola three times wider: the rise
    # at ±3σ is what a parabola of σ gives (9·s²), at ±9σ still 9·s² (not 81·s²: the walk goes on), at
    # ±27σ 81·s² (9× the 9σ rise: it stops). The half-width at which the rise reaches k²·s² is 3σ at
    # 9σ and at 27σ: σ ×3, not ×9 as a plateau without end would give.
    s = NOISE_S

    def g(x: float) -> float:
        return 0.0 if x == 0.3 else s * max(3.0, abs(x - 0.3) / 0.006)

    p, notes, _ = _checked(g, 0.3, 0.002)
    assert p.identifiable and p.std_error == pytest.approx(0.006, rel=1e-6)
    assert notes and "f_cl ×3" in notes[0].text


class _CurvedValleyCost:
    """Two parameters: `name` (x) and b_l (y). The residual is fixed noise n plus two rows n is zero on:
    g(x), and (y − c(x))/ε·s, a valley whose floor c bends away from the straight line the linearized
    profile walks (c'(x̂) = 0). Re-fitting y puts the second row at zero: the real profile of x is g(x)²."""

    def __init__(self, name: str, g, c, eps: float):
        self.names = [name, "b_l"]
        self.noise = np.random.default_rng(3).standard_normal(1000)
        self.noise[:2] = 0.0
        self.g, self.c, self.eps = g, c, eps
        self.nuisance = 0  # no window's start is free
        self.window_of_residual = np.repeat(np.arange(250), 4)  # windows of 4 rows
        self.block_sigma = False
        self.diff_step = 1e-2

    def model_with(self, values):
        return values

    def residuals_of(self, model):
        r = self.noise.copy()
        x = model[self.names[0]]
        r[0] = self.g(x)
        r[1] = (model["b_l"] - self.c(x)) / self.eps * self._s
        return r

    @property
    def _s(self) -> float:
        return math.sqrt(float(self.noise @ self.noise) / (1000 - 2))


def _checked_in_a_valley(name: str, x: float, sigma: float, g, c):
    problem = _CurvedValleyCost(name, g, c, 0.001)
    p = ParameterEstimate(name, x, x, sigma, True)
    q = ParameterEstimate("b_l", 1.0, 1.0, 0.001, True)  # its own cost: a parabola of exactly that σ
    fit = TrajectoryFit(
        {name: x, "b_l": 1.0},  # type: ignore[arg-type]  # the stand-in problem takes values
        [p, q],
        1.0,
        1.0,
        1000,
        profile_direction={name: {name: 1.0, "b_l": 0.0}, "b_l": {name: 0.0, "b_l": 1.0}},
    )
    fit.curvature_sigma = {name: sigma, "b_l": 0.001}  # white rows: the reported σ is the curvature's
    notes: list = []
    _sigma_backed_by_cost(problem, fit, notes)  # type: ignore[arg-type]
    return p, q, problem._s


def test_a_breakaway_level_is_profiled_with_the_others_refitted(monkeypatch: pytest.MonkeyPatch):
    # The profile alone: this stand-in's one informative row sits in one window, and the jackknife
    # (left out, nothing determines it) would rightly call it undetermined (tested on its own below).
    monkeypatch.setattr(identify_module, "_grid_jackknife", lambda *args: 0.0)
    # static_factor (a breakaway level: re-fitted from the start) at 1.05 ± 0.005: a parabola of that σ
    # above, a stair of 2σ below and flat past it (gear 2's shape: the truth 0.76 costs about what 0.95
    # does). The others' valley bends (c = 1 + 1e4·(x − 1.05)², ε = 0.001): along the straight line
    # (b_l held) −3σ already costs (1e4·0.015²/0.001)² = 2250² s², so the former check kept σ. With b_l
    # re-fitted the rise is 4·s² at every k below: the walk goes on by ×3 while the profile is flat, to
    # 81σ (the last before 0); the half-width at which 4·s² reaches 81²·s² is 81/2 σ: σ ×40.5.
    s0 = 0.005

    def g(x: float) -> float:
        s = _CurvedValleyCost("static_factor", None, None, 1.0)._s
        return s * ((x - 1.05) / s0 if x >= 1.05 else min((1.05 - x) / s0, 2.0))

    p, q, _ = _checked_in_a_valley("static_factor", 1.05, s0, g, lambda x: 1.0 + 1e4 * (x - 1.05) ** 2)
    assert p.identifiable and p.std_error == pytest.approx(40.5 * s0, rel=1e-6)
    assert q.identifiable and q.std_error == pytest.approx(0.001, rel=1e-6)  # a parabola: kept


def test_a_straight_walk_that_flattens_then_climbs_a_wall_is_profiled():
    # f_cl (no breakaway level) at 0.3 ± 0.002: a parabola above; below a stair of 3σ then flat. The
    # valley bends as (x − 0.3)⁴ (0.006·((x − 0.3)/0.018)⁴, ε = 0.001): on the straight line the rises
    # below are 9.0055·s² at 3σ, 45·s² at 9σ (5× the 3σ one: slower than a parabola's 9×, so the walk
    # goes on), 9·s² + 486²·s² at 27σ, where the former check stopped: σ ×9/√45 = ×1.34. Re-fitting b_l
    # once the line flattens leaves 9·s² at every k below: flat out to 81σ, σ ×81/3 = ×27.
    s0 = 0.002

    def g(x: float) -> float:
        s = _CurvedValleyCost("f_cl", None, None, 1.0)._s
        return s * ((x - 0.3) / s0 if x >= 0.3 else min((0.3 - x) / s0, 3.0))

    p, q, _ = _checked_in_a_valley("f_cl", 0.3, s0, g, lambda x: 1.0 + 0.006 * ((x - 0.3) / 0.018) ** 4)
    assert p.identifiable and p.std_error == pytest.approx(27.0 * s0, rel=1e-6)
    assert q.identifiable and q.std_error == pytest.approx(0.001, rel=1e-6)


def test_a_sandwich_sigma_wider_than_its_clusters_allow_is_not_asked_of_the_cost():
    # σ 0.02 reported where the white curvature gives σ_c 0.0002 (σ/σ_c = 100: a jackknife driven by
    # leverage or a stair, not by correlation), on clusters (windows) of 4 rows: their correlation can
    # widen σ over σ_c by √4 = 2 at most. The cost is a parabola of half-width 0.002 (10× flatter than
    # σ_c): that half-width times 2 is 0.004, inside the σ reported, which the cost therefore backs. The
    # former check scaled the rise by σ/σ_c = 100 and widened σ ×10 to 0.2.
    problem = _OneParameterCost(lambda x: (x - 0.3) / 0.002 * NOISE_S)
    problem.window_of_residual = np.repeat(np.arange(250), 4)  # type: ignore[attr-defined]
    problem.block_sigma = False  # type: ignore[attr-defined]
    p = ParameterEstimate("f_cl", 0.3, 0.3, 0.02, True)
    fit = TrajectoryFit({"f_cl": 0.3}, [p], 1.0, 1.0, 1000, profile_direction={"f_cl": {"f_cl": 1.0}})  # type: ignore[arg-type]
    fit.curvature_sigma = {"f_cl": 0.0002}
    notes: list = []
    _sigma_backed_by_cost(problem, fit, notes)  # type: ignore[arg-type]
    assert p.identifiable and p.std_error == pytest.approx(0.02, rel=1e-9)
    assert notes == []


class _BreakawayCost:
    """A stand-in TrajectoryProblem whose RMS is |static_factor − 1.27| (the models are real ones)."""

    def residuals_of(self, model: HarmonicDriveModel) -> np.ndarray:
        return np.full(10, abs(get_values(model, ["static_factor"])["static_factor"] - 1.27))


def test_the_joint_step_starts_from_the_breakaway_level_that_costs_least(seed: HarmonicDriveModel):
    """From the seed's 1.0388 (cost 0.23), the ratios 1.0, 1.1, 1.25, 1.5 cost 0.27, 0.17, 0.02, 0.23: it
    starts at 1.25. Held by a staged prior, or costing more than the start everywhere, it stays."""
    notes: list = []
    start = _breakaway_start(_BreakawayCost(), seed, ["J_m", "static_factor"], {}, notes)  # type: ignore[arg-type]
    assert get_values(start, ["static_factor"])["static_factor"] == pytest.approx(1.25)
    assert len(notes) == 1 and "static_factor 1.25" in notes[0].text
    held = _breakaway_start(_BreakawayCost(), seed, ["static_factor"], {"static_factor": (1.0, 0.1)}, [])  # type: ignore[arg-type]
    assert held is seed
    near = with_values(seed, {"static_factor": 1.26})
    assert _breakaway_start(_BreakawayCost(), near, ["static_factor"], {}, []) is near  # type: ignore[arg-type]


class _WindowsOfParabolas:
    """A stand-in TrajectoryProblem: window w is one row √a_w·(x − c_w), so the whole cost is
    Σ a_w·(x − c_w)², lowest at the a-weighted mean of c, and without window i at that of the others."""

    def __init__(self, centres: np.ndarray, weights: np.ndarray, block_sigma: bool = False):
        self.c, self.a = centres, weights
        self.window_of_residual = np.arange(len(centres))
        self.block_sigma = block_sigma

    def model_with(self, values):
        return values

    def residuals_of(self, model):
        return np.sqrt(self.a) * (model["static_factor"] - self.c)


def _jackknife_of_weighted_means(c: np.ndarray, a: np.ndarray, groups: np.ndarray) -> float:
    optima = np.array([np.average(c[groups != g], weights=a[groups != g]) for g in np.unique(groups)])
    n = len(optima)
    return math.sqrt((n - 1) / n * float(np.sum((optima - optima.mean()) ** 2)))


def test_a_breakaway_levels_jackknife_leaves_out_each_window_in_turn():
    """Parabolic windows: leaving window i out moves the optimum to the weighted mean of the others, and
    the jackknife of those optima is √((G − 1)/G·Σ_i (x̂_(i) − x̄)²), computed here from that formula;
    the grid's parabolic vertices make it exact for such costs (rel 1e-6), wherever the grid's points
    fall, and a grid too narrow for the optima widens ×3 until they are inside it."""
    rng = np.random.default_rng(5)
    c = 1.2 + 0.01 * rng.standard_normal(60)
    a = rng.uniform(0.5, 2.0, 60)
    expected = _jackknife_of_weighted_means(c, a, np.arange(60))
    values = {"static_factor": float(np.average(c, weights=a)) + 1e-4}  # off the optimum: no matter
    for half_width in (0.003, 0.0002):
        got = _grid_jackknife(_WindowsOfParabolas(c, a), values, "static_factor", half_width)  # type: ignore[arg-type]
        assert got == pytest.approx(expected, rel=1e-6), half_width


def test_one_window_that_decides_a_breakaway_level_widens_its_sigma():
    """59 windows agree at 1.2; one (a stair: its motor breaks loose or not) weighs as much as all of
    them together and wants 1.2006. The optimum is 1.2003; without that window 1.2000: the jackknife
    spreads that move (≈ 0.0003), where the Jacobian at the optimum sees only the total curvature.
    With `block_sigma` (blocks of 6 windows) σ is the larger of the windows' and the blocks' jackknife."""
    c = np.full(60, 1.2)
    c[7] = 1.2006
    a = np.ones(60)
    a[7] = 59.0
    by_window = _jackknife_of_weighted_means(c, a, np.arange(60))
    by_block = _jackknife_of_weighted_means(c, a, np.arange(60) // 6)
    assert 0.00029 < by_window < 0.00031  # the one window's move, nearly all of it
    values = {"static_factor": 1.2003}
    got = _grid_jackknife(_WindowsOfParabolas(c, a), values, "static_factor", 0.001)  # type: ignore[arg-type]
    assert got == pytest.approx(by_window, rel=1e-6)
    both = _grid_jackknife(_WindowsOfParabolas(c, a, block_sigma=True), values, "static_factor", 0.001)  # type: ignore[arg-type]
    assert both == pytest.approx(max(by_window, by_block), rel=1e-6)
