"""The recording bus tap: a whole in-memory team recorded per process, merged, replayed."""

from __future__ import annotations

import os
from types import SimpleNamespace

import pytest

from autopower.basestation.coordinator import CoordinatorConfig
from autopower.model.loading import load_scenario
from autopower.protocol import Keys, MigrateCommand, encode
from autopower.recording.merge import merge_run
from autopower.recording.recorder import (
    EVENT_TAG,
    Recorder,
    output_path,
    parse_event,
    record_fault,
    run_recording_id,
    tag_event,
)
from autopower.recording.replay import load, summarize
from autopower.recording.telemetry import Telemetry, read_recording
from autopower.runtime.bus import InMemoryBus, InMemoryHub
from tests.unit import sim_team
from tests.unit.sim_team import SimTeam

os.environ.setdefault("RERUN_ANALYTICS", "0")
FC = {"laptop-robot": "802.11a", "robot-robot": "802.11a"}


def test_tagged_events_round_trip():
    line = tag_event("Loc-1 runs on r2", type="stage-ready", stage="Loc-1", downtime_ms=3.5)
    assert EVENT_TAG in line
    text, payload = parse_event(line)
    assert text == "Loc-1 runs on r2" and payload == {"type": "stage-ready", "stage": "Loc-1", "downtime_ms": 3.5}
    assert parse_event("plain text") == ("plain text", None)
    assert parse_event(f"broken{EVENT_TAG}{{not json") == (f"broken{EVENT_TAG}{{not json", None)
    assert parse_event(None) == ("", None)


def test_recording_id_comes_from_the_run_directory(tmp_path):
    a, b = tmp_path / "x" / "run-1", tmp_path / "y" / "run-1"
    assert run_recording_id(a) == run_recording_id(b) != run_recording_id(tmp_path / "run-2")


class _TappedHub(InMemoryHub):
    """Every bus of the SimTeam goes through a Recorder writing <run_dir>/<node>.rrd."""

    run_dir = None
    scenario = None
    clock_holder: list = []
    recorders: dict = {}

    def bus(self, name: str = ""):
        rec = Recorder.open(self.run_dir, name, scenario=self.scenario, clock=lambda: self.clock_holder[0].t)
        self.recorders[name] = rec
        return rec.tap(InMemoryBus(self, name))


@pytest.fixture
def recorded_team(tmp_path, monkeypatch):
    sc = load_scenario("paper-fig7")
    run_dir = tmp_path / "run-42"
    holder: list = []
    hub_cls = type("Hub", (_TappedHub,), {"run_dir": run_dir, "scenario": sc, "clock_holder": holder,
                                          "recorders": {}})
    monkeypatch.setattr(sim_team, "InMemoryHub", hub_cls)
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0, media=FC, auto_replan=False))
    holder.append(team.clock)
    return team, hub_cls.recorders, run_dir


def _publish_status(team: SimTeam) -> None:
    keys = team.keys
    for name, rt in team.nodes.items():
        if rt.started:
            rt.bus.publish(keys.status(name), encode(rt.status(5.0)), reliable=False)
    team.pump()


def test_a_recorded_team_replays_with_migrations_outputs_and_energy(recorded_team):
    team, recorders, run_dir = recorded_team
    for name, rt in team.nodes.items():
        recorders[name].attach(rt)
    team.join()
    for t in range(1, 31):
        team.run_until(float(t))
        if t == 10:
            reply = team.coordinator.on_operator(MigrateCommand(stage="Loc-1", to_node="r2"))
            assert reply.ok, reply.message
        if t % 2 == 0:
            _publish_status(team)
    for rec in recorders.values():
        rec.close()
    files = sorted(p.name for p in run_dir.glob("*.rrd"))
    assert "r1.rrd" in files and "coordinator.rrd" in files
    merged = merge_run(run_dir)
    assert merged.name == "run.rrd"

    rec = load(merged)
    ids = {read_recording(run_dir / f).properties["recording_id"] for f in files}
    assert ids == {run_recording_id(run_dir)} == {rec.properties["recording_id"]}
    s = summarize(rec, merged)
    assert s["kind"] == "live" and s["scenario"] == "paper-fig7"
    assert set(s["robots"]) == {"r1", "r2", "r3"}
    assert 25 <= s["mission"]["end_s"] <= 30.0
    assert all(v["used_j"] > 0 for v in s["robots"].values())
    assert s["decisions"] >= 2  # the first plan and the move
    moved = [m for m in s["migrations"]["list"] if m["stage"] == "Loc-1"]
    assert moved and moved[-1]["to"] == "r2" and moved[-1]["downtime_ms"] is not None
    assert s["outputs"]["recorded"] and s["lost_outputs"] == 0 and s["duplicated_outputs"] == 0
    assert set(s["outputs"]["chains"]) == {c.name for c in team.scenario.chains}
    assert all(c["outputs"] >= 10 for c in s["outputs"]["chains"].values())  # Loc every 2 s, Blob 4 Hz
    assert s["energy_model_error_pct"] is not None and abs(s["energy_model_error_pct"]) < 1
    # the move's state crossed the radios: metered apart from the model's steady state, and reported
    over = s["energy"]["overhead_j"]
    assert over["migration"] > 0 and over["recovery"] == 0
    assert sum(v["overhead_j"]["migration"] for v in s["energy"]["per_robot"].values()) == pytest.approx(
        over["migration"])
    assert s["policy"] == "rebalance"  # the base station's plans say what decided them
    assert s["ok"], s["invariants"]
    assert "robots/r1/model_w" in rec.scalars and "team/allocation" in rec.graphs


