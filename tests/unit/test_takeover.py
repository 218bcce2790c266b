"""A base station that starts while the team runs: it listens, adopts, goes on; a rival steps down."""

from __future__ import annotations

import dataclasses
import os
import zlib

import pytest

from autopower.basestation.coordinator import Coordinator, CoordinatorConfig
from autopower.basestation.process import BaseStation, BaseStationConfig
from autopower.errors import AutoPowerError
from autopower.model.loading import load_scenario
from autopower.node.runtime import NodeRuntime
from autopower.node.sequencing import SinkLedger
from autopower.node.sink_store import SinkStore
from autopower.protocol import ChainCommand, LinkCommand, PeerStatus
from autopower.runtime.bus import InMemoryHub
from tests.unit.sim_team import FakeComponent, FakeSource, SimTeam

ROBOTS = ("r1", "r2", "r3")


@pytest.fixture
def sc():
    return load_scenario("paper-fig7")


def running_team(sc, t_end: float = 60.0) -> SimTeam:
    """A team whose base station ran the mission to ``t_end`` with two stages pinned to robots."""
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0, pins={"Loc-2": "r2", "Blob-3": "r3"}))
    team.join()
    team.run_until(t_end)
    team.report_status()
    return team


def new_base_station(team: SimTeam, **config) -> Coordinator:
    """A second coordinator on the same team (the first one's process is gone or cut off)."""
    co = Coordinator(scenario=team.scenario, bus=team.hub.bus("coordinator-2"), keys=team.keys,
                     config=CoordinatorConfig(**{"speed": 1.0, **config}), wall_fn=team.clock.wall)
    team.coordinator = co  # the team's inbox now reaches it
    return co


def test_a_new_base_station_adopts_the_running_team_before_deciding(sc):
    team = running_team(sc)
    old = team.coordinator
    generations = [g for r in ROBOTS for g in team.nodes[r].status(10.0).generations.values()]
    assert generations  # the robots say which instance they host
    new = new_base_station(team, speed=5.0)  # started with another speed: the team's wins
    for robot in ROBOTS:
        new.on_liveliness(robot, True)
    assert new.mission is None  # seen, not heard: nothing is decided yet
    new.learn(team.nodes["r1"].status(10.0))
    new.learn(team.nodes["r2"].status(10.0))
    assert new.mission is None  # r3 is still to be heard, and the listening time has not passed
    new.learn(team.nodes["r3"].status(10.0))

    assert new.mission == old.mission  # one mission clock: the team's
    assert new.now() == pytest.approx(old.now()) and new.now() >= 60.0
    assert new.placing.placement["Loc-2"] == "r2" and new.placing.placement["Blob-3"] == "r3"  # what runs, where it runs
    assert new.takeover.incarnation == old.takeover.incarnation + 1 and new.plans.epoch == old.plans.epoch + 1
    assert new.placing.generations.last > max(generations)
    assert new.takeover.adopted_team["from_robots"] == list(ROBOTS) and new.takeover.adopted_team["stages"] == 2
    assert new.takeover.adopted_team["previous"] == {"incarnation": old.takeover.incarnation, "epoch": old.plans.epoch, "leader": old.takeover.leader}
    # every chain goes on with its run: those whose stage ran only on the old base station (nobody
    # reports it: here it is cut off, in a real crash it is gone) on a fresh instance, from the oldest
    # input their source still holds (a new run would leave those inputs unrun): each source robot's
    # process reported its run and stayed in sight, so it holds the run's position
    assert new.placing.runs.runs == {"Loc-2": 0, "Blob-3": 0, "Loc-1": 0, "Loc-3": 0, "Blob-2": 0}
    for robot in ROBOTS:  # the policy starts from the batteries as measured, not the scenario's
        assert new.deciding.remaining_energies()[robot] == pytest.approx(team.nodes[robot].meter.battery_j)
        assert new.deciding.remaining_energies()[robot] < sc.robot(robot).energy_j
    team.pump()
    team.report_status()
    team.run_until(80.0)
    for name, rt in team.nodes.items():  # every node follows it, although its epoch may be lower
        assert (rt.plan.incarnation, rt.plan.leader) == (new.takeover.incarnation, new.takeover.leader), name
    assert new.ready
    for name, ledger in team.nodes["laptop"].sinks.items():
        assert ledger.duplicates_total == 0, name


