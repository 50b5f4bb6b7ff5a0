"""Staged identification: the campaign's runs, stage by stage, to the starting point of the joint fit.

`staged_estimates(runs, start)` takes runs (selected by `run.meta["experiment"]`) and a starting model and
returns the updated model with one `StageEstimate` per parameter it touched or judged, and the stages'
notes (`pipeline.Note`). Each stage is an object (`pipeline.Stage`: its name, the experiments it reads,
the parameters it gives) run in the order `PIPELINE` declares; each solves one equation of MODEL.md by
least squares, with standard errors from the covariance, and hands its answer to the `Book`, which
believes or holds each value:

1. motor constants (`pulse`, voltage mode): u = R·i_a + K_b·ω_m → R, K_b; K_m is the rig's, given.
2. mechanics, twice round, each using the others' latest values:
   - stiffness and load friction (`speed-sweep`, `load-variation` steady windows): mean spring torque
     = τ_ext + F_l(r·ω) + J_l·dω_l/dt → K_s (or K1..K3), f_cl, b_l;
   - frequency response (`chirp`): the linear two-inertia FRFs i_cmd → ω_m, θ_l → J_m, J_l, D_s;
   - kinematic error (`position-friction`): θ_l − r·θ_m at k per motor turn through the load's
     response → A, φ.
3. motor friction, twice round: against position (`position-friction`: s1, s2, a1..a10, b1..b10),
   against velocity (sweep windows: s3, k_v, or the baseline law's levels).
4. breakaway (every run's sticks): static_factor.

On a dynamometer bench (runs with the torque transducers' `tau_out`, `tau_in`: `transducer_stage`) the
stiffness stage solves the output equation, mean T_s − F_l = tau_out + J_l·Δω_l/T, in place of the load
drive's τ_ext (no motor friction, no load drive in it), the velocity stage reads r·tau_out in place of
r·τ_ext, and the motor law from tau_in (no K_m, no J_m) is a check beside the current's; the notes name
each value's source.

What the data cannot determine is said, and held at its starting value: v_c (C·(1 + k_v(|ω| − v_c)) =
C·(1 − k_v·v_c) + C·k_v·|ω|: s3 and k_v absorb it), a0 (a constant like s3: fixed at 0), b_m (∝ ω like
C·k_v), K_m and r (given), f_sl, and whatever a stage had no run for. Everything else whose standard
error exceeds a quarter of its size (or, for coefficients that may be zero, of a natural scale) is
flagged the same way. A standard error is that of its stage's own least squares, the other stages'
values held; it carries their errors where they were measured to matter (the velocity stage carries the
position stage's s1, s2 with their covariance: `carry_held`), not elsewhere (A carries J_l's, for one).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from model.errors import UserInputError
from model.params import HarmonicDriveModel
from model.plant import Plant
from model.registry import BREAKAWAY, FRF, KINEMATIC, MOTOR, POSITION, STIFFNESS, STRUCTURAL, VELOCITY
from model.run import Run
from rig.analysis.fit.parameters import get_values, with_values
from rig.analysis.identification.dynamics_stage import (
    Held,
    Solved,
    frequency_response,
    kinematic_error,
    load_friction_names,
    motor_constants,
    runs_of,
    stiffness_and_load_friction,
    stiffness_names,
    sweep_parts,
)
from rig.analysis.identification.friction_stage import (
    FOURIER_NAMES,
    breakaway,
    position_friction,
    velocity_friction,
    velocity_names,
)
from rig.analysis.identification.pipeline import Note, Stage, note_lines
from rig.analysis.identification.transducer_stage import (
    INPUT,
    OUTPUT,
    input_equation,
    output_equation,
    output_run,
    with_transducer,
)

ROUNDS = 2
"""Passes over the coupled stages (mechanics; position ↔ velocity friction): the second settles them."""
DETERMINED = 0.25
"""A value counts as determined by the data when its standard error is under this share of its size
(it stands four standard errors from zero), or of a natural scale for coefficients that may be zero."""
PAIRS = (("f_st", "omega_st"), ("f_sm", "omega_sm"), ("A", "phi"))
"""Parameters of one curve (a bump's height and width, an error's amplitude and phase): both or neither."""
RELATIVE_SCALE = 0.01
"""The natural scale of coefficients that may be zero (a_n, b_n, s1, s2, f_dir): this share of the
Coulomb level s3 (over the stroke, for s1 and s2)."""


@dataclass(frozen=True)
class StageEstimate:
    """One parameter as the staged identification left it: value, standard error, and whether the data
    determine it (if not, `value` is the starting value and `note` says why)."""

    name: str
    value: float
    std_error: float | None
    stage: str
    identifiable: bool
    note: str = ""


@dataclass
class StagedResult:
    model: HarmonicDriveModel
    estimates: list[StageEstimate]
    said: list[Note] = field(default_factory=list)

    @property
    def notes(self) -> list[str]:
        return note_lines(self.said)

    def estimate(self, name: str) -> StageEstimate:
        for each in self.estimates:
            if each.name == name:
                return each
        raise KeyError(f"no estimate of {name!r}")


class Book:
    """The model as the stages update it, what each stage answered, and what was said of each parameter
    and stage."""

    def __init__(self, model: HarmonicDriveModel) -> None:
        self.model = model
        self.estimates: dict[str, StageEstimate] = {}
        self.notes: dict[str, list[Note]] = {}
        self.answers: dict[str, Solved] = {}  # by stage: its latest answer (later stages read its metrics)
        self.joint: dict[str, Held] = {}  # by stage: values believed together, with their covariance

    def value(self, name: str) -> float:
        return get_values(self.model, [name])[name]

    def say(self, stage: str, notes: list[str]) -> None:
        self.notes[stage] = [Note(stage, note) for note in notes]

    def first_note(self, stage: str) -> str:
        """What the stage said first (why it skipped, say), or "not run"."""
        said = self.notes.get(stage)
        return said[0].text if said else "not run"

    def flag(self, name: str, stage: str, note: str) -> None:
        self.estimates[name] = StageEstimate(name, self.value(name), None, stage, False, note)

    def accept(
        self, stage: str, solved: Solved, names: list[str], scales: dict[str, float] | None = None
    ) -> None:
        """Believe each value whose standard error is finite and under DETERMINED·max(|value|, scale)
        (and, for the parameters of one curve in PAIRS, whose partner is believed too)."""
        self.say(stage, solved.notes)
        self.answers[stage] = solved
        believed, doubted = {}, {}
        for name in names:
            if name in solved.undetermined:
                doubted[name] = solved.undetermined[name]
            elif name in solved.values:
                value, se = solved.values[name], solved.std_errors[name]
                if math.isfinite(se) and se <= DETERMINED * max(abs(value), (scales or {}).get(name, 0.0)):
                    believed[name] = value
                else:
                    doubted[name] = f"estimate {value:.4g} ± {se:.3g}: not determined by these data"
        for pair in PAIRS:
            for name, partner in (pair, pair[::-1]):
                if name in believed and partner in doubted:
                    believed.pop(name)
                    doubted[name] = f"its partner {partner} is not determined, so neither is it"
        for name, why in doubted.items():
            self.flag(name, stage, f"{why}: held")
        for name, value in believed.items():
            self.estimates[name] = StageEstimate(name, value, solved.std_errors[name], stage, True)
        self.joint.pop(stage, None)
        if solved.joint is not None and all(name in believed for name in solved.joint.names):
            self.joint[stage] = solved.joint
        self.update(believed)

    def update(self, values: dict[str, float]) -> None:
        if not values:
            return
        data = dict(values)
        lf = self.model.load_friction
        if "f_cl" in data and lf is not None and lf.f_sl is not None and lf.f_sl < data["f_cl"]:
            data["f_sl"] = data["f_cl"]  # the schema's rule: static at least the Coulomb level
        try:
            self.model = with_values(self.model, data, "staged")
        except UserInputError as exc:
            for name in values:
                self.flag(name, self.estimates[name].stage, f"estimate breaks the model's rules: {exc}")


REQUIRED_META = (
    "experiment",
    "sample_rate_hz",
    "gear_ratio",
    "torque_constant_nm_per_a",
    "segments",
    "params",
)


def _rig_constants(runs: list[Run], book: Book) -> None:
    """K_m and r are the rig's (run metadata): the model takes them as given."""
    for run in runs:
        missing = [key for key in REQUIRED_META if key not in run.meta]
        if missing:
            name = run.meta.get("run_id", run.meta.get("experiment", "a run"))
            raise UserInputError(f"staged identification: {name} lacks metadata {', '.join(missing)}")
    for name, key in (("K_m", "torque_constant_nm_per_a"), ("r", "gear_ratio")):
        given = sorted({float(run.meta[key]) for run in runs})
        if len(given) > 1:
            raise UserInputError(f"staged identification: the runs disagree on {key}: {given}")
        book.update({name: given[0]})
        book.flag(name, MOTOR, f"the rig's {key} (run metadata): given, not fitted")


