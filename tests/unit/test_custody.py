"""Custody: frames lost on a silently cut link are resent until their consumer has them.

The team tests cut a link without telling anyone (what a pulled cable or a radio out of range
does: the frames in flight vanish) and check that every output still reaches its sink exactly
once, that a stateful stage never runs an input twice (the fake component raises if it does),
and that it is the consumers' reports that bring the frames back.
"""

from __future__ import annotations

import dataclasses

import pytest
from hypothesis import given, settings, strategies as st

from autopower.basestation.coordinator import CoordinatorConfig
from autopower.model.loading import load_scenario
from autopower.node.custody import Custody, Report, hop_key, is_consumed, parse_hop_key
from autopower.node.ports import SinkListener
from autopower.node.sequencing import MAX_MISSING, SequenceGate, SinkLedger, in_ranges, missing_between, ranges_of
from autopower.node.stages import Lifecycle
from autopower.protocol import Ack, ChainFrame, Consumed, NodeStatus, decode, encode
from tests.unit.sim_team import SimTeam
from tests.unit.test_agent_migration import FC, check_exactly_once, collect


def frame(seq: int, run: int = 0, target: int = 0, chain: str = "Blob-2", size: int = 10) -> ChainFrame:
    return ChainFrame(chain=chain, run=run, seq=seq, target=target, t_virtual=0.0, t_unix=0.0, payload_len=size,
                      payload=bytes(size))


def report(next_seq: int, max_seq: int, missing=(), run: int = 0, generation: int = 1, t: float = 10.0,
           node: str = "laptop") -> Report:
    return Report(node=node, t_unix=t, consumed=Consumed(run=run, generation=generation, next_seq=next_seq,
                                                         max_seq=max_seq, missing=ranges_of(missing)))


# ---- the pieces ------------------------------------------------------------------------------------


def test_hop_keys_round_trip_and_reject_garbage():
    assert parse_hop_key(hop_key("Loc-1", 1)) == ("Loc-1", 1)
    assert parse_hop_key("a#b#2") == ("a#b", 2)
    for bad in ("Loc-1", "#1", "Loc-1#", "Loc-1#-1", "Loc-1#x"):
        assert parse_hop_key(bad) is None


def test_consumed_means_below_the_prefix_or_seen_and_not_missing():
    c = Consumed(run=1, generation=0, next_seq=5, max_seq=9, missing=((6, 6), (8, 8)))
    assert [s for s in range(12) if is_consumed(c, 1, s)] == [0, 1, 2, 3, 4, 5, 7, 9]
    assert is_consumed(c, 0, 100)  # an older run: obsolete
    assert not is_consumed(c, 2, 0)  # a newer run: the consumer has not started it


def test_acknowledged_frames_leave_custody_and_lost_ones_are_resent_once_a_late_report_lacks_them():
    custody = Custody(resend_after_s=1.0)
    for seq in range(5):
        custody.keep(frame(seq), now=0.0)
    custody.on_report("Blob-2", 0, report(next_seq=2, max_seq=4, missing=(2,), t=0.5))
    assert len(custody) == 3  # 0, 1 run; 2 missing; 3, 4 wait behind it in the gate: kept until run
    assert custody.due(now=0.6) == []  # the report is too early to call seq 2 lost
    custody.on_report("Blob-2", 0, report(next_seq=2, max_seq=6, missing=(2,), t=1.2))
    due = custody.due(now=1.3)
    assert [(node, held.frame.seq) for node, held in due] == [("laptop", 2)]  # not 3, 4: it has them
    resent, again = custody.resend(due[0][1], now=1.3)
    assert again and resent.attempt == 1 and resent.seq == 2
    assert custody.due(now=1.4) == []  # sent again just now: wait for a report after that
    custody.on_report("Blob-2", 0, report(next_seq=7, max_seq=6, t=2.0))
    assert len(custody) == 0 and custody.bytes == 0 and custody.evicted == 0


def test_frames_behind_on_a_slow_link_are_not_resent_while_the_consumer_keeps_receiving():
    """The simulator's slowed links (seeds 16, 110, 1008, 1411, 2524): a radio slowed below the chain's
    rate delivered every frame, late; a second after each was sent it was resent behind its original,
    so the slow link carried everything twice and its backlog never drained. A frame sent once and
    past the consumer's highest seq waits while that seq rises; a gap below it is resent as ever, and
    a consumer that stops receiving gets the rest a second after its reception stopped."""
    custody = Custody(resend_after_s=1.0)
    for seq in range(10):
        custody.keep(frame(seq), now=seq * 0.05)
    custody.on_report("Blob-2", 0, report(next_seq=0, max_seq=-1, t=0.5))
    custody.on_report("Blob-2", 0, report(next_seq=1, max_seq=1, t=1.2))  # it rose: the link delivers
    assert custody.due(1.3) == []  # 2-4 were sent over a second ago, but are behind 1 on the link
    custody.on_report("Blob-2", 0, report(next_seq=2, max_seq=3, missing=(2,), t=1.8))
    due = custody.due(1.9)
    assert [h.frame.seq for _, h in due] == [2]  # the gap, not 4-9 behind on the link
    custody.resend(due[0][1], now=1.9)
    custody.on_report("Blob-2", 0, report(next_seq=2, max_seq=5, missing=(2,), t=2.3))
    assert custody.due(2.4) == []
    custody.on_report("Blob-2", 0, report(next_seq=2, max_seq=5, missing=(2,), t=3.4))  # nothing new since 2.3
    due = custody.due(3.5)
    assert [h.frame.seq for _, h in due] == [2, 6, 7, 8, 9]  # the rest is lost now
    for _, held in due:
        custody.resend(held, now=3.5)
    # resent copies arriving raise the highest seq, and say nothing of where the others are: a frame
    # already resent is sent again a second later, as ever
    custody.on_report("Blob-2", 0, report(next_seq=2, max_seq=7, missing=(2,), t=4.6))
    assert [h.frame.seq for _, h in custody.due(4.7)] == [2, 8, 9]
    custody.on_report("Blob-2", 0, report(next_seq=0, max_seq=-1, generation=2, t=5.0))  # a new instance
    assert [h.frame.seq for _, h in custody.due(5.1)] == [2, 3, 4, 5, 6, 7, 8, 9]  # (0 and 1 were run)


def test_inputs_waiting_in_a_gate_stay_in_custody_until_run_and_go_to_the_stages_next_instance():
    """A 30-robot simulated fleet (seed 0, 40 % loss on laptop-r21): Blob-21's gate on the laptop
    held 60, 62, 64, 65 behind the lost 59, and its report freed them from the camera's custody. The
    stage moved to r21 with them, back towards the laptop, and the transfer was given up (lost on the
    link): the stage restarted without state, 60 and the rest were in no one's hands, and the new
    instance ran 59 then 61 (its component raised; 48 outputs lost). Waiting is not running: they
    stay with their producer until a gate has run them, and the next instance gets them."""
    custody = Custody(resend_after_s=1.0)
    for seq in range(59, 68):
        custody.keep(frame(seq), now=0.0)
    waiting = report(next_seq=59, max_seq=67, missing=(59, 61, 63, 66), generation=51, t=0.5)
    custody.on_report("Blob-2", 0, waiting)
    assert len(custody) == 9 and custody.floor("Blob-2", 0, 0, 68) == 59
    custody.on_report("Blob-2", 0, report(next_seq=59, max_seq=67, missing=(59, 61, 63, 66), generation=51, t=1.5))
    assert sorted(held.frame.seq for _, held in custody.due(1.6)) == [59, 61, 63, 66]  # not what waits there
    fresh = report(next_seq=59, max_seq=68, missing=range(59, 68), generation=99, t=2.0, node="laptop")
    custody.on_report("Blob-2", 0, fresh)  # a new instance, started without state: has none of them
    assert sorted(held.frame.seq for _, held in custody.due(2.1)) == list(range(59, 68))
    custody.on_report("Blob-2", 0, report(next_seq=68, max_seq=67, generation=99, t=3.0))
    assert len(custody) == 0 and custody.evicted == 0


