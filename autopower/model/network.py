"""The concrete network of a topology and media choice: links, radios per node, routes.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from itertools import product
from typing import Mapping, Sequence

import networkx as nx

from autopower.errors import ScenarioError
from autopower.model.scenario import Scenario

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


class Network:
    """A concrete network: nodes, links with a chosen medium each, shortest-hop routing."""

    def __init__(self, nodes: Sequence[str], basestation: str, links: Sequence[Link], topology: str = "explicit"):
        self.nodes = tuple(nodes)
        self.basestation = basestation
        self.links = tuple(links)
        self.topology = topology
        seen = set()
        for link in self.links:
            for end in (link.a, link.b):
                if end not in self.nodes:
                    raise ScenarioError(f"link {link.a}-{link.b}: unknown node {end!r}")
            key = frozenset((link.a, link.b))
            if key in seen:
                raise ScenarioError(f"two links between {link.a} and {link.b}; keep one (with one medium)")
            seen.add(key)

    @cached_property
    def graph(self) -> nx.Graph:
        """The links as a graph whose every adjacency list is in node order.

        Routing tie-break (README "The model"): among routes with the fewest hops, the one whose
        nodes come first compared hop by hop in node order (the robots as the scenario lists
        them, then the base station), never by name. networkx's BFS visits neighbours in
        adjacency order, level by level, so adding each node's links in node order makes the
        first route found the first in that order.
        """
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

    def path(self, src: str, dst: str) -> list[str] | None:
        if src not in self._paths:
            self._paths[src] = nx.single_source_shortest_path(self.graph, src) if src in self.graph else {}
        return self._paths[src].get(dst)

    def route(self, src: str, dst: str) -> list[tuple[str, str, str]]:
        """Shortest-hop route as hops (from, to, medium); [] when src == dst."""
        path = self.path(src, dst)
        if path is None:
            raise ScenarioError(f"no route from {src} to {dst} on this network (links: {self.describe()})")
        return [(u, v, self.graph.edges[u, v]["medium"]) for u, v in zip(path, path[1:])]

    def reachable(self, src: str, dst: str) -> bool:
        return self.path(src, dst) is not None

    def media_of(self, node: str) -> set[str]:
        """Media of the radios a node carries: one radio per medium among its links."""
        return set(self._media_by_node.get(node, ()))

    @cached_property
    def _media_by_node(self) -> dict[str, set[str]]:
        # one pass over the links: a fully connected fleet of n robots has ~n^2/2 of them
        out: dict[str, set[str]] = {}
        for link in self.links:
            out.setdefault(link.a, set()).add(link.medium)
            out.setdefault(link.b, set()).add(link.medium)
        return out

    def media_by_group(self) -> dict[str, str]:
        out: dict[str, str] = {}
        for link in self.links:
            out.setdefault(link.group, link.medium)
        return out

    def medium_between(self, a: str, b: str) -> str | None:
        if self.graph.has_edge(a, b):
            return self.graph.edges[a, b]["medium"]
        return None

    # ---- changes (faults, dead robots) ------------------------------------------------------
    def without_link(self, a: str, b: str) -> "Network":
        links = [l for l in self.links if {l.a, l.b} != {a, b}]
        return Network(self.nodes, self.basestation, links, self.topology)

    def without_nodes(self, nodes: set[str] | frozenset[str]) -> "Network":
        links = [l for l in self.links if l.a not in nodes and l.b not in nodes]
        return Network([n for n in self.nodes if n not in nodes], self.basestation, links, self.topology)

    def with_node_media(self, node: str, laptop_robot: str | None = None, robot_robot: str | None = None) -> "Network":
        """The node's links to the base station / to robots switch medium (a radio fault)."""
        if node not in self.nodes:
            raise ScenarioError(f"unknown node {node!r}; nodes: {', '.join(self.nodes)}")
        links = []
        for l in self.links:
            if l.touches(node):
                to_base = self.basestation in (l.a, l.b)
                new = laptop_robot if to_base else robot_robot
                if new is not None:
                    l = Link(a=l.a, b=l.b, medium=new, group=f"{l.group}@{node}")
            links.append(l)
        return Network(self.nodes, self.basestation, links, self.topology)

    def describe(self) -> str:
        return ", ".join(f"{l.a}-{l.b}:{l.medium}" for l in self.links) or "none"

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Network) and (self.nodes, set(self.links)) == (other.nodes, set(other.links))

    def __hash__(self) -> int:
        return hash((self.nodes, frozenset(self.links)))

    def __repr__(self) -> str:
        return f"Network({self.topology}: {self.describe()})"


def media_choices(scenario: Scenario, topology: str | None = None) -> list[dict[str, str]]:
    """Every media assignment (group -> medium) the scenario allows on a topology."""
    groups: dict[str, tuple[str, ...]] = {}
    for spec in scenario.link_specs(topology):
        groups.setdefault(spec.group, spec.media)
    names = list(groups)
    return [dict(zip(names, combo)) for combo in product(*(groups[g] for g in names))]


def build_network(scenario: Scenario, topology: str | None = None, media: Mapping[str, str] | None = None) -> Network:
    """The concrete network of a topology under a media choice (default: first candidates)."""
    topology = topology or scenario.network_spec.topology
    specs = scenario.link_specs(topology)
    media = dict(media or {})
    groups = {s.group: s.media for s in specs}
    for group, medium in media.items():
        if group not in groups:
            raise ScenarioError(f"unknown media group {group!r} on {topology}; groups: {', '.join(groups)}")
        if medium not in scenario.radios:
            raise ScenarioError(f"unknown medium {medium!r}; radios: {', '.join(scenario.radios)}")
    links = [Link(a=s.a, b=s.b, medium=media.get(s.group, s.media[0]), group=s.group) for s in specs]
    return Network(scenario.node_names(), scenario.basestation, links, topology)


