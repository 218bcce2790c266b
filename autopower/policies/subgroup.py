"""Subgroups: the robots that can still reach each other reallocate among themselves.

`subgroup_reallocation` is what agents run without the base station (proposed and committed
peer to peer); `SubgroupPolicy` runs the same rule as a team-wide policy.
"""


from __future__ import annotations

import dataclasses
import itertools
import math
from dataclasses import dataclass
from typing import Mapping, Sequence

import networkx as nx
import numpy as np

from autopower.errors import AutoPowerError
from autopower.model.dag import active_flows
from autopower.model.energy import dag_load
from autopower.model.network import Network
from autopower.model.scenario import Chain, Scenario
from autopower.policies.search import DecisionView, enumerate_network, forced_reason, make_decision, no_placement
from autopower.policies.team import (
    EXHAUSTIVE_UP_TO,
    NEVER,
    Decision,
    MigrationCosts,
    Move,
    TeamState,
    beats,
    plan_moves,
    total_energy,
)

# ---------------------------------------------------------------------------------------------
# Subgroups: peer-to-peer reallocation among the robots that can still reach each other
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class SubgroupProposal:
    """What a subgroup agrees to do (the propose step). Empty `moves`: nothing worth doing."""

    members: tuple[str, ...]
    allocation: Mapping[str, str]  # the full allocation after the moves (stages outside untouched)
    moves: tuple[Move, ...]
    started: tuple[str, ...]  # stages of the subgroup that were not running at all
    min_lifetime_before_s: float | None  # the subgroup's shortest-lived member now; None if it cannot go on
    min_lifetime_after_s: float | None
    reasons: tuple[str, ...] = ()
    search: str = "exhaustive"  # "exhaustive" | "neighbourhood"

    @property
    def changes_anything(self) -> bool:
        return bool(self.moves or self.started)

    def to_dict(self) -> dict:
        return {"members": list(self.members), "allocation": dict(self.allocation),
                "moves": [m.to_dict() for m in self.moves], "started": list(self.started),
                "min_lifetime_before_s": self.min_lifetime_before_s, "min_lifetime_after_s": self.min_lifetime_after_s,
                "reasons": list(self.reasons), "search": self.search}


def subgroups(network: Network) -> list[tuple[str, ...]]:
    """The parts of the team that can reach each other (each with the base station if it is in it)."""
    out = []
    for part in sorted((set(c) for c in nx.connected_components(network.graph)),
                       key=lambda c: min(network.nodes.index(n) for n in c)):
        members = tuple(n for n in network.nodes if n in part)
        if any(n != network.basestation for n in members):
            out.append(members)
    return out


