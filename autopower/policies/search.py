"""One decision's view of the problem: configurations, their predicted value, and the search.

`DecisionView` prices any (network, allocation) for the remaining energies, migrations paid;
every policy searches through it, so they value options the same way.
"""


from __future__ import annotations

import dataclasses
import itertools
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np

from autopower.errors import AutoPowerError, InfeasibleError
from autopower.model.dag import active_flows
from autopower.model.energy import LoadSpace, load_of
from autopower.model.network import Network
from autopower.model.scenario import Chain
from autopower.planner.exhaustive import TIE_REL, add_flow_loads, combine, decode_allocation
from autopower.planner.problem import PlanRequest, host_binaries, make_problem, near_hosts
from autopower.policies.team import (
    EXHAUSTIVE_UP_TO,
    NEVER,
    Decision,
    Move,
    SchedulePhase,
    TeamState,
    _move,
    candidate_networks,
    effective_scenario,
    plan_moves,
    total_energy,
)

# The placement MILP of a decision: its time limit and the relative gap that counts as optimal
MILP_TIME_LIMIT_S = 30.0
MILP_GAP = 1e-6
# Stage-host choices beyond which a decision searches only the hosts near each chain
# (`planner.problem.near_hosts`; its decisions are then not proven optimal): a team whose every
# node may host every stage has n^2 of them, 20,200 at 100 robots (a MILP of 3-12 s), 180,000 at
# 300 (a minute), two million at 1,000 (refused: `milp.MAX_HOST_BINARIES`).
NEAR_HOSTS_ABOVE = 50_000

# ---------------------------------------------------------------------------------------------
# One decision's view: the problem, energies, configurations and their values
# ---------------------------------------------------------------------------------------------


@dataclass
class Option:
    network: Network
    allocation: dict[str, str]
    value_s: float  # predicted remaining lifetime, migrations paid
    moves: list[Move]
    spread: float = 0.0  # sum_i P_i / E_i: the planner's tie-breaker
    label: str = ""
    schedule: list[SchedulePhase] = field(default_factory=list)  # for schedule options: all phases
    # for the search's optimum (`DecisionView.best_static`): proven the best of every configuration
    # the policy may choose, or not (`not_proven` says why, `mip_gap` how far over what was searched)
    proven: bool | None = None
    mip_gap: float | None = None
    not_proven: str = ""


