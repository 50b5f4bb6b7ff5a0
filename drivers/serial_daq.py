"""Serial DAQ driver: a motor encoder and a capacitive output sensor on one board (docs/DAQ_PROTOCOL.md).

The port is any pyserial URL (`/dev/ttyACM0`, a pty path, `socket://127.0.0.1:5000`, `loop://`).
Commands go out as ASCII lines; everything the board sends comes back as COBS frames (replies and
samples alike), which `drivers.daq_protocol.FrameDecoder` turns into frames. Samples are timestamped
by the board; `estimate_clock_offset` relates its clock to the host's (NTP's minimum-delay filter) so
that every sample also carries a host time, to be aligned with the servo's samples.

A reader thread drains the port from open to close, whatever the caller's cadence: the kernel's
buffer for a tty is small (a pty holds ~20 kB, 0.2 s of a 10 kHz stream), and a board whose host does
not read drops frames. Callers wait on what it has decoded; any thread may call any method.

Errors name the port and the command in one line. What the user can fix is a `DaqConfigError`: a port
that will not open, a setting the board refuses as a bad argument (`ERR 2`, e.g. a rate whose period is
not a whole number of µs). A board or line that fails while working is a `DaqError`, a device fault: no
reply, a reply that makes no sense, any other refusal, a stream that stops, a port that fails.
"""

from __future__ import annotations

import math
import select
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Final, Protocol

import numpy as np
import serial
from numpy.typing import ArrayLike
from pydantic import BaseModel, ConfigDict, Field, model_validator

from drivers.daq_protocol import (
    ANALOG_CHANNELS,
    ANALOG_SAMPLE_DTYPE,
    ERR_BAD_ARGUMENT,
    MAX_TAG,
    DataFrame,
    DecoderStats,
    FrameDecoder,
    ReplyFrame,
    command_line,
)
from model.errors import UserInputError
from rig.faults import DeviceFaultError

DEFAULT_BAUDRATE = 921_600
POLL_S = 0.0005
"""How often a port without a file descriptor (socket://, loop://) is polled for input."""
READER_WAIT_S = 0.05
"""The reader thread's longest wait for input on a port with a file descriptor: how fast close() is."""
READ_CHUNK = 65536
DRIFT_MIN_SPAN_S = 10.0
"""Clock estimates must span this much device time before a drift is fitted (50 µs over 10 s: 5 ppm)."""


class DaqConfigError(UserInputError):
    """The port does not open, or the board refuses a setting as a bad argument; names port and command."""


class DaqError(DeviceFaultError):
    """The DAQ board or its line failed while working; the message names the port and the command."""


class SerialPort(Protocol):
    """What the driver needs of a pyserial port (tests hand it a scripted one)."""

    timeout: float | None

    def read(self, size: int = 1) -> bytes: ...

    def write(self, data: bytes) -> int | None: ...

    def close(self) -> None: ...


@dataclass(frozen=True)
class Calibration:
    """The board's scale factors (`CAL?`)."""

    encoder_counts_per_rev: int
    cap_um_per_count: float
    lever_radius_m: float
    """The capacitive sensor reads the arc length at this radius on the output arm."""

    @property
    def rad_per_encoder_count(self) -> float:
        return 2 * math.pi / self.encoder_counts_per_rev

    @property
    def rad_per_cap_count(self) -> float:
        return self.cap_um_per_count * 1e-6 / self.lever_radius_m

    @classmethod
    def parse(cls, text: str) -> Calibration:
        """From `ENC_CPR=131072 CAP_UM=0.001 LEVER_M=0.1` (any order); ValueError if incomplete."""
        fields = dict(item.split("=", 1) for item in text.split())
        calibration = cls(int(fields["ENC_CPR"]), float(fields["CAP_UM"]), float(fields["LEVER_M"]))
        if calibration.encoder_counts_per_rev <= 0 or not (
            calibration.cap_um_per_count > 0 and calibration.lever_radius_m > 0
        ):
            raise ValueError("scale factors must be positive")
        return calibration


