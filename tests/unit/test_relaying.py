"""Forwarding on arrival (`node.relaying`): the same packet, the same energy and counts as the
loop's `on_data`, only for packets that merely cross the node; the rest is left to the loop."""

from __future__ import annotations

import dataclasses
import threading

import pytest

import autopower.node.relaying as relaying
from autopower.agent.process import Agent, AgentConfig
from autopower.model.loading import load_scenario
from autopower.model.network import build_network
from autopower.node.control_meter import ControlPlaneMeter
from autopower.node.meter import BatteryMeter
from autopower.node.ports import NodePorts
from autopower.node.relaying import ArrivalRelay
from autopower.node.runtime import NodeRuntime
from autopower.protocol import ChainFrame, Keys, LinkInfo, MissionInfo, Packet, PlanUpdate, decode, encode
from autopower.runtime.bus import InMemoryHub
from autopower.runtime.clock import ManualClock

SCENARIO = load_scenario("paper-fig7")
KEYS = Keys("t")
MEDIA = {"laptop-robot": "802.11a", "robot-robot": "bluetooth"}


def plan() -> PlanUpdate:
    net = build_network(SCENARIO, media=MEDIA)
    mission = MissionInfo(scenario=SCENARIO.name, accounting=SCENARIO.accounting, epoch_unix=1_000_000.0, speed=1.0,
                          energies_j=SCENARIO.energies_j())
    return PlanUpdate(epoch=1, mission=mission, placement={}, running={},
                      links=tuple(LinkInfo(a=l.a, b=l.b, medium=l.medium) for l in net.links), predicted_w={},
                      predicted_lifetime_s=None, plan_t_virtual=0.0)


def node(hub: InMemoryHub, clock: ManualClock, name: str = "r1", in_sight=lambda dest: True) -> NodeRuntime:
    rt = NodeRuntime(node=name, scenario=SCENARIO, bus=hub.bus(name), keys=KEYS, clock_factory=lambda m: clock,
                     ports=NodePorts(in_sight=in_sight))
    rt.on_plan(plan())
    return rt


def packet(seq: int = 0, size: int = 1059, path=("r3", "r1", "laptop"), media=("bluetooth", "802.11a"), hop=1,
           purpose="chain") -> bytes:
    frame = ChainFrame(chain="Loc-3", run=0, seq=seq, target=0, t_virtual=0.0, t_unix=0.0, payload_len=size,
                       payload=bytes([seq % 251]) * size)
    return encode(Packet(path=path, media=media, hop=hop, charge_bytes=size, weight=4.0, purpose=purpose,
                         chain="Loc-3", body=encode(frame)))


def listen(hub: InMemoryHub, key: str) -> list[bytes]:
    got: list[bytes] = []
    hub.bus("listener").subscribe(key, lambda k, p: got.append(p))
    return got


def test_forwarded_on_arrival_exactly_as_the_loop_forwards():
    """Byte-identical packets to the next node, the same joules in the same meter parts, the same count."""
    clock = ManualClock(t=5.0)
    fast_hub, loop_hub = InMemoryHub(), InMemoryHub()
    fast, loop = node(fast_hub, clock), node(loop_hub, clock)
    fast_out, loop_out = listen(fast_hub, KEYS.node_data("laptop")), listen(loop_hub, KEYS.node_data("laptop"))
    sent = [packet(i, size) for i, size in enumerate([200, 1059, 230_415] * 3)]
    sent.append(packet(9, purpose="recovery"))
    sent.append(packet(10, path=("laptop", "r1", "r2"), media=("802.11a", "bluetooth")))
    for i, payload in enumerate(sent):
        clock.set(5.0 + i)
        assert fast.relay_now(payload)
        loop.frames.on_data(payload)
    assert fast_out[:len(sent) - 1] == loop_out[:len(sent) - 1]
    assert listen(fast_hub, KEYS.node_data("r2")) == []  # (subscribed late: nothing replayed)
    clock.set(30.0)
    fast.status(1.0)  # what the loop does before it reports: charge what was forwarded on arrival
    loop.meter.advance(clock.now())
    assert fast.meter.energy_j.keys() == loop.meter.energy_j.keys()
    for part, joules in loop.meter.energy_j.items():
        assert fast.meter.energy_j[part] == pytest.approx(joules, rel=1e-12), part
    assert fast.meter.airtime_s == pytest.approx(loop.meter.airtime_s, rel=1e-12)
    assert fast.counters["forwarded"] == loop.counters["forwarded"] == len(sent)
    assert fast.counters["forwarded-on-arrival"] == len(sent)
    assert not fast.errors and not loop.errors


def long_header() -> bytes:
    """A valid packet whose header is longer than the header reader looks (`forwarding.MAX_HEADER`):
    the codec takes it, the header reader does not."""
    p = decode(packet(), Packet)
    return encode(dataclasses.replace(p, chain="Blob-2" + "x" * 5000))


@pytest.mark.parametrize("case, payload", [
    ("last hop: ours to consume", packet(path=("r3", "r1"), media=("bluetooth",))),
    ("addressed to another node", packet(path=("r3", "r2", "laptop"))),
    ("a medium the scenario lacks", packet(media=("bluetooth", "lora"))),
    ("garbage", b"\x94\xc4\x02APgarbage"),
    ("a header only the codec reads", long_header()),
])
def test_what_only_the_loop_may_judge_is_left_to_it(case, payload):
    hub = InMemoryHub(record=True)
    rt = node(hub, ManualClock(t=1.0))
    hub.published.clear()
    assert not rt.relay_now(payload), case
    assert hub.published == []
    rt.metering.settle_relayed()
    assert "forwarded" not in rt.counters