def test_a_superseded_output_counts_apart_only_with_a_later_one_delivered_or_in_hand(tmp_path):
    """A latest-only chain's result a newer one replaced in a robot's hold is not lost if the newer
    one did its job: some later output of the run reached the sink, or a node had one in hand at
    its stop. Named superseded past every such output, it is lost: the label alone proves nothing."""
    from autopower.recording.recorder import in_flight_path, produced_path, superseded_path

    t = [0.0]
    rec = Recorder(Telemetry(tmp_path / "x.rrd", kind="live", properties={"scenario": "paper-fig7"}), "laptop",
                   clock=lambda: t[0])
    rec.telemetry.battery(0.0, "r1", 100.0)
    rec.telemetry.battery(1.0, "r1", 90.0)
    for seq in (0, 1, 5):
        rec.on_output("Blob-2", 0, seq, b"")
    tel = rec.telemetry
    tel.scalar(produced_path("Blob-2", 0), 1.0, 10)
    for seq in (2, 3, 4, 7, 9):  # 2-4: superseded by 5 (delivered); 7: by 8 (in hand); 9: by nothing
        tel.scalar(superseded_path("Blob-2", 0), 1.0, seq)
    tel.scalar(in_flight_path("Blob-2", 0), 1.0, 8)
    rec.close()
    s = summarize(load(tmp_path / "x.rrd"))
    run = s["outputs"]["chains"]["Blob-2"]["by_run"]["0"]
    assert (run["delivered"], run["superseded"], run["in_flight"], run["lost"]) == (3, 4, 1, 2)  # lost: 6 and 9
    assert s["outputs"]["superseded"] == 4 and s["lost_outputs"] == 2
    assert s["outputs"]["chains"]["Blob-2"]["lost_seqs"] == [[0, 6], [0, 9]]
    from autopower.recording.report import render_text
    assert "4 of latest-only chains" in render_text(s)


def test_lost_and_duplicated_outputs_are_counted(tmp_path):
    t = [0.0]
    rec = Recorder(Telemetry(tmp_path / "x.rrd", kind="live", properties={"scenario": "paper-fig7"}), "laptop",
                   clock=lambda: t[0])
    rec.telemetry.battery(0.0, "r1", 100.0)
    rec.telemetry.battery(1.0, "r1", 90.0)
    for seq in (0, 1, 1, 3, 4, 4, 4):  # 2 lost, 3 duplicates
        t[0] += 0.1
        rec.on_output("Blob-2", 0, seq, b"")
    rec.on_output("Blob-2", 1, 0, b"")  # a new run starts over at 0
    rec.close()
    s = summarize(load(tmp_path / "x.rrd"))
    blob = s["outputs"]["chains"]["Blob-2"]
    assert {k: v for k, v in blob.items() if k != "by_run"} == {
        "outputs": 8, "distinct": 5, "produced": 6, "produced_known": False, "lost": 1, "duplicated": 3,
        "held_dropped": 0, "superseded": 0, "died_with_process": 0, "unrecorded": 0, "in_flight": 0, "abandoned": 0,
        "runs": [0, 1], "lost_seqs": [[0, 2]]}  # which one: to look up in the recording
    assert s["lost_outputs"] == 1 and s["duplicated_outputs"] == 3
    inv = {i["name"]: i["ok"] for i in s["invariants"]}
    assert inv["every output exactly once at its sink"] is False and not s["ok"]
    assert output_path("Blob-2", 1) in load(tmp_path / "x.rrd").scalars


