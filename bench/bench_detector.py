"""Failure detection on lossy links: false suspicions per robot-day, and what a stuck peer then takes
to be found. Not a timed test.

    .venv/bin/python bench/bench_detector.py [--loss 0,0.05,0.1,0.2] [--robot-days 100] [--minutes 10]

Two parts, each at every loss rate p (each message lost with probability p, independently):

- **The detector alone, at volume.** One robot watches three peers (the base station and two
  robots, as in paper-fig7), each sending a status every 0.5 s with up to 2 ms of jitter, for
  ``--robot-days`` simulated days of mission. The same arrivals feed two `PeerWatch`es: the
  accrual detector the runtime uses, and the same class with the accrual off (silent after two
  periods, whatever the loss: the detector before it) as the baseline, over min(2, robot-days)
  days (its rate is thousands a day: two days measure it). Nothing fails, so every suspicion is
  false. Also the silence each allows, sampled every simulated 10 minutes after the first hour:
  how long a peer whose loop is stuck (its session alive) takes to be found, p50 and p99.
- **In the simulated team.** `autopower sim` runs paper-fig7 with every link lossy for
  ``--minutes`` simulated minutes and nothing failing; the robots' suspicions, the re-plans they
  caused, the oracle's verdict on the run. Baseline: the detector-before's arithmetic (two
  statuses in a row lost: 2/s x 86,400 s x 3 peers x p²).

A cut, both ways or one way, ends the transport's session and its lease finds it (1 s in the
simulator and the testbed), not this detector: its figures are bench_faults' and the testbed's.
Issue 31's target: at most 1 false suspicion per robot-day at 10 % and 20 % loss.
"""

from __future__ import annotations

import argparse
import itertools
import logging
import math
import random
import statistics
from concurrent.futures import ProcessPoolExecutor

import results as bench_results

from autopower.model.loading import load_scenario
from autopower.node.peer_watch import PeerWatch, WatchSettings
from autopower.teamsim import Fault, SimConfig, run, team as sim_team

PERIOD_S = 0.5  # the status period while a robot runs chains
JITTER_S = 0.002
PEERS = ("laptop", "r2", "r3")
LEASE_S = 1.0
SAMPLE_EVERY_S = 600.0
WARM_UP_S = 3600.0


def watch(accrual: bool) -> PeerWatch:
    settings = WatchSettings(periods=2.0, own_period_s=PERIOD_S, lease_s=LEASE_S,
                             false_suspicions_per_day=1.0 if accrual else math.inf)
    w = PeerWatch(settings)
    for peer in PEERS:
        w.on_token(peer, True)
    return w


def alone(p: float, days: float, seed: int, accrual: bool) -> dict:
    """One robot's detector fed its peers' statuses, each lost with probability ``p``."""
    rng = random.Random(f"{seed}-{p}")
    w = watch(accrual)
    suspicions, limits = 0, []
    t, end, next_sample = 0.0, days * 86_400.0, WARM_UP_S
    while t < end:
        t += PERIOD_S
        for peer in PEERS:
            if rng.random() < p:
                continue
            suspicions += len(w.check(t - 0.001))
            w.on_status(peer, PERIOD_S, t + rng.uniform(0.0, JITTER_S))
        if t >= next_sample:
            next_sample += SAMPLE_EVERY_S
            limits += w.limits().values()
    return {"p": p, "accrual": accrual, "days": days, "suspicions": suspicions, "per_robot_day": suspicions / days,
            "stuck_p50_s": statistics.median(limits) if limits else None,
            "stuck_p99_s": sorted(limits)[int(0.99 * (len(limits) - 1))] if limits else None}


