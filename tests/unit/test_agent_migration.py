"""Sequencing and live migration: every output exactly once, state carried, inputs not dropped."""

from __future__ import annotations

import random
from dataclasses import replace

import msgpack
import pytest

from autopower.basestation.coordinator import CoordinatorConfig
from autopower.errors import ProtocolError
from autopower.model.loading import load_scenario
from autopower.node.ports import SinkListener
from autopower.node.sequencing import SequenceGate, SinkLedger
from autopower.node.stages import Lifecycle, pad
from autopower.protocol import ChainCommand, MigrateCommand, OperatorSettings
from tests.unit.sim_team import SimTeam

FC = {"laptop-robot": "802.11a", "robot-robot": "802.11a"}


def test_gate_in_order_and_duplicates():
    gate = SequenceGate(next_seq=0)
    assert gate.offer(0, "a") == ["a"]
    assert gate.offer(2, "c") == []
    assert gate.offer(1, "b") == ["b", "c"]
    assert gate.offer(1, "b") == [] and gate.duplicates == 1
    assert gate.offer(5, "f") == []
    assert gate.offer(5, "f") == [] and gate.duplicates == 2
    assert gate.take_pending() == ["f"] and gate.pending == {}


def test_gate_starts_at_first_offer_when_unknown():
    gate = SequenceGate()
    assert gate.offer(7, "x") == ["x"]
    assert gate.next_seq == 8
    assert gate.offer(6, "old") == [] and gate.duplicates == 1


def test_sink_ledger():
    ledger = SinkLedger()
    for seq in (0, 2, 1, 1, 3):
        ledger.record(0, seq, 1.0)
    assert (ledger.received, ledger.duplicates, ledger.contiguous, ledger.max_seq, ledger.gaps) == (4, 1, 4, 3, 0)
    ledger.record(0, 6)
    assert ledger.gaps == 2 and ledger.contiguous == 4
    assert ledger.record(1, 0)  # a new run starts over
    assert ledger.run == 1 and ledger.received == 1 and ledger.received_total == 6
    assert not ledger.record(0, 7) and ledger.stale == 1


def test_an_older_runs_output_is_handed_on_once_never_twice():
    """Random-fault seed 2 (2026-11-29): Loc-2's seqs 26-30 of run 0 reached the operator twice,
    once from the laptop (which ran its waiting inputs as it was released) and once from the
    stage's restart on r2, after the chain had started run 1. The sink kept no ledger for run 0,
    and handed on every run-0 output as stale. It now remembers the last runs before its own."""
    from autopower.node.sequencing import OLDER_RUNS_KEPT

    ledger = SinkLedger()
    for seq in (0, 1, 2):
        ledger.record(0, seq)
    ledger.record(1, 0)
    dups = ledger.duplicates_total
    assert not ledger.record(0, 4) and ledger.stale == 1  # first copy: the caller hands it on
    assert not ledger.record(0, 4) and ledger.duplicates_total == dups + 1 and ledger.stale == 1
    assert not ledger.record(0, 1) and ledger.duplicates_total == dups + 2  # delivered in run 0 already
    assert not ledger.record(0, 3, attempt=1) and ledger.stale == 2  # a gap filled late: handed on
    assert not ledger.record(0, 3, attempt=1) and ledger.redundant_total == 1  # its resend: redundant
    restored = SinkLedger.from_state(ledger.state())  # a restarted sink remembers as much
    assert not restored.record(0, 4) and restored.duplicates_total == ledger.duplicates_total + 1
    for run in range(2, 3 + OLDER_RUNS_KEPT):
        ledger.record(run, 0)
    assert 0 not in ledger.older and len(ledger.older) == OLDER_RUNS_KEPT  # bounded
    assert not ledger.record(0, 4) and ledger.stale == 3  # forgotten: handed on as before


