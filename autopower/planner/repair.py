"""Warm replanning: repair the plan in force where it fails, and prove the repair optimal.

After one link changes, most of a fleet's plan is still right. `repair` keeps every stage where
the plan in force has it except those of the robots that now limit the lifetime (or break a
limit), solves the placement MILP over those few stages only, and checks the result against
`own_bound`: a lower bound on T that needs no MILP at all. When the repaired plan meets the
bound it is optimal; otherwise the caller solves the whole MILP, starting from the repair.

`own_bound` (per robot: idle power, its radios asleep, and each of its own chains placed where
it costs *that robot* least) is valid because everything it leaves out only adds power:
other robots' stages it hosts or relays, and send/receive power is never below sleep power
(checked when a scenario loads). On the loaded fleets it equals the LP relaxation. The lowest
of the media choices' bounds caps every plan; `milp._reach_bound` looks for a plan that meets
it (cold or warm) before the optimising MILP.
"""

from __future__ import annotations

import dataclasses
from typing import Mapping

from autopower.model.energy import airtime_s, evaluate, flow_rate_hz
from autopower.planner.problem import Problem

MAX_OPTIONS = 5_000  # a chain with more host combinations adds nothing to the bound (still valid)
# A repair searches at most this many stages (or this share of them); beyond, the whole MILP is
# no slower and the plan in force is only its first incumbent.
SMALL_NEIGHBOURHOOD = 30
SMALL_SHARE = 0.1


def repairable(problem: Problem) -> bool:
    """One fixed network, no quality variants or DVFS levels (their choices are not placements)."""
    return len(problem.networks) == 1 and boundable(problem)


def boundable(problem: Problem) -> bool:
    """`own_bound` applies: no quality variants or DVFS levels (a robot's cheapest level is not
    its power), any number of media choices (one bound each), and a robot to bound."""
    from autopower.model.dvfs import has_levels
    from autopower.model.variants import has_variants

    return (type(problem) is Problem and not has_levels(problem.scenario) and not has_variants(problem.scenario)
            and any(n != problem.networks[0].basestation for n in problem.networks[0].nodes))


def own_bound(problem: Problem, cheapest: dict[str, str] | None = None) -> tuple[float, dict[str, float]]:
    """(T bound, robot -> its own bound on T), T in the MILP's units: max_i P_i * E_ref / E_i.

    `cheapest`, when given, is filled with stage -> host: every chain where it costs its source
    robot least (the placement the bound assumes for each robot; `milp._reach_bound` starts its
    move search there)."""
    scenario, network = problem.scenario, problem.networks[0]
    robots = [n for n in network.nodes if n != network.basestation]
    e_ref = max(problem.energies_j[r] for r in robots)
    power = {}
    for robot in robots:
        platform = scenario.platform_of(robot)
        power[robot] = platform.idle_w + sum(scenario.radios[m].sleep_w for m in network.media_of(robot))
    direct: dict[tuple[str, str], str | None] = {}  # (u, v) -> the medium of their link, looked up once
    for chain in problem.chains:
        n_options = 1
        for stage in chain.stages:
            n_options *= len(problem.hosts[stage.name])
        if chain.source not in power or not n_options or n_options > MAX_OPTIONS:
            if cheapest is not None and n_options:  # (its first option: the bound says nothing about it)
                cheapest.update((s.name, problem.hosts[s.name][0]) for s in chain.stages)
            continue
        options = problem.options(chain)
        cost = _own_cost(problem, chain, direct)
        costs = list(map(cost, options))
        best = min(range(len(options)), key=costs.__getitem__)
        power[chain.source] += costs[best]
        if cheapest is not None:
            cheapest.update(zip((s.name for s in chain.stages), options[best], strict=False))
    per_robot = {r: power[r] * e_ref / problem.energies_j[r] for r in robots}
    return max(per_robot.values()), per_robot


def _own_cost(problem: Problem, chain, direct_medium: dict):
    """hosts -> the power the chain with its stages there costs its source robot (as
    PlacementModel.power counts it: CPU above idle, radios above sleep)."""
    scenario, network = problem.scenario, problem.networks[0]
    me = chain.source
    platform = scenario.platform_of(me)
    cpu_w = [(platform.busy_w - platform.idle_w) * scenario.components[s.component].latency_s[platform.name]
             / chain.period_s for s in chain.stages]
    rate = flow_rate_hz(chain, problem.accounting)
    message_w = [{m: ((r.send_w - r.sleep_w) * airtime_s(n, r) * rate, (r.receive_w - r.sleep_w) * airtime_s(n, r) * rate)
                  for m, r in scenario.radios.items()} if n else None
                 for n in chain.message_bytes]

    def cost(hosts: tuple[str, ...]) -> float:
        total = sum(w for w, host in zip(cpu_w, hosts, strict=False) if host == me)
        ends = (me, *hosts, chain.sink)
        for k, watts in enumerate(message_w):
            u, v = ends[k], ends[k + 1]
            if u == v or watts is None:
                continue
            direct = direct_medium.get((u, v), False)
            if direct is False:  # (chains' options share their endpoints: looked up once)
                direct = direct_medium[u, v] = network.medium_between(u, v)
            if direct is not None:  # one hop, the only shortest route: no route to look up
                if me in (u, v):
                    total += watts[direct][0 if u == me else 1]
                continue
            for a, b, medium in network.hops(u, v):
                if a == me:
                    total += watts[medium][0]
                elif b == me:
                    total += watts[medium][1]
        return total

    return cost


def neighbourhood(problem: Problem, start: Mapping[str, str], bound_by_robot: Mapping[str, float],
                  bound: float) -> set[str]:
    """The stages to search again: those whose host is no longer allowed, and the stages of every
    robot that breaks a limit under the plan in force or whose T exceeds the bound (its own and
    the ones it hosts)."""
    network = problem.networks[0]
    stages = {s.name: c for c in problem.chains for s in c.stages}
    free = {s for s in stages if start.get(s) not in problem.hosts[s]}
    if free:
        hot = set()
    else:
        ev = evaluate(problem.scenario, network, {s: start[s] for s in stages}, accounting=problem.accounting,
                      energies_j=problem.energies_j,
                      disabled_chains=frozenset(c.name for c in problem.scenario.chains) - {c.name for c in problem.chains})
        e_ref = max(problem.energies_j[r] for r in bound_by_robot)
        hot = {v.node for v in ev.violations}
        hot |= {r for r, p in ev.robots.items() if p.total_w * e_ref / problem.energies_j[r] > bound * (1 + 1e-9)}
    for stage, chain in stages.items():
        if chain.source in hot or start.get(stage) in hot:
            free.add(stage)
    return free


def restricted(problem: Problem, start: Mapping[str, str], free: set[str]) -> Problem:
    """The problem with every stage outside `free` pinned to its host in `start`."""
    hosts = {s: (list(h) if s in free else [start[s]]) for s, h in problem.hosts.items()}
    return dataclasses.replace(problem, hosts=hosts)
