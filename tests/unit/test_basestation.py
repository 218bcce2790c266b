"""The coordinator: when it plans, what it moves, how it reacts to the team and the operator."""

from __future__ import annotations

import dataclasses
import random

import pytest

from autopower.basestation.coordinator import CoordinatorConfig
from autopower.basestation.process import BaseStation, BaseStationConfig
from autopower.model.energy import evaluate
from autopower.model.loading import load_scenario
from autopower.node.runtime import NodeRuntime
from autopower.protocol import (
    AutoCommand,
    ChainCommand,
    Keys,
    LinkCommand,
    MigrateCommand,
    OperatorReply,
    SnapshotRequest,
    decode,
    encode,
)
from autopower.protocol.codec import looks_like_message, message_kind
from autopower.runtime.bus import InMemoryHub
from autopower.runtime.events import StopRequested
from tests.unit.sim_team import FakeComponent, FakeRequest, FakeSource, SimTeam

ALL_LAPTOP = {"Loc-1": "laptop", "Loc-2": "laptop", "Loc-3": "laptop", "Blob-2": "laptop", "Blob-3": "laptop"}


@pytest.fixture
def sc():
    return load_scenario("paper-fig7")


def test_mission_waits_for_every_robot_then_places_the_optimum(sc):
    team = SimTeam(sc)
    team.join(["r1", "r2"])
    assert team.coordinator.mission is None
    assert not team.coordinator.on_operator(ChainCommand(chain="Blob-2", enabled=False)).ok
    team.join(["r3"])
    co = team.coordinator
    assert co.mission is not None and co.ready
    assert co.placing.placement == ALL_LAPTOP  # Fig. 7's best: everything on the laptop over 802.11a
    assert co.deciding.planned_lifetime_s() == 45715.2
    assert co.deciding.decision.policy == "rebalance" and co.snapshot()["policy"] == "rebalance"  # the default
    assert set(co.placing.runs.running) == {c.name for c in sc.chains}
    assert all(rt.plan is not None and rt.plan.epoch == co.plans.epoch for rt in team.nodes.values())


def test_starts_without_missing_robots_after_the_grace_period(sc):
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0, start_grace_s=5.0))
    team.join(["r1"])
    assert team.coordinator.mission is None
    team.clock.advance(6.0)
    team.coordinator.on_timer()
    team.pump()
    co = team.coordinator
    assert co.mission is not None
    assert set(co.placing.target) == {"Loc-1"}  # r2's and r3's chains cannot run without them


def test_a_waiting_base_station_sleeps_until_the_grace_period_ends(sc):
    """Before the first plan nothing is due (a deadline of 0 made its loop spin at 100 % of a core)."""
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0, start_grace_s=5.0))
    co = team.coordinator
    assert co.next_deadline_unix() == float("inf")  # nobody yet: only an event can wake it
    team.join(["r1"])
    assert co.mission is None
    assert co.next_deadline_unix() == pytest.approx(co.takeover.listening.first_seen_unix + 5.0)
    team.join(["r2", "r3"])
    assert co.mission is not None and co.next_deadline_unix() > team.clock.wall()


def test_a_robot_leaving_drops_its_chains_and_rehosts_what_it_ran(sc):
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0, pins={"Loc-1": "r2"}))
    team.join()
    co = team.coordinator
    assert co.placing.placement["Loc-1"] == "r2"
    team.run_until(4.0)
    team.leave("r2")
    assert "Loc-2" not in co.placing.target and "Blob-2" not in co.placing.target
    assert co.placing.placement["Loc-1"] != "r2" and co.ready  # the pin to a departed robot is ignored
    team.run_until(10.0)
    assert team.nodes["r1"].sinks["Loc-1"].received > 0
    assert co.deciding.replans >= 2


def test_rejoining_robot_is_planned_again(sc):
    team = SimTeam(sc)
    team.join()
    team.leave("r3")
    assert "Loc-3" not in team.coordinator.placing.target
    # the agent comes back (a new process would resubscribe; reuse the runtime's bus here)
    rt = team.nodes["r3"]
    keys = team.keys
    team.subscriptions["r3"] = [rt.bus.subscribe(k, lambda key, p, rt=rt: rt.on_message(key, p))
                                for k in (keys.node_data("r3"), keys.node_control("r3"), keys.plan)]
    team.join(["r3"])
    team.report_status()  # a returning robot is planned from what it reports hosting
    assert team.coordinator.placing.placement == ALL_LAPTOP


