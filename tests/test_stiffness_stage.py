"""The stiffness / load-friction stage and the kinematic-error stage are unbiased
(rig.analysis.identification.dynamics_stage), checked on campaigns of the seed model played by the
in-process sim rig.

Why these tests exist: with ideal sensors the stiffness stage put f_cl −0.44 % and b_l +0.9 % off in the
staged chain (σ 0.17 / 1.4 %), a bias of the method, not noise. Its causes, each tested below:
- the held kinematic error: at 5 rad/s the error's torque slows the motor through part of each cycle, so
  a window's mean of K_s·A·sin(k·θ_m + φ) is ±140 mN·m and odd in the direction, like f_cl; the
  kinematic-error stage's A was 1.7 % low (2.4 % in the chain), and f_cl took it (A −2.4 % → f_cl
  −0.48 %). A is now fitted with the windows (a metric), and the kinematic-error stage takes each time
  harmonic of e^(jk·θ_m) through the load at its own frequency;
- the windows are not steady: after every reversal the load rings at its antiresonance (b_l alone damps
  it), so a window's mean spring torque carries J_l·Δω_l/T of up to a few hundred mN·m: spring torque,
  friction and momentum are now taken over the very same stretch of time (sample spans, the error's
  ripple seen between samples, the friction's sign at instants where the ringing reverses the load),
  and J_l is fitted with the windows too (the FRF's J_l is 0.6 % off; f_cl took 0.13 % of it).

Tolerances. Ideal sensors leave a deterministic residual (the simulated plant's own 0.1 ms step: ≤ 0.4
mN·m in a window against f_cl = 300 mN·m), so their error is the method's bias, and it is judged against
the σ the stage reports with the sim rig's sensors (what coverage is about): |bias| ≤ 0.3·σ, which
keeps the 1σ coverage of normal errors at ≥ 66 % (Φ(1.3) − Φ(−0.7)) against the target of 68 %.
Measured ≤ 0.13 (K_s), 0.04 (f_cl), 0.02 (b_l) (noise seeds 101, 102); the old method up to 1.4, 2.1
and 1.9 here. A single noisy campaign (one fixed seed, so it cannot flake) must be within k = 3 σ, as
any single draw; over 26 seeds (notes) the errors' spread is 0.017 % (f_cl) and 0.17 % (b_l) against
σ 0.029 / 0.20 %. The kinematic-error stage's A with ideal sensors and the true load: within k = 3 of
its σ (measured +0.04 % at σ 0.13 %; the old stage −1.7 %, −14 σ). J_l and A fitted with the windows
(metrics only), ideal sensors: within 0.1 %, an order better than the FRF's J_l (0.6 % off) and the old
A (1.7 %), which is what makes them worth reporting (measured +0.013 %, 0.000 %); their σ is that of
a deterministic floor (J_l: 0.004 %), so not a yardstick here.
"""

from __future__ import annotations

import campaign
import numpy as np
import pytest

from model.params import HarmonicDriveModel
from model.run import Run
from rig.analysis.fit.parameters import get_values, with_values
from rig.analysis.identification.dynamics_stage import (
    CARRIER_TURNS,
    Solved,
    SpanMotion,
    SweepPart,
    kinematic_error,
    load_friction_steady,
    runs_of,
    sign_seen,
    slow_motion,
    span_instants,
    span_motion,
    spline_speed_gain,
    stiffness_and_load_friction,
    sweep_parts,
    window_means,
)
from rig.config import RigConfig, Sensors, load_rig_config
from rig.store.runs import RunStore

K_SIGMA = 3.0  # see the module docstring
K_BIAS = 0.3  # ideal sensors' error / the rig sensors' σ, see the module docstring
EXPERIMENTS = ("speed-sweep", "load-variation", "position-friction")


def play(config: RigConfig, truth: HarmonicDriveModel, store: RunStore) -> list[Run]:
    return campaign.play(EXPERIMENTS, config, truth, store)


@pytest.fixture(scope="module")
def clean_runs(seed: HarmonicDriveModel, tmp_path_factory: pytest.TempPathFactory) -> list[Run]:
    ideal = load_rig_config("sim").model_copy(update={"sensors": Sensors()})
    return play(ideal, seed, RunStore(tmp_path_factory.mktemp("clean")))


