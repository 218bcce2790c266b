"""The base station's coordinator: tracks the team, asks the policy, and moves components.

It owns the *desired* placement (the policy's allocation, overridden by operator pins) and
the *confirmed* one (what nodes have acknowledged), and closes the gap one stage at a time:

- a stage with no live host gets `Assign` (a fresh instance);
- a stage that must move gets `Prepare` on the new host, then (on `Prepared`) `MigrateOut` on
  the old one, which ships its state along the data path; `StageReady` from the new host
  confirms it. Migrations of one stage are never overlapped.

Every change of the confirmed placement is published as a `PlanUpdate` (which also carries
the mission clock), so sources and senders follow.

What to run where is decided by the same code as in the simulator: `autopower.policies`
(``CoordinatorConfig.policy``: static, reactive, rebalance or subgroup). The coordinator builds a
`TeamState` from what it knows (mission time, the network in use with known-down links removed,
what runs, the robots' measured batteries, cut links, the operator's radio changes and disabled
chains, the schedule the last decision planned) plus the `MissionEvent` values that triggered the
decision, calls ``policy.decide(state)`` and carries out the answer: None keeps the current
configuration, a `Decision` becomes the target. It asks when an agent joins or leaves, a link
goes down or comes back, a battery drifts from the prediction, the operator enables or disables
a chain or changes a radio, at the time a decision asked to be revisited (a time-sharing
schedule's next phase) and periodically. The hysteresis (a move must gain enough) is the
policy's; what stays here is link-state debouncing, which is about facts, not decisions: a link
counts as down after ``link_down_after_s`` and as back after ``heal_hold_s``.
"""

from __future__ import annotations

import dataclasses
import logging
import statistics
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable

