"""What a planning request means concretely: networks, active chains, candidate hosts.

Shared by the exhaustive search, the MILP and the time-sharing bound so they all solve exactly
the same problem.
"""

from __future__ import annotations

import dataclasses
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


def host_binaries(problem: Problem) -> int:
    """The placement MILP's stage-host binaries per media choice (`milp.MAX_HOST_BINARIES`)."""
    return sum(len(hosts) for hosts in problem.hosts.values())


def near_hosts(problem: Problem, keep: Mapping[str, str] = {}) -> Problem:  # noqa: B006 (read only)
    """``problem`` with each stage's candidate hosts cut down to those near its chain: its source
    and its sink, the neighbours of those that are robots (one hop on the problem's network), the
    base station, and the host ``keep`` gives it (the plan in force: staying is always a
    candidate). The hosts stay in the order the problem gives them, and a stage keeps only hosts
    it already had (pins and declared hosts hold; one with none of them near keeps all its own).

    A plan for this problem is a plan for the whole one, but its optimum is the optimum among
    those hosts only: with every node a candidate, a team of n robots has O(n^2) binaries (two
    million at 1,000 robots), which no MILP builds in a decision's time; a stage that runs
    farther than one hop from both ends of its chain pays for the relays on its way and is
    rarely the better plan, but nothing here proves it never is."""
    structure = problem.networks[0]
    around: dict[str, set[str]] = {}

    def near(node: str) -> set[str]:  # (the base station's neighbours are the whole team: itself only)
        found = around.get(node)
        if found is None:
            found = around[node] = ({node} if node == structure.basestation or node not in structure.nodes
                                    else {node, *structure.neighbours(node)})
        return found

    hosts = {}
    for chain in problem.chains:
        ends = near(chain.source) | near(chain.sink) | {structure.basestation}
        for stage in chain.stages:
            wanted = ends | {keep[stage.name]} if stage.name in keep else ends
            hosts[stage.name] = [h for h in problem.hosts[stage.name] if h in wanted] or problem.hosts[stage.name]
    return dataclasses.replace(problem, hosts={**problem.hosts, **hosts})
