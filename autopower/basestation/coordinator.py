"""The base station's coordinator: tracks the team, asks the policy, and moves components.

It keeps the *desired* placement (the policy's allocation, overridden by operator pins) and
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

Before deciding anything it listens to the team (`takeover.py`): robots that already run a mission
(this base station was restarted) are adopted with their clock, placement, epochs and generations.

`Coordinator` is the façade the process and the simulator drive (events in: liveliness, statuses,
answers, operator commands, the timer); it owns the team view (who is present, departed or awaited,
the robots' statuses, the mission and its clock, the notes) and the ways out (``send_to``,
``on_own_plan``). The rest is in collaborators, each owning its state, that the
façade and each other call through methods:

- ``deciding`` (`deciding.Deciding`): team view -> policy -> target; the decider, the decisions,
  what to ask next, the plan's network and media;
- ``prediction`` (`prediction.Prediction`): the model's power and lifetime for the plan, DVFS levels,
  battery baselines;
- ``placing`` (`placing.Placement`): target and confirmed placement, migrations, generations and the
  chains' runs (`runs.ChainRuns`);
- ``plans`` (`publishing.PlanPublisher`): the plans' epoch and when they go out; its ``delivery``
  (`delivery.PlanDelivery`): which robot gets which plan when, and the plan each robot holds;
- ``operating`` (`operating.OperatorControl`): the operator's commands and settings, the snapshot;
- ``takeover`` (`takeover.Takeover`): starting the mission or adopting a running team, the
  incarnation and leader id, a rival base station;
- ``faults`` (`faults.TeamFaults`): link states and the faults until a plan handles them.
"""

from __future__ import annotations

import logging
import math
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable

