"""The policy decides on a thread: the coordinator goes on meanwhile, carries the answer out when
it comes, and asks once more for what happened while it decided (`basestation/decider.py`)."""

from __future__ import annotations

import math
import threading
import time

import pytest

from autopower.basestation.coordinator import CoordinatorConfig
from autopower.basestation.decider import AwaitDecision
from autopower.basestation.process import BaseStation, BaseStationConfig
from autopower.model.loading import load_scenario
from autopower.node.runtime import NodeRuntime
from autopower.policies import make_policy
from autopower.protocol import ChainCommand, Keys, LinkCommand, OperatorReply, SnapshotRequest, decode, encode
from autopower.runtime.bus import InMemoryHub
from tests.unit.sim_team import FakeComponent, FakeRequest, FakeSource, SimTeam

FIG7 = load_scenario("paper-fig7")
WAIT_S = 30.0  # a bound on a thread that must answer, never a figure


class Gated:
    """The rebalance policy, deciding only once the test lets it (one question per `release`)."""

    name = "rebalance"

    def __init__(self, fail_with: Exception | None = None):
        self.inner = make_policy("rebalance")
        self.fail_with = fail_with
        self.gate = threading.Semaphore(0)
        self.states: list = []
        self.threads: set[str] = set()

    def decide(self, state):
        assert self.gate.acquire(timeout=WAIT_S), "the test never let the policy decide"
        self.states.append(state)
        self.threads.add(threading.current_thread().name)
        if self.fail_with is not None:
            raise self.fail_with
        return self.inner.decide(state)


class Answers:
    """What the coordinator's `on_decision_answer` sees (it is called from the policy's thread)."""

    def __init__(self):
        self.count = 0
        self.cond = threading.Condition()

    def __call__(self):
        with self.cond:
            self.count += 1
            self.cond.notify_all()

    def wait_for(self, count: int) -> None:
        with self.cond:
            assert self.cond.wait_for(lambda: self.count >= count, timeout=WAIT_S), f"answer {count} never came"


def threaded_team(policy) -> tuple[SimTeam, Answers]:
    answers = Answers()
    team = SimTeam(FIG7, config=CoordinatorConfig(speed=1.0, policy="rebalance", replan_interval_s=1e12),
                   policy=policy, on_decision_answer=answers)
    return team, answers


def answer_next(policy: Gated, answers: Answers, count: int, team: SimTeam) -> None:
    """Let the policy answer the question out (answer number ``count``) and the loop's timer take it."""
    policy.gate.release()
    answers.wait_for(count)
    team.pump()


def started_team() -> tuple[Gated, SimTeam, Answers]:
    """A team deciding on a thread whose mission start is answered and carried out."""
    policy = Gated()
    team, answers = threaded_team(policy)
    team.join()
    answer_next(policy, answers, 1, team)
    return policy, team, answers


def test_the_coordinator_goes_on_while_the_policy_decides_and_carries_the_answer_out_after():
    policy = Gated()
    team, answers = threaded_team(policy)
    co = team.coordinator
    team.join()
    # the mission started and the question is out: nothing is decided, nothing placed, and the loop goes on
    assert co.mission is not None and co.deciding.decider.busy and co.deciding.asked == 1 and co.deciding.decisions == 0
    assert co.placing.target == {} and not co.ready
    team.report_status()  # statuses are taken while the policy decides
    assert all(robot in co.statuses for robot in co.robots)
    assert not co.idle()  # a loop at rest would not wake for the answer's timers

    answer_next(policy, answers, 1, team)  # the loop's timer carries the answer out
    assert co.deciding.decisions == 1 and not co.deciding.decider.busy and co.placing.target and co.ready
    assert policy.threads == {"autopower-decide"}  # decided off the caller's thread


