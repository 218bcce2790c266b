"""Results a robot holds for a sink out of its reach survive a crash of its process."""

from __future__ import annotations

import dataclasses
import stat

from autopower.model.loading import load_scenario
from autopower.node.held_store import HeldStore
from autopower.node.ports import NodeStores, SinkListener
from autopower.node.runtime import NodeRuntime, mission_key
from autopower.protocol import ChainFrame, encode
from tests.unit.sim_team import FakeComponent, FakeSource, SimTeam
from tests.unit.slow_disk import SlowDisk

MISSION = {"scenario": "paper-fig7", "epoch_unix": 1000.0, "speed": 10.0}
HOLD = 512  # results of 3 bytes (`_result`) a node keeps under the budget `_budgeted` gives it


def _budgeted():
    """The paper's scenario with a hold budget of HOLD `_result`s."""
    return dataclasses.replace(load_scenario("paper-fig7"), hold_budget_bytes=HOLD * 3)


def _result(seq: int, run: int = 0) -> ChainFrame:
    return ChainFrame(chain="Blob-2", run=run, seq=seq, target=1, t_virtual=0.0, t_unix=0.0, payload_len=3,
                      payload=b"abc")


def test_the_journal_is_private_survives_a_torn_record_and_belongs_to_one_mission(tmp_path):
    store = HeldStore(tmp_path / "agents" / "r2.held")
    for seq in range(5):
        store.append(MISSION, _result(seq))
    assert stat.S_IMODE(store.path.stat().st_mode) == 0o600
    assert stat.S_IMODE(store.path.parent.stat().st_mode) == 0o700
    assert stat.S_IMODE(store.path.with_name("r2.held.journal.2").stat().st_mode) == 0o600
    store.close()
    with open(store.path.with_name("r2.held.journal.2"), "ab") as f:  # a kill in the middle of the next append
        f.write(len(encode(_result(5))).to_bytes(4, "little") + encode(_result(5))[:7])
    assert [f.seq for f in HeldStore(store.path).load(MISSION)] == [0, 1, 2, 3, 4]
    assert HeldStore(store.path).load({**MISSION, "epoch_unix": 2000.0}) == []  # another mission's
    store.path.write_bytes(b"\xff\xfe garbage\n\x00")
    assert HeldStore(store.path).load(MISSION) == []  # reported, never raised
    assert HeldStore(tmp_path / "none.held").load(MISSION) == []


def test_a_rewrite_keeps_what_is_still_at_risk_and_appends_go_on_after_it(tmp_path):
    store = HeldStore(tmp_path / "r2.held")
    for seq in range(10):
        store.append(MISSION, _result(seq))
    store.rewrite(MISSION, [_result(7), _result(9)])
    store.append(MISSION, _result(10))
    assert [f.seq for f in HeldStore(store.path).load(MISSION)] == [7, 9, 10] and store.records == 3
    store.rewrite(MISSION, [])
    assert HeldStore(store.path).load(MISSION) == [] and not (tmp_path / "r2.held.tmp").exists()


def test_a_file_written_before_journal_generations_still_loads(tmp_path):
    import json

    record = encode(_result(4))
    (tmp_path / "r2.held").write_bytes(json.dumps({"version": 1, "mission": MISSION}).encode() + b"\n"
                                       + len(record).to_bytes(4, "little") + record)
    assert [f.seq for f in HeldStore(tmp_path / "r2.held").load(MISSION)] == [4]


def test_a_rewrite_written_slowly_never_holds_the_loop_and_a_crash_meanwhile_keeps_every_result(tmp_path, monkeypatch):
    import time

    slow = SlowDisk(monkeypatch)
    store = HeldStore(tmp_path / "r2.held", background=True)
    slow.release.set()
    for seq in range(6):
        assert store.append(MISSION, _result(seq))
    assert store._files.written(5)  # the mission's first snapshot, handed over by the first append
    assert store.rewrite(MISSION, [_result(4), _result(5)])
    assert store._files.written(5)
    slow.release.clear()
    slow.entered.clear()
    assert store.rewrite(MISSION, [_result(5)])  # handed over; the writer is stuck in its rename
    assert slow.entered.wait(5)
    started = time.monotonic()
    assert store.append(MISSION, _result(6)) and store.append(MISSION, _result(7))
    assert not store.rewrite(MISSION, [_result(7)])  # skipped while the writer is behind: tried again later
    assert time.monotonic() - started < 0.5  # the loop never waited for the stuck writer
    # killed here: the older snapshot and every journal since it hold all that was at risk, and more
    assert [f.seq for f in HeldStore(store.path).load(MISSION)] == [4, 5, 6, 7]
    slow.release.set()
    assert store._files.written(5)
    assert [f.seq for f in HeldStore(store.path).load(MISSION)] == [5, 6, 7]
    store.close()


