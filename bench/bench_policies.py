"""Reallocation policies vs the time-sharing upper bound, and simulator speed.

    .venv/bin/python bench/bench_policies.py [--quick]

Prints (1) every policy's lifetime as a fraction of the planner's time-sharing bound on the
paper's scenarios (Fig. 7 and Fig. 8 energies, both accountings, both topologies) and on random
scenarios, (2) each policy against static under the shipped event files and random event
sequences, (3) simulator speed in simulated hours per wall second, with static as the baseline
measured in the same run. Not a timed test: figures for docs/results.md and docs/performance.md.
"""

from __future__ import annotations

import statistics
import sys
import time

import results

from autopower.errors import InfeasibleError
from autopower.model.loading import load_scenario
from autopower.model.mission_events import load_events, random_events
from autopower.policies import POLICY_NAMES
from autopower.simulation.simulator import simulate, time_sharing_reference
from autopower.simulation.synthetic import random_scenario

FIGURES: list[dict] = []  # what --json-out writes
PAPER, RANDOM, EVENTS, SPEED = ("Paper scenarios", "Random scenarios, the worst case of each set",
                                "Under events", "Simulator speed")
STATIC = ("static optimum", "the best fixed plan for the whole mission (the planner's optimum), simulated with no "
                            "events")
BOUND = ("time-sharing bound", "the planner's upper bound: the best schedule of plans switched during the mission, "
                               "migration free")
GROUPS = {
    PAPER: {"what": "Each policy's simulated lifetime on the paper's scenarios (both accountings, both topologies), "
                    "against the best fixed plan and against the time-sharing upper bound.",
            "value": "simulated lifetime", "baseline_value": "static optimum (best fixed plan)",
            "ratio": "/ static", "also": ["time-sharing bound (upper bound)"], "also_ratio": ["/ bound"],
            "detail": "moves"},
    RANDOM: {"what": "Random scenarios, each set's worst case for each policy against that case's time-sharing "
                     "bound; the detail gives the mean over the set.",
             "value": "simulated lifetime", "baseline_value": "time-sharing bound (upper bound)", "ratio": "/ bound",
             "detail": "over the set"},
    EVENTS: {"what": "Each policy under the shipped event files and random event sequences, against the static "
                     "policy under the same events.",
             "value": "simulated lifetime", "baseline_value": "static policy, same events", "ratio": "/ static"},
    SPEED: {"what": "Simulated hours per wall second of each policy, against the static policy on the same case.",
            "value": "simulated hours per wall second", "baseline_value": "static policy", "ratio": "/ static"},
}


def paper_table() -> list[float]:
    print("## Paper scenarios: lifetime / time-sharing bound")
    print(f"{'scenario':11} {'accounting':10} {'topology':16} {'bound s':>10} {'static gap':>10} "
          + " ".join(f"{p:>10}" for p in POLICY_NAMES) + f" {'moves':>6} {'move J':>7}")
    best = []
    for name in ("paper-fig7", "paper-fig8"):
        s = load_scenario(name)
        for accounting in ("paper", "physical"):
            for topology in ("fully-connected", "relay"):
                bound, static_plan = time_sharing_reference(s, topology=topology, accounting=accounting)
                runs = {p: simulate(s, policy=p, topology=topology, accounting=accounting) for p in POLICY_NAMES}
                ratios = {p: r.lifetime_s / bound.lifetime_s for p, r in runs.items()}
                best.append(max(ratios.values()))
                rb = runs["rebalance"]
                for p, r in runs.items():
                    FIGURES.append(results.figure(
                        f"{name}, {accounting}, {topology}: {p}", r.lifetime_s, "s", STATIC[0],
                        static_plan.lifetime_s, note=STATIC[1], group=PAPER,
                        also=[(BOUND[0], bound.lifetime_s, BOUND[1])],
                        detail=f"{len(r.migrations)} ({r.migration_energy_j:.2f} J)" if r.migrations else ""))
                print(f"{name:11} {accounting:10} {topology:16} {bound.lifetime_s:10.1f} "
                      f"{bound.lifetime_s / static_plan.lifetime_s - 1:+10.2%} "
                      + " ".join(f"{ratios[p]:10.4%}" for p in POLICY_NAMES)
                      + f" {len(rb.migrations):6d} {rb.migration_energy_j:7.2f}")
    return best


