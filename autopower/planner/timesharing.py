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

from autopower.model import LoadSpace, Network
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
            phases.append(Phase(float(t), network, allocation, dict(zip(robots, map(float, power)))))
    phases.sort(key=lambda p: -p.duration_s)
    return phases


def time_sharing_bound(problem: Problem, seed_configs: list[tuple[Network, dict[str, str]]],
                       max_rounds: int = 60) -> TimeSharingBound:
    if problem.combinations() <= min(MAX_COMBINATIONS, 200_000):
        return _by_enumeration(problem)
    return _by_column_generation(problem, seed_configs, max_rounds)


def _by_enumeration(problem: Problem) -> TimeSharingBound:
    from autopower.planner.exhaustive import decode

    powers, configs = [], []
    robots = None
    for network in problem.networks:
        space, loads, options = search_network(problem, network)
        feasible = np.flatnonzero(space.feasible(loads))
        if feasible.size == 0:
            continue
        robots = space.robots
        energies = space.energy_j
        p = space.total_power(loads[feasible])
        # Only configurations on the Pareto frontier of power can matter; dedupe exact repeats.
        _, unique = np.unique(np.round(p, 12), axis=0, return_index=True)
        for k in unique:
            powers.append(p[k])
            configs.append((network, decode(problem, options, int(feasible[k])), p[k]))
    if not powers:
        return TimeSharingBound(0.0, 0.0, True, [], "enumeration")
    powers = np.array(powers)
    sol = _master(powers, energies)
    total = -sol.objective
    return TimeSharingBound(total, total, sol.optimal, _schedule(sol.values, configs, robots), "enumeration")


def _by_column_generation(problem: Problem, seeds, max_rounds: int) -> TimeSharingBound:
    space0 = LoadSpace(problem.scenario, problem.networks[0], problem.accounting, problem.energies_j)
    robots, energies = space0.robots, space0.energy_j
    configs, powers = [], []

    def add(network, allocation):
        space = LoadSpace(problem.scenario, network, problem.accounting, problem.energies_j)
        from autopower.model import load_of

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
        for robot, weight in zip(robots, pi):
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
    return TimeSharingBound(upper, achieved, upper <= achieved * (1 + 1e-6),
                            _schedule(sol.values, configs, robots), "column generation")
