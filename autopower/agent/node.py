"""What every node of the team does with chain data: host stages, run sources, forward, sink.

`NodeRuntime` is the logic shared by the robot agents and the base station (which hosts
off-loaded components and is the operator's sink). It has no threads and no sockets of its
own: the owning process feeds it events from its loop and it publishes through a `Bus`.

Data follows the model's routes exactly: a sender takes the shortest-hop path of the current
network and puts it in the packet's header; every node on the way (a robot's agent, since
Zenoh peers do not relay) forwards it to the next one and is charged send + receive for it.

Stage lifecycle (per node): STARTING (prepared for an incoming migration: inputs are buffered)
-> RUNNING -> DRAINING (exporting its state) -> MIGRATED (a forwarding pointer: late inputs
go to the new host). Sequence numbers make each stage run each input once and in order.

Every frame a node produces (a source's input, a stage's output) stays in its custody
(`autopower.agent.custody`) until the consumer's status reports it consumed; a report that
still lacks it a while after it was sent gets it resent. That is what makes each output reach
its sink exactly once even when a link is cut silently with frames in flight.
"""

from __future__ import annotations

import dataclasses
import enum
import logging
import math
import time
import zlib
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable

from autopower.agent.custody import Custody, Report, hop_key, parse_hop_key
from autopower.agent.meter import BatteryMeter
from autopower.agent.sequencing import SequenceGate, SinkLedger
from autopower.errors import AutoPowerError, ProtocolError
from autopower.model.energy import flow_weight
from autopower.model.network import Link, Network
from autopower.model.scenario import Chain, Scenario, Stage
from autopower.protocol import (
    Assign,
    ChainFrame,
    Consumed,
    Keys,
    MigrateOut,
    MissionInfo,
    NodeStatus,
    Packet,
    PlanUpdate,
    Prepare,
    Prepared,
    Release,
    SinkStats,
    SourceStats,
    StageReady,
    StateTransfer,
    decode,
    encode,
)
from autopower.protocol.messages import CONTROL_MESSAGES
from autopower.runtime.bus import Bus
from autopower.runtime.clock import Clock, VirtualClock

log = logging.getLogger(__name__)

MAX_FORWARDS = 16  # a frame bounced more often than this between pointers is parked instead
ORPHAN_LIMIT = 256  # frames held for a stage this node is about to host (a transient window)
HELD_OUTPUT_LIMIT = 512  # results held for a sink out of reach (oldest dropped, counted)


class Lifecycle(enum.Enum):
    STARTING = "starting"
    RUNNING = "running"
    DRAINING = "draining"
    MIGRATED = "migrated"


def chain_seed(scenario: Scenario, chain: Chain) -> int:
    """The same seed on every node, so a source and its component agree on the world."""
    return zlib.crc32(f"{scenario.name}/{chain.name}".encode())


def pad(payload: bytes, size: int, what: str) -> bytes:
    """Zero-pad a real payload to the chain's declared message size.

    The radios are charged for the declared sizes (the model's), so the bytes on the wire are
    made exactly that long too; a payload longer than declared is a scenario error.
    """
    if len(payload) > size:
        raise ProtocolError(f"{what}: a real payload of {len(payload)} B exceeds the chain's declared "
                            f"message_bytes {size}; raise message_bytes in the scenario")
    return payload + bytes(size - len(payload))


@dataclass
class HostedStage:
    stage: Stage
    chain: Chain
    index: int
    generation: int
    lifecycle: Lifecycle
    run: int = 0
    component: Any = None
    gate: SequenceGate = field(default_factory=SequenceGate)
    buffer: list[ChainFrame] = field(default_factory=list)  # inputs held while STARTING
    forward_to: str | None = None  # MIGRATED: where late inputs go
    runs: int = 0
    compute_s: float = 0.0


@dataclass
class SourceRunner:
    chain: Chain
    source: Any
    run: int
    next_t: float
    seq: int = 0
    missed: int = 0
    produced_total: int = 0


