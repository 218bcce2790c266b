"""`plan` for scenarios with quality variants or DVFS levels (see `planner.choices`).

The plan carries the chosen variant of every chain and level of every robot; its evaluation is
the scenario with those applied (`model.variants.apply_variants`, `model.dvfs.apply_levels`), so
the model, the meter and the reasons all price the same thing.
"""

from __future__ import annotations

import dataclasses

from autopower.errors import AutoPowerError, InfeasibleError
from autopower.model.dvfs import level_named
from autopower.model.variants import has_variants
from autopower.planner.choices import (
    Choice,
    alternatives,
    applied_scenario,
    combinations,
    enumerate_choices,
    evaluate_choice,
    exhaustive_choices,
    expand,
    finish_choice,
)
from autopower.planner.exhaustive import TIE_REL
from autopower.planner.milp import solve_milp
from autopower.planner.problem import PlanRequest, Problem
from autopower.planner.reasons import explain


def plan_with_choices(request: PlanRequest, problem: Problem):
    from autopower.planner import Plan, infeasible_error

    if not any(n != problem.networks[0].basestation for n in problem.networks[0].nodes):
        raise InfeasibleError("no robot is available to plan for (all are unavailable); wait for one to join")
    scenario = problem.scenario
    weight = scenario.quality_weight if has_variants(scenario) else 0.0
    front: list[Choice] = []
    if weight > 0:
        front = pareto_front(problem, request)
        found = [weighted_pick(front, weight)] if front else []
        method, proven, gap = ("exhaustive" if request.method == "auto" else request.method), True, 0.0
    else:
        found, method, proven, gap = solve(problem, request)
    if not found:
        if any(c.min_quality > 0 for c in problem.chains):
            raise floor_error(problem, request, 0.0)
        raise infeasible_error(problem)
    best = found[0]
    applied = applied_scenario(scenario, best.variants, best.levels)
    evaluation = evaluate_choice(problem, applied, best.network, best.allocation)
    placed = {c.name for c in problem.chains}
    applied_problem = dataclasses.replace(problem, scenario=applied,
                                          chains=[c for c in applied.chains if c.name in placed])
    reasons = explain(applied_problem, best.network, best.allocation, evaluation)
    reasons.update(choice_reasons(problem, request, best))
    out = Plan(allocation=best.allocation, network=best.network, evaluation=evaluation, reasons=reasons,
               method=method, proven_optimal=proven, mip_gap=gap,
               ties=[(c.network, c.allocation) for c in found[1:]], dropped=dict(problem.unroutable),
               variants=dict(best.variants), levels=dict(best.levels),
               quality=best.quality if has_variants(scenario) else None,
               pareto=[{"lifetime_s": c.lifetime_s, "quality": c.quality, "variants": c.variants,
                        "levels": c.levels} for c in front])
    if request.with_bound:
        out.bound = choice_time_sharing_bound(problem)
    return out