def test_a_report_speaks_only_for_what_had_left_its_consumers_queue():
    # the consumer's loop had frames waiting 2.5 s when it reported: frames sent after 10.0 - 2.5
    # may still be in its queue, so its report does not call them lost yet
    custody = Custody(resend_after_s=1.0)
    custody.keep(frame(0), now=5.0)
    custody.keep(frame(1), now=7.0)
    lagging = report(next_seq=0, max_seq=-1, t=10.0)
    custody.on_report("Blob-2", 0, Report(node="laptop", t_unix=10.0, consumed=lagging.consumed, queue_wait_s=2.5))
    assert [held.frame.seq for _, held in custody.due(now=10.0)] == [0]  # sent at 5.0: had 4 s to get in
    custody.on_report("Blob-2", 0, Report(node="laptop", t_unix=10.5, consumed=lagging.consumed, queue_wait_s=2.6))
    assert [held.frame.seq for _, held in custody.due(now=10.5)] == [0]  # 10.5 - 2.6 < 7.0 + 1.0: seq 1 waits
    custody.on_report("Blob-2", 0, Report(node="laptop", t_unix=11.0, consumed=lagging.consumed, queue_wait_s=0.0))
    assert [held.frame.seq for _, held in custody.due(now=11.0)] == [0, 1]  # its queue is empty: lost


def test_a_frame_not_on_the_wire_is_not_resent_and_reports_of_old_generations_are_ignored():
    custody = Custody(resend_after_s=0.0)
    custody.keep(frame(0), now=0.0)
    custody.mark(frame(0), None)  # held back: no route to its consumer
    custody.on_report("Blob-2", 0, report(next_seq=0, max_seq=3, missing=(0,), t=5.0, generation=2))
    assert custody.due(now=5.0) == []
    custody.mark(frame(0), 5.0)
    custody.on_report("Blob-2", 0, report(next_seq=9, max_seq=9, t=9.0, generation=1))  # a stale instance
    assert len(custody) == 1
    custody.on_report("Blob-2", 0, report(next_seq=0, max_seq=3, missing=(0,), t=9.0, generation=2))
    assert [held.frame.seq for _, held in custody.due(now=9.0)] == [0]


def test_a_frame_held_back_for_want_of_a_route_goes_first_as_itself_and_only_then_as_a_resend():
    custody = Custody(resend_after_s=1.0)
    custody.keep(frame(0), now=0.0)
    custody.held_back(frame(0))  # its first send found no route: no copy left this node
    custody.on_report("Blob-2", 0, report(next_seq=0, max_seq=3, missing=(0,), t=2.0))
    [(node, held)] = custody.due(now=2.0)
    first, again = custody.resend(held, now=2.0)
    assert node == "laptop" and not again and first.attempt == 0 and custody.resent == 0
    custody.on_report("Blob-2", 0, report(next_seq=0, max_seq=5, missing=(0,), t=3.5))  # lost on the way too
    [(_, held)] = custody.due(now=3.5)
    second, again = custody.resend(held, now=3.5)
    assert again and second.attempt == 1 and custody.resent == 1


def test_a_held_result_sent_when_its_sink_came_back_is_on_the_air_and_its_next_copy_a_resend():
    """CI, test_supervision: the laptop held r2's poses while r2 was killed (no route to the sink),
    flushed them when r2 was back, and when r2's report still lacked one it sent it again as a
    first copy (attempt 0): the flushed copy arrived too, and r2's sink counted a duplicate instead
    of dropping a redundant resend. A copy that left through the hold's flush is on the air."""
    custody = Custody(resend_after_s=1.0)
    result = frame(7, target=1)
    custody.keep(result, now=0.0, sent=False, result=True)
    custody.held_back(result)  # emit: no route to the sink
    custody.mark(result, None)  # held
    custody.mark(result, 2.0)  # flushed: the sink is routed again
    custody.on_report("Blob-2", 1, report(next_seq=0, max_seq=9, missing=(7,), t=3.5))
    [(_, held)] = custody.due(now=3.5)
    copy, again = custody.resend(held, now=3.5)
    assert again and copy.attempt == 1 and custody.resent == 1


def test_inputs_produced_while_their_consumer_was_out_of_reach_are_the_chains_work_when_they_go():
    """A robot cut from the host of its chain's stage keeps the inputs it produces meanwhile; when
    the route is back they go for the first time. Their radio and their runs are the chain's steady
    work, which the model prices, not an overhead of the fault: metered as such, not as recovery
    (a first copy reaches no consumer twice, so its output is no second copy either)."""
    sc = load_scenario("paper-fig7")
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0, media=FC, auto_replan=False, pins={"Loc-2": "laptop"}))
    outputs = collect(team)
    team.join()
    r2, laptop = team.nodes["r2"], team.nodes["laptop"]
    plan = r2.plan_view.plan
    next_status = [0.5]

    def tick(t: float) -> None:
        if t >= next_status[0]:
            team.exchange_statuses()
            next_status[0] = t + 0.5

    team.run_until(9.7, on_tick=tick)
    r2.plan_view.override_placement(dict(plan.placement), {"laptop"})  # no route to the laptop
    team.run_until(14.5, on_tick=tick)
    held_back = [h for (chain, _), hop in r2.custody.hops.items() if chain == "Loc-2" for h in hop.values()
                 if not h.on_air]
    assert len(held_back) >= 2  # the scans of t = 10 and 12
    r2.plan_view.set_plan(plan)  # the route is back
    team.run_until(30.0, on_tick=tick)
    for _ in range(6):
        team.clock.advance(0.5)
        team.exchange_statuses()
    produced = r2.sources["Loc-2"].seq
    assert sorted(seq for _, seq, _ in outputs["Loc-2"]) == list(range(produced))
    assert r2.sinks["Loc-2"].duplicates_total == 0
    assert not [k for k, joules in r2.meter.energy_j.items() if "recovery" in k and joules > 0], r2.meter.energy_j
    assert r2.custody.resent == 0 and r2.counters.get("resent-frames", 0) == 0
    assert r2.counters.get("held-back-frames-sent", 0) >= len(held_back)
    assert laptop.counters.get("resent-frames", 0) == 0


def test_inputs_that_waited_through_a_reconfiguration_run_as_its_backlog_where_the_stage_restarts():
    """r2 is cut from the laptop, which ran Loc-2; a subgroup restarts Loc-2 on r2 (cold). The scans
    r2 held meanwhile were captured while the model priced Loc-2 on the laptop: running them on r2
    is the reconfiguration's backlog, metered apart (`cpu_backlog`); the scans captured from the
    restart on are the plan's steady work (`cpu_busy`). Each ran once, and every pose arrived once.
    (Live, the demo's all-cut ran such backlogs as chain work: +1.2 % on the robots' steady
    energy against the model.)"""
    from autopower.protocol import Assign

    sc = load_scenario("paper-fig7")
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0, media=FC, auto_replan=False, pins={"Loc-2": "laptop"}))
    outputs = collect(team)
    team.join()
    r2 = team.nodes["r2"]
    team.run_until(9.7)
    team.exchange_statuses()
    r2.plan_view.override_placement({}, {"laptop"})  # no route to the laptop: r2 holds its scans
    team.run_until(14.5)
    waited = sorted(h.frame.seq for (chain, _), hop in r2.custody.hops.items() if chain == "Loc-2"
                    for h in hop.values() if not h.on_air)
    assert len(waited) >= 2  # the scans of t = 10, 12 and 14
    restart_t = r2.now()
    r2.hosting.on_assign(Assign(stage="Loc-2", generation=10**9, chain="Loc-2", run=r2.plan.running["Loc-2"],
                                resume_seq=None))
    r2.plan_view.override_placement({"Loc-2": "r2"}, {"laptop"})
    team.run_until(30.0)
    for _ in range(6):
        team.clock.advance(0.5)
        team.exchange_statuses()
    latency = sc.components["Loc"].latency_s[r2.platform.name]
    per_run = (r2.platform.busy_w - r2.platform.idle_w) * latency
    hosted = r2.hosted["Loc-2"]
    assert hosted.placed_t == pytest.approx(restart_t)
    captured_after = r2.sources["Loc-2"].seq - (max(waited) + 1)  # scans of t = 16 .. 30
    assert r2.meter.energy_j["cpu_backlog"] == pytest.approx(len(waited) * per_run)
    assert r2.meter.energy_j["cpu_busy"] == pytest.approx(captured_after * per_run)
    assert hosted.runs == len(waited) + captured_after
    seqs = sorted(seq for _, seq, _ in outputs["Loc-2"])
    assert seqs[-len(waited) - captured_after:] == list(range(min(waited), r2.sources["Loc-2"].seq))


def test_custody_is_bounded_and_counts_what_it_gives_up():
    custody = Custody(max_frames_per_hop=3, max_bytes=10_000, max_age_s=60.0)
    for seq in range(5):
        custody.keep(frame(seq), now=0.0)
    assert len(custody) == 3 and custody.evicted == 2
    custody.keep(frame(0, chain="Blob-3", size=9_990), now=1.0)  # over the byte budget: the oldest go
    assert custody.bytes == 10_000 and custody.evicted == 4 and len(custody) == 2
    custody.due(now=100.0)  # too old to be worth resending
    assert len(custody) == 0 and custody.evicted == 6
    custody.keep(frame(7), now=200.0)
    custody.forget_chain("Blob-2")  # the chain stopped: not a loss
    assert len(custody) == 0 and custody.evicted == 6 and custody.acknowledged == 1


