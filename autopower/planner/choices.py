"""Planning with quality variants and DVFS levels: variants, hosts, media and levels chosen together.

- Variants: every chain with variants offers one alternative per admissible variant (its
  min_quality met); a plan takes exactly one. The exhaustive search enumerates (variant, hosts)
  per chain; the MILP holds every alternative as its own chain with renamed stages, and a binary
  per variant selects one (`add_selection_row`, hooked into `PlacementModel`).
- Quality floor: a plan's mean chain quality must reach `floor` (the Pareto sweep raises it).
- DVFS: the best level of a robot depends only on its own nominal utilisation (`model.dvfs`), so
  the exhaustive search takes it per robot and combination; the MILP has one binary per level
  and the utilisation carried at each level (`dvfs_cpu_power`, hooked into `PlacementModel.power`).

Scenarios without variants and levels never come here (`has_choices`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Mapping

import numpy as np

from autopower.errors import AutoPowerError
from autopower.model.dvfs import apply_levels, best_levels, cpu_at_best_levels, has_levels, level_table
from autopower.model.energy import LoadSpace, evaluate
from autopower.model.network import Network
from autopower.model.scenario import Chain, Scenario
from autopower.model.variants import admissible, apply_variants, has_variants, variant_chain, with_variant_components
from autopower.planner.exhaustive import MAX_COMBINATIONS, TIE_REL, combine
from autopower.planner.lp import INF
from autopower.planner.problem import Problem

QUALITY_EPS = 1e-9


def has_choices(scenario: Scenario) -> bool:
    return has_variants(scenario) or has_levels(scenario)


@dataclass(frozen=True)
class Alternative:
    chain: Chain  # the chain as declared
    variant: str | None
    quality: float
    model_chain: Chain  # the chain running the variant, named "<chain>@<variant>" (unique cache key)


def alternatives(problem: Problem, chain: Chain) -> list[Alternative]:
    variants = admissible(problem.scenario, chain)
    if not variants:
        return [Alternative(chain, None, 1.0, chain)]
    out = []
    for v in variants:
        mc = variant_chain(problem.scenario, chain, v, rename=True)
        mc = dataclasses.replace(mc, stages=tuple(dataclasses.replace(s, name=f"{orig.name}@{v.name}")
                                                  for s, orig in zip(mc.stages, chain.stages, strict=False)))
        out.append(Alternative(chain, v.name, v.quality, mc))
    return out


@dataclass
class Choice:
    """One configuration: placement, media, variants and levels, with its lifetime and quality."""

    lifetime_s: float  # raw
    quality: float
    spread: float
    network: Network
    allocation: dict[str, str]
    variants: dict[str, str]
    levels: dict[str, str]


def applied_scenario(scenario: Scenario, variants: Mapping[str, str], levels: Mapping[str, str]) -> Scenario:
    return apply_levels(apply_variants(scenario, variants), levels)


# ---- exhaustive ------------------------------------------------------------------------------------
def combinations(problem: Problem) -> int:
    n = len(problem.networks)
    for chain in problem.chains:
        n *= len(alternatives(problem, chain)) * len(problem.options(chain))
    return n


@dataclass
class Enumerated:
    """Every configuration on one network: loads, mean quality, lifetime and power at the best levels."""

    network: Network
    space: LoadSpace
    quality: np.ndarray  # (K,)
    life: np.ndarray  # (K,) raw; -inf where infeasible or below the floor
    power: np.ndarray  # (K, R)
    level_pick: np.ndarray  # (K, R)
    picks: list  # per chain: [(Alternative, hosts)]

    def decode(self, k: int) -> Choice:
        idx = np.unravel_index(int(k), [len(o) for o in self.picks])
        allocation, variants = {}, {}
        for opts, i in zip(self.picks, idx, strict=True):
            alt, hosts = opts[int(i)]
            for stage, host in zip(alt.chain.stages, hosts, strict=False):
                allocation[stage.name] = host
            if alt.variant is not None:
                variants[alt.chain.name] = alt.variant
        _, _, _, names = level_table(self.space.scenario, self.space.robots)
        levels = {r: names[j][int(self.level_pick[k, j])] for j, r in enumerate(self.space.robots) if names[j][0]}
        spread = float((self.power[k] / self.space.energy_j).sum())
        return Choice(float(self.life[k]), float(self.quality[k]), spread, self.network, allocation, variants, levels)


def enumerate_choices(problem: Problem, floor: float = 0.0):
    """Per network, every (variant, hosts) combination of the chains, scored at the best levels."""
    if combinations(problem) > MAX_COMBINATIONS:
        raise AutoPowerError(f"{combinations(problem):,} combinations of variants and hosts is too many for "
                             f"exhaustive search (limit {MAX_COMBINATIONS:,}); use --method milp")
    scenario = with_variant_components(problem.scenario)
    n_chains = max(1, len(problem.chains))
    for network in problem.networks:
        space = LoadSpace(scenario, network, problem.accounting, problem.energies_j)
        loads, quality, picks = np.zeros((1, space.size)), np.zeros((1, 1)), []
        for chain in problem.chains:
            opts, rows, q = [], [], []
            for alt in alternatives(problem, chain):
                for hosts in problem.options(chain):
                    opts.append((alt, hosts))
                    rows.append(space.chain_load(alt.model_chain, hosts))
                    q.append([alt.quality])
            loads, quality = combine(loads, np.array(rows)), combine(quality, np.array(q))
            picks.append(opts)
        quality = quality[:, 0] / n_chains
        life, power, level_pick = lifetimes_with_levels(space, loads)
        life = np.where(quality >= floor - QUALITY_EPS, life, -np.inf)
        yield Enumerated(network, space, quality, life, power, level_pick, picks)


def exhaustive_choices(problem: Problem, floor: float = 0.0, max_ties: int = 8) -> list[Choice]:
    """The best configurations with mean quality >= floor (ties: higher quality, then less drain)."""
    found: list[Choice] = []
    for block in enumerate_choices(problem, floor):
        best = block.life.max()
        if not np.isfinite(best):
            continue
        for k in np.flatnonzero(block.life >= best * (1 - TIE_REL)):
            found.append(block.decode(int(k)))
    if not found:
        return []
    top = max(c.lifetime_s for c in found)
    ties = [c for c in found if c.lifetime_s >= top * (1 - TIE_REL)]
    ties.sort(key=lambda c: (-c.quality, c.spread))
    return ties[:max_ties]


def lifetimes_with_levels(space: LoadSpace, loads: np.ndarray):
    """Raw lifetime per load row with every robot at its best level (-inf where infeasible), the
    robots' power (K, R) and the chosen level index (K, R)."""
    parts = space.breakdown(loads)
    radio_w = (parts["send_w"] + parts["receive_w"] + parts["sleep_w"]).sum(axis=2)
    cpu_w, pick = cpu_at_best_levels(space, parts)
    power = cpu_w + radio_w
    life = (space.energy_j / power).min(axis=1)
    ok = space.feasible(loads) & np.isfinite(cpu_w).all(axis=1)
    return np.where(ok, life, -np.inf), power, pick


