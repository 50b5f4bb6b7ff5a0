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
import struct
from collections.abc import Iterable, Iterator
from pathlib import Path
from types import TracebackType
from typing import IO, Any

import numpy as np
import pyarrow as pa
import pyarrow.csv as pa_csv
import pyarrow.parquet as pq

from model.errors import UserInputError
from model.run import KNOWN_COLUMNS, Run, RunFormatError, check_values

WRITE_SUFFIXES = (".parquet", ".csv", ".mat")
READ_SUFFIXES = (".parquet", ".csv")
_MATLAB_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_]{0,62}")
_MAT_META_VARIABLE = "meta"
ROW_GROUP_ROWS = 1 << 16
"""Rows per Parquet row group in run files: a window or a column of a long run is read a group at a time."""
USE_DICTIONARY = False
"""Parquet dictionary encoding, off: measured sample columns rarely repeat a value, so the writer built a
dictionary per column and row group only to drop it, at +26 MB of peak memory per 16 row groups written
(what a recording's compaction does while it records) and ~5x the time; constant columns still compress."""


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
        pq.write_table(table, f, row_group_size=ROW_GROUP_ROWS, use_dictionary=USE_DICTIONARY)
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
    import scipy.io  # ~0.1 s to import: only MAT files need it

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


# ---- streaming: a run of any length, block by block -----------------------------------------------


class StreamCheck:
    """The run-format checks of `Run.validate`, made block by block: finite values, `t` strictly
    increasing across blocks, and (with `as_run`) `theta_m` present and at least two rows in all."""

    def __init__(self, where: str, names: list[str], as_run: bool = True) -> None:
        self.where = where
        self.as_run = as_run
        self.rows = 0
        self._last_t: float | None = None
        if as_run:
            for required in ("t", "theta_m"):
                if required not in names:
                    raise RunFormatError(f"{where}: required column {required!r} is missing")

    def block(self, columns: dict[str, np.ndarray]) -> None:
        for name, values in columns.items():
            # Finite only: what a simulation writes is whatever the model made of its input.
            check_values(self.where, name, values, self.rows, plausible=False)
        t = columns.get("t")
        if t is not None and t.size:
            steps = np.diff(t)
            if self._last_t is not None and t[0] <= self._last_t:
                bad_row = self.rows
            elif np.any(steps <= 0):
                bad_row = self.rows + int(np.flatnonzero(steps <= 0)[0]) + 1
            else:
                bad_row = -1
            if bad_row >= 0:
                raise RunFormatError(
                    f"{self.where}: column 't' must be strictly increasing; row {bad_row} goes back"
                )
            self._last_t = float(t[-1])
        self.rows += len(next(iter(columns.values()))) if columns else 0

    def close(self) -> None:
        if self.as_run and self.rows < 2:
            raise RunFormatError(f"{self.where}: needs at least 2 samples, has {self.rows}")