def test_a_sink_gives_up_a_gap_that_does_not_fill_and_stays_small():
    """A gap its producer gave up on never fills: the ledger stops waiting once SINK_MAX_AHEAD
    outputs sit above it (it kept every later output, and its report and journal grew with the
    mission); the seq counts as lost, and as received if it comes late after all."""
    import json

    from autopower.node.sequencing import SINK_MAX_AHEAD

    ledger = SinkLedger()
    for seq in range(3 * SINK_MAX_AHEAD):
        if seq != 5:  # never produced: its inputs were given up upstream
            assert ledger.record(0, seq, data=bytes([seq % 251]))
    assert ledger.given_up_total == 1 and ledger.gaps == 1 and ledger.contiguous == 3 * SINK_MAX_AHEAD
    assert not ledger.above and ledger.report().missing == ()
    assert len(json.dumps(ledger.state())) < 1000  # not every output since the gap
    assert ledger.record(0, 5, data=b"late")  # it came after all: delivered, not a duplicate
    assert ledger.late_total == 1 and ledger.gaps == 0 and ledger.duplicates_total == 0
    assert not ledger.record(0, 5, data=b"late")  # and once only
    assert ledger.duplicates_total == 1
    again = SinkLedger.from_state(ledger.state())
    assert (again.given_up_total, again.late_total, again.contiguous) == (1, 1, ledger.contiguous)
    # a gap that fills within the limit is waited for, as before
    ledger = SinkLedger()
    for seq in [0, *range(2, SINK_MAX_AHEAD), 1]:
        assert ledger.record(0, seq)
    assert ledger.given_up_total == 0 and ledger.contiguous == SINK_MAX_AHEAD


def test_pad():
    assert pad(b"ab", 4, "x") == b"ab\0\0"
    with pytest.raises(ProtocolError, match="exceeds the chain's declared"):
        pad(b"abcde", 4, "x")


def collect(team: SimTeam) -> dict:
    outputs: dict[str, list[tuple[int, int, bytes]]] = {}
    for rt in team.nodes.values():
        rt.listen(SinkListener(output=lambda chain, run, seq, data: outputs.setdefault(chain, []).append((run, seq, data))))
    return outputs


def check_exactly_once(team: SimTeam, outputs: dict) -> None:
    for chain in team.scenario.chains:
        source = team.nodes[chain.source].sources[chain.name]
        got = outputs.get(chain.name, [])
        seqs = [seq for run, seq, _ in got if run == source.run]
        assert sorted(seqs) == list(range(source.seq)), f"{chain.name}: outputs {len(seqs)} of {source.seq}"
        for _run, seq, data in got:  # the fake component's count carried across every move
            assert msgpack.unpackb(data) == [seq, seq + 1]
        ledger = team.nodes[chain.sink].sinks[chain.name]
        assert ledger.duplicates_total == 0 and ledger.contiguous == source.seq
    for rt in team.nodes.values():
        bad = {k: v for k, v in rt.errors.items() if k not in ("garbled",)}
        assert not bad, (rt.node, bad)


@pytest.mark.parametrize("order", ["fifo", "random"])
@pytest.mark.parametrize("topology", ["fully-connected", "relay"])
def test_hundreds_of_random_migrations_lose_and_duplicate_nothing(order, topology):
    rng = random.Random(42)
    sc = load_scenario("paper-fig7")
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0, topology=topology, media=FC, auto_replan=False),
                   rng=rng if order == "random" else None)
    outputs = collect(team)
    team.join()
    stages, nodes = sc.stage_names(), sc.node_names()
    moves = 0
    t = 1.0
    while moves < 300:
        team.run_until(t)
        for _ in range(rng.randint(1, 3)):  # several stages move at once, some twice in a row
            stage, node = rng.choice(stages), rng.choice(nodes)
            reply = team.coordinator.on_operator(MigrateCommand(stage=stage, to_node=node))
            assert reply.ok, reply.message
            moves += 1
        if rng.random() < 0.5:
            team.pump()  # let them land before time moves on
        t += rng.choice([0.05, 0.1, 0.25, 0.5])
    team.run_until(t + 10)
    assert team.coordinator.placing.migrations_done > 150
    assert not team.coordinator.placing.migrations
    check_exactly_once(team, outputs)


def test_frames_arriving_during_a_move_are_buffered_not_dropped():
    sc = load_scenario("paper-fig7")
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0, media=FC, auto_replan=False,
                                                pins={"Blob-2": "r2"}))
    outputs = collect(team)
    team.join()
    team.run_until(5.0)
    team.coordinator.on_operator(MigrateCommand(stage="Blob-2", to_node="laptop"))
    # deliver only the Prepare: the laptop now waits for the state while frames keep coming
    team.hub.pump(limit=1)
    assert team.nodes["laptop"].hosted["Blob-2"].lifecycle is Lifecycle.STARTING
    team.clock.set(5.25)
    team.nodes["r2"].on_timer()  # r2 still hosts it: runs this one itself
    team.run_until(20.0)
    assert team.coordinator.placing.placement["Blob-2"] == "laptop"
    check_exactly_once(team, outputs)


