"""The time-sharing bound: how long the team could live if it switched configurations mid-mission.

Let configuration k draw P_ik watts on robot i and run for t_k seconds. The longest mission is

    max sum_k t_k   s.t.  sum_k P_ik t_k <= E_i  (every robot),  t_k >= 0,

an LP with one column per feasible configuration. Small problems enumerate every column.
Larger ones use column generation: the dual prices pi_i of the energy rows ask for the
configuration minimising sum_i pi_i P_i, which is the placement MILP with a weighted objective.
Every pricing round also yields a valid upper bound (LP duality):
    T* <= sum_i E_i pi_i / min_k (pi . P_k).
Migration costs are ignored, so this bounds every dynamic policy from above.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from autopower.model.energy import LoadSpace
from autopower.model.network import Network
from autopower.planner.exhaustive import MAX_COMBINATIONS, search_network
from autopower.planner.lp import INF, LinearProgram
from autopower.planner.milp import PlacementModel
from autopower.planner.problem import Problem


@dataclass
class Phase:
    duration_s: float
    network: Network
    allocation: dict[str, str]
    power_w: dict[str, float]


@dataclass
class TimeSharingBound:
    lifetime_s: float  # upper bound on any schedule of configurations
    achieved_s: float  # lifetime of the best schedule found (== bound when proven)
    proven: bool
    schedule: list[Phase] = field(default_factory=list)
    method: str = "enumeration"


def _master(powers: np.ndarray, energies: np.ndarray):
    lp = LinearProgram()
    cols = [lp.var(0.0, INF, cost=-1.0) for _ in range(powers.shape[0])]
    for i in range(powers.shape[1]):
        lp.row({c: float(powers[k, i]) for k, c in enumerate(cols)}, -INF, float(energies[i]))
    sol = lp.solve()
    return sol


def _schedule(values, configs, robots) -> list[Phase]:
    phases = []
    for k, t in enumerate(values):
        if t > 1e-6:
            network, allocation, power = configs[k]
            phases.append(Phase(float(t), network, allocation, dict(zip(robots, map(float, power), strict=False))))
    phases.sort(key=lambda p: -p.duration_s)
    return phases


def enumerable(problem: Problem) -> bool:
    """The bound comes by enumeration (exact, a fraction of a second), not column generation (a
    pricing MILP per round: tens of seconds from about 25 robots with cameras)."""
    return problem.combinations() <= min(MAX_COMBINATIONS, 500_000)


def time_sharing_bound(problem: Problem, seed_configs: list[tuple[Network, dict[str, str]]],
                       max_rounds: int = 60) -> TimeSharingBound:
    if enumerable(problem):
        return _by_enumeration(problem, seed_configs)
    return _by_column_generation(problem, seed_configs, max_rounds)


def _by_enumeration(problem: Problem, seeds=()) -> TimeSharingBound:
    """Column generation with exact pricing by enumeration.

    Every configuration's power vector is computed at once (loads add up chain by chain); the
    master LP starts from the seeds and the best static configuration, and each round adds the
    configuration with the lowest dual-weighted power until none prices below 1. Only the few
    columns the LP uses are ever decoded, so 10^5 configurations cost a fraction of a second.
    """
    from autopower.model.energy import load_of
    from autopower.planner.exhaustive import decode_allocation

    blocks = []
    robots, energies = None, None
    for network in problem.networks:
        space, loads, options = search_network(problem, network)
        robots, energies = space.robots, space.energy_j
        ok = np.flatnonzero(space.feasible(loads))
        if ok.size:
            blocks.append((network, options, ok, space.total_power(loads[ok])))
    if not blocks:
        return TimeSharingBound(0.0, 0.0, True, [], "enumeration")
    powers = np.concatenate([b[3] for b in blocks])
    where = [(k, int(i)) for k, b in enumerate(blocks) for i in b[2]]
    chosen = [int(np.argmin((powers / energies).max(axis=1)))]
    for network, allocation in seeds:
        space = LoadSpace(problem.scenario, network, problem.accounting, problem.energies_j)
        p = space.total_power(load_of(space, problem.chains, allocation)[None, :])[0]
        match = np.flatnonzero(np.all(np.abs(powers - p) <= 1e-12 * (1 + np.abs(p)), axis=1))
        if match.size and int(match[0]) not in chosen:
            chosen.append(int(match[0]))
    sol, bound, achieved, converged = price_enumerated(powers, energies, chosen)
    configs = []
    for k in chosen:
        block, flat = where[k]
        network, options = blocks[block][0], blocks[block][1]
        configs.append((network, decode_allocation(problem.chains, options, flat), powers[k]))
    return TimeSharingBound(bound, achieved, converged, _schedule(sol.values, configs, robots), "enumeration")


def price_enumerated(powers, energies, chosen: list[int]):
    """Column generation over an enumerated power matrix (one row per configuration): grows
    `chosen` (in place) with the column of least reduced cost until none prices below 1.
    Returns (master solution, bound, achieved lifetime, converged)."""
    sol = None
    upper = INF  # LP duality: any prices give sum(E*pi) / min_k(pi . P_k) >= the optimum
    converged = False
    for _ in range(500):
        sol = _master(powers[chosen], energies)
        prices = np.maximum(-sol.duals, 0.0)
        reduced = powers @ prices
        best = int(np.argmin(reduced))
        if reduced[best] > 0:
            upper = min(upper, float(np.dot(energies, prices)) / reduced[best])
        if reduced[best] >= 1.0 - 1e-9 or best in chosen:
            converged = True  # no column prices below 1: the master's optimum is the LP's
            break
        chosen.append(best)
    achieved = -sol.objective
    return sol, (achieved if converged else max(upper, achieved)), achieved, converged


def _by_column_generation(problem: Problem, seeds, max_rounds: int) -> TimeSharingBound:
    space0 = LoadSpace(problem.scenario, problem.networks[0], problem.accounting, problem.energies_j)
    robots, energies = space0.robots, space0.energy_j
    configs, powers = [], []

    def add(network, allocation):
        space = LoadSpace(problem.scenario, network, problem.accounting, problem.energies_j)
        from autopower.model.energy import load_of

        p = space.total_power(load_of(space, problem.chains, allocation)[None, :])[0]
        configs.append((network, allocation, p))
        powers.append(p)

    for network, allocation in seeds:
        add(network, allocation)
    upper = INF
    sol = None
    for _ in range(max_rounds):
        sol = _master(np.array(powers), energies)
        pi = np.maximum(-sol.duals, 0.0)
        model = PlacementModel(problem)
        const = 0.0
        for robot, weight in zip(robots, pi, strict=False):
            expr, c = model.power(robot)
            const += weight * c
            for col, coef in expr.items():
                model.lp.cost[col] += weight * coef
        priced = model.lp.solve(mip_rel_gap=1e-7)
        if not priced.has_solution:
            break
        best_price = priced.objective + const
        if best_price > 0:
            upper = min(upper, float(np.dot(energies, pi)) / best_price)
        if best_price >= 1.0 - 1e-9:
            break
        allocation, network = model.decode(priced.values)
        add(network, allocation)
    achieved = -sol.objective
    upper = max(upper, achieved)
    # plain floats and bool: the prices are numpy's, and `plan --json` cannot encode a numpy bool
    return TimeSharingBound(float(upper), float(achieved), bool(upper <= achieved * (1 + 1e-6)),
                            _schedule(sol.values, configs, robots), "column generation")
