"""The small frames a robot keeps in custody survive a crash of its process."""

from __future__ import annotations

import stat

from autopower.agent.kept_store import KeptStore
from autopower.agent.node import NodeRuntime
from autopower.agent.resume import mission_key
from autopower.agent.stages import HELD_OUTPUT_LIMIT
from autopower.model.loading import load_scenario
from autopower.protocol import ChainFrame, encode
from tests.unit.sim_team import FakeComponent, FakeSource, SimTeam

MISSION = {"scenario": "paper-fig7", "epoch_unix": 1000.0, "speed": 10.0}


def _result(seq: int, run: int = 0) -> ChainFrame:
    return ChainFrame(chain="Blob-2", run=run, seq=seq, target=1, t_virtual=0.0, t_unix=0.0, payload_len=3,
                      payload=b"abc")


def test_the_journal_is_private_survives_a_torn_record_and_belongs_to_one_mission(tmp_path):
    store = KeptStore(tmp_path / "agents" / "r2.kept")
    for seq in range(5):
        store.append(MISSION, _result(seq))
    assert stat.S_IMODE(store.path.stat().st_mode) == 0o600
    assert stat.S_IMODE(store.path.parent.stat().st_mode) == 0o700
    store.close()
    with open(store.path, "ab") as f:  # a kill in the middle of the next append
        f.write(len(encode(_result(5))).to_bytes(4, "little") + encode(_result(5))[:7])
    assert [f.seq for f in KeptStore(store.path).load(MISSION)] == [0, 1, 2, 3, 4]
    assert KeptStore(store.path).load({**MISSION, "epoch_unix": 2000.0}) == []  # another mission's
    store.path.write_bytes(b"\xff\xfe garbage\n\x00")
    assert KeptStore(store.path).load(MISSION) == []  # reported, never raised
    assert KeptStore(tmp_path / "none.kept").load(MISSION) == []


def test_a_rewrite_keeps_what_is_still_at_risk_and_appends_go_on_after_it(tmp_path):
    store = KeptStore(tmp_path / "r2.kept")
    for seq in range(10):
        store.append(MISSION, _result(seq))
    store.rewrite(MISSION, [_result(7), _result(9)])
    store.append(MISSION, _result(10))
    assert [f.seq for f in KeptStore(store.path).load(MISSION)] == [7, 9, 10] and store.records == 3
    store.rewrite(MISSION, [])
    assert KeptStore(store.path).load(MISSION) == [] and not (tmp_path / "r2.kept.tmp").exists()


def test_a_restarted_robot_takes_back_what_it_kept_and_its_consumers_get_it(tmp_path):
    """Random faults, seed 3: r2, cut off from the base station, held 532 Blob-2 results in memory
    and was SIGKILLed: all were lost. What a robot keeps in custody is journaled (small frames);
    the restarted process takes it back and the sink's reports get it resent; the journal empties
    once the sink has acknowledged it."""
    team = SimTeam(load_scenario("paper-fig7"))
    team.join()
    team.run_until(20.0)
    old = team.nodes["r2"]
    old.kept_store = KeptStore(tmp_path / "r2.kept")
    for robot in ("r1", "r2", "r3"):  # the sink out of reach: results are held
        old.network = old.network.without_link(robot, "laptop")
    results = [_result(100_000 + i) for i in range(HELD_OUTPUT_LIMIT + 4)]
    for frame in results:
        old.emit(frame, "laptop")
    assert len(old.held_outputs) == HELD_OUTPUT_LIMIT
    camera = ChainFrame(chain="Blob-2", run=0, seq=5_000, target=0, t_virtual=0.0, t_unix=0.0,
                        payload_len=230_415, payload=bytes(230_415))
    old.emit(camera, "laptop")  # too large to journal: kept in memory only
    saved = old.resume_state()
    on_disk = KeptStore(tmp_path / "r2.kept").load(mission_key(old.mission))
    # the four the hold let go too: the file is rewritten only once most of it is done with
    assert [f.seq for f in on_disk] == [f.seq for f in results]
    old.kept_store.close()
    # the process is killed; a new one starts, and the plan of the same mission comes
    rt = NodeRuntime(node="r2", scenario=team.scenario, bus=team.hub.bus("r2-again"), keys=team.keys,
                     make_component=FakeComponent, make_source=FakeSource, clock_factory=lambda m: team.clock)
    rt.wall = team.clock.wall
    rt.kept_store = KeptStore(tmp_path / "r2.kept")
    rt.resume_from = saved
    rt.on_plan(old.plan)
    assert len(rt.custody) == len(results)
    team.clock.advance(2.0)  # a report made after the resend delay says they are missing
    rt.on_peer_status(team.nodes["laptop"].status(1.0))
    team.pump()
    sink = team.nodes["laptop"].sinks["Blob-2"]
    delivered = {f.seq for f in results if f.seq < sink.contiguous or f.seq in sink.above}
    assert delivered == {f.seq for f in results}  # all of them (those the hold let go were still on disk)
    team.clock.advance(1.0)
    rt.on_peer_status(team.nodes["laptop"].status(1.0))  # acknowledged
    rt.settle_kept()
    assert KeptStore(tmp_path / "r2.kept").load(mission_key(rt.mission)) == []
