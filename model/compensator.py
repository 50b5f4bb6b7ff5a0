"""Model-based feed-forward: the track a drive needs so that the *output* follows a position trajectory.

From a model (in practice one fitted on the same rig) and motor set-points θ_ref per cycle, the output
is asked to follow θ_l = θ_origin-output + r·(θ_ref − θ_origin). Inverting docs/MODEL.md for that:

1. Load side: T_s = J_l·α_l + F_l(ω_l) + τ_ext, the torque the transmission must pass [N·m].
2. Twist: the spring must be deflected by δ = T_s/K_s (or the catalog curve's inverse) for that.
3. Kinematic error: the motor must stand where r·θ_m + A·sin(k·θ_m + φ) = θ_l + δ. With A·k > r (the
   article's seed: A·k = 5·r) that map folds back on itself, so no smooth θ_m gives a monotonic output.
   It is inverted on windows of phase [2πn − w, 2πn + w] on which it rises, w chosen so that the end of
   one window has the same output as the start of the next (A·sin w + r·w/k = π·r/k); crossing a window
   boundary the motor jumps forward (2π − 2w)/k through the falling part of the error, in `jump_s`
   along a minimum-jerk path centred on the crossing, which the inertia term below drives. The output
   dips and recovers during the jump; its net impulse is small because the path crosses the error's
   peak and trough alike. With A·k ≤ r the window is the whole turn and nothing jumps.
4. Motor torque: J_m·α_m + r·T_s + F_m(θ_m, ω_m), F_m by the model's own law (the article's with its
   position terms, or any baseline) through the kernel's level functions: one copy of the physics.

Rates come from central differences of the set-points; a set-point jump faster than `max_speed_rad_s`
(a step) is not a trajectory and gets no inertia or rate term there. The twist is smoothed over
`jump_s` (zero phase), so a kink (a ramp's reversal, where ideal feed-forward is an impulse and the load
friction flips sign) becomes a short transition the loop can follow.

Not inverted: transmission damping D_s (default 0, and not identifiable from the campaign), hysteresis,
the bristle states of LuGre/Dahl (their steady friction is used), thermal drift (time zero).
`friction_scale` multiplies every friction the plan predicts: the ±20 % runs of the experiment.

Temperature (issue 27 item 7): the motor friction is planned at the thermal law's T_ref. With
`temperature` and a model whose `thermal` section has a nonzero beta_T, the track carries the law, and
a rig that measures the gear's temperature plays the friction columns at it as the run goes
(`FeedForwardTrack.at_temperature`, `Rig.run_segment`); a rig without the probe plays them at T_ref.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from model import kernel as k
from model.feedforward import (
    FF_FRICTION,
    FF_LEVEL,
    FF_OMEGA,
    FF_THETA,
    FF_TORQUE,
    N_FF_COLUMNS,
    FeedForwardTrack,
)
from model.params import HarmonicDriveModel
from model.plant import kernel_vectors
from model.registry import FL, Law, P


@njit(cache=True)
def _motor_friction(
    p: np.ndarray, flags: np.ndarray, theta: np.ndarray, omega: np.ndarray, t_s: np.ndarray
) -> np.ndarray:
    """F_m at each (θ_m, ω_m, T_s) by the kernel's steady moving branch (0 at ω = 0)."""
    out = np.empty(theta.shape[0])
    for i in range(theta.shape[0]):
        out[i] = k.steady_motor_friction(p, flags, theta[i : i + 1], omega[i : i + 1], t_s[i], 0.0)[0]
    return out


@njit(cache=True)
def _load_friction(p: np.ndarray, flags: np.ndarray, omega_l: np.ndarray) -> np.ndarray:
    """F_l at each ω_l: the moving branch of a Karnopp law, the steady state of LuGre/Dahl (0 at rest)."""
    law = flags[FL.LOAD_LAW]
    out = np.zeros(omega_l.shape[0])
    if law == Law.NONE:
        return out
    for i in range(omega_l.shape[0]):
        w = omega_l[i]
        if w == 0.0:
            continue
        if law == Law.LUGRE or law == Law.DAHL:
            level = p[P.F_CL]
            if law == Law.LUGRE:
                x = w / p[P.OMEGA_SL]
                level = p[P.F_CL] + (p[P.F_SL] - p[P.F_CL]) * math.exp(-x * x)
        else:
            level, _ = k.load_levels(p, law, abs(w))
        out[i] = math.copysign(level, w) + p[P.B_L] * w
    return out


