"""Model files and presets: loading, round trips, and one clear line for every bad input."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from model.inputs import InputSpecError, parse_input_spec
from model.params import ModelFileError, load_model, preset_names, save_model
from model.simulate import SimulationError, simulate

SYMBOLS = [
    "J_m",
    "J_l",
    "r",
    "K_s",
    "D_s",
    "K_m",
    "K_b",
    "R",
    "s1",
    "s2",
    "s3",
    "a",
    "b",
    "v_c",
    "k_v",
    "b_m",
    "static_factor",
    "f_cl",
    "b_l",
    "f_sl",
    "A",
    "k",
    "phi",
]


def _leaves(obj: object, out: dict[str, int] | None = None) -> dict[str, int]:
    out = {} if out is None else out
    if isinstance(obj, dict):
        for key, value in obj.items():
            if isinstance(value, dict):
                _leaves(value, out)
            else:
                out[key] = out.get(key, 0) + 1
    return out


def test_presets_include_seed_rigid_and_a_catalog_unit():
    names = preset_names()
    assert {"seed", "seed-rigid"} <= set(names)
    catalog = [n for n in names if n.startswith("catalog-")]
    assert catalog, "a preset from a real catalog unit"
    model = load_model(catalog[0])
    assert model.nonlinear_stiffness is not None and model.mechanics.r == 0.01


@pytest.mark.parametrize("name", ["seed", "seed-rigid"])
def test_every_preset_loads_and_names_each_symbol_once(name: str):
    leaves = _leaves(load_model(name).to_dict())
    wanted = [s for s in SYMBOLS if not (name == "seed-rigid" and s == "K_s")]
    assert [s for s in wanted if leaves.get(s) != 1] == []


def test_seed_carries_the_article_values():
    model = load_model("seed")
    f = model.motor_friction
    assert (f.s1, f.s2, f.s3, f.v_c, f.k_v, f.static_factor) == (
        1.5738e-6,
        -3.7901e-4,
        0.0720,
        0.8,
        4e-4,
        1.0388,
    )
    assert f.b_m == 0.0, "MODEL.md note 3: k_v carries the velocity dependence"
    assert model.transmission.K_s == 1000.0 and model.mechanics.r == 0.01
    assert model.kinematic_error is not None and (model.kinematic_error.A, model.kinematic_error.k) == (
        0.001,
        50,
    )


@pytest.mark.parametrize("suffix", [".json", ".yaml"])
def test_a_saved_model_loads_back_equal(tmp_path: Path, suffix: str):
    model = load_model("seed")
    path = save_model(model, tmp_path / f"m{suffix}")
    assert load_model(path) == model


def test_an_edited_value_in_the_json_is_used(tmp_path: Path):
    data = load_model("seed").to_dict()
    data["transmission"]["K_s"] = 2500.0
    path = tmp_path / "edited.json"
    path.write_text(json.dumps(data))
    assert load_model(path).transmission.K_s == 2500.0


def _write_with(tmp_path: Path, section: str, field: str, value: object, remove: bool = False) -> Path:
    data = load_model("seed").to_dict()
    if remove:
        del data[section][field]
    else:
        data[section][field] = value
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.parametrize(
    ("section", "field", "value", "says"),
    [
        ("mechanics", "J_m", 0.0, "greater than 0"),
        ("mechanics", "J_l", -1.0, "greater than 0"),
        ("mechanics", "r", 1.5, "less than or equal to 1"),
        ("mechanics", "r", 0.0, "greater than 0"),
        ("motor", "R", float("nan"), "finite"),
        ("transmission", "K_s", float("inf"), "finite"),
        ("motor_friction", "a", [0.0] * 10, "needs 11 values"),
        ("motor_friction", "b", [0.0] * 11, "needs 10 values"),
        ("motor_friction", "s3", "lots", "valid number"),
        ("motor_friction", "f_cm", 0.1, "not used by motor_law='article'"),
        ("motor_friction", "motor_law", "magic", "Input should be"),
        ("mechanics", "J_x", 1.0, "Extra inputs are not permitted"),
        ("load_friction", "f_sl", 0.1, "f_sl must be ≥ f_cl"),
    ],
)
def test_a_bad_field_gives_one_line_naming_file_and_field(
    tmp_path: Path, section: str, field: str, value: object, says: str
):
    path = _write_with(tmp_path, section, field, value)
    with pytest.raises(ModelFileError) as info:
        load_model(path)
    message = str(info.value)
    assert "\n" not in message
    assert str(path) in message and section in message and says in message


def test_a_missing_required_field_is_named(tmp_path: Path):
    path = _write_with(tmp_path, "motor", "K_m", None, remove=True)
    with pytest.raises(ModelFileError, match=r"field 'motor\.K_m': Field required"):
        load_model(path)


def test_effect_sections_are_checked_against_the_transmission(tmp_path: Path):
    data = load_model("seed").to_dict()
    data["nonlinear_stiffness"] = {"K1": 3e4, "K2": 5e4, "K3": 6e4, "T1": 10.0, "T2": 40.0}
    path = tmp_path / "ns.json"
    path.write_text(json.dumps(data))
    with pytest.raises(ModelFileError, match=r"must equal nonlinear_stiffness\.K1"):
        load_model(path)
    data["transmission"] = {"K_s": None}
    path.write_text(json.dumps(data))
    with pytest.raises(ModelFileError, match="needs a compliant transmission"):
        load_model(path)


def test_unreadable_files_are_named(tmp_path: Path):
    with pytest.raises(ModelFileError, match="no such model file or preset"):
        load_model(tmp_path / "absent.yaml")
    broken = tmp_path / "broken.yaml"
    broken.write_text("mechanics: {J_m: 1\n  bad")
    with pytest.raises(ModelFileError, match=r"broken.yaml: not valid YAML at line \d+"):
        load_model(broken)
    not_mapping = tmp_path / "list.json"
    not_mapping.write_text("[1, 2]")
    with pytest.raises(ModelFileError, match="must be a mapping"):
        load_model(not_mapping)


@pytest.mark.parametrize(
    ("spec", "says"),
    [
        ("wobble:amp=1", "unknown kind 'wobble'"),
        ("sine:amp=2", "sine needs freq"),
        ("sine:amp=two,freq=1", "amp='two' is not a number"),
        ("sine:amp=1,freq=1,speed=3", "unknown key 'speed'"),
        ("step:amp", "'amp' is not key=value"),
        ("ramp:slope=nan", "must be finite"),
    ],
)
def test_a_bad_input_spec_names_the_spec_and_the_part(spec: str, says: str):
    with pytest.raises(InputSpecError) as info:
        parse_input_spec(spec)
    assert says in str(info.value) and spec in str(info.value)


def test_bad_simulation_settings_are_refused():
    model = load_model("seed")
    with pytest.raises(SimulationError, match="whole multiple of dt"):
        simulate(model, "step:amp=1", 1.0, dt_s=3e-4, rate_hz=1000)
    with pytest.raises(SimulationError, match="duration must be a positive"):
        simulate(model, "step:amp=1", -1.0)
    with pytest.raises(SimulationError, match="dt must be in"):
        simulate(model, "step:amp=1", 1.0, dt_s=0.0)
