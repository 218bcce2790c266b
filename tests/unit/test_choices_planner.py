"""Quality variants and DVFS levels in the planner: the MILP equals exhaustive search, the Pareto
front is a front, floors that cannot be met are explained, the one-variant/one-level case is the
plain planner."""

import dataclasses

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from autopower.errors import InfeasibleError
from autopower.model.dvfs import FrequencyLevel, apply_levels
from autopower.model.energy import evaluate
from autopower.model.loading import load_scenario
from autopower.model.variants import Variant, apply_variants
from autopower.planner import PlanRequest, plan
from autopower.planner.choices import exhaustive_choices
from autopower.planner.plan_choices import milp_choices, pareto_front
from autopower.planner.problem import make_problem
from autopower.simulation.synthetic import random_scenario

PXA = (FrequencyLevel(name="400", idle_w=1.34, busy_w=2.27, latency_factor=1.0),
       FrequencyLevel(name="300", idle_w=1.2937, busy_w=1.7931, latency_factor=1.3333),
       FrequencyLevel(name="200", idle_w=1.2696, busy_w=1.5448, latency_factor=2.0),
       FrequencyLevel(name="100", idle_w=1.2548, busy_w=1.3924, latency_factor=4.0))


def with_choices(s, seed: int, variants: bool, levels: int, floor_q: float):
    """Random variants (1-3 per component: slower periods, cheaper runs, other sizes, lower quality),
    the first `levels` PXA255 levels on the robots' platform, and random chain quality floors."""
    rng = np.random.default_rng(seed)
    components = dict(s.components)
    if variants:
        for name, spec in s.components.items():
            k = int(rng.integers(1, 4))
            vs = [Variant(name="full", quality=1.0)]
            for j in range(1, k):
                vs.append(Variant(name=f"v{j}", quality=round(float(rng.uniform(0.3, 0.95)), 3),
                                  period_s=float(rng.choice([None, 0.5, 1.0, 2.0, 4.0]) or 0) or None,
                                  latency_s={p: t * float(rng.uniform(0.2, 1.0)) for p, t in spec.latency_s.items()},
                                  message_bytes=(int(rng.integers(100, 50000)), int(rng.integers(50, 1000)))
                                  if rng.random() < 0.5 else None))
            components[name] = dataclasses.replace(spec, variants=tuple(vs))
    s = dataclasses.replace(s, components=components)
    # multi-stage chains: only the first stage's component keeps its variants (one variant stage per chain)
    for chain in s.chains:
        for st_ in chain.stages[1:]:
            comps = dict(s.components)
            comps[st_.component] = dataclasses.replace(comps[st_.component], variants=())
            s = dataclasses.replace(s, components=comps)
    chains = tuple(dataclasses.replace(c, min_quality=floor_q if rng.random() < 0.3 else 0.0) for c in s.chains)
    platforms = dict(s.platforms)
    if levels > 1:
        platforms["sitsang"] = dataclasses.replace(platforms["sitsang"], levels=PXA[:levels])
    return dataclasses.replace(s, chains=chains, platforms=platforms)


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 10_000), robots=st.integers(2, 3), chains=st.integers(1, 3),
       topology=st.sampled_from(["fully-connected", "relay"]), accounting=st.sampled_from(["paper", "physical"]),
       multi_stage=st.booleans(), variants=st.booleans(), levels=st.integers(1, 4),
       floor=st.sampled_from([0.0, 0.5, 0.8]), chain_floor=st.sampled_from([0.0, 0.6]))
def test_milp_equals_exhaustive_with_variants_and_levels(seed, robots, chains, topology, accounting, multi_stage,
                                                         variants, levels, floor, chain_floor):
    s = with_choices(random_scenario(seed, robots, chains, topology=topology, accounting=accounting,
                                     multi_stage=multi_stage), seed, variants, levels, chain_floor)
    request = PlanRequest(scenario=s)
    problem = make_problem(request)
    best = exhaustive_choices(problem, floor)
    milp, _, _, _ = milp_choices(problem, floor, request)
    if not best:
        assert milp is None
        return
    assert milp is not None
    assert milp.lifetime_s == pytest.approx(best[0].lifetime_s, rel=1e-7)
    assert milp.quality >= floor - 1e-9
    # the MILP's configuration really is feasible under the evaluator, at the levels it carries
    applied = apply_levels(apply_variants(s, milp.variants), milp.levels)
    ev = evaluate(applied, milp.network, milp.allocation, accounting=accounting)
    assert ev.feasible and ev.lifetime_s == pytest.approx(milp.lifetime_s, rel=1e-9)
    for _robot, u in ev.utilisation.items():
        assert u <= 1 + 1e-9  # latencies scaled by the chosen level: utilisation within 100 %
    for chain in s.chains:
        if chain.name in milp.variants:
            q = next(v.quality for v in s.components[chain.stages[0].component].variants
                     if v.name == milp.variants[chain.name])
            assert q >= chain.min_quality - 1e-12


def test_without_variants_and_levels_the_plain_planner_runs():
    s = load_scenario("paper-fig7")
    p = plan(PlanRequest(scenario=s))
    assert p.variants == {} and p.levels == {} and p.quality is None
    assert "variants" not in p.to_dict()