def test_a_source_has_room_until_its_hop_is_full_and_behind_and_a_stalled_chain_does_not_stop_the_other():
    custody = Custody(max_frames_per_hop=100, max_bytes=1_000, resend_after_s=1.0)
    for seq in range(5):  # a stalled camera chain: nothing acknowledged
        assert custody.has_room("Blob-2", 0, 100, now=0.0, sharers=2)
        custody.keep(frame(seq, size=100), now=0.0)
    # its half of the bytes is full, but its oldest frame is younger than a resend: only the
    # acknowledgements are on their way (keep evicts the oldest, as a fast consumer has run it)
    assert custody.has_room("Blob-2", 0, 100, now=0.5, sharers=2)
    assert not custody.has_room("Blob-2", 0, 100, now=1.0, sharers=2)  # behind: no more captures
    assert custody.has_room("Blob-2", 0, 100, now=1.0, sharers=1)  # alone on the node it could take all
    assert custody.has_room("Loc-2", 0, 100, now=1.0, sharers=2)  # the other source's half is free
    for seq in range(4):
        custody.keep(frame(seq, chain="Loc-2", size=100), now=1.0)
    assert not custody.has_room("Loc-2", 0, 200, now=2.0, sharers=2)
    custody.on_report("Blob-2", 0, report(next_seq=3, max_seq=4))  # the blob finder ran 0-2
    assert custody.hop_bytes == {("Blob-2", 0): 200, ("Loc-2", 0): 400} and custody.evicted == 0
    assert custody.has_room("Blob-2", 0, 100, now=2.0, sharers=2)
    small = Custody(max_frames_per_hop=2)
    small.keep(frame(0), now=0.0)
    small.keep(frame(1), now=0.0)
    assert not small.has_room("Blob-2", 0, 1, now=5.0)  # the frames per hop bound too


def test_gate_reports_its_gaps_and_gives_up_a_gap_that_stays_open():
    gate = SequenceGate(next_seq=0, max_pending=4)
    assert gate.report(0, 3) == Consumed(run=0, generation=3, next_seq=0, max_seq=-1, missing=())
    gate.offer(0, "a")
    for seq in (2, 4):
        gate.offer(seq, seq)
    assert gate.report(0, 3) == Consumed(run=0, generation=3, next_seq=1, max_seq=4, missing=((1, 1), (3, 3)))
    assert gate.offer(3, 3) == [] and gate.offer(5, 5) == []
    assert gate.offer(6, 6) == [2, 3, 4, 5, 6]  # seq 1 never came: given up after 4 waited behind it
    assert gate.skipped == 1 and gate.next_seq == 7
    assert SequenceGate().report(0, 1) is None  # starts wherever its first input is


def test_gate_times_a_gap_from_when_it_became_the_oldest_not_from_the_first_gap_it_had():
    """Under steady loss a gate always has some gap open; each is given its own time for its resend."""
    gate = SequenceGate(next_seq=0, max_gap_s=10.0)
    gate.offer(0, 0, now=0.0)
    gate.offer(2, 2, now=1.0)  # seq 1 missing from t=1
    gate.offer(4, 4, now=2.0)  # seq 3 missing too
    assert gate.offer(1, 1, now=8.0) == [1, 2]  # seq 1's resend came after 7 s; seq 3 is now the oldest gap
    assert gate.offer(5, 5, now=12.0) == [] and gate.skipped == 0  # 11 s after the first gap: seq 3 waits on
    assert gate.offer(3, 3, now=15.0) == [3, 4, 5]
    gate.offer(7, 7, now=16.0)  # seq 6 never comes
    assert gate.offer(8, 8, now=26.5) == [7, 8] and gate.skipped == 1  # given up 10.5 s after it was the oldest


def test_gate_waits_on_a_gap_while_its_producer_says_it_still_holds_it():
    """A frame's floor is its producer's lowest unacknowledged seq: equal to the gap, the producer is
    resending it (custody), however many resends a lossy link ate; the gap is given up only without
    that word for the gate's limit (a producer that died with the frame, or one that gave it up)."""
    gate = SequenceGate(next_seq=0, max_gap_s=10.0)
    gate.offer(0, 0, now=0.0)
    for t in range(1, 30):  # seq 1 lost, again and again; the producer's later frames say it holds it
        assert gate.offer(t + 1, t + 1, floor=1, now=float(t)) == []
    assert gate.skipped == 0 and gate.offer(1, 1, resent=True, now=30.0) == list(range(1, 31))
    gate.offer(32, 32, floor=31, now=31.0)  # seq 31 missing, its producer holds it ...
    assert gate.offer(33, 33, floor=None, now=40.0) == []
    assert gate.offer(34, 34, floor=None, now=41.5) == [32, 33, 34]  # ... then no word for 10.5 s
    assert gate.skipped == 1


def test_a_result_of_an_older_run_leaves_custody_only_once_its_sink_has_it():
    """Sweep seeds 91 and 372: r1 held two of Blob-2's run-0 results, sent into a laptop freeze; the chain
    started run 1; the laptop's sink, reporting run 1, made them obsolete (`is_consumed`: an older run)
    and r1 dropped them undelivered. An older run's result is obsolete only once its sink has forgotten
    that run; until then it is kept, resent while its sink's report of that run lacks it, and let go
    once it has it."""
    custody = Custody(resend_after_s=1.0)
    for seq in (75, 76):
        custody.keep(frame(seq, run=0, target=1), now=19.5, result=True)
        custody.mark(frame(seq, run=0, target=1), 19.5)
    run1 = Consumed(run=1, generation=0, next_seq=2, max_seq=1, missing=())
    custody.on_report("Blob-2", 1, Report(node="laptop", t_unix=21.4, consumed=run1))
    assert len(custody) == 2  # the sink said nothing of run 0 (it never saw it): kept, and resent
    assert sorted(held.frame.seq for _, held in custody.due(21.5)) == [75, 76]
    run0 = Consumed(run=0, generation=0, next_seq=75, max_seq=76, missing=((75, 75),))  # it has 76
    custody.on_report("Blob-2", 1, Report(node="laptop", t_unix=23.0, consumed=run1, older={0: run0}))
    assert [held.frame.seq for hop in custody.hops.values() for held in hop.values()] == [75]
    # a sink that has forgotten run 0 (it remembers four runs since, all reported) can take it no more
    forgot = {r: Consumed(run=r, generation=0, next_seq=0, max_seq=-1, missing=()) for r in (1, 2, 3, 4)}
    custody.on_report("Blob-2", 1, Report(node="laptop", t_unix=24.0, consumed=Consumed(
        run=5, generation=0, next_seq=0, max_seq=-1, missing=()), older=forgot))
    assert len(custody) == 0


def test_a_sink_reports_the_older_runs_it_remembers_even_one_it_saw_nothing_of_before():
    ledger = SinkLedger()
    for seq in range(3):
        ledger.record(1, seq)
    ledger.record(2, 0)  # run 2 starts: run 1 is remembered
    assert not ledger.record(0, 5)  # run 0's result, held upstream all along: handed on (stale), remembered
    assert not ledger.record(0, 5)  # and a second copy is told from it
    assert ledger.duplicates_total == 1
    assert ledger.older_reports() == (
        Consumed(run=0, generation=0, next_seq=0, max_seq=5, missing=((0, 4),)),
        Consumed(run=1, generation=0, next_seq=3, max_seq=2, missing=()))


def test_sink_ledger_tells_redundant_resends_from_real_duplicates():
    ledger = SinkLedger()
    assert ledger.report() is None
    assert ledger.record(0, 0) and ledger.record(0, 2, attempt=1)
    assert ledger.report() == Consumed(run=0, generation=0, next_seq=1, max_seq=2, missing=((1, 1),))
    assert not ledger.record(0, 2)  # the late original of a resent output
    assert not ledger.record(0, 0, attempt=1)  # a resend of one that had arrived
    assert (ledger.redundant_total, ledger.duplicates_total) == (2, 0)
    assert not ledger.record(0, 0)  # produced twice: a bug, counted as such
    assert ledger.duplicates_total == 1
    for seq in range(3, 3 + 2 * MAX_MISSING + 10, 2):
        ledger.record(0, seq)
    assert len(ledger.report().missing) == MAX_MISSING


