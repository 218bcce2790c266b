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
(`autopower.node.custody`) until the consumer's acknowledgement reports it consumed; a report that
still lacks it a while after it was sent gets it resent. That is what makes each output reach
its sink exactly once even when a link is cut silently with frames in flight.

`NodeRuntime` is the façade the processes, the simulator and the tests drive (events in: messages,
the timer, acknowledgements, peers' statuses, liveliness; the status, acknowledgements, resume state
and what it has in hand out). It owns the node's context (its name, scenario, chains, keys and ways
out), the mission with its clock and battery meter, and the counts of what happened. The rest is in
collaborators, each owning its state, that the façade and each other call through methods; a
collaborator holds the runtime and never assigns another's attributes:

- ``plan_view`` (`plan_view.PlanView`): the plan run, its network, the model's power for it;
- ``frames`` (`frames.Frames`): the data path: sending, forwarding, receiving, running a stage's
  inputs (the chains' weights);
- ``hosting`` (`hosting.Hosting`): the orders that start, move and stop stages; the stages hosted, the
  inputs held for them, what failed, parked migration states;
- ``components`` (`components.Components`): building the stages' components, in this process or in
  worker processes;
- ``acknowledging`` (`acknowledging.Acknowledging`): custody's acknowledgements and resends;
- ``sinking`` (`sinks.Sinks`): the sink ledgers and their store;
- ``production`` (`production.Production`): the sources' captures (the sources themselves are
  ``feeds``, `sources.Sources`);
- ``resuming`` (`resuming.Resuming`): carrying on from a crashed process's saved state;
- ``sight`` (`sight.Sight`): the nodes in sight and what the base station said;
- ``metering`` (`metering.Metering`): forwarding on arrival, control-plane bytes, the runtime's CPU.