def fold_window_rad(A: float, k_cycles: float, r: float) -> float:
    """Half-width w of the rising phase windows of r·θ + A·sin(k·θ + φ) that tile the output (see doc).

    π when the map is monotonic (A·k ≤ r); otherwise the smallest root of A·sin w + r·w/k = π·r/k,
    which lies below the fold at arccos(−r/(A·k)).
    """
    if A * k_cycles <= r:
        return math.pi

    def excess(w: float) -> float:
        return A * math.sin(w) + r * w / k_cycles - math.pi * r / k_cycles

    lo, hi = 0.0, math.acos(-r / (A * k_cycles))
    for _ in range(200):  # bisection to machine precision: excess(lo) < 0 < excess(hi)
        mid = 0.5 * (lo + hi)
        if excess(mid) < 0.0:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def _min_jerk_kernel(cycles: int) -> np.ndarray:
    """Weights (sum 1) whose running sum is the minimum-jerk step 10s³ − 15s⁴ + 6s⁵ over `cycles`.

    An odd count, so that centred on a cycle it shifts nothing by half a cycle.
    """
    cycles |= 1
    if cycles < 2:
        return np.ones(1)
    s = np.linspace(0.0, 1.0, cycles + 1)
    step = 10 * s**3 - 15 * s**4 + 6 * s**5
    return np.diff(step)


