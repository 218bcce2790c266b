"""A restarted agent carries on: battery and source positions from its resume file (same mission only)."""

from __future__ import annotations

import stat

import pytest

from autopower.agent.resume import ResumeFile
from autopower.model.loading import load_scenario
from autopower.node.ports import NodeStores, SinkListener
from autopower.node.runtime import NodeRuntime
from tests.unit.sim_team import FakeComponent, FakeSource, SimTeam
from tests.unit.slow_disk import SlowDisk


def _team_at(t_end: float) -> SimTeam:
    team = SimTeam(load_scenario("paper-fig7"))
    team.join()
    team.run_until(t_end)
    return team


def _restarted(team: SimTeam, robot: str, saved: dict | None) -> NodeRuntime:
    old = team.nodes[robot]
    rt = NodeRuntime(node=robot, scenario=team.scenario, bus=team.hub.bus(robot + "-again"), keys=team.keys,
                     make_component=FakeComponent, make_source=FakeSource, clock_factory=lambda m: team.clock,
                     stores=NodeStores(resume_from=saved))
    rt.on_plan(old.plan)
    return rt


def test_the_resume_file_is_private_and_survives_a_round_trip(tmp_path):
    team = _team_at(40.0)
    state = team.nodes["r2"].resume_state()
    store = ResumeFile(tmp_path / "agents" / "r2.json")
    store.save(state)
    assert stat.S_IMODE(store.path.stat().st_mode) == 0o600
    assert store.load()["energy_j"] == pytest.approx(state["energy_j"])
    store.path.write_text("{not json")
    assert store.load() is None  # unreadable: start from the mission's energies, never crash


def test_a_restart_continues_the_battery_and_the_sources():
    team = _team_at(40.0)
    old = team.nodes["r2"]
    saved = old.resume_state()
    consumed = old.meter.consumed_j
    sources = {name: runner.seq for name, runner in old.sources.items()}
    assert sources and all(seq > 0 for seq in sources.values())
    team.clock.set(50.0)  # the process was down for 10 s of mission time
    rt = _restarted(team, "r2", saved)
    assert rt.resuming.resumed
    rt.meter.advance(50.0)
    idle_w = team.scenario.platform_of("r2").idle_w
    # what it had consumed, plus at least the idle CPU of the 10 s it was down: not a full battery
    assert rt.meter.consumed_j >= consumed + idle_w * 10.0 - 1e-6
    assert rt.meter.battery_j < team.scenario.robot("r2").energy_j - consumed
    assert {name: runner.seq for name, runner in rt.sources.items()} == sources


def test_the_state_of_another_mission_is_ignored():
    team = _team_at(20.0)
    saved = team.nodes["r2"].resume_state()
    saved["mission"] = {**saved["mission"], "epoch_unix": saved["mission"]["epoch_unix"] + 1.0}
    rt = _restarted(team, "r2", saved)
    assert not rt.resuming.resumed
    assert rt.meter.battery_j == pytest.approx(team.scenario.robot("r2").energy_j)
    assert all(runner.seq == 0 for runner in rt.sources.values())


@pytest.mark.parametrize("damage", [{"energy_j": "much"}, {"energy_j": {"cpu_idle": float("nan")}},
                                    {"sources": {"Loc-2": {"run": "x"}}}, {"t_virtual": None}])
def test_a_damaged_resume_state_is_ignored_not_a_crash_loop(damage):
    team = _team_at(20.0)
    saved = {**team.nodes["r2"].resume_state(), **damage}
    rt = _restarted(team, "r2", saved)
    assert not rt.resuming.resumed
    assert rt.meter.battery_j == pytest.approx(team.scenario.robot("r2").energy_j)


def test_the_files_of_a_dead_team_go_with_its_resume_files(tmp_path, monkeypatch):
    from autopower.agent.resume import AGENTS_DIR
    from autopower.basestation.operator import remove_team_files, team_dir

    monkeypatch.setenv("AUTOPOWER_STATE_DIR", str(tmp_path))
    ResumeFile(team_dir("t9") / AGENTS_DIR / "r1.json").save({"node": "r1"})
    remove_team_files("t9")
    assert not (tmp_path / "teams" / "t9").exists()


