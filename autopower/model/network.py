"""The concrete network of a topology and media choice: links, radios per node, routes.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from itertools import product
from typing import Iterable, Mapping, Sequence

import networkx as nx

from autopower.errors import ScenarioError
from autopower.model.scenario import Scenario


def connected_parts(nodes: Iterable[str], pairs: Iterable[tuple[str, str]]) -> dict[str, int]:
    """Node -> the number of its connected part (union-find over the pairs; parts numbered in
    the nodes' order)."""
    nodes = list(nodes)
    parent = {n: n for n in nodes}

    def find(n: str) -> str:
        while parent[n] != n:
            parent[n] = parent[parent[n]]
            n = parent[n]
        return n

    for a, b in pairs:
        ra, rb = find(a), find(b)
        if ra != rb:
            parent[ra] = rb
    roots: dict[str, int] = {}
    return {n: roots.setdefault(find(n), len(roots)) for n in nodes}

# ---------------------------------------------------------------------------------------------
# Networks
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class Link:
    a: str
    b: str
    medium: str
    group: str  # the media-choice group it belongs to ("laptop-robot", "robot-robot", ...)

    def touches(self, node: str) -> bool:
        return node in (self.a, self.b)


@dataclass(frozen=True, kw_only=True)
class Clique:
    """Every pair of `nodes` linked on one medium: a fully connected fleet's robots, kept as one
    value because a planner never needs its n^2/2 links one by one (1,000 robots: 499,500)."""

    nodes: tuple[str, ...]
    medium: str
    group: str

    def links(self) -> list[Link]:
        return [Link(a=a, b=b, medium=self.medium, group=self.group)
                for i, a in enumerate(self.nodes) for b in self.nodes[i + 1:]]


class Network:
    """A concrete network: nodes, links with a chosen medium each, shortest-hop routing.

    Links are `explicit` ones plus `cliques` (sets of nodes linked pairwise). `links` lists them
    all (built on first use); routes, media and reachability are answered without it.
    """

    def __init__(self, nodes: Sequence[str], basestation: str, links: Sequence[Link], topology: str = "explicit",
                 cliques: Sequence[Clique] = ()):
        self.nodes = tuple(nodes)
        self.basestation = basestation
        self.explicit = tuple(links)
        self.cliques = tuple(c for c in cliques if len(c.nodes) > 1)  # one node has no links
        self.topology = topology
        known = set(self.nodes)
        self._clique_of: dict[str, list[int]] = {}  # node -> indices of its cliques
        for i, clique in enumerate(self.cliques):
            for end in clique.nodes:
                if end not in known:
                    raise ScenarioError(f"clique {clique.group}: unknown node {end!r}")
                self._clique_of.setdefault(end, []).append(i)
        for i, clique in enumerate(self.cliques):
            for other in self.cliques[i + 1:]:
                common = set(clique.nodes) & set(other.nodes)
                if len(common) > 1:
                    a, b = sorted(common)[:2]
                    raise ScenarioError(f"two links between {a} and {b}; keep one (with one medium)")
        self._adjacent: dict[str, dict[str, Link]] = {}  # explicit links only
        for link in self.explicit:
            for end in (link.a, link.b):
                if end not in known:
                    raise ScenarioError(f"link {link.a}-{link.b}: unknown node {end!r}")
            if link.b in self._adjacent.get(link.a, {}) or self.clique_between(link.a, link.b) is not None:
                raise ScenarioError(f"two links between {link.a} and {link.b}; keep one (with one medium)")
            self._adjacent.setdefault(link.a, {})[link.b] = link
            self._adjacent.setdefault(link.b, {})[link.a] = link

    @cached_property
    def links(self) -> tuple[Link, ...]:
        return self.explicit + tuple(link for clique in self.cliques for link in clique.links())

    def clique_between(self, a: str, b: str) -> int | None:
        """Index of the clique linking a and b (two cliques share at most one node)."""
        mine = self._clique_of.get(a)
        if mine and a != b:
            theirs = self._clique_of.get(b, ())
            for i in mine:
                if i in theirs:
                    return i
        return None

    def link_between(self, a: str, b: str) -> Link | None:
        link = self._adjacent.get(a, {}).get(b)
        if link is None:
            i = self.clique_between(a, b)
            if i is not None:
                c = self.cliques[i]
                link = Link(a=a, b=b, medium=c.medium, group=c.group)
        return link

    def medium_between(self, a: str, b: str) -> str | None:
        link = self._adjacent.get(a, {}).get(b)
        if link is not None:
            return link.medium
        i = self.clique_between(a, b)
        return None if i is None else self.cliques[i].medium

    @cached_property
    def graph(self) -> nx.Graph:
        """The links as a graph whose every adjacency list is in node order (every clique's
        pairs materialised: for callers that need a graph, not for routing)."""
        order = {n: i for i, n in enumerate(self.nodes)}
        graph = nx.Graph()
        graph.add_nodes_from(self.nodes)
        ends = [tuple(sorted((l.a, l.b), key=order.__getitem__)) + (l,) for l in self.links]
        for a, b, link in sorted(ends, key=lambda e: (order[e[0]], order[e[1]])):
            graph.add_edge(a, b, medium=link.medium)
        return graph

    @cached_property
    def _paths(self) -> dict[str, dict[str, list[str]]]:
        return {}

    @cached_property
    def _order(self) -> dict[str, int]:
        return {n: i for i, n in enumerate(self.nodes)}

    def _shortest_paths(self, src: str) -> dict[str, list[str]]:
        """Breadth-first search from src, each node's neighbours visited in node order.

        Routing tie-break (docs/concepts/radios.md): among routes with the fewest hops, the one whose
        nodes come first compared hop by hop in node order (the robots as the scenario lists
        them, then the base station), never by name. Visiting level by level, each node's
        neighbours in node order, makes the first route found the first in that order. A clique
        is expanded once, by the first node of a level that reaches it: all its members are then
        found, so any later member has nothing new to add through it.
        """
        order = self._order
        paths = {src: [src]}
        level = [src]
        expanded: set[int] = set()
        while level:
            following = []
            for v in level:
                neighbours = list(self._adjacent.get(v, ()))
                for i in self._clique_of.get(v, ()):
                    if i not in expanded:
                        expanded.add(i)
                        neighbours.extend(self.cliques[i].nodes)
                for w in sorted(set(neighbours), key=order.__getitem__):
                    if w not in paths:
                        paths[w] = paths[v] + [w]
                        following.append(w)
            level = following
        return paths

    def path(self, src: str, dst: str) -> list[str] | None:
        if src not in self._order or dst not in self._order:
            return None
        if src == dst:
            return [src]
        if self.medium_between(src, dst) is not None:
            return [src, dst]  # one hop: the only shortest route
        if src not in self._paths:
            self._paths[src] = self._shortest_paths(src)
        return self._paths[src].get(dst)

    def route(self, src: str, dst: str) -> list[tuple[str, str, str]]:
        """Shortest-hop route as hops (from, to, medium); [] when src == dst."""
        return list(self.hops(src, dst))

    def hops(self, src: str, dst: str) -> tuple[tuple[str, str, str], ...]:
        """`route`, shared (not a copy): planners ask for the same routes again and again."""
        hops = self._routes.get((src, dst))
        if hops is None:
            path = self.path(src, dst)
            if path is None:
                raise ScenarioError(f"no route from {src} to {dst} on this network (links: {self.describe()})")
            hops = self._routes[src, dst] = tuple((u, v, self.medium_between(u, v)) for u, v in zip(path, path[1:], strict=False))
        return hops

    @cached_property
    def _routes(self) -> dict[tuple[str, str], tuple[tuple[str, str, str], ...]]:
        return {}

    @cached_property
    def _component(self) -> dict[str, int]:
        """Node -> connected component (over links and cliques)."""
        pairs = [(l.a, l.b) for l in self.explicit]
        pairs += [(c.nodes[0], n) for c in self.cliques for n in c.nodes[1:]]
        return connected_parts(self.nodes, pairs)

    def reachable(self, src: str, dst: str) -> bool:
        component = self._component
        return src in component and dst in component and component[src] == component[dst]

    def media_of(self, node: str) -> set[str]:
        """Media of the radios a node carries: one radio per medium among its links."""
        return set(self._media_by_node.get(node, ()))

    @cached_property
    def _media_by_node(self) -> dict[str, set[str]]:
        out: dict[str, set[str]] = {}
        for link in self.explicit:
            out.setdefault(link.a, set()).add(link.medium)
            out.setdefault(link.b, set()).add(link.medium)
        for node, cliques in self._clique_of.items():
            out.setdefault(node, set()).update(self.cliques[i].medium for i in cliques)
        return out

    def explicit_links_of(self, node: str) -> list[Link]:
        return list(self._adjacent.get(node, {}).values())

    def cliques_of(self, node: str) -> list[int]:
        return list(self._clique_of.get(node, ()))

    def neighbours(self, node: str) -> set[str]:
        """The nodes ``node`` has a link with (without building `links`)."""
        out = set(self._adjacent.get(node, {}))
        for i in self._clique_of.get(node, ()):
            out.update(self.cliques[i].nodes)
        out.discard(node)
        return out

    def media_by_group(self) -> dict[str, str]:
        out: dict[str, str] = {}
        for link in self.explicit:
            out.setdefault(link.group, link.medium)
        for clique in self.cliques:
            out.setdefault(clique.group, clique.medium)
        return out

    # ---- changes (faults, dead robots) ------------------------------------------------------
    def without_link(self, a: str, b: str) -> "Network":
        links = [l for l in self.explicit if {l.a, l.b} != {a, b}]
        cliques = []
        for clique in self.cliques:
            if a in clique.nodes and b in clique.nodes:  # the clique loses one pair: list its others
                links += [l for l in clique.links() if {l.a, l.b} != {a, b}]
            else:
                cliques.append(clique)
        return Network(self.nodes, self.basestation, links, self.topology, cliques)

    def without_nodes(self, nodes: set[str] | frozenset[str]) -> "Network":
        links = [l for l in self.explicit if l.a not in nodes and l.b not in nodes]
        cliques = [Clique(nodes=tuple(n for n in c.nodes if n not in nodes), medium=c.medium, group=c.group)
                   for c in self.cliques]
        return Network([n for n in self.nodes if n not in nodes], self.basestation, links, self.topology, cliques)

    def with_node_media(self, node: str, laptop_robot: str | None = None, robot_robot: str | None = None) -> "Network":
        """The node's links to the base station / to robots switch medium (a radio fault)."""
        if node not in self.nodes:
            raise ScenarioError(f"unknown node {node!r}; nodes: {', '.join(self.nodes)}")
        explicit, cliques = list(self.explicit), []
        for clique in self.cliques:
            if node in clique.nodes:  # the node leaves the clique: its links there become single links
                cliques.append(Clique(nodes=tuple(n for n in clique.nodes if n != node), medium=clique.medium,
                                      group=clique.group))
                at = clique.nodes.index(node)
                explicit += [Link(a=a, b=b, medium=clique.medium, group=clique.group)
                             for a, b in [(n, node) for n in clique.nodes[:at]] + [(node, n) for n in clique.nodes[at + 1:]]]
            else:
                cliques.append(clique)
        links = []
        for l in explicit:
            if l.touches(node):
                to_base = self.basestation in (l.a, l.b)
                new = laptop_robot if to_base else robot_robot
                if new is not None:
                    l = Link(a=l.a, b=l.b, medium=new, group=f"{l.group}@{node}")
            links.append(l)
        return Network(self.nodes, self.basestation, links, self.topology, cliques)

    def describe(self) -> str:
        return ", ".join(f"{l.a}-{l.b}:{l.medium}" for l in self.links) or "none"

    def _key(self) -> tuple:
        return self.nodes, self.explicit, self.cliques

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Network):
            return False
        if self._key() == other._key():
            return True
        return (self.nodes, set(self.links)) == (other.nodes, set(other.links))

    def __hash__(self) -> int:
        return hash((self.nodes, frozenset(self.links)))

    def __repr__(self) -> str:
        return f"Network({self.topology}: {self.describe()})"


