"""Staged identification from the torque transducers: the output equation and the input equation.

A dynamometer bench (docs/CATALOG_TESTS.md) carries in-line transducers at both shafts (run columns
`tau_in`, `tau_out` [N·m], docs/INTERFACE.md):

- `tau_out`, in the output shaft between the gear's output and the load drive's rotor, reads what the
  gear passes on: tau_out = T_s − F_l − J_l·dω_l/dt, J_l the gear's own output inertia (ahead of the
  transducer). So, over a steady window's stretch of time,

      mean(T_s − F_l) = mean tau_out + J_l·Δω_l/T,   T_s = K_s·(r·θ_m + θ_err − θ_l − offset)

  linear in K_s, K_s·offset, f_cl, b_l and J_l: the load's balance of `dynamics_stage`'s stiffness stage
  with the transducer in place of the load drive's torque. It needs no motor friction, no K_m, and none
  of what the load drive does beyond the transducer (its rotor's inertia, its bearings' friction, its
  current loop's lag): the drive's `tau_ext` column is the torque it is asked for or applies, its bearing
  friction is not in it, so the stiffness stage on a bench's `tau_ext` puts that friction into f_cl, b_l.
- `tau_in`, in the input shaft, reads the torque the gear takes in, r·T_s + F_m; with the output
  equation, tau_in − r·tau_out = F_m + r·F_l + r·J_l·dω_l/dt: the velocity stage's window equation with
  the transducers in place of K_m·i_a − J_m·dω_m/dt and τ_ext (no K_m, no J_m).

Both reuse the windows, the span-wise averages and the fits of `dynamics_stage` and `friction_stage`
(one copy of the equations): the runs are handed over with the transducers' columns in place of the
drive's (`output_run`, `input_run`). The standard errors are the windows' leave-one-out sandwich
(`nonlinear_fit(unequal_rows=True)`): each window's mean is one row, so noise correlated inside a window
(the transducer's, the ringing load's) is counted as the window's scatter, not as independent samples.

What the steady windows cannot give: D_s (the twist's rate averages to r·ω_m − ω_l ≈ 0 in a steady
window: the FRF stage's), f_sl (the load's breakaway is not in steady windows: held).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from model.params import HarmonicDriveModel
from model.run import Run
from rig.analysis.fit.parameters import with_values
from rig.analysis.identification.dynamics_stage import (
    Held,
    Solved,
    stiffness_and_load_friction,
    sweep_parts,
)
from rig.analysis.identification.friction_stage import velocity_friction

OUTPUT = "tau_out"
INPUT = "tau_in"
SWEEPS = ("speed-sweep", "load-variation")
"""The experiments whose steady windows the transducer stage reads."""
NO_MOTOR_INERTIA_KGM2 = 1e-15
"""J_m handed to the velocity stage on the input transducer's windows: tau_in is read beyond the motor's
rotor, so no J_m·dω_m/dt belongs in its balance (the schema wants J_m > 0; this is nothing beside it)."""


def with_transducer(runs: Sequence[Run], column: str) -> list[Run]:
    """The sweep runs that carry the transducer `column`."""
    return [run for run in runs if column in run and run.meta.get("experiment") in SWEEPS]


def output_run(run: Run) -> Run:
    """The run with tau_out as its τ_ext: the stiffness stage's load balance then reads the output
    transducer's torque where it read the load drive's."""
    return Run({**run.columns, "tau_ext": run[OUTPUT]}, run.meta)


def input_run(run: Run) -> Run:
    """The run with tau_in/K_m as its current and tau_out as its τ_ext: the velocity stage's motor balance
    K_m·i_a − r·τ_ext then reads tau_in − r·tau_out = F_m + r·F_l + r·J_l·dω_l/dt."""
    k_m = float(run.meta["torque_constant_nm_per_a"])
    return Run({**run.columns, "i_a": run[INPUT] / k_m, "tau_ext": run[OUTPUT]}, run.meta)


def distinct_loads(runs: Sequence[Run], model: HarmonicDriveModel) -> int:
    """How many different loads the steady windows hold, by the drive's own τ_ext (the transducer's mean
    differs from window to window by its noise, so it cannot say whether two windows share a load)."""
    loads = set()
    for part in sweep_parts(runs, model):
        if np.any(part.steady):
            loads.add(round(float(np.mean(part.mean(part.run["tau_ext"]))), 3))
    return len(loads)


def output_equation(runs: Sequence[Run], model: HarmonicDriveModel) -> Solved:
    """K_s (or K1..K3), f_cl, b_l from the output transducer's steady windows (see the module).

    J_l fitted with them is the gear's output inertia ahead of the transducer (`J_l_gear` in the
    metrics), not the whole output's the frequency response sees; the load sensor's zero and A are
    metrics as in the stiffness stage."""
    used = [run for run in with_transducer(runs, OUTPUT) if "theta_l" in run]
    out = Solved()
    if not used:
        out.notes.append(f"skipped: no steady sweep with {OUTPUT} and a load angle")
        return out
    if distinct_loads(used, model) < 2:
        out.notes.append(
            f"skipped: {OUTPUT}'s steady windows under one load only: the twist is then F_l/K_s, and the"
            " stiffness cannot be parted from the load's friction (a load-variation run parts them)"
        )
        return out
    solved = stiffness_and_load_friction(sweep_parts([output_run(run) for run in used], model), model)
    source = (
        f"source {OUTPUT} (output transducer): mean T_s − F_l = tau_out + J_l·Δω_l/T, no motor friction"
        " and no load drive in it"
    )
    return _told_by(solved, source, _gear_words)


def _gear_words(note: str) -> str:
    """The stiffness stage's note in the output equation's words: its τ_ext is tau_out, its J_l the gear's."""
    return note.replace("τ_ext", OUTPUT).replace("J_l =", "J_l of the gear =")


def input_equation(runs: Sequence[Run], model: HarmonicDriveModel, held: Held | None = None) -> Solved:
    """The motor law's velocity parameters from tau_in − r·tau_out on the steady windows (see the module):
    the velocity stage's fit, K_m and J_m out of it. F_l is the model's (the output equation's, when it
    ran)."""
    used = [run for run in with_transducer(runs, INPUT) if OUTPUT in run]
    if not used:
        out = Solved()
        out.notes.append(f"skipped: no steady sweep with both {INPUT} and {OUTPUT}")
        return out
    rotorless = with_values(model, {"J_m": NO_MOTOR_INERTIA_KGM2})
    solved = velocity_friction(sweep_parts([input_run(run) for run in used], rotorless), rotorless, held)
    source = (
        f"source {INPUT} (input transducer): tau_in − r·tau_out = F_m + r·F_l + r·J_l·Δω_l/T, no K_m, no J_m"
    )
    return _told_by(solved, source)


def _told_by(solved: Solved, source: str, words: Callable[[str], str] = str) -> Solved:
    """A stage's fit on a transducer's run told as the transducer's: the J_l fitted beside it is the
    gear's own (`J_l_gear`), and each note opens with `source`."""
    if "J_l" in solved.metrics:
        solved.metrics["J_l_gear"] = solved.metrics.pop("J_l")
        solved.metrics["J_l_gear_std"] = solved.metrics.pop("J_l_std")
    solved.notes = [f"{source}; {words(note)}" for note in solved.notes]
    return solved
