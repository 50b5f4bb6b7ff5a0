"""Independent reference formulas from docs/MODEL.md, written apart from the kernel, and model variants."""

from __future__ import annotations

from typing import Any

import numpy as np

from model.params import HarmonicDriveModel


def variant(model: HarmonicDriveModel, **changes: Any) -> HarmonicDriveModel:
    """The model with sections replaced or removed (None).

    A dict merges into an existing section, except one naming a friction law: a law brings its own fields.
    """
    data = model.to_dict()
    for key, value in changes.items():
        if value is None:
            data.pop(key, None)
        elif (
            isinstance(value, dict)
            and isinstance(data.get(key), dict)
            and not {"motor_law", "load_law"} & set(value)
        ):
            data[key] = {**data[key], **value}
        else:
            data[key] = value
    return HarmonicDriveModel.model_validate(data)


def article_friction(model: HarmonicDriveModel, theta: np.ndarray, omega: np.ndarray) -> np.ndarray:
    """docs/MODEL.md moving branch: sgn(ω)·[C(θ)·(1 + k_v(|ω| − v_c)) + P(θ)] + b_m·ω."""
    f = model.motor_friction
    assert f.s1 is not None and f.s2 is not None and f.s3 is not None and f.k_v is not None
    assert f.v_c is not None
    a = np.asarray(f.fourier_a())
    b = np.asarray(f.fourier_b())
    harmonics = np.multiply.outer(np.asarray(theta, dtype=float), np.arange(1, 11))
    c = f.s1 * theta**2 + f.s2 * theta + f.s3
    periodic = a[0] / 2 + (a[1:] * np.cos(harmonics)).sum(-1) + (b * np.sin(harmonics)).sum(-1)
    return np.sign(omega) * (c * (1 + f.k_v * (np.abs(omega) - f.v_c)) + periodic) + f.b_m * omega


def article_static(model: HarmonicDriveModel, theta: np.ndarray) -> np.ndarray:
    """docs/MODEL.md f_sm = static_factor·[C(θ)·(1 − k_v·v_c) + P(θ)]: the moving magnitude at |ω| → 0+."""
    factor = model.motor_friction.static_factor
    assert factor is not None
    return factor * article_friction(model, theta, np.full_like(np.asarray(theta, dtype=float), 1e-300))