def test_what_happens_while_it_decides_is_asked_about_and_an_answer_it_outdates_is_set_aside():
    policy, team, answers = started_team()
    co = team.coordinator
    assert co.ready and co.deciding.asked == 1
    ready_target = dict(co.placing.target)

    # an operator's radio change: the reply waits for the decision that carries it out
    waiting = co.on_operator(LinkCommand(node="r3", laptop_robot="gsm", robot_robot="bluetooth"))
    assert isinstance(waiting, AwaitDecision) and waiting.ticket == 2
    assert co.reply_when_decided(waiting) is None
    # while that question is out, the operator disables a chain: it waits for the question after
    later = co.on_operator(ChainCommand(chain="Blob-2", enabled=False))
    assert isinstance(later, AwaitDecision) and later.ticket == 3
    assert co.deciding.asked == 2 and co.deciding.replan_due  # queued, not asked: one question at a time

    answer_next(policy, answers, 2, team)  # answer 2 is about a team that still ran Blob-2: set aside, question 2 asked again
    asked_about = policy.states[1]
    assert [e.kind for e in asked_about.events] == ["radio-fault"] and "Blob-2" not in asked_about.disabled_chains
    assert co.deciding.asked == 2 and co.deciding.decisions == 1 and co.deciding.decider.busy and co.placing.target == ready_target
    assert co.reply_when_decided(waiting) is None
    assert any("asked again: the chains that run changed" in line for line in co.events)

    answer_next(policy, answers, 3, team)  # question 2, asked again, carried out; the queued reason asked at once as question 3
    again = policy.states[2]
    assert [e.kind for e in again.events] == ["radio-fault", "chain-disable"] and "Blob-2" in again.disabled_chains
    reply = co.reply_when_decided(waiting)
    assert reply is not None and reply.ok, reply
    assert not any(s.startswith("Blob-2") for s in co.placing.target)
    assert co.deciding.asked == 3 and co.deciding.decider.busy and co.reply_when_decided(later) is None

    answer_next(policy, answers, 4, team)
    reply = co.reply_when_decided(later)
    assert reply is not None and reply.ok, reply
    assert policy.states[3].events == ()  # each event told once
    assert co.ready and not co.deciding.decider.busy and co.deciding.asked == co.deciding.decisions == 3


def test_a_team_that_changes_faster_than_the_policy_decides_still_gets_a_plan():
    from autopower.basestation.deciding import STALE_ANSWERS_MAX

    policy, team, answers = started_team()
    co = team.coordinator
    co.deciding.replan("test")
    for i in range(STALE_ANSWERS_MAX + 1):
        # each answer's team is gone before it is in: Blob-2 switched while the policy decides
        co.on_operator(ChainCommand(chain="Blob-2", enabled=i % 2 == 1))
        answer_next(policy, answers, 2 + i, team)
    set_aside = [line for line in co.events if "asked again" in line]
    assert len(set_aside) == STALE_ANSWERS_MAX  # then the answer is carried out all the same
    assert co.deciding.decisions >= 2 and co.deciding.plan_error is None


def test_a_question_asked_again_after_every_robot_left_is_not_put_to_the_policy():
    """`autopower demo`: the last robots left while the question about the first one's leaving
    was out. Asked again without `replan`'s checks, the policy planned a team of no robot
    (lifetime inf), and every snapshot after failed to encode ("non-finite number inf")."""
    policy, team, answers = started_team()
    co = team.coordinator
    team.leave("r1")  # asked about
    assert co.deciding.decider.busy and co.deciding.asked == 2
    team.leave("r2")
    team.leave("r3")
    answer_next(policy, answers, 2, team)
    assert len(policy.states) == 2  # set aside, and not asked again: no robot is left to plan
    assert co.placing.target == {} and any("no robot left" in line for line in co.events)
    reply = co.on_operator(SnapshotRequest())
    encode(reply)  # the snapshot an operator asks for still travels
    assert reply.snapshot["predicted_lifetime_s"] is None or math.isfinite(reply.snapshot["predicted_lifetime_s"])


def test_a_fault_is_not_handled_by_the_plan_from_before_its_decision():
    """`autopower demo`'s cut was marked reconfigured 56 ms before the robots ran its plan: while
    its decision was out, the plan in force (the one before it) was ready and every robot ran it."""
    policy, team, answers = started_team()
    co = team.coordinator
    team.report_status()
    before = co.plans.epoch
    team.leave("r1")
    assert co.deciding.decider.busy and co.ready  # the old plan is in force, and every robot in reach runs it
    team.report_status()
    co.on_timer()
    fault = co.faults.faults[-1]
    assert fault["kind"] == "node-left" and fault["reconfigured_unix"] is None
    answer_next(policy, answers, 2, team)
    team.report_status()
    co.on_timer()
    assert co.plans.epoch > before and fault["epoch"] > before and fault["reconfigured_unix"] is not None


