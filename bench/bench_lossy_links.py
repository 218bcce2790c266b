"""Throughput under loss: 230 KB frames over a shaped 802.11a link losing 0-20 % of its packets. Needs root.

    .venv/bin/python bench/bench_lossy_links.py [--frames 40] [--loss 0,5,10,20]
                     [--transports tcp,quic,udp,tcp@5000/15] [--ack-loss] [--run-timeout 60] [--budget 240]

Two namespaces of the testbed (`NamespaceNetwork`: a veth pair shaped with tbf to paper-fig7's
802.11a rate, 54,000 kbit/s, both ends), made and removed by this bench (also on an error,
ctrl-C or SIGTERM; after a SIGKILL, `autopower testbed down`). A Zenoh publisher in r1 puts ``--frames`` frames of 230 KB back to back
(reliable, BLOCK: an agent's `ZenohBus` with the team's settings) to a subscriber in the laptop's
namespace, for each transport and each loss, once the subscriber is known (on a lossy link the
session's open can take seconds). The loss is the testbed's own (`autopower fault loss`, through
`FaultController`): nftables drops that share of the packets r1 sends, at random, on arrival,
after they crossed the link. Only the data direction loses by default; ``--ack-loss`` drops the
same share of the acknowledgements too.

Per run: goodput (payload delivered / time from the first put to the last arrival) against the
configured rate, each frame's latency from its put to its arrival (p50, p99; it includes the wait
behind the frames put before it), frames lost, the longest put, and the bytes r1's end of the link
really transmitted (its veth's ``tx_bytes``, lost copies included, from just before the first put
to the end). Bytes on the wire per payload byte, divided by the same transport's lossless figure
(headers and framing), is the retransmission factor, which the energy model's per-link ``loss``
prices as 1 / (1 - loss) (docs/concepts/energy-model.md): the figure shows both.

Each veth end has ``gso_max_segs 1``: the kernel would otherwise hand the link 64 KB TCP
super-packets, which the rule would drop 45 frames at a time; a radio loses frames one by one.

Transports: ``tcp``; ``quic`` (Zenoh's QUIC link, TLS with a team CA made for the run by
`autopower.deploy.pki`); ``udp`` (Zenoh's best-effort UDP link: nothing is resent; the kernel
reassembles its 64 KB datagrams before the rule sees them, so the rule loses whole datagrams,
which flatters UDP: on a radio one lost fragment of 45 loses its datagram). ``T@MS/N`` runs
transport T with a Zenoh lease of MS ms instead of the team's 1,000 ms (a put blocked for a lease
closes the link: `ZenohSettings`) and the kernel's ``tcp_retries2`` N instead of the testbed's
2 (a robot's setting, docs/deploying/robots.md: a connection whose segment stays unacknowledged
for ~1.4 s is given up, ETIMEDOUT): at 20 % loss TCP hits both, Zenoh closes and reopens the
link, and the frames put meanwhile are lost. Not a test: prints figures.
"""

from __future__ import annotations

import argparse
import json
import os
import select
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import results

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from autopower.basestation.operator import state_dir  # noqa: E402
from autopower.errors import AutoPowerError  # noqa: E402
from autopower.launch.faults import FaultController  # noqa: E402
from autopower.launch.localhost import LocalTeam  # noqa: E402
from autopower.launch.netns import TCP_RETRIES2, NamespaceNetwork  # noqa: E402
from autopower.launch.testbed import _LinkSwitch  # noqa: E402
from autopower.model.loading import load_scenario  # noqa: E402
from autopower.model.network import Link, Network  # noqa: E402
from autopower.runtime.bus import ZenohSettings  # noqa: E402

FRAME = 230 * 1024
PORT = 7447
KEY = "bench/lossy/frames"
MEDIUM = "802.11a"
SKIPPED: dict[int, list[str]] = {}  # pid -> the log lines `line_of` read past
LOG_TAIL = 1500  # characters of each process's log kept in the JSON (Zenoh's, with RUST_LOG)
LEASE_MS = ZenohSettings().lease_ms  # what a team runs with (deploy's fleet.toml default too)

