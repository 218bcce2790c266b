"""Planner benchmark: MILP time and lifetime vs a greedy baseline measured in the same run.

Run: ./run bench  (or .venv/bin/python bench/bench_planner.py). Not a timed test: the figures
are printed, with ratios, for the README and the notes.
"""

import time

from autopower.model.loading import load_scenario
from autopower.planner import PlanRequest
from autopower.planner.exhaustive import exhaustive
from autopower.planner.greedy import greedy
from autopower.planner.milp import solve_milp
from autopower.planner.problem import make_problem
from autopower.simulation.synthetic import fleet_scenario


def timed(fn):
    t = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t


def main() -> None:
    cases = [
        ("paper-fig7", load_scenario("paper-fig7"), None, 1e-9),
        ("paper-fig8", load_scenario("paper-fig8"), None, 1e-9),
        ("30 robots / 90 comps", fleet_scenario(30, 90, seed=1), None, 1e-9),
        ("30 robots / 90 comps, physical", fleet_scenario(30, 90, seed=2, accounting="physical"), None, 1e-9),
        ("100 robots / 300 comps", fleet_scenario(100, 300, seed=3), 600, 0.01),
    ]
    print(f"{'case':34} {'greedy s':>9} {'MILP s':>8} {'MILP/greedy life':>17} {'proven':>7} {'gap':>7} {'exhaustive s':>13}")
    for name, scenario, limit, gap in cases:
        problem = make_problem(PlanRequest(scenario=scenario))
        g, g_time = timed(lambda: greedy(problem))
        m, m_time = timed(lambda: solve_milp(problem, time_limit_s=limit, mip_rel_gap=gap))
        ex_time = ""
        if problem.combinations() <= 200_000:
            ex, t = timed(lambda: exhaustive(problem))
            assert abs(ex[0].lifetime_s - m.lifetime_s) <= 1e-6 * m.lifetime_s, (ex[0].lifetime_s, m.lifetime_s)
            ex_time = f"{t:.3f}"
        ratio = m.lifetime_s / g[2] if g else float("inf")
        print(f"{name:34} {g_time:9.3f} {m_time:8.2f} {ratio:17.4f} {str(m.optimal):>7} {m.mip_gap:7.2%} {ex_time:>13}")


if __name__ == "__main__":
    main()
