"""One relay hop through an agent against a raw Zenoh echo, at 200 B, 1 KB and 230 KB.

    .venv/bin/python bench/bench_relay.py [round trips per size, default 400]

Not a timed test: every figure is printed beside baselines measured in the same run, between the
same two kinds of processes. This process is the laptop; it sends a message and waits for it to
come back, one at a time:

- raw echo: a bare zenoh-python process (`ZenohBus`) that republishes what it receives from its
  subscriber callback: two Zenoh hops between two processes and nothing else (the baseline);
- echo via a loop: the same process handing each message to a thread that republishes it (the
  hand-off every AutoPower process used for everything it receives): what a thread switch costs;
- agent relay: a real agent (`autopower.cli.processes agent`, r1 of paper-fig7, the mission
  started) forwarding a `Packet` laptop -> r1 -> laptop carrying an encoded `ChainFrame`; every
  packet is built before the timing starts, so the figure is the agent's hop only.

The three are interleaved in blocks so that load changes on a shared machine hit them alike; p50
of each and the ratio to the raw echo are printed, with the load average while measured, and the
agent's counters say how many packets it forwarded on arrival (`agent.relaying`).
"""

from __future__ import annotations

import os
import statistics
import subprocess
import sys
import tempfile
import textwrap
import threading
import time
from pathlib import Path

import results

from autopower.launch.localhost import endpoint, free_ports
from autopower.model.loading import load_scenario
from autopower.model.network import build_network
from autopower.protocol import (
    ChainFrame,
    Keys,
    LinkInfo,
    MissionInfo,
    NodeStatus,
    Packet,
    PlanUpdate,
    StatusDelta,
    decode,
    encode,
)
from autopower.protocol.statuses import StatusAssembler
from autopower.runtime.bus import ZenohBus, ZenohSettings

SIZES = (200, 1059, 230415)
BLOCK = 50  # round trips of one kind before the next kind

ECHO = textwrap.dedent("""
    import sys, threading
    from autopower.runtime.bus import ZenohBus, ZenohSettings
    from autopower.runtime.events import EventQueue
    bus = ZenohBus(ZenohSettings(listen=(sys.argv[1],)))
    bus.subscribe("bench/ping", lambda k, p: bus.publish("bench/pong", p))
    queue = EventQueue(bulk_keys=["bench/loop-ping"])
    bus.subscribe("bench/loop-ping", queue.on_message)
    def loop():
        while True:
            event = queue.get(None)
            if event is not None:
                bus.publish("bench/loop-pong", event.payload)
    threading.Thread(target=loop, daemon=True).start()
    print("ready", flush=True)
    sys.stdin.read()
    bus.close()
""")


def pct(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


class RoundTrips:
    """Send on one key, time until the same message comes back on another (one in flight)."""

    def __init__(self, bus, send_key: str, recv_key: str):
        self.bus, self.send_key = bus, send_key
        self.done = threading.Event()
        self.sent = 0.0
        self.times: list[float] = []
        self.sub = bus.subscribe(recv_key, self._back)

    def _back(self, key, payload) -> None:
        self.times.append(time.perf_counter() - self.sent)
        self.done.set()

    def run(self, payloads: list[bytes]) -> None:
        for payload in payloads:
            self.done.clear()
            self.sent = time.perf_counter()
            self.bus.publish(self.send_key, payload)
            if not self.done.wait(5.0):
                raise RuntimeError(f"no answer to {self.send_key}")

    def close(self) -> None:
        self.sub.close()


def packets(size: int, n: int) -> list[bytes]:
    """Encoded packets laptop -> r1 -> laptop, each carrying a frame of ``size`` payload bytes."""
    out = []
    for i in range(n):
        frame = ChainFrame(chain="Blob-2", run=0, seq=i, target=1, t_virtual=0.0, t_unix=0.0, payload_len=size,
                           payload=bytes([i % 251]) * size)
        out.append(encode(Packet(path=("laptop", "r1", "laptop"), media=("802.11a", "802.11a"), hop=1,
                                 charge_bytes=size, weight=1.0, purpose="chain", chain="Blob-2", body=encode(frame))))
    return out


def start_agent(team: str, port: int, log_path: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "autopower.cli.processes", "agent", "--robot", "r1", "--team", team,
                             "--listen", endpoint(port), "--log-level", "warning"],
                            stdout=open(log_path, "w"), stderr=subprocess.STDOUT)


def start_mission(bus: ZenohBus, keys: Keys, log_path: Path) -> dict:
    """Be the laptop (alive, the plan's author) and wait until r1 runs the mission; its statuses."""
    scenario = load_scenario("paper-fig7")
    net = build_network(scenario, media={"laptop-robot": "802.11a", "robot-robot": "802.11a"})
    mission = MissionInfo(scenario=scenario.name, accounting=scenario.accounting, epoch_unix=time.time(), speed=1.0,
                          energies_j=scenario.energies_j())
    plan = PlanUpdate(epoch=1, mission=mission, placement={}, running={},
                      links=tuple(LinkInfo(a=l.a, b=l.b, medium=l.medium) for l in net.links), predicted_w={},
                      predicted_lifetime_s=None, plan_t_virtual=0.0)
    bus._laptop_alive = bus.declare_token(keys.alive("laptop"))  # r1 forwards to nodes it sees; held until close
    latest: dict = {}
    seen = threading.Event()

    statuses = StatusAssembler()  # r1's statuses, whole again

    def on_status(key, payload):
        status = statuses.whole(decode(payload, (NodeStatus, StatusDelta)))
        if status is None:
            return
        latest["status"] = status
        if status.plan_epoch == 1 and status.links.get("laptop"):
            seen.set()

    bus._status_sub = bus.subscribe(keys.status("r1"), on_status)
    deadline = time.monotonic() + 60.0
    while not seen.is_set():  # the plan again until r1 acknowledges it (one sent before it is up is lost)
        if time.monotonic() > deadline:
            raise RuntimeError(f"agent r1 did not start the mission in 60 s; see {log_path}")
        bus.publish(keys.plan, encode(plan))
        seen.wait(0.5)
    return latest


