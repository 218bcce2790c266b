"""The simulated team at fleet size: the same cores on 3 to 1,000 robots, against the 3-robot fleet.

    .venv/bin/python bench/bench_sim_fleet.py [--robots 3,10,30,100] [--mission 20] [--quiet 10] [--faults 5]
    .venv/bin/python bench/bench_sim_fleet.py --robots 3,100,300,1000   # minutes: 1,000 robots take ~10

Each size is `autopower scenarios fleet N --topology neighbours` (every robot with a camera: a Loc
and a 4 Hz Blob chain each; K = 2 neighbours on either side, 1 for fewer than 5 robots) run by
`autopower.teamsim` with stand-in components and ``--faults`` faults drawn from ``--seed``, then
judged by the oracle. Per size it prints the wall time per simulated second and the events handled
per wall second (what limits the simulator's team size), the base station's decisions (how many,
the policy's wall time each, decisions per second of that time, and how many were not proven
optimal: beyond 50,000 stage-host choices a decision searches only the hosts near each chain, and
a MILP may stop at its time limit), and what each robot sent per simulated second on the control
plane (statuses, plans, orders, votes) and as data. The baseline is the 3-robot fleet measured in
the same run. Not a test.
"""

from __future__ import annotations

import argparse
import logging

import results

GROUP_SPEED = "Simulator speed against team size"
GROUP_CONTROL = "Decisions and the control plane against team size"


def run_fleet(robots: int, seed: int, n_faults: int, mission_s: float, quiet_s: float) -> dict:
    from autopower.simulation.synthetic import paper_fleet
    from autopower.teamsim import SimConfig, draw, run

    _, fleet = paper_fleet(robots, topology="neighbours", neighbours=2 if robots >= 5 else 1)
    _, faults = draw(fleet, seed, n_faults, mission_s)
    result = run(SimConfig(scenario=fleet, seed=seed, faults=tuple(faults), mission_s=mission_s, quiet_s=quiet_s))
    out = result.to_json()
    out["violations_n"] = len(result.violations)
    return out


def decisions_per_s(out: dict) -> float | None:
    """The base station's decisions per wall second its policy spent on them (None: none made)."""
    d = out["decisions"]
    return round(d["count"] / d["seconds"], 4) if d["seconds"] > 0 else None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robots", default="3,10,30,100", help="team sizes, the first is the baseline")
    parser.add_argument("--mission", type=float, default=20.0, help="simulated seconds with faults (default 20)")
    parser.add_argument("--quiet", type=float, default=10.0, help="simulated seconds of healing (default 10)")
    parser.add_argument("--faults", type=int, default=5, help="faults drawn from the seed (default 5)")
    parser.add_argument("--seed", type=int, default=0)
    results.add_json_out(parser)
    args = parser.parse_args()
    sizes = [int(n) for n in args.robots.split(",")]
    logging.disable(logging.CRITICAL)
    runs = {}
    for n in sizes:
        out = run_fleet(n, args.seed, args.faults, args.mission, args.quiet)
        runs[n] = out
        d, per = out["decisions"], out["per_robot_per_s"]
        mean_ms = 1e3 * d["seconds"] / d["count"] if d["count"] else float("nan")
        gap = d.get("not_proven_max_gap")
        print(f"{n:>4} robots: {out['wall_s']:.1f} s wall for {out['virtual_s']:.1f} simulated s "
              f"({out['wall_s'] / out['virtual_s']:.2f} wall s per s, {out['events'] / out['wall_s']:,.0f} events/s); "
              f"{d['count']} decisions, {mean_ms:.0f} ms mean, {1e3 * d['max_s']:.0f} ms max, "
              f"{decisions_per_s(out) or 0:.2f} per policy s, {d.get('not_proven', 0)} not proven optimal"
              + (f" (MILP gap up to {gap:.1%} over the hosts searched)" if gap is not None else "") + "; per robot per s: "
              f"control {per['control']['messages']:.1f} msgs {per['control']['bytes']:,.0f} B, "
              f"data {per['data']['bytes']:,.0f} B; {out['violations_n']} violation(s)", flush=True)
    base_n = sizes[0]
    base = runs[base_n]
    note = f"the {base_n}-robot fleet, same run, same seed and fault count"
    figures = []
    for n in sizes[1:] if len(sizes) > 1 else sizes:
        out = runs[n]
        d, bd = out["decisions"], base["decisions"]
        detail = f"{n} robots"
        figures += [
            results.figure("wall seconds per simulated second", out["wall_s"] / out["virtual_s"], "s/s",
                           f"{base_n} robots", base["wall_s"] / base["virtual_s"], note=note, group=GROUP_SPEED,
                           detail=detail),
            results.figure("events handled per wall second", out["events"] / out["wall_s"], "events/s",
                           f"{base_n} robots", base["events"] / base["wall_s"], note=note, group=GROUP_SPEED,
                           detail=detail),
            results.figure("oracle violations", out["violations_n"], "violations", f"{base_n} robots",
                           base["violations_n"], note=note, group=GROUP_SPEED, detail=detail),
            results.figure("decisions", d["count"], "decisions", f"{base_n} robots", bd["count"], note=note,
                           group=GROUP_CONTROL, detail=detail),
            results.figure("policy wall time per decision", 1e3 * d["seconds"] / max(d["count"], 1), "ms",
                           f"{base_n} robots", 1e3 * bd["seconds"] / max(bd["count"], 1), note=note,
                           group=GROUP_CONTROL, detail=detail),
            results.figure("decisions per second of policy time", decisions_per_s(out), "decisions/s",
                           f"{base_n} robots", decisions_per_s(base), note=note, group=GROUP_CONTROL, detail=detail),
            results.figure("decisions not proven optimal", d.get("not_proven", 0), "decisions", f"{base_n} robots",
                           bd.get("not_proven", 0), note=note, group=GROUP_CONTROL, detail=detail),
            results.figure("control messages sent per robot per simulated s",
                           out["per_robot_per_s"]["control"]["messages"], "msgs/s", f"{base_n} robots",
                           base["per_robot_per_s"]["control"]["messages"], note=note, group=GROUP_CONTROL,
                           detail=detail),
            results.figure("control bytes sent per robot per simulated s",
                           out["per_robot_per_s"]["control"]["bytes"], "B/s", f"{base_n} robots",
                           base["per_robot_per_s"]["control"]["bytes"], note=note, group=GROUP_CONTROL,
                           detail=detail),
        ]
    results.write_result("sim_fleet", {"robots": sizes, "mission_s": args.mission, "quiet_s": args.quiet,
                                       "faults": args.faults, "seed": args.seed}, figures, args.json_out,
                         what=__doc__.splitlines()[0],
                         groups={GROUP_SPEED: {"value": "fleet", "baseline_value": f"{base_n} robots"},
                                 GROUP_CONTROL: {"value": "fleet", "baseline_value": f"{base_n} robots"}},
                         extra={"runs": {str(n): {k: v for k, v in out.items() if k not in ("chains",)}
                                         for n, out in runs.items()}})


if __name__ == "__main__":
    main()