Collaborators built with what they use rather than the runtime: `Flows` (``flows``, `joining.py`, the
DAG flows), `ArrivalRelay` (``arrivals``, `relaying.py`, forwarding packets that only cross this node
on the transport's thread), `Holds` (``holds``, results held for a sink out of reach), `Custody`,
the gates and ledgers (`sequencing.py`) and the meters. The status is built in `status.py`; what a
node hosts is described in `stages.py`.
"""

from __future__ import annotations

import logging
import time
from typing import Callable

from autopower.errors import AutoPowerError, ProtocolError
from autopower.model.energy import flow_weight
from autopower.model.network import build_network
from autopower.model.scenario import Scenario
from autopower.model.variants import apply_variants
from autopower.node.acknowledging import Acknowledging
from autopower.node.components import Components
from autopower.node.control_meter import ControlPlaneMeter
from autopower.node.custody import Custody
from autopower.node.frames import Frames
from autopower.node.guard import GuardedCalls
from autopower.node.holds import Holds
from autopower.node.hosting import Hosting
from autopower.node.in_flight import frames_in_hand, stage_frames, transfer_frames
from autopower.node.joining import Flows
from autopower.node.meter import BatteryMeter
from autopower.node.metering import Metering
from autopower.node.plan_view import PlanView
from autopower.node.ports import NodePorts, NodeStores, SinkListener, SinkListeners
from autopower.node.production import Production
from autopower.node.relaying import ArrivalRelay
from autopower.node.resuming import Resuming, mission_key, new_process_id
from autopower.node.sequencing import SinkLedger
from autopower.node.sight import Sight
from autopower.node.sinks import Sinks
from autopower.node.sources import Sources
from autopower.node.stages import (
    HostedStage,
    SourceRunner,
)
from autopower.node.status import node_status
from autopower.protocol import (
    Ack,
    Keys,
    MissionInfo,
    NodeStatus,
    PeerStatus,
    PlanChange,
    PlanUpdate,
)
from autopower.protocol.codec import message_kind
from autopower.runtime.bus import Bus
from autopower.runtime.clock import Clock, VirtualClock

log = logging.getLogger(__name__)


_PLAN_KINDS = frozenset({PlanUpdate.KIND, PlanChange.KIND})  # what a control key carries of plans


class NodeRuntime:
    """Chain data handling for one node; see the module docstring."""

    def __init__(self, *, node: str, scenario: Scenario, bus: Bus, keys: Keys,
                 make_component: Callable | None = None, make_source: Callable | None = None,
                 clock_factory: Callable[[MissionInfo], Clock] | None = None, stage_workers: bool = False,
                 wall: Callable[[], float] | None = None, perf: Callable[[], float] | None = None,
                 ports: NodePorts | None = None, stores: NodeStores | None = None, process: int | None = None):
        """``wall`` is the node's wall clock (custody, gates, joins, the status's ``t_unix``, a
        frame's capture time) and ``perf`` the clock a component run is timed with (the status's
        ``compute_ms``); a simulator passes its own time for both. ``ports`` and ``stores`` are its
        ways out to the owning process (`autopower.node.ports`). ``process`` says which process of
        the node this is in its statuses (`NodeStatus.process`; None: drawn at random, `new_process_id`)."""
        ports = ports or NodePorts()
        stores = stores or NodeStores()
        if node not in scenario.node_names():
            raise AutoPowerError(f"node {node!r} is not in scenario {scenario.name} "
                                 f"(nodes: {', '.join(scenario.node_names())})")
        if make_component is None or make_source is None:
            from autopower import chains

            make_component = make_component or chains.make_component
            make_source = make_source or chains.make_source
        self.node = node
        self.process = new_process_id() if process is None else process
        self.scenario = scenario
        self.bus = bus
        self.keys = keys
        self.platform = scenario.platform_of(node)
        self._clock_factory = clock_factory or (lambda m: VirtualClock(m.epoch_unix, m.speed))
        self.chains = {c.name: c for c in scenario.chains}
        self.stage_index = {s.name: (c, i) for c in scenario.chains for i, s in enumerate(c.stages)}
        # DAG flows (`autopower.node.joining`): each travels as a pseudo-chain in self.chains
        self.flows = Flows(scenario, count=self.count, tally=self.tally,
                           joined=lambda chain, run, seq: self._sink_listeners.joined(chain, run, seq))
        self.chains.update(self.flows.chains)
        # the stages' components, in this process or each in a worker process of its own (`agent.workers`)
        self.components = Components(self, make_component=make_component, make_source=make_source,
                                     stage_workers=stage_workers, notify_work=ports.notify_work)

        self.mission: MissionInfo | None = None
        self.clock: Clock | None = None
        self.meter: BatteryMeter | None = None
        # the plan this node runs, its network and the model's power for it
        self.plan_view = PlanView(self)
        # the chains this node feeds from its own sensors (`autopower.node.sources`)
        self.feeds = Sources(node=node, key_of=lambda chain: self.components.source_key(chain),
                             build=lambda key: self.components.build_source(*key),
                             count=self.count, tally=self.tally)
        # the nodes in sight, and what this node heard of the base station
        self.sight = Sight(self, link_ends=build_network(scenario).neighbours(node), team=frozenset(scenario.node_names()))
        self.errors: dict[str, int] = {}  # things that should not happen (garbage, lost frames)
        self.counters: dict[str, int] = {}  # things that happen (forwarded, missed periods)
        # who hears of the sink's outputs, and of the results let go or lost in a crash (`listen`):
        # the recording tells these outputs from lost ones (`autopower.recording.replay`)
        self._sink_listeners = SinkListeners()
        # where a restarted process carries on (`autopower.agent.resume`): its saved state, applied
        # at the first plan of the same mission
        self.resuming = Resuming(self, stores.resume_from, self._sink_listeners)
        # what the sources capture, sent on to the first stage (and who is told when a source advanced)
        self.production = Production(self, stores.on_produced)
        # the data path: frames sent, forwarded, received, run by the stages here
        self.frames = Frames(self)
        # the stages hosted here: the orders that start, move and stop them, and the frames held for them
        self.hosting = Hosting(self)
        # the outputs reaching this node as their chain's sink: counted once, handed on once, and kept
        # across a restart when the process gives a `SinkStore`
        self.sinking = Sinks(self, stores.sink_store, self._sink_listeners)
        self.custody = Custody(hold_budget_bytes=scenario.hold_budget_bytes)
        self.control_plane = ControlPlaneMeter()  # the bytes on its links beyond the chain packets
        # custody's acknowledgements: those this node sends, those it hears, and resends
        self.acknowledging = Acknowledging(self)
        # results whose sink has no route from here (the plan's links): kept in order, within the
        # hold budget with the results in custody, on disk when the process gives a `HeldStore`
        self.holds = Holds(node=node, custody=self.custody, store=stores.held_store, chain=lambda name: self.chains.get(name),
                           listeners=self._sink_listeners, tally=self.tally, wall=lambda: self.wall(),
                           mission_key=lambda: mission_key(self.mission) if self.mission is not None else None)
        self.guard = GuardedCalls(node)  # component calls: off this thread, with a time limit
        # what the meter is charged beyond the chain's own work: forwarding on arrival, the control
        # plane's bytes, the runtime's CPU
        self.metering = Metering(self)
        self.wall: Callable[[], float] = wall or time.time
        self.perf: Callable[[], float] = perf or time.perf_counter
        # How a message for one node leaves: the process gives its `Relayer.send`, so that a node
        # out of direct sight is still reached through other agents.
        self.send_to: Callable[..., object] = ports.send_to or (  # (dest, key, payload, *, reliable=True)
            lambda dest, key, payload, reliable=True: self.bus.publish(key, payload, reliable=reliable))
        # packets only crossing this node: forwarded on the transport's thread (`relay_now`)
        self.arrivals = ArrivalRelay(node=node, radios=scenario.radios, keys=keys, bus=bus, in_sight=ports.in_sight,
                                     started=lambda: self.mission is not None, now=self.now)

    def relay_now(self, payload: bytes) -> bool:
        """On the transport's thread: forward ``payload`` if it only crosses this node (True), or
        leave it to the loop (`on_data`). See `autopower.node.relaying`."""
        return self.arrivals.relay_now(payload)

    def listen(self, listener: SinkListener) -> None:
        """Tell ``listener`` of every output reaching this node as its chain's sink, and of every
        result let go or lost in a crash here (`autopower.node.ports.SinkListener`)."""
        self._sink_listeners.add(listener)

    @property
    def hosted(self) -> dict[str, HostedStage]:
        """The stages hosted here, by name (read only: `Hosting` owns them)."""
        return self.hosting.hosted

    @property
    def plan(self) -> PlanUpdate | None:
        """The plan this node runs (read only: `PlanView` owns it)."""
        return self.plan_view.plan

    @property
    def sinks(self) -> dict[str, SinkLedger]:
        """The ledgers of the chains whose sink is this node (read only: `Sinks` owns them)."""
        return self.sinking.ledgers

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
        # plans are ordered by (incarnation, epoch): a base station that took over the team
        # (a higher incarnation) is followed even if its epoch is lower than what runs
        self.plan_view.remember(plan)  # the base of the next change (the base station's host, a saved plan)
        if (plan.incarnation, plan.epoch) <= self.plan_view.order:
            return  # old or repeated
        if plan.mission.scenario != self.scenario.name:
            self.count("foreign-plan", f"plan for scenario {plan.mission.scenario!r}")
            return
        if self.mission is None:
            self.mission = plan.mission
            self.sinking.load(plan.mission.epoch_unix)  # a restarted sink goes on from what it had delivered
            self.clock = self._clock_factory(plan.mission)
            self.sinking.replay_journal()  # at mission time
            if not self.platform.mains and self.node not in plan.mission.energies_j:
                raise AutoPowerError(f"the mission gives no starting energy for {self.node}")
            scenario = with_variants(self.scenario, plan.variants, self.count)
            if scenario is not None:
                self.scenario = scenario
                self.chains = {c.name: c for c in scenario.chains}
                self.stage_index = {s.name: (c, i) for c in scenario.chains for i, s in enumerate(c.stages)}
            self.meter = BatteryMeter(platform=self.platform, radios=self.scenario.radios,
                                      initial_j=plan.mission.energies_j.get(self.node),
                                      t0=max(0.0, self.clock.now()),
                                      loss={peer: loss for peer in self.scenario.node_names()
                                            if (loss := self.scenario.link_loss(self.node, peer))})
            self.frames.start({**{c.name: flow_weight(c, plan.mission.accounting) for c in self.scenario.chains},
                               **self.flows.weights(plan.mission.accounting)})
            self.meter = self.resuming.resume(plan.mission, self.meter)
            if not self.resuming.resumed and self.holds.store is not None:
                # a process without a resume state (the base station's host) keeps its held results
                # on disk all the same: their producers have had the acknowledgement, so a held result
                # lost with this process is held nowhere else
                self.holds.take_back(mission_key(plan.mission))
        self.plan_view.set_plan(plan)
        self.hosting.follow_plan(plan)
        self.feeds.sync(plan.running, self.chains, self.now())
        for chain in ({hop[0] for hop in self.custody.hops} - set(plan.running) - self.flows.running(plan)) \
                & set(plan.operator.disabled):
            # Stopped by the operator (or a failed component): nobody will consume the frames for its
            # stages; its sink still takes its results. A chain stopped because the base station lost
            # a robot for a moment keeps all of them: it is adopted again in the same run when the
            # robot is back, and what was lost in flight meanwhile is then resent (acknowledgements,
            # a newer run or custody's age limit clear the rest).
            stopped = self.chains.get(chain)
            results = len(stopped.stages) if stopped is not None and stopped.sink else None
            self.custody.forget_chain(chain, keep_target=results)
        self.hosting.send_parked()
        self.frames.flush_held()
        self.hosting.replay_early()

    def resume_state(self) -> dict | None:
        """What a restarted process needs to carry on (None before the mission starts; `Resuming.state`)."""
        return self.resuming.state()

    def in_flight_at_stop(self) -> dict[tuple[str, int], set[int]]:
        """(chain, run) -> the seqs of the frames this node still has in hand (`autopower.node.in_flight`)."""
        names = [c.name for c in self.scenario.chains]
        hosting = self.hosting
        moving = [body for _, body, _ in hosting.parked_transfers]
        moving += [h.shipped[2] for h in hosting.hosted.values() if h.shipped is not None and h.shipped[2]]
        return frames_in_hand(names, (self.custody.frames(), self.holds.held.values(), stage_frames(hosting.hosted),
                                      transfer_frames(moving), *hosting.orphans.values()))

    # ---- held results (`autopower.node.holds`) --------------------------------------------------
    def commit_sinks(self) -> None:
        """Write down the outputs the sinks took in since the last commit (before each status).

        Until then an output delivered to a sink here is not safe: a kill loses it with the notes, so
        this node's custody keeps it (`on_timer` acknowledges to it only what is committed) and the
        stage that made it reports its input had, not run (`Acknowledging.acknowledged`). A status's
        acknowledgements to other nodes leave after this commit, so they may say what it wrote.
        """
        self.acknowledging.sinks_committed(self.sinking.commit())

    def close_stores(self, *, commit_sinks: bool = True) -> None:
        """Close what it keeps on disk (the held results' writer finishes first). ``commit_sinks``
        False: the sink's notes since its last commit are not written (as a killed process leaves them)."""
        if self.holds.store is not None:
            self.holds.store.close()
        self.sinking.close(commit=commit_sinks)

    # ---- sources (`autopower.node.sources`) ---------------------------------------------------------
    @property
    def sources(self) -> dict[str, SourceRunner]:
        """The sources running here, by chain (read only: `Sources` owns them)."""
        return self.feeds.runners

    # ---- timers --------------------------------------------------------------------------------
    def next_deadline(self) -> float | None:
        """Virtual time of the next source tick (None: nothing scheduled)."""
        return self.feeds.next_deadline()

    def idle(self) -> bool:
        """Nothing here is timed: no source, no stage hosted, no frame in custody, held or parked.

        The loop of an idle node may sleep until an event or its next status (`StatusCadence.next_build`)
        instead of calling `on_timer` every status period.
        """
        hosting = self.hosting
        return not (self.feeds or hosting.hosted or self.custody or hosting.orphans or self.holds.held
                    or hosting.parked_transfers)

    def on_timer(self) -> None:
        self.metering.settle_relayed()
        if self.components.has_workers:  # stages in worker processes: results in, hung runs killed
            self.components.collect_results()
            self.components.check_workers()
        wall = self.wall()
        self.acknowledging.tick(wall)  # what we consumed ourselves; resends of what our consumers lack
        self.frames.join_tick()  # fan-in steps whose wait is over
        self.production.tick(wall)  # the sources whose period is due

    # ---- peers ----------------------------------------------------------------------------------------
    def on_peer_status(self, status: NodeStatus | PeerStatus) -> None:
        """Another node's status: the acknowledgements it wants (`Acknowledging`), and whether the
        base station runs the plan this node runs (else this node's statuses carry the mission)."""
        self.acknowledging.note_wants(status)
        if status.zid and status.node != self.node and not self.control_plane.learn_zid(status.node, status.zid):
            self.count("zid-refused", f"{status.node} announced session {status.zid[:40]!r}: not a Zenoh id, "
                                      "or another node's")
        if status.node == self.scenario.basestation:
            self.sight.heard_basestation(status)

    # ---- liveliness ----------------------------------------------------------------------------------
    def on_liveliness(self, node: str, alive: bool) -> None:
        """``node`` came into this node's sight or left it (`Sight.on_liveliness`)."""
        self.sight.on_liveliness(node, alive)

    # ---- status ----------------------------------------------------------------------------------------
    # ---- acknowledgements (`autopower.node.acknowledging`) ---------------------------------------------
    def status(self, window_s: float, queue_depth: int = 0, queue_wait_s: float = 0.0) -> NodeStatus:
        """This node's status (`autopower.node.status`)."""
        return node_status(self, window_s, queue_depth, queue_wait_s)

    def on_ack(self, ack: Ack) -> None:
        """Another node's acknowledgement (`Acknowledging.on_ack`)."""
        self.acknowledging.on_ack(ack)

    def acks(self, queue_wait_s: float = 0.0) -> dict[str, Ack]:
        """What this node consumed, as one `Ack` per node that sent it frames (`Acknowledging.acks`)."""
        return self.acknowledging.acks(queue_wait_s)

    # ---- dispatch -----------------------------------------------------------------------------------------
    def on_message(self, key: str, payload: bytes) -> bool:
        """Handle a message on one of this node's keys; False if the key is not ours.

        Garbage (ProtocolError) is counted, logged and dropped; it never propagates.
        """
        try:
            if key == self.keys.node_data(self.node):
                self.frames.on_data(payload)
            elif key == self.keys.node_control(self.node) and message_kind(payload) not in _PLAN_KINDS:
                self.hosting.on_control(payload)  # a robot's plans come on its control key, whole or as changes
            elif (ends := self.keys.addressed_ends(key)) is not None and ends[0] == self.node:
                self.acknowledging.on_ack_message(key, payload)
            elif key in (self.keys.plan, self.keys.node_control(self.node)):
                # a robot's plans come on its control key (`PlanDelivery`; the plan key carries
                # them to base stations and recorders, and a subgroup's prediction): the bytes handled
                # last need no decoding again (plans only move forward: what was applied or ignored
                # once would be ignored now)
                plan = self.plan_view.take(payload)
                if plan is not None:
                    self.on_plan(plan)
            else:
                return False
        except ProtocolError as exc:
            self.count("garbled", f"on {key}: {exc}")
        return True


def with_variants(scenario: Scenario, variants: dict[str, str], count: Callable[..., None]) -> Scenario | None:
    """The mission's quality variants (fixed at its start): each chain's period, message sizes and
    modelled latency become its variant's, and its component and source are built with the variant's
    parameters (`model.variants`, `chains.variants`). None when the plan names none, or names variants
    the scenario lacks (counted with ``count``: it runs as declared)."""
    if not variants:
        return None
    try:
        return apply_variants(scenario, variants)
    except AutoPowerError as exc:
        count("unknown-variant", str(exc)[:200])
        return None
