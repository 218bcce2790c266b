"""The robot agent process: one event loop around a `NodeRuntime`, a battery, a liveliness token.

`autopower agent --robot r2 --scenario paper-fig7 ...` builds an `Agent` and runs it. It
joins Zenoh, declares ``alive/<robot>``, waits for the base station's plan (which carries the
mission clock and starting energies), then hosts what it is assigned, runs its chains' sources
at their periods, forwards other robots' data when it sits on their route, meters its battery
and publishes its status at a steady wall-clock rate. When its battery is empty it publishes a
last status and leaves the team (the base station replans without it).
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

from autopower.agent.resume import ResumeFile
from autopower.errors import ProtocolError
from autopower.model.scenario import Scenario
from autopower.node.held_store import HeldStore
from autopower.node.peer_watch import PeerWatch, WatchSettings
from autopower.node.ports import NodePorts, NodeStores
from autopower.node.runtime import NodeRuntime
from autopower.node.sink_store import SinkStore
from autopower.node.subgroup_rounds import RoundSettings, SubgroupRounds
from autopower.protocol import (
    Assign,
    Keys,
    PeerStatus,
    decode,
    encode,
)
from autopower.protocol.access import TeamAccess, carries_peer_status, status_problem
from autopower.protocol.codec import looks_like_message
from autopower.protocol.statuses import StatusEncoder
from autopower.runtime.bus import Bus, ZenohBus, ZenohSettings
from autopower.runtime.cadence import (
    REPEAT_AFTER_PERIODS,
    REPEAT_EVERY_PERIODS,
    StatusCadence,
)
from autopower.runtime.events import EventQueue, LivelinessChanged, OperatorRequest, Received, StopRequested, WorkDone
from autopower.runtime.link_traffic import LinkTraffic, link_traffic_of
from autopower.runtime.loop_watch import LoopWatch
from autopower.runtime.relay import Relayer
from autopower.runtime.signatures import load_signing

log = logging.getLogger(__name__)

# A peer's silence is judged strictly after its limit: the loop wakes this much later for it.
SILENCE_SLACK_S = 0.001
# Wall seconds a restarted agent with no plan waits for the base station (its liveliness, then its
# plan: a lease and a status period) before it goes on alone with the plan it ran (`_resume_alone`).
RESUME_ALONE_AFTER_S = 3.0
# The agent's last resume state waits this long for the one still being written (a stopping robot
# may wait; a running one never does: `ResumeFile` writes in a thread of its own).
FINAL_SAVE_WAIT_S = 5.0


@dataclass(frozen=True, kw_only=True)
class AgentConfig:
    robot: str
    scenario: Scenario
    team: str
    zenoh: ZenohSettings = field(default_factory=ZenohSettings)
    status_period_s: float = 0.5  # wall seconds between status messages
    # at rest (nothing new in the status but what drifts with time), one every this many wall seconds
    status_rest_period_s: float = 2.0
    status_window_s: float = 2.0  # wall seconds the reported mean power covers
    parent_pid: int | None = None  # stop when this process is gone (no orphans)
    subgroup: bool = True  # reallocate among the robots in reach when the base station is not
    subgroup_settle_s: float = 0.3  # wall seconds the base must be out of reach before that
    subgroup_timeout_s: float = 1.0  # a round not decided by then is aborted
    # where the agent keeps what a restarted process needs to carry on (`autopower.agent.resume`);
    # None: a restart starts from the mission's energies
    resume_path: Path | None = None
    # A node whose statuses stop arriving directly for this many status periods is out of sight,
    # whatever its liveliness token says: a second, independent failure detector (Zenoh keeps a
    # token until the link's lease expires, and a link stuck behind a full send queue can outlive it).
    silence_periods: float = 2.0


def prepare_rounds() -> None:
    """Import what a subgroup round runs: the policies, the planner, HiGHS and networkx. At start,
    before the loop runs: the round that needs them comes when the base station has just gone out
    of reach and must not wait for an import, and an import while the chains run (on the loop or
    beside it) takes the CPU their periods need. (The shared options import the policies today;
    this keeps the rule if they stop.)"""
    import autopower.policies.subgroup  # noqa: F401
    import autopower.policies.team  # noqa: F401


class Agent:
    """A robot's agent (a context manager: the session, token and subscriptions close on exit)."""

    def __init__(self, config: AgentConfig, bus: Bus | None = None, **runtime_kwargs):
        config.scenario.robot(config.robot)  # unknown robot -> ScenarioError
        self.config = config
        self.keys = Keys(config.team)
        # everything an agent subscribes to is an encoded message: random bytes never take room
        self._data_key = self.keys.node_data(config.robot)  # relayed on arrival when it only crosses us
        self.events = EventQueue(bulk_keys=[self._data_key], admit=looks_like_message)
        self._bus = bus
        self._owns_bus = bus is None
        self._handles: list = []
        self._runtime_kwargs = runtime_kwargs
        if config.subgroup:
            prepare_rounds()
        self.runtime: NodeRuntime | None = None
        self.traffic: LinkTraffic | None = None
        self.resume: ResumeFile | None = None
        self.relayer: Relayer | None = None
        self.rounds: SubgroupRounds | None = None
        self.statuses: dict = {}  # node -> its last PeerStatus (battery for subgroup decisions)
        self._started_unix = time.time()  # a restarted agent waits for a plan from then (`_resume_alone`)
        self._resumed_alone = False
        # who is in direct sight: tokens, checked by the statuses that arrive (`node.peer_watch`)
        self.watch = PeerWatch(WatchSettings(periods=config.silence_periods, own_period_s=config.status_period_s,
                                             lease_s=config.zenoh.lease_ms / 1000.0))
        self.cadence = StatusCadence(config.status_period_s, config.status_rest_period_s)
        self.status_encoder = StatusEncoder()  # each status whole or as its change from the last whole one
        self._asleep_at_rest = False  # the loop sleeps past the status period (`run`)
        self.stop_reason: str | None = None

    def __enter__(self) -> "Agent":
        if self._bus is None:
            self._bus = ZenohBus(self.config.zenoh)
        bus, keys, robot = self._bus, self.keys, self.config.robot
        scenario = self.config.scenario
        access = TeamAccess(keys, scenario.basestation, tuple(r.name for r in scenario.robots))
        self.signing = load_signing(robot, self.config.zenoh.tls)  # None: --insecure, nothing signed
        self.relayer = Relayer(node=robot, bus=bus, keys=keys, count=self._count, access=access,
                               signing=self.signing)
        self.resume = ResumeFile(self.config.resume_path, background=True) if self.config.resume_path else None
        self.traffic: LinkTraffic | None = link_traffic_of(bus)  # the bytes on its links (`publish_status`)
        ports = NodePorts(send_to=self.relayer.send,
                          in_sight=self.relayer.direct.__contains__,  # what it may forward on arrival
                          notify_work=lambda: self.events.post(WorkDone()))  # a stage worker's result is in
        self.runtime = NodeRuntime(node=robot, scenario=scenario, bus=bus, keys=keys, ports=ports,
                                   stores=self._stores(), **self._runtime_kwargs)
        cfg = self.config
        self.rounds = SubgroupRounds(
            runtime=self.runtime, scenario=scenario, bus=bus, keys=keys, wall=time.time,
            reachable=self.relayer.reachable, reached=self.relayer.reached, statuses=self.statuses,
            settings=RoundSettings(enabled=cfg.subgroup, settle_s=cfg.subgroup_settle_s,
                                   timeout_s=cfg.subgroup_timeout_s, status_period_s=cfg.status_period_s),
            publish_status=self.publish_status, save_resume=self.save_resume, started_unix=self._started_unix,
            signing=self.signing, relay=self.relayer.send_beyond_sight)
        self.runtime.production.prepare()  # before anyone sees us: a camera's scene takes a while to render
        # what is for this robot (data, control, relayed control, what others address to it) on one
        # subscription (`Keys.node_all`); the peers' statuses as robots need them (`PeerStatus`):
        # whole statuses go to base stations; its plans come on its control key (`PlanDelivery`:
        # the plan key carries every plan to base stations and recorders)
        self._handles.append(bus.subscribe(keys.node_all(robot), self._on_own_key))
        for key in (keys.peer_all, keys.subgroup):
            self._handles.append(bus.subscribe(key, self.events.on_message))
        self._handles.append(bus.watch_liveliness(keys.alive_all, self.events.on_liveliness))
        # Presence last: once the base station sees us, everything we need is declared.
        self._handles.append(bus.declare_token(keys.alive(robot)))
        log.info("agent %s joined team %s", robot, self.config.team)
        return self

    def _stores(self) -> NodeStores:
        """What survives this agent's process, beside its resume file (none without one)."""
        if self.resume is None:
            return NodeStores()
        folder, robot, resume = self.resume.path.parent, self.config.robot, self.resume
        return NodeStores(
            held_store=HeldStore(folder / f"{robot}.held", background=True),
            # a robot is the sink of its own chains (Loc-*): a restarted one must not take the
            # results its producers resend (their acknowledgements were lost) for new ones
            sink_store=SinkStore(folder / f"{robot}.sinks.json"),
            resume_from=resume.load(),
            on_produced=lambda r: resume.note_source(r.chain.name, r.run, r.seq, r.missed, r.produced_total,
                                                     r.missed_stopped))

    def _count(self, what: str, detail: str = "", level: int = logging.WARNING) -> None:
        """The relayer's errors go to the runtime's (built after it: the runtime sends through it)."""
        self.runtime.count(what, detail, level)

    def __exit__(self, *exc) -> None:
        if self.runtime is not None:
            self.runtime.components.close()
        if self.resume is not None:
            self.resume.close()
        if self.runtime is not None:
            self.runtime.close_stores()
        for handle in reversed(self._handles):
            handle.close()
        self._handles.clear()
        if self._owns_bus and self._bus is not None:
            self._bus.close()
            self._bus = None

    def _on_own_key(self, key: str, payload: bytes) -> None:
        """On the transport's thread: a sample on one of this robot's keys."""
        if key == self._data_key:
            self._on_data(key, payload)
        else:
            self.events.on_message(key, payload)

    def _on_data(self, key: str, payload: bytes) -> None:
        """On the transport's thread: a packet only crossing us goes on at once (`agent.relaying`),
        unless data is queued before it (relayed packets keep their order); the rest is queued."""
        try:
            done = not self.events.bulk_depth() and self.runtime.relay_now(payload)
        except Exception:  # a bug here must not lose the packet: the loop handles it as before
            log.exception("agent %s: forwarding on arrival failed; left to the loop", self.config.robot)
            done = False
        if not done:
            self.events.on_message(key, payload)
        elif self._asleep_at_rest:  # the loop charges what was forwarded; asleep for its rest period, it
            self._asleep_at_rest = False  # would only at its next status: wake it once
            self.events.post(WorkDone())

    def request_stop(self, reason: str) -> None:
        """Thread- and signal-safe."""
        self.events.post(StopRequested(reason))

    def _handle(self, event) -> None:
        if isinstance(event, Received):
            self._received(event.key, event.payload)
        elif isinstance(event, LivelinessChanged):
            node = self.keys.node_of_alive(event.key)
            if node is not None and node != self.config.robot:
                log.info("agent %s: %s %s (liveliness)", self.config.robot, self._who(node),
                         "in sight" if event.alive else "out of sight")
                change = self.watch.on_token(node, event.alive)
                if change is not None:
                    self._sight(node, change)
        elif isinstance(event, WorkDone):
            self.runtime.components.collect_results()
        elif isinstance(event, OperatorRequest):
            event.request.close()

    def _who(self, node: str) -> str:
        """A node as the log names it ("base station laptop": what the demo's timing looks for)."""
        return f"base station {node}" if node == self.config.scenario.basestation else node

    def _sight(self, node: str, visible: bool) -> None:
        """``node`` came into direct sight or went out of it (its token, or its statuses' silence)."""
        self.runtime.on_liveliness(node, visible)
        self.relayer.on_liveliness(node, visible)
        if not visible:
            self.rounds.on_member_lost(node)
        # tell the others now, not at the next tick: the base station tells a dead
        # robot from a cut link by what the other robots still see
        self.publish_status()

    def _check_silence(self, now: float) -> None:
        """Nodes in sight by their token whose statuses stopped arriving directly go out of sight."""
        # only once the statuses that arrived are taken: after the loop itself was held up (a put
        # blocked on a saturated radio for seconds) they wait in the queue, and judging before
        # taking them declared every peer silent
        if self.events.urgent_waiting():
            return
        for node, silent_s in self.watch.check(now):
            log.info("agent %s: %s out of sight (no status for %.1f s; its token is still here)",
                     self.config.robot, self._who(node), silent_s)
            self.runtime.tally("silent-peers")
            self._sight(node, False)

    def _heard(self, node: str, next_status_s: float) -> None:
        """A status from ``node`` arrived directly (not relayed)."""
        if self.watch.on_status(node, next_status_s, time.time()):
            log.info("agent %s: %s in sight again (its statuses arrive)", self.config.robot, self._who(node))
            self._sight(node, True)

    def _received(self, key: str, payload: bytes) -> None:
        rt = self.runtime
        relayed = key == self.keys.node_relay(self.config.robot)
        inner = self.relayer.unwrap(key, payload)
        if inner is None:
            return
        key, payload = inner
        if key == self.keys.subgroup:
            self.rounds.on_message(payload)
            return
        if carries_peer_status(self.keys, key, payload, self.config.robot):
            try:
                status = decode(payload, PeerStatus)
                problem = status_problem(self.keys, key, status.node, status.t_unix, time.time())
                if problem is not None:
                    rt.count("forged", problem)
                    return
                if not relayed:  # before the duplicate check: a relayed copy may come first
                    self._heard(status.node, status.next_status_s)
                    self.relayer.on_direct(status.node)  # (`Relayer.on_direct`: why every direct copy counts)
                last = self.statuses.get(status.node)
                if last is not None and status.t_unix <= last.t_unix:
                    return  # a duplicate (direct and relayed) or an older one overtaken
                base_was_reachable = self.relayer.reachable(self.config.scenario.basestation)
                self.relayer.on_status(status)
                self.statuses[status.node] = status
                rt.on_peer_status(status)  # what it consumed: acks for our custody buffer
                # a base station that began listening, or hears us again, gets our next status whole
                heard_again = rt.sight.take_status_asked() or self._base_came_within_reach(base_was_reachable) \
                    or status.send_whole  # it missed our last whole status: the next one goes whole
                if heard_again:
                    self.status_encoder.refresh()
                if rt.hosting.yield_to_newer(status) or heard_again:
                    self.publish_status()
            except ProtocolError as exc:
                rt.count("garbled", f"on {key}: {exc}")
            return
        order, model_w = rt.plan_view.order, rt.plan_view.model_w
        if not rt.on_message(key, payload):
            rt.count("unexpected-key", key)
        elif rt.plan_view.order != order:
            self.publish_status()  # acknowledges the new plan at once (reconfiguration is timed on it)
        elif rt.plan_view.model_w != model_w:
            self.publish_status()  # a stage left: the recording's model steps down when it did

    def _base_came_within_reach(self, was_reachable: bool) -> bool:
        """The base station is within reach again through a peer's links (relayed): it hears us
        only through our statuses, which would otherwise wait for the heartbeat (a base station that
        came back learns the team within a listening window shorter than that)."""
        return not was_reachable and self.relayer.reachable(self.config.scenario.basestation)

    # ---- subgroup (no base station): `node.subgroup_rounds` ------------------------------------------
    def _subgroup_tick(self) -> None:
        self.rounds.tick()

    def _resume_alone(self) -> None:
        """Restarted while the base station is out of reach: go on with the plan this robot ran.

        Without it the robot would idle (no plan: no mission clock, no sources, no subgroup) until the
        base station came back, however long that took, and its peers would go on without its chains.
        Its battery and sources go on from the resume state as they would on the base station's plan,
        it hosts again what the plan puts on it, and the subgroup rounds that follow count it in. The
        base station's next plan (a higher epoch, or a higher incarnation after a takeover) replaces
        it.
        """
        rt = self.runtime
        if (self._resumed_alone or self.relayer.reachable(self.config.scenario.basestation)
                or time.time() - self._started_unix < RESUME_ALONE_AFTER_S):
            return
        self._resumed_alone = True  # once: a file without a usable plan is not read again every tick
        plan = rt.resuming.saved_plan()
        if plan is None:
            return
        me = self.config.robot
        rt.on_plan(plan)
        # What the plan put here is started again (its state died with the process), unless a peer
        # reports running it now (a round while we were down moved it there: two instances would
        # each deliver its outputs). Left unstarted, the peers, whose plan says it runs here, never
        # restarted it either: our sources' frames piled up here for a stage nobody ran.
        elsewhere = {stage: peer for peer in self.statuses if peer != me for stage in self.rounds.running_on(peer)}
        if elsewhere:
            rt.plan_view.override_placement(elsewhere, set())
        generation = int(time.time() * 1000)  # above the crashed instances' (a base station's or a round's)
        restarted = []
        for stage, host in sorted(rt.plan.placement.items()):
            chain, _ = rt.stage_index.get(stage, (None, 0))
            if host == me and chain is not None and chain.name in rt.plan.running and stage not in elsewhere:
                rt.hosting.on_assign(Assign(stage=stage, generation=generation, chain=chain.name,
                                    run=rt.plan.running[chain.name], resume_seq=None))
                restarted.append(stage)
        log.warning("agent %s: restarted with the base station out of reach: going on with the plan it ran "
                    "(epoch %d) until the base station returns; %s", me, plan.epoch,
                    f"restarted {', '.join(restarted)} here" if restarted else "no stage to restart here")
        self.publish_status()

    def save_resume(self, *, wait_s: float = 0.0) -> None:
        self.runtime.holds.settle_store()
        state = self.runtime.resume_state() if self.resume is not None else None
        if state is not None:
            self.resume.save(state, wait_s=wait_s)

    def publish_status(self, *, urgent: bool = True, save_resume: bool = False) -> bool:
        """Our status, to everyone in sight and (relayed) to the base station if it is not.

        Also before the mission starts: with the relay topology the base station sees r2 and r3
        only through r1's statuses (who it sees) and theirs (relayed), and starts the mission as
        soon as every robot is known to be reachable rather than after the start grace.
        The periodic one (not ``urgent``) is held back when it says nothing new (`StatusCadence`);
        False then, what flowed since the last acknowledged all the same.
        ``save_resume``: the resume state is saved first (at rest its state only drifts: saved with
        the statuses that go out, the restart charges idle power from there; while anything runs,
        every period).
        """
        rt = self.runtime
        window = self.config.status_window_s * rt.clock.speed if rt.started else 0.0
        rt.errors.update(self.events.counts())  # dropped before the loop saw them (absolute counts)
        if self.traffic is not None and self.traffic.due(time.monotonic()):
            rt.metering.charge_control(self.traffic.poll(self._bus.links()), self.traffic.packets_by_peer)  # the control plane's bytes, metered
        rt.metering.charge_runtime(time.process_time())  # the runtime's own CPU (all but component code), metered
        if self._bus.repeated:  # statuses put again while the loop was held up
            rt.counters["status-repeats"] = self._bus.repeated
        if self.watch.tokens_lost:  # peers a token that went took out of sight (`PeerWatch` counts them)
            rt.counters["tokens-lost"] = self.watch.tokens_lost
        built = rt.status(window, self.events.depth(), self.events.bulk_wait_s())
        status = self.cadence.due(built, time.time(), urgent=urgent)
        if status is None and self._quiet():
            return False  # at rest: nothing new, nothing to acknowledge
        if save_resume:
            self.save_resume()
        # what is acknowledged is kept first, every period (as the base station's): the sink's notes,
        # then their recording, so that each commit is flushed before the next (`node.sink_store`)
        rt.commit_sinks()
        self._bus.flush_recording()
        if status is not None:  # (held back: only counts moved, the heartbeat waits)
            # the whole status to base stations, the part robots use to the robots (each a heartbeat)
            base = self.config.scenario.basestation
            for key, payload, dests in ((self.keys.status(self.config.robot), self.status_encoder.encode(status), [base]),
                                        (self.keys.peer(self.config.robot), encode(PeerStatus.of(status)),
                                         sorted(rt.acknowledging.producers() - {base}))):
                self._bus.publish(key, payload, reliable=False)
                self._bus.repeat_until_next(key, payload, REPEAT_AFTER_PERIODS * status.next_status_s,
                                            REPEAT_EVERY_PERIODS * status.next_status_s)
                # out of sight: through a robot that still sees them, to the base station and to the
                # robots whose frames we consume (they route by what we see)
                self.relayer.send_beyond_sight(dests, key, payload, reliable=False)
        rt.acknowledging.send(self.relayer.reachable, built.queue_wait_s)  # to the nodes that sent us frames
        return status is not None

    def _quiet(self) -> bool:
        """Nothing here is timed but the status (`StatusCadence.next_build`): no source, stage or frame
        in custody (`NodeRuntime.idle`), no subgroup round or settle under way."""
        return self.runtime.idle() and self.rounds.idle()

    def _own_status(self, event) -> bool:
        """Our own status, back from the bus (Zenoh delivers a put to the session's own subscribers too):
        nothing happened that the next status could say."""
        return isinstance(event, Received) and event.key == self.keys.peer(self.config.robot)

    def _next_wake(self, now: float, next_status: float, deadline: float | None, quiet: bool) -> float:
        """When the loop must wake if no event comes first (wall time): the next status to build, a
        peer's silence deadline, a source tick, the subgroup's settle or round deadline, the time limit."""
        rt = self.runtime
        wake = [self.cadence.next_build(next_status, quiet=quiet)]
        # (a loop that is not quiet wakes every status period and looks then, as it always did)
        if quiet and (silent_at := self.watch.next_deadline()) is not None:
            wake.append(silent_at + SILENCE_SLACK_S)  # found when its limit passes (the check is strict)
        if deadline is not None:
            wake.append(deadline)
        if rt.started and (t := rt.next_deadline()) is not None:
            wake.append(rt.clock.wall_at(t))
        wake += self.rounds.wake_times(now)
        if not rt.started and not self._resumed_alone and rt.resuming.resume_from and self.config.subgroup:
            alone_at = self._started_unix + RESUME_ALONE_AFTER_S  # `_resume_alone` looks then
            if alone_at > now:
                wake.append(alone_at)
        return min(wake)

    def run(self, max_wall_s: float | None = None) -> str:
        """Run until stopped, depleted or ``max_wall_s``; return why it stopped.

        At rest (`_quiet`) the loop wakes only for an event or a deadline (`_next_wake`), not every
        status period: an event then gets the status built at once (sent if it says something new).
        """
        deadline = None if max_wall_s is None else time.time() + max_wall_s
        next_status, period = time.time(), self.config.status_period_s
        news = False  # an event handled since the last status was built (not our own status back)
        loop_watch = LoopWatch(f"agent {self.config.robot}")
        try:
            self._loop(loop_watch, deadline, next_status, period, news)
        finally:
            loop_watch.stop()
        self.save_resume(wait_s=FINAL_SAVE_WAIT_S)  # the last state: after the one being written, if any
        self.publish_status()
        log.info("agent %s stopping: %s", self.config.robot, self.stop_reason)
        return self.stop_reason

    def _loop(self, loop_watch: LoopWatch, deadline: float | None, next_status: float, period: float,
              news: bool) -> None:
        rt = self.runtime
        while True:
            now = time.time()
            quiet = self._quiet()
            self._asleep_at_rest = quiet and self.cadence.resting
            loop_watch.waiting()
            event = self.events.get(max(0.0, self._next_wake(now, next_status, deadline, quiet) - now))
            loop_watch.working()
            self._asleep_at_rest = False
            if isinstance(event, StopRequested):
                self.stop_reason = event.reason
                break
            if event is not None:
                try:
                    self._handle(event)
                except Exception:  # a bug in one handler must not kill the robot's software
                    log.exception("agent %s: error handling %r", self.config.robot, type(event).__name__)
                    rt.count("internal-error")
            self._check_silence(time.time())
            if not rt.started and self.config.subgroup:
                self._resume_alone()  # restarted with the base station out of reach: our saved plan
            if rt.started:
                self._subgroup_tick()
                rt.on_timer()
                rt.meter.advance(rt.now())
                if rt.meter.depleted:
                    log.warning("agent %s: battery empty at t=%.1f s; leaving the team", self.config.robot,
                                rt.now())
                    self.stop_reason = "depleted"
                    break
            now = time.time()
            resting = quiet and self.cadence.resting
            news = news or (quiet and event is not None and not self._own_status(event))
            due = now >= self.cadence.next_build(next_status, quiet=quiet) or (resting and news)
            # at rest, statuses come in clusters: all of them first, then one status (an event still
            # queued counts in it as something new: two statuses for nothing); a stream of events does
            # not hold back the heartbeat for more than a period
            if due and not (resting and self.events.depth()
                            and now < self.cadence.next_build(next_status, quiet=True) + period):
                news = False
                self.publish_status(urgent=False, save_resume=True)
                # on the tick grid; one built at rest (its rest period over, or for an event) starts a new grid
                next_status = now + period if resting else max(next_status + period, now)
                if self.config.parent_pid is not None and os.getppid() != self.config.parent_pid:
                    self.stop_reason = "parent exited"
                    break
            if deadline is not None and now >= deadline:
                self.stop_reason = "time limit"
                break
