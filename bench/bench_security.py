"""What mutual TLS + access control cost, and what a shaped 802.11a link carries.

    .venv/bin/python bench/bench_security.py [--opens 9] [--pings 300] [--frames 40]

1. Session open: a client session to a listening peer, plain tcp vs mTLS with the team's access
   control on the listener (median of --opens); ratio in the same run.
2. One relay hop: A -> R -> C and back (R republishes, as an agent relays), round-trip time of
   small messages over tcp vs mTLS; ratio in the same run.
3. End-to-end signatures on relayed messages: the same round trip through the agents' own
   `Relayer` (A signs, R forwards, C verifies and answers signed, A verifies) over mTLS + ACL,
   with and without signatures; ratio in the same run, and the cost of one sign / one verify.
4. Throughput (root only): 230 KB frames over an 802.11a link of the testbed (two namespaces, a
   veth pair shaped to 54 Mbit/s), from a Zenoh mTLS publisher in one namespace to a subscriber
   in the other, against the configured rate. Not a test: prints figures.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import results

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from autopower.deploy.pki import TeamCA  # noqa: E402
from autopower.launch.localhost import free_ports  # noqa: E402
from autopower.protocol import Keys  # noqa: E402
from autopower.protocol.access import TeamAccess  # noqa: E402
from autopower.runtime.access_control import zenoh_access_control  # noqa: E402
from autopower.runtime.bus import TlsFiles, ZenohBus, ZenohSettings  # noqa: E402

FRAME = 230 * 1024
KEYS = Keys("bench")
ACCESS = TeamAccess(KEYS, "laptop", ("r1", "r2"))


def identities(directory: Path) -> dict[str, TlsFiles]:
    ca = TeamCA.create(directory / "ca", "bench")
    out = {}
    for node in ("laptop", "r1", "r2", "operator"):
        ident = ca.issue(node, ["127.0.0.1", "10.99.1.1", "10.99.1.2"], directory)
        out[node] = TlsFiles(ca=str(ident.ca), cert=str(ident.cert), key=str(ident.key))
    return out


def settings(secure: bool, ids, node: str, *, listen=(), connect=(), mode="peer") -> ZenohSettings:
    scheme = "tls" if secure else "tcp"
    return ZenohSettings(mode=mode, listen=tuple(f"{scheme}/{h}" for h in listen),
                         connect=tuple(f"{scheme}/{h}" for h in connect),
                         tls=ids[node] if secure else None,
                         access_control=zenoh_access_control(ACCESS) if secure else None)


def session_open(secure: bool, ids, n: int) -> float:
    port = free_ports(1)[0]
    with ZenohBus(settings(secure, ids, "laptop", listen=[f"127.0.0.1:{port}"])):
        times = []
        for _ in range(n):
            t = time.perf_counter()
            bus = ZenohBus(settings(secure, ids, "operator", connect=[f"127.0.0.1:{port}"], mode="client"))
            times.append(time.perf_counter() - t)
            bus.close()
    return statistics.median(times)


def relay_rtt(secure: bool, ids, n: int) -> float:
    """A (r1) -> R (laptop) -> C (r2) -> R -> A, R republishing like an agent's relay."""
    p = free_ports(1)[0]
    hub = ZenohBus(settings(secure, ids, "laptop", listen=[f"127.0.0.1:{p}"]))
    a = ZenohBus(settings(secure, ids, "r1", connect=[f"127.0.0.1:{p}"]))
    c = ZenohBus(settings(secure, ids, "r2", connect=[f"127.0.0.1:{p}"]))
    got = threading.Event()
    # keys each identity may put on: r1 -> its relay key; laptop -> r2's relay / r1's data; r2 -> relay
    hub.subscribe(KEYS.node_relay("laptop"), lambda k, v: hub.publish(KEYS.node_relay("r2"), v))
    c.subscribe(KEYS.node_relay("r2"), lambda k, v: c.publish(KEYS.node_data("laptop"), v))
    hub.subscribe(KEYS.node_data("laptop"), lambda k, v: hub.publish(KEYS.node_data("r1"), v))
    a.subscribe(KEYS.node_data("r1"), lambda k, v: got.set())
    time.sleep(1.0)
    times = []
    for i in range(n + 10):
        got.clear()
        t = time.perf_counter()
        a.publish(KEYS.node_relay("laptop"), b"x" * 64)
        if not got.wait(2.0):
            raise SystemExit("a relayed message did not come back (ACL or connection problem)")
        if i >= 10:
            times.append(time.perf_counter() - t)
    for bus in (a, c, hub):
        bus.close()
    return statistics.median(times)