def subgroup_reallocation(scenario: Scenario, network: Network, members: Sequence[str],
                          allocation: Mapping[str, str], energies_j: Mapping[str, float], *,
                          accounting: str | None = None, disabled_chains: frozenset[str] = frozenset(),
                          migration: MigrationCosts | None = None, min_gain: float = 0.001,
                          min_gain_s: float = 10.0, max_enumeration: int = EXHAUSTIVE_UP_TO,
                          max_rounds: int = 50) -> SubgroupProposal:
    """A reallocation among `members` that raises their minimum lifetime, migrations paid.

    Only stages hosted by members (and stages of members' chains whose host is gone) move, only
    onto members; everything else is background load. Media stay as they are. Small cases are
    searched exhaustively; larger ones by a neighbourhood search that moves up to three chains'
    stages at once (multi-party moves: A→B, B→C, C→A), which escapes the local optima that
    pairwise swaps get stuck in. A proposal with no moves means no gain above `min_gain`.
    """
    members = tuple(dict.fromkeys(members))
    for m in members:
        if m not in network.nodes:
            raise AutoPowerError(f"subgroup member {m!r} is not on the network ({', '.join(network.nodes)})")
    state = TeamState(scenario=scenario, time_s=0.0, network=network, allocation=dict(allocation),
                      energies_j=dict(energies_j), disabled_chains=frozenset(disabled_chains), media_locked=True,
                      accounting=accounting, migration=migration or MigrationCosts.from_scenario(scenario))
    view = DecisionView(state)
    member_set = set(members)
    robots = [m for m in members if m != network.basestation]
    net = view.networks[0]
    movable: list[Chain] = []
    fixed: list[Chain] = []
    hosts: dict[str, list[str]] = {}
    started = []
    broken = False  # some stage of the subgroup has no usable host now
    for chain in view.problem.chains:
        mine = False
        for stage in chain.stages:
            host = view.current.get(stage.name)
            stranded = host is None or host not in view.problem.hosts[stage.name]
            if (host in member_set) or (stranded and chain.source in member_set):
                allowed = [h for h in view.problem.hosts[stage.name] if h in member_set]
                hosts[stage.name] = allowed
                mine = True
                broken = broken or stranded
                if host is None:
                    started.append(stage.name)
            else:
                hosts[stage.name] = [host] if not stranded else []
        if mine and all(hosts[s.name] for s in chain.stages):
            movable.append(chain)
        elif all(view.current.get(s.name) in view.problem.hosts[s.name] for s in chain.stages):
            fixed.append(chain)
    space = view.space(net)
    base_load = np.zeros(space.size)
    for chain in fixed:
        base_load += space.chain_load(chain, tuple(view.current[s.name] for s in chain.stages))
    # DAG flows: those between fixed chains are fixed load; those touching a movable one move with it
    fixed_stages = {s.name for c in fixed for s in c.stages}
    movable_stages = {s.name for c in movable for s in c.stages}
    placed = fixed_stages | movable_stages
    flows = [f for f in active_flows(view.problem.chains) if f.producer in placed and f.consumer in placed]
    base_load += dag_load(space, fixed + movable, view.current,
                          [f for f in flows if f.producer in fixed_stages and f.consumer in fixed_stages])
    moving_flows = [f for f in flows if f.producer in movable_stages or f.consumer in movable_stages]
    index = {r: i for i, r in enumerate(space.robots)}
    cols = [index[r] for r in robots if r in index]

    def life_of(alloc: Mapping[str, str]) -> float:
        load = base_load + sum((space.chain_load(c, tuple(alloc[s.name] for s in c.stages)) for c in movable),
                               np.zeros(space.size))
        load = load + dag_load(space, fixed + movable, {**view.current, **alloc}, moving_flows)
        if not space.feasible(load[None, :])[0]:
            return -NEVER
        moves = plan_moves(view.scenario, net, view.current, alloc, view.state.migration)
        cost = total_energy(moves)
        energy = np.maximum(space.energy_j - np.array([cost.get(r, 0.0) for r in space.robots]), 0.0)
        power = space.total_power(load[None, :])[0]
        return float((energy / power)[cols].min()) if cols else NEVER

    before = -NEVER if broken else life_of(view.current)
    combos = 1
    for chain in movable:
        for stage in chain.stages:
            combos *= len(hosts[stage.name])
    if combos <= max_enumeration:
        found = enumerate_network(view, net, movable, hosts, view.current, base_load, robots)
        proposal = dict(view.current)
        if found is not None:
            proposal.update(found[3])
        search = "exhaustive"
    else:
        proposal = neighbourhood_search(view, net, movable, hosts, base_load, robots, life_of, max_rounds,
                                        moving_flows)
        search = "neighbourhood"
    after = life_of(proposal)
    worth = after > -NEVER and (before == -NEVER or beats(after, before, min_gain, min_gain_s))
    final = dict(allocation)
    final.update(proposal if worth else {})
    moves = tuple(plan_moves(view.scenario, net, view.current, final, view.state.migration)) if worth else ()
    reasons = []
    if worth and (moves or started):
        b = "cannot go on" if before == -NEVER else f"{before:,.0f} s"
        reasons.append(f"subgroup {', '.join(members)}: shortest member life {b} → {after:,.0f} s"
                       f" with {len(moves)} move(s)" + (f" and {len(started)} restart(s)" if started else ""))
    elif not worth and before > -NEVER:
        reasons.append(f"subgroup {', '.join(members)}: no reallocation gains more than {min_gain:.1%} + {min_gain_s:g} s")
    else:
        reasons.append(f"subgroup {', '.join(members)}: no feasible reallocation among its members")
    for name, why in view.degraded.items():
        if any(c.name == name for c in movable):
            reasons.append(why)
    return SubgroupProposal(members=members, allocation=final, moves=moves,
                            started=tuple(started) if worth else (),
                            min_lifetime_before_s=None if before == -NEVER else before,
                            min_lifetime_after_s=None if after == -NEVER else after,
                            reasons=tuple(reasons), search=search)


