"""Chunked simulation and streamed run files: the same numbers as one long call, in bounded pieces.

The reference is the plant integrated in one call over the whole duration (what `simulate` did before
chunking), so the chunk boundaries are checked against a computation that has none. Files written
block by block are read back with readers this project did not write: pyarrow for Parquet and CSV,
scipy's `loadmat` for MAT.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import scipy.io
import scipy.signal

from model import simulate as simulate_module
from model.inputs import InputSpecError, parse_input_spec
from model.params import load_model
from model.plant import Plant
from model.registry import OUT
from model.run import RunFormatError
from model.simulate import CHUNK_ROWS, simulate, simulate_stream
from rig.store.runfile import ROW_GROUP_ROWS, RunFileWriter, read_run, write_stream

SEED = load_model("seed")


def test_chunked_simulation_equals_one_call_over_the_whole_duration(monkeypatch: pytest.MonkeyPatch) -> None:
    # 40 Hz at dt = 1e-4: 250 steps a sample, which does not divide CHUNK_STEPS (made small here so
    # that 9 s takes three chunks), so chunks are cut to whole samples; a chirp and a varying load
    # make every step's input differ. The reference gets its inputs as arrays, the stream evaluates
    # them inside the compiled loop.
    monkeypatch.setattr(simulate_module, "CHUNK_STEPS", 1 << 15)
    dt_s, rate_hz, duration_s = 1e-4, 40.0, 9.0
    chirp, load_spec = "chirp:amp=2,f0=0.2,f1=5", "sine:amp=0.3,freq=0.7"
    run = simulate(SEED, chirp, duration_s, dt_s, rate_hz, tau_ext=load_spec)
    t = np.arange(round(duration_s / dt_s)) * dt_s
    drive = parse_input_spec(chirp)(t, duration_s)
    load = parse_input_spec(load_spec)(t, duration_s)
    plant = Plant(SEED)
    rows = plant.advance(drive, "voltage", load, dt_s, 250)
    assert len(run) == rows.shape[0] == 360
    # Bit for bit: the chunks carry the full state, so splitting the loop changes no arithmetic.
    np.testing.assert_array_equal(run["theta_m"], rows[:, OUT.THETA_M])
    np.testing.assert_array_equal(run["theta_l"], rows[:, OUT.THETA_L])
    np.testing.assert_array_equal(run["u"], rows[:, OUT.DRIVE])
    np.testing.assert_array_equal(run["tau_ext"], rows[:, OUT.TAU_EXT])


def test_a_stream_yields_at_most_one_chunk_of_samples_at_a_time() -> None:
    stream = simulate_stream(SEED, "sine:amp=2,freq=0.5", 100.0, 1e-4, 1000.0)
    sizes = [len(block["t"]) for block in stream]
    assert max(sizes) == CHUNK_ROWS
    assert sum(sizes) == stream.rows == 100_000


# Each kind against a generator this project did not write: scipy's chirp, numpy's functions of whole
# arrays. 1e-12 of the amplitude: the compiled profile takes sin(φ) where scipy takes cos(φ − π/2),
# and φ reaches ~600 rad here, whose rounding (~1e-13 rad) is what may differ.
T_S = np.linspace(-0.5, 20.0, 20_501)
INDEPENDENT = {
    "step:amp=1.5,delay=2,offset=0.1": 0.1 + np.where(T_S >= 2.0, 1.5, 0.0),
    "sine:amp=2,freq=0.5,phase=0.3,offset=-1": -1 + 2 * np.sin(2 * np.pi * 0.5 * T_S + 0.3),
    "ramp:slope=0.25,delay=1": 0.25 * np.maximum(T_S - 1.0, 0.0),
    "chirp:amp=2,f0=0.2,f1=5,duration=12": 2 * scipy.signal.chirp(T_S, 0.2, 12.0, 5.0, phi=-90),
    "chirp:amp=1,f0=0.5,f1=8,duration=10,log=1": scipy.signal.chirp(
        T_S, 0.5, 10.0, 8.0, method="logarithmic", phi=-90
    ),
    "pulse:amp=3,width=0.2,period=1.5,delay=0.7": 3 * ((T_S >= 0.7) & (np.mod(T_S - 0.7, 1.5) < 0.2)),
    "staircase:amp=4,steps=5,hold=2.5": np.linspace(-4, 4, 5)[np.clip(T_S // 2.5, 0, 4).astype(int)],
    "const:value=0.75": np.full_like(T_S, 0.75),
}


@pytest.mark.parametrize("spec", INDEPENDENT)
def test_compiled_profiles_match_independent_generators(spec: str) -> None:
    expected = INDEPENDENT[spec]
    got = parse_input_spec(spec)(T_S, 20.0)
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12 * max(1.0, np.max(np.abs(expected))))


def test_the_stream_drives_the_plant_with_the_profile_values() -> None:
    # The drive column of the run is the profile at the sample times, taken from the step index
    # (step · dt, not the integrator's summed clock), evaluated inside the loop.
    load = "pulse:amp=1,width=0.1,period=1"
    run = simulate(SEED, "chirp:amp=2,f0=0.2,f1=5", 4.0, 1e-4, 100.0, tau_ext=load)
    t = (np.arange(len(run)) * 100.0) * 1e-4
    np.testing.assert_array_equal(run["u"], parse_input_spec("chirp:amp=2,f0=0.2,f1=5")(t, 4.0))
    np.testing.assert_array_equal(run["tau_ext"], parse_input_spec(load)(t))
    assert np.count_nonzero(run["tau_ext"]) == 40  # 0.1 s on in every 1 s: 10 of each 100 samples


@pytest.mark.parametrize(
    ("spec", "told"),
    [
        ("pulse:amp=1,width=0,period=1", "width and period"),
        ("chirp:amp=1,f0=0,f1=5,log=1", "f0 and f1 nonzero"),
        ("staircase:amp=1,steps=2.5", "whole number of steps"),
    ],
)
def test_a_bad_profile_fails_before_any_step(spec: str, told: str) -> None:
    with pytest.raises(InputSpecError, match=told):
        simulate_stream(SEED, spec, 1.0)


def _blocks(n_rows: int, size: int) -> list[dict[str, np.ndarray]]:
    t = np.arange(n_rows) / 1000.0
    return [
        {"t": t[i : i + size], "u": np.sin(t[i : i + size]), "theta_m": 1 / 3 + t[i : i + size] ** 2}
        for i in range(0, n_rows, size)
    ]


META = {"sample_rate_hz": 1000.0, "source": "sim", "model": {"name": "seed", "hash": "abc"}}


@pytest.mark.parametrize("suffix", ["parquet", "csv"])
def test_streamed_file_reads_back_exactly(tmp_path: Path, suffix: str) -> None:
    n = ROW_GROUP_ROWS + 12_345  # more than one row group, the last one partial
    path, rows = write_stream(_blocks(n, 7_000), ["t", "u", "theta_m"], META, tmp_path / f"r.{suffix}")
    assert rows == n
    run = read_run(path)
    t = np.arange(n) / 1000.0
    np.testing.assert_array_equal(run["theta_m"], 1 / 3 + t**2)
    assert run.meta == META
    if suffix == "parquet":
        assert pq.ParquetFile(path).metadata.num_row_groups == 2


def test_streamed_mat_file_opens_with_loadmat(tmp_path: Path) -> None:
    n = 2 * ROW_GROUP_ROWS + 3
    path, _ = write_stream(_blocks(n, 10_000), ["t", "u", "theta_m"], META, tmp_path / "r.mat")
    data = scipy.io.loadmat(path, squeeze_me=True)
    t = np.arange(n) / 1000.0
    np.testing.assert_array_equal(data["t"], t)
    np.testing.assert_array_equal(data["u"], np.sin(t))
    assert data["meta"]["model"].item()["name"] == "seed"
    assert [p.name for p in tmp_path.iterdir()] == ["r.mat"]  # the temporary Parquet is gone


def test_a_bad_block_leaves_no_file_and_names_the_row(tmp_path: Path) -> None:
    blocks = _blocks(3000, 1000)
    blocks[2]["u"][5] = np.nan
    with pytest.raises(RunFormatError, match="column 'u' has a non-finite value at row 2005"):
        write_stream(blocks, ["t", "u", "theta_m"], META, tmp_path / "r.parquet")
    assert list(tmp_path.iterdir()) == []


def test_time_going_back_across_blocks_is_refused(tmp_path: Path) -> None:
    blocks = _blocks(2000, 1000)
    blocks[1]["t"] = blocks[1]["t"] - 0.5
    with pytest.raises(RunFormatError, match="row 1000"):
        write_stream(blocks, ["t", "u", "theta_m"], META, tmp_path / "r.csv")
    assert list(tmp_path.iterdir()) == []


def test_a_selection_need_not_be_a_run(tmp_path: Path) -> None:
    with RunFileWriter(tmp_path / "sel.csv", ["t", "u"], {}, as_run=False) as writer:
        writer.write({"t": np.array([0.5]), "u": np.array([1.0])})
    assert (tmp_path / "sel.csv").read_text() == "t,u\n0.5,1\n"
