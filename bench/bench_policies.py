"""Reallocation policies vs the time-sharing upper bound, and simulator speed.

    .venv/bin/python bench/bench_policies.py [--quick]

Prints (1) every policy's lifetime as a fraction of the planner's time-sharing bound on the
paper's scenarios (Fig. 7 and Fig. 8 energies, both accountings, both topologies) and on random
scenarios, (2) each policy against static under the shipped event files and random event
sequences, (3) simulator speed in simulated hours per wall second, with static as the baseline
measured in the same run. Not a timed test: figures for the README and the notes.
"""

from __future__ import annotations

import statistics
import sys
import time

from autopower.errors import InfeasibleError
from autopower.model.loading import load_scenario
from autopower.model.mission_events import load_events, random_events
from autopower.policies import POLICY_NAMES
from autopower.simulation.simulator import simulate, time_sharing_reference
from autopower.simulation.synthetic import random_scenario


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
                ratios[p].append(simulate(s, policy=p).lifetime_s / bound.lifetime_s)
        wall = time.perf_counter() - started
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
        print(f"{name + (' (relay)' if topology else ''):28} "
              + " ".join(f"{runs[p].lifetime_s / static:10.4f}" for p in POLICY_NAMES)
              + f" {len(runs['rebalance'].migrations):18d}")
    # random event sequences: how often does knowing better now cost later?
    ratios = {p: [] for p in POLICY_NAMES}
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
    n = len(ratios["static"])
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


def main() -> None:
    quick = "--quick" in sys.argv
    best = paper_table()
    print(f"best policy on the paper scenarios: min {min(best):.4%} of the bound")
    random_table([(3, 5), (4, 6)] if not quick else [(3, 4)], range(24 if not quick else 6))
    events_table(40 if not quick else 8)
    speed_table(5 if not quick else 2)


if __name__ == "__main__":
    main()