# --- the stages -------------------------------------------------------------------------------------------


class MotorConstants:
    """u = R·i_a + K_b·ω_m on voltage-mode pulses (`dynamics_stage.motor_constants`)."""

    name = MOTOR
    experiments = ("pulse",)

    def gives(self, model: HarmonicDriveModel) -> list[str]:
        return ["R", "K_b"]

    def run(self, runs: Sequence[Run], book: Book) -> None:
        book.accept(self.name, motor_constants(runs_of(runs, "pulse")), ["R", "K_b"])


class StiffnessAndLoadFriction:
    """Mean spring torque = τ_ext + F_l(r·ω) + J_l·dω_l/dt on the steady windows; its answer's metrics
    (the load sensor's zero, the windows' J_l) serve the frequency-response, kinematic-error and breakaway
    stages."""

    name = STIFFNESS
    experiments = ("speed-sweep", "load-variation")

    def gives(self, model: HarmonicDriveModel) -> list[str]:
        return [] if model.rigid else stiffness_names(model)

    def run(self, runs: Sequence[Run], book: Book) -> None:
        names = stiffness_names(book.model) + load_friction_names(book.model)
        if with_transducer(runs, OUTPUT):
            # The output transducer reads what the gear passes on: no load drive, no motor in the balance.
            stiff = output_equation(runs, book.model)
            book.accept(self.name, stiff, names)
            _say_source(book, self.name, names, f"{OUTPUT} (output transducer)")
            return
        stiff = stiffness_and_load_friction(sweep_parts(runs, book.model), book.model)
        book.accept(self.name, stiff, names)