def neighbourhood_search(view: DecisionView, network: Network, chains: list[Chain], hosts: Mapping[str, list[str]],
                          base_load: np.ndarray, robots: Sequence[str], life_of, max_rounds: int,
                          flows=()) -> dict[str, str]:
    """Re-place up to three chains at once (one of them on the bottleneck) until nothing gains.

    Each neighbourhood is searched exactly and vectorised, the other chains' loads held fixed.
    """
    space = view.space(network)
    current = dict(view.current)
    for chain in chains:  # stranded stages start on their source if allowed, else the first member
        for stage in chain.stages:
            if current.get(stage.name) not in hosts[stage.name]:
                allowed = hosts[stage.name]
                current[stage.name] = chain.source if chain.source in allowed else allowed[0]
    value = life_of(current)
    sizes = {c.name: math.prod(len(hosts[s.name]) for s in c.stages) for c in chains}
    index = {r: i for i, r in enumerate(space.robots)}
    for _ in range(max_rounds):
        loads = {c.name: space.chain_load(c, tuple(current[s.name] for s in c.stages)) for c in chains}
        total = base_load + sum(loads.values(), np.zeros(space.size)) + dag_load(space, chains, current, flows)
        power = space.total_power(total[None, :])[0]
        worst = min((r for r in robots if r in index), key=lambda r: space.energy_j[index[r]] / power[index[r]],
                    default=None)
        hot = {c.name for c in chains if any(current[s.name] == worst for s in c.stages)} or {c.name for c in chains}
        best_value, best_alloc = value, None
        for size in (1, 2, 3):
            for group in itertools.combinations(chains, size):
                if not any(c.name in hot for c in group) or math.prod(sizes[c.name] for c in group) > 4096:
                    continue
                others = total - sum((loads[c.name] for c in group), np.zeros(space.size))
                in_group = {s.name for c in group for s in c.stages}  # its DAG flows move with it
                others = others - dag_load(space, chains, current,
                                           [f for f in flows if f.producer in in_group or f.consumer in in_group])
                found = enumerate_network(view, network, group, hosts, view.current, others, robots, flow_ends=current)
                if found is None:
                    continue
                trial = {**current, **found[3]}
                if found[0] > best_value * (1 + 1e-9) + 1e-9 and trial != current:
                    v = life_of(trial)  # with every migration's cost, not only this group's
                    if v > best_value * (1 + 1e-9) + 1e-9:
                        best_value, best_alloc = v, trial
            if best_alloc is not None:
                break
        if best_alloc is None:
            break
        current, value = best_alloc, best_value
    return current


class SubgroupPolicy:
    """The peer-to-peer rule, applied to every connected part of the team (media unchanged)."""

    name = "subgroup"

    def __init__(self, min_gain: float = 0.001, min_gain_s: float = 10.0, recheck_fraction: float = 0.1,
                 min_recheck_s: float = 60.0):
        self.min_gain = min_gain
        self.min_gain_s = min_gain_s
        self.recheck_fraction = recheck_fraction
        self.min_recheck_s = min_recheck_s

    def decide(self, state: TeamState) -> Decision | None:
        view = DecisionView(state)
        if not state.allocation:
            best = view.best_static()
            if best is None:
                raise no_placement(view)
            return self._with_revisit(view, make_decision(self.name, view, best, forced=True, stay_value=None,
                                                      reasons=["mission start: the base station's best static plan"]))
        network = view.stay_network()
        stay_valid = view.stay_valid()
        allocation = dict(view.current)
        reasons: list[str] = []
        for members in subgroups(network):
            proposal = subgroup_reallocation(
                state.scenario, network, members, allocation, view.energies, accounting=view.accounting,
                disabled_chains=frozenset(state.disabled_chains), migration=state.migration, min_gain=self.min_gain,
                min_gain_s=self.min_gain_s)
            if proposal.changes_anything:
                allocation = dict(proposal.allocation)
                reasons.extend(proposal.reasons)
        allocation = {s: h for s, h in allocation.items() if s in view.stages}
        option = view.value(network, allocation, "subgroups")
        stay_value = view.stay().value_s if stay_valid else None
        if option.value_s == -NEVER:
            best = view.best_static()
            if best is None or stay_valid:
                if stay_valid:
                    return None
                raise no_placement(view)
            return self._with_revisit(view, make_decision(
                self.name, view, best, forced=True, stay_value=None,
                reasons=[forced_reason(view), "no subgroup could repair it alone: the base station replanned"]))
        stopped = [s for s in state.allocation if s not in allocation]
        if allocation == view.current and not stopped and stay_valid:
            return self._with_revisit(view, None, option.value_s)
        if not stay_valid:
            reasons.insert(0, forced_reason(view))
        return self._with_revisit(view, make_decision(self.name, view, option, reasons=reasons, forced=not stay_valid,
                                                  stay_value=stay_value))

    def _with_revisit(self, view: DecisionView, decision: Decision | None, horizon_s: float | None = None) -> Decision | None:
        horizon = decision.predicted_lifetime_s if decision is not None else horizon_s
        if horizon is None or not math.isfinite(horizon) or horizon <= 0:
            return decision
        # a fixed fraction of the whole mission (not of what is left): ~1/fraction checks in all
        at = view.state.time_s + max(self.min_recheck_s, self.recheck_fraction * (view.state.time_s + horizon))
        if decision is None:
            stay = view.value(view.stay_network(), view.current, "stay")
            decision = make_decision(self.name, view, stay, reasons=[], forced=False, stay_value=stay.value_s)
        return dataclasses.replace(decision, revisit_at_s=at)


