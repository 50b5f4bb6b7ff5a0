"""Run files: read and write a `Run` as Parquet, CSV (+ `<file>.json` metadata) or MATLAB `.mat`.

The format is docs/INTERFACE.md's run format. Every write goes to a temporary name and is renamed into
place, so a reader never sees a half-written file.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import os
import re
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import IO, Any

import numpy as np
import pyarrow as pa
import pyarrow.csv as pa_csv
import pyarrow.parquet as pq
import scipy.io

from model.errors import UserInputError
from model.run import KNOWN_COLUMNS, Run, RunFormatError

WRITE_SUFFIXES = (".parquet", ".csv", ".mat")
READ_SUFFIXES = (".parquet", ".csv")
_MATLAB_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_]{0,62}")
_MAT_META_VARIABLE = "meta"


class RunFileError(UserInputError):
    """A run file cannot be read or written; the one-line message names the file and what is wrong."""


def ordered_columns(names: Iterable[str]) -> list[str]:
    """docs/INTERFACE.md columns first, in their table order, then any further columns as given."""
    given = list(names)
    return [c for c in KNOWN_COLUMNS if c in given] + [c for c in given if c not in KNOWN_COLUMNS]


def json_text(value: Any, indent: int | None = None) -> str:
    """JSON for metadata and metrics; numpy scalars and arrays become plain numbers and lists."""
    return json.dumps(value, indent=indent, default=_json_default)


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic | np.ndarray):
        return value.tolist()
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    raise TypeError(f"metadata value {value!r} of type {type(value).__name__} is not JSON-serializable")


def _one_line(error: BaseException) -> str:
    text = str(error).strip()
    return text.splitlines()[0] if text else type(error).__name__


@contextlib.contextmanager
def _atomic_write(path: Path) -> Iterator[IO[bytes]]:
    """Yield a file that replaces `path` only once it is completely written and on disk."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as f:
            yield f
            f.flush()
            # fsync so that a power cut after the rename cannot leave an empty file under the real name.
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def _table(columns: dict[str, np.ndarray]) -> pa.Table:
    names = ordered_columns(columns)
    return pa.table({c: np.asarray(columns[c], dtype=np.float64) for c in names})


# ---- writing -------------------------------------------------------------------------------------


def write_parquet(columns: dict[str, np.ndarray], meta: dict[str, Any], path: str | os.PathLike[str]) -> Path:
    """Write columns (any length, not validated) as Parquet; each metadata value JSON-encoded."""
    path = Path(path)
    kv = {key: json_text(value) for key, value in meta.items()}
    table = _table(columns).replace_schema_metadata(kv)
    with _atomic_write(path) as f:
        pq.write_table(table, f)
    return path


def _write_csv(run: Run, path: Path) -> None:
    table = _table(run.columns)
    header = io.StringIO()
    csv.writer(header, lineterminator="\n").writerow(table.column_names)
    with _atomic_write(path) as f:
        f.write(header.getvalue().encode())
        # Arrow prints each double in its shortest form that reads back to the same bits.
        pa_csv.write_csv(table, f, pa_csv.WriteOptions(include_header=False))
    with _atomic_write(sidecar_path(path)) as f:
        f.write(json_text(run.meta, indent=2).encode())


def _matlab_value(value: Any) -> Any:
    """Numbers, text and name-keyed dicts map to MATLAB values and structs; the rest becomes JSON text."""
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, dict) and all(isinstance(k, str) and _MATLAB_NAME.fullmatch(k) for k in value):
        return {k: _matlab_value(v) for k, v in value.items()}
    if isinstance(value, str | bool | int | float):
        return value
    return json_text(value)


def _write_mat(run: Run, path: Path) -> None:
    variables: dict[str, Any] = {}
    for name in ordered_columns(run.columns):
        if not _MATLAB_NAME.fullmatch(name) or name == _MAT_META_VARIABLE:
            raise RunFileError(f"{path}: column {name!r} cannot be a MATLAB variable name")
        variables[name] = run.columns[name]
    variables[_MAT_META_VARIABLE] = _matlab_value(run.meta)
    with _atomic_write(path) as f:
        scipy.io.savemat(f, variables, do_compression=True, oned_as="column", long_field_names=True)


