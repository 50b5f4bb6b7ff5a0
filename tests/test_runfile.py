"""Run files: each format round-trips data and metadata; each bad input is one line naming file and place."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import scipy.io

from model.run import Run
from rig.store.runfile import RunFileError, read_run, sidecar_path, write_run

META = {
    "sample_rate_hz": 1000.0,
    "source": "sim",
    "experiment": "speed-sweep",
    "rig": "sim",
    "model": {"name": "seed", "hash": "3f2a9c"},
    "created": "2026-11-21T15:42:33.000+00:00",
    "notes": "line one, with a comma",
}


def make_run() -> Run:
    """Values chosen to need all 17 significant digits, and an extra column listed before CONTRACT ones."""
    t = np.arange(6) / 1000.0
    return Run(
        {
            "temp_c": np.array([21.0, 1 / 3, -2.5e-300, 1e300, 0.1 + 0.2, -0.0]),
            "theta_m": np.sqrt(np.arange(6.0)) * np.pi,
            "t": t,
            "u": np.sin(2 * np.pi * 7.3 * t),
            "omega_m": np.exp(-t),
        },
        dict(META),
    )


def bad_csv(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "bad.csv"
    path.write_text(text)
    return path


def error_of(path: Path) -> str:
    with pytest.raises(RunFileError) as info:
        read_run(path)
    message = str(info.value)
    assert "\n" not in message
    assert str(path) in message
    return message


# ---- round trips ---------------------------------------------------------------------------------


@pytest.mark.parametrize("suffix", [".parquet", ".csv"])
def test_round_trip_keeps_every_column_bit_exact(tmp_path: Path, suffix: str) -> None:
    run = make_run()
    back = read_run(write_run(run, tmp_path / f"run{suffix}"))
    assert set(back.columns) == set(run.columns)
    for name, values in run.columns.items():
        np.testing.assert_array_equal(back[name], values, strict=True)


@pytest.mark.parametrize("suffix", [".parquet", ".csv"])
def test_round_trip_keeps_metadata(tmp_path: Path, suffix: str) -> None:
    back = read_run(write_run(make_run(), tmp_path / f"run{suffix}"))
    assert back.meta == META


@pytest.mark.parametrize("suffix", [".parquet", ".csv"])
def test_columns_are_written_in_contract_order_then_extras(tmp_path: Path, suffix: str) -> None:
    path = write_run(make_run(), tmp_path / f"run{suffix}")
    if suffix == ".parquet":
        names = pq.read_schema(path).names
    else:
        names = path.read_text().splitlines()[0].split(",")
    assert names == ["t", "u", "theta_m", "omega_m", "temp_c"]


def test_csv_metadata_is_in_a_json_file_beside_it(tmp_path: Path) -> None:
    path = write_run(make_run(), tmp_path / "run.csv")
    assert sidecar_path(path) == tmp_path / "run.csv.json"
    assert json.loads((tmp_path / "run.csv.json").read_text()) == META


def test_parquet_metadata_values_are_json_encoded(tmp_path: Path) -> None:
    path = write_run(make_run(), tmp_path / "run.parquet")
    kv = pq.read_schema(path).metadata
    assert json.loads(kv[b"model"]) == {"name": "seed", "hash": "3f2a9c"}


def test_csv_without_sidecar_reads_with_empty_metadata(tmp_path: Path) -> None:
    path = tmp_path / "plain.csv"
    path.write_text("t,u,theta_m\n0,1,2\n0.5,1.5,2.5\n")
    run = read_run(path)
    assert run.meta == {}
    np.testing.assert_array_equal(run["theta_m"], [2.0, 2.5])


def test_csv_header_tolerates_spaces_and_a_byte_order_mark(tmp_path: Path) -> None:
    path = tmp_path / "excel.csv"
    path.write_text("\ufefft, u, theta_m\n0, 1, 2\n1, 2, 3\n", encoding="utf-8")
    assert list(read_run(path).columns)[:3] == ["t", "u", "theta_m"]


def test_mat_file_holds_each_column_as_a_column_vector(tmp_path: Path) -> None:
    run = make_run()
    mat = scipy.io.loadmat(write_run(run, tmp_path / "run.mat"))
    for name, values in run.columns.items():
        assert mat[name].shape == (len(values), 1)
        np.testing.assert_array_equal(mat[name][:, 0], values)


def test_mat_file_holds_metadata_as_a_struct(tmp_path: Path) -> None:
    mat = scipy.io.loadmat(write_run(make_run(), tmp_path / "run.mat"), simplify_cells=True)
    assert mat["meta"]["model"] == {"name": "seed", "hash": "3f2a9c"}
    assert mat["meta"]["sample_rate_hz"] == 1000.0
    assert mat["meta"]["notes"] == META["notes"]


def test_mat_refuses_a_column_matlab_cannot_name(tmp_path: Path) -> None:
    run = make_run()
    run.columns["2nd_encoder"] = run["t"]
    with pytest.raises(RunFileError, match="'2nd_encoder' cannot be a MATLAB variable name"):
        write_run(run, tmp_path / "run.mat")


def test_write_leaves_the_callers_run_unchanged(tmp_path: Path) -> None:
    run = Run({"t": np.array([0.0, 1.0]), "u": np.zeros(2), "theta_m": np.array([0.0, 2.0])})
    back = read_run(write_run(run, tmp_path / "run.parquet"))
    assert "omega_m" not in run  # validation derives it on the copy that is written
    np.testing.assert_array_equal(back["omega_m"], [2.0, 2.0])


def test_write_replaces_an_existing_file_and_leaves_no_temporary(tmp_path: Path) -> None:
    path = tmp_path / "run.parquet"
    path.write_text("old")
    write_run(make_run(), path)
    assert len(read_run(path)) == 6
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.parquet"]


# ---- bad input -----------------------------------------------------------------------------------


def test_missing_file_is_named(tmp_path: Path) -> None:
    assert "no such file" in error_of(tmp_path / "absent.csv")


def test_unknown_suffix_on_read_is_named(tmp_path: Path) -> None:
    path = tmp_path / "run.txt"
    path.write_text("t,theta_m\n")
    assert "unknown suffix '.txt'" in error_of(path)


def test_unknown_suffix_on_write_is_named(tmp_path: Path) -> None:
    with pytest.raises(RunFileError, match=r"run\.xlsx: unknown suffix '\.xlsx'"):
        write_run(make_run(), tmp_path / "run.xlsx")


def test_non_numeric_cell_names_line_and_column(tmp_path: Path) -> None:
    path = bad_csv(tmp_path, "t,u,theta_m\n0,1,2\n0.1,oops,2\n")
    assert "line 3, column 2 ('u'): 'oops' is not a number" in error_of(path)


def test_empty_cell_names_line_and_column(tmp_path: Path) -> None:
    path = bad_csv(tmp_path, "t,u,theta_m\n0,1,2\n0.1,1,2\n0.2,1,\n")
    assert "line 4, column 3 ('theta_m'): empty cell" in error_of(path)


def test_cell_python_would_accept_but_csv_tools_do_not_is_refused(tmp_path: Path) -> None:
    path = bad_csv(tmp_path, "t,u,theta_m\n0,1,2\n1,1_000,2\n")
    assert "line 3, column 2 ('u')" in error_of(path)


def test_row_with_wrong_cell_count_names_the_line(tmp_path: Path) -> None:
    path = bad_csv(tmp_path, "t,u,theta_m\n0,1,2\n0.1,1\n")
    assert "line 3: 2 cells, the header has 3 columns" in error_of(path)


def test_binary_garbage_names_the_line(tmp_path: Path) -> None:
    path = tmp_path / "bad.csv"
    path.write_bytes(b"t,u,theta_m\n0,1,2\n\xff\xfe\x00garbage\n")
    assert "line 3: not UTF-8 text" in error_of(path)


def test_empty_csv_says_a_header_is_expected(tmp_path: Path) -> None:
    assert "expected a header row" in error_of(bad_csv(tmp_path, ""))


def test_duplicate_header_name_names_the_column(tmp_path: Path) -> None:
    path = bad_csv(tmp_path, "t,u,u,theta_m\n0,1,1,2\n")
    assert "line 1, column 3: column 'u' appears twice" in error_of(path)


def test_run_format_breach_is_a_run_file_error_naming_the_file(tmp_path: Path) -> None:
    path = bad_csv(tmp_path, "t,u,theta_m\n0,1,2\n0,1,2\n")
    assert "column 't' must be strictly increasing" in error_of(path)


def test_bad_sidecar_json_names_the_sidecar_line_and_column(tmp_path: Path) -> None:
    path = bad_csv(tmp_path, "t,u,theta_m\n0,1,2\n1,1,2\n")
    sidecar_path(path).write_text('{\n  "source": "sim",\n  "notes": oops\n}\n')
    with pytest.raises(RunFileError) as info:
        read_run(path)
    assert str(info.value).startswith(f"{path}.json: bad JSON at line 3, column 12")


def test_sidecar_that_is_not_an_object_is_refused(tmp_path: Path) -> None:
    path = bad_csv(tmp_path, "t,u,theta_m\n0,1,2\n1,1,2\n")
    sidecar_path(path).write_text("[1, 2]")
    with pytest.raises(RunFileError, match=r"bad\.csv\.json: expected a JSON object of metadata, found list"):
        read_run(path)


def test_garbled_parquet_is_named(tmp_path: Path) -> None:
    path = tmp_path / "run.parquet"
    path.write_bytes(b"PAR1 this is not really parquet")
    assert "not a readable Parquet file" in error_of(path)


def test_parquet_text_column_is_named(tmp_path: Path) -> None:
    path = tmp_path / "run.parquet"
    pq.write_table(pa.table({"t": [0.0, 1.0], "theta_m": ["a", "b"]}), path)
    assert "column 'theta_m' holds string, not numbers" in error_of(path)