def test_a_base_station_that_takes_over_keeps_what_the_operator_decided(sc):
    """Pins, a disabled chain, a link declared down and a radio change live in the plans the robots
    run, so a new base station keeps them (it did re-enable the chain and forget the pins); what
    names nothing of the scenario (a status is network input) is left out."""
    team = running_team(sc, t_end=30.0)
    old = team.coordinator
    assert old.on_operator(ChainCommand(chain="Blob-2", enabled=False)).ok
    assert old.on_operator(LinkCommand(node="r2", down_peer="r3")).ok
    assert old.on_operator(LinkCommand(node="r1", laptop_robot="bluetooth")).ok
    team.pump()
    team.run_until(40.0)
    team.report_status()
    statuses = {r: team.nodes[r].status(10.0) for r in ROBOTS}
    assert statuses["r1"].plan_operator == old.operating.settings()
    # the robots' copies also name things this scenario does not have
    garbled = dataclasses.replace(statuses["r1"].plan_operator, pins={**old.operating.pins, "Nope-1": "r1", "Loc-1": "mars"},
                                  disabled=("Blob-2", "Ghost"), cuts=(("r2", "r3"), ("r1", "r1"), ("r1", "x")),
                                  radios={"r1": ("bluetooth", None), "r2": ("carrier-pigeon", None)})
    statuses = {r: dataclasses.replace(s, plan_operator=garbled) for r, s in statuses.items()}
    new = new_base_station(team)
    for robot in ROBOTS:
        new.on_liveliness(robot, True)
    for robot in ROBOTS:
        new.learn(statuses[robot])
    assert new.mission == old.mission
    assert new.operating.pins == {"Loc-2": "r2", "Blob-3": "r3"} and new.operating.disabled == {"Blob-2"}
    assert new.operating.operator_cuts == {frozenset(("r2", "r3"))} and new.operating.radio_faults == {"r1": ("bluetooth", None)}
    assert any("kept the operator's settings" in n for n in new.events)
    team.pump()
    team.report_status()
    team.run_until(60.0)
    assert "Blob-2" not in new.placing.runs.running and "Blob-2" not in team.nodes["r2"].sources  # still off
    assert new.placing.placement["Loc-2"] == "r2" and new.placing.placement["Blob-3"] == "r3"  # still pinned
    # and the operator can change them as before
    assert new.on_operator(ChainCommand(chain="Blob-2", enabled=True)).ok
    team.pump()
    team.run_until(70.0)
    assert "Blob-2" in new.placing.runs.running and new.placing.runs.runs["Blob-2"] == old.placing.runs.runs["Blob-2"] + 1


def test_the_older_base_station_steps_down_when_it_hears_of_the_newer(sc):
    team = running_team(sc)
    old = team.coordinator
    new = new_base_station(team)
    for robot in ROBOTS:
        new.on_liveliness(robot, True)
        new.learn(team.nodes[robot].status(10.0))
    on_old_plan = team.nodes["r1"].status(10.0)
    new.on_rival_status(on_old_plan)  # made before our first plan reached r1: not a rival
    assert new.takeover._rival_seen is None
    new.on_rival_status(dataclasses.replace(on_old_plan, t_unix=new.mission_unix + 2.0))
    assert new.takeover._rival_seen == old.takeover.leader and new.takeover.stepped_down is None  # older: noted, it is the one to yield
    team.pump()
    new.on_rival_status(team.nodes["r1"].status(10.0))  # its own plan: nothing to say
    assert new.takeover.stepped_down is None
    old.on_rival_status(team.nodes["r1"].status(10.0))  # r1 runs the newer one's plan
    assert old.takeover.stepped_down is not None and "incarnation 1, ours 0" in old.takeover.stepped_down
    epoch = old.plans.epoch
    old.plans.publish_plan()
    assert old.plans.epoch == epoch  # it decides and publishes nothing any more
    # equal incarnations: the leader id breaks the tie, the same way on both sides
    plan = team.nodes["r1"].plan
    for rival, yields in (("~after-every-id", True), ("!before-every-id", False)):
        co = Coordinator(scenario=sc, bus=team.hub.bus(f"third{rival}"), keys=team.keys, config=CoordinatorConfig(),
                         incarnation=new.takeover.incarnation)
        co.on_rival_plan(dataclasses.replace(plan, leader=rival))
        assert (co.takeover.stepped_down is not None) is yields