def signed_relay_rtt(ids, n: int, signed: bool) -> float:
    """r1 -> laptop -> r2 and back through `Relayer`s, over mTLS + ACL, signed or not."""
    from autopower.protocol import Relayed  # noqa: F401 - what travels
    from autopower.runtime.relay import Relayer
    from autopower.runtime.signatures import Signing

    p = free_ports(1)[0]
    hub = ZenohBus(settings(True, ids, "laptop", listen=[f"127.0.0.1:{p}"]))
    a = ZenohBus(settings(True, ids, "r1", connect=[f"127.0.0.1:{p}"]))
    c = ZenohBus(settings(True, ids, "r2", connect=[f"127.0.0.1:{p}"]))

    def relayer(node, bus, sees, views):
        signing = Signing.load(node, ids[node].ca, ids[node].cert, ids[node].key) if signed else None
        r = Relayer(node=node, bus=bus, keys=KEYS, access=ACCESS, signing=signing)
        r.direct, r.views = set(sees), views
        return r

    ra = relayer("r1", a, {"laptop"}, {"laptop": {"r2"}})
    rh = relayer("laptop", hub, {"r1", "r2"}, {})
    rc = relayer("r2", c, {"laptop"}, {"laptop": {"r1"}})
    got = threading.Event()

    def at_c(k, v):
        if rc.on_relay(v) is not None:
            rc.send("r1", KEYS.node_data("r1"), v[-64:])

    hub.subscribe(KEYS.node_relay("laptop"), lambda k, v: rh.on_relay(v))
    c.subscribe(KEYS.node_relay("r2"), at_c)
    a.subscribe(KEYS.node_relay("r1"), lambda k, v: ra.on_relay(v) is not None and got.set())
    time.sleep(1.0)
    times = []
    for i in range(n + 10):
        got.clear()
        t = time.perf_counter()
        ra.send("r2", KEYS.node_data("r2"), b"x" * 64)
        if not got.wait(2.0):
            raise SystemExit("a relayed message did not come back (signature, ACL or connection problem)")
        if i >= 10:
            times.append(time.perf_counter() - t)
    if signed and (ra.signing.forged or rc.signing.forged):
        raise SystemExit("a genuine relayed message was taken for a forgery")
    for bus in (a, c, hub):
        bus.close()
    return statistics.median(times)


def sign_verify_us(ids, n: int = 500) -> tuple[float, float]:
    from autopower.protocol import Relayed
    from autopower.runtime.signatures import Signing

    r1 = Signing.load("r1", ids["r1"].ca, ids["r1"].cert, ids["r1"].key)
    r2 = Signing.load("r2", ids["r2"].ca, ids["r2"].cert, ids["r2"].key)
    msg = Relayed(path=("r1", "laptop", "r2"), hop=1, key=KEYS.node_data("r2"), payload=b"x" * 64)
    t = time.perf_counter()
    for _ in range(n):
        signed = r1.sign(msg)
    t_sign = (time.perf_counter() - t) / n
    r2.signer(signed)  # the certificate is checked against the CA once, then remembered
    t = time.perf_counter()
    for _ in range(n):
        r2.signer(signed)
    t_verify = (time.perf_counter() - t) / n
    from autopower.protocol import encode

    return t_sign * 1e6, t_verify * 1e6, len(encode(msg)), len(encode(signed))


RECEIVER = r"""
import sys, time, threading
from autopower.runtime.bus import ZenohBus, ZenohSettings, TlsFiles
from autopower.runtime.access_control import zenoh_access_control
from autopower.protocol import Keys
from autopower.protocol.access import TeamAccess
d, n = sys.argv[1], int(sys.argv[2])
keys = Keys("bench")
tls = TlsFiles(ca=d + "/ca.pem", cert=d + "/laptop.pem", key=d + "/laptop.key")
acl = zenoh_access_control(TeamAccess(keys, "laptop", ("r1", "r2")))
done, times = threading.Event(), []
def on(k, v):
    times.append(time.time())
    if len(times) == n:
        done.set()
with ZenohBus(ZenohSettings(listen=("tls/0.0.0.0:7447",), tls=tls, access_control=acl, shared_memory=False)) as bus:
    bus.subscribe(keys.node_data("laptop"), on)
    print("ready", flush=True)
    done.wait(120)
    print(len(times), times[0] if times else 0, times[-1] if times else 0, flush=True)
"""