def test_a_policy_that_fails_on_its_thread_fails_on_the_loop_and_the_next_question_is_asked():
    policy = Gated(fail_with=ValueError("a bug in the policy"))
    team, answers = threaded_team(policy)
    co = team.coordinator
    with pytest.raises(ValueError, match="a bug in the policy"):  # as an inline decision would raise
        team.join()
        answer_next(policy, answers, 1, team)
    assert co.deciding.decisions == 1 and not co.deciding.decider.busy and co.placing.target == {}
    policy.fail_with = None
    co.deciding.replan("again")
    answer_next(policy, answers, 2, team)
    assert co.ready


def test_inline_decisions_are_carried_out_before_replan_returns():
    team = SimTeam(FIG7, config=CoordinatorConfig(speed=1.0, policy="rebalance", replan_interval_s=1e12))
    co = team.coordinator
    team.join()
    assert co.ready and co.deciding.asked == co.deciding.decisions == 1 and not co.deciding.decider.on_thread
    reply = co.on_operator(ChainCommand(chain="Blob-2", enabled=False))
    assert not isinstance(reply, AwaitDecision) and reply.ok and co.deciding.decisions == 2


# ---- the mission start, asked ahead ----------------------------------------------------------------------


def test_the_mission_start_asked_ahead_is_carried_out_at_once_when_the_team_is_as_expected():
    policy = Gated()
    team, answers = threaded_team(policy)
    co = team.coordinator
    co.on_timer()  # the base station is up; no robot seen yet
    assert co.deciding.decider.busy and co.mission is None and co.deciding.asked == 0
    policy.gate.release()
    answers.wait_for(1)
    co.on_timer()
    assert co.deciding.decisions == 0 and co.placing.target == {}  # kept, not carried out: there is no mission
    team.join()  # every robot, every battery full: the question asked ahead
    assert len(policy.states) == 1  # the policy was not asked again
    assert co.deciding.decisions == co.deciding.asked == 1 and co.placing.target and co.ready
    assert any("made ahead" in line for line in co.events)
    assert policy.states[0].time_s == 0.0 and policy.states[0].unavailable_nodes == frozenset()


def test_a_start_unlike_the_one_asked_ahead_is_asked_again():
    policy = Gated()
    answers = Answers()
    team = SimTeam(FIG7, config=CoordinatorConfig(speed=1.0, policy="rebalance", replan_interval_s=1e12,
                                                  start_grace_s=0.0),
                   policy=policy, on_decision_answer=answers)
    co = team.coordinator
    co.on_timer()
    policy.gate.release()
    answers.wait_for(1)
    team.join(["r1", "r2"])  # r3 never comes: the mission starts without it
    assert co.mission is not None and co.deciding.decider.busy and co.deciding.asked == 1
    answer_next(policy, answers, 2, team)
    assert [s.unavailable_nodes for s in policy.states] == [frozenset(), frozenset({"r3"})]
    assert co.deciding.decisions == 1 and "r3" not in co.placing.target.values() and co.ready


def test_a_mission_that_starts_while_its_question_is_asked_ahead_takes_its_answer_and_asks_nothing_more():
    policy = Gated()
    team, answers = threaded_team(policy)
    co = team.coordinator
    co.on_timer()
    team.join()  # the start's question is the one asked ahead: its answer will be the start's
    assert co.mission is not None and co.deciding.asked == 1 and co.deciding.replan_due == [] and co.deciding.decider.busy
    answer_next(policy, answers, 1, team)
    assert len(policy.states) == 1 and co.deciding.decisions == co.deciding.asked == 1 and co.ready


# ---- the base station's process: its loop goes on while the policy decides ----------------------------


def wait_until(check, what: str) -> None:
    deadline = time.monotonic() + WAIT_S
    while not check():
        assert time.monotonic() < deadline, f"never: {what}"
        time.sleep(0.01)