class DecisionView:
    def __init__(self, state: TeamState):
        self.state = state
        self.networks = candidate_networks(state)
        if not self.networks:
            raise InfeasibleError("no network is left to run on")
        self.gone = frozenset(state.unavailable_nodes)
        raw = state.scenario
        self.scenario, self.degraded = effective_scenario(raw, self.networks[0])
        self.accounting = state.accounting or raw.accounting
        self.base = self.networks[0].basestation
        self.robots = [n for n in self.networks[0].nodes if n != self.base]
        energies = {r: float(state.energies_j.get(r, raw.robot(r).energy_j)) for r in self.robots}
        self.energies = {r: max(e, 1e-9) for r, e in energies.items()}
        self.energy = np.array([self.energies[r] for r in self.robots])
        request = PlanRequest(scenario=self.scenario, network=self.networks[0], energies_j=self.energies,
                              disabled_chains=frozenset(state.disabled_chains), unavailable_nodes=self.gone,
                              accounting=self.accounting)
        self.problem = make_problem(request)
        self.problem.networks = list(self.networks)
        # a team whose every node may host every stage: only the hosts near each chain (`near_hosts`)
        self.all_binaries = host_binaries(self.problem)
        self.near_only = self.all_binaries > NEAR_HOSTS_ABOVE
        if self.near_only:
            self.problem = near_hosts(self.problem, state.allocation)
        self.stages = [s.name for c in self.problem.chains for s in c.stages]
        self.current = {s: h for s, h in state.allocation.items() if s in self.stages}
        self._spaces: dict[Network, LoadSpace] = {}

    # ---- evaluation ------------------------------------------------------------------------------
    def space(self, network: Network) -> LoadSpace:
        space = self._spaces.get(network)
        if space is None:
            space = self._spaces[network] = LoadSpace(self.scenario, network, self.accounting, self.energies)
        return space

    def power(self, network: Network, allocation: Mapping[str, str]) -> tuple[np.ndarray, bool]:
        space = self.space(network)
        load = load_of(space, self.problem.chains, allocation)[None, :]
        return space.total_power(load)[0], bool(space.feasible(load)[0])

    def stay_network(self) -> Network:
        """The network in use now, minus nodes that are gone and links known to be cut."""
        net = self.state.network
        extra = set(net.nodes) - set(self.networks[0].nodes)
        if extra:
            net = net.without_nodes(extra)
        for pair in sorted(tuple(sorted(p)) for p in self.state.cut_links):
            if net.medium_between(*pair) is not None:
                net = net.without_link(*pair)
        return net

    def stay_valid(self) -> bool:
        """Can the current configuration go on as it is (every stage placed, routable, feasible)?"""
        if set(self.current) != set(self.stages):
            return False
        net = self.stay_network()
        for chain in self.problem.chains:
            for stage in chain.stages:
                host = self.current[stage.name]
                if host not in net.nodes or not (net.reachable(chain.source, host) and net.reachable(host, chain.sink)):
                    return False
                if stage.pin is not None and host != stage.pin:
                    return False
        return self.power(net, self.current)[1]

    def stay_problems(self) -> list[str]:
        """Why the current configuration cannot go on, in words."""
        out = []
        net = self.stay_network()
        for chain in self.problem.chains:
            for stage in chain.stages:
                host = self.current.get(stage.name)
                if host is None:
                    out.append(f"{stage.name} is not running")
                elif host not in net.nodes:
                    out.append(f"{stage.name}'s host {host} is gone")
                elif not (net.reachable(chain.source, host) and net.reachable(host, chain.sink)):
                    out.append(f"{stage.name} on {host} is cut off from {chain.source}"
                               + (f" or {chain.sink}" if chain.sink != chain.source else ""))
        if not out:
            from autopower.model.energy import evaluate

            try:
                ev = evaluate(self.scenario, net, self.current, accounting=self.accounting, energies_j=self.energies,
                              disabled_chains=frozenset(c.name for c in self.scenario.chains)
                              - {c.name for c in self.problem.chains})
                out.extend(v.message for v in ev.violations)
            except AutoPowerError as exc:
                out.append(str(exc))
        return out

    def value(self, network: Network, allocation: Mapping[str, str], label: str = "") -> Option:
        moves = plan_moves(self.scenario, network, self.current, allocation, self.state.migration)
        power, feasible = self.power(network, allocation)
        cost = total_energy(moves)
        energy = self.energy - np.array([cost.get(r, 0.0) for r in self.robots])
        life = float(np.min(np.maximum(energy, 0.0) / power)) if feasible and len(power) else -NEVER
        if feasible and not len(power):
            life = NEVER
        return Option(network, dict(allocation), life, moves, float((power / self.energy).sum()), label)

    def stay(self) -> Option | None:
        if not self.stay_valid():
            return None
        return self.value(self.stay_network(), self.current, "stay")

    # ---- search --------------------------------------------------------------------------------
    def best_static(self, hosts: Mapping[str, Sequence[str]] | None = None) -> Option | None:
        """The configuration with the longest predicted life, migrations paid (ties: fewest moves)."""
        if not self.problem.chains:
            return self.value(self.stay_network() if self.stay_network() in self.networks else self.networks[0],
                              {}, "optimum")
        if self.problem.combinations() <= EXHAUSTIVE_UP_TO:
            return self._proven(self._enumerate(hosts), True, None)
        from autopower.planner.milp import solve_milp

        # warm: the plan in force, repaired where it fails, is the first incumbent (often the answer)
        result = solve_milp(self.problem, time_limit_s=MILP_TIME_LIMIT_S, mip_rel_gap=MILP_GAP,
                            start=self.current or None)
        if result.allocation is None:
            return None
        # the MILP ignores migration costs; callers weigh its plan against staying, costs included
        return self._proven(self.value(result.network, result.allocation, "optimum"), result.optimal, result.mip_gap)

    def _proven(self, option: Option | None, optimal: bool, gap: float | None) -> Option | None:
        """The search's optimum with what it proves: the best of every configuration the policy may
        choose only when the search was exact over every candidate host."""
        if option is None:
            return None
        option.proven = optimal and not self.near_only
        option.mip_gap = gap
        if option.proven:
            return option
        why = []
        if not optimal:  # (its gap is the decision's `mip_gap`: a figure of the time limit, not of the plan)
            why.append("the MILP stopped at its time limit")
        if self.near_only:
            why.append(f"only the hosts near each chain were searched, {host_binaries(self.problem):,} of the team's "
                       f"{self.all_binaries:,} stage-host choices")
        option.not_proven = ", and ".join(why)
        return option

    def _enumerate(self, hosts: Mapping[str, Sequence[str]] | None = None) -> Option | None:
        best: tuple | None = None
        for network in self.networks:
            found = enumerate_network(self, network, self.problem.chains, hosts or self.problem.hosts, self.current)
            if found is None:
                continue
            key = (found[0], -found[1], -found[2])
            if best is None or better_option(found[0], best[0][0], key, best[0]):
                best = (key, network, found[3])
        if best is None:
            return None
        return self.value(best[1], best[2], "optimum")

    def explain(self, network: Network, allocation: Mapping[str, str], stages: Sequence[str]) -> dict[str, str]:
        if not stages:
            return {}
        try:
            from autopower.planner import evaluate_in
            from autopower.planner.reasons import explain

            problem = dataclasses.replace(self.problem, networks=[network])
            why = explain(problem, network, dict(allocation), evaluate_in(problem, network, dict(allocation)),
                          stages=set(stages))
            return {s: why[s] for s in stages if s in why}
        except AutoPowerError:  # pragma: no cover - explanations are a courtesy
            return {}


