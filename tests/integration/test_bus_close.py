"""A process stops within its launcher's limit even when Zenoh's own close does not return soon.

Zenoh's close waits for a connection attempt in flight to a peer that does not answer (measured
here: 8 s) and, for a link that cannot flush, up to 10 s before it raises (eclipse-zenoh/zenoh#2675).
In the 20-robot testbed the base station, whose configured connects to the robots it retries once
they are gone, met the robot behind a silent cut that way: its close took 0.7-5.8 s, once over the
8 s after which `up` and the testbed kill it. `ZenohBus.close` waits `SESSION_CLOSE_WAIT_S` and goes
on; the process exits next, and its sockets close with it.
"""

from __future__ import annotations

import logging
import socket
import time

from autopower.launch.localhost import endpoint
from autopower.runtime.bus import SESSION_CLOSE_WAIT_S, ZenohBus, ZenohSettings


def test_a_close_with_a_connection_attempt_to_a_mute_peer_in_flight_returns_within_its_wait(caplog):
    # a peer that never answers: the kernel completes the TCP handshake, nobody reads what comes
    with socket.create_server(("127.0.0.1", 0)) as mute:
        bus = ZenohBus(ZenohSettings(connect=(endpoint(mute.getsockname()[1]),)))
        time.sleep(1.0)  # its connection attempt is under way, waiting for the peer's answer
        started = time.monotonic()
        with caplog.at_level(logging.WARNING, logger="autopower.runtime.bus"):
            bus.close()
        waited = time.monotonic() - started
    assert SESSION_CLOSE_WAIT_S - 0.1 <= waited < SESSION_CLOSE_WAIT_S + 1.0, waited
    assert "still closing" in caplog.text