# The subscriber: records each frame's index, put time (its first 16 bytes) and arrival; prints
# one JSON line when it has them all, when no frame came for `idle` s, or at its deadline.
RECEIVER = r"""
import json, struct, sys, threading, time
from autopower.runtime.bus import TlsFiles, ZenohBus, ZenohSettings
endpoint, n, deadline, idle, tls, lease = sys.argv[1], int(sys.argv[2]), float(sys.argv[3]), float(sys.argv[4]), \
    sys.argv[5], int(sys.argv[6])
tls = TlsFiles(ca=tls + "/ca.pem", cert=tls + "/laptop.pem", key=tls + "/laptop.key") if tls != "-" else None
got, sizes, lock, done = {}, [], threading.Lock(), threading.Event()
def on(key, value):
    now = time.time()
    i, sent = struct.unpack_from("<qd", value)
    with lock:
        got.setdefault(i, (sent, now))
        sizes.append(len(value))
        if len(got) >= n:
            done.set()
with ZenohBus(ZenohSettings(listen=(endpoint,), tls=tls, shared_memory=False, lease_ms=lease)) as bus:
    bus.subscribe("__KEY__", on)
    print("ready", flush=True)
    start = time.time()
    while not done.is_set() and time.time() - start < deadline:
        with lock:
            last = max((a for _, a in got.values()), default=start)
        if time.time() - last > idle:  # nothing for `idle` s (since the start, or the last frame)
            break
        done.wait(0.1)
    with lock:
        print(json.dumps({"frames": {str(i): v for i, v in got.items()}, "bytes": sum(sizes),
                          "short": sum(1 for s in sizes if s != __FRAME__)}), flush=True)
""".replace("__KEY__", KEY).replace("__FRAME__", str(FRAME))

# The publisher: connects, waits for the subscriber, reads its own end's tx counter, puts the
# frames back to back, then stays connected (retransmissions go on) until its stdin closes.
SENDER = r"""
import struct, sys, time
from autopower.runtime.bus import TlsFiles, ZenohBus, ZenohSettings
endpoint, n, dev, tls, lease = sys.argv[1], int(sys.argv[2]), sys.argv[3], sys.argv[4], int(sys.argv[5])
tls = TlsFiles(ca=tls + "/ca.pem", cert=tls + "/r1.pem", key=tls + "/r1.key") if tls != "-" else None
def counter():
    return int(open(f"/sys/class/net/{dev}/statistics/tx_bytes").read())
with ZenohBus(ZenohSettings(connect=(endpoint,), tls=tls, shared_memory=False, lease_ms=lease)) as bus:
    # until the subscriber is known: on a lossy link the session's open (SYN, Zenoh's handshake)
    # can take seconds, and a put before it goes nowhere
    probe, waited = bus.session.declare_publisher("__KEY__"), time.time()
    while not probe.matching_status and time.time() - waited < 30:
        time.sleep(0.05)
    matched = time.time() - waited
    time.sleep(0.5)
    body = bytes(__FRAME__ - 16)
    print("start", counter(), time.time(), matched, flush=True)
    longest = 0.0
    for i in range(n):
        t = time.time()
        bus.publish("__KEY__", struct.pack("<qd", i, t) + body)
        longest = max(longest, time.time() - t)
    print("put", time.time(), longest, flush=True)
    sys.stdin.read()
""".replace("__KEY__", KEY).replace("__FRAME__", str(FRAME))


class _Team:
    """What `FaultController` uses of a team for link faults (as tests/integration/test_testbed_loss.py)."""

    proxy = LocalTeam.proxy

    def __init__(self, net: NamespaceNetwork):
        self.nodes = list(net.nodes)
        self.proxies = {frozenset((l.a, l.b)): _LinkSwitch(net, l.a, l.b) for l in net.links}
        self.spec = SimpleNamespace(record_dir=None)

    def supervision(self) -> dict:
        return {}


def _stop(signum, _frame):  # SIGTERM leaves like ctrl-C: the `with` blocks remove the namespaces
    raise KeyboardInterrupt(f"signal {signum}")


def counter(net: NamespaceNetwork, node: str, dev: str, what: str = "tx_bytes") -> int:
    out = subprocess.run([*net.exec_prefix(node), "cat", f"/sys/class/net/{dev}/statistics/{what}"],
                         capture_output=True, text=True, timeout=10, check=True)
    return int(out.stdout)


