"""The serial DAQ: wire format (exact bytes), decoder robustness, the command exchange, and the driver
against its twin over a pty and over socket:// (docs/DAQ_PROTOCOL.md)."""

from __future__ import annotations

import math
import os
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Literal

import numpy as np
import pytest
import serial

from drivers.daq_protocol import (
    MAX_ENCODED_BYTES,
    REORDER_WINDOW,
    SAMPLE_DTYPE,
    STATUS_OVERRUN,
    DataFrame,
    FrameDecoder,
    FrameError,
    ReplyFrame,
    cobs_decode,
    cobs_encode,
    crc32,
    decode_frame,
    encode_data_frame,
    encode_reply_frame,
)
from drivers.hardware_rig import DaqTally
from drivers.serial_daq import ClockEstimate, ClockModel, DaqConfigError, DaqError, SampleBlock, SerialDaq
from hdrig_testing.stepped_plant import SteppedPlantSource
from model.errors import UserInputError
from model.params import HarmonicDriveModel
from model.plant import Plant
from rig.config import Sensors
from rig.faults import DeviceFaultError
from sim_backend.daq_twin import DaqTwin

needs_pty = pytest.mark.skipif(not hasattr(os, "openpty"), reason="no pseudo-terminals on this platform")
Transport = Literal["pty", "socket"]
TRANSPORTS = [pytest.param("pty", marks=needs_pty), "socket"]

CAL_REPLY = "OK ENC_CPR=131072 CAP_UM=0.001 LEVER_M=0.1"
RAD_PER_COUNT = 2 * math.pi / 131072
RAD_PER_CAP_COUNT = 0.001e-6 / 0.1
TWIN_DAQ_TIMEOUT_S = 2.0
"""The wait for a DAQ twin's reply on this machine, as configs/rigs/virtual-can.yaml's daq.timeout_s: with
two CPU hogs on 2 cores its answers were held > 1 s (the driver's default, for a board of its own:
'no reply to TIME? within 1 s' once at load 12), which is no dead board."""
PTY_HELD_S = 4.71
"""The longest a pty held a twin's line here: the caller-away test's reader got no data for 4.71 s, alone in
its process, with two CPU hogs on 2 cores and others' tests and benchmarks (load 9.6; of 39 runs at load
1-10, 16 held it > 0.5 s, 4 > 2 s). Bytes written to one end reach the other only when the kernel's tty
worker runs (a kworker of ordinary priority), and select() on the far end waits for it: a bare pty
reader's select() with a 50 ms timeout returned after 3.04 s, its thread 0 s on the run queue (the
worker, not the reader, was short of CPU); a socketpair's reader, run alike, never waited past 18 ms."""
HOLD_MARGIN = 1.5
"""How much longer than PTY_HELD_S the twin tests ride out: in the board's FIFO and in every wait."""
TWIN_TIMEOUT_S = TWIN_DAQ_TIMEOUT_S + HOLD_MARGIN * PTY_HELD_S
"""The wait for a twin's reply or samples: the line held, then the reply's own wait."""
PTY_HOLDS_MAX_BYTES = 65536 + 4096
"""The most a pty keeps unread: the kernel's limit for a tty port's buffer and the line discipline's read
buffer (here 13.8 kB went in before a write would block)."""


def stream_bytes_per_s(rate_hz: int, samples_per_frame: int) -> float:
    """What a stream puts on the line (a frame's COBS length depends on its data by one byte per 254)."""
    one = encode_data_frame(0, 0, 1, np.zeros(samples_per_frame, dtype=SAMPLE_DTYPE))
    return len(one) * rate_hz / samples_per_frame


def fifo_through_holds(rate_hz: int, samples_per_frame: int = 10) -> int:
    """A board FIFO [bytes] that keeps the stream through HOLD_MARGIN × the longest hold of the pty."""
    return math.ceil(stream_bytes_per_s(rate_hz, samples_per_frame) * HOLD_MARGIN * PTY_HELD_S)


LEAK_PREFIXES = ("serial-daq", "daq-twin")
"""The names of the driver's reader thread and the twin's device thread."""


@pytest.fixture(autouse=True)
def no_reader_or_twin_thread_outlives_its_test() -> Iterator[None]:
    """Every driver and twin a test opens is closed by its end. A reader thread left running polls its
    port for the rest of the session (every 0.5 ms without a file descriptor, as a scripted port): the
    seven the command tests left doubled this process's CPU over the caller-away test's 3 s (1.04 s, 0.46 s
    without them; idle machine) beside the pty tests, whose line waits on a kernel worker (PTY_HELD_S)."""
    before = set(threading.enumerate())
    yield
    left = [t.name for t in threading.enumerate() if t not in before and t.name.startswith(LEAK_PREFIXES)]
    assert not left, f"left running after the test: {left}"


