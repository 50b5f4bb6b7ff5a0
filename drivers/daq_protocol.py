"""The DAQ board's wire format (docs/DAQ_PROTOCOL.md): command lines in, COBS frames with CRC-32 out.

Pure: bytes in, frames out, no I/O and no clock. The host driver (`drivers.serial_daq`) and the device
twin (`sim_backend.daq_twin`) both build on it, so the two ends of the line cannot drift apart.
"""

from __future__ import annotations

import binascii
import struct
from dataclasses import dataclass, replace

import numpy as np

FRAME_DATA = 0x44  # 'D': samples
FRAME_REPLY = 0x52  # 'R': the reply to a command line
FRAME_ANALOG = 0x41  # 'A': samples with the analog channels (after `ANALOG 1`)
VERSION = 1

DATA_HEADER = struct.Struct("<BBIQIB")
"""type, version, seq (u32, frames since START), t0_us (u64, device clock at the first sample),
period_us (u32, between samples), n (u8, samples in the frame)."""
REPLY_HEADER = struct.Struct("<BBH")
"""type, version, tag (u16, echoed from the command line; 0 when the line had none)."""
CRC = struct.Struct("<I")

SAMPLE_DTYPE = np.dtype([("encoder", "<i4"), ("cap", "<i4"), ("status", "u1")])
"""One sample, 9 bytes packed: encoder count since ZERO (i32, wraps), capacitive reading (i32), status."""

ANALOG_CHANNELS = 4
ANALOG_SAMPLE_DTYPE = np.dtype(
    [("encoder", "<i4"), ("cap", "<i4"), ("status", "u1"), ("adc", "<i4", (ANALOG_CHANNELS,))]
)
"""A sample with the analog inputs, 25 bytes packed: SAMPLE_DTYPE's, then the four ADC readings (i32
each; torque transducers, temperature probes: what each means is the rig file's `daq.channels`)."""
_DTYPE_OF = {FRAME_DATA: SAMPLE_DTYPE, FRAME_ANALOG: ANALOG_SAMPLE_DTYPE}

STATUS_ENCODER_FAULT = 0x01
STATUS_CAP_RANGE = 0x02  # the capacitive reading is clipped to the i32 range
STATUS_OVERRUN = 0x04  # the device dropped frames just before this one (its FIFO was full)

SEQ_MODULUS = 2**32
REORDER_WINDOW = 64
"""Frames this far behind the newest one may still be a late or repeated frame; farther back, the
sequence restarted (a device reset)."""
MAX_SAMPLES_PER_FRAME = 255
MAX_FRAME_BYTES = DATA_HEADER.size + MAX_SAMPLES_PER_FRAME * ANALOG_SAMPLE_DTYPE.itemsize + CRC.size
MAX_ENCODED_BYTES = MAX_FRAME_BYTES + MAX_FRAME_BYTES // 254 + 1
_MIN_FRAME_BYTES = REPLY_HEADER.size + CRC.size

ERR_UNKNOWN_COMMAND = 1
ERR_BAD_ARGUMENT = 2
ERR_STREAMING = 3  # not allowed while streaming
ERR_BAD_LINE = 4  # too long or not ASCII
MAX_LINE_BYTES = 80
MAX_TAG = 0xFFFF


def crc32(data: bytes) -> int:
    """CRC-32/ISO-HDLC (zlib's, Ethernet's): check value 0xCBF43926 over b"123456789"."""
    return binascii.crc32(data)


class FrameError(ValueError):
    """Bytes that are not a frame of this protocol."""


class CrcError(FrameError):
    """A well-formed COBS block whose CRC does not match its contents."""


# --- COBS (Cheshire & Baker 1999): no zero inside a frame, so 0x00 ends every frame ------------------


_CODE = [bytes((code,)) for code in range(256)]