def test_real_mcl_state_survives_migration_bit_for_bit():
    """A migrated particle filter produces exactly what an unmigrated one does (state + RNG carried)."""
    sc = load_scenario("paper-fig7")
    off = frozenset(c.name for c in sc.chains if c.name != "Loc-2")

    def run(moves):
        team = SimTeam(sc, config=CoordinatorConfig(speed=1.0, media=FC, auto_replan=False), fake=False)
        team.coordinator.operating.adopt(OperatorSettings(disabled=tuple(sorted(off))))
        outputs = collect(team)
        team.join()
        for t, node in moves:
            team.run_until(t)
            assert team.coordinator.on_operator(MigrateCommand(stage="Loc-2", to_node=node)).ok
        team.run_until(40.0)
        return team, [(seq, data) for run, seq, data in outputs["Loc-2"]]

    ref_team, reference = run([])
    team, moved = run([(6.0, "r1"), (12.0, "r2"), (18.0, "r3"), (26.0, "laptop")])
    assert team.coordinator.placing.migrations_done == 4
    assert len(reference) >= 19 and moved == reference
    assert ref_team.coordinator.placing.placement["Loc-2"] != "r3"


def test_disable_and_enable_start_a_new_run():
    sc = load_scenario("paper-fig7")
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0, media=FC, auto_replan=False))
    outputs = collect(team)
    team.join()
    team.run_until(5.0)
    assert team.coordinator.on_operator(ChainCommand(chain="Blob-2", enabled=False)).ok
    team.run_until(8.0)
    assert "Blob-2" not in team.coordinator.placing.runs.running and "Blob-2" not in team.coordinator.placing.placement
    assert "Blob-2" not in team.nodes["r2"].sources
    before = team.nodes["r2"].feeds.totals["Blob-2"]
    produced_before = before.produced_total
    team.nodes["r2"].feeds.totals["Blob-2"] = replace(before, missed=3)  # as if it had run late
    assert team.coordinator.on_operator(ChainCommand(chain="Blob-2", enabled=True)).ok
    team.run_until(12.0)
    assert team.coordinator.placing.runs.running["Blob-2"] == 1
    # said, once: what the old run still held upstream is obsolete from here (the first runs are not)
    said = [e for e in team.coordinator.events if " starts run " in e]
    assert len(said) == 1 and said[0].endswith("Blob-2 starts run 1 with Blob-2 on laptop (the operator or a failed "
                                               "component had stopped the chain)"), said
    runner = team.nodes["r2"].sources["Blob-2"]
    assert runner.run == 1 and runner.produced_total > produced_before
    # missed periods count over every run, like produced_total (the summaries divide one by the other)
    assert runner.missed == 3 and team.nodes["r2"].status(1.0).sources["Blob-2"].missed == 3
    ledger = team.nodes["laptop"].sinks["Blob-2"]
    assert ledger.run == 1 and ledger.contiguous == runner.seq and ledger.duplicates_total == 0
    runs = sorted({run for run, _, _ in outputs["Blob-2"]})
    assert runs == [0, 1] and sorted(seq for run, seq, _ in outputs["Blob-2"] if run == 1) == list(range(runner.seq))


def test_a_chain_stopped_while_its_source_was_out_of_reach_goes_on_in_its_run():
    """r2 (Blob-2's source) out of the base station's sight: the chain stops, its stage on the laptop
    is released, and the frames r2 sent into a silent cut wait in its custody. Back in sight, the
    chain resumes its run (not a new one), the new instance starts from the oldest frame r2 holds,
    and every output of the run reaches the sink once: none is abandoned."""
    sc = load_scenario("paper-fig7")
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0, media=FC, auto_replan=False, pins={"Blob-2": "laptop"}))
    outputs = collect(team)
    team.join()
    team.run_exchanging_statuses(5.0)
    team.report_status()  # the base station knows r2's process (`NodeStatus.process`)
    team.cut_silently("r2", "laptop", one_way=True)  # frames and statuses from r2 vanish
    team.run_exchanging_statuses(6.0)
    for rt in team.nodes.values():  # r2's session expires: everyone takes it for gone
        if rt.node != "r2":
            rt.on_liveliness("r2", False)
    team.coordinator.on_liveliness("r2", False)
    team.run_exchanging_statuses(8.0)
    assert "Blob-2" not in team.coordinator.placing.runs.running
    waiting = {f.seq for f in team.nodes["r2"].custody.frames() if f.chain == "Blob-2" and f.target == 0}
    assert waiting  # inputs of run 0 the chain had not run when it stopped
    team.heal_silently("r2", "laptop")
    team.join(["r2"])
    assert "Blob-2" not in team.coordinator.placing.migrations  # not before r2's process says what it holds
    team.report_status()  # the same process: it holds run 0's position
    team.run_exchanging_statuses(15.0)
    assert team.coordinator.placing.runs.running["Blob-2"] == 0
    assert not [e for e in team.coordinator.events if " starts run " in e]
    assert [e for e in team.coordinator.events if "Blob-2 resumes run 0" in e]
    runner = team.nodes["r2"].sources["Blob-2"]
    assert runner.run == 0
    seqs = sorted(seq for run, seq, _ in outputs["Blob-2"] if run == 0)
    assert seqs == list(range(runner.seq))  # the waiting inputs were run, each output once
    assert team.nodes["laptop"].sinks["Blob-2"].duplicates_total == 0


