"""Hidden-effect cases: closed-loop data from a truth model on the simulated rig, and a model without it.

The tests and the benchmark both draw their cases here, so "effect X hidden at strength s" means one
thing. The data are what the in-process simulated rig records (17-bit encoder, drive velocity loop,
output-sensor noise) under a velocity probe that visits what every vocabulary effect needs: the whole
stroke at speeds up to ~100 rad/s, slow reversals, start-stop breakaways, and a slow external load.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from model.params import HarmonicDriveModel, load_model
from model.run import Run
from model.simulate import simulate
from rig.analysis.gaps.effects import merge_sections
from rig.config import load_rig_config
from rig.interface import ControlMode, Segment
from sim_backend.inprocess import SimRig

PROBE_STROKE_RAD = 250.0
"""Motor travel of the probe's stroke sweep: 2.5 rad at the output of a 100:1 gear, inside the sim rig."""
PROBE_LOAD_NM = 5.0
"""Amplitude of the probe's slow external load at the output [N·m]."""


def probe_profile(
    duration_s: float, rate_hz: float, load_nm: float = PROBE_LOAD_NM
) -> tuple[np.ndarray, np.ndarray]:
    """Velocity set-point [rad/s] and output load torque [N·m] per control cycle.

    40 % of the time: one sinusoidal sweep out over the stroke and back (speeds 0 → ~100 rad/s);
    30 %: slow reversals at up to 4 rad/s (the Stribeck range); 30 %: start-stop moves of ±3 rad/s
    with rests between (breakaway). Throughout: a slow load sine of `load_nm` at the output.
    """
    n = round(duration_s * rate_hz)
    t = np.arange(n) / rate_hz
    sweep_s, slow_s = 0.4 * duration_s, 0.3 * duration_s
    v = np.zeros(n)
    sweep = t < sweep_s
    v[sweep] = PROBE_STROKE_RAD * np.pi / sweep_s * np.sin(2 * np.pi * t[sweep] / sweep_s)
    slow = (t >= sweep_s) & (t < sweep_s + slow_s)
    v[slow] = 4.0 * np.sin(2 * np.pi * 0.6 * (t[slow] - sweep_s))
    rest = t >= sweep_s + slow_s
    phase = np.mod(t[rest] - sweep_s - slow_s, 1.4)
    v[rest] = np.where((phase >= 0.3) & (phase < 0.7), 3.0, 0.0) - np.where(phase >= 1.0, 3.0, 0.0)
    tau_ext = load_nm * np.sin(2 * np.pi * 0.15 * t)
    return v, tau_ext


def record_probe(
    truth: HarmonicDriveModel,
    duration_s: float = 16.0,
    seed: int = 1,
    load_sensor: bool = True,
    load_nm: float = PROBE_LOAD_NM,
) -> Run:
    """Run the probe on the simulated rig (`configs/rigs/sim.yaml`) whose plant is `truth`.

    The run keeps what a single-axis bench records: t, the current command i_cmd, the quantized motor
    angle, the load torque (unless `load_nm` is 0: then no column, as on a bench without a load
    actuator) and, with `load_sensor`, the noisy output angle.
    """
    config = load_rig_config("sim")
    config = config.model_copy(update={"sensors": config.sensors.model_copy(update={"seed": seed})})
    rig = SimRig(config, model=truth)
    rig.enable()
    blocks: list[dict[str, np.ndarray]] = []
    setpoint, tau_ext = probe_profile(duration_s, config.sample_rate_hz, load_nm)
    result = rig.run_segment(Segment(ControlMode.VELOCITY, setpoint, tau_ext, "probe"), blocks.append)
    if result.aborted:
        raise RuntimeError(f"probe aborted on the simulated rig: {result.aborted}")
    keep = ["t", "i_cmd", "theta_m"] + (["tau_ext"] if load_nm else []) + (["theta_l"] if load_sensor else [])
    columns = {c: np.concatenate([b[c] for b in blocks]) for c in keep}
    meta: dict[str, Any] = {
        "sample_rate_hz": config.sample_rate_hz,
        "source": "sim",
        "experiment": "gap-probe",
        "input_column": "i_cmd",
    }
    return Run(columns, meta).validate("gap probe")


_PLAIN_FRICTION = {"s1": 0.0, "s2": 0.0, "a": [0.0] * 11, "b": [0.0] * 10}


def base_model(rigid: bool = True) -> HarmonicDriveModel:
    """The seed joint with plain friction (constant Coulomb level s3, no position terms) and no
    kinematic error: rigid (`seed-rigid`) or with the article's K_s = 1000 N·m/rad (`seed`)."""
    seed = load_model("seed-rigid" if rigid else "seed")
    return merge_sections(seed, name="gap-base", motor_friction=_PLAIN_FRICTION, kinematic_error=None)