def test_a_fresh_team_starts_only_after_the_robots_are_heard(sc):
    team = SimTeam(sc)
    co = team.coordinator
    for robot in ROBOTS:
        co.on_liveliness(robot, True)
    assert co.mission is None  # present, but they have not said they run nothing yet
    for robot in ROBOTS:
        co.learn(team.nodes[robot].status(0.0))
    assert co.mission is not None and co.takeover.adopted_team is None and co.takeover.incarnation == 0


def test_a_robot_that_never_speaks_delays_the_start_only_for_the_listening_time(sc):
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0, learn_team_s=2.0))
    co = team.coordinator
    for robot in ROBOTS:
        co.on_liveliness(robot, True)
    co.learn(team.nodes["r1"].status(0.0))
    co.learn(team.nodes["r2"].status(0.0))
    assert co.mission is None and co.next_deadline_unix() == pytest.approx(team.clock.wall() + 2.0)
    team.clock.advance(2.0)
    co.on_timer()
    assert co.mission is not None


def test_a_robot_that_comes_into_sight_late_is_heard_before_a_new_mission_starts(sc):
    """Random faults, seed 6: the base station crashed; r1 and r2 crashed too while it was down, and
    came back knowing no mission; r3 ran it, cut off. The restarted base station heard r1 and r2
    (no mission), and when r3 came into sight 4 s later it started a second mission at once: the
    listening time ran from the first robot seen, so r3 was never waited for."""
    team = running_team(sc, t_end=10.0)
    old = team.coordinator
    new = new_base_station(team, learn_team_s=2.0)
    for robot in ("r1", "r2"):  # restarted while the base station was down: no plan, no mission
        new.on_liveliness(robot, True)
        new.learn(dataclasses.replace(team.nodes[robot].status(10.0), mission=None, plan_epoch=-1))
    team.clock.advance(4.0)
    new.on_timer()
    assert new.mission is None  # r3 is out of sight: the robots in sight know no mission, but 1 of 3 is missing
    new.on_liveliness("r3", True)
    assert new.mission is None  # r3 is in sight and must say what it runs first
    assert new.next_deadline_unix() == pytest.approx(team.clock.wall() + 2.0)
    new.learn(team.nodes["r3"].status(10.0))
    assert new.mission == old.mission and new.takeover.adopted_team["from_robots"] == ["r3"]


def test_plans_are_ordered_by_incarnation_then_epoch(sc):
    team = running_team(sc, t_end=10.0)
    rt = team.nodes["r1"]
    current = rt.plan
    stale = dataclasses.replace(current, epoch=current.epoch + 100, running={}, incarnation=current.incarnation - 1)
    rt.on_plan(stale)
    assert rt.plan is current  # a higher epoch of an older base station is ignored
    newer = dataclasses.replace(current, epoch=1, incarnation=current.incarnation + 1, leader="next")
    rt.on_plan(newer)
    assert rt.plan is newer  # a newer base station is followed from its first plan
    status = rt.status(10.0)
    assert (status.plan_incarnation, status.plan_epoch, status.plan_leader) == (newer.incarnation, 1, "next")
    assert status.mission == current.mission


def keep_output(store: SinkStore, ledger: SinkLedger, seq: int, mission: float = 100.0) -> None:
    data = b"out%d" % seq
    assert ledger.record(0, seq, data=data)
    store.keep(mission, {"Blob-2": ledger}, "Blob-2", 0, seq, zlib.crc32(data))
    store.commit()  # the status acknowledging it goes out


def test_outputs_not_yet_acknowledged_are_not_kept(tmp_path):
    """An output noted after the last status dies with the process, as does its recording: the
    producers still hold it in custody and resend it, and the new sink must take it as new."""
    store, ledger = SinkStore(tmp_path / "sinks.json"), SinkLedger()
    keep_output(store, ledger, 0)
    keep_output(store, ledger, 1)
    assert ledger.record(0, 2, data=b"out2")
    store.keep(100.0, {"Blob-2": ledger}, "Blob-2", 0, 2, zlib.crc32(b"out2"))  # no status since: killed now
    restarted = SinkStore(tmp_path / "sinks.json").load(100.0)["Blob-2"]
    assert restarted.contiguous == 2
    assert restarted.record(0, 2, data=b"out2", attempt=1)  # the resend is delivered (and recorded) once


