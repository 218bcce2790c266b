"""End-to-end signatures (`runtime.signatures`): relayed payloads and subgroup rounds carry their author.

Real keys and certificates from a team CA (`deploy.pki`), real ECDSA; the buses are in memory.
Each hostile case is also run without signatures, to show the attack works there (so the test
can fail) and that signing is what stops it.
"""

from __future__ import annotations

import dataclasses

import pytest

from autopower.deploy.pki import TeamCA, identity_in
from autopower.errors import ProtocolError
from autopower.protocol import Keys, Relayed, SubgroupDecision, SubgroupMove, SubgroupVote, encode
from autopower.protocol.access import TeamAccess
from autopower.runtime.bus import InMemoryHub
from autopower.runtime.relay import Relayer
from autopower.runtime.signatures import Signing
from autopower.runtime.subgroup import Phase, SubgroupAgreement

KEYS = Keys("t")
ACCESS = TeamAccess(KEYS, "laptop", ("r1", "r2", "r3"))
NODES = ("laptop", "r1", "r2", "r3")


@pytest.fixture(scope="module")
def ids(tmp_path_factory):
    root = tmp_path_factory.mktemp("pki")
    ca = TeamCA.create(root / "ca", "t")
    for node in NODES:
        ca.issue(node, ["127.0.0.1"], root / "ids")
    # a stranger's CA that also calls its identity "laptop"
    TeamCA.create(root / "evil-ca", "t").issue("laptop", ["127.0.0.1"], root / "evil")

    def signing(node: str, where: str = "ids") -> Signing:
        files = identity_in(root / where, node)
        return Signing.load(node, identity_in(root / "ids", node).ca, files.cert, files.key)

    return signing


PLAN = b"a plan written by r2, epoch 10**6"  # the relayer never decodes what it carries


def test_a_signature_names_its_author_and_covers_every_field(ids):
    laptop, r1 = ids("laptop"), ids("r1")
    msg = laptop.sign(Relayed(path=("laptop", "r2", "r1"), hop=1, key=KEYS.plan, payload=b"p"))
    assert r1.signer(msg) == "laptop"
    assert r1.signer(dataclasses.replace(msg, hop=2), hop=1) == "laptop"  # the hop is not signed
    for changed in ({"payload": b"q"}, {"key": KEYS.node_control("r1")}, {"path": ("laptop", "r3", "r1")}):
        with pytest.raises(ProtocolError, match="does not match laptop's key"):
            r1.signer(dataclasses.replace(msg, **changed))
    with pytest.raises(ProtocolError, match="unsigned"):
        r1.signer(Relayed(path=("laptop", "r1"), hop=1, key=KEYS.plan, payload=b"p"))
    stranger = ids("laptop", where="evil")  # same name, another CA
    with pytest.raises(ProtocolError, match="not issued by the team CA"):
        r1.signer(stranger.sign(msg))


def relay_pair(ids, signed: bool):
    hub = InMemoryHub()
    r1 = Relayer(node="r1", bus=hub.bus("r1"), keys=KEYS, access=ACCESS, signing=ids("r1") if signed else None,
                 count=lambda what, detail="": counts.append(what))
    counts: list[str] = []
    return r1, counts


@pytest.mark.parametrize("signed", [True, False])
def test_a_robot_relaying_a_plan_in_the_base_stations_name_is_dropped(ids, signed):
    r1, counts = relay_pair(ids, signed)
    # r2 relays "from the laptop" a plan it wrote itself: unsigned, or signed with its own key
    forged = Relayed(path=("laptop", "r2", "r1"), hop=2, key=KEYS.plan, payload=PLAN)
    forged_by_r2 = dataclasses.replace(ids("r2").sign(dataclasses.replace(forged, hop=1)), hop=2)
    delivered = [r1.on_relay(encode(m)) for m in (forged, forged_by_r2)]
    if not signed:  # without signatures the origin is whatever the relaying robot writes
        assert delivered[0] == (KEYS.plan, forged.payload)
        return
    assert delivered == [None, None] and counts == ["forged", "forged"]
    # the laptop's own plan, relayed by the same robot, arrives
    real = dataclasses.replace(ids("laptop").sign(dataclasses.replace(forged, hop=1)), hop=2)
    assert r1.on_relay(encode(real)) == (KEYS.plan, PLAN)