class FrequencyResponse:
    """The linear two-inertia FRFs of a chirp; the stiffness too when the steady windows gave none."""

    name = FRF
    experiments = ("chirp",)

    def gives(self, model: HarmonicDriveModel) -> list[str]:
        return ["J_m", "J_l"] + ([] if model.rigid else ["D_s"])

    def run(self, runs: Sequence[Run], book: Book) -> None:
        chirps = runs_of(runs, "chirp")
        if not chirps:
            book.say(self.name, ["skipped: no chirp run"])
            return
        static_known = bool(book.answers[STIFFNESS].values)
        slope = _friction_slope(chirps[0], book.model)
        frf = frequency_response(chirps[0], book.model, not static_known, slope)
        stiffness = stiffness_names(book.model)
        names = ["J_m"] if book.model.rigid else ["J_m"] + ([] if static_known else stiffness[:1])
        if book.model.rigid:
            frf.undetermined["J_l"] = "a rigid axis shows J_m + r²·J_l only: J_m carries the sum"
        book.accept(self.name, frf, [*names, "J_l", "D_s"])


class KinematicError:
    """θ_l − r·θ_m at k per motor turn, through the load's response, on the position passes."""

    name = KINEMATIC
    experiments = ("position-friction",)

    def gives(self, model: HarmonicDriveModel) -> list[str]:
        return ["A", "phi"] if model.kinematic_error is not None else []

    def run(self, runs: Sequence[Run], book: Book) -> None:
        passes = runs_of(runs, "position-friction")
        ripple = kinematic_error(passes, _sharper_load_inertia(book, book.answers[STIFFNESS]))
        book.accept(self.name, ripple, ["A", "phi"], {"phi": math.pi})


