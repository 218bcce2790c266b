"""DAG flows at run time (docs/concepts/chains.md): fan-out, the fan-in join rule, exactly
once per edge, late and lost inputs, and a fan-in stage migrating with its state.

A whole team in one thread (SimTeam: coordinator + a NodeRuntime per node, manual clock) with
the real components: MCL localises each robot and TeamMap merges their poses.
"""

from __future__ import annotations

import msgpack

from autopower.basestation.coordinator import CoordinatorConfig
from autopower.chains.teammap import decode_join, decode_map
from autopower.model.loading import load_scenario
from autopower.node.joining import EdgeGate, JoinState, join_wait_s
from autopower.node.ports import SinkListener
from autopower.protocol import ChainFrame, MigrateCommand
from tests.unit.sim_team import SimTeam

SC = load_scenario("paper-teammap")
FC = {"laptop-robot": "802.11a", "robot-robot": "802.11a"}
LOCS = ("Loc-1", "Loc-2", "Loc-3")


def team_of(**config) -> tuple[SimTeam, dict]:
    team = SimTeam(SC, config=CoordinatorConfig(speed=1.0, media=FC, auto_replan=False, **config), fake=False)
    outputs: dict = {}
    for rt in team.nodes.values():
        rt.listen(SinkListener(output=lambda chain, run, seq, data: outputs.setdefault(chain, []).append((run, seq, data))))
    return team, outputs


def maps(outputs) -> list[dict]:
    return [decode_map(data) for _, _, data in outputs.get("TeamMap", [])]


def loc_steps(outputs, chain: str) -> list[int]:
    return [msgpack.unpackb(data[: data.index(b"\x00" * 8)] if b"\x00" * 8 in data else data)["seq"]
            for _, _, data in outputs[chain]]


def test_every_step_joins_each_input_exactly_once():
    team, outputs = team_of()
    team.join()
    team.run_until(30.0)
    got = maps(outputs)
    assert [m["step"] for m in got] == list(range(len(got))) and len(got) >= 14
    assert all(m["missing"] == [] for m in got)
    assert all(set(m["robots"]) == {"r1", "r2", "r3"} and all(r["age_steps"] == 0 for r in m["robots"].values())
               for m in got)
    assert got[-1]["explored_m2"] > got[0]["explored_m2"]  # the map grows as the robots drive
    # the sink counted each map once; each Loc output still reached its robot (fan-out)
    ledger = team.nodes["laptop"].sinks["TeamMap"]
    assert ledger.duplicates_total == 0 and ledger.contiguous == len(got)
    assert all(len(outputs[c]) >= len(got) for c in LOCS)
    for rt in team.nodes.values():
        assert not rt.errors, (rt.node, rt.errors)


def test_a_late_input_runs_its_step_without_it_then_is_dropped_once():
    """Loc-1 on r1, the map on the laptop: everything r1 sends the laptop vanishes for 10 s (resends
    too). Steps whose Loc-1 pose is not there join_wait_s after the others run without it
    ("missing"); when the link heals, custody resends the poses: each is consumed once, counted
    late, never run. (A pose lost once and resent within the bound joins its own step: the
    SimTeam check in test_a_resent_input_within_the_bound_joins_its_step.)"""
    team, outputs = team_of(pins={"Loc-1": "r1", "TeamMap": "laptop"})
    team.join()
    team.run_until(10.0)
    team.cut_silently("r1", "laptop", one_way=True)
    wait = join_wait_s(2.0, 1.0)
    team.run_exchanging_statuses(20.0)  # the cut lasts 10 s: several steps, each waiting `wait` for Loc-1
    team.heal_silently("r1", "laptop")
    team.run_exchanging_statuses(40.0)
    got = maps(outputs)
    assert [m["step"] for m in got] == list(range(len(got)))  # no step skipped, none twice
    without = [m["step"] for m in got if m["missing"]]
    assert without and all(m["missing"] == ["Loc-1"] for m in got if m["missing"])
    # poses of t = 12, 14, 16 s (steps 6-8) were still absent 3 s after the others: run without;
    # t = 18 s's was resent after the heal at 20 s, within its bound: joined its own step
    assert without == [6, 7, 8]
    assert all("r1" not in m["robots"] or m["robots"]["r1"]["age_steps"] > 0 for m in got if m["missing"])
    laptop = team.nodes["laptop"]
    stats = laptop.frames.join_stats()["TeamMap"]
    assert stats["late"] == len(without) and stats["missing"] == len(without)  # each came once, late
    assert laptop.errors.get("join-late") == len(without)
    assert laptop.errors.get("duplicate-input") is None
    assert not got[-1]["missing"] and got[-1]["robots"]["r1"]["age_steps"] == 0  # back to normal
    assert wait == 3.0