def test_chain_disable_releases_and_stops_the_source(sc):
    team = SimTeam(sc)
    team.join()
    team.run_until(3.0)
    reply = team.coordinator.on_operator(ChainCommand(chain="Blob-2", enabled=False))
    assert reply.ok and "re-planned" in reply.message
    team.run_until(6.0)
    assert "Blob-2" not in team.nodes["laptop"].hosted
    assert "Blob-2" not in team.nodes["r2"].sources
    assert team.coordinator.on_operator(ChainCommand(chain="Blob-2", enabled=False)).message.endswith("disabled")
    assert not team.coordinator.on_operator(ChainCommand(chain="Nope", enabled=False)).ok


def test_operator_pins_and_auto(sc):
    team = SimTeam(sc)
    team.join()
    co = team.coordinator
    for bad in (MigrateCommand(stage="Loc-9", to_node="r1"), MigrateCommand(stage="Loc-1", to_node="r9")):
        reply = co.on_operator(bad)
        assert not reply.ok and "unknown" in reply.message
    assert co.on_operator(MigrateCommand(stage="Loc-2", to_node="r1")).ok
    team.pump()
    assert co.placing.placement["Loc-2"] == "r1" and co.placing.migrations_done == 1
    assert co.on_operator(AutoCommand()).ok
    team.pump()
    assert co.placing.placement == ALL_LAPTOP and co.operating.pins == {}


def test_radio_fault_replans_like_the_paper(sc):
    """Paper V.C: r3 falls back to GSM/Bluetooth; Loc-3 goes to r1, Blob-3 stays on r3."""
    team = SimTeam(sc)
    team.join()
    reply = team.coordinator.on_operator(LinkCommand(node="r3", laptop_robot="gsm", robot_robot="bluetooth"))
    assert reply.ok
    team.run_until(4.0)
    co = team.coordinator
    assert co.placing.placement == {"Loc-1": "laptop", "Loc-2": "laptop", "Loc-3": "r1", "Blob-2": "laptop", "Blob-3": "r3"}
    assert co.deciding.plan_network.medium_between("r3", "laptop") == "gsm"
    assert team.nodes["r3"].meter.media == frozenset({"gsm", "bluetooth"})


def test_reported_link_down_replans_around_it(sc):
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0, link_down_after_s=2.0))
    team.join()
    team.nodes["r2"].sight.alive.discard("laptop")  # r2 no longer sees the laptop (nor it r2)
    team.nodes["laptop"].sight.alive.discard("r2")
    team.report_status()
    assert not team.coordinator.faults.links_down
    team.clock.advance(2.5)  # wall time = virtual / speed 1
    team.report_status()
    co = team.coordinator
    assert co.faults.links_down == {frozenset({"r2", "laptop"})}
    assert not co.deciding.plan_network.reachable("r2", "laptop") or co.deciding.plan_network.medium_between("r2", "laptop") is None
    team.run_until(co.now() + 4.0)
    assert team.nodes["laptop"].sinks["Blob-2"].received > 0  # now relayed by another robot
    assert team.nodes["r1"].counters.get("forwarded", 0) + team.nodes["r3"].counters.get("forwarded", 0) > 0
    team.nodes["r2"].sight.alive.add("laptop")
    team.report_status()
    assert co.faults.links_down  # hysteresis: a link must stay up for heal_hold_s before plans use it
    team.clock.advance(co.config.heal_hold_s + 0.5)
    team.report_status()
    co.on_timer()
    assert not co.faults.links_down
    assert [f["kind"] for f in co.faults.faults] == ["link-down"]


def test_battery_drift_triggers_a_replan(sc):
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0, drift_min_window_s=10.0))
    team.join()
    team.run_until(2.0)
    team.report_status()
    assert team.coordinator.prediction.baselines
    team.run_until(20.0)
    team.nodes["r1"].meter._add("cpu_idle", 50.0)  # r1 burns far more than planned
    team.report_status()
    assert any("plan said" in e for e in team.coordinator.events)