class NodeRuntime:
    """Chain data handling for one node; see the module docstring."""

    def __init__(self, *, node: str, scenario: Scenario, bus: Bus, keys: Keys,
                 make_component: Callable | None = None, make_source: Callable | None = None,
                 clock_factory: Callable[[MissionInfo], Clock] | None = None):
        if node not in scenario.node_names():
            raise AutoPowerError(f"node {node!r} is not in scenario {scenario.name} "
                                 f"(nodes: {', '.join(scenario.node_names())})")
        if make_component is None or make_source is None:
            from autopower import chains

            make_component = make_component or chains.make_component
            make_source = make_source or chains.make_source
        self.node = node
        self.scenario = scenario
        self.bus = bus
        self.keys = keys
        self.platform = scenario.platform_of(node)
        self._make_component = make_component
        self._make_source = make_source
        self._clock_factory = clock_factory or (lambda m: VirtualClock(m.epoch_unix, m.speed))
        self.chains = {c.name: c for c in scenario.chains}
        self.stage_index = {s.name: (c, i) for c in scenario.chains for i, s in enumerate(c.stages)}

        self.mission: MissionInfo | None = None
        self.clock: Clock | None = None
        self.meter: BatteryMeter | None = None
        self.plan: PlanUpdate | None = None
        self.network: Network | None = None
        self.hosted: dict[str, HostedStage] = {}
        self.orphans: dict[str, list[ChainFrame]] = {}
        self.sources: dict[str, SourceRunner] = {}
        self.source_totals: dict[str, SourceStats] = {}
        self.sinks: dict[str, SinkLedger] = {}
        self.last_output: dict[str, bytes] = {}
        self.alive: set[str] = set()
        self.errors: dict[str, int] = {}  # things that should not happen (garbage, lost frames)
        self.counters: dict[str, int] = {}  # things that happen (forwarded, missed periods)
        self.weights: dict[str, float] = {}
        self._early_control: list[bytes] = []
        # results whose sink is out of reach (the base station is cut off): kept, bounded,
        # and delivered when a route to it exists again
        self.held_outputs: deque[ChainFrame] = deque()
        self.held_dropped = 0
        # migration state with no route yet (an order overtook the plan that brings the route
        # back): sent as soon as a plan routes it; never dropped, or the stage would be lost
        self.parked_transfers: list[tuple[str, bytes, str]] = []
        self.on_output: Callable[[str, int, int, bytes], None] | None = None  # every result at this sink
        self.custody = Custody()
        self._next_custody_check = 0.0
        self.wall: Callable[[], float] = time.time  # custody's clock (a test team sets its manual one)
        # How a message for one node leaves: the process replaces it with its `Relayer.send`
        # so that a node out of direct sight is still reached through other agents.
        self.send_to: Callable[[str, str, bytes], object] = lambda dest, key, payload: self.bus.publish(key, payload)

    # ---- small helpers -----------------------------------------------------------------------
    def now(self) -> float:
        return self.clock.now() if self.clock else 0.0

    def count(self, what: str, detail: str = "", level: int = logging.WARNING) -> None:
        n = self.errors.get(what, 0) + 1
        self.errors[what] = n
        if n <= 5 or n % 1000 == 0:  # a flood of garbage must not flood the log
            log.log(level, "%s: %s (%d so far)%s", self.node, what, n, f": {detail}" if detail else "")

    def tally(self, what: str, n: int = 1) -> None:
        self.counters[what] = self.counters.get(what, 0) + n

    @property
    def started(self) -> bool:
        return self.mission is not None

    # ---- plan --------------------------------------------------------------------------------
    def on_plan(self, plan: PlanUpdate) -> None:
        if self.plan is not None and plan.epoch <= self.plan.epoch:
            return  # old or repeated
        if plan.mission.scenario != self.scenario.name:
            self.count("foreign-plan", f"plan for scenario {plan.mission.scenario!r}")
            return
        if self.mission is None:
            self.mission = plan.mission
            self.clock = self._clock_factory(plan.mission)
            if not self.platform.mains and self.node not in plan.mission.energies_j:
                raise AutoPowerError(f"the mission gives no starting energy for {self.node}")
            self.meter = BatteryMeter(platform=self.platform, radios=self.scenario.radios,
                                      initial_j=plan.mission.energies_j.get(self.node),
                                      t0=max(0.0, self.clock.now()))
            self.weights = {c.name: flow_weight(c, plan.mission.accounting) for c in self.scenario.chains}
        self._set_plan(plan)
        # stages that have landed elsewhere: frames held here for them can go now
        for stage, frames in list(self.orphans.items()):
            host = plan.placement.get(stage)
            if host is not None and host != self.node:
                del self.orphans[stage]
                for frame in frames:
                    self.send_frame(frame, host)
        self._sync_sources()
        for chain in {hop[0] for hop in self.custody.hops} - set(plan.running):
            self.custody.forget_chain(chain)  # stopped: nobody will consume its frames
        parked, self.parked_transfers = self.parked_transfers, []
        for dest, body, chain in parked:
            self.send_routed(dest, body, len(body), 1.0, "migration", chain)
        self.flush_held_outputs()
        early, self._early_control = self._early_control, []
        for payload in early:
            self.on_control(payload)

    def _set_plan(self, plan: PlanUpdate) -> None:
        self.plan = plan
        nodes = self.scenario.node_names()
        links = [Link(a=l.a, b=l.b, medium=l.medium, group="runtime") for l in plan.links
                 if l.a in nodes and l.b in nodes and l.medium in self.scenario.radios]
        self.network = Network(nodes, self.scenario.basestation, links, "runtime")
        self.meter.set_media(self.network.media_of(self.node), self.now())

    def override_placement(self, placement: dict[str, str], unreachable: set[str]) -> None:
        """A placement agreed without the base station (a subgroup commit): same epoch, our view.

        Links to ``unreachable`` nodes leave the routing; the next plan from the base station
        (a higher epoch) replaces all of it.
        """
        if self.plan is None:
            return
        links = tuple(l for l in self.plan.links if l.a not in unreachable and l.b not in unreachable)
        self._set_plan(dataclasses.replace(self.plan, placement={**self.plan.placement, **placement}, links=links))
        for stage, frames in list(self.orphans.items()):
            host = self.plan.placement.get(stage)
            if host is not None and host != self.node:
                del self.orphans[stage]
                for frame in frames:
                    self.send_frame(frame, host)

    def hold_output(self, frame: ChainFrame) -> None:
        if len(self.held_outputs) >= HELD_OUTPUT_LIMIT:
            self.held_outputs.popleft()
            self.held_dropped += 1
            self.tally("held-outputs-dropped")
        self.held_outputs.append(frame)
        self.custody.mark(frame, None)  # not on the wire: no resend is due until it is
        if len(self.held_outputs) == 1:
            log.info("%s: the sink of %s is out of reach; holding its results here (at most %d, oldest "
                     "dropped) until it returns", self.node, frame.chain, HELD_OUTPUT_LIMIT)

    def flush_held_outputs(self) -> None:
        if not self.held_outputs or self.network is None:
            return
        held, self.held_outputs = self.held_outputs, deque()
        sent = 0
        for frame in held:
            sink = self.chains[frame.chain].sink
            if self.network.path(self.node, sink) is None:
                self.held_outputs.append(frame)
            else:
                self.send_frame(frame, sink)
                self.custody.mark(frame, self.wall())
                sent += 1
        if sent:
            log.info("%s: delivered %d held result(s)", self.node, sent)
            self.tally("held-outputs-delivered", sent)

    def _sync_sources(self) -> None:
        running = self.plan.running if self.plan else {}
        for name, runner in list(self.sources.items()):
            if running.get(name) != runner.run:
                self._retire_source(runner)
        for name, run in running.items():
            chain = self.chains.get(name)
            if chain is None or chain.source != self.node or name in self.sources:
                continue
            try:
                source = self._make_source(chain.stages[0].component, chain.source, chain_seed(self.scenario, chain))
            except Exception as exc:  # a broken component type must not take the agent down
                self.count("source-failed", f"{name}: {exc}", logging.ERROR)
                continue
            period = chain.period_s
            before = self.source_totals.get(name)
            self.sources[name] = SourceRunner(chain=chain, source=source, run=run,
                                              next_t=math.ceil(self.now() / period - 1e-9) * period,
                                              produced_total=before.produced_total if before else 0)

    def _retire_source(self, runner: SourceRunner) -> None:
        del self.sources[runner.chain.name]
        self.source_totals[runner.chain.name] = self.source_stats(runner)

    def source_stats(self, runner: SourceRunner) -> SourceStats:
        return SourceStats(run=runner.run, produced=runner.seq, missed=runner.missed,
                           produced_total=runner.produced_total)

    # ---- timers --------------------------------------------------------------------------------
    def next_deadline(self) -> float | None:
        """Virtual time of the next source tick (None: nothing scheduled)."""
        return min((r.next_t for r in self.sources.values()), default=None)

    def on_timer(self) -> None:
        wall = self.wall()
        if wall >= self._next_custody_check:
            self._acknowledge(self.node, wall, self.consumed())  # what we consumed ourselves
            self.resend_lost(wall)
        now = self.now()
        for runner in list(self.sources.values()):
            if runner.next_t > now:
                continue
            period = runner.chain.period_s
            late = int((now - runner.next_t) // period)
            if late > 0:  # never burst to catch up: a real camera would have dropped them too
                runner.missed += late
                runner.next_t += late * period
                self.tally("missed-periods", late)
                log.info("%s: source %s is %d period(s) late; skipped them", self.node, runner.chain.name, late)
            self._produce(runner, runner.next_t)
            runner.next_t += period

    def _produce(self, runner: SourceRunner, t_tick: float) -> None:
        chain = runner.chain
        try:
            data = runner.source.produce(runner.seq)
            payload = pad(data, chain.message_bytes[0], f"{chain.name} source")
        except Exception as exc:
            self.count("source-error", f"{chain.name}: {exc}", logging.ERROR)
            return
        host = self.plan.placement.get(chain.stages[0].name)
        if host is None:
            self.count("unplaced-stage", f"{chain.stages[0].name} has no host")
            return
        frame = ChainFrame(chain=chain.name, run=runner.run, seq=runner.seq, target=0, t_virtual=t_tick,
                           t_unix=time.time(), payload_len=len(data), payload=payload)
        runner.seq += 1
        runner.produced_total += 1
        self.emit(frame, host)

    # ---- sending -----------------------------------------------------------------------------
    def emit(self, frame: ChainFrame, dest: str) -> None:
        """Send a frame this node produced, keeping it until its consumer acknowledges it."""
        frame = dataclasses.replace(frame, floor=self.custody.floor(frame.chain, frame.target, frame.run, frame.seq))
        self.custody.keep(frame, self.wall())
        self.send_frame(frame, dest)

    def send_frame(self, frame: ChainFrame, dest: str, forwards: int = 0, purpose: str = "chain") -> None:
        if dest == self.node:
            self.deliver_frame(frame, forwards)
            return
        chain = self.chains[frame.chain]
        self.send_routed(dest, encode(frame), chain.message_bytes[frame.target], self.weights[chain.name],
                         purpose, chain.name)

    def send_routed(self, dest: str, body: bytes, charge_bytes: int, weight: float, purpose: str,
                    chain: str) -> bool:
        path = self.network.path(self.node, dest) if self.network else None
        if path is None:
            if purpose == "migration":
                self.parked_transfers.append((dest, body, chain))
                log.info("%s: no route to %s yet for %s's state; parked until a plan routes it", self.node, dest,
                         chain)
                return False
            if purpose == "chain" and chain in self.chains and dest == self.chains[chain].sink:
                try:
                    frame = decode(body, ChainFrame)
                except ProtocolError:
                    frame = None
                if frame is not None and frame.target == len(self.chains[chain].stages):
                    self.hold_output(frame)
                    return False
            self.count("unroutable", f"no route from {self.node} to {dest}")
            return False
        media = tuple(self.network.medium_between(u, v) for u, v in zip(path, path[1:]))
        packet = Packet(path=tuple(path), media=media, hop=1, charge_bytes=charge_bytes, weight=weight,
                        purpose=purpose, chain=chain, body=body)
        self.meter.charge_radio("send", media[0], charge_bytes, weight, self.now(), purpose)
        self.send_to(path[1], self.keys.node_data(path[1]), encode(packet))
        return True

    # ---- receiving -----------------------------------------------------------------------------
    def on_data(self, payload: bytes) -> None:
        packet = decode(payload, Packet)
        if not self.started:
            self.count("data-before-mission")
            return
        if packet.path[packet.hop] != self.node:
            self.count("misaddressed", f"packet for {packet.path[packet.hop]}")
            return
        for medium in packet.media:
            if medium not in self.scenario.radios:
                raise ProtocolError(f"packet names unknown medium {medium!r}")
        now = self.now()
        self.meter.charge_radio("receive", packet.media[packet.hop - 1], packet.charge_bytes, packet.weight, now,
                                packet.purpose)
        if packet.hop < len(packet.path) - 1:  # a relay: pass it on, untouched
            nxt = Packet(path=packet.path, media=packet.media, hop=packet.hop + 1,
                         charge_bytes=packet.charge_bytes, weight=packet.weight, purpose=packet.purpose,
                         chain=packet.chain, body=packet.body)
            self.meter.charge_radio("send", packet.media[packet.hop], packet.charge_bytes, packet.weight, now,
                                    packet.purpose)
            self.send_to(packet.path[packet.hop + 1], self.keys.node_data(packet.path[packet.hop + 1]), encode(nxt))
            self.tally("forwarded")
            return
        body = decode(packet.body, (ChainFrame, StateTransfer))
        if isinstance(body, StateTransfer):
            self.on_state(body)
        else:
            self.deliver_frame(body)

    def deliver_frame(self, frame: ChainFrame, forwards: int = 0) -> None:
        chain = self.chains.get(frame.chain)
        if chain is None or frame.target > len(chain.stages):
            self.count("unknown-chain", f"{frame.chain} target {frame.target}")
            return
        if frame.target == len(chain.stages):
            self._sink(chain, frame)
            return
        stage = chain.stages[frame.target]
        hosted = self.hosted.get(stage.name)
        if hosted is None:
            host = self.plan.placement.get(stage.name) if self.plan else None
            if host is not None and host != self.node and forwards < MAX_FORWARDS:
                self.tally("rerouted")
                self.send_frame(frame, host, forwards + 1)
            elif host is None and (self.plan is None or frame.chain not in self.plan.running):
                self.count("inactive-chain", f"{frame.chain} seq {frame.seq} arrived after its chain stopped",
                           logging.INFO)
            else:
                held = self.orphans.setdefault(stage.name, [])
                if len(held) >= ORPHAN_LIMIT:
                    self.count("orphan-overflow", f"{stage.name}: dropped seq {frame.seq}", logging.ERROR)
                    return
                held.append(frame)
            return
        if hosted.lifecycle is Lifecycle.STARTING:
            hosted.buffer.append(frame)
        elif hosted.lifecycle is Lifecycle.MIGRATED:
            if forwards >= MAX_FORWARDS:
                self.orphans.setdefault(stage.name, []).append(frame)
                return
            self.tally("pointer-forwarded")
            self.send_frame(frame, hosted.forward_to, forwards + 1)
        else:
            self._admit(hosted, frame)

    def _admit(self, hosted: HostedStage, frame: ChainFrame) -> None:
        if frame.run != hosted.run:
            self.count("stale-run", f"{hosted.stage.name}: frame of run {frame.run}, stage runs {hosted.run}",
                       logging.INFO)
            return
        before, redundant, skipped = hosted.gate.duplicates, hosted.gate.redundant, hosted.gate.skipped
        for ready in hosted.gate.offer(frame.seq, frame, frame.floor, resent=frame.attempt > 0, now=self.wall()):
            self._run(hosted, ready)
        if hosted.gate.duplicates != before:
            self.count("duplicate-input", f"{hosted.stage.name} seq {frame.seq}", logging.INFO)
        if hosted.gate.redundant != redundant:
            self.tally("redundant-input")  # a resent copy of an input that was only late: dropped, as designed
        if hosted.gate.skipped != skipped:
            self.count("inputs-given-up", f"{hosted.stage.name}: {hosted.gate.skipped - skipped} input(s) before "
                       f"seq {hosted.gate.next_seq} never arrived", logging.ERROR)

    def _run(self, hosted: HostedStage, frame: ChainFrame) -> None:
        chain, index = hosted.chain, hosted.index
        started = time.perf_counter()
        try:
            output = hosted.component.run(frame.data())
        except Exception as exc:  # a bad input must not kill the agent
            self.count("run-error", f"{hosted.stage.name} seq {frame.seq}: {exc}", logging.ERROR)
            return
        hosted.compute_s += time.perf_counter() - started
        hosted.runs += 1
        # a stage started without state recomputes what its lost predecessor may have sent already:
        # an overhead of the failover, not the plan's steady work
        recomputed = hosted.gate.catch_up_below is not None and frame.seq < hosted.gate.catch_up_below
        latency = self.scenario.components[hosted.stage.component].latency_s[self.platform.name]
        self.meter.charge_run(latency, self.now(), "recovery" if recomputed else "chain")
        target = index + 1
        try:
            payload = pad(output, chain.message_bytes[target], f"{hosted.stage.name} output")
        except ProtocolError as exc:
            self.count("oversize-output", str(exc), logging.ERROR)
            return
        out = ChainFrame(chain=chain.name, run=frame.run, seq=frame.seq, target=target, t_virtual=frame.t_virtual,
                         t_unix=frame.t_unix, payload_len=len(output), payload=payload, attempt=int(recomputed))
        dest = chain.sink if target == len(chain.stages) else self.plan.placement.get(chain.stages[target].name)
        if dest is None:
            self.count("unplaced-stage", f"{chain.stages[target].name} has no host")
            return
        self.emit(out, dest)

    def _sink(self, chain: Chain, frame: ChainFrame) -> None:
        if chain.sink != self.node:
            self.count("wrong-sink", f"{chain.name} output reached {self.node}")
            return
        ledger = self.sinks.setdefault(chain.name, SinkLedger())
        latency_ms = (time.time() - frame.t_unix) * 1000.0
        redundant = ledger.redundant_total
        if not ledger.record(frame.run, frame.seq, latency_ms, frame.data(), frame.attempt):
            if ledger.redundant_total != redundant:
                self.tally("redundant-output")  # a resent copy of what arrived late: dropped, as designed
                return
            self.count("duplicate-output" if frame.run >= ledger.run else "stale-output",
                       f"{chain.name} run {frame.run} seq {frame.seq}", logging.ERROR)
        elif frame.attempt:
            self.tally("recovered-outputs")  # lost in flight, delivered by a resend
        self.last_output[chain.name] = frame.data()
        if self.on_output is not None:
            self.on_output(chain.name, frame.run, frame.seq, frame.data())

    # ---- control: hosting and migration -----------------------------------------------------------
    def on_control(self, payload: bytes) -> None:
        msg = decode(payload, CONTROL_MESSAGES)
        if not self.started:
            # The plan that starts the mission may arrive after the first orders (other key).
            if len(self._early_control) < 1000:
                self._early_control.append(payload)
            return
        if msg.stage not in self.stage_index:
            self.count("unknown-stage", msg.stage)
            return
        if isinstance(msg, Assign):
            self.on_assign(msg)
        elif isinstance(msg, Prepare):
            self.on_prepare(msg)
        elif isinstance(msg, MigrateOut):
            self.on_migrate_out(msg)
        elif isinstance(msg, Release):
            self.on_release(msg)

    def _new_component(self, chain: Chain, stage: Stage):
        return self._make_component(stage.component, chain.source, chain_seed(self.scenario, chain))

    def _reply(self, msg) -> None:
        self.send_to(self.scenario.basestation, self.keys.inbox, encode(msg))

    def on_assign(self, msg: Assign) -> None:
        chain, index = self.stage_index[msg.stage]
        stage = chain.stages[index]
        current = self.hosted.get(msg.stage)
        if current and current.generation > msg.generation:
            return
        try:
            component = self._new_component(chain, stage)
        except Exception as exc:
            self.count("component-failed", f"{msg.stage}: {exc}", logging.ERROR)
            return
        hosted = HostedStage(stage=stage, chain=chain, index=index, generation=msg.generation,
                             lifecycle=Lifecycle.RUNNING, run=msg.run, component=component,
                             gate=SequenceGate(next_seq=msg.resume_seq))
        held = (current.buffer if current else []) + self.orphans.pop(msg.stage, [])
        self.hosted[msg.stage] = hosted
        self._reply(StageReady(stage=msg.stage, generation=msg.generation, node=self.node, imported_state=False,
                               resume_seq=msg.resume_seq, downtime_ms=0.0, buffered=len(held)))
        for frame in sorted(held, key=lambda f: f.seq):
            self._admit(hosted, frame)

    def on_prepare(self, msg: Prepare) -> None:
        chain, index = self.stage_index[msg.stage]
        current = self.hosted.get(msg.stage)
        if current is not None and current.lifecycle in (Lifecycle.RUNNING, Lifecycle.DRAINING):
            self.count("prepare-while-running", msg.stage, logging.ERROR)
            return
        hosted = HostedStage(stage=chain.stages[index], chain=chain, index=index, generation=msg.generation,
                             lifecycle=Lifecycle.STARTING)
        hosted.buffer = self.orphans.pop(msg.stage, [])
        if current is not None and current.lifecycle is Lifecycle.STARTING:
            hosted.buffer = current.buffer + hosted.buffer
        self.hosted[msg.stage] = hosted
        self._reply(Prepared(stage=msg.stage, generation=msg.generation, node=self.node))

    def on_migrate_out(self, msg: MigrateOut) -> None:
        hosted = self.hosted.get(msg.stage)
        if hosted is None or hosted.lifecycle is not Lifecycle.RUNNING:
            self.count("migrate-not-running", f"{msg.stage} is {hosted.lifecycle.value if hosted else 'absent'}",
                       logging.ERROR)
            return
        # The current run has finished: runs are synchronous in this loop.
        hosted.lifecycle = Lifecycle.DRAINING
        try:
            state = hosted.component.export_state()
        except Exception as exc:
            self.count("export-failed", f"{msg.stage}: {exc}", logging.ERROR)
            hosted.lifecycle = Lifecycle.RUNNING
            return
        pending = tuple(hosted.gate.take_pending())
        transfer = StateTransfer(stage=msg.stage, generation=msg.generation, chain=hosted.chain.name,
                                 run=hosted.run, state=state, next_seq=hosted.gate.next_seq, pending=pending,
                                 t_export_unix=time.time(), from_node=self.node,
                                 resent=hosted.gate.recent_resends())
        body = encode(transfer)
        hosted.lifecycle = Lifecycle.MIGRATED
        hosted.forward_to = msg.to_node
        hosted.component = None
        # The state crosses the network like any message: routed, forwarded, charged (real bytes).
        if msg.to_node == self.node:
            self.on_state(transfer)
        else:
            self.send_routed(msg.to_node, body, len(body), 1.0, "migration", hosted.chain.name)

    def on_state(self, msg: StateTransfer) -> None:
        if msg.stage not in self.stage_index:
            self.count("unknown-stage", msg.stage)
            return
        chain, index = self.stage_index[msg.stage]
        stage = chain.stages[index]
        current = self.hosted.get(msg.stage)
        if current is not None and current.generation > msg.generation:
            self.count("stale-state", f"{msg.stage} generation {msg.generation}")
            return
        try:
            component = self._new_component(chain, stage)
            component.import_state(msg.state)
        except Exception as exc:
            self.count("import-failed", f"{msg.stage}: {exc}", logging.ERROR)
            return
        held = list(msg.pending)
        if current is not None and current.lifecycle is Lifecycle.STARTING:
            held += current.buffer
        held += self.orphans.pop(msg.stage, [])
        hosted = HostedStage(stage=stage, chain=chain, index=index, generation=msg.generation,
                             lifecycle=Lifecycle.RUNNING, run=msg.run, component=component,
                             gate=SequenceGate(next_seq=msg.next_seq))
        hosted.gate.resent.extend(msg.resent)  # late originals of these are redundant here too
        self.hosted[msg.stage] = hosted
        self._reply(StageReady(stage=msg.stage, generation=msg.generation, node=self.node, imported_state=True,
                               resume_seq=msg.next_seq, downtime_ms=max(0.0, (time.time() - msg.t_export_unix) * 1e3),
                               buffered=len(held)))
        for frame in sorted(held, key=lambda f: f.seq):
            self._admit(hosted, frame)

    def on_release(self, msg: Release) -> None:
        hosted = self.hosted.get(msg.stage)
        if hosted is not None and hosted.generation <= msg.generation:
            del self.hosted[msg.stage]
        self.orphans.pop(msg.stage, None)

    def on_peer_status(self, status: NodeStatus) -> None:
        """Another node's status: what it consumed acknowledges what we sent it."""
        if status.node == self.node:
            return
        now = self.wall()
        # never newer than its arrival: a consumer whose clock runs ahead must not make
        # frames still in flight look lost
        self._acknowledge(status.node, min(status.t_unix, now), status.consumed)
        self.resend_lost(now)

    def consumed(self) -> dict[str, Consumed]:
        """What this node's running stages and sinks have taken in, per hop."""
        out = {}
        for hosted in self.hosted.values():
            if hosted.lifecycle is Lifecycle.RUNNING:
                report = hosted.gate.report(hosted.run, hosted.generation)
                if report is not None:
                    out[hop_key(hosted.chain.name, hosted.index)] = report
        for name, ledger in self.sinks.items():
            report = ledger.report()
            if report is not None and name in self.chains:
                out[hop_key(name, len(self.chains[name].stages))] = report
        return out

    def _consumer_of(self, frame: ChainFrame) -> str | None:
        """Where the plan says the frame's consumer runs now (the next stage's host, or the sink)."""
        chain = self.chains[frame.chain]
        if frame.target >= len(chain.stages):
            return chain.sink
        return self.plan.placement.get(chain.stages[frame.target].name) if self.plan else None

    def producers(self) -> set[str]:
        """The nodes that send us frames now (a source or the previous stage's host): our status
        acknowledges their frames, so it must reach them even when they are out of sight."""
        placement = self.plan.placement if self.plan else {}
        out = set()
        for hosted in self.hosted.values():
            chain, index = hosted.chain, hosted.index
            out.add(chain.source if index == 0 else placement.get(chain.stages[index - 1].name))
        for name in self.sinks:
            chain = self.chains.get(name)
            if chain is not None and chain.stages:
                out.add(placement.get(chain.stages[-1].name))
        return out - {None, self.node}

    def _acknowledge(self, node: str, t_unix: float, consumed: dict[str, Consumed]) -> None:
        for key, report in consumed.items():
            hop = parse_hop_key(key)
            if hop is None or hop[0] not in self.chains:
                self.count("garbled", f"{node} reports an unknown hop {key!r}")
                continue
            self.custody.on_report(hop[0], hop[1], Report(node=node, t_unix=t_unix, consumed=report))

    def resend_lost(self, now: float) -> None:
        """Resend what a consumer reported missing well after it was sent (throttled)."""
        if now < self._next_custody_check or self.network is None:
            return
        self._next_custody_check = now + 0.1
        for node, held in self.custody.due(now):
            if node != self._consumer_of(held.frame):
                continue  # the stage is moving: wait for its new host's report (it stays due)
            if node != self.node and self.network.path(self.node, node) is None:
                continue  # no route yet: it stays due
            frame = self.custody.resend(held, now)
            self.tally("resent-frames")
            if frame.attempt == 1:
                log.info("%s: %s seq %d to stage %d was lost on the way to %s; resending", self.node, frame.chain,
                         frame.seq, frame.target, node)
            self.send_frame(frame, node, purpose="recovery")  # metered apart: not the plan's steady traffic

    # ---- liveliness ----------------------------------------------------------------------------------
    def on_liveliness(self, node: str, alive: bool) -> None:
        if alive:
            self.alive.add(node)
        else:
            self.alive.discard(node)

    # ---- status ----------------------------------------------------------------------------------------
    def status(self, window_s: float, queue_depth: int = 0) -> NodeStatus:
        now = self.now()
        power, utilisation = self.meter.window(now, window_s) if self.meter else ({}, 0.0)
        # Every other node, not only today's neighbours: a link that went down must be seen coming back.
        others = [n for n in self.scenario.node_names() if n != self.node]
        sources = {n: self.source_stats(r) for n, r in self.sources.items()}
        for name, stats in self.source_totals.items():
            sources.setdefault(name, stats)
        return NodeStatus(
            node=self.node, t_virtual=now, t_unix=self.wall(), plan_epoch=self.plan.epoch if self.plan else -1,
            initial_j=self.meter.initial_j if self.meter else None,
            battery_j=self.meter.battery_j if self.meter else None,
            energy_j=dict(self.meter.energy_j) if self.meter else {},
            power_w=power, cpu_utilisation=utilisation,
            hosted={n: h.lifecycle.value for n, h in self.hosted.items()},
            sources=sources,
            sinks={n: SinkStats(run=l.run, received=l.received, duplicates=l.duplicates, contiguous=l.contiguous,
                                max_seq=l.max_seq, stale=l.stale, latency_ms_p50=l.latency_ms_p50,
                                latency_ms_max=l.latency_ms_max, received_total=l.received_total,
                                duplicates_total=l.duplicates_total, digest=l.digest,
                                redundant_total=l.redundant_total)
                   for n, l in self.sinks.items()},
            links={n: n in self.alive for n in others},
            runs={n: h.runs for n, h in self.hosted.items() if h.runs},
            compute_ms={n: h.compute_s / h.runs * 1e3 for n, h in self.hosted.items() if h.runs},
            queue_depth=queue_depth, errors=dict(self.errors),
            counters={**self.counters, "held-outputs": len(self.held_outputs), **self.custody.stats()},
            depleted=bool(self.meter and self.meter.depleted),
            consumed=self.consumed(),
        )

    # ---- dispatch -----------------------------------------------------------------------------------------
    def on_message(self, key: str, payload: bytes) -> bool:
        """Handle a message on one of this node's keys; False if the key is not ours.

        Garbage (ProtocolError) is counted, logged and dropped; it never propagates.
        """
        try:
            if key == self.keys.node_data(self.node):
                self.on_data(payload)
            elif key == self.keys.node_control(self.node):
                self.on_control(payload)
            elif key == self.keys.plan:
                self.on_plan(decode(payload, PlanUpdate))
            else:
                return False
        except ProtocolError as exc:
            self.count("garbled", f"on {key}: {exc}")
        return True