def line_of(proc: subprocess.Popen, word: str, timeout: float) -> list[str] | None:
    """The first line of ``proc``'s output starting with ``word``, split (Zenoh's log lines, when
    RUST_LOG asks for them, go to the same output); None if none came within ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if not select.select([proc.stdout], [], [], max(0.0, deadline - time.monotonic()))[0]:
            return None
        line = proc.stdout.readline()
        if not line:
            return None
        if line.split()[:1] == [word]:
            return line.split()
        SKIPPED.setdefault(proc.pid, []).append(line)
    return None


def pct(values: list[float], q: float) -> float | None:
    if not values:
        return None
    values = sorted(values)
    return values[min(len(values) - 1, max(0, round(q * (len(values) - 1))))]


def identities(directory: Path, addresses: list[str]) -> str:
    from autopower.deploy.pki import TeamCA

    ca = TeamCA.create(directory / "ca", "bench")
    for node in ("laptop", "r1"):
        ca.issue(node, addresses, directory)  # ca.pem, NODE.pem, NODE.key
    return str(directory)


def one_run(net: NamespaceNetwork, transport: str, loss: float, frames: int, tls: str, timeout: float,
            lease_ms: int = LEASE_MS) -> dict:
    """One transport at one loss: frames put, frames and bytes delivered, bytes on the wire."""
    link = net.links[0]
    dev_tx, dev_rx = link.dev_a, link.dev_b  # r1 is link.a
    peer = net.peer_address("r1", "laptop")
    listen, connect = f"{transport}/0.0.0.0:{PORT}", f"{transport}/{peer}:{PORT}"
    rx = subprocess.Popen([*net.exec_prefix("laptop"), sys.executable, "-c", RECEIVER, listen, str(frames),
                           str(timeout), "10", tls, str(lease_ms)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                          cwd=ROOT)
    tx = None
    try:
        if line_of(rx, "ready", 20) is None:
            raise AutoPowerError(f"{transport}: the subscriber did not start")
        tx = subprocess.Popen([*net.exec_prefix("r1"), sys.executable, "-c", SENDER, connect, str(frames), dev_tx,
                               tls, str(lease_ms)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True, cwd=ROOT)
        start = line_of(tx, "start", 20)
        if start is None:
            raise AutoPowerError(f"{transport}: the publisher did not connect")
        tx0, t0, connect_s = int(start[1]), float(start[2]), float(start[3])
        ack0 = counter(net, "laptop", dev_rx)
        out, err = rx.communicate(timeout=timeout + 30)
        tx_end, ack_end = counter(net, "r1", dev_tx), counter(net, "laptop", dev_rx)
        put_line = line_of(tx, "put", 5.0) or []  # a put still blocked: no figure (the log may say why)
    finally:
        tx_log = ""
        for proc in (tx, rx):
            if proc is not None and proc.poll() is None:
                if proc is tx:
                    try:
                        proc.stdin.close()
                        proc.wait(5)
                    except (OSError, subprocess.TimeoutExpired):
                        pass
                if proc.poll() is None:
                    proc.kill()
                    proc.wait()
        if tx is not None:
            try:
                tx_log = ("".join(SKIPPED.pop(tx.pid, [])) + tx.stdout.read() + tx.stderr.read())[-LOG_TAIL:]
            except (OSError, ValueError):
                pass
    got = json.loads(next(line for line in reversed(out.splitlines()) if line.startswith("{")))
    arrivals = {int(i): tuple(v) for i, v in got["frames"].items()}
    latencies = [a - s for s, a in arrivals.values()]
    delivered = len(arrivals) * FRAME
    last = max((a for _, a in arrivals.values()), default=t0)
    goodput = delivered * 8 / (last - t0) / 1e6 if arrivals and last > t0 else 0.0
    wire = tx_end - tx0
    return {"transport": transport, "loss_pct": loss, "frames": frames, "received": len(arrivals),
            "lost": frames - len(arrivals), "goodput_mbit_s": goodput, "seconds": last - t0,
            "latency_p50_ms": (pct(latencies, 0.5) or 0) * 1e3 if latencies else None,
            "latency_p99_ms": (pct(latencies, 0.99) or 0) * 1e3 if latencies else None,
            "wire_bytes": wire, "payload_bytes": delivered, "wire_per_payload": wire / delivered if delivered else None,
            "reverse_bytes": ack_end - ack0, "all_put": bool(put_line), "connect_s": connect_s,
            "longest_put_s": float(put_line[2]) if len(put_line) > 2 else None,
            "receiver_log": ("\n".join(l for l in out.splitlines() if not l.startswith("{")) + (err or ""))[-LOG_TAIL:],
            "sender_log": tx_log}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=40, help="frames per run (at most 200)")
    ap.add_argument("--loss", default="0,5,10,20", help="loss levels, %% of the data direction's packets")
    ap.add_argument("--transports", default="tcp,quic,udp,tcp@5000/15",
                    help="Zenoh links to measure; T@MS/N: transport T with a lease of MS ms instead of the team's "
                         "and the kernel's tcp_retries2 N instead of the testbed's 2")
    ap.add_argument("--ack-loss", action="store_true", help="drop the same share of the reverse direction too")
    ap.add_argument("--run-timeout", type=float, default=60.0, help="seconds one run may take at most")
    ap.add_argument("--budget", type=float, default=240.0, help="seconds for all runs; the rest is skipped")
    results.add_json_out(ap)
    args = ap.parse_args()
    if os.geteuid() != 0:
        raise SystemExit("bench_lossy_links needs root (the testbed's namespaces)")
    frames = max(2, min(args.frames, 200))
    losses = [float(x) for x in args.loss.split(",")]
    transports = [t.strip() for t in args.transports.split(",") if t.strip()]
    signal.signal(signal.SIGTERM, _stop)
    started = time.monotonic()
    radios = load_scenario("paper-fig7").radios
    network = Network(["r1", "laptop"], "laptop", [Link(a="r1", b="laptop", medium=MEDIUM, group="x")])
    runs, skipped = [], []
    work = Path(tempfile.mkdtemp(prefix="bench-lossy-"))
    # recorded where `autopower testbed down` looks: it removes what a SIGKILLed run left
    with NamespaceNetwork(network, radios, speed=1.0, state_dir=state_dir()) as net:
        link = net.links[0]
        for node, dev in ((link.a, link.dev_a), (link.b, link.dev_b)):  # one radio frame per packet
            subprocess.run(["ip", "-n", net.ns(node), "link", "set", "dev", dev, "gso_max_segs", "1"], check=True)
        cc = subprocess.run([*net.exec_prefix("r1"), "sysctl", "-n", "net.ipv4.tcp_congestion_control"],
                            capture_output=True, text=True).stdout.strip()
        tls = identities(work / "tls", [link.address("r1"), link.address("laptop"), "127.0.0.1"])
        controller = FaultController(_Team(net))
        configured = net.rate_kbit(link) / 1000
        print(f"802.11a link shaped to {configured:g} Mbit/s; {frames} frames of {FRAME:,} B per run; "
              f"TCP congestion control {cc}; loss on r1->laptop{' and back' if args.ack_loss else ''}; "
              f"load {results.load()}", flush=True)
        for spec in transports:
            transport, _, rest = spec.partition("@")
            lease, _, retries = rest.partition("/")
            lease_ms, retries2 = int(lease) if lease else LEASE_MS, int(retries) if retries else TCP_RETRIES2
            for node in net.nodes:  # the testbed's (a robot's) setting unless the spec says otherwise
                subprocess.run([*net.exec_prefix(node), "sysctl", "-qw", f"net.ipv4.tcp_retries2={retries2}"],
                               check=True)
            for loss in losses:
                if time.monotonic() - started > args.budget:
                    skipped.append(f"{spec} {loss:g}%")
                    continue
                controller.apply({"op": "heal", "a": "r1", "b": "laptop"})
                if loss > 0:
                    controller.apply({"op": "loss", "a": "r1", "b": "laptop", "pct": loss,
                                      "one_way": not args.ack_loss})
                try:
                    r = one_run(net, transport, loss, frames, tls if transport == "quic" else "-", args.run_timeout,
                                lease_ms)
                except (AutoPowerError, subprocess.SubprocessError, ValueError, IndexError, StopIteration) as exc:
                    r = {"loss_pct": loss, "error": str(exc)[:400]}
                r.update(spec=spec, lease_ms=lease_ms, tcp_retries2=retries2)
                runs.append(r)
                if "error" in r:
                    print(f"{spec:>9} {loss:4g} %: FAILED {r['error']}", flush=True)
                    continue
                print(f"{spec:>9} {loss:4g} %: {r['received']}/{frames} frames, {r['goodput_mbit_s']:.1f} Mbit/s "
                      f"({r['goodput_mbit_s'] / configured:.0%} of {configured:g}), latency p50 "
                      f"{r['latency_p50_ms'] or 0:.0f} ms p99 {r['latency_p99_ms'] or 0:.0f} ms, wire/payload "
                      f"{r['wire_per_payload'] or 0:.3f}, reverse {r['reverse_bytes']:,} B, longest put "
                      f"{r['longest_put_s'] if r['longest_put_s'] is not None else float('nan'):.2f} s", flush=True)
        controller.apply({"op": "heal", "a": "r1", "b": "laptop"})
    if skipped:
        print(f"skipped (over --budget {args.budget:g} s): {', '.join(skipped)}")
    figures, groups = [], {}
    for spec in transports:
        mine = [r for r in runs if r["spec"] == spec and "error" not in r]
        if not mine:
            continue
        transport, lease_ms, retries2 = mine[0]["transport"], mine[0]["lease_ms"], mine[0]["tcp_retries2"]
        clean = next((r for r in mine if r["loss_pct"] == 0 and r.get("wire_per_payload")), None)
        tcp = f", tcp_retries2 {retries2}" if transport == "tcp" else ""
        group = f"Zenoh over {transport}, lease {lease_ms / 1000:g} s{tcp}"
        both = " (and the reverse direction too)" if args.ack_loss else ""
        groups[group] = {"what": f"230 KB frames from r1 to the laptop over Zenoh's {transport} link (lease "
                                 f"{lease_ms:,} ms: a put blocked that long closes the link"
                                 + (f"; the kernel gives a TCP connection up after {retries2} retransmission "
                                    "timeouts of one segment" if tcp else "")
                                 + f"), the data direction losing the share of packets shown{both}."}
        for r in mine:
            g = f"{r['loss_pct']:g} % loss"
            detail = (f"{r['received']}/{r['frames']} frames; latency p50 {r['latency_p50_ms'] or 0:.0f} ms, "
                      f"p99 {r['latency_p99_ms'] or 0:.0f} ms; "
                      + (f"longest put {r['longest_put_s']:.2f} s" if r["longest_put_s"] is not None
                         else "puts not done when the subscriber stopped"))
            figures.append(results.figure(f"goodput, {g}", r["goodput_mbit_s"], "Mbit/s", "configured rate",
                                          configured, group=group, detail=detail,
                                          note="the rate the testbed shapes the 802.11a link to (tbf, both ends)"))
            figures.append(results.figure(f"frames lost, {g}", r["lost"], "frames", "frames put", r["frames"],
                                          group=group, note="frames the publisher put, reliably (BLOCK)"))
            if r["loss_pct"] > 0 and r.get("wire_per_payload") and clean:
                factor = r["wire_per_payload"] / clean["wire_per_payload"]
                model = 1 / (1 - r["loss_pct"] / 100)
                cut = f"; {r['lost']} frames lost: the bytes of a frame cut off count too" if r["lost"] else ""
                figures.append(results.figure(
                    f"retransmission factor, {g}", factor, "x", "model 1/(1-loss)", model, group=group,
                    detail=f"wire bytes per payload byte {r['wire_per_payload']:.3f}, lossless "
                           f"{clean['wire_per_payload']:.3f}{cut}",
                    note="the energy model's price of a lossy link's messages; the factor measured is the bytes "
                         "the sender's end put on the link per payload byte delivered, divided by the same "
                         "transport's at 0 % loss"))
    errors = [r for r in runs if "error" in r]
    results.write_result(
        "lossy_links",
        {"frames": frames, "frame_bytes": FRAME, "loss_pct": losses, "transports": transports, "lease_ms": LEASE_MS,
         "ack_loss": args.ack_loss, "configured_mbit_s": configured, "tcp_congestion_control": cc},
        figures, args.json_out, what=__doc__.splitlines()[0].replace(" Needs root.", ""),
        groups=groups,
        extra={"runs": runs, "skipped": skipped})
    if errors:
        print(f"{len(errors)} run(s) failed: " + "; ".join(f"{r['spec']} {r['loss_pct']:g}%: {r['error'][:120]}"
                                                          for r in errors), file=sys.stderr)


if __name__ == "__main__":
    main()
