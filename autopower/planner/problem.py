"""What a planning request means concretely: networks, active chains, candidate hosts.

Shared by the exhaustive search, the MILP and the time-sharing bound so they all solve exactly
the same problem.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from itertools import product
from typing import Mapping

from autopower.model.dag import Flow, active_flows, runnable
from autopower.model.energy import active_chains
from autopower.model.network import Network, build_network, media_choices
from autopower.model.scenario import Chain, Scenario


@dataclass(frozen=True, kw_only=True)
class PlanRequest:
    """Everything the planner needs; a pure value, so a plan is a function of its request."""

    scenario: Scenario
    network: Network | None = None  # fixed media; None = choose media among the candidates
    topology: str | None = None  # when network is None: which topology (default: the scenario's)
    energies_j: Mapping[str, float] | None = None  # remaining battery (default: scenario energies)
    disabled_chains: frozenset[str] = frozenset()
    unavailable_nodes: frozenset[str] = frozenset()  # dead or unreachable robots
    accounting: str | None = None
    method: str = "auto"  # "auto" | "exhaustive" | "milp"
    with_bound: bool = False  # also compute the time-sharing upper bound
    time_limit_s: float | None = None
    mip_rel_gap: float = 1e-9
    max_ties: int = 8


@dataclass
class Problem:
    scenario: Scenario
    accounting: str
    energies_j: dict[str, float]
    networks: list[Network]  # one per media choice (or the one fixed network)
    chains: list[Chain]  # placeable chains
    unroutable: dict[str, str] = field(default_factory=dict)  # chain -> why it cannot run
    hosts: dict[str, list[str]] = field(default_factory=dict)  # stage -> candidate hosts

    def options(self, chain: Chain) -> list[tuple[str, ...]]:
        return list(product(*(self.hosts[s.name] for s in chain.stages)))

    @property
    def flows(self) -> list[Flow]:
        """The DAG flows between placed chains (autopower.model.dag)."""
        return active_flows(self.chains)

    def combinations(self) -> int:
        n = 1
        for chain in self.chains:
            n *= len(self.options(chain))
        return n * len(self.networks)


def make_problem(request: PlanRequest) -> Problem:
    scenario = request.scenario
    accounting = request.accounting or scenario.accounting
    energies = {**scenario.energies_j(), **(request.energies_j or {})}
    gone = frozenset(request.unavailable_nodes)
    if request.network is not None:
        networks = [request.network.without_nodes(gone) if gone else request.network]
    else:
        topology = request.topology or scenario.network_spec.topology
        networks = [build_network(scenario, topology, media).without_nodes(gone) if gone
                    else build_network(scenario, topology, media)
                    for media in media_choices(scenario, topology)]
    structure = networks[0]  # routing is by hop count, the same for every media choice
    problem = Problem(scenario=scenario, accounting=accounting, energies_j=energies, networks=networks, chains=[])
    for chain in active_chains(scenario, structure, request.disabled_chains):
        if not structure.reachable(chain.source, chain.sink):
            problem.unroutable[chain.name] = (f"{chain.name} cannot run: its sink {chain.sink} is unreachable "
                                              f"from {chain.source}")
            continue
        ok = True
        for stage in chain.stages:
            allowed = [n for n in structure.nodes
                       if (stage.pin is None or n == stage.pin)
                       and (stage.hosts is None or n in stage.hosts)
                       # a host must sit on a route from the source to the sink
                       and structure.reachable(chain.source, n) and structure.reachable(n, chain.sink)]
            if not allowed:
                problem.unroutable[chain.name] = f"{chain.name}: no reachable host may run {stage.name}"
                ok = False
            problem.hosts[stage.name] = allowed
        if ok:
            problem.chains.append(chain)
    problem.chains = runnable(problem.chains)  # a DAG chain whose inputs all stopped has nothing to join
    placed = {c.name for c in problem.chains}
    for chain in scenario.chains:
        if (not chain.sourced and chain.name not in placed and chain.name not in problem.unroutable
                and chain.name not in request.disabled_chains):
            problem.unroutable[chain.name] = f"{chain.name} cannot run: none of its inputs runs"
    return problem