def test_a_restarted_robot_takes_back_what_it_held_and_delivers_it_once_the_sink_is_in_reach(tmp_path):
    """Random faults, seed 3: r2, cut off from the base station, held 532 Blob-2 results in memory
    and was SIGKILLed: all were lost. Held results are journaled; the restarted process holds
    them again and sends them when the sink is in reach; the journal empties once it acknowledges."""
    team = SimTeam(_budgeted(), stores={"r2": NodeStores(held_store=HeldStore(tmp_path / "r2.held"))})
    team.join()
    team.run_until(20.0)
    old = team.nodes["r2"]  # what it lets go is logged into a recording batch the kill loses
    results = [_result(100_000 + i) for i in range(HOLD + 4)]
    for frame in results:  # as `Frames.emit` and `send_routed` do with the sink out of reach
        old.holds.keep(frame, sent=False)
        old.holds.hold(frame)
    saved = old.resume_state()
    assert len(HeldStore(tmp_path / "r2.held").load(mission_key(old.mission))) == len(results)
    old.holds.store.close()
    # the process is killed; a new one starts, and the plan of the same mission comes
    rt = NodeRuntime(node="r2", scenario=team.scenario, bus=team.hub.bus("r2-again"), keys=team.keys,
                     make_component=FakeComponent, make_source=FakeSource, clock_factory=lambda m: team.clock,
                     wall=team.clock.wall, stores=NodeStores(held_store=HeldStore(tmp_path / "r2.held"), resume_from=saved))
    logged = []
    rt.listen(SinkListener(held_dropped=lambda chain, run, seq, why: logged.append((chain, run, seq))))
    rt.on_plan(old.plan)
    # the four beyond the budget are in the crashed process's journal: the new one drops them again, logged
    assert logged == [("Blob-2", 0, f.seq) for f in results[:4]]
    team.pump()
    sink = team.nodes["laptop"].sinks["Blob-2"]
    assert sink.duplicates_total == 0
    delivered = {f.seq for f in results if f.seq < sink.contiguous or f.seq in sink.above}
    # the four beyond the budget are dropped, counted; every other one reached the sink
    assert delivered == {f.seq for f in results[4:]}
    assert not rt.holds.held
    # acknowledged: the journal is emptied at the next status tick
    rt.on_ack(team.nodes["laptop"].acks()["r2"])
    rt.holds.settle_store()
    assert HeldStore(tmp_path / "r2.held").load(mission_key(rt.mission)) == []


def test_held_results_the_sink_already_had_are_dropped_there_as_redundant_not_counted_twice(tmp_path):
    """The testbed demo: r2 delivered its held results, the base station acknowledged them, and r2
    was killed before its next status tick rewrote the journal. The restarted process took them
    back and sent them as new: the sink counted and recorded 50 Blob-2 outputs twice. They go
    again as retransmissions now, and a sink that has them drops them as redundant."""
    team = SimTeam(load_scenario("paper-fig7"), stores={"r2": NodeStores(held_store=HeldStore(tmp_path / "r2.held"))})
    team.join()
    team.run_until(20.0)
    old = team.nodes["r2"]
    sink_node = team.nodes["laptop"]
    results = [_result(200_000 + i) for i in range(6)]
    for frame in results:
        old.holds.keep(frame, sent=False)
        old.holds.hold(frame)
    old.frames.flush_held()  # the sink is in reach: delivered
    team.pump()
    sink = sink_node.sinks["Blob-2"]
    had = {f.seq for f in results if f.seq < sink.contiguous or f.seq in sink.above}
    assert had == {f.seq for f in results}
    saved = old.resume_state()
    old.holds.store.close()  # killed before the journal was rewritten: it still lists all six
    recorded = []
    sink_node.listen(SinkListener(output=lambda chain, run, seq, data: recorded.append(seq)))
    rt = NodeRuntime(node="r2", scenario=team.scenario, bus=team.hub.bus("r2-again"), keys=team.keys,
                     make_component=FakeComponent, make_source=FakeSource, clock_factory=lambda m: team.clock,
                     wall=team.clock.wall, stores=NodeStores(held_store=HeldStore(tmp_path / "r2.held"), resume_from=saved))
    rt.on_plan(old.plan)
    team.pump()
    assert not [seq for seq in recorded if seq >= 200_000]  # none handed on (recorded) again
    assert sink.duplicates_total == 0 and sink.redundant_total >= 6


def test_a_held_result_that_reaches_its_sink_late_is_redundant_where_another_instance_delivered_it():
    """Random faults, seed 3: the laptop, cut off from r1, ran the inputs waiting in its released
    Loc-1 and held the result for seq 11; r1's own restarted Loc-1 ran seq 11 again from its
    source's resend and delivered it. r1's sink was then restarted (what came as a resend is not
    kept on disk), and 50 s later the held copy came, sent as new: delivered and recorded twice."""
    import dataclasses

    from autopower.node.sequencing import SinkLedger

    team = SimTeam(load_scenario("paper-fig7"))
    team.join()
    team.run_until(20.0)
    r2, laptop = team.nodes["r2"], team.nodes["laptop"]
    frame = _result(300_000)
    r2.holds.keep(frame, sent=False)
    r2.holds.hold(frame)  # its sink out of reach
    # the stage's next instance ran the resent input: its copy reaches the sink first
    laptop.frames.deliver_frame(dataclasses.replace(frame, attempt=1), 0)
    sink = laptop.sinks["Blob-2"]
    assert 300_000 in sink.above
    laptop.sinks["Blob-2"] = sink = SinkLedger.from_state(sink.state())  # the sink restarted since
    handed_on = []
    laptop.listen(SinkListener(output=lambda chain, run, seq, data: handed_on.append(seq)))
    r2.frames.flush_held()  # back in reach: the held copy goes
    team.pump()
    assert handed_on == [] and sink.duplicates_total == 0 and sink.redundant_total == 1


