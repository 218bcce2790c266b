"""The live base station decides through `autopower.policies`, exactly as the simulator does.

The team is `SimTeam` (coordinator + one NodeRuntime per node, in memory, on a manual clock).
To put the team where a simulated mission would be at time T, the clock jumps to T and each
robot's meter is charged what the model predicts for the plan it ran (as the simulator drains
batteries), then the robots report their status.
"""

from __future__ import annotations

import pytest
from click.testing import CliRunner

from autopower.basestation.coordinator import CoordinatorConfig
from autopower.errors import AutoPowerError
from autopower.model.loading import load_scenario
from autopower.model.mission_events import load_events
from autopower.policies import POLICY_NAMES, make_policy
from autopower.protocol import LinkCommand
from autopower.simulation.simulator import simulate
from tests.unit.sim_team import SimTeam

FIG7 = load_scenario("paper-fig7")
ALL_LAPTOP = {s: "laptop" for s in FIG7.stage_names()}
PAPER_VC = {"Loc-1": "laptop", "Loc-2": "laptop", "Blob-2": "laptop", "Loc-3": "r1", "Blob-3": "r3"}
NEVER = 1e12  # virtual seconds: no periodic decision gets in the way of what a test watches


class Watched:
    """A policy that remembers every state it was asked about and what it answered."""

    def __init__(self, name: str, **params):
        self.inner = make_policy(name, **params)
        self.name = self.inner.name
        self.calls: list = []

    def decide(self, state):
        decision = self.inner.decide(state)
        self.calls.append((state, decision))
        return decision

    def asked_about(self, kind: str) -> tuple:
        """(state, decision) of the last call told about an event of this kind."""
        return next(call for call in reversed(self.calls) if any(e.kind == kind for e in call[0].events))


def team_with(policy: str | Watched, **config) -> SimTeam:
    name = policy if isinstance(policy, str) else policy.name
    team = SimTeam(FIG7, config=CoordinatorConfig(speed=1.0, policy=name, **config),
                   policy=policy if isinstance(policy, Watched) else None)
    team.join()
    return team


def jump_to(team: SimTeam, t: float) -> None:
    """Virtual time t, every robot's battery drained by the model's power for the plan it runs."""
    co = team.coordinator
    elapsed = t - team.clock.t
    used = {robot: team.energy(robot) for robot in co.robots}  # metered up to now
    team.clock.set(t)
    for robot in co.robots:
        meter = team.nodes[robot].meter
        meter.advance(t)  # idle CPU and sleeping radios; the runs the model counts are topped up
        meter._add("cpu_idle", used[robot] + co.prediction.predicted_w[robot] * elapsed - meter.consumed_j)
    team.report_status()


# ---- (a) the coordinator's decision is the policy's -----------------------------------------------------


@pytest.mark.parametrize("name", ["reactive", "rebalance", "subgroup"])
def test_operator_radio_fault_gives_the_simulators_and_the_papers_reallocation(name):
    """Paper V.C through the operator's link command: the same answer as `autopower simulate paper-fig7
    --events paper-vc-fault --policy NAME` at 3600 s, and as the policy called on the coordinator's state."""
    policy = Watched(name)
    team = team_with(policy)
    jump_to(team, 3600.0)
    co = team.coordinator
    reply = co.on_operator(LinkCommand(node="r3", laptop_robot="gsm", robot_robot="bluetooth"))
    assert reply.ok, reply.message
    team.pump()

    state, decision = policy.asked_about("radio-fault")
    assert state.radio_faults == {"r3": ("gsm", "bluetooth")}
    assert [(e.kind, e.robot, e.laptop_robot, e.robot_robot) for e in state.events] == [
        ("radio-fault", "r3", "gsm", "bluetooth")]
    assert state.time_s == pytest.approx(3600.0) and state.allocation == ALL_LAPTOP
    # the coordinator carried out exactly what the policy decided for that state
    assert decision.forced and dict(decision.allocation) == PAPER_VC
    assert co.placing.target == dict(decision.allocation) and co.deciding.plan_network == decision.network
    assert co.placing.placement == PAPER_VC and co.ready
    again = make_policy(name).decide(state)  # a pure function of the state
    assert dict(again.allocation) == dict(decision.allocation) and again.network == decision.network

    simulated = simulate(FIG7, load_events("paper-vc-fault", FIG7), policy=name)
    at_fault = next(d for d in simulated.decisions if d.time_s == 3600.0)
    assert dict(at_fault.allocation) == co.placing.placement
    assert dict(at_fault.media) == co.snapshot()["media"]
    assert team.nodes["r3"].meter.media == frozenset({"gsm", "bluetooth"})
    assert any("r3 radio:gsm utilisation" in line for line in co.snapshot()["decision_reasons"])