def random_table(sizes, seeds) -> None:
    print("\n## Random scenarios: lifetime / time-sharing bound (min / mean over the set)")
    print(f"{'robots x chains':16} {'cases':>5} {'with gain>0.1%':>14} {'max gain':>9} "
          + " ".join(f"{p + ' min':>14} {p + ' mean':>15}" for p in POLICY_NAMES) + f" {'wall s':>7}")
    for robots, chains in sizes:
        ratios = {p: [] for p in POLICY_NAMES}
        worst: dict[str, tuple[float, float, float, int]] = {}  # policy -> (ratio, lifetime, bound, seed)
        gains = []
        started = time.perf_counter()
        for seed in seeds:
            topology = ("fully-connected", "relay")[seed % 2]
            accounting = ("paper", "physical")[(seed // 2) % 2]
            s = random_scenario(seed, robots, chains, topology=topology, accounting=accounting)
            try:
                bound, best = time_sharing_reference(s)
            except InfeasibleError:
                continue
            gains.append(bound.lifetime_s / best.lifetime_s - 1)
            for p in POLICY_NAMES:
                life = simulate(s, policy=p).lifetime_s
                ratios[p].append(life / bound.lifetime_s)
                if p not in worst or ratios[p][-1] < worst[p][0]:
                    worst[p] = (ratios[p][-1], life, bound.lifetime_s, seed)
        wall = time.perf_counter() - started
        for p, (_r, life, bound_s, seed) in worst.items():
            FIGURES.append(results.figure(
                f"{robots} robots x {chains} chains, {len(gains)} cases: {p} (worst: seed {seed})", life, "s",
                BOUND[0], bound_s, note=BOUND[1], group=RANDOM,
                detail=f"mean {statistics.mean(ratios[p]):.4f} of the bound"))
        print(f"{f'{robots} x {chains}':16} {len(gains):5d} {sum(g > 1e-3 for g in gains):14d} {max(gains):+9.2%} "
              + " ".join(f"{min(ratios[p]):14.4%} {statistics.mean(ratios[p]):15.4%}" for p in POLICY_NAMES)
              + f" {wall:7.1f}")


def events_table(random_runs: int) -> None:
    print("\n## Events: lifetime / static's lifetime")
    fig7 = load_scenario("paper-fig7")
    print(f"{'events':28} " + " ".join(f"{p:>10}" for p in POLICY_NAMES) + f" {'migr. (rebalance)':>18}")
    for name, topology in (("paper-vc-fault", None), ("cameras-off", "relay"), ("link-cuts", None)):
        script = load_events(name, fig7, topology=topology)
        runs = {p: simulate(fig7, script, policy=p, topology=topology) for p in POLICY_NAMES}
        static = runs["static"].lifetime_s
        for p, r in runs.items():
            if p != "static":
                FIGURES.append(results.figure(f"{name}{' (relay)' if topology else ''}: {p}", r.lifetime_s, "s",
                                              "static", static, note="the static policy under the same events",
                                              group=EVENTS))
        print(f"{name + (' (relay)' if topology else ''):28} "
              + " ".join(f"{runs[p].lifetime_s / static:10.4f}" for p in POLICY_NAMES)
              + f" {len(runs['rebalance'].migrations):18d}")
    # random event sequences: how often does knowing better now cost later?
    ratios = {p: [] for p in POLICY_NAMES}
    worst: dict[str, tuple[float, float, float, int]] = {}  # policy -> (ratio, lifetime, static's, seed)
    for seed in range(random_runs):
        topology = ("fully-connected", "relay")[seed % 2]
        s = random_scenario(seed, 3, 4, topology=topology, accounting=("paper", "physical")[(seed // 2) % 2])
        script = random_events(s, seed, 4, horizon_s=20_000, topology=topology)
        try:
            runs = {p: simulate(s, script, policy=p, topology=topology) for p in POLICY_NAMES}
        except InfeasibleError:
            continue
        for p in POLICY_NAMES:
            ratios[p].append(runs[p].lifetime_s / runs["static"].lifetime_s)
            if p not in worst or ratios[p][-1] < worst[p][0]:
                worst[p] = (ratios[p][-1], runs[p].lifetime_s, runs["static"].lifetime_s, seed)
    n = len(ratios["static"])
    for p, (_r, life, static, seed) in worst.items():
        if p != "static":
            FIGURES.append(results.figure(
                f"random events ({n} runs): {p}, worst run (seed {seed})", life, "s", "static", static,
                note="the static policy under the same events", group=EVENTS,
                detail=f"mean {statistics.mean(ratios[p]):.4f} of static; "
                       f"{sum(r >= 1 - 1e-9 for r in ratios[p])} of {n} runs at least static's"))
    print(f"{f'random events ({n} runs): min':28} " + " ".join(f"{min(ratios[p]):10.4f}" for p in POLICY_NAMES))
    print(f"{'  mean':28} " + " ".join(f"{statistics.mean(ratios[p]):10.4f}" for p in POLICY_NAMES))
    print(f"{'  runs >= static':28} " + " ".join(f"{sum(r >= 1 - 1e-9 for r in ratios[p]):10d}" for p in POLICY_NAMES))


def speed_table(repeats: int) -> None:
    print("\n## Simulator speed: simulated hours per wall second (static = 1.00x, same run)")
    fig7 = load_scenario("paper-fig7")
    busy = random_events(fig7, 1, 60, horizon_s=30_000,
                         kinds=("link-cut", "link-heal", "radio-fault", "radio-repair", "energy-offset"))
    cases = [("fig7 relay, no events", fig7, None, "relay"),
             ("fig7 link-cuts", fig7, load_events("link-cuts", fig7), None),
             (f"fig7 {len(busy.events)} random events", fig7, busy, None),
             ("random 4 x 6", random_scenario(1, 4, 6, topology="relay"), None, None)]
    print(f"{'case':26} " + " ".join(f"{p + ' h/s':>14} {'x':>6}" for p in POLICY_NAMES))
    for label, s, script, topology in cases:
        speeds = {}
        for p in POLICY_NAMES:
            walls, life = [], 0.0
            for _ in range(repeats):
                t = time.perf_counter()
                r = simulate(s, script, policy=p, topology=topology) if script else simulate(s, policy=p,
                                                                                             topology=topology)
                walls.append(time.perf_counter() - t)
                life = r.lifetime_s
            speeds[p] = life / 3600 / statistics.median(walls)
        print(f"{label:26} " + " ".join(f"{speeds[p]:14,.0f} {speeds[p] / speeds['static']:5.2f}x"
                                         for p in POLICY_NAMES))
        for p in POLICY_NAMES:
            if p != "static":
                FIGURES.append(results.figure(f"{label}: {p}", speeds[p], "h/s", "static",
                                              speeds["static"], group=SPEED,
                                              note=f"the static policy on the same case, median of {repeats}"))


def main() -> None:
    json_out = results.pop_json_out()
    quick = "--quick" in sys.argv
    best = paper_table()
    print(f"best policy on the paper scenarios: min {min(best):.4%} of the bound")
    random_table([(3, 5), (4, 6)] if not quick else [(3, 4)], range(24 if not quick else 6))
    events_table(40 if not quick else 8)
    speed_table(5 if not quick else 2)
    results.write_result("policies", {"quick": quick}, FIGURES, json_out, what=__doc__.splitlines()[0],
                         groups=GROUPS)


if __name__ == "__main__":
    main()