def test_dvfs_plan_charges_the_chosen_level():
    s = load_scenario("paper-pxa255-dvfs")
    p = plan(PlanRequest(scenario=s, method="exhaustive"))
    q = plan(PlanRequest(scenario=s, method="milp"))
    assert p.lifetime_s == pytest.approx(q.lifetime_s, rel=1e-9) and p.levels == q.levels
    # all-laptop at 802.11a leaves every robot idle: the slowest level's idle power wins
    assert p.levels == {"r1": "100MHz", "r2": "100MHz", "r3": "100MHz"}
    assert p.evaluation.robots["r1"].cpu_w == pytest.approx(1.2548)
    assert p.lifetime_s > plan(PlanRequest(scenario=load_scenario("paper-fig7"))).lifetime_s
    assert "r1 runs at 100MHz" in p.reasons["level:r1"]


def test_dvfs_level_keeps_utilisation_within_100_percent():
    s = load_scenario("paper-pxa255-dvfs")
    # everything local: r2 and r3 run Loc (42.5 %) and Blob (46 %) = 88.5 %: only 400 MHz fits
    local = {c.name: c.source for c in s.chains}
    s_local = dataclasses.replace(s, chains=tuple(dataclasses.replace(c, stages=tuple(
        dataclasses.replace(st_, pin=c.source) for st_ in c.stages)) for c in s.chains))
    p = plan(PlanRequest(scenario=s_local, method="exhaustive"))
    assert p.allocation == local
    assert p.levels["r2"] == "400MHz" and p.levels["r3"] == "400MHz"
    assert p.levels["r1"] == "200MHz"  # Loc alone: 42.5 % x 2 = 85 %; 100 MHz would need 170 %
    assert p.evaluation.utilisation["r1"] == pytest.approx(0.85)


def test_pareto_front_trades_lifetime_for_quality():
    s = load_scenario("paper-variants").with_accounting("physical")
    request = PlanRequest(scenario=s, method="exhaustive")
    front = pareto_front(make_problem(request), request)
    assert len(front) >= 3
    lives = [c.lifetime_s for c in front]
    quals = [c.quality for c in front]
    assert lives == sorted(lives, reverse=True) and quals == sorted(quals)
    assert quals[-1] == pytest.approx(1.0)
    assert len(set(np.round(lives, 6))) == len(lives)  # no point dominated by another
    # the MILP sweep finds the same front
    milp_front = pareto_front(make_problem(dataclasses.replace(request, method="milp")),
                              dataclasses.replace(request, method="milp"))
    assert [c.lifetime_s for c in milp_front] == pytest.approx(lives, rel=1e-7)
    assert [c.quality for c in milp_front] == pytest.approx(quals, abs=1e-9)


def test_quality_weight_picks_along_the_front():
    s = load_scenario("paper-variants").with_accounting("physical")
    lifetime_only = plan(PlanRequest(scenario=s, method="exhaustive"))
    quality_only = plan(PlanRequest(scenario=dataclasses.replace(s, quality_weight=1.0), method="exhaustive"))
    assert quality_only.quality == pytest.approx(1.0)
    assert lifetime_only.lifetime_s > quality_only.lifetime_s
    assert quality_only.pareto and quality_only.to_dict()["quality"] == pytest.approx(1.0)


def test_a_chain_floor_that_cannot_be_met_is_explained():
    s = load_scenario("paper-variants").with_accounting("physical")
    # GSM only to the laptop and local blob finding: every Blob variant must fit on r2 beside Loc
    chains = tuple(dataclasses.replace(c, min_quality=1.0) for c in s.chains)
    pinned = tuple(dataclasses.replace(c, stages=tuple(dataclasses.replace(st_, pin=c.source) for st_ in c.stages))
                   for c in chains)
    comps = dict(s.components)
    comps["Blob"] = dataclasses.replace(comps["Blob"], latency_s={**comps["Blob"].latency_s, "sitsang": 0.2})
    s = dataclasses.replace(s, chains=pinned, components=comps)
    with pytest.raises(InfeasibleError) as err:
        plan(PlanRequest(scenario=s, method="exhaustive"))
    text = str(err.value)
    assert "quality floors (Loc-1 ≥ 1" in text and "highest quality that fits is" in text


def test_time_sharing_bound_over_variants_and_levels():
    """The bound switches between configurations (variants and levels included): at least the
    static optimum, its schedule spends no robot's energy twice, and it never beats LP duality."""
    s = load_scenario("paper-variants-dvfs").with_accounting("physical").with_energies({"r2": 32000})
    p = plan(PlanRequest(scenario=s, method="exhaustive", with_bound=True))
    b = p.bound
    assert b.proven and b.lifetime_s >= p.lifetime_s * (1 - 1e-9)
    assert sum(ph.duration_s for ph in b.schedule) == pytest.approx(b.achieved_s, rel=1e-9)
    for robot, energy in s.energies_j().items():
        assert sum(ph.power_w[robot] * ph.duration_s for ph in b.schedule) <= energy * (1 + 1e-9)
    # more configurations than the paper's (levels, variants): never a lower bound than its
    nominal = plan(PlanRequest(scenario=load_scenario("paper-fig7").with_accounting("physical")
                               .with_energies({"r2": 32000}), method="exhaustive", with_bound=True))
    assert b.lifetime_s >= nominal.bound.lifetime_s * (1 + 0.05)
    assert all(any(k.startswith("level:") for k in ph.allocation) for ph in b.schedule)
