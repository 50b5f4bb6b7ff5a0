"""The DAQ board's twin: the device end of docs/DAQ_PROTOCOL.md, on a pty or a loopback TCP socket.

It measures a *source* — the true (θ_m, θ_l) at device times, e.g. the plant that the CANopen twin
runs — through the board's sensors: the encoder quantizes θ_m to whole counts, the capacitive sensor
adds seeded Gaussian noise to θ_l and quantizes the arc at its lever to whole counts. The host opens
`twin.url` with `drivers.serial_daq.SerialDaq` exactly as it would open the board.

One thread runs the device: it parses command lines, answers each with a reply frame, and while
streaming sends a data frame as soon as its last sample is due on the device clock. Like the board,
it keeps a bounded FIFO: when the host does not read, whole data frames are dropped (their sequence
numbers are used up, the next frame carries STATUS_OVERRUN); replies are never dropped.
"""

from __future__ import annotations

import bisect
import math
import os
import queue
import select
import socket
import struct
import threading
import time
from collections.abc import Callable, Mapping
from typing import Final, Literal, Protocol, TypeVar

import numpy as np

from drivers.daq_protocol import (
    ANALOG_CHANNELS,
    ERR_BAD_ARGUMENT,
    ERR_BAD_LINE,
    ERR_STREAMING,
    ERR_UNKNOWN_COMMAND,
    MAX_LINE_BYTES,
    STATUS_CAP_RANGE,
    STATUS_OVERRUN,
    cobs_decode,
    cobs_encode,
    encode_packed_frame,
    encode_reply_frame,
    split_tag,
)
from drivers.serial_daq import AnalogChannel
from model.plant import Plant
from model.registry import X
from rig.config import Sensors

Source = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
"""True (θ_m, θ_l) [rad] at an array of device times [s] (one frame's samples at a time)."""

AnalogSource = Callable[[list[float]], list[list[float]]]
"""The analog inputs' raw readings (ANALOG_CHANNELS each) at a list of device times [s]."""

IDEAL_ENCODER_COUNTS_PER_REV = 2**24
"""What `from_sensors` gives a board whose rig file says 0 (ideal): a board has whole counts."""
MAX_SAMPLES_PER_FRAME = 100
MIN_PERIOD_US, MAX_PERIOD_US = 50, 1_000_000  # 20 kHz .. 1 Hz
POLL_S = 0.02  # the device thread's longest sleep: how fast close() is noticed
_I32 = 2**31
_Times = TypeVar("_Times", float, np.ndarray)
_SAMPLE = struct.Struct("<iiB")  # SAMPLE_DTYPE's bytes: encoder, cap, status
_ANALOG_SAMPLE = struct.Struct(f"<iiB{ANALOG_CHANNELS}i")  # ANALOG_SAMPLE_DTYPE's
TRUTHS: Final = ("tau_in", "tau_out", "temp_gear", "temp_motor")
"""What a `PlantStateSource` keeps beside the angles, for the analog inputs (the run format's columns)."""


def _yield_to_the_loop() -> None:
    """In a real-time process (`rig.realtime.realtime_scheduling`: SCHED_FIFO, inherited by every thread),
    put the calling thread one priority below the others. On a bench the DAQ board is a machine of its
    own; here, at the same priority on the one CPU, its thread, woken first, ran its frame (with the
    socket write) before the drive twin's answer to a SYNC or the host's handling of it."""
    if not hasattr(os, "sched_getscheduler") or os.sched_getscheduler(0) != os.SCHED_FIFO:
        return
    priority = os.sched_getparam(0).sched_priority
    if priority > 1:  # lowering one's own priority needs no permission
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority - 1))