def samples(*rows: tuple[int, int, int]) -> np.ndarray:
    return np.array(list(rows), dtype=SAMPLE_DTYPE)


def frame(seq: int, n: int = 2, t0_us: int = 0, period_us: int = 1000) -> bytes:
    return encode_data_frame(seq, t0_us, period_us, samples(*[(i, -i, 0) for i in range(n)]))


# --- wire format: exact bytes -------------------------------------------------------------------------


def test_crc_is_crc32_iso_hdlc() -> None:
    assert crc32(b"123456789") == 0xCBF43926  # the catalogue check value


@pytest.mark.parametrize(
    ("data", "encoded"),
    [  # Cheshire & Baker's canonical COBS, the examples of its usual description
        (b"", b"\x01"),
        (b"\x00", b"\x01\x01"),
        (b"\x00\x00", b"\x01\x01\x01"),
        (b"\x00\x11\x00", b"\x01\x02\x11\x01"),
        (b"\x11\x22\x00\x33", b"\x03\x11\x22\x02\x33"),
        (b"\x11\x00\x00\x00", b"\x02\x11\x01\x01\x01"),
        (bytes(range(1, 255)), b"\xff" + bytes(range(1, 255))),  # a full run ending the data: no code after
        (bytes(range(0, 255)), b"\x01\xff" + bytes(range(1, 255))),
        (bytes(range(1, 256)), b"\xff" + bytes(range(1, 255)) + b"\x02\xff"),
        (bytes(range(2, 256)) + b"\x00", b"\xff" + bytes(range(2, 256)) + b"\x01\x01"),
        (bytes(range(3, 256)) + b"\x00\x01", b"\xfe" + bytes(range(3, 256)) + b"\x02\x01"),
    ],
)
def test_cobs_matches_the_catalogue_and_decodes_back(data: bytes, encoded: bytes) -> None:
    assert cobs_encode(data) == encoded
    assert cobs_decode(encoded) == data


@pytest.mark.parametrize("data", [bytes(600), b"\x01" * 508, b"\x01" * 254 + b"\x00" * 3 + b"\x02" * 300])
def test_cobs_round_trips_long_runs_with_no_zero_inside(data: bytes) -> None:
    encoded = cobs_encode(data)
    assert 0 not in encoded
    assert cobs_decode(encoded) == data


@pytest.mark.parametrize("bad", [b"\x05\x11\x22", b"\x03\x11\x00\x22", b"\x00"])
def test_cobs_rejects_a_block_past_the_end_or_a_zero(bad: bytes) -> None:
    with pytest.raises(FrameError):
        cobs_decode(bad)


def test_data_frame_exact_bytes() -> None:
    body = (
        b"\x44\x01"  # type 'D', version 1
        + b"\x07\x00\x00\x00"  # seq 7
        + b"\x40\x42\x0f\x00\x00\x00\x00\x00"  # t0 = 1 000 000 µs
        + b"\xf4\x01\x00\x00"  # period 500 µs
        + b"\x02"  # 2 samples
        + b"\xe8\x03\x00\x00\xfe\xff\xff\xff\x00"  # encoder 1000, capacitive -2, status 0
        + b"\xff\xff\xff\xff\x00\x01\x00\x00\x04"  # encoder -1, capacitive 256, overrun
    )
    crc = b"\xd8\xb6\x97\xca"  # CRC-32 of body, little-endian
    line = bytes.fromhex(
        "04 44 01 07 01 01 04 40 42 0f 01 01 01 01 03 f4 01 01 04 02 e8 03 01 05 fe ff ff ff"
        " 05 ff ff ff ff 02 01 01 06 04 d8 b6 97 ca 00"
    )
    sent = encode_data_frame(7, 1_000_000, 500, samples((1000, -2, 0), (-1, 256, STATUS_OVERRUN)))
    assert crc32(body).to_bytes(4, "little") == crc
    assert cobs_decode(line[:-1]) == body + crc
    assert sent == line


def test_data_frame_decodes_back() -> None:
    sent = samples((1000, -2, 0), (-(2**31), 2**31 - 1, 1))
    got = decode_frame(cobs_decode(encode_data_frame(2**32 - 1, 2**40, 50, sent)[:-1]))
    assert isinstance(got, DataFrame)
    assert (got.seq, got.t0_us, got.period_us) == (2**32 - 1, 2**40, 50)
    assert got.samples.tolist() == sent.tolist()


def test_reply_frame_exact_bytes() -> None:
    line = bytes.fromhex("04 52 01 03 15") + b"OK HDRIG-DAQ 1.0 SN1" + bytes.fromhex("04 45 d8 54 00")
    assert encode_reply_frame(3, "OK HDRIG-DAQ 1.0 SN1") == line
    assert decode_frame(cobs_decode(line[:-1])) == ReplyFrame(3, "OK HDRIG-DAQ 1.0 SN1")