def test_every_produced_output_is_in_one_class_tails_included(tmp_path):
    """Issue 30: a sink counted gaps only below the highest seq it got, so a run's tail (and a whole
    old run's after its chain restarted) was counted nowhere. With what the source produced per
    run and what each node had in hand at its stop, every produced output is in exactly one class."""
    from autopower.recording.recorder import died_with_process_path, held_dropped_path, in_flight_path, produced_path

    t = [0.0]
    rec = Recorder(Telemetry(tmp_path / "x.rrd", kind="live", properties={"scenario": "paper-fig7"}), "laptop",
                   clock=lambda: t[0])
    rec.telemetry.battery(0.0, "r1", 100.0)
    rec.telemetry.battery(1.0, "r1", 90.0)
    for seq in (0, 1, 3):  # run 0: 2 missing below the last delivered
        rec.on_output("Loc-1", 0, seq, b"")
    for seq in (0, 1, 2, 3):  # run 1: delivered 0-3 of 9
        rec.on_output("Loc-1", 1, seq, b"")
    tel = rec.telemetry
    tel.scalar(produced_path("Loc-1", 0), 1.0, 6)  # run 0 produced 0-5: 4 and 5 after the last delivered
    tel.scalar(produced_path("Loc-1", 1), 1.0, 9)
    tel.scalar(held_dropped_path("Loc-1", 1), 1.0, 4)  # a full hold let 4 go
    for seq in (5, 6):  # a node had 5 and 6 in hand at its stop
        tel.scalar(in_flight_path("Loc-1", 1), 1.0, seq)
    tel.scalar(died_with_process_path("Loc-1", 1), 1.0, 6)  # a restarted robot's window named 6: it did not die
    rec.close()
    s = summarize(load(tmp_path / "x.rrd"))
    loc = s["outputs"]["chains"]["Loc-1"]
    assert loc["by_run"]["0"] == {"produced": 6, "produced_known": True, "delivered": 3, "duplicated": 0,
                                  "unrecorded": 0, "held_dropped": 0, "superseded": 0, "died_with_process": 0,
                                  "in_flight": 0, "abandoned": 2, "lost": 1}  # 2: a gap; 4, 5: the tail of a run that ended
    assert loc["by_run"]["1"] == {"produced": 9, "produced_known": True, "delivered": 4, "duplicated": 0,
                                  "unrecorded": 0, "held_dropped": 1, "superseded": 0, "died_with_process": 0,
                                  "in_flight": 2, "abandoned": 0, "lost": 2}  # 7, 8: the last run's tail, in no node's hands
    for run in loc["by_run"].values():
        assert run["produced"] == sum(run[k] for k in ("delivered", "unrecorded", "held_dropped", "superseded",
                                                        "died_with_process", "in_flight", "abandoned", "lost"))
    assert loc["lost_seqs"] == [[0, 2], [1, 7], [1, 8]]
    assert s["lost_outputs"] == 3 and s["outputs"]["in_flight"] == 2 and s["outputs"]["abandoned"] == 2
    assert s["outputs"]["produced"] == 15
    detail = {i["name"]: i["detail"] for i in s["invariants"]}["every output exactly once at its sink"]
    assert "2 still in flight when the team stopped" in detail and "2 abandoned when their chain restarted" in detail


def test_faults_detection_and_reconfiguration(tmp_path):
    """Injected by a fault tool, detected by liveliness, replanned, stage moved: times derived."""
    hub = InMemoryHub()
    t = [0.0]
    rec = Recorder(Telemetry(tmp_path / "laptop.rrd", kind="live", properties={"scenario": "paper-fig7"}),
                   "laptop", clock=lambda: t[0])
    watcher = rec.tap(hub.bus("laptop"))
    seen = []
    watcher.watch_liveliness(Keys("t").alive_all, lambda k, alive: seen.append((k, alive)))
    r1 = hub.bus("r1")
    token = r1.declare_token(Keys("t").alive("r1"))
    rec.telemetry.battery(0.0, "r2", 10.0)
    t[0] = 100.0
    record_fault(rec.telemetry, 100.0, kind="cut", target="r1-laptop")
    t[0] = 100.8
    token.close()  # liveliness lost: detected
    rec.telemetry.decision(101.0, tag_event("plan epoch 2", type="plan", epoch=2, placement={}))
    rec.telemetry.migration(101.3, tag_event("Loc-1 runs on r2", type="stage-ready", stage="Loc-1", node="r2",
                                             generation=2, imported_state=True, downtime_ms=120.0))
    rec.telemetry.battery(102.0, "r2", 9.0)
    t[0] = 150.0
    r1.declare_token(Keys("t").alive("r1"))  # back
    watcher.close()
    assert seen[-1] == (Keys("t").alive("r1"), True)  # the process's own callback still runs
    s = summarize(load(tmp_path / "laptop.rrd"))
    [fault] = s["faults"]
    assert fault["kind"] == "cut" and fault["target"] == "r1-laptop"
    assert fault["detected_mission_s"] == pytest.approx(0.8) and fault["reconfigured_mission_s"] == pytest.approx(1.3)
    assert s["migrations"]["count"] == 1 and s["migrations"]["downtime_ms_max"] == 120.0


