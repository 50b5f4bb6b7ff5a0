"""The CAN bus under the CANopen driver: which interface, opening it, and recording its raw traffic.

python-can picks the interface by name (`socketcan`, `pcan`, `kvaser`, `virtual`...), so the bus is a
setting, never code. Tests take a bus of their own from `hdrig_testing.can_bus`.

A bus that will not open, or a raw log that cannot be written, is the user's to fix (`CanBusError`, a
`UserInputError`); a bus that fails under a working drive is the servo driver's device fault.
"""

from __future__ import annotations

import copy
import logging
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import cast

import can
import canopen
from canopen.network import PeriodicMessageTask
from pydantic import BaseModel, ConfigDict, Field

from model.errors import UserInputError

logger = logging.getLogger(__name__)

LOG_SUFFIXES = (".blf", ".asc")


class CanBusError(UserInputError):
    """The bus cannot be opened or its traffic cannot be recorded; one line naming what."""


class BusSettings(BaseModel):
    """Which CAN interface and channel, at what bit rate (a rig config's `canopen:` bus fields)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    interface: str = Field(default="socketcan", description="python-can interface name: socketcan, pcan...")
    channel: str = Field(default="can0", description="interface channel: can0, PCAN_USBBUS1, 0, a name...")
    bitrate: int = Field(default=1_000_000, gt=0, le=1_000_000, description="bus bit rate [bit/s]")


def open_bus(settings: BusSettings) -> can.BusABC:
    """The python-can bus the settings name."""
    if settings.interface == "udp_multicast":
        # Its frames leave the machine: never a test bus, and no use for one drive on one host.
        raise CanBusError("canopen.interface 'udp_multicast' is not supported: use socketcan, pcan...")
    try:
        return can.Bus(interface=settings.interface, channel=settings.channel, bitrate=settings.bitrate)
    except (can.CanError, ImportError, OSError, ValueError) as exc:
        raise CanBusError(
            f"canopen bus {settings.interface}:{settings.channel} cannot be opened: {exc}"
        ) from None


class TrafficRecorder(can.Listener):
    """Writes every frame seen and sent into a python-can log (.blf or .asc), from any thread.

    Received frames come from the network's notifier; sent frames from `on_message_sent`, marked
    `is_rx=False`. With no file open, it records nothing.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._writer: can.io.generic.MessageWriter | None = None
        self.path: Path | None = None

    def record_to(self, path: Path | None) -> None:
        """Close the current file (if any) and start writing `path` (None: stop recording)."""
        if path is not None and path.suffix.lower() not in LOG_SUFFIXES:
            raise CanBusError(f"{path}: a raw CAN log must end in .blf or .asc")
        writer = None
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            try:
                writer = can.Logger(path)
            except OSError as exc:
                raise CanBusError(f"{path}: cannot write the raw CAN log: {exc.strerror}") from None
        with self._lock:
            old, self._writer, self.path = self._writer, writer, path
        if old is not None:
            old.stop()

    def on_message_received(self, msg: can.Message) -> None:
        with self._lock:
            if self._writer is not None:
                # One bus per file: the writer's own channel number, whatever the interface calls it
                # (BLF stores a 16-bit number, and a virtual channel's name may end in any digits).
                entry = copy.copy(msg)
                entry.channel = None
                self._writer.on_message_received(entry)

    @property
    def recording(self) -> bool:
        """Whether a file is open (read without the lock: a frame sent as recording starts or stops
        may or may not be in the file, as it might by a hair either way with the lock)."""
        return self._writer is not None

    def on_message_sent(self, msg: can.Message) -> None:
        msg.is_rx = False
        msg.timestamp = time.time()
        self.on_message_received(msg)

    def stop(self) -> None:
        self.record_to(None)