def test_acknowledgements_reach_the_producers_and_no_one_else():
    sc = load_scenario("paper-fig7")
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0, media=FC, auto_replan=False,
                                                pins={"Blob-2": "laptop"}))
    team.join()
    team.run_until(3.0)
    acks = {dest: decode(encode(ack), Ack) for dest, ack in team.nodes["laptop"].acks().items()}
    assert hop_key("Blob-2", 0) in acks["r2"].consumed  # r2's camera feeds Blob-2 on the laptop
    produced = team.nodes["r2"].sources["Blob-2"].seq
    taken = acks["r2"].consumed[hop_key("Blob-2", 0)]
    assert taken.max_seq == produced - 1 and taken.missing == ()  # every frame had ...
    # ... and run, up to the first whose result the laptop holds in memory only (its sink's own
    # acknowledgement comes with its next status)
    unsafe = team.nodes["laptop"].holds.unsafe_floor("Blob-2", 1, taken.run)
    assert taken.next_seq == (produced if unsafe is None else unsafe)
    assert acks["r2"].consumed[hop_key("Blob-2", 1)].next_seq == produced
    placement = team.nodes["laptop"].plan.placement
    for dest, ack in acks.items():
        for key in ack.consumed:
            chain = sc.chain(parse_hop_key(key)[0])
            feeders = {chain.source, *(placement[s.name] for s in chain.stages)}
            assert dest in feeders, f"{dest} hears {key}, a chain it does not feed"


# ---- a team with a silent cut ----------------------------------------------------------------------------


def run_with_blackout(pins: dict[str, str], cut: tuple[str, str], *, acks: bool, until: float = 30.0,
                      one_way: bool = False):
    sc = load_scenario("paper-fig7")
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0, media=FC, auto_replan=False, pins=pins))
    outputs = collect(team)
    team.join()
    next_status = [0.5]

    def tick(t: float) -> None:
        if 10.0 <= t < 14.5:  # two MCL periods, eighteen camera frames
            team.cut_silently(*cut, one_way=one_way)  # frames in flight vanish; nobody is told
        else:
            team.heal_silently(*cut)
        if acks and t >= next_status[0]:
            team.exchange_statuses()
            next_status[0] = t + 0.5

    team.run_until(until, on_tick=tick)
    if acks:
        for _ in range(6):  # the last reports after the last frames
            team.clock.advance(0.5)
            team.exchange_statuses()
    return team, outputs


@pytest.mark.parametrize("pins, what", [
    ({"Blob-2": "laptop"}, "camera frames to an off-loaded blob finder"),
    ({"Loc-2": "laptop"}, "scans to an off-loaded MCL and its poses back"),
])
def test_frames_lost_on_a_silent_cut_are_resent_and_arrive_exactly_once(pins, what):
    team, outputs = run_with_blackout(pins, ("r2", "laptop"), acks=True)
    assert team.lost_in_cuts > 0, f"the cut lost nothing ({what}): the test proves nothing"
    check_exactly_once(team, outputs)  # the fake MCL raises if it ever runs an input twice or skips one
    resent = sum(rt.custody.resent for rt in team.nodes.values())
    assert resent >= 1
    assert all(rt.custody.evicted == 0 for rt in team.nodes.values())
    for rt in team.nodes.values():  # everything consumed has been acknowledged
        assert len(rt.custody) <= 2, (rt.node, rt.custody.hops)


def test_a_lost_mcl_pose_is_resent_from_custody_not_recomputed():
    # only the poses going back to r2 are lost: the scans got through and MCL ran on them
    team, outputs = run_with_blackout({"Loc-2": "laptop"}, ("laptop", "r2"), acks=True, one_way=True)
    laptop = team.nodes["laptop"]
    assert team.lost_in_cuts > 0
    assert laptop.counters.get("resent-frames", 0) >= 1  # the laptop resent poses it had computed
    assert team.nodes["r2"].counters.get("resent-frames", 0) == 0  # no scan was lost: none resent
    assert laptop.hosted["Loc-2"].runs == team.nodes["r2"].sources["Loc-2"].seq  # each scan run once
    check_exactly_once(team, outputs)


def run_with_backlog(*, say_wait: bool, drop_every: int = 7, r2_holds: int | None = None):
    """The laptop's loop falls 3 s behind for a while (its frames wait in its event queue, and one
    in ``drop_every`` finds the queue full and is dropped; 0: none is), then catches up.

    ``r2_holds``: the camera frames r2's custody may hold for one hop (its `max_frames_per_hop`)."""
    sc = load_scenario("paper-fig7")
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0, media=FC, auto_replan=False, pins={"Blob-2": "laptop"}))
    outputs = collect(team)
    team.join()
    if r2_holds is not None:
        team.nodes["r2"].custody.max_frames_per_hop = r2_holds
    laptop, data_key = team.nodes["laptop"], team.keys.node_data("laptop")
    backlog: list[tuple[float, str, bytes]] = []  # (queued at, key, payload): the laptop's bulk queue
    arrived, dropped, send = [0], [0], team._send

    def slow_laptop(sender, dest, key, payload, bus):
        if dest == "laptop" and key == data_key and 10.0 <= team.clock.t < 20.0:
            arrived[0] += 1
            if not drop_every or arrived[0] % drop_every:
                backlog.append((team.clock.wall(), key, payload))
            else:
                dropped[0] += 1  # "queue-full": lost on arrival
            return
        send(sender, dest, key, payload, bus)

    team._send = slow_laptop
    next_status = [0.5]

    def tick(t: float) -> None:
        now = team.clock.wall()
        while backlog and (now - backlog[0][0] >= 3.0 or t >= 20.0):  # the loop takes what waited 3 s
            _, key, payload = backlog.pop(0)
            laptop.on_message(key, payload)
        team.pump()
        if t >= next_status[0]:
            wait = now - backlog[0][0] if backlog else 0.0
            statuses = {name: rt.status(10.0, queue_wait_s=wait if say_wait and name == "laptop" else 0.0)
                        for name, rt in team.nodes.items() if rt.started}
            for name, rt in team.nodes.items():  # as the wire carries them
                for other, status in statuses.items():
                    if other != name:
                        rt.on_peer_status(decode(encode(status), NodeStatus))
            for name, rt in team.nodes.items():
                if rt.started:
                    for dest, ack in rt.acks(wait if say_wait and name == "laptop" else 0.0).items():
                        team.nodes[dest].on_ack(decode(encode(ack), Ack))
            team.pump()
            next_status[0] = t + 0.5

    team.run_until(30.0, on_tick=tick)
    for _ in range(6):  # the last reports after the last frames
        team.clock.advance(0.5)
        team.exchange_statuses()
    return team, outputs, dropped[0]


def test_a_consumer_behind_on_its_queue_is_resent_only_what_its_queue_dropped():
    team, outputs, dropped = run_with_backlog(say_wait=True)
    assert dropped >= 10
    # each frame the queue dropped was resent (a resend the queue dropped again, again), and none
    # of those that only waited in it
    assert sum(rt.custody.resent for rt in team.nodes.values()) == dropped
    assert team.nodes["laptop"].counters.get("redundant-input", 0) == 0
    check_exactly_once(team, outputs)


def test_a_source_whose_consumer_falls_behind_skips_captures_instead_of_evicting_what_it_holds():
    # r2 may hold 8 camera frames for the blob finder on the laptop, whose loop is 3 s (12 frames,
    # plus a status period for the report) behind: full, r2 skips captures, counted as missed
    # periods, and the stream arrives late but whole. (Evicting the oldest held frame instead left
    # a gap the laptop's gate waited on and gave up: every frame evicted was lost.)
    team, outputs, dropped = run_with_backlog(say_wait=True, drop_every=0, r2_holds=8)
    r2 = team.nodes["r2"]
    assert dropped == 0
    skipped = r2.counters.get("missed-periods-backlog", 0)
    assert skipped > 0, "the custody never filled: the test proves nothing"
    assert r2.custody.evicted == 0
    assert r2.sources["Blob-2"].missed == skipped
    check_exactly_once(team, outputs)
    # the source went on once the laptop caught up: 30 s of camera periods, less those skipped
    assert r2.sources["Blob-2"].seq + skipped == pytest.approx(30.0 / 0.25, abs=2)