class PlantStateSource:
    """The state of a plant stepped by someone else (the CANopen twin), as it was at given host times.

    The stepper calls `record(t_host_s)` after each step (t: when the step's SYNC was taken); a sample
    gets the state last recorded at or before its time, or the present state before any record. The
    DAQ twin's thread can fall behind its sample clock on a loaded machine (stalled for many periods
    with both cores busy; figures: docs/BENCHMARKS.md) and then sends every due frame at once; each
    still carries the state of its own time, as a board sampling in hardware does. Reading the present
    state instead would date it back to the stalled samples' times, an alignment error the host's
    drivers did not make. The DAQ twin asks at host times (`source_clock="host"`).
    """

    HISTORY: Final = 1024
    """States kept: about a second of SYNCs at 1 kHz, longer than any stall measured."""

    def __init__(self, plant: Plant) -> None:
        self.plant = plant
        self._lock = threading.Lock()
        # A ring of plain floats: the twin records one state per SYNC and a frame asks for a handful, for
        # which list stores and bisect cost less than numpy's per-call overhead.
        self._t_s = [-math.inf] * self.HISTORY
        self._theta_m = [0.0] * self.HISTORY
        self._theta_l = [0.0] * self.HISTORY
        self._truths: list[tuple[float, ...]] = [(math.nan,) * len(TRUTHS)] * self.HISTORY
        self._count = 0

    def record(self, t_host_s: float, truths: tuple[float, ...] | None = None) -> None:
        """Keep the plant's present state as its state from `t_host_s` on (times never go back), with
        the stepper's `truths` (TRUTHS' quantities, SI) for the analog inputs."""
        x = self.plant.x
        theta_m, theta_l = float(x[X.THETA_M]), float(x[X.THETA_L])
        with self._lock:
            i = self._count % self.HISTORY
            self._t_s[i], self._theta_m[i], self._theta_l[i] = t_host_s, theta_m, theta_l
            if truths is not None:
                self._truths[i] = truths
            self._count += 1

    def truths(self, t_s: list[float]) -> list[tuple[float, ...]]:
        """The TRUTHS recorded at or before each time (NaN before any record)."""
        with self._lock:
            if not self._count:
                return [(math.nan,) * len(TRUTHS)] * len(t_s)
            return [self._truths[self._slot(t)] for t in t_s]

    def __call__(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        times = t_s.tolist()
        with self._lock:
            if not self._count:
                x = self.plant.x
                return np.full(t_s.shape, x[X.THETA_M]), np.full(t_s.shape, x[X.THETA_L])
            slots = [self._slot(t) for t in times]
            theta_m = [self._theta_m[i] for i in slots]
            theta_l = [self._theta_l[i] for i in slots]
        return np.array(theta_m).reshape(t_s.shape), np.array(theta_l).reshape(t_s.shape)

    def at(self, t_s: list[float]) -> tuple[list[float], list[float]]:
        """`self(t_s)` for a list of times, as lists: no arrays for a frame's few samples."""
        with self._lock:
            if not self._count:
                x = self.plant.x
                return [float(x[X.THETA_M])] * len(t_s), [float(x[X.THETA_L])] * len(t_s)
            slots = [self._slot(t) for t in t_s]
            return [self._theta_m[i] for i in slots], [self._theta_l[i] for i in slots]

    def _slot(self, t_s: float) -> int:
        """The ring slot of the last state recorded at or before `t_s`; before the oldest state kept, the
        oldest (a stall longer than the history). The ring holds times in order from slot `oldest` on,
        wrapping round to slot 0: two sorted runs, each searched by bisection."""
        count, times = self._count, self._t_s
        if count <= self.HISTORY:  # not yet wrapped: slots 0 .. count-1, oldest first
            return max(bisect.bisect_right(times, t_s, 0, count) - 1, 0)
        oldest = count % self.HISTORY
        if oldest and t_s >= times[0]:  # in the newer run, slots 0 .. oldest-1
            return bisect.bisect_right(times, t_s, 0, oldest) - 1
        return max(bisect.bisect_right(times, t_s, oldest, self.HISTORY) - 1, oldest)


class _RefusedError(Exception):
    def __init__(self, code: int, text: str) -> None:
        super().__init__(text)
        self.code = code


class _Line(Protocol):
    url: str

    def read_fds(self) -> list[int]: ...

    def write_fd(self) -> int | None: ...

    def receive(self, fd: int) -> bytes: ...

    def send(self, data: bytes) -> int: ...

    def close(self) -> None: ...


class _PtyLine:
    """A pseudo-terminal: the twin holds the master, the host opens the slave's path."""

    def __init__(self) -> None:
        import tty  # POSIX only, like os.openpty

        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)  # no echo, no line discipline, before the host opens it
        os.set_blocking(self.master, False)
        self.url = os.ttyname(self.slave)

    def read_fds(self) -> list[int]:
        return [self.master]

    def write_fd(self) -> int | None:
        return self.master

    def receive(self, fd: int) -> bytes:
        try:
            return os.read(self.master, 4096)
        except (BlockingIOError, InterruptedError):
            return b""

    def send(self, data: bytes) -> int:
        try:
            return os.write(self.master, data)
        except (BlockingIOError, InterruptedError):
            return 0

    def close(self) -> None:
        os.close(self.master)
        os.close(self.slave)