class PositionFriction:
    """The motor friction's position terms (s1, s2, a_n, b_n) on the position passes."""

    name = POSITION
    experiments = ("position-friction",)

    def gives(self, model: HarmonicDriveModel) -> list[str]:
        return ["s1", "s2", *FOURIER_NAMES] if model.motor_friction.motor_law == "article" else []

    def run(self, runs: Sequence[Run], book: Book) -> None:
        position = position_friction(runs_of(runs, "position-friction"), book.model)
        scales = {}
        if position.values:
            s3 = abs(book.value("s3"))
            span = position.metrics["span_rad"]
            scales = {"s1": RELATIVE_SCALE * s3 / span**2, "s2": RELATIVE_SCALE * s3 / span}
            scales.update({name: RELATIVE_SCALE * s3 for name in FOURIER_NAMES})
            position.notes.append(
                f"s3 from these passes: {position.values['s3']:.5g} N·m (a check of the velocity stage's)"
            )
        book.accept(self.name, position, ["s1", "s2", *FOURIER_NAMES], scales)


class VelocityFriction:
    """The motor friction against velocity on the steady windows, carrying the position stage's σ."""

    name = VELOCITY
    experiments = ("speed-sweep", "load-variation")

    def gives(self, model: HarmonicDriveModel) -> list[str]:
        return velocity_names(model)

    def run(self, runs: Sequence[Run], book: Book) -> None:
        held = book.joint.get(POSITION)
        bench = {id(run) for run in with_transducer(runs, OUTPUT)}
        # On a bench the load drive's τ_ext lacks its bearings' friction: r·tau_out takes its place.
        sweeps = [output_run(run) if id(run) in bench else run for run in runs]
        velocity = velocity_friction(sweep_parts(sweeps, book.model), book.model, held)
        scales = {"f_dir": RELATIVE_SCALE * abs(book.value("s3"))} if book.model.direction_asymmetry else {}
        book.accept(self.name, velocity, velocity_names(book.model), scales)
        if bench:
            _say_source(book, self.name, velocity_names(book.model), f"K_m·i_a − r·{OUTPUT}")
        if with_transducer(runs, INPUT) and velocity.values:
            _input_check(book, self.name, velocity, input_equation(runs, book.model, held))
        if "asymmetry_nm" in velocity.metrics and book.model.direction_asymmetry is None:
            book.notes[self.name].append(
                Note(
                    self.name,
                    f"direction asymmetry (forward − backward)/2 = {velocity.metrics['asymmetry_nm']:.3g}"
                    " N·m (a metric; not in the model)",
                )
            )


class Breakaway:
    """The breakaway level (static_factor, or f_sm of the baseline laws) from every run's sticks."""

    name = BREAKAWAY
    experiments = ()  # every run: any stick in any experiment

    def gives(self, model: HarmonicDriveModel) -> list[str]:
        law = model.motor_friction.motor_law
        return (
            ["static_factor"]
            if law == "article"
            else ["f_sm"]
            if law in ("coulomb_viscous", "stribeck")
            else []
        )

    def run(self, runs: Sequence[Run], book: Book) -> None:
        stiff = book.answers.get(STIFFNESS)
        offset = stiff.metrics.get("theta_l_offset", 0.0) if stiff is not None else 0.0
        book.accept(self.name, breakaway(runs, book.model, offset), ["static_factor", "f_sm"])