def _killed_source_comes_back(saved: bool):
    """Blob-2 (source r2, its stage pinned on the laptop, the laptop its sink) runs; r2 is killed and
    restarted, with its predecessor's saved state or without (a process killed before its first
    snapshot), and joins again. Returns the team, the outputs, the new process and what the laptop's
    sink had of run 0 at the kill."""
    sc = load_scenario("paper-fig7")
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0, media=FC, auto_replan=False, pins={"Blob-2": "laptop"}))
    outputs = collect(team)
    team.join()
    team.run_exchanging_statuses(5.0)
    team.report_status()  # the base station knows r2's process
    old = team.nodes["r2"]
    assert team.coordinator.placing.runs.running["Blob-2"] == 0 and old.sources["Blob-2"].seq > 0
    state = old.resume_state() if saved else None
    delivered = {seq for run, seq, _ in outputs["Blob-2"] if run == 0}
    rt = team.restart("r2", state)  # the kill: the chain stops, its stage on the laptop is released
    team.run_exchanging_statuses(7.0)
    assert "Blob-2" not in team.coordinator.placing.runs.running
    team.join(["r2"])
    # r2 says nothing before its first plan (it takes its saved state up then): the base station
    # replans without its report, and Blob-2 waits for r2's process to say what it holds
    team.run_exchanging_statuses(9.0)
    assert rt.plan_view.plan is not None and rt.resuming.resumed == saved
    assert "Blob-2" in team.coordinator.placing.target and "Blob-2" not in team.coordinator.placing.migrations
    assert "Blob-2" not in team.coordinator.placing.runs.running
    team.report_status()  # it says
    team.run_exchanging_statuses(15.0)
    return team, outputs, rt, delivered


def test_a_source_robot_restarted_without_its_position_starts_a_new_run():
    """The case tests/e2e/test_supervision.py caught: r2 killed before its first resume snapshot
    restarts without its sources' positions and sources Blob-2 from seq 0. Its status says it
    resumed nothing and comes from another process, so the chain starts run 1: resumed in run 0,
    those seqs named inputs the sink had already delivered (duplicates)."""
    team, outputs, rt, _ = _killed_source_comes_back(saved=False)
    status = rt.status(1.0)
    assert status.resumed == {} and status.process != 0
    assert team.coordinator.placing.runs.running["Blob-2"] == 1
    said = [e for e in team.coordinator.events if "Blob-2 starts run 1" in e]
    assert said and said[0].endswith("(its source robot's process does not hold the run's position)"), said
    assert not [e for e in team.coordinator.events if "Blob-2 resumes" in e]
    runner = rt.sources["Blob-2"]
    assert runner.run == 1 and runner.seq > 0
    assert sorted(seq for run, seq, _ in outputs["Blob-2"] if run == 1) == list(range(runner.seq))
    sink = team.nodes["laptop"].sinks["Blob-2"]
    assert sink.run == 1 and sink.duplicates_total == 0