def shaped_throughput(ids_dir: Path, ids, frames: int) -> tuple[float, float]:
    from autopower.launch.netns import NamespaceNetwork
    from autopower.model.loading import load_scenario
    from autopower.model.network import Link, Network

    radios = load_scenario("paper-fig7").radios
    net = Network(["r1", "laptop"], "laptop", [Link(a="r1", b="laptop", medium="802.11a", group="x")])
    with NamespaceNetwork(net, radios, speed=1.0, state_dir=Path(tempfile.mkdtemp())) as ns:
        rx = subprocess.Popen([*ns.exec_prefix("laptop"), sys.executable, "-c", RECEIVER, str(ids_dir), str(frames)],
                              stdout=subprocess.PIPE, text=True, cwd=str(Path(__file__).resolve().parents[1]))
        assert rx.stdout.readline().strip() == "ready"
        sender = f"""
import time
from autopower.runtime.bus import ZenohBus, ZenohSettings, TlsFiles
from autopower.protocol import Keys
d = {str(ids_dir)!r}
tls = TlsFiles(ca=d + "/ca.pem", cert=d + "/r1.pem", key=d + "/r1.key")
with ZenohBus(ZenohSettings(connect=("tls/{ns.peer_address('r1', 'laptop')}:7447",), tls=tls,
                            shared_memory=False)) as bus:
    time.sleep(1.0)
    for i in range({frames}):
        bus.publish(Keys("bench").node_data("laptop"), bytes({FRAME}))
    time.sleep(1.0)
"""
        subprocess.run([*ns.exec_prefix("r1"), sys.executable, "-c", sender], check=True,
                       cwd=str(Path(__file__).resolve().parents[1]))
        out = rx.communicate(timeout=180)[0].split()
        count, first, last = int(out[0]), float(out[1]), float(out[2])
        print(f"  received {count} of {frames} frames in {last - first:.3f} s", file=sys.stderr)
        rate_mbit = (count - 1) * FRAME * 8 / (last - first) / 1e6 if count > 1 else 0.0
        return rate_mbit, ns.rate_kbit(ns.links[0]) / 1000


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--opens", type=int, default=9)
    ap.add_argument("--pings", type=int, default=300)
    ap.add_argument("--frames", type=int, default=40)
    results.add_json_out(ap)
    args = ap.parse_args()
    directory = Path(tempfile.mkdtemp(prefix="bench-security-"))
    ids = identities(directory)
    import zenoh

    zenoh.init_log_from_env_or("error")
    tcp_open, tls_open = session_open(False, ids, args.opens), session_open(True, ids, args.opens)
    print(f"session open (median of {args.opens}): tcp {tcp_open * 1e3:.2f} ms, mTLS+ACL {tls_open * 1e3:.2f} ms, "
          f"ratio {tls_open / tcp_open:.2f}")
    tcp_hop, tls_hop = relay_rtt(False, ids, args.pings), relay_rtt(True, ids, args.pings)
    print(f"one relay hop, round trip (median of {args.pings}): tcp {tcp_hop * 1e3:.3f} ms, "
          f"mTLS+ACL {tls_hop * 1e3:.3f} ms, ratio {tls_hop / tcp_hop:.2f}")
    plain_hop, signed_hop = signed_relay_rtt(ids, args.pings, False), signed_relay_rtt(ids, args.pings, True)
    sign_us, verify_us, plain_bytes, signed_bytes = sign_verify_us(ids)
    print(f"relayed through the agents' Relayer, round trip over mTLS+ACL (median of {args.pings}): "
          f"unsigned {plain_hop * 1e3:.3f} ms, signed {signed_hop * 1e3:.3f} ms, ratio {signed_hop / plain_hop:.2f}; "
          f"one ECDSA P-256 sign {sign_us:.0f} us, one verify {verify_us:.0f} us; "
          f"+{signed_bytes - plain_bytes} B per relayed message (certificate + signature)")
    figures = [
        results.figure("session open, mTLS + access control", tls_open * 1e3, "ms", "plain tcp", tcp_open * 1e3,
                       note=f"the same session opened over plain tcp, median of {args.opens}"),
        results.figure("one relay hop round trip, mTLS + access control", tls_hop * 1e3, "ms", "plain tcp",
                       tcp_hop * 1e3, note=f"the same round trip over plain tcp, median of {args.pings}"),
        results.figure("relayed through Relayer, signed", signed_hop * 1e3, "ms", "unsigned", plain_hop * 1e3,
                       note="the same round trip through the agents' Relayer without signatures, over mTLS + ACL"),
        results.figure("one ECDSA P-256 verify", verify_us, "us", "one sign", sign_us,
                       note="signing the same relayed message"),
        results.figure("relayed message, signed", signed_bytes, "B", "unsigned", plain_bytes,
                       note="the same message without certificate and signature"),
    ]
    if os.geteuid() == 0:
        got, configured = shaped_throughput(directory, ids, args.frames)
        print(f"230 KB frames over a shaped 802.11a link: {got:.1f} Mbit/s of {configured:.0f} Mbit/s configured "
              f"({got / configured:.0%})")
        figures.append(results.figure("230 KB frames over a shaped 802.11a link, mTLS", got, "Mbit/s",
                                      "configured rate", configured,
                                      note="the rate the testbed shapes the link to (tc on a veth pair)"))
    else:
        print("throughput over a shaped link: skipped (needs root for the testbed's namespaces)")
    results.write_result("security", {"opens": args.opens, "pings": args.pings, "frames": args.frames}, figures,
                         args.json_out, what="What mutual TLS, access control and signatures cost, and what a "
                                             "shaped 802.11a link carries.")


if __name__ == "__main__":
    main()
