"""Deciding: what the policy may know, asking it, and turning its answer into the target placement.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

from autopower.basestation.decider import Answer
from autopower.errors import AutoPowerError
from autopower.model.dvfs import apply_levels, best_levels, has_levels
from autopower.model.energy import evaluate, round_lifetime
from autopower.model.mission_events import MissionEvent
from autopower.model.network import Network, describe_media
from autopower.policies import (
    Decision,
    TeamState,
    base_media,
    derive_network,
)
from autopower.protocol import (
    NodeStatus,
)

log = logging.getLogger("autopower.basestation.coordinator")  # one logger for the coordinator's parts

# How far (virtual seconds) the mission start's question may be from the time the answer asked
# ahead was for (`Deciding._answered_ahead`)
AHEAD_SLACK_S = 1.0
# How many answers in a row may be set aside because the team changed while the policy decided
# (`Deciding.take_answer`): a team that changes faster than the policy decides still gets a plan
STALE_ANSWERS_MAX = 3


@dataclass
class Baseline:
    """The coordinator's deciding part: team view -> policy -> target placement. Mixed into `Coordinator`, whose state it uses."""

    t_virtual: float
    battery_j: float
    predicted_w: float


class Deciding:
    """Deciding: what the policy may know, asking it, and turning its answer into the target placement. (a part of `Coordinator`)."""

    def cannot_decide(self, error: str) -> None:
        """Nothing can be decided, for this reason (a takeover of a team that runs another scenario)."""
        self.plan_error = error

    def replan_periodically_from(self, t_virtual: float) -> None:
        """The next periodic decision is due at mission time ``t_virtual`` (then every ``replan_interval_s``)."""
        self.next_periodic_replan = t_virtual

    def remaining_energies(self) -> dict[str, float]:
        out = {}
        for robot in self.robots:
            status = self.statuses.get(robot)
            if status is not None and status.battery_j is not None:
                out[robot] = max(status.battery_j, 1e-6)
            else:
                out[robot] = self.scenario.robot(robot).energy_j
        return out

    def _unavailable(self, everyone: bool = False) -> frozenset[str]:
        if everyone:
            return frozenset()
        alive = self.alive_nodes()  # (a set built per call: once, not once per robot)
        return frozenset(r for r in self.robots if r not in alive)

    def _cut_links(self) -> frozenset[frozenset[str]]:
        return frozenset(self.links_down | self.operating.operator_cuts)

    def network_in_use(self, everyone: bool = False) -> Network:
        """The links the team uses now: the media in use, minus what is down, with the radio faults."""
        return derive_network(self.scenario, self.topology, self.media, self._cut_links(), dict(self.operating.radio_faults),
                              self._unavailable(everyone))

    def _current_allocation(self) -> dict[str, str]:
        """What runs (or is being made to run): the target, where a stage is not on its way somewhere
        else, corrected by where it is confirmed to run (e.g. adopted from a returning robot)."""
        placing = self.placing
        allocation = dict(placing.target)
        for stage, host in placing.placement.items():
            if stage in allocation and stage not in placing.migrations:
                allocation[stage] = host
        return allocation

    def team_state(self, *, everyone: bool = False) -> TeamState:
        """What the policy may know, from the coordinator's view of the team (see the module docstring).
        ``everyone``: as if every robot of the scenario were in reach (`_ask_ahead`)."""
        alive = set(self.robots) | {self.base} if everyone else self.alive_nodes()
        energies = self.remaining_energies()
        return TeamState(
            scenario=self.scenario, time_s=self.now(), network=self.network_in_use(everyone),
            allocation=self._current_allocation(),
            energies_j={r: e for r, e in energies.items() if r in alive},
            disabled_chains=frozenset(self.operating.disabled), unavailable_nodes=self._unavailable(everyone),
            topology=self.topology, cut_links=self._cut_links(), radio_faults=dict(self.operating.radio_faults),
            media_locked=bool(self.config.media), accounting=self.scenario.accounting,
            events=tuple(self._pending_events), migration=self.migration_costs, schedule=self.schedule)

    def _event(self, kind: str, **fields) -> None:
        """Something the next decision should hear about (`TeamState.events`)."""
        self._pending_events.append(MissionEvent(at_s=self.now(), kind=kind, **fields))

    def replan_soon(self, reason: str) -> None:
        """Decide at the next timer (`Coordinator.on_timer`), once for every reason given until then."""
        self.replan_due.append(reason)

    def replan(self, reason: str, *, after_rejoin: bool = False, again: bool = False) -> bool:
        """Ask the policy what to run where now; its answer is carried out by `take_answer`.

        ``reason`` says why we ask (for the notes); what happened since the last decision travels
        as events. Asked inline (the simulator, unit tests), the answer is carried out before this
        returns: True when the policy answered (a new configuration, or keep the current one),
        False when it could not be asked (no mission, robots still to report) or found nothing.
        Asked on a thread (`decider.Decider`), True means asked, or queued behind the question
        out: one question at a time, and the reasons that come meanwhile go with the next one.
        ``again``: the question whose answer was set aside (`take_answer`), asked about the team as
        it is now: the same question for the operators waiting for it (`asked` stays).
        """
        self.replan_waiting = None
        if self.mission is None:
            return False
        if self.decider.busy:
            if not (self._asking_ahead and self._take_up_ahead_question(reason)):
                self.replan_due.append(reason)  # `on_timer` asks once the answer out is carried out
            return True
        if self._awaiting_actual and not after_rejoin:
            # robots are back and have not said what they run yet: decide once they have
            waiting = ", ".join(sorted(self._awaiting_actual))
            self.note(f"decision ({reason}) deferred until {waiting} report")
            self.replan_waiting = f"the re-plan waits until {waiting} report what they run"
            return False
        if len(self._unavailable()) == len(self.robots):
            self.note(f"no robot left ({reason}); nothing to run")
            self.replan_waiting = "no robot is in reach of the base station; the re-plan waits until one is back"
            self.placing.set_target({})
            self.chosen = {}
            self.schedule, self.revisit_at_s = (), None
            self._pending_events.clear()
            self.placing.reconcile()
            self.plans.publish_plan()
            return False
        state = self.team_state()
        self._events_asked = len(self._pending_events)  # the events this question carries
        if not again:
            self.asked += 1
        ahead = self._answered_ahead(state)
        if ahead is not None:
            self.note(f"decision ({reason}) made ahead, before the robots were heard "
                      f"({ahead.took_s:.2f} s of policy time off the path to ready)")
            return self._carry_out_answer(dataclasses.replace(ahead, reason=reason))
        self.decider.ask(state, reason)
        return self.take_answer() if not self.decider.on_thread else True

    def ask_ahead(self) -> None:
        """Before the mission: ask the policy about the mission start as it will most likely be
        asked (every robot in reach, every battery full, time 0), on the decider's thread, while
        the robots start up and are heard. A 30-robot mission start is a MILP of seconds: most
        of the time to ready, spent before the first stage is placed. The answer is kept, not
        carried out; `replan` uses it only for a question equal to the one asked ahead (any
        difference, a robot missing or a battery not full, and the policy is asked again), which
        is exact because a policy's answer is a function of the state it is given. Only when
        deciding on a thread (the simulator and unit tests ask only what they ask)."""
        if (self.mission is not None or self._ahead_asked or not self.decider.on_thread
                or self.decider.busy or self.takeover.stepped_down is not None):
            return
        self._ahead_asked = True
        self._asking_ahead = True
        self._ahead_state = self.team_state(everyone=True)
        self.decider.ask(self._ahead_state, "mission start")

    def _same_as_ahead(self, state: TeamState) -> bool:
        """Whether ``state`` is the question asked ahead. Its time is the mission's start; a
        question within `AHEAD_SLACK_S` of it counts as asked then (no policy's answer turns on
        its first second: revisits and schedules are minutes and hours)."""
        ahead = self._ahead_state
        return (ahead is not None and abs(state.time_s - ahead.time_s) <= AHEAD_SLACK_S
                and dataclasses.replace(state, time_s=ahead.time_s) == ahead)

    def _take_up_ahead_question(self, reason: str) -> bool:
        """The mission starts while the question asked ahead is out: if it is this question, its
        answer is this question's (carried out when it comes, as any answer), not asked twice."""
        if not self._same_as_ahead(self.team_state()):
            return False
        self._asking_ahead, self._ahead_state = False, None
        self._events_asked = len(self._pending_events)
        self.asked += 1
        self.note(f"decision ({reason}) asked ahead, before the robots were heard: its answer is on its way")
        return True

    def _answered_ahead(self, state: TeamState) -> Answer | None:
        """The answer asked ahead, if it was about this state."""
        ahead, self._ahead = self._ahead, None  # asked once, used at most once
        same = self._same_as_ahead(state)
        self._ahead_state = None
        if ahead is None or ahead.decision is None or ahead.error is not None or ahead.failure is not None:
            return None
        return ahead if same else None

    def take_answer(self) -> bool:
        """Carry out the policy's answer, if one is in. True when it answered (a new configuration,
        or keep the current one); False when none is in, or it found nothing feasible.

        An answer is for the team as it was when asked. If what runs, the links, the robots in
        reach or the chains changed while the policy decided (a robot back from a cut reported
        the stages its subgroup moved, and they were adopted), the answer would undo what
        happened: it is set aside and the question asked again about the team as it is now (at
        most `STALE_ANSWERS_MAX` times in a row; then the answer is carried out, and `reconcile`
        places nothing on a node out of reach). What only drifts (time, batteries) does not count."""
        answer = self.decider.take()
        if answer is None:
            return False
        if self._asking_ahead:
            self._asking_ahead = False
            if self.decisions == 0:
                self._ahead = answer  # kept for the mission start (`_answered_ahead` checks it is for it)
            if answer.failure is not None:
                raise answer.failure
            return False
        # (inline, nothing can change between the question and its answer)
        changed = self._changed_since(answer.state) if self.decider.on_thread and answer.failure is None else None
        if changed is not None and self._stale_answers < STALE_ANSWERS_MAX:
            self._stale_answers += 1
            self.decide_s += answer.took_s  # the policy's time all the same (the question is not answered yet)
            self.note(f"decision ({answer.reason}) asked again: {changed} changed while the policy decided")
            self.replan(answer.reason, again=True)  # through its checks: e.g. no robot may be left
            return False
        self._stale_answers = 0
        return self._carry_out_answer(answer)

    def _changed_since(self, asked: TeamState) -> str | None:
        """What about the team differs from ``asked`` (None: nothing a decision turns on)."""
        now = self.team_state()
        for what, then, current in (("what runs", asked.allocation, now.allocation),
                                    ("the robots in reach", asked.unavailable_nodes, now.unavailable_nodes),
                                    ("the links", asked.network, now.network),
                                    ("the chains that run", asked.disabled_chains, now.disabled_chains)):
            if then != current:
                return what
        return None

    def _carry_out_answer(self, answer: Answer) -> bool:
        self.decisions += 1
        self.decide_s += answer.took_s
        self.decide_max_s = max(self.decide_max_s, answer.took_s)
        for fault in self.faults:
            if fault["reconfigured_unix"] is None:
                fault["decide_s"] += answer.took_s
        if answer.failure is not None:
            raise answer.failure  # the policy's bug, raised on the loop as an inline decision would
        if answer.error is not None:
            self.plan_error = str(answer.error)
            self.note(f"decision ({answer.reason}) found nothing feasible: {answer.error}")
            return False
        if self.takeover.stepped_down is not None:
            return False  # another base station leads: its plans, not ours
        self.plan_error = None
        del self._pending_events[:self._events_asked]  # those that came while it decided go with the next
        self._events_asked = 0
        if answer.decision is None:
            self._keep(answer.state, answer.reason)
        else:
            self._carry_out(answer.decision, answer.reason)
        return True

    def _keep(self, state: TeamState, reason: str) -> None:
        """The policy keeps what runs (as the simulator does: no schedule, no revisit)."""
        self.schedule, self.revisit_at_s = (), None
        # what the policy would run without the pins (where `migrate --auto` goes back to)
        self.chosen = {s: self.chosen.get(s, h) if s in self.operating.pins else h for s, h in state.allocation.items()}
        target = self.operating.with_pins(dict(state.allocation), self.alive_nodes())
        changed = target != self.placing.target or state.network != self.plan_network
        self.placing.set_target(target)
        self.plan_network = state.network
        self.note(f"decision ({reason}): policy {self.policy.name} keeps the configuration")
        self._predict()
        if changed:  # e.g. a link is gone from (or back in) the routes, nothing moves
            self.replans += 1  # a new plan all the same: every node takes it up
            self.placing.reconcile()
            self.plans.publish_plan()

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
        target = self.operating.with_pins(dict(decision.allocation), self.alive_nodes())
        before = self.placing.target
        changed = {s for s in target if before.get(s) != target[s]} | (set(before) - set(target))
        network_changed = decision.network != self.plan_network
        self.placing.set_target(target)
        self.plan_network = decision.network
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
                  f"{describe_media(decision.network.media_by_group())}, {len(changed)} stage(s) to place"
                  + (f", dropped {', '.join(decision.dropped)}" if decision.dropped else "")
                  + (f", next decision at t={self.revisit_at_s:.1f}s" if self.revisit_at_s is not None else ""))
        self._predict()
        self.placing.reconcile()
        self.plans.publish_plan()

    def _evaluate(self, allocation: dict[str, str], network: Network | None, energies: dict[str, float],
                  running: set[str] | None = None, levels: dict[str, str] | None = None):
        """The model for an allocation on the network of the nodes alive; None if it has no answer.

        ``running``: the chains that run (default: those with a stage in the allocation; given, an
        empty allocation is a team whose chains are stopped). ``levels``: DVFS levels to price at."""
        if network is None or (not allocation and running is None):
            return None
        active = running if running is not None else {self.chain_of[s].name for s in allocation}
        scenario = apply_levels(self.scenario, levels) if levels else self.scenario
        disabled = frozenset(c.name for c in scenario.chains if c.name not in active)
        try:
            return evaluate(scenario, network.without_nodes(set(self._unavailable())), allocation,
                            energies_j=energies, disabled_chains=disabled)
        except AutoPowerError:
            return None

    def _predict(self) -> None:
        ev = self._evaluate(self.placing.target, self.plan_network, self.remaining_energies())
        ev = self._at_levels(ev)
        self.predicted_w = {r: p.steady_w for r, p in ev.robots.items()} if ev else {}
        self.predicted_lifetime_s = ev.lifetime_s if ev else None
        self.plan_t_virtual = self.now()
        self._reset_baselines()

    def placement_w(self) -> dict[str, float]:
        """The model's power per robot for what runs now: the confirmed placement of the chains
        that run, at the plan's DVFS levels. While stages move this is not the target's
        prediction, and a robot running a stage until its migration lands is drawing for it: the
        plan tells each robot this figure, and the robot's status carries it to the recording
        (replay checks the meter against it). {} when it cannot be evaluated."""
        placement, target, running = self.placing.placement, self.placing.target, set(self.placing.runs.running)
        if placement == target and running == {c.name for c in self.scenario.chains
                                                if any(s.name in target for s in c.stages)}:
            return dict(self.predicted_w)  # settled: the target's prediction is the placement's
        allocation = {s: n for s, n in placement.items() if self.chain_of[s].name in running}
        ev = self._evaluate(allocation, self.plan_network, {}, running=running, levels=self.levels)
        return {r: p.steady_w for r, p in ev.robots.items()} if ev else {}

    def _at_levels(self, ev):
        """DVFS: every robot at the cheapest frequency level at which its placement fits (a robot's
        level changes only its own power, so this is optimal for any policy's placement); the plan
        carries the levels to the agents and the prediction is made at them."""
        self.levels = best_levels(self.scenario, ev.utilisation) if ev is not None and has_levels(self.scenario) else {}
        if not self.levels:
            return ev
        return self._evaluate(self.placing.target, self.plan_network, self.remaining_energies(), levels=self.levels)

    def _reset_baselines(self) -> None:
        self.baselines.clear()  # re-anchored from the next status that reflects the settled plan

    def _check_drift(self, status: NodeStatus) -> None:
        if not self.config.auto_replan or status.battery_j is None or not self.ready:
            return
        if not self.runs_plan(status, self.plans.epoch) or status.node not in self.predicted_w:
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

    def planned_lifetime_s(self) -> float | None:
        """The last decision's predicted lifetime from its time on (rounded as the scenario says)."""
        if self.decision is None:
            return None
        return round_lifetime(self.decision.predicted_lifetime_s, self.scenario.lifetime_rounding_s)