class _SocketLine:
    """A TCP server on 127.0.0.1 (only): one host at a time, through pyserial's socket:// handler."""

    def __init__(self) -> None:
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.listener.setblocking(False)
        self.url = f"socket://127.0.0.1:{self.listener.getsockname()[1]}"
        self.conn: socket.socket | None = None

    def read_fds(self) -> list[int]:
        fds = [self.listener.fileno()]
        return [*fds, self.conn.fileno()] if self.conn is not None else fds

    def write_fd(self) -> int | None:
        return self.conn.fileno() if self.conn is not None else None

    def receive(self, fd: int) -> bytes:
        if fd == self.listener.fileno():
            try:
                conn, _ = self.listener.accept()
            except BlockingIOError:
                return b""
            self._drop()
            conn.setblocking(False)
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self.conn = conn
            return b""
        assert self.conn is not None
        try:
            data = self.conn.recv(4096)
        except BlockingIOError:
            return b""
        except OSError:
            data = b""
        if not data:  # the host closed: wait for the next one
            self._drop()
        return data

    def send(self, data: bytes) -> int:
        if self.conn is None:
            return len(data)  # nobody on the line: the bytes go nowhere, as on an unplugged UART
        try:
            return self.conn.send(data)
        except BlockingIOError:
            return 0
        except OSError:
            self._drop()
            return len(data)

    def _drop(self) -> None:
        if self.conn is not None:
            self.conn.close()
            self.conn = None

    def close(self) -> None:
        self._drop()
        self.listener.close()