@pytest.mark.parametrize("compact_bytes", [1 << 20, 200])  # appended lines; snapshots every few outputs
def test_a_sink_goes_on_from_its_kept_ledgers(tmp_path, compact_bytes):
    store = SinkStore(tmp_path / "sinks.json", compact_bytes=compact_bytes)
    full, first = SinkLedger(), SinkLedger()
    for seq in (0, 1, 2, 4, 5):  # 3 is still on its way
        full.record(0, seq, data=b"out%d" % seq)
        keep_output(store, first, seq)
    assert SinkStore(tmp_path / "sinks.json").load(200.0) == {}  # another mission's sinks start empty
    restarted = SinkStore(tmp_path / "sinks.json").load(100.0)["Blob-2"]
    assert (restarted.contiguous, restarted.max_seq, restarted.received_total) == (3, 5, 5)
    assert not restarted.record(0, 4, data=b"out4", attempt=1)  # resent to the new sink: not delivered again
    assert restarted.redundant_total == 1 and restarted.duplicates_total == 0
    again = SinkStore(tmp_path / "sinks.json")
    for seq in (3, 6):
        full.record(0, seq, data=b"out%d" % seq)
        keep_output(again, restarted, seq)
    assert (restarted.contiguous, restarted.digest) == (full.contiguous, full.digest)  # as if never restarted
    third = SinkStore(tmp_path / "sinks.json").load(100.0)["Blob-2"]
    assert (third.contiguous, third.digest, third.received_total) == (full.contiguous, full.digest, 7)


def test_a_torn_or_damaged_sink_state_is_survived(tmp_path):
    path = tmp_path / "sinks.json"
    store, ledger = SinkStore(path), SinkLedger()
    for seq in range(4):
        keep_output(store, ledger, seq)
    with open(path, "ab") as f:
        f.write(b'["Blob-2",0,4')  # killed in the middle of a line
    assert SinkStore(path).load(100.0)["Blob-2"].contiguous == 4
    path.write_text('{"mission_epoch_unix": 100.0}\n{"sinks": {"Blob-2": {"run": "x"}}}\n')
    assert SinkStore(path).load(100.0) == {}  # not a sink state: reported, the sink starts empty
    path.write_bytes(b"\xff\x00")
    assert SinkStore(path).load(100.0) == {}


def test_one_base_station_per_team_and_host(sc, tmp_path):
    hub = InMemoryHub(synchronous=True)

    def host(**kw):
        return NodeRuntime(make_component=FakeComponent, make_source=FakeSource, **kw)

    config = BaseStationConfig(scenario=sc, team="t", state_dir=tmp_path)
    with BaseStation(config, host_factory=host, bus=hub.bus("laptop")):
        with pytest.raises(AutoPowerError, match="another base station of team 't' runs on this host"):
            with BaseStation(config, host_factory=host, bus=hub.bus("laptop-2")):
                pass
    (tmp_path / "basestation.json").write_text('{"incarnation": 6}')
    with BaseStation(config, host_factory=host, bus=hub.bus("laptop-3")) as base:  # the lock went with it
        assert base.coordinator.takeover.incarnation == 7  # above what this host used last
        base.run(max_wall_s=0.05)
    assert (tmp_path / "basestation.json").exists()  # kept for the next start (a service manager's)


def test_a_launched_base_station_that_stops_cleanly_leaves_no_state(sc, tmp_path):
    hub, state = InMemoryHub(synchronous=True), tmp_path / "team"
    state.mkdir()
    config = BaseStationConfig(scenario=sc, team="t", state_dir=state, parent_pid=os.getppid())

    def host(**kw):
        return NodeRuntime(make_component=FakeComponent, make_source=FakeSource, **kw)

    with BaseStation(config, host_factory=host, bus=hub.bus("laptop")) as base:
        (state / "sinks.json").write_text("{}")
        assert base.run(max_wall_s=0.05) == "time limit"
    assert not state.exists()  # its launcher (`up`) owned the team: nothing is left for a restart