def choice_reasons(problem: Problem, request: PlanRequest, best: Choice) -> dict[str, str]:
    """Why each chain runs its variant and each robot its level: the plan against the next one up."""
    out = {}
    for chain in problem.chains:
        alts = alternatives(problem, chain)
        if alts[0].variant is None:
            continue
        chosen = best.variants[chain.name]
        q = next(a.quality for a in alts if a.variant == chosen)
        floor = f"min_quality {chain.min_quality:g}" if chain.min_quality > 0 else "no min_quality"
        better = [a for a in alts if a.quality > q]
        text = f"{chain.name} runs variant {chosen} (quality {q:g}; {floor})"
        if better:
            up = min(better, key=lambda a: a.quality)
            trial = finish_choice(problem, best.network, best.allocation, {**best.variants, chain.name: up.variant})
            if trial.lifetime_s == float("-inf"):
                text += f"; {up.variant} (quality {up.quality:g}) does not fit with this placement"
            else:
                text += (f"; {up.variant} (quality {up.quality:g}) with this placement gives "
                         f"{trial.lifetime_s:,.1f} s ({trial.lifetime_s / best.lifetime_s - 1:+.1%})")
        out[f"variant:{chain.name}"] = text + "."
    applied = applied_scenario(problem.scenario, best.variants, {})
    ev = evaluate_choice(problem, applied, best.network, best.allocation)
    for robot, level_name in best.levels.items():
        level = level_named(problem.scenario, robot, level_name)
        u = ev.utilisation[robot]
        text = (f"{robot} runs at {level_name}: CPU {u:.1%} at nominal speed becomes {u * level.latency_factor:.1%}, "
                f"{level.idle_w + (level.busy_w - level.idle_w) * level.latency_factor * u:.4f} W")
        slower = [lv for lv in problem.scenario.platform_of(robot).levels if lv.latency_factor > level.latency_factor]
        if slower:
            nxt = min(slower, key=lambda lv: lv.latency_factor)
            if u * nxt.latency_factor > 1:
                text += f"; {nxt.name} would need {u * nxt.latency_factor:.0%} CPU"
            else:
                text += (f"; {nxt.name} would draw "
                         f"{nxt.idle_w + (nxt.busy_w - nxt.idle_w) * nxt.latency_factor * u:.4f} W")
        out[f"level:{robot}"] = text + "."
    return out


def milp_choices(problem: Problem, floor: float, request) -> tuple[Choice | None, bool, float, str]:
    expanded = expand(problem, floor)
    result = solve_milp(expanded, time_limit_s=request.time_limit_s, mip_rel_gap=request.mip_rel_gap)
    if result.allocation is None:
        return None, False, 1.0, result.status
    allocation, variants = {}, {}
    for stage, host in result.allocation.items():
        name, _, variant = stage.partition("@")
        allocation[name] = host
    for _chain_name, alt in expanded.alternative.items():
        if alt.variant is not None and all(s.name in result.allocation for s in alt.model_chain.stages):
            variants[alt.chain.name] = alt.variant
    choice = finish_choice(problem, result.network, allocation, variants)
    return choice, result.optimal, result.mip_gap, result.status


# ---- one plan, and the Pareto front --------------------------------------------------------------
def solve(problem: Problem, request, floor: float = 0.0) -> tuple[list[Choice], str, bool, float]:
    """(best first, ties included; method; proven; gap). [] when nothing meets the floor."""
    method = request.method
    if method == "auto":
        method = "exhaustive" if combinations(problem) <= 20_000 else "milp"
    if method == "exhaustive":
        return exhaustive_choices(problem, floor, request.max_ties), method, True, 0.0
    if method != "milp":
        raise AutoPowerError(f"unknown planning method {method!r}; use auto, exhaustive or milp")
    choice, optimal, gap, status = milp_choices(problem, floor, request)
    if choice is None and "Infeasible" not in status:
        raise AutoPowerError(f"the MILP found no plan ({status}); raise --time-limit")
    return ([choice] if choice else []), method, optimal, gap


def pareto_front(problem: Problem, request) -> list[Choice]:
    """Every lifetime/quality trade-off no other plan beats on both (epsilon-constraint sweep: the
    longest-lived plan, then the longest-lived of strictly higher quality, until none exists)."""
    front: list[Choice] = []
    floor = 0.0
    while True:
        found, _, _, _ = solve(problem, request, floor)
        if not found:
            break
        best = found[0]
        if front and best.lifetime_s >= front[-1].lifetime_s * (1 - TIE_REL):
            front.pop()  # the same lifetime at a higher quality dominates the previous point
        front.append(best)
        floor = best.quality + 1e-6
    return front


def weighted_pick(front: list[Choice], weight: float) -> Choice:
    """The front's point maximising (1 - w) * L / L_best + w * Q."""
    top = max(c.lifetime_s for c in front)
    return max(front, key=lambda c: ((1 - weight) * c.lifetime_s / top + weight * c.quality, c.quality))


