"""Online friction tracking: recursive least squares with exponential forgetting, sample by sample.

The motor-side torque balance of docs/MODEL.md, with the transmission taken as rigid over the slow
motions of a duty cycle, is linear in three unknowns:

    K_m·i_a − r·τ_ext = F_c·sgn(ω_m) + b·ω_m + J·dω_m/dt        (|ω_m| above a threshold)

`F_c` is the friction level the tracker follows (the Coulomb part of F_m + r·F_l, its ripple over the
stroke averaged out), `b` the viscous slope, `J` the inertia seen from the motor. RLS with forgetting
factor λ weighs a sample n steps old by λⁿ, so the estimate remembers about 1/(1 − λ) samples: at
1 kHz and λ = 1 − 1/60,000, the last minute. A level that drifts steadily is followed with a lag of
about that memory; its noise falls as the memory grows (Ljung, "System Identification", 2nd ed., §11.2).

The update is compiled (numba): hours of 1 kHz samples are tracked at millions of samples a second.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numba import njit

N_REGRESSORS = 3  # sgn ω, ω, dω/dt


@njit(cache=True)
def _rls(
    theta: np.ndarray,
    cov: np.ndarray,
    phi: np.ndarray,
    y: np.ndarray,
    use: np.ndarray,
    forgetting: float,
    out: np.ndarray,
) -> None:
    """Update (theta, cov) in place with each row of phi/y where `use`; out[i] = theta[0] after row i."""
    n = y.shape[0]
    k = np.empty(N_REGRESSORS)
    p_phi = np.empty(N_REGRESSORS)
    for i in range(n):
        if use[i]:
            denom = forgetting
            for a in range(N_REGRESSORS):
                s = 0.0
                for b in range(N_REGRESSORS):
                    s += cov[a, b] * phi[i, b]
                p_phi[a] = s
                denom += phi[i, a] * s
            err = y[i]
            for a in range(N_REGRESSORS):
                err -= phi[i, a] * theta[a]
            for a in range(N_REGRESSORS):
                k[a] = p_phi[a] / denom
                theta[a] += k[a] * err
            for a in range(N_REGRESSORS):
                for b in range(N_REGRESSORS):
                    cov[a, b] = (cov[a, b] - k[a] * p_phi[b]) / forgetting
        out[i] = theta[0]


@dataclass
class FrictionTracker:
    """Follows the friction level F_c [N·m] of a drive from its samples, block by block (causal).

    `memory_s`: how far back the estimate looks (sets λ = 1 − 1/(memory_s·rate)); `omega_min_rad_s`:
    slower samples are skipped (sgn ω is ill-defined near rest, and stuck samples carry static friction).
    """

    rate_hz: float
    torque_constant_nm_per_a: float
    gear_ratio: float
    memory_s: float = 60.0
    omega_min_rad_s: float = 1.0
    theta: np.ndarray = field(default_factory=lambda: np.zeros(N_REGRESSORS))
    cov: np.ndarray = field(default_factory=lambda: np.eye(N_REGRESSORS) * 1e3)
    _last_omega: float | None = None
    samples_used: int = 0

    @property
    def forgetting(self) -> float:
        return 1.0 - 1.0 / (self.memory_s * self.rate_hz)

    def feed(self, i_a: np.ndarray, tau_ext: np.ndarray, omega_m: np.ndarray) -> np.ndarray:
        """Take samples (measured current [A], external load [N·m], motor speed [rad/s]); the level
        estimate after each sample [N·m]."""
        omega = np.asarray(omega_m, dtype=np.float64)
        previous = omega[0] if self._last_omega is None else self._last_omega
        accel = np.diff(omega, prepend=previous) * self.rate_hz
        self._last_omega = float(omega[-1]) if omega.size else self._last_omega
        phi = np.column_stack([np.sign(omega), omega, accel])
        y = self.torque_constant_nm_per_a * np.asarray(i_a) - self.gear_ratio * np.asarray(tau_ext)
        use = np.abs(omega) > self.omega_min_rad_s
        out = np.empty(omega.shape[0])
        _rls(self.theta, self.cov, phi, np.ascontiguousarray(y, dtype=np.float64), use, self.forgetting, out)
        self.samples_used += int(np.count_nonzero(use))
        return out

    @property
    def level_nm(self) -> float:
        return float(self.theta[0])
