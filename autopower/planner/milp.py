"""The placement MILP on HiGHS: hosts and media that maximise the team's lifetime.

Variables: x[stage, host] (binary), y[group, medium] (binary, only where a group has a choice),
T (continuous). Minimise T subject to, for every robot i,

    P_i(x, y) <= (E_i / E_ref) * T          (lifetime = E_ref / T)
    cpu_u_i <= 1,  busy_i,m <= 1

P_i is linear in products of binaries (a flow's hop on a medium exists when its endpoints' hosts
and its group's medium are chosen). Every such product appears with a non-negative coefficient
(send/receive power >= sleep power, checked when a scenario loads), so the standard lower-bound
linearisation v >= sum(b) - (k - 1), v >= 0 is exact at the optimum.

A second solve with T fixed at its optimum minimises sum_i P_i / E_i, so non-bottleneck robots
are not left burning energy for nothing (the same tie-break as the exhaustive search).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from itertools import product
from typing import Mapping

from autopower.errors import AutoPowerError
from autopower.model.energy import airtime_s, flow_rate_hz
from autopower.model.network import Clique, Link, Network
from autopower.planner import repair
from autopower.planner.choices import add_selection_row, dvfs_cpu_power
from autopower.planner.lp import INF, LinearProgram, Solution
from autopower.planner.moves import MoveSearch
from autopower.planner.problem import Problem

TERM = tuple[int, ...]  # product of binary columns; () = the constant 1


@dataclass
class MilpResult:
    allocation: dict[str, str] | None
    network: Network | None
    lifetime_s: float | None  # the model's lifetime of the returned plan (raw)
    optimal: bool
    mip_gap: float
    status: str
    runtime_s: float
    columns: int
    rows: int
    proven_s: float | None = None  # when a plan reached the per-robot bound: seconds to find it (before the tie-break)
    untied_allocation: dict[str, str] | None = None  # that plan as found, before the tie-break (least total drain)
    found_by: str | None = None  # who found it: "moves" (moves.MoveSearch.reach), "moves near the plan in force" or "highs"


class PlacementModel:
    """Builds the MILP for a problem; `objective` is either min-max or a weighted power sum."""

    def __init__(self, problem: Problem):
        self.problem = problem
        self.scenario = problem.scenario
        base = problem.networks[0]
        self.structure = base
        self.nodes = list(base.nodes)
        self.robots = [n for n in self.nodes if n != base.basestation]
        self.lp = LinearProgram()
        self._products: dict[TERM, int] = {}
        # media groups: every link of the structure, with the candidates seen across networks
        self.group_media: dict[str, list[str]] = {}
        self.link_group: dict[frozenset, str] = {}
        self.clique_group: dict[int, str] = {}  # a clique's links share one group (and one medium)
        self._hop_terms: dict[tuple[str, str], list[tuple[str, TERM]]] = {}
        joint = len(problem.networks) > 1
        for network in problem.networks:
            named = [(self.link_group, frozenset((l.a, l.b)), l.group if joint else f"{l.a}-{l.b}", l.medium)
                     for l in network.explicit]
            named += [(self.clique_group, i, c.group if joint else f"clique {i}", c.medium)
                      for i, c in enumerate(network.cliques)]
            for index, key, group, medium in named:
                index[key] = group
                media = self.group_media.setdefault(group, [])
                if medium not in media:
                    media.append(medium)
        self.y: dict[tuple[str, str], int] = {}
        for group, media in self.group_media.items():
            if len(media) > 1:
                cols = [self.lp.binary() for _ in media]
                self.y.update({(group, m): c for m, c in zip(media, cols, strict=True)})
                self.lp.row({c: 1.0 for c in cols}, 1.0, 1.0)
        self.x: dict[tuple[str, str], int] = {}
        for chain in problem.chains:
            for stage in chain.stages:
                cols = {h: self.lp.binary() for h in problem.hosts[stage.name]}
                self.x.update({(stage.name, h): c for h, c in cols.items()})
                if not add_selection_row(self, chain, cols):  # a quality variant: placed iff chosen
                    self.lp.row({c: 1.0 for c in cols.values()}, 1.0, 1.0)
        self._build_loads()

    # ---- linear pieces -----------------------------------------------------------------------
    def product(self, term: TERM) -> int | None:
        """Column equal to the product of binary columns (None for the constant 1)."""
        if len(term) < 2:
            return term[0] if term else None
        term = tuple(sorted(set(term)))
        if len(term) == 1:
            return term[0]
        col = self._products.get(term)
        if col is None:
            col = self.lp.var(0.0, 1.0)
            # v >= sum(b) - (k-1)  <=>  v - sum(b) >= 1 - k
            self.lp.row({col: 1.0, **{b: -1.0 for b in term}}, 1.0 - len(term), INF)
            self._products[term] = col
        return col

    def media_terms(self, a: str, b: str) -> list[tuple[str, TERM]]:
        terms = self._hop_terms.get((a, b))
        if terms is None:  # a hop is on many flows' routes
            group = self.link_group.get(frozenset((a, b)))
            if group is None:
                group = self.clique_group[self.structure.clique_between(a, b)]
            terms = self._hop_terms[a, b] = self.group_terms(group)
        return terms

    def group_terms(self, group: str) -> list[tuple[str, TERM]]:
        media = self.group_media[group]
        if len(media) == 1:
            return [(media[0], ())]
        return [(m, (self.y[(group, m)],)) for m in media]

    def _build_loads(self) -> None:
        """Linear expressions (col -> coef, const) for CPU and per-radio airtime."""
        cpu = {n: {} for n in self.nodes}
        send = {(n, m): {} for n in self.nodes for m in self.scenario.radios}
        recv = {(n, m): {} for n in self.nodes for m in self.scenario.radios}
        self.const_send = {k: 0.0 for k in send}
        self.const_recv = {k: 0.0 for k in recv}

        def add(expr: dict, consts: dict, key, term: TERM, coef: float) -> None:
            col = self.product(term)
            if col is None:
                consts[key] += coef
            else:
                expr[col] = expr.get(col, 0.0) + coef

        platform = {n: self.scenario.platform_of(n).name for n in self.nodes}  # (a fleet asks 100,000 times)
        hop_media: dict[tuple[str, str], list] = {}  # (u, v) -> its route's hops and their media: flows share pairs
        for chain in self.problem.chains:
            for stage in chain.stages:
                latency = self.scenario.components[stage.component].latency_s
                for host in self.problem.hosts[stage.name]:
                    col = self.x[(stage.name, host)]
                    u = latency[platform[host]] / chain.period_s
                    cpu[host][col] = cpu[host].get(col, 0.0) + u
            rate = flow_rate_hz(chain, self.problem.accounting)
            ends: list[list[tuple[str, TERM]]] = [[(chain.source, ())]]
            for stage in chain.stages:
                ends.append([(h, (self.x[(stage.name, h)],)) for h in self.problem.hosts[stage.name]])
            ends.append([(chain.sink, ())])
            for k, n_bytes in enumerate(chain.message_bytes):
                if n_bytes == 0:
                    continue
                air_of = {m: airtime_s(n_bytes, radio) * rate for m, radio in self.scenario.radios.items()}
                for (u_node, u_term), (v_node, v_term) in product(ends[k], ends[k + 1]):
                    if u_node == v_node:
                        continue
                    hops = hop_media.get((u_node, v_node))
                    if hops is None:
                        hops = hop_media[u_node, v_node] = [(a, b, self.media_terms(a, b))
                                                            for a, b, _ in self.structure.route(u_node, v_node)]
                    for a, b, hop_terms in hops:
                        loss = self.scenario.link_loss(a, b)  # a lossy hop's retransmissions (model.energy)
                        for medium, m_term in hop_terms:
                            air = air_of[medium] if not loss else airtime_s(n_bytes, self.scenario.radios[medium],
                                                                           loss) * rate
                            term = u_term + v_term + m_term
                            add(send[(a, medium)], self.const_send, (a, medium), term, air)
                            add(recv[(b, medium)], self.const_recv, (b, medium), term, air)
        self._add_dag_flows(add, send, recv)
        self._add_control_plane(add, send, recv)
        self.cpu, self.send, self.recv = cpu, send, recv

        # radio presence r[i, m] >= y[g, m] for every link of i (a constant 1 for fixed media)
        self.present: dict[tuple[str, str], int | float] = {}
        for robot in self.robots:
            groups = [self.link_group[frozenset((l.a, l.b))] for l in self.structure.explicit_links_of(robot)]
            groups += [self.clique_group[i] for i in self.structure.cliques_of(robot)]
            for group in dict.fromkeys(groups):
                for medium, m_term in self.group_terms(group):
                    key = (robot, medium)
                    if not m_term:
                        self.present[key] = 1.0
                    elif self.present.get(key) != 1.0:
                        if key not in self.present:
                            self.present[key] = self.lp.var(0.0, 1.0)
                        self.lp.row({self.present[key]: 1.0, m_term[0]: -1.0}, 0.0, INF)

        # utilisation limits
        for node in self.nodes:
            if cpu[node]:
                self.lp.row(cpu[node], -INF, 1.0)
        radio_limited = self.robots + ([self.structure.basestation] if self.scenario.basestation_radio_limit else [])
        for node in radio_limited:
            for medium in self.scenario.radios:
                key = (node, medium)
                busy = dict(send[key])
                for col, coef in recv[key].items():
                    busy[col] = busy.get(col, 0.0) + coef
                const = self.const_send[key] + self.const_recv[key]
                if busy:
                    self.lp.row(busy, -INF, 1.0 - const)

    def _add_dag_flows(self, add, send: dict, recv: dict) -> None:
        """DAG flows (autopower.model.dag): a hop exists when the producer's and the consumer's
        hosts (and the hop's medium) are chosen, like a chain's own hops."""
        by_stage = {s.name: c for c in self.problem.chains for s in c.stages}
        for flow in self.problem.flows:
            if flow.n_bytes == 0:
                continue
            rate = flow_rate_hz(by_stage[flow.producer], self.problem.accounting)
            for u_node, v_node in product(self.problem.hosts[flow.producer], self.problem.hosts[flow.consumer]):
                if u_node == v_node:
                    continue
                hosts_term = (self.x[(flow.producer, u_node)], self.x[(flow.consumer, v_node)])
                if not self.structure.reachable(u_node, v_node):
                    continue  # partitioned: the flow waits in custody, uncharged (LoadSpace.dag_flow_load)
                for a, b, _ in self.structure.route(u_node, v_node):
                    for medium, m_term in self.media_terms(a, b):
                        air = airtime_s(flow.n_bytes, self.scenario.radios[medium], self.scenario.link_loss(a, b)) * rate
                        add(send[(a, medium)], self.const_send, (a, medium), hosts_term + m_term, air)
                        add(recv[(b, medium)], self.const_recv, (b, medium), hosts_term + m_term, air)

    def _add_control_plane(self, add, send: dict, recv: dict) -> None:
        """The team's own messages on every link (`model.control_plane`): the same whatever runs
        where, priced on the medium the link gets (`LoadSpace._control_load` for a fixed network)."""
        spec = self.scenario.control_plane
        if not spec.enabled:
            return
        for (u, v), n_bytes in spec.directed_bytes(self.structure).items():
            loss = self.scenario.link_loss(u, v)
            for medium, m_term in self.media_terms(u, v):
                air = airtime_s(n_bytes, self.scenario.radios[medium], loss)
                add(send[(u, medium)], self.const_send, (u, medium), m_term, air)
                add(recv[(v, medium)], self.const_recv, (v, medium), m_term, air)

    def power(self, robot: str) -> tuple[dict[int, float], float]:
        """P_robot as (col -> coef, constant) watts."""
        platform = self.scenario.platform_of(robot)
        expr: dict[int, float] = {}
        const = platform.idle_w
        for col, u in self.cpu[robot].items():
            expr[col] = expr.get(col, 0.0) + (platform.busy_w - platform.idle_w) * u
        expr, const = dvfs_cpu_power(self, robot, expr, const)  # DVFS: the level's power instead
        for medium, radio in self.scenario.radios.items():
            key = (robot, medium)
            pres = self.present.get(key)
            if pres is None:
                continue
            if isinstance(pres, float):
                const += radio.sleep_w
            else:
                expr[pres] = expr.get(pres, 0.0) + radio.sleep_w
            for source, consts, active_w in ((self.send[key], self.const_send, radio.send_w),
                                             (self.recv[key], self.const_recv, radio.receive_w)):
                coef = active_w - radio.sleep_w
                for col, air in source.items():
                    expr[col] = expr.get(col, 0.0) + coef * air
                const += coef * consts[key]
        return expr, const

    def start_values(self, allocation: Mapping[str, str]) -> dict[int, float]:
        """The x columns of a plan (stage -> host): 1 at its host, 0 at the stage's others."""
        out = {}
        for (stage, host), col in self.x.items():
            if stage in allocation:
                out[col] = 1.0 if allocation[stage] == host else 0.0
        return out

    # ---- read back -----------------------------------------------------------------------------
    def decode(self, values) -> tuple[dict[str, str], Network]:
        allocation = {}
        for (stage, host), col in self.x.items():
            if values[col] > 0.5:
                allocation[stage] = host
        chosen = {}
        for (group, medium), col in self.y.items():
            if values[col] > 0.5:
                chosen[group] = medium
        def medium(group: str) -> str:
            media = self.group_media[group]
            return media[0] if len(media) == 1 else chosen[group]

        links = [Link(a=l.a, b=l.b, medium=medium(self.link_group[frozenset((l.a, l.b))]), group=l.group)
                 for l in self.structure.explicit]
        cliques = [Clique(nodes=c.nodes, medium=medium(self.clique_group[i]), group=c.group)
                   for i, c in enumerate(self.structure.cliques)]
        network = Network(self.structure.nodes, self.structure.basestation, links, self.structure.topology, cliques)
        return allocation, network


SPLIT_MEDIA_UP_TO = 16  # media combinations solved as separate, product-free MILPs
# Stage-host binaries per media choice beyond which the model is not built: 1,000 robots whose
# stages may each run on any of 1,001 nodes have 3 million, which take minutes of Python and
# gigabytes before HiGHS even starts (the own-robot-or-laptop fleet of that size has 6,000).
MAX_HOST_BINARIES = 1_000_000


def solve_milp(problem: Problem, *, time_limit_s: float | None = None, mip_rel_gap: float = 1e-9,
               refine: bool = True, start: Mapping[str, str] | None = None, reach_bound: bool = True,
               moves: bool = True) -> MilpResult:
    """Min-max lifetime placement; optionally a second pass to minimise total normalised drain.

    With few media combinations (a named topology has 4) one MILP per combination is much smaller
    than the joint model (no binary products) and each solve passes the best lifetime so far as
    an objective cut-off, so hopeless combinations are pruned at once. Otherwise the joint model
    chooses media itself.

    `start` (stage -> host, e.g. the plan in force) is handed to HiGHS as a first incumbent. On
    one fixed network it is first repaired where it fails (`autopower.planner.repair`): when the
    repair meets the per-robot bound it is returned as optimal without the whole MILP (its
    second pass then only reorders the repaired stages).

    `reach_bound`: before the whole MILP, look for a plan whose T *equals* the per-robot bound
    (`_reach_bound`): a feasibility MILP, often found in a second where the optimising MILP
    spends minutes proving the last fraction of a percent. `moves=False`: that search and its
    tie-break by HiGHS alone, without single-stage moves (`autopower.planner.moves`).
    """
    binaries = sum(len(hosts) for hosts in problem.hosts.values())
    if binaries > MAX_HOST_BINARIES:
        raise AutoPowerError(
            f"the placement MILP would need {binaries:,} stage-host binaries per media choice "
            f"({len(problem.hosts):,} stages on up to {max(map(len, problem.hosts.values())):,} hosts each; "
            f"the limit is {MAX_HOST_BINARIES:,}): give the stages fewer hosts (e.g. hosts = [robot, base station])")
    called = time.monotonic()
    warm = bool(start) and repair.repairable(problem)
    own = _own_bounds(problem) if warm or (reach_bound and repair.boundable(problem)) else None
    if warm:
        began = time.monotonic()
        repaired = _repair_start(problem, start, time_limit_s, mip_rel_gap, refine, own[0])
        if isinstance(repaired, MilpResult):
            return repaired
        start = repaired or start
        if time_limit_s is not None:  # the repair's time counts against the limit
            time_limit_s = max(1.0, time_limit_s - (time.monotonic() - began))

    if reach_bound and repair.boundable(problem):
        began = time.monotonic()
        reached = _reach_bound(problem, time_limit_s, mip_rel_gap, refine, own, start, called, moves)
        if reached is not None:
            return reached
        if time_limit_s is not None:
            time_limit_s = max(1.0, time_limit_s - (time.monotonic() - began))

    if not 1 < len(problem.networks) <= SPLIT_MEDIA_UP_TO:
        return _finish(problem, *_first_pass(problem, time_limit_s, mip_rel_gap, None, start), refine, time_limit_s)
    started = time.monotonic()
    best = None
    bounds = []
    runtime = 0.0
    status = "Infeasible"
    for network in problem.networks:
        left = None if time_limit_s is None else max(1.0, time_limit_s - (time.monotonic() - started))
        sub = dataclasses.replace(problem, networks=[network])
        cutoff = best[2].values[best[1]] if best else None
        built, t_col, sol = _first_pass(sub, left, mip_rel_gap, cutoff, start)
        runtime += sol.runtime_s
        if sol.has_solution:
            bounds.append(sol.dual_bound if sol.dual_bound is not None else sol.objective)
            if best is None or sol.objective < best[2].objective:
                best = (built, t_col, sol, sub)
        elif cutoff is not None and sol.status == "Objective bound":
            bounds.append(sol.dual_bound)  # its LP relaxation: within the gap of the incumbent
        elif cutoff is not None and ("Infeasible" in sol.status or "bound" in sol.status.lower()):
            bounds.append(cutoff)  # nothing here beats the incumbent: its bound is at least the cut-off
        elif "Infeasible" not in sol.status:
            status = sol.status
            bounds.append(0.0)  # unknown: no proof for this combination
    if best is None:
        return MilpResult(None, None, None, False, 1.0, status, runtime, 0, 0)
    built, t_col, sol, sub = best
    incumbent = sol.objective
    gap = max(0.0, (incumbent - min(bounds)) / incumbent) if incumbent > 0 else 0.0
    sol.optimal = sol.optimal and gap <= max(mip_rel_gap, 1e-6)
    sol.mip_gap = gap
    result = _finish(sub, built, t_col, sol, refine, time_limit_s)
    result.runtime_s += runtime - sol.runtime_s
    return result


def _own_bounds(problem: Problem) -> list[tuple[float, dict[str, float], dict[str, str]]]:
    """Per media choice: `repair.own_bound` (T, per robot) and the placement it assumes."""
    out = []
    for network in problem.networks:
        cheapest: dict[str, str] = {}
        out.append((*repair.own_bound(dataclasses.replace(problem, networks=[network]), cheapest), cheapest))
    return out


def _repair_start(problem: Problem, start: Mapping[str, str], time_limit_s, mip_rel_gap, refine, own):
    """The plan in force repaired (repair.neighbourhood): a MilpResult when the per-robot bound
    proves it optimal, else its allocation (a better start for the whole MILP) or None."""
    bound, per_robot, _ = own
    free = repair.neighbourhood(problem, start, per_robot, bound)
    stages = sum(len(c.stages) for c in problem.chains)
    if len(free) > max(repair.SMALL_NEIGHBOURHOOD, stages * repair.SMALL_SHARE):
        return None  # not a repair: the plan fails almost everywhere (or its T is far above the bound)
    sub = repair.restricted(problem, start, free)
    built, t_col, sol = _first_pass(sub, None if time_limit_s is None else max(1.0, time_limit_s / 4),
                                    mip_rel_gap, None, start, around_start=False)
    if not sol.has_solution:
        return None
    if sol.objective <= bound * (1 + mip_rel_gap) + 1e-12:
        sol.optimal, sol.dual_bound, sol.status = True, bound, "Optimal (repaired plan meets the per-robot bound)"
        sol.mip_gap = max(0.0, (sol.objective - bound) / sol.objective) if sol.objective > 0 else 0.0
        return _finish(sub, built, t_col, sol, refine, time_limit_s)
    return built.decode(sol.values)[0]


def _reach_bound(problem: Problem, time_limit_s, mip_rel_gap, refine, own=None,
                 start: Mapping[str, str] | None = None, called: float | None = None,
                 moves: bool = True) -> MilpResult | None:
    """A plan whose T equals the per-robot bound, proven optimal by it; None when none is found.

    No plan on any media choice has a T below that choice's `repair.own_bound`, so no plan at
    all has one below the smallest of them. A plan on that media choice reaching it is optimal:
    with T fixed there, the MILP is a pure feasibility problem (place every stage so that each
    robot's power stays within its energy's share, CPU and radios within their limits: a
    generalised assignment). First single-stage moves look for one (`moves.MoveSearch.reach`,
    from `start`, the plan in force, else from every chain where it costs its own robot least;
    at most `MOVES_LIMIT_S` of CPU and half the search's share of the time limit; warm, first
    with every stage pinned where the plan in force has it except those `repair.neighbourhood`
    frees, then all of them); if they find none, HiGHS is asked, and answers at its first
    feasible point instead of closing a bin-packing gap by branching (with a gap asked for, T is
    fixed that much above the bound). The plan is accepted when its evaluated T is within
    max(mip_rel_gap, 1e-9) of the bound (relative, as HiGHS's gap; the 1e-9: floating-point
    summation order); when the bound is not reachable (infeasible, or not found within a
    quarter of the time limit, 10 s without one) the caller runs the optimising MILP.

    The tie-break (least total drain at that T) is not part of the proof. Where moves apply it is
    `MoveSearch.least_drain` (no row above its limit with T at the found plan's own, so its
    lifetime stays; checked again by the evaluator), run until no move lowers the drain; otherwise a second HiGHS pass with as long
    as the search took. `untied_allocation` is the plan before it.
    """
    started = time.monotonic()
    own = own or _own_bounds(problem)
    cheapest = [c for _, _, c in own]  # per media choice: every chain where it costs its robot least
    bounds = [(b, i) for i, (b, _, _) in enumerate(own)]
    lowest = min(bounds)[0]
    tolerance = max(mip_rel_gap, REACH_TOLERANCE)
    # with a gap asked for, any plan within it of the bound will do (an easier packing)
    t_at = lowest * (1 + mip_rel_gap) if mip_rel_gap > REACH_TOLERANCE else lowest

    def gap_of(result: MilpResult) -> float:
        if result.lifetime_s is None:  # HiGHS's feasibility tolerance passed a limit the evaluator does not
            return 1.0
        reached = max(problem.energies_j[r] for r in result.network.nodes if r != result.network.basestation) / result.lifetime_s
        return max(0.0, (reached - lowest) / reached)

    for bound, i in sorted(bounds):
        if bound > lowest:
            break  # a choice whose own bound is higher cannot reach the lowest
        share = REACH_UNLIMITED_S if time_limit_s is None else time_limit_s * REACH_SHARE
        sub = dataclasses.replace(problem, networks=[problem.networks[i]])
        sol = None
        if moves and start and len(problem.networks) == 1:
            # warm: first move only the stages the plan in force gets wrong (a model of those)
            free = repair.neighbourhood(sub, start, own[i][1], own[i][0])
            if len(free) < len(sub.hosts):
                near = repair.restricted(sub, start, free)
                built, t_col = _placement_model(near, t_at)
                if MoveSearch.applicable(built):
                    search = MoveSearch(built, t_col, t_at)
                    choice = search.choice_of(start, cheapest[i])
                    left = max(0.0, share - (time.monotonic() - started))
                    if search.reach(choice, time.monotonic() + left / 4, cpu_s=MOVES_LIMIT_S / 2):
                        sol, sub = _moved(built, search, choice, t_col, t_at, NEAR_STATUS), near
        if sol is None:
            built, t_col = _placement_model(sub, t_at)
            if _relaxation_infeasible(built):
                continue  # no plan on this media choice reaches the bound: no search for one
            search = MoveSearch(built, t_col, t_at) if moves and MoveSearch.applicable(built) else None
        if search is not None and sol is None:
            choice = search.choice_of(start or cheapest[i], cheapest[i])
            left = max(0.0, share - (time.monotonic() - started))
            if search.reach(choice, time.monotonic() + left / 2, cpu_s=MOVES_LIMIT_S):
                sol = _moved(built, search, choice, t_col, t_at)
        if sol is None:
            left = max(0.1, share - (time.monotonic() - started))
            sol = built.lp.solve(time_limit_s=left, mip_rel_gap=mip_rel_gap)
        if not sol.has_solution:
            continue
        found = _finish(sub, built, t_col, sol, False, None)  # the plan as found, evaluated
        if gap_of(found) > tolerance:
            continue
        proven_s = time.monotonic() - (called or started)  # (the bounds and a failed repair included)
        sol.optimal = True  # (for the tie-break pass)
        if not refine:
            result = found
        elif search is not None:
            choice = search.choice_of(found.allocation, found.allocation)
            # T at the plan's own (below t_at when a gap was asked for): the tie-break keeps its lifetime
            search.set_t(min(t_at, max(problem.energies_j[r] for r in built.robots) / found.lifetime_s))
            search.least_drain(choice, time.monotonic() + max(0.1, proven_s))
            result = _finish(sub, built, t_col, _moved(built, search, choice, t_col, t_at), False, None)
        else:
            result = _finish(sub, built, t_col, sol, True, max(0.1, proven_s))
        if gap_of(result) > gap_of(found) or not result.lifetime_s >= found.lifetime_s * (1 - 1e-12):
            result = found  # the tie-break may trade the last 1e-9 of T for less drain: never the proven lifetime
        gap = gap_of(result)
        result.optimal, result.mip_gap, result.proven_s = True, gap, proven_s
        result.untied_allocation = found.allocation
        result.found_by = {MOVES_STATUS: "moves", NEAR_STATUS: "moves near the plan in force"}.get(sol.status, "highs")
        result.status = ("Optimal (meets the per-robot bound)" if gap <= REACH_TOLERANCE
                         else f"Optimal (within {gap:.3%} of the per-robot bound)")
        result.runtime_s = time.monotonic() - (called or started)
        return result
    return None


def _relaxation_infeasible(model: PlacementModel) -> bool:
    """True when the model's LP relaxation (T fixed at the bound) has no point: then no plan
    reaches the bound, and the move search would spend its whole budget looking for one (a
    30-robot fleet whose laptop CPU holds 22 of its 30 Blob finders: 1 s of moves, where the
    relaxation says so in 0.03 s). With T fixed the objective is zero, so HiGHS's "infeasible or
    unbounded" is infeasible; an LP that stops for any other reason proves nothing."""
    status = model.lp.solve_relaxation(time_limit_s=REACH_RELAXATION_S).status
    return status == "Infeasible" or (status == "Primal infeasible or unbounded" and not any(model.lp.cost))


def _moved(model: PlacementModel, search: MoveSearch, choice, t_col: int, t_at: float,
           status: str | None = None) -> Solution:
    """A plan the moves found, as the solver's answer would be."""
    return Solution(status=status or MOVES_STATUS, optimal=True, has_solution=True,
                    values=search.values(choice, len(model.lp.lower), t_col, t_at), duals=None,
                    objective=t_at, mip_gap=0.0, dual_bound=t_at, runtime_s=0.0)


MOVES_STATUS = "Feasible (single-stage moves)"
NEAR_STATUS = "Feasible (single-stage moves of the stages the plan in force gets wrong)"
# The move search's budget before HiGHS is asked, in CPU seconds of its thread (a loaded machine
# must not make it give up early: it reached the any-host 100-robot fleet's bound in 0.15-0.25 s)
MOVES_LIMIT_S = 1.0
REACH_SHARE = 0.25  # of the time limit, for the search of a plan that reaches the per-robot bound
REACH_UNLIMITED_S = 10.0  # that search's limit when the MILP has none (a packing may be slow to prove infeasible)
REACH_RELAXATION_S = 5.0  # the LP relaxation that rules the bound out (0.03 s at 30 robots)
REACH_TOLERANCE = 1e-9  # relative: the same T summed in another order


def _placement_model(problem: Problem, t_at: float | None = None) -> tuple[PlacementModel, int]:
    """The min-max model and its T column (fixed at `t_at` when given)."""
    model = PlacementModel(problem)
    lp = model.lp
    e_ref = max(problem.energies_j[r] for r in model.robots)
    t_col = lp.var(0.0, INF, cost=1.0) if t_at is None else lp.var(t_at, t_at)
    model.power_rows = {}
    for robot in model.robots:
        expr, const = model.power(robot)
        # P_i - (E_i/E_ref) T <= 0  ->  expr - k T <= -const
        model.power_rows[robot] = expr
        lp.row({**expr, t_col: -problem.energies_j[robot] / e_ref}, -INF, -const)
    return model, t_col


def _first_pass(problem: Problem, time_limit_s, mip_rel_gap, cutoff, start=None, around_start=True,
                t_at: float | None = None):
    """The min-max MILP's first pass; with `t_at`, T is fixed there and the MILP only looks
    for a feasible plan (`_reach_bound`)."""
    model, t_col = _placement_model(problem, t_at)
    lp = model.lp
    relaxed = None
    if cutoff is not None or (start and around_start):
        relaxed = lp.solve_relaxation(time_limit_s=time_limit_s)
        if not (relaxed.has_solution and relaxed.optimal):
            relaxed = None
    if cutoff is not None and relaxed and relaxed.objective >= cutoff * (1 - mip_rel_gap):
        # Another media choice already has an incumbent. If this one's LP relaxation cannot beat
        # it by more than the gap asked for, its MILP is not worth a search: HiGHS would spend
        # its whole time limit raising a bound that only needs to be within the gap.
        relaxed.status, relaxed.has_solution, relaxed.values = "Objective bound", False, None
        return model, t_col, relaxed
    first = model.start_values(start) if start else None
    if start and around_start and relaxed:
        began = time.monotonic()
        repaired = _repair(model, relaxed, start, None if time_limit_s is None else max(1.0, time_limit_s / 4),
                           mip_rel_gap)
        if time_limit_s is not None:
            time_limit_s = max(1.0, time_limit_s - (time.monotonic() - began))
        if repaired is not None and (cutoff is None or repaired.objective < cutoff):
            if repaired.objective <= relaxed.objective * (1 + mip_rel_gap) + 1e-12:
                # the LP relaxation of the whole problem proves the repaired plan optimal
                repaired.mip_gap = max(0.0, (repaired.objective - relaxed.objective) / repaired.objective)
                repaired.dual_bound, repaired.optimal, repaired.status = (relaxed.objective, True,
                                                                          "Optimal (meets the LP relaxation)")
                return model, t_col, repaired
            first = dict(enumerate(repaired.values))
    sol = lp.solve(time_limit_s=time_limit_s, mip_rel_gap=mip_rel_gap, objective_cutoff=cutoff, start=first)
    return model, t_col, sol


def _repair(model: PlacementModel, relaxed, start: Mapping[str, str], time_limit_s, mip_rel_gap):
    """The best plan that keeps every stage of `start` (the plan in force) where the LP
    relaxation keeps it too, and searches only the others (relaxation-induced neighbourhood
    search): after one link changes, a MILP over a handful of stages instead of all of them.
    None when that neighbourhood has no feasible plan."""
    lp = model.lp
    hosts = model.problem.hosts
    lower, upper = list(lp.lower), list(lp.upper)
    for stage, host in start.items():
        col = model.x.get((stage, host))
        if col is not None and relaxed.values[col] > 1 - 1e-6:
            for other in hosts[stage]:
                c = model.x[(stage, other)]
                if other == host:
                    lp.lower[c] = 1.0
                else:
                    lp.upper[c] = 0.0
    try:  # the plan in force is in the neighbourhood: nothing worse than it comes back
        sol = lp.solve(time_limit_s=time_limit_s, mip_rel_gap=mip_rel_gap, start=model.start_values(start))
    finally:
        lp.lower, lp.upper = lower, upper
    return sol if sol.has_solution else None


def _finish(problem: Problem, model: PlacementModel, t_col: int, sol, refine: bool, time_limit_s) -> MilpResult:
    from autopower.model.energy import evaluate

    lp = model.lp
    columns, rows = len(lp.lower), len(lp.row_lower)
    if not sol.has_solution:
        return MilpResult(None, None, None, False, 1.0, sol.status, sol.runtime_s, columns, rows)
    runtime = sol.runtime_s
    best = sol
    if refine and sol.optimal:
        t_star = sol.values[t_col]
        lp.cost[t_col] = 0.0
        lp.upper[t_col] = t_star * (1 + 1e-9) + 1e-12
        for robot, expr in model.power_rows.items():
            for col, coef in expr.items():
                lp.cost[col] += coef / problem.energies_j[robot]
        # the first pass's optimum is feasible here: start from it rather than from nothing
        second = lp.solve(time_limit_s=time_limit_s, mip_rel_gap=1e-6, start=dict(enumerate(sol.values)))
        runtime += second.runtime_s
        if second.has_solution:
            best = second
    allocation, network = model.decode(best.values)
    placed = {c.name for c in problem.chains if all(s.name in allocation for s in c.stages)}  # variants: the chosen
    ev = evaluate(problem.scenario, network, allocation, accounting=problem.accounting,
                  energies_j=problem.energies_j,
                  disabled_chains=frozenset(c.name for c in problem.scenario.chains) - placed)
    return MilpResult(allocation, network, ev.lifetime_s, sol.optimal, sol.mip_gap, sol.status, runtime, columns, rows)
