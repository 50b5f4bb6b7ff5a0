"""A third data generator: many flexible gears at once on a fixed step, numpy across the gears.

The event-timed generator (`independent_plant`) locates every stick and slip with `solve_ivp`; on a gear
whose static level lies below its moving one (static_factor < 1, a third of the ±30 % draws) the shaft
creeps through its stick band in a break-loose / brake-to-zero cycle of a few tens of µs, and a 46 s
record takes 10–20 min. This one steps a fixed `dt` (20 µs by default, 50 steps per control period) for
all gears in one Python loop over time, each gear a column of numpy arrays, with its own handling of
standstill written from docs/MODEL.md's text (not the project's kernel):

- a sliding shaft whose speed would change sign within a step stops at zero at that step's end and is
  stuck from there (the event is taken up to one step late: the reason its records differ from the
  event-timed ones by a fraction of an encoder count, tests/test_independent_batch.py);
- a stuck shaft stays at rest while |ψ| ≤ its static level, else breaks away feeling its static level
  until its speed leaves the stick band, the moving law from then on;
- positions and speeds by semi-implicit Euler (speed first): no energy drift on the undamped spring.

The rig around the plant is the event-timed generator's (same 14-bit motor encoder, load encoder and
noise levels, voltage-mode velocity PI, same noise draws for the same seed), so the two can be compared
record for record. Only what the drawn-gear benchmark needs is implemented: flexible transmission,
the article's motor law, Coulomb–viscous–static load friction, the motion error; anything else is
refused.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from hdrig_testing.independent_plant import (
    CURRENT_NOISE_A,
    ENCODER_BITS,
    LOAD_ENCODER_BITS,
    LOAD_NOISE_RAD,
    Controller,
)
from model.params import HarmonicDriveModel
from model.run import Run

SUPPORTED = {
    "mechanics",
    "motor",
    "transmission",
    "motor_friction",
    "load_friction",
    "kinematic_error",
    "numerics",
    "name",
    "description",
}
HARMONICS = 10


class _Gears:
    """docs/MODEL.md's parameters of G gears, one array entry per gear."""

    def __init__(self, models: list[HarmonicDriveModel]) -> None:
        for m in models:
            extra = set(m.to_dict()) - SUPPORTED
            if extra:
                raise ValueError(f"the batch generator does not implement {sorted(extra)}")
            if m.transmission.K_s is None:
                raise ValueError("the batch generator needs a flexible transmission (K_s set)")
            if m.motor_friction.motor_law != "article":
                raise ValueError(
                    f"the batch generator implements motor_law article, not {m.motor_friction.motor_law}"
                )
            if m.load_friction is not None and m.load_friction.load_law != "coulomb_viscous":
                raise ValueError("the batch generator implements load_law coulomb_viscous only")

        def col(get: Callable[[HarmonicDriveModel], float]) -> np.ndarray:
            return np.array([float(get(m)) for m in models])

        self.J_m, self.J_l, self.r = (
            col(lambda m: m.mechanics.J_m),
            col(lambda m: m.mechanics.J_l),
            col(lambda m: m.mechanics.r),
        )
        self.K_m, self.K_b, self.R = (
            col(lambda m: m.motor.K_m),
            col(lambda m: m.motor.K_b),
            col(lambda m: m.motor.R),
        )
        self.K_s, self.D_s = (
            col(lambda m: m.transmission.K_s or 0.0),
            col(lambda m: m.transmission.D_s or 0.0),
        )
        mf = [m.motor_friction for m in models]
        self.s1 = np.array([f.s1 or 0.0 for f in mf])
        self.s2 = np.array([f.s2 or 0.0 for f in mf])
        self.s3 = np.array([f.s3 or 0.0 for f in mf])
        self.k_v = np.array([f.k_v or 0.0 for f in mf])
        self.v_c = np.array([f.v_c or 0.0 for f in mf])
        self.static_factor = np.array([f.static_factor or 1.0 for f in mf])
        self.b_m = np.array([f.b_m or 0.0 for f in mf])
        self.a0 = np.array([(f.a or [0.0])[0] for f in mf])
        self.a = np.array([(f.a or [0.0] * 11)[1:] for f in mf])  # (G, 10): a1..a10
        self.b = np.array([f.b or [0.0] * HARMONICS for f in mf])  # (G, 10): b1..b10
        lf = [m.load_friction for m in models]
        self.f_cl = np.array([(f.f_cl or 0.0) if f is not None else 0.0 for f in lf])
        self.b_l = np.array([(f.b_l or 0.0) if f is not None else 0.0 for f in lf])
        self.f_sl = np.maximum(
            np.array(
                [(f.f_sl if f.f_sl is not None else (f.f_cl or 0.0)) if f is not None else 0.0 for f in lf]
            ),
            self.f_cl,
        )
        ke = [m.kinematic_error for m in models]
        self.A = np.array([k.A if k is not None else 0.0 for k in ke])
        self.k = np.array([k.k if k is not None else 0.0 for k in ke])
        self.phi = np.array([k.phi if k is not None else 0.0 for k in ke])
        self.band_m = col(lambda m: m.numerics.omega_stick_m)
        self.band_l = col(lambda m: m.numerics.omega_stick_l)
        self.n = np.arange(1, HARMONICS + 1)

    def motor_levels(self, theta: np.ndarray, speed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(moving magnitude at |speed|, static level) of the article's motor law at θ_m, never below 0."""
        c = (self.s1 * theta + self.s2) * theta + self.s3
        nt = theta[:, None] * self.n
        p = self.a0 / 2 + np.sum(self.a * np.cos(nt) + self.b * np.sin(nt), axis=1)
        moving = np.maximum(c * (1 + self.k_v * (np.abs(speed) - self.v_c)) + p, 0.0)
        static = self.static_factor * np.maximum(c * (1 - self.k_v * self.v_c) + p, 0.0)
        return moving, static


def _side_step(
    w: np.ndarray,
    mode: np.ndarray,
    loose: np.ndarray,
    psi: np.ndarray,
    sliding_friction: np.ndarray,
    static: np.ndarray,
    band: np.ndarray,
    inertia: np.ndarray,
    dt: float,
) -> np.ndarray:
    """One step of one shaft's speed for all gears; `mode` (−1, 0, +1) and `loose` updated in place.

    Stuck: stays while |ψ| ≤ static, else breaks away in ψ's direction (loose). Loose: friction is the
    static level until |ω| leaves the band. Sliding: the moving law; a sign change within the step
    stops the shaft at zero (stuck from there)."""
    breaks = (mode == 0) & (np.abs(psi) > static)
    mode[breaks] = np.sign(psi[breaks])
    loose[breaks] = True
    friction = np.where(loose, mode * static, sliding_friction)
    w_new = np.where(mode != 0, w + dt * (psi - friction) / inertia, 0.0)
    stops = (mode != 0) & (w_new * mode < 0)
    w_new[stops] = 0.0
    mode[stops] = 0
    loose[stops] = False
    loose &= np.abs(w_new) < band
    return w_new


class BatchRig:
    """Closed-loop records of several gears at once: the event-timed rig's sensors and controller
    (voltage drive), a fixed-step plant."""

    def __init__(
        self,
        truths: list[HarmonicDriveModel],
        seeds: list[int],
        rate_hz: float = 1000.0,
        steps_per_period: int = 50,
        controller: Controller | None = None,
    ) -> None:
        if len(truths) != len(seeds) or not truths:
            raise ValueError("one noise seed per gear, at least one gear")
        if steps_per_period < 1:
            raise ValueError(f"steps_per_period must be ≥ 1, got {steps_per_period}")
        self.p = _Gears(truths)
        self.ctl = controller or Controller(kp=0.1, ki=2.0, limit=24.0)  # the event rig's voltage default
        self.rate_hz = rate_hz
        self.steps = steps_per_period
        self.rngs = [np.random.default_rng(s) for s in seeds]

    def _spring(self, th_m: np.ndarray, w_m: np.ndarray, th_l: np.ndarray, w_l: np.ndarray) -> np.ndarray:
        p = self.p
        err = p.A * np.sin(p.k * th_m + p.phi)
        return p.K_s * (p.r * th_m + err - th_l) + p.D_s * (p.r * w_m - w_l)

    def _period(self, state: list[np.ndarray], modes: list[np.ndarray], u: np.ndarray, tau: float) -> None:
        """Advance every gear over one held voltage `u` and load `tau` (state and modes in place)."""
        p = self.p
        th_m, w_m, th_l, w_l = state
        dt = 1.0 / (self.rate_hz * self.steps)
        for _ in range(self.steps):
            t_s = self._spring(th_m, w_m, th_l, w_l)
            t_m = p.K_m * (u - p.K_b * w_m) / p.R
            moving, static = p.motor_levels(th_m, w_m)
            psi_m = t_m - p.r * t_s
            psi_l = t_s - tau
            w_m = _side_step(
                w_m, modes[0], modes[1], psi_m, modes[0] * moving + p.b_m * w_m, static, p.band_m, p.J_m, dt
            )
            w_l = _side_step(
                w_l, modes[2], modes[3], psi_l, modes[2] * p.f_cl + p.b_l * w_l, p.f_sl, p.band_l, p.J_l, dt
            )
            th_m = th_m + dt * w_m
            th_l = th_l + dt * w_l
        state[:] = [th_m, w_m, th_l, w_l]

    def record(self, speed_rad_s: np.ndarray, tau_ext_nm: np.ndarray) -> list[Run]:
        """Play one motor-speed set-point and one output load per control cycle on every gear."""
        p = self.p
        g = len(p.J_m)
        h = 1.0 / self.rate_hz
        n = len(speed_rad_s)
        state = [np.zeros(g) for _ in range(4)]
        modes = [np.zeros(g), np.zeros(g, dtype=bool), np.zeros(g), np.zeros(g, dtype=bool)]
        q_m = 2 * math.pi / 2**ENCODER_BITS
        q_l = 2 * math.pi / 2**LOAD_ENCODER_BITS
        # the event rig draws (load noise, current noise) per cycle: the same stream, drawn at once
        noise = np.stack([rng.standard_normal((n, 2)) for rng in self.rngs], axis=1)  # (n, G, 2)
        out = {c: np.empty((n, g)) for c in ("theta_m", "theta_l", "i_a", "u")}
        integral, speed_est, last_count = np.zeros(g), np.zeros(g), np.zeros(g)
        alpha = h / (self.ctl.speed_filter_s + h)
        for i in range(n):
            count = np.floor(state[0] / q_m) * q_m
            if i:
                speed_est += alpha * ((count - last_count) / h - speed_est)
            last_count = count
            error = speed_rad_s[i] - speed_est
            raw = self.ctl.kp * error + integral
            u = np.clip(raw, -self.ctl.limit, self.ctl.limit)
            integral = np.where(u == raw, integral + self.ctl.ki * error * h, integral)
            out["theta_m"][i] = count
            out["theta_l"][i] = np.floor(state[2] / q_l) * q_l + LOAD_NOISE_RAD * noise[i, :, 0]
            out["i_a"][i] = (u - p.K_b * state[1]) / p.R + CURRENT_NOISE_A * noise[i, :, 1]
            out["u"][i] = u
            self._period(state, modes, u, float(tau_ext_nm[i]))
        t = np.arange(n) * h
        meta = {"source": "hdrig_testing.independent_batch", "input_column": "u"}
        return [
            Run(
                {
                    "t": t,
                    **{c: v[:, j].copy() for c, v in out.items()},
                    "tau_ext": np.asarray(tau_ext_nm, float),
                },
                meta,
            )
            for j in range(g)
        ]