SEED_A = [0.0, 0.0025, 0.0050, 0.0, 0.0012, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
SEED_B = [0.0015, 0.0040, 0.0, 0.0008, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
Edit = Callable[[HarmonicDriveModel, float], HarmonicDriveModel]


def record_open_loop(truth: HarmonicDriveModel, duration_s: float = 12.0, seed: int = 1) -> Run:
    """Open-loop voltage data from `simulate` (a 3 V, 0.2 Hz sine: reversals and speeds to ~90 rad/s),
    the motor angle quantized like a 17-bit encoder and the output angle with 2 µrad of noise."""

    run = simulate(truth, "sine:amp=3,freq=0.2", duration_s, mode="voltage")
    rng = np.random.default_rng(seed)
    quantum = 2 * np.pi / 2**17
    columns = {
        "t": run.t,
        "u": run["u"],
        "theta_m": np.round(run["theta_m"] / quantum) * quantum,
        "theta_l": run["theta_l"] + 2e-6 * rng.standard_normal(len(run)),
    }
    return Run(columns, {"sample_rate_hz": 1000.0, "source": "sim", "input_column": "u"}).validate(
        "open loop"
    )


def _scaled(values: list[float], s: float) -> list[float]:
    return [v * s for v in values]


# Per effect: (needs a compliant truth, needs the output sensor, truth from base at strength s,
# model from base at strength s). Strength 1 is the nominal size used by the tests.
HIDDEN: dict[str, tuple[bool, bool, Edit, Edit]] = {
    "coulomb_friction": (
        False,
        False,
        lambda m, s: m,
        lambda m, s: merge_sections(m, motor_friction={"s3": 0.072 * (1 - min(s, 1.0))}),
    ),
    "viscous_friction": (
        False,
        False,
        lambda m, s: merge_sections(m, motor_friction={"b_m": 3e-4 * s}),
        lambda m, s: m,
    ),
    "stribeck": (
        False,
        False,
        lambda m, s: merge_sections(m, stribeck={"f_st": 0.04 * s, "omega_st": 1.5}),
        lambda m, s: m,
    ),
    "static_friction": (
        False,
        False,
        lambda m, s: merge_sections(m, motor_friction={"static_factor": 1.0 + 0.6 * s}),
        lambda m, s: merge_sections(m, motor_friction={"static_factor": 1.0}),
    ),
    "position_periodic_friction": (
        False,
        False,
        lambda m, s: merge_sections(m, motor_friction={"a": _scaled(SEED_A, s), "b": _scaled(SEED_B, s)}),
        lambda m, s: m,
    ),
    "position_quadratic_friction": (
        False,
        False,
        lambda m, s: merge_sections(m, motor_friction={"s1": 1.5738e-6 * s, "s2": -3.7901e-4 * s}),
        lambda m, s: m,
    ),
    "direction_asymmetry": (
        False,
        False,
        lambda m, s: merge_sections(m, direction_asymmetry={"f_dir": 0.012 * s}),
        lambda m, s: m,
    ),
    "load_dependent_friction": (
        False,
        False,
        lambda m, s: merge_sections(m, load_dependent_friction={"c_Ts": 0.004 * s}),
        lambda m, s: m,
    ),
    "thermal_drift": (
        False,
        False,
        lambda m, s: merge_sections(m, thermal_drift={"d_th": -0.35 * s, "tau_th": 4.0}),
        lambda m, s: m,
    ),
    "kinematic_error": (
        False,
        True,
        lambda m, s: merge_sections(m, kinematic_error={"A": 1e-3 * s, "k": 2.0, "phi": 0.4}),
        lambda m, s: m,
    ),
    "compliance": (
        True,
        True,
        lambda m, s: merge_sections(m, transmission={"K_s": 1000.0 / s, "D_s": 0.0}),
        lambda m, s: merge_sections(m, transmission={"K_s": None, "D_s": 0.0}),
    ),
    "nonlinear_stiffness": (
        True,
        True,
        lambda m, s: merge_sections(
            m,
            nonlinear_stiffness={
                "K1": 1000.0,
                "K2": 1000.0 * (1 + 1.5 * s),
                "K3": 4000.0,
                "T1": 1.5,
                "T2": 4.5,
            },
        ),
        lambda m, s: m,
    ),
    "hysteresis": (
        True,
        True,
        lambda m, s: merge_sections(m, hysteresis={"T_h": 0.6 * s, "delta_h": 1e-4}),
        lambda m, s: m,
    ),
    "load_side_friction": (
        True,
        True,
        lambda m, s: merge_sections(
            m, load_friction={"load_law": "coulomb_viscous", "f_cl": 0.5 * s, "f_sl": 0.5 * s}
        ),
        lambda m, s: merge_sections(m, load_friction=None),
    ),
}
"""Every vocabulary effect of docs/MODEL.md that the simulator produces, as a (truth, model) recipe."""


@dataclass(frozen=True)
class Case:
    """A truth that makes the data and a model that lacks the `hidden` effects."""

    name: str
    hidden: tuple[str, ...]
    truth: HarmonicDriveModel
    model: HarmonicDriveModel
    load_sensor: bool


def hidden_case(effects: tuple[str, ...], strength: float = 1.0, compliant: bool = False) -> Case:
    """A case with the named effects in the truth and not in the model (none: a null case); the joint
    is compliant when an effect needs it or `compliant` says so."""
    compliant = compliant or any(HIDDEN[e][0] for e in effects)
    base = base_model(rigid=not compliant)
    truth, model = base, base
    for effect in effects:
        _, _, make_truth, make_model = HIDDEN[effect]
        truth, model = make_truth(truth, strength), make_model(model, strength)
    name = "+".join(effects) or ("null-compliant" if compliant else "null")
    sensor = any(HIDDEN[e][1] for e in effects) or compliant
    return Case(
        name,
        effects,
        merge_sections(truth, name=f"truth-{name}"),
        merge_sections(model, name=f"model-{name}"),
        sensor,
    )


ZERO_LOAD_FRICTION = {"load_law": "coulomb_viscous", "f_cl": 0.0, "f_sl": 0.0, "b_l": 0.0}


def carried_at_zero_case(strength: float = 1.0) -> Case:
    """Load-side friction hidden while the model carries its section at zero (f_cl = f_sl = b_l = 0), as
    a model file that lists every section does (issue 25): an effect at zero is still a candidate."""
    case = hidden_case(("load_side_friction",), strength)
    model = merge_sections(case.model, name="model-load_side_friction@zero", load_friction=ZERO_LOAD_FRICTION)
    return Case("load_side_friction@zero", case.hidden, case.truth, model, case.load_sensor)


# --- slow friction factors on the independent generator (issue 27 item 5) --------------------------------

THERMAL_NETWORK = {"T_ref": 25.0, "C_w": 5.0, "C_g": 8.0, "R_wg": 2.0, "R_wa": 6.0, "R_ga": 1.5}
"""A small gear's network (gear time constant C_g·R_ga = 12 s): a run of seconds warms or cools it by
several kelvin, so temperature varies within runs as well as between them."""
BETA_T = 0.025
"""The grease's law of `seed-thermal`: friction × exp(−0.025·(T_g − 25 °C)), ×0.54 from 0 to 25 K over."""
K_WEAR = 1e-3
"""Wear at a rate that shows within a short record: +10 % friction per 100 rad of motor travel."""
THERMAL_DRIFT = {"d_th": -0.2, "tau_th": 2.0}
"""Time drift of a short record: 20 % less friction once warm, with a 2 s time constant."""
SLOW_RUNS = ((20.0, 45.0, 1.0), (20.0, 5.0, 0.4), (25.0, 25.0, 0.7))
"""Per run: ambient and starting temperature [°C], and the scale of the lab profile's speeds. One gear
cools from 45 °C, one warms from 5 °C, one stays near 25 °C; the speeds differ, so the travel does: time,
temperature and travel are three different clocks across the runs."""
SLOW_CASES = ("temperature", "temperature_flat", "carried", "wear", "time")
"""`temperature`: only the gear temperature drives the friction (the model has no thermal law).
`temperature_flat`: temperatures recorded at several levels, friction independent of them (null).
`carried`: the temperature law in the truth and in the model alike (null). `wear`: friction rising with
travel, temperatures recorded but without effect. `time`: friction falling with time since the start,
likewise."""


@dataclass(frozen=True)
class SlowCase:
    """Runs of the independent generator at several temperatures and travels, and the model judged."""

    name: str
    hidden: tuple[str, ...]  # the effects the model lacks (none: a null case)
    runs: list[Run]
    model: HarmonicDriveModel


def slow_case(name: str, duration_s: float = 6.0, strength: float = 1.0, seed: int = 1) -> SlowCase:
    """One of SLOW_CASES: three records of `duration_s` each (rigid joint, no output sensor), the slow
    effect at `strength` × its nominal size, the generator's noise seeded `seed`, `seed` + 1, `seed` + 2."""
    from hdrig_testing.independent_plant import IndependentRig, lab_profile

    if name not in SLOW_CASES:
        raise ValueError(f"unknown case {name!r} (cases: {', '.join(SLOW_CASES)})")
    base = base_model(rigid=True)
    beta = 0.0 if name in ("temperature_flat", "wear", "time") else strength * BETA_T
    extra: dict[str, Any] = {
        "wear": {"wear_drift": {"k_wear": strength * K_WEAR}},
        "time": {"thermal_drift": {**THERMAL_DRIFT, "d_th": strength * THERMAL_DRIFT["d_th"]}},
    }.get(name, {})
    runs = []
    for number, (ambient, start, scale) in enumerate(SLOW_RUNS, start=seed):
        thermal = {**THERMAL_NETWORK, "T_amb": ambient, "T_gear0": start, "T_motor0": start, "beta_T": beta}
        truth = merge_sections(base, name=f"truth-slow-{name}", thermal=thermal, **extra)
        setpoint, load = lab_profile(duration_s)
        runs.append(IndependentRig(truth, seed=number).record(scale * setpoint, load, with_load=False))
    model = base
    if name == "carried":
        model = merge_sections(base, thermal={**THERMAL_NETWORK, "T_amb": 20.0, "beta_T": beta})
    hidden = {"temperature": ("temperature_dependence",), "wear": ("wear_drift",), "time": ("thermal_drift",)}
    return SlowCase(name, hidden.get(name, ()), runs, merge_sections(model, name=f"model-slow-{name}"))