def test_source_positions_after_the_snapshot_come_from_the_journal(tmp_path):
    store = ResumeFile(tmp_path / "r2.json")
    store.note_source("Blob-2", 1, 5, 0, 5)  # before any snapshot: the first snapshot supersedes it
    store.save({"node": "r2", "sources": {"Blob-2": {"run": 1, "seq": 7, "missed": 0, "produced_total": 7}}})
    assert stat.S_IMODE(store.current_journal.stat().st_mode) == 0o600
    for seq in (8, 9, 10):
        store.note_source("Blob-2", 1, seq, 0, seq)
    with open(store.current_journal, "a") as f:
        f.write('["Blob-2", 1, 11')  # the line a SIGKILL cut short
    assert store.load()["sources"]["Blob-2"]["seq"] == 10
    first = store.current_journal
    store.save({"node": "r2", "sources": {"Blob-2": {"run": 1, "seq": 12, "missed": 0, "produced_total": 12}}})
    # the notes before the new snapshot are gone with their generation; the new one starts empty
    assert not first.exists() and store.current_journal.stat().st_size == 0
    assert store.load()["sources"]["Blob-2"]["seq"] == 12
    store.close()


@pytest.mark.parametrize("background", [False, True])
def test_a_restarted_process_notes_its_sources_before_its_first_snapshot(tmp_path, background):
    """A robot killed twice: the process restarted after the first kill produced frames before it
    wrote its first snapshot. Those notes must survive the second kill, or the next restart reuses
    their seqs: two frames under one name (found by the simulator, seed 1031, with a change that lets
    a chain stopped by a fault go on in its run, where the reused seqs are no longer in an old run)."""
    first = ResumeFile(tmp_path / "r2.json", background=background)
    first.save({"node": "r2", "sources": {"Blob-2": {"run": 0, "seq": 40, "missed": 0, "produced_total": 40}}},
               wait_s=5.0)
    for seq in (41, 42, 43, 44):
        first.note_source("Blob-2", 0, seq, 0, seq)
    first.close()  # killed
    second = ResumeFile(tmp_path / "r2.json", background=background)
    assert second.load()["sources"]["Blob-2"]["seq"] == 44
    second.note_source("Blob-2", 0, 45, 0, 45)  # produced before its first snapshot
    second.close()  # killed again
    third = ResumeFile(tmp_path / "r2.json", background=background)
    assert third.load()["sources"]["Blob-2"]["seq"] == 45
    third.save({"node": "r2", "sources": {"Blob-2": {"run": 0, "seq": 45, "missed": 0, "produced_total": 45}}},
               wait_s=5.0)
    third.note_source("Blob-2", 0, 46, 0, 46)
    assert third.written(5.0) and third.load()["sources"]["Blob-2"]["seq"] == 46  # read in order, newest last
    third.close()


def test_the_journal_keeps_periods_missed_while_stopped_and_reads_an_older_one(tmp_path):
    store = ResumeFile(tmp_path / "r2.json")
    store.save({"node": "r2", "sources": {"Blob-2": {"run": 1, "seq": 7, "missed": 0, "produced_total": 7}}})
    store.note_source("Blob-2", 1, 8, 150, 8, 142)
    assert store.load()["sources"]["Blob-2"] == {"run": 1, "seq": 8, "missed": 150, "produced_total": 8,
                                                 "missed_stopped": 142}
    with open(store.current_journal, "a") as f:
        f.write('["Loc-2", 1, 3, 2, 3]\n')  # a line of the build before: five fields
    assert store.load()["sources"]["Loc-2"] == {"run": 1, "seq": 3, "missed": 2, "produced_total": 3,
                                                "missed_stopped": 0}
    store.close()


def test_a_resume_file_written_before_journal_generations_still_resumes(tmp_path):
    (tmp_path / "r2.json").write_text('{"version": 1, "node": "r2", "sources": {"Blob-2": {"run": 1, "seq": 7, '
                                      '"missed": 0, "produced_total": 7}}}')
    (tmp_path / "r2.json.journal").write_text('["Blob-2", 1, 9, 0, 9, 0]\n')
    store = ResumeFile(tmp_path / "r2.json")
    state = store.load()
    assert state["sources"]["Blob-2"]["seq"] == 9
    # the first snapshot says what the old journal said, which then goes; later notes follow it
    assert store.save(state)
    assert not (tmp_path / "r2.json.journal").exists()
    store.note_source("Blob-2", 1, 10, 0, 10)
    assert store.save({**state, "sources": {"Blob-2": {**state["sources"]["Blob-2"], "seq": 10}}})
    store.close()
    assert ResumeFile(tmp_path / "r2.json").load()["sources"]["Blob-2"]["seq"] == 10


