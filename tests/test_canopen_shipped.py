"""Drives as vendors ship them: units said the DSP 402 v2 way, and optional objects with no value.

Two test files of our own (configs/eds/), each with one trait real drives have, tuned to no vendor's file:
`test-dsp402v2-notation.eds` has no factor group (no 0x6091-0x6097, no 0x60A8-0x60AA) and says its
velocity unit by the DSP 402 v2 notation and dimension indices: 0x608B = 0 and 0x608C = 0xA4, rpm (as
maxon's EPOS2 does); its max profile velocity 0x607F is declared within [0, 25000].
`test-optional-factor-no-value.eds` declares the optional velocity encoder factor 0x6094 without a
value, so the drive refuses its read; its velocity unit is encoder increments per second
(131072 / 2π = 20860.8 a motor rad/s), which the rig file gives (as with Technosoft's iPOS).

The figures are worked by hand: 1 rad/s is 60 / 2π = 9.5493 rpm; 600 rad/s (the sim rig's velocity
limit) is 5730 rpm, inside 0x607F's range, where increments per second (131072 / 2π a rad/s: 12.5 M)
are far outside it.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import pytest
import yaml

from drivers.canopen_config import (
    EDS_DIR,
    CanopenConfigError,
    CanopenSettings,
    DriveLimits,
    ObjectReader,
    boot_plan,
    check_plan,
    resolve_scaling,
)
from drivers.pdo_layout import od_variable
from hdrig_testing.can_bus import held_speed_errors
from rig.config import RIG_DIR, RigConfig
from rig.runner import run_experiment
from rig.status import RunStatus
from rig.store.runs import RunStore

pytestmark = pytest.mark.usefixtures("quiet_heap")

NOTATION = EDS_DIR / "test-dsp402v2-notation.eds"
NO_VALUE = EDS_DIR / "test-optional-factor-no-value.eds"
RPM_PER_RAD_S = 60.0 / (2 * math.pi)
LIMITS = DriveLimits(current_a=10.0, velocity_rad_s=600.0)


def settings_for(eds: Path, **scaling: Any) -> CanopenSettings:
    return CanopenSettings.model_validate(
        {
            "eds": str(eds),
            "node_id": 3,
            "interface": "virtual",
            "scaling": {"torque_constant_nm_per_a": 0.03, **scaling},
        }
    )


def shipped_drive(eds: Path, **values: int) -> tuple[CanopenSettings, Any, ObjectReader]:
    """A drive offline: its EDS values, `values` over them ("x608B": -1), None (a refused read) where
    the EDS declares an object without a value."""
    settings = settings_for(eds)
    od = settings.object_dictionary()

    def read(index: int, subindex: int) -> int | None:
        key = f"x{index:04X}" + (f"_{subindex}" if subindex else "")
        if key in values:
            return values[key]
        default = od_variable(od, index, subindex).default
        return None if default is None else int(default)

    return settings, od, read


def test_rpm_from_the_notation_and_dimension_indices_where_there_is_no_factor_group() -> None:
    settings, od, read = shipped_drive(NOTATION)
    scaling = resolve_scaling(settings.scaling, od, read)
    assert scaling.velocity_units_per_rad_s == pytest.approx(RPM_PER_RAD_S, rel=1e-12)
    assert scaling.notes == ()
    plan = boot_plan(od, settings, LIMITS, scaling, 0.001)
    assert check_plan(od, plan) == []  # 0x607F within its declared [0, 25000]
    max_profile = next(write for write in plan if write.index == 0x607F)
    assert max_profile.value == round(600.0 * RPM_PER_RAD_S) == 5730


def test_the_notation_index_is_a_power_of_ten_of_the_dimension() -> None:
    settings, od, read = shipped_drive(NOTATION, x608B=-1)  # 0.1 rpm
    scaling = resolve_scaling(settings.scaling, od, read)
    assert scaling.velocity_units_per_rad_s == pytest.approx(10 * RPM_PER_RAD_S, rel=1e-12)


def test_a_dimension_the_driver_cannot_read_is_asked_of_the_rig_file_in_one_line() -> None:
    settings, od, read = shipped_drive(NOTATION, x608C=0xB3)
    with pytest.raises(CanopenConfigError) as refused:
        resolve_scaling(settings.scaling, od, read)
    message = str(refused.value)
    assert "\n" not in message
    assert message.startswith("canopen.scaling.velocity_units_per_rad_s is needed: 0x608C")
    assert "0xB3" in message


def test_a_refused_optional_factor_falls_back_on_the_rig_file_with_a_note() -> None:
    settings, od, read = shipped_drive(NO_VALUE)
    assert read(0x6094, 1) is None  # the premise: declared without a value
    given = settings.scaling.model_copy(update={"velocity_unit": "increments_per_s"})
    scaling = resolve_scaling(given, od, read)
    assert scaling.velocity_units_per_rad_s == pytest.approx(131072 / (2 * math.pi), rel=1e-12)
    assert scaling.notes == (
        "the drive refused the read of 0x6094:01 (velocity encoder factor): its unit is taken from"
        " canopen.scaling.velocity_units_per_rad_s",
        "the drive refused the read of 0x6094:02 (velocity encoder factor): its unit is taken from"
        " canopen.scaling.velocity_units_per_rad_s",
    )


def test_a_refused_factor_whose_unit_the_rig_file_leaves_to_the_drive_is_an_error_naming_the_setting() -> (
    None
):
    settings, od, read = shipped_drive(NO_VALUE)
    with pytest.raises(CanopenConfigError) as refused:
        resolve_scaling(settings.scaling, od, read)
    assert str(refused.value) == (
        "canopen.scaling.velocity_units_per_rad_s is needed: the drive refused the read of 0x6094:01"
        " (velocity encoder factor)"
    )


@pytest.mark.parametrize(
    ("eds", "scaling"),
    [(NOTATION, {}), (NO_VALUE, {"velocity_unit": "increments_per_s"})],
    ids=["dsp402v2-rpm", "optional-factor-no-value"],
)
def test_the_speed_sweep_runs_on_twins_of_drives_as_shipped(
    eds: Path, scaling: dict[str, Any], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    data = yaml.safe_load((RIG_DIR / "virtual-can.yaml").read_text())
    data["canopen"]["eds"] = str(eds)
    data["canopen"]["scaling"].update(scaling)
    config = RigConfig.model_validate(data)
    sweep = {"speeds_rad_s": [5.0, 20.0], "settle_s": 0.1, "hold_s": 0.1}
    with caplog.at_level(logging.WARNING, logger="drivers.canopen_servo"):
        outcome = run_experiment("speed-sweep", config, sweep, RunStore(tmp_path))
    assert outcome.status == RunStatus.COMPLETE, outcome.reason
    refused = [r.getMessage() for r in caplog.records if "refused the read" in r.getMessage()]
    assert bool(refused) == (eds == NO_VALUE), refused
    run = RunStore(tmp_path).read(outcome.run_id)
    # Each held speed's second half at the motor within 0.5 rad/s of its set-point (as in
    # test_canopen_units: a units error is a factor of 9.5 rpm per rad/s or more, not a fraction).
    assert held_speed_errors(run, {5.0, 20.0}, 0.5) == []