@pytest.fixture(scope="module")
def noisy_runs(seed: HarmonicDriveModel, tmp_path_factory: pytest.TempPathFactory) -> list[Run]:
    return play(load_rig_config("sim"), seed, RunStore(tmp_path_factory.mktemp("noisy")))


def held_as_the_chain_has_them(truth: HarmonicDriveModel) -> HarmonicDriveModel:
    """The truth with J_l and A as the earlier stages hand them over (FRF J_l −0.6 %, the old A −2.4 %)."""
    values = get_values(truth, ["J_l", "A"])
    return with_values(truth, {"J_l": 0.994 * values["J_l"], "A": 0.976 * values["A"]})


def assert_within(solved: Solved, truth: HarmonicDriveModel, names: list[str]) -> None:
    misses = []
    for name in names:
        value, sigma = solved.values[name], solved.std_errors[name]
        true = get_values(truth, [name])[name]
        if not abs(value - true) <= K_SIGMA * sigma:
            error = value - true
            misses.append(f"{name}: {value:.6g} vs {true:.6g} ({error / true:+.3%}), z {error / sigma:+.1f}")
    assert not misses, "; ".join(misses)


@pytest.mark.parametrize("held", ["true", "as the chain has them"])
def test_stiffness_and_load_friction_of_ideal_sensors_are_unbiased(
    held: str, clean_runs: list[Run], noisy_runs: list[Run], seed: HarmonicDriveModel
):
    model = seed if held == "true" else held_as_the_chain_has_them(seed)
    ideal = stiffness_and_load_friction(sweep_parts(clean_runs, model), model)
    rig = stiffness_and_load_friction(sweep_parts(noisy_runs, model), model)
    misses = []
    for name in ("K_s", "f_cl", "b_l"):
        true = get_values(seed, [name])[name]
        bias = ideal.values[name] - true
        if not abs(bias) <= K_BIAS * rig.std_errors[name]:
            misses.append(f"{name}: {bias / true:+.3%} = {bias / rig.std_errors[name]:+.2f} σ of the rig's")
    assert not misses, "; ".join(misses)


def test_the_windows_see_the_load_inertia_and_the_kinematic_error(
    clean_runs: list[Run], seed: HarmonicDriveModel
):
    # Fitted with the windows from held values that are off, reported as metrics: within 0.1 % (above).
    model = held_as_the_chain_has_them(seed)
    metrics = stiffness_and_load_friction(sweep_parts(clean_runs, model), model).metrics
    for name, true in get_values(seed, ["J_l", "A"]).items():
        assert metrics[name] == pytest.approx(true, rel=1e-3), name


def test_stiffness_and_load_friction_with_the_rig_sensors_are_within_their_sigma(
    noisy_runs: list[Run], seed: HarmonicDriveModel
):
    model = held_as_the_chain_has_them(seed)
    solved = stiffness_and_load_friction(sweep_parts(noisy_runs, model), model)
    assert_within(solved, seed, ["K_s", "f_cl", "b_l"])
    # The window's momentum from its ramps, not from two sampled speeds: 2 µrad of load-angle noise
    # gave ±2 mN·m per window and σ(f_cl) 0.2 %, σ(b_l) 1.3 %; now 0.03 / 0.2 % (sizes, 2× margin).
    assert solved.std_errors["f_cl"] / 0.3 < 0.0006
    assert solved.std_errors["b_l"] / 0.05 < 0.004


@pytest.mark.parametrize("case", ["clean", "noisy"])
def test_kinematic_error_amplitude_is_unbiased(
    case: str, clean_runs: list[Run], noisy_runs: list[Run], seed: HarmonicDriveModel
):
    # G(jkω) taken per time harmonic of e^(jk·θ_m): with the true load (K_s, J_l, b_l) A comes back
    # within k·σ (measured +0.04 % at σ 0.13 %); the whole wave through G(jkω) gave −1.7 % (13 σ).
    runs = clean_runs if case == "clean" else noisy_runs
    solved = kinematic_error(runs_of(runs, "position-friction"), seed)
    assert_within(solved, seed, ["A"])
    assert abs(solved.values["phi"] - seed.kinematic_error.phi) <= K_SIGMA * solved.std_errors["phi"]
    # Its σ is the noise's, not a misfit's: the error's wave locked to a straight line and to its own
    # harmonics only left 1.9e-5 rad of residual (the speed's drift over a pass, and the sidebands of the
    # friction's speed ripple) and σ(A) 1.0 % against a spread of 0.04 % over 20 noise seeds; with the
    # slow carrier and the sidebands 0.05 % (sizes: 4× margin, 5× below the old).
    assert solved.std_errors["A"] / seed.kinematic_error.A < 0.002