@dataclass(frozen=True)
class ClockEstimate:
    """One clock comparison: host clock minus device clock, from the quickest of n `TIME?` exchanges."""

    offset_s: float
    round_trip_s: float
    device_s: float
    """Device time of the comparison."""

    @property
    def uncertainty_s(self) -> float:
        """The true offset lies within ± this of `offset_s` (the reply was stamped inside the round trip)."""
        return self.round_trip_s / 2


class ClockModel:
    """Host − device clock offset as a function of device time: the latest estimate, plus a drift
    fitted once the estimates span DRIFT_MIN_SPAN_S."""

    def __init__(self, keep: int = 32) -> None:
        self.estimates: deque[ClockEstimate] = deque(maxlen=keep)
        self._drift: float | None = None  # fitted when an estimate comes, not at every read (1 kHz)

    def add(self, estimate: ClockEstimate) -> None:
        self.estimates.append(estimate)
        self._drift = None
        last = self.estimates[-1]
        if last.device_s - self.estimates[0].device_s >= DRIFT_MIN_SPAN_S:
            device = np.array([e.device_s for e in self.estimates])
            offset = np.array([e.offset_s for e in self.estimates])
            weight = 1.0 / np.maximum([e.uncertainty_s for e in self.estimates], 1e-6)
            self._drift = float(np.polyfit(device - last.device_s, offset, 1, w=weight)[0])

    def offset_s(self, t_device_s: ArrayLike) -> np.ndarray:
        t = np.asarray(t_device_s, dtype=np.float64)
        if not self.estimates:
            raise ValueError("no clock estimate yet: call estimate_clock_offset() first")
        last = self.estimates[-1]
        if self._drift is None:
            return np.full_like(t, last.offset_s)
        # Anchored at the latest estimate: the fit gives the slope, the newest comparison the level.
        return last.offset_s + self._drift * (t - last.device_s)


ANALOG_QUANTITIES: Final = ("tau_in", "tau_out", "temp_gear", "temp_motor")
"""What the analog inputs may measure: the run format's optional columns (docs/INTERFACE.md), SI."""


class AnalogChannel(BaseModel):
    """One analog input of the DAQ (a rig file's `daq.channels.<column>`): value = gain·reading + offset,
    valid within [min, max] (the sensor's range: a reading outside is recorded NaN and counted)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    adc: int = Field(ge=0, lt=ANALOG_CHANNELS, description="which ADC input of the board")
    gain: float = Field(description="SI units per ADC count: N·m or °C per count")
    offset: float = Field(default=0.0, description="the value at a reading of 0 [N·m or °C]")
    min: float = Field(description="lowest valid value, the sensor's range [N·m or °C]")
    max: float = Field(description="highest valid value [N·m or °C]")

    @model_validator(mode="after")
    def _sane(self) -> AnalogChannel:
        if self.gain == 0 or not math.isfinite(self.gain):
            raise ValueError("gain must be a finite nonzero number of units per count")
        if self.max <= self.min:
            raise ValueError("max must be above min")
        return self

    def value(self, reading: np.ndarray) -> np.ndarray:
        """SI values of raw readings, NaN outside the range."""
        value = self.gain * reading + self.offset
        return np.where((value >= self.min) & (value <= self.max), value, np.nan)

    def reading(self, value: float) -> float:
        """The raw reading a value gives (the board's side: the twin's)."""
        return (value - self.offset) / self.gain


@dataclass(frozen=True)
class SampleBlock:
    """Samples in order of device time; one entry per sample in every array."""

    t_device_s: np.ndarray
    t_host_s: np.ndarray
    """Device time + estimated offset: the host clock (`SerialDaq.clock`) at which it was sampled."""
    theta_m_rad: np.ndarray
    """Motor angle from the encoder, counted from ZERO, unwrapped past the i32 count range."""
    theta_l_rad: np.ndarray
    """Output angle from the capacitive sensor: reading × µm per count / lever radius."""
    seq: np.ndarray
    """Sequence number of the frame that carried the sample (u32)."""
    index: np.ndarray
    """Sample number since START, lost samples included: a jump by more than 1 marks a loss."""
    status: np.ndarray
    """Status bits (`drivers.daq_protocol.STATUS_*`)."""
    adc: np.ndarray | None = None
    """The analog inputs' raw readings, one row of ANALOG_CHANNELS per sample (after `set_analog(True)`);
    None when the frames carried none. What a reading means is the rig file's (`daq.channels`)."""

    def __len__(self) -> int:
        return int(self.t_device_s.shape[0])