def test_periodic_replan_with_uneven_batteries_moves_work_off_the_weak_robot():
    sc = load_scenario("paper-fig7")
    media = {"laptop-robot": "gsm", "robot-robot": "bluetooth"}
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0, media=media, replan_interval_s=20.0))
    team.join()
    first = dict(team.coordinator.placing.target)
    team.run_until(10.0)
    team.nodes["r2"].meter._add("cpu_idle", 40000.0)  # r2 has lost most of its battery
    team.report_status()
    team.run_until(25.0)
    team.coordinator.on_timer()
    team.pump()
    co = team.coordinator
    assert co.placing.target != first and co.ready
    # The coordinator no longer has its own 1 % threshold: it moved because the policy's hysteresis
    # (rebalance: gain > 0.1 % + 10 s, migrations paid) says the move is worth it.
    decision = co.deciding.decision
    assert decision.time_s >= 20.0 and not decision.forced and decision.moves
    kept = evaluate(sc, co.deciding.plan_network, first, energies_j=co.deciding.remaining_energies())
    assert decision.predicted_lifetime_s > kept.lifetime_s * 1.001 + 10.0
    assert any("periodic" in e for e in co.events)


def test_depleted_robot_leaves_the_plan(sc):
    team = SimTeam(sc)
    team.join()
    team.nodes["r1"].meter._add("cpu_idle", 64000.0)
    team.report_status()
    co = team.coordinator
    assert "r1" in co.departed and co.first_depletion["robot"] == "r1"
    assert "Loc-1" not in co.placing.target


def test_stuck_migration_is_abandoned_and_restarted(sc):
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0, migration_timeout_s=3.0, pins={"Loc-2": "r2"}))
    team.join()
    co = team.coordinator
    for handle in team.subscriptions["r1"]:  # r1 silently stops answering (no liveliness change)
        handle.close()
    co.on_operator(MigrateCommand(stage="Loc-2", to_node="r1"))
    team.pump()
    assert "Loc-2" in co.placing.migrations
    team.clock.advance(4.0)
    co.on_timer()
    team.pump()
    assert co.placing.aborted == 1
    assert any("abandoned" in e for e in co.events)


def test_base_station_process_survives_garbage_on_every_key(sc):
    hub = InMemoryHub()
    keys = Keys("g")
    config = BaseStationConfig(scenario=sc, team="g", coordinator=CoordinatorConfig(speed=1.0))

    def host(**kw):
        return NodeRuntime(make_component=FakeComponent, make_source=FakeSource, **kw)

    with BaseStation(config, host_factory=host, bus=hub.bus("laptop")) as base:
        attacker = hub.bus("attacker")
        rng = random.Random(1)
        garbage = [b"", b"\x00\xff", encode(SnapshotRequest()), b"\x94\xa2AP\x01\xa5frame\x80"]
        garbage += [bytes(rng.randrange(256) for _ in range(rng.randrange(1, 64))) for _ in range(20)]
        requests = []
        for key in keys.all_keys_of("laptop", basestation=True):
            for junk in garbage:
                if key == keys.operator:
                    requests.append(FakeRequest(key, junk))
                    base.events.on_request(requests[-1])
                else:
                    attacker.publish(key.replace("*", "r1"), junk)
        good = FakeRequest(keys.operator, encode(SnapshotRequest()))
        base.events.on_request(good)
        base.events.post(StopRequested("test"), bulk=True)  # after every queued message
        base.run(max_wall_s=5.0)
        assert base.stop_reason == "test"
        # every request got exactly one answer and was finalised; garbage was refused, not fatal
        assert all(len(r.replies) == 1 and r.closed for r in requests + [good])
        answers = [decode(r.replies[0], OperatorReply) for r in requests]
        assert sum(not a.ok for a in answers) >= len(garbage) - 1
        assert decode(good.replies[0], OperatorReply).ok
        published_keys = len(keys.all_keys_of("laptop", basestation=True)) - 1
        # what does not even start like a message is dropped before it is queued (`not-a-message`,
        # as at the agents); what does and fails to decode is `garbled`
        not_messages = sum(not looks_like_message(junk) for junk in garbage)
        assert base.events.rejected == published_keys * not_messages
        assert base.runtime.errors["garbled"] == published_keys * (len(garbage) - not_messages) + len(garbage) - 1
        base.snapshot()  # what an operator's `status` shows counts both
        assert base.runtime.errors["not-a-message"] == published_keys * not_messages
        assert "internal-error" not in base.runtime.errors