def test_a_consumer_that_does_not_say_how_far_behind_it_is_gets_its_queue_again():
    # the same backlog with the wait left out of the laptop's status (how it was): the camera frames
    # waiting in its queue are resent, decoded there and dropped as redundant, and still exactly once
    team, outputs, dropped = run_with_backlog(say_wait=False)
    resent = sum(rt.custody.resent for rt in team.nodes.values())
    assert resent > 2 * dropped
    assert team.nodes["laptop"].counters.get("redundant-input", 0) > dropped
    check_exactly_once(team, outputs)


def test_without_the_consumers_reports_the_cut_loses_outputs():
    team, outputs = run_with_blackout({"Blob-2": "laptop"}, ("r2", "laptop"), acks=False)
    ledger = team.nodes["laptop"].sinks["Blob-2"]
    # (the fake blob finder raises on the first gap: its stage fails and the chain stops)
    assert ledger.gaps > 0 or ledger.contiguous < team.nodes["r2"].status(1.0).sources["Blob-2"].produced


@pytest.mark.parametrize("topology", ["fully-connected", "relay"])
def test_random_migrations_under_random_silent_cuts_lose_and_duplicate_nothing(topology):
    """Stages keep moving while random links drop chain frames for a while (in both directions)."""
    import random

    from autopower.protocol import MigrateCommand

    rng = random.Random(7)
    sc = load_scenario("paper-fig7")
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0, topology=topology, media=FC, auto_replan=False), rng=rng)
    team.cut_only_chain_frames = True
    outputs = collect(team)
    team.join()
    stages, nodes = sc.stage_names(), sc.node_names()
    t, moves, next_status = 1.0, 0, 0.5
    while moves < 80:
        team.run_until(t)
        if t >= next_status:
            team.exchange_statuses()
            next_status = t + 0.5
        if rng.random() < 0.2:
            a, b = rng.sample(nodes, 2)
            team.cut_silently(a, b, one_way=rng.random() < 0.5)
        if rng.random() < 0.15:
            team.cut_links = frozenset()
        if rng.random() < 0.3:
            reply = team.coordinator.on_operator(MigrateCommand(stage=rng.choice(stages), to_node=rng.choice(nodes)))
            assert reply.ok, reply.message
            moves += 1
        t += rng.choice([0.1, 0.25, 0.5])
    team.cut_links = frozenset()
    end = t + 15.0
    while t < end:  # the reports catch up and the last losses are resent
        team.run_until(t)
        team.exchange_statuses()
        t += 0.5
    assert team.lost_in_cuts > 50
    assert sum(rt.custody.resent for rt in team.nodes.values()) > 20
    check_exactly_once(team, outputs)
    assert all(rt.custody.evicted == 0 for rt in team.nodes.values())


def test_a_gate_started_without_state_starts_at_the_producers_floor_and_marks_recomputed_seqs():
    gate = SequenceGate()
    assert gate.offer(10, 10, floor=7) == []  # 7, 8, 9 are still held by the producer: wait for them
    assert gate.report(0, 1).missing == ((7, 9),)
    assert gate.offer(8, 8, floor=7) == [] and gate.offer(7, 7, floor=7) == [7, 8]
    assert gate.offer(9, 9, floor=7) == [9, 10]
    assert gate.catch_up_below == 10


def test_a_gate_stops_waiting_for_what_its_producer_says_another_instance_consumed():
    gate = SequenceGate(next_seq=5)
    assert gate.offer(9, 9, floor=8) == []  # 5..7 were acknowledged by someone else; 8 is coming
    assert gate.next_seq == 8 and gate.consumed_elsewhere == 3 and gate.skipped == 0
    assert gate.offer(8, 8, floor=8) == [8, 9]


def test_a_gate_runs_what_waits_below_the_floor_past_what_another_instance_consumed():
    """Random faults, seed 6: a restarted stage waited behind 15 and 16, which the laptop's instance
    had acknowledged before it was cut off; 13 and 14 were resent and 17 on waited too. The
    producer's floor rising past them says they will not come: what waits runs, in order."""
    gate = SequenceGate(next_seq=13)
    assert gate.offer(13, 13, floor=13) == [13]
    assert gate.offer(14, 14, floor=13) == [14]
    assert gate.offer(17, 17, floor=13) == [] and gate.offer(18, 18, floor=13) == []  # 15, 16 not here
    assert gate.report(0, 1).missing == ((15, 16),)
    # 17 and 18 acknowledged here, 15 and 16 by the laptop: the producer holds nothing below 19
    assert gate.offer(19, 19, floor=19) == [17, 18, 19]
    assert gate.next_seq == 20 and gate.consumed_elsewhere == 2 and gate.skipped == 0 and not gate.pending
    # a gap the floor does not cover still waits
    assert gate.offer(22, 22, floor=21) == [] and gate.next_seq == 21 and gate.consumed_elsewhere == 3


def test_a_gate_knows_when_a_floor_would_move_it_past_an_input_not_waiting_in_it():
    gate = SequenceGate(next_seq=5)
    assert not gate.skips_below(None) and not gate.skips_below(5) and not gate.skips_below(3)
    gate.offer(5, 5, floor=5)
    gate.offer(7, 7, floor=5)
    assert gate.released == 1  # 5 ran; 7 waits behind 6
    assert not gate.skips_below(6)  # nothing below 6 is missing: 5 ran
    assert gate.skips_below(8)  # 6 is neither run nor waiting
    gate.offer(6, 6, floor=5)
    assert gate.released == 3 and not gate.skips_below(8)


def test_a_stage_whose_producer_lost_the_input_it_waits_for_starts_afresh_at_the_floor():
    """Sweep seed 1695 (CI's plan): r3's camera frames 64-69 for the laptop's Blob-3 vanished in a
    partition, and r3 was killed with them in its custody only. The base station never saw r3 go (a
    keyframe of a relay's status lost on a lossy link left its view of r3 stale), so Blob-3 kept
    running on the laptop, its gate waiting for 64. The restarted r3 went on at 70 with its floor
    there; the gate took the floor as what another instance had run and ran 70 past the gap, and the
    component (whose state expected 64) refused it: the stage failed and its chain stopped. An
    instance that has run inputs does not move past a gap on its producer's floor: it starts afresh
    there, as the chain resumed after its source robot's kill would (`Hosting.start_afresh`)."""
    sc = load_scenario("paper-fig7")
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0, media=FC, auto_replan=False, pins={"Blob-3": "laptop"}))
    outputs = collect(team)
    team.join()
    r3, laptop = team.nodes["r3"], team.nodes["laptop"]
    team.run_exchanging_statuses(5.0)
    assert laptop.hosted["Blob-3"].gate.released > 0
    team.cut_silently("r3", "laptop", one_way=True)  # r3's camera frames vanish on the way
    team.run_exchanging_statuses(6.0)
    waited = laptop.hosted["Blob-3"].gate.next_seq
    died = {h.frame.seq for (chain, target), frames in r3.custody.hops.items() if (chain, target) == ("Blob-3", 0)
            for h in frames.values()}
    assert waited == min(died)
    # r3 is killed with them in its custody only; its restarted source goes on after them (`Resuming`)
    r3.custody.forget_chain("Blob-3")
    team.heal_silently("r3", "laptop")
    team.run_exchanging_statuses(9.0)
    hosted = laptop.hosted["Blob-3"]
    assert hosted.lifecycle is Lifecycle.RUNNING and "Blob-3" not in laptop.hosting.failed
    assert laptop.counters.get("stage-started-afresh") == 1
    produced = r3.sources["Blob-3"].seq
    assert sorted(seq for _, seq, _ in outputs["Blob-3"]) == [seq for seq in range(produced) if seq not in died]
    assert laptop.sinks["Blob-3"].duplicates_total == 0


def test_a_stage_restarted_without_state_catches_up_on_what_never_reached_its_old_host():
    """What a subgroup does when the base station is cut off: restart the stage on a robot, cold."""
    from autopower.protocol import Assign

    sc = load_scenario("paper-fig7")
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0, media=FC, auto_replan=False, pins={"Loc-2": "laptop"}))
    outputs = collect(team)
    team.join()
    r2 = team.nodes["r2"]
    next_status = [0.5]

    def tick(t: float) -> None:
        if 9.7 <= t < 14.5:
            team.cut_silently("r2", "laptop", one_way=True)  # r2's scans (from t = 10) vanish
        else:
            team.heal_silently("r2", "laptop")
        if t >= next_status[0]:
            team.exchange_statuses()
            next_status[0] = t + 0.5

    team.run_until(11.0, on_tick=tick)
    lost_scan = r2.sources["Loc-2"].seq - 1  # the t = 10 scan never reached the laptop
    assert team.nodes["laptop"].hosted["Loc-2"].gate.next_seq == lost_scan
    r2.hosting.on_assign(Assign(stage="Loc-2", generation=10**9, chain="Loc-2", run=r2.plan.running["Loc-2"],
                        resume_seq=None))
    r2.plan_view.override_placement({"Loc-2": "r2"}, set())
    team.run_until(30.0, on_tick=tick)
    for _ in range(6):
        team.clock.advance(0.5)
        team.exchange_statuses()
    produced = r2.sources["Loc-2"].seq
    assert sorted(seq for _, seq, _ in outputs["Loc-2"]) == list(range(produced))  # the lost scan included
    # the new instance said at once that it had nothing (before its first input), so r2 resent the
    # lost scan before its next one: the gate started there, with no range to catch up below a newer
    gate = r2.hosted["Loc-2"].gate
    assert gate.catch_up_below is None and lost_scan in gate.resent
    assert r2.sinks["Loc-2"].duplicates_total == 0


