"""The bytes a node's session exchanges with a peer, as `LinkTraffic` reads them from the kernel,
checked against an independent count: the link's proxy, which counts every byte it forwards in
user space. The peer is another process with its own Zenoh session; the proxy's own sockets are
in this process too, and must not be taken for the link."""

from __future__ import annotations

import socket
import subprocess
import sys
import textwrap
import time

import pytest

from autopower.launch.linkproxy import LinkProxy
from autopower.launch.localhost import endpoint
from autopower.runtime.bus import ZenohBus, ZenohSettings
from autopower.runtime.link_traffic import LinkTraffic, supported
from tests.e2e.test_up import wait_until

pytestmark = [pytest.mark.parallel,  # no wall-clock bound: it waits for what it counts, within 60 s
              pytest.mark.skipif(not supported(), reason="reads TCP_INFO through /proc (Linux)")]

MESSAGES, SIZE = 200, 5_000

# The peer probes until told to go: Zenoh drops a put at its source while the subscriber's
# declaration has not reached it (the link being up does not mean it has), so the messages counted
# go only once a probe has arrived.
PEER = textwrap.dedent("""
    import sys, threading, time
    from autopower.runtime.bus import ZenohBus, ZenohSettings
    bus = ZenohBus(ZenohSettings(listen=("{endpoint}",), shared_memory=False))
    print(bus.zid, flush=True)
    go = threading.Event()
    threading.Thread(target=lambda: (sys.stdin.readline(), go.set()), daemon=True).start()
    while not go.is_set():
        bus.publish("lt/probe", b"?")
        time.sleep(0.1)
    for _ in range({n}):
        bus.publish("lt/data", b"x" * {size})
    sys.stdin.readline()  # counted: stop
    bus.close()
""")


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def test_the_bytes_to_a_peer_session_are_what_its_link_carried_and_nothing_else():
    port = free_port()
    code = PEER.format(n=MESSAGES, size=SIZE, endpoint=endpoint(port))
    peer = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    got: list[int] = []
    try:
        peer_zid = peer.stdout.readline().strip()
        with LinkProxy("r1-laptop", port) as proxy:
            # no shared memory, as the team's processes run: Zenoh would carry a message over 3 kB
            # through it between two processes on one host, and the link would see 25 bytes of it
            bus = ZenohBus(ZenohSettings(connect=(endpoint(proxy.port),), shared_memory=False))
            try:
                probes: list[int] = []
                bus.subscribe("lt/data", lambda key, payload: got.append(len(payload)))
                bus.subscribe("lt/probe", lambda key, payload: probes.append(len(payload)))
                links = wait_until(lambda: bus.links().get(peer_zid), 60.0, "the link to the peer")
                assert all(src.startswith("tcp/127.0.0.1:") and dst == endpoint(proxy.port) for src, dst in links)
                wait_until(lambda: probes, 60.0, "the peer to reach our subscription")
                traffic = LinkTraffic()
                peer.stdin.write("go\n")
                peer.stdin.flush()
                wait_until(lambda: len(got) == MESSAGES, 60.0, "every message")
                time.sleep(0.5)  # what is in flight lands
                by_peer = traffic.poll(bus.links())
                forwarded = proxy.bytes_forwarded
                sent, received = traffic.payload_by_peer[peer_zid]
                # the proxy forwarded what the session sent and received, both ways; only keep-alives
                # (a few dozen bytes each) may cross between the two readings
                assert abs((sent + received) - forwarded) <= 512, (sent, received, forwarded)
                assert received >= MESSAGES * SIZE and sent > 0
                # what the radio carries adds the TCP/IP headers of every segment
                assert by_peer[peer_zid][1] > received and by_peer[peer_zid][0] > sent
                # the proxy's own two sockets live in this process too: never counted as the link
                assert traffic.unattributed[0] + traffic.unattributed[1] >= forwarded
                assert set(by_peer) == {peer_zid}
                again = traffic.poll(bus.links())  # a reading adds only what crossed since the last
                assert again[peer_zid][1] - by_peer[peer_zid][1] < 1_000
            finally:
                bus.close()
    finally:
        if peer.poll() is None:
            peer.stdin.write("stop\n")
            peer.stdin.flush()
            try:
                peer.wait(timeout=20)
            except subprocess.TimeoutExpired:
                peer.kill()
