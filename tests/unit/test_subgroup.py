"""The subgroup two-phase commit on InMemoryBus: commit, abort on timeout / member loss, no double run."""

from __future__ import annotations

import pytest

from autopower.protocol import Keys, SubgroupDecision, SubgroupMove, encode
from autopower.runtime.bus import InMemoryHub
from autopower.runtime.subgroup import Phase, SubgroupAgreement

KEYS = Keys("t")
MOVES = (SubgroupMove(stage="Loc-1", from_node=None, to_node="r1"),
         SubgroupMove(stage="Loc-2", from_node="r2", to_node="r3"))


class Clock:
    t = 0.0

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def group():
    hub = InMemoryHub(synchronous=False)
    clock = Clock()
    applied: dict[str, list[str]] = {}
    nodes = {}
    for name in ("r1", "r2", "r3"):
        bus = hub.bus(name)
        applied[name] = []
        node = SubgroupAgreement(node=name, bus=bus, keys=KEYS, now=clock, timeout_s=1.0,
                                 on_commit=lambda p, n=name: applied[n].append(p.round_id))
        bus.subscribe(KEYS.subgroup, lambda key, payload, n=node: n.on_message(payload))
        nodes[name] = node
    return hub, clock, nodes, applied


def test_every_member_accepts_then_all_commit_once(group):
    hub, clock, nodes, applied = group
    rid = nodes["r1"].propose(("r1", "r2", "r3"), {"Loc-1": "r1", "Loc-2": "r3"}, MOVES, 7, "raise min lifetime")
    assert nodes["r1"].phase is Phase.PROPOSED
    hub.pump()
    assert applied == {"r1": [rid], "r2": [rid], "r3": [rid]}
    assert all(n.phase is Phase.IDLE for n in nodes.values())
    # a repeated decision (e.g. a retransmission) never applies a round twice
    nodes["r2"].round = nodes["r1"].round  # None: r2 is idle; the duplicate is simply ignored
    nodes["r1"].bus.publish(KEYS.subgroup, encode(SubgroupDecision(round_id=rid, commit=True, reason="dup")))
    hub.pump()
    assert applied == {"r1": [rid], "r2": [rid], "r3": [rid]}
    assert nodes["r1"].agreement_s and nodes["r1"].committed == 1


def test_leader_aborts_when_a_vote_does_not_come_in_time(group):
    hub, clock, nodes, applied = group
    nodes["r3"].bus.close()  # r3 hears nothing and says nothing
    nodes["r1"].propose(("r1", "r2", "r3"), {}, MOVES, 8, "x")
    hub.pump()
    assert nodes["r2"].phase is Phase.ACCEPTED and not applied["r1"]
    clock.t = 1.01
    nodes["r1"].on_timer()
    hub.pump()
    assert nodes["r1"].aborted == 1 and nodes["r2"].aborted == 1
    assert applied == {"r1": [], "r2": [], "r3": []}
    assert all(n.phase is Phase.IDLE for n in (nodes["r1"], nodes["r2"]))


def test_leader_aborts_on_member_loss(group):
    hub, clock, nodes, applied = group
    rid = nodes["r1"].propose(("r1", "r2", "r3"), {}, MOVES, 9, "x")
    # deliver the proposal only; r3 is lost before its vote is counted
    hub.pending.clear()
    nodes["r1"].on_member_lost("r3")
    hub.pump()
    assert nodes["r1"].decided[rid] is False
    assert applied["r1"] == []


def test_member_aborts_when_the_leader_is_lost_or_silent(group):
    hub, clock, nodes, applied = group
    nodes["r1"].propose(("r1", "r2", "r3"), {}, MOVES, 10, "x")
    hub.pump(limit=3)  # the proposal reaches every node...
    hub.pending.clear()  # ...and the votes go nowhere
    member = nodes["r2"]
    assert member.phase is Phase.ACCEPTED
    member.on_member_lost("r3")  # another member: the leader's call, not ours
    assert member.phase is Phase.ACCEPTED
    member.on_member_lost("r1")
    assert member.phase is Phase.IDLE and member.aborted == 1
    clock.t = 5.0
    nodes["r3"].on_timer()  # silent leader: presumed abort after the member's deadline
    assert nodes["r3"].phase is Phase.IDLE and nodes["r3"].aborted == 1
    assert applied == {"r1": [], "r2": [], "r3": []}


def test_a_busy_member_rejects_a_second_round(group):
    hub, clock, nodes, applied = group
    first = nodes["r1"].propose(("r1", "r2"), {}, MOVES[:1], 11, "x")
    hub.pump(limit=3)  # r2 accepted the first round; its vote has not arrived
    second = nodes["r3"].propose(("r3", "r2"), {}, MOVES[1:], 12, "y")
    hub.pump()
    assert nodes["r3"].decided[second] is False  # rejected: r2 was busy
    assert applied["r2"] == [first] and applied["r1"] == [first]


class _Line:
    """r1 - r2 - r3 in a line (the r1-r3 link cut): a publish reaches the neighbours only, as Zenoh
    peers do not relay; ``relay`` carries a message to the others through r2 (`Relayer.send_beyond_sight`)."""

    NEIGHBOURS = {"r1": {"r2"}, "r2": {"r1", "r3"}, "r3": {"r2"}}

    def __init__(self):
        self.nodes: dict[str, SubgroupAgreement] = {}
        self.queue: list[tuple[str, bytes]] = []
        self.relayed: list[tuple[str, str]] = []

    def bus(self, name: str):
        line = self

        class Bus:
            def publish(self, key, payload, *, reliable=True):
                line.queue += [(n, payload) for n in sorted(line.NEIGHBOURS[name])]

        return Bus()

    def relay(self, name: str):
        def send_beyond_sight(dests, key, payload, *, reliable=True):
            for dest in dests:
                if dest not in self.NEIGHBOURS[name]:
                    self.relayed.append((name, dest))
                    self.queue.append((dest, payload))
        return send_beyond_sight

    def pump(self):
        while self.queue:
            dest, payload = self.queue.pop(0)
            self.nodes[dest].on_message(payload)


@pytest.mark.parametrize("relaying", [True, False])
def test_a_round_reaches_a_member_behind_a_cut_link_through_another(relaying):
    """Live random faults, seed 8: r1 led rounds of r1, r2, r3 with its link to r2 cut (r2 reached
    through r3); published only, the proposals never reached r2, and eight rounds in a row timed
    out while Loc-2 and Blob-2 ran nowhere for 130 mission seconds."""
    line, clock = _Line(), Clock()
    applied: dict[str, list[str]] = {}
    for name in ("r1", "r2", "r3"):
        applied[name] = []
        line.nodes[name] = SubgroupAgreement(node=name, bus=line.bus(name), keys=KEYS, now=clock, timeout_s=1.0,
                                             on_commit=lambda p, n=name: applied[n].append(p.round_id),
                                             relay=line.relay(name) if relaying else None)
    rid = line.nodes["r1"].propose(("r1", "r2", "r3"), {}, MOVES, 7, "x")
    line.pump()
    if relaying:
        assert applied == {"r1": [rid], "r2": [rid], "r3": [rid]}
        assert ("r1", "r3") in line.relayed and ("r3", "r1") in line.relayed  # proposal and decision; the vote
    else:  # what it did before: r3 never votes, the round times out
        assert applied == {"r1": [], "r2": [], "r3": []} and line.nodes["r1"].phase is Phase.PROPOSED