# ---- MILP --------------------------------------------------------------------------------------------
@dataclass
class ChoiceProblem(Problem):
    """A problem whose chains are every admissible alternative (stages renamed "<stage>@<variant>")."""

    original: Problem | None = None
    group_of: dict[str, str] = field(default_factory=dict)  # alternative chain -> declared chain
    alternative: dict[str, Alternative] = field(default_factory=dict)  # alternative chain -> what it runs
    floor: float = 0.0


def expand(problem: Problem, floor: float) -> ChoiceProblem:
    scenario = with_variant_components(problem.scenario)
    out = ChoiceProblem(scenario=scenario, accounting=problem.accounting, energies_j=problem.energies_j,
                        networks=problem.networks, chains=[], unroutable=problem.unroutable,
                        hosts=dict(problem.hosts), original=problem, floor=floor)
    for chain in problem.chains:
        for alt in alternatives(problem, chain):
            out.chains.append(alt.model_chain)
            out.group_of[alt.model_chain.name] = chain.name
            out.alternative[alt.model_chain.name] = alt
            for stage, orig in zip(alt.model_chain.stages, chain.stages, strict=False):
                out.hosts[stage.name] = problem.hosts[orig.name]
    # the MILP evaluates its answer on this scenario: every alternative is a chain, the unchosen idle
    out.scenario = dataclasses.replace(scenario, chains=tuple(out.chains))
    return out