def test_state_given_to_the_policy_describes_the_team():
    policy = Watched("rebalance")
    team = team_with(policy, media={"laptop-robot": "802.11a", "robot-robot": "802.11a"})
    co = team.coordinator
    co.link_lost("laptop", "r1")
    co.on_timer()  # decided at the loop's next timer
    team.leave("r2")
    state, _ = policy.asked_about("robot-leave")
    assert state.unavailable_nodes == frozenset({"r2"}) and set(state.energies_j) == {"r1", "r3"}
    assert state.cut_links == frozenset({frozenset({"laptop", "r1"})})
    assert state.media_locked and state.network.medium_between("laptop", "r1") is None
    assert [(e.kind, e.robot) for e in state.events] == [("robot-leave", "r2")]  # the cut was decided before
    assert "r2" not in state.network.nodes


def test_battery_drift_reaches_the_policy_as_an_energy_offset():
    policy = Watched("reactive")
    team = team_with(policy, drift_min_window_s=10.0)
    co = team.coordinator
    team.run_until(2.0)
    team.report_status()  # anchors the prediction
    anchor = {r: co.prediction.baselines[r] for r in co.robots}
    team.run_until(20.0)
    team.nodes["r1"].meter._add("cpu_idle", 50.0)  # r1 burns far more than planned
    team.report_status()
    state, _ = policy.asked_about("energy-offset")
    [event] = state.events
    base = anchor["r1"]
    predicted_battery = base.battery_j - base.predicted_w * (state.time_s - base.t_virtual)
    assert event.robot == "r1" and event.delta_j < -40.0  # emptier than predicted by ~50 J
    assert event.delta_j == pytest.approx(state.energies_j["r1"] - predicted_battery)


# ---- (b) rebalance follows its time-sharing schedule ------------------------------------------------------


def test_rebalance_follows_the_schedule_and_switches_phase_at_the_revisit_time():
    team = team_with("rebalance", topology="relay", replan_interval_s=NEVER)
    co = team.coordinator
    first = co.deciding.decision
    assert co.placing.placement == ALL_LAPTOP and len(first.schedule) == 1  # Fig. 7, relay: two phases
    assert co.deciding.revisit_at_s == pytest.approx(first.revisit_at_s) == pytest.approx(32737.9, abs=1.0)
    snap = co.snapshot()
    assert snap["policy"] == "rebalance" and snap["revisit_at_s"] == co.deciding.revisit_at_s
    assert snap["schedule"][0]["allocation"] == dict(first.schedule[0].allocation)
    assert co.next_deadline_unix() <= team.clock.wall_at(co.deciding.revisit_at_s)
    next_phase = first.schedule[0]

    jump_to(team, co.deciding.revisit_at_s - 60.0)
    co.on_timer()
    team.pump()
    assert co.placing.placement == ALL_LAPTOP and co.placing.migrations_done == 0  # not yet

    jump_to(team, first.revisit_at_s + 0.5)
    co.on_timer()
    team.pump()
    decision = co.deciding.decision
    assert decision.time_s == pytest.approx(first.revisit_at_s + 0.5)
    assert dict(decision.allocation) == dict(next_phase.allocation) != ALL_LAPTOP
    assert decision.network == next_phase.network and co.deciding.plan_network.medium_between("r1", "r2") == "bluetooth"
    moved = {s for s in ALL_LAPTOP if next_phase.allocation[s] != "laptop"}
    assert co.placing.placement == dict(next_phase.allocation) and co.placing.migrations_done == len(moved) > 0
    assert {m["stage"] for m in co.placing.migration_log} == moved
    assert co.deciding.revisit_at_s is None  # the last phase runs until the end
    assert any("revisit" in e for e in co.events)


def test_no_replan_means_no_schedule_driven_moves():
    team = team_with("rebalance", topology="relay", auto_replan=False)
    co = team.coordinator
    assert len(co.deciding.schedule) == 1 and co.deciding.revisit_at_s is None  # planned, but the clock decides nothing
    jump_to(team, co.deciding.decision.revisit_at_s + 1.0)
    co.on_timer()
    team.pump()
    assert co.placing.placement == ALL_LAPTOP and co.placing.migrations_done == 0


# ---- (c) static never moves by choice; rebalance does --------------------------------------------------------