def better_option(value: float, best_value: float, key: tuple, best_key: tuple) -> bool:
    if value > best_value * (1 + TIE_REL) + 1e-12:
        return True
    if value < best_value * (1 - TIE_REL) - 1e-12:
        return False
    return key[1:] > best_key[1:]


def enumerate_network(view: DecisionView, network: Network, chains: Sequence[Chain], hosts: Mapping[str, Sequence[str]],
                       current: Mapping[str, str], base_load: np.ndarray | None = None,
                       lifetime_of: Sequence[str] | None = None, flow_ends: Mapping[str, str] | None = None):
    """Exhaustive search on one network, migrations included: (value, moves, -spread, allocation)."""
    space = view.space(network)
    robots = space.robots
    index = {r: i for i, r in enumerate(robots)}
    loads = np.zeros((1, space.size)) if base_load is None else base_load[None, :].copy()
    costs = np.zeros((1, len(robots)))
    moves = np.zeros(1)
    options = []
    for chain in chains:
        opts = list(itertools.product(*(hosts[s.name] for s in chain.stages)))
        rows = np.array([space.chain_load(chain, o) for o in opts])
        crow = np.zeros((len(opts), len(robots)))
        mrow = np.zeros(len(opts))
        for k, opt in enumerate(opts):
            for stage, host in zip(chain.stages, opt, strict=True):
                old = current.get(stage.name)
                if old is not None and old != host:
                    mv = _move(view.scenario, network, chain, stage.name, stage.component, old, host,
                               view.state.migration)
                    mrow[k] += 1
                    for robot, joules in mv.energy_j.items():
                        if robot in index:
                            crow[k, index[robot]] += joules
        loads = combine(loads, rows)
        costs = combine(costs, crow)
        moves = combine(moves, mrow)
        options.append(opts)
    # DAG flows: an end outside `chains` stays where `flow_ends` (default: `current`) puts it
    add_flow_loads(chains, active_flows(view.problem.chains), space, options, loads, dict(flow_ends or current))
    power = space.total_power(loads)
    energy = np.maximum(space.energy_j[None, :] - costs, 0.0)
    cols = list(range(len(robots))) if lifetime_of is None else [index[r] for r in lifetime_of if r in index]
    life = (energy / power)[:, cols].min(axis=1) if cols else np.full(len(loads), NEVER)
    life = np.where(space.feasible(loads), life, -np.inf)
    best = life.max()
    if not np.isfinite(best) and best < 0:
        return None
    ties = np.flatnonzero(life >= best * (1 - TIE_REL) - 1e-12)
    spread = (power / space.energy_j).sum(axis=1)
    k = int(min(ties, key=lambda j: (moves[j], spread[j], j)))
    return float(life[k]), float(moves[k]), float(spread[k]), decode_allocation(chains, options, k)


