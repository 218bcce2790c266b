"""ZenohBus subscribers between two real Zenoh sessions on loopback: what each kind costs at rest
(no thread of ours for a light one, one pump thread for a heavy one), delivery in order, a
callback that raises loses only its own sample, and nothing arrives after close.
"""

from __future__ import annotations

import threading
import time

from autopower.launch.localhost import endpoint, free_ports
from autopower.runtime.bus import ZenohBus, ZenohSettings

N = 50


def connected(sender: ZenohBus, got: list, key: str) -> None:
    deadline = time.monotonic() + 20
    while not got:  # until the link is up
        assert time.monotonic() < deadline, "the two sessions never connected"
        sender.publish(key, b"hello")
        time.sleep(0.1)
    time.sleep(0.3)  # the hellos still on their way
    got.clear()


def wait_for(pred, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not pred():
        assert time.monotonic() < deadline
        time.sleep(0.05)


def test_light_subscribers_use_no_thread_of_ours_and_deliver_in_order():
    at = endpoint(free_ports(1)[0])
    got: list[bytes] = []

    def on_message(key: str, payload: bytes) -> None:
        if payload == b"raise":
            raise RuntimeError("a bug in one callback")
        got.append(payload)

    with ZenohBus(ZenohSettings(listen=(at,))) as receiver, ZenohBus(ZenohSettings(connect=(at,))) as sender:
        before = {t.ident for t in threading.enumerate()}
        handles = [receiver.subscribe(f"light/{i}", on_message) for i in range(5)]
        # what a node at rest relies on: nothing of ours waits on these (a pump woke 10 times a second)
        assert {t.ident for t in threading.enumerate()} == before
        connected(sender, got, "light/0")
        sender.publish("light/1", b"raise")
        for i in range(N):
            sender.publish(f"light/{i % 5}", b"%d" % i)
        wait_for(lambda: len(got) >= N)
        assert got == [b"%d" % i for i in range(N)]  # one session, one link: in order, the bad one alone lost
        handles[0].close()
        time.sleep(0.3)
        sender.publish("light/0", b"after close")
        sender.publish("light/1", b"still here")
        wait_for(lambda: got[-1] == b"still here")
        assert b"after close" not in got


def test_a_heavy_subscriber_has_its_pump_which_ends_with_the_session():
    at = endpoint(free_ports(1)[0])
    got: list[bytes] = []
    with ZenohBus(ZenohSettings(listen=(at,))) as receiver, ZenohBus(ZenohSettings(connect=(at,))) as sender:
        receiver.subscribe("heavy/data", lambda _k, p: got.append(p), heavy=True)
        pumps = [t for t in threading.enumerate() if t.name == "zenoh-sub heavy/data"]
        assert len(pumps) == 1
        connected(sender, got, "heavy/data")
        frame = bytes(range(256)) * 1024  # 256 KB: through shared memory between local sessions
        for _ in range(20):
            sender.publish("heavy/data", frame)
        wait_for(lambda: len(got) >= 20)
        assert got == [frame] * 20
    pumps[0].join(5)
    assert not pumps[0].is_alive()