def test_nothing_is_forwarded_on_arrival_before_the_mission_or_to_a_node_out_of_sight():
    hub = InMemoryHub(record=True)
    idle = NodeRuntime(node="r1", scenario=SCENARIO, bus=hub.bus("r1"), keys=KEYS,
                       ports=NodePorts(in_sight=lambda dest: True))
    assert not idle.relay_now(packet())  # no mission yet: the loop counts it (data-before-mission)
    # the loop's Relayer routes around a node out of sight
    rt = node(hub, ManualClock(t=1.0), in_sight=lambda dest: dest != "laptop")
    assert not rt.relay_now(packet())
    assert rt.relay_now(packet(path=("laptop", "r1", "r2"), media=("802.11a", "bluetooth")))
    assert [k for k, _, _ in hub.published] == [KEYS.node_data("r2")]


def test_a_slow_put_sends_that_node_s_packets_through_the_loop_for_a_while(monkeypatch):
    wall = [100.0]  # the relay's monotonic clock (wall seconds)
    relay = ArrivalRelay(node="r1", radios=SCENARIO.radios, keys=KEYS, bus=InMemoryHub().bus("r1"),
                         in_sight=lambda dest: True, started=lambda: True, now=lambda: 1.0, monotonic=lambda: wall[0])
    monkeypatch.setattr(relaying, "CONGESTED_S", -1.0)  # every put counts as slow
    assert relay.relay_now(packet(0))  # sent (a put is never undone), then that link counts as backed up
    assert not relay.relay_now(packet(1))  # through the loop now, where a blocked put holds no transport thread
    assert relay.relay_now(packet(2, path=("laptop", "r1", "r2"), media=("802.11a", "bluetooth")))  # other nodes: not
    monkeypatch.setattr(relaying, "CONGESTED_S", 1.0)
    wall[0] += relaying.CONGESTED_HOLD_S * 0.99
    assert not relay.relay_now(packet(3))  # still held
    wall[0] += relaying.CONGESTED_HOLD_S * 0.02  # the hold is over
    assert relay.relay_now(packet(4))
    meter = BatteryMeter(platform=SCENARIO.platform_of("r1"), radios=SCENARIO.radios, initial_j=1000.0, t0=0.0)
    assert relay.settle(meter, ControlPlaneMeter()) == (3, 2)  # three forwarded, two after a slow put
    assert meter.consumed_j > 0 and relay.settle(meter, ControlPlaneMeter()) == (0, 0)


def test_forwards_from_several_transport_threads_are_all_charged():
    clock = ManualClock(t=1.0)
    hub, loop_hub = InMemoryHub(), InMemoryHub()
    rt, loop = node(hub, clock), node(loop_hub, clock)
    payloads = [packet(i, 200) for i in range(400)]
    done = threading.Event()

    def transport():
        for payload in payloads:
            assert rt.relay_now(payload)

    def settling():  # the loop, charging meanwhile
        while not done.is_set():
            rt.metering.settle_relayed()

    threads = [threading.Thread(target=transport) for _ in range(4)]
    loop_thread = threading.Thread(target=settling)
    loop_thread.start()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    done.set()
    loop_thread.join()
    rt.metering.settle_relayed()
    for payload in payloads * 4:
        loop.frames.on_data(payload)
    assert rt.counters["forwarded"] == 1600
    for part, joules in loop.meter.energy_j.items():
        assert rt.meter.energy_j[part] == pytest.approx(joules, rel=1e-9), part


def test_an_agent_forwards_on_arrival_only_when_no_data_waits_for_its_loop():
    """Relayed packets keep their order: one queued for the loop holds the later ones behind it."""
    hub = InMemoryHub(record=True)
    with Agent(AgentConfig(robot="r1", scenario=SCENARIO, team="t"), bus=hub.bus("r1")) as agent:
        agent.runtime.on_plan(plan())
        data = KEYS.node_data("r1")
        hub.published.clear()
        agent._on_data(data, packet(0))  # laptop is not in sight yet: the loop's Relayer decides
        agent.relayer.on_liveliness("laptop", True)
        agent._on_data(data, packet(1))  # in sight, but packet 0 waits for the loop: queued behind it
        assert agent.events.bulk_depth() == 2 and hub.published == []
        while agent.events.bulk_depth():
            agent._handle(agent.events.get(0))
        assert len(hub.published) == 2  # the loop forwarded both, in order
        agent._on_data(data, packet(2))  # nothing waits: forwarded on arrival
        assert agent.events.bulk_depth() == 0 and len(hub.published) == 3
        assert [p for _, p, _ in hub.published] == [
            encode(dataclasses.replace(Packet(**_fields(packet(i))), hop=2)) for i in range(3)]
        agent.runtime.metering.settle_relayed()
        assert agent.runtime.counters["forwarded"] == 3 and agent.runtime.counters["forwarded-on-arrival"] == 1


def _fields(payload: bytes) -> dict:
    p = decode(payload, Packet)
    return {f.name: getattr(p, f.name) for f in dataclasses.fields(p)}