from autopower.basestation.links import LinkStates, pair_name
from autopower.errors import AutoPowerError
from autopower.model.energy import evaluate, round_lifetime
from autopower.model.mission_events import MissionEvent
from autopower.model.network import Network, build_network, media_choices
from autopower.model.scenario import Scenario
from autopower.policies import (
    POLICY_NAMES,
    Decision,
    MigrationCosts,
    Policy,
    SchedulePhase,
    TeamState,
    base_media,
    derive_network,
    make_policy,
)
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
from autopower.runtime.bus import Bus
from autopower.runtime.clock import VirtualClock

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class CoordinatorConfig:
    speed: float = 10.0
    topology: str | None = None  # None: the scenario's
    media: dict[str, str] | None = None  # group -> medium, fixed; None: the policy chooses
    pins: dict[str, str] = field(default_factory=dict)  # stage -> node, fixed by the operator
    policy: str = "rebalance"  # autopower.policies.POLICY_NAMES: what decides the placement
    policy_params: dict[str, Any] = field(default_factory=dict)  # its parameters (e.g. min_gain, min_gain_s)
    # ask the policy on battery drift, periodically and when a decision asked to be revisited
    # (joins, leaves, link changes and operator commands always ask)
    auto_replan: bool = True
    replan_interval_s: float = 600.0  # virtual seconds between decisions with the remaining energies
    drift_tolerance: float = 0.03  # relative drift of a battery from the plan that triggers a re-plan
    drift_min_window_s: float = 60.0  # virtual seconds of a plan before drift is judged
    migration_timeout_s: float = 10.0  # wall seconds before a stuck migration is abandoned
    start_grace_s: float = 30.0  # wall seconds to wait for every robot before starting without some
    plan_republish_s: float = 1.0  # wall seconds between repeats of the current plan (late joiners)
    link_down_after_s: float = 3.0  # wall seconds a never-seen-up link must be reported down before it counts
    heal_hold_s: float = 2.0  # wall seconds a link must be back before plans may use it again (no flapping)

    def __post_init__(self) -> None:
        _policy_from(self)  # a wrong policy name or parameter fails here, before anything starts


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
                 policy: Policy | None = None, wall_fn: Callable[[], float] = time.time):
        """``policy`` replaces the one named by ``config.policy`` (tests inject one to watch it)."""
        self.scenario = scenario
        self.bus = bus
        self.keys = keys
        self.config = config
        self.policy: Policy = policy if policy is not None else _policy_from(config)
        self.wall = wall_fn
        self.topology = config.topology or scenario.network_spec.topology
        self.migration_costs = MigrationCosts.from_scenario(scenario)
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
        self.decision: Decision | None = None  # the policy's last decision (None: nothing decided yet)
        self.chosen: dict[str, str] = {}  # the policy's allocation, before operator pins
        self.stage_reasons: dict[str, str] = {}  # stage -> why it runs where it does (the planner's words)
        self.decision_reasons: tuple[str, ...] = ()  # the newest decision that gave reasons (quiet ones do not)
        self.schedule: tuple[SchedulePhase, ...] = ()  # the phases the last decision planned after its own
        self.revisit_at_s: float | None = None  # virtual time the last decision asked to be asked again
        self._pending_events: list[MissionEvent] = []  # what happened since the policy was last asked
        # the base media the team uses (group -> medium); decisions may change them unless config.media
        self.media: dict[str, str] = dict(config.media or media_choices(scenario, self.topology)[0])
        self.plan_network: Network | None = None
        self.radio_faults: dict[str, tuple[str | None, str | None]] = {}  # operator radio commands
        self.operator_cuts: set[frozenset[str]] = set()  # links the operator declared down
        topology = build_network(scenario, topology=config.topology)
        self.links = LinkStates({frozenset((l.a, l.b)) for l in topology.links},
                                down_after_s=config.link_down_after_s, heal_hold_s=config.heal_hold_s)
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

    @property
    def links_down(self) -> set[frozenset[str]]:
        """Links known down now (see `LinkStates`)."""
        return self.links.down

    def link_lost(self, a: str, b: str, detected_unix: float | None = None) -> None:
        """A link an end of which is this base station (seen by its own liveliness) went down."""
        if self.links.lost(a, b):
            self._link_down(frozenset((a, b)), detected_unix or self.wall())
            self.replan("link change")

    def link_seen(self, a: str, b: str) -> None:
        """Evidence that a link works (its ends see each other)."""
        self.links.seen(a, b, self.wall())

    def _link_down(self, pair: frozenset[str], since: float) -> None:
        a, b = sorted(pair)
        self.record_fault("link-down", pair_name(pair), since)
        self.note(f"link {a}-{b} is down")
        self._event("link-cut", a=a, b=b)

    def _heal_links(self) -> None:
        healed = self.links.healed(self.wall())
        for pair in healed:
            self.note(f"link {pair_name(pair)} is back (up for {self.config.heal_hold_s:g} s)")
            a, b = sorted(pair)
            self._event("link-heal", a=a, b=b)
        if healed:  # whether moving back is worth it is the policy's hysteresis
            self.replan("links back")

    @property
    def ready(self) -> bool:
        """The mission runs and every desired stage runs where the plan wants it."""
        return (self.mission is not None and not self.migrations and self.plan_network is not None
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
        self.note(f"policy: {self.policy.name}")
        missing = set(self.robots) - self.present
        self.note("mission started" + (f" without {', '.join(sorted(missing))}" if missing else ""))
        self.replan("mission start")

    # ---- deciding ---------------------------------------------------------------------------------------
    def remaining_energies(self) -> dict[str, float]:
        out = {}
        for robot in self.robots:
            status = self.statuses.get(robot)
            if status is not None and status.battery_j is not None:
                out[robot] = max(status.battery_j, 1e-6)
            else:
                out[robot] = self.scenario.robot(robot).energy_j
        return out

    def _unavailable(self) -> frozenset[str]:
        return frozenset(r for r in self.robots if r not in self.alive_nodes())

    def _cut_links(self) -> frozenset[frozenset[str]]:
        return frozenset(self.links_down | self.operator_cuts)

    def network_in_use(self) -> Network:
        """The links the team uses now: the media in use, minus what is down, with the radio faults."""
        return derive_network(self.scenario, self.topology, self.media, self._cut_links(), dict(self.radio_faults),
                              self._unavailable())

    def _current_allocation(self) -> dict[str, str]:
        """What runs (or is being made to run): the target, where a stage is not on its way somewhere
        else, corrected by where it is confirmed to run (e.g. adopted from a returning robot)."""
        allocation = dict(self.target)
        for stage, host in self.placement.items():
            if stage in allocation and stage not in self.migrations:
                allocation[stage] = host
        return allocation

    def team_state(self) -> TeamState:
        """What the policy may know, from the coordinator's view of the team (see the module docstring)."""
        alive = self.alive_nodes()
        energies = self.remaining_energies()
        return TeamState(
            scenario=self.scenario, time_s=self.now(), network=self.network_in_use(),
            allocation=self._current_allocation(),
            energies_j={r: e for r, e in energies.items() if r in alive},
            disabled_chains=frozenset(self.disabled), unavailable_nodes=self._unavailable(),
            topology=self.topology, cut_links=self._cut_links(), radio_faults=dict(self.radio_faults),
            media_locked=bool(self.config.media), accounting=self.scenario.accounting,
            events=tuple(self._pending_events), migration=self.migration_costs, schedule=self.schedule)

    def _event(self, kind: str, **fields) -> None:
        """Something the next decision should hear about (`TeamState.events`)."""
        self._pending_events.append(MissionEvent(at_s=self.now(), kind=kind, **fields))

    def replan(self, reason: str, *, after_rejoin: bool = False) -> bool:
        """Ask the policy what to run where now, and carry its answer out.

        ``reason`` says why we ask (for the notes); what happened since the last decision travels
        as events. True when the policy answered (a new configuration, or keep the current one);
        False when it could not be asked (no mission, robots still to report) or found nothing.
        """
        if self.mission is None:
            return False
        if self._awaiting_actual and not after_rejoin:
            # robots are back and have not said what they run yet: decide once they have
            self.note(f"decision ({reason}) deferred until {', '.join(sorted(self._awaiting_actual))} report")
            return False
        if len(self._unavailable()) == len(self.robots):
            self.note(f"no robot left ({reason}); nothing to run")
            self.target, self.chosen = {}, {}
            self.schedule, self.revisit_at_s = (), None
            self._pending_events.clear()
            self.reconcile()
            self.publish_plan()
            return False
        state = self.team_state()
        try:
            decision = self.policy.decide(state)
        except AutoPowerError as exc:  # InfeasibleError, or a state the policy rejects
            self.plan_error = str(exc)
            self.note(f"decision ({reason}) found nothing feasible: {exc}")
            return False
        self.plan_error = None
        self._pending_events.clear()
        if decision is None:
            self._keep(state, reason)
        else:
            self._carry_out(decision, reason)
        return True

    def _keep(self, state: TeamState, reason: str) -> None:
        """The policy keeps what runs (as the simulator does: no schedule, no revisit)."""
        self.schedule, self.revisit_at_s = (), None
        # what the policy would run without the pins (where `migrate --auto` goes back to)
        self.chosen = {s: self.chosen.get(s, h) if s in self.pins else h for s, h in state.allocation.items()}
        target = self._with_pins(dict(state.allocation))
        changed = target != self.target or state.network != self.plan_network
        self.target, self.plan_network = target, state.network
        self.note(f"decision ({reason}): policy {self.policy.name} keeps the configuration")
        self._predict()
        if changed:  # e.g. a link is gone from (or back in) the routes, nothing moves
            self.reconcile()
            self.publish_plan()

    def _carry_out(self, decision: Decision, reason: str) -> None:
        """The decision's allocation becomes the target (operator pins win), its network the plan's."""
        self.decision = decision
        self.schedule = tuple(decision.schedule)
        at = decision.revisit_at_s
        # without auto_replan nothing is decided by the clock: no revisit (the schedule still travels)
        self.revisit_at_s = at if self.config.auto_replan and at is not None and at > self.now() + 1e-6 else None
        if not self.config.media:
            self.media.update(base_media(decision.network))
        self.chosen = dict(decision.allocation)
        target = self._with_pins(dict(decision.allocation))
        changed = {s for s in target if self.target.get(s) != target[s]} | (set(self.target) - set(target))
        network_changed = decision.network != self.plan_network
        self.target, self.plan_network = target, decision.network
        self.stage_reasons = {s: why for s, why in {**self.stage_reasons, **decision.stage_reasons}.items()
                              if s in target}
        if changed or network_changed:
            self.replans += 1
        if decision.reasons:
            self.decision_reasons = tuple(decision.reasons)
        for line in decision.reasons:
            self.note(f"decision ({reason}): {line}")
        planned = round_lifetime(decision.predicted_lifetime_s, self.scenario.lifetime_rounding_s)
        self.note(f"plan ({reason}, policy {decision.policy}): predicted lifetime {planned} s, media "
                  f"{decision.network.media_by_group()}, {len(changed)} stage(s) to place"
                  + (f", dropped {', '.join(decision.dropped)}" if decision.dropped else "")
                  + (f", next decision at t={self.revisit_at_s:.1f}s" if self.revisit_at_s is not None else ""))
        self._predict()
        self.reconcile()
        self.publish_plan()

    def _with_pins(self, allocation: dict[str, str]) -> dict[str, str]:
        alive = self.alive_nodes()
        for stage, node in self.pins.items():
            if stage in allocation and node in alive:
                allocation[stage] = node
        return allocation

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
                self.links.rejoined(node, self.wall())
                self._event("robot-join", robot=node)
                self._awaiting_actual[node] = self.wall() + 1.0  # decide once it says what it hosts
        else:
            if node not in self.present:
                return
            self.present.discard(node)
            self.record_fault("node-left", node, detected_unix or self.wall())
            self.note(f"{node} left")
            self._node_lost(node)
            if self.mission is not None:
                self._event("robot-leave", robot=node, note="left")
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
                self._event("robot-leave", robot=status.node, note="depleted")
                self.replan(f"{status.node} depleted")
            return
        if status.node in self._awaiting_actual:
            del self._awaiting_actual[status.node]
            self._adopt_actual(status)
            if not self._awaiting_actual:  # every robot that came back has said what it runs
                self.replan(f"{status.node} joined (from what the robots report hosting)", after_rejoin=True)
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

    def _check_links(self, status: NodeStatus) -> None:
        """A robot's view of its links: what it reports down may be a cut (`LinkStates` debounces)."""
        gone = self.links.reported(status.node, status.links, self.alive_nodes(), self.wall())
        for pair, since in gone:
            self._link_down(pair, since)
        if gone:
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
            # the battery is off the prediction by this much (negative: emptier than predicted)
            self._event("energy-offset", robot=status.node, delta_j=predicted - measured)
            if not self.replan(f"{status.node} battery drift"):
                self._reset_baselines()

    def on_timer(self) -> None:
        now_wall = self.wall()
        self.maybe_start()
        if self.mission is not None:
            late = [n for n, deadline in self._awaiting_actual.items() if now_wall >= deadline]
            for node in late:
                del self._awaiting_actual[node]
            if late and not self._awaiting_actual:
                self.replan(f"{', '.join(late)} joined (no report in time)", after_rejoin=True)
            self._heal_links()
            self._mark_reconfigured()
        for stage, m in list(self.migrations.items()):
            if now_wall - m.started_unix > self.config.migration_timeout_s:
                self._abort(stage, f"no answer in {self.config.migration_timeout_s:g} s")
                self.reconcile()
                self.publish_plan()
        if self.mission is None:
            return
        if self.config.auto_replan:
            self._timed_decisions()
        if now_wall >= self.next_republish:
            self.publish_plan(repeat=True)

    def _timed_decisions(self) -> None:
        """The decision a schedule asked for at its phase's end, and the periodic one (no events)."""
        now = self.now()
        due_periodic = self.next_periodic_replan is not None and now >= self.next_periodic_replan
        if self.revisit_at_s is not None and now >= self.revisit_at_s:
            self.revisit_at_s = None
            self.next_periodic_replan = now + self.config.replan_interval_s  # this one counts as it
            self.replan(f"revisit at t={now:.1f}s, as the last decision asked")
        elif due_periodic:
            self.next_periodic_replan = now + self.config.replan_interval_s
            self.replan("periodic, remaining energies")

    def next_deadline_unix(self) -> float:
        deadlines = [self.next_republish] + [m.started_unix + self.config.migration_timeout_s
                                              for m in self.migrations.values()]
        if self.clock is not None and self.revisit_at_s is not None:
            deadlines.append(self.clock.wall_at(self.revisit_at_s))
        return min(deadlines)

    def publish_plan(self, repeat: bool = False) -> None:
        if self.mission is None:
            return
        if not repeat:
            self.epoch += 1
        network = self.plan_network
        links = tuple(LinkInfo(a=l.a, b=l.b, medium=l.medium) for l in network.links) if network else ()
        update = PlanUpdate(epoch=self.epoch, mission=self.mission, placement=dict(self.placement),
                            running=dict(self.running), links=links, predicted_w=dict(self.predicted_w),
                            predicted_lifetime_s=self.predicted_lifetime_s, plan_t_virtual=self.plan_t_virtual,
                            policy=self.policy.name, reasons=tuple(self.decision_reasons))
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
                self._event("chain-enable" if cmd.enabled else "chain-disable", chains=(cmd.chain,))
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
                self._clear_pins()
                ok = self.replan("operator cleared pins")
                return OperatorReply(ok=ok, message=self._summary(ok))
            if isinstance(cmd, LinkCommand):
                self._operator_link(cmd)
                ok = self.replan(f"operator changed links of {cmd.node}")
                return OperatorReply(ok=ok, message=self._summary(ok))
        except AutoPowerError as exc:
            return OperatorReply(ok=False, message=str(exc))
        return OperatorReply(ok=False, message=f"unsupported command {type(cmd).__name__}")

    def _clear_pins(self) -> None:
        """Back to what the policy chose (pinned stages migrate back), then the policy is asked again."""
        self.pins.clear()
        self.target = {s: self.chosen.get(s, h) for s, h in self.target.items()}
        self.reconcile()

    def _operator_link(self, cmd: LinkCommand) -> None:
        """An operator's link command: a link declared down (a cut link) or a radio change (a radio fault)."""
        nodes = self.scenario.node_names()
        for node in (cmd.node, cmd.down_peer):
            if node is not None and node not in nodes:
                raise AutoPowerError(f"link command: unknown node {node!r}; nodes: {', '.join(nodes)}")
        if cmd.down_peer is not None:
            self.operator_cuts.add(frozenset((cmd.node, cmd.down_peer)))
            self._event("link-cut", a=cmd.node, b=cmd.down_peer, note="operator")
            return
        for medium in (cmd.laptop_robot, cmd.robot_robot):
            if medium is not None and medium not in self.scenario.radios:
                raise AutoPowerError(f"link command for {cmd.node}: unknown medium {medium!r}; radios: "
                                     f"{', '.join(self.scenario.radios)}")
        if cmd.laptop_robot is None and cmd.robot_robot is None:
            raise AutoPowerError(f"link command for {cmd.node}: give a medium for its links to the base station "
                                 "and/or to the robots, or a peer whose link is down")
        before = self.radio_faults.get(cmd.node, (None, None))
        self.radio_faults[cmd.node] = (cmd.laptop_robot or before[0], cmd.robot_robot or before[1])
        self._event("radio-fault", robot=cmd.node, laptop_robot=cmd.laptop_robot, robot_robot=cmd.robot_robot,
                    note="operator")

    def _summary(self, ok: bool) -> str:
        if not ok:
            return f"re-plan failed: {self.plan_error or 'no change'}"
        planned = self.planned_lifetime_s()
        return (f"re-planned ({self.policy.name}): lifetime {planned} s; target "
                + ", ".join(f"{s}->{n}" for s, n in self.target.items()))

    def planned_lifetime_s(self) -> float | None:
        """The last decision's predicted lifetime from its time on (rounded as the scenario says)."""
        if self.decision is None:
            return None
        return round_lifetime(self.decision.predicted_lifetime_s, self.scenario.lifetime_rounding_s)

    def snapshot(self) -> dict[str, Any]:
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
            "media": self.plan_network.media_by_group() if self.plan_network else None,
            "links": [[l.a, l.b, l.medium] for l in self.plan_network.links] if self.plan_network else [],
            "links_down": sorted(sorted(p) for p in self.links_down),
            "planned_lifetime_s": self.planned_lifetime_s(),
            "predicted_lifetime_s": self.predicted_lifetime_s,
            "reasons": dict(self.stage_reasons),  # stage -> why it runs there
            "policy": self.policy.name,
            "decision_reasons": list(self.decision_reasons),
            "schedule": [{"duration_s": p.duration_s, "allocation": dict(p.allocation),
                          "media": p.network.media_by_group()} for p in self.schedule],
            "revisit_at_s": self.revisit_at_s,
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


def _policy_from(config: CoordinatorConfig) -> Policy:
    """The policy a configuration names; a clear error (at construction) for a wrong name or parameter."""
    if config.policy not in POLICY_NAMES:
        raise AutoPowerError(f"coordinator: unknown policy {config.policy!r}; choose one of "
                             f"{', '.join(POLICY_NAMES)} (CoordinatorConfig.policy / --policy)")
    return make_policy(config.policy, **dict(config.policy_params))


def _stats(values: list[float]) -> dict[str, float] | None:
    if not values:
        return None
    ordered = sorted(values)
    return {"n": len(values), "mean": statistics.fmean(values), "p50": ordered[len(ordered) // 2],
            "max": ordered[-1]}


def _status_dict(st: NodeStatus) -> dict[str, Any]:
    return _plain(dataclasses.asdict(st))


def _plain(value: Any) -> Any:
    """Tuples as lists, so that a snapshot is the same after a round trip through msgpack or JSON."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value