class PeriodicFrame(PeriodicMessageTask):
    """A frame sent every period by a thread of this process, through the network's `send_message`.

    Unlike python-can's task (which canopen uses for heartbeats and SYNC), `stop()` waits for the
    thread to end, and every frame passes the network's recorder. If this process hangs or dies, the
    frame stops: what a heartbeat should do. With a `gate`, a period whose gate says False sends
    nothing (a heartbeat withheld while the control loop it vouches for is hung).
    """

    def __init__(
        self,
        network: canopen.Network,
        can_id: int,
        data: bytes,
        period: float,
        remote: bool,
        gate: Callable[[], bool] | None = None,
    ) -> None:
        # PeriodicMessageTask's constructor starts a python-can task: deliberately not called.
        self.bus = network.bus
        self.period = period
        self.msg = can.Message(
            arbitration_id=can_id, data=data, is_extended_id=can_id > 0x7FF, is_remote_frame=remote
        )
        self._network = network
        self._gate = gate
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"hdrig periodic 0x{can_id:03X}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        due = time.monotonic()
        failing = False
        while True:
            msg = self.msg
            try:
                if self._gate is None or self._gate():
                    self._network.send_message(msg.arbitration_id, bytes(msg.data), msg.is_remote_frame)
                failing = False
            except (can.CanError, RuntimeError) as exc:
                if not failing:
                    logger.warning("periodic frame 0x%03X not sent: %s", msg.arbitration_id, exc)
                failing = True
            due += self.period
            if self._stop.wait(max(0.0, due - time.monotonic())):
                return

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not threading.current_thread():
            self._thread.join()

    def update(self, data: bytes) -> None:
        msg = self.msg
        self.msg = can.Message(
            arbitration_id=msg.arbitration_id,
            data=data,
            is_extended_id=msg.is_extended_id,
            is_remote_frame=msg.is_remote_frame,
        )


class ReceiveFailure(can.Listener):
    """What ended the network's receiving: the bus's error, told once and kept.

    Without a listener that takes errors, python-can's notifier thread dies on the bus's first error
    with a traceback on stderr, and canopen re-raises it only at `disconnect`. Taken here, it is one
    warning, and the servo names it when the drive falls silent. A bus that keeps failing is asked
    again every NOTIFIER_CYCLE, not in a busy loop.
    """

    def __init__(self, retry_s: float) -> None:
        self.error: Exception | None = None
        self._retry_s = retry_s

    def on_message_received(self, msg: can.Message) -> None:
        pass

    def on_error(self, exc: Exception) -> None:
        if self.error is None:
            self.error = exc
            logger.warning("CAN receive failed: %s", exc)
        time.sleep(self._retry_s)


class RecordedNetwork(canopen.Network):
    """A canopen network whose traffic, both ways, goes to a `TrafficRecorder`, with joined threads.

    canopen sends everything through `send_message` (its documented point to override), so SDO, NMT,
    PDO, SYNC and heartbeats are all seen here; `send_periodic` (heartbeats, SYNC) runs `PeriodicFrame`,
    whose `stop()` leaves no thread behind.
    """

    NOTIFIER_CYCLE = 0.05  # the receive thread notices a stop within this [s]

    def __init__(self, bus: can.BusABC, recorder: TrafficRecorder | None = None) -> None:
        super().__init__(bus)
        self.recorder = recorder if recorder is not None else TrafficRecorder()
        self.receive_failure = ReceiveFailure(self.NOTIFIER_CYCLE)
        cast(list[can.Listener], self.listeners).extend([self.recorder, self.receive_failure])

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        super().send_message(can_id, data, remote)
        if not self.recorder.recording:  # a message for the file only if there is one (1 kHz)
            return
        msg = can.Message(
            arbitration_id=can_id, data=data, is_extended_id=can_id > 0x7FF, is_remote_frame=remote
        )
        self.recorder.on_message_sent(msg)

    def send_messages(self, frames: Sequence[tuple[int, bytes]]) -> float:
        """Data frames (id, payload) in order, as `send_message` each; in one write where the bus takes
        a batch (`hdrig-tcp`: the same frames, one system call). Returns the host monotonic time just
        before the last frame was handed to the bus [s]."""
        send_frames = getattr(self.bus, "send_frames", None)
        if send_frames is None:
            for can_id, data in frames[:-1]:
                self.send_message(can_id, data)
            t_last_s = time.monotonic()
            self.send_message(*frames[-1])
            return t_last_s
        if not self.bus:
            raise RuntimeError("Not connected to CAN bus")
        t_last_s = time.monotonic()
        with self.send_lock:
            send_frames(frames)
        self.check()
        if self.recorder.recording:
            for can_id, data in frames:
                msg = can.Message(arbitration_id=can_id, data=data, is_extended_id=can_id > 0x7FF)
                self.recorder.on_message_sent(msg)
        return t_last_s

    def send_periodic(
        self,
        can_id: int,
        data: bytes,
        period: float,
        remote: bool = False,
        gate: Callable[[], bool] | None = None,
    ) -> PeriodicFrame:
        return PeriodicFrame(self, can_id, bytes(data), period, remote, gate)
