"""The processes' event queue: urgent events overtake chain data; callbacks only enqueue."""

import os
import signal
import threading
import time

from autopower.runtime.events import EventQueue, LivelinessChanged, Received, StopRequested


def test_urgent_events_overtake_bulk_data():
    q = EventQueue(bulk_keys=["data"])
    for i in range(3):
        q.on_message("data", bytes([i]))
    q.on_message("control", b"c")
    q.on_liveliness("alive/r1", False)
    assert q.depth() == 5
    order = [q.get(0) for _ in range(5)]
    assert order[0] == Received("control", b"c")
    assert order[1] == LivelinessChanged("alive/r1", False)
    assert [e.payload for e in order[2:]] == [b"\x00", b"\x01", b"\x02"]
    assert q.get(0) is None


def test_get_waits_and_wakes_on_post():
    q = EventQueue()
    threading.Timer(0.05, lambda: q.post(StopRequested("x"))).start()
    started = time.monotonic()
    assert q.get(5.0) == StopRequested("x")
    assert time.monotonic() - started < 2.0
    started = time.monotonic()
    assert q.get(0.05) is None and time.monotonic() - started >= 0.04


def test_a_signal_handler_can_post_while_the_loop_waits():
    q = EventQueue()
    previous = signal.signal(signal.SIGUSR1, lambda *_: q.post(StopRequested("signal")))
    try:
        # sent to the process from another thread, as kill(1) does while Zenoh's threads run
        threading.Timer(0.05, lambda: os.kill(os.getpid(), signal.SIGUSR1)).start()
        started = time.monotonic()
        assert q.get(5.0) == StopRequested("signal")
        assert time.monotonic() - started < 1.0
    finally:
        signal.signal(signal.SIGUSR1, previous)
