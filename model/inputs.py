"""Input profiles (step, sine, ramp, chirp, pulse train, velocity staircase) and their text specs.

A spec is `KIND:key=value,key=value`, e.g. `sine:amp=2,freq=0.5` (docs/INTERFACE.md). Every profile is a
function of time returning the input value (V, A, N·m or a set-point, depending on who uses it).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from enum import auto

import numpy as np

from model.errors import UserInputError
from model.slots import Slots


class InputSpecError(UserInputError):
    """A malformed input spec; the message names the spec and the key."""


@dataclass(frozen=True)
class ProfileKind:
    """One kind of profile: its keys with defaults (None: required), and its compiled form.

    `vector` checks the values and lays them out for `model.kernel.profile_value` (the run's duration
    given for a chirp without its own), so the profile is evaluated inside the compiled loop.
    """

    keys: dict[str, float | None]
    help: str
    vector: Callable[[dict[str, float], float], list[float]]


# Here rather than in model.kernel: the command line reads KINDS for its help, and model.kernel loads
# numba (~0.2 s).
class Q(Slots):
    """A profile vector's layout, as model.kernel.profile_value reads it: q[Q.KIND] the kind, q[Q.OFFSET]
    added to every value, q[Q.AMP] the amplitude (ramp: slope), then per kind in A, B, C: step (delay),
    sine (freq, phase), ramp (delay), chirps (f0, f1, sweep s), pulse (width, period, delay), staircase
    (steps, hold)."""

    KIND = auto()
    OFFSET = auto()
    AMP = auto()
    A = auto()
    B = auto()
    C = auto()


class Kind(Slots):
    """The profile kinds' codes in q[Q.KIND]."""

    STEP = auto()
    SINE = auto()
    RAMP = auto()
    CHIRP = auto()
    LOG_CHIRP = auto()
    PULSE = auto()
    STAIRCASE = auto()
    CONST = auto()


def _step(q: dict[str, float], _: float) -> list[float]:
    return [Kind.STEP, q["offset"], q["amp"], q["delay"]]


def _sine(q: dict[str, float], _: float) -> list[float]:
    return [Kind.SINE, q["offset"], q["amp"], q["freq"], q["phase"]]


def _ramp(q: dict[str, float], _: float) -> list[float]:
    return [Kind.RAMP, q["offset"], q["slope"], q["delay"]]


def _chirp(q: dict[str, float], duration_s: float) -> list[float]:
    sweep_s = q["duration"] if q["duration"] > 0 else duration_s
    if sweep_s <= 0:
        raise InputSpecError("chirp: needs duration=S or a simulation duration")
    if q["log"] and not q["f0"] * q["f1"] > 0:
        raise InputSpecError("chirp: log=1 needs f0 and f1 nonzero and of one sign")
    kind = Kind.LOG_CHIRP if q["log"] else Kind.CHIRP
    return [kind, q["offset"], q["amp"], q["f0"], q["f1"], sweep_s]


def _pulse(q: dict[str, float], _: float) -> list[float]:
    if q["period"] <= 0 or q["width"] <= 0:
        raise InputSpecError("pulse: width and period must be > 0")
    return [Kind.PULSE, q["offset"], q["amp"], q["width"], q["period"], q["delay"]]


def _staircase(q: dict[str, float], _: float) -> list[float]:
    if q["steps"] < 2 or q["steps"] != int(q["steps"]) or q["hold"] <= 0:
        raise InputSpecError("staircase: needs a whole number of steps ≥ 2 and hold > 0")
    return [Kind.STAIRCASE, q["offset"], q["amp"], q["steps"], q["hold"]]


def _const(q: dict[str, float], _: float) -> list[float]:
    return [Kind.CONST, q["value"], 0.0]


KINDS: dict[str, ProfileKind] = {
    "step": ProfileKind({"amp": None, "delay": 0.0, "offset": 0.0}, "amp from t ≥ delay", _step),
    "sine": ProfileKind(
        {"amp": None, "freq": None, "phase": 0.0, "offset": 0.0}, "amp·sin(2π·freq·t + phase)", _sine
    ),
    "ramp": ProfileKind({"slope": None, "delay": 0.0, "offset": 0.0}, "slope·(t − delay) from delay", _ramp),
    "chirp": ProfileKind(
        {"amp": None, "f0": None, "f1": None, "duration": 0.0, "log": 0.0, "offset": 0.0},
        "sweep f0→f1 Hz over duration (default: the whole run); log=1 for logarithmic",
        _chirp,
    ),
    "pulse": ProfileKind(
        {"amp": None, "width": None, "period": None, "delay": 0.0, "offset": 0.0},
        "amp for width s every period s",
        _pulse,
    ),
    "staircase": ProfileKind(
        {"amp": None, "steps": 9.0, "hold": 1.0, "offset": 0.0},
        "levels from −amp to +amp in `steps` stairs, each held `hold` s",
        _staircase,
    ),
    "const": ProfileKind({"value": None}, "a constant value", _const),
}


@dataclass(frozen=True)
class InputProfile:
    """A parsed profile: call it with sample times to get the input values."""

    kind: str
    values: dict[str, float]

    def vector(self, duration_s: float = 0.0) -> np.ndarray:
        """The profile as `model.kernel.profile_value` evaluates it (in a run of `duration_s`); a value
        its kind refuses raises InputSpecError here."""
        q = np.zeros(len(Q))
        laid_out = KINDS[self.kind].vector(self.values, duration_s)
        q[: len(laid_out)] = laid_out
        return q

    def __call__(self, t: np.ndarray, duration_s: float = 0.0) -> np.ndarray:
        from model import kernel  # numba, only once a profile is evaluated here

        times = np.ascontiguousarray(np.atleast_1d(np.asarray(t, dtype=np.float64)))
        return np.asarray(kernel.profile_values(self.vector(duration_s), times.ravel()).reshape(times.shape))

    @property
    def spec(self) -> str:
        keys = ",".join(f"{k}={v:g}" for k, v in self.values.items())
        return f"{self.kind}:{keys}"


def parse_input_spec(spec: str) -> InputProfile:
    """Parse `KIND:key=value,...`; errors name the spec and the offending part."""
    kind, _, rest = spec.strip().partition(":")
    kind = kind.strip().lower()
    if kind not in KINDS:
        raise InputSpecError(f"input spec {spec!r}: unknown kind {kind!r} (kinds: {', '.join(KINDS)})")
    known = KINDS[kind].keys
    given: dict[str, float] = {}
    for part in filter(None, (s.strip() for s in rest.split(","))):
        key, sep, text = part.partition("=")
        key = key.strip()
        if not sep:
            raise InputSpecError(f"input spec {spec!r}: {part!r} is not key=value")
        if key not in known:
            raise InputSpecError(
                f"input spec {spec!r}: unknown key {key!r} for {kind} (keys: {', '.join(known)})"
            )
        try:
            value = float(text)
        except ValueError:
            raise InputSpecError(f"input spec {spec!r}: {key}={text!r} is not a number") from None
        if not np.isfinite(value):
            raise InputSpecError(f"input spec {spec!r}: {key}={text!r} must be finite")
        given[key] = value
    missing = [key for key, default in known.items() if default is None and key not in given]
    if missing:
        raise InputSpecError(f"input spec {spec!r}: {kind} needs {', '.join(missing)}")
    values = {key: given.get(key, default) for key, default in known.items()}
    return InputProfile(kind, {key: float(v) for key, v in values.items() if v is not None})
