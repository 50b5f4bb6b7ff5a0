"""A CAN bus between processes of one machine: a hub on a loopback TCP port, python-can buses on it.

`CanHub` listens on 127.0.0.1 (never another address: the frames of a simulated bench stay on this
machine) and repeats every frame a client sends to every other client, as a CAN bus does; buses in
the hub's own process attach without a socket (`CanHub.bus()`). `TcpCanBus` is the python-can
interface `hdrig-tcp` (registered as a `can.interface` entry point): `can.Bus(interface="hdrig-tcp",
channel="127.0.0.1:PORT")`, so canopen's own master can use it too.

A frame is 16 bytes on the stream: arbitration id (uint32, bit 31 extended, bit 30 remote), DLC (uint8),
3 bytes padding, 8 data bytes; TCP_NODELAY sends each at once. A hub or client that goes away closes
the stream: the other side's `recv` then raises `can.CanOperationError`, which the servo driver meets as
a lost drive.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import select
import socket
import struct
import threading
import time
from collections.abc import Sequence
from typing import Any, Final

import can

logger = logging.getLogger(__name__)

LOOPBACK: Final = "127.0.0.1"
FRAME = struct.Struct("<IB3x8s")
EXTENDED_BIT, REMOTE_BIT = 1 << 31, 1 << 30


def encode(msg: can.Message) -> bytes:
    flags = (EXTENDED_BIT if msg.is_extended_id else 0) | (REMOTE_BIT if msg.is_remote_frame else 0)
    return FRAME.pack(msg.arbitration_id | flags, msg.dlc, bytes(msg.data).ljust(8, b"\0"))


def encode_frame(can_id: int, data: bytes) -> bytes:
    """A data frame's record from its id and payload (what `encode` makes of its message, without one)."""
    return FRAME.pack(can_id | (EXTENDED_BIT if can_id > 0x7FF else 0), len(data), data)  # 8s pads with 0


def decode(record: bytes, channel: str) -> can.Message:
    ident, dlc, data = FRAME.unpack(record)
    remote = bool(ident & REMOTE_BIT)
    return can.Message(
        timestamp=time.time(),
        arbitration_id=ident & 0x1FFFFFFF,
        is_extended_id=bool(ident & EXTENDED_BIT),
        is_remote_frame=remote,
        dlc=dlc,
        data=b"" if remote else data[:dlc],
        channel=channel,
    )


def loopback_address(channel: str) -> tuple[str, int]:
    """`127.0.0.1:PORT` (or `localhost:PORT`) as an address; ValueError for anything off this machine."""
    host, sep, port = str(channel).rpartition(":")
    if not sep or host not in (LOOPBACK, "localhost") or not port.isdigit():
        raise ValueError(f"hdrig-tcp channel {channel!r}: expected 127.0.0.1:PORT (loopback only)")
    return LOOPBACK, int(port)


class TcpCanBus(can.BusABC):
    """A client of a `CanHub`: python-can interface `hdrig-tcp`, channel `127.0.0.1:PORT`."""

    def __init__(self, channel: Any, **kwargs: Any) -> None:
        address = loopback_address(channel)
        try:
            self._sock = socket.create_connection(address, timeout=2.0)
        except OSError as exc:
            raise can.CanInitializationError(f"hdrig-tcp: no hub at {channel}: {exc.strerror}") from None
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sock.settimeout(None)
        self._buffer = b""
        self._send_lock = threading.Lock()
        self.channel_info = f"hdrig-tcp {channel}"
        self._channel = str(channel)
        super().__init__(channel, **kwargs)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        try:
            with self._send_lock:
                self._sock.sendall(encode(msg))
        except OSError as exc:
            raise can.CanOperationError(f"hdrig-tcp {self._channel}: hub gone: {exc}") from exc

    def send_frames(self, frames: Sequence[tuple[int, bytes]]) -> None:
        """Data frames (id, payload) in order, in one write: the hub's reader takes them in one read
        (a cycle's RPDOs and SYNC: one wake-up of the twins' process instead of one per frame)."""
        try:
            with self._send_lock:
                self._sock.sendall(b"".join([encode_frame(can_id, data) for can_id, data in frames]))
        except OSError as exc:
            raise can.CanOperationError(f"hdrig-tcp {self._channel}: hub gone: {exc}") from exc

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        deadline = None if timeout is None else time.monotonic() + timeout
        while len(self._buffer) < FRAME.size:
            wait = None if deadline is None else max(0.0, deadline - time.monotonic())
            try:
                ready, _, _ = select.select([self._sock], [], [], wait)
                if not ready:
                    return None, False
                chunk = self._sock.recv(64 * FRAME.size)
            except (OSError, ValueError) as exc:  # ValueError: closed by shutdown() meanwhile
                raise can.CanOperationError(f"hdrig-tcp {self._channel}: hub gone: {exc}") from exc
            if not chunk:
                raise can.CanOperationError(f"hdrig-tcp {self._channel}: the hub closed the bus")
            self._buffer += chunk
        record, self._buffer = self._buffer[: FRAME.size], self._buffer[FRAME.size :]
        return decode(record, self._channel), False

    def shutdown(self) -> None:
        super().shutdown()
        with contextlib.suppress(OSError):
            self._sock.shutdown(socket.SHUT_RDWR)
        self._sock.close()


