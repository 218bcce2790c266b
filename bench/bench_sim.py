"""Deterministic simulation of the team (`autopower sim`): seeds per minute, against the same missions with no fault.

    .venv/bin/python bench/bench_sim.py [--seeds 300] [--mission 600] [--faults 20] [--jobs 2]

Each seed runs the paper's team (paper-fig7) with stand-in components for ``--mission`` simulated
seconds with ``--faults`` faults, then the quiet phase, and is judged (`autopower.teamsim`). The
baseline is the same missions without faults, measured in the same run. The issue's volume target
is 10,000 seeds of 10 simulated minutes and 20 faults: the projected time for it on this machine
(``--jobs`` processes) is printed beside the rate. Seeds that violate an invariant are listed
(each one replays with ``autopower sim --seed N --mission M --faults K``). Not a test.
"""

from __future__ import annotations

import argparse
import os
import time

import results

TARGET_SEEDS = 10_000
GROUP = "Simulated team (autopower sim)"


def sweep(seeds: list[int], mission_s: float, n_faults: int, quiet_s: float, jobs: int) -> tuple[float, list]:
    """(wall seconds, per-seed verdicts) of running ``seeds``."""
    from autopower.teamsim import sweep as teamsim_sweep

    started = time.perf_counter()
    plan = teamsim_sweep.Sweep(mission_s=mission_s, n_faults=n_faults, quiet_s=quiet_s)
    done = teamsim_sweep.sweep(plan, seeds, jobs)
    return time.perf_counter() - started, done


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=300, help="seeds with faults (default 300)")
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--baseline-seeds", type=int, default=None, help="missions without faults (default: as --seeds)")
    parser.add_argument("--mission", type=float, default=600.0, help="simulated seconds of faults (default 600)")
    parser.add_argument("--faults", type=int, default=20, help="faults per seed (default 20)")
    parser.add_argument("--quiet", type=float, default=40.0, help="simulated seconds of healing (default 40)")
    parser.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="processes (default: the cores)")
    results.add_json_out(parser)
    args = parser.parse_args()
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    base_n = args.seeds if args.baseline_seeds is None else args.baseline_seeds
    print(f"# {len(seeds)} seeds of {args.mission:g} + {args.quiet:g} simulated s, {args.faults} faults, "
          f"{args.jobs} process(es)")
    wall, done = sweep(seeds, args.mission, args.faults, args.quiet, args.jobs)
    base_wall, base_done = sweep(seeds[:base_n], args.mission, 0, args.quiet, args.jobs)
    rate = len(seeds) / wall * 60.0
    base_rate = len(base_done) / base_wall * 60.0 if base_done else None
    cpu = sum(d.cpu_s for d in done) / len(done)
    base_cpu = sum(d.cpu_s for d in base_done) / len(base_done) if base_done else None
    projected_h = TARGET_SEEDS / rate / 60.0
    failed = [(d.seed, d.first) for d in done if not d.ok]
    sim_s = args.mission + args.quiet
    print(f"with faults: {rate:.1f} seeds/min ({cpu:.2f} CPU s per seed, {sim_s / cpu:.0f} simulated s per CPU s)")
    if base_done:
        print(f"no faults:   {base_rate:.1f} seeds/min ({base_cpu:.2f} CPU s per seed)")
    print(f"{TARGET_SEEDS:,} seeds would take {projected_h:.1f} h here ({args.jobs} process(es))")
    print(f"{len(failed)} of {len(seeds)} seeds violated an invariant")
    for seed, first in failed:
        print(f"  seed {seed}: {first[:160]}  (autopower sim --seed {seed} --mission {args.mission:g} "
              f"--faults {args.faults} --quiet {args.quiet:g})")
    base_note = f"the same {len(base_done)} missions without faults, same run"
    figures = [
        results.figure(f"seeds per minute, {args.mission:g} s missions, {args.faults} faults", rate, "seeds/min",
                       "no faults", base_rate, note=base_note, group=GROUP, detail=f"{args.jobs} process(es)"),
        results.figure("CPU seconds per seed", cpu, "s", "no faults", base_cpu, note=base_note, group=GROUP),
        results.figure(f"{TARGET_SEEDS:,} seeds (projected)", projected_h, "h", "no faults",
                       TARGET_SEEDS / base_rate / 60.0 if base_rate else None, note=base_note, group=GROUP,
                       detail=f"{args.jobs} process(es)"),
        results.figure("seeds violating an invariant", len(failed), "seeds", "seeds run", len(seeds),
                       note="every seed judged by the oracle", group=GROUP),
    ]
    results.write_result("sim", {"seeds": len(seeds), "first_seed": args.first_seed, "mission_s": args.mission,
                                 "faults": args.faults, "quiet_s": args.quiet, "jobs": args.jobs}, figures,
                         args.json_out, what=__doc__.splitlines()[0],
                         groups={GROUP: {"value": "with faults", "baseline_value": "no faults"}},
                         extra={"failed": [{"seed": s, "first_violation": first} for s, first in failed]})


if __name__ == "__main__":
    main()
