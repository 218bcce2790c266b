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
                assert wait_for(lambda: len(data) > quiet_from, 5), "data did not resume after heal"
        finally:
            far.kill()
            far.wait(timeout=5)
            session.close()
