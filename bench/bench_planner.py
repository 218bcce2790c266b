"""Planner benchmark: MILP time and lifetime vs a greedy baseline measured in the same run.

Run: ./run bench  (or .venv/bin/python bench/bench_planner.py [--big]). Not a timed test: the
figures are printed, with ratios, for docs/performance.md.

Cases: the paper's scenarios; sparse fleets (chains spread over the robots at random, many robots
idle); loaded fleets where every robot runs three chains of its own (localisation, blob finder,
mapper), with any node a possible host or only the robot itself or the laptop; and a replan after
one link changes medium in the loaded 100-robot fleet, cold vs warm-started from the plan in force
(the warm replan repairs that plan and proves it by the per-robot bound, `planner/repair.py`).
--big adds the 1,000-robot / 3,000-component loaded fleets: own robot or laptop (goal: within 1 %
of a proven bound in 60 s, building the model included) and any host (refused: 3 million
stage-host binaries; the refusal and its reason are printed). --loaded runs the loaded fleets only.

--previous also runs every MILP case and replan two earlier ways in the same run: without moves
(`solve_milp(moves=False)`: HiGHS alone looks for the plan at the per-robot bound, and a second
HiGHS pass is the tie-break) and without the search for that plan (`reach_bound=False`: the
optimising MILP only), and replans the any-host fleet from the plan the latter leaves in force
too. "proven at" is when a plan reaching the bound was found, before the tie-break (least total
drain); "tie-break" states what it bought: the team's joules spent until the first robot
depletes, before and after (same lifetime). The load average is printed at the start and end.
"""

import os
import sys
import time

import results as bench_results

from autopower.errors import AutoPowerError
from autopower.model.loading import load_scenario
from autopower.model.network import Link, Network
from autopower.planner import PlanRequest
from autopower.planner.exhaustive import exhaustive
from autopower.planner.greedy import greedy
from autopower.planner.milp import solve_milp
from autopower.planner.problem import make_problem
from autopower.simulation.synthetic import fleet_scenario, loaded_fleet_scenario

CPU = {}  # id(result) -> CPU seconds of this process (HiGHS's threads included) that made it
FIGURES: list[dict] = []  # what --json-out writes
LIFETIME, TIME, REPLAN = "Lifetime of the plan", "Time to plan", "Replan after one link changes medium"


def timed(fn):
    """(result, wall seconds); the CPU seconds go to CPU (on a loaded machine wall >> CPU)."""
    t, c = time.perf_counter(), time.process_time()
    out = fn()
    CPU[id(out)] = time.process_time() - c
    return out, time.perf_counter() - t


def cpu(result) -> str:
    return f"{CPU.get(id(result), float('nan')):.2f} CPU s"


PREVIOUS = "--previous" in sys.argv


def proof(m) -> str:
    return f"proven at {m.proven_s:.2f} s (found by {m.found_by})" if m.proven_s is not None else ""


def team_joules(problem, m, allocation) -> tuple[float, float]:
    """(joules the whole team spends until its first robot depletes, that lifetime)."""
    from autopower.model.energy import evaluate

    ev = evaluate(problem.scenario, m.network, allocation, accounting=problem.accounting, energies_j=problem.energies_j)
    return sum(p.total_w for p in ev.robots.values()) * ev.lifetime_s, ev.lifetime_s


def tie_break(problem, m) -> str:
    if m.untied_allocation is None:
        return ""
    (before, life_before), (after, life_after) = team_joules(problem, m, m.untied_allocation), team_joules(problem, m, m.allocation)
    return (f"tie-break: team {before / 1e3:,.1f} kJ -> {after / 1e3:,.1f} kJ ({(after - before) / 1e3:+,.1f} kJ, "
            f"{after / before - 1:+.3%}) at lifetime {life_before:,.3f} -> {life_after:,.3f} s")


