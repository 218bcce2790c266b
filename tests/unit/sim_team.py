"""A whole team (coordinator + one NodeRuntime per node) in one thread, on a manual clock.

Messages travel through an InMemoryHub that delivers only when pumped (FIFO, or in a random
order for robustness tests); virtual time moves only when the test says so. Everything is
deterministic, so unit tests can check metering to the joule and sequencing to the message.
"""

from __future__ import annotations

import random

import msgpack

from autopower.basestation.coordinator import Coordinator, CoordinatorConfig
from autopower.node.ports import NodePorts, NodeStores
from autopower.node.runtime import NodeRuntime
from autopower.protocol import Keys, Packet, decode
from autopower.runtime.bus import InMemoryHub
from autopower.runtime.clock import ManualClock


class FakeSource:
    """Frames that carry their seq (so components can check what they get)."""

    def __init__(self, component_type, robot, seed, size=64):
        self.component_type, self.robot, self.size = component_type, robot, size

    def produce(self, seq: int) -> bytes:
        return msgpack.packb([self.robot, seq])

    def ground_truth(self, seq):
        return {}


class FakeComponent:
    """Counts its runs; its state is that count. Raises if an input is skipped or repeated."""

    def __init__(self, component_type, robot, seed):
        self.component_type, self.robot = component_type, robot
        self.next_seq: int | None = None
        self.count = 0

    def run(self, payload: bytes) -> bytes:
        robot, seq = msgpack.unpackb(payload)
        if robot != self.robot:
            raise ValueError(f"input of {robot} given to {self.robot}'s component")
        if self.next_seq is not None and seq != self.next_seq:
            raise ValueError(f"expected seq {self.next_seq}, got {seq}: an input was lost, repeated or reordered")
        self.next_seq = seq + 1
        self.count += 1
        return msgpack.packb([seq, self.count])

    def export_state(self) -> bytes:
        return msgpack.packb([self.next_seq, self.count])

    def import_state(self, state: bytes) -> None:
        self.next_seq, self.count = msgpack.unpackb(state)


class FakeRequest:
    """An operator's query as a base station's process gets it (`runtime.bus.Request`)."""

    def __init__(self, key, payload):
        self.key, self.payload, self.replies, self.closed = key, payload, [], False

    def reply(self, payload):
        self.replies.append(payload)

    def close(self):
        self.closed = True