# ---------------------------------------------------------------------------------------------
# Building decisions
# ---------------------------------------------------------------------------------------------


def make_decision(policy: str, view: DecisionView, option: Option, *, reasons: list[str], forced: bool,
              stay_value: float | None, schedule: Sequence[SchedulePhase] = (), revisit_at_s: float | None = None,
              predicted_s: float | None = None) -> Decision:
    state = view.state
    old = dict(state.allocation)
    new = option.allocation
    moves = tuple(plan_moves(view.scenario, option.network, view.current, new, state.migration))
    started = tuple(s for s in new if s not in view.current)
    stopped = tuple(s for s in old if s not in new)
    predicted = option.value_s if predicted_s is None else predicted_s
    gain = NEVER if stay_value is None else predicted - stay_value
    for name, why in view.degraded.items():
        if any(c.name == name for c in view.problem.chains):
            reasons.append(why)
    for _name, why in view.problem.unroutable.items():
        reasons.append(f"not running: {why}")
    return Decision(
        policy=policy, time_s=state.time_s, network=option.network, allocation=dict(new), moves=moves,
        started=started, stopped=stopped, reasons=tuple(dict.fromkeys(r for r in reasons if r)),
        stage_reasons=view.explain(option.network, new, [m.stage for m in moves] + list(started)),
        predicted_lifetime_s=predicted, predicted_gain_s=gain, migration_energy_j=total_energy(moves),
        forced=forced, schedule=tuple(schedule), revisit_at_s=revisit_at_s,
        dropped=dict(view.problem.unroutable),
        degraded={k: v for k, v in view.degraded.items() if any(c.name == k for c in view.problem.chains)},
        proven_optimal=option.proven, mip_gap=option.mip_gap,
    )


def what_happened(state: TeamState) -> str:
    return "; ".join(e.describe() for e in state.events) if state.events else ""


def forced_reason(view: DecisionView) -> str:
    happened = what_happened(view.state)
    if not view.state.allocation:
        return "mission start"
    problems = view.stay_problems()
    return ("the current configuration cannot continue" + (f" after {happened}" if happened else "")
            + (f": {'; '.join(problems)}" if problems else ""))


def no_placement(view: DecisionView) -> InfeasibleError:
    local = {s.name: c.source for c in view.problem.chains for s in c.stages}
    why = ""
    try:
        space = view.space(view.networks[0])
        load = load_of(space, view.problem.chains, local)[None, :]
        if not space.feasible(load)[0]:
            why = " (even running every stage locally exceeds a CPU or radio limit)"
    except AutoPowerError:
        pass
    return InfeasibleError(f"at {view.state.time_s:.1f} s no allocation meets the CPU and radio limits{why}"
                           + (f" after: {what_happened(view.state)}" if view.state.events else ""))