def _say_source(book: Book, stage: str, names: list[str], source: str) -> None:
    """Name the source of the stage's believed values in its notes."""
    believed = [name for name in names if (e := book.estimates.get(name)) is not None and e.identifiable]
    if believed and book.estimates[believed[0]].stage == stage:
        book.notes[stage].insert(0, Note(stage, f"{', '.join(believed)} from {source}"))


INPUT_AGREEMENT_SIGMAS = 3.0
"""The input transducer's motor friction and the current's disagree when further apart than this many
standard errors of their difference: then K_m (the rig's, given) or J_m is suspect."""


def _input_check(book: Book, stage: str, current: Solved, transducer: Solved) -> None:
    """The motor law from tau_in beside the current's: a check of K_m and J_m, not the estimate (on the
    simulated bench the transducer's noise leaves its σ ~100× the current's; docs/IDENTIFICATION.md)."""
    notes = book.notes.setdefault(stage, [])
    notes += [Note(stage, note) for note in transducer.notes]
    for name, value in transducer.values.items():
        if name not in current.values:
            continue
        se = math.hypot(transducer.std_errors[name], current.std_errors[name])
        z = (value - current.values[name]) / se if se > 0 and math.isfinite(se) else math.nan
        verdict = (
            "agrees" if abs(z) <= INPUT_AGREEMENT_SIGMAS else "DISAGREES: K_m (the rig's) or J_m is suspect"
        )
        notes.append(
            Note(
                stage,
                f"{name} from {INPUT}: {value:.5g} ± {transducer.std_errors[name]:.2g} against"
                f" {current.values[name]:.5g} from the current ({z:+.1f}σ): {verdict}",
            )
        )


@dataclass(frozen=True)
class Rounds:
    """Stages run in turn, `times` over: coupled stages, each using the others' latest values."""

    stages: tuple[Stage, ...]
    times: int = 1


PIPELINE = (
    Rounds((MotorConstants(),)),
    Rounds(
        (
            StiffnessAndLoadFriction(),
            FrequencyResponse(),
            KinematicError(),
            PositionFriction(),
            VelocityFriction(),
        ),
        ROUNDS,
    ),
    Rounds((Breakaway(),)),
)
"""The staged identification, in order: a new stage is one more `Rounds` (or joins the coupled ones)."""
STAGES: tuple[Stage, ...] = tuple(stage for rounds in PIPELINE for stage in rounds.stages)


def _friction_slope(chirp: Run, model: HarmonicDriveModel) -> float:
    """c_m: slope dF_m/dω of the model's moving friction at the chirp's mean speed, over its positions."""
    speed = float(chirp.meta["params"]["mean_speed_motor_rad_s"])
    theta = chirp["theta_m"]
    plant = Plant(model)
    up = plant.steady_friction(theta, np.full(theta.shape, speed + 0.5))
    down = plant.steady_friction(theta, np.full(theta.shape, speed - 0.5))
    return float(np.mean(up - down))


def _sharper_load_inertia(book: Book, stiff: Solved) -> HarmonicDriveModel:
    """The model for the kinematic-error stage, with the stiffness windows' J_l where it is the sharper.

    The stage passes the ripple through the load, G ∝ 1/J_l, so A carries J_l's error one to one, and
    the windows, which fit J_l alongside the stiffness as a metric, see it far better than the FRF
    (figures: docs/BENCHMARKS.md). Only this stage takes it: J_l's estimate stays the FRF's (the
    windows' is a by-product of another fit)."""
    value, std = stiff.metrics.get("J_l"), stiff.metrics.get("J_l_std")
    held = book.estimates.get("J_l")
    if value is None or std is None or not math.isfinite(std) or value <= 0:
        return book.model
    if held is not None and held.std_error is not None and held.std_error <= std:
        return book.model
    return with_values(book.model, {"J_l": value})


