"""Deciding: what the policy may know, asking it, and turning its answer into the target placement.

`Deciding` owns the decisions: the policy's question and answer (through `decider.Decider`, inline
or on a thread, and the mission start's question asked ahead), what happened since the last one
(events), when to ask next (revisits, the periodic decision, reasons due at the next timer), the
policy's last decision and allocation, the media and network of the plan in force, and the counts
of questions and answers. The target it derives goes to the placing part (`Placement.set_target`).
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Callable

from autopower.basestation.decider import Answer, Decider
from autopower.model.energy import round_lifetime
from autopower.model.mission_events import MissionEvent
from autopower.model.network import Network, describe_media, media_choices
from autopower.policies import (
    Decision,
    MigrationCosts,
    Policy,
    SchedulePhase,
    TeamState,
    base_media,
    derive_network,
)
from autopower.protocol import NodeStatus

log = logging.getLogger("autopower.basestation.coordinator")  # one logger for the coordinator's parts

# How far (virtual seconds) the mission start's question may be from the time the answer asked
# ahead was for (`AheadQuestion.answered`)
AHEAD_SLACK_S = 1.0
# How many answers in a row may be set aside because the team changed while the policy decided
# (`Deciding.take_answer`): a team that changes faster than the policy decides still gets a plan
STALE_ANSWERS_MAX = 3


class AheadQuestion:
    """The mission start's question, asked before the robots are heard (`Deciding.ask_ahead`), and its answer."""

    def __init__(self):
        self.asked = False  # the mission start was asked about ahead
        self.out = False  # ... and its answer is still out
        self._state: TeamState | None = None  # the question asked ahead (until the mission start's is asked)
        self._answer: Answer | None = None  # ... and its answer, kept for the mission start

    def ask(self, state: TeamState) -> None:
        self.asked, self.out, self._state = True, True, state

    def came(self, answer: Answer, *, keep: bool) -> None:
        """Its answer is in; ``keep``: for the mission start (nothing decided yet)."""
        self.out = False
        if keep:
            self._answer = answer

    def same_as(self, state: TeamState) -> bool:
        """Whether ``state`` is the question asked ahead. Its time is the mission's start; a
        question within `AHEAD_SLACK_S` of it counts as asked then (no policy's answer turns on
        its first second: revisits and schedules are minutes and hours)."""
        ahead = self._state
        return (ahead is not None and abs(state.time_s - ahead.time_s) <= AHEAD_SLACK_S
                and dataclasses.replace(state, time_s=ahead.time_s) == ahead)

    def take_up(self, state: TeamState) -> bool:
        """The mission starts while the question is out: True if ``state`` is that question (its
        answer, when it comes, is then the mission start's, as any answer)."""
        if not self.same_as(state):
            return False
        self.out, self._state = False, None
        return True

    def answered(self, state: TeamState) -> Answer | None:
        """The answer asked ahead, if it was about ``state`` (asked once, used at most once)."""
        ahead, self._answer = self._answer, None
        same = self.same_as(state)
        self._state = None
        if ahead is None or ahead.decision is None or ahead.error is not None or ahead.failure is not None:
            return None
        return ahead if same else None