def test_snapshot_is_plain_data(sc):
    team = SimTeam(sc)
    team.join()
    team.run_until(2.0)
    team.report_status()
    snap = team.coordinator.snapshot()
    assert snap["ready"] and snap["placement"] == ALL_LAPTOP
    assert snap["robots"]["r1"]["status"]["battery_j"] < 64000
    reply = OperatorReply(ok=True, message="", snapshot=snap)
    assert decode(encode(reply)) == dataclasses.replace(reply)


def test_cut_base_link_replans_at_once_and_heals_with_hysteresis(sc):
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0))
    team.join()
    co = team.coordinator
    placement = dict(co.placing.placement)
    co.link_lost("laptop", "r1", detected_unix=team.clock.wall())
    co.on_timer()  # the loop's next timer decides, once for every link change of the batch
    assert co.faults.links_down == {frozenset({"laptop", "r1"})}
    assert co.deciding.plan_network.medium_between("r1", "laptop") is None
    assert co.faults.faults[-1]["kind"] == "link-down" and co.faults.faults[-1]["target"] == "laptop-r1"
    team.pump()  # the new plan reaches the robots
    team.report_status()  # ...which run it
    co.on_timer()
    assert co.faults.faults[-1]["reconfigured_unix"] is not None
    # the policy's time for the decision that handled it, apart from the rest of the handling
    assert co.faults.faults[-1]["decide_s"] > 0 and co.faults.faults[-1]["decide_s"] <= co.deciding.decide_s
    decided = co.faults.faults[-1]["decide_s"]
    co.deciding.replan("periodic, remaining energies")  # after the fault was handled: not its time
    assert co.faults.faults[-1]["decide_s"] == decided
    co.link_seen("laptop", "r1")
    co.on_timer()
    assert co.faults.links_down  # not yet: the link must stay up for heal_hold_s
    team.clock.advance(co.config.heal_hold_s + 0.1)
    co.on_timer()
    assert not co.faults.links_down and co.deciding.plan_network.medium_between("r1", "laptop") is not None
    # nothing moved either way: the relayed plan stays (the policy's hysteresis, no longer a
    # coordinator threshold, found no move worth it) and the link is simply back in the routes
    assert co.placing.placement == placement and co.placing.migrations_done == 0


def test_a_returning_robot_is_planned_from_what_it_actually_runs(sc):
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0))
    team.join()
    co = team.coordinator
    team.leave("r1")
    # while away, r1 took Loc-1 over (a subgroup agreed it); it says so in its first status
    rt = team.nodes["r1"]
    from autopower.protocol import Assign

    gen = int(team.clock.wall() * 1000) - 5  # subgroups hand out time-based generations
    rt.hosting.on_assign(Assign(stage="Loc-1", generation=gen, chain="Loc-1", run=0, resume_seq=None))
    keys = team.keys
    team.subscriptions["r1"] = [rt.bus.subscribe(k, lambda key, p, rt=rt: rt.on_message(key, p))
                                for k in (keys.node_data("r1"), keys.node_control("r1"), keys.plan)]
    team.join(["r1"])
    assert co._awaiting_actual  # no plan until it has reported
    team.report_status()
    assert co.placing.adopted >= 1
    assert co.placing.generations.last > gen  # later orders win over the generation handed out without us
    team.run_until(co.now() + 3.0)
    assert co.placing.placement["Loc-1"] == "laptop"  # and the planner moved it back, with its state
    assert co.placing.migrations_done >= 1


def test_a_robot_back_from_a_freeze_gets_a_grace_before_its_link_reports_count(sc):
    """A thawed robot's sessions reconnect: its first statuses may report links down that are not."""
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0, link_down_after_s=2.0))
    team.join()
    co = team.coordinator
    team.nodes["r1"].sight.alive.add("r3")
    team.report_status()  # r1-r3 seen up: from now on a report of it down would count at once
    co.on_liveliness("r3", False)  # frozen: its lease expired
    co.on_liveliness("r3", True)  # thawed
    team.nodes["r3"].sight.alive.discard("r1")  # its session to r1 is still reconnecting
    team.report_status()
    assert frozenset({"r1", "r3"}) not in co.faults.links_down
    team.clock.advance(2.5)  # still reported down after the grace: a real cut
    team.report_status()
    assert frozenset({"r1", "r3"}) in co.faults.links_down