def test_a_snapshot_written_slowly_never_holds_the_loop_and_loses_no_note(tmp_path, monkeypatch):
    import time

    slow = SlowDisk(monkeypatch)
    store = ResumeFile(tmp_path / "r2.json", background=True)
    position = {"run": 1, "seq": 7, "missed": 0, "produced_total": 7}
    t0 = time.monotonic()
    assert store.save({"node": "r2", "sources": {"Blob-2": position}})
    assert slow.entered.wait(5)  # the writer is stuck in the file system...
    for seq in (8, 9):  # ...while the loop goes on: notes append, the next snapshots are skipped
        store.note_source("Blob-2", 1, seq, 0, seq)
        assert not store.save({"node": "r2", "sources": {"Blob-2": {**position, "seq": seq}}})
    assert time.monotonic() - t0 < 1.0 and store.skipped == 2
    slow.release.set()
    # the last save of a stopping agent waits for the one being written, then goes out itself
    assert store.save({"node": "r2", "sources": {"Blob-2": {**position, "seq": 9}}}, wait_s=5)
    store.note_source("Blob-2", 1, 10, 0, 10)
    store.close()
    assert ResumeFile(tmp_path / "r2.json").load()["sources"]["Blob-2"]["seq"] == 10


def test_a_crash_while_the_snapshot_is_written_resumes_from_the_older_one_and_every_journal(tmp_path, monkeypatch):
    slow = SlowDisk(monkeypatch)
    store = ResumeFile(tmp_path / "r2.json", background=True)
    slow.release.set()
    assert store.save({"node": "r2", "sources": {"Blob-2": {"run": 1, "seq": 7, "missed": 0, "produced_total": 7}}},
                      wait_s=5)
    store.note_source("Blob-2", 1, 8, 0, 8)
    assert store.save({"node": "r2", "sources": {"Blob-2": {"run": 1, "seq": 8, "missed": 0, "produced_total": 8}}},
                      wait_s=5)
    assert store.written(5)
    slow.release.clear()
    slow.entered.clear()
    store.note_source("Blob-2", 1, 9, 0, 9)
    assert store.save({"node": "r2", "sources": {"Blob-2": {"run": 1, "seq": 9, "missed": 0, "produced_total": 9}}},
                      wait_s=5)
    assert slow.entered.wait(5)  # this snapshot is not in place yet: the process dies here
    store.note_source("Blob-2", 1, 10, 0, 10)
    # what a restarted process reads: the snapshot before (seq 8), then every generation from its own on
    assert ResumeFile(tmp_path / "r2.json").load()["sources"]["Blob-2"]["seq"] == 10
    slow.release.set()
    store.close()


def _fresh(team: SimTeam, robot: str, saved: dict | None) -> NodeRuntime:
    """A restarted process of ``robot`` that has heard no plan yet."""
    rt = NodeRuntime(node=robot, scenario=team.scenario, bus=team.hub.bus(robot + "-fresh"), keys=team.keys,
                     make_component=FakeComponent, make_source=FakeSource, clock_factory=lambda m: team.clock,
                     wall=team.clock.wall, stores=NodeStores(resume_from=saved))
    return rt


def test_a_restarted_robot_can_go_on_with_the_plan_it_ran_subgroup_rounds_included(tmp_path):
    """A robot restarted while the base station is out of reach had no plan, so no mission clock, no
    sources, no part in subgroup rounds: it idled until the base station came back. Its resume state
    now holds the plan it ran (with a subgroup round's placement), which it can go on with."""
    import json

    team = _team_at(40.0)
    old = team.nodes["r2"]
    old.plan_view.override_placement({"Loc-2": "r2", "Blob-2": "r2"}, {"laptop"})  # a subgroup round, base out of reach
    store = ResumeFile(tmp_path / "r2.json")
    store.save(old.resume_state())
    saved = json.loads(json.dumps(store.load()))
    rt = _fresh(team, "r2", saved)
    plan = rt.resuming.saved_plan()
    assert plan == old.plan and plan.placement["Blob-2"] == "r2"
    consumed = old.meter.consumed_j
    rt.on_plan(plan)  # what `AgentProcess._resume_alone` does
    assert rt.resuming.resumed and rt.meter.consumed_j >= consumed  # battery goes on, not from the mission's energies
    assert set(rt.sources) == set(old.sources) and all(rt.sources[n].seq >= old.sources[n].seq for n in rt.sources)
    status = rt.status(1.0)  # what its peers' next subgroup round starts from: the mission, and nothing hosted
    assert status.mission == old.mission and status.plan_epoch == old.plan.epoch and not status.hosted


