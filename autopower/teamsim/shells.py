"""The processes around the real cores, as the simulator runs them: a robot's agent, the base station.

Each shell does what its process does with events (`autopower.agent.process.Agent`,
`autopower.basestation.process.BaseStation`), in simulated time: it hands messages and sight
changes to its `NodeRuntime` (and the base station's `Coordinator`), relays through the real
`Relayer`, builds its status every status period and publishes it when its cadence says so
(`StatusCadence`: at once when something in it changed, else a slow heartbeat; what flowed is
acknowledged every period, and kept first: the sink's notes, the resume state, the held results),
and wakes for its next deadline. After each
event and each wake it takes one turn of its loop. The stores are the real ones, in the run's
folder: a restarted process reads what the killed one wrote.

Not here (the processes' own logic, outside the cores until the node-core refactor moves it in):
subgroup rounds, the silence detector, a restarted robot going on alone; the loop that sleeps
through the rest period (the sim builds a status every period and the cadence holds it back).
"""

from __future__ import annotations

import logging
import math

from autopower.agent.resume import ResumeFile
from autopower.basestation.coordinator import Coordinator
from autopower.basestation.peer_view import PeerViews
from autopower.errors import ProtocolError
from autopower.node.held_store import HeldStore
from autopower.node.peer_watch import PeerWatch, WatchSettings
from autopower.node.ports import NodePorts, NodeStores, SinkListener
from autopower.node.runtime import NodeRuntime
from autopower.node.sink_store import SinkStore
from autopower.node.subgroup_rounds import RoundSettings, SubgroupRounds
from autopower.protocol import (
    NodeStatus,
    PeerStatus,
    PlanChange,
    PlanUpdate,
    StatusDelta,
    decode,
    encode,
)
from autopower.protocol.access import carries_peer_status, status_problem
from autopower.protocol.statuses import StatusAssembler, StatusEncoder
from autopower.runtime.cadence import StatusCadence
from autopower.runtime.relay import Relayer
from autopower.teamsim.bus import SimBus
from autopower.teamsim.scheduler import EPOCH_UNIX

SUSPECT_SETTLE_S = 0.2  # `BaseStationConfig.suspect_settle_s`
MIN_WAKE_S = 0.001  # a deadline already past wakes the loop this much later (never at the same instant)


