"""The loopback CAN hub's direct delivery (`_LocalBus.deliver_directly`): the twins' process hands each
frame to the drive twin's listeners in the hub's reader thread, sparing canopen's notifier thread a
wake-up per frame. What it must keep from the queued path: frames in order, one at a time, a
listener's answers sent at once, a failing listener logged and cut off, and no second bus beside it.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterator

import can
import pytest

from drivers.can_bus import RecordedNetwork
from drivers.tcp_can import CanHub

WAIT_S = 5.0
"""How long a frame may take across the hub: a loopback round trip is ~0.5 ms at p50 and a few ms at
its worst under load (measured); 5 s only bounds a failure's wait."""


def until(condition: Callable[[], bool]) -> bool:
    deadline = time.monotonic() + WAIT_S
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.001)
    return True


class Taker(can.Listener):
    """Keeps the ids it is handed and the threads it was handed them in; raises on `fail_on`."""

    def __init__(self, fail_on: int | None = None) -> None:
        self.ids: list[int] = []
        self.threads: set[str] = set()
        self.fail_on = fail_on

    def on_message_received(self, msg: can.Message) -> None:
        self.ids.append(msg.arbitration_id)
        self.threads.add(threading.current_thread().name)
        if msg.arbitration_id == self.fail_on:
            raise ZeroDivisionError("a listener's bug")


def frame(can_id: int, data: bytes = b"") -> can.Message:
    return can.Message(arbitration_id=can_id, data=data, is_extended_id=False)


@pytest.fixture
def hub() -> Iterator[CanHub]:
    hub = CanHub()
    yield hub
    hub.close()


def client(hub: CanHub) -> can.BusABC:
    """A client of the hub, once the hub has accepted it (frames sent before then do not reach it)."""
    before = len(hub._sockets)
    bus = can.Bus(interface="hdrig-tcp", channel=hub.channel)
    assert until(lambda: len(hub._sockets) > before), "the hub did not accept the client"
    return bus


def test_direct_delivery_only_to_the_hubs_one_bus_before_any_client(hub: CanHub) -> None:
    first, second = hub.bus(), hub.bus()
    with pytest.raises(RuntimeError, match="one bus"):
        first.deliver_directly([Taker()])
    second.shutdown()
    first.deliver_directly([Taker()])
    with pytest.raises(RuntimeError, match="second bus"):
        hub.bus()
    first.shutdown()

    late = CanHub()
    try:
        bus = late.bus()
        sender = client(late)
        with pytest.raises(RuntimeError, match="before any client"):
            bus.deliver_directly([Taker()])
        sender.shutdown()
        bus.shutdown()
    finally:
        late.close()


def test_frames_reach_the_listeners_in_order_in_the_hubs_reader_thread(hub: CanHub) -> None:
    bus = hub.bus()
    taker = Taker()
    bus.deliver_directly([taker])
    sender = client(hub)
    try:
        ids = list(range(1, 300))
        for can_id in ids:
            sender.send(frame(can_id, b"x"))
        assert until(lambda: len(taker.ids) == len(ids)), f"{len(taker.ids)} of {len(ids)} frames handed over"
        assert taker.ids == ids
        assert taker.threads == {"hdrig can hub client"}
        assert bus.queue.empty()  # nothing left for a notifier thread
    finally:
        sender.shutdown()
        bus.shutdown()


def test_a_listeners_answers_go_out_in_order(hub: CanHub) -> None:
    bus = hub.bus()

    class Echo(can.Listener):
        def on_message_received(self, msg: can.Message) -> None:
            bus.send(frame(msg.arbitration_id + 0x100, b"1"))
            bus.send(frame(msg.arbitration_id + 0x200, b"2"))

    bus.deliver_directly([Echo()])
    sender = client(hub)
    try:
        for can_id in (0x10, 0x11):
            sender.send(frame(can_id))
        answers = [sender.recv(timeout=WAIT_S) for _ in range(4)]
        assert [a.arbitration_id if a is not None else None for a in answers] == [0x110, 0x210, 0x111, 0x211]
    finally:
        sender.shutdown()
        bus.shutdown()


def test_a_failing_listener_is_logged_and_gets_no_more_frames(
    hub: CanHub, caplog: pytest.LogCaptureFixture
) -> None:
    bus = hub.bus()
    taker = Taker(fail_on=0x666)
    bus.deliver_directly([taker])
    sender, watcher = client(hub), client(hub)
    try:
        with caplog.at_level(logging.ERROR, logger="drivers.tcp_can"):
            for can_id in (0x5, 0x666, 0x7, 0x8):
                sender.send(frame(can_id))
            # The reader thread takes a client's frames one after another: once the watcher has 0x8,
            # the local handing over of 0x7 is done.
            seen = [watcher.recv(timeout=WAIT_S) for _ in range(4)]
        assert [m.arbitration_id if m is not None else None for m in seen] == [0x5, 0x666, 0x7, 0x8]
        assert until(lambda: taker.ids == [0x5, 0x666])
        assert any("a listener failed" in r.getMessage() for r in caplog.records)
    finally:
        sender.shutdown()
        watcher.shutdown()
        bus.shutdown()


@pytest.mark.filterwarnings("error::pytest.PytestUnhandledThreadExceptionWarning")
def test_a_hub_that_goes_away_is_one_warning_and_a_kept_reason_not_a_dead_thread(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The twins' process killed: its hub closes every stream. The host's receive thread must neither die
    with a traceback (python-can's notifier re-raises an error no listener takes) nor spin on a bus
    that keeps failing: the error is kept for the servo's message, told once, and asked again every
    NOTIFIER_CYCLE. canopen still re-raises it at disconnect, as it documents."""
    hub = CanHub()
    network = RecordedNetwork(client(hub))
    network.connect()
    calls: list[float] = []
    failure = network.receive_failure
    real = failure.on_error

    def counted(exc: Exception) -> None:
        calls.append(time.monotonic())
        real(exc)

    failure.on_error = counted  # type: ignore[method-assign]
    with caplog.at_level(logging.WARNING, logger="drivers.can_bus"):
        hub.close()
        assert until(lambda: failure.error is not None), "the hub's closing was not seen"
        time.sleep(10 * RecordedNetwork.NOTIFIER_CYCLE)
    assert "the hub closed the bus" in str(failure.error)
    # Asked again at most once a cycle (+2: the first error and a cycle begun at the boundary).
    span = calls[-1] - calls[0]
    assert len(calls) <= span / RecordedNetwork.NOTIFIER_CYCLE + 2, (len(calls), span)
    assert [r.getMessage() for r in caplog.records].count(f"CAN receive failed: {failure.error}") == 1
    with pytest.raises(can.CanOperationError, match="hub closed"):
        network.disconnect()
