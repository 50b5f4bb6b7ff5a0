"""Model parameters by name, for fitting: read and replace leaf values of a model file.

A parameter name is a docs/MODEL.md symbol (`s3`, `K_s`, `f_cl`...), unique in a model file, or an element
of the Fourier vectors written `a0`..`a10`, `b1`..`b10`. Replacing values goes through the model's
validation, so a fit can never produce a model file that does not load.
"""

from __future__ import annotations

import re
from typing import Any

from model.errors import UserInputError
from model.params import HarmonicDriveModel, parse_model

_FOURIER = re.compile(r"([ab])(\d+)")


def _locate(data: dict[str, Any], name: str) -> tuple[dict[str, Any], str, int | None]:
    """The section dict, key, and (for a_n/b_n) index holding the parameter `name`."""
    match = _FOURIER.fullmatch(name)
    key, index = (match.group(1), int(match.group(2))) if match else (name, None)
    if key == "b" and index is not None:
        index -= 1  # b1 is the first sine coefficient
    for section in data.values():
        if isinstance(section, dict) and key in section:
            return section, key, index
    raise UserInputError(f"parameter {name!r} is not in the model (its sections: {', '.join(data)})")


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
