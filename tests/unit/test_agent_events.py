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


def test_the_queue_says_how_long_its_oldest_chain_data_has_waited():
    q = EventQueue(bulk_keys=["data"])
    assert q.bulk_wait_s() == 0.0
    q.on_message("control", b"c")  # urgent: taken first, not what a producer's frames wait behind
    assert q.bulk_wait_s() == 0.0
    q.on_message("data", b"0")
    time.sleep(0.05)
    before_1 = time.monotonic()
    q.on_message("data", b"1")
    assert 0.05 <= q.bulk_wait_s() < 5.0
    assert q.get(0) == Received("control", b"c") and q.bulk_wait_s() >= 0.05
    assert q.get(0) == Received("data", b"0")
    assert q.bulk_wait_s() <= time.monotonic() - before_1  # now the younger one is the oldest
    q.get(0)
    assert q.bulk_wait_s() == 0.0


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


def test_a_flood_is_bounded_in_bytes_and_events_and_stop_still_gets_through():
    q = EventQueue(bulk_keys=["data"], bulk_limit=(1000, 10_000), urgent_limit=(5, 1_000_000))
    for _ in range(50):
        q.on_message("data", b"x" * 1000)  # 50 KB offered, 10 KB fit
    assert q.depth() == 10 and q.dropped == 40
    for _ in range(8):
        q.on_message("control", b"c")  # 5 events fit
    assert q.depth() == 15 and q.dropped == 43
    q.post(StopRequested("ctrl-c"))  # never dropped
    assert q.get(0) == Received("control", b"c")
    for _ in range(15):  # 4 control, the stop, 10 data
        q.get(0)
    assert q.get(0) is None
    q.on_message("data", b"y" * 10_000)  # the budget is given back as events are taken
    assert q.depth() == 1 and q.dropped == 43


def test_what_admit_refuses_takes_no_room_and_is_counted_and_logged_once_per_interval(caplog):
    from autopower.protocol import SnapshotRequest, encode
    from autopower.protocol.codec import looks_like_message

    q = EventQueue(bulk_keys=["data"], bulk_limit=(1000, 10_000), admit=looks_like_message)
    with caplog.at_level("WARNING", logger="autopower.runtime.events"):
        for _ in range(500):
            q.on_message("data", os.urandom(1000))
        q.on_message("data", b"")
    assert q.depth() == 0 and q.rejected == 501 and q.dropped == 0
    assert sum("not an AutoPower message" in r.message for r in caplog.records) == 1
    real = encode(SnapshotRequest())
    q.on_message("data", real)  # ours: queued (decoding judges the rest)
    assert q.get(0) == Received("data", real)
    for _ in range(20):
        q.on_message("data", real[:8] + b"x" * 992)  # starts like ours: queued, bounded by the limits
    assert q.depth() == 10 and q.dropped == 10
    assert q.counts() == {"queue-full": 10, "not-a-message": 501}
    assert EventQueue().counts() == {}


def test_a_status_replaces_the_one_still_queued_from_its_sender_and_never_crowds_out_orders():
    # the base station's queue: statuses from every robot converge there; one that falls behind
    # takes each robot's newest (an older one says nothing the newest does not), orders first
    q = EventQueue(bulk_keys=["data"], urgent_limit=(3, 1_000_000),
                   newest_only=lambda key, payload: key.startswith("status/"))
    for i in range(1000):  # a loop stalled for minutes: every robot's statuses keep coming
        for robot in ("r1", "r2"):
            q.on_message(f"status/{robot}", f"{robot}:{i}".encode())
    q.on_message("data", b"frame")
    q.on_message("control", b"assign")
    assert q.depth() == 4 and q.dropped == 0 and q.superseded == 2 * 999
    assert q.get(0) == Received("control", b"assign")  # the order first
    assert [q.get(0) for _ in range(2)] == [Received("status/r1", b"r1:999"), Received("status/r2", b"r2:999")]
    assert q.get(0) == Received("data", b"frame") and q.get(0) is None
    # the bound still holds across orders and statuses of distinct senders (a flood of new keys)
    for robot in ("r1", "r2", "r3", "r4"):
        q.on_message(f"status/{robot}", b"s")
    assert q.depth() == 3 and q.dropped == 1
    q.on_message("status/r1", b"newer")  # replacing takes no new room
    assert q.depth() == 3 and q.dropped == 1 and q.get(0) == Received("status/r1", b"newer")
