"""A simulated servo drive around the plant: its loops, its sensors, its envelope — compiled, per cycle.

Each cycle: measure (encoder quantization, filtered encoder-difference speed, current and output-angle
noise), check the envelope, compute the command (voltage as given; current as given or from the
velocity/position loops, limited by what the bus voltage can push), record the sample, then integrate
the plant over the cycle with that command held. A feed-forward track (`model.feedforward`) replaces the
position loop's target by its planned motor angle and adds its torque to the velocity loop's current, as
a drive's torque offset does. The in-process backend and the CANopen twin both use
it, so the simulated drive behaves the same whichever way it is reached.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from model import kernel as k
from model.feedforward import FF_THETA, N_FF_COLUMNS, FeedForwardTrack, loop_torque_nm
from model.plant import Plant
from model.registry import N_OUT, OUT, Mode, P, X
from rig.config import RigConfig
from rig.control import N_CONTROL_STATE, S_PREV_POSITION_REF, S_RATE, gains_vector, position_p, velocity_pi
from rig.interface import SAMPLE_COLUMNS, ControlMode
from rig.safety import NO_ABORT, envelope_breach, limits_vector

MODE_CODES = {
    ControlMode.VOLTAGE: 0,
    ControlMode.CURRENT: 1,
    ControlMode.VELOCITY: 2,
    ControlMode.POSITION: 3,
}
C_T, C_U, C_I_CMD, C_TAU, C_THETA_M, C_OMEGA_M, C_THETA_L, C_I_A, C_SETPOINT = range(len(SAMPLE_COLUMNS))

# Drive constants vector: what the drive knows of its motor and bus, and its sensors.
D_K_B, D_R, D_SUPPLY, D_QUANTUM, D_FILTER_ALPHA, D_CURRENT_NOISE, D_LOAD_NOISE, D_PERIOD, D_K_M = range(9)
# Sensor state: last quantized position [rad], filtered speed [rad/s].
M_THETA_PREV, M_OMEGA = range(2)
_NO_FEEDFORWARD = np.empty((0, N_FF_COLUMNS))
# Load drive vector (a dynamometer's torque-controlled drive on the output, `load_drive` in the rig file):
# present (1/0), current-loop lag factor per cycle, torque limit [N·m], its bearing's Coulomb [N·m] and
# viscous [N·m·s/rad] friction, and the speed over which that Coulomb part goes smoothly through zero [rad/s].
L_ON, L_ALPHA, L_LIMIT, L_COULOMB, L_VISCOUS, L_SMOOTH = range(6)
LOAD_FRICTION_SMOOTH_RAD_S = 0.01
"""The load drive's bearing friction is applied once per cycle from the cycle's start speed, so its
Coulomb part is a tanh of speed over this band rather than a sign (a sign, held a whole cycle, would chatter
at rest); the gear's own load friction keeps the kernel's stick model."""
_NO_LOAD_DRIVE = np.zeros(6)

# The plant's truth per cycle (opt-in, `SimulatedDrive.record_truth`): the states at the cycle's start (as
# the sample is taken), the torques averaged over the cycle's substeps (their mean is what changes the
# speeds over the cycle), the share of substeps each body spent stuck (velocity held at exactly 0), and the
# winding's and gear's temperatures at the cycle's start [°C] (the model's `thermal` section; NaN without).
TRUTH_COLUMNS = (
    "t",
    "theta_m",
    "omega_m",
    "theta_l",
    "omega_l",
    "i_a",
    "tau_m",
    "tau_ext",
    "t_s",
    "f_m",
    "f_l",
    "stuck_m",
    "stuck_l",
    "temp_motor",
    "temp_gear",
)
(
    T_T,
    T_THETA_M,
    T_OMEGA_M,
    T_THETA_L,
    T_OMEGA_L,
    T_I_A,
    T_TAU_M,
    T_TAU_EXT,
    T_T_S,
    T_F_M,
    T_F_L,
    T_STUCK_M,
    T_STUCK_L,
    T_TEMP_MOTOR,
    T_TEMP_GEAR,
) = range(len(TRUTH_COLUMNS))
_NO_TRUTH = np.empty((0, len(TRUTH_COLUMNS)))


@njit(cache=True)
def _truth_row(rows: np.ndarray, t: float, truth_row: np.ndarray) -> None:
    """One cycle's truth from its substeps' kernel rows (model.registry's OUT columns)."""
    n = rows.shape[0]
    truth_row[T_T] = t
    truth_row[T_THETA_M] = rows[0, OUT.THETA_M]
    truth_row[T_OMEGA_M] = rows[0, OUT.OMEGA_M]
    truth_row[T_THETA_L] = rows[0, OUT.THETA_L]
    truth_row[T_OMEGA_L] = rows[0, OUT.OMEGA_L]
    truth_row[T_TEMP_MOTOR] = rows[0, OUT.TEMP_MOTOR]
    truth_row[T_TEMP_GEAR] = rows[0, OUT.TEMP_GEAR]
    for column, out in (
        (T_I_A, OUT.I_A),
        (T_TAU_M, OUT.TAU_M),
        (T_TAU_EXT, OUT.TAU_EXT),
        (T_T_S, OUT.T_S),
        (T_F_M, OUT.F_M),
        (T_F_L, OUT.F_L),
    ):
        total = 0.0
        for j in range(n):
            total += rows[j, out]
        truth_row[column] = total / n
    stuck_m = 0
    stuck_l = 0
    for j in range(n):
        stuck_m += rows[j, OUT.OMEGA_M] == 0.0
        stuck_l += rows[j, OUT.OMEGA_L] == 0.0
    truth_row[T_STUCK_M] = stuck_m / n
    truth_row[T_STUCK_L] = stuck_l / n


@njit(cache=True)
def run_cycles(
    p: np.ndarray,
    flags: np.ndarray,
    x: np.ndarray,
    drive: np.ndarray,
    gains: np.ndarray,
    control_state: np.ndarray,
    sensor_state: np.ndarray,
    lim: np.ndarray,
    mode: int,
    setpoint: np.ndarray,
    tau_ext: np.ndarray,
    noise: np.ndarray,
    substeps: int,
    dt: float,
    t0: float,
    out: np.ndarray,
    ff: np.ndarray,
    ff_band: float,
    truth: np.ndarray,
    load_drive: np.ndarray,
    load_state: np.ndarray,
) -> tuple[int, int]:
    """Run len(setpoint) cycles from time t0; fill `out` rows (SAMPLE_COLUMNS). Returns (rows, abort).

    `ff`: a feed-forward track's rows for these cycles (position mode), or an empty array for none.
    `truth`: rows of TRUTH_COLUMNS to fill per cycle, or an empty array for none (the kernel then writes
    one row a cycle, as without it; with it, one a substep: the same steps either way).
    `load_drive` (L_* entries): when on, `tau_ext` is the load drive's torque command: it is limited, lags
    through the current loop (`load_state[0]` holds the torque it applies), and its bearing friction adds;
    the sample's `tau_ext` is the torque it applies.
    """
    has_ff = ff.shape[0] > 0
    record = truth.shape[0] > 0
    period = drive[D_PERIOD]
    quantum = drive[D_QUANTUM]
    held = np.empty(substeps)
    load = np.empty(1)
    decim = 1 if record else substeps
    row_buf = np.empty((substeps if record else 1, N_OUT))
    for c in range(setpoint.shape[0]):
        theta = x[X.THETA_M]
        theta_meas = math.floor(theta / quantum + 0.5) * quantum if quantum > 0.0 else theta
        raw_speed = (theta_meas - sensor_state[M_THETA_PREV]) / period
        sensor_state[M_THETA_PREV] = theta_meas
        sensor_state[M_OMEGA] += drive[D_FILTER_ALPHA] * (raw_speed - sensor_state[M_OMEGA])
        omega_meas = sensor_state[M_OMEGA]

        sp = setpoint[c]
        position_error = 0.0
        if mode == 0:
            u = sp
            i_true = (u - p[P.K_B] * x[X.OMEGA_M]) / p[P.R_ARM]
            i_cmd = i_true
            plant_mode = Mode.VOLTAGE
            value = u
        else:
            if mode == 1:
                i_cmd = sp
            elif mode == 2:
                i_cmd = velocity_pi(gains, control_state, sp, omega_meas, period)
            else:
                position_error = sp - theta_meas  # the envelope watches the set-point asked for
                target = ff[c, FF_THETA] if has_ff else sp
                offset = loop_torque_nm(ff, c, ff_band, omega_meas) / drive[D_K_M] if has_ff else 0.0
                rate_alpha = drive[D_FILTER_ALPHA] if has_ff else 1.0
                omega_ref = position_p(gains, control_state, target, theta_meas, period, rate_alpha)
                i_cmd = velocity_pi(gains, control_state, omega_ref, omega_meas, period, offset)
            # The bus voltage bounds the current the drive can push at this speed.
            back_emf = drive[D_K_B] * omega_meas
            i_hi = (drive[D_SUPPLY] - back_emf) / drive[D_R]
            i_lo = (-drive[D_SUPPLY] - back_emf) / drive[D_R]
            i_cmd = min(max(i_cmd, i_lo), i_hi)
            u = drive[D_R] * i_cmd + back_emf
            i_true = i_cmd
            plant_mode = Mode.CURRENT
            value = i_cmd
        i_meas = i_true + drive[D_CURRENT_NOISE] * noise[c, 0]

        out[c, C_T] = t0 + c * period
        out[c, C_U] = u
        out[c, C_I_CMD] = i_cmd
        if load_drive[L_ON] != 0.0:
            limit = load_drive[L_LIMIT]
            asked = min(max(tau_ext[c], -limit), limit)
            load_state[0] += load_drive[L_ALPHA] * (asked - load_state[0])
            applied = load_state[0]
            omega_l = x[X.OMEGA_L]
            bearing = load_drive[L_COULOMB] * math.tanh(omega_l / load_drive[L_SMOOTH])
            load_torque = applied + bearing + load_drive[L_VISCOUS] * omega_l
        else:
            applied = tau_ext[c]
            load_torque = applied
        out[c, C_TAU] = applied
        out[c, C_THETA_M] = theta_meas
        out[c, C_OMEGA_M] = omega_meas
        out[c, C_THETA_L] = x[X.THETA_L] + drive[D_LOAD_NOISE] * noise[c, 1]
        out[c, C_I_A] = i_meas
        out[c, C_SETPOINT] = sp
        code = envelope_breach(lim, u, i_meas, omega_meas, theta_meas, position_error)
        if code != NO_ABORT:
            return c + 1, code

        held[:] = value
        load[0] = load_torque
        k.integrate(p, flags, x, plant_mode, held, load, dt, decim, row_buf)
        if record:
            _truth_row(row_buf, t0 + c * period, truth[c])
    return setpoint.shape[0], NO_ABORT


class SimulatedDrive:
    """The plant plus a drive's loops and sensors; stepped a block of cycles at a time."""

    def __init__(self, plant: Plant, config: RigConfig) -> None:
        self.plant = plant
        self.config = config
        period = 1.0 / config.sample_rate_hz
        self.substeps = max(1, round(period / config.sim_dt_s))
        self.dt_s = period / self.substeps
        sensors, motor = config.sensors, plant.model.motor
        quantum = 2 * math.pi / sensors.encoder_counts_per_rev if sensors.encoder_counts_per_rev else 0.0
        alpha = (
            1.0 - math.exp(-2 * math.pi * sensors.velocity_filter_hz * period)
            if sensors.velocity_filter_hz
            else 1.0
        )
        self.drive = np.array(
            [
                motor.K_b,
                motor.R,
                config.control.supply_voltage_v,
                quantum,
                alpha,
                sensors.current_noise_a,
                sensors.load_sensor_noise_rad,
                period,
                motor.K_m,
            ]
        )
        self.gains = gains_vector(config.control)
        self.limits = limits_vector(config.limits, plant.model.mechanics.r)
        self.control_state = np.zeros(N_CONTROL_STATE)
        self.sensor_state = np.zeros(2)
        self.rng = np.random.default_rng(sensors.seed)
        ld = config.load_drive
        self.load_drive = _NO_LOAD_DRIVE
        if ld is not None:
            bandwidth = ld.current_bandwidth_hz
            lag = 1.0 - math.exp(-2 * math.pi * bandwidth * period) if bandwidth else 1.0
            self.load_drive = np.array(
                [1.0, lag, ld.torque_limit_nm, ld.coulomb_nm, ld.viscous_nms, LOAD_FRICTION_SMOOTH_RAD_S]
            )
        self.load_state = np.zeros(1)
        self.truth: list[np.ndarray] | None = None
        """Blocks of TRUTH_COLUMNS rows, one per cycle run, while `record_truth` is on (tests)."""
        self.reset_loops()

    def record_truth(self, on: bool = True) -> None:
        """Keep the plant's true states and torques of every cycle from now on (off: none, the default)."""
        self.truth = [] if on else None

    def reset_loops(self) -> None:
        """Clear integrators and filters, as a drive does on enable; no bump in the speed estimate."""
        theta = float(self.plant.x[X.THETA_M])
        quantum = self.drive[D_QUANTUM]
        self.sensor_state[M_THETA_PREV] = math.floor(theta / quantum + 0.5) * quantum if quantum else theta
        self.sensor_state[M_OMEGA] = float(self.plant.x[X.OMEGA_M])
        self.control_state[:] = 0.0
        self.control_state[S_PREV_POSITION_REF] = self.sensor_state[M_THETA_PREV]
        self._mode: ControlMode | None = None
        self._compensating = False

    def run(
        self,
        mode: ControlMode,
        setpoint: np.ndarray,
        tau_ext: np.ndarray,
        t0: float,
        feedforward: FeedForwardTrack | None = None,
    ) -> tuple[np.ndarray, int]:
        """Run the cycles; return the sample rows taken and the abort code."""
        n = setpoint.shape[0]
        if mode != self._mode:
            # Entering a mode, the position loop's feed-forward starts from where the motor is.
            self.control_state[S_PREV_POSITION_REF] = self.sensor_state[M_THETA_PREV]
            self._mode = mode
        if (feedforward is not None) != self._compensating:
            # The planned angle differs from the set-point: the rate feed-forward must not see the switch.
            first = feedforward.theta_cmd_rad[0] if feedforward is not None else setpoint[0]
            self.control_state[S_PREV_POSITION_REF] = first
            self.control_state[S_RATE] = 0.0
            self._compensating = feedforward is not None
        out = np.empty((n, len(SAMPLE_COLUMNS)))
        truth = np.empty((n, len(TRUTH_COLUMNS))) if self.truth is not None else _NO_TRUTH
        noise = self.rng.standard_normal((n, 2))
        rows, code = run_cycles(
            self.plant.p,
            self.plant.flags,
            self.plant.x,
            self.drive,
            self.gains,
            self.control_state,
            self.sensor_state,
            self.limits,
            MODE_CODES[mode],
            np.ascontiguousarray(setpoint, dtype=np.float64),
            np.ascontiguousarray(tau_ext, dtype=np.float64),
            noise,
            self.substeps,
            self.dt_s,
            t0,
            out,
            np.ascontiguousarray(feedforward.rows) if feedforward is not None else _NO_FEEDFORWARD,
            feedforward.measured_band_rad_s if feedforward is not None else 0.0,
            truth,
            self.load_drive,
            self.load_state,
        )
        if self.truth is not None:
            self.truth.append(truth[:rows])
        return out[:rows], code
