"""The independent generator's thermal state (issue 27 item 5): its own two-node network, checked against
the network's equations solved here by hand, and its temperatures recorded."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hdrig_testing.hidden_effects import base_model
from hdrig_testing.independent_plant import IndependentRig, _Truth
from rig.analysis.gaps.effects import merge_sections

THERMAL = {
    "T_amb": 20.0,
    "T_ref": 25.0,
    "beta_T": 0.02,
    "C_w": 5.0,
    "C_g": 8.0,
    "R_wg": 2.0,
    "R_wa": 6.0,
    "R_ga": 1.5,
}


def _truth(**thermal: float) -> _Truth:
    return _Truth(merge_sections(base_model(rigid=False), thermal={**THERMAL, **thermal}))


def test_the_network_settles_where_its_equations_balance():
    """Held 3 W of copper loss and 5 W of friction: the equilibrium of
    (T_w − T_g)/R_wg + (T_w − T_a)/R_wa = 3 and (T_g − T_w)/R_wg + (T_g − T_a)/R_ga = 5."""
    p = _truth()
    for _ in range(20000):
        p.heat(3.0, 5.0, 0.1)  # 2000 s: many times the slow mode
    a = np.array([[1 / 2 + 1 / 6, -1 / 2], [-1 / 2, 1 / 2 + 1 / 1.5]])
    rise_w, rise_g = np.linalg.solve(a, [3.0, 5.0])
    assert p.T_w == pytest.approx(20.0 + rise_w, abs=1e-6)
    assert p.T_g == pytest.approx(20.0 + rise_g, abs=1e-6)


def test_the_first_step_follows_the_heat_balance_and_friction_follows_the_grease_law():
    p = _truth(T_gear0=30.0, T_motor0=30.0)
    h = 1e-4
    p.heat(0.0, 4.0, h)  # dT_g/dt = (P_f − (T_g − T_a)/R_ga) / C_g; the winding sees only ambient
    assert (p.T_g - 30.0) / h == pytest.approx((4.0 - 10.0 / 1.5) / 8.0, rel=1e-3)
    assert (p.T_w - 30.0) / h == pytest.approx(-10.0 / 6.0 / 5.0, rel=1e-3)
    assert p.warmth() == pytest.approx(math.exp(-0.02 * (p.T_g - 25.0)), rel=1e-12)
    cold = _truth()  # T_g = T_amb = 20: 5 K below T_ref, friction × e^0.1
    assert cold.motor_static(0.0) == pytest.approx(_truth(beta_T=0.0).motor_static(0.0) * math.exp(0.1))


def test_a_record_carries_the_gears_and_the_windings_temperatures():
    truth = merge_sections(base_model(rigid=False), thermal={**THERMAL, "C_g": 0.5, "C_w": 0.5})
    setpoint = np.full(1500, 80.0)
    run = IndependentRig(truth, seed=1).record(setpoint, np.zeros(1500))
    assert {"temp_gear", "temp_motor"} <= set(run.columns)
    assert float(np.mean(run["temp_gear"][-100:])) > float(np.mean(run["temp_gear"][:100])) + 0.5
    plain = IndependentRig(base_model(rigid=False), seed=1).record(setpoint[:50], np.zeros(50))
    assert "temp_gear" not in plain.columns