def _centred_spread(impulses: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """Convolve impulses with `kernel` centred on each impulse (the ends keep what falls inside)."""
    full = np.convolve(impulses, kernel)
    start = (kernel.shape[0] - 1) // 2
    return full[start : start + impulses.shape[0]]


def _rates(theta: np.ndarray, dt_s: float, jumps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Central-difference speed and acceleration; a backward step marked in `jumps` counts as no motion."""
    step = np.diff(theta, prepend=theta[0]) / dt_s
    step[jumps] = 0.0
    ahead = np.append(step[1:], step[-1])
    return 0.5 * (step + ahead), (ahead - step) / dt_s


class Compensator:
    """Plans feed-forward tracks from one model; `friction_scale` scales every friction it predicts."""

    def __init__(
        self, model: HarmonicDriveModel, friction_scale: float = 1.0, temperature: bool = True
    ) -> None:
        self.model = model
        self.friction_scale = friction_scale
        law = model.thermal
        self.thermal = (
            (law.beta_T, law.T_ref) if temperature and law is not None and law.beta_T != 0.0 else None
        )
        self.p, self.flags = kernel_vectors(model)
        ke = model.kinematic_error
        self.ke_A, self.ke_k, self.ke_phi = (ke.A, ke.k, ke.phi) if ke is not None else (0.0, 1.0, 0.0)
        r = model.mechanics.r
        self.window_rad = fold_window_rad(self.ke_A, self.ke_k, r)
        self.jump_rad = (2 * math.pi - 2 * self.window_rad) / self.ke_k  # motor travel at a window boundary
        # The error's frequency k·ω_m must stay a third below the load's resonance for the load to follow
        # it (a rigid output follows anything: 5 Hz, within a position loop's reach).
        k_s = model.transmission.K_s
        resonance_rad_s = math.sqrt(k_s / model.mechanics.J_l) if k_s else 2 * math.pi * 5.0 * 3
        self.ke_max_speed_rad_s = resonance_rad_s / (3.0 * self.ke_k)
        self.resonance_period_s = 2 * math.pi / resonance_rad_s

    # --- the kinematic error ------------------------------------------------------------------------

    def output_of(self, theta_m: np.ndarray) -> np.ndarray:
        """r·θ_m + θ_err(θ_m): the output angle of an undeflected transmission [rad]."""
        phase = self.ke_k * np.asarray(theta_m) + self.ke_phi
        return self.model.mechanics.r * np.asarray(theta_m) + self.ke_A * np.sin(phase)

    def invert_output(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Motor angles θ with output_of(θ) = y, on the rising windows; (θ, window index n) [rad, –]."""
        y = np.asarray(y, dtype=np.float64)
        r, A, kk, phi, w = self.model.mechanics.r, self.ke_A, self.ke_k, self.ke_phi, self.window_rad
        if A == 0.0:
            return y / r, np.zeros(y.shape, dtype=np.int64)
        period_out = 2 * math.pi * r / kk  # output advance per error cycle
        start0 = r * (-w - phi) / kk - A * math.sin(w)  # output at the start of window 0
        n = np.floor((y - start0) / period_out).astype(np.int64)
        lo = (2 * math.pi * n - w - phi) / kk
        hi = (2 * math.pi * n + w - phi) / kk
        for _ in range(60):  # bisection: the map rises on the window, 60 halvings reach 1e-18 rad
            mid = 0.5 * (lo + hi)
            below = self.output_of(mid) < y
            lo = np.where(below, mid, lo)
            hi = np.where(below, hi, mid)
        return 0.5 * (lo + hi), n

    # --- the transmission ---------------------------------------------------------------------------

    def twist_rad(self, t_s: np.ndarray) -> np.ndarray:
        """Deflection δ that passes T_s: T_s/K_s, or the inverse of the catalog's piecewise curve [rad]."""
        model = self.model
        if model.rigid:
            return np.zeros_like(t_s)
        ns = model.nonlinear_stiffness
        if ns is None:
            return t_s / float(model.transmission.K_s or 1.0)
        mag = np.abs(t_s)
        d1 = ns.T1 / ns.K1
        d2 = d1 + (ns.T2 - ns.T1) / ns.K2
        defl = np.where(
            mag <= ns.T1,
            mag / ns.K1,
            np.where(mag <= ns.T2, d1 + (mag - ns.T1) / ns.K2, d2 + (mag - ns.T2) / ns.K3),
        )
        return np.sign(t_s) * defl

    # --- the plan -----------------------------------------------------------------------------------

    def plan(
        self,
        theta_ref_rad: np.ndarray,
        dt_s: float,
        origin_rad: float,
        max_speed_rad_s: float,
        tau_ext_nm: np.ndarray | float = 0.0,
        jump_s: float = 0.016,
        smooth_s: float = 0.008,
        measured_band_rad_s: float = 0.0,
        label: str = "compensation",
    ) -> FeedForwardTrack:
        """The track for motor set-points `theta_ref_rad`, one per cycle of `dt_s`.

        `origin_rad` is the motor angle where output and set-point are taken to agree (the program's
        start); `max_speed_rad_s` the fastest set-point change taken as motion rather than a jump.
        """
        theta_ref = np.asarray(theta_ref_rad, dtype=np.float64)
        n_cycles = theta_ref.shape[0]
        tau_ext = np.broadcast_to(np.asarray(tau_ext_nm, dtype=np.float64), (n_cycles,))
        m = self.model.mechanics
        scale = self.friction_scale
        ref_jumps = np.abs(np.diff(theta_ref, prepend=theta_ref[0])) > max_speed_rad_s * dt_s
        omega_ref, alpha_ref = _rates(theta_ref, dt_s, ref_jumps)

        # 1–2: the load's torque and the twist it needs, smoothed over the jump time.
        omega_l, alpha_l = m.r * omega_ref, m.r * alpha_ref
        t_s = m.J_l * alpha_l + scale * _load_friction(self.p, self.flags, omega_l) + tau_ext
        smooth = _min_jerk_kernel(max(1, round(smooth_s / dt_s)))
        padded = np.concatenate([np.full(smooth.shape[0], t_s[0]), t_s, np.full(smooth.shape[0], t_s[-1])])
        t_s = _centred_spread(padded, smooth)[smooth.shape[0] : smooth.shape[0] + n_cycles]

        # 3: where the motor must be for the output to be at r·(θ_ref − origin) + its start value.
        y = self.output_of(np.array([origin_rad]))[0] + m.r * (theta_ref - origin_rad) + self.twist_rad(t_s)
        theta_win, window = self.invert_output(y)
        steps = np.diff(window, prepend=window[0]).astype(np.float64)
        smooth_steps = np.where(ref_jumps, 0.0, steps)  # a step set-point jumps; a crossing glides
        glide = _centred_spread(smooth_steps, _min_jerk_kernel(max(1, round(jump_s / dt_s))))
        theta_inv = theta_win + self.jump_rad * (np.cumsum(glide) - np.cumsum(smooth_steps))
        # Fast, the error cycles outrun the load (it sees their mean, zero): invert it only where the
        # speed stays low over a period of the load's resonance (a sine's turning point is too short).
        window = np.ones(max(1, round(self.resonance_period_s / dt_s)))
        mean_speed = _centred_spread(np.abs(omega_ref), window / window.shape[0])
        slow = np.clip(2.0 - mean_speed / self.ke_max_speed_rad_s, 0.0, 1.0)
        theta_cmd = y / m.r + slow * (theta_inv - y / m.r)
        omega_m, alpha_m = _rates(theta_cmd, dt_s, ref_jumps)

        # 4: the motor's torque.
        friction = scale * _motor_friction(self.p, self.flags, theta_cmd, omega_m, t_s)
        level = scale * np.abs(_motor_friction(self.p, self.flags, theta_cmd, np.full(n_cycles, 1e-12), t_s))
        rows = np.empty((n_cycles, N_FF_COLUMNS))
        rows[:, FF_THETA] = theta_cmd
        rows[:, FF_OMEGA] = omega_m
        # A drive holds each cycle's torque until the next: aim it at the middle of that cycle.
        torque = m.J_m * alpha_m + m.r * t_s
        rows[:, FF_TORQUE] = 0.5 * (torque + np.append(torque[1:], torque[-1]))
        rows[:, FF_FRICTION] = friction
        rows[:, FF_LEVEL] = level
        return FeedForwardTrack(rows, measured_band_rad_s, label, self.thermal)
