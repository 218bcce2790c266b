"""The application-level relay: direct when in sight, else along the reported graph, hop by hop."""

from __future__ import annotations

from autopower.protocol import Keys, NodeStatus, Relayed, decode, encode
from autopower.runtime.bus import InMemoryHub
from autopower.runtime.relay import Relayer

KEYS = Keys("t")


def status(node: str, sees: list[str]) -> NodeStatus:
    return NodeStatus(node=node, t_virtual=0.0, t_unix=0.0, plan_epoch=1, initial_j=None, battery_j=None,
                      energy_j={}, power_w={}, cpu_utilisation=0.0, hosted={}, sources={}, sinks={},
                      links={n: True for n in sees}, runs={}, compute_ms={}, queue_depth=0, errors={},
                      counters={}, depleted=False)


def make(hub, node, direct):
    r = Relayer(node=node, bus=hub.bus(node), keys=KEYS)
    for n in direct:
        r.on_liveliness(n, True)
    return r


def test_direct_when_in_sight_relayed_through_a_robot_that_sees_the_destination():
    hub = InMemoryHub(record=True)
    base = make(hub, "laptop", ["r2", "r3"])  # the laptop-r1 link is cut
    base.on_status(status("r2", ["laptop", "r1", "r3"]))
    base.on_status(status("r3", ["laptop", "r2"]))
    assert base.path_to("r1") == ["laptop", "r2", "r1"]
    assert base.send("r2", KEYS.node_control("r2"), b"direct")
    assert hub.published[-1][0] == KEYS.node_control("r2")
    assert base.send("r1", KEYS.node_control("r1"), b"order")
    key, payload, _ = hub.published[-1]
    assert key == KEYS.node_relay("r2")
    msg = decode(payload, Relayed)
    assert msg.path == ("laptop", "r2", "r1") and msg.key == KEYS.node_control("r1")

    # r2 passes it on; r1 is its end and gets the original key and payload
    r2 = make(hub, "r2", ["laptop", "r1", "r3"])
    assert r2.on_relay(payload) is None
    key2, payload2, _ = hub.published[-1]
    assert key2 == KEYS.node_relay("r1")
    r1 = make(hub, "r1", ["r2", "r3", "laptop"])  # r1's lease has not expired yet
    assert r1.on_relay(payload2) == (KEYS.node_control("r1"), b"order")
    # ...but the relayed message told it the laptop no longer sees it: answer through r2 too
    assert "laptop" not in r1.direct and "laptop" in r1.shunned
    r1.on_status(status("r2", ["laptop", "r1"]))
    assert r1.path_to("laptop") == ["r1", "r2", "laptop"]
    r1.on_liveliness("laptop", True)  # the link is back for real
    assert "laptop" in r1.direct


def test_unreachable_is_counted_not_raised_and_a_gone_next_hop_is_dropped():
    hub = InMemoryHub(record=True)
    counted = []
    lonely = Relayer(node="r1", bus=hub.bus("r1"), keys=KEYS, count=lambda what, detail="": counted.append(what))
    assert not lonely.reachable("laptop")
    assert lonely.send("laptop", KEYS.inbox, b"x") is False
    assert counted == ["no-relay-path"]
    payload = encode(Relayed(path=("laptop", "r1", "r3"), hop=1, key=KEYS.node_control("r3"), payload=b"y"))
    assert lonely.on_relay(payload) is None  # r3 is not in sight: dropped (the origin resends what matters)
    assert counted[-1] == "relay-next-hop-gone"


def test_broadcast_reaches_those_out_of_sight():
    hub = InMemoryHub(record=True)
    base = make(hub, "laptop", ["r2"])
    base.on_status(status("r2", ["r1", "r3", "laptop"]))
    base.send_beyond_sight(["r1", "r2", "r3"], KEYS.plan, b"plan")
    relayed = sorted(decode(p, Relayed).path[-1] for k, p, _ in hub.published if k == KEYS.node_relay("r2"))
    assert relayed == ["r1", "r3"]


def test_a_late_relayed_message_does_not_cut_off_a_node_that_is_seen_directly():
    """A relayed copy sent while the link was cut may arrive after it is back: the next direct
    message from that node proves the link works and undoes the shun."""
    hub = InMemoryHub(record=True)
    r1 = make(hub, "r1", ["r2", "laptop"])
    late = encode(Relayed(path=("laptop", "r2", "r1"), hop=2, key=KEYS.plan, payload=b"old plan"))
    assert r1.on_relay(late) == (KEYS.plan, b"old plan")
    assert "laptop" not in r1.direct  # shunned: the laptop said (by relaying) it did not see us
    r1.on_status(status("r2", ["r1"]))
    assert not r1.reachable("laptop")
    r1.on_direct("laptop")  # ...but its status just arrived on its own key, directly
    assert "laptop" in r1.direct and r1.path_to("laptop") == ["r1", "laptop"]
    r1.on_direct("r9")  # nothing to undo for a node we never shunned
    assert "r9" not in r1.direct