from autopower.basestation.decider import AwaitDecision
from autopower.basestation.deciding import Deciding
from autopower.basestation.faults import TeamFaults
from autopower.basestation.operating import OperatorControl
from autopower.basestation.placing import Placement
from autopower.basestation.prediction import Prediction
from autopower.basestation.publishing import PlanPublisher
from autopower.basestation.runs import SourceSight
from autopower.basestation.takeover import Takeover
from autopower.errors import AutoPowerError
from autopower.model.scenario import Scenario
from autopower.model.variants import apply_variants
from autopower.planner.plan_choices import mission_variants
from autopower.policies import (
    POLICY_NAMES,
    Policy,
    make_policy,
)
from autopower.protocol import (
    Keys,
    MissionInfo,
    NodeStatus,
    OperatorReply,
    PlanChange,
    PlanUpdate,
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
    migration_resend_s: float = 1.0  # wall seconds an order of a migration waits for its answer before it goes again
    start_grace_s: float = 30.0  # wall seconds to wait for every robot before starting without some
    plan_republish_s: float = 1.0  # wall seconds between repeats of the current plan (late joiners)
    # ... while a robot in reach does not say it runs it; once they all do, only this often (a
    # listener that sends no status, e.g. a recorder joining late): a team at rest does not
    # send, receive and compare the plan every second for nothing
    plan_republish_settled_s: float = 10.0
    # wall seconds a plan that only announces ready stages waits after the last new plan while other
    # orders still wait for their answers, so that a wave of answers (a fleet's start: one per
    # stage) makes one plan, not one each: every new plan costs each robot a decode and a status
    # acknowledging it to each of its peers
    plan_batch_s: float = 0.1
    # wall seconds a robot may hold a plan older than the newest when the newer ones change nothing it
    # acts on (`PlanDelivery`): it gets them all in one change then, or once no order waits
    plan_catch_up_s: float = 1.0
    link_down_after_s: float = 3.0  # wall seconds a never-seen-up link must be reported down before it counts
    heal_hold_s: float = 2.0  # wall seconds a link must be back before plans may use it again (no flapping)
    variants: dict[str, str] = field(default_factory=dict)  # chain -> quality variant, fixed by the operator
    # wall seconds to listen to the robots before deciding (a running team is adopted, see takeover.py):
    # two status periods and a lease, what a running robot needs to reconnect and report
    learn_team_s: float = 2.0

    def __post_init__(self) -> None:
        _policy_from(self)  # a wrong policy name or parameter fails here, before anything starts


class Coordinator:
    """The façade: the team view, the events the process and the simulator bring, and the parts that act on them."""

    def __init__(self, *, scenario: Scenario, bus: Bus, keys: Keys, config: CoordinatorConfig,
                 policy: Policy | None = None, wall_fn: Callable[[], float] = time.time,
                 leader: str | None = None, incarnation: int = 0,
                 perf_fn: Callable[[], float] = time.perf_counter,
                 send_to: Callable[[str, str, bytes], object] | None = None,
                 on_own_plan: Callable[[PlanUpdate], object] | None = None,
                 on_decision_answer: Callable[[], object] | None = None):
        """``policy`` replaces the one named by ``config.policy`` (tests inject one to watch it).
        ``perf_fn`` times the policy's decisions (a figure reported, never an input to one).
        ``leader`` names this base station in its plans (default: `instance_id`, random per process);
        ``incarnation`` is the lowest it starts at (what its host remembers, plus one).

        How messages leave, from the process: ``send_to(node, key, payload)`` sends to one node
        (its `Relayer` reaches robots out of sight through other agents; default: publish: each
        robot's plans go so, `PlanDelivery`), and ``on_own_plan(plan)`` hands each plan to the base
        station's own host before it is published (not after a trip through Zenoh's loopback:
        after a takeover the robots' held results follow the plan at once, and a host without
        the mission would drop them).

        ``on_decision_answer``: None asks the policy inline (the simulator, tests: a decision is
        carried out before `Deciding.replan` returns); given, the policy decides on a thread and this is
        called from it when an answer is in: the process then wakes its loop, whose `on_timer`
        carries the answer out (`decider.Decider`)."""
        # quality variants are fixed for the mission: the policies place the chains as they run them
        self.variants = mission_variants(scenario, config.variants)
        scenario = apply_variants(scenario, self.variants)
        self.scenario = scenario
        self.bus = bus
        self.keys = keys
        self.config = config
        self.policy: Policy = policy if policy is not None else _policy_from(config)
        self.wall = wall_fn
        self.base = scenario.basestation
        self.robots = [r.name for r in scenario.robots]
        self.robot_names = frozenset(self.robots)  # (asked for every robot at every turn of a fleet)
        self.chain_of = {s.name: c for c in scenario.chains for s in c.stages}
        self.send_to = send_to or (lambda node, key, payload: self.bus.publish(key, payload))
        self.on_own_plan = on_own_plan or (lambda plan: None)

        # the team view
        self.mission: MissionInfo | None = None
        self.clock: VirtualClock | None = None
        self.mission_unix = 0.0  # when we started or adopted the mission
        self.present: set[str] = set()
        self.departed: set[str] = set()  # left or depleted: excluded until they come back
        self.statuses: dict[str, NodeStatus] = {}
        # robots that came into sight (or left it) since their last status: what that status says
        # may be another process's (`source_sight`)
        self.unheard: set[str] = set()
        self.sightings: dict[str, int] = {}  # robot -> how many times it came into sight
        # robots back after an absence: their report of what they host (a subgroup may have
        # reallocated without us) is the starting point, not our stale placement
        self._awaiting_actual: dict[str, float] = {}
        self.first_depletion: dict[str, float] | None = None
        self.events: deque[str] = deque(maxlen=50)

        # the collaborators, each owning its state (the module docstring)
        self.deciding = Deciding(self, policy=self.policy, perf_fn=perf_fn, on_decision_answer=on_decision_answer)
        self.prediction = Prediction(self)
        self.operating = OperatorControl(self, config.pins)
        self.placing = Placement(self)
        self.plans = PlanPublisher(self)
        self.takeover = Takeover(self, leader=leader, incarnation=incarnation, up_unix=self.wall(),
                                 learn_team_s=config.learn_team_s)
        self.faults = TeamFaults(self)

    # ---- helpers ----------------------------------------------------------------------------------
    def now(self) -> float:
        return self.clock.now() if self.clock else 0.0

    def runs_plan(self, status: NodeStatus, epoch: int, newer: bool = False) -> bool:
        """Does the node run our plan of ``epoch`` (or, ``newer``, a later one)?"""
        theirs, ours = (status.plan_incarnation, status.plan_epoch), (self.takeover.incarnation, epoch)
        return theirs >= ours if newer else theirs == ours

    def note(self, text: str) -> None:
        line = f"t={self.now():.1f}s {text}"
        self.events.append(line)
        log.info("coordinator: %s", line)

    def alive_nodes(self) -> set[str]:
        return (self.present - self.departed) | {self.base}

    def source_sight(self, robot: str) -> SourceSight:
        """What this base station knows of ``robot`` as a chain's source now: which time it came into
        sight (None: out of sight), its last status, and whether that status speaks for the process
        it runs now (heard since it came into sight, and that process runs a plan: it takes its saved
        state up at its first plan). What says whether it holds a chain's run (`ChainRuns.run_for`)."""
        status = self.statuses.get(robot)
        in_sight = robot in self.present and robot not in self.departed
        return SourceSight(sighting=self.sightings.get(robot) if in_sight else None, status=status,
                           current=in_sight and status is not None and robot not in self.unheard
                           and status.plan_epoch >= 0)

    def awaiting_reports(self) -> list[str]:
        """The robots back after an absence that have not said yet what they run (sorted)."""
        return sorted(self._awaiting_actual)

    @property
    def ready(self) -> bool:
        """The mission runs and every desired stage runs where the plan wants it."""
        placing = self.placing
        return (self.mission is not None and not placing.migrations and self.deciding.plan_network is not None
                and all(placing.placement.get(s) == n for s, n in placing.target.items()))

    # ---- mission start --------------------------------------------------------------------------------
    def start_mission(self, mission: MissionInfo) -> None:
        """Run ``mission`` from now on: a new one, or the one the robots run (its clock goes on)."""
        self.mission = mission
        self.mission_unix = self.wall()
        self.clock = VirtualClock(mission.epoch_unix, mission.speed, wall_fn=self.wall)

    def heard_statuses(self, reports: dict[str, NodeStatus]) -> None:
        """The statuses a team taken over reported (batteries, links: what the policy starts from)."""
        for node, status in reports.items():
            self.statuses[node] = status
            if node in self.present:
                self.unheard.discard(node)

    def learn(self, status: NodeStatus) -> None:
        """A robot's status before this base station runs the mission (`Takeover.learn`)."""
        self.takeover.learn(status)

    def on_rival_plan(self, plan: PlanUpdate | PlanChange) -> None:
        """A plan another base station made (`Takeover.on_rival_plan`)."""
        self.takeover.on_rival_plan(plan)

    def on_rival_status(self, status: NodeStatus) -> None:
        """A robot runs a plan another base station made (`Takeover.on_rival_status`)."""
        self.takeover.on_rival_status(status)

    # ---- events --------------------------------------------------------------------------------------------
    def on_liveliness(self, node: str, alive: bool, detected_unix: float | None = None) -> None:
        if node == self.base or node not in self.robot_names:
            return
        if alive:
            if node in self.present and node not in self.departed:
                return
            self.present.add(node)
            self.departed.discard(node)
            self.unheard.add(node)
            self.sightings[node] = self.sightings.get(node, 0) + 1
            self.takeover.came_into_sight(node)
            self.note(f"{node} joined")
            if self.mission is None:
                self.takeover.maybe_start()
            else:
                self.faults.rejoined(node)
                self.deciding.event("robot-join", robot=node)
                self._awaiting_actual[node] = self.wall() + 1.0  # decide once it says what it hosts
        else:
            if node not in self.present:
                return
            self.present.discard(node)
            self.unheard.add(node)
            self.faults.record("node-left", node, detected_unix or self.wall())
            self.note(f"{node} left")
            self.placing.node_lost(node)
            if self.mission is not None:
                self.deciding.event("robot-leave", robot=node, note="left")
                self.deciding.replan(f"{node} left")

    def on_host_status(self, status: NodeStatus) -> None:
        """The status of the base station's own host, built in the same process (each period once
        its mission runs). It is no robot's; as the sink of a fan-in chain it says the chain's run."""
        self.placing.learn_runs(status)

    def on_status(self, status: NodeStatus) -> None:
        if status.node not in self.robot_names:
            return
        held = self.statuses.get(status.node)
        if held is not None and held.process != status.process:
            if status.t_unix < held.t_unix:
                return  # a late status of a process that ended (relayed, queued): it speaks for nobody now
            if self.mission is not None and status.node in self.present and status.node not in self.unheard:
                # It restarted within the lease (its liveliness never went). Whatever its old process
                # held (custody; its sources' positions, unless this status says it resumed them) is
                # gone as if it had left: it leaves and comes back, so its chains stop and run again
                # by `ChainRuns.run_for`'s rule. Left running, a source it did not resume would name
                # its run's seqs from 0 again, and its consumers would drop the new inputs as copies.
                self.note(f"{status.node} runs another process (it restarted unseen)")
                self.on_liveliness(status.node, False)
                self.on_liveliness(status.node, True)
        self.statuses[status.node] = status
        if status.node in self.present:
            self.unheard.discard(status.node)
        self.placing.generations.follow(status)
        self.placing.learn_runs(status)
        if status.depleted:
            if status.node not in self.departed:
                self.departed.add(status.node)
                if self.first_depletion is None:
                    self.first_depletion = {"robot": status.node, "t_virtual": status.t_virtual}
                self.note(f"{status.node} ran out of energy")
                self.placing.node_lost(status.node)
                self.deciding.event("robot-leave", robot=status.node, note="depleted")
                self.deciding.replan(f"{status.node} depleted")
            return
        if status.node in self._awaiting_actual:
            del self._awaiting_actual[status.node]
            self.placing.adopt_actual(status)
            if not self._awaiting_actual:  # every robot that came back has said what it runs
                self.deciding.replan(f"{status.node} joined (from what the robots report hosting)", after_rejoin=True)
        elif (self.mission is not None and status.node in self.present
              and self.placing.adopt_actual(status, returning=False)):
            # A robot that never left our sight may have run a round alone (it took us for gone on
            # a lossy link): its newer instance is adopted, ours released, and the plan says so at
            # once, or its producers would go on feeding ours the inputs it has not seen.
            self.deciding.replan(f"{status.node} runs stages it agreed on without the base station")
        self.placing.source_heard(status)
        self.faults.check_links(status)
        self.deciding.check_drift(status)

    def link_lost(self, a: str, b: str, detected_unix: float | None = None) -> None:
        """A link an end of which is this base station (seen by its own liveliness) went down
        (`TeamFaults.link_lost`)."""
        self.faults.link_lost(a, b, detected_unix)

    def link_seen(self, a: str, b: str) -> None:
        """Evidence that a link works (its ends see each other)."""
        self.faults.link_seen(a, b)

    def on_timer(self) -> None:
        now_wall = self.wall()
        deciding = self.deciding
        deciding.take_answer()  # before anything new is asked: one question at a time
        self.takeover.maybe_start()
        deciding.ask_ahead()
        deciding.ask_due()
        self.plans.publish_ready(now_wall)
        if self.mission is not None:
            late = [n for n, deadline in self._awaiting_actual.items() if now_wall >= deadline]
            for node in late:
                del self._awaiting_actual[node]
            if late and not self._awaiting_actual:
                deciding.replan(f"{', '.join(late)} joined (no report in time)", after_rejoin=True)
            self.faults.heal_links()
            self.faults.mark_reconfigured()
        self.placing.time_out(now_wall)
        self.placing.resend_orders()
        if self.mission is None:
            return
        if self.config.auto_replan:
            deciding.timed_decisions()
        self.plans.republish(now_wall)

    def next_deadline_unix(self) -> float:
        """When `on_timer` next has something to do (a base station waiting for robots sleeps)."""
        deadlines = self.placing.deadlines() + self.deciding.deadlines() + self.plans.deadlines()
        if self.mission is None:
            deadlines += self.takeover.start_deadlines()
        # nothing else is timed before the first robot appears: the next event wakes us;
        # a rejoined robot's report time is due by the clock too
        deadlines += self._awaiting_actual.values()
        return min(deadlines, default=math.inf)

    def idle(self) -> bool:
        """The mission runs and nothing is under way that only time moves on: no migration, no
        rejoined robot whose report is awaited, no link down (its heal is timed), no fault
        waiting to be reconfigured. The loop may then sleep until an event or `next_deadline_unix`."""
        return (self.mission is not None and not self.deciding.decider.busy and not self.placing.migrations
                and not self._awaiting_actual and self.faults.settled())

    # ---- the other parts' entry points ---------------------------------------------------------------------
    def on_inbox(self, payload: bytes) -> None:
        """An answer to an order, from the base station's inbox (`Placement.on_inbox`; raises
        ProtocolError for anything else: the caller counts it)."""
        self.placing.on_inbox(payload)

    def on_operator(self, cmd) -> OperatorReply | AwaitDecision:
        """The reply to an operator's command (`OperatorControl.on_operator`)."""
        return self.operating.on_operator(cmd)

    def reply_when_decided(self, waiting: AwaitDecision) -> OperatorReply | None:
        """The reply to a command that waited for a decision, once it is in (`OperatorControl.reply_when_decided`)."""
        return self.operating.reply_when_decided(waiting)

    def snapshot(self) -> dict[str, Any]:
        """The team as `autopower status` shows it (`OperatorControl.snapshot`)."""
        return self.operating.snapshot()


def _policy_from(config: CoordinatorConfig) -> Policy:
    """The policy a configuration names; a clear error (at construction) for a wrong name or parameter."""
    if config.policy not in POLICY_NAMES:
        raise AutoPowerError(f"coordinator: unknown policy {config.policy!r}; choose one of "
                             f"{', '.join(POLICY_NAMES)} (CoordinatorConfig.policy / --policy)")
    return make_policy(config.policy, **dict(config.policy_params))