def test_the_slow_motion_follows_the_drift_and_leaves_the_ripple():
    """θ = ω·t + a slow drift (period 30 s) + a ripple at 1 and 2 per turn, ω = 5 rad/s over 30 s:
    the carrier with knots two turns apart keeps the drift to 1 % of its size and the ripple to 2 %."""
    t = np.arange(0.0, 30.0, 1e-3)
    omega = 5.0
    drift = 0.05 * np.sin(2 * np.pi * t / 30.0)
    ripple = 2e-3 * np.sin(omega * t) + 1e-3 * np.cos(2 * omega * t)
    slow = slow_motion(t, omega * t + drift + ripple, 2 * CARRIER_TURNS * np.pi / omega)
    inner = slice(2000, -2000)  # a spline's ends see one side only
    assert np.max(np.abs(slow - omega * t - drift)[inner]) < 0.01 * 0.05 + 0.02 * 3e-3
    assert np.std((omega * t + drift + ripple - slow)[inner]) == pytest.approx(
        np.std(ripple[inner]), rel=0.02
    )


def test_windows_where_the_noise_flips_the_load_friction_are_left_out(clean_runs: list[Run], seed):
    """The clean campaign's θ_l with 2 µrad of white noise added (the rig sensor's; seed fixed): in the
    windows the stage keeps, the mean F_l at the true parameters is the clean one (a single instant
    whose sign flipped would move it by 2·f_cl/(rows·instants) ≈ 0.05 mN·m); among those it leaves
    out, the noise flipped the sign of F_l where the load slows to a near stop (measured −1.36 mN·m at
    +5 rad/s without load). Before, all were kept, and K_s's mean z over 20 seeds was +0.65."""
    rng = np.random.default_rng(5)
    noisy = [
        Run({**r.columns, "theta_l": r["theta_l"] + 2e-6 * rng.standard_normal(len(r))}, r.meta)
        for r in clean_runs
    ]

    def mean_friction(part: SweepPart) -> tuple[np.ndarray, SpanMotion]:
        edges, at = span_instants(part.run, seed)
        load = span_motion(part.run, "theta_l", edges, at)
        return window_means(part, load_friction_steady(seed, load.speed).mean(axis=1)), load

    kept_nm, left_nm = [], []
    for clean, part in zip(sweep_parts(clean_runs, seed), sweep_parts(noisy, seed), strict=True):
        (before, _), (after, load) = mean_friction(clean), mean_friction(part)
        seen = sign_seen(part, load)
        kept_nm += list(np.abs(after - before)[part.steady & seen])
        left_nm += list(np.abs(after - before)[part.steady & ~seen])
    assert kept_nm and max(kept_nm) < 1e-5
    assert left_nm and max(left_nm) > 2.5e-4


def test_the_spline_speed_noise_gain_is_that_of_white_noise_through_the_spline():
    """`spline_speed_gain` from the spline's weights against white noise through `span_motion`'s spline:
    2000 samples × 64 instants, the rms within 3 % (the sampling error of ~10⁵ correlated speeds)."""
    rng = np.random.default_rng(2)
    t = np.arange(2000) * 1e-3
    noise = Run({"t": t, "theta_l": rng.standard_normal(t.size)}, {})
    edges = np.concatenate([[t[0] - 5e-4], (t[:-1] + t[1:]) / 2, [t[-1] + 5e-4]])
    at = edges[:-1, None] + 1e-3 * (np.arange(64) + 0.5) / 64
    speed = span_motion(noise, "theta_l", edges, at).speed[50:-50]
    assert float(np.sqrt(np.mean(speed**2))) * 1e-3 == pytest.approx(spline_speed_gain(), rel=0.03)
