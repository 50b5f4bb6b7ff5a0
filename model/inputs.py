"""Input profiles (step, sine, ramp, chirp, pulse train, velocity staircase) and their text specs.

A spec is `KIND:key=value,key=value`, e.g. `sine:amp=2,freq=0.5` (docs/INTERFACE.md). Every profile is a
function of time returning the input value (V, A, N·m or a set-point, depending on who uses it).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from model.errors import UserInputError


class InputSpecError(UserInputError):
    """A malformed input spec; the message names the spec and the key."""


@dataclass(frozen=True)
class ProfileKind:
    """One kind of profile: its keys with defaults (None: required) and its function of time."""

    keys: dict[str, float | None]
    help: str
    evaluate: Callable[[dict[str, float], np.ndarray, float], np.ndarray]


def _step(q: dict[str, float], t: np.ndarray, _: float) -> np.ndarray:
    return q["offset"] + np.where(t >= q["delay"], q["amp"], 0.0)


def _sine(q: dict[str, float], t: np.ndarray, _: float) -> np.ndarray:
    return q["offset"] + q["amp"] * np.sin(2 * np.pi * q["freq"] * t + q["phase"])


def _ramp(q: dict[str, float], t: np.ndarray, _: float) -> np.ndarray:
    return q["offset"] + q["slope"] * np.clip(t - q["delay"], 0.0, None)


def _chirp(q: dict[str, float], t: np.ndarray, duration_s: float) -> np.ndarray:
    sweep_s = q["duration"] if q["duration"] > 0 else duration_s
    if sweep_s <= 0:
        raise InputSpecError("chirp: needs duration=S or a simulation duration")
    from scipy.signal import chirp as scipy_chirp  # scipy.signal takes ~0.7 s to import: only for chirps

    method = "logarithmic" if q["log"] else "linear"
    # scipy's chirp starts at cos(0) = 1; a sine start keeps the input continuous from rest.
    return q["offset"] + q["amp"] * scipy_chirp(t, q["f0"], sweep_s, q["f1"], method=method, phi=-90)


def _pulse(q: dict[str, float], t: np.ndarray, _: float) -> np.ndarray:
    if q["period"] <= 0 or q["width"] <= 0:
        raise InputSpecError("pulse: width and period must be > 0")
    phase = np.mod(t - q["delay"], q["period"])
    on = (t >= q["delay"]) & (phase < q["width"])
    return q["offset"] + np.where(on, q["amp"], 0.0)


def _staircase(q: dict[str, float], t: np.ndarray, _: float) -> np.ndarray:
    steps = int(q["steps"])
    if steps < 2 or q["hold"] <= 0:
        raise InputSpecError("staircase: needs steps ≥ 2 and hold > 0")
    levels = np.linspace(-q["amp"], q["amp"], steps)
    index = np.clip((t // q["hold"]).astype(np.int64), 0, steps - 1)
    return q["offset"] + levels[index]


def _const(q: dict[str, float], t: np.ndarray, _: float) -> np.ndarray:
    return np.full_like(t, q["value"], dtype=np.float64)


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

    def __call__(self, t: np.ndarray, duration_s: float = 0.0) -> np.ndarray:
        return np.asarray(KINDS[self.kind].evaluate(self.values, np.asarray(t, dtype=np.float64), duration_s))

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
