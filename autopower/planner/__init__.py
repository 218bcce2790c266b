"""The planner: a pure function from a request to a plan with the reasons for each decision.

`plan(PlanRequest(scenario, ...))` chooses every stage's host and the media, maximising the
team's lifetime, by exhaustive search (small problems, the paper's method) or the HiGHS MILP
(anything larger). Both give the same optimum (a property test checks it).

May import: `autopower.errors`, `autopower.model`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from autopower.errors import AutoPowerError, InfeasibleError
from autopower.model.energy import Evaluation, evaluate
from autopower.model.network import Network
from autopower.planner.exhaustive import exhaustive
from autopower.planner.milp import solve_milp
from autopower.planner.problem import PlanRequest, Problem, make_problem
from autopower.planner.reasons import explain
from autopower.planner.timesharing import TimeSharingBound, time_sharing_bound

EXHAUSTIVE_UP_TO = 20_000  # combinations; beyond it "auto" switches to the MILP

__all__ = ["Plan", "PlanRequest", "TimeSharingBound", "plan", "make_problem", "evaluate_in", "infeasible_error"]


@dataclass
class Plan:
    allocation: dict[str, str]
    network: Network
    evaluation: Evaluation
    reasons: dict[str, str]
    method: str
    proven_optimal: bool
    mip_gap: float = 0.0
    ties: list[tuple[Network, dict[str, str]]] = field(default_factory=list)
    dropped: dict[str, str] = field(default_factory=dict)  # chains that cannot run, and why
    bound: TimeSharingBound | None = None
    variants: dict[str, str] = field(default_factory=dict)  # chain -> quality variant (planner.choices)
    levels: dict[str, str] = field(default_factory=dict)  # robot -> DVFS frequency level
    quality: float | None = None  # mean chain quality; None: the scenario has no variants
    pareto: list = field(default_factory=list)  # the lifetime/quality front, when a weight chose the plan

    @property
    def lifetime_s(self) -> float:
        return self.evaluation.lifetime_s

    def to_dict(self) -> dict:
        ev = self.evaluation
        out = {
            "method": self.method,
            "proven_optimal": self.proven_optimal,
            "mip_gap": self.mip_gap,
            "allocation": dict(self.allocation),
            "media": self.network.media_by_group(),
            "links": [{"a": l.a, "b": l.b, "medium": l.medium} for l in self.network.links],
            "lifetime_s": ev.lifetime_rounded_s,
            "lifetime_raw_s": ev.lifetime_s,
            "bottleneck": ev.bottleneck,
            "reasons": dict(self.reasons),
            "dropped_chains": dict(self.dropped),
            "ties": [{"allocation": a, "media": n.media_by_group()} for n, a in self.ties],
            "evaluation": ev.to_dict(),
        }
        if self.variants or self.levels or self.quality is not None:
            out.update(variants=dict(self.variants), levels=dict(self.levels), quality=self.quality)
        if self.pareto:  # a quality_weight chose the plan on this front
            out["pareto"] = [dict(p) for p in self.pareto]
        if self.bound is not None:
            out["time_sharing_bound"] = {
                "lifetime_s": self.bound.lifetime_s,
                "achieved_s": self.bound.achieved_s,
                "proven": self.bound.proven,
                "method": self.bound.method,
                "gain_over_static": self.bound.lifetime_s / ev.lifetime_s - 1 if ev.lifetime_s else None,
                "schedule": [{"duration_s": p.duration_s, "allocation": p.allocation,
                              "media": p.network.media_by_group(), "power_w": p.power_w}
                             for p in self.bound.schedule],
            }
        return out


def evaluate_in(problem: Problem, network: Network, allocation: dict[str, str]) -> Evaluation:
    """Evaluate an allocation for the chains a problem places (dropped chains excluded)."""
    placed = {c.name for c in problem.chains}
    return evaluate(problem.scenario, network, allocation, accounting=problem.accounting,
                    energies_j=problem.energies_j,
                    disabled_chains=frozenset(c.name for c in problem.scenario.chains) - placed)


def plan(request: PlanRequest) -> Plan:
    """The optimal allocation and media for a request; raises InfeasibleError if nothing fits."""
    problem = make_problem(request)
    from autopower.planner.choices import has_choices

    if has_choices(problem.scenario):  # quality variants or DVFS levels to choose too
        from autopower.planner.plan_choices import plan_with_choices

        return plan_with_choices(request, problem)
    if not any(n != problem.networks[0].basestation for n in problem.networks[0].nodes):
        raise InfeasibleError("no robot is available to plan for (all are unavailable); wait for one to join")
    method = request.method
    if method == "auto":
        method = "exhaustive" if problem.combinations() <= EXHAUSTIVE_UP_TO else "milp"
    if method == "exhaustive":
        candidates = exhaustive(problem, max_ties=request.max_ties)
        if not candidates:
            raise infeasible_error(problem)
        best = candidates[0]
        network, allocation, proven, gap = best.network, best.allocation, True, 0.0
        ties = [(c.network, c.allocation) for c in candidates[1:]]
    elif method == "milp":
        result = solve_milp(problem, time_limit_s=request.time_limit_s, mip_rel_gap=request.mip_rel_gap)
        if result.allocation is None:
            if "Infeasible" in result.status:
                raise infeasible_error(problem)
            raise AutoPowerError(f"the MILP found no plan ({result.status}); raise --time-limit")
        network, allocation, proven, gap = result.network, result.allocation, result.optimal, result.mip_gap
        ties = []
    else:
        raise AutoPowerError(f"unknown planning method {method!r}; use auto, exhaustive or milp")
    evaluation = evaluate_in(problem, network, allocation)
    out = Plan(allocation=allocation, network=network, evaluation=evaluation,
               reasons=explain(problem, network, allocation, evaluation), method=method,
               proven_optimal=proven, mip_gap=gap, ties=ties, dropped=dict(problem.unroutable))
    if request.with_bound:
        out.bound = time_sharing_bound(problem, [(network, allocation)])
    return out


def infeasible_error(problem: Problem) -> InfeasibleError:
    """Why nothing fits: the media tried and, for the closest allocation, the resources that break.

    "Closest" is the allocation (within the request's pins and hosts) whose most loaded resource
    is least over its limit; small problems search every combination for it, large ones take each
    stage at its pin or source (else its first allowed host).
    """
    tried = [_media_text(n) for n in problem.networks]
    if len(tried) == 1:
        where = f"with the media fixed ({tried[0]})"
    else:
        where = f"on any of the {len(tried)} media choices tried ({'; '.join(tried)})"
    closest = _closest(problem)
    hint = ""
    if closest is not None:
        network, allocation, ev = closest
        placed = ", ".join(f"{s}→{h}" for s, h in allocation.items())
        hint = (f"; the closest allocation ({placed}{'' if len(tried) == 1 else ' with ' + _media_text(network)}) "
                f"still breaks: {'; '.join(v.message for v in ev.violations)}")
    return InfeasibleError(
        f"no allocation meets the CPU and radio limits {where}{hint}. "
        "Lower the chains' rates, disable a chain, or allow faster media."
    )


def _media_text(network: Network) -> str:
    return ", ".join(f"{g}={m}" for g, m in network.media_by_group().items()) or "no links"


def _closest(problem: Problem) -> tuple[Network, dict[str, str], Evaluation] | None:
    best = None
    for network in problem.networks:
        try:
            if problem.combinations() <= EXHAUSTIVE_UP_TO:
                from autopower.planner.exhaustive import decode_allocation, search_network

                space, loads, options = search_network(problem, network)
                k = int(np.argmin(space.peak_utilisation(loads)))
                allocation = decode_allocation(problem.chains, options, k)
            else:
                allocation = {s.name: (s.pin or (c.source if c.source in problem.hosts[s.name]
                                                 else problem.hosts[s.name][0]))
                              for c in problem.chains for s in c.stages}
            ev = evaluate_in(problem, network, allocation)
        except AutoPowerError:
            continue
        peak = max((v.value / v.limit for v in ev.violations), default=0.0)
        if ev.violations and (best is None or peak < best[0]):
            best = (peak, network, allocation, ev)
    return best[1:] if best else None