def test_a_resent_input_within_the_bound_joins_its_step():
    team, outputs = team_of(pins={"Loc-1": "r1", "TeamMap": "laptop"})
    team.cut_only_chain_frames = True  # first copies are lost, custody's resends get through
    team.join()
    team.run_until(10.0)
    team.cut_silently("r1", "laptop", one_way=True)
    team.run_exchanging_statuses(30.0)
    assert team.lost_in_cuts >= 8 and team.nodes["r1"].counters["resent-frames"] >= 8
    got = maps(outputs)
    assert [m["step"] for m in got] == list(range(len(got))) and all(not m["missing"] for m in got)
    assert team.nodes["laptop"].frames.join_stats()["TeamMap"]["late"] == 0


def test_a_lost_input_never_stalls_the_join():
    """Everything r1 sends the laptop is lost for good (the cut never heals; custody's resends are
    lost too): the map runs every step with Loc-2 and Loc-3, each join_wait_s after they came,
    marking Loc-1 missing. When r1 then leaves, the base station stops Loc-1 and the map stops
    waiting for it (a stopped producer is not expected)."""
    team, outputs = team_of(pins={"Loc-1": "r1", "TeamMap": "laptop"})
    team.join()
    team.run_until(10.0)
    team.cut_silently("r1", "laptop", one_way=True)
    team.run_exchanging_statuses(30.0)
    cut_steps = [m["step"] for m in maps(outputs) if m["missing"]]
    assert cut_steps == list(range(6, 14))  # t = 12 .. 26 s; t = 28 s's is still within its bound
    assert all(m["missing"] == ["Loc-1"] for m in maps(outputs) if m["missing"])
    assert team.nodes["r1"].counters["resent-frames"] > 0  # custody tried
    team.leave("r1")
    team.run_exchanging_statuses(40.0)
    got = maps(outputs)
    assert [m["step"] for m in got] == list(range(len(got))) and len(got) >= 19
    assert all(m["robots"]["r2"]["age_steps"] == 0 and m["robots"]["r3"]["age_steps"] == 0 for m in got)
    assert not got[-1]["missing"] and "Loc-1" not in team.coordinator.placing.runs.running
    stats = team.nodes["laptop"].frames.join_stats()["TeamMap"]
    assert stats["late"] == 0 and stats["missing"] >= len(cut_steps)


def test_the_fan_in_stage_migrates_with_its_state_bit_for_bit():
    """The map moves laptop -> r2 -> r3 -> laptop mid-run: the maps are exactly an unmoved run's."""

    def run(moves):
        team, outputs = team_of()
        team.join()
        for t, node in moves:
            team.run_until(t)
            assert team.coordinator.on_operator(MigrateCommand(stage="TeamMap", to_node=node)).ok
        team.run_until(40.0)
        return team, [(seq, data) for _, seq, data in outputs["TeamMap"]]

    _, reference = run([])
    team, moved = run([(7.0, "r2"), (15.0, "r3"), (23.1, "laptop")])
    assert team.coordinator.placing.migrations_done == 3
    assert len(reference) >= 19 and moved == reference
    for rt in team.nodes.values():
        assert not rt.errors, (rt.node, rt.errors)


def _frame(seq: int, t_virtual: float, data: bytes, run: int = 0, attempt: int = 0) -> ChainFrame:
    return ChainFrame(chain="x", run=run, seq=seq, target=0, t_virtual=t_virtual, t_unix=0.0,
                      payload_len=len(data), payload=data, attempt=attempt)