def bench_relay(n: int = 400, json_out: str | None = None) -> list[dict]:
    print("\n== one relay hop: laptop -> agent r1 -> laptop vs a raw Zenoh echo (real processes, 127.0.0.1) ==")
    team = "bench-relay"
    keys = Keys(team)
    port_echo, port_agent, port_me = free_ports(3)
    echo = subprocess.Popen([sys.executable, "-c", ECHO, endpoint(port_echo)], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    with tempfile.TemporaryDirectory() as tmp:
        log_path = Path(tmp) / "agent.log"
        agent = start_agent(team, port_agent, log_path)
        try:
            assert echo.stdout.readline().strip() == "ready"
            settings = ZenohSettings(listen=(endpoint(port_me),), connect=(endpoint(port_echo), endpoint(port_agent)))
            with ZenohBus(settings) as bus:
                statuses = start_mission(bus, keys, log_path)
                before = dict(statuses["status"].counters)
                kinds = {"raw": RoundTrips(bus, "bench/ping", "bench/pong"),
                         "loop": RoundTrips(bus, "bench/loop-ping", "bench/loop-pong"),
                         "agent": RoundTrips(bus, keys.node_data("r1"), keys.node_data("laptop"))}
                rows = []
                load = [os.getloadavg()[0]]
                for size in SIZES:
                    raw = [bytes([i % 251]) * size for i in range(n)]
                    sent = {"raw": raw, "loop": raw, "agent": packets(size, n)}
                    for name, kind in kinds.items():
                        kind.run(sent[name][:10])  # warm-up: publishers declared, buffers sized
                        kind.times.clear()
                    for start in range(0, n, BLOCK):
                        for name, kind in kinds.items():
                            kind.run(sent[name][start:start + BLOCK])
                    rows.append((size, {name: list(kind.times) for name, kind in kinds.items()}))
                    load.append(os.getloadavg()[0])
                time.sleep(1.2)  # the next status carries the counters
                after = statuses["status"].counters
                for kind in kinds.values():
                    kind.close()
        finally:
            agent.terminate()
            agent.wait(10)
            echo.stdin.close()
            echo.wait(10)
    print(f"{'payload B':>9} {'raw echo p50 ms':>16} {'p99':>6} {'echo via loop p50':>18} {'ratio':>6} "
          f"{'agent relay p50':>16} {'p99':>6} {'ratio':>6}")
    for size, times in rows:
        raw = statistics.median(times["raw"])
        loop = statistics.median(times["loop"])
        via = statistics.median(times["agent"])
        print(f"{size:>9} {raw * 1e3:>16.3f} {pct(times['raw'], 0.99) * 1e3:>6.3f} {loop * 1e3:>18.3f} "
              f"{loop / raw:>6.2f} {via * 1e3:>16.3f} {pct(times['agent'], 0.99) * 1e3:>6.3f} {via / raw:>6.2f}")
    sent_total = len(SIZES) * (n + 10)

    def delta(name):
        return after.get(name, 0) - before.get(name, 0)

    print(f"agent r1: {delta('forwarded')} of {sent_total} packets forwarded, {delta('forwarded-on-arrival')} on "
          f"arrival (the rest through its loop), {delta('relay-congested')} congested puts; "
          f"load average (1 min) {min(load):.2f}-{max(load):.2f} on {os.cpu_count()} cores")
    note = "a bare Zenoh process republishing from its subscriber callback, interleaved in blocks"
    figures = []
    for size, times in rows:
        raw = statistics.median(times["raw"]) * 1e3
        figures += [
            results.figure(f"agent relay, {size} B, round trip p50", statistics.median(times["agent"]) * 1e3, "ms",
                           "raw echo", raw, note=note),
            results.figure(f"echo via a loop thread, {size} B, round trip p50", statistics.median(times["loop"]) * 1e3,
                           "ms", "raw echo", raw, note=note),
            results.figure(f"agent relay, {size} B, round trip p99", pct(times["agent"], 0.99) * 1e3, "ms",
                           "raw echo p99", pct(times["raw"], 0.99) * 1e3, note=note),
        ]
    figures.append(results.figure("packets the agent forwarded on arrival", delta("forwarded-on-arrival"), "packets",
                                  "packets forwarded", delta("forwarded"),
                                  note="every packet the agent forwarded, on arrival or through its loop"))
    results.write_result("relay", {"round_trips_per_size": n, "sizes": list(SIZES)}, figures, json_out,
                         what=__doc__.splitlines()[0])
    return figures


if __name__ == "__main__":
    out = results.pop_json_out()
    bench_relay(int(sys.argv[1]) if len(sys.argv) > 1 else 400, out)