def test_a_takeover_that_did_not_hear_a_chains_source_robot_waits_for_its_run(sc):
    """Found by a random-fault run against `up`: a base station restarted while r3 was still cut
    off adopted Loc-3 running on r1 without knowing Loc-3's run (only its source, r3, reports it)
    and raised KeyError on every later decision, so the team was never reconfigured again. Now the
    chain is not declared running, none of its stages is assigned afresh, and the run r3 reports
    when it speaks is the one the plan goes on with."""
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0, pins={"Loc-3": "r1"}))
    team.join()
    team.run_until(60.0)
    team.report_status()
    r3_run = team.nodes["r3"].status(10.0).sources["Loc-3"].run
    new = new_base_station(team, learn_team_s=2.0)
    for robot in ("r1", "r2"):  # r3 is still cut off from the new base station
        new.on_liveliness(robot, True)
        new.learn(team.nodes[robot].status(10.0))
    assert new.mission is None
    team.clock.advance(3.0)  # listened long enough
    new.learn(team.nodes["r1"].status(10.0))
    assert new.mission is not None and new.takeover.adopted_team["stages"] >= 1  # Loc-3 on r1 among them
    assert new.placing.runs.runs_unknown == {"Loc-3", "Blob-3"}  # r3's chains: only r3 knows their runs
    assert "Loc-3" not in new.placing.runs.running and "Blob-3" not in new.placing.runs.running
    new.on_timer()  # deciding and reconciling no longer fail on the unknown run
    assert not any(m for s, m in new.placing.migrations.items() if new.chain_of[s].name == "Loc-3" and m.phase == "assigning")
    new.on_liveliness("r3", True)
    new.on_status(team.nodes["r3"].status(10.0))
    # learned: a run made up here would have been 0, r3's own, and its restart could not be told apart
    assert not new.placing.runs.runs_unknown and new.placing.runs.runs["Loc-3"] >= r3_run
    team.pump()
    team.report_status()
    team.run_until(team.clock.t + 20.0)
    team.report_status()
    run = new.placing.runs.running["Loc-3"]
    # its host was released: the chain goes on in the run r3's process said it holds, on a fresh instance
    assert run == r3_run
    assert team.nodes["r3"].status(10.0).sources["Loc-3"].run == run  # r3's source follows the plan
    assert team.nodes["r3"].sinks["Loc-3"].run == run and team.nodes["r3"].sinks["Loc-3"].received > 0
    assert not any(rt.errors.get("internal-error") for rt in team.nodes.values())


def test_orders_go_above_a_generation_a_robot_started_without_the_base_station():
    """A robot restarted alone (or a subgroup round) restarts a stage on the host the plan already
    names, with a time-based generation far above the base station's counter. The base station
    jumped past such generations only for a stage adopted from a new host, so its next order for
    the stage was lower: the robot ignored it as stale and the stage could never move again."""
    from autopower.protocol import Assign, MigrateCommand

    sc = load_scenario("paper-fig7")
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0, pins={"Loc-2": "r2"}, auto_replan=False))
    team.join()
    team.run_until(10.0)
    co, r2 = team.coordinator, team.nodes["r2"]
    assert co.placing.placement["Loc-2"] == "r2"
    restarted = int(team.clock.wall() * 1000)  # what `AgentProcess._resume_alone` hands out (wall ms)
    r2.hosting.on_assign(Assign(stage="Loc-2", generation=restarted, chain="Loc-2", run=r2.plan.running["Loc-2"],
                        resume_seq=None))
    team.report_status()
    assert co.placing.generations.last >= restarted
    reply = co.on_operator(MigrateCommand(stage="Loc-2", to_node="laptop"))
    assert reply.ok, reply.message
    team.pump()
    team.run_until(20.0)
    assert co.placing.placement["Loc-2"] == "laptop" and "Loc-2" in team.nodes["laptop"].hosted
    assert team.nodes["laptop"].hosted["Loc-2"].generation > restarted
    assert r2.counters.get("stale-order", 0) == 0


def test_a_robot_names_its_mission_only_to_a_base_station_that_does_not_run_its_plan(sc):
    """The mission (its starting energies grow with the team) is in a robot's status while the
    base station's last status runs another plan, a restarted one says nothing (it sends no status
    before it runs a mission) or its token changed; not while the base station runs the robot's plan."""
    team = running_team(sc)
    r1, base = team.nodes["r1"], team.nodes["laptop"]
    assert r1.status(10.0).mission is not None  # nothing heard from the base station yet
    view = PeerStatus.of(base.status(10.0))
    assert view.plan_epoch == r1.plan.epoch
    r1.on_peer_status(view)
    assert r1.status(10.0).mission is None  # it runs our plan: no need to say which mission
    r1.on_peer_status(dataclasses.replace(view, plan_epoch=-1))  # a base station without a mission
    assert r1.status(10.0).mission == r1.mission
    r1.on_peer_status(view)
    r1.on_liveliness("laptop", False)  # its process is gone: the next one will need it
    assert r1.status(10.0).mission == r1.mission
    r1.on_peer_status(view)
    team.clock.advance(3 * max(view.next_status_s, 0.5) + 0.1)  # silent for three announced periods
    assert r1.status(10.0).mission == r1.mission
