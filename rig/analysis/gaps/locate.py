"""Where a residual lives: over time, speed, motor angle (harmonics of one motor turn), direction, near
reversals, and in frequency. The report plots these and writes their one-line summaries."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import welch

from rig.analysis.gaps.residual import Residual
from rig.analysis.gaps.signals import Signals, spread

CHANNEL_UNITS = {"motor": "N·m", "load": "N·m at the output", "load_position": "rad at the output"}
REVERSAL_S = 0.05  # "near a reversal": within this time of a change of direction
ANGLE_BINS = 24
SPEED_EDGES = np.array([0.0, 0.1, 0.3, 1.0, 3.0, 10.0, 30.0, 100.0, np.inf])


@dataclass
class Where:
    """A residual channel binned by where it occurs."""

    channel: str
    time_s: np.ndarray  # block centres, runs one after another
    time_rms: np.ndarray
    speed_rms: np.ndarray  # per SPEED_EDGES bin of |ω_m| (nan: no data)
    angle_mean: np.ndarray  # per ANGLE_BINS bin of θ_m mod 2π: mean of residual·sgn ω (motor) or residual
    harmonic: int  # of one motor turn, the largest in residual·sgn ω over θ_m
    harmonic_share: float
    forward: float  # mean residual moving forward, backward, at rest
    backward: float
    at_rest: float
    near_reversal_rms: float
    elsewhere_rms: float
    frequency_hz: float  # dominant frequency of the residual
    rms: float

    def lines(self) -> list[str]:
        unit = CHANNEL_UNITS[self.channel]
        worst = int(np.nanargmax(self.time_rms)) if self.time_rms.size else 0
        median = float(np.nanmedian(self.time_rms)) if self.time_rms.size else 0.0
        speed = int(np.nanargmax(self.speed_rms)) if np.any(np.isfinite(self.speed_rms)) else 0
        lo, hi = SPEED_EDGES[speed], SPEED_EDGES[speed + 1]
        return [
            f"RMS {self.rms:.3g} {unit}",
            f"over time: largest around t = {self.time_s[worst]:.1f} s (RMS {self.time_rms[worst]:.3g},"
            f" {self.time_rms[worst] / max(median, 1e-300):.1f}× the median block)",
            f"over speed: largest at |ω_m| in [{lo:g}, {hi:g}) rad/s (RMS {self.speed_rms[speed]:.3g})",
            f"near reversals (±{REVERSAL_S * 1000:.0f} ms): RMS {self.near_reversal_rms:.3g}, elsewhere"
            f" {self.elsewhere_rms:.3g}",
            f"by direction: mean {self.forward:+.3g} forward, {self.backward:+.3g} backward,"
            f" {self.at_rest:+.3g} at rest",
            f"over motor angle: harmonic {self.harmonic} of one motor turn carries"
            f" {100 * self.harmonic_share:.0f} % of the residual's variance",
            f"in frequency: dominant at {self.frequency_hz:.3g} Hz",
        ]


def channel_of(residual: Residual, channel: str) -> np.ndarray:
    value = getattr(residual, channel)
    if value is None:
        raise ValueError(f"no {channel} channel in this residual")
    return np.asarray(value)


def _near_reversals(sig: Signals) -> np.ndarray:
    """Samples within REVERSAL_S of a change of the direction of motion (rests in between skipped)."""
    moving = np.flatnonzero(~sig.stuck)
    flips = moving[1:][np.diff(np.sign(sig.omega_m[moving])) != 0]
    near = np.zeros(sig.n, bool)
    for t_flip in sig.t[flips]:
        near[np.abs(sig.t - t_flip) <= REVERSAL_S] = True
    return near


def locate(
    signals: list[Signals], residuals: list[Residual], channel: str = "motor", block_s: float = 0.5
) -> Where:
    """Bin one residual channel of every run by where it occurs."""
    y = np.concatenate([channel_of(r, channel) for r in residuals])
    omega = np.concatenate([s.omega_m for s in signals])
    theta = np.concatenate([s.theta_m for s in signals])
    stuck = np.concatenate([s.stuck for s in signals])
    direction = np.where(stuck, 0.0, np.sign(omega))
    offsets = np.cumsum([0.0] + [float(s.t[-1]) for s in signals[:-1]])
    t = np.concatenate([s.t + o for s, o in zip(signals, offsets, strict=True)])

    blocks = np.floor(t / block_s).astype(np.int64)
    ids = np.unique(blocks)
    time_rms = np.array([spread(y[blocks == b]) for b in ids])
    speed_bin = np.digitize(np.abs(omega), SPEED_EDGES) - 1
    speed_rms = np.array(
        [spread(y[speed_bin == i]) if np.any(speed_bin == i) else np.nan for i in range(len(SPEED_EDGES) - 1)]
    )
    periodic = y * direction if channel == "motor" else y
    angle_bin = np.floor(np.mod(theta, 2 * np.pi) / (2 * np.pi) * ANGLE_BINS).astype(np.int64)
    angle_mean = np.array(
        [
            float(np.mean(periodic[angle_bin == i])) if np.any(angle_bin == i) else np.nan
            for i in range(ANGLE_BINS)
        ]
    )
    total = float(np.sum(periodic**2)) or 1.0
    shares = []
    for n in range(1, 51):
        basis = np.column_stack([np.cos(n * theta), np.sin(n * theta)])
        beta = np.linalg.lstsq(basis, periodic, rcond=None)[0]
        shares.append(float(np.sum((basis @ beta) ** 2)) / total)
    near = np.concatenate([_near_reversals(s) for s in signals])
    rate = 1.0 / float(np.median(np.diff(signals[0].t)))
    freqs, power = welch(y, fs=rate, nperseg=min(len(y), 4096))
    return Where(
        channel=channel,
        time_s=(ids + 0.5) * block_s,
        time_rms=time_rms,
        speed_rms=speed_rms,
        angle_mean=angle_mean,
        harmonic=int(np.argmax(shares)) + 1,
        harmonic_share=float(max(shares)),
        forward=float(np.mean(y[direction > 0])) if np.any(direction > 0) else 0.0,
        backward=float(np.mean(y[direction < 0])) if np.any(direction < 0) else 0.0,
        at_rest=float(np.mean(y[direction == 0])) if np.any(direction == 0) else 0.0,
        near_reversal_rms=spread(y[near]),
        elsewhere_rms=spread(y[~near]),
        frequency_hz=float(freqs[1:][np.argmax(power[1:])]) if len(freqs) > 1 else 0.0,
        rms=spread(y),
    )