def floor_error(problem: Problem, request, floor: float) -> InfeasibleError:
    """Why no plan reaches the quality floors: which floors, and the best quality that does fit."""
    floors = [f"{c.name} ≥ {c.min_quality:g}" for c in problem.chains if c.min_quality > 0]
    relaxed = dataclasses.replace(problem, scenario=dataclasses.replace(problem.scenario, chains=tuple(
        dataclasses.replace(c, min_quality=0.0) for c in problem.scenario.chains)))
    relaxed.chains = [dataclasses.replace(c, min_quality=0.0) for c in problem.chains]
    front = pareto_front(relaxed, dataclasses.replace(request, method=request.method))
    asked = ", ".join(floors + ([f"mean quality ≥ {floor:g}"] if floor > 0 else []))
    if not front:
        return InfeasibleError(f"no allocation fits the CPU and radio limits even at the lowest-quality variants "
                               f"(quality floors asked: {asked or 'none'})")
    best = max(front, key=lambda c: c.quality)
    return InfeasibleError(
        f"no allocation meets the quality floors ({asked}) within the CPU and radio limits; the highest "
        f"quality that fits is {best.quality:.3f} (variants {', '.join(f'{k}={v}' for k, v in best.variants.items())}"
        f", lifetime {best.lifetime_s:,.1f} s). Lower min_quality, or allow faster media or more hosts.")


def choice_time_sharing_bound(problem: Problem, floor: float = 0.0):
    """The time-sharing bound (`planner.timesharing`) over configurations that include variants
    and levels: every configuration meeting the quality floors, each robot at its best level (the
    best level minimises every robot's power at once, so other levels never help a schedule).
    Exact by enumeration with column generation on the LP; None when there are too many."""
    import numpy as np

    from autopower.planner.exhaustive import MAX_COMBINATIONS
    from autopower.planner.timesharing import Phase, TimeSharingBound, price_enumerated

    if combinations(problem) > MAX_COMBINATIONS:
        return None
    blocks = [(b, np.flatnonzero(np.isfinite(b.life))) for b in enumerate_choices(problem, floor)]
    blocks = [(b, ok) for b, ok in blocks if ok.size]
    if not blocks:
        return TimeSharingBound(0.0, 0.0, True, [], "enumeration")
    powers = np.concatenate([b.power[ok] for b, ok in blocks])
    where = [(b, int(i)) for b, ok in blocks for i in ok]
    energies = blocks[0][0].space.energy_j
    robots = blocks[0][0].space.robots
    chosen = [int(np.argmin((powers / energies).max(axis=1)))]
    sol, bound, achieved, converged = price_enumerated(powers, energies, chosen)
    phases = []
    for k, t in zip(chosen, sol.values, strict=False):
        if t > 1e-6:
            block, i = where[k]
            c = block.decode(i)
            phases.append(Phase(float(t), c.network, {**c.allocation, **{f"variant:{n}": v for n, v in c.variants.items()},
                                                      **{f"level:{r}": lv for r, lv in c.levels.items()}},
                                dict(zip(robots, map(float, powers[k]), strict=False))))
    phases.sort(key=lambda p: -p.duration_s)
    return TimeSharingBound(bound, achieved, converged, phases, "enumeration (variants and levels)")


def mission_variants(scenario, chosen: dict[str, str] | None = None) -> dict[str, str]:
    """The variants a live mission runs (fixed for it): the operator's choice where given, the
    planner's for the other chains (its first-declared variant if nothing fits)."""
    from autopower.errors import ScenarioError
    from autopower.model.variants import check_choice, default_choice
    from autopower.planner import plan

    chosen = dict(chosen or {})
    if not has_variants(scenario):
        if chosen:
            raise ScenarioError(f"{scenario.source_path}: --variant given but no component declares variants")
        return {}
    check_choice(scenario, chosen)
    try:
        planned = plan(PlanRequest(scenario=scenario)).variants
    except AutoPowerError:
        planned = default_choice(scenario)
    return {**planned, **chosen}