# --- the decoder: CRC errors, garbage, gaps -------------------------------------------------------------


def seqs(frames: list[DataFrame | ReplyFrame]) -> list[int]:
    return [f.seq for f in frames if isinstance(f, DataFrame)]


def test_frames_split_anywhere_across_reads_decode_the_same() -> None:
    line = frame(0) + encode_reply_frame(1, "OK") + frame(1)
    decoder = FrameDecoder()
    got = [f for byte in line for f in decoder.feed(bytes([byte]))]
    assert seqs(got) == [0, 1] and got[1] == ReplyFrame(1, "OK")
    assert decoder.stats.discarded_bytes == 0


def test_a_frame_with_a_bad_crc_is_dropped_and_counted_and_the_next_decodes() -> None:
    bad = bytearray(cobs_decode(frame(1)[:-1]))
    bad[20] ^= 0x10  # a bit of the first sample's encoder count
    decoder = FrameDecoder()
    decoder.restart_sequence()
    got = decoder.feed(frame(0) + cobs_encode(bytes(bad)) + b"\x00" + frame(2))
    assert seqs(got) == [0, 2]
    assert decoder.stats.crc_errors == 1
    assert (decoder.stats.lost_frames, decoder.stats.lost_samples) == (1, 2)
    assert decoder.stats.discarded_bytes == len(cobs_encode(bytes(bad)))


def test_garbage_ending_in_a_zero_is_dropped_and_decoding_resumes() -> None:
    decoder = FrameDecoder()
    got = decoder.feed(frame(0) + b"\x13\x37garbage\x00" + frame(1))
    assert seqs(got) == [0, 1]
    assert (decoder.stats.malformed, decoder.stats.discarded_bytes, decoder.stats.lost_frames) == (1, 9, 0)


def test_garbage_without_a_zero_before_a_frame_costs_only_the_garbage() -> None:
    decoder = FrameDecoder()
    got = decoder.feed(frame(0) + b"noise\x44\x01" + frame(1))
    assert seqs(got) == [0, 1]
    assert (decoder.stats.malformed, decoder.stats.crc_errors, decoder.stats.discarded_bytes) == (0, 0, 7)


def test_endless_garbage_without_a_zero_is_bounded_then_the_next_frame_decodes() -> None:
    decoder = FrameDecoder()
    assert decoder.feed(b"\x55" * 10_000) == []
    assert decoder.stats.discarded_bytes == 10_000 - MAX_ENCODED_BYTES
    got = decoder.feed(frame(5))
    assert seqs(got) == [5]
    assert decoder.stats.discarded_bytes == 10_000


def test_a_missing_sequence_number_counts_the_lost_frames_and_samples() -> None:
    decoder = FrameDecoder()
    decoder.restart_sequence()
    got = decoder.feed(frame(0, n=4) + frame(1, n=4) + frame(4, n=4))
    assert (decoder.stats.lost_frames, decoder.stats.lost_samples) == (2, 8)
    assert [f.first_index for f in got if isinstance(f, DataFrame)] == [0, 4, 16]


def test_a_gap_across_the_sequence_wraparound_counts_only_the_missing_frames() -> None:
    decoder = FrameDecoder()
    got = decoder.feed(frame(2**32 - 2, n=3) + frame(2**32 - 1, n=3) + frame(2, n=3))
    assert seqs(got) == [2**32 - 2, 2**32 - 1, 2]
    assert (decoder.stats.lost_frames, decoder.stats.lost_samples) == (2, 6)  # seq 0 and 1


def test_a_first_frame_other_than_zero_after_start_counts_as_lost() -> None:
    decoder = FrameDecoder()
    decoder.restart_sequence()
    decoder.feed(frame(2, n=5))
    assert (decoder.stats.lost_frames, decoder.stats.lost_samples) == (2, 10)


def test_a_sequence_jumping_back_is_a_restarted_device_not_a_loss() -> None:
    decoder = FrameDecoder()
    got = decoder.feed(frame(100) + frame(0) + frame(1))
    assert seqs(got) == [100, 0, 1]
    assert decoder.stats.lost_frames == 0


def timed(seq: int, n: int = 4) -> bytes:
    """Frame `seq` of a stream of n samples per frame at 1 kHz from device time 0, as a board numbers it."""
    return frame(seq, n=n, t0_us=seq * n * 1000)


def test_a_repeated_frame_is_dropped_and_a_late_one_takes_its_own_place() -> None:
    decoder = FrameDecoder()
    decoder.restart_sequence()
    got = decoder.feed(timed(0) + timed(1) + timed(1) + timed(3) + timed(2) + timed(4))
    data = [f for f in got if isinstance(f, DataFrame)]
    assert [f.seq for f in data] == [0, 1, 3, 2, 4]  # delivered as they came, the repeat left out
    assert [f.first_index for f in data] == [0, 4, 12, 8, 16]  # each at its own place: none invented
    stats = decoder.stats
    assert (stats.duplicates, stats.late_frames, stats.lost_frames, stats.lost_samples) == (1, 1, 0, 0)
    assert (stats.frames, stats.samples) == (5, 20)


