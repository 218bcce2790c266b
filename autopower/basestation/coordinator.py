"""The base station's coordinator: tracks the team, plans, and moves components.

It owns the *desired* placement (the planner's allocation, overridden by operator pins) and
the *confirmed* one (what nodes have acknowledged), and closes the gap one stage at a time:

- a stage with no live host gets `Assign` (a fresh instance);
- a stage that must move gets `Prepare` on the new host, then (on `Prepared`) `MigrateOut` on
  the old one, which ships its state along the data path; `StageReady` from the new host
  confirms it. Migrations of one stage are never overlapped.

Every change of the confirmed placement is published as a `PlanUpdate` (which also carries
the mission clock), so sources and senders follow. Replanning happens when an agent joins or
leaves, a link changes, a battery drifts from the plan's prediction, the operator enables or
disables a chain, and periodically with the remaining energies (kept only if it gains).
"""

from __future__ import annotations

import dataclasses
import logging
import statistics
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable

from autopower.bus import Bus
from autopower.clock import VirtualClock
from autopower.errors import AutoPowerError
from autopower.model import Network, evaluate
from autopower.protocol import (
    Assign,
    AutoCommand,
    ChainCommand,
    Keys,
    LinkCommand,
    LinkInfo,
    MigrateCommand,
    MigrateOut,
    MissionInfo,
    NodeStatus,
    OperatorReply,
    PlanUpdate,
    Prepare,
    Prepared,
    Release,
    SnapshotRequest,
    StageReady,
    encode,
)
from autopower.scenario import Scenario

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class CoordinatorConfig:
    speed: float = 10.0
    topology: str | None = None  # None: the scenario's
    media: dict[str, str] | None = None  # group -> medium, fixed; None: the planner chooses
    pins: dict[str, str] = field(default_factory=dict)  # stage -> node, fixed by the operator
    auto_replan: bool = True  # replan on battery drift / periodically (joins, leaves, commands always)
    replan_interval_s: float = 600.0  # virtual seconds between re-plans with remaining energies
    min_gain: float = 0.01  # a re-plan must lengthen the lifetime by this much to move anything
    drift_tolerance: float = 0.03  # relative drift of a battery from the plan that triggers a re-plan
    drift_min_window_s: float = 60.0  # virtual seconds of a plan before drift is judged
    migration_timeout_s: float = 10.0  # wall seconds before a stuck migration is abandoned
    start_grace_s: float = 30.0  # wall seconds to wait for every robot before starting without some
    plan_republish_s: float = 1.0  # wall seconds between repeats of the current plan (late joiners)
    link_down_after_s: float = 3.0  # wall seconds a never-seen-up link must be reported down before it counts
    heal_hold_s: float = 2.0  # wall seconds a link must be back before plans may use it again (no flapping)
    heal_min_gain: float = 0.01  # moving back after a heal must lengthen the lifetime by this much


@dataclass
class Migration:
    stage: str
    generation: int
    to_node: str
    from_node: str | None  # None: a fresh assignment
    phase: str  # "assigning" | "preparing" | "transferring"
    started_unix: float


@dataclass
class Baseline:
    """What the plan predicts for one robot's battery from a starting point."""

    t_virtual: float
    battery_j: float
    predicted_w: float