def test_the_plan_is_repeated_while_a_robot_in_reach_does_not_say_it_runs_it(sc):
    """A team at rest does not get the same plan every second; a robot that comes back without it
    (restarted, back in reach, its acknowledgement lost) gets it within the repeat period, on its
    own control key: the others do not hear again a plan that grows with the team."""
    team = SimTeam(sc)
    team.join()
    team.run_until(5.0)
    co = team.coordinator
    plans = []
    listener = team.hub.bus("listener")
    for key in (team.keys.plan, *(team.keys.node_control(r) for r in ("r1", "r2", "r3"))):
        listener.subscribe(key, lambda key, payload: plans.append(key) if message_kind(payload) == "plan" else None)

    def tick(seconds: float) -> None:
        for _ in range(int(seconds * 4)):
            team.clock.advance(0.25)
            co.on_timer()
            team.pump()

    tick(2.0)  # no robot has said it runs the plan yet: it goes on being repeated
    assert len(plans) >= 1
    team.report_status()  # now every robot says it runs it
    tick(0.5)
    plans.clear()
    tick(5.0)
    # settled: no robot hears it again but in the rare repeat to everyone (`plan_republish_settled_s`)
    assert plans in ([], [team.keys.plan])
    plans.clear()
    behind = dataclasses.replace(team.nodes["r2"].status(10.0), plan_epoch=co.plans.epoch - 1)
    co.on_status(behind)  # r2 came back on an older plan
    tick(1.25)
    assert plans == [team.keys.node_control("r2")]  # repeated within the repeat period, to r2 alone
    team.report_status()
    tick(0.5)
    plans.clear()
    tick(co.config.plan_republish_settled_s)
    assert plans == [team.keys.plan]  # a listener that says nothing (a late recorder) still gets it, rarely


def test_a_command_while_no_robot_is_in_reach_is_noted_and_carried_out_when_they_are_back(sc):
    """Every robot cut from the base station: the operator's radio change is not refused (it was,
    as "re-plan failed: no change", though it then applied); it is noted, and the re-plan that
    follows the robots' return carries it out."""
    team = SimTeam(sc)
    team.join()
    co = team.coordinator
    for robot in ("r1", "r2", "r3"):
        co.on_liveliness(robot, False)
    team.pump()
    reply = co.on_operator(LinkCommand(node="r3", laptop_robot="gsm", robot_robot="bluetooth"))
    assert reply.ok and reply.message.startswith("noted; no robot is in reach of the base station"), reply.message
    reply = co.on_operator(ChainCommand(chain="Blob-2", enabled=False))
    assert reply.ok and reply.message.startswith("noted;"), reply.message
    for robot in ("r1", "r2", "r3"):
        co.on_liveliness(robot, True)
    team.report_status()
    team.run_until(co.now() + 6.0)
    assert "Blob-2" not in co.placing.target
    assert co.placing.placement["Loc-3"] == "r1" and co.deciding.plan_network.medium_between("r3", "laptop") == "gsm"


def test_a_fleets_start_publishes_a_plan_per_wave_of_ready_stages_not_one_per_stage():
    # 20 stages become ready within one batch of events: one plan carries them all (a plan per
    # stage sent 20 whole plans to every node, O(stages^2) work on each at a fleet's start)
    from autopower.simulation.synthetic import paper_fleet

    _, fleet = paper_fleet(10, topology="neighbours")
    team = SimTeam(fleet)
    published = []
    team.coordinator.bus.subscribe(team.keys.plan, lambda key, payload: published.append(decode(payload).epoch))
    team.join()
    co = team.coordinator
    assert co.mission is not None and co.ready and len(co.placing.placement) == 20
    assert co.plans.epoch <= 3 and published == list(range(1, co.plans.epoch + 1)), published
    assert all(rt.plan is not None and rt.plan.epoch == co.plans.epoch for rt in team.nodes.values())


