"""A second data generator that shares no code with the project's plant: data nobody here generated.

Written from docs/MODEL.md's equations alone, with other numerics and another rig around them:

- integration: scipy's `solve_ivp` (RK45, tight tolerances) over each control period, with stick and
  breakaway located as events (ω crossing zero; |ψ| reaching the breakaway level; a shaft breaking away
  reaching its stick band's edge) and the stuck shaft held exactly (Karnopp's idea, but event-timed
  rather than a velocity band on a fixed step). As docs/MODEL.md says, a shaft breaking away feels its
  static level until its speed leaves the band, the moving law from there on: with a static level below
  the moving one (static_factor < 1) the moving law at once would brake it back to zero at the instant
  it broke loose, and the stick/slip events would repeat without time advancing (records of such gears
  took hours);
- sensors: a 14-bit motor encoder (not the sim rig's 17), a load encoder of 20 bits per output turn
  plus 3 µrad of noise, 10 mA of current noise;
- control: its own velocity PI at 1 kHz on a filtered encoder difference, driving voltage or current,
  with a clamped integrator;
- profile: its own closed-loop profile (trapezoidal moves over the stroke, slow reversals, start-stop
  moves, load steps), not the gap probe's.

The truth is read from a model file's values (the schema is shared, the physics code is not): the
article or Coulomb–viscous motor law, the `stribeck` and `kinematic_error` sections, Coulomb–viscous–
static load friction, rigid or flexible, and the `thermal` section: a winding and a gear temperature of
its own (the two-node network stepped per control period by its exact exponential, friction power and
i_a²·R as heat; motor friction × exp(−beta_T·(T_g − T_ref))), recorded as temp_gear and temp_motor with
0.05 °C of noise; and the slow drifts `thermal_drift` (time since the record's start) and `wear_drift`
(motor travel since then), both held per control period. Anything else is refused rather than silently
ignored.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.integrate import solve_ivp

from model.params import HarmonicDriveModel
from model.run import Run

ENCODER_BITS = 14
LOAD_ENCODER_BITS = 20
LOAD_NOISE_RAD = 3e-6
CURRENT_NOISE_A = 0.01
TEMPERATURE_NOISE_C = 0.05
SUPPORTED = {
    "mechanics",
    "motor",
    "transmission",
    "motor_friction",
    "load_friction",
    "kinematic_error",
    "stribeck",
    "thermal",
    "thermal_drift",
    "wear_drift",
    "numerics",
    "name",
    "description",
}


@dataclass(frozen=True)
class Controller:
    """Velocity PI on the motor shaft: output [A or V] per rad/s of error, integral per rad of error."""

    kp: float = 0.3
    ki: float = 6.0
    speed_filter_s: float = 0.002  # first-order filter on the encoder difference
    limit: float = 10.0  # output clamp [A or V]; the integrator stops at it (anti-windup)


class _Truth:
    """docs/MODEL.md's torques, evaluated from a model file's values."""

    def __init__(self, model: HarmonicDriveModel) -> None:
        data = model.to_dict()
        extra = set(data) - SUPPORTED
        if extra:
            raise ValueError(f"the independent generator does not implement {sorted(extra)}")
        me, mo, tr, mf = model.mechanics, model.motor, model.transmission, model.motor_friction
        self.J_m, self.J_l, self.r = me.J_m, me.J_l, me.r
        self.K_m, self.K_b, self.R = mo.K_m, mo.K_b, mo.R
        self.K_s, self.D_s = tr.K_s, tr.D_s
        self.law = mf.motor_law
        if self.law not in ("article", "coulomb_viscous"):
            raise ValueError(f"the independent generator does not implement motor_law {self.law}")
        self.mf = mf
        self.b_m = mf.b_m
        lf = model.load_friction
        self.f_cl = (lf.f_cl or 0.0) if lf is not None else 0.0
        self.b_l = lf.b_l if lf is not None else 0.0
        self.f_sl = max(lf.f_sl if lf is not None and lf.f_sl is not None else self.f_cl, self.f_cl)
        ke = model.kinematic_error
        self.A, self.k, self.phi = (ke.A, ke.k, ke.phi) if ke is not None else (0.0, 0.0, 0.0)
        st = model.stribeck
        self.f_st, self.omega_st = (st.f_st, st.omega_st) if st is not None else (0.0, 1.0)
        self.rigid = self.K_s is None
        # stick bands [rad/s]: a shaft breaking away feels its static level until it leaves its band
        self.band = (model.numerics.omega_stick_m, model.numerics.omega_stick_l)
        self.thermal = model.thermal
        # The gear's and the winding's temperatures [°C]: stepped once per control period by the rig.
        th = self.thermal
        self.T_g = th.gear_start_c if th is not None else 25.0
        self.T_w = th.motor_start_c if th is not None else 25.0
        self.drifts = model.thermal_drift is not None or model.wear_drift is not None
        self.d_th, self.tau_th = (
            (model.thermal_drift.d_th, model.thermal_drift.tau_th) if model.thermal_drift else (0.0, 1.0)
        )
        self.k_wear = model.wear_drift.k_wear if model.wear_drift is not None else 0.0
        self.drift = 1.0  # the two drifts' factor, held per control period (`drift_to`)

    def drift_to(self, t_s: float, travel_rad: float) -> None:
        """(1 + d_th·(1 − e^(−t/tau_th)))·(1 + k_wear·travel) at a period's start (docs/MODEL.md)."""
        self.drift = (1 + self.d_th * (1 - math.exp(-t_s / self.tau_th))) * (1 + self.k_wear * travel_rad)

    def scale(self) -> float:
        """Every factor on the motor friction: the grease's law times the drifts (1.0 without them)."""
        return self.warmth() * self.drift

    def warmth(self) -> float:
        """The grease's law: motor friction × exp(−beta_T·(T_g − T_ref)); 1 without a thermal section."""
        th = self.thermal
        return 1.0 if th is None else math.exp(-th.beta_T * (self.T_g - th.T_ref))

    def heat(self, copper_w: float, friction_w: float, h: float) -> None:
        """The two-node network over one period h, by its exact exponential for a held input (each node
        relaxes to the equilibrium its neighbours and sources set): not the kernel's integrator."""
        th = self.thermal
        if th is None:
            return
        g_w = 1 / th.R_wg + 1 / th.R_wa
        target_w = (copper_w + self.T_g / th.R_wg + th.T_amb / th.R_wa) / g_w
        g_g = 1 / th.R_wg + 1 / th.R_ga
        target_g = (friction_w + self.T_w / th.R_wg + th.T_amb / th.R_ga) / g_g
        self.T_w = target_w + (self.T_w - target_w) * math.exp(-h * g_w / th.C_w)
        self.T_g = target_g + (self.T_g - target_g) * math.exp(-h * g_g / th.C_g)

    def _levels(self, theta: float) -> tuple[float, float, float]:
        """(C(θ), P(θ)) for the article law; (F_c, 0) otherwise; and the law's static level at rest."""
        mf = self.mf
        if self.law == "coulomb_viscous":
            return (
                mf.f_cm or 0.0,
                0.0,
                max(mf.f_sm if mf.f_sm is not None else (mf.f_cm or 0.0), mf.f_cm or 0.0),
            )
        c = (mf.s1 or 0.0) * theta * theta + (mf.s2 or 0.0) * theta + (mf.s3 or 0.0)
        a = mf.a or [0.0] * 11
        b = mf.b or [0.0] * 10
        p = a[0] / 2 + sum(a[n] * math.cos(n * theta) + b[n - 1] * math.sin(n * theta) for n in range(1, 11))
        static = (mf.static_factor or 1.0) * max(c * (1 - (mf.k_v or 0.0) * (mf.v_c or 0.0)) + p, 0.0)
        return c, p, static

    def motor_moving(self, theta: float, omega: float, direction: float) -> float:
        """F_m while sliding in `direction` (the sign of ω, or of the push at ω = 0)."""
        c, p, _ = self._levels(theta)
        if self.law == "article":
            mf = self.mf
            level = c * (1 + (mf.k_v or 0.0) * (abs(omega) - (mf.v_c or 0.0))) + p
        else:
            level = c
        level = max(level, 0.0) + self.f_st * math.exp(-((omega / self.omega_st) ** 2))
        return (direction * level + self.b_m * omega) * self.scale()

    def motor_static(self, theta: float) -> float:
        return (self._levels(theta)[2] + self.f_st) * self.scale()

    def spring(self, th_m: float, w_m: float, th_l: float, w_l: float) -> float:
        err = self.A * math.sin(self.k * th_m + self.phi)
        assert self.K_s is not None
        return self.K_s * (self.r * th_m + err - th_l) + self.D_s * (self.r * w_m - w_l)


