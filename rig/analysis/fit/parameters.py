"""Model parameters by name, for fitting: read and replace leaf values of a model file.

A parameter name is a docs/MODEL.md symbol (`s3`, `K_s`, `f_cl`...), unique in a model file, or an element
of the Fourier vectors written `a0`..`a10`, `b1`..`b10`: an entry of `model.registry.PARAMETERS`, which says
where it lives. Replacing values goes through the model's validation, so a fit can never produce a model
file that does not load.
"""

from __future__ import annotations

from typing import Any

from model.errors import UserInputError
from model.params import HarmonicDriveModel, parse_model
from model.registry import parameter


def _locate(data: dict[str, Any], name: str) -> tuple[dict[str, Any], str, int | None]:
    """The section dict, key, and (for a_n/b_n) index holding the parameter `name`."""
    entry = parameter(name)
    section = data.get(entry.section)
    if not isinstance(section, dict) or entry.field not in section:
        raise UserInputError(
            f"parameter {name!r} is not in the model ({entry.section}.{entry.field} is not set;"
            f" its sections: {', '.join(data)})"
        )
    return section, entry.field, entry.index


def get_values(model: HarmonicDriveModel, names: list[str]) -> dict[str, float]:
    """Current values of the named parameters."""
    data = model.to_dict()
    out = {}
    for name in names:
        section, key, index = _locate(data, name)
        value = section[key] if index is None else section[key][index]
        if not isinstance(value, int | float):
            raise UserInputError(f"parameter {name!r} is not a number (it is {value!r})")
        out[name] = float(value)
    return out


def with_values(
    model: HarmonicDriveModel, values: dict[str, float], source: str = "fit"
) -> HarmonicDriveModel:
    """A validated copy of the model with the named parameters replaced."""
    data = model.to_dict()
    for name, value in values.items():
        section, key, index = _locate(data, name)
        if index is None:
            section[key] = float(value)
        else:
            vector = list(section[key])
            vector[index] = float(value)
            section[key] = vector
    nonlinear = data.get("nonlinear_stiffness")
    if nonlinear is not None and "K1" in values:
        data["transmission"]["K_s"] = float(values["K1"])  # the schema keeps K_s = K1
    return parse_model(data, source)