class DaqTwin:
    """The DAQ board, simulated: serves the protocol on `url` from a thread until `close()`."""

    def __init__(
        self,
        source: Source,
        *,
        transport: Literal["pty", "socket"] = "pty",
        encoder_counts_per_rev: int = 131072,
        load_noise_rad: float = 0.0,
        cap_um_per_count: float = 0.001,
        lever_radius_m: float = 0.1,
        seed: int = 0,
        clock_offset_s: float | None = None,
        drift_ppm: float = 0.0,
        serial_number: str = "SIM0001",
        fifo_bytes: int = 65536,
        clock: Callable[[], float] = time.monotonic,
        source_clock: Literal["device", "host"] = "device",
        analog: AnalogSource | None = None,
    ) -> None:
        """`clock_offset_s`: device clock minus `clock` (None: the device clock starts at 0 now, as a
        board's does at power-up); `drift_ppm`: how much faster the device clock runs; `source_clock`:
        the times `source` is asked at, the device's or `clock`'s (a `PlantStateSource`'s)."""
        self.source = source
        self.analog_source = analog
        """The analog inputs' readings; None: the board reads 0 on each."""
        self.analog = False
        """`ANALOG 1` was given: frames carry the analog inputs."""
        self._source_clock = source_clock
        self.encoder_counts_per_rev = encoder_counts_per_rev
        self.load_noise_rad = load_noise_rad
        self.cap_um_per_count = cap_um_per_count
        self.lever_radius_m = lever_radius_m
        self.serial_number = serial_number
        self.fifo_bytes = fifo_bytes
        self._rng = np.random.default_rng(seed)
        self._clock = clock
        self._host0_s = clock()
        self._device0_s = 0.0 if clock_offset_s is None else self._host0_s + clock_offset_s
        self._rate_factor = 1.0 + drift_ppm * 1e-6

        self.period_us = 1000
        self.samples_per_frame = 10
        self.streaming = False
        self._seq = 0
        self._first_us = 0
        self._overrun = False
        self._zero_counts = 0
        self._inbuf = bytearray()
        self._skipping_line = False
        self._outbuf = bytearray()
        self._line_events: queue.SimpleQueue[bytes | None] = queue.SimpleQueue()
        self._faults: queue.SimpleQueue[Literal["repeat", "swap"]] = queue.SimpleQueue()
        self._held: bytes | None = None  # a frame swapped behind the next one
        self._commands: dict[str, Callable[[list[str]], str]] = {
            "ID?": self._id,
            "RATE": self._rate,
            "RATE?": lambda args: f"{1e6 / self.period_us:g}",
            "BLOCK": self._block,
            "BLOCK?": lambda args: str(self.samples_per_frame),
            "START": self._start,
            "STOP": self._stop,
            "TIME?": lambda args: str(self.device_us()),
            "ZERO": self._zero,
            "CAL?": self._cal,
            "ANALOG": self._analog,
        }

        self._line: _Line = _PtyLine() if transport == "pty" else _SocketLine()
        self.url = self._line.url
        self.error: BaseException | None = None
        self._closing = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"daq-twin {self.url}", daemon=True)
        self._thread.start()

    @classmethod
    def from_sensors(cls, source: Source, sensors: Sensors, **kwargs: object) -> DaqTwin:
        """A twin with a rig file's encoder resolution, output-angle noise and seed."""
        counts = sensors.encoder_counts_per_rev or IDEAL_ENCODER_COUNTS_PER_REV
        return cls(
            source,
            encoder_counts_per_rev=counts,
            load_noise_rad=sensors.load_sensor_noise_rad,
            seed=sensors.seed,
            **kwargs,  # type: ignore[arg-type]
        )

    def device_us(self) -> int:
        """The device clock [µs]."""
        return math.floor((self._device0_s + (self._clock() - self._host0_s) * self._rate_factor) * 1e6)

    def host_time_s(self, t_device_s: _Times) -> _Times:
        """Device times [s] on `clock` (the inverse of `device_us`)."""
        return self._host0_s + (t_device_s - self._device0_s) / self._rate_factor

    def inject_garbage(self, data: bytes) -> None:
        """Put `data` on the line just before the next data frame (tests: line noise)."""
        self._line_events.put(bytes(data))

    def corrupt_next_frame(self) -> None:
        """Flip a payload byte of the next data frame after its CRC is computed (tests: a CRC error)."""
        self._line_events.put(None)

    def repeat_next_frame(self) -> None:
        """Send the next data frame twice in a row (tests: a repeated frame)."""
        self._faults.put("repeat")

    def swap_next_frames(self) -> None:
        """Send the next data frame after the one following it (tests: frames out of order)."""
        self._faults.put("swap")

    def close(self) -> None:
        """Stop the device thread and free the pty or socket; re-raise what ended the thread, if anything."""
        if not self._closing.is_set():
            self._closing.set()
            self._thread.join()
            self._line.close()
        if self.error is not None:
            raise RuntimeError(f"DAQ twin on {self.url} failed") from self.error

    def __enter__(self) -> DaqTwin:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- the device thread --------------------------------------------------------------------------------

    def _run(self) -> None:
        try:
            _yield_to_the_loop()
            while not self._closing.is_set():
                wait = POLL_S
                if self.streaming:
                    wait = min(wait, max(0.0, (self._due_us(self._seq) - self.device_us()) * 1e-6))
                write_fd = self._line.write_fd()
                wants_write = [write_fd] if self._outbuf and write_fd is not None else []
                readable, _, _ = select.select(self._line.read_fds(), wants_write, [], wait)
                for fd in readable:
                    self._on_input(self._line.receive(fd))
                self._emit_due_frames()
                self._flush()
        except BaseException as exc:  # kept for close() to raise in the owner's thread
            self.error = exc

    def _flush(self) -> None:
        while self._outbuf:
            sent = self._line.send(bytes(self._outbuf[:65536]))
            if sent == 0:
                return
            del self._outbuf[:sent]

    def _on_input(self, data: bytes) -> None:
        self._inbuf += data
        while (end := self._inbuf.find(b"\n")) >= 0:
            line = bytes(self._inbuf[:end])
            del self._inbuf[: end + 1]
            if self._skipping_line:  # the end of a line already refused as too long
                self._skipping_line = False
                continue
            self._emit_due_frames()  # replies come after every sample already due: the order of events
            self._outbuf += self._execute(line)
        if len(self._inbuf) >= MAX_LINE_BYTES:  # no end of line within the limit: refuse it now
            self._inbuf.clear()
            self._skipping_line = True
            self._outbuf += self._too_long()

    @staticmethod
    def _too_long() -> bytes:
        return encode_reply_frame(0, f"ERR {ERR_BAD_LINE} line longer than {MAX_LINE_BYTES} bytes")

    def _execute(self, line: bytes) -> bytes:
        if len(line) + 1 > MAX_LINE_BYTES:
            return self._too_long()
        try:
            text = line.rstrip(b"\r").decode("ascii")
        except UnicodeDecodeError:
            return encode_reply_frame(0, f"ERR {ERR_BAD_LINE} not ASCII")
        try:
            tag, text = split_tag(text)
        except ValueError:
            return encode_reply_frame(0, f"ERR {ERR_BAD_LINE} bad tag in {text[:20]!r}")
        word, *args = text.split() or [""]
        handler = self._commands.get(word.upper())
        if handler is None:
            return encode_reply_frame(tag, f"ERR {ERR_UNKNOWN_COMMAND} unknown command {word!r}")
        try:
            answer = handler(args)
        except _RefusedError as refusal:
            return encode_reply_frame(tag, f"ERR {refusal.code} {refusal}")
        return encode_reply_frame(tag, f"OK {answer}" if answer else "OK")

    # --- commands ------------------------------------------------------------------------------------------

    def _id(self, args: list[str]) -> str:
        return f"HDRIG-DAQ 1.0 {self.serial_number}"

    def _cal(self, args: list[str]) -> str:
        return (
            f"ENC_CPR={self.encoder_counts_per_rev} CAP_UM={self.cap_um_per_count:g}"
            f" LEVER_M={self.lever_radius_m:g}"
        )

    def _not_streaming(self) -> None:
        if self.streaming:
            raise _RefusedError(ERR_STREAMING, "not allowed while streaming: STOP first")

    @staticmethod
    def _number(args: list[str], what: str) -> float:
        try:
            (text,) = args
            value = float(text)
        except ValueError:
            raise _RefusedError(ERR_BAD_ARGUMENT, f"expected one number: {what}") from None
        if not math.isfinite(value):
            raise _RefusedError(ERR_BAD_ARGUMENT, f"expected a finite number: {what}")
        return value

    def _rate(self, args: list[str]) -> str:
        self._not_streaming()
        rate_hz = self._number(args, "samples per second")
        period = 1e6 / rate_hz if rate_hz > 0 else math.inf
        if not (MIN_PERIOD_US <= period <= MAX_PERIOD_US and abs(period - round(period)) < 1e-6):
            raise _RefusedError(
                ERR_BAD_ARGUMENT,
                f"rate {rate_hz:g} Hz: must be 1..20000 Hz with a whole number of us per sample",
            )
        self.period_us = round(period)
        return ""

    def _block(self, args: list[str]) -> str:
        self._not_streaming()
        n = self._number(args, "samples per frame")
        if n != int(n) or not 1 <= n <= MAX_SAMPLES_PER_FRAME:
            raise _RefusedError(
                ERR_BAD_ARGUMENT, f"{n:g} samples per frame: must be 1..{MAX_SAMPLES_PER_FRAME}"
            )
        self.samples_per_frame = int(n)
        return ""

    def _start(self, args: list[str]) -> str:
        if self.streaming:
            raise _RefusedError(ERR_STREAMING, "already streaming")
        self._seq = 0
        self._overrun = False
        self._first_us = self.device_us() + self.period_us
        self.streaming = True
        return ""

    def _stop(self, args: list[str]) -> str:
        if not self.streaming:
            return "0 0"
        self.streaming = False
        return f"{self._seq} {self._seq * self.samples_per_frame}"

    def _analog(self, args: list[str]) -> str:
        self._not_streaming()
        if args not in (["0"], ["1"]):
            raise _RefusedError(ERR_BAD_ARGUMENT, "ANALOG takes 0 or 1")
        self.analog = args == ["1"]
        return ""

    def _zero(self, args: list[str]) -> str:
        self._not_streaming()
        theta_m, _ = self._source_at([self.device_us() * 1e-6])
        self._zero_counts = self._raw_counts(theta_m[0])
        return ""

    # --- sampling ------------------------------------------------------------------------------------------

    def _source_at(self, t_device_s: list[float]) -> tuple[list[float], list[float]]:
        """The source's (θ_m, θ_l) at device times, as plain floats (a frame's few samples cost less so)."""
        return self._source_at_own(self._source_times(t_device_s))

    def _source_times(self, t_device_s: list[float]) -> list[float]:
        """Device times on the clock the source is asked at."""
        if self._source_clock == "device":
            return t_device_s
        host0, device0, rate = self._host0_s, self._device0_s, self._rate_factor
        return [host0 + (t - device0) / rate for t in t_device_s]  # host_time_s, unrolled

    def _source_at_own(self, times: list[float]) -> tuple[list[float], list[float]]:
        """The source's (θ_m, θ_l) at times on its own clock."""
        if isinstance(self.source, PlantStateSource):
            return self.source.at(times)
        theta_m, theta_l = self.source(np.array(times))
        return np.asarray(theta_m).tolist(), np.asarray(theta_l).tolist()

    def _due_us(self, seq: int) -> int:
        return self._first_us + ((seq + 1) * self.samples_per_frame - 1) * self.period_us

    def _emit_due_frames(self) -> None:
        if not self.streaming:
            return
        now_us = self.device_us()
        while self._due_us(self._seq) <= now_us:
            if len(self._outbuf) > self.fifo_bytes:
                self._overrun = True  # the FIFO is full: this frame is lost, its number used up
            else:
                self._outbuf += self._misordered(self._frame(self._seq))
            self._seq += 1

    def _misordered(self, frame: bytes) -> bytes:
        """The frame as the fault asked of it (repeated, held back behind the next one), else as is."""
        if self._held is not None:
            frame, self._held = frame + self._held, None
        elif not self._faults.empty():
            fault = self._faults.get()
            if fault == "repeat":
                frame += frame
            else:
                frame, self._held = b"", frame
        return frame

    def _raw_counts(self, theta_m_rad: float) -> int:
        if not math.isfinite(theta_m_rad):
            raise ValueError(f"DAQ twin: the source's θ_m is {theta_m_rad}: no encoder count for it")
        return math.floor(theta_m_rad * (self.encoder_counts_per_rev / (2 * math.pi)) + 0.5)

    def _frame(self, seq: int) -> bytes:
        # Plain float math per sample: for a frame of a few samples numpy's per-call overhead was most of
        # the cost, paid on the CPU that the 1 kHz loop waits for.
        n, period = self.samples_per_frame, self.period_us
        t0_us = self._first_us + seq * n * period
        times = self._source_times([(t0_us + j * period) * 1e-6 for j in range(n)])
        theta_m, theta_l = self._source_at_own(times)
        adc: list[list[int]] | None = None
        if self.analog:
            readings = self.analog_source(times) if self.analog_source is not None else None
            adc = [
                [_adc_count(r) for r in readings[j]] if readings is not None else [0] * ANALOG_CHANNELS
                for j in range(n)
            ]
        noise = self._rng.standard_normal(n).tolist()
        cap_per_rad = self.lever_radius_m * 1e6 / self.cap_um_per_count
        counts_per_rad = self.encoder_counts_per_rev / (2 * math.pi)
        load_noise, zero = self.load_noise_rad, self._zero_counts
        packed = bytearray()
        for j in range(n):
            if not math.isfinite(theta_m[j]):
                raise ValueError(f"DAQ twin: the source's θ_m is {theta_m[j]}: no encoder count for it")
            counts = math.floor(theta_m[j] * counts_per_rad + 0.5) - zero  # _raw_counts, unrolled
            cap = (theta_l[j] + load_noise * noise[j]) * cap_per_rad
            if math.isnan(cap):
                raise ValueError(f"DAQ twin: the source's θ_l is {theta_l[j]}: no capacitive reading for it")
            cap = round(cap) if math.isfinite(cap) else cap  # to nearest, ties to even (as np.rint)
            status = STATUS_CAP_RANGE if abs(cap) >= _I32 else 0
            if self._overrun and j == 0:
                status |= STATUS_OVERRUN
            encoder = (counts + _I32) % (2 * _I32) - _I32  # the board's i32 counter wraps
            cap_count = int(min(max(cap, -_I32), _I32 - 1))
            if adc is None:
                packed += _SAMPLE.pack(encoder, cap_count, status)
            else:
                packed += _ANALOG_SAMPLE.pack(encoder, cap_count, status, *adc[j])
        self._overrun = False
        frame = encode_packed_frame(seq, t0_us, period, n, bytes(packed))
        while not self._line_events.empty():
            event = self._line_events.get()
            if event is None:
                raw = bytearray(cobs_decode(frame[:-1]))
                raw[-5] ^= 0xFF  # the last sample's status byte: the CRC no longer matches
                frame = cobs_encode(bytes(raw)) + b"\x00"
            else:
                self._outbuf += event
        return frame


def _adc_count(reading: float) -> int:
    """A reading as the board's i32 converter gives it: to the nearest count, clipped (NaN: the
    lowest count, as an open input reads)."""
    try:
        count = round(reading)  # to nearest, ties to even
    except (ValueError, OverflowError):  # NaN, ±inf
        return _I32 - 1 if reading > 0 else -_I32
    return -_I32 if count < -_I32 else (_I32 - 1 if count >= _I32 else count)


def analog_readings(source: PlantStateSource, channels: Mapping[str, AnalogChannel]) -> AnalogSource:
    """The board's analog inputs measuring `source`'s truths as the rig file's `daq.channels` say
    (each channel's reading of its quantity; unused inputs read 0)."""
    # (input, quantity, offset, gain) of each channel: `AnalogChannel.reading`'s arithmetic, unrolled
    wired = [(c.adc, TRUTHS.index(name), c.offset, c.gain) for name, c in channels.items()]

    def read(t_s: list[float]) -> list[list[float]]:
        rows = []
        for truths in source.truths(t_s):
            row = [0.0] * ANALOG_CHANNELS
            for adc, k, offset, gain in wired:
                row[adc] = (truths[k] - offset) / gain
            rows.append(row)
        return rows

    return read