@pytest.mark.parametrize("name, moves", [("static", False), ("rebalance", True)])
def test_static_never_moves_by_choice_while_rebalance_does(name, moves):
    team = team_with(name, media={"laptop-robot": "gsm", "robot-robot": "bluetooth"}, replan_interval_s=20.0)
    co = team.coordinator
    start = dict(co.placing.placement)
    team.run_until(10.0)
    team.nodes["r2"].meter._add("cpu_idle", 40000.0)  # r2 has lost most of its battery
    team.report_status()
    for t in (25.0, 50.0, 75.0):  # periodic decisions with very uneven batteries
        team.run_until(t)
        co.on_timer()
        team.pump()
    assert co.ready
    if moves:
        assert co.placing.placement != start and co.placing.migrations_done > 0
        assert co.deciding.decision.policy == "rebalance" and not co.deciding.decision.forced
    else:
        assert co.placing.placement == start and co.placing.migrations_done == 0
        assert co.deciding.decision.time_s == 0.0  # only the start decided anything
        assert any("policy static keeps the configuration" in e for e in co.events)


# ---- (d) heal hysteresis is the policy's --------------------------------------------------------------------


def cut_and_heal(team: SimTeam) -> tuple:
    """Relay topology: cutting r1 from the laptop cuts everyone off (forced moves); then heal it."""
    co = team.coordinator
    team.run_until(5.0)
    co.link_lost("laptop", "r1", detected_unix=team.clock.wall())
    # the laptop is cut off, so the state of what it ran cannot leave it: those migrations time
    # out and the stages restart without it
    team.run_until(5.0 + co.config.migration_timeout_s + 1.0)
    co.on_timer()  # (the base station's loop calls it all the time; SimTeam only when messages flow)
    team.pump()
    assert co.ready
    during = (dict(co.placing.placement), co.placing.migrations_done + co.placing.aborted + co.placing.assignments_done)
    team.run_until(co.now() + 1.0)
    co.link_seen("laptop", "r1")
    co.on_timer()
    assert co.faults.links_down  # back only after heal_hold_s
    team.clock.advance(co.config.heal_hold_s + 0.1)
    co.on_timer()
    team.pump()
    assert not co.faults.links_down
    return during


def test_after_a_heal_components_move_back_only_past_the_policys_gain_threshold():
    # a threshold no move can meet: the forced moves of the cut happen, no voluntary move back after it
    team = team_with("rebalance", topology="relay", replan_interval_s=NEVER, policy_params={"min_gain_s": 1e9})
    co = team.coordinator
    (during, migrated) = cut_and_heal(team)
    assert during != ALL_LAPTOP and migrated > 0
    assert co.placing.placement == during and co.placing.migrations_done + co.placing.aborted + co.placing.assignments_done == migrated
    assert co.deciding.plan_network.medium_between("laptop", "r1") is not None  # the link is in the routes again
    assert any("links back" in e and "keeps the configuration" in e for e in co.events)


def test_after_a_heal_the_default_threshold_moves_back_once_and_does_not_flap():
    policy = Watched("rebalance")
    team = team_with(policy, topology="relay", replan_interval_s=5.0)
    co = team.coordinator
    (during, migrated) = cut_and_heal(team)
    state, decision = policy.asked_about("link-heal")
    assert [e.kind for e in state.events] == ["link-heal"]
    assert decision is not None and decision.moves and not decision.forced
    stay = decision.predicted_lifetime_s - decision.predicted_gain_s
    assert decision.predicted_gain_s > stay * 0.001 + 10.0  # rebalance's min_gain, min_gain_s
    assert co.placing.placement != during and co.ready
    settled, moved = dict(co.placing.placement), co.placing.migrations_done
    for t in (co.now() + 10.0, co.now() + 20.0, co.now() + 30.0):  # asked again with nothing new: no move
        team.run_until(t)
        co.on_timer()
        team.pump()
    assert len(policy.calls) >= 5
    assert co.placing.placement == settled and co.placing.migrations_done == moved


# ---- (e) configuration errors ------------------------------------------------------------------------------


def test_unknown_policy_or_parameter_is_a_clear_error_at_construction():
    with pytest.raises(AutoPowerError, match=r"unknown policy 'greedy'; choose one of static, reactive, rebalance, "
                                             r"subgroup"):
        CoordinatorConfig(policy="greedy")
    with pytest.raises(AutoPowerError, match="policy rebalance: .*min_gian"):
        CoordinatorConfig(policy="rebalance", policy_params={"min_gian": 0.1})


def test_policy_option_on_the_runtime_commands():
    from autopower.cli.demo import demo
    from autopower.cli.processes import basestation
    from autopower.cli.team import up

    for command in (basestation, up, demo):
        option = next(p for p in command.params if p.name == "policy")
        assert list(option.type.choices) == list(POLICY_NAMES) and option.default == "rebalance"
    result = CliRunner().invoke(basestation, ["--policy", "greedy"])
    assert result.exit_code == 2 and "'greedy' is not one of" in result.output
