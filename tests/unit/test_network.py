"""A network's cliques (every pair of their nodes linked, kept as one value) answer exactly as the
same links listed one by one: routes with their tie-break, reachability, radios, media, changes."""

import networkx as nx
from hypothesis import given, settings, strategies as st

from autopower.model.network import Clique, Link, Network, build_network
from autopower.simulation.synthetic import loaded_fleet_scenario


@st.composite
def networks(draw):
    n = draw(st.integers(2, 7))
    nodes = [f"r{i + 1}" for i in range(n)] + ["laptop"]
    media = ["802.11a", "bluetooth", "gsm"]
    cliques, pairs = [], set()
    for k in range(draw(st.integers(0, 2))):
        members = draw(st.lists(st.sampled_from(nodes), min_size=2, max_size=len(nodes), unique=True))
        members = sorted(members, key=nodes.index)
        new = {frozenset((a, b)) for i, a in enumerate(members) for b in members[i + 1:]}
        if new & pairs:
            continue  # two cliques may share one node, never a pair
        pairs |= new
        cliques.append(Clique(nodes=tuple(members), medium=draw(st.sampled_from(media)), group=f"c{k}"))
    links = []
    for a, b in draw(st.lists(st.tuples(st.sampled_from(nodes), st.sampled_from(nodes)), max_size=8)):
        if a != b and frozenset((a, b)) not in pairs:
            pairs.add(frozenset((a, b)))
            links.append(Link(a=a, b=b, medium=draw(st.sampled_from(media)), group=draw(st.sampled_from(["g1", "g2"]))))
    return Network(nodes, "laptop", links, "explicit", cliques)


def assert_same(net: Network, flat: Network) -> None:
    """`net` (with cliques) answers as `flat` (its links one by one) and as networkx's BFS."""
    assert set(net.links) == set(flat.links) and net == flat
    assert net.media_by_group() == flat.media_by_group()
    for a in net.nodes:
        assert net.media_of(a) == flat.media_of(a)
        expected = nx.single_source_shortest_path(flat.graph, a)
        for b in net.nodes:
            assert net.path(a, b) == expected.get(b), (a, b)
            assert net.reachable(a, b) == (b in expected)
            assert net.medium_between(a, b) == flat.medium_between(a, b)
            if b in expected:
                assert net.route(a, b) == flat.route(a, b)


@settings(max_examples=150, deadline=None)
@given(net=networks(), data=st.data())
def test_cliques_answer_as_their_links(net, data):
    assert_same(net, Network(net.nodes, net.basestation, net.links, net.topology))
    a, b = data.draw(st.sampled_from(net.nodes)), data.draw(st.sampled_from(net.nodes))
    node = data.draw(st.sampled_from(net.nodes[:-1]))
    flat = Network(net.nodes, net.basestation, net.links, net.topology)
    assert_same(net.without_link(a, b), flat.without_link(a, b))
    assert_same(net.without_nodes({a, b}), flat.without_nodes({a, b}))
    assert set(net.with_node_media(node, "gsm", "bluetooth").links) == set(flat.with_node_media(node, "gsm", "bluetooth").links)


def test_a_fully_connected_fleet_is_one_clique_not_n_squared_links():
    scenario = loaded_fleet_scenario(1000, 3, hosts="own")
    net = build_network(scenario, media={"robot-robot": "bluetooth", "laptop-robot": "gsm"})
    assert len(net.explicit) == 1000 and len(net.cliques) == 1 and "links" not in vars(net)
    assert net.route("r5", "r999") == [("r5", "r999", "bluetooth")]
    assert net.route("r5", "laptop") == [("r5", "laptop", "gsm")]
    assert net.media_of("r5") == {"bluetooth", "gsm"} and net.media_of("laptop") == {"gsm"}
    assert "links" not in vars(net)  # nothing above listed the 499,500 robot-robot links