def cobs_encode(data: bytes) -> bytes:
    """COBS-encode `data` (without the 0x00 delimiter)."""
    blocks = data.split(b"\x00")
    if max(map(len, blocks)) < 254:  # the usual frame: one join (the twin encodes one every 2 ms)
        return b"".join([part for block in blocks for part in (_CODE[len(block) + 1], block)])
    out = bytearray()
    last = len(blocks) - 1
    for i, block in enumerate(blocks):
        while len(block) >= 254:
            out.append(0xFF)
            out += block[:254]
            block = block[254:]
            if i == last and not block:
                return bytes(out)  # data ends right after a full block: no trailing code byte
        out.append(len(block) + 1)
        out += block
    return bytes(out)


def cobs_decode(encoded: bytes) -> bytes:
    """Invert `cobs_encode`; FrameError on a zero byte or a block running past the end."""
    out = bytearray()
    i, n = 0, len(encoded)
    while i < n:
        code = encoded[i]
        end = i + code
        if code == 0 or end > n:
            raise FrameError("not a COBS block")
        block = encoded[i + 1 : end]
        if 0 in block:
            raise FrameError("zero byte inside a COBS block")
        out += block
        i = end
        if code != 0xFF and i < n:
            out.append(0)
    return bytes(out)


# --- frames ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class DataFrame:
    """A block of samples taken every `period_us` from device time `t0_us`."""

    seq: int
    t0_us: int
    period_us: int
    samples: np.ndarray  # SAMPLE_DTYPE, or ANALOG_SAMPLE_DTYPE in an analog frame
    first_index: int = 0
    """Sample number since START of the first sample, counting lost samples (set by `FrameDecoder`)."""


@dataclass(frozen=True)
class ReplyFrame:
    """The reply to the command line that carried `tag`: `OK ...` or `ERR <code> <text>`."""

    tag: int
    text: str


Frame = DataFrame | ReplyFrame


def _seal(body: bytes) -> bytes:
    return cobs_encode(body + CRC.pack(crc32(body))) + b"\x00"


def encode_data_frame(seq: int, t0_us: int, period_us: int, samples: np.ndarray) -> bytes:
    """The bytes on the line for one data frame, 0x00 delimiter included."""
    n = len(samples)
    if not 1 <= n <= MAX_SAMPLES_PER_FRAME:
        raise ValueError(f"a frame holds 1..{MAX_SAMPLES_PER_FRAME} samples, not {n}")
    kind = FRAME_ANALOG if samples.dtype == ANALOG_SAMPLE_DTYPE else FRAME_DATA
    return encode_packed_frame(
        seq, t0_us, period_us, n, np.ascontiguousarray(samples, _DTYPE_OF[kind]).tobytes()
    )


def encode_packed_frame(seq: int, t0_us: int, period_us: int, n: int, packed: bytes) -> bytes:
    """`encode_data_frame` of `n` samples already packed as SAMPLE_DTYPE's or ANALOG_SAMPLE_DTYPE's bytes
    (which one: from their length), 0x00 delimiter included."""
    if not 1 <= n <= MAX_SAMPLES_PER_FRAME:
        raise ValueError(f"a frame holds 1..{MAX_SAMPLES_PER_FRAME} samples, not {n}")
    kind = FRAME_ANALOG if len(packed) == n * ANALOG_SAMPLE_DTYPE.itemsize else FRAME_DATA
    if len(packed) != n * _DTYPE_OF[kind].itemsize:
        raise ValueError(f"{len(packed)} bytes are not {n} packed samples")
    return _seal(DATA_HEADER.pack(kind, VERSION, seq % SEQ_MODULUS, t0_us, period_us, n) + packed)


def encode_reply_frame(tag: int, text: str) -> bytes:
    """The bytes on the line for one reply, 0x00 delimiter included."""
    return _seal(REPLY_HEADER.pack(FRAME_REPLY, VERSION, tag) + text.encode("ascii"))