def test_a_stale_or_damaged_saved_plan_is_not_gone_on_with(caplog):
    team = _team_at(40.0)
    saved = team.nodes["r2"].resume_state()
    assert _fresh(team, "r2", dict(saved)).resuming.saved_plan() is not None
    assert _fresh(team, "r2", {**saved, "saved_unix": saved["saved_unix"] - 301.0}).resuming.saved_plan() is None  # stale
    assert _fresh(team, "r1", dict(saved)).resuming.saved_plan() is None  # another robot's file
    assert _fresh(team, "r2", {**saved, "plan": "bm90IGEgcGxhbg=="}).resuming.saved_plan() is None  # "not a plan"
    assert _fresh(team, "r2", {**saved, "plan": "%%%"}).resuming.saved_plan() is None
    assert "the saved plan is unusable" in caplog.text
    assert _fresh(team, "r2", {**saved, "mission": {"scenario": "x"}}).resuming.saved_plan() is None
    assert _fresh(team, "r2", {k: v for k, v in saved.items() if k != "plan"}).resuming.saved_plan() is None  # an older file


def test_a_stage_follows_the_plans_newer_run_of_its_chain():
    """Random faults, seed 4: the base station restarted Blob-3 as a new run, then adopted the
    instance a subgroup round had started (old run) as running, with no order. The source followed
    the plan's run, the stage dropped every frame as stale-run, and the chain delivered nothing
    more. A stage whose chain the plan runs in a newer run starts afresh in it."""
    import dataclasses

    from autopower.basestation.coordinator import CoordinatorConfig

    team = SimTeam(load_scenario("paper-fig7"), config=CoordinatorConfig(speed=1.0, pins={"Blob-3": "r3"},
                                                                          auto_replan=False))
    team.join()
    team.run_until(20.0)
    r3 = team.nodes["r3"]
    assert r3.hosted["Blob-3"].run == 0 and team.nodes["laptop"].sinks["Blob-3"].run == 0
    plan = r3.plan
    newer = dataclasses.replace(plan, epoch=plan.epoch + 50, running={**plan.running, "Blob-3": 1})
    for rt in team.nodes.values():  # the plan reaches everyone; no Assign for the new run
        rt.on_plan(newer)
    assert r3.hosted["Blob-3"].run == 1 and r3.counters["stage-new-run"] == 1
    received = team.nodes["laptop"].sinks["Blob-3"].received
    team.run_until(40.0)
    sink = team.nodes["laptop"].sinks["Blob-3"]
    assert sink.run == 1 and sink.received > 5, (sink.run, sink.received, received)
    assert "stale-run" not in r3.errors


def test_a_restarted_robot_sink_does_not_take_a_resent_result_for_a_new_one(tmp_path):
    """Random faults, seed 10: r3, the sink of its own Loc-3, was killed; the robot whose Loc-3
    stage had sent it result 94 had not had the acknowledgement (a cut), resent it to the restarted
    r3, and r3's empty ledger handed it on as new: recorded twice. Robots keep their sinks' ledgers
    on disk as the base station does (`agent.sink_store`), committed before each status."""
    from autopower.basestation.coordinator import CoordinatorConfig
    from autopower.node.sink_store import SinkStore
    from autopower.protocol import ChainFrame

    team = SimTeam(load_scenario("paper-fig7"), config=CoordinatorConfig(speed=1.0, pins={"Loc-3": "r1"},
                                                                          auto_replan=False),
                   stores={"r3": NodeStores(sink_store=SinkStore(tmp_path / "r3.sinks.json"))})
    team.join()
    old = team.nodes["r3"]
    team.run_until(30.0)
    ledger = old.sinks["Loc-3"]
    assert ledger.received > 3
    old.sinking.store.commit()  # what `AgentProcess.publish_status` does before each status
    saved = old.resume_state()
    rt = NodeRuntime(node="r3", scenario=team.scenario, bus=team.hub.bus("r3-again"), keys=team.keys,
                     make_component=FakeComponent, make_source=FakeSource, clock_factory=lambda m: team.clock,
                     stores=NodeStores(sink_store=SinkStore(tmp_path / "r3.sinks.json"), resume_from=saved))
    rt.on_plan(old.plan)
    outputs = []
    rt.listen(SinkListener(output=lambda chain, run, seq, data: outputs.append(seq)))
    resent = ChainFrame(chain="Loc-3", run=ledger.run, seq=ledger.contiguous - 1, target=1, t_virtual=0.0,
                        t_unix=0.0, payload_len=0, payload=b"", attempt=1)
    rt.frames.deliver_frame(resent, 0)
    assert outputs == [] and rt.sinks["Loc-3"].redundant_total == 1