class SerialDaq:
    """The DAQ board on a serial line."""

    def __init__(
        self,
        url: str,
        *,
        baudrate: int = DEFAULT_BAUDRATE,
        timeout_s: float = 1.0,
        clock: Callable[[], float] = time.monotonic,
        port: SerialPort | None = None,
    ) -> None:
        """Open `url` with `serial.serial_for_url`, or use `port` (already open; `url` then names it).

        `timeout_s` bounds the wait for each reply and for `read_*`; `clock` is the host clock that
        `t_host_s` refers to: give the one the servo driver stamps its samples with.
        """
        self.url = url
        self.timeout_s = timeout_s
        self.clock = clock
        if port is None:
            try:
                port = serial.serial_for_url(url, baudrate=baudrate, timeout=0)
            except (OSError, ValueError) as exc:
                raise DaqConfigError(f"DAQ on {url}: cannot open the port: {exc}") from None
        else:
            port.timeout = 0
        self._port = port
        self._fd = _fileno(port)
        self.decoder = FrameDecoder()
        self.clock_model = ClockModel()
        self.stale_replies = 0
        """Replies to earlier commands that arrived after their command timed out (ignored)."""
        self._calibration: Calibration | None = None
        self._encoder_raw: int | None = None  # last raw i32 count, for unwrapping
        self._encoder_count = 0  # its unwrapped value
        self._tag = 0
        self._command_lock = threading.RLock()  # one command (or clock comparison) at a time
        self._take_lock = threading.Lock()  # one taker of samples at a time
        # What the reader thread hands over, guarded by _decoded:
        self._decoded = threading.Condition()
        self._columns = _DecodedColumns()
        self._newest_t_device_s: float | None = None  # the newest sample's device time not yet taken
        self._pending_samples = 0
        self._replies: list[tuple[ReplyFrame, float]] = []  # with the host time of arrival
        self._failure: str | None = None
        self._closing = threading.Event()
        self._reader = threading.Thread(target=self._read_loop, name=f"serial-daq {url}", daemon=True)
        self._reader.start()

    # --- commands ---------------------------------------------------------------------------------------

    def identify(self) -> str:
        """`ID?`: e.g. `HDRIG-DAQ 1.0 SN0042`."""
        return self.command("ID?")

    def calibration(self) -> Calibration:
        """`CAL?`, asked once and kept."""
        if self._calibration is None:
            text = self.command("CAL?")
            try:
                self._calibration = Calibration.parse(text)
            except (KeyError, ValueError) as exc:
                raise DaqError(f"DAQ on {self.url}: 'CAL?' gave {text!r}: unreadable ({exc})") from None
        return self._calibration

    def set_rate(self, rate_hz: float, samples_per_frame: int | None = None) -> None:
        """`RATE` (samples/s; the period must be a whole number of µs) and, if given, `BLOCK`."""
        self.command(f"RATE {rate_hz:g}")
        if samples_per_frame is not None:
            self.command(f"BLOCK {samples_per_frame}")

    def set_analog(self, on: bool) -> None:
        """`ANALOG 1`: the samples carry the analog inputs too (`SampleBlock.adc`); `ANALOG 0`: not."""
        self.command(f"ANALOG {int(on)}")

    def zero_encoder(self) -> None:
        """`ZERO`: the encoder count is 0 at the present position."""
        self.command("ZERO")
        with self._decoded:
            self._encoder_raw = None

    def device_time_s(self) -> float:
        """`TIME?`: the board's clock [s]."""
        return self._device_time()[0]

    def estimate_clock_offset(self, n: int = 8) -> ClockEstimate:
        """Compare clocks n times; keep the quickest exchange (its midpoint is closest to the stamp).

        The reply's arrival is stamped by the reader thread as it decodes it. Also allowed while
        streaming (replies then queue behind data frames: more exchanges help).
        """
        best: ClockEstimate | None = None
        with self._command_lock:
            for _ in range(max(1, n)):
                t0 = self.clock()
                device_s, t1 = self._device_time()
                if best is None or t1 - t0 < best.round_trip_s:
                    best = ClockEstimate((t0 + t1) / 2 - device_s, t1 - t0, device_s)
        assert best is not None
        with self._decoded:
            self.clock_model.add(best)
        return best

    def host_time_s(self, t_device_s: ArrayLike) -> np.ndarray:
        """Device times [s] on the host clock, by the clock model."""
        t = np.asarray(t_device_s, dtype=np.float64)
        with self._decoded:
            return t + self.clock_model.offset_s(t)

    def start(self) -> None:
        """`START` streaming; estimates the clock offset first if it never was."""
        with self._command_lock:
            if not self.clock_model.estimates:
                self.estimate_clock_offset()
            self.calibration()
            with self._decoded:
                self.decoder.restart_sequence()
            self.command("START")

    def stop(self) -> DecoderStats:
        """`STOP`; counts the frames lost at the end of the stream. Returns the decoder's counts.

        Safe when not streaming. Frames decoded before the reply stay for `read_samples`.
        """
        text = self.command("STOP")
        try:
            frames_sent, samples_sent = (int(word) for word in text.split())
        except ValueError:
            raise DaqError(f"DAQ on {self.url}: 'STOP' gave {text!r}, not two counts") from None
        with self._decoded:
            self.decoder.account_tail(frames_sent, samples_sent)
            return replace(self.decoder.stats)

    @property
    def stats(self) -> DecoderStats:
        """Frames, samples, CRC errors, malformed blocks, discarded bytes, lost frames and samples."""
        with self._decoded:
            return replace(self.decoder.stats)

    def command(self, command: str) -> str:
        """Send one command line; return its reply after `OK`.

        DaqConfigError when the board refuses an argument (ERR 2); DaqError on another ERR or no reply.
        """
        return self._exchange(command)[0]

    # --- samples ------------------------------------------------------------------------------------------

    def read_samples(self, min_samples: int = 0, timeout_s: float | None = None) -> SampleBlock:
        """All samples decoded so far, waiting up to `timeout_s` (default: the reply timeout) for at
        least `min_samples`. DaqError if fewer arrive; those already decoded are kept for next time."""
        return self._read(lambda: self._pending_samples < min_samples, timeout_s, f"{min_samples} samples")

    def read_until(self, t_host_s: float, timeout_s: float | None = None) -> SampleBlock:
        """All samples decoded so far, waiting until one taken at or after host time `t_host_s` is in."""

        def short() -> bool:
            if self._newest_t_device_s is None:
                return True
            return float(self.host_time_s(self._newest_t_device_s)) < t_host_s

        return self._read(short, timeout_s, f"a sample at host time {t_host_s:.6f} s")

    def close(self) -> None:
        """Stop the reader thread and close the port."""
        if not self._closing.is_set():
            self._closing.set()
            self._reader.join()
            self._port.close()

    def __enter__(self) -> SerialDaq:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- the caller's side ------------------------------------------------------------------------------

    def _device_time(self) -> tuple[float, float]:
        text, arrival_s = self._exchange("TIME?")
        try:
            return int(text) * 1e-6, arrival_s
        except ValueError:
            raise DaqError(f"DAQ on {self.url}: 'TIME?' gave {text!r}, not a count of µs") from None

    def _exchange(self, command: str) -> tuple[str, float]:
        """The reply's text after OK, and the host time it arrived."""
        with self._command_lock:
            self._tag = self._tag % MAX_TAG + 1
            tag = self._tag
            try:
                self._port.write(command_line(tag, command))
            except (OSError, ValueError) as exc:  # SerialException is an OSError; a closed port a ValueError
                raise DaqError(f"DAQ on {self.url}: {command!r} not sent: {exc}") from None
            with self._decoded:
                found: list[tuple[ReplyFrame, float]] = []

                def replied() -> bool:
                    for item in self._replies:
                        if item[0].tag == tag and not found:
                            found.append(item)
                        else:
                            self.stale_replies += 1
                    self._replies.clear()
                    return bool(found) or self._failure is not None

                if not self._decoded.wait_for(replied, self.timeout_s):
                    raise DaqError(f"DAQ on {self.url}: no reply to {command!r} within {self.timeout_s:g} s")
                if not found:
                    raise DaqError(f"DAQ on {self.url}: {command!r} unanswered: {self._failure}")
        reply, arrival_s = found[0]
        word, _, rest = reply.text.partition(" ")
        if word == "OK":
            return rest, arrival_s
        if word == "ERR":
            refused = DaqConfigError if rest.split(" ", 1)[0] == str(ERR_BAD_ARGUMENT) else DaqError
            raise refused(f"DAQ on {self.url}: {command!r} refused: {reply.text}")
        raise DaqError(f"DAQ on {self.url}: {command!r} got {reply.text!r}, neither OK nor ERR")

    def _read(self, short: Callable[[], bool], timeout_s: float | None, what: str) -> SampleBlock:
        timeout = self.timeout_s if timeout_s is None else timeout_s
        with self._take_lock:
            return self._block(self._wait_samples(short, timeout, what))

    def _wait_samples(self, short: Callable[[], bool], timeout: float, what: str) -> _Taken:
        with self._decoded:
            if not self._decoded.wait_for(lambda: not short() or self._failure is not None, timeout):
                stats = self.decoder.stats
                raise DaqError(
                    f"DAQ on {self.url}: no {what} within {timeout:g} s ({self._pending_samples} in,"
                    f" {stats.frames} frames so far, {stats.lost_frames} lost): is it streaming?"
                )
            if short():
                raise DaqError(f"DAQ on {self.url}: no {what}: {self._failure}")
            taken = self._columns.take()
            self._pending_samples = 0
            self._newest_t_device_s = None
            return taken

    def _block(self, taken: _Taken) -> SampleBlock:
        """The samples taken, scaled; in device-time order (a late frame, read after its successors, goes
        back to its place). The reader thread decoded them as they came: what is left is array-wide."""
        t_device_s, counts, cap, status, seq, index, adc = taken
        if len(index) > 1 and np.any(index[1:] < index[:-1]):
            order = np.argsort(index, kind="stable")
            t_device_s, counts, cap, status, seq, index = (
                a[order] for a in (t_device_s, counts, cap, status, seq, index)
            )
            adc = adc[order] if adc is not None else None
        calibration = self.calibration() if len(index) else None
        return SampleBlock(
            t_device_s=t_device_s,
            t_host_s=self.host_time_s(t_device_s),
            theta_m_rad=counts * calibration.rad_per_encoder_count if calibration else counts.astype(float),
            theta_l_rad=cap * calibration.rad_per_cap_count if calibration else cap.astype(float),
            seq=seq,
            index=index,
            status=status,
            adc=adc,
        )

    def _unwrap_encoder(self, raw: list[int]) -> list[int]:
        """The frame's encoder counts, unwrapped past the i32 range (the count wraps every 16384 turns at
        17 bits; between two samples the motor turns far less). In the order frames arrive: a late frame
        is still within a few frames' motion of the one before it."""
        previous_raw = self._encoder_raw if self._encoder_raw is not None else raw[0]
        count = self._encoder_count if self._encoder_raw is not None else raw[0]
        counts = []
        for value in raw:
            count += (value - previous_raw + 2**31) % 2**32 - 2**31
            previous_raw = value
            counts.append(count)
        self._encoder_raw, self._encoder_count = previous_raw, count
        return counts

    # --- the reader thread ------------------------------------------------------------------------------

    def _read_loop(self) -> None:
        while not self._closing.is_set():
            try:
                data = bytes(self._port.read(READ_CHUNK))
            except (OSError, ValueError) as exc:
                with self._decoded:
                    self._failure = f"read failed: {exc}"
                    self._decoded.notify_all()
                return
            if not data:
                if self._fd is not None:
                    select.select([self._fd], [], [], READER_WAIT_S)
                else:
                    time.sleep(POLL_S)
                continue
            arrival_s = self.clock()
            with self._decoded:
                for frame in self.decoder.feed(data):
                    if isinstance(frame, DataFrame):
                        self._add_frame(frame)
                    else:
                        self._replies.append((frame, arrival_s))
                self._decoded.notify_all()

    def _add_frame(self, frame: DataFrame) -> None:
        """Decode a data frame as it arrives, in this thread: a taker (the 1 kHz loop, at a chunk's end)
        finds arrays to slice, not frames to decode (figures: docs/BENCHMARKS.md, issue 26)."""
        n = len(frame.samples)
        self._columns.add(frame, self._unwrap_encoder(frame.samples["encoder"].tolist()))
        self._pending_samples += n
        t_last_s = (frame.t0_us + (n - 1) * frame.period_us) * 1e-6
        if self._newest_t_device_s is None or t_last_s > self._newest_t_device_s:
            self._newest_t_device_s = t_last_s


