"""Property-based fuzzing (hypothesis): whatever bytes or arguments come in, the readers and the command
line answer with their one-line error or a result, never a traceback (issue 15).

Examples are bounded (`max_examples`) so `make test` stays within minutes; a failure prints the
smallest input hypothesis found.
"""

from __future__ import annotations

import contextlib
import io
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers.daq_protocol import FrameDecoder
from model.errors import UserInputError
from model.params import load_model
from model.run import PLAUSIBLE_MAGNITUDE
from rig.cli import main
from rig.config import load_rig_config
from rig.store.runfile import read_run

SEED_TEXT = (Path(__file__).resolve().parents[1] / "configs" / "models" / "seed.yaml").read_bytes()
FUZZ = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])

# Mutations of a real file find more than random bytes: cut it, flip bytes in it, splice garbage in.
mutated = st.tuples(st.integers(0, len(SEED_TEXT)), st.binary(max_size=64), st.integers(0, 64)).map(
    lambda cut: SEED_TEXT[: cut[0]] + cut[1] + SEED_TEXT[cut[0] + cut[2] :]
)
yamlish = st.recursive(
    st.none() | st.booleans() | st.floats() | st.integers() | st.text(max_size=8),
    lambda children: (
        st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=8), children, max_size=4)
    ),
    max_leaves=30,
).map(lambda doc: repr(doc).encode())


def _write(data: bytes, suffix: str) -> Path:
    folder = Path(tempfile.mkdtemp(prefix="hdrig-fuzz-"))
    path = folder / f"file{suffix}"
    path.write_bytes(data)
    return path


@FUZZ
@given(data=mutated | yamlish | st.binary(max_size=256), suffix=st.sampled_from([".yaml", ".json"]))
def test_a_model_file_of_any_bytes_loads_or_is_one_user_error(data: bytes, suffix: str) -> None:
    try:
        load_model(_write(data, suffix))
    except UserInputError as exc:
        assert "\n" not in str(exc) and str(exc), repr(exc)  # one line, and it says something


@FUZZ
@given(data=mutated | yamlish | st.binary(max_size=256))
def test_a_rig_file_of_any_bytes_loads_or_is_one_user_error(data: bytes) -> None:
    try:
        load_rig_config(_write(data, ".yaml"))
    except UserInputError as exc:
        assert "\n" not in str(exc) and str(exc), repr(exc)


CSV_HEAD = b"t,u,i_cmd,theta_m\n0,0,0,0\n0.001,1,0.1,0\n"


@FUZZ
@given(
    body=st.binary(max_size=200)
    | st.lists(
        st.sampled_from([b"0", b"1e300", b"-5", b"nan", b"inf", b";", b",", b"\n", b"0.001", b"t", b"x"]),
        max_size=60,
    ).map(b"".join)
)
def test_a_csv_run_file_of_any_bytes_reads_or_is_one_user_error(body: bytes) -> None:
    try:
        run = read_run(_write(CSV_HEAD + body, ".csv"))
    except UserInputError:
        return
    # What is accepted is plausible: no 1e300 A reaches a fit.
    for name, limit in PLAUSIBLE_MAGNITUDE.items():
        if name in run:
            assert np.all(np.abs(run[name]) <= limit), name
    assert run.sample_rate_hz > 0


@FUZZ
@given(chunks=st.lists(st.binary(max_size=80), max_size=20))
def test_the_daq_frame_decoder_takes_any_bytes_without_raising(chunks: list[bytes]) -> None:
    decoder = FrameDecoder()
    for chunk in chunks:
        decoder.feed(chunk)  # garbage is dropped and counted, never raised
    # Nothing is invented: what was discarded is at most what was fed.
    assert 0 <= decoder.stats.discarded_bytes <= sum(len(chunk) for chunk in chunks)


WORDS = ["model", "show", "list", "simulate", "run", "runs", "export", "analyze", "fit", "gaps", "seed"]
OPTIONS = [
    "--model",
    "--input",
    "--duration",
    "--rate",
    "--dt",
    "--out",
    "--set",
    "--format",
    "--data",
    "--json",
]


@FUZZ
@given(
    argv=st.lists(
        st.sampled_from(WORDS + OPTIONS)
        | st.text(max_size=12)
        | st.sampled_from(["1e309", "-1", "nan", "sine:"]),
        max_size=6,
    )
)
def test_the_command_line_never_shows_a_traceback(argv: list[str]) -> None:
    if "serve" in argv or "run" in argv:  # a rig or a server would start: the fault suite covers those
        return
    home = tempfile.mkdtemp(prefix="hdrig-fuzz-home-")
    err = io.StringIO()
    with (
        pytest.MonkeyPatch.context() as patch,
        contextlib.redirect_stderr(err),
        contextlib.redirect_stdout(io.StringIO()),
    ):
        patch.setenv("HDRIG_HOME", home)
        patch.chdir(home)  # an --out lands in the scratch folder
        try:
            status = main(argv)
        except SystemExit as exit_:  # argparse: usage errors and --help
            status = exit_.code if isinstance(exit_.code, int) else 2
    assert status in (0, 2), (argv, status, err.getvalue())
