"""A silent link cut between two real processes is detected by the Zenoh lease, and heals."""

import subprocess
import sys
import textwrap
import time

import pytest
import zenoh

from autopower.launch.linkproxy import LinkProxy, free_port

LEASE_MS = 500


def config(listen=None, connect=None):
    c = zenoh.Config()
    for key, value in {
        "mode": '"peer"',
        "scouting/multicast/enabled": "false",
        "scouting/gossip/enabled": "false",
        "listen/endpoints": f'["tcp/127.0.0.1:{listen}"]' if listen else "[]",
        "connect/endpoints": f'["tcp/127.0.0.1:{connect}"]' if connect else "[]",
        "transport/link/tx/lease": str(LEASE_MS),
        "transport/link/tx/keep_alive": "4",
        "connect/retry": "{period_init_ms: 50, period_max_ms: 200, period_increase_factor: 2}",
        "connect/timeout_ms": "-1",
    }.items():
        c.insert_json5(key, value)
    return c


FAR_SIDE = textwrap.dedent("""
    import sys, time, zenoh
    c = zenoh.Config()
    for k, v in [("mode", '"peer"'), ("scouting/multicast/enabled", "false"), ("scouting/gossip/enabled", "false"),
                 ("listen/endpoints", "[]"), ("connect/endpoints", f'["tcp/127.0.0.1:{sys.argv[1]}"]'),
                 ("transport/link/tx/lease", "%d"), ("transport/link/tx/keep_alive", "4"),
                 ("connect/retry", "{period_init_ms: 50, period_max_ms: 200, period_increase_factor: 2}"),
                 ("connect/timeout_ms", "-1")]:
        c.insert_json5(k, v)
    s = zenoh.open(c)
    tok = s.liveliness().declare_token("lp/far")
    pub = s.declare_publisher("lp/data", congestion_control=zenoh.CongestionControl.BLOCK)
    n = 0
    deadline = time.monotonic() + 40   # bounded: the test never leaves it running
    while time.monotonic() < deadline:
        pub.put(str(n).encode()); n += 1; time.sleep(0.01)
""" % LEASE_MS)


def wait_for(predicate, timeout_s):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(0.005)
    return False


@pytest.mark.timeout(60)
def test_silent_cut_detected_within_a_second_and_heals():
    port = free_port()
    session = zenoh.open(config(listen=port))
    events, data = [], []
    session.liveliness().declare_subscriber("lp/**", lambda s: events.append((time.monotonic(), s.kind)), history=True)
    session.declare_subscriber("lp/data", lambda s: data.append(time.monotonic()))
    with LinkProxy("near-far", port) as proxy:
        far = subprocess.Popen([sys.executable, "-c", FAR_SIDE, str(proxy.port)])
        try:
            assert wait_for(lambda: any(k == zenoh.SampleKind.PUT for _, k in events), 10), "far side never joined"
            assert wait_for(lambda: len(data) > 5, 5)
            for _ in range(3):
                events.clear()
                proxy.cut()
                cut_at = time.monotonic()
                assert wait_for(lambda: any(k == zenoh.SampleKind.DELETE for _, k in events), 5)
                detected_s = next(t for t, k in events if k == zenoh.SampleKind.DELETE) - cut_at
                assert detected_s <= 1.0, f"silent cut detected only after {detected_s:.3f} s"
                assert far.poll() is None  # nobody said goodbye: the far process is alive
                quiet_from = len(data)
                time.sleep(0.2)
                assert len(data) == quiet_from, "data crossed a cut link"
                events.clear()
                proxy.heal()
                assert wait_for(lambda: any(k == zenoh.SampleKind.PUT for _, k in events), 5), "no reconnection"
                assert wait_for(lambda: len(data) > quiet_from, 5), "data did not resume after heal"  # noqa: B023 (called in this iteration)
        finally:
            far.kill()
            far.wait(timeout=5)
            session.close()


class _Target:
    """A TCP server on 127.0.0.1 that keeps what each connection sends and can write to it."""

    def __init__(self):
        import socket
        import threading

        self.server = socket.create_server(("127.0.0.1", 0))
        self.port = self.server.getsockname()[1]
        self.conns = []
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self):
        while True:
            try:
                conn, _ = self.server.accept()
            except OSError:
                return
            self.conns.append(conn)

    def close(self):
        self.server.close()
        for c in self.conns:
            c.close()


def _recv_exactly(sock, n, timeout_s=10.0):
    sock.settimeout(timeout_s)
    out = bytearray()
    while len(out) < n:
        chunk = sock.recv(n - len(out))
        if not chunk:
            break
        out += chunk
    return bytes(out)


@pytest.mark.timeout(60)
def test_a_slow_reader_holds_up_only_its_own_direction():
    """48 MB towards a reader that takes nothing yet must not stop the other direction (each
    direction is pumped on its own), and arrives whole and in order once it reads."""
    import socket
    import threading

    target = _Target()
    with LinkProxy("slow", target.port) as proxy:
        client = socket.create_connection(("127.0.0.1", proxy.port))
        assert wait_for(lambda: len(target.conns) == 1, 5)
        far = target.conns[0]
        big = bytes(range(256)) * (48 * 4096)  # 48 MB: far more than the kernel buffers on the way hold
        writer = threading.Thread(target=client.sendall, args=(big,), daemon=True)
        writer.start()  # `far` reads nothing for now: this direction fills up and waits
        time.sleep(0.5)
        assert writer.is_alive()  # held up by the reader, as a real link would be
        for i in range(20):  # meanwhile the other direction flows
            far.sendall(b"ping%02d" % i)
            assert _recv_exactly(client, 6, timeout_s=2) == b"ping%02d" % i
        assert _recv_exactly(far, len(big), timeout_s=20) == big
        writer.join(5)
        assert proxy.bytes_forwarded == len(big) + 20 * 6 and proxy.bytes_dropped == 0
        client.close()
        assert far.recv(1) == b""  # a real close is passed on while the link is up
    target.close()


@pytest.mark.timeout(60)
def test_a_cut_is_silent_both_ways_and_heal_drops_the_black_holed_connections():
    import socket

    target = _Target()
    with LinkProxy("cut", target.port) as proxy:
        client = socket.create_connection(("127.0.0.1", proxy.port))
        assert wait_for(lambda: len(target.conns) == 1, 5)
        far = target.conns[0]
        client.sendall(b"before")
        assert _recv_exactly(far, 6) == b"before"
        proxy.cut()
        assert proxy.is_cut
        client.sendall(b"lost")
        far.sendall(b"lost too")
        late = socket.create_connection(("127.0.0.1", proxy.port))  # taken by the kernel, never answered
        late.sendall(b"hello?")
        for s in (client, far, late):  # no bytes, no FIN, no RST: silence
            s.settimeout(0.4)
            with pytest.raises(TimeoutError):
                s.recv(16)
        assert len(target.conns) == 1  # the late one never reached the target
        assert wait_for(lambda: proxy.bytes_dropped == len(b"lost") + len(b"lost too"), 2)
        proxy.heal()
        assert not proxy.is_cut
        for s in (client, late):  # black-holed: closed, so the ends reconnect
            s.settimeout(2)
            assert s.recv(16) == b""
        again = socket.create_connection(("127.0.0.1", proxy.port))
        assert wait_for(lambda: len(target.conns) == 2, 5)
        again.sendall(b"after")
        assert _recv_exactly(target.conns[1], 5) == b"after"
        for s in (client, late, again):
            s.close()
    assert not proxy._acceptor.is_alive()  # close() ends its accepting thread
    target.close()