def test_a_source_robot_restarted_with_its_position_goes_on_in_its_run():
    """r2 killed and restarted from its saved state: its status says it resumed Blob-2's run 0, so
    the chain goes on in run 0, from the seq after the last the killed process made: nothing the
    killed process had delivered comes again, and nothing of the run is abandoned."""
    team, outputs, rt, delivered = _killed_source_comes_back(saved=True)
    assert rt.status(1.0).resumed == {"Blob-2": 0, "Loc-2": 0}
    assert team.coordinator.placing.runs.running["Blob-2"] == 0
    assert [e for e in team.coordinator.events if "Blob-2 resumes run 0" in e]
    assert not [e for e in team.coordinator.events if " starts run " in e]
    runner = rt.sources["Blob-2"]
    assert runner.run == 0 and runner.seq > max(delivered) + 1
    seqs = sorted(seq for run, seq, _ in outputs["Blob-2"] if run == 0)
    assert seqs == list(range(runner.seq)), set(range(runner.seq)) - set(seqs)  # each once, none abandoned
    assert team.nodes["laptop"].sinks["Blob-2"].duplicates_total == 0


def test_a_source_robot_restarted_unseen_starts_a_new_run_and_loses_no_new_input():
    """r2 restarts within the lease (its liveliness never goes: a supervisor that restarts at once),
    killed before its first snapshot. The base station learns it from r2's status, which names
    another process and no resumed run: r2 leaves and comes back, and Blob-2 starts run 1. Left in
    run 0, the new process would name its captures 0, 1, ... again and the laptop's gate would drop
    them as copies of what the old process sent: new data lost, and counted nowhere as lost. A late
    status of the old process (relayed, queued) then changes nothing."""
    from autopower.node.ports import NodeStores

    sc = load_scenario("paper-fig7")
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0, media=FC, auto_replan=False, pins={"Blob-2": "laptop"}))
    outputs = collect(team)
    team.join()
    team.run_exchanging_statuses(5.0)
    team.report_status()
    old_status = team.nodes["r2"].status(10.0)
    for handle in team.subscriptions.pop("r2"):  # the kill; nobody sees r2's liveliness go
        handle.close()
    rt = team._start("r2", NodeStores(resume_from=None))
    for node in team.present - {"r2"}:
        rt.on_liveliness(node, True)
    team.coordinator.on_status(rt.status(0.0))  # its first status (an agent's go out before it has a plan):
    team.pump()                                   # another process, no plan, nothing resumed
    for t in range(6, 15):
        team.run_exchanging_statuses(float(t))
        team.report_status()
    team.coordinator.on_status(old_status)  # late: older than what the base station holds
    team.run_exchanging_statuses(16.0)
    assert team.coordinator.placing.runs.running["Blob-2"] == 1
    assert team.coordinator.statuses["r2"].process == rt.status(1.0).process
    runner = rt.sources["Blob-2"]
    assert runner.run == 1 and runner.seq > 0
    assert sorted(seq for run, seq, _ in outputs["Blob-2"] if run == 1) == list(range(runner.seq))
    stage = team.nodes["laptop"].hosted["Blob-2"]
    assert stage.run == 1 and stage.gate.duplicates == 0
    assert team.nodes["laptop"].sinks["Blob-2"].duplicates_total == 0
    assert any("r2 runs another process" in e for e in team.coordinator.events)


def test_a_sink_hands_an_older_runs_output_on_once():
    """The node's side of the rule above: the first copy of a run-0 output after run 1 began
    reaches `on_output` (stale, no error), a second one is a duplicate-output error, not handed on."""
    from autopower.protocol import ChainFrame

    team = SimTeam(load_scenario("paper-fig7"), config=CoordinatorConfig(speed=1.0, auto_replan=False))
    team.join()
    team.run_until(2.0)
    r1 = team.nodes["r1"]
    chain = r1.chains["Loc-1"]
    got = []
    r1.listen(SinkListener(output=lambda c, run, seq, data: got.append((c, run, seq))))

    def frame(run: int, seq: int) -> ChainFrame:
        return ChainFrame(chain="Loc-1", run=run, seq=seq, target=len(chain.stages), t_virtual=0.0,
                          t_unix=r1.wall(), payload_len=1, payload=b"x")

    r1.sinks.pop("Loc-1", None)
    for seq in (0, 1):
        r1.sinking.take(chain, frame(0, seq))
    r1.sinking.take(chain, frame(1, 0))
    r1.sinking.take(chain, frame(0, 5))
    r1.sinking.take(chain, frame(0, 5))
    assert got == [("Loc-1", 0, 0), ("Loc-1", 0, 1), ("Loc-1", 1, 0), ("Loc-1", 0, 5)]
    assert r1.errors.get("duplicate-output") == 1 and r1.counters.get("stale-output", 0) + \
        r1.errors.get("stale-output", 0) == 1