class Shell:
    """What both processes share: the bus, the relayer, the loop's turns, freezes, the outputs kept.
    ``world`` is the run's `autopower.teamsim.team.World`."""

    def __init__(self, world, node: str):
        self.world = world
        self.node = node
        self.keys = world.keys
        self.up = False
        self._wake_token = 0
        self._wake_t = math.inf
        self.pending: list[tuple[str, int, int, bytes, float, int]] = []  # outputs not yet committed
        self.bus: SimBus | None = None
        self.rt: NodeRuntime | None = None
        self.relayer: Relayer | None = None
        self.next_status = 0.0
        self.cadence: StatusCadence | None = None
        self.status_encoder: StatusEncoder | None = None

    # ---- life ---------------------------------------------------------------------------------
    def start(self) -> None:
        w = self.world
        self.up = True
        self.bus = SimBus(self.node, w.network, w.trace, self._after_event)
        self.relayer = Relayer(node=self.node, bus=self.bus, keys=self.keys, count=self._count, access=w.access)
        w.process_starts += 1  # its id: unique and as long on the wire as a drawn one (`new_process_id`)
        self.rt = NodeRuntime(node=self.node, scenario=w.scenario, bus=self.bus, keys=self.keys,
                              make_component=w.make_component, make_source=w.make_source,
                              clock_factory=w.clock_for, wall=w.scheduler.wall, perf=w.scheduler.wall,
                              ports=NodePorts(send_to=self.relayer.send), stores=self.stores(),
                              process=1 << 62 | w.process_starts)
        self.rt.listen(SinkListener(
            output=self._output, held_dropped=self._dropped_by_budget,
            died_with_process=lambda c, r, s: w.ledger.let_go((c, r, s), "died-with-process"),
            # a fan-in chain's input is made by a join step: that is its production
            joined=lambda c, r, s: w.ledger.on_produced((c, r, s), w.scheduler.now, w.trace.events)))
        self.cadence = StatusCadence(w.status_period_s, w.status_rest_period_s)  # a new process's: it says all at once
        self.status_encoder = StatusEncoder()  # a new process's: its first status goes whole
        self.build()
        self.next_status = w.scheduler.wall()
        self.turn()

    def _count(self, what: str, detail: str = "", level: int = logging.WARNING) -> None:
        self.rt.count(what, detail, level)  # the relayer's errors (it is built before the runtime)

    def stores(self) -> NodeStores:
        """What this process keeps on disk across a crash (its subclass says)."""
        raise NotImplementedError

    def build(self) -> None:
        """The process's own parts, subscriptions and token (after the runtime exists)."""

    def _dropped_by_budget(self, chain: str, run: int, seq: int, why: str) -> None:
        """A result the node let go from its hold: beyond its hold budget, in the oracle's budget only
        if the node's kept results and this one (its payload is its chain's declared size) exceed it;
        superseded, only if its chain keeps the latest and the node holds a newer result of the run."""
        w, custody = self.world, self.rt.custody
        if why == "superseded":
            newer = any(f.chain == chain and f.run == run and f.seq > seq for f in self.rt.holds.held.values())
            if w.scenario.chain(chain).keep != "latest" or not newer:
                w.ledger.violate("exactly-once", f"{self.node} let {chain} run {run} seq {seq} go as superseded "
                                 f"(keep = {w.scenario.chain(chain).keep!r}, a newer one held: {newer})",
                                 w.scheduler.now, w.trace.events)
                return
            w.ledger.let_go((chain, run, seq), "superseded")
            return
        size = w.scenario.chain(chain).message_bytes[-1]
        if custody.result_bytes + size <= custody.hold_budget_bytes:
            w.ledger.violate("exactly-once", f"{self.node} dropped {chain} run {run} seq {seq} for its hold budget "
                             f"with {custody.result_bytes} of {custody.hold_budget_bytes} bytes kept",
                             w.scheduler.now, w.trace.events)
            return
        w.ledger.let_go((chain, run, seq), "hold-budget")

    def crash(self) -> None:
        """Killed: nothing more is handled; what was not committed dies with it."""
        if not self.up:
            return
        self.up = False
        self.pending.clear()
        self.bus.close()
        self.rt.close_stores(commit_sinks=False)  # a kill writes nothing more

    def freeze(self) -> None:
        self.bus.freeze()

    def thaw(self) -> None:
        self.bus.thaw()
        self.turn()

    @property
    def frozen(self) -> bool:
        return self.bus is not None and self.bus.frozen

    # ---- the loop ------------------------------------------------------------------------------
    def _after_event(self) -> None:
        if self.up and not self.frozen:
            self.turn()

    def turn(self) -> None:
        if not self.up or self.frozen:
            return
        try:
            wake = self._turn()
        except Exception as exc:  # the process logs it and goes on; the simulator calls it a bug
            self.world.internal_error(self.node, exc)
            wake = self.world.scheduler.wall() + self.world.status_period_s
        if self.up:
            self._schedule(max(wake, self.world.scheduler.wall() + MIN_WAKE_S))

    def _turn(self) -> float:
        """One turn of the process's loop; returns when (wall) it must wake next."""
        raise NotImplementedError

    def _schedule(self, wall: float) -> None:
        if wall == self._wake_t:
            return
        self._wake_token += 1
        self._wake_t = wall
        self.world.scheduler.at(wall - EPOCH_UNIX, self._wake, self._wake_token)

    def _wake(self, token: int) -> None:
        if token != self._wake_token:
            return
        self._wake_t = math.inf
        self.turn()

    def guarded(self, handler, *args) -> None:
        """Handle one event as the process does: an exception is logged, counted and survived."""
        if not self.up:
            return
        try:
            handler(*args)
        except Exception as exc:
            self.world.internal_error(self.node, exc)

    # ---- outputs --------------------------------------------------------------------------------------
    def _output(self, chain: str, run: int, seq: int, data: bytes) -> None:
        w = self.world
        self.pending.append((chain, run, seq, data, w.scheduler.now, w.trace.events))

    def commit_outputs(self) -> None:
        """The sink's notes are written: what it handed on is delivered (a recording keeps it now)."""
        pending, self.pending = self.pending, []
        for chain, run, seq, data, t, event in pending:
            self.world.ledger.on_delivered((chain, run, seq), t, event, data, self.world.expected(chain, seq))

    def _status_sent(self, status: NodeStatus) -> None:
        self.world.status_sent(self, status)