class IndependentRig:
    """Closed-loop records of a truth model, by another integrator, controller and sensors."""

    def __init__(
        self,
        truth: HarmonicDriveModel,
        drive: str = "current",
        controller: Controller | None = None,
        rate_hz: float = 1000.0,
        seed: int = 0,
        encoder_step: float = 2 * math.pi / 2**ENCODER_BITS,
    ) -> None:
        if drive not in ("current", "voltage"):
            raise ValueError("drive is current or voltage")
        self.p = _Truth(truth)
        self.drive = drive
        self.ctl = controller or (
            Controller() if drive == "current" else Controller(kp=0.1, ki=2.0, limit=24.0)
        )
        self.rate_hz = rate_hz
        self.rng = np.random.default_rng(seed)
        self.encoder_step = encoder_step  # motor position quantum [rad] (a linear axis: its own unit)
        self.loose = [False, False]  # per side: broken loose, still inside its stick band
        self.events_located = 0  # stick/slip events over the record (a count for tests, not a timing)

    # ---- the plant between two control instants ------------------------------------------------------

    def _torque(self, command: float, w_m: float) -> tuple[float, float]:
        """(T_m, i_a) for the held command."""
        p = self.p
        i_a = command if self.drive == "current" else (command - p.K_b * w_m) / p.R
        return p.K_m * i_a, i_a

    def _period(
        self, y: np.ndarray, mode: list[float], command: float, tau_ext: float, h: float
    ) -> np.ndarray:
        """Advance the state over one held command; `mode` holds each side's direction (0: stuck)."""
        p = self.p
        t, t_end = 0.0, h
        for side in range(1 if p.rigid else 2):  # a new command may break a stuck side loose at once
            if not mode[side]:
                self._switch(side, y, mode, command, tau_ext, located=False)
        while t < t_end - 1e-12:
            events, sides = self._events(mode, command, tau_ext)
            sol = solve_ivp(
                lambda _t, s: self._rhs(s, mode, command, tau_ext),
                (t, t_end),
                y,
                method="RK45",
                rtol=1e-8,
                atol=1e-11,
                events=events,
                max_step=h / 2,
            )
            y = sol.y[:, -1].copy()
            t = float(sol.t[-1])
            fired = [sides[i] for i, te in enumerate(sol.t_events) if te.size]
            if not fired:
                break
            self.events_located += len(fired)
            for side, kind in fired:
                if kind == "band":  # out of the band: the moving law from here on
                    self.loose[side] = False
                else:
                    self._switch(side, y, mode, command, tau_ext)
        return y

    def _psi(self, y: np.ndarray, command: float, tau_ext: float) -> tuple[float, float]:
        """Net torque apart from friction on the motor and on the load (rigid: all on the motor)."""
        p = self.p
        t_m, _ = self._torque(command, y[1])
        if p.rigid:
            return t_m - p.r * tau_ext, 0.0
        ts = p.spring(y[0], y[1], y[2], y[3])
        return t_m - p.r * ts, ts - tau_ext

    def _friction(self, y: np.ndarray, mode: list[float], psi: tuple[float, float]) -> tuple[float, float]:
        """Stuck: what balances ψ; broken loose inside the band: the static level; else the moving law."""
        p = self.p
        if not mode[0]:
            f_m = psi[0]
        elif self.loose[0]:
            f_m = mode[0] * self._static(0, y)  # (rigid: the load's static level is in it)
        else:
            f_m = p.motor_moving(y[0], y[1], mode[0])
            if p.rigid:
                f_m += p.r * (mode[0] * p.f_cl + p.b_l * p.r * y[1])
        if p.rigid:
            return f_m, 0.0
        if not mode[1]:
            f_l = psi[1]
        elif self.loose[1]:
            f_l = mode[1] * p.f_sl
        else:
            f_l = mode[1] * p.f_cl + p.b_l * y[3]
        return f_m, f_l

    def _rhs(self, y: np.ndarray, mode: list[float], command: float, tau_ext: float) -> np.ndarray:
        p = self.p
        psi = self._psi(y, command, tau_ext)
        f_m, f_l = self._friction(y, mode, psi)
        if p.rigid:
            inertia = p.J_m + p.r * p.r * p.J_l
            return np.array([y[1], (psi[0] - f_m) / inertia if mode[0] else 0.0])
        dw_m = (psi[0] - f_m) / p.J_m if mode[0] else 0.0
        dw_l = (psi[1] - f_l) / p.J_l if mode[1] else 0.0
        return np.array([y[1] if mode[0] else 0.0, dw_m, y[3] if mode[1] else 0.0, dw_l])

    def _static(self, side: int, y: np.ndarray) -> float:
        p = self.p
        if side == 0:
            return p.motor_static(y[0]) + (p.r * p.f_sl if p.rigid else 0.0)
        return p.f_sl

    def _events(
        self, mode: list[float], command: float, tau_ext: float
    ) -> tuple[list[Any], list[tuple[int, str]]]:
        """solve_ivp events and, per event, (side, kind): a sliding side's speed crossing zero against
        its motion ("stop"); a side broken loose leaving its stick band ("band"); a stuck side's net
        torque reaching its breakaway level ("break")."""
        out: list[Any] = []
        sides: list[tuple[int, str]] = []
        for side in range(1 if self.p.rigid else 2):
            speed = 1 if side == 0 else 3
            event: Any
            leave: Any
            if mode[side] and self.loose[side]:

                def leave(
                    _t: float, s: np.ndarray, speed: int = speed, edge: float = self.p.band[side]
                ) -> float:
                    return abs(float(s[speed])) - edge

                leave.direction = 1
                leave.terminal = True
                out.append(leave)
                sides.append((side, "band"))
            if mode[side]:

                def event(_t: float, s: np.ndarray, speed: int = speed) -> float:
                    return float(s[speed])

                event.direction = -mode[side]
                sides.append((side, "stop"))
            else:
                sides.append((side, "break"))

                def event(_t: float, s: np.ndarray, side: int = side) -> float:
                    return abs(self._psi(s, command, tau_ext)[side]) - self._static(side, s)

                event.direction = 1
            event.terminal = True
            out.append(event)
        return out, sides

    def _switch(
        self,
        side: int,
        y: np.ndarray,
        mode: list[float],
        command: float,
        tau_ext: float,
        located: bool = True,
    ) -> None:
        """At a located event: a sliding side stops and sticks or reverses; a stuck side breaks away
        (and feels its static level until it leaves its band)."""
        speed = 1 if side == 0 else 3
        psi = self._psi(y, command, tau_ext)[side]
        if not mode[side] and located:  # the breakaway event: |ψ| reached the static level
            mode[side] = math.copysign(1.0, psi)
            self.loose[side] = True
            return
        y[speed] = 0.0
        mode[side] = 0.0 if abs(psi) <= self._static(side, y) else math.copysign(1.0, psi)
        self.loose[side] = bool(mode[side])

    # ---- the rig around it -----------------------------------------------------------------------------

    def record(self, speed_rad_s: np.ndarray, tau_ext_nm: np.ndarray, with_load: bool = True) -> Run:
        """Play a motor-speed set-point and an output load per control cycle; the recorded run."""
        p = self.p
        h = 1.0 / self.rate_hz
        n = len(speed_rad_s)
        y = np.zeros(2 if p.rigid else 4)
        mode = [0.0, 0.0]
        self.loose = [False, False]
        q_m = self.encoder_step
        q_l = 2 * math.pi / 2**LOAD_ENCODER_BITS
        cols = {
            c: np.empty(n)
            for c in ("t", "theta_m", "theta_l", "i_a", "cmd", "tau_ext", "temp_gear", "temp_motor")
        }
        integral, speed_est, last_count = 0.0, 0.0, 0.0
        travel = 0.0  # motor travel since the start [rad], summed per period (reversals inside one: rare)
        alpha = h / (self.ctl.speed_filter_s + h)
        for i in range(n):
            count = math.floor(y[0] / q_m) * q_m
            speed_est += alpha * ((count - last_count) / h - speed_est) if i else 0.0
            last_count = count
            error = speed_rad_s[i] - speed_est
            raw = self.ctl.kp * error + integral
            command = min(max(raw, -self.ctl.limit), self.ctl.limit)
            if command == raw:
                integral += self.ctl.ki * error * h
            _, i_a = self._torque(command, y[1])
            th_l = p.r * y[0] + p.A * math.sin(p.k * y[0] + p.phi) if p.rigid else y[2]
            cols["t"][i] = i * h
            cols["theta_m"][i] = count
            cols["theta_l"][i] = math.floor(th_l / q_l) * q_l + self.rng.normal(0, LOAD_NOISE_RAD)
            cols["i_a"][i] = i_a + self.rng.normal(0, CURRENT_NOISE_A)
            cols["cmd"][i] = command
            cols["tau_ext"][i] = tau_ext_nm[i]
            if p.thermal is not None:  # (no draws otherwise: records without it stay as they were)
                cols["temp_gear"][i] = p.T_g + self.rng.normal(0, TEMPERATURE_NOISE_C)
                cols["temp_motor"][i] = p.T_w + self.rng.normal(0, TEMPERATURE_NOISE_C)
                # the heat of this period, from the state at its start
                f_m, f_l = self._friction(y, mode, self._psi(y, command, float(tau_ext_nm[i])))
                w_l = p.r * y[1] if p.rigid else y[3]
                p.heat(i_a * i_a * p.R, abs(f_m * y[1]) + (0.0 if p.rigid else abs(f_l * w_l)), h)
            if p.drifts:
                p.drift_to(i * h, travel)
            before = y[0]
            y = self._period(y, mode, command, float(tau_ext_nm[i]), h)
            travel += abs(y[0] - before)
        input_column = "i_cmd" if self.drive == "current" else "u"
        cols[input_column] = cols.pop("cmd")
        if not with_load:
            cols.pop("theta_l")
        if p.thermal is None:
            cols.pop("temp_gear")
            cols.pop("temp_motor")
        return Run(cols, {"source": "hdrig_testing.independent_plant", "input_column": input_column})