class SimTeam:
    def __init__(self, scenario, *, config: CoordinatorConfig | None = None, policy=None, fake=True,
                 rng: random.Random | None = None, speed: float = 1.0, relay_on_arrival: bool = True,
                 on_decision_answer=None, stores: dict[str, NodeStores] | None = None,
                 node_kwargs: dict[str, dict] | None = None):
        """``stores``: node -> what its process keeps on disk (none for the others). ``node_kwargs``:
        node -> arguments of its `NodeRuntime` over the team's (its factories, ``stage_workers``)."""
        self.scenario = scenario
        self.clock = ManualClock(speed=speed, epoch_unix=1_000_000.0)
        self.hub = InMemoryHub(synchronous=False)
        self.keys = Keys("sim")
        self.rng = rng
        self.coordinator = Coordinator(scenario=scenario, bus=self.hub.bus("coordinator"), keys=self.keys,
                                       config=config or CoordinatorConfig(speed=speed), policy=policy,
                                       wall_fn=self.clock.wall, on_decision_answer=on_decision_answer)
        self._kwargs = dict(make_component=FakeComponent, make_source=FakeSource) if fake else {}
        self._node_kwargs = node_kwargs or {}
        self._relay_on_arrival = relay_on_arrival
        self._starts: dict[str, int] = {}
        self.nodes: dict[str, NodeRuntime] = {}
        self.subscriptions: dict[str, list] = {}
        for node in scenario.node_names():
            self._start(node, (stores or {}).get(node))
        self.coordinator.bus.subscribe(self.keys.inbox, self._inbox)

    def _start(self, node: str, stores: NodeStores | None) -> NodeRuntime:
        """A process of ``node``: its runtime, on a bus of its own, hearing its keys."""
        starts = self._starts[node] = self._starts.get(node, 0) + 1
        bus = self.hub.bus(node if starts == 1 else f"{node}#{starts}")
        ports = NodePorts(
            send_to=lambda dest, key, payload, node=node, bus=bus, reliable=True: self._send(node, dest, key, payload, bus),
            # as an agent does: a packet only crossing this node is forwarded on arrival (not
            # across a silent cut: that one goes to `on_data`, whose send is lost in `_send`)
            in_sight=lambda dest, node=node: self._relay_on_arrival and (node, dest) not in self.cut_links)
        rt = NodeRuntime(node=node, scenario=self.scenario, bus=bus, keys=self.keys,
                         clock_factory=lambda mission: self.clock,
                         wall=self.clock.wall,  # custody ages frames on the test's clock
                         ports=ports, stores=stores,
                         process=1 << 62 | sum(self._starts.values()),  # as every run of the test has it
                         **{**self._kwargs, **self._node_kwargs.get(node, {})})
        self.nodes[node] = rt
        self.subscriptions[node] = [
            bus.subscribe(k, lambda key, payload, rt=rt: rt.on_message(key, payload))
            for k in ((self.keys.node_control(node), self.keys.plan) if node == self.scenario.basestation
                      else (self.keys.node_control(node),))]  # a robot's plans come on its control key
        self.subscriptions[node].append(bus.subscribe(
            self.keys.node_data(node), lambda key, payload, rt=rt: rt.relay_now(payload) or rt.on_message(key, payload)))
        return rt

    def restart(self, robot: str, saved: dict | None = None) -> NodeRuntime:
        """``robot`` killed (`leave`: what only its process held is gone) and started again as a new
        process, with its predecessor's ``saved`` state (`NodeRuntime.resume_state`; None: none,
        as a process killed before its first snapshot). It is back once it `join`s."""
        if robot in self.subscriptions:
            self.leave(robot)
        return self._start(robot, NodeStores(resume_from=saved))

    # ---- silent cuts: what one node sends another vanishes, nobody is told ----------------------------
    cut_links: frozenset = frozenset()  # (sender, receiver) pairs
    lost_in_cuts = 0

    cut_only_chain_frames = False  # spare migrations' state (a lost state is a cold restart, not this test's point)

    def _send(self, sender: str, dest: str, key: str, payload: bytes, bus) -> None:
        if (sender, dest) in self.cut_links and (not self.cut_only_chain_frames or (
                key == self.keys.node_data(dest) and decode(payload, Packet).purpose == "chain")):
            self.lost_in_cuts += 1
            return
        bus.publish(key, payload)

    def cut_silently(self, a: str, b: str, one_way: bool = False) -> None:
        """Drop what ``a`` sends ``b`` (and, unless ``one_way``, what ``b`` sends ``a``)."""
        self.cut_links = self.cut_links | {(a, b)} | (set() if one_way else {(b, a)})

    def heal_silently(self, a: str, b: str) -> None:
        self.cut_links = self.cut_links - {(a, b), (b, a)}

    def exchange_statuses(self, window_s: float = 10.0) -> None:
        """Every node hears every other node's status, then the acknowledgements addressed to it
        (what it sent was consumed), except across cuts."""
        statuses = {name: rt.status(window_s) for name, rt in self.nodes.items()
                    if rt.started and name in self.subscriptions}
        for name in statuses:  # as the processes do: the sinks write down what a status acknowledges
            self.nodes[name].commit_sinks()
        for name, rt in self.nodes.items():
            if name not in statuses:
                continue
            for other, status in statuses.items():
                if other != name and (other, name) not in self.cut_links:
                    rt.on_peer_status(status)
        for name in statuses:
            for dest, ack in self.nodes[name].acks().items():
                if dest in statuses and (name, dest) not in self.cut_links:
                    self.nodes[dest].on_ack(ack)
        self.pump()

    def _inbox(self, key, payload):
        self.coordinator.on_inbox(payload)

    def pump(self) -> None:
        """As the base station's loop: the messages waiting (and what they cause), then its timer,
        until nothing is left (the timer carries out decisions and plans due by then)."""
        while True:
            self.hub.pump(rng=self.rng)
            self.coordinator.on_timer()
            if not self.hub.pending:
                return

    def join(self, robots=None) -> None:
        robots = robots or [r.name for r in self.scenario.robots]
        self.present = getattr(self, "present", {self.scenario.basestation}) | set(robots)
        for rt in self.nodes.values():  # everyone sees everyone's liveliness token
            for node in self.present - {rt.node}:
                rt.on_liveliness(node, True)
        for robot in robots:
            self.coordinator.on_liveliness(robot, True)
        for robot in robots:  # a robot publishes its status as soon as it sees the base station
            self.coordinator.learn(self.nodes[robot].status(0.0))
        self.pump()

    def leave(self, robot: str) -> None:
        for handle in self.subscriptions.pop(robot):
            handle.close()
        self.present.discard(robot)
        for rt in self.nodes.values():
            rt.on_liveliness(robot, False)
        self.coordinator.on_liveliness(robot, False)
        self.pump()

    def report_status(self, window_s: float = 10.0) -> None:
        for name, rt in self.nodes.items():
            if rt.started and name in self.subscriptions and name != self.scenario.basestation:
                self.coordinator.on_status(rt.status(window_s))
        self.pump()

    def run_until(self, t_end: float, on_tick=None) -> None:
        """Advance virtual time to ``t_end``, firing every source tick on time."""
        while True:
            ticks = [t for name, rt in self.nodes.items()
                     if name in self.subscriptions and (t := rt.next_deadline()) is not None]
            t = min(ticks, default=None)
            if t is None or t > t_end:
                self.clock.set(max(self.clock.t, t_end))
                self.pump()
                return
            self.clock.set(max(self.clock.t, t))
            for name, rt in self.nodes.items():
                if name in self.subscriptions:
                    rt.on_timer()
            self.pump()
            if on_tick is not None:
                on_tick(self.clock.t)

    def run_exchanging_statuses(self, t_end: float, every_s: float = 0.5) -> None:
        """Advance to ``t_end`` with statuses (and acknowledgements) exchanged every ``every_s``."""
        t = self.clock.t
        while t < t_end:
            t += every_s
            self.run_until(t)
            self.exchange_statuses()

    def energy(self, robot: str) -> float:
        self.nodes[robot].metering.settle_relayed()  # what it forwarded on arrival since its last timer
        meter = self.nodes[robot].meter
        meter.advance(self.clock.t)
        return meter.consumed_j