def test_a_frame_later_than_the_reorder_window_stays_lost() -> None:
    decoder = FrameDecoder()
    decoder.restart_sequence()
    late = REORDER_WINDOW + 2
    decoder.feed(timed(0) + b"".join(timed(k) for k in range(2, late + 1)) + timed(1))
    # Frame 1 came after 65 of its successors: taken for a restarted device, not a late frame.
    assert decoder.stats.late_frames == 0 and decoder.stats.lost_frames == 1


# --- the command exchange, pymeasure-style: exact bytes both ways -------------------------------------


class ScriptedPort:
    """Each write must be the next scripted line; its scripted reply bytes then become readable."""

    def __init__(self, script: list[tuple[bytes, bytes]]) -> None:
        self.script = list(script)
        self.incoming = bytearray()
        self.timeout: float | None = None

    def write(self, data: bytes) -> int:
        assert self.script, f"unexpected write {data!r}"
        expected, reply = self.script.pop(0)
        assert data == expected
        self.incoming += reply
        return len(data)

    def read(self, size: int = 1) -> bytes:
        out = bytes(self.incoming[:size])
        del self.incoming[: len(out)]  # the driver's reader thread reads while the test thread writes
        return out

    def close(self) -> None:
        assert not self.script, f"exchanges never made: {self.script!r}"


def reply(tag: int, text: str) -> bytes:
    return encode_reply_frame(tag, text)


def scripted(*script: tuple[bytes, bytes], timeout_s: float = 0.2) -> SerialDaq:
    return SerialDaq("scripted", port=ScriptedPort(list(script)), timeout_s=timeout_s)


def test_commands_go_out_as_tagged_lines_and_replies_are_matched_by_tag() -> None:
    with scripted(
        (b"#1 ID?\n", reply(1, "OK HDRIG-DAQ 1.0 SN7")),
        (b"#2 CAL?\n", reply(2, CAL_REPLY)),
        (b"#3 RATE 2000\n", reply(3, "OK")),
        (b"#4 BLOCK 20\n", reply(4, "OK")),
        (b"#5 ZERO\n", reply(5, "OK")),
    ) as daq:
        assert daq.identify() == "HDRIG-DAQ 1.0 SN7"
        cal = daq.calibration()
        assert (cal.encoder_counts_per_rev, cal.cap_um_per_count, cal.lever_radius_m) == (131072, 0.001, 0.1)
        assert daq.calibration() is cal  # asked once
        daq.set_rate(2000, samples_per_frame=20)
        daq.zero_encoder()


def test_a_bad_argument_refused_is_bad_input_naming_the_port_and_the_command() -> None:
    with (
        scripted((b"#1 RATE 1500\n", reply(1, "ERR 2 rate 1500 Hz: must be ..."))) as daq,
        pytest.raises(
            DaqConfigError, match=r"^DAQ on scripted: 'RATE 1500' refused: ERR 2 rate 1500 Hz"
        ) as info,
    ):
        daq.set_rate(1500)
    assert isinstance(info.value, UserInputError) and not isinstance(info.value, DeviceFaultError)


def test_another_refusal_is_a_device_fault() -> None:
    with (
        scripted((b"#1 ID?\n", reply(1, "ERR 1 unknown command"))) as daq,
        pytest.raises(DaqError, match=r"^DAQ on scripted: 'ID\?' refused: ERR 1 unknown command$"),
    ):
        daq.identify()


def test_no_reply_is_a_device_fault_naming_the_port_the_command_and_the_wait() -> None:
    with (
        scripted((b"#1 ID?\n", b""), timeout_s=0.05) as daq,
        pytest.raises(DaqError, match=r"^DAQ on scripted: no reply to 'ID\?' within 0.05 s$") as info,
    ):
        daq.identify()
    assert isinstance(info.value, DeviceFaultError) and not isinstance(info.value, UserInputError)


def test_a_late_reply_to_an_earlier_command_is_not_taken_for_the_current_one() -> None:
    late = reply(1, "OK 5")
    with scripted(
        (b"#1 TIME?\n", b""), (b"#2 TIME?\n", late + reply(2, "OK 7000000")), timeout_s=0.05
    ) as daq:
        with pytest.raises(DaqError):
            daq.device_time_s()
        assert daq.device_time_s() == 7.0
        assert daq.stale_replies == 1


def test_unexpected_reply_text_raises_daq_error() -> None:
    with (
        scripted((b"#1 TIME?\n", reply(1, "HELLO"))) as daq,
        pytest.raises(DaqError, match="'TIME\\?' got 'HELLO', neither OK nor ERR"),
    ):
        daq.device_time_s()