class RobotShell(Shell):
    """A robot's agent: its stores, its statuses to every peer, superseded instances stopped."""

    def stores(self) -> NodeStores:
        robot = self.node
        folder = self.world.store_dir / robot  # its own, as an agent's state directory on its robot
        folder.mkdir(exist_ok=True)
        self.resume = ResumeFile(folder / f"{robot}.json")
        return NodeStores(held_store=HeldStore(folder / f"{robot}.held"),
                          sink_store=SinkStore(folder / f"{robot}.sinks.json"),
                          resume_from=self.resume.load(), on_produced=self._produced)

    def build(self) -> None:
        w, rt, robot, keys = self.world, self.rt, self.node, self.keys
        self.statuses: dict[str, PeerStatus] = {}  # the peers' last (`PeerStatus`)
        self.watch = PeerWatch(WatchSettings(own_period_s=w.status_period_s, lease_s=w.network.lease_s))
        self.rounds = SubgroupRounds(
            runtime=rt, scenario=w.scenario, bus=self.bus, keys=keys, wall=w.scheduler.wall,
            reachable=self.relayer.reachable, reached=self.relayer.reached, statuses=self.statuses,
            settings=RoundSettings(enabled=w.subgroup, status_period_s=w.status_period_s),
            publish_status=self.publish_status, save_resume=self.save_resume, started_unix=w.scheduler.wall(),
            relay=self.relayer.send_beyond_sight)
        self.bus.subscribe(keys.node_data(robot), lambda k, p: self.guarded(self._received, k, p))
        # (not the plan key: each robot gets its plans on its control key, `PlanDelivery`)
        for key in (keys.node_control(robot), keys.addressed_to(robot), keys.node_relay(robot), keys.peer_all,
                    keys.subgroup):
            self.bus.subscribe(key, lambda k, p: self.guarded(self._received, k, p))
        self.bus.watch_liveliness(keys.alive_all, lambda k, alive: self.guarded(self._liveliness, k, alive))
        self.bus.declare_token(keys.alive(robot))

    def crash(self) -> None:
        if self.up:
            super().crash()
            self.resume.close()

    def _produced(self, runner) -> None:
        w = self.world
        self.resume.note_source(runner.chain.name, runner.run, runner.seq, runner.missed, runner.produced_total,
                                runner.missed_stopped)
        w.ledger.on_produced((runner.chain.name, runner.run, runner.seq - 1), w.scheduler.now, w.trace.events)

    def _liveliness(self, key: str, alive: bool) -> None:
        node = self.keys.node_of_alive(key)
        if node is not None and node != self.node:
            change = self.watch.on_token(node, alive)
            if change is not None:
                self._sight(node, change)

    def _sight(self, node: str, visible: bool) -> None:
        """``node`` came into direct sight or went out of it (its token, or its statuses' silence)."""
        self.rt.on_liveliness(node, visible)
        self.relayer.on_liveliness(node, visible)
        if not visible:
            self.rounds.on_member_lost(node)
        self.publish_status()  # the base station tells a dead robot from a cut link by what the others see

    def _received(self, key: str, payload: bytes) -> None:
        rt, keys = self.rt, self.keys
        relayed = key == keys.node_relay(self.node)
        inner = self.relayer.unwrap(key, payload)
        if inner is None:
            return
        key, payload = inner
        if key == keys.subgroup:
            self.rounds.on_message(payload)
            return
        if carries_peer_status(keys, key, payload, self.node):  # a robot's, or the base station's to us
            try:
                status = decode(payload, PeerStatus)
            except ProtocolError as exc:
                rt.count("garbled", f"on {key}: {exc}")
                return
            if status_problem(keys, key, status.node, status.t_unix, self.world.scheduler.wall()) is not None:
                rt.count("forged", key)
                return
            if status.node == self.node:
                return
            if not relayed and self.watch.on_status(status.node, status.next_status_s, self.world.scheduler.wall()):
                self._sight(status.node, True)  # before the duplicate check: a relayed copy may come first
            last = self.statuses.get(status.node)
            if last is not None and status.t_unix <= last.t_unix:
                return
            base = self.world.scenario.basestation
            base_was_reachable = self.relayer.reachable(base)
            self.relayer.on_status(status)
            if not relayed:
                self.relayer.on_direct(status.node)
            self.statuses[status.node] = status
            rt.on_peer_status(status)
            # as the agent: a base station asking, or back within reach through a peer, hears us at once, whole
            heard_again = rt.sight.take_status_asked() or (not base_was_reachable and self.relayer.reachable(base)) \
                or status.send_whole
            if heard_again:
                self.status_encoder.refresh()
            if rt.hosting.yield_to_newer(status) or heard_again:
                self.publish_status()
            return
        order, model_w = rt.plan_view.order, rt.plan_view.model_w
        if not rt.on_message(key, payload):
            rt.count("unexpected-key", key)
        elif rt.plan_view.order != order or rt.plan_view.model_w != model_w:
            self.publish_status()  # a new plan acknowledged at once; a stage that left, said at once

    def publish_status(self, save_resume: bool = False, urgent: bool = True) -> None:
        """As the agent's (`Agent.publish_status`): the periodic one (not ``urgent``) held back when
        it says nothing new; what flowed acknowledged every period all the same."""
        rt, keys, w = self.rt, self.keys, self.world
        window = w.status_window_s * rt.clock.speed if rt.started else 0.0
        if self.watch.tokens_lost:  # peers a token that went took out of sight, as the agent counts them
            rt.counters["tokens-lost"] = self.watch.tokens_lost
        built = rt.status(window)
        status = self.cadence.due(built, w.scheduler.wall(), urgent=urgent)
        if status is None and rt.idle() and self.rounds.idle():
            self._status_sent(built)  # at rest: nothing new, nothing to acknowledge
            return
        if save_resume:
            self.save_resume()
        rt.commit_sinks()
        self.commit_outputs()
        if status is not None:  # (held back: only counts moved, the heartbeat waits)
            base = w.scenario.basestation
            for key, payload, dests in ((keys.status(self.node), self.status_encoder.encode(status), [base]),
                                        (keys.peer(self.node), encode(PeerStatus.of(status)),
                                         sorted(rt.acknowledging.producers() - {base}))):
                self.bus.publish(key, payload, reliable=False)
                self.relayer.send_beyond_sight(dests, key, payload, reliable=False)
        rt.acknowledging.send(self.relayer.reachable, built.queue_wait_s)
        self._status_sent(built)

    def save_resume(self) -> None:
        rt = self.rt
        rt.holds.settle_store()
        state = rt.resume_state()
        if state is not None:
            self.resume.save(state)

    def _turn(self) -> float:
        rt, s = self.rt, self.world.scheduler
        for node, _ in self.watch.check(s.wall()):
            rt.tally("silent-peers")
            self._sight(node, False)
        if rt.started:
            self.rounds.tick()
            rt.on_timer()
            rt.meter.advance(rt.now())
        now = s.wall()
        if now >= self.next_status:
            self.publish_status(save_resume=True, urgent=False)
            self.next_status = max(self.next_status + self.world.status_period_s, now)
        silent_at = self.watch.next_deadline()
        wake = min([self.next_status, *self.rounds.wake_times(now), *([silent_at + MIN_WAKE_S] if silent_at else [])])
        if rt.started and (t := rt.next_deadline()) is not None:
            wake = min(wake, rt.clock.wall_at(t))
        return wake