def row(name, problem, build_s, limit, gap, run_greedy=True):
    g, g_time = timed(lambda: greedy(problem)) if run_greedy else (None, float("nan"))
    m, m_time = timed(lambda: solve_milp(problem, time_limit_s=limit, mip_rel_gap=gap))
    previous = None
    if PREVIOUS:
        no_moves, n_time = timed(lambda: solve_milp(problem, time_limit_s=limit, mip_rel_gap=gap, moves=False))
        previous, p_time = timed(lambda: solve_milp(problem, time_limit_s=limit, mip_rel_gap=gap, reach_bound=False))
    ex_time = ""
    if problem.combinations() <= 200_000:
        ex, t = timed(lambda: exhaustive(problem))
        assert abs(ex[0].lifetime_s - m.lifetime_s) <= 1e-6 * m.lifetime_s, (ex[0].lifetime_s, m.lifetime_s)
        ex_time = f"{t:.3f}"
    ratio = m.lifetime_s / g[2] if g else float("nan")
    print(f"{name:40} {build_s:8.2f} {g_time:9.3f} {m_time:8.2f} {ratio:17.4f} {str(m.optimal):>7} {m.mip_gap:7.3%} {ex_time:>13}",
          flush=True)
    print(f"{'':40} {cpu(m)}; {proof(m)}; {tie_break(problem, m)}", flush=True)
    state = f"{'proven optimal' if m.optimal else 'not proven'}, gap {m.mip_gap:.3%}"
    if g:
        FIGURES.append(bench_results.figure(name, m.lifetime_s, "s", "greedy", g[2], group=LIFETIME, detail=state,
                                            note="greedy list scheduling on the same problem, same run"))
        FIGURES.append(bench_results.figure(f"{name}: MILP", m_time, "s", "greedy", g_time, group=TIME,
                                            detail=f"{cpu(m)}; build {build_s:.2f} s",
                                            note="greedy list scheduling on the same problem, same run (wall s)"))
    if ex_time:
        FIGURES.append(bench_results.figure(f"{name}: exhaustive search", float(ex_time), "s", "greedy", g_time,
                                            group=TIME, detail="the exact optimum, equal to the MILP's",
                                            note="greedy list scheduling on the same problem, same run (wall s)"))
    if previous is not None:
        print(f"{'  without moves (moves=False)':40} {'':8} {'':9} {n_time:8.2f} {no_moves.lifetime_s / m.lifetime_s:17.4f} "
              f"{str(no_moves.optimal):>7} {no_moves.mip_gap:7.3%}   (lifetime / this build's; time ratio {n_time / m_time:.1f}x, {cpu(no_moves)}) "
              f"{proof(no_moves)}; {tie_break(problem, no_moves)}", flush=True)
        print(f"{'  previous way (reach_bound=False)':40} {'':8} {'':9} {p_time:8.2f} {previous.lifetime_s / m.lifetime_s:17.4f} "
              f"{str(previous.optimal):>7} {previous.mip_gap:7.3%}   (lifetime / this build's; time ratio {p_time / m_time:.1f}x, {cpu(previous)})",
              flush=True)
    return m, previous


def replan_after_link_change(scenario, current, label: str = "") -> None:
    """One robot's laptop link switches medium; replan on that network, cold and from the plan in force."""
    robot = "r7"
    media = scenario.network_spec.laptop_robot_media
    links = []
    for link in current.network.explicit:  # the robot-robot links are one clique, unchanged
        if {link.a, link.b} == {robot, scenario.basestation}:
            other = next(m for m in media if m != link.medium)
            link = Link(a=link.a, b=link.b, medium=other, group=link.group)
        links.append(link)
    changed = Network(current.network.nodes, current.network.basestation, links, current.network.topology,
                      current.network.cliques)
    problem = make_problem(PlanRequest(scenario=scenario, network=changed))
    ways = [("", {})] + ([(" [without moves]", {"moves": False}), (" [previous way]", {"reach_bound": False})]
                         if PREVIOUS else [])
    for way, kwargs in ways:
        cold, cold_s = timed(lambda: solve_milp(problem, time_limit_s=60, **kwargs))  # noqa: B023 (called in this iteration)
        warm, warm_s = timed(lambda: solve_milp(problem, time_limit_s=60, start=current.allocation, **kwargs))  # noqa: B023 (called in this iteration)
        if cold.optimal and warm.optimal:
            assert abs(cold.lifetime_s - warm.lifetime_s) <= 1e-6 * cold.lifetime_s, (cold.lifetime_s, warm.lifetime_s)
        FIGURES.append(bench_results.figure(
            f"{scenario.name}{label}{way}: warm start", warm_s, "s", "cold start", cold_s, group=REPLAN,
            detail=f"{'proven optimal' if warm.optimal else 'not proven'}, gap {warm.mip_gap:.3%}; {cpu(warm)}",
            note="the same replan with no plan in force to start from (wall s)"))
        print(f"replan after {robot}-laptop link change ({scenario.name}{label}){way}: cold {cold_s:.2f} s ({cpu(cold)}), "
              f"warm start {warm_s:.2f} s ({cpu(warm)}) "
              f"(warm/cold {warm_s / cold_s:.2f}); proven optimal: cold {cold.optimal}, warm {warm.optimal}; "
              f"gap cold {cold.mip_gap:.3%}, warm {warm.mip_gap:.3%}; lifetime warm {warm.lifetime_s:.1f} s; "
              f"warm: {warm.status} {proof(warm)}; cold: {cold.status} {proof(cold)}", flush=True)