def lab_profile(
    duration_s: float, rate_hz: float = 1000.0, load_nm: float = 4.0
) -> tuple[np.ndarray, np.ndarray]:
    """Motor speed set-point [rad/s] and output load [N·m] per cycle: the lab's own closed-loop profile.

    35 %: trapezoidal moves out and back at 30–120 rad/s; 30 %: slow triangular reversals up to 6 rad/s;
    20 %: start-stop moves at ±2.5 rad/s with rests; 15 %: 40 rad/s both ways. Load steps of ±`load_nm`
    at the output every 2.3 s throughout.
    """
    n = round(duration_s * rate_hz)
    t = np.arange(n) / rate_hz
    v = np.zeros(n)
    edges = np.cumsum([0.0, 0.35, 0.30, 0.20, 0.15]) * duration_s
    part = np.searchsorted(edges, t, side="right") - 1
    moves = t[part == 0] - edges[0]
    cycle = (edges[1] - edges[0]) / 4
    top = 30 + 90 * (np.floor(moves / cycle) / 3)
    phase = np.mod(moves, cycle) / cycle
    ramp = np.clip(np.minimum(phase, 0.5 - phase) * 10, 0, 1) - np.clip(
        np.minimum(phase - 0.5, 1 - phase) * 10, 0, 1
    )
    v[part == 0] = top * ramp
    slow = t[part == 1] - edges[1]
    v[part == 1] = 6.0 * (2 / math.pi) * np.arcsin(np.sin(2 * math.pi * 0.4 * slow))
    rest = np.mod(t[part == 2] - edges[2], 1.6)
    v[part == 2] = np.where((rest >= 0.3) & (rest < 0.7), 2.5, 0.0) - np.where(
        (rest >= 1.1) & (rest < 1.5), 2.5, 0.0
    )
    fast = t[part == 3] - edges[3]
    v[part == 3] = np.where(np.mod(fast, 2.0) < 1.0, 40.0, -40.0)
    steps = np.floor(t / 2.3)
    tau = load_nm * np.where(np.mod(steps, 3) == 1, 1.0, np.where(np.mod(steps, 3) == 2, -1.0, 0.0))
    return v, tau


def single_axis_profile(duration_s: float, rate_hz: float = 1000.0) -> np.ndarray:
    """A positioning axis' velocity set-point: back-and-forth moves at several speeds, with rests."""
    n = round(duration_s * rate_hz)
    t = np.arange(n) / rate_hz
    speeds = np.array([0.5, 1.0, 0.25, 0.75])
    period = 2.0
    k = np.floor(t / period).astype(int)
    phase = np.mod(t, period) / period
    shape = np.where(phase < 0.4, 1.0, np.where((phase >= 0.5) & (phase < 0.9), -1.0, 0.0))
    return speeds[k % len(speeds)] * shape