def in_team(p: float, minutes: float, seed: int) -> dict:
    scenario = load_scenario("paper-fig7")
    nodes = scenario.node_names()
    faults = tuple(Fault(kind="loss", t=10.0, duration=minutes * 60, a=a, b=b, p=p)
                   for a, b in itertools.combinations(sorted(nodes), 2))
    seen: dict = {}
    checks = sim_team.World.final_checks

    def counting(world) -> None:  # what each robot counted, read before the run is judged
        seen["suspicions"] = sum(s.rt.counters.get("silent-peers", 0) for n, s in world.shells.items()
                                 if n != scenario.basestation and s.up)
        seen["replans"] = world.shells[scenario.basestation].co.deciding.replans
        checks(world)

    logging.disable(logging.CRITICAL)  # the cores' logs: thousands of lines, for no one
    sim_team.World.final_checks = counting
    try:
        result = run(SimConfig(scenario=scenario, seed=seed, faults=faults, mission_s=10.0 + minutes * 60 + 1,
                               quiet_s=20.0))
    finally:
        sim_team.World.final_checks = checks
    robot_days = len(scenario.robots) * minutes / 1440.0
    return {"p": p, "suspicions": seen["suspicions"], "per_robot_day": seen["suspicions"] / robot_days,
            "expected_before": 2.0 * 86_400 * len(PEERS) * p * p, "replans": seen["replans"], "ok": result.ok,
            "violations": [v.detail for v in result.violations[:3]], "wall_s": result.wall_s}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--loss", default="0,0.05,0.1,0.2")
    parser.add_argument("--robot-days", type=float, default=100.0)
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--jobs", type=int, default=2)
    bench_results.add_json_out(parser)
    args = parser.parse_args()
    losses = [float(p) for p in args.loss.split(",")]
    with ProcessPoolExecutor(args.jobs) as pool:
        after = [pool.submit(alone, p, args.robot_days, args.seed, True) for p in losses]
        before = [pool.submit(alone, p, min(2.0, args.robot_days), args.seed, False) for p in losses]
        team = [pool.submit(in_team, p, args.minutes, args.seed) for p in losses if p > 0]
        after, before, team = ([f.result() for f in fs] for fs in (after, before, team))

    print(f"the detector alone, one robot watching {len(PEERS)} peers at {1 / PERIOD_S:g} statuses/s")
    print(f"{'loss':>5} {'robot-days':>10} {'false/robot-day':>16} {'before':>9} {'stuck peer found p50':>21} {'p99':>6}")
    for a, b in zip(after, before, strict=True):
        print(f"{a['p']:>5.2f} {a['days']:>10g} {a['per_robot_day']:>16.3f} {b['per_robot_day']:>9,.0f} "
              f"{a['stuck_p50_s']:>19.2f} s {a['stuck_p99_s']:>5.2f} s")
    print(f"in the simulated team (paper-fig7, {args.minutes:g} minutes, every link lossy)")
    print(f"{'loss':>5} {'suspicions':>11} {'per robot-day':>14} {'before (p²)':>12} {'re-plans':>9}  verdict")
    for r in team:
        print(f"{r['p']:>5.2f} {r['suspicions']:>11} {r['per_robot_day']:>14,.0f} {r['expected_before']:>12,.0f} "
              f"{r['replans']:>9}  {'ok' if r['ok'] else 'FAILED: ' + '; '.join(r['violations'])}")

    figures = []
    for a, b in zip(after, before, strict=True):
        g = f"{100 * a['p']:g} % loss, the detector alone"
        figures += [
            bench_results.figure(
                "false suspicions per robot-day", a["per_robot_day"], "per robot-day",
                "the two-period detector on the same statuses", b["per_robot_day"], group=g,
                note="the detector before: silent after two periods whatever the loss",
                detail=f"{a['suspicions']} over {a['days']:g} robot-days (before: {b['suspicions']} over "
                       f"{b['days']:g}); target at most 1"),
            bench_results.figure(
                "a stuck peer found after (p50)", a["stuck_p50_s"], "s", "the two-period detector",
                b["stuck_p50_s"], group=g, note="the silence allowed, sampled every 10 simulated minutes",
                detail=f"p99 {a['stuck_p99_s']:.2f} s"),
        ]
    for r in team:
        g = f"{100 * r['p']:g} % loss on every link, the simulated team"
        figures += [
            bench_results.figure("false suspicions per robot-day", r["per_robot_day"], "per robot-day",
                                 "the two-period detector's p² estimate", r["expected_before"], group=g,
                                 note="2/s x 86,400 s x 3 peers x p²",
                                 detail=f"{r['suspicions']} over {args.minutes:g} simulated minutes, 3 robots"),
            bench_results.figure("re-plans they caused", r["replans"], "re-plans", "false suspicions",
                                 r["suspicions"], group=g, note="the same run"),
            bench_results.figure("oracle violations", 0 if r["ok"] else len(r["violations"]), "violations",
                                 "a run with nothing failing", 0, group=g, note="the oracle's verdict on the run",
                                 detail="; ".join(r["violations"])[:300]),
        ]
    bench_results.write_result("detector", {"loss": args.loss, "robot_days": args.robot_days,
                                            "minutes": args.minutes, "seed": args.seed}, figures,
                               args.json_out, what=__doc__.splitlines()[0],
                               extra={"alone": after, "before": before, "team": team})


if __name__ == "__main__":
    main()
