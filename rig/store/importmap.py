"""Run files as labs have them: other column names, units and gains, mapped onto the run format.

A mapping says, per run-format column, which column of the file it comes from and how to scale it:

    theta_m=enc*deg          the file's `enc` is in degrees
    i_cmd=volts*2.5          the drive's analog command: 2.5 A per volt
    t=time_ms*ms             milliseconds
    tau_m=force*0.05+0.01    any gain and offset: target = source·gain + offset

given on the command line (`--map theta_m=enc*deg --map i_cmd=volts*2.5`) or in a small YAML/JSON file
(`--map lab.yaml`) holding the same strings (`theta_m: enc*deg`) or `{column, gain, offset}`. A gain is
a number or one of the unit names in UNITS. Columns the mapping does not name are kept when they are
already run-format columns, dropped otherwise. The mapping and the source file are kept in the run's
metadata (`import_map`), so the run remembers where it came from.

CSV and MATLAB `.mat` files are read (a `.mat` of column vectors, or of one struct holding them).
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from model.errors import UserInputError
from model.run import KNOWN_COLUMNS, Run, RunFormatError

UNITS = {
    "deg": math.pi / 180,
    "rev": 2 * math.pi,
    "rpm": 2 * math.pi / 60,
    "deg_s": math.pi / 180,
    "ms": 1e-3,
    "us": 1e-6,
    "mA": 1e-3,
    "mNm": 1e-3,
    "mrad": 1e-3,
    "urad": 1e-6,
}
"""Unit names a gain may be written as, each the factor to SI (docs/MODEL.md: rad, rad/s, s, A, N·m)."""
_ENTRY = re.compile(
    r"\s*(?P<target>\w+)\s*=\s*(?P<source>[^*+]+?)\s*(?:\*\s*(?P<gain>[^+]+?))?\s*(?:\+\s*(?P<offset>\S+))?\s*"
)
MAPPED_SUFFIXES = (".csv", ".mat")


@dataclass(frozen=True)
class ColumnSource:
    """target = file[column]·gain + offset."""

    column: str
    gain: float = 1.0
    offset: float = 0.0


def _number(text: str, what: str) -> float:
    text = text.strip()
    if text in UNITS:
        return UNITS[text]
    try:
        value = float(text)
    except ValueError:
        raise UserInputError(
            f"--map {what}: {text!r} is neither a number nor a unit ({', '.join(UNITS)})"
        ) from None
    if not math.isfinite(value):
        raise UserInputError(f"--map {what}: {text!r} is not finite")
    return value


def _target(name: str, where: str) -> str:
    if name not in KNOWN_COLUMNS:
        raise UserInputError(f"{where}: {name!r} is not a run-format column ({', '.join(KNOWN_COLUMNS)})")
    return name


def parse_entry(text: str) -> tuple[str, ColumnSource]:
    """`TARGET=SOURCE[*GAIN][+OFFSET]` → (target, source)."""
    match = _ENTRY.fullmatch(text)
    if match is None:
        raise UserInputError(f"--map {text!r}: write TARGET=SOURCE[*GAIN][+OFFSET], e.g. theta_m=enc*deg")
    target = _target(match["target"], f"--map {text!r}")
    gain = _number(match["gain"], text) if match["gain"] else 1.0
    offset = _number(match["offset"], text) if match["offset"] else 0.0
    return target, ColumnSource(match["source"].strip(), gain, offset)


def _from_file(path: Path) -> dict[str, ColumnSource]:
    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise UserInputError(f"--map {path}: cannot read the mapping file ({exc})") from None
    if not isinstance(data, dict):
        raise UserInputError(f"--map {path}: a mapping file holds `target: source` pairs")
    out = {}
    for target, value in data.items():
        if isinstance(value, dict):
            where = f"--map {path}: {target}"
            if "column" not in value:
                raise UserInputError(f"{where}: needs `column`")
            out[_target(str(target), where)] = ColumnSource(
                str(value["column"]),
                _number(str(value.get("gain", 1.0)), where),
                _number(str(value.get("offset", 0.0)), where),
            )
        else:
            name, source = parse_entry(f"{target}={value}")
            out[name] = source
    return out


def parse_mapping(items: Sequence[str] | None) -> dict[str, ColumnSource]:
    """The mapping of `--map` arguments: entries, or names of YAML/JSON mapping files, in order."""
    mapping: dict[str, ColumnSource] = {}
    for item in items or []:
        if "=" not in item and Path(item).suffix.lower() in (".yaml", ".yml", ".json"):
            mapping.update(_from_file(Path(item)))
        else:
            target, source = parse_entry(item)
            mapping[target] = source
    return mapping


def _mat_columns(path: Path) -> dict[str, np.ndarray]:
    from scipy.io import loadmat

    try:
        data = loadmat(path, squeeze_me=True, struct_as_record=False)
    except (OSError, ValueError, NotImplementedError) as exc:
        raise UserInputError(f"{path}: cannot read as MATLAB .mat ({exc})") from None
    variables = {k: v for k, v in data.items() if not k.startswith("__")}
    structs = [v for v in variables.values() if hasattr(v, "_fieldnames")]
    if len(structs) == 1 and not any(isinstance(v, np.ndarray) and v.ndim == 1 for v in variables.values()):
        variables = {name: getattr(structs[0], name) for name in structs[0]._fieldnames}
    return {
        name: np.asarray(value, dtype=np.float64).ravel()
        for name, value in variables.items()
        if isinstance(value, np.ndarray) and value.dtype.kind in "fiu" and value.size > 1
    }


def _csv_columns(path: Path) -> dict[str, np.ndarray]:
    from pyarrow import ArrowInvalid, csv

    try:
        table = csv.read_csv(path)
    except (OSError, ArrowInvalid) as exc:
        raise UserInputError(f"{path}: cannot read as CSV ({str(exc).splitlines()[0]})") from None
    out = {}
    for name in table.column_names:
        column = table.column(name)
        if column.type.id in range(2, 13):  # pyarrow's integer and floating type ids
            out[name] = np.asarray(column.to_numpy(zero_copy_only=False), dtype=np.float64)
    return out


def read_mapped(path: str | Path, mapping: dict[str, ColumnSource]) -> Run:
    """Read a CSV or `.mat` file through `mapping` into a validated run that remembers the mapping."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in MAPPED_SUFFIXES:
        raise UserInputError(
            f"{path}: a mapped file is read from {', '.join(MAPPED_SUFFIXES)}, not {suffix!r}"
        )
    if not path.is_file():
        raise UserInputError(f"{path}: no such file")
    raw = _mat_columns(path) if suffix == ".mat" else _csv_columns(path)
    columns = {name: values for name, values in raw.items() if name in KNOWN_COLUMNS}
    for target, source in mapping.items():
        if source.column not in raw:
            raise UserInputError(
                f"{path}: --map {target}={source.column}: no numeric column {source.column!r}"
                f" (the file has {', '.join(raw) or 'none'})"
            )
        columns[target] = raw[source.column] * source.gain + source.offset
    meta: dict[str, Any] = {
        "import_map": {
            "source": str(path.resolve()),
            "columns": {
                t: {"column": s.column, "gain": s.gain, "offset": s.offset} for t, s in mapping.items()
            },
        }
    }
    sidecar = path.with_name(path.name + ".json")
    if sidecar.is_file():
        try:
            meta = json.loads(sidecar.read_text()) | meta
        except json.JSONDecodeError as exc:
            raise UserInputError(f"{sidecar}: not JSON ({exc})") from None
    if "input_column" not in meta:
        # A mapped input column is the one the lab says drove the axis.
        mapped_inputs = [c for c in ("u", "i_cmd", "tau_m") if c in mapping]
        if len(mapped_inputs) == 1:
            meta["input_column"] = mapped_inputs[0]
    try:
        return Run(columns, meta).validate(where=str(path))
    except RunFormatError as exc:
        raise UserInputError(f"{exc} (after --map)") from None
