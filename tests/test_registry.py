"""The parameter registry (model.registry): one entry per schema field and per kernel slot, units and bounds
from the schema, and the kernel reading each parameter where the registry says."""

from __future__ import annotations

import math
import typing

import numpy as np
import pytest

from model import kernel
from model.errors import UserInputError
from model.params import N_FOURIER, HarmonicDriveModel, ModelFileError, load_model, preset_names
from model.plant import kernel_vectors
from model.registry import (
    DERIVED,
    EFFECT_FLAGS,
    FL,
    FLAG_SOURCES,
    PARAMETERS,
    SECTION_OWNERS,
    SELECTORS,
    STAGES,
    P,
    _section_classes,
    determined_by,
    owned_by,
    parameter,
)
from rig.analysis.fit.parameters import with_values


def _schema_leaves() -> list[tuple[str, str]]:
    """(section, field) of every field of every section of the model schema."""
    return [(section, field) for section, cls in _section_classes().items() for field in cls.model_fields]


def test_the_registry_covers_every_field_of_the_schema_exactly_once() -> None:
    covered: dict[tuple[str, str], int] = {}
    for p in PARAMETERS.values():
        covered[(p.section, p.field)] = covered.get((p.section, p.field), 0) + 1
    for name in SELECTORS:
        section = "motor_friction" if name == "motor_law" else "load_friction"
        covered[(section, name)] = covered.get((section, name), 0) + 1
    leaves = _schema_leaves()
    assert sorted(covered) == sorted(leaves), set(covered) ^ set(leaves)
    vectors = {("motor_friction", "a"): N_FOURIER + 1, ("motor_friction", "b"): N_FOURIER}
    for leaf, count in covered.items():
        assert count == vectors.get(leaf, 1), f"{leaf} covered {count} times"
    # Only the model's name and description are outside the sections, and they are no parameters.
    top = {name for name, info in HarmonicDriveModel.model_fields.items() if name not in _section_classes()}
    assert top == {"name", "description"}


def test_every_kernel_slot_is_one_parameter_or_one_derived_value() -> None:
    slots = [p.slot for p in PARAMETERS.values()] + list(DERIVED)
    assert sorted(slots) == list(P), "a slot is missing or taken twice"
    assert list(PARAMETERS) == sorted(PARAMETERS, key=lambda name: PARAMETERS[name].slot)
    assert set(FLAG_SOURCES) == set(FL)
    assert set(EFFECT_FLAGS) <= set(SECTION_OWNERS)
    assert set(SELECTORS.values()) <= set(FL)


def test_the_kernel_numbers_no_slot_itself() -> None:
    constants = {
        name: value
        for name, value in vars(kernel).items()
        if isinstance(value, int) and not isinstance(value, bool) and not name.startswith("__")
    }
    assert constants == {}, f"model/kernel.py numbers slots by hand: {sorted(constants)}"


def test_enums_are_numbered_from_zero_in_declaration_order() -> None:
    for layout in (P, FL, kernel.X, kernel.OUT, kernel.Law, kernel.Mode):
        assert [int(m) for m in layout] == list(range(len(layout)))


@pytest.mark.parametrize("preset", preset_names())
def test_the_kernel_reads_each_parameter_at_its_slot(preset: str) -> None:
    model = load_model(preset)
    p, flags = kernel_vectors(model)
    assert p.shape == (len(P),) and flags.shape == (len(FL),)
    seen = 0
    for param in PARAMETERS.values():
        if getattr(model, param.section) is None:
            assert p[param.slot] == 0.0, param.name  # an absent law or effect: never read
            continue
        value = param.value(model)
        assert p[param.slot] == (param.kernel_default if value is None else value), param.name
        seen += 1
    assert seen > 20
    for effect, flag in EFFECT_FLAGS.items():
        assert flags[flag] == (getattr(model, effect) is not None), effect


def _schema_field(name: str) -> typing.Any:
    p = PARAMETERS[name]
    return _section_classes()[p.section].model_fields[p.field]


def test_units_and_bounds_are_the_schemas() -> None:
    for p in PARAMETERS.values():
        description = _schema_field(p.name).description
        assert description == p.description
        assert f"[{p.unit}]" in description, p.name
    assert parameter("K_s").unit == "N·m/rad"
    assert parameter("a3").unit == "N·m"
    r = parameter("r").bounds
    assert (r.lower, r.lower_inclusive, r.upper, r.upper_inclusive) == (0.0, False, 1.0, True)
    assert parameter("d_th").bounds.lower == -1.0 and not parameter("d_th").bounds.admits(-1.0)
    assert parameter("K_b").bounds.admits(0.0) and not parameter("K_b").bounds.admits(-1e-12)
    assert parameter("s1").bounds.admits(-1e9)