def test_join_rule_in_isolation():
    flows = SC.chain("TeamMap").inputs
    join = JoinState(flows)
    a, b, c = (f.name for f in flows)
    assert join.offer(a, _frame(0, 0.0, b"A0"), 0, now=0.0) == "new"
    assert join.offer(b, _frame(0, 0.0, b"B0"), 0, now=0.1) == "new"
    assert join.ready({a, b, c}, now=1.0, wait_s=3.0) == []  # c not there, not late yet
    assert join.offer(a, _frame(0, 0.0, b"A0"), 0, now=1.0) == "duplicate"  # exactly once per edge
    ran = join.ready({a, b, c}, now=3.5, wait_s=3.0)
    assert [(j.step, j.missing) for j in ran] == [(0, ["Loc-3"])]
    assert decode_join(ran[0].payload)["inputs"] == {"Loc-1": b"A0", "Loc-2": b"B0"}
    assert join.offer(c, _frame(0, 0.0, b"C0"), 0, now=4.0) == "late" and join.late == 1
    for name in (a, b, c):
        join.offer(name, _frame(1, 2.0, b"x"), 1, now=5.0)
    assert [(j.step, j.missing) for j in join.ready({a, b, c}, now=5.0, wait_s=3.0)] == [(1, [])]
    # a step nobody sent is skipped once a later one has waited out the bound
    join.offer(a, _frame(3, 6.0, b"x"), 3, now=6.0)
    assert join.ready({a, b, c}, now=6.5, wait_s=3.0) == []
    assert [j.step for j in join.ready({a, b, c}, now=9.5, wait_s=3.0)] == [3] and join.empty_steps == 1
    # a stopped producer is not waited for
    join.offer(a, _frame(4, 8.0, b"x"), 4, now=10.0)
    join.offer(b, _frame(4, 8.0, b"x"), 4, now=10.0)
    assert [(j.step, j.missing) for j in join.ready({a, b}, now=10.0, wait_s=3.0)] == [(4, [])]


def test_edge_gate_reports_what_custody_must_resend():
    gate = EdgeGate()
    assert [gate.admit(0, s) for s in (0, 2, 2, 3)] == ["new", "new", "duplicate", "new"]
    report = gate.report(generation=5)
    assert (report.next_seq, report.max_seq, report.missing, report.generation) == (1, 3, ((1, 1),), 5)
    assert gate.admit(1, 0) == "new" and gate.admit(0, 9) == "stale"  # a new run of the producer resets it
    # a gate started fresh (failover without state) starts at the producer's floor: what is below
    # was consumed by the previous instance, and is not asked for again
    fresh = EdgeGate()
    assert fresh.admit(0, 50, floor=48) == "new"
    assert fresh.report(generation=1).missing == ((48, 49),) and fresh.admit(0, 47) == "duplicate"
    assert fresh.admit(0, 52, floor=52) == "new" and fresh.report(generation=1).next_seq == 48


def test_a_producer_that_has_not_started_is_not_a_loss():
    """At start-up a producer may begin a step later than the others: the first step runs without
    it after the bound, listed in the join message but counted as not started, not as missing."""
    flows = SC.chain("TeamMap").inputs
    join = JoinState(flows)
    a, b, c = (f.name for f in flows)
    join.offer(a, _frame(0, 0.0, b"A0"), 0, now=0.0)
    join.offer(b, _frame(0, 0.0, b"B0"), 0, now=0.0)
    [first] = join.ready({a, b, c}, now=3.5, wait_s=3.0)
    assert first.missing == ["Loc-3"] and first.lost == []
    assert (join.missing, join.not_started) == (0, 1)
    for name in (a, b, c):
        join.offer(name, _frame(1, 2.0, b"x"), 1, now=4.0)
    join.offer(a, _frame(2, 4.0, b"x"), 2, now=5.0)
    join.offer(b, _frame(2, 4.0, b"x"), 2, now=5.0)
    assert [(j.step, j.lost) for j in join.ready({a, b, c}, now=8.5, wait_s=3.0)] == [(1, []), (2, ["Loc-3"])]
    assert (join.missing, join.not_started) == (1, 1)  # now Loc-3 had delivered: its absence is a loss