def _expected(model: HarmonicDriveModel) -> dict[str, list[str]]:
    """What each stage estimates for this model."""
    return {stage.name: stage.gives(model) for stage in STAGES}


def _structural(runs: list[Run], book: Book) -> None:
    """The parameters these experiments cannot determine, each with the reason."""
    model = book.model
    for stage, names in _expected(model).items():
        why = book.first_note(stage)
        for name in names:
            if name not in book.estimates:
                book.flag(name, stage, f"{why}; held at the start value")
    if model.motor_friction.motor_law == "article":
        book.flag(
            "v_c",
            VELOCITY,
            "C·(1 + k_v(|ω| − v_c)) = C·(1 − k_v·v_c) + C·k_v·|ω|: v_c is absorbed by s3 and k_v; held",
        )
        book.flag("a0", POSITION, "a constant, collinear with s3: fixed at 0 (the mean is in s3)")
        book.flag(
            "b_m",
            VELOCITY,
            "b_m·ω and C·k_v·|ω| both grow ∝ ω at steady speed: held (MODEL.md note 3: 0 with the"
            " article law)",
        )
    lf = model.load_friction
    if lf is not None:
        if "f_cl" not in book.estimates and "f_cl" in load_friction_names(model):
            why = book.first_note(STIFFNESS)
            for name in load_friction_names(model):
                book.flag(
                    name,
                    STIFFNESS,
                    "the load's friction adds r·F_l to the motor's torque at steady speed, inseparable from"
                    f" s3 by the motor current alone; the load angle's stage did not part them ({why}): held",
                )
        if lf.f_sl is not None:
            book.flag(
                "f_sl",
                STIFFNESS,
                "the load's breakaway is not timed by these data (the load angle's noise hides when the"
                " load starts at the sticks' slow speeds): held (at least f_cl)",
            )
    if model.kinematic_error is not None:
        book.flag("k", KINEMATIC, "cycles of the error per motor turn: structural, held")
    if model.nonlinear_stiffness is not None:
        for name in ("T1", "T2"):
            book.flag(name, STIFFNESS, "breakpoint torque: held at the start model's (catalog) value")
    for section, held in (
        ("hysteresis", ("T_h", "delta_h")),
        ("thermal_drift", ("d_th", "tau_th")),
    ):
        if getattr(model, section) is not None:
            for name in (n for n in held if n not in book.estimates):  # unless a stage estimated it
                book.flag(name, STRUCTURAL, f"{section} is not estimated by the staged fit: held")
    data = model.to_dict()
    sections = {**data["motor_friction"], **data.get("load_friction", {})}
    for name in ("sigma0_m", "sigma1_m", "sigma0_l", "sigma1_l"):
        if name in sections:
            book.flag(name, STRUCTURAL, "bristle dynamics are not seen by steady runs: held")


def staged_estimates(runs: list[Run], start: HarmonicDriveModel) -> StagedResult:
    """Staged estimates of the model's parameters from the runs, starting from `start` (see the module)."""
    if not runs:
        raise UserInputError("staged identification needs at least one run")
    book = Book(start)
    if start.motor_friction.motor_law == "article" and start.motor_friction.fourier_a()[0] != 0.0:
        book.update({"a0": 0.0})
    _rig_constants(runs, book)
    for rounds in PIPELINE:
        for _ in range(rounds.times):
            for stage in rounds.stages:
                stage.run(runs, book)
    _structural(runs, book)
    present = {str(run.meta.get("experiment")) for run in runs}
    said = [Note("experiments", ", ".join(sorted(present)))]
    said += [note for stage_notes in book.notes.values() for note in stage_notes]
    return StagedResult(book.model, list(book.estimates.values()), said)