def test_the_base_stations_host_takes_back_what_it_held_after_a_restart(tmp_path):
    """Random faults, seed 6: the laptop, cut off from r1, ran the Loc-1 inputs waiting in its
    released stage and held their results for r1's sink; r1 had had their acknowledgement. The
    laptop was then killed and the held results died in its memory: Loc-1 seq 10 was lost. The
    base station's host has no resume state, and now keeps its held results on disk all the same."""
    team = SimTeam(load_scenario("paper-fig7"), stores={"laptop": NodeStores(held_store=HeldStore(tmp_path / "laptop.held"))})
    team.join()
    team.run_until(20.0)
    old = team.nodes["laptop"]
    results = [ChainFrame(chain="Loc-1", run=0, seq=400_000 + i, target=1, t_virtual=0.0, t_unix=0.0,
                          payload_len=3, payload=b"abc") for i in range(3)]
    for frame in results:
        old.holds.keep(frame, sent=False)
        old.holds.hold(frame)
    old.holds.store.close()
    # killed; the restarted base station's host gets the plan of the same mission (no resume state)
    rt = NodeRuntime(node="laptop", scenario=team.scenario, bus=team.hub.bus("laptop-again"), keys=team.keys,
                     make_component=FakeComponent, make_source=FakeSource, clock_factory=lambda m: team.clock,
                     wall=team.clock.wall, stores=NodeStores(held_store=HeldStore(tmp_path / "laptop.held")))
    rt.on_plan(old.plan)
    team.pump()
    sink = team.nodes["r1"].sinks["Loc-1"]
    assert all(f.seq in sink.above for f in results), sorted(sink.above)  # r1 in reach: delivered
    assert sink.duplicates_total == 0 and not rt.holds.held


def test_a_writer_stuck_at_a_new_mission_is_waited_for_once_and_then_never_again(tmp_path, monkeypatch):
    import time

    import autopower.node.held_store as held_store

    monkeypatch.setattr(held_store, "MISSION_SWITCH_WAIT_S", 0.3)
    slow = SlowDisk(monkeypatch)
    store = HeldStore(tmp_path / "r2.held", background=True)
    slow.release.set()
    assert store.append(MISSION, _result(0)) and store._files.written(5)
    slow.release.clear()
    assert store.rewrite(MISSION, [])  # the writer is stuck in this one's rename
    assert slow.entered.wait(5)
    other = {**MISSION, "epoch_unix": 2000.0}
    started = time.monotonic()
    assert not store.append(other, _result(0))  # not on disk, and said so (the runtime counts it at risk)
    assert time.monotonic() - started >= 0.3  # the new mission's first snapshot waited for the writer
    started = time.monotonic()
    assert not store.append(other, _result(1)) and not store.append(other, _result(2))
    assert time.monotonic() - started < 0.2  # ... once: the loop is not held at every held result
    slow.release.set()
    assert store._files.written(5)
    assert store.append(other, _result(3))
    assert store._files.written(5)
    assert [f.seq for f in HeldStore(store.path).load(other)] == [3]
    store.close()


def test_held_results_sent_once_their_sink_is_back_are_metered_as_a_backlog():
    """Live random faults, seed 18: after the partitions r1 sent what it had held over GSM, and the
    meter charged it as the chain's steady traffic, which the model prices at the chain's rate
    from the plan on: +338 J on r1 inside the reconfiguration windows. Their radio goes to the
    reconfiguration's backlog (`overhead_j/backlog`), as the first runs of a restarted stage's held
    inputs do (and on the receiving end too: the packet says so)."""
    team = SimTeam(load_scenario("paper-fig7"))
    team.join()
    team.run_until(20.0)
    r2 = team.nodes["r2"]
    results = [_result(300_000 + i) for i in range(4)]
    for frame in results:
        r2.holds.keep(frame, sent=False)
        r2.holds.hold(frame)
    sent_before, backlog_before = r2.meter.energy_j.copy(), r2.meter.overhead_j()["backlog"]
    r2.frames.flush_held()
    team.pump()
    assert r2.meter.overhead_j()["backlog"] > backlog_before
    from autopower.model.parts import radio_part

    send = radio_part(next(iter(r2.meter.media)), "send")
    assert send in sent_before  # (its chains sent before: the part's name is right)
    assert r2.meter.energy_j[send] == sent_before[send]
