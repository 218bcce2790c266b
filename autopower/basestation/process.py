"""The base station process: the coordinator plus the laptop's own host, on one event loop.

The laptop is a node of the team like the robots (components are off-loaded to it and it is
the operator's sink for results), so the process runs a node runtime for it
(`autopower.node.NodeRuntime`, the same as the robots', built by ``host_factory`` with the stores
the CLI gives it) beside the `Coordinator`. Both are driven by the same loop; Zenoh callbacks only
enqueue.

What must survive a restart of the process lives in ``BaseStationConfig.state_dir`` (the team's
state directory; systemd's ``StateDirectory``): the last incarnation this host used and the
operator sink's ledgers (`autopower.node.sink_store`), and a lock that refuses a second base
station of the same team on the same host. The rest is learnt from the robots (`takeover.py`).
"""

from __future__ import annotations

import dataclasses
import faulthandler
import fcntl
import json
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from autopower.basestation.coordinator import Coordinator, CoordinatorConfig
from autopower.basestation.decider import AwaitDecision
from autopower.basestation.operating import status_dict
from autopower.basestation.peer_view import PeerViews
from autopower.basestation.ready_waiters import ReadyWaiters
from autopower.errors import AutoPowerError, ProtocolError
from autopower.model.scenario import Scenario
from autopower.node import NodeRuntime
from autopower.node.ports import NodePorts
from autopower.policies import Policy
from autopower.protocol import (
    OPERATOR_COMMANDS,
    Keys,
    NodeStatus,
    OperatorReply,
    PlanChange,
    PlanUpdate,
    SnapshotRequest,
    StatusDelta,
    decode,
    encode,
)
from autopower.protocol.access import TeamAccess, status_problem
from autopower.protocol.codec import looks_like_message
from autopower.protocol.statuses import StatusAssembler, StatusEncoder, replaces_queued
from autopower.runtime.bus import Bus, Request, ZenohBus, ZenohSettings
from autopower.runtime.cadence import REPEAT_AFTER_PERIODS, REPEAT_EVERY_PERIODS, StatusCadence
from autopower.runtime.events import (
    DecisionAnswered,
    EventQueue,
    LivelinessChanged,
    OperatorRequest,
    Received,
    StopRequested,
    WorkDone,
)
from autopower.runtime.link_traffic import LinkTraffic, link_traffic_of
from autopower.runtime.loop_watch import LoopWatch
from autopower.runtime.relay import Relayer
from autopower.runtime.signatures import load_signing

log = logging.getLogger(__name__)

# Wall seconds of queued events the loop handles in a row before its timers' work (see `run`):
# well under a status period (0.5 s) and a source period at x100 (2.5 ms for a 4 Hz camera is
# the base station's own sources' business; it has none in the paper's mission, and a late tick
# takes its captures from the sensor's queue)
BATCH_S = 0.005
# A stall of the base station's loop is reported past this, and says where the time went (the
# policy decides on a thread of its own, `decider`: the loop only builds the question and
# carries the answer out).
LOOP_STALL_S = 2.0
# How long a stopping base station waits for a decision still on its thread: a MILP that runs on
# is abandoned (a daemon thread), so that the supervisor never has to kill us for it
DECISION_CLOSE_WAIT_S = 2.0
# A base station still closing after this writes every thread's stack to its log: a launcher kills
# it at 8 s, and the stacks say what held it (the decision above is the longest wait it allows)
STOP_STACKS_AFTER_S = 5.0


class _StepTimes:
    """Wall seconds of the steps of a sequence, in order: "0.41 s (replies 0.00, decision 0.40, ...)"."""

    def __init__(self):
        self._start = self._last = time.monotonic()
        self._laps: list[tuple[str, float]] = []

    def lap(self, step: str) -> None:
        now = time.monotonic()
        self._laps.append((step, now - self._last))
        self._last = now

    def __str__(self) -> str:
        laps = ", ".join(f"{step} {seconds:.2f}" for step, seconds in self._laps)
        return f"{self._last - self._start:.2f} s ({laps})"