def test_a_status_lists_the_nodes_a_robot_has_links_with_and_has_seen_not_the_whole_team():
    """A robot's status grows with its own links: at 100 robots it listed all 100 (1.4 of 2.5 kB)."""
    from autopower.node.runtime import NodeRuntime
    from autopower.simulation.synthetic import paper_fleet

    _, fleet = paper_fleet(12, topology="neighbours", neighbours=2)
    rt = NodeRuntime(node="r1", scenario=fleet, bus=InMemoryHub().bus("r1"), keys=KEYS)
    assert set(rt.status(1.0).links) == {"laptop", "r2", "r3", "r11", "r12"}  # none up yet: all reported down
    rt.on_liveliness("r2", True)
    rt.on_liveliness("r7", True)  # seen, though the scenario has no r1-r7 link: it is there
    rt.on_liveliness("r7", False)
    links = rt.status(1.0).links
    assert links["r2"] and not links["laptop"] and links["r7"] is False  # gone: reported down until back
    assert set(links) == {"laptop", "r2", "r3", "r11", "r12", "r7"}
    for i in range(1000):  # names from the network that are not the team's: nothing grows
        rt.on_liveliness(f"stranger{i}", True)
        rt.on_liveliness(f"stranger{i}", False)
    assert set(rt.status(1.0).links) == {"laptop", "r2", "r3", "r11", "r12", "r7"}


def test_a_relayed_message_from_a_node_that_sees_us_does_not_shun_it_and_a_shun_ends_when_it_sees_us():
    """Two nodes must not shun each other for good: a node relays to us also when it shunned us
    (on a relayed message of ours), and then its status still lists us. Only a node whose status
    does not list us is cut from us; its next status that lists us ends the shun."""
    hub = InMemoryHub(record=True)
    r20 = make(hub, "r20", ["r1", "laptop"])
    relayed = encode(Relayed(path=("laptop", "r1", "r20"), hop=2, key=KEYS.plan, payload=b"plan"))
    # at start-up the laptop relayed before it saw our token: its status does not list us yet
    r20.on_status(status("laptop", ["r1"]))
    assert r20.on_relay(relayed) == (KEYS.plan, b"plan")
    assert "laptop" in r20.shunned and "laptop" not in r20.direct
    r20.on_status(status("laptop", ["r1", "r20"]))  # now it sees us
    assert "laptop" in r20.direct and "laptop" not in r20.shunned
    # the laptop, meanwhile, got our statuses relayed (we had shunned it) while we listed it
    laptop = make(hub, "laptop", ["r1", "r20"])
    laptop.on_status(status("r20", ["r1", "laptop"]))
    ours = encode(Relayed(path=("r20", "r1", "laptop"), hop=2, key=KEYS.status("r20"), payload=b"s"))
    assert laptop.on_relay(ours) == (KEYS.status("r20"), b"s")
    assert "r20" in laptop.direct and "r20" not in laptop.shunned  # not taken for a cut
    assert laptop.send("r20", KEYS.node_control("r20"), b"order")
    assert hub.published[-1][0] == KEYS.node_control("r20")  # directly


def test_a_view_naming_the_nodes_out_of_sight_routes_as_one_naming_those_in_sight():
    """The base station's view to a robot names whom it does not see when they are fewer
    (`PeerStatus.unseen`): read against the team, the robot routes through it as before."""
    from autopower.protocol import PeerStatus

    hub = InMemoryHub(record=True)
    team = ("laptop", "r1", "r2", "r3", "r4")
    r1 = Relayer(node="r1", bus=hub.bus("r1"), keys=KEYS, team=team)
    r1.on_liveliness("laptop", True)
    view = PeerStatus(node="laptop", t_unix=0.0, plan_epoch=1, battery_j=None, hosted={}, generations={},
                      links={}, unseen=("r4",))
    r1.on_status(view)
    assert r1.views["laptop"] == {"r1", "r2", "r3"}
    assert r1.path_to("r3") == ["r1", "laptop", "r3"] and r1.path_to("r4") is None
    assert not r1._shuns("laptop")  # it sees us: a message it relays to us cuts nothing
    r1.on_status(PeerStatus(node="laptop", t_unix=1.0, plan_epoch=1, battery_j=None, hosted={}, generations={},
                            links={}, unseen=("r1", "r4")))
    assert r1._shuns("laptop")


def test_reached_is_every_node_reachable_says_we_reach_found_by_one_search():
    """`Relayer.reached` answers as `reachable` does for every node (what a subgroup round's members
    are), with one search over the links instead of one per robot."""
    import random

    hub = InMemoryHub()
    nodes = [f"r{i}" for i in range(40)]
    for seed in range(20):
        rng = random.Random(seed)
        r0 = Relayer(node="r0", bus=hub.bus(f"r0-{seed}"), keys=KEYS)
        r0.direct = {n for n in nodes[1:] if rng.random() < 0.05}
        r0.views = {n: {m for m in nodes if m != n and rng.random() < 0.04} for n in nodes[1:]}
        searches = 0
        path_to = r0.path_to

        def counted(dest, path_to=path_to):
            nonlocal searches
            searches += 1
            return path_to(dest)

        r0.path_to = counted
        assert r0.reached() == {n for n in nodes if r0.reachable(n)}
        searches_each = searches
        searches = 0
        r0.reached()
        assert searches == 0 and searches_each == len(nodes)
