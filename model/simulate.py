"""Open-loop simulation to the run format: a profile over a duration, or a replay of a run's inputs."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

import numpy as np

from model import kernel as k
from model.errors import UserInputError
from model.inputs import InputProfile, parse_input_spec
from model.params import HarmonicDriveModel
from model.plant import INPUT_COLUMN, MODE_OF_COLUMN, MODES, InputMode, Plant
from model.registry import OUT
from model.run import Run, RunFormatError

SIM_COLUMNS = ("t", "theta_m", "omega_m", "theta_l", "omega_l", "i_a", "tau_ext")
DIAGNOSTIC_COLUMNS = {"tau_m": OUT.TAU_M, "F_m": OUT.F_M, "F_l": OUT.F_L, "T_s": OUT.T_S}
_CHANNEL = {
    "t": OUT.T,
    "theta_m": OUT.THETA_M,
    "omega_m": OUT.OMEGA_M,
    "theta_l": OUT.THETA_L,
    "omega_l": OUT.OMEGA_L,
    "i_a": OUT.I_A,
    "tau_ext": OUT.TAU_EXT,
}


class SimulationError(UserInputError):
    """Simulation settings that cannot work (a step that does not divide the sample period...)."""


def _as_profile(value: InputProfile | str | float) -> InputProfile:
    if isinstance(value, InputProfile):
        return value
    if isinstance(value, str):
        return parse_input_spec(value)
    return InputProfile("const", {"value": float(value)})


def _run_from_rows(
    rows: np.ndarray, mode: InputMode, meta: dict[str, Any], diagnostics: bool, t: np.ndarray | None = None
) -> Run:
    columns = {name: rows[:, ch].copy() for name, ch in _CHANNEL.items()}
    if t is not None:
        columns["t"] = t.copy()
    columns[INPUT_COLUMN[mode]] = rows[:, OUT.DRIVE].copy()
    if diagnostics:
        columns.update({name: rows[:, ch].copy() for name, ch in DIAGNOSTIC_COLUMNS.items()})
    return Run(columns, meta)


def _meta(model: HarmonicDriveModel, rate_hz: float, **extra: Any) -> dict[str, Any]:
    return {
        "sample_rate_hz": rate_hz,
        "source": "sim",
        "model": {"name": model.name, "hash": model.content_hash()},
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
        **extra,
    }


CHUNK_ROWS = 1 << 15
"""Samples per chunk at most: what a chunk holds in memory (~3 MB), whatever the duration."""
CHUNK_STEPS = 1 << 22
"""Integration steps per chunk at most (~0.2 s of the loop), so a sparse output still streams in pieces."""
MAX_SAMPLES = 100_000_000
"""Samples one simulation may write (28 h at 1 kHz, ~8 GB of ten float64 columns): a longer one is
refused before its first step, not left to fill the disk."""
SPECIALIZE_STEPS = 20_000_000
"""Steps from which the loop is compiled for the model's structure (`kernel.specialized_profiles_loop`,
~10 ns a step less on the seed preset): below, it would save < 0.2 s a run, while the first compile for
a structure costs 3-7 s (once; numba's disk cache keeps it)."""
MAX_STEPS = 10_000_000_000
"""Integration steps one simulation may take (28 h at dt 1e-5 s; ~10 min of the compiled loop at its
16.6 M steps/s, docs/BENCHMARKS.md)."""


@dataclass
class SimulationStream:
    """A simulation not yet run: its metadata and columns now, its samples block by block when iterated.

    Iterating integrates the next chunk of steps and yields its samples, so a run of any duration
    is simulated and written (`rig.store.runfile.write_stream`) with memory bounded by one chunk.
    """

    meta: dict[str, Any]
    columns: list[str]
    rows: int  # samples the whole simulation yields
    _blocks: Callable[[], Iterator[dict[str, np.ndarray]]]

    def __iter__(self) -> Iterator[dict[str, np.ndarray]]:
        return self._blocks()


def simulate_stream(
    model: HarmonicDriveModel,
    input: InputProfile | str | float,
    duration_s: float,
    dt_s: float = 1e-4,
    rate_hz: float = 1000.0,
    mode: InputMode = "voltage",
    tau_ext: InputProfile | str | float = 0.0,
    theta_m0: float = 0.0,
    diagnostics: bool = False,
) -> SimulationStream:
    """`simulate`, chunk by chunk: each chunk's steps are integrated with the inputs evaluated inside the
    compiled loop (`model.kernel.integrate_profiles`) and its samples yielded in turn, so memory does
    not grow with the duration. Settings are checked now, before any step."""
    if not (duration_s > 0 and math.isfinite(duration_s)):
        raise SimulationError(f"duration must be a positive number of seconds, got {duration_s}")
    if not (0 < dt_s <= 0.01):
        raise SimulationError(f"dt must be in (0, 0.01] s, got {dt_s}")
    decim = round(1.0 / (rate_hz * dt_s)) if rate_hz > 0 else 0
    if decim < 1 or not math.isclose(decim * dt_s * rate_hz, 1.0, rel_tol=1e-6):
        raise SimulationError(
            f"the sample period 1/rate = {1 / rate_hz if rate_hz > 0 else math.inf:g} s must be a whole"
            f" multiple of dt = {dt_s:g} s"
        )
    n_steps = round(duration_s / dt_s)
    rows = -(-n_steps // decim)
    if rows > MAX_SAMPLES or n_steps > MAX_STEPS:
        raise SimulationError(
            f"duration {duration_s:g} s is {rows:.3g} samples at {rate_hz:g} Hz ({n_steps:.3g} steps of"
            f" {dt_s:g} s): a simulation writes at most {MAX_SAMPLES:.0e} samples and takes at most"
            f" {MAX_STEPS:.0e} steps; shorten --duration or lower --rate"
        )
    profile = _as_profile(input)
    load = _as_profile(tau_ext)
    # A chunk is a whole number of sample periods, so every chunk starts on a sample. The inputs are
    # evaluated inside the compiled loop, so a chunk holds only its samples, and few long chunks keep
    # the per-chunk work in Python (the file writer's checks) small beside the loop's.
    chunk = decim * max(1, min(CHUNK_ROWS, CHUNK_STEPS // decim))
    drive_q, load_q = profile.vector(duration_s), load.vector(duration_s)  # a bad spec fails here
    meta = _meta(model, rate_hz, experiment="simulate", input=profile.spec, input_mode=mode, dt_s=dt_s)
    if load.kind != "const" or load.values["value"] != 0.0:
        meta["tau_ext"] = load.spec
    channels = {**_CHANNEL, INPUT_COLUMN[mode]: OUT.DRIVE}
    if diagnostics:
        channels.update(DIAGNOSTIC_COLUMNS)

    def blocks() -> Iterator[dict[str, np.ndarray]]:
        plant = Plant(model)
        plant.reset(theta_m=theta_m0)
        out = np.empty((chunk // decim, len(OUT)))
        code = MODES[mode]
        loop = k.profiles_loop(plant.flags, specialized=n_steps >= SPECIALIZE_STEPS)
        for first in range(0, n_steps, chunk):
            n = min(chunk, n_steps - first)
            rows = loop(plant.p, plant.x, code, drive_q, load_q, float(first), n, dt_s, decim, out)
            yield {name: out[:rows, ch].copy() for name, ch in channels.items()}

    return SimulationStream(meta, list(channels), -(-n_steps // decim), blocks)


def simulate(
    model: HarmonicDriveModel,
    input: InputProfile | str | float,
    duration_s: float,
    dt_s: float = 1e-4,
    rate_hz: float = 1000.0,
    mode: InputMode = "voltage",
    tau_ext: InputProfile | str | float = 0.0,
    theta_m0: float = 0.0,
    diagnostics: bool = False,
) -> Run:
    """Simulate `model` driven by a profile for `duration_s`; samples at `rate_hz` in the run format.

    The input is evaluated at every integration step (not only at the samples). With
    `diagnostics=True` the run also carries τ_m, F_m, F_l and T_s, the torques the model applied.
    Memory holds the samples kept, not the steps: `simulate_stream` writes runs longer than memory.
    """
    stream = simulate_stream(model, input, duration_s, dt_s, rate_hz, mode, tau_ext, theta_m0, diagnostics)
    columns = {name: np.empty(stream.rows) for name in stream.columns}
    row = 0
    for block in stream:
        n = len(block["t"])
        for name, values in block.items():
            columns[name][row : row + n] = values
        row += n
    return Run(columns, stream.meta)


def substeps(interval_s: float, dt_s: float) -> int:
    """Integration steps in one sample interval: as many as keep each step at most `dt_s` (the replay's
    rule, which the trajectory fit needs to know where the replay holds its speed)."""
    return max(1, math.ceil(interval_s / dt_s - 1e-9))


def replay(model: HarmonicDriveModel, run: Run, dt_s: float = 1e-4, diagnostics: bool = False) -> Run:
    """Drive `model` with the input columns of `run` on its own time base, from its first state.

    Inputs are held between samples (as a digital drive holds them). Each sample interval is cut into
    equal steps no longer than `dt_s`, so irregular time bases from real hardware replay exactly.
    """
    mode = replay_mode(run)
    rows = replay_rows(Plant(model), run, mode, dt_s)
    meta = _meta(model, run.sample_rate_hz, experiment="replay", input_mode=mode, dt_s=dt_s)
    meta["replayed"] = {k_: run.meta[k_] for k_ in ("experiment", "source", "created") if k_ in run.meta}
    return _run_from_rows(rows, mode, meta, diagnostics, t=run.t)


def replay_mode(run: Run) -> InputMode:
    """The input mode a run's input column implies; an error naming what is missing if none."""
    column = run.input_column
    if column is None:
        raise RunFormatError("run has no input column: replay needs one of u, i_cmd, tau_m")
    return MODE_OF_COLUMN[column]


def replay_rows(
    plant: Plant,
    run: Run,
    mode: InputMode,
    dt_s: float,
    time_s: float = 0.0,
    hidden: np.ndarray | None = None,
) -> np.ndarray:
    """Reset `plant` to the run's first state and drive it with the run's inputs; kernel rows per sample.

    The plant is reused, so a fitter replaying many windows compiles the model into it only once. A
    window cut from a longer run passes its time since the run's start (`time_s`) and, if known, the
    unseen states there (`hidden`, see `model.plant.HIDDEN_STATES`).
    """
    t = run.t
    drive = run[INPUT_COLUMN[mode]]
    load = run["tau_ext"] if "tau_ext" in run else np.zeros(len(t))
    plant.reset(
        theta_m=float(run["theta_m"][0]),
        omega_m=float(run["omega_m"][0]) if "omega_m" in run else 0.0,
        theta_l=float(run["theta_l"][0]) if "theta_l" in run else None,
        omega_l=float(run["omega_l"][0]) if "omega_l" in run else None,
        time_s=time_s,
        hidden=hidden,
    )
    intervals = np.diff(t)
    counts = np.array([substeps(h, dt_s) for h in intervals])
    steps = intervals / counts
    rows = np.empty((len(t), len(OUT)))
    if np.allclose(steps, steps[0], rtol=1e-9, atol=0.0) and np.all(counts == counts[0]):
        # Regular time base: one compiled call for the whole run.
        n = int(counts[0])
        got = plant.advance(np.repeat(drive[:-1], n), mode, np.repeat(load[:-1], n), float(steps[0]), n)
        rows[:-1] = got
    else:
        for i, (n, h) in enumerate(zip(counts, steps, strict=True)):
            rows[i] = plant.advance(np.full(n, drive[i]), mode, load[i : i + 1], float(h), n)[0]
    # The last sample: the state reached at the end, with the last input applied to it.
    rows[-1] = plant.advance(drive[-1:], mode, load[-1:], dt_s, 1)[0]
    return rows