@dataclass(frozen=True, kw_only=True)
class BaseStationConfig:
    scenario: Scenario
    team: str
    zenoh: ZenohSettings = field(default_factory=ZenohSettings)
    coordinator: CoordinatorConfig = field(default_factory=CoordinatorConfig)
    status_period_s: float = 0.5
    status_rest_period_s: float = 2.0  # at rest (nothing new but what drifts), a status this often
    status_window_s: float = 2.0
    parent_pid: int | None = None
    # after losing sight of a robot, how long to wait for the other robots' word on it:
    # still seen by one of them -> only our link is cut (relay through it); else it is gone
    suspect_settle_s: float = 0.2
    # where what survives a restart is kept (incarnation, sink ledgers, the host's lock); None: nothing
    state_dir: Path | None = None


class BaseStation:
    """The base station (a context manager)."""

    def __init__(self, config: BaseStationConfig, *, host_factory: Callable[..., NodeRuntime], bus: Bus | None = None,
                 policy: Policy | None = None):
        """``policy`` overrides the one ``config.coordinator.policy`` names (for tests)."""
        self.config = config
        self.keys = Keys(config.team)
        self.node = config.scenario.basestation
        # everything it subscribes to is an encoded message: random bytes never take queue room
        # statuses from every robot converge here: a loop that falls behind takes each robot's newest
        # (`_received` ignores an older one anyway), and they never crowd the orders out of the queue
        self.events = EventQueue(bulk_keys=[self.keys.node_data(self.node)], admit=looks_like_message,
                                 newest_only=self._newest_only)
        self._bus = bus
        self._owns_bus = bus is None
        self._handles: list = []
        self._policy = policy
        self._host_factory = host_factory
        self.runtime: NodeRuntime | None = None
        self.traffic: LinkTraffic | None = None  # the bytes on its links, read with its status
        self.coordinator: Coordinator | None = None
        self.stop_reason: str | None = None
        self.garbled = 0
        self.relayer: Relayer | None = None
        self._suspects: dict[str, float] = {}  # robot out of direct sight -> when
        self._status_t: dict[str, float] = {}  # node -> t_unix of its newest status seen
        self.cadence = StatusCadence(config.status_period_s, config.status_rest_period_s)
        self.status_encoder = StatusEncoder()  # our status whole or as its change from the last whole one
        self.statuses_in = StatusAssembler()  # the others' statuses, whole again
        self._lock_fd: int | None = None
        self._kept_incarnation: int | None = None  # what the state directory says we used last
        # operator requests whose reply waits for the decision that carries them out
        self._awaiting_decision: list[tuple[Request, AwaitDecision]] = []
        self._awaiting_ready = ReadyWaiters()  # snapshot queries answered once the team is ready

    def _send_view(self, robot: str, key: str, payload: bytes, period: float) -> None:
        """Our status as ``robot`` acts on it: a heartbeat like the status itself.

        Put on its key whether or not we take it for in sight (a robot we suspect hears it if its
        session holds: sent through relays only, it took us for gone in turn and reported the link
        down), relayed as well when it is out of sight, and repeated while this loop is held up (a
        30-robot fleet's robots took the base station for gone 1 s into its 2.6 s mission-start MILP).
        """
        self._bus.publish(key, payload, reliable=False)
        self._bus.repeat_until_next(key, payload, REPEAT_AFTER_PERIODS * period, REPEAT_EVERY_PERIODS * period)
        if robot not in self.relayer.direct:
            self.relayer.send(robot, key, payload, reliable=False)

    def _newest_only(self, key: str, payload: bytes) -> bool:
        """A robot's status as its change from a whole one, or its acknowledgement to us: each says all
        its older ones said. A whole status is never replaced: the changes that follow it need it."""
        if self.keys.node_of_status(key) is not None:
            return replaces_queued(payload)
        return self.keys.addressed_ends(key) is not None

    def __enter__(self) -> "BaseStation":
        if self._bus is None:
            self._bus = ZenohBus(self.config.zenoh)
        bus, keys = self._bus, self.keys
        scenario = self.config.scenario
        access = TeamAccess(keys, scenario.basestation, tuple(r.name for r in scenario.robots))
        self.signing = load_signing(self.node, self.config.zenoh.tls)  # None: --insecure, nothing signed
        self.relayer = Relayer(node=self.node, bus=bus, keys=keys, count=self._count, access=access,
                               signing=self.signing)
        ports = NodePorts(send_to=self.relayer.send,
                          notify_work=lambda: self.events.post(WorkDone()))  # a stage worker's result is in
        self.runtime = self._host_factory(node=self.node, scenario=scenario, bus=bus, keys=keys, ports=ports)
        if self.config.state_dir is not None:
            self._keep_state(Path(self.config.state_dir))
        kept = self._kept_incarnation
        self.coordinator = Coordinator(scenario=self.config.scenario, bus=bus, keys=keys,
                                       config=self.config.coordinator, policy=self._policy,
                                       incarnation=0 if kept is None else kept + 1,
                                       send_to=self.relayer.send,
                                       on_own_plan=self._own_plan,
                                       on_decision_answer=lambda: self.events.post(DecisionAnswered()))
        self.peer_views = PeerViews(scenario, self.keys)
        self.traffic = link_traffic_of(bus)
        # what is for its host on one subscription (`Keys.node_all`): data, control, relayed control
        # and what robots address to it
        for key in (keys.node_all(self.node), keys.base_all, keys.status_all):
            self._handles.append(bus.subscribe(key, self.events.on_message))
        self._handles.append(bus.serve(keys.operator, self.events.on_request))
        self._handles.append(bus.watch_liveliness(keys.alive_all, self.events.on_liveliness))
        self._handles.append(bus.declare_token(keys.alive(self.node)))
        log.info("base station %s up for team %s (scenario %s)", self.node, self.config.team,
                 self.config.scenario.name)
        return self

    def _count(self, what: str, detail: str = "", level: int = logging.WARNING) -> None:
        """The relayer's errors go to the host's (built after it: the host sends through it)."""
        self.runtime.count(what, detail, level)

    # ---- what survives a restart ----------------------------------------------------------------
    def _keep_state(self, folder: Path) -> None:
        """Lock the state directory (one base station per team and host) and read the incarnation it
        ran last (the coordinator starts one above; the sinks' ledgers there are the host's:
        ``host_factory`` gives it its `SinkStore`)."""
        lock = folder / "basestation.lock"
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o600)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            holder = os.read(fd, 64).decode(errors="replace").strip() or "?"
            os.close(fd)
            raise AutoPowerError(f"another base station of team {self.config.team!r} runs on this host (pid "
                                 f"{holder}, lock {lock}); stop it first, or give this one its own state directory") from None
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self._lock_fd = fd
        try:
            kept = json.loads((folder / "basestation.json").read_text())
            self._kept_incarnation = int(kept["incarnation"])
        except FileNotFoundError:
            pass
        except (OSError, ValueError, KeyError, TypeError) as exc:
            log.warning("base station: %s/basestation.json is unreadable (%s); incarnations restart from the "
                        "robots' reports", folder, exc)

    def _remember_incarnation(self) -> None:
        """Once it runs the mission, this host remembers the incarnation (the next start goes above)."""
        co, folder = self.coordinator, self.config.state_dir
        if folder is None or co.mission is None or self._kept_incarnation == co.takeover.incarnation:
            return
        self._kept_incarnation = co.takeover.incarnation
        path, tmp = Path(folder) / "basestation.json", Path(folder) / "basestation.json.tmp"
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
            with os.fdopen(fd, "w") as f:
                json.dump({"incarnation": co.takeover.incarnation, "leader": co.takeover.leader}, f)
            tmp.replace(path)
        except OSError as exc:
            log.error("base station: cannot remember incarnation %d in %s: %s", co.takeover.incarnation, path, exc)

    def _forget_state(self) -> None:
        """A base station whose launcher owns the team (``parent_pid``: `up`, the test launcher) that
        stops cleanly leaves nothing behind: the team ends with it. Under a service manager (no
        parent) the files stay for the next start; after a kill they stay for the restart."""
        from autopower.basestation.operator import basestation_state_paths

        folder = Path(self.config.state_dir)
        for path in basestation_state_paths(folder):
            try:
                path.unlink()
            except FileNotFoundError:
                pass
            except OSError as exc:
                log.warning("base station: cannot remove %s: %s", path, exc)
        try:
            folder.rmdir()  # only if empty: `up`'s session file is `up`'s to remove
        except OSError:
            pass

    def __exit__(self, *exc) -> None:
        # each step timed: a launcher kills a base station that does not stop within its limit
        # (`up`, the testbed: 8 s), and its log must then say which step held it
        steps = _StepTimes()
        faulthandler.dump_traceback_later(STOP_STACKS_AFTER_S)  # to stderr: the process's log
        self._reply_to_waiting(stopping=True)
        for request in self._awaiting_ready.take_all():
            self._reply_snapshot(request)
        steps.lap("replies")
        if self.coordinator is not None and not self.coordinator.deciding.decider.close(DECISION_CLOSE_WAIT_S):
            log.warning("base station: stopping while the policy still decides (over %.0f s)", DECISION_CLOSE_WAIT_S)
        steps.lap("decision")
        if self.runtime is not None:  # the host's stage worker processes
            self.runtime.components.close()
        steps.lap("stage workers")
        if self.runtime is not None:
            # the held results' writer thread finishes first: nothing is written after the state is
            # forgotten; the sink's last commit is its last status's (the recording's order)
            self.runtime.close_stores(commit_sinks=False)
        steps.lap("held store")
        if (self._lock_fd is not None and self.stop_reason is not None and self.config.parent_pid is not None
                and exc[0] is None):
            self._forget_state()
        if self._lock_fd is not None:
            os.close(self._lock_fd)  # releases the lock (a kill releases it too)
            self._lock_fd = None
        for handle in reversed(self._handles):
            handle.close()
        self._handles.clear()
        steps.lap("subscriptions")
        if self._owns_bus and self._bus is not None:
            self._bus.close()
            self._bus = None
        steps.lap("session")
        faulthandler.cancel_dump_traceback_later()
        log.info("base station: closed in %s", steps)

    def _own_plan(self, plan) -> None:
        try:
            self.runtime.on_plan(plan)
        except Exception:  # the host's trouble must not stop the coordinator's plan from going out
            log.exception("base station: the laptop's host could not take its own plan")
            self.runtime.count("internal-error")

    def request_stop(self, reason: str) -> None:
        self.events.post(StopRequested(reason))

    # ---- events ----------------------------------------------------------------------------------
    def _garbage(self, key: str, exc: Exception) -> None:
        self.garbled += 1
        self.runtime.count("garbled", f"on {key}: {exc}")

    def _handle(self, event) -> None:
        rt, co, keys = self.runtime, self.coordinator, self.keys
        if isinstance(event, Received):
            inner = self.relayer.unwrap(event.key, event.payload)
            if inner is None:
                return
            self._received(*inner, relayed=event.key == keys.node_relay(self.node))
        elif isinstance(event, LivelinessChanged):
            node = keys.node_of_alive(event.key)
            if node is not None and node != self.node:
                rt.on_liveliness(node, event.alive)
                self.relayer.on_liveliness(node, event.alive)
                if event.alive:
                    self._suspects.pop(node, None)
                    co.on_liveliness(node, True)
                    co.link_seen(self.node, node)
                elif node in co.robots:
                    self._suspects[node] = time.time()
                else:
                    co.on_liveliness(node, False)
        elif isinstance(event, OperatorRequest):
            self._operator(event.request)
        elif isinstance(event, WorkDone):
            rt.components.collect_results()
        # DecisionAnswered only wakes the loop: `Coordinator.on_timer` carries the answer out

    def _settle_suspects(self) -> None:
        """Decide about robots we lost sight of: a cut link (relay) or a robot gone."""
        co, now = self.coordinator, time.time()
        for node, since in list(self._suspects.items()):
            if now - since < self.config.suspect_settle_s:
                continue
            del self._suspects[node]
            if self.relayer.reachable(node):
                log.info("base station: %s out of sight but reachable via %s", node,
                         "->".join(self.relayer.path_to(node)))
                co.link_lost(self.node, node, detected_unix=since)
            else:
                co.on_liveliness(node, False, detected_unix=since)
        # a robot kept through a relay whose relays no longer see it is gone too
        for node in list(co.present):
            if node not in self.relayer.direct and node not in self._suspects and not self.relayer.reachable(node):
                co.on_liveliness(node, False)

    def _received(self, key: str, payload: bytes, relayed: bool = False) -> None:
        rt, co, keys = self.runtime, self.coordinator, self.keys
        if True:
            if key == keys.plan:
                try:
                    plan = decode(payload, (PlanUpdate, PlanChange))  # whole or a change: both name their leader
                except ProtocolError:
                    pass  # the runtime counts it
                else:
                    if plan.leader != co.takeover.leader:
                        co.on_rival_plan(plan)  # another base station: the older one steps down
            if rt.on_message(key, payload):
                return
            event_key = key
            try:
                if event_key == keys.inbox:
                    co.on_inbox(payload)
                elif keys.node_of_status(event_key) is not None:
                    msg = decode(payload, (NodeStatus, StatusDelta))
                    problem = status_problem(keys, event_key, msg.node, msg.t_unix, time.time())
                    if problem is not None:
                        rt.count("forged", problem)
                        return
                    if not relayed and msg.node != self.node:  # before the duplicate check
                        self.relayer.on_direct(msg.node)  # (`Relayer.on_direct`: why every direct copy counts)
                    status = self.statuses_in.whole(msg)
                    if status is None:  # a change from a whole status we do not hold: the next whole one will do
                        return
                    # a status can come twice (direct and relayed) and out of order: the newest counts
                    if status.t_unix <= self._status_t.get(status.node, 0.0):
                        return
                    self._status_t[status.node] = status.t_unix
                    if status.node != self.node:
                        self.relayer.on_status(status)
                        rt.on_peer_status(status)  # what it consumed: acks for our retransmit buffer
                        if (status.node in co.robots and status.node not in co.present
                                and self.relayer.reachable(status.node)):
                            co.on_liveliness(status.node, True)  # back, through a relay
                        co.on_rival_status(status)  # a robot on another base station's plan
                        if co.mission is None:
                            co.learn(status)  # what a running team runs, before anything is decided
                        # before it runs the mission (plan_epoch -1) a robot's status only says who
                        # it sees (for the relay) and that it is there: its link view may predate
                        # our token reaching it, so it must not count as a link going down
                        elif status.plan_epoch >= 0 and (status.node in co.present or status.node in self.relayer.direct):
                            co.on_status(status)
                else:
                    rt.count("unexpected-key", event_key)
            except ProtocolError as exc:
                self._garbage(event_key, exc)

    def _operator(self, request: Request) -> None:
        try:
            cmd = decode(request.payload, OPERATOR_COMMANDS)
        except ProtocolError as exc:
            self._garbage(self.keys.operator, exc)
            self._reply(request, OperatorReply(ok=False, message=f"bad request: {exc}"))
            return
        if (isinstance(cmd, SnapshotRequest) and cmd.until_ready_s > 0 and not self.coordinator.ready
                and self._awaiting_ready.hold(request, time.time() + cmd.until_ready_s)):
            return  # answered by `_reply_when_ready`
        try:
            reply = self.coordinator.on_operator(cmd)
        except BaseException:
            request.close()
            raise
        if isinstance(reply, AwaitDecision):  # replied to once the decision is carried out
            self._awaiting_decision.append((request, reply))
            return
        if reply.snapshot:
            reply = dataclasses.replace(reply, snapshot=self.snapshot(reply.snapshot))
        self._reply(request, reply)

    def _reply_snapshot(self, request: Request) -> None:
        try:
            self._reply(request, OperatorReply(ok=True, message="snapshot", snapshot=self.snapshot()))
        except Exception:  # the operator gave up waiting (its query timed out)
            log.warning("base station: could not answer a snapshot query", exc_info=True)

    def _reply_when_ready(self) -> None:
        """Answer the snapshot queries held for the team to get ready (`ReadyWaiters`) that are due."""
        for request in self._awaiting_ready.due(self.coordinator.ready, time.time()):
            self._reply_snapshot(request)

    def _reply(self, request: Request, reply: OperatorReply) -> None:
        try:
            request.reply(encode(reply))
        finally:
            request.close()

    def _reply_to_waiting(self, *, stopping: bool = False) -> None:
        """Reply to the operator commands whose decision is carried out (all of them when stopping)."""
        still = []
        for request, waiting in self._awaiting_decision:
            reply = self.coordinator.reply_when_decided(waiting)
            if reply is None and stopping:
                reply = OperatorReply(ok=False, message="the base station stopped before the decision that carries "
                                                        "the command out; give it again to the base station that runs "
                                                        "the team")
            if reply is None:
                still.append((request, waiting))
                continue
            try:
                self._reply(request, reply)
            except Exception:  # the operator gave up waiting (its query timed out): the command stands
                log.warning("base station: could not reply to an operator command", exc_info=True)
        self._awaiting_decision = still

    def snapshot(self, base: dict[str, Any] | None = None) -> dict[str, Any]:
        snap = dict(base) if base is not None else self.coordinator.snapshot()
        self.runtime.errors.update(self.events.counts())  # dropped before the loop saw them
        if self.runtime.started:
            status = self.runtime.status(self.config.status_window_s * self.runtime.clock.speed,
                                         self.events.depth(), self.events.bulk_wait_s())
            snap["basestation"] = status_dict(status)
        else:
            snap["basestation"] = None
        return snap

    def _quiet(self) -> bool:
        """Nothing here is timed but the status and the coordinator's deadlines: the host is idle, the
        coordinator too (`Coordinator.idle`), no robot out of sight awaits the others' word."""
        return self.runtime.idle() and self.coordinator.idle() and not self._suspects

    def run(self, max_wall_s: float | None = None) -> str:
        """Run until stopped or ``max_wall_s``; return why it stopped.

        At rest (`_quiet`, its status held back) the loop wakes only for an event or a deadline, not
        every status period: an event then gets the status built at once (sent if it says something new).
        """
        rt, co = self.runtime, self.coordinator
        deadline = None if max_wall_s is None else time.time() + max_wall_s
        next_status, period = time.time(), self.config.status_period_s
        own_status = self.keys.status(self.node)  # Zenoh gives our own puts to our subscribers too
        news = False  # an event handled since the last status was built (not our own status back)
        loop_watch = LoopWatch("base station", after_s=LOOP_STALL_S)
        try:
            while True:
                now = time.time()
                quiet = self._quiet()
                wake = [self.cadence.next_build(next_status, quiet=quiet), co.next_deadline_unix()]
                wake += [t + self.config.suspect_settle_s for t in self._suspects.values()]
                if deadline is not None:
                    wake.append(deadline)
                if rt.started and (t := rt.next_deadline()) is not None:
                    wake.append(rt.clock.wall_at(t))
                if (t := self._awaiting_ready.next_deadline()) is not None:
                    wake.append(t)
                loop_watch.waiting()
                event = self.events.get(max(0.0, min(wake) - now))
                loop_watch.working()
                # the events already queued are handled one after the other before the timers' work
                # (at most a batch's worth of wall time): at x50 the base station takes ~1,000 messages
                # a second, and the timers' work after each one cost more than most of them did
                batch_end = time.monotonic() + BATCH_S
                while event is not None and not isinstance(event, StopRequested):
                    news = news or (quiet and not (isinstance(event, Received) and event.key == own_status))
                    try:
                        self._handle(event)
                    except Exception:  # never let one bad event stop the coordinator
                        log.exception("base station: error handling %s", type(event).__name__)
                        rt.count("internal-error")
                    event = self.events.get(0.0) if time.monotonic() < batch_end else None
                if isinstance(event, StopRequested):
                    self.stop_reason = event.reason
                    break
                self._settle_suspects()
                co.on_timer()
                if self._awaiting_decision:
                    self._reply_to_waiting()
                if self._awaiting_ready:
                    self._reply_when_ready()
                if co.takeover.stepped_down is not None:
                    self.stop_reason = f"stepped down: {co.takeover.stepped_down}"
                    break
                self._remember_incarnation()
                if rt.started:
                    rt.on_timer()
                now = time.time()
                resting = quiet and self.cadence.resting
                due = now >= self.cadence.next_build(next_status, quiet=quiet) or (resting and news)
                # at rest: the events that came meanwhile first, then one status (see the agent's loop)
                if due and not (resting and self.events.depth()
                                and now < self.cadence.next_build(next_status, quiet=True) + period):
                    news = False
                    # on the tick grid; one built at rest (its rest period over, or for an event) starts a new grid
                    next_status = now + period if resting else max(next_status + period, now)
                    status = None
                    rt.errors.update(self.events.counts())  # dropped before the loop saw them (absolute counts)
                    if self._bus.repeated:  # statuses put again while the loop was held up
                        rt.counters["status-repeats"] = self._bus.repeated
                    if self.events.superseded:  # robots' statuses (and acks) replaced by a newer one while queued
                        rt.counters["statuses-superseded"] = self.events.superseded
                    if self.statuses_in.unapplied:  # changes from a whole status not held (missed or newer)
                        rt.counters["status-deltas-unapplied"] = self.statuses_in.unapplied
                    if self.traffic is not None and self.traffic.due(time.monotonic()):
                        rt.metering.charge_control(self.traffic.poll(self._bus.links()), self.traffic.packets_by_peer)  # its links' bytes, metered
                    rt.metering.charge_runtime(time.process_time())  # its own CPU, measured (mains: reported, not charged)
                    built = None
                    if rt.started:  # held back when nothing in it is new but what drifts or counts
                        built = rt.status(self.config.status_window_s * rt.clock.speed, self.events.depth(),
                                          self.events.bulk_wait_s())
                        co.on_host_status(built)
                        status = self.cadence.due(built, now)
                    else:  # no mission yet: each robot in reach hears that we run no plan
                        for robot, key, payload in self.peer_views.addressed(co, None, now, period):
                            self._send_view(robot, key, payload, period)
                    if built is not None and (status is not None or not self._quiet()):
                        # what is acknowledged is kept first, every period (held back too: only counts
                        # moved, the heartbeat waits): the sink's notes, then the recording of those
                        # outputs, so that each commit is flushed before the next (`node.sink_store`);
                        # an operator's snapshot builds a status too but acknowledges nothing
                        rt.commit_sinks()
                        self._bus.flush_recording()
                        rt.holds.settle_store()  # what the robots acknowledged leaves the held journal
                        if status is not None:
                            # the whole status for a standby base station and the recording, to each robot
                            # the part it acts on (`peer_view`), relayed to those out of sight; each is a
                            # heartbeat
                            key, payload = self.keys.status(self.node), self.status_encoder.encode(status)
                            self._bus.publish(key, payload, reliable=False)
                            self._bus.repeat_until_next(key, payload, REPEAT_AFTER_PERIODS * status.next_status_s,
                                                        REPEAT_EVERY_PERIODS * status.next_status_s)
                            for robot, key, payload in self.peer_views.addressed(
                                    co, status, now, status.next_status_s, self.statuses_in.take_wanted()):
                                self._send_view(robot, key, payload, status.next_status_s)
                        rt.acknowledging.send(self.relayer.reachable, built.queue_wait_s)  # to the nodes that sent us frames
                    if self.config.parent_pid is not None and os.getppid() != self.config.parent_pid:
                        self.stop_reason = "parent exited"
                        break
                if deadline is not None and now >= deadline:
                    self.stop_reason = "time limit"
                    break
        finally:
            loop_watch.stop()
        log.info("base station stopping: %s", self.stop_reason)
        return self.stop_reason