def test_a_stage_restarted_cold_recomputes_what_its_dead_host_delivered_without_a_duplicate():
    """The base station's Loc-2 ran r2's scans and r2, the sink, had the poses; the base station
    died before a status of its acknowledged those scans. The Loc-2 r2 restarts (cold, as a subgroup
    does) gets them again from r2's custody, so its poses for them are second copies of what the
    sink has: redundant (a resend made them), dropped, and not duplicates (seen live in the testbed
    demo: `duplicate-output` at r3 after the base station's SIGKILL, and the pose delivered twice)."""
    from autopower.protocol import Assign

    sc = load_scenario("paper-fig7")
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0, media=FC, auto_replan=False, pins={"Loc-2": "laptop"}))
    outputs = collect(team)
    team.join()
    r2 = team.nodes["r2"]
    for t in range(1, 10):
        team.run_until(float(t))
        team.exchange_statuses()  # the laptop's acknowledgements reach r2 up to t = 9 ...
    team.run_until(15.0)  # ... and none after: the scans of t = 10-14 ran, their poses reached r2
    held = {h.frame.seq for (chain, _), frames in r2.custody.hops.items() if chain == "Loc-2"
            for h in frames.values()}
    delivered = {seq for _, seq, _ in outputs["Loc-2"]}
    assert held and held <= delivered  # delivered, not acknowledged: the window this is about
    team.cut_silently("laptop", "r2")  # the base station is gone
    r2.hosting.on_assign(Assign(stage="Loc-2", generation=10**9, chain="Loc-2", run=r2.plan.running["Loc-2"],
                        resume_seq=None))
    r2.plan_view.override_placement({"Loc-2": "r2"}, set())
    # The resends reach the new instance before any new scan (as live, where custody sent them on
    # at once): its first input is a resend, so nothing marks a catch-up range below a new one.
    for (chain, _), frames in list(r2.custody.hops.items()):
        if chain == "Loc-2":
            for h in sorted(frames.values(), key=lambda h: h.frame.seq):
                r2.frames.send_frame(r2.custody.resend(h, r2.wall())[0], "r2", purpose="recovery")
    team.pump()
    assert r2.hosted["Loc-2"].gate.catch_up_below is None
    team.run_until(30.0)
    for _ in range(6):
        team.clock.advance(0.5)
        team.exchange_statuses()
    ledger = r2.sinks["Loc-2"]
    assert ledger.duplicates_total == 0
    assert ledger.redundant_total >= len(held)  # each held scan was recomputed, its pose dropped
    seqs = [seq for _, seq, _ in outputs["Loc-2"]]
    assert sorted(seqs) == list(range(r2.sources["Loc-2"].seq))  # every pose once, none twice


def test_a_node_knows_whose_frames_it_consumes_so_its_acks_reach_them():
    sc = load_scenario("paper-fig7")
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0, media=FC, auto_replan=False,
                                                pins={"Loc-1": "r2", "Blob-3": "laptop"}))
    team.join()
    team.run_until(3.0)
    # r1's scans come to r2's Loc-1; r2's own poses come back from the laptop's Loc-2
    assert team.nodes["r2"].acknowledging.producers() == {"r1", "laptop"}
    assert team.nodes["r1"].acknowledging.producers() == {"r2"}  # r1 is Loc-1's sink: its poses come from r2
    assert "r3" in team.nodes["laptop"].acknowledging.producers()  # r3's camera frames to the laptop's Blob-3


def test_a_gate_tells_redundant_resends_from_real_duplicates():
    gate = SequenceGate(next_seq=0)
    assert gate.offer(0, "a", resent=True) == ["a"]  # resent: the original was only late ...
    assert gate.offer(0, "a") == []  # ... and arrives now
    assert gate.offer(1, "b") == ["b"]
    assert gate.offer(1, "b", resent=True) == []  # a resend of one that had arrived
    assert (gate.redundant, gate.duplicates) == (2, 0)
    assert gate.offer(1, "b") == []  # the same input twice with no resend involved: a bug
    assert gate.duplicates == 1


def test_a_gate_waits_for_a_late_gap_for_seconds_not_a_count_of_inputs():
    """At 40 inputs a second a migration or a resend takes many inputs to arrive: time decides."""
    gate = SequenceGate(next_seq=0)
    for seq in range(1, 200):  # seq 0 is late: 199 inputs wait behind it for 5 s
        assert gate.offer(seq, seq, now=seq * 0.025) == []
    assert gate.offer(0, 0, now=5.0) == list(range(200)) and gate.skipped == 0
    gate.offer(201, 201, now=10.0)  # seq 200 never comes
    assert gate.offer(202, 202, now=15.0) == [] and gate.skipped == 0
    assert gate.offer(203, 203, now=20.1) == [201, 202, 203] and gate.skipped == 1


def test_a_migrated_stage_still_knows_which_inputs_came_as_resends():
    """A resend reaches the old host, the stage moves, the late original reaches the new host:
    the new host must see a redundant copy, not a duplicate."""
    import dataclasses

    import msgpack

    from autopower.node.stages import pad
    from autopower.protocol import MigrateCommand

    sc = load_scenario("paper-fig7")
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0, media=FC, auto_replan=False, pins={"Blob-2": "laptop"}))
    team.join()
    team.run_until(2.0)
    r2, laptop = team.nodes["r2"], team.nodes["laptop"]
    seq = r2.sources["Blob-2"].seq  # the next frame r2's camera will take
    chain = sc.chain("Blob-2")
    data = msgpack.packb(["r2", seq])
    resend = ChainFrame(chain="Blob-2", run=r2.sources["Blob-2"].run, seq=seq, target=0, t_virtual=0.0,
                        t_unix=0.0, payload_len=len(data), payload=pad(data, chain.message_bytes[0], "x"), attempt=1)
    laptop.frames.deliver_frame(resend)  # the resend got there first
    assert team.coordinator.on_operator(MigrateCommand(stage="Blob-2", to_node="r3")).ok
    team.pump()
    r3 = team.nodes["r3"]
    assert r3.hosted["Blob-2"].gate.next_seq == seq + 1
    r3.frames.deliver_frame(dataclasses.replace(resend, attempt=0))  # the late original, at the new host
    assert r3.hosted["Blob-2"].gate.redundant == 1 and r3.hosted["Blob-2"].gate.duplicates == 0
    assert "duplicate-input" not in r3.errors


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.sampled_from(["keep", "ack", "evict", "floor"]), st.integers(0, 1),
                          st.integers(0, 40)), max_size=300))
def test_the_floor_is_the_lowest_seq_held_whatever_was_kept_and_dropped(ops):
    """The floor every frame sent carries (`ChainFrame.floor`) against a scan of what is held,
    over random keeps (any order, two runs), acknowledgements, evictions and reports."""
    custody = Custody(max_frames_per_hop=25)  # small: evictions too
    for i, (op, run, seq) in enumerate(ops):
        if op == "keep":
            custody.keep(ChainFrame(chain="c", run=run, seq=seq, target=1, t_virtual=0.0, t_unix=0.0,
                                    payload_len=1, payload=b"x"), now=0.0)
        elif op in ("ack", "evict"):
            hop = custody.hops.get(("c", 1), {})
            if (run, seq) in hop:
                custody._drop(hop, (run, seq), evicted=op == "evict")
        else:
            custody.on_report("c", 1, Report(node="n", t_unix=float(i), consumed=Consumed(
                run=run, generation=0, next_seq=seq, max_seq=seq - 1, missing=())))
        for r in (0, 1):
            held = [s for (hr, s) in custody.hops.get(("c", 1), {}) if hr == r]
            assert custody.floor("c", 1, r, default=-1) == (min(held) if held else -1)
        assert custody.hop_bytes.get(("c", 1), 0) == len(custody.hops.get(("c", 1), {})) == custody.bytes
    assert sum(len(h) for h in custody._seqs.values()) <= 2 * 25 * 2 + 2 * 64 + 2  # dropped seqs do not pile up