def test_sources_built_before_the_mission_are_the_ones_its_first_plan_runs():
    """A fleet's first plan must not make every robot render its camera's scene at the same instant."""
    team = _team_at(10.0)
    built = []

    def make_source(kind, robot, seed, *parameters):
        built.append(kind)
        return FakeSource(kind, robot, seed, *parameters)

    rt = NodeRuntime(node="r2", scenario=team.scenario, bus=team.hub.bus("r2-prepared"), keys=team.keys,
                     make_component=FakeComponent, make_source=make_source, clock_factory=lambda m: team.clock)
    rt.production.prepare()
    own = [c.name for c in team.scenario.chains if c.source == "r2" and c.sourced]
    assert own and len(built) == len(own)
    prepared = set(map(id, rt.feeds._prepared.values()))
    rt.on_plan(team.nodes["r2"].plan)
    assert len(built) == len(own)  # the plan built nothing more
    assert {id(runner.source) for runner in rt.sources.values()} == prepared


def test_the_plan_is_written_once_while_it_stays_and_every_snapshot_names_it(tmp_path, monkeypatch):
    """Rule (`agent.resume`): a robot's plan lists the team and changes far less often than its battery,
    so it goes to a side file written only when it changed; each snapshot names it, and a load puts it
    back. A kill between a new plan's file and the snapshot that names it leaves the older pair."""
    from autopower.runtime import snapshot_journal

    written: list[str] = []
    replace = snapshot_journal.SnapshotJournal._replace

    def counted(self, path, content):
        written.append(path.name)
        return replace(self, path, content)

    monkeypatch.setattr(snapshot_journal.SnapshotJournal, "_replace", counted)
    store = ResumeFile(tmp_path / "r2.json")
    plan_a, plan_b = "A" * 40_000, "B" * 40_000
    for battery in (10.0, 9.0, 8.0):
        store.save({"node": "r2", "battery": battery, "plan": plan_a})
    sides = [n for n in written if ".side." in n]
    assert len(sides) == 1 and written.count("r2.json") == 3  # the plan once, the snapshot at every save
    assert (tmp_path / "r2.json").stat().st_size < 1_000  # the snapshot no longer carries the plan
    state = store.load()
    assert state["plan"] == plan_a and state["battery"] == 8.0 and "plan_file" not in state
    store.save({"node": "r2", "battery": 7.0, "plan": plan_b})
    assert ResumeFile(tmp_path / "r2.json").load()["plan"] == plan_b
    new_side = written[-2]  # written before the snapshot that names it; the old one is gone
    assert ".side." in new_side and new_side != sides[0]
    assert [p.name for p in tmp_path.glob("r2.json.side.*")] == [new_side]
    store.save({"node": "r2", "battery": 6.0, "plan": None})  # no plan: no side file left
    assert ResumeFile(tmp_path / "r2.json").load()["plan"] is None and not list(tmp_path.glob("r2.json.side.*"))
    store.close()


def test_a_snapshot_whose_plan_file_is_gone_loads_without_a_plan(tmp_path):
    store = ResumeFile(tmp_path / "r2.json")
    store.save({"node": "r2", "plan": "P" * 100})
    store.close()
    for side in tmp_path.glob("r2.json.side.*"):
        side.unlink()
    state = ResumeFile(tmp_path / "r2.json").load()
    assert state["node"] == "r2" and state["plan"] is None