@pytest.mark.parametrize("preset", ["seed", "catalog-cha-25a-100"])
def test_the_schema_rejects_what_the_bounds_exclude(preset: str) -> None:
    model = load_model(preset)
    checked = 0
    for p in PARAMETERS.values():
        value = p.value(model)
        if value is None:
            continue
        assert p.bounds.admits(value), f"{preset}: {p.name} = {value} outside {p.bounds}"
        outside = []
        if p.bounds.lower is not None:
            outside.append(p.bounds.lower - 1.0 if p.bounds.lower_inclusive else p.bounds.lower)
        if p.bounds.upper is not None:
            outside.append(p.bounds.upper + 1.0 if p.bounds.upper_inclusive else p.bounds.upper)
        for bad in outside:
            assert not p.bounds.admits(bad)
            with pytest.raises(ModelFileError):
                with_values(model, {p.name: bad})
            checked += 1
    assert checked > 10


def test_owners_stages_and_laws() -> None:
    assert owned_by("stribeck") == ("f_st", "omega_st")
    assert owned_by("hysteresis") == ("T_h", "delta_h")
    assert owned_by("compliance") == ("K_s", "D_s")
    assert parameter("s3").laws == ("article",)
    assert parameter("b_m").laws == ("article", "coulomb_viscous", "stribeck", "lugre", "dahl")
    assert set(determined_by("motor")) == {"R", "K_b"}
    assert all(p.stage in STAGES for p in PARAMETERS.values())
    with pytest.raises(ValueError, match="unknown stage"):
        determined_by("nope")
    with pytest.raises(UserInputError, match="'s4' is not a model parameter"):
        parameter("s4")


def test_a_fourier_element_reads_its_vector() -> None:
    model = load_model("seed")
    a = model.motor_friction.fourier_a()
    b = model.motor_friction.fourier_b()
    assert parameter("a0").value(model) == a[0]
    assert parameter("b1").value(model) == b[0]
    assert parameter("b10").value(model) == b[N_FOURIER - 1]
    assert not math.isnan(parameter("J_m").value(model) or math.nan)
    p, _ = kernel_vectors(model)
    assert np.array_equal(p[P.A0 : P.A10 + 1], a) and np.array_equal(p[P.B1 : P.B10 + 1], b)


def _law_variants() -> list[HarmonicDriveModel]:
    seed = load_model("seed")
    data = seed.to_dict()
    laws = [
        {"motor_law": "coulomb_viscous", "f_cm": 0.1, "b_m": 0.001},
        {"motor_law": "stribeck", "f_cm": 0.1, "f_sm": 0.2, "omega_sm": 0.3},
        {"motor_law": "lugre", "f_cm": 0.1, "f_sm": 0.2, "omega_sm": 0.3, "sigma0_m": 1e3, "sigma1_m": 2.0},
        {"motor_law": "dahl", "f_cm": 0.1, "sigma0_m": 1e3},
    ]
    effects = {
        "stribeck": {"f_st": 0.01, "omega_st": 0.5},
        "direction_asymmetry": {"f_dir": 0.01},
        "load_dependent_friction": {"c_Ts": 0.01},
    }
    out = [load_model(name) for name in preset_names()]
    out += [HarmonicDriveModel.model_validate({**data, "motor_friction": law}) for law in laws]
    out.append(HarmonicDriveModel.model_validate({**data, **effects}))
    return out


def test_each_identification_stage_estimates_what_the_registry_says() -> None:
    from rig.analysis.identification.staged import _expected

    for model in _law_variants():
        for stage, names in _expected(model).items():
            assert stage in STAGES
            for name in names:
                assert parameter(name).determined_in(stage), (
                    f"{model.motor_friction.motor_law}: stage {stage} estimates {name},"
                    f" the registry says {parameter(name).stage}"
                )


def test_gap_candidates_own_only_their_effects_parameters() -> None:
    from rig.analysis.gaps.effects import Candidate

    Candidate("stribeck", "motor", 0.1, "", {}, [*owned_by("stribeck"), "s3"], [*owned_by("stribeck")])
    with pytest.raises(ValueError, match="no parameter s3"):
        Candidate("stribeck", "motor", 0.1, "", {}, ["s3"], ["s3"])
    with pytest.raises(UserInputError, match="not a model parameter"):
        Candidate("hysteresis", "load", 0.1, "", {}, ["T_hyst"], [])