class Deciding:
    """The coordinator's deciding part: team view -> policy -> target placement."""

    def __init__(self, team, *, policy: Policy, perf_fn: Callable[[], float],
                 on_decision_answer: Callable[[], object] | None):
        """``team``: the `Coordinator` whose view of the team the policy is asked about; the rest as
        `Coordinator` takes them."""
        self.team = team
        scenario, config = team.scenario, team.config
        self.decider = Decider(policy, perf_fn=perf_fn, on_answer=on_decision_answer)
        self.topology = config.topology or scenario.network_spec.topology
        self.migration_costs = MigrationCosts.from_scenario(scenario)
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
        self.plan_error: str | None = None
        # why the last `replan` did not decide though nothing was wrong (robots to report, none in
        # reach): an operator's command is then noted and carried out by the re-plan that follows
        self.replan_waiting: str | None = None
        # link changes since the last timer: one decision at the next timer for all of them (a
        # fleet under load loses several links within one batch of events, and each decision is
        # a MILP of the whole team that holds up the loop while statuses pile up)
        self.replan_due: list[str] = []
        self.next_periodic_replan: float | None = None
        self.replans = 0
        self.asked = 0  # questions put to the policy
        self._events_asked = 0  # how many of `_pending_events` the question out carries
        self.ahead = AheadQuestion()  # the mission start's question, asked before the robots are heard (`ask_ahead`)
        self._stale_answers = 0  # answers set aside in a row: the team changed while the policy decided
        self.decisions = 0  # the policy answered (a re-plan that decided, whatever it chose)
        self.decide_s = 0.0  # wall seconds the policy took over them (`perf_fn`)
        self.decide_max_s = 0.0

    def decision_pending(self) -> bool:
        """A question is out, or due at the next timer: the plan in force is not the last word."""
        return self.decider.busy or bool(self.replan_due)

    def ask_due(self) -> None:
        """Ask, once for all the reasons given since the last timer, unless a question is out."""
        if self.replan_due and not self.decider.busy:
            reasons, self.replan_due = self.replan_due, []
            self.replan(", ".join(dict.fromkeys(reasons)))

    def deadlines(self) -> list[float]:
        """When the next question is due: reasons waiting, a revisit asked for, the periodic one."""
        team = self.team
        deadlines = []
        if self.replan_due and not self.decider.busy:  # (a question out: its answer wakes the loop)
            deadlines.append(team.wall())
        if team.clock is not None and self.revisit_at_s is not None:
            deadlines.append(team.clock.wall_at(self.revisit_at_s))
        # the periodic decision is due by the clock too (a loop at rest does not wake every status period to look)
        if team.mission is not None and team.config.auto_replan and self.next_periodic_replan is not None:
            deadlines.append(team.clock.wall_at(self.next_periodic_replan))
        return deadlines

    def cannot_decide(self, error: str) -> None:
        """Nothing can be decided, for this reason (a takeover of a team that runs another scenario)."""
        self.plan_error = error

    def replan_periodically_from(self, t_virtual: float) -> None:
        """The next periodic decision is due at mission time ``t_virtual`` (then every ``replan_interval_s``)."""
        self.next_periodic_replan = t_virtual

    def remaining_energies(self) -> dict[str, float]:
        out = {}
        for robot in self.team.robots:
            status = self.team.statuses.get(robot)
            if status is not None and status.battery_j is not None:
                out[robot] = max(status.battery_j, 1e-6)
            else:
                out[robot] = self.team.scenario.robot(robot).energy_j
        return out

    def unavailable(self, everyone: bool = False) -> frozenset[str]:
        if everyone:
            return frozenset()
        alive = self.team.alive_nodes()  # (a set built per call: once, not once per robot)
        return frozenset(r for r in self.team.robots if r not in alive)

    def _cut_links(self) -> frozenset[frozenset[str]]:
        return frozenset(self.team.faults.links_down | self.team.operating.operator_cuts)

    def network_in_use(self, everyone: bool = False) -> Network:
        """The links the team uses now: the media in use, minus what is down, with the radio faults."""
        return derive_network(self.team.scenario, self.topology, self.media, self._cut_links(),
                              dict(self.team.operating.radio_faults),
                              self.unavailable(everyone))

    def _current_allocation(self) -> dict[str, str]:
        """What runs (or is being made to run): the target, where a stage is not on its way somewhere
        else, corrected by where it is confirmed to run (e.g. adopted from a returning robot)."""
        placing = self.team.placing
        allocation = dict(placing.target)
        for stage, host in placing.placement.items():
            if stage in allocation and stage not in placing.migrations:
                allocation[stage] = host
        return allocation

    def team_state(self, *, everyone: bool = False) -> TeamState:
        """What the policy may know, from the coordinator's view of the team (see the module docstring).
        ``everyone``: as if every robot of the scenario were in reach (`ask_ahead`)."""
        alive = set(self.team.robots) | {self.team.base} if everyone else self.team.alive_nodes()
        energies = self.remaining_energies()
        return TeamState(
            scenario=self.team.scenario, time_s=self.team.now(), network=self.network_in_use(everyone),
            allocation=self._current_allocation(),
            energies_j={r: e for r, e in energies.items() if r in alive},
            disabled_chains=frozenset(self.team.operating.disabled), unavailable_nodes=self.unavailable(everyone),
            topology=self.topology, cut_links=self._cut_links(), radio_faults=dict(self.team.operating.radio_faults),
            media_locked=bool(self.team.config.media), accounting=self.team.scenario.accounting,
            events=tuple(self._pending_events), migration=self.migration_costs, schedule=self.schedule)

    def event(self, kind: str, **fields) -> None:
        """Something the next decision should hear about (`TeamState.events`)."""
        self._pending_events.append(MissionEvent(at_s=self.team.now(), kind=kind, **fields))

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
        if self.team.mission is None:
            return False
        if self.decider.busy:
            if not (self.ahead.out and self._take_up_ahead_question(reason)):
                self.replan_due.append(reason)  # `on_timer` asks once the answer out is carried out
            return True
        awaiting = self.team.awaiting_reports()
        if awaiting and not after_rejoin:
            # robots are back and have not said what they run yet: decide once they have
            waiting = ", ".join(awaiting)
            self.team.note(f"decision ({reason}) deferred until {waiting} report")
            self.replan_waiting = f"the re-plan waits until {waiting} report what they run"
            return False
        if len(self.unavailable()) == len(self.team.robots):
            self.team.note(f"no robot left ({reason}); nothing to run")
            self.replan_waiting = "no robot is in reach of the base station; the re-plan waits until one is back"
            self.team.placing.set_target({})
            self.chosen = {}
            self.schedule, self.revisit_at_s = (), None
            self._pending_events.clear()
            self.team.placing.reconcile()
            self.team.plans.publish_plan()
            return False
        state = self.team_state()
        self._events_asked = len(self._pending_events)  # the events this question carries
        if not again:
            self.asked += 1
        ahead = self.ahead.answered(state)
        if ahead is not None:
            self.team.note(f"decision ({reason}) made ahead, before the robots were heard "
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
        if (self.team.mission is not None or self.ahead.asked or not self.decider.on_thread
                or self.decider.busy or self.team.takeover.stepped_down is not None):
            return
        state = self.team_state(everyone=True)
        self.ahead.ask(state)
        self.decider.ask(state, "mission start")

    def _take_up_ahead_question(self, reason: str) -> bool:
        """The mission starts while the question asked ahead is out: if it is this question, its
        answer is this question's (carried out when it comes, as any answer), not asked twice."""
        if not self.ahead.take_up(self.team_state()):
            return False
        self._events_asked = len(self._pending_events)
        self.asked += 1
        self.team.note(f"decision ({reason}) asked ahead, before the robots were heard: its answer is on its way")
        return True

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
        if self.ahead.out:
            self.ahead.came(answer, keep=self.decisions == 0)  # kept for the mission start (`AheadQuestion.answered`)
            if answer.failure is not None:
                raise answer.failure
            return False
        # (inline, nothing can change between the question and its answer)
        changed = self._changed_since(answer.state) if self.decider.on_thread and answer.failure is None else None
        if changed is not None and self._stale_answers < STALE_ANSWERS_MAX:
            self._stale_answers += 1
            self.decide_s += answer.took_s  # the policy's time all the same (the question is not answered yet)
            self.team.note(f"decision ({answer.reason}) asked again: {changed} changed while the policy decided")
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
        self.team.faults.decided(answer.took_s)
        if answer.failure is not None:
            raise answer.failure  # the policy's bug, raised on the loop as an inline decision would
        if answer.error is not None:
            self.plan_error = str(answer.error)
            self.team.note(f"decision ({answer.reason}) found nothing feasible: {answer.error}")
            return False
        if self.team.takeover.stepped_down is not None:
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
        pins = self.team.operating.pins
        self.chosen = {s: self.chosen.get(s, h) if s in pins else h for s, h in state.allocation.items()}
        target = self.team.operating.with_pins(dict(state.allocation), self.team.alive_nodes())
        changed = target != self.team.placing.target or state.network != self.plan_network
        self.team.placing.set_target(target)
        self.plan_network = state.network
        self.team.note(f"decision ({reason}): policy {self.team.policy.name} keeps the configuration")
        self.team.prediction.predict()
        if changed:  # e.g. a link is gone from (or back in) the routes, nothing moves
            self.replans += 1  # a new plan all the same: every node takes it up
            self.team.placing.reconcile()
            self.team.plans.publish_plan()

    def _carry_out(self, decision: Decision, reason: str) -> None:
        """The decision's allocation becomes the target (operator pins win), its network the plan's."""
        self.decision = decision
        self.schedule = tuple(decision.schedule)
        at = decision.revisit_at_s
        # without auto_replan nothing is decided by the clock: no revisit (the schedule still travels)
        revisit = self.team.config.auto_replan and at is not None and at > self.team.now() + 1e-6
        self.revisit_at_s = at if revisit else None
        if not self.team.config.media:
            self.media.update(base_media(decision.network))
        self.chosen = dict(decision.allocation)
        target = self.team.operating.with_pins(dict(decision.allocation), self.team.alive_nodes())
        before = self.team.placing.target
        changed = {s for s in target if before.get(s) != target[s]} | (set(before) - set(target))
        network_changed = decision.network != self.plan_network
        self.team.placing.set_target(target)
        self.plan_network = decision.network
        self.stage_reasons = {s: why for s, why in {**self.stage_reasons, **decision.stage_reasons}.items()
                              if s in target}
        if changed or network_changed:
            self.replans += 1
        if decision.reasons:
            self.decision_reasons = tuple(decision.reasons)
        for line in decision.reasons:
            self.team.note(f"decision ({reason}): {line}")
        planned = round_lifetime(decision.predicted_lifetime_s, self.team.scenario.lifetime_rounding_s)
        self.team.note(f"plan ({reason}, policy {decision.policy}): predicted lifetime {planned} s, media "
                  f"{describe_media(decision.network.media_by_group())}, {len(changed)} stage(s) to place"
                  + (f", dropped {', '.join(decision.dropped)}" if decision.dropped else "")
                  + (f", next decision at t={self.revisit_at_s:.1f}s" if self.revisit_at_s is not None else ""))
        self.team.prediction.predict()
        self.team.placing.reconcile()
        self.team.plans.publish_plan()

    def check_drift(self, status: NodeStatus) -> None:
        """A robot's battery off the prediction asks the policy again (`Prediction.drift`)."""
        team = self.team
        if not team.config.auto_replan or status.battery_j is None or not team.ready:
            return
        if not team.plans.holds_plan(status):
            return
        drift = team.prediction.drift(status, team.config.drift_min_window_s, team.config.drift_tolerance)
        if drift is None:
            return
        team.note(f"{status.node} drew {drift.measured_j / drift.elapsed_s:.3f} W, plan said {drift.predicted_w:.3f} W")
        # the battery is off the prediction by this much (negative: emptier than predicted)
        self.event("energy-offset", robot=status.node, delta_j=drift.predicted_j - drift.measured_j)
        if not self.replan(f"{status.node} battery drift"):
            team.prediction.reset_baselines()

    def timed_decisions(self) -> None:
        """The decision a schedule asked for at its phase's end, and the periodic one (no events)."""
        now = self.team.now()
        due_periodic = self.next_periodic_replan is not None and now >= self.next_periodic_replan
        if self.revisit_at_s is not None and now >= self.revisit_at_s:
            self.revisit_at_s = None
            self.next_periodic_replan = now + self.team.config.replan_interval_s  # this one counts as it
            self.replan(f"revisit at t={now:.1f}s, as the last decision asked")
        elif due_periodic:
            self.next_periodic_replan = now + self.team.config.replan_interval_s
            self.replan("periodic, remaining energies")

    def planned_lifetime_s(self) -> float | None:
        """The last decision's predicted lifetime from its time on (rounded as the scenario says)."""
        if self.decision is None:
            return None
        return round_lifetime(self.decision.predicted_lifetime_s, self.team.scenario.lifetime_rounding_s)