def test_a_new_plan_goes_at_once_to_the_robots_it_concerns_and_to_the_others_once_the_wave_is_over():
    """A robot gets a new plan at once only when it changes what the robot acts on; the others get
    the newest in one change when no order waits for its answer, or `plan_catch_up_s` later: a robot's
    plans follow its own chains, not the team's moves (`PlanDelivery`). None is resent whole,
    and every robot ends on the newest plan."""
    from autopower.basestation.placing import Migration
    from autopower.simulation.synthetic import paper_fleet

    _, fleet = paper_fleet(10, topology="neighbours")
    team = SimTeam(fleet)
    team.join()
    co = team.coordinator
    team.clock.advance(co.config.plan_catch_up_s)
    team.pump()
    assert all(rt.plan.epoch == co.plans.epoch for rt in team.nodes.values())
    team.report_status()
    got: dict[str, list[str]] = {r: [] for r in co.robots}
    listener = team.hub.bus("listener")
    for robot in co.robots:
        listener.subscribe(team.keys.node_control(robot), lambda key, payload, robot=robot:
                           got[robot].append(message_kind(payload)) if message_kind(payload) in ("plan", "plan-change")
                           else None)
    # Loc-4 moves between r4 and the laptop while another order waits for its answer (a wave under way)
    moved_to = "r4" if co.placing.placement["Loc-4"] == "laptop" else "laptop"
    co.placing.placement["Loc-4"] = co.placing.target["Loc-4"] = moved_to
    co.placing.migrations["Blob-9"] = Migration(stage="Blob-9", generation=99, to_node="r9", from_node=None,
                                        phase="assigning", started_unix=team.clock.wall())
    co.plans.publish_plan()
    team.hub.pump()
    concerned = {r for r, kinds in got.items() if kinds}
    assert "r4" in concerned and len(concerned) < len(co.robots) / 2, got
    assert all(kinds == ["plan-change"] for kinds in got.values() if kinds)
    lagging = set(co.robots) - concerned
    assert co.plans.delivery.lagging == lagging, (co.plans.delivery.lagging, lagging)
    assert all(team.nodes[r].plan.epoch == co.plans.epoch - 1 for r in lagging), ({r: team.nodes[r].plan.epoch for r in lagging}, co.plans.epoch)
    # the robot that holds the older plan runs the newest as far as it concerns it: not behind
    team.report_status()
    assert co.plans.behind_plan() == []
    # the wave is over: every other robot gets the newest as one change, none of them whole
    del co.placing.migrations["Blob-9"]
    team.clock.advance(co.config.plan_catch_up_s)
    team.pump()
    assert all(got[r] == ["plan-change"] for r in lagging), got
    assert not co.plans.delivery.lagging
    assert all(rt.plan.epoch == co.plans.epoch and rt.plan.placement["Loc-4"] == moved_to for rt in team.nodes.values())


def test_stages_ready_while_orders_wait_for_answers_wait_plan_batch_s_and_share_the_next_plan(sc):
    # the simulator delivers every answer as its own event: a 30-robot fleet's start made 59 plans in
    # 10 ms, each decoded by every robot and acknowledged with a status to its peers
    team = SimTeam(sc)
    team.join()
    co = team.coordinator
    epoch = co.plans.epoch
    co.plans.mark_due()  # what `Placement.on_stage_ready` asks for: a stage became ready
    co.on_timer()  # no other order waits for an answer: the wave is complete, the plan goes at once
    assert co.plans.epoch == epoch + 1 and not co.plans.plan_due
    host = co.placing.placement["Loc-1"]
    assert co.on_operator(MigrateCommand(stage="Loc-1", to_node="r2" if host != "r2" else "r3")).ok
    assert co.placing.migrations  # its orders wait for answers (the hub is not pumped: none comes)
    epoch, sent_at = co.plans.epoch, co.plans.last_plan_unix
    co.plans.mark_due()  # another stage became ready meanwhile
    co.on_timer()
    assert co.plans.epoch == epoch and co.next_deadline_unix() == pytest.approx(sent_at + co.config.plan_batch_s)
    team.clock.set(team.clock.t + co.config.plan_batch_s / 2)
    co.on_timer()  # a second one: still the same wait
    assert co.plans.epoch == epoch
    team.clock.set(team.clock.t + co.config.plan_batch_s)
    co.on_timer()
    assert co.plans.epoch == epoch + 1 and not co.plans.plan_due  # one plan for both


