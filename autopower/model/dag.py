"""Applications as directed acyclic graphs: the flows that join chains together.

A chain is a linear pipeline (source -> stage 0 -> ... -> sink). A DAG adds *flows*: a stage may
take, besides its chain predecessor's output, the outputs of stages of other chains (fan-in), and
a stage's output may feed several stages (fan-out: its own successor plus every flow that names
it). A chain may have no sensor source at all (`sourced = False`): its first stage is then fed
only by its flows, e.g. a team map merging every robot's localisation output.

The linear chain is the special case with no flows; nothing here changes how it is planned,
charged or run. Each flow is one message per producer run, charged like a chain hop (paper
accounting: one message per second; physical: the producer chain's 1/period).

Pure: no imports from the rest of AutoPower (scenario.py imports `Flow` from here).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Sequence

import networkx as nx


@dataclass(frozen=True, kw_only=True)
class Flow:
    """A DAG edge: `producer`'s output, `n_bytes` long, is an input of `consumer` (another chain's stage)."""

    producer: str  # stage name
    consumer: str  # stage name
    n_bytes: int

    @property
    def name(self) -> str:
        return f"{self.producer}>{self.consumer}"


def chain_of_stage(chains: Iterable) -> dict:
    return {s.name: c for c in chains for s in c.stages}


def flows_of(chains: Iterable) -> list[Flow]:
    """Every flow into the chains' stages (declared on the consuming chain)."""
    return [f for c in chains for f in c.inputs]


def active_flows(chains: Sequence) -> list[Flow]:
    """The flows whose producer and consumer both run (a flow from a stopped chain carries nothing)."""
    running = chain_of_stage(chains)
    return [f for f in flows_of(chains) if f.producer in running and f.consumer in running]


def runnable(chains: Sequence) -> list:
    """`chains` without the source-less chains none of whose inputs run (they would have nothing to join).

    Repeated to a fixed point: a source-less chain fed only by another source-less chain that
    stops, stops too."""
    out = list(chains)
    while True:
        running = chain_of_stage(out)
        keep = [c for c in out if c.sourced or any(f.producer in running for f in c.inputs
                                                   if f.consumer == c.stages[0].name)]
        if len(keep) == len(out):
            return out
        out = keep


def stage_graph(chains: Iterable) -> nx.DiGraph:
    """Stages as nodes; a chain's own hops and every flow as edges."""
    graph = nx.DiGraph()
    for chain in chains:
        names = [s.name for s in chain.stages]
        graph.add_nodes_from(names)
        graph.add_edges_from(zip(names, names[1:], strict=False))
    for flow in flows_of(chains):
        graph.add_edge(flow.producer, flow.consumer)
    return graph


def find_cycle(chains: Iterable) -> list[str] | None:
    """A cycle of stage names (first repeated at the end), or None for a DAG."""
    try:
        edges = nx.find_cycle(stage_graph(chains))
    except nx.NetworkXNoCycle:
        return None
    return [u for u, _ in edges] + [edges[0][0]]


def topological_chains(chains: Sequence) -> list:
    """The chains ordered so that every flow's producer chain comes before its consumer's."""
    by_stage = chain_of_stage(chains)
    graph = nx.DiGraph()
    graph.add_nodes_from(c.name for c in chains)
    for flow in active_flows(chains):
        a, b = by_stage[flow.producer].name, by_stage[flow.consumer].name
        if a != b:
            graph.add_edge(a, b)
    order = {name: i for i, name in enumerate(nx.topological_sort(graph))}
    return sorted(chains, key=lambda c: order[c.name])