def test_frames_past_a_truncated_missing_list_are_kept_and_not_resent_until_it_names_them():
    """A consumer reports at most MAX_MISSING missing ranges, the lowest. A frame past the last of
    them was counted as received and dropped from custody, unsent (random faults, seed 10: a
    robot's 512 held results sent into a link that had just come back, all lost, when the list
    named seqs). Now it is kept, and resent once a later report names it."""
    custody = Custody(resend_after_s=0.1)
    top = 4 * MAX_MISSING
    for seq in range(top):  # results (Blob-2's sink hop): what the sink reports received is delivered
        custody.keep(ChainFrame(chain="Blob-2", run=0, seq=seq, target=1, t_virtual=0.0, t_unix=0.0,
                                payload_len=0, payload=b""), 0.0, result=True)
    evens = list(range(0, top - 2, 2))  # every other frame lost: one range each, about twice what a report holds
    lost_all = Consumed(run=0, generation=0, next_seq=0, max_seq=top + 5, missing=ranges_of(evens)[:MAX_MISSING])
    custody.on_report("Blob-2", 1, Report(node="laptop", t_unix=1.0, consumed=lost_all))
    last_named = evens[MAX_MISSING - 1]
    # the odd seqs below the last named range arrived; nothing past it is given up
    assert len(custody) == top - last_named // 2
    assert sorted(held.frame.seq for _, held in custody.due(1.0)) == evens[:MAX_MISSING]  # listed ones only
    assert not is_consumed(lost_all, 0, last_named + 1)
    # the first half arrived (resent); the next report names the rest
    rest = Consumed(run=0, generation=0, next_seq=last_named + 1, max_seq=top + 5, missing=ranges_of(evens[MAX_MISSING:]))
    custody.on_report("Blob-2", 1, Report(node="laptop", t_unix=2.0, consumed=rest))
    assert len(custody) == len(evens) - MAX_MISSING
    assert sorted(held.frame.seq for _, held in custody.due(2.0)) == evens[MAX_MISSING:]
    # a complete list (shorter than the cap) still acknowledges what it does not name
    done = Consumed(run=0, generation=0, next_seq=last_named + 1, max_seq=top + 5, missing=((top - 2, top - 2),))
    assert is_consumed(done, 0, top - 4) and not is_consumed(done, 0, top - 2)


def test_a_sink_names_the_frames_lost_past_a_run_of_results_that_will_never_come():
    """Random faults, seed 10: a robot cut off from the sink held 512 results, dropped the oldest
    (they never come), then lost the next ones in flight when the link came back. The sink listed
    its missing seqs one by one, the lowest 256: all of them the dropped results, so the lost
    frames past them were never named and their producer never resent them (319 outputs lost).
    Missing ranges name both runs."""
    ledger, custody = SinkLedger(), Custody(resend_after_s=0.1)
    dropped = range(100, 612)  # let go by the robot's full hold: never sent
    lost = range(621, 921)  # sent into the link that had just come back, lost
    for seq in range(1000):
        if seq not in dropped:
            custody.keep(ChainFrame(chain="Blob-2", run=0, seq=seq, target=1, t_virtual=0.0, t_unix=0.0,
                                    payload_len=0, payload=b""), 0.0, result=True)
        if seq not in dropped and seq not in lost:
            ledger.record(0, seq)
    assert ledger.report().missing == ((100, 611), (621, 920))
    custody.on_report("Blob-2", 1, Report(node="laptop", t_unix=1.0, consumed=ledger.report()))
    assert sorted(held.frame.seq for _, held in custody.due(1.0)) == list(lost)  # all resent, nothing else
    assert len(custody) == len(lost)


def test_missing_ranges_are_what_is_absent_lowest_first_and_bounded():
    assert missing_between(3, 10, {3, 5, 6, 10}) == ((4, 4), (7, 9))
    assert missing_between(3, 10, set()) == ((3, 10),)
    assert missing_between(3, 2, set()) == ()
    assert missing_between(0, 3 * MAX_MISSING, set(range(0, 3 * MAX_MISSING, 2))) == tuple(
        (s, s) for s in range(1, 2 * MAX_MISSING, 2))
    assert ranges_of([1, 2, 3, 7, 9, 10]) == ((1, 3), (7, 7), (9, 10))
    ranges = ((1, 3), (7, 7), (9, 10))
    assert [s for s in range(12) if in_ranges(ranges, s)] == [1, 2, 3, 7, 9, 10]
    assert not in_ranges((), 5)


def test_results_beyond_the_hold_budget_are_dropped_oldest_first_and_leave_custody():
    """A robot cut off from a sink keeps its results within the scenario's hold budget and drops the
    oldest beyond it, counted (held-outputs-dropped, dropped-by-budget) and told to the recorder; a
    dropped one leaves custody (it kept the hop's floor at its seq), and custody evicts nothing."""
    import dataclasses

    sc = load_scenario("paper-fig7")
    team = SimTeam(dataclasses.replace(sc, hold_budget_bytes=5 * 100),
                   config=CoordinatorConfig(speed=1.0, media=FC, auto_replan=False))
    team.join()
    team.run_until(2.0)
    r2 = team.nodes["r2"]
    team.pump()
    assert r2.custody.result_bytes == 0  # every result so far acknowledged: the budget is all ours
    frames = [ChainFrame(chain="Blob-2", run=0, seq=10_000 + i, target=1, t_virtual=0.0, t_unix=0.0,
                         payload_len=100, payload=bytes(100)) for i in range(8)]
    before = len(r2.custody)
    told = []
    r2.listen(SinkListener(held_dropped=lambda chain, run, seq, why: told.append((chain, run, seq, why))))  # as the recorder listens
    for frame in frames:
        r2.holds.keep(frame, sent=False)  # as `Frames.emit` does for a result
        r2.holds.hold(frame)  # as `send_routed` does with no route to the sink
    assert len(r2.holds.held) == 5 and r2.holds.dropped == 3
    assert told == [("Blob-2", 0, 10_000, "budget"), ("Blob-2", 0, 10_001, "budget"), ("Blob-2", 0, 10_002, "budget")]
    assert len(r2.custody) == before + 5  # the three dropped ones are not held any more
    assert r2.custody.floor("Blob-2", 1, 0, -1) == 10_003
    stats = r2.custody.stats()
    assert stats["dropped-by-budget"] == 3 and stats["dropped-by-budget-bytes"] == 300
    assert stats["results-kept-bytes"] == 500 and r2.custody.evicted == 0


def test_a_latest_only_chain_holds_its_newest_result_and_lets_the_older_ones_go_as_superseded():
    """`keep = "latest"`: a robot cut off from the sink holds one result per run of the chain; each
    newer one supersedes the one before (counted, told to the recorder, out of custody and of the
    hold), other chains and other runs are untouched, and the newest goes out once a route returns."""
    import dataclasses

    sc = load_scenario("paper-fig7")
    sc = dataclasses.replace(sc, chains=tuple(dataclasses.replace(c, keep="latest") if c.name == "Blob-2" else c
                                              for c in sc.chains))
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0, media=FC, auto_replan=False))
    team.join()
    team.run_until(2.0)
    r2 = team.nodes["r2"]
    team.pump()

    def result(chain, run, seq, target):
        return ChainFrame(chain=chain, run=run, seq=seq, target=target, t_virtual=0.0, t_unix=0.0,
                          payload_len=100, payload=bytes(100))

    told = []
    r2.listen(SinkListener(held_dropped=lambda chain, run, seq, why: told.append((chain, run, seq, why))))
    before = len(r2.custody)
    frames = [result("Blob-2", 0, 10_000 + i, 1) for i in range(4)] + [result("Blob-2", 1, 5, 1),
                                                                      result("Loc-2", 0, 9_000, 1),
                                                                      result("Loc-2", 0, 9_001, 1)]
    for frame in frames:
        r2.holds.keep(frame, sent=False)
        r2.holds.hold(frame)
    assert told == [("Blob-2", 0, 10_000 + i, "superseded") for i in range(3)]
    assert r2.holds.superseded == 3 and r2.holds.dropped == 0
    held = {(f.chain, f.run, f.seq) for f in r2.holds.held.values()}
    assert held == {("Blob-2", 0, 10_003), ("Blob-2", 1, 5), ("Loc-2", 0, 9_000), ("Loc-2", 0, 9_001)}
    assert len(r2.custody) == before + 4 and r2.custody.floor("Blob-2", 1, 0, -1) == 10_003
    assert r2.status(1.0).counters["held-outputs-superseded"] == 3