def add_selection_row(model, chain: Chain, cols: Mapping[str, int]) -> bool:
    """Hook for `PlacementModel`: a variant alternative's stage is placed iff its variant is chosen
    (sum_h x = w_variant; sum_variants w = 1; the quality floor on the w). False: not a variant."""
    problem = model.problem
    if not isinstance(problem, ChoiceProblem) or problem.alternative[chain.name].variant is None:
        return False
    if not hasattr(model, "variant_cols"):
        model.variant_cols = {}
        groups: dict[str, list[int]] = {}
        quality_row, constant = {}, 0.0
        n = max(1, len(problem.original.chains))
        for name, alt in problem.alternative.items():
            if alt.variant is None:
                constant += 1.0 / n
                continue
            col = model.lp.binary()
            model.variant_cols[name] = col
            groups.setdefault(problem.group_of[name], []).append(col)
            quality_row[col] = alt.quality / n
        for cols_of_group in groups.values():
            model.lp.row({c: 1.0 for c in cols_of_group}, 1.0, 1.0)
        if problem.floor > 0:
            model.lp.row(quality_row, problem.floor - constant - QUALITY_EPS, INF)
    model.lp.row({**{c: 1.0 for c in cols.values()}, model.variant_cols[chain.name]: -1.0}, 0.0, 0.0)
    return True


def dvfs_cpu_power(model, robot: str, expr: dict[int, float], const: float) -> tuple[dict[int, float], float]:
    """Hook for `PlacementModel.power`: with levels, the CPU power is sum_l idle_l z_l +
    (busy_l - idle_l) f_l u_l, where the nominal utilisation u = sum_l u_l and 0 <= u_l <= z_l / f_l
    (one level, z binary, carries all of it, within 100 % once scaled). Without levels: unchanged."""
    levels = model.scenario.platform_of(robot).levels
    if not levels:
        return expr, const
    lp = model.lp
    z = [lp.binary() for _ in levels]
    u = [lp.var(0.0, INF) for _ in levels]
    lp.row({c: 1.0 for c in z}, 1.0, 1.0)
    lp.row({**{c: 1.0 for c in u}, **{col: -coef for col, coef in model.cpu[robot].items()}}, 0.0, 0.0)
    for zc, uc, lv in zip(z, u, levels, strict=True):
        lp.row({uc: 1.0, zc: -1.0 / lv.latency_factor}, -INF, 0.0)
    out = {col: coef for col, coef in expr.items() if col not in model.cpu[robot]}
    for zc, uc, lv in zip(z, u, levels, strict=True):
        out[zc] = lv.idle_w
        out[uc] = (lv.busy_w - lv.idle_w) * lv.latency_factor
    return out, const - model.scenario.platform_of(robot).idle_w


def finish_choice(problem: Problem, network: Network, allocation: dict[str, str],
                  variants: dict[str, str]) -> Choice:
    """Levels for a placement (each robot's cheapest fitting level) and its lifetime and quality."""
    with_variants = apply_variants(problem.scenario, variants)
    ev = evaluate_choice(problem, with_variants, network, allocation)
    levels = best_levels(problem.scenario, ev.utilisation)
    ev = evaluate_choice(problem, apply_levels(with_variants, levels), network, allocation)
    n = max(1, len(problem.chains))
    quality = sum(next((a.quality for a in alternatives(problem, c) if a.variant == variants.get(c.name)), 1.0)
                  for c in problem.chains) / n
    spread = sum(rp.total_w / rp.energy_j for rp in ev.robots.values())
    return Choice(ev.lifetime_s or -np.inf, quality, spread, network, allocation, variants, levels)


def evaluate_choice(problem: Problem, scenario: Scenario, network: Network, allocation: dict[str, str]):
    placed = {c.name for c in problem.chains}
    return evaluate(scenario, network, allocation, accounting=problem.accounting, energies_j=problem.energies_j,
                    disabled_chains=frozenset(c.name for c in scenario.chains) - placed)