def decode_frame(raw: bytes) -> Frame:
    """A frame from its COBS-decoded bytes; CrcError or FrameError says why not."""
    if len(raw) < _MIN_FRAME_BYTES:
        raise FrameError(f"{len(raw)} bytes: shorter than any frame")
    body = raw[: -CRC.size]
    if crc32(body) != CRC.unpack_from(raw, len(body))[0]:
        raise CrcError("CRC mismatch")
    kind, version = body[0], body[1]
    if version != VERSION:
        raise FrameError(f"protocol version {version}, expected {VERSION}")
    if kind in _DTYPE_OF:
        dtype = _DTYPE_OF[kind]
        if len(body) < DATA_HEADER.size:
            raise FrameError("data frame shorter than its header")
        _, _, seq, t0_us, period_us, n = DATA_HEADER.unpack_from(body)
        if n == 0 or period_us == 0 or len(body) != DATA_HEADER.size + n * dtype.itemsize:
            raise FrameError(f"data frame of {len(body)} bytes for {n} samples, period {period_us} µs")
        samples = np.frombuffer(body, dtype, count=n, offset=DATA_HEADER.size)
        return DataFrame(seq, t0_us, period_us, samples)
    if kind == FRAME_REPLY:
        (_, _, tag) = REPLY_HEADER.unpack_from(body)
        try:
            return ReplyFrame(tag, body[REPLY_HEADER.size :].decode("ascii"))
        except UnicodeDecodeError:
            raise FrameError("reply text is not ASCII") from None
    raise FrameError(f"unknown frame type 0x{kind:02x}")


# --- the host's streaming decoder -----------------------------------------------------------------------


@dataclass
class DecoderStats:
    """What the decoder has seen since it was made; lost frames/samples since the last START."""

    frames: int = 0
    samples: int = 0
    replies: int = 0
    crc_errors: int = 0
    malformed: int = 0  # not COBS, too short, unknown type or version, length not matching n
    discarded_bytes: int = 0  # bytes not part of any delivered frame (delimiters not counted)
    lost_frames: int = 0  # by sequence number, including frames lost at the end (STOP's count)
    lost_samples: int = 0
    late_frames: int = 0  # arrived after a later one: delivered at their own index, not counted lost
    duplicates: int = 0  # a frame delivered before, again (same number and time): dropped