class Coordinator:
    def __init__(self, *, scenario: Scenario, bus: Bus, keys: Keys, config: CoordinatorConfig,
                 planner: Callable | None = None, wall_fn: Callable[[], float] = time.time):
        if planner is None:
            from autopower.planner import PlanRequest, plan

            def planner(**kwargs):
                return plan(PlanRequest(**kwargs))
        self.scenario = scenario
        self.bus = bus
        self.keys = keys
        self.config = config
        self.planner = planner
        self.wall = wall_fn
        self.base = scenario.basestation
        self.robots = [r.name for r in scenario.robots]
        self.chain_of = {s.name: c for c in scenario.chains for s in c.stages}
        for stage, node in config.pins.items():
            self._check_pin(stage, node)

        self.mission: MissionInfo | None = None
        self.clock: VirtualClock | None = None
        self.present: set[str] = set()
        self.departed: set[str] = set()  # left or depleted: excluded until they come back
        self.statuses: dict[str, NodeStatus] = {}
        self.placement: dict[str, str] = {}
        self.target: dict[str, str] = {}
        self.migrations: dict[str, Migration] = {}
        self.pins: dict[str, str] = dict(config.pins)
        self.disabled: set[str] = set()
        self.running: dict[str, int] = {}
        self.runs: dict[str, int] = {}  # chain -> current run number
        self.run_live: dict[str, bool] = {}  # has the current run produced anything yet
        self.plan_obj: Any = None
        self.plan_network: Network | None = None
        self.network_override: Network | None = None  # operator link commands
        self.links_down: set[frozenset[str]] = set()
        self._link_reports: dict[frozenset[str], float] = {}
        self.predicted_w: dict[str, float] = {}
        self.predicted_lifetime_s: float | None = None
        self.plan_t_virtual = 0.0
        self.baselines: dict[str, Baseline] = {}
        self.plan_error: str | None = None
        self.epoch = 0
        self.generation = 0
        self.first_seen_unix: float | None = None
        self.next_republish = 0.0
        self.next_periodic_replan: float | None = None
        self.events: deque[str] = deque(maxlen=50)
        self.downtimes_ms: list[float] = []
        self.migration_log: deque[dict] = deque(maxlen=200)
        self.migrations_done = 0
        self.assignments_done = 0
        self.aborted = 0
        self.replans = 0
        self.first_depletion: dict[str, float] | None = None
        self._link_seen_up: set[frozenset[str]] = set()
        self._link_up_since: dict[frozenset[str], float] = {}
        # faults as the base station saw them: detection and when the team ran its new plan
        self.faults: deque[dict] = deque(maxlen=100)
        # robots back after an absence: their report of what they host (a subgroup may have
        # reallocated without us) is the starting point, not our stale placement
        self._awaiting_actual: dict[str, float] = {}
        self.adopted = 0
        # how messages leave (the process puts its `Relayer` here: robots out of sight are
        # reached through other agents); defaults publish directly
        self.send_to: Callable[[str, str, bytes], object] = lambda node, key, payload: self.bus.publish(key, payload)
        self.also_relay: Callable[[list[str], str, bytes], object] = lambda nodes, key, payload: None

    # ---- helpers ----------------------------------------------------------------------------------
    def now(self) -> float:
        return self.clock.now() if self.clock else 0.0

    def note(self, text: str) -> None:
        line = f"t={self.now():.1f}s {text}"
        self.events.append(line)
        log.info("coordinator: %s", line)

    def alive_nodes(self) -> set[str]:
        return (self.present - self.departed) | {self.base}

    def _check_pin(self, stage: str, node: str) -> None:
        if stage not in self.chain_of:
            raise AutoPowerError(f"unknown stage {stage!r}; stages: {', '.join(self.chain_of)}")
        if node not in self.scenario.node_names():
            raise AutoPowerError(f"unknown node {node!r}; nodes: {', '.join(self.scenario.node_names())}")

    def _send(self, node: str, msg) -> None:
        self.send_to(node, self.keys.node_control(node), encode(msg))

    # ---- faults -------------------------------------------------------------------------------------
    def record_fault(self, kind: str, target: str, detected_unix: float) -> None:
        self.faults.append({"kind": kind, "target": target, "detected_unix": detected_unix,
                            "decided_unix": self.wall(), "epoch": None, "reconfigured_unix": None})

    def _mark_reconfigured(self) -> None:
        """A fault is handled once its new plan runs: placed, and every robot in reach runs its epoch."""
        open_faults = [f for f in self.faults if f["reconfigured_unix"] is None]
        if not open_faults or not self.ready:
            return
        for fault in open_faults:
            if fault["epoch"] is None:
                fault["epoch"] = self.epoch
        for fault in open_faults:
            acked = all(self.statuses.get(r) is not None and self.statuses[r].plan_epoch >= fault["epoch"]
                        for r in self.alive_nodes() if r in self.robots)
            if acked:
                fault["reconfigured_unix"] = self.wall()
                self.note(f"{fault['kind']} {fault['target']}: reconfigured "
                          f"{fault['reconfigured_unix'] - fault['detected_unix']:.3f} s after detection")

    def link_lost(self, a: str, b: str, detected_unix: float | None = None) -> None:
        """A link an end of which is this base station (seen by its own liveliness) went down."""
        pair = frozenset((a, b))
        self._link_up_since.pop(pair, None)
        if pair in self.links_down:
            return
        self.links_down.add(pair)
        self.record_fault("link-down", "-".join(sorted(pair)), detected_unix or self.wall())
        self.note(f"link {a}-{b} is down")
        self.replan("link change")

    def link_seen(self, a: str, b: str) -> None:
        """Evidence that a link works (its ends see each other)."""
        pair = frozenset((a, b))
        self._link_seen_up.add(pair)
        self._link_reports.pop(pair, None)
        if pair in self.links_down:
            self._link_up_since.setdefault(pair, self.wall())

    def _heal_links(self) -> None:
        now = self.wall()
        healed = [p for p, since in self._link_up_since.items()
                  if p in self.links_down and now - since >= self.config.heal_hold_s]
        for pair in healed:
            self.links_down.discard(pair)
            self._link_up_since.pop(pair, None)
            self.note(f"link {'-'.join(sorted(pair))} is back (up for {self.config.heal_hold_s:g} s)")
        if healed:
            self.replan("links back", hold_placement_gain=self.config.heal_min_gain)

    @property
    def ready(self) -> bool:
        """The mission runs and every desired stage runs where the plan wants it."""
        return (self.mission is not None and not self.migrations and self.plan_obj is not None
                and all(self.placement.get(s) == n for s, n in self.target.items()))

    # ---- mission start --------------------------------------------------------------------------------
    def maybe_start(self) -> None:
        if self.mission is not None:
            return
        everyone = set(self.robots) <= self.present
        late = (self.first_seen_unix is not None
                and self.wall() - self.first_seen_unix >= self.config.start_grace_s)
        if not (everyone or (late and self.present)):
            return
        self.mission = MissionInfo(scenario=self.scenario.name, accounting=self.scenario.accounting,
                                   epoch_unix=self.wall(), speed=self.config.speed,
                                   energies_j=self.scenario.energies_j())
        self.clock = VirtualClock(self.mission.epoch_unix, self.mission.speed, wall_fn=self.wall)
        self.next_periodic_replan = self.config.replan_interval_s
        missing = set(self.robots) - self.present
        self.note("mission started" + (f" without {', '.join(sorted(missing))}" if missing else ""))
        self.replan("mission start")

    # ---- planning --------------------------------------------------------------------------------------
    def remaining_energies(self) -> dict[str, float]:
        out = {}
        for robot in self.robots:
            status = self.statuses.get(robot)
            if status is not None and status.battery_j is not None:
                out[robot] = max(status.battery_j, 1e-6)
            else:
                out[robot] = self.scenario.robot(robot).energy_j
        return out

    def _network_for_request(self) -> Network | None:
        base = self.network_override
        if base is None and self.config.media:
            base = self.scenario.network(topology=self.config.topology, media=self.config.media)
        if self.links_down:
            if base is None:
                # the whole topology (with the media in use), minus what is down now: a link
                # that came back is in it again
                media = self.plan_obj.network.media_by_group() if self.plan_obj is not None else None
                try:
                    base = self.scenario.network(topology=self.config.topology, media=media)
                except AutoPowerError:
                    base = self.scenario.network(topology=self.config.topology)
            if base is not None:
                for pair in self.links_down:
                    a, b = sorted(pair)
                    base = base.without_link(a, b)
        return base

    def replan(self, reason: str, *, only_if_better: bool = False, hold_placement_gain: float | None = None) -> bool:
        """Plan again; with ``hold_placement_gain`` the new network is adopted but components
        move only if that lengthens the lifetime by more than this fraction (hysteresis)."""
        if self.mission is None:
            return False
        if self._awaiting_actual and "joined" not in reason:
            # robots are back and have not said what they run yet: plan once they have
            self.note(f"re-plan ({reason}) deferred until {', '.join(sorted(self._awaiting_actual))} report")
            return False
        unavailable = frozenset(r for r in self.robots if r not in self.alive_nodes())
        if len(unavailable) == len(self.robots):
            self.note(f"no robot left ({reason}); nothing to plan")
            self.target = {}
            self.reconcile()
            self.publish_plan()
            return False
        energies = self.remaining_energies()
        request = dict(scenario=self.scenario, network=self._network_for_request(), topology=self.config.topology,
                       energies_j=energies, disabled_chains=frozenset(self.disabled),
                       unavailable_nodes=unavailable)
        try:
            plan = self.planner(**request)
        except AutoPowerError as exc:  # InfeasibleError, or a request the planner rejects
            self.plan_error = str(exc)
            self.note(f"re-plan ({reason}) found nothing feasible: {exc}")
            return False
        self.plan_error = None
        if only_if_better and self.plan_obj is not None:
            current = self._evaluate(self.target, self.plan_network, energies)
            new_life = plan.evaluation.lifetime_s or 0.0
            if current is not None and current.lifetime_s and new_life < current.lifetime_s * (1 + self.config.min_gain):
                self._reset_baselines()
                return False
        target = dict(plan.allocation)
        if hold_placement_gain is not None and self.target and target != self.target \
                and set(target) == set(self.target):
            current = self._evaluate(self.target, plan.network, energies)
            new_life = plan.evaluation.lifetime_s or 0.0
            if current is not None and current.lifetime_s and new_life < current.lifetime_s * (1 + hold_placement_gain):
                self.note(f"{reason}: moving would gain {new_life / current.lifetime_s - 1:+.2%} "
                          f"(< {hold_placement_gain:.0%}); components stay where they are")
                target = dict(self.target)
        self.replans += 1
        self.plan_obj = plan
        self.plan_network = plan.network
        for stage, node in self.pins.items():
            if stage in target and node in self.alive_nodes():
                target[stage] = node
        changed = {s for s in target if self.target.get(s) != target[s]} | (set(self.target) - set(target))
        self.target = target
        lifetime = plan.evaluation.lifetime_rounded_s
        self.note(f"plan ({reason}): lifetime {lifetime} s, media {plan.network.media_by_group()}, "
                  f"{len(changed)} stage(s) to place" + (f", dropped {', '.join(plan.dropped)}" if plan.dropped else ""))
        self._predict()
        self.reconcile()
        self.publish_plan()
        return True

    def _evaluate(self, allocation: dict[str, str], network: Network | None, energies: dict[str, float]):
        if network is None or not allocation:
            return None
        active = {self.chain_of[s].name for s in allocation}
        disabled = frozenset(c.name for c in self.scenario.chains if c.name not in active)
        try:
            return evaluate(self.scenario, network.without_nodes(
                {r for r in self.robots if r not in self.alive_nodes()}), allocation,
                energies_j=energies, disabled_chains=disabled)
        except AutoPowerError:
            return None

    def _predict(self) -> None:
        ev = self._evaluate(self.target, self.plan_network, self.remaining_energies())
        self.predicted_w = {r: p.total_w for r, p in ev.robots.items()} if ev else {}
        self.predicted_lifetime_s = ev.lifetime_s if ev else None
        self.plan_t_virtual = self.now()
        self._reset_baselines()

    def _reset_baselines(self) -> None:
        self.baselines.clear()  # re-anchored from the next status that reflects the settled plan

    # ---- placement -------------------------------------------------------------------------------------
    def _next_generation(self) -> int:
        self.generation += 1
        return self.generation

    def reconcile(self) -> None:
        alive = self.alive_nodes()
        for stage in list(self.placement):
            if stage not in self.target and stage not in self.migrations:
                node = self.placement.pop(stage)
                if node in alive:
                    self._send(node, Release(stage=stage, generation=self._next_generation()))
        for stage, want in self.target.items():
            if stage in self.migrations or self.placement.get(stage) == want or want not in alive:
                continue
            have = self.placement.get(stage)
            chain = self.chain_of[stage]
            gen = self._next_generation()
            if have is None or have not in alive:
                self.placement.pop(stage, None)
                run, resume = self._run_for(chain)
                self.migrations[stage] = Migration(stage, gen, want, None, "assigning", self.wall())
                self._send(want, Assign(stage=stage, generation=gen, chain=chain.name, run=run, resume_seq=resume))
            else:
                self.migrations[stage] = Migration(stage, gen, want, have, "preparing", self.wall())
                self._send(want, Prepare(stage=stage, generation=gen, from_node=have))
        self._update_running()

    def _run_for(self, chain) -> tuple[int, int | None]:
        """The run a fresh stage instance joins, and the seq it starts at.

        A chain that had stopped entirely (disabled, or its only host died) starts a new run at
        seq 0; a stage replacing a dead host in a chain that keeps running continues the run
        from the first input it sees.
        """
        names = {s.name for s in chain.stages}
        busy = any(s in self.placement or s in self.migrations for s in names)
        if not busy and chain.name not in self.running:
            self.runs[chain.name] = self.runs.get(chain.name, -1) + 1
            self.run_live[chain.name] = False
        return self.runs[chain.name], (None if self.run_live.get(chain.name) else 0)

    def _update_running(self) -> None:
        running = {}
        for chain in self.scenario.chains:
            names = [s.name for s in chain.stages]
            if names and all(s in self.target and s in self.placement for s in names):
                running[chain.name] = self.runs[chain.name]
                self.run_live[chain.name] = True
        self.running = running

    def on_prepared(self, msg: Prepared) -> None:
        m = self.migrations.get(msg.stage)
        if m is None or m.generation != msg.generation or m.phase != "preparing" or msg.node != m.to_node:
            return
        m.phase = "transferring"
        self._send(m.from_node, MigrateOut(stage=msg.stage, generation=m.generation, to_node=m.to_node))

    def on_stage_ready(self, msg: StageReady) -> None:
        m = self.migrations.get(msg.stage)
        if m is None or m.generation != msg.generation or msg.node != m.to_node:
            return
        del self.migrations[msg.stage]
        self.placement[msg.stage] = msg.node
        if m.from_node is None:
            self.assignments_done += 1
        else:
            self.migrations_done += 1
            self.downtimes_ms.append(msg.downtime_ms)
            self.migration_log.append({"stage": msg.stage, "from": m.from_node, "to": msg.node,
                                       "downtime_ms": msg.downtime_ms, "held_inputs": msg.buffered,
                                       "total_ms": (self.wall() - m.started_unix) * 1e3})
            log.info("coordinator: %s moved %s -> %s in %.1f ms (%d inputs held)", msg.stage, m.from_node,
                     msg.node, msg.downtime_ms, msg.buffered)
        self.reconcile()
        self.publish_plan()

    def _abort(self, stage: str, why: str) -> None:
        m = self.migrations.pop(stage)
        self.aborted += 1
        self.note(f"{stage}: {m.phase} to {m.to_node} abandoned ({why}); restarting it without state")
        gen = self._next_generation()
        for node in {m.to_node, m.from_node} - {None}:
            if node in self.alive_nodes():
                self._send(node, Release(stage=stage, generation=gen))
        self.placement.pop(stage, None)

    # ---- events --------------------------------------------------------------------------------------------
    def on_liveliness(self, node: str, alive: bool, detected_unix: float | None = None) -> None:
        if node == self.base or node not in self.robots:
            return
        if alive:
            if node in self.present and node not in self.departed:
                return
            self.present.add(node)
            self.departed.discard(node)
            if self.first_seen_unix is None:
                self.first_seen_unix = self.wall()
            self.note(f"{node} joined")
            if self.mission is None:
                self.maybe_start()
            else:
                self._awaiting_actual[node] = self.wall() + 1.0  # replan once it says what it hosts
        else:
            if node not in self.present:
                return
            self.present.discard(node)
            self.record_fault("node-left", node, detected_unix or self.wall())
            self.note(f"{node} left")
            self._node_lost(node)
            if self.mission is not None:
                self.replan(f"{node} left")

    def _node_lost(self, node: str) -> None:
        for stage, m in list(self.migrations.items()):
            if node in (m.to_node, m.from_node):
                self._abort(stage, f"{node} left")
        for stage, host in list(self.placement.items()):
            if host == node:
                del self.placement[stage]
        self._update_running()

    def on_status(self, status: NodeStatus) -> None:
        if status.node not in self.robots:
            return
        self.statuses[status.node] = status
        if status.depleted:
            if status.node not in self.departed:
                self.departed.add(status.node)
                if self.first_depletion is None:
                    self.first_depletion = {"robot": status.node, "t_virtual": status.t_virtual}
                self.note(f"{status.node} ran out of energy")
                self._node_lost(status.node)
                self.replan(f"{status.node} depleted")
            return
        if status.node in self._awaiting_actual:
            del self._awaiting_actual[status.node]
            self._adopt_actual(status)
            if not self._awaiting_actual:  # every robot that came back has said what it runs
                self.replan(f"{status.node} joined (from what the robots report hosting)")
        self._check_links(status)
        self._check_drift(status)

    def _adopt_actual(self, status: NodeStatus) -> None:
        """Take the stages a returning robot runs as placed there (and stop our stale copies)."""
        alive = self.alive_nodes()
        for stage, state in status.hosted.items():
            if state != "running" or stage not in self.chain_of or stage in self.migrations:
                continue
            previous = self.placement.get(stage)
            if previous == status.node:
                continue
            # generations handed out without us are time-based: jump past them
            self.generation = max(self.generation, int(self.wall() * 1000) + 1)
            self.placement[stage] = status.node
            self.adopted += 1
            self.note(f"{stage} runs on {status.node} (agreed without the base station); adopted")
            if previous is not None and previous in alive:
                self._send(previous, Release(stage=stage, generation=self._next_generation()))

    def _topology_pairs(self) -> set[frozenset[str]]:
        network = self.scenario.network(topology=self.config.topology)
        return {frozenset((l.a, l.b)) for l in network.links}

    def _check_links(self, status: NodeStatus) -> None:
        """A link counts as down once an end has reported it so for ``link_down_after_s``."""
        now = self.wall()
        alive = self.alive_nodes()
        pairs = self._topology_pairs()
        changed = False
        for peer, up in status.links.items():
            pair = frozenset((status.node, peer))
            if pair not in pairs:
                continue
            if up:
                self.link_seen(status.node, peer)
                continue
            if peer not in alive or status.node not in alive:
                self._link_reports.pop(pair, None)
                continue
            self._link_up_since.pop(pair, None)
            since = self._link_reports.setdefault(pair, now)
            # an end that saw the link up and now reports it down has seen its lease expire:
            # that is the detection; a link never seen up gets the start-up grace
            wait = 0.0 if pair in self._link_seen_up else self.config.link_down_after_s
            if now - since >= wait and pair not in self.links_down:
                self.links_down.add(pair)
                self.record_fault("link-down", "-".join(sorted(pair)), since)
                self.note(f"link {status.node}-{peer} is down")
                changed = True
        if changed:
            self.replan("link change")

    def _check_drift(self, status: NodeStatus) -> None:
        if not self.config.auto_replan or status.battery_j is None or not self.ready:
            return
        if status.plan_epoch != self.epoch or status.node not in self.predicted_w:
            return
        base = self.baselines.get(status.node)
        if base is None:
            self.baselines[status.node] = Baseline(status.t_virtual, status.battery_j, self.predicted_w[status.node])
            return
        elapsed = status.t_virtual - base.t_virtual
        if elapsed < self.config.drift_min_window_s:
            return
        predicted = base.predicted_w * elapsed
        measured = base.battery_j - status.battery_j
        if predicted > 0 and abs(measured - predicted) > self.config.drift_tolerance * predicted:
            self.note(f"{status.node} drew {measured / elapsed:.3f} W, plan said {base.predicted_w:.3f} W")
            if not self.replan(f"{status.node} battery drift", only_if_better=True):
                self._reset_baselines()

    def on_timer(self) -> None:
        now_wall = self.wall()
        self.maybe_start()
        if self.mission is not None:
            late = [n for n, deadline in self._awaiting_actual.items() if now_wall >= deadline]
            for node in late:
                del self._awaiting_actual[node]
            if late and not self._awaiting_actual:
                self.replan(f"{', '.join(late)} joined (no report in time)")
            self._heal_links()
            self._mark_reconfigured()
        for stage, m in list(self.migrations.items()):
            if now_wall - m.started_unix > self.config.migration_timeout_s:
                self._abort(stage, f"no answer in {self.config.migration_timeout_s:g} s")
                self.reconcile()
                self.publish_plan()
        if self.mission is None:
            return
        if (self.config.auto_replan and self.next_periodic_replan is not None
                and self.now() >= self.next_periodic_replan):
            self.next_periodic_replan = self.now() + self.config.replan_interval_s
            self.replan("periodic, remaining energies", only_if_better=True)
        if now_wall >= self.next_republish:
            self.publish_plan(repeat=True)

    def next_deadline_unix(self) -> float:
        return min([self.next_republish] + [m.started_unix + self.config.migration_timeout_s
                                             for m in self.migrations.values()])

    def publish_plan(self, repeat: bool = False) -> None:
        if self.mission is None:
            return
        if not repeat:
            self.epoch += 1
        network = self.plan_network
        links = tuple(LinkInfo(a=l.a, b=l.b, medium=l.medium) for l in network.links) if network else ()
        update = PlanUpdate(epoch=self.epoch, mission=self.mission, placement=dict(self.placement),
                            running=dict(self.running), links=links, predicted_w=dict(self.predicted_w),
                            predicted_lifetime_s=self.predicted_lifetime_s, plan_t_virtual=self.plan_t_virtual)
        payload = encode(update)
        self.bus.publish(self.keys.plan, payload)
        self.also_relay([r for r in self.robots if r in self.alive_nodes()], self.keys.plan, payload)
        self.next_republish = self.wall() + self.config.plan_republish_s

    # ---- operator ---------------------------------------------------------------------------------------------
    def on_operator(self, cmd) -> OperatorReply:
        try:
            if isinstance(cmd, SnapshotRequest):
                return OperatorReply(ok=True, message="snapshot", snapshot=self.snapshot())
            if self.mission is None:
                return OperatorReply(ok=False, message="the mission has not started yet (waiting for agents)",
                                     snapshot=self.snapshot())
            if isinstance(cmd, ChainCommand):
                self.scenario.chain(cmd.chain)
                if cmd.enabled == (cmd.chain not in self.disabled):
                    return OperatorReply(ok=True, message=f"{cmd.chain} already {'enabled' if cmd.enabled else 'disabled'}")
                (self.disabled.discard if cmd.enabled else self.disabled.add)(cmd.chain)
                ok = self.replan(f"operator {'enabled' if cmd.enabled else 'disabled'} {cmd.chain}")
                return OperatorReply(ok=ok, message=self._summary(ok))
            if isinstance(cmd, MigrateCommand):
                self._check_pin(cmd.stage, cmd.to_node)
                if cmd.to_node not in self.alive_nodes():
                    return OperatorReply(ok=False, message=f"{cmd.to_node} is not in the team now")
                if cmd.stage not in self.target:
                    return OperatorReply(ok=False, message=f"{cmd.stage} does not run now (chain disabled or dropped)")
                self.pins[cmd.stage] = cmd.to_node
                self.target[cmd.stage] = cmd.to_node
                self._predict()
                self.reconcile()
                self.publish_plan()
                return OperatorReply(ok=True, message=f"{cmd.stage} pinned to {cmd.to_node}")
            if isinstance(cmd, AutoCommand):
                self.pins.clear()
                ok = self.replan("operator cleared pins")
                return OperatorReply(ok=ok, message=self._summary(ok))
            if isinstance(cmd, LinkCommand):
                network = self.network_override or self.plan_network
                if network is None:
                    return OperatorReply(ok=False, message="no network yet")
                if cmd.down_peer is not None:
                    network = network.without_link(cmd.node, cmd.down_peer)
                else:
                    network = network.with_node_media(cmd.node, laptop_robot=cmd.laptop_robot,
                                                      robot_robot=cmd.robot_robot)
                self.network_override = network
                ok = self.replan(f"operator changed links of {cmd.node}")
                return OperatorReply(ok=ok, message=self._summary(ok))
        except AutoPowerError as exc:
            return OperatorReply(ok=False, message=str(exc))
        return OperatorReply(ok=False, message=f"unsupported command {type(cmd).__name__}")

    def _summary(self, ok: bool) -> str:
        if not ok:
            return f"re-plan failed: {self.plan_error or 'no change'}"
        life = self.plan_obj.evaluation.lifetime_rounded_s if self.plan_obj else None
        return f"re-planned: lifetime {life} s; target " + ", ".join(f"{s}->{n}" for s, n in self.target.items())

    def snapshot(self) -> dict[str, Any]:
        plan = self.plan_obj
        robots = {}
        for name in self.robots:
            st = self.statuses.get(name)
            robots[name] = {
                "present": name in self.present, "departed": name in self.departed,
                "status": _status_dict(st) if st else None,
                "predicted_w": self.predicted_w.get(name),
            }
        return {
            "scenario": self.scenario.name,
            "accounting": self.scenario.accounting,
            "ready": self.ready,
            "mission": dataclasses.asdict(self.mission) if self.mission else None,
            "t_virtual": self.now(),
            "epoch": self.epoch,
            "placement": dict(self.placement),
            "target": dict(self.target),
            "migrating": {s: {"from": m.from_node, "to": m.to_node, "phase": m.phase}
                          for s, m in self.migrations.items()},
            "running": dict(self.running),
            "disabled": sorted(self.disabled),
            "pins": dict(self.pins),
            "media": plan.network.media_by_group() if plan else None,
            "links": [[l.a, l.b, l.medium] for l in self.plan_network.links] if self.plan_network else [],
            "links_down": sorted(sorted(p) for p in self.links_down),
            "planned_lifetime_s": plan.evaluation.lifetime_rounded_s if plan else None,
            "predicted_lifetime_s": self.predicted_lifetime_s,
            "reasons": dict(plan.reasons) if plan else {},
            "plan_error": self.plan_error,
            "robots": robots,
            "migrations_done": self.migrations_done,
            "assignments_done": self.assignments_done,
            "aborted": self.aborted,
            "replans": self.replans,
            "downtime_ms": _stats(self.downtimes_ms),
            "migration_log": list(self.migration_log),
            "first_depletion": self.first_depletion,
            "events": list(self.events),
            "faults": list(self.faults),
            "adopted": self.adopted,
        }


def _stats(values: list[float]) -> dict[str, float] | None:
    if not values:
        return None
    ordered = sorted(values)
    return {"n": len(values), "mean": statistics.fmean(values), "p50": ordered[len(ordered) // 2],
            "max": ordered[-1]}


def _status_dict(st: NodeStatus) -> dict[str, Any]:
    d = dataclasses.asdict(st)
    return d
