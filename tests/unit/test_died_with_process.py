"""What a crash of a robot costs its own chains (source and sink on it), said apart from losses.

Random faults: one or two Loc outputs per crash were missing. The source notes each seq on disk
before the frame leaves; the sink notes what it delivered with each status. A frame between the two
at the kill lived only in the process's memory. The restarted process says which ones (a short tail
after the last committed output), the recorder logs them, and the replay counts them apart.
"""

from __future__ import annotations

import copy

from autopower.model.loading import load_scenario
from autopower.node.ports import NodeStores, SinkListener
from autopower.node.runtime import NodeRuntime
from tests.unit.sim_team import FakeComponent, FakeSource, SimTeam


def _restart(team: SimTeam, old: NodeRuntime, ahead: int) -> tuple[NodeRuntime, list, int]:
    """Kill `old` with its Loc-1 source `ahead` seqs past what its sink had committed; start it again."""
    saved = old.resume_state()
    ledger = old.sinks["Loc-1"]
    committed = ledger.contiguous
    assert committed > 10 and not ledger.above
    saved["sources"]["Loc-1"]["seq"] = committed + ahead
    rt = NodeRuntime(node="r1", scenario=team.scenario, bus=team.hub.bus("r1-again"), keys=team.keys,
                     make_component=FakeComponent, make_source=FakeSource, clock_factory=lambda m: team.clock,
                     wall=team.clock.wall, stores=NodeStores(resume_from=saved))
    rt.sinks["Loc-1"] = copy.deepcopy(ledger)  # as its `SinkStore` gives it back
    died = []
    rt.listen(SinkListener(died_with_process=lambda chain, run, seq: died.append((chain, run, seq))))
    rt.on_plan(old.plan)
    return rt, died, committed


def _team() -> tuple[SimTeam, NodeRuntime]:
    team = SimTeam(load_scenario("paper-fig7"))
    team.join()
    team.run_until(30.0)
    return team, team.nodes["r1"]


def test_a_restarted_robot_says_which_of_its_own_outputs_died_with_the_crashed_process():
    team, old = _team()
    rt, died, committed = _restart(team, old, ahead=2)
    run = old.sinks["Loc-1"].run
    assert died == [("Loc-1", run, committed), ("Loc-1", run, committed + 1)]
    assert rt.counters.get("died-with-process") == 2


def test_a_tail_longer_than_a_crash_explains_is_not_put_down_to_the_crash():
    """An old gap (a stage stuck for minutes, say) must still count as lost: only a few periods'
    worth (2 s of wall time at the mission's speed) is the crash's."""
    team, old = _team()
    rt, died, _ = _restart(team, old, ahead=500)
    assert died == [] and not rt.counters.get("died-with-process")


def test_the_replay_counts_outputs_that_died_with_a_process_apart_from_lost_ones(tmp_path):
    from types import SimpleNamespace

    from autopower.recording.merge import merge_run
    from autopower.recording.recorder import Recorder
    from autopower.recording.replay import load, summarize

    t = [0.0]
    run_dir = tmp_path / "run-5"
    robot = Recorder.open(run_dir, "r1", clock=lambda: t[0])
    listeners = []
    robot.attach(SimpleNamespace(listen=listeners.append))
    runtime = listeners[0]  # what the runtime tells the recorder (`SinkListener`)
    robot.telemetry.battery(0.0, "r1", 100.0)
    for seq in (*range(0, 10), *range(12, 20)):
        t[0] += 0.5
        robot.on_output("Loc-1", 0, seq, b"")
    runtime.died_with_process("Loc-1", 0, 10)  # 11 died too, but nobody said so: lost
    runtime.died_with_process("Loc-1", 0, 12)  # said, but it arrived after all: no gap there
    robot.telemetry.battery(10.0, "r1", 90.0)
    robot.close()
    o = summarize(load(merge_run(run_dir)))["outputs"]
    assert (o["lost"], o["died_with_process"]) == (1, 1)
    assert (o["chains"]["Loc-1"]["lost"], o["chains"]["Loc-1"]["died_with_process"]) == (1, 1)


def test_a_restarted_robot_names_what_its_chain_with_a_sink_elsewhere_had_in_its_hands_only():
    """Sweep seed 634: r3's camera frames for Blob-3 (its sink: the laptop's operator) were sent into
    a link that had just died, and r3 was killed before a report could ask for them again: they were
    in its custody only, and the replay called them lost. Its resume state now says, per chain it
    sources with a sink elsewhere, the lowest seq still in its hands; the restarted process names
    every seq from there to what its source made: those their sink never gets died with it."""
    team = SimTeam(load_scenario("paper-fig7"))
    team.join()
    team.run_exchanging_statuses(10.0)
    old = team.nodes["r2"]  # Blob-2: camera on r2, blobs to the laptop's operator
    team.cut_silently("r2", "laptop")
    team.run_exchanging_statuses(12.0)
    saved = old.resume_state()
    run, lowest = saved["in_hand"]["Blob-2"]
    produced = old.sources["Blob-2"].seq
    assert old.custody.floor("Blob-2", 0, run, -1) == lowest and produced - lowest >= 6  # 2 s at 4 Hz, unacknowledged
    assert set(saved["in_hand"]) == {"Blob-2"}  # Loc-2's sink is r2 itself (`_died_with_process`'s case)
    saved["sources"]["Blob-2"]["seq"] = produced + 1  # one more noted by the source before the kill
    rt = NodeRuntime(node="r2", scenario=team.scenario, bus=team.hub.bus("r2-again"), keys=team.keys,
                     make_component=FakeComponent, make_source=FakeSource, clock_factory=lambda m: team.clock,
                     wall=team.clock.wall, stores=NodeStores(resume_from=saved))
    died = []
    rt.listen(SinkListener(died_with_process=lambda chain, r, seq: died.append((chain, r, seq))))
    rt.on_plan(old.plan)
    assert [(r, seq) for chain, r, seq in died if chain == "Blob-2"] == [(run, s) for s in range(lowest, produced + 1)]
    assert rt.counters.get("maybe-died-with-process") == len(died)
    # an older file without the record names none of them
    del saved["in_hand"]
    again = NodeRuntime(node="r2", scenario=team.scenario, bus=team.hub.bus("r2-third"), keys=team.keys,
                        make_component=FakeComponent, make_source=FakeSource, clock_factory=lambda m: team.clock,
                        wall=team.clock.wall, stores=NodeStores(resume_from=saved))
    none = []
    again.listen(SinkListener(died_with_process=lambda chain, r, seq: none.append(seq)))
    again.on_plan(old.plan)
    assert none == []