def test_a_serial_url_that_does_not_open_is_bad_input_naming_it() -> None:
    with pytest.raises(DaqConfigError, match=r"^DAQ on /dev/no-such-daq: cannot open the port") as info:
        SerialDaq("/dev/no-such-daq")
    assert isinstance(info.value, UserInputError) and not isinstance(info.value, DeviceFaultError)


def test_a_port_that_fails_while_reading_raises_daq_error_naming_it() -> None:
    class UnpluggedPort(ScriptedPort):
        def read(self, size: int = 1) -> bytes:
            raise serial.SerialException("device reports readiness to read but returned no data")

    with (
        SerialDaq("/dev/ttyACM0", port=UnpluggedPort([(b"#1 ID?\n", b"")])) as daq,
        pytest.raises(
            DaqError, match=r"^DAQ on /dev/ttyACM0: 'ID\?' unanswered: read failed: device reports"
        ),
    ):
        daq.identify()


def test_a_pyserial_url_without_a_file_descriptor_opens_and_times_out_cleanly() -> None:
    with (
        SerialDaq("loop://", timeout_s=0.1) as daq,  # loop:// echoes the line back: no frame, no reply
        pytest.raises(DaqError, match=r"^DAQ on loop://: no reply to 'ID\?' within 0.1 s$"),
    ):
        daq.identify()


def test_samples_are_scaled_by_cal_and_the_stop_reply_counts_the_tail_lost() -> None:
    n = 2
    frame0 = encode_data_frame(0, 1_000_000, 500, samples((2**31 - 1, 1000, 0), (-(2**31), -1000, 0)))
    frame1 = encode_data_frame(1, 1_001_000, 500, samples((-(2**31) + 5, 0, 0), (-(2**31) + 6, 1, 0)))
    with scripted(
        (b"#1 CAL?\n", reply(1, CAL_REPLY)),
        (b"#2 START\n", reply(2, "OK") + frame0 + frame1),
        (b"#3 STOP\n", reply(3, "OK 4 8")),
    ) as daq:
        daq.clock_model.add(ClockEstimate(offset_s=100.0, round_trip_s=1e-4, device_s=1.0))
        daq.start()
        block = daq.read_samples(min_samples=4)
        stats = daq.stop()
    np.testing.assert_array_equal(block.t_device_s, [1.0, 1.0005, 1.001, 1.0015])
    np.testing.assert_array_equal(block.t_host_s, block.t_device_s + 100.0)
    # the i32 encoder count wraps between samples 0 and 1: unwrapped it moves on by one count at a time
    np.testing.assert_allclose(block.theta_m_rad / RAD_PER_COUNT, [2**31 - 1, 2**31, 2**31 + 5, 2**31 + 6])
    np.testing.assert_allclose(block.theta_l_rad, np.array([1000, -1000, 0, 1]) * RAD_PER_CAP_COUNT)
    assert block.seq.tolist() == [0, 0, 1, 1] and block.index.tolist() == [0, 1, 2, 3]
    assert (stats.frames, stats.lost_frames, stats.lost_samples) == (2, 2, 2 * n)


def test_samples_already_decoded_are_kept_when_a_read_times_out() -> None:
    with scripted((b"#1 CAL?\n", reply(1, CAL_REPLY) + frame(0, n=3)), timeout_s=0.05) as daq:
        daq.clock_model.add(ClockEstimate(0.0, 1e-4, 0.0))
        daq.calibration()
        with pytest.raises(DaqError, match=r"no 10 samples within 0.05 s \(3 in, 1 frames so far"):
            daq.read_samples(min_samples=10)
        assert len(daq.read_samples()) == 3


def test_the_clock_model_fits_a_drift_once_estimates_span_ten_seconds() -> None:
    model = ClockModel()
    drift = 50e-6  # the device clock runs 50 ppm slow against the host
    for device_s in (0.0, 1.0, 5.0):
        model.add(ClockEstimate(2.0 + drift * device_s, 1e-4, device_s))
    assert model.offset_s(100.0) == pytest.approx(2.0 + drift * 5.0, abs=1e-12)  # < 10 s: latest offset
    for device_s in (10.0, 20.0):
        model.add(ClockEstimate(2.0 + drift * device_s, 1e-4, device_s))
    assert model.offset_s(100.0) == pytest.approx(2.0 + drift * 100.0, abs=1e-9)


# --- against the twin, over a pty and over socket:// ------------------------------------------------------