class _LocalBus(can.BusABC):
    """A bus inside the hub's process: sends go straight to the hub, receives come from a queue, or with
    `deliver_directly` are handed to its listeners by the hub's reader threads."""

    def __init__(self, hub: CanHub) -> None:
        self._hub = hub
        self.queue: queue.SimpleQueue[can.Message] = queue.SimpleQueue()
        self.channel_info = f"hdrig-tcp hub {hub.channel}"
        self._listeners: Sequence[can.Listener] | None = None
        self._delivering = threading.Lock()  # one frame at a time, in order, as a notifier hands them
        super().__init__(hub.channel)

    def deliver_directly(self, listeners: Sequence[can.Listener]) -> None:
        """From now on, hand every frame to `listeners` (a canopen network's `listeners`) in the thread
        of the hub that reads it from its client, instead of queueing it for this bus's notifier thread:
        each frame spares that thread's wake-up (between the hub's reader and the drive twin's SYNC
        handler), on the path of the drive's answer.

        Only for the hub's one bus in this process (the twins' process), before any client connects
        (the hub then makes no other): every frame it gets comes from a client's reader thread, handed
        over one at a time, and a listener's own frames never come back to it in the same thread. A
        listener that raises ends the delivery to this bus, logged, as it ends a notifier's thread."""
        self._hub.make_direct(self)
        self._listeners = listeners

    def deliver(self, msg: can.Message) -> None:
        """Take a frame from the hub: to the listeners at once (`deliver_directly`), else to the queue."""
        if self._listeners is None:
            self.queue.put(msg)
            return
        with self._delivering:
            try:
                for listener in self._listeners:
                    listener.on_message_received(msg)
            except Exception:
                logger.exception("hdrig-tcp %s: a listener failed: no more frames for it", self._hub.channel)
                self._listeners = ()

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self._hub.repeat(encode(msg), source=self)

    def send_frames(self, frames: Sequence[tuple[int, bytes]]) -> None:
        """Data frames (id, payload) in order, as `send` each, without a message object for each."""
        for can_id, data in frames:
            self._hub.repeat(encode_frame(can_id, data), source=self)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        try:
            return self.queue.get(timeout=timeout), False
        except queue.Empty:
            return None, False

    def shutdown(self) -> None:
        super().shutdown()
        if self._listeners is not None:
            with self._delivering:  # a frame being handed over is done first; none after
                self._listeners = ()
        self._hub.detach(self)