def test_recording_never_breaks_the_bus(tmp_path):
    hub = InMemoryHub()
    rec = Recorder(Telemetry(tmp_path / "r1.rrd", kind="live"), "r1")
    bus = rec.tap(hub.bus("r1"))
    got = []
    other = hub.bus("laptop")
    other.subscribe("autopower/t/status/*", lambda k, p: got.append(p))
    bus.publish("autopower/t/status/r1", b"garbage", reliable=False)  # undecodable: counted, delivered
    bus.publish("autopower/t/base/plan", b"\x00\x01")
    assert got == [b"garbage"] and rec.errors == 2
    rec.telemetry.stream = None  # the sink is gone: still no exception
    rec.on_output("Loc-1", 0, 0, b"x")
    bus.close()
    bus.publish("autopower/t/status/r1", b"after close")  # closed inner bus drops it; recorder ignores it


def test_outputs_are_drawn_with_the_deploy_visualiser(tmp_path):
    import rerun as rr

    from autopower.chains import make_component, make_source
    from autopower.recording.live import draw_output, open_recorder

    blob = make_component("Blob", "r2", 0).run(make_source("Blob", "r2", 0).produce(0))
    loc = make_component("Loc", "r1", 0).run(make_source("Loc", "r1", 0).produce(0))
    assert [w for w, _ in draw_output(rr, "Blob-2", blob)] == ["blobs"]
    assert [w for w, _ in draw_output(rr, "Loc-1", loc)] == ["particles", "pose"]
    assert draw_output(rr, "X", b"not msgpack") == []
    rec = open_recorder(tmp_path / "run-1", "laptop", clock=lambda: 1.0, visual_every_s=0.0)
    rec.on_output("Blob-2", 0, 0, blob)
    rec.on_output("Loc-1", 0, 0, loc)
    rec.close()
    assert rec.errors == 0 and rec.telemetry.errors == 0
    assert (tmp_path / "run-1" / "laptop.rrd").stat().st_size > 0


def test_a_fault_tool_writes_its_own_file_of_the_run(tmp_path):
    from autopower.recording.recorder import record_fault_event

    run_dir = tmp_path / "run-7"
    t = [0.0]
    rec = Recorder.open(run_dir, "laptop", clock=lambda: t[0])
    rec.telemetry.battery(0.0, "r1", 50.0)
    t[0] = 100.4
    rec.on_liveliness("autopower/t/alive/r1", False)
    rec.telemetry.decision(100.6, tag_event("plan epoch 5", type="plan", epoch=5, placement={}))
    rec.telemetry.battery(110.0, "r1", 40.0)
    rec.close()
    # the tool knows the mission clock from the coordinator's snapshot: t = (wall - epoch) * speed
    path = record_fault_event(run_dir, kind="cut", target="r1-laptop", mission={"epoch_unix": 1000.0, "speed": 10.0},
                              wall_unix=1010.0)
    assert path.parent == run_dir and path.name.startswith("fault-")
    with pytest.raises(Exception, match="needs t_s or the mission"):
        record_fault_event(run_dir, kind="kill", target="r2")
    s = summarize(load(merge_run(run_dir)))
    [fault] = s["faults"]
    assert (fault["kind"], fault["target"], fault["at_mission_s"]) == ("cut", "r1-laptop", 100.0)
    assert fault["detected_mission_s"] == pytest.approx(0.4) and fault["reconfigured_mission_s"] == pytest.approx(0.6)