_Taken = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]
"""Device time [s], unwrapped encoder counts, capacitive counts, status, seq, index, ADC readings."""


class _DecodedColumns:
    """The samples the reader thread has decoded and no one has taken yet, one array per quantity, in the
    order they arrived; grown by doubling, emptied by `take`."""

    def __init__(self, capacity: int = 1024) -> None:
        self.count = 0
        self._allocate(capacity)

    def _allocate(self, capacity: int) -> None:
        self.t_device_s = np.empty(capacity)
        self.counts = np.empty(capacity, np.int64)
        self.cap = np.empty(capacity, np.int32)
        self.status = np.empty(capacity, np.uint8)
        self.seq = np.empty(capacity, np.uint32)
        self.index = np.empty(capacity, np.int64)
        self.adc = np.empty((capacity, ANALOG_CHANNELS), np.int32)
        self.analog = np.empty(capacity, bool)

    _NAMES = ("t_device_s", "counts", "cap", "status", "seq", "index", "adc", "analog")

    def _grow(self, needed: int) -> None:
        old = {name: getattr(self, name) for name in self._NAMES}
        capacity = len(self.index)
        while capacity < needed:
            capacity *= 2
        self._allocate(capacity)
        for name in self._NAMES:
            getattr(self, name)[: self.count] = old[name][: self.count]

    def add(self, frame: DataFrame, counts: list[int]) -> None:
        samples, n, i = frame.samples, len(frame.samples), self.count
        if i + n > len(self.index):
            self._grow(i + n)
        end = i + n
        self.t_device_s[i:end] = [(frame.t0_us + j * frame.period_us) * 1e-6 for j in range(n)]
        self.counts[i:end] = counts
        self.cap[i:end] = samples["cap"]
        self.status[i:end] = samples["status"]
        self.seq[i:end] = frame.seq
        self.index[i:end] = range(frame.first_index, frame.first_index + n)
        analog = samples.dtype == ANALOG_SAMPLE_DTYPE
        if analog:
            self.adc[i:end] = samples["adc"]
        self.analog[i:end] = analog
        self.count = end

    def take(self) -> _Taken:
        """Copies of what was added since the last take; the ADC readings (as floats) only where every
        sample has them (a stream switched between reads: the readings common to both)."""
        n, self.count = self.count, 0
        adc = self.adc[:n].astype(np.float64) if n and self.analog[:n].all() else None
        return (
            self.t_device_s[:n].copy(),
            self.counts[:n].copy(),
            self.cap[:n].copy(),
            self.status[:n].copy(),
            self.seq[:n].copy(),
            self.index[:n].copy(),
            adc,
        )


def _fileno(port: SerialPort) -> int | None:
    """The port's file descriptor, to wait on with select; None for socket://, loop:// and doubles."""
    try:
        return int(port.fileno())  # type: ignore[attr-defined]
    except (AttributeError, OSError, ValueError):
        return None