class FrameDecoder:
    """Bytes in any pieces → frames, in order. No I/O.

    Resynchronises on the next 0x00 after garbage; a block that fails is searched for a frame at its
    end (garbage without a 0x00 glued in front of a good frame costs the garbage only). Frames with a
    bad CRC are dropped and counted; gaps in the sequence numbers are counted in frames and samples,
    modulo 2**32. Within REORDER_WINDOW frames behind the newest: a frame counted lost that turns up
    late is delivered with its own sample index (and no longer counted lost), and a repeat of a frame
    delivered is dropped, so no sample is invented and none is counted twice. Frames are delivered in
    the order they arrive: a late one comes after its successors (`first_index` says where it goes).
    """

    def __init__(self) -> None:
        self.stats = DecoderStats()
        self._buffer = bytearray()
        self._expected_seq: int | None = None
        self._next_index = 0
        self._missing: dict[int, int] = {}  # seq counted lost → its first_index, within the window
        self._delivered: dict[int, int] = {}  # seq → t0_us of the last REORDER_WINDOW frames delivered

    def restart_sequence(self) -> None:
        """Before START: the device numbers the next stream's frames from 0."""
        self._expected_seq = 0
        self._next_index = 0
        self._missing.clear()
        self._delivered.clear()

    def account_tail(self, frames_sent: int, samples_sent: int) -> None:
        """After STOP: count what the device sent (STOP's reply) but never arrived at the end."""
        if self._expected_seq is None:
            return  # a stream this decoder never saw start
        self.stats.lost_frames += (frames_sent - self._expected_seq) % SEQ_MODULUS
        self.stats.lost_samples += max(0, samples_sent - self._next_index)
        self._expected_seq = None
        self._missing.clear()
        self._delivered.clear()

    def feed(self, data: bytes) -> list[Frame]:
        """The frames completed by `data`, in the order they were sent."""
        buffer = self._buffer
        buffer += data
        frames: list[Frame] = []
        start = 0
        while (end := buffer.find(0, start)) >= 0:
            if end > start:
                self._block(bytes(buffer[start:end]), frames)
            start = end + 1
        del buffer[:start]
        if len(buffer) > MAX_ENCODED_BYTES:  # no delimiter for longer than any frame: only its tail can be
            excess = len(buffer) - MAX_ENCODED_BYTES
            self.stats.discarded_bytes += excess
            del buffer[:excess]
        return frames

    def _block(self, block: bytes, frames: list[Frame]) -> None:
        try:
            frame = decode_frame(cobs_decode(block))
        except FrameError as first_error:
            found = self._frame_at_end(block)
            if found is None:
                if isinstance(first_error, CrcError):
                    self.stats.crc_errors += 1
                else:
                    self.stats.malformed += 1
                self.stats.discarded_bytes += len(block)
                return
            skipped, frame = found
            self.stats.discarded_bytes += skipped
        self._accept(frame, frames)

    @staticmethod
    def _frame_at_end(block: bytes) -> tuple[int, Frame] | None:
        # A frame's first COBS block holds at least its type and version bytes (both nonzero).
        for i in range(1, len(block) - _MIN_FRAME_BYTES):
            if (
                block[i] >= 3
                and block[i + 1] in (FRAME_DATA, FRAME_ANALOG, FRAME_REPLY)
                and block[i + 2] == VERSION
            ):
                try:
                    return i, decode_frame(cobs_decode(block[i:]))
                except FrameError:
                    continue
        return None

    def _accept(self, frame: Frame, frames: list[Frame]) -> None:
        if isinstance(frame, ReplyFrame):
            self.stats.replies += 1
            frames.append(frame)
            return
        n, seq = len(frame.samples), frame.seq
        if self._expected_seq is not None:
            lost = (seq - self._expected_seq) % SEQ_MODULUS
            behind = SEQ_MODULUS - lost
            if lost < SEQ_MODULUS // 2:
                for k in range(max(0, lost - REORDER_WINDOW), lost):
                    self._missing[(self._expected_seq + k) % SEQ_MODULUS] = self._next_index + k * n
                self.stats.lost_frames += lost
                self.stats.lost_samples += lost * n  # a stream's frames all hold the same n
                self._next_index += lost * n
            elif behind <= REORDER_WINDOW and seq in self._missing:
                first_index = self._missing.pop(seq)
                self.stats.lost_frames -= 1
                self.stats.lost_samples -= n
                self.stats.late_frames += 1
                self._deliver(replace(frame, first_index=first_index), frames)
                return
            elif behind <= REORDER_WINDOW and self._delivered.get(seq) == frame.t0_us:
                self.stats.duplicates += 1
                return
            else:  # farther back, or a frame never seen: the device restarted its numbering
                self._missing.clear()
                self._delivered.clear()
        self._expected_seq = (seq + 1) % SEQ_MODULUS
        for old in [s for s in self._missing if (seq - s) % SEQ_MODULUS >= REORDER_WINDOW]:
            del self._missing[old]
        self._deliver(replace(frame, first_index=self._next_index), frames)
        self._next_index += n

    def _deliver(self, frame: DataFrame, frames: list[Frame]) -> None:
        self._delivered[frame.seq] = frame.t0_us
        if len(self._delivered) > REORDER_WINDOW:
            del self._delivered[next(iter(self._delivered))]
        frames.append(frame)
        self.stats.frames += 1
        self.stats.samples += len(frame.samples)


# --- command lines ----------------------------------------------------------------------------------------


def command_line(tag: int, command: str) -> bytes:
    """A host command as sent: `#<tag> <COMMAND> [args]\\n`."""
    return f"#{tag} {command}\n".encode("ascii")


def split_tag(line: str) -> tuple[int, str]:
    """`#17 RATE 1000` → (17, "RATE 1000"); a line without a tag has tag 0. ValueError on a bad tag."""
    if not line.startswith("#"):
        return 0, line
    tag_text, _, rest = line[1:].partition(" ")
    tag = int(tag_text)
    if not 0 <= tag <= MAX_TAG:
        raise ValueError(f"tag {tag} outside 0..{MAX_TAG}")
    return tag, rest.strip()