def test_results_dropped_by_a_robot_cut_off_from_their_sink_are_named_with_the_lost_ones(tmp_path):
    """A robot that holds results for a sink out of its reach keeps 512 and drops the oldest
    (`held-outputs-dropped`): the replay says how many of the lost outputs went so, over the
    robot's restarts too (a restarted process counts from 0 again on the same entity)."""
    from autopower.recording.report import render_text

    t = [0.0]
    rec = Recorder(Telemetry(tmp_path / "x.rrd", kind="live", properties={"scenario": "paper-fig7"}), "laptop",
                   clock=lambda: t[0])
    rec.telemetry.battery(0.0, "r2", 100.0)
    rec.telemetry.battery(1.0, "r2", 90.0)
    for seq in (*range(0, 5), *range(605, 610)):  # 600 results never reached the sink
        t[0] += 0.1
        rec.on_output("Blob-2", 0, seq, b"")
    rec._status({"node": "r2", "t_virtual": 1.0, "counters": {"held-outputs-dropped": 300}})
    rec._status({"node": "r2", "t_virtual": 2.0, "counters": {"held-outputs-dropped": 570}})
    rec._status({"node": "r2", "t_virtual": 3.0, "counters": {"held-outputs-dropped": 30}})  # restarted
    rec.close()
    s = summarize(load(tmp_path / "x.rrd"), tmp_path / "x.rrd")
    assert s["outputs"]["lost"] == 600 and s["outputs"]["held_dropped"] == 600
    detail = next(i["detail"] for i in s["invariants"] if i["name"] == "every output exactly once at its sink")
    assert "600 dropped by robots cut off from their sink" in detail
    assert "600 dropped by robots cut off from their sink too long (beyond their hold budget" in render_text(s)


def test_the_replay_tells_results_a_full_hold_dropped_from_lost_ones(tmp_path):
    """A robot's recorder logs each result its full hold lets go (`NodeRuntime.on_held_dropped`).
    The replay then counts as lost only the missing seqs no hold dropped: random faults lost
    outputs beside thousands dropped by design, and one count could not tell them apart."""
    from autopower.recording.report import render_text

    t = [0.0]
    run_dir = tmp_path / "run-3"
    sink = Recorder.open(run_dir, "laptop", clock=lambda: t[0])
    robot = Recorder.open(run_dir, "r2", clock=lambda: t[0])
    listeners = []
    robot.attach(SimpleNamespace(listen=listeners.append))
    runtime = listeners[0]  # what the runtime tells the recorder (`SinkListener`)
    sink.telemetry.battery(0.0, "r2", 100.0)
    sink.telemetry.battery(1.0, "r2", 90.0)
    for seq in (*range(0, 5), *range(605, 610)):
        t[0] += 0.1
        sink.on_output("Blob-2", 0, seq, b"")
    # 602-604 were not dropped: lost; 700 is past the last delivered; 606 reached the sink (a
    # restarted robot logs every result of its journal it does not take back, acknowledged or not)
    for seq in (*range(5, 602), 700, 606):
        runtime.held_dropped("Blob-2", 0, seq, "budget")
    sink.close()
    robot.close()
    s = summarize(load(merge_run(run_dir)))
    o = s["outputs"]
    assert (o["lost"], o["held_dropped"], o["held_dropped_known"]) == (3, 598, True)
    assert (o["chains"]["Blob-2"]["lost"], o["chains"]["Blob-2"]["held_dropped"]) == (3, 597)
    inv = next(i for i in s["invariants"] if i["name"] == "every output exactly once at its sink")
    assert inv["ok"] is False and inv["detail"].startswith("3 lost, 0 duplicated over 10 outputs (besides 598 dropped")
    assert "3 lost" in render_text(s) and "598 more dropped by robots" in render_text(s)


def test_outputs_of_a_runtime_that_started_without_a_plan_on_the_bus_get_its_mission_time(tmp_path):
    """A robot restarted out of the base station's reach goes on with its saved plan: no plan
    crosses its bus, so its recorder knew no mission and logged every output at t = 0 (random
    faults, seed 3: the Loc outputs of three restarted robots, all at the mission's start)."""
    from autopower.runtime.clock import ManualClock

    run_dir = tmp_path / "run-4"
    robot = Recorder.open(run_dir, "r1")
    runtime = SimpleNamespace(listen=lambda listener: None, clock=None)
    robot.attach(runtime)
    robot.telemetry.battery(0.0, "r1", 100.0)
    robot.on_output("Loc-1", 0, 0, b"")  # before the runtime has a clock: 0, as before
    runtime.clock = ManualClock(t=478.5)
    robot.on_output("Loc-1", 0, 1, b"")
    robot.telemetry.battery(480.0, "r1", 90.0)
    robot.close()
    times, values = load(merge_run(run_dir)).scalars["components/Loc-1/run/0/seq"]
    assert sorted(zip(values, times, strict=False)) == [(0.0, 0.0), (1.0, 478.5)]