def write_run(run: Run, path: str | os.PathLike[str]) -> Path:
    """Write a run to `path`; the suffix (.parquet, .csv, .mat) picks the format. Returns the path."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in WRITE_SUFFIXES:
        raise RunFileError(f"{path}: unknown suffix {suffix!r}; use one of {', '.join(WRITE_SUFFIXES)}")
    # Validate a copy: the file must read back, and the caller's run is left as it was.
    run = Run(dict(run.columns), dict(run.meta)).validate(where=str(path))
    if suffix == ".parquet":
        write_parquet(run.columns, run.meta, path)
    elif suffix == ".csv":
        _write_csv(run, path)
    else:
        _write_mat(run, path)
    return path


def write_columns(columns: dict[str, np.ndarray], meta: dict[str, Any], path: str | os.PathLike[str]) -> Path:
    """Write some columns of a run (a download's selection: any columns, any rows) in the format of the
    suffix, without the run-format check `write_run` makes (which asks for `theta_m` and two rows)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in WRITE_SUFFIXES:
        raise RunFileError(f"{path}: unknown suffix {suffix!r}; use one of {', '.join(WRITE_SUFFIXES)}")
    run = Run(dict(columns), dict(meta))
    if suffix == ".parquet":
        write_parquet(run.columns, run.meta, path)
    elif suffix == ".csv":
        _write_csv(run, path)
    else:
        _write_mat(run, path)
    return path


# ---- reading -------------------------------------------------------------------------------------


def sidecar_path(csv_path: Path) -> Path:
    """The metadata file beside a CSV run: `run.csv` -> `run.csv.json`."""
    return csv_path.with_name(csv_path.name + ".json")


def read_parquet(path: str | os.PathLike[str]) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Columns (float64) and metadata of a Parquet file, not validated as a run."""
    path = Path(path)
    try:
        table = pq.read_table(path)
    except FileNotFoundError:
        raise
    except (pa.ArrowException, OSError) as e:
        raise RunFileError(f"{path}: not a readable Parquet file ({_one_line(e)})") from e
    columns: dict[str, np.ndarray] = {}
    for name, column in zip(table.column_names, table.columns, strict=True):
        kind = column.type
        if not (pa.types.is_floating(kind) or pa.types.is_integer(kind) or pa.types.is_boolean(kind)):
            raise RunFileError(f"{path}: column {name!r} holds {kind}, not numbers")
        # Nulls become NaN here, which Run.validate then reports with their row.
        columns[name] = np.asarray(column.to_numpy(), dtype=np.float64)
    meta: dict[str, Any] = {}
    for raw_key, raw_value in (table.schema.metadata or {}).items():
        key = raw_key.decode("utf-8", "replace")
        if key.startswith("ARROW:") or key == "pandas":  # other writers' bookkeeping, not run metadata
            continue
        text = raw_value.decode("utf-8", "replace")
        try:
            meta[key] = json.loads(text)
        except json.JSONDecodeError:
            meta[key] = text  # written by another tool as plain text
    return columns, meta


def _csv_header(path: Path, text: str) -> list[str]:
    first = next(csv.reader(io.StringIO(text)), None)
    if not first:
        raise RunFileError(f"{path}: empty; expected a header row of column names on line 1")
    names = [name.strip() for name in first]
    for j, name in enumerate(names, start=1):
        if not name:
            raise RunFileError(f"{path}: line 1, column {j}: empty column name")
        if name in names[: j - 1]:
            raise RunFileError(f"{path}: line 1, column {j}: column {name!r} appears twice in the header")
    return names


def _is_number(cell: str) -> bool:
    if "_" in cell:  # Python's float() takes "1_000"; Arrow and other CSV tools do not.
        return False
    try:
        float(cell)
    except ValueError:
        return False
    return True


def _locate_csv_error(path: Path, text: str, names: list[str]) -> str | None:
    """Line-and-column reason of the first bad row, or None; only run once the fast reader failed."""
    reader = csv.reader(io.StringIO(text))
    next(reader)
    try:
        for row in reader:
            line = reader.line_num
            if not row:
                continue
            if len(row) != len(names):
                return f"line {line}: {len(row)} cells, the header has {len(names)} columns"
            for j, cell in enumerate(row):
                if not _is_number(cell):
                    what = "empty cell" if not cell.strip() else f"{cell!r} is not a number"
                    return f"line {line}, column {j + 1} ({names[j]!r}): {what}"
    except csv.Error as e:
        return f"line {reader.line_num + 1}: {_one_line(e)}"
    return None


def _read_csv(path: Path) -> dict[str, np.ndarray]:
    raw = path.read_bytes()
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        line = raw.count(b"\n", 0, e.start) + 1
        raise RunFileError(f"{path}: line {line}: not UTF-8 text (byte {raw[e.start]:#04x})") from e
    names = _csv_header(path, text)
    # Arrow parses fast; the stdlib reader is only used to say where a file Arrow rejects goes wrong.
    options = pa_csv.ConvertOptions(
        column_types=dict.fromkeys(names, pa.float64()),
        null_values=[],
        strings_can_be_null=False,
        quoted_strings_can_be_null=False,
    )
    try:
        table = pa_csv.read_csv(
            io.BytesIO(raw),
            read_options=pa_csv.ReadOptions(skip_rows=1, column_names=names),
            convert_options=options,
        )
    except pa.ArrowInvalid as e:
        where = _locate_csv_error(path, text, names) or _one_line(e)
        raise RunFileError(f"{path}: {where}") from e
    return {name: table.column(name).to_numpy() for name in names}


def _read_sidecar(path: Path) -> dict[str, Any]:
    side = sidecar_path(path)
    if not side.exists():
        return {}
    try:
        meta = json.loads(side.read_text(encoding="utf-8"))
    except json.JSONDecodeError as e:
        raise RunFileError(f"{side}: bad JSON at line {e.lineno}, column {e.colno}: {e.msg}") from e
    except UnicodeDecodeError as e:
        raise RunFileError(f"{side}: not UTF-8 text") from e
    if not isinstance(meta, dict):
        raise RunFileError(f"{side}: expected a JSON object of metadata, found {type(meta).__name__}")
    return meta


def read_run(path: str | os.PathLike[str]) -> Run:
    """Read and validate a `.parquet` run, or a `.csv` run with its optional `<file>.json` metadata."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in READ_SUFFIXES:
        raise RunFileError(
            f"{path}: unknown suffix {suffix!r}; runs are read from {', '.join(READ_SUFFIXES)}"
        )
    if not path.is_file():
        raise RunFileError(f"{path}: no such file")
    if suffix == ".parquet":
        columns, meta = read_parquet(path)
    else:
        columns, meta = _read_csv(path), _read_sidecar(path)
    try:
        return Run(columns, meta).validate(where=str(path))
    except RunFormatError as e:
        raise RunFileError(str(e)) from e