def test_link_changes_within_one_batch_of_events_make_one_decision(sc):
    # a fleet under load loses several links at once; each decision is a MILP of the whole team
    # that holds up the loop, so the changes of one batch are decided together at its timer
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0))
    team.join()
    co = team.coordinator
    asked, decide = [], co.policy.decide
    co.policy.decide = lambda state: asked.append(state) or decide(state)
    for robot in ("r1", "r2", "r3"):
        co.link_lost("laptop", robot, detected_unix=team.clock.wall())
    assert asked == [] and co.next_deadline_unix() <= team.clock.wall()  # due, the loop wakes at once
    co.on_timer()
    cut = {frozenset({"laptop", r}) for r in ("r1", "r2", "r3")}
    assert len(asked) == 1 and asked[0].cut_links == cut
    assert co.faults.links_down == cut and all(co.deciding.plan_network.medium_between(r, "laptop") is None for r in ("r1", "r2", "r3"))


def test_a_snapshot_shows_each_status_as_a_round_trip_through_the_wire_would(sc):
    """The snapshot's statuses are built by the codec's field readers (`status_dict`), not by
    `dataclasses.asdict`: the same plain data (lists, not tuples), what msgpack gives back; a
    status with a number the wire refuses is shown as it is rather than failing the snapshot."""
    import math

    import msgpack

    from autopower.basestation.operating import _plain, status_dict

    team = SimTeam(sc)
    team.join()
    team.report_status()
    statuses = team.coordinator.statuses
    assert set(statuses) == {"r1", "r2", "r3"}
    snap = team.coordinator.snapshot()
    for name, st in statuses.items():
        shown = snap["robots"][name]["status"]
        assert shown == _plain(dataclasses.asdict(st))
        assert msgpack.unpackb(msgpack.packb(shown), strict_map_key=False) == shown
    odd = dataclasses.replace(statuses["r1"], cpu_utilisation=math.inf)
    assert status_dict(odd)["cpu_utilisation"] == math.inf


def _back(team, robot: str) -> None:
    """``robot``'s links to the team return (its subscriptions, as `SimTeam.leave` took them)."""
    rt, keys = team.nodes[robot], team.keys
    team.subscriptions[robot] = [rt.bus.subscribe(k, lambda key, p, rt=rt: rt.on_message(key, p))
                                 for k in (keys.node_data(robot), keys.node_control(robot), keys.plan)]


def test_a_stage_adopted_before_the_next_decision_is_neither_released_nor_restarted_meanwhile(sc):
    """Robots back from a cut report one at a time. r2 runs Blob-2, whose chain the plan in force had
    stopped (its source, r2, was away): adopted, it stays where it runs until the policy's answer.
    A reconcile in between (a timer, an order resent) released it, the policy then placed it afresh
    in a new run, and what r2 had held of the old run was obsolete (test_supervision, 1 run in 5)."""
    from autopower.protocol import Assign

    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0))
    team.join()
    co = team.coordinator
    team.run_until(3.0)
    team.leave("r2")
    team.leave("r3")
    assert "Blob-2" not in co.placing.target and "Blob-2" not in co.placing.runs.running  # its source is away: stopped
    run = co.placing.runs.runs["Blob-2"]
    # while away, r2 ran Blob-2 itself (a subgroup agreed it), in the chain's run
    gen = int(team.clock.wall() * 1000) - 5
    team.nodes["r2"].hosting.on_assign(Assign(stage="Blob-2", generation=gen, chain="Blob-2", run=run, resume_seq=None))
    for robot in ("r2", "r3"):
        _back(team, robot)
    team.join(["r2", "r3"])
    co.on_status(team.nodes["r2"].status(10.0))  # r2 reports; r3 has not yet: no decision before it does
    team.pump()
    assert co.placing.placement["Blob-2"] == "r2" and set(co._awaiting_actual) == {"r3"}
    co.placing.reconcile()
    team.pump()
    assert co.placing.placement.get("Blob-2") == "r2" and "Blob-2" in team.nodes["r2"].hosted
    co.on_status(team.nodes["r3"].status(10.0))
    team.pump()
    team.run_until(co.now() + 3.0)
    assert co.placing.runs.runs["Blob-2"] == run and co.placing.runs.running.get("Blob-2") == run  # the same run goes on
    assert not [e for e in co.events if "Blob-2 starts run" in e], co.events