def test_a_plan_change_heard_back_before_its_publication_is_recorded_as_its_decision(tmp_path):
    """A base station hears its own plans back (it subscribes to the plan key); Zenoh's loopback may
    hand the recorder a change before the publish tap does. Each stream is assembled on its own."""
    from autopower.protocol import LinkInfo, MissionInfo, PlanUpdate
    from autopower.protocol.plans import plan_change, published_digest, sorted_plan
    from autopower.recording.replay import DECISIONS, _events

    keys = Keys("t")
    mission = MissionInfo(scenario="paper-fig7", accounting="paper", epoch_unix=1e9, speed=1.0,
                          energies_j={"r1": 100.0})
    links = (LinkInfo(a="laptop", b="r1", medium="802.11a"),)
    plans = [sorted_plan(PlanUpdate(epoch=epoch, mission=mission, placement={"Loc-1": host}, running={"Loc-1": 0},
                                    links=links, predicted_w={"r1": 1.0}, predicted_lifetime_s=None,
                                    plan_t_virtual=0.0, leader="laptop:1")) for epoch, host in ((1, "laptop"), (2, "r1"))]
    (first, d1), (second, d2) = (published_digest(encode(p)) for p in plans)
    change = encode(plan_change(first, d1, second, d2))
    rec = Recorder(Telemetry(tmp_path / "b.rrd", kind="live", properties={"scenario": "paper-fig7"}), "laptop",
                   clock=lambda: 1.0)
    rec.telemetry.battery(0.0, "r1", 100.0)  # a recording the reader takes: one battery sample
    rec.on_publish(keys.plan, encode(first))
    rec.on_receive(keys.plan, encode(first))
    rec.on_receive(keys.plan, change)  # the loopback first
    rec.on_publish(keys.plan, change)
    rec.close()
    decided = [p["epoch"] for _, _, p in _events(load(tmp_path / "b.rrd"), DECISIONS) if p and p.get("type") == "plan"]
    assert decided == [1, 2] and rec.errors == 0


def test_a_fault_of_several_parts_is_reconfigured_by_the_round_committed_before_its_last_part_was_seen(tmp_path):
    """Testbed demo in CI, 2026-11-30: every robot cut from the base station at once (three links).
    r1 and r2 saw it at once, their subgroup round committed at 1.22 s; the base station saw the
    third link only at 1.52 s on a loaded machine, and the base station's later plan was credited.
    The fault is detected when its last part is seen, but reconfigured by the first reaction after
    its first part was."""
    tel = Telemetry(tmp_path / "laptop.rrd", kind="live", properties={"scenario": "paper-fig7",
                                                                     "basestation": "laptop"})
    tel.battery(0.0, "r1", 10.0)
    for robot in ("r1", "r2", "r3"):
        record_fault(tel, 100.0, kind="cut", target=f"{robot}-laptop")
    record_fault(tel, 100.3, kind="node-lost", target="laptop", phase="detected", observer="r1")
    record_fault(tel, 100.35, kind="node-lost", target="laptop", phase="detected", observer="r2")
    record_fault(tel, 100.4, kind="node-lost", target="r1", phase="detected", observer="laptop")
    record_fault(tel, 100.4, kind="node-lost", target="r2", phase="detected", observer="laptop")
    tel.decision(100.9, tag_event("round 7 proposed", type="sg-propose", round_id="r1-7",
                                  moves=[{"stage": "Loc-1", "to": "r2"}]))
    tel.decision(101.22, tag_event("round 7 committed", type="sg-decision", round_id="r1-7", commit=True))
    record_fault(tel, 101.52, kind="node-lost", target="r3", phase="detected", observer="laptop")
    tel.decision(104.29, tag_event("plan epoch 7", type="plan", epoch=7, placement={}))
    tel.battery(106.0, "r1", 9.0)
    tel.close()
    [fault] = summarize(load(tmp_path / "laptop.rrd"))["faults"]
    assert fault["parts"] == ["r1-laptop", "r2-laptop", "r3-laptop"]
    assert fault["detected_mission_s"] == pytest.approx(1.52)  # the last part seen
    assert fault["reconfigured_by"] == "subgroup round r1-7"
    assert fault["reconfigured_mission_s"] == pytest.approx(1.22)