class CanHub:
    """Repeats every frame to every other client: sockets on 127.0.0.1:`port` and buses in this process."""

    def __init__(self, port: int = 0) -> None:
        self._server = socket.create_server((LOOPBACK, port))
        self.port: int = self._server.getsockname()[1]
        self.channel = f"{LOOPBACK}:{self.port}"
        self._lock = threading.Lock()
        self._sockets: dict[socket.socket, threading.Lock] = {}
        self._locals: list[_LocalBus] = []
        self._direct = False  # a local bus takes its frames in the reader threads: no other is made
        self._closing = threading.Event()
        self._threads: list[threading.Thread] = []
        # Per reader thread, while it hands one read's frames on: the records for each socket, written
        # together after the last (`_read_loop`).
        self._held = threading.local()
        self._accept = threading.Thread(target=self._accept_loop, name="hdrig can hub", daemon=True)
        self._accept.start()

    def bus(self) -> _LocalBus:
        """A python-can bus on this hub, in this process."""
        local = _LocalBus(self)
        with self._lock:
            if self._direct:
                raise RuntimeError("hdrig-tcp hub: no second bus beside one that takes frames directly")
            self._locals.append(local)
        return local

    def make_direct(self, local: _LocalBus) -> None:
        """Check that `local` may take its frames in the reader threads (`_LocalBus.deliver_directly`)."""
        with self._lock:
            if self._locals != [local] or self._sockets:
                raise RuntimeError("hdrig-tcp hub: direct delivery only to its one bus, before any client")
            self._direct = True

    def detach(self, local: _LocalBus) -> None:
        with self._lock:
            if local in self._locals:
                self._locals.remove(local)

    def repeat(self, record: bytes, source: object) -> None:
        """Hand a frame to every client but its source (sockets in the caller's thread)."""
        with self._lock:
            sockets = [(s, lock) for s, lock in self._sockets.items() if s is not source]
            locals_ = [b for b in self._locals if b is not source]
        held: dict[socket.socket, list[bytes]] | None = getattr(self._held, "records", None)
        for sock, lock in sockets:  # first: a local bus may take a while over its frame
            if held is not None:
                held.setdefault(sock, []).append(record)
                continue
            try:
                with lock:
                    sock.sendall(record)
            except OSError:
                self._drop(sock)
        if locals_:
            msg = decode(record, self.channel)
            for local in locals_:
                local.deliver(msg)

    def _accept_loop(self) -> None:
        while not self._closing.is_set():
            try:
                sock, _ = self._server.accept()
            except OSError:
                return  # closed
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with self._lock:
                self._sockets[sock] = threading.Lock()
            reader = threading.Thread(
                target=self._read_loop, args=(sock,), name="hdrig can hub client", daemon=True
            )
            self._threads.append(reader)
            reader.start()

    def _read_loop(self, sock: socket.socket) -> None:
        buffer = b""
        while True:
            try:
                chunk = sock.recv(64 * FRAME.size)
            except OSError:
                chunk = b""
            if not chunk:
                self._drop(sock)
                return
            buffer += chunk
            # What the frames of this read make a local bus send (a drive's answers to the SYNC that
            # ends a cycle's RPDOs) goes out in one write per client once all are handed on: one
            # wake-up of the master's receive thread per cycle instead of one per frame, same order.
            held: dict[socket.socket, list[bytes]] = {}
            self._held.records = held
            try:
                while len(buffer) >= FRAME.size:
                    record, buffer = buffer[: FRAME.size], buffer[FRAME.size :]
                    self.repeat(record, source=sock)
            finally:
                self._held.records = None
                self._send_held(held)

    def _send_held(self, held: dict[socket.socket, list[bytes]]) -> None:
        with self._lock:
            locks = {s: self._sockets.get(s) for s in held}
        for sock, records in held.items():
            lock = locks[sock]
            if lock is None:  # dropped meanwhile
                continue
            try:
                with lock:
                    sock.sendall(b"".join(records))
            except OSError:
                self._drop(sock)

    def _drop(self, sock: socket.socket) -> None:
        with self._lock:
            self._sockets.pop(sock, None)
        with contextlib.suppress(OSError):
            sock.shutdown(socket.SHUT_RDWR)
        sock.close()

    def close(self) -> None:
        """Stop accepting, close every client's stream, end the threads."""
        self._closing.set()
        with contextlib.suppress(OSError):
            self._server.shutdown(socket.SHUT_RDWR)
        self._server.close()
        self._accept.join()
        with self._lock:
            sockets = list(self._sockets)
        for sock in sockets:
            self._drop(sock)
        for thread in self._threads:
            thread.join()