def any_host_thousand() -> None:
    """The 1,000-robot fleet with any node a possible host: what the planner does with it."""
    scenario = loaded_fleet_scenario(1000, 3, hosts="any")
    problem, build_s = timed(lambda: make_problem(PlanRequest(scenario=scenario)))
    t = time.perf_counter()
    try:
        m = solve_milp(problem, time_limit_s=60, mip_rel_gap=0.01)
        print(f"{'1000 / 3000 loaded, any host':40} {build_s:8.2f} {'-':>9} {time.perf_counter() - t:8.2f} "
              f"{'-':>17} {str(m.optimal):>7} {m.mip_gap:7.3%}", flush=True)
    except AutoPowerError as e:
        print(f"1000 / 3000 loaded, any host: refused after {build_s + time.perf_counter() - t:.2f} s: {e}", flush=True)


def main() -> None:
    json_out = bench_results.pop_json_out()
    big = "--big" in sys.argv
    cases = [] if "--loaded" in sys.argv else [
        ("paper-fig7", load_scenario("paper-fig7"), None, 1e-9),
        ("paper-fig8", load_scenario("paper-fig8"), None, 1e-9),
        ("30 robots / 90 comps", fleet_scenario(30, 90, seed=1), None, 1e-9),
        ("30 robots / 90 comps, physical", fleet_scenario(30, 90, seed=2, accounting="physical"), None, 1e-9),
        ("100 robots / 300 comps (sparse)", fleet_scenario(100, 300, seed=3), 600, 0.01),
    ]
    cases += [
        ("100 / 300 loaded, own robot or laptop", loaded_fleet_scenario(100, 3, hosts="own"), 60, 1e-9),
        ("100 / 300 loaded, any host", loaded_fleet_scenario(100, 3, hosts="any"), 60, 1e-9),
    ]
    if big:
        cases.append(("1000 / 3000 loaded, own robot or laptop", loaded_fleet_scenario(1000, 3, hosts="own"), 60, 0.01))
    print(f"load average at the start: {os.getloadavg()}", flush=True)
    print(f"{'case':40} {'build s':>8} {'greedy s':>9} {'MILP s':>8} {'MILP/greedy life':>17} {'proven':>7} {'gap':>7} {'exhaustive s':>13}")
    results = {}
    for name, scenario, limit, gap in cases:
        problem, build_s = timed(lambda: make_problem(PlanRequest(scenario=scenario)))  # noqa: B023 (called in this iteration)
        results[name] = (scenario, row(name, problem, build_s, limit, gap))
    own = results["100 / 300 loaded, own robot or laptop"]
    replan_after_link_change(own[0], own[1][0])
    any_host, (reached, previous) = results["100 / 300 loaded, any host"]
    replan_after_link_change(any_host, reached)
    if previous is not None:  # the plan the 60 s MILP left in force (GSM + Bluetooth, 0.6 % short of the bound)
        replan_after_link_change(any_host, previous, ", plan in force made the previous way")
    # the same from the plan a 1 % gap gives the previous way (another plan in force: all on the laptop)
    in_force = solve_milp(make_problem(PlanRequest(scenario=any_host)), time_limit_s=60, mip_rel_gap=0.01,
                          reach_bound=False)
    replan_after_link_change(any_host, in_force, ", plan in force made at a 1 % gap")
    if big:
        any_host_thousand()
    print(f"load average at the end: {os.getloadavg()}", flush=True)
    groups = {LIFETIME: {"what": "The MILP's plan against greedy list scheduling on the same problem.",
                         "value": "MILP lifetime", "baseline_value": "greedy lifetime", "detail": "MILP"},
              TIME: {"what": "Wall seconds to plan (the CPU seconds, HiGHS's threads included, beside them).",
                     "value": "time", "baseline_value": "greedy's time", "detail": "CPU; building the model"},
              REPLAN: {"what": "One robot's laptop link switches medium; the replan from the plan in force "
                               "against the same replan from nothing.",
                       "value": "warm start", "baseline_value": "cold start", "detail": "warm start's result"}}
    bench_results.write_result("planner", {"big": big, "loaded_only": "--loaded" in sys.argv, "previous": PREVIOUS},
                               FIGURES, json_out, what=__doc__.splitlines()[0], groups=groups)


if __name__ == "__main__":
    main()