def test_a_producer_that_starts_later_is_not_waited_for_nor_a_loss():
    """The CI failure of 2026-11-24: on a loaded machine Loc-3's source began two steps after the
    others. The map held every step behind step 0 for the whole bound waiting for a Loc-3 input that
    could never come, then ran it counting Loc-3 as lost (an error) because by then Loc-3 had
    delivered later steps. Once a producer's first output (seq 0) is there for a later step, the
    earlier steps run at once without it, counted as not started."""
    flows = SC.chain("TeamMap").inputs
    join = JoinState(flows)
    a, b, c = (f.name for f in flows)
    for step in (0, 1, 2):
        join.offer(a, _frame(step, 2.0 * step, b"A"), step, now=0.1 * step)
        join.offer(b, _frame(step, 2.0 * step, b"B"), step, now=0.1 * step)
    assert join.ready({a, b, c}, now=0.3, wait_s=3.0) == []  # c might still deliver step 0
    join.offer(c, _frame(0, 4.0, b"C"), 2, now=0.4)  # its first output is for step 2
    ran = join.ready({a, b, c}, now=0.4, wait_s=3.0)  # long before the bound
    assert [(j.step, j.missing, j.lost) for j in ran] == [(0, ["Loc-3"], []), (1, ["Loc-3"], []), (2, [], [])]
    assert (join.missing, join.not_started) == (0, 2)
    # the state migrates with it: a step later is still judged against when Loc-3 began
    moved = JoinState(flows)
    moved.restore(join.export())
    moved.offer(a, _frame(3, 6.0, b"A"), 3, now=1.0)
    moved.offer(b, _frame(3, 6.0, b"B"), 3, now=1.0)
    assert moved.ready({a, b, c}, now=2.0, wait_s=3.0) == []  # Loc-3 began before step 3: wait for it
    [late] = moved.ready({a, b, c}, now=4.5, wait_s=3.0)
    assert (late.step, late.lost) == (3, ["Loc-3"]) and moved.missing == 1


def test_a_first_output_that_is_not_seq_0_still_waits_but_is_not_a_loss():
    """Loc-3's seq 0 was lost and its seq 1 (step 2) came first: step 0's Loc-3 input may be that
    seq 0, resent, so the step waits the bound; if it does not come, Loc-3 had delivered nothing
    for an earlier step: not started, not a loss."""
    flows = SC.chain("TeamMap").inputs
    join = JoinState(flows)
    a, b, c = (f.name for f in flows)
    join.offer(a, _frame(0, 0.0, b"A"), 0, now=0.0)
    join.offer(b, _frame(0, 0.0, b"B"), 0, now=0.0)
    join.offer(c, _frame(1, 4.0, b"C"), 2, now=0.2)
    assert join.ready({a, b, c}, now=1.0, wait_s=3.0) == []
    [first] = join.ready({a, b, c}, now=3.1, wait_s=3.0)
    assert (first.step, first.missing, first.lost) == (0, ["Loc-3"], [])
    assert (join.missing, join.not_started) == (0, 1)


def test_an_earlier_step_that_comes_second_opens_the_join_not_late():
    """Producers' first inputs cross different routes (Loc-1 r1 -> r2, Loc-2 laptop -> r2), so the
    map may see Loc-1's step 3 before Loc-2's step 2. No step has run yet: step 2 is the first step,
    its input is not late (the join had counted it "late", an error, and dropped it)."""
    flows = SC.chain("TeamMap").inputs
    join = JoinState(flows)
    a, b, c = (f.name for f in flows)
    assert join.offer(a, _frame(0, 6.0, b"A3"), 3, now=0.0) == "new"
    assert join.offer(b, _frame(0, 4.0, b"B2"), 2, now=0.1) == "new"
    assert join.offer(c, _frame(0, 4.0, b"C2"), 2, now=0.1) == "new"
    assert join.offer(b, _frame(1, 6.0, b"B3"), 3, now=0.2) == "new"
    assert join.offer(c, _frame(1, 6.0, b"C3"), 3, now=0.2) == "new"
    ran = join.ready({a, b, c}, now=0.3, wait_s=3.0)  # Loc-1 began at step 3: step 2 need not wait
    assert [(j.step, j.missing, j.lost) for j in ran] == [(2, ["Loc-1"], []), (3, [], [])]
    assert join.late == 0 and (join.missing, join.not_started) == (0, 1)
    # once a step ran, an input for an earlier one is late
    assert join.offer(a, _frame(5, 2.0, b"A1"), 1, now=0.4) == "late" and join.late == 1