def noted(co, text: str) -> bool:
    """Whether the coordinator (on the loop's thread) has noted ``text``."""
    try:
        return any(text in line for line in tuple(co.events))
    except RuntimeError:  # noted into while we looked
        return False


def test_the_base_station_keeps_its_heartbeat_and_its_queue_going_while_the_policy_decides():
    """The process, not only the coordinator: while a decision is out, the loop goes on sending
    each robot its heartbeat (a robot takes a silent base station for gone after a lease) and takes
    events; an operator's command gets one reply, after the decision that carries it out; one
    still waiting when the base station stops gets one too."""
    hub = InMemoryHub()  # delivered on the publisher's thread, as Zenoh's callbacks are
    keys = Keys("d")
    policy = Gated()
    config = BaseStationConfig(scenario=FIG7, team="d", coordinator=CoordinatorConfig(speed=1.0))
    robots = {r.name: NodeRuntime(node=r.name, scenario=FIG7, bus=hub.bus(r.name), keys=keys,
                                  make_component=FakeComponent, make_source=FakeSource) for r in FIG7.robots}
    heartbeats: list[float] = []  # when r1 heard the base station
    hub.bus("r1").subscribe(keys.addressed("r1", "laptop"), lambda key, payload: heartbeats.append(time.monotonic()))

    def host(**kw):
        return NodeRuntime(make_component=FakeComponent, make_source=FakeSource, **kw)

    with BaseStation(config, host_factory=host, bus=hub.bus("laptop"), policy=policy) as base:
        loop = threading.Thread(target=base.run, kwargs={"max_wall_s": WAIT_S}, daemon=True)
        loop.start()
        try:
            co = base.coordinator
            wait_until(lambda: co.deciding.decider.busy, "the mission start asked ahead")  # before any robot is seen
            assert co.mission is None
            for name, rt in robots.items():
                hub.bus(name).declare_token(keys.alive(name))
                hub.bus(name).publish(keys.status(name), encode(rt.status(0.0)))
            wait_until(lambda: co.mission is not None, "the mission started")
            assert co.deciding.decider.busy and co.deciding.asked == 1  # its question is the one asked ahead

            before = len(heartbeats)
            time.sleep(3 * config.status_period_s)  # the policy is held: the loop is not
            assert len(heartbeats) >= before + 2, "no heartbeat while the policy decided"
            first = FakeRequest(keys.operator, encode(ChainCommand(chain="Blob-2", enabled=False)))
            base.events.on_request(first)
            time.sleep(2 * config.status_period_s)
            assert first.replies == [] and not first.closed  # its decision is not even asked yet

            policy.gate.release()  # the start's answer: about a team with Blob-2, set aside, asked again
            wait_until(lambda: noted(co, "asked again: the chains that run changed"), "the start asked again")
            policy.gate.release()  # the start, asked again with Blob-2 off; then the command's question
            wait_until(lambda: co.deciding.decisions == 1 and co.deciding.asked == 2, "the command's question asked")
            assert co.placing.target and first.replies == []
            policy.gate.release()
            wait_until(lambda: first.closed, "the reply to the command")
            assert len(first.replies) == 1 and co.deciding.decisions == 2
            reply = decode(first.replies[0], OperatorReply)
            assert reply.ok and reply.message.startswith("re-planned"), reply.message
            assert co.placing.target and not any(stage.startswith("Blob-2") for stage in co.placing.target)
            assert [s.disabled_chains for s in policy.states] == [frozenset()] + [frozenset({"Blob-2"})] * 2

            second = FakeRequest(keys.operator, encode(ChainCommand(chain="Blob-2", enabled=True)))
            base.events.on_request(second)
            wait_until(lambda: co.deciding.asked == 3, "the second command's question asked")
        finally:
            base.request_stop("test")
            loop.join(WAIT_S)
        assert not loop.is_alive()
        policy.gate.release()  # lets the abandoned question end
    assert second.closed and len(second.replies) == 1  # stopped before its decision: told so
    reply = decode(second.replies[0], OperatorReply)
    assert not reply.ok and "stopped before the decision" in reply.message
