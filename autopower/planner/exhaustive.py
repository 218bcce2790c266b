"""Exhaustive search over hosts x media: the paper's method, exact, for small teams.

Loads add up chain by chain, so every combination's load is a sum of per-chain rows; the sums
are built by numpy broadcasting and scored in one batch by the model's own load -> power code.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from autopower.errors import AutoPowerError
from autopower.model.energy import LoadSpace
from autopower.model.network import Network
from autopower.planner.problem import Problem

MAX_COMBINATIONS = 2_000_000  # beyond this, use the MILP
TIE_REL = 1e-9


@dataclass(frozen=True)
class Candidate:
    lifetime_s: float  # raw
    spread: float  # sum of robots' power / energy: the tie-breaker (less drain elsewhere is better)
    network: Network
    allocation: dict[str, str]


def combine(acc: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Every sum of an accumulated row and a new chain's row, in C order: (K, ...) + (M, ...) -> (K*M, ...).

    Adding chains one by one this way enumerates the product of their options; `decode_allocation`
    turns a flat index of the result back into the options it sums."""
    return (acc[:, None, ...] + rows[None, ...]).reshape(-1, *acc.shape[1:])


def decode_allocation(chains, options: list[list[tuple[str, ...]]], flat_index: int) -> dict[str, str]:
    """Index into the C-ordered product of per-chain options -> allocation (stage -> host)."""
    sizes = [len(o) for o in options]
    picks = np.unravel_index(flat_index, sizes) if sizes else ()
    allocation = {}
    for chain, opts, pick in zip(chains, options, picks, strict=False):
        for stage, host in zip(chain.stages, opts[int(pick)], strict=False):
            allocation[stage.name] = host
    return allocation


def search_network(problem: Problem, network: Network) -> tuple[LoadSpace, np.ndarray, list[list[tuple[str, ...]]]]:
    """All combinations on one network: (space, loads (K, D), per-chain option lists)."""
    space = LoadSpace(problem.scenario, network, problem.accounting, problem.energies_j)
    loads = np.zeros((1, space.size))
    options = []
    for chain in problem.chains:
        opts = problem.options(chain)
        rows = np.array([space.chain_load(chain, o) for o in opts])
        loads = combine(loads, rows)
        options.append(opts)
    add_flow_loads(problem.chains, problem.flows, space, options, loads)
    return space, loads, options


def add_flow_loads(chains, flows, space: LoadSpace, options: list[list[tuple[str, ...]]], loads: np.ndarray,
                   fixed: dict[str, str] | None = None) -> None:
    """Add each DAG flow's load to every combination of `chains`' options (in place, C order as
    `combine` builds it): looked up by (producer host, consumer host) per combination. A flow
    with one end outside `chains` takes that end's host from `fixed` (skipped if it has none);
    a flow with both ends outside is the caller's (its base load)."""
    if not flows:
        return
    sizes = [len(o) for o in options]
    picks = np.unravel_index(np.arange(loads.shape[0]), sizes)
    where = {s.name: (i, k) for i, c in enumerate(chains) for k, s in enumerate(c.stages)}
    chain_of = {s.name: c for c in chains for s in c.stages}
    nodes = {n: j for j, n in enumerate(space.nodes)}

    def host_index(stage: str) -> np.ndarray | None:
        if stage in where:
            i, k = where[stage]
            return np.array([nodes[o[k]] for o in options[i]])[picks[i]]
        host = (fixed or {}).get(stage)
        return None if host not in nodes else np.full(loads.shape[0], nodes[host])

    for flow in flows:
        if flow.producer not in where and flow.consumer not in where:
            continue
        src, dst = host_index(flow.producer), host_index(flow.consumer)
        if src is None or dst is None:
            continue
        producer_chain = chain_of.get(flow.producer) or next(c for c in space.scenario.chains
                                                             if any(s.name == flow.producer for s in c.stages))
        table = np.zeros((len(nodes), len(nodes), space.size))
        for a, i in nodes.items():
            for b, j in nodes.items():
                table[i, j] = space.dag_flow_load(flow, producer_chain, a, b)  # 0 without a route
        loads += table[src, dst]


def exhaustive(problem: Problem, max_ties: int = 8) -> list[Candidate]:
    """The optimal configurations (best first, ties included), or [] if nothing is feasible."""
    if problem.combinations() > MAX_COMBINATIONS:
        raise AutoPowerError(
            f"{problem.combinations():,} combinations is too many for exhaustive search "
            f"(limit {MAX_COMBINATIONS:,}); use --method milp"
        )
    found: list[Candidate] = []
    for network in problem.networks:
        space, loads, options = search_network(problem, network)
        life = space.lifetimes(loads)
        best = life.max()
        if not np.isfinite(best):
            continue
        spread = (space.total_power(loads) / space.energy_j).sum(axis=1)
        for k in np.flatnonzero(life >= best * (1 - TIE_REL)):
            found.append(Candidate(float(life[k]), float(spread[k]), network, decode_allocation(problem.chains, options, int(k))))
    if not found:
        return []
    top = max(c.lifetime_s for c in found)
    ties = [c for c in found if c.lifetime_s >= top * (1 - TIE_REL)]
    ties.sort(key=lambda c: (-c.lifetime_s, c.spread))
    return ties[:max_ties]