class RunFileWriter:
    """Writes a run block by block, so its length is bounded by the disk, not by memory.

    Parquet goes out a row group at a time, CSV a block at a time (metadata beside it in
    `<file>.json`); MAT, whose variables are whole columns, is first written as a temporary Parquet
    file beside the target and then converted one column and row group at a time. Nothing appears under
    `path` until `close()` (or a clean `with` exit); on an error the partial file is removed. With
    `as_run=False` the blocks are a selection (any columns, any rows) and only finite values and the
    order of `t` are checked, as `write_columns` does; `checked=False` checks nothing.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        names: Iterable[str],
        meta: dict[str, Any],
        as_run: bool = True,
        checked: bool = True,
    ) -> None:
        self.path = Path(path)
        self.suffix = self.path.suffix.lower()
        if self.suffix not in WRITE_SUFFIXES:
            raise RunFileError(
                f"{self.path}: unknown suffix {self.suffix!r}; use one of {', '.join(WRITE_SUFFIXES)}"
            )
        self.names = ordered_columns(names)
        self.meta = dict(meta)
        self.check = StreamCheck(str(self.path), self.names, as_run)
        self.checked = checked  # False: copy rows as recorded (the store's own compaction and sealing)
        if self.suffix == ".mat":
            for name in self.names:
                if not _MATLAB_NAME.fullmatch(name) or name == _MAT_META_VARIABLE:
                    raise RunFileError(f"{self.path}: column {name!r} cannot be a MATLAB variable name")
        self._schema = pa.schema([(c, pa.float64()) for c in self.names])
        body = self.path if self.suffix != ".mat" else self.path.with_suffix(".mat.parquet")
        self._tmp = body.with_name(f".{body.name}.{os.getpid()}.tmp")
        self._file: IO[bytes] = open(self._tmp, "wb")  # noqa: SIM115 - held until close() or discard()
        self._pending: list[pa.Table] = []
        self._pending_rows = 0
        self._parquet: pq.ParquetWriter | None = None
        self._csv: pa_csv.CSVWriter | None = None
        try:
            self._open_format()
        except BaseException:
            self.discard()
            raise

    def _open_format(self) -> None:
        if self.suffix == ".csv":
            header = io.StringIO()
            csv.writer(header, lineterminator="\n").writerow(self.names)
            self._file.write(header.getvalue().encode())
            self._csv = pa_csv.CSVWriter(
                self._file, self._schema, write_options=pa_csv.WriteOptions(include_header=False)
            )
        else:
            kv = {key: json_text(value) for key, value in self.meta.items()}
            self._parquet = pq.ParquetWriter(
                self._file, self._schema.with_metadata(kv), use_dictionary=USE_DICTIONARY
            )

    def write(self, block: dict[str, np.ndarray]) -> None:
        """Append rows: one array per column, equal lengths, `t` continuing to increase."""
        if set(block) != set(self.names):
            raise ValueError(f"{self.path}: block has columns {sorted(block)}, the file has {self.names}")
        arrays = {c: np.asarray(block[c], dtype=np.float64) for c in self.names}
        if self.checked:
            self.check.block(arrays)
        else:
            self.check.rows += len(arrays[self.names[0]])
        table = pa.table(arrays, schema=self._schema)
        if self._csv is not None:
            self._csv.write_table(table)
            return
        self._pending.append(table)
        self._pending_rows += table.num_rows
        if self._pending_rows >= ROW_GROUP_ROWS:
            self._write_groups(final=False)

    def _write_groups(self, final: bool) -> None:
        assert self._parquet is not None
        joined = pa.concat_tables(self._pending) if self._pending else self._schema.empty_table()
        whole = joined.num_rows if final else joined.num_rows - joined.num_rows % ROW_GROUP_ROWS
        if whole:
            self._parquet.write_table(joined.slice(0, whole), row_group_size=ROW_GROUP_ROWS)
        rest = joined.slice(whole)
        self._pending = [rest] if rest.num_rows else []
        self._pending_rows = rest.num_rows

    def close(self) -> Path:
        """Finish the file and move it into place; returns its path."""
        try:
            if self.checked:
                self.check.close()
            if self._csv is not None:
                self._csv.close()
            else:
                self._write_groups(final=True)
                assert self._parquet is not None
                self._parquet.close()
            self._file.flush()
            os.fsync(self._file.fileno())
            self._file.close()
            if self.suffix == ".mat":
                _parquet_to_mat(self._tmp, self.path, self.meta)
            else:
                os.replace(self._tmp, self.path)
            if self.suffix == ".csv":
                with _atomic_write(sidecar_path(self.path)) as f:
                    f.write(json_text(self.meta, indent=2).encode())
        finally:
            self.discard()
        return self.path

    def discard(self) -> None:
        """Drop what was written (an error happened); the target path is left untouched."""
        for stream in (self._parquet, self._csv):
            if stream is not None and not self._file.closed:
                with contextlib.suppress(pa.ArrowException, ValueError):
                    stream.close()  # its footer goes to the file about to be deleted
        if not self._file.closed:
            self._file.close()
        self._tmp.unlink(missing_ok=True)

    def __enter__(self) -> RunFileWriter:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if exc is None:
            self.close()
        else:
            self.discard()


# MAT level 5 (what MATLAB's `load` reads since v5): 128-byte header, then one data element per variable.
_MI_INT8, _MI_INT32, _MI_UINT32, _MI_DOUBLE, _MI_MATRIX = 1, 5, 6, 9, 14
_MX_DOUBLE_CLASS = 6
_MAT_ELEMENT_LIMIT = 2**32 - 1  # the element size is a uint32: a column of ~536 M doubles at most


def _pad8(n: int) -> int:
    return (8 - n % 8) % 8


def _mat_column_header(name: str, rows: int) -> bytes:
    """An uncompressed miMATRIX element up to its real part's data: rows × 1 doubles named `name`."""
    data_bytes = 8 * rows
    name_bytes = name.encode("ascii")
    body = b"".join(
        [
            struct.pack("<II", _MI_UINT32, 8),
            struct.pack("<II", _MX_DOUBLE_CLASS, 0),
            struct.pack("<II", _MI_INT32, 8),
            struct.pack("<ii", rows, 1),
            struct.pack("<II", _MI_INT8, len(name_bytes)),
            name_bytes + b"\0" * _pad8(len(name_bytes)),
            struct.pack("<II", _MI_DOUBLE, data_bytes),
        ]
    )
    size = len(body) + data_bytes  # 8·rows is a multiple of 8: no padding after the data
    if size > _MAT_ELEMENT_LIMIT:
        raise RunFileError(f"column {name!r}: {rows} rows is more than a MAT variable holds; use parquet")
    return struct.pack("<II", _MI_MATRIX, size) + body


def _parquet_to_mat(source: Path, path: Path, meta: dict[str, Any]) -> None:
    """Write the columns of a Parquet file as MAT variables (column vectors), one row group at a time."""
    import scipy.io

    parquet = pq.ParquetFile(source)
    rows = parquet.metadata.num_rows
    # The metadata struct is small: scipy encodes it, and its element is appended after the columns.
    meta_file = io.BytesIO()
    scipy.io.savemat(
        meta_file, {_MAT_META_VARIABLE: _matlab_value(meta)}, do_compression=True, long_field_names=True
    )
    with _atomic_write(path) as f:
        f.write(meta_file.getvalue()[:128])  # the same header scipy writes
        for name in parquet.schema_arrow.names:
            f.write(_mat_column_header(name, rows))
            for group in range(parquet.num_row_groups):
                column = parquet.read_row_group(group, columns=[name]).column(0)
                f.write(np.ascontiguousarray(column.to_numpy(), dtype="<f8").tobytes())
        f.write(meta_file.getvalue()[128:])


def write_stream(
    blocks: Iterable[dict[str, np.ndarray]],
    names: Iterable[str],
    meta: dict[str, Any],
    path: str | os.PathLike[str],
    as_run: bool = True,
) -> tuple[Path, int]:
    """Write blocks of rows to `path` (format by suffix) in bounded memory; (path, rows written)."""
    with RunFileWriter(path, names, meta, as_run) as writer:
        for block in blocks:
            writer.write(block)
    return writer.path, writer.check.rows


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
    if len(names) == 1:
        other = next((sep for sep in (";", "\t", "|") if sep in names[0]), None)
        if other is not None:
            shown = {";": "';'", "\t": "a tab", "|": "'|'"}[other]
            raise RunFileError(
                f"{path}: line 1 is one column {names[0]!r}: the columns look separated by {shown};"
                " a run CSV is comma-separated with '.' decimals"
            )
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