def test_what_a_relayer_sends_is_signed_and_forwarded_unchanged(ids):
    hub = InMemoryHub()
    got = []
    laptop = Relayer(node="laptop", bus=hub.bus("laptop"), keys=KEYS, signing=ids("laptop"))
    r2 = Relayer(node="r2", bus=hub.bus("r2"), keys=KEYS, signing=ids("r2"))
    r1 = Relayer(node="r1", bus=hub.bus("r1"), keys=KEYS, access=ACCESS, signing=ids("r1"))
    hub.bus("r2").subscribe(KEYS.node_relay("r2"), lambda k, p: r2.on_relay(p))
    hub.bus("r1").subscribe(KEYS.node_relay("r1"), lambda k, p: got.append(r1.on_relay(p)))
    laptop.on_liveliness("r2", True)
    r2.on_liveliness("r1", True)
    laptop.views["r2"] = {"r1", "laptop"}
    assert laptop.send("r1", KEYS.plan, b"the plan")
    assert got == [(KEYS.plan, b"the plan")]
    assert r1.signing.verified == 1 and r1.signing.forged == 0


@pytest.fixture
def subgroup(ids):
    def make(signed: bool):
        hub = InMemoryHub(synchronous=False)
        applied: dict[str, list[str]] = {"r1": [], "r3": []}
        nodes = {}
        for name in ("r1", "r3"):  # r2 is a member that never answers
            bus = hub.bus(name)
            node = SubgroupAgreement(node=name, bus=bus, keys=KEYS, now=lambda: 0.0, timeout_s=1.0,
                                     on_commit=lambda p, n=name: applied[n].append(p.round_id),
                                     signing=ids(name) if signed else None)
            bus.subscribe(KEYS.subgroup, lambda key, payload, n=node: n.on_message(payload))
            nodes[name] = node
        return hub, nodes, applied
    return make


@pytest.mark.parametrize("signed", [True, False])
def test_a_forged_subgroup_vote_has_no_effect(ids, subgroup, signed):
    hub, nodes, applied = subgroup(signed)
    moves = (SubgroupMove(stage="Loc-2", from_node=None, to_node="r1"),)
    round_id = nodes["r1"].propose(("r1", "r2"), {"Loc-2": "r1"}, moves, 7, "test")
    hub.pump()
    # r3 (a robot: it may put on the subgroup key) votes in r2's name, unsigned and signed as itself
    vote = SubgroupVote(round_id=round_id, node="r2", accept=True, reason="")
    r3 = hub.bus("r3")
    r3.publish(KEYS.subgroup, encode(vote))
    if signed:
        r3.publish(KEYS.subgroup, encode(ids("r3").sign(vote)))
    hub.pump()
    if not signed:  # without signatures the forged vote commits the round
        assert applied["r1"] == [round_id]
        return
    assert applied["r1"] == [] and nodes["r1"].phase is Phase.PROPOSED
    assert nodes["r1"].signing.forged == 2
    # only r2's own signed vote counts
    r3.publish(KEYS.subgroup, encode(ids("r2").sign(vote)))
    hub.pump()
    assert applied["r1"] == [round_id]


def test_a_forged_decision_from_a_non_leader_is_ignored(ids, subgroup):
    hub, nodes, applied = subgroup(True)
    sent: list[bytes] = []  # what the leader publishes, held back from r3 until the test hands it over
    hub_l = InMemoryHub()
    hub_l.bus("tap").subscribe(KEYS.subgroup, lambda key, payload: sent.append(payload))
    leader = SubgroupAgreement(node="r1", bus=hub_l.bus("r1"), keys=KEYS, now=lambda: 0.0,
                               on_commit=lambda p: None, signing=ids("r1"))
    moves = (SubgroupMove(stage="Loc-2", from_node=None, to_node="r3"),)
    round_id = leader.propose(("r1", "r3"), {"Loc-2": "r3"}, moves, 7, "test")
    nodes["r3"].on_message(sent[0])  # r3 hears the leader's signed proposal and accepts it
    assert nodes["r3"].phase is Phase.ACCEPTED
    decision = SubgroupDecision(round_id=round_id, commit=True, reason="forged")
    for forged in (decision, ids("r2").sign(decision)):  # unsigned, and signed by another robot
        nodes["r3"].on_message(encode(forged))
    assert applied["r3"] == [] and nodes["r3"].phase is Phase.ACCEPTED and nodes["r3"].signing.forged == 2
    nodes["r3"].on_message(encode(ids("r1").sign(decision)))  # the leader's own decision
    assert applied["r3"] == [round_id]
