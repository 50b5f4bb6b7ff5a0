"""The numbers labs compare (issue 25 item 4): each figure against the equations of docs/MODEL.md worked
out by hand, against the kernel's own friction, and its σ against propagation done by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest

from model import kernel as k
from model.params import load_model, parse_model
from model.plant import kernel_vectors
from rig.analysis.identification.identify import ParameterRow
from rig.analysis.identification.lab_quantities import fitted_sigmas, lab_quantities, lab_table


def _by_name(model, sigma=None, covariance=None):
    return {q.name: q for q in lab_quantities(model, sigma or {}, covariance)}


def _asymmetric_seed():
    """The seed with no Fourier part (so θ_m = 0 is the turn's mean), f_dir 0.01 and Stribeck f_st 0.02."""
    data = load_model("seed").to_dict()
    data["motor_friction"]["a"] = [0.0] * 11
    data["motor_friction"]["b"] = [0.0] * 10
    data["motor_friction"]["b_m"] = 0.002
    data["direction_asymmetry"] = {"f_dir": 0.01}
    data["stribeck"] = {"f_st": 0.02, "omega_st": 2.0}
    return parse_model(data, "asymmetric seed")


def test_the_seed_gives_the_article_law_in_a_labs_terms():
    """s3 0.072, k_v 4e-4, v_c 0.8, b_m 0, static_factor 1.0388, r 0.01, J_m 5.5e-5, J_l 0.2, K_s 1000,
    f_cl 0.3, f_sl 0.35, b_l 0.05 (configs/models/seed)."""
    q = _by_name(load_model("seed"))
    level = 0.072 * (1 - 0.0004 * 0.8)  # 0.07197696
    for direction in ("forward", "backward"):
        assert q[f"coulomb_at_rest_{direction}_Nm"].value == pytest.approx(level, rel=1e-12)
        assert q[f"viscous_slope_{direction}_Nms_per_rad"].value == pytest.approx(0.072 * 0.0004, rel=1e-12)
        assert q[f"breakaway_{direction}_Nm"].value == pytest.approx(1.0388 * level, rel=1e-12)
    assert q["inertia_motor_side_kgm2"].value == pytest.approx(5.5e-5 + 1e-4 * 0.2, rel=1e-12)
    assert q["inertia_output_side_kgm2"].value == pytest.approx(0.2 + 5.5e-5 / 1e-4, rel=1e-12)
    assert q["stiffness_Nm_per_rad"].value == 1000.0
    assert q["load_coulomb_Nm"].value == 0.3 and q["load_breakaway_Nm"].value == 0.35
    assert q["coulomb_at_output_Nm"].value == pytest.approx(level / 0.01 + 0.3, rel=1e-12)
    assert q["viscous_at_output_Nms_per_rad"].value == pytest.approx(0.072 * 0.0004 / 1e-4 + 0.05, rel=1e-12)
    # nothing fitted: every figure exact
    assert all(item.sigma == 0.0 for item in q.values())


def test_levels_per_direction_follow_direction_asymmetry_and_stribeck_is_breakaway_only():
    q = _by_name(_asymmetric_seed())
    level = 0.072 * (1 - 0.0004 * 0.8)
    assert q["coulomb_at_rest_forward_Nm"].value == pytest.approx(level + 0.01, rel=1e-12)
    assert q["coulomb_at_rest_backward_Nm"].value == pytest.approx(level - 0.01, rel=1e-12)
    assert q["viscous_slope_backward_Nms_per_rad"].value == pytest.approx(0.072 * 0.0004 + 0.002, rel=1e-12)
    assert q["breakaway_forward_Nm"].value == pytest.approx(1.0388 * level + 0.02 + 0.01, rel=1e-12)
    assert q["breakaway_backward_Nm"].value == pytest.approx(1.0388 * level + 0.02 - 0.01, rel=1e-12)


def test_the_figures_are_the_kernels_own_friction_line_and_breakaway():
    """The kernel's moving branch at 40 and 80 rad/s (where Stribeck's exp(−(ω/2)²) is nil), extended
    back to rest, and its stuck limit, per direction, at θ_m = 0."""
    model = _asymmetric_seed()
    q = _by_name(model)
    p, flags = kernel_vectors(model)
    theta = np.zeros(2)
    for sign, direction in ((1.0, "forward"), (-1.0, "backward")):
        speeds = sign * np.array([40.0, 80.0])
        friction = sign * k.steady_motor_friction(p, flags, theta, speeds, 0.0, 0.0)
        slope = (friction[1] - friction[0]) / 40.0
        assert slope == pytest.approx(q[f"viscous_slope_{direction}_Nms_per_rad"].value, rel=1e-9)
        at_rest = friction[0] - 40.0 * slope
        assert at_rest == pytest.approx(q[f"coulomb_at_rest_{direction}_Nm"].value, rel=1e-9)
        stuck = k.static_motor_friction(p, flags, theta[:1], sign, 0.0, 0.0)[0]
        assert stuck == pytest.approx(q[f"breakaway_{direction}_Nm"].value, rel=1e-9)


def test_sigma_is_propagated_by_hand_independent_and_through_a_covariance():
    model = load_model("seed")
    s_s3, s_kv, s_bm = 0.002, 1e-4, 3e-5
    q = _by_name(model, {"s3": s_s3, "k_v": s_kv, "b_m": s_bm, "J_m": 1e-6, "J_l": 0.01})
    level_sigma = math.hypot((1 - 0.0004 * 0.8) * s_s3, 0.072 * 0.8 * s_kv)
    assert q["coulomb_at_rest_forward_Nm"].sigma == pytest.approx(level_sigma, rel=1e-6)
    slope_sigma = math.sqrt((0.0004 * s_s3) ** 2 + (0.072 * s_kv) ** 2 + s_bm**2)
    assert q["viscous_slope_forward_Nms_per_rad"].sigma == pytest.approx(slope_sigma, rel=1e-6)
    assert q["inertia_motor_side_kgm2"].sigma == pytest.approx(math.hypot(1e-6, 1e-4 * 0.01), rel=1e-6)
    assert q["inertia_output_side_kgm2"].sigma == pytest.approx(math.hypot(0.01, 1e-6 / 1e-4), rel=1e-6)
    # k_v and b_m traded against each other (correlation −1, b_m's σ = s3·σ_kv): the slope is exact,
    # as the real axis's 200.46 N·s/m was while b_m alone was not determined.
    cov = np.array([[s_kv**2, -0.072 * s_kv**2], [-0.072 * s_kv**2, (0.072 * s_kv) ** 2]])
    traded = _by_name(model, {}, (["k_v", "b_m"], cov))
    assert traded["viscous_slope_forward_Nms_per_rad"].sigma == pytest.approx(0.0, abs=1e-12)
    assert traded["coulomb_at_rest_forward_Nm"].sigma == pytest.approx(0.072 * 0.8 * s_kv, rel=1e-6)


def test_a_parameter_moved_but_not_determined_leaves_its_figures_undetermined_only():
    rows = [
        ParameterRow("s3", 0.08, 0.072, 0.001, True, "joint"),
        ParameterRow("b_m", 0.0, 0.003, None, False, "joint", "not determined"),
        ParameterRow("K_m", 0.06, 0.06, None, False, "given", "given"),
    ]
    sigma = fitted_sigmas(rows)
    assert sigma == {"s3": 0.001, "b_m": None}
    q = _by_name(load_model("seed"), sigma)
    assert q["viscous_slope_forward_Nms_per_rad"].sigma is None
    assert q["coulomb_at_rest_forward_Nm"].sigma == pytest.approx((1 - 0.0004 * 0.8) * 0.001, rel=1e-6)
    table = "\n".join(lab_table(list(q.values())))
    assert "| viscous_slope_forward_Nms_per_rad |" in table and "not determined" in table


def test_a_covariance_of_the_wrong_shape_is_refused_in_one_line():
    with pytest.raises(ValueError, match="not the square"):
        lab_quantities(load_model("seed"), {}, (["s3"], np.eye(2)))


def test_fit_json_and_text_carry_the_figures_beside_the_parameters(capsys):
    """`fit --json` adds `lab_quantities` (CONTRACT.md's fields unchanged); the text output prints them."""
    from rig.analysis.identification.identify import Identification
    from rig.cli import _print_lab_quantities
    from rig.core.actions import fit_document

    rows = [ParameterRow("s3", 0.072, 0.08, 0.001, True, "joint")]
    document = fit_document(Identification(load_model("seed"), rows, 0.5, 0.1)).as_json()
    assert {"parameters", "fit_error", "notes"} <= set(document)
    assert document["parameters"]["s3"]["uncertainty"] == 0.001
    level = document["lab_quantities"]["coulomb_at_rest_forward_Nm"]
    assert level["value"] == pytest.approx(0.072 * (1 - 0.0004 * 0.8), rel=1e-12)
    assert level["sigma"] == pytest.approx((1 - 0.0004 * 0.8) * 0.001, rel=1e-6)
    assert level["unit"] == "N·m"
    from rig.core.documents import FitDocument

    _print_lab_quantities(FitDocument.model_validate(document).lab_quantities)
    printed = capsys.readouterr().out
    assert "coulomb_at_rest_forward_Nm" in printed and "inertia_output_side_kgm2" in printed


def test_the_fit_report_has_the_table_of_lab_quantities():
    from rig.analysis.identification.identify import Identification, _report

    rows = [ParameterRow("J_m", 5e-5, 5.5e-5, 1e-6, True, "joint")]
    text = _report(Identification(load_model("seed"), rows, 0.5, 0.1))
    assert "## The numbers labs compare" in text
    line = next(x for x in text.splitlines() if x.startswith("| inertia_motor_side_kgm2 |"))
    assert "7.5e-05" in line and "1e-06" in line  # J_m + r²·J_l; σ of J_m alone (J_l held)
