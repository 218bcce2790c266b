"""A greedy placement: the baseline the benchmark measures the MILP against.

List scheduling: chains are placed one at a time, heaviest CPU load first, each on the hosts
that keep the team's lifetime highest given the chains already placed.
Fast and often decent; not optimal (the benchmark shows by how much).
"""

from __future__ import annotations

import numpy as np

from autopower.model.energy import LoadSpace
from autopower.model.network import Network
from autopower.planner.problem import Problem


def greedy(problem: Problem) -> tuple[Network, dict[str, str], float] | None:
    """Best greedy result over the problem's media choices: (network, allocation, lifetime_s)."""
    best = None
    for network in problem.networks:
        space = LoadSpace(problem.scenario, network, problem.accounting, problem.energies_j)
        chosen: dict[str, tuple[str, ...]] = {}
        placed = np.zeros(space.size)
        order = sorted(problem.chains, key=lambda c: -max(
            problem.scenario.components[s.component].latency_s.get("sitsang", 0) for s in c.stages) / c.period_s)
        for chain in order:
            options = problem.options(chain)
            loads = placed[None, :] + np.array([space.chain_load(chain, o) for o in options])
            life = space.lifetimes(loads)
            chosen[chain.name] = options[int(np.argmax(life))]
            placed = loads[int(np.argmax(life))]
        total = sum((space.chain_load(c, chosen[c.name]) for c in problem.chains), np.zeros(space.size))
        life = float(space.lifetimes(total[None, :])[0])
        if np.isfinite(life) and (best is None or life > best[2]):
            allocation = {s.name: h for c in problem.chains for s, h in zip(c.stages, chosen[c.name], strict=False)}
            best = (network, allocation, life)
    return best