def test_results_outlive_custodys_age_and_count_limits_within_the_budget():
    """A result waits for its sink as long as the budget allows: neither custody's age limit nor its
    per-hop count gives it up (a cut of an hour loses nothing); other frames still obey both."""
    from autopower.node.custody import Custody

    custody = Custody(max_frames_per_hop=4, max_age_s=10.0, hold_budget_bytes=10**6)
    for seq in range(8):
        custody.keep(ChainFrame(chain="Blob-2", run=0, seq=seq, target=1, t_virtual=0.0, t_unix=0.0,
                                payload_len=10, payload=bytes(10)), now=0.0, result=True)
        custody.keep(ChainFrame(chain="Blob-2", run=0, seq=seq, target=0, t_virtual=0.0, t_unix=0.0,
                                payload_len=10, payload=bytes(10)), now=0.0)
    assert len(custody.hops[("Blob-2", 1)]) == 8 and len(custody.hops[("Blob-2", 0)]) == 4
    custody.due(3600.0)
    assert len(custody.hops[("Blob-2", 1)]) == 8 and not custody.hops[("Blob-2", 0)]


def test_a_stopped_chains_results_stay_in_custody_until_its_sink_has_them():
    """Random faults, seed 4: the base station lost r2 for a moment and stopped its chains; r2 got
    that plan (relayed) and dropped the chain's frames from custody, results included, as
    acknowledged. Adopted again in the same run a second later, the chain went on, but the results
    that had been lost in flight were never resent (14 Blob-2 results at a time). The frames for
    its stages go only when the operator stopped it (no instance will take them); its results stay
    until its sink has them."""
    sc = load_scenario("paper-fig7")
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0, media=FC, pins={"Blob-2": "r2"}, auto_replan=False))
    team.join()
    team.run_until(5.0)
    r2 = team.nodes["r2"]
    result = ChainFrame(chain="Blob-2", run=0, seq=50_000, target=1, t_virtual=0.0, t_unix=0.0, payload_len=0,
                        payload=b"")
    camera = ChainFrame(chain="Blob-2", run=0, seq=50_000, target=0, t_virtual=0.0, t_unix=0.0, payload_len=0,
                        payload=b"")
    r2.custody.keep(result, r2.wall())  # lost in flight to the laptop
    r2.custody.keep(camera, r2.wall())
    running = {c: r for c, r in r2.plan.running.items() if c != "Blob-2"}
    lost_robot = dataclasses.replace(r2.plan, epoch=r2.plan.epoch + 1, running=running)
    r2.on_plan(lost_robot)  # stopped because the base station lost r2: adopted again when it is back
    assert (0, 50_000) in r2.custody.hops[("Blob-2", 1)] and (0, 50_000) in r2.custody.hops[("Blob-2", 0)]
    operator = dataclasses.replace(lost_robot, epoch=lost_robot.epoch + 1,
                                   operator=dataclasses.replace(lost_robot.operator, disabled=("Blob-2",)))
    r2.on_plan(operator)  # stopped by the operator: its stages' frames have no consumer any more
    assert (0, 50_000) in r2.custody.hops[("Blob-2", 1)]  # the result still waits for its sink
    assert (0, 50_000) not in r2.custody.hops.get(("Blob-2", 0), {})


def test_a_late_input_for_a_stage_moved_out_of_reach_waits_as_an_orphan_until_a_plan_routes_it(monkeypatch):
    """A 20-robot fleet's start in CI: r16's links flapped while its process started, the plan moved
    Loc-16 and Blob-16 to r16 (out of reach), and the laptop's moved-out instances forwarded their
    late inputs into no route, counted as errors. They wait here as orphans instead (their producer
    keeps them until a gate has run them), and the plan that routes their stage's host sends them on."""
    from autopower.node.stages import Lifecycle

    team = SimTeam(load_scenario("paper-fig7"))
    team.join()
    laptop = team.nodes["laptop"]
    name, hosted = next((n, h) for n, h in sorted(laptop.hosted.items()) if h.lifecycle is Lifecycle.RUNNING)
    hosted.lifecycle, hosted.forward_to = Lifecycle.MIGRATED, "r2"  # what MigrateOut to r2 leaves behind
    plan = laptop.plan
    cut = dataclasses.replace(plan, epoch=plan.epoch + 1, placement={**plan.placement, name: "r2"},
                              links=tuple(l for l in plan.links if "r2" not in (l.a, l.b)))
    laptop.on_plan(cut)
    late = ChainFrame(chain=hosted.chain.name, run=hosted.run, seq=10_000, target=hosted.index, t_virtual=0.0,
                      t_unix=0.0, payload_len=0, payload=b"")
    laptop.frames.deliver_frame(late)
    assert [f.seq for f in laptop.hosting.orphans[name]] == [10_000] and "unroutable" not in laptop.errors
    sent = []
    monkeypatch.setattr(laptop.frames, "send_frame", lambda frame, dest, *args, **kwargs: sent.append((frame.seq, dest)))
    laptop.on_plan(dataclasses.replace(cut, epoch=cut.epoch + 1, links=plan.links))  # r2 in reach again
    assert sent == [(10_000, "r2")] and name not in laptop.hosting.orphans


def test_a_resent_copy_carries_the_hops_floor_as_it_is_now():
    custody = Custody(resend_after_s=1.0)
    for seq in range(6):
        custody.keep(dataclasses.replace(frame(seq), floor=0), now=0.0)
    custody.on_report("Blob-2", 0, report(next_seq=3, max_seq=5, missing=(3, 4, 5), t=2.0))  # 0-2 run
    [(_, held), *_] = custody.due(now=2.0)
    copy, again = custody.resend(held, now=2.0)
    # a fresh instance starting at this copy starts at 3, not below it at seqs that never come again
    assert again and copy.seq == 3 and copy.floor == 3


def test_a_cold_restarted_stage_gets_what_its_backed_up_producer_holds(tmp_path):
    """Live random faults, seed 7: r3's camera chain ran on the base station, cut off from r3 for a
    while; r3's custody for it filled up (145 camera frames, its share of the bytes), so its source
    skipped every capture (back-pressure: the consumer is behind). A subgroup round restarted the
    stage on r3 itself, cold. The new instance had no input yet, so it reported nothing, so r3 resent
    nothing, so the source, still backed up, captured nothing: the chain stood still for the rest of
    the run (80 s of wall time, 1,700 captures skipped), and r3 read 15 % below the model. A running
    instance reports its hop before its first input too: its producer resends what it holds."""
    from autopower.node.held_store import HeldStore
    from autopower.node.ports import NodeStores
    from autopower.protocol import Assign

    sc = load_scenario("paper-fig7")
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0, media=FC, auto_replan=False, pins={"Blob-3": "laptop"}),
                   stores={"r3": NodeStores(held_store=HeldStore(tmp_path / "r3.held"))})
    outputs = collect(team)
    team.join()
    r3 = team.nodes["r3"]
    next_status = [0.5]

    def tick(t: float) -> None:
        if t >= next_status[0]:
            team.exchange_statuses()
            next_status[0] = t + 0.5

    team.run_until(5.0, on_tick=tick)
    team.cut_silently("laptop", "r3")
    team.run_until(50.0, on_tick=tick)
    source = r3.sources["Blob-3"]
    backed_up = source.seq
    assert r3.counters.get("missed-periods-backlog", 0) > 0  # custody full: captures skipped
    assert not r3.custody.has_room("Blob-3", 0, sc.chain("Blob-3").message_bytes[0], r3.wall(),
                                   sharers=len(r3.feeds))
    r3.hosting.on_assign(Assign(stage="Blob-3", generation=10**9, chain="Blob-3", run=r3.plan.running["Blob-3"],
                                resume_seq=None))  # as a subgroup round restarts it
    r3.plan_view.override_placement({**r3.plan.placement, "Blob-3": "r3"}, {"laptop"})
    team.run_until(70.0, on_tick=tick)
    assert source.seq >= backed_up + 4 * 15  # capturing again at 4 Hz within 5 s of the restart
    hosted = r3.hosted["Blob-3"]
    assert hosted.runs >= source.seq - backed_up  # what was held ran, and what came since
    assert r3.custody.held_for("Blob-3", 0) <= 4  # drained: only the last second's frames
    assert not [seq for _, seq, _ in outputs["Blob-3"] if seq >= backed_up]  # results held for the laptop
    assert len(r3.holds) >= source.seq - backed_up