def wave(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """True angles: the motor swings ±40 rad, the output ±0.4 rad, at 0.7 Hz."""
    s = np.sin(2 * math.pi * 0.7 * t)
    return 40.0 * s, 0.4 * s


@needs_pty
def test_the_clock_offset_estimate_is_within_half_the_round_trip_of_the_true_offset() -> None:
    with (
        DaqTwin(wave, clock_offset_s=1234.5) as twin,
        SerialDaq(twin.url, timeout_s=TWIN_TIMEOUT_S) as daq,
    ):
        estimate = daq.estimate_clock_offset(n=8)
    # device = host + 1234.5 s, so host − device = −1234.5 s; the device clock counts whole µs (floor)
    assert abs(estimate.offset_s + 1234.5) <= estimate.uncertainty_s + 1e-6
    assert estimate.round_trip_s < 0.05


@needs_pty
def test_a_drifting_board_clock_is_followed_once_the_estimates_span_ten_seconds() -> None:
    jumped_s = [0.0]  # both ends read one clock; jumping it stands for waiting

    def clock() -> float:
        return time.monotonic() + jumped_s[0]

    with (
        DaqTwin(wave, drift_ppm=200.0, clock=clock) as twin,
        SerialDaq(twin.url, timeout_s=TWIN_TIMEOUT_S, clock=clock) as daq,
    ):
        first = daq.estimate_clock_offset()
        jumped_s[0] += 20.0
        last = daq.estimate_clock_offset()
        jumped_s[0] += 30.0
        t0 = clock()
        device_s = daq.device_time_s()
        t1 = clock()
        predicted_s = float(daq.host_time_s(device_s))
    # 50 s at 200 ppm: the board gained 10 ms, which a constant offset would miss. The fitted line is
    # off by at most the latest estimate's uncertainty plus the slope's error (both uncertainties over
    # the 20 s between them) carried over 30 s; the check itself is uncertain by half its round trip.
    bound = last.uncertainty_s + (first.uncertainty_s + last.uncertainty_s) * 30 / 20 + (t1 - t0) / 2
    assert abs(device_s + first.offset_s - (t0 + t1) / 2) > 9e-3 - (t1 - t0) / 2  # 7.4 ms seen, held reply
    assert abs(predicted_s - (t0 + t1) / 2) <= bound + 2e-6  # + the board's whole-µs clock


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_samples_stream_at_the_set_rate_and_match_the_source_within_quantization_and_noise(
    transport: Transport,
) -> None:
    noise_rad = 2e-6
    with (
        DaqTwin(
            wave, transport=transport, load_noise_rad=noise_rad, seed=3, fifo_bytes=fifo_through_holds(2000)
        ) as twin,
        SerialDaq(twin.url, timeout_s=TWIN_TIMEOUT_S) as daq,
    ):
        daq.set_rate(2000, samples_per_frame=10)
        daq.start()
        started = time.monotonic()
        block = daq.read_samples(min_samples=1000)
        arrived = time.monotonic()
        stats = daq.stop()
    # 1000 samples at 2 kHz take 0.5 s to be taken: no faster. How much slower is the machine's (a busy
    # one holds the reader back); the rate sustained is bench/bench_daq.py's figure.
    assert arrived - started >= 0.45
    # Stamped on the host clock no later than it arrived, within the clock estimate's stated ±.
    uncertainty = daq.clock_model.estimates[-1].uncertainty_s
    assert block.t_host_s[-1] <= arrived + uncertainty
    np.testing.assert_allclose(np.diff(block.t_device_s), 500e-6, rtol=1e-9)
    assert np.all(np.diff(block.index) == 1) and np.all(np.diff(block.seq.astype(np.int64)) >= 0)
    assert (stats.lost_frames, stats.crc_errors, stats.malformed, stats.discarded_bytes) == (0, 0, 0, 0)
    true_m, true_l = wave(block.t_device_s)
    assert np.max(np.abs(block.theta_m_rad - true_m)) <= RAD_PER_COUNT / 2 * (1 + 1e-9)  # encoder: ±½ count
    residual = block.theta_l_rad - true_l
    assert np.max(np.abs(residual)) < 6 * noise_rad  # capacitive: Gaussian noise (its 1e-8 rad step is ≪ σ)
    assert np.std(residual) == pytest.approx(noise_rad, rel=0.15)  # σ of the std over ≥1000 samples: 2 %


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_line_garbage_and_a_corrupted_frame_cost_one_frame_and_are_counted(transport: Transport) -> None:
    with (
        DaqTwin(wave, transport=transport, fifo_bytes=fifo_through_holds(5000)) as twin,
        SerialDaq(twin.url, timeout_s=TWIN_TIMEOUT_S) as daq,
    ):
        daq.set_rate(5000, samples_per_frame=10)
        daq.start()
        first = daq.read_samples(min_samples=50)
        twin.inject_garbage(b"\x13\x37garbage\x00noise")  # a block not COBS, then bytes before a frame
        second = daq.read_samples(min_samples=50)
        twin.corrupt_next_frame()
        # The corrupted frame is the next one the board sends, which may sit behind frames already queued
        # in its FIFO and the tty on a busy machine: read on until 50 samples past a gap have arrived.
        blocks = [first, second]
        deadline = time.monotonic() + TWIN_TIMEOUT_S
        while time.monotonic() < deadline:
            blocks.append(daq.read_samples(min_samples=50))
            index = np.concatenate([b.index for b in blocks])
            gaps = np.flatnonzero(np.diff(index) != 1)
            if gaps.size and index.size - gaps[-1] > 50:
                break
        stats = daq.stop()
    index = np.concatenate([b.index for b in blocks])
    jumps = np.diff(index)
    assert (stats.malformed, stats.crc_errors, stats.lost_frames, stats.lost_samples) == (1, 1, 1, 10)
    assert sorted(jumps[jumps != 1].tolist()) == [11]  # the corrupted frame's 10 samples, nothing else
    assert stats.discarded_bytes > 14  # the garbage and the corrupted frame


@needs_pty
def test_a_caller_away_for_longer_than_the_tty_buffer_holds_loses_nothing() -> None:
    # The board's FIFO keeps the stream through the pty's holds (PTY_HELD_S, with margin); the caller is
    # away until the board has sent a tenth more than the FIFO and the pty hold together, so a driver
    # that read only when asked would lose frames for sure; its reader thread, draining all along, none.
    rate_hz, per_frame = 10000, 10
    line_bytes_per_s = stream_bytes_per_s(rate_hz, per_frame)
    fifo_bytes = fifo_through_holds(rate_hz, per_frame)
    away_s = 1.1 * (fifo_bytes + PTY_HOLDS_MAX_BYTES) / line_bytes_per_s  # 8.4 s
    with (
        DaqTwin(wave, fifo_bytes=fifo_bytes) as twin,
        SerialDaq(twin.url, timeout_s=TWIN_TIMEOUT_S) as daq,
    ):
        daq.set_rate(rate_hz, samples_per_frame=per_frame)
        daq.start()
        time.sleep(away_s)
        taken = (math.floor(away_s * rate_hz) // per_frame - 1) * per_frame  # whole frames taken by now
        block = daq.read_samples(min_samples=taken)  # delivered or still due
        stats = daq.stop()
    assert len(block) / rate_hz * line_bytes_per_s > fifo_bytes + PTY_HOLDS_MAX_BYTES
    assert np.all(np.diff(block.index) == 1) and stats.lost_samples == 0, stats


@needs_pty
def test_read_until_returns_once_a_sample_taken_at_or_after_the_host_time_is_in() -> None:
    with (
        DaqTwin(wave, fifo_bytes=fifo_through_holds(1000)) as twin,
        SerialDaq(twin.url, timeout_s=TWIN_TIMEOUT_S) as daq,
    ):
        daq.set_rate(1000, samples_per_frame=10)
        daq.start()
        until = time.monotonic() + 0.2
        block = daq.read_until(until)
        returned = time.monotonic()
        daq.stop()
    assert block.t_host_s[-1] >= until
    # Within a frame (10 ms) and its delivery, which the pty may hold (PTY_HELD_S): a wait for more than
    # it needs shows past that margin, and a wait to the timeout raises.
    assert returned - until < HOLD_MARGIN * PTY_HELD_S < TWIN_TIMEOUT_S


@needs_pty
def test_the_twin_answers_a_bad_line_with_err_4_and_goes_on_with_the_next() -> None:
    expected = (
        encode_reply_frame(0, "ERR 4 line longer than 80 bytes")
        + encode_reply_frame(0, "ERR 4 bad tag in '#x ID?'")
        + encode_reply_frame(3, "OK HDRIG-DAQ 1.0 SIM0001")  # lower case and CR LF accepted
    )
    with DaqTwin(wave) as twin:
        line = serial.serial_for_url(twin.url, timeout=2.0)
        line.write(b"X" * 100 + b"\n#x ID?\n#3 id?\r\n")
        got = line.read(len(expected))
        line.close()
    assert got == expected


@needs_pty
def test_configuration_is_refused_while_streaming() -> None:
    with (
        DaqTwin(wave, fifo_bytes=fifo_through_holds(1000)) as twin,
        SerialDaq(twin.url, timeout_s=TWIN_TIMEOUT_S) as daq,
    ):
        daq.start()
        with pytest.raises(DaqError, match=r"'RATE 500' refused: ERR 3 not allowed while streaming"):
            daq.set_rate(500)
        assert daq.identify().startswith("HDRIG-DAQ 1.0")  # queries are answered between frames
        daq.stop()


@needs_pty
def test_a_rate_without_a_whole_number_of_microseconds_is_refused() -> None:
    with DaqTwin(wave) as twin, SerialDaq(twin.url, timeout_s=TWIN_TIMEOUT_S) as daq:
        with pytest.raises(DaqConfigError, match="ERR 2 rate 3000 Hz"):
            daq.set_rate(3000)
        daq.set_rate(2500)  # 400 µs: accepted


@needs_pty
def test_the_twin_measures_a_plant_it_steps_with_the_rig_files_sensors(seed: HarmonicDriveModel) -> None:
    def drive(t: np.ndarray) -> np.ndarray:
        return 2.0 * np.sin(2 * math.pi * 2.0 * t)

    sensors = Sensors(encoder_counts_per_rev=131072, load_sensor_noise_rad=2e-6, seed=1)
    # The plant's compiled loop loaded now, as a board is ready before it streams: its first call took
    # 3.3 s with two CPU hogs on 2 cores (numba's cache, load 8), inside the 5 s wait for 200 samples
    # (0 in after 5 s once, at load 10).
    Plant(seed).advance(drive(np.zeros(1)), "voltage", dt_s=1e-4, decim=1)
    with (
        DaqTwin.from_sensors(
            SteppedPlantSource(Plant(seed), drive), sensors, fifo_bytes=fifo_through_holds(1000)
        ) as twin,
        SerialDaq(twin.url, timeout_s=TWIN_TIMEOUT_S) as daq,
    ):
        daq.set_rate(1000)
        daq.start()
        block = daq.read_samples(min_samples=200)
        daq.stop()
    # The same plant stepped to the same device times gives the truth the board measured.
    true_m, true_l = SteppedPlantSource(Plant(seed), drive)(block.t_device_s)
    assert np.ptp(true_m) > 0.1  # the motor does move
    assert np.max(np.abs(block.theta_m_rad - true_m)) <= RAD_PER_COUNT / 2 * (1 + 1e-9)
    assert np.max(np.abs(block.theta_l_rad - true_l)) < 6 * 2e-6


@pytest.mark.skipif(not Path("/proc/self/fd").exists(), reason="counts open files through /proc")
@pytest.mark.parametrize("transport", TRANSPORTS)
def test_closing_the_twin_and_the_driver_leaves_no_thread_and_no_file_open(transport: Transport) -> None:
    fds, threads = len(os.listdir("/proc/self/fd")), threading.active_count()
    with (
        DaqTwin(wave, transport=transport, fifo_bytes=fifo_through_holds(1000)) as twin,
        SerialDaq(twin.url, timeout_s=TWIN_TIMEOUT_S) as daq,
    ):
        daq.start()
        daq.read_samples(min_samples=10)
        daq.stop()
    assert threading.active_count() == threads
    assert len(os.listdir("/proc/self/fd")) == fds


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_repeated_and_swapped_frames_on_the_line_invent_no_sample_and_lose_none(transport: Transport) -> None:
    with (
        DaqTwin(wave, transport=transport, fifo_bytes=fifo_through_holds(5000)) as twin,
        SerialDaq(twin.url, timeout_s=TWIN_TIMEOUT_S) as daq,
    ):
        daq.set_rate(5000, samples_per_frame=10)
        daq.start()
        blocks = [daq.read_samples(min_samples=50)]
        twin.repeat_next_frame()
        blocks.append(daq.read_samples(min_samples=50))
        twin.swap_next_frames()
        blocks.append(daq.read_samples(min_samples=200))
        stats = daq.stop()
    for block in blocks:  # each block in device-time order, whatever order its frames came in
        assert np.all(np.diff(block.t_device_s) > 0) and np.all(np.diff(block.index) > 0)
    index = np.sort(np.concatenate([b.index for b in blocks]))
    assert np.array_equal(index, np.arange(index[0], index[0] + len(index)))  # none twice, none missing
    assert (stats.duplicates, stats.late_frames, stats.lost_frames, stats.lost_samples) == (1, 1, 0, 0)
    t = np.concatenate([b.t_device_s for b in blocks])
    theta_m, _ = wave(t[np.argsort(np.concatenate([b.index for b in blocks]))])
    # Each sample is the source at its own device time (the encoder's quantum, 2π/131072 rad).
    got = np.concatenate([b.theta_m_rad for b in blocks])[
        np.argsort(np.concatenate([b.index for b in blocks]))
    ]
    assert np.max(np.abs(got - got[0] - (theta_m - theta_m[0]))) <= 2 * RAD_PER_COUNT


def test_the_rigs_tally_counts_no_gap_where_a_late_frame_filled_it() -> None:
    def block(first: int) -> SampleBlock:
        index = np.arange(first, first + 10)
        t = index * 1e-3
        return SampleBlock(t, t, t, t, np.zeros(10, np.uint32), index, np.zeros(10, np.uint8))

    tally = DaqTally()
    tally.add(block(0))
    tally.add(block(20))
    assert tally.index_gaps == 10  # samples 10..19 not (yet) in
    tally.add(block(10))  # the late frame
    assert (tally.index_gaps, tally.samples) == (0, 30)
    tally.new_stream()
    tally.add(block(0))
    tally.add(block(15))
    assert tally.index_gaps == 5  # the new stream's own gap, the first stream's none