def media_choices(scenario: Scenario, topology: str | None = None) -> list[dict[str, str]]:
    """Every media assignment (group -> medium) the scenario allows on a topology."""
    groups: dict[str, tuple[str, ...]] = {}
    specs, cliques = scenario.link_layout(topology)
    for spec in (*specs, *cliques):
        groups.setdefault(spec.group, spec.media)
    names = list(groups)
    return [dict(zip(names, combo, strict=True)) for combo in product(*(groups[g] for g in names))]


def build_network(scenario: Scenario, topology: str | None = None, media: Mapping[str, str] | None = None) -> Network:
    """The concrete network of a topology under a media choice (default: first candidates)."""
    topology = topology or scenario.network_spec.topology
    specs, clique_specs = scenario.link_layout(topology)
    media = dict(media or {})
    groups = {s.group: s.media for s in (*specs, *clique_specs)}
    for group, medium in media.items():
        if group not in groups:
            raise ScenarioError(f"unknown media group {group!r} on {topology}; groups: {', '.join(groups)}")
        if medium not in scenario.radios:
            raise ScenarioError(f"unknown medium {medium!r}; radios: {', '.join(scenario.radios)}")
    links = [Link(a=s.a, b=s.b, medium=media.get(s.group, s.media[0]), group=s.group) for s in specs]
    cliques = [Clique(nodes=c.nodes, medium=media.get(c.group, c.media[0]), group=c.group) for c in clique_specs]
    return Network(scenario.node_names(), scenario.basestation, links, topology, cliques)


def describe_media(media: dict[str, str] | None) -> str:
    """Each link group's medium for people to read: "laptop-robot=802.11a, robot-robot=802.11a"."""
    if not media:
        return "—"
    return ", ".join(f"{group}={medium}" for group, medium in media.items())