class BaseShell(Shell):
    """The base station: the coordinator and its own host; who is gone, or only cut off."""

    def __init__(self, world, node: str, number: int):
        super().__init__(world, node)
        self.number = number  # which start of a base station this is (0: the first)
        self.co: Coordinator | None = None
        self.plan_since: dict[tuple[int, int], float] = {}  # (incarnation, epoch) -> when first published

    def stores(self) -> NodeStores:
        folder = self.world.store_dir
        return NodeStores(sink_store=SinkStore(folder / "sinks.json"), held_store=HeldStore(folder / "basestation.held"))

    def build(self) -> None:
        w, keys, base = self.world, self.keys, self.node
        kept = w.base_state.get("incarnation")
        self.peer_views = PeerViews(w.scenario, self.keys)
        self.co = Coordinator(scenario=w.scenario, bus=self.bus, keys=keys, config=w.coordinator_config,
                                   wall_fn=w.scheduler.wall, leader=f"{base}:sim:{self.number}",
                                   incarnation=0 if kept is None else kept + 1, send_to=self.relayer.send,
                                   on_own_plan=self._own_plan)
        self.suspects: dict[str, float] = {}
        self.status_t: dict[str, float] = {}
        self.statuses_in = StatusAssembler()  # the others' statuses, whole again
        for key in (keys.node_data(base), keys.node_control(base), keys.addressed_to(base), keys.plan, keys.inbox,
                    keys.status_all, keys.node_relay(base)):
            self.bus.subscribe(key, lambda k, p: self.guarded(self._received, k, p))
        self.bus.watch_liveliness(keys.alive_all, lambda k, alive: self.guarded(self._liveliness, k, alive))
        self.bus.declare_token(keys.alive(base))

    def _own_plan(self, plan: PlanUpdate) -> None:
        self.plan_since.setdefault((plan.incarnation, plan.epoch), self.world.scheduler.now)
        try:
            self.rt.on_plan(plan)
        except Exception as exc:
            self.world.internal_error(self.node, exc)

    def operator(self, cmd):
        """An operator's command (None: this base station is down or frozen, the query fails)."""
        if not self.up or self.frozen or self.co is None:
            return None
        try:
            reply = self.co.on_operator(cmd)
        except Exception as exc:
            self.world.internal_error(self.node, exc)
            return None
        self.turn()
        return reply

    def _liveliness(self, key: str, alive: bool) -> None:
        rt, co = self.rt, self.co
        node = self.keys.node_of_alive(key)
        if node is None or node == self.node:
            return
        rt.on_liveliness(node, alive)
        self.relayer.on_liveliness(node, alive)
        if alive:
            self.suspects.pop(node, None)
            co.on_liveliness(node, True)
            co.link_seen(self.node, node)
        elif node in co.robots:
            self.suspects[node] = self.world.scheduler.wall()
        else:
            co.on_liveliness(node, False)

    def _settle_suspects(self) -> None:
        """Robots out of sight: a cut link (relayed to) or gone (`BaseStation._settle_suspects`)."""
        co, now = self.co, self.world.scheduler.wall()
        for node, since in sorted(self.suspects.items()):
            if now - since < SUSPECT_SETTLE_S:
                continue
            del self.suspects[node]
            if self.relayer.reachable(node):
                co.link_lost(self.node, node, detected_unix=since)
            else:
                co.on_liveliness(node, False, detected_unix=since)
        for node in sorted(co.present - self.relayer.direct - self.suspects.keys()):  # (at each turn: not all)
            if node not in self.relayer.direct and node not in self.suspects and not self.relayer.reachable(node):
                co.on_liveliness(node, False)

    def _received(self, key: str, payload: bytes) -> None:
        rt, co, keys = self.rt, self.co, self.keys
        relayed = key == keys.node_relay(self.node)
        inner = self.relayer.unwrap(key, payload)
        if inner is None:
            return
        key, payload = inner
        if key == keys.plan:
            try:
                plan = decode(payload, (PlanUpdate, PlanChange))  # whole or a change: both name their leader
            except ProtocolError:
                plan = None
            if plan is not None and plan.leader != co.takeover.leader:
                co.on_rival_plan(plan)
        if rt.on_message(key, payload):
            return
        try:
            if key == keys.inbox:
                co.on_inbox(payload)
            elif keys.node_of_status(key) is not None:
                self._status(key, decode(payload, (NodeStatus, StatusDelta)), relayed)
            else:
                rt.count("unexpected-key", key)
        except ProtocolError as exc:
            rt.count("garbled", f"on {key}: {exc}")

    def _status(self, key: str, msg: NodeStatus | StatusDelta, relayed: bool) -> None:
        rt, co = self.rt, self.co
        if status_problem(self.keys, key, msg.node, msg.t_unix, self.world.scheduler.wall()) is not None:
            rt.count("forged", key)
            return
        if not relayed and msg.node != self.node:  # as the base station: before the duplicate check
            self.relayer.on_direct(msg.node)
        status = self.statuses_in.whole(msg)
        if status is None:  # a change from a whole status we do not hold: the next whole one will do
            rt.counters["status-deltas-unapplied"] = self.statuses_in.unapplied
            return
        if status.t_unix <= self.status_t.get(status.node, 0.0) or status.node == self.node:
            return
        self.status_t[status.node] = status.t_unix
        self.relayer.on_status(status)
        rt.on_peer_status(status)
        if status.node in co.robots and status.node not in co.present and self.relayer.reachable(status.node):
            co.on_liveliness(status.node, True)
        co.on_rival_status(status)
        if co.mission is None:
            co.learn(status)
        elif status.plan_epoch >= 0 and (status.node in co.present or status.node in self.relayer.direct):
            co.on_status(status)

    def _turn(self) -> float:
        rt, co, w = self.rt, self.co, self.world
        self._settle_suspects()
        co.on_timer()
        if co.takeover.stepped_down is not None:
            w.stepped_down(self)
            return math.inf
        if co.mission is not None and w.base_state.get("incarnation") != co.takeover.incarnation:
            w.base_state["incarnation"] = co.takeover.incarnation  # the host remembers it (basestation.json)
        if rt.started:
            rt.on_timer()
        now = w.scheduler.wall()
        if now >= self.next_status:
            self.next_status = max(self.next_status + w.status_period_s, now)
            if rt.started:
                self.publish_status()
            else:  # no mission yet: the robots hear that it runs no plan (`PeerViews.listening`)
                for robot, key, payload in self.peer_views.addressed(co, None, now, w.status_period_s):
                    self._send_view(robot, key, payload)
        wake = [self.next_status, co.next_deadline_unix()]
        wake += [t + SUSPECT_SETTLE_S for t in self.suspects.values()]
        if rt.started and (t := rt.next_deadline()) is not None:
            wake.append(rt.clock.wall_at(t))
        return min(wake)

    def _send_view(self, robot: str, key: str, payload: bytes) -> None:
        """As the live base station does (`BaseStation._send_view`): on its key whether or not we
        take it for in sight, relayed as well when it is out of sight."""
        self.bus.publish(key, payload, reliable=False)
        if robot not in self.relayer.direct:
            self.relayer.send(robot, key, payload, reliable=False)

    def publish_status(self) -> None:
        """As the base station's loop does: held back when it says nothing new (`StatusCadence`),
        what flowed acknowledged every period all the same."""
        rt, co, w = self.rt, self.co, self.world
        built = rt.status(w.status_window_s * rt.clock.speed)
        co.on_host_status(built)
        status = self.cadence.due(built, w.scheduler.wall())
        if status is None and rt.idle() and co.idle() and not self.suspects:
            self._status_sent(built)
            return
        rt.commit_sinks()
        self.commit_outputs()
        rt.holds.settle_store()
        if status is not None:  # (held back: only counts moved, the heartbeat waits)
            self.bus.publish(self.keys.status(self.node), self.status_encoder.encode(status),
                             reliable=False)  # standby base stations
            # each robot the part it acts on (`basestation.peer_view`)
            for robot, key, payload in self.peer_views.addressed(co, status, w.scheduler.wall(),
                                                                 status.next_status_s, self.statuses_in.take_wanted()):
                self._send_view(robot, key, payload)
        rt.acknowledging.send(self.relayer.reachable, built.queue_wait_s)
        self._status_sent(built)
