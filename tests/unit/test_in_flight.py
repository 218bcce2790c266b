"""What a node says at its stop (autopower.node.in_flight): every frame it has in hand, and what its
sources produced in each run. The replay takes an output as in flight only if a node names it, so
these must be exact: a seq named that no node held would hide a loss, one held but not named would
show as lost."""

from __future__ import annotations

from autopower.basestation.coordinator import CoordinatorConfig
from autopower.model.loading import load_scenario
from autopower.node.ports import SinkListener
from tests.unit.sim_team import SimTeam

SC = load_scenario("paper-fig7")


def _team() -> tuple[SimTeam, dict]:
    team = SimTeam(SC, config=CoordinatorConfig(speed=1.0, auto_replan=False, pins={"Loc-1": "laptop"}))
    delivered: dict = {}
    for rt in team.nodes.values():
        rt.listen(SinkListener(output=lambda chain, run, seq, data: delivered.setdefault((chain, run), set()).add(seq)))
    team.join()
    return team, delivered


def test_every_frame_produced_is_delivered_or_named_in_flight_by_some_node():
    """r1 cut off from the laptop (one way, silently): Loc-1's frames pile up in r1's custody, and
    its results for r1 in the laptop's. At the stop, every Loc-1 output produced is delivered or
    named by a node, and every seq named is one the node really holds."""
    team, delivered = _team()
    team.run_until(10.0)
    team.cut_silently("r1", "laptop", one_way=True)
    team.run_exchanging_statuses(16.0)
    r1 = team.nodes["r1"]
    runner = r1.sources["Loc-1"]
    assert r1.feeds.produced_by_run.counts()[("Loc-1", runner.run)] == runner.seq  # seqs 0 .. seq-1
    held: dict = {}
    for rt in team.nodes.values():
        for key, seqs in rt.in_flight_at_stop().items():
            held.setdefault(key, set()).update(seqs)
    key = ("Loc-1", runner.run)
    got = delivered.get(key, set())
    assert held[key]  # the cut left frames in r1's custody
    assert set(range(runner.seq)) <= got | held[key]  # nothing produced is unaccounted
    in_custody = {f.seq for f in r1.custody.frames() if f.chain == "Loc-1"}
    assert in_custody and in_custody <= held[key]
    # a flow's or another chain's frames never count for Loc-1
    assert all(chain in {c.name for c in SC.chains} for chain, _ in held)



def test_a_moving_stages_state_names_the_frames_it_carries():
    """A stage moved out whose state waits for a route (parked) carries inputs it had not run and
    outputs not yet acknowledged: no other place of the node holds them, so the node names them."""
    from autopower.protocol import ChainFrame, StateTransfer, encode

    team, _ = _team()
    laptop = team.nodes["laptop"]

    def frame(seq: int, target: int) -> ChainFrame:
        return ChainFrame(chain="Blob-2", run=3, seq=seq, target=target, t_virtual=0.0, t_unix=0.0,
                          payload_len=1, payload=b"x")

    state = StateTransfer(stage="Blob-2", generation=1, chain="Blob-2", run=3, state=b"", next_seq=9,
                          pending=(frame(10, 0),), t_export_unix=0.0, from_node="laptop",
                          outputs=(frame(7, 1), frame(8, 1)))
    laptop.hosting.park("r2", encode(state), "Blob-2")
    laptop.hosting.park("r2", b"not a state", "Blob-2")  # names nothing, breaks nothing
    assert laptop.in_flight_at_stop()[("Blob-2", 3)] == {7, 8, 10}
